"""The robot side of a whole job against URSim or a real UR (``CELL_UR_HOST``; motion needs
``CELL_UR_ALLOW_MOTION=1``): plan, validate, drive the arm through every station with settle detection
from RTDE joint speeds, the simulated camera rendering from the pose the robot reports; the job must end
DONE with its MCAP holding one good exposure per station tied to the robot's state.

The example bracket's placement fits a UR10e (URSim: ``ROBOT_MODEL=UR10``); keep the cell clear.
"""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from jobutil import job_variant, records, run_cell  # noqa: E402

HOST = os.environ.get("CELL_UR_HOST")
pytestmark = [pytest.mark.hil, pytest.mark.skipif(not HOST, reason="CELL_UR_HOST not set: no robot to test"),
              pytest.mark.skipif(os.environ.get("CELL_UR_ALLOW_MOTION") != "1",
                                 reason="CELL_UR_ALLOW_MOTION=1 not set: this test moves the arm through a job")]


def test_example_job_runs_on_the_robot_and_ties_every_frame_to_its_state(tmp_path):
    job = job_variant(tmp_path / "job", {"cell": {"backend": "ur", "host": HOST,
                                                  "robot": os.environ.get("CELL_UR_MODEL", "ur10e"),
                                                  "max_joint_speed_rad_s": 0.5}})
    run = run_cell("run", str(job), "--archive", str(tmp_path / "archive"), "--yes", timeout=1800)
    assert run.code == 0 and run.doc["status"] == "DONE", run.stderr[-3000:]
    folder = Path(run.doc["folder"])
    done = [r for r in records(folder) if r["event"] == "station_done"]
    n = len(json.loads((folder / "plan.json").read_text())["stations"])
    assert len(done) == n
    from cell.record.runlog import read_messages

    ex = [m for f in sorted(folder.glob("run*.mcap")) for t, m in read_messages(f) if t == "/camera/exposure"]
    ok = [e for e in ex if e["outcome"] == "ok"]
    assert len(ok) == n and all(e["max_joint_speed_rad_s"] < 0.002 for e in ok)
