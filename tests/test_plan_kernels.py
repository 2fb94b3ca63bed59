"""The planner's compiled kernels (planning/kernels.py) against the dense NumPy formulation they replace:
the same choices and the same figures, bit for bit (issue 21)."""
from __future__ import annotations

import numpy as np
import pytest

from planning import kernels
from planning.planner.problem import _violation
from planning.refine import _sigma6, network_sigma, swap_descent
from planning.sparse_info import SparseInfo
from planning.uncertainty import _IU, _dedupe, criterion, evaluate_networks


def _database(m, n, seed, p):
    """Random per-candidate information ``J^T J`` (2x3 Jacobians, scales spread over 1e4 by candidate) and
    visibility; each ray weighted on its own besides (1 / sigma^2 over 1e2, as the detector model weighs rays by
    their incidence and dot size: planning.kernels.information_rows_model)."""
    rng = np.random.default_rng(seed)
    vis = rng.random((m, n)) < p
    J = rng.normal(size=(m, n, 2, 3)) * rng.uniform(1.0, 100.0, (m, 1, 1, 1)) * rng.uniform(1.0, 10.0, (m, n, 1, 1))
    info = np.einsum("mnri,mnrj->mnij", J, J)[:, :, _IU[0], _IU[1]] * vis[..., None]
    return info.astype(np.float32), vis


def _dense_strict_step(info, visible, S, N, cnt, worst, pool, min_rays, rel_tol=1e-6):
    """The exchange step as it was written on dense arrays (planning/refine.py before the kernels)."""
    vis8 = visible.astype(np.uint8)
    target = worst * (1.0 - rel_tol)
    sig_rm = _sigma6(N[None] - info[S], cnt[None] - vis8[S], min_rays)
    crit = sig_rm >= target
    rest = np.max(np.where(crit, 0.0, sig_rm), axis=1)
    pool = pool[visible[pool, int(np.argmax(np.min(sig_rm, axis=0)))]]
    best = None
    for i in np.argsort(rest, kind="stable"):
        bound = best[0] if best else target
        if rest[i] >= bound:
            break
        cj = np.flatnonzero(crit[i])
        cand = pool[np.all(visible[np.ix_(pool, cj)], axis=1)]
        if cand.size == 0:
            continue
        Ni = N[cj] - info[S[i], cj]
        ci = cnt[cj] - vis8[S[i], cj]
        sc = _sigma6(Ni[None] + info[np.ix_(cand, cj)], ci[None] + vis8[np.ix_(cand, cj)], min_rays)
        w = np.maximum(sc.max(axis=1), rest[i])
        j = int(np.argmin(w))
        if w[j] < bound:
            best = (float(w[j]), int(i), int(cand[j]))
    return best


def _dense_descent(info, visible, S, min_rays, max_swaps=200):
    """Strict steps from a feasible start with the dense step, ``N`` updated by each exchange as
    planning.refine.swap_descent did; the list of (worst, slot, candidate) and the end."""
    S = S.copy()
    steps = []
    N = info[S].sum(axis=0, dtype=np.float64)
    cnt = visible[S].sum(axis=0, dtype=np.int32)
    for _ in range(max_swaps):
        worst = float(_sigma6(N, cnt, min_rays).max())
        pool = np.setdiff1d(np.arange(len(info)), S)
        move = _dense_strict_step(info, visible, S, N, cnt, worst, pool, min_rays)
        if move is None:
            break
        _, i, c = move
        N += info[c].astype(np.float64) - info[S[i]]
        cnt += visible[c].astype(np.int32) - visible[S[i]]
        S[i] = c
        steps.append((float(_sigma6(N, cnt, min_rays).max()), i, c))
    return steps, S


@pytest.mark.parametrize("seed", range(6))
def test_exchange_descent_makes_the_dense_formulations_choices_bit_for_bit(seed):
    m, n, k, p = [(40, 120, 10, 0.5), (120, 400, 16, 0.4)][seed % 2]
    info, vis = _database(m, n, seed, p)
    rng = np.random.default_rng(100 + seed)
    steps = []
    for _ in range(200):  # a random feasible start (every target 2 rays) that can be improved
        S = rng.choice(m, k, replace=False)
        if np.all(vis[S].sum(axis=0) >= 2):
            steps, S_end = _dense_descent(info, vis, S, 2)
            if steps:
                break
    assert steps, "no start found that descends: the test would compare nothing"
    for arr in (info, SparseInfo.from_dense(info, vis)):
        r = swap_descent(arr, vis, np.arange(m), S, 2)
        assert [h["worst"] for h in r.history] == [w for w, _, _ in steps]
        np.testing.assert_array_equal(r.stations, S_end)
    # and the end is a local optimum: no single exchange lowers the worst
    for i in range(k):
        for c in np.setdiff1d(np.arange(m), r.stations)[::3]:
            T = r.stations.copy()
            T[i] = c
            assert network_sigma(info, vis, T, 2).max() >= r.worst * (1 - 1e-6)


def test_population_fitness_equals_evaluate_networks_and_criterion():
    info, vis = _database(150, 900, 3, 0.25)
    sp = SparseInfo.from_dense(info, vis)
    rng = np.random.default_rng(4)
    st = rng.integers(-1, 150, size=(64, 9))  # some stations off (-1), some repeated
    ev = evaluate_networks(info, st, 3, visible=vis)
    req = rng.uniform(0.5, 2.0, 900)
    refs = {0: criterion(ev, "worst", penalty=0.0),
            2: np.max(np.where(ev.sufficient, ev.sigma / req, 0.0), axis=1)}
    for kind, ref in refs.items():
        value, violation, short = np.empty(64), np.empty(64), np.empty(64, dtype=np.int64)
        kernels.population_fitness(sp.starts, sp.ends, sp.indices, sp.data, _dedupe(st), 900, 3, kind, req,
                                   value, violation, short)
        np.testing.assert_array_equal(value, ref)
        np.testing.assert_array_equal(violation, _violation(ev))
        np.testing.assert_array_equal(short, ev.n_insufficient)


def test_sparse_views_share_their_buffers_and_answer_like_the_dense_array():
    info, vis = _database(30, 50, 5, 0.4)
    sp = SparseInfo.from_dense(info.astype(np.float64), vis)
    rows = np.array([29, 0, 4, 4, 17])
    view = sp.rows(rows)
    assert view.data is sp.data and view.indptr is None
    np.testing.assert_array_equal(view.toarray(), info[rows].astype(np.float64))
    np.testing.assert_array_equal(view[np.ix_([1, 3], [2, 40, 7])], info[np.ix_(rows[[1, 3]], [2, 40, 7])])
    np.testing.assert_array_equal(view.compact().toarray(), view.toarray())
    np.testing.assert_array_equal(network_sigma(view, vis[rows], np.array([0, 2, 4]), 2),
                                  network_sigma(info.astype(np.float64), vis, rows[[0, 2, 4]], 2))


def test_compiled_visibility_equals_numpy_and_shared_camera_centres_reuse_the_rays():
    """The compiled geometric tests equal planning.visibility.geometric_visibility (with lens distortion), and a
    pose that keeps another's camera centre (a look-at offset) gets the visibility a fresh ray cast gives it
    from that pose's occlusion answers."""
    from calibration.camera import Intrinsics
    from planning.stations import ViewingSphere
    from planning.visibility import (VisibilityOptions, compute_visibility, geometric_visibility,
                                     geometric_visibility_compiled)
    from tests.test_planner import _box_part

    part = _box_part(300, seed=2)
    intr = Intrinsics(fx_px=2000.0, fy_px=2000.0, cx_px=639.5, cy_px=511.5, width=1280, height=1024,
                      k1=-0.1, k2=0.03, p1=2e-4, p2=-1e-4)
    sphere = ViewingSphere.for_part(part, intr)
    genes = sphere.candidates(40, 3)
    T = sphere.poses(genes)
    xyz, nrm = part.targets.xyz, part.targets.normals
    for opts in (VisibilityOptions(), VisibilityOptions(margin_px=40.0, near_m=0.2, far_m=0.6, min_target_px=12.0)):
        ref = geometric_visibility(intr, T, xyz, nrm, part.target_diameter_m, opts)
        assert 0 < ref.sum() < ref.size
        np.testing.assert_array_equal(geometric_visibility_compiled(intr, T, xyz, nrm, part.target_diameter_m, opts),
                                      ref)
    opts = VisibilityOptions()
    geo = np.empty((len(T), len(xyz)), dtype=bool)
    vis = compute_visibility(part, intr, T, opts, geometric_out=geo)
    moved = genes.copy()
    moved[:, 4] += 0.12  # look-at offsets: the same camera centres
    moved[:, 5] -= 0.08
    T2 = sphere.poses(moved)
    fresh = compute_visibility(part, intr, T2, opts)
    reused = compute_visibility(part, intr, T2, opts, rays_known=geo, rays_free=vis)
    np.testing.assert_array_equal(reused, fresh)
    assert np.any(fresh != vis)  # the offsets do change what is seen: the test compares something


def test_in_two_covers_the_range_once_and_raises_the_threads_error():
    seen = []
    kernels.in_two(11, lambda a, b: seen.append((a, b)))
    assert sorted(seen) == [(0, 5), (5, 11)]
    kernels.in_two(3, lambda a, b: seen.append((a, b)), min_size=4)
    assert seen[-1] == (0, 3)

    def fail(a, b):
        if a > 0:
            raise ValueError("second half")

    with pytest.raises(ValueError, match="second half"):
        kernels.in_two(8, fail)


def test_unlinked_stations_are_those_outside_the_main_block_or_sole_links_as_scipy_finds_them():
    """The search's linking rule (planning.kernels.unlinked_stations) against connected components of the
    stations' common-target graph (scipy): stations outside the largest block of images sharing >= 8 targets;
    for a network that is one block, the stations whose removal splits it."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(0)
    vis = np.zeros((60, 300), bool)  # two groups of candidates on two halves of the targets, a few bridging
    vis[:30, :150] = rng.random((30, 150)) < 0.3
    vis[30:, 150:] = rng.random((30, 150)) < 0.3
    vis[55:, 140:160] = rng.random((5, 20)) < 0.6
    st = _dedupe(rng.integers(-1, 60, (300, 8)))

    def blocks(S):
        common = vis[S].astype(int) @ vis[S].T.astype(int)
        nb, label = connected_components(csr_matrix(common >= 8), directed=False)
        return len(S) - np.bincount(label).max(), nb

    ref = []
    for row in st:
        S = row[row >= 0]
        outside, _ = blocks(S)
        ref.append(outside if outside else sum(blocks(np.delete(S, j))[1] > 1 for j in range(len(S))))
    ref = np.array(ref, dtype=float)
    np.testing.assert_array_equal(kernels.count_unlinked(kernels.pack_rows(vis), st, 8), ref)
    assert (ref == 0).any() and (ref > 0).any() and set(np.unique(ref)) >= {0, 1, 2}
    # without the sole-link rule: only the stations outside the main block
    split = np.array([blocks(row[row >= 0])[0] for row in st], dtype=float)
    np.testing.assert_array_equal(kernels.count_unlinked(kernels.pack_rows(vis), st, 8, sole_links=False), split)
