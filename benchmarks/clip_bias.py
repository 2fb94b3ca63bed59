"""How a clipped dot's centre leans along the image of its normal, at an exposure, against the rendered truth.

The simulated cell's camera renders the example part from random views (with its noise) at the job's exposure
times ``--exposure-factor``, and the detector centres each image. A clipped dot's centre is the middle of its
contour's centres with the ground followed by 0.5 and by 1, and its ``Detections.clip_bound`` half their difference
(decision 0050): the centre less the bound is the contour's at 0.5, as if just clipped, the detector before that
decision and the baseline here. Printed per class of the share of a dot's pixels the sensor clipped: the mean error
along the image of the dot's normal (a lean the views of a target share), its standard error, and the rms bound;
then the ratio of the deeply clipped dots' lean to the baseline's.

    .venv/bin/python -m benchmarks.clip_bias [--exposure-factor 5] [--views 24] [--part-level 0.08] [--seed 0]

``--part-level 0``: a black part, no ground behind the dots (the lean goes with it).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.camera import invert, look_at, project  # noqa: E402
from calibration.targets import DetectionOptions, detect_retro_targets, eccentricity_bias  # noqa: E402
from cell.devices import make_job_sim_cell  # noqa: E402
from cell.loadedjob import load  # noqa: E402
from tests.jobutil import job_variant  # noqa: E402

CLASSES = ((0.0, 0.0, "not clipped"), (1e-9, 0.5, "clipped < 50 %"), (0.5, 0.7, "clipped 50-70 %"),
           (0.7, 0.8, "clipped 70-80 %"), (0.8, 1.01, "clipped >= 80 %"))


def measure(exposure_factor: float, n_views: int, part_level: float | None, seed: int) -> dict:
    base = load(job_variant(Path(tempfile.mkdtemp()) / "job"))
    job = load(job_variant(Path(tempfile.mkdtemp()) / "job",
                           {"camera": {"exposure_s": base.spec.camera.exposure_s * exposure_factor}}))
    sim = make_job_sim_cell(job, nominal_lens=True)  # truth: the nominal lens's projection
    cam, world, intr = sim.camera, sim.world, job.intrinsics
    if part_level is not None:
        cam.photometry = dataclasses.replace(cam.photometry, part_level=part_level)
    cam.rng = np.random.default_rng(seed + 1)
    xyz, nrm, radius = world.true_xyz, world.normals, job.part.target_diameter_m / 2
    centre = xyz.mean(axis=0)
    index = {t: i for i, t in enumerate(job.part.targets.ids)}
    rng = np.random.default_rng(seed)
    variants = ("baseline", "now")
    rows: dict[str, list] = {s: [] for s in variants}
    for _ in range(n_views):
        az, el = rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(8, 85))
        eye = centre + rng.uniform(0.35, 0.7) * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        P = look_at(eye, centre + rng.normal(0, 0.02, 3), roll_rad=rng.uniform(-np.pi, np.pi))
        C = invert(P)
        img, truth = cam.render(P)
        ids, kind = np.array(truth["ids"]), np.array(truth["kind"])
        sel = (kind != "coded") & ~np.isin(ids, truth["partial_ids"])
        tid = np.array([index[i] for i in ids[sel]], dtype=int)
        uv = project(intr, C, xyz[tid]) + eccentricity_bias(intr, C, xyz[tid], nrm[tid], radius)
        step = project(intr, C, xyz[tid] + 1e-3 * nrm[tid]) - project(intr, C, xyz[tid])
        normal = step / np.maximum(np.linalg.norm(step, axis=1, keepdims=True), 1e-12)
        det = detect_retro_targets(img, DetectionOptions())
        d, j = cKDTree(det.uv).query(uv)
        ok = d < 1.0
        share = det.saturated[j[ok]] / np.maximum(det.area_px[j[ok]], 1)
        bound = det.clip_bound[j[ok]]
        for s, found in (("baseline", det.uv[j[ok]] - bound), ("now", det.uv[j[ok]])):
            along = np.einsum("ij,ij->i", found - uv[ok], normal[ok])
            rows[s].append(np.column_stack([share, along, np.linalg.norm(bound, axis=1)]))
    out = {}
    for s in variants:
        R = np.concatenate(rows[s])
        out[s] = []
        for lo, hi, name in CLASSES:
            q = (R[:, 0] == 0) if hi == 0 else (R[:, 0] >= lo) & (R[:, 0] < hi)
            if q.sum() >= 5:
                out[s].append({"class": name, "n": int(q.sum()), "lean_px": float(R[q, 1].mean()),
                               "sem_px": float(R[q, 1].std() / np.sqrt(q.sum())),
                               "bound_rms_px": float(np.sqrt(np.mean(R[q, 2] ** 2)))})
        deep = R[:, 0] >= 0.7
        out[s] = {"classes": out[s], "deep_lean_px": float(R[deep, 1].mean()) if deep.any() else float("nan"),
                  "deep_n": int(deep.sum())}
    return {"variants": variants, "by_variant": out}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--exposure-factor", type=float, default=5.0, help="times the example job's exposure")
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--part-level", type=float, default=None, help="the part's shading (0: a black part)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    r = measure(a.exposure_factor, a.views, a.part_level, a.seed)
    base, now = r["variants"]
    for s in (base, now):
        tag = "baseline (the contour following the ground by 0.5)" if s == base else "the detector (decision 0050)"
        print(f"{tag}:")
        for c in r["by_variant"][s]["classes"]:
            print(f"  {c['class']:16s} n {c['n']:5d}  lean along the normal {c['lean_px']:+.4f} +- {c['sem_px']:.4f} px"
                  f"  bound rms {c['bound_rms_px']:.4f} px")
    lb, ln = r["by_variant"][base]["deep_lean_px"], r["by_variant"][now]["deep_lean_px"]
    print(f"dots clipped over 70 % ({r['by_variant'][now]['deep_n']}): lean {ln:+.4f} px against the baseline's "
          f"{lb:+.4f} px: ratio {ln / lb if lb else float('nan'):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
