"""ADJUST: the rigorous bundle adjustment, initialised from the Faugeras-Toscani results."""
from __future__ import annotations

import io
import json
import time

import numpy as np

from calibration.bundle import BundleConfig, BundleOptions, ScaleBar, bundle_adjust
from calibration.bundle.bartest import bar_residual_test
from calibration.bundle.coherent import certificate_at_face_value, scale_bar_gains
from calibration.detector_model import (C_BACKGROUND_CENTROID, centroid_bound_scale, load_model, observation_covariances,
                                        observation_geometry, observation_sigmas)
from calibration.errors import CalibrationError, ScaleNotEstablishedError
from calibration.plausibility import check_adjustment
from calibration.weights import INCIDENCE_EDGES_DEG, group_labels, incidence_angles, incidence_groups, mean_variance
from cell.record.jobfolder import atomic_write_bytes, atomic_write_json
from cell.stages.clip_level import clip_bounds, clip_covariances, say_clip_level
from cell.stages.dot_precision import blur_weights, observed_blur, rms_sigma, stated_weights
from cell.stages.shared_terms import (add_coherent_background as _add_coherent_background, add_held_lens,
                                     held_lens_line, holds_cell_lens)
from cell.stages.scalebars import (bar_name, bars_doc, protected_entries, say_bars, shape_reason, snooping_reason,
                                   test_reason)
from cell.stages.model_shape import geometry_classes, model_mismatch, range_check, reweighted, shape_check
from cell.stages.outline import outline_doc, outline_doubtful, outline_reason, say_doubtful
from cell.stages.lens import (LENS_BLUR_READJUST, LENS_CENTRE_READJUST, camera_model, choose_start, lens_blur,
                              lens_centres, radial_check, say_stability, stability_doc)
from cell.stages.screen import Resection, Screening, reinstated, resect, screen_network
from cell.thermal import resolve_probe


def observation_arrays(job, obs_doc: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    index = job.part.targets.index()
    img, tgt, uv = [], [], []
    for k, o in enumerate(obs_doc["images"]):
        for tid, p in zip(o["ids"], o["uv"]):
            img.append(k)
            tgt.append(index[tid])
            uv.append(p)
    return np.asarray(img, dtype=int), np.asarray(tgt, dtype=int), np.asarray(uv, dtype=float).reshape(-1, 2)


def background_bounds(obs_doc: dict) -> tuple[np.ndarray, np.ndarray]:
    """The detector's bound on each observation's error from a background that is not a plane, ``(q, 2, 2)``
    px^2 in the order of :func:`observation_arrays`, and ``(q,)`` bool whether it has one.

    Image by image: an image measured before the detector gave bounds (no ``bg_cov_px2``: a job folder of an
    older version, or a closed loop that kept such images) has none; its observations keep the detector model's
    plain sigma (said by the caller), the others keep their bounds (decision 0030: one old image used to switch
    the bounds off for every observation)."""
    B, has = [], []
    for o in obs_doc["images"]:
        k = len(o["ids"])
        b = o.get("bg_cov_px2")
        arr = np.asarray(b, dtype=float).reshape(-1, 2, 2) if b is not None else None
        ok = arr is not None and len(arr) == k and bool(np.all(np.isfinite(arr)))
        B.append(arr if ok else np.zeros((k, 2, 2)))
        has.append(np.full(k, ok))
    if not B:
        return np.zeros((0, 2, 2)), np.zeros(0, dtype=bool)
    return np.concatenate(B), np.concatenate(has)


def ellipse_centred(obs_doc: dict) -> np.ndarray:
    """Whether each observation's centre is the ellipse of its dot's contour, ``(q,)`` bool in the order of
    :func:`observation_arrays` (observations.json ``ellipse_centre``); an image without it (measured before
    decision 0037, when every dot was centred by its centroid) has False."""
    E = []
    for o in obs_doc["images"]:
        k = len(o["ids"])
        e = o.get("ellipse_centre")
        arr = np.asarray(e, dtype=bool).reshape(-1) if e is not None else None
        E.append(arr if arr is not None and len(arr) == k else np.zeros(k, dtype=bool))
    return np.concatenate(E) if E else np.zeros(0, dtype=bool)


def centroid_bounds_scaled(bg: np.ndarray, ellipse: np.ndarray, model=None) -> tuple[np.ndarray, np.ndarray]:
    """The background bounds ``bg: (q, 2, 2)`` with those of the dots centred by their centroid (``ellipse: (q,)``
    False) scaled by :func:`calibration.detector_model.centroid_bound_scale`: the model's ``c_background`` is the
    ellipse centre's, the centroid errs by about four times its share. Returns (the bounds, (q,) which were scaled)."""
    scale = centroid_bound_scale(model or load_model())
    hit = ~np.asarray(ellipse, dtype=bool) & (np.trace(bg, axis1=1, axis2=2) > 0) & (scale != 1.0)
    return (np.where(hit[:, None, None], bg * scale, bg) if hit.any() else bg), hit


def clipped_shares(obs_doc: dict) -> tuple[np.ndarray, np.ndarray]:
    """The share of each observed dot's pixels the sensor clipped, ``(q,)`` in the order of
    :func:`observation_arrays`, and ``(q,)`` bool whether its image has them: an image measured before the detector
    counted clipped pixels has zeros (no saturation term; said by the caller)."""
    S, has = [], []
    for o in obs_doc["images"]:
        k = len(o["ids"])
        c = o.get("clipped_share")
        arr = np.asarray(c, dtype=float).reshape(-1) if c is not None else None
        ok = arr is not None and len(arr) == k and bool(np.all(np.isfinite(arr)))
        S.append(arr if ok else np.zeros(k))
        has.append(np.full(k, ok))
    if not S:
        return np.zeros(0), np.zeros(0, dtype=bool)
    return np.concatenate(S), np.concatenate(has)


def model_sigmas(job, backend: str, cam_from_part: np.ndarray, img: np.ndarray, tgt: np.ndarray,
                 fx_px: float) -> np.ndarray:
    """Each observation's sigma from the detector model (incidence, dot size; the simulated sensor's noise scale on
    the sim backend), floored at 1e-4 px: ADJUST's weights and the pre-analysis's (cell.stages.preanalysis)."""
    t = job.part.targets
    s = observation_sigmas(t.xyz, t.normals, cam_from_part, img, tgt, fx_px, job.part.target_diameter_m,
                           noise_scale=job.spec.sim.noise if backend == "sim" else 1.0)
    return np.maximum(s, 1e-4)


def model_diameters(job, cam_from_part: np.ndarray, img: np.ndarray, tgt: np.ndarray, fx_px: float) -> np.ndarray:
    """Each observation's dot diameter in pixels (the saturation term grows with it: decision 0037)."""
    t = job.part.targets
    return observation_geometry(t.xyz, t.normals, cam_from_part, img, tgt, fx_px, job.part.target_diameter_m)[1]


def bundle_config(job, use_bars=None) -> BundleConfig:
    """What the job's adjustment estimates (self-calibration) and its datum (scale bars, else free).

    ``use_bars``: positions in ``job.scale_bars`` of the bars the adjustment uses (None: every bar; empty: none can
    be used, a free network, scale not established)."""
    keep = set(range(len(job.scale_bars)) if use_bars is None else use_bars)
    scale_bars = tuple(ScaleBar(a, b, length, max(sigma, 1e-7))
                       for j, (a, b, length, sigma) in enumerate(job.scale_bars) if j in keep)
    return BundleConfig(camera_model=camera_model(job), refine_focal_length=(sc := job.spec.camera.self_calibrate),
                        refine_principal_point=sc, refine_distortion=sc, scale_bars=scale_bars)


def max_rejections(n_obs: int) -> int:
    """How many observations data snooping may reject: partly occluded dots are blunders too, so up to
    10 % (many per re-adjustment since issue 21, so the limit no longer bounds the time; 5 % before).
    A network that needs more is broken: bundle.json's ``snooping`` then says how many still fail."""
    return max(20, n_obs // 10)


#: a target whose sigma is this many times the median target's is not determined (two nearly parallel rays):
#: its near-singular block spoils the whole covariance (one 1 m-deep target gave every target a 9 mm axis)
WILD_SIGMA_FACTOR = 100.0
#: adjustments after dropping what the previous one could not use (targets behind a camera, wild targets)
MAX_RETRIES = 4


def _adjust(ctx, scr: Screening, use: list[int], obs: dict, obs_image, obs_target, obs_uv, poses_all, intr0):
    """One bundle adjustment of what the screening kept, with the scale bars ``use`` (positions in
    ``job.scale_bars``); returns the result and the subset it used."""
    job = ctx.job
    kept_images = np.flatnonzero(scr.keep_images)
    new_index = np.full(len(poses_all), -1)
    new_index[kept_images] = np.arange(len(kept_images))
    sel = scr.keep_obs & scr.keep_images[obs_image]
    img, tgt, uv = new_index[obs_image[sel]], obs_target[sel], obs_uv[sel]
    poses0 = poses_all[kept_images]
    config = bundle_config(job, use)
    options = BundleOptions(sigma_px=job.spec.camera.sigma_px, max_rejections=max_rejections(len(uv)))
    targets = job.part.targets
    groups = None
    obs_sigma = model_sigma = None
    flags = {"bg": None, "clip": None, "bg_missing": [], "clip_missing": [], "blur": None}
    weights = job.spec.camera.observation_weights
    if weights == "incidence":  # from the Faugeras-Toscani poses: degrees suffice
        angles = incidence_angles(targets.xyz, targets.normals, poses0, img, tgt)
        groups = incidence_groups(angles, INCIDENCE_EDGES_DEG)

    def weigh(blur, say=True):  # the detector's precision by incidence and dot size; the variance factor scales it
        model_sigma = None
        # (no iterated per-class variance components on top: with issue 21's batch snooping they ran away on generated
        # parts, a face-on class estimated at 0.11 px and 280 rejections; the model alone: 10 rejections, honest sigma;
        # the model's shape is checked once after the adjustment instead, below)
        obs_sigma = model_sigmas(job, ctx.backend, poses0, img, tgt, intr0.fx_px)
        # a dot blurred beyond the model's blur (defocus, focus): its blur term, by the blur its image shows (0049)
        obs_sigma, flags["blur"] = blur_weights(obs_sigma, blur)
        # each centroid-centred dot's noise as the detector states it from its own image (decision 0048)
        stated, usable, flags["stated"] = stated_weights(job, obs, sel, obs_sigma, ellipse_centred(obs))
        theta, dpx = observation_geometry(targets.xyz, targets.normals, poses0, img, tgt, intr0.fx_px,
                                          job.part.target_diameter_m)
        # a dot next to an edge or a step of the shading: the detector's background bound, its measured share
        # (docs/decisions/0023, truth); the covariance is then 2x2 per observation
        bg, has_bg = background_bounds(obs)
        # the model's c_background is the ellipse centre's: a dot with a bound centred by its centroid (a photograph's
        # detector, an ellipse fit that failed, a job measured before decision 0037) states the centroid's share
        bg, centroid = centroid_bounds_scaled(bg, ellipse_centred(obs))
        if say and np.any(centroid[sel]):
            ctx.say(f"  {int(np.count_nonzero(centroid[sel]))} observations next to an edge centred by their centroid: "
                    f"their background bound weighed at the centroid's share ({C_BACKGROUND_CENTROID:g}, not the "
                    "ellipse centre's)")
        # a dot the sensor clipped: the model's saturation term for the clipped share of its pixels (decision 0029)
        clip, has_clip = clipped_shares(obs)
        flags["clip_cov"] = clip_covariances(clip_bounds(obs)[sel])  # a clipped dot's unknown level (decision 0050)
        if np.any(bg[sel]) or np.any(clip[sel] > 0) or stated is not None:
            model_sigma, obs_sigma = (obs_sigma if stated is None else rms_sigma(stated)), observation_covariances(
                obs_sigma if stated is None else stated, bg[sel], clipped_share=clip[sel], diameter_px=dpx
            ) + flags["clip_cov"]
        flags.update({"bg": bg[sel], "clip": clip[sel], "bg_centroid": centroid[sel],
                      "bg_missing": sorted({obs["images"][int(i)]["image"] for i in obs_image[sel & ~has_bg]}),
                      "clip_missing": sorted({obs["images"][int(i)]["image"] for i in obs_image[sel & ~has_clip]})})
        return obs_sigma, model_sigma, theta, dpx, usable

    if weights == "model":
        obs_sigma, model_sigma, theta, dpx, usable = weigh(observed_blur(obs)[sel])
    res = bundle_adjust(img, tgt, uv, intr0, poses0, targets.xyz, options, config, obs_sigma_px=obs_sigma,
                        obs_group=groups)
    # the lens the adjustment found, not the nominal one (decision 0054): each dot's centre with its eccentricity
    # through that lens, and its blur against it; where either matters, the adjustment is made again with them
    again, flags["lens"] = False, {}
    # observations the screening took as gross at the start lens that agree with the adjusted network: a start without
    # the lens's distortion drops the image's outer dots by their residual, and keeps those whose noise leans
    # towards the start: a choice by the noise where the lens is determined (generated skin seed 110: cx and p2
    # 2.9 of their sigmas off, truth ratio 1.30); they are put back and data snooping tests them with the rest
    back = reinstated(scr, obs_image, obs_target, obs_uv, new_index, res)
    if back.any():
        for q in np.flatnonzero(back):
            scr.keep_obs[q] = True
            scr.obs.pop(int(q), None)
        sel = scr.keep_obs & scr.keep_images[obs_image]
        img, tgt, uv = new_index[obs_image[sel]], obs_target[sel], obs_uv[sel]
        if weights == "incidence":
            groups = incidence_groups(incidence_angles(targets.xyz, targets.normals, poses0, img, tgt),
                                      INCIDENCE_EDGES_DEG)
        flags["lens"]["screening_reinstated"] = int(back.sum())
        again = True
    before = None if again else (res.obs_sigma_px if np.ndim(res.obs_sigma_px) == 1 else rms_sigma(res.obs_sigma_px))
    if (corr := lens_centres(job, obs, sel, img, tgt, res)) is not None:
        norm = np.linalg.norm(corr, axis=1)
        flags["lens"]["centres_moved_px"] = {"median": float(np.median(norm)), "max": float(np.max(norm))}
        if again or np.max(norm / before) > LENS_CENTRE_READJUST:
            uv, again = uv + corr, True
    if weights == "model":
        blur = lens_blur(job, obs, sel, img, tgt, res)
        if blur is not None or again:
            obs_sigma, model_sigma, theta, dpx, usable = weigh(observed_blur(obs)[sel] if blur is None else blur,
                                                               say=False)
        if blur is not None:
            flags["blur"]["against"] = "the adjusted lens"
            after = rms_sigma(obs_sigma) if np.ndim(obs_sigma) == 3 else obs_sigma
            again |= bool(np.max(np.abs(after / before - 1)) > LENS_BLUR_READJUST) if before is not None else True
    if again:
        flags["lens"]["adjusted_again"] = True
        res = bundle_adjust(img, tgt, uv, intr0, poses0, targets.xyz, options, config, obs_sigma_px=obs_sigma,
                            obs_group=groups)
    if weights == "model":  # does the model's shape (sigma by incidence and size) fit the images? (decision 0046)
        classes, desc = geometry_classes(np.degrees(theta), dpx)
        shape = shape_check(res.residuals, obs_sigma, res.redundancy, res.rejected, classes, desc)
        if shape["reweight"]:  # a class off the model beyond its scatter: weighted by its own precision, once
            # (not iterated: see above)
            if model_sigma is None:
                model_sigma = obs_sigma
            obs_sigma = reweighted(obs_sigma, classes, shape["factors"])
            res = bundle_adjust(img, tgt, uv, intr0, poses0, targets.xyz, options, config, obs_sigma_px=obs_sigma)
            after = shape_check(res.residuals, obs_sigma, res.redundancy, res.rejected, classes, desc)
            shape["after_reweighting"] = [c["variance_ratio"] for c in after["classes"]]
            if after["mismatch"]:  # a factor held at its clamp, or snooping changed the classes: not mended, said
                shape["mismatch"] = (shape["mismatch"] or "the images do not follow the detector model's shape") + (
                    "; still off after the reweighting: " + "; ".join(after["off"]))
        flags["shape"] = shape
        # where the model was measured (of the dots it weighs), how many dots clipped deeply, the light: said when off
        flags["range"] = range_check(np.degrees(theta), dpx, ~res.rejected & ~usable, load_model().measured_box(),
                                     flags["clip"], ~res.rejected, flags["stated"], flags["blur"])
    if model_sigma is not None:
        # sigma0 of an observation of the noise's rms sigma, not of the rms weight (dots with huge bounds dominate it)
        used = ~res.rejected
        factor = res.sigma0_px**2 / mean_variance(res.obs_sigma_px[used])
        res.sigma0_px = float(np.sqrt(factor * np.mean(model_sigma[used] ** 2)))
    return res, (kept_images, sel, img, tgt, uv, groups, model_sigma, flags)


def _wild_targets(res) -> tuple[np.ndarray, np.ndarray, float]:
    """Targets whose sigma exceeds :data:`WILD_SIGMA_FACTOR` times the median target's: (indices, sigmas, median)."""
    tr = np.trace(res.cov, axis1=1, axis2=2)
    sig = np.sqrt(np.where(tr > 0, tr, np.nan))
    fin = np.isfinite(sig)
    if fin.sum() < 3:
        return np.zeros(0, dtype=int), sig, float("nan")
    med = float(np.median(sig[fin]))
    return np.flatnonzero(fin & (sig > WILD_SIGMA_FACTOR * med)), sig, med


def _weakest(sig: np.ndarray, med: float) -> np.ndarray:
    """When the adjustment did not settle: the targets beyond 10x the median sigma (none: nothing to drop)."""
    return np.flatnonzero(np.isfinite(sig) & (sig > 10.0 * med)) if np.isfinite(med) else np.zeros(0, dtype=int)


def _screen_and_adjust(ctx, obs, obs_image, obs_target, obs_uv, poses_all, intr0, rs, ids, drop_t: dict,
                       bars_out: dict, doubtful: dict, first: Screening | None = None):
    """Screen the network and adjust what it kept with the scale bars not in ``bars_out`` (positions in
    ``job.scale_bars`` -> why left out; completed here when data snooping takes an end below two rays); drop
    the targets the adjustment shows it cannot use (``drop_t``, completed here). Returns ``(res, sub, scr, use,
    retries, wild)``. ``first``: the screening of ``rs`` with nothing dropped yet (:func:`choose_start`'s), used while
    ``drop_t`` is still empty."""
    job = ctx.job
    nb = len(job.scale_bars)
    pairs = [tuple(bar[:2]) for bar in job.scale_bars]
    for attempt in range(MAX_RETRIES + 1):
        if first is not None and attempt == 0 and not drop_t:
            scr = first
        else:
            scr = screen_network(obs_image, obs_target, obs_uv, intr0, rs.poses, len(ids), scale_pairs=pairs,
                                 drop_targets=drop_t, drop_images=rs.left_out, ids=ids)
        left = dict(scr.bars_out) | bars_out
        use = [j for j in range(nb) if j not in left]
        scr.bars_out = left
        if nb and not use:
            scr.scale_ok, scr.scale_reason = False, "; ".join(left[j] for j in range(nb))
        if scr.keep_images.sum() < 2:
            raise CalibrationError(f"bundle: {int(scr.keep_images.sum())} of {len(poses_all)} images usable "
                                   "(see the screening reasons in the log); nothing to adjust: if the images show the "
                                   "part, it may not be where [cell] base_from_part says (run `cell locate JOB "
                                   "--write`), or the light and exposure hide its dots")
        try:
            res, sub = _adjust(ctx, scr, use, obs, obs_image, obs_target, obs_uv, rs.poses, intr0)
        except ScaleNotEstablishedError as exc:
            if attempt == MAX_RETRIES:
                raise
            rej = _snooped_images(exc, scr, obs, obs_image)
            for j in use:
                bars_out[j] = snooping_reason(job, j, exc.ends, rej)
            ctx.log.log("warning", "adjustment: scale not established: " + "; ".join(bars_out[j] for j in use)
                        + "; adjusting a free network")
            continue
        except CalibrationError as exc:
            bad = getattr(exc, "targets", None)
            if bad is None or attempt == MAX_RETRIES:
                raise
            for t in bad:
                drop_t[int(t)] = ("ended behind a camera that observes it during the adjustment "
                                  "(misnamed, or its rays nearly parallel)")
            ctx.log.log("warning", f"adjustment: {len(bad)} target(s) ended behind a camera "
                                   f"({', '.join(ids[int(t)] for t in bad[:8])}); dropped, adjusting again")
            continue
        # a bar whose end data snooping took below two rays while another bar kept the scale: the adjustment did not
        # use its length (calibration.bundle.normal skips it); left out by name and adjusted again without it
        tgt = sub[3]
        kept = np.bincount(tgt[~res.rejected], minlength=len(ids))
        lost = [j for j in use if min(kept[t] for t in pairs[j]) < 2]
        if lost and attempt == MAX_RETRIES:
            raise CalibrationError(f"bundle: scale bar(s) {', '.join(bar_name(job, j) for j in lost)} lost an end to data "
                                   f"snooping after {MAX_RETRIES} retries: no adjustment left to use the others alone")
        if lost:
            ends = {int(t): int(kept[t]) for j in lost for t in pairs[j] if kept[t] < 2}
            sel = np.flatnonzero(scr.keep_obs & scr.keep_images[obs_image])
            rej = sorted({obs["images"][int(obs_image[sel[q]])]["image"]
                          for q in np.flatnonzero(res.rejected & np.isin(tgt, list(ends)))})
            for j in lost:
                bars_out[j] = snooping_reason(job, j, ends, rej)
                ctx.log.log("warning", f"adjustment: {bars_out[j]}; bar left out, adjusting again")
            continue
        wild, sig, med = _wild_targets(res)
        if not res.converged and not wild.size:  # the weakest targets are what keeps an adjustment from settling
            wild = _weakest(sig, med)
        if wild.size and attempt < MAX_RETRIES:
            for t in wild:
                drop_t[int(t)] = (f"sigma {sig[t] * 1e3:.3g} mm, {sig[t] / med:.0f}x the median target's: "
                                  "not determined (rays nearly parallel)")
            ctx.log.log("warning", f"adjustment: {len(wild)} target(s) not determined "
                                   f"({', '.join(ids[int(t)] for t in wild[:8])}); dropped, adjusting again")
            continue
        break
    return res, sub, scr, use, attempt, wild


def _snooped_images(exc, scr: Screening, obs: dict, obs_image) -> list[str]:
    """The images whose observations of a scale-bar end data snooping rejected (``exc``:
    :class:`ScaleNotEstablishedError` of the adjusted subset)."""
    sel = np.flatnonzero(scr.keep_obs & scr.keep_images[obs_image])
    return [obs["images"][int(obs_image[sel[q]])]["image"] for q in exc.rejected if q < len(sel)]


def run_bundle(ctx) -> dict:
    """Screen the network (:mod:`cell.stages.screen`), adjust what it kept, and drop what the adjustment shows
    it cannot use (a target that ends behind a camera, one that is not determined), each with its reason; with
    several scale bars, test their certificates against each other (:mod:`cell.stages.scalebars`)."""
    job = ctx.job = resolve_probe(ctx.job, ctx.folder)  # [thermal] part_C = "probe" (decision 0053)
    obs = json.loads(ctx.folder.file("observations.json").read_text())
    cal = json.loads(ctx.folder.file("calibration.json").read_text())
    obs_image, obs_target, obs_uv = observation_arrays(job, obs)
    poses_all = np.array([r["cam_from_part"] for r in cal["images"]], dtype=float)
    ids = list(job.part.targets.ids)
    # poses that go with the common interior orientation: the screening's rays and the adjustment start from them
    # (Faugeras-Toscani's per-image poses, paired with the common interior orientation, are pixels off: on a thin
    # network with glare the adjustment started from them diverged, 100 targets behind a camera)
    intr0, rs, first, start = choose_start(job, cal, obs_image, obs_target, obs_uv, poses_all, ids,
                                           radial_named=any(o.get("naming_radial") for o in obs["images"]))
    if start.get("reason"):
        ctx.log.log("warning", start["reason"])
        ctx.say(f"  WARNING {start['reason']}")
    drop_t: dict[int, str] = {}
    bars_out: dict[int, str] = {}  # scale bars left out (position in job.scale_bars -> why)
    doubtful, printed = shape_doubtful(obs, ids), outline_doubtful(obs, ids)  # printed: a chipped dot (0051)
    for j in range(len(job.scale_bars)):
        why = shape_reason(job, j, doubtful) or outline_reason(job, j, printed)
        if why is not None:
            bars_out[j] = why
            ctx.log.log("warning", f"adjustment: {why}; bar left out")
    if job.scale_bars and len(bars_out) == len(job.scale_bars):
        ctx.log.log("warning", "adjustment: scale not established: " + "; ".join(bars_out.values())
                    + "; adjusting a free network")
    t0 = time.perf_counter()
    while True:  # with three bars or more, a bar whose certificate fails the test is left out and the job adjusted again
        res, sub, scr, use, attempt, wild = _screen_and_adjust(ctx, obs, obs_image, obs_target, obs_uv, poses_all,
                                                               intr0, rs, ids, drop_t, bars_out, doubtful, first)
        first = None  # the start's screening serves the first round only
        if not res.converged:
            raise CalibrationError(f"bundle adjustment did not converge: {res.summary}")
        if wild.size:  # still undetermined after the last retry: their covariance would spoil every other target's
            raise CalibrationError(f"bundle: {len(wild)} target(s) still not determined after {MAX_RETRIES} retries "
                                   f"({', '.join(ids[int(t)] for t in wild[:8])}): their rays are nearly parallel")
        check_adjustment(res.sigma0_px, res.intrinsics, job.intrinsics)  # a converged nonsense is a failure
        var = np.diagonal(res.cov, axis1=1, axis2=2)
        if np.any(np.isfinite(var).all(axis=1) & (var <= 0).any(axis=1)):  # a singular network, not a measurement
            raise CalibrationError("bundle: the network is not determined (a target's variance is not positive): its "
                                   "images are too weakly linked; see the screening in the log")
        kept_images, sel, img, tgt, uv, groups, model_sigma, flags = sub
        bars = bundle_config(job, use).scale_bars
        K, K_sigma = scale_bar_gains(res.covariance, res.points, bars, res.variance_factor) if bars else (np.zeros((len(ids), 3, 0)), np.zeros(0))
        if bars:  # the certificates at their stated sigma: s0^2 scales what the images determined, not the bars
            res.cov, res.covariance = certificate_at_face_value(res.cov, res.covariance, K, K_sigma, res.variance_factor)
        coherent = _add_coherent_background(res, flags["bg"], img, tgt, ids, bars, K, flags.get("clip_cov")) \
            if model_sigma is not None else None
        held_lens = add_held_lens(res, img, tgt, uv, bundle_config(job, use), job.spec.camera.sigma_px,
                                  job.cell["lens"]["cov"]) if holds_cell_lens(job) else None  # before the bars' test
        v = np.zeros(len(bars))
        for e in (coherent or {}).get("scale_bar_ends", []):
            v[e["bar_index"]] = e["length_sigma_m"] ** 2
        test = bar_residual_test(res.points, res.covariance, K, bars, v) if bars else None
        worst = test.worst() if test is not None else None
        if worst is None:
            break
        if len(use) == 2:  # two bars cannot tell which certificate is wrong
            raise CalibrationError(
                "scale bars disagree: " + ", ".join(
                    f"{bar_name(job, j)} adjusted minus certificate {test.residual_m[k] * 1e6:+.1f} um "
                    f"({test.w[k]:+.1f} sigma)" for k, j in enumerate(use))
                + f" (|w| > {test.critical:.2f}): one certificate, or an end's measurement, is wrong and two bars "
                  "cannot tell which; check both certificates and their ends, or add a third bar")
        bars_out[use[worst]] = test_reason(job, use[worst], test, worst)
        msg = f"{bars_out[use[worst]]}; bar left out, adjusting again with the other {len(use) - 1}"
        ctx.log.log("warning", f"adjustment: {msg}")
        ctx.say(f"  WARNING {msg}")
    held = "held: the cell's, calibrated with its hand-eye" if (job.cell or {}).get("lens") else "nominal (not calibrated)"
    lens = {"model": job.spec.camera.lens_model if job.spec.camera.self_calibrate else held,
            "camera_model": bundle_config(job, use).camera_model} | flags.get("lens", {})
    if held_lens is not None:  # the cell's lens held: its uncertainty from the hand-eye, through the network (0056)
        lens["held_uncertainty"] = held_lens
        ctx.say(f"  {held_lens_line(held_lens)}" if held_lens["carried"] else f"  WARNING {held_lens_line(held_lens)}")
    lens |= {"radial_check": radial_check(res, img, tgt, uv, BundleOptions(sigma_px=job.spec.camera.sigma_px),
                                          bundle_config(job, use))}
    lens["interior_stability"] = stability_doc(res.interior_stability, obs["images"], kept_images,
                                               job.intrinsics.pixel_size_m)  # the lens moved during the job? (0066)
    say_stability(ctx, lens["interior_stability"])
    rc = lens["radial_check"] or {}
    if rc.get("note") or rc.get("tested") is False:  # a check that could not run is said, not taken for a clean lens
        said = rc.get("note") or f"the radial lens model could not be checked: {rc.get('reason')}"
        ctx.log.log("warning", said)
        ctx.say(f"  WARNING {said}")
    suspect = _screened_suspects(scr, obs_target, tgt[~res.rejected], len(ids))
    shaped = {t for t in doubtful if np.any(tgt[~res.rejected] == t)}
    if shaped:  # the views kept share the cause that made most of its views unlike the target's ellipse
        ctx.log.log("warning", "targets unlike their ellipse in most images that found them, reported inconclusive: "
                    + ", ".join(f"{ids[t]} ({doubtful[t][0]} of {sum(doubtful[t])})" for t in sorted(shaped)))
        suspect |= shaped
    suspect |= say_doubtful(ctx, printed, ids, obs)
    dt = time.perf_counter() - t0
    n_img = np.bincount(tgt[~res.rejected], minlength=len(ids))
    # each with the statistic it was rejected with and its degrees of freedom (1: a pair of rays, tested at the 1-dof
    # critical value snooping.threshold_1dof; 2: snooping.threshold)
    rejected = [{"image": obs["images"][int(kept_images[i])]["image"], "target": ids[int(t)], "residual_px": r,
                 "test_statistic": float(w), "test_dof": int(f)}
                for i, t, r, bad, w, f in zip(img, tgt, res.residuals, res.rejected, res.rejected_test, res.test_dof)
                if bad]
    axes, dirs = res.error_ellipsoids()
    # keep the full covariance for the report's alignment (exact propagation)
    buf = io.BytesIO()
    np.savez_compressed(buf, D=res.covariance.D, U=res.covariance.U, C=res.covariance.C, K=K, K_sigma=K_sigma)
    atomic_write_bytes(ctx.folder.file("bundle_covariance.npz"), buf.getvalue())
    return {
        "datum": res.datum,
        "start": start,
        "sigma0_px": res.sigma0_px,
        "observation_weights": (_weights_doc(job, res, groups, model_sigma, flags["bg_missing"])
                                | _flag_counts(flags, res.rejected) | {"model_shape": flags.get("shape"),
                                                                               "model_range": flags.get("range"),
                                                                               "dot_precision": flags.get("stated")}),
        "dof": res.dof,
        "converged": res.converged,
        "summary": res.summary,
        "solver_fallback": res.solver_fallback,
        "time_s": dt,
        "timings": res.timings,
        "n_observations": int(len(uv)),
        "n_rejected": int(res.rejected.sum()),
        "rejected": rejected,
        "screening": screening_doc(scr, obs, obs_image, obs_target, ids, attempt, rs, job),
        "scale_bars": bars_doc(job, use, scr.bars_out, test),
        "coherent_background": coherent,
        "target_print": outline_doc(printed, ids, obs),
        # targets determined >10x worse than the median: out of the datum's minimum trace (calibration.bundle.covariance)
        "datum_left_out": [ids[int(t)] for t in (res.datum_left_out if res.datum_left_out is not None else [])],
        "snooping": res.snooping | {"suspect_targets": [ids[int(t)] for t in sorted(set(
                                        int(t) for t in res.snooping["suspect_targets"]) | suspect)],
                                    "protected": protected_entries(job, use, res.snooping["protected"])},
        "lens": lens,
        "intrinsics": res.intrinsics.to_dict(),
        "intrinsics_refined": list(res.intrinsics_names),
        "intrinsics_sigma": np.sqrt(np.diag(res.intrinsics_cov)).tolist() if len(res.intrinsics_names) else [],
        "images": [{"image": obs["images"][int(k)]["image"], "station": obs["images"][int(k)]["station"],
                    "cam_from_part": T} for k, T in zip(kept_images, res.cam_from_part)],
        "residuals_px": res.residuals,
        "targets": [{"id": tid, "xyz": p, "cov": c, "n_images": int(k), "ellipsoid_axes_m": ax,
                     "ellipsoid_dirs": d} for tid, p, c, k, ax, d in zip(ids, res.points, res.cov, n_img, axes, dirs)],
    }


def shape_doubtful(obs: dict, ids: list[str]) -> dict[int, tuple[int, int]]:
    """Targets MEASURE found unlike their ellipse (``shape ...``, decision 0016) in more images than it kept them:
    {target index: (images unlike, images kept)}. Whatever made most views of a dot unlike it (an edge cutting or
    crowding it, clipping, a wash-out) is in the views that passed as well: on generated skin seed 110 the scale
    bar's end T0064 was unlike its ellipse in 11 of 15 images and the 4 kept erred the bar by ~40 um against 11 um
    stated (the network 115 ppm small, 34 % of the targets inside their 99 % ellipsoid)."""
    index = {t: k for k, t in enumerate(ids)}
    kept = np.zeros(len(ids), dtype=int)
    unlike = np.zeros(len(ids), dtype=int)
    for im in obs["images"]:
        for t in im["ids"]:
            kept[index[t]] += 1
        for d in im.get("dropped") or []:
            if str(d.get("reason", "")).startswith("shape") and d.get("id") in index:
                unlike[index[d["id"]]] += 1
    return {int(t): (int(unlike[t]), int(kept[t])) for t in np.flatnonzero((unlike > kept) & (kept > 0))}


def _screened_suspects(scr: Screening, obs_target, used_target, n: int) -> set[int]:
    """Targets the screening took a ray from that kept two or fewer: the pair left cannot be checked against a
    third (the same rule as data snooping's suspects, decision 0021; generated plate seed 107: T0049 kept two
    rays after one was dropped as 2.1 px off, and came out 328 um from the truth)."""
    lost = np.bincount([int(obs_target[q]) for q in scr.obs], minlength=n) if scr.obs else np.zeros(n, dtype=int)
    kept = np.bincount(np.asarray(used_target, dtype=int), minlength=n)
    return {int(t) for t in np.flatnonzero((lost > 0) & (kept <= 2) & (kept > 0))}


def screening_doc(scr: Screening, obs: dict, obs_image, obs_target, ids: list[str], retries: int,
                  rs: Resection | None = None, job=None) -> dict:
    """bundle.json's ``screening``: every observation, target and image the adjustment did not use, and why;
    whether the scale was established and (``job`` given, with scale bars) ``scale_bars``: per bar whether the
    adjustment used it or why it left it out; ``resection``: how many images took their resection with the common
    interior orientation and which kept their start pose, and why (an image a resection left out is in
    ``dropped_images``)."""
    ims = obs["images"]
    res_doc = None if rs is None else {
        "resected": rs.resected,
        "start_kept": [{"image": ims[i]["image"], "station": ims[i]["station"], "reason": why}
                       for i, why in sorted(rs.kept_start.items())]}
    return {
        "resection": res_doc,
        "dropped_observations": [{"image": ims[int(obs_image[q])]["image"], "target": ids[int(obs_target[q])],
                                  "reason": why} for q, why in sorted(scr.obs.items())],
        "dropped_targets": [{"id": ids[t], "reason": why} for t, why in sorted(scr.targets.items())],
        "dropped_images": [{"image": ims[i]["image"], "station": ims[i]["station"], "reason": why}
                           for i, why in sorted(scr.images.items())],
        "scale_established": scr.scale_ok,
        "scale": scr.scale_reason,
        **({"scale_bars": [{"bar": bar_name(job, j), "used": j not in scr.bars_out, "reason": scr.bars_out.get(j)}
                           for j in range(len(job.scale_bars))]} if job is not None and job.scale_bars else {}),
        "retries": retries,
    }


def _flag_counts(flags: dict, rejected) -> dict:
    """Observations the adjustment used that are of clipped dots, and the images without clipped shares (measured
    before the detector counted them: no saturation term there; decision 0029)."""
    used = ~np.asarray(rejected, dtype=bool)
    out: dict = {}
    if flags["bg"] is not None:  # the dots next to an edge: a non-zero bound (not every 2x2 that differs from the model)
        out["observations_with_background_bound"] = int(np.count_nonzero(
            np.trace(np.asarray(flags["bg"], dtype=float), axis1=1, axis2=2)[used] > 0))
        # of them, centred by their centroid: the bound at the centroid's share (decision 0037)
        out["background_bound_at_centroid_share"] = int(np.count_nonzero(flags["bg_centroid"][used]))
    if flags["clip"] is None:
        return out | {"observations_clipped": None, "images_without_clipped_share": []}
    # clipped dots without a bound for their unknown level (an image measured before decision 0050, a dot centred by
    # its centroid, an end's contour that could not be fitted): their statement lacks that term, said by the caller
    clipped = np.asarray(flags["clip"]) > 0
    cc = flags.get("clip_cov")
    has = np.trace(cc, axis1=1, axis2=2) > 0 if cc is not None else np.zeros(len(clipped), dtype=bool)
    return out | {"observations_clipped": int(np.count_nonzero(clipped[used])),
                  "clipped_without_bound": int(np.count_nonzero((clipped & ~has)[used])),
                  "images_without_clipped_share": list(flags["clip_missing"])}


def _weights_doc(job, res, groups, model_sigma=None, bg_missing=()) -> dict:
    """The a priori image sigmas the adjustment used: one per incidence class (estimated) or one for all.

    ``model_sigma: (q,)`` the detector model's sigmas when the bundle took 2x2 covariances (model plus the
    detector's background bounds): the figures and the variance factor refer to them; ``bg_missing``: the images
    whose observations had no bound (measured before the detector gave them): plain model sigmas."""
    vc = res.variance_components
    if job.spec.camera.observation_weights == "model":
        s = res.obs_sigma_px if model_sigma is None else model_sigma
        used = s[~res.rejected] if s is not None else np.array([np.nan])
        return {"method": "model", "detector_model": load_model().to_dict(),
                "observations_with_background_bound": 0,  # counted from the bounds themselves (_flag_counts)
                "images_without_background_bound": list(bg_missing),
                "a_priori_sigma_px": {"median": float(np.median(used)), "p90": float(np.quantile(used, 0.9)),
                                      "max": float(np.max(used))},
                "variance_factor": (vf := float((res.sigma0_px / np.sqrt(np.mean(used**2))) ** 2)),
                "model_mismatch": model_mismatch(vf, job.spec.camera.dot_precision, not job.spec.camera.self_calibrate)}
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
    say_screening(ctx, doc["screening"])
    say_bars(ctx, doc["scale_bars"])
    if doc.get("datum_left_out"):  # a datum choice, said (calibration.bundle.covariance.WEAK_DATUM)
        ids = doc["datum_left_out"]
        msg = (f"datum: {len(ids)} target(s) determined >10x worse than the median left out of the datum's minimum "
               f"trace ({', '.join(ids[:8])}{' ...' if len(ids) > 8 else ''})")
        ctx.log.log("info", msg)
        ctx.say(f"  {msg}")
    if doc.get("solver_fallback"):
        msg = f"Gauss-Newton handed the adjustment to pycolmap's Levenberg-Marquardt: {doc['solver_fallback']}"
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")
    sn = doc["snooping"]
    for d in sn.get("diverged", []):  # a data-snooping round whose Gauss-Newton left the optimum: stopped, said
        settled = next((h for h in sn.get("handed_over", []) if h.split(":")[0] == d.split(":")[0]), None)
        msg = f"data snooping {d}; " + (settled.split(": ", 1)[1] if settled else "not settled (see below)")
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")
    if not sn["complete"]:
        ctx.log.log("warning", f"data snooping stopped early: {sn['stopped']}")
        ctx.say(f"  WARNING data snooping stopped early: {sn['stopped']}")
    if sn["suspect_targets"]:
        msg = ("targets whose observations data snooping could not verify (lost half of their rays, or kept two or "
               f"fewer after a rejection or a screening drop; reported inconclusive): {', '.join(sn['suspect_targets'])}")
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")
    if doc["observation_weights"]["method"] == "model":
        w = doc["observation_weights"]
        ctx.say(f"  image sigma from the detector model: median {w['a_priori_sigma_px']['median']:.4f} px, "
                f"max {w['a_priori_sigma_px']['max']:.3f} px; variance factor {w['variance_factor']:.2f}; "
                f"{w['observations_with_background_bound']} observation(s) next to an edge (background bound)"
                + (f", {w['observations_clipped']} of clipped dots (saturation term)" if w.get("observations_clipped")
                   else "")
                + (f", {b['raised']} blurred beyond the model's (blur term, largest x{b['largest_factor']:.2f})"
                   if (b := (w.get("model_range") or {}).get("blur") or {}).get("raised") else ""))
    w = doc["observation_weights"]
    for msg in (w.get("model_mismatch"), (w.get("model_shape") or {}).get("mismatch"),
                (w.get("model_range") or {}).get("mismatch")):
        if msg:
            ctx.log.log("warning", msg)
            ctx.say(f"  WARNING {msg}")
    shape = w.get("model_shape") or {}
    if shape.get("reweight") and not shape.get("mismatch"):  # within the band: said, not warned
        moved = [c for c in shape["classes"] if c["significant"]]
        msg = ("image variance by class against the network's, off the detector model beyond its scatter: "
               + "; ".join(f"{c['incidence_deg'][0]:g}-{c['incidence_deg'][1]:g} deg, dots "
                           + (f"< {c['diameter_px'][1]:g}" if c["diameter_px"][1] is not None
                              else f">= {c['diameter_px'][0]:g}") + f" px: {c['variance_ratio']:.2f}" for c in moved)
               + f"; {len(moved)} class(es) weighted by their own precision")
        ctx.log.log("info", msg)
        ctx.say(f"  {msg}")
    for key, what, then in (("images_without_background_bound", "background bounds",
                             "their observations keep the detector model's plain sigma (a dot next to an edge there is "
                             "not down-weighted)"),
                            ("images_without_clipped_share", "count of clipped pixels",
                             "a clipped dot there keeps the detector model's plain sigma (no saturation term)")):
        miss = w.get(key) or []
        if miss:
            msg = (f"{len(miss)} image(s) measured without the detector's {what} (" + ", ".join(miss[:6])
                   + (" ..." if len(miss) > 6 else "") + f"): {then}")
            ctx.log.log("warning", msg)
            ctx.say(f"  WARNING {msg}")
    if w.get("observations_clipped") and w["observations_clipped"] > 0.2 * (doc["n_observations"] - doc["n_rejected"]):
        msg = (f"{w['observations_clipped']} of {doc['n_observations'] - doc['n_rejected']} observations are of dots the "
               "sensor clipped (overexposed: lower the flash or the exposure for near stations); their sigma carries "
               "the detector model's saturation term")
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")
    cb = doc.get("coherent_background")
    for e in (cb or {}).get("scale_bar_ends", []):
        msg = (f"scale bar {e['bar'][0]}-{e['bar'][1]}: its ends sit next to an edge in their views; their shared misfit "
               f"errs the bar's measured length by {e['length_sigma_m'] * 1e6:.1f} um (1 sigma), which every target's "
               "covariance now carries through the scale: a bar with clear surroundings measures better")
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")
    if cb and cb["n_targets"]:
        big = ", ".join(f"{x['target']} x{x['sigma_growth']:.1f}" for x in cb["largest"][:3])
        ctx.say(f"  {cb['n_targets']} target(s) next to an edge in several views: the background misfit their views "
                f"share added to their covariance (sigma x{cb['sigma_growth_median']:.2f} median; largest {big})")
        if not cb.get("share_measured", True):
            msg = ("the detector model gives no measured share of the background misfit the views have in common "
                   "(rho_background, version 4): taken as one, the conservative limit")
            ctx.log.log("info", msg)
            ctx.say(f"  {msg}")
    say_clip_level(ctx, (cb or {}).get("clip_level") or {}, doc["observation_weights"])
    fl = (cb or {}).get("shared_floor") or {}
    if fl.get("n_targets"):
        ctx.say(f"  every dot's views share {fl['rho_all']:.4f} of its error (detector model rho_all, decision 0043): "
                f"added to {fl['n_targets']} target(s) (sigma x{fl['sigma_growth_median']:.2f} median, "
                f"x{fl['sigma_growth_max']:.2f} at most)")
    if doc["observation_weights"]["method"] == "incidence":
        ctx.say("  image sigma by incidence (variance components): " + ", ".join(
            f"{g['name']} {g['sigma_px']:.3f} px" + ("" if g["estimated"] else " (common)")
            for g in doc["observation_weights"]["groups"] if g["n_observations"]))


def say_screening(ctx, sc: dict) -> None:
    """The console and the journal: what the adjustment did not use, and a scale not established."""
    ctx.folder.append("adjustment_screening", dropped_observations=len(sc["dropped_observations"]),
                      dropped_targets=sc["dropped_targets"], dropped_images=sc["dropped_images"],
                      scale_established=sc["scale_established"], scale=sc["scale"])
    kept = (sc.get("resection") or {}).get("start_kept") or []
    if kept:
        msg = (f"{len(kept)} image(s) keep their start pose, not their resection with the common interior "
               "orientation (" + ", ".join(f"{d['image']}: {d['reason']}" for d in kept[:3])
               + (" ..." if len(kept) > 3 else "") + "; bundle.json screening.resection)")
        ctx.log.log("warning", msg)
        ctx.say(f"  {msg}")
    parts = []
    if sc["dropped_observations"]:
        parts.append(f"{len(sc['dropped_observations'])} gross observation(s)")
    if sc["dropped_targets"]:
        parts.append(f"{len(sc['dropped_targets'])} target(s) ("
                     + ", ".join(f"{d['id']}: {d['reason']}" for d in sc["dropped_targets"][:3])
                     + (" ..." if len(sc["dropped_targets"]) > 3 else "") + ")")
    if sc["dropped_images"]:
        parts.append(f"{len(sc['dropped_images'])} image(s) ("
                     + ", ".join(f"{d['image']}: {d['reason']}" for d in sc["dropped_images"][:3])
                     + (" ..." if len(sc["dropped_images"]) > 3 else "") + ")")
    if parts:
        msg = "adjustment left out " + "; ".join(parts) + " (bundle.json screening)"
        ctx.log.log("warning", msg)
        ctx.say(f"  {msg}")
    if not sc["scale_established"]:
        msg = f"scale not established: {sc['scale']}; the network keeps the CAD's scale until it is"
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")
