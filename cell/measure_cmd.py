"""Measuring a folder of existing photographs: ``cell measure`` and ``cell calibrate camera``.

``cell measure IMAGES_DIR --camera CAMERA.toml --layout targets.csv [--control control.csv] --out DIR``

1. detect every image (``cell.detect_cmd``: dots with covariances, ring codes or ArUco);
2. identify: the coded targets name the layout's coded points; with at least 4 of them the image's
   pose follows (SQPnP, refined), and the layout's other targets are projected and matched to the
   dots (mutual nearest neighbours, ratio test; refined on the matched dots and matched again:
   ``calibration.targets.identify_targets``);
3. interior orientation: the camera file's, else the photographs' EXIF focal length and sensor size;
   on a flat layout a Zhang calibration (``calibration.planar``) over all images improves it, and the
   images are identified once more with it;
4. self-calibrating bundle (``calibration.bundle``, OpenCV camera model: fx, fy, cx, cy, k1, k2, p1,
   p2 and k3 with the camera file's ``radial = 3`` (the default); datum: the control points when given, truly fixed where their sigma is 0, else a free network
   on the layout's frame and scale), data snooping;
5. ``DIR/measure.json`` (images, camera with standard deviations, sigma0, targets with covariances),
   ``DIR/observations.csv`` and ``DIR/report.html``.

``cell calibrate camera IMAGES_DIR --layout targets.csv [--camera CAMERA.toml] --out CAMERA_OUT.toml``
runs steps 1-4 with self-calibration and writes the bundle's calibrated camera to the camera file; on a
flat field the JSON document also carries the Zhang start (``zhang``, with OpenCV's standard deviations).

Lengths in the layout and control files are in ``--units`` (mm by default); outputs are SI (m, m^2).
"""
from __future__ import annotations

import csv
import json
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from calibration.bundle import BundleConfig, BundleOptions, ControlPoints, bundle_adjust
from calibration.camera import Intrinsics, make_pose, project
from calibration.errors import CalibrationError, InputError
from calibration.planar import exif_camera, plane_frame, planar_calibration
from calibration.targets import identify_targets, refine_pose_pnp
from cell.camerafile import CameraFile, camera_toml, load_camera_file
from cell.detect_cmd import IMAGE_SUFFIXES, detect_targets, read_image
from planning.part import UNITS_TO_M, Targets, load_targets

__all__ = ["measure_folder", "measure_command", "calibrate_camera_command", "load_control"]


@dataclass
class _Image:
    name: str
    uv: np.ndarray  # (k, 2) dots (coded centres of ring codes included)
    code: np.ndarray  # (k,) ring code of each dot or -1
    aruco_ids: np.ndarray
    aruco_uv: np.ndarray
    target: np.ndarray | None = None  # (k,) layout index or -1
    pose: np.ndarray | None = None
    note: str = ""


def list_images(folder: Path) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder of images")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    if len(files) < 2:
        raise InputError(f"{folder}: {len(files)} image(s) (PNG, TIFF, JPEG); a measurement needs at least 2")
    return files


def load_control(path: str | Path, targets: Targets, units: str) -> ControlPoints:
    """``id,x,y,z[,sigma]`` (lengths in ``units``; sigma 0 or absent: truly fixed) -> ControlPoints."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: control file not found")
    scale = UNITS_TO_M[units]
    index = targets.index() if callable(getattr(targets, "index", None)) else {t: i for i, t in enumerate(targets.ids)}
    idx, xyz, sig = [], [], []
    with path.open(newline="", encoding="utf-8-sig") as f:
        reader = csv.DictReader(f)
        names = [c.strip() for c in reader.fieldnames or []]
        if not {"id", "x", "y", "z"} <= set(names):
            raise InputError(f"{path}: control CSV needs columns id,x,y,z[,sigma]")
        odd = sorted({c for c in names if c not in ("id", "x", "y", "z", "sigma", "note", "comment")}
                     | {c for c in names if names.count(c) > 1})
        if odd:  # a misspelt sigma would hold the point fixed without a word
            raise InputError(f"{path}:1: column(s) {', '.join(odd)} unknown or given twice; the columns are "
                             "id,x,y,z[,sigma] (and note, comment)")
        for lineno, row in enumerate(reader, 2):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k is not None}
            if row["id"] not in index:
                raise InputError(f"{path}:{lineno}: control point {row['id']!r} is not in the layout")
            try:
                xyz.append([float(row[c]) * scale for c in ("x", "y", "z")])
                sig.append(float(row["sigma"]) * scale if row.get("sigma") else 0.0)
            except (ValueError, TypeError) as e:
                raise InputError(f"{path}:{lineno}: {e}") from None
            if not (np.all(np.isfinite(xyz[-1])) and np.isfinite(sig[-1])):
                raise InputError(f"{path}:{lineno}: control point {row['id']!r}: coordinates and sigma must be finite")
            if sig[-1] < 0:
                raise InputError(f"{path}:{lineno}: negative sigma")
            if index[row["id"]] in idx:
                raise InputError(f"{path}:{lineno}: control point {row['id']!r} is given twice")
            idx.append(index[row["id"]])
    if len(idx) < 3:
        raise InputError(f"{path}: {len(idx)} control points; the datum needs at least 3")
    return ControlPoints(np.array(idx), np.array(xyz), np.array(sig))


def prior_intrinsics(cam: CameraFile, first: Path, width: int, height: int) -> tuple[Intrinsics, str]:
    """The interior orientation to start from, and where it came from."""
    if cam.width is not None and (cam.width, cam.height) != (width, height):
        raise InputError(f"camera file: width x height {cam.width}x{cam.height}, images {width}x{height}")
    cx = (width - 1) / 2 if cam.cx_px is None else cam.cx_px
    cy = (height - 1) / 2 if cam.cy_px is None else cam.cy_px
    dist = dict(k1=cam.k1, k2=cam.k2, k3=cam.k3, p1=cam.p1, p2=cam.p2)
    pitch = cam.pixel_size_um * 1e-6 if cam.pixel_size_um else None
    if cam.fx_px is not None:
        return Intrinsics(cam.fx_px, cam.fy_px or cam.fx_px, cx, cy, width, height, pixel_size_m=pitch, **dist), "camera file"
    if cam.focal_length_mm is not None and pitch is not None:
        f = cam.focal_length_mm * 1e-3 / pitch
        return Intrinsics(f, f, cx, cy, width, height, pixel_size_m=pitch, **dist), "camera file"
    ex = exif_camera(first, width)
    if ex is not None and ex.focal_px is not None:
        return Intrinsics(ex.focal_px, ex.focal_px, cx, cy, width, height, pixel_size_m=ex.pixel_size_m, **dist), \
            f"EXIF ({ex.source}, {ex.make} {ex.model})".strip()
    if ex is not None and pitch is None and cam.focal_length_mm is None:
        raise InputError(f"{first}: EXIF has a focal length ({ex.focal_mm} mm) but no sensor size; "
                         "give pixel_size_um in the camera file")
    raise InputError(f"{first}: no focal length: give fx_px, or focal_length_mm and pixel_size_um, in the camera file "
                     "(the photographs carry no usable EXIF)")


def _detect(path: Path, cam: CameraFile) -> tuple[_Image, tuple[int, int]]:
    img = read_image(path)
    det, code, keep, a_ids, a_uv = detect_targets(img, cam)
    return _Image(path.name, det.uv[keep], code[keep], a_ids, a_uv), (img.shape[1], img.shape[0])


def _identify(im: _Image, t: Targets, intr: Intrinsics) -> None:
    """Name the dots of one image (``im.target``) and estimate its pose (``im.pose``)."""
    lookup = {int(c): i for i, c in enumerate(t.code) if c >= 0}
    coded_det = np.flatnonzero(im.code >= 0)
    pairs = [(lookup[int(im.code[i])], im.uv[i]) for i in coded_det if int(im.code[i]) in lookup]
    pairs += [(lookup[int(c)], u) for c, u in zip(im.aruco_ids, im.aruco_uv) if int(c) in lookup]
    im.target = np.full(len(im.uv), -1)
    if len(pairs) < 4:
        im.note = f"{len(pairs)} known coded targets (4 needed to orient the image)"
        return
    xyz = t.xyz[[p[0] for p in pairs]]
    uv = np.array([p[1] for p in pairs], dtype=float)
    dist = np.asarray(intr.dist_coeffs, dtype=np.float64)
    ok = False
    if len(pairs) >= 5:  # a misread code (a single set sector is the easiest to fake) must not pull the pose
        ok, rvec, tvec, inl = cv2.solvePnPRansac(xyz, uv, intr.K, dist, iterationsCount=300,
                                                 reprojectionError=max(8.0, 0.03 * intr.width), confidence=0.999)
        if ok and inl is not None and len(inl) >= 4:
            xyz, uv = xyz[inl.ravel()], uv[inl.ravel()]
        else:
            ok = False
    if ok or len(pairs) < 5:  # the pose from all consistent codes (RANSAC's minimal sets are poor on flat fields)
        ok, rvec, tvec = cv2.solvePnP(xyz, uv, intr.K, dist, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        im.note = "no consistent pose from the coded targets"
        return
    pose = make_pose(cv2.Rodrigues(rvec)[0], tvec.ravel())
    if len(pairs) >= 4:
        pose = refine_pose_pnp(intr, pose, xyz, uv)
    plain = np.flatnonzero(im.code < 0)
    max_dist = 10.0
    if len(plain) >= 2:
        nn = cKDTree(im.uv).query(im.uv[plain], k=2)[0][:, 1]
        max_dist = 0.4 * float(np.median(nn))
        sub_codes = np.where(t.code >= 0, t.code, -1)
        match = identify_targets(im.uv[plain], t.xyz, sub_codes, intr, pose, max_dist)
        im.target[plain] = match
    for i in coded_det:  # a coded centre counts where the pose puts its target (a misread code does not)
        j = lookup.get(int(im.code[i]))
        gross = max(3.0 * max_dist, 0.03 * intr.width)  # codes are unique: only a misread is this far off
        if j is not None and np.linalg.norm(project(intr, pose, t.xyz[j][None])[0] - im.uv[i]) <= gross:
            im.target[i] = j
    named = im.target >= 0
    if np.sum(named) >= 6:
        pose = refine_pose_pnp(intr, pose, t.xyz[im.target[named]], im.uv[named])
    im.pose = pose
    # one dot per target: a target matched twice keeps neither
    vals, counts = np.unique(im.target[named], return_counts=True)
    im.target[np.isin(im.target, vals[counts > 1])] = -1


def measure_folder(folder: Path, cam: CameraFile, targets: Targets, *, control: ControlPoints | None = None,
                   self_calibrate: bool | None = None, say=print) -> dict:
    """Steps 1-4 of the module docstring; returns the result document (SI units) and keeps the bundle."""
    files = list_images(folder)
    images, sizes = zip(*(_detect(p, cam) for p in files))
    if len(set(sizes)) != 1:
        raise InputError(f"{folder}: images of different sizes {sorted(set(sizes))}; one camera setting per folder")
    width, height = sizes[0]
    intr, source = prior_intrinsics(cam, files[0], width, height)
    say(f"{len(files)} images {width}x{height}; interior orientation from the {source}: f {intr.fx_px:.1f} px")
    for im in images:
        _identify(im, targets, intr)
    used = [im for im in images if im.pose is not None and np.sum(im.target >= 0) >= 6]
    if len(used) < 2:
        notes = "; ".join(f"{im.name}: {im.note or 'fewer than 6 targets identified'}" for im in images[:5])
        raise CalibrationError(f"measure: {len(used)} image(s) oriented, at least 2 needed ({notes})")
    self_cal = cam.self_calibrate if self_calibrate is None else self_calibrate
    _, flat = plane_frame(targets.xyz)
    extent = float(np.ptp(targets.xyz, axis=0).max())
    zhang = None
    if self_cal and flat < 0.02 * extent and len(used) >= 3:
        zhang = planar_calibration([targets.xyz[im.target[im.target >= 0]] for im in used],
                                   [im.uv[im.target >= 0] for im in used], width, height, intr, radial=cam.radial)
        intr = zhang.intrinsics
        say(f"flat field (rms {flat * 1e3:.2f} mm off its plane): Zhang start f {intr.fx_px:.1f} px, rms {zhang.rms_px:.3f} px")
        for im in images:  # once more with the better camera: more dots at the image's edges
            _identify(im, targets, intr)
        used = [im for im in images if im.pose is not None and np.sum(im.target >= 0) >= 6]
    obs_image = np.concatenate([np.full(int(np.sum(im.target >= 0)), j) for j, im in enumerate(used)])
    obs_target = np.concatenate([im.target[im.target >= 0] for im in used])
    obs_uv = np.concatenate([im.uv[im.target >= 0] for im in used])
    model = "OPENCV_K3" if cam.radial == 3 and self_cal else "OPENCV"
    start = intr if model == "OPENCV_K3" else replace(intr, k3=0.0)
    poses = np.array([refine_pose_pnp(start, im.pose, targets.xyz[im.target[im.target >= 0]], im.uv[im.target >= 0])
                      for im in used])
    config = BundleConfig(camera_model=model, refine_focal_length=self_cal, refine_principal_point=self_cal,
                          refine_distortion=self_cal, control=control)
    res = bundle_adjust(obs_image, obs_target, obs_uv, start, poses, targets.xyz.copy(),
                        BundleOptions(sigma_px=cam.sigma_px), config)
    if not res.converged:
        hint = ("check the identification (cell detect --png)" if not (self_cal and control is None and
                                                                     flat < 0.02 * extent) else
                "a flat field with the camera self-calibrated and no coordinates held is weak: give the field's "
                "coordinates as control (--control control.csv, e.g. its certificate), or check the identification "
                "(cell detect --png)")
        raise CalibrationError(f"measure: the bundle adjustment did not converge; {hint}")
    n_rays = np.bincount(obs_target[~res.rejected], minlength=len(targets.ids))
    say(f"bundle: {len(obs_uv)} observations in {len(used)} images, sigma0 {res.sigma0_px:.4f} px, "
        f"{int(res.rejected.sum())} rejected, datum {res.datum}")
    names = list(res.intrinsics_names)
    sd = np.sqrt(np.diag(res.intrinsics_cov)) if len(names) else np.zeros(0)
    ri = res.intrinsics
    # what the answer is worth (decision 0057): one camera setting in every image, the bundle's own signals
    from cell.measure_trust import doubts, exif_settings

    said = doubts(res, cam.sigma_px, list(images), used, exif_settings(files))
    if self_cal:  # what the network lacks for a self-calibration
        from cell.measure_trust import geometry_doubts

        said += geometry_doubts(res.cam_from_part, targets.xyz)
    for d in said:
        say(("UNTRUSTED " if d["untrusted"] else "WARNING ") + d["text"])
    doc = {
        "images": [{"name": im.name, "dots": int(len(im.uv)), "identified": int(np.sum(im.target >= 0)) if im.target is not None else 0,
                    "used": any(im is u for u in used), "note": im.note} for im in images],
        "camera": {"source": source, "fx_px": ri.fx_px, "fy_px": ri.fy_px, "cx_px": ri.cx_px, "cy_px": ri.cy_px,
                   "k1": ri.k1, "k2": ri.k2, "k3": ri.k3, "p1": ri.p1, "p2": ri.p2, "width": width, "height": height,
                   "model": model,
                   "sigma": {n: float(s) for n, s in zip(names, sd)}},
        "zhang": None if zhang is None else {"fx_px": zhang.intrinsics.fx_px, "fy_px": zhang.intrinsics.fy_px,
                                              "cx_px": zhang.intrinsics.cx_px, "cy_px": zhang.intrinsics.cy_px,
                                              "k1": zhang.intrinsics.k1, "k2": zhang.intrinsics.k2, "k3": zhang.intrinsics.k3,
                                              "p1": zhang.intrinsics.p1, "p2": zhang.intrinsics.p2,
                                              "sigma": dict(zip(("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3"),
                                                                map(float, zhang.std))), "rms_px": zhang.rms_px},
        "sigma0_px": float(res.sigma0_px), "datum": res.datum, "observations": int(len(obs_uv)),
        "rejected": int(res.rejected.sum()), "flatness_m": flat,
        "converged": bool(res.converged), "solver_fallback": res.solver_fallback,
        "snooping": {k: res.snooping.get(k) for k in ("complete", "stopped", "n_rejected", "suspect_targets",
                                                      "diverged", "handed_over", "protected") if k in res.snooping},
        "variance_factor": float((res.sigma0_px / cam.sigma_px) ** 2),
        "doubts": said, "trusted": not any(d["untrusted"] for d in said),
        "coded_not_judged": [targets.ids[i] for i in np.flatnonzero(targets.kind == "coded") if n_rays[i] < 2],
        "targets": [{"id": targets.ids[i], "xyz": res.points[i].tolist(), "cov": res.cov[i].tolist(),
                     "sigma_m": float(np.sqrt(np.trace(res.cov[i]))), "rays": int(n_rays[i])}
                    for i in range(len(targets.ids)) if n_rays[i] >= 2 and np.all(np.isfinite(res.points[i]))],
    }
    doc["snooping"]["suspect_targets"] = [targets.ids[i] for i in doc["snooping"].get("suspect_targets") or []]
    doc["_observations"] = (obs_image, obs_target, obs_uv, res.residuals, res.rejected, [im.name for im in used])
    return doc


def report_doc(doc: dict, targets: Targets, tolerance_m: float, job_id: str, name: str, started: str, finished: str) -> dict:
    """The measurement as a report.json (ARCHITECTURE.md's contract): deviations from the layout's nominal
    coordinates (the datum's frame: the layout's own for a free network, the control's otherwise)."""
    import platform

    measured = {t["id"]: t for t in doc["targets"]}
    tol = np.where(np.isfinite(targets.tolerance_m), targets.tolerance_m, tolerance_m)
    al = _layout_alignment(doc, targets, tol)
    rows = []
    for i, tid in enumerate(targets.ids):
        m = measured.get(tid)
        nominal = targets.xyz[i].tolist()
        if m is None:
            rows.append({"id": tid, "nominal": nominal, "measured": [None] * 3, "cov": [[None] * 3] * 3,
                         "deviation": [None] * 3, "deviation_norm_m": None, "tolerance_m": float(tol[i]), "pass": False,
                         "predicted_sigma_m": None, "achieved_sigma_m": None, "n_images": 0})
            continue
        xyz, cov = (m["xyz"], m["cov"]) if al is None else (al["aligned"][i].tolist(), al["cov"][i].tolist())
        d = np.asarray(xyz) - targets.xyz[i]
        rows.append({"id": tid, "nominal": nominal, "measured": xyz, "cov": cov, "deviation": d.tolist(),
                     "deviation_norm_m": float(np.linalg.norm(d)), "tolerance_m": float(tol[i]),
                     "pass": bool(np.linalg.norm(d) <= tol[i]), "predicted_sigma_m": None,
                     "achieved_sigma_m": m["sigma_m"], "n_images": m["rays"]})
    fit = [t["id"] for t in doc["targets"]] if al is None else al["fit"]
    dev = np.array([r["deviation_norm_m"] for r in rows if r["id"] in set(fit) and r["deviation_norm_m"] is not None])
    verdict, reasons = _verdict(doc, targets, rows)
    al_trusted = bool(doc["datum"] == "control" or len(fit) >= 4) if al is None else al["trusted"]
    al_reasons = ([] if al_trusted else ["fewer than 4 targets measured"]) if al is None else al["reasons"]
    said = doc.get("doubts") or []
    sn = dict(doc.get("snooping") or {})
    return {
        "job": {"id": job_id, "name": name, "seed": 0, "status": "DONE", "started": started, "finished": finished,
                "versions": {"python": platform.python_version(), "numpy": np.__version__, "opencv": cv2.__version__},
                "part": name},
        "images": sum(im["used"] for im in doc["images"]), "sigma0_px": doc["sigma0_px"], "datum": doc["datum"],
        "verdict": verdict if al_trusted else "UNTRUSTED", "verdict_reasons": reasons, "targets": rows,
        "alignment": {"method": "control" if doc["datum"] == "control" else
                      "free network, robust similarity fit to the layout (targets that agree with it)",
                      "targets_in_fit": fit, "rms_m": float(np.sqrt(np.mean(dev**2))) if len(dev) else None,
                      "trusted": al_trusted, "reasons": al_reasons, "notes": [] if al is None else al["notes"]},
        # what the measurement says of itself (decision 0057): report.html shows each
        "measurement_trusted": bool(doc.get("trusted", True)),
        "untrusted_reasons": [d["text"] for d in said if d["untrusted"]],
        "snooping": sn, "solver_fallback": doc.get("solver_fallback"),
        "uncertainty_budget": {"variance_factor": doc.get("variance_factor"),
                               "detector_model_mismatch": next((d["text"] for d in said
                                                                if d["kind"] == "variance_factor"), None)},
        "left_out": {"images": [{"image": im["name"], "station": "photograph", "reason": im["note"] or
                                 "fewer than 6 targets identified"} for im in doc["images"] if not im["used"]]},
        "part": {"number": None, "revision": None, "serial": None}, "operator": None, "cell_id": None,
        "camera": doc["camera"], "stage_times_s": doc.get("stage_times_s", {}),
    }


def _layout_alignment(doc: dict, targets: Targets, tol: np.ndarray) -> dict | None:
    """A free network's frame on the layout, fitted over the targets that agree with it (None: the control's frame).

    The bundle's free network sits on the layout by inner constraints over every target (translation, rotation and
    scale): targets that deviate pull it, and the others then seem to deviate (an outside check: 6 targets 1.5 mm off
    among 63 made 24 good ones fail a 0.2 mm tolerance). Here the frame is the robust best fit of a similarity
    (:func:`calibration.robust_alignment.robust_best_fit` with a scale: consensus, bounded exclusion, verdict), and
    the deviations and their covariances follow it."""
    from calibration.alignment import align_to_cad
    from calibration.robust_alignment import robust_best_fit

    if doc["datum"] == "control":
        return None
    n = len(targets.ids)
    index = {t: i for i, t in enumerate(targets.ids)}
    xyz = np.full((n, 3), np.nan)
    cov = np.tile(np.eye(3), (n, 1, 1))
    for t in doc["targets"]:
        xyz[index[t["id"]]] = t["xyz"]
        cov[index[t["id"]]] = t["cov"]
    cand = np.all(np.isfinite(xyz), axis=1) & (targets.kind != "coded")
    if cand.sum() < 4:
        cand = np.all(np.isfinite(xyz), axis=1)
    x0 = np.where(np.isfinite(xyz), xyz, 0.0)
    min_fit = min(6, int(cand.sum()))
    out = robust_best_fit(x0, cov, targets.xyz, tol, 3.0, candidates=cand, with_scale=True, min_fit=min_fit)
    a, mask, trusted, reasons, notes = out.alignment, out.fit_mask, out.trusted, list(out.reasons), list(out.notes)
    if not out.trusted and out.consensus is not None and out.consensus.agree.sum() < max(min_fit, cand.sum() / 3):
        # no placement brings the targets to the layout within their stated precision: a printed or worked field is
        # not its layout at the measurement's precision (a sheet's bow). The frame is then fitted over the targets
        # within their tolerance, excluded in turn from the fit over all, and said
        mask = cand.copy()
        stable = False
        for _ in range(10):
            a = align_to_cad(x0, cov, targets.xyz, fit_mask=mask, with_scale=True)
            new = cand & (np.linalg.norm(a.deviation, axis=1) <= tol)
            if np.array_equal(new, mask):
                stable = True
                break
            if new.sum() < max(min_fit, 0.5 * cand.sum()):
                break
            mask = new
        trusted = bool(stable and mask.sum() >= max(min_fit, 0.5 * cand.sum()))
        reasons = [] if trusted else [f"the fit over the targets within their tolerance did not settle on a majority "
                                      f"({int(mask.sum())} of {int(cand.sum())}): {out.reasons[0]}"]
        notes = [f"no placement brings a third of the targets to the layout within their stated precision (the best "
                 f"{int(out.consensus.agree.sum())} of {int(cand.sum())}: the field is not its layout at this "
                 "precision): the frame is fitted over the "
                 f"{int(mask.sum())} of {int(cand.sum())} targets within their tolerance"]
    aligned = np.where(np.isfinite(xyz), a.aligned, np.nan)
    return {"aligned": aligned, "cov": a.deviation_cov, "fit": [targets.ids[i] for i in np.flatnonzero(mask)],
            "trusted": bool(trusted), "reasons": reasons, "notes": notes}


def _verdict(doc: dict, targets: Targets, rows: list[dict]) -> tuple[str, list[str]]:
    """The verdict as a job's (:func:`cell.stages.report.part_verdict`): coded markers that orient the images and
    were not measured (ArUco) are not judged; targets data snooping could not verify are suspect; a measurement
    whose own checks failed (:mod:`cell.measure_trust`) is UNTRUSTED, with why first."""
    from cell.stages.report import part_verdict

    ok = np.array([r["deviation_norm_m"] is not None for r in rows], dtype=bool)
    judged = (targets.kind != "coded") | ok
    passed = np.array([bool(r["pass"]) for r in rows], dtype=bool)
    suspect = np.isin(targets.ids, (doc.get("snooping") or {}).get("suspect_targets") or [])
    verdict, reasons = part_verdict(True, ok, passed, judged, [None] * len(rows), suspect, list(targets.ids))
    bad = [d["text"] for d in doc.get("doubts") or [] if d["untrusted"]]
    if bad:
        return "UNTRUSTED", bad + list(reasons)
    return verdict, list(reasons)


def _write_outputs(out_dir: Path, doc: dict, targets: Targets, report: dict) -> None:
    from cell.record.jobfolder import atomic_write_bytes, atomic_write_json
    from cell.record.report import figure_residuals, render_html

    ids = list(targets.ids)
    out_dir.mkdir(parents=True, exist_ok=True)
    obs_image, obs_target, obs_uv, resid, rejected, names = doc.pop("_observations")
    rows = ["image,target,u,v,du,dv,rejected"]
    rows += [f"{names[j]},{ids[t]},{u:.4f},{v:.4f},{r[0]:.4f},{r[1]:.4f},{int(x)}"
             for j, t, (u, v), r, x in zip(obs_image, obs_target, obs_uv, resid, rejected)]
    atomic_write_bytes(out_dir / "observations.csv", ("\n".join(rows) + "\n").encode())
    atomic_write_json(out_dir / "measure.json", doc)
    atomic_write_json(out_dir / "report.json", report)
    ok = ~np.asarray(rejected, dtype=bool)
    page = render_html(report, {"residuals": figure_residuals(np.asarray(resid)[ok])})
    atomic_write_bytes(out_dir / "report.html", page.encode())


def _archive(archive: Path, out_dir: Path, job_id: str, name: str) -> Path:
    """File the measurement in the archive as a finished job: its outputs, a journal, a manifest, the index."""
    import shutil

    from cell.record.archive import Archive
    from cell.record.jobfolder import JobFolder

    folder = Path(archive) / job_id
    folder.mkdir(parents=True, exist_ok=False)
    jf = JobFolder(folder)
    jf.append("created", name=name, source="cell measure", out=str(out_dir))
    for d in json.loads((out_dir / "measure.json").read_text()).get("doubts") or []:  # said in the journal too
        jf.append("note", text=("UNTRUSTED " if d["untrusted"] else "WARNING ") + d["text"])
    for f in ("measure.json", "observations.csv", "report.json", "report.html"):
        shutil.copy2(out_dir / f, folder / f)
    jf.append("state", **{"from": "MEASURE", "to": "DONE"})
    jf.write_manifest()
    Archive(Path(archive)).reindex(only=folder)
    return folder


#: a layout whose extent in metres lies outside this range is not a photogrammetric field in the units given
LAYOUT_EXTENT_M = (0.005, 50.0)


def _load_layout(args) -> Targets:
    if args.layout is None:
        raise InputError("--layout targets.csv is needed: the targets' nominal coordinates and codes")
    t = load_targets(args.layout, args.units)
    extent = float(np.ptp(t.xyz, axis=0).max()) if len(t.xyz) else 0.0
    lo, hi = LAYOUT_EXTENT_M
    if not lo <= extent <= hi:  # --units m for a layout in mm measured a field 1000x too large, and said nothing
        raise InputError(f"{args.layout}: the layout spans {extent:g} m in --units {args.units}: not a field a camera "
                         f"measures ({lo:g}-{hi:g} m); are its coordinates in another unit? (--units)")
    return t


def measure_command(args, out) -> int:
    import time

    from cell.record.jobfolder import new_job_id, utc_now

    cam = load_camera_file(args.camera)
    targets = _load_layout(args)
    control = load_control(args.control, targets, args.units) if args.control else None
    if args.tolerance <= 0:
        raise InputError(f"--tolerance {args.tolerance}: must be positive")
    started, t0 = utc_now(), time.perf_counter()
    name = Path(args.images).resolve().name or "measure"
    doc = measure_folder(args.images, cam, targets, control=control, say=out.say)
    doc["stage_times_s"] = {"measure": time.perf_counter() - t0}
    job_id = new_job_id(name)
    report = report_doc(doc, targets, args.tolerance * UNITS_TO_M[args.units], job_id, name, started, utc_now())
    al = report["alignment"]  # the frame's doubts and fallbacks, said here as in report.json and report.html
    for r in al.get("reasons", []):
        out.say(f"UNTRUSTED alignment to the layout: {r}")
    for n in al.get("notes", []):
        out.say(f"WARNING alignment to the layout: {n}")
    _write_outputs(Path(args.out), doc, targets, report)
    if args.archive is not None:
        doc["archive"] = str(_archive(args.archive, Path(args.out), job_id, name))
    doc["verdict"] = report["verdict"]

    def human(d):
        out.say(f"measured {len(d['targets'])} targets (sigma0 {d['sigma0_px']:.4f} px), {d['verdict']} against the "
                f"layout: {args.out}/report.html" + (f"; archived as {job_id}" if args.archive is not None else ""))

    out.result(doc, human)
    return 0


def calibrate_camera_command(args, out) -> int:
    cam = load_camera_file(args.camera)
    targets = _load_layout(args)
    if args.out is None or Path(args.out).suffix != ".toml":
        raise InputError("cell calibrate camera: --out CAMERA_OUT.toml is needed")
    control = load_control(args.control, targets, args.units) if getattr(args, "control", None) else None
    doc = measure_folder(args.images, cam, targets, control=control, self_calibrate=True, say=out.say)
    doc.pop("_observations")
    # a camera file is what later measurements hold: one the images do not vouch for is not written (decision 0057)
    why = [d["text"] for d in doc["doubts"] if d["untrusted"]]
    if not np.isfinite(doc["sigma0_px"]) and not why:
        why.append(f"sigma0 {doc['sigma0_px']}: the images' fit is unknown")
    if why:
        raise CalibrationError(f"cell calibrate camera: not written to {args.out}: {'; '.join(why)}")
    c = doc["camera"]
    sig = c["sigma"]
    new = cam.model_copy(update={"fx_px": c["fx_px"], "fy_px": c["fy_px"], "cx_px": c["cx_px"], "cy_px": c["cy_px"],
                                 "k1": c["k1"], "k2": c["k2"], "k3": c["k3"], "p1": c["p1"], "p2": c["p2"],
                                 "width": c["width"], "height": c["height"], "self_calibrate": False})
    comments = {k: f"+- {sig[n]:.3g}" for k, n in (("fx_px", "fx"), ("fy_px", "fy"), ("cx_px", "cx"), ("cy_px", "cy"),
                                                   ("k1", "k1"), ("k2", "k2"), ("k3", "k3"), ("p1", "p1"), ("p2", "p2"))
                if n in sig}
    text = (f"# cell calibrate camera: {len(doc['images'])} images, sigma0 {doc['sigma0_px']:.4f} px\n"
            + "".join(f"# WARNING {d['text']}\n" for d in doc["doubts"]) + camera_toml(new, comments))
    from cell.record.jobfolder import atomic_write_bytes

    atomic_write_bytes(Path(args.out), text.encode())
    doc["camera_file"] = str(args.out)

    def human(d):
        out.say(f"camera: fx {c['fx_px']:.2f} fy {c['fy_px']:.2f} cx {c['cx_px']:.2f} cy {c['cy_px']:.2f} px, "
                f"k1 {c['k1']:.5f} k2 {c['k2']:.5f}; sigma0 {d['sigma0_px']:.4f} px -> {args.out}")

    out.result(doc, human)
    return 0
