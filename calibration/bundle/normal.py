"""The linearised problem: parameter layout, normal equations reduced to the camera side, the step.

Scale bars and control targets enter here as extra observations; the datum's gauge (inner
constraints) as the null space of the similarity transformations.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from calibration.alignment import helmert_basis
from calibration.bundle.config import BundleConfig, ControlPoints
from calibration.bundle.projection import project_observations
from calibration.camera import Intrinsics, skew
from calibration.errors import CalibrationError
from calibration.weights import whitening


def _update_intrinsics(intr: Intrinsics, names: tuple[str, ...], delta: np.ndarray) -> Intrinsics:
    d = {"fx_px": intr.fx_px, "fy_px": intr.fy_px, "cx_px": intr.cx_px, "cy_px": intr.cy_px,
         "k1": intr.k1, "k2": intr.k2, "p1": intr.p1, "p2": intr.p2, "k3": intr.k3}
    for name, dv in zip(names, delta):
        if name == "f":
            d["fx_px"] += dv
            d["fy_px"] += dv
        elif name in ("fx", "fy", "cx", "cy"):
            d[name + "_px"] += dv
        else:
            d[name] += dv
    return replace(intr, **d)


def _outer_sum(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A^T B`` of stacked 2-row matrices ``A: (q, 2, a)``, ``B: (q, 2, b)``, (q, a, b) (no tiny-matrix einsum)."""
    return A[:, 0, :, None] * B[:, 0, None, :] + A[:, 1, :, None] * B[:, 1, None, :]


def _rows_dot(A: np.ndarray, r: np.ndarray) -> np.ndarray:
    """``A^T r`` of ``A: (q, 2, a)``, ``r: (q, 2)``, (q, a)."""
    return A[:, 0, :] * r[:, 0, None] + A[:, 1, :] * r[:, 1, None]


def _segment_sum(values: np.ndarray, ids: np.ndarray, size: int) -> np.ndarray:
    """Sum ``values: (q, ...)`` by ``ids: (q,)`` into ``(size, ...)``."""
    shape = values.shape[1:]
    E = int(np.prod(shape)) if shape else 1
    flat = (ids[:, None] * E + np.arange(E)[None, :]).ravel()
    out = np.bincount(flat, weights=values.reshape(len(ids), E).ravel(), minlength=size * E)
    return out.reshape((size,) + shape)


@dataclass
class _State:
    intr: Intrinsics
    poses: np.ndarray  # (m, 4, 4)
    points: np.ndarray  # (n, 3)


@dataclass
class _Linear:
    """Normal equations reduced to the camera side, at one state."""

    r_img: np.ndarray  # (q, 2) weighted residuals of the active observations
    r_extra: np.ndarray  # (e,) weighted residuals of scale bars and control
    Dinv: np.ndarray  # (nu, 3, 3)
    V: np.ndarray  # (nu, 3, p)  Npp^-1 Npc
    Sigma: np.ndarray  # (p, p) g-inverse of the reduced matrix
    dc: np.ndarray  # (p,) camera-side step
    dp: np.ndarray  # (nu, 3) point step
    Jp: np.ndarray  # (q, 2, 3)
    Jc: np.ndarray  # (q, 2, w) compact camera-side Jacobian
    cidx: np.ndarray  # (q, w) its columns
    slot: np.ndarray  # (q,) unlinked point slot of each observation (or 0 with Jp = 0)
    defect: int


class _Layout:
    """Parameter layout: camera side = poses (6 m) | interior (k) | linked points (3 L); the other points apart."""

    def __init__(self, m: int, n: int, names: tuple[str, ...], active_pts: np.ndarray, linked: np.ndarray):
        self.m, self.n, self.names = m, n, names
        self.k = len(names)
        self.linked = np.flatnonzero(linked & active_pts)
        self.unlinked = np.flatnonzero(~linked & active_pts)
        self.lslot = np.full(n, -1)
        self.lslot[self.linked] = np.arange(len(self.linked))
        self.uslot = np.full(n, -1)
        self.uslot[self.unlinked] = np.arange(len(self.unlinked))
        self.p = 6 * m + self.k + 3 * len(self.linked)
        self._structures: list[tuple[np.ndarray, ...]] = []

    def structure(self, obs_image: np.ndarray, obs_target: np.ndarray) -> tuple[np.ndarray, ...]:
        """What depends only on which observations are used, not on the state: ``cidx (q, 6 + k + 3)`` (the
        compact camera-side columns), the unlinked point ``slot (q,)``, ``is_linked (q,)`` and the observations
        grouped by image (``order``, ``starts``). Computed once per set of observations (the arrays themselves,
        held here, are the key: the Gauss-Newton iterations of a round linearise the same arrays many times)."""
        for entry in self._structures:
            if entry[0] is obs_image and entry[1] is obs_target:
                return entry[2:]
        m, k = self.m, self.k
        is_linked = self.lslot[obs_target] >= 0
        cidx = np.zeros((len(obs_image), 6 + k + 3), dtype=int)
        cidx[:, :6] = 6 * obs_image[:, None] + np.arange(6)
        cidx[:, 6 : 6 + k] = 6 * m + np.arange(k)
        if np.any(is_linked):
            cidx[is_linked, 6 + k :] = self.link_cols(obs_target[is_linked])
        slot = np.where(is_linked, 0, self.uslot[obs_target])
        order = np.argsort(obs_image, kind="stable")
        starts = np.searchsorted(obs_image[order], np.arange(m + 1))
        for a in (cidx, slot, is_linked, order, starts):
            a.flags.writeable = False  # shared by every linearisation of these observations
        self._structures = [(obs_image, obs_target, cidx, slot, is_linked, order, starts)] + self._structures[:3]
        return cidx, slot, is_linked, order, starts

    def link_cols(self, targets: np.ndarray) -> np.ndarray:
        """(len, 3) camera-side columns of linked targets."""
        return 6 * self.m + self.k + 3 * self.lslot[targets][:, None] + np.arange(3)[None, :]


def _null_space(state: _State, lay: _Layout, d: int) -> tuple[np.ndarray, np.ndarray]:
    """Infinitesimal similarities of the whole network: camera side (p, d), unlinked points (nu, 3, d)."""
    if d == 0:
        return np.zeros((lay.p, 0)), np.zeros((len(lay.unlinked), 3, 0))
    act = np.concatenate([lay.unlinked, lay.linked])
    c0 = state.points[act].mean(axis=0)
    G7p = helmert_basis(np.vstack([state.points[act], c0[None]]), with_scale=True)  # centred at c0 (last row 0)
    Gp = np.zeros((lay.n, 3, 7))
    Gp[act] = G7p[:-1]
    Gc = np.zeros((lay.p, 7))
    R = state.poses[:, :3, :3]
    tt = state.poses[:, :3, 3] + np.einsum("mab,b->ma", R, c0)  # translation w.r.t. the centred frame
    G = Gc[: 6 * lay.m].reshape(lay.m, 6, 7)  # a view: every image's 6 x 7 block at once
    G[:, 0:3, 3:6] = -R
    G[:, 3:6, 0:3] = -R
    G[:, 3:6, 3:6] = -np.matmul(skew(tt), R)
    G[:, 3:6, 6] = tt
    if len(lay.linked):
        cols = lay.link_cols(lay.linked)
        Gc[cols.ravel(), :] = Gp[lay.linked].reshape(-1, 7)
    return Gc[:, :d], Gp[lay.unlinked][:, :, :d]


def _jacobians(state: _State, obs_image: np.ndarray, obs_target: np.ndarray, obs_uv: np.ndarray, lay: _Layout,
               sigma_px: float | np.ndarray):
    """Whitened residuals and Jacobians of observations (of active targets) at ``state``.

    ``sigma_px``: one sigma, ``(q,)`` sigmas or ``(q, 2, 2)`` covariances (px^2) of the observations.

    Returns ``r (q, 2)``, ``Jp (q, 2, 3)`` (zero for linked targets), the compact camera-side
    ``Jc (q, 2, 6 + k + 3)`` with its columns ``cidx (q, 6 + k + 3)``, the unlinked point ``slot (q,)``
    and ``is_linked (q,)``.
    """
    m, k = lay.m, lay.k
    R = state.poses[obs_image, :3, :3]
    t = state.poses[obs_image, :3, 3]
    uv, Jp, Jpose, Jin = project_observations(state.intr, R, t, state.points[obs_target], lay.names)
    behind = ~np.isfinite(uv).all(axis=1) | (np.einsum("qb,qb->q", R[:, 2], state.points[obs_target]) + t[:, 2] <= 0)
    if np.any(behind):
        exc = CalibrationError("bundle: a target is behind a camera that observes it; check identification")
        exc.targets = np.unique(obs_target[behind])  # which ones: a caller may drop them and adjust again
        raise exc
    sig = np.asarray(sigma_px, dtype=float)
    if sig.ndim == 3:  # a 2x2 covariance per observation: whiten with the inverse of its Cholesky factor
        Wh = whitening(sig)
        r = np.matmul(Wh, (obs_uv - uv)[:, :, None])[:, :, 0]
        Jp, Jpose, Jin = (np.matmul(Wh, J) for J in (Jp, Jpose, Jin))
    else:
        w = 1.0 / np.broadcast_to(sig, (len(uv),))  # (q,) weights^(1/2)
        r = (obs_uv - uv) * w[:, None]
        Jp, Jpose, Jin = Jp * w[:, None, None], Jpose * w[:, None, None], Jin * w[:, None, None]
    cidx, slot, is_linked, _, _ = lay.structure(obs_image, obs_target)
    # compact camera-side Jacobian: pose (6) | interior (k) | linked point (3)
    W = 6 + k + 3
    Jc = np.zeros((len(r), 2, W))
    Jc[:, :, :6] = Jpose
    Jc[:, :, 6 : 6 + k] = Jin
    if np.any(is_linked):
        Jc[is_linked, :, 6 + k :] = Jp[is_linked]
        Jp = Jp.copy()
        Jp[is_linked] = 0.0
    return r, Jp, Jc, cidx, slot, is_linked


def _linearise(
    state: _State, obs_image: np.ndarray, obs_target: np.ndarray, obs_uv: np.ndarray, lay: _Layout,
    config: BundleConfig, sigma_px: float | np.ndarray, defect: int,
) -> _Linear:
    m, k, p = lay.m, lay.k, lay.p
    W = 6 + k + 3
    r, Jp, Jc, cidx, slot, is_linked = _jacobians(state, obs_image, obs_target, obs_uv, lay, sigma_px)
    # camera side: pose and interior blocks by image, linked points by scatter
    Ncc = np.zeros((p, p))
    # per image, one product of its stacked rows (no per-observation (W, W) blocks: 1.7 GB at 2.5 M observations)
    *_, order, starts = lay.structure(obs_image, obs_target)
    II = np.zeros((k, k))
    for j in range(m):
        A = Jc[order[starts[j] : starts[j + 1]], :, : 6 + k].reshape(-1, 6 + k)
        H = A.T @ A
        Ncc[6 * j : 6 * j + 6, 6 * j : 6 * j + 6] = H[:6, :6]
        if k:
            Ncc[6 * j : 6 * j + 6, 6 * m : 6 * m + k] = H[:6, 6:]
            Ncc[6 * m : 6 * m + k, 6 * j : 6 * j + 6] = H[6:, :6]
            II += H[6:, 6:]
    if k:
        Ncc[6 * m : 6 * m + k, 6 * m : 6 * m + k] = II
    if np.any(is_linked):
        lmask = np.zeros((W, W), dtype=bool)
        lmask[6 + k :, :] = True
        lmask[:, 6 + k :] = True
        cl = cidx[is_linked]
        HH = _outer_sum(Jc[is_linked], Jc[is_linked])
        np.add.at(Ncc, (cl[:, :, None], cl[:, None, :]), HH * lmask)
    bc = np.bincount(cidx.ravel(), weights=_rows_dot(Jc, r).ravel(), minlength=p)
    # point side (unlinked points)
    nu = len(lay.unlinked)
    un = ~is_linked
    Npp = _segment_sum(_outer_sum(Jp, Jp), slot, max(nu, 1))[:nu]
    bp = _segment_sum(_rows_dot(Jp, r), slot, max(nu, 1))[:nu]
    E = _outer_sum(Jp[un], Jc[un, :, : 6 + k])  # (qu, 3, 6 + k)
    Npc = np.zeros((nu, 3, p))
    # one observation per (target, image): the pose blocks are assigned, not summed
    Npc[slot[un][:, None, None], np.arange(3)[None, :, None], cidx[un][:, None, :6]] = E[:, :, :6]
    if k:
        Npc[:, :, 6 * m : 6 * m + k] = _segment_sum(E[:, :, 6:], slot[un], max(nu, 1))[:nu]
    # extra observations
    extra = []
    fixed = np.zeros(0, dtype=int)
    if config.control is not None and len(config.control.index):
        ci = np.asarray(config.control.index)
        sig = _control_sigma(config.control)
        keep = (lay.uslot[ci] >= 0) | (lay.lslot[ci] >= 0)
        fixed = ci[keep & np.all(sig == 0, axis=1)]
        for i, xyz, s in zip(ci[keep], np.asarray(config.control.xyz)[keep], sig[keep]):
            if np.all(s == 0):  # truly fixed: no observation, its unknowns are removed below
                continue
            res = (xyz - state.points[i]) / s
            Jx = np.diag(1.0 / s)
            extra.append(res)
            if lay.uslot[i] >= 0:
                Npp[lay.uslot[i]] += Jx.T @ Jx
                bp[lay.uslot[i]] += Jx.T @ res
            else:
                cols = lay.link_cols(np.array([i]))[0]
                Ncc[np.ix_(cols, cols)] += Jx.T @ Jx
                bc[cols] += Jx.T @ res
    for bar in config.scale_bars:
        a, b = bar.target_a, bar.target_b
        if lay.lslot[a] < 0 or lay.lslot[b] < 0:
            continue
        dvec = state.points[a] - state.points[b]
        dist = np.linalg.norm(dvec)
        u = dvec / dist
        res = (bar.length_m - dist) / bar.sigma_m
        Jx = np.concatenate([u, -u]) / bar.sigma_m
        cols = np.concatenate(lay.link_cols(np.array([a, b])))
        Ncc[np.ix_(cols, cols)] += np.outer(Jx, Jx)
        bc[cols] += Jx * res
        extra.append(np.array([res]))
    # truly fixed control targets: their coordinates are not unknowns. An unlinked one keeps a unit block
    # (then zeroed, so it neither moves nor enters the reduced system), a linked one a unit block on the
    # camera side with no right-hand side and no coupling.
    fu = lay.uslot[fixed][lay.uslot[fixed] >= 0]
    if len(fu):
        Npp[fu] = np.eye(3)
        bp[fu] = 0.0
        Npc[fu] = 0.0
    fl = fixed[lay.lslot[fixed] >= 0]
    if len(fl):
        cols = lay.link_cols(fl).ravel()
        Ncc[cols, :] = 0.0
        Ncc[:, cols] = 0.0
        Ncc[cols, cols] = 1.0
        bc[cols] = 0.0
    # Schur complement on the points
    Dinv = np.linalg.inv(Npp)
    if len(fu):
        Dinv[fu] = 0.0
    V = np.matmul(Dinv, Npc)
    V2 = V.reshape(-1, p)
    S = Ncc - Npc.reshape(-1, p).T @ V2
    bred = bc - V2.T @ bp.reshape(-1)
    Gc, _ = _null_space(state, lay, defect)
    Sreg = S
    if defect:
        Qg, _ = np.linalg.qr(Gc)
        Sreg = S + Qg @ Qg.T * np.mean(np.diag(S))
    try:
        Sigma = np.linalg.inv(0.5 * (Sreg + Sreg.T))
    except np.linalg.LinAlgError as exc:
        raise CalibrationError(
            "bundle: the normal equations are singular: the network does not determine every camera "
            "(too few targets per image, or a datum that does not fix the network)"
        ) from exc
    dc = Sigma @ bred
    dp = np.matmul(Dinv, bp[:, :, None])[:, :, 0] - V @ dc
    r_extra = np.concatenate(extra) if extra else np.zeros(0)
    return _Linear(r, r_extra, Dinv, V, Sigma, dc, dp, Jp, Jc, cidx, slot, defect)


def _control_sigma(control: ControlPoints) -> np.ndarray:
    """Per-axis standard deviations of the control targets, (k, 3)."""
    k = len(control.index)
    s = np.asarray(control.sigma_m, dtype=float)
    if s.ndim == 0:
        s = np.full(k, float(s))
    if s.ndim == 1:
        s = s[:, None]
    out = np.broadcast_to(s, (k, 3)).astype(float)
    if np.any(~(out >= 0)):
        raise CalibrationError("bundle: control target standard deviations must be >= 0 (0: held fixed)")
    if np.any((out == 0).any(axis=1) & (out > 0).any(axis=1)):
        raise CalibrationError("bundle: a control target is either fixed (sigma 0 on all three axes) or weighted")
    return out


def _apply_step(state: _State, lin: _Linear, lay: _Layout) -> _State:
    m, k = lay.m, lay.k
    xi = lin.dc[: 6 * m].reshape(m, 6)
    E = np.zeros((m, 4, 4))  # exp_se3 of every image's step at once
    E[:, :3, :3] = Rotation.from_rotvec(xi[:, :3]).as_matrix()
    E[:, :3, 3] = xi[:, 3:]
    E[:, 3, 3] = 1.0
    poses = np.matmul(E, state.poses)
    intr = _update_intrinsics(state.intr, lay.names, lin.dc[6 * m : 6 * m + k]) if k else state.intr
    pts = state.points.copy()
    pts[lay.unlinked] += lin.dp
    if len(lay.linked):
        pts[lay.linked] += lin.dc[lay.link_cols(lay.linked)]
    return _State(intr, poses, pts)
