"""Retro-target detection on a 5 MP image with 1000 targets (target: <= 100 ms; precision <= 0.02 px).

Run from the repository root:  .venv/bin/python -m benchmarks.bench_detection
[--real] [--centre ellipse] [--dark] [--colour] [--jpeg QUALITY]
(``--real``: the defaults for photographs, ``DetectionOptions.for_real_images()``: polarity, kernel and
size limits found per image; ``--dark``: the image inverted, dark dots on a light ground; ``--jpeg``:
the image through a JPEG round trip at that quality.)
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

from calibration.targets import DetectionOptions, detect_dots
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
    ap.add_argument("--real", action="store_true", help="DetectionOptions.for_real_images()")
    ap.add_argument("--centre", choices=("centroid", "ellipse"), default="centroid")
    ap.add_argument("--dark", action="store_true", help="dark dots on a light ground (the image inverted)")
    ap.add_argument("--colour", action="store_true", help="a 3-channel BGR copy of the image")
    ap.add_argument("--jpeg", type=int, default=0, help="JPEG round trip at this quality (0: none)")
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    h, w = 2048, 2448
    uv = grid_uv(rng, h, w, 40, 25, border=40)
    img = render_dots(rng, h, w, uv, radius_px=a.radius_px)
    base_img = img
    if a.dark:
        img = 255 - img
    if a.jpeg:
        img = cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, a.jpeg])[1], cv2.IMREAD_GRAYSCALE)
        base_img = 255 - img if a.dark else img
    if a.colour:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    opts = DetectionOptions.for_real_images(centre=a.centre) if a.real else DetectionOptions(centre=a.centre)
    times = []
    for _ in range(a.repeat):
        t0 = time.perf_counter()
        det = detect_dots(img, opts)
        times.append(time.perf_counter() - t0)
    d, j, err = _errors(uv, det.uv)
    base_times = []
    for _ in range(max(3, a.repeat // 3)):
        t0 = time.perf_counter()
        base = baseline_scipy(base_img, det.noise)
        base_times.append(time.perf_counter() - t0)
    bd, bj, berr = _errors(uv, base)
    print(f"image {w}x{h} ({w * h / 1e6:.1f} MP), {len(uv)} targets, found {len(det)} "
          f"(unique matches {len(np.unique(j))})")
    sd = np.sqrt(np.concatenate([det.cov[:, 0, 0], det.cov[:, 1, 1]]))
    print(f"options: {'real-image defaults' if a.real else 'defaults'}, centre {a.centre}, polarity found {det.polarity}"
          f"; stated sigma (cov) median {np.median(sd):.4f} px")
    print(f"detection: best {min(times) * 1e3:.1f} ms, median {np.median(times) * 1e3:.1f} ms")
    m = d < 1.0  # a detection more than 1 px from every target is a false one, counted apart
    print(f"centre error (the {int(m.sum())} within 1 px of a target; {int((~m).sum())} false detections): "
          f"bias ({err[m, 0].mean():+.4f}, {err[m, 1].mean():+.4f}) px, "
          f"std ({err[m, 0].std():.4f}, {err[m, 1].std():.4f}) px, max {d[m].max():.3f} px")
    print(f"baseline scipy.ndimage (label + center_of_mass): best {min(base_times) * 1e3:.1f} ms, "
          f"median {np.median(base_times) * 1e3:.1f} ms, found {len(base)}, centre std "
          f"({berr[bd < 1.0, 0].std():.4f}, {berr[bd < 1.0, 1].std():.4f}) px within 1 px of a target")
    print(f"ratio baseline / ours (best): {min(base_times) / min(times):.2f}x")


if __name__ == "__main__":
    main()
