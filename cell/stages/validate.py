"""VALIDATE: IK branches, execution order, collision-checked moves and cycle time for a plan."""
from __future__ import annotations

import json
from pathlib import Path

from calibration.errors import InputError
from cell.loadedjob import LoadedJob
from cell.record.jobfolder import atomic_write_json
from cell.setup import collision_world, robot_model
from planning.execution import MotionLimits, apply_to_plan, stations_from_plan, validate_plan


def validate_plan_doc(job: LoadedJob, plan: dict) -> tuple[dict, dict]:
    """Validate a plan.json document for the job's robot and cell; returns the completed plan and a summary.

    Raises ReachabilityError naming the stations that cannot be reached, or collide, and why.
    """
    ids, part_from_cam = stations_from_plan(plan)
    c = job.spec.cell
    limits = MotionLimits(joint_speed_rad_s=c.max_joint_speed_rad_s, joint_accel_rad_s2=c.max_joint_accel_rad_s2,
                          settle_s=c.settle_s)
    ep = validate_plan(robot_model(job), part_from_cam, job.spec.base_from_part(), job.spec.flange_from_cam(),
                       collision_world(job), limits, ids=ids)
    doc = apply_to_plan(plan, ep)
    return doc, {"stations": len(ids), "order": [ep.ids[i] for i in ep.order], "cycle_time_s": ep.cycle_time_s}


def validate_plan_file(job: LoadedJob, path: Path) -> dict:
    """``cell check JOB --plan plan.json``: the dry run."""
    try:
        plan = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: plan file not found") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from None
    plan_is_this_jobs(job, plan, path)
    _, summary = validate_plan_doc(job, plan)
    return summary


def plan_is_this_jobs(job: LoadedJob, plan: dict, path) -> None:
    """Refuse (``InputError``, one line) a plan made for another camera or another part: its stations would be
    reachable and the check OK (an outside check), and the images would not be the ones it planned."""
    import numpy as np

    cam, intr = plan.get("camera"), job.intrinsics
    if isinstance(cam, dict):
        for key in ("width", "height", "fx_px", "fy_px", "cx_px", "cy_px"):
            mine, theirs = float(getattr(intr, key)), cam.get(key)
            if not isinstance(theirs, (int, float)) or not np.isclose(float(theirs), mine, rtol=1e-6, atol=1e-6):
                raise InputError(f"{path}: planned for another camera ({key} {theirs} there, {mine:g} in "
                                 f"{job.path}'s [camera]): plan the job again (cell plan)")
    tl = plan.get("targets")
    if isinstance(tl, list):
        t = job.part.targets
        index = t.index()
        have = {str(x.get("id")): x.get("xyz") for x in tl if isinstance(x, dict)}
        if set(have) != set(index):
            miss, extra = sorted(set(index) - set(have)), sorted(set(have) - set(index))
            raise InputError(f"{path}: planned for other targets ({len(miss)} of the job's missing: "
                             f"{', '.join(miss[:4])}{' ...' if len(miss) > 4 else ''}; {len(extra)} not the job's: "
                             f"{', '.join(extra[:4])}{' ...' if len(extra) > 4 else ''}): plan the job again")
        moved = [i for i, x in have.items() if not (isinstance(x, list) and len(x) == 3 and
                                                    np.allclose(x, t.xyz[index[i]], atol=1e-6))]
        if moved:
            raise InputError(f"{path}: planned for another part: {len(moved)} target(s) elsewhere than in "
                             f"{job.path}'s targets ({', '.join(moved[:4])}{' ...' if len(moved) > 4 else ''}): plan "
                             "the job again")


def run(ctx) -> None:
    """VALIDATE: IK branch, collision-free moves and execution order for every planned station."""
    doc = ctx.folder.read_json("plan.json")
    doc, summary = validate_plan_doc(ctx.job, doc)
    atomic_write_json(ctx.folder.file("plan.json"), doc)
    ctx.say(f"  execution order {summary['order']}; estimated cycle time {summary['cycle_time_s']:.1f} s")
