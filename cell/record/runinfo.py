"""Who and what a job is about: part number, revision, serial number, operator, cell id.

Written once when a job is created, as ``run.json`` in its folder (beside the copied
job file and inputs); the report, the run log and the archive index read it from there.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from calibration.errors import InputError
from cell.record.jobfolder import atomic_write_json

RUN_INFO = "run.json"
_MAX = 80


def clean_serial(serial: str | None, what: str = "serial number") -> str | None:
    """A serial number as a scanner types it: trimmed, printable, at most 80 characters (None if empty).

    Raises ``InputError`` naming the problem for anything else.
    """
    if serial is None:
        return None
    s = serial.strip()
    if not s:
        return None
    if len(s) > _MAX:
        raise InputError(f"{what} {s[:20]!r}...: longer than {_MAX} characters")
    bad = [c for c in s if not c.isprintable() or c in "/\\"]
    if bad:
        raise InputError(f"{what} {s!r}: contains {bad[0]!r} (only printable characters, no slashes)")
    return s


def make_run_info(spec, serial: str | None, operator: str | None, cell_id: str | None) -> dict:
    """The run.json document of a new job (``spec``: the validated JobSpec)."""
    return {"part": {"number": spec.job.number, "revision": spec.job.revision, "serial": clean_serial(serial)},
            "operator": clean_serial(operator, "operator"),
            "cell_id": clean_serial(cell_id if cell_id is not None else os.environ.get("CELL_ID"), "cell id")}


def write_run_info(folder: Path, info: dict) -> None:
    atomic_write_json(Path(folder) / RUN_INFO, info)


def read_run_info(folder: Path) -> dict:
    """run.json of a job folder; a job from before it existed: every field null."""
    p = Path(folder) / RUN_INFO
    empty = {"part": {"number": None, "revision": None, "serial": None}, "operator": None, "cell_id": None}
    if not p.exists():
        return empty
    doc = json.loads(p.read_text())
    return empty | doc
