"""Planner speed (issue 21): this tree against a baseline commit, on the same synthetic jobs, and the plans compared.

Each configuration (targets x stations, built as in ``benchmarks.bench_scale``: the example's camera, cell and
robot, targets sampled on the bracket) is planned by ``bench_scale --one N K --no-adjust`` in this tree and in
the baseline tree (``git archive`` of ``--baseline``, default the commit before the planner kernels), one after
the other, ``--repeat`` times, alternating, so both see the same load (today's ``bench_scale.py`` in both trees,
so the jobs are built the same way). (Not in one process: both trees are the package ``planning``.) Printed per configuration: the phases' best times of each, the ratio
baseline / now, the planned worst sigma of each and whether the plans' stations are identical (a digest of their
genes), peak memory, and the
load average before and after (the machine is shared; ratios from alternated runs hold better than the
absolute seconds).

    .venv/bin/python -m benchmarks.bench_planspeed                        # 1k x 29, 5k x 64
    .venv/bin/python -m benchmarks.bench_planspeed --configs 20000x128 --repeat 1
    .venv/bin/python -m benchmarks.bench_planspeed --configs 1000x29 --no-baseline --repeat 3
    .venv/bin/python -m benchmarks.bench_planspeed --kernels 5000x64     # the parts, old and new in one process

``--kernels NxK`` times the planner's parts in this process, today's modules beside the baseline's
(``benchmarks.baseline_code.load_package_at``: the whole ``planning`` package as it was at ``--baseline``, its
modules importing each other, so the old polish runs the old refine, visibility, information and sparse
storage; ``calibration`` and the job builder are today's, and the same job, candidates, greedy starts and
information array go to both) on the same job: the visibility database, its information, the exchange descent
from greedy starts, and the polish of a greedy network of K stations; the ratio old / new and whether the answers
are the same. ``--no-warm`` skips the unmeasured first run of this tree (the kernels then compile in the first
measured run).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BASELINE = "e52f1ee"  # main before the planner kernels (branch planspeed)
PHASES = ("visibility_s", "reach_s", "information_s", "search_s", "polish_s", "final_s", "plan_s")


def export_tree(rev: str, dest: Path) -> Path:
    """The files of ``rev`` under ``dest`` (git archive); exits 2 with one line when ``rev`` is unknown."""
    from benchmarks.baseline_code import export_tree as export

    tree = export(rev, dest)
    # the same job builder and report for both trees (today's bench_scale: it also prints the plan's digest)
    (tree / "benchmarks" / "bench_scale.py").write_text((ROOT / "benchmarks" / "bench_scale.py").read_text())
    return tree


def run_one(tree: Path, n: int, k: int, seed: int, timeout: float, search_weights: str | None = None) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(tree))
    cmd = [sys.executable, "-m", "benchmarks.bench_scale", "--one", str(n), str(k), "--no-adjust", "--seed", str(seed)]
    if search_weights is not None:
        cmd += ["--search-weights", search_weights]
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


def kernels_same_process(n: int, k: int, rev: str, seed: int) -> None:
    """Old and new planner parts in one process on the same ``n``-target job (see the module docstring)."""
    from dataclasses import replace

    import numpy as np

    sys.path.insert(0, str(ROOT))
    from benchmarks.baseline_code import load_package_at, submodule
    from benchmarks.bench_scale import JOB, synthetic_targets
    from cell.loadedjob import load
    from cell.setup import planner_options
    from planning import polish as new_polish
    from planning import refine as new_refine
    from planning import uncertainty as new_unc
    from planning import visibility as new_vis
    from planning.part import Part
    from planning.seeding import greedy_cover

    old = load_package_at("planning", rev)  # self-contained: old modules import old modules
    old_vis, old_unc = submodule(old, "visibility"), submodule(old, "uncertainty")
    old_refine, old_polish = submodule(old, "refine"), submodule(old, "polish")

    job = load(JOB)
    targets = synthetic_targets(job.part.mesh, n, np.random.default_rng(seed))
    part = Part(job.part.name, job.part.mesh, targets, target_diameter_m=job.part.target_diameter_m)
    opts = replace(planner_options(replace(job, part=part)), n_stations=k)
    intr, vo = job.intrinsics, opts.visibility_options()
    sphere = opts.search_sphere(part, intr)
    genes = sphere.candidates(max(1, -(-int(opts.n_candidates) // opts.n_shells)), opts.n_shells)
    T = sphere.poses(genes)
    load0 = os.getloadavg()[0]
    print(f"\n{n} targets, {len(T)} candidates, {k} stations: old ({rev}) and new in one process "
          f"(load average {load0:.1f})")

    def timed(f, *args, **kw):
        t0 = time.perf_counter()
        r = f(*args, **kw)
        return r, time.perf_counter() - t0

    new_vis.compute_visibility(part, intr, T[:4], vo)  # load the compiled kernels before timing
    vis_new, t_new = timed(new_vis.compute_visibility, part, intr, T, vo)
    vis_old, t_old = timed(old_vis.compute_visibility, part, intr, T, vo)
    print(f"  visibility database   old {t_old:7.2f} s  new {t_new:7.2f} s  {t_old / t_new:5.1f}x  "
          f"same: {np.array_equal(vis_old, vis_new)}")
    cols = np.flatnonzero(vis_new.sum(axis=0) >= opts.min_rays)
    V = vis_new[:, cols]
    xyz = np.asarray(part.targets.xyz)[cols]
    new_unc.target_information(intr, T[:4], xyz, V[:4], opts.sigma_px, sparse=True)
    info_new, t_new = timed(new_unc.target_information, intr, T, xyz, V, opts.sigma_px, sparse=True)
    info_old, t_old = timed(old_unc.target_information, intr, T, xyz, V, opts.sigma_px, sparse=True)
    diff = float(np.max(np.abs(info_new.data.astype(float) - info_old.data) / np.maximum(np.abs(info_old.data), 1e-30)))
    print(f"  information (sparse)  old {t_old:7.2f} s  new {t_new:7.2f} s  {t_old / t_new:5.1f}x  "
          f"largest relative difference {diff:.1e} (float32)")
    valid = np.flatnonzero(V.any(axis=1))
    starts = np.stack([greedy_cover(V, valid, k, opts.min_rays, np.random.default_rng(seed + i)) for i in range(2)])
    args = (V, valid, starts, opts.min_rays)
    r_new, t_new = timed(new_refine.refine_network, info_new, *args, np.random.default_rng(1), n_kicks=2)
    r_old, t_old = timed(old_refine.refine_network, info_old, *args, np.random.default_rng(1), n_kicks=2)
    print(f"  exchange descent      old {t_old:7.2f} s  new {t_new:7.2f} s  {t_old / t_new:5.1f}x  "
          f"same network: {np.array_equal(r_new.stations, r_old.stations)}, worst {r_old.worst * 1e6:.4f} / "
          f"{r_new.worst * 1e6:.4f} um, {r_new.n_swaps} swaps")
    db = type("DB", (), {"genes": genes})()
    net = genes[starts[0]]
    sph = replace(sphere, max_roll_rad=0.0, max_offset_m=0.0)
    p_new, t_new = timed(new_polish.polish, part, intr, sph, vo, db, net, cols, opts)
    p_old, t_old = timed(old_polish.polish, part, intr, sph, vo, db, net, cols, opts)
    print(f"  polish                old {t_old:7.2f} s  new {t_new:7.2f} s  {t_old / t_new:5.1f}x  "
          f"same network: {np.array_equal(p_new.genes, p_old.genes)}, worst {p_old.worst * 1e6:.4f} / "
          f"{p_new.worst * 1e6:.4f} um, poses ray-cast {p_old.n_poses} / {p_new.n_poses}", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="+", default=["1000x29", "5000x64"], help="TARGETSxSTATIONS")
    ap.add_argument("--baseline", default=BASELINE, help="commit to compare with")
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--search-weights", choices=("sigma", "model"), default=None,
                    help="this tree's search weighs each ray by sigma_px or by the detector model (default: as the "
                         "job: one sigma; decision 0031)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=3600.0)
    ap.add_argument("--warm", action=argparse.BooleanOptionalAction, default=True,
                    help="one unmeasured run of this tree first (compiles and caches the kernels); --no-warm: none")
    ap.add_argument("--kernels", metavar="NxK", help="time the parts old and new in this process (no plans)")
    a = ap.parse_args(argv)
    if a.kernels:
        try:
            n, k = (int(x) for x in a.kernels.lower().split("x"))
        except ValueError:
            print(f"bench_planspeed: --kernels takes TARGETSxSTATIONS, got {a.kernels!r}", file=sys.stderr)
            return 2
        kernels_same_process(n, k, a.baseline, a.seed)
        return 0
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
                now.append(run_one(ROOT, n, k, a.seed, a.timeout, a.search_weights))
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
            line = f"  worst sigma: now {b_now['worst_um']:.9f} um"
            if b_old and "error" not in b_old:
                same = b_old.get("genes_sha") is not None and b_old.get("genes_sha") == b_now.get("genes_sha")
                rel = abs(b_now["worst_um"] / b_old["worst_um"] - 1.0)
                line += (f", baseline {b_old['worst_um']:.9f} um (relative difference {rel:.1e}); stations "
                         + ("identical" if same else "differ" if b_old.get("genes_sha") else "not compared"))
            elif b_old:
                line += f", baseline: {b_old['error']}"
            print(line)
            print(f"  polish: {b_now.get('polish')}; stations digest {b_now.get('genes_sha')}")
            print("  per run (now): " + ", ".join(f"{r.get('plan_s', float('nan')):.2f} s" for r in now)
                  + ("; baseline: " + ", ".join(f"{r.get('plan_s', float('nan')):.2f} s" for r in old) if old else ""),
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
