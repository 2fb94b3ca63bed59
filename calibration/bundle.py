"""Rigorous bundle adjustment of the targets: pycolmap's solver, a datum, covariance, data snooping.

Stages (``bundle_adjust``):

1. A ``pycolmap.Reconstruction`` is built from our data (one camera: PINHOLE,
   SIMPLE_RADIAL, RADIAL or OPENCV; one image per station with ``cam_from_world`` =
   our ``cam_from_part``; one 3-D point per target; the 2-D observations). COLMAP's pixel
   origin is the top-left pixel's corner, ours its centre: ``uv_colmap = uv + 0.5`` (also for
   the principal point). pycolmap's Ceres bundle adjuster refines points, poses and the
   interior orientation groups the :class:`BundleConfig` frees, with its gauge fixed by two cameras.
2. Datum. ``free``: inner constraints on the targets (no net translation, rotation and scale
   with respect to the initial coordinates). ``scale_bar``: calibrated distances between
   target pairs fix the scale, inner constraints the rest. ``control``: targets with known
   coordinates and standard deviations, weighted. Scale bars and control targets are extra
   observations that pycolmap's Python API cannot take (custom Ceres residuals need pyceres,
   not installed, and pycolmap's covariance needs the plain Schur structure), so they are
   applied by Gauss-Newton iterations on the full normal equations, started from pycolmap's
   optimum.
3. Covariance from the same normal equations, reduced to the camera parameters by the
   Schur complement. pycolmap's ``BACovariance`` gives each point's covariance *conditioned
   on the cameras* (documented in ``colmap/estimators/covariance.h``), which understates a
   target's uncertainty, and has no inner-constraint datum nor pose-intrinsics cross terms,
   so the per-target covariance is computed here (its pose block agrees with pycolmap's, a
   test checks it) and returned in the low-rank :class:`PointCovariance` form, so the
   alignment can propagate cross-covariances exactly.
4. Residual statistics (sigma0, redundancy numbers) and data snooping: the observation with
   the largest test statistic ``v^T Q_vv^-1 v / s0^2`` (chi-square, 2 dof) above the critical value
   is removed and the network re-adjusted, until none is left.

Observations of unequal precision (:mod:`calibration.weights`): ``obs_sigma_px`` gives each
image observation its own a priori sigma, ``obs_group`` estimates one variance component per
group (Förstner), re-adjusting until they settle, before each data-snooping test. pycolmap's
solver weights all observations alike, so weighted networks are then iterated to the weighted
optimum by Gauss-Newton on the full normal equations (every datum). Everything downstream
(sigma0, covariance, redundancy numbers, test statistics) works on the whitened observations.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
import pycolmap
from scipy.stats import chi2

try:  # BLAS threads fight with Ceres' threads on small machines: small dense algebra runs faster on one
    from threadpoolctl import threadpool_limits
except ImportError:  # pragma: no cover - optional
    threadpool_limits = None

from calibration.alignment import PointCovariance, helmert_basis, similarity_fit
from calibration.camera import Intrinsics, exp_se3, skew
from calibration.errors import CalibrationError
from calibration.weights import VarianceComponents, check_groups, check_sigmas, variance_component_factors

__all__ = [
    "ScaleBar",
    "ControlPoints",
    "BundleOptions",
    "BundleConfig",
    "BundleResult",
    "bundle_adjust",
    "CAMERA_MODELS",
    "SyntheticNetwork",
    "simulate_network",
    "project_observations",
]

#: our name -> (COLMAP model, parameter names in COLMAP order)
CAMERA_MODELS: dict[str, tuple[str, ...]] = {
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}
_GROUPS = {"focal": ("f", "fx", "fy"), "principal": ("cx", "cy"), "distortion": ("k1", "k2", "p1", "p2")}
_PIXEL_OFFSET = 0.5  # COLMAP pixel origin (corner) minus ours (centre)


@dataclass(frozen=True)
class ScaleBar:
    """A calibrated distance between two targets (indices into the points)."""

    target_a: int
    target_b: int
    length_m: float
    sigma_m: float


@dataclass(frozen=True)
class ControlPoints:
    """Targets with known coordinates: ``index: (k,)`` into the points, ``xyz: (k, 3)``, ``sigma_m: (k,) or (k, 3)``."""

    index: np.ndarray
    xyz: np.ndarray
    sigma_m: np.ndarray


@dataclass(frozen=True)
class BundleOptions:
    """How to solve (not what is held fixed: that is :class:`BundleConfig`).

    Attributes:
        sigma_px: a priori standard deviation of an image coordinate (pixels); weights the
            image observations against scale bars and control targets.
        a_posteriori: scale the covariance by the estimated variance factor ``s0^2``.
        max_iterations: pycolmap (Ceres) iterations.
        num_threads: Ceres threads.
        snooping: run data snooping with re-adjustment.
        alpha: family-wise significance level of data snooping over the whole network
            (each observation is tested at ``alpha / q``, so a clean network keeps all its observations
            with probability ``1 - alpha``).
        max_rejections: at most this many observations removed.
        datum_iterations: Gauss-Newton iterations for scale bars and control targets.
        blas_threads: BLAS threads for the covariance algebra (None: leave as is). One is the fastest
            for networks of up to a few thousand targets on a 2-core machine (needs threadpoolctl).
        vce_iterations: at most this many re-adjustments of the variance component estimation
            (``obs_group``) per data-snooping round.
        vce_min_redundancy: a group with less redundancy (sum over its coordinates) takes the pooled
            variance factor of all groups instead of its own.
        vce_tolerance: the estimation stops when every group's sigma changes by less than this (relative).
    """

    sigma_px: float = 0.05
    a_posteriori: bool = True
    max_iterations: int = 100
    num_threads: int = 2
    snooping: bool = True
    alpha: float = 0.01
    max_rejections: int = 20
    datum_iterations: int = 10
    blas_threads: int | None = 1
    vce_iterations: int = 15
    vce_min_redundancy: float = 50.0
    vce_tolerance: float = 0.005


@dataclass(frozen=True)
class BundleConfig:
    """What is estimated and the datum.

    Attributes:
        camera_model: one of :data:`CAMERA_MODELS`.
        refine_focal_length, refine_principal_point, refine_distortion: self-calibration groups
            (all ``False``: the interior orientation is held fixed).
        scale_bars: calibrated distances (datum ``scale_bar``).
        control: control targets (datum ``control``; takes precedence over scale bars for the datum,
            scale bars are then extra observations).
    """

    camera_model: str = "PINHOLE"
    refine_focal_length: bool = False
    refine_principal_point: bool = False
    refine_distortion: bool = False
    scale_bars: tuple[ScaleBar, ...] = ()
    control: ControlPoints | None = None

    @property
    def datum(self) -> str:
        if self.control is not None and len(self.control.index) > 0:
            return "control"
        if self.scale_bars:
            return "scale_bar"
        return "free"

    def refined_names(self) -> tuple[str, ...]:
        if self.camera_model not in CAMERA_MODELS:
            raise CalibrationError(
                f"bundle: unknown camera model {self.camera_model!r}; use one of {sorted(CAMERA_MODELS)}"
            )
        groups = [g for g, on in (("focal", self.refine_focal_length), ("principal", self.refine_principal_point),
                                  ("distortion", self.refine_distortion)) if on]
        return tuple(p for p in CAMERA_MODELS[self.camera_model] if any(p in _GROUPS[g] for g in groups))


@dataclass
class BundleResult:
    """Outcome of :func:`bundle_adjust` (points, poses and residuals in our conventions).

    Attributes:
        points: (n, 3) adjusted targets (nan where fewer than 2 rays remain).
        cov: (n, 3, 3) per-target covariance (m^2) in the datum.
        covariance: full target covariance (:class:`PointCovariance`), for alignment.
        cam_from_part: (m, 4, 4) adjusted exterior orientations.
        intrinsics: adjusted interior orientation.
        intrinsics_names, intrinsics_cov: the refined interior parameters and their covariance.
        sigma0_px: a posteriori standard deviation of unit weight, in pixels.
        residuals: (q, 2) observed minus computed pixels (rejected ones too).
        test_statistic: (q,) data-snooping statistic (chi-square 2 dof; nan for rejected).
        redundancy: (q,) redundancy number of each observation (0..1 per coordinate, averaged).
        rejected: (q,) observations removed as blunders.
        dof: degrees of freedom.
        datum: "free", "scale_bar" or "control".
        converged: pycolmap reported a usable solution and the datum iterations converged.
        summary: pycolmap's brief report of the last solve.
        timings: seconds per stage.
        obs_sigma_px: (q,) a priori sigma of each image observation used in the final adjustment (pixels;
            ``sigma0_px`` is then the a posteriori sigma of an observation whose a priori sigma is the rms of
            those of the observations used: the network's image precision, as with equal weights).
        variance_components: the per-group estimate when ``obs_group`` was given, else None.
    """

    points: np.ndarray
    cov: np.ndarray
    covariance: PointCovariance
    cam_from_part: np.ndarray
    intrinsics: Intrinsics
    intrinsics_names: tuple[str, ...]
    intrinsics_cov: np.ndarray
    sigma0_px: float
    residuals: np.ndarray
    test_statistic: np.ndarray
    redundancy: np.ndarray
    rejected: np.ndarray
    dof: int
    datum: str
    converged: bool
    summary: str
    timings: dict = field(default_factory=dict)
    obs_sigma_px: np.ndarray | None = None
    variance_components: VarianceComponents | None = None

    def error_ellipsoids(self, k: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Semi-axes ``(n, 3)`` (metres, ascending, times ``k``) and axis directions ``(n, 3, 3)`` (columns)."""
        ok = np.all(np.isfinite(self.cov), axis=(1, 2))
        axes = np.full((len(self.cov), 3), np.nan)
        dirs = np.full((len(self.cov), 3, 3), np.nan)
        w, V = np.linalg.eigh(self.cov[ok])
        axes[ok] = k * np.sqrt(np.clip(w, 0.0, None))
        dirs[ok] = V
        return axes, dirs

    def sigma_m(self) -> np.ndarray:
        """sqrt(trace(cov)) per target, (n,)."""
        return np.sqrt(np.trace(self.cov, axis1=1, axis2=2))


# --- camera model <-> COLMAP ------------------------------------------------------


def _to_colmap_params(intr: Intrinsics, model: str) -> list[float]:
    f = 0.5 * (intr.fx_px + intr.fy_px)
    if model in ("SIMPLE_RADIAL", "RADIAL") and (intr.p1 or intr.p2 or intr.k3 or abs(intr.fx_px - intr.fy_px) > 1e-9 * f):
        raise CalibrationError(
            f"bundle: camera model {model} has one focal length and radial terms only; "
            f"the intrinsics have fx != fy or tangential/k3 terms: use OPENCV"
        )
    if intr.k3:
        raise CalibrationError("bundle: k3 is not supported by the COLMAP models used here; set k3 = 0")
    vals = {"fx": intr.fx_px, "fy": intr.fy_px, "f": f, "cx": intr.cx_px + _PIXEL_OFFSET,
            "cy": intr.cy_px + _PIXEL_OFFSET, "k1": intr.k1, "k2": intr.k2, "p1": intr.p1, "p2": intr.p2}
    if model == "PINHOLE" and intr.has_distortion:
        raise CalibrationError("bundle: the PINHOLE model has no distortion; choose a model with distortion terms")
    return [float(vals[p]) for p in CAMERA_MODELS[model]]


def _from_colmap_params(params: np.ndarray, model: str, base: Intrinsics) -> Intrinsics:
    d = dict(zip(CAMERA_MODELS[model], (float(v) for v in params)))
    if "f" in d:
        d["fx"] = d["fy"] = d.pop("f")
    d["cx"] -= _PIXEL_OFFSET
    d["cy"] -= _PIXEL_OFFSET
    return replace(base, fx_px=d["fx"], fy_px=d["fy"], cx_px=d["cx"], cy_px=d["cy"],
                   k1=d.get("k1", 0.0), k2=d.get("k2", 0.0), p1=d.get("p1", 0.0), p2=d.get("p2", 0.0))


def _update_intrinsics(intr: Intrinsics, names: tuple[str, ...], delta: np.ndarray) -> Intrinsics:
    d = {"fx_px": intr.fx_px, "fy_px": intr.fy_px, "cx_px": intr.cx_px, "cy_px": intr.cy_px,
         "k1": intr.k1, "k2": intr.k2, "p1": intr.p1, "p2": intr.p2}
    for name, dv in zip(names, delta):
        if name == "f":
            d["fx_px"] += dv
            d["fy_px"] += dv
        elif name in ("fx", "fy", "cx", "cy"):
            d[name + "_px"] += dv
        else:
            d[name] += dv
    return replace(intr, **d)


# --- vectorised projection of observations ----------------------------------------


def project_observations(
    intr: Intrinsics, R: np.ndarray, t: np.ndarray, X: np.ndarray, names: tuple[str, ...] = ()
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Project ``X: (q, 3)`` through per-observation poses ``R: (q, 3, 3)``, ``t: (q, 3)``.

    Returns ``uv (q, 2)``, ``J_point (q, 2, 3)``, ``J_pose (q, 2, 6)`` (left perturbation
    ``xi = (omega, tau)``, as :func:`calibration.camera.project_with_jacobians`) and
    ``J_intr (q, 2, len(names))`` for the interior parameters ``names``.
    """
    Xc = np.einsum("qab,qb->qa", R, X) + t
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    iz = 1.0 / z
    xy = np.stack([x * iz, y * iz], axis=1)
    q = len(z)
    dxy_dX = np.zeros((q, 2, 3))
    dxy_dX[:, 0, 0] = iz
    dxy_dX[:, 0, 2] = -x * iz * iz
    dxy_dX[:, 1, 1] = iz
    dxy_dX[:, 1, 2] = -y * iz * iz
    Dd = intr.distortion_jacobian(xy)
    xyd = intr.distort(xy)
    F = np.array([intr.fx_px, intr.fy_px])
    duv_dX = F[None, :, None] * np.einsum("qij,qjk->qik", Dd, dxy_dX)
    uv = np.stack([intr.fx_px * xyd[:, 0] + intr.cx_px, intr.fy_px * xyd[:, 1] + intr.cy_px], axis=1)
    J_point = duv_dX @ R
    J_pose = np.concatenate([duv_dX @ -skew(Xc), duv_dX], axis=2)
    J_intr = np.zeros((q, 2, len(names)))
    xn, yn = xy[:, 0], xy[:, 1]
    r2 = xn * xn + yn * yn
    for c, name in enumerate(names):
        if name == "fx":
            J_intr[:, 0, c] = xyd[:, 0]
        elif name == "fy":
            J_intr[:, 1, c] = xyd[:, 1]
        elif name == "f":
            J_intr[:, :, c] = xyd
        elif name == "cx":
            J_intr[:, 0, c] = 1.0
        elif name == "cy":
            J_intr[:, 1, c] = 1.0
        elif name in ("k1", "k2"):
            rp = r2 if name == "k1" else r2 * r2
            J_intr[:, 0, c] = intr.fx_px * xn * rp
            J_intr[:, 1, c] = intr.fy_px * yn * rp
        elif name == "p1":
            J_intr[:, 0, c] = intr.fx_px * 2 * xn * yn
            J_intr[:, 1, c] = intr.fy_px * (r2 + 2 * yn * yn)
        elif name == "p2":
            J_intr[:, 0, c] = intr.fx_px * (r2 + 2 * xn * xn)
            J_intr[:, 1, c] = intr.fy_px * 2 * xn * yn
    return uv, J_point, J_pose, J_intr


def _segment_sum(values: np.ndarray, ids: np.ndarray, size: int) -> np.ndarray:
    """Sum ``values: (q, ...)`` by ``ids: (q,)`` into ``(size, ...)``."""
    shape = values.shape[1:]
    E = int(np.prod(shape)) if shape else 1
    flat = (ids[:, None] * E + np.arange(E)[None, :]).ravel()
    out = np.bincount(flat, weights=values.reshape(len(ids), E).ravel(), minlength=size * E)
    return out.reshape((size,) + shape)


# --- the linearised problem ----------------------------------------------------------


@dataclass
class _State:
    intr: Intrinsics
    poses: np.ndarray  # (m, 4, 4)
    points: np.ndarray  # (n, 3)


@dataclass
class _Linear:
    """Normal equations reduced to the camera side, at one state."""

    r_img: np.ndarray  # (q, 2) weighted residuals of the active observations
    r_extra: np.ndarray  # (e,) weighted residuals of scale bars and control
    Dinv: np.ndarray  # (nu, 3, 3)
    V: np.ndarray  # (nu, 3, p)  Npp^-1 Npc
    Sigma: np.ndarray  # (p, p) g-inverse of the reduced matrix
    dc: np.ndarray  # (p,) camera-side step
    dp: np.ndarray  # (nu, 3) point step
    Jp: np.ndarray  # (q, 2, 3)
    Jc: np.ndarray  # (q, 2, w) compact camera-side Jacobian
    cidx: np.ndarray  # (q, w) its columns
    slot: np.ndarray  # (q,) unlinked point slot of each observation (or 0 with Jp = 0)
    defect: int


class _Layout:
    """Parameter layout: camera side = poses (6 m) | interior (k) | linked points (3 L); the other points apart."""

    def __init__(self, m: int, n: int, names: tuple[str, ...], active_pts: np.ndarray, linked: np.ndarray):
        self.m, self.n, self.names = m, n, names
        self.k = len(names)
        self.linked = np.flatnonzero(linked & active_pts)
        self.unlinked = np.flatnonzero(~linked & active_pts)
        self.lslot = np.full(n, -1)
        self.lslot[self.linked] = np.arange(len(self.linked))
        self.uslot = np.full(n, -1)
        self.uslot[self.unlinked] = np.arange(len(self.unlinked))
        self.p = 6 * m + self.k + 3 * len(self.linked)

    def link_cols(self, targets: np.ndarray) -> np.ndarray:
        """(len, 3) camera-side columns of linked targets."""
        return 6 * self.m + self.k + 3 * self.lslot[targets][:, None] + np.arange(3)[None, :]


def _null_space(state: _State, lay: _Layout, d: int) -> tuple[np.ndarray, np.ndarray]:
    """Infinitesimal similarities of the whole network: camera side (p, d), unlinked points (nu, 3, d)."""
    if d == 0:
        return np.zeros((lay.p, 0)), np.zeros((len(lay.unlinked), 3, 0))
    act = np.concatenate([lay.unlinked, lay.linked])
    c0 = state.points[act].mean(axis=0)
    G7p = helmert_basis(np.vstack([state.points[act], c0[None]]), with_scale=True)  # centred at c0 (last row 0)
    Gp = np.zeros((lay.n, 3, 7))
    Gp[act] = G7p[:-1]
    Gc = np.zeros((lay.p, 7))
    R = state.poses[:, :3, :3]
    tt = state.poses[:, :3, 3] + np.einsum("mab,b->ma", R, c0)  # translation w.r.t. the centred frame
    for j in range(lay.m):
        Rj, tj = R[j], tt[j]
        Gc[6 * j : 6 * j + 3, 3:6] = -Rj
        Gc[6 * j + 3 : 6 * j + 6, 0:3] = -Rj
        Gc[6 * j + 3 : 6 * j + 6, 3:6] = -skew(tj) @ Rj
        Gc[6 * j + 3 : 6 * j + 6, 6] = tj
    if len(lay.linked):
        cols = lay.link_cols(lay.linked)
        Gc[cols.ravel(), :] = Gp[lay.linked].reshape(-1, 7)
    return Gc[:, :d], Gp[lay.unlinked][:, :, :d]


def _linearise(
    state: _State, obs_image: np.ndarray, obs_target: np.ndarray, obs_uv: np.ndarray, lay: _Layout,
    config: BundleConfig, sigma_px: float | np.ndarray, defect: int,
) -> _Linear:
    m, k, p = lay.m, lay.k, lay.p
    R = state.poses[obs_image, :3, :3]
    t = state.poses[obs_image, :3, 3]
    uv, Jp, Jpose, Jin = project_observations(state.intr, R, t, state.points[obs_target], lay.names)
    if np.any(~np.isfinite(uv)) or np.any(np.einsum("qb,qb->q", R[:, 2], state.points[obs_target]) + t[:, 2] <= 0):
        raise CalibrationError("bundle: a target is behind a camera that observes it; check identification")
    w = 1.0 / np.broadcast_to(np.asarray(sigma_px, dtype=float), (len(uv),))  # (q,) weights^(1/2)
    r = (obs_uv - uv) * w[:, None]
    Jp, Jpose, Jin = Jp * w[:, None, None], Jpose * w[:, None, None], Jin * w[:, None, None]
    is_linked = lay.lslot[obs_target] >= 0
    # compact camera-side Jacobian: pose (6) | interior (k) | linked point (3)
    W = 6 + k + 3
    Jc = np.zeros((len(r), 2, W))
    Jc[:, :, :6] = Jpose
    Jc[:, :, 6 : 6 + k] = Jin
    cidx = np.zeros((len(r), W), dtype=int)
    cidx[:, :6] = 6 * obs_image[:, None] + np.arange(6)
    cidx[:, 6 : 6 + k] = 6 * m + np.arange(k)
    if np.any(is_linked):
        Jc[is_linked, :, 6 + k :] = Jp[is_linked]
        cidx[is_linked, 6 + k :] = lay.link_cols(obs_target[is_linked])
        Jp = Jp.copy()
        Jp[is_linked] = 0.0
    slot = np.where(is_linked, 0, lay.uslot[obs_target])
    # camera side: pose and interior blocks by image, linked points by scatter
    HH = np.einsum("qia,qib->qab", Jc, Jc)
    Ncc = np.zeros((p, p))
    PP = _segment_sum(HH[:, :6, :6], obs_image, m)
    for j in range(m):
        Ncc[6 * j : 6 * j + 6, 6 * j : 6 * j + 6] = PP[j]
    if k:
        PI = _segment_sum(HH[:, :6, 6 : 6 + k], obs_image, m).reshape(6 * m, k)
        Ncc[: 6 * m, 6 * m : 6 * m + k] = PI
        Ncc[6 * m : 6 * m + k, : 6 * m] = PI.T
        Ncc[6 * m : 6 * m + k, 6 * m : 6 * m + k] = HH[:, 6 : 6 + k, 6 : 6 + k].sum(axis=0)
    if np.any(is_linked):
        lmask = np.zeros((W, W), dtype=bool)
        lmask[6 + k :, :] = True
        lmask[:, 6 + k :] = True
        cl = cidx[is_linked]
        np.add.at(Ncc, (cl[:, :, None], cl[:, None, :]), HH[is_linked] * lmask)
    bc = np.bincount(cidx.ravel(), weights=np.einsum("qia,qi->qa", Jc, r).ravel(), minlength=p)
    # point side (unlinked points)
    nu = len(lay.unlinked)
    un = ~is_linked
    Npp = _segment_sum(np.einsum("qia,qib->qab", Jp, Jp), slot, max(nu, 1))[:nu]
    bp = _segment_sum(np.einsum("qia,qi->qa", Jp, r), slot, max(nu, 1))[:nu]
    E = np.einsum("qia,qib->qab", Jp[un], Jc[un, :, : 6 + k])  # (qu, 3, 6 + k)
    Npc = np.zeros((nu, 3, p))
    # one observation per (target, image): the pose blocks are assigned, not summed
    Npc[slot[un][:, None, None], np.arange(3)[None, :, None], cidx[un][:, None, :6]] = E[:, :, :6]
    if k:
        Npc[:, :, 6 * m : 6 * m + k] = _segment_sum(E[:, :, 6:], slot[un], max(nu, 1))[:nu]
    # extra observations
    extra = []
    if config.control is not None and len(config.control.index):
        ci = np.asarray(config.control.index)
        sig = _control_sigma(config.control)
        keep = (lay.uslot[ci] >= 0) | (lay.lslot[ci] >= 0)
        for i, xyz, s in zip(ci[keep], np.asarray(config.control.xyz)[keep], sig[keep]):
            res = (xyz - state.points[i]) / s
            Jx = np.diag(1.0 / s)
            extra.append(res)
            if lay.uslot[i] >= 0:
                Npp[lay.uslot[i]] += Jx.T @ Jx
                bp[lay.uslot[i]] += Jx.T @ res
            else:
                cols = lay.link_cols(np.array([i]))[0]
                Ncc[np.ix_(cols, cols)] += Jx.T @ Jx
                bc[cols] += Jx.T @ res
    for bar in config.scale_bars:
        a, b = bar.target_a, bar.target_b
        if lay.lslot[a] < 0 or lay.lslot[b] < 0:
            continue
        dvec = state.points[a] - state.points[b]
        dist = np.linalg.norm(dvec)
        u = dvec / dist
        res = (bar.length_m - dist) / bar.sigma_m
        Jx = np.concatenate([u, -u]) / bar.sigma_m
        cols = np.concatenate(lay.link_cols(np.array([a, b])))
        Ncc[np.ix_(cols, cols)] += np.outer(Jx, Jx)
        bc[cols] += Jx * res
        extra.append(np.array([res]))
    # Schur complement on the points
    Dinv = np.linalg.inv(Npp)
    V = np.einsum("nab,nbp->nap", Dinv, Npc)
    V2 = V.reshape(-1, p)
    S = Ncc - Npc.reshape(-1, p).T @ V2
    bred = bc - V2.T @ bp.reshape(-1)
    Gc, _ = _null_space(state, lay, defect)
    Sreg = S
    if defect:
        Qg, _ = np.linalg.qr(Gc)
        Sreg = S + Qg @ Qg.T * np.mean(np.diag(S))
    try:
        Sigma = np.linalg.inv(0.5 * (Sreg + Sreg.T))
    except np.linalg.LinAlgError as exc:
        raise CalibrationError(
            "bundle: the normal equations are singular: the network does not determine every camera "
            "(too few targets per image, or a datum that does not fix the network)"
        ) from exc
    dc = Sigma @ bred
    dp = np.einsum("nab,nb->na", Dinv, bp) - V @ dc
    r_extra = np.concatenate(extra) if extra else np.zeros(0)
    return _Linear(r, r_extra, Dinv, V, Sigma, dc, dp, Jp, Jc, cidx, slot, defect)


def _control_sigma(control: ControlPoints) -> np.ndarray:
    """Per-axis standard deviations of the control targets, (k, 3)."""
    k = len(control.index)
    s = np.asarray(control.sigma_m, dtype=float)
    if s.ndim == 0:
        s = np.full(k, float(s))
    if s.ndim == 1:
        s = s[:, None]
    out = np.broadcast_to(s, (k, 3)).astype(float)
    if np.any(~(out > 0)):
        raise CalibrationError("bundle: control target standard deviations must be positive")
    return out


def _apply_step(state: _State, lin: _Linear, lay: _Layout) -> _State:
    m, k = lay.m, lay.k
    poses = state.poses.copy()
    for j in range(m):
        poses[j] = exp_se3(lin.dc[6 * j : 6 * j + 6]) @ poses[j]
    intr = _update_intrinsics(state.intr, lay.names, lin.dc[6 * m : 6 * m + k]) if k else state.intr
    pts = state.points.copy()
    pts[lay.unlinked] += lin.dp
    if len(lay.linked):
        pts[lay.linked] += lin.dc[lay.link_cols(lay.linked)]
    return _State(intr, poses, pts)


def _apply_similarity(state: _State, s: float, R: np.ndarray, t: np.ndarray) -> _State:
    """Move the network by ``x' = s R x + t`` (cameras follow: their images do not change)."""
    pts = s * state.points @ R.T + t
    poses = state.poses.copy()
    Rc = poses[:, :3, :3] @ R.T
    poses[:, :3, 3] = s * poses[:, :3, 3] - np.einsum("mab,b->ma", Rc, t)
    poses[:, :3, :3] = Rc
    return _State(state.intr, poses, pts)


# --- pycolmap -------------------------------------------------------------------------


def _pycolmap_solve(state: _State, obs_image, obs_target, obs_uv, active_pts, config: BundleConfig,
                    options: BundleOptions) -> tuple[_State, bool, str]:
    m = len(state.poses)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, config.camera_model, state.intr.fx_px,
                                                 state.intr.width, state.intr.height)
    cam.params = _to_colmap_params(state.intr, config.camera_model)
    rec.add_camera_with_trivial_rig(cam)
    order = np.lexsort((obs_target, obs_image))
    img_sorted = obs_image[order]
    starts = np.searchsorted(img_sorted, np.arange(m + 1))
    p2d_idx = np.empty(len(order), dtype=int)
    for j in range(m):
        sel = order[starts[j] : starts[j + 1]]
        p2d_idx[sel] = np.arange(len(sel))
        img = pycolmap.Image(name=f"{j:05d}", keypoints=obs_uv[sel] + _PIXEL_OFFSET, camera_id=1, image_id=j + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(state.poses[j][:3, :]))
    by_target = np.argsort(obs_target, kind="stable")
    tstarts = np.searchsorted(obs_target[by_target], np.arange(len(state.points) + 1))
    pid = {}
    for i in np.flatnonzero(active_pts):
        sel = by_target[tstarts[i] : tstarts[i + 1]]
        track = pycolmap.Track()
        track.add_elements([pycolmap.TrackElement(int(a) + 1, int(b)) for a, b in zip(obs_image[sel], p2d_idx[sel])])
        pid[i] = rec.add_point3D(state.points[i], track)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.print_summary = False
    opts.refine_focal_length = config.refine_focal_length
    opts.refine_principal_point = config.refine_principal_point
    opts.refine_extra_params = config.refine_distortion
    opts.ceres.solver_options.max_num_iterations = options.max_iterations
    opts.ceres.solver_options.num_threads = options.num_threads
    opts.ceres.solver_options.function_tolerance = 1e-12
    opts.ceres.solver_options.gradient_tolerance = 1e-12
    opts.ceres.solver_options.parameter_tolerance = 1e-10
    cfg = pycolmap.BundleAdjustmentConfig()
    for j in range(m):
        cfg.add_image(j + 1)
    cfg.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    adjuster = pycolmap.create_default_bundle_adjuster(opts, cfg, rec)
    summary = adjuster.solve()
    pts = state.points.copy()
    for i, p in pid.items():
        pts[i] = rec.point3D(p).xyz
    poses = state.poses.copy()
    for j in range(m):
        poses[j, :3, :] = rec.image(j + 1).cam_from_world().matrix()
    intr = _from_colmap_params(rec.camera(1).params, config.camera_model, state.intr)
    return _State(intr, poses, pts), bool(summary.is_solution_usable()), summary.brief_report()


# --- the whole adjustment ----------------------------------------------------------------


def _validate(obs_image, obs_target, obs_uv, m, n):
    q = len(obs_image)
    if obs_target.shape != (q,) or obs_uv.shape != (q, 2):
        raise CalibrationError(
            f"bundle: obs_image {obs_image.shape}, obs_target {obs_target.shape}, obs_uv {obs_uv.shape} must be (q,), (q,), (q, 2)"
        )
    if q == 0 or obs_image.min() < 0 or obs_image.max() >= m or obs_target.min() < 0 or obs_target.max() >= n:
        raise CalibrationError(f"bundle: observation indices out of range ({m} images, {n} targets) or no observations")
    if not np.all(np.isfinite(obs_uv)):
        raise CalibrationError("bundle: observation pixels contain nan/inf")
    key = obs_image.astype(np.int64) * n + obs_target
    if len(np.unique(key)) != q:
        raise CalibrationError("bundle: a target is observed twice in one image; fix the identification")


def _datum_stage(state: _State, x0: np.ndarray, lay: _Layout, config: BundleConfig, args, sigma_px,
                 iterations: int, weighted: bool = False) -> tuple[_State, bool]:
    """Datum and the observations pycolmap cannot take; ``weighted``: also iterate to the weighted optimum."""
    datum = config.datum
    act = np.concatenate([lay.unlinked, lay.linked])
    if datum == "free":
        s, R, t = similarity_fit(state.points[act], x0[act], with_scale=True)
        state = _apply_similarity(state, s, R, t)
        if not weighted:
            return state, True
        defect = 7
    elif datum == "control":
        ci = np.asarray(config.control.index)
        ok = (lay.uslot[ci] >= 0) | (lay.lslot[ci] >= 0)
        if np.sum(ok) < 3:
            raise CalibrationError(
                f"bundle: control datum needs at least 3 observed control targets, got {int(np.sum(ok))}"
            )
        s, R, t = similarity_fit(state.points[ci[ok]], np.asarray(config.control.xyz)[ok], with_scale=True)
        state = _apply_similarity(state, s, R, t)
        defect = 0
    else:
        bars = [b for b in config.scale_bars if lay.lslot[b.target_a] >= 0 and lay.lslot[b.target_b] >= 0]
        if not bars:
            raise CalibrationError("bundle: no scale bar has both targets observed in two images or more")
        d = np.array([np.linalg.norm(state.points[b.target_a] - state.points[b.target_b]) for b in bars])
        L = np.array([b.length_m for b in bars])
        wts = (d / np.array([b.sigma_m for b in bars])) ** 2
        s = float(np.sum(wts * L / d) / np.sum(wts))
        state = _apply_similarity(state, s, np.eye(3), np.zeros(3))
        defect = 6
    converged = False
    for _ in range(iterations):
        lin = _linearise(state, *args, lay, config, sigma_px, defect)
        state = _apply_step(state, lin, lay)
        step = max(np.max(np.abs(lin.dp), initial=0.0), np.max(np.abs(lin.dc[6 * lay.m + lay.k:]), initial=0.0))
        if step < 1e-10:
            converged = True
            break
    if datum != "control":  # back onto the initial coordinates (gauge moves of the free iterations, too)
        s, R, t = similarity_fit(state.points[act], x0[act], with_scale=datum == "free")
        state = _apply_similarity(state, s, R, t)
    return state, converged


def bundle_adjust(
    obs_image: np.ndarray,
    obs_target: np.ndarray,
    obs_uv: np.ndarray,
    intrinsics: Intrinsics,
    cam_from_part: np.ndarray,
    points: np.ndarray,
    options: BundleOptions | None = None,
    config: BundleConfig | None = None,
    obs_sigma_px: np.ndarray | None = None,
    obs_group: np.ndarray | None = None,
) -> BundleResult:
    """Adjust a network of targets observed in several images.

    Args:
        obs_image: (q,) int image index of each observation (0..m-1).
        obs_target: (q,) int target index (0..n-1).
        obs_uv: (q, 2) measured pixels (origin at the centre of the top-left pixel).
        intrinsics: initial interior orientation (e.g. :func:`calibration.faugeras_toscani.combine_intrinsics`).
        cam_from_part: (m, 4, 4) initial exterior orientations (e.g. from Faugeras-Toscani).
        points: (n, 3) initial targets (e.g. the CAD nominals); the free-network datum keeps their
            centroid, orientation and scale.
        options: solver settings; config: what is refined and the datum.
        obs_sigma_px: (q,) a priori sigma of each observation's coordinates (pixels); None: all
            ``options.sigma_px``.
        obs_group: (q,) int group of each observation: estimate one variance component per group
            (:mod:`calibration.weights`), starting from ``obs_sigma_px``; None: the sigmas stay as given.
    """
    options = options or BundleOptions()
    config = config or BundleConfig()
    args = (obs_image, obs_target, obs_uv, intrinsics, cam_from_part, points, options, config, obs_sigma_px, obs_group)
    if options.blas_threads is not None and threadpool_limits is not None:
        with threadpool_limits(options.blas_threads, user_api="blas"):
            return _bundle_adjust(*args)
    return _bundle_adjust(*args)


def _bundle_adjust(obs_image, obs_target, obs_uv, intrinsics, cam_from_part, points, options, config,
                   obs_sigma_px=None, obs_group=None) -> BundleResult:
    t_start = time.perf_counter()
    obs_image = np.asarray(obs_image, dtype=int)
    obs_target = np.asarray(obs_target, dtype=int)
    obs_uv = np.asarray(obs_uv, dtype=float)
    poses0 = np.asarray(cam_from_part, dtype=float).copy()
    x0 = np.asarray(points, dtype=float).copy()
    m, n = len(poses0), len(x0)
    _validate(obs_image, obs_target, obs_uv, m, n)
    sig0 = check_sigmas(obs_sigma_px, options.sigma_px, len(obs_image))
    sig = sig0.copy()
    weighted = obs_sigma_px is not None or obs_group is not None
    group = None if obs_group is None else check_groups(obs_group, len(obs_image))
    vc = None
    names = config.refined_names()
    linked = np.zeros(n, dtype=bool)
    for bar in config.scale_bars:
        linked[[bar.target_a, bar.target_b]] = True
    defect = {"free": 7, "scale_bar": 6, "control": 0}[config.datum]
    rejected = np.zeros(len(obs_image), dtype=bool)
    state = _State(intrinsics, poses0, x0.copy())
    timings = {"pycolmap_solve": 0.0, "datum": 0.0, "covariance": 0.0}
    thr = chi2.isf(options.alpha / len(obs_image), 2)
    while True:
        act_obs = ~rejected
        counts = np.bincount(obs_target[act_obs], minlength=n)
        active_pts = counts >= 2
        act_obs &= active_pts[obs_target]
        if np.any(np.bincount(obs_image[act_obs], minlength=m) < 3):
            raise CalibrationError("bundle: an image has fewer than 3 observed targets; drop it or identify more targets")
        lay = _Layout(m, n, names, active_pts, linked)
        args = (obs_image[act_obs], obs_target[act_obs], obs_uv[act_obs])
        t0 = time.perf_counter()
        state, usable, report = _pycolmap_solve(state, *args, active_pts, config, options)
        timings["pycolmap_solve"] += time.perf_counter() - t0
        for it in range(1, max(options.vce_iterations, 1) + 1 if group is not None else 2):
            t1 = time.perf_counter()
            state, dconv = _datum_stage(state, x0, lay, config, args, sig[act_obs], options.datum_iterations, weighted)
            t2 = time.perf_counter()
            lin = _linearise(state, *args, lay, config, sig[act_obs], defect)
            stats = _statistics(lin, lay, n_obs=int(act_obs.sum()))
            t3 = time.perf_counter()
            timings["datum"] += t2 - t1
            timings["covariance"] += t3 - t2
            if group is None:
                break
            sig, vc = _variance_step(sig, sig0, group, act_obs, lin, stats, options, it, vc)
            if vc.converged:
                break
        T = np.full(len(obs_image), np.nan)
        T[act_obs] = stats["T"] / stats["s02"]
        testable = np.isfinite(T)
        if (not options.snooping or rejected.sum() >= options.max_rejections or not testable.any()
                or np.nanmax(T) <= thr):
            break  # nothing left to test (e.g. two images: no redundancy per observation) or nothing fails
        rejected[int(np.nanargmax(T))] = True
    res = _result(state, lin, stats, lay, T, rejected, act_obs, obs_image, obs_target, obs_uv, options, config,
                  usable and (dconv or (config.datum == "free" and not weighted)), report, timings,
                  time.perf_counter() - t_start)
    res.obs_sigma_px, res.variance_components = sig, vc
    if weighted:  # sigma0 in pixels: of an observation of the rms a priori sigma (equal weights: options.sigma_px)
        res.sigma0_px = float(np.sqrt(stats["s02"] * np.mean(sig[act_obs] ** 2)))
    return res


def _variance_step(sig, sig0, group, act_obs, lin, stats, options, iteration, previous):
    """One variance-component update of the a priori sigmas ``sig: (q,)`` (initial ones ``sig0``).

    Groups are estimated when their redundancy reaches ``options.vce_min_redundancy`` at the round's
    first iteration; the others take the common factor. Unchanged once settled, or at the last
    iteration (the adjustment then stays consistent with its weights).
    """
    n_groups = int(group.max()) + 1
    g = group[act_obs]
    f, r_g, common = variance_component_factors(g, lin.r_img, stats["redundancy"], n_groups,
                                                (sig / sig0)[act_obs])
    est = r_g >= options.vce_min_redundancy if iteration == 1 or previous is None else previous.estimated
    new = np.where(est[group], sig * np.sqrt(f)[group], sig0 * np.sqrt(common))
    settled = bool(np.all(np.abs(new[act_obs] / sig[act_obs] - 1.0) < options.vce_tolerance))
    if settled or iteration >= options.vce_iterations:
        new = sig
    count = np.bincount(group, minlength=n_groups)
    rms = np.sqrt(np.bincount(group, weights=new**2, minlength=n_groups) / np.maximum(count, 1))
    return new, VarianceComponents(rms, r_g, np.bincount(g, minlength=n_groups), est, iteration, settled)


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


# --- synthetic networks with known truth (tests, benchmarks, planning checks) ----------------


@dataclass(frozen=True)
class SyntheticNetwork:
    """A simulated convergent network: truth and noisy observations.

    Attributes:
        intrinsics: true interior orientation.
        cam_from_part: (m, 4, 4) true poses.
        points: (n, 3) true targets.
        obs_image, obs_target: (q,) observation indices; obs_uv: (q, 2) noisy pixels; sigma_px: the noise.
    """

    intrinsics: Intrinsics
    cam_from_part: np.ndarray
    points: np.ndarray
    obs_image: np.ndarray
    obs_target: np.ndarray
    obs_uv: np.ndarray
    sigma_px: float


def simulate_network(
    rng: np.random.Generator,
    n_targets: int = 200,
    n_images: int = 12,
    intrinsics: Intrinsics | None = None,
    sigma_px: float = 0.05,
    size_m: float = 0.3,
    distance_m: float = 0.8,
    points: np.ndarray | None = None,
) -> SyntheticNetwork:
    """Targets in a box of side ``size_m`` seen by ``n_images`` cameras on a ring looking at its centre.

    Each camera sees the targets whose projection lies in the image (no occlusion); pixel noise is
    Gaussian with ``sigma_px``. Cameras are rolled at random so the interior orientation is determinable.
    """
    from calibration.camera import invert, look_at, project

    intr = intrinsics or Intrinsics(fx_px=3000.0, fy_px=3000.0, cx_px=1223.5, cy_px=1023.5, width=2448, height=2048)
    pts = rng.uniform(-size_m / 2, size_m / 2, (n_targets, 3)) if points is None else np.asarray(points, float)
    poses = []
    for j in range(n_images):
        az = 2 * np.pi * j / n_images + rng.uniform(-0.1, 0.1)
        el = 0.5 + 0.35 * np.sin(3 * az)
        eye = distance_m * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        poses.append(invert(look_at(eye, rng.normal(0, 0.01, 3), roll_rad=rng.uniform(-np.pi, np.pi))))
    poses = np.array(poses)
    oi, ot, ouv = [], [], []
    for j in range(n_images):
        uv = project(intr, poses[j], pts)
        vis = np.flatnonzero(intr.in_image(uv, margin_px=5.0))
        oi.append(np.full(len(vis), j))
        ot.append(vis)
        ouv.append(uv[vis] + rng.normal(0.0, sigma_px, (len(vis), 2)))
    return SyntheticNetwork(intr, poses, pts, np.concatenate(oi), np.concatenate(ot), np.vstack(ouv), sigma_px)
