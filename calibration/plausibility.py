"""Is an estimate a camera at all? Bounds shared by Faugeras-Toscani and the bundle adjustment.

An estimator that converges numerically can still return nonsense (a focal length of 148 px for a
2336 px lens, an image sigma of 16 px): these checks turn such an answer into a
:class:`calibration.errors.CalibrationError` that says what is wrong, so that no caller reports it
as a measurement.
"""
from __future__ import annotations

import numpy as np

from calibration.camera import Intrinsics
from calibration.errors import CalibrationError

__all__ = ["intrinsics_problems", "check_adjustment", "MAX_SIGMA0_PX"]

MAX_ASPECT_DEVIATION = 0.05  # |(fx / fy) / (nominal fx / fy) - 1| (without a nominal: 0.5 <= fx / fy <= 2)
MAX_SKEW = 0.05  # skew term / fx (a linear estimate from a few dozen points reaches 0.01)
MAX_PRINCIPAL_OFFSET = 0.25  # |cx - centre| / width, |cy - centre| / height
MAX_FOCAL_DEVIATION = 0.25  # |f / nominal - 1|, when the nominal lens is known
MAX_RADIAL = 5.0  # |k1| on normalised coordinates (a fisheye is another camera model)
#: an a posteriori image sigma above this is not a measurement of dots (their detector reaches 0.01-0.1 px)
MAX_SIGMA0_PX = 1.0


def intrinsics_problems(intr: Intrinsics, nominal: Intrinsics | None = None, skew_ratio: float = 0.0) -> list[str]:
    """What makes ``intr`` implausible (empty list: nothing)."""
    problems = []
    if not (np.isfinite(intr.fx_px) and np.isfinite(intr.fy_px)) or intr.fx_px <= 0 or intr.fy_px <= 0:
        problems.append(f"focal length {intr.fx_px:.1f} x {intr.fy_px:.1f} px")
    else:
        aspect = intr.fx_px / intr.fy_px
        want = nominal.fx_px / nominal.fy_px if nominal is not None else 1.0
        # against the lens' own aspect when known (rectangular pixels exist); otherwise only absurd ones
        if (nominal is not None and abs(aspect / want - 1) > MAX_ASPECT_DEVIATION) or not 0.5 <= aspect <= 2.0:
            problems.append(f"pixel aspect {aspect:.3f}" + (f" vs the camera's {want:.3f}" if nominal is not None else ""))
        if nominal is not None and abs(intr.fx_px / nominal.fx_px - 1) > MAX_FOCAL_DEVIATION:
            problems.append(f"focal length {intr.fx_px:.1f} px vs the lens' {nominal.fx_px:.1f} px")
    if abs(skew_ratio) > MAX_SKEW:
        problems.append(f"skew {skew_ratio:.3f}")
    if not (np.isfinite(intr.cx_px) and np.isfinite(intr.cy_px)) or (
            abs(intr.cx_px - 0.5 * (intr.width - 1)) > MAX_PRINCIPAL_OFFSET * intr.width
            or abs(intr.cy_px - 0.5 * (intr.height - 1)) > MAX_PRINCIPAL_OFFSET * intr.height):
        problems.append(f"principal point ({intr.cx_px:.0f}, {intr.cy_px:.0f}) px, far from the image centre")
    if not np.isfinite(intr.k1) or abs(intr.k1) > MAX_RADIAL:
        problems.append(f"radial distortion k1 {intr.k1:.3g}")
    return problems


def check_adjustment(sigma0_px: float, intr: Intrinsics, nominal: Intrinsics | None = None,
                     max_sigma0_px: float = MAX_SIGMA0_PX) -> None:
    """Refuse a bundle adjustment whose image sigma or interior orientation is implausible."""
    problems = intrinsics_problems(intr, nominal)
    if not np.isfinite(sigma0_px) or sigma0_px > max_sigma0_px:
        problems.insert(0, f"sigma0 {sigma0_px:.3g} px (more than {max_sigma0_px:g} px: the images do not fit "
                           "one camera and one part; check the identification and the start values)")
    if problems:
        raise CalibrationError("bundle adjustment implausible: " + "; ".join(problems))
