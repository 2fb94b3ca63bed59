"""Vectorised kernels of target sampling (``planning.part.sample_targets``).

* :func:`greedy_spaced` keeps the candidates that a sequential greedy pass would keep ("accept
  a candidate unless an earlier accepted one lies closer than ``spacing``"), without the
  sequential pass: it is the lexicographically first maximal independent set of the
  candidates' conflict graph (pairs closer than ``spacing``, from a k-d tree), found in
  rounds, each a few NumPy operations over the pairs. For candidates in random order the
  number of rounds grows like log n. The result is identical to the sequential pass.
* :func:`facet_clearance` is the distance of each point to the boundary of the planar facet
  that holds it, computed per facet (or per triangle, for faces in no facet) in batches.

Both cost O(n log n) time and O(n) memory for n candidates spread over a surface.
"""
from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

__all__ = ["greedy_spaced", "facet_clearance", "face_to_facet", "point_segment_distance", "spaced_with_clearance"]


def _lexicographic_mis(m: int, pairs: np.ndarray) -> np.ndarray:
    """Lexicographically first maximal independent set of the graph on ``m`` vertices with edges
    ``pairs: (e, 2) int`` (i < j); (m,) bool."""
    UNDECIDED, IN, OUT = 0, 1, 2
    state = np.zeros(m, dtype=np.int8)
    a, b = pairs[:, 0], pairs[:, 1]
    while True:
        und = state == UNDECIDED
        if not und.any():
            break
        live = und[a] & und[b]
        a, b = a[live], b[live]
        blocked = np.zeros(m, dtype=bool)
        blocked[b] = True  # b has an undecided neighbour with a smaller index
        accept = und & ~blocked
        state[accept] = IN
        # the undecided neighbours of what was accepted are out (pairs are i < j: only b can be one)
        hit = accept[a]
        state[b[hit]] = OUT
    return state == IN


def greedy_spaced(points: np.ndarray, n: int, spacing: float) -> np.ndarray:
    """Indices of the first ``n`` points (in order) that a greedy pass keeps at ``spacing``.

    points: (m, 3) float, in the order the greedy pass sees them. Returns (k,) int, k <= n,
    increasing; k < n when the points cannot give n at that spacing.
    """
    m = len(points)
    if spacing <= 0.0 or m == 0:
        return np.arange(min(n, m))
    # the greedy choice among a prefix is the greedy choice among all, restricted to the prefix:
    # grow the prefix until it yields n (most sets need only a few times n candidates)
    size = min(m, max(4 * n, 1024))
    while True:
        tree = cKDTree(points[:size])
        pairs = tree.query_pairs(spacing, output_type="ndarray")
        if len(pairs):
            pairs = np.sort(pairs, axis=1)
        keep = np.flatnonzero(_lexicographic_mis(size, pairs.reshape(-1, 2)))
        if len(keep) >= n or size == m:
            return keep[:n]
        size = min(m, 2 * size)


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points ``p: (..., 3)`` to segments ``a, b: (..., 3)`` (broadcast); (...)."""
    return np.sqrt(_point_segment_d2(p, a, b))


def _point_segment_d2(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    ap = p - a
    t = np.einsum("...i,...i->...", ap, ab) / np.maximum(np.einsum("...i,...i->...", ab, ab), 1e-30)
    np.clip(t, 0.0, 1.0, out=t)
    diff = ap - t[..., None] * ab
    return np.einsum("...i,...i->...", diff, diff)


def face_to_facet(mesh: trimesh.Trimesh) -> np.ndarray:
    """(F,) index of the planar facet holding each face, -1 for a face in no facet."""
    out = np.full(len(mesh.faces), -1)
    facets = mesh.facets
    if len(facets):
        out[np.concatenate(facets)] = np.repeat(np.arange(len(facets)), [len(f) for f in facets])
    return out


def facet_clearance(mesh: trimesh.Trimesh, pts: np.ndarray, faces: np.ndarray, chunk: int = 1 << 16) -> np.ndarray:
    """Distance from each point ``pts: (m, 3)`` (on face ``faces: (m,)``) to the boundary of the planar
    facet holding that face, or to its triangle's edges when the face is in no facet; (m,) float."""
    out = np.full(len(pts), np.inf)
    group = face_to_facet(mesh)[faces]
    # faces in no facet: the three edges of the triangle, all at once
    lone = np.flatnonzero(group < 0)
    if len(lone):
        tri = mesh.vertices[mesh.faces[faces[lone]]]  # (l, 3, 3)
        seg_a, seg_b = tri, np.roll(tri, -1, axis=1)
        for s in range(0, len(lone), chunk):
            sl = slice(s, s + chunk)
            out[lone[sl]] = np.sqrt(_point_segment_d2(pts[lone[sl], None], seg_a[sl], seg_b[sl]).min(axis=1))
    # faces in a facet: each facet's boundary against the points on it
    held = np.flatnonzero(group >= 0)
    if len(held):
        boundaries = mesh.facets_boundary
        order = held[np.argsort(group[held], kind="stable")]
        ks, starts = np.unique(group[order], return_index=True)
        ends = np.append(starts[1:], len(order))
        for k, s0, s1 in zip(ks, starts, ends):
            seg = mesh.vertices[boundaries[k]]  # (e, 2, 3)
            step = max(1, chunk // max(1, len(seg)))
            for s in range(s0, s1, step):
                idx = order[s:min(s + step, s1)]
                out[idx] = np.sqrt(_point_segment_d2(pts[idx, None], seg[None, :, 0], seg[None, :, 1]).min(axis=1))
    return out


def spaced_with_clearance(mesh: trimesh.Trimesh, pts: np.ndarray, faces: np.ndarray, n: int,
                          spacings: tuple[float, ...], clearance: float) -> tuple[np.ndarray, float]:
    """The greedy choice of ``n`` of the candidates whose facet clearance is at least ``clearance``, at the
    first of ``spacings`` that yields ``n``; returns (indices into ``pts``, the spacing used).

    Clearance is computed only for as long a prefix of the candidates as the choice needs (the
    greedy choice over a prefix is the choice over all, restricted to it), so a set of n targets
    costs a few n candidates' clearances, not all 20 n. Fewer than ``n`` indices when even the
    last spacing cannot give ``n``.
    """
    m = len(pts)
    known = np.zeros(0)
    chosen, usable = np.arange(0), np.arange(0)
    for spacing in spacings:  # the first spacing that works over all candidates, as a sequential pass would
        size = min(m, max(5 * n, 2000))
        while True:
            if clearance > 0 and len(known) < size:
                known = np.concatenate([known, facet_clearance(mesh, pts[len(known):size], faces[len(known):size])])
            usable = np.flatnonzero(known[:size] >= clearance) if clearance > 0 else np.arange(size)
            chosen = greedy_spaced(pts[usable], n, spacing)
            if len(chosen) >= n:
                return usable[chosen], spacing
            if size == m:
                break
            size = min(m, 2 * size)
    return usable[chosen], spacings[-1]
