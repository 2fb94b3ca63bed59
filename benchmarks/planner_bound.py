"""How good could any network be?  Lower bounds on the worst-target sigma (planning.bound).

For each size k it prints, on the planner's model (limiting error propagation, sigma_px,
the visibility limits):

* the bound over the visibility database's candidates (what the planner searches);
* the bound after refining the candidate set where the relaxation puts its weight: every
  candidate the fractional optimum uses is nudged (azimuth, elevation, distance, look-at
  offset along u and v, roll), the new poses are ray-cast afresh and added, steps halved,
  ``--rounds`` times.  This follows the bound towards stations off the database (as the
  planner's polish does); it is an estimate of the continuous problem's bound, not a proof;
* optionally the bound over a denser database (``--dense N``);
* optionally (``--like-for-like``) the issue's comparison with random networks made a bound: for
  each of the benchmark's 100 random networks (same seed as bench_planner.py), the bound on ANY
  k-station network's worst over the targets that random network measures, divided by the random
  network's worst there.  The median of that ratio bounds from below the like-for-like median
  ratio any planner can reach (target: <= 0.2).

    .venv/bin/python -m benchmarks.planner_bound [--sizes 8 16 29] [--rounds 6] [--dense 12000] [--like-for-like]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_planner import example_camera, example_part  # noqa: E402
from planning.bound import SigmaBound, worst_sigma_lower_bound  # noqa: E402
from planning.planner import PlannerOptions  # noqa: E402
from planning.polish import local_variants  # noqa: E402
from planning.stations import ViewingSphere  # noqa: E402
from planning.uncertainty import target_information  # noqa: E402
from planning.visibility import VisibilityDB, VisibilityOptions, compute_visibility  # noqa: E402


def refined_bound(part, intr, sphere: ViewingSphere, vis_opts: VisibilityOptions, db: VisibilityDB, k: int,
                  min_rays: int, sigma_px: float, rounds: int = 6, log=print) -> list[tuple[int, SigmaBound]]:
    """Bound over the database, then over it plus nudged copies of the relaxation's support.

    Returns ``[(n_candidates, bound), ...]``, one per round (round 0: the database alone).
    """
    genes, visible = db.genes.copy(), db.visible.copy()
    info = target_information(intr, db.part_from_cam, part.targets.xyz, visible, sigma_px)
    b = worst_sigma_lower_bound(info, k, visible=visible, min_rays=min_rays)
    out = [(len(genes), b)]
    log(f"  k={k:2d} round 0: {len(genes)} candidates, bound {b.lower * 1e6:.2f} um ({b.stopped_because}, "
        f"{b.seconds:.1f} s)")
    band = (sphere.azimuth_max_rad - sphere.azimuth_min_rad) * (
        np.sin(sphere.elevation_max_rad) - np.sin(sphere.elevation_min_rad))
    step_rad = 0.5 * float(np.sqrt(band / (len(db.genes) / 3)))
    step_m = 0.04 * (sphere.distance_max_m - sphere.distance_min_m)
    offset_m, roll_rad = 0.1 * float(part.radius), 0.2
    for r in range(1, rounds + 1):
        support = np.flatnonzero(b.weights > 1e-3)
        base = genes[support]
        var = [local_variants(base, sphere, step_rad, step_m, offset_m).reshape(-1, genes.shape[1])]
        for s in (roll_rad, -roll_rad):
            g = base.copy()
            g[:, 3] += s
            var.append(g)
        new = np.concatenate(var)
        T = sphere.poses(new)
        vis = compute_visibility(part, intr, T, vis_opts)
        genes = np.concatenate([genes, new])
        visible = np.concatenate([visible, vis])
        info = np.concatenate([info, target_information(intr, T, part.targets.xyz, vis, sigma_px)])
        b = worst_sigma_lower_bound(info, k, visible=visible, min_rays=min_rays)
        out.append((len(genes), b))
        log(f"  k={k:2d} round {r}: {len(genes)} candidates ({len(support)} in the support), bound "
            f"{b.lower * 1e6:.2f} um ({b.stopped_because}, {b.seconds:.1f} s)")
        step_rad, step_m, offset_m, roll_rad = 0.5 * step_rad, 0.5 * step_m, 0.5 * offset_m, 0.5 * roll_rad
    return out


def like_for_like(part, intr, sphere, vis_opts, db, k, min_rays, sigma_px, n=100) -> np.ndarray:
    """Per random network of bench_planner.py: bound on any network's worst over its targets / its worst."""
    from benchmarks.bench_planner import random_networks

    cols = np.arange(len(part.targets))
    rnd = random_networks(part, intr, k, sphere, vis_opts, sigma_px, min_rays, cols, n,
                          np.random.default_rng(1000 + k), planned_sigma=np.zeros(len(cols)))
    info = target_information(intr, db.part_from_cam, part.targets.xyz, db.visible, sigma_px)
    t0, q = time.perf_counter(), []
    for finite, worst in rnd["sets"]:
        b = worst_sigma_lower_bound(info, k, visible=db.visible, min_rays=min_rays, targets=finite, rel_tol=5e-3)
        q.append(b.lower / worst)
    q = np.array(q)
    print(f"  like for like, k={k}: over {len(q)} random networks, (bound on any {k}-station network's worst over the "
          f"network's targets) / (the network's worst there): median {np.median(q):.4f}, quartiles "
          f"{np.percentile(q, 25):.4f} / {np.percentile(q, 75):.4f}; above 0.2 for {np.mean(q > 0.2):.0%} "
          f"({time.perf_counter() - t0:.0f} s). Any network's like-for-like median ratio is at least the median.",
          flush=True)
    return q


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[8, 16, 29])
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--dense", type=int, help="also bound over a database of this many candidates (4 shells)")
    ap.add_argument("--like-for-like", action="store_true",
                    help="bound the like-for-like ratio to the median random network (about 10 s per network)")
    args = ap.parse_args(argv)
    part, intr = example_part(), example_camera()
    opts = PlannerOptions(allow_unmeasurable=True)
    sphere = ViewingSphere.for_part(part, intr)
    sphere = ViewingSphere(**{**sphere.to_dict(), "max_roll_rad": 0.0, "max_offset_m": 0.0})
    vis_opts = VisibilityOptions(incidence_max_rad=opts.incidence_max_rad)
    with tempfile.TemporaryDirectory() as cache:
        db = VisibilityDB.load_or_build(part, intr, sphere, vis_opts, opts.n_candidates, cache)
        # the bench's rule: below the fewest stations giving every target 3 rays, plan for 2
        for k in args.sizes:
            min_rays = 2 if k < 11 else opts.min_rays
            t0 = time.perf_counter()
            rows = refined_bound(part, intr, sphere, vis_opts, db, k, min_rays, opts.sigma_px, args.rounds)
            line = (f"k={k:2d} (min_rays {min_rays}): bound over the database {rows[0][1].lower * 1e6:.2f} um, after "
                    f"{args.rounds} refinement rounds {rows[-1][1].lower * 1e6:.2f} um "
                    f"({rows[-1][0]} candidates, {time.perf_counter() - t0:.0f} s)")
            if args.dense:
                dense = VisibilityDB.load_or_build(part, intr, sphere, vis_opts, args.dense, cache, n_shells=4)
                info = target_information(intr, dense.part_from_cam, part.targets.xyz, dense.visible, opts.sigma_px)
                bd = worst_sigma_lower_bound(info, k, visible=dense.visible, min_rays=min_rays)
                line += f"; over {len(dense.genes)} candidates (4 shells) {bd.lower * 1e6:.2f} um"
            print(line, flush=True)
            if args.like_for_like:
                like_for_like(part, intr, sphere, vis_opts, db, k, min_rays, opts.sigma_px)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
