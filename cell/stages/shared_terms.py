"""What every target's covariance carries beyond its own rays, added after the adjustment.

* :func:`add_coherent_background`: the background misfit a target's views share (decision 0029), the share of every
  dot's error its views have in common (the detector model's ``rho_all``, decision 0043), the clip bounds they share
  (decision 0050), and the scale bars' ends' shared misfit through the scale.
* :func:`add_held_lens`: a lens held as the cell's hand-eye calibration estimated it (``self_calibrate = false`` with
  the cell file's ``camera_lens``, decision 0056): its covariance from that calibration, through the network. The
  adjustment is made again at the lens moved by each principal axis of that covariance (one sigma along it), the
  observations and their weights held; the targets' moves are the columns of a low-rank term, whose sum over the
  axes is the lens's share of each target's covariance (and of every pair's, through the low-rank form).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from calibration.bundle import BundleOptions, bundle_adjust
from calibration.bundle.coherent import coherent_background_cov
from calibration.bundle.covariance import append_columns
from calibration.detector_model import load_model
from cell.cellcal.cellfile import LENS_KEYS as LENS_FIELDS  # the cell file's camera_lens fields, in cov's order
from cell.stages.clip_level import clip_level_cov


def holds_cell_lens(job) -> bool:
    """The job holds the cell's lens (``self_calibrate = false``) and the cell file states its covariance."""
    lens = (getattr(job, "cell", None) or {}).get("lens") or {}
    return not job.spec.camera.self_calibrate and lens.get("cov") is not None


def add_coherent_background(res, bg: np.ndarray, img, tgt, ids: list[str], bars=(), K=None, clip_cov=None) -> dict:
    """Add to each target's covariance the background misfit its views share (decision 0029), the clip bounds they
    share (``clip_cov``, decision 0050), and what the scale bars' ends' shares do to every target through the scale
    (``K``: :func:`scale_bar_gains`); what was added."""
    bar_terms: list[dict] = []
    used = ~res.rejected
    model = load_model()
    c, share = model.c_background, model.shared_share  # the share the views have in common (decision 0032)
    extra = coherent_background_cov(res.intrinsics, res.cam_from_part, res.points, img[used], tgt[used],
                                    res.obs_sigma_px[used], bg[used], c, share)
    hit = np.flatnonzero(np.trace(extra, axis1=1, axis2=2) > 0)
    bg_extra = extra
    # every dot's views also share a small part of its whole error (decision 0043: the detector's deterministic
    # response to the dot's own geometry, which more views do not average away): the model's rho_all of the
    # covariance each observation was weighted with, through the same cross terms
    floor = np.zeros_like(extra)
    if model.rho_all > 0:
        C = np.asarray(res.obs_sigma_px, dtype=float)[used]
        C = C[:, None, None] ** 2 * np.eye(2) if C.ndim == 1 else C
        floor = coherent_background_cov(res.intrinsics, res.cam_from_part, res.points, img[used], tgt[used], C, C,
                                        1.0, model.rho_all)
        extra = extra + floor
    clip_extra, clip_doc = clip_level_cov(res, clip_cov, img, tgt)
    extra = extra + clip_extra
    on = np.flatnonzero(np.trace(extra, axis1=1, axis2=2) > 0)
    before = np.trace(res.cov, axis1=1, axis2=2).copy()
    res.cov[on] += extra[on]
    res.covariance.D[on] += extra[on]
    # a scale bar's end with a shared misfit errs the bar's measured length, and every target follows the scale:
    # the ends' extra along the bar, through the gains (rank one per bar, into the covariance's low-rank part;
    # the extra carries the share, so the bar's term scales with it too)
    for j, bar in enumerate(bars):
        u = res.points[bar.target_a] - res.points[bar.target_b]
        u = u / np.linalg.norm(u)
        v = float(u @ (extra[bar.target_a] + extra[bar.target_b]) @ u)
        if v > 0:
            k = np.nan_to_num(K[:, :, j])  # NaN only for targets the adjustment did not determine
            res.cov += v * np.einsum("na,nb->nab", k, k)
            res.covariance = append_columns(res.covariance, k[:, :, None], [v])
            bar_terms.append({"bar": [ids[bar.target_a], ids[bar.target_b]], "bar_index": j,
                              "length_sigma_m": float(np.sqrt(v))})
    grow = np.sqrt(np.trace(res.cov[hit], axis1=1, axis2=2) / np.maximum(np.trace(res.cov[hit] - bg_extra[hit], axis1=1, axis2=2), 1e-300))
    worst = np.argsort(-grow)[:5]
    fl = np.flatnonzero(np.trace(floor, axis1=1, axis2=2) > 0)
    fgrow = np.sqrt((before[fl] + np.trace(floor[fl], axis1=1, axis2=2)) / np.maximum(before[fl], 1e-300))
    return {"share": share, "share_measured": model.rho_background is not None, "c_background": c, "n_targets": int(len(hit)), "scale_bar_ends": bar_terms,
            "sigma_growth_median": float(np.median(grow)) if len(hit) else 1.0,
            "largest": [{"target": ids[int(hit[k])], "sigma_growth": float(grow[k]),
                         "added_sigma_m": float(np.sqrt(np.trace(bg_extra[hit[k]]) / 3))} for k in worst],
            "clip_level": clip_doc, "shared_floor": {"rho_all": model.rho_all, "n_targets": int(len(fl)),
                             "sigma_growth_median": float(np.median(fgrow)) if len(fl) else 1.0,
                             "sigma_growth_max": float(np.max(fgrow)) if len(fl) else 1.0}}


def add_held_lens(res, img: np.ndarray, tgt: np.ndarray, uv: np.ndarray, config, sigma_px: float,
                  lens_cov) -> dict:
    """Carry a held lens's covariance ``lens_cov`` (9 x 9, :data:`LENS_FIELDS`) into ``res``'s targets (see above).

    ``img, tgt, uv``: the adjustment's observations (all of them; the rejected stay out); ``config``: its
    configuration (the lens held, the datum). Returns what was added: the axes used, each one's largest target move,
    how much the targets' sigmas grew, and each target's added variance (``added_variance_m2``, the trace of its
    term; None where its covariance is not finite: predicted / achieved compares the images' precision without it,
    as without the temperatures' shared part). Nothing is added (``carried`` False, ``why``) when a re-adjustment does not
    converge or moves a target by a non-finite amount: a term from it would be a number nobody could trust.
    """
    C = np.asarray(lens_cov, dtype=float)
    lam, V = np.linalg.eigh(0.5 * (C + C.T))
    axes = np.flatnonzero(lam > max(lam.max(), 0.0) * 1e-12)
    used = ~np.asarray(res.rejected, dtype=bool)
    sig = np.asarray(res.obs_sigma_px)[used]
    base = res.points
    cols, moved = [], []
    for k in axes:
        step = np.sqrt(lam[k]) * V[:, k]
        lens = replace(res.intrinsics, **{f: getattr(res.intrinsics, f) + d for f, d in zip(LENS_FIELDS, step)})
        r = bundle_adjust(img[used], tgt[used], uv[used], lens, res.cam_from_part, base,
                          BundleOptions(sigma_px=sigma_px, max_rejections=0), config, obs_sigma_px=sig)
        determined = np.isfinite(base).all(axis=1)
        if not r.converged or not np.isfinite(r.points[determined]).all():
            return {"carried": False, "axes": int(len(axes)), "largest_move_m": moved, "sigma_growth_median": 1.0,
                    "sigma_growth_max": 1.0, "why": f"the adjustment at the lens moved along axis {int(k)} did not "
                    f"converge ({r.summary})"}
        d = np.where(np.isfinite(r.points - base), r.points - base, 0.0)
        cols.append(d)
        moved.append(float(np.max(np.linalg.norm(d, axis=1))))
    if not cols:  # a covariance of zeros: nothing to carry
        return {"carried": False, "axes": 0, "largest_move_m": [], "sigma_growth_median": 1.0, "sigma_growth_max": 1.0,
                "why": "the cell file's lens covariance is zero"}
    cols = np.stack(cols, axis=2)  # (n, 3, axes)
    extra = np.einsum("nak,nbk->nab", cols, cols)
    ok = np.isfinite(np.trace(res.cov, axis1=1, axis2=2))
    before = np.trace(res.cov[ok], axis1=1, axis2=2)
    res.cov = res.cov + extra
    res.covariance = append_columns(res.covariance, cols, np.ones(cols.shape[2]))
    grow = np.sqrt((before + np.trace(extra[ok], axis1=1, axis2=2)) / np.maximum(before, 1e-300))
    added = np.trace(extra, axis1=1, axis2=2)
    return {"carried": True, "axes": int(len(axes)), "largest_move_m": moved,
            "sigma_growth_median": float(np.median(grow)), "sigma_growth_max": float(np.max(grow)),
            "added_variance_m2": [float(v) if o and np.isfinite(v) else None for v, o in zip(added, ok)]}


def held_lens_line(doc: dict) -> str:
    """One line for the console and the log: the held lens's uncertainty carried, or why it was not."""
    if doc["carried"]:
        return (f"the held lens's uncertainty (the cell's hand-eye calibration) carried into every target: sigma "
                f"x{doc['sigma_growth_median']:.2f} median, x{doc['sigma_growth_max']:.2f} at most")
    return (f"the held lens's uncertainty was not carried ({doc['why']}): the targets' covariances leave it out and "
            "are optimistic by it")
