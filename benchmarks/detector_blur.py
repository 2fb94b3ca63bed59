"""The detector model's blur term (decision 0049): how much more a dot's centre scatters when its image is blurred
beyond the blur the model was measured at.

A real lens is sharp at one depth; the simulated one (``[sim] circle_of_confusion_px``) defocuses each dot by its
depth within the job's depth of field. The example's part is rendered from random views by its job's simulated cell
at several blur circles; each clean dot (not clipped, no background bound, centred by its centroid) gives its centre
error against the rendered truth, the detector model's sigma for its incidence and size, and the blur its own image
shows (:func:`calibration.targets.blur_variances`: its second moments less its ellipse's and the pixel's). The fit:

    E[e^2 / sigma_model^2] = k0 (1 + c max(0, b - b_knee))

``b_ref``: the median blur of the dots rendered with a sharp lens (the model's conditions: 0.7 px of lens blur);
``b_knee`` (searched from ``b_ref`` up) and ``c`` by least squares, their sigmas by a bootstrap over views; the range:
``b_knee`` to the 95th percentile of the blurred dots' ``b``. ``--write`` stores ``c_blur_per_px2``, ``blur_reference_px2``, ``blur_range_px2`` with the command
in ``calibration/data/detector_precision.json``; ADJUST and PLAN's pre-analysis then raise a blurred dot's sigma by
``sqrt(1 + c (b - b_knee))`` with ``b`` measured in its own image (MEASURE, observations.json ``blur_px2``).

    .venv/bin/python -m benchmarks.detector_blur [--views 16] [--repeats 2] [--coc 0 3 6] [--write]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.camera import invert, look_at, project  # noqa: E402
from calibration.detector_model import DATA_PATH, load_model  # noqa: E402
from calibration.targets import blur_variances, detect_retro_targets, eccentricity_bias, ellipse_moments  # noqa: E402


def measure(coc_px: float, views: int, repeats: int, seed: int) -> np.ndarray:
    """Rows ``(view, e2, sigma_model^2, b)`` of the clean dots of ``views x repeats`` renders at blur circle ``coc_px``."""
    from benchmarks.detector_precision import JOB, sim_scene
    from cell.loadedjob import load
    from cell.stages.imaging import detection_options

    job, cam, intr, xyz, nrm, radius, centre, index = sim_scene(load(JOB), seed, coc_px)
    model = load_model()
    options = detection_options(job.spec.camera)
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(views):
        az = 2 * np.pi * k / views + rng.uniform(-0.2, 0.2)
        el = np.deg2rad(rng.uniform(8, 85))
        dist = rng.uniform(0.35, 0.7)
        eye = centre + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        part_from_cam = look_at(eye, centre + rng.normal(0, 0.02, 3), roll_rad=rng.uniform(-np.pi, np.pi))
        cfp = invert(part_from_cam)
        for _ in range(repeats):
            img, truth = cam.render(part_from_cam)
            det = detect_retro_targets(img, options)
            ids, kind = np.array(truth["ids"]), np.array(truth["kind"])
            sel = (kind != "coded") & ~np.isin(ids, truth["partial_ids"])
            if not sel.any() or len(det.uv) == 0:
                continue
            tid = np.array([index[i] for i in ids[sel]], dtype=int)
            uv = project(intr, cfp, xyz[tid]) + eccentricity_bias(intr, cfp, xyz[tid], nrm[tid], radius)
            from scipy.spatial import cKDTree

            d, j = cKDTree(det.uv).query(uv)
            ok = d < 1.0
            tid, uv, j = tid[ok], uv[ok], j[ok]
            clean = (det.saturated[j] == 0) & ~np.any(det.background_cov[j] != 0, axis=(1, 2))
            if det.ellipse is not None:
                clean &= ~det.ellipse[j]
            tid, uv, j = tid[clean], uv[clean], j[clean]
            e2 = np.sum((det.uv[j] - uv) ** 2, axis=1) / 2
            Xc = xyz[tid] @ cfp[:3, :3].T + cfp[:3, 3]
            v = eye - xyz[tid]
            inc = np.arccos(np.clip(np.einsum("ij,ij->i", v, nrm[tid]) / np.linalg.norm(v, axis=1), -1, 1))
            s2 = model.sigma_px(inc, intr.fx_px * 2 * radius / Xc[:, 2]) ** 2
            b = blur_variances(det.axes[j], ellipse_moments(intr, cfp, xyz[tid], nrm[tid], radius))
            rows.append(np.column_stack([np.full(len(tid), k), e2, s2, b]))
    return np.concatenate(rows) if rows else np.zeros((0, 4))


def fit(rows: np.ndarray, b_ref: float) -> tuple[float, float, float]:
    """``(k0, c, knee)`` of ``E[e^2 / s^2] = k0 (1 + c max(0, b - knee))`` by least squares, the knee searched from
    ``b_ref`` up by 0.8 px^2: a little blur beyond the model's does not add scatter (it smooths the pixel phase), more
    does (the measured classes rise only from about 0.9 px^2)."""
    q = rows[:, 1] / rows[:, 2]
    best = None
    for knee in b_ref + np.arange(0.0, 0.81, 0.05):
        A = np.column_stack([np.ones(len(q)), np.maximum(rows[:, 3] - knee, 0.0)])
        (k0, k1), res, *_ = np.linalg.lstsq(A, q, rcond=None)
        sse = float(np.sum((A @ np.array([k0, k1]) - q) ** 2))
        if best is None or sse < best[0]:
            best = (sse, float(k0), float(k1 / k0), float(knee))
    return best[1], best[2], best[3]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--coc", type=float, nargs="+", default=[0.0, 3.0, 6.0], help="blur circles at near / far (px); "
                    "the first is the sharp reference")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bootstrap", type=int, default=200)
    ap.add_argument("--write", action="store_true", help="store the term in calibration/data/detector_precision.json")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    by_coc = {c: measure(c, a.views, a.repeats, a.seed) for c in a.coc}
    sharp = by_coc[a.coc[0]]
    b_ref = float(np.median(sharp[:, 3]))
    rows = np.concatenate([r + np.array([1000 * i, 0, 0, 0]) for i, r in enumerate(by_coc.values())])
    k0, c, knee = fit(rows, b_ref)
    rng = np.random.default_rng(a.seed)
    views = np.unique(rows[:, 0])
    boot = []
    for _ in range(a.bootstrap):
        pick = rng.choice(views, len(views))
        boot.append(fit(np.concatenate([rows[rows[:, 0] == v] for v in pick]), b_ref)[1:])
    c_sigma, knee_sigma = (float(v) for v in np.std(boot, axis=0))
    blurred = np.concatenate([r for cc, r in by_coc.items() if cc != a.coc[0]])
    hi = float(np.percentile(blurred[:, 3], 95)) if len(blurred) else b_ref + 1.0
    out = {"sharp_median_px2": b_ref, "blur_reference_px2": knee, "knee_sigma": knee_sigma, "c_blur_per_px2": c,
           "c_blur_sigma": c_sigma, "k0": k0, "blur_range_px2": [knee, hi], "dots": {str(cc): len(r) for cc, r in by_coc.items()},
           "seconds": round(time.perf_counter() - t0, 1)}
    # the check: e^2 over the model's sigma^2 by blur class, without and with the term (1 expected with it, up to k0)
    q = rows[:, 1] / rows[:, 2]
    f2 = 1.0 + c * np.clip(rows[:, 3] - knee, 0.0, hi - knee)
    classes = []
    for lo, up in ((-1, b_ref + 0.1), (b_ref + 0.1, b_ref + 0.4), (b_ref + 0.4, b_ref + 0.8), (b_ref + 0.8, b_ref + 1.5),
                   (b_ref + 1.5, 99)):
        m = (rows[:, 3] >= lo) & (rows[:, 3] < up)
        if m.sum() >= 20:
            classes.append({"blur_px2": [round(max(lo, 0.0), 2), round(min(up, 99), 2)], "dots": int(m.sum()),
                            "without_term": round(float(q[m].mean()), 3), "with_term": round(float((q / f2)[m].mean()), 3)})
    out["classes"] = classes
    print(json.dumps(out, indent=1))
    # a fit that cannot be trusted is never written as the model's term: a slope that is not clearly positive, a knee
    # at the edge of its search (the data did not find it), or classes the term leaves more than 15 % apart
    ref = classes[0]["with_term"] if classes else float("nan")
    doubts = ([f"c = {c:.3f} +- {c_sigma:.3f} is not clearly positive"] if not c > 3 * c_sigma else []) \
        + ([f"the knee {knee:.3f} px^2 lies at the edge of its search"] if knee >= b_ref + 0.79 else []) \
        + ([f"with the term the classes still spread {[c_['with_term'] for c_ in classes]}"]
           if not all(abs(c_["with_term"] / ref - 1) < 0.15 for c_ in classes) else [])
    if doubts:
        print("the fit is not trusted: " + "; ".join(doubts) + (": not written" if a.write else ""), file=sys.stderr)
        return 1
    if a.write:
        doc = json.loads(DATA_PATH.read_text())
        doc.update({"c_blur_per_px2": c, "c_blur_sigma": c_sigma, "blur_reference_px2": knee, "blur_knee_sigma": knee_sigma,
                    "blur_sharp_median_px2": b_ref, "blur_range_px2": [knee, hi],
                    "blur_classes": classes,
                    "blur_measured_by": f"python -m benchmarks.detector_blur --views {a.views} --repeats {a.repeats} "
                                        f"--coc {' '.join(f'{v:g}' for v in a.coc)} --seed {a.seed} --write"})
        DATA_PATH.write_text(json.dumps(doc, indent=1) + "\n")
        print(f"written to {DATA_PATH}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
