"""More stations never measure worse: large networks grow from the plan of fewer stations.

Adding a station only adds information, so no target's sigma rises when a network grows. A
"fixed" plan of ``k > ladder_base`` stations is therefore built on the ladder ``base, 2 base, 4 base,
..., k``: the base size is searched and polished as any plan (identical to ``plan_network`` with
``n_stations = base`` and the same seed), and each further size adds stations greedily to the
plan of the size below (database candidates, valid and reachable; each addition the one that
lowers the worst target most, evaluated exactly on the hardest targets) and polishes the result
(planning.polish, which never raises the worst). So the plan of ``k`` stations is never worse than
the plans of the ladder's sizes below it, and the expensive evolutionary search runs only at the
base size. (Searching 64 or 128 stations directly gave *worse* plans than 29 on the example part:
issue 21, docs/decisions/0019-scale.md.)
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from planning.planner.final import _exact_variants
from planning.planner.search import _Found, _Search, _search_fixed
from planning.polish import polish
from planning.refine import _sigma6
from planning.uncertainty import target_information
from planning.visibility import compute_visibility


def ladder_sizes(k: int, base: int) -> list[int]:
    """The sizes planned in turn for ``k`` stations: ``[base, 2 base, ..., k]`` (``[k]`` if ``k <= base``)."""
    if base <= 0 or k <= base:
        return [k]
    sizes = [base]
    while 2 * sizes[-1] < k:
        sizes.append(2 * sizes[-1])
    return sizes + [k]


def greedy_additions(N: np.ndarray, cnt: np.ndarray, info: np.ndarray, vis: np.ndarray, pool: np.ndarray,
                     n_add: int, min_rays: int, top: int = 64) -> list[int]:
    """Candidates (from ``pool``) added one at a time, each lowering the worst sigma most.

    ``N: (c, 6)`` float64 normal matrices and ``cnt: (c,)`` rays of the current network per target;
    ``info: (m, c, 6)``, ``vis: (m, c)`` of the candidates. Each step is exact on the ``top`` hardest
    targets: a candidate's new worst is the larger of its worst over them and the next target's
    sigma (which it cannot raise); ties go to the fewest insufficient, then the smallest sum of
    sigmas over the hardest targets.
    """
    N, cnt = N.astype(np.float64).copy(), cnt.astype(np.int64).copy()
    pool = np.asarray(pool, dtype=np.intp).copy()
    chosen: list[int] = []
    for _ in range(n_add):
        if pool.size == 0:
            break
        sig = _sigma6(N, cnt, min_rays)
        order = np.argsort(-sig, kind="stable")
        hard = order[:top]
        rest = float(sig[order[top]]) if len(order) > top else 0.0
        sc = _sigma6(N[hard][None] + info[np.ix_(pool, hard)], cnt[hard][None] + vis[np.ix_(pool, hard)], min_rays)
        inf = ~np.isfinite(sc)
        w = np.maximum(np.where(inf.any(axis=1), np.inf, sc.max(axis=1)), rest)
        j = int(np.lexsort((np.where(inf, 0.0, sc).sum(axis=1), inf.sum(axis=1), w))[0])
        c = int(pool[j])
        chosen.append(c)
        N += info[c]
        cnt += vis[c]
        pool = np.delete(pool, j)
    return chosen


def search_ladder(search: _Search, part, intr, reachable, reachable_fn) -> _Found:
    """The fixed-size search along :func:`ladder_sizes` (module docstring)."""
    options, s = search.options, search.s
    sizes = ladder_sizes(options.n_stations, options.ladder_base)
    base_opts = replace(options, n_stations=sizes[0])
    search.options = base_opts
    try:
        found = _search_fixed(search, part, intr, reachable, reachable_fn)
    finally:
        search.options = options
    # the base as plan_network would keep it (continuous or snapped: the better exactly)
    _, final, genes = _exact_variants(part, intr, base_opts, s, found.networks[0])
    steps = [{"stations": sizes[0], "worst_m": float(np.max(final["sigma"]))}]
    polishing = options.polish_rounds > 0 and (reachable is None or reachable_fn)
    pol_stats = dict(found.polish_stats)
    xyz = s.xyz[s.cols]
    for size in sizes[1:]:
        T = s.sphere.poses(genes)
        vis_cur = compute_visibility(part, intr, T, s.vis_opts, backend=options.backend)[:, s.cols]
        info_cur = target_information(intr, T, xyz, vis_cur, options.image_sigma(s.cols), dtype=np.float64)
        taken = np.zeros(len(s.db.genes), dtype=bool)
        taken[s.db.nearest(genes)] = True
        pool = s.problem.valid_idx[~taken[s.problem.valid_idx]]
        add = greedy_additions(info_cur.sum(axis=0), vis_cur.sum(axis=0), s.info, s.vis, pool, size - len(genes),
                               options.min_rays)
        genes = np.vstack([genes, s.db.genes[add]])
        step = {"stations": size, "added": len(add)}
        if polishing:
            pol = polish(part, intr, s.sphere, s.vis_opts, s.db, genes, s.cols, replace(options, n_stations=size),
                         reachable_fn=reachable_fn)
            genes = pol.genes
            step.update(before_polish_m=pol.start_worst, worst_m=pol.worst, polish_swaps=pol.n_swaps)
            pol_stats["polish_swaps"] = pol_stats.get("polish_swaps", 0) + pol.n_swaps
            pol_stats["polish_poses"] = pol_stats.get("polish_poses", 0) + pol.n_poses
            pol_stats["polish_to"] = pol.worst
        steps.append(step)
    pol_stats["ladder"] = steps
    return _Found(found.res, [genes], [steps[-1].get("worst_m", found.search_values[0])], found.pareto, pol_stats)
