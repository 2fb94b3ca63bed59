"""GenICam cameras (GigE Vision, USB3 Vision, CoaXPress ...) through harvesters; implements
``drivers.protocols.Camera``.

Harvesters is the GenTL *consumer* of the GenICam standard: it loads any vendor's GenTL
*producer* (a ``.cti`` file: Basler, Teledyne FLIR, Allied Vision, Matrix Vision, Baumer ...) and
drives the camera through its GenApi node map with the SFNC feature names. The producer is
found from ``producer=`` (a ``.cti`` path or a list of them) or the standard environment
variable ``GENICAM_GENTL64_PATH`` (folders holding ``.cti`` files, ``:``-separated).

What the driver does:

- opens a camera by serial number, user id (``DeviceUserID``) or GenTL device id;
- sets the pixel format (Mono8/10/12/14/16, Mono10p/12p, Mono10Packed/12Packed; unpacked in
  :mod:`drivers.pixels`), exposure (``ExposureTime``, µs), gain (``Gain``, dB), ROI
  (``OffsetX/Y``, ``Width/Height``), the frame-start trigger (``off``: free run, ``software``:
  ``TriggerSoftware``, or a hardware line such as ``Line1``) and a strobe output line
  (``LineSelector`` / ``LineMode=Output`` / ``LineSource=ExposureActive``) that fires the light
  with the exposure;
- stamps each frame with the host time of its trigger (or request) and of its arrival, and the
  device's own timestamp and frame id when the producer gives them;
- takes each frame's bytes as the camera sent them from the GenTL buffer and unpacks them once
  (:mod:`drivers.pixels`); where a consumer does not expose them, harvesters' ``Component2DImage.data``,
  which harvesters has already expanded to one uint16 per pixel for the 10..16-bit and packed formats,
  is taken as it is, never unpacked a second time (:func:`drivers.pixels.from_component`);
- detects incomplete frames (harvesters' INCOMPLETE_BUFFER event, or fewer pixels than the frame's
  size), lost frames (a gap in the frame ids), frames in the wrong pixel format, frames whose size or
  offset is not the one configured at connect (``Width``/``Height``/``OffsetX``/``OffsetY`` read back
  after configuring; ``expected_size``: the size the caller's lens model is for, checked at connect),
  and timeouts, each as its own ``DriverError`` naming the camera; nothing of such a frame reaches
  the caller;
- turns a device that vanished (cable pull, power loss) into ``CameraLostError`` and reopens
  the same camera by its key on :meth:`reconnect` (and on the next :meth:`capture`);
- acquires every buffer in a ``with`` block, so it is queued back to the producer on every path.

A feature the device lacks (the simulated producer in CI has no exposure, gain or trigger) is
refused at :meth:`connect` with the name of the missing node, never skipped silently.
"""
from __future__ import annotations

import glob
import os
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calibration.errors import DriverError, InputError, NotConnectedError
from drivers.pixels import (
    MONO_FORMATS,
    PixelFormatUnsupported,
    ShortBufferError,
    bit_depth,
    expected_bytes,
    from_component,
)
from drivers.protocols import Frame

ENV_PATH = "GENICAM_GENTL64_PATH"


class ProducerMissingError(NotConnectedError):
    """No GenTL producer (.cti) could be loaded."""


class CameraNotFoundError(NotConnectedError):
    """The producer loaded, but no device matches the key."""


class CameraLostError(NotConnectedError):
    """The device vanished while open (cable pull, power loss, another program took it)."""


class FrameTimeoutError(DriverError):
    """No frame arrived within the timeout."""


class IncompleteFrameError(DriverError):
    """The producer delivered a frame with missing data (lost packets)."""


class FrameLostError(DriverError):
    """Frames were lost between two deliveries (a gap in the device's frame ids)."""


class PixelFormatError(DriverError):
    """The frame is not in the configured pixel format, or the device does not offer it."""


class FeatureError(DriverError):
    """The device lacks a feature the configuration asks for, or refused a value."""


class FrameGeometryError(DriverError):
    """The frame's size or offset is not the one configured (binning, an ROI changed behind the driver)."""


def simulated_producer() -> str | None:
    """The GenTL producer shipped by the ``genicam`` package (EMVA's simulated "Viky" cameras), if installed."""
    try:
        import genicam
    except ImportError:
        return None
    path = os.path.join(os.path.dirname(genicam.__file__), "viky.cti")
    return path if os.path.isfile(path) else None


def find_producers(producer: str | Sequence[str] | None = None) -> list[str]:
    """The ``.cti`` files to load: those given, else every one in the folders of ``GENICAM_GENTL64_PATH``.

    Raises ``ProducerMissingError`` (naming what was looked at) when there is none or a given path is missing.
    """
    if producer:
        paths = [producer] if isinstance(producer, str) else list(producer)
        missing = [p for p in paths if not os.path.isfile(p)]
        if missing:
            raise ProducerMissingError(f"GenTL producer {missing[0]} does not exist; install the camera vendor's "
                                       f"GenTL producer (.cti) and give its path, or set {ENV_PATH}")
        return [os.path.abspath(p) for p in paths]
    folders = [d for d in os.environ.get(ENV_PATH, "").split(os.pathsep) if d]
    found = sorted({f for d in folders for f in glob.glob(os.path.join(d, "*.cti"))})
    if not found:
        where = f"{ENV_PATH}={os.environ.get(ENV_PATH, '')!r}" if folders else f"{ENV_PATH} is not set"
        raise ProducerMissingError(f"no GenTL producer (.cti) found ({where}); install the camera vendor's GenTL "
                                   f"producer and point {ENV_PATH} at its folder, or pass its path")
    return found


def _genicam_errors() -> tuple[type[BaseException], ...]:
    from genicam.genapi import GenericException as GenApiError
    from genicam.gentl import GenericException as GenTLError

    return GenApiError, GenTLError


def _harvester(producers: list[str]):
    from harvesters.core import Harvester

    h = Harvester()
    try:
        for p in producers:
            h.add_file(p, check_existence=True, check_validity=True)
        h.update()
    except (OSError, *_genicam_errors()) as exc:
        h.reset()
        raise ProducerMissingError(f"GenTL producer {', '.join(producers)} could not be loaded ({exc}); is it a "
                                   "GenTL producer built for this platform?") from None
    return h


def _info_value(info, name: str) -> str | None:
    try:
        v = getattr(info, name)
    except Exception:  # producers raise NotAvailable / NotImplemented for what they do not keep
        return None
    return None if v is None else str(v)


def describe(info) -> dict:
    """What a producer says about a device: id, serial, user id, vendor, model, transport."""
    return {"id": _info_value(info, "id_"), "serial": _info_value(info, "serial_number"),
            "user_id": _info_value(info, "user_defined_name"), "vendor": _info_value(info, "vendor"),
            "model": _info_value(info, "model"), "tl_type": _info_value(info, "tl_type")}


def list_cameras(producer: str | Sequence[str] | None = None) -> list[dict]:
    """Every device the producer(s) see, as :func:`describe` dicts (``ProducerMissingError`` if none loads)."""
    h = _harvester(find_producers(producer))
    try:
        return [describe(d) for d in h.device_info_list]
    finally:
        h.reset()


def _match(infos: list, key: str) -> int:
    hits = [i for i, d in enumerate(infos) if key in (describe(d)["serial"], describe(d)["user_id"], describe(d)["id"])]
    if len(hits) > 1:
        raise InputError(f"camera {key!r}: {len(hits)} devices match it; give the serial number")
    return hits[0] if hits else -1


@dataclass(frozen=True)
class Roi:
    """Region of interest in sensor pixels: top-left corner and size."""

    x: int
    y: int
    width: int
    height: int


TRIGGERS = ("off", "software")  # or a hardware line name, e.g. "Line1"


class GenICamCamera:
    """A GenICam camera.

    Args:
        device: serial number, user id or GenTL id; ``None``: the only device the producer sees.
        producer: ``.cti`` path(s); ``None``: ``GENICAM_GENTL64_PATH``.
        pixel_format: one of :data:`drivers.pixels.MONO_FORMATS`.
        exposure_s, gain_db: set on connect when given (``ExposureTime`` in µs, ``Gain`` in dB).
        roi: :class:`Roi` to set on connect (None: the device's current one).
        trigger: ``"off"`` (free run: :meth:`capture` takes the next frame after the call),
            ``"software"`` (``TriggerSoftware`` per capture) or a hardware line (``"Line1"``:
            :meth:`capture` waits for the frame that the line's edge starts).
        strobe_line: an output line (``"Line2"``) driven high during the exposure, wired to the
            light controller's trigger input.
        timeout_s: how long :meth:`capture` waits for the frame (beyond the exposure).
        num_buffers: buffers announced to the producer.
        on_frame_loss: ``"fault"`` (raise ``FrameLostError`` when frames are missing from the frame-id
            sequence since the last capture: the producer dropped some) or ``"count"`` (count them in
            ``lost_frames`` and in the frame's meta);
            default ``fault`` with a trigger, ``count`` in free run (where any fresh frame will do).
        packet_size: GigE Vision stream packet size in bytes (``GevSCPSPacketSize``, SFNC 2:
            ``DeviceStreamChannelPacketSize``); with jumbo frames (MTU 9000) 8192 or the camera's maximum.
        expected_size: ``(width, height)`` the frames must have (the job's lens model is for that image);
            the camera's ``Width``/``Height`` after configuring are checked against it at connect
            (``FrameGeometryError``). Every frame is checked against the size (and offset, where the
            producer or the node map tells it) read back at connect, with or without it.
    """

    def __init__(self, device: str | None = None, *, producer: str | Sequence[str] | None = None,
                 pixel_format: str = "Mono8", exposure_s: float | None = None, gain_db: float | None = None,
                 roi: Roi | None = None, trigger: str = "off", strobe_line: str | None = None,
                 timeout_s: float = 2.0, num_buffers: int = 4, on_frame_loss: str | None = None,
                 packet_size: int | None = None, expected_size: tuple[int, int] | None = None):
        try:
            bit_depth(pixel_format)
        except PixelFormatUnsupported as exc:
            raise InputError(f"camera {device}: {exc}") from None
        if trigger not in TRIGGERS and not trigger.startswith("Line"):
            raise InputError(f"camera {device}: trigger {trigger!r} is not off, software or a line (Line1, ...)")
        self.device, self.producer = device, producer
        self.pixel_format, self.exposure_s, self.gain_db, self.roi = pixel_format, exposure_s, gain_db, roi
        self.trigger, self.strobe_line = trigger, strobe_line
        self.timeout_s, self.num_buffers = float(timeout_s), int(num_buffers)
        self.packet_size = packet_size
        self.expected_size = None if expected_size is None else (int(expected_size[0]), int(expected_size[1]))
        self.geometry: dict = {}  # Width/Height/OffsetX/OffsetY read back at connect (None where the device has none)
        self.on_frame_loss = on_frame_loss or ("count" if trigger == "off" else "fault")
        if self.on_frame_loss not in ("fault", "count"):
            raise InputError(f"camera {device}: on_frame_loss {on_frame_loss!r} is not fault or count")
        self.info: dict = {}
        self.incomplete_frames = 0  # incomplete buffers the producer delivered since connect
        self.lost_frames = 0  # frames missing from the frame-id sequence since connect
        self.stale_frames = 0  # frames found waiting before a capture's request (discarded)
        self._h = None
        self._ia = None
        self._last_frame_id: int | None = None
        self._lock = threading.RLock()

    @property
    def name(self) -> str:
        return f"camera {self.device or self.info.get('serial') or '?'}"

    # --- open / close ---------------------------------------------------------------------------

    def connect(self) -> None:
        """Load the producer, open the device, configure it, start streaming."""
        with self._lock:
            if self._ia is not None:
                return
            producers = find_producers(self.producer)
            h = _harvester(producers)
            try:
                infos = list(h.device_info_list)
                if not infos:
                    raise CameraNotFoundError(f"{self.name}: the producer ({', '.join(producers)}) sees no device; "
                                              "check power, cable and network (see docs/bring-up.md)")
                if self.device is None:
                    if len(infos) > 1:
                        raise InputError(f"camera: {len(infos)} devices found ("
                                         + ", ".join(describe(d)["serial"] or "?" for d in infos)
                                         + "); say which by serial number")
                    index = 0
                else:
                    index = _match(infos, self.device)
                    if index < 0:
                        raise CameraNotFoundError(f"{self.name}: no such device; the producer sees "
                                                  + ", ".join(f"{d['serial']} ({d['model']})"
                                                              for d in map(describe, infos)))
                self.info = describe(infos[index])
                try:
                    ia = h.create(index)
                except _genicam_errors() as exc:
                    raise NotConnectedError(f"{self.name}: cannot open it ({exc}); is another program using it?") \
                        from None
                try:
                    ia.num_buffers = max(self.num_buffers, ia.min_num_buffers)
                    self._configure(ia.remote_device.node_map)
                    self.geometry = self._read_geometry(ia.remote_device.node_map)
                    self._watch_incomplete(ia)
                    ia.start()
                except BaseException:
                    ia.destroy()
                    raise
            except BaseException:
                h.reset()
                raise
            self._h, self._ia = h, ia
            self._last_frame_id = None

    def close(self) -> None:
        """Stop streaming and release the device and the producer; safe to call twice."""
        with self._lock:
            ia, h, self._ia, self._h = self._ia, self._h, None, None
            for step in ((ia.stop, ia.destroy) if ia is not None else ()) + ((h.reset,) if h is not None else ()):
                try:
                    step()
                except Exception:  # a device that is gone cannot be stopped; release what is left
                    pass

    def reconnect(self, attempts: int = 5, wait_s: float = 1.0) -> None:
        """Close and reopen the same camera (after a cable pull); ``CameraLostError`` if it does not come back."""
        last: Exception | None = None
        for k in range(max(1, attempts)):
            self.close()
            try:
                self.connect()
                return
            except NotConnectedError as exc:
                last = exc
                if k + 1 < attempts:
                    time.sleep(wait_s)
        raise CameraLostError(f"{self.name}: did not come back after {attempts} attempt(s): {last}")

    def __enter__(self) -> GenICamCamera:
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- configuration -----------------------------------------------------------------------------

    def _node(self, nm, name: str, why: str):
        if not nm.has_node(name):
            raise FeatureError(f"{self.name}: the device has no {name} node, needed for {why}")
        return nm.get_node(name)

    def _set(self, nm, name: str, value, why: str) -> None:
        node = self._node(nm, name, why)
        try:
            node.value = value
        except _genicam_errors() as exc:
            raise FeatureError(f"{self.name}: {name} = {value!r} refused ({why}): {exc}") from None

    def _configure(self, nm) -> None:
        pf = self._node(nm, "PixelFormat", "the pixel format")
        offered = list(getattr(pf, "symbolics", ()))
        if self.pixel_format not in offered:
            raise PixelFormatError(f"{self.name}: does not offer {self.pixel_format} (offers {', '.join(offered)})")
        self._set(nm, "PixelFormat", self.pixel_format, "the pixel format")
        if self.packet_size is not None:
            name = "DeviceStreamChannelPacketSize" if nm.has_node("DeviceStreamChannelPacketSize") \
                else "GevSCPSPacketSize"
            self._set(nm, name, int(self.packet_size), "the GigE packet size")
        if self.roi is not None:
            r = self.roi
            for n in ("OffsetX", "OffsetY"):  # offsets first to 0, so any size fits, then size, then offsets
                if nm.has_node(n):
                    self._set(nm, n, 0, "the ROI")
            self._set(nm, "Width", int(r.width), "the ROI")
            self._set(nm, "Height", int(r.height), "the ROI")
            if r.x or r.y:
                self._set(nm, "OffsetX", int(r.x), "the ROI")
                self._set(nm, "OffsetY", int(r.y), "the ROI")
        if self.exposure_s is not None:
            if nm.has_node("ExposureAuto"):
                self._set(nm, "ExposureAuto", "Off", "a fixed exposure")
            name = "ExposureTime" if nm.has_node("ExposureTime") else "ExposureTimeAbs"
            self._set(nm, name, float(self.exposure_s) * 1e6, "the exposure")
        if self.gain_db is not None:
            if nm.has_node("GainAuto"):
                self._set(nm, "GainAuto", "Off", "a fixed gain")
            self._set(nm, "Gain", float(self.gain_db), "the gain")
        if self.trigger != "off" or nm.has_node("TriggerMode"):
            if nm.has_node("TriggerSelector") or self.trigger != "off":
                self._set(nm, "TriggerSelector", "FrameStart", "the frame trigger")
            if self.trigger == "off":
                self._set(nm, "TriggerMode", "Off", "free run")
            else:
                self._set(nm, "TriggerMode", "On", "the frame trigger")
                self._set(nm, "TriggerSource", "Software" if self.trigger == "software" else self.trigger,
                          "the frame trigger")
                if self.trigger != "software" and nm.has_node("TriggerActivation"):
                    self._set(nm, "TriggerActivation", "RisingEdge", "the hardware trigger")
        if self.strobe_line is not None:
            self._set(nm, "LineSelector", self.strobe_line, "the strobe output")
            self._set(nm, "LineMode", "Output", "the strobe output")
            self._set(nm, "LineSource", "ExposureActive", "the strobe output")

    def _read_geometry(self, nm) -> dict:
        """Width/Height/OffsetX/OffsetY as the device has them now (offsets None where it has no such node); checks
        ``expected_size``."""
        geo = {}
        for n in ("Width", "Height", "OffsetX", "OffsetY"):
            try:
                geo[n] = int(nm.get_node(n).value) if nm.has_node(n) else None
            except _genicam_errors() as exc:
                raise FeatureError(f"{self.name}: cannot read {n} ({exc})") from None
        if geo["Width"] is None or geo["Height"] is None:
            raise FeatureError(f"{self.name}: the device has no Width/Height node, needed to check the frame size")
        if self.expected_size is not None and (geo["Width"], geo["Height"]) != self.expected_size:
            w, h = self.expected_size
            raise FrameGeometryError(f"{self.name}: delivers {geo['Width']}x{geo['Height']} frames, expected {w}x{h} "
                                     "(the lens model's image size); set the camera's ROI / binning, or the size")
        return geo

    def _watch_incomplete(self, ia) -> None:
        from harvesters.core import Callback

        camera = self

        class _Incomplete(Callback):
            def emit(self, context=None) -> None:
                camera.incomplete_frames += 1

        ia.add_callback(ia.Events.INCOMPLETE_BUFFER, _Incomplete())

    @property
    def node_map(self):
        """The device's GenApi node map (for features the driver does not set itself)."""
        if self._ia is None:
            raise NotConnectedError(f"{self.name}: not connected; call connect()")
        return self._ia.remote_device.node_map

    # --- acquisition -----------------------------------------------------------------------------------

    def _flush(self, ia) -> int:
        """Hand back the frames already waiting (taken before this request); gaps among them count as lost.

        At most as many as there are buffers: no more can have been filled before the request, and a
        free-running camera fills new ones as fast as they are handed back (draining "until empty" would
        chase the stream forever).
        """
        n = 0
        for _ in range(ia.num_buffers):
            buf = ia.try_fetch(timeout=1e-3)
            if buf is None:
                break
            with buf:
                self._note_frame_id(_buffer_facts(buf, with_data=False)["frame_id"])
            n += 1
        self.stale_frames += n
        return n

    def _note_frame_id(self, fid: int | None) -> int | None:
        """Record the frame id of a delivered buffer; the number of frames missing before it."""
        if fid is None:
            return None
        last, self._last_frame_id = self._last_frame_id, fid
        if last is not None and fid > last + 1:
            self.lost_frames += fid - last - 1
            return fid - last - 1
        return 0

    def capture(self) -> Frame:
        """One frame: free run -> the next frame; software trigger -> fire and fetch; line -> wait for it.

        Raises ``FrameTimeoutError``, ``IncompleteFrameError``, ``FrameLostError``,
        ``PixelFormatError``, ``CameraLostError`` (each naming the camera); the buffer is queued back on
        every path.
        """
        with self._lock:
            if self._ia is None:
                if self._h is None and self.info:  # lost earlier: try to reopen the same camera once
                    self.reconnect(attempts=1)
                else:
                    raise NotConnectedError(f"{self.name}: not connected; call connect()")
            ia = self._ia
            errors = _genicam_errors()
            try:
                if not self._alive(ia):
                    raise CameraLostError(f"{self.name}: the device is gone (cable pulled, power lost?); the next "
                                          "capture tries to reopen it")
                lost_before = self.lost_frames
                first = self._last_frame_id is None
                self._flush(ia)
                if first:  # what streamed before the first request after connect is not ours to judge
                    self._last_frame_id, self.lost_frames = None, lost_before
                incomplete_before = self.incomplete_frames
                triggered_s = time.time()
                if self.trigger == "software":
                    ia.remote_device.node_map.get_node("TriggerSoftware").execute()
                wait = self.timeout_s + (self.exposure_s or 0.0)
                deadline = time.monotonic() + wait
                buf = None
                while buf is None:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    buf = ia.try_fetch(timeout=min(left, 0.05))
                    if buf is None and self.incomplete_frames > incomplete_before:
                        raise IncompleteFrameError(f"{self.name}: the frame arrived incomplete (lost packets: "
                                                   "check the packet size, MTU and the link; docs/bring-up.md)")
                if buf is None and not self._alive(ia):
                    raise CameraLostError(f"{self.name}: the device went away during acquisition; the next capture "
                                          "tries to reopen it")
                if buf is None:
                    raise FrameTimeoutError(f"{self.name}: no frame within {wait:.2f} s (trigger "
                                            f"{self.trigger}); check the trigger wiring and the exposure")
                with buf:  # everything is copied out of the buffer before it goes back to the producer
                    received_s = time.time()
                    facts = _buffer_facts(buf, with_data=True)
                del buf  # a released buffer must not outlive its block (its repr reads freed producer memory)
                return self._frame(facts, triggered_s, received_s, self.lost_frames - lost_before)
            except CameraLostError:
                self._lost()
                raise
            except errors as exc:
                self._lost()
                raise CameraLostError(f"{self.name}: the device failed during acquisition ({exc}); is the cable "
                                      "pulled or the power gone? the next capture tries to reopen it") from None

    @staticmethod
    def _alive(ia) -> bool:
        """Whether the device still answers: the acquirer is valid and a register read goes through."""
        try:
            return bool(ia.is_valid()) and ia.remote_device.node_map.get_node("PixelFormat").value is not None
        except Exception:  # any failure to talk to it means it is gone
            return False

    def _lost(self) -> None:
        ia, h, self._ia, self._h = self._ia, self._h, None, None
        for step in ((ia.destroy,) if ia is not None else ()) + ((h.reset,) if h is not None else ()):
            try:
                step()
            except Exception:
                pass

    def _frame(self, facts: dict, triggered_s: float, received_s: float, lost_before: int) -> Frame:
        """Check what was copied out of a buffer and make the Frame (the buffer itself is already back)."""
        lost = lost_before + (self._note_frame_id(facts["frame_id"]) or 0)
        if lost and self.on_frame_loss == "fault":
            raise FrameLostError(f"{self.name}: {lost} frame(s) lost since the last capture (gap in the frame ids "
                                 f"before frame {self._last_frame_id}); the producer dropped frames: buffers, bandwidth?")
        if facts["raw"] is None:
            raise IncompleteFrameError(f"{self.name}: the frame carries no image")
        fmt, width, height, raw = facts["format"], facts["width"], facts["height"], facts["raw"]
        if fmt != self.pixel_format:
            raise PixelFormatError(f"{self.name}: frame in {fmt}, configured {self.pixel_format}; another program "
                                   "changed the camera's settings?")
        self._check_geometry(facts)
        if facts.get("x_padding"):
            raw = self._strip_padding(raw, fmt, width, height, int(facts["x_padding"]))
        try:
            image = from_component(raw, fmt, width, height)
        except ShortBufferError as exc:
            raise IncompleteFrameError(f"{self.name}: frame holds {exc.have} of the {exc.need} {exc.unit} of a "
                                       f"{width}x{height} {fmt} image") from None
        except PixelFormatUnsupported as exc:
            raise PixelFormatError(f"{self.name}: {exc}") from None
        meta = {"camera": self.info.get("serial"), "model": self.info.get("model"), "frame_id": self._last_frame_id,
                "pixel_format": fmt, "bit_depth": bit_depth(fmt), "device_timestamp_ns": facts["timestamp_ns"],
                "lost_frames": lost, "trigger": self.trigger, "triggered_host_s": triggered_s,
                "received_host_s": received_s}
        return Frame(image=image, timestamp_s=triggered_s if self.trigger != "off" else received_s,
                     exposure_s=float(self.exposure_s or 0.0), meta=meta)


    def _strip_padding(self, raw: np.ndarray, fmt: str, width: int, height: int, pad: int) -> np.ndarray:
        """The frame's bytes without the ``pad`` bytes that end each line (GenTL ``padding_x``)."""
        line = expected_bytes(fmt, width, 1)
        if raw.dtype != np.uint8 or (width * bit_depth(fmt)) % 8:
            raise PixelFormatError(f"{self.name}: frame lines carry {pad} padding byte(s) each, which this driver "
                                   f"cannot remove from {fmt} {width}x{height} data; switch the camera's line padding off")
        need = (line + pad) * height
        if raw.size < need:
            raise IncompleteFrameError(f"{self.name}: frame holds {raw.size} of the {need} bytes of a {width}x{height} "
                                       f"{fmt} image with {pad} padding byte(s) a line")
        return np.ascontiguousarray(raw[:need].reshape(height, line + pad)[:, :line]).ravel()

    def _check_geometry(self, facts: dict) -> None:
        """The frame's size (and offset, where known) must be the one read back at connect."""
        geo = self.geometry
        if not geo:  # not connected through connect() (a unit test of _frame): only the expected size, if given
            geo = {"Width": self.expected_size[0], "Height": self.expected_size[1]} if self.expected_size else {}
        got, want = (facts["width"], facts["height"]), (geo.get("Width"), geo.get("Height"))
        if None not in want and got != want:
            raise FrameGeometryError(f"{self.name}: frame of {got[0]}x{got[1]} pixels, configured {want[0]}x{want[1]}; "
                                     "binning or the ROI changed behind the driver?")
        for key, n in (("x_offset", "OffsetX"), ("y_offset", "OffsetY")):
            if facts.get(key) is not None and geo.get(n) is not None and facts[key] != geo[n]:
                raise FrameGeometryError(f"{self.name}: frame at {n} {facts[key]}, configured {geo[n]}; the ROI "
                                         "moved behind the driver?")


def _buffer_facts(buf, *, with_data: bool) -> dict:
    """Frame id, device timestamp, and (``with_data``) the first image component's format, size and a copy of its
    bytes, read while the buffer is held. Optional GenTL facts a producer does not keep are None."""
    out: dict = {"frame_id": None, "timestamp_ns": None, "format": None, "width": 0, "height": 0, "raw": None,
                 "x_offset": None, "y_offset": None, "x_padding": 0}
    try:
        out["frame_id"] = int(buf.frame_id)
    except Exception:  # frame ids are optional in GenTL
        pass
    if not with_data:
        return out
    try:
        out["timestamp_ns"] = int(buf.timestamp_ns)
    except Exception:  # timestamps are optional in GenTL (the simulated producer has none)
        pass
    comps = buf.payload.components if buf.payload is not None else []
    if comps:
        c = comps[0]
        out.update(format=str(c.data_format), width=int(c.width), height=int(c.height), raw=_wire_bytes(c))
        if out["raw"] is None and c.data is not None:
            # harvesters' data is already the pixel format's expand(): uint16 pixels for 10..16 bit and packed
            # formats, uint8 for Mono8; copied as it is (its dtype tells drivers.pixels.from_component what it holds)
            out["raw"] = np.array(c.data, copy=True).ravel()
        for key in ("x_offset", "y_offset", "x_padding"):  # from the buffer's info; optional in GenTL
            try:
                v = getattr(c, key)
                out[key] = None if v is None else int(v)
            except Exception:  # a producer (and node map) without it: not checked
                pass
        out["x_padding"] = out["x_padding"] or 0
    return out


def _wire_bytes(c) -> np.ndarray | None:
    """A copy of the image component's bytes as the camera sent them (the GenTL buffer's, from the component's data
    offset; as many as the producer filled), or None where the consumer does not expose them.

    Taken in preference to harvesters' ``Component2DImage.data``, which is already expanded (so never to be unpacked
    again) and which harvesters 1.4.3 cuts short for Mono10Packed (it counts 1.25 bytes a pixel, the format has 1.5)
    and leaves line padding in; the bytes are unpacked once, by :mod:`drivers.pixels`."""
    gentl = getattr(c, "_buffer", None)
    try:
        rb = gentl.raw_buffer
        part = getattr(c, "_part", None)
        if part is not None:
            offset, count = int(part.data_offset), int(part.data_size)
        else:
            offset = 0
            try:
                count = int(gentl.size_filled)
            except Exception:  # a producer that does not say how much it filled: the whole buffer
                count = len(rb)
        return np.frombuffer(rb, dtype=np.uint8, count=count, offset=offset).copy()
    except Exception:  # not a GenTL buffer we can read: harvesters' own data is used
        return None


__all__ = ["GenICamCamera", "Roi", "list_cameras", "find_producers", "simulated_producer", "describe",
           "ProducerMissingError", "CameraNotFoundError", "CameraLostError", "FrameTimeoutError",
           "IncompleteFrameError", "FrameLostError", "PixelFormatError", "FeatureError", "FrameGeometryError",
           "MONO_FORMATS"]
