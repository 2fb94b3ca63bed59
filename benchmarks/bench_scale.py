"""Scaling profile of a job: planning, validation and adjustment at 1k..50k targets x 16..128 stations.

Each configuration is a synthetic job built from the example (examples/bracket/job.toml: same camera,
cell and robot; ``n`` targets sampled on the bracket's non-downward faces, away from facet edges, by
planning.part.sample_targets; ``sample`` its time). It runs in its own process (so the peak memory is that configuration's) and prints the
time of each phase:

- ``visibility``: the visibility database, built afresh (no cache);
- ``reach``: the reachability database (IK + collisions) of its candidates;
- ``information``, ``search`` (evolution + exchange descent), ``polish`` (exact local polish),
  ``final`` (exact re-check): planning.planner's own timing;
- ``validate``: planning.execution.validate_plan of the planned stations;
- ``adjust``: bundle_adjust with data snooping on simulated observations of the plan (every target
  seen by its planned stations, 0.05 px noise, ``--blunders`` of the observations displaced by
  1-10 px), with a scale bar as datum and ADJUST's limit on rejections; ``adjust_old`` the same with
  the one-rejection-per-re-adjustment loop of before (``BundleOptions(snooping_batch=False)``) and
  ADJUST's old limit (5 %), where ``--baseline`` allows it (it grows as rejections x adjustment time);
- ``peak`` the process's peak resident memory.

The planned worst sigma and, for the adjustment, how many blunders were found, missed, and how many
good observations were rejected.

    .venv/bin/python -m benchmarks.bench_scale --quick          # 1k x 16/29, 5k x 29 (minutes)
    .venv/bin/python -m benchmarks.bench_scale --targets 1000 5000 --stations 29 64
    .venv/bin/python -m benchmarks.bench_scale --one 1000 29     # one configuration, JSON line
    .venv/bin/python -m benchmarks.bench_scale --one 1000 29 --no-adjust --bound  # and plan / bound
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
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

JOB = ROOT / "examples" / "bracket" / "job.toml"


def synthetic_targets(mesh, n: int, rng: np.random.Generator):
    """``n`` targets sampled on the faces with normal z >= -0.1, 6 mm from facet edges (planning.part.sample_targets)."""
    from planning.part import sample_targets

    return sample_targets(mesh, n, rng, edge_clearance_m=0.006, min_normal_z=-0.1)


def _peak_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def simulate_observations(intr, T, xyz, visible, rng, sigma_px=0.05, blunder_share=0.05):
    """Observations of targets ``xyz`` in the images ``T: (m, 4, 4) part_from_cam`` where ``visible``."""
    from calibration.camera import invert, project

    oi, ot, ouv = [], [], []
    for j in range(len(T)):
        sel = np.flatnonzero(visible[j])
        uv = project(intr, invert(T[j]), xyz[sel])
        oi.append(np.full(len(sel), j))
        ot.append(sel)
        ouv.append(uv + rng.normal(0, sigma_px, (len(sel), 2)))
    oi, ot, ouv = np.concatenate(oi), np.concatenate(ot), np.vstack(ouv)
    bad = rng.random(len(oi)) < blunder_share
    ang = rng.uniform(0, 2 * np.pi, bad.sum())
    ouv[bad] += rng.uniform(1.0, 10.0, bad.sum())[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    return oi, ot, ouv, bad


def run_adjust(intr, T, xyz, visible, scale_bar, rng, blunders, batch=True, max_rejections=None):
    from calibration.bundle import BundleConfig, BundleOptions, ScaleBar, bundle_adjust
    from calibration.camera import exp_se3, invert

    oi, ot, ouv, bad = simulate_observations(intr, T, xyz, visible, rng, blunder_share=blunders)
    # start like ADJUST: poses a little off (Faugeras-Toscani), targets at the CAD nominals
    cfp = np.array([exp_se3(rng.normal(0, 3e-4, 6)) @ invert(t) for t in T])
    x0 = xyz + rng.normal(0, 2e-4, xyz.shape)
    a, b = scale_bar
    bar = ScaleBar(a, b, float(np.linalg.norm(xyz[a] - xyz[b])), 2e-6)
    kw = {} if max_rejections is None else {"max_rejections": max_rejections}
    opts = BundleOptions(sigma_px=0.05, snooping_batch=batch, **kw)
    t0 = time.perf_counter()
    res = bundle_adjust(oi, ot, ouv, intr, cfp, x0, opts, BundleConfig(scale_bars=(bar,)))
    dt = time.perf_counter() - t0
    rej = res.rejected
    return {"s": dt, "n_obs": int(len(oi)), "blunders": int(bad.sum()), "found": int((rej & bad).sum()),
            "missed": int((~rej & bad).sum()), "false": int((rej & ~bad).sum()),
            "stopped": getattr(res, "snooping", {}).get("stopped_because", ""),
            "rounds": getattr(res, "snooping", {}).get("rounds", None),
            "sigma0_px": res.sigma0_px, "timings": {k: round(v, 3) for k, v in res.timings.items()}}


def one(n_targets: int, n_stations: int, seed: int, blunders: float, baseline: bool, skip_adjust: bool,
        bound: bool = False, search_weights: str | None = None) -> dict:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from cell.loadedjob import load
    from cell.setup import collision_world, planner_options, robot_model
    from planning.execution import MotionLimits, validate_plan
    from planning.part import Part
    from planning.planner import plan_network
    from planning.reachability import ReachabilityDB, ReachabilityOptions, reachability_mask
    from planning.visibility import VisibilityDB

    out: dict = {"targets": n_targets, "stations": n_stations}
    job = load(JOB)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    targets = synthetic_targets(job.part.mesh, n_targets, rng)
    out["sample_s"] = time.perf_counter() - t0
    part = Part(job.part.name, job.part.mesh, targets, target_diameter_m=job.part.target_diameter_m)
    job = replace(job, part=part)
    opts = replace(planner_options(job), n_stations=n_stations)
    if search_weights is not None:  # how the search weighs each ray (default: the job's; docs/decisions/0031)
        from cell.setup import image_precision

        opts = replace(opts, image_precision=image_precision(job) if search_weights == "model" else None)
    out["search_weights"] = "sigma" if opts.image_precision is None else "model"
    vis_opts = opts.visibility_options()
    sphere = replace(opts.sphere, max_roll_rad=0.0, max_offset_m=0.0)
    with tempfile.TemporaryDirectory() as cache:
        t0 = time.perf_counter()
        db = VisibilityDB.load_or_build(part, job.intrinsics, sphere, vis_opts, opts.n_candidates, cache,
                                        n_shells=opts.n_shells, backend=opts.backend)
        out["visibility_s"] = time.perf_counter() - t0
        robot, world = robot_model(job), collision_world(job)
        bfp, ffc = job.spec.base_from_part(), job.spec.flange_from_cam()
        t0 = time.perf_counter()
        reach = ReachabilityDB.load_or_build(robot, bfp, ffc, db.part_from_cam, world, cache_dir=cache)
        out["reach_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        plan = plan_network(part, job.intrinsics, replace(opts, allow_unmeasurable=True, lower_bound=bound),
                            np.random.default_rng(job.spec.job.seed), reachable=reach.reachable, cache_dir=cache,
                            seed=job.spec.job.seed, db=db,
                            reachable_fn=lambda T: reachability_mask(robot, bfp, ffc, T, world,
                                                                     ReachabilityOptions(compute_distances=False)).reachable)
        out["plan_s"] = time.perf_counter() - t0
    tm = plan.timing
    out.update(information_s=tm.get("information_s"), search_s=tm.get("search_s", 0) - tm.get("polish_s", 0),
               polish_s=tm.get("polish_s"), final_s=tm.get("final_s"))
    out["worst_um"] = plan.predicted_sigma_max_m * 1e6
    out["genes_sha"] = __import__("hashlib").sha256(np.ascontiguousarray(plan.genes).tobytes()).hexdigest()[:16]
    if bound and "lower_bound_sigma_m" in plan.search:
        # the bound covers networks of the database's candidates: the search's network (on the database) is one,
        # the polished plan has left the database (continuous poses, look-at offsets) and can be below it
        out.update(bound_um=plan.search["lower_bound_sigma_m"] * 1e6, bound_s=tm.get("bound_s"),
                   search_over_bound=plan.search["search_fitness"] / plan.search["lower_bound_sigma_m"],
                   plan_over_bound=plan.search["plan_over_lower_bound"], bound_stopped=plan.search["lower_bound_stopped"])
    out["unmeasurable"] = len(plan.unmeasurable_target_ids)
    out["polish"] = {k: plan.search.get(k) for k in ("polish_swaps", "polish_from", "polish_to")}
    c = job.spec.cell
    t0 = time.perf_counter()
    try:
        validate_plan(robot, plan.part_from_cam, bfp, ffc, world,
                      MotionLimits(joint_speed_rad_s=c.max_joint_speed_rad_s,
                                   joint_accel_rad_s2=c.max_joint_accel_rad_s2, settle_s=c.settle_s),
                      ids=plan.station_ids)
        out["validate_s"] = time.perf_counter() - t0
    except Exception as exc:  # noqa: BLE001 - a benchmark reports, it does not stop
        out["validate_s"] = time.perf_counter() - t0
        out["validate_error"] = str(exc)[:200]
    if not skip_adjust:
        vis = np.zeros((len(plan.station_ids), n_targets), dtype=bool)
        sid = {s: i for i, s in enumerate(plan.station_ids)}
        for j, seen in enumerate(plan.seen_by):
            vis[[sid[s] for s in seen], j] = True
        meas = np.isfinite(plan.cov).all(axis=(1, 2))
        vis[:, ~meas] = False
        xyz = targets.xyz
        a = int(np.argmin(xyz[:, 0] + xyz[:, 1]))
        b = int(np.argmax(xyz[:, 0] + xyz[:, 1]))
        q = int(vis.sum())
        out["adjust"] = run_adjust(job.intrinsics, plan.part_from_cam, xyz, vis, (a, b),
                                   np.random.default_rng(seed + 1), blunders, max_rejections=adjust_cap(q))
        out["adjust_s"] = out["adjust"]["s"]
        if baseline:
            out["adjust_old"] = run_adjust(job.intrinsics, plan.part_from_cam, xyz, vis, (a, b),
                                           np.random.default_rng(seed + 1), blunders, batch=False,
                                           max_rejections=max(20, q // 20))
            out["adjust_old_s"] = out["adjust_old"]["s"]
    out["peak_gb"] = _peak_gb()
    return out


def adjust_cap(q: int) -> int:
    """ADJUST's limit on rejections (cell.stages.adjust.max_rejections; before issue 21: max(20, q // 20))."""
    from cell.stages.adjust import max_rejections

    return max_rejections(q)


PHASES = ("sample_s", "visibility_s", "reach_s", "information_s", "search_s", "polish_s", "final_s", "validate_s", "adjust_s",
          "adjust_old_s")


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.1f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--targets", type=int, nargs="+", default=[1000, 5000, 20000, 50000])
    ap.add_argument("--stations", type=int, nargs="+", default=[16, 29, 64, 128])
    ap.add_argument("--quick", action="store_true", help="1k x 16/29 and 5k x 29")
    ap.add_argument("--blunders", type=float, default=0.05)
    ap.add_argument("--baseline", type=int, default=1000,
                    help="also run the old one-at-a-time snooping up to this many targets (0: never)")
    ap.add_argument("--no-adjust", action="store_true")
    ap.add_argument("--bound", action="store_true",
                    help="--one: also the lower bound on the worst sigma (planning.bound) and plan / bound")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=1800.0)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--search-weights", choices=("sigma", "model"), default=None,
                    help="--one: the search weighs each ray by sigma_px or by the detector model (default: as the job)")
    ap.add_argument("--one", type=int, nargs=2, metavar=("TARGETS", "STATIONS"))
    a = ap.parse_args()
    if a.one:
        r = one(a.one[0], a.one[1], a.seed, a.blunders, a.one[0] <= a.baseline, a.no_adjust, a.bound,
                a.search_weights)
        print(json.dumps(r, default=float))
        return
    configs = [(1000, 16), (1000, 29), (5000, 29)] if a.quick else [(n, k) for n in a.targets for k in a.stations]
    rows = []
    print("targets stations | " + " ".join(f"{p[:-2]:>10s}" for p in PHASES) + " | worst_um  peak_GB | adjust: "
          "blunders found missed false-rejections")
    for n, k in configs:
        cmd = [sys.executable, "-m", "benchmarks.bench_scale", "--one", str(n), str(k), "--seed", str(a.seed),
               "--blunders", str(a.blunders), "--baseline", str(a.baseline)] + (["--no-adjust"] if a.no_adjust else [])
        t0 = time.perf_counter()
        try:
            p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=a.timeout)
        except subprocess.TimeoutExpired:
            print(f"{n:7d} {k:8d} | not done in {a.timeout:.0f} s")
            rows.append({"targets": n, "stations": k, "timeout_s": a.timeout})
            continue
        if p.returncode != 0:
            print(f"{n:7d} {k:8d} | failed: {p.stderr.strip().splitlines()[-1] if p.stderr.strip() else p.returncode}")
            rows.append({"targets": n, "stations": k, "error": p.stderr[-2000:]})
            continue
        r = json.loads(p.stdout.strip().splitlines()[-1])
        r["wall_s"] = time.perf_counter() - t0
        rows.append(r)
        ad = r.get("adjust", {})
        line = (f"{n:7d} {k:8d} | " + " ".join(f"{_fmt(r.get(ph)):>10s}" for ph in PHASES)
                + f" | {r['worst_um']:8.1f} {r['peak_gb']:7.2f} | "
                + (f"{ad['blunders']} {ad['found']} {ad['missed']} {ad['false']}" if ad else "-"))
        if "adjust_old_s" in r and r["adjust_s"]:
            line += f"  (adjust old/new {r['adjust_old_s'] / r['adjust_s']:.1f}x)"
        print(line, flush=True)
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
