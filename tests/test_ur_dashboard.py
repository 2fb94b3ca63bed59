"""The dashboard client (power on, brake release) against the loopback UR controller."""
from __future__ import annotations

import pytest

from calibration.errors import NotConnectedError
from drivers.ur_dashboard import Dashboard
from test_ur_driver import start_controller


def test_power_on_and_brake_release_bring_a_powered_off_robot_to_running():
    with start_controller() as ctrl:
        ctrl.robot_mode = "POWER_OFF"
        with Dashboard(ctrl.host) as dash:
            assert dash.robot_mode() == "POWER_OFF"
            assert dash.power_on_and_release(timeout_s=5.0) == "RUNNING"
            assert dash.command("is in remote control") == "true"


def test_no_controller_is_a_clear_not_connected():
    with pytest.raises(NotConnectedError, match="UR dashboard at 127.0.0.1:1: cannot connect"):
        with Dashboard("127.0.0.1", port=1, timeout_s=0.5):
            pass
