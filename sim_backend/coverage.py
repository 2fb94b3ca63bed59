"""Exact area coverage of projected targets in pixel windows: the pure kernels under SimCamera.

* :class:`UndistortionLattice`: undistorted normalised coordinates of any pixel position, from a
  cached lattice (bilinear), and of whole pixel grids at once (:meth:`UndistortionLattice.on_grid`);
* :func:`disc_coverage`, :func:`marker_coverage`, :func:`ring_coverage`: the fraction of each pixel
  of k windows covered by a disc, an ArUco marker patch or a ring-coded target, from every pixel
  corner's ray intersected with the target's plane; pixels a rim or cell edge crosses are
  supersampled (``supersample`` x ``supersample``, n-rooks pattern);
* :func:`damaged_disc_coverage`: a disc whose retro-reflective coating is partly lost (a worn target): the
  whole disc as :func:`disc_coverage` gives it, and the share of each pixel that still reflects. An ``edge``
  loses the coating beyond a chord (a circular segment of the disc's area share ``lost``, on the side
  ``direction``), a ``spot`` under a dark round speck (a disc of area ``lost`` times the dot's, its centre
  ``offset`` radii from the dot's in direction ``direction``). Pixels the chord or the speck's rim crosses are
  supersampled as rim pixels are, so the reflective area is exact (no aliasing bias in its centroid);
  :func:`segment_angle` solves the chord for a share.

Split from :mod:`sim_backend.sim_camera` (which re-exports these names) to keep both modules short.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from calibration.camera import Intrinsics
from calibration.errors import InputError

__all__ = ["ARUCO_DICTIONARY", "DAMAGE_EDGE", "DAMAGE_NONE", "DAMAGE_SPOT", "UndistortionLattice", "aruco_texture",
           "damaged_disc_coverage", "disc_coverage", "marker_coverage", "ring_coverage", "segment_angle"]

ARUCO_DICTIONARY = cv2.aruco.DICT_4X4_250
_MARKER_CELLS = 6  # 4 data bits + 1 black border cell each side
_QUIET_CELLS = 1  # white quiet zone around the marker, in cells
#: how a dot's coating is damaged (``sim_backend.world.World.damage_kind``): intact, lost beyond a chord, under a speck
DAMAGE_NONE, DAMAGE_EDGE, DAMAGE_SPOT = 0, 1, 2

# --- pixel -> ray --------------------------------------------------------------


class UndistortionLattice:
    """Undistorted normalised coordinates of any pixel position, from a cached lattice.

    The undistortion is solved exactly (Gauss-Newton) on a lattice every ``step_px`` pixels
    and interpolated bilinearly between (error ~ step^2 * d2(distortion) / 8: below 1e-3 px
    at 4 px for a lens with |k1| ~ 0.1). Without distortion the map is exact and linear.
    """

    def __init__(self, intr: Intrinsics, step_px: float = 4.0, margin_px: float = 16.0) -> None:
        self.intr = intr
        self.step = float(step_px)
        self.exact = not intr.has_distortion
        if self.exact:
            return
        self.u0 = -0.5 - margin_px
        self.v0 = -0.5 - margin_px
        nu = int(math.ceil((intr.width + 2 * margin_px) / self.step)) + 2
        nv = int(math.ceil((intr.height + 2 * margin_px) / self.step)) + 2
        uu, vv = np.meshgrid(self.u0 + self.step * np.arange(nu), self.v0 + self.step * np.arange(nv))
        xy = intr.pixel_to_normalised(np.stack([uu, vv], axis=-1).reshape(-1, 2))
        self.grid = xy.reshape(nv, nu, 2)

    def __call__(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``u, v: (...)`` pixel positions -> (..., 2) undistorted normalised coordinates."""
        intr = self.intr
        if self.exact:
            return np.stack([(u - intr.cx_px) / intr.fx_px, (v - intr.cy_px) / intr.fy_px], axis=-1)
        nv, nu = self.grid.shape[:2]
        gx = (u - self.u0) / self.step
        gy = (v - self.v0) / self.step
        ix = np.clip(np.floor(gx).astype(np.int64), 0, nu - 2)
        iy = np.clip(np.floor(gy).astype(np.int64), 0, nv - 2)
        fx = (gx - ix)[..., None]  # outside the lattice: linear extrapolation of the edge cell
        fy = (gy - iy)[..., None]
        g = self.grid
        return (
            (1 - fy) * ((1 - fx) * g[iy, ix] + fx * g[iy, ix + 1])
            + fy * ((1 - fx) * g[iy + 1, ix] + fx * g[iy + 1, ix + 1])
        )

    def on_grid(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates on k pixel grids: ``u: (k, nu)``, ``v: (k, nv)`` -> (k, nv, nu, 2).

        The same bilinear interpolation as ``self(u[:, None, :], v[:, :, None])``, evaluated as two small
        matrix products per grid (the interpolation weights are separable; issue 21: the per-point form
        was the targets' largest cost).
        """
        u = np.asarray(u, dtype=float)
        v = np.asarray(v, dtype=float)
        if self.exact:
            return self(np.broadcast_to(u[:, None, :], (len(u), v.shape[1], u.shape[1])),
                        np.broadcast_to(v[:, :, None], (len(u), v.shape[1], u.shape[1])))
        nv, nu = self.grid.shape[:2]
        ax, ix0, nx = _interpolation_matrix((u - self.u0) / self.step, nu)  # (k, nu_pts, nx)
        ay, iy0, ny = _interpolation_matrix((v - self.v0) / self.step, nv)  # (k, nv_pts, ny)
        rows = np.minimum(iy0[:, None] + np.arange(ny), nv - 1)
        cols = np.minimum(ix0[:, None] + np.arange(nx), nu - 1)
        g = self.grid[rows[:, :, None], cols[:, None, :]]  # (k, ny, nx, 2)
        g = np.moveaxis(g, -1, 1)  # (k, 2, ny, nx)
        out = ay[:, None] @ g @ np.swapaxes(ax, 1, 2)[:, None]  # (k, 2, nv_pts, nu_pts)
        return np.moveaxis(out, 1, -1)


def _interpolation_matrix(g: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Linear interpolation weights of positions ``g: (k, p)`` (lattice units) on a lattice of ``n`` nodes.

    Returns ``A: (k, p, m)`` with ``A[i] @ values[i0[i] : i0[i] + m]`` the interpolated values (outside the
    lattice: the edge cell extrapolated linearly), ``i0: (k,)`` and ``m``.
    """
    i = np.clip(np.floor(g).astype(np.int64), 0, n - 2)
    f = g - i
    i0 = i.min(axis=1)
    m = int((i.max(axis=1) - i0).max()) + 2
    a = np.zeros(g.shape + (m,))
    kk, pp = np.indices(g.shape)
    j = i - i0[:, None]
    a[kk, pp, j] = 1 - f
    a[kk, pp, j + 1] = f
    return a, i0, m


def _plane_coords(xy: np.ndarray, centre_c: np.ndarray, e1_c: np.ndarray, e2_c: np.ndarray, n_c: np.ndarray) -> np.ndarray:
    """Intersect rays ``(x, y, 1)`` with target planes, in-plane coordinates (metres).

    Args:
        xy: (k, ..., 2) normalised ray coordinates, one block per target.
        centre_c, e1_c, e2_c, n_c: (k, 3) target centre, in-plane axes, normal (camera frame).
    Returns:
        (k, ..., 2) ``(s, t)`` along ``(e1, e2)`` from the centre; 1e3 where a ray misses.
    """
    k = xy.shape[0]
    shape = (k,) + (1,) * (xy.ndim - 2)
    x, y = xy[..., 0], xy[..., 1]

    def dot_ray(a: np.ndarray) -> np.ndarray:
        return x * a[:, 0].reshape(shape) + y * a[:, 1].reshape(shape) + a[:, 2].reshape(shape)

    denom = dot_ray(n_c)
    num = np.sum(centre_c * n_c, axis=1).reshape(shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = num / denom
    ok = np.isfinite(tt) & (tt > 0)
    c1 = np.sum(centre_c * e1_c, axis=1).reshape(shape)
    c2 = np.sum(centre_c * e2_c, axis=1).reshape(shape)
    s = np.where(ok, tt * dot_ray(e1_c) - c1, 1e3)
    t = np.where(ok, tt * dot_ray(e2_c) - c2, 1e3)
    return np.stack([s, t], axis=-1)


def _subpixel_weights(n: int) -> np.ndarray:
    """Bilinear weights of n*n sub-pixel samples on the corners (00, 01, 10, 11), (n*n, 4).

    The samples form a regular "n-rooks" (multi-jittered) pattern: sample (i, j) sits at
    ``x = (i + (j + 0.5) / n) / n``, ``y = (j + (i + 0.5) / n) / n``, so all n*n samples have
    distinct x and distinct y offsets. An edge parallel to a pixel axis (markers seen square
    on, for instance) is then resolved to 1/n^2 of a pixel instead of 1/n, which removes the
    coherent quantisation a plain n x n grid leaves along such edges.
    """
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    fx = ((i + (j + 0.5) / n) / n).ravel()
    fy = ((j + (i + 0.5) / n) / n).ravel()
    return np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], axis=1)


def _norm2(x: np.ndarray) -> np.ndarray:
    """Length of the 2-vectors ``x: (..., 2)`` (as ``np.linalg.norm(x, axis=-1)``, without its generic reduction)."""
    x0, x1 = x[..., 0], x[..., 1]
    return np.sqrt(x0 * x0 + x1 * x1)


def _half_diagonal(c00: np.ndarray, c01: np.ndarray, c10: np.ndarray, c11: np.ndarray) -> np.ndarray:
    """Half the longer diagonal of each pixel's quadrilateral of corners (..., 2), grown by 2 %: the reach of
    its footprint from its centre."""
    return 0.5 * np.maximum(_norm2(c00 - c11), _norm2(c01 - c10)) * 1.02


def _window_corners(lattice, u0, v0, h, w, shift_px, centre_c, e1_c, e2_c, normal_c, unit=1.0, offset=0.0):
    """The target-plane coordinates of every pixel corner of k windows, ``(st + offset) / unit`` (k, h+1, w+1, 2),
    each pixel's centre (the mean of its four corners, (k, h, w, 2)) and the half diagonal of its footprint."""
    st = _plane_coords(_pixel_lattice(lattice, u0, v0, h, w, shift_px), centre_c, e1_c, e2_c, normal_c)
    if offset != 0.0 or unit != 1.0:
        st = (st + offset) / unit
    c00, c01, c10, c11 = st[:, :-1, :-1], st[:, :-1, 1:], st[:, 1:, :-1], st[:, 1:, 1:]
    return st, 0.25 * (c00 + c01 + c10 + c11), _half_diagonal(c00, c01, c10, c11)


def _corner_blocks(st: np.ndarray, idx: tuple[np.ndarray, ...]) -> np.ndarray:
    """Plane coords of the 4 corners of the pixels ``idx = (k, i, j)``, (b, 4, 2)."""
    k, i, j = idx
    return np.stack([st[k, i, j], st[k, i, j + 1], st[k, i + 1, j], st[k, i + 1, j + 1]], axis=1)


def _pixel_lattice(lattice: UndistortionLattice, u0: np.ndarray, v0: np.ndarray, h: int, w: int, shift: np.ndarray) -> np.ndarray:
    """Normalised coords of the pixel corners of windows at ``(u0, v0)`` (k,), (k, h+1, w+1, 2)."""
    U = u0[:, None] + np.arange(w + 1) - 0.5 - shift[:, 0:1]
    V = v0[:, None] + np.arange(h + 1) - 0.5 - shift[:, 1:2]
    return lattice.on_grid(U, V)


def disc_coverage(
    lattice: UndistortionLattice,
    u0: np.ndarray,
    v0: np.ndarray,
    h: int,
    w: int,
    centre_c: np.ndarray,
    normal_c: np.ndarray,
    e1_c: np.ndarray,
    e2_c: np.ndarray,
    radius_m: float,
    shift_px: np.ndarray,
    supersample: int = 8,
    adaptive: bool = True,
) -> np.ndarray:
    """Fraction of each pixel covered by the image of a disc, for k windows of h x w pixels.

    Args:
        u0, v0: (k,) int pixel index of each window's top-left pixel.
        centre_c, normal_c, e1_c, e2_c: (k, 3) disc centre, normal and in-plane axes (camera frame).
        shift_px: (k, 2) image-plane displacement of each disc's image (jitter), pixels.
    Returns:
        (k, h, w) float coverage in [0, 1].
    """
    st, centre, half_diag = _window_corners(lattice, u0, v0, h, w, shift_px, centre_c, e1_c, e2_c, normal_c)
    rho = _norm2(centre)
    cov = (rho < radius_m).astype(float)
    boundary = np.abs(rho - radius_m) <= half_diag if adaptive else np.ones_like(rho, dtype=bool)
    idx = np.nonzero(boundary)
    if len(idx[0]):
        cov[idx] = _supersampled(st, idx, radius_m, supersample)[0]
    return cov


def _supersampled(st: np.ndarray, idx: tuple[np.ndarray, ...], radius_m: float, supersample: int, dark=None
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """The pixels ``idx = (k, i, j)`` sampled ``supersample`` x ``supersample`` (n-rooks, from their corners' plane
    coordinates ``st``): the share of each inside the disc, and (``dark(s, t, k)`` given: where the coating is lost)
    the share inside and not lost, else None."""
    W = _subpixel_weights(supersample).astype(np.float32)
    C = _corner_blocks(st, idx).astype(np.float32)
    r2 = np.float32(radius_m * radius_m)
    al = np.empty(len(idx[0]))
    wh = np.empty(len(idx[0])) if dark is not None else None
    for a in range(0, len(al), 32768):
        sl = slice(a, a + 32768)
        ss = C[sl, :, 0] @ W.T
        tt = C[sl, :, 1] @ W.T
        ins = ss * ss + tt * tt <= r2
        al[sl] = np.mean(ins, axis=1)
        if dark is not None:
            wh[sl] = np.mean(ins & ~dark(ss.astype(float), tt.astype(float), idx[0][sl, None]), axis=1)
    return al, wh


def segment_angle(share: np.ndarray) -> np.ndarray:
    """Central angle (rad) of the circular segment that holds ``share`` (0..1) of its disc's area, elementwise.

    The segment cut off by a chord that subtends ``theta`` at the centre has the area share
    ``(theta - sin theta) / (2 pi)``, increasing from 0 to 1 on ``[0, 2 pi]``; solved by bisection (60 halvings:
    to the float's resolution). The chord lies ``cos(theta / 2)`` radii from the centre.
    """
    f = np.clip(np.asarray(share, dtype=float), 0.0, 1.0)
    lo, hi = np.zeros_like(f), np.full_like(f, 2 * np.pi)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        low = (mid - np.sin(mid)) < 2 * np.pi * f
        lo, hi = np.where(low, mid, lo), np.where(low, hi, mid)
    return 0.5 * (lo + hi)


def damaged_disc_coverage(
    lattice: UndistortionLattice,
    u0: np.ndarray,
    v0: np.ndarray,
    h: int,
    w: int,
    centre_c: np.ndarray,
    normal_c: np.ndarray,
    e1_c: np.ndarray,
    e2_c: np.ndarray,
    radius_m: float,
    kind: np.ndarray,
    lost: np.ndarray,
    direction_rad: np.ndarray,
    offset: np.ndarray,
    shift_px: np.ndarray,
    supersample: int = 8,
    adaptive: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Coverage of k discs whose reflective coating is partly lost, for k windows of h x w pixels.

    Args:
        u0, v0, centre_c, normal_c, e1_c, e2_c, radius_m, shift_px: as :func:`disc_coverage`.
        kind: (k,) int, :data:`DAMAGE_NONE`, :data:`DAMAGE_EDGE` or :data:`DAMAGE_SPOT`.
        lost: (k,) share of the disc's area that does not reflect (edge: 0..1; spot: its speck, of radius
            ``sqrt(lost) * radius_m``, lies inside the disc).
        direction_rad: (k,) in-plane direction from the disc's centre to the lost side (edge) or to the speck's
            centre (spot), from ``e1`` towards ``e2``.
        offset: (k,) spot: its centre's distance from the disc's centre, in disc radii (edge: unused).
    Returns:
        alpha: (k, h, w) fraction of each pixel covered by the disc (as :func:`disc_coverage`).
        white: (k, h, w) fraction covered by its part that still reflects.
    """
    st, centre, half_diag = _window_corners(lattice, u0, v0, h, w, shift_px, centre_c, e1_c, e2_c, normal_c)
    k = len(u0)
    kind = np.asarray(kind).reshape(k)
    lost = np.asarray(lost, dtype=float).reshape(k)
    phi = np.asarray(direction_rad, dtype=float).reshape(k)
    dx, dy = np.cos(phi), np.sin(phi)
    edge, spot = kind == DAMAGE_EDGE, kind == DAMAGE_SPOT
    chord = np.where(edge, radius_m * np.cos(0.5 * segment_angle(np.where(edge, lost, 0.0))), np.inf)
    q = np.where(spot, np.asarray(offset, dtype=float).reshape(k) * radius_m, 0.0)
    qx, qy = q * dx, q * dy
    r_spot = np.where(spot, np.sqrt(np.where(spot, lost, 0.0)) * radius_m, 0.0)

    def dark(s: np.ndarray, t: np.ndarray, kk: np.ndarray) -> np.ndarray:
        """Whether the in-plane points ``(s, t)`` of targets ``kk`` lie where the coating is lost."""
        beyond = s * dx[kk] + t * dy[kk] > chord[kk]
        ds, dt = s - qx[kk], t - qy[kk]
        return beyond | (ds * ds + dt * dt < r_spot[kk] ** 2)

    kk = np.arange(k)[:, None, None]
    s, t = centre[..., 0], centre[..., 1]
    rho = _norm2(centre)
    inside = rho < radius_m
    alpha = inside.astype(float)
    white = (inside & ~dark(s, t, kk)).astype(float)
    if adaptive:
        near_rim = np.abs(rho - radius_m) <= half_diag
        near_chord = (edge[kk] & (np.abs(s * dx[kk] + t * dy[kk] - chord[kk]) <= half_diag)
                      & (rho <= radius_m + half_diag))
        near_speck = spot[kk] & (np.abs(np.hypot(s - qx[kk], t - qy[kk]) - r_spot[kk]) <= half_diag)
        boundary = near_rim | near_chord | near_speck
    else:
        boundary = np.ones_like(rho, dtype=bool)
    idx = np.nonzero(boundary)
    if len(idx[0]):
        alpha[idx], white[idx] = _supersampled(st, idx, radius_m, supersample, dark)
    return alpha, white


def aruco_texture(code: int) -> np.ndarray:
    """(8, 8) float texture, 1 = white, of ArUco ``code`` (DICT_4X4_250) with its quiet zone."""
    d = cv2.aruco.getPredefinedDictionary(ARUCO_DICTIONARY)
    n_codes = d.bytesList.shape[0]
    if not 0 <= int(code) < n_codes:
        raise InputError(f"coded target id {code} is outside DICT_4X4_250 (0..{n_codes - 1}); renumber the coded targets")
    img = cv2.aruco.generateImageMarker(d, int(code), _MARKER_CELLS, borderBits=1)
    return np.pad(img.astype(float) / 255.0, _QUIET_CELLS, constant_values=1.0)


def marker_coverage(
    lattice: UndistortionLattice,
    u0: np.ndarray,
    v0: np.ndarray,
    h: int,
    w: int,
    centre_c: np.ndarray,
    normal_c: np.ndarray,
    e1_c: np.ndarray,
    e2_c: np.ndarray,
    side_m: float,
    textures: np.ndarray,
    shift_px: np.ndarray,
    supersample: int = 8,
    adaptive: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Coverage of coded-marker patches (marker + quiet zone) for k windows.

    Args:
        side_m: marker side (outer edge of the black border).
        textures: (k, G, G) 1 = white cells, G = 8 (marker + quiet zone).
    Returns:
        alpha: (k, h, w) fraction of each pixel covered by the patch.
        white: (k, h, w) fraction of each pixel covered by white cells.
    """
    G = textures.shape[1]
    cell = side_m / _MARKER_CELLS
    half = 0.5 * G * cell
    # cell coordinates, the patch spans [0, G)
    ab, centre, hd = _window_corners(lattice, u0, v0, h, w, shift_px, centre_c, e1_c, e2_c, normal_c, cell, half)
    a, b = centre[..., 0], centre[..., 1]
    outside = (a < -hd) | (a > G + hd) | (b < -hd) | (b > G + hd)
    uniform = (np.abs(a - np.round(a)) > hd) & (np.abs(b - np.round(b)) > hd)
    ia = np.clip(np.floor(a).astype(np.int64), 0, G - 1)
    ib = np.clip(np.floor(b).astype(np.int64), 0, G - 1)
    inside = ~outside & (a >= 0) & (a < G) & (b >= 0) & (b < G)
    kk = np.broadcast_to(np.arange(len(u0))[:, None, None], a.shape)
    alpha = inside.astype(float)
    white = np.where(inside, textures[kk, ib, ia], 0.0)
    # a pixel across the edges of cells of one colour, all in the patch, is uniform too (issue 21: half of a
    # marker's cell edges part equal cells; supersampling them gave alpha 1 and that colour exactly)
    a0, a1 = np.floor(a - hd).astype(np.int64), np.floor(a + hd).astype(np.int64)
    b0, b1 = np.floor(b - hd).astype(np.int64), np.floor(b + hd).astype(np.int64)
    near = ~outside & ~uniform & (a0 >= 0) & (a1 < G) & (b0 >= 0) & (b1 < G) & (a1 - a0 <= 1) & (b1 - b0 <= 1)
    q = np.nonzero(near)
    t00 = textures[q[0], b0[q], a0[q]]
    one = ((t00 == textures[q[0], b0[q], a1[q]]) & (t00 == textures[q[0], b1[q], a0[q]])
           & (t00 == textures[q[0], b1[q], a1[q]]))
    uniform[q[0][one], q[1][one], q[2][one]] = True
    boundary = ~outside & ~uniform if adaptive else np.ones_like(a, dtype=bool)
    idx = np.nonzero(boundary)
    if len(idx[0]):
        W = _subpixel_weights(supersample)
        C = _corner_blocks(ab, idx)
        al = np.empty(len(idx[0]))
        wh = np.empty(len(idx[0]))
        for s0 in range(0, len(al), 32768):
            sl = slice(s0, s0 + 32768)
            sa = C[sl, :, 0] @ W.T
            sb = C[sl, :, 1] @ W.T
            ins = (sa >= 0) & (sa < G) & (sb >= 0) & (sb < G)
            ja = np.clip(np.floor(sa).astype(np.int64), 0, G - 1)
            jb = np.clip(np.floor(sb).astype(np.int64), 0, G - 1)
            tex = textures[idx[0][sl, None], jb, ja]
            al[sl] = ins.mean(axis=1)
            wh[sl] = np.where(ins, tex, 0.0).mean(axis=1)
        alpha[idx] = al
        white[idx] = wh
    return alpha, white


def ring_coverage(
    lattice: UndistortionLattice,
    u0: np.ndarray,
    v0: np.ndarray,
    h: int,
    w: int,
    centre_c: np.ndarray,
    normal_c: np.ndarray,
    e1_c: np.ndarray,
    e2_c: np.ndarray,
    radius_m: float,
    bits: np.ndarray,
    family,
    shift_px: np.ndarray,
    supersample: int = 8,
    adaptive: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Coverage of ring-coded targets (``calibration.ringcodes`` layout) for k windows.

    Args:
        radius_m: the centre dot's radius R; the patch (quiet zone) reaches ``family.quiet`` R.
        bits: (k, n) 0/1 sector bits, sector b from ``e1`` towards ``e2``.
        family: the ``calibration.ringcodes.RingFamily`` (its radii).
    Returns:
        alpha: (k, h, w) fraction of each pixel covered by the patch; white: by the dot and the set sectors.
    """
    n, inner, outer, quiet = bits.shape[1], family.inner, family.outer, family.quiet
    st, centre, hd = _window_corners(lattice, u0, v0, h, w, shift_px, centre_c, e1_c, e2_c, normal_c, radius_m)
    kk = np.broadcast_to(np.arange(len(u0))[:, None, None], hd.shape)

    def shade(s, t, kidx):
        rho = np.hypot(s, t)
        sector = np.floor((np.arctan2(t, s) % (2 * np.pi)) / (2 * np.pi / n)).astype(np.int64) % n
        inring = (rho >= inner) & (rho <= outer)
        white = (rho <= 1.0) | (inring & (bits[kidx, sector] > 0))
        return (rho <= quiet).astype(float), white.astype(float)

    alpha, white = shade(centre[..., 0], centre[..., 1], kk)
    rho = _norm2(centre)
    near_circle = np.zeros(rho.shape, dtype=bool)
    for rr in (1.0, inner, outer, quiet):
        near_circle |= np.abs(rho - rr) <= hd
    ang = np.arctan2(centre[..., 1], centre[..., 0]) % (2 * np.pi / n)
    near_edge = (np.minimum(ang, 2 * np.pi / n - ang) * rho <= hd) & (rho >= inner - hd) & (rho <= outer + hd)
    boundary = (near_circle | near_edge) if adaptive else np.ones_like(rho, dtype=bool)
    idx = np.nonzero(boundary)
    if len(idx[0]):
        W = _subpixel_weights(supersample)
        C = _corner_blocks(st, idx)
        for a0 in range(0, len(idx[0]), 32768):
            sl = slice(a0, a0 + 32768)
            sa = C[sl, :, 0] @ W.T
            sb = C[sl, :, 1] @ W.T
            al, wh = shade(sa, sb, idx[0][sl, None])
            alpha[idx[0][sl], idx[1][sl], idx[2][sl]] = al.mean(axis=1)
            white[idx[0][sl], idx[1][sl], idx[2][sl]] = wh.mean(axis=1)
    return alpha, white
