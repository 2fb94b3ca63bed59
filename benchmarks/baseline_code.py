"""Load a module as it was at an earlier commit, for benchmarks that compare with the code before a change.

``load_at("calibration/dots.py", "e52f1ee")`` runs ``git show e52f1ee:calibration/dots.py`` and imports the text
as a fresh module (its own imports resolve to today's packages), so a benchmark can time and score the old
functions beside today's in one process, on the same images.
"""
from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def load_at(path: str, rev: str) -> ModuleType:
    """The module at ``path`` (relative to the repository) as of git revision ``rev``.

    Exits with one line (status 2) when git cannot give it (no such revision or file, no git checkout).
    """
    try:
        text = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, check=True, capture_output=True,
                              text=True).stdout
    except (OSError, subprocess.CalledProcessError) as e:
        err = getattr(e, "stderr", "") or str(e)
        sys.exit(f"baseline: cannot read {path} at {rev}: {err.strip().splitlines()[-1] if err.strip() else e}")
    name = f"_baseline_{rev}_{path.replace('/', '_').removesuffix('.py')}"
    tmp = Path(tempfile.mkdtemp(prefix="cell-baseline-")) / f"{name}.py"
    tmp.write_text(text)
    spec = importlib.util.spec_from_file_location(name, tmp)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod
