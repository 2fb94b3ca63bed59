"""The first adjustment of each data-snooping round: Gauss-Newton on our own normal equations, pycolmap's
Levenberg-Marquardt (Ceres) where it does not converge.

The statistics need the normal equations at the optimum anyway (:mod:`calibration.bundle.normal`), and from a
start as good as Faugeras-Toscani's Gauss-Newton converges in three to five of their iterations (quadratically:
the last step is ~1e-14 m), each cheaper than one of Ceres' (no problem construction, no preprocessing). The
iterations are watched: a rising cost, a target behind a camera, singular normal equations or no convergence
within ``BundleOptions.gn_iterations`` hand the same start to pycolmap, so a poor start is no worse off than
before. Both reach the same least-squares optimum (coordinates agree to ~1e-12 m;
``tests/test_bundle_fast.py``). ``BundleOptions(solver="pycolmap")`` always takes pycolmap.
"""
from __future__ import annotations

import numpy as np

from calibration.bundle.colmap import _pycolmap_solve
from calibration.bundle.config import BundleConfig, BundleOptions
from calibration.bundle.datum import _datum_stage
from calibration.bundle.normal import _Layout, _State
from calibration.errors import CalibrationError


def _solve(state: _State, x0: np.ndarray, lay: _Layout, config: BundleConfig, args, sigma_px: np.ndarray,
           active_pts: np.ndarray, options: BundleOptions) -> tuple[_State, bool, str, bool]:
    """Adjust the network from ``state``: ``(state, usable, summary, on_datum)``.

    ``on_datum``: the state is the weighted optimum in the datum already (the Gauss-Newton path; the datum stage
    has nothing left to do for these sigmas); False after pycolmap (its gauge fixes two cameras).
    """
    if options.solver not in ("gauss_newton", "pycolmap"):
        raise CalibrationError(f"bundle: unknown solver {options.solver!r}; use 'gauss_newton' or 'pycolmap'")
    why = "solver=pycolmap"
    if options.solver == "gauss_newton":
        trace: dict = {}
        try:
            new, converged = _datum_stage(state, x0, lay, config, args, sigma_px, options.gn_iterations,
                                          weighted=True, trace=trace)
        except (CalibrationError, np.linalg.LinAlgError) as exc:  # behind a camera, singular: Levenberg-Marquardt
            converged, why = False, f"Gauss-Newton stopped: {exc}"
        else:
            if converged:
                return new, True, (f"Gauss-Newton: {trace['iterations']} iterations, initial cost "
                                   f"{trace['initial_cost']:.6e}, final cost {trace['final_cost']:.6e}, "
                                   "Termination: CONVERGENCE"), True
            why = ("Gauss-Newton: the cost rose" if trace.get("diverged") else
                   f"Gauss-Newton: not converged in {options.gn_iterations} iterations")
    new, usable, report = _pycolmap_solve(state, *args, active_pts, config, options)
    return new, usable, f"{report} ({why})" if options.solver != "pycolmap" else report, False
