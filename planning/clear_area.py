"""How much clear flat surface lies around a target: the radius of the largest disc in its tangent plane that
stays on the part's surface.

A dot next to an edge of the part is centred off by what lies beyond the edge (the dark ground, another face):
on generated plates, dots within 6 mm of the plate's outline (5 mm dots) came out 0.64 um outward on average
(standard error 0.14 um, 23 dots of six parts), those 10 mm or more away without a measurable shift (decision
0042). A target's own uncertainty states such an error as a random one; a scale bar's end is different: its error
along the bar becomes the scale of every target. The cell therefore says when a bar's end has an edge close by.

The test: points on circles of growing radius in the target's tangent plane are projected onto the mesh; the disc
is on the surface while every point lies within ``gap`` of it, where its normal is within ``acos(min_cos)`` of the
target's. An edge inside the disc fails it (the circle leaves the face: beyond the outline its closest point is on
a side face, another normal). A gently curved skin passes with a gap of a few tenths of a millimetre.
"""
from __future__ import annotations

import numpy as np
import trimesh

__all__ = ["disc_on_surface", "clear_radius"]


def _tangent_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.cross(normals, [0.0, 0.0, 1.0])
    a[np.linalg.norm(a, axis=1) < 1e-6] = [1.0, 0.0, 0.0]
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    return a, np.cross(normals, a)


def disc_on_surface(mesh: trimesh.Trimesh, points: np.ndarray, normals: np.ndarray, radius: float, gap: float,
                    min_cos: float, rings: int = 1) -> np.ndarray:
    """Whether a disc of ``radius`` in each point's tangent plane lies on the surface: its rim (and ``rings - 1``
    circles inside it, equally spaced) within ``gap`` of the mesh where the mesh's normal is within
    ``acos(min_cos)`` of the point's. Lengths in the mesh's units. (n,) bool."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    normals = np.asarray(normals, dtype=float).reshape(-1, 3)
    keep = np.ones(len(points), dtype=bool)
    if not len(points):
        return keep
    a, b = _tangent_frames(normals)
    for r in radius * np.arange(1, rings + 1) / rings:
        for ang in np.linspace(0, 2 * np.pi, 8 if rings == 1 else 16, endpoint=False):
            q = points + r * (np.cos(ang) * a + np.sin(ang) * b)
            _, dist, tri = trimesh.proximity.closest_point(mesh, q)
            keep &= (dist < gap) & (np.einsum("ij,ij->i", mesh.face_normals[tri], normals) > min_cos)
    return keep


def clear_radius(mesh: trimesh.Trimesh, points: np.ndarray, normals: np.ndarray, radii: np.ndarray,
                 gap_per_radius: float = 0.05, min_cos: float = 0.98) -> np.ndarray:
    """The largest of ``radii`` (increasing) whose disc around each point stays on the surface, checked on every
    circle up to it; 0 where even the smallest does not. ``gap = gap_per_radius * r`` (a curved face stands off
    its tangent plane by ``r^2 / 2R``: 0.05 r passes radii of curvature down to 10 r). (n,) in the mesh's units."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    out = np.zeros(len(points))
    alive = np.ones(len(points), dtype=bool)
    for r in np.asarray(radii, dtype=float):
        idx = np.flatnonzero(alive)
        if not len(idx):
            break
        ok = disc_on_surface(mesh, points[idx], np.asarray(normals, dtype=float).reshape(-1, 3)[idx], r,
                             gap_per_radius * r, min_cos)
        out[idx[ok]] = r
        alive[idx[~ok]] = False
    return out
