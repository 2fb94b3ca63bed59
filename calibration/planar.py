"""Starting values for flat and nearly flat target fields, and the EXIF prior of a photograph's camera.

* :func:`exif_camera`: focal length (mm) and pixel pitch from a photograph's EXIF (``FocalLength``,
  ``FocalPlaneXResolution`` / ``FocalPlaneResolutionUnit``, or the 35 mm equivalent focal length).
  Pillow reads the tags.
* :func:`plane_frame`: the best-fit plane of a target field; its rms out-of-plane distance says whether
  the field is flat (then Faugeras-Toscani, which needs depth, cannot start it).
* :func:`planar_calibration`: Zhang's method as OpenCV implements it (``cv2.calibrateCameraExtended``:
  homographies -> closed-form interior orientation -> Levenberg-Marquardt over all images), on the
  targets expressed in their plane's frame; the camera model is OpenCV's (k1, k2, p1, p2 and
  optionally k3). Few images fix what they cannot determine (principal point, aspect, k3, tangential).
* :func:`ippe_pose`: one image's pose from a flat field with known interior orientation
  (``cv2.solvePnP`` with ``SOLVEPNP_IPPE``, then refined iteratively on all points).

Each estimator checks its answer (reprojection rms, focal length inside the image's plausible range,
points in front of the camera) and raises ``CalibrationError`` saying why when it is not trustworthy.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calibration.camera import Intrinsics, invert, make_pose
from calibration.errors import CalibrationError

__all__ = ["ExifCamera", "exif_camera", "plane_frame", "PlanarCalibration", "planar_calibration", "ippe_pose"]

_MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}  # EXIF FocalPlaneResolutionUnit: inch, cm, mm, um


@dataclass(frozen=True)
class ExifCamera:
    """What a photograph's EXIF says of its camera.

    Attributes:
        focal_mm: lens focal length (mm).
        pixel_size_m: pixel pitch at the stored image's size (m), or None when EXIF has no sensor size.
        focal_px: focal length in pixels at the stored image's size, or None.
        source: which tags gave ``focal_px`` ("focal plane resolution" or "35 mm equivalent").
        make, model: camera make and model strings ("" when absent).
    """

    focal_mm: float
    pixel_size_m: float | None
    focal_px: float | None
    source: str
    make: str = ""
    model: str = ""


def exif_camera(path: str | Path, width: int | None = None) -> ExifCamera | None:
    """The EXIF camera of image ``path`` (None without a focal length); ``width`` of the stored image."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            exif = im.getexif()
            w = width or im.size[0]
            sub = exif.get_ifd(0x8769)  # Exif sub-IFD
    except (OSError, ValueError):
        return None
    tags = {**dict(exif), **dict(sub)}
    f = tags.get(37386)  # FocalLength
    if f is None or float(f) <= 0:
        return None
    f = float(f)
    make, model = str(tags.get(271, "")).strip("\x00 "), str(tags.get(272, "")).strip("\x00 ")
    xres, unit = tags.get(41486), tags.get(41488, 2)
    exif_w = tags.get(40962)  # PixelXDimension: the size the resolution refers to
    if xres is not None and float(xres) > 0 and int(unit) in _MM_PER_UNIT:
        pitch_mm = _MM_PER_UNIT[int(unit)] / float(xres)
        if exif_w and int(exif_w) > 0 and int(exif_w) != w:
            pitch_mm *= int(exif_w) / w
        return ExifCamera(f, pitch_mm * 1e-3, f / pitch_mm, "focal plane resolution", make, model)
    f35 = tags.get(41989)  # FocalLengthIn35mmFilm: the frame's diagonal as 43.27 mm
    if f35 is not None and float(f35) > 0:
        h = None
        try:
            with Image.open(path) as im:
                h = im.size[1] * w / im.size[0]
        except OSError:
            pass
        diag_px = np.hypot(w, h) if h else w * 1.2
        focal_px = float(f35) / 43.2666 * diag_px
        return ExifCamera(f, f * 1e-3 / focal_px, focal_px, "35 mm equivalent", make, model)
    return ExifCamera(f, None, None, "", make, model)


def plane_frame(xyz: np.ndarray) -> tuple[np.ndarray, float]:
    """Best-fit plane of ``xyz: (n, 3)``: ``part_from_plane`` (4, 4; z = the plane's normal) and the rms
    distance of the points from the plane (m)."""
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    if len(xyz) < 3:
        raise CalibrationError(f"plane fit: {len(xyz)} points; at least 3 are needed")
    c = xyz.mean(axis=0)
    _, s, Vt = np.linalg.svd(xyz - c, full_matrices=False)
    R = Vt.T.copy()
    if np.linalg.det(R) < 0:
        R[:, 2] *= -1
    return make_pose(R, c), float(s[2] / np.sqrt(len(xyz)))


@dataclass
class PlanarCalibration:
    """Result of :func:`planar_calibration`.

    Attributes:
        intrinsics: the interior orientation (OpenCV model: k1, k2, p1, p2, k3).
        std: standard deviations of fx, fy, cx, cy, k1, k2, p1, p2, k3 (0 for what was held fixed).
        cam_from_part: (m, 4, 4) each image's pose in the field's own frame.
        rms_px: rms reprojection error.
        per_image_rms_px: (m,).
        flatness_m: rms distance of the targets from their plane (the start ignores it).
    """

    intrinsics: Intrinsics
    std: np.ndarray
    cam_from_part: np.ndarray
    rms_px: float
    per_image_rms_px: np.ndarray
    flatness_m: float


def planar_calibration(xyz: list[np.ndarray], uv: list[np.ndarray], width: int, height: int,
                       prior: Intrinsics | None = None, *, radial: int = 3, max_rms_px: float = 3.0) -> PlanarCalibration:
    """Interior and exterior orientation from images of one flat (or nearly flat) field.

    Args:
        xyz: per image, (n_i, 3) targets seen (part frame; together they define the plane).
        uv: per image, (n_i, 2) their image points (px, origin at the centre of the top-left pixel).
        width, height: image size.
        prior: starting interior orientation (e.g. from EXIF); None: OpenCV's closed form alone.
        radial: 2 (k1, k2) or 3 (k1, k2, k3).
        max_rms_px: larger reprojection rms is an error (wrong identification, or not one plane).
    """
    if len(xyz) != len(uv) or not xyz:
        raise CalibrationError("planar calibration: give as many point sets as images, at least one")
    allp = np.concatenate([np.asarray(p, dtype=float).reshape(-1, 3) for p in xyz])
    part_from_plane, flat = plane_frame(np.unique(allp, axis=0))
    plane_from_part = invert(part_from_plane)
    obj, img = [], []
    for p, q in zip(xyz, uv):
        p = np.asarray(p, dtype=float).reshape(-1, 3)
        if len(p) < 6:
            raise CalibrationError(f"planar calibration: an image has {len(p)} identified targets; at least 6 are needed")
        loc = p @ plane_from_part[:3, :3].T + plane_from_part[:3, 3]
        loc[:, 2] = 0.0  # nearly flat fields: the start uses the plane; the bundle takes the depth
        obj.append(loc.astype(np.float32))
        img.append(np.asarray(q, dtype=np.float32).reshape(-1, 1, 2))
    m = len(obj)
    flags = 0
    if radial < 3:
        flags |= cv2.CALIB_FIX_K3
    if m < 3:  # two views or one cannot separate the principal point, aspect and higher terms
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    K0 = None
    if prior is not None:
        K0 = prior.K.copy()
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    elif m < 3:
        raise CalibrationError("planar calibration: fewer than 3 images need a focal-length prior (EXIF or the camera file)")
    try:
        rms, K, dist, rvecs, tvecs, std_int, _, per_view = cv2.calibrateCameraExtended(
            obj, img, (int(width), int(height)), K0,
            None if prior is None else np.asarray(prior.dist_coeffs, dtype=np.float64).reshape(1, 5).copy(), flags=flags)
    except cv2.error as e:
        raise CalibrationError(f"planar calibration: OpenCV failed ({str(e).strip()[:300]})") from None
    d = dist.ravel()
    intr = Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height),
                      k1=float(d[0]), k2=float(d[1]), k3=float(d[4]) if len(d) > 4 else 0.0, p1=float(d[2]), p2=float(d[3]),
                      pixel_size_m=prior.pixel_size_m if prior is not None else None)
    if not (0.1 * max(width, height) < intr.fx_px < 100 * max(width, height)) or abs(intr.fy_px / intr.fx_px - 1) > 0.2:
        raise CalibrationError(f"planar calibration: implausible focal length fx {intr.fx_px:.1f} px, fy {intr.fy_px:.1f} px; "
                               "check the identification and the images' variety of viewing angles")
    if rms > max_rms_px:
        raise CalibrationError(f"planar calibration: reprojection rms {rms:.2f} px above {max_rms_px} px; "
                               "targets wrongly identified, or the field is not flat")
    poses = np.array([make_pose(cv2.Rodrigues(r)[0], t.ravel()) @ plane_from_part for r, t in zip(rvecs, tvecs)])
    return PlanarCalibration(intr, std_int.ravel()[:9], poses, float(rms), np.asarray(per_view).ravel(), flat)


def ippe_pose(intr: Intrinsics, xyz: np.ndarray, uv: np.ndarray, max_rms_px: float = 5.0) -> np.ndarray:
    """``cam_from_part`` (4, 4) of one image of a flat field of at least 4 targets (IPPE, then refined)."""
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    if len(xyz) < 4:
        raise CalibrationError(f"IPPE pose: {len(xyz)} targets; at least 4 are needed")
    part_from_plane, _ = plane_frame(xyz)
    plane_from_part = invert(part_from_plane)
    loc = xyz @ plane_from_part[:3, :3].T + plane_from_part[:3, 3]
    loc[:, 2] = 0.0
    dist = np.asarray(intr.dist_coeffs, dtype=np.float64)
    ok, rvec, tvec = cv2.solvePnP(loc, uv, intr.K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise CalibrationError("IPPE pose: OpenCV found no pose")
    pose = make_pose(cv2.Rodrigues(rvec)[0], tvec.ravel()) @ plane_from_part
    rvec, _ = cv2.Rodrigues(pose[:3, :3])
    ok, rvec, tvec = cv2.solvePnP(xyz, uv, intr.K, dist, rvec, pose[:3, 3].reshape(3, 1).copy(),
                                  useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    pose = make_pose(cv2.Rodrigues(rvec)[0], tvec.ravel())
    proj, _ = cv2.projectPoints(xyz, rvec, tvec, intr.K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - uv) ** 2, axis=1))))
    depth = xyz @ pose[2, :3] + pose[2, 3]
    if rms > max_rms_px or np.any(depth <= 0):
        raise CalibrationError(f"IPPE pose: reprojection rms {rms:.2f} px (or targets behind the camera); "
                               "check the identification or the interior orientation")
    return pose
