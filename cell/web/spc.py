"""Statistical process control for one characteristic over serial parts: pure functions.

Individuals and moving-range (I-MR) chart after Montgomery, *Introduction to Statistical Quality
Control*, ch. 6.4: sigma_within = MRbar / d2 (d2 = 1.128 for n = 2), X limits center +- 3 sigma_within,
MR upper limit D4 MRbar (D4 = 3.267). Capability Cp = (USL - LSL) / 6 sigma, Cpk = min(USL - mu,
mu - LSL) / 3 sigma with sigma_within; their confidence intervals: Cp by the chi-square interval,
Cpk by Bissell's normal approximation (1990). Out-of-control rules: Western Electric 1-4 and
Nelson 3 (a trend of six). Few points make wide intervals; the result says so.
"""
from __future__ import annotations

import numpy as np
from scipy import stats

D2, D4 = 1.128, 3.267

RULES = {
    "WE1": "one point beyond 3 sigma",
    "WE2": "2 of 3 points beyond 2 sigma on one side",
    "WE3": "4 of 5 points beyond 1 sigma on one side",
    "WE4": "8 points in a row on one side of the centre line",
    "N3": "6 points in a row steadily increasing or decreasing",
    "MR": "moving range beyond its upper limit",
}


def imr_limits(x: np.ndarray, baseline: int | None = None) -> dict:
    """Centre line, sigma_within and limits of the I and MR charts from ``x[:baseline]`` (all by default)."""
    x = np.asarray(x, dtype=float)
    base = x if baseline is None else x[:baseline]
    if len(base) < 2:
        raise ValueError("a control chart needs at least two points in its baseline")
    mr = np.abs(np.diff(base))
    mr_bar = float(mr.mean())
    center = float(base.mean())
    sigma = mr_bar / D2
    return {"center": center, "sigma_within": sigma, "ucl": center + 3 * sigma, "lcl": center - 3 * sigma,
            "mr_bar": mr_bar, "mr_ucl": D4 * mr_bar, "baseline": len(base)}


def violations(x: np.ndarray, center: float, sigma: float, mr_ucl: float | None = None) -> list[dict]:
    """Every rule broken, each as {rule, index (the point that completes it), text}."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    out: list[dict] = []
    if sigma <= 0 or not np.isfinite(sigma):
        return out
    z = (x - center) / sigma

    def add(rule, i):
        out.append({"rule": rule, "index": int(i), "text": RULES[rule]})

    for i in range(n):
        if abs(z[i]) > 3:
            add("WE1", i)
        for rule, m, k, lim in (("WE2", 3, 2, 2.0), ("WE3", 5, 4, 1.0)):
            if i >= m - 1:
                w = z[i - m + 1:i + 1]
                for side in (1, -1):
                    if (side * w > lim).sum() >= k and side * z[i] > lim:
                        add(rule, i)
        if i >= 7:
            w = z[i - 7:i + 1]
            if (w > 0).all() or (w < 0).all():
                add("WE4", i)
        if i >= 5:
            d = np.diff(x[i - 5:i + 1])
            if (d > 0).all() or (d < 0).all():
                add("N3", i)
    if mr_ucl is not None and n > 1:
        for i, m in enumerate(np.abs(np.diff(x)), start=1):
            if m > mr_ucl:
                add("MR", i)
    return out


def capability(mean: float, sigma: float, n: int, lsl: float | None, usl: float | None,
               confidence: float = 0.95) -> dict:
    """Cp and Cpk with their two-sided confidence intervals (None where a limit is missing)."""
    doc: dict = {"cp": None, "cp_ci": None, "cpk": None, "cpk_ci": None, "n": n, "confidence": confidence,
                 "note": ""}
    if n < 2 or not sigma > 0:
        doc["note"] = "not enough points (or no variation) to estimate capability"
        return doc
    a = 1 - confidence
    if lsl is not None and usl is not None:
        cp = (usl - lsl) / (6 * sigma)
        df = n - 1
        doc["cp"] = cp
        doc["cp_ci"] = [cp * np.sqrt(stats.chi2.ppf(a / 2, df) / df), cp * np.sqrt(stats.chi2.ppf(1 - a / 2, df) / df)]
    sides = [v for v in ((usl - mean) if usl is not None else None, (mean - lsl) if lsl is not None else None)
             if v is not None]
    if sides:
        cpk = min(sides) / (3 * sigma)
        zq = stats.norm.ppf(1 - a / 2)
        half = zq * np.sqrt(1 / (9 * n) + cpk ** 2 / (2 * (n - 1)))
        doc["cpk"] = cpk
        doc["cpk_ci"] = [cpk - half, cpk + half]
    if n < 25:
        doc["note"] = f"only {n} parts: the intervals are wide; 25 or more are usual for a capability study"
    return doc


def analyse(values: list[float], lsl: float | None, usl: float | None, baseline: int | None = None) -> dict:
    """The whole I-MR analysis of one characteristic: limits, moving ranges, rules broken, capability."""
    x = np.asarray(values, dtype=float)
    lim = imr_limits(x, baseline)
    viol = violations(x, lim["center"], lim["sigma_within"], lim["mr_ucl"])
    cap = capability(float(x.mean()), lim["sigma_within"], len(x), lsl, usl)
    if any(v["rule"] != "MR" for v in viol):
        cap["note"] = ("the chart shows the process out of control: Cp/Cpk describe a stable process only"
                       + ("; " + cap["note"] if cap["note"] else ""))
    return lim | {"moving_range": [None, *np.abs(np.diff(x)).tolist()], "violations": viol, "capability": cap,
                  "cp": cap["cp"], "cpk": cap["cpk"]}
