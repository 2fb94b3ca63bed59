"""The lower bound on a network's worst sigma (planning/bound.py) against brute force."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from calibration.camera import Intrinsics
from calibration.errors import PlanningError
from planning.bound import _trace_inverse, worst_sigma_lower_bound
from planning.stations import ViewingSphere, fibonacci_band
from planning.uncertainty import sym_from_6, target_information


def _problem(n_cand=12, n_targets=25, seed=0, p_visible=1.0):
    rng = np.random.default_rng(seed)
    intr = Intrinsics.from_focal_length(0.012, 3.45e-6, 2448, 2048)
    sphere = ViewingSphere(centre=(0.0, 0.0, 0.0), distance_min_m=0.8, distance_max_m=1.2,
                           elevation_min_rad=0.2, elevation_max_rad=1.4, max_roll_rad=0.0)
    genes = np.zeros((n_cand, 6))
    genes[:, :2] = fibonacci_band(n_cand, 0.2, 1.4)
    genes[:, 2] = rng.uniform(0.8, 1.2, n_cand)
    T = sphere.poses(genes)
    xyz = rng.uniform(-0.1, 0.1, (n_targets, 3))
    visible = rng.random((n_cand, n_targets)) < p_visible
    info = target_information(intr, T, xyz, visible, 0.05, dtype=np.float64)
    return info, visible


def _worst(info, subset, visible=None, min_rays=0):
    N = sym_from_6(info[list(subset)].sum(axis=0))
    if visible is not None and np.any(visible[list(subset)].sum(axis=0) < min_rays):
        return np.inf
    if np.any(np.linalg.det(N / np.trace(N, axis1=1, axis2=2)[:, None, None]) <= 1e-12):
        return np.inf
    return float(np.sqrt(np.max(np.trace(np.linalg.inv(N), axis1=1, axis2=2))))


@pytest.mark.parametrize("k", [3, 5])
def test_bound_below_the_best_network_found_by_brute_force(k):
    info, _ = _problem()
    best = min(_worst(info, s) for s in itertools.combinations(range(len(info)), k))
    b = worst_sigma_lower_bound(info, k)
    assert b.converged
    assert b.lower <= best * (1 + 1e-9)
    assert b.lower <= b.relaxed <= b.lower * 1.002
    # not a trivial bound: within a few percent of the true optimum on this small problem
    assert b.lower >= 0.9 * best, (b.lower, best)
    assert b.weights.sum() <= k + 1e-6 and b.weights.min() >= 0 and b.weights.max() <= 1 + 1e-9


def test_bound_with_visibility_and_min_rays():
    info, visible = _problem(n_cand=11, n_targets=30, seed=3, p_visible=0.6)
    k = 5
    best = min(_worst(info, s, visible, 2) for s in itertools.combinations(range(len(info)), k))
    assert np.isfinite(best)
    b = worst_sigma_lower_bound(info, k, visible=visible, min_rays=2)
    assert b.lower <= best * (1 + 1e-9)
    # the coverage constraint can only raise the bound
    assert b.lower >= worst_sigma_lower_bound(info, k).lower * (1 - 1e-3)


def test_bound_on_a_subset_of_targets_and_scaled():
    info, _ = _problem(seed=5)
    k = 4
    sub = np.arange(0, 25, 3)
    b_all = worst_sigma_lower_bound(info, k)
    b_sub = worst_sigma_lower_bound(info, k, targets=sub)
    best_sub = min(_worst(info[:, sub], s) for s in itertools.combinations(range(len(info)), k))
    assert b_sub.lower <= best_sub * (1 + 1e-9)
    assert b_sub.lower <= b_all.lower * (1 + 1e-3)
    # a uniform scale divides the bound
    b_scaled = worst_sigma_lower_bound(info, k, scale=np.full(25, 1e-5))
    assert b_scaled.lower == pytest.approx(b_all.lower / 1e-5, rel=2e-3)


def test_tangent_cuts_underestimate_everywhere():
    """The cutting planes are valid because trace(N(x)^-1) is convex and its gradient is -<N_i, C^2>."""
    info, _ = _problem(n_cand=8, n_targets=6, seed=7)
    rng = np.random.default_rng(1)
    flat = info.reshape(8, -1)
    for _ in range(20):
        x, y = rng.uniform(0.2, 1, 8), rng.uniform(0.05, 1, 8)
        fx, C2 = _trace_inverse((x @ flat).reshape(6, 6))
        fy, _ = _trace_inverse((y @ flat).reshape(6, 6))
        g = -np.einsum("itk,tk->ti", info, C2 * np.array([1, 2, 2, 1, 2, 1.0]))
        assert np.all(fy >= fx + g @ (y - x) - 1e-9 * fx)
        # and the gradient is right (central differences)
        e = np.zeros(8)
        e[2] = 1e-6
        fp, _ = _trace_inverse(((x + e) @ flat).reshape(6, 6))
        fm, _ = _trace_inverse(((x - e) @ flat).reshape(6, 6))
        np.testing.assert_allclose((fp - fm) / 2e-6, g[:, 2], rtol=1e-4)


def test_thresholds_stop_early():
    info, _ = _problem()
    full = worst_sigma_lower_bound(info, 4)
    above = worst_sigma_lower_bound(info, 4, stop_above=0.5 * full.lower)
    assert above.stopped_because == "above" and above.lower > 0.5 * full.lower
    below = worst_sigma_lower_bound(info, 4, stop_below=2.0 * full.relaxed)
    assert below.stopped_because == "below" and below.relaxed < 2.0 * full.relaxed


def test_bad_input_is_refused():
    info, _ = _problem()
    with pytest.raises(PlanningError, match=r"\(m, n, 6\)"):
        worst_sigma_lower_bound(info[..., :5], 3)
    with pytest.raises(PlanningError, match="valid has shape"):
        worst_sigma_lower_bound(info, 3, valid=np.ones(3, dtype=bool))
    with pytest.raises(PlanningError, match="no valid candidate"):
        worst_sigma_lower_bound(info, 3, valid=np.zeros(len(info), dtype=bool))


def test_too_few_stations_for_min_rays_is_an_infinite_bound():
    info, visible = _problem(n_cand=11, n_targets=30, seed=3, p_visible=0.6)
    b = worst_sigma_lower_bound(info, 1.5, visible=visible, min_rays=2)
    assert b.stopped_because == "infeasible" and b.lower == np.inf
