"""Several scale bars test each other: each certificate against the scale the rest of the network gives.

With ``b >= 2`` bars the certified lengths are redundant observations of the adjustment, and each has a residual
``r_j = l_hat_j - l_j`` (adjusted length minus certificate). Its variance follows from the quantities the
adjustment already has (decision 0041).

Write the adjusted length's error as a linear function of the errors it was made from: the images' errors and
each certificate's error ``e_k`` (variance ``s_k^2``). The gains :func:`calibration.bundle.coherent.scale_bar_gains`
``k_k`` say how the points move per metre of ``e_k``; through the bar's length derivative ``A_j`` (``+u`` at one
end, ``-u`` at the other) the adjusted length moves by ``h_jk = A_j k_k``. The certificate itself enters the
residual with ``-1``, so ``r_j = g^T e_img + sum_k (h_jk - delta_jk) e_k`` and, with the images' part of the
length's variance ``A_j C A_j^T - sum_k h_jk^2 s_k^2`` (``C`` the points' honest covariance, in which each
certificate's share is ``s_k^2 k_k k_k^T``: :func:`calibration.bundle.coherent.certificate_at_face_value`),

    var(r_j) = A_j C A_j^T - sum_k h_jk^2 s_k^2 + sum_k (h_jk - delta_jk)^2 s_k^2
             = A_j C A_j^T + s_j^2 (1 - 2 h_jj).

(For an a priori adjustment ``h_jj s_j^2 = A_j Q A_j^T`` and this is the textbook ``Q_rr = Q_ll - Q_l^l^``:
``s_j^2 - A_j Q A_j^T``.) The ends' shared background misfit (decision 0029) is an error ``d_j`` of the images'
length of bar ``j`` (variance ``v_j``): ADJUST states it twice in ``C``, in the ends' own blocks (``v_j`` along the
bar) and through the gains (``v_j k_j k_j^T``, as if it were a certificate's error), without the cross term. Its
true effect on the residual is ``(1 - h_jj) d_j`` (the scale pulls the adjusted length back by ``h_jj d_j``), on
another bar's ``h_ij d_j``; so ``A_j C A_j^T`` carries ``v_j (1 + h_jj^2)`` where ``(1 - h_jj)^2 v_j`` belongs:

    var(r_j) = A_j C A_j^T + s_j^2 (1 - 2 h_jj) - 2 h_jj v_j.

With one bar ``h_jj = 1`` and ``A C A^T = s^2 + 2 v``: the variance is zero, the residual too; the certificate
cannot be tested.

The test is two-sided on the normalised residual ``w_j = r_j / sigma(r_j)``, Bonferroni over the bars tested
(``alpha / b`` each): ``|w_j| > z_{1 - alpha / (2 b)}`` fails. The normalised residuals are correlated (they sum
to zero in the weighted sense): a certificate off by ``x`` of its sigma shows most in its own ``w`` (three equal
bars: ``0.82 x`` on it, ``0.41 x`` on the others), so the caller leaves out the worst failing bar and adjusts
again; with two bars ``|w|`` is the same on both and the bars cannot be told apart.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import norm

__all__ = ["BarTest", "bar_residual_test", "ALPHA"]

#: the family-wise false-alarm rate of the bar test (split over the bars: Bonferroni)
ALPHA = 0.001


@dataclass
class BarTest:
    """Per bar (in the order given): ``length_m`` the adjusted length, ``certificate_m``, ``residual_m`` (adjusted
    minus certificate), ``sigma_m`` its standard deviation (NaN where not testable), ``w`` the normalised residual,
    ``h`` the bar's own gain ``h_jj`` (its certificate's weight in its adjusted length); ``critical`` the bound on
    ``|w|``; ``failed`` (b,) bool."""

    length_m: np.ndarray
    certificate_m: np.ndarray
    residual_m: np.ndarray
    sigma_m: np.ndarray
    w: np.ndarray
    h: np.ndarray
    critical: float
    failed: np.ndarray

    def worst(self) -> int | None:
        """The failing bar with the largest ``|w|`` (None: none fails)."""
        if not self.failed.any():
            return None
        return int(np.nanargmax(np.where(self.failed, np.abs(self.w), -np.inf)))


def _length_var(cov, a: int, b: int, u: np.ndarray) -> float:
    """``A C A^T`` of the length between points ``a`` and ``b`` (direction ``u``) for a ``PointCovariance``."""
    D = np.nan_to_num(cov.D)
    U = np.nan_to_num(cov.U)
    w = U[a].T @ u - U[b].T @ u
    return float(u @ D[a] @ u + u @ D[b] @ u + w @ cov.C @ w)


def bar_residual_test(points: np.ndarray, cov, K: np.ndarray, bars, extra_var=None, alpha: float = ALPHA) -> BarTest:
    """The residual test of each bar's certificate (see the module).

    Args:
        points: (n, 3) adjusted coordinates; ``cov``: their honest :class:`calibration.alignment.PointCovariance`
            (the certificates at face value, with the ends' shared misfit when ``extra_var`` is given).
        K: (n, 3, b) the gains of :func:`calibration.bundle.coherent.scale_bar_gains`; ``bars``: the ``b``
            :class:`calibration.bundle.config.ScaleBar` the adjustment used, in the order of ``K``'s columns.
        extra_var: (b,) m^2 the variance of each bar's measured length from its ends' shared background misfit (the
            rank-one terms ADJUST added to ``cov``); None: none.
        alpha: the family-wise level, split over the bars.
    Returns:
        :class:`BarTest`; with fewer than two bars nothing is tested (``sigma_m`` NaN, nothing fails).
    """
    nb = len(bars)
    v = np.zeros(nb) if extra_var is None else np.asarray(extra_var, dtype=float)
    L = np.zeros(nb)
    cert = np.array([b.length_m for b in bars], dtype=float)
    s2 = np.array([b.sigma_m for b in bars], dtype=float) ** 2
    sig = np.full(nb, np.nan)
    h = np.full(nb, np.nan)
    Kz = np.nan_to_num(np.asarray(K, dtype=float))
    for j, bar in enumerate(bars):
        a, b = bar.target_a, bar.target_b
        d = np.asarray(points[a] - points[b], dtype=float)
        L[j] = float(np.linalg.norm(d))
        u = d / L[j]
        h[j] = float(u @ (Kz[a, :, j] - Kz[b, :, j]))
        var = _length_var(cov, a, b, u) + s2[j] * (1.0 - 2.0 * h[j]) - 2.0 * h[j] * v[j]
        # a residual whose variance is below a millionth of the certificate's is not testable (one bar: zero)
        if nb >= 2 and var > 1e-6 * (s2[j] + v[j]):
            sig[j] = np.sqrt(var)
    r = L - cert
    with np.errstate(invalid="ignore", divide="ignore"):
        w = r / sig
    crit = float(norm.isf(alpha / (2 * max(nb, 1))))
    failed = np.isfinite(w) & (np.abs(w) > crit)
    return BarTest(L, cert, r, sig, w, h, crit, failed)
