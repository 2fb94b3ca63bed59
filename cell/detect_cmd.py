"""``cell detect IMAGE [--camera CAMERA.toml] [--png OUT.png]``: every detected centre of one image.

With ``--json`` one document on stdout (contract in ARCHITECTURE.md): ``image``, ``width``, ``height``,
``detections``: list of {``u``, ``v`` (px, origin at the centre of the top-left pixel), ``cov`` (2x2, px^2),
``polarity`` ("bright" | "dark"), ``code`` (int or null), ``family`` (str or null)}; plus ``noise``
(grey levels) and ``polarity`` of the image, and ``noise_levels`` ({``variance_at_zero``, ``variance_per_grey_level``}:
the pixel noise's variance as a line in the grey level, measured on the dots' tops and rings, what each ``cov``
propagated; a zero slope where the image had too few dots to measure it; decision 0047). Ring-coded targets are reported once, at their centre dot,
with their code; the pieces of their rings are not dots and are left out. ArUco markers are reported
at the intersection of their diagonals with a covariance of (0.3 px)^2 (their corners' bias,
decision 0004).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from pydantic import ValidationError

from calibration.dots import DetectionOptions, Detections, detect_dots
from calibration.errors import InputError
from calibration.ringcodes import RING_FAMILIES, decode_ring_codes
from calibration.targets import detect_coded_targets
from cell.camerafile import CameraFile, load_camera_file

__all__ = ["read_image", "detect_image", "draw_detections", "detect_command"]

#: ArUco centres from the diagonals: the corners' bias (decision 0004) as a standard deviation, px
ARUCO_SIGMA_PX = 0.3
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm")


def read_image(path: str | Path) -> np.ndarray:
    """An image file as OpenCV reads it, unchanged (8 or 16 bit, grey or BGR); InputError if unreadable."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: image not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{path}: not an image OpenCV can read (PNG, TIFF, JPEG, ...)")
    if img.dtype not in (np.uint8, np.uint16):
        raise InputError(f"{path}: {img.dtype} pixels; detection needs 8- or 16-bit integer images")
    return img


def detection_options(cam: CameraFile) -> DetectionOptions:
    return DetectionOptions.for_real_images(polarity=cam.polarity)


def detect_targets(image: np.ndarray, cam: CameraFile):
    """Dots and coded targets of one image.

    Returns ``(det, code, keep, aruco_ids, aruco_centres)``: the detections, each one's ring code (-1: none),
    which of them are targets (not pieces of a code ring, not inside an ArUco marker), and the ArUco
    markers found. With ring codes and ``polarity = "auto"`` both polarities are tried and the one that
    reads more codes is kept: the blob count that decides otherwise can be won by a cluttered room
    around a small sheet (decision 0015).
    """
    from cell.stages.imaging import MARKER_GROW, inside_any

    opts = detection_options(cam)
    det = detect_dots(image, opts)
    ids, centres = np.zeros(0, dtype=int), np.zeros((0, 2))
    code = np.full(len(det), -1)
    keep = np.ones(len(det), dtype=bool)
    if cam.coded_family in RING_FAMILIES:
        rc = decode_ring_codes(image, det, cam.coded_family)
        if cam.polarity == "auto":
            other = detect_dots(image, replace(opts, polarity="dark" if det.polarity == "bright" else "bright"))
            rc_other = decode_ring_codes(image, other, cam.coded_family)
            if len(rc_other) > len(rc):
                det, rc = other, rc_other
                code = np.full(len(det), -1)
                keep = np.ones(len(det), dtype=bool)
        keep &= ~rc.ring_parts(det.uv)
        code[rc.index] = rc.code
        keep[rc.index] = True
    elif cam.coded_family == "aruco":
        ids, corners, centres = detect_coded_targets(image)
        keep &= ~inside_any(det.uv, corners, grow=MARKER_GROW)
    return det, code, keep, ids, centres


def detect_image(image: np.ndarray, cam: CameraFile) -> tuple[Detections, list[dict]]:
    """Detect the dots and coded targets of one image; returns the dots and the contract's detection list."""
    det, code, keep, ids, centres = detect_targets(image, cam)
    out: list[dict] = []
    if cam.coded_family == "aruco":
        for i, c in zip(ids, centres):
            out.append({"u": float(c[0]), "v": float(c[1]), "cov": (ARUCO_SIGMA_PX**2 * np.eye(2)).tolist(),
                        "polarity": det.polarity, "code": int(i), "family": "aruco"})
    for i in np.flatnonzero(keep):
        coded = code[i] >= 0
        out.append({"u": float(det.uv[i, 0]), "v": float(det.uv[i, 1]), "cov": det.cov[i].tolist(),
                    "polarity": det.polarity, "code": int(code[i]) if coded else None,
                    "family": cam.coded_family if coded else None})
    return det, out


def draw_detections(image: np.ndarray, detections: list[dict]) -> np.ndarray:
    """An 8-bit colour copy of ``image`` with each centre marked (green dots, orange coded targets + code)."""
    img = image
    if img.dtype == np.uint16:
        img = cv2.convertScaleAbs(img, alpha=255.0 / max(int(img.max()), 1))
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    img = img.copy()
    scale = max(1, int(round(max(img.shape[:2]) / 1500)))
    for d in detections:
        p = (int(round(d["u"] * 16)), int(round(d["v"] * 16)))
        if d["code"] is None:
            cv2.circle(img, p, 6 * 16 * scale, (0, 200, 0), scale, cv2.LINE_AA, shift=4)
        else:
            cv2.circle(img, p, 10 * 16 * scale, (0, 140, 255), 2 * scale, cv2.LINE_AA, shift=4)
            cv2.putText(img, str(d["code"]), (int(d["u"]) + 12 * scale, int(d["v"]) - 12 * scale),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, (0, 140, 255), 2 * scale, cv2.LINE_AA)
    return img


def detect_command(args, out) -> int:
    cam = load_camera_file(args.camera)
    over = {k: v for k, v in (("polarity", getattr(args, "polarity", None)), ("coded_family", getattr(args, "family", None)))
            if v is not None}
    if over:
        try:
            cam = CameraFile(**(cam.model_dump() | over))
        except ValidationError as e:
            err = e.errors()[0]
            raise InputError(f"cell detect: --{'family' if err['loc'][0] == 'coded_family' else err['loc'][0]}: "
                             f"{err['msg']}") from None
    image = read_image(args.image)
    det, dets = detect_image(image, cam)
    doc = {"image": str(args.image), "width": int(image.shape[1]), "height": int(image.shape[0]),
           "polarity": det.polarity, "noise": float(det.noise),
           "noise_levels": None if det.noise_levels is None else
           {"variance_at_zero": det.noise_levels[0], "variance_per_grey_level": det.noise_levels[1]},
           "detections": dets}
    if args.png is not None:
        png = Path(args.png)
        if png.suffix.lower() != ".png":
            raise InputError(f"--png {png}: give a .png file name")
        tmp = png.with_name(png.name + ".part.png")
        if not cv2.imwrite(str(tmp), draw_detections(image, dets)):
            raise InputError(f"--png {png}: cannot write there")
        tmp.replace(png)

    def human(d):
        n_coded = sum(1 for x in d["detections"] if x["code"] is not None)
        out.say(f"{d['image']}: {d['width']}x{d['height']}, {d['polarity']} dots, noise {d['noise']:.2f} grey levels: "
                f"{len(d['detections']) - n_coded} dots, {n_coded} coded targets")
        lv = d.get("noise_levels")
        if lv and lv["variance_per_grey_level"] != 0:  # the line the covariances propagated (decision 0047)
            out.say(f"  pixel noise variance {lv['variance_at_zero']:.3f} + {lv['variance_per_grey_level']:.4f} x grey "
                    "level (measured on the dots' tops and rings)")
        elif lv:
            out.say("  pixel noise: one figure for every pixel (too few dots to measure its growth with the light)")
        if not out.as_json:
            for x in d["detections"]:
                sd = np.sqrt(np.diag(np.asarray(x["cov"])))
                tag = f"  code {x['code']} ({x['family']})" if x["code"] is not None else ""
                print(f"{x['u']:10.3f} {x['v']:10.3f}  sd {sd[0]:.3f} {sd[1]:.3f} px{tag}")

    out.result(doc, human)
    return 0
