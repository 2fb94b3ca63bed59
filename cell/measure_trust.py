"""What ``cell measure`` and ``cell calibrate camera`` say of their own answer (decision 0057).

A folder of photographs is whatever the operator put there: images of two cameras or zoom settings, a layout whose
spacing is wrong, over-exposed dots, images the codes could not orient. A self-calibrating bundle absorbs much of it
into a camera that fits every image a little worse, and reported ``converged`` with a confident, wrong focal length
(an outside check: 5 images of another zoom among 10 gave fx 570.5 +- 1.7 px for 542.4). What is said here:

* :func:`doubts`: the bundle's own signals, each said (console, measure.json, report.json / report.html, journal):
  images not used and why, a solver hand-over, data snooping stopped before the end, targets it could not verify,
  a variance factor outside :data:`cell.stages.model_shape.VARIANCE_FACTOR_RANGE` against the camera file's
  ``sigma_px``. Snooping stopped before the end, or images that fit beyond :data:`CALIBRATION_MAX_SIGMA_RATIO` times
  ``sigma_px`` (data snooping tests against the a posteriori variance, so a misfit shared by every observation
  fails none: a 6 % wrong layout held as control fit 2.6 px with nothing rejected), make the measurement UNTRUSTED
  and refuse a camera calibration.

Photographs whose EXIF names more than one camera or focal length make it UNTRUSTED too (:func:`exif_doubt`). Tried
and left out: each image's own focal length against the others' (an F test of the network adjusted with and without
a focal length per image) told 5 zoomed images among 10 (F 305) but also flagged the clean set (F 56): a printed
sheet on cardboard is not its flat layout, and each image's focal length absorbs the difference. A folder of two
zoom settings without EXIF is only warned by its variance factor.
"""
from __future__ import annotations

import numpy as np

from cell.stages.model_shape import VARIANCE_FACTOR_RANGE

__all__ = ["doubts", "exif_settings", "exif_doubt", "geometry_doubts", "CALIBRATION_MAX_SIGMA_RATIO"]

#: a camera calibrated from fewer images is said (not untrusted): each image's orientation takes six of the few
#: images' degrees of freedom, and what the layout and the lens model get wrong goes into the interior orientation
MIN_SELF_CALIBRATION_IMAGES = 5
#: the images' roll about their optical axis must span this much (degrees) for the principal point and the
#: decentring to be told from the orientations (Fraser 1997, "Digital camera self-calibration": rolled images)
MIN_ROLL_SPAN_DEG = 60.0

#: a measurement whose images fit beyond this many times the camera file's sigma_px is UNTRUSTED, and ``cell calibrate
#: camera`` writes no camera from them (as the hand-eye)
CALIBRATION_MAX_SIGMA_RATIO = 3.0


def exif_settings(files: list) -> dict:
    """The camera settings the photographs' EXIF states, ``{(make, model, focal_mm): [names]}`` (files without a
    focal length in their EXIF are left out). More than one key: the folder mixes cameras or zoom settings."""
    from calibration.planar import exif_camera

    out: dict = {}
    for f in files:
        ex = exif_camera(f)
        if ex is not None:
            out.setdefault((ex.make, ex.model, round(float(ex.focal_mm), 2)), []).append(f.name)
    return out


def exif_doubt(settings: dict) -> dict | None:
    """An untrusted doubt when the EXIF of the photographs names more than one camera or focal length: one
    interior orientation cannot describe them, and a self-calibrating bundle takes a compromise for a camera (an
    outside check: 5 images of another zoom among 10 gave fx 570.5 +- 1.7 px for 542.4, with nothing failing)."""
    if len(settings) < 2:
        return None
    said = "; ".join(f"{(mk + ' ' + md).strip() or 'camera'} at {f:g} mm: {len(n)} image(s) ({', '.join(n[:3])}"
                     f"{' ...' if len(n) > 3 else ''})" for (mk, md, f), n in sorted(settings.items()))
    return {"kind": "cameras", "untrusted": True,
            "text": f"the photographs' EXIF names {len(settings)} camera settings ({said}): one camera setting per "
                    "folder"}


def doubts(res, sigma_px: float, images: list, used: list, settings: dict | None = None) -> list[dict]:
    """What makes the measurement doubtful, each ``{"kind", "untrusted": bool, "text"}``: ``untrusted`` ones make a
    measurement UNTRUSTED and refuse a camera calibration; the others are said. ``settings``: :func:`exif_settings`."""
    out = []
    if settings and (d := exif_doubt(settings)) is not None:
        out.append(d)
    left = [im for im in images if not any(im is u for u in used)]
    if left:
        out.append({"kind": "images", "untrusted": False,
                    "text": f"{len(left)} of {len(images)} image(s) not used: "
                            + "; ".join(f"{im.name}: {im.note or 'fewer than 6 targets identified'}" for im in left[:8])
                            + ("; ..." if len(left) > 8 else "")})
    if res.solver_fallback:
        out.append({"kind": "solver", "untrusted": False,
                    "text": f"Gauss-Newton handed the adjustment to pycolmap's Levenberg-Marquardt: {res.solver_fallback}"})
    sn = res.snooping or {}
    if not sn.get("complete", True):
        out.append({"kind": "snooping", "untrusted": True,
                    "text": f"data snooping stopped before the end: {sn.get('stopped')}: the images hold more gross "
                            "errors than it removes (a misnamed target, a wrong layout, images of another camera)"})
    if sn.get("suspect_targets"):
        out.append({"kind": "suspect", "untrusted": False,
                    "text": f"{len(sn['suspect_targets'])} target(s) whose observations data snooping could not verify"})
    vf = float((res.sigma0_px / sigma_px) ** 2)
    lo, hi = VARIANCE_FACTOR_RANGE
    if not lo <= vf <= hi:  # far beyond it (sigma0 over CALIBRATION_MAX_SIGMA_RATIO x sigma_px) the model is wrong
        out.append({"kind": "variance_factor", "untrusted": bool(res.sigma0_px > CALIBRATION_MAX_SIGMA_RATIO * sigma_px),
                    "text": f"the images fit {res.sigma0_px:.3f} px, {np.sqrt(vf):.2f}x the camera file's sigma_px "
                            f"{sigma_px:g} (variance factor {vf:.2f}, {lo:g}-{hi:g} expected): "
                            + ("the model does not describe these images (images of two cameras or zoom settings, a "
                               "layout whose spacing or shape is wrong, over-exposed or blurred dots, a lens beyond "
                               "the camera model); the stated uncertainties follow the fit, a systematic error does "
                               "not" if vf > hi else "better than the camera file states: its sigma_px is pessimistic")})
    return out


def roll_span_deg(cam_from_part: np.ndarray, xyz: np.ndarray) -> float:
    """How far the images' rolls about their optical axes spread, degrees (0..180): the angle the layout's longest
    axis makes in each image, taken as a line (modulo 180), and the span is 180 less the widest gap between them."""
    c = xyz - xyz.mean(axis=0)
    axis = np.linalg.svd(c, full_matrices=False)[2][0]
    d = np.einsum("nij,j->ni", np.asarray(cam_from_part)[:, :3, :3], axis)
    ang = np.sort(np.mod(np.degrees(np.arctan2(d[:, 0], d[:, 1])), 180.0))
    if len(ang) < 2:
        return 0.0
    gaps = np.diff(np.concatenate([ang, ang[:1] + 180.0]))
    return float(180.0 - gaps.max())


def geometry_doubts(cam_from_part: np.ndarray, xyz: np.ndarray) -> list[dict]:
    """What a self-calibration's network lacks, said (not untrusted): too few images, no rolled image. The stated
    uncertainties of the interior orientation hold only if the model does; such a network has no redundancy to show
    it does not (an outside check: 3 of 15 photographs stated a principal point 7 sigma from the 15's, as OpenCV
    did on the same images)."""
    out = []
    n = len(cam_from_part)
    if n < MIN_SELF_CALIBRATION_IMAGES:
        out.append({"kind": "network", "untrusted": False,
                    "text": f"the camera is calibrated from {n} image(s), fewer than {MIN_SELF_CALIBRATION_IMAGES}: "
                            "its interior orientation takes up what the layout and the lens model get wrong, beyond "
                            "its stated uncertainty; take more images, convergent and rolled"})
    span = roll_span_deg(cam_from_part, xyz)
    if n >= 2 and span < MIN_ROLL_SPAN_DEG:
        out.append({"kind": "roll", "untrusted": False,
                    "text": f"the images' rolls about their optical axes span {span:.0f} deg (under "
                            f"{MIN_ROLL_SPAN_DEG:.0f}): the principal point and the decentring are told from the "
                            "orientations by rolled images; take some rolled by 90 deg"})
    return out
