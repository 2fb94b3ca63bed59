"""The exports and the archive say what the report says: a target's decision (ISO 14253-1, inconclusive within U of
its tolerance or for a suspect/doubtful measurement, undecided in an untrusted frame), not only ``pass``; a target
not measured is not a failed one; an untrusted job or an undecided target is no point of a capability study; a
drift is judged against both jobs' covariances. Reports are built here (synthesized DONE jobs, no simulation)."""
from __future__ import annotations

import csv
import io
import json
import tarfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from webutil import PART, TARGETS, seed_trend_archive

from cell.record.archive import Archive
from cell.record.archive.records import job_record
from cell.record.qif import NS, qif_results

Q = f"{{{NS}}}"
XSD = Path(__file__).parent / "data" / "qif3-xsd.tar.xz"


def _edit(archive: Path, job_id: str, fn) -> dict:
    """Change report.json of a synthesized job (``fn(doc)`` in place) and index it again."""
    p = archive / job_id / "report.json"
    doc = json.loads(p.read_text())
    fn(doc)
    p.write_text(json.dumps(doc))
    from cell.record.jobfolder import JobFolder

    JobFolder(archive / job_id).write_manifest()  # as a job that wrote this report would have closed it
    Archive(archive).reindex(only=archive / job_id)
    return doc


def _not_measured(t: dict) -> None:
    t.update({"measured": [None] * 3, "deviation": [None] * 3, "deviation_norm_m": None, "cov": [[None] * 3] * 3,
              "pass": False, "decision": None, "uncertainty_U_m": None, "achieved_sigma_m": None})


def _untrusted(doc: dict, *, new_style: bool) -> None:
    doc["verdict"] = "UNTRUSTED"
    doc["alignment"] |= {"trusted": False, "reasons": ["ambiguous: another placement agrees"]}
    if new_style:  # REPORT now writes 'undecided' for every measured target of an untrusted frame
        for t in doc["targets"]:
            if t["measured"][0] is not None:
                t["decision"] = "undecided"


def _mixed(doc: dict) -> None:
    """T01 conforming, T02 inconclusive (within U), T03 not measured, T04 nonconforming, T05 doubtful, T06 suspect."""
    ts = {t["id"]: t for t in doc["targets"]}
    ts["T02"]["decision"] = "inconclusive"
    _not_measured(ts["T03"])
    ts["T04"] |= {"pass": False, "decision": "nonconforming", "deviation_norm_m": 0.2e-3}
    ts["T05"] |= {"print_doubtful": "a speck on its edge", "decision": "conforming"}
    ts["T06"] |= {"suspect": True, "decision": "inconclusive"}
    doc["verdict"] = "FAIL"


@pytest.fixture
def archive(tmp_path):
    root = tmp_path / "archive"
    ids = seed_trend_archive(root, n_parts=6)
    return root, ids


# --- 1. QIF --------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def schema(tmp_path_factory):
    etree = pytest.importorskip("lxml.etree")
    d = tmp_path_factory.mktemp("qif3")
    with tarfile.open(XSD) as tf:
        tf.extractall(d, filter="data")
    return etree.XMLSchema(etree.parse(str(d / "QIFApplications" / "QIFDocument.xsd")))


def _statuses(xml: bytes) -> list[str]:
    import xml.etree.ElementTree as ET

    doc = ET.fromstring(xml)
    return [c.find(f"{Q}Status/{Q}CharacteristicStatusEnum").text
            for c in doc.iter(f"{Q}PositionCharacteristicMeasurement")]


def test_qif_status_is_the_decision_and_an_undecided_target_is_indeterminate(archive, schema):
    from lxml import etree

    root, ids = archive
    doc = _edit(root, ids[-1], _mixed)
    xml = qif_results(doc, ids[-1])
    assert schema.validate(etree.fromstring(xml)), [str(e) for e in schema.error_log][:5]
    assert _statuses(xml) == ["PASS", "INDETERMINATE", "NOT_ANALYZED", "FAIL", "INDETERMINATE", "INDETERMINATE"]
    # the target not measured has its characteristic, with no feature measurement and no value
    t03 = [c for c in etree.fromstring(xml).iter(f"{Q}PositionCharacteristicMeasurement")][2]
    assert t03.find(f"{Q}Value") is None and t03.find(f"{Q}FeatureMeasurementIds") is None


@pytest.mark.parametrize("new_style", [True, False])
def test_qif_of_an_untrusted_job_decides_no_target(archive, schema, new_style):
    from lxml import etree

    root, ids = archive
    doc = _edit(root, ids[-1], lambda d: _untrusted(d, new_style=new_style))
    xml = qif_results(doc, ids[-1])
    assert schema.validate(etree.fromstring(xml)), [str(e) for e in schema.error_log][:5]
    assert set(_statuses(xml)) == {"INDETERMINATE"}
    assert etree.fromstring(xml).find(f".//{Q}InspectionStatus/{Q}InspectionStatusEnum").text == "UNKNOWN"


def test_qif_time_created_keeps_the_utc_offset(archive, schema):
    from lxml import etree

    root, ids = archive
    doc = json.loads((root / ids[0] / "report.json").read_text())
    doc["job"]["finished"] = "2026-11-25T07:04:13.051+01:00"
    xml = etree.fromstring(qif_results(doc, ids[0]))
    assert schema.validate(xml), [str(e) for e in schema.error_log][:5]
    assert xml.find(f"{Q}Version/{Q}TimeCreated").text == "2026-11-25T07:04:13.051+01:00"


# --- 2. CSV and the HTML table's header ------------------------------------------------------------------------------
def _csv(doc: dict) -> list[dict]:
    from cell.web.service import Console

    fake = SimpleNamespace(view=SimpleNamespace(report=lambda job_id: doc))
    text = Console.report_csv(fake, doc["job"]["id"])
    rows = list(csv.reader(io.StringIO(text)))
    return [dict(zip(rows[0], r)) for r in rows[1:]], rows[0]


def test_csv_says_yes_or_no_only_where_the_decision_decides_and_ends_with_verdict_and_trust(archive):
    root, ids = archive
    doc = _edit(root, ids[-1], _mixed)
    rows, head = _csv(doc)
    assert head[:17] == ["job_id", "part_number", "revision", "serial", "target", "nominal_x_mm", "nominal_y_mm",
                         "nominal_z_mm", "dx_um", "dy_um", "dz_um", "deviation_um", "tolerance_um", "U_k2_um",
                         "sigma_um", "pass", "decision"]
    assert head[17:] == ["verdict", "alignment_trusted"]
    assert [r["pass"] for r in rows] == ["yes", "", "", "no", "", ""]
    assert [r["decision"] for r in rows] == ["conforming", "inconclusive", "", "nonconforming", "conforming",
                                             "inconclusive"]
    assert {r["verdict"] for r in rows} == {"FAIL"} and {r["alignment_trusted"] for r in rows} == {"yes"}


@pytest.mark.parametrize("new_style", [True, False])
def test_csv_of_an_untrusted_job_has_no_pass_and_says_the_alignment(archive, new_style):
    root, ids = archive
    doc = _edit(root, ids[-1], lambda d: _untrusted(d, new_style=new_style))
    rows, _ = _csv(doc)
    assert {r["pass"] for r in rows} == {""}
    assert {r["verdict"] for r in rows} == {"UNTRUSTED"} and {r["alignment_trusted"] for r in rows} == {"no"}


def _html_doc(targets: list[dict], verdict: str = "FAIL", trusted: bool = True) -> dict:
    return {"job": {"id": "j1", "name": "n", "seed": 1, "started": "s", "finished": "f", "versions": {}},
            "verdict": verdict, "targets": targets, "stage_times_s": {}, "images": 3, "sigma0_px": 0.01,
            "alignment": {"method": "best_fit", "targets_in_fit": ["T1"], "rms_m": 2e-6, "trusted": trusted,
                          "reasons": [] if trusted else ["ambiguous"], "notes": []}}


def _t(i: int, decision: str | None, ok: bool = True, measured: bool = True, **kw) -> dict:
    m = [0.001 * i, 0.0, 0.0] if measured else [None] * 3
    return {"id": f"T{i}", "pass": ok and measured, "decision": decision if measured else None, "measured": m,
            "deviation": [1e-5, 0, 0] if measured else [None] * 3, "deviation_norm_m": 1e-5 if measured else None,
            "tolerance_m": 2.5e-4, "achieved_sigma_m": 2e-6 if measured else None, "predicted_sigma_m": 2e-6,
            "uncertainty_U_m": 4e-6 if measured else None, "n_images": 6, **kw}


def test_html_headline_counts_not_measured_and_undecided_apart_and_the_columns_say_measured():
    from cell.record.report import render_html

    targets = [_t(1, "conforming"), _t(2, "conforming"), _t(3, "nonconforming", ok=False),
               _t(4, "inconclusive"), _t(5, None, measured=False), _t(6, "conforming", print_doubtful="a speck")]
    html = render_html(_html_doc(targets), {})
    assert ("FAIL: 2 of 6 targets within tolerance, 1 beyond it, 2 undecided or inconclusive, 1 not measured"
            in html), html[html.index('id="verdict"'):][:300]
    assert "<th>measured x [mm]</th><th>measured y [mm]</th><th>measured z [mm]</th>" in html
    # an untrusted frame decides nothing: none within, the one beyond is said undecided too
    for t in targets:
        if t["decision"] is not None:
            t["decision"] = "undecided"
    html = render_html(_html_doc(targets, "UNTRUSTED", trusted=False), {})
    assert ("UNTRUSTED: 0 of 6 targets within tolerance, 1 beyond it (1 of them undecided or inconclusive), "
            "4 undecided or inconclusive, 1 not measured") in html
    assert "(undecided: the alignment to CAD is not trusted)" in html


# --- 4. failed = measured and beyond tolerance -------------------------------------------------------------------------
def test_a_target_not_measured_is_not_counted_failed_by_the_archive_the_console_and_the_cli(archive, capsys):
    from cell.cli import main
    from cell.web.store import ArchiveView

    root, ids = archive
    jid = ids[-1]
    _edit(root, jid, _mixed)
    rec = job_record(root / jid, "here")
    assert rec.failed == 1 and rec.not_measured == 1  # T04 beyond; T03 not measured
    a = Archive(root)
    shown = a.show(jid)
    assert shown["failed"] == ["T04"] and shown["not_measured"] == ["T03"]
    assert shown["undecided"] == ["T02", "T05", "T06"]
    assert a.index.get_job(jid)["failed"] == 1
    a.close()
    view = ArchiveView(root)
    try:
        got = view.get_job(jid)
        listed = {r["id"]: r for r in view.list_jobs()}  # the console's list (GET /api/jobs)
    finally:
        view.close()
    assert got["failed"] == ["T04"] and got["not_measured"] == ["T03"] and got["alignment_trusted"] is True
    assert listed[jid]["failed"] == 1 and listed[jid]["not_measured"] == 1 and listed[ids[0]]["not_measured"] == 0
    assert main(["archive", "list", "--archive", str(root)]) == 0
    line = next(x for x in capsys.readouterr().err.splitlines() if x.startswith(jid))
    assert "1 failed of 6, 1 not measured" in line, line
    assert main(["archive", "list", "--archive", str(root), "--json"]) == 0
    row = next(r for r in json.loads(capsys.readouterr().out)["jobs"] if r["id"] == jid)
    assert row["failed"] == 1 and row["not_measured"] == 1


def test_cell_archive_sync_reindexes_a_failed_count_of_before(archive):
    import sqlalchemy as sa

    from cell.record.archive.tables import jobs

    root, ids = archive
    jid = ids[-1]
    _edit(root, jid, _mixed)
    a = Archive(root)
    with a.index.engine.begin() as conn:  # the count an index written before this change holds
        conn.execute(sa.update(jobs).where(jobs.c.id == jid).values(failed=2))
    assert any("index says 2 failed" in p for p in a.verify_index()["problems"])
    assert jid in a.sync()["indexed"] and a.index.get_job(jid)["failed"] == 1
    a.close()


# --- 5. trend / SPC ----------------------------------------------------------------------------------------------------
def test_trend_keeps_untrusted_and_undecided_points_but_leaves_them_out_of_the_statistics(tmp_path):
    from cell.web.service import trend, trend_csv
    from cell.web.spc import analyse
    from cell.web.store import ArchiveView

    root = tmp_path / "archive"
    ids = seed_trend_archive(root, n_parts=10, drift_from=99)
    _edit(root, ids[3], lambda d: _untrusted(d, new_style=False))  # an old-style untrusted job: decisions say conforming

    def far_and_inconclusive(doc):
        t = next(t for t in doc["targets"] if t["id"] == "T01")
        t |= {"deviation": [0, 0, 90e-6], "deviation_norm_m": 90e-6, "decision": "inconclusive"}

    _edit(root, ids[6], far_and_inconclusive)
    _edit(root, ids[-1], lambda d: [t.update(tolerance_m=150e-6) for t in d["targets"]])  # the drawing changed
    view = ArchiveView(root)
    try:
        doc = trend(view, PART, "T01", "norm")
        group = trend(view, PART, "T01,T02", "norm")
    finally:
        view.close()
    pts = doc["points"]
    assert [p["job_id"] for p in pts] == ids  # every measurement is still a point
    assert "not trusted" in pts[3]["excluded"] and "inconclusive" in pts[6]["excluded"]
    assert all(p["excluded"] is None for i, p in enumerate(pts) if i not in (3, 6))
    used = [p["value_m"] for i, p in enumerate(pts) if i not in (3, 6)]
    ref = analyse(used, None, 150e-6)
    assert doc["n_used"] == 8 and doc["n_excluded"] == 2 and doc["baseline"] == 8
    assert doc["ucl"] == pytest.approx(ref["ucl"]) and doc["lcl"] == pytest.approx(ref["lcl"])
    assert doc["cpk"] == pytest.approx(ref["cpk"])
    assert doc["usl"] == doc["tolerance_m"] == pytest.approx(150e-6)  # the newest job's, not the median's 100 um
    assert pts[0]["tolerance_m"] == pytest.approx(100e-6) and pts[-1]["tolerance_m"] == pytest.approx(150e-6)
    assert doc["moving_range"][3] is None and doc["moving_range"][6] is None
    assert doc["moving_range"][4] == pytest.approx(abs(pts[4]["value_m"] - pts[2]["value_m"]))
    assert not any(v["index"] in (3, 6) for v in doc["violations"])  # the 90 um outlier breaks no rule: it is out
    for k in ("points", "ucl", "lcl", "cp", "cpk", "violations"):  # the API's documented fields
        assert k in doc
    assert {"job_id", "serial", "finished", "deviation_norm_m", "value_m"} <= set(pts[0])
    rows = list(csv.reader(io.StringIO(trend_csv(doc))))
    assert rows[0][-2:] == ["tolerance_um", "excluded"] and "not trusted" in rows[4][-1] and rows[1][-1] == ""
    assert group["n_used"] == 8 and group["points"][6]["excluded"].startswith("T01: inconclusive")


# --- 6. cell archive compare -------------------------------------------------------------------------------------------
def test_compare_uses_both_covariances_skips_a_target_not_measured_and_says_an_untrusted_job(archive, capsys):
    from cell.cli import main

    root, ids = archive
    a_id, b_id = ids[0], ids[1]

    def wide_b(doc):
        for t in doc["targets"]:
            t["cov"] = (np.diag([1e-6, 1e-6, 30e-6]) ** 2).tolist()  # 30 um along z in B alone
            t["achieved_sigma_m"] = float(np.sqrt(np.trace(t["cov"])))
        t = next(t for t in doc["targets"] if t["id"] == "T02")
        t["measured"] = (np.array(t["nominal"]) + [0, 0, 60e-6 + np.array(t["deviation"])[2]]).tolist()
        _not_measured(next(t for t in doc["targets"] if t["id"] == "T03"))

    _edit(root, b_id, wide_b)
    ra = json.loads((root / a_id / "report.json").read_text())
    rb = json.loads((root / b_id / "report.json").read_text())
    arch = Archive(root)
    doc = arch.compare([a_id, b_id])
    rows = {r["id"]: r for r in doc["targets"]}
    t2a = next(t for t in ra["targets"] if t["id"] == "T02")
    t2b = next(t for t in rb["targets"] if t["id"] == "T02")
    change = np.array(t2b["measured"]) - np.array(t2a["measured"])
    u = change / np.linalg.norm(change)
    sig = np.sqrt(u @ (np.array(t2a["cov"]) + np.array(t2b["cov"])) @ u)
    assert rows["T02"]["drift_sigma_m"] == pytest.approx(sig) and sig > 25e-6  # B's 30 um along z counts
    assert rows["T02"]["drift_significant"] is False  # ~60 um against ~30 um: not beyond 3 sigma
    assert rows["T03"]["drift_m"] is None and rows["T03"]["drift_significant"] is None
    assert doc["not_measured"] == [{"id": "T03", "jobs": [b_id]}] and doc["untrusted"] == [] and doc["note"] is None
    assert main(["archive", "compare", a_id, b_id, "--archive", str(root)]) == 0
    err = capsys.readouterr().err
    assert "T03 in " + b_id in err and "drift --" in err
    _edit(root, b_id, lambda d: _untrusted(d, new_style=True))
    doc = arch.compare([a_id, b_id])
    assert [u["job_id"] for u in doc["untrusted"]] == [b_id] and "not trusted" in doc["note"]
    assert doc["drifting"] == [] and all(r["drift_significant"] is None for r in doc["targets"])
    assert main(["archive", "compare", a_id, b_id, "--archive", str(root)]) == 0
    assert "WARNING alignment to CAD not trusted in " + b_id in capsys.readouterr().err
    arch.close()


def test_compare_writes_nothing_into_the_archive(archive):
    root, ids = archive
    before = sorted((p.relative_to(root), p.stat().st_mtime_ns) for p in root.rglob("*") if p.is_file())
    Archive(root).compare(ids[:2])
    after = sorted((p.relative_to(root), p.stat().st_mtime_ns) for p in root.rglob("*") if p.is_file())
    assert before == after


# --- 7. the tolerance's precision, and both jobs' tolerances on /compare -----------------------------------------------
def test_the_3d_hover_gives_the_tolerance_to_the_precision_of_d():
    from cell.record.figures3d import deviations_3d
    import trimesh

    mesh = trimesh.creation.box()
    fig = deviations_3d(mesh, np.zeros((2, 3)), ["T1", "T2"], np.array([200.4e-6, np.nan]), np.array([201e-6, 201e-6]),
                        np.array([True, False]))
    text = fig["data"][1]["text"]
    assert text[0].startswith("T1: |d| 200.4 um / tol 201.0 um")


def test_compare_page_shows_both_tolerances_when_they_differ(archive):
    from fastapi.testclient import TestClient

    from cell.web.app import Config, create_app
    from cell.web.users import UserStore

    root, ids = archive
    _edit(root, ids[1], lambda d: [t.update(tolerance_m=100.5e-6) for t in d["targets"]])
    _edit(root, ids[1], lambda d: _not_measured(d["targets"][2]))
    UserStore(root / "console.sqlite").add("eve", "engineer", "engineer-pw-2m")
    programs = root.parent / "programs"
    programs.mkdir()
    with TestClient(create_app(Config(archive=root, programs=programs))) as c:
        r = c.post("/login", data={"username": "eve", "password": "engineer-pw-2m"}, follow_redirects=False)
        assert r.status_code == 303
        page = c.get("/compare", params={"a": ids[0], "b": ids[1]}).text
    assert "<td>100.0 / 100.5</td>" in page and "not measured" in page
    assert len(TARGETS) == page.count("<td>100.0 / 100.5</td>")
