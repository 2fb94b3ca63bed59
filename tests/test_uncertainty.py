"""Limiting error propagation: the predicted covariance against finite differences and Monte Carlo."""
import numpy as np
import pytest

from calibration.camera import Intrinsics, invert, look_at, project, project_with_jacobians
from calibration.errors import PlanningError
from planning.uncertainty import (
    CRITERIA,
    covariance_for_network,
    criterion,
    eigvalsh_6,
    ellipsoid_axes,
    evaluate_networks,
    sym_from_6,
    target_information,
)

INTR = Intrinsics(fx_px=3500.0, fy_px=3480.0, cx_px=1230.0, cy_px=1010.0, width=2448, height=2048,
                  k1=-0.08, k2=0.02, p1=3e-4, p2=-2e-4)
SIGMA_PX = 0.3


def ring(n: int, distance: float, elevation_deg: float, az0_deg: float = 0.0, span_deg: float = 360.0):
    """``n`` cameras looking at the origin, azimuths over ``span_deg``; (n, 4, 4) part_from_cam."""
    az = np.deg2rad(az0_deg + (np.arange(n) * span_deg / n if span_deg >= 360 else np.linspace(0, span_deg, n)))
    el = np.deg2rad(elevation_deg)
    eyes = distance * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full_like(az, np.sin(el))], 1)
    return np.stack([look_at(e, np.zeros(3)) for e in eyes])


NETWORKS = {
    "weak pair": ring(2, 0.8, 40.0, span_deg=6.0),  # 6 deg convergence
    "convergent pair": ring(2, 0.8, 30.0, span_deg=90.0),
    "8 stations": ring(8, 0.8, 45.0),
}
POINTS = np.array([[0.0, 0.0, 0.0], [0.03, -0.02, 0.01], [-0.04, 0.03, -0.02]])


def fd_point_jacobian(T, X, h=1e-7):
    J = np.zeros((2, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        J[:, k] = (project(INTR, invert(T), (X + d)[None])[0] - project(INTR, invert(T), (X - d)[None])[0]) / (2 * h)
    return J


@pytest.mark.parametrize("name", list(NETWORKS))
def test_covariance_equals_inverse_normal_matrix_from_finite_differences(name):
    T = NETWORKS[name]
    vis = np.ones((len(T), len(POINTS)), dtype=bool)
    cov, n_rays = covariance_for_network(INTR, T, POINTS, vis, SIGMA_PX)
    np.testing.assert_array_equal(n_rays, len(T))
    for j, X in enumerate(POINTS):
        N = sum(fd_point_jacobian(Ti, X).T @ fd_point_jacobian(Ti, X) for Ti in T) / SIGMA_PX**2
        np.testing.assert_allclose(cov[j], np.linalg.inv(N), rtol=1e-5, atol=1e-6 * np.abs(cov[j]).max())


def triangulate(T, uv_obs, X0, iterations=6):
    """Gauss-Newton on reprojection error, vectorised over trials. ``uv_obs: (k, trials, 2)``; (trials, 3)."""
    X = np.repeat(X0[None], uv_obs.shape[1], axis=0)
    cam_from_part = invert(T)
    for _ in range(iterations):
        H = np.zeros((len(X), 3, 3))
        g = np.zeros((len(X), 3))
        for i in range(len(T)):
            uv, J, _ = project_with_jacobians(INTR, cam_from_part[i], X)
            r = uv_obs[i] - uv
            H += np.einsum("tri,trj->tij", J, J)
            g += np.einsum("tri,tr->ti", J, r)
        X = X + np.linalg.solve(H, g[..., None])[..., 0]
    return X


@pytest.mark.parametrize("name", list(NETWORKS))
def test_monte_carlo_triangulation_matches_predicted_covariance(name):
    T = NETWORKS[name]
    rng = np.random.default_rng(list(NETWORKS).index(name))
    trials = 4000
    vis = np.ones((len(T), len(POINTS)), dtype=bool)
    cov, _ = covariance_for_network(INTR, T, POINTS, vis, SIGMA_PX)
    for j, X in enumerate(POINTS):
        clean = np.stack([project(INTR, invert(Ti), X[None])[0] for Ti in T])  # (k, 2)
        uv_obs = clean[:, None, :] + rng.normal(scale=SIGMA_PX, size=(len(T), trials, 2))
        est = triangulate(T, uv_obs, X)
        emp = np.cov(est.T)
        # variance along each predicted principal axis, and the whole whitened matrix
        axes, dirs = ellipsoid_axes(cov[j])
        emp_axes = np.sqrt(np.einsum("ij,ik,kj->j", dirs, emp, dirs))
        np.testing.assert_allclose(emp_axes, axes, rtol=0.10)
        L = np.linalg.cholesky(np.linalg.inv(cov[j]))
        W = L.T @ emp @ L
        assert np.abs(W - np.eye(3)).max() < 0.10
        assert np.linalg.norm(est.mean(0) - X) < 4 * np.sqrt(np.trace(cov[j]) / trials) + 1e-9


def test_weak_pair_is_much_worse_in_depth_than_convergent_pair():
    vis = np.ones((2, 1), dtype=bool)
    weak, _ = covariance_for_network(INTR, NETWORKS["weak pair"], POINTS[:1], vis, SIGMA_PX)
    strong, _ = covariance_for_network(INTR, NETWORKS["convergent pair"], POINTS[:1], vis, SIGMA_PX)
    aw, _ = ellipsoid_axes(weak)
    as_, _ = ellipsoid_axes(strong)
    assert aw[0, 0] / aw[0, 2] > 10 and as_[0, 0] / as_[0, 2] < 3
    assert aw[0, 0] > 5 * as_[0, 0]


def candidate_scene(seed=0, m=60, n=40):
    rng = np.random.default_rng(seed)
    T = np.concatenate([ring(m // 3, d, el, az0_deg=rng.uniform(0, 30)) for d, el in ((0.7, 20), (0.8, 45), (0.9, 70))])
    xyz = rng.uniform(-0.05, 0.05, (n, 3))
    vis = rng.random((len(T), n)) < 0.6
    return T, xyz, vis


def test_population_evaluation_equals_exact_per_network_covariance():
    T, xyz, vis = candidate_scene()
    rng = np.random.default_rng(1)
    stations = np.stack([rng.choice(len(T), 6, replace=False) for _ in range(25)])
    stations[::4, 2] = -1  # some cameras switched off
    info64 = target_information(INTR, T, xyz, vis, SIGMA_PX, dtype=np.float64)
    info32 = target_information(INTR, T, xyz, vis, SIGMA_PX)
    ev64 = evaluate_networks(info64, stations, min_rays=2, workers=2, chunk=4)
    ev32 = evaluate_networks(info32, stations, min_rays=2, visible=vis)
    for p, st in enumerate(stations):
        on = st[st >= 0]
        cov, n_rays = covariance_for_network(INTR, T[on], xyz, vis[on], SIGMA_PX)
        np.testing.assert_array_equal(ev64.n_rays[p], n_rays)
        np.testing.assert_array_equal(ev64.sufficient[p], n_rays >= 2)
        ok = n_rays >= 2
        np.testing.assert_allclose(ev64.cov[p][ok], cov[ok], rtol=1e-8, atol=1e-12 * np.nanmax(np.abs(cov)))
        np.testing.assert_allclose(ev32.sigma[p][ok], np.sqrt(np.trace(cov[ok], axis1=1, axis2=2)), rtol=1e-3)
        assert np.all(np.isinf(ev64.sigma[p][~ok])) and np.all(np.isnan(ev64.cov6[p][~ok]))


def test_insufficient_data_makes_the_criterion_infinite_or_penalised():
    T = NETWORKS["8 stations"]
    xyz = POINTS
    vis = np.ones((8, 3), dtype=bool)
    vis[1:, 2] = False  # target 2 seen by station 0 only
    info = target_information(INTR, T, xyz, vis, SIGMA_PX)
    ev = evaluate_networks(info, np.arange(8)[None], min_rays=2)
    np.testing.assert_array_equal(ev.n_rays[0], [8, 8, 1])
    np.testing.assert_array_equal(ev.n_insufficient, [1])
    assert np.isinf(criterion(ev, "worst"))[0]
    value = criterion(ev, "worst", penalty=1.0)[0]
    assert value == pytest.approx(ev.sigma[0, :2].max() + 1.0)
    ev3 = evaluate_networks(info, np.arange(8)[None], min_rays=9)
    assert ev3.n_insufficient[0] == 3 and np.isinf(criterion(ev3, "mean")[0])


def test_criteria_follow_their_definitions():
    T, xyz, vis = candidate_scene(seed=2)
    vis[:] = True
    info = target_information(INTR, T, xyz, vis, SIGMA_PX, dtype=np.float64)
    stations = np.random.default_rng(3).integers(0, len(T), (10, 5))
    ev = evaluate_networks(info, stations)
    cov = ev.cov
    tr = np.trace(cov, axis1=2, axis2=3)
    big = np.sqrt(np.linalg.eigvalsh(cov)[..., -1])
    np.testing.assert_allclose(criterion(ev, "worst"), np.sqrt(tr).max(1), rtol=1e-10)
    np.testing.assert_allclose(criterion(ev, "mean"), np.sqrt(tr).mean(1), rtol=1e-10)
    np.testing.assert_allclose(criterion(ev, "trace"), tr.mean(1), rtol=1e-10)
    np.testing.assert_allclose(criterion(ev, "max_axis"), big.max(1), rtol=1e-6)
    assert set(CRITERIA) == {"worst", "mean", "max_axis", "trace"}
    with pytest.raises(PlanningError, match="criterion"):
        criterion(ev, "best")


def test_a_candidate_listed_twice_counts_once():
    T, xyz, vis = candidate_scene(seed=4)
    info = target_information(INTR, T, xyz, vis, SIGMA_PX, dtype=np.float64)
    a = evaluate_networks(info, np.array([[3, 7, 11, 30]]))
    b = evaluate_networks(info, np.array([[3, 7, 11, 30, 7, 7, -1]]))
    np.testing.assert_array_equal(a.n_rays, b.n_rays)
    np.testing.assert_allclose(a.sigma, b.sigma)
    c = evaluate_networks(info, np.array([[3, 7, 11, 30, 7]]), count_duplicates=True)
    assert np.all(c.n_rays >= a.n_rays) and np.any(c.n_rays > a.n_rays)


def test_closed_form_eigenvalues_and_ellipsoid_axes():
    rng = np.random.default_rng(6)
    A = rng.normal(size=(500, 3, 3))
    S = A @ np.swapaxes(A, 1, 2) + 1e-3 * np.eye(3)
    s6 = S[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    np.testing.assert_allclose(sym_from_6(s6), S)
    np.testing.assert_allclose(eigvalsh_6(s6), np.linalg.eigvalsh(S)[:, ::-1], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(eigvalsh_6(np.array([2.0, 0, 0, 2.0, 0, 2.0])), [2.0, 2.0, 2.0])
    axes, dirs = ellipsoid_axes(np.diag([1e-8, 9e-8, 4e-8]))
    np.testing.assert_allclose(axes, [3e-4, 2e-4, 1e-4])
    np.testing.assert_allclose(np.abs(dirs), np.eye(3)[:, [1, 2, 0]], atol=1e-12)
    axes, _ = ellipsoid_axes(np.full((2, 3, 3), np.nan))
    assert np.all(np.isnan(axes))


def test_bad_inputs_raise_planning_error():
    T, xyz, vis = candidate_scene()
    info = target_information(INTR, T, xyz, vis, SIGMA_PX)
    with pytest.raises(PlanningError, match="out of range"):
        evaluate_networks(info, np.array([[0, len(T)]]))
    with pytest.raises(PlanningError, match="min_rays"):
        evaluate_networks(info, np.array([[0, 1]]), min_rays=1)
    with pytest.raises(PlanningError, match="visible"):
        target_information(INTR, T, xyz, vis[:, :3], SIGMA_PX)
    with pytest.raises(PlanningError, match="sigma"):
        target_information(INTR, T, xyz, vis, 0.0)


def test_sparse_information_gives_the_dense_results_exactly():
    """Issue 21: the planner keeps large information sparse; every selection, evaluation, exchange
    refine and bound on it equals the dense array's, bit for bit."""
    from planning.bound import worst_sigma_lower_bound
    from planning.refine import refine_network
    from planning.sparse_info import SparseInfo, add_rows

    T, xyz, vis = candidate_scene(seed=3, m=60, n=50)
    vis[7] = False  # a candidate that sees nothing
    dense = target_information(INTR, T, xyz, vis, SIGMA_PX)
    sp = target_information(INTR, T, xyz, vis, SIGMA_PX, sparse=True)
    assert isinstance(sp, SparseInfo) and sp.shape == dense.shape and sp.dtype == dense.dtype
    assert len(sp.indices) == vis.sum() and sp.nbytes < dense.nbytes
    np.testing.assert_array_equal(sp.toarray(), dense)
    np.testing.assert_array_equal(SparseInfo.from_dense(dense, vis).toarray(), dense)
    rows, cols = np.array([5, 7, 0, 59, 5]), np.array([49, 3, 0, 17])
    np.testing.assert_array_equal(sp[rows], dense[rows])
    np.testing.assert_array_equal(sp[12], dense[12])
    np.testing.assert_array_equal(sp[np.ix_(rows, cols)], dense[np.ix_(rows, cols)])
    np.testing.assert_array_equal(sp[3, cols], dense[3, cols])
    np.testing.assert_array_equal(sp[:, cols, 3], dense[:, cols, 3])
    np.testing.assert_array_equal(sp[:, np.array([4, 4, 1])], dense[:, [4, 4, 1]])
    w = np.linspace(0.5, 2.0, 50).astype(np.float32)
    np.testing.assert_array_equal(sp.scale_targets(w).toarray(), dense * w[None, :, None])
    acc_d, acc_s = np.ones((3, 50, 6), np.float32), np.ones((3, 50, 6), np.float32)
    add_rows(dense, acc_d, np.array([0, 2]), np.array([7, 9]))
    add_rows(sp, acc_s, np.array([0, 2]), np.array([7, 9]))
    np.testing.assert_array_equal(acc_s, acc_d)
    with pytest.raises(TypeError):
        np.asarray(sp)
    with pytest.raises(PlanningError, match="visible"):
        evaluate_networks(sp, np.array([[1, 2, 3]]))

    rng = np.random.default_rng(4)
    stations = np.stack([rng.choice(len(T), 6, replace=False) for _ in range(20)])
    stations[::3, 1] = -1
    ev_d = evaluate_networks(dense, stations, visible=vis, chunk=4)
    ev_s = evaluate_networks(sp, stations, visible=vis, chunk=4)
    for f in ("cov6", "sigma", "n_rays", "sufficient"):
        np.testing.assert_array_equal(getattr(ev_s, f), getattr(ev_d, f))

    starts = np.stack([rng.choice(len(T), 5, replace=False) for _ in range(2)])
    r_d = refine_network(dense, vis, np.arange(len(T)), starts, 2, np.random.default_rng(5), n_kicks=2)
    r_s = refine_network(sp, vis, np.arange(len(T)), starts, 2, np.random.default_rng(5), n_kicks=2)
    np.testing.assert_array_equal(r_s.stations, r_d.stations)
    assert r_s.worst == r_d.worst and r_s.n_swaps == r_d.n_swaps

    b_d = worst_sigma_lower_bound(dense, 5, visible=vis, min_rays=2)
    b_s = worst_sigma_lower_bound(sp, 5, visible=vis, min_rays=2)
    assert b_s.lower == b_d.lower and b_s.relaxed == b_d.relaxed


def test_sparse_information_selects_and_stacks_candidates():
    from planning.sparse_info import SparseInfo

    T, xyz, vis = candidate_scene(seed=5, m=30, n=20)
    dense = target_information(INTR, T, xyz, vis, SIGMA_PX, dtype=np.float64)
    sp = target_information(INTR, T, xyz, vis, SIGMA_PX, dtype=np.float64, sparse=True)
    rows = np.array([29, 0, 4, 4])
    np.testing.assert_array_equal(sp.select(rows).toarray(), dense[rows])
    both = SparseInfo.vstack([SparseInfo.from_dense(dense[:3], vis[:3]), sp.select(rows)])
    np.testing.assert_array_equal(both.toarray(), np.concatenate([dense[:3], dense[rows]]))


def test_image_precision_by_the_detector_model_weights_each_ray_by_its_geometry():
    from calibration.detector_model import DetectorModel, load_model
    from planning.uncertainty import ImagePrecision

    rng = np.random.default_rng(3)
    xyz = rng.uniform(-0.05, 0.05, (20, 3))
    normals = np.tile([0.0, 0.0, 1.0], (20, 1))
    T = ring(6, 0.6, 40.0)
    vis = np.ones((6, 20), bool)
    flat = DetectorModel(a_px=0.02, b_px=0.0, p=1.0, q=1.0)  # no geometry term: one sigma for every ray
    a = target_information(INTR, T, xyz, vis, 0.02, dtype=np.float64)
    b = target_information(INTR, T, xyz, vis, ImagePrecision(normals, 0.005, flat), dtype=np.float64)
    np.testing.assert_allclose(a, b, rtol=1e-12)
    prec = ImagePrecision(normals, 0.005)
    vis[2, :7] = False
    np.testing.assert_array_equal(  # the sparse layout (issue 21) holds the same values
        target_information(INTR, T, xyz, vis, prec, sparse=True).toarray(), target_information(INTR, T, xyz, vis, prec))
    # the measured model: a grazing ray carries less information than a face-on one at the same distance
    steep, grazing = ring(1, 0.6, 85.0), ring(1, 0.6, 12.0)
    prec = ImagePrecision(normals[:1], 0.005)
    i_steep = target_information(INTR, steep, np.zeros((1, 3)), np.ones((1, 1), bool), prec, dtype=np.float64)
    i_graz = target_information(INTR, grazing, np.zeros((1, 3)), np.ones((1, 1), bool), prec, dtype=np.float64)
    s_steep = prec.sigma_px(INTR, invert(steep[0]), np.zeros((1, 3)), np.array([0]))[0]
    s_graz = prec.sigma_px(INTR, invert(grazing[0]), np.zeros((1, 3)), np.array([0]))[0]
    assert s_graz > 3 * s_steep and s_steep == pytest.approx(load_model().sigma_px(np.radians(5.0), 0.005 * INTR.fx_px / 0.6),
                                                            rel=0.05)
    assert i_graz[0, 0, [0, 3, 5]].sum() < i_steep[0, 0, [0, 3, 5]].sum()


def test_per_ray_model_information_is_the_numpy_model_held_inside_its_measured_range():
    """The compiled per-ray weights (planning.kernels.information_rows_model) against J^T J / sigma^2 with the
    model's sigma computed in NumPy; rays beyond the measured incidence or dot size count as the nearest measured."""
    from calibration.detector_model import load_model
    from planning.uncertainty import ImagePrecision, point_information

    model = load_model()
    inc_max, d_min, d_max = model.measured_box()
    assert np.degrees(inc_max) == pytest.approx(80.0) and (d_min, d_max) == (15.4, 38.9)
    rng = np.random.default_rng(5)
    xyz = rng.uniform(-0.05, 0.05, (30, 3))
    normals = rng.normal(size=(30, 3)) + [0.0, 0.0, 3.0]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # close (dots of 40-60 px at f = 3500 px), far (dots of ~14 px) and low (grazing beyond 80 deg) stations
    T = np.concatenate([ring(4, 0.35, 60.0), ring(3, 1.2, 45.0), ring(3, 0.5, 3.0)])
    vis = rng.random((10, 30)) < 0.8
    prec = ImagePrecision(normals, 0.005, noise_scale=1.7)
    got = target_information(INTR, T, xyz, vis, prec, dtype=np.float64, sparse=True)
    cfp = invert(T)
    d_seen, inc_seen = [], []
    for i in range(len(T)):
        cols = np.flatnonzero(vis[i])
        s = prec.sigma_px(INTR, cfp[i], xyz, cols)
        ref = point_information(INTR, np.repeat(cfp[i][None], len(cols), axis=0), xyz[cols]) / s[:, None] ** 2
        np.testing.assert_allclose(got.data[got.indptr[i]:got.indptr[i + 1]], ref, rtol=1e-12)
        np.testing.assert_array_equal(got.indices[got.indptr[i]:got.indptr[i + 1]], cols)
        z = xyz[cols] @ cfp[i, 2, :3] + cfp[i, 2, 3]
        sight = T[i, :3, 3] - xyz[cols]
        inc = np.arccos(np.einsum("ka,ka->k", sight / np.linalg.norm(sight, axis=1, keepdims=True), normals[cols]))
        d = INTR.fx_px * 0.005 / z
        d_seen.append(d), inc_seen.append(inc)
        # no extrapolation: the sigma is the model's at the geometry clipped into the measured box
        np.testing.assert_allclose(s, model.sigma_px(np.minimum(inc, inc_max), np.clip(d, d_min, d_max), 1.7),
                                   rtol=1e-12)
    d_seen, inc_seen = np.concatenate(d_seen), np.concatenate(inc_seen)
    assert (d_seen > d_max).any() and (d_seen < d_min).any() and (inc_seen > inc_max).any()  # the clip was exercised
    # a larger dot than any measured gets no smaller sigma than the largest measured one
    assert model.sigma_px_measured(0.3, 80.0) == model.sigma_px_measured(0.3, d_max) > model.sigma_px(0.3, 80.0)
