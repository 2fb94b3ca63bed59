"""A light/strobe controller on a serial line (pyserial); implements ``drivers.protocols.Light``.

The line protocol (ASCII, one command per line, ``\\n`` terminated, one reply each)::

    ID?              -> OK ID <model> <firmware>
    INT 0.80         -> OK INT 0.80        (intensity, fraction of full power, 2 decimals)
    STROBE 0.0020    -> OK STROBE          (one flash of 2.0 ms; the camera trigger is wired to it)
    anything bad     -> ERR <reason>

Every reply is checked against what the command asked; a missing reply, a garbled
one, a refusal and a vanished port each raise their own error with a message that
says what to check.
"""
from __future__ import annotations

import re
import termios
import threading

import serial

from calibration.errors import DriverError, NotConnectedError


class NoReplyError(NotConnectedError):
    """The device did not answer within the timeout."""


class GarbledReplyError(DriverError):
    """The device answered something that is not a reply to the command sent."""


class DeviceRefusedError(DriverError):
    """The device answered ``ERR ...``."""


MAX_STROBE_S = 0.1


class SerialLight:
    """A serial light controller.

    Args:
        port: serial device path (``/dev/ttyUSB0``, or an emulator's pseudo-terminal).
        baud: line speed.
        timeout_s: how long to wait for each reply line.
    """

    def __init__(self, port: str, baud: int = 115200, timeout_s: float = 0.5):
        self.port, self.baud, self.timeout_s = port, int(baud), float(timeout_s)
        self.device_id: str | None = None
        self._serial: serial.Serial | None = None
        self._lock = threading.Lock()

    def connect(self) -> None:
        """Open the port and check that a light controller answers ``ID?``."""
        if self._serial is not None:
            return
        try:
            self._serial = serial.Serial(self.port, self.baud, timeout=self.timeout_s, write_timeout=self.timeout_s)
        except (serial.SerialException, OSError) as exc:
            raise NotConnectedError(f"light on {self.port}: cannot open the port ({exc}); check the cable and the "
                                    "device path") from None
        try:
            reply = self._transact("ID?", r"OK ID (.+)")
        except DriverError:
            self.close()
            raise
        self.device_id = reply.group(1)

    def close(self) -> None:
        ser, self._serial = self._serial, None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError):
                pass

    def __enter__(self) -> SerialLight:
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def set_intensity(self, fraction: float) -> None:
        """Set the intensity in ``[0, 1]`` (sent with 2 decimals, echoed back by the device)."""
        if not 0.0 <= fraction <= 1.0:
            raise DriverError(f"light on {self.port}: intensity {fraction} is outside [0, 1]")
        text = f"{fraction:.2f}"
        self._transact(f"INT {text}", rf"OK INT {re.escape(text)}")

    def strobe(self, duration_s: float) -> None:
        """Fire one flash of ``duration_s`` (0 < duration <= 0.1 s, sent in 0.1 ms steps)."""
        if not 0.0 < duration_s <= MAX_STROBE_S:
            raise DriverError(f"light on {self.port}: strobe duration {duration_s} s is outside (0, {MAX_STROBE_S}] s")
        self._transact(f"STROBE {duration_s:.4f}", r"OK STROBE")

    def _transact(self, command: str, expected: str) -> re.Match:
        with self._lock:
            ser = self._serial
            if ser is None:
                raise NotConnectedError(f"light on {self.port}: not connected; call connect()")
            try:
                ser.reset_input_buffer()  # a stale line must not be taken for this reply
                ser.write(command.encode("ascii") + b"\n")
                ser.flush()
                raw = ser.readline()
            except (serial.SerialException, OSError, termios.error) as exc:
                self.close()
                raise NotConnectedError(f"light on {self.port}: the port failed during '{command}' ({exc}); "
                                        "is the device unplugged? reconnect it and call connect()") from None
        if not raw.endswith(b"\n"):
            raise NoReplyError(f"light on {self.port}: no reply to '{command}' within {self.timeout_s:.2f} s "
                               f"(got {raw!r}); check power, cable and baud rate ({self.baud})")
        line = raw.decode("ascii", "replace").strip()
        if line.startswith("ERR"):
            raise DeviceRefusedError(f"light on {self.port}: device refused '{command}': {line}")
        match = re.fullmatch(expected, line)
        if match is None:
            raise GarbledReplyError(f"light on {self.port}: unexpected reply {line!r} to '{command}'; check the "
                                    "baud rate and that this is a light controller")
        return match
