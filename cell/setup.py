"""Turn a loaded job into the objects of the packages below: planner options, robot, collision world."""
from __future__ import annotations

import numpy as np

from cell.jobspec import pose_matrix
from cell.loadedjob import LoadedJob
from planning.kinematics import BoxObstacle, CollisionWorld, RobotModel, ToolBox, load_robot
from planning.planner import PlannerOptions
from planning.stations import ViewingSphere
from planning.visibility import VisibilityOptions


#: a part too large to frame in one image within the depth of field: the stations look at regions of it, their
#: look-at point up to this fraction of the part's radius from its centre (the whole part is framed: 0.25)
REGION_OFFSET_FRACTION = 0.6


def viewing_sphere(job: LoadedJob) -> tuple[ViewingSphere, str | None]:
    """The stations' viewing sphere for a job, and a note when the part is too large to frame in one image.

    Sized so that the part fills the image (:meth:`ViewingSphere.for_part`), overridden by ``[planning]
    distance_min / distance_max``, and kept where every target is in the depth of field (``[camera] near / far``,
    half the part's radius inside them). A part that the image frames only beyond the depth of field (a panel
    wider than the field of view at ``far``) is planned from within it, the stations looking at regions of the
    part (their look-at offsets up to :data:`REGION_OFFSET_FRACTION` of its radius): said in the note. A range
    that is empty even so is an error naming the keys."""
    from dataclasses import replace

    from calibration.errors import JobSpecError

    s, p, c = job.spec, job.spec.planning, job.spec.camera
    k = s.scale
    r = float(job.part.radius)
    sphere = ViewingSphere.for_part(job.part, job.intrinsics)
    framed = sphere.distance_min_m
    overrides = {}
    if p.distance_min is not None:
        overrides["distance_min_m"] = p.distance_min * k
    if p.distance_max is not None:
        overrides["distance_max_m"] = p.distance_max * k
    sphere = replace(sphere, elevation_min_rad=np.deg2rad(p.elevation_min_deg),
                     elevation_max_rad=np.deg2rad(p.elevation_max_deg), **overrides)
    # the camera's distance to the part's centre must keep every target within the depth of field
    near, far = c.near * k, c.far * k
    lo, hi = max(sphere.distance_min_m, near + r * 0.5), min(sphere.distance_max_m, far - r * 0.5)
    note = None
    if lo > hi and p.distance_min is None:  # the framing distance, not the job, put the range beyond the depth of field
        lo = max(near + r * 0.5, r + 0.05)
        if lo <= hi:
            sphere = replace(sphere, max_offset_m=max(sphere.max_offset_m, REGION_OFFSET_FRACTION * r))
            note = (f"the part ({2 * r / k:.0f} {s.job.units} across) fits one image only from {framed / k:.0f} "
                    f"{s.job.units}, beyond the camera's depth of field ({c.near:g}-{c.far:g} {s.job.units}): the "
                    f"stations stand {lo / k:.0f}-{hi / k:.0f} {s.job.units} from its centre and look at regions of it")
    if lo > hi:
        raise JobSpecError(
            f"{job.path}: no camera distance keeps the part ({2 * r / k:.0f} {s.job.units} across) within the "
            f"camera's depth of field: the stations would stand {lo / k:.0f}-{hi / k:.0f} {s.job.units} from its "
            f"centre; widen [camera] near / far (now {c.near:g}-{c.far:g}) or [planning] distance_min / distance_max")
    return replace(sphere, distance_min_m=lo, distance_max_m=hi), note


def planner_options(job: LoadedJob) -> PlannerOptions:
    s, p, c = job.spec, job.spec.planning, job.spec.camera
    k = s.scale
    sphere, _ = viewing_sphere(job)
    near, far = c.near * k, c.far * k
    vis = VisibilityOptions(margin_px=p.margin_px, near_m=near, far_m=far,
                            incidence_max_rad=np.deg2rad(p.incidence_max_deg))
    return PlannerOptions(
        n_stations=p.n_stations if p.mode == "fixed" else p.max_stations,
        min_rays=p.min_rays,
        incidence_max_rad=float(np.deg2rad(p.incidence_max_deg)),
        criterion=p.criterion,
        sigma_px=c.sigma_px,
        # [planning] search_weights = "model": the search ranks networks with the detector model's sigma of each ray,
        # and they must be one block of linked images, no station alone linking a part (docs/decisions/0031: not yet
        # the default; on the planner's rays the rule also changes one-sigma plans that ADJUST links well); plan.json's
        # predicted covariance is the pre-analysis either way
        image_precision=image_precision(job) if search_weights(job) == "model" else None,
        link_targets=8 if search_weights(job) == "model" else 0,
        mode=p.mode,
        required_sigma_m=None if p.required_sigma is None else p.required_sigma * k,
        default_tolerance_m=s.report.tolerance * k,
        population=p.population,
        generations=p.generations,
        visibility=vis,
        sphere=sphere,
        n_candidates=p.n_candidates,
        lower_bound=p.lower_bound,
        allow_unmeasurable=p.unmeasurable == "report",
        scale_bars=job.scale_bars,  # the bars' ends get the stations they need after the search (planning.scalebar)
    )


def search_weights(job: LoadedJob) -> str:
    """How the search weighs each ray: ``[planning] search_weights`` (default one sigma, ``[camera] sigma_px``:
    docs/decisions/0031 says why the model is not yet the default)."""
    return job.spec.planning.search_weights or "sigma"


def camera_box_pose(size_m, flange_from_cam: np.ndarray | None) -> np.ndarray:
    """Where the camera's collision box (``[cell] camera_box``, its sides along the camera's x, y and optical axis)
    sits on the flange: around the camera as the hand-eye ``flange_from_cam`` places it.

    The box is centred on the optical axis through the projection centre and, along it, reaches from the flange
    (where the axis crosses the flange's face, z = 0) to the box's length: the body behind the centre and the lens
    in front of it. A centre farther from the flange than the box is long (a camera on an extension) gets the box
    centred on it. Without a hand-eye (None), the box stands on the flange axis, half its length along it."""
    size = np.asarray(size_m, dtype=float)
    box = np.eye(4)
    if flange_from_cam is None:
        box[2, 3] = size[2] / 2
        return box
    R, c = np.asarray(flange_from_cam, dtype=float)[:3, :3], np.asarray(flange_from_cam, dtype=float)[:3, 3]
    axis = R[:, 2]
    back = c[2] / axis[2] if axis[2] > 1e-6 else np.inf  # from the centre back along the axis to the flange face
    if not 0.0 <= back <= size[2]:
        back = size[2] / 2
    box[:3, :3] = R
    box[:3, 3] = c + (size[2] / 2 - back) * axis
    return box


def robot_model(job: LoadedJob) -> RobotModel:
    """The job's arm with its camera's collision box where the hand-eye puts the camera (:func:`camera_box_pose`;
    before decision 0061 the box stood on the flange axis whatever the hand-eye, the example's projection centre on
    its face)."""
    c = job.spec.cell
    k = job.spec.scale
    size = tuple(v * k for v in c.camera_box)
    hand_eye = job.spec.flange_from_cam() if c.flange_from_cam is not None else None
    return load_robot(c.robot, tool=ToolBox("camera", size, camera_box_pose(size, hand_eye)),
                      elbow_limit_rad=np.deg2rad(c.elbow_limit_deg))


def collision_world(job: LoadedJob, clearance_m: float = 0.005) -> CollisionWorld:
    c = job.spec.cell
    k = job.spec.scale
    obstacles = tuple(
        BoxObstacle(o.name, tuple(v * k for v in o.size), pose_matrix(o.pose, k)) for o in c.obstacles
    )
    return CollisionWorld(part_mesh=job.part.mesh, base_from_part=job.spec.base_from_part(), table_z=c.table_z * k,
                          obstacles=obstacles, clearance_m=clearance_m)


#: a part may touch the table or an obstacle by this much (its placement's own error, a locate's sigma) and pass
PLACEMENT_TOL_M = 0.5e-3


def part_placement_error(job: LoadedJob) -> str | None:
    """One line saying how the part, placed by ``[cell] base_from_part``, goes into the table or a fixed obstacle of
    the cell's collision world; None when it is clear of both (touching within :data:`PLACEMENT_TOL_M` is clear).

    Nothing else checks the part against the cell: the collision world pairs only the robot's bodies with it, so a
    part sunk into the table was planned, seen and reached through the table top (an outside check)."""
    import coal

    s, c = job.spec, job.spec.cell
    k, u = s.scale, s.job.units
    T = s.base_from_part()
    mesh = job.part.mesh
    v = np.asarray(mesh.vertices, dtype=float) @ T[:3, :3].T + T[:3, 3]
    table = c.table_z * k
    depth = table - float(v[:, 2].min())
    if depth > PLACEMENT_TOL_M:
        below = int(np.sum((job.part.targets.xyz @ T[:3, :3].T + T[:3, 3])[:, 2] < table))
        return (f"the part goes {depth / k:.4g} {u} into the table (its lowest point at z = {v[:, 2].min() / k:.4g} "
                f"{u}, the table top at [cell] table_z = {c.table_z:g}; {below} of {len(job.part.targets)} targets "
                "below it): correct [cell] base_from_part so that the part rests on the table")
    if not c.obstacles:
        return None
    from planning.kinematics import mesh_bvh

    bvh = mesh_bvh(mesh)
    part_tf = coal.Transform3s(T[:3, :3], T[:3, 3])
    for o in c.obstacles:
        B = pose_matrix(o.pose, k)
        half = 0.5 * np.asarray(o.size, dtype=float) * k
        inner = np.maximum(2 * (half - PLACEMENT_TOL_M), 1e-9)  # touching a face within the tolerance is clear
        res = coal.CollisionResult()
        coal.collide(bvh, part_tf, coal.Box(*inner), coal.Transform3s(B[:3, :3], B[:3, 3]), coal.CollisionRequest(),
                     res)
        local = np.abs((v - B[:3, 3]) @ B[:3, :3])  # the part's vertices in the box's frame
        inside = np.min(half - local, axis=1)  # > 0: that far inside the box
        if res.isCollision() or inside.max() > PLACEMENT_TOL_M:
            how = (f"up to {inside.max() / k:.4g} {u} inside it" if inside.max() > 0 else "its faces cross the box")
            return (f"the part intersects the cell's obstacle {o.name!r} ({how}): correct [cell] base_from_part (or "
                    "the obstacle's pose in [cell] obstacles)")
    return None


def image_precision(job):
    """The planner's image precision: the detector model (``[camera] observation_weights = "model"``), else None."""
    from planning.uncertainty import ImagePrecision

    s = job.spec
    if s.camera.observation_weights != "model":
        return None
    return ImagePrecision(np.asarray(job.part.targets.normals, dtype=float), job.part.target_diameter_m,
                          noise_scale=s.sim.noise if s.cell.backend == "sim" else 1.0)
