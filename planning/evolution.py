"""The evolutionary engine of the network planner (EPOCA, seed paper section "Evolutionary ...").

Genetic representation (seed Fig. 2): an individual is a network of ``k`` station *slots*;
each slot holds real-coded genes on the viewing sphere, ``genes: (k, G) float``, and a
control bit ``bits: (k,) bool`` that switches the station on or off.  A population is
``genes: (p, k, G)``, ``bits: (p, k)``.

Pure, vectorised kernels (each takes an explicit ``numpy.random.Generator``):

* :func:`sbx_beta`, :func:`sbx_children`, :func:`sbx` -- simulated binary crossover,
  seed eq. (8), children clipped into the bounds (or wrapped for periodic genes).
* :func:`polynomial_delta`, :func:`polynomial_mutation` -- Deb's polynomial mutation.
  Seed eq. (9) as printed has two typos: it reads ``delta = (2u)^(1/(eta+1)-1)`` and
  ``delta = (1 - [2(1-u)])^(1/(eta+1))``.  It transcribes Deb's operator,
  ``delta = (2u)^(1/(eta+1)) - 1`` for ``u < 0.5`` and ``delta = 1 - [2(1-u)]^(1/(eta+1))``
  otherwise, with ``C = P + (P_up - P_low) delta``, which is what
  :func:`polynomial_delta` implements.  :func:`polynomial_mutation` applies the *bounded*
  form Deb uses in NSGA-II (the distribution is truncated at the bounds, so a child is
  always inside them); it equals eq. (9) for a parent one full range away from a bound.
* :func:`bit_flip`, :func:`tournament`, :func:`non_dominated_sort`,
  :func:`crowding_distance`.

The engine :func:`evolve` runs either a generational GA with tournament selection and
elitism (one objective), or, for several objectives (station count vs precision), an
NSGA-II style (mu + lambda) search with constrained non-dominated sorting and crowding.
Constraint handling is the problem's business: ``evaluate`` corrects invalid stations
(Lamarckian: it returns the corrected genes and bits) and returns a constraint violation
(``0`` when feasible); a feasible individual always beats an infeasible one and among
infeasible ones the smaller violation wins (the "predetermined fitness" of the seed,
graded so the search can climb out of infeasibility).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

__all__ = [
    "sbx_beta",
    "sbx_children",
    "sbx",
    "polynomial_delta",
    "polynomial_mutation",
    "bit_flip",
    "tournament",
    "non_dominated_sort",
    "crowding_distance",
    "Evaluation",
    "EvolutionOptions",
    "EvolutionResult",
    "evolve",
]


# --- kernels ------------------------------------------------------------------


def sbx_beta(u: np.ndarray, eta: float) -> np.ndarray:
    """Spread factor of simulated binary crossover, seed eq. (8).

    ``beta = (2u)^(1/(eta+1))`` if ``u < 0.5`` else ``(1 / (2(1-u)))^(1/(eta+1))``.

    Args:
        u: (...) uniform random numbers in [0, 1).
        eta: distribution index (>= 0); large values keep children near their parents.
    Returns:
        beta: (...) float, >= 0.
    """
    u = np.asarray(u, dtype=float)
    e = 1.0 / (eta + 1.0)
    with np.errstate(divide="ignore"):
        return np.where(u < 0.5, (2.0 * u) ** e, (1.0 / (2.0 * (1.0 - u))) ** e)


def sbx_children(p1: np.ndarray, p2: np.ndarray, beta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Children of seed eq. (8): ``C1 = 0.5[(1+b)P1 + (1-b)P2]``, ``C2 = 0.5[(1-b)P1 + (1+b)P2]``.

    All arguments broadcast; returns ``(c1, c2)`` of the broadcast shape.
    """
    c1 = 0.5 * ((1.0 + beta) * p1 + (1.0 - beta) * p2)
    c2 = 0.5 * ((1.0 - beta) * p1 + (1.0 + beta) * p2)
    return c1, c2


def _into_bounds(x: np.ndarray, lower: np.ndarray, upper: np.ndarray, periodic: np.ndarray | None) -> np.ndarray:
    """Clip ``x: (..., d)`` into ``[lower, upper]``; wrap the periodic variables instead."""
    out = np.clip(x, lower, upper)
    if periodic is not None and np.any(periodic):
        span = upper - lower
        wrapped = lower + np.mod(x - lower, np.where(span > 0, span, 1.0))
        out = np.where(periodic, wrapped, out)
    return out


def sbx(
    parents1: np.ndarray,
    parents2: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    eta: float,
    rng: np.random.Generator,
    *,
    prob: float = 0.9,
    prob_var: float = 0.5,
    periodic: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Simulated binary crossover of pairs of parents (seed eq. 8).

    Each pair is crossed with probability ``prob``; within a crossed pair each variable
    is crossed with probability ``prob_var`` (otherwise copied), with its own ``u``.
    Children are clipped into the bounds (periodic variables are wrapped).

    Args:
        parents1, parents2: (p, d) float.
        lower, upper: (d,) bounds.
        eta: distribution index eta_c.
        rng: the random generator.
        periodic: (d,) bool, variables that wrap around (e.g. a full-circle azimuth).
    Returns:
        children1, children2: (p, d) float.
    """
    p1 = np.asarray(parents1, dtype=float)
    p2 = np.asarray(parents2, dtype=float)
    u = rng.random(p1.shape)
    do = (rng.random(p1.shape[0]) < prob)[:, None] & (rng.random(p1.shape) < prob_var)
    beta = sbx_beta(u, eta)
    c1, c2 = sbx_children(p1, p2, beta)
    c1 = np.where(do, c1, p1)
    c2 = np.where(do, c2, p2)
    return _into_bounds(c1, lower, upper, periodic), _into_bounds(c2, lower, upper, periodic)


def polynomial_delta(u: np.ndarray, eta: float) -> np.ndarray:
    """Deb's polynomial mutation step (seed eq. 9, typos corrected), in units of the range.

    ``delta = (2u)^(1/(eta+1)) - 1`` if ``u < 0.5`` else ``1 - (2(1-u))^(1/(eta+1))``,
    so ``delta`` lies in [-1, 1] and the child is ``C = P + (P_up - P_low) delta``.

    Args:
        u: (...) uniform random numbers in [0, 1).
        eta: distribution index eta_m.
    Returns:
        delta: (...) float.
    """
    u = np.asarray(u, dtype=float)
    e = 1.0 / (eta + 1.0)
    return np.where(u < 0.5, (2.0 * u) ** e - 1.0, 1.0 - (2.0 * (1.0 - u)) ** e)


def polynomial_mutation(
    x: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    eta: float,
    prob: float,
    rng: np.random.Generator,
    *,
    periodic: np.ndarray | None = None,
) -> np.ndarray:
    """Polynomial mutation within bounds (Deb's bounded form of seed eq. 9).

    Each variable mutates with probability ``prob``.  With ``d1 = (x - low)/(up - low)``,
    ``d2 = (up - x)/(up - low)``:
    ``dq = (2u + (1-2u)(1-d1)^(eta+1))^(1/(eta+1)) - 1`` for ``u < 0.5``, else
    ``dq = 1 - (2(1-u) + 2(u-0.5)(1-d2)^(eta+1))^(1/(eta+1))``; child ``x + dq (up - low)``.
    The child never leaves ``[low, up]``.  Periodic variables use the unbounded step
    (:func:`polynomial_delta`) and wrap.

    Args:
        x: (p, d) float, inside the bounds.
        lower, upper: (d,) bounds.
    Returns:
        (p, d) float, the mutated copy.
    """
    x = np.asarray(x, dtype=float)
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    span = upper - lower
    safe = np.where(span > 0, span, 1.0)
    u = rng.random(x.shape)
    do = (rng.random(x.shape) < prob) & (span > 0)
    e = 1.0 / (eta + 1.0)
    d1 = np.clip((x - lower) / safe, 0.0, 1.0)
    d2 = np.clip((upper - x) / safe, 0.0, 1.0)
    lo = (2.0 * u + (1.0 - 2.0 * u) * (1.0 - d1) ** (eta + 1.0)) ** e - 1.0
    hi = 1.0 - (2.0 * (1.0 - u) + 2.0 * (u - 0.5) * (1.0 - d2) ** (eta + 1.0)) ** e
    dq = np.where(u < 0.5, lo, hi)
    if periodic is not None and np.any(periodic):
        dq = np.where(periodic, polynomial_delta(u, eta), dq)
    child = np.where(do, x + dq * span, x)
    return _into_bounds(child, lower, upper, periodic)


def bit_flip(bits: np.ndarray, prob: float, rng: np.random.Generator) -> np.ndarray:
    """Flip each control bit ``bits: (...) bool`` with probability ``prob``; returns a copy."""
    bits = np.asarray(bits, dtype=bool)
    return bits ^ (rng.random(bits.shape) < prob)


def tournament(rank: np.ndarray, n_select: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Tournament selection: ``n_select`` winners of ``size`` random contestants each.

    Args:
        rank: (p,) float, smaller is better (ties go to the first drawn contestant).
    Returns:
        (n_select,) int indices into ``rank``.
    """
    rank = np.asarray(rank)
    contestants = rng.integers(0, rank.shape[0], size=(n_select, max(1, int(size))))
    winner = np.argmin(rank[contestants], axis=1)
    return contestants[np.arange(n_select), winner]


def non_dominated_sort(objectives: np.ndarray, violation: np.ndarray | None = None) -> np.ndarray:
    """Front index of every individual under (constrained) Pareto dominance, minimising.

    ``a`` dominates ``b`` if it is no worse in every objective and better in one.  With
    ``violation``, Deb's constrained dominance: a feasible individual (violation 0)
    dominates every infeasible one, and an infeasible one dominates another with a
    larger violation.

    Args:
        objectives: (p, m) float.
        violation: (p,) float >= 0, or None.
    Returns:
        rank: (p,) int, 0 for the first (non-dominated) front.
    """
    F = np.asarray(objectives, dtype=float)
    p = F.shape[0]
    le = np.all(F[:, None, :] <= F[None, :, :], axis=2)
    lt = np.any(F[:, None, :] < F[None, :, :], axis=2)
    dom = le & lt  # dom[i, j]: i dominates j
    if violation is not None:
        v = np.asarray(violation, dtype=float)
        feas = v <= 0
        both_feas = feas[:, None] & feas[None, :]
        dom = np.where(both_feas, dom, (v[:, None] < v[None, :]))
    rank = np.full(p, -1, dtype=int)
    n_dominators = dom.sum(axis=0)
    current = np.flatnonzero(n_dominators == 0)
    r = 0
    while current.size:
        rank[current] = r
        n_dominators = n_dominators - dom[current].sum(axis=0)
        n_dominators[rank >= 0] = -1
        current = np.flatnonzero(n_dominators == 0)
        r += 1
    return rank


def crowding_distance(objectives: np.ndarray, rank: np.ndarray) -> np.ndarray:
    """NSGA-II crowding distance within each front; boundary points get ``inf``.

    Args:
        objectives: (p, m) float; rank: (p,) int front index.
    Returns:
        (p,) float, larger means less crowded.
    """
    F = np.asarray(objectives, dtype=float)
    out = np.zeros(F.shape[0])
    for r in np.unique(rank):
        idx = np.flatnonzero(rank == r)
        if idx.size <= 2:
            out[idx] = np.inf
            continue
        for j in range(F.shape[1]):
            f = F[idx, j]
            order = np.argsort(f, kind="stable")
            fs = f[order]
            d = np.zeros(idx.size)
            d[0] = d[-1] = np.inf
            if np.all(np.isfinite(fs)) and fs[-1] > fs[0]:
                d[1:-1] = (fs[2:] - fs[:-2]) / (fs[-1] - fs[0])
            out[idx[order]] += d
    return out


# --- engine -------------------------------------------------------------------


@dataclass
class Evaluation:
    """What a problem returns for a population of ``p`` individuals of ``k`` slots.

    Attributes:
        objectives: (p, m) float, minimised (m = 1: the fitness).
        violation: (p,) float, 0 when feasible, > 0 measures how infeasible.
        genes: (p, k, G) the genes after correction of invalid stations.
        bits: (p, k) bool the control bits after correction.
    """

    objectives: np.ndarray
    violation: np.ndarray
    genes: np.ndarray
    bits: np.ndarray


class EvaluateFn(Protocol):
    def __call__(self, genes: np.ndarray, bits: np.ndarray) -> Evaluation: ...


@dataclass
class EvolutionOptions:
    """Options of the search (defaults suit ~30 stations on a few thousand candidates).

    Attributes:
        population: individuals per generation.
        generations: hard limit on generations.
        stall_generations: stop when the best (or the Pareto front) has not improved
            by more than ``stall_rel_tol`` for this many generations.
        time_limit_s: stop after this wall time (None: no limit).
        eta_c: SBX distribution index; eta_m: mutation distribution index.
        p_crossover: probability that a pair is crossed; p_crossover_var: per variable.
        p_mutation: per-gene mutation probability (None: 1 / genes per station / slots * 2).
        p_bit_flip: per-slot control-bit flip probability (ignored with ``fix_bits``).
        tournament_size: contestants per tournament.
        n_elite: best individuals copied unchanged into the next generation (one objective).
        fix_bits: keep every control bit on (a network of exactly ``k`` stations).
        align_gene: before crossover, order each individual's slots by this gene (e.g.
            azimuth) so that slot i of two parents are neighbours on the sphere (None: off).
        plus_selection: one objective: parents and children compete for survival
            ((mu + lambda), elitist by construction) instead of the generational
            replacement with ``n_elite`` elites.
        p_reset: per-slot probability that a child's station is redrawn uniformly within
            the bounds (random-reset mutation: long jumps that polynomial mutation with a
            large eta_m rarely makes).
    """

    population: int = 80
    generations: int = 150
    stall_generations: int = 30
    stall_rel_tol: float = 1e-4
    time_limit_s: float | None = None
    eta_c: float = 15.0
    eta_m: float = 20.0
    p_crossover: float = 0.9
    p_crossover_var: float = 0.5
    p_mutation: float | None = None
    p_bit_flip: float | None = None
    tournament_size: int = 2
    n_elite: int = 2
    fix_bits: bool = False
    align_gene: int | None = 0
    p_reset: float = 0.0
    plus_selection: bool = False


@dataclass
class EvolutionResult:
    """Outcome of :func:`evolve`.

    Attributes:
        genes: (P, k, G), bits: (P, k), objectives: (P, m), violation: (P,): the final
            population, best first (one objective) or first front first (several).
        rank: (P,) front index (one objective: order of merit).
        history: one dict per generation (generation, best, mean, n_active, n_feasible,
            elapsed_s, and for several objectives front_size).
        stopped_because: "generations" | "stall" | "time".
        n_evaluations: individuals evaluated.
    """

    genes: np.ndarray
    bits: np.ndarray
    objectives: np.ndarray
    violation: np.ndarray
    rank: np.ndarray
    history: list[dict] = field(default_factory=list)
    stopped_because: str = "generations"
    n_evaluations: int = 0

    @property
    def best_genes(self) -> np.ndarray:
        """(k, G) genes of the best individual (single objective)."""
        return self.genes[0]

    @property
    def best_bits(self) -> np.ndarray:
        return self.bits[0]

    def pareto_front(self) -> np.ndarray:
        """Indices of the feasible first-front individuals, (f,) int."""
        return np.flatnonzero((self.rank == 0) & (self.violation <= 0))


def _merit_order(objectives: np.ndarray, violation: np.ndarray) -> np.ndarray:
    """Order (best first) for one objective: feasible by fitness, then by violation."""
    return np.lexsort((objectives[:, 0], violation))


def _align(genes: np.ndarray, bits: np.ndarray, gene: int | None) -> tuple[np.ndarray, np.ndarray]:
    if gene is None:
        return genes, bits
    order = np.argsort(genes[:, :, gene], axis=1, kind="stable")
    return np.take_along_axis(genes, order[:, :, None], axis=1), np.take_along_axis(bits, order, axis=1)


def _offspring(
    genes: np.ndarray,
    bits: np.ndarray,
    parents: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    periodic: np.ndarray | None,
    opt: EvolutionOptions,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Children of consecutive pairs in ``parents: (2q,)``; returns genes (2q,k,G), bits (2q,k)."""
    _, k, G = genes.shape
    a, b = parents[0::2], parents[1::2]
    lo, hi = np.tile(lower, k), np.tile(upper, k)
    per = None if periodic is None else np.tile(periodic, k)
    c1, c2 = sbx(
        genes[a].reshape(len(a), k * G), genes[b].reshape(len(b), k * G), lo, hi, opt.eta_c, rng,
        prob=opt.p_crossover, prob_var=opt.p_crossover_var, periodic=per,
    )
    swap = rng.random((len(a), k)) < 0.5
    b1 = np.where(swap, bits[b], bits[a])
    b2 = np.where(swap, bits[a], bits[b])
    child_genes = np.concatenate([c1, c2]).reshape(2 * len(a), k * G)
    child_bits = np.concatenate([b1, b2])
    pm = opt.p_mutation if opt.p_mutation is not None else min(1.0, 2.0 / (k * G))
    child_genes = polynomial_mutation(child_genes, lo, hi, opt.eta_m, pm, rng, periodic=per)
    if opt.p_reset > 0:
        g = child_genes.reshape(-1, k, G)
        reset = rng.random((g.shape[0], k)) < opt.p_reset
        g[reset] = rng.uniform(lower, upper, size=(int(reset.sum()), G))
        child_genes = g.reshape(-1, k * G)
    if opt.fix_bits:
        child_bits = np.ones_like(child_bits)
    else:
        pb = opt.p_bit_flip if opt.p_bit_flip is not None else 1.0 / k
        child_bits = bit_flip(child_bits, pb, rng)
    return child_genes.reshape(-1, k, G), child_bits


def evolve(
    evaluate: EvaluateFn,
    lower: np.ndarray,
    upper: np.ndarray,
    init_genes: np.ndarray,
    init_bits: np.ndarray,
    options: EvolutionOptions,
    rng: np.random.Generator,
    *,
    periodic: np.ndarray | None = None,
    progress: Callable[[float, dict], None] | None = None,
) -> EvolutionResult:
    """Run the search from an initial population.

    Args:
        evaluate: maps ``genes (p, k, G), bits (p, k)`` to an :class:`Evaluation`.
        lower, upper: (G,) bounds of one station's genes.
        init_genes: (P, k, G) initial population (P = options.population);
        init_bits: (P, k) bool.
        options: :class:`EvolutionOptions`.
        rng: the only source of randomness.
        periodic: (G,) bool genes that wrap around.
        progress: called as ``progress(fraction, history_row)`` after each generation.
    Returns:
        :class:`EvolutionResult`; the population is sorted best first.
    """
    opt = options
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    genes = np.asarray(init_genes, dtype=float).copy()
    bits = np.asarray(init_bits, dtype=bool).copy()
    if opt.fix_bits:
        bits[:] = True
    P = genes.shape[0]
    ev = evaluate(genes, bits)
    n_eval = P
    genes, bits, F, V = ev.genes, ev.bits, ev.objectives, ev.violation
    multi = F.shape[1] > 1
    t0 = time.perf_counter()
    history: list[dict] = []
    best_so_far: dict[int, float] | float = {} if multi else np.inf
    stall = 0
    stopped = "generations"

    for gen in range(opt.generations + 1):
        # rank the current population, best first
        if multi:
            rank = non_dominated_sort(F, V)
            crowd = crowding_distance(F, rank)
            order = np.lexsort((-crowd, rank))
        else:
            order = _merit_order(F, V)
            rank = np.empty(P)
            rank[order] = np.arange(P)
            crowd = np.zeros(P)
        genes, bits, F, V, rank, crowd = genes[order], bits[order], F[order], V[order], rank[order], crowd[order]

        feas = V <= 0
        improved = False
        if multi:
            front = feas & (rank == 0)
            for n_act, f in zip(F[front, 0], F[front, 1]):
                key = int(round(n_act))
                old = best_so_far.get(key, np.inf)
                if f < old * (1.0 - opt.stall_rel_tol) or (not np.isfinite(old) and np.isfinite(f)):
                    improved = True
                    best_so_far[key] = f
            row = {"front_size": int(front.sum()), "best": float(np.min(F[front, 1])) if front.any() else float("nan")}
        else:
            best = float(F[0, 0]) if feas[0] else float("inf")
            if best < best_so_far * (1.0 - opt.stall_rel_tol) or (np.isinf(best_so_far) and np.isfinite(best)):
                improved = True
                best_so_far = best
            row = {"best": best}
        stall = 0 if improved else stall + 1
        fit = F[:, -1]
        row.update(
            generation=gen,
            mean=float(np.mean(fit[feas])) if feas.any() else float("nan"),
            n_active=int(bits[0].sum()),
            n_feasible=int(feas.sum()),
            violation_min=float(V.min()),
            elapsed_s=time.perf_counter() - t0,
        )
        history.append(row)
        if progress is not None:
            progress(min(1.0, (gen + 1) / (opt.generations + 1)), row)
        if gen == opt.generations:
            stopped = "generations"
            break
        if stall >= opt.stall_generations:
            stopped = "stall"
            break
        if opt.time_limit_s is not None and row["elapsed_s"] >= opt.time_limit_s:
            stopped = "time"
            break

        # variation
        # smaller is better; within a front, less crowded first (inf crowding -> +0)
        merit = rank.astype(float) + (0.5 / (1.0 + crowd) if multi else 0.0)
        n_children = P if (multi or opt.plus_selection) else P - opt.n_elite
        n_pairs = (n_children + 1) // 2
        parents = tournament(merit, 2 * n_pairs, opt.tournament_size, rng)
        ag, ab = _align(genes, bits, opt.align_gene)
        cg, cb = _offspring(ag, ab, parents, lower, upper, periodic, opt, rng)
        cg, cb = cg[:n_children], cb[:n_children]
        cev = evaluate(cg, cb)
        n_eval += n_children
        if multi:  # (mu + lambda): parents and children compete
            genes = np.concatenate([genes, cev.genes])
            bits = np.concatenate([bits, cev.bits])
            F = np.concatenate([F, cev.objectives])
            V = np.concatenate([V, cev.violation])
            r = non_dominated_sort(F, V)
            c = crowding_distance(F, r)
            keep = np.lexsort((-c, r))[:P]
            genes, bits, F, V = genes[keep], bits[keep], F[keep], V[keep]
        elif opt.plus_selection:  # (mu + lambda) on one objective
            genes = np.concatenate([genes, cev.genes])
            bits = np.concatenate([bits, cev.bits])
            F = np.concatenate([F, cev.objectives])
            V = np.concatenate([V, cev.violation])
            keep = _merit_order(F, V)[:P]
            genes, bits, F, V = genes[keep], bits[keep], F[keep], V[keep]
        else:  # generational with elitism
            e = opt.n_elite
            genes = np.concatenate([genes[:e], cev.genes])
            bits = np.concatenate([bits[:e], cev.bits])
            F = np.concatenate([F[:e], cev.objectives])
            V = np.concatenate([V[:e], cev.violation])

    return EvolutionResult(
        genes=genes, bits=bits, objectives=F, violation=V, rank=np.asarray(rank),
        history=history, stopped_because=stopped, n_evaluations=n_eval,
    )
