"""The truth criteria's own odds under an exact statement (tests/test_truth_partgen.py ``statement_odds``): sampled
through the low-rank form as a dense multivariate normal samples them, and what the targets' correlation does."""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2, norm

from tests.test_truth_partgen import FALSE_SIGNIFICANT_MAX, IN99_MIN, RATIO_BAND, statement_odds


def _network(rng, n: int, r: int, shared: float):
    """A bundle-like covariance (blocks D0, anisotropic; a shared part U0 C0 U0^T of about ``shared`` times D0's size)
    after an alignment that removes the mean translation, in the form the report stores: ``D + U C U^T`` with ``C``
    indefinite (``T Sigma T^T``, ``T = I - J/n``: the blocks' cross terms ``S/n^2 - (D0_i + D0_j)/n`` are
    ``[I, D0_i] [[S/n^2, -I/n], [-I/n, 0]] [I, D0_j]^T``)."""
    A = rng.normal(size=(n, 3, 3)) * np.array([1.0, 0.6, 0.3])
    D0 = np.einsum("nab,ncb->nac", A, A) + 0.05 * np.eye(3)
    U0 = rng.normal(size=(n, 3, r)) * np.sqrt(shared / max(r, 1))
    B = rng.normal(size=(r, r))
    C0 = B @ B.T / max(r, 1) + 0.1 * np.eye(r)
    eye = np.broadcast_to(np.eye(3), (n, 3, 3))
    U = np.concatenate([U0 - U0.mean(axis=0), eye, D0], axis=2)
    Ssum, Z = D0.sum(axis=0), np.zeros((3, 3))
    C = np.block([[C0, np.zeros((r, 6))],
                  [np.zeros((3, r)), Ssum / n**2, -np.eye(3) / n],
                  [np.zeros((3, r)), -np.eye(3) / n, Z]])
    return D0, U, C


def _dense_odds(D, U, C, untouched, k_sigma, draws, rng):
    n = len(D)
    S = np.einsum("nar,rs,mbs->namb", U, C, U).reshape(3 * n, 3 * n)
    for i in range(n):
        S[3 * i:3 * i + 3, 3 * i:3 * i + 3] += D[i]
    e = rng.multivariate_normal(np.zeros(3 * n), S, size=draws).reshape(draws, n, 3)
    inv = np.linalg.inv(np.array([S[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(n)]))
    m2 = np.einsum("dna,nab,dnb->dn", e, inv, e)
    ratio = np.sqrt(m2.mean(axis=1) / 3)
    in99 = np.mean(m2[:, untouched] <= chi2.ppf(0.99, 3), axis=1)
    fsig = np.mean(m2[:, untouched] > chi2.isf(2 * norm.sf(k_sigma), 3), axis=1)
    return {"ratio": np.mean((ratio < RATIO_BAND[0]) | (ratio > RATIO_BAND[1])), "in99": np.mean(in99 < IN99_MIN),
            "false_significant": np.mean(fsig > FALSE_SIGNIFICANT_MAX)}


def test_odds_agree_with_dense_sampling_of_the_joint_covariance():
    rng = np.random.default_rng(3)
    D, U, C = _network(rng, 60, 6, shared=0.6)
    untouched = rng.random(60) > 0.3
    got = statement_odds(D, U, C, untouched, 2.0, draws=4000, seed=1)
    want = _dense_odds(D, U, C, untouched, 2.0, 4000, np.random.default_rng(2))
    for key in ("ratio", "in99", "false_significant"):
        p = 0.5 * (got[key] + want[key])
        se = np.sqrt(2 * max(p * (1 - p), 1e-4) / 4000)
        assert abs(got[key] - want[key]) < 4.5 * se + 1e-3, (key, got, want)
    assert 0.05 < got["ratio"] < 0.95, got  # a case where the odds are neither zero nor certain
    assert got["any"] >= max(got["ratio"], got["in99"], got["false_significant"])
    assert np.linalg.eigvalsh(C).min() < -1e-3  # the stored form: C indefinite, only the whole a covariance


def test_independent_targets_keep_the_ratio_in_its_band_and_a_shared_mode_does_not():
    rng = np.random.default_rng(5)
    D, U, C = _network(rng, 300, 4, shared=0.0)
    alone = statement_odds(D, U, C, np.ones(300, bool), draws=1000)
    assert alone["ratio"] < 0.01 and 0.95 < alone["ratio_5_95"][0] < 1.0 < alone["ratio_5_95"][1] < 1.05, alone
    D, U, C = _network(rng, 300, 4, shared=3.0)
    shared = statement_odds(D, U, C, np.ones(300, bool), draws=1000)
    assert shared["ratio"] > 0.2, shared  # the same statement, honest, misses the band often
    lo, hi = shared["ratio_5_95"]
    assert hi - lo > 3 * (alone["ratio_5_95"][1] - alone["ratio_5_95"][0]), (alone, shared)
