"""Helpers for the whole-job tests: job-file variants, the ``cell`` command in a subprocess,
reading a job folder, and one uninterrupted run of the example job shared by a test session.

The jobs run as the operator runs them: ``cell run JOB --archive DIR --json`` in a child
process (so a SIGKILL is a real one, and no warning filter of pytest's leaks into the job).
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "bracket"


def start_loopback_controller(subnet: str, **kwargs):
    """A loopback UR controller (``sim_backend.ur_controller``) started on the first free address
    ``<subnet>.10`` .. ``<subnet>.49`` (the ports are fixed: another controller, another test, may hold one)."""
    from sim_backend.ur_controller import LoopbackURController

    for k in range(40):
        try:
            return LoopbackURController(f"{subnet}.{10 + k}", **kwargs).start()
        except OSError:
            continue
    raise RuntimeError(f"no free loopback address in {subnet}.x for a UR controller")


def cell_command() -> list[str]:
    """The ``cell`` console script of this interpreter's environment (or ``python -m cell.cli``)."""
    script = Path(sys.executable).parent / "cell"
    return [str(script)] if script.exists() else [sys.executable, "-m", "cell.cli"]


def child_env() -> dict:
    env = dict(os.environ)
    env.pop("CELL_DEBUG", None)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + " }"
    return repr(v)


def edit_toml(text: str, changes: dict[str, dict]) -> str:
    """Set ``changes[section][key] = value`` in a TOML text, keeping everything else as written.

    A key already in its section has its (single-line) value replaced; a new key is added
    at the top of the section; a value ``None`` deletes the key.
    """
    lines = text.splitlines()
    for section, kv in changes.items():
        head = next((i for i, ln in enumerate(lines) if ln.split("#")[0].strip() == f"[{section}]"), None)
        if head is None:
            lines += ["", f"[{section}]"]
            head = len(lines) - 1
        end = next((i for i in range(head + 1, len(lines)) if lines[i].lstrip().startswith("[")
                    and not lines[i].lstrip().startswith("[[") and "=" not in lines[i].split("#")[0]), len(lines))
        for key, value in kv.items():
            pat = re.compile(rf"^\s*{re.escape(key)}\s*=")
            idx = next((i for i in range(head + 1, end) if pat.match(lines[i])), None)
            if idx is not None and value is None:
                del lines[idx]
                end -= 1
            elif idx is not None:
                lines[idx] = f"{key} = {toml_value(value)}"
            elif value is not None:
                lines.insert(head + 1, f"{key} = {toml_value(value)}")
                end += 1
    out = "\n".join(lines) + "\n"
    tomllib.loads(out)  # the variant must still be valid TOML
    return out


def job_variant(dst: Path, changes: dict[str, dict] | None = None, text: str | None = None) -> Path:
    """Copy the example job (mesh, targets, deviations) to ``dst`` with ``changes`` to its job file."""
    dst.mkdir(parents=True, exist_ok=True)
    for f in EXAMPLE.iterdir():
        if f.suffix in (".stl", ".csv"):
            shutil.copy(f, dst / f.name)
    src = (EXAMPLE / "job.toml").read_text() if text is None else text
    (dst / "job.toml").write_text(edit_toml(src, changes or {}))
    return dst / "job.toml"


@dataclass
class CellRun:
    code: int
    doc: dict | None
    stderr: str
    elapsed_s: float


def run_cell(*args: str, timeout: float = 300.0, env: dict | None = None) -> CellRun:
    """``cell ARGS --json`` in a child process; the JSON document it printed (if any)."""
    import time

    t0 = time.perf_counter()
    p = subprocess.run([*cell_command(), *args, "--json"], capture_output=True, text=True, timeout=timeout,
                       env=env or child_env(), cwd=REPO)
    doc = None
    if p.stdout.strip():
        doc = json.loads(p.stdout)
    return CellRun(p.returncode, doc, p.stderr, time.perf_counter() - t0)


def records(folder: Path) -> list[dict]:
    """The complete records of a job's journal (a torn last line is ignored, as the cell does)."""
    p = Path(folder) / "journal.jsonl"
    if not p.exists():
        return []
    out = []
    with open(p, encoding="utf-8") as f:
        for line in f:
            if not line.endswith("\n"):
                break
            out.append(json.loads(line))
    return out


def archive_entries(archive: Path) -> set[str]:
    """What the archive holds besides its index: job folders and anything else (not .incoming)."""
    if not archive.exists():
        return set()
    return {p.name for p in archive.iterdir() if p.name != ".incoming" and not p.name.startswith("index.sqlite")}


def incoming_entries(archive: Path) -> list[str]:
    inc = archive / ".incoming"
    return sorted(p.name for p in inc.iterdir()) if inc.exists() else []


def truth_xyz_m(job_toml: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The simulated part's truth: ids, CAD nominal (n, 3) m, and CAD + deviations (n, 3) m."""
    spec = tomllib.loads(job_toml.read_text())
    scale = {"m": 1.0, "mm": 1e-3, "cm": 1e-2, "um": 1e-6, "in": 0.0254, "ft": 0.3048}[spec["job"]["units"]]
    folder = job_toml.parent
    ids, xyz = [], []
    with open(folder / spec["job"]["targets"]) as f:
        next(f)
        for line in f:
            row = line.strip().split(",")
            if row and row[0]:
                ids.append(row[0])
                xyz.append([float(v) for v in row[1:4]])
    nominal = np.asarray(xyz) * scale
    truth = nominal.copy()
    dev = spec.get("sim", {}).get("deviations")
    if dev:
        index = {t: i for i, t in enumerate(ids)}
        with open(folder / dev) as f:
            next(f)
            for line in f:
                row = line.strip().split(",")
                if row and row[0]:
                    truth[index[row[0]]] += np.asarray([float(v) for v in row[1:4]]) * scale
    return ids, nominal, truth


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform (Kabsch) taking ``src: (n, 3)`` onto ``dst: (n, 3)``, 4x4."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cd - R @ cs
    return T


def mahalanobis(d: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """sqrt(d_i^T cov_i^-1 d_i) for ``d: (n, 3)``, ``cov: (n, 3, 3)``, (n,)."""
    return np.sqrt(np.einsum("ni,ni->n", d, np.linalg.solve(cov, d[..., None])[..., 0]))


_RUNS: dict[str, tuple[Path, Path, CellRun]] = {}


def example_run(tmp_path_factory) -> tuple[Path, Path, CellRun]:
    """One uninterrupted run of the example job per test session: ``(job.toml, job folder, run)``."""
    if "example" not in _RUNS:  # kept also when it failed: the tests that need it fail at once, not by re-running it
        base = tmp_path_factory.mktemp("example_job")
        job = job_variant(base / "job")
        run = run_cell("run", str(job), "--archive", str(base / "archive"), timeout=400)
        _RUNS["example"] = (job, Path(run.doc["folder"]) if run.doc and "folder" in run.doc else None, run)
    job, folder, run = _RUNS["example"]
    assert run.code == 0, f"the example job did not finish (exit {run.code}):\n{run.stderr[-3000:]}"
    return job, folder, run


class RecordingOutput:
    """Stands in for the CLI's Output in tests: records what a job says, ignores progress."""

    def __init__(self):
        self.lines: list[str] = []

    def say(self, s: str) -> None:
        self.lines.append(s)

    def progress(self, stage: str, fraction: float) -> None:
        pass
