"""The camera model: Jacobians against finite differences, projective == collinearity, round trips."""
import numpy as np
import pytest

from calibration.camera import (
    Intrinsics, collinearity_from_pose, decompose_projection_matrix, exp_se3, invert, look_at,
    pose_from_collinearity, project, project_collinearity, project_with_jacobians, projection_matrix,
)
from calibration.errors import CalibrationError


def _scene(rng, n=30, distorted=True):
    intr = Intrinsics.from_focal_length(
        0.012, 3.45e-6, 2448, 2048, cx_px=1230.2, cy_px=1019.7,
        **({"k1": -0.08, "k2": 0.05, "k3": -0.01, "p1": 2e-4, "p2": -1e-4} if distorted else {}),
    )
    part_from_cam = look_at(np.array([0.4, -0.3, 0.5]), np.array([0.01, 0.02, 0.0]), roll_rad=0.3)
    cam_from_part = invert(part_from_cam)
    pts = rng.uniform(-0.12, 0.12, size=(n, 3))
    return intr, cam_from_part, pts


@pytest.mark.parametrize("distorted", [False, True])
def test_point_jacobian_matches_finite_differences(distorted):
    intr, T, pts = _scene(np.random.default_rng(1), distorted=distorted)
    _, J, _ = project_with_jacobians(intr, T, pts)
    h = 1e-7
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        fd = (project(intr, T, pts + d) - project(intr, T, pts - d)) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], fd, rtol=1e-5, atol=1e-3)


@pytest.mark.parametrize("distorted", [False, True])
def test_pose_jacobian_matches_finite_differences(distorted):
    intr, T, pts = _scene(np.random.default_rng(2), distorted=distorted)
    _, _, J = project_with_jacobians(intr, T, pts)
    h = 1e-7
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = h
        fd = (project(intr, exp_se3(xi) @ T, pts) - project(intr, exp_se3(-xi) @ T, pts)) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], fd, rtol=1e-5, atol=1e-3)


def test_projective_and_collinearity_models_give_the_same_image_points():
    intr, T, pts = _scene(np.random.default_rng(3), distorted=False)
    M = projection_matrix(intr, T)
    h = np.c_[pts, np.ones(len(pts))] @ M.T
    uv_projective = h[:, :2] / h[:, 2:]
    R, Pc = collinearity_from_pose(T)
    uv_collinearity = project_collinearity(intr, R, Pc, pts)
    np.testing.assert_allclose(uv_projective, uv_collinearity, atol=1e-9)
    np.testing.assert_allclose(uv_projective, project(intr, T, pts), atol=1e-9)
    # Pc is the camera centre: Pc = -R^T T (seed eq. 5)
    np.testing.assert_allclose(Pc, invert(T)[:3, 3], atol=1e-12)
    np.testing.assert_allclose(pose_from_collinearity(R, Pc), T, atol=1e-12)


def test_projection_matrix_decomposes_back_to_interior_and_exterior_orientation():
    intr, T, _ = _scene(np.random.default_rng(4), distorted=False)
    M = projection_matrix(intr, T) * -3.7  # any scale and sign
    intr2, T2 = decompose_projection_matrix(M, intr.width, intr.height)
    np.testing.assert_allclose([intr2.fx_px, intr2.fy_px, intr2.cx_px, intr2.cy_px],
                               [intr.fx_px, intr.fy_px, intr.cx_px, intr.cy_px], rtol=1e-9)
    np.testing.assert_allclose(T2, T, atol=1e-9)


def test_degenerate_projection_matrix_is_a_calibration_error():
    with pytest.raises(CalibrationError, match="degenerate"):
        decompose_projection_matrix(np.zeros((3, 4)), 100, 100)


def test_distortion_round_trip():
    intr, T, pts = _scene(np.random.default_rng(5))
    uv = project(intr, T, pts)
    xy = intr.pixel_to_normalised(uv)
    Xc = pts @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(xy, Xc[:, :2] / Xc[:, 2:], atol=1e-12)


def test_pose_inverse_and_look_at_round_trip():
    eye, tgt = np.array([0.3, 0.2, 0.6]), np.array([0.0, 0.05, 0.02])
    part_from_cam = look_at(eye, tgt)
    np.testing.assert_allclose(invert(invert(part_from_cam)), part_from_cam, atol=1e-12)
    np.testing.assert_allclose(part_from_cam[:3, 3], eye)
    # the target projects to the principal point
    intr = Intrinsics(1000, 1000, 320, 240, 640, 480)
    np.testing.assert_allclose(project(intr, invert(part_from_cam), tgt[None]), [[320, 240]], atol=1e-9)
    assert np.isclose(np.linalg.det(part_from_cam[:3, :3]), 1.0)


def test_point_behind_camera_projects_to_nan():
    intr = Intrinsics(1000, 1000, 320, 240, 640, 480)
    uv = project(intr, np.eye(4), np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]))
    assert np.isnan(uv[0]).all() and np.isfinite(uv[1]).all()


def test_pixel_origin_is_the_centre_of_the_top_left_pixel():
    intr = Intrinsics.from_focal_length(0.01, 1e-5, 640, 480)
    assert (intr.cx_px, intr.cy_px) == (319.5, 239.5)
    assert intr.in_image(np.array([[-0.5, -0.5], [639.5, 479.5]])).all()
    assert not intr.in_image(np.array([[-0.6, 0.0]])).any()
