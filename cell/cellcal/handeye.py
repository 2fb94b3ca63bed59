"""The hand-eye job (``cell calibrate hand-eye CELL.toml``): stations around the calibration artefact
chosen for a well-conditioned hand-eye, images, exterior orientations, AX = XB, the joint refinement."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.camera import invert
from calibration.errors import CalibrationError, InputError, PlanningError
from calibration.faugeras_toscani import faugeras_toscani
from calibration.handeye import (HandEyeConditioning, HandEyeOptions, compare_methods, hand_eye_conditioning,
                                 hand_eye_information, pose_error, refine_hand_eye, refine_with_lens)
from calibration.targets import refine_pose_pnp
from cell.cellcal.common import (StationPlan, artefact_job, capture_at, centres_through_lens, measure_image,
                                 plan_stations, record_folder, save_image)
from cell.cellcal.cellfile import load_cell_file, write_flange_from_cam
from cell.record.jobfolder import atomic_write_json, utc_now
from cell.loadedjob import LoadedJob
from planning.visibility import Occluder


#: the lens terms the hand-eye estimates with X and Y (the artefact seen from many stations determines them all)
HAND_EYE_LENS_TERMS = ("f", "cx", "cy", "k1", "k2", "k3", "p1", "p2")
#: sigma0 beyond this many times the camera's sigma_px: the hand-eye is not written (the model does not fit)
HAND_EYE_MAX_VARIANCE_RATIO = 3.0


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
    rec = record_folder(archive_root, cf.cell.name, "hand-eye")
    rec.append("created", kind="hand_eye", cell=cf.cell.name, cell_file=str(cell_toml), backend=backend)
    intr = job.intrinsics
    X0, Y0 = job.spec.flange_from_cam(), job.spec.base_from_part()
    occluder = Occluder(job.part.mesh)
    devices = open_devices(job, backend)
    truth = None
    if backend == "sim":
        truth = (devices.world.true_flange_from_cam.copy(), devices.world.true_base_from_part.copy())
    B, A, img_idx, tgt_idx, uvs, eccs, per_image = [], [], [], [], [], [], []
    try:
        for i, q in enumerate(joints):
            out.progress("hand-eye acquire", i / len(joints))
            img, bff = capture_at(devices, q, job.spec.cell)
            name = f"images/{i:04d}.png"
            save_image(rec, name, img)
            approx = invert(X0) @ invert(bff) @ Y0
            tid, uv, pose, ecc = measure_image(img, job.part, intr, approx, occluder)
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
            eccs.append(ecc)
        out.progress("hand-eye acquire", 1.0)
    finally:
        devices.close()
    if len(B) < 4:
        raise CalibrationError(f"hand-eye: only {len(B)} images measured the artefact (need 4); check the light and "
                               f"the artefact's placement in {cell_toml} [hand_eye] placement")
    B, A = np.array(B), np.array(A)
    img_idx, tgt_idx, uvs, eccs = (np.concatenate(img_idx), np.concatenate(tgt_idx), np.concatenate(uvs),
                                   np.concatenate(eccs))
    sols, failed = compare_methods(B, A)
    best = sols[0]
    res = refine_hand_eye(intr, B, img_idx, job.part.targets.xyz[tgt_idx], uvs, best.flange_from_cam,
                          best.base_from_target, HandEyeOptions(sigma_px=cf.camera.sigma_px))
    # the lens with them: held at the data sheet's, X absorbs its principal distance and distortion (decision 0055)
    ok = ~res.rejected
    fit = refine_with_lens(intr, B, img_idx[ok], job.part.targets.xyz[tgt_idx[ok]], uvs[ok], res.flange_from_cam,
                           res.base_from_target, HAND_EYE_LENS_TERMS)
    # the centres through the lens found: MEASURE took off each dot's eccentricity for the data sheet's pinhole lens,
    # and a distorting lens moves a dot's centre further, by its curvature over the dot (decision 0057); once more
    # with the centres MEASURE would have given through this lens
    t = job.part.targets
    C = np.array([invert(fit.flange_from_cam) @ invert(b) @ fit.base_from_target for b in B])
    uvs_lens = centres_through_lens(fit.lens, C, img_idx, t.xyz[tgt_idx], t.normals[tgt_idx],
                                    job.part.target_diameter_m / 2, uvs, eccs)
    relensed_px = float(np.sqrt(np.mean(np.sum((uvs_lens - uvs) ** 2, axis=1))))
    fit = refine_with_lens(intr, B, img_idx[ok], job.part.targets.xyz[tgt_idx[ok]], uvs_lens[ok], fit.flange_from_cam,
                           fit.base_from_target, HAND_EYE_LENS_TERMS)
    from cell.cellcal.placement import lens_doc

    lens = lens_doc(intr, fit)
    cov_x = fit.cov[:6, :6]
    R = fit.flange_from_cam[:3, :3]
    sig_t = np.sqrt(np.clip(np.diag(R @ cov_x[3:, 3:] @ R.T), 0, None))
    sig_r = np.sqrt(np.clip(np.diag(R @ cov_x[:3, :3] @ R.T), 0, None))
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
           "flange_from_cam": fit.flange_from_cam, "flange_from_cam_before": X0,
           "base_from_artefact": fit.base_from_target, "covariance": fit.cov[:12, :12],
           "covariance_with_lens": fit.cov, "lens": lens,
           "sigma_translation_m": sig_t, "sigma_rotation_rad": sig_r,
           "sigma0_px": fit.sigma0_px, "sigma0_px_nominal_lens": res.sigma0_px,
           "centres_through_lens_rms_px": relensed_px,
           "n_rejected": int(res.rejected.sum()), "dof": fit.dof,
           "per_image_rms_px": res.per_image_rms_px, "refinement": res.history,
           "change_translation_m": pose_error(fit.flange_from_cam, X0)[0],
           "change_rotation_rad": pose_error(fit.flange_from_cam, X0)[1]}
    if truth is not None:
        dt, dr = pose_error(fit.flange_from_cam, truth[0])
        doc["truth"] = {"flange_from_cam": truth[0], "error_translation_m": dt, "error_rotation_rad": dr,
                        "placement_error_translation_m": pose_error(fit.base_from_target, truth[1])[0]}
    out.say(f"hand-eye: lens estimated with it: principal distance {lens['principal_distance_mm']:.4f} "
            f"+- {lens['principal_distance_sigma_mm']:.4f} mm (the cell file's {lens['nominal_principal_distance_mm']:.4f}), "
            f"principal point {lens['principal_point_offset_px'][0]:+.1f}, {lens['principal_point_offset_px'][1]:+.1f} px "
            f"off the file's, k1 {lens['k1']:+.4f}; sigma0 {fit.sigma0_px:.3f} px (with the file's lens "
            f"{res.sigma0_px:.3f})")
    # the images must fit as well as the camera measures: a hand-eye from images its model does not explain is not
    # written into the cell file (every job would inherit it)
    why = None
    lens_cov = lens_covariance(intr, fit)
    if not fit.converged:
        why = "its adjustment with the lens did not converge"
    elif not (np.isfinite(lens_cov).all() and np.linalg.eigvalsh(lens_cov).min() >= -1e-9 * np.abs(lens_cov).max()):
        why = "the lens found with it has no finite covariance: these stations do not determine its terms"
    elif not fit.sigma0_px <= HAND_EYE_MAX_VARIANCE_RATIO * cf.camera.sigma_px:
        why = (f"the images fit {fit.sigma0_px:.3f} px, beyond {HAND_EYE_MAX_VARIANCE_RATIO:g}x the camera's sigma_px "
               f"{cf.camera.sigma_px:g} even with the lens estimated: the model does not explain them (a lens beyond "
               "k3 and p1, p2, a moving artefact, a robot pose that is not the image's)")
    if why is not None:
        doc["refused"] = why
        atomic_write_json(rec.file("hand_eye.json"), doc)
        rec.append("terminal", status="FAULTED", reason=why)
        rec.write_manifest()
        raise CalibrationError(f"hand-eye: not written to {cell_toml}: {why}; record {rec.job_id}")
    atomic_write_json(rec.file("hand_eye.json"), doc)
    write_flange_from_cam(cell_toml, fit.flange_from_cam, date, record=rec.job_id, lens=fit.lens,
                          lens_cov=lens_cov)
    rec.append("cell_file_updated", flange_from_cam=fit.flange_from_cam, date=date)
    rec.append("terminal", status="DONE", reason="")
    rec.write_manifest()
    summary = {"status": "ok", "record": rec.job_id, "folder": str(rec.path), "date": date,
               "flange_from_cam": fit.flange_from_cam, "sigma_translation_m": sig_t,
               "sigma_rotation_rad": sig_r, "sigma0_px": fit.sigma0_px, "lens": lens,
               "methods": methods, "methods_failed": failed, "images": int(len(B)), "truth": doc.get("truth"),
               "planned_conditioning": cond.to_dict()}
    st, sr = np.linalg.norm(sig_t), np.rad2deg(np.linalg.norm(sig_r))
    out.say(f"hand-eye: {len(B)} images, sigma0 {fit.sigma0_px:.3f} px; flange_from_cam +- {st * 1e3:.3f} mm, "
            f"{sr:.4f} deg; written to {cell_toml} ({date}), with the lens found ([cell] camera_lens)")
    return summary


def lens_covariance(start, fit) -> np.ndarray:
    """The covariance of the lens ``fit`` found (9 x 9 over the cell file's ``camera_lens`` fields, fx_px .. p2) from
    its terms' (``fit.terms``: ``f`` relative to ``start``'s focal length, the others added; X and Y marginalised)."""
    from cell.cellcal.cellfile import LENS_KEYS

    n = len(fit.cov) - len(fit.terms)
    J = np.zeros((len(LENS_KEYS), len(fit.terms)))
    for j, t in enumerate(fit.terms):
        if t == "f":
            J[0, j], J[1, j] = start.fx_px, start.fy_px
        else:
            J[LENS_KEYS.index({"cx": "cx_px", "cy": "cy_px"}.get(t, t)), j] = 1.0
    C = J @ fit.cov[n:, n:] @ J.T
    return 0.5 * (C + C.T)


# --- reverification (VDI/VDE 2634 part 1) --------------------------------------------------------------------
