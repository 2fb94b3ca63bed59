"""Faugeras-Toscani calibration against synthetic truth."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.camera import Intrinsics, invert, look_at, make_pose, project
from calibration.errors import CalibrationError
from calibration.faugeras_toscani import combine_intrinsics, faugeras_toscani
from scipy.spatial.transform import Rotation

INTR = Intrinsics(fx_px=2500.0, fy_px=2520.0, cx_px=1230.5, cy_px=1015.5, width=2448, height=2048)


def _scene(rng, n=60, noise=0.0):
    xyz = rng.uniform(-0.15, 0.15, (n, 3))
    pose = invert(look_at([0.45, 0.4, 0.6], [0.0, 0.0, 0.0], roll_rad=0.3))
    uv = project(INTR, pose, xyz) + rng.normal(0.0, noise, (n, 2)) if noise else project(INTR, pose, xyz)
    return xyz, uv, pose


def test_exact_data_give_the_exact_interior_and_exterior_orientation():
    xyz, uv, pose = _scene(np.random.default_rng(0))
    r = faugeras_toscani(xyz, uv, INTR.width, INTR.height)
    for a, b in [(r.intrinsics.fx_px, 2500.0), (r.intrinsics.fy_px, 2520.0), (r.intrinsics.cx_px, 1230.5),
                 (r.intrinsics.cy_px, 1015.5)]:
        assert abs(a - b) < 1e-6
    np.testing.assert_allclose(r.cam_from_part, pose, atol=1e-9)
    assert r.rms_px < 1e-8 and abs(r.skew) < 1e-10
    assert abs(np.linalg.norm(r.M[2, :3]) - 1.0) < 1e-12


def test_noisy_data_give_a_close_calibration():
    xyz, uv, pose = _scene(np.random.default_rng(1), n=100, noise=0.1)
    r = faugeras_toscani(xyz, uv, INTR.width, INTR.height)
    assert abs(r.intrinsics.fx_px - 2500.0) < 10.0
    assert abs(r.intrinsics.cx_px - 1230.5) < 10.0
    assert np.linalg.norm(r.cam_from_part[:3, 3] - pose[:3, 3]) < 5e-3
    assert 0.05 < r.rms_px < 0.15


def test_calibration_does_not_depend_on_where_the_world_frame_is():
    """The constraint ||m3|| = 1 makes the estimate invariant to rigid motions of the points."""
    rng = np.random.default_rng(2)
    xyz, uv, _ = _scene(rng, n=40, noise=0.2)
    a = faugeras_toscani(xyz, uv, INTR.width, INTR.height)
    T = make_pose(Rotation.from_rotvec([0.4, -1.0, 0.7]).as_matrix(), [3.0, -2.0, 5.0])
    b = faugeras_toscani(xyz @ T[:3, :3].T + T[:3, 3], uv, INTR.width, INTR.height)
    for f in ("fx_px", "fy_px", "cx_px", "cy_px"):
        assert abs(getattr(a.intrinsics, f) - getattr(b.intrinsics, f)) < 1e-6
    np.testing.assert_allclose(b.cam_from_part @ T, a.cam_from_part, atol=1e-8)


def test_coplanar_points_are_refused_with_the_reason():
    rng = np.random.default_rng(3)
    xyz, uv, _ = _scene(rng)
    xyz[:, 2] = 0.0
    with pytest.raises(CalibrationError, match="coplanar"):
        faugeras_toscani(xyz, uv, INTR.width, INTR.height)


def test_fewer_than_six_points_are_refused():
    xyz, uv, _ = _scene(np.random.default_rng(4), n=5)
    with pytest.raises(CalibrationError, match="at least 6"):
        faugeras_toscani(xyz, uv, INTR.width, INTR.height)


def test_mismatched_points_behind_the_camera_are_reported():
    xyz, uv, _ = _scene(np.random.default_rng(5), n=30)
    with pytest.raises(CalibrationError):
        faugeras_toscani(xyz, uv[::-1].copy() * np.array([1.0, -1.0]), INTR.width, INTR.height)


def test_combined_intrinsics_are_the_median_over_images():
    rng = np.random.default_rng(6)
    res = []
    for k in range(5):
        xyz, uv, _ = _scene(rng, n=50, noise=0.05)
        res.append(faugeras_toscani(xyz, uv, INTR.width, INTR.height))
    c = combine_intrinsics(res)
    assert c.fx_px == pytest.approx(np.median([r.intrinsics.fx_px for r in res]))
    assert abs(c.fx_px - 2500.0) < 5.0
