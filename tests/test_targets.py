"""Target detection and identification on rendered images with known truth."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.camera import Intrinsics, exp_se3, invert, look_at, project
from calibration.errors import CalibrationError
from calibration.targets import (
    detect_coded_targets,
    detect_retro_targets,
    identify_targets,
)

FULL_WELL_E = 10000.0  # the simulated sensor's photometry: 0.70 full scale on a dot, 0.08 background
READ_NOISE_E = 10.0


def render_dots(rng, h, w, uv, radius_px=3.5, level=0.70, bg_level=0.08, blur_px=0.7, ss=8, bits=8):
    """Discs (area coverage by ``ss`` x ``ss`` supersampling), Gaussian blur, shot + read noise, quantised.

    ``bg_level``: a number or an (h, w) array (the surface the dots hide).
    """
    r = int(np.ceil(radius_px)) + 2
    img = np.pad(np.broadcast_to(np.asarray(bg_level, dtype=np.float64), (h, w)), r, mode="edge")  # dots may straddle the border
    off = (np.arange(ss) + 0.5) / ss - 0.5
    for u, v in uv:
        u, v = u + r, v + r
        x0, y0 = int(round(u)), int(round(v))
        ys, xs = np.mgrid[y0 - r : y0 + r + 1, x0 - r : x0 + r + 1]
        sx = xs[..., None, None] + off[None, None, None, :] - u
        sy = ys[..., None, None] + off[None, None, :, None] - v
        cov = np.mean((sx**2 + sy**2) <= radius_px**2, axis=(2, 3))
        patch = img[y0 - r : y0 + r + 1, x0 - r : x0 + r + 1]
        patch += (level - patch) * cov  # the dot hides the surface under it
    img = cv2.GaussianBlur(img, (0, 0), blur_px)[r:-r, r:-r]
    e = img * FULL_WELL_E
    e += np.sqrt(e + READ_NOISE_E**2) * rng.standard_normal(e.shape)
    full = 2**bits - 1
    return np.clip(np.round(e / FULL_WELL_E * full), 0, full).astype(np.uint8 if bits == 8 else np.uint16)


def grid_uv(rng, h, w, nx, ny, border=30):
    gx, gy = np.meshgrid(np.linspace(border, w - border, nx), np.linspace(border, h - border, ny))
    return np.stack([gx.ravel(), gy.ravel()], 1) + rng.uniform(-0.5, 0.5, (nx * ny, 2))


def _nearest(truth, found):
    d = np.linalg.norm(found[:, None, :] - truth[None, :, :], axis=2)
    return np.argmin(d, axis=1), np.min(d, axis=1)


def test_dots_on_a_sloping_surface_are_not_pulled_towards_its_brighter_side():
    """The part's shading slopes under a tilted dot; a flat background estimate biased centres by ~0.02 px."""
    rng = np.random.default_rng(4)
    h, w = 480, 640
    uv = grid_uv(rng, h, w, 16, 12)
    slope = 0.0006  # of full scale per pixel, rising to the right: 0.05 to 0.43 across the view
    bg = 0.05 + slope * np.arange(w)[None, :] * np.ones((h, 1))
    img = render_dots(rng, h, w, uv, radius_px=5.0, level=0.7, bg_level=bg, blur_px=0.7)
    det = detect_retro_targets(img)
    j, d = _nearest(uv, det.uv)
    assert len(det) == len(uv) and len(np.unique(j)) == len(uv)
    err = det.uv - uv[j]
    assert abs(err[:, 0].mean()) < 0.004, f"bias along the slope {err[:, 0].mean():+.4f} px"
    assert err.std(axis=0).max() < 0.02


def test_a_bright_plate_filling_half_the_view_does_not_hide_the_dots():
    """Large bright areas are not noise: the threshold stays a few grey levels above the background."""
    rng = np.random.default_rng(5)
    h, w = 480, 640
    uv = grid_uv(rng, h, w, 16, 12)
    bg = np.where(np.arange(w)[None, :] < w // 2, 0.05, 0.45) * np.ones((h, 1))
    img = render_dots(rng, h, w, uv, radius_px=4.0, level=0.9, bg_level=bg)
    det = detect_retro_targets(img)
    assert det.noise < 5.0, f"noise estimate {det.noise:.1f} grey levels"
    j, d = _nearest(uv, det.uv)
    away = np.abs(uv[:, 0] - w // 2) > 12  # dots straddling the plate's edge are not round blobs
    assert set(np.flatnonzero(away)) <= set(j[d < 0.1])


def test_retro_centres_are_unbiased_and_within_two_hundredths_of_a_pixel():
    rng = np.random.default_rng(1)
    uv = grid_uv(rng, 480, 640, 16, 12)
    img = render_dots(rng, 480, 640, uv)
    det = detect_retro_targets(img)
    assert len(det) == len(uv)
    j, d = _nearest(uv, det.uv)
    assert len(np.unique(j)) == len(uv)
    err = det.uv - uv[j]
    assert np.all(np.abs(err.mean(axis=0)) < 0.005)
    assert np.all(err.std(axis=0) < 0.02)


def test_retro_detection_of_16_bit_images_matches_truth():
    rng = np.random.default_rng(2)
    uv = grid_uv(rng, 300, 400, 8, 6)
    img = render_dots(rng, 300, 400, uv, bits=12)
    assert img.dtype == np.uint16
    det = detect_retro_targets(img)
    _, d = _nearest(uv, det.uv)
    assert len(det) == len(uv) and d.max() < 0.08


def test_retro_detection_rejects_elongated_blobs_and_border_cuts():
    rng = np.random.default_rng(3)
    uv = np.array([[100.0, 100.0], [200.0, 120.0], [1.0, 150.0]])  # the last one is cut by the border
    img = render_dots(rng, 240, 320, uv)
    img[200:204, 40:140] = 200  # a glint: a long thin line
    det = detect_retro_targets(img)
    assert len(det) == 2
    _, d = _nearest(uv[:2], det.uv)
    assert d.max() < 0.1


def test_retro_detection_of_an_empty_image_returns_nothing():
    rng = np.random.default_rng(4)
    img = render_dots(rng, 120, 160, np.zeros((0, 2)))
    assert len(detect_retro_targets(img)) == 0


def test_retro_detection_refuses_colour_images():
    with pytest.raises(CalibrationError, match="grey image"):
        detect_retro_targets(np.zeros((10, 10, 3), np.uint8))


def _marker_image(ids, centres, side=60, h=480, w=640):
    dic = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_250)
    img = np.full((h, w), 230, np.uint8)
    for i, (cx, cy) in zip(ids, centres):
        m = cv2.aruco.generateImageMarker(dic, int(i), side)
        img[cy - side // 2 : cy - side // 2 + side, cx - side // 2 : cx - side // 2 + side] = m
    return img


def test_coded_targets_are_found_with_their_ids_and_centres():
    ids = [3, 17, 42]
    centres = [(120, 120), (320, 240), (520, 360)]
    img = _marker_image(ids, centres)
    got_ids, corners, got_c = detect_coded_targets(img)
    assert sorted(got_ids.tolist()) == ids
    assert corners.shape == (3, 4, 2)
    for i, c in zip(ids, centres):
        # the marker occupies pixels [c - 30, c + 29]: its centre is at c - 0.5 in our convention
        np.testing.assert_allclose(got_c[got_ids == i][0], np.array(c) - 0.5, atol=0.3)


def test_unknown_aruco_dictionary_is_a_clear_error():
    with pytest.raises(CalibrationError, match="ArUco dictionary"):
        detect_coded_targets(np.zeros((50, 50), np.uint8), dictionary="DICT_NOPE")


def _identification_scene(rng, n=150):
    intr = Intrinsics(fx_px=1500.0, fy_px=1500.0, cx_px=639.5, cy_px=479.5, width=1280, height=960)
    xyz = rng.uniform(-0.12, 0.12, (n, 3))
    codes = np.full(n, -1)
    codes[:6] = np.arange(6) + 10
    pose = invert(look_at([0.3, 0.35, 0.55], [0, 0, 0], roll_rad=0.4))
    uv = project(intr, pose, xyz)
    return intr, xyz, codes, pose, uv


def test_identification_recovers_every_retro_target_from_a_rough_pose():
    rng = np.random.default_rng(5)
    intr, xyz, codes, pose, uv = _identification_scene(rng)
    retro = np.flatnonzero(codes < 0)
    perm = rng.permutation(retro)
    det = uv[perm] + rng.normal(0, 0.05, (len(perm), 2))
    rough = exp_se3(np.array([0.004, -0.003, 0.002, 0.002, -0.002, 0.003])) @ pose
    got = identify_targets(det, xyz, codes, intr, rough, max_dist_px=15.0)
    ok = got >= 0
    assert ok.mean() > 0.95
    assert np.all(got[ok] == perm[ok])


def test_identification_uses_coded_targets_to_fix_a_bad_pose():
    rng = np.random.default_rng(6)
    intr, xyz, codes, pose, uv = _identification_scene(rng)
    retro = np.flatnonzero(codes < 0)
    det = uv[retro] + rng.normal(0, 0.05, (len(retro), 2))
    bad = exp_se3(np.array([0.03, -0.02, 0.02, 0.01, -0.01, 0.01])) @ pose  # tens of pixels off
    coded = np.flatnonzero(codes >= 0)
    without = identify_targets(det, xyz, codes, intr, bad, max_dist_px=8.0)
    with_codes = identify_targets(det, xyz, codes, intr, bad, max_dist_px=8.0,
                                  coded_ids=codes[coded], coded_uv=uv[coded])
    good = with_codes >= 0
    assert good.mean() > 0.95 and np.all(with_codes[good] == retro[good])
    assert np.sum((without >= 0) & (without == retro)) < good.sum()


def test_identification_leaves_spurious_dots_unnamed():
    rng = np.random.default_rng(7)
    intr, xyz, codes, pose, uv = _identification_scene(rng)
    retro = np.flatnonzero(codes < 0)
    spurious = rng.uniform([0, 0], [1280, 960], (40, 2))
    d = np.min(np.linalg.norm(spurious[:, None] - uv[None, retro], axis=2), axis=1)
    spurious = spurious[d > 20]
    det = np.vstack([uv[retro], spurious])
    got = identify_targets(det, xyz, codes, intr, pose, max_dist_px=6.0)
    assert np.all(got[len(retro):] == -1)
    assert np.all(got[: len(retro)][got[: len(retro)] >= 0] == retro[got[: len(retro)] >= 0])
