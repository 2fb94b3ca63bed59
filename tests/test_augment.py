"""The closed loop's planner (planning.augment): fewest extra stations, against an exhaustive search."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from calibration.camera import Intrinsics
from planning.augment import _IU, information_from_covariance, plan_extra_stations
from planning.uncertainty import sym_from_6, target_information


def _look_at(eye: np.ndarray) -> np.ndarray:
    """part_from_cam of a camera at ``eye`` looking at the origin (z forward)."""
    z = -eye / np.linalg.norm(eye)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.95 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = eye
    return T


def _scene(seed: int, m: int = 14, n: int = 10):
    rng = np.random.default_rng(seed)
    intr = Intrinsics.from_focal_length(8e-3, 3.45e-6, 2448, 2048)
    xyz = np.column_stack([rng.uniform(-0.1, 0.1, n), rng.uniform(-0.1, 0.1, n), rng.uniform(0, 0.03, n)])
    az = rng.uniform(0, 2 * np.pi, m)
    el = rng.uniform(np.deg2rad(25), np.deg2rad(80), m)
    eyes = 0.6 * np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    T = np.array([_look_at(e) for e in eyes])
    visible = rng.random((m, n)) < 0.45  # occlusion by the part: each candidate sees some targets
    info = target_information(intr, T, xyz, visible, 0.05, dtype=np.float64)
    return info, visible


def _meets(N6, rays, req, min_rays, sel, info, visible):
    N = N6 + (info[list(sel)].sum(axis=0) if sel else 0.0)
    r = rays + (visible[list(sel)].sum(axis=0) if sel else 0)
    ok = r >= min_rays
    sig = np.full(len(req), np.inf)
    for t in np.flatnonzero(ok):
        M = sym_from_6(N[t])
        if np.linalg.cond(M) < 1e12:
            sig[t] = np.sqrt(np.trace(np.linalg.inv(M)))
    return sig <= req, sig


@pytest.mark.parametrize("seed", range(6))
def test_extra_stations_within_one_of_exhaustive_search(seed):
    info, visible = _scene(seed)
    m, n = visible.shape
    have = [0, 1]  # the stations already taken: their information is fixed
    N_have = info[have].sum(axis=0)
    rays = visible[have].sum(axis=0)
    pool = np.ones(m, dtype=bool)
    pool[have] = False
    # a requirement between what the taken stations give and what every candidate could give
    _, sig_have = _meets(N_have, rays, np.full(n, np.inf), 3, (), info, visible)
    _, sig_all = _meets(N_have, rays, np.full(n, np.inf), 3, tuple(np.flatnonzero(pool)), info, visible)
    finite = np.isfinite(sig_all)
    req = np.where(finite, 1.6 * sig_all, 1e-3)
    aug = plan_extra_stations(N_have, rays, req, info, visible, pool, min_rays=3, max_new=m)
    fixable = aug.short & ~aug.unreachable
    # the proof: with every candidate added a target misses -> it is named unreachable, and only then
    assert np.array_equal(aug.unreachable, aug.short & ~(sig_all <= req))
    met, _ = _meets(N_have, rays, req, 3, tuple(aug.added), info, visible)
    assert np.all(met[fixable]), "the chosen stations do not bring every fixable target within its requirement"
    assert np.all(aug.met_after[fixable])
    # exhaustive: the fewest candidates that fix every fixable target
    cand = np.flatnonzero(pool)
    best = None
    for k in range(0, len(cand) + 1):
        for sel in itertools.combinations(cand, k):
            ok, _ = _meets(N_have, rays, req, 3, sel, info, visible)
            if np.all(ok[fixable]):
                best = k
                break
        if best is not None:
            break
    assert best is not None
    assert len(aug.added) <= best + 1, (len(aug.added), best)
    assert len(set(aug.added.tolist()) & set(have)) == 0


def test_bound_is_below_every_choice_of_stations():
    info, visible = _scene(11, m=12, n=8)
    m, n = visible.shape
    pool = np.ones(m, dtype=bool)
    pool[0] = False
    N_have, rays = info[0], visible[0].astype(int)
    aug = plan_extra_stations(N_have, rays, np.full(n, 1e-9), info, visible, pool, min_rays=2, max_new=3)
    assert aug.unreachable.all()  # 1 nm: no station can, and every target is named with the bound
    rng = np.random.default_rng(0)
    for _ in range(40):
        sel = tuple(rng.choice(np.flatnonzero(pool), size=rng.integers(1, m), replace=False))
        _, sig = _meets(N_have, rays, np.full(n, np.inf), 2, sel, info, visible)
        assert np.all(aug.bound_sigma <= sig * (1 + 1e-9))


def test_target_seen_by_no_candidate_is_proved_unreachable():
    info, visible = _scene(3, m=10, n=6)
    visible = visible.copy()
    visible[:, 2] = False
    info = info.copy()
    info[:, 2] = 0.0
    aug = plan_extra_stations(np.zeros((6, 6)), np.zeros(6, int), np.full(6, 1.0), info, visible,
                              np.ones(10, dtype=bool), min_rays=2, max_new=10)
    assert aug.unreachable[2] and not np.isfinite(aug.bound_sigma[2])


def test_information_from_covariance_inverts_measured_and_skips_unmeasured():
    A = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 0.5], [0.0, 0.5, 2.0]]) * 1e-10
    cov = np.stack([A, np.full((3, 3), np.nan), -A])
    N6, measured = information_from_covariance(cov)
    assert measured.tolist() == [True, False, False]
    assert np.allclose(sym_from_6(N6[0]) @ A, np.eye(3))
    assert np.all(N6[1:] == 0)
    assert N6.shape == (3, 6) and len(_IU[0]) == 6
