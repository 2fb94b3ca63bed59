"""The child process of :class:`drivers.ur.URRobot`: the ur-rtde client lives here.

Run as ``python -m drivers.ur_worker FD`` where FD is one end of a socket pair
wrapped as a ``multiprocessing.connection.Connection``. Requests are dicts with an
``op`` and a ``seq``; each gets one reply ``{"ok": True, "value": ..., "seq": ...}`` or
``{"ok": False, "error": <name of a DriverError subclass>, "message": ..., "seq": ...}``.

A stop comes as a signal, not a message, so that it reaches the arm at once whatever
this process is doing: ``SIGUSR1`` (sent by ``URRobot.signal_stop``) and ``SIGTERM``
set a flag that the move loop (every few ms) and the idle loop look at; the arm is
then stopped (``stopj``) and the move answered "stopped on request". The flag stays
set, refusing any further move, until the parent's ``stop`` request has run (it
answers with the state at rest and when the arm came to rest). ``SIGINT`` is ignored:
a Ctrl-C is the parent's to handle (this process also runs in a session of its own).

Moves are sent asynchronously to the controller; the child then polls the RTDE
state until the arm is at the target, checking on every poll: an interrupt from
the parent, the safety bits, the program's runtime state, the freshness of the
RTDE timestamp, the speed the arm is let to run at (``speed_scaling`` x
``target_speed_fraction``: at 0 for longer than a short grace the move is stopped
and named), and the move's deadline; and it kicks the controller's watchdog,
as it does while idle. When the pipe closes, the child exits at once.

Before sending a move it also refuses one the arm could not make: the pendant's
speed slider (``target_speed_fraction``) at or near 0, or a robot in local control
(the dashboard's ``is in remote control``, asked through ur-rtde's
``DashboardClient.isInRemoteControl()`` on PolyScope 5.6 and later, the versions
that answer it). Decision 0063.
"""
from __future__ import annotations

import math
import os
import signal
import sys
import time
from multiprocessing.connection import Connection

from drivers.motion import arm_moved, describe_change, joint_change_rad

BIT_PROTECTIVE_STOP, BIT_ROBOT_ESTOP, BIT_ESTOP = 2, 6, 7
RUNTIME_PLAYING = 2
RECEIVE_VARIABLES = ["timestamp", "actual_q", "actual_qd", "actual_TCP_pose", "safety_status_bits",
                     "runtime_state", "robot_mode", "safety_mode", "speed_scaling", "target_speed_fraction"]
#: a speed fraction below this is "at 0": the pendant's slider (target_speed_fraction) before a move, and the speed the
#: arm is let to run at (speed_scaling x target_speed_fraction) during one
SPEED_ZERO = 0.01
#: the dashboard answers ``is in remote control`` from PolyScope 5.6 on (ur-rtde asks it only there, as here)
REMOTE_QUERY_SINCE = (5, 6)
LOCAL_CONTROL = "the robot is in local control (dashboard 'is in remote control': false)"
LOCAL_CONTROL_LINE = (f"{LOCAL_CONTROL}: switch the teach pendant from Local to Remote control, then resume the job; "
                      "nothing was sent and the arm did not move")
RUNTIME_NAMES = {0: "stopping", 1: "stopped", 2: "playing", 3: "pausing", 4: "paused", 5: "resuming"}


#: ur-rtde error texts that mean the socket to the controller is gone (not a refused command).
_CONNECTION_LOST = ("broken pipe", "connection reset", "connection refused", "not connected", "end of file",
                    "bad file descriptor")

class _Fail(Exception):
    """A failure to send back: ``kind`` names a ``calibration.errors`` class."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind, self.message = kind, message


def slider_problem(state: dict) -> str | None:
    """The one line that refuses a move when the pendant's speed slider is at (or near) 0, else None."""
    fraction = state.get("target_speed_fraction")
    if fraction is None or fraction >= SPEED_ZERO:
        return None
    return (f"the speed slider on the teach pendant stands at {100 * fraction:.0f}% (RTDE target_speed_fraction "
            f"{fraction:.3f}): the arm would not move; push the slider up (100% for the planned cycle time), then "
            "resume the job; nothing was sent and the arm did not move")


def standstill_line(state: dict, held_s: float) -> str:
    """The one line that ends a move whose speed stood at 0 (slider pulled down, or the controller's scaling)."""
    fraction, scaling = state["target_speed_fraction"], state["speed_scaling"]
    if fraction < SPEED_ZERO:
        return (f"the speed slider on the teach pendant was pulled down to {100 * fraction:.0f}% during the move "
                f"(target_speed_fraction {fraction:.3f} for {held_s:.1f} s): the arm stood still; the move was "
                "stopped and is not resumed: push the slider up, then resume the job")
    return (f"the controller's speed scaling stood at {scaling:.3f} for {held_s:.1f} s during the move (RTDE "
            f"speed_scaling; slider at {100 * fraction:.0f}%): the arm stood still (a stop, a safety limit or a "
            "paused program); the move was stopped and is not resumed: check the pendant, then resume the job")


def _version_tuple(text: str) -> tuple[int, ...]:
    parts = []
    for piece in text.strip().split("."):
        if not piece.isdigit():
            break
        parts.append(int(piece))
    return tuple(parts)


def _rotvec_angle_between(a, b) -> float:
    """Angle (rad) between two rotations given as rotation vectors ``(3,)``."""
    def quat(r):
        th = math.sqrt(sum(x * x for x in r))
        if th < 1e-12:
            return (1.0, 0.0, 0.0, 0.0)
        s = math.sin(th / 2) / th
        return (math.cos(th / 2), r[0] * s, r[1] * s, r[2] * s)

    qa, qb = quat(a), quat(b)
    dot = abs(sum(x * y for x, y in zip(qa, qb)))
    return 2.0 * math.acos(min(1.0, dot))


class Worker:
    def __init__(self, conn: Connection):
        self.conn = conn
        self.ctrl = None
        self.rcv = None
        self.db = None  # ur-rtde's DashboardClient (port 29999): the remote-control question
        self.polyscope: tuple[int, ...] = ()
        self.opts: dict = {}
        self._last_ts = None
        self._last_change = 0.0
        self._last_kick = 0.0
        self.stop_requested = False  # set by SIGUSR1 / SIGTERM, cleared by the parent's "stop" request
        self.last_rest: dict | None = None
        self._pending: list[dict] = []  # requests read during a move, answered after it
        self._eof = False
        self._stop_done = False  # the signalled stop was carried out (last_rest says when the arm came to rest)

    def _on_stop_signal(self, signum, frame) -> None:
        # one abort may signal more than once (handler, runner, stop()): a repeat while the stop is pending must not
        # send a second stopj to an arm at rest, nor replace the rest time the first one measured
        if not self.stop_requested:
            self.stop_requested, self._stop_done = True, False

    # ------------------------------------------------------------ main loop
    def run(self) -> None:
        while True:
            if self._pending:
                msg = self._pending.pop(0)
            else:
                try:
                    period = self._kick_period() if self.ctrl is not None else 1.0
                    if not self.conn.poll(period):
                        self._idle()
                        continue
                    msg = self.conn.recv()
                except (EOFError, OSError):
                    self._parent_gone()
            op = msg.get("op")
            try:
                handler = getattr(self, f"op_{op}", None)
                if handler is None:
                    raise _Fail("DriverError", f"unknown request {op!r}")
                reply = {"ok": True, "value": handler(msg)}
            except _Fail as exc:
                reply = {"ok": False, "error": exc.kind, "message": exc.message}
            except (RuntimeError, ValueError, TypeError) as exc:  # ur-rtde raises these
                # a socket torn down under ur-rtde surfaces as e.g. "write: Broken pipe": the connection is lost
                lost = any(s in str(exc).lower() for s in _CONNECTION_LOST)
                reply = {"ok": False, "error": "NotConnectedError" if lost else "DriverError",
                         "message": f"ur-rtde: {exc}" + ("; the connection to the robot was lost" if lost else "")}
            reply["seq"] = msg.get("seq")
            try:
                self.conn.send(reply)
            except (OSError, ValueError):
                os._exit(0)
            if op == "close":
                sys.stdout.flush()
                os._exit(0)

    def _kick_period(self) -> float:
        return 0.25 / self.opts["watchdog_hz"]

    def _parent_gone(self) -> None:
        """The pipe closed (the parent ended, maybe killed mid-move): stop the arm, then leave.

        No teardown of the client (it has crashed tearing down during a reconnect), just exit.
        """
        if self.rcv is not None:
            self._try_stop()
        os._exit(0)

    def _idle(self) -> None:
        if self.rcv is None:
            return
        if self.stop_requested and not self._stop_done:
            self._try_stop()
            self._stop_done = True
        try:
            self._kick()
        except _Fail:
            pass  # reported on the next request

    def _kick(self) -> None:
        """Kick the controller's watchdog if due (only while the program runs: else it would just fail)."""
        now = time.monotonic()
        if now - self._last_kick < self._kick_period():
            return
        if self.rcv.getRuntimeState() == RUNTIME_PLAYING and not self._stopped_bits():
            self.ctrl.kickWatchdog()
        self._last_kick = now

    # ------------------------------------------------------------ state
    def _stopped_bits(self) -> int:
        bits = int(self.rcv.getSafetyStatusBits())
        return bits & ((1 << BIT_PROTECTIVE_STOP) | (1 << BIT_ESTOP) | (1 << BIT_ROBOT_ESTOP))

    def _state(self) -> dict:
        """The latest RTDE reading; ``NotConnectedError`` if its timestamp has stopped advancing."""
        if self.rcv is None:
            raise _Fail("NotConnectedError", "not connected; call connect()")
        ts = float(self.rcv.getTimestamp())
        now = time.monotonic()
        if ts != self._last_ts:
            self._last_ts, self._last_change = ts, now
        elif now - self._last_change > self.opts["stale_after_s"]:
            raise _Fail("NotConnectedError",
                        f"RTDE data stale: controller timestamp {ts:.3f} s has not advanced for "
                        f"{now - self._last_change:.2f} s (connection lost?); call connect() once the link is back")
        return {"timestamp": ts, "q": list(self.rcv.getActualQ()), "qd": list(self.rcv.getActualQd()),
                "pose": list(self.rcv.getActualTCPPose()), "safety_bits": int(self.rcv.getSafetyStatusBits()),
                "runtime_state": int(self.rcv.getRuntimeState()),
                "speed_scaling": float(self.rcv.getSpeedScaling()),
                "target_speed_fraction": float(self.rcv.getTargetSpeedFraction())}

    def _in_remote_control(self) -> bool | None:
        """The dashboard's ``is in remote control`` (None: this PolyScope does not answer it, nor has the mode)."""
        if self.db is None or self.polyscope < REMOTE_QUERY_SINCE or self.polyscope[0] != 5:
            return None
        for attempt in (1, 2):
            try:
                return bool(self.db.isInRemoteControl())
            except RuntimeError as exc:  # the dashboard connection dropped: one new connection, then it is a fault
                if attempt == 2:
                    raise _Fail("NotConnectedError", f"the dashboard server (port 29999) did not answer 'is in "
                                f"remote control' ({exc}); nothing was sent") from None
                try:
                    self.db.connect()
                except RuntimeError:
                    pass
        return None

    def _check_ready(self, state: dict) -> None:
        """Refuse a move the arm could not make: the pendant's slider at 0, or the robot in local control."""
        problem = slider_problem(state)
        if problem is not None:
            raise _Fail("MotionError", problem)
        if self._in_remote_control() is False:
            raise _Fail("MotionError", LOCAL_CONTROL_LINE)

    @staticmethod
    def _check_safe(state: dict, when: str) -> None:
        bits = state["safety_bits"]
        if bits & ((1 << BIT_ESTOP) | (1 << BIT_ROBOT_ESTOP)):
            raise _Fail("ProtectiveStopError", f"emergency stop {when} (safety_status_bits={bits:#x}); release it, "
                        "check the cell, then reconnect; the move is not resumed")
        if bits & (1 << BIT_PROTECTIVE_STOP):
            raise _Fail("ProtectiveStopError", f"protective stop {when} (safety_status_bits={bits:#x}); "
                        "unlock it on the pendant, check the cell, then reconnect; the move is not resumed")
        rs = state["runtime_state"]
        if rs != RUNTIME_PLAYING:
            raise _Fail("MotionError", f"the control script is not running on the controller {when} "
                        f"(runtime_state={rs}, {RUNTIME_NAMES.get(rs, '?')}); nothing more is sent; "
                        "check the pendant log, then reconnect to upload the script again")

    def _wait_fresh(self, timeout_s: float) -> dict:
        end = time.monotonic() + timeout_s
        first = float(self.rcv.getTimestamp())
        while float(self.rcv.getTimestamp()) == first:
            if time.monotonic() > end:
                raise _Fail("NotConnectedError", f"no new RTDE data within {timeout_s:.1f} s (connection lost?)")
            time.sleep(0.002)
        return self._state()

    # ------------------------------------------------------------ operations
    def op_connect(self, msg: dict) -> dict:
        self.opts = msg
        import dashboard_client
        import rtde_control
        import rtde_receive

        host, freq = msg["host"], float(msg["frequency_hz"])
        try:
            # first the dashboard: local control is named here (ur-rtde's control interface would refuse it with
            # "Please enable remote control", and not at all for 127.0.0.1)
            self.db = dashboard_client.DashboardClient(host)
            self.db.connect()
            self.polyscope = _version_tuple(self.db.polyscopeVersion())
            if self._in_remote_control() is False:
                raise _Fail("NotConnectedError", f"{LOCAL_CONTROL}: switch the teach pendant from Local to Remote "
                            "control, then connect again (ur-rtde uploads its control script only in remote control)")
            self.ctrl = rtde_control.RTDEControlInterface(host, freq)
            self.rcv = rtde_receive.RTDEReceiveInterface(host, freq, RECEIVE_VARIABLES)
        except RuntimeError as exc:
            raise _Fail("NotConnectedError", f"ur-rtde could not connect to {host}: {exc}") from None
        state = self._wait_fresh(2.0)
        self._check_safe(state, "after connecting")
        if not self.ctrl.setTcp([0.0] * 6):
            raise _Fail("DriverError", "setTcp([0]*6) failed: the flange is the TCP of this driver")
        if not self.ctrl.setWatchdog(float(msg["watchdog_hz"])):
            raise _Fail("DriverError", "arming the controller's RTDE watchdog failed")
        self._last_kick = time.monotonic()
        return self._state()

    def op_state(self, msg: dict) -> dict:
        return self._state()

    def op_close(self, msg: dict) -> None:
        if self.ctrl is not None and self.rcv is not None and self.rcv.getRuntimeState() == RUNTIME_PLAYING:
            self.ctrl.stopScript()
        return None

    def op_stop(self, msg: dict) -> dict:
        """Stop (if not yet at rest) and answer the state at rest; clears a signalled stop."""
        if self.stop_requested and self._stop_done:
            rest = self.last_rest  # stopped already, when the signal came
        else:
            rest = self._try_stop()
        self.stop_requested, self._stop_done = False, False
        state = self._state()
        if rest is not None:
            state["rest"] = rest
        return state

    def op_move_joints(self, msg: dict) -> dict:
        return self._move(msg, joint_space=True)

    def op_move_pose(self, msg: dict) -> dict:
        return self._move(msg, joint_space=False)

    def _try_stop(self) -> dict | None:
        """Decelerate to rest (async stop, kicked and bounded); never raises.

        Returns when the arm came to rest: ``{"controller_timestamp_s", "after_s"}`` (controller
        clock, and wall seconds from the stop being sent), or None if no stop was sent (the arm
        was already halted by the controller, or the link is gone).
        """
        try:
            state = self._state()
            if state["runtime_state"] != RUNTIME_PLAYING or self._stopped_bits():
                return None
            t_sent = time.monotonic()
            self.ctrl.stopJ(float(self.opts["stop_decel"]), True)
            end = t_sent + 2.0 + max(abs(v) for v in state["qd"]) / float(self.opts["stop_decel"])
            while time.monotonic() < end:  # the async stop is an async operation: wait for its end
                self._kick()
                state = self._state()
                if not self.ctrl.getAsyncOperationProgressEx().isAsyncOperationRunning() and \
                        max(abs(v) for v in state["qd"]) < 1e-4:
                    self.last_rest = {"controller_timestamp_s": state["timestamp"],
                                      "after_s": time.monotonic() - t_sent}
                    return self.last_rest
                time.sleep(0.004)
        except (_Fail, RuntimeError):
            return None
        return None

    def _move(self, msg: dict, joint_space: bool) -> dict:
        target, speed, accel = list(msg["target"]), float(msg["speed"]), float(msg["accel"])
        deadline = time.monotonic() + float(msg["deadline_s"])
        if self.stop_requested:
            raise _Fail("MotionError", "move refused: a stop was requested and not yet acknowledged")
        state = self._state()
        self._check_safe(state, "before the move")
        self._check_ready(state)
        self._check_target(target, joint_space, state)
        if self.stop_requested:
            raise _Fail("MotionError", "move refused: a stop was requested and not yet acknowledged")
        sent = (self.ctrl.moveJ(target, speed, accel, True) if joint_space
                else self.ctrl.moveL(target, speed, accel, True))
        if not sent:
            # the receive interface's stream may be a packet behind the control interface's, which saw the failure
            state = self._wait_fresh(0.5)
            self._check_safe(state, "when the move was sent")
            raise _Fail("MotionError", "the controller did not accept the move (ur-rtde returned False)")
        grace = float(self.opts.get("speed_zero_grace_s", 0.5))
        still_since = None  # when the speed the arm is let to run at fell to 0
        slowest = 1.0  # the least target_speed_fraction seen, for the deadline's message
        while True:
            if self.stop_requested or self._parent_closed():
                self.last_rest = None
                self._try_stop()
                self._stop_done = True
                if self._eof:
                    self._parent_gone()
                raise _Fail("MotionError", "move stopped on request before reaching its target")
            self._kick()
            state = self._state()
            self._check_safe(state, "during the move")
            if not self.ctrl.getAsyncOperationProgressEx().isAsyncOperationRunning() and \
                    self._arrived(state, target, joint_space):
                return state
            now = time.monotonic()
            slowest = min(slowest, state["target_speed_fraction"])
            if state["speed_scaling"] * state["target_speed_fraction"] >= SPEED_ZERO:
                still_since = None
            elif still_since is None:
                still_since = now
            elif now - still_since > grace:
                self._try_stop()
                raise _Fail("MotionError", standstill_line(state, now - still_since))
            if now > deadline:
                self._try_stop()
                slider = (f" (the pendant's speed slider went down to {100 * slowest:.0f}% during it)"
                          if slowest < 0.995 else "")
                raise _Fail("MotionError", f"move did not reach its target within its deadline of "
                            f"{msg['deadline_s']:.2f} s{slider}; the arm was stopped")
            time.sleep(0.004)

    def _check_target(self, target: list, joint_space: bool, before: dict) -> None:
        """Ask the controller whether it will take the target (``is_within_safety_limits``: joint limits, safety
        planes, tool orientation limits, reach); ``MoveRefusedError`` only for its own "no" with the arm where it was.

        ur-rtde answers False also when the command could not run (a stop, the program not running, no answer):
        those are faults, told apart by the state after the answer and by asking the same about the arm's own
        joints, which a working check must accept.
        """
        ok = (self.ctrl.isJointsWithinSafetyLimits(target) if joint_space
              else self.ctrl.isPoseWithinSafetyLimits(target))
        if ok:
            return
        state = self._wait_fresh(0.5)  # a packet newer than the one the answer came with (another RTDE stream)
        self._check_safe(state, "when the controller checked the target")
        if not self.ctrl.isJointsWithinSafetyLimits(state["q"]):
            self._check_safe(self._state(), "when the controller checked the target")
            raise _Fail("MotionError", "the controller's safety-limit check refuses even the arm's own joints: it "
                        "does not answer as it should; nothing was sent, check the pendant log")
        if arm_moved(before["q"], state["q"]):
            moved = describe_change(joint_change_rad(before["q"], state["q"]))
            raise _Fail("MotionError", f"the arm moved {moved} while the controller checked the target "
                        "(nothing was sent): the job stops")
        if self.stop_requested:  # an abort that came during the check wins over the refusal (nothing was sent)
            raise _Fail("MotionError", "move refused: a stop was requested and not yet acknowledged")
        kind = "joints" if joint_space else "pose"
        raise _Fail("MoveRefusedError", f"the controller refused the move: target {kind} "
                    f"{[round(v, 4) for v in target]} is outside its safety limits or reach "
                    "(is_within_safety_limits: false); nothing was sent and the arm did not move")

    def _arrived(self, state: dict, target: list, joint_space: bool) -> bool:
        tol = float(self.opts["position_tol"])
        if max(abs(v) for v in state["qd"]) > 1e-3:
            return False
        if joint_space:
            return max(abs(a - b) for a, b in zip(state["q"], target)) <= tol
        pose = state["pose"]
        if math.dist(pose[:3], target[:3]) > tol:
            return False
        return _rotvec_angle_between(pose[3:], target[3:]) <= float(self.opts["orientation_tol"])

    def _parent_closed(self) -> bool:
        """True once the parent's end of the pipe is closed (the parent sends nothing during a move)."""
        try:
            if not self.conn.poll(0):
                return False
        except (EOFError, OSError):
            self._eof = True
            return True
        # a request during a move: the parent gave up waiting for it (an abort unwound its wait) and asks
        # for something else, normally a stop. Keep it for the main loop; a stop request also stops this move
        try:
            msg = self.conn.recv()
        except (EOFError, OSError):
            self._eof = True
            return True
        self._pending.append(msg)
        if msg.get("op") in ("stop", "close"):
            self.stop_requested = True
        return False


def main(argv: list[str]) -> None:
    worker = Worker(Connection(int(argv[1])))
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGUSR1, worker._on_stop_signal)
    signal.signal(signal.SIGTERM, worker._on_stop_signal)
    worker.run()


if __name__ == "__main__":
    main(sys.argv)
