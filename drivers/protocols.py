"""Capabilities of the cell's devices as small typed Protocols.

The state machine in ``cell/`` sees only these; the real drivers in ``drivers/``
and the simulation in ``sim_backend/`` both satisfy them, so the simulated and the
real cell run the same code path. Units are SI: metres, radians, seconds.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class SafetyStatus:
    """What the controller says about safety.

    ``normal`` is True only when the robot may move: no protective stop, no
    emergency stop, no fault, and the program/script is running.
    """

    normal: bool
    protective_stop: bool = False
    emergency_stop: bool = False
    fault: bool = False
    program_running: bool = True
    detail: str = ""


@dataclass(frozen=True)
class RobotState:
    """One reading of the robot.

    Attributes:
        joints_rad: (6,) measured joint positions.
        base_from_flange: (4, 4) measured flange pose in the robot base frame.
        safety: safety status at the time of the reading.
        timestamp_s: controller time of the reading (seconds); freshness is judged by it.
        joint_speeds_rad_s: (6,) measured joint speeds, when the controller reports them (RTDE
            ``actual_qd``); None otherwise (then settling is judged from successive positions).
    """

    joints_rad: np.ndarray
    base_from_flange: np.ndarray
    safety: SafetyStatus
    timestamp_s: float
    joint_speeds_rad_s: np.ndarray | None = None


@runtime_checkable
class Robot(Protocol):
    """A 6-axis arm that carries the camera."""

    def connect(self) -> None:
        """Open the connection; raises ``NotConnectedError`` if it cannot."""

    def close(self) -> None:
        """Close the connection; safe to call twice."""

    def move_joints(self, joints_rad: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> RobotState:
        """Move in joint space to ``joints_rad: (6,)`` and block until there.

        Raises ``LimitError`` before sending anything if the command exceeds the cell's
        limits, ``ProtectiveStopError`` if the controller stops, ``MotionError`` on
        any other failure or on the driver's own deadline. Returns the state at arrival.
        """

    def move_pose(self, base_from_flange: np.ndarray, speed_m_s: float, accel_m_s2: float) -> RobotState:
        """Move linearly to the flange pose ``base_from_flange: (4, 4)``; as :meth:`move_joints`."""

    def stop(self) -> None:
        """Decelerate and stop now. Never raises for a robot already stopped."""

    def state(self) -> RobotState:
        """The latest reading; raises ``NotConnectedError`` if it is stale."""


@dataclass(frozen=True)
class Frame:
    """One captured image and what is known about it.

    Attributes:
        image: (height, width) uint8 or uint16 grey image.
        timestamp_s: capture time (host clock, seconds).
        exposure_s: exposure time used.
        meta: anything else the device reports (serial, gain, frame id).
    """

    image: np.ndarray
    timestamp_s: float
    exposure_s: float
    meta: dict = field(default_factory=dict)


@runtime_checkable
class Camera(Protocol):
    """An image source."""

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def capture(self) -> Frame:
        """Take one image now (or on the next trigger); raises ``DriverError`` on failure."""


@runtime_checkable
class Light(Protocol):
    """A light/strobe controller (serial line or Ethernet; the real one is ``drivers.gardasoft.GardasoftRT``)."""

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def set_intensity(self, fraction: float) -> None:
        """Set the light's intensity in ``[0, 1]``."""

    def strobe(self, duration_s: float) -> str | None:
        """Fire one flash of ``duration_s`` now (a software trigger of the controller); a line saying the settings
        the controller had lost and were set again, else None."""

    def arm(self, duration_s: float) -> str | None:
        """Pulse mode: one flash of ``duration_s`` per edge on the controller's trigger input (the camera's
        strobe line), so the light fires with the exposure itself; read back, re-armed (and said) when lost."""

    def check(self) -> str | None:
        """After an exposure: what the controller's read-back differs in from what was armed (None: as armed)."""


@runtime_checkable
class Thermometer(Protocol):
    """The part's temperature readout (the real one is ``drivers.thermometer.FlukeReadout``): the cell states the part
    at the ISO 1 reference of 20 C from it, so a reading is in deg C or an error, never a guess."""

    @property
    def name(self) -> str:
        """What the journal and the report call it, with where it is (``Fluke 1522 readout on /dev/ttyUSB0``)."""

    def connect(self) -> None:
        """Open the port and identify the readout; raises ``NotConnectedError`` if it cannot."""

    def close(self) -> None:
        """Close the port; safe to call twice."""

    def read_C(self) -> float:
        """The current reading in deg C; raises ``DriverError`` on no reply, a garbled one, or a non-temperature."""

    def read_n_C(self, n: int = 5, interval_s: float = 0.0) -> list[float]:
        """``n`` readings in deg C, as read (the caller judges them: one glitch must not move a mean)."""
