"""What the index holds of one job, read from its folder (the record of truth).

:func:`job_record` reads the journal (name, state, start), ``run.json`` (part number, serial,
operator, cell), ``report.json`` (part, verdict, every judged target's values) and the manifest's hash; the index stores exactly
that, so re-indexing a folder is idempotent and the database can always be rebuilt.
"""
from __future__ import annotations

import hashlib
import json
import math
from datetime import datetime
from dataclasses import dataclass, field
from pathlib import Path

from calibration.errors import InputError
from cell.record.archive.tables import COV_INDEX, COV_KEYS
from cell.record.decisions import beyond, measured
from cell.record.jobfolder import MANIFEST, JobFolder
from cell.record.runinfo import read_run_info


def _num(v) -> float | None:
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _vec(v, what: str) -> list[float | None]:
    if v is None:
        return [None, None, None]
    if len(v) != 3:
        raise InputError(f"{what}: expected 3 values, found {len(v)}")
    return [_num(x) for x in v]


def target_row(t: dict, where: str) -> dict:
    """A report.json target as a ``targets`` row (without job_id, part, finished)."""
    if not isinstance(t, dict) or "id" not in t or "nominal" not in t:
        raise InputError(f"{where}: a target without 'id' or 'nominal': {str(t)[:80]}")
    row = {"target_id": str(t["id"]), "kind": t.get("kind")}
    nominal = _vec(t["nominal"], f"{where}: target {t['id']} nominal")
    if any(v is None for v in nominal):
        raise InputError(f"{where}: target {t['id']} has no finite nominal position")
    for p, vals in (("nominal", nominal), ("measured", _vec(t.get("measured"), f"{where}: {t['id']} measured")),
                    ("deviation", _vec(t.get("deviation"), f"{where}: {t['id']} deviation"))):
        row |= {f"{p}_{a}": v for a, v in zip("xyz", vals)}
    cov = t.get("cov")
    for k, (i, j) in zip(COV_KEYS, COV_INDEX):
        row[f"cov_{k}"] = None if cov is None else _num(cov[i][j])
    row |= {"deviation_norm_m": _num(t.get("deviation_norm_m")), "tolerance_m": _num(t.get("tolerance_m")),
            "uncertainty_u_m": _num(t.get("uncertainty_U_m")), "achieved_sigma_m": _num(t.get("achieved_sigma_m")),
            "decision": t.get("decision"),
            "passed": None if t.get("pass") is None else bool(t["pass"])}
    return row


@dataclass
class JobRecord:
    """One job as the index sees it."""

    id: str
    name: str
    status: str
    origin: str
    folder: str
    part: str | None = None
    part_number: str | None = None
    serial: str | None = None
    cell_id: str | None = None
    operator: str | None = None
    verdict: str | None = None
    started: str | None = None
    finished: str | None = None
    sigma0_px: float | None = None
    manifest_sha256: str | None = None
    targets: list[dict] = field(default_factory=list)
    failed: int | None = None  # measured and beyond tolerance (cell.record.decisions.beyond)
    not_measured: int | None = None  # not in the jobs table: counted from the target rows where a count is shown
    problem: str | None = None  # what in the folder could not be read (indexed as far as it reads)

    def job_row(self) -> dict:
        return {"id": self.id, "name": self.name, "part": self.part, "part_number": self.part_number,
                "serial": self.serial, "cell_id": self.cell_id, "operator": self.operator,
                "status": self.status, "verdict": self.verdict, "started": self.started, "finished": self.finished,
                "targets": len(self.targets) if self.failed is not None else None, "failed": self.failed,
                "sigma0_px": _num(self.sigma0_px), "origin": self.origin, "folder": self.folder,
                "manifest_sha256": self.manifest_sha256, "problem": self.problem}


def manifest_sha256(folder: Path) -> str | None:
    p = Path(folder) / MANIFEST
    if not p.exists():
        return None
    return hashlib.sha256(p.read_bytes()).hexdigest()


def job_record(folder: Path, origin: str) -> JobRecord:
    """The index record of the job folder ``folder``, from what reads.

    A damaged journal (up to its first bad line) or report (no report values) is indexed as far as it
    reads, with what is wrong in ``problem``: one damaged folder never stops the others.
    """
    folder = Path(folder)
    jf = JobFolder(folder)
    problems = []
    try:
        recs, damage = jf.read_journal()
    except OSError as exc:
        recs, damage = [], exc
    if damage is not None:
        problems.append(f"journal damaged: {damage}")
    status = next((r.get("to") for r in reversed(recs) if r.get("event") == "state"), "CREATED")
    created = next((r for r in recs if r.get("event") == "created"), {})
    start = recs[0].get("t") if recs else None
    rec = JobRecord(id=folder.name, name=str(created.get("name") or folder.name), status=str(status), origin=origin,
                    folder=str(folder), started=start if _is_time(start) else None, serial=created.get("serial"),
                    cell_id=created.get("cell_id"), operator=created.get("operator"),
                    manifest_sha256=manifest_sha256(folder))
    try:  # run.json: who and what (part number, serial, operator, cell), written when the job was created
        info = read_run_info(folder)
        rec.part_number = info["part"]["number"] or None
        rec.serial = info["part"]["serial"] or rec.serial
        rec.operator = info["operator"] or rec.operator
        rec.cell_id = info["cell_id"] or rec.cell_id
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
        problems.append(f"run.json damaged ({type(exc).__name__}: {exc})")
    rep = folder / "report.json"
    if rep.is_file():
        try:
            doc = json.loads(rep.read_text(encoding="utf-8"))
            job, tl = doc["job"], doc["targets"]
            if not isinstance(tl, list) or not isinstance(job, dict):
                raise ValueError("no 'targets' list or 'job' table")
            finished = job.get("finished")
            if finished is not None and not _is_time(finished):
                raise ValueError(f"job.finished {finished!r} is not an ISO 8601 time")
            rows = [target_row(t, "report.json") for t in tl]
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError, InputError) as exc:
            problems.append(f"report.json damaged ({type(exc).__name__}: {exc})")
        else:
            part = doc.get("part")
            rec.part = job.get("part")  # the part's name, as the job file and report.json's job.part say
            if isinstance(part, dict):
                rec.serial = str(part["serial"]) if part.get("serial") else rec.serial
                rec.part_number = str(part["number"]) if part.get("number") else rec.part_number
            rec.cell_id = doc.get("cell_id") or rec.cell_id
            rec.operator = doc.get("operator") or rec.operator
            rec.verdict = doc.get("verdict")
            rec.finished = finished
            rec.sigma0_px = doc.get("sigma0_px")
            rec.targets = rows
            # failed: measured and beyond tolerance; a target not measured did not fail (``not_measured``)
            rec.failed = sum(1 for t in tl if beyond(t))
            rec.not_measured = sum(1 for t in tl if not measured(t))
    rec.problem = "; ".join(problems) or None
    return rec


def _is_time(t) -> bool:
    if not isinstance(t, str):
        return False
    try:
        datetime.fromisoformat(t)
    except ValueError:
        return False
    return True
