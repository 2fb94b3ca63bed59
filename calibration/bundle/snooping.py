"""Residual statistics of an adjustment and the data-snooping decisions.

Statistics: variance factor, redundancy numbers, and each observation's test statistic
``T = v^T Q_vv^+ v`` (whitened, not yet divided by a variance factor; chi-square with as many degrees of
freedom as its 2x2 redundancy block ``Q_vv`` has rank, times the variance factor, for a good observation).
The rank is one where the block's smaller eigenvalue is below :data:`RANK_RTOL` of its larger (a target seen
by exactly two rays); such a statistic is tested against the 1-dof quantile at the same ``alpha``
(:func:`critical_values`), the others against the 2-dof one.

Decisions (docs/decisions/0019-scale.md):

- :func:`test_variance_factor`: the variance factor the tests divide by: the adjustment's own
  ``s0^2`` (Pope's test), unless the network is evidently contaminated (``s0^2`` above
  ``contamination`` x a robust estimate from the median of the statistics), where the robust one
  is used (blunders inflate ``s0^2`` and would mask each other).
- :func:`pick_rejections`: many rejections per round. A blunder spreads into the residuals of the
  other observations of its target (they share the point) and, much less, of its image (the pose is
  fixed by many targets). So of the failing observations only those with the largest statistic of
  their target are rejected in one round, at most a tenth of an image's observations, largest first.
- :func:`predicted_test`: after the rounds, every rejected observation whose target is still in the
  network is tested against the final adjustment (its predicted residual with cofactor
  ``I + J Q_xx J^T``: the same statistic it would have in the adjustment that includes it); one that
  passes is put back once, and the network re-adjusted.
"""
from __future__ import annotations

import numpy as np
from scipy.special import chdtri  # chi2.isf without importing scipy.stats

from calibration.bundle.normal import _jacobians, _Layout, _Linear
from calibration.errors import CalibrationError

_MEDIAN_CHI2_2 = 2.0 * np.log(2.0)  # median of chi-square with 2 degrees of freedom
#: median of chi-square with 0 (untestable: nan), 1 and 2 degrees of freedom, by the statistic's dof
_MEDIAN_CHI2 = np.array([np.nan, float(chdtri(1, 0.5)), _MEDIAN_CHI2_2])


def _cofactor_blocks(lin: _Linear, lay: _Layout) -> tuple[np.ndarray, np.ndarray]:
    """``Qpp (nu, 3, 3)`` (points' cofactor blocks) and ``VS = V Sigma (nu, 3, p)``."""
    nu, p = lin.V.shape[0], lin.Sigma.shape[0]
    VS = (lin.V.reshape(-1, p) @ lin.Sigma).reshape(nu, 3, p)
    Qpp = lin.Dinv + np.matmul(VS, np.swapaxes(lin.V, 1, 2))
    return Qpp, VS


_CHUNK = 1 << 14  # observations per batch of the projected cofactors (bounds the (chunk, w, w) camera gathers)


def _projected_cofactor(lin: _Linear, lay: _Layout, Qpp, VS, Jp, Jc, cidx, slot) -> np.ndarray:
    """``J Q_xx J^T`` of observations with Jacobians ``Jp, Jc`` (compact) at columns ``cidx``; (q, 2, 2).

    ``Jp Q_pp Jp^T + 2 Jp Q_pc Jc^T + Jc Q_cc Jc^T`` as batched small products over chunks of observations: the
    camera blocks ``Q_cc`` are gathered once per image, ``Q_pc = -V Sigma`` on the observation's own columns.
    """
    m, k = lay.m, lay.k
    w = 6 + k
    q = len(slot)
    img = cidx[:, 0] // 6
    cols = np.empty((m, w), dtype=int)
    cols[:, :6] = 6 * np.arange(m)[:, None] + np.arange(6)
    cols[:, 6:] = 6 * m + np.arange(k)
    Qcc_img = lin.Sigma[cols[:, :, None], cols[:, None, :]]  # (m, w, w)
    A = np.empty((q, 2, 2))
    three = np.arange(3)[None, :, None]
    for s in range(0, q, _CHUNK):
        sl = slice(s, s + _CHUNK)
        oi, os_ = img[sl], slot[sl]
        Jpo, Jco = Jp[sl], Jc[sl, :, :w]
        Jct = np.swapaxes(Jco, 1, 2)
        Qpc = -VS[os_[:, None, None], three, cols[oi][:, None, :]]  # (c, 3, w)
        A[sl] = (np.matmul(np.matmul(Jpo, Qpp[os_]), np.swapaxes(Jpo, 1, 2))
                 + 2 * np.matmul(np.matmul(Jpo, Qpc), Jct)
                 + np.matmul(np.matmul(Jco, Qcc_img[oi]), Jct))
    if len(lay.linked):
        linked = np.any(cidx[:, w:] != 0, axis=1) | np.any(Jc[:, :, w:] != 0, axis=(1, 2))
        if np.any(linked):  # observations of scale-bar targets: the general (slow) gather, on few rows
            cl = cidx[linked]
            Jl = Jc[linked]
            Ql = lin.Sigma[cl[:, :, None], cl[:, None, :]]
            A[linked] = np.matmul(np.matmul(Jl, Ql), np.swapaxes(Jl, 1, 2))
    return 0.5 * (A + np.swapaxes(A, 1, 2))


def _quadratic(Q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``v^T Q^-1 v`` for 2x2 ``Q: (q, 2, 2)``; nan where ``Q`` is (near) singular."""
    det = Q[:, 0, 0] * Q[:, 1, 1] - Q[:, 0, 1] ** 2
    det = np.where(det > 1e-12, det, np.nan)
    return (Q[:, 1, 1] * v[:, 0] ** 2 - 2 * Q[:, 0, 1] * v[:, 0] * v[:, 1] + Q[:, 0, 0] * v[:, 1] ** 2) / det


#: a ray whose cofactor block Q_vv has a trace below this has (almost) no redundancy: it cannot be tested
MIN_TRACE_QVV = 1e-3
#: a 2x2 redundancy block whose smaller eigenvalue is below this share of its larger is of rank one: the statistic
#: has one degree of freedom. A direction with a thousandth of the other's redundancy shows an error there at
#: ~3 % of its size (a blunder along it must exceed ~30x the other's detectable bias to be seen), and dividing by its
#: eigenvalue amplifies the residual's rounding and convergence error (~1e-5 whitened) beyond the statistic's own
#: size once the eigenvalue nears 1e-9; a truly rank-one block (two rays) computes to ~1e-12 of its larger
RANK_RTOL = 1e-3


def _eig2(Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smaller and larger eigenvalue of each symmetric 2x2 block ``Q: (q, 2, 2)`` (closed form)."""
    half = 0.5 * (Q[:, 0, 0] + Q[:, 1, 1])
    rad = np.hypot(0.5 * (Q[:, 0, 0] - Q[:, 1, 1]), 0.5 * (Q[:, 0, 1] + Q[:, 1, 0]))
    return half - rad, half + rad


def _test_statistic(Q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``v^T Q_vv^+ v`` of each observation and its degrees of freedom ``(q,)`` int: 2 where the 2x2 block is regular
    (its inverse), 1 where it is of rank one (smaller eigenvalue below :data:`RANK_RTOL` of the larger: the
    pseudo-inverse), 0 and nan where it has no redundancy (trace < :data:`MIN_TRACE_QVV`).

    A target seen by two rays has one redundancy for its four coordinates: each ray's block is ``lambda e e^T`` and its
    residual lies along ``e``, so ``T = (e . v)^2 / lambda`` (one degree of freedom; the two rays have the same
    statistic, so a failure says the pair disagrees, not which ray is wrong). It used to be left untested (nan;
    decision 0030), then tested against the 2-dof quantile, which at the family-wise ``alpha`` missed a pair's error
    between the 1-dof and the 2-dof quantile (a test of less power than ``alpha`` says). ``e e^T`` is
    ``(Q - lambda_min I) / (lambda_max - lambda_min)``: exact for a block near rank one too."""
    T = _quadratic(Q, v)
    lo, hi = _eig2(Q)
    rank2 = np.isfinite(T) & (lo >= RANK_RTOL * hi)
    tr = Q[:, 0, 0] + Q[:, 1, 1]
    rank1 = ~rank2 & (tr > MIN_TRACE_QVV)
    dof = np.where(rank2, 2, np.where(rank1, 1, 0))
    T = np.where(rank2, T, np.nan)
    if np.any(rank1):
        Qr, vr, l0, l1 = Q[rank1], v[rank1], lo[rank1], hi[rank1]
        P = Qr - l0[:, None, None] * np.eye(2)
        T[rank1] = np.einsum("qi,qij,qj->q", vr, P, vr) / ((l1 - l0) * l1)
    return T, dof


def _predicted_statistic(M: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The statistic of an observation left out of the adjustment from its predicted residual ``v`` of cofactor
    ``M = I + J Q_xx J^T``, and its degrees of freedom: ``M^-1`` is the redundancy block the observation would have
    inside the adjustment (its eigenvalues ``1 / m``), so the rank is decided as in :func:`_test_statistic` on the
    ratio of ``M``'s eigenvalues; at rank one only the direction of ``M``'s smaller eigenvalue is kept
    (``(e . v)^2 / m_min``: the statistic it would have inside)."""
    T = _quadratic(M, v)
    lo, hi = _eig2(M)
    rank1 = np.isfinite(lo) & (lo < RANK_RTOL * hi)
    dof = np.where(np.isfinite(T), 2, 0)
    if np.any(rank1):
        Mr, vr, l0, l1 = M[rank1], v[rank1], lo[rank1], hi[rank1]
        P = l1[:, None, None] * np.eye(2) - Mr  # (m_max - m_min) e_min e_min^T
        T[rank1] = np.einsum("qi,qij,qj->q", vr, P, vr) / ((l1 - l0) * l0)
        dof[rank1] = 1
    return T, dof


def critical_values(alpha: float) -> np.ndarray:
    """Chi-square quantiles at ``alpha`` indexed by the degrees of freedom: ``[nan, q_1, q_2]`` (``crit[dof]`` gives
    each observation's threshold; nan for an untestable one, which then never fails)."""
    return np.array([np.nan, float(chdtri(1, alpha)), float(chdtri(2, alpha))])


def _statistics(lin: _Linear, lay: _Layout, n_obs: int) -> dict:
    """Variance factor, redundancy numbers and the data-snooping statistic of each active observation."""
    r2 = float(np.sum(lin.r_img**2) + np.sum(lin.r_extra**2))
    n_par = 3 * len(lin.Dinv) + lay.p - lin.defect
    dof = 2 * n_obs + len(lin.r_extra) - n_par
    if dof <= 0:
        raise CalibrationError(f"bundle: no redundancy ({dof} degrees of freedom); more images or targets are needed")
    s02 = r2 / dof
    Qpp, VS = _cofactor_blocks(lin, lay)
    A = _projected_cofactor(lin, lay, Qpp, VS, lin.Jp, lin.Jc, lin.cidx, lin.slot)
    Qvv = np.eye(2) - A
    red = 0.5 * np.trace(Qvv, axis1=1, axis2=2)
    T, T_dof = _test_statistic(Qvv, lin.r_img)  # observations without redundancy cannot be tested: nan
    return {"s02": s02, "dof": dof, "T": T, "T_dof": T_dof, "redundancy": red, "Qpp": Qpp, "VS": VS}


def test_variance_factor(T: np.ndarray, s02: float, contamination: float,
                         dof: np.ndarray | None = None) -> tuple[float, str]:
    """The variance factor the tests divide by, and which one ("adjustment" | "robust").

    ``dof: (q,)`` the statistics' degrees of freedom (None: all 2): the robust one is the median of each statistic
    over the median of its chi-square (1 and 2 dof have medians 0.455 and 1.386)."""
    T = np.asarray(T, dtype=float)
    norm = _MEDIAN_CHI2_2 if dof is None else _MEDIAN_CHI2[np.clip(np.asarray(dof, dtype=int), 0, 2)]
    finite = (T / norm)[np.isfinite(T / norm)]
    if contamination <= 0 or len(finite) < 20:
        return s02, "adjustment"
    robust = float(np.median(finite))
    if robust > 0 and s02 > contamination * robust:
        return robust, "robust"
    return s02, "adjustment"


def pick_rejections(T: np.ndarray, threshold, obs_image: np.ndarray, obs_target: np.ndarray,
                    budget: int, image_share: float = 0.1) -> np.ndarray:
    """Observations to reject in one round (indices into ``T``), largest statistic first.

    ``T: (q,)`` divided statistics (nan: untestable or inactive); ``threshold``: one critical value, or ``(q,)`` each
    observation's (by its degrees of freedom): then "largest" is the largest ``T / threshold``. A failing observation
    is taken only if it is the largest of its target's; at most ``max(1, image_share x active observations of its
    image)`` per image, and at most ``budget`` in all.
    """
    act = np.isfinite(T)
    fails = act & (T > threshold)
    if not fails.any() or budget <= 0:
        return np.zeros(0, dtype=int)
    score = T if np.ndim(threshold) == 0 else T / threshold
    idx = np.flatnonzero(act)
    n_t = int(obs_target.max()) + 1
    best = np.full(n_t, -np.inf)
    np.maximum.at(best, obs_target[idx], score[idx])
    cand = np.flatnonzero(fails & (score >= best[obs_target]))
    cand = cand[np.argsort(-score[cand], kind="stable")]
    # one per target (ties: the first), then the per-image share
    _, first = np.unique(obs_target[cand], return_index=True)
    cand = cand[np.sort(first)]
    per_img = np.bincount(obs_image[idx], minlength=int(obs_image.max()) + 1)
    cap = np.maximum(1, np.floor(image_share * per_img)).astype(int)
    rank = np.zeros(len(cand), dtype=int)
    seen: dict[int, int] = {}
    for i, j in enumerate(obs_image[cand]):
        rank[i] = seen.get(int(j), 0)
        seen[int(j)] = rank[i] + 1
    cand = cand[rank < cap[obs_image[cand]]]
    return cand[:budget]


def predicted_test(state, lin: _Linear, lay: _Layout, stats: dict, obs_image, obs_target, obs_uv,
                   sigma_px, with_dof: bool = False):
    """Statistic ``v^T (I + J Q_xx J^T)^-1 v`` (whitened, undivided) of observations left out of the
    adjustment, at its final state; (q,) nan where their target is not in the adjustment. ``with_dof``: also
    ``(q,)`` its degrees of freedom (:func:`_predicted_statistic`: 1 where the observation's block inside the
    adjustment would be of rank one)."""
    out = np.full(len(obs_image), np.nan)
    dof = np.zeros(len(obs_image), dtype=int)
    ok = (lay.uslot[obs_target] >= 0) | (lay.lslot[obs_target] >= 0)
    if ok.any():
        sig = np.asarray(sigma_px, dtype=float)
        sig = sig[ok] if sig.ndim == 3 else np.broadcast_to(sig, (len(ok),))[ok]
        r, Jp, Jc, cidx, slot, _ = _jacobians(state, obs_image[ok], obs_target[ok], obs_uv[ok], lay, sig)
        A = _projected_cofactor(lin, lay, stats["Qpp"], stats["VS"], Jp, Jc, cidx, slot)
        out[ok], dof[ok] = _predicted_statistic(np.eye(2) + A, r)
    return (out, dof) if with_dof else out


def local_followers(picked: np.ndarray, T: np.ndarray, threshold, obs_target: np.ndarray,
                    act_idx: np.ndarray, r_img: np.ndarray, Jp: np.ndarray, s_test: float,
                    excluded: np.ndarray, budget: int, crit: np.ndarray | None = None) -> list[int]:
    """Further rejections in the same round, among the other failing observations of the picked targets.

    With the picked observation removed, the target's point is re-estimated from its other rays with the
    cameras held (one Gauss-Newton step of the point alone) and their statistics recomputed
    (``Q_vv = I - J (J^T J)^-1 J^T`` of the point alone); the largest that still fails is rejected
    too, and so on. A second blunder of the same target then goes in the same round instead of the
    next. The next round re-tests everything with the full adjustment, and the final re-test puts
    back any observation wrongly taken. ``act_idx``: the active observations ``r_img, Jp`` belong to
    (whitened; ``Jp`` zero for scale-bar targets, which are left to the next round). ``threshold``: one critical
    value or ``(q,)`` each observation's; ``crit``: :func:`critical_values` for the point-alone statistics (by their
    own degrees of freedom; None: ``threshold``, which must then be one value).
    """
    pos = np.full(len(T), -1)
    pos[act_idx] = np.arange(len(act_idx))
    fails = np.isfinite(T) & (T > threshold) & ~excluded
    out: list[int] = []
    picked_set = {int(p) for p in picked}
    multi = np.bincount(obs_target[fails], minlength=int(obs_target.max()) + 1)
    todo = sorted({int(obs_target[p]) for p in picked if multi[obs_target[p]] >= 2})
    if not todo:
        return out
    testable = np.flatnonzero(np.isfinite(T))
    testable = testable[np.isin(obs_target[testable], todo)]
    order = testable[np.argsort(obs_target[testable], kind="stable")]
    starts = np.searchsorted(obs_target[order], todo + [todo[-1] + 1])
    for i, t in enumerate(todo):
        if len(out) >= budget:
            break
        rest = [int(o) for o in order[starts[i] : starts[i + 1]] if int(o) not in picked_set]
        while len(rest) >= 3 and len(out) < budget:
            P = pos[rest]
            J, r = Jp[P], r_img[P]
            N = np.einsum("qia,qib->ab", J, J)
            if not np.any(N) or np.linalg.cond(N) > 1e12:
                break
            Ninv = np.linalg.inv(N)
            rr = r - np.einsum("qia,a->qi", J, Ninv @ np.einsum("qia,qi->a", J, r))
            Q = np.eye(2) - np.einsum("qia,ab,qjb->qij", J, Ninv, J)
            Tl, dl = _test_statistic(Q, rr)
            Tl = Tl / s_test
            thr = crit[dl] if crit is not None else np.full(len(rest), float(threshold))
            score = np.where(np.isfinite(Tl), Tl / thr if crit is not None else Tl, -np.inf)
            j = int(np.argmax(score))
            if not (Tl[j] > thr[j]) or not fails[rest[j]]:
                break
            out.append(rest.pop(j))
    return out
