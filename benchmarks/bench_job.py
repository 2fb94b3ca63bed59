"""The example job end to end, per stage, today and with the render and detection before issue 21.

    .venv/bin/python -m benchmarks.bench_job [--repeat 3] [--before REV] [--cli 0]

Runs ``examples/bracket`` (16 stations, 5 MP images, simulated cell, instant robot motion) in this process
with ``cell.job.start_job`` into a temporary archive, after one warm-up run (the planning databases are
cached, as in a cell that has run the part before). Two variants, interleaved so that both see the same
machine load:

* today: this checkout;
* before: the same, with the simulated camera's rendering (``SimCamera`` methods, ``World.first_hit``) and the
  dot detector (``calibration/dots.py``) as they were at git revision ``--before`` (loaded by ``git show``):
  the rest of the job is today's, so the difference is what issue 21's render and detection work bought.

Printed: each stage's time (the job's own ``stage_times_s``), the whole job, and per image the render, the
detection and MEASURE's whole per-image work (detect, ArUco markers, naming); best and median over
``--repeat`` with the load average. ``--cli N`` also times N runs of ``cell run`` as a new process (interpreter
start, imports and exit included: what an operator waits for).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cell.stages.imaging as imaging  # noqa: E402
import cell.stages.measure as measure  # noqa: E402
from benchmarks.baseline_code import load_at  # noqa: E402
from cell.job import start_job  # noqa: E402
from sim_backend.sim_camera import SimCamera  # noqa: E402
from sim_backend.world import World  # noqa: E402

#: main before issue 21's render and detection work (the render branch started here)
BEFORE_REV = "e52f1ee"
STAGES = ("LOAD", "PLAN", "VALIDATE", "ACQUIRE", "MEASURE", "CALIBRATE", "ADJUST", "CLOSE_LOOP", "REPORT")
_CAMERA_METHODS = ("render", "_render_background", "_select", "_extent", "_windows", "_draw_targets",
                   "_visibility_mask", "_compose")


class _Quiet:
    def say(self, s: str) -> None:
        pass

    def progress(self, stage: str, fraction: float) -> None:
        pass


class _Timed:
    """Replaces ``owner.name`` by a wrapper that records each call's wall time (s) in ``self.times``."""

    def __init__(self, owner, name: str) -> None:
        self.owner, self.name, self.orig, self.times = owner, name, getattr(owner, name), []
        fn = self.orig

        def wrapper(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                self.times.append(time.perf_counter() - t0)

        setattr(owner, name, wrapper)

    def restore(self) -> None:
        setattr(self.owner, self.name, self.orig)


def _patch_before(rev: str) -> list[tuple[object, str, object]]:
    """Swap in the render and detection of ``rev``; returns what to put back."""
    old_cam = load_at("sim_backend/sim_camera.py", rev)
    old_world = load_at("sim_backend/world.py", rev)
    old_dots = load_at("calibration/dots.py", rev)
    swaps = [(SimCamera, n, old_cam.SimCamera.__dict__[n]) for n in _CAMERA_METHODS]  # staticmethods stay static
    swaps += [(World, "first_hit", old_world.World.__dict__["first_hit"]), (imaging, "detect_dots", old_dots.detect_dots)]
    undo = [(o, n, o.__dict__[n]) for o, n, _ in swaps]
    for o, n, f in swaps:
        setattr(o, n, f)
    return undo


def run_once(job: Path, archive: Path) -> dict:
    timers = [_Timed(SimCamera, "render"), _Timed(imaging, "detect_dots"), _Timed(measure, "measure_image")]
    try:
        t0 = time.perf_counter()
        res = start_job(job, archive, None, _Quiet())
        wall = time.perf_counter() - t0
    finally:
        for t in reversed(timers):
            t.restore()
    if res.status.value != "DONE":
        sys.exit(f"bench_job: the example job ended {res.status.value}, not DONE: {res.reason}")
    st = {}  # the journal's stage_done durations (report.json's stage_times_s is written before REPORT ends)
    for line in (res.folder / "journal.jsonl").read_text().splitlines():
        rec = json.loads(line)
        if rec.get("event") == "stage_done":
            st[rec["stage"]] = st.get(rec["stage"], 0.0) + float(rec.get("duration_s", 0.0))
    shutil.rmtree(res.folder, ignore_errors=True)
    return {"wall": wall, "stages": st, "render": timers[0].times, "detect": timers[1].times,
            "measure_image": timers[2].times}


def _bm(values: list[float], scale: float = 1.0, unit: str = "s", width: int = 6, digits: int = 2) -> str:
    import numpy as np

    v = np.asarray(values, dtype=float) * scale
    return f"{v.min():{width}.{digits}f} / {np.median(v):{width}.{digits}f} {unit}"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--before", default=BEFORE_REV, help="git revision of the render and detection to compare with")
    ap.add_argument("--cli", type=int, default=0, metavar="N", help="also time N runs of `cell run` as a new process")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_job_"))
    try:
        shutil.copytree(ROOT / "examples" / "bracket", tmp / "job")
        job = tmp / "job" / "job.toml"
        run_once(job, tmp / "archive")  # warm-up: planning caches, imports, Embree scenes
        load0 = os.getloadavg()[0]
        runs: dict[str, list[dict]] = {"today": [], "before": []}
        for _ in range(a.repeat):
            runs["today"].append(run_once(job, tmp / "archive"))
            undo = _patch_before(a.before)
            try:
                runs["before"].append(run_once(job, tmp / "archive"))
            finally:
                for o, n, f in undo:
                    setattr(o, n, f)
        load1 = os.getloadavg()[0]
        print(f"example job (examples/bracket: 16 stations, 2448 x 2048 images), in-process, warm caches; "
              f"{a.repeat} run(s) of each variant, interleaved; load average {load0:.1f} -> {load1:.1f} on "
              f"{os.cpu_count()} cores; figures are best / median")
        print(f"{'stage':12s} {'today':>20s} {'before issue 21 (' + a.before + ')':>30s}")
        for s in STAGES:
            t = [r["stages"].get(s, 0.0) for r in runs["today"]]
            b = [r["stages"].get(s, 0.0) for r in runs["before"]]
            print(f"{s:12s} {_bm(t):>20s} {_bm(b):>30s}")
        t_out = [r["wall"] - sum(r["stages"].values()) for r in runs["today"]]
        b_out = [r["wall"] - sum(r["stages"].values()) for r in runs["before"]]
        print(f"{'(between)':12s} {_bm(t_out):>20s} {_bm(b_out):>30s}   job folder, archive index, run log, outside the stages")
        t_wall = [r["wall"] for r in runs["today"]]
        b_wall = [r["wall"] for r in runs["before"]]
        print(f"{'whole job':12s} {_bm(t_wall):>20s} {_bm(b_wall):>30s}   ratio before / today "
              f"{min(b_wall) / min(t_wall):.2f}x (best)")
        for key, label in (("render", "render"), ("detect", "detect dots"), ("measure_image", "MEASURE/img")):
            t = [x for r in runs["today"] for x in r[key]]
            b = [x for r in runs["before"] for x in r[key]]
            print(f"{label:12s} {_bm(t, 1e3, 'ms', 6, 1):>20s} {_bm(b, 1e3, 'ms', 6, 1):>30s}   per image "
                  f"(ratio {min(b) / min(t):.2f}x best)")
        cli = []
        for _ in range(a.cli):
            arch = tmp / "cli_archive"
            t0 = time.perf_counter()
            p = subprocess.run([str(Path(sys.executable).parent / "cell"), "run", str(job), "--archive", str(arch), "--yes"],
                               cwd=ROOT, capture_output=True, text=True)
            cli.append(time.perf_counter() - t0)
            if p.returncode not in (0, 1):  # 1: the example's verdict is FAIL by design
                sys.exit(f"bench_job: cell run exited {p.returncode}: {p.stderr.strip().splitlines()[-1:]}")
            shutil.rmtree(arch, ignore_errors=True)
        if cli:
            print(f"`cell run` as a new process (today): {_bm(cli)} over {len(cli)} run(s), load average "
                  f"{os.getloadavg()[0]:.1f}")
        print("BENCHMARK " + json.dumps({
            "what": "example job end to end in-process (16 stations, 5 MP, warm caches)",
            "figure": f"{min(t_wall):.2f} s best (load {load0:.1f}); render {min(x for r in runs['today'] for x in r['render']) * 1e3:.0f} ms, "
                      f"detection {min(x for r in runs['today'] for x in r['detect']) * 1e3:.0f} ms per image (best)",
            "baseline": f"render and detection before issue 21 ({a.before}): {min(b_wall):.2f} s",
            "ratio": f"{min(b_wall) / min(t_wall):.2f}x faster; target 8 s"}))
        return 0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    raise SystemExit(main())
