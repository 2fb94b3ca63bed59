"""Turn a loaded job into the objects of the packages below: planner options, robot, collision world."""
from __future__ import annotations

import numpy as np

from cell.jobspec import pose_matrix
from cell.loadedjob import LoadedJob
from planning.kinematics import BoxObstacle, CollisionWorld, RobotModel, ToolBox, load_robot
from planning.planner import PlannerOptions
from planning.stations import ViewingSphere
from planning.visibility import VisibilityOptions


def planner_options(job: LoadedJob) -> PlannerOptions:
    s, p, c = job.spec, job.spec.planning, job.spec.camera
    k = s.scale
    sphere = ViewingSphere.for_part(job.part, job.intrinsics)
    overrides = {}
    if p.distance_min is not None:
        overrides["distance_min_m"] = p.distance_min * k
    if p.distance_max is not None:
        overrides["distance_max_m"] = p.distance_max * k
    from dataclasses import replace

    sphere = replace(sphere, elevation_min_rad=np.deg2rad(p.elevation_min_deg),
                     elevation_max_rad=np.deg2rad(p.elevation_max_deg), **overrides)
    # the camera's distance to the part's centre must keep every target within the depth of field
    near, far = c.near * k, c.far * k
    sphere = replace(sphere, distance_min_m=max(sphere.distance_min_m, near + job.part.radius * 0.5),
                     distance_max_m=min(sphere.distance_max_m, far - job.part.radius * 0.5))
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


def robot_model(job: LoadedJob) -> RobotModel:
    c = job.spec.cell
    k = job.spec.scale
    size = tuple(v * k for v in c.camera_box)
    # the camera body: a box on the flange, centred half its length along the tool axis
    box = np.eye(4)
    box[2, 3] = size[2] / 2
    return load_robot(c.robot, tool=ToolBox("camera", size, box), elbow_limit_rad=np.deg2rad(c.elbow_limit_deg))


def collision_world(job: LoadedJob, clearance_m: float = 0.005) -> CollisionWorld:
    c = job.spec.cell
    k = job.spec.scale
    obstacles = tuple(
        BoxObstacle(o.name, tuple(v * k for v in o.size), pose_matrix(o.pose, k)) for o in c.obstacles
    )
    return CollisionWorld(part_mesh=job.part.mesh, base_from_part=job.spec.base_from_part(), table_z=c.table_z * k,
                          obstacles=obstacles, clearance_m=clearance_m)


def image_precision(job):
    """The planner's image precision: the detector model (``[camera] observation_weights = "model"``), else None."""
    from planning.uncertainty import ImagePrecision

    s = job.spec
    if s.camera.observation_weights != "model":
        return None
    return ImagePrecision(np.asarray(job.part.targets.normals, dtype=float), job.part.target_diameter_m,
                          noise_scale=s.sim.noise if s.cell.backend == "sim" else 1.0)
