"""The Gardasoft RT driver over its real transports (pyserial on a pseudo-terminal, a TCP socket)
against the emulator of the RT command set."""
from __future__ import annotations

import time

import pytest

from calibration.errors import DriverError, NotConnectedError
from drivers.gardasoft import (
    ERRORS,
    DeviceRefusedError,
    GardasoftRT,
    GarbledReplyError,
    NoReplyError,
    TimingAdjustedError,
    max_pulse_ms,
    parse_status,
)
from drivers.protocols import Light
from sim_backend.gardasoft_emulator import GardasoftSerialEmulator, GardasoftTcpEmulator


def _open(kind, **kw):
    """(emulator, driver kwargs) for a transport."""
    if kind == "serial":
        em = GardasoftSerialEmulator(**kw)
        return em, {"port": em.port}
    em = GardasoftTcpEmulator(**kw)
    return em, {"host": em.host, "tcp_port": em.port}


TRANSPORTS = ["serial", "tcp"]


@pytest.mark.parametrize("kind", TRANSPORTS)
def test_pulse_mode_strobe_and_status(kind):
    em, where = _open(kind)
    with em, GardasoftRT(**where, channel=3, trigger_input=2, brightness_pct=250.0, timeout_s=0.5) as light:
        assert isinstance(light, Light)
        assert light.device_id == "RT820-20 (HW02) V031"
        light.strobe(0.002)
        light.strobe(0.002)  # same pulse: read back (ST), then only the trigger is sent again
        st = light.status()
        assert st["mode"] == "pulse" and st["input"] == 2
        assert st["pulse_s"] == pytest.approx(0.002) and st["brightness_pct"] == pytest.approx(250.0)
        assert st["delay_s"] == pytest.approx(2e-5)  # the RT range's least delay, 0.02 ms
        assert [(p.channel, p.width_s, p.brightness_pct, p.source) for p in em.controller.pulses] == \
            [(3, pytest.approx(0.002), 250.0, "TR")] * 2
        # the settings read back after they are sent and before each trigger (a controller that lost them is found)
        assert em.controller.received == ["VR", "RP3,2", "RT3,2.000,0.020,250", "ST3", "TR3", "ST3", "TR3", "ST3"]
        # the camera's strobe line on input 2 fires channel 3
        assert em.controller.input_edge(2) == 1 and em.controller.input_edge(1) == 0
        light.set_continuous(40)
        assert light.status()["mode"] == "continuous"
        light.set_switched(60)
        assert light.status()["mode"] == "switched"
        light.save()
        assert em.controller.saved


def test_retrigger_delay_ignores_triggers_too_soon_as_the_device_does():
    with GardasoftSerialEmulator() as em, GardasoftRT(em.port, retrigger_s=0.2) as light:
        light.set_pulse(0.001)
        light.trigger()
        light.trigger()  # within 200 ms of the first: ignored
        assert len(em.controller.pulses) == 1
        assert light.status()["retrigger_s"] == pytest.approx(0.2)


@pytest.mark.parametrize("cmd, code", [("XX1", 2), ("RS1", 4), ("RS1,abc", 3), ("RS9,50", 1), ("RS1,150", 1),
                                       ("RT1,5,0.01,400", 1), ("RT1,1,0.001,100", 5), ("RP1", 4), ("TR1,2", 4)])
def test_every_error_code_of_the_protocol_is_a_clear_refusal(cmd, code):
    with GardasoftSerialEmulator() as em, GardasoftRT(em.port) as light:
        cls = TimingAdjustedError if code == 5 else DeviceRefusedError
        with pytest.raises(cls, match=rf"light controller RT820-20 \(HW02\) V031 on {em.port}: '{cmd}' refused: "
                                      rf"Err {code} \({ERRORS[code]}\)") as info:
            light.command(cmd)
        assert info.value.code == code
        assert light.last_event() == (0, code)  # GR reports it once, then it is cleared
        assert light.last_event() is None


def test_pulse_limits_are_checked_before_sending():
    assert max_pulse_ms(100) == 999 and max_pulse_ms(250) == 10 and max_pulse_ms(1000) == 1 and max_pulse_ms(1001) == 0
    with GardasoftSerialEmulator() as em, GardasoftRT(em.port, brightness_pct=600) as light:
        with pytest.raises(DriverError, match="pulse width 2 ms is outside \\(0, 1\\] ms at 600 %"):
            light.strobe(0.002)
        with pytest.raises(DriverError, match="outside 0..100"):
            light.set_continuous(120)
        assert em.controller.received == ["VR"]


@pytest.mark.parametrize("kind", TRANSPORTS)
def test_no_reply_is_a_timeout_naming_the_device(kind):
    em, where = _open(kind)
    with em, GardasoftRT(**where, timeout_s=0.2) as light:
        em.fault = "no_reply"
        start = time.monotonic()
        with pytest.raises(NoReplyError, match="no reply to 'TR1' within 0.20 s"):
            light.trigger()
        assert 0.15 < time.monotonic() - start < 5.0  # upper bound loose: a loaded machine
        assert isinstance(NoReplyError("x"), NotConnectedError)
        em.fault = None
        time.sleep(0.05)
        light.trigger()  # the next exchange is clean


@pytest.mark.parametrize("kind", TRANSPORTS)
def test_garbled_reply_is_refused_and_the_next_exchange_is_clean(kind):
    em, where = _open(kind)
    with em, GardasoftRT(**where, timeout_s=0.3) as light:
        em.fault = "garbled"
        with pytest.raises(GarbledReplyError, match="unreadable reply"):
            light.strobe(0.001)
        em.fault = None
        light.strobe(0.001)
        assert len(em.controller.pulses) == 1


def test_silent_or_foreign_device_fails_connect():
    with GardasoftSerialEmulator(fault="no_reply") as em:
        with pytest.raises(NotConnectedError, match="no reply to 'VR'"):
            GardasoftRT(em.port, timeout_s=0.1).connect()
    with GardasoftSerialEmulator() as em:
        em.controller.model = "PP610 V2"
        with pytest.raises(GarbledReplyError, match="not an RT-series controller"):
            GardasoftRT(em.port).connect()


@pytest.mark.parametrize("kind", TRANSPORTS)
def test_port_or_connection_gone_is_not_connected(kind):
    em, where = _open(kind)
    light = GardasoftRT(**where, timeout_s=0.3)
    light.connect()
    em.unplug()
    with pytest.raises(NotConnectedError):
        light.strobe(0.001)
    with pytest.raises(NotConnectedError, match="not connected"):
        light.trigger()
    light.close()


def test_missing_port_or_host_is_not_connected():
    with pytest.raises(NotConnectedError, match="cannot open the port"):
        GardasoftRT("/dev/does-not-exist-light").connect()
    with GardasoftTcpEmulator() as em:
        port = em.port
    with pytest.raises(NotConnectedError, match=f"127.0.0.1:{port}: cannot connect"):
        GardasoftRT(host="127.0.0.1", tcp_port=port, timeout_s=0.2).connect()


def test_status_line_parser_tolerates_spacing():
    st = parse_status("CH 1, MD 1, S 100%, DL 0.01ms, PU 2.00ms, RT 0.0ms, IP 1, FL 0, CS 0.00A, RA 1.00A")
    assert st["MD"] == "1" and st["PU"] == "2.00ms" and st["RA"] == "1.00A"
    assert parse_status("TM 1, TP 20.00ms") == {"TM": "1", "TP": "20.00ms"}
