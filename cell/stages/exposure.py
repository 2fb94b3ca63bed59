"""One triggered exposure at a station: wait until the arm has settled, trigger the camera with the light
pulsing in the exposure, and tie the frame to the robot state at the frame's instant.

Settling is judged on the controller's clock: every joint slower than ``speed_tol_rad_s`` (the RTDE
``actual_qd`` where the robot reports speeds, else the change between successive readings) without a
break for ``hold_s``. The frame must come after its trigger and within ``exposure + frame_timeout`` of it,
must not repeat a frame already taken (same frame id, or a timestamp not after the previous frame's),
and the arm must not have moved between the settled reading and the reading after the frame. Its size must be
the job's camera's (``frame_size``; without it, the session's first frame's): binning or an ROI changed behind the
cell would put every image point elsewhere. The light controller's pulse settings are read back before each
exposure (one that lost them, a power blip, is re-armed and that is said through ``on_notice``) and after it: a
frame taken while the light was not armed may be unlit. Anything else is a :class:`FrameFault` naming the station
and what went wrong; the caller retakes the station, so a frame is never stored as another station's.
"""
from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from calibration.errors import DriverError, NotConnectedError
from drivers.motion import arm_moved, describe_change, joint_change_rad
from drivers.protocols import Frame, RobotState

POLL_S = 0.008  # 125 Hz: the UR's RTDE rate


class FrameFault(DriverError):
    """The station's frame came late, twice, never, before its trigger, or while the arm moved."""

    def __init__(self, outcome: str, message: str):
        super().__init__(message)
        self.outcome = outcome


@dataclass
class Exposure:
    """What the run log keeps of one exposure (``/camera/exposure``)."""

    station: str
    attempt: int
    outcome: str
    detail: str
    trigger_host_s: float
    light: str
    frame_host_s: float | None = None
    frame_id: int | None = None
    device_timestamp_ns: int | None = None
    latency_s: float | None = None
    exposure_s: float | None = None
    robot_timestamp_s: float | None = None
    joints_rad: list | None = None
    settled_for_s: float | None = None
    max_joint_speed_rad_s: float | None = None
    light_note: str | None = None  # the light controller had lost its settings and was re-armed before this exposure
    frame_size: list | None = None  # [width, height] of the frame delivered

    def as_dict(self) -> dict:
        return asdict(self)


def wait_settled(robot, *, speed_tol_rad_s: float, hold_s: float, timeout_s: float, station: str = "",
                 poll_s: float = POLL_S) -> tuple[RobotState, float, float]:
    """Poll the robot until it has been still for ``hold_s`` (controller time).

    Returns ``(state, host_time_of_state, largest joint speed seen in the window)``. Raises
    ``DriverError`` when it does not settle within ``timeout_s`` (host time), or on a safety stop.
    """
    start = time.monotonic()
    prev = robot.state()
    still_since = prev.timestamp_s if _speed(prev, None) < speed_tol_rad_s else None
    peak = 0.0
    worst = _speed(prev, None)
    while True:
        if not prev.safety.normal:
            raise DriverError(f"station {station}: robot not in normal mode while settling ({prev.safety.detail})")
        if still_since is not None and prev.timestamp_s - still_since >= hold_s:
            return prev, time.time(), peak
        if time.monotonic() - start > timeout_s:
            raise DriverError(f"station {station}: the arm did not settle within {timeout_s:.1f} s (joint speed "
                              f"{worst:.4f} rad/s, limit {speed_tol_rad_s} rad/s held for {hold_s} s)")
        time.sleep(poll_s)
        cur = robot.state()
        v = _speed(cur, prev)
        worst = v
        if v < speed_tol_rad_s:
            if still_since is None:
                still_since = cur.timestamp_s
            peak = max(peak, v)
        else:
            still_since, peak = None, 0.0
        prev = cur


def _speed(cur: RobotState, prev: RobotState | None) -> float:
    """Largest joint speed of a reading: reported, or from the previous reading (inf when unknown)."""
    if cur.joint_speeds_rad_s is not None:
        return float(np.max(np.abs(cur.joint_speeds_rad_s)))
    if prev is None or cur.timestamp_s <= prev.timestamp_s:
        return 0.0 if prev is not None and np.allclose(cur.joints_rad, prev.joints_rad, atol=1e-9) else float("inf")
    return float(np.max(np.abs(np.asarray(cur.joints_rad) - prev.joints_rad)) / (cur.timestamp_s - prev.timestamp_s))


class ExposureTaker:
    """Takes the exposures of one session; remembers the frames taken so that none is used twice."""

    def __init__(self, robot, camera, light, *, exposure_s: float, frame_timeout_s: float, light_by_line: bool,
                 frame_size: tuple[int, int] | None = None, on_notice: Callable[[str, str], None] | None = None):
        """``frame_size``: ``(width, height)`` of the job's camera (None: the first frame's); ``on_notice(station,
        line)``: says what the light controller was found in and re-armed from (None: the line goes to stderr)."""
        self.robot, self.camera, self.light = robot, camera, light
        self.exposure_s, self.frame_timeout_s = float(exposure_s), float(frame_timeout_s)
        self.light_by_line = light_by_line
        self.frame_size = None if frame_size is None else (int(frame_size[0]), int(frame_size[1]))
        self.on_notice = on_notice
        self._frame_ids: set = set()
        self._last_frame_s = -np.inf
        self._first_size: tuple[int, int] | None = None
        if light is not None and light_by_line:
            light.arm(self.exposure_s)  # pulse mode: the camera's strobe line fires each flash

    def _notice(self, station: str, line: str) -> None:
        if self.on_notice is not None:
            self.on_notice(station, line)
        else:
            print(f"WARNING station {station}: {line}", file=sys.stderr, flush=True)

    def take(self, station: str, attempt: int, settled: RobotState, settled_host_s: float,
             peak_speed: float, hold_s: float) -> tuple[Frame, Exposure]:
        """Trigger, capture, check; ``FrameFault`` (with the exposure record in ``.record``) on a bad frame."""
        light, note = "none", None
        if self.light is not None and self.light_by_line:  # read back (re-armed when lost) before the exposure
            note = self.light.arm(self.exposure_s)
            light = "camera strobe line"
        trigger_s = time.time()
        if self.light is not None and not self.light_by_line:
            note = self.light.strobe(self.exposure_s)  # pulse now (controller software trigger), exposure follows
            light = "software trigger"
        if note:
            self._notice(station, note)
        rec = Exposure(station=station, attempt=attempt, outcome="ok", detail="", trigger_host_s=trigger_s, light=light,
                       exposure_s=self.exposure_s, settled_for_s=hold_s, max_joint_speed_rad_s=peak_speed,
                       light_note=note or None)
        try:
            frame = self.camera.capture()
        except NotConnectedError:
            raise
        except DriverError as exc:
            rec.outcome, rec.detail = "missing", str(exc)
            raise self._fault(rec, f"station {station}: no frame ({exc})") from None
        received_s = time.time()
        lost = self.light.check() if self.light is not None else None
        if lost:
            rec.outcome = "unlit"
            raise self._fault(rec, f"station {station}: after the exposure, {getattr(self.light, 'name', 'the light')}:"
                                   f" {lost}: it lost its settings, the light may not have flashed")
        h, w = np.shape(frame.image)[:2]
        rec.frame_size = [int(w), int(h)]
        want = self.frame_size or self._first_size
        if want is not None and (w, h) != want:
            rec.outcome = "size"
            size = (f"the job's camera is {want[0]}x{want[1]} ([camera] width x height)" if self.frame_size else
                    f"this session's first frame was {want[0]}x{want[1]}")
            raise self._fault(rec, f"station {station}: the camera delivered a {w}x{h} frame, {size}: binning or the "
                                   "ROI changed behind the cell?")
        meta = frame.meta or {}
        t_frame = float(meta.get("triggered_host_s", frame.timestamp_s))
        rec.frame_host_s, rec.frame_id = float(frame.timestamp_s), meta.get("frame_id")
        rec.device_timestamp_ns = meta.get("device_timestamp_ns")
        rec.latency_s = received_s - trigger_s
        key = (meta.get("camera") or meta.get("device"), rec.frame_id) if rec.frame_id is not None else None
        if (key is not None and key in self._frame_ids) or frame.timestamp_s <= self._last_frame_s:
            rec.outcome = "duplicate"
            raise self._fault(rec, f"station {station}: the camera delivered frame {rec.frame_id} again (taken "
                                   "before); a double trigger or a stale buffer")
        if t_frame < trigger_s - 1e-3:
            rec.outcome = "stale"
            raise self._fault(rec, f"station {station}: the frame was exposed {trigger_s - t_frame:.3f} s before its "
                                   "trigger")
        if rec.latency_s > self.exposure_s + self.frame_timeout_s:
            rec.outcome = "late"
            raise self._fault(rec, f"station {station}: the frame came {rec.latency_s:.3f} s after its trigger (limit "
                                   f"{self.exposure_s + self.frame_timeout_s:.3f} s)")
        after = self.robot.state()
        if arm_moved(settled.joints_rad, after.joints_rad) or not after.safety.normal:
            rec.outcome = "moved"
            moved = describe_change(joint_change_rad(settled.joints_rad, after.joints_rad))
            raise self._fault(rec, f"station {station}: the arm moved {moved} during the exposure"
                                   + ("" if after.safety.normal else f" ({after.safety.detail})"))
        # the robot state at the frame's instant: the arm was still from the settled reading to the one after the
        # frame, so its joints are the settled ones; its controller time is mapped from the host clock
        rec.robot_timestamp_s = settled.timestamp_s + (t_frame - settled_host_s)
        rec.joints_rad = np.asarray(settled.joints_rad, dtype=float).tolist()
        if key is not None:
            self._frame_ids.add(key)
        if want is None:  # no size from the job: the session's first frame sets it
            self._first_size = (int(w), int(h))
        self._last_frame_s = float(frame.timestamp_s)
        return frame, rec

    def _fault(self, rec: Exposure, message: str) -> FrameFault:
        fault = FrameFault(rec.outcome, message)
        rec.detail = message
        fault.record = rec
        return fault
