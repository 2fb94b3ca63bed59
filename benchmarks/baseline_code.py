"""Code as it was at an earlier commit, for benchmarks that compare with the code before a change.

- ``load_at("calibration/dots.py", "e52f1ee")`` runs ``git show e52f1ee:calibration/dots.py`` and imports the text
  as a fresh module. Only that file is old: its own imports resolve to today's packages.
- ``load_package_at("planning", "e52f1ee")`` imports the whole package as it was, under the name
  ``_baseline_e52f1ee_planning``: its modules' imports of each other (``from planning.x import ...``) are rewritten
  to the old package, so old modules use old modules; imports of other packages (``calibration``, ...) are today's.
- ``export_tree(rev, dest)``: every file of ``rev`` under ``dest`` (``git archive``), for a baseline run in a process
  of its own; ``default_baseline()``: the commit a change is compared with when none is given.

Files go into one temporary folder per process, removed when the process exits.
"""
from __future__ import annotations

import atexit
import importlib
import importlib.util
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]
_TMP: Path | None = None


def _tmp() -> Path:
    global _TMP
    if _TMP is None:
        _TMP = Path(tempfile.mkdtemp(prefix="cell-baseline-"))
        atexit.register(shutil.rmtree, _TMP, ignore_errors=True)
    return _TMP


def _git(*args: str, what: str) -> bytes:
    try:
        return subprocess.run(["git", "-C", str(ROOT), *args], check=True, capture_output=True).stdout
    except (OSError, subprocess.CalledProcessError) as e:
        err = (getattr(e, "stderr", b"") or b"").decode(errors="replace").strip() or str(e)
        sys.exit(f"baseline: cannot read {what}: {err.splitlines()[-1]}")


def load_at(path: str, rev: str) -> ModuleType:
    """The module at ``path`` (relative to the repository) as of git revision ``rev``.

    Exits with one line (status 2) when git cannot give it (no such revision or file, no git checkout).
    """
    text = _git("show", f"{rev}:{path}", what=f"{path} at {rev}").decode()
    name = f"_baseline_{rev}_{path.replace('/', '_').removesuffix('.py')}"
    tmp = _tmp() / f"{name}.py"
    tmp.write_text(text)
    spec = importlib.util.spec_from_file_location(name, tmp)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def load_package_at(package: str, rev: str) -> ModuleType:
    """The package ``package`` (a top-level folder of the repository) as of ``rev``, self-contained.

    Returns the package module ``_baseline_<rev>_<package>``; its modules are imported with
    ``importlib.import_module(f"{pkg.__name__}.visibility")`` or ``submodule(pkg, "visibility")``.
    """
    alias = f"_baseline_{re.sub(r'[^0-9A-Za-z_]', '_', rev)}_{package}"
    if alias in sys.modules:
        return sys.modules[alias]
    root = _tmp() / alias
    export_tree(rev, root, package)
    src = root / "tree" / package
    if not (src / "__init__.py").exists():
        sys.exit(f"baseline: {package} is not a package at {rev}")
    pat = re.compile(rf"(^|\n)(\s*)(from|import) {re.escape(package)}(?=[.\s])")
    for f in src.rglob("*.py"):
        f.write_text(pat.sub(rf"\1\2\3 {alias}", f.read_text()))
    dst = _tmp() / "packages"
    dst.mkdir(exist_ok=True)
    shutil.move(str(src), str(dst / alias))
    if str(dst) not in sys.path:
        sys.path.append(str(dst))
    return importlib.import_module(alias)


def submodule(pkg: ModuleType, name: str) -> ModuleType:
    """``pkg.name`` imported (a package from :func:`load_package_at`)."""
    return importlib.import_module(f"{pkg.__name__}.{name}")


def export_tree(rev: str, dest: Path, *paths: str) -> Path:
    """The files of ``rev`` (only ``paths`` if given) under ``dest / "tree"``; exits 2 when ``rev`` is unknown."""
    data = _git("archive", "--format=tar", rev, *paths, what=f"the tree of {rev}")
    dest.mkdir(parents=True, exist_ok=True)
    tar = dest / "tree.tar"
    tar.write_bytes(data)
    with tarfile.open(tar) as t:
        t.extractall(dest / "tree", filter="data")
    tar.unlink()
    return dest / "tree"


def default_baseline() -> str:
    """The code before the latest change, as a short hash.

    On a branch with commits not on ``main``: where it meets ``main`` (``git merge-base HEAD main``: main without
    the branch's work, also after main was merged into the branch). On ``main``: HEAD's first parent when HEAD is
    a merge (the code before the branch just merged), else the latest merge on HEAD's first-parent line.
    """
    on_main = subprocess.run(["git", "-C", str(ROOT), "merge-base", "--is-ancestor", "HEAD", "main"],
                             capture_output=True).returncode == 0
    if not on_main and subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", "-q", "main"],
                                      capture_output=True).returncode == 0:
        rev = _git("merge-base", "HEAD", "main", what="where HEAD meets main").decode().strip()
    else:
        parents = _git("rev-list", "--parents", "-n", "1", "HEAD", what="HEAD").decode().split()
        if len(parents) > 2:
            rev = parents[1]
        else:
            rev = _git("rev-list", "--first-parent", "--merges", "-n", "1", "HEAD", what="the last merge").decode()
            if not rev.strip():
                sys.exit("baseline: no merge commit in HEAD's history; give a baseline commit")
    return _git("rev-parse", "--short", rev.strip(), what=rev).decode().strip()
