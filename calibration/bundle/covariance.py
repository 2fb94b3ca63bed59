"""The adjustment's result: per-target covariance in the datum (S-transform), residuals, redundancy."""
from __future__ import annotations

import numpy as np

from calibration.alignment import PointCovariance, helmert_basis, similarity_fit
from calibration.bundle.config import BundleResult
from calibration.bundle.datum import _apply_similarity
from calibration.bundle.projection import project_pixels


#: a target whose own intersection (its rays alone, cameras and interior held: :func:`own_intersection_sigma`) is this
#: many times worse than the median target's is left out of the datum's minimum trace. Generated plate seed 113: two
#: targets seen by two nearly parallel rays each (0.3-0.5 mm in depth) gave every other target 11 um instead of 1.6 um
#: through the datum (decision 0036). The own intersection depends on no datum: in a free network a target far behind
#: the part (2-12 x the cameras' distance) put its depth into the datum's scale, inflated every target's sigma and so
#: the median a rule on the datum's sigma compared with, and hid itself (decision 0040). Why 10: the datum averages
#: the targets' own errors; one target at k x the median brings k^2 median targets' worth of variance into that
#: average, at 10 as much as 100 of them, the same order as all the others on a 100-400 target part. Measured
#: (decision 0040): the example's largest is 3.8x; on generated parts 0-4 targets per run exceed 10x, seen by 2-11
#: rays (most by 2-5) where the median target is seen by 6-24
WEAK_DATUM = 10.0


def append_columns(pc: PointCovariance, cols: np.ndarray, weights) -> PointCovariance:
    """``pc`` with ``b`` more columns in its low-rank factor: ``Q + sum_j w_j c_j c_j^T`` (``cols: (n, 3, b)``,
    ``weights: (b,)`` their variances, the new core block diagonal).

    Weight zero leaves the covariance as it is: the columns then ride along any transformation of it (an alignment's
    S-transformation) and come out transformed like the points (REPORT: the scale bars' gains, decision 0029);
    a positive weight adds a shared term (ADJUST: a scale bar's ends' shared misfit through the gains). A target
    the adjustment did not determine (NaN block) keeps NaN rows."""
    cols = np.asarray(cols, dtype=float).reshape(pc.n, 3, -1)
    w = np.atleast_1d(np.asarray(weights, dtype=float))
    r, b = pc.U.shape[2], cols.shape[2]
    if w.shape != (b,):
        raise ValueError(f"append_columns: {b} column(s) need {b} weight(s), got {w.shape}")
    C = np.zeros((r + b, r + b))
    C[:r, :r] = pc.C
    C[r:, r:] = np.diag(w)
    return PointCovariance(pc.D, np.concatenate([pc.U, np.where(np.isnan(pc.D[:, :, :1]), np.nan, cols)], axis=2), C)


def _datum_blocks(Q: np.ndarray, D: np.ndarray, U: np.ndarray, C: np.ndarray, P: np.ndarray,
                  H: np.ndarray | None = None) -> np.ndarray:
    """Per-point blocks of ``S Q S^T`` with ``S = I - P H^T`` (``P, H: (n, 3, d)``, ``H^T P = I``; ``H = P``
    orthonormal by default) for ``Q = blockdiag(D) + U C U^T`` whose own blocks are ``Q: (n, 3, 3)``; (n, 3, 3).

    ``(S Q S^T)_ii = Q_ii - P_i X_i^T - X_i P_i^T + P_i (H^T Q H) P_i^T`` with ``X = Q H`` (n, 3, d): batched
    3 x d products, no ``(3n, r) x (r, r)`` product of the low-rank form.
    """
    H = P if H is None else H
    n, _, d = P.shape
    r = U.shape[2]
    W = U.reshape(3 * n, r).T @ H.reshape(3 * n, d)  # U^T H (r, d)
    X = np.matmul(D, H) + (U.reshape(3 * n, r) @ (C @ W)).reshape(n, 3, d)
    M = H.reshape(3 * n, d).T @ X.reshape(3 * n, d)  # H^T Q H (d, d)
    PXt = np.matmul(P, np.swapaxes(X, 1, 2))
    out = Q - PXt - np.swapaxes(PXt, 1, 2) + np.matmul(np.matmul(P, M), np.swapaxes(P, 1, 2))
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def _datum_projectors(G: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``P, H`` of the minimum-trace datum over the points ``keep`` (the S-transformation ``I - P H^T`` =
    ``I - G (G_k^T G_k)^-1 G_k^T``): ``H`` orthonormal, zero outside ``keep``; ``P = G R^-1`` (``G_k = H R``)."""
    n, _, d = G.shape
    Gk = G * keep[:, None, None]
    Qk, R = np.linalg.qr(Gk.reshape(-1, d))
    P = np.linalg.solve(R.T, G.reshape(-1, d).T).T  # G R^-1
    return P.reshape(n, 3, d), Qk.reshape(n, 3, d)


def own_intersection_sigma(lin, lay, obs_target_act: np.ndarray) -> np.ndarray:
    """Each adjusted target's sigma (m, a priori: ``sqrt(trace(N_pp^-1))``) from its own rays with the cameras and the
    interior orientation held: its 3 x 3 block of the normal equations, in the order ``[unlinked, linked]`` of the
    covariance. It depends on no datum (a similarity of the network scales every block alike): a weak target's own
    intersection is weak whatever frame the others' sigma is stated in.

    The unlinked targets' blocks are the Schur complement's ``N_pp^-1`` (``lin.Dinv``; a weighted control target's
    own observation is in it). The linked ones (scale-bar ends) carry their point Jacobian in the camera-side columns
    ``6 + k ..`` of ``lin.Jc``: their blocks are summed from their rays here (the bar's length is not their own
    intersection). ``obs_target_act``: the targets of the observations ``lin`` linearised. A singular block: inf."""
    nu, nl = len(lay.unlinked), len(lay.linked)
    tr = np.empty(nu + nl)
    tr[:nu] = np.trace(lin.Dinv, axis1=1, axis2=2)
    if nl:
        k = lay.k
        ls = lay.lslot[obs_target_act]
        on = ls >= 0
        J = lin.Jc[on][:, :, 6 + k : 6 + k + 3]
        N = np.zeros((nl, 3, 3))
        np.add.at(N, ls[on], np.matmul(np.swapaxes(J, 1, 2), J))
        ev = np.linalg.eigvalsh(N)
        tiny = ev[:, -1:] * 1e-15
        tr[nu:] = np.where(np.all(ev > tiny, axis=1), np.sum(1.0 / np.where(ev > tiny, ev, 1.0), axis=1), np.inf)
    return np.sqrt(np.where(tr >= 0, tr, np.inf))


def _refit_coordinates(state, x0: np.ndarray, keep: np.ndarray, with_scale: bool, pc: PointCovariance,
                       blocks: np.ndarray):
    """The coordinates into the covariance's datum over the targets ``keep``: the similarity (rigid without scale)
    onto the approximate coordinates ``x0`` fitted over those targets only (the datum stage fits over all).

    A least-squares fit over ``keep`` is, to first order, the S-transformation ``I - G (G_k^T G_k)^-1 G_k^T`` the
    covariance took (:func:`_datum_projectors`): with it, the kept targets' centroid, orientation (and scale) sit on
    their approximate ones in the coordinates as in the covariance, and a left-out target's approximate coordinates
    (e.g. a CAD nominal far off its two nearly parallel rays) no longer move every other target. The network moves
    as a whole (cameras too: the images and residuals do not change); the covariance, already in that datum, is
    carried along (``s R`` applied to it). Returns ``(state, pc, blocks)``."""
    s, R, t = similarity_fit(state.points[keep], x0[keep], with_scale=with_scale)
    A = s * R
    return _apply_similarity(state, s, R, t), pc.rotated(A), A @ blocks @ A.T


def _result(state, lin, stats, lay, T, rejected, act_obs, obs_image, obs_target, obs_uv, options, config,
            converged, report, timings, total, x0: np.ndarray | None = None) -> BundleResult:
    n = lay.n
    s02 = stats["s02"]
    factor = s02 if options.a_posteriori else 1.0
    # per-point representation: x = D-part + A dc
    p = lay.p
    D = np.zeros((n, 3, 3))
    A = np.zeros((n, 3, p))
    D[lay.unlinked] = lin.Dinv
    A[lay.unlinked] = -lin.V
    if len(lay.linked):
        cols = lay.link_cols(lay.linked)
        A[lay.linked[:, None], np.arange(3)[None, :], cols] = 1.0
    act = np.concatenate([lay.unlinked, lay.linked])
    pc = PointCovariance(D[act], A[act], lin.Sigma)
    # the points' own blocks before the datum: the unlinked ones are the statistics' Qpp, the linked ones Sigma's
    Qii = np.empty((len(act), 3, 3))
    Qii[: len(lay.unlinked)] = stats["Qpp"]
    if len(lay.linked):
        Qii[len(lay.unlinked) :] = lin.Sigma[cols[:, :, None], cols[:, None, :]]
    left_out = np.zeros(0, dtype=int)
    if lin.defect:
        G = helmert_basis(state.points[act], with_scale=lin.defect == 7)
        Qg, _ = np.linalg.qr(G.reshape(-1, lin.defect))
        Qg = Qg.reshape(len(act), 3, lin.defect)
        blocks = _datum_blocks(Qii, pc.D, pc.U, pc.C, Qg)
        P = H = Qg
        # the minimum trace over the determined targets: a weak one would spread its uncertainty to every other. Which
        # are weak: by their own intersection (no datum in it), not by their sigma in a datum they would shape
        sig = own_intersection_sigma(lin, lay, obs_target[act_obs])
        fin = np.isfinite(sig)
        weak = ~fin | (sig > WEAK_DATUM * np.median(sig[fin])) if fin.sum() >= 3 else np.zeros(len(sig), dtype=bool)
        if weak.any() and (~weak).sum() >= 3:
            try:  # the kept targets span the datum's motions (not all on one line): else the all-target datum stays
                P, H = _datum_projectors(G, ~weak)
                blocks = _datum_blocks(Qii, pc.D, pc.U, pc.C, P, H)
                left_out = act[weak]
            except np.linalg.LinAlgError:
                P = H = Qg
        pc = pc.s_transform(P, H)
        if len(left_out) and x0 is not None:  # the coordinates in the same datum as the covariance
            state, pc, blocks = _refit_coordinates(state, x0, act[~weak], lin.defect == 7, pc, blocks)
    else:
        blocks = 0.5 * (Qii + np.swapaxes(Qii, 1, 2))
    pc = pc.scaled(factor)
    # back to all n targets (inactive: nan)
    Dn = np.full((n, 3, 3), np.nan)
    Un = np.full((n, 3, pc.U.shape[2]), np.nan)
    Dn[act], Un[act] = pc.D, pc.U
    full = PointCovariance(Dn, Un, pc.C)
    cov = np.full((n, 3, 3), np.nan)
    cov[act] = blocks * factor
    points = np.full((n, 3), np.nan)
    points[act] = state.points[act]
    k = lay.k
    icov = lin.Sigma[6 * lay.m : 6 * lay.m + k, 6 * lay.m : 6 * lay.m + k] * factor
    # residuals of all observations at the final state (rejected ones too, where their target survives)
    res = np.full((len(obs_image), 2), np.nan)
    ok = np.isin(obs_target, act)
    R = state.poses[obs_image[ok], :3, :3]
    tt = state.poses[obs_image[ok], :3, 3]
    uv = project_pixels(state.intr, R, tt, state.points[obs_target[ok]])
    res[ok] = obs_uv[ok] - uv
    red = np.full(len(obs_image), np.nan)
    red[act_obs] = stats["redundancy"]
    timings = dict(timings, total=total)
    return BundleResult(
        points=points, cov=cov, covariance=full, cam_from_part=state.poses, intrinsics=state.intr,
        intrinsics_names=lay.names, intrinsics_cov=icov, sigma0_px=float(np.sqrt(s02) * options.sigma_px),
        residuals=res, test_statistic=T, redundancy=red, rejected=rejected, dof=int(stats["dof"]),
        datum=config.datum, converged=bool(converged), summary=report, timings=timings,
        datum_left_out=np.sort(left_out), variance_factor=float(factor),
    )
