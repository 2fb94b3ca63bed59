"""The camera's collision box sits where the hand-eye puts the camera (decision 0061): it contains the projection
centre that ``[cell] flange_from_cam`` gives and the lens in front of it, whatever the hand-eye. Before, it stood
centred on the flange axis: the example's centre (40 mm off the axis) lay on its face and a camera on a side
bracket was not modelled at all."""
from __future__ import annotations

import numpy as np

from cell.loadedjob import load
from cell.setup import robot_model
from jobutil import job_variant


def _inside(tool, p_flange) -> float:
    """How far the flange-frame point lies inside the tool's box (negative: outside), metres."""
    T = tool.flange_from_box
    local = np.abs(T[:3, :3].T @ (np.asarray(p_flange, dtype=float) - T[:3, 3]))
    return float(np.min(0.5 * np.asarray(tool.size_m) - local))


def _camera(tmp_path, xyz, rpy=(0.0, 0.0, 0.0)):
    job = load(job_variant(tmp_path, {"cell": {"flange_from_cam": {"xyz": list(xyz), "rpy_deg": list(rpy)}}}))
    F = job.spec.flange_from_cam()
    return robot_model(job).tools[0], F[:3, 3], F[:3, 2]


def test_the_example_camera_and_its_lens_lie_inside_the_box(tmp_path):
    tool, centre, axis = _camera(tmp_path, [0.0, 40.0, 90.0])
    assert _inside(tool, centre) >= 0.03 - 1e-9  # 80 mm wide: the centre on its axis, 30 mm from the front face
    assert _inside(tool, centre + 0.02 * axis) > 0.009  # the lens in front of it
    assert abs(_inside(tool, [0.0, 0.04, 0.0])) < 1e-9  # the box reaches back to the flange face
    assert tool.size_m == (0.08, 0.08, 0.12)


def test_a_camera_on_a_side_bracket_or_tilted_is_inside_its_box(tmp_path):
    tool, centre, axis = _camera(tmp_path / "side", [0.0, 200.0, 60.0])
    assert _inside(tool, centre) > 0.03 and _inside(tool, centre + 0.05 * axis) > 0.009
    tool, centre, axis = _camera(tmp_path / "tilt", [30.0, 0.0, 80.0], [0.0, 25.0, 0.0])
    assert _inside(tool, centre) > 0.03 and _inside(tool, centre + 0.02 * axis) > 0.0
    np.testing.assert_allclose(tool.flange_from_box[:3, 2], axis, atol=1e-12)  # the box along the optical axis
    tool, centre, axis = _camera(tmp_path / "far", [0.0, 0.0, 300.0])  # beyond the box's length: centred on it
    assert _inside(tool, centre) > 0.039 and _inside(tool, centre + 0.05 * axis) > 0.009
