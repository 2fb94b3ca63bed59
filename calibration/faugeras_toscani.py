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

It needs at least 6 points that are not coplanar (a plane leaves ``M`` undetermined). Near a plane
it is not undetermined but ill-conditioned: the focal length and the distance trade off, and noise
of a tenth of a pixel moves the focal length by percent (a warped sheet of paper, thickness ratio
0.003, returned 57 px for a 2336 px lens). So the method refuses, with a :class:`CalibrationError`
that says why, inputs it cannot calibrate from (:func:`check_conditioning`: too few points, points
thinner than ``NEAR_PLANAR_RATIO`` of their extent, image points bunched or on a line), and results
that are not a camera (:func:`check_plausible`: non-square pixels, skew, principal point off the
image centre, a focal length far from the nominal lens). Callers then orient the image another way
(PnP from the robot pose, or a plane's homography) and say so.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera import Intrinsics, decompose_projection_matrix, project
from calibration.errors import CalibrationError
from calibration.plausibility import intrinsics_problems

__all__ = ["FTResult", "faugeras_toscani", "estimate_projection_matrix", "combine_intrinsics", "check_conditioning",
           "check_plausible", "orient_without_ft"]

#: smallest singular value of the centred points over the largest below which the points count as coplanar
COPLANAR_RATIO = 1e-3
#: ... and below which they are too flat for a trustworthy projection matrix (the interior orientation
#: then trades off with the distance; 0.02: the focal length scatters ~0.2 % at 0.1 px noise, 0.003: ~2 %, biased)
NEAR_PLANAR_RATIO = 0.02
#: fewest points accepted (6 determine M exactly, with no check at all)
MIN_POINTS = 8
#: the image points' spread (standard deviation along their principal axes) as a share of the image diagonal
MIN_IMAGE_SPREAD = (0.05, 0.02)


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


def check_conditioning(xyz: np.ndarray, uv: np.ndarray, width: int, height: int) -> float:
    """Refuse point sets Faugeras-Toscani cannot calibrate from reliably; returns the thickness ratio.

    Raises :class:`CalibrationError` for fewer than :data:`MIN_POINTS` points, points thinner than
    :data:`NEAR_PLANAR_RATIO` of their extent (smallest over largest singular value of the centred
    points), or image points spread less than :data:`MIN_IMAGE_SPREAD` of the image diagonal.
    """
    xyz = np.asarray(xyz, dtype=float)
    uv = np.asarray(uv, dtype=float)
    _check_geometry(xyz, uv)
    n = len(xyz)
    if n < MIN_POINTS:
        raise CalibrationError(f"Faugeras-Toscani: {n} points; at least {MIN_POINTS} are needed for a checked "
                               "estimate (6 fit it exactly, with no redundancy)")
    s = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False)
    ratio = float(s[2] / s[0])
    if ratio < NEAR_PLANAR_RATIO:
        raise CalibrationError(f"Faugeras-Toscani: the {n} points are nearly planar (thickness ratio {ratio:.3f} < "
                               f"{NEAR_PLANAR_RATIO:g}); the interior orientation would be ill-conditioned")
    su = np.linalg.svd(uv - uv.mean(axis=0), compute_uv=False) / np.sqrt(n)
    diag = float(np.hypot(width, height))
    if su[0] < MIN_IMAGE_SPREAD[0] * diag or su[1] < MIN_IMAGE_SPREAD[1] * diag:
        raise CalibrationError(f"Faugeras-Toscani: the {n} image points are bunched or on a line (spread "
                               f"{su[0]:.0f} x {su[1]:.0f} px, needs {MIN_IMAGE_SPREAD[0] * diag:.0f} x "
                               f"{MIN_IMAGE_SPREAD[1] * diag:.0f})")
    return ratio


def check_plausible(intr: Intrinsics, skew_ratio: float, nominal: Intrinsics | None = None) -> None:
    """Refuse an interior orientation that is not a camera (:mod:`calibration.plausibility`); :class:`CalibrationError`."""
    problems = intrinsics_problems(intr, nominal, skew_ratio)
    if problems:
        raise CalibrationError("Faugeras-Toscani: implausible interior orientation: " + "; ".join(problems))


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


def faugeras_toscani(xyz: np.ndarray, uv: np.ndarray, width: int, height: int,
                     nominal: Intrinsics | None = None) -> FTResult:
    """Calibrate one image from known points.

    Args:
        xyz: (n, 3) target coordinates (part frame, metres), n >= :data:`MIN_POINTS`, not (nearly) coplanar.
        uv: (n, 2) their image coordinates (pixels, origin at the centre of the top-left pixel).
        width, height: image size in pixels.
        nominal: the lens' nominal interior orientation, if known: a focal length far from it is refused.

    Returns:
        :class:`FTResult`. Raises :class:`CalibrationError` for ill-conditioned input
        (:func:`check_conditioning`), an implausible interior orientation (:func:`check_plausible`),
        or when the points lie behind the recovered camera.
    """
    xyz = np.asarray(xyz, dtype=float)
    uv = np.asarray(uv, dtype=float)
    check_conditioning(xyz, uv, width, height)
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
    check_plausible(intr, float(c_uv / intr.fx_px), nominal)
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


def orient_without_ft(xyz: np.ndarray, uv: np.ndarray, intr: Intrinsics, guess: np.ndarray | None = None,
                      max_rms_px: float = 10.0) -> tuple[np.ndarray, float, str]:
    """Exterior orientation with a known interior orientation, for images Faugeras-Toscani refuses.

    Args:
        xyz: (n, 3) points (part frame), n >= 4; uv: (n, 2) pixels.
        intr: interior orientation (the nominal lens).
        guess: (4, 4) ``cam_from_part`` to start from (e.g. the robot's pose and the hand-eye): iterative PnP;
            None: IPPE (the planar PnP) for (nearly) planar points, SQPnP otherwise, then refined.
        max_rms_px: a larger reprojection error means the orientation is wrong: refused.

    Returns ``(cam_from_part (4, 4), rms_px, method)``; raises :class:`CalibrationError` when it fails.
    """
    import cv2

    xyz = np.asarray(xyz, dtype=float)
    uv = np.asarray(uv, dtype=float)
    if len(xyz) < 4:
        raise CalibrationError(f"{len(xyz)} points; an orientation by PnP needs at least 4")
    K, dist = intr.K, intr.dist_coeffs
    if guess is not None:
        rvec0, _ = cv2.Rodrigues(np.asarray(guess, dtype=float)[:3, :3])
        ok, rvec, tvec = cv2.solvePnP(xyz, uv, K, dist, rvec0.copy(), np.asarray(guess, float)[:3, 3].copy(),
                                      useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        method = "PnP from the robot pose"
    else:
        s = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False)
        planar = s[2] < NEAR_PLANAR_RATIO * s[0]
        flag = cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_SQPNP
        ok, rvec, tvec = cv2.solvePnP(xyz, uv, K, dist, flags=flag)
        if ok:
            rvec, tvec = cv2.solvePnPRefineLM(xyz, uv, K, dist, rvec, tvec)
        method = "planar PnP (IPPE)" if planar else "PnP (SQPnP)"
    if not ok:
        raise CalibrationError(f"{method} failed")
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = np.ravel(tvec)
    if np.any(xyz @ T[2, :3] + T[2, 3] <= 0):
        raise CalibrationError(f"{method}: points behind the camera; the identification is wrong")
    rms = float(np.sqrt(np.mean(np.sum((project(intr, T, xyz) - uv) ** 2, axis=1))))
    if not np.isfinite(rms) or rms > max_rms_px:
        raise CalibrationError(f"{method}: reprojection rms {rms:.2f} px (more than {max_rms_px:g} px)")
    return T, rms, method
