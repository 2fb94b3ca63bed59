"""Rigorous bundle adjustment of the targets: pycolmap's solver, a datum, covariance, data snooping.

Stages (``bundle_adjust``):

0. Gauss-Newton on our own normal equations (stage 2's iterations, from the start, the datum and weights
   included) solves first; when it does not converge (cost rising, no convergence within
   ``BundleOptions.gn_iterations``) stage 1 solves from the same start (:mod:`calibration.bundle.solve`,
   docs/decisions/0024-bundlefast-gauss-newton-first-solve.md). ``BundleOptions(solver="pycolmap")``: stage 1 always.
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
4. Residual statistics (sigma0, redundancy numbers) and data snooping: each observation's test
   statistic ``v^T Q_vv^+ v / s0^2`` (chi-square, 2 dof; 1 dof where the observation's redundancy block
   is of rank one, e.g. a target seen by two rays) against the critical value of its dof at ``alpha / q``.
   Many observations are rejected per re-adjustment (the largest failing statistic of each target, at
   most a tenth of an image's observations; a robust variance factor while blunders inflate ``s0^2``),
   until none fails; then every rejected observation is tested against the final adjustment and put
   back (once) if it passes (:mod:`calibration.bundle.snooping`, docs/decisions/0019-scale.md).
   ``BundleOptions(snooping_batch=False)``: one observation per re-adjustment, as before.
   ``result.snooping`` says how it stopped (and how many still failed when the cap stopped it).

Observations of unequal precision (:mod:`calibration.weights`): ``obs_sigma_px`` gives each
image observation its own a priori sigma, ``obs_group`` estimates one variance component per
group (Förstner), re-adjusting until they settle, before each data-snooping test. pycolmap's
solver weights all observations alike, so weighted networks are then iterated to the weighted
optimum by Gauss-Newton on the full normal equations (every datum). Everything downstream
(sigma0, covariance, redundancy numbers, test statistics) works on the whitened observations.

Modules (docs/decisions/0012-split-bundle-planner.md): ``config`` (options, config, result),
``adjust`` (the loop above), ``solve`` (stage 0 and the hand-over), ``colmap`` (stage 1), ``normal`` (linearised problem), ``datum``
(stage 2), ``covariance`` (stage 3, the result), ``snooping`` (stage 4's statistics), ``vce``
(variance components), ``projection``, ``synthetic`` (simulated networks).
"""
from __future__ import annotations

from calibration.bundle.adjust import bundle_adjust
from calibration.bundle.colmap import _PIXEL_OFFSET, _to_colmap_params  # noqa: F401 (tests use them)
from calibration.bundle.config import (
    CAMERA_MODELS,
    BundleConfig,
    BundleOptions,
    BundleResult,
    ControlPoints,
    ScaleBar,
)
from calibration.bundle.projection import project_observations
from calibration.bundle.synthetic import SyntheticNetwork, simulate_network

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
