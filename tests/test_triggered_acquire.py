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
from jobutil import child_env, job_variant, records, run_cell


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
def test_bad_frames_are_retaken_never_stored_as_another_station_and_resume_retakes_only_the_missing(tmp_path):
    """One job: a late, a repeated and a missing frame, each retaken; then a station whose frame never comes
    (3 tries) faults the job with nothing of it stored; once the camera is mended, resume takes only the
    stations without an image."""
    faults = {"2": "late", "5": "duplicate", "7": "missing", "10": "missing", "11": "missing", "12": "missing"}
    job = job_variant(tmp_path / "job", {"sim": {"light": True}, "camera": {"frame_timeout_s": 1.5}})
    env = child_env() | {"CELL_SIM_FRAME_FAULTS": json.dumps(faults)}  # this session's camera misbehaves
    run = run_cell("run", str(job), "--archive", str(tmp_path / "archive"), timeout=400, env=env)
    assert run.code == 1 and run.doc["status"] == "FAULTED", run.stderr[-2000:]
    folder = Path(run.doc["folder"])
    order = [s["id"] for s in sorted(json.loads((folder / "plan.json").read_text())["stations"],
                                     key=lambda s: s["order"])]
    recs = records(folder)
    faults_seen = [(r["station"], r["outcome"]) for r in recs if r["event"] == "frame_fault"]
    # capture 2 is the 2nd station's first try, its retake capture 3; so capture 5 is the 4th station's first,
    # 7 the 5th's, and 10, 11, 12 are the 7th station's three tries
    assert faults_seen == [(order[1], "late"), (order[3], "duplicate"), (order[4], "missing")] + \
        [(order[6], "missing")] * 3
    assert f"station {order[6]}: no frame" in run.doc["reason"] and "3 attempts" in run.doc["reason"]
    done = [r for r in recs if r["event"] == "station_done"]
    assert [r["station"] for r in done] == order[:6]
    assert {r["station"]: r["attempts"] for r in done if r["attempts"] > 1} == {order[1]: 2, order[3]: 2, order[4]: 2}
    assert sorted(p.name for p in (folder / "images").iterdir()) == [f"{k:04d}.png" for k in range(6)]
    shas = [r["sha256"] for r in done]
    assert len(set(shas)) == len(shas)  # the repeated frame (the 3rd station's) was not stored as the 4th's
    assert len({r["frame_id"] for r in done}) == len(done)
    # the run log: every exposure with its trigger, frame and the robot state at the frame's instant
    ex = _exposures(folder)
    assert sorted(e["outcome"] for e in ex if e["outcome"] != "ok") == ["duplicate", "late"] + ["missing"] * 4
    ok = {e["station"]: e for e in ex if e["outcome"] == "ok"}
    assert len(ok) == 6
    for r in done:
        e = ok[r["station"]]
        assert e["frame_id"] == r["frame_id"] and e["light"] == "software trigger"
        assert e["trigger_host_s"] <= e["frame_host_s"] and e["latency_s"] < 1.5
        np.testing.assert_allclose(e["joints_rad"], r["joints"], atol=1e-12)
        assert e["robot_timestamp_s"] == pytest.approx(r["robot_timestamp_s"])
    late = next(e for e in ex if e["outcome"] == "late")
    assert late["latency_s"] > 1.5 and late["robot_timestamp_s"] is None  # never tied to a robot state

    # the camera is mended (a session without injected faults): resume takes only the stations without an image
    res = run_cell("resume", folder.name, "--archive", str(folder.parent), "--yes", timeout=400)
    assert res.code == 0 and res.doc["status"] == "DONE", res.stderr[-2000:]
    again = [r for r in records(folder) if r["event"] == "station_done"]
    assert [r["station"] for r in again] == order  # each station stored once, in order
    assert again[:6] == done  # the first six were not taken again


@pytest.mark.parametrize("light_input, source", [(1, "IP1"), (None, "TR")])
def test_the_light_pulses_once_per_exposure_within_it(tmp_path, light_input, source):
    """The simulated cell's light is the Gardasoft driver on its emulator. With ``light_input`` the camera's strobe
    line fires the controller's input (pulse mode armed once); without, the driver's software trigger fires it just
    before the exposure. Either way: one pulse of the exposure's length per frame, between trigger and frame."""
    from cell.devices import open_devices
    from cell.loadedjob import load
    from cell.stages.exposure import ExposureTaker

    job = load(job_variant(tmp_path / "job", {"sim": {"light": True}, "cell": {"light_input": light_input}}))
    devices = open_devices(job, "sim")
    try:
        emulator = devices.light.emulator
        taker = ExposureTaker(devices.robot, devices.camera, devices.light, exposure_s=0.002, frame_timeout_s=2.0,
                              light_by_line=light_input is not None)
        recs = []
        for k in range(3):
            st, host_s, peak = wait_settled(devices.robot, speed_tol_rad_s=0.002, hold_s=0.02, timeout_s=2.0)
            recs.append(taker.take(f"S{k}", 1, st, host_s, peak, 0.02)[1])
        pulses = emulator.controller.pulses
        assert [p.source for p in pulses] == [source] * 3
        assert all(p.channel == 1 and p.width_s == pytest.approx(0.002) for p in pulses)
        for p, r in zip(pulses, recs):
            assert r.trigger_host_s <= p.t_s <= r.frame_host_s
            assert r.light == ("camera strobe line" if light_input else "software trigger")
    finally:
        devices.close()
