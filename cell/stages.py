"""The stages of a job. Each reads what earlier stages wrote into the job folder and
writes its own result atomically before the state machine moves on."""
from __future__ import annotations

import json
import time

import cv2
import numpy as np

from calibration.camera import invert
from calibration.errors import CalibrationError, DriverError
from cell.jobfolder import atomic_write_bytes, atomic_write_json, sha256_file


def _read(ctx, name: str) -> dict:
    return json.loads(ctx.folder.file(name).read_text())


# --- LOAD ---------------------------------------------------------------------------


def load(ctx) -> None:
    atomic_write_json(ctx.folder.file("part.json"), ctx.job.summary())


# --- PLAN / VALIDATE ---------------------------------------------------------------------


def plan(ctx) -> None:
    from cell.stage_plan import make_plan

    p, facts = make_plan(ctx.job, progress=ctx.progress)
    doc = p.to_plan_dict() | {"databases": facts}
    atomic_write_json(ctx.folder.file("plan.json"), doc)
    try:
        from planning.plot import plot_plan

        plot_plan(ctx.job.part, p, ctx.folder.file("figures/plan.png"))
    except ImportError:
        pass
    ctx.say(f"  {len(p.station_ids)} stations; predicted sigma max {p.predicted_sigma_max_m * 1e6:.1f} um, "
            f"mean {p.predicted_sigma_mean_m * 1e6:.1f} um")


def validate(ctx) -> None:
    from cell.validate import validate_plan_doc

    doc = _read(ctx, "plan.json")
    doc, summary = validate_plan_doc(ctx.job, doc)
    atomic_write_json(ctx.folder.file("plan.json"), doc)
    ctx.say(f"  execution order {summary['order']}; estimated cycle time {summary['cycle_time_s']:.1f} s")


# --- ACQUIRE -------------------------------------------------------------------------------


def _stations_in_order(plan_doc: dict) -> list[dict]:
    st = plan_doc["stations"]
    return sorted(st, key=lambda s: s["order"])


def acquire(ctx) -> None:
    """Move to each station, strobe, capture; a station is done when its image is on disk and journalled."""
    from cell.devices import open_devices

    plan_doc = _read(ctx, "plan.json")
    stations = _stations_in_order(plan_doc)
    done = {r["station"] for r in ctx.folder.records() if r["event"] == "station_done"}
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
    recs = {r["station"]: r for r in ctx.folder.records() if r["event"] == "station_done"}
    images = [{"station": s["id"], "order": s["order"], "image": recs[s["id"]]["image"],
               "sha256": recs[s["id"]]["sha256"], "joints": recs[s["id"]]["joints"],
               "base_from_flange": recs[s["id"]]["base_from_flange"]} for s in stations]
    atomic_write_json(ctx.folder.file("acquisition.json"), {"images": images})


# --- MEASURE -------------------------------------------------------------------------------


def measure(ctx) -> None:
    """Detect, centre and identify the targets in every image (cell.imaging.measure_image).

    Dots are named by projecting the nominal targets with the robot's pose and the hand-eye, refined
    by the coded targets (solvePnP) where at least four are seen; coded targets are not measured.
    """
    from cell.imaging import measure_image
    from planning.visibility import Occluder

    job = ctx.job
    acq = _read(ctx, "acquisition.json")
    ids_all = job.part.targets.ids
    bfp, ffc = job.spec.base_from_part(), job.spec.flange_from_cam()
    occluder = Occluder(job.part.mesh)
    out = []
    for k, im in enumerate(acq["images"]):
        ctx.progress("measure", k / len(acq["images"]))
        img = cv2.imread(str(ctx.folder.file(im["image"])), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise CalibrationError(f"{im['image']}: cannot read the image")
        cam_from_part = invert(invert(bfp) @ np.asarray(im["base_from_flange"], dtype=float) @ ffc)
        m, counts = measure_image(img, job.part, job.intrinsics, cam_from_part, occluder)
        names = [ids_all[int(i)] for i in m.target]
        out.append({"station": im["station"], "image": im["image"], "ids": names, "uv": m.uv,
                    "n_unidentified": m.n_unidentified, "n_partly_hidden": m.n_partly_hidden} | counts)
        ctx.log.detections(im["station"], names, m.uv)
    ctx.progress("measure", 1.0)
    atomic_write_json(ctx.folder.file("observations.json"), {"images": out})
    n = [len(o["ids"]) for o in out]
    ctx.say(f"  {sum(n)} observations in {len(out)} images ({min(n)}..{max(n)} per image); "
            f"{sum(o['n_partly_hidden'] for o in out)} partly hidden dots dropped, "
            f"{sum(o['n_unidentified'] for o in out)} other blobs (marker pieces, edges) ignored")


# --- CALIBRATE -----------------------------------------------------------------------------


def _pnp_from_robot(job, xyz: np.ndarray, uv: np.ndarray, base_from_flange: np.ndarray) -> tuple[np.ndarray, float]:
    """Exterior orientation by PnP with the nominal camera, started from the robot's pose and the hand-eye."""
    cam_from_part = invert(invert(job.spec.base_from_part()) @ base_from_flange @ job.spec.flange_from_cam())
    rvec, _ = cv2.Rodrigues(cam_from_part[:3, :3])
    ok, rvec, tvec = cv2.solvePnP(xyz, uv, job.intrinsics.K, job.intrinsics.dist_coeffs, rvec.copy(),
                                  cam_from_part[:3, 3].copy(), useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError("PnP from the robot pose failed")
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    from calibration.camera import project

    rms = float(np.sqrt(np.mean(np.sum((project(job.intrinsics, T, xyz) - uv) ** 2, axis=1))))
    return T, rms


def calibrate(ctx) -> None:
    """Faugeras-Toscani per image: interior and exterior orientation from the nominal targets.

    An image whose targets are nearly coplanar (one face of the part fills it) gives Faugeras-Toscani
    no depth to work with: it fails, or returns an orientation far from the robot's. Such an image
    is oriented by PnP with the nominal camera instead, started from the robot pose, and says so.
    """
    from calibration.faugeras_toscani import faugeras_toscani

    job = ctx.job
    obs = _read(ctx, "observations.json")
    acq = {a["station"]: a for a in _read(ctx, "acquisition.json")["images"]}
    index = job.part.targets.index()
    res = []
    for o in obs["images"]:
        xyz = job.part.targets.xyz[[index[i] for i in o["ids"]]]
        uv = np.asarray(o["uv"], dtype=float).reshape(-1, 2)
        bff = np.asarray(acq[o["station"]]["base_from_flange"], dtype=float)
        robot_pose = invert(invert(job.spec.base_from_part()) @ bff @ job.spec.flange_from_cam())
        rec = {"station": o["station"], "image": o["image"], "n_points": len(uv)}
        try:
            ft = faugeras_toscani(xyz, uv, job.intrinsics.width, job.intrinsics.height)
            centre_gap = float(np.linalg.norm(invert(ft.cam_from_part)[:3, 3] - invert(robot_pose)[:3, 3]))
            if centre_gap > 0.1 * float(np.linalg.norm(robot_pose[:3, 3])):
                raise CalibrationError(f"its camera centre is {centre_gap * 1e3:.0f} mm from the robot's")
            rec |= {"method": "Faugeras-Toscani", "alpha_u": ft.intrinsics.fx_px, "alpha_v": ft.intrinsics.fy_px,
                    "u0": ft.intrinsics.cx_px, "v0": ft.intrinsics.cy_px, "cam_from_part": ft.cam_from_part,
                    "M": ft.M, "rms_px": ft.rms_px}
        except CalibrationError as exc:
            if len(uv) < 4:
                raise CalibrationError(f"image {o['image']} (station {o['station']}): only {len(uv)} targets "
                                       "identified; cannot orient it") from None
            T, rms = _pnp_from_robot(job, xyz, uv, bff)
            rec |= {"method": "PnP from the robot pose", "fallback_reason": f"Faugeras-Toscani: {exc}",
                    "cam_from_part": T, "rms_px": rms}
            ctx.log.log("warning", f"{o['image']}: Faugeras-Toscani unusable ({exc}); oriented by PnP")
        res.append(rec)
    atomic_write_json(ctx.folder.file("calibration.json"), {"method": "Faugeras-Toscani", "images": res})
    ft_ok = [r for r in res if r["method"] == "Faugeras-Toscani"]
    if not ft_ok:
        raise CalibrationError("Faugeras-Toscani failed on every image: check the target identification")
    fx = np.array([r["alpha_u"] for r in ft_ok])
    ctx.say(f"  alpha_u {fx.mean():.1f} +- {fx.std():.1f} px over {len(ft_ok)} images "
            f"(nominal {job.intrinsics.fx_px:.1f}); rms {np.median([r['rms_px'] for r in ft_ok]):.3f} px"
            + (f"; {len(res) - len(ft_ok)} image(s) oriented by PnP" if len(ft_ok) < len(res) else ""))


# --- ADJUST ---------------------------------------------------------------------------------


def adjust(ctx) -> None:
    """Rigorous bundle adjustment from the Faugeras-Toscani start, with the job's datum."""
    from cell.stage_adjust import run_bundle

    doc = run_bundle(ctx)
    atomic_write_json(ctx.folder.file("bundle.json"), doc)
    ctx.say(f"  sigma0 {doc['sigma0_px']:.3f} px, {doc['n_rejected']} observation(s) rejected, "
            f"datum {doc['datum']}, {doc['time_s']:.2f} s")
    if doc["observation_weights"]["method"] == "incidence":
        ctx.say("  image sigma by incidence (variance components): " + ", ".join(
            f"{g['name']} {g['sigma_px']:.3f} px" + ("" if g["estimated"] else " (common)")
            for g in doc["observation_weights"]["groups"] if g["n_observations"]))


# --- REPORT ---------------------------------------------------------------------------------


def report(ctx) -> None:
    from cell.stage_report import write_report

    verdict = write_report(ctx)
    ctx.say(f"  verdict {verdict}: report {ctx.folder.file('report.html')}")
