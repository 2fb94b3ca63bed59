"""Render time of SimCamera on a 5 MP image of the example bracket with a few hundred targets.

Run: .venv/bin/python benchmarks/bench_render.py [--targets 300] [--coded 10] [--repeat 5] [--before REV]
[--all-pixels] [--precision N]

Prints ms per image (wall clock best and median of ``--repeat``, the process's CPU time, and the
1-minute load average: the machine is shared) for
  * today's renderer (adaptive supersampling: only the pixels a rim or cell edge crosses);
  * the renderer before issue 21 (``sim_backend/sim_camera.py`` and ``world.py`` at git revision
    ``--before``, loaded by ``git show``), in the same process, interleaved with today's, on the same
    scene and pose and with the same random streams: the images must be the same;
  * with ``--all-pixels``: the same exact renderer supersampling *every* pixel of every target window
    (``RenderOptions(adaptive=False)``), the naive way of doing area coverage;
and the parts of today's render (part background, targets, blur, sensor noise + quantisation).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script or with -m, from anywhere

from benchmarks.baseline_code import load_at  # noqa: E402
from calibration.camera import Intrinsics, invert, look_at  # noqa: E402
from planning.part import Part, make_bracket, sample_targets  # noqa: E402
from sim_backend.sim_camera import RenderOptions, SimCamera, apply_sensor  # noqa: E402
from sim_backend.world import World  # noqa: E402

#: main before issue 21's render work (the render branch started here)
BEFORE_REV = "e52f1ee"


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
    ap.add_argument("--before", default=BEFORE_REV, help="git revision of the renderer to compare with")
    ap.add_argument("--all-pixels", action="store_true", help="also time supersampling every window pixel")
    ap.add_argument("--seed", type=int, default=11, help="noise stream of --precision")
    ap.add_argument("--precision", type=int, default=0, metavar="N",
                    help="also detect the dots in N noisy images with each sensor model and compare the scatter")
    args = ap.parse_args()
    old_world = load_at("sim_backend/world.py", args.before)
    old_camera = load_at("sim_backend/sim_camera.py", args.before)
    mesh = make_bracket()
    targets = sample_targets(mesh, args.targets, np.random.default_rng(1), n_coded=args.coded)
    part = Part("bracket", mesh, targets)
    intr = Intrinsics.from_focal_length(0.012, 3.45e-6, 2448, 2048, k1=-0.05, k2=0.02)
    world = World(part, np.eye(4), np.eye(4), intr, seed=0)
    pose = look_at(part.centre + np.array([0.05, -0.45, 0.55]), part.centre)

    def timed(cam, fn) -> tuple[list[float], list[float]]:
        fn(cam)  # warm-up
        wall, cpu = [], []
        for _ in range(args.repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            fn(cam)
            wall.append(1e3 * (time.perf_counter() - t0))
            cpu.append(1e3 * (time.process_time() - c0))
        return wall, cpu

    def fmt(t: tuple[list[float], list[float]]) -> str:
        return f"best {min(t[0]):7.1f} ms, median {np.median(t[0]):7.1f} ms (CPU best {min(t[1]):.1f} ms)"

    cam = SimCamera(world, rng=np.random.default_rng(5))
    before = old_camera.SimCamera(old_world.World(part, np.eye(4), np.eye(4), intr, seed=0), rng=np.random.default_rng(5))
    img_now, truth = cam.render(pose)
    img_before, truth_before = before.render(pose)
    diff = np.abs(img_now.astype(int) - img_before.astype(int))
    print(f"image {intr.width} x {intr.height}, {len(truth['ids'])} targets rendered "
          f"({len(truth['partial_ids'])} partly occluded, {len(truth['occluded_ids'])} hidden), "
          f"supersample {cam.options.supersample}x{cam.options.supersample}, repeat {args.repeat}")
    print(f"same scene, pose and random streams: today's image vs before issue 21 ({args.before}): "
          + ("identical" if not diff.any() else f"{np.count_nonzero(diff)} pixels differ, by at most {diff.max()} DN")
          + ("; truth identical" if truth == truth_before else "; TRUTH DIFFERS"))
    load0 = os.getloadavg()[0]
    now, old = ([], []), ([], [])
    for _ in range(args.repeat):  # interleaved: both see the same load
        for cam_, acc in ((cam, now), (before, old)):
            t0, c0 = time.perf_counter(), time.process_time()
            cam_.render(pose)
            acc[0].append(1e3 * (time.perf_counter() - t0))
            acc[1].append(1e3 * (time.process_time() - c0))
    load1 = os.getloadavg()[0]
    print(f"load average {load0:.1f} -> {load1:.1f} on {os.cpu_count()} cores")
    print(f"today                   {fmt(now)} per image")
    pair = np.asarray(old[0]) / np.asarray(now[0])  # each pair rendered back to back: the same load
    print(f"before issue 21         {fmt(old)} per image   (ratio before / today {min(old[0]) / min(now[0]):.2f}x best, "
          f"{np.median(pair):.2f}x median of pairs, CPU time {min(old[1]) / min(now[1]):.2f}x)")
    if args.all_pixels:
        base = SimCamera(world, options=replace(RenderOptions(), adaptive=False))
        t_base = timed(base, lambda c: c.render(pose))
        print(f"all pixels supersampled {fmt(t_base)} per image   ({min(t_base[0]) / min(now[0]):.1f}x slower)")
    img = cam._render_background(pose, 1.0)
    t_bg = timed(cam, lambda c: c._render_background(pose, 1.0))

    def targets_only(c: SimCamera) -> None:
        vis = c._select(pose, invert(pose))
        c._draw_targets(img.copy(), vis, invert(pose), np.zeros((len(vis.index), 2)), 1.0)

    t_targets = timed(cam, targets_only)
    t_blur = timed(cam, lambda c: cv2.GaussianBlur(img, (0, 0), c.sensor.blur_sigma_px, borderType=cv2.BORDER_REFLECT))
    t_sensor = timed(cam, lambda c: apply_sensor(img, c.sensor, c.rng))
    t_sensor_old = timed(cam, lambda c: apply_sensor_before(img, c.sensor, c.rng))
    print(f"  part background       {fmt(t_bg)}")
    print(f"  targets (select+draw) {fmt(t_targets)}")
    print(f"  lens blur             {fmt(t_blur)}")
    print(f"  noise + quantisation  {fmt(t_sensor)}   (the sensor before issue 21, NumPy normals: "
          f"{min(t_sensor_old[0]):.1f} ms best, {min(t_sensor_old[0]) / min(t_sensor[0]):.1f}x)")
    # the lens's depth of field (decision 0049): each target's window blurred by its defocus; the jobs' default is a
    # 2 px blur circle at the depth of field's limits, here 0.45 / 0.95 m about this pose's 0.7 m
    from sim_backend.sim_camera import Sensor

    dof = SimCamera(world, sensor=Sensor().with_depth_of_field(0.45, 0.95, 2.0), rng=np.random.default_rng(5))
    t_dof = timed(dof, lambda c: c.render(pose))
    print(f"  with a depth of field {fmt(t_dof)}   ({min(t_dof[0]) / min(now[0]):.2f}x the render without, CPU "
          f"{min(t_dof[1]) / min(now[1]):.2f}x)")
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
    print("BENCHMARK " + json.dumps({
        "what": f"SimCamera render ({intr.width} x {intr.height}, {len(truth['ids'])} targets, noise on)",
        "figure": f"{min(now[0]):.1f} ms best, {np.median(now[0]):.1f} ms median, CPU {min(now[1]):.1f} ms (load {load0:.1f})",
        "baseline": f"before issue 21 ({args.before}) {min(old[0]):.1f} ms best",
        "ratio": f"{min(old[0]) / min(now[0]):.2f}x faster; {min(now[0]) / 100:.2f} of the 100 ms budget"}))


if __name__ == "__main__":
    main()
