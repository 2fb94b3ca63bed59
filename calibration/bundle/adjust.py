"""The whole adjustment: pycolmap's solve, the datum, variance components and data snooping in a loop."""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

try:  # BLAS threads fight with Ceres' threads on small machines: small dense algebra runs faster on one
    from threadpoolctl import threadpool_limits
except ImportError:  # pragma: no cover - optional
    threadpool_limits = None

from calibration.bundle.colmap import _to_colmap_params
from calibration.bundle.config import COLMAP_MODELS, BundleConfig, BundleOptions, BundleResult
from calibration.bundle.covariance import _result
from calibration.bundle.datum import _datum_stage
from calibration.bundle.normal import _Layout, _linearise, _State
from calibration.bundle.solve import _solve
from calibration.bundle.stability import interior_stability
from calibration.bundle.snooping import (
    _statistics,
    critical_values,
    local_followers,
    pick_rejections,
    predicted_test,
    test_variance_factor,
)
from calibration.bundle.vce import _variance_step
from calibration.camera import Intrinsics
from calibration.errors import CalibrationError, ScaleNotEstablishedError
from calibration.weights import check_groups, check_sigmas, mean_variance


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
        obs_sigma_px: (q,) a priori sigma of each observation's coordinates (pixels), or (q, 2, 2) the
            covariance of each observation (px^2: the residuals are whitened with it); None: all
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
    # models whose distortion pycolmap cannot refine (COLMAP_MODELS) take the full Gauss-Newton iterations too
    full_gn = weighted or (config.camera_model in COLMAP_MODELS and config.refine_distortion)
    group = None if obs_group is None else check_groups(obs_group, len(obs_image))
    if group is not None and sig0.ndim == 3:
        raise CalibrationError("bundle: variance components (obs_group) take sigmas (q,), not covariances (q, 2, 2)")
    vc = None
    names = config.refined_names()
    _to_colmap_params(intrinsics, config.camera_model)  # the model must hold the intrinsics (whichever solver runs)
    linked = np.zeros(n, dtype=bool)
    for bar in config.scale_bars:
        linked[[bar.target_a, bar.target_b]] = True
    defect = {"free": 7, "scale_bar": 6, "control": 0}[config.datum]
    q = len(obs_image)
    rejected = np.zeros(q, dtype=bool)
    reinstated = np.zeros(q, dtype=bool)  # put back once: never rejected again by the batch rounds' mistakes
    state = _State(intrinsics, poses0, x0.copy())
    timings = {"solve": 0.0, "datum": 0.0, "covariance": 0.0, "snooping": 0.0}
    # chi2.isf(alpha / q, dof) by each statistic's degrees of freedom (1: a rank-one redundancy block, two rays)
    crit = critical_values(options.alpha / q)
    test_dof = np.zeros(q, dtype=int)  # each observation's, when last tested (a rejected one's: when rejected)
    rejected_T = np.full(q, np.nan)  # the divided statistic each rejected observation was rejected with
    solver_fallback = None
    snoop = {"rounds": 0, "threshold": float(crit[2]), "threshold_1dof": float(crit[1]), "reinstated": 0,
             "untestable_rejected": 0, "batch": bool(options.snooping_batch)}
    while True:
        snoop["rounds"] += 1
        act_obs = ~rejected
        counts = np.bincount(obs_target[act_obs], minlength=n)
        active_pts = counts >= 2
        act_obs &= active_pts[obs_target]
        _check_scale(config, active_pts, counts, rejected, obs_target, snoop["rounds"])
        if np.any(np.bincount(obs_image[act_obs], minlength=m) < 3):
            raise CalibrationError("bundle: an image has fewer than 3 observed targets; drop it or identify more targets")
        lay = _Layout(m, n, names, active_pts, linked)
        args = (obs_image[act_obs], obs_target[act_obs], obs_uv[act_obs])
        # after a batch of rejections the network is already near its optimum: Gauss-Newton on our own normal
        # equations (the datum stage's iterations, which the statistics need anyway) finishes it
        warm = options.snooping_batch and snoop["rounds"] > 1
        on_datum = False
        pre_conv = None  # the first datum stage already ran (converged or not)
        if not warm:
            t0 = time.perf_counter()
            state, usable, report, on_datum = _solve(state, x0, lay, config, args, sig[act_obs], active_pts, options)
            timings["solve"] += time.perf_counter() - t0
            if options.solver == "gauss_newton" and not on_datum:  # pycolmap took over: said by the caller
                solver_fallback = report
            pre_conv = True if on_datum else None
        else:
            t0 = time.perf_counter()
            warm_state, pre_conv = _warm_round(state, x0, lay, config, args, sig[act_obs], active_pts, options, snoop)
            timings["solve"] += time.perf_counter() - t0
            if warm_state is None:  # diverged, and pycolmap did not save it: the last round that settled is kept
                state, lin, stats, act_obs, T, dconv, lay = (good[k] for k in ("state", "lin", "stats", "act_obs",
                                                                              "T", "dconv", "lay"))
                back = rejected & ~good["rejected"]
                rejected[:] = good["rejected"]
                snoop["still_failing"] = good["still_failing"]
                snoop["stopped_because"] = (f"{snoop['diverged'][-1]}, and pycolmap did not settle that round "
                                            f"either: round {snoop['rounds'] - 1}'s adjustment is "
                                            f"kept; the {int(back.sum())} observation(s) it would have rejected next "
                                            f"are not, and {good['still_failing']} observation(s) still fail the test")
                break
            state = warm_state
        for it in range(1, max(options.vce_iterations, 1) + 1 if group is not None else 2):
            t1 = time.perf_counter()
            if it == 1 and pre_conv is not None:  # the solve ended at the optimum for these sigmas, in the datum
                dconv = pre_conv
            else:
                state, dconv = _datum_stage(state, x0, lay, config, args, sig[act_obs], options.datum_iterations,
                                            full_gn or warm)
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
        t4 = time.perf_counter()
        s_test, which = (test_variance_factor(stats["T"], stats["s02"], options.snooping_contamination,
                                              stats["T_dof"])
                         if options.snooping_batch else (stats["s02"], "adjustment"))
        snoop["variance_factor"] = which
        T = np.full(q, np.nan)
        T[act_obs] = stats["T"] / s_test
        test_dof[act_obs] = stats["T_dof"]
        thr = crit[np.where(act_obs, test_dof, 0)]  # each observation's critical value (nan: untestable, inactive)
        testable = np.isfinite(T)
        snoop["tested_1dof"] = int(np.count_nonzero(testable & (test_dof == 1)))
        fails = testable & (T > thr)
        snoop["still_failing"] = int(fails.sum())
        # this round settled: what a later round that diverges falls back to
        good = {"state": state, "lin": lin, "stats": stats, "act_obs": act_obs.copy(), "T": T.copy(), "dconv": dconv,
                "lay": lay, "rejected": rejected.copy(), "still_failing": snoop["still_failing"]}
        stop = None
        if not options.snooping:
            stop = "off"
        elif not testable.any():
            stop = "nothing testable"  # e.g. two images: no redundancy per observation
        elif not fails.any():
            back = _reinstate(options, rejected, reinstated, act_obs, state, lin, lay, stats, s_test, crit,
                              obs_image, obs_target, obs_uv, sig, snoop, test_dof)
            if not back.any():
                stop = "no observation fails"
            rejected[back], reinstated[back] = False, True
            snoop["reinstated"] += int(back.sum())
        elif rejected.sum() >= options.max_rejections:
            stop = "max_rejections reached"
        elif options.snooping_batch:
            pick = pick_rejections(np.where(reinstated, np.nan, T), thr, obs_image, obs_target,
                                   options.max_rejections - int(rejected.sum()))
            if len(pick) == 0:  # only reinstated observations fail: take the largest (the plain rule)
                pick = [int(np.nanargmax(T / thr))]
            rejected[pick] = True
            more = local_followers(np.asarray(pick), T, thr, obs_target, np.flatnonzero(act_obs), lin.r_img, lin.Jp,
                                   s_test, reinstated | rejected, options.max_rejections - int(rejected.sum()), crit)
            rejected[more] = True
            rejected_T[pick], rejected_T[more] = T[pick], T[more]
        else:
            worst = int(np.nanargmax(T / thr))
            rejected[worst], rejected_T[worst] = True, T[worst]
        timings["snooping"] += time.perf_counter() - t4
        if stop is not None:
            snoop["stopped_because"] = stop
            break
    res = _result(state, lin, stats, lay, T, rejected, act_obs, obs_image, obs_target, obs_uv, options, config,
                  usable and (dconv or (config.datum == "free" and not full_gn and not warm)), report, timings,
                  time.perf_counter() - t_start, x0)
    res.obs_sigma_px, res.variance_components, res.snooping = sig, vc, snoop
    res.test_dof, res.rejected_test = test_dof, np.where(rejected, rejected_T, np.nan)
    res.solver_fallback = solver_fallback
    res.interior_stability = _stability(state, lin, lay, obs_image[act_obs], obs_target[act_obs], sig[act_obs],
                                        stats["s02"], options)
    _say_snooping(snoop, config, options, rejected, obs_target)
    if weighted:  # sigma0 in pixels: of an observation of the rms a priori sigma (equal weights: options.sigma_px)
        res.sigma0_px = float(np.sqrt(stats["s02"] * mean_variance(sig[act_obs])))
    return res


def _stability(state, lin, lay, img, tgt, sig, s02, options) -> dict:
    """The test of one interior orientation for all images (:mod:`calibration.bundle.stability`); one that cannot run
    says why (never silently left out)."""
    if not options.interior_stability:
        return {"tested": False, "significant": False, "reason": "not asked (BundleOptions.interior_stability)"}
    t0 = time.perf_counter()
    try:
        out = interior_stability(state, lin, lay, img, tgt, sig, s02)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
        out = {"tested": False, "significant": False, "reason": f"the test failed: {exc}"}
    out["seconds"] = time.perf_counter() - t0
    return out


def _warm_round(state, x0, lay, config, args, sigma, active_pts, options, snoop) -> tuple[object, bool | None]:
    """A data-snooping round after the first, from the previous round's optimum: Gauss-Newton on our own normal
    equations, watched. A round whose cost (sigma0) rises or whose step grows is stopped and said
    (``snoop["diverged"]``) and handed to pycolmap's Levenberg-Marquardt from the round's start (then the datum
    stage); ``snoop["handed_over"]`` lists those it settled. Returns ``(state, converged)``, or ``(None, None)``
    when pycolmap did not settle it either (the caller keeps the last round that did)."""
    trace: dict = {"watch_step": True}
    try:
        new, conv = _datum_stage(state, x0, lay, config, args, sigma, options.datum_iterations, True, trace=trace)
    except (CalibrationError, np.linalg.LinAlgError) as exc:  # a step put a target behind a camera, or singular
        trace.update(diverged=True, why=f"stopped: {exc}")
    if not trace.get("diverged"):
        return new, conv
    rnd = snoop["rounds"]
    snoop.setdefault("diverged", []).append(f"round {rnd}: Gauss-Newton {trace['why']}")
    new, usable, report, _ = _solve(state, x0, lay, config, args, sigma, active_pts,
                                    replace(options, solver="pycolmap"))
    if usable:
        new, conv = _datum_stage(new, x0, lay, config, args, sigma, options.datum_iterations, True)
        if conv:
            snoop.setdefault("handed_over", []).append(f"round {rnd}: pycolmap settled it ({report})")
            return new, conv
    return None, None


def _check_scale(config, active_pts: np.ndarray, counts: np.ndarray, rejected: np.ndarray, obs_target: np.ndarray,
                 round_: int) -> None:
    """Raise :class:`ScaleNotEstablishedError` when no scale bar keeps both ends with two usable rays (before the
    first round: the input; later: data snooping took an end's rays), instead of the datum stage's generic error."""
    if not config.scale_bars or config.datum != "scale_bar":
        return
    if any(active_pts[b.target_a] and active_pts[b.target_b] for b in config.scale_bars):
        return
    ends = {int(t): int(counts[t]) for b in config.scale_bars for t in (b.target_a, b.target_b) if not active_pts[t]}
    rej = [int(q) for q in np.flatnonzero(rejected & np.isin(obs_target, list(ends)))]
    how = (f" after data snooping rejected {len(rej)} of their observation(s) (round {round_})" if rej else "")
    raise ScaleNotEstablishedError(
        "bundle: scale not established: " + ", ".join(f"scale bar end {t} keeps {k} usable ray(s)"
                                                        for t, k in ends.items()) + f" (2 needed){how}", ends, rej)


def _reinstate(options, rejected, reinstated, act_obs, state, lin, lay, stats, s_test, crit, obs_image, obs_target,
               obs_uv, sig, snoop, test_dof) -> np.ndarray:
    """Rejected observations that pass the test against the final adjustment (batch rounds only; each once), each
    at the critical value ``crit[dof]`` of its predicted statistic's degrees of freedom (``test_dof`` takes those of
    the ones put back)."""
    back = np.zeros(len(rejected), dtype=bool)
    out = rejected & ~act_obs
    if not options.snooping_batch or not out.any():
        return back
    idx = np.flatnonzero(out & ~reinstated)
    Tp, dp = predicted_test(state, lin, lay, stats, obs_image[idx], obs_target[idx], obs_uv[idx], sig[idx],
                            with_dof=True)
    Tp = Tp / s_test
    snoop["untestable_rejected"] = int(np.count_nonzero(~np.isfinite(Tp)))
    ok = np.isfinite(Tp) & (Tp <= crit[dp])
    back[idx[ok]] = True
    test_dof[idx[ok]] = dp[ok]
    return back


def _say_snooping(snoop: dict, config, options, rejected: np.ndarray, obs_target: np.ndarray) -> None:
    """Add to ``snoop`` what an operator must read: ``complete`` (False: stopped before the end), ``stopped``
    (why, with how many still fail at the cap), ``n_rejected``, ``suspect_targets`` (targets that lost half of
    their observations or more: the target itself, e.g. its control coordinates or its name, is suspect; or that
    lost any and kept two rays or fewer: a pair of rays has one redundancy, an error in it can be neither located
    nor told from the rejected ray's, so the choice snooping made between them cannot be verified) and
    ``protected`` (observations snooping never tests: scale-bar lengths, control coordinates)."""
    why = snoop.get("stopped_because", "")
    snoop["complete"] = why in ("off", "nothing testable", "no observation fails")
    snoop["stopped"] = (f"cap of {options.max_rejections} rejections reached; {snoop.get('still_failing', 0)} "
                        "observation(s) still fail the test" if why == "max_rejections reached" else why)
    snoop["n_rejected"] = int(rejected.sum())
    n_obs = np.bincount(obs_target, minlength=int(obs_target.max()) + 1 if len(obs_target) else 0)
    n_rej = np.bincount(obs_target[rejected], minlength=len(n_obs))
    unverified = (2 * n_rej >= n_obs) | (n_obs - n_rej <= 2)
    snoop["suspect_targets"] = [int(t) for t in np.flatnonzero((n_rej > 0) & unverified)]
    protected = [f"scale bar {b.target_a}-{b.target_b} length (not tested: it defines the scale)"
                 for b in config.scale_bars]
    if config.control is not None and len(config.control.index):
        protected.append(f"{len(config.control.index)} control target coordinates (not tested: they define the datum)")
    snoop["protected"] = protected
