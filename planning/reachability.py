"""Reachability of candidate camera stations: IK branches, joint limits, collisions.

For each station ``part_from_cam`` the flange target is
``base_from_flange = base_from_part @ part_from_cam @ inv(flange_from_cam)``. A station is
reachable when at least one analytic IK branch lies inside the joint limits (with a
required margin) and is collision-free in the cell. The *best* branch is the collision-free
one with the highest dexterity score (joint-limit margin and Jacobian conditioning); its
joints, margin to the joint limits and distance to the nearest collision are stored.

Work is vectorised: IK for all stations at once, then collision checks in rounds (best
branch of every unresolved station first, in pinocchio's parallel C++ loop), so a typical
station costs one collision query. Results are cached on disk like the visibility
database, keyed by a hash of every input.
"""
from __future__ import annotations

import hashlib
import json
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from calibration.errors import InputError
from planning.cache import load_arrays, save_arrays
from planning.kinematics import N_BRANCHES, CollisionWorld, RobotModel, dh_fk, geometric_jacobian

__all__ = [
    "ReachabilityOptions",
    "ReachabilityResult",
    "ReachabilityDB",
    "reachability_mask",
    "flange_targets",
    "branch_scores",
]

_CACHE_VERSION = "reach-1"


@dataclass(frozen=True)
class ReachabilityOptions:
    """How reachability is judged.

    Attributes:
        min_joint_margin_rad: a branch closer than this to a joint limit is not used.
        check_collisions: check the chosen branch against the cell (robot, tool, part,
            table, obstacles; the world's clearance counts as contact).
        compute_distances: also measure the distance to the nearest collision of the
            chosen branch (one distance query per reachable station).
        n_threads: threads for the batched collision checks.
        margin_cap_rad: joint margins above this do not improve a branch's score.
    """

    min_joint_margin_rad: float = 0.0
    check_collisions: bool = True
    compute_distances: bool = True
    n_threads: int = 2
    margin_cap_rad: float = 0.5


@dataclass(frozen=True)
class ReachabilityResult:
    """Reachability of m stations.

    Attributes:
        reachable: (m,) bool.
        joints: (m, 6) the best branch (rad), nan where unreachable.
        branch: (m,) int index of the best branch (b = 4*shoulder + 2*wrist + elbow), -1 if none.
        joint_margin_rad: (m,) smallest distance of the best branch to a joint limit (nan if none).
        collision_margin_m: (m,) distance of the best branch to the nearest collision (nan
            when not computed or unreachable; inf with nothing to collide with).
        reason: (m,) str, why a station is unreachable ("" when reachable).
        branches_ok: (m, 8) bool, branches inside the joint limits with the required margin
            (only the chosen one, and those tried before it, were checked for collisions).
        base_from_flange: (m, 4, 4) flange targets.
    """

    reachable: np.ndarray
    joints: np.ndarray
    branch: np.ndarray
    joint_margin_rad: np.ndarray
    collision_margin_m: np.ndarray
    reason: np.ndarray
    branches_ok: np.ndarray
    base_from_flange: np.ndarray

    def summary(self) -> str:
        """One line: how many stations are reachable and the commonest reasons why not."""
        m = len(self.reachable)
        n = int(self.reachable.sum())
        kinds: dict[str, int] = {}
        for r in self.reason[~self.reachable]:
            k = re.match(r"[a-z ]*", str(r)).group(0).strip()
            kinds[k] = kinds.get(k, 0) + 1
        tail = ", ".join(f"{v} {k}" for k, v in sorted(kinds.items(), key=lambda kv: -kv[1]))
        return f"{n}/{m} stations reachable" + (f" ({tail})" if tail else "")


def flange_targets(base_from_part: np.ndarray, part_from_cam: np.ndarray, flange_from_cam: np.ndarray) -> np.ndarray:
    """base_from_flange (m, 4, 4) = base_from_part @ part_from_cam (m, 4, 4) @ inv(flange_from_cam)."""
    ffc = np.asarray(flange_from_cam, dtype=float)
    cam_from_flange = np.eye(4)
    cam_from_flange[:3, :3] = ffc[:3, :3].T
    cam_from_flange[:3, 3] = -ffc[:3, :3].T @ ffc[:3, 3]
    return np.asarray(base_from_part, dtype=float) @ np.asarray(part_from_cam, dtype=float) @ cam_from_flange


def branch_scores(robot: RobotModel, q: np.ndarray, margin_cap_rad: float = 0.5) -> np.ndarray:
    """Dexterity score of joint vectors q (..., 6); higher is better, -inf for nan rows.

    score = min(joint margin, cap) / cap + inverse condition number of the Jacobian
    (angular rows scaled by half the reach, so both terms lie in [0, 1]).
    """
    q = np.asarray(q, dtype=float)
    finite = np.all(np.isfinite(q), axis=-1)
    q0 = np.where(finite[..., None], q, 0.0)
    J = geometric_jacobian(dh_fk(robot.params, q0, all_frames=True))
    J = J.copy()
    J[..., 3:, :] *= 0.5 * robot.params.reach_m
    s = np.linalg.svd(J, compute_uv=False)
    inv_cond = s[..., -1] / np.maximum(s[..., 0], 1e-300)
    margin = np.clip(robot.joint_margin(q0), 0.0, margin_cap_rad) / margin_cap_rad
    return np.where(finite, margin + inv_cond, -np.inf)


def reachability_mask(
    robot: RobotModel,
    base_from_part: np.ndarray,
    flange_from_cam: np.ndarray,
    part_from_cam: np.ndarray,
    world: CollisionWorld | None = None,
    options: ReachabilityOptions | None = None,
) -> ReachabilityResult:
    """Which stations the robot can reach, and with which joints.

    Args:
        robot: the arm (with its tool boxes).
        base_from_part: (4, 4) where the part sits in the base frame.
        flange_from_cam: (4, 4) hand-eye transform.
        part_from_cam: (m, 4, 4) candidate stations.
        world: the cell's collision world (part, table, obstacles); None: no collision checks.
        options: see ReachabilityOptions.
    Returns:
        ReachabilityResult aligned with part_from_cam.
    """
    opt = options or ReachabilityOptions()
    pfc = np.asarray(part_from_cam, dtype=float)
    if pfc.ndim != 3 or pfc.shape[1:] != (4, 4):
        raise InputError(f"part_from_cam must be (m, 4, 4), got {pfc.shape}")
    m = len(pfc)
    bff = flange_targets(base_from_part, pfc, flange_from_cam)
    sol = robot.ik_many(bff)
    margin = robot.joint_margin(np.where(sol.exists[..., None], sol.q, 0.0))
    ok = sol.within_limits & (margin >= opt.min_joint_margin_rad)
    score = np.where(ok, branch_scores(robot, sol.q, opt.margin_cap_rad), -np.inf)
    order = np.argsort(-score, axis=1, kind="stable")  # (m, 8) best first
    n_ok = ok.sum(axis=1)

    reason = np.array(sol.failure, dtype=object)
    for i in np.flatnonzero((n_ok == 0) & sol.within_limits.any(axis=1)):
        reason[i] = (
            f"joint limits: best margin {np.max(np.where(sol.within_limits[i], margin[i], -np.inf)):.3f} rad "
            f"< required {opt.min_joint_margin_rad:.3f} rad"
        )
    chosen = np.full(m, -1)
    check = opt.check_collisions and world is not None
    if not check:
        has = n_ok > 0
        chosen[has] = order[has, 0]
    else:
        unresolved = n_ok > 0
        for rank in range(N_BRANCHES):
            idx = np.flatnonzero(unresolved & (n_ok > rank))
            if len(idx) == 0:
                break
            b = order[idx, rank]
            free = robot.collision_free_many(sol.q[idx, b], world, n_threads=opt.n_threads)
            chosen[idx[free]] = b[free]
            unresolved[idx[free]] = False
        for i in np.flatnonzero((n_ok > 0) & (chosen < 0)):
            rep = robot.check_collision(sol.q[i, order[i, 0]], world)
            reason[i] = (
                f"collision: {rep.pair[0]} vs {rep.pair[1]} ({rep.distance_m * 1000:.0f} mm) in every one of "
                f"{n_ok[i]} IK branches"
            )
    reachable = chosen >= 0
    rows = np.arange(m)
    joints = np.full((m, 6), np.nan)
    joints[reachable] = sol.q[rows[reachable], chosen[reachable]]
    jm = np.full(m, np.nan)
    jm[reachable] = margin[rows[reachable], chosen[reachable]]
    cm = np.full(m, np.nan)
    if check and opt.compute_distances:
        for i in np.flatnonzero(reachable):
            cm[i] = robot.check_collision(joints[i], world).distance_m
    reason[reachable] = ""
    return ReachabilityResult(
        reachable=reachable,
        joints=joints,
        branch=chosen,
        joint_margin_rad=jm,
        collision_margin_m=cm,
        reason=np.array([str(r) for r in reason], dtype=str).reshape(m),
        branches_ok=ok,
        base_from_flange=bff,
    )


def _key(robot: RobotModel, base_from_part, flange_from_cam, part_from_cam, world, options) -> str:
    h = hashlib.sha256()
    h.update(_CACHE_VERSION.encode())
    h.update(robot.name.encode())
    h.update(hashlib.sha256(robot.urdf.encode()).digest())
    h.update(np.round(np.concatenate([robot.lower, robot.upper]), 12).tobytes())
    for tool in robot.tools:
        h.update(tool.key().encode())
    for arr in (base_from_part, flange_from_cam, part_from_cam):
        h.update(np.ascontiguousarray(np.asarray(arr, dtype=np.float64).round(12)).tobytes())
    h.update((world.key if world is not None else "no-world").encode())
    h.update(json.dumps(asdict(options), sort_keys=True).encode())
    return h.hexdigest()[:24]


@dataclass
class ReachabilityDB:
    """Reachability of a set of stations, cached on disk by a hash of its inputs.

    Attributes:
        key: hash of robot, limits, tools, base_from_part, flange_from_cam, stations,
            world and options.
        result: the ReachabilityResult.
        loaded: True when it came from the cache.
    """

    key: str
    result: ReachabilityResult
    loaded: bool = field(default=False)

    @property
    def reachable(self) -> np.ndarray:
        return self.result.reachable

    @classmethod
    def load_or_build(
        cls,
        robot: RobotModel,
        base_from_part: np.ndarray,
        flange_from_cam: np.ndarray,
        part_from_cam: np.ndarray,
        world: CollisionWorld | None = None,
        options: ReachabilityOptions | None = None,
        cache_dir: str | Path | None = None,
    ) -> ReachabilityDB:
        """Load the database from ``cache_dir`` if its inputs match, else compute (and store)."""
        opt = options or ReachabilityOptions()
        key = _key(robot, base_from_part, flange_from_cam, part_from_cam, world, opt)
        path = Path(cache_dir) / f"reachability-{key}.npz" if cache_dir is not None else None
        fields = tuple(ReachabilityResult.__dataclass_fields__)
        if path is not None:
            cached = load_arrays(path, fields)  # None when missing or damaged (then rebuilt)
            if cached is not None:
                return cls(key=key, result=ReachabilityResult(**cached), loaded=True)
        res = reachability_mask(robot, base_from_part, flange_from_cam, part_from_cam, world, opt)
        if path is not None:
            try:
                save_arrays(path, {k: getattr(res, k) for k in fields})
            except OSError:
                pass  # a cache that cannot be written (full or read-only disk) costs time next run, nothing else
        return cls(key=key, result=res, loaded=False)
