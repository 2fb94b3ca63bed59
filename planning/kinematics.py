"""Robot kinematics of the cell: forward and inverse kinematics, joint limits, collisions.

The robot is a Universal Robots arm (UR5e or UR10e) described by a URDF generated from the
published DH parameters (``planning/robots``) and loaded with pinocchio (``pin``). Frames:

* ``base``: the controller's base frame (the robot stands on the table, z up).
* ``tool0`` / flange: the controller's TCP with zero TCP offset, so ``fk(q)`` is what a UR
  reports as its TCP pose when no TCP is set.

Inverse kinematics is the closed-form solution of the UR geometry (three parallel axes and
a spherical-free wrist with offsets), vectorised over poses: every pose has up to eight
branches, indexed ``b = 4 * shoulder + 2 * wrist + elbow`` (each flag 0 or 1). Solutions are
polished by Newton steps on the exact model until the flange error is below 1e-9 m.

Collisions are checked with coal (through pinocchio's GeometryModel) between the robot's
links, the camera/tool boxes on the flange, the part mesh, the table (a half-space below
``z = table_z``) and box obstacles. All world geometry is given in the base frame.
"""
from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import coal
import numpy as np
import pinocchio as pin

from calibration.errors import InputError
from planning.robots import JOINT_NAMES, LINK_NAMES, UR_PARAMS, URParams, urdf_path

if TYPE_CHECKING:
    import trimesh

__all__ = [
    "ToolBox",
    "BoxObstacle",
    "CollisionWorld",
    "CollisionReport",
    "IKSolutions",
    "RobotModel",
    "load_robot",
    "dh_fk",
    "geometric_jacobian",
    "refine_ik",
    "ur_ik",
    "DEFAULT_CAMERA",
    "N_BRANCHES",
]

N_BRANCHES = 8
IK_TOL_M = 1e-9  # flange position tolerance of IK solutions
IK_TOL_RAD = 1e-9  # flange orientation tolerance of IK solutions


def _translation(x: float, y: float, z: float) -> np.ndarray:
    t = np.eye(4)
    t[:3, 3] = (x, y, z)
    return t


@dataclass(frozen=True)
class ToolBox:
    """A box carried by the flange (camera body, tool, light).

    Attributes:
        name: label used in collision reports.
        size_m: (3,) edge lengths (x, y, z) in metres.
        flange_from_box: (4, 4) pose of the box centre in the flange (tool0) frame.
    """

    name: str = "camera"
    size_m: tuple[float, float, float] = (0.08, 0.08, 0.12)
    flange_from_box: np.ndarray = field(default_factory=lambda: _translation(0.0, 0.0, 0.06))

    def key(self) -> str:
        return f"{self.name}:{np.round(self.size_m, 9).tolist()}:{np.round(self.flange_from_box, 9).tolist()}"


#: The default camera: a 0.08 x 0.08 x 0.12 m body on the flange, along the tool axis.
DEFAULT_CAMERA = ToolBox()


@dataclass(frozen=True)
class BoxObstacle:
    """A box in the cell.

    Attributes:
        name: label used in error messages ("fixture", "wall").
        size_m: (3,) edge lengths in metres.
        base_from_box: (4, 4) pose of the box centre in the robot base frame.
    """

    name: str
    size_m: tuple[float, float, float]
    base_from_box: np.ndarray


@dataclass(frozen=True)
class CollisionWorld:
    """Everything in the cell that is not the robot, in the robot base frame.

    Attributes:
        part_mesh: the part (trimesh, metres, part frame) or None.
        base_from_part: (4, 4) where the part sits.
        table_z: height of the table top in the base frame (the robot stands on it, so
            usually 0.0); None for no table.
        obstacles: box obstacles.
        clearance_m: a configuration closer than this to anything counts as a collision.
    """

    part_mesh: trimesh.Trimesh | None = None
    base_from_part: np.ndarray = field(default_factory=lambda: np.eye(4))
    table_z: float | None = 0.0
    obstacles: tuple[BoxObstacle, ...] = ()
    clearance_m: float = 0.0

    @cached_property
    def key(self) -> str:
        """A hash of the contents (for caches; computed once, the world is immutable)."""
        h = hashlib.sha256()
        if self.part_mesh is not None:
            h.update(np.ascontiguousarray(self.part_mesh.vertices, dtype=np.float64).tobytes())
            h.update(np.ascontiguousarray(self.part_mesh.faces, dtype=np.int64).tobytes())
        h.update(np.asarray(self.base_from_part, dtype=np.float64).round(12).tobytes())
        h.update(repr(self.table_z).encode())
        for ob in self.obstacles:
            h.update(ob.name.encode())
            h.update(np.asarray(ob.size_m, dtype=np.float64).tobytes())
            h.update(np.asarray(ob.base_from_box, dtype=np.float64).round(12).tobytes())
        h.update(repr(float(self.clearance_m)).encode())
        return h.hexdigest()[:16]


@dataclass(frozen=True)
class CollisionReport:
    """Result of a collision check at one configuration; truthy when collision-free.

    Attributes:
        free: no pair is closer than the world's clearance.
        distance_m: smallest distance over all checked pairs (negative: penetration depth
            estimate); inf when nothing was checked. A part mesh of more than
            :data:`HULL_STAND_IN_FACES` faces is measured through its convex hull where that is
            more than :data:`PART_EXACT_WITHIN_M` beyond the clearance: there, a lower bound.
        pair: names of the closest pair ("wrist_3_link", "part").
    """

    free: bool
    distance_m: float
    pair: tuple[str, str]

    def __bool__(self) -> bool:
        return self.free


@dataclass(frozen=True)
class IKSolutions:
    """All analytic branches for m poses.

    Attributes:
        q: (m, 8, 6) joint angles (rad), each wrapped into the joint limits when possible;
            nan where the branch does not exist.
        exists: (m, 8) bool, the branch is a solution of the pose (within 1e-9 m / rad).
        within_limits: (m, 8) bool, exists and inside the joint limits.
        failure: (m,) str, why a pose has no branch within limits ("" when it has one).
    """

    q: np.ndarray
    exists: np.ndarray
    within_limits: np.ndarray
    failure: np.ndarray


# ----------------------------------------------------------------------------------------
# Pure kernels
# ----------------------------------------------------------------------------------------


def _dh_matrices(d: np.ndarray, a: np.ndarray, alpha: np.ndarray, q: np.ndarray) -> np.ndarray:
    """A_i = Rz(q) Tz(d) Tx(a) Rx(alpha).  q: (..., 6) -> (..., 6, 4, 4)."""
    ct, st = np.cos(q), np.sin(q)
    ca, sa = np.cos(alpha), np.sin(alpha)
    out = np.zeros(q.shape + (4, 4))
    out[..., 0, 0] = ct
    out[..., 0, 1] = -st * ca
    out[..., 0, 2] = st * sa
    out[..., 0, 3] = a * ct
    out[..., 1, 0] = st
    out[..., 1, 1] = ct * ca
    out[..., 1, 2] = -ct * sa
    out[..., 1, 3] = a * st
    out[..., 2, 1] = sa
    out[..., 2, 2] = ca
    out[..., 2, 3] = d
    out[..., 3, 3] = 1.0
    return out


def dh_fk(params: URParams, q: np.ndarray, all_frames: bool = False) -> np.ndarray:
    """Forward kinematics of the DH model.

    Args:
        params: the arm's DH parameters.
        q: (..., 6) joint angles (rad).
        all_frames: return every DH frame instead of only the flange.
    Returns:
        (..., 4, 4) base_from_flange, or (..., 7, 4, 4) base_from_frame_i for i = 0..6.
    """
    q = np.asarray(q, dtype=float)
    A = _dh_matrices(np.asarray(params.d), np.asarray(params.a), np.asarray(params.alpha), q)
    frames = [np.broadcast_to(np.eye(4), q.shape[:-1] + (4, 4))]
    for i in range(6):
        frames.append(frames[-1] @ A[..., i, :, :])
    if all_frames:
        return np.stack(frames, axis=-3)
    return frames[-1]


def _inv_dh(params: URParams, i: int, qi: np.ndarray) -> np.ndarray:
    """inv(A_i(qi)) for qi: (m,) -> (m, 4, 4)."""
    A = _dh_matrices(params.d[i], params.a[i], params.alpha[i], qi)
    R = A[..., :3, :3]
    out = np.zeros_like(A)
    out[..., :3, :3] = np.swapaxes(R, -1, -2)
    out[..., :3, 3] = -np.einsum("...ji,...j->...i", R, A[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _wrap(x: np.ndarray) -> np.ndarray:
    """Angles into (-pi, pi]."""
    return np.pi - np.mod(np.pi - x, 2 * np.pi)


def ur_ik(params: URParams, base_from_flange: np.ndarray, q6_ref: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form inverse kinematics of a UR arm, all eight branches, vectorised.

    Args:
        params: DH parameters.
        base_from_flange: (m, 4, 4) target poses.
        q6_ref: (m,) or scalar, wrist 3 angle used where the wrist is singular (q5 = 0).
    Returns:
        q: (m, 8, 6) joint angles wrapped into (-pi, pi], nan where the branch has no
            real solution; branch b = 4 * shoulder + 2 * wrist + elbow.
        code: (m, 8) int: 0 solved, 1 wrist centre inside the cylinder of radius d4 about
            the base axis, 2 wrist centre out of the arm's planar reach.
    """
    T = np.asarray(base_from_flange, dtype=float).reshape(-1, 4, 4)
    m = T.shape[0]
    d4, d6 = params.d[3], params.d[5]
    a2, a3 = params.a[1], params.a[2]
    q = np.full((m, 2, 2, 2, 6), np.nan)
    code = np.zeros((m, 2, 2, 2), dtype=int)

    p5 = T[:, :3, 3] - d6 * T[:, :3, 2]  # origin of DH frame 5
    r = np.hypot(p5[:, 0], p5[:, 1])
    psi = np.arctan2(p5[:, 1], p5[:, 0])
    ratio = d4 / np.maximum(r, 1e-300)
    near_axis = ratio > 1.0
    code[near_axis] = 1
    phi = np.arcsin(np.clip(ratio, -1.0, 1.0))
    q6_ref = np.broadcast_to(np.asarray(q6_ref, dtype=float), (m,))
    for s in range(2):
        q1 = psi + phi if s == 0 else psi + np.pi - phi
        T16 = _inv_dh(params, 0, q1) @ T
        c5 = np.clip(T16[:, 2, 2], -1.0, 1.0)
        for w in range(2):
            q5 = np.arccos(c5) if w == 0 else -np.arccos(c5)
            s5 = np.sin(q5)
            singular = np.abs(s5) < 1e-10
            sgn = np.where(s5 >= 0, 1.0, -1.0)
            q6 = np.where(singular, q6_ref, np.arctan2(-T16[:, 2, 1] * sgn, T16[:, 2, 0] * sgn))
            T14 = T16 @ _inv_dh(params, 5, q6)
            T14 = T14 @ _inv_dh(params, 4, q5)
            x, y = T14[:, 0, 3], T14[:, 1, 3]
            c3 = (x * x + y * y - a2 * a2 - a3 * a3) / (2 * a2 * a3)
            too_far = np.abs(c3) > 1.0 + 1e-12
            q234 = np.arctan2(T14[:, 1, 0], T14[:, 0, 0])
            for e in range(2):
                q3 = np.arccos(np.clip(c3, -1.0, 1.0)) * (1.0 if e == 0 else -1.0)
                q2 = np.arctan2(y, x) - np.arctan2(a3 * np.sin(q3), a2 + a3 * np.cos(q3))
                q4 = q234 - q2 - q3
                sol = np.stack([q1, q2, q3, q4, q5, q6], axis=-1)
                bad = near_axis | too_far
                sol[bad] = np.nan
                q[:, s, w, e] = _wrap(sol)
                code[:, s, w, e] = np.where(near_axis, 1, np.where(too_far, 2, 0))
    return q.reshape(m, N_BRANCHES, 6), code.reshape(m, N_BRANCHES)


def _pose_error(T: np.ndarray, T_goal: np.ndarray) -> np.ndarray:
    """6-vector error (translation, rotation vector) in the base frame.  (..., 6)."""
    dp = T_goal[..., :3, 3] - T[..., :3, 3]
    R_err = T_goal[..., :3, :3] @ np.swapaxes(T[..., :3, :3], -1, -2)
    # small-angle-robust log map
    cos = np.clip((np.trace(R_err, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.arccos(cos)
    vee = np.stack([R_err[..., 2, 1] - R_err[..., 1, 2], R_err[..., 0, 2] - R_err[..., 2, 0], R_err[..., 1, 0] - R_err[..., 0, 1]], -1)
    s = np.sin(ang)
    factor = np.where(s > 1e-9, ang / (2 * np.maximum(s, 1e-300)), 0.5)
    return np.concatenate([dp, vee * factor[..., None]], axis=-1)


def geometric_jacobian(frames: np.ndarray) -> np.ndarray:
    """Base-frame Jacobian (linear over angular) from DH frames (..., 7, 4, 4) -> (..., 6, 6)."""
    z = frames[..., :6, :3, 2]
    o = frames[..., :6, :3, 3]
    pe = frames[..., 6, :3, 3]
    Jv = np.cross(z, pe[..., None, :] - o)
    return np.concatenate([np.swapaxes(Jv, -1, -2), np.swapaxes(z, -1, -2)], axis=-2)


def refine_ik(params: URParams, q: np.ndarray, base_from_flange: np.ndarray, iterations: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Newton-polish IK solutions on the exact model.

    Args:
        q: (m, k, 6) solutions (nan rows are left alone).
        base_from_flange: (m, 4, 4) goals.
    Returns:
        q: (m, k, 6) polished, err_m: (m, k) position error, err_rad: (m, k) rotation error.
    """
    q = q.copy()
    goal = np.broadcast_to(base_from_flange[:, None], q.shape[:2] + (4, 4))
    finite = np.all(np.isfinite(q), axis=-1)
    err = np.full(q.shape[:2] + (6,), np.inf)
    for it in range(iterations + 1):
        frames = dh_fk(params, np.where(finite[..., None], q, 0.0), all_frames=True)
        err = _pose_error(frames[..., 6, :, :], goal)
        todo = finite & ((np.linalg.norm(err[..., :3], axis=-1) > 0.1 * IK_TOL_M) | (np.linalg.norm(err[..., 3:], axis=-1) > 0.1 * IK_TOL_RAD))
        if it == iterations or not np.any(todo):
            break
        J = geometric_jacobian(frames[todo])
        lam = 1e-12
        JT = np.swapaxes(J, -1, -2)
        step = np.linalg.solve(JT @ J + lam * np.eye(6), (JT @ err[todo][..., None]))[..., 0]
        q[todo] = q[todo] + step
    err_m = np.where(finite, np.linalg.norm(err[..., :3], axis=-1), np.inf)
    err_rad = np.where(finite, np.linalg.norm(err[..., 3:], axis=-1), np.inf)
    return q, err_m, err_rad


# ----------------------------------------------------------------------------------------
# The robot
# ----------------------------------------------------------------------------------------


def _se3(T: np.ndarray) -> pin.SE3:
    T = np.asarray(T, dtype=float)
    return pin.SE3(T[:3, :3].copy(), T[:3, 3].copy())


def _mesh_bvh(mesh: trimesh.Trimesh) -> coal.BVHModelOBBRSS:
    bvh = coal.BVHModelOBBRSS()
    verts = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    bvh.beginModel(len(faces), len(verts))
    bvh.addVertices(verts)
    bvh.addTriangles(faces)
    bvh.endModel()
    return bvh


mesh_bvh = _mesh_bvh  # the part's BVH for a check of the part itself against the cell (cell.setup)


@dataclass
class _Scene:
    """A pinocchio GeometryModel of robot + world, with its collision pairs."""

    gmodel: pin.GeometryModel
    gdata: pin.GeometryData
    pair_names: list[tuple[str, str]]
    pool: pin.GeometryPool | None = None
    margin_pools: dict = field(default_factory=dict)  # security margin (m) -> GeometryPool
    # the part's convex hull against the robot (a model of its own: its pairs must never count as collisions),
    # and for each of its pairs the pair of the part's mesh it stands for (:meth:`RobotModel.check_collision`)
    hull_gmodel: pin.GeometryModel | None = None
    hull_gdata: pin.GeometryData | None = None
    hull_pairs: tuple = ()


#: a part mesh with more faces than this gets a convex-hull stand-in for its distances (a far mesh costs tens of ms)
HULL_STAND_IN_FACES = 2000
#: the part's exact distance is computed when its hull is nearer than this beyond the clearance
PART_EXACT_WITHIN_M = 0.05


class RobotModel:
    """A UR arm: kinematics (DH / pin), joint limits, tool boxes and collision checks.

    Attributes:
        name: "ur5e" | "ur10e".
        params: the DH parameters it was built from.
        model: the pinocchio model loaded from the URDF.
        lower, upper: (6,) joint limits (rad).
        max_velocity: (6,) joint speed limits (rad/s).
        tools: boxes carried by the flange.
    """

    #: link pairs that cannot touch by design (adjacent, or kept apart by the arm's offsets)
    _SELF_EXCLUDED = {
        ("base", "shoulder_link"), ("base", "upper_arm_link"), ("shoulder_link", "upper_arm_link"),
        ("upper_arm_link", "forearm_link"), ("forearm_link", "wrist_1_link"), ("wrist_1_link", "wrist_2_link"),
        ("wrist_2_link", "wrist_3_link"), ("wrist_1_link", "wrist_3_link"),
    }
    #: links fixed above the table (the robot stands on it)
    _ON_TABLE = {"base", "shoulder_link"}
    #: links a flange-mounted box is attached to or flush with
    _TOOL_EXCLUDED = {"wrist_2_link", "wrist_3_link"}

    def __init__(self, params: URParams, urdf: str, tools: Sequence[ToolBox], lower: np.ndarray, upper: np.ndarray):
        self.name = params.name
        self.params = params
        self.urdf = urdf
        self.model = pin.buildModelFromXML(urdf)
        self.data = self.model.createData()
        if self.model.nq != 6:
            raise InputError(f"robot {self.name}: URDF has {self.model.nq} joints, expected 6")
        self.flange_frame = self.model.getFrameId("tool0")
        self.lower = np.asarray(lower, dtype=float).copy()
        self.upper = np.asarray(upper, dtype=float).copy()
        self.max_velocity = np.asarray(self.model.velocityLimit, dtype=float).copy()
        self.tools = tuple(tools)
        # joint placements and flange placement, for vectorised FK without DH
        self._placements = np.stack([self.model.jointPlacements[i].homogeneous for i in range(1, 7)])
        self._flange_placement = self.model.frames[self.flange_frame].placement.homogeneous
        self._robot_geom = pin.buildGeomFromUrdfString(self.model, urdf, pin.GeometryType.COLLISION)
        self._scenes: dict[str, _Scene] = {}

    # -- kinematics --------------------------------------------------------------------

    def fk(self, q: np.ndarray) -> np.ndarray:
        """base_from_flange (4, 4) at joints q (6,) (pinocchio on the URDF)."""
        pin.framesForwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        return self.data.oMf[self.flange_frame].homogeneous.copy()

    def fk_many(self, q: np.ndarray) -> np.ndarray:
        """base_from_flange (m, 4, 4) at joints q (m, 6), vectorised on the URDF's placements."""
        q = np.asarray(q, dtype=float)
        c, s = np.cos(q), np.sin(q)
        T = np.broadcast_to(np.eye(4), q.shape[:-1] + (4, 4))
        for i in range(6):
            Rz = np.zeros(q.shape[:-1] + (4, 4))
            Rz[..., 0, 0] = c[..., i]
            Rz[..., 0, 1] = -s[..., i]
            Rz[..., 1, 0] = s[..., i]
            Rz[..., 1, 1] = c[..., i]
            Rz[..., 2, 2] = 1.0
            Rz[..., 3, 3] = 1.0
            T = T @ self._placements[i] @ Rz
        return T @ self._flange_placement

    def within_limits(self, q: np.ndarray) -> np.ndarray:
        """(...,) bool: q (..., 6) inside the joint limits."""
        q = np.asarray(q, dtype=float)
        return np.all((q >= self.lower - 1e-12) & (q <= self.upper + 1e-12), axis=-1)

    def joint_margin(self, q: np.ndarray) -> np.ndarray:
        """(...,) smallest distance (rad) of q (..., 6) to a joint limit (negative: outside)."""
        q = np.asarray(q, dtype=float)
        return np.min(np.minimum(q - self.lower, self.upper - q), axis=-1)

    def nearest_equivalent(self, q: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
        """The 2*pi-shift of q (..., 6) nearest to q_ref (..., 6) that stays inside the limits."""
        q = np.asarray(q, dtype=float)
        best = q.copy()
        best_d = np.full(q.shape, np.inf)
        for k in (-2, -1, 0, 1, 2):
            cand = q + 2 * np.pi * k
            ok = (cand >= self.lower - 1e-12) & (cand <= self.upper + 1e-12)
            dist = np.where(ok, np.abs(cand - q_ref), np.inf)
            better = dist < best_d
            best = np.where(better, cand, best)
            best_d = np.where(better, dist, best_d)
        return best

    def _into_limits(self, q: np.ndarray) -> np.ndarray:
        """Shift each angle by 2*pi multiples into the limits when possible (prefer |q| small)."""
        return self.nearest_equivalent(q, np.zeros_like(q))

    def ik_many(self, base_from_flange: np.ndarray, q_ref: np.ndarray | None = None) -> IKSolutions:
        """All IK branches of m poses (vectorised).

        Args:
            base_from_flange: (m, 4, 4) flange targets in the base frame.
            q_ref: (m, 6) or (6,) reference joints: solutions are shifted by 2*pi to the
                equivalent nearest to it, and it fixes q6 at wrist singularities.
        Returns:
            IKSolutions with q (m, 8, 6).
        """
        T = np.asarray(base_from_flange, dtype=float).reshape(-1, 4, 4)
        m = T.shape[0]
        ref = None if q_ref is None else np.broadcast_to(np.asarray(q_ref, dtype=float), (m, 6))
        q, code = ur_ik(self.params, T, 0.0 if ref is None else ref[:, 5])
        q, err_m, err_rad = refine_ik(self.params, q, T)
        exists = (err_m <= IK_TOL_M) & (err_rad <= IK_TOL_RAD)
        q = np.where(exists[..., None], q, np.nan)
        q = _wrap(q)
        if ref is None:
            q = self._into_limits(q)
        else:
            q = self.nearest_equivalent(q, ref[:, None, :])
        within = exists & self.within_limits(np.where(exists[..., None], q, 0.0))
        failure = self._failure_reasons(T, code, exists, within)
        return IKSolutions(q=q, exists=exists, within_limits=within, failure=failure)

    def ik(self, base_from_flange: np.ndarray, q_ref: np.ndarray | None = None) -> np.ndarray:
        """(k, 6) every IK branch of one pose (4, 4) inside the joint limits; (0, 6) if none.

        Rows are in branch order (b = 4 * shoulder + 2 * wrist + elbow), duplicates removed.
        With q_ref (6,), each row is the 2*pi-equivalent nearest to q_ref.
        """
        sol = self.ik_many(np.asarray(base_from_flange)[None], q_ref=q_ref)
        rows = sol.q[0][sol.within_limits[0]]
        keep: list[np.ndarray] = []
        for row in rows:
            if not any(np.max(np.abs(_wrap(row - k))) < 1e-7 for k in keep):
                keep.append(row)
        return np.array(keep).reshape(-1, 6)

    def _failure_reasons(self, T: np.ndarray, code: np.ndarray, exists: np.ndarray, within: np.ndarray) -> np.ndarray:
        """(m,) str: why each pose has no branch within limits ("" if it has one)."""
        m = T.shape[0]
        out = np.full(m, "", dtype=object)
        p = self.params
        shoulder = np.array([0.0, 0.0, p.d[0]])
        dist = np.linalg.norm(T[:, :3, 3] - shoulder, axis=1)
        p5 = T[:, :3, 3] - p.d[5] * T[:, :3, 2]
        r5 = np.hypot(p5[:, 0], p5[:, 1])
        planar = abs(p.a[1]) + abs(p.a[2])
        for i in np.flatnonzero(~np.any(within, axis=1)):
            if np.any(exists[i]):
                out[i] = "joint limits: every IK branch is outside the joint limits"
            elif np.all(code[i] == 1):
                out[i] = (
                    f"too close to the base axis: wrist {r5[i]:.3f} m from it < {p.d[3]:.3f} m"
                )
            elif dist[i] > p.reach_m:
                out[i] = f"out of reach {dist[i]:.3f} m > {p.reach_m:.3f} m from the shoulder"
            else:
                out[i] = (
                    f"out of reach for this orientation: {dist[i]:.3f} m from the shoulder, "
                    f"the upper arm and forearm span {planar:.3f} m"
                )
        return out

    # -- collisions --------------------------------------------------------------------

    def _scene(self, world: CollisionWorld) -> _Scene:
        key = world.key
        scene = self._scenes.get(key)
        if scene is not None:
            return scene
        gm = pin.GeometryModel()
        link_of: dict[int, str] = {}
        for go in self._robot_geom.geometryObjects:
            gid = gm.addGeometryObject(pin.GeometryObject(go))
            link_of[gid] = go.name.rsplit("_", 1)[0]
        wrist3_joint = self.model.getJointId(JOINT_NAMES[5])
        joint_from_flange = self._flange_placement
        tool_ids = []
        for tool in self.tools:
            geom = coal.Box(*np.asarray(tool.size_m, dtype=float))
            go = pin.GeometryObject(tool.name, wrist3_joint, _se3(joint_from_flange @ tool.flange_from_box), geom)
            tool_ids.append(gm.addGeometryObject(go))
            link_of[tool_ids[-1]] = tool.name
        world_ids: list[int] = []
        table_id = None
        if world.table_z is not None:
            go = pin.GeometryObject("table", 0, pin.SE3.Identity(), coal.Halfspace(np.array([0.0, 0.0, 1.0]), float(world.table_z)))
            table_id = gm.addGeometryObject(go)
            link_of[table_id] = "table"
        if world.part_mesh is not None:
            go = pin.GeometryObject("part", 0, _se3(world.base_from_part), _mesh_bvh(world.part_mesh))
            world_ids.append(gm.addGeometryObject(go))
            link_of[world_ids[-1]] = "part"
        for ob in world.obstacles:
            go = pin.GeometryObject(ob.name, 0, _se3(ob.base_from_box), coal.Box(*np.asarray(ob.size_m, dtype=float)))
            world_ids.append(gm.addGeometryObject(go))
            link_of[world_ids[-1]] = ob.name
        robot_ids = [i for i in link_of if link_of[i] in LINK_NAMES] + tool_ids
        pairs: list[tuple[int, int]] = []
        for ii, i in enumerate(robot_ids):
            for j in robot_ids[ii + 1:]:
                a, b = link_of[i], link_of[j]
                if a == b or (a, b) in self._SELF_EXCLUDED or (b, a) in self._SELF_EXCLUDED:
                    continue
                if (i in tool_ids and b in self._TOOL_EXCLUDED) or (j in tool_ids and a in self._TOOL_EXCLUDED):
                    continue
                if i in tool_ids and j in tool_ids:
                    continue
                pairs.append((i, j))
            if table_id is not None and link_of[i] not in self._ON_TABLE:
                pairs.append((i, table_id))
            for w in world_ids:
                pairs.append((i, w))
        names = []
        for i, j in pairs:
            gm.addCollisionPair(pin.CollisionPair(i, j))
            names.append((link_of[i], link_of[j]))
        gd = pin.GeometryData(gm)
        for req in gd.collisionRequests:
            req.security_margin = float(world.clearance_m)
        scene = _Scene(gmodel=gm, gdata=gd, pair_names=names)
        if world.part_mesh is not None and len(world.part_mesh.faces) > HULL_STAND_IN_FACES:
            # the hull contains the part: its distance is a lower bound of the part's, cheap at any range
            hgm = pin.GeometryModel()
            hull_id = hgm.addGeometryObject(pin.GeometryObject("part_hull", 0, _se3(world.base_from_part),
                                                               _mesh_bvh(world.part_mesh.convex_hull)))
            own = {}
            for gid in robot_ids:
                own[gid] = hgm.addGeometryObject(pin.GeometryObject(gm.geometryObjects[gid]))
            hp = []
            for k, (i, j) in enumerate(pairs):
                if j == world_ids[0]:
                    hgm.addCollisionPair(pin.CollisionPair(own[i], hull_id))
                    hp.append(k)
            scene.hull_gmodel, scene.hull_gdata, scene.hull_pairs = hgm, pin.GeometryData(hgm), tuple(hp)
        self._scenes[key] = scene
        return scene

    def check_collision(self, q: np.ndarray, world: CollisionWorld) -> CollisionReport:
        """Distances between every checked pair at q (6,); see CollisionReport."""
        scene = self._scene(world)
        if not scene.pair_names:
            return CollisionReport(True, float("inf"), ("", ""))
        q = np.asarray(q, dtype=float)
        if scene.hull_gmodel is None:
            pin.computeDistances(self.model, self.data, scene.gmodel, scene.gdata, q)
            d = np.array([r.min_distance for r in scene.gdata.distanceResults])
        else:
            d = self._distances_with_hull(q, scene, world.clearance_m)
        # coal's distance between a shape and a mesh is only a lower bound once they
        # intersect: confirm with the collision test, which is exact
        k = int(np.argmin(d))
        collided = bool(np.min(d) < world.clearance_m)
        if not collided:
            collided = pin.computeCollisions(scene.gmodel, scene.gdata, True)
            if collided:
                hits = [i for i, r in enumerate(scene.gdata.collisionResults) if r.isCollision()]
                k = hits[0]
                d[k] = min(d[k], 0.0)
        return CollisionReport(free=not collided, distance_m=float(d[k]), pair=scene.pair_names[k])

    def _distances_with_hull(self, q: np.ndarray, scene: _Scene, clearance_m: float) -> np.ndarray:
        """Every pair's distance at ``q``, the part's through its convex hull where that is farther than
        :data:`PART_EXACT_WITHIN_M` beyond the clearance: a lower bound there (the hull contains the part), which
        a conservative advancement may step by; nearer, the part's mesh itself."""
        gm, gd = scene.gmodel, scene.gdata
        pin.updateGeometryPlacements(self.model, self.data, gm, gd, q)
        pin.updateGeometryPlacements(self.model, self.data, scene.hull_gmodel, scene.hull_gdata, q)
        part = set(scene.hull_pairs)
        d = np.array([np.inf if k in part else pin.computeDistance(gm, gd, k).min_distance
                      for k in range(len(scene.pair_names))])
        for hk, k in enumerate(scene.hull_pairs):
            dh = pin.computeDistance(scene.hull_gmodel, scene.hull_gdata, hk).min_distance
            d[k] = dh if dh >= clearance_m + PART_EXACT_WITHIN_M else pin.computeDistance(gm, gd, k).min_distance
        return d

    def collision_free(self, q: np.ndarray, world: CollisionWorld) -> CollisionReport:
        """Collision check at q (6,): a CollisionReport, truthy when free (distance in .distance_m)."""
        return self.check_collision(q, world)

    def collision_free_many(self, q: np.ndarray, world: CollisionWorld, n_threads: int = 2,
                            margin_m: float | None = None) -> np.ndarray:
        """(m,) bool: configurations q (m, 6) free of collision (C++ loop over a pool, in parallel).

        ``margin_m``: the distance every pair must keep (default: the world's clearance); a larger one
        certifies a neighbourhood of each configuration (planning.execution's batched move check).
        """
        q = np.asarray(q, dtype=float).reshape(-1, 6)
        scene = self._scene(world)
        if not scene.pair_names or len(q) == 0:
            return np.ones(len(q), dtype=bool)
        margin = float(world.clearance_m if margin_m is None else margin_m)
        pool = scene.margin_pools.get(margin)
        if pool is None or pool.size() < n_threads:
            if pool is None:
                pool = pin.GeometryPool(self.model, scene.gmodel, max(1, n_threads))
            else:
                pool.resize(n_threads)
            for gd in pool.getGeometryDatas():
                for req in gd.collisionRequests:
                    req.security_margin = margin
            scene.margin_pools[margin] = pool
        hit = pin.computeCollisionsInParallel(max(1, n_threads), pool, np.asfortranarray(q.T), True)
        return ~np.asarray(hit, dtype=bool)


def load_robot(
    name: str,
    tool: ToolBox | Sequence[ToolBox] | None = DEFAULT_CAMERA,
    elbow_limit_rad: float | None = np.pi,
    lower: Sequence[float] | None = None,
    upper: Sequence[float] | None = None,
) -> RobotModel:
    """Load a UR arm from its packaged URDF.

    Args:
        name: "ur5e" | "ur10e".
        tool: the box(es) on the flange (default: a 0.08 x 0.08 x 0.12 m camera); None for none.
        elbow_limit_rad: symmetric elbow limit (pi is the usual safe cell setting, keeping
            the forearm out of the upper arm); None keeps the hardware's +-2 pi.
        lower, upper: (6,) joint limits (rad) replacing the URDF's (+-2 pi) entirely.
    Raises:
        InputError: unknown robot or inconsistent limits.
    """
    key = name.lower()
    if key not in UR_PARAMS:
        raise InputError(f"unknown robot model {name!r}: use one of {sorted(UR_PARAMS)}")
    urdf = urdf_path(key).read_text()
    model = pin.buildModelFromXML(urdf)
    lo = np.array(model.lowerPositionLimit if lower is None else lower, dtype=float)
    hi = np.array(model.upperPositionLimit if upper is None else upper, dtype=float)
    if elbow_limit_rad is not None and lower is None and upper is None:
        lo[2], hi[2] = -abs(elbow_limit_rad), abs(elbow_limit_rad)
    if lo.shape != (6,) or hi.shape != (6,) or np.any(lo >= hi):
        raise InputError(f"robot {name}: joint limits must be 6 pairs with lower < upper, got {lo} / {hi}")
    if tool is None:
        tools: tuple[ToolBox, ...] = ()
    elif isinstance(tool, ToolBox):
        tools = (tool,)
    else:
        tools = tuple(tool)
    return RobotModel(UR_PARAMS[key], urdf, tools, lo, hi)
