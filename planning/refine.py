"""Local refinement of a network on the visibility database: exchange (1-swap) descent.

The evolutionary search ranks networks by their *worst* target, a max-type objective
whose landscape is flat almost everywhere (only a change that helps the hardest target
changes it).  This module exploits that structure.  For a network of stations ``S``
(candidate indices) with worst sigma ``f``, an exchange replaces one station ``s_i`` by
a candidate ``c`` not in ``S``.  Removing ``s_i`` can only raise the targets' sigmas and
adding ``c`` can only lower them, so:

* the *critical* targets of ``s_i`` are those whose sigma without ``s_i`` is ``>= f``
  (targets left with fewer than ``min_rays`` rays have sigma ``inf`` and are critical);
* an exchange ``(s_i, c)`` can lower the worst only if ``c`` sees *every* critical
  target, and its new worst is the larger of the worst over the non-critical targets
  (known once per ``i``) and the worst over the critical targets with ``c`` added.

A strict step therefore costs one removal per station over all targets plus, per
station, the candidates that see all its critical targets over those targets only: an
exact best-improvement step on the database at a small fraction of the cost of
evaluating every exchange.  (Also tried, and not kept: "plateau" steps that move a station to
a nearby candidate when that keeps the worst and lowers a soft-max of all sigmas; on the
example part, 29 stations x 1000 targets, they cost 2-3x the time for about 1 % lower worst,
less than the same time spent on perturb-and-descend restarts, :func:`refine_network`.)

Pure functions of arrays, no randomness: the result is a deterministic function of the
starting network.  The information may be dense ``(m, n, 6)`` or a :class:`planning.sparse_info.SparseInfo`;
the descent works on its visible pairs only, with compiled kernels (:mod:`planning.kernels`:
the removal sigmas on each station's own targets, candidates dropped as soon as a critical target
reaches the best exchange found, ``N`` and the sigmas updated only on the targets the exchanged
stations see), which make the same choices as the dense NumPy formulation, bit for bit.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from planning import kernels
from planning.sparse_info import SparseInfo
from planning.uncertainty import _DET_MIN

__all__ = ["SwapResult", "network_sigma", "swap_descent"]


def _sigma6(N: np.ndarray, n_rays: np.ndarray, min_rays: int) -> np.ndarray:
    """sqrt(trace(inverse)) of symmetric 3x3 normal matrices ``N: (..., 6)``; (...) float64,
    inf where fewer than ``min_rays`` rays or singular (as planning.uncertainty's inverse)."""
    N = N.astype(np.float64, copy=False)
    a, b, c, d, e, f = (N[..., i] for i in range(6))
    tr = a + d + f
    A = d * f - e * e
    D = a * f - c * c
    F = a * d - b * b
    det = a * A + b * (c * e - b * f) + c * (b * e - c * d)
    s3 = np.where(tr > 0, tr / 3.0, 1.0) ** 3
    ok = (n_rays >= min_rays) & (det > _DET_MIN * s3)
    out = np.full(ok.shape, np.inf)
    np.sqrt(np.divide(A + D + F, det, out=np.zeros_like(det), where=ok), out=out, where=ok)
    return out


def network_sigma(info: np.ndarray, visible: np.ndarray, stations: np.ndarray, min_rays: int) -> np.ndarray:
    """Per-target sigma (m) of one network on the database; (n,) float64, inf where insufficient.

    ``info: (m, n, 6)`` (or SparseInfo), ``visible: (m, n)`` bool, ``stations: (k,)`` distinct int.
    """
    if isinstance(info, SparseInfo):
        N, cnt = kernels.network_normal(info.starts, info.ends, info.indices, info.data,
                                        np.asarray(stations, dtype=np.intp), info.shape[1])
        return kernels.sigma6_rows(N, cnt, min_rays)
    N = info[stations].sum(axis=0, dtype=np.float64)
    cnt = visible[stations].sum(axis=0)
    return _sigma6(N, cnt, min_rays)


def as_csr(info, visible: np.ndarray) -> SparseInfo:
    """``info`` as a SparseInfo whose entries are exactly the ``visible`` pairs (the kernels' layout)."""
    if isinstance(info, SparseInfo):
        return info
    return SparseInfo.from_dense(np.asarray(info), visible)


def soft_max(sigma: np.ndarray, scale: float, p: float) -> np.ndarray:
    """``sum_j (sigma_j / scale)^p`` over the last axis; inf entries count as inf."""
    return np.sum((np.asarray(sigma) / scale) ** p, axis=-1)


@dataclass
class SwapResult:
    """Outcome of :func:`swap_descent`.

    Attributes:
        stations: (k,) int the refined network (candidate indices).
        worst: its worst target sigma on the database (m, inf if infeasible);
            start_worst: the starting network's.
        n_swaps: exchanges made; stopped_because: "local optimum" |
            "max_swaps" | "time".
        history: one dict per exchange (swap, kind "strict" | "cover", worst, soft,
            elapsed_s).
    """

    stations: np.ndarray
    worst: float
    start_worst: float
    n_swaps: int
    stopped_because: str
    history: list[dict] = field(default_factory=list)


def _strict_step(sp: SparseInfo, visible, S, N, cnt, sig, worst, pool, min_rays, rel_tol):
    """Best exchange lowering the worst: (new_worst, slot, candidate) or None (planning.kernels.strict_step;
    the removal sigmas on two threads, each a half of the network's entries)."""
    sp_args = (sp.starts, sp.ends, sp.indices, sp.data)
    off = np.concatenate([[0], np.cumsum(sp.ends[S] - sp.starts[S])])
    srm = np.empty(int(off[-1]))
    half = int(np.searchsorted(off, off[-1] / 2))
    parts = [(0, half), (half, len(S))]
    if off[-1] > 200_000 and 0 < half < len(S):
        kernels.in_two(2, lambda a, b: kernels.removal_sigmas(*sp_args, S, N, cnt, min_rays, off, *parts[a], srm))
    else:
        kernels.removal_sigmas(*sp_args, S, N, cnt, min_rays, off, 0, len(S), srm)
    w, i, c = kernels.strict_step(*sp_args, visible, S, N, cnt, sig, worst * (1.0 - rel_tol), pool, min_rays, off, srm)
    return None if i < 0 else (float(w), int(i), int(c))


def _cover_step(vis8, S, N, cnt, pool, min_rays):
    """Infeasible network: the exchange that leaves the fewest short targets (ties: the smaller
    total shortfall); (n_short, slot, candidate) or None if none reduces the shortfall."""
    short_now = np.maximum(min_rays - cnt, 0)
    best = (int(np.count_nonzero(short_now)), int(short_now.sum()), -1, -1)
    for i in range(len(S)):
        ci = cnt - vis8[S[i]]
        need = np.flatnonzero(ci < min_rays)  # only targets left short by the removal can be short after it
        if need.size == 0:
            continue  # (cannot happen while the network is short: removing a station never adds rays)
        c_new = ci[need][None].astype(np.int32) + vis8[np.ix_(pool, need)]
        sh = np.maximum(min_rays - c_new, 0)
        n_short, total = np.count_nonzero(sh, axis=1), sh.sum(axis=1)
        j = int(np.lexsort((total, n_short))[0])
        if (n_short[j], total[j]) < best[:2]:
            best = (int(n_short[j]), int(total[j]), i, int(pool[j]))
    return None if best[2] < 0 else (best[0], best[2], best[3])


def swap_descent(
    info: np.ndarray,
    visible: np.ndarray,
    allowed: np.ndarray,
    stations: np.ndarray,
    min_rays: int,
    *,
    max_swaps: int = 200,
    time_limit_s: float | None = None,
    p: float = 8.0,
    rel_tol: float = 1e-6,
) -> SwapResult:
    """Exchange descent on the worst sigma (best-improvement strict steps); see module docstring.

    Args:
        info: (m, n, 6) per-candidate target information (planning.uncertainty).
        visible: (m, n) bool, the visibility ``info`` was built from.
        allowed: (a,) int, the candidates a station may move to (valid and reachable).
        stations: (k,) int, the starting network (distinct candidate indices).
        min_rays: fewest rays per target.
        max_swaps, time_limit_s: stopping criteria besides a local optimum.
        p: exponent of the soft-max recorded in the history (the tie-break of :func:`refine_network`).
        rel_tol: smallest relative lowering of the worst that counts.
    Returns:
        :class:`SwapResult`. The worst never increases. A network that starts infeasible
        is first repaired by exchanges that reduce its shortfall of rays.
    """
    S = np.array(stations, dtype=np.intp)
    allowed = np.unique(np.asarray(allowed, dtype=np.intp))
    t0 = time.perf_counter()
    visible = np.ascontiguousarray(visible, dtype=bool)
    sp = as_csr(info, visible)
    N, cnt = kernels.network_normal(sp.starts, sp.ends, sp.indices, sp.data, S, sp.shape[1])
    sig = kernels.sigma6_rows(N, cnt, min_rays)
    worst = start = float(sig.max())
    history: list[dict] = []
    stopped = "local optimum"
    in_net = np.zeros(visible.shape[0], dtype=bool)
    vis8 = None
    while True:
        if len(history) >= max_swaps:
            stopped = "max_swaps"
            break
        if time_limit_s is not None and time.perf_counter() - t0 >= time_limit_s:
            stopped = "time"
            break
        in_net[:] = False
        in_net[S] = True
        pool = allowed[~in_net[allowed]]
        if pool.size == 0:
            break
        kind, move = "strict", None
        if not np.isfinite(worst):
            vis8 = visible.view(np.uint8) if vis8 is None else vis8
            kind, move = "cover", _cover_step(vis8, S, N, cnt, pool, min_rays)
        else:
            move = _strict_step(sp, visible, S, N, cnt, sig, worst, pool, min_rays, rel_tol)
        if move is None:
            break
        _, i, c = move
        kernels.exchange(sp.starts, sp.ends, sp.indices, sp.data, N, cnt, sig, S[i], c, min_rays)
        S[i] = c
        worst = float(sig.max())
        history.append({"swap": len(history) + 1, "kind": kind, "worst": worst,
                        "soft": float(soft_max(sig, worst, p)) if np.isfinite(worst) else float("inf"),
                        "elapsed_s": time.perf_counter() - t0})
    return SwapResult(stations=S, worst=worst, start_worst=start, n_swaps=len(history), stopped_because=stopped,
                      history=history)


@dataclass
class RefineResult:
    """Outcome of :func:`refine_network`.

    Attributes:
        stations: (k,) int the best network found; worst: its worst sigma on the database (m).
        start_worst: the best starting network's worst (m).
        n_swaps: exchanges made over all descents; n_kicks, n_kicks_accepted: perturbations
            tried and those that led to a better network.
    """

    stations: np.ndarray
    worst: float
    start_worst: float
    n_swaps: int
    n_kicks: int
    n_kicks_accepted: int


def refine_network(
    info: np.ndarray,
    visible: np.ndarray,
    allowed: np.ndarray,
    starts: np.ndarray,
    min_rays: int,
    rng: np.random.Generator,
    *,
    n_kicks: int = 8,
    kick_size: int = 2,
    max_swaps: int = 200,
    p: float = 8.0,
) -> RefineResult:
    """Iterated exchange descent: descend from every start, then perturb-and-descend the best.

    Each start is descended by :func:`swap_descent`; the best result (lexicographic
    (worst, soft-max)) is then kicked ``n_kicks`` times (``kick_size`` of its stations
    redrawn uniformly from ``allowed``, drawn with ``rng``) and re-descended; a kicked
    network replaces the best only if it is better.  Deterministic for a given ``rng``.

    Args:
        starts: (s, k) int starting networks (candidate indices, distinct within a row).
        Others: as :func:`swap_descent`.
    Returns:
        :class:`RefineResult` (its worst is never above the best start's).
    """
    starts = np.atleast_2d(np.asarray(starts, dtype=np.intp))
    allowed = np.unique(np.asarray(allowed, dtype=np.intp))
    kw = dict(max_swaps=max_swaps, p=p)
    visible = np.ascontiguousarray(visible, dtype=bool)
    info = as_csr(info, visible)  # once for every descent

    def key(r: SwapResult) -> tuple[float, float]:
        if not np.isfinite(r.worst):
            return (np.inf, np.inf)
        return (r.worst, float(soft_max(network_sigma(info, visible, r.stations, min_rays), r.worst, p)))

    start_worst = min(float(network_sigma(info, visible, s, min_rays).max()) for s in starts)
    best, best_key, n_swaps = None, (np.inf, np.inf), 0
    for s in starts:
        r = swap_descent(info, visible, allowed, s, min_rays, **kw)
        n_swaps += r.n_swaps
        if best is None or key(r) < best_key:
            best, best_key = r, key(r)
    accepted = 0
    k = starts.shape[1]
    for _ in range(n_kicks):
        S = best.stations.copy()
        slots = rng.choice(k, size=min(kick_size, k), replace=False)
        free = np.setdiff1d(allowed, S)
        if free.size < len(slots):
            break
        S[slots] = rng.choice(free, size=len(slots), replace=False)
        r = swap_descent(info, visible, allowed, S, min_rays, **kw)
        n_swaps += r.n_swaps
        if key(r) < best_key:
            best, best_key = r, key(r)
            accepted += 1
    return RefineResult(stations=best.stations, worst=best.worst, start_worst=start_worst, n_swaps=n_swaps,
                        n_kicks=n_kicks, n_kicks_accepted=accepted)
