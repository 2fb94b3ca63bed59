"""More stations never measure worse (planning.planner.ladder), on a small self-occluding part."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.camera import Intrinsics
from planning.planner import PlannerOptions, plan_network
from planning.planner.ladder import greedy_additions, ladder_sizes
from planning.refine import _sigma6
from tests.test_planner import _box_part


def _opts(k: int) -> PlannerOptions:
    return PlannerOptions(n_stations=k, min_rays=3, population=16, generations=12, stall_generations=12,
                          n_candidates=600, sigma_px=0.1, refine_kicks=2, polish_rounds=3)


@pytest.mark.slow
def test_plans_with_more_stations_are_never_worse(tmp_path):
    part = _box_part(40, seed=1)
    intr = Intrinsics(fx_px=2000.0, fy_px=2000.0, cx_px=639.5, cy_px=511.5, width=1280, height=1024)
    worst = {}
    plans = {}
    for k in (16, 29, 32, 64, 128):
        plans[k] = plan_network(part, intr, _opts(k), cache_dir=tmp_path, seed=5)
        worst[k] = plans[k].predicted_sigma_max_m
        assert len(plans[k].station_ids) == k and np.all(plans[k].n_rays >= 3)
    sizes = [16, 29, 64, 128]
    for a, b in zip(sizes, sizes[1:]):
        assert worst[b] <= worst[a] * (1 + 1e-9), worst
    assert worst[128] < worst[16]  # and the extra stations do help
    # 64 and 128 grow from the plan of 32 stations (the same one plan_network(32) gives), through 64
    ladder = plans[128].search["ladder"]
    assert [s["stations"] for s in ladder] == [32, 64, 128]
    assert ladder[0]["worst_m"] == pytest.approx(worst[32], rel=1e-12)
    assert ladder[1]["worst_m"] == pytest.approx(worst[64], rel=1e-12)
    assert worst[128] <= worst[64] <= worst[32]


def test_ladder_sizes_double_from_the_base():
    assert ladder_sizes(29, 32) == [29]
    assert ladder_sizes(64, 32) == [32, 64]
    assert ladder_sizes(100, 32) == [32, 64, 100]
    assert ladder_sizes(128, 32) == [32, 64, 128]
    assert ladder_sizes(128, 0) == [128]


def test_greedy_addition_takes_the_candidate_that_lowers_the_worst_most():
    rng = np.random.default_rng(0)
    m, c = 30, 12
    A = rng.normal(size=(m, c, 3, 3))
    info_full = np.einsum("mcij,mckj->mcik", A, A)  # symmetric positive definite per candidate x target
    vis = rng.random((m, c)) < 0.7
    info_full[~vis] = 0.0
    iu = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))
    info = info_full[:, :, iu[0], iu[1]]
    start = np.arange(4)
    N, cnt = info[start].sum(axis=0), vis[start].sum(axis=0)
    pool = np.arange(4, m)
    got = greedy_additions(N, cnt, info, vis, pool, 1, 2)
    # brute force over every candidate, on every target
    worst = [_sigma6(N + info[p], cnt + vis[p], 2).max() for p in pool]
    assert _sigma6(N + info[got[0]], cnt + vis[got[0]], 2).max() == pytest.approx(min(worst))
