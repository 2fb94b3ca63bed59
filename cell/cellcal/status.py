"""What an inspection report states of the cell's calibration: the latest hand-eye and reverification."""
from __future__ import annotations

import json
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from calibration.handeye import pose_error
from cell.cellcal.common import CAL_DIR
from cell.cellcal.cellfile import load_cell_file


def _parse_time(v) -> datetime:
    if isinstance(v, datetime):
        return v if v.tzinfo else v.replace(tzinfo=timezone.utc)
    if isinstance(v, (int, float)):
        return datetime.fromtimestamp(v, timezone.utc)
    d = datetime.fromisoformat(str(v))
    return d if d.tzinfo else d.replace(tzinfo=timezone.utc)


def calibration_status(archive_root: Path, cell_name_or_file, now) -> dict:
    """The cell's reverification status for an inspection report.

    ``cell_name_or_file``: the cell's name, or its cell file (then a reverification made with another
    hand-eye than the file's current one does not count). ``now``: datetime, ISO string or epoch seconds.
    Returns ``{"status": "verified"|"expired"|"failed"|"not verified", "last": record or None, "detail": str}``.
    """
    current_ffc = None
    name = str(cell_name_or_file)
    p = Path(str(cell_name_or_file))
    if p.suffix == ".toml" and p.is_file():
        cf, _ = load_cell_file(p)
        name, current_ffc = cf.cell.name, cf.flange_from_cam()
    root = Path(archive_root) / CAL_DIR
    recs = []
    if root.is_dir():
        for f in root.glob("*/reverification.json"):
            try:
                d = json.loads(f.read_text())
            except (OSError, ValueError):
                continue
            if d.get("cell") == name:
                recs.append((_parse_time(d["finished"]), f.parent.name, d))
    if not recs:
        return {"status": "not verified", "last": None, "detail": f"no reverification of cell {name!r} in {root}"}
    when, rid, d = max(recs, key=lambda r: r[0])
    last = {"record": rid, "date": d["finished"], "passed": d["passed"], "max_abs_error_m": d.get("max_abs_error_m"),
            "interval_days": d["interval_days"]}
    now_t = _parse_time(now)
    if current_ffc is not None:
        dt, dr = pose_error(current_ffc, np.asarray(d["flange_from_cam"], dtype=float))
        if dt > 1e-6 or dr > 1e-6:
            return {"status": "not verified", "last": last,
                    "detail": f"the hand-eye changed ({dt * 1e3:.3f} mm) after the last reverification {rid}: "
                              "run the reverification again"}
    if not d["passed"]:
        return {"status": "failed", "last": last, "detail": f"last reverification {rid} failed: {d['detail']}"}
    due = when + timedelta(days=float(d["interval_days"]))
    if now_t > due:
        return {"status": "expired", "last": last,
                "detail": f"last reverification {rid} passed but its interval of {d['interval_days']:g} days ended "
                          f"{due.isoformat(timespec='seconds')}"}
    return {"status": "verified", "last": last,
            "detail": f"reverification {rid} passed ({d['detail']}); due again {due.isoformat(timespec='seconds')}"}
