"""The Fluke readout driver over its real transport (pyserial on a pseudo-terminal) against the emulated readout."""
from __future__ import annotations

import statistics
import time
from datetime import datetime

import pytest

from calibration.errors import DriverError, NotConnectedError
from drivers.gardasoft import DeviceRefusedError, GarbledReplyError, NoReplyError
from drivers.protocols import Thermometer
from drivers.thermometer import FlukeReadout, NotATemperatureError, to_celsius
from sim_backend.gardasoft_emulator import GardasoftSerialEmulator
from sim_backend.thermometer_emulator import ThermometerEmulator, from_celsius, pt100_ohm


def test_reads_a_known_temperature_within_the_noise():
    with ThermometerEmulator(temperature_C=23.4, noise_K=0.005, seed=1) as em, FlukeReadout(em.port) as th:
        assert isinstance(th, Thermometer)
        assert th.model == "1522" and th.firmware == "1.24"
        assert th.name == f"Fluke 1522 readout on {em.port}"
        t = th.read_C()
        assert abs(t - 23.4) < 0.03  # 6 sigma
        assert t == em.readings[-1].value and em.readings[-1].text == f"t: {t:8.3f} C"
        assert em.received == ["*ver", "fetch?"]


@pytest.mark.parametrize("unit", ["F", "K", "R"])
def test_other_units_are_converted_to_celsius(unit):
    with ThermometerEmulator(temperature_C=-12.25, noise_K=0.0, unit=unit) as em, FlukeReadout(em.port) as th:
        assert th.read_C() == pytest.approx(-12.25, abs=1e-3)  # 3 decimals in F, K or R
        assert em.readings[-1].unit == unit
        assert em.readings[-1].value == pytest.approx(from_celsius(-12.25, unit), abs=5e-4)


def test_unit_set_through_the_driver_and_through_a_raw_command():
    with ThermometerEmulator(temperature_C=31.0, noise_K=0.0) as em, FlukeReadout(em.port) as th:
        th.set_unit("f")
        assert em.unit == "F" and th.unit() == "F"
        assert th.read_C() == pytest.approx(31.0, abs=1e-3) and em.readings[-1].value == pytest.approx(87.8)
        assert th.command("u=K", reply=False) == ""
        assert th.unit() == "K" and th.read_C() == pytest.approx(31.0, abs=1e-3)
        assert em.received == ["*ver", "u=F", "u", "u", "fetch?", "u=K", "u", "fetch?"]
        with pytest.raises(DriverError, match="unit 'X' is not one of C, F, K, R, O"):
            th.set_unit("x")


def test_ohms_are_refused_with_a_clear_error():
    with ThermometerEmulator(temperature_C=100.0, noise_K=0.0, unit="O") as em, FlukeReadout(em.port) as th:
        with pytest.raises(NotATemperatureError, match=rf"readout on {em.port}: the readout is set to ohms, not a "
                                                       r"temperature \('fetch\?' answered 't:  138.505 O'\)"):
            th.read_C()
        assert em.readings[-1].value == pytest.approx(pt100_ohm(100.0), abs=5e-4)
        with pytest.raises(NotATemperatureError, match="set to ohms"):
            th.read_extended()
        th.set_unit("C")
        assert th.read_C() == pytest.approx(100.0)


def test_no_reply_is_a_timeout_naming_the_port_and_the_next_exchange_is_clean():
    with ThermometerEmulator(temperature_C=20.0) as em, FlukeReadout(em.port, timeout_s=0.2) as th:
        em.fault = "no_reply"
        start = time.monotonic()
        with pytest.raises(NoReplyError, match=rf"Fluke 1522 readout on {em.port}: no reply to 'fetch\?' within "
                                               r"0.20 s \(got b''\); check that the readout is on") as info:
            th.read_C()
        assert 0.15 < time.monotonic() - start < 5.0  # upper bound loose: a loaded machine
        assert isinstance(info.value, NotConnectedError) and "\n" not in str(info.value)
        em.fault = None
        assert abs(th.read_C() - 20.0) < 0.05


def test_a_silent_or_foreign_device_fails_connect():
    with ThermometerEmulator(fault="no_reply") as em:
        th = FlukeReadout(em.port, timeout_s=0.1)
        with pytest.raises(NoReplyError, match=rf"Fluke readout on {em.port}: no reply to '\*ver'"):
            th.connect()
        with pytest.raises(NotConnectedError, match="not connected; call connect"):
            th.read_C()  # a failed connect leaves the port closed
    with GardasoftSerialEmulator() as light:  # the light controller's port given by mistake: it answers "Err 2"
        with pytest.raises(GarbledReplyError, match=r"'\*ver' answered 'Err 2', not a Fluke/Hart readout; check "
                                                    r"the port and that the readout is at 2400 baud"):
            FlukeReadout(light.port, timeout_s=0.3).connect()


def test_garbled_reply_names_the_bytes_and_the_port():
    with ThermometerEmulator(temperature_C=20.0) as em, FlukeReadout(em.port, timeout_s=0.3) as th:
        em.fault = "garbled"
        with pytest.raises(GarbledReplyError, match=rf"readout on {em.port}: unreadable reply b'\\x15\\xf8t\\x7f"
                                                    r"\\x00:\\xe6\\x8c\\r\\n' to 'fetch\?'; check the baud rate"):
            th.read_C()
        em.fault = None
        assert abs(th.read_C() - 20.0) < 0.05


def test_unplugged_mid_session_is_not_connected():
    em = ThermometerEmulator(temperature_C=20.0).start()
    th = FlukeReadout(em.port, timeout_s=0.3)
    try:
        th.connect()
        th.read_C()
        em.unplug()
        with pytest.raises(NotConnectedError, match=rf"readout on {em.port}: the port failed during 'fetch\?' "
                                                    r"\(.*\); is the readout unplugged or off\?"):
            th.read_C()
        with pytest.raises(NotConnectedError, match=rf"Fluke 1522 readout on {em.port}: not connected; call connect"):
            th.read_n_C()
    finally:
        th.close()
        th.close()  # twice is safe
        em.stop()


def test_missing_port_is_not_connected():
    with pytest.raises(NotConnectedError, match="readout on /dev/does-not-exist-probe: cannot open the port"):
        FlukeReadout("/dev/does-not-exist-probe").connect()


def test_n_readings_are_the_readouts_own():
    with ThermometerEmulator(temperature_C=26.0, noise_K=0.05, seed=7) as em, FlukeReadout(em.port) as th:
        start = time.monotonic()
        values = th.read_n_C(20, interval_s=0.01)
        assert time.monotonic() - start >= 0.19
        served = [r.value for r in em.readings]
        assert values == pytest.approx(served, abs=1e-12) and len(served) == 20
        assert abs(statistics.fmean(values) - 26.0) < 0.05 and 0.02 < statistics.stdev(values) < 0.1
        assert th.read_n_C(1) == pytest.approx([em.readings[-1].value], abs=1e-12)
        with pytest.raises(DriverError, match="n >= 1"):
            th.read_n_C(0)


def test_a_warming_part_is_followed_reading_by_reading():
    temps = iter([20.0, 20.5, 21.0])
    with ThermometerEmulator(temperature_C=lambda: next(temps), noise_K=0.0) as em, FlukeReadout(em.port) as th:
        assert [th.read_C() for _ in range(3)] == [20.0, 20.5, 21.0]
        assert [r.celsius for r in em.readings] == [20.0, 20.5, 21.0]


def test_extended_format_gives_the_readouts_time_stamp():
    with ThermometerEmulator(temperature_C=125.745, noise_K=0.0, unit="K") as em, FlukeReadout(em.port) as th:
        before = datetime.now().replace(microsecond=0)
        value, stamp = th.read_extended()
        after = datetime.now()
        assert value == pytest.approx(125.745, abs=1e-3)
        when = datetime.strptime(stamp, "%m-%d-%Y %H:%M:%S")
        assert before <= when <= after
        assert em.received[-1] == "t" and em.readings[-1].text == "t:  398.895 K"


def test_unknown_command_is_refused():
    with ThermometerEmulator() as em, FlukeReadout(em.port) as th:
        with pytest.raises(DeviceRefusedError, match=rf"readout on {em.port}: the readout did not understand 'time'"):
            th.command("time")


def test_the_emulator_takes_every_form_of_a_command():
    em = ThermometerEmulator(temperature_C=25.587, noise_K=0.0, model="1521", firmware="2.11")  # not started: no pty
    for cmd in ["f", "FETCH?", "fetc?", "rea", "Read?", "me", "meas?", "measure?"]:
        assert em.execute(cmd) == "t:   25.587 C\r\n", cmd
    assert em.execute("T").startswith("t:   25.587 C ") and em.execute("temperature").endswith("\r\n")
    assert em.execute("*ver") == "ver.1521,2.11\r\n" and em.execute("*IDN?") == "HART,1521,A12345,2.11\r\n"
    assert em.execute("u = r") is None and em.execute("unit") == "u: R\r\n"
    assert em.execute("u=X") == "?\r\n" and em.execute("fetchx") == "?\r\n" and em.execute("ti") == "?\r\n"
    with pytest.raises(ValueError, match="unknown fault"):
        em.fault = "smoke"


class _Bare1504(ThermometerEmulator):
    """A 1504: ``FETCH?`` answers the bare number, without the label and the unit."""

    def execute(self, line: str) -> str | None:
        reply = super().execute(line)
        if line.lower().startswith("f") and reply and reply.startswith("t:"):
            return reply.split()[1] + "\r\n"
        return reply


def test_a_bare_number_is_read_in_the_unit_the_readout_reports():
    with _Bare1504(temperature_C=40.0, noise_K=0.0, model="1504", unit="F") as em, FlukeReadout(em.port) as th:
        assert th.read_C() == pytest.approx(40.0, abs=1e-3)
        assert em.received == ["*ver", "fetch?", "u"]


def test_unit_conversions_round_trip():
    for unit in "CFKR":
        assert to_celsius(from_celsius(-40.0, unit), unit) == pytest.approx(-40.0)
    assert to_celsius(32.0, "f") == 0.0 and to_celsius(0.0, "K") == -273.15
    assert pt100_ohm(0.0) == 100.0 and pt100_ohm(-100.0) == pytest.approx(60.2558, abs=1e-4)
    with pytest.raises(ValueError, match="not a temperature unit"):
        to_celsius(100.0, "O")
