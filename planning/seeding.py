"""Starting networks for the planner's search: greedy covers, random networks, convergent rings.

* :func:`greedy_cover`: a randomised greedy set multicover (every target ``min_rays``
  times, rare targets first), the classical constructive heuristic for a coverage
  constraint;
* :func:`ring_genes`: single-ring and two-ring convergent networks (the textbook
  design a photogrammetrist would start from), swept over elevations, distance and
  phase;
* :func:`initial_population`: the search's first generation (greedy covers + random
  distinct valid candidates).

Every function that draws takes an explicit ``numpy.random.Generator``.
"""
from __future__ import annotations

import numpy as np

from planning.stations import N_GENES, ViewingSphere

__all__ = ["greedy_cover", "ring_genes", "ring_sweep", "initial_population"]


def greedy_cover(visible: np.ndarray, candidates: np.ndarray, k: int, min_rays: int,
                 rng: np.random.Generator, noise: float = 0.3) -> np.ndarray:
    """A randomised greedy network of ``k`` distinct candidates covering targets ``min_rays`` times.

    Set multicover heuristic: each step takes the candidate with the largest (noisy)
    gain, the sum over the targets it sees of their remaining shortfall of rays weighted
    by rarity (1 / how many candidates see the target); once every target is covered,
    the gain is the sum of ``1 / rays so far`` (rays go to the weakest targets).

    Args:
        visible: (m, n) bool; candidates: (c,) int allowed rows of ``visible``.
        noise: relative multiplicative noise on the gains (diversity between networks).
    Returns:
        (k,) int candidate indices (repeats only if fewer than ``k`` candidates exist).
    """
    V = visible[candidates].astype(np.float32)
    draws = rng.random((k, len(candidates)))  # the draws one per step would give (the same stream)
    return _greedy_cover(V, 1.0 / np.maximum(V.sum(axis=0), 1.0), candidates, k, min_rays, draws, noise)


def _greedy_cover(V: np.ndarray, rarity: np.ndarray, candidates: np.ndarray, k: int, min_rays: int,
                  draws: np.ndarray, noise: float = 0.3) -> np.ndarray:
    """:func:`greedy_cover` on ``V = visible[candidates]`` as float32 and its ``rarity`` (computed once for many),
    with the uniform draws ``(k, len(candidates))`` of its steps given."""
    count = np.zeros(V.shape[1], dtype=np.float32)
    chosen: list[int] = []
    free = np.ones(len(candidates), dtype=bool)
    for step in range(k):
        short = np.maximum(min_rays - count, 0.0)
        w = short * rarity if short.any() else 1.0 / (1.0 + count)
        gain = (V @ w) * (1.0 + noise * draws[step])
        gain[~free] = -1.0
        c = int(np.argmax(gain))
        chosen.append(c)
        count += V[c]
        free[c] = False
        if not free.any():
            free[:] = True
    return candidates[np.array(chosen)]


def ring_genes(k: int, elevations_rad, distance_m: float, phase_rad: float = 0.0,
               counts: list[int] | None = None) -> np.ndarray:
    """``k`` stations on convergent rings looking at the centre; (k, N_GENES).

    Args:
        elevations_rad: one elevation per ring.
        distance_m: camera distance from the centre.
        phase_rad: azimuth of the first station of the first ring; the next ring is
            staggered by half its spacing.
        counts: stations per ring (sum k); None: as even as possible.
    """
    elevations = list(np.atleast_1d(elevations_rad))
    r = len(elevations)
    if counts is None:
        counts = [k // r + (1 if i < k % r else 0) for i in range(r)]
    rows = []
    for i, (el, c) in enumerate(zip(elevations, counts)):
        az = phase_rad + (i * np.pi / c if r > 1 else 0.0) + 2 * np.pi * np.arange(c) / c
        g = np.zeros((c, N_GENES))
        g[:, 0] = np.mod(az + np.pi, 2 * np.pi) - np.pi
        g[:, 1], g[:, 2] = el, distance_m
        rows.append(g)
    return np.vstack(rows)


def ring_sweep(k: int, sphere: ViewingSphere, *, elevation_step_rad: float = np.deg2rad(10.0),
               n_distances: int = 3, n_phases: int = 2, splits: tuple[float, ...] = (0.5,)) -> np.ndarray:
    """Single- and two-ring networks of ``k`` stations over a grid; (r, k, N_GENES).

    Elevations from the sphere's lower to upper bound in ``elevation_step_rad`` steps,
    ``n_distances`` distances across the band, ``n_phases`` phases over one station
    spacing, and for two rings the share ``splits`` of the stations on the lower ring.
    """
    lo = max(sphere.elevation_min_rad, np.deg2rad(5.0))
    els = np.arange(lo, min(sphere.elevation_max_rad, np.deg2rad(85.0)) + 1e-9, elevation_step_rad)
    dists = np.linspace(sphere.distance_min_m, sphere.distance_max_m, n_distances)
    out = []
    for d in dists:
        for ph in range(n_phases):
            phase = ph / n_phases * 2 * np.pi / k
            out += [ring_genes(k, [e], d, phase) for e in els]
            if k >= 4:
                for s in splits:
                    c1 = int(np.clip(round(s * k), 2, k - 2))
                    out += [ring_genes(k, [e1, e2], d, phase, [c1, k - c1])
                            for i, e1 in enumerate(els) for e2 in els[i + 1:]]
    return np.array(out)


def initial_population(valid_idx: np.ndarray, visible: np.ndarray, candidate_genes: np.ndarray, k: int, P: int,
                       mode: str, min_rays: int, rng: np.random.Generator,
                       greedy_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Initial networks: a fraction by :func:`greedy_cover`, the rest random distinct valid candidates.

    Args:
        valid_idx: (v,) int candidates allowed; visible: (m, n) bool over the targets
            searched; candidate_genes: (m, N_GENES) the database's stations.
        mode: "fixed" (all bits on) | "cheapest" (random density, at least ``min_rays``
            on; greedy networks there are built for a random station count).
    Returns:
        genes: (P, k, N_GENES), bits: (P, k) bool.
    """
    v = valid_idx
    if len(v) >= k:
        pick = v[np.argsort(rng.random((P, len(v))), axis=1)[:, :k]]
    else:
        pick = v[rng.integers(0, len(v), size=(P, k))]
    if mode == "fixed":
        bits = np.ones((P, k), dtype=bool)
    else:
        density = rng.uniform(min(1.0, min_rays / k), 1.0, size=(P, 1))
        bits = rng.random((P, k)) < density
        short = bits.sum(axis=1) < min_rays
        bits[short, :min_rays] = True
    n_greedy = int(round(greedy_fraction * P))
    if n_greedy:
        V = visible[v].astype(np.float32)
        rarity = 1.0 / np.maximum(V.sum(axis=0), 1.0)
    if mode == "fixed" and n_greedy > 1:
        # the covers' draws come one after the other from rng (the same stream as drawn step by step), so the
        # covers are independent: two at a time on two threads (the products release the GIL)
        draws = rng.random((n_greedy, k, len(v)))
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(2) as ex:
            covers = list(ex.map(lambda i: _greedy_cover(V, rarity, v, k, min_rays, draws[i]), range(n_greedy)))
        pick[:n_greedy] = np.array(covers)
        bits[:n_greedy] = True
        n_greedy = 0
    for i in range(n_greedy):
        size = k if mode == "fixed" else int(rng.integers(min_rays, k + 1))
        pick[i, :size] = _greedy_cover(V, rarity, v, size, min_rays, rng.random((size, len(v))))
        bits[i] = np.arange(k) < size
    return candidate_genes[pick].copy(), bits
