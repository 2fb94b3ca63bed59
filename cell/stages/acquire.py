"""ACQUIRE: move to each station, wait until the arm has settled, trigger the camera with the light pulsing in
the exposure, check the frame (:mod:`cell.stages.exposure`); a station is done when its image is on disk and
journalled. A frame that comes late, twice or never is logged (``/camera/exposure``, journal ``frame_fault``) and
the station retaken (``[cell] retakes``), so no frame is ever stored as another station's."""
from __future__ import annotations

import cv2
import numpy as np

from calibration.errors import DriverError, MoveRefusedError
from cell.thermal import read_probe
from cell.record.integrity import acquired
from cell.record.jobfolder import atomic_write_bytes, atomic_write_json, sha256_file
from cell.stages.exposure import ExposureTaker, FrameFault, wait_settled
from drivers.motion import arm_moved

SIM_HOLD_S = 0.02


def _stations_in_order(plan_doc: dict) -> list[dict]:
    st = plan_doc["stations"]
    return sorted(st, key=lambda s: s["order"])


#: decoded images ACQUIRE hands to MEASURE in the same session (bytes in all; beyond it MEASURE reads the files)
FRAME_CACHE_BYTES = 512 << 20


def keep_frame(ctx, name: str, sha256: str, image: np.ndarray) -> None:
    """Keep ``image``, the pixels of the PNG ``name`` whose file hashes to ``sha256``, for MEASURE in this session.

    PNG is lossless, so MEASURE gets the stored pixels without decoding the file again (~45 ms per 5 MP image);
    it takes them only while the file's sha256 in acquisition.json is this one.
    """
    frames = ctx.cache.setdefault("frames", {})
    size = sum(im.nbytes for _, im in frames.values())
    if size + image.nbytes <= FRAME_CACHE_BYTES:
        frames[name] = (sha256, np.array(image, copy=True))  # a copy: a camera may reuse its frame buffers


def run(ctx) -> None:
    """Move to each station, strobe, capture; a station is done when its image is on disk and journalled."""
    from cell.devices import inject_unreachable, open_devices

    plan_doc = ctx.folder.read_json("plan.json")
    stations = _stations_in_order(plan_doc)
    recs0 = list(ctx.folder.records())
    done = set(acquired(recs0))  # stations whose image stands (verified on resume)
    if ctx.devices is None:
        ctx.devices = open_devices(ctx.job, ctx.backend)
    dev = ctx.devices
    unreachable = set(ctx.job.spec.sim.unreachable_stations)
    if unreachable:  # the sim's knob: stations whose move the (simulated or loopback) controller refuses
        inject_unreachable(dev, ctx.job, ctx.backend, [s["joints"] for s in stations if s["id"] in unreachable])
    skipped = {r["station"]: r["reason"] for r in recs0 if r["event"] == "station_skipped"}
    c = ctx.job.spec.cell
    read_probe(ctx, dev.thermometer, "start")  # [thermal] part_C = "probe" (decision 0053)
    (ctx.folder.path / "images").mkdir(exist_ok=True)
    cam = ctx.job.spec.camera
    light_by_line = dev.light is not None and c.light_input is not None
    taker = ExposureTaker(dev.robot, dev.camera, dev.light, exposure_s=cam.exposure_s,
                          frame_timeout_s=cam.frame_timeout_s, light_by_line=light_by_line,
                          frame_size=(cam.width, cam.height), on_notice=lambda sid, line: _light_rearmed(ctx, sid, line))
    # the simulated arm is still the instant it arrives: a short hold proves it without slowing the sim down
    hold_s = c.settle_s if ctx.backend != "sim" else min(c.settle_s, SIM_HOLD_S)
    first = True  # the first move of this run (a fresh job or a resume) starts wherever the arm is
    for k, s in enumerate(stations):
        sid = s["id"]
        if sid in done or sid in skipped:  # a station the robot could not reach is not tried again in this job
            continue
        ctx.progress("acquire", k / len(stations))
        q = np.asarray(s["joints"], dtype=float)
        ctx.folder.append("station_start", station=sid)
        after = next((t for t in stations[k + 1:] if t["id"] not in done and t["id"] not in skipped), None)
        if first:
            via = s.get("validated_from_q")  # a loop station: its round was validated from there (decision 0070)
            if via is None and s.get("round") is not None:  # recorded before 0070: the last station taken before it
                via = next((t["joints"] for t in reversed(stations[:k]) if t["id"] in done), None)
            check_first_move(ctx, dev.robot, sid, q, plan_doc, via=via)
            first = False
        if not _move_or_skip(ctx, dev.robot, sid, q, skipped, None if after is None else after["joints"]):
            continue
        for attempt in range(1, c.retakes + 2):
            state, state_host_s, peak = wait_settled(dev.robot, speed_tol_rad_s=c.settle_speed_rad_s, hold_s=hold_s,
                                                     timeout_s=c.settle_timeout_s, station=sid)
            err = float(np.max(np.abs(np.asarray(state.joints_rad) - q)))
            if err > 1e-3:
                raise DriverError(f"station {sid}: robot stopped {err:.4f} rad away from the station's joints")
            try:
                frame, rec = taker.take(sid, attempt, state, state_host_s, peak, hold_s)
                break
            except FrameFault as fault:
                ctx.log.exposure(fault.record.as_dict())
                ctx.folder.append("frame_fault", station=sid, attempt=attempt, outcome=fault.outcome, detail=str(fault))
                ctx.log.log("warning", f"{fault}; retaking" if attempt <= c.retakes else str(fault))
                ctx.say(f"  {fault}" + ("; retaking" if attempt <= c.retakes else ""))
                if attempt > c.retakes:
                    raise DriverError(f"{fault} ({attempt} attempts); the station is not stored: resume retakes it") \
                        from None
        ctx.log.robot(state.joints_rad, state.base_from_flange, rec.robot_timestamp_s, sid)
        ctx.log.exposure(rec.as_dict())
        ok, png = cv2.imencode(".png", frame.image)
        if not ok:
            raise DriverError(f"station {sid}: could not encode the image")
        name = f"images/{int(s['order']):04d}.png"
        atomic_write_bytes(ctx.folder.file(name), png.tobytes())
        ctx.log.image(png.tobytes(), sid)
        digest = sha256_file(ctx.folder.file(name))
        keep_frame(ctx, name, digest, frame.image)
        ctx.folder.append("station_done", station=sid, image=name, sha256=digest,
                          joints=np.asarray(state.joints_rad), base_from_flange=np.asarray(state.base_from_flange),
                          robot_timestamp_s=rec.robot_timestamp_s, exposure_s=frame.exposure_s,
                          frame_id=rec.frame_id, trigger_host_s=rec.trigger_host_s, frame_host_s=rec.frame_host_s,
                          attempts=attempt)
    ctx.progress("acquire", 1.0)
    read_probe(ctx, dev.thermometer, "end")
    recs = acquired(list(ctx.folder.records()))
    images = [{"station": s["id"], "order": s["order"], "image": recs[s["id"]]["image"],
               "sha256": recs[s["id"]]["sha256"], "joints": recs[s["id"]]["joints"],
               "base_from_flange": recs[s["id"]]["base_from_flange"]} for s in stations if s["id"] in recs]
    missed = [{"station": s["id"], "reason": skipped.get(s["id"], "not taken")} for s in stations
              if s["id"] not in recs]
    if len(images) < 2:
        raise DriverError(f"{len(images)} of {len(stations)} stations taken; nothing to measure")
    atomic_write_json(ctx.folder.file("acquisition.json"), {"images": images, "skipped": missed})


def _light_rearmed(ctx, sid: str, line: str) -> None:
    """The light controller had lost its pulse settings (a power blip) and was re-armed before station ``sid``'s
    exposure: said on the console, in the run log and in the journal (``light_rearmed``)."""
    ctx.folder.append("light_rearmed", station=sid, detail=line)
    ctx.log.log("warning", f"station {sid}: {line}")
    ctx.say(f"  WARNING station {sid}: {line}")


def _move_or_skip(ctx, robot, sid: str, q: np.ndarray, skipped: dict, q_next) -> bool:
    """Move to a station; a move the controller refuses before the arm moves (``MoveRefusedError``) skips the
    station (journal ``station_skipped``, log, console) when the move from here to the next station is
    collision-free too. Anything else (a protective stop, the cell's own limits, an abort, an arm that moved
    and stopped) faults the job as before."""
    c = ctx.job.spec.cell
    q_from = np.asarray(robot.state().joints_rad, dtype=float)
    try:
        robot.move_joints(q, c.max_joint_speed_rad_s, c.max_joint_accel_rad_s2)
        return True
    except MoveRefusedError as exc:  # only a refusal before any motion: a stop, a limit, an abort still fault
        if arm_moved(q_from, robot.state().joints_rad):
            raise
        if q_next is not None:
            _check_detour(ctx, sid, q_from, np.asarray(q_next, dtype=float))
        reason = f"the robot cannot reach it: {exc}"
        skipped[sid] = reason
        ctx.folder.append("station_skipped", station=sid, reason=reason)
        ctx.log.log("warning", f"station {sid} skipped: {reason}")
        ctx.say(f"  WARNING station {sid} skipped: {reason}")
        return False


def _deg(q) -> str:
    return "[" + ", ".join(f"{v:.1f}" for v in np.rad2deg(np.asarray(q, dtype=float))) + "] deg"


def check_first_move(ctx, robot, sid: str, q: np.ndarray, plan_doc: dict, via=None) -> None:
    """Check the first move of ACQUIRE (of a job, or after ``cell resume``) from the arm's measured joints.

    VALIDATE checked the tour from the plan's start pose (``execution.start_q``); the arm stands wherever it was
    left, stopped or jogged. The move from there to the first station is checked as VALIDATE and the detour check
    it (:func:`planning.execution.check_move`, the cell's collision world and clearance). Not free: ``DriverError``
    before anything moves, telling the operator to jog the arm to the start pose. Free: journalled
    (``first_move_checked``) and logged.

    A closed-loop station (``via``: plan.json ``validated_from_q``, the pose its round was validated from, decision
    0070) whose direct move is not free is reached through that pose when both legs are: the round's tour was
    validated from there, not from the plan's start pose. Otherwise the advice names that pose."""
    from cell.setup import collision_world, robot_model
    from planning.execution import MotionLimits, check_move, lever_arms

    q_from = np.asarray(robot.state().joints_rad, dtype=float)
    model, world = robot_model(ctx.job), collision_world(ctx.job)
    chk = check_move(model, world, q_from, np.asarray(q, dtype=float), lever_arms(model),
                     MotionLimits().check_resolution_rad, ("measured", sid), 0.0)
    start = (plan_doc.get("execution") or {}).get("start_q")
    a, b = chk.pair
    if not chk.free and via is not None:
        via = np.asarray(via, dtype=float)
        legs = [check_move(model, world, x, y, lever_arms(model), MotionLimits().check_resolution_rad,
                           ("measured", sid), 0.0) for x, y in ((q_from, via), (via, np.asarray(q, dtype=float)))]
        if all(leg.free for leg in legs):
            c = ctx.job.spec.cell
            robot.move_joints(via, c.max_joint_speed_rad_s, c.max_joint_accel_rad_s2)
            msg = (f"first move to station {sid} from {_deg(q_from)} is not collision-free ({a} vs {b}); went through "
                   f"{_deg(via)}, the pose its closed-loop round was validated from (both legs collision-free)")
            ctx.folder.append("first_move_checked", station=sid, joints=q_from, via=via,
                              min_distance_m=min(leg.min_distance_m for leg in legs), closest=list(legs[0].pair),
                              n_checks=sum(leg.n_checks for leg in legs))
            ctx.log.log("info", msg)
            ctx.say(f"  {msg}")
            return
    if not chk.free:
        raise DriverError(
            f"the first move, from where the arm stands ({_deg(q_from)}) to station {sid}, is not collision-free: "
            f"{a} vs {b} {chk.min_distance_m * 1e3:.1f} mm apart at {chk.at_fraction:.0%} of the move (clearance "
            f"{world.clearance_m * 1e3:.0f} mm); nothing moved: jog the arm to "
            + (f"{_deg(via)}, the pose the station's closed-loop round was validated from," if via is not None else
               f"the plan's start pose start_q {_deg(start) if start is not None else '(plan.json execution.start_q)'}")
            + " and resume the job")
    msg = (f"first move checked from the measured pose {_deg(q_from)} to station {sid}: collision-free, least "
           f"clearance {chk.min_distance_m * 1e3:.1f} mm ({a} vs {b})")
    ctx.folder.append("first_move_checked", station=sid, joints=q_from, min_distance_m=chk.min_distance_m,
                      closest=[a, b], n_checks=chk.n_checks)
    ctx.log.log("info", msg)


def _check_detour(ctx, sid: str, qa: np.ndarray, qb: np.ndarray) -> None:
    """The move past a skipped station was not in the validated plan: check it for collisions before it is made."""
    from cell.setup import collision_world, robot_model
    from planning.execution import MotionLimits, check_move, lever_arms

    robot = robot_model(ctx.job)
    chk = check_move(robot, collision_world(ctx.job), qa, qb, lever_arms(robot), MotionLimits().check_resolution_rad,
                     ("here", "next"), 0.0)
    if not chk.free:
        raise DriverError(f"station {sid} cannot be reached and the move past it collides ({chk.pair}); "
                          "the job stops here")
