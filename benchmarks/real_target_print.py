"""The worn-target checks (decision 0051) on real photographs that are not ours: do whole printed dots pass?

Data: ROS-Industrial's 10x10 circle-grid set (``benchmarks.real_circle_grid``: 15 colour photographs, 640x480, of
black dots printed on white paper and taped to cardboard). The dots are taken as whole. Each dot of the grid
(OpenCV's ``findCirclesGrid`` orders them) is a target, and each photograph is a view of it. Our detector runs with
the defaults for photographs and the outline on (``DetectionOptions.for_real_images(outline=True)``, as MEASURE runs
it). The views are judged as the cell judges a job (``cell.stages.outline.outline_doubtful``).

Printed:
* per view: the outline ratio (each contour's misfit over the set's median) and the centroid score (the centroid
  against the contour's ellipse centre, scaled to chi-square(2)), by percentile;
* per target: the largest median over its views, against the limits;
* the targets flagged (whole dots: a flag is a false alarm);
* the baseline, in the same process: the same figures on synthetic whole dots (``tests.test_outline``'s renderer:
  8-bit, 0.7 px blur, shot and read noise), and the ratio of the contours' absolute misfit (chi2 / (n - 5), median)
  between the photographs and the synthetic dots. The limits are relative to each job's own dots because that
  figure is not one.

    .venv/bin/python -m benchmarks.real_target_print --repo CLONE

CLONE as for ``benchmarks.real_circle_grid``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.real_circle_grid import COLS, ROWS, read_images  # noqa: E402
from calibration.dots import DetectionOptions, detect_dots  # noqa: E402
from cell.stages.outline import CENTROID_LIMIT, MIN_VIEWS, OUTLINE_LIMIT, _scores, outline_doubtful  # noqa: E402


def _record(det, ids: list[str], index: np.ndarray) -> dict:
    """observations.json's figures for the detections ``index`` named ``ids`` (as MEASURE writes them)."""
    ol = det.outline[index, :2]
    sh, sc = det.centroid_shift[index], det.centroid_shift_cov[index]
    cc = np.full(len(index), np.nan)
    fin = np.isfinite(sh).all(axis=1) & np.isfinite(sc).all(axis=(1, 2))
    fin[fin] &= np.linalg.det(sc[fin]) > 0
    cc[fin] = np.einsum("ka,ka->k", sh[fin], np.linalg.solve(sc[fin], sh[fin][..., None])[..., 0])
    return {"ids": ids, "outline": [[None if not np.isfinite(v) else float(v) for v in r] for r in ol],
            "centroid_chi2": [None if not np.isfinite(v) else float(v) for v in cc],
            "clipped_share": [0.0] * len(ids)}


def _figures(obs: dict, ids: list[str]) -> dict:
    index = {t: k for k, t in enumerate(ids)}
    tgt, ratio, score = _scores(obs, index)
    per = {}
    for name, v in (("outline", ratio), ("centroid", score)):
        med = [float(np.median(x[np.isfinite(x)])) for t in np.unique(tgt) for x in [v[tgt == t]]
               if np.isfinite(x).sum() >= MIN_VIEWS]
        per[name] = {"view_p50": float(np.nanpercentile(v, 50)), "view_p99": float(np.nanpercentile(v, 99)),
                     "view_max": float(np.nanmax(v)), "target_median_max": max(med) if med else None,
                     "targets_judged": len(med)}
    chi = np.array([r[0] / max(r[1] - 5, 1) for im in obs["images"] for r in im["outline"] if r[0] is not None])
    flagged = outline_doubtful(obs, ids)
    return {"views": len(tgt), "per": per, "abs_misfit_median": float(np.median(chi)),
            "flagged": {ids[t]: d["why"] for t, d in flagged.items()}}


def real(repo: Path) -> dict:
    opts = DetectionOptions.for_real_images(outline=True)
    ids = [f"G{r}{c}" for r in range(ROWS) for c in range(COLS)]
    images = []
    for name, im in read_images(repo):
        ok, cen = cv2.findCirclesGrid(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY), (COLS, ROWS), flags=cv2.CALIB_CB_SYMMETRIC_GRID)
        if not ok:
            continue
        det = detect_dots(im, opts)
        d, j = cKDTree(det.uv).query(cen.reshape(-1, 2).astype(float))
        m = d < 2.0
        images.append(_record(det, [ids[k] for k in np.flatnonzero(m)], j[m]))
    return _figures({"images": images}, ids)


def synthetic(views: int = 15, seed: int = 0) -> dict:
    from tests.test_outline import _match, _render

    rng = np.random.default_rng(seed)
    n = 21
    ids = [f"S{k:02d}" for k in range(n)]
    images = []
    for _ in range(views):
        uv = np.stack([40 + 60 * (np.arange(n) % 7), 40 + 70 * (np.arange(n) // 7)], axis=1) + rng.uniform(-0.5, 0.5, (n, 2))
        det = detect_dots(_render(rng, uv, rng.uniform(4.0, 8.0), [None] * n, h=250, w=460), DetectionOptions(outline=True))
        images.append(_record(det, ids, _match(det, uv)))
    return _figures({"images": images}, ids)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repo", type=Path, default=None)
    a = ap.parse_args(argv)
    repo = a.repo or (Path(os.environ["CELL_REAL_DATA"]) / "ros-industrial+industrial_calibration" / "repo"
                      if "CELL_REAL_DATA" in os.environ else None)
    if repo is None:
        raise SystemExit("real_target_print: give --repo (a clone of ros-industrial/industrial_calibration) or set "
                         "CELL_REAL_DATA")
    r, s = real(repo), synthetic()
    for label, f in (("photographs (whole printed dots)", r), ("synthetic whole dots (baseline)", s)):
        o, c = f["per"]["outline"], f["per"]["centroid"]
        print(f"{label}: {f['views']} views; outline ratio per view p50 {o['view_p50']:.2f} p99 {o['view_p99']:.2f} "
              f"max {o['view_max']:.2f}, per target median at most {o['target_median_max']:.2f} "
              f"(limit {OUTLINE_LIMIT:g}, {o['targets_judged']} targets judged); centroid score per view p50 "
              f"{c['view_p50']:.2f} p99 {c['view_p99']:.2f} max {c['view_max']:.2f}, per target median at most "
              f"{c['target_median_max']:.2f} (limit {CENTROID_LIMIT:g}); flagged {len(f['flagged'])}"
              + (f": {f['flagged']}" if f["flagged"] else ""))
    ratio = r["abs_misfit_median"] / s["abs_misfit_median"]
    print(f"contour misfit chi2/(n-5), median: photographs {r['abs_misfit_median']:.2f}, synthetic "
          f"{s['abs_misfit_median']:.2f}; ratio {ratio:.2f}")
    print("BENCHMARK " + json.dumps({
        "what": "worn-target checks on whole printed dots (ROS-Industrial 10x10 circle grid, 15 photographs)",
        "figure": f"{len(r['flagged'])} of {r['per']['outline']['targets_judged']} whole targets flagged; per-target "
                  f"median outline ratio at most {r['per']['outline']['target_median_max']:.2f} (limit "
                  f"{OUTLINE_LIMIT:g}), centroid score at most {r['per']['centroid']['target_median_max']:.2f} "
                  f"(limit {CENTROID_LIMIT:g})",
        "baseline": f"synthetic whole dots: {len(s['flagged'])} flagged, at most "
                    f"{s['per']['outline']['target_median_max']:.2f} / {s['per']['centroid']['target_median_max']:.2f}",
        "ratio": f"absolute contour misfit photographs / synthetic {ratio:.2f}"}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
