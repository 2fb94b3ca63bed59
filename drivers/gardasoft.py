"""A Gardasoft RT-series LED lighting controller (RT220/RT420/RT820 over Ethernet, RT260/RT460/RT860
over RS232); implements ``drivers.protocols.Light``.

The command set is Gardasoft's public text protocol, as given in the "RTxxx LED lighting controllers
- User Manual" (section 12, "Command configuration"; read through the public manual pages of the
RT-20 series) and, for the error numbers, the same family's VTR1 manual (section 10.3):

- Framing: a command line is ASCII terminated by a carriage return (13); several commands may share
  a line separated by ``;``. The controller answers with whatever the command prints, and then the
  prompt ``>``: the host waits for ``>`` before the next command. RS232: 115200 baud, 8N1, no
  handshake. Ethernet: TCP to port 30313 (UDP: from 30312 to 30313, replies to 30312).
- Numbers: comma-separated, decimal point; times in ms unless suffixed ``s``/``ms``/``us``.
- ``VR``: firmware version, e.g. ``RT420-20 (HW02) V031``.
- ``RSc,s``: channel ``c`` continuous at ``s`` % of full brightness (0..100).
- ``RWc,s``: switched mode (the trigger input switches the output on/off) at ``s`` %.
- ``RTc,p,d,s[,r]``: pulse mode: pulse width ``p`` ms, delay ``d`` ms from the trigger to the
  pulse, brightness ``s`` % (up to 1000 % of the light's rating for short pulses), retrigger delay
  ``r`` ms (minimum time between triggers; in steps of 100 µs). The operating limits (RT manual
  7.2): <=100 %: 999 ms; <=200 %: 30 ms; <=300 %: 10 ms; <=500 %: 2 ms; <=1000 %: 1 ms pulse width.
- ``RPc,i``: the trigger input ``i`` that fires output channel ``c``.
- ``TRc``: simulate a trigger on channel ``c`` (pulse mode: one pulse).
- ``STc``: the channel's settings (``MD`` mode, ``S`` brightness, ``DL`` delay, ``PU`` pulse width,
  ``RT`` retrigger, ``IP`` input, ``FL`` flags, ``CS``/``RA`` ratings); ``ST0``: general settings
  (``TM`` internal trigger, ``TP`` its period).
- ``GR``: the last event or error (``Evtc,e``) and clears it; only ``>`` when there is none.
- ``AW``: save the settings to non-volatile memory.
- Errors: ``Err 1`` a parameter value is invalid, ``Err 2`` command not recognised, ``Err 3``
  numeric value in the wrong format, ``Err 4`` wrong number of parameters, ``Err 5`` (a warning) a
  timing parameter was out of range and has been adjusted to a valid value.

Not taken from the manual (not in the pages read): the exact spacing of the ``ST`` line (the driver
parses ``KEY value`` pairs separated by commas, tolerant of spacing; a controller seen answers
``CH1,MD0,S 50.0, 0.0,DL1.000ms,...``, one line per channel when it lists several, so the lines are
parsed per channel and the one asked for is taken) and the ``MD`` numbers other than 1 = pulse and
2 = switched (continuous is taken as 0, selected as 3). Our cell uses pulse mode: the camera's strobe
output (or :meth:`GardasoftRT.strobe`'s ``TR``) triggers one flash per exposure. The ``RT`` delay
range is 0.02..999 ms (the manual); the default delay is its least, 0.02 ms.

The pulse settings are volatile unless saved (``AW``): a controller that lost its power for a moment
comes back in its saved (or power-on: continuous at 0 %) settings, accepts ``TR`` and never flashes.
So the settings are read back (``ST``) after they are sent and before each exposure
(:meth:`GardasoftRT.arm` re-sends them when they were lost and says so in what it returns), and
:meth:`GardasoftRT.check` reads them after an exposure, so that a frame taken with the light not armed
is known.

Every reply is checked: no ``>`` in time -> ``NoReplyError``; bytes that are not a reply ->
``GarbledReplyError``; ``Err n`` -> ``DeviceRefusedError`` with the manual's meaning (``Err 5``:
``TimingAdjustedError``, since a pulse that is not the one asked for would light a different
exposure); the port or the connection gone -> ``NotConnectedError``. Every message names the device.
"""
from __future__ import annotations

import re
import socket
import threading
import time

from calibration.errors import DriverError, NotConnectedError

TCP_PORT = 30313
BAUD = 115200
ERRORS = {
    1: "a parameter value is invalid",
    2: "command not recognised",
    3: "numeric value is wrong format",
    4: "wrong number of parameters",
    5: "a timing parameter was out of range and has been adjusted to a valid value",
}
# (max brightness %, max pulse width ms): the RT series' operating limits for pulsed output
PULSE_LIMITS = ((100.0, 999.0), (200.0, 30.0), (300.0, 10.0), (500.0, 2.0), (1000.0, 1.0))
MODES = {0: "continuous", 1: "pulse", 2: "switched", 3: "selected"}


class NoReplyError(NotConnectedError):
    """The device did not finish its reply (the ``>`` prompt) within the timeout."""


class GarbledReplyError(DriverError):
    """The device answered something that is not a reply to the command sent."""


class DeviceRefusedError(DriverError):
    """The device answered ``Err n``."""

    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.code = code


class TimingAdjustedError(DeviceRefusedError):
    """``Err 5``: the device changed a timing parameter to one it accepts."""


def max_pulse_ms(brightness_pct: float) -> float:
    """The longest pulse the RT series allows at ``brightness_pct`` (0 if above 1000 %)."""
    for pct, width in PULSE_LIMITS:
        if brightness_pct <= pct:
            return width
    return 0.0


def _parse_line(line: str) -> dict:
    out = {}
    for item in line.split(","):
        m = re.fullmatch(r"\s*([A-Z]{1,3})\s*:?\s*(\S.*?)\s*", item)
        if m:
            out[m.group(1)] = m.group(2)
    return out


def parse_status(text: str, channel: int | None = None) -> dict:
    """``CH 1, MD 1, S 100%, DL 0.02ms, PU 2.00ms, ...`` -> {"CH": "1", "MD": "1", "S": "100%", ...}.

    A reply of several lines (one per channel) is parsed line by line, never merged: ``channel`` picks the line
    whose ``CH`` it is. Without ``channel``, a reply must hold one line. ``ValueError`` when the channel's line is
    not there, or several lines and no channel."""
    lines = [_parse_line(ln) for ln in text.replace("\r", "\n").split("\n") if ln.strip()]
    lines = [d for d in lines if d]
    if channel is not None:
        mine = [d for d in lines if d.get("CH", "").strip() == str(int(channel))]
        if len(mine) == 1:
            return mine[0]
        if not mine and len(lines) == 1 and "CH" not in lines[0]:
            return lines[0]  # a one-line reply that does not name its channel: the one asked for
        raise ValueError(f"no single status line of channel {channel} in {text!r}")
    if len(lines) > 1:
        raise ValueError(f"{len(lines)} status lines in {text!r}; say which channel")
    return lines[0] if lines else {}


def _ms(value: str) -> float:
    m = re.fullmatch(r"([0-9.]+)\s*(s|ms|us)?", value.strip())
    if m is None:
        raise ValueError(value)
    return float(m.group(1)) * {"s": 1e3, "ms": 1.0, "us": 1e-3, None: 1.0}[m.group(2)]


class SerialTransport:
    """RS232 (pyserial): 115200 8N1 by default."""

    def __init__(self, port: str, baud: int = BAUD):
        self.port, self.baud = port, int(baud)
        self._ser = None

    @property
    def where(self) -> str:
        return self.port

    def open(self, timeout_s: float) -> None:
        import serial

        try:
            self._ser = serial.Serial(self.port, self.baud, timeout=timeout_s, write_timeout=timeout_s)
        except (serial.SerialException, OSError) as exc:
            raise NotConnectedError(f"light controller on {self.port}: cannot open the port ({exc}); check the "
                                    "cable and the device path") from None

    def close(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # a port that is gone cannot be closed cleanly
                pass

    def is_open(self) -> bool:
        return self._ser is not None

    def exchange(self, line: bytes, deadline: float) -> bytes:
        """Send ``line``; return every byte up to and including the prompt (or what came before the deadline)."""
        import termios

        import serial

        ser = self._ser
        try:
            ser.reset_input_buffer()  # a stale prompt must not be taken for this reply
            ser.write(line)
            ser.flush()
            got = b""
            while not got.endswith(b">") and time.monotonic() < deadline:
                ser.timeout = max(0.005, deadline - time.monotonic())
                chunk = ser.read_until(b">")
                if not chunk:
                    break
                got += chunk
            return got
        except (serial.SerialException, OSError, termios.error) as exc:
            raise ConnectionError(str(exc)) from None


class TcpTransport:
    """Ethernet: one TCP connection to the controller's command port (30313)."""

    def __init__(self, host: str, port: int = TCP_PORT):
        self.host, self.port = host, int(port)
        self._sock: socket.socket | None = None

    @property
    def where(self) -> str:
        return f"{self.host}:{self.port}"

    def open(self, timeout_s: float) -> None:
        try:
            self._sock = socket.create_connection((self.host, self.port), timeout=timeout_s)
        except OSError as exc:
            raise NotConnectedError(f"light controller at {self.where}: cannot connect ({exc}); check power, "
                                    "cable, IP address and that no other program holds the connection") from None

    def close(self) -> None:
        s, self._sock = self._sock, None
        if s is not None:
            try:
                s.close()
            except OSError:
                pass

    def is_open(self) -> bool:
        return self._sock is not None

    def exchange(self, line: bytes, deadline: float) -> bytes:
        s = self._sock
        try:
            s.setblocking(False)  # drop a stale prompt left over from a timed-out exchange
            try:
                while s.recv(4096):
                    pass
            except BlockingIOError:
                pass
            s.setblocking(True)
            s.settimeout(max(0.005, deadline - time.monotonic()))
            s.sendall(line)
            got = b""
            while not got.endswith(b">"):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                s.settimeout(left)
                try:
                    chunk = s.recv(4096)
                except TimeoutError:
                    break
                if not chunk:
                    raise ConnectionError("the controller closed the connection")
                got += chunk
            return got
        except OSError as exc:
            raise ConnectionError(str(exc)) from None


class GardasoftRT:
    """A Gardasoft RT-series controller driving one light channel in pulse mode.

    Args:
        port: serial device (``/dev/ttyUSB0``) -- or give ``host`` for Ethernet.
        host, tcp_port: the controller's IP address and command port (Ethernet models).
        channel: output channel of the light (1..8).
        trigger_input: the controller's trigger input wired to the camera's strobe line (``RPc,i``).
        brightness_pct: pulse brightness in % of the light's rating (<= 1000, see :data:`PULSE_LIMITS`).
        delay_s: delay from trigger to pulse (the RT range: 0.02..999 ms).
        retrigger_s: minimum time between two triggers (None: leave the device's).
        timeout_s: how long to wait for each reply's prompt.
    """

    def __init__(self, port: str | None = None, *, host: str | None = None, tcp_port: int = TCP_PORT,
                 channel: int = 1, trigger_input: int | None = None, brightness_pct: float = 100.0,
                 delay_s: float = 2e-5, retrigger_s: float | None = None, timeout_s: float = 0.5, baud: int = BAUD):
        if (port is None) == (host is None):
            raise DriverError("light controller: give either a serial port or a host")
        self.transport = SerialTransport(port, baud) if port is not None else TcpTransport(host, tcp_port)
        self.channel, self.trigger_input = int(channel), trigger_input
        self.brightness_pct, self.delay_s, self.retrigger_s = float(brightness_pct), float(delay_s), retrigger_s
        self.timeout_s = float(timeout_s)
        self.device_id: str | None = None
        self._pulse_ms: float | None = None
        self.rearmed = 0  # times the controller was found to have lost its pulse settings and was re-armed
        self._lock = threading.Lock()
        if not 1 <= self.channel <= 8:
            raise DriverError(f"light controller on {self.transport.where}: channel {channel} is not 1..8")

    @property
    def name(self) -> str:
        return f"light controller {self.device_id or ''} on {self.transport.where}".replace("  ", " ")

    # --- connection ---------------------------------------------------------------------------

    def connect(self) -> None:
        """Open the port, check that an RT-series controller answers ``VR``, set the trigger input."""
        if self.transport.is_open():
            return
        self.transport.open(self.timeout_s)
        try:
            reply = self.command("VR")
            if not re.match(r"RT\d", reply):
                raise GarbledReplyError(f"{self.name}: 'VR' answered {reply!r}, not an RT-series controller; "
                                        "check the port and the baud rate")
            self.device_id = reply
            if self.trigger_input is not None:
                self.command(f"RP{self.channel},{int(self.trigger_input)}")
            self._pulse_ms = None
        except DriverError:
            self.close()
            raise

    def close(self) -> None:
        self.transport.close()

    def __enter__(self) -> GardasoftRT:
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- the protocol -------------------------------------------------------------------------------

    def command(self, cmd: str) -> str:
        """Send one command line; return its output without the prompt. Raises on ``Err n`` and bad replies."""
        with self._lock:
            if not self.transport.is_open():
                raise NotConnectedError(f"{self.name}: not connected; call connect()")
            try:
                raw = self.transport.exchange(cmd.encode("ascii") + b"\r", time.monotonic() + self.timeout_s)
            except ConnectionError as exc:
                self.transport.close()
                raise NotConnectedError(f"{self.name}: the connection failed during '{cmd}' ({exc}); is the device "
                                        "unplugged or off? reconnect it and call connect()") from None
        if not raw.endswith(b">"):
            raise NoReplyError(f"{self.name}: no reply to '{cmd}' within {self.timeout_s:.2f} s (got {raw!r}); check "
                               "power, cable, baud rate / IP address")
        try:
            text = raw[:-1].decode("ascii")
        except UnicodeDecodeError:
            raise GarbledReplyError(f"{self.name}: unreadable reply {raw!r} to '{cmd}'; check the baud rate") from None
        if any(ord(ch) < 32 and ch not in "\r\n\t" or ord(ch) > 126 for ch in text):
            raise GarbledReplyError(f"{self.name}: unreadable reply {raw!r} to '{cmd}'; check the baud rate")
        lines = [ln.strip() for ln in text.replace("\r", "\n").split("\n") if ln.strip()]
        if lines and lines[0] == cmd:  # a controller (or terminal server) that echoes the command
            lines = lines[1:]
        for ln in lines:
            m = re.fullmatch(r"Err\s*(\d+)", ln)
            if m:
                code = int(m.group(1))
                meaning = ERRORS.get(code, "an error the manual does not list")
                cls = TimingAdjustedError if code == 5 else DeviceRefusedError
                raise cls(f"{self.name}: '{cmd}' refused: Err {code} ({meaning})", code)
        return "\n".join(lines)

    def set_continuous(self, percent: float) -> None:
        """``RSc,s``: the light on continuously at ``percent`` (0..100) of full brightness."""
        if not 0.0 <= percent <= 100.0:
            raise DriverError(f"{self.name}: continuous brightness {percent} % is outside 0..100")
        self.command(f"RS{self.channel},{percent:g}")
        self._pulse_ms = None

    def set_switched(self, percent: float) -> None:
        """``RWc,s``: the trigger input switches the light on and off, at ``percent`` (0..100)."""
        if not 0.0 <= percent <= 100.0:
            raise DriverError(f"{self.name}: switched brightness {percent} % is outside 0..100")
        self.command(f"RW{self.channel},{percent:g}")
        self._pulse_ms = None

    def set_pulse(self, width_s: float, delay_s: float | None = None, brightness_pct: float | None = None,
                  retrigger_s: float | None = None) -> None:
        """``RTc,p,d,s[,r]``: one pulse per trigger; checked against the RT limits before sending."""
        pct = self.brightness_pct if brightness_pct is None else float(brightness_pct)
        delay = self.delay_s if delay_s is None else float(delay_s)
        retrig = self.retrigger_s if retrigger_s is None else retrigger_s
        width_ms = width_s * 1e3
        limit = max_pulse_ms(pct)
        if not 0.0 < pct <= 1000.0:
            raise DriverError(f"{self.name}: pulse brightness {pct} % is outside (0, 1000]")
        if not 0.0 < width_ms <= limit:
            raise DriverError(f"{self.name}: pulse width {width_ms:g} ms is outside (0, {limit:g}] ms at {pct:g} %")
        cmd = f"RT{self.channel},{width_ms:.3f},{delay * 1e3:.3f},{pct:g}"
        if retrig is not None:
            cmd += f",{retrig * 1e3:.1f}"
        self.command(cmd)
        self._pulse_ms = width_ms

    def trigger(self) -> None:
        """``TRc``: one software trigger (in pulse mode: one pulse)."""
        self.command(f"TR{self.channel}")

    def status(self) -> dict:
        """``STc`` parsed: {"mode": str, "brightness_pct", "delay_s", "pulse_s", "retrigger_s", "input", "raw"}."""
        raw = self.command(f"ST{self.channel}")
        try:
            st = parse_status(raw, self.channel)
            return {"mode": MODES.get(int(st["MD"]), st["MD"]), "brightness_pct": float(st["S"].rstrip("%")),
                    "delay_s": _ms(st["DL"]) / 1e3, "pulse_s": _ms(st["PU"]) / 1e3,
                    "retrigger_s": _ms(st["RT"]) / 1e3 if "RT" in st else None,
                    "input": int(st["IP"]) if "IP" in st else None, "raw": raw}
        except (KeyError, ValueError):
            raise GarbledReplyError(f"{self.name}: 'ST{self.channel}' answered {raw!r}, not a channel status") from None

    def last_event(self) -> tuple[int, int] | None:
        """``GR``: the last event/error as (channel, event number), cleared; None when there is none."""
        raw = self.command("GR")
        if not raw:
            return None
        m = re.fullmatch(r"Evt\s*(\d+)\s*,\s*(\d+)", raw)
        if m is None:
            raise GarbledReplyError(f"{self.name}: 'GR' answered {raw!r}")
        return int(m.group(1)), int(m.group(2))

    def save(self) -> None:
        """``AW``: keep the settings over a power cycle."""
        self.command("AW")

    # --- drivers.protocols.Light ------------------------------------------------------------------------

    def set_intensity(self, fraction: float) -> None:
        """Pulse brightness as a fraction of the light's rating (1.0 = 100 %); used by the next pulse setting."""
        if not 0.0 < fraction <= 10.0:
            raise DriverError(f"{self.name}: intensity {fraction} is outside (0, 10] (x the light's rating)")
        self.brightness_pct = fraction * 100.0
        self._pulse_ms = None

    def arm(self, duration_s: float) -> str | None:
        """Pulse mode with a pulse of ``duration_s``, fired by the trigger input (the camera's strobe line) or
        :meth:`trigger`, and checked on the controller (``ST``).

        Sent when it changed, then read back: a controller that does not show it raises ``DriverError``. When it
        was sent before, it is read back only: a controller that lost it (a power blip: back to continuous at
        0 %) is re-armed, and the line saying what it had found is returned (None when it was as armed)."""
        if self._pulse_ms is None or abs(self._pulse_ms - duration_s * 1e3) > 1e-6:
            self._send_and_verify(duration_s, inputs=False)  # connect() set the trigger input
            return None
        found = self.check()
        if found is None:
            return None
        self._send_and_verify(duration_s, inputs=True)
        self.rearmed += 1
        return f"{self.name}: {found}: it lost its settings (a power blip?); re-armed"

    def check(self) -> str | None:
        """The channel's settings read back (``ST``) against the pulse last armed: None when they agree (or none was
        armed), else what the controller has instead, in words."""
        if self._pulse_ms is None:
            return None
        st = self.status()
        want = {"mode": "pulse", "brightness_pct": self.brightness_pct, "pulse_s": self._pulse_ms * 1e-3,
                "delay_s": self.delay_s}
        bad = [k for k in ("mode", "brightness_pct", "pulse_s", "delay_s")
               if (st[k] != want[k] if k == "mode" else abs(st[k] - want[k]) > 6e-7 + 2e-3 * abs(want[k])
                   + (0.05 if k == "brightness_pct" else 0.0))]
        if self.trigger_input is not None and st["input"] is not None and st["input"] != int(self.trigger_input):
            bad.append("input")
        if not bad:
            return None
        return (f"channel {self.channel} reads {st['mode']} mode at {st['brightness_pct']:g} %, pulse "
                f"{st['pulse_s'] * 1e3:.3f} ms, delay {st['delay_s'] * 1e3:.3f} ms"
                + (f", input {st['input']}" if self.trigger_input is not None else "")
                + f" (armed: pulse mode at {self.brightness_pct:g} %, pulse {self._pulse_ms:.3f} ms, delay "
                f"{self.delay_s * 1e3:.3f} ms" + (f", input {self.trigger_input}" if self.trigger_input is not None
                                                  else "") + ")")

    def _send_and_verify(self, duration_s: float, inputs: bool) -> None:
        if inputs and self.trigger_input is not None:
            self.command(f"RP{self.channel},{int(self.trigger_input)}")
        self.set_pulse(duration_s)
        found = self.check()
        if found is not None:
            self._pulse_ms = None
            raise DriverError(f"{self.name}: the pulse settings were sent and accepted, but {found}")

    def strobe(self, duration_s: float) -> str | None:
        """One flash of ``duration_s`` now: pulse mode (sent when it changed, read back always; see :meth:`arm`,
        whose finding it returns) and a software trigger."""
        note = self.arm(duration_s)
        self.trigger()
        return note
