"""The inspection report: report.json (the contract) and report.html (one self-contained file).

report.json follows ARCHITECTURE.md: ``job``, ``images``, ``sigma0_px``, ``targets``
[{id, nominal, measured, cov, deviation, deviation_norm_m, tolerance_m, pass,
predicted_sigma_m, achieved_sigma_m}], plus ``verdict`` and the time per stage.
Figures are PNGs rendered with matplotlib (Agg) and embedded as data URIs, so the
HTML opens anywhere, offline, as one file.
"""
from __future__ import annotations

import base64
import html
from typing import Any

import numpy as np

import matplotlib

matplotlib.use("Agg")
from matplotlib.figure import Figure  # noqa: E402  (not pyplot: its import is ~0.3-0.5 s of a job)
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection  # noqa: E402

from cell.record.decisions import counts, trusted  # noqa: E402
from planning.plot import figure_png  # noqa: E402


def _png(fig) -> str:
    """The figure as base64 PNG at 110 dpi, cut to its artists (drawn once: :func:`planning.plot.figure_png`)."""
    return base64.b64encode(figure_png(fig, dpi=110, tight=True)).decode()


def _mesh_axes(ax, mesh, alpha=0.18):
    tris = mesh.vertices[mesh.faces] * 1000.0
    ax.add_collection3d(Poly3DCollection(tris, facecolor=(0.6, 0.65, 0.7, alpha), edgecolor=(0.3, 0.3, 0.35, 0.25),
                                         linewidths=0.3))


def _equal_3d(ax, pts):
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    for set_lim, ci in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), c):
        set_lim(ci - r, ci + r)
    ax.set_box_aspect((1, 1, 1))


def figure_network(mesh, stations_part_from_cam: np.ndarray, xyz: np.ndarray) -> str:
    """Part, targets and camera stations (as small pyramids looking at the part)."""
    fig = Figure(figsize=(6.5, 5.5))
    ax = fig.add_subplot(projection="3d")
    _mesh_axes(ax, mesh)
    ax.scatter(*(xyz * 1000).T, s=4, c="k")
    pts = [xyz * 1000]
    segments = []  # every station's pyramid in one collection (one artist, not five lines per station)
    for k, T in enumerate(stations_part_from_cam):
        c = T[:3, 3] * 1000
        R = T[:3, :3]
        s = 40.0
        corners = [c + s * (R @ np.array([x, y, 1.5])) for x, y in ((-1, -0.8), (1, -0.8), (1, 0.8), (-1, 0.8))]
        segments += [(c, p) for p in corners] + [(corners[i], corners[(i + 1) % 4]) for i in range(4)]
        ax.text(*c, str(k + 1), fontsize=6, color="tab:blue")
        pts.append(c[None])
    if segments:
        ax.add_collection3d(Line3DCollection(np.array(segments), colors="tab:blue", linewidths=0.7))
    _equal_3d(ax, np.vstack(pts))
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_zlabel("z [mm]")
    ax.set_title(f"Network: {len(stations_part_from_cam)} stations")
    return _png(fig)


def figure_deviations(mesh, nominal: np.ndarray, dev_norm: np.ndarray, tol: np.ndarray, passed: np.ndarray) -> str:
    """Targets on the part coloured by |deviation| / tolerance; failures ringed in red."""
    fig = Figure(figsize=(6.5, 5.5))
    ax = fig.add_subplot(projection="3d")
    _mesh_axes(ax, mesh, alpha=0.12)
    ratio = dev_norm / tol
    size = float(np.clip(18 * np.sqrt(200 / max(len(nominal), 1)), 1, 18))  # thousands of targets stay apart
    sc = ax.scatter(*(nominal * 1000).T, c=np.clip(ratio, 0, 2), cmap="RdYlGn_r", vmin=0, vmax=2, s=size)
    bad = ~passed
    if bad.any():
        ax.scatter(*(nominal[bad] * 1000).T, s=90, facecolors="none", edgecolors="red", linewidths=1.2)
    fig.colorbar(sc, ax=ax, shrink=0.7, label="|deviation| / tolerance")
    _equal_3d(ax, nominal * 1000)
    ax.set_title("Deviation from CAD")
    return _png(fig)


def figure_ellipsoids(mesh, measured: np.ndarray, cov: np.ndarray) -> str:
    """Error ellipsoids (scaled so the largest is 1/25 of the part), as their three principal axes."""
    fig = Figure(figsize=(6.5, 5.5))
    ax = fig.add_subplot(projection="3d")
    _mesh_axes(ax, mesh, alpha=0.1)
    w, V = np.linalg.eigh(cov)
    axes = np.sqrt(np.clip(w, 0, None))
    size = np.ptp(measured, axis=0).max()
    scale = size / 25 / max(axes.max(), 1e-12)
    shown = np.argsort(-axes.sum(axis=1))[:FIGURE_ELLIPSOIDS]  # the least precise targets
    if len(shown) < len(measured):
        ax.scatter(*(measured * 1000).T, s=0.5, c="0.8")
    p = measured[shown] * 1000
    for k, col in zip(range(3), ("tab:red", "tab:green", "tab:blue")):
        d = V[shown, :, k] * (axes[shown, k] * scale * 1000)[:, None]
        ax.add_collection3d(Line3DCollection(np.stack([p - d, p + d], axis=1), colors=col, linewidths=1.0))
    _equal_3d(ax, measured * 1000)
    extra = f", the {len(shown)} least precise of {len(measured)} targets" if len(shown) < len(measured) else ""
    ax.set_title(f"Error ellipsoids (1 sigma axes x {scale:.0f}{extra})")
    return _png(fig)


def figure_sigma(predicted: np.ndarray, achieved: np.ndarray) -> str:
    fig = Figure(figsize=(5, 4))
    ax = fig.subplots()
    ok = np.isfinite(predicted) & np.isfinite(achieved)
    ax.scatter(predicted[ok] * 1e6, achieved[ok] * 1e6, s=8)
    hi = max(np.nanmax(predicted[ok], initial=0), np.nanmax(achieved[ok], initial=0)) * 1e6 * 1.1
    ax.plot([0, hi], [0, hi], "k--", lw=0.8, label="achieved = predicted")
    ax.set_xlabel("predicted sigma [um] (plan)")
    ax.set_ylabel("achieved sigma [um] (bundle)")
    ax.legend()
    ax.set_title("Predicted vs achieved precision")
    return _png(fig)


def accepted_residuals(residuals_px: np.ndarray, rejected: np.ndarray | None) -> tuple[np.ndarray, float]:
    """The accepted observations' residuals ``(m, 2)`` and the histogram's half-range (5 % beyond the largest)."""
    r = np.asarray(residuals_px, dtype=float)
    keep = np.isfinite(r).all(axis=1)
    if rejected is not None and len(rejected) == len(r):
        keep &= ~np.asarray(rejected, dtype=bool)
    a = r[keep]
    return a, (float(np.max(np.abs(a))) * 1.05 if a.size else 1.0)


def figure_residuals(residuals_px: np.ndarray, rejected: np.ndarray | None = None) -> str:
    """Histogram of the accepted observations' image residuals (u and v), its axis scaled to them.

    ``rejected: (n,) bool`` marks the observations the bundle adjustment rejected: they are left out
    (one gross outlier would stretch the axis far past the accepted ones) and listed apart in the report.
    """
    fig = Figure(figsize=(5, 4))
    ax = fig.subplots()
    a, lim = accepted_residuals(residuals_px, rejected)
    n_rej = 0 if rejected is None else int(np.asarray(rejected, dtype=bool).sum())
    ax.hist(a.ravel(), bins=60, range=(-lim, lim), color="tab:gray", histtype="stepfilled")  # one polygon, not 60 bars
    ax.set_xlim(-lim, lim)
    ax.set_xlabel("image residual [px] (u and v), accepted observations")
    ax.set_ylabel("count")
    rms = float(np.sqrt(np.mean(a ** 2))) if a.size else float("nan")
    ax.set_title(f"Residuals: rms {rms:.3f} px, {len(a)} accepted" + (f", {n_rej} rejected (listed below)" if n_rej else ""))
    return _png(fig)


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:24px;color:#222;max-width:1200px}
.verdict{font-size:28px;font-weight:700;padding:14px 20px;border-radius:8px;color:#fff;display:inline-block}
.PASS{background:#1a7f37}.FAIL{background:#cf222e}.INCOMPLETE{background:#9a6700}.UNTRUSTED{background:#82071e}
.alert{color:#fff;background:#cf222e;font-weight:700;padding:10px 16px;border-radius:6px;margin:10px 0}
.warn{background:#fff8c5;border:1px solid #d4a72c;padding:8px 14px;border-radius:6px;margin:10px 0}
table{border-collapse:collapse;font-size:13px}td,th{border:1px solid #ccc;padding:3px 7px;text-align:right}
th{background:#f3f3f3}td.l{text-align:left}tr.fail td{background:#ffebe9}
.figs img{max-width:560px;margin:6px;border:1px solid #ddd}.fig3d{max-width:1100px;margin:8px 0}
@media print{.noprint{display:none}}.kv td{text-align:left}
"""


def _num(v: Any, scale: float, digits: int) -> str:
    return "&mdash;" if v is None or not np.isfinite(v) else f"{v * scale:.{digits}f}"


def _fmt_um(v: Any) -> str:
    return "" if v is None or not np.isfinite(v) else f"{v * 1e6:.1f}"


def _status(t: dict) -> str:
    if t["measured"][0] is None:
        return "NOT MEASURED"
    status = "PASS" if t["pass"] else "FAIL"
    if t.get("print_doubtful"):
        status += f" (inconclusive: its images are not a clean dot: {t['print_doubtful']})"
    elif t.get("suspect"):
        status += " (inconclusive: suspect, its observations could not be verified)"
    elif t.get("decision") == "inconclusive":
        status += " (inconclusive: within U of the tolerance)"
    elif t.get("decision") == "undecided":
        status += " (undecided: the alignment to CAD is not trusted)"
    return status


def _headline(doc: dict) -> str:
    """The verdict line's counts: within tolerance and decided; beyond it (measured); within but not decided
    (inconclusive, undecided, suspect or doubtful); not measured. A target not measured is not beyond its
    tolerance, and an undecided one is not within it (:mod:`cell.record.decisions`)."""
    c = counts(doc["targets"], trusted(doc))
    out = f"{c['within']} of {len(doc['targets'])} targets within tolerance"
    if c["beyond"]:
        out += f", {c['beyond']} beyond it" + (f" ({c['beyond_undecided']} of them undecided or inconclusive)"
                                               if c["beyond_undecided"] else "")
    if c["undecided"]:
        out += f", {c['undecided']} undecided or inconclusive"
    if c["not_measured"]:
        out += f", {c['not_measured']} not measured"
    return out


def _inconclusive(doc: dict) -> str:
    """The verdict line's undecided targets: suspect ones (unverified observations) apart from those within U of
    their tolerance (ISO 14253-1); a report written before ``suspect`` existed counts them from the targets."""
    suspect = set(doc["suspect"]) if "suspect" in doc else {t["id"] for t in doc["targets"] if t.get("suspect")}
    near = [t for t in doc.get("inconclusive", []) if t not in suspect]
    out = ""
    if suspect:
        out += f"; {len(suspect)} suspect (observations not verified by the blunder test)"
    if near:
        out += f"; {len(near)} too close to their tolerance for this measurement to decide (ISO 14253-1)"
    return out


def _verdict_reasons(doc: dict) -> str:
    """Why the verdict is not PASS (report.json ``verdict_reasons``), under the verdict."""
    reasons = doc.get("verdict_reasons") or []
    if doc.get("verdict") == "PASS" or not reasons:
        return ""
    return ('<ul id="verdict-reasons">' + "".join(f"<li>{html.escape(r)}</li>" for r in reasons) + "</ul>")


def _alerts(doc: dict) -> str:
    """Red banners for what makes the numbers untrustworthy; yellow notes for what the operator should know."""
    out = []
    al = doc.get("alignment") or {}
    if al and not al.get("trusted", True):
        out.append(f'<div class="alert" id="alignment-alert">ALIGNMENT NOT TRUSTED: '
                   f'{html.escape("; ".join(al.get("reasons", [])))}. The deviations below are in a frame that '
                   "cannot be relied on.</div>")
    if (doc.get("layout_symmetry") or {}).get("warning"):  # the dots' names rest on the placement (decision 0058)
        out.append(f'<div class="warn" id="symmetry-alert">Target layout: '
                   f'{html.escape(doc["layout_symmetry"]["warning"])}</div>')
    if doc.get("untrusted_reasons"):  # a measurement of photographs whose own checks failed (decision 0057)
        out.append('<div class="alert" id="measurement-alert">MEASUREMENT NOT TRUSTED: '
                   f'{html.escape("; ".join(doc["untrusted_reasons"]))}</div>')
    sn = doc.get("snooping") or {}
    if sn and not sn.get("complete", True):
        out.append(f'<div class="alert" id="snooping-alert">Blunder test stopped before the end: '
                   f'{html.escape(str(sn.get("stopped")))}</div>')
    if sn.get("diverged"):
        said = "; ".join(sn["diverged"] + sn.get("handed_over", []))
        out.append('<div class="warn" id="snooping-diverged">Data-snooping rounds whose Gauss-Newton diverged '
                   f"(stopped, handed to pycolmap): {html.escape(said)}</div>")
    if sn.get("suspect_targets"):
        out.append(f'<div class="warn">Targets whose observations the blunder test could not verify (lost half of their rays, kept two or fewer after a rejection or a screening drop, or unlike their ellipse in most images; inconclusive): '
                   f'{html.escape(", ".join(sn["suspect_targets"]))}</div>')
    printed = (doc.get("target_print") or {}).get("doubtful") or []
    if printed:  # decision 0051
        out.append('<div class="alert" id="print-alert">Targets whose images are not a clean dot (a chipped edge, a '
                   "speck or stain): their centres are not the targets' and their deviations are not the part's; "
                   "inconclusive, left out of the alignment. Clean or replace them: "
                   f'{html.escape("; ".join(d["id"] + ": " + d["why"] for d in printed))}</div>')
    # what the images say of the detector model and the plan (decisions 0044, 0046, 0047): one note each
    budget, plan = doc.get("uncertainty_budget") or {}, doc.get("predicted_over_achieved") or {}
    for said, tag, head in ((budget.get("detector_model_mismatch"), "model-mismatch", "Image precision"),
                            (budget.get("detector_model_shape"), "model-shape", "Image precision"),
                            (budget.get("detector_model_range"), "model-range", "Image precision"),
                            (plan.get("note"), "prediction-off", "Plan"),
                            ((plan.get("held_lens") or {}).get("note"), "prediction-held-lens", "Plan")):
        if said:
            out.append(f'<div class="warn" id="{tag}">{head}: {html.escape(said)}</div>')
    if doc.get("solver_fallback"):
        out.append('<div class="warn" id="solver-fallback">Gauss-Newton handed the adjustment to pycolmap: '
                   f'{html.escape(str(doc["solver_fallback"]))}</div>')
    fb = doc.get("orientation_fallbacks") or []
    if fb:
        out.append(f'<div class="warn">{len(fb)} image(s) not calibrated by Faugeras-Toscani: '
                   + html.escape("; ".join(f"{x['image']}: {x.get('method', '')} ({x['reason']})" for x in fb[:6]))
                   + ("; ..." if len(fb) > 6 else "") + "</div>")
    lo = doc.get("left_out") or {}
    if lo.get("images") or lo.get("targets") or lo.get("observations"):
        what = [f"{lo.get('observations', 0)} gross observation(s)"] if lo.get("observations") else []
        what += [f"{d['id']}: {d['reason']}" for d in (lo.get("targets") or [])[:6]]
        what += [f"{d['image']} ({d['station']}): {d['reason']}" for d in (lo.get("images") or [])[:6]]
        more = len(lo.get("targets") or []) > 6 or len(lo.get("images") or []) > 6
        out.append('<div class="warn" id="left-out">Left out of the adjustment (bundle.json screening): '
                   + html.escape("; ".join(what)) + ("; ..." if more else "") + "</div>")
    dr = doc.get("identification_dropped") or {}
    unusual = {k: v for k, v in (dr.get("by_reason") or {}).items() if k != "partly hidden (CAD)"}
    if unusual:
        out.append('<div class="warn" id="identification-dropped">Named dots left unnamed by MEASURE rather than '
                   "misnamed: " + html.escape(", ".join(f"{v} {k}" for k, v in unusual.items()))
                   + " (by image below)</div>")
    smeared = [d for d in dr.get("images") or [] if d.get("smear")]
    if smeared:  # decision 0067
        out.append('<div class="warn" id="smeared">Images left out because their dots are smeared (the camera moved '
                   "during the exposure: the robot not settled, or its mount vibrating; raise [cell] settle_s, or "
                   "shorten [camera] exposure_s): " + html.escape("; ".join(
                       f"{d['image']} ({d['station']}): ~{d['smear']['length_px']:.1f} px along "
                       f"{d['smear']['direction_deg']:.0f} deg" for d in smeared)) + "</div>")
    kept = lo.get("start_pose_kept") or []
    if kept:
        listed = "; ".join(f"{d['image']}: {d['reason']}" for d in kept[:6]) + ("; ..." if len(kept) > 6 else "")
        out.append('<div class="warn" id="start-pose-kept">Images adjusted from their start pose, not from their '
                   f"resection with the common interior orientation: {html.escape(listed)}</div>")
    for n in al.get("notes", []):
        out.append(f'<div class="warn">Alignment: {html.escape(n)}</div>')
    th = doc.get("target_thickness") or {}
    if th.get("note"):
        out.append(f'<div class="warn" id="thickness-unstated">Targets: {html.escape(th["note"])}</div>')
    cal = doc.get("cell_calibration") or {}
    if "hand_eye" in cal and cal.get("status") != "verified":  # the cell the job names was not verified for it
        out.append(f'<div class="warn" id="cell-calibration">Cell calibration {html.escape(str(cal["status"]))}: '
                   f'{html.escape(str(cal.get("detail") or ""))}</div>')
    ln = doc.get("lens") or {}
    if ln.get("note"):  # decision 0054: the images refute the radial lens model
        out.append(f'<div class="alert" id="lens-alert">Lens: {html.escape(ln["note"])}</div>')
    if ln.get("stability_note"):  # decision 0066: the lens changed during the acquisition
        out.append(f'<div class="alert" id="lens-stability">Lens: {html.escape(ln["stability_note"])}</div>')
    if ln.get("focal_note"):
        out.append(f'<div class="warn" id="lens-focal">Lens: {html.escape(ln["focal_note"])}</div>')
    if ln.get("held_note"):
        out.append(f'<div class="warn" id="lens-held">Lens: {html.escape(ln["held_note"])}</div>')
    tm = doc.get("thermal") or {}
    if tm.get("note"):  # decision 0053: the part's size is not its CAD's
        out.append(f'<div class="alert" id="scale-alert">Part scale: {html.escape(tm["note"])}</div>')
    return "".join(out)


def _alignment_facts(doc: dict) -> dict:
    al = doc.get("alignment") or {}
    if not al:
        return {}
    ratio = doc.get("predicted_over_achieved") or {}
    out = {"Alignment": f"{al.get('description', al.get('method'))}; {len(al.get('targets_in_fit', []))} targets "
                        f"define the frame; rms {_fmt_um(al.get('rms_m'))} um; "
                        + ("trusted" if al.get("trusted") else "NOT TRUSTED")
                        + ("" if al.get("stable", True) else ", not stable")}
    if ratio.get("median") is not None:
        held = ratio.get("held_lens") or {}
        out["Predicted / achieved sigma"] = (f"{ratio['median']:.2f} (median over {ratio['n']} targets; "
                                             f"10-90 %: {ratio['p10']:.2f}-{ratio['p90']:.2f})"
                                             + ("" if held.get("total_median") is None else
                                                f"; the images' precision, without the held lens's share "
                                                f"(with it {held['total_median']:.2f}: the lens grew sigma "
                                                f"x{held['achieved_growth_median']:.2f}, planned "
                                                f"x{held['planned_growth_median']:.2f})"))
    if doc.get("snooping"):
        out["Rejected observations"] = f"{doc.get('n_rejected', 0)} (listed in bundle.json and in report.json rejected_observations)"
    return out


def _measure_facts(doc: dict) -> dict:
    th = doc.get("target_thickness")
    out = {} if th is None else {"Target thickness": (
        f"{th['thickness_m'] * 1e3:.3g} mm, taken off along each target's CAD normal: coordinates are of the surface"
        if th.get("thickness_m") else "0 (coordinates are of the targets' faces)")
        + ("" if th.get("stated_in_job") else "; not given in the job")}
    tm = doc.get("thermal")
    if tm is not None:  # decision 0053
        ps = tm.get("part_scale")
        said = (f"part {tm['part_C']:.1f} C +- {tm['part_sigma_K']:.1f} K at {tm['part_cte_ppm_per_K']:.1f} ppm/K, "
                f"scale bars {tm['bars_C']:.1f} C; " if tm.get("stated_in_job") else "not given ([thermal]); ")
        pr = tm.get("probe")
        if pr:
            said += (f"read by {pr.get('device')}: {pr['start_C']:.2f} C at the start of the acquisition"
                     + (f", {pr['end_C']:.2f} C at its end" if pr.get("end_C") is not None else "") + "; ")
        out["Temperature"] = said + tm["correction"]
        if doc.get("scale_bar_ends"):
            out["Scale bar ends (the bar's, not judged)"] = ", ".join(e["id"] for e in doc["scale_bar_ends"])
        if ps is not None:
            out["Part scale against CAD"] = (f"{ps['scale_ppm']:+.1f} ppm +- {ps['sigma_ppm']:.1f} ppm over "
                                             f"{ps['targets']} targets" + ("" if ps["significant"] else
                                                                           " (not significant)"))
        elif tm.get("part_scale_not_estimated"):
            out["Part scale against CAD"] = "NOT CHECKED: " + tm["part_scale_not_estimated"]
    ln = doc.get("lens")
    if ln and ln.get("focal_length_mm") is not None:  # decision 0054
        f_sig = ln.get("focal_length_sigma_mm")
        out["Lens"] = (f"{ln['model']} ({', '.join(ln['estimated']) or 'held at the nominal'}): principal distance "
                       f"{ln['focal_length_mm']:.3f}" + (f" +- {f_sig:.4f}" if f_sig else "") + f" mm (nominal "
                       f"{ln['nominal_focal_length_mm']:.3g}), principal point ({ln['principal_point_px'][0]:.1f}, "
                       f"{ln['principal_point_px'][1]:.1f}) px, distortion at the corner "
                       f"{ln['distortion_at_corner_px']:.1f} px")
    dr = doc.get("identification_dropped")
    if dr is None:
        return out
    return out | {"Named dots left unnamed (MEASURE)": f"{dr.get('n_dropped', 0)}" + (": " + ", ".join(
        f"{v} {k}" for k, v in dr["by_reason"].items()) if dr.get("by_reason") else "")}


def _budget_facts(doc: dict) -> dict:
    """The uncertainty budget (report.json ``uncertainty_budget``) in a line or two."""
    b = doc.get("uncertainty_budget")
    if not b:
        return {}
    out = {}
    if b.get("scale_sigma_ppm") is not None:
        out["Scale uncertainty (1 sigma)"] = (f"{b['scale_sigma_ppm']:.1f} ppm, of which the scale bar certificate "
                                              f"{b['scale_sigma_certificate_ppm']:.1f} ppm")
    for d in doc.get("scale_bars") or []:  # each bar: its certificate, its test, used or left out (decision 0041)
        name = "-".join(d["bar"])
        cert = f"certificate {d['certificate_m'] * 1e3:.4f} mm +- {d['certificate_sigma_m'] * 1e6:.1f} um"
        if d.get("certified_at_20C_m") is not None:  # decision 0053
            cert += f" at the measurement (certified {d['certified_at_20C_m'] * 1e3:.4f} mm at 20 C)"
        if not d.get("used"):
            out[f"Scale bar {name}"] = f"{cert}; LEFT OUT: {d.get('left_out')}"
        elif d.get("normalised_residual") is not None:
            out[f"Scale bar {name}"] = (f"{cert}; adjusted minus certificate {d['residual_m'] * 1e6:+.1f} um "
                                        f"({d['normalised_residual']:+.2f} sigma): {d['test']}; used")
        else:
            out[f"Scale bar {name}"] = f"{cert}; used; {d.get('test') or 'not tested'}"
    if b.get("scale_bar_share_median") is not None:
        out["Scale bar certificate in the variance"] = (f"{100 * b['scale_bar_share_median']:.0f} % median, "
                                                         f"{100 * b['scale_bar_share_max']:.0f} % at most")
    extra = [f"{b['shared_misfit_targets']} target(s) with a background misfit shared by their views"] \
        if b.get("shared_misfit_targets") else []
    if b.get("observations_clipped"):
        extra.append(f"{b['observations_clipped']} observation(s) of clipped (overexposed) dots")
    if (b.get("clip_level") or {}).get("n_targets"):
        c = b["clip_level"]
        extra.append(f"the bound of {c['n_observations']} clipped dot(s)' unknown level ({c['bound_rms_px']:.4f} px rms), "
                     f"shared by their views (sigma x{c['sigma_growth_median']:.3f} median, "
                     f"x{c['sigma_growth_max']:.2f} at most)")
    if (b.get("shared_floor") or {}).get("n_targets"):
        f = b["shared_floor"]
        extra.append(f"a share {f['rho_all']:.4f} of every dot's error common to its views (sigma x"
                     f"{f['sigma_growth_median']:.2f} median)")
    extra += [f"scale bar {'-'.join(e['bar'])} ends next to an edge: length {1e6 * e['length_sigma_m']:.1f} um (1 sigma)"
              for e in b.get("scale_bar_ends") or []]
    if extra:
        out["Stated beyond the detector model"] = "; ".join(extra)
    if b.get("datum_left_out"):
        ids = b["datum_left_out"]
        out["Left out of the bundle's datum"] = (f"{len(ids)} target(s) determined >10x worse than the median: "
                                                 + ", ".join(ids[:8]) + (" ..." if len(ids) > 8 else ""))
    return out


def _rejected_table(doc: dict) -> str:
    rej = doc.get("rejected_observations") or []
    if not rej:
        return ""
    rows = "".join(f"<tr><td class=l>{html.escape(str(r.get('image')))}</td><td class=l>{html.escape(str(r.get('target')))}</td>"
                   f"<td>{_num((r.get('residual_px') or [None, None])[0], 1, 2)}</td>"
                   f"<td>{_num((r.get('residual_px') or [None, None])[1], 1, 2)}</td>"
                   f"<td>{_num(r.get('test_statistic'), 1, 1)}</td><td>{html.escape(str(r.get('test_dof', '')))}</td></tr>"
                   for r in rej)
    return (f"<h3>Observations rejected by the bundle adjustment ({len(rej)})</h3><table id=rejected><tr><th>image</th>"
            f"<th>target</th><th>residual u [px]</th><th>residual v [px]</th><th>test statistic</th><th>dof</th></tr>"
            f"{rows}</table>")


def _dropped_table(doc: dict) -> str:
    """MEASURE's drops per image (report.json ``identification_dropped``): how many named dots each check left
    unnamed in each image."""
    dr = doc.get("identification_dropped") or {}
    ims = dr.get("images") or []
    if not ims:
        return ""
    kinds = list(dr.get("by_reason") or {})
    head = "".join(f"<th>{html.escape(k)}</th>" for k in kinds)
    rows = "".join(f"<tr><td class=l>{html.escape(str(r['image']))}</td>"
                   f"<td class=l>{html.escape(str(r.get('station')))}</td><td>{r['n_dropped']}</td>"
                   + "".join(f"<td>{r['by_reason'].get(k, 0)}</td>" for k in kinds) + "</tr>" for r in ims)
    total = "".join(f"<td><b>{dr['by_reason'][k]}</b></td>" for k in kinds)
    return (f"<h3>Named dots left unnamed by MEASURE ({dr.get('n_dropped', 0)})</h3><table id=dropped><tr>"
            f"<th>image</th><th>station</th><th>dropped</th>{head}</tr>{rows}<tr><td class=l><b>all</b></td><td></td>"
            f"<td><b>{dr.get('n_dropped', 0)}</b></td>{total}</tr></table>")


def _requirement_html(doc: dict) -> str:
    """The precision the job asked for and how many targets the measurement brought within it (decision 0070)."""
    pr = doc.get("precision_requirement")
    if not pr:
        return ""
    req = pr.get("required_sigma_m")
    short = pr.get("short") or []
    return (f'<p id="precision-requirement"><b>Precision requirement</b>: required sigma '
            f"{_fmt_um(req) + ' um' if req else 'per target'} ({html.escape(pr['source'])}"
            f"{'' if pr.get('closed_loop') else '; closed loop off'}): {pr['n_met']} of {pr['n_judged']} target(s) "
            "within it" + (f"; {len(short)} measured less precisely than required: "
                          + html.escape(", ".join(short[:12]) + (" ..." if len(short) > 12 else "")) if short else "")
            + (f"; {len(pr.get('not_measured') or [])} not measured" if pr.get("not_measured") else "") + ".</p>")


def _closed_loop_html(doc: dict) -> str:
    """The closed loop's rounds and the targets that still miss their requirement (with why)."""
    cl = doc.get("closed_loop")
    if not cl:
        return ""
    req = cl.get("required_sigma_m")
    rows = "".join(
        f"<tr><td>{r['round']}</td><td class=l>{html.escape(r['status'])}</td><td>{len(r['targets_short'])}</td>"
        f"<td class=l>{html.escape(', '.join(r['stations_added']))}</td><td>{len(r['targets_fixed'])}</td>"
        f"<td>{_num(r.get('time_s'), 1, 1)}</td></tr>"
        for r in cl["rounds"])
    unmet = "".join(f'<tr class="fail"><td class=l>{html.escape(u["id"])}</td><td class=l>{html.escape(u["reason"])}</td></tr>'
                    for u in cl["unmet"])
    head = ("every target within its requirement" if not cl["unmet"] else
            f"{len(cl['unmet'])} target(s) still miss their requirement")
    return (f"<h2>Closed loop</h2><p id=closed-loop>Required sigma {_fmt_um(req) + ' um' if req else 'per target'}: "
            f"{html.escape(head)}.</p>"
            "<table class=kv><tr><th>round</th><th>status</th><th>short</th><th>stations added</th><th>fixed</th>"
            f"<th>time [s]</th></tr>{rows}</table>"
            + (f"<table class=kv><tr><th>target</th><th>why it still misses</th></tr>{unmet}</table>" if unmet else ""))


#: the HTML table lists at most this many targets besides those that fail or are undecided (all are in report.json)
TABLE_ROWS = 1000
#: the ellipsoid figure draws at most this many (the least precise); the others would hide the part
FIGURE_ELLIPSOIDS = 400


def render_html(doc: dict, figures: dict[str, str], interactive: str = "") -> str:
    """The self-contained HTML report (``interactive``: the 3-D section of :mod:`cell.record.figures3d`)."""
    j = doc["job"]
    verdict = doc["verdict"]
    rows = []
    ordered = sorted(doc["targets"], key=lambda t: (t["pass"], -(t["deviation_norm_m"] or 0)))
    # every target that fails, is undecided or was not measured is listed; the others up to TABLE_ROWS in all
    listed = [t for i, t in enumerate(ordered)
              if i < TABLE_ROWS or not t["pass"] or t.get("decision") == "inconclusive" or t["measured"][0] is None]
    more = len(ordered) - len(listed)
    req_col = doc.get("precision_requirement") is not None
    for t in listed:
        cls = "" if t["pass"] else ' class="fail"'
        req = (f"<td>{_fmt_um(t.get('required_sigma_m'))}{'' if t.get('required_met') else ' short'}</td>"
               if req_col else "")
        rows.append(
            f"<tr{cls}><td class=l>{html.escape(t['id'])}</td>"
            + "".join(f"<td>{_num(v, 1000, 4)}</td>" for v in t["measured"])
            + "".join(f"<td>{_num(v, 1e6, 1)}</td>" for v in t["deviation"])
            + f"<td>{_fmt_um(t['deviation_norm_m'])}</td><td>{_fmt_um(t['tolerance_m'])}</td>"
            f"<td>{_fmt_um(t.get('uncertainty_U_m'))}</td>"
            f"<td>{_fmt_um(t['achieved_sigma_m'])}</td>{req}<td>{_fmt_um(t['predicted_sigma_m'])}</td>"
            f"<td>{t['n_images']}</td><td class=l>{_status(t)}</td></tr>"
        )
    stages = "".join(f"<tr><td class=l>{html.escape(k)}</td><td>{v:.2f}</td></tr>" for k, v in doc["stage_times_s"].items())
    figs = "".join(f'<img alt="{html.escape(k)}" src="data:image/png;base64,{v}">' for k, v in figures.items())
    facts = {
        "Job": j["id"], "Part": j.get("part", ""),
        "Part number / revision": " / ".join(str(v) for v in ((doc.get("part") or {}).get("number"),
                                                              (doc.get("part") or {}).get("revision")) if v) or "\u2014",
        "Serial number": (doc.get("part") or {}).get("serial") or "\u2014",
        "Operator": doc.get("operator") or "\u2014", "Cell": doc.get("cell_id") or "\u2014",
        "Seed": j["seed"], "Started": j["started"],
        "Finished": j["finished"], "Images": doc["images"], "sigma0 [px]": f"{doc['sigma0_px']:.3f}",
        "Datum": doc.get("datum", ""), "Cell calibration": doc.get("cell_calibration", {}).get("status", "unknown"),
        "Measured with": doc.get("cell_calibration", {}).get("measured_with", "\u2014"),
        **_alignment_facts(doc), **_measure_facts(doc), **_budget_facts(doc),
        "Versions": ", ".join(f"{k} {v}" for k, v in j["versions"].items()),
    }
    kv = "".join(f"<tr><td><b>{html.escape(k)}</b></td><td>{html.escape(str(v))}</td></tr>" for k, v in facts.items())
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>Inspection report {html.escape(j['id'])}</title>
<style>{_CSS}</style></head><body>
<h1>Inspection report: {html.escape(j['name'])}</h1>
<div class="verdict {verdict}" id="verdict">{verdict}: {_headline(doc)}{_inconclusive(doc)}</div>
{_verdict_reasons(doc)}{_requirement_html(doc)}{_alerts(doc)}
<h2>Job</h2><table class="kv">{kv}</table>
<h2>Figures</h2><div class="figs">{figs}</div>
{_rejected_table(doc)}{_dropped_table(doc)}
<h2>Targets</h2>
<table id="targets"><tr><th>id</th><th>measured x [mm]</th><th>measured y [mm]</th><th>measured z [mm]</th>
<th>dx [um]</th><th>dy [um]</th><th>dz [um]</th><th>|d| [um]</th><th>tol [um]</th><th>U (k=2) [um]</th>
<th>sigma [um]</th>{'<th>required sigma [um]</th>' if req_col else ''}<th>predicted [um]</th><th>images</th><th></th></tr>
{''.join(rows)}</table>
{f'<p id="more-targets">{more} more targets within tolerance (smaller deviations) are not listed here: report.json has every target.</p>' if more else ''}
{_closed_loop_html(doc)}<h2>Time per stage</h2><table class="kv">{stages}</table>
{interactive}
</body></html>
"""
