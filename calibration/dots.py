"""Sub-pixel centres of circular dots in real and rendered images, with each centre's covariance.

:func:`detect_dots` takes a grey or colour image (uint8, or uint16 holding 10-16 bits), bright
dots on a dark background (retro-reflective targets lit by a ring flash) or dark dots on a light
one (a printed sheet); ``polarity="auto"`` decides per image (:mod:`calibration.polarity`); a 4x
reduced copy gives the typical dot size that the background kernel then adapts to.

1. The background is removed by a top-hat (image minus its morphological opening) with a square
   kernel larger than the dots; the noise is the MAD of differences of pixels two apart.
2. Blobs: pixels above ``max(threshold_sigma * noise, local_fraction * local maximum)``. The
   second term is a local half-maximum (the top-hat dilated over ``local_window`` pixels): on a
   compressed JPEG the noise estimate is tiny (0.6 grey levels) and a pure noise threshold
   bridges a dot to its neighbour through their blurred skirts; half the local peak does not.
3. Blobs are filtered by shape (bounding-box aspect, fill) and by size relative to the image's
   dots: no fixed pixel counts unless given. The noise of a lit surface is 2-3 times the image's
   figure and joins its dots to blobs that are no dot (lost) or pass as one with a wrong centre:
   with the automatic threshold such blobs are split again at the noise of their own background
   (:mod:`calibration.dot_split`, decision 0039); what the first pass found otherwise stays as it is.
4. Centre: the intensity-weighted centroid of the blob grown by a margin, over a plane fitted to
   a ring of background pixels around it, each pixel weighted by the dot's share of it
   (decision 0007), or (``centre="ellipse"``) an ellipse fitted to the blob's sub-pixel
   half-level contour. Decision 0015 compares both on tilted, blurred renders. The default
   ``centre="auto"`` fits the ellipse to the dots whose intensities mislead the centroid (clipped
   pixels; a ring whose background is not the plane) and keeps the centroid for the others
   (decision 0037); ``for_real_images`` keeps the centroid.
5. ``cov``: each centre's 2x2 covariance in px^2 propagated from the pixel noise (the centroid is
   linear in the grey levels), each pixel with its own noise (a line in the grey level measured on the
   dots' tops and rings: photon noise grows with the light), and from the background plane's own error
   (its ring's noise), plus ``cov_floor_px^2`` on the diagonal (decision 0047).
6. ``background_cov``: what a background that is not the fitted plane does to the centre (an edge of
   the part or a step of its shading near the dot; docs/decisions/0023): the ring's residuals about
   the plane have a smooth part (the misfit, significant at 3 standard errors of the pixel noise) and
   a misfit ``e`` of one sign over each half of the dot moves the centroid by ``e sum|(x_i - u) . a|
   / (span_i sum w)`` along a direction ``a``: that bound along the dot's two principal axes, px^2.
   ``ring_px`` says how many ring pixels carried the plane and the test: below :data:`MIN_RING_PX`
   there is neither, and a zero bound means "not measured", not "a plane" (decision 0030).

Pixel convention: origin at the centre of the top-left pixel (OpenCV's too).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from calibration.dot_noise import NOISE_DOTS, noise_levels, plane_cov
from calibration.errors import CalibrationError

__all__ = ["DetectionOptions", "Detections", "to_grey", "detect_dots", "detect_retro_targets", "POLARITIES"]

POLARITIES = ("auto", "bright", "dark")
CENTRES = ("auto", "centroid", "ellipse")


@dataclass(frozen=True)
class DetectionOptions:
    """Dot detection.

    Attributes:
        polarity: "bright" (light dots on a dark ground), "dark" (dark dots on a light ground) or
            "auto" (decided per image).
        threshold_sigma: blob threshold = this many noise standard deviations above the local background
            (ignored when ``threshold`` is given).
        threshold: absolute threshold on the top-hat in grey levels, or None for automatic.
        local_fraction: a pixel also has to exceed this fraction of the largest top-hat value within
            ``local_window`` pixels (a local half-maximum that separates neighbours); 0 disables it.
        local_window: side (px) of that window, or 0 for automatic (the typical dot diameter + 3).
        min_area_px: smallest blob (pixels above threshold).
        max_area_px: largest blob, or None for automatic (what the background kernel can hold).
        max_aspect: largest bounding-box aspect ratio (elongated blobs are edges or glints).
        min_fill: smallest fraction of the bounding box covered by the blob.
        margin_px: the blob is grown by this many pixels for the centroid.
        min_peak_snr: smallest (peak - background) / noise.
        subsample: stride of the subsample used for background and noise.
        background_kernel_px: side of the square opening that estimates the local background, larger
            than the largest dot; 0 for automatic (from the dots of a 4x reduced copy); -1 for one
            global level (a dark, uniform scene).
        centre: "centroid" (intensity-weighted, decision 0007) or "ellipse" (ellipse fit to the half-level contour).
        cov_floor_px: added in quadrature to each centre's standard deviation (what noise propagation does
            not see: print, blur, compression); pixels.
        outline: fit every dot's half-level contour (not only the dots centred by it) for its outline's misfit and
            the centroid's check against it (``Detections.outline``, ``centroid_shift``; decision 0051). The cell's
            MEASURE turns it on; it costs about half the detection's time again (``benchmarks.bench_detection``).
    """

    polarity: str = "bright"
    threshold_sigma: float = 8.0
    threshold: float | None = None
    local_fraction: float = 0.0
    local_window: int = 0
    min_area_px: int = 4
    max_area_px: int | None = 5000
    max_aspect: float = 3.0
    min_fill: float = 0.4
    margin_px: int = 2
    min_peak_snr: float = 10.0
    subsample: int = 7
    background_kernel_px: int = 41
    centre: str = "auto"
    cov_floor_px: float = 0.005
    outline: bool = False

    def __post_init__(self) -> None:
        if self.polarity not in POLARITIES:
            raise CalibrationError(f"detection polarity must be one of {POLARITIES}, got {self.polarity!r}")
        if self.centre not in CENTRES:
            raise CalibrationError(f"detection centre must be one of {CENTRES}, got {self.centre!r}")

    @classmethod
    def for_real_images(cls, **kw) -> "DetectionOptions":
        """Defaults for photographs of unknown make: polarity, kernel and size limits from the image."""
        # the centroid everywhere: what the real-image benchmarks validated (decision 0015)
        base = dict(polarity="auto", local_fraction=0.5, max_area_px=None, background_kernel_px=0, cov_floor_px=0.01,
                    centre="centroid")
        base.update(kw)
        return cls(**base)


@dataclass(frozen=True)
class Detections:
    """Detected dots.

    Attributes:
        uv: (k, 2) sub-pixel centres (px, origin at the centre of the top-left pixel).
        cov: (k, 2, 2) covariance of each centre in px^2 (each pixel's noise and the background plane's error
            propagated + ``cov_floor_px^2``).
        area_px: (k,) pixels above threshold.
        peak: (k,) peak contrast above (bright) or below (dark) the local background, grey levels.
        flux: (k,) summed background-subtracted grey levels over the grown blob.
        background: (k,) local background grey level (of the polarised image).
        noise: global noise standard deviation (grey levels).
        polarity: "bright" or "dark": what these dots are.
        axes: (k, 2, 2) each blob's second-moment matrix (px^2) over its grown pixels: the dot's
            ellipse is ``x^T axes^-1 x = 4`` about the centre (for a uniform disc of radius r, r^2/4 I).
        background_cov: (k, 2, 2) bound of the centre's error from a local background that is not a
            plane (px^2; zero where the ring shows no significant misfit), or None.
        saturated: (k,) pixels of each dot at the sensor's ceiling (clipped: the dot's profile is cut flat and
            its centre errs by what no noise model states; decision 0029), or None.
        ring_px: (k,) int ring pixels the background plane and the misfit test used; below
            :data:`MIN_RING_PX` the bound could not be measured (it is zero then, not known), or None.
        noise_levels: ``(v0, s)``: a pixel's noise variance at grey level ``v`` is ``v0 + s v`` (grey levels^2; photon
            noise grows with the light), measured on the dots' own plateaus and background rings
            (:func:`calibration.dot_noise.noise_levels`); what ``cov`` propagated. None: not measured.
        ellipse: (k,) bool, the centre is the ellipse fitted to the dot's half-level contour (``centre="ellipse"``,
            or ``"auto"`` for a clipped dot or one with a background misfit; decision 0037), not the centroid; or None.
        clip_bound: (k, 2) px, how far a clipped dot's centre may be off for its unknown level: its contour must
            follow the ground behind the dot with a slope between 0.5 (just clipped) and 1 (far over the ceiling), the
            centre is the middle of the centres at those two and this is half their difference (decision 0050); zero
            for a dot not clipped, not centred by its ellipse, or whose second contour could not be fitted (its centre
            then the one at 0.5; ADJUST counts and says such dots); or None.
        outline: (k, 4) each dot's half-level contour about its fitted ellipse, ``[chi2, n, rms_px, stray]``
            (:func:`calibration.ellipse_fit.contour_ellipse_centres`): an ellipse's image leaves ``chi2`` about
            ``n - 5``, a chipped edge more (decision 0051); NaN where the contour could not be fitted; None when
            ``DetectionOptions.outline`` is off.
        centroid_shift, centroid_shift_cov: (k, 2) px and (k, 2, 2) px^2, a centroid dot's centre less its contour's
            ellipse centre, and the sum of their covariances: the two agree on an ellipse's image, a speck on the dot
            moves the centroid only (decision 0051); NaN for a dot centred by its ellipse or not fitted; or None.
    """

    uv: np.ndarray
    area_px: np.ndarray
    peak: np.ndarray
    flux: np.ndarray
    background: np.ndarray
    noise: float
    cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    polarity: str = "bright"
    axes: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    background_cov: np.ndarray | None = None
    saturated: np.ndarray | None = None
    ring_px: np.ndarray | None = None
    ellipse: np.ndarray | None = None
    noise_levels: tuple[float, float] | None = None
    clip_bound: np.ndarray | None = None
    outline: np.ndarray | None = None
    centroid_shift: np.ndarray | None = None
    centroid_shift_cov: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.uv)

    def subset(self, keep: np.ndarray) -> "Detections":
        """These detections restricted to ``keep`` (bool mask or indices)."""
        return replace(self, uv=self.uv[keep], area_px=self.area_px[keep], peak=self.peak[keep], flux=self.flux[keep],
                       background=self.background[keep], cov=self.cov[keep], axes=self.axes[keep],
                       background_cov=None if self.background_cov is None else self.background_cov[keep],
                       saturated=None if self.saturated is None else self.saturated[keep],
                       ring_px=None if self.ring_px is None else self.ring_px[keep],
                       ellipse=None if self.ellipse is None else self.ellipse[keep],
                       clip_bound=None if self.clip_bound is None else self.clip_bound[keep],
                       outline=None if self.outline is None else self.outline[keep],
                       centroid_shift=None if self.centroid_shift is None else self.centroid_shift[keep],
                       centroid_shift_cov=None if self.centroid_shift_cov is None else self.centroid_shift_cov[keep])


def to_grey(image: np.ndarray) -> np.ndarray:
    """A (h, w) uint8/uint16 grey image from grey or colour (h, w, 3|4, OpenCV's BGR order) input."""
    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16):
        raise CalibrationError(f"target detection needs a uint8 or uint16 image, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    elif image.ndim == 3 and image.shape[2] in (3, 4):
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if image.ndim != 2 or min(image.shape) < 8:
        raise CalibrationError(f"target detection needs a (h, w) grey or (h, w, 3) colour image, got {image.shape}")
    return np.ascontiguousarray(image)


def _invert(image: np.ndarray) -> np.ndarray:
    return cv2.bitwise_not(image)


def _ceiling(image: np.ndarray) -> float:
    """The grey level at which ``image``'s sensor clips: 255 for 8 bits; for 16-bit containers the all-ones code of
    the bit depth the image reaches (10, 12, 14 or 16 bits), so a 12-bit image clips at 4095. A camera that puts
    its 12 bits in the high bits of the word (clipping at 65520) is not recognised: its clipped pixels are not counted
    (GenICam's Mono12 / Mono16 are low-aligned)."""
    if image.dtype == np.uint8:
        return 255.0
    top = int(image.max())
    for bits in (10, 12, 14, 16):
        if top <= (1 << bits) - 1:
            return float((1 << bits) - 1)
    return 65535.0


def _noise(image: np.ndarray, stride: int) -> float:
    """Pixel noise standard deviation: MAD of differences of pixels two apart along every ``stride``-th row.

    Large bright areas and smooth shading do not count as noise, as they would in the spread of the
    grey levels themselves. The differences are integers: both medians are exact order statistics read
    from one histogram of them (what ``np.median`` gives, without two partitions of the data).
    """
    rows = image[::stride]
    if rows.dtype == np.uint8:  # differences + 255 in 0..510: OpenCV's histogram
        d = cv2.subtract(rows[:, 2:], rows[:, :-2], dtype=cv2.CV_16S)
        shifted = cv2.add(d, 255, dtype=cv2.CV_16U)
        counts = cv2.calcHist([shifted], [0], None, [511], [0, 511]).ravel().astype(np.int64)
        values = np.arange(-255, 256)
    else:
        d = rows[:, 2:].astype(np.int32) - rows[:, :-2]
        lo = int(d.min())
        counts = np.bincount((d - lo).ravel())
        values = lo + np.arange(len(counts))
    med2 = _twice_median(values, counts)  # 2 x median: an integer
    # median |d - median(d)| from the histogram of |2 d - 2 median|
    mad = 0.25 * _twice_median(np.arange(int(np.abs(2 * values - med2).max()) + 1),
                               np.bincount(np.abs(2 * values - med2), weights=counts).astype(np.int64))
    noise = 1.4826 * mad / np.sqrt(2.0)
    if noise == 0.0:  # quantised, nearly noise-free (or clipped at black): the spread of the small differences
        d = np.asarray(d, dtype=np.int32).ravel()
        small = d[np.abs(d) <= 3].astype(np.float32)
        noise = float(np.std(small)) / np.sqrt(2.0) if len(small) > 1 else 1.0
    return max(noise, 0.5)


def _twice_median(values: np.ndarray, counts: np.ndarray) -> int:
    """2 x the median of integers given as a histogram: ``counts[i]`` times ``values[i]`` (increasing), exactly."""
    cs = np.cumsum(counts)
    n = int(cs[-1])
    upper = int(values[np.searchsorted(cs, n // 2 + 1)])  # the element of rank n // 2 (from 0)
    if n % 2:
        return 2 * upper
    return int(values[np.searchsorted(cs, n // 2)]) + upper


def _survey(image: np.ndarray, o: DetectionOptions) -> tuple[int, float, float]:
    """(compact blobs found, their median and 95th-percentile diameters in px) on copies of a polarised image
    reduced 4x (dots of 3-100 px) and 8x (up to 200 px)."""
    n4, d4, big4 = _survey_at(image, o, 4)
    n8, _, big8 = _survey_at(image, o, 8)
    return n4 + n8, d4, max(big4, big8)


def _survey_at(image: np.ndarray, o: DetectionOptions, s: int) -> tuple[int, float, float]:
    small = cv2.resize(image, (image.shape[1] // s, image.shape[0] // s), interpolation=cv2.INTER_AREA)
    kern = cv2.getStructuringElement(cv2.MORPH_RECT, (31, 31))
    th = cv2.morphologyEx(small, cv2.MORPH_TOPHAT, kern)
    noise = max(_noise(th, 2), _noise(small, 2))
    locmax = cv2.dilate(th, cv2.getStructuringElement(cv2.MORPH_RECT, (9, 9)))
    mask = ((th > o.threshold_sigma * noise) & (th.astype(np.float32) > 0.5 * locmax)).astype(np.uint8)
    n, _, st, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return 0, 0.0, 0.0
    w, h, a = st[1:, 2].astype(float), st[1:, 3].astype(float), st[1:, 4].astype(float)
    ok = (a >= 2) & (np.maximum(w, h) <= 2.0 * np.minimum(w, h)) & (a >= 0.5 * w * h) & (w < 25) & (h < 25)
    if not np.any(ok):
        return 0, 0.0, 0.0
    d = np.sqrt(4 * a[ok] / np.pi) * s
    return int(ok.sum()), float(np.median(d)), float(np.percentile(d, 95))


def _tophat(image: np.ndarray, kernel: int) -> np.ndarray:
    """White top-hat with a square ``kernel``; beyond 61 px the opening is taken on a reduced copy (its cost
    grows with the kernel) and enlarged again: it only has to be the smooth ground under the dots."""
    if kernel <= 61:
        return cv2.morphologyEx(image, cv2.MORPH_TOPHAT, cv2.getStructuringElement(cv2.MORPH_RECT, (kernel, kernel)))
    s = int(np.ceil(kernel / 41))
    small = cv2.resize(image, (max(image.shape[1] // s, 1), max(image.shape[0] // s, 1)), interpolation=cv2.INTER_AREA)
    k = 2 * (kernel // (2 * s)) + 1
    opened = cv2.morphologyEx(small, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    # the reduced opening can sit above a dark pixel's own level: the top-hat never goes below zero
    return cv2.subtract(image, cv2.resize(opened, (image.shape[1], image.shape[0]), interpolation=cv2.INTER_LINEAR))


#: ring pixels needed for a background plane and its misfit test (fewer: no slope, and no bound can be measured)
MIN_RING_PX = 8


def _ring_planes(lab: np.ndarray, dx: np.ndarray, dy: np.ndarray, val: np.ndarray, k: int, fallback: float,
                 normal: bool = False):
    """Least-squares plane ``b0 + gx dx + gy dy`` through the ring pixels of each of ``k`` blobs.

    ``lab`` (1..k) names the blob of each ring pixel at offset ``(dx, dy)`` from the blob's centre.
    Returns (k, 3) ``(b0, gx, gy)``; a blob whose ring cannot carry a plane gets its mean (or
    ``fallback`` without ring pixels) and no slope. ``normal``: also the (k, 3, 3) normal matrices ``A^T A``.
    """
    def s(w):
        return np.bincount(lab, weights=w, minlength=k + 1)[1:]

    n = s(np.ones_like(dx, dtype=float))
    A = np.empty((k, 3, 3))
    A[:, 0, 0] = n
    A[:, 0, 1] = A[:, 1, 0] = s(dx)
    A[:, 0, 2] = A[:, 2, 0] = s(dy)
    A[:, 1, 1] = s(dx * dx)
    A[:, 1, 2] = A[:, 2, 1] = s(dx * dy)
    A[:, 2, 2] = s(dy * dy)
    b = np.stack([s(val), s(val * dx), s(val * dy)], axis=1)
    coef = np.zeros((k, 3))
    coef[:, 0] = np.where(n > 0, b[:, 0] / np.maximum(n, 1), fallback)
    ok = n >= MIN_RING_PX
    if np.any(ok):
        det = np.linalg.det(A[ok])
        good = np.flatnonzero(ok)[np.abs(det) > 1e-9 * np.maximum(n[ok], 1) ** 3]
        if len(good):
            coef[good] = np.linalg.solve(A[good], b[good][..., None])[..., 0]
    return (coef, A) if normal else coef


def _ring_fit(lab: np.ndarray, xs: np.ndarray, ys: np.ndarray, val: np.ndarray, xc: np.ndarray, yc: np.ndarray, k: int,
              fallback: float) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Each blob's background plane through its ring pixels ``lab`` (1..k) at ``(xs, ys)`` of grey ``val``, fitted
    twice (the second time without the pixels far off the first plane: an edge of the part, a neighbour's rim), and
    its misfit (:func:`_ring_misfit`): ((k, 3) plane, (k,) misfit, (the labels of the ring pixels that carried them,
    (k, 3, 3) their normal matrices)))."""
    rdx, rdy = xs - xc[lab - 1], ys - yc[lab - 1]
    coef = _ring_planes(lab, rdx, rdy, val, k, fallback)
    r = val - (coef[lab - 1, 0] + coef[lab - 1, 1] * rdx + coef[lab - 1, 2] * rdy)
    cnt = np.maximum(np.bincount(lab, minlength=k + 1)[1:], 1)
    rms = np.sqrt(np.bincount(lab, weights=r * r, minlength=k + 1)[1:] / cnt)
    fit = np.abs(r) <= 2.0 * rms[lab - 1] + 1.0
    coef, A = _ring_planes(lab[fit], rdx[fit], rdy[fit], val[fit], k, fallback, normal=True)
    lf, dxf, dyf = lab[fit], rdx[fit], rdy[fit]
    misfit = _ring_misfit(lf, dxf, dyf, val[fit] - (coef[lf - 1, 0] + coef[lf - 1, 1] * dxf + coef[lf - 1, 2] * dyf), k)
    return coef, misfit, (lf, A)


def _ring_misfit(lab: np.ndarray, dx: np.ndarray, dy: np.ndarray, r: np.ndarray, k: int, z: float = 3.0) -> np.ndarray:
    """The smooth part of each ring's residuals ``r`` about its background plane, (k,) grey levels.

    The mean square of the residuals is the pixel noise plus the misfit; neighbours along the ring
    share the misfit but not the noise, so half the mean square of their differences is the noise
    alone, where the dot is: misfit^2 = ms(r) - ms(diff) / 2, which is the mean product of neighbours
    (the ring's lag-one autocovariance). For white noise of variance s^2 over n ring pixels those n
    products are uncorrelated, each of variance s^4: the estimate scatters by s^2 / sqrt(n), and a misfit
    below ``z`` times that cannot be told from the noise and is 0.
    """
    order = np.lexsort((np.arctan2(dy, dx), lab))
    lo, ro = lab[order], r[order]
    same = lo[1:] == lo[:-1]
    n_d = np.bincount(lo[1:], weights=same.astype(float), minlength=k + 1)[1:]
    noise2 = 0.5 * np.bincount(lo[1:], weights=np.where(same, np.diff(ro) ** 2, 0.0), minlength=k + 1)[1:]
    noise2 /= np.maximum(n_d, 1)
    n = np.bincount(lab, minlength=k + 1)[1:]
    excess = np.bincount(lab, weights=r * r, minlength=k + 1)[1:] / np.maximum(n, 1) - noise2
    significant = (n >= MIN_RING_PX) & (excess > z * noise2 / np.sqrt(np.maximum(n, 1)))
    return np.where(significant, np.sqrt(np.maximum(excess, 0.0)), 0.0)


def _above(image: np.ndarray, thr: float) -> np.ndarray:
    """(h, w) uint8 1 where the integer ``image`` exceeds ``thr`` (any real), 0 elsewhere."""
    if image.dtype == np.uint8:
        return cv2.threshold(image, thr, 1, cv2.THRESH_BINARY)[1]  # x > floor(thr): x > thr for integers
    return (image > int(np.floor(thr))).view(np.uint8)


def _components(mask: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """``cv2.connectedComponentsWithStats(mask, 8-connectivity)``: (n, (H, W) int32 labels, (n, 5) stats).

    Labelled on the rows and columns that hold a blob pixel only (issue 21: dots cover a few per cent of
    an image; labelling costs per pixel): empty rows and columns are dropped, one empty pair kept between
    runs so that no two blobs touch, in aligned pairs so that OpenCV's 2 x 2 block scan numbers the blobs
    as it does on the whole image. Labels and stats are those of the whole image.
    """
    H, W = mask.shape
    ri = _busy_pairs(cv2.reduce(mask, 1, cv2.REDUCE_MAX).ravel() > 0)
    ci = _busy_pairs(mask.max(axis=0) > 0)
    if len(ri) == 0:  # no blob at all
        return 1, np.zeros((H, W), dtype=np.int32), np.array([[0, 0, W, H, H * W]], dtype=np.int32)
    if len(ri) * len(ci) > 0.6 * H * W:
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8, ltype=cv2.CV_32S)
        return n, labels, stats
    n, lc, sc, _ = cv2.connectedComponentsWithStats(mask[ri][:, ci], connectivity=8, ltype=cv2.CV_32S)
    labels = np.zeros((H, W), dtype=np.int32)
    labels[np.ix_(ri, ci)] = lc
    stats = sc.copy()
    if n > 1:
        L, T, Wc, Hc = (sc[1:, i] for i in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
        stats[1:, cv2.CC_STAT_LEFT], stats[1:, cv2.CC_STAT_TOP] = ci[L], ri[T]
        stats[1:, cv2.CC_STAT_WIDTH] = ci[L + Wc - 1] - ci[L] + 1
        stats[1:, cv2.CC_STAT_HEIGHT] = ri[T + Hc - 1] - ri[T] + 1
    stats[0] = (0, 0, W, H, H * W - int(stats[1:, cv2.CC_STAT_AREA].sum()))
    return n, labels, stats



def _blob_tests(stats: np.ndarray, o: DetectionOptions, max_area: float, shape: tuple[int, int]
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per component 1..n-1 of ``stats``: (size and shape of a dot: area, bounding-box aspect and fill; clear of the
    image border by the margin, so that the centroid's window is whole)."""
    w_box = stats[1:, cv2.CC_STAT_WIDTH].astype(float)
    h_box = stats[1:, cv2.CC_STAT_HEIGHT].astype(float)
    area = stats[1:, cv2.CC_STAT_AREA].astype(float)
    compact = ((area >= o.min_area_px) & (area <= max_area)
               & (np.maximum(w_box, h_box) / np.minimum(w_box, h_box) <= o.max_aspect)
               & (area / (w_box * h_box) >= o.min_fill))
    x0, y0 = stats[1:, cv2.CC_STAT_LEFT], stats[1:, cv2.CC_STAT_TOP]
    H, W = shape
    m = o.margin_px
    clear = (x0 - m - 1 >= 0) & (y0 - m - 1 >= 0) & (x0 + w_box + m + 1 <= W) & (y0 + h_box + m + 1 <= H)
    return compact, clear


def _busy_pairs(busy: np.ndarray) -> np.ndarray:
    """Indices of the aligned pairs (2i, 2i+1) with a busy member, and of the pair after each run of them."""
    n = len(busy)
    b = np.zeros(n + n % 2, dtype=bool)
    b[:n] = busy
    pair = b.reshape(-1, 2).any(axis=1)
    pair[1:] |= pair[:-1].copy()
    return np.flatnonzero(np.repeat(pair, 2)[:n])


def _bucket(n: np.ndarray) -> np.ndarray:
    """Sizes ``n`` (px, >= 1) rounded up to a multiple of 8, or of a quarter of their power of two above 32."""
    n = np.asarray(n, dtype=np.int64)
    q = 2 ** np.maximum(np.floor(np.log2(np.maximum(n, 1))).astype(np.int64) - 2, 3)
    return q * -(-n // q)


def _grown_blobs(labels: np.ndarray, remap: np.ndarray, x0: np.ndarray, y0: np.ndarray, w: np.ndarray, h: np.ndarray,
                 m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pixels of the kept blobs grown by ``m`` and of a ring 2 px further out, with their labels.

    Exactly what dilating the whole relabelled image ``remap[labels]`` with discs of diameter ``2 m + 1``
    (``grown``) and ``2 m + 5`` (``outer``) and taking its non-zero pixels gives, but computed in windows
    around the kept blobs only (issue 21: the two full-image dilations were the detector's hot spot): a
    window holds the blob's box grown by ``r = m + 2`` (where its ``outer`` label can reach) plus ``r`` of
    context, so the dilation inside it sees every pixel it would see in the whole image. Windows of one
    size are stacked into one tall image and dilated together; a window's rows near its neighbours in the
    stack are never read.

    Args:
        labels: (H, W) int32 component labels; ``remap`` (n_lab,) float32 maps them to 1..k (0: dropped).
        x0, y0, w, h: (k,) the kept blobs' boxes (px), in the order of their new labels.
    Returns:
        ys, xs: (p,) pixels whose ``outer`` label is > 0, window by window (each blob's in raster order);
        lo, lg: (p,) int64 their ``outer`` and ``grown`` labels.
    """
    H, W = labels.shape
    r = m + 2
    pad = 2 * r
    k1 = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * m + 1, 2 * m + 1))
    k2 = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    x0, y0, w, h = (np.asarray(a, dtype=np.int64) for a in (x0, y0, w, h))
    # window sizes rounded up (to 8 px, or a quarter of their octave: few groups of sizes), at most the image;
    # windows shifted into the image, whose own edge is the dilation's border as it is for the whole image
    bw = np.minimum(_bucket(w + 2 * pad), W)
    bh = np.minimum(_bucket(h + 2 * pad), H)
    wx = np.clip(x0 - pad, 0, W - bw)
    wy = np.clip(y0 - pad, 0, H - bh)
    small = remap.max() < 65536  # uint16 labels dilate faster than float32 ones
    table = remap.astype(np.uint16) if small else remap
    own = np.arange(1, len(x0) + 1).astype(table.dtype)
    out: list[tuple[np.ndarray, ...]] = []
    order = np.lexsort((bh, bw))
    cuts = np.flatnonzero((np.diff(bw[order]) != 0) | (np.diff(bh[order]) != 0)) + 1
    for g in np.split(order, cuts):
        gw, gh = int(bw[g[0]]), int(bh[g[0]])
        win = table[np.lib.stride_tricks.sliding_window_view(labels, (gh, gw))[wy[g], wx[g]]]  # (n, gh, gw)
        stack = win.reshape(-1, gw)
        grown = cv2.dilate(stack, k1).reshape(win.shape)
        outer = cv2.dilate(stack, k2).reshape(win.shape)
        # the part of each window that is exact: the blob's box grown by r (its outer label reaches no further)
        ry, rx = y0[g] - r - wy[g], x0[g] - r - wx[g]
        rows = (np.arange(gh) >= ry[:, None]) & (np.arange(gh) < (ry + h[g] + 2 * r)[:, None])
        cols = (np.arange(gw) >= rx[:, None]) & (np.arange(gw) < (rx + w[g] + 2 * r)[:, None])
        sel = (outer == own[g][:, None, None]) & rows[:, :, None] & cols[:, None, :]
        i, yy, xx = np.nonzero(sel)
        out.append((g[i], wy[g][i] + yy, wx[g][i] + xx, grown[i, yy, xx]))
    blob, ys, xs, lg = (np.concatenate(a) for a in zip(*out))
    return ys, xs, blob + 1, lg.astype(np.int64)


def detect_dots(image: np.ndarray, options: DetectionOptions | None = None, labels: np.ndarray | None = None) -> Detections:
    """Sub-pixel centres and covariances of the dots in ``image`` (grey or colour, uint8/uint16).

    ``labels``: an (h, w) integer image of the surface each pixel sees (``cell.stages.surface_labels``: >= 1 a
    surface, 0 unknown, < 0 near a change of surface). A dot's surface is the label at its centre pixel; when it
    is >= 1, ring pixels of any other non-zero label are left out of its background plane and misfit test and
    margin pixels (grown, below threshold) of another surface get no weight in its centroid (decision 0035).
    None: the background is fitted to every ring pixel."""
    o = options or DetectionOptions()
    grey = to_grey(image)
    if labels is not None and np.shape(labels) != grey.shape:
        raise CalibrationError(f"detect_dots: surface labels of shape {np.shape(labels)} for an image of {grey.shape}")
    polarity, kernel, window = o.polarity, o.background_kernel_px, o.local_window
    if polarity == "auto" or kernel == 0 or (window == 0 and o.local_fraction > 0):
        if polarity == "auto":  # by the blobs that stand out from their ground, not by a plain count of blobs
            from calibration.polarity import choose_polarity
            polarity = choose_polarity(grey, o.threshold_sigma).polarity
        _, d, d_big = _survey(grey if polarity == "bright" else _invert(grey), o)  # the dots' sizes
        if kernel == 0:  # holds the largest dots
            kernel = 41 if d == 0 else int(np.clip(2 * round(0.75 * d_big + 5) + 1, 15, 401))
        if window == 0:
            # reaches a dot's own peak from its rim, not a neighbour's: a dim dot is not cut by a bright one
            window = 9 if d == 0 else int(2 * round(0.5 * d + 1.5) + 1)
    work = grey if polarity == "bright" else _invert(grey)
    o = replace(o, polarity=polarity, background_kernel_px=kernel, local_window=max(window, 3))
    return _detect(work, o, labels)


def detect_retro_targets(image: np.ndarray, options: DetectionOptions | None = None,
                         labels: np.ndarray | None = None) -> Detections:
    """Sub-pixel centres of bright dots in ``image: (h, w) uint8/uint16`` (the simulated cell's images)."""
    o = options or DetectionOptions()
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise CalibrationError(
            f"target detection needs a (h, w) uint8 or uint16 grey image, got {image.shape} {image.dtype}"
        )
    return detect_dots(image, o, labels)


#: a dot's background is fitted on its own surface only when that keeps this share of its ring: with less, the plane
#: is extrapolated across the dot from one side (an oblique dot along an edge) and errs more than the whole ring's
#: (decision 0035: 0.5-0.6 kept, worse in 88 % of the dots; 0.6-0.7 even; 0.7-1 better in 69-79 %); such a dot
#: keeps its whole ring and the bound that ring's misfit gives
MASK_MIN_RING_SHARE = 0.6


def _own_surface(surface: np.ndarray, comp: np.ndarray, remap: np.ndarray, ys: np.ndarray, xs: np.ndarray,
                 lo: np.ndarray, lg: np.ndarray, xc: np.ndarray, yc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which of the grown blobs' pixels (:func:`_grown_blobs`) see another surface than their dot, by ``surface``.

    A blob's surface is the label at its centre pixel; when it is >= 1, a pixel of another non-zero label (another
    surface, or :data:`cell.stages.surface_labels.NO_USE` near a change of surface) is foreign, unless it is one of
    the blob's own pixels above threshold. A blob whose centre label is <= 0, or whose ring would keep less than
    :data:`MASK_MIN_RING_SHARE` of its pixels, has none.
    Returns (foreign ring pixels, foreign grown pixels), (p,) bool each.
    """
    H, W = surface.shape
    k = len(xc)
    own = surface[np.clip(np.round(yc), 0, H - 1).astype(np.int64), np.clip(np.round(xc), 0, W - 1).astype(np.int64)]
    s = surface[ys, xs]
    ring = lg == 0
    blob = np.where(ring, lo, lg)
    mine = own[blob - 1]
    other = (mine > 0) & (s != mine) & (s != 0)
    n_ring = np.bincount(lo[ring], minlength=k + 1)[1:]
    n_off = np.bincount(lo[ring & other], minlength=k + 1)[1:]
    masked = n_off <= (1.0 - MASK_MIN_RING_SHARE) * n_ring
    other &= masked[blob - 1]
    in_blob = remap[comp[ys, xs]] == blob
    return ring & other, ~ring & other & ~in_blob


def _symmetric(li: np.ndarray, xi: np.ndarray, yi: np.ndarray, v: np.ndarray, foreign: np.ndarray, k: int,
               shape: tuple[int, int]) -> np.ndarray:
    """Which grown pixels to keep so that each dot's centroid window stays point-symmetric: the foreign ones
    (another surface's light under the dot's skirt) and their mirror images about the dot's preliminary centre
    (the centroid of the others, rounded to half a pixel) are left out. Leaving out one side of a skirt alone would
    move the centroid away from it as surely as the other surface's light moves it towards it (decision 0035)."""
    H, W = shape
    w = np.where(foreign, 0.0, np.maximum(v, 0.0))
    sw = np.maximum(np.bincount(li, weights=w, minlength=k + 1), 1e-12)
    cx2 = np.round(2 * np.bincount(li, weights=w * xi, minlength=k + 1) / sw).astype(np.int64)
    cy2 = np.round(2 * np.bincount(li, weights=w * yi, minlength=k + 1) / sw).astype(np.int64)
    key = (li.astype(np.int64) * (2 * H) + yi + H) * (2 * W) + xi + W
    mirror = (li.astype(np.int64) * (2 * H) + cy2[li] - yi + H) * (2 * W) + cx2[li] - xi + W
    return ~(foreign | np.isin(mirror, key[foreign]))


def _detect(image: np.ndarray, o: DetectionOptions, surface: np.ndarray | None = None) -> Detections:
    """The detector on a polarised image (dots bright), with every option resolved."""
    if o.background_kernel_px > 0:
        tophat = _tophat(image, o.background_kernel_px)
        noise = max(_noise(tophat, o.subsample), _noise(image, o.subsample))
        thr = o.threshold if o.threshold is not None else o.threshold_sigma * noise
        bg = float(np.median(image[:: o.subsample, :: o.subsample]))
    else:
        bg = float(np.median(image[:: o.subsample, :: o.subsample]))
        noise = _noise(image, o.subsample)
        tophat = cv2.subtract(image, np.full_like(image, int(round(bg))))
        thr = o.threshold - bg if o.threshold is not None else o.threshold_sigma * noise
    mask = _above(tophat, thr)
    if o.local_fraction > 0:
        win = cv2.getStructuringElement(cv2.MORPH_RECT, (o.local_window, o.local_window))
        local = cv2.dilate(tophat, win).astype(np.float32)
        local *= np.float32(o.local_fraction)
        mask &= cv2.compare(tophat.astype(np.float32), local, cv2.CMP_GT)  # 0/255: keeps mask's 0/1
    n_lab, labels, stats = _components(mask)
    max_area = o.max_area_px if o.max_area_px is not None else 0.5 * o.background_kernel_px**2
    compact, clear = _blob_tests(stats, o, max_area, image.shape)
    det, found = _measure(image, o, surface, labels, stats, compact & clear, np.full(len(compact), noise), noise, bg)
    if o.threshold is not None or n_lab <= 1:
        return det
    from calibration.dot_split import split_pass  # dots joined by the noise of a lit surface (issue 15)

    return split_pass(image, o, surface, tophat, thr, noise, bg, labels, stats, compact, max_area, det, found)


def _measure(image: np.ndarray, o: DetectionOptions, surface: np.ndarray | None, labels: np.ndarray, stats: np.ndarray,
             keep: np.ndarray, blob_noise: np.ndarray, noise: float, bg: float, ceiling: float | None = None,
             agree_px: float | None = None, levels: tuple[float, float] | None = None) -> tuple[Detections, np.ndarray]:
    """Centres, covariances and the rest of the blobs ``keep`` ((n - 1,) bool over the components 1..n-1 of
    ``labels`` / ``stats``); ``blob_noise`` (n - 1,) is each one's noise for the peak test, ``noise`` the image's,
    ``bg`` its median level, ``ceiling`` its clipping level (None: ``image``'s). ``agree_px``: the ellipse is fitted to
    every blob and a blob is kept only where the fit succeeds and its centre is within this of the centroid (two
    estimates of one dot's centre; a patch of the surface, a dot cut by an edge, is not one). Returns (the detections,
    (k,) the component index (0-based, label - 1) of each). ``levels``: the pixel noise's line
    (:func:`calibration.dot_noise.noise_levels`) when already measured on the image (the split pass's few blobs take
    the first pass's), else measured on these blobs.
    """
    empty = Detections(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), noise,
                       np.zeros((0, 2, 2)), o.polarity, np.zeros((0, 2, 2)), np.zeros((0, 2, 2)),
                       np.zeros(0, dtype=int), np.zeros(0, dtype=int), np.zeros(0, dtype=bool))
    if not np.any(keep):
        return empty, np.zeros(0, dtype=np.int64)
    n_lab = len(stats)
    w_box = stats[1:, cv2.CC_STAT_WIDTH].astype(float)
    h_box = stats[1:, cv2.CC_STAT_HEIGHT].astype(float)
    area = stats[1:, cv2.CC_STAT_AREA].astype(float)
    x0, y0 = stats[1:, cv2.CC_STAT_LEFT], stats[1:, cv2.CC_STAT_TOP]
    m = o.margin_px
    # relabel the kept blobs 1..k, grow them by the margin, and a ring further out for the local background
    remap = np.zeros(n_lab, dtype=np.float32)
    kept = np.flatnonzero(keep) + 1
    k = len(kept)
    remap[kept] = np.arange(1, k + 1, dtype=np.float32)
    ys, xs, lo, lg = _grown_blobs(labels, remap, x0[keep], y0[keep], stats[kept, cv2.CC_STAT_WIDTH],
                                  stats[kept, cv2.CC_STAT_HEIGHT], m)
    xc = (x0 + 0.5 * w_box)[keep]
    yc = (y0 + 0.5 * h_box)[keep]
    foreign = None
    if surface is not None:  # only the pixels of each dot's own surface (decision 0035)
        off_ring, foreign = _own_surface(surface, labels, remap, ys, xs, lo, lg, xc, yc)
        if off_ring.any():
            # the whole ring's misfit still bounds the dot: what the labels do not remove (the other surface's light
            # blurred into the dot's own pixels, an edge a pixel off the CAD's) scales with it (decision 0035)
            ring_all = lg == 0
            _, misfit_all, _ = _ring_fit(lo[ring_all], xs[ring_all], ys[ring_all],
                                         image[ys[ring_all], xs[ring_all]].astype(np.float64), xc, yc, k, bg)
        ys, xs, lo, lg, foreign = (a[~off_ring] for a in (ys, xs, lo, lg, foreign))
    val = image[ys, xs].astype(np.float64)
    ring = lg == 0
    coef, misfit, (lf, ring_normal) = _ring_fit(lo[ring], xs[ring], ys[ring], val[ring], xc, yc, k, bg)
    if surface is not None and off_ring.any():
        misfit = np.maximum(misfit, misfit_all)
    bg_local = coef[:, 0]
    inside = ~ring
    li, xi, yi, vi = lg[inside], xs[inside], ys[inside], val[inside]
    bgp = coef[li - 1, 0] + coef[li - 1, 1] * (xi - xc[li - 1]) + coef[li - 1, 2] * (yi - yc[li - 1])
    if foreign is not None and foreign.any():
        sym = _symmetric(li, xi, yi, vi - bgp, foreign[inside], k, image.shape)
        li, xi, yi, vi, bgp = li[sym], xi[sym], yi[sym], vi[sym], bgp[sym]
    top = np.zeros(k + 1)
    np.maximum.at(top, li, vi)
    n_sat = np.bincount(li, weights=(vi >= (_ceiling(image) if ceiling is None else ceiling)).astype(float),
                        minlength=k + 1)[1:]
    peak = top[1:] - bg_local
    # the dot hides the surface behind it: a pixel's value is bg (1 - a) + L a for a dot of level L
    # covering the fraction a, so its share of the dot is (value - bg) / (L - bg), with L ~ the peak
    span = np.maximum(top[li] - bgp, 1.0)
    wgt = (vi - bgp) / span

    def per_blob(w):
        return np.bincount(li, weights=w, minlength=k + 1)[1:]

    sw = per_blob(wgt)
    sws = np.where(sw > 0, sw, 1.0)
    uv = np.stack([per_blob(wgt * xi) / sws, per_blob(wgt * yi) / sws], axis=1)
    dx, dy = xi - uv[li - 1, 0], yi - uv[li - 1, 1]
    # second moments of the dot (its ellipse), for ring decoding and size checks
    axes = np.empty((k, 2, 2))
    axes[:, 0, 0] = per_blob(wgt * dx * dx) / sws
    axes[:, 0, 1] = axes[:, 1, 0] = per_blob(wgt * dx * dy) / sws
    axes[:, 1, 1] = per_blob(wgt * dy * dy) / sws
    # covariance: u = sum(w x) / sum(w) with w_i = (v_i - b_i) / span_i, so du/dv_i = (x_i - u) / (span_i sum w),
    # each pixel with its own noise (photon noise grows with the light: a dot's pixels are noisier than the
    # background the image's figure is measured on), and the background plane's own error from its ring's noise
    # the noise's line from every step-th dot (a sensor's line needs no more than a few hundred): their flat tops,
    # within half the ellipse's radius (chosen by position, not by the noisy values) and unclipped, and their rings
    step = max(1, k // NOISE_DOTS)
    ps = np.flatnonzero(li % step == 0) if step > 1 else np.arange(len(li))
    lp, dxp, dyp = li[ps], dx[ps], dy[ps]
    det_ax = axes[:, 0, 0] * axes[:, 1, 1] - axes[:, 0, 1] ** 2
    q = (axes[lp - 1, 1, 1] * dxp * dxp - 2 * axes[lp - 1, 0, 1] * dxp * dyp + axes[lp - 1, 0, 0] * dyp * dyp)
    flat_top = ps[(q <= det_ax[lp - 1]) & (det_ax[lp - 1] > 0)]
    flat_top = flat_top[vi[flat_top] < (_ceiling(image) if ceiling is None else ceiling)]
    rs = np.flatnonzero(ring)
    rs = rs[lo[rs] % step == 0] if step > 1 else rs
    lr = lo[rs]
    ring_r = val[rs] - (coef[lr - 1, 0] + coef[lr - 1, 1] * (xs[rs] - xc[lr - 1])
                        + coef[lr - 1, 2] * (ys[rs] - yc[lr - 1]))
    var0, slope = levels if levels is not None else noise_levels(
        image.shape, (li[flat_top], xi[flat_top], yi[flat_top], vi[flat_top]), (lr, xs[rs], ys[rs], val[rs], ring_r),
        noise)
    var_px = np.maximum(var0 + slope * vi, 0.25 * noise**2)
    g = var_px / (span * sws[li - 1]) ** 2
    cov = np.empty((k, 2, 2))
    cov[:, 0, 0] = per_blob(g * dx * dx)
    cov[:, 0, 1] = cov[:, 1, 0] = per_blob(g * dx * dy)
    cov[:, 1, 1] = per_blob(g * dy * dy)
    cov += plane_cov(li, vi, wgt, top[li], span, sws, dx, dy, xi, yi, xc, yc, ring_normal,
                     np.maximum(var0 + slope * bg_local, 0.25 * noise**2), k, MIN_RING_PX)
    # the ellipse fitted to the half-level contour: for every dot ("ellipse"), or ("auto") for the dots whose centroid
    # the intensities mislead: a clipped dot (its clipped pixels weigh by the ceiling, not by their light) and a dot
    # whose ring shows a background that is not the plane (the misfit enters every pixel's weight); decision 0037
    pick = np.ones(k, dtype=bool) if o.centre == "ellipse" else (
        (n_sat > 0) | (misfit > 0) if o.centre == "auto" else np.zeros(k, dtype=bool))
    used_ellipse = np.zeros(k, dtype=bool)
    outline, shift, shift_cov = np.full((k, 4), np.nan), np.full((k, 2), np.nan), np.full((k, 2, 2), np.nan)
    clip_bound = np.zeros((k, 2))  # what a clipped dot's unknown level can move its centre by (px)
    fit = pick if agree_px is None else np.ones(k, dtype=bool)
    agree = np.ones(k, dtype=bool)
    if k:
        from calibration.ellipse_fit import contour_ellipses, contour_ellipse_centres_in_boxes

        # each contour's noise at its own level, halfway between the background and the peak
        half_noise = np.sqrt(np.maximum(var0 + slope * 0.5 * (bg_local + top[1:]), 0.25 * noise**2))
        box = np.stack([x0[keep], y0[keep], w_box[keep], h_box[keep]], axis=1)

        def contours(sel):
            return contour_ellipses(image, labels, remap, sel, box, coef, xc, yc, top[1:], half_noise, kept)

        e_uv, e_cov, ok, outline = contours(fit) if fit.any() else (np.zeros((k, 2)), np.zeros((k, 2, 2)),
                                                                     np.zeros(k, dtype=bool), outline)
        # a clipped dot hides the ground behind it as any dot does, but its level T is not its peak: the contour at
        # half its peak covers 1 / (2 k) of a pixel (k: T over the ceiling, both above the ground), and must follow
        # the ground with the slope 1 - 1 / (2 k), anywhere in 0.5-1 (decision 0050). The fit above took 0.5; with
        # the fit at 1, the centre is their middle and half their difference the bound of what the unknown k moves
        # it by (the centre moves linearly with the slope: within 1e-4 px of a fit at 0.75)
        clipped = fit & ok & (n_sat > 0)
        if clipped.any():
            far, _, far_ok, _ = contour_ellipse_centres_in_boxes(image, labels, remap, clipped, box, coef, xc, yc,
                                                                 top[1:], half_noise, kept, ground=1.0)
            both = clipped & far_ok
            clip_bound[both] = 0.5 * (far[both] - e_uv[both])
            e_uv = e_uv + clip_bound
        if o.outline and not fit.all():  # the others' contours too, for their outlines and the centroid's check
            rest = contours(~fit)
            e_uv, e_cov, ok = (np.where(np.reshape(fit, (-1,) + (1,) * (a.ndim - 1)), a, b)
                               for a, b in zip((e_uv, e_cov, ok), rest[:3]))
            outline = np.where(fit[:, None], outline, rest[3])
        if agree_px is not None:
            agree = ok & (np.hypot(*(e_uv - uv).T) <= agree_px)
        used_ellipse = ok & pick
        # a centroid dot's two centres, by its light and by its edge, agree on an ellipse's image; a speck on the dot
        # moves the first only (decision 0051). Their difference's covariance is taken as the sum (they share noise)
        cdot = ok & ~pick
        shift[cdot] = (uv - e_uv)[cdot]
        shift_cov[cdot] = (cov + e_cov)[cdot]
        uv = np.where(used_ellipse[:, None], e_uv, uv)
        cov = np.where(used_ellipse[:, None, None], e_cov, cov)
    cov += o.cov_floor_px**2 * np.eye(2)
    # a misfit e of one sign over each half of the dot, along each principal axis a of the dot's ellipse:
    # the centroid moves by e sum|(x_i - u) . a| / (span_i sum w)
    _, vec = np.linalg.eigh(axes)  # (k, 2, 2): columns are the axes
    h = 1.0 / (span * sws[li - 1])
    a1 = per_blob(h * np.abs(dx * vec[li - 1, 0, 0] + dy * vec[li - 1, 1, 0]))
    a2 = per_blob(h * np.abs(dx * vec[li - 1, 0, 1] + dy * vec[li - 1, 1, 1]))
    bcov = (misfit**2)[:, None, None] * (a1[:, None, None] ** 2 * np.einsum("ka,kb->kab", vec[:, :, 0], vec[:, :, 0])
                                         + a2[:, None, None] ** 2 * np.einsum("ka,kb->kab", vec[:, :, 1], vec[:, :, 1]))
    good = (sw > 0) & (peak >= o.min_peak_snr * blob_noise[keep]) & agree
    flux = sw * np.maximum(peak, 0.0)
    ring_px = np.bincount(lf, minlength=k + 1)[1:]
    return (Detections(uv[good], area[keep][good], peak[good], flux[good], bg_local[good], noise, cov[good],
                       o.polarity, axes[good], bcov[good], n_sat[good].astype(int), ring_px[good], used_ellipse[good],
                       (float(var0), float(slope)), np.where(used_ellipse[:, None], clip_bound, 0.0)[good],
                       outline[good] if o.outline else None, shift[good] if o.outline else None,
                       shift_cov[good] if o.outline else None),
            np.flatnonzero(keep)[good])
