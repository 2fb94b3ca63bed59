"""The reverification job (VDI/VDE 2634 part 1, ``cell calibrate reverify CELL.toml``): the scale bar in
several positions, its ends triangulated in the robot base frame, length errors against E_MPE."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.camera import Intrinsics, invert, project, project_with_jacobians
from calibration.errors import AbortRequested, CalibrationError, InputError
from cell.cellcal.common import (artefact_job, ask_operator, capture_at, centres_through_lens, measure_image,
                                 plan_stations, record_folder, save_image)
from cell.cellcal.cellfile import CellFile, load_cell_file
from cell.record.jobfolder import JobFolder, atomic_write_json, utc_now
from cell.jobspec import Pose
from planning.visibility import Occluder


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
            save_image(rec, name, img)
            tid, uv, pose_i, ecc = measure_image(img, job.part, intr, invert(X) @ invert(bff) @ Y0, occluder)
            if intr.has_distortion and len(tid):  # the centres through the cell's lens (decision 0057)
                t = job.part.targets
                uv = centres_through_lens(intr, pose_i[None], np.zeros(len(tid), dtype=int), t.xyz[tid],
                                          t.normals[tid], job.part.target_diameter_m / 2, uv, ecc)
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
    rec = record_folder(archive_root, cf.cell.name, "reverification")
    rec.append("created", kind="reverification", cell=cf.cell.name, cell_file=str(cell_toml), backend=backend)
    rows = []
    lens = cf.cell.camera_lens
    out.say("reverification: the lens " + (f"estimated with the hand-eye (record {cf.cell.flange_from_cam_record}; "
                                           f"[cell] camera_lens, fx {lens.fx_px:.2f} px)" if lens is not None else
                                           "of [camera] (its data sheet: no hand-eye lens in the cell file)"))
    rec.append("note", text="lens: " + ("[cell] camera_lens" if lens is not None else "[camera]"))
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
