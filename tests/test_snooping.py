"""Data snooping that scales (calibration.bundle.snooping): many rejections per round, re-tests, honesty."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.bundle import BundleConfig, BundleOptions, ScaleBar, bundle_adjust, simulate_network
from calibration.bundle.colmap import _pycolmap_solve
from calibration.bundle.datum import _datum_stage
from calibration.bundle.normal import _Layout, _linearise, _State
from calibration.bundle.snooping import _statistics, pick_rejections, predicted_test
from calibration.camera import exp_se3


def _blundered(rng, n_targets=300, n_images=12, share=0.05):
    net = simulate_network(rng, n_targets=n_targets, n_images=n_images, sigma_px=0.05)
    uv = net.obs_uv.copy()
    bad = rng.random(len(uv)) < share
    ang = rng.uniform(0, 2 * np.pi, bad.sum())
    uv[bad] += rng.uniform(1.0, 10.0, bad.sum())[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    poses0 = np.array([exp_se3(rng.normal(0, 0.002, 6)) @ T for T in net.cam_from_part])
    return net, uv, bad, poses0, net.points + rng.normal(0, 5e-4, net.points.shape)


def test_batch_snooping_finds_every_blunder_in_few_rounds_and_matches_truth():
    rng = np.random.default_rng(21)
    net, uv, bad, poses0, x0 = _blundered(rng)
    res = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0,
                        BundleOptions(sigma_px=0.05, max_rejections=len(uv)), BundleConfig())
    assert res.snooping["stopped_because"] == "no observation fails"
    assert res.snooping["rounds"] <= 8  # one observation per re-adjustment would take ~bad.sum() rounds
    assert np.array_equal(res.rejected, bad)
    assert abs(res.sigma0_px / 0.05 - 1) < 0.05
    # the same optimum and covariance as the adjustment of the clean observations alone
    keep = ~bad
    ref = bundle_adjust(net.obs_image[keep], net.obs_target[keep], uv[keep], net.intrinsics, poses0, x0,
                        BundleOptions(sigma_px=0.05, snooping=False), BundleConfig())
    assert res.converged and np.max(np.abs(res.points - ref.points)) < 1e-9
    np.testing.assert_allclose(res.cov, ref.cov, rtol=1e-6, atol=0)
    # coordinates agree with the truth within their stated uncertainty (free network: after a similarity)
    from calibration.alignment import similarity_fit

    s, R, t = similarity_fit(res.points, net.points, with_scale=True)
    err = s * res.points @ R.T + t - net.points
    z = np.linalg.norm(err, axis=1) / res.sigma_m()
    assert np.percentile(z, 95) < 3.5


def test_cap_is_said_not_silent():
    rng = np.random.default_rng(22)
    net, uv, bad, poses0, x0 = _blundered(rng, n_targets=150, n_images=8)
    res = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0,
                        BundleOptions(sigma_px=0.05, max_rejections=5), BundleConfig())
    assert res.rejected.sum() == 5
    assert res.snooping["stopped_because"] == "max_rejections reached"
    assert res.snooping["still_failing"] > 0


def test_predicted_test_of_a_left_out_observation_equals_its_statistic_inside():
    """Baarda's equivalence: the statistic of an observation in the adjustment that includes it equals that of its
    predicted residual from the adjustment without it (linear model; here to the linearisation error)."""
    rng = np.random.default_rng(23)
    net = simulate_network(rng, n_targets=60, n_images=6, sigma_px=0.05)
    uv = net.obs_uv.copy()
    i = 17
    uv[i] += [0.3, -0.2]  # a small blunder, so the statistic is well above noise
    config = BundleConfig(scale_bars=(ScaleBar(0, 1, float(np.linalg.norm(net.points[0] - net.points[1])), 1e-6),))
    opts = BundleOptions(sigma_px=0.05, snooping=False)
    n, m = len(net.points), len(net.cam_from_part)
    linked = np.zeros(n, bool)
    linked[[0, 1]] = True

    def adjust(keep):
        args = (net.obs_image[keep], net.obs_target[keep], uv[keep])
        lay = _Layout(m, n, (), np.ones(n, bool), linked)
        st = _State(net.intrinsics, net.cam_from_part.copy(), net.points.copy())
        st, *_ = _pycolmap_solve(st, *args, np.ones(n, bool), config, opts)
        st, _ = _datum_stage(st, net.points, lay, config, args, 0.05, 20, True)
        lin = _linearise(st, *args, lay, config, 0.05, 6)
        return st, lin, lay, _statistics(lin, lay, int(keep.sum()))

    keep = np.ones(len(uv), bool)
    _, _, _, full = adjust(keep)
    keep[i] = False
    st, lin, lay, stats = adjust(keep)
    Tp = predicted_test(st, lin, lay, stats, net.obs_image[[i]], net.obs_target[[i]], uv[[i]], np.array([0.05]))
    assert full["T"][i] > 20
    assert abs(Tp[0] / full["T"][i] - 1) < 1e-3


def test_pick_rejections_takes_one_per_target_and_a_share_per_image():
    T = np.array([50.0, 40.0, 60.0, 1.0, 45.0, np.nan])
    img = np.array([0, 1, 1, 0, 0, 1])
    tgt = np.array([0, 0, 1, 1, 2, 2])
    got = pick_rejections(T, 30.0, img, tgt, budget=10, image_share=1.0)
    assert list(got) == [2, 0, 4]  # target 0 only its largest (50 > 40), largest first
    assert list(pick_rejections(T, 30.0, img, tgt, budget=2, image_share=1.0)) == [2, 0]
    # a tenth of an image's (3 active) observations: one per image
    assert list(pick_rejections(T, 30.0, img, tgt, budget=10)) == [2, 0]


def test_two_blunders_of_one_target_go_in_one_round():
    rng = np.random.default_rng(24)
    net = simulate_network(rng, n_targets=120, n_images=8, sigma_px=0.05)
    uv = net.obs_uv.copy()
    bad = np.zeros(len(uv), bool)
    for t in range(0, 100, 10):  # ten targets with two displaced rays each (3 and 4 px)
        obs = np.flatnonzero(net.obs_target == t)[:2]
        uv[obs[0]] += [3.0, 0.0]
        uv[obs[1]] += [0.0, -4.0]
        bad[obs] = True
    poses0 = np.array([exp_se3(rng.normal(0, 0.002, 6)) @ T for T in net.cam_from_part])
    res = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, net.points,
                        BundleOptions(sigma_px=0.05, max_rejections=100), BundleConfig())
    assert np.array_equal(res.rejected, bad)
    # one round rejects all twenty (and a few good rays of the same images, smeared through the poses), the next
    # finds nothing failing and puts the good ones back, the last confirms: one round per blunder of a target
    # would need a fourth
    assert res.snooping["rounds"] <= 3


def test_a_warm_round_that_diverges_is_stopped_said_and_settled_by_pycolmap():
    """A warm round (Gauss-Newton from the previous round's optimum) is watched: here started far from its optimum
    (every camera turned at random by 0.7 rad per axis), its step grows; the round is stopped, said, and pycolmap's
    Levenberg-Marquardt from the round's start settles it at the optimum an adjustment from the truth reaches."""
    from calibration.bundle.adjust import _warm_round

    rng = np.random.default_rng(32)
    net = simulate_network(rng, n_targets=120, n_images=10, sigma_px=0.05)
    n, m = len(net.points), len(net.cam_from_part)
    config = BundleConfig()
    lay = _Layout(m, n, config.refined_names(), np.ones(n, bool), np.zeros(n, bool))
    args = (net.obs_image, net.obs_target, net.obs_uv)
    poses = np.array([exp_se3(np.r_[rng.normal(0, 0.7, 3), rng.normal(0, 0.175, 3)]) @ T for T in net.cam_from_part])
    state = _State(net.intrinsics, poses, net.points + rng.normal(0, 0.02, net.points.shape))
    snoop = {"rounds": 2}
    new, conv = _warm_round(state, net.points, lay, config, args, np.full(len(args[0]), 0.05), np.ones(n, bool),
                            BundleOptions(sigma_px=0.05), snoop)
    assert snoop["diverged"][0].startswith("round 2: Gauss-Newton step grew at iteration")
    assert snoop["handed_over"][0].startswith("round 2: pycolmap settled it")
    ref = bundle_adjust(*args, net.intrinsics, net.cam_from_part, net.points, BundleOptions(sigma_px=0.05,
                        snooping=False), config)
    assert conv and np.max(np.abs(new.points - ref.points)) < 1e-9


def test_a_diverged_round_pycolmap_cannot_settle_keeps_the_last_settled_round_and_says_so(monkeypatch):
    """When neither the warm Gauss-Newton nor pycolmap settles a round (injected: the two solvers are tested above),
    the adjustment is the previous round's, converged, and data snooping is said to have stopped early: not "did not
    converge", and no observation rejected that the kept adjustment did not test."""
    import calibration.bundle.adjust as A

    def diverges(state, x0, lay, config, args, sigma, active_pts, options, snoop):
        snoop.setdefault("diverged", []).append(f"round {snoop['rounds']}: Gauss-Newton cost rose (injected)")
        return None, None

    rng = np.random.default_rng(22)
    net, uv, bad, poses0, x0 = _blundered(rng, n_targets=150, n_images=8)
    monkeypatch.setattr(A, "_warm_round", diverges)
    res = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0,
                        BundleOptions(sigma_px=0.05, max_rejections=len(uv)), BundleConfig())
    monkeypatch.undo()
    ref = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, poses0, x0,
                        BundleOptions(sigma_px=0.05, snooping=False), BundleConfig())
    assert res.converged and not res.rejected.any()
    assert np.max(np.abs(res.points - ref.points)) < 1e-9
    sn = res.snooping
    assert not sn["complete"] and sn["still_failing"] >= bad.sum() // 2
    assert sn["stopped"].startswith("round 2: Gauss-Newton cost rose (injected), and pycolmap did not settle that "
                                    "round either: round 1's adjustment is kept")


def _pairs_network(rng, n_pairs=250, n_targets=400, n_images=10):
    """A network whose first ``n_pairs`` targets are seen by exactly two (adjacent) images: each of their rays has a
    rank-one redundancy block. Returns the network and the true projections of its observations."""
    from calibration.camera import project

    net = simulate_network(rng, n_targets=n_targets, n_images=n_images, sigma_px=0.05)
    keep = np.ones(len(net.obs_image), bool)
    for t in range(n_pairs):
        keep[np.flatnonzero(net.obs_target == t)[2:]] = False
    oi, ot = net.obs_image[keep], net.obs_target[keep]
    true_uv = np.array([project(net.intrinsics, net.cam_from_part[i], net.points[t][None])[0] for i, t in zip(oi, ot)])
    return net, oi, ot, true_uv


def test_a_rank_one_statistic_is_tested_at_its_one_dof_quantile_with_the_false_alarm_rate_alpha():
    """A pair of rays' statistic has one degree of freedom: at the 2-dof quantile its false-alarm rate was 1.4 % where
    alpha said 5 % (less power than stated). Monte Carlo over fresh noise: the bundle's own dof and critical values
    (per-test alpha 5 %) give 5 % for the rank-one and the rank-two statistics alike."""
    from scipy.special import chdtri

    rng = np.random.default_rng(31)
    net, oi, ot, true_uv = _pairs_network(rng)
    q = len(oi)
    a = 0.05
    fa = {1: [0, 0], 2: [0, 0]}
    for _ in range(5):
        uv = true_uv + rng.normal(0, 0.05, true_uv.shape)
        res = bundle_adjust(oi, ot, uv, net.intrinsics, net.cam_from_part, net.points,
                            BundleOptions(sigma_px=0.05, alpha=a * q, max_rejections=0), BundleConfig())
        sn = res.snooping
        assert sn["threshold"] == pytest.approx(chdtri(2, a)) and sn["threshold_1dof"] == pytest.approx(chdtri(1, a))
        crit = np.array([np.nan, sn["threshold_1dof"], sn["threshold"]])
        pair = ot < 250
        assert np.all(res.test_dof[pair] == 1) and np.all(res.test_dof[~pair] == 2)
        fails = res.test_statistic > crit[res.test_dof]
        assert sn["still_failing"] == int(fails.sum())  # the bundle's decisions are these
        assert sn["tested_1dof"] == int(pair.sum())
        first = np.zeros(q, bool)  # both rays of a pair have the same statistic: one per pair
        first[np.unique(ot, return_index=True)[1]] = True
        for dof, sel in ((1, pair & first), (2, ~pair)):
            fa[dof][0] += int(fails[sel].sum())
            fa[dof][1] += int(sel.sum())
    for dof, (k, n) in fa.items():
        rate, se = k / n, np.sqrt(a * (1 - a) / n)
        assert abs(rate - a) < 3.5 * se, (dof, rate, n)  # 1 dof at the 2-dof quantile: 0.014 (6.5 se below)


def test_a_gross_error_on_a_two_ray_target_between_the_1_and_2_dof_quantiles_is_rejected():
    """An error across the epipolar line of a two-ray target whose statistic lies between the 1-dof and the 2-dof
    critical value at the network's alpha: rejected at 1 dof (it was not at 2: the pair kept its error), listed with
    its dof; the rank-two observations keep their 2-dof test (nothing else rejected)."""
    from scipy.special import chdtri

    rng = np.random.default_rng(32)
    net, oi, ot, true_uv = _pairs_network(rng)
    uv = true_uv + rng.normal(0, 0.05, true_uv.shape)
    opts = BundleOptions(sigma_px=0.05)
    clean = bundle_adjust(oi, ot, uv, net.intrinsics, net.cam_from_part, net.points, opts, BundleConfig())
    assert not clean.rejected.any()
    k = int(np.flatnonzero(ot == 7)[0])  # a two-ray target's first ray
    # the rank-one residual lies along e; an error d along e changes the whitened statistic's root by
    # sqrt(lambda) d / sigma (lambda = 2 x the redundancy number)
    r = clean.residuals[k]
    e = r / np.linalg.norm(r)
    lam = 2 * clean.redundancy[k]
    w0 = np.linalg.norm(r) / (0.05 * np.sqrt(lam))
    t1, t2 = chdtri(1, opts.alpha / len(oi)), chdtri(2, opts.alpha / len(oi))
    target = 0.5 * (t1 + t2)  # 27 between 24.9 and 29.7
    d = 0.05 * (np.sqrt(target) - w0) / np.sqrt(lam)
    bad = uv.copy()
    bad[k] += d * e
    res = bundle_adjust(oi, ot, bad, net.intrinsics, net.cam_from_part, net.points, opts, BundleConfig())
    both = np.flatnonzero(ot == 7)
    assert res.rejected[both].sum() == 1 and res.rejected.sum() == 1  # one ray of the pair, nothing else
    assert 7 in res.snooping["suspect_targets"]
    j = int(both[res.rejected[both]][0])
    assert clean.test_dof[k] == 1 and res.test_dof[j] == 1 and t1 < res.rejected_test[j] < t2
    assert res.snooping["threshold_1dof"] == pytest.approx(t1) and res.snooping["threshold"] == pytest.approx(t2)
    assert np.all(clean.test_dof[ot >= 250] == 2)


def test_the_rank_of_a_redundancy_block_decides_the_statistic_and_its_degrees_of_freedom():
    """A regular block keeps ``v^T Q^-1 v`` (2 dof) to the bit; a block whose smaller eigenvalue is below RANK_RTOL of
    the larger gets ``(e . v)^2 / lambda`` along its larger eigenvector (1 dof), no redundancy stays untestable; the
    re-test of a left-out observation (from ``M = I + J Q_xx J^T``) decides and computes as the block it would have
    inside (``M^-1``) with the residual it would have there (``M^-1 v``)."""
    from calibration.bundle.snooping import RANK_RTOL, _predicted_statistic, _quadratic, _test_statistic

    rng = np.random.default_rng(33)

    def blocks(lam):
        a = rng.uniform(0, np.pi, len(lam))
        E = np.stack([np.column_stack([np.cos(a), np.sin(a)]), np.column_stack([-np.sin(a), np.cos(a)])], axis=2)
        return np.einsum("qij,qj,qkj->qik", E, lam, E), E

    v = rng.normal(size=(200, 2))
    lam = np.column_stack([rng.uniform(0.05, 1, 200), rng.uniform(0.05, 1, 200)])
    Q, _ = blocks(lam)
    T, dof = _test_statistic(Q, v)
    assert np.all(dof == 2) and np.array_equal(T, _quadratic(Q, v))
    lam1 = np.column_stack([rng.uniform(0.1, 1, 200), np.zeros(200)])
    lam1[:, 1] = lam1[:, 0] * rng.uniform(0, 0.5 * RANK_RTOL, 200)  # near rank one (det well above 1e-12)
    Q1, E1 = blocks(lam1)
    T1, dof1 = _test_statistic(Q1, v)
    assert np.all(dof1 == 1)
    np.testing.assert_allclose(T1, np.einsum("qi,qi->q", E1[:, :, 0], v) ** 2 / lam1[:, 0], rtol=1e-9)
    Tn, dn = _test_statistic(np.array([[[4e-4, 0.0], [0.0, 0.0]]]), v[:1])  # no redundancy
    assert np.isnan(Tn[0]) and dn[0] == 0
    for Qin in (Q, Q1):  # the predicted statistic: M = Qin^-1, the predicted residual M v_in
        M = np.linalg.inv(Qin)
        Tp, dp = _predicted_statistic(M, v)
        Ti, di = _test_statistic(Qin, np.einsum("qij,qj->qi", Qin, v))
        assert np.array_equal(dp, di)
        np.testing.assert_allclose(Tp, Ti, rtol=1e-6)
