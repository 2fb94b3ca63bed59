"""SPC for the archive's trends: I-MR limits by hand, each out-of-control rule on a series built to break
it (and none on a series built not to), Cp/Cpk intervals that cover the truth as often as they claim,
and the trend of ten synthesized serial parts whose drifting targets (from part 6 on) are flagged."""
from __future__ import annotations

import numpy as np
import pytest

from webutil import DRIFTING, PART, TARGETS, seed_trend_archive

from cell.web.service import trend, trend_csv
from cell.web.spc import capability, imr_limits, violations
from cell.web.store import ArchiveView


def test_imr_limits_match_the_textbook_constants():
    x = np.array([10.0, 12.0, 11.0, 13.0, 12.0])
    lim = imr_limits(x)
    mr_bar = np.mean([2, 1, 2, 1])
    assert lim["center"] == pytest.approx(11.6)
    assert lim["mr_bar"] == pytest.approx(mr_bar)
    assert lim["ucl"] == pytest.approx(11.6 + 3 * mr_bar / 1.128)
    assert lim["lcl"] == pytest.approx(11.6 - 3 * mr_bar / 1.128)
    assert lim["mr_ucl"] == pytest.approx(3.267 * mr_bar)
    assert imr_limits(np.r_[x, 100.0], baseline=5)["center"] == pytest.approx(11.6)  # limits from the baseline only


@pytest.mark.parametrize("rule,series", [
    ("WE1", [0, 0.5, -0.5, 0.2, 3.5]),
    ("WE2", [0, 0.1, 2.5, 0.0, 2.4]),
    ("WE3", [0, 1.5, 1.2, 0.2, 1.4, 1.3]),
    ("WE4", [0.3, 0.2, 0.5, 0.1, 0.4, 0.6, 0.2, 0.3]),
    ("N3", [-1.0, -0.6, -0.2, 0.1, 0.5, 0.9]),
])
def test_each_rule_fires_on_a_series_built_to_break_it(rule, series):
    v = violations(np.asarray(series), center=0.0, sigma=1.0)
    hits = [x for x in v if x["rule"] == rule]
    assert hits and hits[0]["index"] == len(series) - 1, v


def test_no_rule_fires_on_an_in_control_series():
    x = np.array([0.3, -0.4, 0.8, -0.2, 0.1, -0.9, 0.5, -0.1, 0.2, -0.6, 0.4, -0.3])
    assert violations(x, 0.0, 1.0) == []


def test_capability_intervals_cover_the_truth_at_their_confidence():
    rng = np.random.default_rng(1)
    sigma, mu, lsl, usl, n = 1.0, 0.5, -4.0, 4.0, 30
    cp_true, cpk_true = (usl - lsl) / (6 * sigma), (usl - mu) / (3 * sigma)
    hit_cp = hit_cpk = 0
    trials = 1500
    for _ in range(trials):
        x = rng.normal(mu, sigma, n)
        c = capability(x.mean(), x.std(ddof=1), n, lsl, usl)  # the intervals assume the sample sigma
        hit_cp += c["cp_ci"][0] <= cp_true <= c["cp_ci"][1]
        hit_cpk += c["cpk_ci"][0] <= cpk_true <= c["cpk_ci"][1]
    # 95 % intervals: 3 binomial sigmas of 1500 trials is 1.7 %
    assert abs(hit_cp / trials - 0.95) < 0.02, hit_cp / trials
    assert abs(hit_cpk / trials - 0.95) < 0.025, hit_cpk / trials
    one_sided = capability(1.0, 1.0, 10, None, 4.0)
    assert one_sided["cp"] is None and one_sided["cpk"] == pytest.approx(1.0) and "only 10" in one_sided["note"]


def test_trend_of_ten_serial_parts_flags_the_targets_that_drift_from_part_6(tmp_path):
    archive = tmp_path / "archive"
    seed_trend_archive(archive, n_parts=10, drift_from=6)
    view = ArchiveView(archive)
    assert view.job_targets(PART) == TARGETS
    for t in TARGETS:
        for axis in ("z", "norm"):
            doc = trend(view, PART, t, axis)  # limits from all ten parts (phase I)
            assert doc["baseline"] == 10
            assert [p["serial"] for p in doc["points"]] == [f"SN-{i:04d}" for i in range(1, 11)]
            x = np.array([p["value_m"] for p in doc["points"]])
            if t in DRIFTING:
                # the drift pulls the centre line up: the parts above it that break a rule are drifted ones
                high = {v["index"] + 1 for v in doc["violations"] if x[v["index"]] > doc["center"] and v["rule"] != "MR"}
                assert high and min(high) >= 6, (t, axis, doc["violations"])
                assert {9, 10} <= {v["index"] + 1 for v in doc["violations"] if v["rule"] == "WE1"}
            else:
                assert doc["violations"] == [], (t, axis, doc["violations"])
            # limits from the five parts before the drift (phase II): flagged only from part 6 on
            ref = trend(view, PART, t, axis, baseline=5)
            flagged = sorted({v["index"] + 1 for v in ref["violations"] if v["rule"] != "MR"})
            if t in DRIFTING:
                assert flagged and min(flagged) >= 6 and {8, 9, 10} <= set(flagged), (t, axis, ref["violations"])
                assert ref["ucl"] - ref["lcl"] < 0.5 * (doc["ucl"] - doc["lcl"])  # the drift widened the phase I limits
    doc = trend(view, PART, DRIFTING[0], "z")
    assert "out of control" in doc["capability"]["note"]  # Cp/Cpk of a drifting process are not read as capability
    assert "out of control" not in trend(view, PART, TARGETS[0], "z")["capability"]["note"]
    # the tolerance band: z is two-sided (Cp and Cpk), |d| one-sided (Cpk only)
    assert doc["lsl"] == -doc["usl"] and doc["cp"] is not None
    assert trend(view, PART, TARGETS[0], "norm")["cp"] is None
    csv = trend_csv(doc).splitlines()
    assert len(csv) == 11 and csv[0].startswith("part,target,axis") and "SN-0010" in csv[-1]
    rules = csv[0].split(",").index("rules")
    assert any(r.split(",")[rules] in ("WE1", "WE2", "N3", "WE1 WE2", "N3 WE1", "N3 WE2", "N3 WE1 WE2")
               for r in csv[6:])


def test_a_group_trend_follows_its_worst_target(tmp_path):
    archive = tmp_path / "archive"
    seed_trend_archive(archive, n_parts=10, drift_from=6)
    view = ArchiveView(archive)
    group = ",".join(["T01", DRIFTING[0], "T04"])
    doc = trend(view, PART, group, "norm")
    worst = [p["target"] for p in doc["points"]]
    assert worst[-1] == DRIFTING[0] and doc["group"] == ["T01", DRIFTING[0], "T04"]
    single = {t: [p["value_m"] for p in trend(view, PART, t, "norm")["points"]] for t in ("T01", DRIFTING[0], "T04")}
    assert [p["value_m"] for p in doc["points"]] == pytest.approx(np.max(list(single.values()), axis=0))
    assert {v["index"] + 1 for v in doc["violations"] if v["rule"] == "WE1"} >= {9, 10}
