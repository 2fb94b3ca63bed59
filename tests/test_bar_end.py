"""A scale bar end on the part that moved since its certificate is named (decision 0064's F5).

The bar's length is certified between two of the part's targets. One of them moved puts the whole measurement out of
scale; the alignment is untrusted (loud), and its reasons name the end that stays off its CAD place once the scale is
taken out, so the operator knows which target to check.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from calibration.alignment import PointCovariance
from cell.stages.report import align_measurement, bar_end_hints

SIGMA = 2e-6


def _job(nominal: np.ndarray, a: int, b: int, length: float):
    ids = tuple(f"T{i:04d}" for i in range(len(nominal)))
    targets = SimpleNamespace(xyz=nominal, ids=ids, kind=np.array(["plain"] * len(nominal)),
                              index=lambda: {t: i for i, t in enumerate(ids)})
    spec = SimpleNamespace(alignment=SimpleNamespace(method="best_fit", targets=None),
                           report=SimpleNamespace(sigma_factor=3.0), job=SimpleNamespace(
                               seed=5, bars=lambda: [("scale_bar", SimpleNamespace(cte_ppm_per_K=None))]))
    return SimpleNamespace(part=SimpleNamespace(targets=targets), scale_bars=((a, b, length, 2e-6),),
                           tolerance_m=np.full(len(nominal), 2.5e-4), spec=spec)


def _part(rng: np.random.Generator, n: int = 90) -> np.ndarray:
    """A curved skin 320 x 200 mm with a flange: no plane, no symmetry."""
    u, v = rng.uniform(-0.16, 0.16, n), rng.uniform(-0.1, 0.1, n)
    z = 0.03 * np.cos(6 * u) + 0.01 * v + np.where(u > 0.12, 0.04 * (u - 0.12) / 0.04, 0.0)
    return np.column_stack([u, v, z])


def _measure(rng, true: np.ndarray, a: int, b: int, length: float) -> np.ndarray:
    """The network scaled by the certificate over the ends' true distance, in a frame of its own, with noise."""
    scale = length / np.linalg.norm(true[b] - true[a])
    R = Rotation.from_rotvec([0.2, -0.1, 0.3]).as_matrix()
    return (true * scale) @ R.T + [0.5, -0.2, 0.1] + rng.normal(0, SIGMA, true.shape)


def test_a_bar_end_moved_since_its_certificate_is_named_and_the_frame_stays_untrusted():
    rng = np.random.default_rng(3)
    nominal = _part(rng)
    a, b = int(np.argmin(nominal[:, 0])), int(np.argmax(nominal[:, 0]))
    length = float(np.linalg.norm(nominal[b] - nominal[a]))
    u = (nominal[b] - nominal[a]) / length
    true = nominal.copy()
    aside = np.cross(u, [0.0, 0.0, 1.0])
    true[b] += -1.2e-3 * u + 0.4e-3 * aside / np.linalg.norm(aside)  # stuck again 1.2 mm nearer along the bar, 0.4 aside
    job = _job(nominal, a, b, length)
    pc = PointCovariance.independent(np.tile(np.eye(3) * SIGMA**2, (len(nominal), 1, 1)))
    out = align_measurement(job, _measure(rng, true, a, b, length), pc, np.ones(len(nominal), bool), "scale_bar")
    assert not out.trusted
    named = [r for r in out.reasons if r.startswith(f"scale bar T{a:04d}-T{b:04d}")]
    assert len(named) == 1 and f"its end T{b:04d} is" in named[0] and f"other end T{a:04d} agrees" in named[0], \
        out.reasons
    along = float(named[0].split("(")[1].split(" um along")[0])
    assert abs(along - (-1200.0)) < 60.0, named[0]  # the end's move along the bar, stated within 5 %


def test_a_part_out_of_scale_with_its_bar_ends_in_place_names_no_end():
    rng = np.random.default_rng(4)
    nominal = _part(rng)
    a, b = int(np.argmin(nominal[:, 0])), int(np.argmax(nominal[:, 0]))
    length = float(np.linalg.norm(nominal[b] - nominal[a]))
    true = nominal * (1 - 2000e-6)  # the part shrunk, the certificate right: the bar measures it
    job = _job(nominal, a, b, length * (1 - 2000e-6))
    pc = PointCovariance.independent(np.tile(np.eye(3) * SIGMA**2, (len(nominal), 1, 1)))
    out = align_measurement(job, _measure(rng, true, a, b, length * (1 - 2000e-6)), pc, np.ones(len(nominal), bool),
                            "scale_bar")
    assert not out.trusted and any("frame would be trusted" in r for r in out.reasons), out.reasons
    assert not any(r.startswith("scale bar") for r in out.reasons), out.reasons
    assert bar_end_hints(job, out) == ()  # the untrusted rigid frame has both ends out: nothing to name
