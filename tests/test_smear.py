"""An image smeared by a camera that moved during the exposure is found from its own dots (decision 0067)."""
import math

import numpy as np
import pytest

import sim_backend.sim_camera as simcam
from calibration.camera import invert
from calibration.smear import deviatoric_excess, image_smear
from calibration.targets import DetectionOptions, detect_dots, ellipse_moments
from cell.jobspec import CameraSection, CellSection
from cell.stages.measure import _left_out, dropped_by_reason, judge_smears, measure_with_excess, smeared_message
from planning.visibility import Occluder
from sim_backend.sim_camera import SimCamera
from sim_backend.world import World
from tests.test_sim_camera import FIELD_POSE, INTR, RADIUS, _field_part


_APPLY_SENSOR = simcam.apply_sensor


def _kernel(length, deg, kind):
    """The path of a camera that moved during the exposure, as an image kernel (the tester's: a uniform path, or a
    one-sided one whose dwell decays exponentially over its length), and the path's variance along it (px^2)."""
    n = int(math.ceil(length)) * 2 + 3
    k = np.zeros((n, n), np.float32)
    c = (n - 1) / 2
    th = math.radians(deg)
    s = np.linspace(-length / 2, length / 2, 400) if kind == "box" else np.linspace(0, length, 400)
    w = np.ones(len(s)) if kind == "box" else np.exp(-s / (length / 3))
    for si, wi in zip(s, w):
        x, y = c + si * math.cos(th), c + si * math.sin(th)
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - x0, y - y0
        k[y0, x0] += wi * (1 - fx) * (1 - fy)
        k[y0, x0 + 1] += wi * fx * (1 - fy)
        k[y0 + 1, x0] += wi * (1 - fx) * fy
        k[y0 + 1, x0 + 1] += wi * fx * fy
    mean = np.sum(w * s) / np.sum(w)
    return k / k.sum(), float(np.sum(w * (s - mean) ** 2) / np.sum(w))


def _render(monkeypatch, kernel=None, defocus_px=0.0, seed=3):
    """The field of 63 dots (tests/test_sim_camera.py) rendered with ``kernel`` applied to the irradiance before the
    sensor (a camera moving during the exposure), or an extra isotropic blur of ``defocus_px`` (sigma)."""
    import cv2

    orig = _APPLY_SENSOR

    def apply(img, sensor, rng, **kw):
        x = np.asarray(img, np.float32)
        if kernel is not None:
            x = cv2.filter2D(x, -1, kernel, borderType=cv2.BORDER_REFLECT)
        if defocus_px > 0:
            x = cv2.GaussianBlur(x, (0, 0), defocus_px, borderType=cv2.BORDER_REFLECT)
        return orig(x, sensor, rng, **kw)

    monkeypatch.setattr(simcam, "apply_sensor", apply)
    part = _field_part()
    img, truth = SimCamera(World(part, np.eye(4), np.eye(4), INTR, seed=seed)).render(FIELD_POSE)
    return part, img, np.array(truth["uv"])


def _smear(monkeypatch, **kw):
    part, img, uv = _render(monkeypatch, **kw)
    det = detect_dots(img, DetectionOptions(outline=True))
    j = np.argmin(np.linalg.norm(det.uv[:, None] - uv[None], axis=2), axis=0)
    assert np.all(np.linalg.norm(det.uv[j] - uv, axis=1) < 3.0)
    pred = ellipse_moments(INTR, invert(FIELD_POSE), part.targets.xyz, part.targets.normals, RADIUS)
    radius = np.hypot(uv[:, 0] - INTR.cx_px, uv[:, 1] - INTR.cy_px)
    return image_smear(deviatoric_excess(det.axes[j], pred), radius=radius,
                       size=np.sqrt(np.trace(pred, axis1=1, axis2=2)))


def _angle_gap(a, b):
    d = abs(a - b) % 180.0
    return min(d, 180.0 - d)


@pytest.mark.parametrize("kind,length,deg", [("box", 4.0, 30.0), ("decay", 4.0, 30.0), ("decay", 4.0, 125.0),
                                             ("box", 3.0, 80.0)])
def test_a_smeared_image_is_found_with_its_direction_and_length(monkeypatch, kind, length, deg):
    kernel, var = _kernel(length, deg, kind)
    s = _smear(monkeypatch, kernel=kernel)
    assert s["smeared"] is True, s
    assert _angle_gap(s["direction_deg"], deg) < 10.0, s
    expected = math.sqrt(12 * var)  # the uniform smear of the path's variance (4 px for the uniform path)
    assert abs(s["length_px"] / expected - 1.0) < 0.3, (s, expected)


@pytest.mark.parametrize("defocus_px", [0.0, 1.5])
def test_a_sharp_or_a_defocused_image_is_not_smeared(monkeypatch, defocus_px):
    s = _smear(monkeypatch, defocus_px=defocus_px)
    assert s["smeared"] is False, s
    assert s["variance_px2"] < 0.1, s


def test_measure_leaves_a_smeared_image_out_and_says_why(monkeypatch):
    """MEASURE's own steps on a rendered image: the record, the dots dropped with the reason, the line to say."""
    kernel, _ = _kernel(4.0, 30.0, "decay")
    part, img, _ = _render(monkeypatch, kernel=kernel)
    args = (part, INTR, invert(FIELD_POSE), Occluder(part.mesh), DetectionOptions(outline=True), "aruco", None)
    m, counts, e = measure_with_excess(img, *args)
    assert len(m.target) >= 50
    part2, clean, _ = _render(monkeypatch)
    m2, _, e2 = measure_with_excess(clean, part2, *args[1:])
    s, s2, kept = judge_smears([e, e2, None], part, INTR)
    assert s["smeared"] is True and s2["smeared"] is False and kept == {}
    assert _angle_gap(s["direction_deg"], 30.0) < 10.0
    left = _left_out(m, "smeared: its dots are smeared")
    assert len(left.target) == 0 and len(left.uv) == 0 and len(left.dropped) == len(m.dropped) + len(m.target)
    by = dropped_by_reason([{"dropped": [{"id": "T0", "reason": why} for _, why in left.dropped]}])
    assert by.get("in images smeared by the camera's motion") == len(m.target)
    msg = smeared_message("images/0007.png", "S012", s)
    assert "S012" in msg and "left out of the adjustment" in msg and "settle_s" in msg
    # the keys the line names are the job's
    assert {"settle_s", "settle_speed_rad_s"} <= set(CellSection.model_fields)
    assert "exposure_s" in CameraSection.model_fields


def test_too_few_dots_are_not_judged():
    s = image_smear(np.zeros((5, 2)))
    assert s["smeared"] is None and s["n_dots"] == 5


def test_the_report_names_a_smeared_image():
    from cell.record.report import _alerts
    from cell.stages.report import identification_drops

    smear = {"n_dots": 80, "variance_px2": 0.9, "length_px": 3.3, "direction_deg": 29.0, "z2": 900.0, "smeared": True}
    obs = {"images": [{"image": "images/0002.png", "station": "S010", "smear": smear,
                       "dropped": [{"id": "T0001", "reason": "smeared: its dots are smeared by ~3.3 px"}]},
                      {"image": "images/0003.png", "station": "S011", "smear": smear | {"smeared": False},
                       "dropped": [{"id": "T0002", "reason": "partly hidden by an edge of the part (CAD)"}]}]}
    dr = identification_drops(obs)
    assert dr["images"][0]["smear"]["length_px"] == 3.3 and "smear" not in dr["images"][1]
    html = _alerts({"identification_dropped": dr, "alignment": {}})
    assert 'id="smeared"' in html and "images/0002.png (S010): ~3.3 px along 29 deg" in html


def test_an_excess_that_grows_across_the_image_is_no_smear_and_one_tensor_everywhere_is():
    """A camera's motion adds one tensor to every dot; a shape the prediction misses grows with the dot's place (a
    clean plate's images had a 'smear' of 1.04 px^2, z^2 84, its halves 78 deg apart: decision 0067)."""
    rng = np.random.default_rng(5)
    n = 60
    radius, size = rng.uniform(20, 1100, n), rng.uniform(5, 12, n)
    one = np.tile([0.35, 0.25], (n, 1)) + rng.normal(0, 0.05, (n, 2))  # 0.86 px^2 along 18 deg, everywhere
    s = image_smear(one, radius=radius, size=size)
    assert s["smeared"] and all(h["agree"] for h in s["halves"])
    grows = np.column_stack([0.9 * (1 - radius / 1100), 0.1 * radius / 1100]) + rng.normal(0, 0.05, (n, 2))
    g = image_smear(grows, radius=radius, size=size)
    assert g["variance_px2"] > 0.6 and g["z2"] > 25  # the rule without the halves takes it for a smear
    assert g["smeared"] is False and not g["halves"][0]["agree"]
