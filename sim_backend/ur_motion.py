"""Motion kernels of the loopback UR controller (:mod:`sim_backend.ur_controller`).

What the controller's arm does on a tick: ``movej`` is a synchronised trapezoidal profile in joint space (leading
joint at the given speed and acceleration), ``movel`` a trapezoidal profile along the straight line of the TCP with the
orientation interpolated on SO(3), joints by IK (branch nearest the current joints), a stop a constant deceleration
of every joint. Each motion answers ``at(t, model) -> (joints (6,), done)`` for ``t`` seconds of its own clock
(which the controller advances at the speed slider's fraction: decision 0063).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from drivers.ur import profile_duration as trapezoid_duration


def trapezoid(distance: float, v: float, a: float, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Position and speed along a rest-to-rest trapezoidal (or triangular) profile.

    distance: path length (>= 0); v, a: peak speed and acceleration (> 0); t: time(s) since start.
    Returns (s, s_dot) with s clipped to [0, distance].
    """
    t = np.asarray(t, dtype=float)
    if distance <= 0.0:
        return np.zeros_like(t), np.zeros_like(t)
    t_acc = v / a
    if a * t_acc**2 >= distance:  # triangular: never reaches v
        t_acc = np.sqrt(distance / a)
        v = a * t_acc
    t_flat = distance / v - t_acc
    total = 2 * t_acc + t_flat
    tc = np.clip(t, 0.0, total)
    s_acc = 0.5 * a * np.minimum(tc, t_acc) ** 2
    s_flat = v * np.clip(tc - t_acc, 0.0, t_flat)
    t_dec = np.clip(tc - t_acc - t_flat, 0.0, t_acc)
    s_dec = v * t_dec - 0.5 * a * t_dec**2
    speed = np.where(tc < t_acc, a * tc, np.where(tc < t_acc + t_flat, v, v - a * t_dec))
    return np.minimum(s_acc + s_flat + s_dec, distance), np.where(tc >= total, 0.0, speed)


class _IKFailed(RuntimeError):
    pass


@dataclass
class _JointMotion:
    q0: np.ndarray
    q1: np.ndarray
    v: float
    a: float
    is_async: bool = False

    def __post_init__(self):
        self.span = float(np.max(np.abs(self.q1 - self.q0)))
        self.duration = trapezoid_duration(self.span, self.v, self.a)

    def at(self, t: float, model) -> tuple[np.ndarray, bool]:
        if self.span == 0.0:
            return self.q1.copy(), True
        s, _ = trapezoid(self.span, self.v, self.a, t)
        return self.q0 + (self.q1 - self.q0) * (float(s) / self.span), t >= self.duration


@dataclass
class _LinearMotion:
    base_from_tcp0: np.ndarray
    base_from_tcp1: np.ndarray
    q_start: np.ndarray
    v: float
    a: float
    flange_from_tcp: np.ndarray
    is_async: bool = False
    # rotation is given the path length of a point 0.1 m off the axis (an assumption of this emulator)
    rot_radius_m: float = 0.1
    q_prev: np.ndarray = field(init=False)

    def __post_init__(self):
        p0, p1 = self.base_from_tcp0[:3, 3], self.base_from_tcp1[:3, 3]
        self.rotvec = Rotation.from_matrix(self.base_from_tcp0[:3, :3].T @ self.base_from_tcp1[:3, :3]).as_rotvec()
        self.span = max(float(np.linalg.norm(p1 - p0)), float(np.linalg.norm(self.rotvec)) * self.rot_radius_m)
        self.duration = trapezoid_duration(self.span, self.v, self.a)
        self.q_prev = self.q_start.copy()
        self.tcp_from_flange = np.linalg.inv(self.flange_from_tcp)

    def at(self, t: float, model) -> tuple[np.ndarray, bool]:
        if self.span == 0.0:
            return self.q_prev.copy(), True
        s, _ = trapezoid(self.span, self.v, self.a, t)
        u = float(s) / self.span
        target = np.eye(4)
        target[:3, :3] = self.base_from_tcp0[:3, :3] @ Rotation.from_rotvec(u * self.rotvec).as_matrix()
        target[:3, 3] = (1 - u) * self.base_from_tcp0[:3, 3] + u * self.base_from_tcp1[:3, 3]
        branches = np.asarray(model.ik(target @ self.tcp_from_flange, self.q_prev)).reshape(-1, 6)
        if branches.size == 0:
            raise _IKFailed(f"movel: no inverse kinematics solution at {np.round(target[:3, 3], 4)} m")
        diff = (branches - self.q_prev + np.pi) % (2 * np.pi) - np.pi
        best = int(np.argmin(np.max(np.abs(diff), axis=1)))
        if np.max(np.abs(diff[best])) > 0.5:
            raise _IKFailed("movel: joint jump on the straight line (singularity or branch change)")
        self.q_prev = self.q_prev + diff[best]
        return self.q_prev.copy(), t >= self.duration


@dataclass
class _StopMotion:
    q0: np.ndarray
    qd0: np.ndarray
    decel: float
    is_async: bool = False

    def __post_init__(self):
        self.duration = float(np.max(np.abs(self.qd0))) / self.decel if self.decel > 0 else 0.0

    def at(self, t: float, model) -> tuple[np.ndarray, bool]:
        if self.duration <= 0.0:
            return self.q0.copy(), True
        tc = min(t, self.duration)
        return self.q0 + self.qd0 * (tc - tc * tc / (2 * self.duration)), t >= self.duration
