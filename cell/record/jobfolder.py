"""The job folder: atomic files, an append-only journal, and the manifest that closes it.

Durability rules (see shared notes/durability.md): a file counts as written only
when its bytes are in a temporary file that was flushed, fsync'ed and renamed
over the final name (and the folder fsync'ed); a journal record counts only when
its line is flushed and fsync'ed. Readers ignore a torn last journal line.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator

import numpy as np

MANIFEST = "manifest.json"
JOURNAL = "journal.jsonl"


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a crash leaves the old file or the new one, never half of it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def to_jsonable(o: Any) -> Any:
    if isinstance(o, dict):
        return {str(k): to_jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [to_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return to_jsonable(o.tolist())
    if isinstance(o, (np.floating,)):
        o = float(o)
    if isinstance(o, float):
        return o if np.isfinite(o) else None
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.bool_,)):
        return bool(o)
    if isinstance(o, Path):
        return str(o)
    return o


def atomic_write_json(path: Path, doc: Any) -> None:
    atomic_write_bytes(path, (json.dumps(to_jsonable(doc), indent=1) + "\n").encode())


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


@dataclass
class JobFolder:
    """One job's folder in the archive."""

    path: Path

    @property
    def job_id(self) -> str:
        return self.path.name

    def file(self, name: str) -> Path:
        return self.path / name

    def read_json(self, name: str) -> Any:
        """A JSON result an earlier stage wrote (``plan.json``, ``observations.json``, ...)."""
        return json.loads(self.file(name).read_text())

    # --- journal ----------------------------------------------------------
    def append(self, event: str, **fields: Any) -> dict:
        rec = {"t": utc_now(), "event": event} | to_jsonable(fields)
        line = json.dumps(rec) + "\n"
        with open(self.path / JOURNAL, "a", encoding="utf-8") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())
        return rec

    def records(self) -> Iterator[dict]:
        p = self.path / JOURNAL
        if not p.exists():
            return
        with open(p, encoding="utf-8") as f:
            for line in f:
                if not line.endswith("\n"):
                    break  # torn last line of a crash
                try:
                    yield json.loads(line)
                except json.JSONDecodeError:
                    break

    def lock(self) -> int:
        """Take the job's session lock (``.lock``, an exclusive ``flock``); returns its file descriptor.

        One process at a time runs a job: a second ``cell resume`` while a session still runs
        would acquire the same stations twice. The lock goes with the process (also on SIGKILL).
        Raises ``InputError`` if another process holds it.
        """
        import fcntl

        from calibration.errors import InputError

        fd = os.open(self.path / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise InputError(f"{self.job_id}: the job is running in another process; wait for it to end "
                             "(or stop it) before resuming") from None
        return fd

    def remove_partial_files(self) -> list[str]:
        """Delete the temporary files of writes a killed session left unfinished (``.NAME.tmpPID``).

        Such a file never became the file it was meant to be (the rename did not happen);
        returns their paths relative to the folder.
        """
        gone = []
        for p in sorted(self.path.rglob(".*.tmp*")):
            if p.is_file():
                p.unlink()
                gone.append(str(p.relative_to(self.path)))
        return gone

    # --- manifest -----------------------------------------------------------
    def write_manifest(self) -> dict:
        files = {}
        for p in sorted(self.path.rglob("*")):
            if p.is_file() and p.name != MANIFEST and not p.name.startswith("."):
                files[str(p.relative_to(self.path))] = {"sha256": sha256_file(p), "bytes": p.stat().st_size}
        doc = {"job_id": self.job_id, "written": utc_now(), "files": files}
        atomic_write_json(self.path / MANIFEST, doc)
        return doc

    def verify_manifest(self) -> list[str]:
        """Problems found (empty when intact)."""
        p = self.path / MANIFEST
        if not p.exists():
            return [f"{self.job_id}: no manifest (the job never closed)"]
        doc = json.loads(p.read_text())
        problems = []
        for name, meta in doc["files"].items():
            f = self.path / name
            if not f.exists():
                problems.append(f"{name}: missing")
            elif sha256_file(f) != meta["sha256"]:
                problems.append(f"{name}: changed (sha256 differs)")
        listed = set(doc["files"])
        for f in self.path.rglob("*"):
            rel = str(f.relative_to(self.path))
            if f.is_file() and f.name != MANIFEST and not f.name.startswith(".") and rel not in listed:
                problems.append(f"{rel}: not in the manifest")
        return problems


def new_job_id(name: str, now: float | None = None) -> str:
    stamp = time.strftime("%Y-%m-%dT%H-%M-%S", time.localtime(now))
    safe = "".join(c if c.isalnum() or c in "-_" else "-" for c in name)[:40]
    return f"{stamp}-{safe}"
