"""Ring-coded targets in images that are not ours, against the codes their authors printed.

Data (read from local clones, not copied into this repository; the search tool's ``fetch`` gives them):

* ``poxiao2/CCTDecode`` (``--cct``): ``CCTDecode/data/cct_bit12_black6.jpg``, a 24 MP phone photograph of
  a laptop screen showing 50 generated 12-bit targets (black on white) in a file browser, sorted by
  name: target k (row-major, 5 rows of 10) is the file ``c.png`` with c = 0, 1, 3, 5, ..., 97 (c = 2k - 1;
  0 is a plain dot). Their own decoder's result image (``CCTDecode/result/cct_bit12_black6.jpg``)
  labels 47 of the 49 (37 and 57 unread). And ``cct_bit8_white2.jpg``: a phone photograph of 8-bit
  targets (white on black) stuck on cabinets; their decoder labels 4 (13, 63, 85, 255); the printed
  labels legible in the photograph: 13, 63, 85.
* ``matthiashar/14-Bit-Circular-Coded-Target-Generation`` (``--sheet``): ``example.JPG``, a rendered
  (not photographed) sheet of DE19733466A1 14-bit targets numbered 1-8 and 17-20 under each target.

Printed: codes read, correct, wrong, missed, and codes read elsewhere in the scene (false codes), and
the time per image, all with ``cell detect``'s defaults (polarity "auto": with ring codes, the polarity
that reads more codes).

    .venv/bin/python -m benchmarks.real_ring_codes [--cct DIR] [--sheet DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.camerafile import CameraFile  # noqa: E402
from cell.detect_cmd import detect_targets  # noqa: E402

#: folder holding the clones as ``owner+name/repo`` (set CELL_REAL_DATA), or pass --cct and --sheet
MIRROR = Path(os.environ.get("CELL_REAL_DATA", "real-data"))


def _read(repo: Path, path: str) -> np.ndarray:
    """An image from a git directory (``git show HEAD:path``) or a work tree."""
    if (repo / path).is_file():
        data = (repo / path).read_bytes()
    else:
        git = repo / ".git" if (repo / ".git").is_dir() else repo
        data = subprocess.run(["git", "--git-dir", str(git), "show", f"HEAD:{path}"], check=True, capture_output=True).stdout
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SystemExit(f"real_ring_codes: cannot decode {path} in {repo}")
    return img


def _read_codes(img: np.ndarray, family: str, polarity: str) -> tuple[np.ndarray, np.ndarray, float]:
    """What ``cell detect`` reads: the coded centres and their codes, and the seconds it took."""
    t0 = time.perf_counter()
    det, code, _, _, _ = detect_targets(img, CameraFile(polarity=polarity, coded_family=family))
    sel = code >= 0
    return det.uv[sel], code[sel], time.perf_counter() - t0


def _grid_check(uv: np.ndarray, code: np.ndarray, rows: int, cols: int, box, expected) -> dict:
    """Codes inside ``box`` (u0, v0, u1, v1) assigned to a rows x cols grid by their order; compared with
    ``expected(r, c)`` (None: a plain dot)."""
    u0, v0, u1, v1 = box
    inside = (uv[:, 0] > u0) & (uv[:, 0] < u1) & (uv[:, 1] > v0) & (uv[:, 1] < v1)
    p, c = uv[inside], code[inside]
    pitch = (v1 - v0) / rows
    want = {(r, k): expected(r, k) for r in range(rows) for k in range(cols) if expected(r, k) is not None}
    got: dict = {}
    for (x, y), cc in zip(p, c):
        r = int(np.clip(np.round((y - v0) / pitch - 0.5), 0, rows - 1))
        k = int(np.clip(np.round((x - u0) / ((u1 - u0) / cols) - 0.5), 0, cols - 1))
        got.setdefault((r, k), []).append(int(cc))
    correct = sum(1 for key, w in want.items() if w in got.get(key, []))
    wrong = sum(1 for key, cs in got.items() for cc in cs if cc != want.get(key))
    return {"expected": len(want), "correct": correct, "wrong_in_grid": wrong,
            "missed": len(want) - correct, "outside": int((~inside).sum())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cct", type=Path, default=MIRROR / "poxiao2+CCTDecode" / "repo")
    ap.add_argument("--sheet", type=Path, default=MIRROR / "matthiashar+14-Bit-Circular-Coded-Target-Generation" / "repo")
    a = ap.parse_args(argv)
    rows = []
    if a.cct.exists():
        img = _read(a.cct, "CCTDecode/data/cct_bit12_black6.jpg")
        uv, code, dt = _read_codes(img, "cct12", "auto")
        # the file browser's grid of icons: 5 rows of 10 between these pixel bounds (measured on the photograph)
        r = _grid_check(uv, code, 5, 10, (2230, 1190, 3560, 1840), lambda i, k: None if i == k == 0 else 2 * (10 * i + k) - 1)
        rows.append(("cct_bit12_black6.jpg (photo, 5632x4224)", r, dt, "their decoder: 47 of 49"))
        img = _read(a.cct, "CCTDecode/data/cct_bit8_white2.jpg")
        uv, code, dt = _read_codes(img, "cct8", "auto")
        legible = {13, 63, 85}
        got = set(int(c) for c in code)
        rows.append(("cct_bit8_white2.jpg (photo, 2268x4032)",
                     {"expected": len(legible), "correct": len(legible & got), "wrong_in_grid": 0,
                      "missed": len(legible - got), "outside": 0}, dt,
                     f"their decoder: 13, 63, 85, 255; ours: {sorted(int(c) for c in code)}, the others' labels not legible"))
    else:
        print(f"real_ring_codes: no clone at {a.cct} (fetch github:poxiao2/CCTDecode); skipped", file=sys.stderr)
    if a.sheet.exists():
        img = _read(a.sheet, "example.JPG")
        uv, code, dt = _read_codes(img, "schneider14", "auto")
        # numbered targets, left to right / top to bottom as printed: 1-8 in two columns, 17-20 in the panels
        want = {1: (236, 236), 2: (1003, 236), 3: (236, 665), 4: (1003, 665), 5: (236, 1094), 6: (1003, 1094),
                7: (236, 1523), 8: (1003, 1523), 17: (1554, 438), 18: (2174, 1318), 19: (3418, 1319), 20: (4352, 879)}
        correct = sum(1 for c, p in want.items() if np.any((code == c) & (np.linalg.norm(uv - p, axis=1) < 20)))
        rows.append(("example.JPG (rendered sheet, 4973x1759)",
                     {"expected": len(want), "correct": correct, "wrong_in_grid": int(np.sum(~np.isin(code, list(want)))),
                      "missed": len(want) - correct, "outside": 0}, dt, "numbers printed under the targets"))
    else:
        print(f"real_ring_codes: no clone at {a.sheet}; skipped", file=sys.stderr)
    if not rows:
        print("real_ring_codes: none of the image sets is here: clone them under CELL_REAL_DATA (owner+name/repo) "
              "or pass --cct / --sheet", file=sys.stderr)
        return 2
    for name, r, dt, note in rows:
        print(f"{name}: {r['correct']}/{r['expected']} read correctly, {r['wrong_in_grid']} wrong, {r['missed']} missed, "
              f"{r['outside']} codes read elsewhere in the scene; {dt:.2f} s ({note})")
    tot = sum(r["expected"] for _, r, _, _ in rows)
    ok = sum(r["correct"] for _, r, _, _ in rows)
    print("BENCHMARK " + json.dumps({
        "what": "ring-coded targets in others' images (CCTDecode photographs, DE19733466A1 sheet)",
        "figure": f"{ok}/{tot} codes read correctly, {sum(r['wrong_in_grid'] for _, r, _, _ in rows)} wrong, "
                  f"{sum(r['outside'] for _, r, _, _ in rows)} false codes elsewhere in the scenes",
        "baseline": "CCTDecode's own decoder on its 12-bit photograph: 47/49", "ratio": ""}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
