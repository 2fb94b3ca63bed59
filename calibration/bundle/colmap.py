"""pycolmap's side: our camera model <-> COLMAP's parameters, and the Ceres solve of the network.

COLMAP's pixel origin is the top-left pixel's corner, ours its centre: ``uv_colmap = uv + 0.5``
(also for the principal point).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from calibration.bundle.config import CAMERA_MODELS, COLMAP_MODELS, BundleConfig, BundleOptions
from calibration.bundle.normal import _State
from calibration.camera import Intrinsics
from calibration.errors import CalibrationError

_PIXEL_OFFSET = 0.5  # COLMAP pixel origin (corner) minus ours (centre)


def _to_colmap_params(intr: Intrinsics, model: str) -> list[float]:
    f = 0.5 * (intr.fx_px + intr.fy_px)
    if model in ("SIMPLE_RADIAL", "RADIAL") and (intr.p1 or intr.p2 or intr.k3 or abs(intr.fx_px - intr.fy_px) > 1e-9 * f):
        raise CalibrationError(
            f"bundle: camera model {model} has one focal length and radial terms only; "
            f"the intrinsics have fx != fy or tangential/k3 terms: use OPENCV"
        )
    if intr.k3 and "k3" not in CAMERA_MODELS[model]:
        raise CalibrationError(f"bundle: camera model {model} has no k3; use OPENCV_K3 or set k3 = 0")
    vals = {"fx": intr.fx_px, "fy": intr.fy_px, "f": f, "cx": intr.cx_px + _PIXEL_OFFSET,
            "cy": intr.cy_px + _PIXEL_OFFSET, "k1": intr.k1, "k2": intr.k2, "p1": intr.p1, "p2": intr.p2, "k3": intr.k3}
    if model == "PINHOLE" and intr.has_distortion:
        raise CalibrationError("bundle: the PINHOLE model has no distortion; choose a model with distortion terms")
    return [float(vals[p]) for p in CAMERA_MODELS[model]] + [0.0] * COLMAP_MODELS.get(model, (model, 0))[1]


def _from_colmap_params(params: np.ndarray, model: str, base: Intrinsics) -> Intrinsics:
    d = dict(zip(CAMERA_MODELS[model], (float(v) for v in params)))  # COLMAP's extra (held zero) terms dropped
    if "f" in d:
        d["fx"] = d["fy"] = d.pop("f")
    d["cx"] -= _PIXEL_OFFSET
    d["cy"] -= _PIXEL_OFFSET
    return replace(base, fx_px=d["fx"], fy_px=d["fy"], cx_px=d["cx"], cy_px=d["cy"],
                   k1=d.get("k1", 0.0), k2=d.get("k2", 0.0), p1=d.get("p1", 0.0), p2=d.get("p2", 0.0), k3=d.get("k3", 0.0))


def _pycolmap_solve(state: _State, obs_image, obs_target, obs_uv, active_pts, config: BundleConfig,
                    options: BundleOptions) -> tuple[_State, bool, str]:
    import pycolmap  # here, not at the top: the Gauss-Newton path never needs it (~0.15 s of a job's start)

    m = len(state.poses)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, COLMAP_MODELS.get(config.camera_model, (config.camera_model, 0))[0],
                                                 state.intr.fx_px, state.intr.width, state.intr.height)
    cam.params = _to_colmap_params(state.intr, config.camera_model)
    rec.add_camera_with_trivial_rig(cam)
    order = np.lexsort((obs_target, obs_image))
    img_sorted = obs_image[order]
    starts = np.searchsorted(img_sorted, np.arange(m + 1))
    p2d_idx = np.empty(len(order), dtype=int)
    for j in range(m):
        sel = order[starts[j] : starts[j + 1]]
        p2d_idx[sel] = np.arange(len(sel))
        img = pycolmap.Image(name=f"{j:05d}", keypoints=obs_uv[sel] + _PIXEL_OFFSET, camera_id=1, image_id=j + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(state.poses[j][:3, :]))
    by_target = np.argsort(obs_target, kind="stable")
    tstarts = np.searchsorted(obs_target[by_target], np.arange(len(state.points) + 1))
    pid = {}
    for i in np.flatnonzero(active_pts):
        sel = by_target[tstarts[i] : tstarts[i + 1]]
        track = pycolmap.Track()
        track.add_elements([pycolmap.TrackElement(int(a) + 1, int(b)) for a, b in zip(obs_image[sel], p2d_idx[sel])])
        pid[i] = rec.add_point3D(state.points[i], track)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.print_summary = False
    opts.refine_focal_length = config.refine_focal_length
    opts.refine_principal_point = config.refine_principal_point
    # a model with held-zero COLMAP terms keeps its distortion here; the full Gauss-Newton refines it
    opts.refine_extra_params = config.refine_distortion and config.camera_model not in COLMAP_MODELS
    opts.ceres.solver_options.max_num_iterations = options.max_iterations
    opts.ceres.solver_options.num_threads = options.num_threads
    opts.ceres.solver_options.function_tolerance = 1e-12
    opts.ceres.solver_options.gradient_tolerance = 1e-12
    opts.ceres.solver_options.parameter_tolerance = 1e-10
    cfg = pycolmap.BundleAdjustmentConfig()
    for j in range(m):
        cfg.add_image(j + 1)
    cfg.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    adjuster = pycolmap.create_default_bundle_adjuster(opts, cfg, rec)
    summary = adjuster.solve()
    pts = state.points.copy()
    for i, p in pid.items():
        pts[i] = rec.point3D(p).xyz
    poses = state.poses.copy()
    for j in range(m):
        poses[j, :3, :] = rec.image(j + 1).cam_from_world().matrix()
    intr = _from_colmap_params(rec.camera(1).params, config.camera_model, state.intr)
    return _State(intr, poses, pts), bool(summary.is_solution_usable()), summary.brief_report()
