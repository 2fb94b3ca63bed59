"""Measuring the dots in one image: the chain every job (inspection, hand-eye, placement, the paper's
experiments) uses, in one place.

detect -> drop blobs inside coded markers -> offer the matcher only the targets in view from the
approximate pose (a hidden dot would steal a visible neighbour's detection) -> identify -> drop dots
whose rim an edge of the part clips -> check each named dot against the ellipse its target must image
as (a dot clipped by something the CAD does not have, washed out on one side, or merged with a glint is
left unnamed, with the reason) -> check the image's naming as a whole (a resection on the named dots:
a naming the pose does not explain is dropped) -> remove the eccentricity of each dot's ellipse. Coded
targets identify the image and refine its pose; they are not measured (docs/decisions/0004).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from calibration.camera import Intrinsics, invert, make_pose, project
from calibration.dots import MIN_RING_PX
from calibration.ringcodes import RING_FAMILIES, decode_ring_codes
from calibration.errors import CalibrationError
from calibration.targets import (DetectionOptions, detect_coded_targets, detect_dots, eccentricity_bias,
                                 blur_variances, ellipse_moments, identify_targets, refine_pose_pnp,
                                 shape_ratios)
from cell.stages.surface_labels import SurfaceLabeller
from planning.visibility import Occluder, VisibilityOptions, compute_visibility

#: a coded marker's square, grown by a third, covers its quiet zone: blobs there are the marker's
MARKER_GROW = 1.33

#: a named dot's second moments against those of the ellipse its target images as (eigenvalues of the one
#: in the other's metric). Blur only grows a dot, so below SHAPE_MIN it was clipped (an edge or a fixture the
#: CAD does not have, glare eating one side); above SHAPE_MAX, after BLUR_PX of blur is allowed for, it is
#: two blobs merged or a glint. On the example's renders whole dots lie in 0.99..1.41 (1,224 dots), the
#: clipped ones that biased centres by 1-24 px mostly below 0.85 or above 1.9 (decision 0027, hamper).
SHAPE_MIN = 0.85
SHAPE_MAX = 1.5
BLUR_PX = 1.0
#: an image whose named dots a resection (pose only, the nominal interior orientation) leaves with a median
#: residual above this is named inconsistently: its naming is not trusted at all. Real deviations of a few
#: targets do not move a median; a naming that is wrong dot by dot does. A third of the matching window, so
#: that an uncorrected lens (a real camera's distortion before ADJUST estimates it) is not taken for one.
RESECTION_MEDIAN_PX = 8.0
#: fewest named dots for the resection check (below it the image's naming is kept unchecked and said so)
RESECTION_MIN_DOTS = 8


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
        clipped_share: (k,) the share of each dot's pixels the sensor clipped (``Detections.saturated`` over its
            area; the bundle adds the detector model's saturation term), or None.
        ellipse: (k,) bool, the centre is the ellipse of the dot's half-level contour (``Detections.ellipse``:
            a clipped dot, a dot next to an edge; decision 0037), not its centroid; or None.
        dropped: (target index, reason) of every dot that was named and then left unnamed (partly hidden,
            shape unlike its target's ellipse, the image's naming inconsistent); never silent.
        resection_median_px: median residual of the resection on the named dots (None: too few to check).
        blur_px2: (k,) the optical blur each dot's image shows, a variance along each axis (px^2,
            :func:`calibration.targets.blur_variances`: its second moments less its ellipse's and the pixel's; NaN
            for a clipped dot, whose flat top says nothing of it); ADJUST's blur term (decision 0049); or None.
        moments_px2: (k,) half the trace of each dot's measured second moments (px^2; NaN for a clipped dot): ADJUST
            measures the blur again against the lens it found (decision 0054); or None.
        eccentricity_px: (k, 2) the eccentricity taken off each centre (the nominal lens at the robot's pose): ADJUST
            takes it again with the lens it found, its distortion included (decision 0054).
        naming_radial: ``(k1, k2)`` of the radial lens the dots were named with, where the nominal one left the
            image's outer dots off their projections (:func:`naming_radial`); None: the nominal lens.
        named_turned_deg: how far (deg) the pose the dots were named from turned from the robot's, where the robot's
            pose left them off their projections and a resection named them again (:func:`naming_radial`); None: the
            robot's pose.
        codes_seen: ``(target index, px, limit px)`` of every decoded coded marker of the part: how far its centre is
            from the projection of its own target at the pose the named dots resect (the naming pose when too few),
            and the distance beyond which it is not where the placement puts it (:func:`code_limit_px`; decision 0064).
        clip_bound: (k, 2) px, how far a clipped dot's centre may be off for its unknown level
            (``Detections.clip_bound``, decision 0050; zero for the others); ADJUST carries it; or None.
        outline: (k, 2) ``[chi2, n]`` of each dot's contour about its ellipse (``Detections.outline``; NaN: not
            fitted), and ``centroid_chi2`` (k,) its centroid's difference from that ellipse's centre in the
            difference's covariance (NaN for a dot centred by its ellipse): what :mod:`cell.stages.outline` judges
            a target's print by (decision 0051); or None.
    """

    target: np.ndarray
    uv: np.ndarray
    cam_from_part: np.ndarray
    n_unidentified: int = 0
    n_partly_hidden: int = 0
    cov: np.ndarray | None = None
    bg_cov: np.ndarray | None = None
    clipped_share: np.ndarray | None = None
    dropped: list = field(default_factory=list)
    resection_median_px: float | None = None
    ellipse: np.ndarray | None = None
    blur_px2: np.ndarray | None = None
    clip_bound: np.ndarray | None = None
    outline: np.ndarray | None = None
    centroid_chi2: np.ndarray | None = None
    moments_px2: np.ndarray | None = None
    eccentricity_px: np.ndarray | None = None
    naming_radial: tuple[float, float] | None = None
    named_turned_deg: float | None = None
    codes_seen: list = field(default_factory=list)

    @property
    def n_shape(self) -> int:
        """Named dots dropped because their shape is not their target's ellipse."""
        return sum(1 for _, why in self.dropped if why.startswith("shape"))


#: the nominal lens's median residual over an image's named dots above which a radial lens is fitted to them, and
#: the share of it the fitted lens must leave for the dots to be named again with it
NAMING_RADIAL_PX = 1.0
NAMING_RADIAL_GAIN = 0.5


#: how far (px) a detection may be from a projection to vote for the image's common shift, the votes' bin (px),
#: and the shift (px) below which the robot's pose is kept for the naming
SHIFT_REACH_PX = 60.0
SHIFT_BIN_PX = 2.0
SHIFT_MIN_PX = 2.0


def common_shift(proj_uv: np.ndarray, det_uv: np.ndarray) -> np.ndarray | None:
    """The shift (px, (2,)) that most of the projections ``proj_uv: (n, 2)`` need to land on detections
    ``det_uv: (k, 2)``, or None when there is no clear one or it is below :data:`SHIFT_MIN_PX`.

    Every detection-projection pair within :data:`SHIFT_REACH_PX` votes for its difference; the votes' densest
    cell (:data:`SHIFT_BIN_PX`, 3x3 cells summed) wins when it holds at least 6 votes and a quarter of the
    projections, and is refined by the mean of the votes within a cell of it. A principal point off the data
    sheet's or a hand-eye error turns the whole image and shows as such a shift; the nearest-neighbour naming at
    the robot's pose would pair dots with their neighbours' projections."""
    if len(proj_uv) < 6 or len(det_uv) < 6:
        return None
    from scipy.spatial import cKDTree

    pairs = cKDTree(proj_uv).query_ball_point(det_uv, SHIFT_REACH_PX)
    d = [det_uv[i] - proj_uv[j] for i, js in enumerate(pairs) for j in js]
    if len(d) < 6:
        return None
    d = np.asarray(d)
    n = int(np.ceil(SHIFT_REACH_PX / SHIFT_BIN_PX))
    h, _, _ = np.histogram2d(d[:, 0], d[:, 1], bins=2 * n + 1, range=[[-(n + 0.5) * SHIFT_BIN_PX,
                                                                     (n + 0.5) * SHIFT_BIN_PX]] * 2)
    k = np.ones((3, 3))
    from scipy.signal import convolve2d

    hs = convolve2d(h, k, mode="same")
    a, b = np.unravel_index(int(np.argmax(hs)), hs.shape)
    if hs[a, b] < max(6, 0.25 * len(proj_uv)):
        return None
    peak = (np.array([a, b]) - n) * SHIFT_BIN_PX
    near = np.all(np.abs(d - peak) <= 1.5 * SHIFT_BIN_PX, axis=1)
    shift = d[near].mean(axis=0)
    return shift if np.linalg.norm(shift) >= SHIFT_MIN_PX else None


def turned_by(intr: Intrinsics, cam_from_part: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``cam_from_part`` turned about its projection centre so that the principal point's projection moves by
    ``shift`` (px)."""
    v = np.array([shift[0] / intr.fx_px, shift[1] / intr.fy_px, 1.0])
    v /= np.linalg.norm(v)
    axis = np.cross([0.0, 0.0, 1.0], v)
    angle = np.arcsin(min(1.0, np.linalg.norm(axis)))
    Rd = cv2.Rodrigues(axis / max(np.linalg.norm(axis), 1e-15) * angle)[0]
    # a point on the principal ray is seen along v afterwards: the camera turned the other way
    out = np.array(cam_from_part, dtype=float, copy=True)
    out[:3, :3] = Rd @ out[:3, :3]
    out[:3, 3] = Rd @ out[:3, 3]
    return out


def naming_radial(intr: Intrinsics, cam_from_part: np.ndarray, xyz: np.ndarray, det_uv: np.ndarray,
                  match: np.ndarray, code: np.ndarray) -> tuple[Intrinsics, np.ndarray] | None:
    """The lens and pose to name an image's dots again with, where the nominal lens at the robot's pose leaves its
    named dots ``match`` (index into ``xyz`` per detection, -1: unnamed) off their projections; None when it does
    not (median residual at most :data:`NAMING_RADIAL_PX`) or there are fewer than 15.

    First the pose: a resection from the robot's pose, without the dots its start puts beyond 3 robust sigma
    (a principal point off the data sheet's, or an arm's pose error, turn the whole image). If the nominal lens
    at that pose fits the dots (median at most :data:`NAMING_RADIAL_PX`), ``(intr, pose)``. Otherwise a radial
    lens (k1, k2 with the pose; the nominal lens's other terms), fitted robustly: ``(lens, pose)`` when it brings
    the median below :data:`NAMING_RADIAL_GAIN` of the resected nominal's, else ``(intr, pose)`` when the resection
    alone halved the robot's pose's median, else None. The lens is fitted with its pose and used with it: a k1, k2
    paired with another pose is not a lens."""
    from scipy.optimize import least_squares

    sel = np.flatnonzero((match >= 0) & (code[np.maximum(match, 0)] < 0))
    if len(sel) < 15:
        return None
    X, uv = xyz[match[sel]], det_uv[sel]
    r = np.linalg.norm(project(intr, cam_from_part, X) - uv, axis=1)
    at_start = float(np.median(r))
    if not at_start > NAMING_RADIAL_PX:
        return None
    pose = cam_from_part
    try:
        for _ in range(2):
            good = r <= max(1.0, 3.0 * 1.4826 * np.median(r)) if np.all(np.isfinite(r)) else np.isfinite(r)
            pose = refine_pose_pnp(intr, pose, X[good] if good.sum() >= 6 else X, uv[good] if good.sum() >= 6 else uv)
            r = np.linalg.norm(project(intr, pose, X) - uv, axis=1)
    except CalibrationError:
        return None
    before = float(np.median(r))
    if before <= NAMING_RADIAL_PX:
        return intr, pose
    rvec = cv2.Rodrigues(pose[:3, :3])[0].ravel()

    def lens(p):
        return replace(intr, k1=intr.k1 + p[6], k2=intr.k2 + p[7])

    def pose_of(p):
        return make_pose(cv2.Rodrigues(p[:3])[0], p[3:6])

    def resid(p):
        return (project(lens(p), pose_of(p), X) - uv).ravel()

    fit = least_squares(resid, np.r_[rvec, pose[:3, 3], 0.0, 0.0], loss="soft_l1", f_scale=2.0, x_scale="jac")
    after = float(np.median(np.linalg.norm(fit.fun.reshape(-1, 2), axis=1)))
    if fit.success and after < NAMING_RADIAL_GAIN * before:
        return lens(fit.x), pose_of(fit.x)
    # no radial lens helps: the resected pose alone, where it halved the robot's pose's median
    return (intr, pose) if before < NAMING_RADIAL_GAIN * at_start else None


def name_dots(det_uv: np.ndarray, part, intr: Intrinsics, cam_from_part: np.ndarray, occluder: Occluder, *,
              max_dist_px: float = 25.0, incidence_max_rad: float = float(np.deg2rad(85.0)),
              coded_ids: np.ndarray | None = None, coded_uv: np.ndarray | None = None,
              det_cov: np.ndarray | None = None, det_bg_cov: np.ndarray | None = None,
              det_axes: np.ndarray | None = None, det_ring_px: np.ndarray | None = None,
              det_clipped: np.ndarray | None = None, det_ellipse: np.ndarray | None = None,
              det_clip_bound: np.ndarray | None = None, det_outline: np.ndarray | None = None,
              det_shift: np.ndarray | None = None, det_shift_cov: np.ndarray | None = None) -> DotMeasurement:
    """Identify detected dot centres ``det_uv: (k, 2)`` with an approximate pose and measure them.

    ``det_cov, det_bg_cov: (k, 2, 2)`` (px^2), ``det_clip_bound: (k, 2)`` (px) and the outline's figures
    (``Detections.outline``, ``centroid_shift``, ``centroid_shift_cov``) travel with the centres they belong to.
    ``det_axes: (k, 2, 2)`` (px^2, ``Detections.axes``): each named dot's shape is checked against its target's ellipse
    (:data:`SHAPE_MIN`, :data:`SHAPE_MAX`) and dropped with the reason when it is not that ellipse; None: no
    shape check. ``det_ring_px: (k,)`` (``Detections.ring_px``): a named dot whose background ring had fewer than
    :data:`calibration.dots.MIN_RING_PX` pixels is dropped with the reason: its centre's error from the background
    cannot be bounded (its zero bound would say "a plane" without having looked; decision 0030).

    Only dots in view from the pose at no more than ``incidence_max_rad`` are offered to the matcher;
    coded detections (``coded_ids``, ``coded_uv``) refine the pose first (PnP) when there are enough.
    The naming is then checked as a whole by a resection (:data:`RESECTION_MEDIAN_PX`).
    """
    t = part.targets
    det_uv = np.asarray(det_uv, dtype=float).reshape(-1, 2)
    seeable = VisibilityOptions(margin_px=0.0, incidence_max_rad=incidence_max_rad, min_target_px=1.0)
    code_to_index = {int(c): i for i, c in enumerate(t.code) if c >= 0}
    if coded_ids is not None and len(coded_ids):  # the part's codes only
        own = np.array([int(c) in code_to_index for c in coded_ids], dtype=bool)
        coded_ids = np.asarray(coded_ids, dtype=int)[own]
        coded_uv = np.asarray(coded_uv, dtype=float).reshape(-1, 2)[own]
    code_idx = np.array([code_to_index[int(c)] for c in coded_ids], dtype=int) if coded_ids is not None else \
        np.zeros(0, dtype=int)
    all_code_uv = np.zeros((0, 2)) if coded_uv is None else np.asarray(coded_uv, dtype=float).reshape(-1, 2)
    with_codes = len(code_idx) > 0

    def named(lens, pose, in_view=None):
        if in_view is None:
            in_view = compute_visibility(part, lens, invert(pose)[None], seeable, occluder=occluder)[0]
        cand = np.flatnonzero((in_view & (t.code < 0)) | ((t.code >= 0) if with_codes else False))
        if len(cand) == 0:  # nothing of the part in view from the pose (a part far off it, upside down): none named
            return np.full(len(det_uv), -1, dtype=int)
        sub = identify_targets(det_uv, t.xyz[cand], t.code[cand], lens, pose, max_dist_px,
                               coded_ids=coded_ids if with_codes else None, coded_uv=coded_uv if with_codes else None)
        return np.where(sub >= 0, cand[np.maximum(sub, 0)], -1)

    # the image's dots all off their projections by one shift (a principal point off the data sheet's, a hand-eye
    # error): named from the pose turned by it, not paired with their neighbours' projections
    start = cam_from_part
    in_view0 = compute_visibility(part, intr, invert(cam_from_part)[None], seeable, occluder=occluder)[0]
    ids = np.flatnonzero(in_view0 & (t.code < 0))
    shift = common_shift(project(intr, cam_from_part, t.xyz[ids]), det_uv) if len(ids) else None
    if shift is not None:
        start = turned_by(intr, cam_from_part, shift)
    if with_codes:  # markers far off their own projections while others are on theirs do not steer the pose (F2, 0064)
        off, limit = code_offsets(part, intr, start, code_idx, all_code_uv, max_dist_px)
        near = off <= limit
        # far: beyond STEER_OFF_FACTOR x the limit (swapped markers: 7x and more). A robot pose or hand-eye a little
        # off leaves every marker near its limit (a hand-eye 2 mm off: 74.5 px for 70.3): all of them still steer
        far = off > STEER_OFF_FACTOR * limit
        if near.any() and far.any():
            coded_ids, coded_uv = coded_ids[~far], all_code_uv[~far]
    match = named(intr, start, in_view0 if start is cam_from_part else None)  # the robot's pose: seen once
    # a principal point off the data sheet's, or a lens whose distortion the job does not state, moves the image's
    # dots off their projections: the pose resected from the named dots, and where that is not enough a radial lens
    # fitted with it, name them again (decisions 0054, 0055); MEASURE's centres do not depend on it
    naming = naming_radial(intr, start, t.xyz, det_uv, match, t.code)
    if naming is None and start is not cam_from_part:
        naming = (intr, start)
    naming_lens = turned = None
    if naming is not None:
        if naming[0] is not intr:
            naming_lens = naming[0]
        intr, name_pose = naming
        match = named(intr, name_pose)
        R = name_pose[:3, :3] @ np.asarray(cam_from_part, dtype=float)[:3, :3].T
        turned = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
    dots = np.flatnonzero((match >= 0) & (t.code[np.maximum(match, 0)] < 0))
    radius = part.target_diameter_m / 2
    eye = invert(cam_from_part)[:3, 3]
    clear = rim_clear(occluder, t.xyz[match[dots]], t.normals[match[dots]], radius, eye)
    dropped = [(int(i), "partly hidden by an edge of the part (CAD)") for i in match[dots[~clear]]]
    dots = dots[clear]
    blur_all = np.full(len(det_uv), np.nan)  # the blur each dot shows, per detection (decision 0049)
    if det_axes is not None and len(dots):
        tid = match[dots]
        pred = ellipse_moments(intr, cam_from_part, t.xyz[tid], t.normals[tid], radius)
        blur_all[dots] = blur_variances(np.asarray(det_axes, dtype=float)[dots], pred)
        lo, hi = shape_ratios(np.asarray(det_axes, dtype=float)[dots], pred, BLUR_PX)
        ok = (lo >= SHAPE_MIN) & (hi <= SHAPE_MAX)
        dropped += [(int(i), f"shape {a:.2f}..{b:.2f} of its ellipse's (clipped, washed out or merged; "
                             f"{SHAPE_MIN}..{SHAPE_MAX} accepted)") for i, a, b in zip(tid[~ok], lo[~ok], hi[~ok])]
        dots = dots[ok]
    if det_ring_px is not None and len(dots):
        n_ring = np.asarray(det_ring_px)[dots]
        ok = n_ring >= MIN_RING_PX
        dropped += [(int(i), f"background not measurable: its ring has {int(n)} px (< {MIN_RING_PX}), so its "
                             "centre's error from the background cannot be bounded")
                    for i, n in zip(match[dots[~ok]], n_ring[~ok])]
        dots = dots[ok]
    tid = match[dots]
    bias = eccentricity_bias(intr, cam_from_part, t.xyz[tid], t.normals[tid], radius)
    uv = det_uv[dots] - bias
    keep = np.arange(len(dots))
    med = None
    dots_pose = name_pose if naming is not None else start  # the pose the dots were named from
    if len(dots) >= RESECTION_MIN_DOTS:
        try:
            pose = refine_pose_pnp(intr, cam_from_part, t.xyz[tid], uv)
            med = float(np.median(np.linalg.norm(uv - project(intr, pose, t.xyz[tid]), axis=1)))
        except CalibrationError:
            med = float("inf")
        if med <= RESECTION_MEDIAN_PX:
            dots_pose = pose
        if not med <= RESECTION_MEDIAN_PX:
            dropped += [(int(i), f"the image's naming is inconsistent: resection median residual {med:.1f} px > "
                                 f"{RESECTION_MEDIAN_PX} px") for i in tid]
            dots, tid, uv, keep = dots[:0], tid[:0], uv[:0], keep[:0]
    blur = moments = None
    if det_axes is not None:  # a clipped dot's flat top says nothing of its blur
        blur = blur_all[dots]
        moments = 0.5 * np.trace(np.asarray(det_axes, dtype=float).reshape(-1, 2, 2)[dots], axis1=1, axis2=2)
        if det_clipped is not None:
            blur[np.asarray(det_clipped, dtype=float)[dots] > 0] = np.nan
            moments[np.asarray(det_clipped, dtype=float)[dots] > 0] = np.nan
    codes_seen = []
    if len(code_idx):  # each decoded marker against its own target's projection where the dots put the part (0064)
        off, limit = code_offsets(part, intr, dots_pose, code_idx, all_code_uv, max_dist_px)
        codes_seen = [(int(i), float(d), float(lim)) for i, d, lim in zip(code_idx, off, limit)]
    outline = centroid_chi2 = None
    if det_outline is not None:
        outline = np.asarray(det_outline, dtype=float).reshape(-1, 4)[dots, :2]
        centroid_chi2 = np.full(len(dots), np.nan)
        if det_shift is not None and det_shift_cov is not None and len(dots):
            sh = np.asarray(det_shift, dtype=float).reshape(-1, 2)[dots]
            sc = np.asarray(det_shift_cov, dtype=float).reshape(-1, 2, 2)[dots]
            fin = np.isfinite(sh).all(axis=1) & np.isfinite(sc).all(axis=(1, 2))
            fin[fin] &= np.linalg.det(sc[fin]) > 0  # a covariance that says nothing gives no figure
            if fin.any():
                centroid_chi2[fin] = np.einsum("ka,ka->k", sh[fin],
                                               np.linalg.solve(sc[fin], sh[fin][..., None])[..., 0])
    return DotMeasurement(tid, uv, np.asarray(cam_from_part, dtype=float),
                          int((match < 0).sum()), int((~clear).sum()),
                          None if det_cov is None else np.asarray(det_cov)[dots],
                          None if det_bg_cov is None else np.asarray(det_bg_cov)[dots],
                          None if det_clipped is None else np.asarray(det_clipped, dtype=float)[dots], dropped, med,
                          None if det_ellipse is None else np.asarray(det_ellipse, dtype=bool)[dots], blur,
                          None if det_clip_bound is None
                          else np.asarray(det_clip_bound, dtype=float).reshape(-1, 2)[dots], outline, centroid_chi2,
                          moments, bias[keep], None if naming_lens is None else (naming_lens.k1, naming_lens.k2),
                          turned, codes_seen)


#: a decoded coded marker whose centre is more than this many imaged dot diameters (and more than the naming window)
#: from the projection of its own target is not where the placement puts it: targets are spaced at least about two
#: diameters apart (each dot's background ring), so a part one step of its layout off moves every marker by at least
#: that, while a right placement leaves a marker within the naming's residual (0.0-1.2 px on the example; 0064)
CODE_OFF_DIAMETERS = 2.0

#: a marker leaves the naming pose's markers only when it is this many times beyond its limit while another is within
#: its own: a marker swapped with another, not a pose a few pixels off (decision 0064)
STEER_OFF_FACTOR = 2.0


def code_offsets(part, intr: Intrinsics, cam_from_part: np.ndarray, idx: np.ndarray, uv: np.ndarray,
                 window_px: float) -> tuple[np.ndarray, np.ndarray]:
    """How far (px) each coded marker seen at ``uv: (c, 2)`` is from the projection of its own target ``idx: (c,)``
    at ``cam_from_part``, and the limit beyond which it is not where that pose puts it: :data:`CODE_OFF_DIAMETERS`
    imaged dot diameters at the marker's depth, at least ``window_px`` (the naming window)."""
    idx = np.asarray(idx, dtype=int)
    if len(idx) == 0:
        return np.zeros(0), np.zeros(0)
    xyz = part.targets.xyz[idx]
    depth = xyz @ np.asarray(cam_from_part, dtype=float)[2, :3] + cam_from_part[2, 3]
    off = np.full(len(idx), np.inf)
    front = depth > 0
    if front.any():
        off[front] = np.linalg.norm(project(intr, cam_from_part, xyz[front]) - np.asarray(uv)[front], axis=1)
    diameter = max(intr.fx_px, intr.fy_px) * part.target_diameter_m / np.maximum(depth, 1e-6)
    return off, np.maximum(CODE_OFF_DIAMETERS * diameter, window_px)


def surface_labeller(camera, part) -> SurfaceLabeller | None:
    """The CAD's surface labeller when the job's ``[camera] background_mask`` is "cad", else None."""
    return SurfaceLabeller(part.mesh) if getattr(camera, "background_mask", "none") == "cad" else None


def detection_options(camera) -> DetectionOptions:
    """The detector's options for a job's ``[camera]`` section (``polarity``, ``detection``); every dot's outline is
    fitted (``DetectionOptions.outline``: a chipped or stained target is found by it, decision 0051)."""
    polarity = getattr(camera, "polarity", "bright")
    if getattr(camera, "detection", "cell") == "photograph":
        return DetectionOptions.for_real_images(polarity=polarity, outline=True)
    return DetectionOptions(polarity=polarity, outline=True)


def measure_image(image: np.ndarray, part, intr: Intrinsics, cam_from_part_approx: np.ndarray, occluder: Occluder, *,
                  detection: DetectionOptions | None = None, max_dist_px: float = 25.0,
                  incidence_max_rad: float = float(np.deg2rad(85.0)),
                  coded_family: str = "aruco", shape_check: bool = True,
                  surfaces: SurfaceLabeller | None = None) -> tuple[DotMeasurement, dict]:
    """Detect, identify and measure the dots of one image from its approximate pose.

    ``coded_family``: "aruco" (markers found by OpenCV) or a ring-code family (``calibration.ringcodes``:
    the code rings around detected dots are read, the rings' pieces dropped). Either way the coded targets
    name the image and refine its pose; they are not measured (decision 0004).
    ``shape_check``: drop named dots whose shape is not their target's ellipse (:func:`name_dots`).
    ``surfaces`` (``[camera] background_mask = "cad"``): once the dots are named, the image's pose is resected on
    them, the surface each pixel around a named dot sees is labelled from the CAD at that pose and the dots are
    detected again with each dot's background fitted on its own surface only (:func:`masked_labels`;
    decision 0035). None: one detection, every ring pixel used.
    Returns the measurement and counts for the record (dots, coded markers seen; with ``surfaces``, whether the
    image was masked).
    """
    m, counts, _ = measure_image_detections(image, part, intr, cam_from_part_approx, occluder, detection=detection,
                                            max_dist_px=max_dist_px, incidence_max_rad=incidence_max_rad,
                                            coded_family=coded_family, shape_check=shape_check, surfaces=surfaces)
    return m, counts


def measure_image_detections(image: np.ndarray, part, intr: Intrinsics, cam_from_part_approx: np.ndarray,
                             occluder: Occluder, *, detection: DetectionOptions | None = None,
                             max_dist_px: float = 25.0, incidence_max_rad: float = float(np.deg2rad(85.0)),
                             coded_family: str = "aruco", shape_check: bool = True,
                             surfaces: SurfaceLabeller | None = None):
    """:func:`measure_image`, with the detections the measurement was named from (the last detection: the masked
    one with ``surfaces``): (measurement, counts, detections). MEASURE judges a smeared image by their moments."""
    det = detect_dots(image, detection or DetectionOptions())
    m, counts = _name_detections(image, det, part, intr, cam_from_part_approx, occluder, max_dist_px,
                                 incidence_max_rad, coded_family, shape_check)
    if surfaces is not None:
        labels = masked_labels(surfaces, part, intr, m)
        if labels is not None:
            det = detect_dots(image, detection or DetectionOptions(), labels=labels)
            m, counts = _name_detections(image, det, part, intr, cam_from_part_approx, occluder, max_dist_px,
                                         incidence_max_rad, coded_family, shape_check)
        # said in the record: an image with too few named dots for a pose to label with is measured unmasked
        counts["background_mask"] = "cad" if labels is not None else "none (no pose to label with)"
    # the pixel noise's line that the centres' covariances propagated (decision 0047): in the record, with its fallback
    counts["noise_levels"] = None if det.noise_levels is None else [float(v) for v in det.noise_levels]
    return m, counts, det


def masked_labels(surfaces: SurfaceLabeller, part, intr: Intrinsics, m: DotMeasurement) -> np.ndarray | None:
    """The surface labels around the dots ``m`` named, at the pose resected on them (None: fewer than
    :data:`RESECTION_MIN_DOTS` named, or the resection failed: no pose good to a pixel to label with)."""
    t = part.targets
    if len(m.target) < RESECTION_MIN_DOTS:
        return None
    xyz = t.xyz[m.target]
    try:
        pose = refine_pose_pnp(intr, m.cam_from_part, xyz, m.uv)
    except CalibrationError:
        return None
    uv = project(intr, pose, xyz)
    depth = xyz @ pose[:3, :3].T + pose[:3, 3]
    # the dot's imaged diameter, plus blur, the detector's margin (2) and ring (2) and a spare pixel
    half = 0.5 * max(intr.fx_px, intr.fy_px) * part.target_diameter_m / np.maximum(depth[:, 2], 1e-6) + 7.0
    return surfaces.labels(intr, pose, uv, half)


def _name_detections(image, det, part, intr, cam_from_part_approx, occluder, max_dist_px, incidence_max_rad,
                     coded_family, shape_check) -> tuple[DotMeasurement, dict]:
    t = part.targets
    code_to_index = {int(c): i for i, c in enumerate(t.code) if c >= 0}
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
                  det_cov=det.cov[keep], det_bg_cov=None if det.background_cov is None else det.background_cov[keep],
                  det_axes=det.axes[keep] if shape_check else None,
                  det_ring_px=None if det.ring_px is None else det.ring_px[keep],
                  det_clipped=None if det.saturated is None else (det.saturated / np.maximum(det.area_px, 1.0))[keep],
                  det_ellipse=None if det.ellipse is None else det.ellipse[keep],
                  det_clip_bound=None if det.clip_bound is None else det.clip_bound[keep],
                  det_outline=None if det.outline is None else det.outline[keep],
                  det_shift=None if det.centroid_shift is None else det.centroid_shift[keep],
                  det_shift_cov=None if det.centroid_shift_cov is None else det.centroid_shift_cov[keep])
    return m, {"n_dots": int(keep.sum()), "n_coded": int(known.sum())}
