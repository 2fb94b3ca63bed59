"""Image observations of unequal precision: groups by incidence angle, variance components.

A dot seen at grazing incidence is imaged as a thin ellipse on few pixels; its measured centre
scatters more than a dot seen face-on (decision 0010). The bundle adjustment therefore weights
each image coordinate with its own a priori standard deviation ``obs_sigma_px: (q,)``, and can
estimate one variance component per group of observations from the adjustment itself
(Förstner's iterative estimate, the Helmert type for groups of uncorrelated observations):

    sigma_g^2  <-  sigma_g^2 * (v_g^T P_g v_g) / r_g,     r_g = sum of the redundancy numbers in g,

with ``v_g^T P_g v_g`` the weighted squared residuals of group ``g`` at the current weights.
Repeated with a re-adjustment until the factors are 1 (a fixed point: each group's weighted
residuals then match its share of the redundancy). A group with a redundancy below
``min_redundancy`` cannot be estimated reliably (the relative standard deviation of a variance
estimate is about ``sqrt(2 / r_g)``): it takes the pooled factor of all groups,
i.e. it keeps the common a posteriori sigma (one factor on the initial sigmas of all observations,
estimated from all of them). Which groups are estimated is decided once per data-snooping round,
at the start, so that a group near the limit does not flip in and out.

Kernels only; :func:`calibration.bundle.bundle_adjust` runs the iteration (``obs_group``).
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from calibration.errors import CalibrationError

__all__ = [
    "INCIDENCE_EDGES_DEG",
    "VarianceComponents",
    "group_labels",
    "incidence_angles",
    "incidence_groups",
    "variance_component_factors",
    "mean_variance",
    "whitening",
]

#: class edges of the incidence angle between a dot's normal and the line of sight (degrees)
INCIDENCE_EDGES_DEG: tuple[float, ...] = (50.0, 70.0)


def incidence_angles(points: np.ndarray, normals: np.ndarray, cam_from_part: np.ndarray, obs_image: np.ndarray,
                     obs_target: np.ndarray) -> np.ndarray:
    """Angle between each observed target's normal and its line of sight to the camera, ``(q,)`` radians.

    Args:
        points: (n, 3) targets (part frame, metres); normals: (n, 3) unit outward normals.
        cam_from_part: (m, 4, 4) camera poses (approximate ones suffice).
        obs_image, obs_target: (q,) observation indices.
    """
    poses = np.asarray(cam_from_part, dtype=float)
    R, t = poses[:, :3, :3], poses[:, :3, 3]
    centres = -np.einsum("mba,mb->ma", R, t)  # camera centres in the part frame, (m, 3)
    sight = centres[obs_image] - np.asarray(points, float)[obs_target]
    sight /= np.linalg.norm(sight, axis=1, keepdims=True)
    nrm = np.asarray(normals, float)[obs_target]
    nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    return np.arccos(np.clip(np.einsum("qa,qa->q", sight, nrm), -1.0, 1.0))


def incidence_groups(angles_rad: np.ndarray, edges_deg: tuple[float, ...] = INCIDENCE_EDGES_DEG) -> np.ndarray:
    """Class of each incidence angle ``(q,)`` radians: 0 below the first edge, ..., ``len(edges)`` above the last."""
    return np.searchsorted(np.radians(np.asarray(edges_deg, float)), np.asarray(angles_rad, float), side="right")


def group_labels(edges_deg: tuple[float, ...] = INCIDENCE_EDGES_DEG) -> list[str]:
    """Readable names of the incidence classes, e.g. ``['< 50 deg', '50-70 deg', '>= 70 deg']``."""
    e = [f"{x:g}" for x in edges_deg]
    if not e:
        return ["all"]
    return [f"< {e[0]} deg"] + [f"{a}-{b} deg" for a, b in pairwise(e)] + [f">= {e[-1]} deg"]


@dataclass(frozen=True)
class VarianceComponents:
    """Outcome of the variance component estimation (one entry per group).

    Attributes:
        sigma_px: (g,) a priori standard deviation of the group's image coordinates after the
            estimation, in pixels (for observations given individual sigmas: their rms in the group).
        redundancy: (g,) sum of the redundancy numbers of the group's coordinates (2 per observation).
        n_observations: (g,) active observations (points with two coordinates) in the group.
        estimated: (g,) the group's component was estimated (else it took the common factor).
        iterations: re-adjustments until the factors settled.
        converged: the factors settled within the tolerance.
    """

    sigma_px: np.ndarray
    redundancy: np.ndarray
    n_observations: np.ndarray
    estimated: np.ndarray
    iterations: int
    converged: bool


def variance_component_factors(group: np.ndarray, r_white: np.ndarray, redundancy: np.ndarray, n_groups: int,
                               ratio: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """One Förstner step: the variance factor of each group at the current weights, and the common one.

    Args:
        group: (q,) group index of each active observation (0..n_groups-1).
        r_white: (q, 2) residuals divided by their current a priori sigma.
        redundancy: (q,) redundancy number per observation, averaged over its two coordinates.
        n_groups: number of groups.
        ratio: (q,) current sigma / initial sigma of each observation (None: all 1).

    Returns:
        factors: (g,) multiply the group's current variances by these; r_g: (g,) group redundancies;
        common: one factor for the *initial* variances of all observations together (for the groups
        too small to be estimated on their own: they keep the common sigma).
    """
    group = np.asarray(group, dtype=int)
    if np.any(group < 0) or np.any(group >= n_groups):
        raise CalibrationError(f"variance components: group indices must lie in 0..{n_groups - 1}")
    red = 2.0 * np.nan_to_num(np.asarray(redundancy, float), nan=0.0)
    vpv = np.sum(np.asarray(r_white, float) ** 2, axis=1)
    r_g = np.bincount(group, weights=red, minlength=n_groups)
    vpv_g = np.bincount(group, weights=vpv, minlength=n_groups)
    factors = np.where(r_g > 0, vpv_g / np.where(r_g > 0, r_g, 1.0), 1.0)
    k = np.ones(len(group)) if ratio is None else np.asarray(ratio, float) ** 2
    common = float(np.sum(vpv * k) / np.sum(red)) if np.sum(red) > 0 else 1.0
    return factors, r_g, common


def check_groups(obs_group, q: int) -> np.ndarray:
    """``obs_group`` as a (q,) int array of small non-negative group indices."""
    g = np.asarray(obs_group)
    if g.shape != (q,) or not np.issubdtype(g.dtype, np.integer) or (q and g.min() < 0):
        raise CalibrationError(f"bundle: obs_group must be (q,) = ({q},) non-negative integers, got {g.shape} {g.dtype}")
    return g.astype(int)


def check_sigmas(obs_sigma_px, default_px: float, q: int) -> np.ndarray:
    """``obs_sigma_px`` (None, scalar or (q,)) as a (q,) positive float array, or a (q, 2, 2) covariance of
    each observation (px^2) checked symmetric positive definite."""
    if obs_sigma_px is None:
        return np.full(q, float(default_px))
    s = np.asarray(obs_sigma_px, dtype=float)
    if s.ndim == 0:
        s = np.full(q, float(s))
    if s.ndim == 3:
        det = s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0] if s.shape == (q, 2, 2) else None
        if (det is None or not np.all(np.isfinite(s)) or np.any(s[:, 0, 1] != s[:, 1, 0]) or np.any(s[:, 0, 0] <= 0)
                or np.any(det <= 0)):
            raise CalibrationError(f"bundle: observation covariances must be ({q}, 2, 2) symmetric positive definite px^2, "
                                   f"got shape {s.shape}")
        return s.copy()
    if s.shape != (q,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise CalibrationError(f"bundle: obs_sigma_px must be ({q},) positive finite pixels, got shape {s.shape}")
    return s.copy()


def whitening(sigma: np.ndarray) -> np.ndarray:
    """Per observation the matrix ``W`` with ``W C W^T = I``: ``(q, 2, 2)`` from sigmas ``(q,)`` (``I / sigma``) or
    from covariances ``C: (q, 2, 2)`` (the inverse of C's Cholesky factor)."""
    s = np.asarray(sigma, dtype=float)
    if s.ndim == 1:
        return np.eye(2)[None] / s[:, None, None]
    l11 = np.sqrt(s[:, 0, 0])
    l21 = s[:, 1, 0] / l11
    l22 = np.sqrt(s[:, 1, 1] - l21**2)
    W = np.zeros_like(s)
    W[:, 0, 0] = 1.0 / l11
    W[:, 1, 0] = -l21 / (l11 * l22)
    W[:, 1, 1] = 1.0 / l22
    return W


def mean_variance(sigma: np.ndarray) -> float:
    """Mean variance of one image coordinate over observations with sigmas ``(q,)`` or covariances ``(q, 2, 2)``."""
    s = np.asarray(sigma, dtype=float)
    return float(np.mean(s**2)) if s.ndim == 1 else float(np.mean(np.trace(s, axis1=1, axis2=2)) / 2)
