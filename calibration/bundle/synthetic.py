"""Synthetic networks with known truth (tests, benchmarks, planning checks)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera import Intrinsics


@dataclass(frozen=True)
class SyntheticNetwork:
    """A simulated convergent network: truth and noisy observations.

    Attributes:
        intrinsics: true interior orientation.
        cam_from_part: (m, 4, 4) true poses.
        points: (n, 3) true targets.
        obs_image, obs_target: (q,) observation indices; obs_uv: (q, 2) noisy pixels; sigma_px: the noise.
    """

    intrinsics: Intrinsics
    cam_from_part: np.ndarray
    points: np.ndarray
    obs_image: np.ndarray
    obs_target: np.ndarray
    obs_uv: np.ndarray
    sigma_px: float


def simulate_network(
    rng: np.random.Generator,
    n_targets: int = 200,
    n_images: int = 12,
    intrinsics: Intrinsics | None = None,
    sigma_px: float = 0.05,
    size_m: float = 0.3,
    distance_m: float = 0.8,
    points: np.ndarray | None = None,
) -> SyntheticNetwork:
    """Targets in a box of side ``size_m`` seen by ``n_images`` cameras on a ring looking at its centre.

    Each camera sees the targets whose projection lies in the image (no occlusion); pixel noise is
    Gaussian with ``sigma_px``. Cameras are rolled at random so the interior orientation is determinable.
    """
    from calibration.camera import invert, look_at, project

    intr = intrinsics or Intrinsics(fx_px=3000.0, fy_px=3000.0, cx_px=1223.5, cy_px=1023.5, width=2448, height=2048)
    pts = rng.uniform(-size_m / 2, size_m / 2, (n_targets, 3)) if points is None else np.asarray(points, float)
    poses = []
    for j in range(n_images):
        az = 2 * np.pi * j / n_images + rng.uniform(-0.1, 0.1)
        el = 0.5 + 0.35 * np.sin(3 * az)
        eye = distance_m * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        poses.append(invert(look_at(eye, rng.normal(0, 0.01, 3), roll_rad=rng.uniform(-np.pi, np.pi))))
    poses = np.array(poses)
    oi, ot, ouv = [], [], []
    for j in range(n_images):
        uv = project(intr, poses[j], pts)
        vis = np.flatnonzero(intr.in_image(uv, margin_px=5.0))
        oi.append(np.full(len(vis), j))
        ot.append(vis)
        ouv.append(uv[vis] + rng.normal(0.0, sigma_px, (len(vis), 2)))
    return SyntheticNetwork(intr, poses, pts, np.concatenate(oi), np.concatenate(ot), np.vstack(ouv), sigma_px)
