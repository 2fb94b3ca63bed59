"""Target sampling and targets-CSV loading at the job file's maximum (100,000 targets).

Run: .venv/bin/python benchmarks/bench_sampling.py [--max 100000] [--baseline 2000,4000]
Prints the time of ``sample_targets`` (vectorised greedy spacing + facet clearance) for a few
sizes on a large box part, and, for the baseline sizes, the time of the former sequential
implementation (a Python loop over candidates against every accepted target, and a per-point
facet-clearance loop) run here on the same candidates, with the ratio, after checking that both
keep exactly the same targets. Then writes a CSV of the largest set and times ``load_targets``
with the peak memory it allocated (tracemalloc).
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
import trimesh

from planning.part import check_targets, load_targets, sample_targets
from planning.target_sampling import facet_clearance, greedy_spaced


def part_mesh() -> trimesh.Trimesh:
    """A 3 x 2 x 1 m box with its faces split into a fine triangulation (22 m^2: room for 100,000 dots)."""
    box = trimesh.creation.box(extents=(3.0, 2.0, 1.0))
    return box.subdivide().subdivide().subdivide()


def sequential_greedy(pts: np.ndarray, n: int, spacing: float) -> np.ndarray:
    """The former implementation: one candidate at a time against every accepted target."""
    chosen: list[int] = []
    tree_pts: list[np.ndarray] = []
    for i in range(len(pts)):
        if len(chosen) >= n:
            break
        if spacing > 0 and tree_pts:
            if np.linalg.norm(np.asarray(tree_pts) - pts[i], axis=1).min() < spacing:
                continue
        chosen.append(i)
        tree_pts.append(pts[i])
    return np.array(chosen)


def sequential_clearance(mesh, pts, faces) -> np.ndarray:
    """The former implementation: a Python loop over points."""
    face_to_facet = np.full(len(mesh.faces), -1)
    for k, f in enumerate(mesh.facets):
        face_to_facet[f] = k
    out = np.full(len(pts), np.inf)
    boundaries = mesh.facets_boundary
    for i, (p, f) in enumerate(zip(pts, faces)):
        k = face_to_facet[f]
        seg = mesh.vertices[mesh.faces[f]][np.array([[0, 1], [1, 2], [2, 0]])] if k < 0 else mesh.vertices[boundaries[k]]
        a, b = seg[:, 0], seg[:, 1]
        ab = b - a
        t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-30), 0, 1)
        out[i] = np.linalg.norm(a + t[:, None] * ab - p, axis=1).min()
    return out


def candidates(mesh, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """The candidates sample_targets draws (20 n points on the surface by area) and their faces."""
    m = max(20 * n, 2000)
    faces = rng.choice(len(mesh.faces), size=m, p=mesh.area_faces / mesh.area)
    r = rng.random((m, 2))
    flip = r.sum(axis=1) > 1
    r[flip] = 1 - r[flip]
    tri = mesh.triangles[faces]
    return tri[:, 0] + r[:, :1] * (tri[:, 1] - tri[:, 0]) + r[:, 1:] * (tri[:, 2] - tri[:, 0]), faces


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--max", type=int, default=100_000)
    ap.add_argument("--baseline", default="2000,4000", help="sizes at which the sequential version also runs")
    args = ap.parse_args()
    mesh = part_mesh()
    print(f"part: box 3 x 2 x 1 m, {len(mesh.faces)} triangles, {mesh.area:.1f} m^2")

    base = None
    for n in [int(v) for v in args.baseline.split(",") if v]:
        pts, faces = candidates(mesh, n, np.random.default_rng(n))
        spacing = 0.6 * np.sqrt(mesh.area / n)
        t = time.perf_counter()
        fast = greedy_spaced(pts, n, spacing)
        clear_fast = facet_clearance(mesh, pts, faces)
        t_fast = time.perf_counter() - t
        t = time.perf_counter()
        slow = sequential_greedy(pts, n, spacing)
        clear_slow = sequential_clearance(mesh, pts, faces)
        t_slow = time.perf_counter() - t
        assert np.array_equal(fast, slow), "the vectorised greedy keeps other targets than the sequential one"
        assert np.allclose(clear_fast, clear_slow, rtol=0, atol=1e-12)
        base = (n, t_fast, t_slow)
        print(f"n = {n:>6}: spacing + clearance vectorised {t_fast:7.3f} s, sequential {t_slow:7.2f} s, "
              f"ratio {t_slow / t_fast:6.1f}x (same {len(fast)} targets, same clearances)")

    sizes = sorted({2000, 8000, 25_000, args.max})
    last, t_max = None, 0.0
    for n in sizes:
        t = time.perf_counter()
        last = sample_targets(mesh, n, np.random.default_rng(1), n_coded=8, edge_clearance_m=0.004,
                              coded_clearance_m=0.02)
        t_max = time.perf_counter() - t
        print(f"sample_targets n = {n:>6}: {t_max:7.2f} s ({len(last)} targets kept)")
    t = time.perf_counter()
    check_targets(mesh, last, target_diameter_m=0.003, coded_size_m=0.01)
    print(f"check_targets (on the surface, overlaps, under a marker) n = {len(last)}: {time.perf_counter() - t:.2f} s")

    with tempfile.TemporaryDirectory() as tmp:
        csv_path = Path(tmp) / "targets.csv"
        with open(csv_path, "w") as f:
            f.write("id,x,y,z,nx,ny,nz,kind,tolerance,code\n")
            for i in range(len(last)):
                x, y, z = last.xyz[i] * 1e3
                nx, ny, nz = last.normals[i]
                f.write(f"{last.ids[i]},{x:.4f},{y:.4f},{z:.4f},{nx:.6f},{ny:.6f},{nz:.6f},{last.kind[i]},,"
                        f"{last.code[i] if last.code[i] >= 0 else ''}\n")
        size_mb = csv_path.stat().st_size / 1e6
        t = time.perf_counter()
        loaded = load_targets(csv_path, "mm")
        dt = time.perf_counter() - t
        tracemalloc.start()  # a second read, traced (tracemalloc slows it down several times)
        load_targets(csv_path, "mm")
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert len(loaded) == len(last) and np.allclose(loaded.xyz, last.xyz, atol=1e-6)
        print(f"load_targets: {len(loaded)} targets from a {size_mb:.1f} MB CSV in {dt:.2f} s, "
              f"peak {peak / 1e6:.0f} MB allocated")
    summary = {"what": "target sampling and targets CSV (100,000 targets)",
               "figure": f"{args.max} sampled in {t_max:.2f} s; CSV of {len(loaded)} read in {dt:.2f} s "
                         f"(peak {peak / 1e6:.0f} MB)"}
    if base is not None:
        summary |= {"baseline": f"sequential greedy + per-point clearance at n = {base[0]}: {base[2]:.2f} s",
                    "ratio": f"{base[2] / base[1]:.0f}x faster at n = {base[0]}"}
    print("BENCHMARK " + json.dumps(summary), flush=True)


if __name__ == "__main__":
    main()
