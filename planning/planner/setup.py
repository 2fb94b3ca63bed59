"""Set-up of a plan: the visibility database, the valid candidates, the targets planned for, their
information, the requirement ("cheapest") and the search problem built on them."""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from calibration.camera import Intrinsics
from calibration.errors import InputError, PlanningError
from planning.planner.options import PlannerOptions, Progress
from planning.planner.problem import _Problem
from planning.stations import ViewingSphere
from planning.uncertainty import target_information
from planning.visibility import VisibilityDB, VisibilityOptions


def build_database(part, intr: Intrinsics, options: PlannerOptions, cache_dir=None,
                   progress: Progress | None = None) -> VisibilityDB:
    """The visibility database :func:`plan_network` searches (cached under ``cache_dir``).

    Build it first when the robot's reachability is wanted: compute
    ``reachable = reachability_mask(..., db.part_from_cam, ...).reachable`` and pass both
    ``db`` and ``reachable`` to :func:`plan_network`.
    """
    return VisibilityDB.load_or_build(
        part, intr, options.search_sphere(part, intr), options.visibility_options(), options.n_candidates,
        cache_dir, progress, n_shells=options.n_shells, backend=options.backend,
    )


def required_sigma(part, options: PlannerOptions) -> np.ndarray:
    """Required sigma per target (m), (n,): ``required_sigma_m`` or tolerance / ratio."""
    n = len(part.targets.xyz)
    if options.required_sigma_m is not None:
        req = np.broadcast_to(np.asarray(options.required_sigma_m, dtype=float), (n,)).copy()
    else:
        tol = np.asarray(part.targets.tolerance_m, dtype=float).copy()
        if options.default_tolerance_m is not None:
            tol[np.isnan(tol)] = options.default_tolerance_m
        if np.any(np.isnan(tol)):
            raise InputError(
                "planning mode 'cheapest' needs a required precision: set [planning] required_sigma, or give every "
                "target a tolerance (targets file, or [report] tolerance for the others)"
            )
        req = tol / options.tolerance_ratio
    if np.any(~(req > 0)):
        raise InputError("required precision must be positive for every target")
    return req


@dataclass
class _SetUp:
    """What the search of one plan works on.

    Attributes:
        db: the visibility database; sphere: its viewing sphere with roll and look-at offset held at zero.
        vis_opts: the measurability limits of the plan.
        valid: (m,) candidates that see a target and are reachable.
        measurable: (n,) targets that ``min_rays`` valid candidates can measure; cols: their indices.
        ids: (n,) target ids; xyz: (n, 3) targets.
        vis: (m, len(cols)) visibility of the targets planned for; info: their information per candidate.
        required: (n,) required sigma ("cheapest"), else None.
        problem: the search's fitness on the database.
    """

    db: VisibilityDB
    sphere: ViewingSphere
    vis_opts: VisibilityOptions
    valid: np.ndarray
    measurable: np.ndarray
    cols: np.ndarray
    ids: list[str]
    xyz: np.ndarray
    vis: np.ndarray
    info: np.ndarray
    required: np.ndarray | None
    problem: _Problem


def _set_up(part, intr: Intrinsics, options: PlannerOptions, reachable: np.ndarray | None, cache_dir,
            report: Progress, db: VisibilityDB | None, timing: dict) -> _SetUp:
    """Build (or check) the database and everything the search needs; adds to ``timing``."""
    t0 = time.perf_counter()
    vis_opts = options.visibility_options()
    if db is None:
        db = build_database(part, intr, options, cache_dir, report)
    elif db.options != vis_opts or db.visible.shape[1] != len(part.targets.xyz):
        raise InputError(
            "the visibility database given was built for other visibility options or targets; "
            "build it with planning.planner.build_database(part, intr, options)"
        )
    # search azimuth, elevation and distance only (see planning.planner's docstring)
    sphere = replace(db.sphere, max_roll_rad=0.0, max_offset_m=0.0)
    timing["visibility_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    m, n = db.visible.shape
    valid = db.visible.any(axis=1)
    if reachable is not None:
        reachable = np.asarray(reachable, dtype=bool)
        if reachable.shape != (m,):
            raise PlanningError(f"reachable has shape {reachable.shape}; it must be aligned with the {m} candidates")
        valid &= reachable
    if not valid.any():
        raise PlanningError(
            "no candidate station both sees a target and is reachable: check the viewing sphere, "
            "the part's placement and the robot's reach"
        )
    seen = db.visible[valid].sum(axis=0)
    measurable = seen >= options.min_rays
    ids = list(part.targets.ids)
    if not measurable.all():
        bad = [ids[j] for j in np.flatnonzero(~measurable)]
        if not options.allow_unmeasurable:
            raise PlanningError(
                f"{len(bad)} target(s) cannot be measured by {options.min_rays} valid stations "
                f"(e.g. {', '.join(bad[:5])}): lower [planning] min_rays, raise [planning] incidence_max_deg, widen "
                "the viewing sphere ([planning] elevation_min_deg, elevation_max_deg, distance_min, distance_max), "
                "or remove those targets from the targets file ([planning] unmeasurable = \"report\" plans for the "
                "others and reports them not measured)"
            )
    cols = np.flatnonzero(measurable)
    if cols.size == 0:
        raise PlanningError("no target can be measured by min_rays valid stations")
    xyz = np.asarray(part.targets.xyz, dtype=float)
    vis = db.visible[:, cols]
    # only the visible pairs (CSR, the layout of planning.kernels; the same values as the dense array)
    info = target_information(intr, db.part_from_cam, xyz[cols], vis, options.image_sigma(cols), sparse=True)
    report("information", 1.0)
    required = required_sigma(part, options) if options.mode == "cheapest" else None
    problem = _Problem(db, info, vis, valid, options, None if required is None else required[cols])
    timing["information_s"] = time.perf_counter() - t0
    return _SetUp(db, sphere, vis_opts, valid, measurable, cols, ids, xyz, vis, info, required, problem)
