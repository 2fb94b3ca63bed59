"""The first move of ACQUIRE starts wherever the arm stands, which VALIDATE never saw (it checks the tour from the
plan's start pose): it is checked from the arm's measured joints before anything moves (decision 0061). On the
loopback UR controller with the arm left at a pose whose move to the first station breaks the cell's clearance
(the outside tester's pose: camera vs wrist_1_link 5 mm at 14 % of the move), the job faults before the first move
with one line telling the operator to jog the arm to the start pose; jogged there and resumed, the move is checked
from the measured pose, journalled, and the job completes."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from jobutil import job_variant, records, run_cell, start_loopback_controller

BAD_START = [-0.221, -1.055, 0.874, -0.117, -4.035, -1.341]  # clear of everything by > 40 mm where it stands
START_Q = [0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0]


@pytest.fixture
def controller():
    ctrl = start_loopback_controller("127.0.61", robot="ur10e", time_scale=8.0, joints_rad=BAD_START)
    yield ctrl
    ctrl.close()


@pytest.mark.slow
@pytest.mark.timeout(500)
def test_first_move_from_where_the_arm_stands_is_checked_before_it_is_made(controller, tmp_path):
    from cell.loadedjob import load
    from cell.setup import collision_world, robot_model
    from drivers.ur import URRobot
    from planning.execution import MotionLimits, check_move, lever_arms

    job = job_variant(tmp_path / "job", {"cell": {"backend": "ur", "host": controller.host, "settle_s": 0.05}})
    archive = tmp_path / "archive"
    r = run_cell("run", str(job), "--archive", str(archive), "--yes", timeout=300)
    assert r.code == 1 and r.doc["status"] == "FAULTED", (r.doc, r.stderr[-2000:])
    reason = r.doc["reason"]
    assert "first move" in reason and "not collision-free" in reason and "camera" in reason, reason
    assert "jog the arm to the plan's start pose start_q [0.0, -90.0, 90.0, -90.0, -90.0, 0.0] deg" in reason, reason
    assert "\n" not in reason
    # nothing was sent, the arm never moved
    assert not [c for c in controller.commands if c.name in ("movej", "movel")]
    assert max(np.max(np.abs(q - BAD_START)) for _, q in controller.trace_copy()) < 1e-9
    folder = Path(r.doc["folder"])
    recs = records(folder)
    assert not [x for x in recs if x["event"] in ("station_done", "first_move_checked")]
    # the premise: the validated plan's first move from there is not free by the cell's own check
    plan = json.loads((folder / "plan.json").read_text())
    first = min(plan["stations"], key=lambda s: s["order"])
    assert first["id"] in reason
    jl = load(job)
    model = robot_model(jl)
    chk = check_move(model, collision_world(jl), np.array(BAD_START), np.array(first["joints"]), lever_arms(model),
                     MotionLimits().check_resolution_rad, ("a", "b"), 0.0)
    assert not chk.free

    # the operator jogs the arm to the start pose and resumes: checked from there, journalled, DONE
    with URRobot(controller.host) as arm:
        arm.move_joints(START_Q, 1.0, 1.5)
    r = run_cell("resume", folder.name, "--archive", str(archive), "--yes", timeout=400)
    assert r.code in (0, 1) and r.doc["status"] == "DONE", (r.doc, r.stderr[-2000:])  # 1: the verdict FAIL
    checked = [x for x in records(folder) if x["event"] == "first_move_checked"]
    assert len(checked) == 1 and checked[0]["station"] == first["id"], checked
    np.testing.assert_allclose(checked[0]["joints"], START_Q, atol=1e-3)
    assert checked[0]["min_distance_m"] > 0.005
