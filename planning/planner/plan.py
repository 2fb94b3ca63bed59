"""The planner's entry points: :func:`plan_network` (set-up, search, exact check, the plan) and
:func:`cheapest_network`."""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from calibration.camera import Intrinsics
from planning.planner.cheapest import _search_cheapest
from planning.planner.final import _bound_facts, _exact_check
from planning.planner.ladder import ladder_sizes, search_ladder
from planning.planner.options import PlannerOptions, Progress
from planning.planner.result import NetworkPlan
from planning.planner.search import _Search, _search_fixed
from planning.planner.setup import _set_up
from planning.scalebar import covariance_with, finish_doc, secure_scale_bar
from planning.visibility import VisibilityDB


def plan_network(
    part,
    intr: Intrinsics,
    options: PlannerOptions,
    rng: np.random.Generator | None = None,
    reachable: np.ndarray | None = None,
    cache_dir=None,
    progress: Progress | None = None,
    *,
    seed: int | None = None,
    db: VisibilityDB | None = None,
    reachable_fn=None,
) -> NetworkPlan:
    """Design a network (see :mod:`planning.planner`); the same inputs and seed give the same plan.

    Args:
        part: planning.part.Part (mesh, targets with xyz, normals, ids, tolerance_m).
        intr: the camera.
        options: :class:`PlannerOptions` (``mode`` chooses fixed size or cheapest).
        rng: the search's generator; None: ``numpy.random.default_rng(seed)``.
        reachable: (m,) bool aligned with the visibility database's candidates, or None.
        reachable_fn: ``part_from_cam (p, 4, 4) -> (p,) bool`` for poses off the database (the
            exact local polish, ``polish_rounds``); with ``reachable`` but without it the polish is
            skipped, since its poses' reachability would be unknown.
        cache_dir: where the visibility database is cached (None: default cache).
        progress: called as ``progress(stage, fraction)``.
        seed: recorded in the plan (and used when ``rng`` is None).
        db: a visibility database already built for this part, camera and options.
    Returns:
        :class:`NetworkPlan`.
    Raises:
        InputError: bad options.  PlanningError: no valid station, targets that cannot be
        measured by ``min_rays`` stations, or (cheapest) no network reaches the precision.
    """
    options.check()
    if rng is None:
        rng = np.random.default_rng(seed)
    report = progress or (lambda stage, fraction: None)
    timing: dict[str, float] = {}
    t_all = time.perf_counter()
    s = _set_up(part, intr, options, reachable, cache_dir, report, db, timing)

    t0 = time.perf_counter()
    search = _Search(s, options, rng, report)
    if options.mode == "fixed" and options.criterion == "worst" and len(ladder_sizes(options.n_stations,
                                                                                     options.ladder_base)) > 1:
        found = search_ladder(search, part, intr, reachable, reachable_fn)
    elif options.mode == "fixed":
        found = _search_fixed(search, part, intr, reachable, reachable_fn)
    else:
        found = _search_cheapest(search)
    timing["search_s"] = time.perf_counter() - t0
    if "polish_s" in found.polish_stats:  # part of search_s
        timing["polish_s"] = found.polish_stats.pop("polish_s")

    t0 = time.perf_counter()
    kept, final, final_genes, search_fitness = _exact_check(part, intr, options, s, found)
    report("final", 1.0)
    timing["final_s"] = time.perf_counter() - t0
    bound_facts = _bound_facts(options, s.info, s.valid, s.vis, final_genes, final, s.required, s.cols, report) \
        if options.lower_bound else {}
    if bound_facts:
        timing["bound_s"] = bound_facts.pop("seconds")
    timing["total_s"] = time.perf_counter() - t_all

    m, n = s.db.visible.shape
    cols, ids, res, pareto, refine_stats = s.cols, s.ids, found.res, found.pareto, search.refine_stats
    order = np.lexsort((final_genes[:, 2], final_genes[:, 1], final_genes[:, 0]))
    T, final_genes, visible = final["T"][order], final_genes[order], final["visible"][order]
    station_ids = [f"S{i + 1:03d}" for i in range(len(order))]
    cov, n_rays = final["cov"], final["n_rays"]
    bar_docs: list[dict] = []
    if options.scale_bars:  # the scale bars' ends: stations added after the search's (planning.scalebar)
        t0 = time.perf_counter()
        added_ids: list[list[str]] = []
        for bar in options.scale_bars:  # bar after bar: a station added for one bar counts for the next
            added, doc = secure_scale_bar(part, intr, options, s.db, s.valid, T, visible, cov, s.cols, bar)
            new_ids = [f"S{len(station_ids) + i + 1:03d}" for i in range(len(added))]
            if len(added):
                T = np.concatenate([T, s.db.part_from_cam[added]])
                final_genes = np.concatenate([final_genes, s.db.genes[added]])
                visible, cov, n_rays = covariance_with(intr, options, part, T)
                station_ids = station_ids + new_ids
            bar_docs.append(doc)
            added_ids.append(new_ids)
        # each bar judged on the final network (the stations added for the bars after it count too)
        bar_docs = [finish_doc(d, part, intr, options, T, visible, station_ids, a) for d, a in zip(bar_docs, added_ids)]
        timing["scale_bar_s"] = time.perf_counter() - t0
        timing["total_s"] += timing["scale_bar_s"]
    sig = np.sqrt(np.trace(cov, axis1=1, axis2=2))
    sig_cols = sig[cols]
    finite = np.isfinite(sig_cols)
    return NetworkPlan(
        seed=seed,
        criterion=options.criterion,
        mode=options.mode,
        intrinsics=intr,
        sigma_px=float(options.sigma_px),
        min_rays=int(options.min_rays),
        incidence_max_rad=float(options.incidence_max_rad),
        station_ids=station_ids,
        part_from_cam=T,
        genes=final_genes,
        target_ids=ids,
        xyz=s.xyz.copy(),
        normals=np.asarray(part.targets.normals, dtype=float).copy(),
        cov=cov,
        n_rays=n_rays,
        seen_by=[[station_ids[i] for i in np.flatnonzero(visible[:, j])] for j in range(n)],
        predicted_sigma_max_m=float(np.max(sig_cols)) if finite.all() else float("inf"),
        predicted_sigma_mean_m=float(np.mean(sig_cols)) if finite.all() else float("inf"),
        history=search.history,
        pareto_front=pareto,
        required_sigma_m=s.required,
        unmeasurable_target_ids=[ids[j] for j in np.flatnonzero(~s.measurable)],
        timing=timing,
        scale_bars=bar_docs,
        search={
            "stopped_because": res.stopped_because,
            "generations": len(res.history) - 1,
            "refine_runs": sum(1 for row in pareto if row.get("phase") == "refine"),
            **({"exchange_swaps": sum(x["swaps"] for x in refine_stats),
                "exchange_from": refine_stats[0]["from"], "exchange_to": refine_stats[0]["to"]} if refine_stats else {}),
            **found.polish_stats,
            "image_precision": _precision_name(options),
            "n_evaluations": search.n_evaluations,
            "n_candidates": int(m),
            "n_valid_candidates": int(s.valid.sum()),
            "visibility_key": s.db.key,
            "visibility_from_cache": bool(s.db.from_cache),
            "poses_kept": kept,
            "search_fitness": search_fitness,
            "exact_fitness": final["score"],
            "exact_violation": final["violation"],
            "exact_unlinked": final["unlinked"],
            "link_targets": options.link_targets,
            "sole_links": options.sole_links,
            **bound_facts,
        },
    )


def cheapest_network(
    part,
    intr: Intrinsics,
    options: PlannerOptions,
    rng: np.random.Generator | None = None,
    reachable: np.ndarray | None = None,
    cache_dir=None,
    progress: Progress | None = None,
    **kwargs,
) -> NetworkPlan:
    """The fewest stations (at most ``options.n_stations``) meeting the required precision."""
    return plan_network(part, intr, replace(options, mode="cheapest"), rng, reachable, cache_dir, progress, **kwargs)


def _precision_name(options: PlannerOptions) -> str:
    """What the search weighted each ray by (plan.json ``search.image_precision``)."""
    if options.image_precision is None:
        return f"one image sigma, {options.sigma_px:g} px"
    m = options.image_precision.detector_model()
    return (f"detector model version {m.version} per ray (incidence, dot size; held inside the measured range), "
            f"noise scale {options.image_precision.noise_scale:g}")
