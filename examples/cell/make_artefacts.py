"""Regenerate the example cell's artefacts (mm): the hand-eye target field and the scale bar.

    python examples/cell/make_artefacts.py

* ``field.stl`` / ``field_targets.csv``: a 300 x 240 x 10 mm plate with three raised blocks
  (20, 35 and 50 mm), retro dots on every top face (the field is not coplanar, so Faugeras-Toscani
  works on each image) and 8 ArUco-coded targets for identification.
* ``bar.stl`` / ``bar_targets.csv``: a 460 x 30 x 20 mm scale bar; targets A and B 400 mm apart,
  five more dots and four coded targets along its top face.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent
BLOCKS = [((-95.0, 60.0), 60.0, 20.0), ((90.0, 55.0), 60.0, 35.0), ((0.0, -60.0), 60.0, 50.0)]  # centre, side, height


def _box(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    b = trimesh.creation.box(extents=hi - lo)
    b.apply_translation((lo + hi) / 2)
    return b


def _write(path, rows):
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["id", "x", "y", "z", "nx", "ny", "nz", "kind", "tolerance", "code"])
        for r in rows:
            w.writerow(r)


def field() -> None:
    parts = [_box((-150, -120, 0), (150, 120, 10))]
    for (cx, cy), s, h in BLOCKS:
        parts.append(_box((cx - s / 2, cy - s / 2, 10), (cx + s / 2, cy + s / 2, 10 + h)))
    trimesh.util.concatenate(parts).export(HERE / "field.stl")
    coded = [(-130, -100), (130, -100), (-130, 100), (130, 100), (0, 100), (-60, 0), (60, 0), (-130, 0)]
    rows, k = [], 0

    def near_block(x, y, m):
        return any(abs(x - cx) < s / 2 + m and abs(y - cy) < s / 2 + m for (cx, cy), s, _ in BLOCKS)

    for x in np.arange(-135, 136, 27.0):
        for y in np.arange(-108, 109, 27.0):
            if near_block(x, y, 12) or min(np.hypot(x - a, y - b) for a, b in coded) < 22:
                continue
            rows.append([f"F{k:03d}", f"{x:.3f}", f"{y:.3f}", "10.000", 0, 0, 1, "retro", "", -1])
            k += 1
    for (cx, cy), s, h in BLOCKS:
        for dx, dy in ((-18, -18), (18, -18), (-18, 18), (18, 18), (0, 0)):
            rows.append([f"F{k:03d}", f"{cx + dx:.3f}", f"{cy + dy:.3f}", f"{10 + h:.3f}", 0, 0, 1, "retro", "", -1])
            k += 1
    for i, (x, y) in enumerate(coded):
        rows.append([f"C{i}", f"{x:.3f}", f"{y:.3f}", "10.000", 0, 0, 1, "coded", "", 100 + i])
    _write(HERE / "field_targets.csv", rows)


def bar() -> None:
    _box((-230, -15, 0), (230, 15, 20)).export(HERE / "bar.stl")
    rows = [["A", "-200.000", "0.000", "20.000", 0, 0, 1, "retro", "", -1],
            ["B", "200.000", "0.000", "20.000", 0, 0, 1, "retro", "", -1]]
    for i, x in enumerate((-160, -80, 0, 80, 160)):
        rows.append([f"D{i}", f"{x:.3f}", "0.000", "20.000", 0, 0, 1, "retro", "", -1])
    for i, x in enumerate((-120, -40, 40, 120)):
        rows.append([f"K{i}", f"{x:.3f}", "0.000", "20.000", 0, 0, 1, "coded", "", 120 + i])
    _write(HERE / "bar_targets.csv", rows)


if __name__ == "__main__":
    field()
    bar()
