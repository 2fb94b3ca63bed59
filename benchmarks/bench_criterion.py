"""Network evaluations per second of the planner's criterion on the example part.

Run: .venv/bin/python benchmarks/bench_criterion.py [--targets 1000] [--stations 29] [--population 2000]
Builds the visibility database and the information table (candidates x targets x 6),
then evaluates a population of random networks of ``--stations`` stations three ways,
in the same process: the vectorised population evaluation (float32 table, float64
table) and a naive per-network NumPy loop (gather, sum, np.linalg.inv per network).
Prints evaluations/s, the speed-up over the naive loop, and the float32-vs-float64
difference of the criterion.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from planning.stations import ViewingSphere
from planning.uncertainty import criterion, evaluate_networks, sym_from_6, target_information
from planning.visibility import VisibilityDB, VisibilityOptions

from bench_visibility import example


def naive_worst(info: np.ndarray, visible: np.ndarray, stations: np.ndarray, min_rays: int = 2,
                penalty: float = 1.0) -> np.ndarray:
    """Reference: one network at a time; worst target sigma plus ``penalty`` per insufficient target."""
    out = np.empty(len(stations))
    for p, st in enumerate(stations):
        st = np.unique(st[st >= 0])
        N = sym_from_6(info[st].sum(axis=0).astype(np.float64))
        ok = visible[st].sum(axis=0) >= min_rays
        cov = np.linalg.inv(N[ok])
        sigma = np.sqrt(np.trace(cov, axis1=1, axis2=2))
        out[p] = (sigma.max() if len(sigma) else 0.0) + penalty * np.count_nonzero(~ok)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--targets", type=int, default=1000)
    ap.add_argument("--candidates", type=int, default=3000)
    ap.add_argument("--stations", type=int, default=29)
    ap.add_argument("--population", type=int, default=2000)
    ap.add_argument("--sigma-px", type=float, default=0.1)
    args = ap.parse_args()

    # sample extra targets and keep those that at least two candidates see (the bottom face
    # and pocket floors are never measurable from the sphere above the table)
    part, intr = example(int(args.targets * 1.45))
    sphere = ViewingSphere.for_part(part, intr)
    db = VisibilityDB.build(part, intr, sphere, VisibilityOptions(), n_candidates=args.candidates)
    keep = db.visible.sum(axis=0) >= 2
    xyz, vis = part.targets.xyz[keep], np.ascontiguousarray(db.visible[:, keep])
    t = time.perf_counter()
    info32 = target_information(intr, db.part_from_cam, xyz, vis, args.sigma_px)
    print(f"information table {info32.shape} float32: {time.perf_counter() - t:.2f} s")
    info64_exact = target_information(intr, db.part_from_cam, xyz, vis, args.sigma_px, np.float64)
    m, n = vis.shape
    rng = np.random.default_rng(0)
    stations = np.stack([rng.choice(m, args.stations, replace=False) for _ in range(args.population)])
    p = len(stations)
    print(f"{m} candidates x {n} measurable targets; population {p} networks of {args.stations} stations; 2 threads")

    def timed(fn, repeats=3):
        best = np.inf
        for _ in range(repeats):
            t = time.perf_counter()
            r = fn()
            best = min(best, time.perf_counter() - t)
        return r, best

    evaluate_networks(info32, stations[:50], visible=vis)
    c32, t32 = timed(lambda: criterion(evaluate_networks(info32, stations, visible=vis), "worst", penalty=1.0))
    c64, t64 = timed(lambda: criterion(evaluate_networks(info64_exact, stations, visible=vis), "worst", penalty=1.0))
    _, t32_1 = timed(lambda: criterion(evaluate_networks(info32, stations, visible=vis, workers=1), "worst", penalty=1.0))
    k_naive = min(p, 500)
    cn, tn = timed(lambda: naive_worst(info64_exact, vis, stations[:k_naive]), repeats=2)
    r32, r64, rn = p / t32, p / t64, k_naive / tn
    print(f"vectorised, float32 table, 2 threads: {r32:,.0f} evaluations/s")
    print(f"vectorised, float32 table, 1 thread:  {p / t32_1:,.0f} evaluations/s")
    print(f"vectorised, float64 table, 2 threads: {r64:,.0f} evaluations/s")
    print(f"naive per-network loop (float64):     {rn:,.0f} evaluations/s")
    print(f"speed-up over the naive loop: {r32 / rn:.1f}x (float32), {r64 / rn:.1f}x (float64)")
    print(f"naive and vectorised (float64) criterion: max relative difference {np.max(np.abs(c64[:k_naive] / cn - 1)):.1e}; "
          f"networks with every target sufficient: {np.mean(c64 < 1.0):.1%}")
    # accuracy of float32 against float64 on the sufficient targets, penalised criterion
    ev32 = evaluate_networks(info32, stations, visible=vis)
    ev64 = evaluate_networks(info64_exact, stations, visible=vis)
    both = ev32.sufficient & ev64.sufficient
    rel = np.abs(ev32.sigma[both] / ev64.sigma[both] - 1)
    for kind in ("worst", "mean", "max_axis", "trace"):
        a, b = criterion(ev32, kind, penalty=1.0), criterion(ev64, kind, penalty=1.0)
        print(f"float32 vs float64, criterion {kind!r} (penalised): max relative difference {np.max(np.abs(a / b - 1)):.1e}")
    print(f"float32 vs float64 per-target sigma: median {np.median(rel):.1e}, 99.9% {np.quantile(rel, 0.999):.1e}, "
          f"max {rel.max():.1e}; sufficiency differs on {np.count_nonzero(ev32.sufficient != ev64.sufficient)} "
          f"of {ev32.sufficient.size} target-network pairs")
    print(f"worst-target sigma of the best random network: {np.min(criterion(ev64, 'worst', penalty=1.0)) * 1e6:.1f} um "
          f"(penalised: +1 m per insufficient target)")


if __name__ == "__main__":
    main()
