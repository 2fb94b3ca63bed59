"""Observations of unequal precision in the bundle adjustment: weights, variance components, truth."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.alignment import similarity_fit
from calibration.bundle import BundleConfig, BundleOptions, ScaleBar, bundle_adjust, simulate_network
from calibration.camera import exp_se3, invert, look_at
from calibration.errors import CalibrationError
from calibration.weights import group_labels, incidence_angles, incidence_groups, variance_component_factors

SIGMA_LOW, SIGMA_HIGH = 0.03, 0.09  # px: two groups 3x apart


def _two_group_network(seed: int, share_high: float = 0.4):
    """A ring network whose observations belong to two groups with sigmas 3x apart (truth known)."""
    rng = np.random.default_rng(seed)
    net = simulate_network(rng, n_targets=200, n_images=12, sigma_px=0.0)
    q = len(net.obs_image)
    group = (rng.random(q) < share_high).astype(int)
    sigma = np.where(group == 1, SIGMA_HIGH, SIGMA_LOW)
    uv = net.obs_uv + rng.normal(0.0, 1.0, (q, 2)) * sigma[:, None]
    poses0 = np.array([exp_se3(rng.normal(0, 0.002, 6)) @ T for T in net.cam_from_part])
    x0 = net.points + rng.normal(0.0, 5e-4, net.points.shape)
    return net, uv, group, sigma, poses0, x0


def _errors(res, truth):
    """Errors after the free network's similarity fit to the truth, and their m^2 under the stated covariance."""
    s, R, t = similarity_fit(res.points, truth, with_scale=True)
    e = s * res.points @ R.T + t - truth
    C = (s * s) * R @ res.cov @ R.T
    return e, np.einsum("na,na->n", e, np.linalg.solve(C, e[..., None])[..., 0])


def test_variance_components_recover_two_group_sigmas_and_beat_equal_weights():
    m2_all, rms_w, rms_u = [], [], []
    for seed in (0, 1, 2):
        net, uv, group, _, poses0, x0 = _two_group_network(seed)
        opts = BundleOptions(sigma_px=0.05)
        equal = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, opts)
        vce = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, opts, obs_group=group)
        vc = vce.variance_components
        assert vc.converged and vc.estimated.all()
        np.testing.assert_allclose(vc.sigma_px, [SIGMA_LOW, SIGMA_HIGH], rtol=0.15)
        np.testing.assert_allclose(vce.obs_sigma_px, vc.sigma_px[group])
        e_w, m2 = _errors(vce, net.points)
        e_u, _ = _errors(equal, net.points)
        rms_w.append(np.sqrt(np.mean(np.sum(e_w**2, axis=1))))
        rms_u.append(np.sqrt(np.mean(np.sum(e_u**2, axis=1))))
        m2_all.append(m2)
    # weighting by the estimated sigmas: smaller errors than equal weights, and honestly stated
    assert np.mean(rms_w) < 0.8 * np.mean(rms_u)
    assert 0.7 <= np.mean(np.concatenate(m2_all)) / 3.0 <= 1.4


def test_weighted_data_snooping_statistics_follow_chi_square_and_keep_clean_observations():
    net, uv, group, _, poses0, x0 = _two_group_network(3)
    opts = BundleOptions(sigma_px=0.05)
    equal = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, opts)
    vce = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, opts, obs_group=group)
    # equal weights take the noisy group's tail for blunders; the weighted test does not
    assert equal.rejected.sum() >= 2
    assert vce.rejected.sum() == 0
    T = vce.test_statistic[np.isfinite(vce.test_statistic)]
    assert 1.85 < T.mean() < 2.15  # chi-square, 2 degrees of freedom
    # redundancy numbers of the whitened observations add up to the degrees of freedom
    assert np.nansum(2 * vce.redundancy) == pytest.approx(vce.dof, rel=1e-6)


def test_given_sigmas_weight_the_adjustment_and_scale_out_of_the_a_posteriori_covariance():
    net, uv, _, sigma, poses0, x0 = _two_group_network(4)
    opts = BundleOptions(sigma_px=0.05, snooping=False)
    a = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, opts, obs_sigma_px=sigma)
    b = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, opts, obs_sigma_px=3 * sigma)
    np.testing.assert_allclose(a.points, b.points, atol=1e-10)
    np.testing.assert_allclose(a.cov, b.cov, rtol=1e-6, atol=1e-18)
    # sigma0 in pixels is the measured image precision, whatever scale the a priori sigmas had
    assert a.sigma0_px == pytest.approx(b.sigma0_px, rel=1e-6)
    assert a.sigma0_px == pytest.approx(np.sqrt(np.mean(sigma**2)), rel=0.05)
    assert a.variance_components is None and a.converged


def test_equal_given_sigmas_reproduce_the_unweighted_adjustment():
    net, uv, _, _, poses0, x0 = _two_group_network(5)
    opts = BundleOptions(sigma_px=0.05)
    ref = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, opts)
    w = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, opts,
                      obs_sigma_px=np.full(len(uv), 0.05))
    np.testing.assert_allclose(w.points, ref.points, atol=1e-9)
    np.testing.assert_allclose(w.cov, ref.cov, rtol=1e-5, atol=1e-18)
    assert w.sigma0_px == pytest.approx(ref.sigma0_px, rel=1e-6)
    np.testing.assert_array_equal(w.rejected, ref.rejected)


def test_small_group_keeps_the_common_sigma_and_its_blunder_is_rejected():
    net, uv, group, _, poses0, x0 = _two_group_network(6, share_high=0.0)
    small = np.flatnonzero(np.random.default_rng(6).random(len(uv)) < 0.01)  # ~1%: too little redundancy
    group = group.copy()
    group[small] = 1
    uv = uv.copy()
    uv[small[0]] += [4.0, -3.0]  # a blunder in the small group
    res = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0,
                        BundleOptions(sigma_px=0.05), obs_group=group)
    vc = res.variance_components
    assert res.rejected[small[0]] and res.rejected.sum() <= 2
    assert list(vc.estimated) == [True, False]
    np.testing.assert_allclose(vc.sigma_px, SIGMA_LOW, rtol=0.1)  # not inflated by the blunder


def test_variance_components_with_a_scale_bar_keep_its_length():
    net, uv, group, _, poses0, x0 = _two_group_network(7)
    a, b = int(np.argmin(net.points[:, 0])), int(np.argmax(net.points[:, 0]))
    length = float(np.linalg.norm(net.points[a] - net.points[b]))
    cfg = BundleConfig(scale_bars=(ScaleBar(a, b, length, 1e-6),))
    res = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, BundleOptions(sigma_px=0.05),
                        cfg, obs_group=group)
    assert res.converged and res.datum == "scale_bar"
    assert np.linalg.norm(res.points[a] - res.points[b]) == pytest.approx(length, abs=3e-6)
    np.testing.assert_allclose(res.variance_components.sigma_px, [SIGMA_LOW, SIGMA_HIGH], rtol=0.15)


def test_incidence_angle_is_measured_between_normal_and_line_of_sight():
    points = np.zeros((1, 3))
    normals = np.array([[0.0, 0.0, 1.0]])
    angles = np.radians([0.0, 30.0, 55.0, 80.0])
    poses = np.array([invert(look_at(0.5 * np.array([0.0, np.sin(a), np.cos(a)]), np.zeros(3)))
                      for a in angles])
    got = incidence_angles(points, normals, poses, np.arange(4), np.zeros(4, dtype=int))
    np.testing.assert_allclose(got, angles, atol=1e-9)
    np.testing.assert_array_equal(incidence_groups(got), [0, 0, 1, 2])
    assert group_labels() == ["< 50 deg", "50-70 deg", ">= 70 deg"]


def test_variance_factor_of_a_group_is_its_weighted_square_sum_over_its_redundancy():
    r = np.array([[1.0, 1.0], [2.0, 0.0], [0.0, 3.0]])
    f, r_g, common = variance_component_factors(np.array([0, 0, 1]), r, np.array([0.5, 0.5, 0.25]), 2)
    np.testing.assert_allclose(r_g, [2.0, 0.5])
    np.testing.assert_allclose(f, [6.0 / 2.0, 9.0 / 0.5])
    assert common == pytest.approx(15.0 / 2.5)


def test_bad_observation_sigmas_and_groups_are_refused():
    net, uv, group, _, poses0, x0 = _two_group_network(8)
    with pytest.raises(CalibrationError, match="obs_sigma_px"):
        bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0,
                      obs_sigma_px=np.zeros(len(uv)))
    with pytest.raises(CalibrationError, match="obs_group"):
        bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, obs_group=group[:-1])


def test_a_2x2_covariance_per_observation_whitens_the_adjustment_and_states_honest_errors():
    """Elongated image errors (5:1, random directions): the full 2x2 covariance per observation beats the
    isotropic sigma of the same size and states its errors honestly; an isotropic covariance is the sigma."""
    rng = np.random.default_rng(9)
    net = simulate_network(rng, n_targets=200, n_images=12, sigma_px=0.0)
    q = len(net.obs_image)
    ang = rng.uniform(0, np.pi, q)
    d = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    n = np.stack([-d[:, 1], d[:, 0]], axis=1)
    C = 0.1**2 * np.einsum("qa,qb->qab", d, d) + 0.02**2 * np.einsum("qa,qb->qab", n, n)
    uv = net.obs_uv + rng.normal(size=(q, 1)) * 0.1 * d + rng.normal(size=(q, 1)) * 0.02 * n
    poses0 = np.array([exp_se3(rng.normal(0, 0.002, 6)) @ T for T in net.cam_from_part])
    x0 = net.points + rng.normal(0.0, 5e-4, net.points.shape)
    opts = BundleOptions(sigma_px=0.05, snooping=False)
    iso = np.sqrt(np.trace(C, axis1=1, axis2=2) / 2)
    full = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, opts, obs_sigma_px=C)
    flat = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, opts, obs_sigma_px=iso)
    same = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, opts,
                         obs_sigma_px=iso[:, None, None] ** 2 * np.eye(2))
    np.testing.assert_allclose(same.points, flat.points, atol=1e-10)
    np.testing.assert_allclose(same.cov, flat.cov, rtol=1e-6, atol=1e-18)
    assert same.sigma0_px == pytest.approx(flat.sigma0_px, rel=1e-9)
    e_full, m2 = _errors(full, net.points)
    e_flat, _ = _errors(flat, net.points)
    assert np.sqrt(np.mean(np.sum(e_full**2, axis=1))) < 0.8 * np.sqrt(np.mean(np.sum(e_flat**2, axis=1)))
    assert 0.7 <= np.mean(m2) / 3.0 <= 1.4
    assert full.sigma0_px == pytest.approx(np.sqrt(np.mean(iso**2)), rel=0.1)
    with pytest.raises(CalibrationError, match="symmetric positive definite"):
        bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0, opts,
                      obs_sigma_px=C * np.array([[1.0, 1.0], [1.0, -1.0]]))
