"""What the console reads from the archive, behind one small adapter.

Today it reads the SQLite index of :class:`cell.record.archive.Archive` and the job folders'
report.json, run.json and journal. When the archive grows a query API (list_jobs, get_job,
target_trend, job_targets: issue 19), only this module changes.

Every job id that comes from a URL goes through :func:`job_folder`, which refuses anything that
is not a plain folder name directly inside the archive.
"""
from __future__ import annotations

import json
import re
from datetime import datetime
from pathlib import Path

import numpy as np

from calibration.errors import InputError
from cell.record.archive import Archive
from cell.record.jobfolder import JobFolder
from cell.record.runinfo import read_run_info

_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.:-]{0,150}$")


class NotFound(InputError):
    """No such job (or an id that could not name one): the console answers 404."""


def job_folder(root: Path, job_id: str, *, staged: bool = False) -> Path:
    """The folder of job ``job_id`` in archive ``root``; NotFound for anything else.

    Goes through the archive's own resolver (:func:`cell.record.archive.resolve_job_id`: a plain name,
    no separators, no '..', no leading dot, no link out of the archive); a job still staged in
    ``.incoming`` counts only with ``staged``. Every id that comes from a URL passes here.
    """
    from cell.record.archive import resolve_job_id

    if not isinstance(job_id, str) or not _ID.match(job_id) or ".." in job_id:
        raise NotFound(f"no job {str(job_id)[:60]!r}")
    try:
        p = resolve_job_id(Path(root), job_id).path
    except InputError:
        raise NotFound(f"no job {job_id!r}") from None
    root = Path(root).resolve()
    real = p.resolve()
    if not (real.parent == root or (staged and real.parent == root / ".incoming")) or \
            not (real / "journal.jsonl").is_file():
        raise NotFound(f"no job {job_id!r}")
    return real


def _parse_time(s: str | None) -> datetime | None:
    if not s:
        return None
    try:
        d = datetime.fromisoformat(s)
    except ValueError:
        raise InputError(f"date {s!r}: use YYYY-MM-DD or an ISO 8601 time") from None
    return d if d.tzinfo is not None else d.astimezone()


class ArchiveView:
    """Read-only questions the console asks of the archive at ``root``."""

    def __init__(self, root: Path):
        self.root = Path(root).resolve()
        self.archive = Archive(self.root)

    def refresh(self, job_id: str | None = None) -> None:
        """Bring the index up to date with the folders (one job, or all)."""
        if job_id is None:
            self.archive.reindex()
        else:
            self.archive.reindex(only=job_folder(self.root, job_id))

    def list_jobs(self, part: str | None = None, serial: str | None = None, verdict: str | None = None,
                  operator: str | None = None, since: str | None = None, until: str | None = None,
                  status: str | None = None, limit: int = 500) -> list[dict]:
        """Jobs, newest first, filtered. ``part`` matches the part number or the part's name; ``serial`` a
        substring; ``since``/``until`` the start time (dates are inclusive)."""
        t0, t1 = _parse_time(since), _parse_time(until)
        if t1 is not None and len(until or "") == 10:  # a date: the whole day
            t1 = t1.replace(hour=23, minute=59, second=59)
        out = []
        for r in reversed(self.archive.list()):
            if part and part not in (r.get("part_number"), r.get("part"), r.get("name")):
                continue
            if serial and serial.lower() not in (r.get("serial") or "").lower():
                continue
            if verdict and (r.get("verdict") or "").upper() != verdict.upper():
                continue
            if status and r.get("status") != status.upper():
                continue
            if operator and (r.get("operator") or "") != operator:
                continue
            t = _parse_time(r.get("started"))
            if (t0 and (t is None or t < t0)) or (t1 and (t is None or t > t1)):
                continue
            r.pop("folder", None)
            out.append(r)
            if len(out) >= limit:
                break
        return out

    def report(self, job_id: str) -> dict | None:
        p = job_folder(self.root, job_id) / "report.json"
        return json.loads(p.read_text()) if p.exists() else None

    def get_job(self, job_id: str) -> dict:
        """One job: its index row, who/what (run.json), its journal's terminal record, its report summary."""
        folder = job_folder(self.root, job_id)
        recs, damage = JobFolder(folder).read_journal()
        state = next((r["to"] for r in reversed(recs) if r["event"] == "state"), "CREATED")
        terminal = next((r for r in reversed(recs) if r["event"] == "terminal"), None)
        info = read_run_info(folder)
        doc = {"id": job_id, "state": state, "part": info["part"], "operator": info["operator"],
               "cell_id": info["cell_id"], "started": recs[0]["t"] if recs else None,
               "reason": terminal.get("reason") if terminal else "", "verdict": None,
               "audit": [r for r in recs if r.get("event") in ("audit", "created", "resumed")],
               "record_damage": None if damage is None else str(damage)}
        rep = self.report(job_id)
        if rep is not None:
            doc |= {"verdict": rep.get("verdict"), "name": rep["job"].get("name"), "part_name": rep["job"].get("part"),
                    "finished": rep["job"].get("finished"), "targets": len(rep["targets"]),
                    "failed": [t["id"] for t in rep["targets"] if not t["pass"]], "sigma0_px": rep.get("sigma0_px")}
        return doc

    # --- trends ----------------------------------------------------------------------
    def _part_reports(self, part: str) -> list[tuple[dict, dict]]:
        """(index row, report.json) of every DONE job of ``part`` (number or name), oldest first."""
        rows = [r for r in self.archive.list() if r.get("status") == "DONE"
                and part in (r.get("part_number"), r.get("part"), r.get("name"))]
        out = []
        for r in rows:
            rep = self.report(r["id"])
            if rep is not None:
                out.append((r, rep))
        out.sort(key=lambda rr: (rr[1]["job"].get("finished") or "", rr[0]["id"]))
        return out

    def job_targets(self, part: str) -> list[str]:
        """Target ids measured in the jobs of ``part`` (those of its latest job)."""
        reps = self._part_reports(part)
        if not reps:
            raise NotFound(f"no finished job of part {part!r}")
        return [t["id"] for t in reps[-1][1]["targets"]]

    def target_trend(self, part: str, target: str, axis: str = "norm") -> dict:
        """One target's deviation over the part's jobs (or a group's: ``target`` = ids joined by commas).

        ``axis``: ``norm`` (|deviation|, one-sided: 0..tolerance) or ``x``/``y``/``z`` (a signed component
        in the part frame, two-sided: -tolerance..+tolerance). ``value_m`` is the charted value; for a
        group it is the group's worst per part (largest |d|, or the component farthest from zero), with
        ``target`` naming which one.
        """
        if axis not in ("norm", "x", "y", "z"):
            raise InputError(f"axis {axis!r}: norm, x, y or z")
        group = [t.strip() for t in target.split(",") if t.strip()]
        if not group or len(group) > 500:
            raise InputError("name one target, or a group of up to 500 separated by commas")
        pts, tols = [], []
        for row, rep in self._part_reports(part):
            by_id = {t["id"]: t for t in rep["targets"]}
            cand = []
            for tid in group:
                t = by_id.get(tid)
                if t is None or t["deviation_norm_m"] is None:
                    continue
                v = t["deviation_norm_m"] if axis == "norm" else t["deviation"]["xyz".index(axis)]
                cand.append((abs(v) / t["tolerance_m"], v, t))
            if len(cand) < len(group):  # a part where the group was not all measured is no point of the trend
                continue
            _, v, t = max(cand, key=lambda c: c[0])
            pts.append({"job_id": row["id"], "serial": (rep.get("part") or {}).get("serial") or row.get("serial"),
                        "finished": rep["job"].get("finished"), "deviation_norm_m": t["deviation_norm_m"],
                        "value_m": v, "sigma_m": t.get("achieved_sigma_m"), "pass": t["pass"], "target": t["id"]})
            tols.append(t["tolerance_m"])
        if not pts:
            raise NotFound(f"no measurement of target {target!r} in the finished jobs of part {part!r}")
        tol = float(np.median(tols))
        if len(group) > 1 and (max(tols) - min(tols)) > 1e-12:
            raise InputError(f"the targets {target!r} have different tolerances: a group trend needs one tolerance")
        lsl, usl = (None, tol) if axis == "norm" else (-tol, tol)
        return {"part": part, "target": target, "group": group, "axis": axis, "points": pts, "tolerance_m": tol,
                "lsl": lsl, "usl": usl}

def reverifications(root: Path) -> list[dict]:
    """The cell's reverification records (scale-bar length errors against the MPE), oldest first."""
    from cell.cellcal.common import CAL_DIR

    out = []
    base = Path(root) / CAL_DIR
    for f in sorted(base.glob("*/reverification.json")) if base.is_dir() else []:
        try:
            d = json.loads(f.read_text())
        except (OSError, ValueError):
            continue
        out.append({"record": f.parent.name, "cell": d.get("cell"), "finished": d.get("finished"),
                    "passed": d.get("passed"), "detail": d.get("detail"),
                    "positions": [{"position": p.get("position"), "error_m": p.get("error_m"), "mpe_m": p.get("mpe_m")}
                                  for p in d.get("positions", [])]})
    out.sort(key=lambda r: r["finished"] or "")
    return out
