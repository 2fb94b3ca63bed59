"""Residual statistics of an adjustment and the data-snooping decisions.

Statistics: variance factor, redundancy numbers, and each observation's test statistic
``T = v^T Q_vv^-1 v`` (whitened, not yet divided by a variance factor; chi-square with 2 dof times
the variance factor for a good observation).

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

from calibration.bundle.normal import _jacobians, _Layout, _Linear
from calibration.errors import CalibrationError

_MEDIAN_CHI2_2 = 2.0 * np.log(2.0)  # median of chi-square with 2 degrees of freedom


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


def _test_statistic(Q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``v^T Q_vv^+ v`` of each observation: the inverse where its 2x2 block is regular, the pseudo-inverse where the
    block is of rank one, nan where it has no redundancy (trace < :data:`MIN_TRACE_QVV`).

    A target seen by two rays has one redundancy for its four coordinates: each ray's block is ``lambda e e^T`` and its
    residual lies along ``e``, so ``T = (e . v)^2 / lambda = v^T Q v / trace(Q)^2`` (one degree of freedom; the two
    rays have the same statistic, so a failure says the pair disagrees, not which ray is wrong). It used to be left
    untested (nan): a blunder on such a pair was never found and spread into its images' other observations
    (decision 0030)."""
    T = _quadratic(Q, v)
    tr = Q[:, 0, 0] + Q[:, 1, 1]
    rank1 = ~np.isfinite(T) & (tr > MIN_TRACE_QVV)
    if np.any(rank1):
        Qr, vr = Q[rank1], v[rank1]
        vQv = np.einsum("qi,qij,qj->q", vr, Qr, vr)
        T[rank1] = vQv / tr[rank1] ** 2
    return T


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
    T = _test_statistic(Qvv, lin.r_img)  # observations without redundancy cannot be tested: nan
    return {"s02": s02, "dof": dof, "T": T, "redundancy": red, "Qpp": Qpp, "VS": VS}


def test_variance_factor(T: np.ndarray, s02: float, contamination: float) -> tuple[float, str]:
    """The variance factor the tests divide by, and which one ("adjustment" | "robust")."""
    finite = T[np.isfinite(T)]
    if contamination <= 0 or len(finite) < 20:
        return s02, "adjustment"
    robust = float(np.median(finite)) / _MEDIAN_CHI2_2
    if robust > 0 and s02 > contamination * robust:
        return robust, "robust"
    return s02, "adjustment"


def pick_rejections(T: np.ndarray, threshold: float, obs_image: np.ndarray, obs_target: np.ndarray,
                    budget: int, image_share: float = 0.1) -> np.ndarray:
    """Observations to reject in one round (indices into ``T``), largest statistic first.

    ``T: (q,)`` divided statistics (nan: untestable or inactive). A failing observation is taken
    only if its statistic is the largest of its target's; at most ``max(1, image_share x active
    observations of its image)`` per image, and at most ``budget`` in all.
    """
    act = np.isfinite(T)
    fails = act & (T > threshold)
    if not fails.any() or budget <= 0:
        return np.zeros(0, dtype=int)
    idx = np.flatnonzero(act)
    n_t = int(obs_target.max()) + 1
    best = np.full(n_t, -np.inf)
    np.maximum.at(best, obs_target[idx], T[idx])
    cand = np.flatnonzero(fails & (T >= best[obs_target]))
    cand = cand[np.argsort(-T[cand], kind="stable")]
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
                   sigma_px) -> np.ndarray:
    """Statistic ``v^T (I + J Q_xx J^T)^-1 v`` (whitened, undivided) of observations left out of the
    adjustment, at its final state; (q,) nan where their target is not in the adjustment."""
    out = np.full(len(obs_image), np.nan)
    ok = (lay.uslot[obs_target] >= 0) | (lay.lslot[obs_target] >= 0)
    if not ok.any():
        return out
    sig = np.asarray(sigma_px, dtype=float)
    sig = sig[ok] if sig.ndim == 3 else np.broadcast_to(sig, (len(ok),))[ok]
    r, Jp, Jc, cidx, slot, _ = _jacobians(state, obs_image[ok], obs_target[ok], obs_uv[ok], lay, sig)
    A = _projected_cofactor(lin, lay, stats["Qpp"], stats["VS"], Jp, Jc, cidx, slot)
    out[ok] = _quadratic(np.eye(2) + A, r)
    return out


def local_followers(picked: np.ndarray, T: np.ndarray, threshold: float, obs_target: np.ndarray,
                    act_idx: np.ndarray, r_img: np.ndarray, Jp: np.ndarray, s_test: float,
                    excluded: np.ndarray, budget: int) -> list[int]:
    """Further rejections in the same round, among the other failing observations of the picked targets.

    With the picked observation removed, the target's point is re-estimated from its other rays with the
    cameras held (one Gauss-Newton step of the point alone) and their statistics recomputed
    (``Q_vv = I - J (J^T J)^-1 J^T`` of the point alone); the largest that still fails is rejected
    too, and so on. A second blunder of the same target then goes in the same round instead of the
    next. The next round re-tests everything with the full adjustment, and the final re-test puts
    back any observation wrongly taken. ``act_idx``: the active observations ``r_img, Jp`` belong to
    (whitened; ``Jp`` zero for scale-bar targets, which are left to the next round).
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
            det = Q[:, 0, 0] * Q[:, 1, 1] - Q[:, 0, 1] ** 2
            ok = det > 1e-12
            Tl = np.full(len(rest), -np.inf)
            Tl[ok] = (Q[ok, 1, 1] * rr[ok, 0] ** 2 - 2 * Q[ok, 0, 1] * rr[ok, 0] * rr[ok, 1]
                      + Q[ok, 0, 0] * rr[ok, 1] ** 2) / det[ok] / s_test
            j = int(np.argmax(Tl))
            if not (Tl[j] > threshold) or not fails[rest[j]]:
                break
            out.append(rest.pop(j))
    return out
