"""``cell detect`` on photographs of printed sheets that are not clean: over-exposed, grainy, 16-bit copies, tiny.

Each test makes a small synthetic sheet that reproduces one thing an outside tester found on ROS-Industrial's
circle-grid photographs (dark dots on white paper) and their altered copies, and checks what the detector says.
"""
from __future__ import annotations

import json
import warnings
from dataclasses import replace

import cv2
import numpy as np
import pytest

from calibration.dot_noise import line_in_image_levels
from calibration.dots import DetectionOptions, detect_dots
from calibration.polarity import choose_polarity
from calibration.ringcodes import decode_ring_codes
from cell.cli import main

H, W = 240, 320


def _grid(rng, nx=7, ny=5, border=40):
    gx, gy = np.meshgrid(np.linspace(border, W - border, nx), np.linspace(border, H - border, ny))
    return np.stack([gx.ravel(), gy.ravel()], 1) + rng.uniform(-0.5, 0.5, (nx * ny, 2))


def _coverage(u, v, radius, ss=6):
    """(H, W) share of each pixel inside the disc of ``radius`` about ``(u, v)`` (ss x ss supersampling)."""
    r = int(np.ceil(radius)) + 2
    out = np.zeros((H, W))
    x0, y0 = int(round(u)), int(round(v))
    ys, xs = np.mgrid[y0 - r:y0 + r + 1, x0 - r:x0 + r + 1]
    off = (np.arange(ss) + 0.5) / ss - 0.5
    sx = xs[..., None, None] + off[None, None, None, :] - u
    sy = ys[..., None, None] + off[None, None, :, None] - v
    out[y0 - r:y0 + r + 1, x0 - r:x0 + r + 1] = np.mean(sx**2 + sy**2 <= radius**2, axis=(2, 3))
    return out


def sheet(rng, uv, radius=5.0, ink=40.0, paper=215.0, pale=None, pale_radius=2.5, gain=1.0, grain=0.0,
          noise=1.5, blur=0.8, photon=0.0):
    """A printed sheet, grey 8 bit: dark dots (``ink``) on ``paper`` with a Gaussian blur, pixel noise and
    ``grain`` (smooth specks of the paper, grey levels), ``photon``: the noise's variance grows by this per grey level;
    ``pale``: the dots' middle that light (a ring-shaped
    print); then a ``gain`` and clipping at 255 (an over-exposure)."""
    img = np.full((H, W), paper, dtype=np.float64)
    if grain:
        g = cv2.GaussianBlur(rng.standard_normal((H, W)), (0, 0), 2.5)
        img += grain * g / g.std()
    for (u, v), level in zip(uv, np.broadcast_to(ink, (len(uv),))):
        img += (level - img) * _coverage(u, v, radius)
        if pale is not None:
            img += (pale - img) * _coverage(u, v, pale_radius)
    img = cv2.GaussianBlur(img, (0, 0), blur)
    img += np.sqrt(noise**2 + photon * np.maximum(img, 0)) * rng.standard_normal((H, W))
    return np.clip(np.round(img * gain), 0, 255).astype(np.uint8)


def _detect_json(tmp_path, capsys, img, name="sheet.png", *extra):
    path = tmp_path / name
    cv2.imwrite(str(path), img)
    rc = main(["detect", str(path), "--json", *extra])
    said = capsys.readouterr()
    return rc, (json.loads(said.out) if rc == 0 else None), said.err


def _matches(truth, doc, within):
    found = np.array([[d["u"], d["v"]] for d in doc["detections"]]).reshape(-1, 2)
    if not len(found):
        return np.zeros(len(truth), dtype=int), found
    d = np.linalg.norm(found[None] - truth[:, None], axis=2)
    return (d <= within).sum(axis=1), found


# D1: the polarity must not flip to the paper's grain or to the gaps of an over-exposed sheet


def test_grainy_paper_does_not_flip_the_polarity_of_its_dark_dots(tmp_path, capsys):
    rng = np.random.default_rng(11)
    uv = _grid(rng, 5, 4)
    # specks of grain a few grey levels high outnumber the dots: the plain count of blobs took them for bright dots
    img = sheet(rng, uv, paper=180.0, grain=25.0, noise=0.3)
    choice = choose_polarity(img)
    assert choice.polarity == "dark" and not choice.ambiguous, choice
    rc, doc, err = _detect_json(tmp_path, capsys, img)
    assert rc == 0 and doc["polarity"] == "dark"
    n, found = _matches(uv, doc, 1.0)
    assert np.mean(n >= 1) >= 0.9, f"{(n == 0).sum()} dots lost"  # (a speck of grain can touch a dot)
    assert doc["polarity_choice"]["polarity"] == "dark" and not doc["polarity_choice"]["ambiguous"]


def test_over_exposed_sheet_keeps_its_dark_dots(tmp_path, capsys):
    rng = np.random.default_rng(11)
    uv = _grid(rng, 4, 3)
    # a grainy paper, then a gain of 2.5 that clips most of it: the plain count of blobs found more bright ones (the
    # unclipped grain between clipped patches) than dots
    img = sheet(rng, uv, paper=100.0, grain=8.0, gain=2.5, noise=0.3)
    rc, doc, _ = _detect_json(tmp_path, capsys, img)
    assert rc == 0 and doc["polarity"] == "dark"
    n, _ = _matches(uv, doc, 1.0)
    assert np.all(n >= 1), f"{(n == 0).sum()} dots lost"


def test_an_image_whose_polarity_cannot_be_told_says_so(tmp_path, capsys):
    rng = np.random.default_rng(13)
    uv = _grid(rng)
    img = sheet(rng, uv[::2], paper=128.0, ink=20.0)
    img = np.where(_bright_dots(uv[1::2]) > 0.5, 236, img).astype(np.uint8)  # as many bright dots as dark ones
    rc, doc, err = _detect_json(tmp_path, capsys, img)
    assert rc == 0
    assert doc["polarity_choice"]["ambiguous"] is True
    assert "WARNING polarity ambiguous" in err
    # a camera file's or the command line's polarity settles it: nothing to say then
    rc, doc, err = _detect_json(tmp_path, capsys, img, "sheet.png", "--polarity", "dark")
    assert rc == 0 and doc["polarity_choice"] is None and "ambiguous" not in err


def _bright_dots(uv, radius=5.0):
    return sum(_coverage(u, v, radius) for u, v in uv)


# D2: a clipped dot is flagged, its sd says more than an unclipped one's, and a dot split in two is not two dots


def test_over_exposed_ring_shaped_dots_are_flagged_clipped_and_never_reported_twice(tmp_path, capsys):
    rng = np.random.default_rng(21)
    uv = _grid(rng)
    # a printed dot whose middle is paler than its rim (as the ROS-Industrial sheet's are); a gain of 2.5 clips
    # the paper and the dots' middles
    img = sheet(rng, uv, radius=5.0, ink=30.0, paper=200.0, pale=95.0, pale_radius=2.6, gain=2.5, noise=0.8)
    rc, doc, err = _detect_json(tmp_path, capsys, img)
    assert rc == 0 and doc["polarity"] == "dark"
    n, found = _matches(uv, doc, 5.0)
    assert n.max() <= 1, f"{(n > 1).sum()} dots reported twice"
    near = [d for d in doc["detections"] if np.min(np.linalg.norm(uv - [d["u"], d["v"]], axis=1)) < 5.0]
    assert near and all(d["clipped"] and d["clipped_share"] >= 0.75 for d in near)
    sd = np.array([np.sqrt(np.trace(np.asarray(d["cov"])) / 2) for d in near])
    assert np.all(sd >= 0.1)  # the edge the saturation hides: 3.5% of a 5 px radius at least
    assert "clipped" in err and "WARNING" in err
    # the same sheet exposed well: nothing clipped, no extra sd
    img = sheet(np.random.default_rng(21), uv, radius=5.0, ink=30.0, paper=200.0, pale=95.0, pale_radius=2.6,
                noise=0.8)
    rc, doc, _ = _detect_json(tmp_path, capsys, img, "well.png")
    n, _ = _matches(uv, doc, 0.3)
    assert np.all(n == 1)
    assert not any(d["clipped"] for d in doc["detections"])
    assert all(d["clipped_edge_sd_px"] == 0 for d in doc["detections"])


# D4


def test_ring_codes_of_dots_with_no_ring_to_sample_raise_no_all_nan_warning():
    rng = np.random.default_rng(31)
    uv = np.array([[60.0, 120.0], [160.0, 120.0], [260.5, 60.0]])
    img = sheet(rng, uv, radius=4.0)
    det = detect_dots(img, DetectionOptions.for_real_images(polarity="dark"))
    assert len(det) == 3
    # a dot whose rings all fall off the image (here: an ellipse the detector could not measure) has only NaN samples
    axes = det.axes.copy()
    axes[1] = np.nan
    det = replace(det, axes=axes)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rc = decode_ring_codes(img, det, "schneider14")
    assert 1 not in rc.index


@pytest.mark.parametrize("levels, polarity, expect", [
    ((93.287, -0.3378), "dark", (7.148, 0.3378, True)),  # a dark image's inverted line: photon noise in its own levels
    ((-15.288, 1.0444), "bright", (-15.288, 1.0444, False)),  # negative at black: not physical
    ((5.0, 0.2), "dark", (56.0, -0.2, False)),  # falls with the light: not physical
])
def test_the_noise_line_is_said_in_the_images_own_grey_levels_and_judged_there(levels, polarity, expect):
    m = line_in_image_levels(levels, polarity, 255.0, 1.0)
    assert m["variance_at_zero"] == pytest.approx(expect[0], abs=1e-3)
    assert m["variance_per_grey_level"] == pytest.approx(expect[1], abs=1e-4)
    assert m["physical"] is expect[2] and m["constant"] is False
    assert ("NOT" in m["note"]) is (not expect[2])


def test_a_noise_line_negative_in_the_grey_range_falls_back_to_one_stated_figure(tmp_path, capsys):
    rng = np.random.default_rng(41)
    uv = _grid(rng, 9, 6, 25)
    # the paper clipped at 255 (no noise there) and ink with a print texture: the old fit went through the clipped
    # paper's zero variance and came out negative at black
    img = sheet(rng, uv, radius=5.0, ink=60.0, paper=330.0, noise=4.0)
    rc, doc, err = _detect_json(tmp_path, capsys, img)
    assert rc == 0
    m = doc["noise_model"]
    line = (m["variance_at_zero"], m["variance_per_grey_level"])
    assert m["constant"] or (min(line[0], line[0] + 255 * line[1]) >= -doc["noise"] ** 2)
    assert m["physical"] or "NOT photon noise" in err
    for x in err.splitlines():  # a negative figure is never printed without comment
        if "pixel noise variance" in x and ("+ -" in x or "variance -" in x):
            assert "NOT" in x


def test_a_16_bit_copy_measures_the_same_noise_line_as_its_8_bit_original():
    rng = np.random.default_rng(51)
    uv = _grid(rng, 9, 6, 25)
    # dots of several inks on a paper mostly at the ceiling: there the 8-bit copy's pixels differ by 0 or 1, the
    # 16-bit one's by 0 or 257 (which a fixed 3 grey levels took for outliers: no noise at all)
    img8 = sheet(rng, uv, radius=6.0, ink=np.linspace(30, 150, len(uv)), paper=262.0, noise=1.0, photon=0.02)
    o = DetectionOptions.for_real_images(polarity="dark")
    d8 = detect_dots(img8, o)
    d16 = detect_dots(img8.astype(np.uint16) * 257, o)
    assert len(d8) == len(d16) == len(uv)
    v8, s8 = d8.noise_levels
    v16, s16 = d16.noise_levels
    assert s8 != 0.0 and s16 != 0.0  # a line was measured on both, not "too few dots to measure its growth"
    assert v16 == pytest.approx(v8 * 257**2, rel=0.02)  # the same line, in units 257 times finer
    assert s16 == pytest.approx(s8 * 257, rel=0.02)
    assert line_in_image_levels(d8.noise_levels, "dark", 255.0, d8.noise)["physical"]


def test_an_image_too_small_to_hold_a_dot_is_bad_input_with_exit_2(tmp_path, capsys):
    path = tmp_path / "one.png"
    cv2.imwrite(str(path), np.zeros((1, 1), np.uint8))
    assert main(["detect", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "one.png" in err[0] and "1x1" in err[0]
