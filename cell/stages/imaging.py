"""Measuring the dots in one image: the chain every job (inspection, hand-eye, placement, the paper's
experiments) uses, in one place.

detect -> drop blobs inside coded markers -> offer the matcher only the targets in view from the
approximate pose (a hidden dot would steal a visible neighbour's detection) -> identify -> drop dots
whose rim an edge of the part clips -> remove the eccentricity of each dot's ellipse. Coded targets
identify the image and refine its pose; they are not measured (docs/decisions/0004).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.camera import Intrinsics, invert
from calibration.ringcodes import RING_FAMILIES, decode_ring_codes
from calibration.targets import (DetectionOptions, detect_coded_targets, detect_dots, eccentricity_bias,
                                 identify_targets)
from planning.visibility import Occluder, VisibilityOptions, compute_visibility

#: a coded marker's square, grown by a third, covers its quiet zone: blobs there are the marker's
MARKER_GROW = 1.33


def rim_clear(occluder: Occluder, xyz: np.ndarray, normals: np.ndarray, radius_m: float, eye: np.ndarray,
              samples: int = 12, margin: float = 1.3) -> np.ndarray:
    """Whether the whole rim of each dot (grown by ``margin``) is in view from ``eye``, (n,) bool.

    A dot partly hidden by an edge of the part images as a clipped disc whose centroid is biased by
    up to its radius; such an observation is dropped, not measured.
    """
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    normals = np.asarray(normals, dtype=float).reshape(-1, 3)
    n = len(xyz)
    if n == 0:
        return np.zeros(0, dtype=bool)
    a = np.where(np.abs(normals[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(normals, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normals, e1)
    ang = np.linspace(0, 2 * np.pi, samples, endpoint=False)
    rim = (xyz[:, None] + margin * radius_m * (np.cos(ang)[None, :, None] * e1[:, None] + np.sin(ang)[None, :, None]
           * e2[:, None]) + 2e-4 * normals[:, None])
    hit = occluder.occluded(rim.reshape(-1, 3), np.broadcast_to(np.asarray(eye, dtype=float), (n * samples, 3)))
    return ~hit.reshape(n, samples).any(axis=1)


def inside_any(uv: np.ndarray, quads: np.ndarray, grow: float = 1.0) -> np.ndarray:
    """Which points ``uv: (k, 2)`` lie inside any of the quadrilaterals ``quads: (c, 4, 2)`` grown by ``grow``."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    inside = np.zeros(len(uv), dtype=bool)
    for q in np.asarray(quads, dtype=float).reshape(-1, 4, 2):
        c = q.mean(axis=0)
        poly = ((q - c) * grow + c).astype(np.float32)
        inside |= np.array([cv2.pointPolygonTest(poly, (float(u), float(v)), False) >= 0 for u, v in uv], dtype=bool)
    return inside


@dataclass
class DotMeasurement:
    """The dots measured in one image.

    Attributes:
        target: (k,) index into the part's targets.
        uv: (k, 2) centres, eccentricity-corrected (pixels, origin at the centre of the top-left pixel).
        cam_from_part: (4, 4) the pose the dots were named with.
        n_unidentified: blobs no target was matched to (marker pieces, glints, edges).
        n_partly_hidden: identified dots dropped because an edge of the part clips them.
        cov: (k, 2, 2) each centre's covariance from the detector (px^2, ``Detections.cov``), or None
            when the caller gave none.
        bg_cov: (k, 2, 2) the detector's bound on each centre's error from a background that is not a
            plane (px^2, ``Detections.background_cov``), or None.
    """

    target: np.ndarray
    uv: np.ndarray
    cam_from_part: np.ndarray
    n_unidentified: int = 0
    n_partly_hidden: int = 0
    cov: np.ndarray | None = None
    bg_cov: np.ndarray | None = None


def name_dots(det_uv: np.ndarray, part, intr: Intrinsics, cam_from_part: np.ndarray, occluder: Occluder, *,
              max_dist_px: float = 25.0, incidence_max_rad: float = float(np.deg2rad(85.0)),
              coded_ids: np.ndarray | None = None, coded_uv: np.ndarray | None = None,
              det_cov: np.ndarray | None = None, det_bg_cov: np.ndarray | None = None) -> DotMeasurement:
    """Identify detected dot centres ``det_uv: (k, 2)`` with an approximate pose and measure them.

    ``det_cov, det_bg_cov: (k, 2, 2)`` (px^2) travel with the centres they belong to.

    Only dots in view from the pose at no more than ``incidence_max_rad`` are offered to the matcher;
    coded detections (``coded_ids``, ``coded_uv``) refine the pose first (PnP) when there are enough.
    """
    t = part.targets
    det_uv = np.asarray(det_uv, dtype=float).reshape(-1, 2)
    seeable = VisibilityOptions(margin_px=0.0, incidence_max_rad=incidence_max_rad, min_target_px=1.0)
    in_view = compute_visibility(part, intr, invert(cam_from_part)[None], seeable, occluder=occluder)[0]
    with_codes = coded_ids is not None and len(coded_ids) > 0
    cand = np.flatnonzero((in_view & (t.code < 0)) | ((t.code >= 0) if with_codes else False))
    sub = identify_targets(det_uv, t.xyz[cand], t.code[cand], intr, cam_from_part, max_dist_px,
                           coded_ids=coded_ids if with_codes else None, coded_uv=coded_uv if with_codes else None)
    match = np.where(sub >= 0, cand[np.maximum(sub, 0)], -1)
    dots = np.flatnonzero((match >= 0) & (t.code[np.maximum(match, 0)] < 0))
    radius = part.target_diameter_m / 2
    eye = invert(cam_from_part)[:3, 3]
    clear = rim_clear(occluder, t.xyz[match[dots]], t.normals[match[dots]], radius, eye)
    dots = dots[clear]
    tid = match[dots]
    bias = eccentricity_bias(intr, cam_from_part, t.xyz[tid], t.normals[tid], radius)
    return DotMeasurement(tid, det_uv[dots] - bias, np.asarray(cam_from_part, dtype=float),
                          int((match < 0).sum()), int((~clear).sum()),
                          None if det_cov is None else np.asarray(det_cov)[dots],
                          None if det_bg_cov is None else np.asarray(det_bg_cov)[dots])


def detection_options(camera) -> DetectionOptions:
    """The detector's options for a job's ``[camera]`` section (``polarity``, ``detection``)."""
    polarity = getattr(camera, "polarity", "bright")
    if getattr(camera, "detection", "cell") == "photograph":
        return DetectionOptions.for_real_images(polarity=polarity)
    return DetectionOptions(polarity=polarity)


def measure_image(image: np.ndarray, part, intr: Intrinsics, cam_from_part_approx: np.ndarray, occluder: Occluder, *,
                  detection: DetectionOptions | None = None, max_dist_px: float = 25.0,
                  incidence_max_rad: float = float(np.deg2rad(85.0)),
                  coded_family: str = "aruco") -> tuple[DotMeasurement, dict]:
    """Detect, identify and measure the dots of one image from its approximate pose.

    ``coded_family``: "aruco" (markers found by OpenCV) or a ring-code family (``calibration.ringcodes``:
    the code rings around detected dots are read, the rings' pieces dropped). Either way the coded targets
    name the image and refine its pose; they are not measured (decision 0004).
    Returns the measurement and counts for the record (dots, coded markers seen).
    """
    t = part.targets
    code_to_index = {int(c): i for i, c in enumerate(t.code) if c >= 0}
    det = detect_dots(image, detection or DetectionOptions())
    if coded_family in RING_FAMILIES:
        rc = decode_ring_codes(image, det, coded_family)
        codes, centres = rc.code, det.uv[rc.index]
        known = np.array([int(c) in code_to_index for c in codes], dtype=bool)
        keep = ~rc.ring_parts(det.uv)
        keep[rc.index] = False
    else:
        codes, corners, centres = detect_coded_targets(image)
        known = np.array([int(c) in code_to_index for c in codes], dtype=bool)
        keep = ~inside_any(det.uv, corners[known], grow=MARKER_GROW)
    m = name_dots(det.uv[keep], part, intr, cam_from_part_approx, occluder, max_dist_px=max_dist_px,
                  incidence_max_rad=incidence_max_rad, coded_ids=codes[known], coded_uv=centres[known],
                  det_cov=det.cov[keep], det_bg_cov=None if det.background_cov is None else det.background_cov[keep])
    return m, {"n_dots": int(keep.sum()), "n_coded": int(known.sum())}
