"""Ring-coded targets: a centre dot and a ring of n angular sectors that carry the code.

Layout, in units of the centre dot's radius R (the common industrial form: a dot inside a segmented
annulus on a contrasting ground)::

    centre dot      r <= R                      bright (retro) / dark (print): the measured point
    gap             R < r < inner R             ground
    code ring       inner R <= r <= outer R,    n sectors of 360/n deg; a set bit is like the dot
    quiet zone      up to quiet R               ground

Sector b covers the angles [360 b / n, 360 (b + 1) / n) from the target's first in-plane axis ``e1``
towards ``e2`` (``sim_backend.world.marker_axes``: seen from the front, e1 points right and e2 down, as
an image's x and y, so the sectors run clockwise as seen; e1 x e2 = -normal).

Families (codes are rotation-invariant: every codeword is the smallest of its n cyclic rotations):

* ``ring12``, ``ring14``: this project's. Ring 2.0-3.5 R, quiet zone 4.2 R; sector b carries bit b
  (least significant first); the codewords are the aperiodic ones (different from each of their
  rotations, so a read also fixes the in-plane orientation); a target's code is the codeword's rank
  in ascending order, from 0: 335 codes (12 bits), 1161 (14 bits).
* ``schneider12``, ``schneider14``: the 14-bit code of the expired patent DE19733466A1 (Schneider,
  IDENT/VISION 1991) as laid out by M. Petroff's public-domain target generator (2018): ring 2.0-3.0 R
  (a stroke of width R at radius 2.5 R), quiet zone 3.6 R; sector b carries bit n-1-b (most
  significant first, clockwise from e1 as seen); codewords: the odd words ``2 i + 1`` for i = 0 ..
  2^(n-2) - 1 in that order, each replaced by its smallest rotation, kept if it has an even number
  of ones, at least one pair of diametrically opposite set sectors, and was not kept before; a
  target's code is its place in that order from 1 (the number printed under the target): 516 codes
  for 14 bits (the generator's count), 147 for 12 by the same rule.

* ``cct8``, ``cct12``: the "CCT" (circular coded target) of github.com/poxiao2/CCTDecode: ring 2.0-3.0 R;
  sector b (clockwise from e1 as seen) carries bit b; every word that is the smallest of its rotations
  (periodic ones and the full ring too) except all zeros; a target's code is that smallest value (the
  number the generator names the target's image by): 35 codes for 8 bits, 351 for 12.

PhotoModeler's ring-coded targets are not included: their layout is not publicly documented.

:func:`decode_ring_codes` reads the ring around detected dots: the dot's second moments give the
affine frame of its ellipse, in which the ring is sampled on two circles at 16 samples per sector;
the phase that best separates the sectors is chosen, each sector's majority is its bit, and the word
is accepted when every sector is clean (most of its samples agree), the ring's contrast is a good
fraction of the dot's, and the gap between dot and ring and the quiet zone are ground.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from calibration.dots import Detections, to_grey
from calibration.errors import CalibrationError

__all__ = ["RingFamily", "RING_FAMILIES", "ring_family", "family_codes", "code_bits", "bits_code",
           "decode_ring_codes", "RingCodes"]

_SAMPLES = 16  # per sector


@dataclass(frozen=True)
class RingFamily:
    """A ring-code family: ``n`` sectors, radii in units of the centre dot's radius, the code rule."""

    name: str
    n: int
    inner: float
    outer: float
    quiet: float
    rule: str  # "aperiodic" | "schneider" | "necklace"
    msb_first: bool
    first_id: int  # code of the first codeword; -1: a code is its codeword's value


RING_FAMILIES = {
    "ring12": RingFamily("ring12", 12, 2.0, 3.5, 4.2, "aperiodic", False, 0),
    "ring14": RingFamily("ring14", 14, 2.0, 3.5, 4.2, "aperiodic", False, 0),
    "schneider12": RingFamily("schneider12", 12, 2.0, 3.0, 3.6, "schneider", True, 1),
    "schneider14": RingFamily("schneider14", 14, 2.0, 3.0, 3.6, "schneider", True, 1),
    "cct8": RingFamily("cct8", 8, 2.0, 3.0, 3.6, "necklace", False, -1),
    "cct12": RingFamily("cct12", 12, 2.0, 3.0, 3.6, "necklace", False, -1),
}


def ring_family(family: str) -> RingFamily:
    """The family called ``family``; CalibrationError naming the known ones otherwise."""
    if family not in RING_FAMILIES:
        raise CalibrationError(f"unknown ring-code family {family!r}; known: {', '.join(RING_FAMILIES)}")
    return RING_FAMILIES[family]


def _rotations(word: int, n: int) -> list[int]:
    mask = (1 << n) - 1
    return [((word >> r) | (word << (n - r))) & mask for r in range(n)]


@lru_cache(maxsize=None)
def family_codes(family: str) -> np.ndarray:
    """(m,) the family's codewords (ints), in code order: code ``first_id + i`` is codeword i."""
    f = ring_family(family)
    n = f.n
    out: list[int] = []
    if f.rule in ("aperiodic", "necklace"):
        for w in range(1, (1 << n) - (f.rule == "aperiodic")):  # a full ring is a necklace code
            rot = _rotations(w, n)
            if w == min(rot) and (f.rule == "necklace" or rot.count(w) == 1):
                out.append(w)
    else:
        half = (1 << (n // 2)) - 1
        seen: set[int] = set()
        for i in range(1 << (n - 2)):
            w = min(_rotations(2 * i + 1, n))
            if bin(w).count("1") % 2 == 0 and (w & half) & (w >> (n // 2)) and w not in seen:
                seen.add(w)
                out.append(w)
    return np.array(out, dtype=np.int64)


@lru_cache(maxsize=None)
def _word_to_code(family: str) -> dict[int, int]:
    f = ring_family(family)
    return {int(w): (int(w) if f.first_id < 0 else i + f.first_id) for i, w in enumerate(family_codes(family))}


def code_bits(family: str, code: int) -> np.ndarray:
    """(n,) 0/1 bits of the sectors 0..n-1 of target ``code`` in ``family``."""
    f = ring_family(family)
    words = family_codes(family)
    if f.first_id < 0:
        hit = np.flatnonzero(words == int(code))
        if not len(hit):
            raise CalibrationError(f"ring code {code} is not a codeword of family {family} (the smallest rotation "
                                   f"of a {f.n}-bit word other than 0)")
        i = int(hit[0])
    else:
        i = int(code) - f.first_id
    if not 0 <= i < len(words):
        raise CalibrationError(f"ring code {code} is outside family {family} "
                               f"({f.first_id}..{f.first_id + len(words) - 1})")
    bits = (int(words[i]) >> np.arange(f.n)) & 1
    return bits[::-1].copy() if f.msb_first else bits


def bits_code(family: str, bits: np.ndarray) -> tuple[int, int]:
    """(code, rotation) of sector bits read from any starting sector; code -1 when not in the family."""
    f = ring_family(family)
    b = np.asarray(bits, dtype=np.int64)
    if f.msb_first:
        b = b[::-1]
    word = int(np.sum(b << np.arange(f.n)))
    rot = _rotations(word, f.n)
    r = int(np.argmin(rot))
    return _word_to_code(family).get(rot[r], -1), r


class RingCodes:
    """Decoded ring-coded targets of one image.

    Attributes:
        index: (c,) index of the centre dot in the detections.
        code: (c,) code (rank in the family).
        family: the family read.
        ring_px: (c,) the quiet zone's radius in pixels (mean over the ellipse): detections closer than
            this to the centre are the ring's sectors, not dots.
    """

    def __init__(self, index, code, family, ring_px) -> None:
        self.index = np.asarray(index, dtype=int)
        self.code = np.asarray(code, dtype=int)
        self.family = family
        self.ring_px = np.asarray(ring_px, dtype=float)

    def __len__(self) -> int:
        return len(self.index)

    def ring_parts(self, uv: np.ndarray) -> np.ndarray:
        """Which of the points ``uv: (k, 2)`` (detections of the same image) lie on a decoded target's
        ring or quiet zone, centre dots excluded: (k,) bool. They are pieces of the code, not dots."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        out = np.zeros(len(uv), dtype=bool)
        for i, r in zip(self.index, self.ring_px):
            d = np.linalg.norm(uv - uv[i], axis=1)
            out |= (d > 1e-9) & (d <= r)
        return out


def decode_ring_codes(image: np.ndarray, det: Detections, family: str, *, min_clean: float = 0.75,
                      min_contrast: float = 0.35) -> "RingCodes":
    """Read the code ring around every detected dot of ``det`` (found in ``image``) that carries one.

    Args:
        image: the image the dots were detected in (grey or colour).
        det: its detections (their ``polarity`` says which way the image is polarised).
        family: a name in ``RING_FAMILIES``.
        min_clean: fraction of a sector's samples that must agree with its bit.
        min_contrast: the ring's bright-dark difference as a fraction of the dot's peak.
    """
    f = ring_family(family)
    n = f.n
    grey = to_grey(image)
    work = (grey if det.polarity == "bright" else cv2.bitwise_not(grey)).astype(np.float32)
    k = len(det)
    if k == 0:
        return RingCodes([], [], family, [])
    # affine frame of each dot's ellipse: x = c + S (cos t, sin t) on the rim, S = 2 sqrtm(axes)
    w, V = np.linalg.eigh(det.axes)
    w = np.clip(w, 1e-6, None)
    S = np.einsum("kij,kj,klj->kil", V, 2.0 * np.sqrt(w), V)
    M = n * _SAMPLES
    t = 2 * np.pi * (np.arange(M) + 0.5) / M
    circ = np.stack([np.cos(t), np.sin(t)])  # (2, M)
    radii = np.array([f.inner + 0.3 * (f.outer - f.inner), f.inner + 0.7 * (f.outer - f.inner),
                      0.5 * (1.0 + f.inner), 0.5 * (f.outer + f.quiet)])
    pts = det.uv[:, None, None, :] + radii[None, :, None, None] * np.einsum("kij,jm->kmi", S, circ)[:, None]
    mx = pts[..., 0].astype(np.float32).reshape(k, -1)
    my = pts[..., 1].astype(np.float32).reshape(k, -1)
    smp = cv2.remap(work, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    smp = smp.reshape(k, len(radii), M).astype(np.float64)
    # a dot whose rings reach past the image's edge (samples NaN there) carries no code it can be read by: it is
    # left out below, and its samples are zeroed so that no maximum is taken over an empty (all-NaN) set
    finite = np.isfinite(smp).all(axis=(1, 2))
    smp[~finite] = 0.0
    ring = 0.5 * (smp[:, 0] + smp[:, 1])  # (k, M)
    gap, quiet = smp[:, 2], smp[:, 3]
    bg, peak = det.background[:, None], det.peak[:, None]
    level = bg + 0.5 * peak
    on = ring > level
    contrast = (ring.max(axis=1) - gap.max(axis=1)) / np.maximum(det.peak, 1e-9)  # set sectors vs the gap
    ground = (gap.max(axis=1) < level[:, 0]) & (quiet.max(axis=1) < level[:, 0])
    # best phase: the offset of sector boundaries (in samples) whose sectors are cleanest
    best_clean = np.zeros(k)
    best_bits = np.zeros((k, n), dtype=np.int64)
    best_off = np.zeros(k, dtype=int)
    for off in range(_SAMPLES):
        sec = np.roll(on, -off, axis=1).reshape(k, n, _SAMPLES).mean(axis=2)
        clean = np.minimum(sec, 1 - sec).max(axis=1)  # worst sector's minority share
        score = 1 - clean
        better = score > best_clean
        best_clean[better] = score[better]
        best_bits[better] = (sec[better] > 0.5).astype(np.int64)
        best_off[better] = off
    cand = finite & ground & (contrast >= min_contrast) & (best_clean >= min_clean)
    idx, codes, ring_px = [], [], []
    for i in np.flatnonzero(cand):
        # the image's angle runs the same way as the target's (e1 -> e2 is clockwise seen from the front,
        # as the image's x -> y); an affinity keeps that sense, only a mirror image would reverse it
        code, _ = bits_code(family, best_bits[i])
        if code < 0:
            continue
        idx.append(i)
        codes.append(code)
        ring_px.append(float(f.quiet * np.sqrt(np.prod(2.0 * np.sqrt(w[i])))))
    return RingCodes(idx, codes, family, ring_px)
