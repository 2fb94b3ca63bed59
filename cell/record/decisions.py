"""What a report.json target says of its part, as every export and the archive count it.

A target is *not measured* (no measured point), *beyond* its tolerance (measured, ``pass`` False),
*undecided* (measured, and its decision is ``inconclusive`` (within U of the tolerance, ISO 14253-1, or a
suspect / doubtful measurement) or ``undecided`` (the alignment to CAD is not trusted)), or *within*
(measured, ``pass``, and decided). ``failed`` in the archive and the console is *beyond*: a target that was
not measured did not fail, the measurement did not decide it. A target beyond its tolerance may be undecided
too (within U outside the tolerance, or in an untrusted frame): it is counted beyond, and said undecided.
"""
from __future__ import annotations

#: the decisions that do not decide (report.json ``decision``)
UNDECIDED = ("inconclusive", "undecided")


def measured(t: dict) -> bool:
    """The target has a measured point (report.json ``measured``, or an index row's ``deviation_norm_m``)."""
    m = t.get("measured")
    if m is not None:
        return m[0] is not None
    return t.get("deviation_norm_m") is not None


def trusted(report: dict) -> bool:
    """The report's frame can be relied on: its alignment to CAD is trusted and its verdict is not UNTRUSTED (a
    report written before ``undecided`` existed has decided targets in an untrusted frame: this says so)."""
    return report.get("verdict") != "UNTRUSTED" and (report.get("alignment") or {}).get("trusted") is not False


def undecided(t: dict, frame_trusted: bool = True) -> bool:
    """Measured, but its decision does not decide: inconclusive or undecided, suspect, or doubtful (or any measured
    target when ``frame_trusted`` is False: :func:`trusted` of its report)."""
    return measured(t) and (not frame_trusted or t.get("decision") in UNDECIDED or bool(t.get("suspect"))
                            or bool(t.get("print_doubtful")))


def beyond(t: dict) -> bool:
    """Measured and beyond its tolerance (|d| > tolerance): what the archive counts as failed."""
    return measured(t) and not t.get("pass")


def within(t: dict, frame_trusted: bool = True) -> bool:
    """Measured, within its tolerance, and decided (not inconclusive, undecided, suspect or doubtful)."""
    return measured(t) and bool(t.get("pass")) and not undecided(t, frame_trusted)


def counts(targets: list[dict], frame_trusted: bool = True) -> dict:
    """``within``, ``beyond``, ``undecided`` (within tolerance but not decided), ``beyond_undecided`` (beyond and
    not decided: also in ``beyond``), ``not_measured``; within + beyond + undecided + not_measured = all.
    ``frame_trusted``: :func:`trusted` of the report (False: every measured target is undecided)."""
    out = {"within": 0, "beyond": 0, "undecided": 0, "beyond_undecided": 0, "not_measured": 0}
    for t in targets:
        if not measured(t):
            out["not_measured"] += 1
        elif beyond(t):
            out["beyond"] += 1
            out["beyond_undecided"] += undecided(t, frame_trusted)
        elif undecided(t, frame_trusted):
            out["undecided"] += 1
        else:
            out["within"] += 1
    return out


def exclusion(t: dict, verdict: str | None = None, trusted: bool | None = None) -> str | None:
    """Why a target's value is left out of a statistic (Cp/Cpk, control limits, drift), or None: not measured,
    the job's alignment not trusted (verdict UNTRUSTED), or its own decision does not decide."""
    if not measured(t):
        return "not measured"
    if verdict == "UNTRUSTED" or trusted is False or t.get("decision") == "undecided":
        return "alignment to CAD not trusted (verdict UNTRUSTED)"
    if t.get("print_doubtful"):
        return "doubtful: its images are not a clean dot"
    if t.get("suspect"):
        return "suspect: its observations could not be verified"
    if t.get("decision") == "inconclusive":
        return "inconclusive: within U of its tolerance"
    return None
