"""What the cell's own calibration jobs share: an artefact as a job, stations planned by the
inspection planner, capture and measurement of one image, the record folder and the operator prompt."""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from calibration.camera import Intrinsics, invert
from calibration.errors import (AbortRequested, CalibrationError, DriverError, InputError, PlanningError,
                                ReachabilityError)
from calibration.targets import refine_pose_pnp
from cell.stages import imaging
from cell.cellcal.cellfile import CellFile, pose_from_matrix
from cell.record.jobfolder import JobFolder, atomic_write_bytes, new_job_id
from cell.jobspec import CellSection, JobSection, JobSpec, Pose, ReportSection, SimSection, pose_matrix, resolve
from cell.loadedjob import LoadedJob
from planning.part import load_part
from planning.planner import NetworkPlan, PlannerOptions, build_database, plan_network
from planning.stations import ViewingSphere
from planning.visibility import Occluder, VisibilityOptions, compute_visibility

CAL_DIR = "calibration"


def artefact_job(cf: CellFile, folder: Path, cell_path: Path, *, name: str, mesh: str, targets: str,
                 target_diameter: float, coded_size: float, placement: Pose, seed: int = 0) -> LoadedJob:
    """A :class:`LoadedJob` whose part is a calibration artefact placed at ``placement`` (base frame)."""
    c = cf.cell
    cell = CellSection(**c.model_dump(exclude={"name", "units", "base_from_part", "flange_from_cam_date",
                                               "flange_from_cam_record", "camera_lens"}), base_from_part=placement)
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
    intr = spec.intrinsics()
    if c.camera_lens is not None:  # the lens the hand-eye was calibrated with, not the data sheet's (decision 0055)
        intr = replace(intr, **c.camera_lens.model_dump(exclude={"cov"}))
    return LoadedJob(spec=spec, path=Path(cell_path), folder=folder, part=part, intrinsics=intr,
                     deviations=np.zeros((n, 3)), tolerance_m=np.full(n, k))


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
                  bands: tuple[tuple[float, float], ...] = ((0.0, 1.0),), roll_spread_rad: float = 0.0,
                  allow_unmeasurable: bool = False) -> StationPlan:
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
    branches, collision-checked moves, visiting order). ``allow_unmeasurable``: a counted target that no
    ``min_rays`` reachable candidates see is left out of the plan (its id in the plans'
    ``unmeasurable_target_ids``) instead of failing it.
    """
    from planning.execution import MotionLimits, validate_plan
    from planning.reachability import ReachabilityDB, reachability_mask
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
                              allow_unmeasurable=allow_unmeasurable,
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
        reaches = lambda Q: reachability_mask(robot, Y, X, Q, world).reachable  # noqa: E731
        P, visible, facts["roll_spread_deg"] = _spread_rolls(part, job.intrinsics, P, visible, vis_opts, roll_spread_rad,
                                                             min(min_rays, k), np.random.default_rng(seed), reaches)
    ids = [f"{job.part.name}-{b}-{sid}" for b, p in enumerate(plans) for sid in p.station_ids]
    ep = validate_plan(robot, P, Y, X, world, MotionLimits(
        joint_speed_rad_s=c.max_joint_speed_rad_s, joint_accel_rad_s2=c.max_joint_accel_rad_s2, settle_s=c.settle_s),
        ids=ids)
    facts["cycle_time_s"] = float(ep.cycle_time_s)
    return StationPlan(P[ep.order], ep.joints[ep.order], plans, visible[ep.order], facts)


def _spread_rolls(part, intr: Intrinsics, P: np.ndarray, visible: np.ndarray, vis_opts: VisibilityOptions,
                  spread: float, min_rays: int, rng: np.random.Generator,
                  reaches=None) -> tuple[np.ndarray, np.ndarray, float]:
    """Turn the stations ``P: (k, 4, 4)`` about their optical axes by rolls spread over +-``spread``.

    Returns the rolled stations, what each measures, and the spread used (degrees): halved (up to
    three times, then none) while a target measured ``min_rays`` times before would be measured fewer.
    ``reaches(Q) -> (k,) bool``: whether the robot reaches each rolled station without collision (IK and
    the cell's collision world). A station it does not reach at its roll takes half the roll, a quarter,
    then none (the planner's own station, which the robot reaches): a turn about the optical axis is a
    different flange pose, and a roll chosen after the planning must not leave the robot's reach.
    """
    k = len(P)
    order = rng.permutation(k)
    need = np.minimum(visible.sum(axis=0), min_rays)
    for _ in range(4):
        roll = spread * np.linspace(-1.0, 1.0, k)[order]
        Q = _rolled(P, roll)
        if reaches is not None:
            for f in (0.5, 0.25, 0.0):
                bad = ~np.asarray(reaches(Q), dtype=bool)
                if not bad.any():
                    break
                roll = np.where(bad, roll * f, roll)
                Q = _rolled(P, roll)
        vis = compute_visibility(part, intr, Q, vis_opts)
        if np.all(vis.sum(axis=0) >= need):
            return Q, vis, float(np.rad2deg(spread))
        spread *= 0.5
    return P, visible, 0.0


def _rolled(P: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``P: (k, 4, 4)`` turned about each camera's optical axis (its z) by ``roll: (k,)`` radians."""
    c, s = np.cos(roll), np.sin(roll)
    Rz = np.zeros((len(P), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    Q = P.copy()
    Q[:, :3, :3] = P[:, :3, :3] @ Rz
    return Q


def _seen_matrix(plan: NetworkPlan) -> np.ndarray:
    """(k, n) bool: which target each station of ``plan`` measures (from its exact ``seen_by``)."""
    index = {sid: i for i, sid in enumerate(plan.station_ids)}
    out = np.zeros((len(plan.station_ids), len(plan.target_ids)), dtype=bool)
    for j, seen in enumerate(plan.seen_by):
        out[[index[sid] for sid in seen], j] = True
    return out


def measure_image(img: np.ndarray, part, intr: Intrinsics, cam_from_part_approx: np.ndarray,
                  occluder: Occluder) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Dots measured in one image: ``(target index (k,), uv (k, 2) eccentricity-corrected, cam_from_part used,
    the eccentricity taken off (k, 2) px)``.

    :func:`cell.stages.imaging.measure_image` from the approximate pose; with six dots or more the pose is
    refined by PnP on them and the dots are named and measured again from it.
    """
    m, _ = imaging.measure_image(img, part, intr, cam_from_part_approx, occluder)
    if len(m.target) >= 6:
        pose = refine_pose_pnp(intr, m.cam_from_part, part.targets.xyz[m.target], m.uv)
        m, _ = imaging.measure_image(img, part, intr, pose, occluder)
    ecc = m.eccentricity_px if m.eccentricity_px is not None else np.zeros((len(m.target), 2))
    return m.target, m.uv, m.cam_from_part, np.asarray(ecc, dtype=float).reshape(-1, 2)


def centres_through_lens(lens: Intrinsics, cam_from_target: np.ndarray, obs_image: np.ndarray, xyz: np.ndarray,
                         normals: np.ndarray, radius_m: float, uv: np.ndarray, applied: np.ndarray) -> np.ndarray:
    """Measured centres ``uv (q, 2)`` with the eccentricity MEASURE took off (``applied``: the data sheet's pinhole
    lens) given back and the eccentricity through ``lens`` at the poses ``cam_from_target (m, 4, 4)`` taken off
    (:func:`cell.stages.lens.lens_eccentricity`: a distorting lens moves a dot's centre further, by its curvature
    over the dot; decision 0057). ``obs_image (q,)`` indexes the poses; ``xyz, normals (q, 3)`` each observation's."""
    from cell.stages.lens import lens_eccentricity

    out = np.asarray(uv, dtype=float) + np.asarray(applied, dtype=float)
    for i in np.unique(obs_image):
        k = np.flatnonzero(obs_image == i)
        out[k] -= lens_eccentricity(lens, cam_from_target[i], xyz[k], normals[k], radius_m)
    return out


def capture_at(devices, q: np.ndarray, c, exposure_s: float = 0.002,
               frame_timeout_s: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Move to joints ``q``, wait until the arm has settled, take a triggered exposure (as ACQUIRE does:
    :mod:`cell.stages.exposure`, a late / repeated / missing frame retaken up to ``c.retakes`` times);
    returns ``(image, base_from_flange measured)``."""
    from cell.stages.acquire import SIM_HOLD_S
    from cell.stages.exposure import ExposureTaker, FrameFault, wait_settled

    devices.robot.move_joints(q, c.max_joint_speed_rad_s, c.max_joint_accel_rad_s2)
    taker = getattr(devices, "exposure_taker", None)
    if taker is None:  # one per session, so that no frame is used twice
        taker = devices.exposure_taker = ExposureTaker(
            devices.robot, devices.camera, devices.light, exposure_s=exposure_s, frame_timeout_s=frame_timeout_s,
            light_by_line=devices.light is not None and c.light_input is not None)
    hold_s = c.settle_s if c.backend != "sim" else min(c.settle_s, SIM_HOLD_S)
    for attempt in range(1, c.retakes + 2):
        try:
            st, host_s, peak = wait_settled(devices.robot, speed_tol_rad_s=c.settle_speed_rad_s, hold_s=hold_s,
                                            timeout_s=c.settle_timeout_s)
        except DriverError as exc:
            raise CalibrationError(f"robot: {exc}") from None
        try:
            frame, _ = taker.take("", attempt, st, host_s, peak, hold_s)
            return frame.image, np.asarray(st.base_from_flange, dtype=float)
        except FrameFault:
            if attempt > c.retakes:
                raise


def record_folder(archive_root: Path, cell_name: str, kind: str) -> JobFolder:
    root = Path(archive_root) / CAL_DIR
    root.mkdir(parents=True, exist_ok=True)
    rid = new_job_id(f"{cell_name}-{kind}")
    k = 1
    while (root / rid).exists():
        k += 1
        rid = f"{new_job_id(f'{cell_name}-{kind}')}-{k}"
    (root / rid).mkdir()
    return JobFolder(root / rid)


def save_image(folder: JobFolder, name: str, img: np.ndarray) -> None:
    ok, png = cv2.imencode(".png", img)
    if not ok:
        raise CalibrationError(f"{name}: could not encode the image")
    atomic_write_bytes(folder.file(name), png.tobytes())


# --- the hand-eye job -----------------------------------------------------------------------------------------


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
