"""The detector model's blur term (decision 0049): a dot blurred beyond the blur the model was measured at scatters
more, and each dot's blur is measured from its own image (its second moments less its ellipse's), so a real lens's
defocus or focus error raises the weights where the images show it."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from calibration.detector_model import load_model
from calibration.errors import CalibrationError
from cell.stages.dot_precision import BLUR_BEYOND_SHARE_MAX, blur_weights, observed_blur


def test_the_blur_term_raises_blurred_dots_only_and_holds_at_its_measured_edge():
    m = replace(load_model(), c_blur=0.5, blur_reference_px2=0.5, blur_range_px2=(0.5, 2.5))
    f = m.blur_factor(np.array([0.2, 0.5, 1.5, 2.5, 9.0, np.nan]))
    np.testing.assert_allclose(f, [1.0, 1.0, np.sqrt(1.5), np.sqrt(2.0), np.sqrt(2.0), 1.0])
    none = replace(m, c_blur=0.0)
    np.testing.assert_array_equal(none.blur_factor(np.array([3.0, np.nan])), [1.0, 1.0])


def test_the_repository_model_carries_a_measured_blur_term():
    """The model file has the term, with the command that measured it, its sigma and the range it holds over."""
    m = load_model()
    doc = json.loads((__import__("calibration.detector_model", fromlist=["DATA_PATH"]).DATA_PATH).read_text())
    assert m.c_blur > 0 and "benchmarks.detector_blur" in doc["blur_measured_by"]
    assert doc["c_blur_sigma"] < 0.5 * m.c_blur
    lo, hi = m.blur_range_px2
    assert lo == m.blur_reference_px2 and 0.4 < lo < 1.3 and hi > lo + 0.5
    # with the term, every blur class of the measurement is within 15 % of the sharp class in variance
    cls = doc["blur_classes"]
    ref = cls[0]["with_term"]
    assert all(abs(c["with_term"] / ref - 1) < 0.15 for c in cls), cls
    assert cls[-1]["without_term"] / cls[0]["without_term"] > 1.3  # and without it they were not


def test_a_model_file_with_a_broken_blur_term_is_refused(tmp_path):
    from calibration.detector_model import DATA_PATH

    doc = json.loads(DATA_PATH.read_text())
    doc["blur_range_px2"] = [2.0, 1.0]
    (tmp_path / "m.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match="blur_range_px2"):
        load_model(str(tmp_path / "m.json"))


def test_blur_weights_count_and_say_dots_beyond_the_measured_range():
    m = replace(load_model(), c_blur=0.5, blur_reference_px2=0.5, blur_range_px2=(0.5, 2.5))
    sigma = np.full(8, 0.01)
    s, doc = blur_weights(sigma, np.array([0.5, 0.6, 1.5, np.nan, 0.5, 0.5, 0.5, 0.5]), m)
    assert doc["raised"] == 2 and doc["measured"] == 7 and "warning" not in doc
    np.testing.assert_allclose(s[2], 0.01 * np.sqrt(1.5))
    n_beyond = int(np.ceil(BLUR_BEYOND_SHARE_MAX * 8)) + 1
    s, doc = blur_weights(sigma, np.r_[np.full(n_beyond, 4.0), np.full(8 - n_beyond, 0.5)], m)
    assert doc["beyond_measured_range"] == n_beyond and "near / far" in doc["warning"]


def test_observed_blur_reads_observations_json_with_gaps():
    obs = {"images": [{"ids": ["a", "b"], "blur_px2": [0.6, None]}, {"ids": ["c"]}, {"ids": ["d"], "blur_px2": [0.7]}]}
    np.testing.assert_array_equal(observed_blur(obs), [0.6, np.nan, np.nan, 0.7])


def test_many_dots_blurred_beyond_the_term_are_said_with_the_model_range():
    """ADJUST hands blur_weights' account to range_check, which keeps it and says its warning with the other
    conditions the model was not measured in (console, run log, bundle.json, report.json: the model-range path)."""
    from cell.stages.model_shape import range_check

    m = replace(load_model(), c_blur=0.5, blur_reference_px2=0.5, blur_range_px2=(0.5, 2.5))
    rng = np.random.default_rng(5)
    inc, d, used = rng.uniform(0, 75, 1000), rng.uniform(17, 35, 1000), np.ones(1000, bool)
    box = (np.radians(80.0), 15.4, 38.9)
    _, sharp = blur_weights(np.full(1000, 0.01), np.full(1000, 0.6), m)
    calm = range_check(inc, d, used, box, blur=sharp)
    assert calm["mismatch"] is None and calm["blur"]["measured"] == 1000
    _, soft = blur_weights(np.full(1000, 0.01), np.full(1000, 3.0), m)
    out = range_check(inc, d, used, box, blur=soft)
    assert out["blur"]["beyond_measured_range"] == 1000 and soft["warning"] in out["mismatch"]
