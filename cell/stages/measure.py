"""MEASURE: sub-pixel target detection and identification in every image; observations.json.

observations.json: ``images``: list of {``station``, ``image``, ``ids``, ``uv`` (k, 2 px), ``cov_px2`` (k, 2, 2:
each centre's covariance from the detector, px^2, ``calibration.dots.Detections.cov``), ``noise_levels`` ([v0, s]:
the pixel noise's variance ``v0 + s v`` at grey level ``v`` that ``cov_px2`` propagated, measured on the image's own
dots; ``s`` 0 where too few dots carried it and the image's one figure stood for every pixel; decision 0047),
``bg_cov_px2`` (k, 2, 2:
the detector's bound on each centre's error from a background that is not a plane, px^2,
``Detections.background_cov``; ADJUST adds its share to the image precision), ``clipped_share`` (k,),
``ellipse_centre`` (k, bool: the centre is the ellipse of the dot's contour, not its centroid; decision 0037),
``blur_px2`` (k: the blur each dot's image shows; decision 0049), ``moments_px2`` (k: half the trace of its second
moments) and ``eccentricity_px`` (k, 2: the eccentricity taken off its centre), from which ADJUST takes the blur and
the eccentricity again through the adjusted lens (decision 0054), ``clip_bound_px`` (k, 2: how far a clipped dot's
centre may be off for its unknown level, zero for the others; ADJUST carries it; decision 0050), ``outline`` (k, 2:
``[chi2, n]`` of each dot's contour about its fitted ellipse) and ``centroid_chi2`` (k: its centroid against that
ellipse's centre; null for a dot centred by its ellipse): a target's print is judged by them (decision 0051), ``smear``
(the directional spread the image's dots share beyond their ellipses, :func:`calibration.smear.image_smear`; an image
whose dots are smeared, the camera moving during the exposure, has every named dot dropped; decision 0067), counts,
``background_mask`` (only when ``[camera] background_mask = "cad"``: "cad", or "none (...)" for an image measured
unmasked because too few dots were named to label it from; docs/decisions/0035),
``dropped``: list of {``id``, ``reason``} (dots that were named and then left unnamed: partly hidden,
shape unlike the target's ellipse, the image's naming inconsistent, a background ring too small to bound the
centre's error, the image smeared), ``resection_median_px``};
``n_dropped`` (all images) and ``dropped_by_reason`` at the top level.
"""
from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from calibration.camera import invert
from calibration.errors import CalibrationError
from calibration.smear import deviatoric_excess, image_smear
from calibration.targets import ellipse_moments, refine_pose_pnp
from cell.record.jobfolder import atomic_write_json
from cell.stages.imaging import detection_options, measure_image_detections, surface_labeller
from planning.visibility import Occluder


def run(ctx, keep: bool = False) -> None:
    """Detect, centre and identify the targets in every image (cell.stages.imaging.measure_image).

    ``keep``: images already in observations.json keep their measurement (the closed loop's rounds).

    Dots are named by projecting the nominal targets with the robot's pose and the hand-eye, refined
    by the coded targets (solvePnP) where at least four are seen; coded targets are not measured.
    """
    job = ctx.job
    acq = ctx.folder.read_json("acquisition.json")
    ids_all = job.part.targets.ids
    bfp, ffc = job.spec.base_from_part(), job.spec.flange_from_cam()
    occluder = Occluder(job.part.mesh)
    detection = detection_options(job.spec.camera)
    surfaces = surface_labeller(job.spec.camera, job.part)  # [camera] background_mask (decision 0035)
    # images measured before (a closed-loop round adds images to a measured network): kept as they are
    path = ctx.folder.file("observations.json")
    before = {o["image"]: o for o in ctx.folder.read_json("observations.json")["images"]} if keep and path.exists() else {}
    measured = []  # (k, acquisition record, measurement, counts, the dots' excess over their ellipses)
    for k, im in enumerate(acq["images"]):
        if im["image"] in before:
            measured.append((k, im, None, None, None))
            continue
        ctx.progress("measure", k / len(acq["images"]))
        kept = ctx.cache.get("frames", {}).get(im["image"])  # this session's ACQUIRE: the same pixels, decoded
        img = kept[1] if kept is not None and kept[0] == im["sha256"] else \
            cv2.imread(str(ctx.folder.file(im["image"])), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise CalibrationError(f"{im['image']}: cannot read the image")
        cam_from_part = invert(invert(bfp) @ np.asarray(im["base_from_flange"], dtype=float) @ ffc)
        m, counts, excess = measure_with_excess(img, job.part, job.intrinsics, cam_from_part, occluder, detection,
                                                job.spec.job.coded_family, surfaces)
        measured.append((k, im, m, counts, excess))
    smears = judge_smears([e for *_, e in measured], job.part, job.intrinsics)  # decision 0067
    out = []
    for (k, im, m, counts, _), smear in zip(measured, smears):
        if m is None:
            out.append(before[im["image"]])
            continue
        if smear.get("smeared"):  # its centres are moved along the smear, which no sigma covers: none measured
            m = _left_out(m, f"smeared: {smear_words(smear)}")
            msg = smeared_message(im["image"], im["station"], smear)
            ctx.log.log("warning", msg)
            ctx.say(f"  WARNING {msg}")
        names = [ids_all[int(i)] for i in m.target]
        dropped = [{"id": ids_all[i], "reason": why} for i, why in m.dropped]
        out.append({"station": im["station"], "image": im["image"], "ids": names, "uv": m.uv, "cov_px2": m.cov,
                    "bg_cov_px2": m.bg_cov, "clipped_share": m.clipped_share,
                    **({"ellipse_centre": m.ellipse} if m.ellipse is not None else {}),
                    **({"blur_px2": m.blur_px2} if m.blur_px2 is not None else {}),
                    **({"moments_px2": m.moments_px2} if m.moments_px2 is not None else {}),
                    "eccentricity_px": m.eccentricity_px,
                    **({"naming_radial": list(m.naming_radial)} if m.naming_radial is not None else {}),
                    **({"named_turned_deg": m.named_turned_deg} if m.named_turned_deg is not None else {}),
                    **({"clip_bound_px": m.clip_bound} if m.clip_bound is not None else {}),
                    **({"outline": m.outline, "centroid_chi2": m.centroid_chi2} if m.outline is not None else {}),
                    "smear": smear, "n_unidentified": m.n_unidentified, "n_partly_hidden": m.n_partly_hidden,
                    "n_shape_rejected": m.n_shape, "dropped": dropped,
                    "resection_median_px": m.resection_median_px,
                    "codes_seen": [{"id": ids_all[i], "px": round(d, 2), "limit_px": round(lim, 1)}
                                   for i, d, lim in m.codes_seen]} | counts)
        if (m.n_shape or len(m.dropped) > m.n_partly_hidden) and not smear.get("smeared"):
            ctx.log.log("warning", f"{im['image']}: {len(m.dropped)} named dot(s) left unnamed: " + "; ".join(
                f"{d['id']} {d['reason']}" for d in dropped[:6]) + (" ..." if len(dropped) > 6 else ""))
        ctx.log.detections(im["station"], names, m.uv)
    ctx.progress("measure", 1.0)
    by_reason = dropped_by_reason(out)
    atomic_write_json(ctx.folder.file("observations.json"), {"images": out, "n_dropped": sum(by_reason.values()),
                                                             "dropped_by_reason": by_reason})
    off = codes_off_placement(out, job.part.targets)
    if off is not None:  # the dots were named from a placement the job does not describe: not adjusted (0064)
        raise CalibrationError(off)
    n = [len(o["ids"]) for o in out]
    ctx.folder.append("identification_dropped", total=sum(by_reason.values()), by_reason=by_reason)
    ctx.say(f"  {sum(n)} observations in {len(out)} images ({min(n)}..{max(n)} per image); "
            f"{sum(o['n_partly_hidden'] for o in out)} partly hidden dots dropped, "
            f"{sum(o['n_unidentified'] for o in out)} other blobs (marker pieces, edges) ignored")
    unjudged = [o["image"] for o in out if (o.get("smear") or {}).get("why")]
    if unjudged:  # said, not silent: a smear there would go unseen (decision 0067)
        msg = (f"{len(unjudged)} image(s) with too few unclipped named dots to judge a smear (camera motion during the "
               f"exposure) from: {', '.join(unjudged[:6])}" + (" ..." if len(unjudged) > 6 else ""))
        ctx.log.log("info", msg)
        ctx.say(f"  {msg}")
    n_ell = sum(int(np.sum(o.get("ellipse_centre", []))) for o in out)
    if n_ell:
        ctx.say(f"  {n_ell} dots centred by the ellipse of their contour (clipped, or next to an edge: decision 0037)")
    if getattr(job.spec.camera, "detection", "cell") == "cell":
        kept = centroid_kept(out)
        if kept:  # said, not silent: their weights are the centroid's (ADJUST), their centres the centroid's
            ctx.say(f"  {kept} clipped or edge dots kept their centroid: the ellipse fit of their contour failed")
            ctx.log.log("info", f"{kept} clipped or edge dots kept their centroid (ellipse fit failed; decision 0037)")
    radial = [o["naming_radial"] for o in out if o.get("naming_radial")]
    if radial:  # said: the job's lens is not the camera's (decision 0054)
        k1 = np.median([r[0] for r in radial])
        msg = (f"{len(radial)} of {len(out)} images named with a radial lens fitted to their own dots (median k1 "
               f"{k1:+.3f}; [camera] k1 {job.spec.camera.k1:+.3f}): the nominal lens left their outer dots off their "
               "projections. State the lens's distortion in [camera] (k1..p2, from a calibration); ADJUST estimates it")
        ctx.say(f"  {msg}")
        ctx.log.log("info", msg)
    turned = [o["named_turned_deg"] for o in out if o.get("named_turned_deg") is not None]
    if turned:  # said: the robot's pose, or the lens's principal point, is not what the job says
        msg = (f"{len(turned)} of {len(out)} images named again from the pose their dots resect (turned "
               f"{np.median(turned):.2f} deg median, {max(turned):.2f} at most from the robot's): at the robot's pose "
               "the nominal lens left their dots over 1 px off (principal point or hand-eye off the job's)")
        ctx.say(f"  {msg}")
        ctx.log.log("info", msg)
    other = {k: v for k, v in by_reason.items() if k != "partly hidden (CAD)"}
    if other:
        ctx.say("  named dots left unnamed rather than misnamed: " + ", ".join(f"{v} {k}" for k, v in other.items()))


#: a coded marker seen beyond its limit (``cell.stages.imaging.code_offsets``) in at least this share of the images
#: that see it, and in at least CODE_OFF_MIN_IMAGES of them, is not where the placement puts it: one poor view (a
#: grazing or partly hidden marker) is not a wrong placement (as ``cell locate`` judges marker views, decision 0045)
CODE_OFF_SHARE = 0.5
CODE_OFF_MIN_IMAGES = 2


def codes_off_placement(images: list[dict], targets) -> str | None:
    """One line when a decoded coded marker is not where the job's placement and targets file put it, else None.

    ``images``: observations.json's records (``codes_seen``). The dots of every image are named from the job's
    placement ([cell] base_from_part); a part placed one step of its layout off (a symmetric layout turned by its
    pitch) is named dot by dot as its neighbours, consistently, and only its markers can tell (decision 0064)."""
    seen: dict[str, list[tuple[float, float]]] = {}
    for o in images:
        for c in o.get("codes_seen", []):
            seen.setdefault(c["id"], []).append((c["px"], c["limit_px"]))
    bad, good = [], []
    for tid, v in seen.items():
        n_off = sum(d > lim for d, lim in v)
        if n_off >= CODE_OFF_MIN_IMAGES and n_off >= CODE_OFF_SHARE * len(v):
            px = sorted(d for d, lim in v if d > lim)
            bad.append((tid, n_off, len(v), px[0], px[-1], min(lim for _, lim in v)))
        else:
            good.append(tid)
    if not bad:
        return None
    code = {i: int(c) for i, c in zip(targets.ids, targets.code)}
    what = ", ".join(f"code {code[t]} (target {t}) {lo:.0f}-{hi:.0f} px off in {k} of {n} images"
                     for t, k, n, lo, hi, _ in sorted(bad, key=lambda b: code[b[0]]))
    limit = min(b[5] for b in bad)
    if good:  # other markers are where the placement puts them: the markers named are not where the file says
        why = (f"they are not where the targets file puts them (the other marker(s) seen, {', '.join(sorted(good))}, "
               "are where the placement puts them): check the file's code column against the markers stuck on the part "
               "(swapped?) and correct it, or if the part is not where [cell] base_from_part says, run "
               "`cell locate JOB --write`")
    else:
        why = ("the part is not where [cell] base_from_part says (moved, or turned by a step of its layout, so that "
               "every dot would be named as its neighbour), or the targets file's codes are not where they are stuck: "
               "run `cell locate JOB --write`, or correct the targets file")
    return (f"coded marker(s) seen far from the projection of their own target (beyond {limit:.0f} px, two imaged dot "
            f"diameters): {what}; {why}; not adjusted, since the dots were named from that placement")


def centroid_kept(images: list[dict]) -> int:
    """Clipped dots and dots with a background bound that kept their centroid (the ellipse fit of their contour failed;
    decision 0037), over ``images`` (observations.json's records; records without the flags count nothing)."""
    n = 0
    for o in images:
        if "ellipse_centre" not in o or o.get("clipped_share") is None or o.get("bg_cov_px2") is None:
            continue
        flagged = np.asarray(o["clipped_share"], dtype=float) > 0
        if len(o["bg_cov_px2"]):
            flagged |= np.trace(np.asarray(o["bg_cov_px2"], dtype=float).reshape(-1, 2, 2), axis1=1, axis2=2) > 0
        n += int(np.sum(flagged & ~np.asarray(o["ellipse_centre"], dtype=bool)))
    return n


def dropped_by_reason(images: list[dict]) -> dict[str, int]:
    """How many named dots each check left unnamed, over ``images`` (observations.json's records)."""
    kinds = {"partly hidden": "partly hidden (CAD)", "shape": "shape unlike the target's ellipse",
             "the image's naming": "in images whose naming is inconsistent",
             "background not measurable": "background not measurable (ring < 8 px)",
             "smeared": "in images smeared by the camera's motion"}
    out: dict[str, int] = {}
    for o in images:
        for d in o.get("dropped", []):
            k = next((v for p, v in kinds.items() if d["reason"].startswith(p)), "other")
            out[k] = out.get(k, 0) + 1
    return out


def measure_with_excess(img, part, intr, cam_from_part, occluder, detection, coded_family, surfaces):
    """:func:`cell.stages.imaging.measure_image`, keeping the detections: the named dots' second moments judge whether
    the image is smeared (:func:`dots_excess`, :func:`judge_smears`). Returns (measurement, counts, the dots' excess)."""
    m, counts, det = measure_image_detections(img, part, intr, cam_from_part, occluder, detection=detection,
                                              coded_family=coded_family, surfaces=surfaces)
    return m, counts, dots_excess(det, m, part, intr)


def dots_excess(det, m, part, intr) -> dict | None:
    """What judges whether ``m``'s image is smeared (:func:`judge_smears`): its named dots' second moments
    (``det.axes``, found by each one's detected centre, ``m.uv`` plus the eccentricity taken off), their targets, their
    centres, the robot's pose and which dots judge (clipped dots and dots centred by their contour's ellipse, clipped
    or next to an edge, do not). None: no named dot."""
    from scipy.spatial import cKDTree

    k = len(m.target)
    if k == 0 or len(det.uv) == 0:
        return None
    uv = np.asarray(m.uv, dtype=float) + np.asarray(m.eccentricity_px, dtype=float)
    d, j = cKDTree(det.uv).query(uv)
    use = d < 1e-6
    if m.clipped_share is not None:
        use &= np.asarray(m.clipped_share, dtype=float) <= 0
    if m.ellipse is not None:
        use &= ~np.asarray(m.ellipse, dtype=bool)
    return {"axes": det.axes[np.minimum(j, len(det.uv) - 1)], "target": np.asarray(m.target), "uv": uv,
            "centre": np.asarray(m.uv, dtype=float), "pose": m.cam_from_part, "use": use}


def judge_smears(excess: list, part, intr) -> list[dict]:
    """observations.json's ``smear`` record of each image (:func:`calibration.smear.image_smear`) from its dots
    (:func:`dots_excess`; None: an image kept from before, or without a named dot: {}): each dot's deviatoric excess
    over its target's ellipse at the pose the image's named dots resect with the job's lens."""
    t, out = part.targets, []
    for e in excess:
        if e is None:
            out.append({})
            continue
        xyz, nrm = t.xyz[e["target"]], t.normals[e["target"]]
        pose = e["pose"]
        if len(xyz) >= 6:
            try:
                pose = refine_pose_pnp(intr, e["pose"], xyz, e["centre"])
            except CalibrationError:
                pass
        pred = ellipse_moments(intr, pose, xyz, nrm, part.target_diameter_m / 2)
        radius = np.hypot(e["uv"][:, 0] - intr.cx_px, e["uv"][:, 1] - intr.cy_px)
        size = np.sqrt(np.trace(pred, axis1=1, axis2=2))
        out.append(image_smear(deviatoric_excess(e["axes"], pred), e["use"], radius=radius, size=size))
    return out


def smear_words(smear: dict) -> str:
    """"its dots are smeared by ~L px along D deg" for a judged ``smear`` record."""
    return (f"its dots are smeared by ~{smear['length_px']:.1f} px along {smear['direction_deg']:.0f} deg (image u "
            f"towards v; {smear['n_dots']} dots, z^2 {smear['z2']:.0f})")


def smeared_message(image: str, station: str, smear: dict) -> str:
    """The console's and the run log's line for an image left out because its dots are smeared (decision 0067)."""
    return (f"image {image} (station {station}): {smear_words(smear)}: the camera moved during the exposure (the "
            "robot not settled, or its mount vibrating); its centres would be moved along the smear, which no stated "
            "sigma covers: left out of the adjustment; raise [cell] settle_s (or lower settle_speed_rad_s), shorten "
            "[camera] exposure_s, or stiffen the mount, and run the job again to retake it")


def _left_out(m, reason: str):
    """``m`` with none of its named dots measured: each one dropped with ``reason``."""
    none = np.zeros(0, dtype=int)
    kw = {k: (None if getattr(m, k) is None else getattr(m, k)[none])
          for k in ("cov", "bg_cov", "clipped_share", "ellipse", "blur_px2", "clip_bound", "outline", "centroid_chi2",
                    "moments_px2", "eccentricity_px")}
    return replace(m, target=m.target[none], uv=np.asarray(m.uv)[none], **kw,
                   dropped=list(m.dropped) + [(int(i), reason) for i in m.target])
