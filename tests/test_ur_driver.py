"""drivers/ur.py with the real ur-rtde client against the loopback UR controller."""
from __future__ import annotations

import itertools
import os
import signal
import threading
import time

import numpy as np
import pytest

from calibration.errors import LimitError, MotionError, MoveRefusedError, NotConnectedError, ProtectiveStopError
from drivers.protocols import Robot
from drivers.ur import CellLimits, URRobot
from planning.kinematics import load_robot
from sim_backend.ur_controller import PAUSED, PLAYING, STOPPED, LoopbackURController

MODEL = load_robot("ur5e")
Q0 = np.array([0.0, -1.3, 1.6, -1.87, -1.57, 0.0])
_hosts = (f"127.0.{k // 250}.{k % 250 + 2}" for k in itertools.cycle(range(20, 2000)))


def start_controller(hosts=None, **kwargs) -> LoopbackURController:
    """A controller on the next free loopback address of ``hosts`` (default this file's range; another test run may
    hold some)."""
    hosts = _hosts if hosts is None else hosts
    for _ in range(50):
        try:
            return LoopbackURController(next(hosts), model=MODEL, joints_rad=Q0, **kwargs).start()
        except OSError:
            continue
    raise RuntimeError("no free loopback address for a UR controller")


@pytest.fixture
def controller():
    with start_controller(time_scale=4.0) as ctrl:
        yield ctrl


@pytest.fixture
def robot(controller):
    arm = URRobot(controller.host, CellLimits(), deadline_s=3.0, model=MODEL)
    arm.connect()
    yield arm
    arm.close()


def _motion_names(controller) -> list[str]:
    return [c.name for c in controller.commands if c.name in ("movej", "movel")]


def _later(delay_s: float, action) -> threading.Thread:
    thread = threading.Thread(target=lambda: (time.sleep(delay_s), action()))
    thread.start()
    return thread


def _once_moving(controller, delay_s: float, action) -> threading.Thread:
    """``action()`` ``delay_s`` (wall) after the arm starts moving: a fault during the move whatever the load."""
    def run():
        if controller.wait_for(lambda: controller.moving, 10.0):
            time.sleep(delay_s)
        action()
    thread = threading.Thread(target=run)
    thread.start()
    return thread


def test_connect_then_move_joints_and_move_pose_reach_their_targets(controller, robot):
    assert isinstance(robot, Robot)
    start = robot.state()
    np.testing.assert_allclose(start.joints_rad, Q0, atol=1e-12)
    np.testing.assert_allclose(start.base_from_flange, MODEL.fk(Q0), atol=1e-9)
    assert start.safety.normal and start.timestamp_s > 0

    q1 = Q0 + np.array([0.3, -0.2, 0.1, 0.2, 0.1, -0.3])
    at_q1 = robot.move_joints(q1, 0.8, 1.5)
    np.testing.assert_allclose(at_q1.joints_rad, q1, atol=1e-9)
    np.testing.assert_allclose(controller.joints, q1, atol=1e-9)
    assert at_q1.timestamp_s > start.timestamp_s

    target = at_q1.base_from_flange.copy()
    target[:3, 3] += [0.06, 0.04, -0.05]
    mark = len(controller.trace)
    at_target = robot.move_pose(target, 0.2, 0.8)
    np.testing.assert_allclose(at_target.base_from_flange, target, atol=1e-6)
    np.testing.assert_allclose(MODEL.fk(at_target.joints_rad), target, atol=1e-6)

    # moveL: the flange stayed on the straight segment between start and target
    p0, p1 = at_q1.base_from_flange[:3, 3], target[:3, 3]
    path = np.array([MODEL.fk(q)[:3, 3] for _, q in list(controller.trace)[mark:]])
    u = np.clip((path - p0) @ (p1 - p0) / np.dot(p1 - p0, p1 - p0), 0, 1)
    off_line = np.linalg.norm(path - (p0 + u[:, None] * (p1 - p0)), axis=1)
    assert off_line.max() < 1e-6
    assert len(path) > 5  # it moved over time, not in one jump
    assert _motion_names(controller) == ["movej", "movel"]


def test_protective_stop_during_move_raises_and_the_arm_stays_halted(controller, robot):
    _once_moving(controller, 0.04, controller.protective_stop).join(0)
    with pytest.raises(ProtectiveStopError, match="protective stop during the move"):
        robot.move_joints(Q0 + 0.6, 0.5, 1.0)
    halted = controller.joints
    assert 0.0 < np.max(np.abs(halted - Q0)) < 0.59
    state = robot.state()
    assert state.safety.protective_stop and not state.safety.normal
    # the driver never clears it: a new move is refused and the arm does not move
    with pytest.raises(ProtectiveStopError):
        robot.move_joints(Q0, 0.5, 1.0)
    np.testing.assert_allclose(controller.joints, halted, atol=0)
    assert controller.runtime_state == PAUSED

    # the operator unlocks it; reconnecting uploads the script again and motion resumes from the measured pose
    assert controller.unlock_protective_stop()
    robot.close()
    robot.connect()
    assert controller.runtime_state == PLAYING
    np.testing.assert_allclose(robot.move_joints(Q0, 0.8, 1.5).joints_rad, Q0, atol=1e-9)


def test_emergency_stop_during_move_raises_protective_stop_error(controller, robot):
    _once_moving(controller, 0.02, controller.emergency_stop).join(0)
    with pytest.raises(ProtectiveStopError, match="emergency stop"):
        robot.move_joints(Q0 - 0.5, 0.5, 1.0)
    state = robot.state()
    assert state.safety.emergency_stop and not state.safety.program_running


def test_connection_drop_raises_not_connected_within_a_second(controller, robot):
    dropped = []
    _once_moving(controller, 0.05, lambda: (dropped.append(time.monotonic()),
                                               controller.drop_connections(down_s=3.0))).join(0)
    with pytest.raises(NotConnectedError):
        robot.move_joints(Q0 + 0.8, 0.3, 1.0)  # about 1 s of motion at time_scale 4
    assert time.monotonic() - dropped[0] < 1.0
    assert not robot.connected
    with pytest.raises(NotConnectedError, match="not connected"):
        robot.state()


def test_script_stopped_gives_a_clear_error_and_no_further_motion(controller, robot):
    controller.stop_script()
    assert controller.runtime_state == STOPPED
    with pytest.raises(MotionError, match="control script is not running"):
        robot.move_joints(Q0 + 0.2, 0.5, 1.0)
    with pytest.raises(MotionError, match="runtime_state=1"):
        robot.move_pose(MODEL.fk(Q0), 0.1, 0.5)
    assert _motion_names(controller) == []
    np.testing.assert_array_equal(controller.joints, Q0)


def test_script_stopped_during_a_move_halts_and_raises(controller, robot):
    _once_moving(controller, 0.02, controller.stop_script).join(0)
    with pytest.raises(MotionError, match="not running on the controller during the move"):
        robot.move_joints(Q0 + 0.5, 0.5, 1.0)
    halted = controller.joints
    time.sleep(0.1)
    np.testing.assert_array_equal(controller.joints, halted)


@pytest.mark.parametrize("call, message", [
    (lambda r: r.move_joints(Q0 + 0.1, 1.5, 1.0), "joint speed 1.5 rad/s exceeds the cell limit 1"),
    (lambda r: r.move_joints(Q0 + 0.1, 0.5, 3.0), "joint acceleration 3 rad/s\\^2 exceeds"),
    (lambda r: r.move_pose(MODEL.fk(Q0), 0.5, 0.5), "TCP speed 0.5 m/s exceeds the cell limit 0.25"),
    (lambda r: r.move_pose(MODEL.fk(Q0), 0.1, 2.0), "TCP acceleration 2 m/s\\^2 exceeds"),
    (lambda r: r.move_joints(Q0 + 0.1, -0.5, 1.0), "must be a positive number"),
])
def test_commands_above_the_cell_limits_are_refused_before_sending(controller, robot, call, message):
    with pytest.raises(LimitError, match=message):
        call(robot)
    time.sleep(0.05)
    assert _motion_names(controller) == []
    np.testing.assert_array_equal(controller.joints, Q0)


def test_targets_outside_the_workspace_box_are_refused_before_sending(controller):
    box = CellLimits(workspace_min_m=(-0.8, -0.5, 0.2), workspace_max_m=(0.0, 0.5, 0.8))
    with URRobot(controller.host, box, model=MODEL) as arm:
        low = MODEL.fk(Q0)
        low[2, 3] = 0.1
        with pytest.raises(LimitError, match="outside the cell's workspace box"):
            arm.move_pose(low, 0.1, 0.5)
        # a joint move whose end is inside the box but whose path swings the flange round the base, out of it
        q_swing = Q0 + np.array([6.2, 0, 0, 0, 0, 0])
        end = MODEL.fk(q_swing)[:3, 3]
        assert np.all(end >= box.workspace_min_m) and np.all(end <= box.workspace_max_m)
        with pytest.raises(LimitError, match="move_joints: flange at"):
            arm.move_joints(q_swing, 0.5, 1.0)
    assert _motion_names(controller) == []


def test_stop_from_another_thread_halts_a_move(controller, robot):
    _once_moving(controller, 0.05, robot.stop).join(0)
    with pytest.raises(MotionError, match="stopped on request"):
        robot.move_joints(Q0 + 0.8, 0.4, 1.0)
    assert not controller.moving
    halted = controller.joints
    assert 0.0 < np.max(np.abs(halted - Q0)) < 0.79
    robot.stop()  # a stopped robot: no error
    assert controller.commands[-1].name == "stopj"


def test_move_past_the_driver_deadline_is_stopped(controller):
    controller.time_scale = 0.25  # the arm runs 4x slower than it should
    with URRobot(controller.host, deadline_s=0.3, model=MODEL) as arm:
        start = time.monotonic()
        with pytest.raises(MotionError, match="deadline"):
            arm.move_joints(Q0 + 0.3, 1.0, 2.0)  # 0.5 s of motion planned, 2 s of wall time needed
        assert time.monotonic() - start < 4.0
        assert controller.wait_for(lambda: not controller.moving, 2.0)


def test_dead_client_process_is_not_connected_then_watchdog_stops_program_and_reconnect_works(controller, robot):
    pid = robot._worker.process.pid
    _once_moving(controller, 0.05, lambda: os.kill(pid, signal.SIGKILL)).join(0)
    with pytest.raises(NotConnectedError, match="client process died"):
        robot.move_joints(Q0 + 0.8, 0.3, 1.0)
    # nobody kicks the watchdog any more: the controller stops the program and the arm
    assert controller.wait_for(lambda: controller.runtime_state == STOPPED, 2.0)
    assert any("watchdog" in m for m in controller.messages)
    assert not controller.moving
    robot.connect()
    np.testing.assert_allclose(robot.move_joints(Q0, 0.8, 1.5).joints_rad, Q0, atol=1e-9)


def test_idle_driver_keeps_the_watchdog_fed(controller, robot):
    time.sleep(1.0)  # five watchdog periods at 5 Hz without any request
    assert controller.runtime_state == PLAYING
    assert robot.state().safety.normal


def test_a_target_the_controller_refuses_is_move_refused_nothing_is_sent_and_the_next_move_goes(controller, robot):
    q_bad = Q0 + np.array([0.2, -0.1, 0.1, 0.0, 0.1, 0.0])
    controller.refuse_targets([q_bad])
    with pytest.raises(MoveRefusedError, match="refused the move: target joints .* did not move"):
        robot.move_joints(q_bad, 0.5, 1.0)
    with pytest.raises(MoveRefusedError, match="target pose"):  # the same joints asked for as a flange pose
        robot.move_pose(MODEL.fk(q_bad), 0.1, 0.5)
    assert _motion_names(controller) == []  # nothing was sent: the controller answered the check
    assert [c.name for c in controller.commands].count("is_joints_within_safety_limits") >= 1
    np.testing.assert_array_equal(controller.joints, Q0)
    assert controller.runtime_state == PLAYING
    q_ok = Q0 + np.array([0.2, -0.1, 0.1, 0.0, 0.1, 0.05])
    np.testing.assert_allclose(robot.move_joints(q_ok, 0.8, 1.5).joints_rad, q_ok, atol=1e-9)


def test_a_check_that_refuses_the_arms_own_joints_is_a_fault_not_a_refusal(controller, robot):
    q_bad = Q0 + 0.1
    controller.refuse_targets([q_bad, Q0])  # the controller refuses where the arm stands: it is not answering right
    with pytest.raises(MotionError, match="refuses even the arm's own joints") as info:
        robot.move_joints(q_bad, 0.5, 1.0)
    assert not isinstance(info.value, MoveRefusedError)
    assert _motion_names(controller) == []


def test_a_move_the_program_dies_on_before_the_arm_moves_is_a_fault_not_a_refusal(controller, robot):
    # the check said yes, then the target became forbidden (a safety restriction switched on): the movej is a
    # runtime error, the program stops before the arm moves. Over RTDE this looks like a stop from the pendant:
    # the job must stop, not skip the station
    q = Q0 + np.array([0.0, 0.1, -0.1, 0.0, 0.0, 0.2])
    controller.after_command = lambda c: c.name == "is_joints_within_safety_limits" and controller.refuse_targets([q])
    with pytest.raises(MotionError, match="control script is not running") as info:
        robot.move_joints(q, 0.5, 1.0)
    assert not isinstance(info.value, MoveRefusedError)
    assert any("runtime error: movej" in m for m in controller.messages)
    assert controller.runtime_state == STOPPED
    np.testing.assert_array_equal(controller.joints, Q0)


@pytest.mark.parametrize("first_ends", ["closed", "killed"])
def test_a_jobs_refused_targets_end_with_its_program_a_later_job_setting_none_is_not_refused(controller, first_ends):
    # two jobs on one controller: the first refuses a target (as ACQUIRE does for [sim] unreachable_stations, from
    # another process), the second sets none; its move to that target goes. Whether the first job's driver
    # closed (stopScript) or died (its program replaced by the next job's upload), its refusals went with it
    from sim_backend.ur_controller import refuse_targets_at

    q = Q0 + np.array([0.2, -0.1, 0.1, 0.0, 0.1, 0.0])
    first = URRobot(controller.host, CellLimits(), deadline_s=3.0, model=MODEL)
    first.connect()
    try:
        refuse_targets_at(controller.host, [q])
        with pytest.raises(MoveRefusedError, match="refused the move"):
            first.move_joints(q, 0.8, 1.5)
    finally:
        first.close() if first_ends == "closed" else first._discard_worker(kill=True)
    second = URRobot(controller.host, CellLimits(), deadline_s=3.0, model=MODEL)
    second.connect()
    try:
        np.testing.assert_allclose(second.move_joints(q, 0.8, 1.5).joints_rad, q, atol=1e-9)
    finally:
        second.close()
    assert sum(c.name == "movej" for c in controller.commands) == 1  # the second job's only
    assert controller.within_safety_limits(q)
