"""Part placement from a quick first image set: ``base_from_part`` from the coded markers, then every dot.

The operator need not measure where the part sits: a few overview images (stations planned by the
inspection's planner for the coded markers, :func:`cell.cellcal.common.plan_stations`) give it, with the
job's hand-eye held fixed. Used by ``cell locate`` (:mod:`cell.cellcal.locate`).
"""
from __future__ import annotations


import cv2
import numpy as np

from calibration.camera import Intrinsics, invert, make_pose, project
from calibration.errors import CalibrationError, InputError, ReachabilityError
from calibration.handeye import HandEyeOptions, pose_error, refine_hand_eye, refine_with_lens
from calibration.targets import DetectionOptions, detect_coded_targets, detect_retro_targets
from cell.stages import imaging
from cell.cellcal.common import capture_at, plan_stations
from cell.loadedjob import LoadedJob
from planning.visibility import Occluder

__all__ = ["estimate_part_placement"]


# --- part placement from a quick first image set -------------------------------------------------------------
#
# The dots can only be named once the placement is known to a few pixels, so the placement is
# found first from what names itself: the coded markers. Each marker gives its four corners (one
# marker already fixes an image's pose; the bracket shows two or three of its five per overview
# image, fewer than the four marker centres a centre-only PnP needs), the corners of all images are
# adjusted together with the hand-eye held fixed, and only then are the dots named (by projecting
# them with that placement, among the targets in view from it) and the placement adjusted on them.

#: OpenCV's sub-pixel marker corners on these images: biased by 0.1-0.3 px.
PLACEMENT_CORNER_SIGMA_PX = 0.3
#: Largest distance between a dot and its prediction from the placement of the coded markers.
PLACEMENT_MATCH_PX = 12.0
#: A marker whose corners miss the joint placement by more (rms) is not where its code says.
PLACEMENT_MARKER_RMS_PX = 3.0
#: Two views of markers agree on the placement within this (translation + part radius x rotation).
PLACEMENT_AGREE_M = 0.015
#: Bias of a dot's measured centre that more dots do not average away: a bound for real targets (print,
#: lighting). On the simulated images the mean centring error along the normal's image is now 0.001 px,
#: 0.0035 px beyond 70 deg incidence (benchmarks/centre_bias.py; it was 0.006-0.014 px before decision 0007).
PLACEMENT_SYSTEMATIC_PX = 0.015
#: The overview plans for the coded markers it can show twice; fewer than this many such markers is an error (one
#: marker fixes an image's pose, but a marker whose code is on the wrong target needs others to outvote it).
PLACEMENT_MIN_MARKERS = 3


def estimate_part_placement(job: LoadedJob, devices, out, *, n_images: int = 4) -> tuple[np.ndarray, dict]:
    """``base_from_part`` (4, 4) from a few images of the part, with the job's hand-eye held fixed.

    Stations look at the nominal part from ``n_images`` azimuths, chosen among the reachable ones
    that see at least two coded markers. The placement comes first from the markers' corners
    (:func:`_placement_from_codes`), then the dots are identified with it and the placement is
    adjusted on every dot of every image (:func:`refine_hand_eye` with X fixed, Huber loss and
    rejection), then again with the lens's principal distance, principal point, k1 and k2
    (:func:`placement_with_lens`); dots are named a second time with the adjusted placement and lens.

    Returns ``(base_from_part, summary)``; the summary has ``cov`` (6, 6) of ``xi = (omega, tau)``
    with ``true = Exp(xi) @ base_from_part`` (base frame, rad and m) from the image residuals,
    ``sigma_translation_m`` (3,) of the part origin and ``sigma_rotation_rad`` (3,) about the base
    axes (that covariance plus the bound of a centring bias, :func:`placement_with_lens`), ``coded``
    (the marker stage) and the figures of the adjustment. The robot's readings and the hand-eye are
    taken as exact: their errors (tens of micrometres on a calibrated UR) come on top.
    """
    P, joints, unseen = _placement_stations(job, n_images)
    if unseen:
        out.say(f"placement: WARNING: coded marker(s) {', '.join(unseen)} cannot be seen twice from the reachable "
                f"overview stations; the placement uses the other {int((job.part.targets.kind == 'coded').sum()) - len(unseen)}")
    X, Y0 = job.spec.flange_from_cam(), job.spec.base_from_part()
    intr = job.intrinsics
    B, images = [], []
    for i, q in enumerate(joints):
        out.progress("placement", i / (len(joints) + 1))
        img, bff = capture_at(devices, q, job.spec.cell)
        images.append(img)
        B.append(bff)
    B = np.array(B)
    markers = [_coded_markers(job, img) for img in images]
    occluder = Occluder(job.part.mesh)
    dots = [_free_dots(img, m[2]) for img, m in zip(images, markers)]
    Y, coded = _placement_from_codes(job, B, markers, dots, occluder)
    lens = intr
    for _pass in range(2):
        img_idx, tgt_idx, uvs = [], [], []
        for i, (b, d) in enumerate(zip(B, dots)):
            tid, uv = _identify_dots(job, d, invert(X) @ invert(b) @ Y, occluder, lens)
            img_idx.append(np.full(len(tid), i))
            tgt_idx.append(tid)
            uvs.append(uv)
        tgt = np.concatenate(tgt_idx)
        if len(tgt) < 12:
            raise InputError(f"part placement: only {len(tgt)} dots identified in {len(B)} images (12 needed); "
                                   "check the light and that the part's targets file matches the part")
        res = refine_hand_eye(lens, B, np.concatenate(img_idx), job.part.targets.xyz[tgt], np.concatenate(uvs), X, Y,
                              HandEyeOptions(sigma_px=job.spec.camera.sigma_px, fix_flange_from_cam=True))
        ok = ~res.rejected
        fit = placement_with_lens(intr, lens, B, X, res.base_from_target, np.concatenate(img_idx)[ok],
                                  job.part.targets.xyz[tgt[ok]], np.concatenate(uvs)[ok])
        Y, lens = fit["base_from_part"], fit["lens"]
    out.progress("placement", 1.0)
    # the markers' views judged again with the lens and placement the dots found: the nominal lens alone leaves the
    # corners of a view near the image's edge tens of pixels off, which is the lens, not a marker on the wrong target
    v_img, v_xyz, v_uv = coded.pop("_views")
    v_rms = np.array([np.sqrt(np.mean(np.sum((project(lens, invert(X) @ invert(B[i]) @ Y, p) - u) ** 2, axis=1)))
                      for i, p, u in zip(v_img, v_xyz, v_uv)])
    by_key = {(d["image"], d["target"]): d for d in coded["dropped"]}
    coded["dropped_at_start"] = len(coded["dropped"])
    coded["dropped"] = [by_key[(int(v_img[v]), t)] | {"rms_px": float(v_rms[v])}
                        for v, t in enumerate(coded["views_target"])
                        if (int(v_img[v]), t) in by_key and v_rms[v] >= PLACEMENT_MARKER_RMS_PX]
    cov = fit["cov"]
    sys_r, sys_t = fit["systematic_rotation_rad"], fit["systematic_translation_m"]
    J_origin = np.hstack([-_skew3(Y[:3, 3]), np.eye(3)])  # d(origin) = omega x origin + tau
    sig_t = np.sqrt(np.clip(np.diag(J_origin @ cov @ J_origin.T), 0.0, None) + sys_t**2)
    sig_r = np.sqrt(np.clip(np.diag(cov[:3, :3]), 0.0, None) + sys_r**2)
    dt, dr = pose_error(Y, Y0)
    dt1, dr1 = pose_error(coded["base_from_part"], Y)
    summary = {"base_from_part": Y, "cov": cov, "sigma_translation_m": sig_t, "sigma_rotation_rad": sig_r,
               "systematic_translation_m": sys_t, "systematic_rotation_rad": sys_r,
               "images": int(len(B)), "n_observations": int(len(tgt)), "n_rejected": int(res.rejected.sum()),
               "sigma0_px": fit["doc"]["sigma0_px"], "per_image_rms_px": res.per_image_rms_px,
               "change_from_nominal_m": dt, "change_from_nominal_rad": dr,
               "coded": coded | {"error_m": dt1, "error_rad": dr1}, "stations_part_from_cam": P,
               "markers_not_planned": unseen, "lens": fit["doc"]}
    out.say(f"placement: {len(B)} images, {coded['n_markers']} marker views, {len(tgt)} dots "
            f"({summary['n_rejected']} rejected), sigma0 {summary['sigma0_px']:.3f} px; the part is {dt * 1e3:.2f} mm, "
            f"{np.rad2deg(dr):.3f} deg from the job's base_from_part (+- {np.linalg.norm(sig_t) * 1e6:.1f} um, "
            f"{np.rad2deg(np.linalg.norm(sig_r)) * 3600:.1f} arcsec)")
    ld = fit["doc"]
    out.say(f"placement: lens estimated with it (decision 0055): principal distance {ld['principal_distance_mm']:.4f} "
            f"+- {ld['principal_distance_sigma_mm']:.4f} mm (job's {ld['nominal_principal_distance_mm']:.4f}), "
            f"principal point {ld['principal_point_offset_px'][0]:+.1f}, {ld['principal_point_offset_px'][1]:+.1f} px "
            f"off the job's, k1 {ld['k1']:+.4f}, k2 {ld['k2']:+.4f}")
    summary["warnings"] = placement_doubts(ld, job.spec.camera.sigma_px)
    for w in summary["warnings"]:
        out.say(f"placement: WARNING: {w}")
    if coded["dropped"]:
        # a marker none of whose views fits the placement is not where the file says; a single view that does not
        # fit while the marker's other views do is a poor view (grazing, partly hidden), not a wrong file
        kept = set(coded["used_targets"])
        bad = sorted({(d["code"], d["target"]) for d in coded["dropped"] if d["target"] not in kept})
        poor = [d for d in coded["dropped"] if d["target"] in kept]
        if bad:
            out.say("placement: WARNING: marker(s) " + ", ".join(f"code {c} (target {t})" for c, t in bad) + " are "
                    "not where the targets file puts them (none of their views fits the others and the dots); they "
                    "were left out: check the file's code column")
        if poor:
            out.say("placement: " + ", ".join(f"{d['target']} in image {d['image']} ({d['rms_px']:.1f} px)" for d in poor)
                    + f": view(s) whose corners miss the placement by more than {PLACEMENT_MARKER_RMS_PX:g} px rms "
                    "while the marker's other views fit; left out")
    return Y, summary


#: the lens terms estimated with the placement: the principal distance (fx, fy together), the principal point, k1, k2
PLACEMENT_LENS_TERMS = ("f", "cx", "cy", "k1", "k2")


def placement_with_lens(nominal: Intrinsics, start: Intrinsics, B: np.ndarray, X: np.ndarray, Y: np.ndarray,
                        obs_image: np.ndarray, obs_xyz: np.ndarray, obs_uv: np.ndarray) -> dict:
    """The placement ``Y`` and the lens's :data:`PLACEMENT_LENS_TERMS` adjusted together on the named dots, with the
    hand-eye ``X`` and the robot's poses ``B`` held (:func:`calibration.handeye.refine_with_lens`; decision 0055).

    A lens is not its data sheet: its principal distance scales the depth of every dot (0.75 % longer put the
    part 4.8 mm off at a stated 20 um), and its distortion moves the outer dots. The robot's known motion between
    the images fixes the depth by itself, so the lens is estimated with the placement rather than assumed.

    Returns ``base_from_part``, ``lens``, ``cov`` (6, 6) of the placement's ``xi = (omega, tau)`` (the lens
    marginalised), ``systematic_rotation_rad`` / ``systematic_translation_m`` (3,): the largest effect of a
    ``PLACEMENT_SYSTEMATIC_PX`` bias on every dot (``s0^2 (J^T J)^-1`` assumes independent centring errors, which
    average down with the number of dots; a bias does not: with ``G = (J^T J)^-1 J^T``, biases ``|b| <= s`` move a
    parameter by at most ``s * sum |G_row|``), and ``doc`` (the lens found, with its sigmas).
    """
    fit = refine_with_lens(start, B, obs_image, obs_xyz, obs_uv, X, Y, PLACEMENT_LENS_TERMS, fix_flange_from_cam=True)
    Y1, lens = fit.base_from_target, fit.lens
    G = fit.gain[6:12]
    G_origin = np.hstack([-_skew3(Y1[:3, 3]), np.eye(3)]) @ G
    sb = PLACEMENT_SYSTEMATIC_PX
    return {"base_from_part": Y1, "lens": lens, "cov": fit.cov[6:12, 6:12],
            "systematic_rotation_rad": sb * np.abs(G[:3]).sum(axis=1),
            "systematic_translation_m": sb * np.abs(G_origin).sum(axis=1), "doc": lens_doc(nominal, fit)}


#: the placement's image fit beyond this many times the camera's sigma_px, or its principal distance further than this
#: share from the job's, is said: a placement from images its model does not explain, or a lens unlike any the job's
#: camera could have (a wrong pixel size or focal length in [camera]), is not trusted quietly
PLACEMENT_MAX_VARIANCE_RATIO = 3.0
PLACEMENT_MAX_FOCAL_SHARE = 0.05


def placement_doubts(doc: dict, sigma_px: float) -> list[str]:
    """What makes the placement's adjustment (``doc``: :func:`lens_doc` with ``converged``) doubtful, in words."""
    out = []
    if not doc.get("converged", True):
        out.append("the placement's adjustment with the lens did not converge: its placement is not trustworthy")
    if not doc["sigma0_px"] <= PLACEMENT_MAX_VARIANCE_RATIO * sigma_px:
        out.append(f"the images fit {doc['sigma0_px']:.3f} px, beyond {PLACEMENT_MAX_VARIANCE_RATIO:g}x [camera] "
                   f"sigma_px {sigma_px:g} even with the lens estimated: the placement's stated uncertainty is "
                   "optimistic (misnamed dots, a moving part, a lens beyond k1, k2)")
    share = doc["principal_distance_mm"] / doc["nominal_principal_distance_mm"] - 1
    if not abs(share) <= PLACEMENT_MAX_FOCAL_SHARE:
        out.append(f"the principal distance found is {100 * share:+.1f} % off the job's: check [camera] "
                   "focal_length_mm and pixel_size_um")
    return out


def lens_doc(nominal: Intrinsics, fit) -> dict:
    """What a :class:`calibration.handeye.LensRefinement` found of the lens, against the ``nominal`` one: the
    principal distance (mm) and principal point offset (px) with their sigmas, and each distortion term's."""
    lens, sig = fit.lens, fit.lens_sigma()
    mm = (nominal.pixel_size_m or float("nan")) * 1e3
    doc = {"terms": list(fit.terms), "sigma0_px": fit.sigma0_px, "converged": fit.converged,
           "principal_distance_mm": float(lens.fx_px * mm), "nominal_principal_distance_mm": float(nominal.fx_px * mm),
           "principal_distance_sigma_mm": float(sig.get("f", 0.0) * lens.fx_px * mm),
           "principal_point_offset_px": [float(lens.cx_px - nominal.cx_px), float(lens.cy_px - nominal.cy_px)],
           "principal_point_sigma_px": [sig.get("cx", 0.0), sig.get("cy", 0.0)]}
    for t in ("k1", "k2", "k3", "p1", "p2"):
        doc[t] = float(getattr(lens, t))
        if t in sig:
            doc[f"{t}_sigma"] = sig[t]
    return doc


def _skew3(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _coded_markers(job: LoadedJob, img: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The part's markers in one image: ``(target index (k,), corners uv (k, 4, 2), every marker's corners)``.

    A code that is not the part's, or that appears twice in the image, names nothing; every
    detected marker's square still masks the dots inside it.
    """
    t = job.part.targets
    code_to_index = {int(c): i for i, c in enumerate(t.code) if c >= 0}
    codes, corners, _ = detect_coded_targets(img)
    codes = np.asarray(codes, dtype=int)
    once = {int(c) for c, n in zip(*np.unique(codes, return_counts=True)) if n == 1}
    keep = [j for j, c in enumerate(codes) if int(c) in code_to_index and int(c) in once]
    idx = np.array([code_to_index[int(codes[j])] for j in keep], dtype=int)
    return idx, corners[keep].reshape(-1, 4, 2), corners.reshape(-1, 4, 2)


def _marker_corners_part(job: LoadedJob, idx: np.ndarray) -> np.ndarray:
    """Corners (k, 4, 3) of the markers of targets ``idx`` in the part frame, in OpenCV's ArUco order."""
    from sim_backend.world import marker_corners

    t = job.part.targets
    return marker_corners(t.xyz[idx], t.normals[idx], float(job.part.coded_size_m))


def _pnp_corners(intr: Intrinsics, xyz: np.ndarray, uv: np.ndarray, approx: np.ndarray) -> tuple[np.ndarray, float]:
    """``cam_from_part`` (4, 4) from marker corners ``xyz: (q, 3)`` seen at ``uv: (q, 2)``, and its rms (px).

    Candidates: Levenberg-Marquardt from ``approx``, and a global solution (IPPE's two for one
    marker's four coplanar corners, SQPnP otherwise), each polished by Levenberg-Marquardt. The
    smallest reprojection error wins; near-ties (the planar ambiguity) go to the one closest to ``approx``.
    """
    xyz = np.ascontiguousarray(xyz, dtype=np.float64)
    uv = np.ascontiguousarray(uv, dtype=np.float64)
    K, dist = intr.K, intr.dist_coeffs
    starts = [(cv2.Rodrigues(np.asarray(approx[:3, :3], dtype=float))[0], approx[:3, 3].reshape(3, 1).copy())]
    try:
        flag = cv2.SOLVEPNP_IPPE if len(xyz) == 4 else cv2.SOLVEPNP_SQPNP
        _, rv, tv, _ = cv2.solvePnPGeneric(xyz, uv, K, dist, flags=flag)
        starts += list(zip(rv, tv))
    except cv2.error:
        pass
    cands = []
    for r0, t0 in starts:
        ok, r, tt = cv2.solvePnP(xyz, uv, K, dist, np.array(r0, dtype=float).reshape(3, 1).copy(),
                                 np.array(t0, dtype=float).reshape(3, 1).copy(), useExtrinsicGuess=True,
                                 flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            continue
        T = make_pose(cv2.Rodrigues(r)[0], tt.ravel())
        if np.any(xyz @ T[2, :3] + T[2, 3] <= 0):
            continue
        rms = float(np.sqrt(np.mean(np.sum((project(intr, T, xyz) - uv) ** 2, axis=1))))
        cands.append((rms, pose_error(T, approx)[1], T))
    if not cands:
        raise CalibrationError("part placement: no pose of the camera fits the coded markers' corners")
    best = min(c[0] for c in cands)
    rms, _, T = min((c for c in cands if c[0] <= 2.0 * best + 0.5), key=lambda c: c[1])
    return T, rms


def _placement_from_codes(job: LoadedJob, B: np.ndarray, markers: list, dots: list,
                          occluder: Occluder) -> tuple[np.ndarray, dict]:
    """``base_from_part`` from the coded markers' corners in every image, with the hand-eye held fixed.

    Every view of a marker gives a placement by itself (PnP on its four corners, then
    ``B_i X A``). Views that agree (within ``PLACEMENT_AGREE_M``, rotations weighted by the part's
    radius) form a hypothesis; each of the three largest is adjusted on the corners of its views
    (joined by every view whose corners it fits within ``PLACEMENT_MARKER_RMS_PX``), and the dots
    decide: the hypothesis under which most dots are found where they should be wins. A marker
    whose code is on another target than the targets file says forms a wrong hypothesis that the
    dots reject; its views are reported in ``dropped``.
    """
    X, Y0 = job.spec.flange_from_cam(), job.spec.base_from_part()
    intr = job.intrinsics
    t = job.part.targets
    views = [(i, int(k), uv) for i, (idx, corners, _) in enumerate(markers) for k, uv in zip(idx, corners)]
    if len(views) < 2:
        raise CalibrationError(f"part placement: {len(views)} view(s) of the part's coded markers in {len(B)} images "
                               "(2 needed); check that the markers are on the part and lit, and that base_from_part "
                               "is within a few centimetres")
    xyz = _marker_corners_part(job, np.array([v[1] for v in views]))  # (v, 4, 3)
    uv = np.array([v[2] for v in views])  # (v, 4, 2)
    img = np.array([v[0] for v in views])
    hyp = np.array([B[i] @ X @ _pnp_corners(intr, p, u, invert(X) @ invert(B[i]) @ Y0)[0]
                    for i, p, u in zip(img, xyz, uv)])
    r = job.part.radius
    dist = np.array([[np.dot(pose_error(a, b), [1.0, r]) for b in hyp] for a in hyp])
    agree = dist < PLACEMENT_AGREE_M
    seeds, seen = [], set()
    for j in np.argsort(-agree.sum(axis=1), kind="stable"):
        key = frozenset(np.flatnonzero(agree[j]).tolist())
        if key not in seen:
            seen.add(key)
            seeds.append((j, np.flatnonzero(agree[j])))
    best = None
    for j, members in seeds[:3]:
        Y, use = hyp[j], members
        for _round in range(3):
            if len(use) < 2:
                break
            res = refine_hand_eye(intr, B, np.repeat(img[use], 4), xyz[use].reshape(-1, 3), uv[use].reshape(-1, 2),
                                  X, Y, HandEyeOptions(sigma_px=PLACEMENT_CORNER_SIGMA_PX, fix_flange_from_cam=True))
            Y = res.base_from_target
            rms = np.array([np.sqrt(np.mean(np.sum((project(intr, invert(X) @ invert(B[i]) @ Y, p) - u) ** 2, axis=1)))
                            for i, p, u in zip(img, xyz, uv)])
            new = np.flatnonzero(rms < PLACEMENT_MARKER_RMS_PX)
            if np.array_equal(new, use):
                break
            use = new
        if len(use) < 2:
            continue
        score = sum(len(_identify_dots(job, d, invert(X) @ invert(b) @ Y, occluder)[0]) for b, d in zip(B, dots))
        if best is None or score > best[0]:
            best = (score, Y, use, rms, res.sigma0_px)
    if best is None:
        raise CalibrationError("part placement: no two views of the coded markers agree about where the part is; "
                               "check the code column of the targets file against the markers on the part")
    score, Y, use, rms, s0 = best
    if score == 0:  # the markers agree, but no dot is where they put the part (F3, decision 0064)
        raise InputError(f"part placement: the coded markers were not found where the part's dots expect them: no dot "
                         f"is where {len(use)} agreeing marker view(s) put the part; check that the part is the job's "
                         "part, right side up and within a few centimetres of [cell] base_from_part, and that the "
                         "targets file's code column matches the markers on it")
    dropped = [{"image": int(img[v]), "target": t.ids[views[v][1]], "code": int(t.code[views[v][1]]),
                "rms_px": float(rms[v])} for v in range(len(views)) if v not in set(use.tolist())]
    return Y, {"base_from_part": Y, "n_markers": int(len(use)), "images": int(len(set(img[use].tolist()))),
               "sigma0_px": s0, "max_marker_rms_px": float(rms[use].max()), "dropped": dropped,
               "used_targets": sorted({t.ids[views[v][1]] for v in use.tolist()}),
               "views_target": [t.ids[v[1]] for v in views],
               "hypotheses": min(3, len(seeds)), "dots_found": int(score), "_views": (img, xyz, uv)}


def _free_dots(img: np.ndarray, all_corners: np.ndarray) -> np.ndarray:
    """Dot centres (k, 2) outside every detected marker's square (grown by a third)."""
    det = detect_retro_targets(img, DetectionOptions())
    if len(all_corners) == 0:
        return det.uv
    return det.uv[~imaging.inside_any(det.uv, all_corners, grow=imaging.MARKER_GROW)]


def _identify_dots(job: LoadedJob, det_uv: np.ndarray, cam_from_part: np.ndarray,
                   occluder: Occluder, lens: Intrinsics | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Name the dots ``det_uv: (k, 2)`` with the pose ``cam_from_part``; ``(target index (m,), uv (m, 2))``.

    Only dots in view from that pose are offered to the matcher (a hidden dot would steal a visible
    neighbour's detection); dots seen more obliquely than the job's ``incidence_max_deg`` (their
    centres are biased by up to 0.3 px on grazing views) and dots whose rim an edge of the part clips
    are not measured; the centres are corrected for the eccentricity of the dot's ellipse.
    """
    t = job.part.targets
    m = imaging.name_dots(det_uv, job.part, lens or job.intrinsics, cam_from_part, occluder,
                          max_dist_px=PLACEMENT_MATCH_PX)
    sight = invert(cam_from_part)[:3, 3] - t.xyz[m.target]
    cos_inc = np.sum(sight * t.normals[m.target], axis=1) / np.linalg.norm(sight, axis=1)
    steep = cos_inc >= np.cos(np.deg2rad(job.spec.planning.incidence_max_deg))
    return m.target[steep], m.uv[steep]


def _placement_stations(job: LoadedJob, n: int) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Overview stations around the nominal part, ``(part_from_cam (n, 4, 4), joints (n, 6), markers left out)``
    in visiting order.

    Planned by :func:`plan_stations` (the inspection's planner and reachability) for the coded
    markers alone, with a wide image margin (the part may be centimetres off its nominal place)
    and every marker in two images (more stations than ``n`` when the markers need them). A marker that
    no two reachable candidates see (under a flange, on a face turned away from the robot) is left out and
    named; fewer than :data:`PLACEMENT_MIN_MARKERS` markers left is an error naming them.
    """
    coded = job.part.targets.kind == "coded"
    if not coded.any():
        raise InputError(f"{job.part.name}: part placement needs coded markers on the part (job.n_coded or the "
                         "targets file's code column)")
    last = None
    for k in range(n, n + 5):  # more stations when n cannot show every marker twice
        try:
            sp = plan_stations(job, k, min_rays=2, max_tilt_rad=np.deg2rad(60.0), incidence_max_rad=np.deg2rad(60.0),
                               sigma_px=job.spec.camera.sigma_px, n_candidates=300, seed=job.spec.job.seed,
                               targets=coded, margin_px=150.0, allow_unmeasurable=True)
            break
        except ReachabilityError as exc:
            last = exc
    else:
        raise ReachabilityError(f"part placement: {last}")
    unseen = sorted({i for p in sp.plans for i in p.unmeasurable_target_ids})
    n_coded = int(coded.sum())
    if n_coded - len(unseen) < min(PLACEMENT_MIN_MARKERS, n_coded):
        raise ReachabilityError(
            f"part placement: only {n_coded - len(unseen)} of the part's {n_coded} coded markers can be seen twice from "
            f"the reachable overview stations ({PLACEMENT_MIN_MARKERS} needed; not seen: {', '.join(unseen)}): put "
            "markers where the robot sees the part from above, or move the part within the robot's reach")
    return sp.part_from_cam, sp.joints, unseen
