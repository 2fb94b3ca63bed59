"""Faugeras-Toscani camera calibration: linear projection matrix, then interior and exterior orientation.

The seed paper calibrates every recorded image this way and uses the result to
initialise the bundle adjustment. For each image point ``(u, v)`` of a known 3-D point
``P`` the projection matrix ``M`` (rows ``m1, m2, m3`` with last column ``m14, m24, m34``)
satisfies two linear equations::

    m1 . P + m14 - u (m3 . P + m34) = 0
    m2 . P + m24 - v (m3 . P + m34) = 0

Faugeras and Toscani (1987) fix the scale of ``M`` with the constraint ``||m3|| = 1``
(the third row of ``K R`` is the third row of a rotation) instead of ``m34 = 1``: the
estimate is then invariant to rigid motions of the world frame. Writing the system as
``B x + C m3 = 0`` with ``x`` the 9 other unknowns, the constrained least-squares solution
is ``m3`` = the eigenvector of the smallest eigenvalue of ``C^T C - C^T B (B^T B)^-1 B^T C``,
and ``x = -(B^T B)^-1 B^T C m3``. The data are normalised first (translation and an
isotropic scale, which only rescales ``m3`` and so keeps the constraint), then ``M`` is
split into ``alpha_u, alpha_v, u0, v0`` and ``(R, T)`` (seed eq. 1-5).

It needs at least 6 points that are not coplanar (a plane leaves ``M`` undetermined).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera import Intrinsics, decompose_projection_matrix, project
from calibration.errors import CalibrationError

__all__ = ["FTResult", "faugeras_toscani", "estimate_projection_matrix", "combine_intrinsics"]

#: smallest singular value of the centred points over the largest below which the points count as coplanar
COPLANAR_RATIO = 1e-3


@dataclass(frozen=True)
class FTResult:
    """One image calibrated by Faugeras-Toscani.

    Attributes:
        M: (3, 4) projection matrix, scaled so that ``||M[2, :3]|| = 1`` and points in front have positive depth.
        intrinsics: interior orientation (``fx_px = alpha_u``, ``fy_px = alpha_v``, ``cx_px = u0``, ``cy_px = v0``),
            no distortion.
        cam_from_part: (4, 4) exterior orientation.
        rms_px: root mean square reprojection error of the points used, pixels.
        skew: ratio of the dropped skew term of ``K`` to ``alpha_u`` (near 0 for a sound calibration).
        n_points: number of points used.
    """

    M: np.ndarray
    intrinsics: Intrinsics
    cam_from_part: np.ndarray
    rms_px: float
    skew: float
    n_points: int


def _check_geometry(xyz: np.ndarray, uv: np.ndarray) -> None:
    if xyz.ndim != 2 or xyz.shape[1] != 3 or uv.shape != (xyz.shape[0], 2):
        raise CalibrationError(
            f"Faugeras-Toscani needs xyz (n, 3) and uv (n, 2) of the same n; got {xyz.shape} and {uv.shape}"
        )
    if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(uv))):
        raise CalibrationError("Faugeras-Toscani: xyz or uv contains nan/inf; drop unmatched targets first")
    n = xyz.shape[0]
    if n < 6:
        raise CalibrationError(
            f"Faugeras-Toscani needs at least 6 non-coplanar points, got {n}: "
            "take the image closer or identify more targets"
        )
    s = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False)
    if s[0] == 0 or s[2] / s[0] < COPLANAR_RATIO:
        raise CalibrationError(
            f"Faugeras-Toscani: the {n} points are coplanar (thickness ratio {s[2] / max(s[0], 1e-300):.1e} "
            f"< {COPLANAR_RATIO:g}); the projection matrix is undetermined: use targets on more than one plane"
        )


def estimate_projection_matrix(xyz: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Linear Faugeras-Toscani estimate of ``M`` from ``xyz: (n, 3)`` and ``uv: (n, 2)``, (3, 4).

    ``M`` is scaled so that ``||M[2, :3]|| = 1``; its sign is not fixed here.
    """
    xyz = np.asarray(xyz, dtype=float)
    uv = np.asarray(uv, dtype=float)
    _check_geometry(xyz, uv)
    # normalisation: T_uv M T_x^-1 keeps ||m3|| = const
    cx = xyz.mean(axis=0)
    sx = np.sqrt(3.0) / np.sqrt(np.mean(np.sum((xyz - cx) ** 2, axis=1)))
    cu = uv.mean(axis=0)
    su = np.sqrt(2.0) / np.sqrt(np.mean(np.sum((uv - cu) ** 2, axis=1)))
    P = (xyz - cx) * sx
    q = (uv - cu) * su
    n = len(P)
    one = np.ones((n, 1))
    zero3 = np.zeros((n, 3))
    zero1 = np.zeros((n, 1))
    # unknown order: x = (m1 (3), m14, m2 (3), m24, m34), then m3 (3)
    B = np.vstack(
        [
            np.hstack([P, one, zero3, zero1, -q[:, :1]]),
            np.hstack([zero3, zero1, P, one, -q[:, 1:]]),
        ]
    )
    C = np.vstack([-q[:, :1] * P, -q[:, 1:] * P])
    BtB = B.T @ B
    BtC = B.T @ C
    try:
        X = np.linalg.solve(BtB, BtC)  # (9, 3)
    except np.linalg.LinAlgError as exc:  # pragma: no cover - guarded by _check_geometry
        raise CalibrationError("Faugeras-Toscani: singular normal equations; check the point geometry") from exc
    E = C.T @ C - BtC.T @ X
    w, V = np.linalg.eigh(0.5 * (E + E.T))
    m3 = V[:, 0]
    x = -X @ m3
    Mn = np.array(
        [
            [*x[0:3], x[3]],
            [*x[4:7], x[7]],
            [*m3, x[8]],
        ]
    )
    # undo the normalisation: M = T_uv^-1 Mn T_x
    Tuv_inv = np.array([[1 / su, 0, cu[0]], [0, 1 / su, cu[1]], [0, 0, 1.0]])
    Tx = np.eye(4)
    Tx[:3, :3] *= sx
    Tx[:3, 3] = -sx * cx
    M = Tuv_inv @ Mn @ Tx
    return M / np.linalg.norm(M[2, :3])


def faugeras_toscani(xyz: np.ndarray, uv: np.ndarray, width: int, height: int) -> FTResult:
    """Calibrate one image from known points.

    Args:
        xyz: (n, 3) target coordinates (part frame, metres), n >= 6, not coplanar.
        uv: (n, 2) their image coordinates (pixels, origin at the centre of the top-left pixel).
        width, height: image size in pixels.

    Returns:
        :class:`FTResult`. Raises :class:`CalibrationError` for too few or coplanar points,
        or when the points lie behind the recovered camera.
    """
    xyz = np.asarray(xyz, dtype=float)
    uv = np.asarray(uv, dtype=float)
    M = estimate_projection_matrix(xyz, uv)
    # sign: the points must be in front of the camera (positive third coordinate)
    depth = xyz @ M[2, :3] + M[2, 3]
    if np.median(depth) < 0:
        M = -M
    if np.linalg.det(M[:, :3]) < 0:
        # A left-handed K R: happens only with inconsistent data (e.g. mirrored image coordinates)
        raise CalibrationError(
            "Faugeras-Toscani: the projection matrix implies a mirrored camera; "
            "check the pixel axis convention and the target identification"
        )
    # skew before decomposition
    A = M[:, :3]
    a3 = A[2]
    av = np.linalg.norm(np.cross(A[1], a3))
    c_uv = (np.cross(A[0], a3) @ np.cross(A[1], a3)) / max(av, 1e-300)
    intr, cam_from_part = decompose_projection_matrix(M, width, height)
    if np.any(xyz @ cam_from_part[2, :3] + cam_from_part[2, 3] <= 0):
        n_behind = int(np.sum(xyz @ cam_from_part[2, :3] + cam_from_part[2, 3] <= 0))
        raise CalibrationError(
            f"Faugeras-Toscani: {n_behind} of {len(xyz)} points fall behind the recovered camera; "
            "the correspondences are wrong (check target identification)"
        )
    res = project(intr, cam_from_part, xyz) - uv
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    return FTResult(
        M=M,
        intrinsics=intr,
        cam_from_part=cam_from_part,
        rms_px=rms,
        skew=float(c_uv / intr.fx_px),
        n_points=len(xyz),
    )


def combine_intrinsics(results: list[FTResult]) -> Intrinsics:
    """One interior orientation from several images of the same camera: the median of each parameter.

    The per-image Faugeras-Toscani estimates scatter (the focal length is correlated with the
    distance); the median is a robust starting value for a self-calibrating bundle adjustment.
    """
    if not results:
        raise CalibrationError("combine_intrinsics: no Faugeras-Toscani result to combine")
    arr = np.array([[r.intrinsics.fx_px, r.intrinsics.fy_px, r.intrinsics.cx_px, r.intrinsics.cy_px] for r in results])
    med = np.median(arr, axis=0)
    i0 = results[0].intrinsics
    return Intrinsics(fx_px=med[0], fy_px=med[1], cx_px=med[2], cy_px=med[3], width=i0.width, height=i0.height)
