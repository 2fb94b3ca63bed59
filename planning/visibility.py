"""Which targets each candidate station can measure, and the database that stores it.

A target is measurable from a station when all of these hold (seed: "visibility
constraints ... incidence angle constraint"):

* it is in front of the camera and its image lies inside the image by ``margin_px``
  (with the lens distortion of the intrinsics);
* its depth is inside the depth of field ``[near_m, far_m]``;
* the angle between its outward normal and the direction to the camera centre is at
  most ``incidence_max_rad``;
* its image is at least ``min_target_px`` across (``diameter * fx / depth``);
* the segment from the target (moved ``ray_offset_m`` along its normal, off the
  surface) to the camera centre meets no triangle of the part (self-occlusion).

Occlusion is a segment test, so it is right for any camera position. Two
interchangeable backends answer it: Embree (``embreex``, float32, a few tens of
millions of rays per second) and trimesh's pure-NumPy triangle intersector (slow;
for tiny meshes and as the reference of the parity test).

The results over a dense set of candidate stations are kept in a :class:`VisibilityDB`
cached on disk under a sha256 of everything they depend on, so the same part and
camera reuse it (the seed's "database for online query").
"""
from __future__ import annotations

import hashlib
import json
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from calibration.camera import Intrinsics, invert
from calibration.errors import PlanningError
from planning.cache import load_arrays, save_arrays
from planning.stations import N_GENES, ViewingSphere

__all__ = [
    "VisibilityOptions",
    "Occluder",
    "geometric_visibility",
    "geometric_visibility_compiled",
    "compute_visibility",
    "VisibilityDB",
    "default_cache_dir",
]

Progress = Callable[[str, float], None]
_DB_FORMAT = "visibility-db-2"  # 2: the visibility stored as packed bits, uncompressed


@dataclass(frozen=True)
class VisibilityOptions:
    """Measurability limits.

    Attributes:
        margin_px: a target's image centre must lie this far inside the image border.
        near_m, far_m: depth of field (camera-frame z of the target).
        incidence_max_rad: largest angle between target normal and line of sight.
        min_target_px: smallest image diameter of a target (``diameter * fx / depth``).
        ray_offset_m: the occlusion ray starts this far off the surface along the normal.
        check_occlusion: ray-cast against the part (off only for diagnostics).
    """

    margin_px: float = 10.0
    near_m: float = 0.0
    far_m: float = float("inf")
    incidence_max_rad: float = float(np.deg2rad(60.0))
    min_target_px: float = 4.0
    ray_offset_m: float = 1e-4
    check_occlusion: bool = True

    def __post_init__(self) -> None:
        if not 0 <= self.near_m < self.far_m:
            raise PlanningError(f"visibility options: need 0 <= near_m < far_m, got {self.near_m} and {self.far_m}")
        if not 0 < self.incidence_max_rad <= np.pi / 2:
            raise PlanningError(f"visibility options: incidence_max_rad must be in (0, pi/2], got {self.incidence_max_rad}")
        if self.margin_px < 0 or self.min_target_px < 0 or self.ray_offset_m < 0:
            raise PlanningError("visibility options: margin_px, min_target_px and ray_offset_m must be >= 0")

    def to_dict(self) -> dict:
        return {k: (repr(v) if isinstance(v, float) and not np.isfinite(v) else v) for k, v in asdict(self).items()}


def default_cache_dir() -> Path:
    """``$CELL_CACHE_DIR`` or ``~/.cache/inspection-cell``."""
    env = os.environ.get("CELL_CACHE_DIR")
    return Path(env) if env else Path.home() / ".cache" / "inspection-cell"


# --- occlusion -----------------------------------------------------------------


class Occluder:
    """Segment-against-mesh occlusion tests, Embree or NumPy behind one call.

    ``Occluder(mesh, backend="embree" | "numpy").occluded(starts, ends)`` tells for each
    segment whether it meets the mesh strictly between its ends.
    """

    def __init__(self, mesh: trimesh.Trimesh, backend: str = "embree", workers: int | None = None):
        if backend not in ("embree", "numpy"):
            raise PlanningError(f"unknown ray-casting backend {backend!r}: use 'embree' or 'numpy'")
        if len(mesh.faces) == 0:
            raise PlanningError("cannot ray-cast against an empty mesh")
        self.mesh = mesh
        self.backend = backend
        self.workers = workers or min(2, os.cpu_count() or 1)
        # embree works in float32: move the mesh near the origin to keep precision
        self._origin = np.asarray(mesh.bounds, dtype=float).mean(axis=0)
        if backend == "embree":
            try:
                from embreex import rtcore_scene
                from embreex.mesh_construction import TriangleMesh
            except ImportError as exc:  # pragma: no cover - embreex is a dependency
                raise PlanningError("the 'embree' ray-casting backend needs embreex; install it or use backend='numpy'") from exc
            self._scene = rtcore_scene.EmbreeScene()
            TriangleMesh(
                scene=self._scene,
                vertices=np.ascontiguousarray(mesh.vertices - self._origin, dtype=np.float32),
                indices=np.ascontiguousarray(mesh.faces, dtype=np.int32),
            )
        else:
            from trimesh.ray.ray_triangle import RayMeshIntersector

            self._numpy = RayMeshIntersector(mesh)

    def occluded(self, starts: np.ndarray, ends: np.ndarray, chunk: int = 1 << 18) -> np.ndarray:
        """Whether each segment ``starts[i] -> ends[i]`` (``(r, 3)`` float) hits the mesh, (r,) bool."""
        starts = np.asarray(starts, dtype=float).reshape(-1, 3)
        ends = np.asarray(ends, dtype=float).reshape(-1, 3)
        if starts.shape != ends.shape:
            raise PlanningError(f"occluded: {len(starts)} segment starts but {len(ends)} ends")
        r = len(starts)
        if r == 0:
            return np.zeros(0, dtype=bool)
        if self.backend == "numpy":
            return self._occluded_numpy(starts, ends)
        slices = [slice(i, min(i + chunk, r)) for i in range(0, r, chunk)]
        out = np.empty(r, dtype=bool)

        def run(sl: slice) -> None:
            o = starts[sl] - self._origin
            d = ends[sl] - starts[sl]
            length = np.linalg.norm(d, axis=1)
            d = d / np.where(length > 0, length, 1.0)[:, None]
            hit = self._scene.run(
                o.astype(np.float32), d.astype(np.float32), query="OCCLUDED", dists=length.astype(np.float32)
            )
            out[sl] = (np.asarray(hit) != -1) & (length > 0)

        self._each_chunk(run, slices)
        return out

    def _each_chunk(self, run, slices: list[slice]) -> None:
        """``run(sl)`` for every slice: on ``self.workers`` threads when there is more than one (Embree releases
        the GIL), else in turn."""
        if self.workers > 1 and len(slices) > 1:
            with ThreadPoolExecutor(self.workers) as pool:
                list(pool.map(run, slices))
        else:
            for sl in slices:
                run(sl)

    def occluded_pairs(self, cast: np.ndarray, starts_all: np.ndarray, eyes: np.ndarray,
                       chunk: int = 1 << 18) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The segments of the pairs ``cast (c, n)`` bool, from ``starts_all[t]`` to ``eyes[i]``: their
        ``(ci, ti)`` and whether each hits the mesh (the answers of :meth:`occluded` on the same segments)."""
        if self.backend == "numpy":
            ci, ti = np.nonzero(cast)
            return ci, ti, self.occluded(starts_all[ti], eyes[ci], chunk)
        from planning import kernels

        ci, ti, o, d, length = kernels.segments(np.ascontiguousarray(cast), np.ascontiguousarray(starts_all),
                                                np.ascontiguousarray(eyes), np.ascontiguousarray(self._origin))
        r = len(ci)
        out = np.empty(r, dtype=bool)

        def run(sl: slice) -> None:
            hit = self._scene.run(o[sl], d[sl], query="OCCLUDED", dists=length[sl])
            out[sl] = (np.asarray(hit) != -1) & (length[sl] > 0)

        self._each_chunk(run, [slice(i, min(i + chunk, r)) for i in range(0, r, chunk)])
        return ci, ti, out

    def _occluded_numpy(self, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
        d = ends - starts
        length = np.linalg.norm(d, axis=1)
        d = d / np.where(length > 0, length, 1.0)[:, None]
        _, index_ray, locations = self._numpy.intersects_id(
            starts, d, multiple_hits=True, return_locations=True
        )
        locations = np.asarray(locations, dtype=float).reshape(-1, 3)
        index_ray = np.asarray(index_ray, dtype=np.intp)
        t = np.einsum("ij,ij->i", locations - starts[index_ray], d[index_ray])
        eps = 1e-9 * max(1.0, float(self.mesh.scale))
        inside = (t > eps) & (t < length[index_ray] - eps)
        out = np.zeros(len(starts), dtype=bool)
        out[index_ray[inside]] = True
        return out


# --- visibility -----------------------------------------------------------------


def geometric_visibility(
    intr: Intrinsics,
    part_from_cam: np.ndarray,
    xyz: np.ndarray,
    normals: np.ndarray,
    target_diameter_m: float,
    options: VisibilityOptions,
) -> np.ndarray:
    """Every test but occlusion, for ``part_from_cam: (m, 4, 4)`` x ``xyz: (n, 3)``; (m, n) bool.

    The cheap tests (incidence angle, depth of field, target size) run on every pair as matrix
    products; the projection into the image only on the pairs that pass them.
    """
    T = np.asarray(part_from_cam, dtype=float).reshape(-1, 4, 4)
    xyz = np.asarray(xyz, dtype=float)
    normals = np.asarray(normals, dtype=float)
    cam_from_part = invert(T)
    R, t = cam_from_part[:, :3, :3], cam_from_part[:, :3, 3]
    eye = T[:, :3, 3]
    # incidence: (eye - x) . n >= cos(max) |eye - x|
    sn = eye @ normals.T - np.sum(xyz * normals, axis=1)[None, :]
    d2 = np.sum(eye**2, axis=1)[:, None] - 2.0 * (eye @ xyz.T) + np.sum(xyz**2, axis=1)[None, :]
    ok = sn >= np.cos(options.incidence_max_rad) * np.sqrt(np.maximum(d2, 1e-24))
    z = R[:, 2, :] @ xyz.T + t[:, 2:3]
    ok &= (z > 1e-9) & (z >= options.near_m) & (z <= options.far_m)
    ok &= target_diameter_m * intr.fx_px >= options.min_target_px * np.where(z > 1e-9, z, np.inf)
    ci, ti = np.nonzero(ok)
    if len(ci):
        zc = z[ci, ti]
        xn = (R[:, 0, :] @ xyz.T + t[:, 0:1])[ci, ti] / zc
        yn = (R[:, 1, :] @ xyz.T + t[:, 1:2])[ci, ti] / zc
        xyd = intr.distort(np.stack([xn, yn], axis=1))
        uv = np.stack([intr.fx_px * xyd[:, 0] + intr.cx_px, intr.fy_px * xyd[:, 1] + intr.cy_px], axis=-1)
        out = ~intr.in_image(uv, options.margin_px)
        ok[ci[out], ti[out]] = False
    return ok


def geometric_visibility_compiled(intr: Intrinsics, part_from_cam: np.ndarray, xyz: np.ndarray, normals: np.ndarray,
                                  target_diameter_m: float, options: VisibilityOptions) -> np.ndarray:
    """:func:`geometric_visibility` compiled (planning.kernels.geometric_ok: each pair tested on its own, stopping
    at the first test it fails, no ``(m, n)`` temporaries); the same answers but where a pair lies within
    rounding (1e-15) of a limit."""
    from planning import kernels

    T = np.ascontiguousarray(np.asarray(part_from_cam, dtype=float).reshape(-1, 4, 4))
    cfp = np.ascontiguousarray(invert(T))
    xyz, normals = np.ascontiguousarray(xyz, dtype=float), np.ascontiguousarray(normals, dtype=float)
    cam = kernels.camera_vector(intr, options.margin_px)
    out = np.empty((len(T), len(xyz)), dtype=bool)
    args = (float(np.cos(options.incidence_max_rad)), float(options.near_m), float(options.far_m),
            float(target_diameter_m * intr.fx_px), float(options.min_target_px), cam)
    kernels.in_two(len(T), lambda a, b: kernels.geometric_ok(T[a:b], cfp[a:b], xyz, normals, *args, out[a:b]),
                   min_size=max(2, 200_000 // max(1, len(xyz))))
    return out


def compute_visibility(
    part,
    intr: Intrinsics,
    part_from_cam: np.ndarray,
    options: VisibilityOptions | None = None,
    backend: str = "embree",
    progress: Progress | None = None,
    occluder: Occluder | None = None,
    chunk_cameras: int = 128,
    *,
    rays_known: np.ndarray | None = None,
    rays_free: np.ndarray | None = None,
    geometric_out: np.ndarray | None = None,
) -> np.ndarray:
    """Whether each target of ``part`` is measurable from each pose; (m, n) bool.

    ``part`` has ``mesh``, ``targets.xyz (n, 3)``, ``targets.normals (n, 3)`` and
    ``target_diameter_m``; ``part_from_cam: (m, 4, 4)``. Only the (station, target)
    pairs that pass the geometric tests are ray-cast, and of those only the ones whose answer is
    not known already: ``rays_known (m, n)`` bool marks pairs whose occlusion segment (target to camera
    centre) was tested before, ``rays_free`` its answer (True: not occluded) -- a pose that shares its
    camera centre with one tested before (a look-at offset, a roll) casts no ray again.
    ``geometric_out (m, n)`` bool, if given, receives the geometric tests' result (the pairs whose
    occlusion is then known).
    """
    options = options or VisibilityOptions()
    T = np.asarray(part_from_cam, dtype=float).reshape(-1, 4, 4)
    xyz = np.asarray(part.targets.xyz, dtype=float)
    normals = np.asarray(part.targets.normals, dtype=float)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or normals.shape != xyz.shape:
        raise PlanningError(f"part {getattr(part, 'name', '?')!r}: targets need (n, 3) xyz and normals")
    if options.check_occlusion and occluder is None:
        occluder = Occluder(part.mesh, backend=backend)
    m = len(T)
    out = np.zeros((m, len(xyz)), dtype=bool)
    starts_all = xyz + options.ray_offset_m * normals  # each occlusion segment starts off the surface
    for c0 in range(0, m, chunk_cameras):
        c1 = min(c0 + chunk_cameras, m)
        ok = geometric_visibility_compiled(intr, T[c0:c1], xyz, normals, part.target_diameter_m, options)
        if geometric_out is not None:
            geometric_out[c0:c1] = ok
        if options.check_occlusion:
            cast = ok if rays_known is None else ok & ~rays_known[c0:c1]
            if rays_known is not None:
                ok &= ~rays_known[c0:c1] | rays_free[c0:c1]
            ci, ti, blocked = occluder.occluded_pairs(cast, starts_all, T[c0:c1, :3, 3])
            ok[ci[blocked], ti[blocked]] = False
        out[c0:c1] = ok
        if progress is not None:
            progress("visibility", c1 / m)
    return out


# --- database ---------------------------------------------------------------------


def _hash_inputs(part, intr: Intrinsics, sphere: ViewingSphere, options: VisibilityOptions, genes: np.ndarray) -> str:
    h = hashlib.sha256()
    h.update(_DB_FORMAT.encode())
    for a in (
        np.asarray(part.mesh.vertices, dtype=np.float64),
        np.asarray(part.mesh.faces, dtype=np.int64),
        np.asarray(part.targets.xyz, dtype=np.float64),
        np.asarray(part.targets.normals, dtype=np.float64),
        np.asarray(genes, dtype=np.float64),
    ):
        h.update(str(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    meta = {
        "target_diameter_m": float(part.target_diameter_m),
        "intrinsics": intr.to_dict(),
        "options": options.to_dict(),
        "sphere": sphere.to_dict(),
    }
    h.update(json.dumps(meta, sort_keys=True, default=repr).encode())
    return h.hexdigest()


@dataclass
class VisibilityDB:
    """Visibility of every target from a dense set of candidate stations.

    Attributes:
        genes: (m, N_GENES) candidate stations (zero roll and offset).
        part_from_cam: (m, 4, 4) their poses.
        visible: (m, n) bool, target j measurable from candidate i.
        key: sha256 (hex) of the inputs; the cache file's name.
        sphere, options: what it was built with.
        from_cache: whether it was loaded rather than computed.
    """

    genes: np.ndarray
    part_from_cam: np.ndarray
    visible: np.ndarray
    key: str
    sphere: ViewingSphere
    options: VisibilityOptions
    from_cache: bool = False
    _tree: object = field(default=None, repr=False, compare=False)

    @property
    def eyes(self) -> np.ndarray:
        """(m, 3) camera centres of the candidates (part frame)."""
        return self.part_from_cam[:, :3, 3]

    def nearest(self, genes: np.ndarray) -> np.ndarray:
        """Index of the candidate nearest to each station ``genes: (..., N_GENES)``; (...) int.

        "Nearest" is by camera centre (Euclidean, metres); roll and look-at offset are
        ignored because the database holds them at zero.
        """
        g = np.asarray(genes, dtype=float)
        if g.shape[-1] != N_GENES:
            raise PlanningError(f"nearest: station genes must have {N_GENES} entries, got {g.shape[-1]}")
        if self._tree is None:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.eyes)
        _, idx = self._tree.query(self.sphere.eyes(g).reshape(-1, 3))
        return np.asarray(idx, dtype=np.intp).reshape(g.shape[:-1])

    @classmethod
    def build(
        cls,
        part,
        intr: Intrinsics,
        sphere: ViewingSphere,
        options: VisibilityOptions | None = None,
        n_candidates: int = 3000,
        n_shells: int = 3,
        backend: str = "embree",
        progress: Progress | None = None,
    ) -> "VisibilityDB":
        """Compute (no cache). ``n_candidates`` is rounded up to a multiple of ``n_shells``."""
        options = options or VisibilityOptions()
        genes = sphere.candidates(max(1, -(-int(n_candidates) // n_shells)), n_shells)
        key = _hash_inputs(part, intr, sphere, options, genes)
        T = sphere.poses(genes)
        visible = compute_visibility(part, intr, T, options, backend=backend, progress=progress)
        return cls(genes=genes, part_from_cam=T, visible=visible, key=key, sphere=sphere, options=options)

    @classmethod
    def load_or_build(
        cls,
        part,
        intr: Intrinsics,
        sphere: ViewingSphere,
        options: VisibilityOptions | None = None,
        n_candidates: int = 3000,
        cache_dir: str | Path | None = None,
        progress: Progress | None = None,
        *,
        n_shells: int = 3,
        backend: str = "embree",
    ) -> "VisibilityDB":
        """Load the database from ``cache_dir`` if the same inputs were seen, else build and store it.

        The file is ``visibility-<sha256>.npz``, written atomically (temporary file, fsync,
        ``os.replace``). A damaged or mismatching file is rebuilt.
        """
        options = options or VisibilityOptions()
        cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        genes = sphere.candidates(max(1, -(-int(n_candidates) // n_shells)), n_shells)
        key = _hash_inputs(part, intr, sphere, options, genes)
        path = cache / f"visibility-{key}.npz"
        n = len(part.targets.xyz)
        cached = load_arrays(path, ("key", "visible_bits"))  # None when missing or damaged (then rebuilt)
        shape = (len(genes), -(-n // 8))
        if cached is not None and str(cached["key"]) == key and cached["visible_bits"].shape == shape:
            if progress is not None:
                progress("visibility (cached)", 1.0)
            visible = np.unpackbits(cached["visible_bits"], axis=1, count=n).astype(bool)
            return cls(genes=genes, part_from_cam=sphere.poses(genes), visible=visible,
                       key=key, sphere=sphere, options=options, from_cache=True)
        T = sphere.poses(genes)
        visible = compute_visibility(part, intr, T, options, backend=backend, progress=progress)
        db = cls(genes=genes, part_from_cam=T, visible=visible, key=key, sphere=sphere, options=options)
        try:
            db.save(path)
        except OSError:
            pass  # a cache that cannot be written (full or read-only disk) costs time next run, nothing else
        return db

    def save(self, path: str | Path) -> Path:
        """Write atomically and durably to ``path`` (.npz with a digest; see ``planning.cache``)."""
        # packed bits, not zlib: 8x smaller than bools and written at disk speed (zlib took 7 s at 20k targets)
        return save_arrays(path, {"key": np.array(self.key), "genes": self.genes,
                                  "visible_bits": np.packbits(self.visible, axis=1)})
