"""Planner speed (issue 21): this tree against a baseline commit, on the same synthetic jobs, and the plans compared.

Each configuration (targets x stations, built as in ``benchmarks.bench_scale``: the example's camera, cell and
robot, targets sampled on the bracket) is planned by ``bench_scale --one N K --no-adjust`` in this tree and in
the baseline tree (``git archive`` of ``--baseline``, default the commit before the planner kernels), one after
the other, ``--repeat`` times, alternating, so both see the same load. (Not in one process: both trees are
the package ``planning``.) Printed per configuration: the phases' best times of each, the ratio
baseline / now, the planned worst sigma of each and whether the plans are identical, peak memory, and the
load average before and after (the machine is shared; ratios from alternated runs hold better than the
absolute seconds).

    .venv/bin/python -m benchmarks.bench_planspeed                        # 1k x 29, 5k x 64
    .venv/bin/python -m benchmarks.bench_planspeed --configs 20000x128 --repeat 1
    .venv/bin/python -m benchmarks.bench_planspeed --configs 1000x29 --no-baseline --repeat 3
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BASELINE = "e52f1ee"  # main before the planner kernels (branch planspeed)
PHASES = ("visibility_s", "reach_s", "information_s", "search_s", "polish_s", "final_s", "plan_s")


def export_tree(rev: str, dest: Path) -> Path:
    """The files of ``rev`` under ``dest`` (git archive); exits 2 with one line when ``rev`` is unknown."""
    p = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", rev], capture_output=True)
    if p.returncode != 0:
        print(f"bench_planspeed: cannot export baseline {rev!r}: {p.stderr.decode().strip()}", file=sys.stderr)
        raise SystemExit(2)
    tar = dest / "tree.tar"
    tar.write_bytes(p.stdout)
    with tarfile.open(tar) as t:
        t.extractall(dest / "tree", filter="data")
    return dest / "tree"


def run_one(tree: Path, n: int, k: int, seed: int, timeout: float) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(tree))
    cmd = [sys.executable, "-m", "benchmarks.bench_scale", "--one", str(n), str(k), "--no-adjust", "--seed", str(seed)]
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"not done in {timeout:.0f} s"}
    if p.returncode != 0:
        return {"error": (p.stderr.strip().splitlines() or ["exit %d" % p.returncode])[-1][:300]}
    r = json.loads(p.stdout.strip().splitlines()[-1])
    r["wall_s"] = time.perf_counter() - t0
    return r


def best(rows: list[dict]) -> dict:
    ok = [r for r in rows if "error" not in r]
    if not ok:
        return rows[-1] if rows else {"error": "not run"}
    out = dict(ok[0])
    for ph in PHASES + ("wall_s", "peak_gb"):
        vals = [r[ph] for r in ok if r.get(ph) is not None]
        out[ph] = min(vals) if vals else None
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="+", default=["1000x29", "5000x64"], help="TARGETSxSTATIONS")
    ap.add_argument("--baseline", default=BASELINE, help="commit to compare with")
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=3600.0)
    ap.add_argument("--warm", action="store_true", default=True,
                    help="one unmeasured run of this tree first (compiles and caches the kernels)")
    a = ap.parse_args(argv)
    try:
        configs = [tuple(int(x) for x in c.lower().split("x")) for c in a.configs]
    except ValueError:
        print(f"bench_planspeed: --configs takes TARGETSxSTATIONS, got {a.configs}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        base = None if a.no_baseline else export_tree(a.baseline, Path(tmp))
        if a.warm:
            run_one(ROOT, 200, 8, a.seed, a.timeout)
        for n, k in configs:
            load0 = os.getloadavg()
            now, old = [], []
            for _ in range(a.repeat):
                now.append(run_one(ROOT, n, k, a.seed, a.timeout))
                if base is not None:
                    old.append(run_one(base, n, k, a.seed, a.timeout))
            load1 = os.getloadavg()
            b_now, b_old = best(now), best(old) if base is not None else None
            print(f"\n{n} targets x {k} stations (best of {a.repeat}; load average {load0[0]:.1f} before, "
                  f"{load1[0]:.1f} after)")
            if "error" in b_now:
                print(f"  this tree: {b_now['error']}")
                continue
            print(f"  {'phase':14s} {'now':>9s}" + (f" {'baseline':>9s} {'ratio':>7s}" if b_old else ""))
            for ph in PHASES + ("wall_s", "peak_gb"):
                v = b_now.get(ph)
                line = f"  {ph:14s} {'-' if v is None else format(v, '9.2f'):>9s}"
                if b_old and "error" not in b_old:
                    w = b_old.get(ph)
                    line += f" {'-' if w is None else format(w, '9.2f'):>9s}"
                    if v and w:
                        line += f" {w / v:6.2f}x"
                print(line)
            print(f"  worst sigma: now {b_now['worst_um']:.6f} um" + (
                f", baseline {b_old['worst_um']:.6f} um ({'identical' if b_old['worst_um'] == b_now['worst_um'] else 'differs'})"
                if b_old and "error" not in b_old else (f", baseline: {b_old['error']}" if b_old else "")))
            print(f"  polish: {b_now.get('polish')}")
            print("  per run (now): " + ", ".join(f"{r.get('plan_s', float('nan')):.2f} s" for r in now)
                  + ("; baseline: " + ", ".join(f"{r.get('plan_s', float('nan')):.2f} s" for r in old) if old else ""),
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
