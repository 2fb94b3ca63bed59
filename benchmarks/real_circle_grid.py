"""The detector on real photographs that are not ours: ROS-Industrial's 10x10 circle-grid calibration set.

Data: ``examples/data/test_set_10x10`` of github.com/ros-industrial/industrial_calibration (Apache-2.0):
15 colour PNGs (640x480, a Kinect-class RGB camera) of a printed 10x10 grid of black dots on white
paper, 25.4 mm apart, taped to cardboard in a cluttered room. The images are not copied into this
repository; the benchmark reads them from a local clone (``--repo``: a git directory or work tree,
e.g. the search tool's ``fetch`` of ``ros-industrial/industrial_calibration``).

Reference: OpenCV's own circle-grid finder (``cv2.findCirclesGrid``: SimpleBlobDetector centres over
many thresholds), and OpenCV's calibration (``cv2.calibrateCameraExtended``) from those centres. Our
detector runs with the defaults for photographs (``DetectionOptions.for_real_images()``: polarity and
sizes found per image) and nothing tuned. Printed:

* found: the reference's marks that have one of our detections within 2 px (and how many blobs we
  report in all: the clutter around the sheet gives extra blobs that identification must reject);
* centre rms and mean offset of ours from the reference's marks;
* sigma0 (rms reprojection error) of the same calibration (same images, same target-image pairs, same
  model: k1, k2, p1, p2, k3) from the reference's centres and from ours;
* the calibrations side by side, the difference in units of the reference's standard deviation;
* the same from our own chain: Zhang start (``calibration.planar``), then our self-calibrating bundle
  (camera model OPENCV_K3, every grid point truly fixed control) on our centres.

    .venv/bin/python -m benchmarks.real_circle_grid --repo CLONE [--centre ellipse]

CLONE: a clone (work tree or git directory) of github:ros-industrial/industrial_calibration, or set
``CELL_REAL_DATA`` to a folder holding it as ``ros-industrial+industrial_calibration/repo``.
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
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.dots import DetectionOptions, detect_dots  # noqa: E402

DATA = "examples/data/test_set_10x10/images"
ROWS = COLS = 10
SPACING_M = 0.0254
NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def read_images(repo: Path) -> list[tuple[str, np.ndarray]]:
    """The set's images as (name, BGR array), from a git directory (``git show``) or a work tree."""
    tree = repo / DATA
    out = []
    for i in range(15):
        name = f"{i}.png"
        if tree.is_dir():
            data = (tree / name).read_bytes()
        else:
            data = subprocess.run(["git", "--git-dir", str(repo), "show", f"HEAD:{DATA}/{name}"], check=True,
                                  capture_output=True).stdout
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise SystemExit(f"real_circle_grid: cannot decode {name} in {repo}")
        out.append((name, img))
    return out


def calibrate(obj: list[np.ndarray], img: list[np.ndarray], size: tuple[int, int]) -> tuple[float, np.ndarray, np.ndarray]:
    """OpenCV calibration: (rms px, (9,) fx fy cx cy k1 k2 p1 p2 k3, (9,) their standard deviations)."""
    rms, K, dist, _, _, std_int, _, _ = cv2.calibrateCameraExtended(
        [o.astype(np.float32) for o in obj], [i.astype(np.float32).reshape(-1, 1, 2) for i in img], size, None, None)
    d = dist.ravel()
    vals = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], d[0], d[1], d[2], d[3], d[4]])
    return float(rms), vals, std_int.ravel()[:9]


def our_bundle(obj: list[np.ndarray], img: list[np.ndarray], size: tuple[int, int]) -> tuple[float, np.ndarray, np.ndarray, bool]:
    """Our chain: Zhang start (calibration.planar) then our self-calibrating bundle (OPENCV_K3) with every grid
    point as truly fixed control. Returns (sigma0 px, (9,) values as ``calibrate``, (9,) sigmas, converged)."""
    from calibration.bundle import BundleConfig, BundleOptions, ControlPoints, bundle_adjust
    from calibration.planar import planar_calibration

    pts = np.array([(c * SPACING_M, r * SPACING_M, 0.0) for r in range(ROWS) for c in range(COLS)])
    index = [np.array([int(round(p[1] / SPACING_M)) * COLS + int(round(p[0] / SPACING_M)) for p in o]) for o in obj]
    start = planar_calibration([pts[i] for i in index], img, size[0], size[1])
    oi = np.concatenate([np.full(len(i), j) for j, i in enumerate(index)])
    ot = np.concatenate(index)
    ouv = np.concatenate(img)
    cfg = BundleConfig(camera_model="OPENCV_K3", refine_focal_length=True, refine_principal_point=True,
                       refine_distortion=True, control=ControlPoints(np.arange(len(pts)), pts, np.zeros(len(pts))))
    res = bundle_adjust(oi, ot, ouv, start.intrinsics, start.cam_from_part, pts.copy(),
                        BundleOptions(sigma_px=0.2, snooping=False), cfg)
    i = res.intrinsics
    order = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"]
    sd = np.sqrt(np.diag(res.intrinsics_cov))
    sd = np.array([sd[list(res.intrinsics_names).index(n)] for n in order])
    return (float(res.sigma0_px), np.array([i.fx_px, i.fy_px, i.cx_px, i.cy_px, i.k1, i.k2, i.p1, i.p2, i.k3]), sd,
            bool(res.converged))


def run(repo: Path, centre: str = "centroid") -> dict:
    objp = np.array([(c * SPACING_M, r * SPACING_M, 0.0) for r in range(ROWS) for c in range(COLS)])
    opts = DetectionOptions.for_real_images(centre=centre)
    n_ref = n_found = n_blobs = 0
    diffs, obj_l, ref_l, ours_l, times = [], [], [], [], []
    size = None
    for name, im in read_images(repo):
        size = (im.shape[1], im.shape[0])
        ok, cen = cv2.findCirclesGrid(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY), (COLS, ROWS), flags=cv2.CALIB_CB_SYMMETRIC_GRID)
        t0 = time.perf_counter()
        det = detect_dots(im, opts)
        times.append(time.perf_counter() - t0)
        n_blobs += len(det)
        if not ok:
            print(f"  {name}: OpenCV finds no grid; skipped")
            continue
        ref = cen.reshape(-1, 2).astype(float)
        d, j = cKDTree(det.uv).query(ref)
        m = d < 2.0
        n_ref += len(ref)
        n_found += int(m.sum())
        diffs.append(det.uv[j[m]] - ref[m])
        obj_l.append(objp[m])
        ref_l.append(ref[m])
        ours_l.append(det.uv[j[m]])
    diffs_a = np.concatenate(diffs)
    rms_ref, cal_ref, sd_ref = calibrate(obj_l, ref_l, size)
    rms_our, cal_our, sd_our = calibrate(obj_l, ours_l, size)
    s0_b, cal_b, sd_b, conv_b = our_bundle(obj_l, ours_l, size)
    return {"bundle_sigma0": s0_b, "cal_bundle": cal_b, "sd_bundle": sd_b, "bundle_converged": conv_b,"images": len(obj_l), "n_ref": n_ref, "n_found": n_found, "n_blobs": n_blobs,
            "rms_px": float(np.sqrt(np.mean(np.sum(diffs_a**2, axis=1)))), "offset_px": diffs_a.mean(axis=0),
            "sigma0_ref": rms_ref, "sigma0_ours": rms_our, "cal_ref": cal_ref, "sd_ref": sd_ref, "cal_ours": cal_our,
            "sd_ours": sd_our, "ms_per_image": 1e3 * float(np.median(times)), "polarity": opts.polarity}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    data = os.environ.get("CELL_REAL_DATA")
    ap.add_argument("--repo", type=Path,
                    default=Path(data) / "ros-industrial+industrial_calibration" / "repo" if data else None,
                    help="clone of ros-industrial/industrial_calibration (git directory or work tree)")
    ap.add_argument("--centre", choices=("centroid", "ellipse"), default="centroid")
    a = ap.parse_args(argv)
    if a.repo is None or not a.repo.exists():
        print(f"real_circle_grid: no clone at {a.repo}; fetch github:ros-industrial/industrial_calibration", file=sys.stderr)
        return 2
    r = run(a.repo, a.centre)
    print(f"{r['images']} real images, {r['n_ref']} reference marks (OpenCV findCirclesGrid); "
          f"ours found {r['n_found']} ({100 * r['n_found'] / r['n_ref']:.1f}%), {r['n_blobs']} blobs reported in all, "
          f"median {r['ms_per_image']:.1f} ms per 0.3 MP image")
    print(f"centre rms from the reference marks {r['rms_px']:.3f} px, mean offset "
          f"({r['offset_px'][0]:+.3f}, {r['offset_px'][1]:+.3f}) px")
    print(f"sigma0 (rms reprojection, same pairs, same OpenCV calibration): reference centres {r['sigma0_ref']:.4f} px, "
          f"ours {r['sigma0_ours']:.4f} px ({100 * (r['sigma0_ours'] / r['sigma0_ref'] - 1):+.1f}%)")
    print(f"{'':4s} {'reference':>22s} {'ours':>22s} {'diff/sd_ref':>11s}")
    for n, a_, sa, b, sb in zip(NAMES, r["cal_ref"], r["sd_ref"], r["cal_ours"], r["sd_ours"]):
        print(f"{n:4s} {a_:12.5g} +- {sa:8.3g} {b:12.5g} +- {sb:8.3g} {(b - a_) / sa:+11.2f}")
    print(f"our bundle (Zhang start, OPENCV_K3, grid held fixed) on our centres: sigma0 {r['bundle_sigma0']:.4f} px "
          f"per coordinate (OpenCV's rms above is per point: / sqrt 2 = {r['sigma0_ours'] / np.sqrt(2):.4f}), "
          f"converged {r['bundle_converged']}")
    for n, a_, sa, b, sb in zip(NAMES, r["cal_ref"], r["sd_ref"], r["cal_bundle"], r["sd_bundle"]):
        print(f"{n:4s} {a_:12.5g} +- {sa:8.3g} {b:12.5g} +- {sb:8.3g} {(b - a_) / sa:+11.2f}")
    worst_b = np.max(np.abs((r["cal_bundle"] - r["cal_ref"]) / r["sd_ref"]))
    worst = np.max(np.abs((r["cal_ours"] - r["cal_ref"]) / r["sd_ref"]))
    print("BENCHMARK " + json.dumps({
        "what": f"real circle-grid photographs (ROS-Industrial, 15 x 640x480), centre {a.centre}",
        "figure": f"found {100 * r['n_found'] / r['n_ref']:.1f}%, {r['rms_px']:.3f} px from OpenCV's marks, calibration "
                  f"within {worst:.2f} sd of OpenCV's (our bundle: {worst_b:.2f} sd)",
        "baseline": f"sigma0 from OpenCV's own centres {r['sigma0_ref']:.4f} px",
        "ratio": f"sigma0 ours/theirs {r['sigma0_ours'] / r['sigma0_ref']:.3f}"}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
