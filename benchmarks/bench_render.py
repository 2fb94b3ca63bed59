"""Render time of SimCamera on a 5 MP image of the example bracket with a few hundred targets.

Run: .venv/bin/python benchmarks/bench_render.py [--targets 300] [--coded 10] [--repeat 5]

Prints ms per image for
  * adaptive: the default renderer (supersampling only the pixels a rim or cell edge crosses);
  * baseline: the same exact renderer supersampling *every* pixel of every target window
    (``RenderOptions(adaptive=False)``), the naive way of doing area coverage;
and the parts of the default render (part background, targets, blur + sensor).
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from calibration.camera import Intrinsics, invert, look_at
from planning.part import Part, make_bracket, sample_targets
from sim_backend.sim_camera import RenderOptions, SimCamera, apply_sensor
from sim_backend.world import World


def apply_sensor_before(img, sensor, rng):
    """apply_sensor before issue 21 (NumPy normal variates, out-of-place arithmetic): the baseline."""
    full = float(2**sensor.bit_depth - 1)
    x = np.asarray(img, dtype=np.float32)
    if sensor.noise:
        electrons = np.maximum(x, 0.0) * np.float32(sensor.full_well_e)
        sigma = np.sqrt(electrons + np.float32(sensor.read_noise_e**2))
        electrons += sigma * rng.standard_normal(x.shape, dtype=np.float32)
        x = electrons * np.float32(1.0 / sensor.full_well_e)
    x = (x + np.float32(sensor.black_level)) * np.float32(full)
    np.clip(x, 0.0, full, out=x)
    return np.rint(x).astype(np.uint8 if sensor.bit_depth == 8 else np.uint16)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--targets", type=int, default=300)
    ap.add_argument("--coded", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--seed", type=int, default=11, help="noise stream of --precision")
    ap.add_argument("--precision", type=int, default=0, metavar="N",
                    help="also detect the dots in N noisy images with each sensor model and compare the scatter")
    args = ap.parse_args()
    mesh = make_bracket()
    targets = sample_targets(mesh, args.targets, np.random.default_rng(1), n_coded=args.coded)
    part = Part("bracket", mesh, targets)
    intr = Intrinsics.from_focal_length(0.012, 3.45e-6, 2448, 2048, k1=-0.05, k2=0.02)
    world = World(part, np.eye(4), np.eye(4), intr, seed=0)
    pose = look_at(part.centre + np.array([0.05, -0.45, 0.55]), part.centre)

    def timed(cam: SimCamera, fn) -> float:
        fn(cam)  # warm-up
        t0 = time.perf_counter()
        for _ in range(args.repeat):
            fn(cam)
        return 1e3 * (time.perf_counter() - t0) / args.repeat

    cam = SimCamera(world)
    base = SimCamera(world, options=replace(RenderOptions(), adaptive=False))
    _, truth = cam.render(pose)
    print(f"image {intr.width} x {intr.height}, {len(truth['ids'])} targets rendered "
          f"({len(truth['partial_ids'])} partly occluded, {len(truth['occluded_ids'])} hidden), "
          f"supersample {cam.options.supersample}x{cam.options.supersample}, repeat {args.repeat}")
    t_adapt = timed(cam, lambda c: c.render(pose))
    t_base = timed(base, lambda c: c.render(pose))
    t_bg = timed(cam, lambda c: c._render_background(pose, 1.0))
    img = cam._render_background(pose, 1.0)
    t_sensor = timed(cam, lambda c: apply_sensor(img, c.sensor, c.rng))
    t_sensor_old = timed(cam, lambda c: apply_sensor_before(img, c.sensor, c.rng))
    a, b = apply_sensor(img, cam.sensor, np.random.default_rng(2)), apply_sensor_before(img, cam.sensor, np.random.default_rng(2))
    d = a.astype(float) - b.astype(float)

    def targets_only(c: SimCamera) -> None:
        vis = c._select(pose, invert(pose))
        c._draw_targets(img.copy(), vis, invert(pose), np.zeros((len(vis.index), 2)), 1.0)

    t_targets = timed(cam, targets_only)
    print(f"adaptive (default)      {t_adapt:8.1f} ms/image")
    print(f"baseline (all pixels)   {t_base:8.1f} ms/image   ({t_base / t_adapt:.1f}x slower)")
    if args.precision:
        from scipy.spatial import cKDTree

        from calibration.targets import detect_retro_targets

        clean_img, _ = cam.render(pose, quantise=False)
        ref = detect_retro_targets(apply_sensor(clean_img, replace(cam.sensor, noise=False), None)).uv
        for name, fn in (("now", apply_sensor), ("before", apply_sensor_before)):
            rng, errs = np.random.default_rng(args.seed), []
            for _ in range(args.precision):
                uv = detect_retro_targets(fn(clean_img, cam.sensor, rng)).uv
                dist, j = cKDTree(ref).query(uv)
                errs.append(uv[dist < 0.5] - ref[j[dist < 0.5]])
            e = np.concatenate(errs)
            mad = 1.4826 * np.median(np.abs(e - np.median(e, axis=0)), axis=0)
            print(f"  centres, {name:6s} sensor noise vs noise-free: {len(e)} matches, mean ({e[:, 0].mean():+.4f}, "
                  f"{e[:, 1].mean():+.4f}) px, std ({e[:, 0].std():.4f}, {e[:, 1].std():.4f}) px, "
                  f"robust std ({mad[0]:.4f}, {mad[1]:.4f}) px")
    print(f"  part background       {t_bg:8.1f} ms")
    print(f"  targets (select+draw) {t_targets:8.1f} ms")
    print(f"  noise + quantisation  {t_sensor:8.1f} ms   (before issue 21: {t_sensor_old:.1f} ms, "
          f"{t_sensor_old / t_sensor:.1f}x; mean / std of the two images' difference {d.mean():+.4f} / {d.std():.3f} DN, "
          f"std of each {a.std():.3f} / {b.std():.3f} DN)")


if __name__ == "__main__":
    main()
