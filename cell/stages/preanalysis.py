"""PLAN's pre-analysis: what ADJUST will report for the planned network, from the cell's own images of the CAD part.

Predicted = achieved needs the same rays and the same image precision as the bundle. Both depend on the images:
which dots the detector will find and name (a dot clipped by an edge is dropped, a dot at grazing incidence is
unlike its ellipse), which of them sit next to an edge or a shading step (the detector's background bound, whose
misfit the views of a target partly share: :mod:`calibration.bundle.coherent`), and which of them the sensor clips
(the detector model's saturation term). A geometric visibility test knows none of that. So the pre-analysis renders
the nominal part from every planned station with the simulated cell's camera (its photometry, sensor noise, blur and
quantisation: :mod:`sim_backend.sim_camera`), measures the renders with MEASURE's own function
(:func:`cell.stages.imaging.measure_image`), and adjusts exact observations of the nominal targets over the rays it
named, each weighted as ADJUST will weight it (detector model, background bound, clipped share), with the job's
self-calibration and datum; the shared misfit and the scale bar's ends are then added as ADJUST adds them.

On a real cell the renders are a prediction (the twin's light and sensor are the simulator's defaults). When the
rendering cannot run, the rays come from the geometric visibility (every dot up to 85 deg incidence) without the
image terms, and plan.json says so.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from calibration.camera import invert, project
from calibration.errors import CalibrationError, PlanningError

#: the twin's noise stream: fixed, so a plan's prediction does not change between runs of the same job
TWIN_SEED = 20260
#: incidence up to which MEASURE names dots (cell.stages.imaging.measure_image's default)
NAMING_INCIDENCE_DEG = 85.0


@dataclass
class PredictedRays:
    """The rays the pre-analysis adjusts: per observation its image and target, and the image terms."""

    obs_image: np.ndarray
    obs_target: np.ndarray
    bg_cov: np.ndarray | None = None  # (q, 2, 2) px^2, the detector's background bound on the render
    clipped_share: np.ndarray | None = None  # (q,) share of the dot's pixels at the sensor's ceiling
    ellipse: np.ndarray | None = None  # (q,) bool, the centre is the ellipse of the dot's contour (decision 0037)
    cov: np.ndarray | None = None  # (q, 2, 2) px^2, the detector's covariance of the centre (decision 0048)
    line: np.ndarray | None = None  # (q,) bool, the render's noise line was measured (cell.stages.dot_precision)
    blur: np.ndarray | None = None  # (q,) px^2, the blur the dot's render shows (NaN: clipped; decision 0049)
    clip_bound: np.ndarray | None = None  # (q, 2) px, a clipped dot's bound for its unknown level (decision 0050)
    method: str = "rendered"
    facts: dict = field(default_factory=dict)


def twin_camera(job):
    """The simulated cell's camera on the nominal part at its nominal placement (no deviations, no fixture)."""
    from dataclasses import replace

    from sim_backend.sim_camera import Photometry, Sensor, SimCamera
    from sim_backend.world import World

    s = job.spec
    photometry = Photometry()
    if s.sim.dot_max_incidence_deg is not None:
        photometry = replace(photometry, max_incidence_rad=float(np.deg2rad(s.sim.dot_max_incidence_deg)))
    # the simulated cell's own sensor (noise, bit depth, gain) and exposure: the brightness of its dots, how many clip
    # and how precise the rest are; a real camera's exposure and gain say nothing of the twin's light, which stays at
    # the simulator's reference (its bit depth is kept)
    sim = s.cell.backend == "sim"
    world = World(job.part, s.base_from_part(), s.flange_from_cam(), job.intrinsics, seed=TWIN_SEED)
    exposure = {"exposure_s": s.camera.exposure_s} if sim else {}
    sensor = Sensor().with_noise_scale(s.sim.noise if sim else 1.0).with_camera(s.camera.pixel_format,
                                                                                s.camera.gain_db if sim else None)
    # the lens's defocus at each dot's depth, from the job's depth of field (a real lens's as well as the simulator's)
    sensor = sensor.with_depth_of_field(s.camera.near * s.scale, s.camera.far * s.scale, s.sim.circle_of_confusion_px)
    return SimCamera(world, photometry=photometry, sensor=sensor,
                     rng=np.random.default_rng(TWIN_SEED), coded_family=s.job.coded_family, **exposure)


#: the code the renders' measurement depends on: a change to any of them makes a cached result stale (every project
#: module these import, tests/test_preanalysis.py checks; the detector model is applied after the cache)
_SOURCES = ("calibration/dots.py", "calibration/dot_noise.py", "calibration/dot_split.py", "calibration/ellipse_fit.py",
            "calibration/targets.py", "calibration/camera.py", "calibration/ringcodes.py", "calibration/errors.py",
            "planning/visibility.py", "planning/cache.py", "planning/stations.py", "sim_backend/coverage.py",
            "drivers/protocols.py", "sim_backend/sim_camera.py", "sim_backend/world.py", "cell/stages/imaging.py",
            "cell/stages/surface_labels.py", "cell/stages/preanalysis.py", "drivers/pixels.py",
            "calibration/polarity.py")


def _cache_key(job, poses: np.ndarray) -> str:
    """Everything the rendered rays depend on: the part, the camera, the poses, the twin's settings, the code."""
    import hashlib
    from pathlib import Path

    h = hashlib.sha256()
    part, t = job.part, job.part.targets
    for a in (part.mesh.vertices, part.mesh.faces, t.xyz, t.normals, np.asarray(t.code), poses,
              job.spec.base_from_part(), job.spec.flange_from_cam()):
        h.update(np.ascontiguousarray(a).tobytes())
    i = job.intrinsics
    s = job.spec
    h.update(repr((list(t.ids), list(t.kind), part.target_diameter_m, part.coded_size_m, i.fx_px, i.fy_px, i.cx_px,
                   i.cy_px, i.width, i.height, i.k1, i.k2, i.k3, i.p1, i.p2, s.sim.noise, s.sim.dot_max_incidence_deg,
                   s.sim.circle_of_confusion_px,
                   s.cell.backend, s.job.coded_family, repr(s.camera))).encode())
    root = Path(__file__).resolve().parents[2]
    for f in _SOURCES:
        h.update((root / f).read_bytes())
    return h.hexdigest()[:32]


def cached_rendered_rays(job, part_from_cam: np.ndarray, cache_dir, progress=None) -> PredictedRays:
    """:func:`rendered_rays`, kept in ``cache_dir`` (keyed by everything they depend on, the code included).

    Written and read as the planning caches are (:mod:`planning.cache`: a digest of every array, fsync'ed and
    renamed): a damaged file (a flipped byte, a torn write) is refused, deleted and rendered again, and the job's
    journal says so (a note in the stage that ran it), never a quietly different predicted sigma (decision 0060).
    """
    import json
    from pathlib import Path

    from planning.cache import load_arrays, save_arrays

    names = ("obs_image", "obs_target", "bg_cov", "clipped_share", "ellipse", "cov", "line", "blur", "clip_bound")
    poses = np.asarray(part_from_cam, dtype=float)
    path = Path(cache_dir) / f"preanalysis-{_cache_key(job, poses)}.npz"
    damaged: list[str] = []
    z = load_arrays(path, (*names, "facts"), on_damaged=damaged.append)
    if z is not None:
        try:
            r = PredictedRays(*(z[k] for k in names))
            r.facts = json.loads(str(z["facts"]))
            return r
        except ValueError as exc:  # arrays that verify but do not read as rays: a foreign file
            damaged.append(f"{type(exc).__name__}: {exc}")
    if damaged:
        from cell.record.jobfolder import recording_now

        msg = (f"pre-analysis cache {path.name} refused ({damaged[0]}): deleted, the plan's images rendered and "
               "measured again")
        rec = recording_now()
        if rec is not None:
            rec[0].append("note", text=msg)
    r = rendered_rays(job, poses, progress)
    try:
        save_arrays(path, {k: getattr(r, k) for k in names} | {"facts": np.array(json.dumps(r.facts))})
    except OSError:  # a read-only cache: measured every time
        pass
    if damaged:  # PLAN says it on the console and in the run log too (plan.json prediction.facts.cache_refused)
        r.facts = dict(r.facts) | {"cache_refused": msg}
    return r


def rendered_rays(job, part_from_cam: np.ndarray, progress=None) -> PredictedRays:
    """Render every planned station's image of the nominal part and name its dots as MEASURE will.

    Two images at a time (rendering and detection release the GIL for most of their work); each image has its
    own noise stream, so the result does not depend on the order the threads take them in."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from cell.stages.imaging import detection_options, measure_image, surface_labeller
    from planning.visibility import Occluder

    detection = detection_options(job.spec.camera)
    local = threading.local()
    poses = np.asarray(part_from_cam, dtype=float)
    done = [0]
    lock = threading.Lock()

    def one(i: int):
        if not hasattr(local, "cam"):  # per thread: the camera's buffers and the ray caster are not shared
            local.cam, local.occluder = twin_camera(job), Occluder(job.part.mesh)
            local.surfaces = surface_labeller(job.spec.camera, job.part)  # as MEASURE: [camera] background_mask
        local.cam.rng = np.random.default_rng([TWIN_SEED, i])
        image, _ = local.cam.render(poses[i])
        m, counts = measure_image(image, job.part, job.intrinsics, invert(poses[i]), local.occluder,
                                  detection=detection, coded_family=job.spec.job.coded_family, surfaces=local.surfaces)
        with lock:
            done[0] += 1
            if progress is not None:
                progress("pre-analysis", done[0] / len(poses))
        lv = counts.get("noise_levels")
        return m, lv is not None and float(lv[1]) != 0.0

    workers = max(1, min(2, os.cpu_count() or 1, len(poses)))
    with ThreadPoolExecutor(max_workers=workers) as ex:
        found = list(ex.map(one, range(len(poses))))
    img_idx, tgt, bg, clip, ell, cov, line, blur, cb = [], [], [], [], [], [], [], [], []
    lost: dict[str, int] = {}
    for i, (m, measured) in enumerate(found):
        k = len(m.target)
        cov.append(np.full((k, 2, 2), np.nan) if m.cov is None else np.asarray(m.cov, dtype=float).reshape(k, 2, 2))
        line.append(np.full(k, measured))
        blur.append(np.full(k, np.nan) if m.blur_px2 is None else np.asarray(m.blur_px2, dtype=float).reshape(k))
        img_idx.append(np.full(k, i))
        tgt.append(np.asarray(m.target, dtype=int))
        bg.append(np.zeros((k, 2, 2)) if m.bg_cov is None else np.asarray(m.bg_cov, dtype=float).reshape(k, 2, 2))
        clip.append(np.zeros(k) if m.clipped_share is None else np.asarray(m.clipped_share, dtype=float).reshape(k))
        ell.append(np.zeros(k, dtype=bool) if m.ellipse is None else np.asarray(m.ellipse, dtype=bool).reshape(k))
        cb.append(np.zeros((k, 2)) if m.clip_bound is None else np.asarray(m.clip_bound, dtype=float).reshape(k, 2))
        for _, why in m.dropped:
            key = "shape unlike its ellipse" if why.startswith("shape") else why.split(":")[0].split("(")[0].strip()
            lost[key] = lost.get(key, 0) + 1
    r = PredictedRays(np.concatenate(img_idx).astype(int), np.concatenate(tgt).astype(int), np.concatenate(bg),
                      np.concatenate(clip), np.concatenate(ell), np.concatenate(cov), np.concatenate(line),
                      np.concatenate(blur), np.concatenate(cb))
    r.facts = {"images_rendered": len(poses), "rays": len(r.obs_target),
               "rays_with_background_bound": int(np.count_nonzero(np.trace(r.bg_cov, axis1=1, axis2=2) > 0)),
               "rays_clipped": int(np.count_nonzero(r.clipped_share > 0)), "dots_left_unnamed": lost}
    return r


def geometric_rays(job, part_from_cam: np.ndarray) -> PredictedRays:
    """Every dot the detector could see (incidence up to 85 deg, margin 0): the fallback without renders."""
    from planning.visibility import VisibilityOptions, compute_visibility

    c, k = job.spec.camera, job.spec.scale
    seeable = VisibilityOptions(margin_px=0.0, incidence_max_rad=float(np.deg2rad(NAMING_INCIDENCE_DEG)),
                                min_target_px=1.0, near_m=c.near * k, far_m=c.far * k)
    visible = compute_visibility(job.part, job.intrinsics, part_from_cam, seeable)
    visible &= (job.part.targets.kind != "coded")[None, :]
    obs_image, obs_target = np.nonzero(visible)
    return PredictedRays(obs_image, obs_target, method="geometric",
                         facts={"rays": len(obs_target)})


def adjust_prediction(job, part_from_cam: np.ndarray, rays: PredictedRays) -> tuple[np.ndarray, dict]:
    """The job's adjustment on exact observations over ``rays``, weighted as ADJUST weighs them.

    Returns the predicted covariance ``(n, 3, 3)`` (m^2, a priori variance) and what the shared misfit added.
    Raises CalibrationError when the network cannot be adjusted (e.g. an image with fewer than 3 targets)."""
    from cell.stages.adjust import WILD_SIGMA_FACTOR, _wild_targets
    from cell.stages.screen import screen_network

    poses = np.array([invert(T) for T in part_from_cam])
    xyz = job.part.targets.xyz
    if len(rays.obs_image) == 0:  # e.g. [sim] dot_max_incidence_deg = 1: an internal AttributeError before
        raise CalibrationError("pre-analysis: the plan's simulated images show no dot the detector measures (the "
                               "light, the exposure, the simulated cell's settings?): nothing to predict from")
    order = np.lexsort((rays.obs_target, rays.obs_image))  # image by image, as the bundle groups them
    img, tgt = rays.obs_image[order], rays.obs_target[order]
    uv = np.zeros((len(img), 2))
    for i in np.unique(img):
        sel = img == i
        uv[sel] = project(job.intrinsics, poses[i], xyz[tgt[sel]])
    # what ADJUST's screening will drop (a target with one ray or nearly parallel ones, an image with too few dots,
    # a block not linked to the rest), then a target the adjustment cannot determine, as ADJUST drops it
    ids = list(job.part.targets.ids)
    scale_pairs = [tuple(bar[:2]) for bar in job.scale_bars]
    drop: dict[int, str] = {}
    for _ in range(3):
        scr = screen_network(img, tgt, uv, job.intrinsics, poses, len(xyz), scale_pairs=scale_pairs, drop_targets=drop,
                             ids=ids)
        if scr.keep_images.sum() < 2:
            raise CalibrationError("pre-analysis: fewer than 2 images usable")
        res, added = _adjust_exact(job, poses, img, tgt, uv, scr, rays, order)
        wild, _, _ = _wild_targets(res)  # ADJUST's own rule
        if not wild.size:
            break
        drop.update({int(t): f"sigma beyond {WILD_SIGMA_FACTOR:g} x the median" for t in wild})
    added["screened_targets"] = sorted(ids[t] for t in scr.targets)
    added["screened_images"] = int((~scr.keep_images).sum())
    added["scale_established"] = bool(scr.scale_ok) if scale_pairs else None
    if scale_pairs and not scr.scale_ok:
        added["scale_reason"] = scr.scale_reason
    if scr.bars_out and scr.scale_ok:  # some bars lost, not all: ADJUST measures with the others
        added["scale_bars_left_out"] = [scr.bars_out[j] for j in sorted(scr.bars_out)]
    return res.cov, added


def _adjust_exact(job, poses, img, tgt, uv, scr, rays: PredictedRays, order):
    """One adjustment of the exact observations the screening kept (NaN covariance for the targets it dropped)."""
    from calibration.bundle import BundleOptions, bundle_adjust
    from calibration.bundle.coherent import scale_bar_gains
    from calibration.detector_model import observation_covariances
    from cell.stages.dot_precision import blur_weights, noise_weights, rms_sigma, stated_usable
    from cell.stages.adjust import (_add_coherent_background, bundle_config, centroid_bounds_scaled, model_diameters,
                                    model_sigmas)
    from cell.stages.clip_level import clip_covariances

    xyz = job.part.targets.xyz
    kept = np.flatnonzero(scr.keep_images)
    new_index = np.full(len(poses), -1)
    new_index[kept] = np.arange(len(kept))
    sel = scr.keep_obs & scr.keep_images[img]
    poses = poses[kept]
    img, tgt, uv = new_index[img[sel]], tgt[sel], uv[sel]
    sig = model_sigmas(job, job.spec.cell.backend, poses, img, tgt, job.intrinsics.fx_px)  # as ADJUST weighs them
    if rays.blur is not None:  # as ADJUST: the blur term, by the blur each dot's render shows (decision 0049)
        sig = blur_weights(sig, rays.blur[order][sel])[0]
    bg = None if rays.bg_cov is None else rays.bg_cov[order][sel]
    if bg is not None:  # as ADJUST: a centroid-centred dot's bound at the centroid's share (decision 0037)
        bg = centroid_bounds_scaled(bg, np.zeros(len(bg), dtype=bool) if rays.ellipse is None
                                    else rays.ellipse[order][sel])[0]
    clip = None if rays.clipped_share is None else rays.clipped_share[order][sel]
    noise, stated = sig, None  # as ADJUST: a centroid-centred dot's noise as the detector states it (decision 0048)
    if job.spec.camera.dot_precision == "stated":
        stated = {"source": "model", "why": "no renders to state the dots' noise (geometric rays)"}
        if rays.cov is not None:
            ell = np.zeros(len(sig), dtype=bool) if rays.ellipse is None else rays.ellipse[order][sel]
            ok, why = stated_usable(rays.cov[order][sel], ell, rays.line[order][sel])
            noise = noise_weights(sig, rays.cov[order][sel], ok)
            stated = {"source": "stated", "observations_stated": int(ok.sum()), "observations_by_model": why}
    # as ADJUST: a clipped dot's bound for its unknown level, in its weight and shared by its views (decision 0050)
    clip_cov = None if rays.clip_bound is None else clip_covariances(rays.clip_bound[order][sel])
    obs_sigma = noise if bg is None and clip is None else observation_covariances(
        noise, bg, clipped_share=clip, diameter_px=model_diameters(job, poses, img, tgt, job.intrinsics.fx_px)
    ) + (0.0 if clip_cov is None else clip_cov)
    config = bundle_config(job, [j for j in range(len(job.scale_bars)) if j not in scr.bars_out])
    sigma_px = float(np.sqrt(np.mean(rms_sigma(noise) ** 2)))
    res = bundle_adjust(img, tgt, uv, job.intrinsics, poses, xyz,
                        BundleOptions(sigma_px=sigma_px, a_posteriori=False, snooping=False), config, obs_sigma_px=obs_sigma)
    added: dict = {}
    if bg is not None:
        bars = config.scale_bars
        K = scale_bar_gains(res.covariance, res.points, bars, res.variance_factor)[0] if bars else None
        added = _add_coherent_background(res, bg, img, tgt, list(job.part.targets.ids), bars, K, clip_cov)
    if stated is not None:  # plan.json says which dots the prediction weighed by the statement, and why not the rest
        added["dot_precision"] = stated
    from cell.stages.shared_terms import add_held_lens, holds_cell_lens

    if holds_cell_lens(job):  # as ADJUST: the held lens's uncertainty
        added["held_lens"] = add_held_lens(res, img, tgt, uv, config, sigma_px, job.cell["lens"]["cov"])
    return res, added


def measurement_prediction(job, part_from_cam: np.ndarray, progress=None, cache_dir=None):
    """Predicted covariance ``(n, 3, 3)``, rays per target ``(n,)`` and the facts for plan.json; None when the job
    does not weight with the detector model or the network cannot be adjusted."""
    if job.spec.camera.observation_weights != "model":
        return None
    part_from_cam = np.asarray(part_from_cam, dtype=float)
    fallback = None
    try:
        rays = (rendered_rays(job, part_from_cam, progress) if cache_dir is None
                else cached_rendered_rays(job, part_from_cam, cache_dir, progress))
    except (CalibrationError, ValueError, MemoryError) as e:  # a render or a measurement that cannot run
        fallback = f"the renders could not be measured ({e}); rays from the geometric visibility, no image terms"
        rays = geometric_rays(job, part_from_cam)
    if rays.method == "rendered" and len(rays.obs_image) == 0:  # a plan whose images will show nothing to measure
        raise PlanningError("pre-analysis: the plan's simulated images show no dot the detector measures (the light, "
                            "the exposure, the simulated cell's settings?); the robot is not moved for images that measure "
                            "nothing")
    try:
        cov, added = adjust_prediction(job, part_from_cam, rays)
    except CalibrationError:
        if rays.method != "rendered":
            return None
        # the renders lost too much for an image to be adjusted: the geometric rays still give a prediction
        fallback = "the rendered rays could not be adjusted; rays from the geometric visibility, no image terms"
        rays = geometric_rays(job, part_from_cam)
        try:
            cov, added = adjust_prediction(job, part_from_cam, rays)
        except CalibrationError:
            return None
    n = len(job.part.targets.xyz)
    facts = dict(rays.facts)
    facts["rays_from"] = ("renders of the nominal part from the planned stations, measured as MEASURE does"
                          if rays.method == "rendered" else "geometric visibility (incidence up to 85 deg)")
    if fallback:
        facts["fallback"] = fallback
    facts["screened_targets"] = added.pop("screened_targets", [])  # ADJUST's screening will drop them too
    facts["screened_images"] = added.pop("screened_images", 0)
    facts["scale_established"] = added.pop("scale_established", None)
    if "scale_reason" in added:
        facts["scale_reason"] = added.pop("scale_reason")
    if "scale_bars_left_out" in added:
        facts["scale_bars_left_out"] = added.pop("scale_bars_left_out")
    if "dot_precision" in added:
        facts["dot_precision"] = added.pop("dot_precision")
    if "held_lens" in added:  # the held lens's share (PLAN keeps each target's sigma without it, then the summary)
        facts["held_lens"] = added.pop("held_lens")
    if added:
        facts["shared_misfit_targets"] = added.get("n_targets", 0)
        facts["scale_bar_ends"] = added.get("scale_bar_ends", [])
    return cov, np.bincount(rays.obs_target, minlength=n), facts
