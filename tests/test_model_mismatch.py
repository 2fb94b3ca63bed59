"""Images the detector model does not describe are said (ADJUST's variance factor out of its range), not only
absorbed into an a posteriori covariance: console, run log, bundle.json, report.json and report.html."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cell.record.report import render_html
from cell.stages.model_shape import VARIANCE_FACTOR_RANGE, model_mismatch
from cell.record.runlog import read_messages
from tests.jobutil import job_variant, run_cell


def test_variance_factors_inside_the_range_are_quiet_and_outside_it_are_named():
    lo, hi = VARIANCE_FACTOR_RANGE
    assert model_mismatch(1.0) is None and model_mismatch(lo) is None and model_mismatch(hi) is None
    noisy = model_mismatch(16.0)
    assert "4.00x" in noisy and "does not describe these images" in noisy and "variance factor 16.00" in noisy
    quiet = model_mismatch(0.2)
    assert "better than the model allows" in quiet
    assert "unknown" in model_mismatch(float("nan"))


def test_report_shows_the_mismatch_as_a_note():
    doc = {"job": {"id": "j1", "name": "n", "seed": 1, "started": "s", "finished": "f", "versions": {}},
           "verdict": "PASS", "targets": [], "stage_times_s": {}, "images": 3, "sigma0_px": 0.05,
           "uncertainty_budget": {"detector_model_mismatch": model_mismatch(16.0)}}
    html = render_html(doc, {})
    assert 'id="model-mismatch"' in html and "4.00x the detector model" in html
    doc["uncertainty_budget"]["detector_model_mismatch"] = None
    assert 'id="model-mismatch"' not in render_html(doc, {})


def test_images_jittered_beyond_the_model_are_said_in_every_record(tmp_path):
    """The example with every dot displaced by 0.03 px of jitter ([sim] image_sigma_px, not rendered physics): the
    job measures, its statement follows the images, and the mismatch is said on the console, in the run log, in
    bundle.json and in report.json."""
    job = job_variant(tmp_path / "job", {"sim": {"image_sigma_px": 0.03}})
    run = run_cell("run", str(job), "--archive", str(tmp_path / "archive"), timeout=900)
    assert run.code == 0, run.stderr[-3000:]
    folder = Path(run.doc["folder"])
    w = json.loads((folder / "bundle.json").read_text())["observation_weights"]
    assert w["variance_factor"] > VARIANCE_FACTOR_RANGE[1] and w["model_mismatch"], w
    assert "WARNING the images fit" in run.stderr
    logged = [m["message"] for t, m in read_messages(folder / "run.mcap") if t == "/log"]
    assert any(m == w["model_mismatch"] for m in logged), logged[-10:]
    budget = json.loads((folder / "report.json").read_text())["uncertainty_budget"]
    assert budget["detector_model_mismatch"] == w["model_mismatch"]
    assert np.isclose(budget["variance_factor"], w["variance_factor"])
    assert 'id="model-mismatch"' in (folder / "report.html").read_text()
