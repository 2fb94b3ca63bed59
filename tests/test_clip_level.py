"""A clipped dot on a shaded ground (decision 0050): its centre follows the ground behind it, its unknown level is
bounded, and ADJUST carries the bound as an error its views share."""
from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np

from calibration.camera import Intrinsics, invert, look_at, project
from calibration.dots import DetectionOptions, detect_dots
from cell.stages.clip_level import clip_bounds, clip_covariances, clip_level_cov

CEILING = 65535.0


def _dot_on_ground(level: float, ground: float, slope: float, centre, axes=(9.0, 5.0), angle_deg=0.0, blur=0.8,
                   ss=6, shape=(160, 200)) -> np.ndarray:
    """A 16-bit image of an elliptical dot that hides the ground behind it: ``ground (1 - a) + level a`` for the
    share ``a`` of each pixel it covers (area-sampled, then blurred), over a ground rising by ``slope`` per px along
    x; clipped at the ceiling."""
    H, W = shape
    yy, xx = np.mgrid[0:H * ss, 0:W * ss]
    x, y = (xx + 0.5) / ss - 0.5 - centre[0], (yy + 0.5) / ss - 0.5 - centre[1]
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    inside = ((x * c + y * s) / axes[0]) ** 2 + ((-x * s + y * c) / axes[1]) ** 2 <= 1.0
    a = cv2.GaussianBlur(inside.astype(float).reshape(H, ss, W, ss).mean(axis=(1, 3)), (0, 0), blur)
    b = np.broadcast_to(ground + slope * (np.arange(W)[None, :] - centre[0]), (H, W))
    return np.clip(b * (1 - a) + level * a, 0, CEILING).round().astype(np.uint16)


def _errors(k: float, n: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Centre errors (n, 2) px and clip bounds (n, 2) of dots ``k`` times over the ceiling (both above the ground) at
    random sub-pixel positions and orientations. The centre less the bound is the contour's at the slope 0.5 (the
    detector before decision 0050)."""
    rng = np.random.default_rng(5)
    b0 = 0.3 * CEILING
    err, bound = [], []
    for _ in range(n):
        centre = np.array([100.0, 80.0]) + rng.uniform(0, 1, 2)
        img = _dot_on_ground(b0 + k * (CEILING - b0), b0, 0.004 * CEILING, centre, angle_deg=rng.uniform(0, 180))
        det = detect_dots(img, DetectionOptions())
        j = int(np.argmin(np.linalg.norm(det.uv - centre, axis=1)))
        assert det.ellipse[j] and det.saturated[j] > 0
        err.append(det.uv[j] - centre)
        bound.append(det.clip_bound[j])
    return np.array(err), np.array(bound)


def test_a_clipped_dot_on_a_shaded_ground_is_centred_between_the_slopes_its_level_allows():
    """Centred as if just clipped (the contour following the ground by 0.5), dots far over the ceiling lean towards
    the darker ground: by +0.019 to +0.023 px on a ground that rises by 7 % of the ceiling across the dot. Centred
    between the slopes, the lean is at most about half of that whatever the dot's level, within the bound the
    detector states; across the gradient nothing moves."""
    worst_half, worst_mid = 0.0, 0.0
    for k in (1.2, 3.0, 10.0):
        mid, bound = _errors(k)
        half = mid - bound
        lean_half, lean_mid = half[:, 0].mean(), mid[:, 0].mean()
        worst_half, worst_mid = max(worst_half, abs(lean_half)), max(worst_mid, abs(lean_mid))
        # the bound: along the ground's gradient (for an ellipse turned to it, a little across: on average along),
        # and no smaller than the lean it bounds
        assert np.all(np.abs(bound[:, 0]) > 0) and abs(bound[:, 1].mean()) < 0.2 * abs(bound[:, 0].mean()), bound
        assert abs(lean_mid) <= np.mean(np.abs(bound[:, 0])), (k, lean_mid, bound[:, 0].mean())
        # across it, only the contour's sampling by the pixels (its phase), which averages out
        assert abs(mid[:, 1].mean()) < 3 * mid[:, 1].std() / np.sqrt(len(mid)), (k, mid[:, 1].mean())
    assert worst_half > 0.015 and worst_mid < 0.6 * worst_half, (worst_half, worst_mid)


def test_a_dot_that_is_not_clipped_has_no_bound_and_keeps_its_centre():
    """Below the ceiling the dot's peak is its level, and its contour follows the ground by one half exactly, on a
    ground as steep as the clipped dots' above: no bound, and its centre where it is."""
    b0 = 0.3 * CEILING
    centre = np.array([100.4, 80.3])
    img = _dot_on_ground(b0 + 0.5 * (CEILING - b0), b0, 0.004 * CEILING, centre)
    det = detect_dots(img, DetectionOptions(centre="ellipse"))
    j = int(np.argmin(np.linalg.norm(det.uv - centre, axis=1)))
    assert det.saturated[j] == 0 and det.ellipse[j] and not np.any(det.clip_bound[j])
    assert np.linalg.norm(det.uv[j] - centre) < 0.02


def test_clip_bounds_are_read_per_image_and_missing_ones_are_zero():
    doc = {"images": [{"ids": ["A", "B"], "clip_bound_px": [[0.01, -0.02], [0.0, 0.0]]},
                      {"ids": ["A"]},  # measured before decision 0050
                      {"ids": ["B", "C"], "clip_bound_px": [[0.01, 0.0]]}]}  # not its dots': not used
    b = clip_bounds(doc)
    assert b.shape == (5, 2)
    assert np.allclose(b, [[0.01, -0.02], [0, 0], [0, 0], [0, 0], [0, 0]])
    C = clip_covariances(b)
    assert np.allclose(C[0], np.outer([0.01, -0.02], [0.01, -0.02]) / 3) and not np.any(C[1:])


def _network(n_views: int = 8):
    intr = Intrinsics(2000.0, 2000.0, 1024.0, 768.0, 2048, 1536)
    points = np.array([[0.0, 0.0, 0.0], [0.05, 0.02, 0.0]])
    poses = []
    for k in range(n_views):
        az = 2 * np.pi * k / n_views
        eye = np.array([0.4 * np.cos(az), 0.4 * np.sin(az), 0.5])
        poses.append(invert(look_at(eye, np.zeros(3))))
    img = np.repeat(np.arange(n_views), 2)
    tgt = np.tile([0, 1], n_views)
    uv = np.concatenate([project(intr, T, points) for T in poses])
    res = SimpleNamespace(points=points, cam_from_part=np.array(poses), intrinsics=intr,
                          obs_sigma_px=np.full(len(img), 0.03), rejected=np.zeros(len(img), dtype=bool),
                          cov=np.repeat((1e-6) ** 2 * np.eye(3)[None], 2, axis=0))
    return res, img, tgt, uv


def test_the_views_of_a_target_share_its_clip_bound():
    """A target seen clipped in every view with a bound along one direction in space: the cross terms of its views
    add to its covariance; a target without a bound gets nothing."""
    res, img, tgt, uv = _network()
    # every view of target 0 leans the same way in space: a displacement along x, seen in each image
    intr = res.intrinsics
    d = np.array([project(intr, T, res.points[:1] + [[2e-6, 0.0, 0.0]])[0] - project(intr, T, res.points[:1])[0]
                  for T in res.cam_from_part])
    bound = np.zeros((len(img), 2))
    bound[tgt == 0] = d
    extra, doc = clip_level_cov(res, clip_covariances(bound), img, tgt)
    assert doc["n_observations"] == 8 and doc["n_targets"] == 1 and doc["sigma_growth_max"] > 1.0
    assert not np.any(extra[1])
    w = np.linalg.eigvalsh(extra[0])
    assert w.min() > -1e-24 and w.max() > 0
    # shared along x in space: the added variance lies along x
    assert extra[0][0, 0] > 10 * max(extra[0][1, 1], extra[0][2, 2]), extra[0]
    # none at all: nothing added, said as none
    none, doc0 = clip_level_cov(res, clip_covariances(np.zeros((len(img), 2))), img, tgt)
    assert not np.any(none) and doc0 == {"n_observations": 0, "n_targets": 0}


def test_the_report_says_what_the_clip_bounds_added():
    from cell.record.report import _budget_facts

    facts = _budget_facts({"uncertainty_budget": {"clip_level": {"n_observations": 1634, "bound_rms_px": 0.0148,
                                                                 "bound_max_px": 0.34, "n_targets": 189,
                                                                 "sigma_growth_median": 1.013,
                                                                 "sigma_growth_max": 1.049}}})
    line = facts["Stated beyond the detector model"]
    assert "1634 clipped dot(s)' unknown level (0.0148 px rms)" in line and "x1.013 median" in line
    assert "Stated beyond the detector model" not in _budget_facts(
        {"uncertainty_budget": {"clip_level": {"n_observations": 0, "n_targets": 0}}})


def test_clipped_dots_without_a_bound_are_counted_and_said():
    """An image measured before decision 0050 has clipped dots but no bounds: ADJUST counts them in bundle.json and
    says on the console and in the run log that their sigma lacks the term."""
    from cell.stages.adjust import _flag_counts
    from cell.stages.clip_level import say_clip_level

    # three clipped observations, one with its bound; one not clipped; the last clipped one rejected by the adjustment
    cc = clip_covariances(np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.0], [0.0, 0.0]]))
    flags = {"bg": None, "clip": np.array([0.5, 0.7, 0.0, 0.8]), "clip_cov": cc, "clip_missing": []}
    counts = _flag_counts(flags, np.array([False, False, False, True]))
    assert counts["observations_clipped"] == 2 and counts["clipped_without_bound"] == 1
    said, logged = [], []
    ctx = SimpleNamespace(say=said.append, log=SimpleNamespace(log=lambda level, msg: logged.append((level, msg))))
    say_clip_level(ctx, {"n_observations": 0, "n_targets": 0}, {"clipped_without_bound": 12})
    assert logged and logged[0][0] == "warning" and "12 observation(s) of clipped dots carry no bound" in logged[0][1]
    assert said == [f"  WARNING {logged[0][1]}"]
    said.clear()
    say_clip_level(ctx, {"n_observations": 5, "n_targets": 2, "bound_rms_px": 0.001, "sigma_growth_median": 1.0,
                         "sigma_growth_max": 1.01}, {"clipped_without_bound": 0})
    assert len(said) == 1 and "5 clipped dot(s) centred between the slopes" in said[0] and len(logged) == 1
