"""Hampered first networks on the simulated cell: a fixture the plan did not know, glare, a station the robot
cannot reach. MEASURE leaves what it cannot name with certainty unnamed (with the reason), ADJUST leaves out
what it cannot use (with the reason) instead of faulting, and CLOSE_LOOP adds stations until every reachable
target meets its requirement; the measured coordinates agree with the simulated truth within their stated
covariance. Plus the kernels of those checks on data with a known answer."""
from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from jobutil import REPO, child_env, job_variant, mahalanobis, records, rigid_fit, run_cell, truth_xyz_m
from scipy.stats import chi2

from calibration.bundle.synthetic import simulate_network
from calibration.camera import Intrinsics, invert, look_at
from calibration.targets import ellipse_moments, shape_ratios
from cell.stages.screen import GROSS_PX, screen_network
from planning.augment import _sigma, plan_extra_stations

REQUIRED_MM = 0.016  # the example's 16-station plan predicts 13 um at worst: met when nothing hampers it
FIXTURE = [{"name": "clamp", "size": [20.0, 120.0, 20.0], "pose": {"xyz": [-40.0, 0.0, 110.0]}}]


# --- kernels --------------------------------------------------------------------------------------------
def _disc_moments(radius_px: float, keep=lambda x, y: np.ones_like(x, dtype=bool), n: int = 400) -> np.ndarray:
    """Second moments of a uniformly bright disc sampled on a fine grid, only where ``keep``."""
    g = np.linspace(-radius_px, radius_px, n)
    x, y = np.meshgrid(g, g)
    m = (x**2 + y**2 <= radius_px**2) & keep(x, y)
    x, y = x[m] - x[m].mean(), y[m] - y[m].mean()
    return np.array([[np.mean(x * x), np.mean(x * y)], [np.mean(x * y), np.mean(y * y)]])


def test_shape_ratios_accept_a_whole_dot_and_reject_a_clipped_or_merged_one():
    intr = Intrinsics(2300.0, 2300.0, 1223.5, 1023.5, 2448, 2048)
    T = invert(look_at(np.array([0.0, 0.0, 0.5]), np.zeros(3)))
    pred = ellipse_moments(intr, T, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), 0.0025)
    r_px = 2300.0 * 0.0025 / 0.5  # a face-on disc of 11.5 px radius: moments r^2/4
    assert pred[0] == pytest.approx(np.eye(2) * r_px**2 / 4, rel=1e-6)
    whole = _disc_moments(r_px)
    clipped = _disc_moments(r_px, lambda x, y: x < 0.3 * r_px)  # a fixture's edge across the dot
    merged = _disc_moments(r_px) + np.diag([(0.8 * r_px) ** 2, 0.0])  # two dots run together
    lo, hi = shape_ratios(np.stack([whole, clipped, merged]), np.repeat(pred, 3, axis=0), blur_px=1.0)
    assert 0.97 < lo[0] <= 1.01 and hi[0] <= 1.01
    assert lo[1] < 0.85  # clipped: shrinks across the cut
    assert hi[2] > 1.5  # merged: grows along the pair
    # a target seen edge-on has no ellipse: not a number, never "accepted"
    lo, hi = shape_ratios(whole[None], np.zeros((1, 2, 2)))
    assert np.isnan(lo[0]) and np.isnan(hi[0])


def test_screening_drops_gross_observations_undetermined_targets_and_unlinked_images_with_reasons():
    rng = np.random.default_rng(5)
    net = simulate_network(rng, n_targets=60, n_images=8, sigma_px=0.05)
    oi, ot, uv = net.obs_image.copy(), net.obs_target.copy(), net.obs_uv.copy()
    q_bad = int(np.flatnonzero(ot == 3)[1])
    uv[q_bad] += [6.0, -4.0]  # a misnamed dot
    # an image far from the others, seeing only targets nobody else sees: its own block
    extra_pts = rng.uniform(-0.05, 0.05, (8, 3)) + [3.0, 0.0, 0.0]
    T_far = invert(look_at(np.array([3.0, 0.0, 0.8]), np.array([3.0, 0.0, 0.0])))
    T_far2 = invert(look_at(np.array([3.3, 0.0, 0.8]), np.array([3.0, 0.0, 0.0])))
    from calibration.camera import project

    pts = np.vstack([net.points, extra_pts])
    poses = np.concatenate([net.cam_from_part, T_far[None], T_far2[None]])
    for k, T in enumerate((T_far, T_far2)):
        oi = np.concatenate([oi, np.full(8, 8 + k)])
        ot = np.concatenate([ot, 60 + np.arange(8)])
        uv = np.vstack([uv, project(net.intrinsics, T, extra_pts)])
    s = screen_network(oi, ot, uv, net.intrinsics, poses, len(pts), scale_pairs=[(0, 60)])
    assert q_bad in s.obs and f"> {GROSS_PX} px" in s.obs[q_bad]
    assert len(s.obs) <= 3, s.obs  # the clean observations stay (0.05 px noise)
    assert not s.keep_images[8] and not s.keep_images[9]
    assert "not linked to the main network" in s.images[8]
    assert s.keep_images[:8].all()
    assert not s.scale_ok and "60 usable in 0 image(s)" in s.scale_reason
    # a clean network keeps everything; a target seen twice from one place is not determined
    s2 = screen_network(net.obs_image, net.obs_target, net.obs_uv, net.intrinsics, net.cam_from_part, 60)
    assert not s2.obs and not s2.targets and not s2.images and s2.scale_ok
    poses3 = np.concatenate([net.cam_from_part, net.cam_from_part[:1]])  # station 0 taken twice
    extra = invert(net.cam_from_part[0]) @ np.array([0.01, 0.02, 0.7, 1.0])  # a target only station 0 sees
    uv_extra = project(net.intrinsics, net.cam_from_part[0], extra[None, :3])
    oi3 = np.concatenate([net.obs_image, [0, 8]])
    ot3 = np.concatenate([net.obs_target, [60, 60]])
    uv3 = np.vstack([net.obs_uv, uv_extra, uv_extra + 0.03])
    s3 = screen_network(oi3, ot3, uv3, net.intrinsics, poses3, 61)
    assert "not determined" in s3.targets[60]
    assert set(s3.targets) == {60}
    assert set(s3.images) == {8} and "0 usable observation(s)" in s3.images[8]  # it saw nothing else: dropped too


def _plate(n_side: int = 7):
    import trimesh

    from planning.part import Part, Targets

    g = np.linspace(-0.12, 0.12, n_side)
    P = np.array([(x, y, 0.0) for x in g for y in g])
    n = len(P)
    t = Targets(ids=[f"T{i}" for i in range(n)], xyz=P, normals=np.tile([0, 0, 1.0], (n, 1)),
                kind=np.array(["retro"] * n), tolerance_m=np.full(n, np.nan), code=np.full(n, -1))
    plate = trimesh.creation.box(extents=(0.5, 0.5, 0.02))
    plate.apply_translation((0, 0, -0.01))
    return Part("plate", plate, t, target_diameter_m=0.005, coded_size_m=0.02), P


def test_naming_no_pose_explains_is_dropped_whole_and_a_few_deviating_dots_are_not():
    from calibration.camera import project
    from cell.stages.imaging import RESECTION_MEDIAN_PX, name_dots
    from planning.visibility import Occluder

    part, P = _plate()
    intr = Intrinsics.from_focal_length(0.008, 3.45e-6, 2448, 2048)
    cam_from_part = invert(look_at(np.array([0.03, -0.05, 0.5]), np.zeros(3), up=(0, 1, 0)))
    uv = project(intr, cam_from_part, P)
    rng = np.random.default_rng(3)
    occ = Occluder(part.mesh)
    # a few dots off by 10 px (the part deviates there): named, kept; the rest fit the resection
    dev = uv.copy()
    dev[[4, 17, 30]] += [10.0, 0.0]
    m = name_dots(dev, part, intr, cam_from_part, occ)
    assert len(m.target) == len(P) and not m.dropped and m.resection_median_px < 1.5
    # every dot off by 10-12 px in its own direction: a naming no pose explains, dropped whole with the reason
    ang = rng.uniform(0, 2 * np.pi, len(P))
    bad = uv + rng.uniform(10.0, 12.0, (len(P), 1)) * np.column_stack([np.cos(ang), np.sin(ang)])
    m = name_dots(bad, part, intr, cam_from_part, occ)
    assert len(m.target) == 0 and m.resection_median_px > RESECTION_MEDIAN_PX
    assert len(m.dropped) >= 40 and all("naming is inconsistent" in why for _, why in m.dropped)


def test_a_named_dot_whose_background_ring_is_too_small_to_bound_is_dropped_with_the_reason():
    """Below MIN_RING_PX ring pixels the detector fits no plane and tests no misfit: its zero bound would mean "not
    looked at", so MEASURE leaves the dot unnamed, and observations.json counts it by its reason (decision 0030)."""
    from calibration.camera import project
    from calibration.dots import MIN_RING_PX
    from cell.stages.imaging import name_dots
    from cell.stages.measure import dropped_by_reason
    from planning.visibility import Occluder

    part, P = _plate()
    intr = Intrinsics.from_focal_length(0.008, 3.45e-6, 2448, 2048)
    cam_from_part = invert(look_at(np.array([0.03, -0.05, 0.5]), np.zeros(3), up=(0, 1, 0)))
    uv = project(intr, cam_from_part, P)
    ring = np.full(len(P), 120)
    ring[[3, 11]] = [0, MIN_RING_PX - 1]
    m = name_dots(uv, part, intr, cam_from_part, Occluder(part.mesh), det_ring_px=ring)
    assert sorted(i for i, _ in m.dropped) == [3, 11] and len(m.target) == len(P) - 2
    assert all("background not measurable" in why for _, why in m.dropped)
    doc = [{"dropped": [{"id": str(i), "reason": why} for i, why in m.dropped]}]
    assert dropped_by_reason(doc) == {"background not measurable (ring < 8 px)": 2}


# --- whole jobs -------------------------------------------------------------------------------------------
def _run(tmp_path: Path, sim: dict, planning: dict | None = None):
    job = job_variant(tmp_path / "job", {"planning": {"required_sigma": REQUIRED_MM, "closed_loop_rounds": 3}
                                         | (planning or {}), "sim": sim})
    res = run_cell("run", str(job), "--archive", str(tmp_path / "archive"), "--yes", timeout=540)
    assert res.doc is not None, res.stderr[-3000:]
    return job, Path(res.doc["folder"]), res


def _check_truth_and_requirement(job: Path, folder: Path) -> dict:
    report = json.loads((folder / "report.json").read_text())
    cl = report["closed_loop"]
    unmet = {u["id"]: u["reason"] for u in cl["unmet"]}
    assert all(unmet.values())
    for t in report["targets"]:
        if t["id"] not in unmet:
            assert t["achieved_sigma_m"] <= REQUIRED_MM * 1e-3 * (1 + 1e-9), t["id"]
    ids, _, true_xyz = truth_xyz_m(job)
    where = {tid: k for k, tid in enumerate(ids)}
    T = [t for t in report["targets"] if t["id"] not in report["not_measured"]]
    meas = np.array([t["measured"] for t in T], dtype=float)
    cov = np.array([t["cov"] for t in T], dtype=float)
    truth = np.array([true_xyz[where[t["id"]]] for t in T])
    fit = rigid_fit(meas, truth)
    R = fit[:3, :3]
    m2 = mahalanobis(meas @ R.T + fit[:3, 3] - truth, R @ cov @ R.T) ** 2  # the covariance turned with the points
    assert np.mean(m2 <= chi2.ppf(0.9973, 3)) >= 0.95, f"{np.mean(m2 <= chi2.ppf(0.9973, 3)):.1%} within 3 sigma"
    assert 0.8 <= m2.mean() <= 6.0, f"mean squared normalised error {m2.mean():.2f} (3 expected)"
    return report


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_fixture_the_plan_did_not_know_dots_left_unnamed_and_closed_loop_brings_targets_within_requirement(tmp_path):
    job, folder, res = _run(tmp_path, {"fixture": FIXTURE})
    assert res.doc["status"] == "DONE", res.stderr[-2000:]
    obs = json.loads((folder / "observations.json").read_text())
    # the fixture clips dots: they are left unnamed, each with its reason, counted and journalled
    assert obs["dropped_by_reason"].get("shape unlike the target's ellipse", 0) >= 10, obs["dropped_by_reason"]
    assert all(d["reason"] for o in obs["images"] for d in o["dropped"])
    assert any(r["event"] == "identification_dropped" and r["total"] == obs["n_dropped"] for r in records(folder))
    report = _check_truth_and_requirement(job, folder)
    rounds = [r for r in report["closed_loop"]["rounds"] if r["status"] == "done"]
    assert rounds and sum(len(r["stations_added"]) for r in rounds) >= 1
    assert len(report["closed_loop"]["unmet"]) <= 2, report["closed_loop"]["unmet"]


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_station_the_robot_cannot_reach_is_skipped_and_closed_loop_makes_up_for_it(tmp_path):
    job, folder, res = _run(tmp_path, {"unreachable_stations": ["S003", "S007"]})
    assert res.doc["status"] == "DONE", res.stderr[-2000:]
    acq = json.loads((folder / "acquisition.json").read_text())
    assert {s["station"] for s in acq["skipped"]} == {"S003", "S007"}
    assert all("cannot reach" in s["reason"] for s in acq["skipped"])
    assert {r["station"] for r in records(folder) if r["event"] == "station_skipped"} == {"S003", "S007"}
    report = _check_truth_and_requirement(job, folder)
    assert len(report["closed_loop"]["unmet"]) <= 2, report["closed_loop"]["unmet"]


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_glare_beyond_55_deg_screened_network_and_closed_loop_measure_every_target(tmp_path):
    job, folder, res = _run(tmp_path, {"dot_max_incidence_deg": 55.0})
    assert res.doc["status"] == "DONE", res.stderr[-2000:]
    loop = json.loads((folder / "closed_loop.json").read_text())
    # the images lost their dots beyond the glare: the loop learnt that limit from them and planned within it
    learned = [r["incidence_limit_learned_deg"] for r in loop["rounds"] if r.get("incidence_limit_learned_deg")]
    assert learned and all(50.0 <= a <= 56.0 for a in learned), learned
    report = _check_truth_and_requirement(job, folder)
    assert len(report["closed_loop"]["unmet"]) <= 3, report["closed_loop"]["unmet"]
    assert len(report["not_measured"]) <= 3, report["not_measured"]


POOL = 12  # candidates in the small case: 2^12 subsets at most


def _meets(N_have, rays, req, min_rays, sel, info, visible):
    sel = list(sel)
    sig, ok = _sigma(N_have + info[sel].sum(axis=0), rays + visible[sel].sum(axis=0), min_rays)
    return ok & (sig <= req)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_extra_stations_for_the_fixture_within_one_of_exhaustive_search_on_a_small_pool(tmp_path):
    """Each closed-loop round of the fixture job, its real planning problem (the achieved information of the
    taken stations, the cell's candidate database) cut down to the planner's stations plus the candidates that
    see most short targets, 12 in all: the planner's count is within one of the exhaustive minimum."""
    job = job_variant(tmp_path / "job", {"planning": {"required_sigma": REQUIRED_MM, "closed_loop_rounds": 2},
                                         "sim": {"fixture": FIXTURE}})
    out = tmp_path / "rounds.npz"
    p = subprocess.run([sys.executable, str(REPO / "tests" / "augment_capture.py"), str(job), str(tmp_path / "a"),
                        str(out)], capture_output=True, text=True, env=child_env(), timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    z = np.load(out)
    assert str(z["status"]) == "DONE"
    n_rounds = len([k for k in z.files if k.endswith("_added")])
    assert n_rounds >= 1
    compared = 0
    for r in range(n_rounds):
        N_have, rays, req = z[f"r{r}_N_have"], z[f"r{r}_rays"], z[f"r{r}_required"]
        info, visible, added = z[f"r{r}_info"], z[f"r{r}_visible"], z[f"r{r}_added"]
        min_rays = int(z[f"r{r}_min_rays"])
        sig0, ok0 = _sigma(N_have, rays, min_rays)
        short = ~(ok0 & (sig0 <= req))
        order = np.argsort(-visible[:, short].sum(axis=1), kind="stable")
        pool = list(dict.fromkeys([int(a) for a in added] + [int(c) for c in order]))[:POOL]
        aug = plan_extra_stations(N_have, rays, req, info[pool], visible[pool], np.ones(len(pool), dtype=bool),
                                  min_rays=min_rays, max_new=len(pool))
        # fixable, judged here and not by the planner: short targets the whole pool together brings within reach
        fixable = short & _meets(N_have, rays, req, min_rays, range(len(pool)), info[pool], visible[pool])
        assert not (aug.unreachable & fixable).any(), "the planner called a target unreachable that the pool fixes"
        if not fixable.any():
            continue
        assert np.all(_meets(N_have, rays, req, min_rays, aug.added, info[pool], visible[pool])[fixable])
        best = next(k for k in range(len(pool) + 1) for sel in itertools.combinations(range(len(pool)), k)
                    if np.all(_meets(N_have, rays, req, min_rays, sel, info[pool], visible[pool])[fixable]))
        assert len(aug.added) <= best + 1, (r, len(aug.added), best)
        compared += 1
    assert compared >= 1


def test_report_names_what_the_adjustment_left_out():
    from cell.record.report import _alerts

    doc = {"left_out": {"observations": 3, "targets": [{"id": "T0164", "reason": "its 2 rays meet at 0.0 deg"}],
                        "images": [{"image": "images/0003.png", "station": "S010", "reason": "4 usable observation(s)"}]}}
    html = _alerts(doc)
    assert 'id="left-out"' in html and "3 gross observation(s)" in html
    assert "T0164: its 2 rays meet at 0.0 deg" in html and "images/0003.png (S010): 4 usable" in html
    assert "left-out" not in _alerts({"left_out": {"observations": 0, "targets": [], "images": []}})


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_scale_bar_end_hidden_without_closed_loop_faults_with_one_line(tmp_path):
    # a cap the plan does not know over the bar's end T0100 (glare beyond 52 deg no longer loses it: PLAN gives the
    # bar's ends views within 50 deg, planning/scalebar.py)
    cap = [{"name": "cap", "size": [12.0, 14.0, 14.0], "pose": {"xyz": [-150.0, -53.7535, 16.3703]}}]
    job = job_variant(tmp_path / "job", {"planning": {"required_sigma": REQUIRED_MM, "closed_loop": False},
                                         "sim": {"fixture": cap}})
    res = run_cell("run", str(job), "--archive", str(tmp_path / "archive"), "--yes", timeout=600)
    assert res.code == 1 and res.doc is not None, res.stderr[-2000:]
    assert res.doc["status"] == "FAULTED"
    folder = Path(res.doc["folder"])
    bundle = json.loads((folder / "bundle.json").read_text())
    sc = bundle["screening"]
    assert sc["scale_established"] is False and "T0094-T0100" in sc["scale"]
    assert bundle["datum"] == "free"  # adjusted, but in no scale of its own: not reported
    assert not (folder / "report.json").exists()
    line = [ln for ln in res.stderr.splitlines() if "scale not established" in ln and "FAULTED" in ln]
    assert len(line) == 1 and "T0094-T0100" in line[0], res.stderr[-2000:]
    assert any(r["event"] == "adjustment_screening" and r["scale_established"] is False for r in records(folder))
