"""The lens: the interior orientation the adjustment starts from, and the camera model it estimates
(decision 0054: a real lens is not its data sheet)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from scipy.stats import chi2

from calibration.alignment import similarity_fit
from calibration.bundle import bundle_adjust
from calibration.camera import Intrinsics
from calibration.errors import CalibrationError
from cell.stages.screen import Resection, Screening, resect, screen_network


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
    return replace(nominal, fx_px=f, fy_px=f * nominal.fy_px / nominal.fx_px, cx_px=a[2], cy_px=a[3])


#: a start whose screening takes more than this share of the observations as gross is tried against the nominal lens
START_GROSS_SHARE = 0.10


def choose_start(job, cal_doc: dict, obs_image: np.ndarray, obs_target: np.ndarray, obs_uv: np.ndarray,
                 poses_all: np.ndarray, ids: list[str], radial_named: bool = False
                 ) -> tuple[Intrinsics, Resection, Screening, dict]:
    """The interior orientation the adjustment starts from, with the poses resected with it.

    :func:`initial_intrinsics` (Faugeras-Toscani's median), unless its screening takes more than
    :data:`START_GROSS_SHARE` of the observations as gross and the nominal lens's takes fewer: a wrong start makes
    good rays disagree, and the screening would leave them out. Returns ``(intr0, resection, doc)``, ``doc`` for
    bundle.json ``start``: which interior orientation and, for each tried, the share of observations screened gross.
    The chosen start's screening is returned too: the adjustment's first round uses it (not screened twice).
    ``radial_named``: MEASURE named some images with a radial lens of their own (the job does not state the lens's
    distortion): the start with k1, k2 fitted to every image (:func:`radial_start`) is tried too, and taken when
    its screening takes fewer observations as gross (decision 0054).
    """
    nominal = job.intrinsics
    pairs = [tuple(bar[:2]) for bar in job.scale_bars]

    def tried(intr):
        rs = resect(intr, poses_all, obs_image, job.part.targets.xyz[obs_target], obs_uv)
        scr = screen_network(obs_image, obs_target, obs_uv, intr, rs.poses, len(ids), scale_pairs=pairs,
                             drop_images=rs.left_out, ids=ids)
        return rs, scr, len(scr.obs) / max(len(obs_uv), 1)

    intr0 = initial_intrinsics(job, cal_doc)
    rs, scr, gross = tried(intr0)
    name = "nominal lens" if intr0 is nominal else "Faugeras-Toscani (median of the accepted images)"
    doc = {"interior": name, "fx_px": float(intr0.fx_px), "gross_share": {name: gross}}
    if intr0 is not nominal and gross > START_GROSS_SHARE:
        rs_n, scr_n, gross_n = tried(nominal)
        doc["gross_share"]["nominal lens"] = gross_n
        if gross_n < gross:
            doc |= {"interior": "nominal lens", "fx_px": float(nominal.fx_px),
                    "reason": f"Faugeras-Toscani's interior orientation (fx {intr0.fx_px:.1f} px) left {gross:.0%} of "
                              f"the observations gross in the screening, the nominal lens (fx {nominal.fx_px:.1f} px) "
                              f"{gross_n:.0%}: the adjustment starts from the nominal lens"}
            intr0, rs, scr, gross = nominal, rs_n, scr_n, gross_n
    # MEASURE named images with a radial lens of their own: the job's lens is not the camera's. Without
    # self-calibration the job's lens is held as it is: no other start (the adjustment's fit says how it fits)
    if radial_named and job.spec.camera.self_calibrate:
        lens = radial_start(intr0, rs, obs_image, job.part.targets.xyz[obs_target], obs_uv)
        rs_r, scr_r, gross_r = tried(lens)
        name = f"{doc['interior']} with a radial lens fitted to every image (k1 {lens.k1:+.4f}, k2 {lens.k2:+.4f})"
        doc["gross_share"][name] = gross_r
        if gross_r < gross:
            doc |= {"interior": name, "fx_px": float(lens.fx_px), "reason": f"the job's lens left {gross:.0%} of the observations gross in the "
                                                f"screening, the same with a radial lens fitted to the images "
                                                f"{gross_r:.0%}: MEASURE named images with a radial lens of their "
                                                "own, and the adjustment starts from it"}
            return lens, rs_r, scr_r, doc
    return intr0, rs, scr, doc


def radial_start(intr: Intrinsics, rs: Resection, obs_image: np.ndarray, xyz: np.ndarray, uv: np.ndarray,
                 rounds: int = 2) -> Intrinsics:
    """``intr`` with its principal distance, k1 and k2 fitted (robustly, soft L1 at 2 px) to every observation at the resected poses and the
    targets' CAD places, the images resected again with it, ``rounds`` times (decision 0054): a start for a lens
    whose distortion the job does not state, so that the screening does not take its outer dots for gross."""
    from scipy.optimize import least_squares

    from calibration.camera import project

    poses = rs.poses
    for _ in range(rounds):
        def lens(k):
            return replace(intr, fx_px=intr.fx_px * k[0], fy_px=intr.fy_px * k[0], k1=k[1], k2=k[2])

        def resid(k):
            return np.concatenate([(project(lens(k), poses[i], xyz[obs_image == i]) - uv[obs_image == i]).ravel()
                                   for i in np.unique(obs_image)])
        intr = lens(least_squares(resid, [1.0, intr.k1, intr.k2], loss="soft_l1", f_scale=2.0, x_scale="jac").x)
        poses = resect(intr, poses, obs_image, xyz, uv).poses
    return intr


def camera_model(job) -> str:
    """The bundle's camera model: ``[camera] lens_model`` when self-calibrating (brown: OPENCV_K3, radial: RADIAL);
    without self-calibration the model that holds the nominal lens as it is (decision 0054)."""
    c = job.spec.camera
    if c.self_calibrate:
        return "OPENCV_K3" if c.lens_model == "brown" else "RADIAL"
    return "OPENCV_K3" if job.intrinsics.has_distortion or job.intrinsics.fx_px != job.intrinsics.fy_px else "PINHOLE"


#: the brown terms a radial lens model leaves out (decision 0054)
BROWN_EXTRA = ("fy - fx", "k3", "p1", "p2")
#: they are said when jointly significant at this level (chi-square, four degrees of freedom)
RADIAL_TEST_ALPHA = 1e-3


def radial_check(res, img, tgt, uv, options, config) -> dict | None:
    """With ``lens_model = "radial"``: does the lens have terms the radial model does not carry? One more adjustment
    of the observations the radial one kept, with the brown model (no data snooping), and a joint test of the four
    terms the radial model holds at zero (fy - fx, k3, p1, p2) on their covariance. Returns bundle.json's
    ``lens.radial_check`` (None for any other model): the estimates, their sigmas, the statistic, and how far the
    brown adjustment moves the targets (after a rigid fit of one onto the other), in um and in their own sigmas."""
    if config.camera_model != "RADIAL" or not config.refine_distortion:
        return None
    keep = ~res.rejected
    sig = None if res.obs_sigma_px is None else np.asarray(res.obs_sigma_px)[keep]
    try:
        brown = bundle_adjust(img[keep], tgt[keep], uv[keep], res.intrinsics, res.cam_from_part, res.points,
                              replace(options, snooping=False, interior_stability=False),
                              replace(config, camera_model="OPENCV_K3"),
                              obs_sigma_px=sig)
    except CalibrationError as e:  # the check could not run: said, not taken for a clean lens
        return {"model": "radial", "tested": False, "reason": f"the brown adjustment failed: {e}"}
    names = list(brown.intrinsics_names)
    J = np.zeros((4, len(names)))
    for row, terms in enumerate(({"fy": 1.0, "fx": -1.0}, {"k3": 1.0}, {"p1": 1.0}, {"p2": 1.0})):
        for name, c in terms.items():
            J[row, names.index(name)] = c
    i = brown.intrinsics
    est = np.array([i.fy_px - i.fx_px, i.k3, i.p1, i.p2])
    cov = J @ brown.intrinsics_cov @ J.T
    stat = float(est @ np.linalg.lstsq(cov, est, rcond=None)[0])
    crit = float(chi2.isf(RADIAL_TEST_ALPHA, 4))
    ok = np.isfinite(res.points).all(axis=1) & np.isfinite(brown.points).all(axis=1)
    _, R, t = similarity_fit(brown.points[ok], res.points[ok])
    moved = np.zeros(len(ok))
    moved[ok] = np.linalg.norm(brown.points[ok] @ R.T + t - res.points[ok], axis=1)
    m = np.zeros(len(ok))
    d = brown.points[ok] @ R.T + t - res.points[ok]
    m[ok] = np.sqrt(np.einsum("ni,nij,nj->n", d, np.linalg.pinv(res.cov[ok]), d))
    doc = {"model": "radial", "tested": True, "terms": list(BROWN_EXTRA), "estimate": est.tolist(),
           "sigma": np.sqrt(np.diag(cov)).tolist(), "statistic": stat, "critical": crit, "alpha": RADIAL_TEST_ALPHA,
           "significant": bool(stat > crit), "targets_moved_max_m": float(moved.max()),
           "targets_moved_median_m": float(np.median(moved[ok])), "targets_moved_max_sigma": float(m.max()),
           "targets_moved_median_sigma": float(np.median(m[ok]))}
    if doc["significant"]:
        z = np.abs(est) / np.sqrt(np.diag(cov))
        top = ", ".join(f"{n} {e:+.3g} ({k:.1f} sigma)" for n, e, k in zip(BROWN_EXTRA, est, z) if k > 3)
        doc["note"] = (f"the lens has terms the radial model does not carry ({top or 'jointly'}; chi-square "
                       f"{stat:.1f} > {crit:.1f}): with them the targets move by up to "
                       f"{1e6 * doc['targets_moved_max_m']:.1f} um, {doc['targets_moved_max_sigma']:.1f} of their "
                       "sigmas, so the coordinates and their uncertainty are not those of this lens; set [camera] "
                       "lens_model = \"brown\" (the default)")
    return doc


def stability_doc(st: dict | None, images: list[dict], kept_images, pixel_size_m: float | None) -> dict:
    """bundle.json's ``lens.interior_stability``: the bundle's test of one lens for all images against a change of the
    principal distance and point during the acquisition (:func:`calibration.bundle.stability.interior_stability`),
    with the change point named by its images and stations (``images``: observations.json's, ``kept_images``: the
    adjustment's images among them, in capture order), the principal distance's change in um, and ``note`` (what
    ADJUST warns and report.json ``lens.stability_note`` carries) when it is significant; a test that did not run says
    why (``tested`` False, ``reason``)."""
    if st is None:
        return {"tested": False, "significant": False, "reason": "the adjustment did not run the test"}
    doc = dict(st)
    if not st.get("tested"):
        return doc
    k = int(st["first_changed"])
    before, after = (images[int(kept_images[k - 1])], images[int(kept_images[k])])
    doc["between"] = [{"image": x["image"], "station": x["station"]} for x in (before, after)]
    doc["statistics"] = {images[int(kept_images[int(j)])]["image"]: t for j, t in st["statistics"].items()}
    d, s = st["change_px"], st["change_sigma_px"]
    um = 1e6 * pixel_size_m if pixel_size_m else None
    doc["principal_distance_change_um"] = d[0] * um if um else None
    doc["principal_distance_change_sigma_um"] = s[0] * um if um else None
    if st["significant"]:
        pd = (f"{d[0] * um:+.2f} um (+- {s[0] * um:.2f})" if um else f"{d[0]:+.3f} px (+- {s[0]:.3f})")
        doc["note"] = (f"the lens changed during the acquisition between images {before['image']} (station "
                       f"{before['station']}) and {after['image']} (station {after['station']}): principal distance "
                       f"{pd}, principal point ({d[1]:+.2f}, {d[2]:+.2f}) px (+- {s[1]:.2f}, {s[2]:.2f}); chi-square "
                       f"{st['statistic']:.1f} > {st['critical']:.1f}: its focus or zoom ring moved, or the camera's "
                       "mount; the coordinates rest on one lens for all images and their uncertainty does not carry the "
                       "change; lock the lens's rings and run the job again")
    return doc


def say_stability(ctx, st: dict) -> None:
    """ADJUST's console and run log: a lens that changed during the acquisition (a warning), a test that could not
    run (said, not taken for a stable lens)."""
    if st.get("note"):
        ctx.log.log("warning", st["note"])
        ctx.say(f"  WARNING {st['note']}")
    elif not st.get("tested"):
        msg = f"the lens's stability over the acquisition was not tested: {st.get('reason')}"
        ctx.log.log("info", msg)
        ctx.say(f"  {msg}")


#: a principal distance this far from the nominal focal length is said (focusing an 8 mm lens at 300-700 mm moves
#: it by 1.2-2.7 %; a lens of another focal length is 25 % or more off: calibration.plausibility refuses it)
FOCAL_NOTE = 0.05


def lens_doc(job, bundle: dict) -> dict:
    """report.json's ``lens``: the lens the adjustment estimated (or held), against the job's nominal one: the model
    and its terms, the principal distance and point with their sigmas, the distortion terms, how far the distortion
    moves the image's corner, the radial model's check (:func:`radial_check`); ``note``: a radial model the images
    refute (the statement is not this lens's); ``focal_note``: a principal distance far from the nominal focal length."""
    b = bundle.get("lens") or {}
    intr = Intrinsics.from_dict(bundle["intrinsics"])
    nominal = job.intrinsics
    names = list(bundle.get("intrinsics_refined") or [])
    sig = dict(zip(names, bundle.get("intrinsics_sigma") or []))
    mm = (nominal.pixel_size_m or 0.0) * 1e3
    f_sig = sig.get("fx", sig.get("f"))
    corner = np.array([[-0.5 - intr.cx_px, -0.5 - intr.cy_px], [intr.width - 0.5 - intr.cx_px, -0.5 - intr.cy_px],
                       [-0.5 - intr.cx_px, intr.height - 0.5 - intr.cy_px],
                       [intr.width - 0.5 - intr.cx_px, intr.height - 0.5 - intr.cy_px]]) / [intr.fx_px, intr.fy_px]
    shift = (intr.distort(corner) - corner) * [intr.fx_px, intr.fy_px]
    doc = {"model": b.get("model"), "camera_model": b.get("camera_model"), "estimated": names,
           "focal_length_mm": intr.fx_px * mm if mm else None, "focal_length_sigma_mm": f_sig * mm if mm and f_sig
           else None, "nominal_focal_length_mm": nominal.fx_px * mm if mm else None,
           "principal_distance_px": [intr.fx_px, intr.fy_px], "principal_point_px": [intr.cx_px, intr.cy_px],
           "principal_point_sigma_px": [sig.get("cx"), sig.get("cy")],
           "distortion": {k: getattr(intr, k) for k in ("k1", "k2", "k3", "p1", "p2")},
           "distortion_sigma": {k: sig.get(k) for k in ("k1", "k2", "k3", "p1", "p2")},
           "distortion_at_corner_px": float(np.max(np.linalg.norm(shift, axis=1))),
           "radial_check": b.get("radial_check"), "note": None, "focal_note": None}
    doc["note"] = (b.get("radial_check") or {}).get("note")  # the statement is not this lens's
    # one lens for all images, tested against a change during the acquisition (decision 0066)
    doc["interior_stability"] = {k: v for k, v in (b.get("interior_stability") or {}).items() if k != "statistics"} \
        or None
    doc["stability_note"] = (b.get("interior_stability") or {}).get("note")
    cells = bool((getattr(job, "cell", None) or {}).get("lens"))  # the job started from the cell's lens (decision 0056)
    held = b.get("held_uncertainty") or {}
    # the held lens's covariance carried (decision 0056); each target's share stays in bundle.json
    doc["held_uncertainty"] = {k: v for k, v in held.items() if k != "added_variance_m2"} if held else None
    if cells and not names and not held.get("carried"):
        why = held.get("why") or "the cell file states no covariance for it"
        doc["held_note"] = (f"the lens is held as the cell's hand-eye calibration estimated it ([cell] camera_lens of "
                            f"the cell file), and its own uncertainty is not in the targets' covariances ({why}): they "
                            "are optimistic by it (decision 0056); calibrate the hand-eye again (its lens is then "
                            "written with its covariance), or set self_calibrate = true to refine the lens on this "
                            "job's images")
    off = intr.fx_px / nominal.fx_px - 1
    if abs(off) > FOCAL_NOTE:  # said, not a fault: the measurement is the images' own
        says = "the cell's calibrated lens says" if cells else "[camera] focal_length_mm says"
        doc["focal_note"] = (f"the lens's principal distance is {intr.fx_px * mm:.3f} mm where {says} "
                             f"{nominal.fx_px * mm:.3g} ({100 * off:+.1f} %): is this the lens "
                             "mounted, and focused as planned? The plan's visibility and prediction were made for the "
                             "nominal lens" if mm else f"the lens's principal distance is {100 * off:+.1f} % off the "
                             "nominal focal length")
    return doc


#: a weight the blur measured against the adjusted lens changes by more than this share makes the adjustment run again
LENS_BLUR_READJUST = 0.01


def observed_moments(obs_doc: dict) -> np.ndarray | None:
    """Each observed dot's measured second moments, half their trace (px^2, observations.json ``moments_px2``),
    ``(q,)`` in the order of :func:`cell.stages.adjust.observation_arrays`; NaN for a clipped dot. None when no image
    has them (a job measured before decision 0054)."""
    out, some = [], False
    for o in obs_doc["images"]:
        k = len(o["ids"])
        v = o.get("moments_px2")
        ok = v is not None and len(v) == k
        some |= ok
        out.append(np.array([np.nan if x is None else x for x in v], dtype=float) if ok else np.full(k, np.nan))
    return np.concatenate(out) if some and out else None


def lens_blur(job, obs_doc: dict, sel: np.ndarray, img: np.ndarray, tgt: np.ndarray, res) -> np.ndarray | None:
    """Each adjusted observation's blur (px^2, ``(q,)`` for ``img, tgt``, the observations ``sel`` keeps) measured
    against the lens, poses and targets the adjustment ``res`` found: the dot's measured moments less those of the
    ellipse it images through that lens (its principal distance, and the distortion's local stretch) and the pixel's.

    MEASURE's ``blur_px2`` was taken against the nominal lens at the robot's pose: a real lens's principal distance
    0.75 % longer and its barrel distortion made the example's blur read 0.84 px^2 in the image's middle and -0.11 at
    its corners where the rendered blur is the same everywhere (decision 0054). None without measured moments."""
    from calibration.targets import PIXEL_VARIANCE_PX2, ellipse_moments

    moments = observed_moments(obs_doc)
    if moments is None:
        return None
    m = moments[sel]
    out = np.full(len(m), np.nan)
    intr = res.intrinsics
    pinhole = intr.without_distortion()
    f = np.diag([intr.fx_px, intr.fy_px])
    t = job.part.targets
    radius = job.part.target_diameter_m / 2
    for i in np.unique(img):
        k = np.flatnonzero((img == i) & np.isfinite(m) & np.isfinite(res.points[tgt]).all(axis=1))
        if not len(k):
            continue
        T = res.cam_from_part[i]
        xyz = res.points[tgt[k]]
        P = ellipse_moments(pinhole, T, xyz, t.normals[tgt[k]], radius)
        pc = xyz @ T[:3, :3].T + T[:3, 3]
        J = f @ intr.distortion_jacobian(pc[:, :2] / pc[:, 2:3]) @ np.linalg.inv(f)
        out[k] = m[k] - 0.5 * np.trace(J @ P @ np.swapaxes(J, 1, 2), axis1=1, axis2=2) - PIXEL_VARIANCE_PX2
    return out


#: a centre the adjusted lens moves by more than this share of its sigma makes the adjustment run again
LENS_CENTRE_READJUST = 0.05


def observed_eccentricity(obs_doc: dict) -> np.ndarray | None:
    """The eccentricity MEASURE took off each centre (px, observations.json ``eccentricity_px``), ``(q, 2)`` in the
    order of :func:`cell.stages.adjust.observation_arrays`; None when an image lacks it (measured before decision
    0054: its centres stay as measured)."""
    out = []
    for o in obs_doc["images"]:
        e = o.get("eccentricity_px")
        if e is None or len(e) != len(o["ids"]):
            return None
        out.append(np.asarray(e, dtype=float).reshape(-1, 2))
    return np.concatenate(out) if out else None


def _through(intr: Intrinsics, uv: np.ndarray) -> np.ndarray:
    """Pinhole pixel positions ``uv: (..., 2)`` of ``intr`` without distortion, through its distortion."""
    f = np.array([intr.fx_px, intr.fy_px])
    c = np.array([intr.cx_px, intr.cy_px])
    return intr.distort((uv - c) / f) * f + c


def lens_centres(job, obs_doc: dict, sel: np.ndarray, img: np.ndarray, tgt: np.ndarray, res) -> np.ndarray | None:
    """What to add to each adjusted observation's centre ``(q, 2)`` px (for ``img, tgt``, the observations ``sel``
    keeps): MEASURE's eccentricity (the nominal lens, the robot's pose, no distortion) given back and the
    eccentricity through the lens, poses and targets the adjustment ``res`` found taken off.

    Through a distorting lens a dot's centre is not the distorted image of its ellipse's centre: the distortion's
    curvature and the stretch of its area move a uniformly bright dot's centroid, and the centre of the ellipse fitted
    to its contour alike, by ``D''[M] / 2 + J M grad ln det J`` (``M`` its ellipse's second moments;
    :func:`lens_eccentricity`), and the ellipse's own offset from the projected centre is stretched by the
    distortion's Jacobian. On a generated plate with k1 = -0.116, the targets intersected from their observations at
    the true poses and lens were 2.2x their statement before (decision 0054). None without MEASURE's eccentricity."""
    applied = observed_eccentricity(obs_doc)
    if applied is None:
        return None
    applied = applied[sel]
    out = np.zeros((len(tgt), 2))
    t = job.part.targets
    for i in np.unique(img):
        k = np.flatnonzero((img == i) & np.isfinite(res.points[tgt]).all(axis=1))
        if len(k):
            out[k] = applied[k] - lens_eccentricity(res.intrinsics, res.cam_from_part[i], res.points[tgt[k]],
                                                    t.normals[tgt[k]], job.part.target_diameter_m / 2)
    return out


def lens_eccentricity(intr: Intrinsics, cam_from_part: np.ndarray, xyz: np.ndarray, normals: np.ndarray,
                      radius_m: float) -> np.ndarray:
    """Each dot's measured centre less the image of its target's centre through the lens ``intr``, ``(k, 2)`` px:
    the eccentricity of :func:`calibration.targets.eccentricity_bias` with the distortion's stretch and curvature
    (:func:`lens_centres`), for a centroid and a contour's ellipse alike."""
    from calibration.targets import _disc_conics

    H, C = _disc_conics(intr.without_distortion(), cam_from_part, xyz, normals, radius_m)
    A, b = C[:, :2, :2], C[:, :2, 2]
    centre = -np.linalg.solve(A, b[..., None])[..., 0]
    s = np.einsum("ni,ni->n", b, np.linalg.solve(A, b[..., None])[..., 0]) - C[:, 2, 2]
    M = s[:, None, None] * np.linalg.inv(A) / 4.0  # the ellipse's second moments
    lam, V = np.linalg.eigh(M)
    axes = V * np.sqrt(np.maximum(lam, 0.0))[:, None, :]  # columns: the scaled axes
    D0 = _through(intr, centre)
    curve = sum(_through(intr, centre + axes[:, :, j]) + _through(intr, centre - axes[:, :, j]) - 2 * D0
                for j in range(2))
    # a centroid is the mean over the dot's image, whose area element is det J of the pinhole ellipse's: the
    # distortion's stretch weighs the side it enlarges (to second order J M grad ln det J). The ellipse fitted to the
    # dot's contour moves by the same to second order (the first harmonic of the rim's normal displacement: M grad
    # tr J + D''[M] / 2), so one formula serves both (tests/test_lens.py checks both against the exact image)
    f = np.array([intr.fx_px, intr.fy_px])
    x = (centre - np.array([intr.cx_px, intr.cy_px])) / f
    h = 1e-4
    grad = np.stack([(np.log(np.linalg.det(intr.distortion_jacobian(x + d)))
                      - np.log(np.linalg.det(intr.distortion_jacobian(x - d)))) / (2 * h)
                     for d in (np.array([h, 0.0]), np.array([0.0, h]))], axis=-1) / f
    J = f[:, None] * intr.distortion_jacobian(x) / f[None, :]
    return D0 + 0.5 * curve + np.einsum("nab,nbc,nc->na", J, M, grad) - _through(intr, H[:, :2, 2] / H[:, 2:3, 2])
