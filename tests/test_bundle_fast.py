"""The bundle's fast paths against reference computations: the Gauss-Newton solve against pycolmap's optimum
(and its hand-over to pycolmap), the batched cofactor kernels against dense matrices, the per-point datum
blocks against the low-rank S-transformation."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calibration.alignment import PointCovariance, similarity_fit
from calibration.bundle import BundleConfig, BundleOptions, ScaleBar, bundle_adjust, simulate_network
from calibration.bundle.covariance import _datum_blocks
from calibration.bundle.normal import _Layout, _linearise, _State
from calibration.bundle.snooping import _statistics
from calibration.camera import exp_se3


def _network(seed=3, n_targets=80, n_images=8, pose_noise=0.002):
    rng = np.random.default_rng(seed)
    net = simulate_network(rng, n_targets=n_targets, n_images=n_images, sigma_px=0.05)
    poses0 = np.array([exp_se3(rng.normal(0, pose_noise, 6)) @ T for T in net.cam_from_part])
    return net, poses0, net.points + rng.normal(0.0, 5e-4, net.points.shape)


def _adjust(net, poses0, x0, config=None, **opts):
    return bundle_adjust(net.obs_image, net.obs_target, net.obs_uv, net.intrinsics, poses0, x0,
                         BundleOptions(sigma_px=0.05, **opts), config or BundleConfig())


@pytest.mark.parametrize("config", [BundleConfig(), BundleConfig(refine_focal_length=True, refine_principal_point=True)],
                         ids=["fixed_interior", "self_calibration"])
def test_gauss_newton_solve_reaches_pycolmaps_optimum(config):
    net, poses0, x0 = _network()
    gn = _adjust(net, poses0, x0, config)
    ref = _adjust(net, poses0, x0, config, solver="pycolmap")
    assert gn.summary.startswith("Gauss-Newton") and "CONVERGENCE" in gn.summary
    assert gn.converged and ref.converged
    # pycolmap stops at Ceres' function tolerance (1e-12 relative cost change), Gauss-Newton at steps of 1e-10 m
    np.testing.assert_allclose(gn.points, ref.points, rtol=0, atol=1e-10)
    np.testing.assert_allclose(gn.cam_from_part, ref.cam_from_part, rtol=0, atol=1e-9)
    np.testing.assert_allclose(gn.cov, ref.cov, rtol=1e-6, atol=1e-6 * np.abs(ref.cov).max())
    assert gn.sigma0_px == pytest.approx(ref.sigma0_px, rel=1e-9)
    np.testing.assert_allclose(gn.redundancy, ref.redundancy, rtol=0, atol=1e-8)
    # and the truth lies within the covariance (the solve is right, not only equal to pycolmap's); the free
    # network's datum is the noisy start, so compare after a similarity fit
    sc, R, t = similarity_fit(gn.points, net.points, with_scale=True)
    err = (sc * gn.points @ R.T + t) - net.points
    z = err / (sc * np.sqrt(np.diagonal(gn.cov, axis1=1, axis2=2)))
    assert np.sqrt(np.mean(z**2)) < 1.5


def test_gauss_newton_hands_an_unconverged_solve_to_pycolmap():
    net, poses0, x0 = _network(seed=4)
    res = _adjust(net, poses0, x0, gn_iterations=1)  # one iteration never meets the 1e-10 m step test
    assert "Ceres" in res.summary and "not converged in 1 iterations" in res.summary
    ref = _adjust(net, poses0, x0)
    np.testing.assert_allclose(res.points, ref.points, rtol=0, atol=1e-10)
    with pytest.raises(Exception, match="unknown solver"):
        _adjust(net, poses0, x0, solver="newton")


def test_a_start_gauss_newton_cannot_take_goes_to_pycolmap_and_reaches_the_same_optimum():
    """Poses 0.3 rad and targets 10 cm off: the undamped steps fail, Levenberg-Marquardt gets there."""
    rng = np.random.default_rng(0)
    net = simulate_network(rng, n_targets=80, n_images=8, sigma_px=0.05)
    far = np.array([exp_se3(rng.normal(0, 0.3, 6)) @ T for T in net.cam_from_part])
    res = _adjust(net, far, net.points + rng.normal(0, 0.1, net.points.shape))
    near = np.array([exp_se3(rng.normal(0, 0.002, 6)) @ T for T in net.cam_from_part])
    x_near = net.points + rng.normal(0, 5e-4, net.points.shape)
    assert "Ceres" in res.summary and "(Gauss-Newton" in res.summary  # the summary says why it handed over
    good = _adjust(net, near, x_near)
    assert res.sigma0_px == pytest.approx(good.sigma0_px, rel=1e-6)


def test_gauss_newton_with_a_scale_bar_keeps_the_bar_and_matches_pycolmap():
    net, poses0, x0 = _network(seed=5)
    L = float(np.linalg.norm(net.points[0] - net.points[1]))
    cfg = BundleConfig(scale_bars=(ScaleBar(0, 1, L, 1e-6),))
    gn, ref = _adjust(net, poses0, x0, cfg), _adjust(net, poses0, x0, cfg, solver="pycolmap")
    assert gn.summary.startswith("Gauss-Newton")
    np.testing.assert_allclose(gn.points, ref.points, rtol=0, atol=1e-10)
    np.testing.assert_allclose(gn.cov, ref.cov, rtol=1e-6, atol=1e-6 * np.abs(ref.cov).max())
    assert np.linalg.norm(gn.points[0] - gn.points[1]) == pytest.approx(L, abs=3e-6)


def test_projected_cofactors_and_point_blocks_equal_the_dense_computation():
    """Redundancy numbers (1 - J Q_xx J^T per observation) and the points' blocks against the dense inverse of
    the full normal matrix (inner constraints by the same regularisation)."""
    net, poses0, x0 = _network(seed=6, n_targets=25, n_images=5)
    m, n = len(poses0), len(x0)
    names = ("fx", "fy", "cx", "cy")
    lay = _Layout(m, n, names, np.ones(n, bool), np.zeros(n, bool))
    state = _State(net.intrinsics, net.cam_from_part, net.points)
    cfg = BundleConfig(refine_focal_length=True, refine_principal_point=True)
    lin = _linearise(state, net.obs_image, net.obs_target, net.obs_uv, lay, cfg, 0.05, 7)
    stats = _statistics(lin, lay, len(net.obs_image))
    # dense Jacobian: points (3n) | camera side (p)
    q, p = len(net.obs_image), lay.p
    J = np.zeros((q, 2, 3 * n + p))
    for o in range(q):
        J[o, :, 3 * lin.slot[o] : 3 * lin.slot[o] + 3] = lin.Jp[o]
        J[o][:, 3 * n + lin.cidx[o, : 6 + lay.k]] = lin.Jc[o, :, : 6 + lay.k]
    Jd = J.reshape(2 * q, -1)
    # the full cofactor matrix from the Schur form: Qpp = D + V Sigma V^T, Qpc = -V Sigma, Qcc = Sigma
    V = lin.V.reshape(3 * n, p)
    D = np.zeros((3 * n, 3 * n))
    for i in range(n):
        D[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = lin.Dinv[i]
    Q = np.block([[D + V @ lin.Sigma @ V.T, -V @ lin.Sigma], [-lin.Sigma @ V.T, lin.Sigma]])
    A = np.einsum("qia,ab,qjb->qij", J, Q, J)
    np.testing.assert_allclose(stats["redundancy"], 1 - 0.5 * np.trace(A, axis1=1, axis2=2), rtol=0, atol=1e-10)
    Qpp = np.array([Q[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] for i in range(n)])
    np.testing.assert_allclose(stats["Qpp"], Qpp, rtol=1e-9, atol=1e-12 * np.abs(Qpp).max())
    # J Q J^T is the hat matrix of the adjustment: its trace is the number of determined parameters
    assert np.trace(Jd @ Q @ Jd.T) == pytest.approx(3 * n + p - 7, abs=1e-6)


def test_datum_blocks_equal_the_low_rank_s_transformation():
    rng = np.random.default_rng(7)
    n, r, d = 40, 12, 7
    Dm = rng.normal(size=(n, 3, 3))
    D = Dm @ np.swapaxes(Dm, 1, 2)
    U = rng.normal(size=(n, 3, r))
    Cm = rng.normal(size=(r, r))
    C = Cm @ Cm.T
    P, _ = np.linalg.qr(rng.normal(size=(3 * n, d)))
    P = P.reshape(n, 3, d)
    pc = PointCovariance(D, U, C)
    ref = pc.s_transform(P, P).blocks()
    got = _datum_blocks(pc.blocks(), D, U, C, P)
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-10 * np.abs(ref).max())
    # and against the dense S Q S^T
    Qd = pc.dense()
    S = np.eye(3 * n) - P.reshape(3 * n, d) @ P.reshape(3 * n, d).T
    QS = S @ Qd @ S.T
    dense_blocks = np.array([QS[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] for i in range(n)])
    np.testing.assert_allclose(got, dense_blocks, rtol=1e-9, atol=1e-10 * np.abs(dense_blocks).max())


def test_fast_projection_matches_finite_differences_with_distortion():
    from calibration.bundle.projection import project_observations, project_pixels

    net, _, _ = _network(seed=8, n_targets=20, n_images=2)
    intr = replace(net.intrinsics, k1=-0.08, k2=0.02, k3=0.01, p1=1e-4, p2=-2e-4)
    o = np.arange(len(net.obs_image))
    R = net.cam_from_part[net.obs_image, :3, :3]
    t = net.cam_from_part[net.obs_image, :3, 3]
    X = net.points[net.obs_target]
    uv, Jp, Jpose, _ = project_observations(intr, R, t, X)
    np.testing.assert_array_equal(project_pixels(intr, R, t, X), uv)
    h = 1e-7
    for a in range(3):
        dX = np.zeros(3)
        dX[a] = h
        num = (project_pixels(intr, R, t, X + dX) - project_pixels(intr, R, t, X - dX)) / (2 * h)
        np.testing.assert_allclose(Jp[o, :, a], num, rtol=1e-5, atol=1e-3)
    for a in range(6):
        xi = np.zeros(6)
        xi[a] = h
        Tp, Tm = exp_se3(xi), exp_se3(-xi)
        up = project_pixels(intr, Tp[:3, :3] @ R, np.einsum("ab,qb->qa", Tp[:3, :3], t) + Tp[:3, 3], X)
        um = project_pixels(intr, Tm[:3, :3] @ R, np.einsum("ab,qb->qa", Tm[:3, :3], t) + Tm[:3, 3], X)
        np.testing.assert_allclose(Jpose[:, :, a], (up - um) / (2 * h), rtol=1e-5, atol=1e-3)
