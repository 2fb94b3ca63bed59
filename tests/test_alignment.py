"""Alignment to CAD and deviations, with propagated covariance, against known truth."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.alignment import PointCovariance, align_to_cad, helmert_basis, similarity_fit
from calibration.bundle import BundleOptions, bundle_adjust, simulate_network
from calibration.camera import exp_se3, make_pose, project
from calibration.errors import CalibrationError
from scipy.spatial.transform import Rotation


def test_similarity_fit_recovers_a_known_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(30, 3))
    R = Rotation.from_rotvec([0.3, -0.5, 1.1]).as_matrix()
    dst = 1.3 * src @ R.T + [1.0, 2.0, -3.0]
    s, R2, t = similarity_fit(src, dst, with_scale=True)
    assert s == pytest.approx(1.3) and np.allclose(R2, R) and np.allclose(t, [1.0, 2.0, -3.0])
    with pytest.raises(CalibrationError, match="one line"):
        similarity_fit(np.outer(np.arange(5.0), [1, 2, 3]), np.outer(np.arange(5.0), [1, 2, 3]))


def test_s_transform_of_the_low_rank_form_equals_the_dense_product():
    rng = np.random.default_rng(1)
    n, r = 12, 5
    A = rng.normal(size=(n, 3, 3))
    D = A @ np.swapaxes(A, 1, 2)
    U = rng.normal(size=(n, 3, r))
    C = np.cov(rng.normal(size=(r, 40)))
    pc = PointCovariance(D, U, C)
    G = helmert_basis(rng.normal(size=(n, 3)))
    w = rng.uniform(0.5, 2.0, n)
    H = G * w[:, None, None]
    P = G @ np.linalg.inv(np.einsum("nad,nae->de", H, G))
    S = np.eye(3 * n) - P.reshape(3 * n, -1) @ H.reshape(3 * n, -1).T
    dense = S @ pc.dense() @ S.T
    np.testing.assert_allclose(pc.s_transform(P, H).dense(), dense, atol=1e-10)
    Rm = Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix() * 1.1
    Rb = np.kron(np.eye(n), Rm)
    np.testing.assert_allclose(pc.rotated(Rm).dense(), Rb @ pc.dense() @ Rb.T, atol=1e-10)


def test_rigid_alignment_brings_a_moved_part_back_and_finds_no_deviation():
    rng = np.random.default_rng(2)
    nominal = rng.uniform(-0.2, 0.2, (50, 3))
    T = make_pose(Rotation.from_rotvec([0.2, 0.1, -0.4]).as_matrix(), [0.5, -0.1, 0.3])
    sig = 1e-5
    measured = nominal @ T[:3, :3].T + T[:3, 3] + rng.normal(0, sig, (50, 3))
    al = align_to_cad(measured, np.broadcast_to(np.eye(3) * sig**2, (50, 3, 3)).copy(), nominal)
    np.testing.assert_allclose(al.part_from_measured @ T, np.eye(4), atol=1e-5)
    assert al.rms_m < 3 * sig
    # independent targets: the fit absorbs 6 of the 150 degrees of freedom
    assert np.mean(np.trace(al.deviation_cov, axis1=1, axis2=2)) == pytest.approx(3 * sig**2 * (1 - 6 / 150), rel=1e-6)


def _project_all(net, points):
    return np.vstack([project(net.intrinsics, net.cam_from_part[j], points[net.obs_target[net.obs_image == j]])
                      for j in range(len(net.cam_from_part))])


def _network_deviation_runs(rng, n_runs, inject_sigma=0.0, n_inject=0):
    """Free networks (no scale information): the CAD fit is a similarity. Returns sigma levels and injected flags."""
    base = simulate_network(rng, n_targets=150, n_images=10, sigma_px=0.05)
    levels, injected = [], []
    for run in range(n_runs):
        x0 = base.points + rng.normal(0, 5e-4, base.points.shape)
        poses0 = np.array([exp_se3(rng.normal(0, 0.002, 6)) @ T for T in base.cam_from_part])
        idx = rng.choice(150, n_inject, replace=False) if n_inject else np.zeros(0, int)
        truth = base.points.copy()
        if n_inject:
            # size each deviation from its own predicted deviation sigma along its direction
            dirs = rng.normal(size=(n_inject, 3))
            dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
            res0 = bundle_adjust(base.obs_image, base.obs_target, _project_all(base, truth), base.intrinsics,
                                 poses0, x0, BundleOptions(snooping=False, a_posteriori=False))
            al0 = align_to_cad(res0.points, res0.covariance, base.points, with_scale=True)
            sd = np.sqrt(np.einsum("na,nab,nb->n", dirs, al0.deviation_cov[idx], dirs))
            truth[idx] += dirs * (inject_sigma * sd)[:, None]
        uv = _project_all(base, truth) + rng.normal(0, 0.05, base.obs_uv.shape)
        res = bundle_adjust(base.obs_image, base.obs_target, uv, base.intrinsics, poses0, x0,
                            BundleOptions(snooping=False))
        al = align_to_cad(res.points, res.covariance, base.points, with_scale=True)
        levels.append(al.sigma_level())
        injected.append(np.isin(np.arange(150), idx))
    return np.concatenate(levels), np.concatenate(injected)


def test_deviation_false_alarms_at_three_sigma_stay_below_one_percent():
    levels, _ = _network_deviation_runs(np.random.default_rng(3), n_runs=12)
    assert np.mean(levels > 3.0) <= 0.01
    # the normalised deviations are chi-square(3): their mean square is 3 (to Monte Carlo precision)
    from scipy.stats import chi2, norm
    m2 = chi2.isf(2 * norm.sf(levels), 3)
    assert abs(np.mean(m2) / 3.0 - 1.0) < 0.1


def test_deviations_larger_than_five_sigma_are_all_found():
    levels, injected = _network_deviation_runs(np.random.default_rng(4), n_runs=4, inject_sigma=7.0, n_inject=10)
    assert np.all(levels[injected] > 3.0)
    assert np.mean(levels[~injected] > 3.0) <= 0.02


def test_independent_covariance_approximation_is_accepted_but_cross_covariance_is_exact():
    rng = np.random.default_rng(5)
    net = simulate_network(rng, n_targets=100, n_images=8)
    res = bundle_adjust(net.obs_image, net.obs_target, net.obs_uv, net.intrinsics, net.cam_from_part,
                        net.points, BundleOptions(snooping=False))
    exact = align_to_cad(res.points, res.covariance, net.points)
    approx = align_to_cad(res.points, res.cov, net.points)
    np.testing.assert_allclose(exact.deviation, approx.deviation)
    # same deviations; the covariances differ (the exact one accounts for the targets' correlation)
    assert not np.allclose(exact.deviation_cov, approx.deviation_cov, rtol=1e-3, atol=0.0)
    dense = exact.deviation_covariance.dense()
    np.testing.assert_allclose(dense[:3, :3], exact.deviation_cov[0], rtol=1e-8, atol=1e-20)


def test_shape_mismatch_is_a_clear_error():
    with pytest.raises(CalibrationError, match="must both be"):
        align_to_cad(np.zeros((4, 3)), np.zeros((4, 3, 3)), np.zeros((5, 3)))
