"""Stop means stop: an abort (SIGTERM or Ctrl-C to the process group, the console's Abort) stops the
arm within the controller's stopping time, on the real driver path (drivers/ur.py, the ur-rtde
client) against the loopback UR controller running at real-time speed.

One job serves the three aborts: ``cell run`` is aborted by SIGTERM to its process group during a
move, ``cell resume`` by SIGINT to its process group, and a resume in this process by
:func:`cell.job.abort_job` from another thread (the console's path). After each, the controller's
own trace says when the arm came to rest; it must be within the stopping time of a ``stopj`` at the
driver's deceleration from the speed the arm had when the abort came, plus a small latency.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from jobutil import RecordingOutput, cell_command, child_env, job_variant, records, start_loopback_controller

STOP_DECEL = 4.0  # rad/s^2: URRobot's default stop deceleration
LATENCY_S = 0.25  # signal -> parent -> client process -> RTDE -> controller tick, on a loaded 2-core machine
MIN_SPEED = 0.4  # rad/s: abort only once the arm is well under way


@pytest.fixture
def controller():
    ctrl = start_loopback_controller("127.0.8", robot="ur10e", time_scale=1.0)
    yield ctrl
    ctrl.close()


def _wait_moving_fast(controller, proc_alive, timeout_s: float = 120.0) -> tuple[float, float]:
    """Block until the arm moves at MIN_SPEED or more; returns (controller clock, speed) at that moment."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if not proc_alive():
            pytest.fail("the job ended before the arm moved")
        speed = float(np.max(np.abs(controller.joint_speeds)))
        if controller.moving and speed >= MIN_SPEED:
            return controller.clock_s, speed
        time.sleep(0.002)
    pytest.fail("the arm never moved fast enough to abort a move")


def _check_stopped(controller, folder: Path, t_abort: float, speed: float, reason: str) -> float:
    """The arm came to rest within its stopping time of the abort; the journal says when. Returns the stop time."""
    assert controller.wait_for(lambda: not controller.moving, 5.0)
    time.sleep(0.1)
    t_rest = controller.rest_time_after(t_abort)
    assert t_rest is not None
    stopping_s = speed / STOP_DECEL  # at least this: the speed can only have grown since we looked
    took = t_rest - t_abort
    # the speed at the abort bounds the stopping time from above once the move has reached its peak speed
    assert took <= 1.0 / STOP_DECEL + LATENCY_S, f"{reason}: the arm came to rest {took:.3f} s after the abort"
    assert took >= 0.5 * stopping_s, f"{reason}: rest {took:.3f} s after the abort: faster than a stop can be"
    recs = records(folder)
    stopped = [r for r in recs if r["event"] == "robot_stopped"]
    assert stopped and stopped[-1]["abort_reason"] == reason, stopped[-1:]
    assert stopped[-1]["rest_after_stop_s"] is not None and stopped[-1]["rest_after_stop_s"] < 1.0 / STOP_DECEL + 0.2
    assert abs(stopped[-1]["rest_controller_timestamp_s"] - t_rest) < 0.05  # the driver saw what the controller did
    term = [r for r in recs if r["event"] == "terminal"][-1]
    assert term["status"] == "ABORTED" and reason in term["reason"], term
    return took


def _run_and_abort(controller, args: list[str], sig: int, archive: Path) -> tuple[Path, float, float]:
    proc = subprocess.Popen([*cell_command(), *args, "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=child_env(), start_new_session=True)
    try:
        t_abort, speed = _wait_moving_fast(controller, lambda: proc.poll() is None)
        t_abort = controller.clock_s
        os.killpg(proc.pid, sig)  # the whole process group, as a terminal's Ctrl-C or a service manager does
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    doc = json.loads(out)
    assert doc["status"] == "ABORTED", doc
    return Path(doc["folder"]), t_abort, speed


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_abort_by_sigterm_sigint_and_console_stops_the_arm_within_its_stopping_time(controller, tmp_path):
    from cell.job import abort_job, resume_job

    job = job_variant(tmp_path / "job", {"cell": {"backend": "ur", "host": controller.host, "settle_s": 0.05},
                                         "planning": {"generations": 20, "population": 24}})
    archive = tmp_path / "archive"
    folder, t_abort, speed = _run_and_abort(controller, ["run", str(job), "--archive", str(archive), "--yes"],
                                            signal.SIGTERM, archive)
    took = {"SIGTERM": _check_stopped(controller, folder, t_abort, speed, "SIGTERM")}
    # the station in flight was not reached: the move did not finish after the abort
    plan = json.loads((folder / "plan.json").read_text())
    started = [r["station"] for r in records(folder) if r["event"] == "station_start"]
    target = next(np.asarray(s["joints"]) for s in plan["stations"] if s["id"] == started[-1])
    assert np.max(np.abs(controller.joints - target)) > 1e-3

    folder2, t_abort, speed = _run_and_abort(controller, ["resume", folder.name, "--archive", str(archive), "--yes"],
                                             signal.SIGINT, archive)
    assert folder2 == folder
    took["SIGINT"] = _check_stopped(controller, folder, t_abort, speed, "SIGINT")

    # the console: the job runs in a thread of this process, the Abort comes from another
    result = {}
    runner = threading.Thread(target=lambda: result.setdefault("r", resume_job(folder.name, archive,
                                                                               RecordingOutput())))
    runner.start()
    try:
        t_abort, speed = _wait_moving_fast(controller, runner.is_alive)
        t_abort = controller.clock_s
        assert abort_job(folder.name, "console")
    finally:
        runner.join(60)
    assert not runner.is_alive()
    assert result["r"].status.value == "ABORTED"
    took["console"] = _check_stopped(controller, folder, t_abort, speed, "console")
    assert not abort_job(folder.name, "console")  # nothing runs any more
    print("\narm at rest after the abort: " + ", ".join(f"{k} {v:.3f} s" for k, v in took.items())
          + f" (stopping time at 1 rad/s: {1.0 / STOP_DECEL:.3f} s)")


@pytest.mark.timeout(300)
def test_console_abort_of_a_job_in_another_process_ends_it_aborted_with_the_arm_at_rest(tmp_path):
    """abort_job(id, archive_root=...) reaches a job run by another process (the pid in its lock)."""
    from cell.job import abort_job

    job = job_variant(tmp_path / "job", {"sim": {"motion": "timed", "time_scale": 1.0},
                                         "planning": {"generations": 20, "population": 24}})
    archive = tmp_path / "archive"
    proc = subprocess.Popen([*cell_command(), "run", str(job), "--archive", str(archive), "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=child_env())
    try:
        end = time.monotonic() + 200
        folder = None
        while time.monotonic() < end and proc.poll() is None:
            dirs = [d for d in archive.iterdir() if d.is_dir() and not d.name.startswith(".")] if archive.exists() else []
            if dirs and any(r["event"] == "station_start" for r in records(dirs[0])):
                folder = dirs[0]
                break
            time.sleep(0.02)
        assert folder is not None, "the job never started a station"
        assert abort_job(folder.name, "console", archive_root=archive)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130 and "Traceback" not in err, err[-3000:]
    assert json.loads(out)["status"] == "ABORTED"
    recs = records(folder)
    assert [r for r in recs if r["event"] == "robot_stopped"][-1]["abort_reason"] == "SIGTERM"
    assert recs[-1]["event"] == "terminal" and recs[-1]["status"] == "ABORTED"
    assert not abort_job(folder.name, "console", archive_root=archive)  # nothing runs it any more


def test_ur_client_ignores_ctrl_c_and_stops_the_arm_on_sigterm(capfd):
    """The client process: SIGINT (a terminal's Ctrl-C, were it in the group) neither kills it nor prints a
    traceback, the move goes on; SIGTERM stops the arm at once ('stopped on request')."""
    from calibration.errors import MotionError
    from drivers.ur import CellLimits, URRobot
    from planning.kinematics import load_robot

    model = load_robot("ur5e")
    q0 = np.array([0.0, -1.3, 1.6, -1.87, -1.57, 0.0])
    ctrl = start_loopback_controller("127.0.7", model=model, joints_rad=q0, time_scale=2.0)

    def kill_once_moving(pid: int, sig: int) -> None:  # the signal must come during the move, whatever the load
        def go():
            ctrl.wait_for(lambda: ctrl.moving, timeout_s=10.0)
            os.kill(pid, sig)

        threading.Thread(target=go, daemon=True).start()

    try:
        with URRobot(ctrl.host, CellLimits(), deadline_s=3.0, model=model) as arm:
            pid = arm._worker.process.pid
            assert os.getpgid(pid) != os.getpgid(0)  # a session of its own: a terminal's Ctrl-C does not reach it
            kill_once_moving(pid, signal.SIGINT)
            np.testing.assert_allclose(arm.move_joints(q0 + 0.4, 0.8, 1.5).joints_rad, q0 + 0.4, atol=1e-6)
            assert arm.connected
            kill_once_moving(pid, signal.SIGTERM)
            with pytest.raises(MotionError, match="stopped on request"):
                arm.move_joints(q0, 0.8, 1.5)
            assert not ctrl.moving and np.max(np.abs(ctrl.joints - q0)) > 0.05
            rest = arm.stop()
            assert rest is not None and arm.connected
            np.testing.assert_allclose(arm.move_joints(q0, 0.8, 1.5).joints_rad, q0, atol=1e-6)  # usable again
    finally:
        ctrl.close()
    assert "Traceback" not in capfd.readouterr().err
