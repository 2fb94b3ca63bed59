"""Each dot's noise as the detector states it from its own image: the weights of ADJUST and of PLAN's pre-analysis.

The detector propagates each pixel's noise, measured on the image's own dots as a line in the grey level (decision
0047), into each centre's 2x2 covariance (``calibration.dots.Detections.cov``, observations.json ``cov_px2``). That
statement follows what the detector model (``calibration/detector_model.py``, by incidence and dot size in pixels,
measured once on the simulated camera at its reference light) cannot know: how bright the dots are (exposure, gain,
the light, the dot's size at a given size in pixels), how noisy the sensor is, and the ellipse's own direction.

Measured against the rendered truth (clean dots of the example, 12 views x 2 noise draws per condition, session
script; decision 0048), the rms centre error over the rms stated sigma and over the model's a priori sigma:

=====================================  =========  ===========
condition                              stated     model
=====================================  =========  ===========
reference (exposure 2 ms, noise 1)     1.02       0.97
a third of the light (0.6 ms)          1.08       1.95
2.5 x the light (5 ms)                 0.98       0.62
noise x 3                              0.98       0.93
3 mm dots (12-22 px)                   0.80       0.58
=====================================  =========  ===========

It is ``[camera] dot_precision = "stated"``, not the default: at the reference light the model predicts the achieved
precision better (the statement is about 27 % pessimistic on face-on dots), and the model's variance factor is the
canary that says the light is unlike the model's (the statement absorbs it; :func:`stated_weights` gives the
``light`` factor for that instead).

A dot centred by the ellipse of its contour (clipped, next to an edge; decision 0037) keeps the model's sigma: its
centre does not come from the propagated pixels, and its stated covariance is not its error (about 2x pessimistic in
sigma). So does every dot of an image whose noise line could not be measured (too few dots: the image's one noise
figure then stood for every pixel, which understates the noise on the dots' bright tops), and a covariance that is
not a finite positive-definite matrix. Each such fallback is counted in bundle.json.
"""
from __future__ import annotations

import numpy as np

__all__ = ["BLUR_BEYOND_SHARE_MAX", "FALLBACK_SHARE_MAX", "SOURCES", "blur_weights", "observed_blur", "stated_covariances", "stated_usable", "noise_weights", "rms_sigma", "stated_weights"]

#: ``[camera] dot_precision`` values
SOURCES = ("stated", "model")
#: more of the observations than this share falling back to the model (not by design: their statement could not be
#: made) is said with the model-range warnings
FALLBACK_SHARE_MAX = 0.1


def stated_usable(cov: np.ndarray, ellipse: np.ndarray, line_measured: np.ndarray) -> tuple[np.ndarray, dict]:
    """Which observations can be weighted by their stated covariance ``cov: (q, 2, 2)`` px^2: centred by their
    centroid (``ellipse: (q,)`` False), in an image whose noise line was measured (``line_measured: (q,)``), and
    finite and positive definite. Returns ``(q,)`` bool and the counts of the others by reason."""
    C = _symmetric(cov)
    ell = np.asarray(ellipse, dtype=bool).reshape(-1)
    line = np.asarray(line_measured, dtype=bool).reshape(-1)
    finite = np.all(np.isfinite(C), axis=(1, 2))
    Cf = np.where(finite[:, None, None], C, 1.0)
    det = Cf[:, 0, 0] * Cf[:, 1, 1] - Cf[:, 0, 1] * Cf[:, 1, 0]
    pd = finite & (Cf[:, 0, 0] > 0) & (Cf[:, 1, 1] > 0) & (det > 0)
    ok = pd & ~ell & line
    why = {"centred_by_ellipse": int(np.count_nonzero(ell)),
           "noise_line_not_measured": int(np.count_nonzero(~ell & ~line)),
           "not_positive_definite": int(np.count_nonzero(~ell & line & ~pd))}
    return ok, why


def stated_covariances(obs_doc: dict) -> tuple[np.ndarray, np.ndarray]:
    """Each observation's stated covariance ``(q, 2, 2)`` px^2 in the order of
    :func:`cell.stages.adjust.observation_arrays` (NaN where its image has none: a job measured before the
    detector gave them), and ``(q,)`` bool whether its image's noise line was measured (observations.json
    ``noise_levels`` with a non-zero slope; an image without the record: not measured)."""
    C, line = [], []
    for o in obs_doc["images"]:
        k = len(o["ids"])
        c = o.get("cov_px2")
        arr = np.asarray(c, dtype=float).reshape(-1, 2, 2) if c is not None else None
        C.append(arr if arr is not None and len(arr) == k else np.full((k, 2, 2), np.nan))
        lv = o.get("noise_levels")
        line.append(np.full(k, lv is not None and len(lv) == 2 and float(lv[1]) != 0.0))
    if not C:
        return np.zeros((0, 2, 2)), np.zeros(0, dtype=bool)
    return np.concatenate(C), np.concatenate(line)


def noise_weights(model_sigma: np.ndarray, stated: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """The covariance ``(q, 2, 2)`` px^2 each observation's noise is weighted with: its stated covariance where
    ``usable``, else the detector model's ``model_sigma: (q,)`` on both coordinates."""
    s = np.asarray(model_sigma, dtype=float).reshape(-1)
    C = s[:, None, None] ** 2 * np.eye(2)
    ok = np.asarray(usable, dtype=bool).reshape(-1)
    C[ok] = _symmetric(stated)[ok]
    return C


def _symmetric(cov) -> np.ndarray:
    """``(q, 2, 2)`` covariances made exactly symmetric (a record's rounding can leave the two off-diagonals apart)."""
    C = np.asarray(cov, dtype=float).reshape(-1, 2, 2)
    return 0.5 * (C + np.swapaxes(C, 1, 2))


def rms_sigma(weights: np.ndarray) -> np.ndarray:
    """One coordinate's sigma ``(q,)`` of sigmas ``(q,)`` or covariances ``(q, 2, 2)``: sqrt(trace / 2)."""
    w = np.asarray(weights, dtype=float)
    return w if w.ndim == 1 else np.sqrt(np.trace(w, axis1=1, axis2=2) / 2.0)


def stated_weights(job, obs: dict, sel: np.ndarray, model_sigma: np.ndarray, ellipse: np.ndarray
                   ) -> tuple[np.ndarray | None, np.ndarray, dict]:
    """ADJUST's noise covariance ``(q, 2, 2)`` of the observations ``sel: (Q,)`` picks out of observations.json
    ``obs``: the detector's statement where it can stand, the model's ``model_sigma: (q,)`` elsewhere (``ellipse:
    (Q,)`` the dots centred by their ellipse); None with ``[camera] dot_precision = "model"``. Also ``(q,)`` bool,
    which are weighted by the statement, and what bundle.json says of it (with ``light``: the median of the stated
    variance over the model's, the images' light and noise against the model's measurement; None when no dot has a
    statement)."""
    if job.spec.camera.dot_precision != "stated":
        return None, np.zeros(len(model_sigma), dtype=bool), {"source": "model"}
    cov, line = stated_covariances(obs)
    ok, why = stated_usable(cov[sel], np.asarray(ellipse, dtype=bool)[sel], line[sel])
    C = noise_weights(model_sigma, cov[sel], ok)
    light = float(np.median(rms_sigma(C[ok]) ** 2 / np.asarray(model_sigma, dtype=float)[ok] ** 2)) if ok.any() else None
    doc = {"source": "stated", "observations_stated": int(ok.sum()), "observations_by_model": why, "light": light,
           "fallback": None}
    # a dot centred by its ellipse keeps the model by design; one whose statement could not be made is a fallback
    lost = why["noise_line_not_measured"] + why["not_positive_definite"]
    if lost > FALLBACK_SHARE_MAX * max(len(ok), 1):
        doc["fallback"] = (f"dot_precision = \"stated\": {lost} of {len(ok)} observations keep the detector model's "
                           f"sigma ({why['noise_line_not_measured']} in images whose noise line could not be measured, "
                           f"too few dots; {why['not_positive_definite']} whose covariance is not finite): their "
                           "weights do not follow the light")
    return C, ok, doc


#: more than this share of the weighed observations blurred beyond where the model's blur term was measured: said
BLUR_BEYOND_SHARE_MAX = 0.25


def observed_blur(obs_doc: dict) -> np.ndarray:
    """Each observed dot's blur variance (px^2, observations.json ``blur_px2``; decision 0049), ``(q,)`` in the order of
    :func:`cell.stages.adjust.observation_arrays`; NaN where it was not measured (a clipped dot, an image measured
    before the blur was): the model's sigma then stands unchanged."""
    out = []
    for o in obs_doc["images"]:
        k = len(o["ids"])
        b = o.get("blur_px2")
        arr = np.array([np.nan if v is None else v for v in b], dtype=float) if b is not None else None
        out.append(arr if arr is not None and len(arr) == k else np.full(k, np.nan))
    return np.concatenate(out) if out else np.zeros(0)


def blur_weights(sigma: np.ndarray, blur_px2: np.ndarray, model=None) -> tuple[np.ndarray, dict]:
    """The detector model's sigma ``(q,)`` for each dot's measured blur (its blur term), and what bundle.json says of
    it: how many dots it raised, the median blur, the largest factor, and how many were blurred beyond where the term
    was measured (held at its edge there, and said when many)."""
    from calibration.detector_model import load_model

    model = model or load_model()
    b = np.asarray(blur_px2, dtype=float)
    f = model.blur_factor(b)
    hi = model.blur_range_px2[1] if model.blur_range_px2 else np.inf
    beyond = int(np.count_nonzero(np.isfinite(b) & (b > hi)))
    doc = {"term": model.c_blur > 0, "measured": int(np.count_nonzero(np.isfinite(b))),
           "median_blur_px2": float(np.nanmedian(b)) if np.isfinite(b).any() else None,
           "p5_p95_blur_px2": [float(v) for v in np.nanpercentile(b, [5, 95])] if np.isfinite(b).any() else None,
           "raised": int(np.count_nonzero(f > 1.005)), "largest_factor": float(f.max()) if len(f) else 1.0,
           "reference_px2": model.blur_reference_px2, "beyond_measured_range": beyond}
    if model.c_blur and beyond > BLUR_BEYOND_SHARE_MAX * max(len(b), 1):
        doc["warning"] = (f"{beyond} of {len(b)} observations are of dots blurred beyond {hi:.2f} px^2 (the blur the "
                          f"detector model's blur term was measured to; median here {doc['median_blur_px2']:.2f} px^2): "
                          "their sigma is held at the term's edge and may be optimistic; focus the lens, stop it down "
                          "or narrow [camera] near / far, or weigh by the detector's own statement ([camera] "
                          'dot_precision = "stated")')
    return np.asarray(sigma, dtype=float) * f, doc
