"""The background misfit a target's views share (calibration.bundle.coherent, decision 0029): against a Monte
Carlo of the error it models, the stated covariance is honest with it and optimistic without it."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from calibration.bundle.coherent import coherent_background_cov
from calibration.camera import Intrinsics, invert, look_at, project

INTR = Intrinsics(2320.0, 2320.0, 1224.0, 1024.0, 2448, 2048)


def _views(rng, n_views=10, spread_deg=20.0):
    """Poses (cam_from_part) of views within ``spread_deg`` of one direction, 0.5 m from a point at the origin."""
    poses = []
    for _ in range(n_views):
        d = np.array([0.0, 0.0, 1.0]) + np.tan(np.deg2rad(spread_deg)) * rng.uniform(-1, 1, 3) * [1, 1, 0]
        eye = 0.5 * d / np.linalg.norm(d)
        poses.append(invert(look_at(eye, rng.normal(0, 0.02, 3))))
    return np.array(poses)


def _jacobian(T, X, h=1e-7):
    return np.column_stack([(project(INTR, T, (X + h * e)[None])[0] - project(INTR, T, (X - h * e)[None])[0]) / (2 * h)
                            for e in np.eye(3)])


def test_a_misfit_shared_by_the_views_is_stated_and_a_view_without_one_adds_nothing():
    rng = np.random.default_rng(4)
    poses = _views(rng)
    X = np.zeros((1, 3))
    m = len(poses)
    img, tgt = np.arange(m), np.zeros(m, dtype=int)
    sigma = np.full(m, 0.006)
    B = np.zeros((m, 2, 2))
    none = coherent_background_cov(INTR, poses, X, img, tgt, sigma, B, 0.26)
    assert np.all(none == 0)
    B[:] = np.diag([0.2, 0.1]) ** 2
    B[0] = 0.0  # one view without a misfit: the others still share theirs
    E = coherent_background_cov(INTR, poses, X, img, tgt, sigma, B, 0.26)[0]
    assert np.trace(E) > 0 and np.all(np.linalg.eigvalsh(E) >= -1e-12 * np.trace(E))
    # one view with a bound is nothing shared
    B1 = np.zeros((m, 2, 2))
    B1[3] = np.diag([0.2, 0.1]) ** 2
    assert np.all(coherent_background_cov(INTR, poses, X, img, tgt, sigma, B1, 0.26) == 0)


def test_the_stated_covariance_covers_a_misfit_common_to_the_views_monte_carlo():
    """Errors d_i = S_i Jh_i z (one z per trial: the surroundings are the same in every view) plus independent
    noise; the weighted intersection's error against (independent + shared) covariance: m^2 ~ chi^2(3)."""
    rng = np.random.default_rng(7)
    poses = _views(rng, 12)
    X = np.array([[0.001, -0.002, 0.0]])
    m = len(poses)
    c = 0.26
    B = np.array([np.diag(rng.uniform(0.05, 0.25, 2) ** 2) for _ in range(m)])
    sig = rng.uniform(0.005, 0.01, m)
    C = sig[:, None, None] ** 2 * np.eye(2) + c * c * B
    W = np.linalg.inv(C)
    J = np.array([_jacobian(T, X[0]) for T in poses])
    N = np.einsum("qba,qbc,qcd->ad", J, W, J)
    indep = np.linalg.inv(N)
    E = coherent_background_cov(INTR, poses, X, np.arange(m), np.zeros(m, dtype=int), C, B, c)[0]
    Xc = np.einsum("qab,b->qa", poses[:, :3, :3], X[0]) + poses[:, :3, 3]
    Jh = J * (Xc[:, 2] / INTR.fx_px)[:, None, None]
    S = np.array([np.sqrt(c * c * b) for b in B])  # diagonal bounds: the square root is elementwise
    trials = 3000
    z = rng.normal(size=(trials, 3))
    d = np.einsum("qab,qbc,tc->tqa", S, Jh, z) + rng.normal(size=(trials, m, 2)) * sig[None, :, None]
    err = np.einsum("ab,qcb,qcd,tqd->ta", indep, J, W, d)  # the weighted least-squares point's error
    m2_with = np.einsum("ta,ab,tb->t", err, np.linalg.inv(indep + E), err)
    m2_without = np.einsum("ta,ab,tb->t", err, N, err)
    assert 0.85 <= np.sqrt(m2_with.mean() / 3) <= 1.15, m2_with.mean()
    assert np.mean(m2_with <= chi2.ppf(0.99, 3)) >= 0.97
    assert np.sqrt(m2_without.mean() / 3) > 1.5  # independent weights alone: optimistic


def test_scale_bar_gains_are_how_the_adjusted_points_move_with_the_certified_length():
    """K from the covariance against two adjustments whose bar lengths differ by 20 um."""
    from calibration.bundle import BundleConfig, BundleOptions, ScaleBar, bundle_adjust, simulate_network
    from calibration.bundle.coherent import scale_bar_gains
    from calibration.camera import exp_se3

    rng = np.random.default_rng(3)
    net = simulate_network(rng, n_targets=120, n_images=10, sigma_px=0.05)
    poses0 = np.array([exp_se3(rng.normal(0, 0.002, 6)) @ T for T in net.cam_from_part])
    x0 = net.points + rng.normal(0.0, 5e-4, net.points.shape)
    a, b = int(np.argmin(net.points[:, 0])), int(np.argmax(net.points[:, 0]))
    length = float(np.linalg.norm(net.points[a] - net.points[b]))
    sigma, delta = 2e-6, 20e-6
    runs = []
    for L in (length, length + delta):
        cfg = BundleConfig(scale_bars=(ScaleBar(a, b, L, sigma),))
        runs.append(bundle_adjust(net.obs_image, net.obs_target, net.obs_uv, net.intrinsics, poses0, x0,
                                  BundleOptions(sigma_px=0.05, max_rejections=0), cfg))
    K, sig = scale_bar_gains(runs[0].covariance, runs[0].points, (ScaleBar(a, b, length, sigma),))
    moved = (runs[1].points - runs[0].points) / delta
    assert sig[0] == sigma
    np.testing.assert_allclose(K[:, :, 0], moved, atol=0.02 * np.abs(moved).max())
    assert np.abs(moved).max() > 0.1  # the far targets move a good share of the bar's change


def test_the_report_states_the_uncertainty_budget():
    """report.html's facts say how much of the variance is the scale bar's certificate, and what is stated beyond
    the detector model (report.json ``uncertainty_budget``)."""
    from cell.record.report import _budget_facts

    doc = {"uncertainty_budget": {"scale_bar_share_median": 0.095, "scale_bar_share_max": 0.376,
                                  "shared_misfit_targets": 17, "observations_clipped": 311,
                                  "scale_bar_ends": [{"bar": ["T0047", "T0172"], "length_sigma_m": 3.98e-6}]}}
    facts = _budget_facts(doc)
    assert facts["Scale bar certificate in the variance"] == "10 % median, 38 % at most"
    line = facts["Stated beyond the detector model"]
    assert "17 target(s)" in line and "311 observation(s)" in line and "T0047-T0172" in line and "4.0 um" in line
    assert _budget_facts({}) == {}
    doc["uncertainty_budget"].update(scale_sigma_ppm=14.23, scale_sigma_certificate_ppm=6.21)
    assert _budget_facts(doc)["Scale uncertainty (1 sigma)"] == "14.2 ppm, of which the scale bar certificate 6.2 ppm"


def test_the_stated_scale_uncertainty_is_what_a_similarity_fit_finds_over_noise_draws():
    """scale_sigma's g^T Q g against the scale of similarity fits to points drawn from Q (block-diagonal part and a
    shared low-rank scale mode)."""
    from calibration.alignment import PointCovariance, similarity_fit
    from cell.stages.report import scale_sigma

    rng = np.random.default_rng(11)
    n = 60
    X = rng.uniform(-0.15, 0.15, (n, 3))
    D = np.array([np.diag(rng.uniform(0.5, 2.0, 3) * 1e-6) ** 2 for _ in range(n)])
    k = (X - X.mean(axis=0))[:, :, None]  # a scale mode: every point moves with its distance from the centre
    pc = PointCovariance(D, k, np.array([[(10e-6) ** 2]]))  # 10 ppm
    use = np.ones(n, dtype=bool)
    sig, cert = scale_sigma(X, pc, use, k, np.array([5e-6]))
    draws = []
    for _ in range(3000):
        e = rng.normal(size=(n, 3)) * np.sqrt(np.diagonal(D, axis1=1, axis2=2)) + k[:, :, 0] * rng.normal() * 10e-6
        s, _, _ = similarity_fit(X + e, X, with_scale=True)
        draws.append(1.0 / s - 1.0)
    assert sig == pytest.approx(np.std(draws), rel=0.06)
    assert cert == pytest.approx(5e-6, rel=1e-9)
