"""A light/strobe controller emulated on a pseudo-terminal, for the real pyserial path in tests.

It speaks the line protocol of :mod:`drivers.serial_light` on the slave side of an
``os.openpty`` pair (``emulator.port`` is its device path). Faults to inject:
``fault = "no_reply"`` (reads, never answers), ``fault = "garbled"`` (answers
noise), and :meth:`unplug` (the port goes away: both ends closed).
"""
from __future__ import annotations

import os
import re
import select
import threading
import tty

FAULTS = (None, "no_reply", "garbled")


class SerialEmulator:
    """A light controller on a pseudo-terminal; use as a context manager.

    Attributes:
        intensity: last intensity set, in [0, 1].
        strobes_s: durations of the flashes fired, in order.
        received: every command line received.
    """

    model = "LOOPBACK-LIGHT 1.0"

    def __init__(self, fault: str | None = None):
        if fault not in FAULTS:
            raise ValueError(f"unknown fault {fault!r}; one of {FAULTS}")
        self.fault = fault
        self.intensity = 0.0
        self.strobes_s: list[float] = []
        self.received: list[str] = []
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing: bytes pass as they are
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._serve, name="serial-emulator", daemon=True)
        self._thread.start()

    def __enter__(self) -> SerialEmulator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def unplug(self) -> None:
        """The device goes away: the pseudo-terminal is closed under the client."""
        self.close()

    def close(self) -> None:
        """Stop the thread and close both ends; safe to call twice."""
        self._stop.set()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=2.0)
        with self._lock:
            for fd in (self._master, self._slave):
                if fd >= 0:
                    os.close(fd)
            self._master = self._slave = -1

    def _serve(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], 0.02)
                if not ready:
                    continue
                chunk = os.read(self._master, 1024)
            except (OSError, ValueError):
                return
            if not chunk:
                return
            buffer += chunk
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                reply = self._answer(line.decode("ascii", "replace").strip())
                if reply is not None:
                    try:
                        os.write(self._master, reply.encode("ascii", "replace") + b"\n")
                    except OSError:
                        return

    def _answer(self, line: str) -> str | None:
        self.received.append(line)
        if self.fault == "no_reply":
            return None
        if self.fault == "garbled":
            return "\x15K\x7f?INT"
        if line == "ID?":
            return f"OK ID {self.model}"
        m = re.fullmatch(r"INT (\d+(?:\.\d+)?)", line)
        if m:
            value = float(m.group(1))
            if not 0.0 <= value <= 1.0:
                return f"ERR intensity {m.group(1)} out of range"
            self.intensity = value
            return f"OK INT {value:.2f}"
        m = re.fullmatch(r"STROBE (\d+(?:\.\d+)?)", line)
        if m:
            duration = float(m.group(1))
            if not 0.0 < duration <= 0.1:
                return f"ERR strobe {m.group(1)} s out of range"
            self.strobes_s.append(duration)
            return "OK STROBE"
        return f"ERR unknown command {line!r}"
