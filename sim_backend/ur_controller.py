"""A loopback Universal Robots controller that the real ur-rtde client can drive.

It speaks the public RTDE protocol on port 30004, answers the dashboard server on 29999, and accepts URScript programs
on 30003. The program that ur-rtde uploads (its ``rtde_control`` script) is not interpreted line by line: the
controller checks that the script's command table is the one it knows (:func:`sim_backend.rtde_protocol.
check_control_script`, the contract with the pinned ur-rtde version) and then *plays* that script's register
handshake: command id in ``input_int_register_0``, arguments in ``input_double_register_0..``, 1 (ready) / 2 (done) in
``output_int_register_0``, async progress in ``output_int_register_2``.

Motion comes from the pin model of the arm (``planning.kinematics``): ``movej`` is a synchronised trapezoidal profile
in joint space (leading joint at the given speed and acceleration), ``movel`` a trapezoidal profile along the straight
line of the TCP with the orientation interpolated on SO(3), joints by IK (branch nearest the current joints); the
kernels are in :mod:`sim_backend.ur_motion`. ``time_scale`` > 1 runs the robot's clock faster than the wall. A motion
runs at the pendant's speed slider (:attr:`LoopbackURController.speed_slider`, RTDE ``target_speed_fraction``; also set
by the RTDE inputs ``speed_slider_mask`` / ``speed_slider_fraction``, as ur-rtde's ``RTDEIOInterface.setSpeedSlider``
does) times the trajectory limiter's :attr:`~LoopbackURController.speed_scaling` (RTDE ``speed_scaling``); a stop
does not.

Faults to inject: :meth:`protective_stop`, :meth:`emergency_stop`, :meth:`drop_connections`, :meth:`stop_script`,
:meth:`set_speed_slider` (0: the arm does not advance), :meth:`set_remote_control` (False: local mode; the dashboard's
``is in remote control`` answers ``false`` and programs sent to 30003 are dropped, as a real e-Series drops its
clients on 30001-30003). The RTDE input watchdog that the script arms (``rtde_set_watchdog``) stops the program if
the host stops writing.

Targets refused: ``is_within_safety_limits`` (ur-rtde's ``isJointsWithinSafetyLimits`` / ``isPoseWithinSafetyLimits``,
commands 37 / 36) is false for joints outside the arm's limits, a pose without an IK branch inside them, and joint
targets given to :meth:`refuse_targets` (a safety restriction the plan does not know: ``[sim] unreachable_stations``,
also from another process by the emulator-only dashboard command ``sim refuse targets``, :func:`refuse_targets_at`;
they end with the running control program, or the next one if none runs: a later job's program starts with none). A
``movej`` / ``movel`` to such a target is a runtime error: the program stops before the arm moves (what ur-rtde's
sources expect of a real controller when, e.g., inverse kinematics fails; decision 0028).

Only loopback addresses are accepted; several controllers run side by side on 127.0.0.2, 127.0.0.3, ... because the
ports are fixed.
"""
from __future__ import annotations

import collections
import ipaddress
import json
import re
import socket
import struct
import threading
import time
from dataclasses import dataclass

import numpy as np

from drivers.ur import matrix_to_pose, pose_to_matrix
from sim_backend import rtde_protocol as rp
from sim_backend.rtde_protocol import PLAYED_COMMANDS, ScriptContractError, check_control_script
from sim_backend.ur_motion import _IKFailed, _JointMotion, _LinearMotion, _StopMotion
from sim_backend.ur_motion import trapezoid, trapezoid_duration  # noqa: F401  (public names kept importable here)

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003

# runtime_state values (RTDE guide)
STOPPING, STOPPED, PLAYING, PAUSING, PAUSED, RESUMING = range(6)
# safety_status_bits
BIT_NORMAL, BIT_PROTECTIVE_STOP, BIT_ROBOT_ESTOP, BIT_ESTOP = 0, 2, 6, 7
# safety_mode values
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP, SAFETY_ROBOT_EMERGENCY_STOP = 1, 3, 7
ROBOT_MODE_RUNNING = 7
JOINT_MODE_RUNNING = 253

@dataclass(frozen=True)
class ScriptCommand:
    """One command the control script executed: id, name, arguments, and the input recipe
    (register names) of the RTDE package that carried it."""

    cmd: int
    name: str
    args: dict
    recipe: tuple[str, ...] = ()


@dataclass
class _Script:
    """The state of the played control script (one per uploaded program)."""

    reg_offset: int
    executing: bool = False
    blocking: bool = False  # a synchronous command (move, stop) is running
    async_wr_count: int = 0
    async_op_id: int = 0


class LoopbackURController:
    """A UR controller on a loopback address, driven by a pin model of the arm.

    Args:
        host: loopback address to bind (``127.0.0.x``); the ports are the UR ones.
        robot: robot model name for ``planning.kinematics.load_robot``.
        joints_rad: (6,) start joints; default a bent, non-singular pose.
        time_scale: robot seconds per wall second (> 1 runs faster than real time).
        tick_s: wall period of the controller loop (and of the RTDE output stream).
        model: a ``RobotModel`` to use instead of loading ``robot``.
    """

    polyscope_version = "5.11.1.108318"
    controller_version = (5, 11, 1, 108318)
    serial_number = "20235500001"

    def __init__(self, host: str = "127.0.0.2", *, robot: str = "ur5e", joints_rad=None,
                 time_scale: float = 1.0, tick_s: float = 0.008, model=None):
        if not ipaddress.ip_address(host).is_loopback:
            raise ValueError(f"loopback UR controller: {host} is not a loopback address; only 127.x.x.x is allowed")
        if model is None:
            from planning.kinematics import load_robot

            model = load_robot(robot)
        self.host, self.model = host, model
        self.time_scale, self.tick_s = float(time_scale), float(tick_s)
        q0 = np.array([0.0, -1.3, 1.6, -1.87, -1.57, 0.0]) if joints_rad is None else np.asarray(joints_rad, float)
        self._lock = threading.RLock()
        self._q, self._qd = q0.copy(), np.zeros(6)
        self.robot_mode = "RUNNING"  # the dashboard's robotmode: POWER_OFF -> (power on) IDLE -> (brake release) RUNNING
        self._t = 0.0
        self._flange_from_tcp = np.eye(4)
        self._motion = None
        self._motion_elapsed = 0.0  # seconds of the running motion's own clock (advanced at the slider's speed)
        self.speed_slider = 1.0  # the pendant's speed slider (RTDE target_speed_fraction), 0..1
        self.speed_scaling = 1.0  # the trajectory limiter's scaling (RTDE speed_scaling), 0..1
        self.remote_control = True  # the pendant's remote / local switch (dashboard "is in remote control")
        self._runtime = STOPPED
        self._safety_bits = 1 << BIT_NORMAL
        self._safety_mode = SAFETY_NORMAL
        self._script: _Script | None = None
        self._pending_program: str | None = None
        self._inputs: dict[str, object] = {}
        self._command_recipe: tuple[str, ...] = ()
        self._out_int = np.zeros(48, dtype=np.int64)
        self._out_double = np.zeros(48)
        self._watchdog_var: str | None = None
        self._watchdog_period_s = 0.0
        self._watchdog_last = 0.0
        self._sessions: list[_RtdeSession] = []
        self.commands: list[ScriptCommand] = []
        self.uploaded_scripts: list[str] = []
        self.input_recipes: list[tuple[str, ...]] = []
        self.messages: list[str] = []
        self.trace: collections.deque = collections.deque(maxlen=50_000)
        self._refused = np.zeros((0, 6))  # joint targets outside the (injected) safety limits
        #: called with each :class:`ScriptCommand` once the controller has executed it (under its lock): tests
        #: inject a fault at an exact point of the handshake (e.g. a safety restriction switched on after a check)
        self.after_command = None
        self._stop = threading.Event()
        self._services: list[rp.TcpService] = []
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------ lifecycle
    def start(self) -> LoopbackURController:
        """Bind the three ports and start the control loop (``OSError`` if the address is taken)."""
        if self._thread is not None:
            return self
        try:
            self._services = [rp.TcpService(self.host, RTDE_PORT, self._serve_rtde, "rtde")]
            self._services.append(rp.TcpService(self.host, DASHBOARD_PORT, self._serve_dashboard, "dashboard"))
            self._services.append(rp.TcpService(self.host, SCRIPT_PORT, self._serve_script, "script"))
        except OSError:
            self.close()
            raise
        self._thread = threading.Thread(target=self._loop, name="ur-controller", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop every server thread and the control loop; safe to call twice."""
        self._stop.set()
        for service in self._services:
            service.close()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._services = []

    def __enter__(self) -> LoopbackURController:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------ inspection
    @property
    def joints(self) -> np.ndarray:
        with self._lock:
            return self._q.copy()

    @property
    def base_from_flange(self) -> np.ndarray:
        return np.asarray(self.model.fk(self.joints))

    @property
    def runtime_state(self) -> int:
        return self._runtime

    @property
    def safety_status_bits(self) -> int:
        return self._safety_bits

    @property
    def moving(self) -> bool:
        return self._motion is not None

    @property
    def clock_s(self) -> float:
        """The controller's clock (robot seconds, the RTDE ``timestamp``)."""
        with self._lock:
            return self._t

    @property
    def joint_speeds(self) -> np.ndarray:
        """(6,) current joint speeds, rad/s."""
        with self._lock:
            return self._qd.copy()

    def trace_copy(self) -> list[tuple[float, np.ndarray]]:
        """The recent ``(controller time s, joints (6,))`` of every tick, copied (the loop keeps appending)."""
        with self._lock:
            return list(self.trace)

    def rest_time_after(self, t0_s: float, tol_rad: float = 1e-9) -> float | None:
        """From the trace: the controller time (after ``t0_s``) from which the arm no longer moved.

        None when the trace holds nothing after ``t0_s`` or the arm was still moving at its end.
        """
        with self._lock:
            trace = [(t, q) for t, q in self.trace if t >= t0_s]
        if len(trace) < 2:
            return None
        last_q = trace[-1][1]
        rest = None
        for t, q in reversed(trace):
            if np.max(np.abs(q - last_q)) > tol_rad:
                break
            rest = t
        return None if rest == trace[-1][0] and self._motion is not None else rest

    def wait_for(self, predicate, timeout_s: float = 5.0) -> bool:
        """Poll ``predicate()`` until true or ``timeout_s`` passes; returns the last value."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if predicate():
                return True
            time.sleep(0.005)
        return bool(predicate())

    # ------------------------------------------------------------ faults
    def protective_stop(self, reason: str = "injected protective stop") -> None:
        """Halt now, set bit 2 of safety_status_bits, pause the program."""
        with self._lock:
            self._halt()
            self._safety_bits = 1 << BIT_PROTECTIVE_STOP
            self._safety_mode = SAFETY_PROTECTIVE_STOP
            if self._runtime == PLAYING:
                self._runtime = PAUSED
            self.messages.append(f"protective stop: {reason}")

    def unlock_protective_stop(self) -> bool:
        with self._lock:
            if not self._safety_bits & (1 << BIT_PROTECTIVE_STOP):
                return False
            self._safety_bits, self._safety_mode = 1 << BIT_NORMAL, SAFETY_NORMAL
            return True

    def emergency_stop(self) -> None:
        """Halt now, set the emergency-stop bits, stop the program."""
        with self._lock:
            self._halt()
            self._safety_bits = (1 << BIT_ESTOP) | (1 << BIT_ROBOT_ESTOP)
            self._safety_mode = SAFETY_ROBOT_EMERGENCY_STOP
            self._end_program("emergency stop")

    def release_emergency_stop(self) -> None:
        with self._lock:
            self._safety_bits, self._safety_mode = 1 << BIT_NORMAL, SAFETY_NORMAL

    def drop_connections(self, down_s: float = 2.0) -> None:
        """Close every client socket and turn new clients away for ``down_s`` (a pulled cable)."""
        until = time.monotonic() + down_s
        for service in self._services:
            service.refuse_until = until
            service.drop_clients()

    def set_speed_slider(self, fraction: float) -> None:
        """Move the pendant's speed slider (0..1, RTDE ``target_speed_fraction``); at 0 a running motion stands."""
        with self._lock:
            self.speed_slider = float(np.clip(fraction, 0.0, 1.0))

    def set_speed_scaling(self, scaling: float) -> None:
        """The trajectory limiter's scaling (0..1, RTDE ``speed_scaling``), e.g. a safety limit slowing the arm."""
        with self._lock:
            self.speed_scaling = float(np.clip(scaling, 0.0, 1.0))

    def set_remote_control(self, remote: bool) -> None:
        """Turn the pendant's remote / local switch: False is local mode (programs sent to 30003 are dropped)."""
        with self._lock:
            self.remote_control = bool(remote)
            if not remote:
                self.messages.append("local mode: the pendant took control")

    def stop_script(self, reason: str = "injected: program stopped") -> None:
        """Stop the running program (runtime_state -> STOPPED) and halt the arm."""
        with self._lock:
            self._halt()
            self._end_program(reason)

    # ------------------------------------------------------------ safety limits
    def refuse_targets(self, joints_rad) -> None:
        """Joint targets ``(n, 6)`` outside the controller's safety limits (replaces the last set) until the control
        program ends (stop, a new upload, runtime error, watchdog, e-stop): give them once the job's driver connected."""
        with self._lock:
            self._refused = np.asarray(joints_rad, dtype=float).reshape(-1, 6).copy()

    def within_safety_limits(self, q) -> bool:
        """URScript ``is_within_safety_limits(q)``: inside the joint limits and not a refused target."""
        q = np.asarray(q, dtype=float)
        if q.shape != (6,) or not np.all(np.isfinite(q)) or not bool(self.model.within_limits(q)):
            return False
        return not (len(self._refused) and np.any(np.max(np.abs(self._refused - q), axis=1) < 1e-6))

    def _pose_target_joints(self, pose) -> np.ndarray | None:
        """The joints a ``movel`` to TCP ``pose`` ends at (IK branch nearest the current joints), None if none."""
        base_from_flange = pose_to_matrix(pose) @ np.linalg.inv(self._flange_from_tcp)
        branches = np.asarray(self.model.ik(base_from_flange, self._q)).reshape(-1, 6)
        if branches.size == 0:
            return None
        return branches[int(np.argmin(np.max(np.abs(branches - self._q), axis=1)))]

    # ------------------------------------------------------------ control loop
    def _loop(self) -> None:
        next_tick = time.monotonic()
        last = next_tick
        while not self._stop.is_set():
            now = time.monotonic()
            dt = min(now - last, 0.05) * self.time_scale
            last = now
            with self._lock:
                self._t += dt
                self._load_pending_program()
                self._check_watchdog(now)
                self._script_tick()
                self._advance(dt)
                self.trace.append((self._t, self._q.copy()))
                packet_values = self._output_values()
            self._publish(packet_values)
            next_tick += self.tick_s
            delay = next_tick - time.monotonic()
            if delay < -0.1:
                next_tick = time.monotonic()
            self._stop.wait(max(delay, 0.0))

    def _halt(self) -> None:
        self._motion = None
        self._qd = np.zeros(6)
        if self._script is not None:
            self._script.blocking = False

    def _end_program(self, reason: str) -> None:
        self._halt()
        if self._script is not None:
            self.messages.append(f"program stopped: {reason}")
            self._refused = np.zeros((0, 6))  # the injected restriction was the ending program's (its job's)
        self._script = None
        self._runtime = STOPPED
        self._watchdog_var = None

    def _advance(self, dt: float) -> None:
        if self._motion is None:
            return
        q_old = self._q
        try:
            # a stop decelerates whatever the slider says; a move advances at the slider's (and the limiter's) speed
            rate = 1.0 if isinstance(self._motion, _StopMotion) else self.speed_slider * self.speed_scaling
            self._motion_elapsed += dt * rate
            q, done = self._motion.at(self._motion_elapsed, self.model)
        except _IKFailed as exc:
            self._end_program(f"runtime error: {exc}")
            return
        self._q = np.asarray(q, float)
        self._qd = (self._q - q_old) / dt if dt > 0 else np.zeros(6)
        if done:
            was_async = self._motion.is_async
            self._motion, self._qd = None, np.zeros(6)
            if was_async:
                self._write_async_progress(-1)

    def _check_watchdog(self, now: float) -> None:
        if self._watchdog_var is None or self._runtime != PLAYING:
            return
        if now - self._watchdog_last > self._watchdog_period_s:
            self._end_program(f"RTDE input watchdog: no write to {self._watchdog_var} "
                              f"for {self._watchdog_period_s:.3f} s")

    # ------------------------------------------------------------ the played control script
    def _load_pending_program(self) -> None:
        text, self._pending_program = self._pending_program, None
        if text is None:
            return
        if not self._safety_bits & (1 << BIT_NORMAL):
            self.messages.append("program refused: the robot is not in normal safety mode")
            return
        try:
            offset = check_control_script(text)
        except ScriptContractError as exc:
            self._end_program(f"script refused: {exc}")
            self.messages.append(f"script refused: {exc}")
            return
        self._halt()
        self._script = _Script(reg_offset=offset)
        self._watchdog_var = None
        self._out_int[offset + 2] = 0
        self._runtime = PLAYING

    def _reg(self, kind: str, i: int):
        off = self._script.reg_offset
        return self._inputs.get(f"input_{kind}_register_{i + off}", 0)

    def _signal(self, value: int) -> None:
        self._out_int[self._script.reg_offset] = value

    def _write_async_progress(self, value: int) -> None:
        sc = self._script
        if sc is None:
            return
        sc.async_wr_count = (sc.async_wr_count + 1) % 128
        if value == 0:
            sc.async_op_id = (sc.async_op_id + 1) % 128
        reg = sc.async_wr_count * 65536 + sc.async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self._out_int[sc.reg_offset + 2] = reg

    def _script_tick(self) -> None:
        sc = self._script
        if sc is None or self._runtime != PLAYING:
            return
        if sc.blocking:
            if self._motion is not None:
                return
            sc.blocking = False
            self._signal(2)
        cmd = int(self._reg("int", 0))
        if cmd == 0:
            sc.executing = False
            self._signal(1)
        elif not sc.executing:
            sc.executing = True
            self._process(cmd)
            if self._script is not None and not self._script.blocking:
                self._signal(2)

    def _process(self, cmd: int) -> None:
        d = np.array([float(self._reg("double", i)) for i in range(8)])
        is_async = int(self._reg("int", 1)) == 1
        name = PLAYED_COMMANDS.get(cmd, ("unknown", ()))[0]
        if cmd in (1, 3):
            args = {"target": d[:6].copy(), "speed": d[6], "acceleration": d[7], "async": is_async}
        elif cmd in (36, 37):
            args = {"target": d[:6].copy()}
        elif cmd in (33, 34):
            args = {"deceleration": d[0], "async": is_async}
        elif cmd == 35:
            args = {"min_frequency_hz": d[0]}
        elif cmd == 29:
            args = {"tcp": d[:6].copy()}
        else:
            args = {}
        self.commands.append(ScriptCommand(cmd, name, args, self._command_recipe))
        sc = self._script
        if cmd in (1, 3, 33, 34) and self._motion is not None and self._motion.is_async:
            self._write_async_progress(-1)  # stop_async_move(): the running async move is killed
        if cmd in (1, 3):  # a target outside the safety limits: a runtime error, the program stops, the arm stays
            q_end = d[:6] if cmd == 1 else self._pose_target_joints(d[:6])
            if q_end is None or not self.within_safety_limits(q_end):
                self._end_program(f"runtime error: {name}: target {np.round(d[:6], 4).tolist()} is outside the "
                                  "safety limits or out of reach")
                return
        if cmd == 1:
            self._start_motion(_JointMotion(self._q.copy(), d[:6].copy(), d[6], d[7], is_async), is_async)
        elif cmd in (36, 37):
            q_end = d[:6] if cmd == 37 else self._pose_target_joints(d[:6])
            self._out_int[sc.reg_offset + 1] = int(q_end is not None and self.within_safety_limits(q_end))
        elif cmd == 3:
            base_from_tcp0 = np.asarray(self.model.fk(self._q)) @ self._flange_from_tcp
            motion = _LinearMotion(base_from_tcp0, pose_to_matrix(d[:6]), self._q.copy(), d[6], d[7],
                                   self._flange_from_tcp.copy(), is_async)
            self._start_motion(motion, is_async)
        elif cmd in (33, 34):  # an async stop runs as an async operation of its own (the script's stop_thread)
            self._start_motion(_StopMotion(self._q.copy(), self._qd.copy(), d[0], is_async), is_async)
        elif cmd == 29:
            self._flange_from_tcp = pose_to_matrix(d[:6])
        elif cmd == 31:
            self.protective_stop("protective_stop() called by the script")
        elif cmd == 35:
            self._watchdog_var = f"input_int_register_{sc.reg_offset}"
            self._watchdog_period_s = 1.0 / d[0] if d[0] > 0 else float("inf")
            self._watchdog_last = time.monotonic()
        elif cmd == 255:
            self._end_program("stop script command")
        else:
            self._end_program(f"command {cmd} is not played by the loopback controller")
        if self.after_command is not None:
            self.after_command(self.commands[-1])

    def _start_motion(self, motion, is_async: bool) -> None:
        self._motion, self._motion_elapsed = motion, 0.0
        if is_async:
            self._write_async_progress(0)
        else:
            self._script.blocking = True

    # ------------------------------------------------------------ RTDE outputs
    def _output_values(self) -> dict:
        base_from_tcp = np.asarray(self.model.fk(self._q)) @ self._flange_from_tcp
        pose = matrix_to_pose(base_from_tcp)
        running = self._runtime == PLAYING
        zeros6 = np.zeros(6)
        values = {
            "timestamp": self._t, "target_q": self._q, "actual_q": self._q,
            "target_qd": self._qd, "actual_qd": self._qd, "target_qdd": zeros6, "actual_qdd": zeros6,
            "target_current": zeros6, "actual_current": zeros6, "target_moment": zeros6, "actual_moment": zeros6,
            "joint_control_output": zeros6, "actual_TCP_pose": pose, "target_TCP_pose": pose,
            "actual_TCP_speed": zeros6, "target_TCP_speed": zeros6, "actual_TCP_force": zeros6,
            "actual_digital_input_bits": 0, "actual_digital_output_bits": 0,
            "joint_temperatures": np.full(6, 30.0), "actual_execution_time": 0.1,
            "robot_mode": ROBOT_MODE_RUNNING, "joint_mode": [JOINT_MODE_RUNNING] * 6,
            "safety_mode": self._safety_mode, "safety_status": self._safety_mode,
            "actual_tool_accelerometer": (0.0, 0.0, -9.81), "speed_scaling": self.speed_scaling,
            "target_speed_fraction": self.speed_slider,
            "actual_momentum": 0.0, "actual_main_voltage": 48.0, "actual_robot_voltage": 48.0,
            "actual_robot_current": 0.5, "actual_joint_voltage": np.full(6, 48.0),
            "runtime_state": self._runtime, "robot_status_bits": 0b1 | (0b10 if running else 0),
            "safety_status_bits": self._safety_bits,
            "standard_analog_input0": 0.0, "standard_analog_input1": 0.0,
            "standard_analog_output0": 0.0, "standard_analog_output1": 0.0,
            "ft_raw_wrench": zeros6, "payload": 0.0, "payload_cog": (0.0, 0.0, 0.0), "payload_inertia": zeros6,
            "elbow_position": (0.0, 0.0, 0.0), "elbow_velocity": (0.0, 0.0, 0.0),
            "output_bit_registers0_to_31": 0, "output_bit_registers32_to_63": 0,
        }
        for i in range(48):
            values[f"output_int_register_{i}"] = int(self._out_int[i])
            values[f"output_double_register_{i}"] = float(self._out_double[i])
        return values

    def _publish(self, values: dict) -> None:
        for session in list(self._sessions):
            if session.started and session.output is not None:
                try:
                    session.send(session.output.pack_values(values))
                except OSError:
                    session.started = False

    # ------------------------------------------------------------ servers
    def _serve_rtde(self, conn, service: rp.TcpService) -> None:
        session = _RtdeSession(conn)
        with self._lock:
            self._sessions.append(session)
        try:
            while service.wait_readable(conn):
                kind, payload = rp.read_package(conn)
                self._handle_rtde(session, kind, payload)
        finally:
            with self._lock:
                self._sessions.remove(session)

    def _handle_rtde(self, session: _RtdeSession, kind: int, payload: bytes) -> None:
        if kind == rp.REQUEST_PROTOCOL_VERSION:
            version = struct.unpack(">H", payload[:2])[0]
            session.send(rp.pack(kind, bytes([1 if version in (1, 2) else 0])))
        elif kind == rp.GET_URCONTROL_VERSION:
            session.send(rp.pack(kind, struct.pack(">IIII", *self.controller_version)))
        elif kind == rp.SETUP_OUTPUTS:
            names = rp.split_names(payload[8:])
            recipe = rp.Recipe.make(1, names, rp.OUTPUT_TYPES)
            session.output = recipe if recipe.valid else None
            session.send(rp.pack(kind, recipe.setup_reply()))
        elif kind == rp.SETUP_INPUTS:
            names = rp.split_names(payload)
            recipe = rp.Recipe.make(len(session.inputs) + 1, names, rp.INPUT_TYPES)
            if recipe.valid:
                session.inputs[recipe.recipe_id] = recipe
                with self._lock:
                    self.input_recipes.append(recipe.names)
            session.send(rp.pack(kind, recipe.setup_reply()))
        elif kind == rp.START:
            session.started = session.output is not None
            session.send(rp.pack(kind, bytes([1 if session.started else 0])))
        elif kind == rp.PAUSE:
            session.started = False
            session.send(rp.pack(kind, b"\x01"))
        elif kind == rp.DATA_PACKAGE:
            recipe = session.inputs.get(payload[0])
            if recipe is None:
                raise rp.ProtocolError(f"data package for unknown input recipe {payload[0]}")
            values = recipe.unpack_values(payload)
            with self._lock:
                self._inputs.update(values)
                offset = self._script.reg_offset if self._script is not None else 0
                if values.get(f"input_int_register_{offset}", 0) != 0:
                    self._command_recipe = recipe.names
                if values.get("speed_slider_mask") == 1 and "speed_slider_fraction" in values:
                    self.speed_slider = float(np.clip(values["speed_slider_fraction"], 0.0, 1.0))
                if self._watchdog_var is not None and self._watchdog_var in values:
                    self._watchdog_last = time.monotonic()
        else:
            raise rp.ProtocolError(f"unknown RTDE package type {kind}")

    def _serve_dashboard(self, conn, service: rp.TcpService) -> None:
        conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
        buffer = b""
        while service.wait_readable(conn):
            chunk = conn.recv(4096)
            if not chunk:
                return
            buffer += chunk
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                reply = self._dashboard(line.decode("ascii", "replace").strip())
                conn.sendall(reply.encode() + b"\n")
                if reply == "Disconnected":
                    return

    def _dashboard(self, line: str) -> str:
        cmd = line.lower()
        if cmd == "polyscopeversion":
            return f"URSoftware {self.polyscope_version} (Mar 22 2022)"
        if cmd == "get serial number":
            return self.serial_number
        if cmd == "is in remote control":
            return "true" if self.remote_control else "false"
        if cmd == "get robot model":
            return "UR5"
        if cmd == "robotmode":
            return f"Robotmode: {self.robot_mode}"
        if cmd == "power on":
            if self.robot_mode == "POWER_OFF":
                self.robot_mode = "IDLE"
            return "Powering on"
        if cmd == "brake release":
            if self.robot_mode == "IDLE":
                self.robot_mode = "RUNNING"
            return "Brake releasing"
        if cmd == "power off":
            self.robot_mode = "POWER_OFF"
            return "Powering off"
        if cmd == "safetystatus":
            names = {SAFETY_NORMAL: "NORMAL", SAFETY_PROTECTIVE_STOP: "PROTECTIVE_STOP",
                     SAFETY_ROBOT_EMERGENCY_STOP: "ROBOT_EMERGENCY_STOP"}
            return f"Safetystatus: {names.get(self._safety_mode, 'FAULT')}"
        if cmd == "running":
            return f"Program running: {'true' if self._runtime == PLAYING else 'false'}"
        if cmd == "programstate":
            return f"{'PLAYING' if self._runtime == PLAYING else 'STOPPED'} rtde_control"
        if cmd == "stop":
            with self._lock:
                self._end_program("dashboard stop")
            return "Stopped"
        if cmd == "unlock protective stop":
            return "Protective stop releasing" if self.unlock_protective_stop() else "Cannot unlock protective stop"
        if cmd.startswith("sim refuse targets "):  # the emulator's own injection channel (not a UR command)
            try:
                q = np.asarray(json.loads(line[len("sim refuse targets "):]), dtype=float).reshape(-1, 6)
            except (ValueError, TypeError):
                return "sim refuse targets: expected a JSON list of 6-joint lists"
            self.refuse_targets(q)
            return f"Refusing {len(q)} targets"
        if cmd == "close safety popup":
            return "closing safety popup"
        if cmd == "quit":
            return "Disconnected"
        return f"could not understand: '{line}'"

    def _serve_script(self, conn, service: rp.TcpService) -> None:
        buffer = ""
        while service.wait_readable(conn):
            chunk = conn.recv(65536)
            if not chunk:
                return
            buffer += chunk.decode("utf-8", "replace")
            while True:
                m = re.search(r"^def \w+\(\):\n.*?^end[ \t]*\n", buffer, flags=re.M | re.S)
                if m is None:
                    break
                program, buffer = m.group(0), buffer[m.end():]
                with self._lock:
                    if not self.remote_control:  # local mode: a real e-Series drops its clients on 30001-30003
                        self.messages.append("program refused: the robot is in local control")
                        return
                    self.uploaded_scripts.append(program)
                    self._halt()
                    if self._script is not None:
                        self._end_program("replaced by a new program")
                    self._pending_program = program


def refuse_targets_at(host: str, joints_rad, timeout_s: float = 5.0) -> None:
    """Tell the loopback controller at ``host`` (another process) to refuse the joint targets ``(n, 6)``.

    Uses the emulator-only dashboard command ``sim refuse targets``; ``OSError`` / ``ValueError`` when
    ``host`` is not a loopback address or the controller there does not understand it (a real one does not).
    """
    if not ipaddress.ip_address(host).is_loopback:
        raise ValueError(f"{host} is not a loopback address: only the loopback UR controller takes injected targets")
    q = np.asarray(joints_rad, dtype=float).reshape(-1, 6)
    with socket.create_connection((host, DASHBOARD_PORT), timeout=timeout_s) as conn:
        f = conn.makefile("rwb")
        f.readline()  # the greeting
        f.write(b"sim refuse targets " + json.dumps(q.tolist()).encode() + b"\n")
        f.flush()
        reply = f.readline().decode("ascii", "replace").strip()
    if reply != f"Refusing {len(q)} targets":
        raise ValueError(f"the controller at {host} did not take the refused targets: {reply!r}")


class _RtdeSession:
    """One RTDE client connection: its output recipe, input recipes, started flag."""

    def __init__(self, conn):
        self.conn = conn
        self.output: rp.Recipe | None = None
        self.inputs: dict[int, rp.Recipe] = {}
        self.started = False
        self._send_lock = threading.Lock()

    def send(self, data: bytes) -> None:
        with self._send_lock:
            self.conn.sendall(data)
