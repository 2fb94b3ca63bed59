"""The one simulated world of the sim cell.

The world holds the *true* state of the simulated cell: the part as it really is
(CAD targets plus their true deviations), where it really sits (``true_base_from_part``),
the camera's true mounting on the flange (``true_flange_from_cam``), and the robot's
current joints and flange pose. :class:`~sim_backend.sim_robot.SimRobot` writes the
robot's pose into it; :class:`~sim_backend.sim_camera.SimCamera` renders from it.

"True" and "nominal" are kept apart: the job states a nominal ``base_from_part`` and
``flange_from_cam``; the world may differ from them (to test hand-eye calibration and
part placement). Only the world's *true* values reach the renderer.

Conventions fixed here (the measurement code must follow them, see ``marker_axes``):

* A target is a flat disc (retro-reflective) or a square ArUco marker (coded) centred on
  its point, lying in the plane through the point perpendicular to its outward normal.
* In-plane axes of a target: ``e1`` is the part's +x axis projected onto the plane (the
  part's +y if the normal is within ~8 degrees of x), ``e2 = -n x e1``. Seen from the front
  (looking against ``n``), ``e1`` points to the right of the marker image and ``e2`` down,
  so a marker is not mirrored; its corners, in OpenCV ArUco order (top-left, top-right,
  bottom-right, bottom-left of the marker image), are ``c + (-a, -a), (a, -a), (a, a),
  (-a, a)`` in ``(e1, e2)`` with ``a = coded_size_m / 2`` (the outer edge of the black
  border). The marker's centre (the target point) is the intersection of its diagonals.

Worn targets: the world may hold damage to the coating of plain dots (:class:`TargetDamage`; the job's
``[sim] damaged_targets``), one row per target in ``damage_kind`` (0 intact, 1 ``edge``: the coating lost beyond
a chord, 2 ``spot``: a dark round speck on it), ``damage_lost`` (the share of the dot's area that no longer
reflects), ``damage_dir_rad`` (in-plane direction from the dot's centre, from ``e1`` towards ``e2``, to the lost
side or to the speck) and ``damage_offset`` (the speck's centre from the dot's, in dot radii). It is an unknown
defect of the real part: the renderer draws it (:func:`sim_backend.coverage.damaged_disc_coverage`), nothing the
cell plans or predicts with knows it (PLAN's twin builds its own world without it).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.camera import Intrinsics, invert
from calibration.errors import InputError

__all__ = ["TargetDamage", "World", "marker_axes", "marker_corners"]

#: the largest reach of a spot's rim from its dot's centre, in dot radii (``offset + sqrt(lost)``)
SPOT_MAX_REACH = 0.95
#: the largest share of a dot's area a damage may take
DAMAGE_MAX_LOST = 0.5


def marker_axes(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane axes ``(e1, e2)`` of targets with unit ``normals: (n, 3)``; each (n, 3).

    ``e1`` = part +x projected onto the target plane (part +y when the normal is almost
    parallel to x); ``e2 = -n x e1``, so that ``(e1, e2, -n)`` is right-handed.
    """
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    ref = np.where((np.abs(n[:, 0]) > 0.99)[:, None], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0])
    e1 = ref - np.sum(ref * n, axis=1, keepdims=True) * n
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(-n, e1)
    return e1, e2


def marker_corners(centres: np.ndarray, normals: np.ndarray, side_m: float) -> np.ndarray:
    """Corners of square markers of side ``side_m``, ArUco order (TL, TR, BR, BL), (n, 4, 3)."""
    c = np.asarray(centres, dtype=float).reshape(-1, 3)
    e1, e2 = marker_axes(normals)
    a = side_m / 2.0
    signs = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    return c[:, None, :] + a * (signs[None, :, 0, None] * e1[:, None, :] + signs[None, :, 1, None] * e2[:, None, :])


@dataclass(frozen=True)
class TargetDamage:
    """Damage to the retro-reflective coating of plain dots, one row per target of the part.

    Attributes:
        kind: (n,) int8, 0 intact, 1 edge (lost beyond a chord), 2 spot (under a dark round speck); the codes of
            :data:`sim_backend.coverage.DAMAGE_EDGE` / ``DAMAGE_SPOT``.
        lost: (n,) share of the dot's area that no longer reflects, 0 < lost <= 0.5 where damaged.
        direction_rad: (n,) in-plane direction from the dot's centre to the lost side (edge) or to the speck's
            centre (spot), radians from the target's ``e1`` towards ``e2`` (:func:`marker_axes`).
        offset: (n,) spot: the speck's centre from the dot's, in dot radii; the speck (radius ``sqrt(lost)`` dot
            radii) lies inside the dot: ``offset + sqrt(lost) <= 0.95``.
    """

    kind: np.ndarray
    lost: np.ndarray
    direction_rad: np.ndarray
    offset: np.ndarray

    @classmethod
    def none(cls, n: int) -> "TargetDamage":
        """No target damaged."""
        return cls(np.zeros(n, dtype=np.int8), np.zeros(n), np.zeros(n), np.zeros(n))

    @classmethod
    def of(cls, n: int, index: Any, kind: Any, lost: Any, direction_rad: Any, offset: Any) -> "TargetDamage":
        """``n`` targets, those at ``index: (m,)`` damaged as the (m,) rows ``kind`` (``"edge"``/``"spot"``),
        ``lost``, ``direction_rad``, ``offset`` say."""
        codes = {"edge": 1, "spot": 2}
        unknown = sorted({str(k) for k in kind} - set(codes))
        if unknown:
            raise InputError(f"target damage: kind {unknown[0]!r} is neither 'edge' nor 'spot'")
        d = cls.none(n)
        index = np.asarray(index, dtype=np.int64).reshape(-1)
        d.kind[index] = [codes[str(k)] for k in kind]
        d.lost[index] = lost
        d.direction_rad[index] = direction_rad
        d.offset[index] = offset
        return d

    def checked(self, ids: Any, kinds: Any) -> "TargetDamage":
        """This damage as validated arrays for the targets ``ids``, ``kinds`` (n,) (``"retro"``/``"coded"``);
        ``InputError`` naming the first bad target."""
        n = len(ids)
        arrays = []
        for name in ("kind", "lost", "direction_rad", "offset"):
            a = np.asarray(getattr(self, name))
            if a.shape != (n,) or not np.all(np.isfinite(a)):
                raise InputError(f"target damage: {name} must be a finite ({n},) array (one row per target), "
                                 f"got shape {a.shape}")
            arrays.append(a)
        kind, lost, direction, offset = (a.astype(float) for a in arrays)
        hurt = kind != 0
        reach = offset + np.sqrt(np.clip(lost, 0.0, None))
        checks = (
            (~np.isin(kind, (0, 1, 2)), lambda i: f"kind {kind[i]:g} is none of 0 (intact), 1 (edge), 2 (spot)"),
            (hurt & (np.asarray(kinds) == "coded"), lambda i: "it is a coded target; only plain dots are damaged"),
            (hurt & ~((lost > 0) & (lost <= DAMAGE_MAX_LOST)),
             lambda i: f"lost {lost[i]} is outside 0 < lost <= {DAMAGE_MAX_LOST}"),
            ((kind == 2) & ((reach > SPOT_MAX_REACH + 1e-12) | (offset < 0)),
             lambda i: f"the spot reaches {reach[i]:.3f} dot radii from the centre (offset {offset[i]} + sqrt(lost "
                       f"{lost[i]})): it must lie inside the dot (offset + sqrt(lost) <= {SPOT_MAX_REACH})"),
        )
        for bad, why in checks:
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise InputError(f"target damage of {ids[i]}: {why(i)}")
        return TargetDamage(kind.astype(np.int8), np.where(hurt, lost, 0.0), np.where(hurt, direction, 0.0),
                            np.where(kind == 2, offset, 0.0))


def _check_pose(T: Any, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"{name} must be a finite 4x4 transform, got shape {T.shape}")
    R = T[:3, :3]
    if np.max(np.abs(R.T @ R - np.eye(3))) > 1e-6 or np.linalg.det(R) < 0:
        raise InputError(f"{name} is not a rigid transform (rotation part not orthonormal)")
    return T.copy()


class World:
    """The true state of the simulated cell.

    Args:
        part: a ``planning.part.Part`` (``mesh`` in metres, ``targets`` with ``xyz``,
            ``normals``, ``kind``, ``code``, ``ids``; ``target_diameter_m``, ``coded_size_m``).
        base_from_part: (4, 4) nominal placement of the part, as the job states it.
        flange_from_cam: (4, 4) nominal hand-eye transform, as the job states it.
        intrinsics: the camera's true interior orientation (the renderer uses it).
        deviations: (n, 3) metres, true displacement of each target from CAD (part frame);
            zeros by default.
        true_base_from_part, true_flange_from_cam: (4, 4) the real values; default to the
            nominal ones.
        fixture: a mesh in the part frame (metres) that is in the cell but not in the part's CAD: a
            clamp or a support that hides dots from some directions. Rays are cast against the part
            and the fixture together.
        damage: worn coating of plain dots (:class:`TargetDamage`, one row per target); None: every dot intact.
            Held as the arrays ``damage_kind`` (n,) int8, ``damage_lost``, ``damage_dir_rad``, ``damage_offset``.
        seed: seed of the world's random streams (each device takes its own child stream).
    """

    def __init__(
        self,
        part: Any,
        base_from_part: np.ndarray,
        flange_from_cam: np.ndarray,
        intrinsics: Intrinsics,
        deviations: np.ndarray | None = None,
        *,
        true_base_from_part: np.ndarray | None = None,
        true_flange_from_cam: np.ndarray | None = None,
        seed: int = 0,
        fixture: Any = None,
        damage: TargetDamage | None = None,
    ) -> None:
        self.part = part
        self.fixture = fixture
        n = len(part.targets.xyz)
        self.base_from_part = _check_pose(base_from_part, "base_from_part")
        self.flange_from_cam = _check_pose(flange_from_cam, "flange_from_cam")
        self.true_base_from_part = _check_pose(
            self.base_from_part if true_base_from_part is None else true_base_from_part, "true_base_from_part"
        )
        self.true_flange_from_cam = _check_pose(
            self.flange_from_cam if true_flange_from_cam is None else true_flange_from_cam, "true_flange_from_cam"
        )
        self.intrinsics = intrinsics
        if deviations is None:
            deviations = np.zeros((n, 3))
        deviations = np.asarray(deviations, dtype=float)
        if deviations.shape != (n, 3) or not np.all(np.isfinite(deviations)):
            raise InputError(
                f"deviations must be a finite ({n}, 3) array in metres (one row per target), got {deviations.shape}"
            )
        self.deviations = deviations
        damage = (TargetDamage.none(n) if damage is None else damage).checked(part.targets.ids, part.targets.kind)
        self.damage_kind = damage.kind  # (n,) int8: 0 intact, 1 edge, 2 spot
        self.damage_lost = damage.lost  # (n,) share of the dot's area that does not reflect
        self.damage_dir_rad = damage.direction_rad  # (n,) from e1 towards e2
        self.damage_offset = damage.offset  # (n,) spot centre from the dot's, in dot radii
        self._seeds = np.random.SeedSequence(seed)
        self.lock = threading.RLock()
        self.joints_rad = np.zeros(6)
        self.base_from_flange = np.eye(4)
        self.light_fraction = 1.0  # illumination of the strobe, [0, 1]; a sim light may set it
        self._intersector = None
        self._embree = None  # (scene, centre, face normals, first vertices): Embree on the mesh moved to its centre
        self._scene = None

    # --- the part as it really is -----------------------------------------
    @property
    def true_xyz(self) -> np.ndarray:
        """(n, 3) true target positions in the part frame: CAD + deviations."""
        return np.asarray(self.part.targets.xyz, dtype=float) + self.deviations

    @property
    def normals(self) -> np.ndarray:
        """(n, 3) unit target normals in the part frame (the CAD ones)."""
        return np.asarray(self.part.targets.normals, dtype=float)

    def true_marker_corners(self) -> np.ndarray:
        """(n, 4, 3) true corners of every target's marker square (meaningful for coded ones)."""
        return marker_corners(self.true_xyz, self.normals, float(self.part.coded_size_m))

    def spawn_rng(self) -> np.random.Generator:
        """A fresh independent random stream derived from the world's seed."""
        return np.random.default_rng(self._seeds.spawn(1)[0])

    # --- robot state ----------------------------------------------------------
    def set_robot(self, joints_rad: np.ndarray, base_from_flange: np.ndarray) -> None:
        """Written by the robot: its actual joints (6,) and flange pose (4, 4)."""
        with self.lock:
            self.joints_rad = np.array(joints_rad, dtype=float)
            self.base_from_flange = np.array(base_from_flange, dtype=float)

    def true_part_from_cam(self) -> np.ndarray:
        """(4, 4) where the camera really is, in the part frame, at the current robot pose."""
        with self.lock:
            base_from_flange = self.base_from_flange.copy()
        return invert(self.true_base_from_part) @ base_from_flange @ self.true_flange_from_cam

    # --- ray casting ------------------------------------------------------------
    @property
    def scene_mesh(self):
        """What rays hit: the part, and the fixture when there is one (its faces after the part's)."""
        if self._scene is None:
            self._scene = self.part.mesh
            if self.fixture is not None and len(self.fixture.faces):
                import trimesh

                self._scene = trimesh.util.concatenate([self.part.mesh, self.fixture])
        return self._scene

    @property
    def intersector(self):
        """Ray-mesh intersector of the part and its fixture (Embree when available, else trimesh's NumPy one)."""
        if self._intersector is None:
            try:
                from trimesh.ray.ray_pyembree import RayMeshIntersector
            except ImportError:  # pragma: no cover - embreex is a dependency
                from trimesh.ray.ray_triangle import RayMeshIntersector
            self._intersector = RayMeshIntersector(self.scene_mesh)
        return self._intersector

    def first_hit(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First intersection of rays with the part's mesh (or the fixture).

        Embree finds the hit triangle (one call, no Python per ray; issue 21: trimesh's wrapper around
        it cost twice the ray casting), the distance is then recomputed in float64 from that
        triangle's plane (Embree works in float32).

        Args:
            origins: (m, 3) or (3,) ray origins, part frame.
            directions: (m, 3) ray directions (need not be unit).
        Returns:
            distance: (m,) distance along the unit ray to the first hit (``inf`` if none).
            tri: (m,) index of the hit triangle (-1 if none).
        """
        d = np.asarray(directions, dtype=float).reshape(-1, 3)
        d = d / np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
        o = np.broadcast_to(np.asarray(origins, dtype=float), d.shape)
        dist = np.full(len(d), np.inf)
        tri = np.full(len(d), -1, dtype=np.int64)
        if len(d) == 0:
            return dist, tri
        embree = self._embree_scene()
        if embree is None:  # pragma: no cover - embreex is a dependency
            loc, idx_ray, idx_tri = self.intersector.intersects_location(o, d, multiple_hits=False)
            if len(idx_ray):
                dist[idx_ray] = np.einsum("ij,ij->i", loc - o[idx_ray], d[idx_ray])
                tri[idx_ray] = idx_tri
            return dist, tri
        scene, centre, normals, v0 = embree
        o32 = (o - centre).astype(np.float32)
        res = scene.run(o32, d.astype(np.float32), output=1)
        prim = np.asarray(res["primID"], dtype=np.int64)
        hit = np.flatnonzero(prim >= 0)
        if len(hit):
            p, oh, dh = prim[hit], o[hit], d[hit]
            n = normals[p]
            dn = np.einsum("ij,ij->i", dh, n)
            grazing = np.abs(dn) < 1e-9  # the plane cannot give the distance: Embree's own
            with np.errstate(divide="ignore", invalid="ignore"):
                plane = np.einsum("ij,ij->i", v0[p] - oh, n) / dn
            dist[hit] = np.where(grazing, np.asarray(res["tfar"], dtype=float)[hit], plane)
            tri[hit] = p
        return dist, tri

    def _embree_scene(self):
        if self._embree is None:
            try:
                from embreex import rtcore_scene
                from embreex.mesh_construction import TriangleMesh
            except ImportError:  # pragma: no cover - embreex is a dependency
                return None
            mesh = self.scene_mesh
            centre = np.asarray(mesh.bounds, dtype=float).mean(axis=0)
            scene = rtcore_scene.EmbreeScene()
            TriangleMesh(scene=scene, vertices=np.ascontiguousarray(mesh.vertices - centre, dtype=np.float32),
                         indices=np.ascontiguousarray(mesh.faces, dtype=np.int32))
            faces = np.asarray(mesh.faces)
            self._embree = (scene, centre, np.ascontiguousarray(mesh.face_normals, dtype=float),
                            np.ascontiguousarray(np.asarray(mesh.vertices, dtype=float)[faces[:, 0]]))
        return self._embree
