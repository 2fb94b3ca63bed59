"""The part's thermometer: a Fluke (Hart Scientific) handheld thermometer readout on RS-232, read in its simple
format; implements ``drivers.protocols.Thermometer``.

The cell reads the part's temperature at the start and the end of ACQUIRE (``cell.thermal.read_probe``) to state
the part at the ISO 1 reference of 20 C, so a reading must be right or fail loudly: a reply that is not a
temperature is never taken for one.

What the manuals confirm (1521 and 1522 User's Guides, section 8 "Communications Interface", read through public
copies of the manual pages; 1504 and 1502A User's Guides, section 7):

- Serial line: 8 data bits, 1 stop bit, no parity, no flow control, 2400 baud (fixed on the 1521/1522), linefeed
  on (every CR the readout sends is followed by LF), half duplex (no echo).
- A command ends with CR or LF and may be upper or lower case; every reply ends with CR LF. The syntax shows
  optional letters in brackets, so ``f``, ``fetch?``, ``rea``, ``read?``, ``me``, ``meas?`` are one command.
- ``fetch?`` (and its other forms): the measurement in simple format, ``t: 25.587 C``; the unit is one of
  ``C``, ``F``, ``K``, ``R`` (Rankine) or ``O`` (ohms). The 1504 documents the value as right-aligned in a
  field (leading spaces), three decimals.
- ``t`` / ``temperature``: the extended format, ``t: 125.745 C 03-01-1999 15:49:15`` (mm-dd-yyyy hh:mm:ss).
- ``u`` / ``unit``: reads the unit, ``u: C`` (the 1522 table: ``u:{C,O,F,R or K}``); ``u=C`` (``O``, ``F``,
  ``K``, ``R``) sets it. A setting command has no reply in the tables, so :meth:`FlukeReadout.set_unit` reads the
  unit back to check it.
- ``*ver``: model and firmware. The manuals give ``ver.1522,1.24`` (1521: ``ver.1521,2.11``; 1502A:
  ``ver.1502A,1.10``) -- not ``VER,1522,1.10``; the driver accepts either spelling.

What the manuals say otherwise, and what is assumed:

- The 1504/1502A answer ``FETCH?`` with the bare number, without the label and the unit, and their ``T`` with the
  time only (``t: nnnn.nnn u hh:mm:ss``, when the time stamp is enabled). The driver takes a bare number in the
  unit the readout reports to ``u`` (assumed to be answered like the 1522's; not confirmed for the 1504), and an
  extended reply with or without the date. The 1523/1524 were not confirmed (their command pages were not read).
- What the readout answers to a command it does not know is not documented in the pages read: a ``?`` line is
  taken as a refusal (``DeviceRefusedError``, code 0), silence as ``NoReplyError``.
- With a serial sample period set (``sa=n``, n > 0) the readout sends readings unasked; the driver drops what
  came before each command, and a stray reading has the same form as the one asked for, but ``sa=0`` is best.

Errors (each message one line naming the readout's port and what to check): the port cannot be opened or fails
-> ``NotConnectedError``; no complete reply within ``timeout_s`` -> ``NoReplyError``; bytes that are not the
reply -> ``GarbledReplyError`` naming them; the readout set to ohms -> ``NotATemperatureError``.
"""
from __future__ import annotations

import re
import threading
import time

from calibration.errors import DriverError, NotConnectedError
from drivers.gardasoft import DeviceRefusedError, GarbledReplyError, NoReplyError

BAUD = 2400
UNITS = ("C", "F", "K", "R", "O")
#: deg C from a reading in each temperature unit of the readout
TO_C = {"C": lambda v: v, "F": lambda v: (v - 32.0) * 5.0 / 9.0, "K": lambda v: v - 273.15,
        "R": lambda v: v * 5.0 / 9.0 - 273.15}
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)"
_SIMPLE = re.compile(rf"t\s*:\s*({_NUMBER})\s*([CFKRO])", re.IGNORECASE)
_BARE = re.compile(rf"\s*({_NUMBER})\s*")
_EXTENDED = re.compile(rf"t\s*:\s*({_NUMBER})\s*([CFKRO])\s+((?:\d{{2}}-\d{{2}}-\d{{4}}\s+)?\d{{2}}:\d{{2}}:\d{{2}})",
                       re.IGNORECASE)
_UNIT = re.compile(r"u\s*:\s*([CFKRO])", re.IGNORECASE)
_VER = re.compile(r"ver\s*[.,:]?\s*([0-9A-Za-z]+)\s*,\s*([0-9A-Za-z.]+)", re.IGNORECASE)


class NotATemperatureError(DriverError):
    """The readout reports a resistance (unit ``O``, ohms), not a temperature."""


def to_celsius(value: float, unit: str) -> float:
    """A reading in the readout's ``unit`` (C, F, K, R) in deg C; ohms are not a temperature (``ValueError``)."""
    try:
        return TO_C[unit.upper()](float(value))
    except KeyError:
        raise ValueError(f"unit {unit!r} is not a temperature unit") from None


class FlukeReadout:
    """A Fluke / Hart Scientific 1521, 1522, 1504, 1523 or 1524 thermometer readout on a serial port, read through
    its simple-format protocol (``fetch?`` -> ``t: 25.587 C``); every reading is returned in deg C.

    Args:
        port: the serial device (``/dev/ttyUSB0``, ``COM3``) or a pyserial URL (``socket://host:port`` for a
            terminal server).
        baud: 2400, fixed on the 1521/1522.
        timeout_s: how long to wait for each reply (a reply is ~20 bytes: 80 ms at 2400 baud).
    """

    def __init__(self, port: str, baud: int = BAUD, timeout_s: float = 2.0):
        self.port, self.baud, self.timeout_s = str(port), int(baud), float(timeout_s)
        self.model: str | None = None
        self.firmware: str | None = None
        self._ser = None
        self._lock = threading.Lock()

    @property
    def name(self) -> str:
        """``Fluke 1522 readout on /dev/pts/3`` (the model once connected)."""
        return f"Fluke {self.model + ' ' if self.model else ''}readout on {self.port}"

    # --- connection ---------------------------------------------------------------------------------------------

    def connect(self) -> None:
        """Open the port (8N1, no flow control) and identify the readout with ``*ver``; keeps ``model``."""
        if self._ser is not None:
            return
        import serial

        try:
            self._ser = serial.serial_for_url(self.port, baudrate=self.baud, bytesize=serial.EIGHTBITS,
                                              parity=serial.PARITY_NONE, stopbits=serial.STOPBITS_ONE,
                                              xonxoff=False, rtscts=False, dsrdtr=False, timeout=self.timeout_s,
                                              write_timeout=self.timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise NotConnectedError(f"{self.name}: cannot open the port ({exc}); check the cable, the USB-serial "
                                    "adapter and the device path") from None
        try:
            reply = self.command("*ver")
            m = _VER.fullmatch(reply.strip())
            if m is None:
                raise GarbledReplyError(f"{self.name}: '*ver' answered {reply!r}, not a Fluke/Hart readout; check "
                                        f"the port and that the readout is at {self.baud} baud")
            self.model, self.firmware = m.group(1), m.group(2)
        except DriverError:
            self.close()
            raise

    def close(self) -> None:
        """Close the port; safe to call twice and on a port that is gone."""
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # a port that is gone cannot be closed cleanly
                pass

    def __enter__(self) -> FlukeReadout:
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- the protocol -------------------------------------------------------------------------------------------

    def command(self, cmd: str, reply: bool = True) -> str:
        """Send one command line (CR-terminated); return its reply line without CR LF, or ``""`` when ``reply`` is
        False (setting commands, ``u=F``, answer nothing). A ``?`` reply raises ``DeviceRefusedError``."""
        import termios

        import serial

        with self._lock:
            ser = self._ser
            if ser is None:
                raise NotConnectedError(f"{self.name}: not connected; call connect()")
            deadline = time.monotonic() + self.timeout_s
            try:
                ser.reset_input_buffer()  # a stale or unasked reading must not be taken for this reply
                ser.write(cmd.encode("ascii") + b"\r")
                ser.flush()
                raw = self._read_line(ser, cmd, deadline) if reply else b"\r\n"
            except (serial.SerialException, OSError, termios.error) as exc:
                self.close()
                raise NotConnectedError(f"{self.name}: the port failed during '{cmd}' ({exc}); is the readout "
                                        "unplugged or off? reconnect it and call connect()") from None
        if not raw.endswith(b"\n"):
            raise NoReplyError(f"{self.name}: no reply to '{cmd}' within {self.timeout_s:.2f} s (got {raw!r}); check "
                               f"that the readout is on, the RS-232 cable (null-modem) and {self.baud} baud")
        text = raw.decode("latin-1").strip()
        if any(not 32 <= ord(ch) <= 126 for ch in text):
            raise GarbledReplyError(f"{self.name}: unreadable reply {raw!r} to '{cmd}'; check the baud rate "
                                    f"({self.baud}) and the cable")
        if text == "?":
            raise DeviceRefusedError(f"{self.name}: the readout did not understand '{cmd}' (answered '?'); check "
                                     "the command against its manual", 0)
        return text

    def _read_line(self, ser, cmd: str, deadline: float) -> bytes:
        """Bytes up to the reply's LF (what came before the deadline if none); skips an echo of ``cmd``."""
        got = b""
        while time.monotonic() < deadline:
            ser.timeout = max(0.005, deadline - time.monotonic())
            chunk = ser.read_until(b"\n")
            if not chunk:
                break
            got += chunk
            if got.endswith(b"\n"):
                if got.strip().lower() in (b"", cmd.lower().encode("ascii", "replace")):
                    got = b""  # an empty line, or the readout (or a terminal server) set to full duplex echoing
                    continue
                break
        return got

    def unit(self) -> str:
        """``u``: the unit the readout reports in (C, F, K, R, or O for ohms)."""
        text = self.command("u")
        m = _UNIT.fullmatch(text)
        if m is None:
            raise GarbledReplyError(f"{self.name}: 'u' answered {text!r}, not a unit; check the baud rate and the "
                                    "cable")
        return m.group(1).upper()

    def set_unit(self, unit: str) -> None:
        """``u=C`` (F, K, R, O): set the readout's unit, then read it back (a setting command answers nothing)."""
        unit = unit.strip().upper()
        if unit not in UNITS:
            raise DriverError(f"{self.name}: unit {unit!r} is not one of {', '.join(UNITS)}")
        self.command(f"u={unit}", reply=False)
        got = self.unit()
        if got != unit:
            raise DriverError(f"{self.name}: the readout kept unit {got} after 'u={unit}'; check that its menus are "
                              "not open (the front panel may lock remote settings)")

    def _temperature(self, value: str, unit: str, cmd: str, text: str) -> float:
        if unit.upper() == "O":
            raise NotATemperatureError(f"{self.name}: the readout is set to ohms, not a temperature ('{cmd}' "
                                       f"answered {text!r}); set its unit to C (front panel, or 'u=C')")
        return to_celsius(float(value), unit)

    def read_C(self) -> float:
        """``fetch?``: the current measurement in deg C (F, K, R converted)."""
        text = self.command("fetch?")
        m = _SIMPLE.fullmatch(text)
        if m is not None:
            return self._temperature(m.group(1), m.group(2), "fetch?", text)
        if _BARE.fullmatch(text):  # the 1504/1502A: the value without label and unit, in the unit set
            return self._temperature(text, self.unit(), "fetch?", text)
        raise GarbledReplyError(f"{self.name}: 'fetch?' answered {text!r}, not a reading; check the baud rate and "
                                "the cable")

    def read_extended(self) -> tuple[float, str]:
        """``t``: the current measurement in deg C and the readout's own time stamp (``mm-dd-yyyy hh:mm:ss``, or
        ``hh:mm:ss`` on readouts that give the time only), as text."""
        text = self.command("t")
        m = _EXTENDED.fullmatch(text)
        if m is None:
            raise GarbledReplyError(f"{self.name}: 't' answered {text!r}, not a time-stamped reading; check the "
                                    "baud rate, the cable, and that the readout's time stamp is on")
        return self._temperature(m.group(1), m.group(2), "t", text), " ".join(m.group(3).split())

    def read_n_C(self, n: int = 5, interval_s: float = 0.0) -> list[float]:
        """``n`` readings ``interval_s`` apart, as read: no mean here, since one glitch (a sensor-open -200 C, a
        0.000 dropout) would move it; the caller judges them (``cell.thermal.agreeing_readings``: the median's band)."""
        if n < 1:
            raise DriverError(f"{self.name}: read_n_C needs n >= 1 readings, not {n}")
        values = []
        for i in range(n):
            if i and interval_s > 0:
                time.sleep(interval_s)
            values.append(self.read_C())
        return values
