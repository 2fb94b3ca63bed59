"""Dot centres from an ellipse fitted to each blob's sub-pixel half-level contour (vectorised over blobs).

For each blob the level is halfway between its local background plane and its peak (by default). Every pair of
4-neighbours (horizontal and vertical) inside the blob's window whose grey levels straddle that
level gives one contour point by linear interpolation. A conic ``a x^2 + b xy + c y^2 + d x + e y +
f = 0`` with ``a + c = 1`` (invariant to rotation and translation) is fitted by least squares to
each blob's points, all blobs at once through ``bincount`` sums of the 5x5 normal equations; the
centre is where the conic's gradient vanishes.

A hole (pixels below the level that the blob's pixels above it enclose: a speck of dirt showing through a clipped
plateau) is not the dot's edge: pairs with a pixel of a hole give no point (decision 0051).

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

__all__ = ["contour_ellipse_centres", "contour_ellipse_centres_in_boxes", "contour_ellipses", "STRAY_PX"]

STRAY_PX = 1.0  # a contour point farther than this (or a fifth of the mean radius) from the conic is no edge point


def contour_ellipse_centres(image: np.ndarray, lab: np.ndarray, k: int, coef: np.ndarray, xc: np.ndarray,
                            yc: np.ndarray, top: np.ndarray, noise, components: np.ndarray | None = None,
                            own: np.ndarray | None = None, ground=None
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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
        uv (k, 2), cov (k, 2, 2) px^2, ok (k,) bool (enough contour points and a real ellipse), and outline (k, 4):
        each contour's misfit about its ellipse, ``[chi2, n, rms, stray]``: the squared distances from the conic
        refitted without the strays (points farther than :data:`STRAY_PX` or a fifth of the mean radius from the first
        conic) of the points whose pair crosses the edge within 60 deg of its normal, along their pairs' axes in their
        own variances, summed (``chi2``: of the order of ``n - 5`` for an ellipse's image, about half that on the
        simulated camera, whose contour noise the pairs' model overstates; decision 0051 judges it against the job's
        own dots), the number ``n`` of those points, their distances' rms in px (along the normal) and the number of
        strays; NaN where not ``ok``. The centre is the first conic's, strays and all, as before decision 0051.
    """
    import cv2

    grown = cv2.dilate(lab, cv2.getStructuringElement(cv2.MORPH_RECT, (5, 5)))
    slope = np.broadcast_to(np.asarray(0.5 if ground is None else ground, dtype=float), (k,))
    rows, cols = np.flatnonzero(grown.any(axis=1)), np.flatnonzero(grown.any(axis=0))
    if not len(rows):
        return np.zeros((k, 2)), np.zeros((k, 2, 2)), np.zeros(k, dtype=bool), np.full((k, 4), np.nan)
    # the pixel pairs, in image space over the grown blobs' bounding box (row-major, as np.nonzero orders them): each
    # pixel of a blob's grown window with its right and its lower neighbour of the same window, neither of another
    # blob; table lookups by the label (row 0: no blob) give each pixel its blob's plane and level
    r0, c0 = rows[0], cols[0]
    G = grown[r0:rows[-1] + 1, c0:cols[-1] + 1].astype(np.int64)
    V = image[r0:rows[-1] + 1, c0:cols[-1] + 1]
    mine = G > 0
    if components is not None:  # neither pixel of another blob (the background is 0)
        C = components[r0:rows[-1] + 1, c0:cols[-1] + 1]
        mine &= (C == 0) | (C == np.concatenate([[0], own])[G])

    def table(v):
        return np.concatenate([[0.0], np.asarray(v, dtype=float)])

    half_t, slope_t = table(0.5 * (coef[:, 0] + top)), table(slope)
    gx_t, gy_t, xc_t, yc_t = table(coef[:, 1]), table(coef[:, 2]), table(xc), table(yc)
    # a hole: pixels below the level that the blob's own pixels above it close in (a speck of dirt on the dot, dark
    # through a clipped plateau). Its rim is no edge of the dot: a pair with a pixel of a hole gives no point (decision
    # 0051: a speck of 2 % of the area at half the radius moved a just-clipped dot's ellipse by 0.2 px)
    # (the level as a + bx x + by y per blob: three lookups a pixel, where the pairs below take the formula itself)
    a_t = half_t - slope_t * (gx_t * xc_t + gy_t * yc_t)
    above = mine & (V > a_t[G] + (slope_t * gx_t)[G] * np.arange(c0, cols[-1] + 1)[None, :]
                    + (slope_t * gy_t)[G] * np.arange(r0, rows[-1] + 1)[:, None])
    n_cc, cc = cv2.connectedComponents((~above).astype(np.uint8), connectivity=4)
    outer = np.zeros(n_cc, dtype=bool)
    outer[cc[G == 0]] = True
    outer[np.concatenate([cc[0], cc[-1], cc[:, 0], cc[:, -1]])] = True  # the crop's border is open to the outside
    mine &= ~((cc > 0) & ~outer[cc]) | above
    nz2_t = table(np.broadcast_to(np.asarray(noise, dtype=float) ** 2, (k,)))
    px, py, pl, pw, ax = [], [], [], [], []
    for ddx, ddy in ((1, 0), (0, 1)):
        h2, w2 = G.shape[0] - ddy, G.shape[1] - ddx
        G1 = G[:h2, :w2]
        pair = (G1 > 0) & (G1 == G[ddy:, ddx:]) & mine[:h2, :w2] & mine[ddy:, ddx:]
        iy, ix = np.nonzero(pair)
        l1 = G1[iy, ix]
        x1, y1 = ix + c0, iy + r0
        # the level at the pair's middle: halfway between the blob's plane and its peak, following the ground
        lv = half_t[l1] + slope_t[l1] * (gx_t[l1] * ((x1 + 0.5 * ddx) - xc_t[l1])
                                         + gy_t[l1] * ((y1 + 0.5 * ddy) - yc_t[l1]))
        f1 = V[iy, ix].astype(np.float64) - lv
        f2 = V[iy + ddy, ix + ddx].astype(np.float64) - lv
        cross = (f1 * f2 < 0)
        f1, f2, x1, y1, l1 = f1[cross], f2[cross], x1[cross], y1[cross], l1[cross]
        t = f1 / (f1 - f2)
        px.append(x1 + t * ddx)
        py.append(y1 + t * ddy)
        pl.append(l1)
        pw.append((f1 - f2) ** 2 / (2 * nz2_t[l1]))  # 1 / sigma^2 of the point along the pair's axis
        ax.append(np.full(len(l1), ddx == 1))
    x, y, ll, w, along_x = map(np.concatenate, (px, py, pl, pw, ax))
    # centre the coordinates on each blob for conditioning
    x = x - xc[ll - 1]
    y = y - yc[ll - 1]
    n = np.bincount(ll, minlength=k + 1)[1:]
    sol, ok = _fit_conics(x, y, ll, k, np.ones(len(x)))
    uv, ok = _centres(sol, ok, xc, yc)

    def s(v):
        return np.bincount(ll, weights=v, minlength=k + 1)[1:]

    info_x = s(np.where(along_x, w, 0.0))
    info_y = s(np.where(along_x, 0.0, w))
    cov = np.zeros((k, 2, 2))
    cov[:, 0, 0] = 2.0 / np.maximum(info_x, 1e-12)
    cov[:, 1, 1] = 2.0 / np.maximum(info_y, 1e-12)
    ok &= (info_x > 0) & (info_y > 0)
    # the outline's misfit. A point farther than STRAY_PX (or a fifth of the ellipse's mean radius) from the fitted
    # conic is no point of the dot's edge (the ground's own level crossing in the window, a neighbour's skirt): it is
    # counted and left out, and the conic fitted again to the others. Each remaining point's distance from that conic
    # along its pair's axis (where its noise is), in its own standard deviations: an ellipse's image leaves the
    # noise, a chipped or stained edge more (decision 0051)
    geo, _ = _distances(sol, x, y, ll, along_x)
    reach = np.maximum(STRAY_PX, 0.2 * _mean_radius(sol))
    inl = np.abs(geo) <= reach[ll - 1]
    stray = n - s(inl.astype(float))
    sol2, ok2 = _fit_conics(x, y, ll, k, inl.astype(float))
    geo2, along = _distances(sol2, x, y, ll, along_x)
    # a pair nearly along the edge places its point poorly (its step is the noise's): the points whose pair crosses the
    # edge within 60 deg of its normal carry the misfit (every stretch of an edge has them, along x or along y)
    inl &= np.abs(geo2) >= 0.5 * np.abs(along)
    n_in = s(inl.astype(float))
    outline = np.stack([s(np.where(inl, w * along * along, 0.0)), n_in,
                        np.sqrt(s(np.where(inl, geo2 * geo2, 0.0)) / np.maximum(n_in, 1)), stray], axis=1)
    outline[~(ok & ok2)] = np.nan
    return uv, cov, ok, outline


def _fit_conics(x: np.ndarray, y: np.ndarray, ll: np.ndarray, k: int, wt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares conics ``a x^2 + b xy + c y^2 + d x + e y + f = 0``, ``a + c = 1``, one per blob label ``ll``
    (1..k) of the points ``x, y`` weighted ``wt``: (k, 5) ``[a, b, d, e, f]`` and (k,) bool solved."""
    F = np.stack([x * x - y * y, x * y, x, y, np.ones_like(x)], axis=1)
    rhs = -y * y

    def s(v):
        return np.bincount(ll, weights=v * wt, minlength=k + 1)[1:]

    A = np.empty((k, 5, 5))
    bvec = np.empty((k, 5))
    for i in range(5):
        bvec[:, i] = s(F[:, i] * rhs)
        for j in range(i, 5):
            A[:, i, j] = A[:, j, i] = s(F[:, i] * F[:, j])
    ok = s(np.ones_like(x)) >= 12
    ok[ok] &= np.abs(np.linalg.det(A[ok])) > 1e-12
    sol = np.zeros((k, 5))
    if np.any(ok):
        sol[ok] = np.linalg.solve(A[ok], bvec[ok][..., None])[..., 0]
    return sol, ok


def _centres(sol: np.ndarray, ok: np.ndarray, xc: np.ndarray, yc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each conic's centre (where its gradient vanishes) about its blob's reference point, and ``ok`` where it is an
    ellipse."""
    a, b, d, e = sol[:, 0], sol[:, 1], sol[:, 2], sol[:, 3]
    c = 1.0 - a
    M = np.stack([np.stack([2 * a, b], -1), np.stack([b, 2 * c], -1)], -2)
    ok = ok & (4 * a * c - b * b > 1e-9)  # an ellipse
    cen = np.zeros((len(sol), 2))
    if np.any(ok):
        cen[ok] = -np.linalg.solve(M[ok], np.stack([d, e], -1)[ok][..., None])[..., 0]
    return cen + np.stack([xc, yc], -1), ok


def _distances(sol: np.ndarray, x: np.ndarray, y: np.ndarray, ll: np.ndarray, along_x: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Each point's distance from its blob's conic to first order: along the conic's normal, and along its pair's
    axis (x where ``along_x``)."""
    a, b, d, e, f = (sol[ll - 1, i] for i in range(5))
    c = 1.0 - a
    Q = a * x * x + b * x * y + c * y * y + d * x + e * y + f
    gx, gy = 2 * a * x + b * y + d, b * x + 2 * c * y + e
    g_axis = np.where(along_x, gx, gy)
    return Q / np.maximum(np.hypot(gx, gy), 1e-12), Q / np.where(np.abs(g_axis) > 1e-9, g_axis, 1e-9)


def _mean_radius(sol: np.ndarray) -> np.ndarray:
    """(k,) the geometric mean of each conic's semi-axes (0 where it is no ellipse)."""
    a, b, d, e, f = (sol[:, i] for i in range(5))
    c = 1.0 - a
    det = 4 * a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        # the centred conic x^T M x = -f', f' = f - (a x0^2 + b x0 y0 + c y0^2); semi-axes^2 = -f' / eigenvalues
        x0 = (b * e - 2 * c * d) / det
        y0 = (b * d - 2 * a * e) / det
        fc = f + 0.5 * (d * x0 + e * y0)
        r2 = -fc / np.sqrt(np.maximum(a * c - 0.25 * b * b, 1e-18))
    return np.where((det > 1e-9) & (r2 > 0), np.sqrt(np.maximum(r2, 0.0)), 0.0)


def contour_ellipses(image: np.ndarray, labels: np.ndarray, remap: np.ndarray, sel: np.ndarray, box: np.ndarray,
                     coef: np.ndarray, xc: np.ndarray, yc: np.ndarray, top: np.ndarray, noise, own_comp: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`contour_ellipse_centres` of the blobs ``sel`` (arguments as :func:`contour_ellipse_centres_in_boxes`):
    on the whole image when their boxes cover over a quarter of it (blobs all over), else each in its own box (a few:
    the clipped dots, those next to an edge, a split pass's parts)."""
    k = len(sel)
    if np.sum((box[sel, 2] + 6) * (box[sel, 3] + 6)) > 0.25 * image.size:
        blobs = remap if sel.all() else np.where(np.concatenate([[False], sel])[remap.astype(np.int64)], remap,
                                                 np.float32(0)).astype(np.float32)
        return contour_ellipse_centres(image, blobs[labels], k, coef, xc, yc, top, noise, labels, own_comp)
    return contour_ellipse_centres_in_boxes(image, labels, remap, sel, box, coef, xc, yc, top, noise, own_comp)


def contour_ellipse_centres_in_boxes(image: np.ndarray, labels: np.ndarray, remap: np.ndarray, sel: np.ndarray,
                                     box: np.ndarray, coef: np.ndarray, xc: np.ndarray, yc: np.ndarray,
                                     top: np.ndarray, noise, own_comp: np.ndarray | None = None,
                                     ground=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`contour_ellipse_centres` of the blobs ``sel: (k,) bool`` only, each in its own box: the boxes (each
    blob's bounding box ``box: (k, 4)`` x0, y0, w, h grown by 3 px, what the contour's 5 x 5 growth and its pixel pairs
    reach) are cut out, stacked into one small image with only their own blob labelled, and fitted at once. The same
    centres as the whole image gives (where no other selected blob reaches within 2 px) for a fraction of its cost
    when few blobs are selected (decision 0037: the clipped dots and those next to an edge).

    ``labels``: (h, w) component labels; ``remap``: (n,) float32, component label -> 1..k (0: not kept);
    ``own_comp``: (k,) each blob's component label (pairs with a pixel of another component are left out, as
    :func:`contour_ellipse_centres` does with them; None: kept). ``ground``: as there.
    Returns uv (k, 2), cov (k, 2, 2), ok (k,) bool (False where not selected), outline (k, 4) (NaN there).
    """
    k = len(sel)
    uv, cov, ok, outline = np.zeros((k, 2)), np.zeros((k, 2, 2)), np.zeros(k, dtype=bool), np.full((k, 4), np.nan)
    idx = np.flatnonzero(sel)
    if not len(idx):
        return uv, cov, ok, outline
    H, W = image.shape
    g = 3
    bx0 = np.maximum(box[idx, 0] - g, 0).astype(int)
    by0 = np.maximum(box[idx, 1] - g, 0).astype(int)
    bx1 = np.minimum(box[idx, 0] + box[idx, 2] + g, W).astype(int)
    by1 = np.minimum(box[idx, 1] + box[idx, 3] + g, H).astype(int)
    hh, ww = by1 - by0, bx1 - bx0
    m, Hm, Wm = len(idx), int(hh.max()), int(ww.max())
    sx, sy = np.zeros(k), np.zeros(k)  # where each box's window starts in the image, less where it starts in the mosaic
    if m * Hm * Wm <= 2 * int(np.sum(hh * ww)) and Hm <= H and Wm <= W:
        # boxes of about one size: a window of the largest size each (moved inside the image where it would leave it),
        # cut in one gather and stacked with g empty rows after each; the pixels beyond a box are no blob's own
        y0, x0 = np.minimum(by0, H - Hm), np.minimum(bx0, W - Wm)
        win = np.lib.stride_tricks.sliding_window_view(image, (Hm, Wm))[y0, x0]
        cwin = np.lib.stride_tricks.sliding_window_view(labels, (Hm, Wm))[y0, x0]
        mine = (idx + 1).astype(np.float32)[:, None, None]
        own = np.where(remap[cwin] == mine, mine, np.float32(0))

        def stack(a):
            return np.concatenate([a, np.zeros((m, g, Wm), dtype=a.dtype)], axis=1).reshape(-1, Wm)

        mosaic, comp, lab = stack(win), stack(cwin), stack(own)
        sx[idx], sy[idx] = x0, y0 - np.arange(m) * (Hm + g)
    else:  # every box's pixels: box j's pixel (r, c) is the image's (by0 + r, bx0 + c) and the mosaic's (oy + r, c)
        oy = np.concatenate([[0], np.cumsum(hh + g)[:-1]])  # a gap of g empty rows between the boxes
        mosaic = np.zeros((int(oy[-1] + hh[-1]), Wm), dtype=image.dtype)
        lab = np.zeros(mosaic.shape, dtype=np.float32)
        comp = np.zeros(mosaic.shape, dtype=labels.dtype)  # the components, as in the image (others' pixels excluded)
        size = hh * ww
        j = np.repeat(np.arange(m), size)
        local = np.arange(int(size.sum())) - np.repeat(np.cumsum(size) - size, size)
        r, c = local // ww[j], local % ww[j]
        iy, ix, my = by0[j] + r, bx0[j] + c, oy[j] + r
        mosaic[my, c] = image[iy, ix]
        cw = labels[iy, ix]
        comp[my, c] = cw
        lab[my, c] = np.where(remap[cw] == idx[j] + 1, (idx[j] + 1).astype(np.float32), np.float32(0))
        sx[idx], sy[idx] = bx0, by0 - oy
    # the blobs' plane reference points moved with their boxes (the plane is in x - xc, y - yc: unchanged)
    out = contour_ellipse_centres(mosaic, lab, k, coef, xc - sx, yc - sy, top, noise,
                                  None if own_comp is None else comp, own_comp, ground)
    uv[idx] = out[0][idx] + np.stack([sx[idx], sy[idx]], axis=1)
    cov[idx], ok[idx], outline[idx] = out[1][idx], out[2][idx], out[3][idx]
    return uv, cov, ok, outline
