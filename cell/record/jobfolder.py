"""The job folder: atomic files, an append-only journal, and the manifest that closes it.

Durability rules (see shared notes/durability.md): a file counts as written only
when its bytes are in a temporary file that was flushed, fsync'ed and renamed
over the final name (and the folder fsync'ed); a journal record counts only when
its line is flushed and fsync'ed. Readers ignore a torn last journal line (a crash
mid-write), and nothing else: every record carries ``h``, a checksum of the rest of
its line, so a flipped byte anywhere in the journal is found and named (line number),
never read as a different record.
"""
from __future__ import annotations

import contextlib
import contextvars
import hashlib
import json
import math
import os
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from calibration.errors import RecordError

MANIFEST = "manifest.json"
JOURNAL = "journal.jsonl"
#: where files that failed verification are moved (kept for the record, out of the job's data)
DAMAGED = "damaged"


class JournalDamaged(RecordError):
    """A complete journal line that does not read back as the record written (``line`` 1-based)."""

    def __init__(self, path: Path, line: int, why: str):
        super().__init__(f"{path}:{line}: {why}")
        self.path, self.line, self.why = path, line, why


def _line_hash(body: str) -> str:
    return hashlib.sha256(body.encode("utf-8")).hexdigest()[:16]


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


#: the job folder whose stage is running in this thread (context), and the stage: see :meth:`JobFolder.recording`
_RECORDING: contextvars.ContextVar[tuple["JobFolder", str] | None] = contextvars.ContextVar("recording", default=None)


def recording_now() -> "tuple[JobFolder, str] | None":
    """The job folder whose stage runs in this thread, and the stage (None outside a job's stage): code that
    has no handle on the job (a cache deep in a stage) journals what it must say there."""
    return _RECORDING.get()


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a crash leaves the old file or the new one, never half of it.

    While a stage of a job runs (:meth:`JobFolder.recording`), a file written into that job's folder is
    journalled first (``stored``: path, sha256, stage), then renamed into place: the journal vouches for
    every version of every result (images excepted: their ``station_done`` record does it).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    rec = _RECORDING.get()
    if rec is not None:
        folder, stage = rec
        try:
            rel = path.resolve().relative_to(folder.path.resolve())
        except ValueError:
            rel = None
        if rel is not None and rel.parts[0] != "images":
            folder.append("stored", file=str(rel), sha256=hashlib.sha256(data).hexdigest(), stage=stage)
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def to_jsonable(o: Any) -> Any:
    if isinstance(o, dict):
        return {str(k): to_jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [to_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        if o.dtype.kind in "iub" or (o.dtype.kind == "f" and np.isfinite(o).all()):
            return o.tolist()  # already Python ints, bools and finite floats: no walk element by element
        return to_jsonable(o.tolist())
    if isinstance(o, (np.floating,)):
        o = float(o)
    if isinstance(o, float):
        return o if math.isfinite(o) else None
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
        rec["h"] = _line_hash(json.dumps(rec))
        line = json.dumps(rec) + "\n"
        # never through a symlink: the journal is this folder's own file
        fd = os.open(self.path / JOURNAL, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        with open(fd, "a", encoding="utf-8") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())
        del rec["h"]
        return rec

    def read_journal(self) -> tuple[list[dict], JournalDamaged | None]:
        """The journal's records up to the first damaged line, and that damage (None when it reads whole).

        A last line without its newline is a write cut short by a crash and is ignored, unless it is
        a complete record (then its newline was lost: damage). Lines written by an older version,
        without checksums, are read as they are, but only before the first checksummed one.
        """
        p = self.path / JOURNAL
        if not p.is_file():
            return [], None
        data = p.read_bytes()
        lines = data.split(b"\n")
        tail = lines.pop()
        out: list[dict] = []
        hashed_seen = False
        for i, raw in enumerate(lines, 1):
            rec, why = _parse_line(raw)
            if why is None:
                hashed = rec.pop("_hashed")
                if hashed_seen and not hashed:  # an older version's lines may only come first
                    why = "record without its checksum"
                hashed_seen |= hashed
            if why is not None:
                return out, JournalDamaged(p, i, why)
            out.append(rec)
        if tail and not _torn(tail):
            return out, JournalDamaged(p, len(lines) + 1, "the last line is neither a record nor a write cut short")
        return out, None

    def drop_torn_tail(self) -> int:
        """Cut a last line that a crash left unfinished (see :meth:`read_journal`), so that new records
        start on a line of their own; returns the number of bytes cut."""
        p = self.path / JOURNAL
        if not p.is_file():
            return 0
        data = p.read_bytes()
        keep = data.rfind(b"\n") + 1
        if keep == len(data):
            return 0
        fd = os.open(p, os.O_WRONLY | os.O_NOFOLLOW)
        try:
            os.ftruncate(fd, keep)
            os.fsync(fd)
        finally:
            os.close(fd)
        return len(data) - keep

    def records(self) -> Iterator[dict]:
        """Every record of the journal; ``JournalDamaged`` at a damaged line (after yielding those before it)."""
        recs, damage = self.read_journal()
        yield from recs
        if damage is not None:
            raise damage
    def lock(self) -> int:
        """Take the job's session lock (``.lock``, an exclusive ``flock``); returns its file descriptor.

        One process at a time runs a job: a second ``cell resume`` while a session still runs
        would acquire the same stations twice. The lock goes with the process (also on SIGKILL).
        Raises ``InputError`` if another process holds it.
        """
        import fcntl

        from calibration.errors import InputError

        fd = os.open(self.path / ".lock", os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise InputError(f"{self.job_id}: the job is running in another process; wait for it to end "
                             "(or stop it) before resuming") from None
        try:  # who holds it: an abort from another process (the console) signals this pid
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError:
            pass
        return fd

    def running_pid(self) -> int | None:
        """The pid of the process running this job now (it holds ``.lock``), or None."""
        import fcntl

        try:
            fd = os.open(self.path / ".lock", os.O_RDONLY | os.O_NOFOLLOW)
        except OSError:
            return None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                # :meth:`lock` writes its pid just after taking the lock: wait (bounded) for it to be there
                end = time.monotonic() + 0.2
                while True:
                    text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
                    if text.isdigit() or time.monotonic() > end:
                        return int(text) if text.isdigit() else None
                    time.sleep(0.002)
            fcntl.flock(fd, fcntl.LOCK_UN)
            return None
        finally:
            os.close(fd)

    def remove_partial_files(self) -> list[str]:
        """Delete the temporary files of writes a killed session left unfinished (:func:`is_partial`:
        ``.NAME.tmpPID`` of :func:`atomic_write_bytes`, and any ``*.tmp`` of another writer).

        Such a file never became the file it was meant to be (the rename did not happen);
        returns their paths relative to the folder.
        """
        gone = []
        for p in sorted(self.path.rglob("*")):
            if p.is_file() and not p.is_symlink() and is_partial(p.name):
                p.unlink()
                gone.append(str(p.relative_to(self.path)))
        return gone

    @contextlib.contextmanager
    def recording(self, stage: str):
        """While in this block, files written with :func:`atomic_write_bytes` into this folder are journalled."""
        token = _RECORDING.set((self, stage))
        try:
            yield self
        finally:
            _RECORDING.reset(token)

    # --- stored files -----------------------------------------------------------
    def stored_files(self) -> list[str]:
        """The job's data files (relative paths): not the journal, run logs, manifest, hidden or damaged files."""
        out = []
        for p in sorted(self.path.rglob("*")):
            rel = p.relative_to(self.path)
            if p.is_symlink() or not p.is_file() or any(part.startswith(".") for part in rel.parts):
                continue
            if rel.parts[0] == DAMAGED or p.name in (MANIFEST, JOURNAL) or _is_run_log(p.name) or is_partial(p.name):
                continue
            out.append(str(rel))
        return out

    def quarantine(self, rel: str) -> str | None:
        """Move a file that failed verification to ``damaged/`` (kept, out of the job's data); its new path."""
        src = self.path / rel
        if not src.exists():
            return None
        dst = self.path / DAMAGED / f"{rel}.{time.strftime('%Y%m%dT%H%M%S')}"
        dst.parent.mkdir(parents=True, exist_ok=True)
        os.replace(src, dst)
        _fsync_dir(dst.parent)
        return str(dst.relative_to(self.path))

    # --- manifest -----------------------------------------------------------
    def write_manifest(self, unverified: dict[str, str] | None = None, expected: dict[str, str] | None = None) -> dict:
        """Close the folder: sha256 of every file, but those in ``unverified`` (path -> why) and those whose
        sha256 differs from ``expected`` (path -> the sha256 the journal recorded), which are listed apart
        and not vouched for."""
        unverified = dict(unverified or {})
        expected = expected or {}
        files = {}
        for p in sorted(self.path.rglob("*")):
            rel = str(p.relative_to(self.path))
            if p.is_symlink() or not p.is_file() or p.name == MANIFEST or \
                    any(part.startswith(".") for part in p.relative_to(self.path).parts):
                continue
            if rel in unverified:
                continue
            if is_partial(p.name):  # a write a killed session left unfinished: never vouched for
                unverified[rel] = "a temporary file of a write that never finished (killed before its rename)"
                continue
            sha = sha256_file(p)
            if rel in expected and expected[rel] != sha:
                unverified[rel] = "differs from the sha256 the journal recorded when it was written"
                continue
            files[rel] = {"sha256": sha, "bytes": p.stat().st_size}
        doc = {"job_id": self.job_id, "written": utc_now(), "files": files}
        if unverified:
            doc["unverified"] = unverified
        atomic_write_json(self.path / MANIFEST, doc)
        return doc

    def verify_manifest(self) -> list[str]:
        """Problems found (empty when intact); a damaged manifest is one problem, never an exception."""
        p = self.path / MANIFEST
        if not p.exists():
            return [f"{self.job_id}: no manifest (the job never closed)"]
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
            listed_files = doc["files"]
            if not isinstance(listed_files, dict) or not all(
                    isinstance(m, dict) and isinstance(m.get("sha256"), str) for m in listed_files.values()):
                raise ValueError("'files' is not a table of sha256")
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
            return [f"{MANIFEST}: damaged ({type(exc).__name__}: {exc}); 'cell archive verify {self.job_id} --repair' "
                    "rewrites it over the files the journal vouches for"]
        problems = []
        for name, meta in listed_files.items():
            f = self.path / name
            if not f.is_file():
                problems.append(f"{name}: missing")
            elif sha256_file(f) != meta["sha256"]:
                problems.append(f"{name}: changed (sha256 differs)")
        listed = set(listed_files) | set(doc.get("unverified") or {})
        for f in self.path.rglob("*"):
            rel = str(f.relative_to(self.path))
            if f.is_file() and f.name != MANIFEST and not any(part.startswith(".") for part in f.relative_to(self.path).parts) \
                    and rel not in listed:
                problems.append(f"{rel}: not in the manifest")
        for name, why in (doc.get("unverified") or {}).items():
            problems.append(f"{name}: not vouched for ({why})")
        return problems


def is_partial(name: str) -> bool:
    """Whether a file name is that of a write left unfinished: ``.NAME.tmpPID`` (:func:`atomic_write_bytes`),
    ``.NAME.XXXX.tmp`` (``planning.cache``) or ``NAME.XXXX.tmp`` (any other writer's ``mkstemp``)."""
    return (name.startswith(".") and ".tmp" in name) or name.endswith(".tmp")


def _is_run_log(name: str) -> bool:
    return name.startswith("run.") and name.endswith(".mcap")


def _torn(tail: bytes) -> bool:
    """Whether ``tail`` (a last line without its newline) is a record cut short: the start of a JSON
    object that runs out before its end. A complete record (its newline lost), or a complete one
    followed by junk, or junk, is not."""
    try:
        text = tail.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.reason != "unexpected end of data":  # only a multi-byte character cut at the very end is a tear
            return False
        text = tail[:exc.start].decode("utf-8")
    if not text.startswith("{"):
        return False
    try:
        json.loads(text)
    except json.JSONDecodeError as exc:
        return exc.msg != "Extra data"
    return False  # a whole record without its line end: damage


def _parse_line(raw: bytes) -> tuple[dict | None, str | None]:
    """(record with ``_hashed``, None) for a good line, else (None, why)."""
    try:
        rec = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        return None, "not UTF-8 text (a damaged byte)"
    except json.JSONDecodeError as exc:
        return None, f"not a JSON record ({exc.msg} at column {exc.colno})"
    if not isinstance(rec, dict) or not isinstance(rec.get("event"), str):
        return None, "not a journal record (no 'event')"
    h = rec.pop("h", None)
    if h is None:
        rec["_hashed"] = False
        return rec, None
    if h != _line_hash(json.dumps(rec)):
        return None, "record damaged (its checksum differs)"
    # the checksum is over the record as JSON text: a flipped digit that parses to the same float
    # (the 17th of a double) would pass it, so the line must also be byte for byte what append() wrote
    if raw.decode("utf-8") != json.dumps(rec | {"h": h}):
        return None, "record damaged (its bytes differ from the record they spell)"
    rec["_hashed"] = True
    return rec, None


def new_job_id(name: str, now: float | None = None) -> str:
    """``<local time>-<name>``: the name kept to ASCII letters, digits, '-' and '_' (what a job id may hold everywhere:
    the archive's resolver, the console's routes): accents transliterated ('Bügel' -> 'Bugel'), anything else '-'."""
    import unicodedata

    stamp = time.strftime("%Y-%m-%dT%H-%M-%S", time.localtime(now))
    ascii_name = unicodedata.normalize("NFKD", name).encode("ascii", "ignore").decode("ascii")
    safe = "".join(c if (c.isascii() and c.isalnum()) or c in "-_" else "-" for c in ascii_name)[:40]
    return f"{stamp}-{safe}"
