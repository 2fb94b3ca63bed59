"""Dot centres from an ellipse fitted to each blob's sub-pixel half-level contour (vectorised over blobs).

For each blob the level is halfway between its local background plane and its peak (by default). Every pair of
4-neighbours (horizontal and vertical) inside the blob's window whose grey levels straddle that
level gives one contour point by linear interpolation. A conic ``a x^2 + b xy + c y^2 + d x + e y +
f = 0`` with ``a + c = 1`` (invariant to rotation and translation) is fitted by least squares to
each blob's points, all blobs at once through ``bincount`` sums of the 5x5 normal equations; the
centre is where the conic's gradient vanishes.

Covariance: a contour point found along x moves by ``noise * sqrt(2) / |step|`` (``step`` the grey
level change across the pair); the centre of a closed contour is the mean of those moves
projected on the axes, so its information is ``sum(1 / sigma_i^2)`` per axis over the points found
along that axis, halved (the contour's two sides share the shape's unknowns).

The dot hides the ground behind it: a pixel covered by the fraction ``a`` of a dot of level ``T`` reads
``b (1 - a) + T a`` over a ground ``b``. A contour at one fraction ``a`` of the dot follows the ground with the slope
``1 - a``: ``level = (b0 + top) / 2 + (1 - a) (b - b0)`` about the ground ``b0`` at the blob's reference point,
with ``a = (top - b0) / (2 (T - b0))``. Where the dot is not clipped its peak is ``T``, ``a`` is one half, and the
level is the mean of the ground and the peak. A clipped dot's peak is the sensor's ceiling, not ``T``, and the
slope that follows the ground right is somewhere in 0.5..1: the caller's ``ground`` (decision 0050). With 0.5
there, dots clipped over 80 % of their pixels at five times the light leaned by -0.014 px on average.
"""
from __future__ import annotations

import numpy as np

__all__ = ["contour_ellipse_centres", "contour_ellipse_centres_in_boxes"]


def contour_ellipse_centres(image: np.ndarray, lab: np.ndarray, k: int, coef: np.ndarray, xc: np.ndarray,
                            yc: np.ndarray, top: np.ndarray, noise, components: np.ndarray | None = None,
                            own: np.ndarray | None = None, ground=None
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ellipse centres of ``k`` blobs.

    Args:
        image: (h, w) the polarised image (dots bright).
        lab: (h, w) float32 blob labels 1..k (0 elsewhere), the thresholded blobs.
        coef: (k, 3) background plane ``b0 + gx (x - xc) + gy (y - yc)`` of each blob.
        xc, yc: (k,) reference point of each blob's plane.
        top: (k,) peak grey level of each blob.
        noise: pixel noise standard deviation (grey levels): one for the image, or (k,) each blob's at its contour's
            level.
        components, own: (h, w) int the thresholded components and (k,) each blob's own component: a pair of pixels
            one of which belongs to another component is no point of the blob's contour (a neighbour's rim within
            the blob's window crosses the blob's level too). None: every pair in the window counts.
        ground: (k,) or one, the slope with which the level follows the ground across the blob (None: 0.5, right
            where ``top`` is the dot's own level; module docstring).

    Returns:
        uv (k, 2), cov (k, 2, 2) px^2, ok (k,) bool (enough contour points and a real ellipse).
    """
    import cv2

    grown = cv2.dilate(lab, cv2.getStructuringElement(cv2.MORPH_RECT, (5, 5)))
    ys, xs = np.nonzero(grown)
    L = grown[ys, xs].astype(np.int64)
    img = image.astype(np.float64)

    slope = np.broadcast_to(np.asarray(0.5 if ground is None else ground, dtype=float), (k,))

    def level(ll, x, y):
        c = coef[ll - 1]
        b0 = c[:, 0]
        return 0.5 * (b0 + top[ll - 1]) + slope[ll - 1] * (c[:, 1] * (x - xc[ll - 1]) + c[:, 2] * (y - yc[ll - 1]))

    px, py, pl, pw, ax = [], [], [], [], []
    for ddx, ddy in ((1, 0), (0, 1)):
        x2, y2 = xs + ddx, ys + ddy
        inb = (x2 < image.shape[1]) & (y2 < image.shape[0])
        x1, y1, l1, x2, y2 = xs[inb], ys[inb], L[inb], x2[inb], y2[inb]
        same = grown[y2, x2].astype(np.int64) == l1
        x1, y1, l1, x2, y2 = x1[same], y1[same], l1[same], x2[same], y2[same]
        if components is not None:  # neither pixel of another blob (the background is 0)
            c1, c2, mine = components[y1, x1], components[y2, x2], own[l1 - 1]
            mine_only = ((c1 == 0) | (c1 == mine)) & ((c2 == 0) | (c2 == mine))
            x1, y1, l1, x2, y2 = x1[mine_only], y1[mine_only], l1[mine_only], x2[mine_only], y2[mine_only]
        f1 = img[y1, x1] - level(l1, x1 + 0.5 * ddx, y1 + 0.5 * ddy)
        f2 = img[y2, x2] - level(l1, x1 + 0.5 * ddx, y1 + 0.5 * ddy)
        cross = (f1 * f2 < 0)
        f1, f2, x1, y1, l1 = f1[cross], f2[cross], x1[cross], y1[cross], l1[cross]
        t = f1 / (f1 - f2)
        px.append(x1 + t * ddx)
        py.append(y1 + t * ddy)
        pl.append(l1)
        nz2 = noise**2 if np.ndim(noise) == 0 else np.asarray(noise, dtype=float)[l1 - 1] ** 2
        pw.append((f1 - f2) ** 2 / (2 * nz2))  # 1 / sigma^2 of the point along the pair's axis
        ax.append(np.full(len(l1), ddx == 1))
    x, y, ll, w, along_x = map(np.concatenate, (px, py, pl, pw, ax))
    # centre the coordinates on each blob for conditioning
    x = x - xc[ll - 1]
    y = y - yc[ll - 1]
    F = np.stack([x * x - y * y, x * y, x, y, np.ones_like(x)], axis=1)
    rhs = -y * y

    def s(v):
        return np.bincount(ll, weights=v, minlength=k + 1)[1:]

    A = np.empty((k, 5, 5))
    bvec = np.empty((k, 5))
    for i in range(5):
        bvec[:, i] = s(F[:, i] * rhs)
        for j in range(i, 5):
            A[:, i, j] = A[:, j, i] = s(F[:, i] * F[:, j])
    n = np.bincount(ll, minlength=k + 1)[1:]
    ok = n >= 12
    ok[ok] &= np.abs(np.linalg.det(A[ok])) > 1e-12
    sol = np.zeros((k, 5))
    if np.any(ok):
        sol[ok] = np.linalg.solve(A[ok], bvec[ok][..., None])[..., 0]
    a, b, d, e = sol[:, 0], sol[:, 1], sol[:, 2], sol[:, 3]
    c = 1.0 - a
    M = np.stack([np.stack([2 * a, b], -1), np.stack([b, 2 * c], -1)], -2)
    det = 4 * a * c - b * b
    ok &= det > 1e-9  # an ellipse
    cen = np.zeros((k, 2))
    if np.any(ok):
        cen[ok] = -np.linalg.solve(M[ok], np.stack([d, e], -1)[ok][..., None])[..., 0]
    uv = cen + np.stack([xc, yc], -1)
    info_x = s(np.where(along_x, w, 0.0))
    info_y = s(np.where(along_x, 0.0, w))
    cov = np.zeros((k, 2, 2))
    cov[:, 0, 0] = 2.0 / np.maximum(info_x, 1e-12)
    cov[:, 1, 1] = 2.0 / np.maximum(info_y, 1e-12)
    ok &= (info_x > 0) & (info_y > 0)
    return uv, cov, ok


def contour_ellipse_centres_in_boxes(image: np.ndarray, labels: np.ndarray, remap: np.ndarray, sel: np.ndarray,
                                     box: np.ndarray, coef: np.ndarray, xc: np.ndarray, yc: np.ndarray,
                                     top: np.ndarray, noise, own_comp: np.ndarray | None = None,
                                     ground=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`contour_ellipse_centres` of the blobs ``sel: (k,) bool`` only, each in its own box: the boxes (each
    blob's bounding box ``box: (k, 4)`` x0, y0, w, h grown by 3 px, what the contour's 5 x 5 growth and its pixel pairs
    reach) are cut out, stacked into one small image with only their own blob labelled, and fitted at once. The same
    centres as the whole image gives (where no other selected blob reaches within 2 px) for a fraction of its cost
    when few blobs are selected (decision 0037: the clipped dots and those next to an edge).

    ``labels``: (h, w) component labels; ``remap``: (n,) float32, component label -> 1..k (0: not kept);
    ``own_comp``: (k,) each blob's component label (pairs with a pixel of another component are left out, as
    :func:`contour_ellipse_centres` does with them; None: kept). ``ground``: as there.
    Returns uv (k, 2), cov (k, 2, 2), ok (k,) bool (False where not selected).
    """
    k = len(sel)
    uv, cov, ok = np.zeros((k, 2)), np.zeros((k, 2, 2)), np.zeros(k, dtype=bool)
    idx = np.flatnonzero(sel)
    if not len(idx):
        return uv, cov, ok
    H, W = image.shape
    g = 3
    bx0 = np.maximum(box[idx, 0] - g, 0).astype(int)
    by0 = np.maximum(box[idx, 1] - g, 0).astype(int)
    bx1 = np.minimum(box[idx, 0] + box[idx, 2] + g, W).astype(int)
    by1 = np.minimum(box[idx, 1] + box[idx, 3] + g, H).astype(int)
    hh = by1 - by0
    oy = np.concatenate([[0], np.cumsum(hh + g)[:-1]])  # a gap of g empty rows between the boxes
    mosaic = np.zeros((int(oy[-1] + hh[-1]), int((bx1 - bx0).max())), dtype=image.dtype)
    lab = np.zeros(mosaic.shape, dtype=np.float32)
    comp = np.zeros(mosaic.shape, dtype=labels.dtype)  # the components, as in the image (others' pixels excluded)
    for j, q in enumerate(idx):
        win = image[by0[j]:by1[j], bx0[j]:bx1[j]]
        cw = labels[by0[j]:by1[j], bx0[j]:bx1[j]]
        own = remap[cw] == q + 1
        mosaic[oy[j]:oy[j] + hh[j], :win.shape[1]] = win
        comp[oy[j]:oy[j] + hh[j], :win.shape[1]] = cw
        lab[oy[j]:oy[j] + hh[j], :win.shape[1]][own] = q + 1
    # the blobs' plane reference points moved with their boxes (the plane is in x - xc, y - yc: unchanged)
    sx, sy = np.zeros(k), np.zeros(k)
    sx[idx], sy[idx] = bx0, by0 - oy
    out = contour_ellipse_centres(mosaic, lab, k, coef, xc - sx, yc - sy, top, noise,
                                  None if own_comp is None else comp, own_comp, ground)
    uv[idx] = out[0][idx] + np.stack([sx[idx], sy[idx]], axis=1)
    cov[idx], ok[idx] = out[1][idx], out[2][idx]
    return uv, cov, ok
