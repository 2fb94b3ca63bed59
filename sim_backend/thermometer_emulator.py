"""A Fluke / Hart Scientific handheld thermometer readout (1521/1522 command set), emulated on a pseudo-terminal so
the real driver (:mod:`drivers.thermometer`) runs its real pyserial path in tests and in the simulated cell.

It follows the protocol documented in :mod:`drivers.thermometer`: a command ends with CR or LF, case does not
matter, optional letters may be left off (``f``, ``fetc?``, ``fetch?``, ``rea``, ``read?``, ``me``, ``meas?``), no
echo, every reply ends with CR LF. It answers:

- ``fetch?`` (and its forms): ``t:   25.587 C`` -- the value rounded to 3 decimals, right-aligned in 8 characters
  (the 1504 manual's ``nnnn.nnn`` field; the 1522's width is not given), in the unit set;
- ``t`` / ``temperature``: ``t:   25.587 C 03-01-1999 15:49:15`` with the host's local date and time;
- ``u``: ``u: C``; ``u=C`` / ``F`` / ``K`` / ``R`` / ``O``: sets the unit, no reply (as in the manual's tables);
- ``*ver``: ``ver.1522,1.24`` (the manual's form); ``*idn?``: ``HART,1522,<serial>,1.24``.

Anything else (an unknown command, a unit it does not have) is answered ``?``: the manuals read do not say what the
readout does, and a reply lets the driver say so at once instead of timing out. In ohms (``O``) it reports the
resistance of a PT100 (IEC 60751, R0 = 100 ohm) at the probe's temperature.

Faults to inject: ``fault = "no_reply"`` (reads, never answers), ``"garbled"`` (answers line noise ending in
CR LF, as at a wrong baud rate), :meth:`ThermometerEmulator.unplug` (the port goes away under the client), and
``glitches = {n: value_C}`` (the n-th reading served, from 1, reads ``value_C`` instead: a sensor-open or dropout
value such as -200 or 0 C).
"""
from __future__ import annotations

import os
import random
import re
import threading
import tty
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime

from sim_backend.pty_lines import serve_lines

FAULTS = (None, "no_reply", "garbled")
UNITS = ("C", "F", "K", "R", "O")
#: (the letters required, the full command): any prefix of the full command from the required letters on
_COMMANDS = {"fetch": ("f", "fetch"), "read": ("rea", "read"), "measure": ("me", "measure"),
             "temperature": ("t", "temperature"), "unit": ("u", "unit"), "version": ("*v", "*version"),
             "idn": ("*i", "*idn")}
GARBLED = "\x15\xf8t\x7f\x00:\xe6\x8c\r\n"  # a reading at the wrong baud rate: noise, the line end intact


def pt100_ohm(t_C: float) -> float:
    """A PT100's resistance at ``t_C`` (Callendar-Van Dusen, IEC 60751 coefficients)."""
    a, b, c = 3.9083e-3, -5.775e-7, -4.183e-12
    r = 1.0 + a * t_C + b * t_C * t_C
    if t_C < 0.0:
        r += c * (t_C - 100.0) * t_C ** 3
    return 100.0 * r


def from_celsius(t_C: float, unit: str) -> float:
    """``t_C`` in the readout's ``unit`` (C, F, K, R; O: a PT100's ohms)."""
    return {"C": lambda: t_C, "F": lambda: t_C * 9.0 / 5.0 + 32.0, "K": lambda: t_C + 273.15,
            "R": lambda: (t_C + 273.15) * 9.0 / 5.0, "O": lambda: pt100_ohm(t_C)}[unit]()


def _match(word: str) -> str | None:
    """The command ``word`` (lower case, without a trailing ``?``) stands for, or None."""
    for name, (required, full) in _COMMANDS.items():
        if word.startswith(required) and full.startswith(word):
            return name
    return None


@dataclass(frozen=True)
class Reading:
    """One reading the readout served: the value as shown (3 decimals) in ``unit``, the noisy temperature it came
    from (deg C), the reply line without CR LF."""

    value: float
    unit: str
    celsius: float
    text: str


class ThermometerEmulator:
    """The readout on a pseudo-terminal (``.port``, after :meth:`start`); use as a context manager.

    Args:
        temperature_C: the probe's true temperature, deg C: a number, or a function of no arguments called at each
            reading (a part warming up).
        noise_K: standard deviation of each reading (the readout's own noise and the contact's flicker).
        model, firmware, serial_number: what ``*ver`` and ``*idn?`` report.
        unit: the unit set at power-on (C, F, K, R, O).
        fault: None, ``"no_reply"`` or ``"garbled"`` (may be changed while it runs).
        seed: of the noise, for repeatable readings.
    """

    def __init__(self, temperature_C: float | Callable[[], float] = 20.0, noise_K: float = 0.005, model: str = "1522",
                 unit: str = "C", fault: str | None = None, seed: int | None = None, firmware: str = "1.24",
                 serial_number: str = "A12345"):
        if unit.upper() not in UNITS:
            raise ValueError(f"unknown unit {unit!r}; one of {UNITS}")
        self.temperature_C = temperature_C
        self.noise_K = float(noise_K)
        self.model, self.firmware, self.serial_number = str(model), str(firmware), str(serial_number)
        self.unit = unit.upper()
        self.fault = fault
        self.readings: list[Reading] = []
        self.glitches: dict[int, float] = {}  # reading number (from 1) -> the value it reads instead, deg C
        self.received: list[str] = []
        self.port: str | None = None
        self._rng = random.Random(seed)
        self._master = self._slave = -1
        self._stop = threading.Event()
        self._fd_lock = threading.Lock()
        self._thread: threading.Thread | None = None

    @property
    def fault(self) -> str | None:
        return self._fault

    @fault.setter
    def fault(self, value: str | None) -> None:
        if value not in FAULTS:
            raise ValueError(f"unknown fault {value!r}; one of {FAULTS}")
        self._fault = value

    # --- the device ---------------------------------------------------------------------------------------------

    def true_C(self) -> float:
        """The probe's true temperature now."""
        t = self.temperature_C
        return float(t() if callable(t) else t)

    def _reading(self) -> tuple[float, str]:
        celsius = self.true_C() + (self._rng.gauss(0.0, self.noise_K) if self.noise_K > 0 else 0.0)
        celsius = float(self.glitches.get(len(self.readings) + 1, celsius))
        shown = f"{from_celsius(celsius, self.unit):8.3f}"
        text = f"t: {shown} {self.unit}"
        self.readings.append(Reading(float(shown), self.unit, celsius, text))
        return celsius, text

    def execute(self, line: str) -> str | None:
        """One command line (without its CR/LF) -> the reply including CR LF, or None (no reply)."""
        self.received.append(line)
        if self.fault == "no_reply":
            return None
        if self.fault == "garbled":
            return GARBLED
        cmd = re.sub(r"\s+", "", line.lower())
        key, _, value = cmd.partition("=")
        name = _match(key.removesuffix("?"))
        if "=" in cmd:
            if name == "unit" and value.upper() in UNITS:
                self.unit = value.upper()
                return None
            return "?\r\n"
        if name in ("fetch", "read", "measure"):
            return self._reading()[1] + "\r\n"
        if name == "temperature":
            return f"{self._reading()[1]} {datetime.now():%m-%d-%Y %H:%M:%S}\r\n"
        if name == "unit":
            return f"u: {self.unit}\r\n"
        if name == "version":
            return f"ver.{self.model},{self.firmware}\r\n"
        if name == "idn":
            return f"HART,{self.model},{self.serial_number},{self.firmware}\r\n"
        return "?\r\n"

    # --- the pseudo-terminal ------------------------------------------------------------------------------------

    def start(self) -> ThermometerEmulator:
        """Open the pseudo-terminal and serve it from a background thread; returns self."""
        if self._thread is not None:
            return self
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing: bytes pass as they are (the readout is half duplex)
        self.port = os.ttyname(self._slave)
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="thermometer-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the pseudo-terminal; safe to call twice."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
        with self._fd_lock:
            for fd in (self._master, self._slave):
                if fd >= 0:
                    os.close(fd)
            self._master = self._slave = -1

    def unplug(self) -> None:
        """The readout goes away: the pseudo-terminal is closed under the client."""
        self.stop()

    def __enter__(self) -> ThermometerEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _serve(self) -> None:
        serve_lines(self._master, self._stop, self._split, self._answer)

    @staticmethod
    def _split(buffer: bytes) -> tuple[list[bytes], bytes]:
        *lines, rest = re.split(rb"[\r\n]", buffer)
        return [ln for ln in lines if ln.strip()], rest  # the LF of a CR LF, or an empty line, is no command

    def _answer(self, line: bytes) -> str | None:
        return self.execute(line.decode("ascii", "replace").strip())
