"""ACQUIRE: move to each station, strobe, capture; a station is done when its image is on disk and journalled."""
from __future__ import annotations

import time

import cv2
import numpy as np

from calibration.errors import DriverError
from cell.record.integrity import acquired
from cell.record.jobfolder import atomic_write_bytes, atomic_write_json, sha256_file


def _stations_in_order(plan_doc: dict) -> list[dict]:
    st = plan_doc["stations"]
    return sorted(st, key=lambda s: s["order"])


def run(ctx) -> None:
    """Move to each station, strobe, capture; a station is done when its image is on disk and journalled."""
    from cell.devices import open_devices

    plan_doc = ctx.folder.read_json("plan.json")
    stations = _stations_in_order(plan_doc)
    done = set(acquired(list(ctx.folder.records())))  # stations whose image stands (verified on resume)
    if ctx.devices is None:
        ctx.devices = open_devices(ctx.job, ctx.backend)
    dev = ctx.devices
    c = ctx.job.spec.cell
    (ctx.folder.path / "images").mkdir(exist_ok=True)
    for k, s in enumerate(stations):
        sid = s["id"]
        if sid in done:
            continue
        ctx.progress("acquire", k / len(stations))
        q = np.asarray(s["joints"], dtype=float)
        ctx.folder.append("station_start", station=sid)
        state = dev.robot.move_joints(q, c.max_joint_speed_rad_s, c.max_joint_accel_rad_s2)
        if c.settle_s and ctx.backend != "sim":
            time.sleep(c.settle_s)
        state = dev.robot.state()
        if not state.safety.normal:
            raise DriverError(f"station {sid}: robot not in normal mode after the move ({state.safety.detail})")
        err = float(np.max(np.abs(np.asarray(state.joints_rad) - q)))
        if err > 1e-3:
            raise DriverError(f"station {sid}: robot stopped {err:.4f} rad away from the station's joints")
        ctx.log.robot(state.joints_rad, state.base_from_flange, state.timestamp_s, sid)
        if dev.light is not None:
            dev.light.strobe(ctx.job.spec.camera.exposure_s)
        frame = dev.camera.capture()
        ok, png = cv2.imencode(".png", frame.image)
        if not ok:
            raise DriverError(f"station {sid}: could not encode the image")
        name = f"images/{int(s['order']):04d}.png"
        atomic_write_bytes(ctx.folder.file(name), png.tobytes())
        ctx.log.image(png.tobytes(), sid)
        ctx.folder.append("station_done", station=sid, image=name, sha256=sha256_file(ctx.folder.file(name)),
                          joints=np.asarray(state.joints_rad), base_from_flange=np.asarray(state.base_from_flange),
                          robot_timestamp_s=state.timestamp_s, exposure_s=frame.exposure_s)
    ctx.progress("acquire", 1.0)
    recs = acquired(list(ctx.folder.records()))
    images = [{"station": s["id"], "order": s["order"], "image": recs[s["id"]]["image"],
               "sha256": recs[s["id"]]["sha256"], "joints": recs[s["id"]]["joints"],
               "base_from_flange": recs[s["id"]]["base_from_flange"]} for s in stations]
    atomic_write_json(ctx.folder.file("acquisition.json"), {"images": images})
