"""Retro-target detection on a 5 MP image with 1000 targets (target: <= 100 ms; precision <= 0.02 px).

Run from the repository root:  .venv/bin/python -m benchmarks.bench_detection
The image is rendered like the simulated camera's (discs, 0.7 px blur, 0.70 / 0.08 of full scale,
shot and read noise of a 10 000 e- sensor, 8 bits); precision is the scatter of the centres
about the truth. Baseline, in the same process: the textbook SciPy route (white top-hat,
threshold, ``ndimage.label``, ``ndimage.center_of_mass`` per blob), timed and scored the same way.
"""
from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from calibration.targets import DetectionOptions, detect_retro_targets
from tests.test_targets import grid_uv, render_dots


def baseline_scipy(img: np.ndarray, noise: float) -> np.ndarray:
    """Centres by ``scipy.ndimage``: top-hat, threshold at 8 noise sigmas, label, centre of mass, (k, 2)."""
    k = DetectionOptions().background_kernel_px
    tophat = cv2.morphologyEx(img, cv2.MORPH_TOPHAT, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    lab, n = ndimage.label(ndimage.binary_dilation(tophat > 8 * noise, iterations=2))
    com = np.array(ndimage.center_of_mass(tophat.astype(np.float64), lab, np.arange(1, n + 1)))
    return com[:, ::-1]


def _errors(uv: np.ndarray, found: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d, j = cKDTree(uv).query(found)
    return d, j, found - uv[j]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--radius-px", type=float, default=3.5)
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    h, w = 2048, 2448
    uv = grid_uv(rng, h, w, 40, 25, border=40)
    img = render_dots(rng, h, w, uv, radius_px=a.radius_px)
    times = []
    for _ in range(a.repeat):
        t0 = time.perf_counter()
        det = detect_retro_targets(img)
        times.append(time.perf_counter() - t0)
    d, j, err = _errors(uv, det.uv)
    base_times = []
    for _ in range(max(3, a.repeat // 3)):
        t0 = time.perf_counter()
        base = baseline_scipy(img, det.noise)
        base_times.append(time.perf_counter() - t0)
    bd, bj, berr = _errors(uv, base)
    print(f"image {w}x{h} ({w * h / 1e6:.1f} MP), {len(uv)} targets, found {len(det)} "
          f"(unique matches {len(np.unique(j))})")
    print(f"detection: best {min(times) * 1e3:.1f} ms, median {np.median(times) * 1e3:.1f} ms")
    print(f"centre error: bias ({err[:, 0].mean():+.4f}, {err[:, 1].mean():+.4f}) px, "
          f"std ({err[:, 0].std():.4f}, {err[:, 1].std():.4f}) px, max {d.max():.3f} px")
    print(f"baseline scipy.ndimage (label + center_of_mass): best {min(base_times) * 1e3:.1f} ms, "
          f"median {np.median(base_times) * 1e3:.1f} ms, found {len(base)}, centre std "
          f"({berr[:, 0].std():.4f}, {berr[:, 1].std():.4f}) px")
    print(f"ratio baseline / ours (best): {min(base_times) / min(times):.2f}x")


if __name__ == "__main__":
    main()
