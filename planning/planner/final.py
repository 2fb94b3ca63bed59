"""After the search: the exact re-evaluation of its networks and the lower bound (planning.bound)."""
from __future__ import annotations

import numpy as np

from calibration.errors import PlanningError
from planning.bound import worst_sigma_lower_bound
from planning.planner.options import PlannerOptions
from planning.planner.problem import _exact
from planning.planner.search import _Found
from planning.planner.setup import _SetUp


def _exact_variants(part, intr, options: PlannerOptions, s: _SetUp, genes: np.ndarray) -> tuple[str, dict, np.ndarray]:
    """Exact evaluation of the continuous stations ``genes: (c, G)`` and of their database
    neighbours (identical to what the search saw); the better one is kept."""
    snapped = s.db.genes[s.problem.snap(genes)[0]]
    variants = {"continuous": (_exact(part, intr, options, s.vis_opts, genes, s.sphere, s.cols), genes)}
    if not np.allclose(snapped, genes):
        variants["snapped"] = (_exact(part, intr, options, s.vis_opts, snapped, s.sphere, s.cols), snapped)
    if options.mode == "cheapest":
        for v, _ in variants.values():
            v["score"] = float(np.max(v["sigma"] / s.required[s.cols]))
    name = min(variants, key=lambda n_: (variants[n_][0]["violation"] + variants[n_][0]["unlinked"],
                                         variants[n_][0]["score"]))
    return name, *variants[name]


def _exact_check(part, intr, options: PlannerOptions, s: _SetUp, found: _Found) -> tuple[str, dict, np.ndarray, float]:
    """The first of the found networks (cheapest: walking up the sizes) that passes the exact check.

    Returns (poses kept: "continuous" | "snapped", its exact evaluation, its genes, its fitness in the search).
    """
    k, cols = options.n_stations, s.cols
    for genes, search_fitness in zip(found.networks, found.search_values):
        kept, final, final_genes = _exact_variants(part, intr, options, s, genes)
        if options.mode == "fixed" and final["violation"] > 0:
            short = int(np.count_nonzero(final["n_rays"][cols] < options.min_rays))
            raise PlanningError(
                f"no network of {k} stations found measures every target with {options.min_rays} rays "
                f"(the best leaves {short} target(s) short): raise [planning] n_stations or lower [planning] min_rays"
            )
        # stations left weakly linked (a part with few targets per face may allow no better): the plan says so
        # (search.exact_unlinked; PLAN warns), the search having preferred every network with fewer
        if options.mode == "fixed" or (final["violation"] == 0 and final["unlinked"] == 0 and final["score"] <= 1.0):
            break
    else:
        raise PlanningError(
            f"the networks found ({', '.join(str(len(g)) for g in found.networks)} stations) met the "
            "required precision on the visibility database but not when re-checked exactly: raise n_candidates "
            "(a finer database) or n_stations"
        )
    return kept, final, final_genes, search_fitness


def _bound_facts(options: PlannerOptions, info: np.ndarray, valid: np.ndarray, vis: np.ndarray,
                 genes: np.ndarray, final: dict, required: np.ndarray | None, cols: np.ndarray, report) -> dict:
    """``search`` entries of the lower bound (planning.bound) for this plan; {} if it does not apply."""
    progress = lambda stage, fraction: report("bound", fraction)  # noqa: E731
    if options.mode == "fixed":
        if options.criterion != "worst":
            return {}
        b = worst_sigma_lower_bound(info, len(genes), valid=valid, visible=vis, min_rays=options.min_rays,
                                    progress=progress)
        worst = float(np.max(final["sigma"]))
        return {"lower_bound_sigma_m": b.lower, "lower_bound_relaxed_m": b.relaxed,
                "plan_over_lower_bound": worst / b.lower, "lower_bound_stopped": b.stopped_because,
                "seconds": b.seconds}
    fewer = len(genes) - 1
    if fewer < options.min_rays or required is None:
        return {}
    # one station fewer: can any network reach sigma / required <= 1?  Stop as soon as it is decided.
    b = worst_sigma_lower_bound(info, fewer, valid=valid, visible=vis, min_rays=options.min_rays,
                                scale=required[cols], stop_above=1.0, stop_below=1.0, progress=progress)
    return {"fewer_stations": fewer, "fewer_stations_lower_bound_ratio": b.lower,
            "fewer_stations_cannot_meet": bool(b.lower > 1.0), "seconds": b.seconds}
