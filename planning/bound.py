"""A lower bound on the worst-target sigma that any network of ``k`` stations can reach.

The planner's search (evolution, exchange descent, polish) gives a good network but says
nothing about how far it is from the best one.  This module answers that on the planner's own
model (limiting error propagation over the visibility database's candidates):

    minimise over x in {0, 1}^m:   max_t  f_t(x),   f_t(x) = trace((sum_i x_i N_ti)^-1) / r_t^2
    subject to  sum_i x_i <= k,   sum_i x_i V_ti >= min_rays  (every target measured)

with ``N_ti`` the information (3x3, ``J^T J / sigma^2``) that candidate ``i`` gives target
``t``, ``V`` the visibility and ``r_t`` an optional scale (the required sigma, for the
tolerance-driven criterion).  ``f_t`` is convex in ``x`` (the trace of the inverse is convex
on positive definite matrices and ``N(x)`` is linear), so relaxing ``x`` to ``[0, 1]`` gives
a convex problem whose optimum is a lower bound on the integer one.  It is solved by
Kelley's cutting planes: at each point ``x_j`` the tangent ``f_t(x_j) + g_t(x_j).(x - x_j)``
(``g_ti = -<N_ti, C_t^2>``, ``C_t = N_t(x_j)^-1``) under-estimates ``f_t`` everywhere, so the
value of every cutting-plane LP (HiGHS) is itself a valid lower bound, and the worst target
of the LP's fractional network is an upper end of the relaxation's gap.

What the bound covers: networks whose stations are the database's candidates (the ones
``valid`` allows), scored by the planner's criterion.  The planner's polish moves stations
off the database (continuous position, look-at offset), so for those it is a bound on the
model of a dense sampling of the sphere, not a proof; ``benchmarks/bench_planner.py`` shows
how it moves with a denser database.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.optimize import linprog

from calibration.errors import PlanningError
from planning.sparse_info import SparseInfo
from planning.uncertainty import _IU, sym_from_6

# Frobenius weights of the unique entries (00, 01, 02, 11, 12, 22) of a symmetric 3x3
_FROB6 = np.array([1.0, 2.0, 2.0, 1.0, 2.0, 1.0])


@dataclass
class SigmaBound:
    """Result of :func:`worst_sigma_lower_bound` (sigmas in metres, or in units of ``scale``).

    Attributes:
        lower: no network of ``k`` stations (database candidates) has its worst target below this.
        relaxed: worst target of the best fractional network found (the relaxation's optimum
            lies between ``lower`` and ``relaxed``).
        weights: (m,) that fractional network (station weights in [0, 1]).
        iterations, n_cuts: cutting-plane iterations and cuts used.
        stopped_because: "converged", "above" / "below" (a threshold was decided), "iterations",
            or "infeasible" (no k stations, even fractional, give every target ``min_rays`` rays:
            ``lower`` is inf).
        seconds: wall time.
    """

    lower: float
    relaxed: float
    weights: np.ndarray
    iterations: int
    n_cuts: int
    stopped_because: str
    seconds: float

    @property
    def converged(self) -> bool:
        return self.stopped_because == "converged"


def _trace_inverse(N6: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``trace(N^-1)`` (inf where singular) and ``N^-2`` as 6-vectors, for ``N6: (n, 6)``."""
    N = sym_from_6(np.asarray(N6, dtype=np.float64))
    tr = np.trace(N, axis1=-2, axis2=-1)
    s = np.where(tr > 0, tr / 3.0, 1.0)
    Ns = N / s[:, None, None]
    ok = np.linalg.det(Ns) > 1e-12
    C = np.zeros_like(N)
    C[ok] = np.linalg.inv(Ns[ok]) / s[ok, None, None]
    f = np.where(ok, np.trace(C, axis1=-2, axis2=-1), np.inf)
    C2 = np.einsum("tab,tbc->tac", C, C)[:, _IU[0], _IU[1]]
    return f, C2


def worst_sigma_lower_bound(
    info: np.ndarray,
    k: float,
    *,
    valid: np.ndarray | None = None,
    visible: np.ndarray | None = None,
    min_rays: int = 0,
    targets: np.ndarray | None = None,
    scale: np.ndarray | None = None,
    rel_tol: float = 1e-3,
    max_iterations: int = 200,
    cuts_per_iteration: int = 300,
    stop_above: float | None = None,
    stop_below: float | None = None,
    progress=None,
) -> SigmaBound:
    """Lower bound on the worst target's sigma over all networks of ``k`` candidates.

    Args:
        info: (m, n, 6) per candidate x target information (``target_information``), 1/m^2.
        k: number of stations.
        valid: (m,) bool, candidates allowed (reachable, seeing something); None: all.
        visible: (m, n) bool; with ``min_rays`` the constraint that every target (all n, not
            only ``targets``) is measured ``min_rays`` times.  Omit for no such constraint.
        targets: (n,) bool or indices: the targets whose worst is bounded (None: all).
        scale: (n,) per-target divisor of sigma (e.g. the required sigma); None: 1.
        rel_tol: stop when (relaxed - lower) / lower < rel_tol.
        stop_above / stop_below: stop as soon as the bound proves ``lower > stop_above``, or
            the fractional network shows the relaxation cannot prove more than ``stop_below``.
        progress: ``progress(stage, fraction)`` (optional).
    Returns:
        :class:`SigmaBound` (sigma units: metres / ``scale``).
    Raises:
        PlanningError: shapes disagree, no valid candidate, or a bounded target that no
        valid candidate sees with a non-singular geometry.
    """
    t_start = time.perf_counter()
    if not isinstance(info, SparseInfo):
        info = np.asarray(info)
    if info.ndim != 3 or info.shape[2] != 6:
        raise PlanningError(f"worst_sigma_lower_bound: info must be (m, n, 6), got {info.shape}")
    m, n, _ = info.shape
    if not k > 0:
        raise PlanningError(f"worst_sigma_lower_bound: k must be positive, got {k}")
    valid = np.ones(m, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if valid.shape != (m,):
        raise PlanningError(f"worst_sigma_lower_bound: valid has shape {valid.shape}, expected ({m},)")
    cols = np.arange(n) if targets is None else np.asarray(targets)
    if cols.dtype == bool:
        cols = np.flatnonzero(cols)
    sub = info[:, cols] if isinstance(info, SparseInfo) else None  # (m, nt, 6), only the bounded targets
    tr = (sub if sub is not None else info)[:, slice(None) if sub is not None else cols]
    cand = np.flatnonzero(valid & np.any(tr[..., 0] + tr[..., 3] + tr[..., 5] > 0, axis=1))
    del tr
    if cand.size == 0:
        raise PlanningError("worst_sigma_lower_bound: no valid candidate sees a bounded target")
    A_info = np.ascontiguousarray(sub[cand] if sub is not None else info[cand][:, cols], dtype=np.float64)
    del sub  # A_info: (mc, nt, 6)
    mc, nt = A_info.shape[:2]
    r2 = np.ones(nt) if scale is None else np.asarray(scale, dtype=float)[cols] ** 2
    flat = A_info.reshape(mc, nt * 6)

    def evaluate(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f, C2 = _trace_inverse((x @ flat).reshape(nt, 6))
        return f / r2, C2

    # start: all allowed candidates weighted equally (every target's geometry is as good as it can be)
    x0 = np.full(mc, min(1.0, k / mc))
    f0, _ = evaluate(x0)
    if not np.all(np.isfinite(f0)):
        bad = int(np.flatnonzero(~np.isfinite(f0))[0])
        raise PlanningError(f"worst_sigma_lower_bound: target {int(cols[bad])} has no non-singular geometry "
                            "from the valid candidates")
    unit = float(np.max(f0))  # LP unit for s (keeps the LP well scaled)

    cut_rows: list[np.ndarray] = []
    cut_rhs: list[float] = []

    def add_cuts(x: np.ndarray, ts: np.ndarray) -> None:
        f, C2 = evaluate(x)
        g = -np.einsum("itk,tk->it", A_info[:, ts], C2[ts] * _FROB6) / r2[ts]  # (mc, len(ts))
        for j, t in enumerate(ts):
            # f_t(x) + g.(y - x) <= s   ->   g.y - s <= g.x - f_t(x)
            cut_rows.append(np.append(g[:, j], -unit) / unit)
            cut_rhs.append((g[:, j] @ x - f[t]) / unit)

    add_cuts(x0, np.arange(nt))
    A_extra, b_extra = [], []
    if visible is not None and min_rays > 0:
        V = np.asarray(visible, dtype=bool)[cand].T.astype(float)  # (n, mc): every target, not only cols
        need = V.sum(axis=1) > 0
        A_extra.append(sparse.hstack([-sparse.csr_matrix(V[need]), sparse.csr_matrix((int(need.sum()), 1))]))
        b_extra.append(np.full(int(need.sum()), -float(min_rays)))
    A_extra.append(sparse.csr_matrix(np.append(np.ones(mc), 0.0)[None]))  # sum x <= k
    b_extra.append(np.array([float(k)]))
    c = np.zeros(mc + 1)
    c[-1] = 1.0
    bounds = [(0.0, 1.0)] * mc + [(0.0, None)]

    lower, relaxed, best_x, why, it = 0.0, math.inf, x0, "iterations", 0
    for it in range(1, max_iterations + 1):
        A = sparse.vstack([sparse.csr_matrix(np.array(cut_rows))] + A_extra).tocsr()
        b = np.concatenate([np.array(cut_rhs)] + b_extra)
        res = linprog(c, A_ub=A, b_ub=b, bounds=bounds, method="highs")
        if res.status == 2:  # infeasible: not even fractional stations give every target min_rays rays
            return SigmaBound(lower=math.inf, relaxed=math.inf, weights=np.zeros(m), iterations=it,
                              n_cuts=len(cut_rows), stopped_because="infeasible",
                              seconds=time.perf_counter() - t_start)
        if res.status != 0:
            raise PlanningError(f"worst_sigma_lower_bound: the cutting-plane LP failed ({res.message}); "
                                "the coverage constraint may be infeasible for this k")
        x = np.clip(res.x[:mc], 0.0, 1.0)
        lower = max(lower, float(res.x[-1]) * unit)
        f, _ = evaluate(x)
        if not np.all(np.isfinite(f)):
            # singular at this fractional point: cut at a point slightly towards x0 instead (still valid)
            x = 0.99 * x + 0.01 * x0
            f, _ = evaluate(x)
        if float(np.max(f)) < relaxed:
            relaxed, best_x = float(np.max(f)), x
        if progress is not None:
            progress("bound", min(1.0, it / max_iterations))
        if stop_above is not None and lower > stop_above**2:
            why = "above"
            break
        if stop_below is not None and relaxed < stop_below**2:
            why = "below"
            break
        if relaxed - lower <= rel_tol * 2.0 * lower:  # on sigma^2: ~rel_tol on sigma
            why = "converged"
            break
        order = np.argsort(-f)[:cuts_per_iteration]
        order = order[f[order] > lower]
        if order.size == 0:
            why = "converged"
            break
        add_cuts(x, order)
    weights = np.zeros(m)
    weights[cand] = best_x
    return SigmaBound(lower=math.sqrt(lower), relaxed=math.sqrt(relaxed), weights=weights, iterations=it,
                      n_cuts=len(cut_rows), stopped_because=why, seconds=time.perf_counter() - t_start)
