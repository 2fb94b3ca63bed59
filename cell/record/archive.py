"""The archive: one folder per job, closed by a manifest, listed in an SQLite index.

The index is a convenience that can always be rebuilt from the folders
(:meth:`Archive.reindex`); the folders and their manifests are the record.

Job ids are names, never paths: :func:`resolve_job_id` is the one way from an id (given on
the command line or to the web console) to a job folder, and it never leaves the archive.
A job still being set up (before ACQUIRE) lives in ``.incoming/``; it is found there too.
"""
from __future__ import annotations

import json
import os
import re
import sqlite3
import time
from pathlib import Path

import numpy as np

from calibration.errors import InputError
from cell.record.jobfolder import JobFolder
from cell.record.runinfo import read_run_info

#: what a job id may be made of: letters, digits, '-', '_', '.', '+', ':' (not first: '.'); no separators
JOB_ID_PATTERN = re.compile(r"[A-Za-z0-9_+:-][A-Za-z0-9_.+:-]{0,199}")
INCOMING = ".incoming"


def check_job_id(job_id: str) -> str:
    """``job_id`` if it is a plain name (no path separator, no '..', no leading '.'); else ``InputError``."""
    if not isinstance(job_id, str) or not JOB_ID_PATTERN.fullmatch(job_id) or job_id in (".", ".."):
        shown = job_id if isinstance(job_id, str) and len(job_id) < 80 else f"{str(job_id)[:80]}..."
        raise InputError(f"{shown!r} is not a job id: an id is a name of letters, digits, '-', '_', '.', '+', ':' "
                         "(no path, no '..'); see 'cell archive list'")
    return job_id


def resolve_job_id(root: Path, job_id: str) -> JobFolder:
    """The folder of job ``job_id`` in the archive at ``root`` (finished, or staged in ``.incoming``).

    The id is a name, never a path; a folder that is a symlink leading out of the archive is
    refused. Used by every command that takes a job id, and by the web console.

    Raises:
        InputError: not a job id, no such job, or a folder that leaves the archive.
    """
    check_job_id(job_id)
    root = Path(root)
    real_root = root.resolve()
    for parent in (root, root / INCOMING):
        p = parent / job_id
        if not (p.is_dir() or p.is_symlink()):
            continue
        real = p.resolve()
        if real.parent != parent.resolve() or not real.is_relative_to(real_root) or not real.is_dir():
            raise InputError(f"{root}: job {job_id!r} is a link that leads out of the archive ({real}); refused")
        return JobFolder(p)
    raise InputError(f"{root}: no job {job_id!r} in the archive (see 'cell archive list')")


def check_archive_root(root: Path, *, write: bool) -> Path:
    """The archive folder, checked: not a file; writable when ``write``. ``InputError`` otherwise."""
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise InputError(f"--archive {root}: is a file, not an archive folder")
    if write:
        try:
            root.mkdir(parents=True, exist_ok=True)
            probe = root / f".write-probe-{os.getpid()}"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            raise InputError(f"--archive {root}: cannot write there ({exc.strerror or exc}); choose a writable "
                             "folder") from None
    return root

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
    folder TEXT NOT NULL,
    part_number TEXT,
    serial TEXT,
    operator TEXT,
    cell_id TEXT
);
"""
#: columns added after the first release: an index written before them gets them on open
_ADDED = ("part_number", "serial", "operator", "cell_id")


def _add_columns(con: sqlite3.Connection) -> None:
    have = {r[1] for r in con.execute("PRAGMA table_info(jobs)")}
    for col in _ADDED:
        if col not in have:
            con.execute(f"ALTER TABLE jobs ADD COLUMN {col} TEXT")


class Archive:
    """The archive at ``root`` (default ``./archive``)."""

    def __init__(self, root: Path):
        self.root = Path(root)
        #: job id -> what is damaged in its folder, found by the last :meth:`reindex` / :meth:`summary`
        self.problems: dict[str, str] = {}

    def _db(self) -> sqlite3.Connection:
        check_archive_root(self.root, write=False)
        self.root.mkdir(parents=True, exist_ok=True)
        path = self.root / "index.sqlite"
        con = None
        try:
            con = sqlite3.connect(path, timeout=10)
            con.execute("PRAGMA journal_mode=WAL")
            con.executescript(_SCHEMA)
            _add_columns(con)
            return con
        except sqlite3.OperationalError:  # locked, disk full, read-only: not damage
            if con is not None:
                con.close()
            raise
        except sqlite3.DatabaseError:  # a damaged index: it is only a convenience; set it aside and rebuild
            if con is not None:
                con.close()
            if not path.exists():
                raise
            path.rename(path.with_name(f"index.sqlite.damaged-{time.strftime('%Y%m%dT%H%M%S')}"))
            for extra in ("-wal", "-shm"):
                path.with_name(path.name + extra).unlink(missing_ok=True)
            con = sqlite3.connect(path, timeout=10)
            con.execute("PRAGMA journal_mode=WAL")
            con.executescript(_SCHEMA)
            _add_columns(con)
            self.reindex()
            return con

    def folder(self, job_id: str) -> JobFolder:
        """The job's folder (see :func:`resolve_job_id`)."""
        return resolve_job_id(self.root, job_id)

    def staged(self) -> list[JobFolder]:
        """Jobs still in ``.incoming`` (stopped before ACQUIRE): listed, resumable."""
        inc = self.root / INCOMING
        if not inc.is_dir():
            return []
        return [JobFolder(d) for d in sorted(inc.iterdir()) if d.is_dir() and not d.is_symlink()
                and JOB_ID_PATTERN.fullmatch(d.name)]

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
        """Rebuild the index from the job folders (their journals and reports); ``only`` one folder.

        A folder that is not a job (no journal) is skipped; a job whose journal or report is damaged
        is indexed from what reads (its problems in :attr:`problems`), never failing the others.
        """
        n = 0
        self.problems: dict[str, str] = {}
        if only is not None:
            dirs = [Path(only)]
        elif self.root.is_dir():
            dirs = sorted(d for d in self.root.iterdir() if d.is_dir() and not d.is_symlink()
                          and JOB_ID_PATTERN.fullmatch(d.name))
        else:
            dirs = []
        for d in dirs:
            fields = self.summary(JobFolder(d))
            if fields is None:
                continue
            self.record(d.name, **fields)
            n += 1
        return n

    def summary(self, folder: JobFolder) -> dict | None:
        """What the index holds of a job, from its folder (None: not a job); problems noted in :attr:`problems`."""
        d = folder.path
        if not (d / "journal.jsonl").is_file():
            return None
        try:
            recs, damage = folder.read_journal()
        except OSError as exc:
            recs, damage = [], exc
        if damage is not None:
            self.problems[d.name] = f"journal damaged: {damage}"
        status = next((r.get("to") for r in reversed(recs) if r.get("event") == "state"), "CREATED")
        start = recs[0].get("t") if recs else None
        name = next((r.get("name") for r in recs if r.get("event") == "created"), d.name)
        fields = {"name": str(name), "status": str(status), "started": start}
        try:
            info = read_run_info(d)
            fields |= {"part_number": info["part"]["number"], "serial": info["part"]["serial"],
                       "operator": info["operator"], "cell_id": info["cell_id"]}
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
            self.problems[d.name] = f"run.json damaged ({type(exc).__name__}: {exc})"
        rep = d / "report.json"
        if rep.is_file():
            try:
                doc = json.loads(rep.read_text(encoding="utf-8"))
                targets = doc["targets"]
                fields |= {"finished": doc["job"].get("finished"), "targets": len(targets),
                           "failed": sum(not t["pass"] for t in targets), "sigma0_px": doc.get("sigma0_px"),
                           "verdict": doc.get("verdict"), "part": doc["job"].get("part")}
            except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as exc:
                self.problems[d.name] = f"report.json damaged ({type(exc).__name__}: {exc})"
        return fields

    def listing(self) -> list[dict]:
        """``cell archive list``: every job of the index (rebuilt first), staged ones too, with their problems."""
        self.reindex()
        rows = self.list()
        for r in rows:
            r["staged"] = False
            if r["id"] in self.problems:
                r["problem"] = self.problems[r["id"]]
        for f in self.staged():
            fields = self.summary(f)
            if fields is None:
                continue
            row = {"id": f.job_id, "folder": str(f.path), "staged": True, **fields}
            if f.job_id in self.problems:
                row["problem"] = self.problems[f.job_id]
            rows.append(row)
        return rows

    def show(self, job_id: str) -> dict:
        folder = self.folder(job_id)
        recs, damage = folder.read_journal()
        doc = {"id": job_id, "folder": str(folder.path), "journal": recs[-5:]}
        if damage is not None:
            doc["problem"] = f"journal damaged: {damage}"
        rep = folder.file("report.json")
        if rep.is_file():
            try:
                r = json.loads(rep.read_text(encoding="utf-8"))
                doc |= {"job": r["job"], "verdict": r.get("verdict"), "sigma0_px": r.get("sigma0_px"),
                        "targets": len(r["targets"]), "failed": [t["id"] for t in r["targets"] if not t["pass"]]}
            except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as exc:
                doc["problem"] = f"report.json damaged ({type(exc).__name__}: {exc})"
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
            try:
                doc = json.loads(p.read_text(encoding="utf-8"))
                if not isinstance(doc.get("targets"), list) or not isinstance(doc.get("job"), dict):
                    raise ValueError("no 'targets' list or 'job' table")
            except (OSError, UnicodeDecodeError, ValueError, AttributeError) as exc:
                raise InputError(f"{j}: report.json is damaged ({exc}); see 'cell archive verify {j}'") from None
            reports.append(doc)
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
        """Problems of the job's folder against its manifest and its journal (empty: intact)."""
        from cell.record import integrity

        folder = self.folder(job_id)
        problems = folder.verify_manifest()
        recs, damage = folder.read_journal()
        if damage is not None:
            problems.append(f"journal damaged: {damage}")
        found = integrity.check_stored(folder, recs, decode_images=False)
        problems += [f"station {sid}: {why}" for sid, why in found.stations.items()]
        problems += [f"{rel}: {why} (per the journal)" for rel, (why, _) in found.files.items()]
        return list(dict.fromkeys(problems))
