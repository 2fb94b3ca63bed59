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
