"""Is the interior orientation the same in every image? A score test for a change of the lens during the acquisition.

The adjustment estimates (or holds) one interior orientation for all images. A focus or zoom ring that slips, or a
camera that shifts in its mount, midway through the acquisition changes the principal distance and the principal point
of the later images; the poses absorb most of it and the rest leaks into the targets, with a variance factor that stays
in its band (decision 0066: an outside tester's slip of +0.05 % and (0.5, -0.35) px from the 13th of 24 images: sigma0
0.020 px, variance factor 1.23, no warning, the targets 3.1 um median off at a stated ~1.5 um).

The test (:func:`interior_stability`): for each change point ``k`` (the images are in capture order; at least
:data:`MIN_SIDE` on each side) three extra parameters: a change of the principal distance (``fx`` and ``fy`` alike, in px
of ``fx``) and of the principal point (``cx, cy``) for the images ``k ..``. Their score (Lagrange multiplier) at the
converged adjustment, ``g = E^T v`` (whitened residuals ``v`` after the last step, whitened extra columns ``E``), has the
cofactor ``M = E^T Q_vv E = E^T E - E^T J N^- J^T E``, formed from the reduced normal equations (:class:`_Linear`: the
points' ``D^-1``, ``V``, ``Sigma``; no new factorisation). ``T_k = g^T M^-1 g / s0^2`` is chi-square with 3 degrees of
freedom for a lens that did not change; the largest over the ``K`` change points is tested at ``alpha / K``
(Bonferroni: the ``T_k`` of neighbouring change points are strongly correlated, so the bound is conservative). The
change at the best ``k`` is estimated as ``M^-1 g`` with the covariance ``s0^2 M^-1`` (one Gauss-Newton step of the
extended model: the second part's lens minus the first part's).

The interior orientation held (not estimated, or partly): the held terms' common error is no change; it is estimated
for the test (the common columns as nuisance parameters, projected out of the score and its cofactor) so that a held
lens that is merely off is not taken for a lens that moved. A term the adjustment estimates needs no nuisance (its
column is in ``J`` already).
"""
from __future__ import annotations

import numpy as np
from scipy.special import chdtrc, chdtri

from calibration.bundle.normal import _Layout, _Linear, _outer_sum, _rows_dot, _segment_sum, _State
from calibration.bundle.projection import project_observations
from calibration.weights import whitening

#: images on each side of a change point (fewer do not determine their own lens against the poses)
MIN_SIDE = 3
#: the family-wise level of the test over all change points (the largest statistic at ``alpha / K``). Calibrated on
#: clean runs (decision 0066): the example and generated parts stayed far below the critical value
ALPHA = 1e-3
#: what is tested: a change of these (the principal distance moves fx and fy alike)
TERMS = ("principal distance", "cx", "cy")


def _change_columns(state: _State, obs_image: np.ndarray, obs_target: np.ndarray, sigma_px) -> np.ndarray:
    """Whitened columns ``(q, 2, 3)`` of a change of the principal distance (px of ``fx``; ``fy`` by ``fy / fx`` of
    it), ``cx`` and ``cy`` (px) for every observation."""
    R = state.poses[obs_image, :3, :3]
    t = state.poses[obs_image, :3, 3]
    _, _, _, Jin = project_observations(state.intr, R, t, state.points[obs_target], ("fx", "fy", "cx", "cy"))
    E = np.empty((len(obs_image), 2, 3))
    E[:, :, 0] = Jin[:, :, 0] + (state.intr.fy_px / state.intr.fx_px) * Jin[:, :, 1]
    E[:, :, 1:] = Jin[:, :, 2:]
    sig = np.asarray(sigma_px, dtype=float)
    if sig.ndim == 3:
        return np.matmul(whitening(sig), E)
    return E / np.broadcast_to(sig, (len(E),))[:, None, None]


def _residual_after_step(lin: _Linear) -> np.ndarray:
    """The whitened residuals after the last linearisation's step ``(q, 2)``: ``J^T v = 0`` holds for them exactly,
    also where the iterations stopped a hair short of the optimum."""
    dpo = lin.dp[lin.slot] if len(lin.dp) else np.zeros((len(lin.slot), 3))
    return (lin.r_img - np.einsum("qia,qa->qi", lin.Jp, dpo)
            - np.einsum("qiw,qw->qi", lin.Jc, lin.dc[lin.cidx]))


def interior_stability(state: _State, lin: _Linear, lay: _Layout, obs_image: np.ndarray, obs_target: np.ndarray,
                       sigma_px, s02: float, alpha: float = ALPHA, min_side: int = MIN_SIDE) -> dict:
    """The test of one interior orientation for all images against a change after each change point (module doc).

    ``obs_image, obs_target, sigma_px``: the active observations ``lin`` linearised (image indices in capture order);
    ``s02``: the adjustment's variance factor. Returns bundle.json's ``interior_stability``: ``tested`` (False with
    ``reason`` where it cannot be: too few images), ``terms``, ``interior`` ("estimated" | "held" | "partly held"),
    ``statistic`` (the largest ``T_k``), ``dof``, ``critical``, ``alpha``, ``change_points`` (how many ``K``),
    ``p_value`` (Bonferroni, at most 1), ``first_changed`` (index of the first image after the best change point),
    ``change_px`` and ``change_sigma_px`` (principal distance, cx, cy), ``statistics`` (every ``T_k``, by the index of
    the first image after it), ``significant``."""
    m = lay.m
    base = {"terms": list(TERMS), "dof": 3, "alpha": alpha, "min_side": min_side}
    est = {"principal distance": any(n in lay.names for n in ("f", "fx", "fy")),
           "cx": "cx" in lay.names, "cy": "cy" in lay.names}
    base["interior"] = ("estimated" if all(est.values()) else "held" if not any(est.values()) else "partly held")
    splits = np.arange(min_side, m - min_side + 1)
    if len(splits) == 0:
        return base | {"tested": False, "significant": False,
                       "reason": f"{m} images: a change point needs {min_side} images on each side"}
    E = _change_columns(state, obs_image, obs_target, sigma_px)
    v = _residual_after_step(lin)
    nu, p = len(lay.unlinked), lay.p
    W = lin.Jc.shape[2]
    k = lay.k
    # per image: the score, E^T E, and the camera side's pose and interior blocks of J^T E
    g_img = _segment_sum(_rows_dot(E, v), obs_image, m)  # (m, 3)
    EE_img = _segment_sum(_outer_sum(E, E), obs_image, m)  # (m, 3, 3)
    JcE = _outer_sum(lin.Jc, E)  # (q, W, 3)
    pose_img = _segment_sum(JcE[:, :6], obs_image, m)  # (m, 6, 3)
    int_img = _segment_sum(JcE[:, 6 : 6 + k], obs_image, m) if k else np.zeros((m, 0, 3))
    linked = np.any(lin.Jc[:, :, 6 + k :] != 0, axis=(1, 2)) if W > 6 + k else np.zeros(len(E), dtype=bool)
    JpE = _outer_sum(lin.Jp, E)  # (q, 3, 3): zero for linked targets
    V2 = lin.V.reshape(-1, p)

    def pieces(after: np.ndarray):
        """``g``, ``J^T E`` reduced (point blocks ``ap (nu, 3, 3)``, camera ``b = ac - V^T ap (p, 3)``) and
        ``E^T E`` of the columns restricted to the images ``after`` (bool, (m,))."""
        ac = np.zeros((p, 3))
        ac[: 6 * m].reshape(m, 6, 3)[after] = pose_img[after]
        if k:
            ac[6 * m : 6 * m + k] = int_img[after].sum(axis=0)
        on = after[obs_image]
        if np.any(linked & on):
            sel = linked & on
            np.add.at(ac, lin.cidx[sel][:, 6 + k :], JcE[sel][:, 6 + k :])
        ap = _segment_sum(JpE * on[:, None, None], lin.slot, max(nu, 1))[:nu]
        b = ac - V2.T @ ap.reshape(-1, 3) if nu else ac
        return g_img[after].sum(axis=0), ap, b, EE_img[after].sum(axis=0)

    def cross(x, y):
        """``E_x^T J N^- J^T E_y`` from two ``pieces``."""
        return np.einsum("nia,nij,njb->ab", x[1], lin.Dinv, y[1]) + x[2].T @ lin.Sigma @ y[2]

    # the common columns (all images) of the terms the adjustment did not estimate: nuisance parameters
    allp = pieces(np.ones(m, dtype=bool))
    M00 = allp[3] - cross(allp, allp)
    M00 = 0.5 * (M00 + M00.T)
    scale = np.sqrt(np.clip(np.diag(allp[3]), 1e-300, None))
    w, U = np.linalg.eigh(M00 / np.outer(scale, scale))
    keep = w > 1e-8  # a direction the adjustment estimates has (numerically) no cofactor left
    U = U[:, keep] / scale[:, None]  # M00 = (U w U^T) in the scaled frame: nuisance directions, unscaled
    N00 = U.T @ M00 @ U if keep.any() else np.zeros((0, 0))
    g0 = U.T @ allp[0]
    stats = np.full(len(splits), np.nan)
    best = None
    order = np.argsort(obs_image, kind="stable")
    starts = np.searchsorted(obs_image[order], np.arange(m + 1))
    g, ap, b, EE = pieces(np.arange(m) >= splits[0])
    for i, s in enumerate(splits):
        if i:  # the change point one image later: image s - 1 leaves the changed part (no new pass over the network)
            g, ap, b, EE = _drop_image(s - 1, (g, ap, b, EE), order[starts[s - 1] : starts[s]], lin, g_img, EE_img,
                                       pose_img, int_img, JcE, JpE, linked, k)
        pk = (g, ap, b, EE)
        Mkk = EE - cross(pk, pk)
        gk = g
        if keep.any():  # project the common (held) terms out: E_0 restricted to the later images is E_k's own rows
            Mk0 = (EE - cross(pk, allp)) @ U
            sol = np.linalg.solve(N00, np.column_stack([Mk0.T, g0]))
            Mkk = Mkk - Mk0 @ sol[:, :3]
            gk = gk - Mk0 @ sol[:, 3]
        Mkk = 0.5 * (Mkk + Mkk.T)
        try:
            d = np.linalg.solve(Mkk, gk)
        except np.linalg.LinAlgError:
            continue
        T = float(gk @ d) / s02
        stats[i] = T
        if np.isfinite(T) and (best is None or T > best[0]):
            best = (T, int(s), d, np.linalg.inv(Mkk) * s02)
    if best is None:
        return base | {"tested": False, "significant": False,
                       "reason": "the change's cofactor is singular at every change point"}
    K = int(np.count_nonzero(np.isfinite(stats)))
    T, s, d, C = best
    crit = float(chdtri(3, alpha / K))
    return base | {
        "tested": True, "statistic": T, "critical": crit, "change_points": K,
        "p_value": float(min(1.0, K * chdtrc(3, T))), "first_changed": s,
        "change_px": d.tolist(), "change_sigma_px": np.sqrt(np.diag(C)).tolist(),
        "statistics": {int(a): (float(b) if np.isfinite(b) else None) for a, b in zip(splits, stats)},
        "significant": bool(T > crit),
    }


_CHUNK = 4096  # observations per batch of ``V^T`` products (bounds the (chunk, 3, p) gathers)


def _drop_image(j: int, cur, obs: np.ndarray, lin: _Linear, g_img, EE_img, pose_img, int_img, JcE, JpE, linked,
                k: int):
    """The pieces ``(g, ap, b, E^T E)`` of the columns restricted to the later images with image ``j`` (its
    observations ``obs``) taken out: ``b = ac - V^T ap`` loses ``ac_j - V^T ap_j``."""
    g, ap, b, EE = cur
    m = len(g_img)
    ap = ap.copy()
    if len(ap):
        np.subtract.at(ap, lin.slot[obs], JpE[obs])
    db = np.zeros_like(b)
    db[6 * j : 6 * j + 6] = pose_img[j]
    if k:
        db[6 * m : 6 * m + k] = int_img[j]
    ol = obs[linked[obs]]
    if len(ol):
        np.add.at(db, lin.cidx[ol][:, 6 + k :], JcE[ol][:, 6 + k :])
    if len(ap):
        for c in range(0, len(obs), _CHUNK):  # V^T ap_j, point by point of the image
            o = obs[c : c + _CHUNK]
            db -= lin.V[lin.slot[o]].reshape(-1, b.shape[0]).T @ JpE[o].reshape(-1, 3)
    return g - g_img[j], ap, b - db, EE - EE_img[j]
