"""Triggered exposures in ACQUIRE: settle detection, the frame tied to the robot state, and frames that come
late, twice or never faulting the station, which is retaken and never stored as another station's."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calibration.errors import DriverError
from cell.record.runlog import read_messages
from cell.stages.exposure import _speed, wait_settled
from drivers.protocols import RobotState, SafetyStatus
from jobutil import job_variant, records, run_cell


def _state(q, t, qd=None):
    return RobotState(joints_rad=np.asarray(q, float), base_from_flange=np.eye(4), safety=SafetyStatus(normal=True),
                      timestamp_s=t, joint_speeds_rad_s=None if qd is None else np.asarray(qd, float))


def test_joint_speed_is_the_reported_one_or_from_successive_positions():
    assert _speed(_state(np.zeros(6), 1.0, [0, 0.01, -0.03, 0, 0, 0]), None) == pytest.approx(0.03)
    a, b = _state(np.zeros(6), 1.0), _state([0, 0, 0.002, 0, 0, 0], 1.1)
    assert _speed(b, a) == pytest.approx(0.02)
    assert _speed(a, None) == float("inf")  # one reading without speeds says nothing


class _SwayingArm:
    """A simulated arm swaying after a stop: joint 2 at ``amp * exp(-t / tau) * sin(2 pi f t)`` (controller clock)."""

    def __init__(self, amp, tau, f=3.0):
        import time

        self.t0, self.amp, self.tau, self.f = time.monotonic(), amp, tau, f

    def state(self):
        import time

        t = time.monotonic() - self.t0
        q = np.zeros(6)
        q[2] = self.amp * np.exp(-t / self.tau) * np.sin(2 * np.pi * self.f * t)
        qd = np.zeros(6)
        qd[2] = self.amp * np.exp(-t / self.tau) * (2 * np.pi * self.f * np.cos(2 * np.pi * self.f * t)
                                                    - np.sin(2 * np.pi * self.f * t) / self.tau)
        return _state(q, t, qd)


def test_settling_waits_until_the_sway_has_died_down():
    arm = _SwayingArm(amp=0.01, tau=0.1)
    state, _, peak = wait_settled(arm, speed_tol_rad_s=0.002, hold_s=0.1, timeout_s=3.0)
    # the sway's speed envelope is amp * 2 pi f * exp(-t/tau): below 0.002 rad/s after about 0.45 s
    assert state.timestamp_s > 0.4 and peak < 0.002


def test_an_arm_that_never_settles_faults_the_station():
    arm = _SwayingArm(amp=0.01, tau=1e9)
    with pytest.raises(DriverError, match="station S007: the arm did not settle within 0.3 s"):
        wait_settled(arm, speed_tol_rad_s=0.002, hold_s=0.1, timeout_s=0.3, station="S007")


def _exposures(folder: Path) -> list[dict]:
    return [m for f in sorted(folder.glob("run*.mcap")) for t, m in read_messages(f) if t == "/camera/exposure"]


@pytest.mark.slow
def test_late_duplicate_and_missing_frames_are_retaken_never_stored_as_another_station(tmp_path):
    job = job_variant(tmp_path / "job", {"sim": {"frame_faults": {"2": "late", "5": "duplicate", "7": "missing"},
                                                 "light": True},
                                         "camera": {"frame_timeout_s": 1.5}})
    run = run_cell("run", str(job), "--archive", str(tmp_path / "archive"), timeout=400)
    assert run.code == 0 and run.doc["status"] == "DONE", run.stderr[-2000:]
    folder = Path(run.doc["folder"])
    recs = records(folder)
    order = [s["id"] for s in sorted(json.loads((folder / "plan.json").read_text())["stations"],
                                     key=lambda s: s["order"])]
    faults = [(r["station"], r["outcome"]) for r in recs if r["event"] == "frame_fault"]
    # capture 2 is the 2nd station's first try; its retake is capture 3, so capture 5 is the 4th station's, 7 the 5th's
    assert faults == [(order[1], "late"), (order[3], "duplicate"), (order[4], "missing")]
    done = [r for r in recs if r["event"] == "station_done"]
    assert [r["station"] for r in done] == order
    assert {r["station"]: r["attempts"] for r in done if r["attempts"] > 1} == {order[1]: 2, order[3]: 2, order[4]: 2}
    frame_ids = [r["frame_id"] for r in done]
    assert len(set(frame_ids)) == len(frame_ids)  # no frame stored twice
    shas = [r["sha256"] for r in done]
    assert len(set(shas)) == len(shas)  # the duplicate (the 3rd station's frame) was not stored as the 4th's
    # the run log: every exposure with its trigger, frame and the robot state at the frame's instant
    ex = _exposures(folder)
    assert [e["outcome"] for e in ex].count("ok") == len(order)
    assert sorted(e["outcome"] for e in ex if e["outcome"] != "ok") == ["duplicate", "late", "missing"]
    ok = {e["station"]: e for e in ex if e["outcome"] == "ok"}
    for r in done:
        e = ok[r["station"]]
        assert e["frame_id"] == r["frame_id"] and e["light"] == "software trigger"
        assert e["trigger_host_s"] <= e["frame_host_s"] and e["latency_s"] < 1.5
        np.testing.assert_allclose(e["joints_rad"], r["joints"], atol=1e-12)
        assert e["robot_timestamp_s"] == pytest.approx(r["robot_timestamp_s"])
    late = next(e for e in ex if e["outcome"] == "late")
    assert late["latency_s"] > 1.5 and late["robot_timestamp_s"] is None  # never tied to a robot state


@pytest.mark.slow
def test_a_station_whose_frames_never_come_faults_the_job_and_is_not_stored(tmp_path):
    job = job_variant(tmp_path / "job", {"sim": {"frame_faults": {"3": "missing", "4": "missing"}},
                                         "cell": {"retakes": 1}})
    run = run_cell("run", str(job), "--archive", str(tmp_path / "archive"), timeout=400)
    assert run.code == 1 and run.doc["status"] == "FAULTED"
    folder = Path(run.doc["folder"])
    recs = records(folder)
    order = [s["id"] for s in sorted(json.loads((folder / "plan.json").read_text())["stations"],
                                     key=lambda s: s["order"])]
    assert [r["station"] for r in recs if r["event"] == "station_done"] == order[:2]
    assert f"station {order[2]}: no frame" in run.doc["reason"] and "2 attempts" in run.doc["reason"]
    assert sorted(p.name for p in (folder / "images").iterdir()) == ["0000.png", "0001.png"]
