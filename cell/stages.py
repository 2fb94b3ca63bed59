"""The stages of a job. Each reads what earlier stages wrote into the job folder and
writes its own result atomically before the state machine moves on."""
from __future__ import annotations

import json
import time

import cv2
import numpy as np

from calibration.camera import Intrinsics, invert
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


def _rim_clear(occluder, xyz: np.ndarray, normals: np.ndarray, radius_m: float, eye: np.ndarray,
               samples: int = 12, margin: float = 1.3) -> np.ndarray:
    """Whether the whole rim of each dot (grown by ``margin``) is in view from ``eye``, (n,) bool.

    A dot partly hidden by an edge of the part images as a clipped disc whose centroid is biased
    by up to its radius; such an observation is dropped, not measured.
    """
    n = len(xyz)
    if n == 0:
        return np.zeros(0, dtype=bool)
    a = np.where(np.abs(normals[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(normals, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normals, e1)
    ang = np.linspace(0, 2 * np.pi, samples, endpoint=False)
    rim = (xyz[:, None] + margin * radius_m * (np.cos(ang)[None, :, None] * e1[:, None] + np.sin(ang)[None, :, None]
           * e2[:, None]) + 2e-4 * normals[:, None])
    hit = occluder.occluded(rim.reshape(-1, 3), np.broadcast_to(eye, (n * samples, 3)))
    return ~hit.reshape(n, samples).any(axis=1)


def _inside_any(uv: np.ndarray, quads: np.ndarray, grow: float = 1.0) -> np.ndarray:
    """Which points ``uv: (k, 2)`` lie inside any of the quadrilaterals ``quads: (c, 4, 2)``."""
    inside = np.zeros(len(uv), dtype=bool)
    for q in quads:
        c = q.mean(axis=0)
        poly = ((q - c) * grow + c).astype(np.float32)
        inside |= np.array([cv2.pointPolygonTest(poly, (float(u), float(v)), False) >= 0 for u, v in uv], dtype=bool)
    return inside


def measure(ctx) -> None:
    """Detect, centre and identify the targets in every image.

    Coded targets name themselves (their centre is the intersection of the marker's
    diagonals: the exact image of its centre under perspective); dots are named by
    projecting the nominal targets with the robot's pose and the hand-eye, refined by
    the coded targets (solvePnP) where at least four are seen.
    """
    from calibration.targets import (DetectionOptions, detect_coded_targets, detect_retro_targets, eccentricity_bias,
                                     identify_targets)

    job = ctx.job
    acq = _read(ctx, "acquisition.json")
    t = job.part.targets
    ids_all = t.ids
    code_to_index = {int(c): i for i, c in enumerate(t.code) if c >= 0}
    bfp, ffc = job.spec.base_from_part(), job.spec.flange_from_cam()
    from planning.visibility import Occluder, VisibilityOptions, compute_visibility

    opts = DetectionOptions()
    max_dist = 25.0
    # which targets can be in view at all from the approximate pose: a dot hidden behind the part must
    # not be offered to the matcher, or it steals the detection of a visible neighbour
    seeable = VisibilityOptions(margin_px=0.0, incidence_max_rad=np.deg2rad(85.0), min_target_px=1.0)
    occluder = Occluder(job.part.mesh)
    poses = np.array([invert(bfp) @ np.asarray(im["base_from_flange"], dtype=float) @ ffc for im in acq["images"]])
    in_view = compute_visibility(job.part, job.intrinsics, poses, seeable, occluder=occluder)
    out = []
    for k, im in enumerate(acq["images"]):
        ctx.progress("measure", k / len(acq["images"]))
        img = cv2.imread(str(ctx.folder.file(im["image"])), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise CalibrationError(f"{im['image']}: cannot read the image")
        cam_from_part = invert(invert(bfp) @ np.asarray(im["base_from_flange"], dtype=float) @ ffc)
        codes, corners, centres = detect_coded_targets(img)
        known = np.array([c in code_to_index for c in codes], dtype=bool)
        codes, centres = codes[known], centres[known]
        det = detect_retro_targets(img, opts)
        # a dot inside a coded marker's square (grown by a third) is part of the marker, not a target
        keep = ~_inside_any(det.uv, corners[known], grow=1.33)
        det_uv = det.uv[keep]
        cand = np.flatnonzero(in_view[k] | (t.code >= 0))
        sub = identify_targets(det_uv, t.xyz[cand], t.code[cand], job.intrinsics, cam_from_part, max_dist,
                               coded_ids=codes, coded_uv=centres)
        match = np.where(sub >= 0, cand[np.maximum(sub, 0)], -1)
        # coded targets identify the image (and refine its pose) but are not measured: OpenCV's
        # sub-pixel marker corners are biased by 0.1-0.3 px, ten times the dots' precision
        names, uv = [], []
        dots = np.flatnonzero((match >= 0) & (t.code[np.maximum(match, 0)] < 0))
        clear = _rim_clear(occluder, t.xyz[match[dots]], t.normals[match[dots]], job.part.target_diameter_m / 2,
                           poses[k][:3, 3])
        n_clipped = int((~clear).sum())
        dots = dots[clear]
        # the centroid of a dot's ellipse is not the image of its centre: remove that eccentricity
        bias = eccentricity_bias(job.intrinsics, cam_from_part, t.xyz[match[dots]], t.normals[match[dots]],
                                 job.part.target_diameter_m / 2)
        for j, b in zip(dots, bias):
            names.append(ids_all[int(match[j])])
            uv.append(det_uv[j] - b)
        out.append({"station": im["station"], "image": im["image"], "ids": names,
                    "uv": np.asarray(uv, dtype=float).reshape(-1, 2), "n_dots": int(len(det_uv)),
                    "n_coded": int(len(codes)), "n_unidentified": int((match < 0).sum()),
                    "n_partly_hidden": n_clipped})
        ctx.log.detections(im["station"], names, np.asarray(uv).reshape(-1, 2))
    ctx.progress("measure", 1.0)
    atomic_write_json(ctx.folder.file("observations.json"), {"images": out})
    n = [len(o["ids"]) for o in out]
    ctx.say(f"  {sum(n)} observations in {len(out)} images ({min(n)}..{max(n)} per image), "
            f"{sum(o['n_unidentified'] for o in out)} dots unidentified")


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


# --- REPORT ---------------------------------------------------------------------------------


def report(ctx) -> None:
    from cell.stage_report import write_report

    verdict = write_report(ctx)
    ctx.say(f"  verdict {verdict}: report {ctx.folder.file('report.html')}")
