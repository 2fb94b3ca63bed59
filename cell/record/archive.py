"""The archive: one folder per job, closed by a manifest, listed in an SQLite index.

The index is a convenience that can always be rebuilt from the folders
(:meth:`Archive.reindex`); the folders and their manifests are the record.
"""
from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import numpy as np

from calibration.errors import InputError
from cell.record.jobfolder import JobFolder

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    part TEXT,
    status TEXT NOT NULL,
    started TEXT,
    finished TEXT,
    targets INTEGER,
    failed INTEGER,
    sigma0_px REAL,
    verdict TEXT,
    folder TEXT NOT NULL
);
"""


class Archive:
    """The archive at ``root`` (default ``./archive``)."""

    def __init__(self, root: Path):
        self.root = Path(root)

    def _db(self) -> sqlite3.Connection:
        self.root.mkdir(parents=True, exist_ok=True)
        con = sqlite3.connect(self.root / "index.sqlite", timeout=10)
        con.execute("PRAGMA journal_mode=WAL")
        con.executescript(_SCHEMA)
        return con

    def folder(self, job_id: str) -> JobFolder:
        p = self.root / job_id
        if not p.is_dir():
            raise InputError(f"{self.root}: no job {job_id!r} in the archive (see 'cell archive list')")
        return JobFolder(p)

    def record(self, job_id: str, **fields) -> None:
        """Insert or update a job's row."""
        con = self._db()
        with con:
            row = con.execute("SELECT id FROM jobs WHERE id=?", (job_id,)).fetchone()
            if row is None:
                fields.setdefault("folder", str(self.root / job_id))
                fields.setdefault("name", job_id)
                fields.setdefault("status", "CREATED")
                cols = ["id", *fields]
                con.execute(f"INSERT INTO jobs ({','.join(cols)}) VALUES ({','.join('?' * len(cols))})",
                            [job_id, *fields.values()])
            elif fields:
                con.execute(f"UPDATE jobs SET {','.join(f'{k}=?' for k in fields)} WHERE id=?", [*fields.values(), job_id])
        con.close()

    def list(self) -> list[dict]:
        con = self._db()
        con.row_factory = sqlite3.Row
        rows = [dict(r) for r in con.execute("SELECT * FROM jobs ORDER BY started, id")]
        con.close()
        return rows

    def reindex(self, only: Path | None = None) -> int:
        """Rebuild the index from the job folders (their journals and reports); ``only`` one folder."""
        n = 0
        dirs = [Path(only)] if only is not None else (sorted(self.root.iterdir()) if self.root.exists() else [])
        for d in dirs:
            if not (d / "journal.jsonl").exists():
                continue
            folder = JobFolder(d)
            recs = list(folder.records())
            status = next((r["to"] for r in reversed(recs) if r["event"] == "state"), "CREATED")
            start = recs[0]["t"] if recs else None
            name = next((r.get("name") for r in recs if r["event"] == "created"), d.name)
            fields = {"name": name, "status": status, "started": start}
            rep = d / "report.json"
            if rep.exists():
                doc = json.loads(rep.read_text())
                fields |= {"finished": doc["job"].get("finished"), "targets": len(doc["targets"]),
                           "failed": sum(not t["pass"] for t in doc["targets"]), "sigma0_px": doc.get("sigma0_px"),
                           "verdict": doc.get("verdict"), "part": doc["job"].get("part")}
            self.record(d.name, **fields)
            n += 1
        return n

    def show(self, job_id: str) -> dict:
        folder = self.folder(job_id)
        rep = folder.file("report.json")
        doc = {"id": job_id, "folder": str(folder.path), "journal": list(folder.records())[-5:]}
        if rep.exists():
            r = json.loads(rep.read_text())
            doc |= {"job": r["job"], "verdict": r.get("verdict"), "sigma0_px": r.get("sigma0_px"),
                    "targets": len(r["targets"]), "failed": [t["id"] for t in r["targets"] if not t["pass"]]}
        return doc

    def compare(self, ids: list[str]) -> dict:
        """Deviation trends of the same part over several jobs: per target, the deviation norm in each job."""
        if len(ids) < 2:
            raise InputError("cell archive compare needs at least two job ids")
        reports = []
        for j in ids:
            p = self.folder(j).file("report.json")
            if not p.exists():
                raise InputError(f"{j}: has no report (status: not DONE)")
            reports.append(json.loads(p.read_text()))
        parts = {r["job"].get("part") for r in reports}
        if len(parts) > 1:
            raise InputError(f"cell archive compare: the jobs inspect different parts ({', '.join(map(str, parts))})")
        common = set.intersection(*({t["id"] for t in r["targets"]} for r in reports))
        rows = []
        for tid in sorted(common):
            dev = [next(t for t in r["targets"] if t["id"] == tid) for r in reports]
            norms = [d["deviation_norm_m"] for d in dev]
            sig = [d["achieved_sigma_m"] for d in dev]
            change = np.asarray(dev[-1]["measured"]) - np.asarray(dev[0]["measured"])
            sig_change = float(np.hypot(sig[0], sig[-1]))
            rows.append({"id": tid, "deviation_norm_m": norms, "pass": [d["pass"] for d in dev],
                         "drift_m": float(np.linalg.norm(change)),
                         "drift_significant": bool(np.linalg.norm(change) > 3 * sig_change)})
        return {"jobs": ids, "part": parts.pop(), "targets": rows,
                "drifting": [r["id"] for r in rows if r["drift_significant"]]}

    def verify(self, job_id: str) -> list[str]:
        return self.folder(job_id).verify_manifest()
