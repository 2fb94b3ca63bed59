"""Helpers of the fault-injection suite: copies of one finished job (the example job, run once per test
session by ``jobutil.example_run``), cut back to earlier moments of its life, and snapshots of a folder."""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

from jobutil import records


def copy_job(folder: Path, archive: Path) -> Path:
    """A copy of the job folder ``folder`` in ``archive`` (same id); the index is rebuilt on first use."""
    archive.mkdir(parents=True, exist_ok=True)
    dst = archive / folder.name
    shutil.copytree(folder, dst, ignore=shutil.ignore_patterns(".lock"))
    return dst


def journal_lines(folder: Path) -> list[bytes]:
    return (folder / "journal.jsonl").read_bytes().splitlines(keepends=True)


def cut_journal(folder: Path, keep) -> list[dict]:
    """Keep the journal's lines up to and including the first for which ``keep(record, index)`` is False
    excluded: i.e. keep lines while ``keep`` says so (bytes untouched); returns the kept records."""
    lines = journal_lines(folder)
    recs = [json.loads(ln) for ln in lines]
    n = 0
    while n < len(recs) and keep(recs[n], n):
        n += 1
    (folder / "journal.jsonl").write_bytes(b"".join(lines[:n]))
    return records(folder)


def kill_during_acquire(folder: Path, stations_done: int) -> list[str]:
    """Turn a finished job into one killed during ACQUIRE after ``stations_done`` stations (journal cut,
    what the killed session could not have written removed). Returns the ids of the stations kept."""
    seen = {"n": 0}

    def keep(rec, i):
        if rec["event"] == "station_done":
            seen["n"] += 1
            return seen["n"] <= stations_done
        return not (rec["event"] == "station_start" and seen["n"] >= stations_done + 1)

    recs = cut_journal(folder, keep)
    # the session was killed as it started the next station: what it had not yet written goes
    from cell.record.integrity import expected_hashes

    vouched = expected_hashes(recs)
    for p in sorted(folder.rglob("*"), reverse=True):
        rel = str(p.relative_to(folder))
        if p.is_file() and rel not in vouched and p.name != "journal.jsonl" and not rel.startswith("run"):
            p.unlink()
    return [r["station"] for r in recs if r["event"] == "station_done"]


def snapshot(folder: Path) -> dict[str, str]:
    """sha256 of every file under ``folder`` (relative path -> hex)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != ".lock"}


def staged_copy(finished: Path, archive: Path) -> Path:
    """The finished job cut back to just after VALIDATE, in .incoming: stopped (or killed) before the robot moved."""
    folder = copy_job(finished, archive)
    kill_during_acquire(folder, 0)
    cut_journal(folder, lambda r, i: not (r["event"] == "state" and r["to"] == "ACQUIRE"))
    (archive / ".incoming").mkdir()
    staged = archive / ".incoming" / folder.name
    folder.rename(staged)
    return staged
