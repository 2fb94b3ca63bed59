"""Which way an image's dots go (bright on a dark ground, or dark on a light one), and how sure that choice is.

:func:`choose_polarity` decides ``DetectionOptions(polarity="auto")`` per image. It used to count the compact
blobs of either polarity on 4x and 8x reduced copies; on real photographs of dark dots on white paper that count is
won by the wrong side when the paper is over-exposed (the clipped gaps between the dots pass as bright blobs) or
textured (an enlarged copy's paper grain), and the detector then reported hundreds of "dots" and none of the real
ones. A dot stands out from the ground around it: its level is far from the local median (the ground is most of
the pixels around a dot), by about the contrast the image's strongest dots have. The gaps between dark dots sit at
the paper's own level, paper grain a few grey levels off it. So only blobs whose peak stands above their local
median by at least half the contrast of the image's strongest blobs (of either polarity) count, on copies reduced
2x (dots of 3-50 px), 4x and 8x. When the two counts are close (the smaller at least half the larger), the larger
is below :data:`MIN_BLOBS`, or no blob of either polarity stands out, the choice is said to be ambiguous
(``PolarityChoice.ambiguous``, with why): ``cell detect`` says so and a camera file or ``--polarity`` settles it.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["PolarityChoice", "choose_polarity", "AMBIGUOUS_RATIO", "MIN_BLOBS", "STAND_OUT"]

#: the smaller polarity's count of standing-out blobs over the larger's from which the choice is ambiguous
AMBIGUOUS_RATIO = 0.5
#: a blob stands out when its peak is above its local median by this share of the strongest blobs' contrast
STAND_OUT = 0.5
#: fewer standing-out blobs than this in the winning polarity: too little to go by (ambiguous)
MIN_BLOBS = 5
#: reductions surveyed (a 2x copy sees dots of 3-50 px, 4x 6-100 px, 8x up to 200 px)
SCALES = (2, 4, 8)


@dataclass(frozen=True)
class PolarityChoice:
    """The polarity chosen for one image.

    Attributes:
        polarity: "bright" or "dark".
        counts: {"bright": n, "dark": n}: blobs that stand out from their ground, summed over the reduced copies.
        contrast: the strongest blobs' contrast the test used (grey levels of the image, the 90th percentile of
            either polarity's blobs' peak above their local median; 0 when no blob was found).
        ambiguous: True when the counts do not separate the two (see :data:`AMBIGUOUS_RATIO`) or none stands out.
        note: one line saying how the choice was made (and why it is ambiguous).
    """

    polarity: str
    counts: dict
    contrast: float
    ambiguous: bool
    note: str

    def as_dict(self) -> dict:
        return {"polarity": self.polarity, "counts": dict(self.counts), "contrast": self.contrast,
                "ambiguous": self.ambiguous, "note": self.note}


def _blob_contrasts(image: np.ndarray, s: int, threshold_sigma: float) -> np.ndarray:
    """The compact blobs of a polarised ``image`` (dots bright) on a copy reduced ``s`` times: each one's peak above
    the median of the ground around it (a window of 31 reduced pixels), grey levels; (n,)."""
    from calibration.dots import _noise

    h, w = image.shape[0] // s, image.shape[1] // s
    if min(h, w) < 8:
        return np.zeros(0)
    small = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    kern = cv2.getStructuringElement(cv2.MORPH_RECT, (31, 31))
    th = cv2.morphologyEx(small, cv2.MORPH_TOPHAT, kern)
    noise = max(_noise(th, 2), _noise(small, 2))
    locmax = cv2.dilate(th, cv2.getStructuringElement(cv2.MORPH_RECT, (9, 9)))
    mask = ((th > threshold_sigma * noise) & (th.astype(np.float32) > 0.5 * locmax)).astype(np.uint8)
    n, lab, st, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return np.zeros(0)
    bw, bh, a = st[1:, 2].astype(float), st[1:, 3].astype(float), st[1:, 4].astype(float)
    ok = (a >= 2) & (np.maximum(bw, bh) <= 2.0 * np.minimum(bw, bh)) & (a >= 0.5 * bw * bh) & (bw < 25) & (bh < 25)
    if not np.any(ok):
        return np.zeros(0)
    # the ground's level: the median over a window several dots wide (the ground is most of its pixels), taken on a
    # copy reduced 4x more (cheap) and read at each blob's peak
    f = 4
    tiny = cv2.resize(small, (max(w // f, 1), max(h // f, 1)), interpolation=cv2.INTER_AREA).astype(np.float32)
    ground = _median_filter(tiny, 7)
    # each blob's peak and where it is, from the blobs' own pixels (a few per cent of the image)
    px = np.flatnonzero(lab.ravel())
    li, v = lab.ravel()[px], small.ravel()[px].astype(np.float64)
    order = np.lexsort((-v, li))
    first = order[np.flatnonzero(np.r_[True, np.diff(li[order]) != 0])]  # per label 1..n-1, its brightest pixel
    first = first[ok[li[first] - 1]]
    peak = v[first]
    pos = np.stack(np.divmod(px[first], w), axis=1)
    gy = np.clip(pos[:, 0] // f, 0, ground.shape[0] - 1)
    gx = np.clip(pos[:, 1] // f, 0, ground.shape[1] - 1)
    return peak - ground[gy, gx]


def _median_filter(img: np.ndarray, k: int) -> np.ndarray:
    """Median over a ``k`` x ``k`` window (edges replicated) of a small float image."""
    from scipy.ndimage import median_filter

    return median_filter(img, size=k, mode="nearest")


def choose_polarity(grey: np.ndarray, threshold_sigma: float = 8.0) -> PolarityChoice:
    """The polarity of ``grey`` ((h, w) uint8/uint16) by its blobs that stand out from their ground (module doc)."""
    inverted = cv2.bitwise_not(grey)
    c = {p: [_blob_contrasts(grey if p == "bright" else inverted, s, threshold_sigma) for s in SCALES]
         for p in ("bright", "dark")}
    allc = {p: np.concatenate(v) for p, v in c.items()}
    ref = max((float(np.percentile(v, 90)) for v in allc.values() if len(v)), default=0.0)
    counts = {p: int(np.sum(v >= STAND_OUT * ref)) if ref > 0 else 0 for p, v in allc.items()}
    hi, lo = ("bright", "dark") if counts["bright"] >= counts["dark"] else ("dark", "bright")
    if counts[hi] == 0:
        # nothing stands out either way: the plain count of compact blobs (the old rule) decides, said as a guess
        raw = {p: len(v) for p, v in allc.items()}
        hi = "bright" if raw["bright"] >= raw["dark"] else "dark"
        return PolarityChoice(hi, counts, ref, True, f"no blob stands out from its ground in either polarity; "
                              f"{hi} taken by the count of compact blobs ({raw['bright']} bright, {raw['dark']} dark)")
    ambiguous = counts[lo] >= AMBIGUOUS_RATIO * counts[hi] or counts[hi] < MIN_BLOBS
    note = (f"{counts[hi]} {hi} blobs stand out from their ground by >= {STAND_OUT * ref:.0f} grey levels against "
            f"{counts[lo]} {lo}")
    if counts[hi] < MIN_BLOBS:
        note += f": too few to tell (fewer than {MIN_BLOBS}); set the polarity if {hi} is wrong"
    elif ambiguous:
        note += f": too close to tell (ambiguous at >= {AMBIGUOUS_RATIO:.0%}); set the polarity if {hi} is wrong"
    return PolarityChoice(hi, counts, ref, bool(ambiguous), note)
