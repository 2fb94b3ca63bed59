"""Ring-coded targets: the families, and decoding what the simulated camera renders."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from calibration.camera import Intrinsics, invert, look_at, project
from calibration.dots import DetectionOptions, detect_dots
from calibration.errors import CalibrationError
from calibration.ringcodes import bits_code, code_bits, decode_ring_codes, family_codes, ring_family
from planning.part import Part, Targets
from sim_backend.sim_camera import SimCamera
from sim_backend.world import World

INTR = Intrinsics.from_focal_length(0.012, 3.45e-6, 2448, 2048, k1=-0.08, k2=0.05)
RADIUS = 0.003


def test_families_have_their_published_sizes_and_read_from_any_rotation():
    # aperiodic binary necklaces: 335 of length 12, 1161 of length 14; the DE19733466A1 14-bit code: 516 targets
    sizes = {"ring12": 335, "ring14": 1161, "schneider12": 147, "schneider14": 516}
    for fam, size in sizes.items():
        f = ring_family(fam)
        assert len(family_codes(fam)) == size
        for code in (f.first_id, f.first_id + 7, f.first_id + size - 1):
            b = code_bits(fam, code)
            for r in range(f.n):
                assert bits_code(fam, np.roll(b, r))[0] == code
    with pytest.raises(CalibrationError):
        code_bits("ring12", 335)
    with pytest.raises(CalibrationError):
        code_bits("schneider14", 0)  # numbered from 1


def _field(family, seed):
    xs, ys = np.linspace(-0.12, 0.12, 7), np.linspace(-0.09, 0.09, 5)
    P = np.array([(x, y, 0.0) for x in xs for y in ys])
    n = len(P)
    code = np.full(n, -1)
    kind = np.array(["retro"] * n, dtype=object)
    coded = np.arange(0, n, 3)
    f = ring_family(family)
    code[coded] = f.first_id + np.random.default_rng(seed).choice(len(family_codes(family)), len(coded), replace=False)
    kind[coded] = "coded"
    t = Targets(ids=[f"T{i}" for i in range(n)], xyz=P, normals=np.tile([0, 0, 1.0], (n, 1)), kind=kind.astype(str),
                tolerance_m=np.full(n, np.nan), code=code)
    plate = trimesh.creation.box(extents=(0.5, 0.4, 0.02))
    plate.apply_translation((0, 0, -0.01))
    return Part("plate", plate, t, target_diameter_m=2 * RADIUS, coded_size_m=0.02), P, code


@pytest.mark.parametrize("family,tilt_deg", [("ring12", 0.0), ("ring14", 45.0), ("schneider14", 30.0)])
def test_rendered_ring_codes_are_all_read_and_plain_dots_never(family, tilt_deg):
    part, P, code = _field(family, seed=int(tilt_deg) + 1)
    eye = np.array([0.0, -0.5 * np.sin(np.radians(tilt_deg)), 0.5 * np.cos(np.radians(tilt_deg))])
    part_from_cam = look_at(eye, np.zeros(3), up=(0, 1, 0))
    cam = SimCamera(World(part, np.eye(4), np.eye(4), INTR, seed=3), coded_family=family)
    img, _ = cam.render(part_from_cam)
    det = detect_dots(img, DetectionOptions.for_real_images())
    rc = decode_ring_codes(img, det, family)
    uv = project(INTR, invert(part_from_cam), P)
    nearest = np.array([np.argmin(np.linalg.norm(uv - det.uv[i], axis=1)) for i in rc.index])
    assert len(rc) == np.sum(code >= 0)
    assert np.array_equal(code[nearest], rc.code)
    # centre dots measured like any dot; the ring's sectors are flagged, the plain dots are not
    assert np.max(np.linalg.norm(uv[nearest] - det.uv[rc.index], axis=1)) < 0.1
    parts = rc.ring_parts(det.uv)
    plain = [np.argmin(np.linalg.norm(det.uv - uv[i], axis=1)) for i in np.flatnonzero(code < 0)]
    assert not parts[plain].any()
    assert np.sum(~parts) == len(P)


def test_the_job_chain_names_dots_with_ring_codes_from_a_poor_pose():
    """cell.stages.imaging.measure_image with coded_family: codes refine a pose 2 cm / 2 deg off, every dot named right."""
    from calibration.camera import exp_se3
    from cell.stages.imaging import measure_image
    from planning.visibility import Occluder

    part, P, code = _field("schneider14", seed=9)
    part_from_cam = look_at(np.array([0.05, -0.2, 0.45]), np.zeros(3), up=(0, 1, 0))
    cam = SimCamera(World(part, np.eye(4), np.eye(4), INTR, seed=4), coded_family="schneider14")
    img, truth = cam.render(part_from_cam)
    approx = exp_se3(np.array([0.02, -0.015, 0.01, 0.03, -0.02, 0.02])) @ invert(part_from_cam)
    m, counts = measure_image(img, part, INTR, approx, Occluder(part.mesh), coded_family="schneider14",
                              detection=DetectionOptions.for_real_images())
    assert counts["n_coded"] == np.sum(code >= 0)
    uv_true = project(INTR, invert(part_from_cam), P)
    assert len(m.target) == np.sum(code < 0)  # coded targets identify, they are not measured (decision 0004)
    assert np.max(np.linalg.norm(m.uv - uv_true[m.target], axis=1)) < 0.1
    assert m.cov.shape == (len(m.target), 2, 2) and np.all(np.linalg.eigvalsh(m.cov) > 0)  # observations.json cov_px2
