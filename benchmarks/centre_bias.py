"""Systematic error of the dot centres on the simulated cell's images of the example part.

Twelve stations around the bracket (three elevations, twelve azimuths) are rendered by the
simulated camera *without* sensor noise; the detector's centres are compared with the exact
projections of the true targets plus the perspective eccentricity of each dot's ellipse and the
renderer's own image jitter. Fully visible, uncoded dots only. Printed: the mean error along the
image of each dot's normal (what a bias of the centring turns into: an offset of the triangulated
point along the normal), the rms error, and both by incidence angle.

    .venv/bin/python -m benchmarks.centre_bias [--part-level 0.08] [--background-kernel 41] [--centre ellipse] [--real]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.camera import invert, look_at, project  # noqa: E402
from calibration.targets import DetectionOptions, detect_retro_targets, eccentricity_bias  # noqa: E402
from cell.devices import make_job_sim_cell  # noqa: E402
from cell.loadedjob import load  # noqa: E402

JOB = Path(__file__).resolve().parents[1] / "examples" / "bracket" / "job.toml"


def measure(part_level: float | None = None, kernel: int = 41, n_views: int = 12, centre_method: str = "centroid",
            real: bool = False) -> dict:
    job = load(JOB)
    sim = make_job_sim_cell(job, nominal_lens=True)  # truth: the nominal lens's projection
    cam, world, intr = sim.camera, sim.world, job.intrinsics
    if part_level is not None:
        cam.photometry = dataclasses.replace(cam.photometry, part_level=part_level)
    xyz, nrm = world.true_xyz, world.normals
    centre = xyz.mean(axis=0)
    index = {t: i for i, t in enumerate(job.part.targets.ids)}
    along, err, inc = [], [], []
    for k in range(n_views):
        az, el = 2 * np.pi * k / n_views, np.deg2rad(35 + 15 * (k % 3))
        eye = centre + 0.55 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        part_from_cam = look_at(eye, centre)
        cam_from_part = invert(part_from_cam)
        img, truth = cam.render(part_from_cam, noise=False)
        opts = (DetectionOptions.for_real_images(centre=centre_method) if real
                else DetectionOptions(background_kernel_px=kernel, centre=centre_method))
        det = detect_retro_targets(img, opts)
        ids, kind = np.array(truth["ids"]), np.array(truth["kind"])
        sel = (kind != "coded") & ~np.isin(ids, truth["partial_ids"])
        tid = np.array([index[i] for i in ids[sel]], dtype=int)
        uv = (project(intr, cam_from_part, xyz[tid])
              + eccentricity_bias(intr, cam_from_part, xyz[tid], nrm[tid], job.part.target_diameter_m / 2)
              + np.array(truth["shift_px"])[sel])
        d, j = cKDTree(det.uv).query(uv)
        ok = d < 1.0
        e = det.uv[j[ok]] - uv[ok]
        a = project(intr, cam_from_part, xyz[tid[ok]])
        b = project(intr, cam_from_part, xyz[tid[ok]] + 0.003 * nrm[tid[ok]])
        dn = (b - a) / np.maximum(np.linalg.norm(b - a, axis=1), 1e-9)[:, None]
        v = eye - xyz[tid[ok]]
        along.append(np.einsum("ij,ij->i", e, dn))
        err.append(e)
        inc.append(np.degrees(np.arccos(np.einsum("ij,ij->i", v, nrm[tid[ok]]) / np.linalg.norm(v, axis=1))))
    along, err, inc = np.concatenate(along), np.concatenate(err), np.concatenate(inc)
    bins = {}
    for lo, hi in ((0, 30), (30, 45), (45, 60), (60, 70), (70, 90)):
        s = (inc >= lo) & (inc < hi)
        if s.any():
            bins[f"{lo}-{hi}"] = {"n": int(s.sum()), "rms_px": float(np.sqrt((err[s] ** 2).sum(axis=1).mean())),
                                  "along_normal_px": float(along[s].mean())}
    return {"n": int(len(along)), "along_normal_px": float(along.mean()),
            "rms_px": float(np.sqrt((err**2).sum(axis=1).mean())),
            "p99_px": float(np.percentile(np.linalg.norm(err, axis=1), 99)), "by_incidence_deg": bins}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part-level", type=float, default=None, help="the part's shading (0: a black part)")
    ap.add_argument("--background-kernel", type=int, default=41)
    ap.add_argument("--centre", choices=("centroid", "ellipse"), default="centroid")
    ap.add_argument("--real", action="store_true", help="DetectionOptions.for_real_images() (polarity, kernel found per image)")
    a = ap.parse_args(argv)
    r = measure(a.part_level, a.background_kernel, centre_method=a.centre, real=a.real)
    print(f"{r['n']} dot images: mean error along the normal's image {r['along_normal_px']:+.4f} px, "
          f"rms {r['rms_px']:.4f} px, 99% below {r['p99_px']:.4f} px")
    for k, v in r["by_incidence_deg"].items():
        print(f"  incidence {k:>5s} deg: n {v['n']:4d}, rms {v['rms_px']:.4f} px, along normal {v['along_normal_px']:+.4f} px")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
