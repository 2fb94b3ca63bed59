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


def _sheet(rng, thickness_ratio, n=80, noise=0.1, warp=False):
    """A flat sheet of targets (300 mm), optionally warped out of plane by ``thickness_ratio`` of its extent."""
    xy = rng.uniform(-0.15, 0.15, (n, 2))
    z = (0.3 * thickness_ratio) * (np.sin(9 * xy[:, 0]) * np.cos(7 * xy[:, 1]) if warp else rng.uniform(-1, 1, n))
    xyz = np.c_[xy, z]
    pose = invert(look_at([0.2, 0.25, 0.55], [0.0, 0.0, 0.0], roll_rad=0.2))
    return xyz, project(INTR, pose, xyz) + rng.normal(0.0, noise, (n, 2)), pose


@pytest.mark.parametrize("ratio", [0.003, 0.01, 0.03])
def test_a_nearly_planar_sheet_is_refused_not_calibrated(ratio):
    xyz, uv, _ = _sheet(np.random.default_rng(3), ratio, warp=True)
    with pytest.raises(CalibrationError, match="planar"):
        faugeras_toscani(xyz, uv, INTR.width, INTR.height)


def test_too_few_points_and_bunched_image_points_are_refused():
    xyz, uv, _ = _scene(np.random.default_rng(4), n=7)
    with pytest.raises(CalibrationError, match="at least 8"):
        faugeras_toscani(xyz, uv, INTR.width, INTR.height)
    rng = np.random.default_rng(5)
    xyz = rng.uniform(-0.004, 0.004, (30, 3))  # an 8 mm cluster seen from 0.85 m: ~20 px across
    pose = invert(look_at([0.45, 0.4, 0.6], [0.0, 0.0, 0.0]))
    with pytest.raises(CalibrationError, match="bunched"):
        faugeras_toscani(xyz, project(INTR, pose, xyz), INTR.width, INTR.height)


def test_an_implausible_interior_orientation_is_refused():
    xyz, uv, _ = _scene(np.random.default_rng(6), n=60, noise=0.05)
    far_lens = Intrinsics(fx_px=1500.0, fy_px=1500.0, cx_px=1224.0, cy_px=1024.0, width=2448, height=2048)
    with pytest.raises(CalibrationError, match="implausible.*lens"):
        faugeras_toscani(xyz, uv, INTR.width, INTR.height, nominal=far_lens)
    stretched = uv * np.array([1.0, 1.2])  # pixels 20 % taller than the camera's: not this camera
    with pytest.raises(CalibrationError, match="pixel aspect"):
        faugeras_toscani(xyz, stretched - [0, 200], INTR.width, INTR.height, nominal=INTR)
    faugeras_toscani(xyz, stretched - [0, 200], INTR.width, INTR.height)  # rectangular pixels exist (no nominal)


@pytest.mark.parametrize("ratio,expect", [(0.0, "IPPE"), (0.003, "IPPE"), (0.3, "SQPnP")])
def test_images_refused_by_faugeras_toscani_are_oriented_by_pnp(ratio, expect):
    from calibration.faugeras_toscani import orient_without_ft

    xyz, uv, pose = _sheet(np.random.default_rng(7), ratio, warp=True, noise=0.05)
    T, rms, method = orient_without_ft(xyz, uv, INTR)
    assert expect in method and rms < 0.1
    assert np.linalg.norm(T[:3, 3] - pose[:3, 3]) < 2e-3
    guess = pose.copy()
    guess[:3, 3] += [0.01, -0.01, 0.02]  # the robot's pose: a centimetre off
    T2, _, method2 = orient_without_ft(xyz, uv, INTR, guess=guess)
    assert "robot" in method2 and np.linalg.norm(T2[:3, 3] - pose[:3, 3]) < 2e-3
    with pytest.raises(CalibrationError, match="rms|behind"):
        orient_without_ft(xyz, uv[::-1].copy(), INTR)  # wrong identification


def test_a_bundle_with_an_implausible_sigma0_or_lens_is_refused():
    from calibration.plausibility import check_adjustment

    check_adjustment(0.05, INTR, INTR)
    with pytest.raises(CalibrationError, match="sigma0 16.5"):
        check_adjustment(16.5, INTR, INTR)
    tiny = Intrinsics(fx_px=148.0, fy_px=148.0, cx_px=1230.5, cy_px=1015.5, width=2448, height=2048)
    with pytest.raises(CalibrationError, match="focal length 148"):
        check_adjustment(0.05, tiny, INTR)
