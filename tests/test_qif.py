"""QIF 3.0 Results export: the document validates against the published QIF 3.0 schema (libxml2, with its
identity constraints), carries the part number, revision and serial number, one point feature and one
position characteristic per target with the report's numbers, and a broken document is refused."""
from __future__ import annotations

import json
import tarfile
from pathlib import Path

import pytest

from webutil import PART, seed_trend_archive

from cell.record.qif import NS, qif_results

etree = pytest.importorskip("lxml.etree")
XSD = Path(__file__).parent / "data" / "qif3-xsd.tar.xz"
Q = f"{{{NS}}}"


@pytest.fixture(scope="module")
def schema(tmp_path_factory):
    d = tmp_path_factory.mktemp("qif3")
    with tarfile.open(XSD) as tf:
        tf.extractall(d, filter="data")
    return etree.XMLSchema(etree.parse(str(d / "QIFApplications" / "QIFDocument.xsd")))


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    archive = tmp_path_factory.mktemp("a") / "archive"
    ids = seed_trend_archive(archive, n_parts=7)
    rep = json.loads((archive / ids[-1] / "report.json").read_text())
    rep["targets"][2]["measured"] = [None, None, None]  # one target not measured
    rep["targets"][2]["deviation_norm_m"] = None
    rep["targets"][2]["pass"] = False
    return ids[-1], rep


def test_qif_results_validate_against_the_qif3_schema_and_carry_the_report(schema, report):
    job_id, rep = report
    doc = etree.fromstring(qif_results(rep, job_id))
    assert schema.validate(doc), [str(e) for e in schema.error_log][:5]
    assert doc.find(f"{Q}Product/{Q}PartSet/{Q}Part/{Q}ModelNumber").text == PART
    assert doc.find(f"{Q}Product/{Q}PartSet/{Q}Part/{Q}Version").text == "B"
    ac = doc.find(f"{Q}Results/{Q}ActualComponentSets/{Q}ActualComponentSet/{Q}ActualComponent")
    assert ac.find(f"{Q}SerialNumber").text == "SN-0007"
    names = [e.text for e in doc.iter(f"{Q}FeatureName")]
    assert names == [t["id"] for t in rep["targets"]]
    measured = [t for t in rep["targets"] if t["measured"][0] is not None]
    feats = doc.findall(f".//{Q}MeasuredFeatures/{Q}PointFeatureMeasurement")
    every = doc.findall(f".//{Q}CharacteristicMeasurements/{Q}PositionCharacteristicMeasurement")
    # every characteristic has its status; the one not measured says so (NOT_ANALYZED) and has no value
    assert len(every) == len(rep["targets"])
    assert every[2].find(f"{Q}Status/{Q}CharacteristicStatusEnum").text == "NOT_ANALYZED"
    assert every[2].find(f"{Q}Value") is None
    chars = every[:2] + every[3:]
    assert len(feats) == len(chars) == len(measured) == len(rep["targets"]) - 1
    for t, f, c in zip(measured, feats, chars):
        xyz = [float(v) for v in f.find(f"{Q}Location").text.split()]
        assert xyz == pytest.approx([v * 1000 for v in t["measured"]], abs=1e-6)
        assert float(c.find(f"{Q}Value").text) == pytest.approx(2 * t["deviation_norm_m"] * 1000, abs=1e-6)
        want = {"conforming": "PASS", "nonconforming": "FAIL"}.get(t["decision"], "INDETERMINATE")
        assert c.find(f"{Q}Status/{Q}CharacteristicStatusEnum").text == want
    tol = {float(e.text) for e in doc.iter(f"{Q}ToleranceValue")}
    assert sorted(tol) == pytest.approx([0.2])  # 2 x 0.1 mm: the report's |d| <= tolerance as a spherical zone
    all_ids = [e.get("id") for e in doc.iter() if e.get("id")]
    assert len(all_ids) == len(set(all_ids)) and int(doc.get("idMax")) == max(map(int, all_ids))


def test_the_schema_check_refuses_a_broken_document(schema, report):
    job_id, rep = report
    doc = etree.fromstring(qif_results(rep, job_id))
    item = doc.find(f".//{Q}PositionCharacteristicMeasurement/{Q}CharacteristicItemId")
    item.text = "99999"  # a reference to nothing
    assert not schema.validate(doc)
    doc = etree.fromstring(qif_results(rep, job_id))
    chars = doc.find(f"{Q}Characteristics")
    chars.remove(chars.find(f"{Q}FormalStandardId"))
    assert not schema.validate(doc)
