"""The network planner on a small synthetic scene with known geometry (fixed seeds)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from calibration.camera import Intrinsics
from calibration.errors import InputError, PlanningError
from planning.part import Part, Targets, sample_targets
from planning.planner import (
    NetworkPlan,
    PlannerOptions,
    build_database,
    cheapest_network,
    greedy_cover,
    plan_network,
)
from planning.plot import plot_plan
from planning.stations import N_GENES, ViewingSphere
from planning.uncertainty import covariance_for_network
from planning.visibility import VisibilityOptions, compute_visibility


def _box_part(n_targets: int = 60, seed: int = 0) -> Part:
    """A 0.20 x 0.15 x 0.08 m block with a 0.05 m tall step on top (self-occluding)."""
    base = trimesh.creation.box(extents=(0.20, 0.15, 0.08))
    base.apply_translation((0, 0, 0.04))
    step = trimesh.creation.box(extents=(0.06, 0.15, 0.05))
    step.apply_translation((0.07, 0, 0.105))
    mesh = trimesh.boolean.union([base, step], engine="manifold", check_volume=False)
    targets = sample_targets(mesh, n_targets, np.random.default_rng(seed), edge_clearance_m=0.004, min_normal_z=-0.1)
    return Part("block", mesh, targets)


def _bottom_target(part: Part) -> Part:
    """The part plus one target on its bottom face (normal -z): no station above can see it."""
    t = part.targets
    extra = Targets(
        ids=t.ids + ["BOTTOM"],
        xyz=np.vstack([t.xyz, [[0.0, 0.0, 0.0]]]),
        normals=np.vstack([t.normals, [[0.0, 0.0, -1.0]]]),
        kind=np.append(t.kind, "retro"),
        tolerance_m=np.append(t.tolerance_m, np.nan),
        code=np.append(t.code, -1),
    )
    return Part(part.name, part.mesh, extra)


@pytest.fixture(scope="module")
def scene():
    part = _box_part()
    intr = Intrinsics(fx_px=2000.0, fy_px=2000.0, cx_px=639.5, cy_px=511.5, width=1280, height=1024)
    return part, intr


def _options(**kw) -> PlannerOptions:
    base = dict(n_stations=8, min_rays=3, population=24, generations=25, stall_generations=25,
                n_candidates=450, sigma_px=0.1)
    base.update(kw)
    return PlannerOptions(**base)


@pytest.fixture(scope="module")
def fixed_plan(scene, tmp_path_factory):
    part, intr = scene
    cache = tmp_path_factory.mktemp("cache")
    stages = []
    plan = plan_network(part, intr, _options(), np.random.default_rng(3), cache_dir=cache,
                        progress=lambda s, f: stages.append((s, f)), seed=3)
    return plan, cache, stages


def test_fixed_plan_measures_every_target_with_min_rays_and_reports_exact_covariance(scene, fixed_plan):
    part, intr = scene
    plan, _, _ = fixed_plan
    assert len(plan.station_ids) == 8 and plan.part_from_cam.shape == (8, 4, 4)
    assert np.all(plan.n_rays >= 3)
    # the covariance is the exact one for the stations in the plan, recomputed from scratch
    vis = compute_visibility(part, intr, plan.part_from_cam, VisibilityOptions(incidence_max_rad=plan.incidence_max_rad))
    cov, n_rays = covariance_for_network(intr, plan.part_from_cam, part.targets.xyz, vis, 0.1, min_rays=3)
    assert np.array_equal(n_rays, plan.n_rays)
    assert np.allclose(cov, plan.cov, rtol=1e-9, atol=0)
    sig = np.sqrt(np.trace(cov, axis1=1, axis2=2))
    assert np.isclose(plan.predicted_sigma_max_m, sig.max()) and np.isclose(plan.predicted_sigma_mean_m, sig.mean())
    # seen_by names exactly the stations whose fresh visibility includes the target
    for j, ids in enumerate(plan.seen_by):
        assert ids == [plan.station_ids[i] for i in np.flatnonzero(vis[:, j])]
    # the stations are the poses of their genes
    sphere = ViewingSphere.for_part(part, intr)
    assert np.allclose(sphere.poses(plan.genes), plan.part_from_cam)


def test_history_records_every_generation_and_best_never_worsens(fixed_plan):
    plan, _, stages = fixed_plan
    best = [h["best"] for h in plan.history]
    assert len(best) == plan.search["generations"] + 1
    assert all(a >= b for a, b in zip(best, best[1:]))
    assert all(h["n_active"] == 8 for h in plan.history)
    names = [s for s, _ in stages]
    assert names[0].startswith("visibility") and "search" in names and names[-1] == "final"
    assert [f for s, f in stages if s == "search"][-1] == pytest.approx(1.0) or plan.search["stopped_because"] != "generations"


def test_same_seed_gives_the_same_plan(scene, fixed_plan):
    part, intr = scene
    plan, cache, _ = fixed_plan
    again = plan_network(part, intr, _options(), np.random.default_rng(3), cache_dir=cache, seed=3)
    assert np.array_equal(again.part_from_cam, plan.part_from_cam)
    assert again.predicted_sigma_max_m == plan.predicted_sigma_max_m
    other = plan_network(part, intr, _options(), np.random.default_rng(4), cache_dir=cache, seed=4)
    assert not np.array_equal(other.part_from_cam, plan.part_from_cam)


def test_planned_network_beats_random_networks_of_the_same_size(scene, fixed_plan):
    part, intr = scene
    plan, _, _ = fixed_plan
    sphere = ViewingSphere.for_part(part, intr)
    rng = np.random.default_rng(99)
    opts = VisibilityOptions(incidence_max_rad=plan.incidence_max_rad)
    worst = []
    for _ in range(30):
        g = np.zeros((8, N_GENES))
        g[:, 0] = rng.uniform(-np.pi, np.pi, 8)
        g[:, 1] = np.arcsin(rng.uniform(np.sin(sphere.elevation_min_rad), 1.0, 8))
        g[:, 2] = rng.uniform(sphere.distance_min_m, sphere.distance_max_m, 8)
        T = sphere.poses(g)
        cov, _ = covariance_for_network(intr, T, part.targets.xyz, compute_visibility(part, intr, T, opts), 0.1, 3)
        s = np.sqrt(np.trace(cov, axis1=1, axis2=2))
        worst.append(np.inf if np.any(~np.isfinite(s)) else s.max())
    assert plan.predicted_sigma_max_m < 0.5 * np.median(worst)
    assert plan.predicted_sigma_max_m <= min(worst)


def test_unreachable_candidates_are_never_used(scene, fixed_plan):
    part, intr = scene
    _, cache, _ = fixed_plan
    db = build_database(part, intr, _options(), cache)
    # the robot cannot reach a 1.5 rad wedge of azimuths, where the unconstrained plan puts stations
    reachable = ~((db.genes[:, 0] > -0.5) & (db.genes[:, 0] < 1.0))
    assert not np.all(reachable[db.nearest(fixed_plan[0].genes)])
    plan = plan_network(part, intr, _options(), np.random.default_rng(5), reachable=reachable, db=db)
    assert np.all(reachable[db.nearest(plan.genes)])
    assert np.all(plan.n_rays >= 3)
    with pytest.raises(PlanningError, match="aligned"):
        plan_network(part, intr, _options(), np.random.default_rng(5), reachable=reachable[:-1], db=db)
    with pytest.raises(InputError, match="other visibility options"):
        plan_network(part, intr, _options(incidence_max_rad=1.0), np.random.default_rng(5), db=db)


def test_plan_dict_has_the_contract_keys_and_round_trips(fixed_plan):
    plan, _, _ = fixed_plan
    d = json.loads(json.dumps(plan.to_plan_dict(), allow_nan=False))
    for key in ("seed", "criterion", "camera", "min_rays", "incidence_max_rad", "stations", "targets",
                "predicted_sigma_max_m", "predicted_sigma_mean_m"):
        assert key in d
    assert set(d["camera"]) >= {"fx_px", "fy_px", "cx_px", "cy_px", "width", "height", "sigma_px"}
    assert d["seed"] == 3 and d["criterion"] == "worst" and d["min_rays"] == 3
    assert {"id", "part_from_cam"} <= set(d["stations"][0]) and np.shape(d["stations"][0]["part_from_cam"]) == (4, 4)
    t0 = d["targets"][0]
    assert {"id", "xyz", "normal", "seen_by", "predicted_cov"} <= set(t0)
    assert np.isclose(np.sqrt(np.trace(t0["predicted_cov"])), plan.sigma[0])
    assert np.isclose(d["predicted_sigma_max_m"], max(np.sqrt(np.trace(t["predicted_cov"])) for t in d["targets"]))
    back = NetworkPlan.from_plan_dict(d)
    assert back.station_ids == plan.station_ids and back.target_ids == plan.target_ids
    assert np.array_equal(back.part_from_cam, plan.part_from_cam) and np.array_equal(back.cov, plan.cov)
    assert back.seen_by == plan.seen_by and back.intrinsics == plan.intrinsics
    assert back.predicted_sigma_max_m == plan.predicted_sigma_max_m


def test_reading_a_broken_plan_dict_raises_input_error(fixed_plan):
    d = fixed_plan[0].to_plan_dict()
    del d["stations"]
    with pytest.raises(InputError, match="plan.json"):
        NetworkPlan.from_plan_dict(d)


def test_cheapest_network_is_the_smallest_on_the_front_that_meets_the_requirement(scene, fixed_plan):
    part, intr = scene
    plan8, cache, _ = fixed_plan
    # a requirement the 8-station plan meets with some margin
    required = 1.3 * plan8.predicted_sigma_max_m
    opts = _options(n_stations=10, population=40, generations=40, stall_generations=40, required_sigma_m=required)
    plan = cheapest_network(part, intr, opts, np.random.default_rng(7), cache_dir=cache)
    k = len(plan.station_ids)
    assert plan.mode == "cheapest" and 3 <= k <= 10
    assert np.all(plan.sigma <= required) and np.all(plan.n_rays >= 3)
    front = [r for r in plan.pareto_front if r["phase"] == "front"]
    refine = [r for r in plan.pareto_front if r["phase"] == "refine"]
    counts = [r["n_stations"] for r in front]
    ratios = [r["sigma_ratio_max"] for r in front]
    # non-dominated: sorted by count, more stations buy strictly better precision
    assert counts == sorted(counts) and all(a > b for a, b in zip(ratios, ratios[1:]))
    # the smallest front network meeting it (the front search has no exchange descent, so with a
    # tight requirement only the refining fixed-size searches may meet it)
    first_ok = min((c for c, f in zip(counts, ratios) if f <= 1.0), default=opts.n_stations)
    assert k <= first_ok
    if k < first_ok:  # a refining search found a smaller network that meets the requirement
        assert any(r["n_stations"] == k and r["sigma_ratio_max"] <= 1.0 for r in refine)
    # the refinement stopped because one station fewer failed (or its budget ran out)
    tried_below = [r for r in refine if r["n_stations"] == k - 1]
    assert (tried_below and tried_below[0]["sigma_ratio_max"] > 1.0) or len(refine) == opts.cheapest_refine
    # a looser requirement never needs more stations
    loose = cheapest_network(part, intr, opts.__class__(**{**opts.__dict__, "required_sigma_m": 3 * required}),
                             np.random.default_rng(7), cache_dir=cache)
    assert len(loose.station_ids) <= k


def test_cheapest_network_derives_the_requirement_from_tolerances(scene, fixed_plan):
    part, intr = scene
    _, cache, _ = fixed_plan
    opts = _options(n_stations=10, mode="cheapest", default_tolerance_m=10 * 2 * fixed_plan[0].predicted_sigma_max_m)
    plan = plan_network(part, intr, opts, np.random.default_rng(2), cache_dir=cache)
    assert np.allclose(plan.required_sigma_m, 2 * fixed_plan[0].predicted_sigma_max_m)
    assert np.all(plan.sigma <= plan.required_sigma_m)
    with pytest.raises(InputError, match="required precision"):
        plan_network(part, intr, _options(mode="cheapest"), np.random.default_rng(2), cache_dir=cache)


def test_an_unreachable_precision_raises_planning_error(scene, fixed_plan):
    part, intr = scene
    _, cache, _ = fixed_plan
    opts = _options(n_stations=5, mode="cheapest", required_sigma_m=1e-9, generations=5)
    with pytest.raises(PlanningError, match="no network of at most 5 stations"):
        plan_network(part, intr, opts, np.random.default_rng(2), cache_dir=cache)


def test_a_target_no_station_can_see_is_an_error_unless_allowed(scene, tmp_path):
    part, intr = scene
    part2 = _bottom_target(part)
    with pytest.raises(PlanningError, match="BOTTOM"):
        plan_network(part2, intr, _options(generations=3), np.random.default_rng(0), cache_dir=tmp_path)
    plan = plan_network(part2, intr, _options(generations=3, allow_unmeasurable=True), np.random.default_rng(0),
                        cache_dir=tmp_path)
    assert plan.unmeasurable_target_ids == ["BOTTOM"]
    j = plan.target_ids.index("BOTTOM")
    assert plan.n_rays[j] == 0 and np.all(np.isnan(plan.cov[j]))
    d = json.loads(json.dumps(plan.to_plan_dict(), allow_nan=False))
    assert d["targets"][j]["predicted_cov"] is None


def test_bad_options_raise_input_error(scene):
    part, intr = scene
    for bad in (dict(mode="best"), dict(criterion="median"), dict(min_rays=1), dict(n_stations=2),
                dict(incidence_max_rad=2.0)):
        with pytest.raises(InputError):
            plan_network(part, intr, _options(**bad), np.random.default_rng(0))


def test_greedy_cover_reaches_min_rays_when_enough_stations_exist():
    rng = np.random.default_rng(0)
    # 40 candidates x 30 targets, each target seen by exactly 4 candidates arranged in blocks of 10 targets
    vis = np.zeros((40, 30), dtype=bool)
    for c in range(40):
        vis[c, (c % 3) * 10:(c % 3) * 10 + 10] = rng.random() < 0.3 or c < 12
    cand = np.arange(40)
    chosen = greedy_cover(vis, cand, 9, 3, rng)
    assert len(set(chosen.tolist())) == 9
    assert np.all(vis[chosen].sum(axis=0) >= 3)


def test_plot_plan_writes_a_picture(scene, fixed_plan, tmp_path):
    import matplotlib.image as mpimg

    part, _ = scene
    path = plot_plan(part, fixed_plan[0], tmp_path / "plan.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = mpimg.imread(path)
    assert img.shape[0] > 500 and img.shape[1] > 700
    assert img[..., :3].std() > 0.05  # not a blank canvas
    assert not list(tmp_path.glob("*.tmp"))


def test_a_network_too_small_for_min_rays_is_an_error_not_a_silent_plan(scene, fixed_plan):
    part, intr = scene
    _, cache, _ = fixed_plan
    # three stations would each have to see every target, including all four side faces
    with pytest.raises(PlanningError, match=r"raise \[planning\] n_stations or lower \[planning\] min_rays"):
        plan_network(part, intr, _options(n_stations=3, generations=10), np.random.default_rng(0), cache_dir=cache)


# --- exchange descent (planning.refine) and seeds (planning.seeding) ---------------------------


def _random_database(m: int = 14, n: int = 9, seed: int = 0):
    """Random per-candidate information ``J^T J`` (2x3 Jacobians) and visibility."""
    from planning.uncertainty import _IU

    rng = np.random.default_rng(seed)
    vis = rng.random((m, n)) < 0.6
    J = rng.normal(size=(m, n, 2, 3))
    info = np.einsum("mnri,mnrj->mnij", J, J)[:, :, _IU[0], _IU[1]] * vis[..., None]
    return info.astype(np.float32), vis


def _brute_worst(info, vis, S, min_rays):
    from planning.refine import network_sigma

    return float(network_sigma(info, vis, np.asarray(S), min_rays).max())


def test_exchange_descent_ends_where_no_single_exchange_improves_the_worst():
    from planning.refine import swap_descent

    for seed in range(4):
        info, vis = _random_database(seed=seed)
        allowed = np.arange(len(vis))
        start = np.array([0, 1, 2, 3])
        r = swap_descent(info, vis, allowed, start, 2)
        assert np.isfinite(r.worst) and r.worst <= _brute_worst(info, vis, start, 2) or not np.isfinite(r.start_worst)
        worst = [h["worst"] for h in r.history]
        assert all(a >= b for a, b in zip(worst, worst[1:]))
        # brute force over every single exchange: none lowers the worst (the pruning is exact)
        for i in range(len(r.stations)):
            for c in np.setdiff1d(allowed, r.stations):
                S = r.stations.copy()
                S[i] = c
                assert _brute_worst(info, vis, S, 2) >= r.worst * (1 - 1e-5)


def test_iterated_exchange_descent_finds_the_brute_force_optimum_of_a_small_network():
    from itertools import combinations

    from planning.refine import refine_network

    info, vis = _random_database(m=12, n=8, seed=7)
    best = min(_brute_worst(info, vis, S, 2) for S in combinations(range(12), 3))
    r = refine_network(info, vis, np.arange(12), np.array([[0, 1, 2]]), 2, np.random.default_rng(0), n_kicks=10)
    assert r.worst == pytest.approx(best, rel=1e-5)
    assert r.worst <= r.start_worst


def test_exchange_descent_repairs_a_network_that_leaves_targets_short_of_rays():
    from planning.refine import swap_descent

    vis = np.zeros((6, 4), dtype=bool)
    vis[0, :2] = vis[1, :2] = True  # the start sees targets 0, 1 only
    vis[2:, :] = True
    info, _ = _random_database(m=6, n=4, seed=1)
    info = info * vis[..., None]
    r = swap_descent(info, vis, np.arange(6), np.array([0, 1]), 2)
    assert np.isinf(r.start_worst) and np.isfinite(r.worst)
    assert np.all(vis[r.stations].sum(axis=0) >= 2)


def test_ring_networks_put_evenly_spaced_stations_on_their_elevations():
    from planning.seeding import ring_genes

    g = ring_genes(10, np.deg2rad([20.0, 60.0]), 0.8, phase_rad=0.1, counts=[4, 6])
    assert g.shape == (10, N_GENES)
    assert np.allclose(g[:4, 1], np.deg2rad(20)) and np.allclose(g[4:, 1], np.deg2rad(60)) and np.allclose(g[:, 2], 0.8)
    az1 = np.sort(np.mod(g[:4, 0] - 0.1, 2 * np.pi))
    assert np.allclose(np.diff(az1), np.pi / 2) and np.isclose(az1[0], 0.0)
    az2 = np.sort(np.mod(g[4:, 0] - 0.1 - np.pi / 6, 2 * np.pi))  # staggered by half its spacing
    assert np.allclose(np.diff(az2), np.pi / 3) and np.isclose(az2[0], 0.0, atol=1e-9)


def test_plan_is_no_worse_than_the_best_ring_and_refinement_improves_on_the_search(scene, fixed_plan):
    from planning.planner import _Problem, _best_rings
    from planning.uncertainty import target_information

    part, intr = scene
    plan, cache, _ = fixed_plan
    db = build_database(part, intr, _options(), cache)
    info = target_information(intr, db.part_from_cam, part.targets.xyz, db.visible, 0.1)
    problem = _Problem(db, info, db.visible, db.visible.any(axis=1), _options(), None)
    rings = _best_rings(problem, 8, db.sphere, 4)
    ev = problem(rings, np.ones((4, 8), dtype=bool))
    feasible = ev.violation <= 0
    assert plan.search["search_fitness"] <= np.min(np.where(feasible, ev.objectives[:, 0], np.inf)) + 1e-12
    # the exchange descent ran and did not make the search's best worse
    assert plan.search["exchange_to"] <= plan.search["exchange_from"]
    plain = plan_network(part, intr, _options(refine_starts=0, ring_seeds=0), np.random.default_rng(3), db=db, seed=3)
    assert "exchange_swaps" not in plain.search
    assert plan.predicted_sigma_max_m <= plain.predicted_sigma_max_m * (1 + 1e-9)


def test_exact_polish_lowers_the_worst_target_and_its_figure_is_the_exact_one(scene, fixed_plan):
    from planning.polish import polish_network

    part, intr = scene
    plan, cache, _ = fixed_plan
    db = build_database(part, intr, _options(), cache)
    vis_opts = _options().visibility_options()
    cols = np.arange(len(part.targets.xyz))
    # start from the plan without the polish (the search + exchange descent on the database)
    raw = plan_network(part, intr, _options(polish_rounds=0), np.random.default_rng(3), db=db, seed=3)
    assert "polish_to" not in raw.search
    r = polish_network(part, intr, db.sphere, vis_opts, raw.genes, cols, 3, 0.1,
                       step_rad=0.05, step_m=0.02, offset_m=0.01, rounds=6)
    assert r.start_worst == pytest.approx(raw.predicted_sigma_max_m, rel=1e-6)
    assert r.worst < r.start_worst  # strictly better on this scene
    # the polished figure is what fresh ray casting + float64 propagation gives at those poses
    T = db.sphere.poses(r.genes)
    cov, n_rays = covariance_for_network(intr, T, part.targets.xyz, compute_visibility(part, intr, T, vis_opts),
                                         0.1, min_rays=3)
    assert np.all(n_rays >= 3)
    assert np.max(np.sqrt(np.trace(cov, axis1=1, axis2=2))) == pytest.approx(r.worst, rel=1e-6)
    # the planner's default runs it and reports the polished network
    assert plan.search["polish_to"] <= plan.search["polish_from"]
    assert plan.predicted_sigma_max_m <= raw.predicted_sigma_max_m * (1 + 1e-9)


def test_lower_bound_lies_below_the_searched_network_and_proves_station_counts(scene, fixed_plan):
    """planning.bound on the planner's database: every database network is at least as bad as the bound."""
    part, intr = scene
    plan8, cache, _ = fixed_plan
    plan = plan_network(part, intr, _options(lower_bound=True, polish_rounds=0), np.random.default_rng(3),
                        cache_dir=cache, seed=3)
    s = plan.search
    # the search's own figure is a network on the database: never below the bound
    assert s["lower_bound_sigma_m"] <= s["search_fitness"] * (1 + 1e-5)
    assert s["lower_bound_sigma_m"] >= 0.8 * s["search_fitness"], "a bound far below any plan says nothing"
    assert s["plan_over_lower_bound"] == pytest.approx(plan.predicted_sigma_max_m / s["lower_bound_sigma_m"])
    assert "bound_s" in plan.timing
    # cheapest: is one station fewer than the plan's count provably not enough?
    required = 1.3 * plan8.predicted_sigma_max_m
    opts = _options(n_stations=10, population=40, generations=40, stall_generations=40, required_sigma_m=required,
                    mode="cheapest", lower_bound=True)
    cheap = plan_network(part, intr, opts, np.random.default_rng(7), cache_dir=cache)
    c = cheap.search
    assert c["fewer_stations"] == len(cheap.station_ids) - 1
    if c["fewer_stations_cannot_meet"]:
        assert c["fewer_stations_lower_bound_ratio"] > 1.0
        assert not any(r["n_stations"] == c["fewer_stations"] and r["sigma_ratio_max"] <= 1.0
                       for r in cheap.pareto_front)


def test_plan_counts_its_weakly_linked_stations_as_adjust_would_see_them(scene, tmp_path):
    """search.exact_unlinked: stations outside the main block of images sharing link_targets targets, or alone
    linking a part of it (planning.kernels.unlinked_stations), recounted here from the plan's own rays
    (docs/decisions/0031)."""
    from planning import kernels

    part, intr = scene
    plan = plan_network(part, intr, _options(link_targets=8), cache_dir=tmp_path, seed=3)
    vis = np.array([[sid in seen for seen in plan.seen_by] for sid in plan.station_ids])
    k = len(plan.station_ids)
    assert plan.search["link_targets"] == 8
    assert plan.search["exact_unlinked"] == kernels.count_unlinked(kernels.pack_rows(vis), np.arange(k)[None], 8)[0]
    # 60 targets on a stepped block: 8 stations can be one block with no sole link
    assert plan.search["exact_unlinked"] == 0
    assert kernels.count_unlinked(kernels.pack_rows(vis), np.arange(k)[None], 10**6, sole_links=False)[0] == k - 1


def test_a_plan_ranked_by_the_detector_model_reports_its_covariance_with_the_model(scene, tmp_path):
    """image_precision: the search and the exact check weigh each ray by the detector model; plan.cov is the
    model-weighted limiting error propagation of the plan's own rays, and the plan says how it was ranked."""
    from planning.uncertainty import ImagePrecision

    part, intr = scene
    prec = ImagePrecision(np.asarray(part.targets.normals), 0.005)
    plan = plan_network(part, intr, _options(image_precision=prec), cache_dir=tmp_path, seed=4)
    assert plan.search["image_precision"].startswith("detector model version")
    vis = np.array([[sid in seen for seen in plan.seen_by] for sid in plan.station_ids])
    cov, n_rays = covariance_for_network(intr, plan.part_from_cam, part.targets.xyz, vis, prec, min_rays=3)
    np.testing.assert_allclose(plan.cov, cov, rtol=1e-9)
    one_sigma, _ = covariance_for_network(intr, plan.part_from_cam, part.targets.xyz, vis, 0.1, min_rays=3)
    r = np.trace(plan.cov, axis1=1, axis2=2) / np.trace(one_sigma, axis1=1, axis2=2)
    assert r.max() / r.min() > 1.2  # each ray weighed on its own, not one sigma rescaled
