"""Variance component estimation inside the adjustment (kernels: :mod:`calibration.weights`)."""
from __future__ import annotations

import numpy as np

from calibration.weights import VarianceComponents, variance_component_factors


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
