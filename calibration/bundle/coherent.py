"""The part of a target's background misfit that its views share: a covariance the residuals cannot see.

A dot next to an edge of the part or a step of its shading is centred off its true centre because the
detector's background plane does not fit its surroundings (decision 0023). The detector bounds that error per
image (``Detections.background_cov``) and the bundle weights each observation with it, as if the errors of the
target's views were independent. They are not: the surroundings are the same piece of surface in every view, so
views from similar directions err the same way (on generated skins, ten to twelve rays of one target off by
0.02-0.06 px with one sign; the point 5.5 um from the truth against 1.8 um stated, decision 0029). A shared
error moves the point as a whole and leaves no residual, so neither the data snooping nor the variance factor
can see it: it has to be added to the covariance from the model.

The model: the misfit's effect is a common displacement ``e`` of the target in space, seen by view ``i`` as
``d_i = S_i Jh_i z`` (``z ~ N(0, I_3)``, ``Jh_i`` the unit-scale projection of the view (the rows of its
rotation with the perspective term), ``S_i`` the square root of the view's bound ``c^2 B_i``, so each view alone
keeps the variance the detector stated). The adjusted point moves by ``N^-1 sum_i J_i^T W_i d_i`` (``N =
sum J_i^T W_i J_i``, ``W_i`` the inverse covariance the bundle weighted the observation with). Its covariance is
``N^-1 G G^T N^-T`` with ``G = sum_i J_i^T W_i S_i Jh_i``; the bundle already states the independent part
``N^-1 sum_i g_i g_i^T N^-T`` (``g_i`` the terms of ``G``); the difference, the cross terms between views,
is what is added (its positive part only: the statement never shrinks), scaled by the share ``rho`` of the
misfit that the views have in common: ``E[e_i e_j^T] = rho S_i Jh_i Jh_j^T S_j^T`` for views ``i != j``. Decision
0029 took ``rho = 1`` (the surroundings do not change between views: the conservative limit). Decision 0032
measured it against the rendered truth (:func:`share_pairs`, :func:`fit_share`, ``benchmarks/background_share.py``):
the pairs of views with a bound carry 0.55 +- 0.06 of the modelled cross terms, about alike up to 90 deg between
the views (a common displacement seen through ``Jh``), less beyond. But the misfit is also shared with the target's
views whose ring saw no edge (no bound: nothing modelled), and targets intersected from their views with the true
poses come out optimistic even at ``rho = 1`` (1.18), as do such targets in whole jobs (1.09 pooled over eleven
generated parts; 1.14 at 0.55). The share applied is therefore one, read from the detector model
(``rho_background``; one for a model file without it); the cross terms and the scale bar ends' term scale with it.
"""
from __future__ import annotations

import numpy as np

from calibration.camera import Intrinsics

__all__ = ["coherent_background_cov", "fit_share", "scale_bar_gains", "share_pairs", "unit_projection"]


def unit_projection(cam_from_part: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The unit-scale projection ``Jh: (q, 2, 3)`` of points ``(q, 3)`` in views ``cam_from_part: (q, 4, 4)`` (the
    rows of the rotation with the perspective term: depth times the derivative of the normalised image
    coordinates by the point), and the points' depths ``(q,)``."""
    R = cam_from_part[:, :3, :3]
    Xc = np.einsum("qab,qb->qa", R, points) + cam_from_part[:, :3, 3]
    P = np.zeros((len(Xc), 2, 3))
    P[:, 0, 0] = P[:, 1, 1] = 1.0
    P[:, 0, 2], P[:, 1, 2] = -Xc[:, 0] / Xc[:, 2], -Xc[:, 1] / Xc[:, 2]
    return np.einsum("qab,qbc->qac", P, R), Xc[:, 2]


def _sqrt_psd(B: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(0.5 * (B + np.swapaxes(B, 1, 2)))
    return np.einsum("qab,qb,qcb->qac", V, np.sqrt(np.maximum(w, 0.0)), V)


def coherent_background_cov(intr: Intrinsics, cam_from_part: np.ndarray, points: np.ndarray, obs_image: np.ndarray,
                            obs_target: np.ndarray, obs_cov: np.ndarray, bg_cov: np.ndarray, c: float,
                            share: float = 1.0) -> np.ndarray:
    """The covariance ``(n, 3, 3)`` (m^2) to add to each target's for the background misfit its views share.

    Args:
        intr: the adjusted interior orientation; ``cam_from_part: (m, 4, 4)`` the adjusted poses.
        points: (n, 3) adjusted target coordinates (NaN for targets not adjusted).
        obs_image, obs_target: (q,) the observations the adjustment used (rejected ones left out).
        obs_cov: (q, 2, 2) px^2 the a priori covariance each observation was weighted with (or (q,) sigmas).
        bg_cov: (q, 2, 2) px^2 the detector's background bounds; ``c``: their measured share (``c_background``).
        share: the share ``rho`` of the misfit's variance that the views have in common (the cross terms scale
            by it; the detector model's ``rho_background``, measured by :func:`fit_share`).
    Returns:
        (n, 3, 3) positive semi-definite blocks; zero for targets without a background bound in two views.
    """
    n = len(points)
    out = np.zeros((n, 3, 3))
    obs_image, obs_target = np.asarray(obs_image, dtype=int), np.asarray(obs_target, dtype=int)
    B = c * c * np.asarray(bg_cov, dtype=float).reshape(-1, 2, 2)
    has = np.trace(B, axis1=1, axis2=2) > 0
    per_target = np.bincount(obs_target[has], minlength=n)
    todo = per_target >= 2
    sel = todo[obs_target]
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"coherent background: the shared share must be in [0, 1], got {share}")
    if not np.any(sel) or c <= 0 or share == 0:
        return out
    img, tgt, B = obs_image[sel], obs_target[sel], B[sel]
    C = np.asarray(obs_cov, dtype=float)
    C = (C[sel] ** 2)[:, None, None] * np.eye(2) if C.ndim == 1 else C[sel]
    W = np.linalg.inv(C)
    Jh, depth = unit_projection(np.asarray(cam_from_part, dtype=float)[img], np.asarray(points, dtype=float)[tgt])
    J = Jh * (np.array([intr.fx_px, intr.fy_px])[None, :, None] / depth[:, None, None])  # d(uv)/dX (2, 3)
    JtW = np.einsum("qba,qbc->qac", J, W)  # J^T W (3, 2)
    h = np.einsum("qab,qbc->qac", JtW, J)  # J^T W J (3, 3)
    g = np.einsum("qab,qbc,qcd->qad", JtW, _sqrt_psd(B), Jh)  # J^T W S Jh (3, 3)
    N = np.zeros((n, 3, 3))
    G = np.zeros((n, 3, 3))
    D = np.zeros((n, 3, 3))
    np.add.at(N, tgt, h)
    np.add.at(G, tgt, g)
    np.add.at(D, tgt, np.einsum("qab,qcb->qac", g, g))
    idx = np.flatnonzero(todo & np.all(np.isfinite(points), axis=1))
    Ni = np.linalg.pinv(N[idx], hermitian=True)
    cross = share * (np.einsum("kab,kcb->kac", G[idx], G[idx]) - D[idx])
    E = np.einsum("kab,kbc,kdc->kad", Ni, cross, Ni)
    w, V = np.linalg.eigh(0.5 * (E + np.swapaxes(E, 1, 2)))
    out[idx] = np.einsum("kab,kb,kcb->kac", V, np.maximum(w, 0.0), V)
    return out


def scale_bar_gains(cov, points: np.ndarray, bars, variance_factor: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """How each target moves per metre of error in each scale bar's certified length, and the bars' sigmas.

    The length of a bar is an observation of weight ``1 / sigma^2`` in the adjustment, so the adjusted points
    move by ``k = Q A^T / sigma^2`` per unit of its error (``Q`` the points' covariance in the datum, ``A`` the
    length's derivative: ``+u`` at one end, ``-u`` at the other; a datum without a scale leaves ``A`` unchanged,
    as a rigid motion keeps every length). The certificate's own error, which every target shares, is then
    ``sigma^2 k k^T`` of their covariance: the reference's share of the uncertainty budget.

    Args:
        cov: the bundle's :class:`calibration.alignment.PointCovariance` (in its datum).
        variance_factor: the factor ``cov`` was scaled by (a posteriori ``s0^2``, ``BundleResult.variance_factor``):
            the gains are ``N^-1 A^T / sigma^2`` of the a priori weights, whatever the covariance is scaled by.
        points: (n, 3) adjusted coordinates; ``bars``: :class:`calibration.bundle.config.ScaleBar` sequence.
    Returns:
        ``K: (n, 3, b)`` gains (m per m; NaN for targets not adjusted) and ``sigma: (b,)`` metres.
    """
    n = len(points)
    K = np.full((n, 3, len(bars)), np.nan)
    sig = np.array([b.sigma_m for b in bars], dtype=float)
    D = np.nan_to_num(cov.D)
    U = np.nan_to_num(cov.U)
    for j, bar in enumerate(bars):
        a, b = bar.target_a, bar.target_b
        u = np.asarray(points[a] - points[b], dtype=float)
        u = u / np.linalg.norm(u)
        # Q A^T: column blocks of the low-rank part at a and b, plus the diagonal blocks at a and b
        col = U @ (cov.C @ (U[a].T @ u - U[b].T @ u))  # (n, 3)
        col[a] += D[a] @ u
        col[b] -= D[b] @ u
        K[:, :, j] = col / (bar.sigma_m**2 * variance_factor)
    K[~np.all(np.isfinite(points), axis=1)] = np.nan
    return K, sig


def certificate_at_face_value(cov_blocks: np.ndarray, cov, K: np.ndarray, sigma: np.ndarray,
                              variance_factor: float):
    """The covariance with the scale bars' certificates at their stated sigma, not at ``s0^2`` times it.

    An a posteriori adjustment scales its whole covariance ``Q`` by the variance factor ``s0^2`` that the image
    residuals estimate. The certificates' share of ``Q`` is ``sum_b sigma_b^2 k_b k_b^T`` (``k_b`` the gains of
    :func:`scale_bar_gains`); the residuals say nothing about a certificate (a free network has no other scale),
    so that share must stay as certified. The honest covariance is ``s0^2 (Q_a - C) + C = s0^2 Q_a + (1 - s0^2) C``
    (``Q_a`` the a priori one, ``C`` the certificates' share): ``(1 - s0^2) sigma_b^2`` more along each bar's gains,
    a rank-one term per bar (negative when ``s0^2 > 1``, where the images were worse than their weights; the sum
    stays positive, as ``s0^2 (Q_a - C)`` is a covariance).

    Args:
        cov_blocks: (n, 3, 3) the points' blocks (``BundleResult.cov``); ``cov``: the
            :class:`calibration.alignment.PointCovariance` (``BundleResult.covariance``); both as scaled by
            ``variance_factor``.
        K: (n, 3, b) gains (NaN rows for targets not adjusted); ``sigma``: (b,) the certificates' sigmas (m).
    Returns:
        ``(cov_blocks, cov)`` corrected (new arrays; the inputs are not changed).
    """
    from calibration.bundle.covariance import append_columns

    w = (1.0 - float(variance_factor)) * np.asarray(sigma, dtype=float) ** 2
    if not len(w) or not np.any(w):
        return cov_blocks, cov
    k = np.nan_to_num(np.asarray(K, dtype=float))
    blocks = np.asarray(cov_blocks, dtype=float) + np.einsum("nar,r,nbr->nab", k, w, k)
    return blocks, append_columns(cov, k, w)


def share_pairs(errors_px: np.ndarray, bound_px2: np.ndarray, Jh: np.ndarray, target: np.ndarray, view: np.ndarray,
                sight: np.ndarray | None = None, obs_cov: np.ndarray | None = None) -> dict:
    """The moments behind the shared share: for every pair of observations of one target, both with a background
    bound, the observed cross product ``e_i^T M_ij e_j`` and the model's ``||M_ij||_F^2``, ``M_ij = S_i Jh_i Jh_j^T
    S_j`` (``E[e_i e_j^T] = rho M_ij`` for distinct views; ``S`` the square root of the bound ``c^2 B``).

    With ``obs_cov`` (``(q, 2, 2)`` px^2, the covariance the bundle weights each observation with) the moments are
    whitened by it (``e -> C^-1/2 e``, ``M_ij -> C_i^-1/2 M_ij C_j^-1/2``): each pair then counts as much as the
    weighted intersection lets it move the point, not with the fourth power of its bound. Unwhitened, a few dots
    with bounds far above their error (c sqrt(B) of 0.2 px and more against 0.1 px realised) take nearly all the
    weight (decision 0032).

    Args:
        errors_px: (q, 2) centres against the true projection (eccentricity removed); ``bound_px2: (q, 2, 2)`` the
            scaled bounds ``c^2 B`` (zero: no misfit; such observations take no part).
        Jh: (q, 2, 3) unit-scale projections (:func:`unit_projection`); ``target, view: (q,)`` integer labels (the
            same view rendered again with fresh noise keeps its label: such pairs are marked ``same_view``).
        sight: (q, 3) unit lines of sight (optional): the pairs' angle between them, degrees.
        obs_cov: (q, 2, 2) px^2 the observations' a priori covariance (optional): whiten the moments by it.
    Returns:
        dict of ``(p,)`` arrays ``target, num, den, same_view`` (and ``angle_deg``).
    """
    e = np.asarray(errors_px, dtype=float)
    S = _sqrt_psd(np.asarray(bound_px2, dtype=float).reshape(-1, 2, 2))
    has = np.trace(S, axis1=1, axis2=2) > 0
    if obs_cov is None:
        a = np.einsum("qba,qbc,qc->qa", Jh, S, e)  # Jh^T S e (3,)
        A = np.einsum("qba,qbc,qcd->qad", Jh, S @ S, Jh)  # Jh^T S^2 Jh (3, 3)
    else:  # F = C^-1/2 S Jh: a = F^T C^-1/2 e = Jh^T S C^-1 e, A = F^T F = Jh^T S C^-1 S Jh
        Ci = np.linalg.inv(np.asarray(obs_cov, dtype=float).reshape(-1, 2, 2))
        a = np.einsum("qba,qbc,qcd,qd->qa", Jh, S, Ci, e)
        A = np.einsum("qba,qbc,qcd->qad", Jh, S @ Ci @ S, Jh)
    target, view = np.asarray(target), np.asarray(view)
    out: dict[str, list] = {"target": [], "num": [], "den": [], "same_view": [], "angle_deg": []}
    idx = np.flatnonzero(has)
    order = idx[np.argsort(target[idx], kind="stable")]
    starts = np.flatnonzero(np.r_[True, np.diff(target[order]) != 0, True])
    for s0, s1 in zip(starts[:-1], starts[1:]):
        q = order[s0:s1]
        if len(q) < 2:
            continue
        i, j = np.triu_indices(len(q), 1)
        i, j = q[i], q[j]
        out["target"].append(target[i])
        out["num"].append(np.einsum("pa,pa->p", a[i], a[j]))
        out["den"].append(np.einsum("pab,pab->p", A[i], A[j]))
        out["same_view"].append(view[i] == view[j])
        if sight is not None:
            out["angle_deg"].append(np.degrees(np.arccos(np.clip(np.einsum("pa,pa->p", sight[i], sight[j]), -1, 1))))
    doc = {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}
    if sight is None:
        doc.pop("angle_deg")
    return doc


def fit_share(num: np.ndarray, den: np.ndarray, target: np.ndarray, n_boot: int = 2000,
              rng: np.random.Generator | None = None, min_targets: int = 20) -> tuple[float, float]:
    """Least squares (method of moments) of the shared share ``rho`` over pairs of distinct views
    (:func:`share_pairs`): ``sum num / sum den``; its standard error by a bootstrap over targets (a target's pairs
    share its errors, so the target is the independent unit). Raises when fewer than ``min_targets`` targets have
    a pair: the figure would not be a measurement."""
    num, den, target = np.asarray(num, float), np.asarray(den, float), np.asarray(target)
    if len(num) == 0:
        raise ValueError("shared share: no target with a background bound in two views")
    _, t = np.unique(target, return_inverse=True)
    nt, dt = np.bincount(t, num), np.bincount(t, den)
    if len(nt) < min_targets or dt.sum() <= 0:
        raise ValueError(f"shared share: {len(nt)} target(s) with a bound in two views; at least {min_targets} needed")
    rng = rng or np.random.default_rng(0)
    counts = rng.multinomial(len(nt), np.full(len(nt), 1.0 / len(nt)), size=n_boot)
    boot = (counts @ nt) / np.maximum(counts @ dt, 1e-300)
    return float(nt.sum() / dt.sum()), float(np.std(boot, ddof=1))
