"""Benchmark of the network planner on the example part (the bracket).

For 8, 16 and 29 stations it compares the planned network's worst-target sigma with
(i) the best single-ring or two-ring convergent network of the same size found by
sweeping elevation(s) and radius, and (ii) random networks; and it times planning
29 stations x ~1000 targets with the visibility database built from scratch.

Every network (planned, ring, random) is scored the same way: fresh ray casting at its
poses, float64 limiting error propagation (``covariance_for_network``), sigma =
sqrt(trace(cov)), worst over the targets that *some* network of valid candidates can
measure with ``min_rays`` rays (the planner's measurable set).  The exact fewest stations
that can give every measurable target 3 (or 2) rays is computed (set multicover MILP); a
size below it is planned and compared with ``min_rays = 2``.  A ring or random network
that measures a target with fewer than ``min_rays`` rays is infeasible; for those the
worst sigma over the targets with at least 2 rays is also reported (a lenient figure).

    .venv/bin/python benchmarks/bench_planner.py [--quick] [--bound] [--json out.json] [--png DIR] [--timing-only --repeat 5]

``--bound`` adds planning.bound's lower bound on the worst sigma of ANY k-station network on the
database (how far the plan is from the best possible) and, for 8 stations, decides per random
network whether any network could reach 0.2 x its worst on its targets.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.camera import Intrinsics  # noqa: E402
from planning.part import Part, make_bracket, sample_targets  # noqa: E402
from planning.planner import PlannerOptions, plan_network  # noqa: E402
from planning.seeding import ring_genes  # noqa: E402
from planning.stations import N_GENES, ViewingSphere  # noqa: E402
from planning.uncertainty import covariance_for_network  # noqa: E402
from planning.visibility import VisibilityDB, VisibilityOptions, compute_visibility  # noqa: E402


def example_part(n_targets: int = 1000, seed: int = 0) -> Part:
    """The bracket with ``n_targets`` targets on its non-downward faces (it sits on them)."""
    mesh = make_bracket()
    targets = sample_targets(mesh, n_targets, np.random.default_rng(seed), edge_clearance_m=0.006, min_normal_z=-0.1)
    return Part("bracket", mesh, targets)


def example_camera() -> Intrinsics:
    """5 MP industrial camera, 3.45 um pixels, 12 mm lens."""
    return Intrinsics.from_focal_length(0.012, 3.45e-6, 2448, 2048)


def score(part, intr, genes, sphere, vis_opts, sigma_px, min_rays, cols) -> dict:
    """Exact worst-target sigma of the network ``genes: (k, N_GENES)`` over targets ``cols``."""
    T = sphere.poses(genes)
    vis = compute_visibility(part, intr, T, vis_opts)
    cov, n_rays = covariance_for_network(intr, T, part.targets.xyz, vis, sigma_px, min_rays=2)
    sig = np.sqrt(np.trace(cov, axis1=1, axis2=2))[cols]
    nr = n_rays[cols]
    feasible = bool(np.all(nr >= min_rays) and np.all(np.isfinite(sig)))
    finite = np.isfinite(sig)
    covered = finite & (nr >= min_rays)
    return {
        "worst_m": float(np.max(sig)) if feasible else float("inf"),
        "worst_lenient_m": float(np.max(sig[finite])) if finite.any() else float("inf"),
        "worst_covered_m": float(np.max(sig[covered])) if covered.any() else float("inf"),
        "coverage": float(covered.mean()),
        "covered": covered,
        "sigma": sig,
        "feasible": feasible,
        "min_rays_seen": int(nr.min()),
    }


def best_ring(part, intr, k, sphere, vis_opts, sigma_px, min_rays, cols, quick=False) -> dict:
    """Best single- or two-ring convergent network of ``k`` stations, by exact scoring.

    Stage 1 sweeps elevations (5 deg steps; 15 with ``quick``) for one ring and every
    pair for two rings (split evenly, staggered), at 5 distances across the sphere's
    band.  Stage 2 takes the 6 best of stage 1 (by each figure below) and sweeps the phase
    (8 steps over one station spacing), the split of stations between two rings (1/3,
    1/2, 2/3) and the distance +-1/8 of the band.  Figures kept: the best *feasible*
    ring (every target >= ``min_rays`` rays), the best ring covering >= 95 % of the
    targets (its worst over the targets it covers), and the best lenient ring (worst over
    targets with >= 2 rays).
    """
    els = np.deg2rad(np.arange(10, 86, 15 if quick else 5))
    span = sphere.distance_max_m - sphere.distance_min_m
    dists = np.linspace(sphere.distance_min_m, sphere.distance_max_m, 3 if quick else 5)
    best = {"worst_m": np.inf, "worst_lenient_m": np.inf, "worst_covered_m": np.inf, "coverage_max": 0.0}
    scored: list[tuple[dict, tuple]] = []

    def run(elevs, d, phase=0.0, counts=None):
        s = score(part, intr, ring_genes(k, list(elevs), d, phase, counts), sphere, vis_opts, sigma_px, min_rays, cols)
        cfg = {"elevations_deg": np.rad2deg(elevs).round(1).tolist(), "distance_m": round(float(d), 4),
               "phase_deg": round(float(np.rad2deg(phase)), 1), "counts": counts}
        best["coverage_max"] = max(best["coverage_max"], s["coverage"])
        if s["worst_m"] < best["worst_m"]:
            best.update(worst_m=s["worst_m"], feasible_config=cfg)
        if s["coverage"] >= 0.95 and s["worst_covered_m"] < best["worst_covered_m"]:
            best.update(worst_covered_m=s["worst_covered_m"], coverage=s["coverage"], covered=s["covered"],
                        covered_config=cfg)
        if s["worst_lenient_m"] < best["worst_lenient_m"]:
            best.update(worst_lenient_m=s["worst_lenient_m"], lenient_coverage=s["coverage"], lenient_config=cfg)
        scored.append((s, (tuple(elevs), float(d))))

    configs = [[e] for e in els] + [[e1, e2] for i, e1 in enumerate(els) for e2 in els[i + 1:]]
    for d in dists:
        for elevs in configs:
            run(elevs, d)
    # stage 2: phase, split and distance around the best of stage 1
    keys = ("worst_m", "worst_covered_m", "worst_lenient_m")
    top = []
    for key in keys:
        for s, c in sorted(scored, key=lambda sc: sc[0][key] if key != "worst_covered_m" or sc[0]["coverage"] >= 0.95
                           else np.inf)[: (2 if quick else 6)]:
            if c not in top and np.isfinite(s[key]):
                top.append(c)
    for elevs, d in top:
        splits = [None] if len(elevs) == 1 else [None] + [[c, k - c] for c in sorted({round(k / 3), round(2 * k / 3)})
                                                        if 2 <= c <= k - 2]
        for dd in (d - span / 8, d, d + span / 8):
            if not sphere.distance_min_m <= dd <= sphere.distance_max_m:
                continue
            for counts in splits:
                n_first = counts[0] if counts else k // len(elevs) + (k % len(elevs) > 0)
                for ph in np.arange(4 if quick else 8) / (4 if quick else 8) * 2 * np.pi / n_first:
                    run(elevs, dd, ph, counts)
    best["n_networks"] = len(scored)
    return best


def random_networks(part, intr, k, sphere, vis_opts, sigma_px, min_rays, cols, n, rng,
                    planned_sigma: np.ndarray | None = None) -> dict:
    """``n`` random networks of ``k`` stations; with ``planned_sigma`` (over ``cols``) also, per network,
    the plan's worst over the targets that network measures with >= 2 rays / the network's worst there."""
    worst, lenient, feas, same_set, sets = [], [], [], [], []
    s0, s1 = np.sin(sphere.elevation_min_rad), np.sin(sphere.elevation_max_rad)
    for _ in range(n):
        g = np.zeros((k, N_GENES))
        g[:, 0] = rng.uniform(sphere.azimuth_min_rad, sphere.azimuth_max_rad, k)
        g[:, 1] = np.arcsin(rng.uniform(s0, s1, k))  # uniform over the band's area
        g[:, 2] = rng.uniform(sphere.distance_min_m, sphere.distance_max_m, k)
        s = score(part, intr, g, sphere, vis_opts, sigma_px, min_rays, cols)
        worst.append(s["worst_m"])
        lenient.append(s["worst_lenient_m"])
        feas.append(s["feasible"])
        finite = np.isfinite(s["sigma"])
        if planned_sigma is not None and finite.any():
            same_set.append(float(np.max(planned_sigma[finite])) / s["worst_lenient_m"])
            sets.append((finite, s["worst_lenient_m"]))
    return {
        "sets": sets,  # per network: the targets it measures (over cols), and its worst there
        "median_ratio_same_targets": float(np.median(same_set)) if same_set else float("nan"),
        "median_worst_m": float(np.median(worst)),
        "median_worst_lenient_m": float(np.median(lenient)),
        "fraction_feasible": float(np.mean(feas)),
        "n_networks": n,
    }


# the bound over the database's candidates fell by 9.5 % over a 4x denser database and by 7.3 % when the
# relaxation's stations were refined off the database (benchmarks/planner_bound.py, k = 8): a decision
# about target (ii) below asks for this much margin
BOUND_MARGIN = 1.15


def bound_figures(db, intr, part, cols, k, min_rays, sigma_px, planned, sets) -> dict:
    """Lower bound on the worst sigma of any k-station network on the database (planning.bound) and, per
    random network, whether ANY network's worst over that network's targets must exceed 0.2 x its worst."""
    from planning.bound import worst_sigma_lower_bound
    from planning.uncertainty import target_information

    vis = db.visible[:, cols]
    info = target_information(intr, db.part_from_cam, part.targets.xyz[cols], vis, sigma_px)
    b = worst_sigma_lower_bound(info, k, visible=vis, min_rays=min_rays)
    um = 1e6
    print(f"  bound: no {k}-station network on the {len(db.genes)} candidates has its worst target below "
          f"{b.lower * um:.2f} um ({b.stopped_because}, {b.seconds:.1f} s); the plan is {planned['worst_m'] / b.lower:.3f} "
          f"x that; 0.2 x median random needs <= {0.2 * np.median([w for _, w in sets]) * um:.2f} um", flush=True)
    out = {"lower_bound_m": b.lower, "plan_over_bound": planned["worst_m"] / b.lower, "seconds": b.seconds}
    like_for_like = np.median([np.max(planned["sigma"][finite]) / w for finite, w in sets])
    if like_for_like <= 0.2:  # (ii) met by the plan: nothing to decide
        return out
    t0, above, below, undecided = time.perf_counter(), 0, 0, 0
    for finite, worst in sets:
        thr = 0.2 * worst * BOUND_MARGIN
        bs = worst_sigma_lower_bound(info, k, visible=vis, min_rays=min_rays, targets=finite, stop_above=thr,
                                     stop_below=thr, rel_tol=1e-2)
        above += bs.lower > thr
        below += bs.relaxed < thr
        undecided += not (bs.lower > thr or bs.relaxed < thr)
    n = len(sets)
    verdict = ("so the median ratio of ANY network exceeds 0.2: target (ii) is out of reach"
               if above > n / 2 else "not enough to decide")
    print(f"  like for like: for {above} of {n} random networks no {k}-station network can get below "
          f"0.2 x {BOUND_MARGIN} x their worst on their targets ({below} could, {undecided} undecided; "
          f"{time.perf_counter() - t0:.0f} s): {verdict}", flush=True)
    out.update(like_for_like_out_of_reach=above, like_for_like_reachable=below, like_for_like_n=n,
               margin=BOUND_MARGIN)
    return out


def min_stations_for_cover(visible: np.ndarray, min_rays: int, time_limit_s: float = 120.0) -> int | None:
    """Fewest candidates covering every target ``min_rays`` times (exact set multicover, HiGHS MILP).

    ``visible: (m, n)`` bool over the measurable targets. A lower bound for any network on
    the database's candidates (continuous stations could differ marginally). None if not solved.
    """
    from scipy.optimize import Bounds, LinearConstraint, milp

    m = visible.shape[0]
    res = milp(np.ones(m), constraints=LinearConstraint(visible.T.astype(float), lb=min_rays),
               integrality=np.ones(m), bounds=Bounds(0, 1), options={"time_limit": time_limit_s})
    return int(round(res.fun)) if res.status == 0 else None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="coarser sweeps, fewer random networks")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--sizes", type=int, nargs="*", default=[8, 16, 29])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--generations", type=int, help="search generations (default: the planner's)")
    ap.add_argument("--stall", type=int, help="stall generations (default: the planner's)")
    ap.add_argument("--timing-only", action="store_true", help="only the 29-station timing run")
    ap.add_argument("--repeat", type=int, default=1, help="timing runs (best and median are printed)")
    ap.add_argument("--png", type=Path, help="write a picture of each plan into this folder")
    ap.add_argument("--bound", action="store_true",
                    help="also bound how good any network could be (planning.bound), and whether (ii) is reachable")
    args = ap.parse_args(argv)

    part, intr = example_part(), example_camera()
    search_kw = {k: v for k, v in (("generations", args.generations), ("stall_generations", args.stall)) if v}
    opts = PlannerOptions(allow_unmeasurable=True)
    sphere = ViewingSphere.for_part(part, intr)
    sphere = ViewingSphere(**{**sphere.to_dict(), "max_roll_rad": 0.0, "max_offset_m": 0.0})
    vis_opts = VisibilityOptions(incidence_max_rad=opts.incidence_max_rad)
    out: dict = {"n_targets": len(part.targets), "sigma_px": opts.sigma_px, "min_rays": opts.min_rays,
                 "search": search_kw, "sizes": {}}

    # timing: 29 stations, visibility database built from scratch (empty cache), --repeat times
    import os

    walls = []
    for _ in range(args.repeat):
        with tempfile.TemporaryDirectory() as cache:
            t0, c0 = time.perf_counter(), time.process_time()
            plan = plan_network(part, intr, PlannerOptions(n_stations=29, allow_unmeasurable=True, **search_kw),
                                np.random.default_rng(args.seed), cache_dir=cache, seed=args.seed)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        walls.append(wall)
        print(f"timing 29 stations x {len(part.targets)} targets (cold cache): wall {wall:.2f} s, process CPU "
              f"{cpu:.2f} s, load average {os.getloadavg()[0]:.1f}, {plan.search['generations']} generations, "
              f"worst {plan.predicted_sigma_max_m * 1e6:.2f} um  "
              f"{ {k: round(v, 2) for k, v in plan.timing.items()} }", flush=True)
    out["timing_29"] = {"wall_s": walls, "best_wall_s": min(walls), "median_wall_s": float(np.median(walls)),
                        "cpu_s": cpu, **{k: round(v, 3) for k, v in plan.timing.items()},
                        "generations": plan.search["generations"], "stopped_because": plan.search["stopped_because"]}
    if args.repeat > 1:
        print(f"timing over {len(walls)} runs: best {min(walls):.2f} s, median {np.median(walls):.2f} s "
              f"(target <= 10 s, stretch 5 s)", flush=True)
    if args.timing_only:
        return 0

    with tempfile.TemporaryDirectory() as cache:
        db = VisibilityDB.load_or_build(part, intr, sphere, vis_opts, opts.n_candidates, cache)
        measurable = db.visible.sum(axis=0) >= opts.min_rays
        bounds = {r: min_stations_for_cover(db.visible[:, measurable], r) for r in (2, 3)}
        out["min_stations_for_min_rays"] = bounds
        print(f"fewest database stations covering all {int(measurable.sum())} measurable targets: "
              f"{bounds[2]} for 2 rays, {bounds[3]} for 3 rays", flush=True)
        for k in args.sizes:
            # below the exact lower bound no network can give every target 3 rays: plan for 2
            min_rays = opts.min_rays if bounds[3] is None or k >= bounds[3] else 2
            t0 = time.perf_counter()
            plan = plan_network(part, intr, PlannerOptions(n_stations=k, min_rays=min_rays, allow_unmeasurable=True,
                                                           **search_kw),
                                np.random.default_rng(args.seed), cache_dir=cache, seed=args.seed)
            t_plan = time.perf_counter() - t0
            if args.png:
                from planning.plot import plot_plan

                plot_plan(part, plan, args.png / f"plan_{k}.png")
            ids = part.targets.index()
            cols = np.array(sorted(set(range(len(part.targets))) - {ids[t] for t in plan.unmeasurable_target_ids}))
            planned = score(part, intr, plan.genes, sphere, vis_opts, opts.sigma_px, min_rays, cols)
            ring = best_ring(part, intr, k, sphere, vis_opts, opts.sigma_px, min_rays, cols, args.quick)
            rnd = random_networks(part, intr, k, sphere, vis_opts, opts.sigma_px, min_rays, cols,
                                  30 if args.quick else 100, np.random.default_rng(1000 + k),
                                  planned_sigma=planned["sigma"])
            covered = ring.pop("covered", None)
            sets = rnd.pop("sets")
            row = {
                "min_rays": min_rays,
                "planned_worst_m": planned["worst_m"],
                "planned_feasible": planned["feasible"],
                "planned_min_rays": planned["min_rays_seen"],
                "plan_s": t_plan,
                "n_measurable_targets": int(len(cols)),
                "best_ring": ring,
                "random": rnd,
                # (i) strict: only rings that give every target min_rays rays compete
                "ratio_to_best_feasible_ring": planned["worst_m"] / ring["worst_m"],
                # (i) lenient: the best ring covering >= 95 %, both scored on the targets it covers
                "ratio_to_best_95pc_ring_on_its_set": None,
                # (ii) against the median random network's worst over the targets it measures with >= 2 rays
                "ratio_to_median_random_lenient": planned["worst_m"] / rnd["median_worst_lenient_m"],
            }
            if covered is not None:
                on_set = float(np.max(planned["sigma"][covered]))
                row["planned_worst_on_ring_covered_set_m"] = on_set
                row["ratio_to_best_95pc_ring_on_its_set"] = on_set / ring["worst_covered_m"]
            out["sizes"][k] = row
            um = 1e6
            lines = [f"k={k:2d} (min_rays {min_rays}, {len(cols)} targets, planned in {t_plan:.1f} s): planned worst "
                     f"{planned['worst_m'] * um:.2f} um, feasible={planned['feasible']} (fewest rays {planned['min_rays_seen']})"]
            if np.isfinite(ring["worst_m"]):
                r = row["ratio_to_best_feasible_ring"]
                lines.append(f"  (i) best feasible ring {ring['worst_m'] * um:.2f} um {ring['feasible_config']}: "
                             f"ratio {r:.3f} -> target <= 0.75 {'MET' if r <= 0.75 else 'NOT met'}")
            else:
                lines.append(f"  (i) no ring of {ring['n_networks']} tried gives every target {min_rays} rays (best "
                             f"coverage {ring['coverage_max']:.3f}): every ring is infeasible, so none is better than the plan")
            if covered is not None:
                r = row["ratio_to_best_95pc_ring_on_its_set"]
                lines.append(f"      best ring covering >= 95% ({ring['coverage']:.3f}) {ring['worst_covered_m'] * um:.2f} um on "
                             f"its targets {ring['covered_config']}; planned on the same targets "
                             f"{row['planned_worst_on_ring_covered_set_m'] * um:.2f} um: ratio {r:.3f} -> target <= 0.75 "
                             f"{'MET' if r <= 0.75 else 'NOT met'} (lenient comparison)")
            lines.append(f"      lowest lenient ring (worst over targets with >= 2 rays, coverage "
                         f"{ring['lenient_coverage']:.3f}): {ring['worst_lenient_m'] * um:.2f} um (not comparable: "
                         "it leaves targets out)")
            r = row["ratio_to_median_random_lenient"]
            med = f"{rnd['median_worst_m'] * um:.2f} um" if np.isfinite(rnd["median_worst_m"]) else "infeasible"
            lines.append(f"  (ii) {rnd['n_networks']} random networks: {rnd['fraction_feasible']:.2f} feasible, median "
                         f"worst {med}; median lenient worst (targets with >= 2 rays) "
                         f"{rnd['median_worst_lenient_m'] * um:.2f} um: ratio {r:.3f} -> target <= 0.2 "
                         f"{'MET' if r <= 0.2 else 'NOT met'}")
            r2 = rnd["median_ratio_same_targets"]
            lines.append(f"      like for like (each random network's measured targets; median over the networks of "
                         f"planned worst / its worst there): {r2:.3f} -> target <= 0.2 {'MET' if r2 <= 0.2 else 'NOT met'}")
            print("\n".join(lines), flush=True)
            if args.bound:
                row["bound"] = bound_figures(db, intr, part, cols, k, min_rays, opts.sigma_px, planned, sets)
    rows = out["sizes"]

    def ring_ratio(row) -> float:
        if np.isfinite(row["best_ring"]["worst_m"]):
            return row["ratio_to_best_feasible_ring"]
        return row["ratio_to_best_95pc_ring_on_its_set"] or float("nan")

    summary = {
        "what": "network planner on the bracket, 1000 targets (worst-target sigma of the plan)",
        "figure": f"planning 29 stations: {out['timing_29']['best_wall_s']:.1f} s; " + "; ".join(
            f"k={k}: worst {row['planned_worst_m'] * 1e6:.2f} um" for k, row in rows.items()),
        "baseline": "best ring (feasible, else >= 95% coverage on its targets); random networks like for like",
        "ratio": "; ".join(f"k={k}: " + (f"{ring_ratio(row):.3f} of ring (<= 0.75), " if np.isfinite(ring_ratio(row))
                                         else "no ring of the sweep covers >= 95 % (none to compare), ")
                           + f"{row['random']['median_ratio_same_targets']:.3f} of random (<= 0.2)"
                           + (f", {row['bound']['plan_over_bound']:.2f} x the lower bound" if "bound" in row else "")
                           + (f" [(ii) out of reach for any network: {row['bound']['like_for_like_out_of_reach']} of "
                              f"{row['bound']['like_for_like_n']} random networks]"
                              if row.get("bound", {}).get("like_for_like_out_of_reach", 0) * 2
                              > row.get("bound", {}).get("like_for_like_n", 1) else "")
                           for k, row in rows.items()),
    }
    print("BENCHMARK " + json.dumps(summary), flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=2, default=lambda v: v.tolist() if hasattr(v, "tolist") else None))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
