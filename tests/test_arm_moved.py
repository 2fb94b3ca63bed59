"""One test of "did the arm move" (drivers.motion), used by the UR client process, the driver and the cell."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from drivers.motion import MOVED_TOL_RAD, arm_moved, joint_change_rad
from drivers.protocols import Frame, RobotState, SafetyStatus

Q = np.array([0.1, -1.3, 1.6, -1.87, -1.57, 0.2])


def test_the_tolerance_is_the_boundary_and_a_still_arm_with_encoder_noise_is_still():
    assert MOVED_TOL_RAD == 1e-4
    still = [0.0] * 6
    edge = [0.0, 0.0, -1e-4, 0.0, 0.0, 0.0]  # exactly the tolerance: still
    assert joint_change_rad(still, edge) == 1e-4 and not arm_moved(still, edge)
    beyond = [0.0, 0.0, -np.nextafter(1e-4, 1.0), 0.0, 0.0, 0.0]
    assert arm_moved(still, beyond)
    rng = np.random.default_rng(3)  # a UR at rest: readings scatter by ~1e-5 rad
    assert not any(arm_moved(Q, Q + rng.normal(0.0, 1e-5, 6)) for _ in range(200))
    assert arm_moved(Q, Q + [0, 0, 0, 0, 0, 2e-4])  # numpy arrays and lists alike
    assert not arm_moved(Q, Q + 5e-4, tol_rad=1e-3)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_reading_that_is_not_finite_never_shows_the_arm_still(bad):
    for k in range(6):  # wherever the bad value stands (max() alone would skip a NaN after the first value)
        q = Q.copy()
        q[k] = bad
        assert joint_change_rad(Q + [1e-3, 0, 0, 0, 0, 0], q) == math.inf and arm_moved(Q, q) and arm_moved(q, Q)


def test_readings_of_different_lengths_are_an_error_not_an_answer():
    with pytest.raises(ValueError, match="6 and 5"):
        joint_change_rad(Q, Q[:5])
    with pytest.raises(ValueError):
        arm_moved([], [])


class _Robot:
    """The reading after the frame: the settled joints plus ``drift``."""

    def __init__(self, drift):
        self.drift = np.asarray(drift, float)

    def state(self):
        return RobotState(joints_rad=Q + self.drift, base_from_flange=np.eye(4), safety=SafetyStatus(normal=True),
                          timestamp_s=2.0)


class _Camera:
    def __init__(self):
        self.n = 0

    def capture(self):
        self.n += 1
        return Frame(image=np.zeros((4, 4), np.uint8), timestamp_s=time.time(), exposure_s=0.01,
                     meta={"frame_id": self.n, "camera": "test"})


@pytest.mark.parametrize("drift,outcome", [
    ([0, 0, 0, 0, 0.9e-4, 0], "ok"),  # within the tolerance: still, the frame is the station's
    ([0, 0, 0, 0, 1.2e-4, 0], "moved"),
    ([0, 0, 0, math.nan, 0, 0], "moved"),  # a reading that cannot show the arm still: retaken, never kept
])
def test_the_exposure_check_uses_it(drift, outcome):
    from cell.stages.exposure import ExposureTaker, FrameFault

    settled = RobotState(joints_rad=Q.copy(), base_from_flange=np.eye(4), safety=SafetyStatus(normal=True),
                         timestamp_s=1.0)
    taker = ExposureTaker(_Robot(drift), _Camera(), None, exposure_s=0.01, frame_timeout_s=1.0, light_by_line=False)
    if outcome == "ok":
        frame, rec = taker.take("S001", 1, settled, time.time(), 0.0, 0.1)
        assert rec.outcome == "ok" and rec.joints_rad == Q.tolist()
        return
    with pytest.raises(FrameFault, match="station S001: the arm moved") as info:
        taker.take("S001", 1, settled, time.time(), 0.0, 0.1)
    assert info.value.outcome == "moved"
    assert ("0.00012 rad" in str(info.value)) if not math.isnan(drift[3]) else ("not finite" in str(info.value))
