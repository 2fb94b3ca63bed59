"""An image smeared by a camera that moved during the exposure, found from its own dots (decision 0067).

A camera that moves while the shutter is open (a robot not yet settled, a mount that vibrates) draws every point of
the image along the same short path: each dot's light is its sharp image convolved with that path. The convolution
adds the path's second moments to each dot's second moments, the same tensor for every dot of the image, with a
direction. The lens's blur and its defocus add an isotropic variance instead, and the target's own ellipse adds what
its projection predicts. So per dot the measured second moments (``Detections.axes``) less its ellipse's
(:func:`calibration.targets.ellipse_moments`) leave the blur (isotropic) plus the smear (directional); the
deviatoric (trace-free) part of that excess is the smear's alone:

    E = M - P,   a = (E_uu - E_vv) / 2,   b = E_uv;   a smear of variance s along the unit direction d adds
    s d d^T, whose deviatoric part has a = s cos(2 th) / 2, b = s sin(2 th) / 2.

Per image the common (a, b) is the median over its unclipped dots (robust to a merged pair, a dot next to an edge);
its standard error comes from the dots' own scatter (MAD). An image is smeared when the common deviatoric part is
significant against that scatter (:data:`Z2_LIMIT`) and the smear's variance beyond the clean images' largest
(:data:`VARIANCE_FLOOR_PX2`). The smear's length is said as the uniform smear of the same variance, ``sqrt(12 s)``
(a uniform smear of L px has variance L^2 / 12).

The centres of a smeared image are moved along the smear by the path's mean (for a one-sided path, e.g. a decaying
vibration, a good part of the path's length), which no stated sigma covers: MEASURE leaves the image out.
"""
from __future__ import annotations

import numpy as np

__all__ = ["Z2_LIMIT", "VARIANCE_FLOOR_PX2", "MIN_DOTS", "HALVES_ANGLE_DEG", "HALVES_RATIO", "deviatoric_excess",
           "homogeneous", "image_smear", "smear_length_px"]

#: the common deviatoric excess over its standard error, squared (chi-square with 2 dof): above it the image's dots
#: share a direction. 2 dof: 0.1 % at 13.8; a high bar, the floor below decides on clean images
Z2_LIMIT = 25.0
#: the smear's variance (px^2) along its direction above which an image is smeared (a uniform smear of 2.7 px): 1.5x
#: the largest clean image whose halves agree (decision 0067: 0.39 on generated skin 103, whose steep views of one
#: surface share their ellipses' misprediction; the example's 0.198), 0.76x the tester's smeared images (0.79-0.97)
VARIANCE_FLOOR_PX2 = 0.6
#: an image with fewer unclipped named dots is not judged (its record says so): two halves of eight each
MIN_DOTS = 16
#: the halves of an image's dots (nearer and farther from the principal point; smaller and larger) agree on a smear
#: within this angle and this factor of its variance (:func:`homogeneous`): the tester's smeared images 4-10 deg and
#: 1.4-1.8x apart, a clean plate's false ones 25-78 deg and 3.4-10x
HALVES_ANGLE_DEG = 20.0
HALVES_RATIO = 2.5
_MAD_TO_SIGMA = 1.4826
_MEDIAN_EFFICIENCY = 1.2533  # the standard error of a normal sample's median over the mean's


def smear_length_px(variance_px2: float) -> float:
    """The length (px) of the uniform smear with this variance along its direction: ``sqrt(12 s)``."""
    return float(np.sqrt(12.0 * max(variance_px2, 0.0)))


def deviatoric_excess(measured: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """Each dot's deviatoric excess ``(k, 2)`` px^2: ``[a, b]`` of ``E = measured - predicted`` (second moments,
    ``(k, 2, 2)`` each), ``a = (E_uu - E_vv) / 2``, ``b = E_uv``. Isotropic blur leaves it zero."""
    E = np.asarray(measured, dtype=float).reshape(-1, 2, 2) - np.asarray(predicted, dtype=float).reshape(-1, 2, 2)
    return np.stack([0.5 * (E[:, 0, 0] - E[:, 1, 1]), E[:, 0, 1]], axis=1)


def _common(dev: np.ndarray) -> tuple[float, float]:
    """The smear's variance along its direction and its direction (deg) from the median deviatoric excess."""
    a, b = float(np.median(dev[:, 0])), float(np.median(dev[:, 1]))
    return 2.0 * float(np.hypot(a, b)), float(np.degrees(0.5 * np.arctan2(b, a))) % 180.0


def homogeneous(dev: np.ndarray, *keys: np.ndarray) -> tuple[bool, list[dict]]:
    """Whether the dots' deviatoric excess is one tensor across the image: for each ``key`` (a dot's distance from the
    principal point, its predicted size), the dots below and above its median give the same smear within
    :data:`HALVES_ANGLE_DEG` and a factor :data:`HALVES_RATIO`. A camera's motion adds the same spread to every dot; a
    shape the prediction misses (a lens the job does not state, a steep view of small far dots) grows with the dot's
    place or size, and the halves disagree (decision 0067: a clean plate's images 78 deg and 3-10x apart)."""
    halves, ok = [], True
    for key in keys:
        lo = key < np.median(key)
        (v1, d1), (v2, d2) = _common(dev[lo]), _common(dev[~lo])
        gap = abs(d1 - d2) % 180.0
        gap = min(gap, 180.0 - gap)
        agree = (min(v1, v2) > 0.5 * VARIANCE_FLOOR_PX2 and gap <= HALVES_ANGLE_DEG
                 and max(v1, v2) <= HALVES_RATIO * min(v1, v2))
        halves.append({"variance_px2": [round(v1, 4), round(v2, 4)], "direction_deg": [round(d1, 1), round(d2, 1)],
                       "agree": bool(agree)})
        ok &= agree
    return ok, halves


def image_smear(dev: np.ndarray, use: np.ndarray | None = None, radius: np.ndarray | None = None,
                size: np.ndarray | None = None) -> dict:
    """The smear the dots of one image share.

    ``dev: (k, 2)`` each dot's deviatoric excess (:func:`deviatoric_excess`), ``use: (k,)`` bool the dots to judge by (unclipped, finite; None: all finite ones).

    Returns observations.json's ``smear`` record: ``n_dots``, and when judged (``n_dots`` >= :data:`MIN_DOTS`)
    ``variance_px2`` (the common smear's variance along its direction, 2 hypot(a, b)), ``length_px`` (the uniform
    smear of that variance), ``direction_deg`` (image u towards v, 0-180), ``z2`` (the common deviatoric part over its
    standard error, squared) and ``smeared`` (bool); not judged: ``smeared`` None and ``why``.
    """
    dev = np.asarray(dev, dtype=float).reshape(-1, 2)
    ok = np.isfinite(dev).all(axis=1)
    if use is not None:
        ok &= np.asarray(use, dtype=bool)
    n = int(ok.sum())
    if n < MIN_DOTS:
        return {"n_dots": n, "smeared": None, "why": f"fewer than {MIN_DOTS} unclipped named dots: not judged"}
    a, b = dev[ok, 0], dev[ok, 1]
    ma, mb = float(np.median(a)), float(np.median(b))
    se = [max(_MEDIAN_EFFICIENCY * _MAD_TO_SIGMA * float(np.median(np.abs(x - m))) / np.sqrt(n), 1e-9)
          for x, m in ((a, ma), (b, mb))]
    z2 = (ma / se[0]) ** 2 + (mb / se[1]) ** 2
    var = 2.0 * float(np.hypot(ma, mb))
    direction = float(np.degrees(0.5 * np.arctan2(mb, ma))) % 180.0
    keys = [np.asarray(k, dtype=float).reshape(-1)[ok] for k in (radius, size) if k is not None]
    same, halves = homogeneous(dev[ok], *keys) if keys else (True, [])
    out = {"n_dots": n, "variance_px2": round(var, 4), "length_px": round(smear_length_px(var), 2),
           "direction_deg": round(direction, 1), "z2": round(float(z2), 1),
           "smeared": bool(z2 > Z2_LIMIT and var > VARIANCE_FLOOR_PX2 and same)}
    if halves:
        out["halves"] = halves  # by distance from the principal point, then by size: one tensor or not
    return out
