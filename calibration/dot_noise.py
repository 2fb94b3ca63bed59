"""The pixel noise a dot's centre carries: a line in the grey level measured on the image's own dots, and what the
background plane's own error does to the centroid (decision 0047).

:func:`noise_levels` measures the line (photon noise grows with the light: a bright dot's top is noisier than the
ground around it, a dark dot's quieter than its lit paper); :func:`plane_cov` propagates the ring fit's error into
the centroid. :func:`calibration.dots.detect_dots` uses both for ``Detections.cov``.
"""
from __future__ import annotations

import numpy as np

__all__ = ["CLIPPED_SHARE", "MIN_PLATEAU_PAIRS", "NOISE_DOTS", "grey_step", "level_variances", "line_in_image_levels",
           "noise_levels", "pairs_two_apart", "plane_cov", "range_top", "triples_two_apart"]


#: fewest pixel pairs on the dots' plateaus for the noise's growth with the light to be measured (else none is used)
MIN_PLATEAU_PAIRS = 200
#: about this many dots (every n-th) measure the noise's line
NOISE_DOTS = 250
#: a level at the end of the grey range that at least this share of the ring pixels hold exactly is a clipped ground
CLIPPED_SHARE = 0.02


def pairs_two_apart(lab: np.ndarray, x: np.ndarray, y: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)`` of pixels of the same label two apart along a row or a column (the image's noise
    figure's spacing: neighbours share the lens blur's light but not the noise, two apart barely share either)."""
    return _runs(lab, x, y, shape, 2)


def triples_two_apart(lab: np.ndarray, x: np.ndarray, y: np.ndarray, shape: tuple[int, int]
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index triples ``(i, j, k)`` of pixels of the same label at 0, 2 and 4 along a row or a column: their second
    difference ``v_i - 2 v_j + v_k`` is blind to a local slope (a shading the ring's plane does not follow)."""
    return _runs(lab, x, y, shape, 3)


def _runs(lab: np.ndarray, x: np.ndarray, y: np.ndarray, shape: tuple[int, int], n: int) -> tuple[np.ndarray, ...]:
    """``n`` index arrays: runs of ``n`` pixels of one label, each two from the last, along a row or a column."""
    H, W = shape
    key = (lab.astype(np.int64) * H + y) * W + x
    order = np.argsort(key, kind="stable")
    sk = key[order]
    out: list[list[np.ndarray]] = [[] for _ in range(n)]
    for along_row in (True, False):
        step = 2 if along_row else 2 * W
        ok = np.ones(len(key), dtype=bool)
        idx = [np.arange(len(key))]
        for m in range(1, n):
            ok &= (x + 2 * m < W) if along_row else (y + 2 * m < H)
            want = key + m * step
            pos = np.minimum(np.searchsorted(sk, want), max(len(sk) - 1, 0))
            if len(sk):
                ok &= sk[pos] == want
            idx.append(order[pos] if len(sk) else pos)
        for m in range(n):
            out[m].append(idx[m][ok])
    return tuple(np.concatenate(o) for o in out)


def level_variances(level: np.ndarray, d: np.ndarray, n_bins: int, gain: float = 2.0, step: float = 1.0
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per bin of grey ``level`` (quantiles), the noise variance from the differences ``d`` of pixels (``mean(d^2) /
    gain`` over those within 4 robust sd of the median, and never fewer than those within 3 of the grey levels'
    ``step``: an edge or a neighbour's rim left out; ``gain`` 2 for a difference of two pixels, 6 for a second
    difference); returns (mean level, variance, differences) per bin. ``step`` is the smallest change of grey level
    the image has (1; 257 for a 16-bit copy of an 8-bit image): a bin whose differences are mostly 0 keeps its +-1
    steps as noise, not as outliers (with 3 grey levels there a 16-bit copy's bins came out noise-free)."""
    if len(d) < 20:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    edges = np.unique(np.quantile(level, np.linspace(0.0, 1.0, n_bins + 1)))
    b = np.clip(np.searchsorted(edges, level, side="right") - 1, 0, max(len(edges) - 2, 0))
    lv, var, cnt = [], [], []
    for j in range(max(len(edges) - 1, 1)):
        m = b == j
        if m.sum() < 20:
            continue
        dj = d[m]
        med = np.median(dj)
        scale = 1.4826 * np.median(np.abs(dj - med))
        keep = np.abs(dj - med) <= max(4.0 * scale, 3.0 * step)
        lv.append(float(level[m][keep].mean()))
        var.append(float(np.mean(dj[keep] ** 2) / gain))
        cnt.append(int(keep.sum()))
    return np.array(lv), np.array(var), np.array(cnt)


def noise_levels(shape: tuple[int, int], dots: tuple, rings: tuple, noise: float) -> tuple[float, float]:
    """The pixel noise's variance as a line in the grey level, ``(v0, s)``: ``var(v) = v0 + s v``.

    Photon noise makes a pixel's variance grow with its light: on the simulated sensor a dot's plateau is about 3x
    noisier (in sd) than the part's shading around it, and a camera's photon transfer is the same line. Measured on
    the image's own dots:
    - differences of pixels two apart on their flat tops (``dots = (label, x, y, value)``: the unclipped pixels
      within half the dot's ellipse, chosen by position: a choice by value would keep the pixels the noise lifted
      and halve the variance);
    - second differences of pixels 0, 2 and 4 apart on their background rings about the fitted plane (``rings =
      (label, x, y, value, residual)``), blind to a local slope of the shading the plane does not follow;
    binned by a level the pairs' own noise does not set (a dot's mean top, the ring's plane), and a line fitted to
    the bins, weighted by their pairs over the line's variance squared (the estimates' scatter).
    Ring pixels at a clipped level (the grey range's end, held by many pixels: a dark dot's paper over-exposed) have
    no noise and are left out. Too few plateau pairs (:data:`MIN_PLATEAU_PAIRS`), or a line that is negative anywhere
    in the grey range (0 to the range's top, 255 for 8 bits: no pixel can have a negative variance; a fit through the
    few levels measured can extrapolate to one) by more than the ground's variance ``noise^2``, give ``(noise^2, 0)``:
    the image's one figure for every pixel (its ground's noise), as before this was measured;
    :func:`line_in_image_levels` says which happened. No check says whether a
    line describes the image's noise: the bins' misfit to the line is 13-1400x their sampling scatter even on the
    simulated sensor, whose noise is a line, so it cannot tell a camera whose noise is not (decision 0047).
    """
    flat = (noise**2, 0.0)
    lt, xt, yt, vt = dots
    lr, xr, yr, vr, rr = rings
    i, j = pairs_two_apart(lt, xt, yt, shape)
    if len(i) < MIN_PLATEAU_PAIRS:
        return flat
    # the rings by second differences: the part's shading is no plane across a ring (kinks, curvature), and first
    # differences took its local slope for noise (the renders' statement came out 4-10 % more pessimistic)
    ir, jr, kr = triples_two_apart(lr, xr, yr, shape)
    # a clipped ground (a level at the end of the range that many ring pixels hold exactly) has no noise to measure
    ends = [v for v in (min(vr.min(initial=np.inf), vt.min()), max(vr.max(initial=-np.inf), vt.max()))
            if np.count_nonzero(vr == v) >= CLIPPED_SHARE * max(len(vr), 1)]
    if ends:
        at_end = np.isin(vr, ends)
        unclipped = ~(at_end[ir] | at_end[jr] | at_end[kr])
        ir, jr, kr = ir[unclipped], jr[unclipped], kr[unclipped]
    step = grey_step(vt, vr)
    # each pair binned by a level its own noise does not set (binned by their own values, the pairs the noise pushed
    # apart and those it left alike fall in different bins): a dot's mean top, the ring's fitted plane
    n_top = np.bincount(lt)
    mean_top = np.bincount(lt, weights=vt) / np.maximum(n_top, 1)
    plane = vr - rr
    l1, v1, n1 = level_variances(mean_top[lt[i]], vt[i] - vt[j], 4, step=step)
    l2, v2, n2 = level_variances(plane[jr], rr[ir] - 2.0 * rr[jr] + rr[kr], 4, gain=6.0, step=step)
    lv, var, cnt = np.concatenate([l1, l2]), np.concatenate([v1, v2]), np.concatenate([n1, n2])
    if len(lv) < 2 or np.ptp(lv) <= 0:
        return flat
    # weighted by the pairs over the line's variance squared (the estimates' scatter), not over their own: a bin the
    # noise made quiet would otherwise weigh more and pull the line down
    X = np.column_stack([np.ones_like(lv), lv])
    w = cnt.astype(float)
    for _ in range(2):
        v0, s = np.linalg.lstsq(X * np.sqrt(w)[:, None], var * np.sqrt(w), rcond=None)[0]
        w = cnt / np.maximum(v0 + s * lv, 1e-6) ** 2
    # a dark dot's image is inverted before it is measured: there the line falls (the paper around it is the lit part)
    if not (np.isfinite(v0) and np.isfinite(s)) or min(v0 + s * lv.min(), v0 + s * lv.max()) <= 0:
        return flat
    # negative somewhere in the grey range, by more than the ground's own variance (what the fit can tell from 0)
    if min(v0, v0 + s * range_top(max(vt.max(), vr.max(initial=0.0)))) < -noise**2:
        return flat
    return float(v0), float(s)


def grey_step(*values: np.ndarray) -> float:
    """The smallest step between the integer grey levels of ``values``: 1, or e.g. 257 for a 16-bit copy of an 8-bit
    image (every level a multiple of 257); 1 when they hold fewer than two levels."""
    v = np.unique(np.concatenate([np.asarray(a, dtype=np.float64).ravel() for a in values]))
    v = v[np.isfinite(v)]
    if len(v) < 2:
        return 1.0
    return float(max(np.gcd.reduce(np.round(v - v[0]).astype(np.int64)), 1))


def range_top(top: float) -> float:
    """The top of the grey range a level ``top`` lies in: 255 for 8 bits, else the all-ones code of 10, 12, 14 or 16
    bits (what :func:`calibration.dots._ceiling` takes as the sensor's clipping level)."""
    for bits in (8, 10, 12, 14, 16):
        if top <= (1 << bits) - 1:
            return float((1 << bits) - 1)
    return 65535.0


def line_in_image_levels(levels: tuple[float, float] | None, polarity: str, top: float, noise: float) -> dict:
    """The noise line ``levels`` (``(v0, s)`` in the polarised image the detector measured: a dark dot's image is
    inverted first, ``top - v``) said in the image's own grey levels, and whether it is photon noise's shape.

    Returns {``variance_at_zero``, ``variance_per_grey_level`` (the image's own levels), ``constant`` (True: one
    figure for every pixel, the ground's noise squared: too few dots to measure a line, or a fitted line negative
    somewhere in the grey range, see :func:`noise_levels`), ``physical`` (a variance that does not fall with the light
    and is not negative at black; False: said, the covariances still carry it), ``note``}."""
    if levels is None:
        return {"variance_at_zero": None, "variance_per_grey_level": None, "constant": True, "physical": False,
                "note": "not measured (no dots)"}
    v0, s = levels
    if polarity == "dark":  # var(v_polarised) = v0 + s (top - v): in the image's own levels
        v0, s = v0 + s * top, -s
    if s == 0.0:
        return {"variance_at_zero": float(v0), "variance_per_grey_level": 0.0, "constant": True, "physical": True,
                "note": f"one figure for every pixel, the ground's noise {noise:.3g} grey levels squared: the dots' "
                        "tops and rings gave no usable line (too few pixels on flat tops, or a fitted line negative "
                        "somewhere in the grey range)"}
    physical = v0 >= 0.0 and s >= 0.0
    note = "measured on the dots' tops and rings" + ("" if physical else (
        ": NOT photon noise's shape (it falls with the light); the covariances carry it as measured" if s < 0 else
        ": NOT photon noise's shape (negative at black); the covariances carry it as measured"))
    return {"variance_at_zero": float(v0), "variance_per_grey_level": float(s), "constant": False,
            "physical": bool(physical), "note": note}


def plane_cov(li, vi, wi, top_i, span, sws, dx, dy, xi, yi, xc, yc, A: np.ndarray, ring_var: np.ndarray,
              k: int, min_ring_px: int) -> np.ndarray:
    """What the background plane's own error does to each centroid, (k, 2, 2) px^2.

    The plane ``b0 + gx (x - xc) + gy (y - yc)`` is fitted to the ring's pixels (``A``: (k, 3, 3) their normal
    matrices; fewer than ``min_ring_px`` carry none): its coefficients err by ``ring_var A^-1``. A pixel's weight
    ``w = (v - b) / (top - b)`` moves by ``(v - top) / (top - b)^2`` per grey level of the plane under it: the
    margin's pixels (w ~ 0) the most, the plateau's (w ~ 1) hardly (those above 0.9 are left out: a few per cent of the term). So the centre moves by
    ``sum (x - u) (v - top) / (top - b)^2 [1, x - xc, y - yc] / sum w`` per unit of the coefficients.
    """
    m = wi < 0.9
    lm = li[m]

    def per(w):
        return np.bincount(lm, weights=w, minlength=k + 1)[1:]

    h = np.where(span[m] > 1.0, (vi[m] - top_i[m]) / span[m] ** 2, 0.0) / sws[lm - 1]
    rx, ry = xi[m] - xc[lm - 1], yi[m] - yc[lm - 1]
    hx, hy = h * dx[m], h * dy[m]
    J = np.stack([np.stack([per(hx), per(hx * rx), per(hx * ry)], -1),
                  np.stack([per(hy), per(hy * rx), per(hy * ry)], -1)], 1)  # (k, 2, 3)
    out = np.zeros((k, 2, 2))
    n = A[:, 0, 0]
    ok = n >= min_ring_px
    if np.any(ok):
        det = np.linalg.det(A[ok])
        good = np.flatnonzero(ok)[np.abs(det) > 1e-9 * np.maximum(n[ok], 1) ** 3]
        if len(good):
            Jg = J[good]
            out[good] = ring_var[good, None, None] * (Jg @ np.linalg.solve(A[good], np.swapaxes(Jg, 1, 2)))
            ok[:] = False
            ok[good] = True
    # a ring that carried no plane (too few pixels): its mean level alone, erring by ring_var / n
    flat = ~ok & (n > 0)
    if np.any(flat):
        out[flat] = (ring_var[flat] / n[flat])[:, None, None] * np.einsum("ka,kb->kab", J[flat, :, 0], J[flat, :, 0])
    return out
