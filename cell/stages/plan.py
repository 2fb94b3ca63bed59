"""PLAN and VALIDATE: design the network, then prove the robot can execute it."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.errors import PlanningError, ReachabilityError
from cell.loadedjob import LoadedJob
from cell.record.jobfolder import atomic_write_json
from cell.setup import collision_world, planner_options, robot_model
from planning.planner import NetworkPlan, cheapest_network, plan_network
from planning.reachability import ReachabilityDB
from planning.visibility import VisibilityDB, default_cache_dir


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
            from planning.reachability import reachability_mask

            world, bfp, ffc = collision_world(job), job.spec.base_from_part(), job.spec.flange_from_cam()
            extra["reachable_fn"] = lambda T: reachability_mask(robot, bfp, ffc, T, world).reachable
        plan = fn(job.part, job.intrinsics, opts, np.random.default_rng(job.spec.job.seed), reachable=reachable,
                  cache_dir=cache_dir, progress=report, seed=job.spec.job.seed, db=db, **extra)
    except PlanningError as exc:
        if not isinstance(exc, ReachabilityError) and (~reachable & useful).sum() > 0.5 * useful.sum():
            raise ReachabilityError(
                f"{exc} ({int((~reachable & useful).sum())} of {int(useful.sum())} useful candidate stations are "
                "out of the robot's reach or collide)"
            ) from None
        raise
    facts = {"candidates": int(len(reachable)), "reachable": n_ok, "visibility_cached": bool(db.from_cache),
             "reachability_cached": bool(reach.loaded)}
    return plan, facts


def run(ctx) -> None:
    """PLAN: the network design; plan.json and figures/plan.png."""
    p, facts = make_plan(ctx.job, progress=ctx.progress)
    doc = p.to_plan_dict() | {"databases": facts}
    atomic_write_json(ctx.folder.file("plan.json"), doc)
    try:
        from planning.plot import plot_plan

        plot_plan(ctx.job.part, p, ctx.folder.file("figures/plan.png"))
    except ImportError:
        pass
    ctx.say(f"  {len(p.station_ids)} stations; predicted sigma max {p.predicted_sigma_max_m * 1e6:.1f} um, "
            f"mean {p.predicted_sigma_mean_m * 1e6:.1f} um")
