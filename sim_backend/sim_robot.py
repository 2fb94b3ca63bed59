"""SimRobot: a simulated 6-axis arm that satisfies ``drivers.protocols.Robot``.

A real simulation, not a call recorder (cf. ophyd-async ``SimMotor``): joint moves follow
a synchronised trapezoidal profile (the leading joint at the commanded speed and
acceleration, the others scaled to arrive together); linear moves follow the straight
flange path (position linear, orientation slerp) at a trapezoidal Cartesian speed, each
path sample solved by IK on the branch continuous with the previous one. ``motion="timed"``
plays the motion in real time divided by ``time_scale`` and writes every tick's pose into
the world (a camera capture mid-move sees the intermediate pose); ``motion="instant"`` jumps
to the end and advances the controller clock by the motion's duration.

Before anything moves, every command is checked against the cell's limits (``LimitError``):
joint limits along the whole path, joint speed and acceleration, Cartesian speed and
acceleration, the flange workspace box, IK existence, and joint speeds along a linear path
(which blow up near a singularity).

Faults (for tests of the cell's fault handling):

* :meth:`inject_protective_stop` after ``after_s`` seconds of motion (0: at the start of
  the next move). The arm halts where it is, the move raises ``ProtectiveStopError`` and
  every later move too, until :meth:`reset_protective_stop` (an operator's act).
* :meth:`inject_connection_loss` now or after ``after_s`` seconds of motion: the controller
  halts the arm (its program stops without the client) and every call raises
  ``NotConnectedError`` until :meth:`connect`. :meth:`fail_next_connects` refuses connects.
* ``repeatability_rad``: Gaussian joint error at each arrival (encoders report it truly).
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from calibration.errors import LimitError, MotionError, MoveRefusedError, NotConnectedError, ProtectiveStopError
from drivers.protocols import RobotState, SafetyStatus
from sim_backend.world import World

__all__ = ["RobotLimits", "SimRobot", "trapezoid_duration", "trapezoid_fraction", "HOME_JOINTS"]

#: a comfortable start pose of a UR arm (elbow up, tool pointing down), rad
HOME_JOINTS = np.array([0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])


def trapezoid_duration(distance: np.ndarray, speed: float, accel: float) -> np.ndarray:
    """Duration (s) of a rest-to-rest trapezoidal (or triangular) profile over ``distance`` (...)."""
    d = np.abs(np.asarray(distance, dtype=float))
    tri = d <= speed * speed / accel
    return np.where(tri, 2.0 * np.sqrt(d / accel), d / speed + speed / accel)


def trapezoid_fraction(t: np.ndarray, distance: float, speed: float, accel: float) -> np.ndarray:
    """Fraction of ``distance`` covered at times ``t`` (...) of a rest-to-rest trapezoid, in [0, 1]."""
    t = np.asarray(t, dtype=float)
    d = abs(float(distance))
    if d == 0.0:
        return np.ones_like(t)
    T = float(trapezoid_duration(d, speed, accel))
    v = min(speed, math.sqrt(d * accel))  # peak speed
    ta = v / accel
    t = np.clip(t, 0.0, T)
    acc = 0.5 * accel * t**2
    cruise = 0.5 * accel * ta**2 + v * (t - ta)
    dec = d - 0.5 * accel * (T - t) ** 2
    s = np.where(t < ta, acc, np.where(t <= T - ta, cruise, dec))
    return np.clip(s / d, 0.0, 1.0)


@dataclass(frozen=True)
class RobotLimits:
    """The cell's own motion limits (checked before anything moves).

    ``max_joint_speed_rad_s=None`` takes the smallest joint speed limit of the robot model.
    ``workspace_m``: (2, 3) min/max corner of a box (base frame) the flange must stay in, or None.
    """

    max_joint_speed_rad_s: float | None = None
    max_joint_accel_rad_s2: float = 10.0
    max_tcp_speed_m_s: float = 1.0
    max_tcp_accel_m_s2: float = 5.0
    workspace_m: Any = None
    rotation_lever_m: float = 0.1  # a rotation of theta counts as a path of theta * lever
    path_step_m: float = 0.005
    max_path_samples: int = 200


class SimRobot:
    """A simulated arm in a :class:`World`.

    Args:
        world: the world it writes its joints and flange pose into.
        model: a ``planning.kinematics.RobotModel`` (``fk``, ``ik_many``, ``lower``, ``upper``,
            ``max_velocity``, ``nearest_equivalent``).
        motion: "instant" or "timed".
        time_scale: simulated seconds per wall second in timed mode (10 = ten times faster).
        limits: the cell's motion limits.
        repeatability_rad: standard deviation of the joint error at each arrival.
        rng: random stream for the repeatability error (default: a child of the world's seed).
        initial_joints: (6,) start joints (default :data:`HOME_JOINTS`).
        tick_s: simulated time between pose updates in timed mode.
    """

    def __init__(
        self,
        world: World,
        model: Any,
        *,
        motion: str = "instant",
        time_scale: float = 1.0,
        limits: RobotLimits = RobotLimits(),
        repeatability_rad: float = 0.0,
        rng: np.random.Generator | None = None,
        initial_joints: np.ndarray | None = None,
        tick_s: float = 0.008,
    ) -> None:
        if motion not in ("instant", "timed"):
            raise ValueError(f"motion must be 'instant' or 'timed', got {motion!r}")
        if not time_scale > 0:
            raise ValueError(f"time_scale must be > 0, got {time_scale}")
        self.world = world
        self.model = model
        self.motion = motion
        self.time_scale = float(time_scale)
        self.limits = limits
        self.repeatability_rad = float(repeatability_rad)
        self.rng = world.spawn_rng() if rng is None else rng
        self.tick_s = float(tick_s)
        q0 = HOME_JOINTS.copy() if initial_joints is None else np.asarray(initial_joints, dtype=float)
        self._q = q0.copy()
        world.set_robot(q0, model.fk(q0))
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._moving = False
        self._connected = False
        self._refuse_connects = 0
        self._protective_stop = False
        self._ps_budget: float | None = None
        self._loss_budget: float | None = None
        self._t0 = time.monotonic()
        self._sim_offset_s = 0.0
        self.last_duration_s = 0.0  # simulated duration of the last move
        self._unreachable = np.zeros((0, 6))  # joint targets the controller refuses (injected)

    # --- connection ------------------------------------------------------------
    def connect(self) -> None:
        with self._lock:
            if self._refuse_connects:
                self._refuse_connects -= 1
                raise NotConnectedError("sim robot: controller did not answer (injected); check the network and retry")
            self._connected = True

    def close(self) -> None:
        with self._lock:
            self._stop.set()
            self._connected = False

    # --- fault injection ----------------------------------------------------------
    def inject_unreachable(self, joints_rad: np.ndarray) -> None:
        """Refuse moves to these joint targets ``(k, 6)`` rad: the move raises ``MotionError`` before the arm
        moves (a station something in the real cell keeps the robot from, which the plan did not know)."""
        with self._lock:
            self._unreachable = np.asarray(joints_rad, dtype=float).reshape(-1, 6)

    def inject_protective_stop(self, after_s: float = 0.0) -> None:
        """Protective stop after ``after_s`` seconds of (simulated) motion; 0: at the next move."""
        self._ps_budget = float(after_s)

    def reset_protective_stop(self) -> None:
        """Clear a protective stop (the operator's unlock); the arm stays where it stopped."""
        self._protective_stop = False
        self._ps_budget = None

    def inject_connection_loss(self, after_s: float | None = None) -> None:
        """Drop the connection now (``None``) or after ``after_s`` seconds of motion."""
        if after_s is None:
            self._connected = False
        else:
            self._loss_budget = float(after_s)

    def fail_next_connects(self, n: int = 1) -> None:
        """The next ``n`` calls to :meth:`connect` raise ``NotConnectedError``."""
        self._refuse_connects += int(n)

    # --- readings -------------------------------------------------------------------
    def _now(self) -> float:
        return (time.monotonic() - self._t0) * self.time_scale + self._sim_offset_s

    def _safety(self) -> SafetyStatus:
        if self._protective_stop:
            return SafetyStatus(normal=False, protective_stop=True, detail="protective stop (simulated)")
        return SafetyStatus(normal=True)

    def _check_connected(self) -> None:
        if not self._connected:
            raise NotConnectedError("sim robot: not connected (or the connection dropped); call connect() first")

    def state(self) -> RobotState:
        self._check_connected()
        with self.world.lock:
            q = self.world.joints_rad.copy()
            T = self.world.base_from_flange.copy()
        return RobotState(joints_rad=q, base_from_flange=T, safety=self._safety(), timestamp_s=self._now())

    def stop(self) -> None:
        """Decelerate and stop a timed move now; nothing happens when the arm is still."""
        if self._moving:
            self._stop.set()

    # --- motion ----------------------------------------------------------------------
    def move_joints(self, joints_rad: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> RobotState:
        self._ready_to_move()
        q1 = np.asarray(joints_rad, dtype=float)
        if q1.shape != (6,) or not np.all(np.isfinite(q1)):
            raise LimitError(f"move_joints: target must be 6 finite joint angles (rad), got {np.asarray(joints_rad)!r}")
        vmax = self.limits.max_joint_speed_rad_s or float(np.min(self.model.max_velocity))
        self._check_rate("joint speed", speed_rad_s, vmax, "rad/s")
        self._check_rate("joint acceleration", accel_rad_s2, self.limits.max_joint_accel_rad_s2, "rad/s^2")
        self._check_joint_limits(q1[None], "target")
        if len(self._unreachable) and np.any(np.max(np.abs(self._unreachable - q1), axis=1) < 1e-6):
            raise MoveRefusedError("sim robot: move refused, the target is not reachable (injected: [sim] "
                              "unreachable_stations); the arm did not move")
        q0 = self._q.copy()
        lead = float(np.max(np.abs(q1 - q0)))
        n = max(2, min(self.limits.max_path_samples, int(math.ceil(lead / 0.02)) + 1))
        path = q0 + np.linspace(0.0, 1.0, n)[:, None] * (q1 - q0)
        self._check_workspace(path)
        return self._execute(path, lead, float(speed_rad_s), float(accel_rad_s2))

    def move_pose(self, base_from_flange: np.ndarray, speed_m_s: float, accel_m_s2: float) -> RobotState:
        self._ready_to_move()
        T1 = np.asarray(base_from_flange, dtype=float)
        if T1.shape != (4, 4) or not np.all(np.isfinite(T1)):
            raise LimitError("move_pose: target must be a finite 4x4 base_from_flange transform")
        R1 = T1[:3, :3]
        if np.max(np.abs(R1.T @ R1 - np.eye(3))) > 1e-6 or np.linalg.det(R1) < 0:
            raise LimitError("move_pose: target rotation is not orthonormal; re-orthonormalise the pose")
        lim = self.limits
        self._check_rate("TCP speed", speed_m_s, lim.max_tcp_speed_m_s, "m/s")
        self._check_rate("TCP acceleration", accel_m_s2, lim.max_tcp_accel_m_s2, "m/s^2")
        q0 = self._q.copy()
        T0 = self.model.fk(q0)
        rot = Rotation.from_matrix(np.stack([T0[:3, :3], R1]))
        angle = float((rot[0].inv() * rot[1]).magnitude())
        length = max(float(np.linalg.norm(T1[:3, 3] - T0[:3, 3])), angle * lim.rotation_lever_m)
        n = max(2, min(lim.max_path_samples, int(math.ceil(length / lim.path_step_m)) + 1))
        s = np.linspace(0.0, 1.0, n)
        poses = np.tile(np.eye(4), (n, 1, 1))
        poses[:, :3, :3] = Slerp([0.0, 1.0], rot)(s).as_matrix()
        poses[:, :3, 3] = T0[:3, 3] + s[:, None] * (T1[:3, 3] - T0[:3, 3])
        path = self._ik_path(poses, q0)
        self._check_workspace(path)
        # joint speeds along the path at the commanded Cartesian speed (singularities)
        if length > 0:
            dq_ds = np.abs(np.diff(path, axis=0)) / np.diff(s)[:, None] / length  # rad per metre
            peak = float(np.max(dq_ds / self.model.max_velocity)) * min(speed_m_s, math.sqrt(length * accel_m_s2))
            if peak > 1.0:
                raise LimitError(
                    f"move_pose: the linear path needs {peak:.1f}x the joint speed limit (near a singularity); "
                    "lower the speed or move in joint space"
                )
        return self._execute(path, length, float(speed_m_s), float(accel_m_s2))

    # --- checks ------------------------------------------------------------------------
    def _ready_to_move(self) -> None:
        self._check_connected()
        if self._protective_stop:
            raise ProtectiveStopError(
                "sim robot is in protective stop: an operator must clear it (reset_protective_stop) "
                "and resume from the measured pose"
            )
        if self._moving:
            raise MotionError("sim robot: a move is already running; wait for it or stop() it")

    @staticmethod
    def _check_rate(what: str, value: float, limit: float, unit: str) -> None:
        if not (np.isfinite(value) and value > 0):
            raise LimitError(f"{what} must be a positive number ({unit}), got {value}")
        if value > limit:
            raise LimitError(f"{what} {value:g} {unit} exceeds the cell limit {limit:g} {unit}; lower it")

    def _check_joint_limits(self, q: np.ndarray, where: str) -> None:
        lo, hi = self.model.lower, self.model.upper
        bad = (q < lo - 1e-9) | (q > hi + 1e-9)
        if bad.any():
            j = int(np.nonzero(bad.any(axis=0))[0][0])
            v = q[np.nonzero(bad[:, j])[0][0], j]
            raise LimitError(
                f"{where}: joint {j + 1} = {v:.4f} rad is outside its limits [{lo[j]:.4f}, {hi[j]:.4f}] rad"
            )

    def _check_workspace(self, path: np.ndarray) -> None:
        box = self.limits.workspace_m
        if box is None:
            return
        box = np.asarray(box, dtype=float)
        p = self.model.fk_many(path)[:, :3, 3]
        out = np.any((p < box[0]) | (p > box[1]), axis=1)
        if out.any():
            raise LimitError(
                f"the flange would leave the cell's workspace box at {np.round(p[out][0], 4).tolist()} m "
                f"(box {box.tolist()}); choose another station or enlarge the workspace"
            )

    def _ik_path(self, poses: np.ndarray, q0: np.ndarray) -> np.ndarray:
        """(n, 6) joints along flange ``poses: (n, 4, 4)``, continuous from ``q0``."""
        sol = self.model.ik_many(poses, q_ref=q0)
        path = np.empty((len(poses), 6))
        prev = q0
        for k in range(len(poses)):
            ok = sol.within_limits[k]
            if not ok.any():
                why = sol.failure[k] or "no IK solution"
                where = "target" if k == len(poses) - 1 else f"path sample {k}/{len(poses) - 1}"
                raise LimitError(f"move_pose: {where} is unreachable: {why}")
            cand = self.model.nearest_equivalent(sol.q[k][ok], prev)
            if not np.all(self.model.within_limits(cand)):
                cand = np.where(self.model.within_limits(cand)[:, None], cand, np.inf)
            d = np.max(np.abs(cand - prev), axis=1)
            best = int(np.argmin(d))
            if k > 0 and d[best] > 0.5:
                raise LimitError(
                    f"move_pose: the linear path jumps {d[best]:.2f} rad in joint space at sample {k} "
                    "(it crosses a singularity or a branch change); move in joint space instead"
                )
            path[k] = prev = cand[best]
        self._check_joint_limits(path, "move_pose path")
        return path

    # --- execution ------------------------------------------------------------------
    def _execute(self, path: np.ndarray, distance: float, speed: float, accel: float) -> RobotState:
        """Play ``path: (n, 6)`` (uniform in the profile's distance) under a trapezoid."""
        duration = float(trapezoid_duration(distance, speed, accel))
        s_nodes = np.linspace(0.0, 1.0, len(path))

        def q_at(frac: float) -> np.ndarray:
            return np.array([np.interp(frac, s_nodes, path[:, j]) for j in range(6)])

        # the first fault (motion time) that falls within this move
        events = [(b, kind) for b, kind in ((self._ps_budget, "ps"), (self._loss_budget, "loss")) if b is not None]
        t_event, kind = min(events) if events else (math.inf, "")
        self._moving = True
        self._stop.clear()
        try:
            if self.motion == "instant":
                t_end = min(duration, t_event)
                self._sim_offset_s += t_end
                frac = float(trapezoid_fraction(t_end, distance, speed, accel)) if distance else 1.0
                stopped = False
            else:
                t_end, frac, stopped = self._play_timed(q_at, duration, distance, speed, accel, t_event)
        finally:
            self._moving = False
        self._spend_budgets(t_end)
        if t_end < duration or stopped:
            self._set(q_at(frac))
            if stopped:
                raise MotionError(f"move stopped by stop() at {frac:.0%} of the path; the target was not reached")
            if kind == "ps":
                self._protective_stop = True
                self._ps_budget = None
                raise ProtectiveStopError(
                    f"protective stop (injected) {t_end:.3f} s into a {duration:.3f} s move at {frac:.0%} of the path; "
                    "clear it and resume from the measured pose"
                )
            self._connected = False
            self._loss_budget = None
            raise NotConnectedError(
                f"connection to the sim robot lost {t_end:.3f} s into the move; the arm halted. Reconnect and "
                "resume from the measured pose"
            )
        q = path[-1].copy()
        if self.repeatability_rad > 0:
            q = q + self.repeatability_rad * self.rng.standard_normal(6)
        self._set(q)
        self.last_duration_s = duration
        return self.state()

    def _play_timed(self, q_at, duration, distance, speed, accel, t_event):
        """Real-time playback; returns (simulated time reached, path fraction, stopped by stop())."""
        start = time.monotonic()
        t_stop = None
        frac_stop = sdot = 0.0
        a_s = accel / distance if distance else 1.0  # path-fraction acceleration
        while True:
            t = (time.monotonic() - start) * self.time_scale
            if t_stop is None and self._stop.is_set():
                t_stop = t
                frac_stop = float(trapezoid_fraction(t, distance, speed, accel)) if distance else 1.0
                dt = 1e-4
                sdot = (float(trapezoid_fraction(t + dt, distance, speed, accel)) - frac_stop) / dt if distance else 0.0
            if t >= t_event:
                t = t_event
            if t_stop is not None:
                tau = min(t - t_stop, sdot / a_s)
                frac = min(1.0, frac_stop + sdot * tau - 0.5 * a_s * tau * tau)
                done_stop = t - t_stop >= sdot / a_s
            else:
                frac = float(trapezoid_fraction(t, distance, speed, accel)) if distance else 1.0
                done_stop = False
            if t >= t_event:
                return t, frac, False
            if done_stop:
                return t, frac, True
            if t >= duration:
                return duration, 1.0, False
            self._set(q_at(frac))
            time.sleep(self.tick_s / self.time_scale)

    def _spend_budgets(self, t: float) -> None:
        if self._ps_budget is not None:
            self._ps_budget = max(0.0, self._ps_budget - t)
        if self._loss_budget is not None:
            self._loss_budget = max(0.0, self._loss_budget - t)

    def _set(self, q: np.ndarray) -> None:
        self._q = np.asarray(q, dtype=float).copy()
        self.world.set_robot(self._q, self.model.fk(self._q))
