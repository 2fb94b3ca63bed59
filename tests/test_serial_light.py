"""The serial light driver over the real pyserial path, against the emulator on a pseudo-terminal."""
from __future__ import annotations

import time

import pytest

from calibration.errors import DriverError, NotConnectedError
from drivers.protocols import Light
from drivers.serial_light import DeviceRefusedError, GarbledReplyError, NoReplyError, SerialLight
from sim_backend.serial_emulator import SerialEmulator


def test_light_satisfies_protocol_and_sets_intensity_and_strobes():
    with SerialEmulator() as emulator, SerialLight(emulator.port, timeout_s=0.5) as light:
        assert isinstance(light, Light)
        assert light.device_id == SerialEmulator.model
        light.set_intensity(0.8)
        light.strobe(0.002)
        light.strobe(0.0155)
        assert emulator.intensity == pytest.approx(0.80)
        assert emulator.strobes_s == pytest.approx([0.002, 0.0155])
        assert emulator.received == ["ID?", "INT 0.80", "STROBE 0.0020", "STROBE 0.0155"]


def test_no_reply_raises_no_reply_error_after_the_timeout():
    with SerialEmulator() as emulator, SerialLight(emulator.port, timeout_s=0.2) as light:
        emulator.fault = "no_reply"
        start = time.monotonic()
        with pytest.raises(NoReplyError, match="no reply to 'INT 0.50' within 0.20 s"):
            light.set_intensity(0.5)
        assert 0.15 < time.monotonic() - start < 1.0
        assert isinstance(NoReplyError("x"), NotConnectedError)


def test_silent_device_fails_connect_with_not_connected():
    with SerialEmulator(fault="no_reply") as emulator:
        light = SerialLight(emulator.port, timeout_s=0.1)
        with pytest.raises(NotConnectedError, match="no reply to 'ID\\?'"):
            light.connect()


def test_garbled_reply_raises_garbled_reply_error():
    with SerialEmulator() as emulator, SerialLight(emulator.port, timeout_s=0.3) as light:
        emulator.fault = "garbled"
        with pytest.raises(GarbledReplyError, match="unexpected reply"):
            light.strobe(0.002)
        emulator.fault = None  # the next exchange is clean again: no stale bytes are taken for a reply
        light.strobe(0.003)
        assert emulator.strobes_s[-1] == pytest.approx(0.003)


def test_device_error_reply_raises_device_refused():
    with SerialEmulator() as emulator, SerialLight(emulator.port) as light:
        with pytest.raises(DeviceRefusedError, match="ERR unknown command"):
            light._transact("FLASH", r"OK")


def test_values_outside_range_are_refused_before_sending():
    with SerialEmulator() as emulator, SerialLight(emulator.port) as light:
        with pytest.raises(DriverError, match="outside"):
            light.set_intensity(1.2)
        with pytest.raises(DriverError, match="outside"):
            light.strobe(0.5)
        assert emulator.received == ["ID?"]


def test_port_gone_raises_not_connected():
    emulator = SerialEmulator()
    light = SerialLight(emulator.port, timeout_s=0.3)
    light.connect()
    emulator.unplug()
    with pytest.raises(NotConnectedError):
        light.set_intensity(0.3)
    with pytest.raises(NotConnectedError, match="not connected"):
        light.strobe(0.001)
    light.close()


def test_missing_port_raises_not_connected():
    with pytest.raises(NotConnectedError, match="cannot open the port"):
        SerialLight("/dev/does-not-exist-light").connect()
