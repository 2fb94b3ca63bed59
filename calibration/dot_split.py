"""Dots that the noise of a lit surface joined to it, split off at that surface's own noise (issue 15).

The detector's threshold is ``threshold_sigma`` times one noise figure of the whole image, which its dark background
(most of its pixels) sets. On the lit surface of the part the photon noise is 2-3 times that, and the top-hat (the image
minus its opening, a maximum of minima) sits ~2.5 of that noise above zero: about half of the surface's pixels pass the
threshold, and 8-connected they percolate into clusters of thousands of pixels, or tendrils, that reach a dot's rim at
random. The dot is then

- part of a blob too large or too loose to be one, and lost (the large, clipped dots of a near view lie on the brightest
  surface: 2-10 of 34 per render on one view of a generated plate); or
- part of a blob that still passes as one dot, two dots bridged or a dot with a cluster of the noise, whose centre the
  cluster pulls (0.04-0.13 px; several px for a bridged pair): a wrong centre, not a missing one.

:func:`split_pass` runs after the detector's own pass and leaves what that pass found as it is, to the bit, except the
blobs of the second kind, which it replaces by their parts where one of them is a dot. It measures the noise as a
function of the background level (:func:`noise_by_level`), keeps in each such component only the pixels whose top-hat
exceeds ``threshold_sigma`` times the noise of the opening under them, labels them anew and measures the new blobs as
the detector measures any (:func:`calibration.dots._measure`), keeping those whose ellipse and centroid centres agree.
Decision 0039.
"""
from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from calibration.dots import DetectionOptions, Detections, _blob_tests, _ceiling, _measure, _twice_median

#: a component that is too large or too loose for a dot is split at its own noise (:func:`split_pass`) when it has
#: at least this many pixels (smaller: noise, or a small dot that stays lost)
SPLIT_MIN_AREA_PX = 64

#: a blob that passed as one dot is measured again at its own noise where its largest part there keeps less than this
#: share of its pixels: a dot with a cluster of the surface's noise attached (a single dot on a lit surface keeps
#: ~85 %: its skirt between the two thresholds), whose centre the cluster pulls
JOINED_MIN_SHARE = 0.7

#: a blob split off a merged component is a dot only if its ellipse and centroid centres agree within this (px)
SPLIT_AGREE_PX = 0.25

#: pairs of pixels a level's bin needs for its noise (:func:`noise_by_level`): ~5 % on the standard deviation
NOISE_BIN_MIN_PAIRS = 200


def split_pass(image: np.ndarray, o: DetectionOptions, surface: np.ndarray | None, tophat: np.ndarray, thr: float,
               noise: float, bg: float, labels: np.ndarray, stats: np.ndarray, compact: np.ndarray, max_area: float,
               det: Detections, found: np.ndarray) -> Detections:
    """The detections ``det`` of the detector's pass (``found``: the 0-based component of each), with the dots that the
    noise of a lit surface joined split off and measured (module docstring). ``labels`` / ``stats``: that pass's
    components (``labels`` is relabelled in place), ``compact`` which of them passed as dots by size and shape,
    ``tophat`` / ``thr`` / ``noise`` / ``bg`` its top-hat, threshold, noise and median level."""
    n_lab = len(stats)
    # dots joined to the lit surface they lie on, split off at that surface's own noise; a new blob that comes within
    # the reach of a detected one's margin and ring (m + 2 px) or of its ellipse fit's window (2 + 2 px) is its skirt
    merged = np.flatnonzero(~compact & (stats[1:, cv2.CC_STAT_AREA] >= SPLIT_MIN_AREA_PX)) + 1
    opening = cv2.subtract(image, tophat)  # the background under the top-hat
    levels, sigmas = noise_by_level(image, opening, 2 * o.subsample)
    if len(levels) == 0 or o.threshold_sigma * sigmas.max() <= thr:  # nowhere noisier than the image's figure
        return det
    # a detection whose own pixels' top-hat does not reach min_peak_snr times the noise of the opening under it is a
    # speck of that noise (its peak may not say so: its margin and ring may have held the merged dot): no dot next to
    # it is its skirt. Asked of the detections that could hold two dots, or that come within reach of a merged blob.
    H, W = image.shape
    reach = 2 * (o.margin_px + 2)
    noise_at = np.interp(np.arange(int(_ceiling(image)) + 1), levels, sigmas)  # by grey level of the opening
    big = stats[found + 1, cv2.CC_STAT_AREA] >= 2 * SPLIT_MIN_AREA_PX
    fb, mb = stats[found + 1, :4].astype(np.int64), stats[merged, :4].astype(np.int64)
    close = np.ones((len(found), len(merged)), dtype=bool)
    for a in (0, 1):  # the boxes, grown by the reach, overlap along x and along y
        close &= ((fb[:, None, a] <= mb[None, :, a] + mb[None, :, a + 2] + reach)
                  & (mb[None, :, a] <= fb[:, None, a] + fb[:, None, a + 2] + reach))
    close = close.any(axis=1)
    is_found = np.zeros(n_lab, dtype=bool)
    for i in np.flatnonzero(big | close):
        f = found[i] + 1
        x, y, w, h = (int(a) for a in stats[f, :4])
        top = tophat[y:y + h, x:x + w][labels[y:y + h, x:x + w] == f].max()
        u, v = det.uv[i]
        under = opening[min(max(int(round(v)), 0), H - 1), min(max(int(round(u)), 0), W - 1)]
        is_found[f] = top >= o.min_peak_snr * noise_at[under]
    joined = found[big & is_found[found + 1]] + 1
    # only where the ground under a blob's centre is noisier than the image's figure can the noise have joined it
    cx = np.minimum(stats[joined, 0] + stats[joined, 2] // 2, W - 1)
    cy = np.minimum(stats[joined, 1] + stats[joined, 3] // 2, H - 1)
    joined = joined[o.threshold_sigma * noise_at[opening[cy, cx]] > thr]
    stats, new_noise, parent, undone = _split(image, tophat, opening, noise_at, labels, stats, merged, joined, is_found,
                                              reach, o.threshold_sigma, thr)
    if len(new_noise) == 0:
        return det
    compact, clear = _blob_tests(stats, o, max_area, image.shape)
    keep = compact & clear & (np.arange(len(compact)) >= n_lab - 1)  # the new blobs only
    if not np.any(keep):
        return det
    # measured in the box that holds them with what their margins, rings and ellipse windows reach: the new blobs are
    # few, the image large
    box = stats[1:][keep]
    pad = 4 * (o.margin_px + 2)
    bx0, by0 = max(int(box[:, 0].min()) - pad, 0), max(int(box[:, 1].min()) - pad, 0)
    bx1, by1 = min(int((box[:, 0] + box[:, 2]).max()) + pad, W), min(int((box[:, 1] + box[:, 3]).max()) + pad, H)
    shifted = stats.copy()
    shifted[1:, cv2.CC_STAT_LEFT] -= bx0
    shifted[1:, cv2.CC_STAT_TOP] -= by0
    blob_noise = np.concatenate([np.full(n_lab - 1, noise), new_noise])
    crop = (slice(by0, by1), slice(bx0, bx1))
    more, comp = _measure(image[crop], o, None if surface is None else surface[crop], labels[crop], shifted, keep,
                          blob_noise, noise, bg, _ceiling(image), SPLIT_AGREE_PX, levels=det.noise_levels)
    # a blob that passed as one dot gives way to its parts only where one of them is a dot
    replaced = np.intersect1d(undone, parent[comp - (n_lab - 1)])
    det = det.subset(~np.isin(found + 1, replaced))
    return _concatenate(det, replace(more, uv=more.uv + np.array([bx0, by0], dtype=float)))


def _concatenate(a: Detections, b: Detections) -> Detections:
    """The detections ``a`` followed by ``b`` (of one image: ``a``'s noise and polarity)."""
    if len(b) == 0:
        return a
    if len(a) == 0:
        return b
    cat = {f: None if getattr(a, f) is None or getattr(b, f) is None else np.concatenate([getattr(a, f), getattr(b, f)])
           for f in ("uv", "area_px", "peak", "flux", "background", "cov", "axes", "background_cov", "saturated",
                     "ring_px", "ellipse", "clip_bound", "outline", "centroid_shift", "centroid_shift_cov")}
    return replace(a, **cat)


def noise_by_level(image: np.ndarray, background: np.ndarray, stride: int, bins: int = 16
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The pixel noise as a function of the background level: photon noise grows with the light.

    The differences of pixels two apart along every ``stride``-th row (as :func:`calibration.dots._noise`), neither
    clipped, binned by the mean ``background`` level of the pair in ``bins`` equal bins up to the sensor's ceiling; per
    bin of at least
    :data:`NOISE_BIN_MIN_PAIRS` pairs, their rms about the median within 5 robust standard deviations (the steps
    across a dot's rim are left out), over sqrt(2).
    Returns ((b,) mean background level of each such bin, increasing; (b,) its noise standard deviation).
    """
    ceiling = _ceiling(image)
    rows = image[::stride].astype(np.int32)
    d = rows[:, 2:] - rows[:, :-2]
    ok = (rows[:, 2:] < ceiling) & (rows[:, :-2] < ceiling)
    back = background[::stride].astype(np.float32)
    g = 0.5 * (back[:, 2:] + back[:, :-2])[ok]
    d = d[ok]
    if len(d) == 0:
        return np.zeros(0), np.zeros(0)
    b = np.minimum((g * np.float32(bins / (ceiling + 1.0))).astype(np.int64), bins - 1)
    lo = int(d.min())
    nv = int(d.max()) - lo + 1
    hist = np.bincount(b * nv + (d - lo), minlength=bins * nv).reshape(bins, nv)
    n = hist.sum(axis=1)
    mean_g = np.bincount(b, weights=g, minlength=bins) / np.maximum(n, 1)
    values = lo + np.arange(nv)
    levels, sigmas = [], []
    for i in np.flatnonzero(n >= NOISE_BIN_MIN_PAIRS):
        med2 = _twice_median(values, hist[i])
        dev2 = np.abs(2 * values - med2)
        mad = 0.25 * _twice_median(np.arange(int(dev2.max()) + 1), np.bincount(dev2, weights=hist[i]).astype(np.int64))
        s = max(1.4826 * mad, 1.0)  # integer differences: a MAD of 0 or 1 is coarse
        r = values - 0.5 * med2
        sel = np.abs(r) <= 5.0 * s
        levels.append(mean_g[i])
        sigmas.append(np.sqrt(np.sum(hist[i][sel] * r[sel] ** 2) / max(np.sum(hist[i][sel]), 1) / 2.0))
    return np.asarray(levels), np.asarray(sigmas)


def _split(image: np.ndarray, tophat: np.ndarray, opening: np.ndarray, noise_at: np.ndarray, labels: np.ndarray,
           stats: np.ndarray, merged: np.ndarray, joined: np.ndarray, found: np.ndarray, reach: int,
           threshold_sigma: float, thr: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Split the components ``merged`` (too large or too loose for a dot) at ``threshold_sigma`` times the noise of
    their own background (module docstring).

    In such a component a pixel is kept where its top-hat exceeds ``max(thr, threshold_sigma * noise)``, the noise
    ``noise_at`` (:func:`noise_by_level`, by grey level) of the ``opening`` under it; the kept pixels are labelled anew
    and their blobs appended to ``labels`` (in place; the component's other pixels become background) and ``stats``.
    A new blob within ``reach`` px of a dot ``found`` before ((n,) bool per component, 0 the background) is left out:
    it is that dot's own skirt, cut off. The components ``joined`` passed as dots (two dots bridged by the noise can,
    or a dot with a cluster of it); one of them is taken apart the same way only where it falls into two or more blobs
    of :data:`SPLIT_MIN_AREA_PX` or its largest part keeps less than :data:`JOINED_MIN_SHARE` of its pixels (its
    pixels are relabelled then; the caller keeps its detection unless one of its parts is a dot).
    Returns (the extended stats; (appended,) each appended blob's noise, the mean over its pixels, and the component it
    came from; the components of ``joined`` taken apart).
    """
    n = len(stats)
    new_stats, new_noise, parent, undone = [stats], [], [], []
    H, W = image.shape
    n0 = len(found)
    found = np.append(found, False).astype(np.uint8)  # labels from n0 on are new blobs: not found before
    near_kernel = np.ones((2 * reach + 1, 2 * reach + 1), dtype=np.uint8)
    for c, whole in [(c, True) for c in joined] + [(c, False) for c in merged]:
        x, y, w, h = (int(v) for v in stats[c, :4])
        lab = labels[y:y + h, x:x + w]  # a view: written in place
        comp = lab == c
        sig = noise_at[opening[y:y + h, x:x + w]]
        level = np.maximum(threshold_sigma * sig, thr)
        if not np.any(level[comp] > thr):  # its noise is the image's: nothing to split off
            continue
        sub = (comp & (tophat[y:y + h, x:x + w] > level)).astype(np.uint8)
        ns, sl, ss, _ = cv2.connectedComponentsWithStats(sub, connectivity=8, ltype=cv2.CV_32S)
        if whole:  # a blob that passed as one dot is taken apart only if it holds two, or a dot and much noise
            a = ss[1:, cv2.CC_STAT_AREA]
            whole_share = a.max(initial=0) / stats[c, cv2.CC_STAT_AREA]
            if np.count_nonzero(a >= SPLIT_MIN_AREA_PX) < 2 and whole_share >= JOINED_MIN_SHARE:
                continue
            undone.append(c)
        lab[comp] = 0
        if ns > 1:
            # the other dots found before, in the box grown by the reach, dilated by it: where a new blob may not come
            ex0, ey0, ex1, ey1 = max(x - reach, 0), max(y - reach, 0), min(x + w + reach, W), min(y + h + reach, H)
            around = labels[ey0:ey1, ex0:ex1]
            near = cv2.dilate(found[np.minimum(around, n0)] * (around != c).astype(np.uint8),
                              near_kernel)[y - ey0:y - ey0 + h, x - ex0:x - ex0 + w] > 0
            close = np.zeros(ns, dtype=bool)
            close[sl[near]] = True
            close[0] = False
            if close.any():
                sl = np.where(close[sl], 0, sl)
                ns, sl, ss, _ = cv2.connectedComponentsWithStats((sl > 0).astype(np.uint8), connectivity=8,
                                                                 ltype=cv2.CV_32S)
        if ns > 1:
            inside = sl > 0
            lab[inside] = sl[inside] + (n - 1)
            ss = ss[1:].copy()
            ss[:, cv2.CC_STAT_LEFT] += x
            ss[:, cv2.CC_STAT_TOP] += y
            new_stats.append(ss)
            new_noise.append(np.bincount(sl[inside], weights=sig[inside], minlength=ns)[1:] / ss[:, cv2.CC_STAT_AREA])
            parent.append(np.full(ns - 1, c))
            n += ns - 1
        stats[c, cv2.CC_STAT_AREA] = 0  # no longer a blob: fails every test
    return (np.concatenate(new_stats), (np.concatenate(new_noise) if new_noise else np.zeros(0)),
            (np.concatenate(parent) if parent else np.zeros(0, dtype=np.int64)), np.asarray(undone, dtype=np.int64))
