"""What the index holds of one job, read from its folder (the record of truth).

:func:`job_record` reads the journal (name, state, start), ``report.json`` (part, serial,
verdict, every judged target's values) and the manifest's hash; the index stores exactly
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
from cell.record.jobfolder import MANIFEST, JobFolder


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
            "uncertainty_u_m": _num(t.get("uncertainty_U_m")), "decision": t.get("decision"),
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
    serial: str | None = None
    cell_id: str | None = None
    verdict: str | None = None
    started: str | None = None
    finished: str | None = None
    sigma0_px: float | None = None
    manifest_sha256: str | None = None
    targets: list[dict] = field(default_factory=list)
    failed: int | None = None

    def job_row(self) -> dict:
        return {"id": self.id, "name": self.name, "part": self.part, "serial": self.serial, "cell_id": self.cell_id,
                "status": self.status, "verdict": self.verdict, "started": self.started, "finished": self.finished,
                "targets": len(self.targets) if self.verdict is not None else None, "failed": self.failed,
                "sigma0_px": _num(self.sigma0_px), "origin": self.origin, "folder": self.folder,
                "manifest_sha256": self.manifest_sha256}


def manifest_sha256(folder: Path) -> str | None:
    p = Path(folder) / MANIFEST
    if not p.exists():
        return None
    return hashlib.sha256(p.read_bytes()).hexdigest()


def job_record(folder: Path, origin: str) -> JobRecord:
    """The index record of the job folder ``folder`` (raises ``InputError`` naming a malformed file)."""
    folder = Path(folder)
    jf = JobFolder(folder)
    recs = list(jf.records())
    status = next((r["to"] for r in reversed(recs) if r.get("event") == "state"), "CREATED")
    created = next((r for r in recs if r.get("event") == "created"), {})
    rec = JobRecord(id=folder.name, name=created.get("name") or folder.name, status=status, origin=origin,
                    folder=str(folder), started=recs[0]["t"] if recs else None, serial=created.get("serial"),
                    cell_id=created.get("cell_id"), manifest_sha256=manifest_sha256(folder))
    rep = folder / "report.json"
    if rep.exists():
        try:
            doc = json.loads(rep.read_text())
            job = doc["job"]
            tl = doc["targets"]
        except (ValueError, KeyError, TypeError) as exc:
            raise InputError(f"{rep}: not a report of this cell ({type(exc).__name__}: {exc})") from None
        part = doc.get("part")
        rec.part = job.get("part")  # the part's name, as the job file and report.json's job.part say
        if isinstance(part, dict) and part.get("serial"):
            rec.serial = str(part["serial"])
        rec.cell_id = doc.get("cell_id") or rec.cell_id
        rec.verdict = doc.get("verdict")
        rec.finished = job.get("finished")
        try:
            for t in (rec.started, rec.finished):
                if t is not None:
                    datetime.fromisoformat(t)
        except (TypeError, ValueError):
            raise InputError(f"{rep}: job.finished {rec.finished!r} is not an ISO 8601 time") from None
        rec.sigma0_px = doc.get("sigma0_px")
        rec.targets = [target_row(t, str(rep)) for t in tl]
        rec.failed = sum(1 for t in tl if not t.get("pass"))
    return rec
