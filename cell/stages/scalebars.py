"""ADJUST's scale bars: which the adjustment uses, which it leaves out and why, and the test of their certificates.

A job may carry several certified bars (``[job] scale_bars``, decision 0041). Every bar whose ends the network
measures enters the adjustment; a bar is left out, said in the journal, the console and bundle.json
(``screening.scale_bars``, ``scale_bars``), when

- an end is unlike its ellipse in most images that found it (:func:`cell.stages.adjust.shape_doubtful`: the views
  kept share the cause),
- the screening or data snooping leaves an end fewer than two rays,
- with three bars or more, its certificate fails the test against the others
  (:func:`calibration.bundle.bartest.bar_residual_test`) and it is the worst failing one: the job is adjusted again
  without it.

The scale is established while one bar is left. With two bars whose certificates disagree the job faults ("scale
bars disagree"): the test cannot tell which is wrong. With one bar the certificate is not tested (said).
"""
from __future__ import annotations

import numpy as np

from calibration.bundle.bartest import ALPHA, BarTest

__all__ = ["bar_name", "bars_doc", "protected_entries", "say_bars", "shape_reason", "snooping_reason",
           "test_reason"]


def bar_name(job, j: int) -> str:
    """``"T0012-T0150"``: the ends of bar ``j`` of ``job.scale_bars``."""
    ids = job.part.targets.ids
    a, b = job.scale_bars[j][:2]
    return f"{ids[a]}-{ids[b]}"


def end_reason(job, j: int, doubtful: dict, why, sep: str = ", ", tail: str = "") -> str | None:
    """Why bar ``j`` is left out when an end is in ``doubtful`` ({target index: ...}; ``why(target)`` says of one),
    or None."""
    bad = [t for t in job.scale_bars[j][:2] if t in doubtful]
    if not bad:
        return None
    return f"scale bar {bar_name(job, j)}: " + sep.join(why(t) for t in bad) + tail


def shape_reason(job, j: int, doubtful: dict) -> str | None:
    """Why bar ``j`` is left out when an end is unlike its ellipse in most images that found it (None: it is not)."""
    ids = job.part.targets.ids
    return end_reason(job, j, doubtful, lambda t: (
        f"{ids[int(t)]} unlike its ellipse in {doubtful[t][0]} of the {sum(doubtful[t])} images that found it "
        "(cut or crowded by an edge, clipped or washed out): the views kept cannot be trusted either"))


def snooping_reason(job, j: int, ends: dict[int, int], rejected_images: list[str]) -> str:
    """Why bar ``j`` is left out when data snooping took an end below two rays (``ends``: {end: rays kept})."""
    ids = job.part.targets.ids
    mine = {t: k for t, k in ends.items() if t in job.scale_bars[j][:2]}
    return (f"scale bar {bar_name(job, j)}: " + ", ".join(f"{ids[int(t)]} usable in {k} image(s)"
                                                          for t, k in mine.items())
            + " (2 needed)" + (f" after data snooping rejected its observation(s) in {', '.join(rejected_images)}"
                               if rejected_images else ""))


def test_reason(job, j: int, test: BarTest, k: int) -> str:
    """Why bar ``j`` (``k``-th of the bars tested) was left out by the test of the certificates."""
    return (f"scale bar {bar_name(job, j)}: its certificate disagrees with the other bars: adjusted length minus "
            f"certificate {test.residual_m[k] * 1e6:+.1f} um, {test.w[k]:+.1f} sigma (|w| > {test.critical:.2f}, "
            f"alpha {ALPHA:g} over {len(test.w)} bars)")


def bars_doc(job, use: list[int], left: dict[int, str], test: BarTest | None) -> list[dict]:
    """bundle.json ``scale_bars``: per bar of the job, its certificate, whether the adjustment used it or why not,
    and the test (with two bars or more: the adjusted length, the residual, its sigma, the normalised residual,
    ``test`` "pass" / "fail"; with one: "not tested: one bar"); ``gain_column``: the bar's column of the gains
    ``K`` (bundle_covariance.npz) and of report.json's ``scale_bar_gains`` (None: not used). ``certificate_m`` is the
    length the adjustment took: a bar of its own material under ``[thermal]`` at the bars' temperature in units of
    the part at 20 C, its certificate then in ``certified_at_20C_m`` (decision 0053)."""
    ids = job.part.targets.ids
    out = []
    for j, (a, b, length, sigma) in enumerate(job.scale_bars):
        d = {"bar": [ids[a], ids[b]], "certificate_m": length, "certificate_sigma_m": sigma, "used": j in use,
             "left_out": left.get(j),
             # the bar's column in bundle_covariance.npz K and report.json's targets' scale_bar_gains
             "gain_column": use.index(j) if j in use else None}
        spec_bars = job.spec.job.bars()
        bar = spec_bars[j][1] if j < len(spec_bars) else None
        if job.spec.thermal is not None and bar is not None and bar.cte_ppm_per_K is not None:  # decision 0053
            d.update(certified_at_20C_m=bar.length * job.spec.scale, cte_ppm_per_K=bar.cte_ppm_per_K)
        if j in use and test is not None:
            k = use.index(j)
            tested = bool(np.isfinite(test.sigma_m[k]))
            d.update(adjusted_length_m=float(test.length_m[k]), residual_m=float(test.residual_m[k]),
                     residual_sigma_m=float(test.sigma_m[k]) if tested else None,
                     normalised_residual=float(test.w[k]) if tested else None,
                     certificate_weight=float(test.h[k]),
                     test=("pass" if not test.failed[k] else "fail") if tested
                     else ("not tested: one bar: its certificate is not tested" if len(use) == 1
                           else "not tested: the residual has no variance"),
                     critical=test.critical if tested else None)
        out.append(d)
    return out


def protected_entries(job, use: list[int], snoop_protected: list[str]) -> list[str]:
    """bundle.json ``snooping.protected``: each bar used, by its ends' names, and what tests its certificate; the
    other entries of the bundle (control) as they are."""
    rest = [p for p in snoop_protected if not p.startswith("scale bar ")]
    if len(use) == 1:
        bars = [f"scale bar {bar_name(job, use[0])} length (not tested: it defines the scale; one bar: its "
                "certificate is not tested)"]
    else:
        bars = [f"scale bar {bar_name(job, j)} length (not tested by data snooping: the bars define the scale; "
                f"its certificate is tested against the other {len(use) - 1} bars, bundle.json scale_bars)"
                for j in use]
    return bars + rest


def say_bars(ctx, doc: list[dict]) -> None:
    """The console and the journal: with several bars, each bar's test or why it was left out."""
    if len(doc) < 2:
        return
    for d in doc:
        name = "-".join(d["bar"])
        if not d["used"]:
            msg = f"{d['left_out']}; left out of the adjustment"
            ctx.log.log("warning", msg)
            ctx.say(f"  WARNING {msg}")
        elif d.get("normalised_residual") is not None:
            msg = (f"scale bar {name}: certificate {d['certificate_m'] * 1e3:.4f} mm, adjusted "
                   f"{d['adjusted_length_m'] * 1e3:.4f} mm, residual {d['residual_m'] * 1e6:+.1f} um (sigma "
                   f"{d['residual_sigma_m'] * 1e6:.1f} um, {d['normalised_residual']:+.2f} sigma): {d['test']}")
            ctx.log.log("info", msg)
            ctx.say(f"  {msg}")
        else:  # used, but its residual has no variance to test it by: said, not passed over
            msg = f"scale bar {name}: used; {d.get('test') or 'not tested'}"
            ctx.log.log("warning", msg)
            ctx.say(f"  WARNING {msg}")
    ctx.folder.append("scale_bars", bars=[{"bar": d["bar"], "used": d["used"], "left_out": d["left_out"],
                                           "test": d.get("test"), "normalised_residual": d.get("normalised_residual")}
                                          for d in doc])
