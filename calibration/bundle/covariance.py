"""The adjustment's result: per-target covariance in the datum (S-transform), residuals, redundancy."""
from __future__ import annotations

import numpy as np

from calibration.alignment import PointCovariance, helmert_basis
from calibration.bundle.config import BundleResult
from calibration.bundle.projection import project_observations


def _result(state, lin, stats, lay, T, rejected, act_obs, obs_image, obs_target, obs_uv, options, config,
            converged, report, timings, total) -> BundleResult:
    n = lay.n
    s02 = stats["s02"]
    factor = s02 if options.a_posteriori else 1.0
    # per-point representation: x = D-part + A dc
    p = lay.p
    D = np.zeros((n, 3, 3))
    A = np.zeros((n, 3, p))
    D[lay.unlinked] = lin.Dinv
    A[lay.unlinked] = -lin.V
    if len(lay.linked):
        cols = lay.link_cols(lay.linked)
        A[lay.linked[:, None], np.arange(3)[None, :], cols] = 1.0
    act = np.concatenate([lay.unlinked, lay.linked])
    pc = PointCovariance(D[act], A[act], lin.Sigma)
    if lin.defect:
        G = helmert_basis(state.points[act], with_scale=lin.defect == 7)
        Qg, _ = np.linalg.qr(G.reshape(-1, lin.defect))
        Qg = Qg.reshape(len(act), 3, lin.defect)
        pc = pc.s_transform(Qg, Qg)
    pc = pc.scaled(factor)
    # back to all n targets (inactive: nan)
    Dn = np.full((n, 3, 3), np.nan)
    Un = np.full((n, 3, pc.U.shape[2]), np.nan)
    Dn[act], Un[act] = pc.D, pc.U
    full = PointCovariance(Dn, Un, pc.C)
    cov = np.full((n, 3, 3), np.nan)
    cov[act] = pc.blocks()
    points = np.full((n, 3), np.nan)
    points[act] = state.points[act]
    k = lay.k
    icov = lin.Sigma[6 * lay.m : 6 * lay.m + k, 6 * lay.m : 6 * lay.m + k] * factor
    # residuals of all observations at the final state (rejected ones too, where their target survives)
    res = np.full((len(obs_image), 2), np.nan)
    ok = np.isin(obs_target, act)
    R = state.poses[obs_image[ok], :3, :3]
    tt = state.poses[obs_image[ok], :3, 3]
    uv, *_ = project_observations(state.intr, R, tt, state.points[obs_target[ok]])
    res[ok] = obs_uv[ok] - uv
    red = np.full(len(obs_image), np.nan)
    red[act_obs] = stats["redundancy"]
    timings = dict(timings, total=total)
    return BundleResult(
        points=points, cov=cov, covariance=full, cam_from_part=state.poses, intrinsics=state.intr,
        intrinsics_names=lay.names, intrinsics_cov=icov, sigma0_px=float(np.sqrt(s02) * options.sigma_px),
        residuals=res, test_statistic=T, redundancy=red, rejected=rejected, dof=int(stats["dof"]),
        datum=config.datum, converged=bool(converged), summary=report, timings=timings,
    )
