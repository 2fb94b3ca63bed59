"""What a clipped dot's unknown level does to its centre, carried in ADJUST's statement (decision 0050).

A dot hides the ground behind it: its edge pixels read ``b (1 - a) + T a`` over a ground ``b``, for a dot of level
``T`` covering the fraction ``a`` of the pixel. The detector centres a clipped dot by the ellipse of its half-level
contour, whose level must follow the ground across the dot with the slope ``1 - 1 / (2 k)`` (``k``: the dot's
level over the sensor's ceiling, both above the ground) for the contour to lie at one fraction of the dot all
round. The image does not tell ``k`` (the clipped pixels are what would show it), so the detector takes the middle
of the centres at the slopes' ends, 0.5 and 1, and states half their difference as the bound
``calibration.dots.Detections.clip_bound`` (observations.json ``clip_bound_px``).

The error within that bound is taken as uniform: a covariance ``b b^T / 3`` per observation, added to its weight.
It comes from the ground's brightness across the dot and the dot's level, which are the same from one view to the
next: the views of a target share it. Like the background misfit's share (:mod:`calibration.bundle.coherent`), the
cross terms between a target's views are added to its covariance, here with a share of one.
"""
from __future__ import annotations

import numpy as np

from calibration.bundle.coherent import coherent_background_cov

__all__ = ["clip_bounds", "clip_covariances", "clip_level_cov", "say_clip_level"]


def clip_bounds(obs_doc: dict) -> np.ndarray:
    """Each observation's clip bound ``(q, 2)`` px in the order of :func:`cell.stages.adjust.observation_arrays`
    (observations.json ``clip_bound_px``); zero for an image measured without it (before decision 0050: its clipped
    dots were centred at the slope 0.5 and carry no bound)."""
    out = []
    for o in obs_doc["images"]:
        k = len(o["ids"])
        b = o.get("clip_bound_px")
        arr = np.asarray(b, dtype=float).reshape(-1, 2) if b is not None else None
        out.append(arr if arr is not None and len(arr) == k and np.all(np.isfinite(arr)) else np.zeros((k, 2)))
    return np.concatenate(out) if out else np.zeros((0, 2))


def clip_covariances(bound: np.ndarray) -> np.ndarray:
    """``(q, 2, 2)`` px^2: the covariance of an error uniform within each bound ``(q, 2)`` along its direction."""
    b = np.asarray(bound, dtype=float).reshape(-1, 2)
    return np.einsum("qa,qb->qab", b, b) / 3.0


def clip_level_cov(res, clip_cov: np.ndarray | None, img: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, dict]:
    """The covariance ``(n, 3, 3)`` to add to each adjusted target's for the clip bounds its views share, and its
    account for bundle.json (``coherent_background.clip_level``): the observations with a bound, the bounds' rms,
    and the targets whose sigma it raises (median and largest growth). ``clip_cov: (q, 2, 2)`` over the adjustment's
    observations (:func:`clip_covariances`), ``img``, ``tgt`` their image and target indices."""
    n = len(res.points)
    used = ~np.asarray(res.rejected, dtype=bool)
    if clip_cov is None or not np.any(clip_cov[used]):
        return np.zeros((n, 3, 3)), {"n_observations": 0, "n_targets": 0}
    C = np.asarray(res.obs_sigma_px, dtype=float)[used]
    C = C[:, None, None] ** 2 * np.eye(2) if C.ndim == 1 else C
    extra = coherent_background_cov(res.intrinsics, res.cam_from_part, res.points, img[used], tgt[used], C,
                                    clip_cov[used], 1.0, 1.0)
    on = np.flatnonzero(np.trace(extra, axis1=1, axis2=2) > 0)
    tr = np.trace(res.cov[on], axis1=1, axis2=2)
    growth = np.sqrt((tr + np.trace(extra[on], axis1=1, axis2=2)) / np.maximum(tr, 1e-300))
    has = np.trace(clip_cov[used], axis1=1, axis2=2) > 0
    bound = np.sqrt(3.0 * np.trace(clip_cov[used][has], axis1=1, axis2=2))
    return extra, {"n_observations": int(np.count_nonzero(has)), "bound_rms_px": float(np.sqrt(np.mean(bound**2))),
                   "bound_max_px": float(bound.max()), "n_targets": int(len(on)),
                   "sigma_growth_median": float(np.median(growth)) if len(on) else 1.0,
                   "sigma_growth_max": float(growth.max()) if len(on) else 1.0}


def say_clip_level(ctx, level: dict, weights: dict) -> None:
    """The console (and the run log for a warning): what the clip bounds added (bundle.json
    ``coherent_background.clip_level``), and the clipped dots that carry none (bundle.json
    ``observation_weights.clipped_without_bound``: an image measured before decision 0050, a dot centred by its
    centroid, an end's contour that could not be fitted; their statement lacks the term, which is said)."""
    nb = weights.get("clipped_without_bound") or 0
    if nb:
        msg = (f"{nb} observation(s) of clipped dots carry no bound for their unknown level (measured before decision "
               "0050, centred by their centroid, or a contour that could not be fitted): their sigma lacks that term")
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")
    if level.get("n_targets"):
        ctx.say(f"  {level['n_observations']} clipped dot(s) centred between the slopes their unknown level allows "
                f"(bound {level['bound_rms_px']:.4f} px rms, decision 0050): shared by their views, added to "
                f"{level['n_targets']} target(s) (sigma x{level['sigma_growth_median']:.3f} median, "
                f"x{level['sigma_growth_max']:.2f} at most)")
