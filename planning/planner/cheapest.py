"""The "cheapest" search: the Pareto front of station count versus precision, then fixed-size
searches for one station fewer while they succeed."""
from __future__ import annotations

import math

import numpy as np

from calibration.errors import PlanningError
from planning.planner.search import _Found, _Search, _feasible_ratio


def _search_cheapest(search: _Search) -> _Found:
    """Candidate networks meeting the requirement, fewest stations first (see :mod:`planning.planner`)."""
    options, rng = search.options, search.rng
    k = options.n_stations
    res = search.run(k, "cheapest", "count_ratio", "search")
    front: dict[int, tuple[float, np.ndarray]] = {}
    for i in res.pareto_front():
        c, f = int(res.objectives[i, 0]), float(res.objectives[i, 1])
        if c not in front or f < front[c][0]:
            front[c] = (f, res.genes[i][res.bits[i]])
    pareto = [{"n_stations": c, "sigma_ratio_max": f, "phase": "front"} for c, (f, _) in sorted(front.items())]
    meets = sorted(c for c, (f, _) in front.items() if f <= 1.0)
    best: tuple[int, np.ndarray, float] | None = (meets[0], front[meets[0]][1], front[meets[0]][0]) if meets else None
    if best is None:  # the front falls short: the strongest search at the largest size decides
        seeds = [front[max(front)][1]] if front and max(front) == k else []
        r = search.run(k, "fixed", "ratio", f"refine {k}", seeds)
        pareto.append({"n_stations": k, "sigma_ratio_max": _feasible_ratio(r), "phase": "refine"})
        if _feasible_ratio(r) <= 1.0:
            best = (k, r.genes[0], _feasible_ratio(r))
    if best is None:
        top = min(pareto, key=lambda row: row["sigma_ratio_max"], default=None)
        raise PlanningError(
            f"no network of at most {k} stations reaches the required precision"
            + (f" (best: sigma/required = {top['sigma_ratio_max']:.2f} with {top['n_stations']} stations)"
               if top and math.isfinite(top["sigma_ratio_max"]) else "")
            + ": raise [planning] max_stations, relax [planning] required_sigma (or the tolerances), or use a camera "
              "with smaller image noise ([camera] sigma_px)"
        )
    # refine: a fixed-size search (seeded with the front) for one station fewer, while it succeeds
    for _ in range(options.cheapest_refine):
        c = best[0] - 1
        if c < options.min_rays:
            break
        drop = best[1][np.argsort(rng.random(best[0]))[:c]]
        seeds = ([front[c][1]] if c in front else []) + [drop]
        r = search.run(c, "fixed", "ratio", f"refine {c}", seeds)
        pareto.append({"n_stations": c, "sigma_ratio_max": _feasible_ratio(r), "phase": "refine"})
        if _feasible_ratio(r) > 1.0:
            break
        best = (c, r.genes[0], _feasible_ratio(r))
    networks = [best[1]] + [front[c][1] for c in meets if c > best[0]]
    search_values = [best[2]] + [front[c][0] for c in meets if c > best[0]]
    return _Found(res, networks, search_values, pareto)
