"""Residual statistics of an adjustment: variance factor, redundancy numbers, data-snooping statistic."""
from __future__ import annotations

import numpy as np

from calibration.bundle.normal import _Layout, _Linear
from calibration.errors import CalibrationError


def _statistics(lin: _Linear, lay: _Layout, n_obs: int) -> dict:
    """Variance factor, redundancy numbers and the data-snooping statistic of each active observation."""
    r2 = float(np.sum(lin.r_img**2) + np.sum(lin.r_extra**2))
    n_par = 3 * len(lin.Dinv) + lay.p - lin.defect
    dof = 2 * n_obs + len(lin.r_extra) - n_par
    if dof <= 0:
        raise CalibrationError(f"bundle: no redundancy ({dof} degrees of freedom); more images or targets are needed")
    s02 = r2 / dof
    nu, p = lin.V.shape[0], lin.Sigma.shape[0]
    m, k = lay.m, lay.k
    VS = (lin.V.reshape(-1, p) @ lin.Sigma).reshape(nu, 3, p)
    Qpp = lin.Dinv + np.einsum("nar,nbr->nab", VS, lin.V)
    sl, ci = lin.slot, lin.cidx
    img = ci[:, 0] // 6
    w = 6 + k
    # Q blocks each observation needs, gathered from contiguous per-image blocks
    Qpc = np.empty((len(sl), 3, w))
    VSr = np.ascontiguousarray(VS[:, :, : 6 * m].reshape(nu, 3, m, 6).transpose(0, 2, 1, 3))
    Qpc[:, :, :6] = -VSr[sl, img]
    Sr = lin.Sigma[: 6 * m, : 6 * m].reshape(m, 6, m, 6)
    Qcc = np.empty((len(sl), w, w))
    Qcc[:, :6, :6] = Sr[np.arange(m), :, np.arange(m), :][img]
    if k:
        Qpc[:, :, 6:] = -VS[:, :, 6 * m : 6 * m + k][sl]
        SI = lin.Sigma[: 6 * m, 6 * m : 6 * m + k].reshape(m, 6, k)[img]
        Qcc[:, :6, 6:] = SI
        Qcc[:, 6:, :6] = np.swapaxes(SI, 1, 2)
        Qcc[:, 6:, 6:] = lin.Sigma[6 * m : 6 * m + k, 6 * m : 6 * m + k]
    Jp, Jc = lin.Jp, lin.Jc[:, :, :w]
    Qsl = Qpp[sl]
    A = (
        np.einsum("qib,qjb->qij", np.einsum("qia,qab->qib", Jp, Qsl), Jp)
        + 2 * np.einsum("qib,qjb->qij", np.einsum("qia,qab->qib", Jp, Qpc), Jc)
        + np.einsum("qib,qjb->qij", np.einsum("qia,qab->qib", Jc, Qcc), Jc)
    )
    linked = np.any(lin.cidx[:, w:] != 0, axis=1) | np.any(lin.Jc[:, :, w:] != 0, axis=(1, 2))
    if np.any(linked):  # observations of scale-bar targets: the general (slow) gather, on few rows
        cl = lin.cidx[linked]
        Jl = lin.Jc[linked]
        Ql = lin.Sigma[cl[:, :, None], cl[:, None, :]]
        A[linked] = np.einsum("qib,qjb->qij", np.einsum("qia,qab->qib", Jl, Ql), Jl)
    A = 0.5 * (A + np.swapaxes(A, 1, 2))
    Qvv = np.eye(2) - A
    red = 0.5 * np.trace(Qvv, axis1=1, axis2=2)
    det = Qvv[:, 0, 0] * Qvv[:, 1, 1] - Qvv[:, 0, 1] ** 2
    det = np.where(det > 1e-12, det, np.nan)  # observations without redundancy cannot be tested
    v = lin.r_img
    T = (Qvv[:, 1, 1] * v[:, 0] ** 2 - 2 * Qvv[:, 0, 1] * v[:, 0] * v[:, 1] + Qvv[:, 0, 0] * v[:, 1] ** 2) / det
    return {"s02": s02, "dof": dof, "T": T, "redundancy": red}
