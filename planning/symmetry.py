"""The symmetries of a target layout: rigid motions that carry the targets onto each other.

Plain dots are named by projecting the nominal targets from the job's placement of the part. When the layout maps
onto itself under a rigid motion (a disc of dots in rings of equal pitch, a regular grid), a part placed off by that
motion has its dots named as their neighbours, and nothing in the images can tell: every dot lands where a nominal
one is expected, and the alignment fits as well as the truth. Only the layout can warn, before the job; coded targets
(unique codes) break the symmetry, since a code names its target whatever the placement (decision 0058).

:func:`layout_symmetries` finds the proper motions (rotations and translations, screws; no reflections, not the
identity) that carry at least ``min_share`` of the targets onto targets of the same label (-1 for plain dots, the
code for coded targets) within ``tol_m`` and with normals within ``normal_tol_deg``; :func:`symmetry_note` says the
closest one to an operator.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: the normals of a target and of its image under a symmetry agree within this angle
NORMAL_TOL_DEG = 10.0
#: default position tolerance, as a share of the median nearest-neighbour spacing (a dot's naming window in an image
#: is about 0.4 of the spacing: a motion that carries a dot within a quarter of it onto another names it wrongly)
TOL_SHARE_OF_SPACING = 0.25
#: candidate images of the distinctive target (family A), at most (evenly chosen among more)
MAX_IMAGES = 512
#: source targets for the local candidates (family B) and how many nearest neighbours each may move to
LOCAL_SOURCES = 4
LOCAL_NEIGHBOURS = 13
#: targets checked per candidate before the full check, and candidates checked in full, at most
SAMPLE = 64
MAX_VERIFIED = 64
#: a layout of more targets is refitted and screened on this many of them (the returned motions are counted on all)
CHECK_MAX = 1000
#: symmetries returned, at most (the smallest motions first)
MAX_RESULTS = 16


def median_spacing(xyz: np.ndarray) -> float:
    """Median distance of a target to its nearest other target (m); 0 for fewer than two targets.

    ``xyz``: (n, 3) float."""
    xyz = np.asarray(xyz, dtype=float)
    if len(xyz) < 2:
        return 0.0
    d, _ = cKDTree(xyz).query(xyz, k=2)
    pos = d[:, 1][d[:, 1] > 0]
    return float(np.median(pos)) if len(pos) else 0.0


def _kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched least-squares proper rotation: ``src``, ``dst`` (k, p, 3) -> R (k, 3, 3), t (k, 3), rms (k,)."""
    sc, dc = src.mean(axis=1), dst.mean(axis=1)
    H = np.einsum("kpi,kpj->kij", src - sc[:, None], dst - dc[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("kji,klj->kil", Vt, U)))  # det(V U^T)
    d[d == 0] = 1.0
    D = np.zeros_like(H)
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.einsum("kji,kjl,kml->kim", Vt, D, U)  # V D U^T
    t = dc - np.einsum("kij,kj->ki", R, sc)
    res = np.einsum("kij,kpj->kpi", R, src) + t[:, None] - dst
    return R, t, np.sqrt((res ** 2).sum(axis=2).mean(axis=1))


class _Layout:
    """The targets and what every check needs of them."""

    def __init__(self, xyz, normals, labels, tol_m, normal_tol_deg):
        self.xyz = np.asarray(xyz, dtype=float)
        n = np.asarray(normals, dtype=float)
        self.normals = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        self.labels = np.asarray(labels).astype(np.int64)
        self.tree = cKDTree(self.xyz)
        self.tol = tol_m
        self.cos = np.cos(np.radians(normal_tol_deg))
        self.coded = np.flatnonzero(self.labels >= 0)

    def images(self, R: np.ndarray, t: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where the motions (k of them) carry the targets ``idx``: (k, m) index of the matching target (-1: none)
        and (k, m) bool matched (same label, normals agree)."""
        p = np.einsum("kij,mj->kmi", R, self.xyz[idx]) + t[:, None]
        d, j = self.tree.query(p.reshape(-1, 3), distance_upper_bound=self.tol)
        j = j.reshape(p.shape[:2])
        ok = np.isfinite(d).reshape(j.shape)
        jj = np.where(ok, j, 0)
        nrm = np.einsum("kij,mj->kmi", R, self.normals[idx])
        ok &= self.labels[jj] == self.labels[idx][None]
        ok &= np.einsum("kmi,kmi->km", nrm, self.normals[jj]) >= self.cos
        return np.where(ok, jj, -1), ok


def _pairs_at(lay: _Layout, centre: np.ndarray, dist: float, label: int) -> np.ndarray:
    """Targets of ``label`` at ``dist`` (+- tol) from ``centre``."""
    cand = np.asarray(lay.tree.query_ball_point(centre, dist + lay.tol), dtype=np.int64)
    if not len(cand):
        return cand
    r = np.linalg.norm(lay.xyz[cand] - centre, axis=1)
    return cand[(np.abs(r - dist) <= lay.tol) & (lay.labels[cand] == label)]


def _correspondences(lay: _Layout, pts: list[int], imgs: list[tuple[int, ...]], ell: float,
                     fixed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Source and destination point sets for Kabsch: the targets, and a point ``ell`` out along each one's normal
    (the normals fix a turn about the line through two targets); ``fixed`` (the centroid) maps onto itself."""
    X, N = lay.xyz, lay.normals
    src = [X[i] for i in pts] + [X[i] + ell * N[i] for i in pts] + ([fixed] if fixed is not None else [])
    s = np.array(src)
    dst = []
    for im in imgs:
        d = [X[i] for i in im] + [X[i] + ell * N[i] for i in im] + ([fixed] if fixed is not None else [])
        dst.append(d)
    return np.broadcast_to(s, (len(imgs), *s.shape)).copy(), np.array(dst).reshape(len(imgs), *s.shape)


def _centroid_candidates(lay: _Layout, ell: float) -> tuple[np.ndarray, np.ndarray]:
    """Family A: a symmetry of the whole layout fixes its centroid, so it keeps each target's distance to it. Take
    a target ``a`` whose distance few others of its label share, a neighbour ``b`` not in line with the centroid,
    and every pair (a', b') that keeps those distances and the distance a-b."""
    X, L = lay.xyz, lay.labels
    c = X.mean(axis=0)
    r = np.linalg.norm(X - c, axis=1)
    # how many targets of its label share each target's distance to the centroid (one sorted key: label, distance)
    _, rank = np.unique(L, return_inverse=True)
    key = rank * (float(r.max()) + 4 * lay.tol + 1.0) + r
    ks = np.sort(key)
    count = np.searchsorted(ks, key + lay.tol, "right") - np.searchsorted(ks, key - lay.tol, "left")
    off_axis = r > 2 * lay.tol
    if not off_axis.any():
        return np.empty((0, 5, 3)), np.empty((0, 5, 3))
    order = np.lexsort((-r, count))
    sources = [int(i) for i in order if off_axis[i]][:3]
    srcs, dsts = [], []
    k = min(len(X), 9)
    for a in sources:
        _, nb = lay.tree.query(X[a], k=k)
        b = None
        for j in np.atleast_1d(nb)[1:]:
            u, v = X[a] - c, X[j] - c
            if np.linalg.norm(np.cross(u, v)) >= 0.3 * np.linalg.norm(u) * max(np.linalg.norm(v), lay.tol):
                b = int(j)
                break
        if b is None:
            b = int(np.atleast_1d(nb)[1])
        images_a = np.flatnonzero((L == L[a]) & (np.abs(r - r[a]) <= lay.tol))
        if len(images_a) > MAX_IMAGES:
            images_a = images_a[np.linspace(0, len(images_a) - 1, MAX_IMAGES).astype(int)]
        dab = float(np.linalg.norm(X[a] - X[b]))
        imgs = []
        for a2 in images_a:
            for b2 in _pairs_at(lay, X[a2], dab, int(L[b])):
                if b2 != a2 and abs(r[b2] - r[b]) <= lay.tol:
                    imgs.append((int(a2), int(b2)))
        if imgs:
            s, d = _correspondences(lay, [a, b], imgs, ell, fixed=c)
            srcs.append(s)
            dsts.append(d)
    if not srcs:
        return np.empty((0, 5, 3)), np.empty((0, 5, 3))
    return np.concatenate(srcs), np.concatenate(dsts)


def _local_candidates(lay: _Layout, ell: float) -> tuple[np.ndarray, np.ndarray]:
    """Family B (partial symmetries, e.g. a grid shifted by a pitch, which fix no centroid): a few targets ``a``
    (nearest the centroid and at its median distance) with their nearest neighbour ``b``, each carried to one of its
    ``LOCAL_NEIGHBOURS`` nearest targets (itself included) and ``b`` to any target at the distance a-b from there."""
    X, L = lay.xyz, lay.labels
    r = np.linalg.norm(X - X.mean(axis=0), axis=1)
    order = np.argsort(r, kind="stable")
    picks = [order[int(q * (len(X) - 1))] for q in (0.0, 0.15, 0.35, 0.5)][:LOCAL_SOURCES]
    sources = list(dict.fromkeys(int(i) for i in picks))
    k = min(len(X), LOCAL_NEIGHBOURS)
    srcs, dsts = [], []
    for a in sources:
        _, nb = lay.tree.query(X[a], k=k)
        nb = np.atleast_1d(nb)
        b = int(nb[1])
        dab = float(np.linalg.norm(X[a] - X[b]))
        imgs = []
        for a2 in nb:
            if L[a2] != L[a]:
                continue
            for b2 in _pairs_at(lay, X[a2], dab, int(L[b])):
                if b2 != a2:
                    imgs.append((int(a2), int(b2)))
        if imgs:
            s, d = _correspondences(lay, [a, b], imgs, ell)
            srcs.append(s)
            dsts.append(d)
    if not srcs:
        return np.empty((0, 4, 3)), np.empty((0, 4, 3))
    return np.concatenate(srcs), np.concatenate(dsts)


def _describe(R: np.ndarray, t: np.ndarray, X: np.ndarray, matched: np.ndarray, j: np.ndarray) -> dict:
    """A motion x -> R x + t as its turn (angle, axis, a point on the axis nearest the targets' centroid), its slide
    along the axis and the step it takes at the targets it carries onto others."""
    from scipy.spatial.transform import Rotation

    rv = Rotation.from_matrix(R).as_rotvec()
    angle = float(np.linalg.norm(rv))
    moved = matched & (j != np.arange(len(X)))
    step = np.linalg.norm(X[moved] @ R.T + t - X[moved], axis=1)
    out = {"angle_deg": float(np.degrees(angle)), "axis": None, "axis_point_m": None,
           "slide_m": float(np.linalg.norm(t)), "translation_m": _clean(t), "rotation": _clean(R),
           "share": float(matched.mean()), "mapped": int(matched.sum()), "moved": int(moved.sum()),
           "n_targets": int(len(X)), "step_m": float(np.median(step)) if len(step) else 0.0}
    if angle > 1e-6:
        axis = rv / angle
        slide = float(axis @ t)
        # the screw axis: points p with (R - I) p + t = slide * axis; the one nearest the centroid
        c = X.mean(axis=0)
        A = np.vstack([R - np.eye(3), axis[None]])
        rhs = np.concatenate([slide * axis - t, [axis @ c]])
        p = np.linalg.lstsq(A, rhs, rcond=None)[0]
        out |= {"axis": _clean(axis), "axis_point_m": _clean(p), "slide_m": _clean(slide)}
    else:
        out["axis"] = _clean(t / np.linalg.norm(t)) if np.linalg.norm(t) > 0 else None
    return out


def _clean(v):
    """A vector, matrix or number as JSON-friendly floats without the solver's 1e-18 crumbs (m, or unitless)."""
    return (np.round(np.asarray(v, dtype=float), 12) + 0.0).tolist()


def layout_symmetries(xyz: np.ndarray, normals: np.ndarray, labels: np.ndarray, tol_m: float | None = None,
                      min_share: float = 0.8, *, normal_tol_deg: float = NORMAL_TOL_DEG,
                      rng: np.random.Generator | None = None) -> list[dict]:
    """The proper rigid motions that carry at least ``min_share`` of the targets onto other targets of their label.

    Args:
        xyz: (n, 3) float target centres (m).
        normals: (n, 3) float target normals.
        labels: (n,) int: -1 for plain dots, the code of a coded target. Every coded target must land on a target
            of its own code (one code read in an image breaks the ambiguity): a unique code off the axis pins the
            layout, one on the axis (its normal along it) leaves the turns about that axis.
        tol_m: how close a carried target must come to another (m); default a quarter of the median
            nearest-neighbour spacing (``TOL_SHARE_OF_SPACING``).
        min_share: the share of all targets a motion must carry onto targets (1: a symmetry of the whole layout;
            0.8 also finds e.g. a 10 x 10 grid shifted by one pitch, 90 of 100).
        normal_tol_deg: a carried target's normal and its image's agree within this angle.
        rng: picks the targets every candidate is first checked on (default: ``default_rng(0)``, reproducible).

    Returns:
        list of dict, the smallest motions first (``step_m``, then ``angle_deg``), at most ``MAX_RESULTS`` (the
        whole layout's symmetries chosen first, then the partial ones, the smallest motions first):
        ``angle_deg`` (0..180), ``axis`` (unit 3-vector: the turn's axis, a pure shift's direction; None for
        neither), ``axis_point_m`` (the point on the axis nearest the targets' centroid; None for a shift),
        ``slide_m`` (along the axis), ``translation_m`` and ``rotation`` (x -> R x + t), ``share``, ``mapped``
        (targets carried onto a target), ``moved`` (carried onto another target), ``n_targets``, ``step_m``
        (median distance a moved target travels). Empty for fewer than 3 targets.

    Method: candidates from two families, each a Kabsch fit of two targets, their normals (and the centroid),
    onto candidate images: (A) a symmetry of the whole layout fixes its centroid, so the images of a target whose
    distance to it is rare are few; (B) partial symmetries (share < 1) come from small motions, a target carried to
    one of its ``LOCAL_NEIGHBOURS`` nearest. Each candidate is first checked on ``SAMPLE`` targets, the survivors
    (the whole layout's first, then the smallest motions; at most ``MAX_VERIFIED``) refitted on every target they
    carry, and the ``MAX_RESULTS`` kept counted on all targets with a k-d tree.

    Cost and caps: about O(n log n). On 2 shared cores a 400-target layout takes 0.01-0.3 s, 20 000 targets
    0.06-0.9 s (decision 0058). Large layouts are capped and subsampled: at most ``MAX_IMAGES`` images of the
    distinctive target, ``SAMPLE`` targets (and as many coded ones) in the first check, ``MAX_VERIFIED`` refits, on
    ``CHECK_MAX`` targets of a larger layout (the returned counts are on all). So a partial symmetry that does not
    fix the centroid and carries every target further than its ``LOCAL_NEIGHBOURS`` nearest (a grid shifted by
    three pitches) can be missed, a symmetry of the whole layout whose distinctive target has more than
    ``MAX_IMAGES`` look-alikes can be, and a layout with more than ``MAX_RESULTS`` symmetries has only that many
    listed.
    """
    X = np.asarray(xyz, dtype=float)
    n = len(X)
    if n < 3:
        return []
    spacing = median_spacing(X)
    if tol_m is None:
        tol_m = TOL_SHARE_OF_SPACING * spacing
    if not tol_m > 0:
        return []
    lay = _Layout(X, normals, labels, float(tol_m), normal_tol_deg)
    ell = max(spacing, 4 * tol_m)
    rng = np.random.default_rng(0) if rng is None else rng
    Rs, ts = [], []
    for fam in (_centroid_candidates, _local_candidates):
        src, dst = fam(lay, ell)
        if len(src):
            R, t, rms = _kabsch(src, dst)
            keep = rms <= tol_m
            Rs.append(R[keep])
            ts.append(t[keep])
    if not Rs or not sum(len(R) for R in Rs):
        return []
    R, t = np.concatenate(Rs), np.concatenate(ts)
    # drop the identity and the same motion found twice: the images of three reference points within tol
    c = X.mean(axis=0)
    span = max(float(np.sqrt(((X - c) ** 2).sum(axis=1).mean())), tol_m)
    ref = c + np.vstack([np.zeros(3), span * np.eye(3)[:2]])
    sig = (np.einsum("kij,mj->kmi", R, ref) + t[:, None]).reshape(len(R), -1)
    ident = np.abs(sig - ref.reshape(-1)).max(axis=1) < tol_m
    _, first = np.unique(np.round(sig / tol_m).astype(np.int64), axis=0, return_index=True)
    keep = np.zeros(len(R), dtype=bool)
    keep[first] = True
    keep &= ~ident
    R, t = R[keep], t[keep]
    if not len(R):
        return []
    # the first check, on a sample of the targets (and of the coded ones: each must land on its code)
    def pick(k: int) -> np.ndarray:
        coded = lay.coded if len(lay.coded) <= k else rng.choice(lay.coded, size=k, replace=False)
        return np.union1d(rng.choice(n, size=min(n, k), replace=False), coded)

    sample = pick(SAMPLE)
    j, ok = lay.images(R, t, sample)
    need = min_share - (3 * np.sqrt(min_share * (1 - min_share) / len(sample)) if len(sample) < n else 0.0)
    coded_in = np.isin(sample, lay.coded)
    share = ok.mean(axis=1)
    good = np.flatnonzero((share >= need - 1e-12) & ok[:, coded_in].all(axis=1))
    # the whole layout's symmetries first, then the smallest motions (median step of the sample)
    step = np.median(np.linalg.norm(np.einsum("kij,mj->kmi", R[good], X[sample]) + t[good, None] - X[sample], axis=2),
                     axis=1)
    good = good[np.lexsort((np.round(step / tol_m), share[good] < 1))][:MAX_VERIFIED]
    R, t = R[good], t[good]
    # refit each on everything it carries (on CHECK_MAX targets of a larger layout), drop the same motion found
    # twice (the same targets carried onto the same targets), then count the chosen ones on every target
    check = np.arange(n) if n <= CHECK_MAX else pick(CHECK_MAX)
    margin = 3 * np.sqrt(min_share * (1 - min_share) / len(check)) if len(check) < n else 0.0
    found, seen = [], set()
    for k in range(len(R)):
        Rk, tk = R[k:k + 1], t[k:k + 1]
        j, ok = (a[0] for a in lay.images(Rk, tk, check))
        if ok.sum() >= 3:  # refit on every target it carries, check again
            Rk, tk, _ = _kabsch(X[check[ok]][None], X[j[ok]][None])
            j, ok = (a[0] for a in lay.images(Rk, tk, check))
        if ok.sum() < 3 or ok.mean() < min_share - margin - 1e-12 or not ok[np.isin(check, lay.coded)].all():
            continue
        moved = ok & (j != check)
        if not moved.any():  # carries every target onto itself: the identity, for naming
            continue
        key = np.where(ok, j, -1).tobytes()
        if key in seen:
            continue
        seen.add(key)
        travel = float(np.median(np.linalg.norm(X[check[moved]] @ Rk[0].T + tk[0] - X[check[moved]], axis=1)))
        found.append((ok.mean() >= 1 - 1e-12, round(travel / tol_m), Rk[0], tk[0]))
    # the whole layout's symmetries first, then the partial ones, the smallest motions first; at most MAX_RESULTS
    found.sort(key=lambda f: (not f[0], f[1]))
    out = []
    everything = np.arange(n)
    for _, _, Rk, tk in found[:MAX_RESULTS]:
        j, ok = lay.images(Rk[None], tk[None], everything)
        j, ok = j[0], ok[0]
        if ok.mean() < min_share - 1e-12 or not ok[lay.coded].all() or not (ok & (j != everything)).any():
            continue
        out.append(_describe(Rk, tk, X, ok, j))

    def order(s: dict) -> tuple:
        return (round(s["step_m"] / tol_m), round(s["angle_deg"], 3), -s["share"],
                tuple(-np.round(s["axis"] or (0, 0, 0), 6)))

    return sorted(out, key=order)


def _vec(v) -> str:
    v = np.asarray(v, dtype=float)
    for i, name in enumerate("xyz"):
        if abs(abs(v[i]) - 1.0) < 1e-6:
            return f"the part's {'+' if v[i] > 0 else '-'}{name} axis"
    return "(" + ", ".join(f"{x:.3f}" for x in v) + ")"


def symmetry_note(sym: dict) -> str:
    """What one symmetry (an entry of :func:`layout_symmetries`) means for the operator, and what to do."""
    n, mapped, moved = sym["n_targets"], sym["mapped"], sym["moved"]
    if sym["angle_deg"] > 1e-4:
        p = np.round(np.asarray(sym["axis_point_m"]) * 1000, 1) + 0.0  # no "-0.0"
        motion = (f"a turn of {sym['angle_deg']:.1f} deg about {_vec(sym['axis'])} through "
                  f"({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm")
        if abs(sym["slide_m"]) * 1000 >= 0.05:
            motion += f" and a slide of {sym['slide_m'] * 1000:.1f} mm along it"
        half = f"{sym['angle_deg'] / 2:.1f} deg, {sym['step_m'] * 500:.1f} mm at the dots"
    else:
        motion = f"a shift of {sym['slide_m'] * 1000:.1f} mm along {_vec(sym['axis'])}"
        half = f"{sym['slide_m'] * 500:.1f} mm"
    who = "every dot" if moved == n else f"{moved} of the {n} targets"
    return (f"the targets' layout maps onto itself under {motion} ({mapped} of {n} targets): a part placed one step "
            f"off would have {who} named as {'its' if moved == n else 'their'} neighbour{'' if moved == n else 's'}, "
            "and no image can tell; put coded markers that break the symmetry (job.n_coded or the targets file's "
            f"code column) or fix the part's placement to well within half a step ({half})")


def symmetry_summary(xyz: np.ndarray, normals: np.ndarray, labels: np.ndarray, min_share: float = 0.8) -> dict:
    """The part summary's ``symmetry``: ``tol_m`` (default of :func:`layout_symmetries`), ``min_share``,
    ``symmetries`` (its list, without the rotation matrices) and ``warning`` (:func:`symmetry_note` of the smallest
    motion; None when the layout has no symmetry)."""
    tol = TOL_SHARE_OF_SPACING * median_spacing(xyz)
    found = layout_symmetries(xyz, normals, labels, tol_m=tol if tol > 0 else None, min_share=min_share)
    return {"tol_m": tol, "min_share": min_share,
            "symmetries": [{k: v for k, v in s.items() if k != "rotation"} for s in found],
            "warning": symmetry_note(found[0]) if found else None}
