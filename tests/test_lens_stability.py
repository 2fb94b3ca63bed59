"""One lens for all images, tested: a focus or zoom ring that slips midway through the acquisition is found, named at its
change point and estimated; clean networks, and a held lens that is merely off, are not taken for it (decision 0066)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_adjust_trust import _ctx, example  # noqa: F401  (the fixture: the example part's synthetic network)

from calibration.bundle import BundleConfig, BundleOptions, ScaleBar, bundle_adjust, simulate_network
from calibration.camera import project

SLIP = (0.0005, 0.5, -0.35)  # the outside tester's: principal distance +0.05 %, principal point (+0.5, -0.35) px


def _network(seed: int, change=(0.0, 0.0, 0.0), first_changed: int = 12, m: int = 24, n: int = 150,
             sigma_px: float = 0.05, held_off=(0.0, 0.0)):
    """A ring of ``m`` images (capture order = index) whose images ``first_changed ..`` see the lens changed by
    ``change`` (relative principal distance, cx px, cy px); ``held_off``: the start lens's principal distance (relative)
    and cx (px) off the true lens in every image."""
    rng = np.random.default_rng(seed)
    net = simulate_network(rng, n_targets=n, n_images=m, sigma_px=sigma_px)
    i0 = net.intrinsics
    i1 = replace(i0, fx_px=i0.fx_px * (1 + change[0]), fy_px=i0.fy_px * (1 + change[0]), cx_px=i0.cx_px + change[1],
                 cy_px=i0.cy_px + change[2])
    uv = net.obs_uv.copy()
    for j in range(first_changed, m):
        s = net.obs_image == j
        X = net.points[net.obs_target[s]]
        uv[s] += project(i1, net.cam_from_part[j], X) - project(i0, net.cam_from_part[j], X)
    start = replace(i0, fx_px=i0.fx_px * (1 + held_off[0]), fy_px=i0.fy_px * (1 + held_off[0]),
                    cx_px=i0.cx_px + held_off[1])
    x0 = net.points + np.random.default_rng(seed + 1000).normal(0.0, 1e-4, net.points.shape)
    return net, uv, start, x0


def _adjust(net, uv, start, x0, held: bool, sigma_px: float = 0.05, bars=()):
    config = BundleConfig(camera_model="PINHOLE", refine_focal_length=not held, refine_principal_point=not held,
                          scale_bars=bars)
    return bundle_adjust(net.obs_image, net.obs_target, uv, start, net.cam_from_part.copy(), x0,
                         BundleOptions(sigma_px=sigma_px), config)


@pytest.mark.parametrize("held", [False, True], ids=["estimated", "held"])
def test_a_lens_that_slips_midway_is_found_at_its_change_point(held):
    net, uv, start, x0 = _network(0, SLIP)
    st = _adjust(net, uv, start, x0, held).interior_stability
    assert st["tested"] and st["significant"], st
    assert st["interior"] == ("held" if held else "estimated")
    assert abs(st["first_changed"] - 12) <= 1
    assert st["statistic"] > 3 * st["critical"]
    # the change estimated: the principal distance in px of fx, the principal point in px, each within 4 sigma
    truth = np.array([SLIP[0] * net.intrinsics.fx_px, SLIP[1], SLIP[2]])
    z = (np.array(st["change_px"]) - truth) / np.array(st["change_sigma_px"])
    assert np.all(np.abs(z) < 4), z


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_clean_networks_do_not_take_their_noise_for_a_lens_that_moved(seed):
    net, uv, start, x0 = _network(seed)
    for held in (False, True):
        st = _adjust(net, uv, start, x0, held).interior_stability
        assert st["tested"] and not st["significant"], st
        assert st["change_points"] == 24 - 2 * 3 + 1
        assert st["statistic"] < st["critical"]


def test_a_held_lens_that_is_off_in_every_image_is_no_change():
    """The held lens 0.1 % long and 1 px off in cx for all images: its common error is no change (estimated for the
    test, projected out), so the test does not fire, where a test of the later images' lens against the held one
    alone would (the same error in both halves)."""
    net, uv, start, x0 = _network(5, held_off=(0.001, 1.0))
    res = _adjust(net, uv, start, x0, held=True)
    st = res.interior_stability
    assert res.intrinsics_names == () and st["interior"] == "held"
    assert st["tested"] and not st["significant"], st


def test_the_change_estimate_is_the_extended_models_with_a_scale_bar_in_the_network():
    """Nearly noise-free images: the one-step estimate from the score (``M^-1 g``) recovers the change itself, so its
    score and cofactor (the scale bar's ends on the camera side of the reduced normal equations too) are right."""
    net, uv, start, x0 = _network(6, SLIP, first_changed=10, sigma_px=1e-4)
    d = np.linalg.norm(net.points[:, None] - net.points[None], axis=2)
    a, b = np.unravel_index(np.argmax(d), d.shape)
    bars = (ScaleBar(int(a), int(b), float(d[a, b]), 1e-6),)
    st = _adjust(net, uv, start, x0, held=False, sigma_px=1e-4, bars=bars).interior_stability
    assert st["first_changed"] == 10
    truth = np.array([SLIP[0] * net.intrinsics.fx_px, SLIP[1], SLIP[2]])
    np.testing.assert_allclose(st["change_px"], truth, rtol=0, atol=0.02 * np.abs(truth).max())


def test_too_few_images_for_a_change_point_are_said_not_tested():
    net, uv, start, x0 = _network(7, m=5)
    st = _adjust(net, uv, start, x0, held=False).interior_stability
    assert st["tested"] is False and not st["significant"] and "3 images on each side" in st["reason"]


def test_adjusts_record_names_the_change_by_its_images_and_the_report_shows_it_red():
    from cell.record.report import render_html
    from cell.stages.lens import stability_doc

    st = {"tested": True, "significant": True, "statistic": 901.5, "critical": 22.4, "first_changed": 11,
          "change_px": [1.15, 0.47, -0.33], "change_sigma_px": [0.045, 0.031, 0.042], "statistics": {3: 1.0, 11: 901.5}}
    images = [{"image": f"images/{k:04d}.png", "station": f"S{k:03d}"} for k in range(24)]
    kept = np.array([k for k in range(24) if k != 4])  # image 4 left out: the change point is named in capture order
    doc = stability_doc(st, images, kept, 3.45e-6)
    assert doc["between"] == [{"image": "images/0011.png", "station": "S011"},
                              {"image": "images/0012.png", "station": "S012"}]
    assert doc["principal_distance_change_um"] == pytest.approx(1.15 * 3.45)
    assert "between images images/0011.png (station S011) and images/0012.png (station S012)" in doc["note"]
    assert "+3.97 um" in doc["note"] and "lock the lens's rings" in doc["note"]
    quiet = stability_doc(st | {"significant": False, "statistic": 5.0}, images, kept, 3.45e-6)
    assert "note" not in quiet
    assert stability_doc(None, images, kept, 3.45e-6)["tested"] is False
    html = render_html({"job": {"id": "j1", "name": "n", "seed": 1, "started": "s", "finished": "f", "versions": {}},
                        "verdict": "PASS", "targets": [], "stage_times_s": {}, "images": 3, "sigma0_px": 0.01,
                        "alignment": {"method": "best_fit", "description": "robust best fit", "targets_in_fit": [],
                                      "rms_m": 2e-6, "trusted": True, "stable": True, "reasons": [], "notes": []},
                        "snooping": {"complete": True, "stopped": "none left", "suspect_targets": []},
                        "n_rejected": 0, "lens": {"stability_note": doc["note"]}}, {})
    assert 'class="alert" id="lens-stability"' in html and "the lens changed during the acquisition" in html


def test_adjust_warns_of_a_lens_that_slipped_midway_and_records_it_in_bundle_json(tmp_path, example):
    """ADJUST's own ``run_bundle`` on the example part (tests/test_adjust_trust.py's synthetic network, 14 images):
    the tester's slip from the 8th image on is warned naming images 0006 and 0007 and recorded in bundle.json's
    ``lens``; the same images without the slip are not."""
    from cell.stages.adjust import run_bundle

    job, poses, obs = example
    i0 = job.intrinsics
    i1 = replace(i0, fx_px=i0.fx_px * (1 + SLIP[0]), fy_px=i0.fy_px * (1 + SLIP[0]), cx_px=i0.cx_px + SLIP[1],
                 cy_px=i0.cy_px + SLIP[2])
    X = job.part.targets.xyz
    slipped = [(seen, uv + (project(i1, poses[k], X[seen]) - project(i0, poses[k], X[seen]) if k >= 7 else 0.0))
               for k, (seen, uv) in enumerate(obs)]
    for d in ("slip", "clean"):
        (tmp_path / d).mkdir()
    ctx, said = _ctx(tmp_path / "slip", job, poses, slipped)
    st = run_bundle(ctx)["lens"]["interior_stability"]
    assert st["significant"] and st["between"][1]["image"] in ("images/0006.png", "images/0007.png", "images/0008.png")
    warned = [m for lvl, m in (x for x in said if isinstance(x, tuple)) if lvl == "warning" and "lens changed" in m]
    assert len(warned) == 1 and st["between"][1]["image"] in warned[0], warned
    assert any(isinstance(x, str) and x.startswith("  WARNING the lens changed during the acquisition") for x in said)
    ctx, said = _ctx(tmp_path / "clean", job, poses, obs)
    st = run_bundle(ctx)["lens"]["interior_stability"]
    assert st["tested"] and not st["significant"] and "note" not in st
    assert not any("lens changed" in str(x) for x in said)


def test_a_lens_that_moved_makes_a_pass_incomplete_and_says_why_and_leaves_a_fail():
    from cell.stages.report import lens_verdict

    moved = {"note": None, "stability_note": "the lens changed during the acquisition between images ..."}
    verdict, reasons = lens_verdict(moved, "PASS", [])
    assert verdict == "INCOMPLETE" and any("lens.stability_note" in r for r in reasons)
    assert lens_verdict(moved, "FAIL", ["T0105 beyond"]) == ("FAIL", ["T0105 beyond", reasons[0]])
    assert lens_verdict({"note": None, "stability_note": None}, "PASS", []) == ("PASS", [])
