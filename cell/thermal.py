"""The measurement's temperature (decision 0053): coordinates at the ISO 1 reference of 20 C, and a part whose size is
not its CAD's said.

A part expands uniformly with its temperature: by ``s_p = alpha_p (T_p - 20 C)``, 138 ppm for aluminium 6 K warm,
69 um over 500 mm against a stated sigma of a few um. The cell's scale comes from its scale bars, so what matters is
the bars against the part:

- a bar whose ends sit on the part (no ``cte_ppm_per_K``: the default) expands with it; its certificate is a
  distance of the part at 20 C, and the coordinates are the part's at 20 C whatever its (uniform) temperature;
- a bar of its own material (carbon fibre, invar, steel) at ``bars_C`` is ``L (1 + s_b)`` long. The adjustment
  takes it as ``L (1 + s_b) / (1 + s_p)``: its length in units of the part at 20 C. The coordinates then are the
  part's at 20 C.

LOAD gives the adjustment those lengths (:func:`bar_at_measurement`), with each bar's own expansion coefficient's
uncertainty in its sigma (independent per bar). The part's temperature and expansion coefficient, and the bars'
temperature, are shared by every bar: REPORT adds them to the covariance as two shared columns through the bars'
gains (:func:`shared_columns`), so each target's ellipsoid and the joint covariance carry them.

Whether or not ``[thermal]`` is given, REPORT estimates the part's scale against CAD over the targets that agree with
it (:func:`part_scale`, invariant to the alignment's rigid motion). A significant one is said, with the temperature it
would take (:func:`scale_note`): without ``[thermal]`` a warm part with carbon bars was reported 138 ppm large at full
precision, with nothing said. The simulated cell expands its part and its bars by ``[sim] part_C`` / ``bars_C``
(:func:`sim_expansion`)."""
from __future__ import annotations

import numpy as np

from calibration.alignment import PointCovariance
from calibration.errors import CalibrationError, DriverError

__all__ = ["REFERENCE_C", "SCALE_Z", "agreeing", "bar_at_measurement", "cte_sigma", "own_bar_ends", "read_probe", "resolve_probe", "sim_part_C", "part_scale", "scale_note", "shared_columns",
           "sim_expansion", "thermal_doc"]

#: ISO 1: the reference temperature of geometrical product specification, deg C.
REFERENCE_C = 20.0
#: a part scale beyond this many of its sigmas is said (two-sided 0.1 %): a real scale should not hide, and an honest
#: statement of an exact part says it once in a thousand runs.
SCALE_Z = 3.29
#: the expansion coefficients of common part materials the note converts a scale to a temperature with, ppm/K.
MATERIALS = (("aluminium", 23.1), ("steel", 11.5))


def cte_sigma(cte: float, given: float | None) -> float:
    """The standard uncertainty of an expansion coefficient, ppm/K: as given, else 10 % of it, at least 0.1."""
    return float(given) if given is not None else max(0.1 * abs(cte), 0.1)


def sim_part_C(spec) -> float:
    """The simulated part's true temperature: ``[sim] part_C``, else what ``[thermal]`` states, else 20 C."""
    th = spec.thermal
    if spec.sim.part_C is not None:
        return spec.sim.part_C
    return th.part_C if th is not None and th.part_C != "probe" else REFERENCE_C


def _bars_C(th) -> float:
    return th.part_C if th.bars_C is None else th.bars_C


def part_expansion(th) -> tuple[float, float]:
    """``(s_p, sigma)``: the part's expansion from 20 C (relative) and its standard uncertainty from the temperature's
    and the coefficient's."""
    dt = th.part_C - REFERENCE_C
    cs = cte_sigma(th.part_cte_ppm_per_K, th.part_cte_sigma_ppm_per_K)
    return th.part_cte_ppm_per_K * 1e-6 * dt, 1e-6 * float(np.hypot(th.part_cte_ppm_per_K * th.part_sigma_K, dt * cs))


def bar_at_measurement(spec, bar, length_m: float, sigma_m: float) -> tuple[float, float]:
    """A scale bar's length for the adjustment, in units of the part at 20 C, and its own sigma (m).

    A bar on the part (no ``cte_ppm_per_K``), or a job without ``[thermal]``: the certificate as it is. A bar of its
    own material: ``L (1 + s_b) / (1 + s_p)``, and its coefficient's uncertainty ``L |T_b - 20| sigma_cte`` added to
    the certificate's in quadrature (the shared temperatures are REPORT's: :func:`shared_columns`)."""
    th = spec.thermal
    if th is None or bar.cte_ppm_per_K is None or th.part_C == "probe":  # a probe's reading: at ADJUST (resolve_probe)
        return length_m, sigma_m
    dt = _bars_C(th) - REFERENCE_C
    s_b = bar.cte_ppm_per_K * 1e-6 * dt
    s_p, _ = part_expansion(th)
    own = length_m * abs(dt) * 1e-6 * cte_sigma(bar.cte_ppm_per_K, bar.cte_sigma_ppm_per_K)
    return length_m * (1.0 + s_b) / (1.0 + s_p), float(np.hypot(sigma_m, own))


def shared_columns(spec, K: np.ndarray, bars_doc: list[dict]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The shared thermal uncertainties as columns of the covariance's low-rank factor: ``(cols (n, 3, r), weights
    (r,), names)``; r = 0 without ``[thermal]`` or without a used bar of its own material.

    ``K: (n, 3, b)`` the used bars' gains (m of each point per m of each certificate's error; bundle.json
    ``scale_bars[].gain_column``). An error ``d`` in the part's expansion moves every own-material bar's length by
    ``-L d``, so the points by ``-sum_j K_j L_j d`` (variance ``sigma_sp^2``); an error ``dT`` in the bars'
    temperature by ``sum_j K_j L_j alpha_j dT`` (variance ``bars_sigma_K^2``)."""
    th = spec.thermal
    n = K.shape[0]
    bars = [bar for _, bar in spec.job.bars()]
    if th is None:
        return np.zeros((n, 3, 0)), np.zeros(0), []
    part = np.zeros((n, 3))
    temp = np.zeros((n, 3))
    used = False
    for bar, d in zip(bars, bars_doc):
        c = d.get("gain_column")
        if c is None or bar.cte_ppm_per_K is None:
            continue
        used = True
        k = np.nan_to_num(K[:, :, c]) * d["certificate_m"]
        part -= k
        temp += k * bar.cte_ppm_per_K * 1e-6
    if not used:
        return np.zeros((n, 3, 0)), np.zeros(0), []
    _, sp = part_expansion(th)
    return np.stack([part, temp], axis=2), np.array([sp ** 2, th.bars_sigma_K ** 2]), ["part_expansion",
                                                                                       "bars_temperature"]


def own_bar_ends(job) -> np.ndarray:
    """(n,) bool: the ends of the job's scale bars of their own material (``cte_ppm_per_K`` given). They are the bar's,
    not the part's: a warm part moves under them by the difference of the expansions (23-32 um on the example 6 K
    warm with a carbon bar), so they neither define the frame nor are judged against the part's tolerance."""
    out = np.zeros(len(job.part.targets.ids), dtype=bool)
    for (_, bar), (a, b, *_) in zip(job.spec.job.bars(), job.scale_bars):
        if bar.cte_ppm_per_K is not None:
            out[[a, b]] = True
    return out


def sim_expansion(spec, xyz: np.ndarray, bar_ends: list[tuple[int, int]]) -> np.ndarray:
    """(n, 3) m: how far the simulated part's targets ``xyz`` (their 20 C places, part frame) move with the true
    temperatures (``[sim] part_C``, ``bars_C``): about the part's origin, and a bar of its own material's ends about
    its middle. Zeros at 20 C. ``bar_ends``: ``(a, b)`` per bar of ``spec.job.bars()``."""
    s, th = spec.sim, spec.thermal
    part_C = sim_part_C(spec)
    cte = s.part_cte_ppm_per_K if s.part_cte_ppm_per_K is not None else (th.part_cte_ppm_per_K if th else 0.0)
    bars_C = s.bars_C if s.bars_C is not None else (th.bars_C if th is not None and th.bars_C is not None else part_C)
    xyz = np.asarray(xyz, dtype=float)
    out = cte * 1e-6 * (part_C - REFERENCE_C) * xyz
    for (_, bar), (a, b) in zip(spec.job.bars(), bar_ends):
        if bar.cte_ppm_per_K is None:
            continue
        mid = 0.5 * (xyz[a] + xyz[b])
        for e in (a, b):
            out[e] = bar.cte_ppm_per_K * 1e-6 * (bars_C - REFERENCE_C) * (xyz[e] - mid)
    return out


def agreeing(deviation: np.ndarray, nominal: np.ndarray, blocks: np.ndarray, use: np.ndarray, k: float,
             start: np.ndarray | None = None) -> np.ndarray:
    """The targets of ``use`` that agree with one similarity of the part (scale, rotation, translation of the
    deviated nominals onto the nominals): from ``start`` (the alignment's own targets, when six or more of them are in
    ``use``; else all of ``use``), up to five rounds of the best similarity over those kept, keeping every target of
    ``use`` whose residual is within ``max(k, 3 x the median)`` sigma in its block. The median's bound keeps a first
    fit that local deviations pulled (a part with 40 of 132 targets deviating within tolerance: residuals of 17 sigma
    median) from leaving out every target at once; it falls to ``k`` as the fit comes clean."""
    from calibration.alignment import deviation_sigma_level, similarity_fit

    use = np.asarray(use, dtype=bool) & np.all(np.isfinite(deviation), axis=1)
    keep = use.copy()
    if start is not None and (np.asarray(start, dtype=bool) & use).sum() >= 6:
        keep = np.asarray(start, dtype=bool) & use
    for _ in range(5):
        if keep.sum() < 6:
            break
        s, R, t = similarity_fit(nominal[keep] + deviation[keep], nominal[keep], with_scale=True)
        level = deviation_sigma_level(np.where(use[:, None], s * (nominal + deviation) @ R.T + t - nominal, np.nan),
                                      blocks)
        new = use & ~(level > max(k, 3 * float(np.nanmedian(level[keep]))))
        if np.array_equal(new, keep):
            break
        keep = new
    return keep


#: readings averaged at each end of ACQUIRE (the readout's own noise is ~0.01 K; five average a loose contact's flicker)
PROBE_READINGS = 5
PROBE_AGREE_MIN = 3  # fewer readings of a block that agree: the probe is not read, the job faults
PROBE_BAND_SIGMAS = 3.0  # a reading farther than this many part_sigma_K from its block's median is an outlier ...
PROBE_BAND_MIN_K = 0.1  # ... or than this, whichever is larger (a small part_sigma_K against the readout's noise)


def agreeing_readings(values, sigma_K: float) -> tuple[float, float, list[float], list[float], float]:
    """The readings of one probe block that agree: those within ``max(PROBE_BAND_SIGMAS x sigma_K, PROBE_BAND_MIN_K)``
    of their median. Returns ``(mean of them, their sample standard deviation, them, the others, the band)``; one
    glitch (-200 C sensor-open, a 0.000 dropout) does not move the median, so it is left out, not averaged in."""
    vals = [float(v) for v in values]
    med = float(np.median(vals))
    band = max(PROBE_BAND_SIGMAS * float(sigma_K), PROBE_BAND_MIN_K)
    kept = [v for v in vals if abs(v - med) <= band]
    out = [v for v in vals if abs(v - med) > band]
    mean = float(np.mean(kept)) if kept else med
    sd = float(np.std(kept, ddof=1)) if len(kept) > 1 else 0.0
    return mean, sd, kept, out, band


def read_probe(ctx, thermometer, when: str) -> None:
    """ACQUIRE: the part's thermometer read (``[thermal] part_C = "probe"``) at the ``"start"`` or the ``"end"``,
    journalled (``part_temperature``) and logged. A resumed job keeps the start it read. At the end, a change beyond
    ``part_sigma_K`` since the start is said: the part was not soaked (:func:`resolve_probe` takes it into the
    sigma). A probe that does not answer faults the job (the job asked for it): resume reads it again.

    ``PROBE_READINGS`` readings; those beyond the band of :func:`agreeing_readings` from their median are named as
    outliers and left out (console, run log, journal ``outliers``); fewer than ``PROBE_AGREE_MIN`` that agree fault
    ACQUIRE. The scatter of those kept is journalled (``sd_K``), said beyond ``part_sigma_K``, and carried into the
    sigma by :func:`resolve_probe`."""
    th = ctx.job.spec.thermal
    if th is None or th.part_C != "probe":
        return
    recs = [r for r in ctx.folder.records() if r["event"] == "part_temperature"]
    if when == "start" and any(r["when"] == "start" for r in recs):
        return
    if thermometer is None:
        raise DriverError("[thermal] part_C = \"probe\" but the cell has no thermometer ([cell] thermometer_port)")
    values = [float(v) for v in thermometer.read_n_C(PROBE_READINGS)]
    mean, sd, kept, out, band = agreeing_readings(values, th.part_sigma_K)
    shown = ", ".join(f"{v:.3f}" for v in values)
    if len(kept) < PROBE_AGREE_MIN:
        raise DriverError(f"the part's thermometer ({thermometer.name}) gave {PROBE_READINGS} readings at the {when} "
                          f"of ACQUIRE that do not agree: only {len(kept)} within {band:.2f} K of their median "
                          f"{float(np.median(values)):.3f} C ({shown} C); check the probe's contact and cable")
    if not -30.0 <= mean <= 90.0:  # the job's own range for part_C: a probe off the part, or a wrong channel
        raise DriverError(f"the part's thermometer ({thermometer.name}) reads {mean:.2f} C at the {when} of ACQUIRE: "
                          "no part in a measuring cell is at that (-30..90 C); check that the probe is on the part")
    if out:
        msg = (f"the part's thermometer gave {len(out)} of {PROBE_READINGS} readings at the {when} of ACQUIRE beyond "
               f"{band:.2f} K of the others' median ({', '.join(f'{v:.3f}' for v in out)} C among {shown} C): left "
               f"out as outliers, the temperature is the mean of the {len(kept)} that agree; check the probe's "
               "contact and cable")
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")
    if sd > th.part_sigma_K:  # a loose contact flickers: the mean is taken, its scatter said and in the sigma
        msg = (f"the part's thermometer scattered by {sd:.2f} K over {len(kept)} readings at the {when} of ACQUIRE "
               f"(more than part_sigma_K = {th.part_sigma_K} K): check the probe's contact; the scatter is in the "
               "temperature's sigma")
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")
    ctx.folder.append("part_temperature", when=when, C=mean, sd_K=sd, n=len(kept), device=thermometer.name,
                      readings=values, outliers=out)
    ctx.log.log("info", f"part temperature at the {when} of ACQUIRE: {mean:.3f} C ({thermometer.name})")
    ctx.say(f"  part temperature ({when}): {mean:.2f} C")
    start = next((r["C"] for r in recs if r["when"] == "start"), None)
    if when == "end" and start is not None and abs(mean - start) > th.part_sigma_K:
        msg = (f"the part's temperature changed by {mean - start:+.2f} K during ACQUIRE ({start:.2f} C at the start, "
               f"{mean:.2f} C at the end): it was not soaked; its expansion is taken at the mean, the change in its "
               "sigma")
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")


def resolve_probe(job, journal):
    """The job with ``[thermal] part_C = "probe"`` replaced by the readings ACQUIRE journalled: the mean of the start
    and the end, its sigma ``sqrt(part_sigma_K^2 + change^2 / 12 + scatter^2)`` (a steady drift between them; the
    larger standard deviation of the readings kept at the start or the end, ``sd_K``), and the bars of
    their own material at that temperature. Unchanged without a probe (the journal is not read). ``journal``: the job
    folder (its ``records()``) or the records. ``CalibrationError`` when ACQUIRE read none."""
    from dataclasses import replace

    th = job.spec.thermal
    if th is None or th.part_C != "probe":
        return job
    records = journal.records() if hasattr(journal, "records") else journal
    reads = [r for r in records if r["event"] == "part_temperature"]
    start = next((r for r in reads if r["when"] == "start"), None)
    end = next((r for r in reversed(reads) if r["when"] == "end"), None)
    if start is None:
        raise CalibrationError("[thermal] part_C = \"probe\": the journal has no reading of the part's thermometer "
                               "(ACQUIRE reads it first); give part_C in deg C to adjust without it")
    vals = [start["C"]] + ([end["C"]] if end is not None else [])
    change = vals[-1] - vals[0]
    scatter = max(float(r.get("sd_K") or 0.0) for r in (start, end) if r is not None)
    sigma = float(np.sqrt(th.part_sigma_K ** 2 + change ** 2 / 12 + scatter ** 2))
    spec = job.spec.model_copy(update={"thermal": th.model_copy(update={"part_C": float(np.mean(vals)),
                                                                        "part_sigma_K": sigma})})
    k = spec.scale
    bars = tuple((a, b, *bar_at_measurement(spec, bar, bar.length * k, bar.sigma * k))
                 for (_, bar), (a, b, *_) in zip(spec.job.bars(), job.scale_bars))
    return replace(job, spec=spec, scale_bars=bars, probe={"start_C": vals[0], "end_C": vals[-1] if end else None,
                                                           "device": start.get("device"), "change_K": change,
                                                           "scatter_K": scatter})


def part_scale(deviation: np.ndarray, nominal: np.ndarray, cov: PointCovariance, use: np.ndarray) -> dict | None:
    """The part's scale against CAD from its aligned deviations over the targets ``use``, and its stated sigma.

    ``s = sum_i g_i . d_i`` with ``g_i = (x_i - c) / sum_j |x_j - c|^2`` (``x`` the nominals, ``c`` their centroid):
    the least-squares scale of ``d = s (x - c)``. ``g`` is orthogonal to every small rigid motion, so the alignment's
    own placement does not enter. Its variance is ``g^T Sigma g`` from the deviations' joint covariance (blocks and
    shared part: the poses, the bars' certificates, the alignment). None with fewer than six targets."""
    idx = np.flatnonzero(np.asarray(use, dtype=bool) & np.all(np.isfinite(deviation), axis=1))
    if len(idx) < 6:
        return None
    x = nominal[idx] - nominal[idx].mean(axis=0)
    g = x / np.sum(x * x)
    s = float(np.sum(g * deviation[idx]))
    D, U = np.nan_to_num(cov.D[idx]), np.nan_to_num(cov.U[idx])
    Ug = np.einsum("nar,na->r", U, g)
    var = float(np.einsum("na,nab,nb->", g, D, g) + Ug @ cov.C @ Ug)
    sigma = float(np.sqrt(max(var, 0.0)))
    z = s / sigma if sigma > 0 else float("inf")
    return {"scale_ppm": s * 1e6, "sigma_ppm": sigma * 1e6, "z": z, "targets": int(len(idx)),
            "extent_m": float(2 * np.sqrt(np.max(np.sum(x * x, axis=1)))), "significant": bool(abs(z) > SCALE_Z)}


def scale_note(spec, scale: dict | None, applied_ppm: float | None) -> str | None:
    """What a significant part scale means, in a line the engineer can act on (None: not significant)."""
    if scale is None or not scale["significant"]:
        return None
    ppm, z = scale["scale_ppm"], scale["z"]
    size = (f"the part measures {ppm:+.0f} ppm ({z:+.1f} sigma, {ppm * 1e-6 * scale['extent_m'] * 1e6:+.0f} um over "
            f"its {scale['extent_m'] * 1e3:.0f} mm) {'larger' if ppm > 0 else 'smaller'} than its CAD over the "
            f"{scale['targets']} targets that agree with it")
    own = any(bar.cte_ppm_per_K is not None for _, bar in spec.job.bars())
    if applied_ppm is not None:
        return (f"{size}, after the correction to 20 C ({-applied_ppm:+.0f} ppm from [thermal]): check [thermal] "
                "part_C, part_cte_ppm_per_K and the bars' cte_ppm_per_K, or the part is out of scale")
    if not own:
        return (f"{size}: the scale bars sit on the part (no cte_ppm_per_K) and expand with it, so a uniform "
                "temperature does not explain it; the part is out of scale, a bar's certificate is off, or one of its "
                "ends moved")
    temps = ", ".join(f"{ppm / c:+.1f} K from 20 C if {m} ({c} ppm/K)" for m, c in MATERIALS)
    return (f"{size}: {temps}. The deviations are at the measurement's temperature, not at 20 C: give [thermal] "
            "part_C and part_cte_ppm_per_K to report the part at 20 C, or the part is out of scale")


def thermal_doc(spec, bars_doc: list[dict], scale: dict | None, probe: dict | None = None) -> dict:
    """report.json ``thermal``: the temperatures the job gave, what the correction to 20 C did to each bar, the part's
    scale against CAD and, when significant, the note (:func:`scale_note`)."""
    th = spec.thermal
    doc: dict = {"reference_C": REFERENCE_C, "stated_in_job": th is not None, "part_scale": scale, "probe": probe}
    if scale is None:  # said, not left blank: a part out of scale would pass unseen
        doc["part_scale_not_estimated"] = ("fewer than six measured targets within tolerance agree with one "
                                           "similarity of the part: its scale against CAD is not checked")
    applied = None
    if th is not None:
        s_p, sp = part_expansion(th)
        own = [(key, bar) for key, bar in spec.job.bars() if bar.cte_ppm_per_K is not None]
        applied = s_p * 1e6 if own else None  # bars on the part: nothing to correct, a scale is the part's
        doc.update(part_C=th.part_C, part_sigma_K=th.part_sigma_K, part_cte_ppm_per_K=th.part_cte_ppm_per_K,
                   part_cte_sigma_ppm_per_K=cte_sigma(th.part_cte_ppm_per_K, th.part_cte_sigma_ppm_per_K),
                   bars_C=_bars_C(th), bars_sigma_K=th.bars_sigma_K, part_expansion_ppm=s_p * 1e6,
                   part_expansion_sigma_ppm=sp * 1e6,
                   bars=[{"bar": d["bar"], "cte_ppm_per_K": bar.cte_ppm_per_K, "length_at_measurement_m":
                          d["certificate_m"]} for (_, bar), d in zip(spec.job.bars(), bars_doc)],
                   correction=("coordinates are of the part at 20 C: the bars of their own material enter the "
                               "adjustment at their length at bars_C in units of the part at 20 C" if own else
                               "none needed: every scale bar sits on the part and expands with it; the coordinates "
                               "are of the part at 20 C if its temperature is uniform"))
    else:
        doc["correction"] = ("none: the job gives no [thermal]; coordinates and deviations are at the part's "
                             "temperature during the measurement")
    note = scale_note(spec, scale, applied)
    if note:
        doc["note"] = note
    return doc
