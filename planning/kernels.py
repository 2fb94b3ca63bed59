"""Compiled (numba) kernels of the planner's hot loops, on the candidate x target information kept
sparse (planning.sparse_info: row ``i`` is ``indices[starts[i]:ends[i]]``, its visible targets in increasing
order, and ``data[starts[i]:ends[i]]``, their ``(., 6)`` information).

Each kernel does exactly the floating-point operations of the NumPy code it replaces, in the same order
(no fast-math: no reassociation, no fused multiply-add), so the planner's choices and figures are the same
bit for bit; the tests compare them with the NumPy reference. What they save is the work NumPy cannot skip:
the zeros of the dense ``(candidates, targets, 6)`` array, the temporaries of the closed-form 3x3 inverse, and
candidates whose score already exceeds the best exchange found (an exact early exit).
docs/decisions/0026-planspeed-numba.md says what each bought.

* :func:`population_fitness`: the evolutionary search's fitness of whole populations (limiting error
  propagation, :func:`planning.uncertainty.evaluate_networks` + criterion + violation) with no
  ``population x targets`` array;
* :func:`strict_step`: one best-improvement exchange of :mod:`planning.refine`;
* :func:`gather`: ``dense[rows][:, cols]`` of a CSR information for few columns (binary search per pair);
* :func:`pair_information`: ``J^T J`` of (pose, point) pairs (:func:`planning.uncertainty.point_information`);
* :func:`unlinked_stations`: the stations of each network outside its largest block of images linked by common
  targets (what ADJUST's screening would drop);
* :func:`information_rows`, :func:`information_rows_model`: the candidate x target information, CSR, each ray
  weighted by one sigma per target or by the detector model's sigma of that ray.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

# relative determinant below which a normal matrix is singular (planning.uncertainty._DET_MIN)
DET_MIN = 1e-12


@njit(cache=True, nogil=True, inline="always")
def _sigma_invert6(n0, n1, n2, n3, n4, n5, rays, min_rays):
    """sqrt(trace(N^-1)) as :func:`planning.uncertainty._invert6` computes it (inf where insufficient)."""
    tr = n0 + n3 + n5
    s = tr / 3.0 if tr > 0 else 1.0
    a, b, c, d, e, f = n0 / s, n1 / s, n2 / s, n3 / s, n4 / s, n5 / s
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    D = a * f - c * c
    F = a * d - b * b
    det = a * A + b * B + c * C
    if rays >= min_rays and det > DET_MIN:
        k = 1.0 / (det * s)
        return math.sqrt((A + D + F) * k)
    return math.inf


@njit(cache=True, nogil=True, inline="always")
def sigma6(a, b, c, d, e, f, rays, min_rays):
    """sqrt(trace(N^-1)) as :func:`planning.refine._sigma6` computes it (inf where insufficient).

    The singularity threshold's ``s^3`` is ``s * s * s`` here, NumPy's ``s ** 3`` calls ``pow``: the two
    can differ by an ulp, which changes the verdict only for a determinant within 1e-16 of the threshold."""
    tr = a + d + f
    A = d * f - e * e
    D = a * f - c * c
    F = a * d - b * b
    det = a * A + b * (c * e - b * f) + c * (b * e - c * d)
    s = tr / 3.0 if tr > 0 else 1.0
    s3 = s * s * s
    if rays >= min_rays and det > DET_MIN * s3:
        return math.sqrt((A + D + F) / det)
    return math.inf


@njit(cache=True, nogil=True)
def sigma6_rows(N, cnt, min_rays):
    """:func:`sigma6` of ``N: (n, 6)`` float64, ``cnt: (n,)``; (n,) float64."""
    out = np.empty(N.shape[0])
    for t in range(N.shape[0]):
        out[t] = sigma6(N[t, 0], N[t, 1], N[t, 2], N[t, 3], N[t, 4], N[t, 5], cnt[t], min_rays)
    return out


@njit(cache=True, nogil=True)
def population_fitness(starts, ends, indices, data, stations, n, min_rays, kind, required, out_value, out_violation,
                       out_short):
    """Fitness of networks ``stations: (p, k)`` (sorted, -1 = off, no repeats) on a CSR information.

    The information of a network's stations is summed per target in the information's precision and
    station order (as ``evaluate_networks``), inverted in closed form (``_invert6``), and reduced:
    ``kind`` 0: worst sigma over the sufficient targets; 2: max sigma / required over them. ``out_value (p,)``
    gets it (0 when no target is sufficient, the criterion's ``penalty=0`` form), ``out_violation (p,)`` the
    shortfall of rays summed over targets plus one per target with enough rays but a singular geometry,
    ``out_short (p,)`` the targets not sufficient.
    """
    p, k = stations.shape
    acc = np.zeros((n, 6), dtype=data.dtype)
    cnt = np.zeros(n, dtype=np.int32)
    for q in range(p):
        acc[:] = 0
        cnt[:] = 0
        for j in range(k):
            c = stations[q, j]
            if c < 0:
                continue
            for e in range(starts[c], ends[c]):
                t = indices[e]
                for u in range(6):
                    acc[t, u] += data[e, u]
                cnt[t] += 1
        best = -math.inf
        n_ok = 0
        short = 0
        singular = 0
        for t in range(n):
            sg = _sigma_invert6(np.float64(acc[t, 0]), np.float64(acc[t, 1]), np.float64(acc[t, 2]),
                                np.float64(acc[t, 3]), np.float64(acc[t, 4]), np.float64(acc[t, 5]), cnt[t], min_rays)
            if sg < math.inf:
                n_ok += 1
                v = sg / required[t] if kind == 2 else sg
                if v > best:
                    best = v
            else:
                if cnt[t] < min_rays:
                    short += min_rays - cnt[t]
                else:
                    singular += 1
        out_value[q] = best if n_ok > 0 else 0.0
        out_violation[q] = short + singular
        out_short[q] = n - n_ok


@njit(cache=True, nogil=True)
def _root(parent, a):
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@njit(cache=True, nogil=True, inline="always")
def _popcount(x):
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return (x * np.uint64(0x0101010101010101)) >> np.uint64(56)


@njit(cache=True, nogil=True)
def unlinked_stations(bits, stations, link, sole_links, out):
    """Stations of each network ``stations: (p, k)`` (-1 = off, no repeats) outside its largest linked block;
    ``out (p,)``. ``bits: (m, w)`` uint64, the targets each candidate sees as a bitset (:func:`pack_rows`). Two
    stations are linked when they see ``link`` or more common targets; blocks are the connected components (ADJUST's
    screening drops the images of every block but the main one: cell/stages/screen.py ``LINK_TARGETS``). 0 when
    the network is one block; then, with ``sole_links``, the number of stations that are the only link of some
    part of the block to the rest (articulation points of the link graph)."""
    p, k = stations.shape
    w = bits.shape[1]
    linked = np.zeros((k, k), dtype=np.bool_)
    parent = np.empty(k, dtype=np.int64)
    size = np.empty(k, dtype=np.int64)
    for q in range(p):
        active = 0
        for a in range(k):
            ca = stations[q, a]
            if ca < 0:
                continue
            active += 1
            for b in range(a + 1, k):
                cb = stations[q, b]
                linked[a, b] = False
                if cb < 0:
                    continue
                c = np.uint64(0)
                for u in range(w):  # common targets, counted until the link is certain
                    c += _popcount(bits[ca, u] & bits[cb, u])
                    if c >= link:
                        linked[a, b] = True
                        break
        for j in range(k):
            parent[j] = j
        for a in range(k):
            if stations[q, a] < 0:
                continue
            for b in range(a + 1, k):
                if stations[q, b] >= 0 and linked[a, b]:
                    ra, rb = _root(parent, a), _root(parent, b)
                    if ra != rb:
                        parent[rb] = ra
        size[:] = 0
        best = 0
        for j in range(k):
            if stations[q, j] >= 0:
                r = _root(parent, j)
                size[r] += 1
                if size[r] > best:
                    best = size[r]
        out[q] = active - best
        if out[q] > 0 or not sole_links:
            continue
        # one block: a station whose image is the only link of a part of the network to the rest (removing it
        # splits the block) counts too
        for x in range(k):
            if stations[q, x] < 0:
                continue
            for j in range(k):
                parent[j] = j
            for a in range(k):
                if a == x or stations[q, a] < 0:
                    continue
                for b in range(a + 1, k):
                    if b != x and stations[q, b] >= 0 and linked[a, b]:
                        ra, rb = _root(parent, a), _root(parent, b)
                        if ra != rb:
                            parent[rb] = ra
            roots = 0
            for j in range(k):
                if j != x and stations[q, j] >= 0 and _root(parent, j) == j:
                    roots += 1
            if roots > 1:
                out[q] += 1


def count_unlinked(bits: np.ndarray, stations: np.ndarray, link: int, sole_links: bool = True) -> np.ndarray:
    """(p,) float :func:`unlinked_stations` of networks ``stations: (p, k)`` (sorted, -1 off, no repeats) of the
    candidates whose visibility ``bits`` holds (:func:`pack_rows`), on two threads."""
    import os

    st = np.ascontiguousarray(stations, dtype=np.int64).reshape(len(stations), -1)
    out = np.zeros(len(st), dtype=np.int64)
    in_two(len(st), lambda lo, hi: unlinked_stations(bits, st[lo:hi], int(link), bool(sole_links), out[lo:hi]),
           min_size=2 if (os.cpu_count() or 1) > 1 else len(st) + 1)
    return out.astype(float)


def pack_rows(visible: np.ndarray) -> np.ndarray:
    """Each row of ``visible: (m, n)`` bool as a bitset, ``(m, ceil(n / 64))`` uint64 (:func:`unlinked_stations`)."""
    v = np.asarray(visible, dtype=bool)
    packed = np.packbits(v, axis=1, bitorder="little")
    pad = (-packed.shape[1]) % 8
    if pad or packed.shape[1] == 0:
        packed = np.concatenate([packed, np.zeros((len(v), pad or 8), dtype=np.uint8)], axis=1)
    return np.ascontiguousarray(packed).view(np.uint64)


@njit(cache=True, nogil=True)
def add_rows(starts, ends, indices, data, acc, rows, cand):
    """``acc[rows[i]] += dense[cand[i]]`` for each i (rows distinct), in the data's precision."""
    for i in range(cand.shape[0]):
        r = rows[i]
        for e in range(starts[cand[i]], ends[cand[i]]):
            t = indices[e]
            for u in range(6):
                acc[r, t, u] += data[e, u]


@njit(cache=True, nogil=True)
def _find(indices, lo, hi, t):
    """Position of ``t`` in the sorted ``indices[lo:hi]``, or -1."""
    while lo < hi:
        mid = (lo + hi) >> 1
        v = indices[mid]
        if v < t:
            lo = mid + 1
        elif v > t:
            hi = mid
        else:
            return mid
    return -1


@njit(cache=True, nogil=True)
def gather(starts, ends, indices, data, rows, cols):
    """``dense[rows][:, cols]``: (len(rows), len(cols), 6) in the data's precision, zero where not visible."""
    out = np.zeros((rows.shape[0], cols.shape[0], 6), dtype=data.dtype)
    for i in range(rows.shape[0]):
        lo, hi = starts[rows[i]], ends[rows[i]]
        for jj in range(cols.shape[0]):
            e = _find(indices, lo, hi, cols[jj])
            if e >= 0:
                for u in range(6):
                    out[i, jj, u] = data[e, u]
    return out


@njit(cache=True, nogil=True)
def rows_dense(starts, ends, indices, data, rows, n):
    """``dense[rows]``: (len(rows), n, 6) in the data's precision."""
    out = np.zeros((rows.shape[0], n, 6), dtype=data.dtype)
    for i in range(rows.shape[0]):
        for e in range(starts[rows[i]], ends[rows[i]]):
            for u in range(6):
                out[i, indices[e], u] = data[e, u]
    return out


@njit(cache=True, nogil=True)
def network_normal(starts, ends, indices, data, stations, n):
    """Normal matrices ``(n, 6)`` float64 and ray counts ``(n,)`` int32 of a network: the stations' rows
    summed in float64, one station after the other (``info[stations].sum(axis=0, dtype=np.float64)``)."""
    N = np.zeros((n, 6))
    cnt = np.zeros(n, dtype=np.int32)
    for j in range(stations.shape[0]):
        c = stations[j]
        for e in range(starts[c], ends[c]):
            t = indices[e]
            for u in range(6):
                N[t, u] += np.float64(data[e, u])
            cnt[t] += 1
    return N, cnt


@njit(cache=True, nogil=True)
def exchange(starts, ends, indices, data, N, cnt, sig, old, new, min_rays):
    """Replace station ``old`` by ``new`` in the network's ``N (n, 6)``, ``cnt`` and ``sig`` (in place):
    ``N += info[new] - info[old]`` on the targets either sees, and their sigmas recomputed."""
    a, a1 = starts[old], ends[old]
    b, b1 = starts[new], ends[new]
    while a < a1 or b < b1:
        ta = indices[a] if a < a1 else 1 << 30
        tb = indices[b] if b < b1 else 1 << 30
        if ta == tb:
            t = ta
            for u in range(6):
                N[t, u] += np.float64(data[b, u]) - np.float64(data[a, u])
            a += 1
            b += 1
        elif ta < tb:
            t = ta
            for u in range(6):
                N[t, u] += 0.0 - np.float64(data[a, u])
            cnt[t] -= 1
            a += 1
        else:
            t = tb
            for u in range(6):
                N[t, u] += np.float64(data[b, u])
            cnt[t] += 1
            b += 1
        sig[t] = sigma6(N[t, 0], N[t, 1], N[t, 2], N[t, 3], N[t, 4], N[t, 5], cnt[t], min_rays)


_TOP = 32


@njit(cache=True, nogil=True)
def removal_sigmas(starts, ends, indices, data, S, N, cnt, min_rays, off, j0, j1, srm):
    """Sigma of each target a station sees, without that station: ``srm[off[j]:off[j+1]]`` for the
    entries of station ``S[j]``, ``j0 <= j < j1`` (``N - info``, one ray fewer)."""
    for j in range(j0, j1):
        e0 = starts[S[j]]
        for q in range(off[j], off[j + 1]):
            e = e0 + q - off[j]
            t = indices[e]
            srm[q] = sigma6(N[t, 0] - np.float64(data[e, 0]), N[t, 1] - np.float64(data[e, 1]),
                            N[t, 2] - np.float64(data[e, 2]), N[t, 3] - np.float64(data[e, 3]),
                            N[t, 4] - np.float64(data[e, 4]), N[t, 5] - np.float64(data[e, 5]), cnt[t] - 1, min_rays)


@njit(cache=True, nogil=True)
def strict_step(starts, ends, indices, data, vis, S, N, cnt, sig, target, pool, min_rays, off, srm):
    """The best exchange lowering the worst sigma below ``target`` (planning.refine._strict_step).

    ``vis: (m, n)`` bool, the information's visibility; ``S: (k,)`` the network; ``N, cnt, sig`` its normal
    matrices, rays and sigmas; ``pool``: the candidates a station may move to, in order; ``srm`` the
    removal sigmas (:func:`removal_sigmas`) at offsets ``off``.
    Returns ``(new_worst, slot, candidate)``; slot -1 when no exchange lowers the worst.

    Removing station ``j`` changes only the targets it sees: their sigmas without it are computed on its
    entries, every other target keeps ``sig``. A target is critical for ``j`` when its sigma without ``j``
    is ``>= target``; an exchange ``(j, c)`` helps only if ``c`` sees all of them, and its new worst is
    the larger of the worst over the non-critical targets (``rest``) and over the critical ones with ``c``.
    Candidates are scored in pool order and dropped as soon as a critical target reaches the best found.
    """
    k = S.shape[0]
    n = sig.shape[0]
    # min over stations of the removal sigma (stations that do not see t keep sig[t]), and each station's
    # worst non-critical removal sigma
    minrm = sig.copy()
    for t in range(n):
        if cnt[t] >= k:  # every station sees t: min over the stations only
            minrm[t] = math.inf
    rest = np.zeros(k)
    for j in range(k):
        e0 = starts[S[j]]
        r = 0.0
        for q in range(off[j], off[j + 1]):
            v = srm[q]
            t = indices[e0 + q - off[j]]
            if v < minrm[t]:
                minrm[t] = v
            if v < target and v > r:
                r = v
        rest[j] = r
    # globally critical targets, and the largest non-critical sigmas (descending)
    n_g = 0
    for t in range(n):
        if sig[t] >= target:
            n_g += 1
    crit_g = np.empty(n_g, dtype=np.int64)
    top = np.full(_TOP, -1, dtype=np.int64)
    n_top = 0
    g = 0
    for t in range(n):
        v = sig[t]
        if v >= target:
            crit_g[g] = t
            g += 1
            continue
        if n_top == _TOP and v <= sig[top[n_top - 1]]:
            continue
        # insert, keeping the first of equal values first (a stable descending order)
        pos = n_top if n_top < _TOP else _TOP - 1
        while pos > 0 and sig[top[pos - 1]] < v:
            pos -= 1
        last = n_top if n_top < _TOP else _TOP - 1
        for r in range(last, pos, -1):
            top[r] = top[r - 1]
        top[pos] = t
        if n_top < _TOP:
            n_top += 1
    # rest[j] also covers the targets j does not see: their sigmas, the non-critical ones
    for j in range(k):
        r = rest[j]
        row = vis[S[j]]
        found = False
        for h in range(n_top):
            t = top[h]
            if not row[t]:
                if sig[t] > r:
                    r = sig[t]
                found = True
                break
        if not found and n_top == _TOP:  # every listed target is seen by j: scan the others
            for t in range(n):
                if not row[t] and sig[t] < target and sig[t] > r:
                    r = sig[t]
        rest[j] = r
    # the current worst target is critical for every station: only candidates seeing it can help
    wt = 0
    for t in range(n):
        if minrm[t] > minrm[wt]:
            wt = t
    order = np.argsort(rest, kind="mergesort")
    best_w, best_j, best_c = target, -1, -1
    cj = np.empty(n, dtype=np.int64)
    base = np.empty((n, 6))
    cbase = np.empty(n, dtype=np.int64)
    for oi in range(k):
        j = order[oi]
        if rest[j] >= best_w:
            break
        row = vis[S[j]]
        nc = 0
        for g in range(n_g):
            t = crit_g[g]
            if not row[t]:
                cj[nc] = t
                for u in range(6):
                    base[nc, u] = N[t, u]
                cbase[nc] = cnt[t]
                nc += 1
        e0 = starts[S[j]]
        for q in range(off[j], off[j + 1]):
            if srm[q] >= target:
                e = e0 + q - off[j]
                t = indices[e]
                cj[nc] = t
                for u in range(6):
                    base[nc, u] = N[t, u] - np.float64(data[e, u])
                cbase[nc] = cnt[t] - 1
                nc += 1
        for pi in range(pool.shape[0]):
            c = pool[pi]
            vrow = vis[c]
            if not vrow[wt]:
                continue
            sees = True
            for h in range(nc):
                if not vrow[cj[h]]:
                    sees = False
                    break
            if not sees:
                continue
            lo, hi = starts[c], ends[c]
            mx = -math.inf
            for h in range(nc):
                e = _find(indices, lo, hi, cj[h])
                if e >= 0:
                    v = sigma6(base[h, 0] + np.float64(data[e, 0]), base[h, 1] + np.float64(data[e, 1]),
                               base[h, 2] + np.float64(data[e, 2]), base[h, 3] + np.float64(data[e, 3]),
                               base[h, 4] + np.float64(data[e, 4]), base[h, 5] + np.float64(data[e, 5]),
                               cbase[h] + 1, min_rays)
                else:
                    v = sigma6(base[h, 0] + 0.0, base[h, 1] + 0.0, base[h, 2] + 0.0, base[h, 3] + 0.0,
                               base[h, 4] + 0.0, base[h, 5] + 0.0, cbase[h] + 1, min_rays)
                if v > mx:
                    mx = v
                    if mx >= best_w:
                        break
            w = mx if mx > rest[j] else rest[j]
            if w < best_w:
                best_w, best_j, best_c = w, j, c
    return best_w, best_j, best_c


@njit(cache=True, nogil=True)
def geometric_ok(part_from_cam, cam_from_part, xyz, normals, cos_max, near, far, size_px, min_px, cam, out):
    """Every visibility test but occlusion (planning.visibility.geometric_visibility), pair by pair with an
    early exit; ``out (m, n)`` bool. ``cam``: fx, fy, cx, cy, k1, k2, k3, p1, p2, distorted (0/1), and the
    image limits umin, umax, vmin, vmax (the margin applied)."""
    fx, fy, cx, cy, k1, k2, k3, p1, p2 = cam[0], cam[1], cam[2], cam[3], cam[4], cam[5], cam[6], cam[7], cam[8]
    distorted = cam[9] != 0.0
    umin, umax, vmin, vmax = cam[10], cam[11], cam[12], cam[13]
    m, n = out.shape
    xn2 = np.empty(n)
    xx = np.empty(n)
    for t in range(n):
        xn2[t] = xyz[t, 0] * normals[t, 0] + xyz[t, 1] * normals[t, 1] + xyz[t, 2] * normals[t, 2]
        xx[t] = xyz[t, 0] * xyz[t, 0] + xyz[t, 1] * xyz[t, 1] + xyz[t, 2] * xyz[t, 2]
    for i in range(m):
        e0, e1, e2 = part_from_cam[i, 0, 3], part_from_cam[i, 1, 3], part_from_cam[i, 2, 3]
        ee = e0 * e0 + e1 * e1 + e2 * e2
        R = cam_from_part[i]
        for t in range(n):
            out[i, t] = False
            x0, x1, x2 = xyz[t, 0], xyz[t, 1], xyz[t, 2]
            sn = (e0 * normals[t, 0] + e1 * normals[t, 1] + e2 * normals[t, 2]) - xn2[t]
            d2 = ee - 2.0 * (e0 * x0 + e1 * x1 + e2 * x2) + xx[t]
            if not sn >= cos_max * math.sqrt(max(d2, 1e-24)):
                continue
            z = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2 + R[2, 3]
            if not (z > 1e-9 and z >= near and z <= far and size_px >= min_px * z):
                continue
            xn = (R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2 + R[0, 3]) / z
            yn = (R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2 + R[1, 3]) / z
            if distorted:
                r2 = xn * xn + yn * yn
                radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
                yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
            else:
                xd, yd = xn, yn
            u = fx * xd + cx
            v = fy * yd + cy
            out[i, t] = u >= umin and u <= umax and v >= vmin and v <= vmax


@njit(cache=True, nogil=True, inline="always")
def _pair_info(R, X0, X1, X2, fx, fy, k1, k2, k3, p1, p2, distorted, out):
    """``J^T J`` (upper triangle, 6) of one pose ``R: (4, 4) cam_from_part`` and point, J = d(uv)/dX."""
    xc0 = R[0, 0] * X0 + R[0, 1] * X1 + R[0, 2] * X2 + R[0, 3]
    xc1 = R[1, 0] * X0 + R[1, 1] * X1 + R[1, 2] * X2 + R[1, 3]
    xc2 = R[2, 0] * X0 + R[2, 1] * X1 + R[2, 2] * X2 + R[2, 3]
    iz = 1.0 / xc2
    xn, yn = xc0 * iz, xc1 * iz
    if distorted:
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dr = k1 + 2 * k2 * r2 + 3 * k3 * r2 * r2
        d00 = radial + 2 * xn * xn * dr + 2 * p1 * yn + 6 * p2 * xn
        d01 = 2 * xn * yn * dr + 2 * p1 * xn + 2 * p2 * yn
        d11 = radial + 2 * yn * yn * dr + 6 * p1 * yn + 2 * p2 * xn
        d10 = d01
    else:
        d00, d01, d10, d11 = 1.0, 0.0, 0.0, 1.0
    a0, b0 = d00 * fx * iz, d01 * fx * iz
    a1, b1 = d10 * fy * iz, d11 * fy * iz
    c0, c1 = -(a0 * xn + b0 * yn), -(a1 * xn + b1 * yn)
    j00 = a0 * R[0, 0] + b0 * R[1, 0] + c0 * R[2, 0]
    j01 = a0 * R[0, 1] + b0 * R[1, 1] + c0 * R[2, 1]
    j02 = a0 * R[0, 2] + b0 * R[1, 2] + c0 * R[2, 2]
    j10 = a1 * R[0, 0] + b1 * R[1, 0] + c1 * R[2, 0]
    j11 = a1 * R[0, 1] + b1 * R[1, 1] + c1 * R[2, 1]
    j12 = a1 * R[0, 2] + b1 * R[1, 2] + c1 * R[2, 2]
    out[0] = j00 * j00 + j10 * j10
    out[1] = j00 * j01 + j10 * j11
    out[2] = j00 * j02 + j10 * j12
    out[3] = j01 * j01 + j11 * j11
    out[4] = j01 * j02 + j11 * j12
    out[5] = j02 * j02 + j12 * j12


@njit(cache=True, nogil=True)
def information_rows(cam_from_part, xyz, visible, w, cam, indptr, indices, data):
    """The information ``J^T J * w[t]`` of every visible pair, CSR by pose: fills ``indices``, ``data`` (in
    its precision) at the rows ``indptr`` (the visible pairs counted per pose)."""
    fx, fy, k1, k2, k3, p1, p2 = cam[0], cam[1], cam[4], cam[5], cam[6], cam[7], cam[8]
    distorted = cam[9] != 0.0
    v = np.empty(6)
    m, n = visible.shape
    for i in range(m):
        e = indptr[i]
        R = cam_from_part[i]
        for t in range(n):
            if visible[i, t]:
                _pair_info(R, xyz[t, 0], xyz[t, 1], xyz[t, 2], fx, fy, k1, k2, k3, p1, p2, distorted, v)
                for u in range(6):
                    data[e, u] = v[u] * w[t]
                indices[e] = t
                e += 1


@njit(cache=True, nogil=True)
def information_rows_model(cam_from_part, xyz, normals, visible, model, cam, indptr, indices, data):
    """:func:`information_rows` with each pair's weight ``1 / sigma^2`` from the detector model
    (:meth:`calibration.detector_model.DetectorModel.sigma_px_measured`: incidence between the target's unit
    normal ``normals[t]`` and its line of sight, dot diameter ``fx D / depth`` px, both held inside the measured
    range). ``model``: a^2, (noise_scale b)^2, p, q, d_ref px, fx D (px m), smallest and largest diameter px,
    cos of the largest incidence."""
    fx, fy, k1, k2, k3, p1, p2 = cam[0], cam[1], cam[4], cam[5], cam[6], cam[7], cam[8]
    distorted = cam[9] != 0.0
    a2, b2, pp, qq, dref, fxd, d0, d1, cmin = (model[0], model[1], model[2], model[3], model[4], model[5], model[6],
                                               model[7], model[8])
    v = np.empty(6)
    m, n = visible.shape
    for i in range(m):
        e = indptr[i]
        R = cam_from_part[i]
        # the camera centre in the part frame: -R^T t
        c0 = -(R[0, 0] * R[0, 3] + R[1, 0] * R[1, 3] + R[2, 0] * R[2, 3])
        c1 = -(R[0, 1] * R[0, 3] + R[1, 1] * R[1, 3] + R[2, 1] * R[2, 3])
        c2 = -(R[0, 2] * R[0, 3] + R[1, 2] * R[1, 3] + R[2, 2] * R[2, 3])
        for t in range(n):
            if visible[i, t]:
                x0, x1, x2 = xyz[t, 0], xyz[t, 1], xyz[t, 2]
                _pair_info(R, x0, x1, x2, fx, fy, k1, k2, k3, p1, p2, distorted, v)
                s0, s1, s2 = c0 - x0, c1 - x1, c2 - x2
                cos_t = (s0 * normals[t, 0] + s1 * normals[t, 1] + s2 * normals[t, 2]) / math.sqrt(
                    s0 * s0 + s1 * s1 + s2 * s2)
                cos_t = min(max(cos_t, cmin), 1.0)
                z = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2 + R[2, 3]
                d = min(max(fxd / max(z, 1e-9), d0), d1)
                w = 1.0 / (a2 + b2 * (d / dref) ** (-2.0 * pp) * cos_t ** (-2.0 * qq))
                for u in range(6):
                    data[e, u] = v[u] * w
                indices[e] = t
                e += 1


@njit(cache=True, nogil=True)
def segments(cast, starts_all, eyes, origin):
    """The occlusion segments of the pairs ``cast (c, n)`` bool, from ``starts_all[t]`` to ``eyes[i]``, as
    Embree takes them (planning.visibility.Occluder.occluded: origins moved by ``origin``, unit directions,
    lengths, float32 from the float64 values): ``(ci, ti, o, d, length)``."""
    c, n = cast.shape
    q = 0
    for i in range(c):
        for t in range(n):
            if cast[i, t]:
                q += 1
    ci = np.empty(q, dtype=np.int64)
    ti = np.empty(q, dtype=np.int64)
    o = np.empty((q, 3), dtype=np.float32)
    d = np.empty((q, 3), dtype=np.float32)
    length = np.empty(q, dtype=np.float32)
    q = 0
    for i in range(c):
        for t in range(n):
            if cast[i, t]:
                ci[q], ti[q] = i, t
                s0, s1, s2 = starts_all[t, 0], starts_all[t, 1], starts_all[t, 2]
                o[q, 0], o[q, 1], o[q, 2] = s0 - origin[0], s1 - origin[1], s2 - origin[2]
                d0, d1, d2 = eyes[i, 0] - s0, eyes[i, 1] - s1, eyes[i, 2] - s2
                ln = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                dv = ln if ln > 0 else 1.0
                d[q, 0], d[q, 1], d[q, 2] = d0 / dv, d1 / dv, d2 / dv
                length[q] = ln
                q += 1
    return ci, ti, o, d, length


@njit(cache=True, nogil=True)
def pair_information(cam_from_part, X, cam, out):
    """``J^T J`` of pairs ``cam_from_part: (q, 4, 4)``, ``X: (q, 3)``; fills ``out (q, 6)``."""
    fx, fy, k1, k2, k3, p1, p2 = cam[0], cam[1], cam[4], cam[5], cam[6], cam[7], cam[8]
    distorted = cam[9] != 0.0
    for q in range(X.shape[0]):
        _pair_info(cam_from_part[q], X[q, 0], X[q, 1], X[q, 2], fx, fy, k1, k2, k3, p1, p2, distorted, out[q])


def in_two(n: int, call, min_size: int = 2) -> None:
    """``call(lo, hi)`` over ``[0, n)`` in two halves, the second on a thread of its own (the kernels release
    the GIL; the thread is joined before returning), or once when ``n < min_size``."""
    if n < max(2, min_size):
        call(0, n)
        return
    import threading

    h = n // 2
    err: list[BaseException] = []

    def second() -> None:
        try:
            call(h, n)
        except BaseException as e:  # noqa: BLE001 - re-raised in the caller's thread
            err.append(e)

    t = threading.Thread(target=second, name="planning-kernels")
    t.start()
    try:
        call(0, h)
    finally:
        t.join()
    if err:
        raise err[0]


def camera_vector(intr, margin_px: float = 0.0) -> np.ndarray:
    """The camera as the kernels take it: fx, fy, cx, cy, k1, k2, k3, p1, p2, distorted, image limits."""
    return np.array([intr.fx_px, intr.fy_px, intr.cx_px, intr.cy_px, intr.k1, intr.k2, intr.k3, intr.p1, intr.p2,
                     1.0 if intr.has_distortion else 0.0, -0.5 + margin_px, intr.width - 0.5 - margin_px,
                     -0.5 + margin_px, intr.height - 0.5 - margin_px], dtype=np.float64)
