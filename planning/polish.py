"""Continuous local polish of a planned network, evaluated exactly (fresh ray casting).

The visibility database holds candidates on a coarse lattice (a few distance shells,
zero roll and look-at offset), so the exchange descent of :mod:`planning.refine` cannot
make small moves.  This module builds, around the stations of a network, a small local
candidate set -- each station nudged in azimuth, elevation and distance and with small
look-at offsets -- casts rays for exactly those poses (:func:`compute_visibility`),
computes their target information, and runs the same exchange descent
(:func:`planning.refine.swap_descent`) on that local set: a station may be replaced by
any local variant of any station, if the worst target sigma falls.  Rounds repeat
around the improved network with the steps halved whenever a round brings nothing.

Only the stations that see the hardest targets (sigma within ``focus`` of the worst)
are nudged: an exchange lowers the worst only if the new station sees every critical
target, and stations that see none of the hard targets cannot change the worst.

Every pose ray-cast is kept in a cache while it can come again: a round whose steps did not change meets the
variants of the stations that did not move once more, and they are not cast again; a look-at-offset variant keeps
its station's camera centre, so its occlusion answers are its station's (only its geometric tests and information
are new). The exchange descent works on a view of the cache (no copies). The same poses, answers and choices as
casting every variant afresh (docs/decisions/0026-planspeed-numba.md).

Deterministic: no randomness, fixed step pattern.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera import Intrinsics
from planning.refine import network_sigma, swap_descent
from planning.stations import ViewingSphere
from planning import kernels
from planning.sparse_info import SparseInfo
from planning.uncertainty import target_information
from planning.visibility import Occluder, VisibilityOptions, compute_visibility


__all__ = ["PolishResult", "local_variants", "polish", "polish_network"]


@dataclass
class PolishResult:
    """Outcome of :func:`polish_network`.

    Attributes:
        genes: (k, N_GENES) the polished network (continuous genes).
        worst, start_worst: worst sigma (m) over the targets planned for, after and before.
        n_rounds: rounds run; n_swaps: exchanges made; n_poses: poses ray-cast.
    """

    genes: np.ndarray
    worst: float
    start_worst: float
    n_rounds: int
    n_swaps: int
    n_poses: int


def local_variants(genes: np.ndarray, sphere: ViewingSphere, step_rad: float, step_m: float,
                   offset_m: float) -> np.ndarray:
    """Nudged copies of stations ``genes: (s, N_GENES)``; (s, 10, N_GENES).

    Per station: azimuth +-``step_rad`` (scaled by 1/cos(elevation), so the camera moves
    about ``step_rad`` of arc), elevation +-``step_rad``, distance +-``step_m`` and the
    look-at point moved +-``offset_m`` along the image's u and v axes.  Azimuth wraps,
    elevation and distance are clipped into the sphere's bounds.
    """
    g = np.asarray(genes, dtype=float)
    s = len(g)
    out = np.repeat(g[:, None, :], 10, axis=1)
    daz = step_rad / np.maximum(np.cos(g[:, 1]), 0.2)
    out[:, 0, 0] += daz
    out[:, 1, 0] -= daz
    out[:, 2, 1] += step_rad
    out[:, 3, 1] -= step_rad
    out[:, 4, 2] += step_m
    out[:, 5, 2] -= step_m
    out[:, 6, 4] += offset_m
    out[:, 7, 4] -= offset_m
    out[:, 8, 5] += offset_m
    out[:, 9, 5] -= offset_m
    lo, hi = sphere.lower, sphere.upper
    out[..., 0] = lo[0] + np.mod(out[..., 0] - lo[0], hi[0] - lo[0]) if hi[0] - lo[0] >= 2 * np.pi - 1e-9 \
        else np.clip(out[..., 0], lo[0], hi[0])
    out[..., 1] = np.clip(out[..., 1], lo[1], hi[1])
    out[..., 2] = np.clip(out[..., 2], lo[2], hi[2])
    return out.reshape(s, 10, -1)


def polish_network(
    part,
    intr: Intrinsics,
    sphere: ViewingSphere,
    vis_opts: VisibilityOptions,
    genes: np.ndarray,
    cols: np.ndarray,
    min_rays: int,
    sigma_px,
    *,
    step_rad: float,
    step_m: float,
    offset_m: float,
    rounds: int = 6,
    focus: float = 0.9,
    backend: str = "embree",
    reachable_fn=None,
    link_targets: int = 0,
    sole_links: bool = True,
) -> PolishResult:
    """Exchange descent over exactly ray-cast local variants of the network (module docstring).

    Args:
        genes: (k, N_GENES) the network; cols: (c,) int the targets planned for.
        step_rad, step_m, offset_m: first steps (halved after a round without improvement).
        rounds: rounds of variants + descent; focus: stations seeing a target with
            sigma >= ``focus`` x worst are nudged.
        reachable_fn: ``part_from_cam (m, 4, 4) -> (m,) bool``, the robot's reachability of the
            variants (IK and collisions, :func:`planning.reachability.reachability_mask`); None: all.
        link_targets: a round's exchanges are taken only if they leave no more stations outside the network's
            largest block linked by this many common targets (or, ``sole_links``, stations that alone link a part of
            it) than before (0: not checked).
    Returns:
        :class:`PolishResult`; its worst is never above the start's.
    """
    xyz = np.asarray(part.targets.xyz, dtype=float)[cols]
    cur = np.array(genes, dtype=float)
    k = len(cur)
    sub = _TargetSubset(part, cols)
    occluder = Occluder(part.mesh, backend=backend) if vis_opts.check_occlusion else None
    cache = _VariantCache(len(cols))

    def visibility(g: np.ndarray, parent_rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Poses, visibility and geometric tests of ``g``; a pose with the camera centre of its parent (cache
        rows ``parent_rows``, -1: none) reuses the parent's occlusion answers."""
        T = sphere.poses(g)
        geo = np.empty((len(g), len(cols)), dtype=bool)
        known = free = None
        if parent_rows is not None and np.any(parent_rows >= 0):
            known = np.zeros_like(geo)
            free = np.zeros_like(geo)
            same = np.flatnonzero(parent_rows >= 0)
            known[same], free[same] = cache.geo[parent_rows[same]], cache.vis[parent_rows[same]]
        vis = compute_visibility(sub, intr, T, vis_opts, backend=backend, occluder=occluder, rays_known=known,
                                 rays_free=free, geometric_out=geo)
        return T, vis, geo

    def information(T: np.ndarray, vis: np.ndarray, used: np.ndarray) -> SparseInfo:
        """The information of the poses ``used`` (the others get empty rows: they never enter a pool)."""
        info = target_information(intr, T[used], xyz, vis[used], sigma_px, dtype=np.float64, sparse=True)
        lens = np.zeros(len(T), dtype=np.int64)
        lens[used] = np.diff(info.indptr)
        return SparseInfo(np.concatenate([[0], np.cumsum(lens)]), info.indices, info.data, len(cols))

    T0, vis0, geo0 = visibility(cur)
    all_k = np.ones(k, dtype=bool)
    cur_rows = cache.add(information(T0, vis0, all_k), vis0, geo0, all_k)
    sig = network_sigma(cache.info(cur_rows), vis0, np.arange(k), min_rays)
    start = worst = float(sig.max())
    unlinked = kernels.count_unlinked(kernels.pack_rows(vis0), np.arange(k)[None], link_targets, sole_links)[0] \
        if link_targets > 0 else 0.0
    n_rounds = n_swaps = 0
    n_poses = k
    if not np.isfinite(worst):
        return PolishResult(cur, worst, start, 0, 0, n_poses)
    for _ in range(rounds):
        n_rounds += 1
        hard = sig >= focus * worst
        movers = np.flatnonzero(cache.vis[cur_rows][:, hard].any(axis=1))
        var = local_variants(cur[movers], sphere, step_rad, step_m, offset_m).reshape(-1, cur.shape[1])
        # a variant met in an earlier round (its station did not move, the steps did not change) is not
        # ray-cast again: its rows are the same
        new = cache.missing(var)
        if len(new):
            parents = np.repeat(cur[movers], 10, axis=0)[new]
            # a look-at offset keeps the camera centre: the occlusion segments are the parent's
            same_eye = np.all(var[new][:, :3] == parents[:, :3], axis=1)
            parent_rows = np.where(same_eye, np.repeat(cur_rows[movers], 10)[new], -1)
            T_n, vis_n, geo_n = visibility(var[new], parent_rows)
            n_poses += len(new)
            ok = vis_n.any(axis=1)
            if reachable_fn is not None and ok.any():
                idx = np.flatnonzero(ok)
                ok[idx[~np.asarray(reachable_fn(sphere.poses(var[new][idx])), dtype=bool)]] = False
            # information only for the usable variants (seeing something, reachable)
            cache.add(information(T_n, vis_n, ok), vis_n, geo_n, ok, var[new], parents=parents)
        rows, keep = cache.lookup(var)
        pool_rows = np.concatenate([cur_rows, rows[keep]])
        pool_genes = np.concatenate([cur, var[keep]])
        r = swap_descent(cache.info(pool_rows), cache.vis[pool_rows], np.arange(len(pool_rows)), np.arange(k),
                         min_rays)
        if r.worst < worst and link_targets > 0 and kernels.count_unlinked(
                kernels.pack_rows(cache.vis[pool_rows[r.stations]]), np.arange(k)[None], link_targets,
                sole_links)[0] > unlinked:
            r.worst = worst  # splits the network into blocks ADJUST would not link: not taken
        if r.worst < worst:
            n_swaps += r.n_swaps
            cur, cur_rows = pool_genes[r.stations], pool_rows[r.stations]
            sig = network_sigma(cache.info(cur_rows), cache.vis[cur_rows], np.arange(k), min_rays)
            worst = float(sig.max())
            # with the same steps, the variants of stations still in the network come again, and this round's
            # may (a station moved and back)
            cur_rows = cache.keep(np.concatenate([cur_rows, rows]), {g.tobytes() for g in cur})[:k]
        else:
            step_rad, step_m, offset_m = 0.5 * step_rad, 0.5 * step_m, 0.5 * offset_m
            cur_rows = cache.keep(cur_rows, set())  # new steps: no variant comes again
    return PolishResult(cur, worst, start, n_rounds, n_swaps, n_poses)


class _TargetSubset:
    """The part with only the targets ``cols`` (what compute_visibility needs: mesh, targets, diameter)."""

    def __init__(self, part, cols: np.ndarray):
        self.name = getattr(part, "name", "?")
        self.mesh = part.mesh
        self.target_diameter_m = part.target_diameter_m
        self.targets = _Targets(np.asarray(part.targets.xyz, dtype=float)[cols],
                                np.asarray(part.targets.normals, dtype=float)[cols])


@dataclass
class _Targets:
    xyz: np.ndarray
    normals: np.ndarray


class _VariantCache:
    """Ray-cast poses: information rows (float64, in buffers that double when full, so appending costs the
    new rows only), visibility, usable; variants are found again by their exact genes."""

    def __init__(self, n: int):
        self.n = n
        self.index: dict[bytes, int] = {}
        self.m = self.nnz = 0
        self.starts = np.zeros(64, dtype=np.int64)
        self.ends = np.zeros(64, dtype=np.int64)
        self.ok = np.zeros(64, dtype=bool)
        self.vis = np.zeros((64, n), dtype=bool)
        self.geo = np.zeros((64, n), dtype=bool)  # the pairs whose occlusion was tested (geometric tests passed)
        self.indices = np.zeros(1 << 16, dtype=np.int32)
        self.data = np.zeros((1 << 16, 6))
        self.keys: list[bytes | None] = []
        self.parents: list[bytes | None] = []

    def missing(self, var: np.ndarray) -> np.ndarray:
        """Indices of the rows of ``var`` not cached (first occurrences only)."""
        seen, out = set(), []
        for i, g in enumerate(var):
            key = g.tobytes()
            if key not in self.index and key not in seen:
                seen.add(key)
                out.append(i)
        return np.array(out, dtype=np.intp)

    @staticmethod
    def _fit(a: np.ndarray, size: int) -> np.ndarray:
        if size <= len(a):
            return a
        out = np.empty((max(size, 2 * len(a)),) + a.shape[1:], dtype=a.dtype)
        out[:len(a)] = a
        return out

    def add(self, info: SparseInfo, vis: np.ndarray, geo: np.ndarray, ok: np.ndarray, var: np.ndarray | None = None,
            parents: np.ndarray | None = None) -> np.ndarray:
        """Store rows (``var``: the genes they are found by, ``parents``: the stations they vary; None: not
        found by genes); their cache rows."""
        r, m0, e0, nnz = len(vis), self.m, self.nnz, len(info.indices)
        self.starts, self.ends = self._fit(self.starts, m0 + r), self._fit(self.ends, m0 + r)
        self.ok, self.vis = self._fit(self.ok, m0 + r), self._fit(self.vis, m0 + r)
        self.geo = self._fit(self.geo, m0 + r)
        self.indices, self.data = self._fit(self.indices, e0 + nnz), self._fit(self.data, e0 + nnz)
        self.starts[m0:m0 + r], self.ends[m0:m0 + r] = e0 + info.indptr[:-1], e0 + info.indptr[1:]
        self.ok[m0:m0 + r], self.vis[m0:m0 + r], self.geo[m0:m0 + r] = ok, vis, geo
        self.indices[e0:e0 + nnz], self.data[e0:e0 + nnz] = info.indices, info.data
        keys = [None] * r if var is None else [g.tobytes() for g in var]
        for i, key in enumerate(keys):
            if key is not None:
                self.index[key] = m0 + i
        self.keys += keys
        self.parents += [None] * r if parents is None else [g.tobytes() for g in parents]
        self.m, self.nnz = m0 + r, e0 + nnz
        return np.arange(m0, m0 + r)

    def keep(self, rows: np.ndarray, parents: set) -> np.ndarray:
        """Drop every row but ``rows`` (the network) and the variants of the stations ``parents`` (gene bytes;
        the variants that may come again): the cache holds what can still be used, not every pose the polish
        cast. Returns the new row numbers of ``rows``."""
        again = [i for i, p in enumerate(self.parents) if p is not None and p in parents]
        order = np.unique(np.concatenate([rows, np.array(again, dtype=np.intp)]).astype(np.intp))
        live = np.zeros(self.m, dtype=bool)
        live[order] = True
        lens = self.ends[:self.m] - self.starts[:self.m]
        if lens[~live].sum() <= lens[live].sum():  # few dead rows: forget them, move nothing
            for i in np.flatnonzero(~live):
                if self.keys[i] is not None:
                    self.index.pop(self.keys[i], None)
                self.keys[i] = self.parents[i] = None
            return rows
        new_of = np.full(self.m, -1, dtype=np.intp)
        new_of[order] = np.arange(len(order))
        lens = self.ends[order] - self.starts[order]
        offs = np.concatenate([[0], np.cumsum(lens)])
        e = np.repeat(self.starts[order] - offs[:-1], lens) + np.arange(int(offs[-1]))
        self.indices[:len(e)], self.data[:len(e)] = self.indices[e], self.data[e]
        self.starts[:len(order)], self.ends[:len(order)] = offs[:-1], offs[1:]
        for a in (self.ok, self.vis, self.geo):
            a[:len(order)] = a[order]
        self.keys = [self.keys[i] for i in order]
        self.parents = [self.parents[i] for i in order]
        self.index = {key: i for i, key in enumerate(self.keys) if key is not None}
        self.m, self.nnz = len(order), int(offs[-1])
        return new_of[rows]

    def lookup(self, var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cache row of each variant, and whether it is usable (sees a target, reachable)."""
        rows = np.array([self.index[g.tobytes()] for g in var], dtype=np.intp)
        return rows, self.ok[rows]

    def info(self, rows: np.ndarray) -> SparseInfo:
        """The information of cache rows ``rows``, in that order (a view: no copy)."""
        return SparseInfo.view(self.starts[rows], self.ends[rows], self.indices, self.data, self.n)


def polish(part, intr: Intrinsics, sphere: ViewingSphere, vis_opts: VisibilityOptions, db, genes: np.ndarray,
           cols: np.ndarray, options, reachable_fn=None) -> PolishResult:
    """:func:`polish_network` with steps scaled to the database ``db`` and the part.

    First steps: half the database's angular spacing (its directions per shell spread
    over the band's solid angle), 4 % of the sphere's distance range, and 10 % of the
    part's bounding radius for the look-at offsets.  ``options``: PlannerOptions.
    """
    band = (sphere.azimuth_max_rad - sphere.azimuth_min_rad) * (
        np.sin(sphere.elevation_max_rad) - np.sin(sphere.elevation_min_rad))
    n_dirs = max(1, len(db.genes) // max(1, options.n_shells))
    step_rad = 0.5 * float(np.sqrt(band / n_dirs))
    step_m = 0.04 * (sphere.distance_max_m - sphere.distance_min_m)
    return polish_network(part, intr, sphere, vis_opts, genes, cols, options.min_rays, options.image_sigma(cols),
                          step_rad=step_rad, step_m=step_m, offset_m=0.1 * float(part.radius),
                          rounds=options.polish_rounds, backend=options.backend, reachable_fn=reachable_fn,
                          link_targets=options.link_targets, sole_links=options.sole_links)
