"""PLAN and VALIDATE: design the network, then prove the robot can execute it."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from calibration.errors import PlanningError, ReachabilityError
from cell.loadedjob import LoadedJob
from cell.record.jobfolder import atomic_write_bytes, atomic_write_json
from cell.setup import collision_world, planner_options, robot_model
from cell.stages.preanalysis import measurement_prediction
from planning.planner import NetworkPlan, cheapest_network, plan_network
from planning.reachability import ReachabilityDB
from planning.visibility import VisibilityDB, default_cache_dir


def load_databases(job: LoadedJob, opts, cache_dir: Path, report) -> tuple[VisibilityDB, ReachabilityDB, object]:
    """The job's candidate stations: the visibility database and the robot's reachability of each (both cached).

    Used by PLAN and by CLOSE_LOOP (which must see the same candidates). Returns ``(db, reach, robot)``.
    """
    from dataclasses import replace

    from planning.visibility import VisibilityOptions

    vis_opts = replace(opts.visibility or VisibilityOptions(), incidence_max_rad=opts.incidence_max_rad)
    sphere = replace(opts.sphere, max_roll_rad=0.0, max_offset_m=0.0)
    db = VisibilityDB.load_or_build(job.part, job.intrinsics, sphere, vis_opts, opts.n_candidates, cache_dir, report,
                                    n_shells=opts.n_shells, backend=opts.backend)
    report("reachability", 0.0)
    robot = robot_model(job)
    reach = ReachabilityDB.load_or_build(robot, job.spec.base_from_part(), job.spec.flange_from_cam(),
                                         db.part_from_cam, collision_world(job), cache_dir=cache_dir)
    report("reachability", 1.0)
    return db, reach, robot


def make_plan(job: LoadedJob, progress=None, cache_dir: Path | None = None,
              lower_bound: bool | None = None) -> tuple[NetworkPlan, dict]:
    """Design the network for a job: visibility database, reachability database, evolutionary search.

    ``lower_bound``: overrides the job's ``[planning] lower_bound`` (planning.bound).
    Returns the plan and facts about the databases (candidates, reachable, cached).
    """
    from dataclasses import replace

    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    opts = planner_options(job)
    if lower_bound is not None:
        opts = replace(opts, lower_bound=bool(lower_bound))
    report = progress or (lambda s, f: None)

    db, reach, robot = load_databases(job, opts, cache_dir, report)
    reachable = reach.reachable
    n_ok = int(reachable.sum())
    useful = db.visible.any(axis=1)
    if n_ok == 0 or not (reachable & useful).any():
        reasons = {}
        import re

        for r in reach.result.reason[~reachable]:
            kind = re.split(r"[:(]|\s\d", str(r))[0].strip()  # "out of reach 3.400 m > ..." -> "out of reach"
            reasons[kind] = reasons.get(kind, 0) + 1
        top = ", ".join(f"{v} {k}" for k, v in sorted(reasons.items(), key=lambda kv: -kv[1])[:3])
        bfp = job.spec.base_from_part()[:3, 3]
        raise ReachabilityError(
            f"{job.path}: the robot ({job.spec.cell.robot}) reaches none of the {len(reachable)} candidate stations "
            f"around the part placed at {np.round(bfp, 3).tolist()} m ({top}): move the part closer "
            "(cell.base_from_part) or use a larger robot"
        )
    fn = cheapest_network if job.spec.planning.mode == "cheapest" else plan_network
    try:
        extra = {}
        if fn is plan_network:
            from planning.reachability import ReachabilityOptions, reachability_mask

            world, bfp, ffc = collision_world(job), job.spec.base_from_part(), job.spec.flange_from_cam()
            fast = ReachabilityOptions(compute_distances=False)  # the polish needs yes/no, not the margins
            extra["reachable_fn"] = lambda T: reachability_mask(robot, bfp, ffc, T, world, fast).reachable
        plan = fn(job.part, job.intrinsics, opts, np.random.default_rng(job.spec.job.seed), reachable=reachable,
                  cache_dir=cache_dir, progress=report, seed=job.spec.job.seed, db=db, **extra)
    except PlanningError as exc:
        if not isinstance(exc, ReachabilityError) and (~reachable & useful).sum() > 0.5 * useful.sum():
            raise ReachabilityError(
                f"{exc} ({int((~reachable & useful).sum())} of {int(useful.sum())} useful candidate stations are "
                "out of the robot's reach or collide)"
            ) from None
        raise
    facts = {"candidates": len(reachable), "reachable": n_ok, "visibility_cached": bool(db.from_cache),
             "reachability_cached": bool(reach.loaded)}
    return plan, facts


def unmeasurable_targets(job: LoadedJob, cache_dir: Path | None = None) -> dict:
    """Targets that fewer than ``[planning] min_rays`` reachable candidate stations can measure (before planning).

    The same visibility and reachability databases as PLAN (cached), so ``cell check`` says what PLAN would
    refuse. Returns {``min_rays``, ``candidates``, ``reachable``, ``unmeasurable``: ids, ``rays``: per id the count,
    and with scale bars ``scale_bars``: per bar {``ends``, ``candidates``: reachable candidates seeing each with a ray
    the bar counts on (:func:`planning.scalebar.trusted_views`), ``rays_min``}}.
    """
    from dataclasses import replace as _replace

    from planning.visibility import VisibilityOptions

    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    opts = planner_options(job)
    vis_opts = _replace(opts.visibility or VisibilityOptions(), incidence_max_rad=opts.incidence_max_rad)
    sphere = _replace(opts.sphere, max_roll_rad=0.0, max_offset_m=0.0)
    db = VisibilityDB.load_or_build(job.part, job.intrinsics, sphere, vis_opts, opts.n_candidates, cache_dir,
                                    lambda s, f: None, n_shells=opts.n_shells, backend=opts.backend)
    reach = ReachabilityDB.load_or_build(robot_model(job), job.spec.base_from_part(), job.spec.flange_from_cam(),
                                         db.part_from_cam, collision_world(job), cache_dir=cache_dir)
    rays = db.visible[reach.reachable].sum(axis=0)
    coded = job.part.targets.kind == "coded"
    bad = np.flatnonzero((rays < opts.min_rays) & ~coded)
    ids = job.part.targets.ids
    out = {"min_rays": int(opts.min_rays), "candidates": len(reach.reachable),
           "reachable": int(reach.reachable.sum()), "unmeasurable": [ids[j] for j in bad],
           "rays": {ids[j]: int(rays[j]) for j in bad},
           "buried": _buried(job, bad, vis_opts.ray_offset_m)}
    if job.scale_bars:  # the bars' ends need more rays than any target, and sure ones (planning/scalebar.py)
        from planning.scalebar import RAYS_FACTOR, trusted_views

        t = job.part.targets
        out["scale_bars"] = []
        for a, b, *_ in job.scale_bars:
            e = [a, b]
            sure = trusted_views(job.intrinsics, db.part_from_cam, t.xyz[e], t.normals[e],
                                 db.visible[:, e] & reach.reachable[:, None], opts.incidence_max_rad).sum(axis=0)
            out["scale_bars"].append({"ends": [ids[k] for k in e], "candidates": [int(k) for k in sure],
                                      "rays_min": RAYS_FACTOR * int(opts.min_rays)})
    return out


def _buried(job: LoadedJob, which: np.ndarray, offset_m: float) -> list[str]:
    """Of the targets ``which``, those the part's own surface covers within two dot diameters along their normal:
    under the surface or facing into the part (a wrong targets file or unit), which no placement or limit mends."""
    if not len(which):
        return []
    from planning.visibility import Occluder

    t = job.part.targets
    xyz, n = t.xyz[which], t.normals[which]
    reach = offset_m + 2 * job.part.target_diameter_m
    hit = Occluder(job.part.mesh, backend=planner_options(job).backend).occluded(xyz + offset_m * n, xyz + reach * n)
    return [t.ids[j] for j, h in zip(which, hit) if h]


def run(ctx) -> None:
    """PLAN: the network design; plan.json and figures/plan.png."""
    from cell.setup import viewing_sphere

    note = viewing_sphere(ctx.job)[1]
    if note:
        ctx.log.log("info", note)
        ctx.say(f"  {note}")
    p, facts = make_plan(ctx.job, progress=ctx.progress)
    doc = p.to_plan_dict() | {"databases": facts, "framing": note}
    pred = measurement_prediction(ctx.job, np.asarray(p.part_from_cam, dtype=float), progress=ctx.progress,
                                  cache_dir=default_cache_dir())
    if pred is None and ctx.job.spec.camera.observation_weights == "model":
        doc["prediction"] = {"method": "limiting error propagation of the search (the pre-analysis could not run)"}
        ctx.log.log("warning", "plan: pre-analysis failed; predicted covariance is the search's (fixed orientations)")
        ctx.say("  WARNING predicted precision from the search's limiting error propagation (pre-analysis failed)")
    if pred is not None:  # predicted = what the bundle will achieve: its rays, the detector's precision
        cov, n_rays, pre_facts = pred
        if pre_facts.get("cache_refused"):  # a damaged cache file: rebuilt, and said (decision 0060)
            ctx.log.log("warning", f"plan: {pre_facts['cache_refused']}")
            ctx.say(f"  WARNING {pre_facts['cache_refused']}")
        retro = ctx.job.part.targets.kind != "coded"
        unpredicted = []
        # the held lens's share of each target's variance (decision 0056): predicted / achieved compares the images'
        # precision without it (decision 0062); the plan keeps its summary, each target its sigma without it
        held = pre_facts.get("held_lens") or {}
        lens_var = held.pop("added_variance_m2", None)
        lens_var = np.zeros(len(cov)) if not lens_var or len(lens_var) != len(cov) else \
            np.array([0.0 if v is None else float(v) for v in lens_var])
        for t, c_, n_, r_, v_ in zip(doc["targets"], cov, n_rays, retro, lens_var):
            t["planned_cov"] = t["predicted_cov"]
            # a target the renders do not measure (or ADJUST's screening would drop) has no prediction: not the
            # search's optimistic one in its place
            t["predicted_cov"] = c_ if np.isfinite(c_).all() else None
            t["predicted_rays"] = int(n_)
            if held.get("carried") and t["predicted_cov"] is not None:
                t["predicted_sigma_images_m"] = float(np.sqrt(max(np.trace(c_) - v_, 0.0)))
            if r_ and t["predicted_cov"] is None:
                unpredicted.append(t["id"])
        pre_facts["targets_not_predicted"] = unpredicted
        if unpredicted:
            msg = (f"plan: the renders of the plan do not measure {len(unpredicted)} target(s) ("
                   f"{', '.join(unpredicted[:8])}{' ...' if len(unpredicted) > 8 else ''}): no predicted precision; "
                   "they are likely to be reported not measured")
            ctx.log.log("warning", msg)
            ctx.say(f"  WARNING {msg}")
        sig = np.array([np.sqrt(np.trace(np.asarray(t["predicted_cov"], dtype=float))) if t["predicted_cov"] is not None
                        else np.nan for t in doc["targets"]])
        doc["predicted_sigma_max_m"] = float(np.nanmax(sig)) if np.isfinite(sig).any() else float("nan")
        doc["predicted_sigma_mean_m"] = float(np.nanmean(sig)) if np.isfinite(sig).any() else float("nan")
        doc["prediction"] = {"method": "pre-analysis: the job's bundle adjustment (self-calibration, datum) on exact "
                                       "observations of the nominal targets from the planned stations",
                             "rays": pre_facts["rays_from"],
                             "image_precision": ("the detector's stated covariance of each centroid-centred dot on the "
                                                 "renders, the detector model for the others (decision 0048; facts "
                                                 "dot_precision)" if ctx.job.spec.camera.dot_precision == "stated"
                                                 else "detector model (calibration/data/detector_precision.json)")
                             + ", with the background bounds and clipped shares of the renders where rendered",
                             "facts": pre_facts}
        if pre_facts.get("scale_established") is False:  # ADJUST would fault with this plan's images
            msg = (f"plan: the renders of the plan do not establish the scale ({pre_facts.get('scale_reason')}): the "
                   "prediction is a free network's, and REPORT will fault unless the images see both ends better")
            ctx.log.log("warning", msg)
            ctx.say(f"  WARNING {msg}")
        for why in pre_facts.get("scale_bars_left_out") or []:  # ADJUST would leave this bar out, use the others
            msg = f"plan: the renders of the plan do not measure a scale bar ({why}): ADJUST will use the other bars"
            ctx.log.log("warning", msg)
            ctx.say(f"  WARNING {msg}")
        if pre_facts.get("fallback"):
            ctx.log.log("warning", f"plan: pre-analysis: {pre_facts['fallback']}")
            ctx.say(f"  WARNING pre-analysis: {pre_facts['fallback']}")
        p = replace(p, predicted_sigma_max_m=doc["predicted_sigma_max_m"],
                    predicted_sigma_mean_m=doc["predicted_sigma_mean_m"])
    bar_rendered: list[list] = [[] for _ in p.scale_bars]
    if p.scale_bars and pred is not None and not pred[2].get("fallback"):  # the renders' word on the ends
        from planning.scalebar import rendered_rays_note

        bar_rendered = [rendered_rays_note(d, [int(pred[1][k]) for k in bar[:2]])
                        for d, bar in zip(doc["scale_bars"], ctx.job.scale_bars)]
    if ctx.job.target_thickness_m:  # plan.json's xyz is the CAD nominal (ARCHITECTURE.md), not the targets' faces
        cad = ctx.job.surface_points(ctx.job.part.targets.xyz)
        index = ctx.job.part.targets.index()
        for t in doc["targets"]:
            t["xyz"] = cad[index[t["id"]]].tolist()
    atomic_write_json(ctx.folder.file("plan.json"), doc)
    try:
        from planning.plot import plot_plan

        plot_plan(ctx.job.part, p, ctx.folder.file("figures/plan.png"), write=atomic_write_bytes)
    except ImportError:
        pass
    ctx.say(f"  {len(p.station_ids)} stations; predicted sigma max {p.predicted_sigma_max_m * 1e6:.1f} um, "
            f"mean {p.predicted_sigma_mean_m * 1e6:.1f} um")
    if p.unmeasurable_target_ids:  # [planning] unmeasurable = "report": planned for the others, said
        bad = p.unmeasurable_target_ids
        msg = (f"plan: {len(bad)} target(s) cannot be seen by [planning] min_rays = {ctx.job.spec.planning.min_rays} "
               f"reachable stations ({', '.join(bad[:8])}{' ...' if len(bad) > 8 else ''}); planned for the others, "
               "they will be reported not measured unless the images happen to measure them")
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")
    for bar_doc, rendered in zip(p.scale_bars, bar_rendered):  # what the plan did for each bar's ends (planning/scalebar.py)
        from planning.scalebar import bar_warnings

        ctx.folder.append("scale_bar_plan", **{k: bar_doc.get(k) for k in ("ends", "met", "before", "after")},
                          stations_added=[st["id"] for st in bar_doc["stations_added"]])
        for level, line in bar_warnings(bar_doc) + rendered:
            ctx.log.log(level, f"plan: {line}")
            ctx.say(f"  {'WARNING ' if level == 'warning' else ''}{line}")
    weak = int(p.search.get("exact_unlinked") or 0)
    if weak:  # docs/decisions/0031: ADJUST may drop their images, or their block may hang on one image
        msg = (f"plan: {weak} station(s) share fewer than {p.search.get('link_targets')} targets with the rest of the "
               "network, or alone link a "
               "part of it: ADJUST may leave their images out; more stations ([planning] n_stations) or a larger "
               "[planning] incidence_max_deg tie them in")
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")
