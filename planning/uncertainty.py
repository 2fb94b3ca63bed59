"""Predicted uncertainty of the targets: limiting error propagation (seed eq. 6-7).

With the stations' orientations held fixed, a target ``P`` is triangulated from its
image points ``p_i`` by least squares. Linearising (eq. 6) and propagating the image
noise ``Lambda_p = sigma_px^2 I`` (eq. 7) gives the 3x3 covariance

    Lambda_P = (sum_i J_i^T J_i / sigma_px^2)^-1,      J_i = d(uv_i)/dP  (2 x 3)

summed over the stations that measure ``P`` (Fraser's "limiting error propagation").
For the search, the 6 unique entries of each ``J_i^T J_i / sigma^2`` are precomputed
per candidate station x target (:func:`target_information`); a network's evaluation is
then a gather-sum over its stations and a closed-form 3x3 inversion per target,
vectorised over a whole population (:func:`evaluate_networks`).

The 6 unique entries of a symmetric 3x3 matrix are stored in the order
``(xx, xy, xz, yy, yz, zz)``.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from calibration.camera import Intrinsics, invert
from calibration.errors import PlanningError
from planning import kernels
from planning.sparse_info import SparseInfo, add_rows

__all__ = [
    "ImagePrecision",
    "CRITERIA",
    "NetworkEval",
    "target_information",
    "evaluate_networks",
    "criterion",
    "ellipsoid_axes",
    "covariance_for_network",
    "sym_from_6",
    "eigvalsh_6",
]

CRITERIA = ("worst", "mean", "max_axis", "trace")
_IU = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))
# relative determinant (of the normal matrix scaled to trace 3) below which it is singular
_DET_MIN = 1e-12


def sym_from_6(s6: np.ndarray) -> np.ndarray:
    """Symmetric matrices ``(..., 3, 3)`` from their unique entries ``(..., 6)``."""
    s6 = np.asarray(s6)
    out = np.empty(s6.shape[:-1] + (3, 3), dtype=s6.dtype)
    out[..., _IU[0], _IU[1]] = s6
    out[..., _IU[1], _IU[0]] = s6
    return out


@dataclass(frozen=True)
class ImagePrecision:
    """The image precision of a dot by its geometry, for planning: the detector model
    (:mod:`calibration.detector_model`: incidence angle, dot diameter in pixels, sensor noise), held inside
    the incidences and dot sizes it was measured over (``DetectorModel.sigma_px_measured``).

    Attributes:
        normals: (n, 3) unit outward normals of the targets the information is computed for.
        diameter_m: the dots' diameter.
        model: the detector model (None: the repository's measured one).
        noise_scale: the sensor's noise relative to the one the model was measured with.
    """

    normals: np.ndarray
    diameter_m: float
    model: object | None = None
    noise_scale: float = 1.0

    def subset(self, cols: np.ndarray) -> "ImagePrecision":
        """The same precision for a subset of the targets."""
        return ImagePrecision(np.asarray(self.normals)[cols], self.diameter_m, self.model, self.noise_scale)

    def detector_model(self):
        from calibration.detector_model import load_model

        return self.model or load_model()

    def model_vector(self, intr: Intrinsics) -> np.ndarray:
        """The model as :func:`planning.kernels.information_rows_model` takes it."""
        from calibration.detector_model import D_REF_PX

        m = self.detector_model()
        inc, d0, d1 = m.measured_box()
        return np.array([m.a_px**2, (self.noise_scale * m.b_px) ** 2, m.p, m.q, D_REF_PX,
                         intr.fx_px * self.diameter_m, d0, min(d1, 1e30), np.cos(inc)], dtype=np.float64)

    def sigma_px(self, intr: Intrinsics, cam_from_part: np.ndarray, xyz: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Sigma of one image coordinate ``(k,)`` pixels of targets ``cols`` seen from one station."""
        model = self.detector_model()
        Xc = xyz[cols] @ cam_from_part[:3, :3].T + cam_from_part[:3, 3]
        centre = -cam_from_part[:3, :3].T @ cam_from_part[:3, 3]
        sight = centre - xyz[cols]
        sight /= np.linalg.norm(sight, axis=1, keepdims=True)
        nrm = np.asarray(self.normals, dtype=float)[cols]
        theta = np.arccos(np.clip(np.einsum("ka,ka->k", sight, nrm), -1.0, 1.0))
        d_px = intr.fx_px * self.diameter_m / np.maximum(Xc[:, 2], 1e-9)
        return model.sigma_px_measured(theta, d_px, self.noise_scale)


def target_information(
    intr: Intrinsics,
    part_from_cam: np.ndarray,
    xyz: np.ndarray,
    visible: np.ndarray,
    sigma_px: "float | np.ndarray | ImagePrecision",
    dtype: type = np.float32,
    sparse: bool = False,
):
    """Information ``J^T J / sigma^2`` per station x target; (m, n, 6) in ``dtype``.

    ``sparse=True`` returns the same values as a :class:`planning.sparse_info.SparseInfo` (visible
    pairs only), never materialising the dense array.

    ``part_from_cam: (m, 4, 4)``, ``xyz: (n, 3)``, ``visible: (m, n)`` bool,
    ``sigma_px``: image measurement standard deviation (scalar, (n,) per target, or an
    :class:`ImagePrecision` for the (n,) targets: per station and target from the detector model).
    ``J = d(uv)/d(point)`` (2 x 3, pixels per metre) includes the lens distortion.
    Zero where not visible. Units: 1/m^2.
    """
    if isinstance(sigma_px, ImagePrecision):
        return _information_by_model(intr, part_from_cam, xyz, visible, sigma_px, dtype, sparse)
    T = np.asarray(part_from_cam, dtype=float).reshape(-1, 4, 4)
    xyz = np.asarray(xyz, dtype=float)
    visible = np.asarray(visible, dtype=bool)
    m, n = len(T), len(xyz)
    if visible.shape != (m, n):
        raise PlanningError(f"target_information: visible has shape {visible.shape}, expected ({m}, {n})")
    sig = np.broadcast_to(np.asarray(sigma_px, dtype=float), (n,))
    if not np.all(np.isfinite(sig)) or np.any(sig <= 0):
        raise PlanningError(f"target_information: sigma_px must be positive and finite, got {sigma_px!r}")
    w = 1.0 / sig**2
    cam_from_part = np.ascontiguousarray(invert(T))
    indptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(visible.sum(axis=1), out=indptr[1:])
    indices = np.empty(int(indptr[-1]), dtype=np.int32)
    data = np.empty((int(indptr[-1]), 6), dtype=dtype)
    # every visible pair, pose by pose, compiled (planning.kernels: the values of point_information)
    xyz, visible, w, cam = np.ascontiguousarray(xyz), np.ascontiguousarray(visible), np.ascontiguousarray(w), \
        kernels.camera_vector(intr)
    kernels.in_two(m, lambda a, b: kernels.information_rows(cam_from_part[a:b], xyz, visible[a:b], w, cam,
                                                            indptr[a:b + 1], indices, data),
                   min_size=max(2, 400_000 // max(1, n)))
    sp = SparseInfo(indptr, indices, data, n)
    return sp if sparse else sp.toarray()


def point_information(intr: Intrinsics, cam_from_part: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Upper triangle (6) of ``J^T J`` of each pair of pose ``cam_from_part: (q, 4, 4)`` and point
    ``X: (q, 3)`` (part frame), ``J = d(uv)/d(X)`` with the lens distortion; (q, 6) in px^2/m^2."""
    cfp = np.ascontiguousarray(cam_from_part, dtype=np.float64).reshape(-1, 4, 4)
    X = np.ascontiguousarray(X, dtype=np.float64).reshape(-1, 3)
    out = np.empty((len(X), 6))
    kernels.pair_information(cfp, X, kernels.camera_vector(intr), out)
    return out


def _information_by_model(intr, part_from_cam, xyz, visible, precision: ImagePrecision, dtype, sparse=False):
    """The information of every visible pair, each ray weighted by the detector model's sigma for it (compiled,
    planning.kernels.information_rows_model; the same CSR layout as the one-sigma path)."""
    T = np.asarray(part_from_cam, dtype=float).reshape(-1, 4, 4)
    xyz = np.asarray(xyz, dtype=float)
    visible = np.asarray(visible, dtype=bool)
    m, n = len(T), len(xyz)
    normals = np.asarray(precision.normals, dtype=float)
    if visible.shape != (m, n) or normals.shape != (n, 3):
        raise PlanningError(f"target_information: visible {visible.shape} and normals "
                            f"{normals.shape} must match ({m}, {n}) and ({n}, 3)")
    normals = np.ascontiguousarray(normals / np.linalg.norm(normals, axis=1, keepdims=True))
    cam_from_part = np.ascontiguousarray(invert(T))
    indptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(visible.sum(axis=1), out=indptr[1:])
    indices = np.empty(int(indptr[-1]), dtype=np.int32)
    data = np.empty((int(indptr[-1]), 6), dtype=dtype)
    xyz, visible, cam = np.ascontiguousarray(xyz), np.ascontiguousarray(visible), kernels.camera_vector(intr)
    model = precision.model_vector(intr)
    kernels.in_two(m, lambda a, b: kernels.information_rows_model(cam_from_part[a:b], xyz, normals, visible[a:b],
                                                                  model, cam, indptr[a:b + 1], indices, data),
                   min_size=max(2, 400_000 // max(1, n)))
    sp = SparseInfo(indptr, indices, data, n)
    return sp if sparse else sp.toarray()


def _invert6(N: np.ndarray, n_rays: np.ndarray, min_rays: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form inverse of symmetric 3x3 ``N: (..., 6)``.

    Returns ``cov6 (..., 6)`` float64 (nan where insufficient), ``sigma (...)`` =
    sqrt(trace(cov)) (inf where insufficient), ``sufficient (...)`` bool.
    """
    N = N.astype(np.float64, copy=False)
    tr = N[..., 0] + N[..., 3] + N[..., 5]
    s = np.where(tr > 0, tr / 3.0, 1.0)
    a, b, c, d, e, f = (N[..., i] / s for i in range(6))
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    D = a * f - c * c
    E = b * c - a * e
    F = a * d - b * b
    det = a * A + b * B + c * C
    ok = (n_rays >= min_rays) & (det > _DET_MIN)
    k = np.divide(1.0, det * s, out=np.zeros_like(det), where=ok)
    cov6 = np.stack([A, B, C, D, E, F], axis=-1) * k[..., None]
    cov6[~ok] = np.nan
    sigma = np.full(ok.shape, np.inf)
    np.sqrt((A + D + F) * k, out=sigma, where=ok)
    return cov6, sigma, ok


@dataclass
class NetworkEval:
    """Predicted precision of a population of networks.

    Attributes:
        cov6: (p, n, 6) float64 unique covariance entries (m^2), nan where insufficient.
        sigma: (p, n) sqrt(trace(cov)) per target (m), inf where insufficient.
        n_rays: (p, n) int, stations that measure each target.
        sufficient: (p, n) bool, at least ``min_rays`` rays and a regular normal matrix.
        min_rays: the data-sufficiency threshold used.
    """

    cov6: np.ndarray
    sigma: np.ndarray
    n_rays: np.ndarray
    sufficient: np.ndarray
    min_rays: int

    @property
    def cov(self) -> np.ndarray:
        """(p, n, 3, 3) covariances (m^2)."""
        return sym_from_6(self.cov6)

    @property
    def n_insufficient(self) -> np.ndarray:
        """(p,) int, targets whose data are insufficient (seen by fewer than ``min_rays``)."""
        return np.count_nonzero(~self.sufficient, axis=-1)


def _dedupe(stations: np.ndarray) -> np.ndarray:
    """Stations ``(p, k)`` with repeated candidates (and negatives) replaced by -1, sorted."""
    s = np.sort(np.where(stations < 0, -1, stations), axis=1)
    dup = np.zeros_like(s, dtype=bool)
    dup[:, 1:] = s[:, 1:] == s[:, :-1]
    s[dup] = -1
    return s


def evaluate_networks(
    info: np.ndarray,
    stations: np.ndarray,
    min_rays: int = 2,
    *,
    visible: np.ndarray | None = None,
    count_duplicates: bool = False,
    workers: int | None = None,
    chunk: int = 64,
) -> NetworkEval:
    """Limiting error propagation for a whole population of networks at once.

    Args:
        info: (m, n, 6) from :func:`target_information` (float32 is accurate enough).
        stations: (p, k) int candidate indices per network; -1 = camera switched off.
        min_rays: data sufficiency, fewest stations that must measure a target.
        visible: (m, n) bool, the visibility used to build ``info``; derived from it
            (trace > 0) when not given. Pass it when calling repeatedly.
        count_duplicates: if False (default) a candidate listed twice in one network
            counts once (a repeated image adds no geometry).
        workers: threads over the population (default: up to 2).
    """
    if not isinstance(info, SparseInfo):
        info = np.asarray(info)
    if info.ndim != 3 or info.shape[2] != 6:
        raise PlanningError(f"evaluate_networks: info must be (m, n, 6), got {info.shape}")
    m, n, _ = info.shape
    st = np.asarray(stations)
    if st.ndim == 1:
        st = st[None, :]
    if st.ndim != 2 or not np.issubdtype(st.dtype, np.integer):
        raise PlanningError(f"evaluate_networks: stations must be (p, k) integer indices, got {st.shape} {st.dtype}")
    if np.any(st >= m):
        raise PlanningError(f"evaluate_networks: station index {int(st.max())} out of range (database has {m} candidates)")
    if min_rays < 2:
        raise PlanningError(f"evaluate_networks: min_rays must be >= 2 for triangulation, got {min_rays}")
    if visible is None:
        if isinstance(info, SparseInfo):
            raise PlanningError("evaluate_networks: give visible with a sparse info")
        visible = (info[..., 0] + info[..., 3] + info[..., 5]) > 0
    vis = np.asarray(visible, dtype=np.uint8)
    if vis.shape != (m, n):
        raise PlanningError(f"evaluate_networks: visible has shape {vis.shape}, expected ({m}, {n})")
    if not count_duplicates:
        st = _dedupe(st)
    p, k = st.shape
    cov6 = np.empty((p, n, 6))
    sigma = np.empty((p, n))
    n_rays = np.empty((p, n), dtype=np.int32)
    ok = np.empty((p, n), dtype=bool)

    def run(lo: int, hi: int) -> None:
        s = st[lo:hi]
        acc = np.zeros((hi - lo, n, 6), dtype=info.dtype)
        cnt = np.zeros((hi - lo, n), dtype=np.int32)
        for j in range(k):
            col = s[:, j]
            on = col >= 0
            if on.all():
                add_rows(info, acc, None, col)
                cnt += vis[col]
            elif on.any():
                rows = np.flatnonzero(on)
                add_rows(info, acc, rows, col[rows])
                cnt[rows] += vis[col[rows]]
        c6, sg, good = _invert6(acc, cnt, min_rays)
        cov6[lo:hi], sigma[lo:hi], n_rays[lo:hi], ok[lo:hi] = c6, sg, cnt, good

    bounds = [(lo, min(lo + chunk, p)) for lo in range(0, p, chunk)]
    workers = workers or min(2, os.cpu_count() or 1)
    if workers > 1 and len(bounds) > 1:
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(lambda b: run(*b), bounds))
    else:
        for b in bounds:
            run(*b)
    return NetworkEval(cov6=cov6, sigma=sigma, n_rays=n_rays, sufficient=ok, min_rays=min_rays)


def eigvalsh_6(s6: np.ndarray) -> np.ndarray:
    """Eigenvalues, descending, of symmetric 3x3 ``s6: (..., 6)``; (..., 3). Closed form (trigonometric)."""
    a, b, c, d, e, f = (np.asarray(s6, dtype=np.float64)[..., i] for i in range(6))
    q = (a + d + f) / 3.0
    p1 = b * b + c * c + e * e
    p2 = (a - q) ** 2 + (d - q) ** 2 + (f - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    ps = np.where(p > 0, p, 1.0)
    a1, d1, f1 = (a - q) / ps, (d - q) / ps, (f - q) / ps
    b1, c1, e1 = b / ps, c / ps, e / ps
    detB = a1 * (d1 * f1 - e1 * e1) - b1 * (b1 * f1 - e1 * c1) + c1 * (b1 * e1 - d1 * c1)
    phi = np.arccos(np.clip(detB / 2.0, -1.0, 1.0)) / 3.0
    l1 = q + 2.0 * p * np.cos(phi)
    l3 = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    l2 = 3.0 * q - l1 - l3
    return np.stack([l1, l2, l3], axis=-1)


def criterion(ev: NetworkEval, kind: str = "worst", penalty: float | None = None) -> np.ndarray:
    """One figure per network to minimise; (p,) float.

    ``kind``:
      * ``"worst"``: largest target sigma, sqrt(trace(cov)) (m);
      * ``"mean"``: mean target sigma (m);
      * ``"max_axis"``: largest 1-sigma error-ellipsoid semi-axis over the targets (m);
      * ``"trace"``: mean trace of the covariances (m^2).

    Data insufficiency: with ``penalty=None`` a network with any insufficient target
    scores ``inf``; otherwise it scores the figure over its sufficient targets plus
    ``penalty`` per insufficient target (so the search can rank infeasible networks).
    """
    if kind not in CRITERIA:
        raise PlanningError(f"unknown criterion {kind!r}: choose one of {', '.join(CRITERIA)}")
    ok = ev.sufficient
    if kind in ("worst", "mean"):
        per_target = ev.sigma
    elif kind == "trace":
        per_target = ev.cov6[..., 0] + ev.cov6[..., 3] + ev.cov6[..., 5]
    else:
        per_target = np.sqrt(np.maximum(eigvalsh_6(ev.cov6)[..., 0], 0.0))
    per_target = np.where(ok, per_target, np.nan)
    n_ok = np.count_nonzero(ok, axis=-1)
    any_ok = n_ok > 0
    if kind == "worst" or kind == "max_axis":
        value = np.max(np.where(ok, per_target, -np.inf), axis=-1)
    else:
        value = np.sum(np.where(ok, per_target, 0.0), axis=-1) / np.maximum(n_ok, 1)
    value = np.where(any_ok, value, np.inf)
    bad = ev.n_insufficient
    if penalty is None:
        return np.where(bad > 0, np.inf, value)
    return np.where(any_ok, value, 0.0) + penalty * bad


def ellipsoid_axes(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Error-ellipsoid semi-axes (1 sigma) and directions of ``cov: (n, 3, 3)``.

    Returns ``axes: (n, 3)`` descending (m) and ``directions: (n, 3, 3)`` whose column
    ``j`` is the unit axis of ``axes[:, j]``. Rows with non-finite covariance give nan.
    """
    cov = np.asarray(cov, dtype=float)
    single = cov.ndim == 2
    cov = cov.reshape(-1, 3, 3)
    finite = np.all(np.isfinite(cov), axis=(1, 2))
    axes = np.full((len(cov), 3), np.nan)
    dirs = np.full((len(cov), 3, 3), np.nan)
    if finite.any():
        w, v = np.linalg.eigh(cov[finite])
        axes[finite] = np.sqrt(np.maximum(w[:, ::-1], 0.0))
        dirs[finite] = v[:, :, ::-1]
    if single:
        return axes[0], dirs[0]
    return axes, dirs


def covariance_for_network(
    intr: Intrinsics,
    part_from_cam: np.ndarray,
    xyz: np.ndarray,
    visible: np.ndarray,
    sigma_px: float | np.ndarray,
    min_rays: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact (float64, LAPACK inverse) limiting-error-propagation covariance of one network.

    ``part_from_cam: (k, 4, 4)`` its stations, ``xyz: (n, 3)``, ``visible: (k, n)``.
    Returns ``cov: (n, 3, 3)`` (m^2; nan where fewer than ``min_rays`` stations see the
    target or the rays do not intersect) and ``n_rays: (n,)`` int.
    """
    visible = np.asarray(visible, dtype=bool)
    info = target_information(intr, part_from_cam, xyz, visible, sigma_px, dtype=np.float64)
    N = sym_from_6(info.sum(axis=0))
    n_rays = visible.sum(axis=0).astype(int)
    cov = np.full(N.shape, np.nan)
    tr = np.trace(N, axis1=1, axis2=2)
    scaled = N / np.where(tr > 0, tr / 3.0, 1.0)[:, None, None]
    ok = (n_rays >= min_rays) & (np.linalg.det(scaled) > _DET_MIN)
    if ok.any():
        cov[ok] = np.linalg.inv(N[ok])
    return cov, n_rays
