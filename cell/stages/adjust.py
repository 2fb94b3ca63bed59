"""ADJUST: the rigorous bundle adjustment, initialised from the Faugeras-Toscani results."""
from __future__ import annotations

import io
import json
import time

import numpy as np

from calibration.bundle import BundleConfig, BundleOptions, ScaleBar, bundle_adjust
from calibration.camera import Intrinsics
from calibration.detector_model import load_model, observation_covariances, observation_sigmas
from calibration.errors import CalibrationError
from calibration.plausibility import check_adjustment
from calibration.weights import INCIDENCE_EDGES_DEG, group_labels, incidence_angles, incidence_groups, mean_variance
from cell.record.jobfolder import atomic_write_bytes, atomic_write_json


def observation_arrays(job, obs_doc: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    index = job.part.targets.index()
    img, tgt, uv = [], [], []
    for k, o in enumerate(obs_doc["images"]):
        for tid, p in zip(o["ids"], o["uv"]):
            img.append(k)
            tgt.append(index[tid])
            uv.append(p)
    return np.asarray(img, dtype=int), np.asarray(tgt, dtype=int), np.asarray(uv, dtype=float).reshape(-1, 2)


def background_bounds(obs_doc: dict) -> np.ndarray | None:
    """The detector's bound on each observation's error from a background that is not a plane, ``(q, 2, 2)``
    px^2 in the order of :func:`observation_arrays`; None when observations.json has none (measured before)."""
    if not obs_doc["images"] or any(o.get("bg_cov_px2") is None for o in obs_doc["images"]):
        return None
    return np.concatenate([np.asarray(o["bg_cov_px2"], dtype=float).reshape(-1, 2, 2) for o in obs_doc["images"]])


def initial_intrinsics(job, cal_doc: dict) -> Intrinsics:
    """Median of the per-image Faugeras-Toscani interior orientations (robust to a weak image)."""
    nominal = job.intrinsics
    if not job.spec.camera.self_calibrate:
        return nominal
    ft = [[r["alpha_u"], r["alpha_v"], r["u0"], r["v0"]] for r in cal_doc["images"] if "alpha_u" in r]
    if not ft:  # every image refused by Faugeras-Toscani (calibration.json says so): the nominal lens
        return nominal
    a = np.median(ft, axis=0)
    # the linear method has no distortion and little focal accuracy per image: keep it only if plausible
    if abs(a[0] / nominal.fx_px - 1) > 0.1 or abs(a[2] - nominal.cx_px) > 0.1 * nominal.width:
        return nominal
    f = 0.5 * (a[0] + a[1])
    return Intrinsics(f, f, a[2], a[3], nominal.width, nominal.height, k1=nominal.k1, k2=nominal.k2,
                      pixel_size_m=nominal.pixel_size_m)


def bundle_config(job) -> BundleConfig:
    """What the job's adjustment estimates (self-calibration) and its datum (scale bar, else free)."""
    scale_bars = ()
    if job.scale_bar is not None:
        a, b, length, sigma = job.scale_bar
        scale_bars = (ScaleBar(a, b, length, max(sigma, 1e-7)),)
    sc = job.spec.camera.self_calibrate
    return BundleConfig(camera_model="RADIAL" if sc else "PINHOLE", refine_focal_length=sc,
                        refine_principal_point=sc, refine_distortion=sc, scale_bars=scale_bars)


def max_rejections(n_obs: int) -> int:
    """How many observations data snooping may reject: partly occluded dots are blunders too, so up to
    10 % (many per re-adjustment since issue 21, so the limit no longer bounds the time; 5 % before).
    A network that needs more is broken: bundle.json's ``snooping`` then says how many still fail."""
    return max(20, n_obs // 10)


def run_bundle(ctx) -> dict:
    job = ctx.job
    obs = json.loads(ctx.folder.file("observations.json").read_text())
    cal = json.loads(ctx.folder.file("calibration.json").read_text())
    obs_image, obs_target, obs_uv = observation_arrays(job, obs)
    poses0 = np.array([r["cam_from_part"] for r in cal["images"]], dtype=float)
    intr0 = initial_intrinsics(job, cal)
    config = bundle_config(job)
    options = BundleOptions(sigma_px=job.spec.camera.sigma_px, max_rejections=max_rejections(len(obs_uv)))
    targets = job.part.targets
    groups = None
    obs_sigma = model_sigma = None
    weights = job.spec.camera.observation_weights
    if weights == "incidence":  # from the Faugeras-Toscani poses: degrees suffice
        angles = incidence_angles(targets.xyz, targets.normals, poses0, obs_image, obs_target)
        groups = incidence_groups(angles, INCIDENCE_EDGES_DEG)
    if weights == "model":  # the detector's precision by incidence and dot size; the variance factor scales it
        # (no per-class variance components on top: with issue 21's batch snooping they ran away on generated parts,
        # a face-on class estimated at 0.11 px and 280 rejections; the model alone: 10 rejections, honest sigma)
        obs_sigma = observation_sigmas(targets.xyz, targets.normals, poses0, obs_image, obs_target, intr0.fx_px,
                                       job.part.target_diameter_m,
                                       noise_scale=job.spec.sim.noise if ctx.backend == "sim" else 1.0)
        obs_sigma = np.maximum(obs_sigma, 1e-4)
        # a dot next to an edge or a step of the shading: the detector's background bound, its measured share
        # (docs/decisions/0023); the covariance is then 2x2 per observation
        bg = background_bounds(obs)
        if bg is not None and np.any(bg):
            model_sigma, obs_sigma = obs_sigma, observation_covariances(obs_sigma, bg)
    t0 = time.perf_counter()
    res = bundle_adjust(obs_image, obs_target, obs_uv, intr0, poses0, targets.xyz, options, config,
                        obs_sigma_px=obs_sigma, obs_group=groups)
    dt = time.perf_counter() - t0
    if model_sigma is not None:
        # sigma0 of an observation of the model's rms sigma: a few dots with large background bounds (near zero
        # weight) would otherwise dominate the rms a priori sigma the bundle refers sigma0 to
        used = ~res.rejected
        factor = res.sigma0_px**2 / mean_variance(res.obs_sigma_px[used])
        res.sigma0_px = float(np.sqrt(factor * np.mean(model_sigma[used] ** 2)))
    if not res.converged:
        raise CalibrationError(f"bundle adjustment did not converge: {res.summary}")
    check_adjustment(res.sigma0_px, res.intrinsics, job.intrinsics)  # a converged nonsense is a failure
    ids = job.part.targets.ids
    n_img = np.bincount(obs_target[~res.rejected], minlength=len(ids))
    rejected = [{"image": obs["images"][int(i)]["image"], "target": ids[int(t)], "residual_px": r}
                for i, t, r, bad in zip(obs_image, obs_target, res.residuals, res.rejected) if bad]
    axes, dirs = res.error_ellipsoids()
    # keep the full covariance for the report's alignment (exact propagation)
    buf = io.BytesIO()
    np.savez_compressed(buf, D=res.covariance.D, U=res.covariance.U, C=res.covariance.C)
    atomic_write_bytes(ctx.folder.file("bundle_covariance.npz"), buf.getvalue())
    return {
        "datum": res.datum,
        "sigma0_px": res.sigma0_px,
        "observation_weights": _weights_doc(job, res, groups, model_sigma),
        "dof": res.dof,
        "converged": res.converged,
        "summary": res.summary,
        "time_s": dt,
        "timings": res.timings,
        "n_observations": int(len(obs_uv)),
        "n_rejected": int(res.rejected.sum()),
        "rejected": rejected,
        "snooping": res.snooping | {"suspect_targets": [ids[int(t)] for t in res.snooping["suspect_targets"]],
                                    "protected": [p.replace(f"scale bar {a}-{b} ", f"scale bar {ids[a]}-{ids[b]} ")
                                                  for p in res.snooping["protected"]
                                                  for a, b in [job.scale_bar[:2] if job.scale_bar else (-1, -1)]]},
        "intrinsics": res.intrinsics.to_dict(),
        "intrinsics_refined": list(res.intrinsics_names),
        "intrinsics_sigma": np.sqrt(np.diag(res.intrinsics_cov)).tolist() if len(res.intrinsics_names) else [],
        "images": [{"image": o["image"], "station": o["station"], "cam_from_part": T}
                   for o, T in zip(obs["images"], res.cam_from_part)],
        "residuals_px": res.residuals,
        "targets": [{"id": tid, "xyz": p, "cov": c, "n_images": int(k), "ellipsoid_axes_m": ax,
                     "ellipsoid_dirs": d} for tid, p, c, k, ax, d in zip(ids, res.points, res.cov, n_img, axes, dirs)],
    }


def _weights_doc(job, res, groups, model_sigma=None) -> dict:
    """The a priori image sigmas the adjustment used: one per incidence class (estimated) or one for all.

    ``model_sigma: (q,)`` the detector model's sigmas when the bundle took 2x2 covariances (model plus the
    detector's background bounds): the figures and the variance factor refer to them."""
    vc = res.variance_components
    if job.spec.camera.observation_weights == "model":
        s = res.obs_sigma_px if model_sigma is None else model_sigma
        used = s[~res.rejected] if s is not None else np.array([np.nan])
        n_bg = 0
        if model_sigma is not None:
            C = res.obs_sigma_px
            n_bg = int(np.count_nonzero(np.abs(C - model_sigma[:, None, None] ** 2 * np.eye(2)).max(axis=(1, 2)) > 0))
        return {"method": "model", "detector_model": load_model().to_dict(),
                "observations_with_background_bound": n_bg,
                "a_priori_sigma_px": {"median": float(np.median(used)), "p90": float(np.quantile(used, 0.9)),
                                      "max": float(np.max(used))},
                "variance_factor": float((res.sigma0_px / np.sqrt(np.mean(used**2))) ** 2)}
    if groups is None or vc is None:
        return {"method": "equal", "sigma_px": job.spec.camera.sigma_px}
    edges = (0.0,) + INCIDENCE_EDGES_DEG + (90.0,)
    n_all = np.bincount(groups, minlength=len(edges) - 1)
    out = []
    for g, name in enumerate(group_labels(INCIDENCE_EDGES_DEG)):
        est = g < len(vc.sigma_px) and bool(vc.estimated[g])
        out.append({"name": name, "incidence_deg": [edges[g], edges[g + 1]], "n_observations": int(n_all[g]),
                    "redundancy": float(vc.redundancy[g]) if g < len(vc.redundancy) else 0.0,
                    "sigma_px": float(vc.sigma_px[g]) if n_all[g] else None, "estimated": est})
    # one image sigma for the whole network: the groups' variances weighted by their redundancy
    r = np.sum(vc.redundancy)
    pooled = float(np.sqrt(np.sum(vc.redundancy * vc.sigma_px**2) / r)) if r > 0 else None
    return {"method": job.spec.camera.observation_weights, "a_priori_sigma_px": job.spec.camera.sigma_px,
            "groups": out, "pooled_sigma_px": pooled, "iterations": vc.iterations, "converged": vc.converged}


def run(ctx) -> None:
    """Rigorous bundle adjustment from the Faugeras-Toscani start, with the job's datum."""
    doc = run_bundle(ctx)
    atomic_write_json(ctx.folder.file("bundle.json"), doc)
    ctx.say(f"  sigma0 {doc['sigma0_px']:.3f} px, {doc['n_rejected']} observation(s) rejected, "
            f"datum {doc['datum']}, {doc['time_s']:.2f} s")
    sn = doc["snooping"]
    if not sn["complete"]:
        ctx.log.log("warning", f"data snooping stopped early: {sn['stopped']}")
        ctx.say(f"  WARNING data snooping stopped early: {sn['stopped']}")
    if sn["suspect_targets"]:
        ctx.say(f"  WARNING targets that lost half of their observations (suspect): {', '.join(sn['suspect_targets'])}")
    if doc["observation_weights"]["method"] == "model":
        w = doc["observation_weights"]
        ctx.say(f"  image sigma from the detector model: median {w['a_priori_sigma_px']['median']:.4f} px, "
                f"max {w['a_priori_sigma_px']['max']:.3f} px; variance factor {w['variance_factor']:.2f}; "
                f"{w['observations_with_background_bound']} observation(s) next to an edge (background bound)")
    if doc["observation_weights"]["method"] == "incidence":
        ctx.say("  image sigma by incidence (variance components): " + ", ".join(
            f"{g['name']} {g['sigma_px']:.3f} px" + ("" if g["estimated"] else " (common)")
            for g in doc["observation_weights"]["groups"] if g["n_observations"]))
