"""The GenICam driver through harvesters against a real GenTL producer.

The producer is the simulated one shipped in the ``genicam`` package (EMVA's "Viky": three
free-running cameras, Mono8/RGBa8, frame ids, no exposure/gain/trigger nodes); docs/decisions
0016-hw-genicam.md says why this one and not pylon's emulator. Nothing of harvesters is mocked.
"""
from __future__ import annotations

import time

import numpy as np
import pytest

from calibration.errors import InputError, NotConnectedError
from drivers.genicam import (
    CameraLostError,
    IncompleteFrameError,
    CameraNotFoundError,
    FeatureError,
    FrameLostError,
    FrameTimeoutError,
    GenICamCamera,
    PixelFormatError,
    ProducerMissingError,
    Roi,
    find_producers,
    list_cameras,
    simulated_producer,
)
from drivers.protocols import Camera

PRODUCER = simulated_producer()
needs_producer = pytest.mark.skipif(PRODUCER is None, reason="the genicam package (GenTL producer viky.cti) is not "
                                    "installed: pip install genicam")


@needs_producer
def test_list_finds_the_producers_cameras_with_serials():
    cams = list_cameras(PRODUCER)
    assert [c["serial"] for c in cams] == ["0", "1", "2"]
    assert {c["model"] for c in cams} == {"Viky"}


@needs_producer
def test_open_by_serial_and_by_gentl_id_gives_fresh_mono8_frames():
    with GenICamCamera("2", producer=PRODUCER) as cam:
        assert isinstance(cam, Camera)
        assert cam.info["id"] == "VikyTL_DEV_blue"
        a, b = cam.capture(), cam.capture()
    for f in (a, b):
        assert f.image.dtype == np.uint8 and f.image.shape == (400, 400)
        assert f.meta["camera"] == "2" and f.meta["pixel_format"] == "Mono8" and f.meta["bit_depth"] == 8
        assert f.meta["triggered_host_s"] <= f.meta["received_host_s"]
    assert b.meta["frame_id"] > a.meta["frame_id"]  # a new frame, not the same buffer twice
    assert a.image.max() > a.image.min()  # the bouncing ball is in the picture
    with GenICamCamera("VikyTL_DEV_red", producer=PRODUCER) as cam:
        assert cam.info["serial"] == "0"


@needs_producer
def test_roi_sets_the_frame_size():
    with GenICamCamera("0", producer=PRODUCER, roi=Roi(0, 0, 320, 240)) as cam:
        f = cam.capture()
    assert f.image.shape == (240, 320)


@needs_producer
def test_producer_environment_variable_is_searched(monkeypatch, tmp_path):
    import os

    monkeypatch.setenv("GENICAM_GENTL64_PATH", os.pathsep.join([str(tmp_path), os.path.dirname(PRODUCER)]))
    assert find_producers() == [PRODUCER]


def test_producer_missing_is_a_clear_fault(monkeypatch, tmp_path):
    monkeypatch.setenv("GENICAM_GENTL64_PATH", str(tmp_path))  # a folder without any .cti
    with pytest.raises(ProducerMissingError, match="no GenTL producer"):
        GenICamCamera("1").connect()
    with pytest.raises(ProducerMissingError, match="does not exist"):
        GenICamCamera("1", producer=str(tmp_path / "vendor.cti")).connect()
    bogus = tmp_path / "bogus.cti"
    bogus.write_bytes(b"not a shared library")
    with pytest.raises(ProducerMissingError, match="could not be loaded"):
        GenICamCamera("1", producer=str(bogus)).connect()


@needs_producer
def test_unknown_camera_names_what_the_producer_sees():
    with pytest.raises(CameraNotFoundError, match=r"camera 42: no such device; the producer sees 0 \(Viky\)"):
        GenICamCamera("42", producer=PRODUCER).connect()
    with pytest.raises(InputError, match="3 devices found"):
        GenICamCamera(None, producer=PRODUCER).connect()


@needs_producer
def test_pixel_format_the_device_does_not_offer_is_refused_at_connect():
    with pytest.raises(PixelFormatError, match="camera 1: does not offer Mono12 \\(offers RGBa8, Mono8\\)"):
        GenICamCamera("1", producer=PRODUCER, pixel_format="Mono12").connect()
    with pytest.raises(InputError, match="not one of"):
        GenICamCamera("1", producer=PRODUCER, pixel_format="BayerRG8")


@needs_producer
@pytest.mark.parametrize("kw, node", [({"exposure_s": 0.002}, "ExposureTimeAbs"), ({"gain_db": 3.0}, "Gain"),
                                      ({"trigger": "software"}, "TriggerSelector"),
                                      ({"trigger": "Line1"}, "TriggerSelector"),
                                      ({"strobe_line": "Line2"}, "LineSelector"),
                                      ({"packet_size": 8192}, "GevSCPSPacketSize")])
def test_feature_the_device_lacks_is_refused_with_its_node_name(kw, node):
    cam = GenICamCamera("1", producer=PRODUCER, **kw)
    with pytest.raises(FeatureError, match=f"camera 1: the device has no {node} node"):
        cam.connect()
    assert cam._ia is None and cam._h is None  # nothing left open


@needs_producer
def test_frame_in_the_wrong_pixel_format_is_not_delivered():
    with GenICamCamera("1", producer=PRODUCER) as cam:
        cam._ia.stop()
        cam.node_map.PixelFormat.value = "RGBa8"  # another program reconfigures the camera
        cam._ia.start()
        with pytest.raises(PixelFormatError, match="camera 1: frame in RGBa8, configured Mono8"):
            cam.capture()


@needs_producer
def test_no_frame_within_the_timeout_is_a_frame_timeout():
    with GenICamCamera("1", producer=PRODUCER, timeout_s=0.3) as cam:
        cam.capture()
        cam.node_map.AcquisitionStop.execute()  # the camera stops sending (trigger never comes)
        start = time.monotonic()
        with pytest.raises(FrameTimeoutError, match="camera 1: no frame within 0.30 s"):
            cam.capture()
        assert 0.25 < time.monotonic() - start < 2.0


@needs_producer
def test_frames_dropped_by_the_producer_are_detected_by_frame_id():
    with GenICamCamera("1", producer=PRODUCER, on_frame_loss="fault", num_buffers=4) as cam:
        cam.node_map.AcquisitionFrameRate.value = 10.0
        cam.capture()
        cam.node_map.AcquisitionFrameRate.value = 200.0
        time.sleep(0.4)  # ~80 frames into 4 buffers: the producer drops the rest
        with pytest.raises(FrameLostError, match=r"camera 1: \d+ frame\(s\) lost since the last capture"):
            cam.capture()
        assert cam.lost_frames > 0  # how many depends on the machine's load
        cam.node_map.AcquisitionFrameRate.value = 10.0  # slow enough that nothing is dropped while we fetch
        cam.capture()
        cam.capture()  # the stream goes on
    with GenICamCamera("1", producer=PRODUCER, num_buffers=4) as cam:  # free run: counted, not a fault
        cam.node_map.AcquisitionFrameRate.value = 10.0
        first = cam.capture()
        cam.node_map.AcquisitionFrameRate.value = 200.0
        time.sleep(0.4)
        f = cam.capture()
        assert f.meta["lost_frames"] > 0 and cam.lost_frames == first.meta["lost_frames"] + f.meta["lost_frames"]


@needs_producer
def test_device_gone_mid_acquisition_faults_then_reconnects_by_serial():
    with GenICamCamera("1", producer=PRODUCER) as cam:
        first = cam.capture()
        cam._ia.destroy()  # the device handle dies under the driver (what a cable pull leaves behind)
        with pytest.raises(CameraLostError, match="camera 1: the device is gone"):
            cam.capture()
        assert isinstance(CameraLostError("x"), NotConnectedError)
        again = cam.capture()  # reopened by its serial number
        assert again.meta["camera"] == "1" and again.image.shape == first.image.shape
        cam.reconnect(attempts=1)
        assert cam.capture().meta["frame_id"] >= 1


@needs_producer
def test_buffers_go_back_to_the_producer_on_every_path():
    """More captures than announced buffers, with faults in between: a leaked buffer would starve the stream."""
    with GenICamCamera("0", producer=PRODUCER, num_buffers=3, timeout_s=1.0) as cam:
        for k in range(12):
            if k % 4 == 3:
                cam._ia.stop()
                cam.node_map.PixelFormat.value = "RGBa8"
                cam._ia.start()
                with pytest.raises(PixelFormatError):
                    cam.capture()
                cam._ia.stop()
                cam.node_map.PixelFormat.value = "Mono8"
                cam._ia.start()
            else:
                assert cam.capture().image.shape == (400, 400)


@needs_producer
def test_cli_camera_list_and_snap_write_the_producers_frame(tmp_path, capsys):
    import json

    import cv2

    from cell.cli import main

    assert main(["camera", "list", "--sim", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [c["serial"] for c in doc["cameras"]] == ["0", "1", "2"]
    out = tmp_path / "x.png"
    assert main(["camera", "snap", "2", "--producer", PRODUCER, "--out", str(out), "--json"]) == 0
    snap = json.loads(capsys.readouterr().out)
    img = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert img.shape == (400, 400) and snap["meta"]["camera"] == "2" and img.max() > img.min()
    assert main(["camera", "snap", "9", "--sim", "--out", str(tmp_path / "y.png")]) == 1
    assert "camera 9: no such device" in capsys.readouterr().err
    assert not (tmp_path / "y.png").exists()
    assert main(["camera", "snap", "1", "--sim", "--out", str(tmp_path / "no" / "y.png")]) == 2


def _sfnc_node_map():
    from pathlib import Path

    from genicam.genapi import NodeMap

    nm = NodeMap()
    nm.load_xml_from_string((Path(__file__).parent / "data" / "sfnc_camera.xml").read_text())
    return nm


def test_configuration_sets_the_sfnc_features_through_the_genapi_engine():
    """The driver's configuration against a real GenApi node map with the SFNC names (no device needed)."""
    nm = _sfnc_node_map()
    cam = GenICamCamera("SN1", pixel_format="Mono12p", exposure_s=0.0025, gain_db=6.0, roi=Roi(32, 16, 1024, 768),
                        trigger="Line1", strobe_line="Line2", packet_size=8192)
    cam._configure(nm)
    got = {n: nm.get_node(n).value for n in ("PixelFormat", "Width", "Height", "OffsetX", "OffsetY", "ExposureAuto",
                                             "ExposureTime", "GainAuto", "Gain", "TriggerSelector", "TriggerMode",
                                             "TriggerSource", "TriggerActivation", "LineSelector", "LineMode",
                                             "LineSource", "GevSCPSPacketSize")}
    assert got == {"PixelFormat": "Mono12p", "Width": 1024, "Height": 768, "OffsetX": 32, "OffsetY": 16,
                   "ExposureAuto": "Off", "ExposureTime": pytest.approx(2500.0), "GainAuto": "Off", "Gain": 6.0,
                   "TriggerSelector": "FrameStart", "TriggerMode": "On", "TriggerSource": "Line1",
                   "TriggerActivation": "RisingEdge", "LineSelector": "Line2", "LineMode": "Output",
                   "LineSource": "ExposureActive", "GevSCPSPacketSize": 8192}
    GenICamCamera("SN1", trigger="software")._configure(nm)
    assert (nm.get_node("TriggerMode").value, nm.get_node("TriggerSource").value) == ("On", "Software")
    GenICamCamera("SN1")._configure(nm)
    assert nm.get_node("TriggerMode").value == "Off"


@pytest.mark.parametrize("kw, message", [({"exposure_s": 2.0}, "ExposureTime = 2000000.0 refused"),
                                         ({"gain_db": 40.0}, "Gain = 40.0 refused"),
                                         ({"trigger": "Line2"}, "TriggerSource = 'Line2' refused"),
                                         ({"roi": Roi(0, 0, 4096, 100)}, "Width = 4096 refused")])
def test_a_value_the_camera_refuses_is_a_feature_error_naming_the_node(kw, message):
    with pytest.raises(FeatureError, match=f"camera SN1: {message}"):
        GenICamCamera("SN1", **kw)._configure(_sfnc_node_map())


def test_a_short_or_imageless_buffer_is_an_incomplete_frame_not_an_image():
    """What the driver does with a buffer's contents once copied out (the simulated producer never delivers a
    truncated one): fewer bytes than one image of its format, or no image component, is refused."""
    cam = GenICamCamera("7")
    facts = {"frame_id": 1, "timestamp_ns": None, "format": "Mono8", "width": 400, "height": 400,
             "raw": np.zeros(400 * 399, np.uint8)}
    with pytest.raises(IncompleteFrameError, match="camera 7: frame holds 159600 of the 160000 bytes"):
        cam._frame(facts, 0.0, 0.0, 0)
    with pytest.raises(IncompleteFrameError, match="camera 7: the frame carries no image"):
        cam._frame(facts | {"frame_id": 2, "raw": None}, 0.0, 0.0, 0)
    ok = cam._frame(facts | {"frame_id": 3, "raw": np.arange(160000, dtype=np.uint32).astype(np.uint8)}, 0.0, 0.0, 0)
    assert ok.image.shape == (400, 400) and ok.image[0, 1] == 1
