"""Monte Carlo of the whole measurement on simulated images: is the stated uncertainty honest?

The example job (examples/bracket) is run ``--runs`` times on the simulated cell, each run with a
different ``[sim] seed`` (new sensor noise, new image jitter; same part, same deviations, same
plan). Every run renders its images, detects and identifies the dots, orients the images
(Faugeras-Toscani), runs the bundle adjustment with self-calibration and reports coordinates with
their covariance, exactly as ``cell run`` does. Against the truth (CAD + injected deviations, after
a rigid fit, as the end-to-end test compares):

* ``m^2``: the squared Mahalanobis distance of each target's error under its stated covariance;
  for an honest covariance its mean is 3, and ``sqrt(mean m^2 / 3)`` is the empirical / reported
  sigma ratio (issue 7's target: 1.00 +- 0.10 over >= 40 runs);
* the share of targets inside their 3-sigma ellipsoid (chi-square, 3 degrees of freedom);
* per target, the rms error over the runs / the rms stated sigma (median over the targets);
* the same ratio by each target's class of largest incidence among its rays (< 50, 50-70, >= 70 deg);
* interior orientation: the bundle's focal length and principal point against the simulated
  camera's, and OpenCV's ``calibrateCamera`` on the same observations given the *true* target
  coordinates (its best case) — the issue asks for at least OpenCV's accuracy.

    .venv/bin/python -m benchmarks.mc_measurement [--runs 40] [--json out.json]
        [--weights incidence|equal] [--image-sigma-px 0.03]

``--weights`` and ``--image-sigma-px`` override the job's ``[camera] observation_weights`` and
``[sim] image_sigma_px`` (decision 0010 compares them).

Runs in-process (``cell.job.start_job``); the planning cache makes every run after the first
plan in well under a second. Each run takes 5-10 s on 2 cores.
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.stats import chi2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.alignment import similarity_fit  # noqa: E402
from cell.job import load_from_folder, start_job  # noqa: E402

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "bracket"
CHI2_3SIGMA = float(chi2.ppf(0.9973, 3))


class _Quiet:
    def say(self, s: str) -> None:
        pass

    def progress(self, stage: str, fraction: float) -> None:
        pass


def job_with_seed(dst: Path, sim_seed: int, weights: str | None = None, image_sigma_px: float | None = None) -> Path:
    """A copy of the example job whose ``[sim] seed`` is ``sim_seed`` (optionally other weights or image jitter)."""
    dst.mkdir(parents=True, exist_ok=True)
    for f in EXAMPLE.iterdir():
        if f.suffix in (".stl", ".csv"):
            shutil.copy(f, dst / f.name)
    text = (EXAMPLE / "job.toml").read_text()
    head, sim = text.split("\n[sim]", 1)
    sim, n = re.subn(r"(?m)^seed\s*=.*$", f"seed = {sim_seed}", sim, count=1)
    if n != 1:
        raise RuntimeError("examples/bracket/job.toml: [sim] has no seed line")
    if image_sigma_px is not None:
        sim, n = re.subn(r"(?m)^image_sigma_px\s*=.*$", f"image_sigma_px = {image_sigma_px}", sim, count=1)
        if n != 1:
            raise RuntimeError("examples/bracket/job.toml: [sim] has no image_sigma_px line")
    if weights is not None:
        head, n = re.subn(r"(?m)^(\[camera\].*)$", rf'\1\nobservation_weights = "{weights}"', head, count=1)
        if n != 1:
            raise RuntimeError("examples/bracket/job.toml: no [camera] table")
    (dst / "job.toml").write_text(head + "\n[sim]" + sim)
    return dst / "job.toml"


def opencv_calibration(job, obs_doc: dict, truth: np.ndarray) -> dict:
    """``cv2.calibrateCamera`` on the job's observations with the true 3-D targets (RADIAL: k1, k2)."""
    index = job.part.targets.index()
    obj, img = [], []
    for o in obs_doc["images"]:
        if len(o["ids"]) < 6:
            continue
        obj.append(truth[[index[t] for t in o["ids"]]].astype(np.float32))
        img.append(np.asarray(o["uv"], dtype=np.float32).reshape(-1, 1, 2))
    intr = job.intrinsics
    K0 = intr.K.copy()
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST
             | cv2.CALIB_FIX_K3)
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, (intr.width, intr.height), K0, np.zeros(5), flags=flags)
    return {"f": float(0.5 * (K[0, 0] + K[1, 1])), "cx": float(K[0, 2]), "cy": float(K[1, 2]), "rms_px": float(rms)}


def one_run(workdir: Path, run: int, sim_seed: int, **overrides) -> dict:
    job_path = job_with_seed(workdir / f"job{run:03d}", sim_seed, **overrides)
    archive = workdir / "archive"
    t0 = time.perf_counter()
    res = start_job(job_path, archive, "sim", _Quiet())
    elapsed = time.perf_counter() - t0
    folder = Path(res.folder)
    job = load_from_folder(folder)
    truth = job.part.targets.xyz + job.deviations
    bundle = json.loads((folder / "bundle.json").read_text())
    X = np.array([t["xyz"] if t["xyz"][0] is not None else [np.nan] * 3 for t in bundle["targets"]], dtype=float)
    C = np.array([t["cov"] if t["xyz"][0] is not None else np.full((3, 3), np.nan) for t in bundle["targets"]],
                 dtype=float)
    ok = np.isfinite(X).all(axis=1)
    s, R, t = similarity_fit(X[ok], truth[ok], with_scale=False)
    err = np.full_like(X, np.nan)
    err[ok] = X[ok] @ R.T + t - truth[ok]
    covr = np.full_like(C, np.nan)
    covr[ok] = R @ C[ok] @ R.T
    m2 = np.full(len(X), np.nan)
    m2[ok] = np.einsum("ni,nij,nj->n", err[ok], np.linalg.inv(covr[ok]), err[ok])
    # the scale the datum gave: a similarity fit to the truth, in ppm
    scale_ppm = float((similarity_fit(X[ok], truth[ok], with_scale=True)[0] - 1.0) * 1e6)
    # each target's class: the largest incidence among the rays that measured it
    from calibration.weights import incidence_angles

    obs_doc = json.loads((folder / "observations.json").read_text())
    index = job.part.targets.index()
    oi = np.concatenate([np.full(len(o["ids"]), k) for k, o in enumerate(obs_doc["images"])]).astype(int)
    ot = np.array([index[t] for o in obs_doc["images"] for t in o["ids"]], dtype=int)
    poses = np.array([im["cam_from_part"] for im in bundle["images"]], dtype=float)
    ang = np.degrees(incidence_angles(job.part.targets.xyz, job.part.targets.normals, poses, oi, ot))
    max_inc = np.full(len(X), np.nan)
    np.fmax.at(max_inc, ot, ang)
    ba = bundle["intrinsics"]
    true_intr = job.intrinsics  # the simulated camera renders with the job's interior orientation
    obs = json.loads((folder / "observations.json").read_text())
    ocv = opencv_calibration(job, obs, truth)
    return {
        "run": run, "sim_seed": sim_seed, "elapsed_s": elapsed, "status": str(res.status),
        "n_targets": int(ok.sum()), "sigma0_px": bundle["sigma0_px"], "n_rejected": bundle["n_rejected"],
        "mean_m2": float(np.nanmean(m2)), "within_3sigma": float(np.mean(m2[ok] <= CHI2_3SIGMA)),
        "rms_err_um": float(np.sqrt(np.nanmean((err**2).sum(axis=1))) * 1e6), "scale_ppm": scale_ppm,
        "ba_f_err_px": ba["fx_px"] - true_intr.fx_px, "ba_cx_err_px": ba["cx_px"] - true_intr.cx_px,
        "ba_cy_err_px": ba["cy_px"] - true_intr.cy_px,
        "cv_f_err_px": ocv["f"] - true_intr.fx_px, "cv_cx_err_px": ocv["cx"] - true_intr.cx_px,
        "cv_cy_err_px": ocv["cy"] - true_intr.cy_px,
        "_err": err, "_cov": covr, "_m2": m2, "_max_inc": max_inc,
    }


def summarise(runs: list[dict]) -> dict:
    m2 = np.concatenate([r["_m2"] for r in runs])
    m2 = m2[np.isfinite(m2)]
    err = np.stack([r["_err"] for r in runs])  # (runs, n, 3)
    cov = np.stack([r["_cov"] for r in runs])
    seen = np.isfinite(err).all(axis=2).all(axis=0)
    rms_err = np.sqrt(np.mean((err[:, seen] ** 2).sum(axis=2), axis=0))
    rms_sig = np.sqrt(np.mean(np.trace(cov[:, seen], axis1=2, axis2=3), axis=0))
    # the spread around each target's mean over the runs (bias removed) against the stated sigma
    spread = np.sqrt(np.mean(((err[:, seen] - err[:, seen].mean(axis=0)) ** 2).sum(axis=2), axis=0)
                     * len(runs) / max(len(runs) - 1, 1))
    bias = np.linalg.norm(err[:, seen].mean(axis=0), axis=1)

    inc = np.concatenate([r["_max_inc"] for r in runs])
    m2_all = np.concatenate([r["_m2"] for r in runs])
    by_class = {}
    for lo, hi in ((0, 50), (50, 70), (70, 90)):
        sel = np.isfinite(m2_all) & (inc >= lo) & (inc < hi)
        if sel.any():
            by_class[f"{lo}-{hi} deg"] = {"targets": int(sel.sum()), "ratio": float(np.sqrt(m2_all[sel].mean() / 3)),
                                          "within_3sigma": float(np.mean(m2_all[sel] <= CHI2_3SIGMA))}

    def rms(key):
        return float(np.sqrt(np.mean([r[key] ** 2 for r in runs])))

    return {
        "runs": len(runs),
        "observations_m2": int(len(m2)),
        "ratio_empirical_over_reported": float(np.sqrt(m2.mean() / 3.0)),
        "mean_m2": float(m2.mean()),
        "within_3sigma": float(np.mean(m2 <= CHI2_3SIGMA)),
        "per_target_rms_error_over_rms_sigma_median": float(np.median(rms_err / rms_sig)),
        "per_target_spread_over_rms_sigma_median": float(np.median(spread / rms_sig)),
        "per_target_bias_over_rms_sigma_median": float(np.median(bias / rms_sig)),
        "rms_error_um": float(np.sqrt(np.mean(rms_err**2)) * 1e6),
        "rms_sigma_um": float(np.sqrt(np.mean(rms_sig**2)) * 1e6),
        "scale_ppm_mean": float(np.nanmean([r["scale_ppm"] for r in runs])),
        "scale_ppm_std": float(np.nanstd([r["scale_ppm"] for r in runs])),
        "ba_focal_rms_err_px": rms("ba_f_err_px"), "cv_focal_rms_err_px": rms("cv_f_err_px"),
        "ba_pp_rms_err_px": float(np.sqrt(np.mean([r["ba_cx_err_px"] ** 2 + r["ba_cy_err_px"] ** 2 for r in runs]))),
        "cv_pp_rms_err_px": float(np.sqrt(np.mean([r["cv_cx_err_px"] ** 2 + r["cv_cy_err_px"] ** 2 for r in runs]))),
        "median_run_s": float(np.median([r["elapsed_s"] for r in runs])),
        "by_largest_incidence": by_class,
    }


def monte_carlo(n_runs: int, workdir: Path, first_seed: int = 1000, progress=None,
                **overrides) -> tuple[dict, list[dict]]:
    runs = []
    for k in range(n_runs):
        runs.append(one_run(workdir, k, first_seed + k, **overrides))
        if progress:
            progress(runs[-1])
    return summarise(runs), runs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--first-seed", type=int, default=1000)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--weights", choices=("incidence", "equal"), help="[camera] observation_weights of the job")
    ap.add_argument("--image-sigma-px", type=float, help="[sim] image_sigma_px of the job (image-plane jitter)")
    args = ap.parse_args(argv)

    def show(r):
        print(f"run {r['run'] + 1:3d}/{args.runs}: {r['n_targets']} targets, sigma0 {r['sigma0_px']:.4f} px, "
              f"mean m2 {r['mean_m2']:.2f}, within 3 sigma {r['within_3sigma']:.1%}, rms {r['rms_err_um']:.1f} um, "
              f"scale {r['scale_ppm']:+.1f} ppm, f err BA {r['ba_f_err_px']:+.3f} / OpenCV {r['cv_f_err_px']:+.3f} px "
              f"({r['elapsed_s']:.1f} s)", flush=True)

    with tempfile.TemporaryDirectory(prefix="mc-measurement-") as tmp:
        summary, runs = monte_carlo(args.runs, Path(tmp), args.first_seed, show, weights=args.weights,
                                    image_sigma_px=args.image_sigma_px)
    print(json.dumps(summary, indent=2))
    if args.json:
        args.json.write_text(json.dumps({"summary": summary,
                                         "runs": [{k: v for k, v in r.items() if not k.startswith("_")} for r in runs]},
                                        indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
