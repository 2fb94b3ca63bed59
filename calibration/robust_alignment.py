"""Alignment to CAD that a metrologist can trust: a high-breakdown start, a bounded exclusion, and a verdict.

A least-squares fit over all targets is pulled by the very deviations it should reveal: one
target off by 0.9 mm moves a fit over 200 targets measured to 5 um by far more than their
sigma, and the "significant" targets that follow are the fit's own error. So:

1. **Consensus start** (:func:`consensus_fit`): rigid fits to minimal subsets of three targets
   (spread apart), each scored by how many targets agree with it under their *stated*
   covariance (squared Mahalanobis distance below a chi-square bound, MSAC score), the best
   one refined by least squares on its agreeing set (locally optimised RANSAC). The answer
   stays right as long as the targets that agree with CAD are the largest consistent group,
   i.e. with up to half of them (and more) deviating at random.
2. **Bounded exclusion** (:func:`robust_best_fit`): from that set, fit, test every target
   (beyond tolerance, or significant at ``k`` sigma against the fit's full S-transformed
   covariance), refit on those that pass; a target may come back in. It stops at a fixed point
   (*stable*), on a cycle or after ``max_iterations`` (*not stable*), and it never leaves the
   consensus: a set that loses a fifth of the consensus targets is refused, not followed.
3. **Verdict**: the fit is *trusted* only if it is stable, the consensus is unambiguous (no
   rival transformation agreeing with a comparable number of targets: a part bent into two
   rigid pieces has two), enough targets span it (at least ``min_fit`` and a third of the
   candidates, not on one line) and its residuals match the stated precision (``residual_ratio``,
   sqrt of the mean squared Mahalanobis distance of the fit targets over its expectation, at most
   ``max_residual_ratio``). Every reason it is not trusted is listed.

Also the alignments inspection software offers: RPS / 3-2-1 on named datum targets
(:func:`rps_align`: the locked coordinates of the datum targets equal the nominal ones) and the
measurement's own frame (:func:`frame_alignment`: a fixtured part whose datum is the fixture's
control points).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import chdtr, chdtri, gammaincinv, ndtr  # scipy.stats' own kernels, without its import

from calibration.alignment import (Alignment, align_to_cad, deviation_sigma_level, similarity_fit,
                                   transformed_alignment)
from calibration.camera import skew
from calibration.errors import CalibrationError

__all__ = [
    "AlignmentOutcome",
    "Consensus",
    "consensus_fit",
    "robust_best_fit",
    "rps_align",
    "rps_locks",
    "frame_alignment",
]

#: a rival placement held by at least this share of the best one's targets is said (half of them: not trusted)
RIVAL_NOTE_SHARE = 0.2
#: an RPS frame that moves some target from the robust best fit by more than this share of its tolerance is not
#: trusted: the datum targets disagree with the rest of the part by a good part of what is being judged
RPS_SHIFT_TOLERANCE_SHARE = 0.5
#: an RPS frame whose locked coordinates miss their nominals by more than this after the iterations did not converge
RPS_LOCK_RESIDUAL_M = 1e-6

#: chi-square (3 dof) bound of a target agreeing with a hypothesis in the consensus (99.9 %)
CHI2_AGREE = float(2.0 * gammaincinv(1.5, 0.999))  # chi2.ppf(0.999, 3)


@dataclass(frozen=True)
class Consensus:
    """The high-breakdown start.

    Attributes:
        R, t: rigid transformation ``nominal ~ R measured + t`` refined on the agreeing targets.
        agree: (n,) bool, targets that agree with it under their stated covariance.
        hypotheses: minimal-subset hypotheses scored.
        rival: size of the largest consensus of a hypothesis that mostly disagrees with the best one
            (0 if none), at the loose bound: a rival as large as ``agree_loose`` (the best one's consensus at
            the same bound) means two transformations fit the data equally.
        scale_factor: robust ratio of the agreeing targets' residuals to their stated sigma
            (sqrt of the median squared Mahalanobis distance over the chi-square median).
    """

    R: np.ndarray
    t: np.ndarray
    agree: np.ndarray
    hypotheses: int
    rival: int
    scale_factor: float
    agree_loose: int = 0


@dataclass(frozen=True)
class AlignmentOutcome:
    """An alignment and how far to trust it.

    Attributes:
        alignment: the :class:`calibration.alignment.Alignment` (deviations and their covariance).
        method: "best_fit", "rps" or "bundle_frame".
        fit_mask: (n,) bool, the targets that defined the frame.
        trusted: the frame can be relied on (see the module docstring); else ``reasons`` says why.
        stable: the set of fit targets reached a fixed point (always True for rps and bundle_frame).
        reasons: why the frame is not trusted (empty when trusted).
        notes: what else the operator should know (e.g. how many targets were left out and why).
        residual_ratio: sqrt(mean m^2 / E[m^2]) over the fit targets (1 for an honest covariance; nan if
            the frame has no redundancy).
        iterations: refits of the exclusion.
        consensus: the start (None for rps and bundle_frame).
    """

    alignment: Alignment
    method: str
    fit_mask: np.ndarray
    trusted: bool
    stable: bool
    reasons: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    residual_ratio: float = float("nan")
    iterations: int = 0
    consensus: Consensus | None = None


def _inverse_blocks(blocks: np.ndarray) -> np.ndarray:
    """Inverse 3x3 covariance blocks; a singular or non-finite block gets zeros (it then agrees with anything)."""
    out = np.zeros_like(blocks)
    ok = np.all(np.isfinite(blocks), axis=(1, 2))
    if ok.any():
        w, V = np.linalg.eigh(blocks[ok])
        good = np.all(w > 0, axis=1)
        inv = np.einsum("nab,nb,ncb->nac", V, 1.0 / np.where(w > 0, w, 1.0), V)
        sub = np.zeros_like(inv)
        sub[good] = inv[good]
        out[ok] = sub
    return out


def _kabsch_batch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid ``dst ~ R src + t`` for a batch of point sets ``(h, k, 3)``: ``R (h, 3, 3)``, ``t (h, 3)``."""
    ms, md = src.mean(axis=1), dst.mean(axis=1)
    S = np.einsum("hka,hkb->hab", dst - md[:, None], src - ms[:, None])
    U, _, Vt = np.linalg.svd(S)
    d = np.sign(np.linalg.det(U @ Vt))
    E = np.tile(np.eye(3), (len(src), 1, 1))
    E[:, 2, 2] = d
    R = U @ E @ Vt
    return R, md - np.einsum("hab,hb->ha", R, ms)


def _m2(measured: np.ndarray, nominal: np.ndarray, cinv: np.ndarray, R: np.ndarray, t: np.ndarray,
        s: np.ndarray | None = None) -> np.ndarray:
    """Squared Mahalanobis distance of every target under every hypothesis, ``(h, n)``.

    The residual is taken in the measurement's frame, ``x - R^T (nominal - t) / s``, where ``cinv`` lives
    (``s``: (h,) scales of similarity hypotheses, default 1).
    """
    back = np.einsum("hba,hnb->hna", R, nominal[None] - t[:, None, :])
    if s is not None:
        back = back / np.asarray(s, dtype=float)[:, None, None]
    r = measured[None] - back
    return np.einsum("hna,nab,hnb->hn", r, cinv, r)


def consensus_fit(measured: np.ndarray, cov_blocks: np.ndarray, nominal: np.ndarray, candidates: np.ndarray,
                  rng: np.random.Generator, n_hypotheses: int = 400, loose: float = 3.0,
                  with_scale: bool = False) -> Consensus:
    """High-breakdown rigid fit by consensus over minimal subsets (see the module docstring).

    Args:
        measured, nominal: (n, 3); cov_blocks: (n, 3, 3) stated covariance of the measured targets.
        candidates: (n,) bool, the targets the fit may use (finite, chosen).
        rng: the random stream that draws the subsets.
        n_hypotheses: minimal subsets drawn (400 find an all-agreeing triple with probability
            1 - 1e-23 when half the targets agree).
        loose: a minimal subset's own fit error grows away from it: a target agrees with a hypothesis
            within ``loose`` times its stated sigma (99.9 % chi-square bound); the refinement then tightens it.
        with_scale: similarity hypotheses (each triple's own scale), for a measurement whose scale is not its own.
    """
    idx = np.flatnonzero(candidates)
    if len(idx) < 3:
        raise CalibrationError(f"alignment: a best fit needs at least 3 measured targets, got {len(idx)}")
    X, N = measured[idx], nominal[idx]
    cinv = _inverse_blocks(np.asarray(cov_blocks, dtype=float)[idx])
    extent = float(np.max(np.linalg.norm(N - N.mean(axis=0), axis=1)))
    trip = rng.integers(0, len(idx), size=(4 * n_hypotheses, 3))
    a, b, c = N[trip[:, 0]], N[trip[:, 1]], N[trip[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    good = area > (0.1 * extent) ** 2  # well spread triangles only: a thin one fixes no rotation
    if good.sum() < 10:
        good = area > 1e-6 * max(extent, 1e-9) ** 2
    trip = trip[good][:n_hypotheses]
    if len(trip) == 0:
        raise CalibrationError("alignment: the measured targets lie on one line; no rigid fit is possible")
    sc = np.ones(len(trip))
    if with_scale:  # each triple's own scale: the spread of its nominals over that of its measurements
        Xt, Nt = X[trip], N[trip]
        sc = np.sqrt(np.sum((Nt - Nt.mean(axis=1, keepdims=True)) ** 2, axis=(1, 2))
                     / np.sum((Xt - Xt.mean(axis=1, keepdims=True)) ** 2, axis=(1, 2)))
    R, t = _kabsch_batch(X[trip] * sc[:, None, None], N[trip])
    bound = CHI2_AGREE * loose**2
    m2 = _m2(X, N, cinv, R, t, sc)
    score = np.sum(np.minimum(m2, bound), axis=1)  # MSAC: agreeing targets count by how well they agree
    best = int(np.argmin(score))
    agree = m2[best] < bound
    Rb, tb, sb = R[best], t[best], sc[best]
    for loosen in (loose, 1.0, 1.0):  # local optimisation: refit on the agreeing set, tighten the bound
        if agree.sum() < 3:
            break
        sb, Rb, tb = similarity_fit(X[agree], N[agree], with_scale=with_scale)
        m2b = _m2(X, N, cinv, Rb[None], tb[None], [sb])[0]
        new = m2b < CHI2_AGREE * loosen**2
        if new.sum() < 3:
            break
        agree = new
    # a rival: a hypothesis whose agreeing set (same loose bound) mostly lies outside the best one's
    sets = m2 < bound
    best_sets = _m2(X, N, cinv, Rb[None], tb[None], [sb])[0] < bound
    overlap = (sets & best_sets[None]).sum(axis=1)
    size = sets.sum(axis=1)
    rival = int(np.max(np.where(overlap < 0.5 * size, size, 0))) if len(size) else 0
    best_loose = int(best_sets.sum())
    m2b = _m2(X, N, cinv, Rb[None], tb[None], [sb])[0]
    factor = float(np.sqrt(np.median(m2b[agree]) / (2.0 * gammaincinv(1.5, 0.5)))) if agree.any() else float("nan")
    full = np.zeros(len(measured), dtype=bool)
    full[idx[agree]] = True
    return Consensus(Rb, tb, full, len(trip), rival, factor, best_loose)


def _expected_truncated_m2(k: float) -> float:
    """E[m^2 | target passes the k-sigma test] for chi-square 3 dof (the test keeps the ones below the bound)."""
    c = float(chdtri(3, 2 * ndtr(-k)))  # chi2.isf(2 norm.sf(k), 3)
    return 3.0 * float(chdtr(5, c) / chdtr(3, c))


def _spans(points: np.ndarray) -> bool:
    """The points fix a rotation: not all on one line (second singular value not negligible)."""
    if len(points) < 3:
        return False
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return bool(s[1] > 1e-3 * s[0])


def robust_best_fit(measured: np.ndarray, cov, nominal: np.ndarray, tolerance_m: np.ndarray, k: float,
                    candidates: np.ndarray | None = None, rng: np.random.Generator | None = None,
                    max_iterations: int = 10, min_fit: int = 6, max_residual_ratio: float = 2.0,
                    with_scale: bool = False) -> AlignmentOutcome:
    """Best fit to CAD over the targets that agree with it: consensus start, bounded exclusion, verdict.

    Args:
        measured: (n, 3) measured targets (any datum; nan where not measured).
        cov: their covariance (:class:`calibration.alignment.PointCovariance` or (n, 3, 3) blocks).
        nominal: (n, 3) CAD nominals.
        tolerance_m: (n,) tolerance of each target's deviation length: a target beyond it is not fitted.
        k: a target significant at ``k`` sigma (3-D, as :func:`calibration.alignment.deviation_sigma_level`)
            is not fitted.
        candidates: (n,) bool, the targets the fit may use (default: all measured).
        rng: random stream of the consensus (default: a fixed seed, so a report is reproducible).
        max_iterations: refits of the exclusion before it is declared not stable.
        min_fit: fewest targets a trusted fit rests on.
        max_residual_ratio: fit residuals larger than this times their stated sigma are not trusted.
        with_scale: also fit a scale (a free network whose scale is the layout's own, as ``cell measure``'s): the
            consensus draws similarity hypotheses, the exclusion fits a similarity on the targets it keeps.
    """
    measured = np.asarray(measured, dtype=float)
    nominal = np.asarray(nominal, dtype=float)
    tol = np.broadcast_to(np.asarray(tolerance_m, dtype=float), (len(measured),))
    finite = np.all(np.isfinite(measured), axis=1) & np.all(np.isfinite(nominal), axis=1)
    cand = finite if candidates is None else (np.asarray(candidates, dtype=bool) & finite)
    rng = rng if rng is not None else np.random.default_rng(20261122)
    blocks = _measured_blocks(cov, len(measured))
    cons = consensus_fit(measured, blocks, nominal, cand, rng, with_scale=with_scale)
    reasons: list[str] = []
    notes: list[str] = []
    if cons.agree.sum() < max(3, min_fit):  # no placement brings enough targets to CAD: a fit over all, untrusted
        al = align_to_cad(measured, cov, nominal, fit_mask=cand, with_scale=with_scale)
        return AlignmentOutcome(al, "best_fit", cand.copy(), False, False, (
            f"no rigid placement brings {max(3, min_fit)} targets to CAD within their stated sigma (the best brings "
            f"{int(cons.agree.sum())}, {cons.agree_loose} within 3x): the part is not its CAD, its targets stand off "
            "the surface by other than the job says (target thickness), or the stated precision is far too small; the "
            "frame shown is a fit over every target",), (), float("nan"), 0, cons)
    mask = cons.agree.copy()
    seen = [mask.copy()]
    stable = False
    it = 0
    while it < max_iterations:
        it += 1
        al = align_to_cad(measured, cov, nominal, fit_mask=mask, with_scale=with_scale)
        level = al.sigma_level()
        dev = np.linalg.norm(al.deviation, axis=1)
        new = cand & (dev <= tol) & ~(level > k)
        if np.array_equal(new, mask):
            stable = True
            break
        if (new & cons.agree).sum() < 0.8 * cons.agree.sum() or new.sum() < 3:
            reasons.append(f"the exclusion would leave the consensus ({int((new & cons.agree).sum())} of "
                           f"{int(cons.agree.sum())} consensus targets); kept the last fit")
            break
        if any(np.array_equal(new, s) for s in seen):
            notes.append("the set of fit targets oscillates between refits")
            break
        seen.append(new.copy())
        mask = new
    if not stable:
        al = align_to_cad(measured, cov, nominal, fit_mask=mask, with_scale=with_scale)
    if not stable and not reasons:
        reasons.append(f"the set of fit targets did not settle in {it} refits")
    n_fit, n_cand = int(mask.sum()), int(cand.sum())
    if n_fit < min_fit:
        reasons.append(f"only {n_fit} targets agree with CAD (fewer than {min_fit})")
    elif n_fit < n_cand / 3:
        reasons.append(f"only {n_fit} of {n_cand} targets agree with CAD: the frame rests on a minority")
    if n_fit >= 3 and not _spans(nominal[mask]):
        reasons.append("the targets that agree with CAD lie on one line: the rotation about it is not fixed")
    if cons.rival >= 0.5 * cons.agree_loose:
        reasons.append(f"ambiguous: another placement agrees with {cons.rival} targets "
                       f"(the best with {cons.agree_loose}, within {3:g}x their stated sigma); is the part in one piece?")
    elif cons.rival >= max(min_fit, RIVAL_NOTE_SHARE * cons.agree_loose):
        notes.append(f"another placement agrees with {cons.rival} targets (the best with {cons.agree_loose}, within "
                     f"{3:g}x their stated sigma): a group of targets moved together (a bent flange, a loose insert); "
                     "the frame is the majority's")
    d = al.deviation[mask]
    C = al.deviation_cov[mask]
    m2 = np.einsum("na,na->n", d, np.linalg.solve(C, d[..., None])[..., 0]) if n_fit else np.array([])
    ratio = float(np.sqrt(np.mean(m2) / _expected_truncated_m2(k))) if n_fit > 6 else float("nan")
    if np.isfinite(ratio) and ratio > max_residual_ratio:
        reasons.append(f"the fit targets deviate {ratio:.2f} times their stated sigma "
                       f"(more than {max_residual_ratio:g}): the stated precision or the CAD is wrong")
    left_out = cand & ~mask
    if left_out.any():
        notes.append(f"{int(left_out.sum())} of {n_cand} targets left out of the fit (beyond tolerance or "
                     f"significant at {k:g} sigma)")
    return AlignmentOutcome(al, "best_fit", mask, not reasons, stable, tuple(reasons), tuple(notes), ratio, it, cons)


def _measured_blocks(cov, n: int) -> np.ndarray:
    from calibration.alignment import PointCovariance

    if isinstance(cov, PointCovariance):
        return cov.blocks()
    return np.asarray(cov, dtype=float).reshape(n, 3, 3)


_AXES = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}


def rps_locks(datum: dict[int, str]) -> list[tuple[int, np.ndarray]]:
    """``{target index: "xyz"-letters}`` -> one (index, unit axis) per locked coordinate (part frame)."""
    out = []
    for i, axes in datum.items():
        letters = str(axes).lower()
        if not letters or any(a not in _AXES for a in letters) or len(set(letters)) != len(letters):
            raise CalibrationError(f"RPS: target {i}: the locked axes must be distinct letters of 'xyz', got {axes!r}")
        out += [(int(i), _AXES[a]) for a in letters]
    return out


def rps_align(measured: np.ndarray, cov, nominal: np.ndarray, locks: list[tuple[int, np.ndarray]],
              tolerance_m: np.ndarray | None = None, k: float = 3.0, iterations: int = 20,
              ids: list[str] | None = None) -> AlignmentOutcome:
    """RPS / 3-2-1 alignment: the locked coordinates of the datum targets equal their nominals.

    Args:
        measured, nominal: (n, 3); cov: covariance of the measured targets.
        locks: (target index, unit axis (3,) in the part frame) per locked coordinate; at least 6 that fix
            the rigid motion (3-2-1: three targets along the primary axis, two along the secondary, one along
            the tertiary). More than 6: least squares on the locked coordinates.
        tolerance_m, k: for the check of the datum targets against a robust best fit (a datum target that is
            itself out of tolerance shifts the whole frame: not trusted).
        ids: the targets' names, for the messages (default: their indices).

    The covariance is the S-transformation that holds the locked coordinates: ``H`` has, for lock ``l`` on
    target ``i``, the axis ``e_l`` in row block ``i``, column ``l``.
    """
    measured = np.asarray(measured, dtype=float)
    nominal = np.asarray(nominal, dtype=float)
    if len(locks) < 6:
        raise CalibrationError(f"RPS: {len(locks)} locked coordinates; a 3-2-1 alignment needs 6")
    ti = np.array([i for i, _ in locks], dtype=int)
    E = np.array([e for _, e in locks], dtype=float)
    if np.any(ti < 0) or np.any(ti >= len(measured)):
        raise CalibrationError("RPS: a datum target index is out of range")
    if not np.all(np.isfinite(measured[ti])):
        missing = sorted({int(i) for i in ti if not np.all(np.isfinite(measured[i]))})
        raise CalibrationError(f"RPS: datum target(s) {missing} were not measured")
    # start: a best fit on the datum targets when they span, else the robust best fit over all
    uniq = np.unique(ti)
    if len(uniq) >= 3 and _spans(nominal[uniq]):
        _, R, t = similarity_fit(measured[uniq], nominal[uniq])
    else:
        start = robust_best_fit(measured, cov, nominal, np.inf if tolerance_m is None else tolerance_m, k)
        R, t = start.alignment.part_from_measured[:3, :3], start.alignment.part_from_measured[:3, 3]
    def name(i: int) -> str:
        return str(ids[i]) if ids is not None else str(i)

    converged = False
    for _ in range(iterations):  # Gauss-Newton on r_l = e_l . (R x_i + t - nominal_i)
        y = measured[ti] @ R.T + t
        r = np.einsum("la,la->l", E, y - nominal[ti])
        J = np.hstack([E, np.einsum("la,lab->lb", E, -skew(y))])  # d(y)/d(omega) = -[y]x
        if np.linalg.matrix_rank(J, tol=1e-9 * max(np.abs(J).max(), 1e-12)) < 6:
            raise CalibrationError("RPS: the datum targets and axes do not fix the part (rank < 6): choose "
                                   "3 targets for the primary axis, 2 for the secondary, 1 for the tertiary")
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        dR = _rotvec(step[3:])
        R, t = dR @ R, dR @ t + step[:3]
        if np.linalg.norm(step) < 1e-13:
            converged = True
            break
    y = measured[ti] @ R.T + t
    lock_residual = np.abs(np.einsum("la,la->l", E, y - nominal[ti]))
    finite = np.all(np.isfinite(measured), axis=1) & np.all(np.isfinite(nominal), axis=1)
    pos = {int(i): p for p, i in enumerate(np.flatnonzero(finite))}

    def datum(G):
        # least squares on the locked coordinates: H^T x = (L^T G)^T (L^T x), the normal equations' right side
        L = np.zeros((G.shape[0], 3, len(locks)))
        for col, (i, e) in enumerate(locks):
            L[pos[i], :, col] = e
        LtG = np.einsum("nal,nad->ld", L, G)  # (L, 6)
        return np.einsum("nal,ld->nad", L, LtG)

    al = transformed_alignment(measured, cov, nominal, 1.0, R, t, datum, rms_mask=np.isin(np.arange(len(measured)), ti))
    reasons, notes = [], []
    if not converged or (len(locks) == 6 and lock_residual.max() > RPS_LOCK_RESIDUAL_M):
        worst = int(np.argmax(lock_residual))
        reasons.append(f"the RPS locks did not converge in {iterations} iterations (lock {worst + 1}, on target "
                       f"{name(int(ti[worst]))}, {lock_residual[worst] * 1e6:.1f} um from its nominal): the datum targets fix "
                       "the part weakly (two targets locking one axis that are close across it?)")
    if tolerance_m is not None:
        ref = robust_best_fit(measured, cov, nominal, tolerance_m, k)
        tol = np.broadcast_to(np.asarray(tolerance_m, dtype=float), (len(measured),))
        bad = [name(int(i)) for i in uniq if not ref.fit_mask[i]
               and np.linalg.norm(ref.alignment.deviation[i]) > tol[i]]
        if bad:
            reasons.append(f"datum target(s) {', '.join(bad)} deviate beyond their tolerance in a best fit: "
                           "the RPS frame is shifted by a bad datum")
        diff = al.aligned - ref.alignment.aligned
        shift = np.linalg.norm(diff, axis=1)
        share = np.where(np.isfinite(shift) & (tol > 0), shift / np.where(tol > 0, tol, 1.0), 0.0)
        notes.append(f"RPS frame vs robust best fit: largest shift of a target {np.nanmax(shift) * 1e6:.1f} um")
        # the shift against its own uncertainty (the two frames' covariances added: on the safe side, as the best
        # fit's is the smaller): a shift within it is the datums' noise, which the RPS covariance states. The datum
        # targets themselves are left out: their locked coordinates have no variance in the RPS frame
        Cd = np.nan_to_num(al.deviation_cov + ref.alignment.deviation_cov) + 1e-30 * np.eye(3)
        level = np.where(np.isfinite(shift), deviation_sigma_level(np.nan_to_num(diff), Cd), 0.0)
        share = np.where((level > k) & ~np.isin(np.arange(len(shift)), uniq), share, 0.0)
        if not bad and ref.trusted and share.max() > RPS_SHIFT_TOLERANCE_SHARE:
            j = int(np.argmax(share))
            off = {int(i): float(np.linalg.norm(ref.alignment.deviation[i])) for i in uniq}
            worst = sorted(off, key=lambda i: -off[i])[:2]
            reasons.append(
                f"the RPS frame moves target {name(j)} by {shift[j] * 1e6:.0f} um from the best fit, "
                f"{share[j]:.0%} of its tolerance: the datum targets disagree with the rest of the part (in a best "
                f"fit target {name(worst[0])} deviates {off[worst[0]] * 1e6:.0f} um"
                + (f", target {name(worst[1])} {off[worst[1]] * 1e6:.0f} um" if len(worst) > 1 else "")
                + "); the deviations are relative to the datums as RPS defines them, not to the part's best fit")
    mask = np.zeros(len(measured), dtype=bool)
    mask[uniq] = True
    return AlignmentOutcome(al, "rps", mask, not reasons, True, tuple(reasons), tuple(notes))


def _rotvec(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    K = skew(w)
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * K @ K


def frame_alignment(measured: np.ndarray, cov, nominal: np.ndarray, fixtured: bool, why: str = "") -> AlignmentOutcome:
    """The measurement's own frame is the part frame (a fixtured part, datum on the fixture's control points).

    ``fixtured`` says whether the measurement's datum really is the part's frame; if not, the outcome is
    not trusted (``why`` says what the datum is instead).
    """
    measured = np.asarray(measured, dtype=float)
    al = transformed_alignment(measured, cov, nominal, 1.0, np.eye(3), np.zeros(3), None)
    reasons = () if fixtured else (why or "the measurement's datum is not the part's fixture",)
    return AlignmentOutcome(al, "bundle_frame", np.zeros(len(measured), dtype=bool), fixtured, True, reasons)
