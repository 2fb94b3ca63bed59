"""Device faults that went through silently before (outside tester's findings, 2026-11):

1. packed pixel formats unpacked twice (harvesters' ``Component2DImage.data`` is already expanded);
2. a light controller that lost its settings (power blip) and was only sent ``TR`` afterwards;
3. a frame of another size than the job's camera accepted;
4. one bad thermometer reading in the mean;
5. the Gardasoft delay below the RT range, and a multi-line ``ST`` reply merged over its channels.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from calibration.errors import DriverError
from drivers.pixels import MONO_FORMATS, bit_depth, pack
from drivers.protocols import Frame, RobotState, SafetyStatus

# --- 1. the pixels through harvesters' own image component ------------------------------------------------------


class _GenTLBuffer:
    """What harvesters' ``Component2DImage`` reads of a GenTL buffer (``genicam.gentl.Buffer``): its bytes, size,
    pixel format code, padding and offsets."""

    def __init__(self, raw: bytes, fmt: str, width: int, height: int, pad: int = 0):
        from harvesters.util.pfnc import dict_by_names

        if pad:  # pad bytes (0xAB) at the end of every line
            lines = np.frombuffer(raw, dtype=np.uint8).reshape(height, -1)
            raw = np.concatenate([lines, np.full((height, pad), 0xAB, np.uint8)], axis=1).tobytes()
        self.raw_buffer = bytearray(raw)
        self.width, self.height, self.delivered_image_height = width, height, height
        self.pixel_format = dict_by_names[fmt]
        self.padding_y = self.offset_x = self.offset_y = 0
        self.padding_x = pad


def _harvesters_buffer(image: np.ndarray, fmt: str, frame_id: int = 1, pad: int = 0):
    """A fetched harvesters buffer as the driver sees it, whose component is harvesters' own Component2DImage."""
    from harvesters.core import Component2DImage

    h, w = image.shape
    comp = Component2DImage(buffer=_GenTLBuffer(pack(image, fmt), fmt, w, h, pad), part=None,
                            node_map=SimpleNamespace())
    return SimpleNamespace(frame_id=frame_id, timestamp_ns=123, payload=SimpleNamespace(components=[comp]))


@pytest.mark.parametrize("fmt", MONO_FORMATS)
def test_every_pixel_format_through_harvesters_component_gives_the_cameras_pixels(fmt):
    """The camera's pixels packed as on the wire, through harvesters 1.4's ``Component2DImage`` (which expands
    them itself), the driver's ``_buffer_facts`` and ``_frame``: the same pixels. Before the fix Mono10p, Mono12p,
    Mono10Packed and Mono12Packed came out wrong (unpacked a second time: errors up to 4000 counts)."""
    from drivers.genicam import GenICamCamera, _buffer_facts

    rng = np.random.default_rng(7)
    image = rng.integers(0, 1 << bit_depth(fmt), size=(12, 64), dtype=np.uint16)
    if fmt == "Mono8":
        image = image.astype(np.uint8)
    cam = GenICamCamera("7", pixel_format=fmt, expected_size=(64, 12))
    frame = cam._frame(_buffer_facts(_harvesters_buffer(image, fmt), with_data=True), 0.0, 0.0, 0)
    assert frame.image.shape == (12, 64) and frame.image.dtype == (np.uint8 if fmt == "Mono8" else np.uint16)
    np.testing.assert_array_equal(frame.image, image)


def test_a_frame_of_another_size_or_with_line_padding_is_refused_by_the_genicam_driver():
    from drivers.genicam import FrameGeometryError, GenICamCamera, PixelFormatError, _buffer_facts

    image = np.arange(12 * 64, dtype=np.uint16).reshape(12, 64) % 4096
    cam = GenICamCamera("7", pixel_format="Mono12p", expected_size=(80, 12))
    with pytest.raises(FrameGeometryError, match="camera 7: frame of 64x12 pixels, configured 80x12"):
        cam._frame(_buffer_facts(_harvesters_buffer(image, "Mono12p"), with_data=True), 0.0, 0.0, 0)
    cam = GenICamCamera("7", pixel_format="Mono12p")
    cam.geometry = {"Width": 64, "Height": 12, "OffsetX": 16, "OffsetY": 0}  # as read back at connect
    with pytest.raises(FrameGeometryError, match="camera 7: frame at OffsetX 0, configured 16"):
        cam._frame(_buffer_facts(_harvesters_buffer(image, "Mono12p"), with_data=True), 0.0, 0.0, 0)


@pytest.mark.parametrize("fmt", ["Mono8", "Mono12", "Mono12p"])
def test_line_padding_is_taken_out_of_the_frame(fmt):
    """GenTL ``padding_x`` bytes end every line (harvesters 1.4.3 leaves them in its ``data``: the rows shear)."""
    from drivers.genicam import GenICamCamera, _buffer_facts

    image = (np.arange(12 * 64).reshape(12, 64) * 37 % (1 << bit_depth(fmt))).astype(np.uint16)
    if fmt == "Mono8":
        image = image.astype(np.uint8)
    buf = _harvesters_buffer(image, fmt, pad=8)
    frame = GenICamCamera("7", pixel_format=fmt)._frame(_buffer_facts(buf, with_data=True), 0.0, 0.0, 0)
    np.testing.assert_array_equal(frame.image, image)


@pytest.mark.parametrize("fmt", MONO_FORMATS)
def test_harvesters_already_expanded_data_is_taken_as_pixels_not_unpacked_again(fmt):
    """Where the consumer hands only ``Component2DImage.data`` (harvesters' own ``expand`` of the bytes), its dtype
    says what it is: uint16 words are the pixels, uint8 the wire's bytes."""
    from harvesters.util.pfnc import Dictionary

    from drivers.pixels import from_component

    rng = np.random.default_rng(3)
    image = rng.integers(0, 1 << bit_depth(fmt), size=(8, 64), dtype=np.uint16)
    data = Dictionary.get_proxy(symbolic=fmt).expand(np.frombuffer(pack(image, fmt), dtype=np.uint8).copy())
    np.testing.assert_array_equal(from_component(np.asarray(data), fmt, 64, 8), image)


def test_a_frame_size_changed_behind_the_driver_is_refused_on_the_simulated_producer():
    """genicam's simulated producer (Viky): the ROI set to 320x240 at connect, then changed to 400x300 behind the
    driver (another program, a vendor tool). Before: the 400x300 frame was delivered without a word."""
    from drivers.genicam import FrameGeometryError, GenICamCamera, Roi, simulated_producer

    producer = simulated_producer()
    if producer is None:
        pytest.skip("the genicam package (viky.cti) is not installed")
    with GenICamCamera("1", producer=producer, roi=Roi(0, 0, 320, 240), expected_size=(320, 240)) as cam:
        assert cam.capture().image.shape == (240, 320)
        cam._ia.stop()
        cam.node_map.Width.value, cam.node_map.Height.value = 400, 300
        cam._ia.start()
        with pytest.raises(FrameGeometryError, match="camera 1: frame of 400x300 pixels, configured 320x240"):
            cam.capture()
    with pytest.raises(FrameGeometryError, match="camera 1: delivers 320x240 frames, expected 640x480"):
        GenICamCamera("1", producer=producer, roi=Roi(0, 0, 320, 240), expected_size=(640, 480)).connect()


# --- 2. and 3. the exposure: the light armed as configured, the frame of the job's size ------------------------

Q = np.zeros(6)


class _Robot:
    def state(self):
        return RobotState(joints_rad=Q, base_from_flange=np.eye(4), safety=SafetyStatus(normal=True), timestamp_s=2.0)


class _Camera:
    """Frames of ``shape``; with ``strobe`` (the camera's strobe line) it fires the controller's input 1."""

    def __init__(self, shape=(48, 64), strobe=None):
        self.n, self.shape, self.strobe = 0, shape, strobe

    def capture(self):
        import time

        if self.strobe is not None:
            self.strobe()
        self.n += 1
        return Frame(image=np.zeros(self.shape, np.uint8), timestamp_s=time.time(), exposure_s=0.002,
                     meta={"frame_id": self.n, "camera": "test"})


def _take(taker, station):
    import time

    settled = RobotState(joints_rad=Q, base_from_flange=np.eye(4), safety=SafetyStatus(normal=True), timestamp_s=1.0)
    return taker.take(station, 1, settled, time.time(), 0.0, 0.02)


@pytest.mark.parametrize("by_line", [False, True])
def test_a_light_controller_that_lost_its_settings_is_found_and_rearmed_and_said(by_line):
    """The Gardasoft driver on its emulator, the controller power-cycled (back to continuous at 0 %) as the 2nd
    exposure's TR arrives (software trigger), or between exposures (strobe line). Before: only TR / the input edge was
    sent afterwards, accepted, and nothing flashed; the frames went on as if lit. Now the exposure whose light was
    lost is a frame fault naming the light controller, the next one re-arms it and says so, and it flashes."""
    from cell.stages.exposure import ExposureTaker, FrameFault
    from drivers.gardasoft import GardasoftRT
    from sim_backend.gardasoft_emulator import GardasoftSerialEmulator

    notices = []
    with GardasoftSerialEmulator() as em, GardasoftRT(em.port, trigger_input=1 if by_line else None,
                                                      timeout_s=0.5) as light:
        ctl = em.controller
        camera = _Camera(strobe=(lambda: ctl.input_edge(1)) if by_line else None)
        taker = ExposureTaker(_Robot(), camera, light, exposure_s=0.002, frame_timeout_s=2.0, light_by_line=by_line,
                              frame_size=(64, 48), on_notice=lambda sid, line: notices.append((sid, line)))
        _take(taker, "S1")
        assert len(ctl.pulses) == 1
        if by_line:  # the blip between two exposures: found before the next one, re-armed, said; it flashes
            ctl.power_cycle()
            _, rec = _take(taker, "S2")
            assert len(ctl.pulses) == 2 and rec.light_note == notices[0][1]
        else:  # the blip as the trigger arrives: no flash; the frame is refused, the retake re-arms and flashes
            ctl.power_cycle_at_trigger = 2
            with pytest.raises(FrameFault, match=r"station S2: after the exposure, light controller RT820-20 \(HW02\) "
                                                 rf"V031 on {em.port}: channel 1 reads continuous mode at 0 %") as info:
                _take(taker, "S2")
            assert info.value.outcome == "unlit" and len(ctl.pulses) == 1 and not notices
            _, rec = _take(taker, "S2")
            assert len(ctl.pulses) == 2 and ctl.pulses[-1].brightness_pct == 100.0
        assert [sid for sid, _ in notices] == ["S2"] and light.rearmed == 1
        assert "continuous mode at 0 %" in notices[0][1] and "re-armed" in notices[0][1]
        assert f"on {em.port}" in notices[0][1] and "\n" not in notices[0][1]
        _take(taker, "S3")
        assert len(ctl.pulses) == 3 and len(notices) == 1  # armed again: nothing more to say


def test_settings_saved_with_aw_come_back_after_a_power_cycle_and_nothing_is_said():
    from drivers.gardasoft import GardasoftRT
    from sim_backend.gardasoft_emulator import GardasoftSerialEmulator

    with GardasoftSerialEmulator() as em, GardasoftRT(em.port) as light:
        assert light.strobe(0.002) is None
        light.save()
        em.controller.power_cycle()
        assert light.check() is None and light.strobe(0.002) is None and len(em.controller.pulses) == 2


def test_a_controller_that_accepts_the_pulse_settings_but_does_not_show_them_faults():
    from drivers.gardasoft import GardasoftRT
    from sim_backend.gardasoft_emulator import GardasoftSerialEmulator

    with GardasoftSerialEmulator() as em, GardasoftRT(em.port) as light:
        original = em.controller._one

        def forgetful(cmd):  # takes RT, keeps nothing
            return "" if cmd.startswith("RT") else original(cmd)

        em.controller._one = forgetful
        with pytest.raises(DriverError, match=rf"light controller RT820-20 \(HW02\) V031 on {em.port}: the pulse "
                                              "settings were sent and accepted, but channel 1 reads continuous mode"):
            light.strobe(0.002)
        assert not em.controller.pulses


def test_a_frame_not_of_the_jobs_camera_size_is_a_frame_fault_naming_both_sizes():
    """Before: a frame cropped by an ROI offset or halved by binning was stored as the station's image."""
    from cell.stages.exposure import ExposureTaker, FrameFault

    camera = _Camera(shape=(48, 64))
    taker = ExposureTaker(_Robot(), camera, None, exposure_s=0.002, frame_timeout_s=2.0, light_by_line=False,
                          frame_size=(64, 48))
    _, rec = _take(taker, "S1")
    assert rec.frame_size == [64, 48]
    camera.shape = (18, 24)
    with pytest.raises(FrameFault, match=r"station S2: the camera delivered a 24x18 frame, the job's camera is 64x48 "
                                         r"\(\[camera\] width x height\)") as info:
        _take(taker, "S2")
    assert info.value.outcome == "size" and info.value.record.frame_size == [24, 18]
    # without the job's size (the calibration captures), the session's first frame sets it
    taker = ExposureTaker(_Robot(), _Camera(shape=(48, 64)), None, exposure_s=0.002, frame_timeout_s=2.0,
                          light_by_line=False)
    _take(taker, "S1")
    taker.camera.shape = (48, 60)
    with pytest.raises(FrameFault, match="delivered a 60x48 frame, this session's first frame was 64x48"):
        _take(taker, "S2")


def test_acquire_says_a_rearmed_light_on_the_console_in_the_run_log_and_in_the_journal():
    from cell.stages.acquire import _light_rearmed

    journal, said, logged = [], [], []
    ctx = SimpleNamespace(say=said.append, log=SimpleNamespace(log=lambda level, m: logged.append((level, m))),
                          folder=SimpleNamespace(append=lambda event, **f: journal.append({"event": event} | f)))
    _light_rearmed(ctx, "S7", "light controller X on /dev/ttyS0: channel 1 reads continuous mode at 0 % ...")
    assert journal == [{"event": "light_rearmed", "station": "S7",
                        "detail": "light controller X on /dev/ttyS0: channel 1 reads continuous mode at 0 % ..."}]
    assert logged[0][0] == "warning" and "S7" in logged[0][1] and said[0].startswith("  WARNING station S7: light")


# --- 4. the part's thermometer: one bad reading is not averaged in ----------------------------------------------


def _probe_ctx(tmp_path, sigma_K=0.3):
    from cell.loadedjob import load
    from tests.jobutil import job_variant

    bar = {"a": "T0094", "b": "T0100", "length": 357.3936, "sigma": 0.002, "cte_ppm_per_K": 0.5}
    warm = {"part_C": "probe", "part_cte_ppm_per_K": 23.1, "bars_C": 21.0, "part_sigma_K": sigma_K}
    job = load(job_variant(tmp_path / "p", {"job": {"scale_bar": bar}, "thermal": warm}))
    journal, said, logged = [], [], []
    ctx = SimpleNamespace(job=job, say=said.append, log=SimpleNamespace(log=lambda level, m: logged.append((level, m))),
                          folder=SimpleNamespace(records=lambda: list(journal),
                                                 append=lambda event, **f: journal.append({"event": event} | f)))
    return ctx, journal, said, logged


@pytest.mark.parametrize("glitch", [-200.0, 0.0])
def test_one_glitched_probe_reading_is_named_and_left_out(tmp_path, glitch):
    """The 3rd of 5 readings is a sensor-open -200 C or a 0.000 dropout. Before: the part at -19.2 C (sigma 0.3 K)
    or 20.8 C. Now 26 C from the four that agree, the glitch named on the console, in the run log and journal."""
    from cell.thermal import read_probe
    from drivers.thermometer import FlukeReadout
    from sim_backend.thermometer_emulator import ThermometerEmulator

    ctx, journal, said, logged = _probe_ctx(tmp_path)
    with ThermometerEmulator(temperature_C=26.0, seed=1) as emu:
        emu.glitches = {3: glitch}
        probe = FlukeReadout(emu.port)
        probe.connect()
        try:
            read_probe(ctx, probe, "start")
        finally:
            probe.close()
    (rec,) = journal
    assert rec["C"] == pytest.approx(26.0, abs=0.02) and rec["n"] == 4 and rec["outliers"] == [glitch]
    assert len(rec["readings"]) == 5 and rec["sd_K"] < 0.05
    assert any(level == "warning" and "left out as outliers" in m and f"{glitch:.3f}" in m for level, m in logged)
    assert any("left out as outliers" in m for m in said)


@pytest.mark.parametrize("glitches, noise_K", [({2: -200.0, 3: 0.0, 5: -200.0}, 0.005), ({}, 1.0)])
def test_probe_readings_that_do_not_agree_fault_naming_them(tmp_path, glitches, noise_K):
    """Three of five glitched, or a contact flickering by 1 K at part_sigma_K 0.2 K: fewer than three readings agree
    within 0.6 K of their median: ACQUIRE faults with the readings, nothing journalled."""
    from cell.thermal import read_probe
    from drivers.thermometer import FlukeReadout
    from sim_backend.thermometer_emulator import ThermometerEmulator

    ctx, journal, _, _ = _probe_ctx(tmp_path, sigma_K=0.2)
    with ThermometerEmulator(temperature_C=26.0, noise_K=noise_K, seed=3) as emu:
        emu.glitches = glitches
        probe = FlukeReadout(emu.port)
        probe.connect()
        try:
            with pytest.raises(DriverError, match=r"the part's thermometer \(Fluke 1522 readout on .*\) gave 5 readings "
                                                  r"at the start of ACQUIRE that do not agree: only [0-2] within 0.60 K"):
                read_probe(ctx, probe, "start")
        finally:
            probe.close()
    assert not journal


def test_the_readings_scatter_is_carried_into_the_temperatures_sigma(tmp_path):
    from cell.thermal import resolve_probe

    ctx, _, _, _ = _probe_ctx(tmp_path, sigma_K=0.3)
    recs = [{"event": "part_temperature", "when": "start", "C": 26.0, "sd_K": 0.4, "device": "probe"},
            {"event": "part_temperature", "when": "end", "C": 26.0, "sd_K": 0.1}]
    job = resolve_probe(ctx.job, recs)
    assert job.spec.thermal.part_sigma_K == pytest.approx(0.5)  # sqrt(0.3^2 + 0.4^2)
    assert job.probe["scatter_K"] == 0.4


# --- 5. the Gardasoft delay and a multi-line status ---------------------------------------------------------------


def test_the_default_delay_is_the_rt_minimum_and_below_it_the_controller_adjusts_it():
    from drivers.gardasoft import GardasoftRT, TimingAdjustedError
    from sim_backend.gardasoft_emulator import GardasoftSerialEmulator

    with GardasoftSerialEmulator() as em, GardasoftRT(em.port) as light:
        light.set_pulse(0.002)
        assert em.controller.received[-1] == "RT1,2.000,0.020,100"
        assert light.status()["delay_s"] == pytest.approx(2e-5)
        with pytest.raises(TimingAdjustedError, match="Err 5"):
            light.set_pulse(0.002, delay_s=1e-5)
        assert em.controller.channels[1].delay_ms == pytest.approx(0.02)


def test_a_multi_line_status_is_read_per_channel():
    from drivers.gardasoft import parse_status

    text = ("CH1,MD1,S 100.0, 0.0,DL0.020ms,PU2.000ms,RT0.0ms,IP1\r\n"
            "CH2,MD0,S 50.0, 0.0,DL1.000ms,PU1.000ms,RT0.0ms,IP2\r\n")
    assert parse_status(text, 1)["MD"] == "1" and parse_status(text, 1)["PU"] == "2.000ms"
    assert parse_status(text, 2) == {"CH": "2", "MD": "0", "S": "50.0", "DL": "1.000ms", "PU": "1.000ms",
                                     "RT": "0.0ms", "IP": "2"}
    with pytest.raises(ValueError, match="channel 3"):
        parse_status(text, 3)
    with pytest.raises(ValueError, match="say which channel"):
        parse_status(text)
