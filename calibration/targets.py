"""Target measurement in images: retro-reflective dots, coded (ArUco) targets, identification.

* :func:`detect_dots` / :func:`detect_retro_targets` (in :mod:`calibration.dots`, re-exported):
  dot centres with covariances, bright or dark dots, grey or colour images.
* :func:`detect_coded_targets`: OpenCV's ArUco detector; a marker's centre is the intersection
  of its diagonals (the projective centre, not the corners' mean).
* :func:`identify_targets`: names the uncoded dots by projecting the nominal targets with an
  approximate pose (from the robot and hand-eye, refined with ``solvePnP`` on the coded
  targets when at least 4 are seen), then mutual-nearest-neighbour matching with a ratio
  test; the pose is refined once more on the matched dots and the matching repeated.

Pixel convention: origin at the centre of the top-left pixel (OpenCV's too).
"""
from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from calibration.camera import Intrinsics, make_pose, project
from calibration.dots import DetectionOptions, Detections, detect_dots, detect_retro_targets, to_grey
from calibration.errors import CalibrationError

__all__ = [
    "DetectionOptions",
    "Detections",
    "detect_retro_targets",
    "detect_dots",
    "to_grey",
    "detect_coded_targets",
    "identify_targets",
    "refine_pose_pnp",
]


def _aruco_dictionary(dictionary: str | int):
    if isinstance(dictionary, str):
        if not hasattr(cv2.aruco, dictionary):
            raise CalibrationError(f"unknown ArUco dictionary {dictionary!r} (e.g. 'DICT_4X4_50', 'DICT_5X5_100')")
        dictionary = getattr(cv2.aruco, dictionary)
    return cv2.aruco.getPredefinedDictionary(int(dictionary))


def detect_coded_targets(
    image: np.ndarray, dictionary: str | int = "DICT_4X4_250"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coded (ArUco) targets in ``image`` (grey or colour, uint8/uint16).

    Returns ``ids (k,) int``, ``corners (k, 4, 2)`` (sub-pixel, OpenCV's order: clockwise from
    the top-left of the marker) and ``centres (k, 2)`` (intersection of the diagonals).
    """
    image = to_grey(image)
    if image.dtype == np.uint16:
        image = cv2.convertScaleAbs(image, alpha=255.0 / max(int(image.max()), 1))
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.ArucoDetector(_aruco_dictionary(dictionary), params)
    corners, ids, _ = det.detectMarkers(image)
    if ids is None or len(ids) == 0:
        return np.zeros(0, dtype=int), np.zeros((0, 4, 2)), np.zeros((0, 2))
    C = np.array([c.reshape(4, 2) for c in corners], dtype=float)
    return ids.ravel().astype(int), C, _diagonal_intersection(C)


def _diagonal_intersection(C: np.ndarray) -> np.ndarray:
    """Intersection of the lines corner0-corner2 and corner1-corner3, ``C: (k, 4, 2)`` -> (k, 2)."""
    h = np.concatenate([C, np.ones(C.shape[:2] + (1,))], axis=2)
    l1 = np.cross(h[:, 0], h[:, 2])
    l2 = np.cross(h[:, 1], h[:, 3])
    p = np.cross(l1, l2)
    return p[:, :2] / p[:, 2:3]


def refine_pose_pnp(
    intr: Intrinsics, cam_from_part: np.ndarray, xyz: np.ndarray, uv: np.ndarray
) -> np.ndarray:
    """``cam_from_part`` refined by ``cv2.solvePnP`` (iterative, from the given pose), (4, 4)."""
    rvec, _ = cv2.Rodrigues(np.asarray(cam_from_part[:3, :3], dtype=float))
    tvec = np.asarray(cam_from_part[:3, 3], dtype=float).reshape(3, 1).copy()
    ok, rvec, tvec = cv2.solvePnP(
        np.ascontiguousarray(xyz, dtype=np.float64), np.ascontiguousarray(uv, dtype=np.float64),
        intr.K, intr.dist_coeffs, rvec, tvec, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok:
        raise CalibrationError("identification: solvePnP failed; check the approximate pose and the coded targets")
    return make_pose(cv2.Rodrigues(rvec)[0], tvec.ravel())


def _match(det_uv: np.ndarray, proj_uv: np.ndarray, cand: np.ndarray, max_dist_px: float, ratio: float) -> np.ndarray:
    """Mutual nearest neighbours with a ratio test; returns (k,) index into ``cand`` targets or -1."""
    out = np.full(len(det_uv), -1)
    if len(cand) == 0 or len(det_uv) == 0:
        return out
    tree_p = cKDTree(proj_uv[cand])
    kk = min(2, len(cand))
    d, j = tree_p.query(det_uv, k=kk)
    if kk == 1:
        d, j = d[:, None], j[:, None]
        d = np.concatenate([d, np.full_like(d, np.inf)], axis=1)
    tree_d = cKDTree(det_uv)
    kd = min(2, len(det_uv))
    dd, jd = tree_d.query(proj_uv[cand], k=kd)
    if kd == 1:
        dd, jd = dd[:, None], jd[:, None]
        dd = np.concatenate([dd, np.full_like(dd, np.inf)], axis=1)
    i = np.arange(len(det_uv))
    mutual = jd[j[:, 0], 0] == i
    unambiguous = (d[:, 0] < ratio * d[:, 1]) & (dd[j[:, 0], 0] < ratio * dd[j[:, 0], 1])
    ok = mutual & unambiguous & (d[:, 0] <= max_dist_px)
    out[ok] = cand[j[ok, 0]]
    return out


def identify_targets(
    det_uv: np.ndarray,
    nominal_xyz: np.ndarray,
    target_ids: np.ndarray,
    intr: Intrinsics,
    cam_from_part_approx: np.ndarray,
    max_dist_px: float,
    coded_ids: np.ndarray | None = None,
    coded_uv: np.ndarray | None = None,
    ratio: float = 0.5,
) -> np.ndarray:
    """Name the detected dots.

    Args:
        det_uv: (k, 2) detected dot centres.
        nominal_xyz: (n, 3) nominal targets, part frame.
        target_ids: (n,) int ArUco code of each target, -1 for uncoded dots (``Targets.code``).
        intr: camera interior orientation.
        cam_from_part_approx: (4, 4) approximate pose (robot pose and hand-eye).
        max_dist_px: largest distance between a dot and a projected target.
        coded_ids, coded_uv: (c,), (c, 2) detected coded targets (ids and centres); with at least 4
            known codes the pose is refined by ``solvePnP`` first.
        ratio: a match is kept when the nearest distance is below ``ratio`` times the second nearest
            (both ways).

    Returns:
        (k,) index into the nominal targets, or -1 for an unidentified dot.
    """
    det_uv = np.asarray(det_uv, dtype=float).reshape(-1, 2)
    xyz = np.asarray(nominal_xyz, dtype=float)
    codes = np.asarray(target_ids, dtype=int)
    if codes.shape != (len(xyz),):
        raise CalibrationError(f"identify_targets: target_ids {codes.shape} must be (n,) for {len(xyz)} targets")
    pose = np.asarray(cam_from_part_approx, dtype=float)
    if coded_ids is not None and coded_uv is not None and len(coded_ids):
        lookup = {c: t for t, c in enumerate(codes) if c >= 0}
        pairs = [(lookup[c], u) for c, u in zip(np.asarray(coded_ids, dtype=int), np.asarray(coded_uv)) if c in lookup]
        if len(pairs) >= 4:
            pose = refine_pose_pnp(intr, pose, xyz[[p[0] for p in pairs]], np.array([p[1] for p in pairs]))
    retro = np.flatnonzero(codes < 0)
    Xc_z = xyz[retro] @ pose[2, :3] + pose[2, 3]
    proj = np.full((len(xyz), 2), np.nan)
    front = retro[Xc_z > 0]
    proj[front] = project(intr, pose, xyz[front])
    cand = front[intr.in_image(proj[front], margin_px=-max_dist_px)]
    match = _match(det_uv, proj, cand, max_dist_px, ratio)
    if np.sum(match >= 0) >= 6:
        # refine the pose on the matched dots and match again, tighter
        sel = match >= 0
        pose = refine_pose_pnp(intr, pose, xyz[match[sel]], det_uv[sel])
        proj[front] = project(intr, pose, xyz[front])
        cand = front[intr.in_image(proj[front], margin_px=-max_dist_px)]
        match = _match(det_uv, proj, cand, max_dist_px, ratio)
    return match


def _disc_conics(
    intr: Intrinsics, cam_from_part: np.ndarray, xyz: np.ndarray, normals: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """``H = K [r R e1, r R e2, R c + t]`` (n, 3, 3) of circles of ``radius_m`` at ``xyz`` with ``normals``, and
    their image conics ``C = H^-T diag(1, 1, -1) H^-1`` (n, 3, 3)."""
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    nrm = np.asarray(normals, dtype=float).reshape(-1, 3)
    T = np.asarray(cam_from_part, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    a = np.where(np.abs(nrm[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(nrm, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(nrm, e1)
    H = intr.K @ np.stack([radius_m * e1 @ R.T, radius_m * e2 @ R.T, xyz @ R.T + t], axis=2)  # camera frame
    Hinv = np.linalg.inv(H)
    C = np.einsum("nji,jk,nkl->nil", Hinv, np.diag([1.0, 1.0, -1.0]), Hinv)
    return H, C


def eccentricity_bias(
    intr: Intrinsics, cam_from_part: np.ndarray, xyz: np.ndarray, normals: np.ndarray, radius_m: float
) -> np.ndarray:
    """Image offset of a circular target's ellipse centre from the projection of its centre, (n, 2) px.

    A circle of ``radius_m`` on the plane through ``xyz: (n, 3)`` with normal ``normals: (n, 3)`` maps
    to the image conic ``C' = H^-T diag(1, 1, -1) H^-1`` with ``H = K [r R e1, r R e2, R c + t]``;
    the intensity centroid of a uniformly bright dot is that ellipse's centre, which under
    perspective is not the image of the circle's centre (the eccentricity error, growing with the
    target's size and its tilt). Subtract it from measured centres. Distortion is ignored: its
    effect on this small offset is of second order.
    """
    H, C = _disc_conics(intr, cam_from_part, xyz, normals, radius_m)
    A = C[:, :2, :2]
    b = C[:, :2, 2]
    centre = -np.linalg.solve(A, b[..., None])[..., 0]
    proj = H[:, :2, 2] / H[:, 2:3, 2]
    return centre - proj


def ellipse_moments(
    intr: Intrinsics, cam_from_part: np.ndarray, xyz: np.ndarray, normals: np.ndarray, radius_m: float
) -> np.ndarray:
    """Second-moment matrix of the ellipse each circular target images as, (n, 2, 2) px^2.

    The image conic of :func:`eccentricity_bias`, ``(x - c)^T A (x - c) = s``, is the ellipse of shape
    ``S = s A^-1``; a uniformly bright ellipse has second moments ``S / 4`` (a disc of radius r: r^2/4 I),
    what :func:`calibration.dots.detect_dots` reports as ``Detections.axes``. Distortion is ignored.
    """
    if len(np.asarray(xyz).reshape(-1, 3)) == 0:
        return np.zeros((0, 2, 2))
    _, C = _disc_conics(intr, cam_from_part, xyz, normals, radius_m)
    A = C[:, :2, :2]
    b = C[:, :2, 2]
    s = np.einsum("ni,ni->n", b, np.linalg.solve(A, b[..., None])[..., 0]) - C[:, 2, 2]
    return s[:, None, None] * np.linalg.inv(A) / 4.0


#: a pixel's own width adds 1/12 px^2 to a dot's second moments along each axis (the box it integrates the light over)
PIXEL_VARIANCE_PX2 = 1.0 / 12.0


def blur_variances(measured: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """The optical blur each dot's image shows, as a variance along each axis, ``(k,)`` px^2: its measured second
    moments ``measured: (k, 2, 2)`` (``Detections.axes``) less those of the ellipse it images as ``predicted: (k, 2,
    2)`` (:func:`ellipse_moments`) and the pixel's width (:data:`PIXEL_VARIANCE_PX2`), half the trace. Blur adds its
    variance to a dot's moments, so this is the lens's blur and its defocus at the dot's depth. On the simulator's
    renders it comes out within 0.02-0.1 px^2 of the blur rendered (tests/test_sim_camera.py); a clipped dot's flat
    top makes it meaningless (NaN is not returned for it: the caller knows which dots are clipped)."""
    measured = np.asarray(measured, dtype=float).reshape(-1, 2, 2)
    predicted = np.asarray(predicted, dtype=float).reshape(-1, 2, 2)
    return 0.5 * (np.trace(measured, axis1=1, axis2=2) - np.trace(predicted, axis1=1, axis2=2)) - PIXEL_VARIANCE_PX2


def shape_ratios(measured: np.ndarray, predicted: np.ndarray, blur_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """How a dot's second moments ``measured: (k, 2, 2)`` compare with its ellipse's ``predicted: (k, 2, 2)``.

    Returns ``(lo, hi)``, (k,) each: the smallest eigenvalue of the measured moments in the metric of the
    predicted ones (1 for a whole dot; a clipped dot shrinks along the cut), and the largest after removing
    ``blur_px`` of isotropic blur (a merged pair or a glint grows it). A predicted matrix that is not
    positive definite (a target seen edge-on) gives ``lo = hi = nan``.
    """
    measured = np.asarray(measured, dtype=float).reshape(-1, 2, 2)
    predicted = np.asarray(predicted, dtype=float).reshape(-1, 2, 2)
    lo = np.full(len(measured), np.nan)
    hi = np.full(len(measured), np.nan)
    det = predicted[:, 0, 0] * predicted[:, 1, 1] - predicted[:, 0, 1] ** 2
    ok = (predicted[:, 0, 0] > 0) & (det > 0) & np.all(np.isfinite(measured), axis=(1, 2))
    if ok.any():
        L = np.linalg.cholesky(np.linalg.inv(predicted[ok]))
        lo[ok] = np.linalg.eigvalsh(np.swapaxes(L, 1, 2) @ measured[ok] @ L)[:, 0]
        hi[ok] = np.linalg.eigvalsh(np.swapaxes(L, 1, 2) @ (measured[ok] - blur_px**2 * np.eye(2)) @ L)[:, 1]
    return lo, hi
