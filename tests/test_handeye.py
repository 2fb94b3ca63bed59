"""Hand-eye calibration (AX = XB) against a synthetic cell with a known hand-eye and artefact placement."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.camera import Intrinsics, exp_se3, invert, look_at, make_pose, project
from calibration.errors import CalibrationError
from calibration.handeye import (
    METHODS,
    HandEyeOptions,
    adjoint,
    compare_methods,
    hand_eye_conditioning,
    hand_eye_information,
    mean_pose,
    pose_consistency,
    pose_error,
    refine_hand_eye,
    reprojection_jacobian,
    solve_opencv,
    weakest_rotation,
)

INTR = Intrinsics.from_focal_length(8e-3, 3.45e-6, 2448, 2048)
X_TRUE = make_pose(np.eye(3), [0.0, 0.04, 0.09]) @ exp_se3([0.02, -0.03, 0.05, 0.0012, -0.0008, 0.0015])
Y_TRUE = make_pose(np.eye(3), [0.65, 0.05, 0.0]) @ exp_se3([0.0, 0.0, 0.4, 0.0, 0.0, 0.0])


def _field(rng: np.random.Generator, n: int = 80) -> np.ndarray:
    """A stepped target field, 0.3 x 0.24 m, heights 0..60 mm (not coplanar)."""
    xy = rng.uniform([-0.15, -0.12], [0.15, 0.12], size=(n, 2))
    z = 0.02 * np.floor(rng.uniform(0, 4, size=n))
    return np.column_stack([xy, z])


def _stations(rng: np.random.Generator, m: int) -> np.ndarray:
    """part_from_cam (m, 4, 4): cameras 0.5 m from the field, tilted up to 45 deg, rolled +-90 deg."""
    out = []
    for _ in range(m):
        az = rng.uniform(-np.pi, np.pi)
        el = rng.uniform(np.deg2rad(45), np.deg2rad(88))
        eye = 0.5 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        out.append(look_at(eye, rng.normal(0, 0.02, 3), roll_rad=rng.uniform(-np.pi / 2, np.pi / 2)))
    return np.array(out)


def _scene(seed: int = 0, m: int = 15, sigma_px: float = 0.05):
    rng = np.random.default_rng(seed)
    xyz = _field(rng)
    P = _stations(rng, m)
    B = Y_TRUE @ P @ invert(X_TRUE)  # base_from_flange
    img, pts, uv = [], [], []
    for i in range(m):
        u = project(INTR, invert(P[i]), xyz)
        ok = INTR.in_image(u, 10)
        img += [i] * int(ok.sum())
        pts.append(xyz[ok])
        uv.append(u[ok] + rng.normal(0, sigma_px, (int(ok.sum()), 2)))
    return B, invert(P), np.array(img), np.concatenate(pts), np.concatenate(uv), xyz, P


def test_opencv_methods_recover_exact_hand_eye_from_exact_poses():
    B, A, *_ = _scene()
    for m in METHODS:
        s = solve_opencv(B, A, m)
        dt, dr = pose_error(s.flange_from_cam, X_TRUE)
        assert dt < 1e-6 and dr < 1e-7, m
        dt, dr = pose_error(s.base_from_target, Y_TRUE)
        assert dt < 1e-6 and dr < 1e-7, m


def test_compare_methods_runs_all_five_opencv_methods_and_ranks_them_by_consistency():
    B, A, *_ = _scene()
    rng = np.random.default_rng(3)
    noisy = np.array([exp_se3(np.r_[rng.normal(0, 2e-4, 3), rng.normal(0, 2e-4, 3)]) @ a for a in A])
    sols, failed = compare_methods(B, noisy)
    assert failed == {}
    assert {s.method for s in sols} == set(METHODS) == {"tsai", "park", "horaud", "andreff", "daniilidis"}
    assert [s.rms_translation_m for s in sols] == sorted(s.rms_translation_m for s in sols)
    assert sols[0].rms_translation_m > 0
    for s in sols:  # a sound set of stations: every method lands within 2 mm / 0.1 deg
        dt, dr = pose_error(s.flange_from_cam, X_TRUE)
        assert dt < 2e-3 and np.rad2deg(dr) < 0.1, s.method
    # the methods are different estimators: on noisy poses they do not all give the same answer
    X = np.array([s.flange_from_cam[:3, 3] for s in sols])
    assert np.ptp(X, axis=0).max() > 1e-6


def test_pure_translations_are_rejected_as_degenerate():
    B, A, *_ = _scene(m=3)
    # three stations differing only by a translation of the flange: the rotation of X is undetermined
    B2 = np.array([B[0] @ make_pose(np.eye(3), d) for d in ([0, 0, 0], [0.05, 0, 0], [0, 0.05, 0])])
    A2 = invert(X_TRUE) @ invert(B2) @ Y_TRUE
    for m in METHODS:
        with pytest.raises(CalibrationError, match="rotate"):
            solve_opencv(B2, A2, m)


def test_rotations_about_one_axis_only_are_rejected_as_degenerate():
    # the flange turns about its z axis only: X's translation along z is undetermined
    B = np.array([make_pose(np.eye(3), [0.5, 0.0, 0.4]) @ exp_se3([0, 0, a, 0, 0, 0]) for a in (0.0, 0.6, 1.2, 1.8)])
    A = invert(X_TRUE) @ invert(B) @ Y_TRUE
    weak, axis = weakest_rotation(B)
    assert weak < 1e-6 and abs(abs(axis[2]) - 1.0) < 1e-9
    with pytest.raises(CalibrationError, match="rotate"):
        compare_methods(B, A)


def test_weakest_rotation_is_the_angle_of_motions_about_perpendicular_axes():
    # every motion turns by 60 deg about an axis in the xy plane: z is informed as by a 60 deg
    # rotation about a perpendicular axis; x and y less (the axes share them)
    R = [exp_se3([0, 0, 0, 0, 0, 0])] + [exp_se3(np.r_[np.deg2rad(60.0) * np.array([np.cos(a), np.sin(a), 0.0]), 0, 0, 0])
                                         for a in np.deg2rad([0.0, 90.0])]
    weak, axis = weakest_rotation(np.array(R))
    assert 0 < np.rad2deg(weak) < 60.0
    assert weakest_rotation(np.array([np.eye(4), np.eye(4)]))[0] == 0.0


def test_adjoint_maps_perturbations_through_a_transform():
    T = exp_se3([0.3, -0.2, 0.5, 0.1, 0.2, -0.3])
    xi = np.array([1e-6, -2e-6, 3e-6, 4e-6, -1e-6, 2e-6])
    lhs = T @ exp_se3(xi) @ invert(T)
    rhs = exp_se3(adjoint(T) @ xi)
    assert np.allclose(lhs, rhs, atol=1e-11)


def test_reprojection_jacobian_matches_finite_differences():
    B, _, img, xyz, uv, *_ = _scene(m=4)
    u0, J = reprojection_jacobian(INTR, B, X_TRUE, Y_TRUE, img, xyz)
    h = 1e-7
    for k in range(12):
        d = np.zeros(12)
        d[k] = h
        X = X_TRUE @ exp_se3(d[:6])
        Y = exp_se3(d[6:]) @ Y_TRUE
        u1, _ = reprojection_jacobian(INTR, B, X, Y, img, xyz)
        assert np.allclose((u1 - u0) / h, J[:, :, k], rtol=1e-4, atol=1e-2), k


def test_joint_refinement_recovers_hand_eye_and_its_uncertainty_is_honest():
    errs, sig = [], []
    for seed in range(6):
        B, A, img, xyz, uv, *_ = _scene(seed=seed, sigma_px=0.05)
        X0 = X_TRUE @ exp_se3([0.01, -0.01, 0.02, 0.003, 0.002, -0.002])  # ~1.4 deg, 4 mm off
        res = refine_hand_eye(INTR, B, img, xyz, uv, X0, mean_pose(B @ X0 @ A), HandEyeOptions(sigma_px=0.05))
        dt, dr = pose_error(res.flange_from_cam, X_TRUE)
        assert dt < 0.1e-3 and np.rad2deg(dr) < 0.01
        assert 0.04 < res.sigma0_px < 0.06
        assert not res.rejected.any()
        errs.append(invert(X_TRUE) @ res.flange_from_cam)
        sig.append(np.linalg.norm(res.sigma_translation_m))
    # the translation errors scatter like the stated uncertainty (within a factor of ~2.5 over 6 runs)
    rms = np.sqrt(np.mean([np.sum(e[:3, 3] ** 2) for e in errs]))
    assert 0.4 < rms / np.mean(sig) < 2.5


def test_joint_refinement_drops_a_blunder():
    B, A, img, xyz, uv, *_ = _scene(seed=1)
    uv = uv.copy()
    uv[17] += [3.0, -2.0]
    res = refine_hand_eye(INTR, B, img, xyz, uv, X_TRUE, Y_TRUE, HandEyeOptions(sigma_px=0.05))
    assert res.rejected[17] and res.rejected.sum() <= 2
    assert pose_error(res.flange_from_cam, X_TRUE)[0] < 0.1e-3


def test_fixed_hand_eye_refines_only_the_artefact_placement():
    B, A, img, xyz, uv, *_ = _scene(seed=2)
    Y0 = exp_se3([0.01, 0.02, -0.01, 0.01, -0.02, 0.005]) @ Y_TRUE
    res = refine_hand_eye(INTR, B, img, xyz, uv, X_TRUE, Y0, HandEyeOptions(fix_flange_from_cam=True))
    assert np.array_equal(res.flange_from_cam, X_TRUE)
    assert pose_error(res.base_from_target, Y_TRUE)[0] < 0.05e-3
    assert np.all(res.cov[:6] == 0)


def test_pose_consistency_is_zero_for_exact_data():
    B, A, *_ = _scene()
    dt, dr = pose_consistency(B, X_TRUE, A, Y_TRUE)
    assert dt.max() < 1e-9 and dr.max() < 1e-9


def test_conditioning_predicts_the_refinements_precision_and_flags_parallel_stations():
    B, A, img, xyz, uv, field, P = _scene(seed=4, sigma_px=0.05)
    vis = np.array([INTR.in_image(project(INTR, invert(p), field), 10) for p in P])
    info = hand_eye_information(INTR, P, vis, field, X_TRUE, Y_TRUE, 0.05)
    cond = hand_eye_conditioning(info, P, X_TRUE)
    res = refine_hand_eye(INTR, B, img, xyz, uv, X_TRUE, Y_TRUE, HandEyeOptions(sigma_px=0.05))
    # the same linearisation: predicted sigmas are the refinement's, scaled by a priori / a posteriori sigma
    scale = 0.05 / res.sigma0_px
    assert np.allclose(cond.sigma_translation_m, res.sigma_translation_m * scale, rtol=0.05)
    assert np.allclose(cond.sigma_rotation_rad, res.sigma_rotation_rad * scale, rtol=0.05)
    assert np.rad2deg(cond.weakest_rotation_rad) > 20.0
    assert cond.shortfall(0.5e-3, np.deg2rad(0.05), np.deg2rad(10.0)) == []
    # ten views straight down, the same roll: the camera only translates; X is not determined
    rng = np.random.default_rng(5)
    par = np.array([look_at([x, y, 0.5], [x, y, 0.0], roll_rad=0.0) for x, y in rng.uniform(-0.05, 0.05, (10, 2))])
    vis_p = np.array([INTR.in_image(project(INTR, invert(p), field), 10) for p in par])
    bad = hand_eye_conditioning(hand_eye_information(INTR, par, vis_p, field, X_TRUE, Y_TRUE, 0.05), par, X_TRUE)
    assert bad.weakest_rotation_rad < 1e-6
    missed = bad.shortfall(0.5e-3, np.deg2rad(0.05), np.deg2rad(10.0))
    assert any("weakest rotation" in m for m in missed) and any("translation" in m for m in missed)
