"""Regenerate the bracket example's files: bracket.stl (mm), targets.csv, deviations.csv.

    python examples/bracket/make_example.py

The part is planning.part.make_bracket(); 200 targets (8 of them ArUco-coded) are
sampled on it with a fixed seed; a handful get a known deviation for the simulated
cell, so the inspection report has something real to find.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from planning.part import make_bracket, sample_targets

HERE = Path(__file__).resolve().parent


def _measurable(mesh, targets):
    """Keep the targets that at least 4 reachable candidate stations of the example cell can measure
    (as an engineer places targets where the cell can see them)."""
    from dataclasses import replace

    from cell.jobspec import load_job
    from cell.loadedjob import LoadedJob
    from cell.setup import collision_world, planner_options, robot_model
    from planning.part import Part
    from planning.reachability import ReachabilityDB
    from planning.visibility import VisibilityDB

    spec, folder = load_job(HERE / "job.toml")  # the cell and camera of the example (not its targets)
    k = spec.scale
    part = Part("bracket", mesh, targets, spec.job.target_diameter * k, spec.job.coded_size * k)
    job = LoadedJob(spec, HERE / "job.toml", folder, part, spec.intrinsics(), np.zeros((len(targets), 3)),
                    np.full(len(targets), spec.report.tolerance * k))
    o = planner_options(job)
    sphere = replace(o.sphere, max_roll_rad=0.0, max_offset_m=0.0)
    vis = replace(o.visibility, incidence_max_rad=o.incidence_max_rad)
    db = VisibilityDB.load_or_build(part, job.intrinsics, sphere, vis, o.n_candidates)
    reach = ReachabilityDB.load_or_build(robot_model(job), job.spec.base_from_part(), job.spec.flange_from_cam(),
                                         db.part_from_cam, collision_world(job))
    keep = db.visible[reach.reachable].sum(axis=0) >= 4
    idx = np.flatnonzero(keep)
    out = targets.subset(idx)
    # renumber the retro targets so ids stay T0000..; coded keep their codes
    out.ids = [f"C{c}" if k == "coded" else f"T{i:04d}" for i, (k, c) in enumerate(zip(out.kind, out.code))]
    return out


def main() -> None:
    mesh = make_bracket()
    rng = np.random.default_rng(20261121)
    targets = sample_targets(mesh, 250, rng, n_coded=8, edge_clearance_m=0.012, min_normal_z=-0.5,
                             coded_clearance_m=0.02 * (0.5 + 1 / 6) * np.sqrt(2) + 0.0025 + 0.001)
    targets = _measurable(mesh, targets).subset(np.arange(200))
    mm = mesh.copy()
    mm.apply_scale(1000.0)
    mm.export(HERE / "bracket.stl")
    with (HERE / "targets.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["id", "x", "y", "z", "nx", "ny", "nz", "kind", "tolerance", "code"])
        for i, t in enumerate(targets.ids):
            p = targets.xyz[i] * 1000.0
            n = targets.normals[i]
            tol = 0.25 if targets.kind[i] == "retro" else ""
            w.writerow([t, *(f"{v:.4f}" for v in p), *(f"{v:.6f}" for v in n), targets.kind[i], tol, targets.code[i]])
    # deviations: 6 retro targets pushed out along their normal: 3 within tolerance, 3 beyond
    retro = np.flatnonzero(targets.kind == "retro")
    pick = rng.choice(retro, size=6, replace=False)
    with (HERE / "deviations.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["id", "dx", "dy", "dz"])
        for k, i in enumerate(sorted(pick)):
            d = targets.normals[i] * (0.12, 0.16, 0.2, 0.4, 0.5, 0.6)[k]
            w.writerow([targets.ids[i], *(f"{v:.4f}" for v in d)])
    # the scale bar: the two undeviated retro targets farthest apart (calibrated on a CMM, say)
    ok = np.flatnonzero((targets.kind == "retro") & ~np.isin(np.arange(len(targets)), pick))
    d = np.linalg.norm(targets.xyz[ok, None] - targets.xyz[None, ok], axis=2)
    a, b = np.unravel_index(np.argmax(d), d.shape)
    print(f"scale bar {targets.ids[ok[a]]}-{targets.ids[ok[b]]} length {d[a, b] * 1000:.4f} mm")


if __name__ == "__main__":
    main()
