"""The scale bars' test (calibration/bundle/bartest.py, decision 0041): its false alarms and its normalised residuals
over noise draws, and how a bad certificate shows.

1. Monte Carlo on a synthetic network (``--targets`` targets, ``--images`` images, three bars): image noise and each
   certificate's error drawn at their sigmas, the bundle adjusted, the test run. Prints sqrt(mean w^2) (1 when the
   residual's variance is right), mean w, the runs with a false failure at alpha 0.001, the residual's mean sigma
   and the certificates' own weight h.
2. With ``--offset K``: the same network with the middle bar's certificate K sigma off, the share of runs in which
   the test finds it (its |w| the largest and beyond the critical value).

    .venv/bin/python -m benchmarks.bar_test --draws 400
    .venv/bin/python -m benchmarks.bar_test --draws 200 --offset 10 --certificate-um 1
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from calibration.bundle import BundleConfig, BundleOptions, ScaleBar, bundle_adjust, simulate_network
from calibration.bundle.bartest import bar_residual_test
from calibration.bundle.coherent import certificate_at_face_value, scale_bar_gains


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=400)
    ap.add_argument("--targets", type=int, default=60)
    ap.add_argument("--images", type=int, default=8)
    ap.add_argument("--sigma-px", type=float, default=0.05)
    ap.add_argument("--certificate-um", type=float, default=3.0)
    ap.add_argument("--offset", type=float, default=0.0, help="the middle bar's certificate off by this many sigma")
    ap.add_argument("--seed", type=int, default=5)
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    net = simulate_network(rng, n_targets=a.targets, n_images=a.images, sigma_px=0.0)
    n = a.targets
    pairs = [(0, n // 2), (n // 6, 3 * n // 4), (n // 3, n - 5)]
    L = [float(np.linalg.norm(net.points[i] - net.points[j])) for i, j in pairs]
    s = a.certificate_um * 1e-6
    w, sig, h, false_alarm, found = [], [], [], 0, 0
    t0 = time.perf_counter()
    for _ in range(a.draws):
        uv = net.obs_uv + rng.normal(0, a.sigma_px, net.obs_uv.shape)
        bars = tuple(ScaleBar(i, j, Lk + rng.normal(0, s) + (a.offset * s if k == 1 else 0.0), s)
                     for k, ((i, j), Lk) in enumerate(zip(pairs, L)))
        res = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, net.cam_from_part, net.points,
                            BundleOptions(sigma_px=a.sigma_px, snooping=False), BundleConfig(scale_bars=bars))
        K, Ks = scale_bar_gains(res.covariance, res.points, bars, res.variance_factor)
        _, cov = certificate_at_face_value(res.cov, res.covariance, K, Ks, res.variance_factor)
        t = bar_residual_test(res.points, cov, K, bars)
        w.append(t.w)
        sig.append(t.sigma_m)
        h.append(t.h)
        false_alarm += bool(t.failed.any()) and a.offset == 0
        found += t.worst() == 1
    w = np.array(w)
    print(f"{a.draws} draws, {a.targets} targets, {a.images} images, 3 bars, certificates {a.certificate_um:g} um, "
          f"images {a.sigma_px:g} px; {time.perf_counter() - t0:.1f} s")
    if a.offset == 0:
        print(f"  sqrt(mean w^2) {np.sqrt(np.mean(w**2)):.3f} (per bar "
              + ", ".join(f"{v:.3f}" for v in np.sqrt(np.mean(w**2, axis=0))) + f"), mean w {w.mean():+.3f}")
        print(f"  runs with a false failure: {false_alarm} of {a.draws} (alpha 0.001 family-wise)")
    else:
        print(f"  middle certificate {a.offset:g} sigma off: found in {found} of {a.draws} runs; its mean w "
              f"{w[:, 1].mean():+.2f}, the others' {w[:, [0, 2]].mean():+.2f}")
    print(f"  residual sigma {np.mean(sig) * 1e6:.2f} um (certificate {a.certificate_um:g} um); the certificates' own "
          f"weight h {np.mean(h):.2f}")


if __name__ == "__main__":
    main()
