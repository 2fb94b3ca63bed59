"""Target measurement in images: retro-reflective dots, coded (ArUco) targets, identification.

* :func:`detect_retro_targets`: bright blobs on a dark background (retro-reflective dots lit
  by a ring flash). Background and noise are estimated robustly on a subsample, the image is
  thresholded, blobs are labelled (OpenCV connected components) and filtered by size and
  shape, and each centre is the background-subtracted intensity-weighted centroid over the
  blob grown by a margin (the skirt below the threshold carries position information; cutting
  it biases the centre). All per-blob sums are vectorised with ``bincount`` over the labels.
* :func:`detect_coded_targets`: OpenCV's ArUco detector; a marker's centre is the intersection
  of its diagonals (the projective centre, not the corners' mean).
* :func:`identify_targets`: names the uncoded dots by projecting the nominal targets with an
  approximate pose (from the robot and hand-eye, refined with ``solvePnP`` on the coded
  targets when at least 4 are seen), then mutual-nearest-neighbour matching with a ratio
  test; the pose is refined once more on the matched dots and the matching repeated.

Pixel convention: origin at the centre of the top-left pixel (OpenCV's too).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from calibration.camera import Intrinsics, make_pose, project
from calibration.errors import CalibrationError

__all__ = [
    "DetectionOptions",
    "Detections",
    "detect_retro_targets",
    "detect_coded_targets",
    "identify_targets",
    "refine_pose_pnp",
]


@dataclass(frozen=True)
class DetectionOptions:
    """Retro-reflective dot detection.

    Attributes:
        threshold_sigma: threshold = background + this many noise standard deviations
            (ignored when ``threshold`` is given).
        threshold: absolute threshold in grey levels, or None for automatic.
        min_area_px, max_area_px: blob size limits (pixels above threshold).
        max_aspect: largest bounding-box aspect ratio (elongated blobs are edges or glints).
        min_fill: smallest fraction of the bounding box covered by the blob.
        margin_px: the blob is grown by this many pixels for the centroid.
        min_peak_snr: smallest (peak - background) / noise.
        subsample: stride of the subsample used for background and noise.
        background_kernel_px: side of the square opening that estimates the local
            background (a white top-hat), larger than the largest dot; 0 for one global
            background level (a dark, uniform scene).
    """

    threshold_sigma: float = 8.0
    threshold: float | None = None
    min_area_px: int = 4
    max_area_px: int = 5000
    max_aspect: float = 3.0
    min_fill: float = 0.4
    margin_px: int = 2
    min_peak_snr: float = 10.0
    subsample: int = 7
    background_kernel_px: int = 41


@dataclass(frozen=True)
class Detections:
    """Detected dots.

    Attributes:
        uv: (k, 2) sub-pixel centres.
        area_px: (k,) pixels above threshold.
        peak: (k,) peak grey level above background.
        flux: (k,) summed background-subtracted grey levels over the grown blob.
        background: (k,) local background grey level.
        noise: global noise standard deviation (grey levels).
    """

    uv: np.ndarray
    area_px: np.ndarray
    peak: np.ndarray
    flux: np.ndarray
    background: np.ndarray
    noise: float

    def __len__(self) -> int:
        return len(self.uv)


def _check_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise CalibrationError(
            f"target detection needs a (h, w) uint8 or uint16 grey image, got {image.shape} {image.dtype}"
        )
    return image


def _background_noise(image: np.ndarray, stride: int) -> tuple[float, float]:
    """Background level (median of a subsample) and the pixel noise's standard deviation.

    The noise comes from differences of pixels two apart along every ``stride``-th row (MAD / sqrt 2):
    large bright areas (a plate filling half the view) and smooth shading do not count as noise,
    as they would in the spread of the grey levels themselves.
    """
    sample = image[::stride, ::stride].astype(np.float32).ravel()
    med = float(np.median(sample))
    rows = image[::stride].astype(np.float32)
    d = (rows[:, 2:] - rows[:, :-2]).ravel()
    noise = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / np.sqrt(2.0)
    if noise == 0.0:  # quantised, nearly noise-free: the spread of the small differences
        small = d[np.abs(d) <= 3]
        noise = float(np.std(small)) / np.sqrt(2.0) if len(small) > 1 else 1.0
    return med, max(noise, 0.5)


def _ring_planes(lab: np.ndarray, dx: np.ndarray, dy: np.ndarray, val: np.ndarray, k: int, fallback: float) -> np.ndarray:
    """Least-squares plane ``b0 + gx dx + gy dy`` through the ring pixels of each of ``k`` blobs.

    ``lab`` (1..k) names the blob of each ring pixel at offset ``(dx, dy)`` from the blob's centre.
    Returns (k, 3) ``(b0, gx, gy)``; a blob whose ring cannot carry a plane gets its mean (or
    ``fallback`` without ring pixels) and no slope.
    """
    def s(w):
        return np.bincount(lab, weights=w, minlength=k + 1)[1:]

    n = s(np.ones_like(dx, dtype=float))
    A = np.empty((k, 3, 3))
    A[:, 0, 0] = n
    A[:, 0, 1] = A[:, 1, 0] = s(dx)
    A[:, 0, 2] = A[:, 2, 0] = s(dy)
    A[:, 1, 1] = s(dx * dx)
    A[:, 1, 2] = A[:, 2, 1] = s(dx * dy)
    A[:, 2, 2] = s(dy * dy)
    b = np.stack([s(val), s(val * dx), s(val * dy)], axis=1)
    coef = np.zeros((k, 3))
    coef[:, 0] = np.where(n > 0, b[:, 0] / np.maximum(n, 1), fallback)
    ok = n >= 8
    if np.any(ok):
        det = np.linalg.det(A[ok])
        good = np.flatnonzero(ok)[np.abs(det) > 1e-9 * np.maximum(n[ok], 1) ** 3]
        if len(good):
            coef[good] = np.linalg.solve(A[good], b[good][..., None])[..., 0]
    return coef


def detect_retro_targets(image: np.ndarray, options: DetectionOptions | None = None) -> Detections:
    """Sub-pixel centres of bright dots in ``image: (h, w) uint8/uint16``."""
    o = options or DetectionOptions()
    image = _check_image(image)
    if o.background_kernel_px > 0:
        # the part's own diffuse surface is brighter than the threshold in places: threshold the
        # white top-hat (image minus its opening), which keeps only structures smaller than the kernel
        kern = cv2.getStructuringElement(cv2.MORPH_RECT, (o.background_kernel_px, o.background_kernel_px))
        tophat = cv2.morphologyEx(image, cv2.MORPH_TOPHAT, kern)
        _, noise = _background_noise(tophat, o.subsample)
        noise = max(noise, _background_noise(image, o.subsample)[1])
        thr = o.threshold if o.threshold is not None else o.threshold_sigma * noise
        mask = (tophat > thr).astype(np.uint8)
        bg = float(np.median(image[:: o.subsample, :: o.subsample]))
    else:
        bg, noise = _background_noise(image, o.subsample)
        thr = o.threshold if o.threshold is not None else bg + o.threshold_sigma * noise
        mask = (image > thr).astype(np.uint8)
    n_lab, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8, ltype=cv2.CV_32S)
    empty = Detections(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), noise)
    if n_lab <= 1:
        return empty
    w_box = stats[1:, cv2.CC_STAT_WIDTH].astype(float)
    h_box = stats[1:, cv2.CC_STAT_HEIGHT].astype(float)
    area = stats[1:, cv2.CC_STAT_AREA].astype(float)
    keep = (
        (area >= o.min_area_px)
        & (area <= o.max_area_px)
        & (np.maximum(w_box, h_box) / np.minimum(w_box, h_box) <= o.max_aspect)
        & (area / (w_box * h_box) >= o.min_fill)
    )
    # blobs touching the border are cut: their centroid would be biased
    x0, y0 = stats[1:, cv2.CC_STAT_LEFT], stats[1:, cv2.CC_STAT_TOP]
    H, W = image.shape
    m = o.margin_px
    keep &= (x0 - m - 1 >= 0) & (y0 - m - 1 >= 0) & (x0 + w_box + m + 1 <= W) & (y0 + h_box + m + 1 <= H)
    if not np.any(keep):
        return empty
    # relabel the kept blobs 1..k, grow them by the margin, and a ring further out for the local background
    remap = np.zeros(n_lab, dtype=np.float32)
    kept = np.flatnonzero(keep) + 1
    remap[kept] = np.arange(1, len(kept) + 1, dtype=np.float32)
    lab = remap[labels]
    k1 = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * m + 1, 2 * m + 1))
    k2 = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * m + 5, 2 * m + 5))
    grown = cv2.dilate(lab, k1)
    outer = cv2.dilate(lab, k2)
    k = len(kept)
    ys, xs = np.nonzero(outer)
    lo = outer[ys, xs].astype(np.int64)
    lg = grown[ys, xs].astype(np.int64)
    val = image[ys, xs].astype(np.float64)
    ring = lg == 0
    # local background: a plane fitted to the ring around each blob. The part's shading slopes
    # under a tilted dot; a constant level leaves that slope in the margin pixels and pulls the
    # centroid towards the brighter side (0.02-0.03 px on the simulated cell's tilted dots).
    xc = (x0 + 0.5 * w_box)[keep]
    yc = (y0 + 0.5 * h_box)[keep]
    rl, rdx, rdy, rv = lo[ring], xs[ring] - xc[lo[ring] - 1], ys[ring] - yc[lo[ring] - 1], val[ring]
    coef = _ring_planes(rl, rdx, rdy, rv, k, bg)
    # once more without the ring pixels far off the plane (an edge of the part, a neighbour's rim)
    r = rv - (coef[rl - 1, 0] + coef[rl - 1, 1] * rdx + coef[rl - 1, 2] * rdy)
    rms = np.sqrt(np.bincount(rl, weights=r * r, minlength=k + 1)[1:] / np.maximum(np.bincount(rl, minlength=k + 1)[1:], 1))
    fit = np.abs(r) <= 2.0 * rms[rl - 1] + 1.0
    coef = _ring_planes(rl[fit], rdx[fit], rdy[fit], rv[fit], k, bg)
    bg_local = coef[:, 0]
    inside = ~ring
    li = lg[inside]
    bgp = coef[li - 1, 0] + coef[li - 1, 1] * (xs[inside] - xc[li - 1]) + coef[li - 1, 2] * (ys[inside] - yc[li - 1])
    top = np.zeros(k + 1)
    np.maximum.at(top, li, val[inside])
    peak = top[1:] - bg_local
    # the dot hides the surface behind it: a pixel's value is bg (1 - a) + L a for a dot of level L
    # covering the fraction a, so its share of the dot is (value - bg) / (L - bg), with L ~ the peak
    wgt = (val[inside] - bgp) / np.maximum(top[li] - bgp, 1.0)
    sw = np.bincount(li, weights=wgt, minlength=k + 1)[1:]
    sx = np.bincount(li, weights=wgt * xs[inside], minlength=k + 1)[1:]
    sy = np.bincount(li, weights=wgt * ys[inside], minlength=k + 1)[1:]
    good = (sw > 0) & (peak >= o.min_peak_snr * noise)
    uv = np.stack([sx / np.where(sw > 0, sw, 1), sy / np.where(sw > 0, sw, 1)], axis=1)
    flux = sw * np.maximum(peak, 0.0)
    return Detections(uv[good], area[keep][good], peak[good], flux[good], bg_local[good], noise)


def _aruco_dictionary(dictionary: str | int):
    if isinstance(dictionary, str):
        if not hasattr(cv2.aruco, dictionary):
            raise CalibrationError(f"unknown ArUco dictionary {dictionary!r} (e.g. 'DICT_4X4_50', 'DICT_5X5_100')")
        dictionary = getattr(cv2.aruco, dictionary)
    return cv2.aruco.getPredefinedDictionary(int(dictionary))


def detect_coded_targets(
    image: np.ndarray, dictionary: str | int = "DICT_4X4_250"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coded (ArUco) targets in ``image: (h, w) uint8/uint16``.

    Returns ``ids (k,) int``, ``corners (k, 4, 2)`` (sub-pixel, OpenCV's order: clockwise from
    the top-left of the marker) and ``centres (k, 2)`` (intersection of the diagonals).
    """
    image = _check_image(image)
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
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    nrm = np.asarray(normals, dtype=float).reshape(-1, 3)
    T = np.asarray(cam_from_part, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    a = np.where(np.abs(nrm[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(nrm, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(nrm, e1)
    K = intr.K
    H = np.stack([radius_m * e1 @ R.T, radius_m * e2 @ R.T, xyz @ R.T + t], axis=2)  # (n, 3, 3) camera frame
    H = K @ H
    Hinv = np.linalg.inv(H)
    C = np.einsum("nji,jk,nkl->nil", Hinv, np.diag([1.0, 1.0, -1.0]), Hinv)
    A = C[:, :2, :2]
    b = C[:, :2, 2]
    centre = -np.linalg.solve(A, b[..., None])[..., 0]
    proj = H[:, :2, 2] / H[:, 2:3, 2]
    return centre - proj
