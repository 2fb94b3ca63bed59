"""A Gardasoft RT-series lighting controller, emulated: on a pseudo-terminal (the RS232 models) and
on a TCP port of 127.0.0.1 (the Ethernet models), so the real driver (:mod:`drivers.gardasoft`) runs
its real pyserial / socket path in tests.

It follows the command set documented in :mod:`drivers.gardasoft` command by command, with the
manual's error numbers: ``Err 2`` for an unknown command, ``Err 4`` for a wrong number of
parameters, ``Err 3`` for a number it cannot read, ``Err 1`` for a value out of range (channel,
brightness, a pulse longer than the RT limits allow at that brightness), ``Err 5`` when it adjusts a
timing parameter (a delay outside the manual's 0.02..999 ms is clamped to it). Commands end in CR, may
be joined by ``;``, and every reply ends with the prompt ``>``. ``VR`` answers ``RT820-20 (HW02) V031``.
``STc`` answers in the shape a controller was seen to (``CH1,MD1,S 100.0, 0.0,DL0.020ms,PU2.000ms,...``).

Faults to inject: ``fault = "no_reply"`` (reads, never answers), ``"garbled"`` (answers line noise),
:meth:`unplug` (the port, or the listening socket and every connection, go away), and
:meth:`RTController.power_cycle` (a power blip: every channel back to the settings saved with ``AW``,
or to the power-on defaults, continuous at 0 %; ``power_cycle_at_trigger = n`` does it as the n-th
``TR`` arrives, before it is acted on).
"""
from __future__ import annotations

import os
import re
import socket
import threading
import time
import tty
from dataclasses import dataclass, field

from sim_backend.pty_lines import serve_lines

FAULTS = (None, "no_reply", "garbled")
MAX_PULSE_MS = ((100.0, 999.0), (200.0, 30.0), (300.0, 10.0), (500.0, 2.0), (1000.0, 1.0))


class _Err(Exception):
    def __init__(self, code: int):
        self.code = code


def _number(text: str, unit: str = "ms") -> float:
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*(s|ms|us|A|ma|mA)?\s*", text)
    if m is None:
        raise _Err(3)
    v, suffix = float(m.group(1)), m.group(2)
    if unit == "ms":
        return v * {"s": 1e3, "ms": 1.0, "us": 1e-3, None: 1.0}.get(suffix, 1.0)
    return v


@dataclass
class Channel:
    mode: int = 0  # 0 continuous, 1 pulse, 2 switched, 3 selected
    brightness_pct: float = 0.0
    delay_ms: float = 0.02
    pulse_ms: float = 1.0
    retrigger_ms: float = 0.0
    trigger_input: int = 1
    last_pulse_s: float = -1e9


@dataclass
class Pulse:
    """One flash the controller fired: when (host clock), on which channel, how long, how bright."""

    channel: int
    t_s: float
    width_s: float
    brightness_pct: float
    source: str  # "TR" (software) or "IPn" (input n)


@dataclass
class RTController:
    """The controller's state and command interpreter (shared by both transports)."""

    n_channels: int = 8
    model: str = "RT820-20 (HW02) V031"
    channels: dict = field(default_factory=dict)
    pulses: list = field(default_factory=list)
    received: list = field(default_factory=list)
    saved: bool = False
    last_event: tuple | None = None
    fault: str | None = None
    power_cycle_at_trigger: int | None = None  # the n-th TR finds the controller just power-cycled (a test hook)
    triggers: int = 0  # TR commands received
    power_cycles: int = 0

    def __post_init__(self):
        self.channels = {c: Channel() for c in range(1, self.n_channels + 1)}
        self._saved_channels: dict | None = None
        self._lock = threading.Lock()

    def power_cycle(self) -> None:
        """A power blip: the volatile settings are lost; every channel comes back as saved by ``AW`` (or as at
        power-on: continuous mode at 0 %)."""
        from dataclasses import replace

        saved = self._saved_channels
        self.channels = {c: (replace(saved[c]) if saved else Channel()) for c in range(1, self.n_channels + 1)}
        self.power_cycles += 1

    def _channel(self, text: str) -> Channel:
        try:
            c = int(text)
        except ValueError:
            raise _Err(3) from None
        if c not in self.channels:
            raise _Err(1)
        return self.channels[c]

    def input_edge(self, input_no: int, t_s: float | None = None) -> int:
        """A rising edge on trigger input ``input_no`` (the camera's strobe line); returns pulses fired."""
        with self._lock:
            return sum(self._fire(c, f"IP{input_no}", t_s) for c, ch in self.channels.items()
                       if ch.trigger_input == input_no and ch.mode == 1)

    def _fire(self, c: int, source: str, t_s: float | None = None) -> int:
        ch = self.channels[c]
        now = time.monotonic() if t_s is None else t_s
        if now - ch.last_pulse_s < ch.retrigger_ms * 1e-3:
            return 0  # within the retrigger delay: ignored, as the device does
        ch.last_pulse_s = now
        self.pulses.append(Pulse(c, time.time(), ch.pulse_ms * 1e-3, ch.brightness_pct, source))
        return 1

    def execute(self, line: str) -> str | None:
        """One command line (without CR) -> the reply text including the prompt, or None (no reply)."""
        self.received.append(line)
        if self.fault == "no_reply":
            return None
        if self.fault == "garbled":
            return "\x15\x7fK\x00?>"  # line noise at the wrong baud rate, a stray prompt byte included
        out = []
        for cmd in line.split(";"):
            cmd = cmd.strip()
            if not cmd:
                continue
            try:
                with self._lock:
                    text = self._one(cmd)
            except _Err as e:
                self.last_event = (0, e.code)
                out.append(f"Err {e.code}")
                if e.code != 5:
                    break  # an error stops the rest of the line
                continue
            if text:
                out.append(text)
        return "".join(t + "\r\n" for t in out) + ">"

    def _one(self, cmd: str) -> str:
        m = re.fullmatch(r"([A-Z]{2})(.*)", cmd)
        if m is None:
            raise _Err(2)
        op, rest = m.group(1), m.group(2)
        args = [a for a in rest.split(",")] if rest.strip() else []
        if op == "VR":
            if args:
                raise _Err(4)
            return self.model
        if op == "AW":
            from dataclasses import replace

            self.saved = True
            self._saved_channels = {c: replace(ch) for c, ch in self.channels.items()}
            return ""
        if op == "GR":
            ev, self.last_event = self.last_event, None
            return "" if ev is None else f"Evt{ev[0]},{ev[1]}"
        if op in ("RS", "RW"):
            if len(args) != 2 and not (op == "RW" and len(args) in (3, 4)):
                raise _Err(4)
            ch = self._channel(args[0])
            s = _number(args[1], "pct")
            if not 0.0 <= s <= 100.0:
                raise _Err(1)
            ch.mode, ch.brightness_pct = (0 if op == "RS" else 2), s
            return ""
        if op == "RT":
            if len(args) not in (4, 5):
                raise _Err(4)
            ch = self._channel(args[0])
            p, d, s = _number(args[1]), _number(args[2]), _number(args[3], "pct")
            r = _number(args[4]) if len(args) == 5 else ch.retrigger_ms
            limit = next((w for pct, w in MAX_PULSE_MS if s <= pct), 0.0)
            if not 0.0 < s <= 1000.0 or not 0.0 < p <= limit:
                raise _Err(1)
            adjusted = not 0.02 <= d <= 999.0  # the manual's delay range
            ch.mode, ch.pulse_ms, ch.delay_ms, ch.brightness_pct = 1, p, min(max(d, 0.02), 999.0), s
            ch.retrigger_ms = round(r * 10.0) / 10.0  # steps of 100 us
            if adjusted:
                raise _Err(5)
            return ""
        if op == "RP":
            if len(args) != 2:
                raise _Err(4)
            ch = self._channel(args[0])
            try:
                i = int(args[1])
            except ValueError:
                raise _Err(3) from None
            if not 1 <= i <= self.n_channels:
                raise _Err(1)
            ch.trigger_input = i
            return ""
        if op == "TR":
            if len(args) != 1:
                raise _Err(4)
            c = int(self._channel_no(args[0]))
            self.triggers += 1
            if self.triggers == self.power_cycle_at_trigger:
                self.power_cycle()
            if self.channels[c].mode == 1:
                self._fire(c, "TR")
            return ""
        if op == "ST":
            if len(args) != 1:
                raise _Err(4)
            if args[0].strip() == "0":
                return "TM 0, TP 20.00ms"
            c = self._channel_no(args[0])
            ch = self.channels[c]
            return (f"CH{c},MD{ch.mode},S {ch.brightness_pct:.1f}, 0.0,DL{ch.delay_ms:.3f}ms,PU{ch.pulse_ms:.3f}ms,"
                    f"RT{ch.retrigger_ms:.1f}ms,IP{ch.trigger_input},FL0,CS0.00A,RA1.00A")
        raise _Err(2)

    def _channel_no(self, text: str) -> int:
        self._channel(text)
        return int(text)


class _Front:
    """Common line handling: CR-terminated command lines in, replies out."""

    controller: RTController

    def _lines(self, buffer: bytes) -> tuple[list[str], bytes]:
        lines = []
        while b"\r" in buffer:
            line, buffer = buffer.split(b"\r", 1)
            lines.append(line.decode("ascii", "replace").strip("\n "))
        return lines, buffer


class GardasoftSerialEmulator(_Front):
    """The RS232 model on a pseudo-terminal (``emulator.port``); use as a context manager."""

    def __init__(self, controller: RTController | None = None, fault: str | None = None):
        if fault not in FAULTS:
            raise ValueError(f"unknown fault {fault!r}; one of {FAULTS}")
        self.controller = controller or RTController()
        self.controller.fault = fault
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing: bytes pass as they are
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._serve, name="gardasoft-serial-emulator", daemon=True)
        self._thread.start()

    @property
    def fault(self) -> str | None:
        return self.controller.fault

    @fault.setter
    def fault(self, value: str | None) -> None:
        self.controller.fault = value

    def __enter__(self) -> GardasoftSerialEmulator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def unplug(self) -> None:
        """The device goes away: the pseudo-terminal is closed under the client."""
        self.close()

    def close(self) -> None:
        self._stop.set()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=2.0)
        with self._lock:
            for fd in (self._master, self._slave):
                if fd >= 0:
                    os.close(fd)
            self._master = self._slave = -1

    def _serve(self) -> None:
        serve_lines(self._master, self._stop, self._lines, self.controller.execute)


class GardasoftTcpEmulator(_Front):
    """The Ethernet model: a TCP server on 127.0.0.1 (``emulator.port``; 0 picks a free port)."""

    def __init__(self, controller: RTController | None = None, fault: str | None = None, port: int = 0):
        if fault not in FAULTS:
            raise ValueError(f"unknown fault {fault!r}; one of {FAULTS}")
        self.controller = controller or RTController()
        self.controller.fault = fault
        self._server = socket.create_server(("127.0.0.1", port))
        self._server.settimeout(0.05)
        self.host, self.port = self._server.getsockname()[:2]
        self._stop = threading.Event()
        self._conns: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._thread = threading.Thread(target=self._accept, name="gardasoft-tcp-emulator", daemon=True)
        self._thread.start()

    @property
    def fault(self) -> str | None:
        return self.controller.fault

    @fault.setter
    def fault(self, value: str | None) -> None:
        self.controller.fault = value

    def __enter__(self) -> GardasoftTcpEmulator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def unplug(self) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        for c in list(self._conns):
            try:
                c.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            c.close()
        self._server.close()
        for t in [self._thread, *self._threads]:
            if t is not threading.current_thread():
                t.join(timeout=2.0)

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self._conns.append(conn)
            t = threading.Thread(target=self._serve, args=(conn,), name="gardasoft-tcp-conn", daemon=True)
            self._threads.append(t)
            t.start()

    def _serve(self, conn: socket.socket) -> None:
        conn.settimeout(0.05)
        buffer = b""
        while not self._stop.is_set():
            try:
                chunk = conn.recv(1024)
            except TimeoutError:
                continue
            except OSError:
                return
            if not chunk:
                return
            lines, buffer = self._lines(buffer + chunk)
            for line in lines:
                reply = self.controller.execute(line)
                if reply is not None:
                    try:
                        conn.sendall(reply.encode("latin-1", "replace"))
                    except OSError:
                        return
