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


def run_info_from_journal(recs: list[dict]) -> dict | None:
    """The run.json document a job's ``created`` record holds (it journals the same fields when the job starts);
    None for a job from before run.json existed."""
    created = next((r for r in recs if r.get("event") == "created"), None)
    if created is None or not isinstance(created.get("part"), dict):
        return None
    return {"part": created["part"], "operator": created.get("operator"), "cell_id": created.get("cell_id")}


def run_info_problem(folder: Path, info: dict, changed: str | None = None) -> str | None:
    """What is wrong with the folder's run.json against ``info`` (:func:`run_info_from_journal`), or None.

    ``changed``: why the journal's check of the stored files failed it, if it did (a copy whose fields agree but
    whose bytes differ from the ones the journal vouches for is still not the file that was written)."""
    p = Path(folder) / RUN_INFO
    if not p.is_file():
        return "missing"
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        return f"cannot be read ({type(exc).__name__})"
    if doc != info:
        if not isinstance(doc, dict):
            return "not a run.json document"
        flat = _flat(info)
        other = _flat(doc)
        diff = [f"{k} {other.get(k)!r} (journal {flat.get(k)!r})" for k in sorted(set(flat) | set(other))
                if flat.get(k) != other.get(k)]
        return "disagrees with the journal's created record: " + ", ".join(diff[:4]) + (" ..." if len(diff) > 4 else "")
    return changed


def describe(info: dict) -> str:
    """``part P rev R, serial S, operator O`` for one line."""
    part = info.get("part") or {}
    return (f"part {part.get('number')} rev {part.get('revision')}, serial {part.get('serial')}, "
            f"operator {info.get('operator')}")


def _flat(doc: dict) -> dict:
    out = {}
    for k, v in doc.items():
        if isinstance(v, dict):
            out |= {f"{k}.{k2}": v2 for k2, v2 in v.items()}
        else:
            out[k] = v
    return out
