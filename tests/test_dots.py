"""The detector on images as real cameras deliver them: dark or bright dots, colour, 12 bits, JPEG; covariances."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.dots import DetectionOptions, detect_dots
from calibration.errors import CalibrationError
from tests.test_targets import grid_uv, render_dots

REAL = DetectionOptions.for_real_images()


def _match(truth, found):
    d = np.linalg.norm(found[:, None, :] - truth[None, :, :], axis=2)
    return np.argmin(d, axis=1), np.min(d, axis=1)


def _jpeg(img, quality=90):
    return cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])[1], cv2.IMREAD_UNCHANGED)


def test_dark_printed_dots_in_a_colour_jpeg_are_found_with_polarity_auto():
    rng = np.random.default_rng(1)
    h, w = 360, 480
    uv = grid_uv(rng, h, w, 12, 9)
    img = 255 - render_dots(rng, h, w, uv, radius_px=4.0)  # black dots on white paper
    colour = _jpeg(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), 90)
    det = detect_dots(colour, REAL)
    assert det.polarity == "dark"
    j, d = _match(uv, det.uv)
    assert len(det) == len(uv) and len(np.unique(j)) == len(uv)
    assert np.sqrt(np.mean(d**2)) < 0.03
    # the cell's old default (bright dots only) finds none of them
    assert len(detect_dots(colour, DetectionOptions())) < len(uv) // 4


def test_bright_dots_in_12_bit_images_keep_their_precision():
    rng = np.random.default_rng(2)
    h, w = 360, 480
    uv = grid_uv(rng, h, w, 12, 9)
    img = render_dots(rng, h, w, uv, radius_px=3.5, bits=12)
    assert img.dtype == np.uint16 and img.max() < 4096
    det = detect_dots(img, REAL)
    assert det.polarity == "bright"
    j, d = _match(uv, det.uv)
    assert len(det) == len(uv)
    assert np.sqrt(np.mean(d**2)) < 0.02


def test_neighbours_bridged_at_the_noise_threshold_are_split_by_the_local_half_maximum():
    """On a clean JPEG the noise estimate is tiny; a noise threshold joins dots 2 px apart, half-max does not."""
    rng = np.random.default_rng(3)
    h, w = 200, 260
    pairs = []
    for y in (50.3, 100.6, 150.2):
        for x in (50.4, 130.7):
            pairs += [(x, y), (x + 10.5, y + 0.3)]  # radius 4: a 2.5 px gap
    uv = np.array(pairs)
    img = _jpeg(255 - render_dots(rng, h, w, uv, radius_px=4.0, blur_px=1.2), 95)
    det = detect_dots(img, REAL)
    j, d = _match(uv, det.uv)
    assert len(det) == len(uv) and len(np.unique(j)) == len(uv)
    assert d.max() < 0.1
    merged = detect_dots(img, DetectionOptions.for_real_images(local_fraction=0.0))
    assert len(merged) < len(uv)


def test_stated_covariance_matches_the_scatter_over_noise_realisations():
    h, w = 120, 160
    uv = np.array([[40.3, 40.7], [80.6, 60.2], [120.1, 80.9]])
    found = []
    covs = []
    for s in range(150):
        rng = np.random.default_rng(100 + s)
        det = detect_dots(render_dots(rng, h, w, uv, radius_px=3.0, level=0.25), DetectionOptions(cov_floor_px=0.0))
        assert len(det) == 3
        order = _match(uv, det.uv)[0]
        found.append(det.uv[np.argsort(order)])
        covs.append(det.cov[np.argsort(order)])
    found, covs = np.array(found), np.array(covs)
    emp = found.std(axis=0)  # (3, 2)
    stated = np.sqrt(np.median(covs[:, :, [0, 1], [0, 1]], axis=0))
    ratio = emp / stated
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio


def test_float_and_odd_shaped_images_are_refused_with_one_clear_error():
    with pytest.raises(CalibrationError, match="uint8 or uint16"):
        detect_dots(np.zeros((50, 50), np.float32))
    with pytest.raises(CalibrationError, match="grey or"):
        detect_dots(np.zeros((50, 50, 2), np.uint8))


def test_ellipse_fit_centres_agree_with_the_truth_and_state_a_covariance():
    rng = np.random.default_rng(6)
    h, w = 360, 480
    uv = grid_uv(rng, h, w, 12, 9)
    img = render_dots(rng, h, w, uv, radius_px=4.5)
    det = detect_dots(img, DetectionOptions(centre="ellipse", cov_floor_px=0.0))
    j, d = _match(uv, det.uv)
    assert len(det) == len(uv) and np.sqrt(np.mean(d**2)) < 0.02
    sd = np.sqrt(det.cov[:, [0, 1], [0, 1]])
    assert np.all((sd > 0.002) & (sd < 0.05))


def test_large_dots_get_a_kernel_that_holds_them():
    """No fixed pixel counts: 90 px dots (6400 px each, above the cell's 5000 px limit) are found."""
    rng = np.random.default_rng(8)
    h, w = 600, 800
    uv = np.array([[200.3, 200.6], [500.7, 210.2], [210.4, 430.9], [560.5, 420.1]])
    img = 255 - render_dots(rng, h, w, uv, radius_px=45.0, blur_px=1.5)
    fixed = detect_dots(img, DetectionOptions(polarity="dark"))  # the cell's 41 px kernel cuts them to pieces
    assert len(fixed) == 0 or np.sum(_match(uv, fixed.uv)[1] < 0.5) == 0
    det = detect_dots(img, REAL)
    j, d = _match(uv, det.uv)
    assert len(det) == 4 and d.max() < 0.05


def test_a_job_camera_section_chooses_the_detector_settings():
    from types import SimpleNamespace

    from cell.stages.imaging import detection_options

    o = detection_options(SimpleNamespace(polarity="dark", detection="photograph"))
    assert o == DetectionOptions.for_real_images(polarity="dark")
    assert detection_options(SimpleNamespace(polarity="bright", detection="cell")) == DetectionOptions()


def test_a_step_of_the_background_next_to_a_dot_is_bounded_in_its_background_covariance():
    """Dots 2-5 px from a step of the surface (an edge of the part next to them) are off by 5-20x their noise
    sigma; the detector's background bound covers them, and is zero where the ring around a dot is a plane."""
    rng = np.random.default_rng(2)
    dists = np.array([-60, -12, -9, -8, -7.5, -7], float)  # dot centre to the step, px (radius 5)
    edges = 100 + 120 * np.arange(len(dists))
    h, w = 120, int(edges.max() + 120)
    uv = np.stack([edges + dists + rng.uniform(-0.5, 0.5, len(dists)), 60 + rng.uniform(-0.5, 0.5, len(dists))], 1)
    bg = np.full((h, w), 0.08)
    for e in edges:
        bg[:, e:e + 60] = 0.16  # wider than the top-hat kernel: ground, not a blob
    det = detect_dots(render_dots(rng, h, w, uv, radius_px=5.0, bg_level=bg), DetectionOptions())
    j, d = _match(uv, det.uv)
    order = np.argsort(j)
    assert len(det) == len(uv) and np.all(j[order] == np.arange(len(uv)))
    err = np.linalg.norm(det.uv[order] - uv, axis=1)
    noise = np.sqrt(np.linalg.eigvalsh(det.cov[order])[:, 1])
    bound = np.sqrt(np.linalg.eigvalsh(det.background_cov[order])[:, 1])
    far = np.abs(dists) >= 12
    assert np.all(bound[far] == 0) and np.all(err[far] < 4 * noise[far])
    assert np.all(err[~far] > 5 * noise[~far]) and np.all(bound[~far] > 0)
    assert np.all(err[~far] <= bound[~far])
