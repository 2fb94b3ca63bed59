"""The example job end to end (issue 21: <= 8 s warm), per stage, against a baseline checkout run alternately.

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_job_e2e --repeat 3                    # baseline: the last merge (below)
    .venv/bin/python -m benchmarks.bench_job_e2e --repeat 3 --baseline 9a190b3
    .venv/bin/python -m benchmarks.bench_job_e2e --repeat 3 --baseline-src /tmp/cell_main   # a checkout of your own
    .venv/bin/python -m benchmarks.bench_job_e2e --repeat 3 --no-baseline

The default baseline is ``benchmarks.baseline_code.default_baseline()``: HEAD's first parent when HEAD is a merge
(main right after merging a branch: the code before that branch), else the latest merge on HEAD's first-parent
line; it is exported with ``git archive`` into a temporary folder (removed at the end) and named in the output.

Each run is ``cell run JOB --yes`` in a fresh process (imports included, as an operator meets it) into a
temporary archive; the planning caches are warmed by one untimed run first. The baseline runs the same command
with ``<baseline-src>`` first on ``sys.path`` (same interpreter and packages; checked), alternating with ours so both see the same
load. Prints wall time, the process's CPU time (user + system: less at the mercy of other work on a shared
machine than wall time) and each stage's duration (from the job's journal): best and median, the load average,
and the ratio ours / baseline.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

STAGES = ("LOAD", "PLAN", "VALIDATE", "ACQUIRE", "MEASURE", "CALIBRATE", "ADJUST", "CLOSE_LOOP", "REPORT")


def _run(job: str, src: Path | None, archive: Path) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    if src is not None:
        env["BENCH_JOB_SRC"] = str(src)
    # the console script's own entry point where the version has one (cell.cli.entry), else main
    # (the baseline's directory goes first on sys.path: '' (the working directory, this checkout) would win)
    code = ("import os, sys; src = os.environ.get('BENCH_JOB_SRC'); src and sys.path.insert(0, src); "
            "import cell.cli as c; assert not src or c.__file__.startswith(src), c.__file__; "
            "sys.argv = ['cell'] + sys.argv[1:]; f = getattr(c, 'entry', None); sys.exit(f() if f else c.main())")
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code, "run", job, "--yes", "--archive", str(archive)],
                         env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    if out.returncode not in (0, 1):  # 1: the job ran and its verdict is FAIL (the example's deviations)
        raise SystemExit(f"cell run failed ({out.returncode}): {out.stderr.strip().splitlines()[-1:]}")
    folder = max((p for p in archive.iterdir() if p.is_dir() and (p / "journal.jsonl").exists()),
                 key=lambda p: p.stat().st_mtime)
    stages = {}
    for line in (folder / "journal.jsonl").read_text().splitlines():
        rec = json.loads(line)
        if rec.get("event") == "stage_done":
            stages[rec["stage"]] = float(rec["duration_s"])
    return {"wall": wall, "cpu": cpu, **stages}


def _summary(runs: list[dict], key: str) -> tuple[float, float]:
    v = [r[key] for r in runs if key in r]
    return (min(v), float(np.median(v))) if v else (float("nan"), float("nan"))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--job", default="examples/bracket/job.toml")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--baseline", default=None, help="commit to compare with (default: the last merge, see above)")
    ap.add_argument("--baseline-src", type=Path, default=None,
                    help="a directory holding another version of the packages (instead of --baseline)")
    ap.add_argument("--no-baseline", action="store_true")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_job_") as tmp:
        src, label = None, None
        if a.baseline_src:
            src, label = a.baseline_src.resolve(), str(a.baseline_src)
        elif not a.no_baseline:
            from benchmarks.baseline_code import default_baseline, export_tree

            label = a.baseline or default_baseline()
            src = export_tree(label, Path(tmp) / "baseline_src")
        variants = {"ours": None} | ({"baseline": src} if src else {})
        if label:
            print(f"baseline: {label}", flush=True)
        _bench(a, variants, Path(tmp), label)


def _bench(a, variants: dict, tmp: Path, label: str | None) -> None:
    runs: dict[str, list[dict]] = {k: [] for k in variants}
    loads = []
    for name, src in variants.items():  # warm the planning caches (and the OS file cache) for each version
        _run(a.job, src, tmp / name)
    for _ in range(a.repeat):
        for name, src in variants.items():
            loads.append(os.getloadavg()[0])
            runs[name].append(_run(a.job, src, tmp / name))
    print(f"{a.job}: {a.repeat} runs each, load average {min(loads):.2f}..{max(loads):.2f}")
    head = f"{'':10s}" + "".join(f"{n + ' best':>17s}{n + ' median':>17s}" for n in variants)
    print(head + ("   ratio ours / baseline (best, median)" if len(variants) == 2 else ""))
    for key in ("wall", "cpu") + STAGES:
        row = f"{key:10s}"
        vals = {}
        for n in variants:
            vals[n] = _summary(runs[n], key)
            row += f"{vals[n][0]:17.2f}{vals[n][1]:17.2f}"
        if len(variants) == 2 and vals["baseline"][0] > 0:
            row += f"   {vals['ours'][0] / vals['baseline'][0]:.2f}, {vals['ours'][1] / vals['baseline'][1]:.2f}"
        print(row)
    if len(variants) == 2:
        ours, base = _summary(runs["ours"], "wall")[0], _summary(runs["baseline"], "wall")[0]
        print("BENCHMARK " + json.dumps({"what": f"cell run {a.job}, wall (best)", "figure": f"{ours:.2f} s",
                                         "baseline": f"{label}: {base:.2f} s", "ratio": round(ours / base, 2)}))
    other = {n: [r["wall"] - sum(r.get(s, 0.0) for s in STAGES) for r in runs[n]] for n in variants}
    print("outside the stages (start-up, imports, closing): " + ", ".join(
        f"{n} best {min(v):.2f} s median {np.median(v):.2f} s" for n, v in other.items()))


if __name__ == "__main__":
    main()
