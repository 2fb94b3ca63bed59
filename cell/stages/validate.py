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
    _, summary = validate_plan_doc(job, plan)
    return summary


def run(ctx) -> None:
    """VALIDATE: IK branch, collision-free moves and execution order for every planned station."""
    doc = ctx.folder.read_json("plan.json")
    doc, summary = validate_plan_doc(ctx.job, doc)
    atomic_write_json(ctx.folder.file("plan.json"), doc)
    ctx.say(f"  execution order {summary['order']}; estimated cycle time {summary['cycle_time_s']:.1f} s")
