"""Retro-target detection on a 5 MP image with 1000 targets (target: <= 100 ms; precision <= 0.02 px).

Run from the repository root:  .venv/bin/python -m benchmarks.bench_detection
The image is rendered like the simulated camera's (discs, 0.7 px blur, 0.70 / 0.08 of full scale,
shot and read noise of a 10 000 e- sensor, 8 bits); precision is the scatter of the centres
about the truth.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial import cKDTree

from calibration.targets import detect_retro_targets
from tests.test_targets import grid_uv, render_dots


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
    d, j = cKDTree(uv).query(det.uv)
    err = det.uv - uv[j]
    print(f"image {w}x{h} ({w * h / 1e6:.1f} MP), {len(uv)} targets, found {len(det)} "
          f"(unique matches {len(np.unique(j))})")
    print(f"detection: best {min(times) * 1e3:.1f} ms, median {np.median(times) * 1e3:.1f} ms")
    print(f"centre error: bias ({err[:, 0].mean():+.4f}, {err[:, 1].mean():+.4f}) px, "
          f"std ({err[:, 0].std():.4f}, {err[:, 1].std():.4f}) px, max {d.max():.3f} px")


if __name__ == "__main__":
    main()
