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
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from calibration.errors import CalibrationError

__all__ = ["DetectorModel", "fit_model", "load_model", "observation_sigmas", "DATA_PATH"]

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

    def sigma_px(self, incidence_rad, diameter_px, noise_scale: float = 1.0) -> np.ndarray:
        """Standard deviation of one coordinate, ``(k,)`` pixels, for incidence ``(k,)`` rad and dot size ``(k,)`` px.

        ``noise_scale`` scales the sensor-noise driven part (the ``b`` term) as the sensor's noise scales.
        """
        th = np.minimum(np.asarray(incidence_rad, dtype=float), np.radians(MAX_INCIDENCE_DEG))
        d = np.maximum(np.asarray(diameter_px, dtype=float), 1.0)
        c = np.maximum(np.cos(th), np.cos(np.radians(MAX_INCIDENCE_DEG)))
        return np.sqrt(self.a_px**2 + (noise_scale * self.b_px) ** 2 * (d / D_REF_PX) ** (-2 * self.p) * c ** (-2 * self.q))

    def describe(self) -> str:
        return (f"sigma^2 = {self.a_px:.4f}^2 + {self.b_px:.4f}^2 (d/{D_REF_PX:g} px)^-{2 * self.p:.2f} "
                f"cos(theta)^-{2 * self.q:.2f} px^2 (version {self.version})")

    def to_dict(self) -> dict:
        return {"model": "sigma_px^2 = a^2 + b^2 (d / d_ref)^(-2p) cos(theta)^(-2q)", "d_ref_px": D_REF_PX,
                "a_px": self.a_px, "b_px": self.b_px, "p": self.p, "q": self.q, "version": self.version}


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
    r = minimize(nll, x0, method="Nelder-Mead", options={"maxiter": 4000, "xatol": 1e-6, "fatol": 1e-6})
    return DetectorModel(float(np.exp(r.x[0])), float(np.exp(r.x[1])), float(r.x[2]), float(r.x[3]), version)


@lru_cache(maxsize=4)
def load_model(path: str | None = None) -> DetectorModel:
    """The model in the repository (``calibration/data/detector_precision.json``) or at ``path``."""
    p = Path(path) if path else DATA_PATH
    try:
        doc = json.loads(p.read_text())
        return DetectorModel(float(doc["a_px"]), float(doc["b_px"]), float(doc["p"]), float(doc["q"]),
                             str(doc.get("version", "1")))
    except (OSError, KeyError, ValueError) as exc:
        raise CalibrationError(f"{p}: cannot read the detector precision model ({exc})") from None


def observation_sigmas(points: np.ndarray, normals: np.ndarray, cam_from_part: np.ndarray, obs_image: np.ndarray,
                       obs_target: np.ndarray, fx_px: float, diameter_m: float, model: DetectorModel | None = None,
                       noise_scale: float = 1.0) -> np.ndarray:
    """A priori sigma of each observation ``(q,)`` pixels from the model, at approximate poses ``(m, 4, 4)``."""
    model = model or load_model()
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
    d_px = fx_px * diameter_m / np.maximum(Xc[:, 2], 1e-9)
    return model.sigma_px(theta, d_px, noise_scale)
