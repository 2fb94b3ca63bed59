"""Time of one small UR move through the driver (ur-rtde client in its child process) against the loopback
controller: this tree and a baseline commit, alternately, in fresh processes (both trees are the package
``drivers``, so not in one process). Decision 0028 added a safety-limit check before each move; this shows
what it costs.

    .venv/bin/python -m benchmarks.bench_ur_moves                  # baseline: baseline_code.default_baseline()
    .venv/bin/python -m benchmarks.bench_ur_moves --moves 40 --repeat 3 --baseline HEAD~3

Each run starts a loopback controller (time_scale 8, 8 ms ticks), connects, and times ``--moves`` joint moves of
0.01 rad back and forth; printed: median and best per move of each tree (best over ``--repeat`` runs), the ratio,
the load average.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
import numpy as np
from drivers.ur import URRobot
from sim_backend.ur_controller import LoopbackURController
for last in range(2, 250):
    try:
        c = LoopbackURController(f"127.0.6.{last}", time_scale=8.0).start()
        break
    except OSError:
        continue
with URRobot(c.host) as r:
    q = r.state().joints_rad
    r.move_joints(q + 0.01, 1.0, 2.0)
    t = []
    for k in range(int(sys.argv[1])):
        t0 = time.perf_counter()
        r.move_joints(q + 0.01 * (k % 2), 1.0, 2.0)
        t.append(time.perf_counter() - t0)
c.close()
print(json.dumps({"median_ms": 1e3 * float(np.median(t)), "best_ms": 1e3 * min(t)}))
"""


def run(tree: Path, moves: int) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(tree))
    p = subprocess.run([sys.executable, "-c", CHILD, str(moves)], cwd=tree, env=env, capture_output=True, text=True,
                       timeout=300)
    if p.returncode != 0:
        raise SystemExit(f"bench_ur_moves: run in {tree} failed: {(p.stderr.strip().splitlines() or ['?'])[-1]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", default=None, help="commit to compare with (default: where HEAD meets main, "
                    "or the code before the last merge)")
    ap.add_argument("--moves", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=2)
    a = ap.parse_args(argv)
    from benchmarks.baseline_code import default_baseline, export_tree

    a.baseline = a.baseline or default_baseline()
    with tempfile.TemporaryDirectory(prefix="bench_ur_moves_") as tmp:
        tree = export_tree(a.baseline, Path(tmp))
        rows = {"now": [], "baseline": []}
        load0 = os.getloadavg()[0]
        for _ in range(a.repeat):
            rows["now"].append(run(ROOT, a.moves))
            rows["baseline"].append(run(tree, a.moves))
        load1 = os.getloadavg()[0]
    best = {k: (min(r["median_ms"] for r in v), min(r["best_ms"] for r in v)) for k, v in rows.items()}
    print(f"{a.moves} moves of 0.01 rad, best of {a.repeat} runs (load average {load0:.1f} before, {load1:.1f} after)")
    for k, (med, b) in best.items():
        print(f"  {k:9s} median {med:6.1f} ms  best {b:6.1f} ms per move")
    print(f"  ratio now / baseline ({a.baseline}): median {best['now'][0] / best['baseline'][0]:.2f}x, "
          f"best {best['now'][1] / best['baseline'][1]:.2f}x")
    print("BENCHMARK " + json.dumps({"what": "UR driver: one 0.01 rad joint move on the loopback controller (median)",
                                     "figure": f"{best['now'][0]:.1f} ms",
                                     "baseline": f"{a.baseline}: {best['baseline'][0]:.1f} ms",
                                     "ratio": round(best["now"][0] / best["baseline"][0], 2)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
