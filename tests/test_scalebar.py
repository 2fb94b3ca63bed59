"""PLAN secures the scale bar's ends (planning/scalebar.py): stations added after the search where the ends fall
short of the requirement, none where they meet it, and one line saying so where no candidate can meet it."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.camera import Intrinsics
from planning.planner import build_database, cheapest_network, plan_network
from planning.scalebar import (
    AZIMUTH_GAP_MAX_DEG,
    RAYS_FACTOR,
    azimuth_gap_deg,
    bar_warnings,
    covariance_with,
    secure_scale_bar,
    trusted_views,
)
from planning.uncertainty import covariance_for_network
from tests.test_planner import _box_part, _options


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    part = _box_part()
    intr = Intrinsics(fx_px=2000.0, fy_px=2000.0, cx_px=639.5, cy_px=511.5, width=1280, height=1024)
    return part, intr, tmp_path_factory.mktemp("cache")


def _far_pair(part, among: np.ndarray) -> tuple[int, int, float]:
    """The two top-facing targets of ``among`` furthest apart (as tests/partgen.py picks a bar's ends)."""
    t = part.targets
    top = np.asarray([k for k in among if t.normals[k, 2] > 0.9])
    d = np.linalg.norm(t.xyz[top][:, None] - t.xyz[top][None], axis=2)
    i, j = np.unravel_index(np.argmax(d), d.shape)
    return int(top[i]), int(top[j]), float(d[i, j])


def _length_sigma(cov: np.ndarray, xyz: np.ndarray, a: int, b: int) -> float:
    u = (xyz[a] - xyz[b]) / np.linalg.norm(xyz[a] - xyz[b])
    return float(np.sqrt(u @ (cov[a] + cov[b]) @ u))


def test_weak_bar_end_gets_stations_and_meets_the_requirement(scene):
    part, intr, cache = scene
    a, b, L = _far_pair(part, np.arange(len(part.targets.ids)))
    plain = plan_network(part, intr, _options(), np.random.default_rng(3), cache_dir=cache, seed=3)
    assert min(plain.n_rays[[a, b]]) < RAYS_FACTOR * 3  # the search alone leaves an end weak
    p = plan_network(part, intr, _options(scale_bars=((a, b, L, 2e-6),)), np.random.default_rng(3), cache_dir=cache,
                     seed=3)
    bar = p.scale_bars[0]
    k = len(plain.station_ids)
    added = [s["id"] for s in bar["stations_added"]]
    # the search's own stations are kept station for station; the added ones come after them
    assert p.station_ids[:k] == plain.station_ids and np.array_equal(p.part_from_cam[:k], plain.part_from_cam)
    assert added and p.station_ids[k:] == added and len(p.station_ids) == k + len(added)
    assert not bar["before"]["met"] and bar["met"] and bar["after"]["met"] and "note" not in bar
    # the requirement, checked independently on the final network (fresh ray casting, exact covariance over the
    # rays the bar counts on)
    visible, cov_all, _ = covariance_with(intr, _options(), part, p.part_from_cam)
    t = part.targets
    vis = visible.copy()
    vis[:, [a, b]] = trusted_views(intr, p.part_from_cam, t.xyz[[a, b]], t.normals[[a, b]], visible[:, [a, b]],
                                   _options().incidence_max_rad)
    cov, n_rays = covariance_for_network(intr, p.part_from_cam, t.xyz, vis, 0.1, min_rays=3)
    req = bar["requirement"]
    assert min(n_rays[a], n_rays[b]) >= req["rays_min"] == RAYS_FACTOR * 3
    assert _length_sigma(cov, part.targets.xyz, a, b) <= req["length_sigma_max_m"]
    assert _length_sigma(cov, part.targets.xyz, a, b) == pytest.approx(bar["after"]["length_sigma_m"], rel=1e-6)
    for e, g in zip((a, b), req["azimuth_gap_goal_deg"]):
        assert azimuth_gap_deg(p.part_from_cam[vis[:, e], :3, 3], t.xyz[e], t.normals[e]) <= g
    # the stations only add information: no target's predicted sigma got worse
    assert np.all(p.sigma <= plain.sigma * (1 + 1e-9))
    assert len(p.seen_by[a]) >= n_rays[a] and p.to_plan_dict()["scale_bar"]["ends"] == [part.targets.ids[a],
                                                                                        part.targets.ids[b]]
    # a network that meets it gets nothing more (the reference: the search's network, as in the plan)
    db = build_database(part, intr, _options(), cache)
    more, doc = secure_scale_bar(part, intr, _options(), db, db.visible.any(axis=1), p.part_from_cam, visible,
                                 plain.cov, np.arange(len(cov)), (a, b, L, 2e-6))
    assert more.size == 0 and doc["met"]


def test_plan_already_meeting_the_requirement_is_unchanged_station_for_station(scene):
    part, intr, cache = scene
    plain = plan_network(part, intr, _options(n_stations=24), np.random.default_rng(3), cache_dir=cache, seed=3)
    t = part.targets
    vis = trusted_views(intr, plain.part_from_cam, t.xyz, t.normals,
                        covariance_with(intr, _options(), part, plain.part_from_cam)[0], _options().incidence_max_rad)
    eyes = plain.part_from_cam[:, :3, 3]
    sure = [k for k in np.flatnonzero(vis.sum(axis=0) >= RAYS_FACTOR * 3)
            if azimuth_gap_deg(eyes[vis[:, k]], t.xyz[k], t.normals[k]) <= AZIMUTH_GAP_MAX_DEG]
    a, b, L = _far_pair(part, np.asarray(sure))
    # a bar of a loose certificate (40 um): the ends' length part may be as large (the network's own reference
    # is below it), and their rays and spread are already there
    p = plan_network(part, intr, _options(n_stations=24, scale_bars=((a, b, L, 40e-6),)), np.random.default_rng(3),
                     cache_dir=cache, seed=3)
    assert p.scale_bars[0]["before"]["met"] and p.scale_bars[0]["met"] and p.scale_bars[0]["stations_added"] == []
    assert p.station_ids == plain.station_ids and np.array_equal(p.part_from_cam, plain.part_from_cam)
    assert np.array_equal(p.cov, plain.cov, equal_nan=True)
    level, line = bar_warnings(p.scale_bars[0])[0]
    assert level == "info" and "0 station(s) added" in line


def test_bar_end_no_candidate_can_serve_is_said_in_one_line_and_the_plan_goes_on(scene):
    part, intr, cache = scene
    a, b, L = _far_pair(part, np.arange(len(part.targets.ids)))
    db = build_database(part, intr, _options(), cache)
    t = part.targets
    sees_b = np.flatnonzero(trusted_views(intr, db.part_from_cam, t.xyz[[b]], t.normals[[b]], db.visible[:, [b]],
                                          _options().incidence_max_rad)[:, 0])
    # the robot reaches only 5 of the candidates that see end b (5 < 2 x min_rays): no choice can meet the rays
    reachable = ~db.visible[:, b]
    reachable[sees_b[np.argsort(-db.visible[sees_b].sum(axis=1))[:5]]] = True
    p = plan_network(part, intr, _options(scale_bars=((a, b, L, 2e-6),)), np.random.default_rng(3), reachable=reachable,
                     cache_dir=cache, seed=3, db=db)
    bar = p.scale_bars[0]
    assert not bar["met"] and bar["best_achievable"]["rays"][1] == 5 and bar["after"]["rays"][1] == 5
    assert bar["candidates_seeing_end"][1] == 5
    lines = bar_warnings(bar)
    # the two about the rays, then one about an edge next to an end when the far pair has one (planning.clear_area)
    near = [e["target"] for e in bar["ends_clear"] if not e["clear"]]
    assert [lv for lv, _ in lines] == ["warning", "warning"] + (["warning"] if near else [])
    assert all(t in lines[2][1] and "edge of the part" in lines[2][1] for t in near)
    assert "requirement NOT met" in lines[0][1] and "best achievable" in lines[0][1] and "\n" not in lines[0][1]
    assert bar["note"] == lines[0][1]
    assert part.targets.ids[b] in lines[1][1] and f"{part.targets.ids[a]}-{part.targets.ids[b]}" in lines[1][1]
    # every station added is one of the candidates the robot reaches; the network measures end b 5 times
    k = len(bar["stations_added"])
    for T in p.part_from_cam[len(p.station_ids) - k:]:
        hit = np.flatnonzero(np.all(np.abs(db.part_from_cam - T).reshape(len(db.part_from_cam), -1) < 1e-12, axis=1))
        assert hit.size and reachable[hit].all()
    _, n_rays = covariance_for_network(intr, p.part_from_cam, part.targets.xyz,
                                       covariance_with(intr, _options(), part, p.part_from_cam)[0], 0.1, min_rays=3)
    assert n_rays[b] == 5 and k > 0 and bar["after"]["length_sigma_m"] < bar["before"]["length_sigma_m"]


def test_cell_check_names_the_bar_when_an_end_has_few_sure_views_or_none(tmp_path):
    from tests.jobutil import job_variant, run_cell

    # cameras no lower than 40 deg: the bar's ends (on the example's side faces) have few views well inside the
    # image and 10 deg below the incidence limit; a warning names the bar, the check passes
    job = job_variant(tmp_path / "low", {"planning": {"elevation_min_deg": 40.0}})
    r = run_cell("check", str(job), timeout=300)
    assert r.code == 0, r.stderr[-2000:]
    bar = r.doc["measurability"]["scale_bars"][0]
    assert bar["ends"] == ["T0094", "T0100"] and bar["rays_min"] == 6 and min(bar["candidates"]) < 6
    assert "scale bar T0094-T0100" in bar["warning"] and "T0100 (" in bar["warning"]
    # no lower than 45 deg: T0100 cannot be seen by min_rays stations at all: one line naming the bar, exit 2
    job = job_variant(tmp_path / "high", {"planning": {"elevation_min_deg": 45.0}})
    r = run_cell("check", str(job), timeout=300)
    assert r.code == 2 and r.doc["error"] == "JobSpecError" and "\n" not in r.doc["message"].strip()
    line = r.doc["message"]
    assert "the end(s) T0100 of the scale bar T0094-T0100" in line and "scale cannot be established" in line


def test_extra_stations_judge_a_target_along_a_direction_when_asked():
    from planning.augment import plan_extra_stations

    # one target measured with information diag(1, 4, 9) (sigma along x 1, along z 1/3); candidates add along x
    N_have = np.array([[1.0, 0, 0, 4.0, 0, 9.0]])
    info = np.array([[[3.0, 0, 0, 0, 0, 0]], [[0, 0, 0, 0, 0, 90.0]]])
    vis, ok = np.ones((2, 1), bool), np.ones(2, bool)
    along_x = plan_extra_stations(N_have, np.array([3]), np.array([0.6]), info, vis, ok, min_rays=3, max_new=2,
                                  along=np.array([[1.0, 0, 0]]))
    assert along_x.sigma_before[0] == pytest.approx(1.0) and list(along_x.added) == [0]
    assert along_x.sigma_after[0] == pytest.approx(0.5)
    along_z = plan_extra_stations(N_have, np.array([3]), np.array([0.6]), info, vis, ok, min_rays=3, max_new=2,
                                  along=np.array([[0, 0, 1.0]]))
    assert along_z.sigma_before[0] == pytest.approx(1 / 3) and along_z.added.size == 0
    trace = plan_extra_stations(N_have, np.array([3]), np.array([0.6]), info, vis, ok, min_rays=3, max_new=2)
    assert trace.sigma_before[0] == pytest.approx(np.sqrt(1 + 1 / 4 + 1 / 9))


def test_cheapest_mode_gets_the_bar_stations_after_its_search(scene):
    part, intr, cache = scene
    a, b, L = _far_pair(part, np.arange(len(part.targets.ids)))
    kw = dict(n_stations=10, population=40, generations=40, stall_generations=40, required_sigma_m=60e-6)
    plain = cheapest_network(part, intr, _options(**kw), np.random.default_rng(3), cache_dir=cache, seed=3)
    p = cheapest_network(part, intr, _options(**kw, scale_bars=((a, b, L, 2e-6),)), np.random.default_rng(3),
                         cache_dir=cache, seed=3)
    k, added = len(plain.station_ids), p.scale_bars[0]["stations_added"]
    assert p.mode == "cheapest" and added and len(p.station_ids) == k + len(added)
    assert np.array_equal(p.part_from_cam[:k], plain.part_from_cam) and p.scale_bars[0]["met"]
    assert np.all(p.sigma <= np.asarray(p.required_sigma_m) * (1 + 1e-9))  # still meets the search's requirement


def test_renders_that_lose_a_bar_end_are_said():
    from planning.scalebar import rendered_rays_note

    doc = {"ends": ["A", "B"], "requirement": {"rays_min": 6}, "after": {"rays": [10, 8]}}
    assert rendered_rays_note(doc, [7, 6]) == [] and doc["rendered_rays"] == [7, 6]
    (level, line), = rendered_rays_note(doc, [3, 9])
    assert level == "warning" and "scale bar A-B" in line and "A in 3 image(s) (10 sure views planned)" in line
    assert "B in" not in line and doc["rendered_rays"] == [3, 9]


def test_every_bar_of_several_gets_its_ends_secured_and_plan_json_lists_them(scene):
    """Two bars (the far top pair, and a second pair of other top targets): each is secured after the search, bar
    after bar, and judged on the final network; plan.json carries ``scale_bars`` (and ``scale_bar`` only for one)."""
    part, intr, cache = scene
    a, b, L = _far_pair(part, np.arange(len(part.targets.ids)))
    rest = np.setdiff1d(np.arange(len(part.targets.ids)), [a, b])
    c, d, L2 = _far_pair(part, rest)
    p = plan_network(part, intr, _options(scale_bars=((a, b, L, 2e-6), (c, d, L2, 2e-6))), np.random.default_rng(3),
                     cache_dir=cache, seed=3)
    ids = part.targets.ids
    assert [bar["ends"] for bar in p.scale_bars] == [[ids[a], ids[b]], [ids[c], ids[d]]]
    assert all(bar["met"] and bar["after"]["met"] for bar in p.scale_bars)
    doc = p.to_plan_dict()
    assert len(doc["scale_bars"]) == 2 and "scale_bar" not in doc
    # the stations added for each bar are the plan's last ones, in the bars' order, none twice
    added = [s["id"] for bar in p.scale_bars for s in bar["stations_added"]]
    assert added == p.station_ids[len(p.station_ids) - len(added):] and len(set(added)) == len(added)
    # every end has its rays on the final network
    visible, _, _ = covariance_with(intr, _options(), part, p.part_from_cam)
    t = part.targets
    for e in (a, b, c, d):
        sure = trusted_views(intr, p.part_from_cam, t.xyz[[e]], t.normals[[e]], visible[:, [e]],
                             _options().incidence_max_rad)
        assert sure.sum() >= RAYS_FACTOR * 3
