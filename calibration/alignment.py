"""Datum transformations of measured targets: covariance bookkeeping, best fit to the CAD nominals, deviations.

A bundle adjustment determines the targets' shape; where the shape sits (and, without a
scale bar, its size) is a datum choice. Changing datum is an S-transformation (Baarda):
``x' = S x`` with ``S = I - P H^T`` where the columns of ``P`` span the infinitesimal
motions (Helmert: translation, rotation, scale) and ``H`` says which weighted combination
of the points is held fixed. A least-squares fit to the CAD nominals is such a transformation,
so the deviations' covariance is ``S Q S^T``: it needs the targets' cross-covariances, not
only their 3x3 blocks. :class:`PointCovariance` keeps the full ``(3n, 3n)`` covariance in the
low-rank form the bundle adjustment produces, ``blockdiag(D) + U C U^T``, and transforms it
without ever forming a ``(3n, 3n)`` matrix.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import chdtrc, ndtri  # chi2.sf, norm.isf without importing scipy.stats (~1 s)

from calibration.camera import skew
from calibration.errors import CalibrationError

__all__ = [
    "PointCovariance",
    "Alignment",
    "similarity_fit",
    "helmert_basis",
    "align_to_cad",
    "transformed_alignment",
    "deviation_sigma_level",
]


@dataclass(frozen=True)
class PointCovariance:
    """Covariance of ``n`` points, ``Q = blockdiag(D) + U C U^T``.

    Attributes:
        D: (n, 3, 3) block-diagonal part.
        U: (n, 3, r) low-rank factor (rows of the point coordinates).
        C: (r, r) symmetric core.
    """

    D: np.ndarray
    U: np.ndarray
    C: np.ndarray

    @classmethod
    def independent(cls, cov: np.ndarray) -> "PointCovariance":
        """Targets without cross-covariance, from ``cov: (n, 3, 3)``."""
        cov = np.asarray(cov, dtype=float)
        return cls(D=cov, U=np.zeros((len(cov), 3, 0)), C=np.zeros((0, 0)))

    @property
    def n(self) -> int:
        return self.D.shape[0]

    def blocks(self) -> np.ndarray:
        """Per-point 3x3 covariance, (n, 3, 3)."""
        if self.U.shape[2] == 0:
            return self.D.copy()
        n, _, r = self.U.shape
        UC = (self.U.reshape(3 * n, r) @ self.C).reshape(n, 3, r)
        out = self.D + np.einsum("nar,nbr->nab", UC, self.U)
        return 0.5 * (out + np.swapaxes(out, 1, 2))

    def dense(self) -> np.ndarray:
        """The full covariance, (3n, 3n). Memory grows as n^2: for reports, not for loops."""
        n = self.n
        U = self.U.reshape(3 * n, -1)
        Q = U @ self.C @ U.T
        for i in range(n):
            Q[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] += self.D[i]
        return Q

    def select(self, index: np.ndarray) -> "PointCovariance":
        """Covariance of a subset of the points (index into the n points)."""
        index = np.asarray(index)
        return PointCovariance(self.D[index], self.U[index], self.C)

    def scaled(self, factor: float) -> "PointCovariance":
        """Covariance multiplied by a variance factor."""
        return PointCovariance(self.D * factor, self.U, self.C * factor)

    def rotated(self, A: np.ndarray) -> "PointCovariance":
        """Covariance of ``A @ x_i`` for every point, ``A: (3, 3)`` (e.g. scale times rotation)."""
        A = np.asarray(A, dtype=float)
        return PointCovariance(A @ self.D @ A.T, np.einsum("ab,nbr->nar", A, self.U), self.C)

    def s_transform(self, P: np.ndarray, H: np.ndarray) -> "PointCovariance":
        """Covariance of ``S x`` with ``S = I - P H^T``; ``P, H: (n, 3, d)`` with ``H^T P = I``."""
        n, _, d = P.shape
        if d == 0:
            return self
        HtD = np.einsum("nad,nab->dnb", H, self.D)  # (d, n, 3) = rows of H^T D
        DH = np.swapaxes(HtD, 0, 1).transpose(0, 2, 1)  # (n, 3, d)
        HtDH = np.einsum("dna,nae->de", HtD, H)
        r = self.U.shape[2]
        HtU = H.reshape(3 * n, d).T @ self.U.reshape(3 * n, r)
        SU = self.U - (P.reshape(3 * n, d) @ HtU).reshape(n, 3, r)
        C = np.zeros((2 * d + r, 2 * d + r))
        C[:d, :d] = HtDH
        C[:d, d : 2 * d] = -np.eye(d)
        C[d : 2 * d, :d] = -np.eye(d)
        C[2 * d :, 2 * d :] = self.C
        U = np.concatenate([P, DH, SU], axis=2)
        return PointCovariance(self.D.copy(), U, C)


def helmert_basis(points: np.ndarray, with_scale: bool = True) -> np.ndarray:
    """Infinitesimal similarity motions of ``points: (n, 3)``, (n, 3, d), d = 7 (or 6 without scale).

    Columns: translation x, y, z; rotation about x, y, z (``delta x = theta cross x``); scale.
    The points are centred first (the span is the same, the conditioning better).
    """
    x = np.asarray(points, dtype=float)
    x = x - x.mean(axis=0)
    n = len(x)
    G = np.zeros((n, 3, 7 if with_scale else 6))
    G[:, :, :3] = np.eye(3)
    G[:, :, 3:6] = -skew(x)
    if with_scale:
        G[:, :, 6] = x
    return G


def similarity_fit(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = False, weights: np.ndarray | None = None
) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares ``dst ~ s R src + t`` (Umeyama), ``src, dst: (n, 3)``. Returns ``(s, R (3, 3), t (3,))``."""
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=float)
    if len(src) < 3 or np.sum(w > 0) < 3:
        raise CalibrationError(f"a best fit needs at least 3 points, got {int(np.sum(w > 0))}")
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    a = src - mu_s
    b = dst - mu_d
    Sigma = (b * w[:, None]).T @ a
    Uu, sv, Vt = np.linalg.svd(Sigma)
    E = np.eye(3)
    if np.linalg.det(Uu) * np.linalg.det(Vt) < 0:
        E[2, 2] = -1.0
    if sv[1] < 1e-12 * max(sv[0], 1e-300):
        raise CalibrationError("a best fit needs points that are not all on one line")
    R = Uu @ E @ Vt
    s = float(np.trace(np.diag(sv) @ E) / (w @ np.sum(a * a, axis=1))) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


@dataclass(frozen=True)
class Alignment:
    """Measured targets brought onto the CAD nominals.

    Attributes:
        part_from_measured: (4, 4) similarity (rotation times ``scale`` in the upper-left block).
        scale: the scale of the fit (1 for a rigid fit).
        aligned: (n, 3) measured targets in the part (CAD) frame.
        deviation: (n, 3) ``aligned - nominal``.
        deviation_cov: (n, 3, 3) covariance of the deviations, including the fit's own uncertainty.
        deviation_covariance: the full :class:`PointCovariance` of the deviations.
        rms_m: root mean square deviation of the targets used in the fit.
    """

    part_from_measured: np.ndarray
    scale: float
    aligned: np.ndarray
    deviation: np.ndarray
    deviation_cov: np.ndarray
    deviation_covariance: PointCovariance
    rms_m: float

    def sigma_level(self) -> np.ndarray:
        """Each deviation's significance as an equivalent one-dimensional sigma level, (n,)."""
        return deviation_sigma_level(self.deviation, self.deviation_cov)


def align_to_cad(
    measured: np.ndarray,
    cov: np.ndarray | PointCovariance,
    nominal: np.ndarray,
    with_scale: bool = False,
    fit_mask: np.ndarray | None = None,
) -> Alignment:
    """Best fit (rigid, or similarity) of measured targets to their CAD nominals.

    Args:
        measured: (n, 3) measured target coordinates (any datum).
        cov: their covariance: a :class:`PointCovariance` (with cross-covariances, as the bundle
            adjustment returns it; exact propagation) or (n, 3, 3) blocks (treated as
            independent targets: an approximation that overstates the fit's effect on correlated targets).
        nominal: (n, 3) CAD coordinates, part frame.
        with_scale: also fit a scale (when the datum has no scale of its own).
        fit_mask: (n,) bool, the targets the fit uses (default: all finite). The others are
            transformed and get deviations too.

    The fit is unweighted least squares; the deviations' covariance is the S-transformation of
    the measured covariance: ``S (sR) Q (sR)^T S^T`` with ``S = I - G (G_f^T G_f)^-1 G_f^T``.
    """
    measured = np.asarray(measured, dtype=float)
    nominal = np.asarray(nominal, dtype=float)
    if measured.shape != nominal.shape or measured.ndim != 2 or measured.shape[1] != 3:
        raise CalibrationError(
            f"align_to_cad: measured {measured.shape} and nominal {nominal.shape} must both be (n, 3)"
        )
    pc = _as_point_covariance(cov, len(measured))
    finite = np.all(np.isfinite(measured), axis=1) & np.all(np.isfinite(nominal), axis=1)
    mask = finite if fit_mask is None else (np.asarray(fit_mask, dtype=bool) & finite)
    s, R, t = similarity_fit(measured[mask], nominal[mask], with_scale=with_scale)
    return transformed_alignment(measured, pc, nominal, s, R, t,
                                 lambda G: G * mask[finite_index(finite)][:, None, None].astype(float),
                                 with_scale=with_scale, rms_mask=mask)


def finite_index(finite: np.ndarray) -> np.ndarray:
    """Indices of the finite targets (the rows the datum matrices are built over)."""
    return np.flatnonzero(finite)


def _as_point_covariance(cov, n: int) -> PointCovariance:
    pc = cov if isinstance(cov, PointCovariance) else PointCovariance.independent(cov)
    if pc.n != n:
        raise CalibrationError(f"alignment: covariance for {pc.n} targets, {n} measured")
    return pc


def transformed_alignment(measured: np.ndarray, cov, nominal: np.ndarray, s: float, R: np.ndarray, t: np.ndarray,
                          datum, with_scale: bool = False, rms_mask: np.ndarray | None = None) -> Alignment:
    """The :class:`Alignment` of a given transformation ``x -> s R x + t`` and the datum that defined it.

    Args:
        measured, nominal: (n, 3); cov: :class:`PointCovariance` or (n, 3, 3).
        s, R, t: the transformation (scale, (3, 3) rotation, (3,) translation).
        datum: what the transformation holds fixed, for the covariance: a function of the Helmert basis
            ``G: (f, 3, d)`` at the f finite aligned targets returning ``H: (f, 3, d)`` with ``H^T G``
            invertible (the S-transformation ``I - G (H^T G)^-1 H^T``: e.g. ``G * w`` for a weighted best
            fit, unit vectors along the locked axes for RPS), or None: no transformation uncertainty (the
            measurement's own frame).
        with_scale: the transformation includes a fitted scale (d = 7, else 6).
        rms_mask: (n,) the targets whose rms deviation is reported (default: all finite).
    """
    measured = np.asarray(measured, dtype=float)
    nominal = np.asarray(nominal, dtype=float)
    pc = _as_point_covariance(cov, len(measured))
    finite = np.all(np.isfinite(measured), axis=1) & np.all(np.isfinite(nominal), axis=1)
    aligned = np.full_like(measured, np.nan)
    aligned[finite] = s * measured[finite] @ R.T + t
    deviation = aligned - nominal
    # propagate: rotate, then the S-transformation of the datum (at the aligned points)
    idx = finite_index(finite)
    sub = pc.select(idx).rotated(s * R)
    if datum is None:
        dev_pc_sub = sub
    else:
        G = helmert_basis(aligned[idx], with_scale=with_scale)
        H = np.asarray(datum(G), dtype=float)
        HtG = np.einsum("nad,nae->de", H, G)
        if np.linalg.cond(HtG) > 1e12:
            raise CalibrationError("alignment: the datum targets do not fix the transformation (singular datum)")
        dev_pc_sub = sub.s_transform(G @ np.linalg.inv(HtG), H)
    D = np.full((len(measured), 3, 3), np.nan)
    Uf = np.full((len(measured), 3, dev_pc_sub.U.shape[2]), np.nan)
    D[idx] = dev_pc_sub.D
    Uf[idx] = dev_pc_sub.U
    dev_pc = PointCovariance(D, Uf, dev_pc_sub.C)
    blocks = np.full((len(measured), 3, 3), np.nan)
    blocks[idx] = dev_pc_sub.blocks()
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = t
    rm = finite if rms_mask is None else (np.asarray(rms_mask, dtype=bool) & finite)
    rms = float(np.sqrt(np.mean(np.sum(deviation[rm] ** 2, axis=1)))) if rm.any() else float("nan")
    return Alignment(T, s, aligned, deviation, blocks, dev_pc, rms)


def deviation_sigma_level(deviation: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Significance of 3-D deviations as an equivalent 1-D sigma level, (n,).

    ``m^2 = d^T C^-1 d`` is chi-square with 3 degrees of freedom when the deviation is noise;
    it is mapped to the ``z`` with the same two-sided tail probability, so ``z > 3`` flags
    0.27 % of the targets without a real deviation, as a 1-D 3-sigma test would.
    """
    d = np.asarray(deviation, dtype=float)
    C = np.asarray(cov, dtype=float)
    out = np.full(len(d), np.nan)
    ok = np.all(np.isfinite(d), axis=1) & np.all(np.isfinite(C), axis=(1, 2))
    try:
        m2 = np.einsum("na,na->n", d[ok], np.linalg.solve(C[ok], d[ok][..., None])[..., 0])
    except np.linalg.LinAlgError:  # a fit target's covariance can be singular (a frame on few targets): its range
        m2 = np.einsum("na,na->n", d[ok], np.einsum("nab,nb->na", np.linalg.pinv(C[ok], hermitian=True), d[ok]))
    p = chdtrc(3, m2)  # chi2.sf(m2, 3)
    out[ok] = -ndtri(np.clip(p, 1e-300, 1.0) / 2.0)  # norm.isf
    return out
