"""Benchmark: reachability of 2,000 candidate stations (target <= 2 s on 2 cores).

Compares the vectorised database (analytic IK for all stations at once, batched collision
checks of the best branches in pinocchio's parallel loop, one distance query per reachable
station) with a simple baseline in the same process: a per-station loop that solves IK
for one pose at a time and checks every branch in turn with a distance query.

Run: .venv/bin/python benchmarks/bench_reachability.py [--n 2000] [--robot ur5e]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import trimesh

from calibration.camera import look_at
from planning.kinematics import BoxObstacle, CollisionWorld, load_robot
from planning.reachability import ReachabilityOptions, branch_scores, flange_targets, reachability_mask


def scene(n: int, seed: int = 0):
    """A bracket-sized part on the table, a post, and n stations on a viewing hemisphere."""
    rng = np.random.default_rng(seed)
    part = trimesh.util.concatenate([
        trimesh.creation.box((0.30, 0.20, 0.02)),
        trimesh.creation.box((0.02, 0.20, 0.15), transform=trimesh.transformations.translation_matrix((0.14, 0, 0.085))),
    ])
    base_from_part = np.eye(4)
    base_from_part[:3, 3] = (0.45, 0.10, 0.01)
    post = BoxObstacle("post", (0.1, 0.1, 0.8), np.array([[1, 0, 0, 0.1], [0, 1, 0, 0.45], [0, 0, 1, 0.4], [0, 0, 0, 1.0]]))
    world = CollisionWorld(part_mesh=part, base_from_part=base_from_part, table_z=0.0, obstacles=(post,), clearance_m=0.005)
    u = rng.normal(size=(n, 3))
    u[:, 2] = np.abs(u[:, 2]) + 0.2
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    eyes = u * rng.uniform(0.3, 0.55, n)[:, None]
    pfc = np.stack([look_at(e, np.zeros(3), np.array([0.0, 0.0, 1.0])) for e in eyes])
    flange_from_cam = np.eye(4)
    flange_from_cam[:3, 3] = (0.0, 0.04, 0.09)
    return base_from_part, flange_from_cam, pfc, world


def baseline(robot, base_from_part, flange_from_cam, pfc, world) -> np.ndarray:
    """Per-station loop: IK of one pose, branches by score, a distance query per branch."""
    out = np.zeros(len(pfc), dtype=bool)
    for i, t in enumerate(flange_targets(base_from_part, pfc, flange_from_cam)):
        sols = robot.ik(t)
        if len(sols) == 0:
            continue
        for q in sols[np.argsort(-branch_scores(robot, sols))]:
            if robot.check_collision(q, world):
                out[i] = True
                break
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=2000)
    ap.add_argument("--robot", default="ur5e")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    robot = load_robot(args.robot)
    bfp, ffc, pfc, world = scene(args.n)
    reachability_mask(robot, bfp, ffc, pfc[:10], world)  # build the collision scene once (warm-up)
    opt = ReachabilityOptions(n_threads=args.threads)
    t0 = time.perf_counter()
    res = reachability_mask(robot, bfp, ffc, pfc, world, opt)
    t_vec = time.perf_counter() - t0
    t0 = time.perf_counter()
    res_nodist = reachability_mask(robot, bfp, ffc, pfc, world, ReachabilityOptions(n_threads=args.threads, compute_distances=False))
    t_nodist = time.perf_counter() - t0
    t0 = time.perf_counter()
    base = baseline(robot, bfp, ffc, pfc, world)
    t_base = time.perf_counter() - t0
    agree = bool(np.array_equal(base, res.reachable) and np.array_equal(res_nodist.reachable, res.reachable))
    print(f"robot {robot.name}, {args.n} stations, {args.threads} threads: {res.summary()}")
    print(f"vectorised reachability (with collision margins): {t_vec:.3f} s  ({1e6 * t_vec / args.n:.0f} us/station)")
    print(f"vectorised reachability (mask only):              {t_nodist:.3f} s")
    print(f"baseline per-station loop:                        {t_base:.3f} s")
    print(f"speed-up over the baseline: {t_base / t_vec:.1f}x (mask only {t_base / t_nodist:.1f}x); same answers: {agree}")
    print(f"target <= 2 s: {'met' if t_vec <= 2.0 else 'MISSED'}")


if __name__ == "__main__":
    main()
