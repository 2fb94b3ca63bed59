"""Advice that works: every job key an error message tells the operator to change exists in the job schema.

The messages of every ``raise`` in the packages are walked (their string parts, f-strings included). A
key is named as advice when it follows a verb of advice (raise, lower, set, ...) or is written as
``[section] key`` / ``section.key``; each such name must be a key of that section of
:class:`cell.jobspec.JobSpec` (or of some section when none is written).
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

from pydantic import BaseModel

from cell.jobspec import JobSpec

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("calibration", "planning", "cell", "sim_backend", "drivers")
SECTIONS = {name: f.annotation for name, f in JobSpec.model_fields.items()}
VERB = r"(?:raise|lower|set|increase|decrease|widen|narrow|relax|reduce|enlarge|shorten|lengthen|use|give|add)"
ADVICE = re.compile(rf"\b{VERB}\s+(?:the\s+)?(\[\w+\]\s+|\w+\.)?([a-z][a-z0-9]*_[a-z0-9_]+)\b")
QUALIFIED = re.compile(r"\[(\w+)\]\s+([a-z][a-z0-9]*_[a-z0-9_]+)\b")  # "[planning] min_rays"; a bare "job.x" may be
# report.json's (job.finished), so the dotted form counts only after a verb of advice (ADVICE)
#: messages about another file's schema (the cell file CELL.toml has its own [cell] and [sim]; `cell measure`'s
#: camera file has fx_px etc.)
OTHER_SCHEMA = ("cell/cellcal/cellfile.py", "cell/measure_cmd.py", "cell/camerafile.py")
FILES = {"json", "csv", "toml", "html", "png", "mcap", "npz", "stl", "pdf"}


def _keys(section: str) -> set[str]:
    model = SECTIONS.get(section)
    return set(model.model_fields) if isinstance(model, type) and issubclass(model, BaseModel) else set()


ALL_KEYS = set().union(*(_keys(s) for s in SECTIONS))


def _messages():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            tree = ast.parse(path.read_text())
            for node in ast.walk(tree):
                if isinstance(node, ast.Raise) and node.exc is not None:
                    parts = [c.value for c in ast.walk(node.exc) if isinstance(c, ast.Constant) and isinstance(c.value, str)]
                    if parts and str(path.relative_to(ROOT)) not in OTHER_SCHEMA:
                        yield f"{path.relative_to(ROOT)}:{node.lineno}", " ".join(parts)


def _bad_names(text: str) -> list[str]:
    bad = []
    for m in QUALIFIED.finditer(text):
        section, key = m.group(1), m.group(2)
        if section in SECTIONS and key not in _keys(section) and key not in FILES:
            bad.append(f"{section}.{key}")
    for m in ADVICE.finditer(text):
        prefix, key = m.group(1), m.group(2)
        if prefix and prefix.startswith("["):
            continue  # checked above with its section
        section = prefix[:-1] if prefix else None
        if section in SECTIONS:
            if key not in _keys(section):
                bad.append(f"{section}.{key}")
        elif key not in ALL_KEYS:
            bad.append(key)
    return bad


def test_the_checker_catches_the_names_the_issue_found():
    assert _bad_names("raise incidence_max_rad, or set allow_unmeasurable") == ["incidence_max_rad", "allow_unmeasurable"]
    assert _bad_names("raise [planning] incidence_max_deg or lower [planning] min_rays") == []
    assert _bad_names("move the part (cell.base_from_part) or raise [planning] n_station") == ["planning.n_station"]
    assert _bad_names("set planning.incidence_max_rad") == ["planning.incidence_max_rad"]
    assert _bad_names("report.json: job.finished is not a time") == []


def test_every_key_an_error_message_advises_exists_in_the_job_schema():
    found = [(where, _bad_names(text)) for where, text in _messages()]
    bad = [f"{where}: {names}" for where, names in found if names]
    assert len(found) > 100  # the walk sees the packages' messages
    assert not bad, "messages advise keys the job file does not have:\n" + "\n".join(bad)
