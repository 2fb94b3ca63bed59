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

Tried and left out: each image's own focal length against the others' (an F test of the network adjusted with and
without a focal length per image) told 5 zoomed images among 10 (F 305) but also flagged the clean set (F 56): a
printed sheet on cardboard is not its flat layout, and each image's focal length absorbs the difference.
"""
from __future__ import annotations

import numpy as np

from cell.stages.model_shape import VARIANCE_FACTOR_RANGE

__all__ = ["doubts", "CALIBRATION_MAX_SIGMA_RATIO"]

#: a measurement whose images fit beyond this many times the camera file's sigma_px is UNTRUSTED, and ``cell calibrate
#: camera`` writes no camera from them (as the hand-eye)
CALIBRATION_MAX_SIGMA_RATIO = 3.0


def doubts(res, sigma_px: float, images: list, used: list) -> list[dict]:
    """What makes the measurement doubtful, each ``{"kind", "untrusted": bool, "text"}``: ``untrusted`` ones make a
    measurement UNTRUSTED and refuse a camera calibration; the others are said."""
    out = []
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
