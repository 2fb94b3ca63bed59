"""PLAN's pre-analysis from renders of the nominal part (cell/stages/preanalysis.py): the rays it predicts are the
rays MEASURE finds, its image terms are the detector's, it is cached safely, and a fallback is said."""
from __future__ import annotations

import json

import numpy as np
import pytest

import cell.stages.preanalysis as PA
from calibration.errors import CalibrationError
from cell.loadedjob import load
from jobutil import example_run


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    job, folder, run = example_run(tmp_path_factory)
    return job, folder


def _observed(folder) -> tuple[dict, int, int]:
    obs = json.loads((folder / "observations.json").read_text())
    rays: dict[str, int] = {}
    clipped = bounded = 0
    for im in obs["images"]:
        for tid in im["ids"]:
            rays[tid] = rays.get(tid, 0) + 1
        clipped += sum(1 for c in im["clipped_share"] if c > 0)
        bounded += sum(1 for b in im["bg_cov_px2"] if np.trace(np.array(b)) > 0)
    return rays, clipped, bounded


def test_predicted_rays_are_the_rays_measure_finds(example):
    job, folder = example
    plan = json.loads((folder / "plan.json").read_text())
    facts = plan["prediction"]["facts"]
    assert facts["rays_from"].startswith("renders") and "fallback" not in facts
    observed, clipped, bounded = _observed(folder)
    pred = {t["id"]: t["predicted_rays"] for t in plan["targets"] if t["id"] in observed}
    diff = np.array([pred[i] - observed[i] for i in pred])
    # the part lies where the job says and the robot stands where planned: the same dots, one lost or won at most
    assert np.mean(np.abs(diff) <= 1) >= 0.95, f"rays per target differ: {np.unique(diff, return_counts=True)}"
    assert abs(facts["rays"] - sum(observed.values())) <= 0.03 * sum(observed.values())
    # the image terms: as many clipped dots (within noise) as the real images have
    assert abs(facts["rays_clipped"] - clipped) <= max(5, 0.15 * clipped), (facts["rays_clipped"], clipped)
    assert abs(facts["rays_with_background_bound"] - bounded) <= max(5, 0.5 * bounded), \
        (facts["rays_with_background_bound"], bounded)


def test_rendered_rays_are_deterministic_and_cached_by_everything_they_depend_on(example, tmp_path):
    job_path, folder = example
    job = load(job_path)
    plan = json.loads((folder / "plan.json").read_text())
    poses = np.array([s["part_from_cam"] for s in plan["stations"][:3]])
    a = PA.cached_rendered_rays(job, poses, tmp_path)
    files = list(tmp_path.glob("preanalysis-*.npz"))
    assert len(files) == 1
    b = PA.cached_rendered_rays(job, poses, tmp_path)  # from the cache
    c = PA.rendered_rays(job, poses)  # measured again: the twin's noise is per image, not per run
    for r in (b, c):
        np.testing.assert_array_equal(r.obs_target, a.obs_target)
        np.testing.assert_array_equal(r.obs_image, a.obs_image)
        np.testing.assert_allclose(r.bg_cov, a.bg_cov)
        np.testing.assert_allclose(r.clipped_share, a.clipped_share)
        np.testing.assert_array_equal(r.ellipse, a.ellipse)  # which bounds are the centroid's (decision 0037)
    assert b.facts == a.facts and len(a.obs_target) > 60
    moved = poses.copy()
    moved[0, :3, 3] += 0.01  # another station: another key
    assert PA._cache_key(job, moved) != PA._cache_key(job, poses)
    files[0].write_bytes(b"torn")  # a torn cache file is measured again, not trusted
    d = PA.cached_rendered_rays(job, poses, tmp_path)
    np.testing.assert_array_equal(d.obs_target, a.obs_target)


def test_the_cache_key_holds_every_module_the_measurement_imports():
    # the cache lives on across versions of the code (planning's cache folder): a module the renders or their naming
    # import (the camera's projection, the ring codes, the visibility that names dots) changed without a new key
    # would serve stale rays
    import ast
    from pathlib import Path

    root = Path(PA.__file__).resolve().parents[2]
    seen, todo = set(), [f for f in PA._SOURCES if f != "cell/stages/preanalysis.py"]
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        seen.add(f)
        for node in ast.walk(ast.parse((root / f).read_text())):
            names = ([node.module] if isinstance(node, ast.ImportFrom) and node.module and node.level == 0
                     else [a.name for a in node.names] if isinstance(node, ast.Import) else [])
            todo += [p for p in (n.replace(".", "/") + ".py" for n in names) if (root / p).exists()]
    assert sorted(seen - set(PA._SOURCES)) == []


def test_a_prediction_without_renders_says_so(example, monkeypatch):
    job_path, folder = example
    job = load(job_path)
    plan = json.loads((folder / "plan.json").read_text())
    poses = np.array([s["part_from_cam"] for s in plan["stations"]])

    def broken(*a, **k):
        raise CalibrationError("twin camera: cannot render")

    monkeypatch.setattr(PA, "rendered_rays", broken)
    cov, rays, facts = PA.measurement_prediction(job, poses)
    assert "cannot render" in facts["fallback"] and facts["rays_from"].startswith("geometric")
    assert cov.shape == (len(job.part.targets.ids), 3, 3)
    retro = job.part.targets.kind != "coded"
    assert np.all(rays[retro] >= 0) and rays.sum() == facts["rays"]


def test_renders_that_show_no_dot_stop_the_plan_before_the_robot_moves(example, monkeypatch):
    """An outside check's job (``[sim] dot_max_incidence_deg = 1``: no dot renders) faulted PLAN with an internal
    AttributeError; then, predicted from the geometry instead, it drove the robot through 24 stations for images
    that measured nothing. A twin that sees no dot stops the plan (decision 0057)."""
    from calibration.errors import PlanningError

    job_path, folder = example
    job = load(job_path)
    plan = json.loads((folder / "plan.json").read_text())
    poses = np.array([s["part_from_cam"] for s in plan["stations"]])
    empty = PA.PredictedRays(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 2, 2)), np.zeros(0))
    monkeypatch.setattr(PA, "rendered_rays", lambda *args, **kw: empty)
    with pytest.raises(PlanningError, match="show no dot the detector measures"):
        PA.measurement_prediction(job, poses)


def test_renders_that_lose_a_bar_end_say_the_scale_is_not_established(example, monkeypatch):
    """A plan whose renders do not name a scale bar's end: the prediction is a free network's and says so (PLAN warns
    from ``scale_established``), and the end gets no prediction rather than another method's figure."""
    job_path, folder = example
    job = load(job_path)
    plan = json.loads((folder / "plan.json").read_text())
    poses = np.array([s["part_from_cam"] for s in plan["stations"]])
    a = job.scale_bars[0][0]
    full = PA.rendered_rays(job, poses)
    keep = full.obs_target != a
    lost = PA.PredictedRays(full.obs_image[keep], full.obs_target[keep], full.bg_cov[keep], full.clipped_share[keep])
    monkeypatch.setattr(PA, "rendered_rays", lambda *args, **kw: lost)
    cov, rays, facts = PA.measurement_prediction(job, poses)
    assert facts["scale_established"] is False and job.part.targets.ids[a] in facts["scale_reason"]
    assert rays[a] == 0 and not np.isfinite(cov[a]).any()
    ok = np.isfinite(cov).all(axis=(1, 2))
    assert ok.sum() > 150  # the others predicted, in a free network


def test_measure_says_which_dots_it_centred_by_their_ellipse(example):
    """Decision 0037: observations.json marks the dots centred by the ellipse of their contour; they are the clipped
    dots and the dots with a background bound (the ellipse fit may fail on a few, which keep their centroid)."""
    job, folder = example
    obs = json.loads((folder / "observations.json").read_text())
    flagged = ellipse = stray = 0
    for im in obs["images"]:
        e = np.asarray(im["ellipse_centre"], dtype=bool)
        f = (np.asarray(im["clipped_share"]) > 0) | (np.trace(np.asarray(im["bg_cov_px2"]), axis1=1, axis2=2) > 0)
        assert len(e) == len(im["ids"])
        flagged += int(f.sum())
        ellipse += int((e & f).sum())
        stray += int((e & ~f).sum())
    assert stray == 0 and flagged > 50 and ellipse >= 0.9 * flagged, (stray, ellipse, flagged)


def test_clipped_or_edge_dots_that_kept_their_centroid_are_counted():
    """MEASURE says how many flagged dots kept their centroid because the ellipse fit failed (decision 0037)."""
    from cell.stages.measure import centroid_kept

    bound = [[1e-3, 0.0], [0.0, 1e-3]]
    zero = [[0.0, 0.0], [0.0, 0.0]]
    rec = {"clipped_share": [0.0, 0.7, 0.0, 0.5], "bg_cov_px2": [zero, zero, bound, zero],
           "ellipse_centre": [False, True, False, False]}
    assert centroid_kept([rec]) == 2  # the edge dot and the second clipped one
    assert centroid_kept([{"clipped_share": [0.7], "bg_cov_px2": [zero]}]) == 0  # measured before the flags
    assert centroid_kept([{"clipped_share": [], "bg_cov_px2": [], "ellipse_centre": []}]) == 0
