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
    # sigma_px as simulated, and half of it: the covariance is then scaled by an a posteriori s0^2 of ~4, which the
    # gains must not follow (they are the a priori weights' N^-1 A^T / sigma^2)
    for sigma_px in (0.05, 0.025):
        runs = []
        for L in (length, length + delta):
            cfg = BundleConfig(scale_bars=(ScaleBar(a, b, L, sigma),))
            runs.append(bundle_adjust(net.obs_image, net.obs_target, net.obs_uv, net.intrinsics, poses0, x0,
                                      BundleOptions(sigma_px=sigma_px, max_rejections=0), cfg))
        K, sig = scale_bar_gains(runs[0].covariance, runs[0].points, (ScaleBar(a, b, length, sigma),),
                                 runs[0].variance_factor)
        moved = (runs[1].points - runs[0].points) / delta
        assert sig[0] == sigma
        np.testing.assert_allclose(K[:, :, 0], moved, atol=0.02 * np.abs(moved).max())
        assert np.abs(moved).max() > 0.1  # the far targets move a good share of the bar's change
    assert runs[0].variance_factor > 3.0  # the second case did scale the covariance


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


def _drawn_errors(rng, rho, n_targets=200, n_views=6, c=0.27):
    """Errors drawn from the shared-misfit model: ``e_i = sqrt(rho) S_i Jh_i z_t + sqrt(1 - rho) S_i w_i + noise``
    for ``n_targets`` targets seen in ``n_views`` views each (some without a bound); the rows share_pairs takes."""
    from calibration.bundle.coherent import unit_projection

    rows = {"e": [], "bound": [], "Jh": [], "target": [], "view": [], "cov": []}
    for t in range(n_targets):
        poses = _views(rng, n_views, spread_deg=35.0)
        X = np.zeros((n_views, 3))
        Jh, _ = unit_projection(poses, X)
        B = np.array([np.diag(rng.uniform(0.02, 0.25, 2) ** 2) for _ in range(n_views)])
        B[rng.uniform(size=n_views) < 0.2] = 0.0  # views where the dot's surroundings are a plane
        S = np.sqrt(c * c * B)  # diagonal bounds
        z = rng.normal(size=3)
        e = (np.sqrt(rho) * np.einsum("qab,qbc,c->qa", S, Jh, z)
             + np.sqrt(1 - rho) * np.einsum("qab,qb->qa", S, rng.normal(size=(n_views, 2)))
             + rng.normal(0, 0.006, (n_views, 2)))
        for key, v in (("e", e), ("bound", c * c * B), ("Jh", Jh), ("target", np.full(n_views, t)),
                       ("view", np.arange(n_views)), ("cov", 0.006**2 * np.eye(2) + c * c * B)):
            rows[key].append(v)
    return {k: np.concatenate(v) for k, v in rows.items()}


@pytest.mark.parametrize("rho", [0.4, 1.0])
def test_the_shared_share_is_recovered_from_errors_drawn_from_the_model(rho):
    """benchmarks/background_share.py's estimator (least squares over pairs of distinct views, bootstrap over
    targets) on errors drawn with a known share."""
    from calibration.bundle.coherent import fit_share, share_pairs

    r = _drawn_errors(np.random.default_rng(int(rho * 10)), rho, n_targets=300)
    for cov in (None, r["cov"]):  # plain least squares, and whitened by the bundle's weights (the benchmark's)
        p = share_pairs(r["e"], r["bound"], r["Jh"], r["target"], r["view"], obs_cov=cov)
        assert not np.any(p["same_view"]) and len(p["num"]) > 1000
        est, sig = fit_share(p["num"], p["den"], p["target"])
        assert 0.02 < sig < 0.15, sig  # a measurement, not an exact echo
        assert abs(est - rho) < 3 * sig, (est, sig)
    with pytest.raises(ValueError, match="at least 20"):  # too few targets is said, not estimated
        fit_share(p["num"][:30], p["den"][:30], p["target"][:30])


def test_adjust_adds_the_shared_misfit_scaled_by_the_measured_share(monkeypatch):
    """ADJUST's added covariance (per target and the scale bar ends' rank-one term) is proportional to the detector
    model's rho_background; a model without it takes one and says so in bundle.json."""
    from types import SimpleNamespace

    import cell.stages.adjust as adjust
    import cell.stages.shared_terms as shared_terms
    from calibration.alignment import PointCovariance
    from calibration.bundle import ScaleBar
    from calibration.detector_model import DetectorModel

    rng = np.random.default_rng(5)
    poses = _views(rng, 8)
    n = 3
    X = np.array([[0.0, 0.0, 0.0], [0.05, 0.01, 0.0], [-0.04, 0.03, 0.0]])
    img = np.tile(np.arange(8), n)
    tgt = np.repeat(np.arange(n), 8)
    bg = np.array([np.diag(rng.uniform(0.05, 0.2, 2) ** 2) for _ in img])
    K = rng.normal(0, 0.3, (n, 3, 1))
    bars = (ScaleBar(1, 2, float(np.linalg.norm(X[1] - X[2])), 2e-6),)
    added = {}
    for rho in (None, 0.4, 1.0):
        model = DetectorModel(0.004, 0.003, 1.5, 2.4, "4", 0.27, rho_background=rho)
        monkeypatch.setattr(shared_terms, "load_model", lambda m=model: m)
        cov0 = np.array([np.eye(3) * 1e-12] * n)
        res = SimpleNamespace(intrinsics=INTR, cam_from_part=poses, points=X.copy(), rejected=np.zeros(len(img), bool),
                              obs_sigma_px=np.full(len(img), 0.006), cov=cov0.copy(),
                              covariance=PointCovariance(cov0.copy(), np.zeros((n, 3, 0)), np.zeros((0, 0))))
        doc = adjust._add_coherent_background(res, bg, img, tgt, ["T1", "T2", "T3"], bars, K)
        assert doc["share"] == (1.0 if rho is None else rho) and doc["share_measured"] == (rho is not None)
        assert doc["n_targets"] == n and len(doc["scale_bar_ends"]) == 1
        added[rho] = (res.cov - cov0, doc["scale_bar_ends"][0]["length_sigma_m"] ** 2)
    assert np.trace(added[1.0][0][0]) > 0
    np.testing.assert_allclose(added[None][0], added[1.0][0], rtol=1e-12, atol=0)
    np.testing.assert_allclose(added[0.4][0], 0.4 * added[1.0][0], rtol=1e-9, atol=1e-30)
    np.testing.assert_allclose(added[0.4][1], 0.4 * added[1.0][1], rtol=1e-9)


def test_the_detector_model_carries_the_share_and_an_older_file_takes_one(tmp_path):
    import json

    from calibration.detector_model import DATA_PATH, load_model
    from calibration.errors import CalibrationError

    doc = json.loads(DATA_PATH.read_text())
    assert load_model().shared_share == doc["rho_background"]  # the applied share is the file's, not a default
    old = {k: v for k, v in doc.items() if not k.startswith("rho_background")} | {"version": "3"}
    (tmp_path / "old.json").write_text(json.dumps(old))
    m = load_model(str(tmp_path / "old.json"))
    assert m.rho_background is None and m.shared_share == 1.0 and "1 (not measured)" in m.describe()
    (tmp_path / "bad.json").write_text(json.dumps(doc | {"rho_background": 1.4}))
    with pytest.raises(CalibrationError, match="rho_background must be in"):
        load_model(str(tmp_path / "bad.json"))


def test_the_report_names_the_targets_left_out_of_the_datum():
    from cell.record.report import _budget_facts

    facts = _budget_facts({"uncertainty_budget": {"datum_left_out": ["T0035", "T0111"]}})
    assert facts["Left out of the bundle's datum"] == ("2 target(s) determined >10x worse than the median: "
                                                       "T0035, T0111")
    assert "Left out of the bundle's datum" not in _budget_facts({"uncertainty_budget": {"datum_left_out": []}})


def test_one_function_appends_columns_to_the_low_rank_covariance_for_adjust_and_report(monkeypatch):
    """ADJUST (the scale bar ends' shared misfit: a column of weight v) and REPORT (the bars' gains: columns of weight
    zero that ride along the alignment) append columns to the covariance's low-rank factor with one function; the
    covariance is the one each built before (a target not adjusted keeps NaN rows)."""
    from types import SimpleNamespace

    import cell.stages.adjust as adjust
    import cell.stages.shared_terms as shared_terms
    from calibration.alignment import PointCovariance
    from calibration.bundle import ScaleBar
    from calibration.bundle.covariance import append_columns
    from calibration.detector_model import DetectorModel

    def before(cv, k, weights):  # the two copies' construction, written out
        r, b = cv.U.shape[2], k.shape[2]
        C = np.zeros((r + b, r + b))
        C[:r, :r] = cv.C
        C[r:, r:] = np.diag(weights)
        return cv.D, np.concatenate([cv.U, np.where(np.isnan(cv.D[:, :, :1]), np.nan, k)], axis=2), C

    rng = np.random.default_rng(8)
    n = 4
    D = np.array([np.diag(rng.uniform(1, 2, 3)) * 1e-12 for _ in range(n)])
    U = rng.normal(0, 1e-6, (n, 3, 2))
    D[3], U[3] = np.nan, np.nan  # a target the adjustment did not determine
    pc = PointCovariance(D, U, np.array([[2.0, 0.3], [0.3, 1.0]]))
    K = rng.normal(0, 0.3, (n, 3, 2))
    K[3] = np.nan
    got = append_columns(pc, K, np.zeros(2))  # REPORT's
    for a, b in zip((got.D, got.U, got.C), before(pc, K, np.zeros(2))):
        np.testing.assert_array_equal(a, b)
    # ADJUST's, through _add_coherent_background
    poses = _views(rng, 8)
    X = np.array([[0.0, 0.0, 0.0], [0.05, 0.01, 0.0], [-0.04, 0.03, 0.0], [np.nan] * 3])
    img = np.tile(np.arange(8), 3)
    tgt = np.repeat(np.arange(3), 8)
    bg = np.array([np.diag(rng.uniform(0.05, 0.2, 2) ** 2) for _ in img])
    bars = (ScaleBar(1, 2, float(np.linalg.norm(X[1] - X[2])), 2e-6),)
    model = DetectorModel(0.004, 0.003, 1.5, 2.4, "4", 0.27, rho_background=0.6)
    monkeypatch.setattr(shared_terms, "load_model", lambda: model)
    D_added = pc.D + coherent_background_cov(INTR, poses, X, img, tgt, np.full(len(img), 0.006), bg, 0.27, 0.6)
    res = SimpleNamespace(intrinsics=INTR, cam_from_part=poses, points=X, rejected=np.zeros(len(img), bool),
                          obs_sigma_px=np.full(len(img), 0.006), cov=pc.blocks(),
                          covariance=PointCovariance(pc.D.copy(), pc.U, pc.C))
    doc = adjust._add_coherent_background(res, bg, img, tgt, ["T1", "T2", "T3", "T4"], bars, K[:, :, :1])
    v = doc["scale_bar_ends"][0]["length_sigma_m"] ** 2
    assert v > 0 and doc["n_targets"] == 3
    want = before(PointCovariance(D_added, pc.U, pc.C), np.nan_to_num(K[:, :, :1]), [v])
    np.testing.assert_array_equal(res.covariance.D, want[0])
    np.testing.assert_array_equal(res.covariance.U, want[1])
    np.testing.assert_allclose(res.covariance.C, want[2], rtol=1e-14, atol=0)  # v read back through a sqrt


def test_the_certificate_keeps_its_stated_sigma_when_the_covariance_is_scaled_by_s0():
    """An a posteriori covariance scales the images' part by s0^2 and must leave the bar's certificate as certified:
    corrected, it equals the a priori covariance of the same adjustment weighted at the sigma the residuals found
    (images at sigma_px * s0, the bar at its certificate), block by block and in the low-rank form."""
    from calibration.bundle import BundleConfig, BundleOptions, ScaleBar, bundle_adjust, simulate_network
    from calibration.bundle.coherent import certificate_at_face_value, scale_bar_gains
    from calibration.camera import exp_se3

    rng = np.random.default_rng(5)
    net = simulate_network(rng, n_targets=80, n_images=10, sigma_px=0.05)
    poses0 = np.array([exp_se3(rng.normal(0, 0.002, 6)) @ T for T in net.cam_from_part])
    x0 = net.points + rng.normal(0.0, 5e-4, net.points.shape)
    a, b = int(np.argmin(net.points[:, 0])), int(np.argmax(net.points[:, 0]))
    bar = ScaleBar(a, b, float(np.linalg.norm(net.points[a] - net.points[b])), 20e-6)
    cfg = BundleConfig(scale_bars=(bar,))
    post = bundle_adjust(net.obs_image, net.obs_target, net.obs_uv, net.intrinsics, poses0, x0,
                         BundleOptions(sigma_px=0.025, max_rejections=0), cfg)
    vf = post.variance_factor
    assert vf > 3.0  # the images were weighted at half their noise
    prior = bundle_adjust(net.obs_image, net.obs_target, net.obs_uv, net.intrinsics, poses0, x0,
                          BundleOptions(sigma_px=0.025 * np.sqrt(vf), max_rejections=0, a_posteriori=False), cfg)
    K, sig = scale_bar_gains(post.covariance, post.points, (bar,), vf)
    blocks, pc = certificate_at_face_value(post.cov, post.covariance, K, sig, vf)
    ok = np.isfinite(post.cov).all(axis=(1, 2))
    np.testing.assert_allclose(blocks[ok], prior.cov[ok], rtol=2e-3, atol=1e-4 * np.abs(prior.cov[ok]).max())
    # the bar's direction, through the whole covariance: the variance of the scale of a similarity fit
    g = net.points[ok] - net.points[ok].mean(axis=0)
    g /= np.sum(g * g)

    def var(q):
        U = np.einsum("nar,na->r", np.nan_to_num(q.U[ok]), g)
        return float(np.einsum("na,nab,nb->", g, np.nan_to_num(q.D[ok]), g) + U @ q.C @ U)

    assert var(pc) == pytest.approx(var(prior.covariance), rel=2e-3)
    assert var(post.covariance) > 1.5 * var(pc)  # uncorrected, the certificate was stated ~vf times too large


def test_a_small_share_of_every_error_common_to_many_views_is_stated_monte_carlo():
    """decision 0043: each view errs by its own noise plus a share rho of its whole variance that all views of the
    target have in common (``e_i = sqrt(rho) S_i Jh_i z + sqrt(1 - rho) S_i n_i``, ``S_i^2`` the observation's
    covariance). With 40 views and rho 0.02 the weighted intersection is ~1.3x optimistic; the cross terms with the
    observations' own covariance as the bound (c = 1, share rho) make it honest."""
    rng = np.random.default_rng(12)
    m, rho = 40, 0.02
    poses = _views(rng, m, spread_deg=35.0)
    X = np.array([[0.0005, 0.001, 0.0]])
    sig = rng.uniform(0.006, 0.012, m)
    C = sig[:, None, None] ** 2 * np.eye(2)
    W = np.linalg.inv(C)
    J = np.array([_jacobian(T, X[0]) for T in poses])
    N = np.einsum("qba,qbc,qcd->ad", J, W, J)
    indep = np.linalg.inv(N)
    E = coherent_background_cov(INTR, poses, X, np.arange(m), np.zeros(m, dtype=int), C, C, 1.0, rho)[0]
    Xc = np.einsum("qab,b->qa", poses[:, :3, :3], X[0]) + poses[:, :3, 3]
    Jh = J * (Xc[:, 2] / INTR.fx_px)[:, None, None]
    trials = 4000
    z = rng.normal(size=(trials, 3))
    d = (np.sqrt(rho) * np.einsum("q,qbc,tc->tqb", sig, Jh, z)
         + np.sqrt(1 - rho) * rng.normal(size=(trials, m, 2)) * sig[None, :, None])
    err = np.einsum("ab,qcb,qcd,tqd->ta", indep, J, W, d)
    with_ = np.sqrt(np.einsum("ta,ab,tb->t", err, np.linalg.inv(indep + E), err).mean() / 3)
    without = np.sqrt(np.einsum("ta,ab,tb->t", err, N, err).mean() / 3)
    assert 0.9 <= with_ <= 1.1, with_
    assert without > 1.2, without


def test_the_model_file_gives_the_common_share_of_every_error_and_refuses_one_out_of_range(tmp_path):
    """detector_precision.json ``rho_all`` (decision 0043): read, round-tripped, said in the report's facts; outside
    [0, 1] the model is refused with the file named."""
    import json

    from calibration.detector_model import DATA_PATH, load_model
    from calibration.errors import CalibrationError
    from cell.record.report import _budget_facts

    doc = json.loads(DATA_PATH.read_text())
    for value, ok in ((0.004, True), (1.5, False)):
        p = tmp_path / f"m{value}.json"
        p.write_text(json.dumps(doc | {"rho_all": value}))
        if ok:
            m = load_model(str(p))
            assert m.rho_all == 0.004 and m.to_dict()["rho_all"] == 0.004 and "0.004 of every observation" in m.describe()
        else:
            with pytest.raises(CalibrationError, match="rho_all"):
                load_model(str(p))
    facts = _budget_facts({"uncertainty_budget": {"shared_floor": {"rho_all": 0.0033, "n_targets": 120,
                                                                    "sigma_growth_median": 1.03}}})
    assert "0.0033 of every dot's error" in facts["Stated beyond the detector model"]
