"""A camera through OpenCV's ``VideoCapture``; implements ``drivers.protocols.Camera``.

The source is a device index (UVC / V4L2), a GStreamer pipeline (a string with
``!``, e.g. a GigE camera through the vendor's plugin ending in ``appsink``), or a
file: a video or an image sequence (``frame_%04d.png``), which is how the driver
is tested without a device. Exposure is set through ``CAP_PROP_EXPOSURE`` in the
backend's units (``exposure_units_per_s``: V4L2 counts 100 µs steps, so 10 000 per
second). A trigger (for instance a strobe on the light controller, wired to the
camera's trigger input) is fired before each grab.
"""
from __future__ import annotations

import time
from collections.abc import Callable

import cv2
import numpy as np

from calibration.errors import DriverError, NotConnectedError
from drivers.protocols import Frame


class OpenCVCamera:
    """An OpenCV image source.

    Args:
        source: device index, GStreamer pipeline, or a video / image-sequence path.
        exposure_s: exposure to set on connect (None: leave the device's own setting).
        exposure_units_per_s: backend units of ``CAP_PROP_EXPOSURE`` per second.
        trigger: called before each grab (e.g. ``lambda: light.strobe(0.002)``).
        width, height: resolution to ask for (devices only).
        flush_frames: frames read and dropped before each capture (stale frames in the driver's queue).
    """

    def __init__(self, source: int | str, *, exposure_s: float | None = None, exposure_units_per_s: float = 1e4,
                 trigger: Callable[[], None] | None = None, width: int | None = None, height: int | None = None,
                 flush_frames: int = 0):
        self.source = source
        self.exposure_s = exposure_s
        self.exposure_units_per_s = float(exposure_units_per_s)
        self.trigger = trigger
        self.width, self.height = width, height
        self.flush_frames = int(flush_frames)
        self._cap: cv2.VideoCapture | None = None
        self._frames = 0

    @property
    def backend(self) -> int:
        if isinstance(self.source, str) and "!" in self.source:
            return cv2.CAP_GSTREAMER
        return cv2.CAP_ANY

    def connect(self) -> None:
        """Open the source; ``NotConnectedError`` if it cannot be opened."""
        if self._cap is not None:
            return
        cap = cv2.VideoCapture(self.source, self.backend)
        if not cap.isOpened():
            cap.release()
            raise NotConnectedError(f"camera {self.source!r}: cannot open it (no such device, file or pipeline, or "
                                    "in use by another program); check the index/path and permissions")
        if isinstance(self.source, int):
            if self.width:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
            if self.height:
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        if self.exposure_s is not None:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2 "manual" mode
            if not cap.set(cv2.CAP_PROP_EXPOSURE, self.exposure_s * self.exposure_units_per_s) and \
                    isinstance(self.source, int):
                cap.release()
                raise DriverError(f"camera {self.source!r}: the device refused exposure {self.exposure_s} s")
        self._cap = cap
        self._frames = 0

    def close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    def __enter__(self) -> OpenCVCamera:
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def capture(self) -> Frame:
        """Fire the trigger, grab one image, return it as grey ``(height, width)`` uint8/uint16."""
        if self._cap is None:
            raise NotConnectedError(f"camera {self.source!r}: not connected; call connect()")
        for _ in range(self.flush_frames):
            self._cap.grab()
        if self.trigger is not None:
            self.trigger()
        stamp = time.time()
        ok, image = self._cap.read()
        if not ok or image is None:
            raise DriverError(f"camera {self.source!r}: no image (end of stream, device unplugged, or no trigger "
                              "within the backend's timeout)")
        self._frames += 1
        grey = to_grey(image)
        exposure = self._cap.get(cv2.CAP_PROP_EXPOSURE) / self.exposure_units_per_s
        meta = {"source": str(self.source), "frame_index": self._frames - 1,
                "backend": self._cap.getBackendName(), "shape": list(grey.shape)}
        return Frame(image=grey, timestamp_s=stamp,
                     exposure_s=float(self.exposure_s if self.exposure_s is not None else exposure), meta=meta)


def to_grey(image: np.ndarray) -> np.ndarray:
    """An OpenCV image ``(h, w)``, ``(h, w, 3)`` BGR or ``(h, w, 4)`` BGRA -> grey ``(h, w)``, same dtype."""
    if image.ndim == 2:
        return image
    if image.shape[2] == 1:
        return image[:, :, 0]
    code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
    return cv2.cvtColor(image, code)
