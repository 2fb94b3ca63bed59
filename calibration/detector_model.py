"""The dot detector's precision as a function of the geometry: a measured, versioned model.

One image coordinate of a retro-reflective dot's centre scatters with a standard deviation that grows as
the dot gets smaller in the image and as it is seen more obliquely (fewer, dimmer pixels across the
ellipse's minor axis; shading under the dot). The model

    sigma_px(theta, d)^2 = a^2 + b^2 * (d / d_ref)^(-2 p) * (cos theta)^(-2 q)

(``theta`` incidence between the dot's normal and the line of sight, ``d`` the dot's diameter in pixels
``f * D / depth``, ``d_ref`` = 20 px) is fitted by :func:`fit_model` to the errors measured on the
simulated camera by ``benchmarks/detector_precision.py`` and stored with its conditions and the command
that measured it in ``calibration/data/detector_precision.json`` (:data:`DATA_PATH`). The planner predicts
with it and the bundle adjustment starts its weights from it (the variance components then scale it
to what the images show), so both use the same image precision.

A dot whose local background is not the plane the detector fits (an edge of the part or a step of its
shading next to it) carries a further error the geometry cannot predict; the detector bounds it per dot
(``Detections.background_cov``, observations.json ``bg_cov_px2``) and the bundle adds ``c^2`` times that
bound to the model's variance (:func:`observation_covariances`); ``c`` (``c_background``), the share of the
bound that such errors reach on average, is measured by ``benchmarks/detector_precision.py --fit-background``
against the simulated truth (docs/decisions/0023), for the detector's default centre (from version 5 the auto
centre, whose dots with a bound are centred by their ellipse: decision 0037; a dot with a bound centred by its
centroid takes the centroid's share, :data:`C_BACKGROUND_CENTROID`). The share of that error a target's views have in common
(``rho_background``; ADJUST adds the cross terms between the views, calibration/bundle/coherent.py) comes from
``benchmarks/background_share.py`` (decision 0032); a model file without it (before version 4) gives one.

A dot the sensor clips (its pixels at the ceiling: an exposure too bright for a near station) is centred with
an error of pixel phase that grows with how far it is overexposed (decision 0029: 0.0046 px rms with 60-70 % of
its pixels clipped, 0.0104 px with 80-90 %, against 0.005 px unclipped). The detector counts the clipped pixels
(``Detections.saturated``; observations.json ``saturated_px`` with ``area_px``) and the bundle adds
``c_s^2 rho^k_s (d / d_ref)^m_s`` (``rho`` the clipped share of the dot's pixels, ``d`` its diameter; the size
factor from version 5, decision 0037) to the model's variance; the geometry terms are
fitted on dots that are neither clipped nor next to an edge.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from calibration.errors import CalibrationError

__all__ = ["DetectorModel", "fit_model", "fit_background", "fit_saturation", "load_model", "observation_sigmas",
           "observation_geometry", "centroid_bound_scale", "C_BACKGROUND_CENTROID",
           "observation_covariances", "DATA_PATH"]

DATA_PATH = Path(__file__).resolve().parent / "data" / "detector_precision.json"
D_REF_PX = 20.0
#: incidence beyond which the model is not extrapolated (the detector's own limit is about there)
MAX_INCIDENCE_DEG = 86.0


@dataclass(frozen=True)
class DetectorModel:
    """``sigma_px(theta, d)^2 = a^2 + b^2 (d / 20)^(-2p) cos(theta)^(-2q)``, per image coordinate (pixels)."""

    a_px: float
    b_px: float
    p: float
    q: float
    version: str = "1"
    c_background: float = 0.0
    c_saturation: float = 0.0
    k_saturation: float = 1.0
    #: where the model was measured: incidence (deg) and dot diameter (px) ranges of the dots it was fitted to
    #: (None: not recorded); :meth:`sigma_px_measured` does not extrapolate beyond them
    incidence_range_deg: tuple[float, float] | None = None
    diameter_range_px: tuple[float, float] | None = None
    #: the share of a dot's background misfit (``c^2 B``) that ADJUST takes as common to its views, from the
    #: rendered truth by ``benchmarks/background_share.py`` (decision 0032: the pairs' moments, and the intersections
    #: that say whether the statement built with it covers the errors); None: not in the model file (a model before
    #: version 4), :attr:`shared_share` then takes the conservative limit one
    rho_background: float | None = None
    #: the saturation term's change with the dot's size: ``(d / 20 px)^m`` (decision 0037; measured for the auto
    #: centre, whose ellipse fits the longer rim of a large clipped dot better: version 5's m is negative, the term
    #: shrinks with size); 0: a model before version 5
    m_saturation: float = 0.0
    #: the share of every observation's variance (the covariance it is weighted with) that a target's views have in
    #: common (decision 0043: measured on clean dots against the rendered truth with the true poses,
    #: ``benchmarks/shared_floor.py``); 0: not in the model file, nothing added
    rho_all: float = 0.0
    #: the blur term (decision 0049): a dot's image blurred beyond the blur the model was measured at
    #: (``blur_reference_px2``, the optical variance along each axis, :func:`calibration.targets.blur_variances`)
    #: scatters more, ``sigma^2 x (1 + c_blur (b - reference))`` for its measured blur variance ``b``, held within
    #: ``blur_range_px2`` (where it was measured); 0: not in the model file, no term
    c_blur: float = 0.0
    blur_reference_px2: float = 0.0
    blur_range_px2: tuple[float, float] | None = None

    def blur_factor(self, blur_px2) -> np.ndarray:
        """The factor ``(k,)`` on a dot's sigma for its measured blur variance ``blur_px2: (k,)`` px^2 (NaN: not
        measured, e.g. a clipped dot: 1). A dot sharper than the reference keeps the model (no credit)."""
        b = np.asarray(blur_px2, dtype=float)
        if not self.c_blur:
            return np.ones_like(b)
        hi = self.blur_range_px2[1] if self.blur_range_px2 else np.inf
        extra = np.clip(np.where(np.isfinite(b), b, self.blur_reference_px2), self.blur_reference_px2, hi)
        return np.sqrt(1.0 + self.c_blur * (extra - self.blur_reference_px2))

    @property
    def shared_share(self) -> float:
        """:attr:`rho_background`, or 1 (the conservative limit) where the model file does not give it."""
        return 1.0 if self.rho_background is None else self.rho_background

    def saturation_var(self, clipped_share, diameter_px=None) -> np.ndarray:
        """Variance (px^2) a clipped dot adds to each coordinate, for the clipped share of its pixels ``(k,)`` and
        the dot's diameter ``(k,)`` px (needed when the model has a size term, :attr:`m_saturation`)."""
        rho = np.clip(np.asarray(clipped_share, dtype=float), 0.0, 1.0)
        size = 1.0
        if self.m_saturation:
            if diameter_px is None:
                raise CalibrationError("detector model: the saturation term needs each clipped dot's diameter")
            size = (np.maximum(np.asarray(diameter_px, dtype=float), 1.0) / D_REF_PX) ** self.m_saturation
        return np.where(rho > 0, self.c_saturation**2 * rho**self.k_saturation * size, 0.0)

    def sigma_px(self, incidence_rad, diameter_px, noise_scale: float = 1.0) -> np.ndarray:
        """Standard deviation of one coordinate, ``(k,)`` pixels, for incidence ``(k,)`` rad and dot size ``(k,)`` px.

        ``noise_scale`` scales the sensor-noise driven part (the ``b`` term) as the sensor's noise scales.
        """
        th = np.minimum(np.asarray(incidence_rad, dtype=float), np.radians(MAX_INCIDENCE_DEG))
        d = np.maximum(np.asarray(diameter_px, dtype=float), 1.0)
        c = np.maximum(np.cos(th), np.cos(np.radians(MAX_INCIDENCE_DEG)))
        return np.sqrt(self.a_px**2 + (noise_scale * self.b_px) ** 2 * (d / D_REF_PX) ** (-2 * self.p) * c ** (-2 * self.q))

    def measured_box(self) -> tuple[float, float, float]:
        """``(largest incidence rad, smallest, largest dot diameter px)`` the model was measured over (the
        detector's own incidence limit and no size bound where the data file does not record them)."""
        inc = np.radians(self.incidence_range_deg[1]) if self.incidence_range_deg else np.radians(MAX_INCIDENCE_DEG)
        d0, d1 = self.diameter_range_px if self.diameter_range_px else (1.0, np.inf)
        return float(min(inc, np.radians(MAX_INCIDENCE_DEG))), float(max(d0, 1.0)), float(d1)

    def sigma_px_measured(self, incidence_rad, diameter_px, noise_scale: float = 1.0) -> np.ndarray:
        """:meth:`sigma_px` with the geometry held inside where the model was measured (:meth:`measured_box`): a
        dot seen more obliquely, or larger or smaller in the image, than any the fit saw counts as the nearest
        measured one. For planning: the search must not chase an extrapolated gain (a larger dot than measured
        is not credited with a smaller error). The bundle's weights keep :meth:`sigma_px`."""
        inc, d0, d1 = self.measured_box()
        th = np.minimum(np.asarray(incidence_rad, dtype=float), inc)
        return self.sigma_px(th, np.clip(np.asarray(diameter_px, dtype=float), d0, d1), noise_scale)

    def describe(self) -> str:
        return (f"sigma^2 = {self.a_px:.4f}^2 + {self.b_px:.4f}^2 (d/{D_REF_PX:g} px)^-{2 * self.p:.2f} "
                f"cos(theta)^-{2 * self.q:.2f} px^2, + {self.c_background:.3f}^2 x the detector's background bound, "
                f"+ {self.c_saturation:.4f}^2 rho^{self.k_saturation:.1f}"
                + (f" (d/{D_REF_PX:g} px)^{self.m_saturation:.2f}" if self.m_saturation else "")
                + " for a dot with a share rho of its pixels clipped; views share "
                + (f"{self.rho_background:.2f}" if self.rho_background is not None else "1 (not measured)")
                + " of the background misfit"
                + (f" and {self.rho_all:.3f} of every observation's variance" if self.rho_all else "")
                + (f"; x (1 + {self.c_blur:.2f} (b - {self.blur_reference_px2:.2f} px^2)) for a dot blurred by a "
                   f"variance b" if self.c_blur else "")
                + f" (version {self.version})")

    def to_dict(self) -> dict:
        return {"model": "sigma_px^2 = a^2 + b^2 (d / d_ref)^(-2p) cos(theta)^(-2q)", "d_ref_px": D_REF_PX,
                "a_px": self.a_px, "b_px": self.b_px, "p": self.p, "q": self.q, "c_background": self.c_background,
                "c_saturation_px": self.c_saturation, "k_saturation": self.k_saturation,
                **({"m_saturation": self.m_saturation} if self.m_saturation else {}),
                "version": self.version,
                **({"incidence_range_deg": list(self.incidence_range_deg)} if self.incidence_range_deg else {}),
                **({"diameter_range_px": list(self.diameter_range_px)} if self.diameter_range_px else {}),
                **({"rho_background": self.rho_background} if self.rho_background is not None else {}),
                **({"rho_all": self.rho_all} if self.rho_all else {}),
                **({"c_blur_per_px2": self.c_blur, "blur_reference_px2": self.blur_reference_px2,
                    "blur_range_px2": list(self.blur_range_px2) if self.blur_range_px2 else None}
                   if self.c_blur else {})}


def fit_model(incidence_deg: np.ndarray, diameter_px: np.ndarray, errors_px: np.ndarray,
              version: str = "1") -> DetectorModel:
    """Fit the model to measured centre errors ``errors_px: (k, 2)`` of dots at ``incidence_deg, diameter_px: (k,)``.

    Maximum likelihood for zero-mean normal errors whose variance follows the model (both coordinates).
    """
    from scipy.optimize import minimize

    th = np.radians(np.asarray(incidence_deg, dtype=float))
    d = np.asarray(diameter_px, dtype=float)
    e2 = np.sum(np.asarray(errors_px, dtype=float) ** 2, axis=1)
    if len(e2) < 50:
        raise CalibrationError(f"detector model: {len(e2)} measured dots; at least 50 are needed")

    def nll(x):
        m = DetectorModel(np.exp(x[0]), np.exp(x[1]), x[2], x[3])
        s2 = m.sigma_px(th, d) ** 2
        return float(np.sum(np.log(s2) + 0.5 * e2 / s2))  # two coordinates: 2 * (log s + e^2 / (2 s^2)) / ...

    x0 = np.array([np.log(0.005), np.log(0.01), 1.0, 1.0])
    r = minimize(nll, x0, method="Nelder-Mead", options={"maxiter": 4000, "maxfev": 8000, "xatol": 1e-6, "fatol": 1e-6})
    if not r.success:  # where the optimiser stopped is no fit: never written to the model file as one
        raise CalibrationError(f"detector model: the fit did not converge ({r.message})")
    return DetectorModel(float(np.exp(r.x[0])), float(np.exp(r.x[1])), float(r.x[2]), float(r.x[3]), version)


def fit_background(model: DetectorModel, incidence_deg: np.ndarray, diameter_px: np.ndarray, errors_px: np.ndarray,
                   background_cov: np.ndarray) -> float:
    """Maximum-likelihood ``c`` of ``e ~ N(0, sigma_px^2 I + c^2 B)`` for centre errors ``errors_px: (k, 2)`` with
    the detector's background bounds ``B: (k, 2, 2)``, the geometry model held as it is."""
    from scipy.optimize import minimize_scalar

    s2 = model.sigma_px(np.radians(np.asarray(incidence_deg, dtype=float)), np.asarray(diameter_px, dtype=float)) ** 2
    e = np.asarray(errors_px, dtype=float)
    B = np.asarray(background_cov, dtype=float)
    if not np.any(B):
        raise CalibrationError("detector model: no dot with a background misfit; c cannot be measured")

    def nll(log_c):
        C = s2[:, None, None] * np.eye(2) + np.exp(2 * log_c) * B
        det = C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] ** 2
        quad = (C[:, 1, 1] * e[:, 0] ** 2 - 2 * C[:, 0, 1] * e[:, 0] * e[:, 1] + C[:, 0, 0] * e[:, 1] ** 2) / det
        return float(np.sum(np.log(det) + quad))

    r = minimize_scalar(nll, bounds=(-8.0, 3.0), method="bounded")
    return float(np.exp(r.x))


def fit_saturation(model: DetectorModel, incidence_deg: np.ndarray, diameter_px: np.ndarray, errors_px: np.ndarray,
                   clipped_share: np.ndarray, size: bool = False) -> tuple[float, float, float]:
    """Maximum-likelihood ``(c_s, k_s, m_s)`` of ``e ~ N(0, (sigma_px^2 + c_s^2 rho^k_s (d / 20)^m_s) I)`` for the
    centre errors ``errors_px: (k, 2)`` of clipped dots (``clipped_share: (k,)`` > 0), the geometry model held as it
    is; ``size=False`` holds ``m_s`` at 0 (the term of a model before version 5)."""
    from scipy.optimize import minimize

    d = np.asarray(diameter_px, dtype=float)
    s2 = model.sigma_px(np.radians(np.asarray(incidence_deg, dtype=float)), d) ** 2
    e2 = np.sum(np.asarray(errors_px, dtype=float) ** 2, axis=1)
    rho = np.clip(np.asarray(clipped_share, dtype=float), 1e-6, 1.0)
    ld = np.log(np.maximum(d, 1.0) / D_REF_PX)
    if len(e2) < 50:
        raise CalibrationError(f"detector model: {len(e2)} clipped dots; at least 50 are needed for the saturation term")

    def nll(x):
        v = s2 + np.exp(2 * x[0] + np.exp(x[1]) * np.log(rho) + (x[2] if size else 0.0) * ld)
        return float(np.sum(2 * np.log(v) + e2 / v))

    r = minimize(nll, np.array([np.log(0.005), 0.0, 0.0]), method="Nelder-Mead",
                 options={"xatol": 1e-6, "fatol": 1e-6, "maxiter": 4000, "maxfev": 8000})
    if not r.success:  # Nelder-Mead's default 600 evaluations: ~500 on a size term's fit
        raise CalibrationError(f"detector model: the saturation term's fit did not converge ({r.message})")
    return float(np.exp(r.x[0])), float(np.exp(r.x[1])), float(r.x[2]) if size else 0.0


#: ``c_background`` of the centroid: version 4's, measured for a detector that centred every dot by its centroid
#: (``python -m benchmarks.detector_precision --views 80 --repeats 2 --seed 0 --plates 3 --skins 3 --write`` at
#: 69a810f). From version 5 on the model's ``c_background`` is the auto centre's (decision 0037: its dots with a
#: bound are centred by their ellipse, which feels a quarter of the misfit); a dot with a bound that was centred by
#: its centroid (a photograph's detector, ``DetectionOptions.for_real_images``; an ellipse fit that failed; a job
#: measured before version 5) errs by the centroid's share, not by that one
C_BACKGROUND_CENTROID = 0.2712


def centroid_bound_scale(model: DetectorModel) -> float:
    """Factor on the detector's background bound of a dot centred by its centroid, so that ``c_background^2`` times
    the scaled bound is the centroid's share :data:`C_BACKGROUND_CENTROID` squared: one for a model before version 5
    (its ``c_background`` is the centroid's) or without a background term."""
    try:
        v = int(str(model.version).split(".")[0])
    except ValueError:
        v = 0
    if v < 5 or model.c_background <= 0:
        return 1.0
    return (C_BACKGROUND_CENTROID / model.c_background) ** 2


@lru_cache(maxsize=4)
def load_model(path: str | None = None) -> DetectorModel:
    """The model in the repository (``calibration/data/detector_precision.json``) or at ``path``."""
    p = Path(path) if path else DATA_PATH
    try:
        doc = json.loads(p.read_text())
        ranges = [tuple(float(v) for v in doc[k]) if doc.get(k) is not None else None
                  for k in ("incidence_range_deg", "diameter_range_px")]
        if any(r is not None and not (len(r) == 2 and 0 <= r[0] < r[1]) for r in ranges):
            raise ValueError("incidence_range_deg and diameter_range_px must be [low, high], 0 <= low < high")
        rho = doc.get("rho_background")
        if rho is not None and not 0.0 <= float(rho) <= 1.0:
            raise ValueError(f"rho_background must be in [0, 1], got {rho}")
        rho_all = float(doc.get("rho_all", 0.0))
        if not 0.0 <= rho_all <= 1.0:
            raise ValueError(f"rho_all must be in [0, 1], got {rho_all}")
        c_blur = float(doc.get("c_blur_per_px2", 0.0))
        blur_range = tuple(float(v) for v in doc["blur_range_px2"]) if doc.get("blur_range_px2") else None
        if c_blur < 0 or (blur_range is not None and not (len(blur_range) == 2 and blur_range[0] < blur_range[1])):
            raise ValueError(f"c_blur_per_px2 must be >= 0 and blur_range_px2 [low, high], got {c_blur}, {blur_range}")
        return DetectorModel(float(doc["a_px"]), float(doc["b_px"]), float(doc["p"]), float(doc["q"]),
                             str(doc.get("version", "1")), float(doc.get("c_background", 0.0)),
                             float(doc.get("c_saturation_px", 0.0)), float(doc.get("k_saturation", 1.0)),
                             *ranges, None if rho is None else float(rho), float(doc.get("m_saturation", 0.0)),
                             rho_all, c_blur, float(doc.get("blur_reference_px2", 0.0)), blur_range)
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise CalibrationError(f"{p}: cannot read the detector precision model ({exc})") from None


def observation_geometry(points: np.ndarray, normals: np.ndarray, cam_from_part: np.ndarray, obs_image: np.ndarray,
                         obs_target: np.ndarray, fx_px: float, diameter_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Each observation's incidence ``(q,)`` rad and dot diameter ``(q,)`` px, at approximate poses ``(m, 4, 4)``."""
    poses = np.asarray(cam_from_part, dtype=float)
    P = np.asarray(points, dtype=float)[obs_target]
    R, t = poses[obs_image, :3, :3], poses[obs_image, :3, 3]
    Xc = np.einsum("qab,qb->qa", R, P) + t
    centres = -np.einsum("mba,mb->ma", poses[:, :3, :3], poses[:, :3, 3])
    sight = centres[obs_image] - P
    sight /= np.linalg.norm(sight, axis=1, keepdims=True)
    nrm = np.asarray(normals, dtype=float)[obs_target]
    nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    theta = np.arccos(np.clip(np.einsum("qa,qa->q", sight, nrm), -1.0, 1.0))
    return theta, fx_px * diameter_m / np.maximum(Xc[:, 2], 1e-9)


def observation_sigmas(points: np.ndarray, normals: np.ndarray, cam_from_part: np.ndarray, obs_image: np.ndarray,
                       obs_target: np.ndarray, fx_px: float, diameter_m: float, model: DetectorModel | None = None,
                       noise_scale: float = 1.0) -> np.ndarray:
    """A priori sigma of each observation ``(q,)`` pixels from the model, at approximate poses ``(m, 4, 4)``."""
    model = model or load_model()
    theta, d_px = observation_geometry(points, normals, cam_from_part, obs_image, obs_target, fx_px, diameter_m)
    return model.sigma_px(theta, d_px, noise_scale)


def observation_covariances(sigma_px: np.ndarray, background_cov: np.ndarray | None,
                            model: DetectorModel | None = None, clipped_share: np.ndarray | None = None,
                            diameter_px: np.ndarray | None = None) -> np.ndarray:
    """A priori covariance of each observation ``(q, 2, 2)`` px^2: the model's ``sigma_px: (q,)`` on both
    coordinates (or a ``(q, 2, 2)`` covariance of the dot's noise: the detector's statement, decision 0048) plus
    ``c_background^2`` times the detector's background bound ``background_cov: (q, 2, 2)`` (None: no bound, e.g. a job measured before the detector gave one), plus the saturation term for the clipped
    share of each dot's pixels ``clipped_share: (q,)`` (None: not known) and its diameter ``diameter_px: (q,)``
    (:func:`observation_diameters`; the model's saturation term grows with it)."""
    model = model or load_model()
    s = np.asarray(sigma_px, dtype=float)
    C = s[:, None, None] ** 2 * np.eye(2) if s.ndim == 1 else s.reshape(-1, 2, 2).copy()
    if clipped_share is not None:
        C = C + model.saturation_var(clipped_share, diameter_px)[:, None, None] * np.eye(2)
    if background_cov is not None:
        B = np.asarray(background_cov, dtype=float)
        if B.shape != C.shape or not np.all(np.isfinite(B)):
            raise CalibrationError(f"observation covariances: background bounds must be {C.shape} finite, got {B.shape}")
        C = C + model.c_background**2 * B
    return C
