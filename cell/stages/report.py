"""REPORT: align to CAD, judge each target against its tolerance, write report.json and report.html."""
from __future__ import annotations

import io
import json
import platform
from importlib import metadata

import numpy as np

from calibration.alignment import PointCovariance
from calibration.bundle.covariance import append_columns
from calibration.errors import CalibrationError
from calibration.robust_alignment import AlignmentOutcome, frame_alignment, robust_best_fit, rps_align, rps_locks
from cell.record import report as R
from cell.record.jobfolder import atomic_write_bytes, atomic_write_json, utc_now
from cell.stages.close_loop import requirement_doc, stated_requirement
from cell.stages.lens import lens_doc
from cell.thermal import agreeing, own_bar_ends, part_scale, resolve_probe, shared_columns, thermal_doc

DEVIATION_COVARIANCE = "deviation_covariance.npz"  # the deviations' joint covariance (report.json deviation_covariance)


def _versions() -> dict:
    out = {"python": platform.python_version()}
    for pkg in ("inspection-cell", "numpy", "scipy", "trimesh", "pin", "pycolmap", "opencv-contrib-python-headless",
                "ur-rtde", "mcap"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            pass
    return out


def align_measurement(job, measured: np.ndarray, pc: PointCovariance, ok: np.ndarray, datum: str,
                      suspect: np.ndarray | None = None) -> AlignmentOutcome:
    """The job's alignment (``[alignment]``): robust best fit (default), RPS / 3-2-1, or the bundle's frame.

    ``suspect: (n,)`` bool: targets whose observations data snooping could not verify; a best fit never takes
    them as candidates for the frame."""
    spec = job.spec.alignment
    nominal = job.part.targets.xyz
    tol = job.tolerance_m
    k = job.spec.report.sigma_factor
    measurable = ok & (job.part.targets.kind != "coded") & ~own_bar_ends(job)
    if spec.method == "rps":
        index = job.part.targets.index()
        return rps_align(measured, pc, nominal, rps_locks({index[t]: a for t, a in spec.rps.items()}), tol, k,
                         ids=list(job.part.targets.ids))
    if spec.method == "bundle_frame":
        return frame_alignment(measured, pc, nominal, fixtured=datum == "control",
                               why=f"the bundle's datum is '{datum}' (inner constraints on the CAD nominals), not a "
                                   "fixture's control points: use best_fit or rps")
    cand = measurable if suspect is None else measurable & ~np.asarray(suspect, dtype=bool)
    if spec.targets is not None:
        index = job.part.targets.index()
        chosen = np.zeros(len(ok), dtype=bool)
        chosen[[index[t] for t in spec.targets]] = True
        cand = cand & chosen
    out = robust_best_fit(measured, pc, nominal, tol, k, candidates=cand, rng=np.random.default_rng(job.spec.job.seed))
    if out.trusted:
        return out
    hinted = _scale_hint(job, measured, pc, tol, k, cand, out)
    return hinted if hinted is not out else _standoff_hint(job, measured, pc, tol, k, cand, out)


def measured_scale(job, outcome: AlignmentOutcome, use: np.ndarray) -> dict | None:
    """The part's scale against CAD (:func:`cell.thermal.part_scale`) over the targets of ``use`` within tolerance that
    agree with one similarity of it (decision 0053), found from the alignment's own targets. Not those alone: a rigid
    fit leaves out the far targets a scale moves most (1.5 K warm, 94 of 195 on the example), and with them most of
    what tells a scale."""
    al = outcome.alignment
    nominal = job.part.targets.xyz
    start = use & (np.linalg.norm(al.deviation, axis=1) <= job.tolerance_m)
    return part_scale(al.deviation, nominal, al.deviation_covariance,
                      agreeing(al.deviation, nominal, al.deviation_cov, start, job.spec.report.sigma_factor,
                               outcome.fit_mask))


def _scale_hint(job, measured: np.ndarray, pc: PointCovariance, tol, k: float, cand: np.ndarray,
                out: AlignmentOutcome) -> AlignmentOutcome:
    """An untrusted best fit, with a reason more when the part's scale explains it (decision 0053): a part 6 K warm
    with a carbon bar is 138 ppm larger than its CAD, 35 um at 250 mm from its middle against a sigma of 2 um, and no
    rigid placement finds six targets that agree. When the measurement shrunk by the significant scale over the
    candidates fits with a trusted frame, the reason says so; the frame stays untrusted (the numbers are the job's),
    and report.json ``thermal`` says what the scale means."""
    sc = measured_scale(job, out, cand)
    if sc is None or not sc["significant"]:
        return out
    trial = robust_best_fit(measured / (1 + sc["scale_ppm"] * 1e-6), pc, job.part.targets.xyz, tol, k,
                            candidates=cand, rng=np.random.default_rng(job.spec.job.seed))
    if not trial.trusted:
        return out
    from dataclasses import replace

    hint = (f"with the part {sc['scale_ppm']:+.0f} ppm {'larger' if sc['scale_ppm'] > 0 else 'smaller'} than its CAD, "
            f"{int(trial.fit_mask.sum())} of {int(cand.sum())} targets agree with CAD and the frame would be trusted: "
            "see the part's scale")
    return replace(out, reasons=out.reasons + (hint,) + bar_end_hints(job, trial))


def bar_end_hints(job, trial: AlignmentOutcome) -> tuple[str, ...]:
    """The scale bar ends on the part that the scaled frame ``trial`` leaves out while their bar's other end agrees.

    A bar's length is certified between its two targets. One of them moved or stuck again since (F5 of decision 0064:
    T0100 of the example 2 mm off) puts the whole measurement out of scale by the change over the bar's length, and
    in the frame scaled back that end alone stays off its CAD place: the one target to check."""
    dev, fit = trial.alignment.deviation, trial.fit_mask
    nominal, ids = job.part.targets.xyz, job.part.targets.ids
    hints = []
    for a, b, length, _ in job.scale_bars:
        off = [i for i in (a, b) if not fit[i] and np.all(np.isfinite(dev[i]))]
        if len(off) != 1 or not fit[a + b - off[0]]:  # both ends out, or the other not in the frame: nothing to name
            continue
        i = off[0]
        u = (nominal[b] - nominal[a]) / np.linalg.norm(nominal[b] - nominal[a])
        along = float(dev[i] @ u) * (1.0 if i == b else -1.0)  # > 0: the bar between its targets is longer
        hints.append(
            f"scale bar {ids[a]}-{ids[b]}: in that frame its end {ids[i]} is {np.linalg.norm(dev[i]) * 1e6:.0f} um "
            f"off its CAD place ({along * 1e6:+.0f} um along the bar, {along / length * 1e6:+.0f} ppm of its "
            f"length) where its other end {ids[a + b - i]} agrees: an end moved or stuck again since its certificate "
            "puts every coordinate out of scale; check that end's target")
    return tuple(hints)


def _standoff(X: np.ndarray, N: np.ndarray, n: np.ndarray) -> tuple[float, np.ndarray]:
    """The common offset ``off`` along the normals ``n`` and the rigid placement that best bring the measured ``X`` to
    ``N + off n`` (Gauss-Newton from the rigid best fit, least squares), and each target's residual length after."""
    from scipy.spatial.transform import Rotation

    from calibration.alignment import similarity_fit

    _, R, t = similarity_fit(X, N)
    off = 0.0
    for _ in range(6):
        Y = X @ R.T + t
        r = Y - N - off * n
        J = np.zeros((len(X), 3, 7))  # d(residual) / d(rotation vector, translation, offset)
        J[:, 0, 1], J[:, 0, 2], J[:, 1, 0] = Y[:, 2], -Y[:, 1], -Y[:, 2]
        J[:, 1, 2], J[:, 2, 0], J[:, 2, 1] = Y[:, 0], Y[:, 1], -Y[:, 0]
        J[:, :, 3:6] = np.eye(3)
        J[:, :, 6] = -n
        p = np.linalg.lstsq(J.reshape(-1, 7), -r.reshape(-1), rcond=None)[0]
        dR = Rotation.from_rotvec(p[:3]).as_matrix()
        R, t, off = dR @ R, dR @ t + p[3:6], off + float(p[6])
    return off, np.linalg.norm(X @ R.T + t - N - off * n, axis=1)


def _standoff_hint(job, measured: np.ndarray, pc: PointCovariance, tol, k: float, cand: np.ndarray,
                   out: AlignmentOutcome) -> AlignmentOutcome:
    """An untrusted best fit, with a reason more when every target standing a common distance off the CAD surface
    along its normal explains it: a mis-stated ``[job] target_thickness`` puts each target's face that far off the
    surface the job assumes, which no rigid placement absorbs on a part whose faces look several ways (the example
    with 0.2 mm not stated: no three targets agreed). The offset is estimated with the placement by least squares
    over the candidates (twice: the second without those farther off than three times the median); the frame stays
    untrusted (the numbers are the job's)."""
    nominal, normals = job.part.targets.xyz, job.part.targets.normals
    idx = np.flatnonzero(cand)
    if len(idx) < 6:
        return out
    off, keep = 0.0, idx
    for _ in range(2):
        off, resid = _standoff(measured[keep], nominal[keep], normals[keep])
        keep = keep[resid <= 3 * np.median(resid)]
        if len(keep) < 6:
            return out
    from dataclasses import replace

    from calibration.alignment import similarity_fit

    # the scale bars' ends stand off their surfaces as well: the measurement's scale is off with them
    scale = similarity_fit(measured[keep], nominal[keep] + off * normals[keep], with_scale=True)[0]
    trial = robust_best_fit(measured * scale, pc, nominal + off * normals, tol, k, candidates=cand,
                            rng=np.random.default_rng(job.spec.job.seed))
    if not trial.trusted:
        return out
    said = job.target_thickness_m
    hint = (f"with every target {off * 1e3:+.3f} mm further off its CAD surface along the normal (and the scale "
            f"{(scale - 1) * 1e6:+.0f} ppm, the scale bars' ends standing off too), {int(trial.fit_mask.sum())} of "
            f"{len(idx)} targets agree with CAD and the frame would be trusted: the targets' thickness is likely "
            f"{(said + off) * 1e3:.3f} mm, not the {said * 1e3:.3f} mm the job says ([job] target_thickness), or the "
            "whole surface is offset")
    return replace(out, reasons=out.reasons + (hint,))


def alignment_doc(out: AlignmentOutcome, ids: list[str], spec) -> dict:
    """report.json's ``alignment``: the contract's method, targets_in_fit (ids), rms_m, trusted, and why."""
    al = out.alignment
    doc = {"method": out.method, "targets_in_fit": [ids[j] for j in np.flatnonzero(out.fit_mask)],
           "rms_m": al.rms_m, "trusted": bool(out.trusted), "stable": bool(out.stable),
           "reasons": list(out.reasons), "notes": list(out.notes), "residual_ratio": out.residual_ratio,
           "part_from_measured": al.part_from_measured, "scale": al.scale, "iterations": out.iterations,
           "on_untrusted": spec.on_untrusted,
           "description": {"best_fit": "rigid best fit to CAD over the targets that agree with it (consensus over "
                                       "minimal subsets, then exclusion of targets beyond tolerance or significant)",
                           "rps": "RPS / 3-2-1 on the named datum targets",
                           "bundle_frame": "the bundle adjustment's own frame (fixtured part)"}[out.method]}
    if out.consensus is not None:
        doc["consensus"] = {"agree": int(out.consensus.agree.sum()), "rival": out.consensus.rival,
                            "hypotheses": out.consensus.hypotheses, "scale_factor": out.consensus.scale_factor}
    if out.method == "rps":
        doc["rps"] = dict(spec.rps)
    return doc


def thickness_doc(job, backend: str) -> dict:
    """report.json ``target_thickness``: how far the targets' faces stood above the CAD surface, and whether the job
    said so. A real cell whose job does not say it gets a note: its targets have a thickness, which then shows as a
    deviation along every normal (decision 0049)."""
    given = job.spec.job.target_thickness is not None
    doc = {"thickness_m": job.target_thickness_m, "stated_in_job": given,
           "compensation": "coordinates are of the CAD surface under each target: the measured face centre less the "
                           "thickness along the target's CAD normal; deviations are the face's own"}
    if not given and backend != "sim":
        doc["note"] = (f"the job does not give [job] target_thickness: the cell measures the centre of each target's "
                       f"face, which stands the target's thickness above the surface (adhesive dots 0.1-0.3 mm, "
                       f"magnetic ones 1-2 mm), and takes it as a deviation along every normal; give it in "
                       f"{job.spec.job.units} (0 for targets flush with the surface)")
    return doc


def _calibration_status(ctx) -> dict:
    """Whether the cell was within its reverification interval and passed (from the archive)."""
    from datetime import datetime, timezone

    from cell.cellcal.status import calibration_status
    from cell.jobspec import resolve

    cf = ctx.job.spec.cell.cell_file
    if cf is None:
        return {"status": "not verified", "detail": "the job names no cell file ([cell] cell_file)",
                "measured_with": "the job file's hand-eye and [camera] lens"}
    archive_root = ctx.folder.path.parent
    snapshot = ctx.folder.path / "inputs" / "cell_file.toml"  # the cell file as the job took it (decision 0056)
    path = snapshot if snapshot.is_file() else resolve(ctx.job.folder, cf)
    doc = calibration_status(archive_root, path, datetime.now(timezone.utc))
    out = {k: doc.get(k) for k in ("status", "detail", "last")}
    if ctx.job.cell is not None:  # which hand-eye and lens the job measured with (decision 0056)
        from cell.cellcal.jobcell import taken_line

        out |= {"measured_with": taken_line(ctx.job.cell), "hand_eye": ctx.job.cell["hand_eye"],
                "lens": ctx.job.cell["lens"], "cell_file_sha256": ctx.job.cell["sha256"]}
    return out


#: How each target's conformance is decided, stated in the report.
DECISION_RULE = ("ISO 14253-1: conforming if |d| + U <= tolerance, nonconforming if |d| - U > tolerance, "
                 "else inconclusive; U = 2 sigma of the deviation along its direction (k = 2). 'pass' is |d| <= tolerance. "
                 "A suspect target (its observations could not be verified by data snooping) is inconclusive. "
                 "Every measured target is undecided when the alignment to CAD is not trusted.")


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


def part_verdict(trusted: bool, ok: np.ndarray, passed: np.ndarray, judged: np.ndarray, decision: list,
                 suspect: np.ndarray, ids, requirement: tuple | None = None) -> tuple[str, list[str]]:
    """The part's verdict and why, from each target's measurement (``ok``), ``passed`` (|d| <= tolerance),
    ``decision`` (ISO 14253-1, per target) and ``suspect`` (observations data snooping could not verify).
    ``requirement``: ``(required (n,), achieved (n,), source)`` sigmas (m) when the job states a precision requirement.

    UNTRUSTED (the frame), else FAIL (a target beyond its tolerance), else INCOMPLETE (a target not measured,
    suspect, within U of its tolerance, or measured less precisely than its requirement asks: the measurement does
    not show that the part conforms to the precision asked, decision 0070), else PASS.
    The verdict set is the one the archive, the console and QIF read (decision 0030): a part with undecided
    targets is not a new kind of verdict, it is an inspection that did not decide every target.
    """
    ok, passed, judged = (np.asarray(a, dtype=bool) for a in (ok, passed, judged))
    suspect = np.asarray(suspect, dtype=bool) & judged & ok
    fail = judged & ok & ~passed
    missing = judged & ~ok
    near = judged & ok & ~suspect & np.array([d == "inconclusive" for d in decision], dtype=bool)
    unmet = np.zeros(len(ok), dtype=bool)
    if requirement is not None:
        req, ach = (np.asarray(a, dtype=float) for a in requirement[:2])
        with np.errstate(invalid="ignore"):
            unmet = judged & ok & ~(ach <= req * (1 + 1e-9))  # a nan sigma of a measured target is short too

    def some(mask, what):
        idx = np.flatnonzero(mask)
        names = ", ".join(ids[j] for j in idx[:8]) + (" ..." if len(idx) > 8 else "")
        return f"{len(idx)} target(s) {what}: {names}"

    reasons = []
    if not trusted:
        reasons.append("the alignment to CAD is not trusted")
    if fail.any():
        reasons.append(some(fail, "beyond tolerance") + (f" ({int((fail & suspect).sum())} of them suspect)"
                                                          if (fail & suspect).any() else ""))
    if missing.any():
        reasons.append(some(missing, "not measured"))
    if (suspect & ~fail).any():
        reasons.append(some(suspect & ~fail, "suspect (their observations could not be verified by data snooping, or "
                                             "their images are not a clean dot: report.json target_print)"))
    if (near & passed).any():
        reasons.append(some(near & passed, "within U of their tolerance (ISO 14253-1 cannot decide)"))
    if unmet.any():
        idx = np.flatnonzero(unmet)
        reasons.append(f"{len(idx)} target(s) measured less precisely than required ({requirement[2]}): "
                       + ", ".join(f"{ids[j]} {ach[j] * 1e6:.2f} um > {req[j] * 1e6:.2f} um" for j in idx[:6])
                       + (" ..." if len(idx) > 6 else ""))
    if not trusted:
        return "UNTRUSTED", reasons
    if fail.any():
        return "FAIL", reasons
    if missing.any() or (suspect | near | unmet).any():
        return "INCOMPLETE", reasons
    return "PASS", reasons


#: the plan's predicted sigma over the achieved one (median over the targets): outside this it is said (issue 15:
#: 1.00 +- 0.25)
PREDICTION_BAND = (0.75, 1.25)


def held_lens_variance(bundle: dict) -> np.ndarray:
    """Each target's variance (trace, m^2) the held lens's uncertainty added in ADJUST (bundle.json
    ``lens.held_uncertainty.added_variance_m2``); zeros when the lens was not held or nothing was carried; None when
    it was carried but the shares are not there (a bundle.json of an older version): then neither side of
    predicted / achieved takes the lens's share off, rather than only one."""
    n = len(bundle["targets"])
    held = (bundle.get("lens") or {}).get("held_uncertainty") or {}
    v = held.get("added_variance_m2")
    if not v or len(v) != n:
        return None if held.get("carried") else np.zeros(n)
    return np.array([0.0 if x is None else float(x) for x in v])


def _held_lens_growth(plan: dict, bundle: dict, targets: list[dict]) -> dict:
    """The held lens's share as the plan expected it and as ADJUST carried it (``held_lens``: the sigmas' median
    growth each, the observations rejected, predicted / achieved with it (``total_median``), and a ``note`` when the
    growths differ by more than :data:`PREDICTION_BAND` allows); {} when the lens was not held."""
    planned = (((plan.get("prediction") or {}).get("facts") or {}).get("held_lens") or {})
    carried = ((bundle.get("lens") or {}).get("held_uncertainty") or {})
    if not (planned.get("carried") and carried.get("carried")):
        return {}
    gp, ga = float(planned["sigma_growth_median"]), float(carried["sigma_growth_median"])
    tot = [t["predicted_sigma_m"] / t["achieved_sigma_m"] for t in targets
           if np.isfinite(t["predicted_sigma_m"]) and np.isfinite(t["achieved_sigma_m"]) and t["achieved_sigma_m"] > 0]
    out = {"planned_growth_median": gp, "achieved_growth_median": ga,
           "total_median": float(np.median(tot)) if tot else None,
           "rejected_observations": int(bundle.get("n_rejected") or 0), "note": None}
    lo, hi = PREDICTION_BAND
    if not lo <= gp / ga <= hi:
        out["note"] = (f"the held lens's uncertainty grew the targets' sigma x{ga:.2f} (median) where the plan expected "
                       f"x{gp:.2f}, so the plan's whole predicted sigma is {out['total_median']:.2f}x the achieved one "
                       f"(the images' part alone: predicted_over_achieved): ADJUST's data snooping rejected "
                       f"{out['rejected_observations']} observation(s), those the held lens describes worst (near the "
                       "frame's corners its own uncertainty is many times a dot's noise), and the lens's share shrank "
                       "with them" if gp > ga and out["rejected_observations"] else
                       f"the held lens's uncertainty grew the targets' sigma x{ga:.2f} (median) where the plan expected "
                       f"x{gp:.2f}: the images the network took are not the planned ones (check the images left out "
                       "and the observations rejected)")
    return {"held_lens": out}


def _nan(v) -> float:
    return float("nan") if v is None else float(v)


def _predicted_over_achieved(targets: list[dict]) -> dict:
    """Predicted / achieved sigma over the measured targets: median, and the 10 / 90 % quantiles; ``note``: what a
    median outside :data:`PREDICTION_BAND` means (None inside it)."""
    # the plan predicts the images' precision, without the temperatures' and the held lens's shared parts
    a = "achieved_sigma_images_m"
    p = [t.get("predicted_sigma_images_m", t["predicted_sigma_m"]) for t in targets]
    r = np.array([pj / t[a] for pj, t in zip(p, targets)
                  if pj is not None and np.isfinite(pj) and np.isfinite(t[a]) and t[a] > 0])
    if not len(r):
        return {"median": None, "p10": None, "p90": None, "n": 0, "band": list(PREDICTION_BAND), "note": None}
    m = float(np.median(r))
    lo, hi = PREDICTION_BAND
    note = None
    if not lo <= m <= hi:
        note = (f"the plan predicted {m:.2f}x the sigma the images achieved (median over {len(r)} targets; "
                f"{lo:g}-{hi:g} expected): the plan's image precision (the detector model) does not describe these "
                "images; the stated uncertainties follow the images. The network measured "
                + ("better than planned: a plan to a required sigma took more stations than it needed" if m > hi else
                   "worse than planned: a plan to a required sigma has less margin than it showed (CLOSE_LOOP and the "
                   "decisions use the achieved sigma, not the prediction)"))
    return {"median": m, "p10": float(np.quantile(r, 0.1)), "p90": float(np.quantile(r, 0.9)), "n": int(len(r)),
            "band": list(PREDICTION_BAND), "note": note}


def _run_info(folder) -> dict:
    """report.json's ``part`` {number, revision, serial}, ``operator``, ``cell_id`` (null when unknown)."""
    from cell.record.runinfo import read_run_info

    info = read_run_info(folder)
    return {"part": info["part"], "operator": info["operator"], "cell_id": info["cell_id"]}


def rejected_mask(bundle: dict) -> np.ndarray:
    """(n_observations,) bool: the observations the bundle adjustment rejected, found by their residuals
    (bundle.json lists each rejected one with its residual, in the order of ``residuals_px``)."""
    res = np.asarray(bundle["residuals_px"], dtype=float)
    mask = np.zeros(len(res), dtype=bool)
    for r in bundle.get("rejected", []):
        hit = np.flatnonzero(np.all(res == np.asarray(r["residual_px"], dtype=float), axis=1) & ~mask)
        if len(hit):
            mask[hit[0]] = True
    return mask


def identification_drops(obs: dict) -> dict:
    """report.json's ``identification_dropped``: the named dots MEASURE left unnamed (observations.json
    ``dropped``): ``n_dropped``, ``by_reason`` and, per image with any, ``image``, ``station``, ``n_dropped``,
    ``by_reason`` (the reasons' kinds of :func:`cell.stages.measure.dropped_by_reason`) and, for an image left out
    because its dots are smeared, its ``smear`` record (decision 0067)."""
    from cell.stages.measure import dropped_by_reason

    images = []
    for o in obs.get("images", []):
        if o.get("dropped"):
            by = dropped_by_reason([o])
            images.append({"image": o["image"], "station": o.get("station"), "n_dropped": sum(by.values()),
                           "by_reason": by, **({"smear": o["smear"]} if (o.get("smear") or {}).get("smeared") else {})})
    by_reason = dropped_by_reason(obs.get("images", []))
    return {"n_dropped": sum(by_reason.values()), "by_reason": by_reason, "images": images}


def align_with_gains(job, measured: np.ndarray, pc: PointCovariance, K: np.ndarray, ok: np.ndarray, datum: str,
                     suspect: np.ndarray | None = None):
    """:func:`align_measurement` with the scale bars' gains ``K: (n, 3, b)`` riding along: extra columns of the
    covariance's low-rank factor with zero weight (the alignment and every covariance stay as they are) come out
    transformed like the deviations (decision 0029). Returns ``(outcome, Kd)``, ``Kd: (n, 3, b)`` the change of
    each aligned deviation per metre of each certificate's error (report.json ``scale_bar_gains``); None when the
    alignment dropped the low-rank part (or ``b`` is 0 and ``K`` has no column: then ``(n, 3, 0)``)."""
    nb = K.shape[2]
    outcome = align_measurement(job, measured, append_columns(pc, K, np.zeros(nb)) if nb else pc, ok, datum, suspect)
    U = outcome.alignment.deviation_covariance.U
    if nb and U.shape[2] < nb:
        return outcome, None
    return outcome, U[:, :, U.shape[2] - nb:]


def scale_sigma(measured: np.ndarray, pc: PointCovariance, use: np.ndarray, K: np.ndarray, K_sigma: np.ndarray):
    """The stated uncertainty of the measurement's scale, and the bars' certificates' part of it (relative, 1 sigma).

    The scale of a similarity fit over the targets ``use`` is, to first order, ``s = sum g_i . x_i`` with
    ``g_i = (x_i - c) / sum |x_j - c|^2``; its variance is ``g^T Q g`` from the full covariance (its block-diagonal
    and low-rank parts), the certificates' part ``sum_b sigma_b^2 (g . k_b)^2``. None without three targets."""
    idx = np.flatnonzero(use & np.all(np.isfinite(measured), axis=1))
    if len(idx) < 3:
        return None
    x = measured[idx] - measured[idx].mean(axis=0)
    g = x / np.sum(x * x)
    D, U = np.nan_to_num(pc.D[idx]), np.nan_to_num(pc.U[idx])
    Ug = np.einsum("nar,na->r", U, g)
    var = float(np.einsum("na,nab,nb->", g, D, g) + Ug @ pc.C @ Ug)
    kg = np.einsum("nab,na->b", np.nan_to_num(K[idx]), g) if K.shape[2] else np.zeros(0)
    return float(np.sqrt(max(var, 0.0))), float(np.sqrt(np.sum((np.asarray(K_sigma) * kg) ** 2)))


def _budget(cov_scale, dev_cov, use, bundle: dict, scale=None) -> dict:
    """report.json ``uncertainty_budget``: the scale bar certificate's share of the targets' variance (median, max),
    the measurement's scale uncertainty (``scale``: :func:`scale_sigma`), and what else the statement carries
    beyond the detector model (decision 0029)."""
    out: dict = {"scale_bar_share_median": None, "scale_bar_share_max": None}
    if cov_scale is not None and np.any(use):
        share = np.trace(cov_scale[use], axis1=1, axis2=2) / np.trace(dev_cov[use], axis1=1, axis2=2)
        share = share[np.isfinite(share)]
        if len(share):
            out.update(scale_bar_share_median=float(np.median(share)), scale_bar_share_max=float(np.max(share)))
    cb = bundle.get("coherent_background") or {}
    w = bundle.get("observation_weights") or {}
    out.update(scale_sigma_ppm=None, scale_sigma_certificate_ppm=None)
    if scale is not None:
        out.update(scale_sigma_ppm=scale[0] * 1e6, scale_sigma_certificate_ppm=scale[1] * 1e6)
    out.update(shared_floor=cb.get("shared_floor"), clip_level=cb.get("clip_level"))
    out.update(shared_misfit_targets=cb.get("n_targets", 0), scale_bar_ends=cb.get("scale_bar_ends", []),
               observations_with_background_bound=w.get("observations_with_background_bound"),
               observations_clipped=w.get("observations_clipped"),
               variance_factor=w.get("variance_factor"), detector_model_mismatch=w.get("model_mismatch"),
               detector_model_shape=(w.get("model_shape") or {}).get("mismatch"),
               detector_model_range=(w.get("model_range") or {}).get("mismatch"),
               detector_model_classes_reweighted=sum(bool(c.get("significant")) for c in
                                                     (w.get("model_shape") or {}).get("classes", [])),
               datum_left_out=bundle.get("datum_left_out") or [])
    return out


def _closed_loop(f) -> dict | None:
    """report.json's ``closed_loop`` (when the stage ran with it on): each round and what still misses."""
    if not f.file("closed_loop.json").exists():
        return None
    cl = json.loads(f.file("closed_loop.json").read_text())
    if not cl.get("enabled"):
        return None
    rounds = [{"round": r["round"], "status": r["status"], "stations_added": r.get("stations_added", []),
               "targets_short": r.get("targets_short", []), "targets_fixed": r.get("targets_fixed", []),
               "time_s": r.get("time_s"), "incidence_limit_learned_deg": r.get("incidence_limit_learned_deg"),
               "stations_refused": r.get("stations_refused", []), "stopped": r.get("stopped"),
               # the round's prediction for the targets it meant to fix, and what it achieved (decision 0070)
               "prediction": {t: {"predicted_sigma_m": (r.get("predicted_sigma_m") or {}).get(t),
                                  "achieved_sigma_m": (r.get("achieved_sigma_m") or {}).get(t)}
                              for t in r.get("predicted_fixed", [])},
               "prediction_missed": r.get("prediction_missed", [])}
              for r in cl["rounds"]]
    return {"required_sigma_m": cl.get("required_sigma_m"), "rounds": rounds,
            "unmet": [{"id": u["id"], "reason": u["reason"]} for u in cl.get("unmet", [])]}


def write_report(ctx) -> tuple[str, list[str]]:
    job = ctx.job = resolve_probe(ctx.job, ctx.folder)  # a resumed REPORT reads the probe again
    f = ctx.folder
    bundle = json.loads(f.file("bundle.json").read_text())
    sc = bundle.get("screening") or {}
    if sc.get("scale_established") is False:  # the job declares a scale bar: no report in the CAD's scale
        why = str(sc.get("scale"))
        advice = ("choose scale bar ends on a clear flat area ([job] scale_bar / scale_bars), away from the part's edges"
                  if "unlike its ellipse" in why else "add stations that see both ends ([planning] closed_loop = true "
                  "plans them) or check the scale bar's targets")
        raise CalibrationError(f"scale not established: {why}; {advice}")
    plan = json.loads(f.file("plan.json").read_text())
    ids = job.part.targets.ids
    # the cell measured the targets' faces; the report speaks of the CAD surface under them (deviations are the same)
    nominal = job.surface_points(job.part.targets.xyz)
    measured = np.array([t["xyz"] for t in bundle["targets"]], dtype=float)
    cov = np.array([t["cov"] if t["cov"] is not None else np.full((3, 3), np.nan) for t in bundle["targets"]], dtype=float)
    with np.load(f.file("bundle_covariance.npz")) as z:
        pc = PointCovariance(z["D"], z["U"], z["C"])
        K, K_sigma = (z["K"], z["K_sigma"]) if "K" in z.files else (np.zeros((len(ids), 3, 0)), np.zeros(0))
    nb = len(K_sigma)
    # decision 0053: the part's and the bars' temperatures, shared by every own-material bar, in the covariance
    th_cols, th_w, _ = shared_columns(job.spec, K, bundle.get("scale_bars") or [])
    # what the plan predicts is the measurement's (images, network, certificates): predicted / achieved compares it
    # without the temperatures' shared scale, which the plan does not know, and without the held lens's share, whose
    # size depends on the observations ADJUST's data snooping rejects where the held lens does not describe the
    # images (the frame's corners): the plan cannot know which (decision 0062); both sides leave it out
    lens_var = held_lens_variance(bundle)
    achieved_images = np.sqrt(np.maximum(np.trace(cov, axis1=1, axis2=2) - (0.0 if lens_var is None else lens_var),
                                         0.0))
    if len(th_w):
        pc = append_columns(pc, th_cols, th_w)
        cov = cov + np.einsum("nar,r,nbr->nab", th_cols, th_w, th_cols)
    ok = np.isfinite(measured).all(axis=1)
    tol = job.tolerance_m
    k = job.spec.report.sigma_factor
    suspect = set((bundle.get("snooping") or {}).get("suspect_targets") or [])
    printed = {d["id"]: d["why"] for d in (bundle.get("target_print") or {}).get("doubtful", [])}  # decision 0051
    outcome, Kd = align_with_gains(job, measured, pc, K, ok, bundle["datum"], np.array([t in suspect for t in ids]))
    al = outcome.alignment
    if not outcome.trusted and job.spec.alignment.on_untrusted == "fault":
        raise CalibrationError("alignment not trusted: " + "; ".join(outcome.reasons))
    if not outcome.trusted:
        ctx.log.log("warning", "alignment not trusted: " + "; ".join(outcome.reasons))
        ctx.say("  WARNING alignment not trusted: " + "; ".join(outcome.reasons))
    dev_norm = np.linalg.norm(al.deviation, axis=1)
    # a target's sigma, as every record shows it: of its measured covariance with the temperatures' shared part (an
    # outside check: with [thermal] and an own-material bar the HTML, CSV and index showed 1.7 um for 9.2); without
    # [thermal] the same as before (the closed loop's requirement is on it)
    achieved = np.sqrt(np.trace(cov, axis1=1, axis2=2))
    surface = job.surface_points(al.aligned)
    if nb and Kd is None:  # an alignment that dropped the low-rank part: no share known
        ctx.log.log("warning", "uncertainty budget: the alignment did not carry the scale bar's gains; "
                               "cov_scale_bar not reported")
        nb = 0
    if Kd is None:
        Kd = np.zeros((len(ids), 3, 0))
    cov_scale = np.einsum("nar,r,nbr->nab", Kd, K_sigma[:nb] ** 2, Kd)
    level = al.sigma_level()
    predicted = {t["id"]: (np.sqrt(np.trace(t["predicted_cov"])) if t["predicted_cov"] is not None else np.nan)
                 for t in plan["targets"]}
    predicted_images = {t["id"]: t.get("predicted_sigma_images_m", predicted[t["id"]]) if lens_var is not None
                        else predicted[t["id"]] for t in plan["targets"]}
    coded = job.part.targets.kind == "coded"  # identification aids: not measured, not judged
    bar_end = own_bar_ends(job)  # the ends of a bar of its own material: the bar's, not the part's (decision 0053)
    passed = ok & (dev_norm <= tol)
    U, decision = conformance(al.deviation, al.deviation_cov, tol, ok)
    # a target whose observations snooping could not verify (bundle.json snooping.suspect_targets: it lost half of
    # its rays as blunders, or lost any and kept two or fewer) cannot be decided on: its measurement may be wrong
    decision = ["inconclusive" if d is not None and tid in suspect else d for d, tid in zip(decision, ids)]
    if not outcome.trusted:  # no target is decided in a frame that cannot be trusted: every export reads the decision
        decision = ["undecided" if d is not None else d for d in decision]
    n_img = [t["n_images"] for t in bundle["targets"]]
    targets = []
    for j, tid in enumerate(ids):
        if coded[j] or bar_end[j]:
            continue
        targets.append({
            "id": tid, "kind": str(job.part.targets.kind[j]), "nominal": nominal[j], "measured": surface[j],
            "cov": al.deviation_cov[j], "measured_cov": cov[j], "cov_scale_bar": cov_scale[j] if nb else None,
            # metres per metre of each used bar's certificate error, aligned frame (3 x b; bundle.json scale_bars
            # gain_column gives each bar's column); null for a target not measured or without the gains
            "scale_bar_gains": Kd[j] if nb and np.isfinite(Kd[j]).all() else None,
            "deviation": al.deviation[j],
            "deviation_norm_m": dev_norm[j], "tolerance_m": tol[j], "pass": bool(passed[j]),
            "significance_sigma": level[j], "significant": bool(level[j] > k),
            "uncertainty_U_m": U[j], "decision": decision[j], "suspect": tid in suspect,
            "print_doubtful": printed.get(tid),
            "predicted_sigma_m": predicted.get(tid, np.nan), "achieved_sigma_m": achieved[j],
            "predicted_sigma_images_m": _nan(predicted_images.get(tid)), "achieved_sigma_images_m": achieved_images[j],
            "n_images": n_img[j],
        })
    recs = list(f.records())
    started = next((r["t"] for r in recs if r["event"] == "created"), recs[0]["t"])
    times = {}
    for r in recs:
        if r["event"] == "stage_done":
            times[r["stage"]] = times.get(r["stage"], 0.0) + r["duration_s"]
    judged = ~coded & ~bar_end
    scale = measured_scale(job, outcome, ok & judged & ~np.isin(ids, list(suspect) + list(printed)))
    required, req_source = stated_requirement(job)
    verdict, verdict_reasons = part_verdict(outcome.trusted, ok, passed, judged, decision,
                                            np.array([t in suspect for t in ids]), ids,
                                            None if required is None else (required, achieved, req_source))
    if scale is not None and scale["significant"] and verdict != "PASS":  # judged at the measurement's scale: said
        verdict_reasons = list(verdict_reasons) + [f"the part measures {scale['scale_ppm']:+.0f} ppm against its CAD "
                                                   "(report.json thermal.note)"]
    lens = lens_doc(job, bundle)
    verdict, verdict_reasons = lens_verdict(lens, verdict, verdict_reasons)
    doc = {
        "job": {"id": f.job_id, "name": job.spec.job.name, "part": job.part.name, "seed": job.spec.job.seed,
                "sim_seed": job.spec.sim.seed if ctx.backend == "sim" else None, "backend": ctx.backend,
                "status": "DONE", "started": started, "finished": utc_now(), "versions": _versions()},
        "verdict": verdict,
        "verdict_reasons": verdict_reasons,
        # LOAD found the targets' layout mapping onto itself (decision 0058): the naming rests on the placement
        "layout_symmetry": next(({"warning": r["warning"], "symmetries": r.get("symmetries")} for r in recs
                                 if r["event"] == "layout_symmetry"), None),
        **_run_info(f.path),
        "images": len(bundle["images"]),
        "sigma0_px": bundle["sigma0_px"],
        "datum": bundle["datum"],
        "alignment": alignment_doc(outcome, ids, job.spec.alignment),
        "target_thickness": thickness_doc(job, ctx.backend),
        "thermal": thermal_doc(job.spec, bundle.get("scale_bars") or [], scale, job.probe),
        "intrinsics": bundle["intrinsics"],
        "lens": lens,
        "n_observations": bundle["n_observations"],
        "n_rejected": bundle["n_rejected"],
        "snooping": bundle.get("snooping"),
        "target_print": bundle.get("target_print"),
        "solver_fallback": bundle.get("solver_fallback"),
        "orientation_fallbacks": [{"image": r["image"], "method": r["method"], "reason": r["fallback_reason"]}
                                  for r in f.read_json("calibration.json")["images"] if "fallback_reason" in r],
        "predicted_sigma_max_m": plan["predicted_sigma_max_m"],
        "achieved_sigma_max_m": float(np.nanmax(achieved)),
        "predicted_over_achieved": _predicted_over_achieved(targets) | _held_lens_growth(plan, bundle, targets),
        "stage_times_s": times,
        "cell_calibration": _calibration_status(ctx),
        "targets": targets,
        "not_measured": [ids[j] for j in np.flatnonzero(~ok & judged)],
        "decision_rule": DECISION_RULE,
        "inconclusive": [ids[j] for j in np.flatnonzero(judged) if decision[j] == "inconclusive"],
        "suspect": [ids[j] for j in np.flatnonzero(judged & ok) if ids[j] in suspect],
        "coded_targets": [ids[j] for j in np.flatnonzero(coded)],
        # measured, not judged: where the bar holds them, not where the part's surface is
        "scale_bar_ends": [{"id": ids[j], "measured": al.aligned[j], "cov": al.deviation_cov[j]}
                           for j in np.flatnonzero(bar_end)],
        "rejected_observations": bundle.get("rejected", []),
        "identification_dropped": identification_drops(f.read_json("observations.json")),
        "scale_bars": bundle.get("scale_bars") or [],
        "uncertainty_budget": _budget(cov_scale if nb else None, al.deviation_cov, judged & ok, bundle,
                                      scale_sigma(measured, pc, judged & ok & ~np.isin(ids, list(suspect)), K, K_sigma)
                                      if nb else None),
        # the deviations' joint covariance (targets correlate through the poses, the camera, the scale and the
        # alignment): what a derived quantity (a distance, a feature's position) needs beyond each target's block
        "deviation_covariance": {"file": DEVIATION_COVARIANCE, "ids": list(ids), "units": "m^2",
                                 "form": "Sigma = blockdiag(D) + U C U^T: D (n, 3, 3), U (n, 3, r), C (r, r); targets "
                                         "in the order of ids, the aligned (CAD) frame; NaN for a target not measured"},
        "left_out": {"observations": len(sc.get("dropped_observations", [])),
                     "targets": sc.get("dropped_targets", []), "images": sc.get("dropped_images", []),
                     "start_pose_kept": (sc.get("resection") or {}).get("start_kept", [])},
    }
    doc["precision_requirement"] = requirement_doc(job, required, req_source, achieved, ok, judged, targets)
    loop = _closed_loop(f)
    if loop is not None:
        doc["closed_loop"] = loop
    figs = {
        "network": R.figure_network(job.part.mesh, np.array([s["part_from_cam"] for s in plan["stations"]]), nominal),
        "deviations": R.figure_deviations(job.part.mesh, nominal[judged], np.nan_to_num(dev_norm[judged], nan=np.inf),
                                          tol[judged], passed[judged]),
        "ellipsoids": R.figure_ellipsoids(job.part.mesh, al.aligned[ok], cov[ok]),
        "sigma": R.figure_sigma(np.array([t["predicted_sigma_images_m"] for t in targets], dtype=float),
                                achieved_images[judged]),
        "residuals": R.figure_residuals(np.asarray(bundle["residuals_px"], dtype=float), rejected_mask(bundle)),
    }
    from cell.record import figures3d as F3

    stations = np.array([s["part_from_cam"] for s in plan["stations"]])
    judged_ids = [t for t, j in zip(ids, judged) if j]
    interactive = F3.html_block({
        "deviations": F3.deviations_3d(job.part.mesh, nominal[judged], judged_ids, dev_norm[judged], tol[judged],
                                       passed[judged]),
        "network": F3.network_3d(job.part.mesh, stations, nominal, list(ids)),
    })
    dc = al.deviation_covariance
    buf = io.BytesIO()
    np.savez_compressed(buf, D=dc.D, U=dc.U, C=dc.C, ids=np.asarray(ids, dtype=str))
    atomic_write_bytes(f.file(DEVIATION_COVARIANCE), buf.getvalue())
    # the REPORT stage's own time is not known yet: the report lists the stages before it
    atomic_write_json(f.file("report.json"), doc)
    from cell.record.jobfolder import to_jsonable

    atomic_write_bytes(f.file("report.html"), R.render_html(to_jsonable(doc), figs, interactive).encode())
    return verdict, verdict_reasons


def lens_verdict(lens: dict, verdict: str, reasons) -> tuple[str, list]:
    """The verdict and its reasons with what report.json's ``lens`` says against the statement: a PASS becomes
    INCOMPLETE (the measurement does not show that the part conforms) when the images refute the radial lens model
    (``note``, decision 0054) or the lens changed during the acquisition (``stability_note``, decision 0066)."""
    reasons = list(reasons)
    if lens.get("note"):
        reasons.append("the lens has terms its radial model does not carry: the targets' coordinates and uncertainties "
                       "are off (report.json lens.note)")
    if lens.get("stability_note"):
        reasons.append("the lens changed during the acquisition: the targets' coordinates and uncertainties rest on "
                       "one lens for all images (report.json lens.stability_note)")
    if (lens.get("note") or lens.get("stability_note")) and verdict == "PASS":
        verdict = "INCOMPLETE"
    return verdict, reasons


def run(ctx) -> None:
    """REPORT: alignment to CAD, deviations, decisions; report.json and report.html."""
    verdict, reasons = write_report(ctx)
    doc = ctx.folder.read_json("report.json")
    for note in ((doc.get("predicted_over_achieved") or {}).get("note"),  # the plan's prediction did not hold (issue 15)
                 ((doc.get("predicted_over_achieved") or {}).get("held_lens") or {}).get("note"),
                 (doc.get("target_thickness") or {}).get("note"),  # a real cell's targets' thickness not given
                 (doc.get("thermal") or {}).get("note"),  # the part's size is not its CAD's (decision 0053)
                 (doc.get("thermal") or {}).get("part_scale_not_estimated"),
                 (doc.get("lens") or {}).get("focal_note"),  # said by ADJUST: lens.note
                 (doc.get("lens") or {}).get("held_note")):  # the cell's lens held as exact (decision 0056)
        if note:
            ctx.log.log("warning", note)
            ctx.say(f"  WARNING {note}")
    pr = doc.get("precision_requirement")
    if pr:  # said whether the closed loop ran or not (decision 0070)
        msg = (f"precision requirement ({pr['source']}): {pr['n_met']} of {pr['n_judged']} target(s) within it"
               + ("" if pr["closed_loop"] else "; the closed loop is off ([planning] closed_loop = false)"))
        ctx.log.log("info" if pr["n_met"] == pr["n_judged"] else "warning", msg)
        ctx.say(f"  {msg}")
    if verdict != "PASS" and reasons:
        msg = f"verdict {verdict}: " + "; ".join(reasons)
        if verdict in ("INCOMPLETE", "UNTRUSTED"):
            ctx.log.log("warning", msg)
        ctx.say(f"  {msg}")
    ctx.say(f"  verdict {verdict}: report {ctx.folder.file('report.html')}")
