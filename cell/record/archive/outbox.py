"""The outbox: jobs of this cell whose index write is waiting for the database.

One small file per job, ``<archive>/.outbox/index/<job_id>.json`` ({``job_id``, ``since``, ``reason``,
``kind``}), written atomically when a write to the index fails: ``kind`` ``unreachable`` (the database is
away or silent: the next write retries), ``refused`` (the database refused the record, e.g. a value too
long for its column) or ``conflict`` (another cell's job has this id): these two wait for a person, and
``cell archive verify`` counts them as problems. The reason never holds a password. The
folder holds the job's truth, so the outbox holds no copy of it: draining re-reads the folder and
writes its record in one transaction, then removes the file. A process killed between the two
leaves the file, and the next drain writes the same record again (idempotent: one row per job).
Pushes to shared storage that failed wait the same way in ``.outbox/push/``.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from cell.record.jobfolder import atomic_write_json, utc_now

OUTBOX = ".outbox"


class Outbox:
    def __init__(self, root: Path, kind: str = "index"):
        self.path = Path(root) / OUTBOX / kind

    def add(self, job_id: str, reason: str, kind: str = "unreachable") -> None:
        """Put ``job_id`` in the outbox (or keep it there: the first failure's time, the newest reason)."""
        p = self.path / f"{job_id}.json"
        if p.exists():
            old = self.entry(job_id)
            if kind == "unreachable" or (old.get("reason") == reason and old.get("kind", "unreachable") == kind):
                return  # waiting for the database: the first failure's reason says most
            doc = {"job_id": job_id, "since": old.get("since") or utc_now(), "reason": reason, "kind": kind}
            st = p.stat()
            atomic_write_json(p, doc)
            os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns))  # its place in the queue (oldest first) stays
            return
        atomic_write_json(p, {"job_id": job_id, "since": utc_now(), "reason": reason, "kind": kind})

    def pending(self) -> list[str]:
        """Job ids waiting, oldest first."""
        if not self.path.is_dir():
            return []
        files = [p for p in self.path.glob("*.json") if not p.name.startswith(".")]
        files.sort(key=lambda p: (p.stat().st_mtime, p.name))
        return [p.name[:-len(".json")] for p in files]

    def entry(self, job_id: str) -> dict:
        try:
            return json.loads((self.path / f"{job_id}.json").read_text())
        except (OSError, ValueError):
            return {"job_id": job_id}

    def done(self, job_id: str) -> None:
        try:
            os.unlink(self.path / f"{job_id}.json")
        except FileNotFoundError:
            pass
