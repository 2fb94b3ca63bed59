"""Calibrating the cell itself: the hand-eye job, the part placement estimate, the reverification job.

* :func:`run_hand_eye` (``cell calibrate hand-eye CELL.toml``): stations around the calibration
  artefact chosen for a well-conditioned hand-eye (D-optimal on the predicted information, among
  the candidates the robot reaches without collision), ordered and collision-checked like an
  inspection's; per image: dots detected, identified, centred (eccentricity), exterior orientation
  by Faugeras-Toscani refined by resection; AX = XB by every closed-form method; then the joint
  refinement on all observations with its covariance. ``flange_from_cam`` and the date go into
  the cell file; everything is archived under ``<archive>/calibration/<id>/``.
* :func:`estimate_part_placement`: a few images of the part's coded targets, then the placement
  adjusted on every identified dot with the hand-eye held fixed.
* :func:`run_reverification` (after VDI/VDE 2634 part 1): the scale bar in several positions;
  its two targets triangulated in the robot base frame from the robot's poses and the hand-eye
  (the cell measuring as a whole); the length measurement error of each position against
  ``E_MPE``; archived. :func:`calibration_status` is what an inspection report states.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, replace
from datetime import datetime, timedelta, timezone
from pathlib import Path

import cv2
import numpy as np

from calibration.camera import Intrinsics, invert, project, project_with_jacobians
from calibration.errors import AbortRequested, CalibrationError, InputError, PlanningError, ReachabilityError
from calibration.faugeras_toscani import faugeras_toscani
from calibration.handeye import (HandEyeConditioning, HandEyeOptions, compare_methods, hand_eye_conditioning,
                                 hand_eye_information, pose_error, refine_hand_eye)
from calibration.targets import refine_pose_pnp
from cell import imaging
from cell.cellfile import CellFile, load_cell_file, pose_from_matrix, write_flange_from_cam
from cell.jobfolder import JobFolder, atomic_write_bytes, atomic_write_json, new_job_id, utc_now
from cell.jobspec import CellSection, JobSection, JobSpec, Pose, ReportSection, SimSection, pose_matrix, resolve
from cell.load import LoadedJob
from planning.part import load_part
from planning.planner import NetworkPlan, PlannerOptions, build_database, plan_network
from planning.stations import ViewingSphere
from planning.visibility import Occluder, VisibilityOptions, compute_visibility

__all__ = ["run_hand_eye", "run_reverification", "calibration_status",
           "artefact_job", "measure_image", "plan_stations", "capture_at", "plan_hand_eye_stations", "ask_operator",
           "StationPlan"]

CAL_DIR = "calibration"


# --- an artefact as a job: the robot, the cell's collision world and the sim follow from it ---------


def artefact_job(cf: CellFile, folder: Path, cell_path: Path, *, name: str, mesh: str, targets: str,
                 target_diameter: float, coded_size: float, placement: Pose, seed: int = 0) -> LoadedJob:
    """A :class:`LoadedJob` whose part is a calibration artefact placed at ``placement`` (base frame)."""
    c = cf.cell
    cell = CellSection(**c.model_dump(exclude={"name", "units", "base_from_part", "flange_from_cam_date",
                                               "flange_from_cam_record"}), base_from_part=placement)
    sim = cf.sim.model_dump(exclude={"flange_from_cam_true"})
    if cf.sim.flange_from_cam_true is not None:
        true_x = pose_matrix(cf.sim.flange_from_cam_true, cf.scale)
        sim["flange_from_cam_error"] = pose_from_matrix(invert(cf.flange_from_cam()) @ true_x, cf.scale)
    spec = JobSpec(job=JobSection(name=name, mesh=str(resolve(folder, mesh)), units=c.units,
                                  targets=str(resolve(folder, targets)), n_coded=0, target_diameter=target_diameter,
                                  coded_size=coded_size, seed=seed),
                   camera=cf.camera, cell=cell, report=ReportSection(tolerance=1.0), sim=SimSection(**sim))
    k = spec.scale
    part = load_part(resolve(folder, mesh), c.units, targets_csv=resolve(folder, targets), name=name,
                     target_diameter_m=target_diameter * k, coded_size_m=coded_size * k)
    n = len(part.targets)
    return LoadedJob(spec=spec, path=Path(cell_path), folder=folder, part=part, intrinsics=spec.intrinsics(),
                     deviations=np.zeros((n, 3)), tolerance_m=np.full(n, k), scale_bar=None)


# --- stations: the inspection's planner, reachability and validation -----------------------------------

#: The evolutionary search's size for a calibration artefact (a few dozen targets, a handful of stations).
CAL_POPULATION, CAL_GENERATIONS, CAL_STALL = 60, 120, 30


@dataclass
class StationPlan:
    """Stations of a calibration job as the planner chose them, in visiting order.

    Attributes:
        part_from_cam: (k, 4, 4) stations (artefact frame); joints: (k, 6) validated joint targets.
        plans: the planner's :class:`NetworkPlan` of each distance band.
        visible: (k, n) which of the planning part's targets each station measures (exact visibility).
        facts: candidates, reachable ones, predicted sigmas, cycle time, seed used.
    """

    part_from_cam: np.ndarray
    joints: np.ndarray
    plans: list[NetworkPlan]
    visible: np.ndarray
    facts: dict


def plan_stations(job: LoadedJob, k: int, *, min_rays: int, max_tilt_rad: float, incidence_max_rad: float,
                  sigma_px: float, n_candidates: int, seed: int, targets: np.ndarray | None = None,
                  margin_px: float = 20.0, depth_margin: float = 0.35,
                  bands: tuple[tuple[float, float], ...] = ((0.0, 1.0),), roll_spread_rad: float = 0.0) -> StationPlan:
    """``k`` stations around the artefact of ``job`` by the network planner, as an inspection plans them.

    The artefact is the part planned for (``targets``: a boolean mask of the targets that count,
    default all). Candidates on a viewing sphere tilted at most ``max_tilt_rad`` from the artefact's
    normal, at distances that keep it in the depth of field (``depth_margin`` of its radius inside
    ``near``/``far``); the visibility database (:func:`build_database`), the robot's reachability
    (:class:`ReachabilityDB`, IK + collisions in the cell), then :func:`plan_network` in fixed-size
    mode (every counted target measured by ``min_rays`` stations, the worst predicted sigma minimised).
    ``bands``: fractions of that distance range, one planned network each (the stations split evenly);
    ``roll_spread_rad``: the planner plans at zero roll (roll does not change what a centred artefact's
    points are measured with); a job that needs rotations about the optical axis too (the hand-eye)
    gets rolls spread evenly over +-``roll_spread_rad`` (in a seeded order), halved while a target would
    lose one of its ``min_rays`` rays to the image border. Then :func:`validate_plan` on them all (IK
    branches, collision-checked moves, visiting order).
    """
    from planning.execution import MotionLimits, validate_plan
    from planning.reachability import ReachabilityDB
    from planning.visibility import default_cache_dir

    from cell.setup import collision_world, robot_model

    c, sc = job.spec.cell, job.spec.scale
    near, far = job.spec.camera.near * sc, job.spec.camera.far * sc
    part = job.part if targets is None else replace(job.part, targets=job.part.targets.subset(np.asarray(targets)))
    r = part.radius
    d0, d1 = near + depth_margin * r, far - depth_margin * r
    if d1 <= d0:
        raise ReachabilityError(f"{job.part.name}: the artefact ({2 * r * 1000:.0f} mm across) does not fit in the "
                                f"camera's depth of field {near * 1000:.0f}..{far * 1000:.0f} mm")
    robot, world = robot_model(job), collision_world(job)
    X, Y = job.spec.flange_from_cam(), job.spec.base_from_part()
    cache = default_cache_dir()
    sizes = np.diff(np.round(np.linspace(0, k, len(bands) + 1)).astype(int))
    plans, facts = [], {"seed": int(seed), "bands": []}
    for b, ((f0, f1), kb) in enumerate(zip(bands, sizes)):
        sphere = replace(ViewingSphere.for_part(part, job.intrinsics, elevation_min_rad=np.pi / 2 - max_tilt_rad),
                         distance_min_m=d0 + f0 * (d1 - d0), distance_max_m=d0 + f1 * (d1 - d0))
        opts = PlannerOptions(n_stations=int(kb), min_rays=min(min_rays, int(kb)), incidence_max_rad=float(incidence_max_rad),
                              criterion="worst", sigma_px=sigma_px, mode="fixed", population=CAL_POPULATION,
                              generations=CAL_GENERATIONS, stall_generations=CAL_STALL, sphere=sphere,
                              n_candidates=n_candidates, n_shells=2,
                              visibility=VisibilityOptions(margin_px=margin_px, near_m=near, far_m=far,
                                                           incidence_max_rad=float(incidence_max_rad)))
        db = build_database(part, job.intrinsics, opts, cache_dir=cache)
        reach = ReachabilityDB.load_or_build(robot, Y, X, db.part_from_cam, world, cache_dir=cache)
        if not (reach.reachable & db.visible.any(axis=1)).any():
            raise ReachabilityError(f"{job.part.name}: the robot reaches none of the {len(db.part_from_cam)} candidate "
                                    f"stations around the artefact at {np.round(Y[:3, 3], 3).tolist()} m: move it closer")
        try:
            plan = plan_network(part, job.intrinsics, opts, np.random.default_rng(seed + 1000 * b),
                                reachable=reach.reachable, cache_dir=cache, seed=seed + 1000 * b, db=db)
        except PlanningError as exc:
            raise ReachabilityError(f"{job.part.name}: {exc} ({int(reach.reachable.sum())} of {len(reach.reachable)} "
                                    "candidate stations reachable)") from None
        plans.append(plan)
        facts["bands"].append({"distance_m": [sphere.distance_min_m, sphere.distance_max_m], "stations": int(kb),
                               "candidates": int(len(reach.reachable)), "reachable": int(reach.reachable.sum()),
                               "predicted_sigma_max_m": plan.predicted_sigma_max_m,
                               "stopped_because": plan.search.get("stopped_because")})
    P = np.concatenate([p.part_from_cam for p in plans])
    visible = np.concatenate([_seen_matrix(p) for p in plans])
    if roll_spread_rad > 0:
        vis_opts = VisibilityOptions(margin_px=margin_px, near_m=near, far_m=far, incidence_max_rad=float(incidence_max_rad))
        P, visible, facts["roll_spread_deg"] = _spread_rolls(part, job.intrinsics, P, visible, vis_opts, roll_spread_rad,
                                                             min(min_rays, k), np.random.default_rng(seed))
    ids = [f"{job.part.name}-{b}-{sid}" for b, p in enumerate(plans) for sid in p.station_ids]
    ep = validate_plan(robot, P, Y, X, world, MotionLimits(
        joint_speed_rad_s=c.max_joint_speed_rad_s, joint_accel_rad_s2=c.max_joint_accel_rad_s2, settle_s=c.settle_s),
        ids=ids)
    facts["cycle_time_s"] = float(ep.cycle_time_s)
    return StationPlan(P[ep.order], ep.joints[ep.order], plans, visible[ep.order], facts)


def _spread_rolls(part, intr: Intrinsics, P: np.ndarray, visible: np.ndarray, vis_opts: VisibilityOptions,
                  spread: float, min_rays: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """Turn the stations ``P: (k, 4, 4)`` about their optical axes by rolls spread over +-``spread``.

    Returns the rolled stations, what each measures, and the spread used (degrees): halved (up to
    three times, then none) while a target measured ``min_rays`` times before would be measured fewer.
    """
    k = len(P)
    order = rng.permutation(k)
    need = np.minimum(visible.sum(axis=0), min_rays)
    for _ in range(4):
        roll = spread * np.linspace(-1.0, 1.0, k)[order]
        c, s = np.cos(roll), np.sin(roll)
        Rz = np.zeros((k, 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
        Q = P.copy()
        Q[:, :3, :3] = P[:, :3, :3] @ Rz
        vis = compute_visibility(part, intr, Q, vis_opts)
        if np.all(vis.sum(axis=0) >= need):
            return Q, vis, float(np.rad2deg(spread))
        spread *= 0.5
    return P, visible, 0.0


def _seen_matrix(plan: NetworkPlan) -> np.ndarray:
    """(k, n) bool: which target each station of ``plan`` measures (from its exact ``seen_by``)."""
    index = {sid: i for i, sid in enumerate(plan.station_ids)}
    out = np.zeros((len(plan.station_ids), len(plan.target_ids)), dtype=bool)
    for j, seen in enumerate(plan.seen_by):
        out[[index[sid] for sid in seen], j] = True
    return out


def plan_hand_eye_stations(job: LoadedJob, he, sigma_px: float, out) -> tuple[StationPlan, HandEyeConditioning, list]:
    """The hand-eye's stations: planned (:func:`plan_stations`), then checked for the hand-eye's conditioning.

    The planner minimises the artefact's point precision, which also wants wide, convergent
    views; rotations about the optical axis, which that criterion cannot see, come from rolls spread
    over +-``[hand_eye] roll_spread_deg``; what AX = XB needs besides is checked on the planned network
    (:func:`hand_eye_conditioning`): X's predicted sigmas and the motions' weakest rotation
    against ``[hand_eye]`` ``max_sigma_translation``, ``max_sigma_rotation_deg`` and
    ``min_weakest_rotation_deg``. A network that misses them is replaced by the planner's
    network for the next seed (up to ``max_plans``); the best-conditioned one that meets the
    requirement is used, else the job stops with what was missed. Returns the stations, their
    conditioning and one row per network tried.
    """
    sc = job.spec.scale
    dots = job.part.targets.kind != "coded"
    req = (he.max_sigma_translation * sc, np.deg2rad(he.max_sigma_rotation_deg), np.deg2rad(he.min_weakest_rotation_deg))
    tried = []
    for attempt in range(he.max_plans):
        sp = plan_stations(job, he.n_stations, min_rays=he.min_rays, max_tilt_rad=np.deg2rad(he.max_tilt_deg),
                           incidence_max_rad=np.deg2rad(he.incidence_max_deg), sigma_px=sigma_px,
                           n_candidates=he.n_candidates, seed=he.seed + attempt, targets=dots,
                           bands=((0.0, 0.3), (0.7, 1.0)), roll_spread_rad=np.deg2rad(he.roll_spread_deg))
        info = hand_eye_information(job.intrinsics, sp.part_from_cam, sp.visible, job.part.targets.xyz[dots],
                                    job.spec.flange_from_cam(), job.spec.base_from_part(), sigma_px)
        cond = hand_eye_conditioning(info, sp.part_from_cam, job.spec.flange_from_cam())
        missed = cond.shortfall(*req)
        tried.append({"seed": sp.facts["seed"], "conditioning": cond.to_dict(), "missed": missed,
                      "bands": sp.facts["bands"]})
        out.say(f"hand-eye: planned {len(sp.part_from_cam)} stations (seed {sp.facts['seed']}): X predicted "
                f"+- {np.linalg.norm(cond.sigma_translation_m) * 1e3:.4f} mm, "
                f"{np.rad2deg(np.linalg.norm(cond.sigma_rotation_rad)):.5f} deg; weakest rotation "
                f"{np.rad2deg(cond.weakest_rotation_rad):.1f} deg, pivot rms {cond.pivot_rms_m * 1e3:.1f} mm"
                + (f" -- misses: {'; '.join(missed)}" if missed else ""))
        if not missed:
            return sp, cond, tried
    raise PlanningError(f"hand-eye: none of {he.max_plans} planned networks is conditioned well enough for the "
                        f"hand-eye ({'; '.join(tried[-1]['missed'])}): raise [hand_eye] n_stations or max_tilt_deg, "
                        "or move the artefact where the robot can turn the camera more")


# --- one image --------------------------------------------------------------------------------------------


def measure_image(img: np.ndarray, part, intr: Intrinsics, cam_from_part_approx: np.ndarray,
                  occluder: Occluder) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dots measured in one image: ``(target index (k,), uv (k, 2) eccentricity-corrected, cam_from_part used)``.

    :func:`cell.imaging.measure_image` from the approximate pose; with six dots or more the pose is
    refined by PnP on them and the dots are named and measured again from it.
    """
    m, _ = imaging.measure_image(img, part, intr, cam_from_part_approx, occluder)
    if len(m.target) >= 6:
        pose = refine_pose_pnp(intr, m.cam_from_part, part.targets.xyz[m.target], m.uv)
        m, _ = imaging.measure_image(img, part, intr, pose, occluder)
    return m.target, m.uv, m.cam_from_part


def capture_at(devices, q: np.ndarray, c) -> tuple[np.ndarray, np.ndarray]:
    """Move to joints ``q``, capture; returns ``(image, base_from_flange measured)``."""
    devices.robot.move_joints(q, c.max_joint_speed_rad_s, c.max_joint_accel_rad_s2)
    st = devices.robot.state()
    if not st.safety.normal:
        raise CalibrationError(f"robot not in normal mode after the move ({st.safety.detail})")
    if devices.light is not None:
        devices.light.strobe(0.002)
    frame = devices.camera.capture()
    return frame.image, np.asarray(st.base_from_flange, dtype=float)


def _record_folder(archive_root: Path, cell_name: str, kind: str) -> JobFolder:
    root = Path(archive_root) / CAL_DIR
    root.mkdir(parents=True, exist_ok=True)
    rid = new_job_id(f"{cell_name}-{kind}")
    k = 1
    while (root / rid).exists():
        k += 1
        rid = f"{new_job_id(f'{cell_name}-{kind}')}-{k}"
    (root / rid).mkdir()
    return JobFolder(root / rid)


def _save_image(folder: JobFolder, name: str, img: np.ndarray) -> None:
    ok, png = cv2.imencode(".png", img)
    if not ok:
        raise CalibrationError(f"{name}: could not encode the image")
    atomic_write_bytes(folder.file(name), png.tobytes())


# --- the hand-eye job -----------------------------------------------------------------------------------------


def run_hand_eye(cell_toml: Path, archive_root: Path, out, *, backend: str | None = None) -> dict:
    """Calibrate ``flange_from_cam``; writes it (and the date) into ``cell_toml``. Returns the summary."""
    from cell.devices import open_devices

    cell_toml = Path(cell_toml)
    cf, folder = load_cell_file(cell_toml)
    he = cf.hand_eye
    if he is None:
        raise InputError(f"{cell_toml}: no [hand_eye] section (the calibration artefact)")
    job = artefact_job(cf, folder, cell_toml, name="hand-eye-artefact", mesh=he.mesh, targets=he.targets,
                       target_diameter=he.target_diameter, coded_size=he.coded_size, placement=he.placement, seed=he.seed)
    backend = backend or cf.cell.backend
    out.say(f"hand-eye: artefact {len(job.part.targets)} targets; planning {he.n_stations} stations")
    sp, cond, tried = plan_hand_eye_stations(job, he, cf.camera.sigma_px, out)
    joints = sp.joints
    rec = _record_folder(archive_root, cf.cell.name, "hand-eye")
    rec.append("created", kind="hand_eye", cell=cf.cell.name, cell_file=str(cell_toml), backend=backend)
    intr = job.intrinsics
    X0, Y0 = job.spec.flange_from_cam(), job.spec.base_from_part()
    occluder = Occluder(job.part.mesh)
    devices = open_devices(job, backend)
    truth = None
    if backend == "sim":
        truth = (devices.world.true_flange_from_cam.copy(), devices.world.true_base_from_part.copy())
    B, A, img_idx, tgt_idx, uvs, per_image = [], [], [], [], [], []
    try:
        for i, q in enumerate(joints):
            out.progress("hand-eye acquire", i / len(joints))
            img, bff = capture_at(devices, q, job.spec.cell)
            name = f"images/{i:04d}.png"
            _save_image(rec, name, img)
            approx = invert(X0) @ invert(bff) @ Y0
            tid, uv, pose = measure_image(img, job.part, intr, approx, occluder)
            ft_ok = len(tid) >= 8
            if ft_ok:
                try:
                    ft = faugeras_toscani(job.part.targets.xyz[tid], uv, intr.width, intr.height)
                    A_i = refine_pose_pnp(intr, ft.cam_from_part, job.part.targets.xyz[tid], uv)
                except CalibrationError as exc:
                    rec.append("note", text=f"{name}: {exc}")
                    ft_ok = False
            per_image.append({"image": name, "n_dots": int(len(tid)), "base_from_flange": bff,
                              "used": bool(ft_ok), "ft_rms_px": float(ft.rms_px) if ft_ok else None,
                              "cam_from_artefact": A_i if ft_ok else None})
            rec.append("station_done", image=name, n_dots=int(len(tid)), base_from_flange=bff)
            if not ft_ok:
                continue
            k = len(B)
            B.append(bff)
            A.append(A_i)
            img_idx.append(np.full(len(tid), k))
            tgt_idx.append(tid)
            uvs.append(uv)
        out.progress("hand-eye acquire", 1.0)
    finally:
        devices.close()
    if len(B) < 4:
        raise CalibrationError(f"hand-eye: only {len(B)} images measured the artefact (need 4); check the light and "
                               f"the artefact's placement in {cell_toml} [hand_eye] placement")
    B, A = np.array(B), np.array(A)
    img_idx, tgt_idx, uvs = np.concatenate(img_idx), np.concatenate(tgt_idx), np.concatenate(uvs)
    sols, failed = compare_methods(B, A)
    best = sols[0]
    res = refine_hand_eye(intr, B, img_idx, job.part.targets.xyz[tgt_idx], uvs, best.flange_from_cam,
                          best.base_from_target, HandEyeOptions(sigma_px=cf.camera.sigma_px))
    methods = []
    for s in sols:
        row = {"method": s.method, "flange_from_cam": s.flange_from_cam,
               "rms_translation_m": s.rms_translation_m, "rms_rotation_rad": s.rms_rotation_rad}
        if truth is not None:
            dt, dr = pose_error(s.flange_from_cam, truth[0])
            row |= {"error_translation_m": dt, "error_rotation_rad": dr}
        methods.append(row)
    date = utc_now()
    doc = {"kind": "hand_eye", "cell": cf.cell.name, "cell_file": str(cell_toml), "finished": date,
           "backend": backend, "images": per_image, "n_images_used": int(len(B)), "n_observations": int(len(uvs)),
           "methods": methods, "methods_failed": failed, "start_method": best.method,
           "planning": {"stations_part_from_cam": sp.part_from_cam, "joints": sp.joints, "facts": sp.facts,
                        "conditioning": cond.to_dict(), "networks_tried": tried},
           "flange_from_cam": res.flange_from_cam, "flange_from_cam_before": X0,
           "base_from_artefact": res.base_from_target, "covariance": res.cov,
           "sigma_translation_m": res.sigma_translation_m, "sigma_rotation_rad": res.sigma_rotation_rad,
           "sigma0_px": res.sigma0_px, "n_rejected": int(res.rejected.sum()), "dof": res.dof,
           "per_image_rms_px": res.per_image_rms_px, "refinement": res.history,
           "change_translation_m": pose_error(res.flange_from_cam, X0)[0],
           "change_rotation_rad": pose_error(res.flange_from_cam, X0)[1]}
    if truth is not None:
        dt, dr = pose_error(res.flange_from_cam, truth[0])
        doc["truth"] = {"flange_from_cam": truth[0], "error_translation_m": dt, "error_rotation_rad": dr,
                        "placement_error_translation_m": pose_error(res.base_from_target, truth[1])[0]}
    atomic_write_json(rec.file("hand_eye.json"), doc)
    write_flange_from_cam(cell_toml, res.flange_from_cam, date, record=rec.job_id)
    rec.append("cell_file_updated", flange_from_cam=res.flange_from_cam, date=date)
    rec.append("terminal", status="DONE", reason="")
    rec.write_manifest()
    summary = {"status": "ok", "record": rec.job_id, "folder": str(rec.path), "date": date,
               "flange_from_cam": res.flange_from_cam, "sigma_translation_m": res.sigma_translation_m,
               "sigma_rotation_rad": res.sigma_rotation_rad, "sigma0_px": res.sigma0_px,
               "methods": methods, "methods_failed": failed, "images": int(len(B)), "truth": doc.get("truth"),
               "planned_conditioning": cond.to_dict()}
    st, sr = np.linalg.norm(res.sigma_translation_m), np.rad2deg(np.linalg.norm(res.sigma_rotation_rad))
    out.say(f"hand-eye: {len(B)} images, sigma0 {res.sigma0_px:.3f} px; flange_from_cam +- {st * 1e3:.3f} mm, "
            f"{sr:.4f} deg; written to {cell_toml} ({date})")
    return summary


# --- reverification (VDI/VDE 2634 part 1) --------------------------------------------------------------------


def triangulate(intr: Intrinsics, cam_from_base: np.ndarray, uv: np.ndarray, start: np.ndarray,
                sigma_px: float, iterations: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Forward intersection of one point seen in ``cam_from_base: (m, 4, 4)`` at ``uv: (m, 2)``.

    Returns ``(point (3,), covariance (3, 3) a priori from sigma_px, residuals (m, 2) px)``.
    """
    P = np.asarray(start, dtype=float).copy()
    for _ in range(iterations):
        r, J = [], []
        for T, u in zip(cam_from_base, uv):
            p, Jp, _ = project_with_jacobians(intr, T, P[None])
            r.append(u - p[0])
            J.append(Jp[0])
        r, J = np.concatenate(r), np.concatenate(J)
        N = J.T @ J
        dP = np.linalg.solve(N, J.T @ r)
        P += dP
        if np.linalg.norm(dP) < 1e-10:
            break
    res = np.array([u - project(intr, T, P[None])[0] for T, u in zip(cam_from_base, uv)])
    return P, sigma_px**2 * np.linalg.inv(N), res


def _measure_position(cf: CellFile, folder: Path, cell_toml: Path, k: int, pose: Pose, rec: JobFolder, backend: str,
                      out) -> dict:
    from cell.devices import open_devices

    rv = cf.reverification
    job = artefact_job(cf, folder, cell_toml, name=f"scale-bar-{k}", mesh=rv.mesh, targets=rv.targets,
                       target_diameter=rv.target_diameter, coded_size=rv.coded_size, placement=pose, seed=rv.seed + k)
    index = job.part.targets.index()
    for key in (rv.a, rv.b):
        if key not in index:
            raise InputError(f"{cell_toml}: reverification target {key!r} is not in {rv.targets}")
    ia, ib = index[rv.a], index[rv.b]
    ends = np.zeros(len(job.part.targets), dtype=bool)
    ends[[ia, ib]] = True
    sp = plan_stations(job, rv.stations_per_position, min_rays=rv.stations_per_position,
                       max_tilt_rad=np.deg2rad(rv.max_tilt_deg), incidence_max_rad=np.deg2rad(rv.incidence_max_deg),
                       sigma_px=cf.camera.sigma_px, n_candidates=rv.n_candidates, seed=rv.seed + k, targets=ends)
    joints = sp.joints
    X, Y0 = job.spec.flange_from_cam(), job.spec.base_from_part()
    intr = job.intrinsics
    occluder = Occluder(job.part.mesh)
    seen = {ia: [], ib: []}
    devices = open_devices(job, backend, seed_offset=k)  # each position its own image noise
    try:
        for i, q in enumerate(joints):
            img, bff = capture_at(devices, q, job.spec.cell)
            name = f"images/p{k}_{i:02d}.png"
            _save_image(rec, name, img)
            tid, uv, pose_i = measure_image(img, job.part, intr, invert(X) @ invert(bff) @ Y0, occluder)
            for t, u in zip(tid, uv):
                if t in seen:
                    seen[t].append((invert(X) @ invert(bff), u, invert(bff @ X) @ np.eye(4), pose_i))
            rec.append("station_done", position=k, image=name, base_from_flange=bff, n_dots=int(len(tid)))
    finally:
        devices.close()
    pts, covs, rms = [], [], []
    for t in (ia, ib):
        if len(seen[t]) < 2:
            raise CalibrationError(f"reverification position {k}: target {job.part.targets.ids[t]} measured in "
                                   f"{len(seen[t])} image(s), 2 needed; check the bar's position and the light")
        C = np.array([s[0] for s in seen[t]])
        uv = np.array([s[1] for s in seen[t]])
        # start: the target seen through the first image's identified pose, in the base frame
        start = invert(C[0]) @ invert(seen[t][0][3]) @ np.r_[job.part.targets.xyz[t], 1.0]
        p, c, r = triangulate(intr, C, uv, start[:3], cf.camera.sigma_px)
        pts.append(p)
        covs.append(c)
        rms.append(float(np.sqrt(np.mean(np.sum(r**2, axis=1)))))
    d = pts[1] - pts[0]
    L = float(np.linalg.norm(d))
    u = d / L
    sigma_L = float(np.sqrt(u @ (covs[0] + covs[1]) @ u))
    L_cal = rv.length * cf.scale
    err = L - L_cal
    mpe = cf.mpe_m(L_cal)
    return {"position": k, "base_from_bar_nominal": Y0, "images": int(len(joints)), "a": pts[0], "b": pts[1],
            "length_m": L, "calibrated_length_m": L_cal, "error_m": err, "sigma_m": sigma_L, "mpe_m": mpe,
            "ray_rms_px": max(rms), "rays_consistent": bool(max(rms) <= RAY_RMS_LIMIT * cf.camera.sigma_px),
            "length_within_mpe": bool(abs(err) <= mpe),
            "pass": bool(abs(err) <= mpe and max(rms) <= RAY_RMS_LIMIT * cf.camera.sigma_px)}


#: A bar end whose rays miss each other by more than this many image sigmas (rms) fails its position,
#: whatever its length error: the geometry is inconsistent (a calibrated cell: 0.01-0.05 px rms; a
#: hand-eye 2 mm off: 7-13 px, though some of its lengths stay within the MPE by chance).
RAY_RMS_LIMIT = 5.0


def ask_operator(out, message: str) -> None:
    """Wait until the operator has done what ``message`` asks (Enter), or abort (``AbortRequested``).

    Through ``out.ask(message)`` when the output object offers it (a GUI, a test), else at the terminal.
    Without a terminal nobody can move the bar: an :class:`InputError` says so.
    """
    import sys

    ask = getattr(out, "ask", None)
    if ask is not None:
        answer = ask(message)
    elif sys.stdin is not None and sys.stdin.isatty():
        answer = input(f"{message} Press Enter when done (or type 'abort'): ")
    else:
        raise InputError(f"{message} -- this needs the operator at a terminal: run the reverification interactively")
    if str(answer or "").strip().lower() in ("abort", "a", "q", "quit", "no", "n"):
        raise AbortRequested(f"the operator aborted: {message}")


def run_reverification(cell_toml: Path, archive_root: Path, out, *, backend: str | None = None,
                       operator=None) -> dict:
    """Measure the scale bar in every position of ``[reverification]``; archive and return the result.

    On the simulated cell the bar is where ``positions`` puts it (the simulation places it). On a
    real cell a person moves it: before each position ``operator(message)`` (default
    :func:`ask_operator`) names the position and waits; the robot stands still meanwhile.
    """
    cell_toml = Path(cell_toml)
    cf, folder = load_cell_file(cell_toml)
    rv = cf.reverification
    if rv is None:
        raise InputError(f"{cell_toml}: no [reverification] section (the scale bar and its positions)")
    backend = backend or cf.cell.backend
    rec = _record_folder(archive_root, cf.cell.name, "reverification")
    rec.append("created", kind="reverification", cell=cf.cell.name, cell_file=str(cell_toml), backend=backend)
    rows = []
    if operator is None and backend != "sim":
        operator = lambda message: ask_operator(out, message)  # noqa: E731
    for k, pose in enumerate(rv.positions):
        out.progress("reverification", k / len(rv.positions))
        if operator is not None:
            xyz = ", ".join(f"{v:g}" for v in pose.xyz)
            rpy = ", ".join(f"{v:g}" for v in pose.rpy_deg)
            message = (f"Reverification position {k + 1} of {len(rv.positions)}: put the scale bar at "
                       f"xyz = [{xyz}] {cf.cell.units}, rpy = [{rpy}] deg (robot base frame, within a few cm).")
            rec.append("operator", position=k, text=message)
            try:
                operator(message)
            except AbortRequested as exc:
                rec.append("terminal", status="ABORTED", reason=str(exc))
                raise
        row = _measure_position(cf, folder, cell_toml, k, pose, rec, backend, out)
        rows.append(row)
        out.say(f"  position {k}: L = {row['length_m'] * 1e3:.4f} mm, E = {row['error_m'] * 1e6:+.1f} um "
                f"(MPE {row['mpe_m'] * 1e6:.1f} um, sigma {row['sigma_m'] * 1e6:.1f} um, rays {row['ray_rms_px']:.2f} px) "
                f"{'pass' if row['pass'] else 'FAIL'}")
    out.progress("reverification", 1.0)
    passed = all(r["pass"] for r in rows)
    worst = max(rows, key=lambda r: abs(r["error_m"]) / r["mpe_m"])
    date = utc_now()
    detail = (f"{sum(r['length_within_mpe'] for r in rows)} of {len(rows)} positions within E_MPE; worst position "
              f"{worst['position']}: E = {worst['error_m'] * 1e6:+.1f} um against {worst['mpe_m'] * 1e6:.1f} um")
    crossed = [r["position"] for r in rows if not r["rays_consistent"]]
    if crossed:
        detail += (f"; at position(s) {crossed} the rays to a bar end miss each other by more than {RAY_RMS_LIMIT:g} "
                   "sigma: the hand-eye (or the robot's kinematics) is off")
    if not passed:
        detail += "; the cell measures lengths wrongly: recalibrate the hand-eye (cell calibrate hand-eye) and repeat"
    doc = {"kind": "reverification", "standard": "VDI/VDE 2634 part 1 (length measurement error)",
           "cell": cf.cell.name, "cell_file": str(cell_toml), "finished": date, "backend": backend,
           "passed": passed, "detail": detail, "interval_days": rv.interval_days,
           "flange_from_cam": cf.flange_from_cam(), "flange_from_cam_date": cf.cell.flange_from_cam_date,
           "scale_bar": {"a": rv.a, "b": rv.b, "length_m": rv.length * cf.scale, "sigma_m": rv.sigma * cf.scale},
           "positions": rows, "max_abs_error_m": max(abs(r["error_m"]) for r in rows)}
    atomic_write_json(rec.file("reverification.json"), doc)
    rec.append("terminal", status="DONE", reason="" if passed else "failed: " + detail)
    rec.write_manifest()
    out.say(f"reverification {'PASSED' if passed else 'FAILED'}: {detail}")
    return {"status": "passed" if passed else "failed", "passed": passed, "record": rec.job_id,
            "folder": str(rec.path), "date": date, "detail": detail, "positions": rows,
            "max_abs_error_m": doc["max_abs_error_m"]}


def _parse_time(v) -> datetime:
    if isinstance(v, datetime):
        return v if v.tzinfo else v.replace(tzinfo=timezone.utc)
    if isinstance(v, (int, float)):
        return datetime.fromtimestamp(v, timezone.utc)
    d = datetime.fromisoformat(str(v))
    return d if d.tzinfo else d.replace(tzinfo=timezone.utc)


def calibration_status(archive_root: Path, cell_name_or_file, now) -> dict:
    """The cell's reverification status for an inspection report.

    ``cell_name_or_file``: the cell's name, or its cell file (then a reverification made with another
    hand-eye than the file's current one does not count). ``now``: datetime, ISO string or epoch seconds.
    Returns ``{"status": "verified"|"expired"|"failed"|"not verified", "last": record or None, "detail": str}``.
    """
    current_ffc = None
    name = str(cell_name_or_file)
    p = Path(str(cell_name_or_file))
    if p.suffix == ".toml" and p.is_file():
        cf, _ = load_cell_file(p)
        name, current_ffc = cf.cell.name, cf.flange_from_cam()
    root = Path(archive_root) / CAL_DIR
    recs = []
    if root.is_dir():
        for f in root.glob("*/reverification.json"):
            try:
                d = json.loads(f.read_text())
            except (OSError, ValueError):
                continue
            if d.get("cell") == name:
                recs.append((_parse_time(d["finished"]), f.parent.name, d))
    if not recs:
        return {"status": "not verified", "last": None, "detail": f"no reverification of cell {name!r} in {root}"}
    when, rid, d = max(recs, key=lambda r: r[0])
    last = {"record": rid, "date": d["finished"], "passed": d["passed"], "max_abs_error_m": d.get("max_abs_error_m"),
            "interval_days": d["interval_days"]}
    now_t = _parse_time(now)
    if current_ffc is not None:
        dt, dr = pose_error(current_ffc, np.asarray(d["flange_from_cam"], dtype=float))
        if dt > 1e-6 or dr > 1e-6:
            return {"status": "not verified", "last": last,
                    "detail": f"the hand-eye changed ({dt * 1e3:.3f} mm) after the last reverification {rid}: "
                              "run the reverification again"}
    if not d["passed"]:
        return {"status": "failed", "last": last, "detail": f"last reverification {rid} failed: {d['detail']}"}
    due = when + timedelta(days=float(d["interval_days"]))
    if now_t > due:
        return {"status": "expired", "last": last,
                "detail": f"last reverification {rid} passed but its interval of {d['interval_days']:g} days ended "
                          f"{due.isoformat(timespec='seconds')}"}
    return {"status": "verified", "last": last,
            "detail": f"reverification {rid} passed ({d['detail']}); due again {due.isoformat(timespec='seconds')}"}
