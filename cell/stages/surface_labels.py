"""Which surface of the part each pixel near a dot sees: the label image the detector masks its background with.

A dot a few pixels from an edge of the part (in the image) has the other surface (a side face, the scene far
behind) in the ring its background plane is fitted to and in the margin its centroid is grown by: its centre is
biased, with one sign in every view from one side (decisions 0023, 0029). MEASURE knows the CAD and, after naming,
a pose good to a fraction of a pixel; :class:`SurfaceLabeller` casts the ray of every pixel in a window around each
given dot against the mesh and labels it with the *patch* its ray hits: faces joined across edges that bend by no
more than ``max_bend_deg`` (a plane's coplanar triangles, a gently curved skin's facets), so that the labels change
only where the surface does. Rays that miss the part get :attr:`SurfaceLabeller.miss` (the scene behind it).
Pixels within ``band_px`` of a change of label are :data:`NO_USE` (the pose and the rendering of an edge are
not exact to a pixel), pixels outside every window :data:`UNKNOWN`. ``calibration.dots.detect_dots(labels=...)``
then fits each dot's background only to ring pixels of its own surface (docs/decisions/0035).
"""
from __future__ import annotations

import cv2
import numpy as np
import trimesh

from calibration.camera import Intrinsics, invert

__all__ = ["NO_USE", "UNKNOWN", "SurfaceLabeller", "surface_patches"]

#: a pixel whose label is not known (outside every window)
UNKNOWN = 0
#: a pixel within ``band_px`` of a change of surface: used by no dot's background
NO_USE = -1


def surface_patches(mesh: trimesh.Trimesh, max_bend_deg: float = 15.0) -> np.ndarray:
    """(F,) int patch label >= 1 of each face: faces joined across shared edges that bend by at most
    ``max_bend_deg`` (connected components of that face graph)."""
    n = len(mesh.faces)
    adj = np.asarray(mesh.face_adjacency, dtype=np.int64).reshape(-1, 2)
    ang = np.asarray(mesh.face_adjacency_angles, dtype=float).reshape(-1)
    keep = adj[ang <= np.radians(max_bend_deg)]
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    g = coo_matrix((np.ones(len(keep)), (keep[:, 0], keep[:, 1])), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    return comp.astype(np.int32) + 1


class SurfaceLabeller:
    """Per-image surface label images of one part's mesh (built once per job: patches and the ray scene)."""

    def __init__(self, mesh: trimesh.Trimesh, max_bend_deg: float = 15.0, band_px: int = 2):
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        if len(mesh.faces) == 0:
            raise ValueError("surface labels need a mesh with faces")
        self.mesh = mesh
        self.patch = surface_patches(mesh, max_bend_deg)
        #: the label of pixels whose ray misses the part (the scene behind it)
        self.miss = int(self.patch.max()) + 1
        self.band_px = int(band_px)
        self._rays = RayMeshIntersector(mesh)

    def labels(self, intr: Intrinsics, cam_from_part: np.ndarray, centres_uv: np.ndarray,
               half_px: np.ndarray | float) -> np.ndarray:
        """(height, width) int32 labels in the windows ``centre +- half_px`` around ``centres_uv: (n, 2)`` (px).

        Each window pixel: its patch (>= 1), :attr:`miss`, or :data:`NO_USE` within ``band_px`` of another label;
        :data:`UNKNOWN` elsewhere. The windows are grown by ``band_px + 1`` so that the band is right at their edge.
        """
        H, W = intr.height, intr.width
        out = np.zeros((H, W), dtype=np.int32)
        c = np.asarray(centres_uv, dtype=float).reshape(-1, 2)
        if len(c) == 0:
            return out
        half = np.broadcast_to(np.asarray(half_px, dtype=float), (len(c),)) + self.band_px + 1
        x0 = np.clip(np.floor(c[:, 0] - half), 0, W).astype(int)
        x1 = np.clip(np.ceil(c[:, 0] + half) + 1, 0, W).astype(int)
        y0 = np.clip(np.floor(c[:, 1] - half), 0, H).astype(int)
        y1 = np.clip(np.ceil(c[:, 1] + half) + 1, 0, H).astype(int)
        win = np.zeros((H, W), dtype=np.uint8)
        for a, b, p, q in zip(x0, x1, y0, y1):
            win[p:q, a:b] = 1
        ys, xs = np.nonzero(win)
        if len(ys) == 0:
            return out
        xy = intr.pixel_to_normalised(np.stack([xs, ys], axis=1).astype(float))
        d_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        part_from_cam = invert(np.asarray(cam_from_part, dtype=float))
        d = d_cam @ part_from_cam[:3, :3].T
        o = np.broadcast_to(part_from_cam[:3, 3], d.shape)
        face = self._rays.intersects_first(np.ascontiguousarray(o), np.ascontiguousarray(d))
        out[ys, xs] = np.where(face >= 0, self.patch[np.maximum(face, 0)], self.miss)
        if self.band_px > 0:
            # another label within band_px: the pixel is near a change of surface (UNKNOWN pixels do not count)
            k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * self.band_px + 1, 2 * self.band_px + 1))
            bb = (slice(int(y0.min()), int(y1.max())), slice(int(x0.min()), int(x1.max())))
            sub = out[bb].astype(np.float32)
            hi = cv2.dilate(sub, k)
            lo = cv2.erode(np.where(sub > 0, sub, np.float32(2**24)), k)
            near = (sub > 0) & ((hi != sub) | (lo != sub))
            out[bb][near] = NO_USE
        return out
