"""The evolutionary search on the database (seeded with rings, refined by exchange descent),
and the fixed-size plan's search (with the exact local polish)."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from planning.evolution import EvolutionResult, evolve
from planning.planner.options import PlannerOptions, Progress
from planning.planner.problem import _Problem
from planning.planner.setup import _SetUp
from planning.polish import polish
from planning.refine import refine_network
from planning.seeding import initial_population, ring_sweep
from planning.sparse_info import SparseInfo
from planning.stations import N_GENES, ViewingSphere


@dataclass
class _Found:
    """What a search found: candidates for the plan, best first, and its records.

    Attributes:
        res: the first evolutionary run's result.
        networks: (c, G) station genes of each candidate network; search_values: their fitness on the database.
        pareto: "cheapest": rows of the Pareto front and of the refining searches.
        polish_stats: the exact polish's summary ("fixed").
    """

    res: EvolutionResult
    networks: list[np.ndarray]
    search_values: list[float]
    pareto: list[dict] = field(default_factory=list)
    polish_stats: dict = field(default_factory=dict)


class _Search:
    """Evolutionary runs on one plan's problem, with their history, refinement statistics and evaluation count."""

    def __init__(self, s: _SetUp, options: PlannerOptions, rng: np.random.Generator, report: Progress):
        self.s, self.options, self.rng, self.report = s, options, rng, report
        self.lower, self.upper = s.sphere.lower, s.sphere.upper
        self.periodic = np.zeros(N_GENES, dtype=bool)
        self.periodic[0] = (self.upper[0] - self.lower[0]) >= 2 * math.pi - 1e-9
        self.history: list[dict] = []
        self.refine_stats: list[dict] = []
        self.n_evaluations = 0

    def run(self, size: int, mode: str, objective: str, phase: str, seeds: list[np.ndarray] = ()) -> EvolutionResult:
        """One evolutionary run; ``seeds`` are (size, G) networks put into the initial population."""
        options, rng, report, problem = self.options, self.rng, self.report, self.s.problem
        P = options.population
        problem.objective = objective
        run_opts = replace(options, n_stations=size, mode=mode)
        g0, b0 = initial_population(problem.valid_idx, problem.vis, self.s.db.genes, size, P, mode, options.min_rays,
                                    rng, options.greedy_fraction)
        if mode == "fixed" and options.ring_seeds > 0:
            seeds = list(seeds) + list(_best_rings(problem, size, self.s.sphere, options.ring_seeds))
        for i, g in enumerate(seeds[: P // 4]):
            g0[P - 1 - i], b0[P - 1 - i] = g, True
        r = evolve(problem, self.lower, self.upper, g0, b0, run_opts.evolution_options(), rng, periodic=self.periodic,
                   progress=lambda f, row: report(phase, f))
        self.n_evaluations += r.n_evaluations
        if options.refine_starts > 0 and mode == "fixed" and (objective == "ratio" or options.criterion == "worst"):
            r, stats = _refine(problem, r, objective, rng)
            self.refine_stats.append({"phase": phase, **stats})
        start = len(self.history)
        self.history.extend({**row, "phase": phase, "step": start + j} for j, row in enumerate(r.history))
        return r


def _feasible_ratio(r: EvolutionResult) -> float:
    return float(r.objectives[0, 0]) if r.violation[0] <= 0 else float("inf")


def _search_fixed(search: _Search, part, intr, reachable: np.ndarray | None, reachable_fn) -> _Found:
    """"fixed": the best network of ``n_stations``, polished exactly when the criterion is the worst target."""
    options, s = search.options, search.s
    res = search.run(options.n_stations, "fixed", "criterion", "search")
    found = _Found(res, [res.genes[0]], [float(res.objectives[0, 0])])
    if options.polish_rounds > 0 and options.criterion == "worst" and (reachable is None or reachable_fn):
        t0 = time.perf_counter()
        pol = polish(part, intr, s.sphere, s.vis_opts, s.db, res.genes[0], s.cols, options, reachable_fn=reachable_fn)
        found.networks = [pol.genes]
        found.polish_stats.update(polish_swaps=pol.n_swaps, polish_from=pol.start_worst, polish_to=pol.worst,
                                  polish_poses=pol.n_poses, polish_s=time.perf_counter() - t0)
    return found


def _best_rings(problem: _Problem, k: int, sphere: ViewingSphere, n: int) -> np.ndarray:
    """The ``n`` best ring networks of ``k`` stations on the database (feasible first); (n, k, G)."""
    rings = ring_sweep(k, sphere)
    ev = problem(rings, np.ones(rings.shape[:2], dtype=bool))
    order = np.lexsort((ev.objectives[:, 0], ev.violation))[:n]
    return ev.genes[order]


def _refine(problem: _Problem, r: EvolutionResult, objective: str,
            rng: np.random.Generator) -> tuple[EvolutionResult, dict]:
    """Exchange descent (planning.refine) from the search's best distinct networks.

    Returns ``r`` with its best individual replaced by the refined network when that is
    better, and a summary (swaps, objective before and after).
    """
    opt = problem.opt
    idx = problem.snap(r.genes)[0]
    starts, seen = [], set()
    for row in idx:  # best first
        key = tuple(sorted(row))
        if len(set(row)) == len(row) and key not in seen:
            seen.add(key)
            starts.append(row)
        if len(starts) == opt.refine_starts:
            break
    before = float(r.objectives[0, 0]) if r.violation[0] <= 0 else float("inf")
    if not starts:
        return r, {"swaps": 0, "from": before, "to": before}
    info = problem.info
    if objective == "ratio":  # sigma / required: the information scaled by required^2
        w = problem.required.astype(np.float32) ** 2
        info = info.scale_targets(w) if isinstance(info, SparseInfo) else info * w[None, :, None]
    res = refine_network(info, problem.vis, problem.valid_idx, np.array(starts), opt.min_rays, rng,
                         n_kicks=opt.refine_kicks)
    stats = {"swaps": res.n_swaps, "from": before, "to": min(before, res.worst)}
    if problem.opt.link_targets > 0 and problem.unlinked(res.stations[None])[0] > \
            problem.unlinked(np.where(r.bits[:1], idx[:1], -1))[0]:
        # the exchange descent ranks by the worst target only: a network with more weakly linked stations than the
        # search's best (ADJUST would drop their images, or a block would hang on one image) is not taken
        stats.update(to=before, unlinked=True)
        return r, stats
    if not res.worst < before:
        return r, stats
    genes, bits = r.genes.copy(), r.bits.copy()
    objectives, violation = r.objectives.copy(), r.violation.copy()
    genes[0], bits[0] = problem.db.genes[res.stations], True
    objectives[0, 0], violation[0] = res.worst, 0.0
    return replace(r, genes=genes, bits=bits, objectives=objectives, violation=violation), stats
