"""REPORT: align to CAD, judge each target against its tolerance, write report.json and report.html."""
from __future__ import annotations

import json
import platform
from importlib import metadata

import numpy as np

from calibration.alignment import PointCovariance, align_to_cad
from cell.record import report as R
from cell.record.jobfolder import atomic_write_bytes, atomic_write_json, utc_now


def _versions() -> dict:
    out = {"python": platform.python_version()}
    for pkg in ("inspection-cell", "numpy", "scipy", "trimesh", "pin", "pycolmap", "opencv-contrib-python-headless",
                "ur-rtde", "mcap"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            pass
    return out


def robust_alignment(measured, pc, nominal, ok, tol, k, iterations: int = 5):
    """Rigid best fit to CAD that leaves out the targets that deviate.

    A least-squares fit over all targets is pulled by the very deviations it should reveal (six
    targets off by half a millimetre shift a 200-target fit by ~10 um): refit without the
    targets that are beyond their tolerance or significant at ``k`` sigma, until the set is stable.
    """
    mask = ok.copy()
    for _ in range(iterations):
        al = align_to_cad(measured, pc, nominal, with_scale=False, fit_mask=mask)
        dev = np.linalg.norm(al.deviation, axis=1)
        new = ok & (dev <= tol) & ~(al.sigma_level() > k)
        if new.sum() < max(6, ok.sum() // 2):  # never fit to a handful: keep the last fit
            break
        if np.array_equal(new, mask):
            break
        mask = new
    return al, mask


def _calibration_status(ctx) -> dict:
    """Whether the cell was within its reverification interval and passed (from the archive)."""
    from datetime import datetime, timezone

    from cell.cellcal.status import calibration_status
    from cell.jobspec import resolve

    cf = ctx.job.spec.cell.cell_file
    if cf is None:
        return {"status": "not verified", "detail": "the job names no cell file ([cell] cell_file)"}
    archive_root = ctx.folder.path.parent
    doc = calibration_status(archive_root, resolve(ctx.job.folder, cf), datetime.now(timezone.utc))
    return {k: doc.get(k) for k in ("status", "detail", "last")}


#: How each target's conformance is decided, stated in the report.
DECISION_RULE = ("ISO 14253-1: conforming if |d| + U <= tolerance, nonconforming if |d| - U > tolerance, "
                 "else inconclusive; U = 2 sigma of the deviation along its direction (k = 2). 'pass' is |d| <= tolerance.")


def conformance(deviation: np.ndarray, deviation_cov: np.ndarray, tol: np.ndarray, ok: np.ndarray,
                k: float = 2.0) -> tuple[np.ndarray, list]:
    """Expanded uncertainty ``U (n,)`` of each deviation's length and the decision per target.

    ``deviation: (n, 3)``, ``deviation_cov: (n, 3, 3)``, ``tol: (n,)``, ``ok: (n,)`` measured. ``U`` is
    ``k`` sigma along the deviation's direction (for a deviation near zero: the largest axis); decisions
    "conforming", "nonconforming", "inconclusive" (the measurement cannot tell), None if not measured.
    """
    d = np.asarray(deviation, dtype=float)
    C = np.asarray(deviation_cov, dtype=float)
    ok = np.asarray(ok, dtype=bool)
    length = np.linalg.norm(d, axis=1)
    U = np.full(len(d), np.nan)
    if ok.any():
        u = d[ok] / np.maximum(length[ok], 1e-300)[:, None]
        along = np.einsum("ni,nij,nj->n", u, C[ok], u)
        largest = np.linalg.eigvalsh(C[ok])[:, -1]
        U[ok] = k * np.sqrt(np.maximum(np.where(length[ok] > 1e-12, along, largest), 0.0))
    decision = np.where(length + U <= tol, "conforming", np.where(length - U > tol, "nonconforming", "inconclusive"))
    return U, [str(x) if m else None for x, m in zip(decision, ok)]


def write_report(ctx) -> str:
    job = ctx.job
    f = ctx.folder
    bundle = json.loads(f.file("bundle.json").read_text())
    plan = json.loads(f.file("plan.json").read_text())
    ids = job.part.targets.ids
    nominal = job.part.targets.xyz
    measured = np.array([t["xyz"] for t in bundle["targets"]], dtype=float)
    cov = np.array([t["cov"] if t["cov"] is not None else np.full((3, 3), np.nan) for t in bundle["targets"]], dtype=float)
    with np.load(f.file("bundle_covariance.npz")) as z:
        pc = PointCovariance(z["D"], z["U"], z["C"])
    ok = np.isfinite(measured).all(axis=1)
    tol = job.tolerance_m
    k = job.spec.report.sigma_factor
    al, fit_mask = robust_alignment(measured, pc, nominal, ok, tol, k)
    dev_norm = np.linalg.norm(al.deviation, axis=1)
    level = al.sigma_level()
    predicted = {t["id"]: (np.sqrt(np.trace(t["predicted_cov"])) if t["predicted_cov"] is not None else np.nan)
                 for t in plan["targets"]}
    achieved = np.sqrt(np.trace(cov, axis1=1, axis2=2))
    coded = job.part.targets.kind == "coded"  # identification aids: not measured, not judged
    passed = ok & (dev_norm <= tol)
    U, decision = conformance(al.deviation, al.deviation_cov, tol, ok)
    n_img = [t["n_images"] for t in bundle["targets"]]
    targets = []
    for j, tid in enumerate(ids):
        if coded[j]:
            continue
        targets.append({
            "id": tid, "kind": str(job.part.targets.kind[j]), "nominal": nominal[j], "measured": al.aligned[j],
            "cov": al.deviation_cov[j], "measured_cov": cov[j], "deviation": al.deviation[j],
            "deviation_norm_m": dev_norm[j], "tolerance_m": tol[j], "pass": bool(passed[j]),
            "significance_sigma": level[j], "significant": bool(level[j] > k),
            "uncertainty_U_m": U[j], "decision": decision[j],
            "predicted_sigma_m": predicted.get(tid, np.nan), "achieved_sigma_m": achieved[j], "n_images": n_img[j],
        })
    recs = list(f.records())
    started = next((r["t"] for r in recs if r["event"] == "created"), recs[0]["t"])
    times = {}
    for r in recs:
        if r["event"] == "stage_done":
            times[r["stage"]] = times.get(r["stage"], 0.0) + r["duration_s"]
    judged = ~coded
    if not passed[judged & ok].all():
        verdict = "FAIL"
    elif not ok[judged].all():
        verdict = "INCOMPLETE"
    else:
        verdict = "PASS"
    doc = {
        "job": {"id": f.job_id, "name": job.spec.job.name, "part": job.part.name, "seed": job.spec.job.seed,
                "sim_seed": job.spec.sim.seed if ctx.backend == "sim" else None, "backend": ctx.backend,
                "status": "DONE", "started": started, "finished": utc_now(), "versions": _versions()},
        "verdict": verdict,
        "images": len(bundle["images"]),
        "sigma0_px": bundle["sigma0_px"],
        "datum": bundle["datum"],
        "alignment": {"part_from_measured": al.part_from_measured, "rms_m": al.rms_m, "scale": al.scale,
                      "targets_in_fit": int(fit_mask.sum()), "method": "rigid, iterative exclusion of deviating targets"},
        "intrinsics": bundle["intrinsics"],
        "n_observations": bundle["n_observations"],
        "n_rejected": bundle["n_rejected"],
        "predicted_sigma_max_m": plan["predicted_sigma_max_m"],
        "achieved_sigma_max_m": float(np.nanmax(achieved)),
        "stage_times_s": times,
        "cell_calibration": _calibration_status(ctx),
        "targets": targets,
        "not_measured": [ids[j] for j in np.flatnonzero(~ok & judged)],
        "decision_rule": DECISION_RULE,
        "inconclusive": [ids[j] for j in np.flatnonzero(judged) if decision[j] == "inconclusive"],
        "coded_targets": [ids[j] for j in np.flatnonzero(coded)],
    }
    figs = {
        "network": R.figure_network(job.part.mesh, np.array([s["part_from_cam"] for s in plan["stations"]]), nominal),
        "deviations": R.figure_deviations(job.part.mesh, nominal[judged], np.nan_to_num(dev_norm[judged], nan=np.inf),
                                          tol[judged], passed[judged]),
        "ellipsoids": R.figure_ellipsoids(job.part.mesh, al.aligned[ok], cov[ok]),
        "sigma": R.figure_sigma(np.array([t["predicted_sigma_m"] for t in targets], dtype=float), achieved[judged]),
        "residuals": R.figure_residuals(np.asarray(bundle["residuals_px"], dtype=float)),
    }
    # the REPORT stage's own time is not known yet: the report lists the stages before it
    atomic_write_json(f.file("report.json"), doc)
    from cell.record.jobfolder import to_jsonable

    atomic_write_bytes(f.file("report.html"), R.render_html(to_jsonable(doc), figs).encode())
    return verdict


def run(ctx) -> None:
    """REPORT: alignment to CAD, deviations, decisions; report.json and report.html."""
    verdict = write_report(ctx)
    ctx.say(f"  verdict {verdict}: report {ctx.folder.file('report.html')}")
