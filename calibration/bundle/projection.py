"""Vectorised projection of the observations with their Jacobians (points, poses, interior)."""
from __future__ import annotations

import numpy as np

from calibration.camera import Intrinsics, skew


def project_observations(
    intr: Intrinsics, R: np.ndarray, t: np.ndarray, X: np.ndarray, names: tuple[str, ...] = ()
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Project ``X: (q, 3)`` through per-observation poses ``R: (q, 3, 3)``, ``t: (q, 3)``.

    Returns ``uv (q, 2)``, ``J_point (q, 2, 3)``, ``J_pose (q, 2, 6)`` (left perturbation
    ``xi = (omega, tau)``, as :func:`calibration.camera.project_with_jacobians`) and
    ``J_intr (q, 2, len(names))`` for the interior parameters ``names``.
    """
    Xc = np.einsum("qab,qb->qa", R, X) + t
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    iz = 1.0 / z
    xy = np.stack([x * iz, y * iz], axis=1)
    q = len(z)
    dxy_dX = np.zeros((q, 2, 3))
    dxy_dX[:, 0, 0] = iz
    dxy_dX[:, 0, 2] = -x * iz * iz
    dxy_dX[:, 1, 1] = iz
    dxy_dX[:, 1, 2] = -y * iz * iz
    Dd = intr.distortion_jacobian(xy)
    xyd = intr.distort(xy)
    F = np.array([intr.fx_px, intr.fy_px])
    duv_dX = F[None, :, None] * np.einsum("qij,qjk->qik", Dd, dxy_dX)
    uv = np.stack([intr.fx_px * xyd[:, 0] + intr.cx_px, intr.fy_px * xyd[:, 1] + intr.cy_px], axis=1)
    J_point = duv_dX @ R
    J_pose = np.concatenate([duv_dX @ -skew(Xc), duv_dX], axis=2)
    J_intr = np.zeros((q, 2, len(names)))
    xn, yn = xy[:, 0], xy[:, 1]
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
