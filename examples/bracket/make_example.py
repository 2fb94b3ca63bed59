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


def main() -> None:
    mesh = make_bracket()
    rng = np.random.default_rng(20261121)
    targets = sample_targets(mesh, 200, rng, n_coded=8, edge_clearance_m=0.012, min_normal_z=-0.5)
    mm = mesh.copy()
    mm.apply_scale(1000.0)
    mm.export(HERE / "bracket.stl")
    with (HERE / "targets.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["id", "x", "y", "z", "nx", "ny", "nz", "kind", "tolerance", "code"])
        for i, t in enumerate(targets.ids):
            p = targets.xyz[i] * 1000.0
            n = targets.normals[i]
            tol = 0.05 if targets.kind[i] == "retro" else ""
            w.writerow([t, *(f"{v:.4f}" for v in p), *(f"{v:.6f}" for v in n), targets.kind[i], tol, targets.code[i]])
    # deviations: 6 retro targets pushed out along their normal by 0.15-0.4 mm
    retro = np.flatnonzero(targets.kind == "retro")
    pick = rng.choice(retro, size=6, replace=False)
    with (HERE / "deviations.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["id", "dx", "dy", "dz"])
        for k, i in enumerate(sorted(pick)):
            d = targets.normals[i] * (0.15 + 0.05 * k)
            w.writerow([targets.ids[i], *(f"{v:.4f}" for v in d)])
    c0, c1 = (np.flatnonzero(targets.code == c)[0] for c in (0, 1))
    print(f"scale bar C0-C1 length {np.linalg.norm(targets.xyz[c0] - targets.xyz[c1]) * 1000:.4f} mm")


if __name__ == "__main__":
    main()
