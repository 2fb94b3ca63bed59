"""The datum (free network, scale bars, control targets) by Gauss-Newton on the full normal equations.

Scale bars and control targets are observations pycolmap's Python API cannot take, so they are
applied here, started from pycolmap's optimum (see :mod:`calibration.bundle`).
"""
from __future__ import annotations

import numpy as np

from calibration.alignment import similarity_fit
from calibration.bundle.config import BundleConfig
from calibration.bundle.normal import _control_sigma, _Layout, _State, _apply_step, _linearise
from calibration.errors import CalibrationError


def _apply_similarity(state: _State, s: float, R: np.ndarray, t: np.ndarray) -> _State:
    """Move the network by ``x' = s R x + t`` (cameras follow: their images do not change)."""
    pts = s * state.points @ R.T + t
    poses = state.poses.copy()
    Rc = poses[:, :3, :3] @ R.T
    poses[:, :3, 3] = s * poses[:, :3, 3] - np.einsum("mab,b->ma", Rc, t)
    poses[:, :3, :3] = Rc
    return _State(state.intr, poses, pts)


def _datum_stage(state: _State, x0: np.ndarray, lay: _Layout, config: BundleConfig, args, sigma_px,
                 iterations: int, weighted: bool = False, trace: dict | None = None) -> tuple[_State, bool]:
    """Datum and the observations pycolmap cannot take; ``weighted``: also iterate to the weighted optimum.

    ``trace``: the iterations solve the network from a start that may be far (:mod:`calibration.bundle.solve`):
    they stop unconverged as soon as the cost rises, converge only when the poses' step is negligible too, and
    record ``iterations``, ``initial_cost``, ``final_cost`` and ``diverged`` (with ``why``) in the dict; with
    ``trace["watch_step"]`` a growing step is a divergence too (a start near the optimum: a warm data-snooping round).
    """
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
        fixed = ok & np.all(_control_sigma(config.control) == 0, axis=1)
        if np.any(fixed):  # truly fixed control sits at its coordinates; the iterations below do not move it
            pts = state.points.copy()
            pts[ci[fixed]] = np.asarray(config.control.xyz, dtype=float)[fixed]
            state = _State(state.intr, state.poses, pts)
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
    prev = np.inf
    for it in range(iterations):
        lin = _linearise(state, *args, lay, config, sigma_px, defect)
        if trace is not None:
            cost = float(np.sum(lin.r_img**2) + np.sum(lin.r_extra**2))
            trace.setdefault("initial_cost", cost)
            trace["iterations"] = it + 1
            if not np.isfinite(cost) or cost > trace.get("final_cost", np.inf) * (1.0 + 1e-6) + 1e-12:
                trace["diverged"] = True
                trace["why"] = (f"cost rose at iteration {it + 1} ({trace.get('final_cost', np.nan):.6e} -> "
                                f"{cost:.6e})")
                return state, False
            trace["final_cost"] = cost
        state = _apply_step(state, lin, lay)
        step = max(np.max(np.abs(lin.dp), initial=0.0), np.max(np.abs(lin.dc[6 * lay.m + lay.k:]), initial=0.0))
        if trace is not None and not trace.get("watch_step"):  # rad and m (a warm round keeps the points' rule)
            step = max(step, np.max(np.abs(lin.dc[: 6 * lay.m]), initial=0.0))
        # converged: a step below 1e-10, or one below 1e-8 that shrank a thousandfold (Gauss-Newton's quadratic
        # convergence: the next would be ~1e-14, not worth a linearisation to find out)
        if step < 1e-10 or (step < 1e-8 and step < 1e-3 * prev):
            converged = True
            break
        if trace is not None and trace.get("watch_step") and step > prev and step > 1e-8:
            # from an optimum's neighbourhood (a warm data-snooping round) Gauss-Newton's steps shrink: one that
            # grows is leaving it
            trace["diverged"] = True
            trace["why"] = f"step grew at iteration {it + 1} ({prev:.3e} -> {step:.3e})"
            return state, False
        prev = step
    if datum != "control":  # back onto the initial coordinates (gauge moves of the free iterations, too)
        s, R, t = similarity_fit(state.points[act], x0[act], with_scale=datum == "free")
        state = _apply_similarity(state, s, R, t)
    return state, converged
