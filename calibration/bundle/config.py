"""What a bundle adjustment solves, how, and what it returns: options, config (datum), result."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration.alignment import PointCovariance
from calibration.camera import Intrinsics
from calibration.errors import CalibrationError
from calibration.weights import VarianceComponents

#: our name -> (COLMAP model, parameter names in COLMAP order)
CAMERA_MODELS: dict[str, tuple[str, ...]] = {
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    # OpenCV's five-term model (k3 too): COLMAP's FULL_OPENCV with its rational terms k4..k6 held at 0;
    # pycolmap keeps the distortion fixed and the Gauss-Newton iterations on the full normal equations
    # refine k1, k2, p1, p2, k3 (calibration.bundle.adjust)
    "OPENCV_K3": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"),
}
#: our model -> COLMAP's model (and how many trailing zero parameters COLMAP's has beyond ours)
COLMAP_MODELS: dict[str, tuple[str, int]] = {"OPENCV_K3": ("FULL_OPENCV", 3)}
_GROUPS = {"focal": ("f", "fx", "fy"), "principal": ("cx", "cy"), "distortion": ("k1", "k2", "p1", "p2", "k3")}


@dataclass(frozen=True)
class ScaleBar:
    """A calibrated distance between two targets (indices into the points)."""

    target_a: int
    target_b: int
    length_m: float
    sigma_m: float


@dataclass(frozen=True)
class ControlPoints:
    """Targets with known coordinates: ``index: (k,)`` into the points, ``xyz: (k, 3)``, ``sigma_m: (k,) or (k, 3)``.

    A target whose sigma is 0 (on all three axes) is truly fixed: its coordinates are not unknowns of the
    adjustment, it keeps ``xyz`` exactly and its covariance is zero. Positive sigmas weight the control.
    """

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
        max_rejections: at most this many observations removed (``result.snooping`` says when it stopped
            the tests with observations still failing).
        snooping_batch: reject many observations per re-adjustment (the largest failing statistic of each
            target, at most a tenth of an image's observations per round), then test every rejected
            observation against the final adjustment and put back those that pass
            (:mod:`calibration.bundle.snooping`); False: one observation per re-adjustment (the old loop).
        snooping_contamination: the tests divide by a robust variance factor (median of the statistics)
            while the adjustment's ``s0^2`` exceeds it by more than this factor (blunders mask each other
            through ``s0^2``); 0: always the adjustment's ``s0^2``.
        datum_iterations: Gauss-Newton iterations for scale bars and control targets.
        solver: the first adjustment of each data-snooping round: "gauss_newton" (our own normal equations, with
            pycolmap's Levenberg-Marquardt when they do not converge; :mod:`calibration.bundle.solve`) or
            "pycolmap" (always Ceres).
        gn_iterations: at most this many Gauss-Newton iterations before pycolmap takes over.
        blas_threads: BLAS threads for the covariance algebra (None: leave as is). One is the fastest
            for networks of up to a few thousand targets on a 2-core machine (needs threadpoolctl).
        vce_iterations: at most this many re-adjustments of the variance component estimation
            (``obs_group``) per data-snooping round.
        vce_min_redundancy: a group with less redundancy (sum over its coordinates) takes the pooled
            variance factor of all groups instead of its own.
        vce_tolerance: the estimation stops when every group's sigma changes by less than this (relative).
        interior_stability: test the final adjustment for a change of the interior orientation during the
            acquisition (:mod:`calibration.bundle.stability`; ``result.interior_stability``).
    """

    sigma_px: float = 0.05
    a_posteriori: bool = True
    max_iterations: int = 100
    num_threads: int = 2
    snooping: bool = True
    alpha: float = 0.01
    max_rejections: int = 20
    snooping_batch: bool = True
    snooping_contamination: float = 2.0
    datum_iterations: int = 10
    solver: str = "gauss_newton"
    gn_iterations: int = 12
    blas_threads: int | None = 1
    vce_iterations: int = 15
    vce_min_redundancy: float = 50.0
    vce_tolerance: float = 0.005
    interior_stability: bool = True


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
        test_statistic: (q,) data-snooping statistic (divided by the variance factor; chi-square with ``test_dof``
            degrees of freedom for a good observation; nan for rejected).
        test_dof: (q,) its degrees of freedom: 2, 1 where the observation's redundancy block is of rank one (a target
            seen by two rays; :data:`calibration.bundle.snooping.RANK_RTOL`), 0 untestable; a rejected observation's:
            those it was rejected with. Each is tested at its own dof's quantile (``snooping`` ``threshold`` and
            ``threshold_1dof``).
        rejected_test: (q,) the statistic each rejected observation was rejected with (nan for the others).
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
        snooping: how data snooping went: ``rounds`` (re-adjustments), ``threshold`` (critical value of the
            divided statistic with 2 dof; ``threshold_1dof``: with 1 dof, at the same ``alpha / q``; ``tested_1dof``:
            how many of the last round's statistics had 1 dof), ``stopped_because`` ("no observation fails" | "max_rejections reached" |
            "off" | "nothing testable"), ``still_failing`` (active observations above the threshold when
            it stopped), ``reinstated`` (observations put back), ``untestable_rejected`` (rejected
            observations whose target left the network, so they could not be re-tested),
            ``variance_factor`` ("adjustment" | "robust": what the last round's tests divided by).
        solver_fallback: None when the chosen solver ran to the end; else why Gauss-Newton handed the first
            solve over to pycolmap's Levenberg-Marquardt (the result is pycolmap's, then checked as any other).
        datum_left_out: indices of the targets the datum's minimum trace (free network, scale bars) leaves out
            because they are determined far worse than the others (:data:`calibration.bundle.covariance.WEAK_DATUM`).
            ``points`` are then in the same datum as the covariance: the similarity onto the approximate coordinates
            is fitted over the other targets only.
        interior_stability: the test of one interior orientation for all images against a change of the principal
            distance and point after some image (capture order; :func:`calibration.bundle.stability.interior_stability`):
            ``tested``, ``statistic``, ``critical``, ``first_changed``, ``change_px``, ``significant`` ...
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
    snooping: dict = field(default_factory=dict)
    solver_fallback: str | None = None
    datum_left_out: np.ndarray | None = None  # targets the datum's minimum trace leaves out (weakly determined)
    variance_factor: float = 1.0  # what ``cov`` and ``covariance`` were scaled by (a posteriori s0^2, or 1)
    test_dof: np.ndarray | None = None  # (q,) each statistic's degrees of freedom (1: rank-one block; 0: untestable)
    rejected_test: np.ndarray | None = None  # (q,) the statistic a rejected observation was rejected with
    interior_stability: dict | None = None  # the lens's stability over the acquisition (calibration.bundle.stability)

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
