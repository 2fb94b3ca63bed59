"""Vectorised projection of the observations with their Jacobians (points, poses, interior).

The Jacobians are formed column by column (no ``(q, 2, 2) @ (q, 2, 3)`` stacks of tiny matrix products, no
``skew`` matrices): ``d(uv)/d(X_cam) = diag(f) D_dist d(xy)/d(X_cam)`` has rows ``g_i``; the point Jacobian is
``g_i R``, the pose Jacobian (left perturbation ``xi = (omega, tau)``) ``(X_cam x g_i, g_i)``.
"""
from __future__ import annotations

import numpy as np

from calibration.camera import Intrinsics


def _camera_points(R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``R X + t`` per observation, (q, 3)."""
    return np.einsum("qab,qb->qa", R, X) + t


def project_pixels(intr: Intrinsics, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """The pixels ``uv (q, 2)`` of :func:`project_observations`, without the Jacobians."""
    Xc = _camera_points(R, t, X)
    iz = 1.0 / Xc[:, 2]
    xy = Xc[:, :2] * iz[:, None]
    xyd = intr.distort(xy)
    return np.stack([intr.fx_px * xyd[:, 0] + intr.cx_px, intr.fy_px * xyd[:, 1] + intr.cy_px], axis=1)


def project_observations(
    intr: Intrinsics, R: np.ndarray, t: np.ndarray, X: np.ndarray, names: tuple[str, ...] = ()
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Project ``X: (q, 3)`` through per-observation poses ``R: (q, 3, 3)``, ``t: (q, 3)``.

    Returns ``uv (q, 2)``, ``J_point (q, 2, 3)``, ``J_pose (q, 2, 6)`` (left perturbation
    ``xi = (omega, tau)``, as :func:`calibration.camera.project_with_jacobians`) and
    ``J_intr (q, 2, len(names))`` for the interior parameters ``names``.
    """
    Xc = _camera_points(R, t, X)
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    iz = 1.0 / z
    xn, yn = x * iz, y * iz
    xy = np.stack([xn, yn], axis=1)
    q = len(z)
    F = (intr.fx_px, intr.fy_px)
    # g[:, i, :] = d uv_i / d X_cam = f_i (D_i0 d(xn)/dX + D_i1 d(yn)/dX), d(xn)/dX = (iz, 0, -xn iz)
    g = np.empty((q, 2, 3))
    if intr.has_distortion:
        Dd = intr.distortion_jacobian(xy)
        for i in range(2):
            a, b = F[i] * Dd[:, i, 0] * iz, F[i] * Dd[:, i, 1] * iz
            g[:, i, 0] = a
            g[:, i, 1] = b
            g[:, i, 2] = -(a * xn + b * yn)
        xyd = intr.distort(xy)
    else:
        g[:, 0, 0] = F[0] * iz
        g[:, 0, 1] = 0.0
        g[:, 0, 2] = -F[0] * iz * xn
        g[:, 1, 0] = 0.0
        g[:, 1, 1] = F[1] * iz
        g[:, 1, 2] = -F[1] * iz * yn
        xyd = xy
    uv = np.stack([intr.fx_px * xyd[:, 0] + intr.cx_px, intr.fy_px * xyd[:, 1] + intr.cy_px], axis=1)
    # J_point = g R: row i is sum_k g[:, i, k] R[:, k, :]
    J_point = (g[:, :, 0, None] * R[:, None, 0, :] + g[:, :, 1, None] * R[:, None, 1, :]
               + g[:, :, 2, None] * R[:, None, 2, :])
    J_pose = np.empty((q, 2, 6))
    # g (-[X_cam]x) = X_cam x g (row vectors)
    J_pose[:, :, 0] = y[:, None] * g[:, :, 2] - z[:, None] * g[:, :, 1]
    J_pose[:, :, 1] = z[:, None] * g[:, :, 0] - x[:, None] * g[:, :, 2]
    J_pose[:, :, 2] = x[:, None] * g[:, :, 1] - y[:, None] * g[:, :, 0]
    J_pose[:, :, 3:] = g
    J_intr = np.zeros((q, 2, len(names)))
    r2 = xn * xn + yn * yn
    for c, name in enumerate(names):
        if name == "fx":
            J_intr[:, 0, c] = xyd[:, 0]
        elif name == "fy":
            J_intr[:, 1, c] = xyd[:, 1]
        elif name == "f":
            J_intr[:, :, c] = xyd
        elif name == "cx":
            J_intr[:, 0, c] = 1.0
        elif name == "cy":
            J_intr[:, 1, c] = 1.0
        elif name in ("k1", "k2", "k3"):
            rp = r2 if name == "k1" else r2 * r2 if name == "k2" else r2 * r2 * r2
            J_intr[:, 0, c] = intr.fx_px * xn * rp
            J_intr[:, 1, c] = intr.fy_px * yn * rp
        elif name == "p1":
            J_intr[:, 0, c] = intr.fx_px * 2 * xn * yn
            J_intr[:, 1, c] = intr.fy_px * (r2 + 2 * yn * yn)
        elif name == "p2":
            J_intr[:, 0, c] = intr.fx_px * (r2 + 2 * xn * xn)
            J_intr[:, 1, c] = intr.fy_px * 2 * xn * yn
    return uv, J_point, J_pose, J_intr
