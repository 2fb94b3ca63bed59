"""Ray-casting throughput and visibility-database build time on the example part.

Run: .venv/bin/python benchmarks/bench_visibility.py [--targets 1000] [--candidates 3000]
Prints rays/s for the Embree segment test (the 'embree' backend), trimesh's
RayMeshIntersector.intersects_any on the same rays (for comparison), the NumPy backend
on a subset, and the end-to-end build time of the visibility database.
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from calibration.camera import Intrinsics
from planning.part import Part, make_bracket, sample_targets
from planning.stations import ViewingSphere
from planning.visibility import Occluder, VisibilityDB, VisibilityOptions


def example(n_targets: int, seed: int = 0) -> tuple[Part, Intrinsics]:
    mesh = make_bracket()
    part = Part("bracket", mesh, sample_targets(mesh, n_targets, np.random.default_rng(seed)))
    intr = Intrinsics.from_focal_length(0.012, 3.45e-6, 2448, 2048)
    return part, intr


def best_of(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--targets", type=int, default=1000)
    ap.add_argument("--candidates", type=int, default=3000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    part, intr = example(args.targets)
    sphere = ViewingSphere.for_part(part, intr)
    genes = sphere.candidates(-(-args.candidates // 3), 3)
    T = sphere.poses(genes)
    opts = VisibilityOptions()
    xyz, nrm = part.targets.xyz, part.targets.normals
    m, n = len(T), len(xyz)
    ci, ti = np.divmod(np.arange(m * n), n)
    starts = xyz[ti] + opts.ray_offset_m * nrm[ti]
    ends = T[ci, :3, 3]
    print(f"part: {part.name}, {len(part.mesh.faces)} triangles, {n} targets; {m} candidate stations; "
          f"{os.cpu_count()} cpus")

    occ = Occluder(part.mesh, "embree")
    occ.occluded(starts[:1000], ends[:1000])
    dt = best_of(lambda: occ.occluded(starts, ends), args.repeats)
    hit = occ.occluded(starts, ends)
    print(f"embree segment test (all {m * n:,} candidate x target rays, 2 threads): {dt:.3f} s, "
          f"{m * n / dt / 1e6:.1f} M rays/s ({hit.mean():.1%} occluded)")
    occ1 = Occluder(part.mesh, "embree", workers=1)
    dt1 = best_of(lambda: occ1.occluded(starts, ends), args.repeats)
    print(f"embree segment test, 1 thread: {m * n / dt1 / 1e6:.1f} M rays/s")

    from trimesh.ray.ray_pyembree import RayMeshIntersector

    tri = RayMeshIntersector(part.mesh)
    dirs = ends - starts
    k = min(len(starts), 1_000_000)
    dtt = best_of(lambda: tri.intersects_any(starts[:k], dirs[:k]), args.repeats)
    print(f"trimesh ray_pyembree intersects_any (infinite rays, 1 thread), {k:,} rays: {k / dtt / 1e6:.1f} M rays/s")

    k_np = 20_000
    sel = np.random.default_rng(0).choice(len(starts), k_np, replace=False)
    occ_np = Occluder(part.mesh, "numpy")
    dtn = best_of(lambda: occ_np.occluded(starts[sel], ends[sel]), 1)
    agree = np.mean(occ_np.occluded(starts[sel], ends[sel]) == hit[sel])
    print(f"numpy backend, {k_np:,} rays: {k_np / dtn / 1e6:.3f} M rays/s; agrees with embree on {agree:.4%}")

    t = time.perf_counter()
    db = VisibilityDB.build(part, intr, sphere, opts, n_candidates=args.candidates)
    dtb = time.perf_counter() - t
    seen = db.visible.sum(axis=0)
    print(f"visibility database build ({m} candidates x {n} targets, geometric tests + occlusion): {dtb:.2f} s; "
          f"{db.visible.mean():.1%} of pairs measurable; targets seen by >= 2 candidates: {np.mean(seen >= 2):.1%}")


if __name__ == "__main__":
    main()
