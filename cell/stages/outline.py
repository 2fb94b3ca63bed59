"""A target's print: does each image of it show an ellipse, and does its light agree with its edge? (decision 0051)

A retro-reflective dot wears: its coating chips at the edge, a speck of dirt or paint sits on it. The centre the
detector finds is then the centre of what is left, off the target's true centre by the same amount on the part in
every view. The bundle cannot see it (the rays agree), the blunder test cannot either, and the report would state
the target to its full precision, off by up to a tenth of the dot's radius: a silent wrong number, and on a precise
cell a deviation of many sigma that is the target's, not the part's.

Two checks, from what MEASURE keeps per observation (observations.json ``outline`` and ``centroid_chi2``,
:func:`calibration.dots.detect_dots` with ``outline`` on):

* **outline**: the half-level contour about its fitted ellipse, ``chi2 / (n - 5)`` over the median of the image's
  dots of the same kind (clipped or not: the contour's noise model is not the same for both; the job's median where
  the image has fewer than :data:`MIN_IMAGE_DOTS` of them). An ellipse's image gives about one, a chipped edge more.
* **centroid**: a centroid dot's centre less its contour's ellipse centre, in their covariance (``centroid_chi2``),
  over the image's median (or the job's) and times the median of chi-square(2): a speck inside the dot moves its
  light's centre and not its edge.

A target whose median over its views (:data:`MIN_VIEWS` or more) exceeds :data:`OUTLINE_LIMIT` or
:data:`CENTROID_LIMIT` is doubtful: ADJUST reports it inconclusive (as a suspect of data snooping; report.json says
why), the alignment leaves it out, and a scale bar with it at an end is left out. Both limits are relative to each
image's own dots, so the image's noise, blur, focus, exposure and compression need no model (on photographs the
contours' misfit was 11x the simulated camera's, and it changes from one photograph to the next); they presume that
most of an image's targets are whole.
"""
from __future__ import annotations

import numpy as np

__all__ = ["OUTLINE_LIMIT", "CENTROID_LIMIT", "MIN_VIEWS", "outline_doubtful", "outline_reason", "outline_doc",
           "judged_targets", "say_doubtful"]

#: a target's median outline misfit over its views, in the job's median for its kind of dot, beyond which its print
#: is doubtful (decision 0051: whole dots of the example stay below 1.7; a chipped edge of 1 % of the dot's area gives
#: about 4 at a radius of 5 px)
OUTLINE_LIMIT = 3.0
#: the same for the centroid's disagreement with the edge's ellipse, scaled to chi-square(2) (median 1.39; 12 is its
#: 0.25 % point, and the median of three views passes it once in 50 000 whole targets)
CENTROID_LIMIT = 12.0
#: a print is judged on at least this many views (the median of fewer is one odd view)
MIN_VIEWS = 3
#: an image with this many dots of a kind judges them against their own median, else against the job's
MIN_IMAGE_DOTS = 10
_CHI2_2_MEDIAN = 2.0 * np.log(2.0)


def _scores(obs: dict, index: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per observation: target index, outline ratio, centroid score (NaN where not measured)."""
    tgt, oc, on, clip, cc = [], [], [], [], []
    for im in obs["images"]:
        if "outline" not in im:
            continue
        k = len(im["ids"])
        ol = np.array([[np.nan, np.nan] if r is None else [np.nan if v is None else v for v in r]
                       for r in im["outline"]], dtype=float).reshape(-1, 2)
        tgt += [index[t] for t in im["ids"]]
        oc.append(ol[:, 0])
        on.append(ol[:, 1])
        clip.append(np.asarray(im.get("clipped_share") or np.zeros(k), dtype=float) > 0)
        cc.append(np.array([np.nan if v is None else v for v in im.get("centroid_chi2") or [None] * k], dtype=float))
    if not tgt:
        return np.zeros(0, dtype=int), np.zeros(0), np.zeros(0)
    img = np.concatenate([np.full(len(a), i) for i, a in enumerate(oc)])
    oc, on, clip, cc = (np.concatenate(a) for a in (oc, on, clip, cc))
    z = oc / np.maximum(on - 5, 1)
    ratio = np.full(len(z), np.nan)
    for kind in (False, True):
        ratio = np.where(clip == kind, _relative(z, img, (clip == kind) & np.isfinite(z)), ratio)
    score = _relative(cc, img, np.isfinite(cc)) * _CHI2_2_MEDIAN
    return np.asarray(tgt, dtype=int), ratio, score


def _relative(v: np.ndarray, img: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``v`` over the median of its image's values ``m`` (:data:`MIN_IMAGE_DOTS` or more), else over the job's (5 or
    more), else NaN: a photograph's focus, light and compression are its own (decision 0051)."""
    out = np.full(len(v), np.nan)
    if m.sum() < 5:
        return out
    job = max(float(np.median(v[m])), 1e-12)
    for i in np.unique(img[m]):
        here = m & (img == i)
        ref = max(float(np.median(v[here])), 1e-12) if here.sum() >= MIN_IMAGE_DOTS else job
        out[here] = v[here] / ref
    return out


def outline_doubtful(obs: dict, ids: list[str]) -> dict[int, dict]:
    """Targets whose print is doubtful: {target index: {"views", "outline", "centroid", "why"}} (the medians over their
    views, None with fewer than :data:`MIN_VIEWS`; observations.json records without the outline figures count
    nothing)."""
    index = {t: k for k, t in enumerate(ids)}
    tgt, ratio, score = _scores(obs, index)
    out: dict[int, dict] = {}
    for t in np.unique(tgt):
        r, c = ratio[tgt == t], score[tgt == t]
        r, c = r[np.isfinite(r)], c[np.isfinite(c)]
        mo = float(np.median(r)) if len(r) >= MIN_VIEWS else None
        mc = float(np.median(c)) if len(c) >= MIN_VIEWS else None
        why = []
        if mo is not None and mo > OUTLINE_LIMIT:
            why.append(f"its outline is not an ellipse ({mo:.1f}x the job's median misfit, the median over {len(r)} "
                       f"images; > {OUTLINE_LIMIT:g}): a chipped or worn edge")
        if mc is not None and mc > CENTROID_LIMIT:
            why.append(f"its light's centre is off its edge's ({mc:.1f}, the median over {len(c)} images; "
                       f"> {CENTROID_LIMIT:g}): a speck or stain on the dot")
        if why:
            out[int(t)] = {"views": int(np.sum(tgt == t)), "outline": mo, "centroid": mc, "why": "; ".join(why)}
    return out


def outline_reason(job, j: int, doubtful: dict) -> str | None:
    """Why scale bar ``j`` is left out when an end's print is doubtful (None: it is not)."""
    from cell.stages.scalebars import end_reason

    ids = job.part.targets.ids
    return end_reason(job, j, doubtful, lambda t: f"{ids[int(t)]}: {doubtful[t]['why']}", "; ",
                      " (its centre is not the target's: the bar's length would be wrong)")


def outline_doc(doubtful: dict, ids: list[str], obs: dict) -> dict:
    """bundle.json ``target_print``: how many targets were judged, those measured that were not (fewer than
    :data:`MIN_VIEWS` views with the figures: a worn one among them would pass unseen), the limits and each doubtful
    target with why."""
    judged, unjudged = judged_targets(obs, ids)
    return {"checked_targets": judged, "not_checked": unjudged, "outline_limit": OUTLINE_LIMIT,
            "centroid_limit": CENTROID_LIMIT, "doubtful": [{"id": ids[t]} | d for t, d in sorted(doubtful.items())]}


def judged_targets(obs: dict, ids: list[str]) -> tuple[int, list[str]]:
    """How many measured targets have an outline or a centroid figure in :data:`MIN_VIEWS` views or more, and the ids
    of the measured ones that have not (not judged)."""
    index = {t: k for k, t in enumerate(ids)}
    tgt, ratio, score = _scores(obs, index)
    judged = {ids[t] for t in np.unique(tgt)
              if max(np.isfinite(ratio[tgt == t]).sum(), np.isfinite(score[tgt == t]).sum()) >= MIN_VIEWS}
    measured = {t for im in obs["images"] for t in im["ids"]}
    return len(judged), sorted(measured - judged)


def say_doubtful(ctx, doubtful: dict, ids: list[str], obs: dict) -> set[int]:
    """Warn of each doubtful print (console and run log), and say which measured targets were not judged; returns the
    doubtful targets, to be reported inconclusive."""
    unjudged = judged_targets(obs, ids)[1]
    if unjudged:
        msg = (f"{len(unjudged)} target(s) not checked for wear (fewer than {MIN_VIEWS} images with an outline "
               f"figure): " + ", ".join(unjudged[:8]) + (" ..." if len(unjudged) > 8 else ""))
        ctx.log.log("info", msg)
        ctx.say(f"  {msg}")
    if doubtful:
        msg = ("targets whose images are not a clean dot, reported inconclusive and left out of the alignment: "
               + "; ".join(f"{ids[t]} ({d['why']})" for t, d in sorted(doubtful.items())))
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")
    return set(doubtful)
