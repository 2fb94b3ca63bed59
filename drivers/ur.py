"""Universal Robots arm through ur-rtde, with the ur-rtde client in a process of its own.

:class:`URRobot` implements :class:`drivers.protocols.Robot`. The ur-rtde client
(control, receive, dashboard) runs in a child interpreter (``drivers.ur_worker``)
that talks to this process over a pipe, so a crash of the client (it has
segfaulted while tearing down during a reconnect) cannot take the job down: a dead
child becomes ``NotConnectedError`` and :meth:`URRobot.connect` starts a new one.

What this driver adds to ur-rtde:

* every failure is an exception (ur-rtde's motion calls return ``False``):
  ``ProtectiveStopError`` (protective or emergency stop), ``MotionError`` (script
  not running, deadline, stopped on request), ``NotConnectedError`` (stale RTDE
  data, dead client);
* before each move the controller is asked whether it takes the target
  (``is_within_safety_limits``: its joint limits, safety planes, tool orientation limits and
  reach); its "no", with the arm still where the move started (checked on both sides of the
  pipe), is ``MoveRefusedError`` and nothing is sent. Anything else stays a fault, also a
  program that stops before the arm moved (a runtime error and a stop from the pendant look
  the same over RTDE; decision 0028);
* a move the arm could not make is refused at once with one line naming the cause: the teach
  pendant's speed slider at (or near) 0 (RTDE ``target_speed_fraction``), or the robot in local
  control (the dashboard's ``is in remote control``); during a move, a speed at 0 (RTDE
  ``speed_scaling`` x ``target_speed_fraction``: the slider pulled down, a stop) for longer than
  ``speed_zero_grace_s`` stops the move and names it instead of waiting out the deadline; a
  slider below 100% stretches the move's deadline (decision 0063);
* the cell's own limits (joint speed and acceleration, TCP speed and acceleration,
  a workspace box in the base frame for the flange) are checked before anything
  is sent (``LimitError``);
* its own deadline on every blocking call, on both sides of the pipe;
* the controller's RTDE watchdog is armed, and kicked by the child while it waits;
* freshness is judged by the RTDE ``timestamp``, not by ``isConnected()``;
* the safety status is checked after each move; it never unlocks a protective stop
  or resumes on its own: that is the operator's act;
* :meth:`URRobot.stop` reaches the client at once, as a signal, whatever it is doing (also in
  the middle of a move another thread waits for), and reports when the arm came to rest.

The child is a fresh interpreter (spawn semantics) started with ``subprocess``
rather than ``multiprocessing``: the latter's spawn context starts a
resource-tracker process that outlives the driver.
"""
from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from calibration import errors
from calibration.errors import DriverError, LimitError, MotionError, MoveRefusedError, NotConnectedError
from drivers.motion import arm_moved, describe_change, joint_change_rad
from drivers.protocols import RobotState, SafetyStatus
from drivers.ur_worker import LOCAL_CONTROL, SPEED_ZERO, slider_problem

# safety_status_bits (RTDE guide)
BIT_PROTECTIVE_STOP, BIT_ROBOT_ESTOP, BIT_ESTOP, BIT_VIOLATION, BIT_FAULT = 2, 6, 7, 8, 9
RUNTIME_PLAYING = 2
PINNED_UR_RTDE = "1.6.5"


def pose_to_matrix(pose) -> np.ndarray:
    """UR pose vector ``(6,)`` [x, y, z, rx, ry, rz] (metres, rotation vector) -> (4, 4)."""
    pose = np.asarray(pose, dtype=float)
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(pose[3:6]).as_matrix()
    out[:3, 3] = pose[:3]
    return out


def matrix_to_pose(a_from_b: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform -> UR pose vector ``(6,)``."""
    return np.concatenate([a_from_b[:3, 3], Rotation.from_matrix(a_from_b[:3, :3]).as_rotvec()])


def profile_duration(distance: float, speed: float, accel: float) -> float:
    """Duration (s) of a rest-to-rest trapezoidal profile over ``distance`` (triangular if short)."""
    if distance <= 0.0:
        return 0.0
    if speed * speed / accel >= distance:
        return 2.0 * float(np.sqrt(distance / accel))
    return distance / speed + speed / accel


def safety_from_bits(bits: int, runtime_state: int) -> SafetyStatus:
    """A :class:`SafetyStatus` from RTDE ``safety_status_bits`` and ``runtime_state``."""
    pstop = bool(bits & (1 << BIT_PROTECTIVE_STOP))
    estop = bool(bits & ((1 << BIT_ESTOP) | (1 << BIT_ROBOT_ESTOP)))
    fault = bool(bits & ((1 << BIT_FAULT) | (1 << BIT_VIOLATION)))
    running = runtime_state == RUNTIME_PLAYING
    detail = ", ".join(name for name, flag in (("protective stop", pstop), ("emergency stop", estop),
                                               ("fault", fault), ("program not running", not running)) if flag)
    return SafetyStatus(normal=not (pstop or estop or fault) and running, protective_stop=pstop,
                        emergency_stop=estop, fault=fault, program_running=running, detail=detail)


@dataclass(frozen=True)
class CellLimits:
    """The cell's own motion limits, checked before anything is sent to the robot.

    The workspace box bounds the flange origin in the robot base frame (metres).
    """

    max_joint_speed_rad_s: float = 1.0
    max_joint_accel_rad_s2: float = 2.0
    max_tcp_speed_m_s: float = 0.25
    max_tcp_accel_m_s2: float = 1.0
    workspace_min_m: tuple[float, float, float] = (-1.0, -1.0, -0.1)
    workspace_max_m: tuple[float, float, float] = (1.0, 1.0, 1.2)

    def check_box(self, points: np.ndarray, what: str) -> None:
        """Raise ``LimitError`` if any of ``points: (n, 3)`` lies outside the workspace box."""
        lo, hi = np.asarray(self.workspace_min_m), np.asarray(self.workspace_max_m)
        outside = np.any((points < lo) | (points > hi), axis=1)
        if outside.any():
            p = points[np.argmax(outside)]
            raise LimitError(f"{what}: flange at {np.round(p, 3).tolist()} m is outside the cell's workspace box "
                             f"{list(lo)}..{list(hi)} m; nothing was sent to the robot")


def _check_speed(value: float, limit: float, what: str, unit: str) -> None:
    if not np.isfinite(value) or value <= 0.0:
        raise LimitError(f"{what} must be a positive number, got {value} {unit}; nothing was sent to the robot")
    if value > limit:
        raise LimitError(f"{what} {value:g} {unit} exceeds the cell limit {limit:g} {unit}; "
                         "nothing was sent to the robot")


@dataclass
class _Worker:
    process: subprocess.Popen
    conn: Connection
    send_lock: threading.Lock = field(default_factory=threading.Lock)


class URRobot:
    """A UR arm over RTDE (ur-rtde in a child process); implements ``drivers.protocols.Robot``.

    Args:
        host: robot (or loopback controller) address.
        limits: the cell's own limits.
        deadline_s: deadline of non-motion calls, and the margin added to a move's expected duration.
        model: a ``planning.kinematics.RobotModel`` for joint limits and the workspace check along
            joint moves (loaded from ``robot`` if None).
        frequency_hz: RTDE output frequency asked of the controller.
        watchdog_hz: minimum input frequency the controller's watchdog demands (the child kicks faster).
        stale_after_s: RTDE data whose timestamp has not advanced for this long is stale.
        stop_decel_rad_s2: deceleration of :meth:`stop` and of a stop at a deadline.
        position_tol: arrival tolerance (rad for joints, m for the flange position).
        speed_zero_grace_s: how long (wall) the arm may stand still during a move at a speed of 0 (slider
            pulled down, the controller's speed scaling at 0) before the move is stopped and the cause named.
    """

    def __init__(self, host: str, limits: CellLimits | None = None, deadline_s: float = 5.0, *,
                 model=None, robot: str = "ur5e", frequency_hz: float = 125.0, watchdog_hz: float = 5.0,
                 stale_after_s: float = 0.5, stop_decel_rad_s2: float = 4.0, position_tol: float = 1e-3,
                 connect_timeout_s: float = 30.0, speed_zero_grace_s: float = 0.5):
        self.host = host
        self.limits = limits or CellLimits()
        self.deadline_s = float(deadline_s)
        if model is None:
            from planning.kinematics import load_robot

            model = load_robot(robot)
        self.model = model
        self._options = {"host": host, "frequency_hz": frequency_hz, "watchdog_hz": watchdog_hz,
                         "stale_after_s": stale_after_s, "stop_decel": stop_decel_rad_s2,
                         "position_tol": position_tol, "orientation_tol": 1e-3,
                         "speed_zero_grace_s": float(speed_zero_grace_s)}
        self.connect_timeout_s = connect_timeout_s
        self._worker: _Worker | None = None
        self._request_lock = threading.Lock()
        self._seq = itertools.count(1)
        #: after :meth:`stop`: when the arm came to rest, ``{"controller_timestamp_s", "after_s"}`` (None: no stop
        #: was needed, the controller had halted it already)
        self.last_rest: dict | None = None

    # ------------------------------------------------------------ lifecycle
    @property
    def connected(self) -> bool:
        return self._worker is not None and self._worker.process.poll() is None

    def connect(self) -> None:
        """Start the client process and connect; raises ``NotConnectedError`` if it cannot."""
        if self.connected:
            return
        self._discard_worker()
        parent_sock, child_sock = _socketpair()
        root = str(Path(__file__).resolve().parents[1])
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
        # a session of its own: Ctrl-C at the terminal (SIGINT to the foreground process group) reaches this
        # process, which stops the arm through the child; the child never dies of it mid-move
        process = subprocess.Popen([sys.executable, "-m", "drivers.ur_worker", str(child_sock.fileno())],
                                   pass_fds=(child_sock.fileno(),), env=env, cwd=root, start_new_session=True)
        child_sock.close()
        self._worker = _Worker(process, Connection(parent_sock.detach()))
        try:
            self._request({"op": "connect", **self._options}, self.connect_timeout_s)
        except DriverError as exc:
            self._discard_worker(kill=True)
            if LOCAL_CONTROL in str(exc):  # its own line says what to do
                line = str(exc).removeprefix(f"UR at {self.host}: ")
                raise NotConnectedError(f"UR at {self.host}: could not connect: {line}") from exc
            raise NotConnectedError(f"UR at {self.host}: could not connect ({exc}); check the address, that the "
                                    "robot is powered, in remote control and not stopped") from exc

    def close(self) -> None:
        """Stop the control script, end the client process; safe to call twice."""
        worker = self._worker
        if worker is None:
            return
        if worker.process.poll() is None:
            try:
                self._request({"op": "close"}, 5.0)
            except DriverError:
                pass
        self._discard_worker()

    def __enter__(self) -> URRobot:
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------ Robot protocol
    def state(self) -> RobotState:
        """The latest reading; ``NotConnectedError`` if the RTDE timestamp is stale or the client is gone."""
        return self._to_state(self._request({"op": "state"}, self.deadline_s))

    def move_joints(self, joints_rad, speed_rad_s: float, accel_rad_s2: float) -> RobotState:
        q = np.asarray(joints_rad, dtype=float)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise LimitError(f"move_joints: expected 6 finite joint values, got {joints_rad!r}")
        _check_speed(speed_rad_s, self.limits.max_joint_speed_rad_s, "joint speed", "rad/s")
        _check_speed(accel_rad_s2, self.limits.max_joint_accel_rad_s2, "joint acceleration", "rad/s^2")
        lower, upper = np.asarray(self.model.lower), np.asarray(self.model.upper)
        if np.any(q < lower) or np.any(q > upper):
            raise LimitError(f"move_joints: target {np.round(q, 4).tolist()} rad is outside the joint limits; "
                             "nothing was sent to the robot")
        start, fraction = self._ready_state()
        # the controller moves on a straight line in joint space: check the flange along it
        path = start.joints_rad + np.linspace(0.0, 1.0, 25)[:, None] * (q - start.joints_rad)
        flange = np.array([np.asarray(self.model.fk(qi))[:3, 3] for qi in path])
        self.limits.check_box(flange, "move_joints")
        expected = profile_duration(float(np.max(np.abs(q - start.joints_rad))), speed_rad_s, accel_rad_s2)
        return self._move({"op": "move_joints", "target": q.tolist(), "speed": speed_rad_s,
                           "accel": accel_rad_s2}, expected / fraction, start)

    def move_pose(self, base_from_flange, speed_m_s: float, accel_m_s2: float) -> RobotState:
        target = np.asarray(base_from_flange, dtype=float)
        if target.shape != (4, 4) or not np.all(np.isfinite(target)) or \
                not np.allclose(target[:3, :3] @ target[:3, :3].T, np.eye(3), atol=1e-6):
            raise LimitError("move_pose: base_from_flange must be a finite (4, 4) rigid transform")
        _check_speed(speed_m_s, self.limits.max_tcp_speed_m_s, "TCP speed", "m/s")
        _check_speed(accel_m_s2, self.limits.max_tcp_accel_m_s2, "TCP acceleration", "m/s^2")
        # the box is convex: both ends inside means the straight line is inside
        self.limits.check_box(target[None, :3, 3], "move_pose")
        if len(np.asarray(self.model.ik(target)).reshape(-1, 6)) == 0:
            raise LimitError(f"move_pose: {np.round(target[:3, 3], 3).tolist()} m is out of the arm's reach; "
                             "nothing was sent to the robot")
        start, fraction = self._ready_state()
        self.limits.check_box(start.base_from_flange[None, :3, 3], "move_pose (start)")
        length = float(np.linalg.norm(target[:3, 3] - start.base_from_flange[:3, 3]))
        angle = float(np.linalg.norm(Rotation.from_matrix(start.base_from_flange[:3, :3].T @ target[:3, :3])
                                     .as_rotvec()))
        expected = profile_duration(max(length, 0.1 * angle), speed_m_s, accel_m_s2)
        return self._move({"op": "move_pose", "target": matrix_to_pose(target).tolist(), "speed": speed_m_s,
                           "accel": accel_m_s2}, expected / fraction, start)

    def stop(self) -> RobotState | None:
        """Decelerate and stop now, whatever the client is doing; returns the state once the arm is at rest.

        The stop reaches the client at once as a signal (:meth:`signal_stop`), also while another
        thread waits for a move; this call then waits (bounded) until the arm is at rest. Never
        raises: for a robot already stopped, or gone, it returns what it can (None when gone).
        """
        self.last_rest = None  # a stop that returns early says nothing about when the arm came to rest
        worker = self._worker
        if worker is None:
            return None
        self.signal_stop()
        # a move in flight in another thread ends within the stop's own bound; then ask for the rest state
        wait_s = 2.5 + self.limits.max_joint_speed_rad_s / self._options["stop_decel"] + self.deadline_s
        if not self._request_lock.acquire(timeout=wait_s):
            return None
        self._request_lock.release()
        try:
            value = self._request({"op": "stop"}, wait_s)
        except DriverError:
            return None
        self.last_rest = value.get("rest")
        return self._to_state(value)

    def signal_stop(self) -> None:
        """Tell the client to stop the arm now, without waiting: safe from a signal handler or any thread.

        The client (a process of its own) gets ``SIGUSR1``; it sends the controller a ``stopj``
        within one poll of its loop (a few ms), also in the middle of a move. Any move it is
        given after this is refused until :meth:`stop` has run.
        """
        worker = self._worker
        if worker is None:
            return
        try:
            if worker.process.poll() is None:
                os.kill(worker.process.pid, signal.SIGUSR1)
        except OSError:
            pass

    # ------------------------------------------------------------ internals
    def _ready_state(self) -> tuple[RobotState, float]:
        """The state a move starts from, and the pendant's speed slider (``target_speed_fraction``, 0..1).

        A slider at (or near) 0 is ``MotionError`` at once with its one line: the arm would stand still until
        the deadline. (The child checks it again, and the remote control, just before it sends the move.)
        """
        value = self._request({"op": "state"}, self.deadline_s)
        problem = slider_problem(value)
        if problem is not None:
            raise MotionError(f"UR at {self.host}: {problem}")
        return self._to_state(value), max(float(value.get("target_speed_fraction", 1.0)), SPEED_ZERO)

    def _move(self, request: dict, expected_s: float, start: RobotState) -> RobotState:
        deadline = 1.5 * expected_s + self.deadline_s
        request["deadline_s"] = deadline
        # backstop on this side of the pipe: the child's deadline, then its bounded stop, then a margin
        stop_allowance = 2.5 + self.limits.max_joint_speed_rad_s / self._options["stop_decel"]
        try:
            reply = self._request(request, deadline + stop_allowance + self.deadline_s)
        except MoveRefusedError:
            # a refusal only if the arm is still where this move started (the child checked from its own reading)
            now = self.state().joints_rad
            if arm_moved(start.joints_rad, now):
                raise MotionError(f"UR at {self.host}: the controller refused the move, but the arm is "
                                  f"{describe_change(joint_change_rad(start.joints_rad, now))} from where the move "
                                  "started: the job stops") from None
            raise
        state = self._to_state(reply)
        if not state.safety.normal:  # the child checked already; a second look costs nothing
            raise MotionError(f"UR at {self.host}: move ended with safety status '{state.safety.detail}'")
        return state

    def _request(self, request: dict, timeout_s: float) -> dict:
        with self._request_lock:
            worker = self._worker
            if worker is None or worker.process.poll() is not None:
                self._discard_worker()
                raise NotConnectedError(f"UR at {self.host}: not connected (the client process is not running); "
                                        "call connect()")
            seq = next(self._seq)
            try:
                with worker.send_lock:
                    worker.conn.send(request | {"seq": seq})
                end = time.monotonic() + timeout_s
                while True:
                    while not worker.conn.poll(0.05):
                        if worker.process.poll() is not None:
                            raise EOFError
                        if time.monotonic() > end:
                            self._discard_worker(kill=True)
                            raise NotConnectedError(f"UR at {self.host}: no answer to '{request['op']}' within "
                                                    f"{timeout_s:.1f} s; the client process was ended, call connect()")
                    reply = worker.conn.recv()
                    # a reply to an earlier request whose wait was cut short (an abort unwound it): not ours
                    if reply.get("seq") == seq:
                        break
            except (EOFError, OSError):
                code = worker.process.poll()
                self._discard_worker(kill=True)
                raise NotConnectedError(f"UR at {self.host}: the client process died (exit code {code}) during "
                                        f"'{request['op']}'; call connect() to start a new one") from None
        if reply.get("ok"):
            return reply["value"]
        error_class = getattr(errors, reply.get("error", ""), None)
        if not (isinstance(error_class, type) and issubclass(error_class, DriverError)):
            error_class = DriverError
        if error_class is NotConnectedError:
            self._discard_worker(kill=True)
        raise error_class(f"UR at {self.host}: {reply.get('message', 'unknown failure')}")

    def _discard_worker(self, kill: bool = False) -> None:
        """Forget the child; ``kill`` ends it at once (its client may be stuck in a reconnect)."""
        worker, self._worker = self._worker, None
        if worker is None:
            return
        try:
            worker.conn.close()
        except OSError:
            pass
        process = worker.process
        if kill and process.poll() is None:
            process.kill()
        try:
            process.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=5.0)

    @staticmethod
    def _to_state(value: dict) -> RobotState:
        return RobotState(joints_rad=np.asarray(value["q"], dtype=float),
                          base_from_flange=pose_to_matrix(value["pose"]),
                          safety=safety_from_bits(int(value["safety_bits"]), int(value["runtime_state"])),
                          timestamp_s=float(value["timestamp"]),
                          joint_speeds_rad_s=np.asarray(value["qd"], dtype=float) if value.get("qd") is not None
                          else None)


def _socketpair():
    import socket

    return socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
