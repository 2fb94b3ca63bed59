"""The teach pendant's speed slider and its remote / local switch, on the real ur-rtde client (decision 0063).

A slider at 0 before a move, the slider pulled to 0 (or the controller's speed scaling at 0) during one, and a
robot in local control each end the move at once with one line naming the cause, well under the move's deadline;
a slider below 100% stretches the deadline instead of faulting a move that is only slow.
"""
from __future__ import annotations

import itertools
import subprocess
import sys
import time

import numpy as np
import pytest

from calibration.errors import MotionError, MoveRefusedError, NotConnectedError
from drivers.ur import CellLimits, URRobot
from planning.kinematics import load_robot
from sim_backend.ur_controller import PLAYING, LoopbackURController
from test_ur_driver import start_controller as _start_controller

MODEL = load_robot("ur5e")
Q0 = np.array([0.0, -1.3, 1.6, -1.87, -1.57, 0.0])
_hosts = (f"127.0.{k // 250}.{k % 250 + 2}" for k in itertools.cycle(range(2000, 2400)))
GRACE_S = 0.3


def start_controller(**kwargs) -> LoopbackURController:
    """test_ur_driver's, on an address range of this file's own (the two files may run on two workers at once)."""
    return _start_controller(_hosts, **kwargs)


@pytest.fixture
def controller():
    with start_controller(time_scale=4.0) as ctrl:
        yield ctrl


@pytest.fixture
def robot(controller):
    arm = URRobot(controller.host, CellLimits(), deadline_s=3.0, model=MODEL, speed_zero_grace_s=GRACE_S)
    arm.connect()
    yield arm
    arm.close()


def _motions(controller) -> list[str]:
    return [c.name for c in controller.commands if c.name in ("movej", "movel")]


def _seen(controller, robot) -> None:
    """Wait until the driver has read an RTDE packet sent after a change made on the controller."""
    t = controller.clock_s
    end = time.monotonic() + 2.0
    while robot.state().timestamp_s <= t:
        assert time.monotonic() < end, "no new RTDE packet"
        time.sleep(0.002)


def _once_moving(controller, delay_s: float, action) -> None:
    def run():
        if controller.wait_for(lambda: controller.moving, 10.0):
            time.sleep(delay_s)
        action()
    import threading

    threading.Thread(target=run, daemon=True).start()


def test_a_slider_at_zero_refuses_the_move_at_once_naming_the_slider(controller, robot):
    controller.set_speed_slider(0.0)
    _seen(controller, robot)
    for move in (lambda: robot.move_joints(Q0 + 0.3, 0.8, 1.5), lambda: robot.move_pose(MODEL.fk(Q0 + 0.1), 0.1, 0.5)):
        start = time.monotonic()
        with pytest.raises(MotionError, match=r"speed slider on the teach pendant stands at 0% .*push the slider "
                                              r"up.*nothing was sent") as info:
            move()
        assert time.monotonic() - start < 0.5  # the move's deadline is over 3 s
        assert not isinstance(info.value, MoveRefusedError)  # a fault, not a station to skip
        assert "\n" not in str(info.value)
    assert _motions(controller) == []
    np.testing.assert_array_equal(controller.joints, Q0)
    # the operator pushes it up: the next move goes
    controller.set_speed_slider(1.0)
    _seen(controller, robot)
    np.testing.assert_allclose(robot.move_joints(Q0 + 0.1, 0.8, 1.5).joints_rad, Q0 + 0.1, atol=1e-9)


def test_the_slider_pulled_to_zero_during_a_move_stops_it_after_the_grace(controller, robot):
    pulled = []
    _once_moving(controller, 0.03, lambda: (pulled.append(time.monotonic()), controller.set_speed_slider(0.0)))
    with pytest.raises(MotionError, match=r"speed slider on the teach pendant was pulled down to 0% during the "
                                          r"move .*move was stopped and is not resumed"):
        robot.move_joints(Q0 + 0.8, 0.4, 1.0)  # deadline 1.5 * 2.4 s + 3 s
    waited = time.monotonic() - pulled[0]
    assert GRACE_S <= waited < GRACE_S + 0.7
    assert controller.commands[-1].name == "stopj" and not controller.moving
    halted = controller.joints
    assert 0.0 < np.max(np.abs(halted - Q0)) < 0.79
    # the move is not resumed when the slider comes back up
    controller.set_speed_slider(1.0)
    time.sleep(0.1)
    np.testing.assert_array_equal(controller.joints, halted)
    assert controller.runtime_state == PLAYING


def test_the_controllers_speed_scaling_at_zero_during_a_move_is_named(controller, robot):
    _once_moving(controller, 0.03, lambda: controller.set_speed_scaling(0.0))
    start = time.monotonic()
    with pytest.raises(MotionError, match=r"controller's speed scaling stood at 0.000 .*slider at 100%"):
        robot.move_joints(Q0 - 0.8, 0.4, 1.0)
    assert time.monotonic() - start < GRACE_S + 1.0


def test_a_short_dip_of_the_slider_does_not_end_the_move(controller, robot):
    def dip():
        controller.set_speed_slider(0.0)
        time.sleep(GRACE_S / 3)
        controller.set_speed_slider(1.0)
    _once_moving(controller, 0.03, dip)
    q = Q0 + 0.5
    np.testing.assert_allclose(robot.move_joints(q, 0.5, 1.0).joints_rad, q, atol=1e-9)


def test_local_control_refuses_the_move_at_once_naming_the_switch(controller, robot):
    controller.set_remote_control(False)
    start = time.monotonic()
    with pytest.raises(MotionError, match=r"robot is in local control .*switch the teach pendant from Local to "
                                          r"Remote control.*nothing was sent") as info:
        robot.move_joints(Q0 + 0.3, 0.8, 1.5)
    assert time.monotonic() - start < 0.5
    assert not isinstance(info.value, MoveRefusedError) and "\n" not in str(info.value)
    assert _motions(controller) == []
    np.testing.assert_array_equal(controller.joints, Q0)
    controller.set_remote_control(True)
    np.testing.assert_allclose(robot.move_joints(Q0 + 0.1, 0.8, 1.5).joints_rad, Q0 + 0.1, atol=1e-9)


def test_connecting_in_local_control_names_the_switch(controller):
    controller.set_remote_control(False)
    start = time.monotonic()
    with pytest.raises(NotConnectedError, match=r"could not connect: the robot is in local control .*from Local to "
                                                r"Remote control, then connect again"):
        URRobot(controller.host, model=MODEL).connect()
    assert time.monotonic() - start < 5.0
    assert controller.uploaded_scripts == []


def test_a_slider_at_half_stretches_the_deadline_and_the_move_completes():
    # at time_scale 1 the move takes 0.77 s; at 50% 1.55 s, past the deadline planned for 100% (1.5 x 0.77 + 0.3 s)
    with start_controller(time_scale=1.0) as controller:
        with URRobot(controller.host, deadline_s=0.3, model=MODEL) as arm:
            controller.set_speed_slider(0.5)
            _seen(controller, arm)
            start = time.monotonic()
            np.testing.assert_allclose(arm.move_joints(Q0 + 0.3, 1.0, 2.0).joints_rad, Q0 + 0.3, atol=1e-9)
            assert 1.4 < time.monotonic() - start < 2.6


def test_ur_rtdes_own_set_speed_slider_reaches_target_speed_fraction(controller, robot):
    # RTDEIOInterface.setSpeedSlider writes the RTDE inputs speed_slider_mask / speed_slider_fraction; its calls hold
    # the interpreter, so it runs in a process of its own
    code = (f"import rtde_io; io = rtde_io.RTDEIOInterface({controller.host!r}); "
            "assert io.setSpeedSlider(0.0); io.disconnect()")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=30, capture_output=True)
    assert controller.speed_slider == 0.0
    _seen(controller, robot)
    with pytest.raises(MotionError, match="speed slider on the teach pendant stands at 0%"):
        robot.move_joints(Q0 + 0.3, 0.8, 1.5)
