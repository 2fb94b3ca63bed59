"""The OpenCV camera driver, with files standing in for a device."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.errors import DriverError, NotConnectedError
from drivers.opencv_camera import OpenCVCamera, to_grey
from drivers.protocols import Camera


def _frames(n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """n distinct grey test images (64 x 80) with a bright square at a known place."""
    out = []
    for k in range(n):
        img = rng.integers(0, 40, size=(64, 80), dtype=np.uint8)
        img[10 + 5 * k:20 + 5 * k, 30:40] = 250
        out.append(img)
    return out


def test_image_sequence_frames_come_back_exactly_in_order(tmp_path):
    truth = _frames(3, np.random.default_rng(7))
    for k, img in enumerate(truth):
        assert cv2.imwrite(str(tmp_path / f"frame_{k:03d}.png"), img)
    with OpenCVCamera(str(tmp_path / "frame_%03d.png"), exposure_s=0.004) as cam:
        assert isinstance(cam, Camera)
        frames = [cam.capture() for _ in range(3)]
        with pytest.raises(DriverError, match="no image"):
            cam.capture()
    for k, (frame, img) in enumerate(zip(frames, truth)):
        assert frame.image.shape == (64, 80) and frame.image.dtype == np.uint8
        np.testing.assert_array_equal(frame.image, img)
        assert frame.meta["frame_index"] == k
        assert frame.exposure_s == 0.004
    assert frames[0].timestamp_s <= frames[1].timestamp_s <= frames[2].timestamp_s


def test_video_file_is_read_as_grey_with_the_trigger_fired_per_frame(tmp_path):
    truth = _frames(4, np.random.default_rng(3))
    path = str(tmp_path / "clip.avi")
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (80, 64))
    assert writer.isOpened()
    for img in truth:
        writer.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    writer.release()
    fired = []
    with OpenCVCamera(path, trigger=lambda: fired.append(1)) as cam:
        frames = [cam.capture() for _ in range(4)]
    assert len(fired) == 4
    for frame, img in zip(frames, truth):
        assert frame.image.shape == (64, 80)
        # MJPG is lossy: the bright square is where it was put, the noise roughly so
        assert np.mean(np.abs(frame.image.astype(float) - img)) < 6.0
        rows = np.nonzero(frame.image[:, 35] > 128)[0]
        assert rows.min() == np.nonzero(img[:, 35] > 128)[0].min()


def test_missing_device_and_missing_file_raise_not_connected(tmp_path):
    with pytest.raises(NotConnectedError, match="cannot open"):
        OpenCVCamera(str(tmp_path / "nothing_%03d.png")).connect()
    with pytest.raises(NotConnectedError, match="cannot open"):
        OpenCVCamera(97).connect()
    with pytest.raises(NotConnectedError, match="not connected"):
        OpenCVCamera(0).capture()


def test_to_grey_keeps_depth_and_weights_channels():
    bgr = np.zeros((2, 3, 3), np.uint16)
    bgr[..., 1] = 1000  # pure green
    grey = to_grey(bgr)
    assert grey.dtype == np.uint16 and grey.shape == (2, 3)
    assert np.all(np.abs(grey.astype(int) - 587) <= 1)  # ITU-R BT.601 weight of green
