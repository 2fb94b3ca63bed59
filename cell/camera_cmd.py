"""``cell camera list`` and ``cell camera snap DEVICE --out x.png``.

DEVICE is a GenICam camera's serial number, user id or GenTL id (through the GenTL producer
given by ``--producer`` or ``GENICAM_GENTL64_PATH``), or ``opencv:SOURCE`` for a USB camera
through OpenCV (``opencv:0``). ``--sim`` uses the simulated GenTL producer of the ``genicam``
package (three "Viky" cameras), to try the commands without hardware.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

from calibration.errors import InputError


def add_camera_parser(sub, common) -> None:
    c = sub.add_parser("camera", parents=[common], help="list GenICam cameras, or take one picture")
    c.add_argument("action", choices=["list", "snap"])
    c.add_argument("device", nargs="?", help="serial number / user id / GenTL id, or opencv:SOURCE")
    c.add_argument("--out", type=Path, help="PNG to write (snap)")
    c.add_argument("--producer", action="append", help="GenTL producer .cti (default: GENICAM_GENTL64_PATH)")
    c.add_argument("--sim", action="store_true", help="use the simulated GenTL producer of the genicam package")
    c.add_argument("--pixel-format", default="Mono8")
    c.add_argument("--exposure-s", type=float)
    c.add_argument("--gain-db", type=float)
    c.add_argument("--trigger", default="off", help="off, software or a line (Line1)")
    c.add_argument("--timeout-s", type=float, default=3.0)
    c.add_argument("--packet-size", type=int, help="GigE Vision stream packet size (bytes), e.g. 8192 with MTU 9000")
    c.set_defaults(func=cmd_camera)


def _producer(args):
    if args.sim:
        from drivers.genicam import simulated_producer

        p = simulated_producer()
        if p is None:
            raise InputError("--sim: the genicam package (simulated GenTL producer) is not installed")
        return [p]
    return args.producer


def cmd_camera(args, out) -> int:
    if args.action == "list":
        from drivers.genicam import list_cameras

        cams = list_cameras(_producer(args))

        def human(doc):
            if not doc["cameras"]:
                out.say("no camera found")
            for c in doc["cameras"]:
                out.say(f"{c['serial'] or '-':<16} {c['user_id'] or '-':<16} {c['vendor'] or '?'} {c['model'] or '?'}"
                        f"  ({c['id']}, {c['tl_type']})")

        out.result({"cameras": cams}, human)
        return 0
    if not args.device:
        raise InputError("camera snap: give the DEVICE (serial number, user id, or opencv:SOURCE)")
    if args.out is None:
        raise InputError("camera snap: give --out PNG")
    if args.out.suffix.lower() != ".png":
        raise InputError(f"camera snap: --out {args.out} must end in .png")
    if not args.out.parent.exists():
        raise InputError(f"camera snap: folder {args.out.parent} does not exist")
    if args.device.startswith("opencv:"):
        from drivers.opencv_camera import OpenCVCamera

        src = args.device.split(":", 1)[1]
        camera = OpenCVCamera(int(src) if src.isdigit() else src, exposure_s=args.exposure_s)
    else:
        from drivers.genicam import GenICamCamera

        camera = GenICamCamera(args.device, producer=_producer(args), pixel_format=args.pixel_format,
                               exposure_s=args.exposure_s, gain_db=args.gain_db, trigger=args.trigger,
                               timeout_s=args.timeout_s, packet_size=args.packet_size)
    camera.connect()
    try:
        frame = camera.capture()
    finally:
        camera.close()
    import cv2

    ok, png = cv2.imencode(".png", frame.image)
    if not ok:
        raise InputError(f"camera snap: cannot encode a {frame.image.dtype} {frame.image.shape} image as PNG")
    fd, tmp = tempfile.mkstemp(dir=args.out.parent, prefix=".snap-", suffix=".png")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(png.tobytes())
        os.replace(tmp, args.out)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    h, w = frame.image.shape[:2]
    doc = {"device": args.device, "out": str(args.out), "width": w, "height": h, "dtype": str(frame.image.dtype),
           "timestamp_s": frame.timestamp_s, "meta": frame.meta}
    out.result(doc, lambda d: out.say(f"{d['out']}: {w}x{h} {d['dtype']} from {args.device}"))
    return 0
