"""Camera stations on the viewing sphere (the search space of network design).

A station is a camera pose described by ``N_GENES`` real numbers ("genes"), in this order:

====  ===============  ==========================================================
 0    ``azimuth_rad``   direction from the part's centre to the camera, about +z
 1    ``elevation_rad`` angle of that direction above the part's xy plane
 2    ``distance_m``    distance from the part's centre to the camera centre
 3    ``roll_rad``      rotation of the camera about its optical axis
 4    ``offset_u_m``    look-at point moved along the image's +u (x) axis
 5    ``offset_v_m``    look-at point moved along the image's +v (y, down) axis
====  ===============  ==========================================================

The camera centre is ``centre + distance * d(az, el)`` with
``d = (cos el cos az, cos el sin az, sin el)``, and the camera looks at
``centre + offset_u * x0 + offset_v * y0`` where ``x0, y0`` are the image axes of the
un-offset, un-rolled camera. With zero roll the image's "up" (-v) follows the part's
+z axis (as :func:`calibration.camera.look_at` with ``up=(0, 0, 1)``); the frame is
built from the azimuth, so it is smooth through the pole (elevation = 90 deg).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera import Intrinsics
from calibration.errors import PlanningError

__all__ = ["N_GENES", "GENE_NAMES", "ViewingSphere", "fibonacci_band"]

GENE_NAMES = ("azimuth_rad", "elevation_rad", "distance_m", "roll_rad", "offset_u_m", "offset_v_m")
N_GENES = len(GENE_NAMES)

_GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


def fibonacci_band(n: int, elevation_min_rad: float, elevation_max_rad: float,
                   azimuth_min_rad: float = -np.pi, azimuth_max_rad: float = np.pi) -> np.ndarray:
    """``n`` near-uniform directions (Fibonacci lattice) within an elevation band.

    Returns ``(n, 2)`` float: ``(azimuth_rad, elevation_rad)``. Equal-area in the band:
    ``sin(elevation)`` is uniform; the azimuth advances by the golden angle (wrapped into
    the azimuth range, scaled when the range is not the full circle).
    """
    if n < 1:
        raise PlanningError(f"fibonacci_band: need at least one direction, got n={n}")
    i = np.arange(n, dtype=float)
    s0, s1 = np.sin(elevation_min_rad), np.sin(elevation_max_rad)
    s = s0 + (s1 - s0) * (i + 0.5) / n
    el = np.arcsin(np.clip(s, -1.0, 1.0))
    frac = np.mod(i * _GOLDEN_ANGLE / (2 * np.pi), 1.0)
    az = azimuth_min_rad + frac * (azimuth_max_rad - azimuth_min_rad)
    return np.stack([az, el], axis=1)


@dataclass(frozen=True)
class ViewingSphere:
    """Where stations may lie: a spherical shell about the part's centre.

    Attributes:
        centre: (3,) the part's centre (part frame, metres); cameras look at it.
        distance_min_m, distance_max_m: camera-centre distance range.
        elevation_min_rad, elevation_max_rad: elevation band (part frame +z is up).
        azimuth_min_rad, azimuth_max_rad: azimuth range.
        max_offset_m: bound of the look-at offset genes (each of u and v).
        max_roll_rad: bound of the roll gene.
    """

    centre: tuple[float, float, float]
    distance_min_m: float
    distance_max_m: float
    elevation_min_rad: float
    elevation_max_rad: float
    azimuth_min_rad: float = -np.pi
    azimuth_max_rad: float = np.pi
    max_offset_m: float = 0.0
    max_roll_rad: float = np.pi / 2

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre", tuple(float(c) for c in np.asarray(self.centre, dtype=float).reshape(3)))
        if not 0 < self.distance_min_m <= self.distance_max_m:
            raise PlanningError(
                f"viewing sphere: need 0 < distance_min_m <= distance_max_m, got "
                f"{self.distance_min_m} and {self.distance_max_m}"
            )
        if not -np.pi / 2 <= self.elevation_min_rad <= self.elevation_max_rad <= np.pi / 2:
            raise PlanningError(
                f"viewing sphere: elevation bounds must satisfy -pi/2 <= min <= max <= pi/2, got "
                f"{self.elevation_min_rad} and {self.elevation_max_rad}"
            )
        if not self.azimuth_min_rad <= self.azimuth_max_rad:
            raise PlanningError("viewing sphere: azimuth_min_rad must not exceed azimuth_max_rad")
        if self.max_offset_m < 0 or self.max_roll_rad < 0:
            raise PlanningError("viewing sphere: max_offset_m and max_roll_rad must be >= 0")

    # --- bounds -------------------------------------------------------------
    @property
    def lower(self) -> np.ndarray:
        """(N_GENES,) lower bounds of the genes."""
        return np.array([self.azimuth_min_rad, self.elevation_min_rad, self.distance_min_m,
                         -self.max_roll_rad, -self.max_offset_m, -self.max_offset_m])

    @property
    def upper(self) -> np.ndarray:
        """(N_GENES,) upper bounds of the genes."""
        return np.array([self.azimuth_max_rad, self.elevation_max_rad, self.distance_max_m,
                         self.max_roll_rad, self.max_offset_m, self.max_offset_m])

    def clip(self, genes: np.ndarray) -> np.ndarray:
        """Genes ``(..., N_GENES)`` clipped into the bounds."""
        return np.clip(genes, self.lower, self.upper)

    # --- geometry -----------------------------------------------------------
    def eyes(self, genes: np.ndarray) -> np.ndarray:
        """Camera centres (part frame) of ``genes: (..., N_GENES)``, (..., 3)."""
        g = np.asarray(genes, dtype=float)
        az, el, d = g[..., 0], g[..., 1], g[..., 2]
        ce = np.cos(el)
        direction = np.stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)], axis=-1)
        return np.asarray(self.centre) + d[..., None] * direction

    def poses(self, genes: np.ndarray) -> np.ndarray:
        """``part_from_cam`` of ``genes: (..., N_GENES)``, (..., 4, 4). Vectorised."""
        g = np.asarray(genes, dtype=float)
        if g.shape[-1] != N_GENES:
            raise PlanningError(f"station genes must have {N_GENES} entries ({', '.join(GENE_NAMES)}), got {g.shape[-1]}")
        az, roll = g[..., 0], g[..., 3]
        eye = self.eyes(g)
        centre = np.asarray(self.centre)
        z0 = centre - eye
        z0 /= np.linalg.norm(z0, axis=-1, keepdims=True)
        # x0 = normalise(z0 x up) with up = +z, written with the azimuth so it is defined at the pole
        x0 = np.stack([-np.sin(az), np.cos(az), np.zeros_like(az)], axis=-1)
        y0 = np.cross(z0, x0)
        aim = centre + g[..., 4, None] * x0 + g[..., 5, None] * y0
        z = aim - eye
        z /= np.linalg.norm(z, axis=-1, keepdims=True)
        x = x0 - np.sum(x0 * z, axis=-1, keepdims=True) * z
        x /= np.linalg.norm(x, axis=-1, keepdims=True)
        y = np.cross(z, x)
        # roll about the optical axis: R = [x y z] @ Rz(roll)
        c, s = np.cos(roll)[..., None], np.sin(roll)[..., None]
        xr = c * x + s * y
        yr = -s * x + c * y
        T = np.zeros(g.shape[:-1] + (4, 4))
        T[..., :3, 0] = xr
        T[..., :3, 1] = yr
        T[..., :3, 2] = z
        T[..., :3, 3] = eye
        T[..., 3, 3] = 1.0
        return T

    # --- candidates ---------------------------------------------------------
    def candidates(self, n: int, n_shells: int = 3) -> np.ndarray:
        """Dense candidate stations: ``n`` Fibonacci directions x ``n_shells`` distances.

        Returns ``(n * n_shells, N_GENES)`` genes, zero roll and offset, ordered shell by
        shell (the distances are evenly spaced from ``distance_min_m`` to
        ``distance_max_m``; one shell at the mean distance when ``n_shells == 1``).
        """
        if n_shells < 1:
            raise PlanningError(f"candidates: need at least one distance shell, got n_shells={n_shells}")
        ae = fibonacci_band(n, self.elevation_min_rad, self.elevation_max_rad,
                            self.azimuth_min_rad, self.azimuth_max_rad)
        if n_shells == 1:
            dists = np.array([0.5 * (self.distance_min_m + self.distance_max_m)])
        else:
            dists = np.linspace(self.distance_min_m, self.distance_max_m, n_shells)
        out = np.zeros((n_shells, n, N_GENES))
        out[:, :, 0:2] = ae
        out[:, :, 2] = dists[:, None]
        return out.reshape(-1, N_GENES)

    @classmethod
    def for_part(
        cls,
        part,
        intr: Intrinsics,
        *,
        fill: float = 0.7,
        distance_ratio: tuple[float, float] = (0.75, 1.5),
        clearance_m: float = 0.05,
        elevation_min_rad: float = float(np.deg2rad(5.0)),
        elevation_max_rad: float = np.pi / 2,
        max_offset_fraction: float = 0.25,
        max_roll_rad: float = np.pi / 2,
    ) -> "ViewingSphere":
        """A sphere sized so that the part fills the image sensibly.

        At the nominal distance the part's bounding sphere spans ``fill`` of the image's
        smaller side; the distance range is ``distance_ratio`` times that, but never
        closer than ``part.radius + clearance_m`` to the centre (cameras stay outside the
        part's bounding sphere). Look-at offsets are bounded by ``max_offset_fraction``
        of the part's radius.
        """
        radius = float(part.radius)
        if not radius > 0:
            raise PlanningError(f"part {getattr(part, 'name', '?')!r} has zero size; cannot size a viewing sphere")
        half_px = 0.5 * min(intr.width, intr.height)
        f_px = intr.fx_px if intr.width <= intr.height else intr.fy_px
        # bounding sphere radius r at distance d subtends r/d rad -> r * f / d pixels (half width)
        nominal = radius * f_px / (fill * half_px)
        d_min = max(distance_ratio[0] * nominal, radius + clearance_m)
        d_max = max(distance_ratio[1] * nominal, d_min * 1.2)
        return cls(
            centre=tuple(np.asarray(part.centre, dtype=float)),
            distance_min_m=d_min,
            distance_max_m=d_max,
            elevation_min_rad=float(elevation_min_rad),
            elevation_max_rad=float(elevation_max_rad),
            max_offset_m=float(max_offset_fraction * radius),
            max_roll_rad=float(max_roll_rad),
        )

    def to_dict(self) -> dict:
        return {
            "centre": list(self.centre),
            "distance_min_m": self.distance_min_m,
            "distance_max_m": self.distance_max_m,
            "elevation_min_rad": self.elevation_min_rad,
            "elevation_max_rad": self.elevation_max_rad,
            "azimuth_min_rad": self.azimuth_min_rad,
            "azimuth_max_rad": self.azimuth_max_rad,
            "max_offset_m": self.max_offset_m,
            "max_roll_rad": self.max_roll_rad,
        }
