"""QIF 3.0 Results (ANSI/DMSC QIF 3.0, ISO 23952): a job's measured targets as a quality system imports them.

Each judged target is a point feature (nominal, item, measurement at its aligned measured position)
with a position characteristic: a spherical tolerance zone of diameter 2 x tolerance around the nominal
(the report's pass rule |d| <= tolerance), measured value 2 |d| (the diameter of the smallest zone
centred on the nominal that holds the measured point). The characteristic's status is the report's decision
(ISO 14253-1), not ``pass``: conforming PASS, nonconforming FAIL, inconclusive (within U of the tolerance, a
suspect or doubtful measurement) and undecided (the alignment to CAD not trusted; every measured target of a
report whose alignment is not trusted or whose verdict is UNTRUSTED) INDETERMINATE; a target not
measured has a characteristic measurement with status NOT_ANALYZED and no value (CharacteristicStatusEnumType
has no NOT_MEASURED). A report without decisions (older) falls back to ``pass``. The part number and revision
are the Product's Part (ModelNumber, Version); the serial number is the ActualComponent's SerialNumber. Lengths in mm
(FileUnits). The schema is public (the QIF community repository on GitHub); tests/test_qif.py checks
the document against it when the schema set is given (QIF_XSD_DIR), and its ids and references always.
"""
from __future__ import annotations

import uuid
import xml.etree.ElementTree as ET

from cell.record.decisions import UNDECIDED
from cell.record.decisions import trusted as frame_trusted

NS = "http://qifstandards.org/xsd/qif3"
_MM = 1000.0


def _fmt(v: float) -> str:
    return f"{v:.6f}".rstrip("0").rstrip(".") if v == v else "0"


def _time(t: str) -> str:
    """An ISO 8601 time as xs:dateTime, its UTC offset kept (a time without one is local to nobody)."""
    from datetime import datetime

    try:
        d = datetime.fromisoformat(t)
    except ValueError:
        return t[:19]
    return d.isoformat(timespec="milliseconds" if d.microsecond else "seconds")


def characteristic_status(t: dict, trusted: bool = True) -> str:
    """The QIF 3 CharacteristicStatusEnum of a report.json target (see the module docstring); ``trusted`` False
    (the report's alignment not trusted, or its verdict UNTRUSTED): no measured target is decided."""
    if t["measured"][0] is None:
        return "NOT_ANALYZED"
    d = t.get("decision")
    if not trusted or d in UNDECIDED or t.get("suspect") or t.get("print_doubtful"):
        return "INDETERMINATE"
    if d == "conforming":
        return "PASS"
    if d == "nonconforming":
        return "FAIL"
    return "PASS" if t["pass"] else "FAIL"  # a report written before decisions


class _Ids:
    def __init__(self):
        self.n = 0

    def __call__(self) -> str:
        self.n += 1
        return str(self.n)


def _sub(parent, tag, text=None, **attrs):
    e = ET.SubElement(parent, tag, {k: str(v) for k, v in attrs.items()})
    if text is not None:
        e.text = str(text)
    return e


def _list(parent, tag, ids: list[str], item="Id"):
    e = _sub(parent, tag, n=len(ids))
    for i in ids:
        _sub(e, item, i)
    return e


def qif_results(report: dict, job_id: str) -> bytes:
    """The QIF 3.0 Results document (UTF-8 XML) of one job's report.json."""
    ids = _Ids()
    root = ET.Element("QIFDocument", {"xmlns": NS, "versionQIF": "3.0.0", "idMax": "0"})
    _sub(root, "QPId", str(uuid.uuid5(uuid.NAMESPACE_URL, f"inspection-cell/{job_id}")))
    version = _sub(root, "Version")
    _sub(version, "TimeCreated", _time(report["job"].get("finished") or report["job"]["started"]))
    header = _sub(root, "Header")
    app = _sub(header, "Application")
    _sub(app, "Name", "inspection-cell (robotic photogrammetric inspection)")
    _sub(app, "Organization", "inspection-cell")
    std = ids()
    st = _sub(_sub(root, "StandardsDefinitions", n=1), "Standard", id=std)
    _sub(_sub(st, "Organization"), "StandardsOrganizationEnum", "ISO")
    _sub(st, "Designator", "1101")
    _sub(st, "Year", "2017")
    units = _sub(_sub(root, "FileUnits"), "PrimaryUnits")
    lin = _sub(units, "LinearUnit")
    _sub(lin, "SIUnitName", "meter")
    _sub(lin, "UnitName", "mm")
    _sub(_sub(lin, "UnitConversion"), "Factor", "0.001")
    drf = ids()
    _sub(_sub(root, "DatumReferenceFrames", n=1), "DatumReferenceFrame", id=drf)  # best fit to CAD: no datums
    device = ids()
    devs = _sub(_sub(root, "MeasurementResources"), "MeasurementDevices", n=1)
    dev = _sub(devs, "MeasurementDevice", id=device)
    _sub(dev, "Name", f"photogrammetric cell {report.get('cell_id') or ''}".strip())
    part_info = report.get("part") or {}
    part_id = ids()
    part = _sub(_sub(root, "Product"), "PartSet", n=1)
    p = _sub(part, "Part", id=part_id)
    if part_info.get("number"):
        _sub(p, "ModelNumber", part_info["number"])
    if part_info.get("revision"):
        _sub(p, "Version", part_info["revision"])

    targets = [t for t in report["targets"]]
    feat = _sub(root, "Features")
    fdef = ids()
    _sub(_sub(feat, "FeatureDefinitions", n=1), "PointFeatureDefinition", id=fdef)
    nominals = _sub(feat, "FeatureNominals", n=len(targets))
    items = _sub(feat, "FeatureItems", n=len(targets))
    rows = []
    for t in targets:
        nid, iid = ids(), ids()
        n = _sub(nominals, "PointFeatureNominal", id=nid)
        _sub(n, "FeatureDefinitionId", fdef)
        _sub(n, "Location", " ".join(_fmt(v * _MM) for v in t["nominal"]))
        it = _sub(items, "PointFeatureItem", id=iid)
        _sub(it, "FeatureNominalId", nid)
        _sub(it, "FeatureName", t["id"])
        _sub(_sub(_sub(it, "DeterminationMode"), "Checked"), "CheckDetails").append(ET.Element("Measured"))
        rows.append((t, iid))

    chars = _sub(root, "Characteristics")
    _sub(chars, "FormalStandardId", std)
    tols = sorted({round(t["tolerance_m"], 12) for t in targets})
    cdefs = _sub(chars, "CharacteristicDefinitions", n=len(tols))
    cnoms = _sub(chars, "CharacteristicNominals", n=len(tols))
    nominal_of = {}
    for tol in tols:
        d, cn = ids(), ids()
        cd = _sub(cdefs, "PositionCharacteristicDefinition", id=d)
        _sub(cd, "ToleranceValue", _fmt(2 * tol * _MM))
        _sub(cd, "DatumReferenceFrameId", drf)
        _sub(cd, "MaterialCondition", "REGARDLESS")
        _sub(cd, "ZoneShape").append(ET.Element("SphericalZone"))
        c = _sub(cnoms, "PositionCharacteristicNominal", id=cn)
        _sub(c, "CharacteristicDefinitionId", d)
        nominal_of[tol] = cn
    citems = _sub(chars, "CharacteristicItems", n=len(rows))
    char_item = []
    for t, iid in rows:
        ci = ids()
        c = _sub(citems, "PositionCharacteristicItem", id=ci)
        _sub(c, "Name", f"{t['id']} position")
        _list(c, "FeatureItemIds", [iid])
        _list(c, "MeasurementDeviceIds", [device])
        _sub(c, "CharacteristicNominalId", nominal_of[round(t["tolerance_m"], 12)])
        char_item.append(ci)

    results = _sub(root, "Results")
    mr = _sub(_sub(results, "MeasurementResultsSet", n=1), "MeasurementResults", id=ids())
    measured = [(t, iid, ci) for (t, iid), ci in zip(rows, char_item) if t["measured"][0] is not None]
    judged = [(t, iid, ci) for (t, iid), ci in zip(rows, char_item)]
    mf = _sub(mr, "MeasuredFeatures", n=len(measured))
    meas_of = {}
    for t, iid, _ci in measured:
        m = _sub(mf, "PointFeatureMeasurement", id=ids())
        _sub(m, "FeatureItemId", iid)
        _sub(m, "Location", " ".join(_fmt(v * _MM) for v in t["measured"]))
        meas_of[iid] = m.get("id")
    # every characteristic has its status; one not measured has no feature measurement and no value
    cms = _sub(_sub(mr, "MeasuredCharacteristics"), "CharacteristicMeasurements", n=len(judged))
    trusted = frame_trusted(report)
    for t, iid, ci in judged:
        m = _sub(cms, "PositionCharacteristicMeasurement", id=ids())
        _sub(_sub(m, "Status"), "CharacteristicStatusEnum", characteristic_status(t, trusted))
        _sub(m, "CharacteristicItemId", ci)
        if iid in meas_of:
            _list(m, "FeatureMeasurementIds", [meas_of[iid]])
            _sub(m, "Value", _fmt(2 * t["deviation_norm_m"] * _MM))
    status = {"PASS": "PASS", "FAIL": "FAIL"}.get(report.get("verdict"), "UNKNOWN")
    _sub(_sub(mr, "InspectionStatus"), "InspectionStatusEnum", status)
    comp = ids()
    _list(mr, "ActualComponentIds", [comp])
    ac = _sub(_sub(_sub(results, "ActualComponentSets", n=1), "ActualComponentSet", n=1), "ActualComponent", id=comp)
    if part_info.get("serial"):
        _sub(ac, "SerialNumber", part_info["serial"])
    _sub(_sub(ac, "Status"), "InspectionStatusEnum", status)
    if report.get("operator"):
        trace = _sub(results, "InspectionTraceability")
        _sub(_sub(trace, "ReportPreparer"), "Name", report["operator"])
    root.set("idMax", str(ids.n))
    ET.indent(root)
    return b'<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="utf-8")
