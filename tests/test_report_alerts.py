"""The report never shows an untrusted frame or an unfinished blunder test quietly."""
from cell.record.report import render_html


def _doc(**over):
    doc = {"job": {"id": "j1", "name": "n", "seed": 1, "started": "s", "finished": "f", "versions": {}},
           "verdict": "PASS", "targets": [], "stage_times_s": {}, "images": 3, "sigma0_px": 0.01,
           "alignment": {"method": "best_fit", "description": "robust best fit", "targets_in_fit": ["T1", "T2"],
                         "rms_m": 2e-6, "trusted": True, "stable": True, "reasons": [], "notes": []},
           "snooping": {"complete": True, "stopped": "none left", "suspect_targets": []},
           "predicted_over_achieved": {"median": 1.05, "p10": 0.9, "p90": 1.2, "n": 2}, "n_rejected": 0}
    doc.update(over)
    return doc


def test_a_trusted_report_has_no_alert_and_shows_the_frame_and_the_ratio():
    html = render_html(_doc(), {})
    assert "NOT TRUSTED" not in html and 'class="alert"' not in html
    assert "2 targets define the frame" in html and "Predicted / achieved sigma" in html and "1.05" in html


def test_an_untrusted_alignment_is_a_red_banner_with_its_reasons():
    al = _doc()["alignment"] | {"trusted": False, "reasons": ["ambiguous: another placement agrees with 90 targets"]}
    html = render_html(_doc(verdict="UNTRUSTED", alignment=al), {})
    assert 'id="alignment-alert"' in html and "ALIGNMENT NOT TRUSTED: ambiguous" in html
    assert 'class="verdict UNTRUSTED"' in html


def test_a_blunder_test_stopped_at_its_cap_is_said():
    sn = {"complete": False, "stopped": "cap of 20 rejections reached; 4 observation(s) still fail the test",
          "suspect_targets": ["T0007"]}
    html = render_html(_doc(snooping=sn), {})
    assert 'id="snooping-alert"' in html and "cap of 20" in html and "T0007" in html


def test_images_oriented_without_faugeras_toscani_are_listed_with_the_reason():
    fb = [{"image": "images/0013.png", "method": "PnP from the robot pose",
           "reason": "Faugeras-Toscani: the 75 points are nearly planar (thickness ratio 0.017 < 0.02)"}]
    html = render_html(_doc(orientation_fallbacks=fb), {})
    assert "1 image(s) not calibrated by Faugeras-Toscani" in html and "nearly planar" in html


def _targets(decisions: list[str], suspect: list[bool]) -> list[dict]:
    return [{"id": f"T{i}", "pass": d != "nonconforming", "decision": d, "suspect": s, "measured": [0.0, 0.0, 0.0],
             "deviation": [0.0, 0.0, 0.0], "deviation_norm_m": 1e-5, "tolerance_m": 2.5e-4, "achieved_sigma_m": 2e-6,
             "predicted_sigma_m": 2e-6, "n_images": 6} for i, (d, s) in enumerate(zip(decisions, suspect))]


def test_a_part_with_suspect_or_undecided_targets_is_not_a_plain_pass():
    import numpy as np

    from cell.stages.report import part_verdict

    ids = [f"T{i}" for i in range(5)]
    ok = np.ones(5, bool)
    judged = np.ones(5, bool)
    conforming = ["conforming"] * 5
    assert part_verdict(True, ok, ok, judged, conforming, np.zeros(5, bool), ids) == ("PASS", [])
    # a suspect target (data snooping could not verify its rays; REPORT makes it inconclusive): INCOMPLETE
    v, why = part_verdict(True, ok, ok, judged, ["conforming"] * 4 + ["inconclusive"], np.eye(5, dtype=bool)[4], ids)
    assert v == "INCOMPLETE" and why == ["1 target(s) suspect (their observations could not be verified by data "
                                         "snooping, or their images are not a clean dot: report.json target_print): "
                                         "T4"]
    # one within U of its tolerance (ISO 14253-1 cannot decide): INCOMPLETE, counted apart from the suspect ones
    dec = ["inconclusive", "conforming", "conforming", "conforming", "inconclusive"]
    v, why = part_verdict(True, ok, ok, judged, dec, np.eye(5, dtype=bool)[4], ids)
    assert v == "INCOMPLETE" and len(why) == 2 and why[1].startswith("1 target(s) within U of their tolerance") \
        and why[1].endswith(": T0")
    # beyond tolerance still fails, and an untrusted frame still says so first
    passed = np.array([False, True, True, True, True])
    fails = ["nonconforming"] + conforming[1:]
    assert part_verdict(True, ok, passed, judged, fails, np.zeros(5, bool), ids)[0] == "FAIL"
    assert part_verdict(False, ok, ok, judged, conforming, np.zeros(5, bool), ids)[0] == "UNTRUSTED"
    # a coded (not judged) target decides nothing
    assert part_verdict(True, ok, ok, judged & ~np.eye(5, dtype=bool)[4], dec[:4] + ["inconclusive"],
                        np.eye(5, dtype=bool)[4], ids)[0] == "INCOMPLETE"  # T0 is still within U


def test_the_banner_counts_suspect_targets_apart_from_those_within_u_of_the_tolerance():
    t = _targets(["conforming", "inconclusive", "inconclusive", "inconclusive"], [False, True, False, False])
    doc = _doc(verdict="INCOMPLETE", targets=t, inconclusive=["T1", "T2", "T3"], suspect=["T1"],
               verdict_reasons=["1 target(s) suspect (...): T1",
                                "2 target(s) within U of their tolerance (...): T2, T3"])
    html = render_html(doc, {})
    # the three undecided ones are not within tolerance: the measurement did not decide them
    assert ("INCOMPLETE: 1 of 4 targets within tolerance, 3 undecided or inconclusive; 1 suspect (observations not "
            "verified by the blunder test); 2 too close to their tolerance") in html
    assert 'id="verdict-reasons"' in html and "T2, T3" in html


def test_measure_drops_are_in_report_json_by_reason_and_image_and_in_the_html():
    from cell.stages.report import identification_drops

    obs = {"images": [
        {"image": "images/0000.png", "station": "S001", "dropped": []},
        {"image": "images/0001.png", "station": "S002", "dropped": [
            {"id": "T0003", "reason": "partly hidden by an edge of the part (CAD)"},
            {"id": "T0009", "reason": "shape 0.61..1.02 of its ellipse's (clipped, washed out or merged; 0.85..1.5)"}]},
        {"image": "images/0002.png", "station": "S003", "dropped": [
            {"id": "T0009",
             "reason": "the image's naming is inconsistent: resection median residual 9.1 px > 8.0 px"}]}]}
    dr = identification_drops(obs)
    assert dr["n_dropped"] == 3 and dr["by_reason"] == {"partly hidden (CAD)": 1,
                                                          "shape unlike the target's ellipse": 1,
                                                          "in images whose naming is inconsistent": 1}
    assert [(r["image"], r["n_dropped"]) for r in dr["images"]] == [("images/0001.png", 2), ("images/0002.png", 1)]
    html = render_html(_doc(identification_dropped=dr), {})
    assert 'id="identification-dropped"' in html and "1 shape unlike the target&#x27;s ellipse" in html
    assert "id=dropped" in html and "images/0002.png" in html and "Named dots left unnamed (MEASURE)" in html
    # the routine drops (dots the CAD says an edge clips) are listed, not raised as a warning
    only_hidden = identification_drops({"images": [obs["images"][1] | {"dropped": obs["images"][1]["dropped"][:1]}]})
    assert 'id="identification-dropped"' not in render_html(_doc(identification_dropped=only_hidden), {})


def test_a_plan_whose_prediction_did_not_hold_is_said():
    """Predicted / achieved outside 1.00 +- 0.25 (issue 15): the report says what it means, in a note."""
    from cell.stages.report import PREDICTION_BAND, _predicted_over_achieved

    def targets(ratio):
        return [{"predicted_sigma_m": ratio * 5e-6, "achieved_sigma_images_m": 5e-6} for _ in range(10)]

    held = _predicted_over_achieved(targets(1.1))
    assert held["note"] is None and held["band"] == list(PREDICTION_BAND)
    assert 'id="prediction-off"' not in render_html(_doc(predicted_over_achieved=held), {})
    over = _predicted_over_achieved(targets(1.29))
    assert "predicted 1.29x" in over["note"] and "took more stations than it needed" in over["note"]
    assert 'id="prediction-off"' in render_html(_doc(predicted_over_achieved=over), {})
    under = _predicted_over_achieved(targets(0.6))
    assert "worse than planned" in under["note"] and "less margin" in under["note"]
