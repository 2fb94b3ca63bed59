"""drivers/ur.py on a real Universal Robots arm (hardware in the loop).

Skipped unless ``CELL_UR_HOST`` names the robot. Motion tests also need
``CELL_UR_ALLOW_MOTION=1``: they move joint 6 by 0.05 rad and back, slowly, from
wherever the arm is. Keep the cell clear and a hand on the emergency stop.
"""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

from calibration.errors import LimitError
from drivers.ur import CellLimits, URRobot

HOST = os.environ.get("CELL_UR_HOST")
pytestmark = [pytest.mark.hil, pytest.mark.skipif(not HOST, reason="CELL_UR_HOST not set: no robot to test")]
ALLOW_MOTION = os.environ.get("CELL_UR_ALLOW_MOTION") == "1"


@pytest.fixture
def robot():
    arm = URRobot(HOST, CellLimits(max_joint_speed_rad_s=0.2, max_joint_accel_rad_s2=0.5,
                                   max_tcp_speed_m_s=0.05, max_tcp_accel_m_s2=0.2,
                                   workspace_min_m=(-2.0, -2.0, -2.0), workspace_max_m=(2.0, 2.0, 2.0)),
                  deadline_s=5.0, robot=os.environ.get("CELL_UR_MODEL", "ur5e"))
    arm.connect()
    yield arm
    arm.close()


def test_state_is_fresh_and_consistent_with_the_model(robot):
    first = robot.state()
    time.sleep(0.1)
    second = robot.state()
    assert second.timestamp_s > first.timestamp_s
    assert first.safety.normal, first.safety.detail
    # the controller's flange pose agrees with our kinematic model to a few millimetres (nominal DH)
    np.testing.assert_allclose(robot.model.fk(second.joints_rad)[:3, 3], second.base_from_flange[:3, 3], atol=5e-3)


def test_too_fast_a_move_is_refused_before_sending(robot):
    start = robot.state()
    with pytest.raises(LimitError):
        robot.move_joints(start.joints_rad, 1.0, 0.5)


@pytest.mark.skipif(not ALLOW_MOTION, reason="CELL_UR_ALLOW_MOTION=1 not set")
def test_small_joint_move_there_and_back(robot):
    start = robot.state()
    target = start.joints_rad + np.array([0, 0, 0, 0, 0, 0.05])
    there = robot.move_joints(target, 0.1, 0.3)
    np.testing.assert_allclose(there.joints_rad, target, atol=2e-3)
    back = robot.move_joints(start.joints_rad, 0.1, 0.3)
    np.testing.assert_allclose(back.joints_rad, start.joints_rad, atol=2e-3)
