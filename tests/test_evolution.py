"""The evolutionary kernels against the seed's equations (8), (9) and the engine on known problems."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from planning.evolution import (
    Evaluation,
    EvolutionOptions,
    bit_flip,
    crowding_distance,
    evolve,
    non_dominated_sort,
    polynomial_delta,
    polynomial_mutation,
    sbx,
    sbx_beta,
    sbx_children,
    tournament,
)


# --- SBX, seed eq. (8) -----------------------------------------------------------


def test_sbx_beta_matches_seed_eq8_for_known_u():
    eta = 1.0
    u = np.array([0.0, 0.125, 0.25, 0.5, 0.75, 0.875])
    expected = np.array([0.0, 0.5, np.sqrt(0.5), 1.0, np.sqrt(2.0), 2.0])
    assert np.allclose(sbx_beta(u, eta), expected)
    eta = 4.0
    assert np.isclose(sbx_beta(0.3, eta), 0.6 ** (1 / 5))
    assert np.isclose(sbx_beta(0.9, eta), (1 / 0.2) ** (1 / 5))


def test_sbx_children_preserve_mean_and_spread_by_beta():
    rng = np.random.default_rng(1)
    p1, p2 = rng.normal(size=(2, 50))
    beta = rng.random(50) * 3
    c1, c2 = sbx_children(p1, p2, beta)
    assert np.allclose(c1 + c2, p1 + p2)
    assert np.allclose(np.abs(c1 - c2), beta * np.abs(p1 - p2))
    # explicit eq. (8) values
    c1, c2 = sbx_children(1.0, 3.0, 0.5)
    assert np.isclose(c1, 0.5 * (1.5 * 1.0 + 0.5 * 3.0)) and np.isclose(c2, 0.5 * (0.5 * 1.0 + 1.5 * 3.0))


@pytest.mark.parametrize("eta", [2.0, 15.0])
def test_sbx_spread_factor_follows_the_sbx_distribution(eta):
    # density 0.5(eta+1) b^eta (b <= 1), 0.5(eta+1) b^-(eta+2) (b > 1)  ->  CDF below
    def cdf(b):
        b = np.asarray(b, dtype=float)
        return np.where(b <= 1, 0.5 * b ** (eta + 1), 1 - 0.5 * b ** -(eta + 1))

    rng = np.random.default_rng(7)
    lower, upper = np.full(1, -1e9), np.full(1, 1e9)
    p1 = np.zeros((20000, 1))
    p2 = np.ones((20000, 1))
    c1, c2 = sbx(p1, p2, lower, upper, eta, rng, prob=1.0, prob_var=1.0)
    beta = np.abs(c2 - c1)[:, 0]  # |c1 - c2| = beta |p1 - p2|
    assert stats.kstest(beta, cdf).pvalue > 0.01
    # and the children are distributed symmetrically around the parents' mean
    assert abs(np.median(c1 + c2 - 1.0)) < 1e-9


def test_sbx_children_respect_bounds_and_wrap_periodic_genes():
    rng = np.random.default_rng(3)
    lower, upper = np.array([0.0, -np.pi]), np.array([1.0, np.pi])
    p1 = np.column_stack([rng.random(5000) * 0.05, rng.uniform(-np.pi, np.pi, 5000)])
    p2 = np.column_stack([1.0 - rng.random(5000) * 0.05, rng.uniform(-np.pi, np.pi, 5000)])
    c1, c2 = sbx(p1, p2, lower, upper, 0.5, rng, prob=1.0, prob_var=1.0, periodic=np.array([False, True]))
    for c in (c1, c2):
        assert np.all(c >= lower) and np.all(c <= upper)
    # eta = 0.5 spreads widely: some children must have hit the bounds of gene 0 (clipped)
    assert np.any(c1[:, 0] == 0.0) or np.any(c1[:, 0] == 1.0)


def test_sbx_with_zero_probability_copies_the_parents():
    rng = np.random.default_rng(0)
    p1, p2 = rng.random((2, 10, 4))
    c1, c2 = sbx(p1, p2, np.zeros(4), np.ones(4), 10.0, rng, prob=0.0)
    assert np.array_equal(c1, p1) and np.array_equal(c2, p2)


# --- polynomial mutation, seed eq. (9) (Deb's operator) -------------------------------


def test_polynomial_delta_matches_debs_operator_for_known_u():
    eta = 1.0
    u = np.array([0.0, 0.125, 0.25, 0.5, 0.75, 0.875, 0.98])
    expected = np.array([-1.0, 0.5 - 1.0, np.sqrt(0.5) - 1.0, 0.0, 1.0 - np.sqrt(0.5), 1.0 - 0.5, 0.8])
    assert np.allclose(polynomial_delta(u, eta), expected)
    # the printed eq. (9) ((2u)^(1/(eta+1) - 1)) would not even be bounded: at u = 0.125 it is 2.
    assert np.isclose((2 * 0.125) ** (1 / 2 - 1), 2.0)


@pytest.mark.parametrize("eta", [5.0, 20.0])
def test_polynomial_delta_follows_its_distribution(eta):
    def cdf(d):
        d = np.asarray(d, dtype=float)
        return np.where(d < 0, 0.5 * (1 + d) ** (eta + 1), 1 - 0.5 * (1 - d) ** (eta + 1))

    delta = polynomial_delta(np.random.default_rng(11).random(20000), eta)
    assert np.all(np.abs(delta) <= 1)
    assert stats.kstest(delta, cdf).pvalue > 0.01


def test_polynomial_mutation_keeps_children_within_bounds_near_the_bounds():
    rng = np.random.default_rng(5)
    lower, upper = np.array([0.0, -2.0, 10.0]), np.array([1.0, 2.0, 10.5])
    x = np.vstack([lower + 1e-6, upper - 1e-6, 0.5 * (lower + upper), lower, upper])
    x = np.repeat(x, 4000, axis=0)
    for eta in (0.0, 1.0, 20.0):
        y = polynomial_mutation(x, lower, upper, eta, 1.0, rng)
        assert np.all(y >= lower) and np.all(y <= upper)
        mid = slice(8000, 12000)
        assert np.all(y[mid] != x[mid])  # prob 1: every parent inside the range moved
    # small eta moves parents at a bound well inside the range
    y = polynomial_mutation(np.repeat(lower[None], 4000, 0), lower, upper, 0.0, 1.0, rng)
    assert np.mean((y - lower) / (upper - lower)) > 0.2


def test_polynomial_mutation_equals_eq9_one_full_range_from_the_bound():
    # parent at the upper bound: d1 = 1, so for u < 0.5 the bounded form is eq. (9) exactly,
    # and for u >= 0.5 the child cannot move up (d2 = 0).
    eta, lower, upper = 7.0, np.array([-3.0]), np.array([5.0])
    x = np.full((1000, 1), 5.0)
    rng = np.random.default_rng(21)
    u = np.random.default_rng(21).random(x.shape)  # the kernel draws u first
    y = polynomial_mutation(x, lower, upper, eta, 1.0, rng)
    lo = u < 0.5
    assert np.allclose(y[lo], x[lo] + 8.0 * polynomial_delta(u[lo], eta))
    assert np.allclose(y[~lo], 5.0)


def test_polynomial_mutation_rate_and_spread_follow_probability_and_eta():
    rng = np.random.default_rng(8)
    x = np.full((20000, 1), 0.5)
    y = polynomial_mutation(x, np.zeros(1), np.ones(1), 20.0, 0.3, rng)
    assert abs(np.mean(y != x) - 0.3) < 0.02
    wide = polynomial_mutation(x, np.zeros(1), np.ones(1), 1.0, 1.0, rng)
    narrow = polynomial_mutation(x, np.zeros(1), np.ones(1), 50.0, 1.0, rng)
    assert np.std(narrow) < 0.5 * np.std(wide)


# --- selection, bits, sorting ---------------------------------------------------------


def test_bit_flip_flips_at_the_requested_rate():
    rng = np.random.default_rng(2)
    bits = np.zeros((1000, 50), dtype=bool)
    flipped = bit_flip(bits, 0.1, rng)
    assert abs(flipped.mean() - 0.1) < 0.01
    assert not bits.any()  # a copy


def test_tournament_picks_the_best_with_the_expected_frequency():
    rng = np.random.default_rng(4)
    p, size = 10, 3
    rank = np.arange(p, dtype=float)[::-1]  # index 9 is best
    winners = tournament(rank, 100000, size, rng)
    expected_best = 1 - ((p - 1) / p) ** size
    assert abs(np.mean(winners == 9) - expected_best) < 0.01
    expected_worst = (1 / p) ** size
    assert abs(np.mean(winners == 0) - expected_worst) < 0.002


def test_non_dominated_sort_finds_the_known_fronts():
    F = np.array([[1, 5], [2, 3], [3, 1], [2, 4], [4, 4], [5, 5]], dtype=float)
    # (2,4) is dominated by (2,3); (4,4) by (2,4); (5,5) by (4,4)
    assert non_dominated_sort(F).tolist() == [0, 0, 0, 1, 2, 3]
    # constrained: the infeasible points (0, 0) rank after every feasible point, by violation
    F2 = np.vstack([F, [[0.0, 0.0], [0.0, 0.0]]])
    v = np.array([0, 0, 0, 0, 0, 0, 1.0, 2.0])
    r = non_dominated_sort(F2, v)
    assert r[:6].tolist() == [0, 0, 0, 1, 2, 3]
    assert r[6] == 4 and r[7] == 5


def test_non_dominated_sort_agrees_with_brute_force_dominance():
    rng = np.random.default_rng(9)
    F = rng.integers(0, 6, size=(60, 3)).astype(float)
    rank = non_dominated_sort(F)
    for i in range(len(F)):
        dominated_by = [j for j in range(len(F)) if np.all(F[j] <= F[i]) and np.any(F[j] < F[i])]
        expected = 0 if not dominated_by else 1 + max(rank[j] for j in dominated_by)
        assert rank[i] == expected


def test_crowding_distance_gives_boundaries_infinity_and_interior_the_cuboid():
    F = np.array([[0.0, 4.0], [1.0, 2.0], [2.0, 1.0], [4.0, 0.0]])
    d = crowding_distance(F, np.zeros(4, dtype=int))
    assert np.isinf(d[0]) and np.isinf(d[3])
    assert np.isclose(d[1], (2 - 0) / 4 + (4 - 1) / 4)
    assert np.isclose(d[2], (4 - 1) / 4 + (2 - 0) / 4)


# --- the engine -------------------------------------------------------------------------


def _sphere_problem(target):
    """k slots of 2 genes; fitness = sum over active slots of the squared distance to target."""

    def evaluate(genes, bits):
        d2 = np.sum((genes - target) ** 2, axis=2)
        f = np.sum(np.where(bits, d2, 0.0), axis=1)
        return Evaluation(f[:, None], np.zeros(len(f)), genes, bits)

    return evaluate


@pytest.mark.parametrize("plus_selection", [False, True])
def test_evolve_converges_on_a_known_optimum_and_is_reproducible(plus_selection):
    lower, upper = np.array([-5.0, -5.0]), np.array([5.0, 5.0])
    target = np.array([1.5, -2.0])
    opt = EvolutionOptions(population=40, generations=200, stall_generations=300, fix_bits=True,
                           plus_selection=plus_selection)

    def run(seed):
        rng = np.random.default_rng(seed)
        g0 = rng.uniform(lower, upper, size=(40, 4, 2))
        return evolve(_sphere_problem(target), lower, upper, g0, np.ones((40, 4), bool), opt, rng)

    a, b = run(12), run(12)
    assert np.array_equal(a.genes, b.genes)
    assert a.objectives[0, 0] < 2e-3 < 1e-3 * a.history[0]["best"]
    assert np.allclose(a.best_genes, target, atol=0.04)
    best = [h["best"] for h in a.history]
    assert all(x >= y for x, y in zip(best, best[1:]))  # elitism: the best never gets worse
    assert a.bits.all()
    assert np.all(a.genes >= lower) and np.all(a.genes <= upper)


def test_evolve_stops_when_the_search_stalls():
    opt = EvolutionOptions(population=10, generations=100, stall_generations=5)

    def flat(genes, bits):
        return Evaluation(np.ones((len(genes), 1)), np.zeros(len(genes)), genes, bits)

    rng = np.random.default_rng(0)
    res = evolve(flat, np.zeros(1), np.ones(1), rng.random((10, 3, 1)), np.ones((10, 3), bool), opt, rng)
    assert res.stopped_because == "stall"
    assert len(res.history) == 6  # generation 0 improves from inf, then 5 without progress


def test_evolve_prefers_feasible_individuals():
    # feasible only when gene > 0.8; fitness rewards small genes -> optimum at the constraint
    def evaluate(genes, bits):
        g = genes[:, 0, 0]
        return Evaluation(g[:, None].copy(), np.maximum(0.0, 0.8 - g), genes, bits)

    rng = np.random.default_rng(1)
    opt = EvolutionOptions(population=30, generations=80, stall_generations=80)
    res = evolve(evaluate, np.zeros(1), np.ones(1), rng.random((30, 1, 1)) * 0.5, np.ones((30, 1), bool), opt, rng)
    assert res.violation[0] == 0
    assert 0.8 <= res.best_genes[0, 0] < 0.82


def test_multi_objective_search_returns_a_front_of_station_count_versus_error():
    # error = 1 / (number of active slots near the target): more stations -> smaller error
    target = np.array([0.3])

    def evaluate(genes, bits):
        good = bits & (np.abs(genes[:, :, 0] - target) < 0.2)
        n_active = bits.sum(axis=1).astype(float)
        n_good = good.sum(axis=1)
        err = np.where(n_good > 0, 1.0 / np.maximum(n_good, 1), np.inf)
        viol = (n_good == 0).astype(float)
        return Evaluation(np.column_stack([n_active, err]), viol, genes, bits)

    rng = np.random.default_rng(6)
    k, P = 6, 40
    g0 = rng.random((P, k, 1))
    b0 = rng.random((P, k)) < rng.uniform(0.1, 1.0, (P, 1))
    opt = EvolutionOptions(population=P, generations=60, stall_generations=60)
    res = evolve(evaluate, np.zeros(1), np.ones(1), g0, b0, opt, rng)
    front = res.pareto_front()
    pts = {(int(res.objectives[i, 0]), round(float(res.objectives[i, 1]), 6)) for i in front}
    # the true front is n stations -> error 1/n for n = 1..6
    assert pts == {(n, round(1.0 / n, 6)) for n in range(1, k + 1)}


def test_random_reset_mutation_redraws_stations_uniformly_within_bounds():
    lower, upper = np.array([-1.0, 2.0]), np.array([1.0, 6.0])
    seen = []

    def evaluate(genes, bits):
        seen.append(genes.copy())
        return Evaluation(np.zeros((len(genes), 1)), np.zeros(len(genes)), genes, bits)

    rng = np.random.default_rng(0)
    g0 = np.tile([0.0, 4.0], (200, 5, 1))  # every station at the same point
    opt = EvolutionOptions(population=200, generations=1, stall_generations=5, p_crossover=0.0,
                           p_mutation=0.0, p_reset=1.0, n_elite=0, fix_bits=True)
    evolve(evaluate, lower, upper, g0, np.ones((200, 5), bool), opt, rng)
    children = seen[1].reshape(-1, 2)
    assert np.all(children >= lower) and np.all(children <= upper)
    assert np.allclose(children.mean(axis=0), [0.0, 4.0], atol=0.1)
    assert np.allclose(children.std(axis=0), (upper - lower) / np.sqrt(12), rtol=0.05)
