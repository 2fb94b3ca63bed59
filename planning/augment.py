"""Extra stations for a measured network: the closed loop's planner.

After a bundle adjustment some targets may miss their required precision (a dot lost to glare, a
rejected observation, a station the robot could not reach) or not be measured at all. This module
chooses the fewest extra stations, among the visibility database's candidates that the robot
reaches, that bring every such target within its requirement, with the stations already taken held
fixed: their contribution is the information the adjustment *achieved* (the inverse of each target's
3x3 covariance block), not a prediction.

Information is additive and positive semi-definite, and ``sigma = sqrt(trace(N^-1))`` can only fall
when information is added (Loewner order). So the network made of the taken stations plus *every*
valid candidate gives each target the smallest sigma any choice of extra stations can give it: a
target that misses its requirement even then cannot be brought within it by any reachable candidate
station (:attr:`Augmentation.bound_sigma`, a proof, not a heuristic).

The choice itself is greedy with an exact score (every candidate evaluated against every target still
short: closed-form 3x3 inversions, vectorised), followed by a pruning pass that drops any added station
the others make unnecessary (one whose removal leaves no target further from its requirement: partial gains
towards a target that needs more stations than one round allows are kept). Tests compare its station count with an exhaustive search on small cases.

Arrays: ``N_have: (n, 3, 3)`` information achieved per target (1/m^2; zeros for a target not measured),
``rays_have: (n,)`` surviving rays per target, ``required: (n,)`` required sigma (m), ``info: (m, n, 6)``
candidate information (:func:`planning.uncertainty.target_information`), ``visible: (m, n)`` bool,
``valid: (m,)`` bool (sees a target and is reachable).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from planning.uncertainty import _invert6

__all__ = ["Augmentation", "plan_extra_stations", "information_from_covariance"]

_IU = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))
#: deficiency of a target with too few rays or a singular intersection, per missing ray
_RAY_PENALTY = 10.0


def information_from_covariance(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-target information ``inv(cov)`` as 6-vectors, and whether the target was measured.

    ``cov: (n, 3, 3)`` (m^2; nan or non-positive-definite where a target was not measured).
    Returns ``N6: (n, 6)`` (zeros where not measured) and ``measured: (n,)`` bool.
    """
    cov = np.asarray(cov, dtype=float)
    n = len(cov)
    N6 = np.zeros((n, 6))
    measured = np.zeros(n, dtype=bool)
    for t in range(n):
        c = cov[t]
        if not np.all(np.isfinite(c)):
            continue
        c = 0.5 * (c + c.T)
        w = np.linalg.eigvalsh(c)
        if w[0] <= 0:
            continue
        N6[t] = np.linalg.inv(c)[_IU]
        measured[t] = True
    return N6, measured


def _deficiency(sigma: np.ndarray, ok: np.ndarray, rays: np.ndarray, required: np.ndarray, min_rays: int) -> np.ndarray:
    """How far each target is from its requirement (0 when met): log ratio, or a penalty per missing ray."""
    short = np.maximum(min_rays - rays, 0)
    ratio = np.where(ok, np.log(np.maximum(sigma / required, 1.0)), _RAY_PENALTY)
    return np.where(short > 0, _RAY_PENALTY * (1 + short), ratio)


@dataclass
class Augmentation:
    """The extra stations for one round of the closed loop.

    Attributes:
        added: candidate indices chosen, in the order the greedy search added them (after pruning).
        short: (n,) targets that missed their requirement (or were unmeasured) before the round.
        sigma_before: (n,) achieved sigma (inf where not measured); sigma_after: predicted with ``added``.
        bound_sigma: (n,) the smallest sigma any set of valid candidates can give (taken + all valid).
        unreachable: targets short whose bound still misses the requirement: no reachable station helps.
        met_after: (n,) whether each short target meets its requirement with ``added`` (prediction).
        facts: ``stopped`` why the greedy search stopped: "met" (every target it could fix is predicted met),
            "max_new" (the round's limit: targets the bound says stations can fix are still short, ``added`` holds
            the partial gains), "no gain" (no single candidate improves them), "unreachable" (only targets the
            bound proves no candidate can fix).
    """

    added: np.ndarray
    short: np.ndarray
    sigma_before: np.ndarray
    sigma_after: np.ndarray
    bound_sigma: np.ndarray
    unreachable: np.ndarray
    met_after: np.ndarray
    facts: dict = field(default_factory=dict)


def _sigma(N6: np.ndarray, rays: np.ndarray, min_rays: int,
           along: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """sqrt(trace(N^-1)) per target, or ``sqrt(u^T N^-1 u)`` for a target whose ``along`` row ``u`` is not zero."""
    cov6, sigma, ok = _invert6(N6, rays, min_rays)
    if along is not None and np.any(along):
        u = np.asarray(along, dtype=float)  # (t, 3), broadcast over leading axes of cov6 (..., t, 6)
        w = np.stack([u[:, 0] ** 2, 2 * u[:, 0] * u[:, 1], 2 * u[:, 0] * u[:, 2], u[:, 1] ** 2, 2 * u[:, 1] * u[:, 2],
                      u[:, 2] ** 2], axis=-1)
        var = np.einsum("...k,...k->...", np.nan_to_num(cov6), w)
        directed = np.broadcast_to(np.any(u != 0, axis=1), sigma.shape)
        sigma = np.where(directed & ok, np.sqrt(np.maximum(var, 0.0)), sigma)
    return sigma, ok


def plan_extra_stations(N_have: np.ndarray, rays_have: np.ndarray, required: np.ndarray, info: np.ndarray,
                        visible: np.ndarray, valid: np.ndarray, *, min_rays: int, max_new: int,
                        consider: np.ndarray | None = None, along: np.ndarray | None = None) -> Augmentation:
    """The fewest extra candidate stations that bring every short target within its requirement.

    ``N_have`` is ``(n, 6)`` (or ``(n, 3, 3)``); ``consider: (n,)`` bool restricts the targets looked at
    (default: all). ``max_new`` caps the number of stations added in this round. ``along: (n, 3)`` unit vectors:
    a target with a non-zero row is judged by its sigma along that direction, ``sqrt(u^T N^-1 u)``, instead of
    ``sqrt(trace(N^-1))`` (the scale bar's ends along the bar, :mod:`planning.scalebar`); the bound holds for
    it too (the variance in any direction can only fall when information is added).
    """
    N_have = np.asarray(N_have, dtype=float)
    if N_have.ndim == 3:
        N_have = N_have[:, _IU[0], _IU[1]]
    rays_have = np.asarray(rays_have, dtype=int)
    required = np.asarray(required, dtype=float)
    visible = np.asarray(visible, dtype=bool)
    valid = np.asarray(valid, dtype=bool)
    m, n = visible.shape
    if info.shape != (m, n, 6) or N_have.shape != (n, 6) or rays_have.shape != (n,) or required.shape != (n,):
        raise ValueError("plan_extra_stations: shapes of N_have, rays_have, required, info, visible disagree")
    consider = np.ones(n, dtype=bool) if consider is None else np.asarray(consider, dtype=bool)
    U = np.zeros((n, 3)) if along is None else np.asarray(along, dtype=float).reshape(n, 3)

    sigma0, ok0 = _sigma(N_have, rays_have, min_rays, U)
    short = consider & ~((sigma0 <= required) & ok0)
    cand = np.flatnonzero(valid)
    # the bound: every valid candidate added at once
    N_all = N_have + info[cand].astype(float).sum(axis=0)
    rays_all = rays_have + visible[cand].sum(axis=0)
    bound, ok_all = _sigma(N_all, rays_all, min_rays, U)
    bound = np.where(ok_all, bound, np.inf)
    unreachable = short & ~(ok_all & (bound <= required))
    goal = short & ~unreachable  # what the stations can fix

    T = np.flatnonzero(goal)
    N = N_have[T].copy()
    rays = rays_have[T].copy()
    req = required[T]
    UT = U[T]
    added: list[int] = []
    if T.size:
        infoT = info[cand][:, T].astype(float)  # (c, t, 6)
        visT = visible[cand][:, T]
        used = np.zeros(len(cand), dtype=bool)
        while len(added) < max_new:
            s, ok = _sigma(N, rays, min_rays, UT)
            d_now = _deficiency(s, ok, rays, req, min_rays)
            if not np.any(d_now > 0):
                break
            Nc = N[None] + infoT  # (c, t, 6)
            rc = rays[None] + visT
            sc, okc = _sigma(Nc, rc, min_rays, UT)
            gain = (d_now[None] - _deficiency(sc, okc, rc, req[None], min_rays)).sum(axis=1)
            gain[used] = -np.inf
            k = int(np.argmax(gain))
            if not gain[k] > 0:
                break
            used[k] = True
            added.append(int(cand[k]))
            N += infoT[k]
            rays += visT[k]
        s_end, ok_end = _sigma(N, rays, min_rays, UT)
        left = _deficiency(s_end, ok_end, rays, req, min_rays) > 0
        stopped = "met" if not left.any() else ("max_new" if len(added) >= max_new else "no gain")
        # prune: drop a station the others make unnecessary: without it no target is further from its requirement
        # (latest-added last to go). A station that brings a target still short closer is kept: its partial gain is
        # what the next round builds on (decision 0070; pruning it left a target that needs more stations than one
        # round allows with nothing, and the loop ended claiming no station helps)
        for c in list(added):
            rest = [a for a in added if a != c]
            Nr = N_have[T] + (info[rest][:, T].astype(float).sum(axis=0) if rest else 0.0)
            rr = rays_have[T] + (visible[rest][:, T].sum(axis=0) if rest else 0)
            s, ok = _sigma(Nr, rr, min_rays, UT)
            s_full, ok_full = _sigma(N, rays, min_rays, UT)
            d_full = _deficiency(s_full, ok_full, rays, req, min_rays)
            d_rest = _deficiency(s, ok, rr, req, min_rays)
            if np.all(d_rest <= d_full + 1e-12):  # nothing that was met becomes short, no partial gain is lost
                added = rest
                N, rays = Nr, rr
    else:
        stopped = "met" if not short.any() else "unreachable"
    N_after = N_have + (info[added].astype(float).sum(axis=0) if added else 0.0)
    rays_after = rays_have + (visible[added].sum(axis=0) if added else 0)
    sigma_after, ok_after = _sigma(N_after, rays_after, min_rays, U)
    sigma_after = np.where(ok_after, sigma_after, np.inf)
    met_after = (sigma_after <= required) & ok_after
    return Augmentation(added=np.asarray(added, dtype=int), short=short,
                        sigma_before=np.where(ok0, sigma0, np.inf), sigma_after=sigma_after, bound_sigma=bound,
                        unreachable=unreachable, met_after=met_after,
                        facts={"candidates_valid": int(valid.sum()), "targets_short": int(short.sum()),
                               "targets_unreachable": int(unreachable.sum()), "stopped": stopped,
                               "limited_by_max_new": stopped == "max_new"})
