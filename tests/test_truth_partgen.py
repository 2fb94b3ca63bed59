"""Truth on parts the suite has never seen: random plates and skins, deviations at 0.5x / 3x / 10x tolerance
and 5 sigma on up to half of the targets (tests/partgen.py), whole jobs on the simulated cell.

Per run, report.json's deviations against the injected truth: sqrt(mean m^2 / 3) within 1.00 +- 0.15, at least
97 % of the untouched targets inside their 99 % ellipsoid, at most 2 % of them flagged significant, every
deviation beyond tolerance failed, the alignment trusted. The figures are also computed given the scale bar (the covariance less its certificate's share, ``cov_scale_bar``), printed for the record: the generated bar's certificate is off its true length by a draw of its sigma, as a real one is. One run with the part misplaced by 10 mm / 5 deg, found by ``cell locate --write`` first: never a quiet
wrong number. More seeds: benchmarks/truth_partgen.py, decisions 0021, 0029.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2, norm

from tests.jobutil import run_cell
from tests.partgen import make_part_job

pytestmark = pytest.mark.slow


def truth_figures(report: dict, part) -> dict:
    """Deviations in report.json against the injected truth (``part.deviations``, mm).

    Targets the report calls suspect (decision "inconclusive": their rays could not be verified) are counted, not
    compared. ``ratio`` and ``untouched_in_99`` use each target's stated covariance (``cov``); the ``_given_bar`` ones the
    same less the scale bar certificate's share (``cov_scale_bar``), for the record: the generated bar's certificate
    is off its true length by a draw of its sigma (tests/partgen.py), so a run realises that share (decision 0036)."""
    m2, m2b, untouched, significant, beyond_failed, suspect, quiet, no_share = [], [], [], [], [], 0, 0, 0
    not_measured = 0
    for t in report["targets"]:
        if t["measured"][0] is None:
            not_measured += t["kind"] != "coded"
            continue
        if t.get("suspect"):  # reported inconclusive, with a warning: loud, not a quiet number (decision 0021)
            suspect += 1
            quiet += t.get("decision") != "inconclusive"
            continue
        d = np.asarray(part.deviations.get(t["id"], np.zeros(3))) * 1e-3
        e = np.asarray(t["deviation"]) - d
        C = np.asarray(t["cov"])
        m2.append(float(e @ np.linalg.solve(C, e)))
        no_share += t.get("cov_scale_bar") is None
        Cb = C - np.asarray(t["cov_scale_bar"]) if t.get("cov_scale_bar") is not None else C
        m2b.append(float(e @ np.linalg.solve(Cb, e)))
        untouched.append(t["id"] not in part.deviations)
        significant.append(bool(t["significant"]))
        if np.linalg.norm(d) > t["tolerance_m"]:
            beyond_failed.append(not t["pass"])
    m2, m2b, untouched, significant = np.array(m2), np.array(m2b), np.array(untouched), np.array(significant)
    q99 = chi2.ppf(0.99, 3)
    # the realised scale error of the measurement (a similarity fit of the untouched targets to the truth, first
    # order) against the stated one (report.json uncertainty_budget.scale_sigma_ppm): one draw of one shared variable
    pts = [(np.asarray(t["measured"]), np.asarray(t["nominal"])) for t in report["targets"]
           if t["measured"][0] is not None and not t.get("suspect") and t["id"] not in part.deviations]
    scale_ppm = scale_z = None
    if len(pts) >= 3:
        X, T = (np.array(a) for a in zip(*pts))
        x = T - T.mean(axis=0)
        scale_ppm = float(np.sum(x * (X - X.mean(axis=0) - x)) / np.sum(x * x) * 1e6)
        sig = (report.get("uncertainty_budget") or {}).get("scale_sigma_ppm")
        scale_z = scale_ppm / sig if sig else None
    given = given_certificate(report, part)
    return {**given, "ratio": float(np.sqrt(m2.mean() / 3)), "ratio_given_bar": float(np.sqrt(m2b.mean() / 3)),
            "n": int(len(m2)),
            "untouched_in_99": float(np.mean(m2[untouched] <= q99)),
            "untouched_in_99_given_bar": float(np.mean(m2b[untouched] <= q99)),
            "false_significant": float(np.mean(significant[untouched])),
            "beyond_tolerance": len(beyond_failed), "beyond_tolerance_failed": int(sum(beyond_failed)),
            "suspect": suspect, "suspect_not_inconclusive": quiet, "without_scale_bar_share": no_share, "not_measured": not_measured, "scale_ppm": scale_ppm, "scale_z": scale_z}


# the truth criteria of issue 15, per run
RATIO_BAND = (0.85, 1.15)
IN99_MIN = 0.97
FALSE_SIGNIFICANT_MAX = 0.02


def statement_odds(D: np.ndarray, U: np.ndarray, C: np.ndarray, untouched: np.ndarray, k_sigma: float = 3.0,
                   draws: int = 2000, seed: int = 0) -> dict:
    """How often a run misses each truth criterion when the cell's statement is exactly right.

    The deviations' errors of the judged targets are drawn from their stated joint covariance
    ``blockdiag(D) + U C U^T`` (``D: (n, 3, 3)``, ``U: (n, 3, r)``, ``C: (r, r)``, report.json
    ``deviation_covariance``) and judged as :func:`truth_figures` judges the real ones, each with its own block
    ``D_i + U_i C U_i^T``. Targets correlate through the poses, the camera, the scale and the alignment: one shared
    draw moves them all, so a run's ratio scatters far more than ``n`` independent chi-square(3) would make it, and a
    band such as 1.00 +- 0.15 is missed by an honest statement at a rate this gives. Returns the shares of draws
    outside each criterion (``ratio``, ``in99`` of the ``untouched`` targets, ``false_significant`` at ``k_sigma``),
    ``any`` (at least one), and the 5-95 % range of the ratio."""
    D, U, C = (np.nan_to_num(np.asarray(a, dtype=float)) for a in (D, U, C))
    n = len(D)
    # dense: the aligned form's C is indefinite (the alignment's S-transformation writes its cross terms there),
    # only the whole is a covariance
    S = np.einsum("nar,rs,mbs->namb", U, C, U).reshape(3 * n, 3 * n)
    S[np.arange(3 * n)[:, None], 3 * (np.arange(3 * n) // 3)[:, None] + np.arange(3)] += D.reshape(3 * n, 3)
    S = 0.5 * (S + S.T)
    w, V = np.linalg.eigh(S)
    if w[0] < -1e-9 * w[-1]:
        raise ValueError(f"statement_odds: the stated joint covariance is not positive semi-definite "
                         f"(eigenvalue {w[0]:.3g} against {w[-1]:.3g})")
    L = V * np.sqrt(np.clip(w, 0.0, None))
    blocks = np.array([S[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(n)])
    inv = np.linalg.inv(blocks)
    q99 = chi2.ppf(0.99, 3)
    q_sig = chi2.isf(2 * norm.sf(k_sigma), 3)  # report.json significant: sigma level > k (deviation_sigma_level)
    e = (L @ np.random.default_rng(seed).standard_normal((3 * n, draws))).T.reshape(draws, n, 3)
    m2 = np.einsum("dna,nab,dnb->dn", e, inv, e)
    ratio = np.sqrt(m2.mean(axis=1) / 3)
    in99 = np.mean(m2[:, untouched] <= q99, axis=1) if untouched.any() else np.ones(draws)
    fsig = np.mean(m2[:, untouched] > q_sig, axis=1) if untouched.any() else np.zeros(draws)
    out_ratio = (ratio < RATIO_BAND[0]) | (ratio > RATIO_BAND[1])
    out_in99, out_fsig = in99 < IN99_MIN, fsig > FALSE_SIGNIFICANT_MAX
    return {"ratio": float(out_ratio.mean()), "in99": float(out_in99.mean()), "false_significant": float(out_fsig.mean()),
            "any": float((out_ratio | out_in99 | out_fsig).mean()),
            "ratio_5_95": [float(np.quantile(ratio, 0.05)), float(np.quantile(ratio, 0.95))]}


def report_odds(report: dict, folder: Path, part, draws: int = 2000, seed: int = 0) -> dict:
    """:func:`statement_odds` for a finished run: the judged targets of report.json (measured, not suspect), their
    joint covariance from the job folder's ``deviation_covariance`` file, the job's ``[report] sigma_factor``."""
    import tomllib

    ref = report["deviation_covariance"]
    with np.load(Path(folder) / ref["file"]) as z:
        D, U, C = z["D"], z["U"], z["C"]
    row = {t: i for i, t in enumerate(ref["ids"])}
    judged = [t["id"] for t in report["targets"] if t["measured"][0] is not None and not t.get("suspect")]
    idx = np.array([row[t] for t in judged], dtype=int)
    k = (tomllib.loads(Path(part.job).read_text()).get("report") or {}).get("sigma_factor", 3.0)
    untouched = np.array([t not in part.deviations for t in judged], dtype=bool)
    return statement_odds(D[idx], U[idx], C, untouched, float(k), draws, seed)


def given_certificate(report: dict, part) -> dict:
    """The truth figures given the scale bar certificates' realised errors: the generator knows each bar's true
    length, so the measurement's error from the certificates is taken out of each deviation (exactly, through the
    report's ``scale_bar_gains``: metres per metre of each certificate's error, in the aligned frame; for a report
    without them and one bar, to first order: every coordinate scaled by ``certified / true`` about the alignment's
    centroid), and the certificates' share (``cov_scale_bar``) out of each covariance. What is left is the rest of the
    statement: the images, the network and the bar ends' measurement. One shared draw moves every target of a run
    (decision 0036), so this tells a run whose ratio a certificate draw moved from a statement that is wrong; it is
    printed, the criteria stay the unconditional ones. ``certificate_z``: the bars' draws, combined as the scale
    sees them (their gains' weights), in units of the combination's sigma."""
    import csv
    import tomllib

    doc = tomllib.loads(Path(part.job).read_text())
    job = doc.get("job") or {}
    bars = job.get("scale_bars") or ([job["scale_bar"]] if job.get("scale_bar") else [])
    if not bars:
        return {}
    with open(Path(part.job).parent / job["targets"], newline="") as f:
        # a bar's true length is between its ends' faces: the CAD points lifted by the targets' thickness
        th = float(job.get("target_thickness") or 0.0)
        cad = {r["id"]: np.array([float(r[a]) + th * float(r["n" + a]) for a in "xyz"]) for r in csv.DictReader(f)}
    err_mm, sig_mm = [], []
    for bar in bars:
        ends = [cad[bar[k]] + np.asarray(part.deviations.get(bar[k], np.zeros(3))) for k in ("a", "b")]
        err_mm.append(float(bar["length"]) - float(np.linalg.norm(ends[0] - ends[1])))
        sig_mm.append(float(bar["sigma"]))
    err_m, sig_m = 1e-3 * np.array(err_mm), 1e-3 * np.array(sig_mm)
    fit = set(report["alignment"].get("targets_in_fit") or [])
    c = np.mean([t["nominal"] for t in report["targets"] if t["id"] in fit], axis=0) if fit else None
    # the gains' columns are the bars ADJUST used (report.json scale_bars[i].gain_column); a bar left out has none,
    # and its certificate did not enter the measurement
    cols = [b.get("gain_column") for b in report.get("scale_bars") or []]
    if len(cols) != len(bars):
        cols = list(range(len(bars)))
    used = [i for i, col in enumerate(cols) if col is not None]
    m2, inside = [], []
    for t in report["targets"]:
        if t["measured"][0] is None or t.get("suspect") or t.get("cov_scale_bar") is None or c is None:
            continue
        d = np.asarray(part.deviations.get(t["id"], np.zeros(3))) * 1e-3
        gains = t.get("scale_bar_gains")
        if gains is not None and np.shape(gains) == (3, len(used)):
            G = np.asarray(gains, dtype=float)
            shift = G @ err_m[used] if used else np.zeros(3)
        elif len(bars) == 1:
            eps = err_mm[0] / (float(bars[0]["length"]) - err_mm[0])
            shift = eps * (np.asarray(t["nominal"]) - c)
        else:
            return {}
        e = np.asarray(t["deviation"]) - d - shift
        C = np.asarray(t["cov"]) - np.asarray(t["cov_scale_bar"])
        m2.append(float(e @ np.linalg.solve(C, e)))
        if t["id"] not in part.deviations:
            inside.append(m2[-1] <= chi2.ppf(0.99, 3))
    if not m2:
        return {}
    if len(bars) == 1:
        cz = err_mm[0] / sig_mm[0]
    else:  # the combination the scale sees: inverse-variance weights of the used bars' relative errors
        L = np.array([float(bars[i]["length"]) for i in used]) * 1e-3
        err_m, sig_m = err_m[used], sig_m[used]
        w = (L / sig_m) ** 2
        cz = float(np.sum(w * err_m / L) / np.sum(w) / (1.0 / np.sqrt(np.sum(w))))
    return {"certificate_z": float(cz), "certificate_z_bars": [float(v) for v in err_m / sig_m],
            "ratio_given_certificate": float(np.sqrt(np.mean(m2) / 3)),
            "untouched_in_99_given_certificate": float(np.mean(inside)) if inside else None}


def _check(fig: dict, report: dict) -> None:
    assert report["alignment"]["trusted"], report["alignment"]["reasons"]
    assert RATIO_BAND[0] <= fig["ratio"] <= RATIO_BAND[1], fig
    assert fig["untouched_in_99"] >= IN99_MIN, fig
    assert fig["without_scale_bar_share"] == 0, fig  # the generated jobs have a scale bar: every target states its share
    assert fig["ratio_given_bar"] >= fig["ratio"], fig  # the certificate's share is part of the statement
    assert fig["false_significant"] <= FALSE_SIGNIFICANT_MAX, fig
    assert fig["suspect_not_inconclusive"] == 0, fig
    assert fig["beyond_tolerance"] > 0 and fig["beyond_tolerance_failed"] == fig["beyond_tolerance"], fig


def test_random_part_deviations_match_the_truth(tmp_path):
    """A random skin (seed 100, as benchmarks/truth_partgen.py draws it): every truth criterion holds."""
    part = make_part_job(tmp_path / "job", np.random.default_rng(100))
    run = run_cell("run", str(part.job), "--archive", str(tmp_path / "archive"), timeout=900)
    assert run.code == 0, run.stderr[-3000:]
    report = json.loads((Path(run.doc["folder"]) / "report.json").read_text())
    fig = truth_figures(report, part)
    print(f"\n{part.kind} seed 100: {fig}")
    _check(fig, report)
    # the deviations' joint covariance in the job folder: its blocks are the report's per-target covariances
    ref = report["deviation_covariance"]
    with np.load(Path(run.doc["folder"]) / ref["file"]) as z:
        assert list(z["ids"]) == ref["ids"]
        blocks = z["D"] + np.einsum("nar,rs,nbs->nab", z["U"], z["C"], z["U"])
    row = {t: i for i, t in enumerate(ref["ids"])}
    for t in report["targets"]:
        if t["measured"][0] is not None:
            assert np.allclose(blocks[row[t["id"]]], t["cov"], rtol=1e-9, atol=1e-20), t["id"]
    # the dots are 0.05-0.3 mm thick (tests/partgen.py): the cell measured their faces, the report speaks of the
    # CAD surface under them, in report.json and in plan.json alike (decision 0049)
    import csv
    import tomllib

    th = tomllib.loads(part.job.read_text())["job"]["target_thickness"]
    assert report["target_thickness"]["thickness_m"] == pytest.approx(th * 1e-3) and th > 0
    with (part.folder / "targets.csv").open(newline="") as f:
        cad = {r["id"]: 1e-3 * np.array([float(r[a]) for a in "xyz"]) for r in csv.DictReader(f)}
    plan = json.loads((Path(run.doc["folder"]) / "plan.json").read_text())
    assert max(np.abs(np.asarray(t["xyz"]) - cad[t["id"]]).max() for t in plan["targets"]) < 1e-9
    for t in report["targets"]:
        assert np.abs(np.asarray(t["nominal"]) - cad[t["id"]]).max() < 1e-9, t["id"]
        if t["measured"][0] is not None:
            assert np.allclose(np.asarray(t["measured"]) - t["nominal"], t["deviation"], rtol=0, atol=1e-12), t["id"]
    odds = report_odds(report, Path(run.doc["folder"]), part, draws=500)
    print(f"odds that an exact statement misses a criterion here: {odds}")
    assert 0.0 <= odds["any"] < 0.5, odds  # the criteria are not a coin toss for an honest statement on this part
    # predicted = achieved: the pre-analysis from renders (decision 0034) on a part the suite has never seen
    assert 0.75 <= report["predicted_over_achieved"]["median"] <= 1.25, report["predicted_over_achieved"]


def test_a_misplaced_part_is_located_and_never_reported_quietly_wrong(tmp_path):
    """Misplaced by 10 mm / 5 deg, found by ``cell locate --write``, then measured: either the truth criteria
    hold, or the report says the alignment is not trusted (verdict UNTRUSTED, with its reasons)."""
    part = make_part_job(tmp_path / "job", np.random.default_rng(5), "plate", deviating_share=0.25,
                         misplacement=(10.0, 5.0))
    loc = run_cell("locate", str(part.job), "--write", timeout=600)
    assert loc.code == 0, loc.stderr[-3000:]
    run = run_cell("run", str(part.job), "--archive", str(tmp_path / "archive"), timeout=900)
    assert run.code == 0, run.stderr[-3000:]
    report = json.loads((Path(run.doc["folder"]) / "report.json").read_text())
    fig = truth_figures(report, part)
    print(f"\nmisplaced plate: {fig}, alignment {report['alignment']['trusted']} {report['alignment']['reasons']}")
    if report["alignment"]["trusted"]:
        _check(fig, report)
    else:
        assert report["verdict"] == "UNTRUSTED" and report["alignment"]["reasons"]


def test_a_misplaced_skin_is_located_by_its_coded_markers(tmp_path):
    """A curved skin carries coded markers too (rigid plates touching it at their centre): ``cell locate`` finds a
    10 mm / 5 deg misplacement within what it states, against the simulated truth, through the part's drawn lens,
    which the job does not state (the placement estimates the lens with it: decision 0055)."""
    import csv

    part = make_part_job(tmp_path / "job", np.random.default_rng(100), "skin", misplacement=(10.0, 5.0))
    with (part.folder / "targets.csv").open(newline="") as f:
        assert sum(r["kind"] == "coded" for r in csv.DictReader(f)) >= 6
    loc = run_cell("locate", str(part.job), "--write", timeout=600)
    assert loc.code == 0, loc.stderr[-3000:]
    s = loc.doc
    assert s["written"] and abs(s["change_from_nominal_m"] - 0.010) < 1e-4
    assert s["truth"]["error_m"] <= 4 * np.linalg.norm(s["sigma_translation_m"]) + 20e-6, s["truth"]
    assert s["truth"]["error_rad"] <= 4 * np.linalg.norm(s["sigma_rotation_rad"]) + 1e-4, s["truth"]
