"""Network design: the EPOCA evolutionary search over stations on the viewing sphere.

``plan_network(part, intr, options, rng)`` answers one of two questions:

* ``mode="fixed"``: the best network of ``n_stations`` stations (every control bit on);
* ``mode="cheapest"``: the network with the fewest stations (at most ``n_stations``)
  whose every target reaches its required precision (``required_sigma_m``, or the
  target's tolerance / ``tolerance_ratio``), read off a Pareto front of station count
  versus precision found by non-dominated sorting (:func:`cheapest_network`).

The pipeline (seed Fig. 3): candidate stations on the viewing sphere -> visibility
database (ray casting, field of view, incidence angle, depth of field; cached) ->
per candidate x target information ``J^T J / sigma^2`` -> evolutionary search whose
fitness is the limiting-error-propagation criterion evaluated on the database (its first
generation: greedy covers, random networks and the best convergent rings,
:mod:`planning.seeding`) -> for worst-case objectives, exchange descent from the search's
best networks (:mod:`planning.refine`: the max objective is flat for the GA, the
descent moves exactly the stations that help the hardest targets) ->
the final stations re-evaluated *exactly* (fresh ray casting at their continuous poses,
float64 covariance).

Constraint handling as in the seed: a station that snaps to a candidate which sees no
target, or which the robot cannot reach (``reachable``), is corrected to the nearest
valid candidate (Lamarckian: its genes are rewritten); the incidence angle is enforced
per target by the visibility test; a network in which some target is measured by fewer
than ``min_rays`` stations is infeasible and ranks below every feasible one by its
shortfall of rays (the seed's predetermined penalty, graded).

Genes searched: azimuth, elevation, distance (:mod:`planning.stations`).  Roll and the
look-at offsets are held at zero during the search, because the database holds its
candidates at zero roll and offset and so the fitness cannot see them.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from calibration.camera import Intrinsics
from calibration.errors import InputError, PlanningError
from planning.bound import worst_sigma_lower_bound
from planning.evolution import Evaluation, EvolutionOptions, EvolutionResult, evolve
from planning.polish import polish
from planning.refine import refine_network
from planning.seeding import greedy_cover, initial_population, ring_sweep
from planning.stations import N_GENES, ViewingSphere
from planning.uncertainty import (
    CRITERIA,
    NetworkEval,
    covariance_for_network,
    criterion,
    evaluate_networks,
    target_information,
)
from planning.visibility import VisibilityDB, VisibilityOptions, compute_visibility

__all__ = [
    "PlannerOptions",
    "NetworkPlan",
    "build_database",
    "plan_network",
    "cheapest_network",
    "required_sigma",
    "greedy_cover",
]

Progress = Callable[[str, float], None]
_IU = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))
MODES = ("fixed", "cheapest")


@dataclass
class PlannerOptions:
    """What to plan and how to search.

    Attributes:
        n_stations: stations of the network ("fixed"), or the most allowed ("cheapest").
        min_rays: fewest stations that must measure every target (data sufficiency).
        incidence_max_rad: largest angle between a target's normal and its line of sight.
        criterion: "worst" | "mean" | "max_axis" | "trace" (see planning.uncertainty).
        sigma_px: image measurement standard deviation (pixels).
        mode: "fixed" | "cheapest".
        required_sigma_m: "cheapest": required sigma per target (scalar or (n,)); None ->
            each target's tolerance / ``tolerance_ratio``.
        tolerance_ratio: sigma <= tolerance / this (the "1/10 rule").
        default_tolerance_m: tolerance for targets whose own is nan.
        population, generations, stall_generations, time_limit_s: the search's size and
            stopping criteria.
        eta_c, eta_m, p_crossover, p_mutation, p_bit_flip, tournament_size, n_elite,
            p_reset, plus_selection: operators (see planning.evolution.EvolutionOptions);
            p_reset None: 0.5 / n_stations (about one station in two children jumps
            anywhere). The defaults ((mu + lambda) survival, eta_m = 5, 5 % of the genes
            mutated) were chosen on the example part: at equal generations they reach a
            smaller worst-target sigma than generational replacement with eta_m = 20.
        visibility: measurability limits (its incidence angle is replaced by
            ``incidence_max_rad``); None: defaults.
        sphere: where stations may lie; None: ViewingSphere.for_part.
        n_candidates, n_shells: size of the visibility database.
        backend: ray casting, "embree" | "numpy".
        allow_unmeasurable: if False, a target that fewer than ``min_rays`` valid
            candidates can measure is an error; if True it is left out and listed.
        greedy_fraction: share of the initial population built by :func:`greedy_cover`
            (randomised set multicover); the rest is random.
        cheapest_refine: "cheapest": after the Pareto front, at most this many fixed-size
            searches (minimising max sigma / required, seeded with the front) try one
            station fewer each, stopping at the first that fails.
        refine_starts: after each fixed-size search with a worst-case objective ("worst"
            criterion, or max sigma / required), exchange descent (planning.refine) from
            this many of its best distinct networks (0: off).
        refine_kicks: then this many perturb-and-descend restarts of the best.
        ring_seeds: fixed-size searches: this many of the best single- and two-ring
            convergent networks (planning.seeding.ring_sweep, scored on the database) join
            the initial population, so the plan is never worse than them on the database.
        polish_rounds: "fixed" with the "worst" criterion and no reachability mask: rounds
            of exact local polish (planning.polish: stations nudged off the database's
            lattice, ray-cast afresh, exchange descent); 0: off.
        lower_bound: also compute (planning.bound) how good any network could be on the
            database: "fixed" with the "worst" criterion: a lower bound on the worst target's
            sigma for ``n_stations`` (``search["lower_bound_sigma_m"]``); "cheapest": whether
            one station fewer than the plan's could possibly meet the requirement
            (``search["fewer_stations_lower_bound_ratio"]`` > 1 proves it cannot).
    """

    n_stations: int = 16
    min_rays: int = 3
    incidence_max_rad: float = float(np.deg2rad(60.0))
    criterion: str = "worst"
    sigma_px: float = 0.05
    mode: str = "fixed"
    required_sigma_m: float | np.ndarray | None = None
    tolerance_ratio: float = 10.0
    default_tolerance_m: float | None = None
    population: int = 80
    generations: int = 120
    stall_generations: int = 50
    time_limit_s: float | None = None
    eta_c: float = 15.0
    eta_m: float = 5.0
    p_crossover: float = 0.9
    p_mutation: float | None = 0.05
    p_bit_flip: float | None = None
    tournament_size: int = 2
    n_elite: int = 2
    p_reset: float | None = None
    plus_selection: bool = True
    visibility: VisibilityOptions | None = None
    sphere: ViewingSphere | None = None
    n_candidates: int = 3000
    n_shells: int = 3
    backend: str = "embree"
    allow_unmeasurable: bool = False
    greedy_fraction: float = 0.25
    cheapest_refine: int = 3
    refine_starts: int = 2
    refine_kicks: int = 8
    ring_seeds: int = 8
    polish_rounds: int = 12
    lower_bound: bool = False

    def check(self) -> None:
        """Raise InputError naming the first bad option."""
        if self.mode not in MODES:
            raise InputError(f"planning option mode={self.mode!r}: use one of {', '.join(MODES)}")
        if self.criterion not in CRITERIA:
            raise InputError(f"planning option criterion={self.criterion!r}: use one of {', '.join(CRITERIA)}")
        if self.min_rays < 2:
            raise InputError(f"planning option min_rays={self.min_rays}: a target needs at least 2 rays")
        if self.n_stations < self.min_rays:
            raise InputError(
                f"planning option n_stations={self.n_stations} is below min_rays={self.min_rays}: "
                "no network could measure a target often enough; raise n_stations"
            )
        if not 0 < self.incidence_max_rad <= math.pi / 2:
            raise InputError(f"planning option incidence_max_rad={self.incidence_max_rad}: must be in (0, pi/2]")
        if not self.sigma_px > 0:
            raise InputError(f"planning option sigma_px={self.sigma_px}: must be > 0")
        if self.population < 4 or self.generations < 0:
            raise InputError("planning options: population must be >= 4 and generations >= 0")
        if self.mode == "fixed" and self.n_elite >= self.population:
            raise InputError("planning options: n_elite must be smaller than the population")

    def visibility_options(self) -> VisibilityOptions:
        """The measurability limits, with this plan's incidence angle."""
        return replace(self.visibility or VisibilityOptions(), incidence_max_rad=self.incidence_max_rad)

    def search_sphere(self, part, intr: Intrinsics) -> ViewingSphere:
        """The viewing sphere searched: ``sphere`` (or one sized for the part) with roll and
        look-at offset held at zero (see module docstring)."""
        sphere = self.sphere or ViewingSphere.for_part(part, intr)
        return replace(sphere, max_roll_rad=0.0, max_offset_m=0.0)

    def evolution_options(self) -> EvolutionOptions:
        return EvolutionOptions(
            population=self.population,
            generations=self.generations,
            stall_generations=self.stall_generations,
            time_limit_s=self.time_limit_s,
            eta_c=self.eta_c,
            eta_m=self.eta_m,
            p_crossover=self.p_crossover,
            p_mutation=self.p_mutation,
            p_bit_flip=self.p_bit_flip,
            tournament_size=self.tournament_size,
            n_elite=self.n_elite,
            fix_bits=self.mode == "fixed",
            align_gene=0,
            p_reset=(0.5 / self.n_stations) if self.p_reset is None else self.p_reset,
            plus_selection=self.plus_selection,
        )


@dataclass
class NetworkPlan:
    """A planned network and its predicted precision (the content of plan.json).

    Attributes:
        seed: the seed the search's generator was made from (None if not given).
        criterion: the criterion minimised; mode: "fixed" | "cheapest".
        intrinsics: the camera; sigma_px: image noise assumed (pixels).
        min_rays, incidence_max_rad: the constraints planned for.
        station_ids: (k,) str; part_from_cam: (k, 4, 4); genes: (k, N_GENES).
        target_ids: (n,) str; xyz, normals: (n, 3).
        cov: (n, 3, 3) predicted covariance (m^2), exact for the final stations; nan
            where a target is measured by fewer than ``min_rays`` stations.
        n_rays: (n,) int; seen_by: per target the ids of the stations that measure it.
        predicted_sigma_max_m, predicted_sigma_mean_m: over the targets planned for (those
            in ``unmeasurable_target_ids`` excluded), sigma = sqrt(trace(cov)).
        history: one dict per generation (best, mean, n_active, n_feasible, phase: "search"
            or "refine <k>", step: running index over the phases, ...).
        pareto_front: "cheapest": [{n_stations, sigma_ratio_max, phase}] of the front
            (phase "front") and of the refining searches (phase "refine"; inf if infeasible).
        required_sigma_m: (n,) the requirement in "cheapest" mode, else None.
        unmeasurable_target_ids: targets left out of the search (allow_unmeasurable).
        timing: seconds per stage.
        search: summary (stopped_because, n_evaluations, which poses were kept, ...).
    """

    seed: int | None
    criterion: str
    mode: str
    intrinsics: Intrinsics
    sigma_px: float
    min_rays: int
    incidence_max_rad: float
    station_ids: list[str]
    part_from_cam: np.ndarray
    genes: np.ndarray
    target_ids: list[str]
    xyz: np.ndarray
    normals: np.ndarray
    cov: np.ndarray
    n_rays: np.ndarray
    seen_by: list[list[str]]
    predicted_sigma_max_m: float
    predicted_sigma_mean_m: float
    history: list[dict] = field(default_factory=list)
    pareto_front: list[dict] = field(default_factory=list)
    required_sigma_m: np.ndarray | None = None
    unmeasurable_target_ids: list[str] = field(default_factory=list)
    timing: dict = field(default_factory=dict)
    search: dict = field(default_factory=dict)

    @property
    def sigma(self) -> np.ndarray:
        """(n,) sqrt(trace(cov)) per target (m), inf where not measurable."""
        s = np.sqrt(np.trace(self.cov, axis1=1, axis2=2))
        return np.where(np.isfinite(s), s, np.inf)

    def to_plan_dict(self) -> dict:
        """The plan.json document (ARCHITECTURE.md "plan.json"), JSON-ready."""
        i = self.intrinsics
        cov_list = [None if not np.all(np.isfinite(c)) else c.tolist() for c in self.cov]
        return {
            "seed": self.seed,
            "criterion": self.criterion,
            "mode": self.mode,
            "camera": {
                "fx_px": i.fx_px, "fy_px": i.fy_px, "cx_px": i.cx_px, "cy_px": i.cy_px,
                "width": i.width, "height": i.height, "sigma_px": self.sigma_px,
                "k1": i.k1, "k2": i.k2, "k3": i.k3, "p1": i.p1, "p2": i.p2,
            },
            "min_rays": self.min_rays,
            "incidence_max_rad": self.incidence_max_rad,
            "stations": [
                {"id": sid, "part_from_cam": T.tolist(), "genes": g.tolist()}
                for sid, T, g in zip(self.station_ids, self.part_from_cam, self.genes)
            ],
            "targets": [
                {
                    "id": tid, "xyz": x.tolist(), "normal": nrm.tolist(), "seen_by": list(sb),
                    "predicted_cov": c, "n_rays": int(nr),
                    **({} if self.required_sigma_m is None else {"required_sigma_m": float(self.required_sigma_m[j])}),
                }
                for j, (tid, x, nrm, sb, c, nr) in enumerate(
                    zip(self.target_ids, self.xyz, self.normals, self.seen_by, cov_list, self.n_rays)
                )
            ],
            "predicted_sigma_max_m": _json_float(self.predicted_sigma_max_m),
            "predicted_sigma_mean_m": _json_float(self.predicted_sigma_mean_m),
            "unmeasurable_target_ids": list(self.unmeasurable_target_ids),
            "history": [{k: _json_float(v) for k, v in row.items()} for row in self.history],
            "pareto_front": [{k: _json_float(v) for k, v in row.items()} for row in self.pareto_front],
            "timing": dict(self.timing),
            "search": {k: _json_float(v) for k, v in self.search.items()},
        }

    @classmethod
    def from_plan_dict(cls, d: dict) -> "NetworkPlan":
        """Read a plan.json document back (extra keys, e.g. added by VALIDATE, are ignored)."""
        try:
            cam = d["camera"]
            intr = Intrinsics(
                fx_px=float(cam["fx_px"]), fy_px=float(cam["fy_px"]), cx_px=float(cam["cx_px"]),
                cy_px=float(cam["cy_px"]), width=int(cam["width"]), height=int(cam["height"]),
                **{k: float(cam.get(k, 0.0)) for k in ("k1", "k2", "k3", "p1", "p2")},
            )
            st = d["stations"]
            tg = d["targets"]
            cov = np.array([np.full((3, 3), np.nan) if t["predicted_cov"] is None else t["predicted_cov"] for t in tg],
                           dtype=float).reshape(-1, 3, 3)
            station_ids = [str(s["id"]) for s in st]
            seen_by = [[str(x) for x in t["seen_by"]] for t in tg]
            req = [t.get("required_sigma_m") for t in tg]
            return cls(
                seed=d.get("seed"),
                criterion=str(d["criterion"]),
                mode=str(d.get("mode", "fixed")),
                intrinsics=intr,
                sigma_px=float(cam["sigma_px"]),
                min_rays=int(d["min_rays"]),
                incidence_max_rad=float(d["incidence_max_rad"]),
                station_ids=station_ids,
                part_from_cam=np.array([s["part_from_cam"] for s in st], dtype=float).reshape(-1, 4, 4),
                genes=np.array([s.get("genes", [np.nan] * N_GENES) for s in st], dtype=float).reshape(-1, N_GENES),
                target_ids=[str(t["id"]) for t in tg],
                xyz=np.array([t["xyz"] for t in tg], dtype=float).reshape(-1, 3),
                normals=np.array([t["normal"] for t in tg], dtype=float).reshape(-1, 3),
                cov=cov,
                n_rays=np.array([t.get("n_rays", len(s)) for t, s in zip(tg, seen_by)], dtype=int),
                seen_by=seen_by,
                predicted_sigma_max_m=_float_back(d["predicted_sigma_max_m"]),
                predicted_sigma_mean_m=_float_back(d["predicted_sigma_mean_m"]),
                history=list(d.get("history", [])),
                pareto_front=list(d.get("pareto_front", [])),
                required_sigma_m=None if any(r is None for r in req) or not req else np.array(req, dtype=float),
                unmeasurable_target_ids=list(d.get("unmeasurable_target_ids", [])),
                timing=dict(d.get("timing", {})),
                search=dict(d.get("search", {})),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"plan.json is not a valid plan ({type(exc).__name__}: {exc}); re-run `cell plan`") from exc


def _json_float(v):
    if isinstance(v, (float, np.floating)):
        v = float(v)
        return v if math.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def _float_back(v) -> float:
    return float("inf") if v is None else float(v)


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
                "planning mode 'cheapest' needs a required precision: set required_sigma_m, or give every "
                "target a tolerance (targets file or [report] default tolerance)"
            )
        req = tol / options.tolerance_ratio
    if np.any(~(req > 0)):
        raise InputError("required precision must be positive for every target")
    return req


# --- the search problem ----------------------------------------------------------------


class _Problem:
    """Evaluates populations on the visibility database (see module docstring)."""

    def __init__(self, db: VisibilityDB, info: np.ndarray, vis: np.ndarray, valid: np.ndarray,
                 options: PlannerOptions, required: np.ndarray | None):
        self.db, self.info, self.vis = db, info, vis
        self.opt = options
        self.required = required
        #: "criterion" (fixed size), "ratio" (max sigma / required), "count_ratio" (front)
        self.objective = "criterion" if options.mode == "fixed" else "count_ratio"
        self.valid_idx = np.flatnonzero(valid)
        tree = cKDTree(db.eyes[valid])
        _, nearest_valid = tree.query(db.eyes)
        self.repair = np.where(valid, np.arange(len(valid)), self.valid_idx[nearest_valid])

    def snap(self, genes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Candidate index of each station after correction, and whether it was corrected."""
        idx = self.db.nearest(genes)
        fixed = self.repair[idx]
        return fixed, fixed != idx

    def __call__(self, genes: np.ndarray, bits: np.ndarray) -> Evaluation:
        genes = genes.copy()
        idx, corrected = self.snap(genes)
        genes[corrected] = self.db.genes[idx[corrected]]
        stations = np.where(bits, idx, -1)
        ev = evaluate_networks(self.info, stations, self.opt.min_rays, visible=self.vis)
        violation = _violation(ev)
        if self.objective == "criterion":
            objectives = criterion(ev, self.opt.criterion, penalty=0.0)[:, None]
        else:
            ratio = np.max(np.where(ev.sufficient, ev.sigma / self.required, 0.0), axis=1)
            if self.objective == "ratio":
                objectives = ratio[:, None]
            else:
                objectives = np.column_stack([bits.sum(axis=1).astype(float), ratio])
        return Evaluation(objectives, violation, genes, bits)


def _violation(ev: NetworkEval) -> np.ndarray:
    """(p,) shortfall of rays summed over targets, plus one per target with singular geometry."""
    short = np.maximum(ev.min_rays - ev.n_rays, 0).sum(axis=1)
    singular = np.count_nonzero(~ev.sufficient & (ev.n_rays >= ev.min_rays), axis=1)
    return (short + singular).astype(float)


def _exact(part, intr: Intrinsics, options: PlannerOptions, vis_opts: VisibilityOptions, genes: np.ndarray,
           sphere: ViewingSphere, cols: np.ndarray) -> dict:
    """Fresh ray casting and float64 covariance for one network; scored like the search."""
    T = sphere.poses(genes)
    visible = compute_visibility(part, intr, T, vis_opts, backend=options.backend)
    cov, n_rays = covariance_for_network(
        intr, T, part.targets.xyz, visible, options.sigma_px, min_rays=options.min_rays
    )
    c6 = cov[:, _IU[0], _IU[1]][cols][None]
    sig = np.sqrt(np.trace(cov, axis1=1, axis2=2))[cols][None]
    ok = np.isfinite(sig)
    ev = NetworkEval(cov6=c6, sigma=np.where(ok, sig, np.inf), n_rays=n_rays[cols][None], sufficient=ok,
                     min_rays=options.min_rays)
    return {"T": T, "visible": visible, "cov": cov, "n_rays": n_rays, "violation": float(_violation(ev)[0]),
            "score": float(criterion(ev, options.criterion, penalty=0.0)[0]), "sigma": np.where(ok, sig, np.inf)[0]}


def _best_rings(problem: _Problem, k: int, sphere: ViewingSphere, n: int) -> np.ndarray:
    """The ``n`` best ring networks of ``k`` stations on the database (feasible first); (n, k, G)."""
    rings = ring_sweep(k, sphere)
    ev = problem(rings, np.ones(rings.shape[:2], dtype=bool))
    order = np.lexsort((ev.objectives[:, 0], ev.violation))[:n]
    return ev.genes[order]


def _refine(problem: _Problem, r: EvolutionResult, objective: str,
            rng: np.random.Generator) -> tuple[EvolutionResult, dict]:
    """Exchange descent (planning.refine) from the search's best distinct networks.

    Returns ``r`` with its best individual replaced by the refined network when that is
    better, and a summary (swaps, objective before and after).
    """
    opt = problem.opt
    idx = problem.snap(r.genes)[0]
    starts, seen = [], set()
    for row in idx:  # best first
        key = tuple(sorted(row))
        if len(set(row)) == len(row) and key not in seen:
            seen.add(key)
            starts.append(row)
        if len(starts) == opt.refine_starts:
            break
    before = float(r.objectives[0, 0]) if r.violation[0] <= 0 else float("inf")
    if not starts:
        return r, {"swaps": 0, "from": before, "to": before}
    info = problem.info
    if objective == "ratio":  # sigma / required: the information scaled by required^2
        info = info * (problem.required.astype(np.float32) ** 2)[None, :, None]
    res = refine_network(info, problem.vis, problem.valid_idx, np.array(starts), opt.min_rays, rng,
                         n_kicks=opt.refine_kicks)
    stats = {"swaps": res.n_swaps, "from": before, "to": min(before, res.worst)}
    if not res.worst < before:
        return r, stats
    genes, bits = r.genes.copy(), r.bits.copy()
    objectives, violation = r.objectives.copy(), r.violation.copy()
    genes[0], bits[0] = problem.db.genes[res.stations], True
    objectives[0, 0], violation[0] = res.worst, 0.0
    return replace(r, genes=genes, bits=bits, objectives=objectives, violation=violation), stats


# --- entry points -----------------------------------------------------------------------------


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


def plan_network(
    part,
    intr: Intrinsics,
    options: PlannerOptions,
    rng: np.random.Generator | None = None,
    reachable: np.ndarray | None = None,
    cache_dir=None,
    progress: Progress | None = None,
    *,
    seed: int | None = None,
    db: VisibilityDB | None = None,
    reachable_fn=None,
) -> NetworkPlan:
    """Design a network (see module docstring); the same inputs and seed give the same plan.

    Args:
        part: planning.part.Part (mesh, targets with xyz, normals, ids, tolerance_m).
        intr: the camera.
        options: :class:`PlannerOptions` (``mode`` chooses fixed size or cheapest).
        rng: the search's generator; None: ``numpy.random.default_rng(seed)``.
        reachable: (m,) bool aligned with the visibility database's candidates, or None.
        reachable_fn: ``part_from_cam (p, 4, 4) -> (p,) bool`` for poses off the database (the
            exact local polish, ``polish_rounds``); with ``reachable`` but without it the polish is
            skipped, since its poses' reachability would be unknown.
        cache_dir: where the visibility database is cached (None: default cache).
        progress: called as ``progress(stage, fraction)``.
        seed: recorded in the plan (and used when ``rng`` is None).
        db: a visibility database already built for this part, camera and options.
    Returns:
        :class:`NetworkPlan`.
    Raises:
        InputError: bad options.  PlanningError: no valid station, targets that cannot be
        measured by ``min_rays`` stations, or (cheapest) no network reaches the precision.
    """
    options.check()
    if rng is None:
        rng = np.random.default_rng(seed)
    report = progress or (lambda stage, fraction: None)
    timing: dict[str, float] = {}
    t_all = t0 = time.perf_counter()
    vis_opts = options.visibility_options()
    if db is None:
        db = build_database(part, intr, options, cache_dir, report)
    elif db.options != vis_opts or db.visible.shape[1] != len(part.targets.xyz):
        raise InputError(
            "the visibility database given was built for other visibility options or targets; "
            "build it with planning.planner.build_database(part, intr, options)"
        )
    # search azimuth, elevation and distance only (see module docstring)
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
                f"(e.g. {', '.join(bad[:5])}): lower min_rays, raise incidence_max_rad, widen the viewing "
                "sphere, or set allow_unmeasurable to plan without them"
            )
    cols = np.flatnonzero(measurable)
    if cols.size == 0:
        raise PlanningError("no target can be measured by min_rays valid stations")
    xyz = np.asarray(part.targets.xyz, dtype=float)
    vis = db.visible[:, cols]
    info = target_information(intr, db.part_from_cam, xyz[cols], vis, options.sigma_px)
    report("information", 1.0)
    required = required_sigma(part, options) if options.mode == "cheapest" else None
    problem = _Problem(db, info, vis, valid, options, None if required is None else required[cols])
    timing["information_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    k, P = options.n_stations, options.population
    lower, upper = sphere.lower, sphere.upper
    periodic = np.zeros(N_GENES, dtype=bool)
    periodic[0] = (upper[0] - lower[0]) >= 2 * math.pi - 1e-9
    history: list[dict] = []
    refine_stats: list[dict] = []
    n_evaluations = [0]

    def search(size: int, mode: str, objective: str, phase: str, seeds: list[np.ndarray] = ()):
        """One evolutionary run; ``seeds`` are (size, G) networks put into the initial population."""
        problem.objective = objective
        run_opts = replace(options, n_stations=size, mode=mode)
        g0, b0 = initial_population(problem.valid_idx, problem.vis, db.genes, size, P, mode, options.min_rays, rng,
                                    options.greedy_fraction)
        if mode == "fixed" and options.ring_seeds > 0:
            seeds = list(seeds) + list(_best_rings(problem, size, sphere, options.ring_seeds))
        for i, g in enumerate(seeds[: P // 4]):
            g0[P - 1 - i], b0[P - 1 - i] = g, True
        r = evolve(problem, lower, upper, g0, b0, run_opts.evolution_options(), rng, periodic=periodic,
                   progress=lambda f, row: report(phase, f))
        n_evaluations[0] += r.n_evaluations
        if options.refine_starts > 0 and mode == "fixed" and (objective == "ratio" or options.criterion == "worst"):
            r, stats = _refine(problem, r, objective, rng)
            refine_stats.append({"phase": phase, **stats})
        start = len(history)
        history.extend({**row, "phase": phase, "step": start + j} for j, row in enumerate(r.history))
        return r

    def feasible_ratio(r) -> float:
        return float(r.objectives[0, 0]) if r.violation[0] <= 0 else float("inf")

    polish_stats: dict = {}
    networks: list[np.ndarray] = []  # best first: candidates for the plan, each (c, G)
    pareto: list[dict] = []
    if options.mode == "fixed":
        res = search(k, "fixed", "criterion", "search")
        networks = [res.genes[0]]
        if options.polish_rounds > 0 and options.criterion == "worst" and (reachable is None or reachable_fn):
            pol = polish(part, intr, sphere, vis_opts, db, res.genes[0], cols, options, reachable_fn=reachable_fn)
            networks = [pol.genes]
            polish_stats.update(polish_swaps=pol.n_swaps, polish_from=pol.start_worst, polish_to=pol.worst,
                                polish_poses=pol.n_poses)
        search_values = [float(res.objectives[0, 0])]
    else:
        res = search(k, "cheapest", "count_ratio", "search")
        front: dict[int, tuple[float, np.ndarray]] = {}
        for i in res.pareto_front():
            c, f = int(res.objectives[i, 0]), float(res.objectives[i, 1])
            if c not in front or f < front[c][0]:
                front[c] = (f, res.genes[i][res.bits[i]])
        pareto = [{"n_stations": c, "sigma_ratio_max": f, "phase": "front"} for c, (f, _) in sorted(front.items())]
        meets = sorted(c for c, (f, _) in front.items() if f <= 1.0)
        best: tuple[int, np.ndarray, float] | None = (meets[0], front[meets[0]][1], front[meets[0]][0]) if meets else None
        if best is None:  # the front falls short: the strongest search at the largest size decides
            seeds = [front[max(front)][1]] if front and max(front) == k else []
            r = search(k, "fixed", "ratio", f"refine {k}", seeds)
            pareto.append({"n_stations": k, "sigma_ratio_max": feasible_ratio(r), "phase": "refine"})
            if feasible_ratio(r) <= 1.0:
                best = (k, r.genes[0], feasible_ratio(r))
        if best is None:
            top = min(pareto, key=lambda row: row["sigma_ratio_max"], default=None)
            raise PlanningError(
                f"no network of at most {k} stations reaches the required precision"
                + (f" (best: sigma/required = {top['sigma_ratio_max']:.2f} with {top['n_stations']} stations)"
                   if top and math.isfinite(top["sigma_ratio_max"]) else "")
                + ": raise n_stations, relax the requirement, or lower sigma_px"
            )
        # refine: a fixed-size search (seeded with the front) for one station fewer, while it succeeds
        for _ in range(options.cheapest_refine):
            c = best[0] - 1
            if c < options.min_rays:
                break
            drop = best[1][np.argsort(rng.random(best[0]))[:c]]
            seeds = ([front[c][1]] if c in front else []) + [drop]
            r = search(c, "fixed", "ratio", f"refine {c}", seeds)
            pareto.append({"n_stations": c, "sigma_ratio_max": feasible_ratio(r), "phase": "refine"})
            if feasible_ratio(r) > 1.0:
                break
            best = (c, r.genes[0], feasible_ratio(r))
        networks = [best[1]] + [front[c][1] for c in meets if c > best[0]]
        search_values = [best[2]] + [front[c][0] for c in meets if c > best[0]]
    timing["search_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()

    def exact_variants(genes: np.ndarray) -> tuple[str, dict, np.ndarray]:
        """Exact evaluation of the continuous stations ``genes: (c, G)`` and of their database
        neighbours (identical to what the search saw); the better one is kept."""
        snapped = db.genes[problem.snap(genes)[0]]
        variants = {"continuous": (_exact(part, intr, options, vis_opts, genes, sphere, cols), genes)}
        if not np.allclose(snapped, genes):
            variants["snapped"] = (_exact(part, intr, options, vis_opts, snapped, sphere, cols), snapped)
        if options.mode == "cheapest":
            for v, _ in variants.values():
                v["score"] = float(np.max(v["sigma"] / required[cols]))
        name = min(variants, key=lambda n_: (variants[n_][0]["violation"], variants[n_][0]["score"]))
        return name, *variants[name]

    for genes, search_fitness in zip(networks, search_values):  # cheapest: walk up until the exact check passes
        kept, final, final_genes = exact_variants(genes)
        if options.mode == "fixed" and final["violation"] > 0:
            short = int(np.count_nonzero(final["n_rays"][cols] < options.min_rays))
            raise PlanningError(
                f"no network of {k} stations found measures every target with {options.min_rays} rays "
                f"(the best leaves {short} target(s) short): raise n_stations or lower min_rays"
            )
        if options.mode == "fixed" or (final["violation"] == 0 and final["score"] <= 1.0):
            break
    else:
        raise PlanningError(
            f"the networks found ({', '.join(str(len(g)) for g in networks)} stations) met the "
            "required precision on the visibility database but not when re-checked exactly: raise n_candidates "
            "(a finer database) or n_stations"
        )
    report("final", 1.0)
    timing["final_s"] = time.perf_counter() - t0
    bound_facts = _bound_facts(options, info, valid, vis, final_genes, final, required, cols, report) \
        if options.lower_bound else {}
    if bound_facts:
        timing["bound_s"] = bound_facts.pop("seconds")
    timing["total_s"] = time.perf_counter() - t_all

    order = np.lexsort((final_genes[:, 2], final_genes[:, 1], final_genes[:, 0]))
    T, final_genes, visible = final["T"][order], final_genes[order], final["visible"][order]
    station_ids = [f"S{i + 1:03d}" for i in range(len(order))]
    cov, n_rays = final["cov"], final["n_rays"]
    sig = np.sqrt(np.trace(cov, axis1=1, axis2=2))
    sig_cols = sig[cols]
    finite = np.isfinite(sig_cols)
    return NetworkPlan(
        seed=seed,
        criterion=options.criterion,
        mode=options.mode,
        intrinsics=intr,
        sigma_px=float(options.sigma_px),
        min_rays=int(options.min_rays),
        incidence_max_rad=float(options.incidence_max_rad),
        station_ids=station_ids,
        part_from_cam=T,
        genes=final_genes,
        target_ids=ids,
        xyz=xyz.copy(),
        normals=np.asarray(part.targets.normals, dtype=float).copy(),
        cov=cov,
        n_rays=n_rays,
        seen_by=[[station_ids[i] for i in np.flatnonzero(visible[:, j])] for j in range(n)],
        predicted_sigma_max_m=float(np.max(sig_cols)) if finite.all() else float("inf"),
        predicted_sigma_mean_m=float(np.mean(sig_cols)) if finite.all() else float("inf"),
        history=history,
        pareto_front=pareto,
        required_sigma_m=required,
        unmeasurable_target_ids=[ids[j] for j in np.flatnonzero(~measurable)],
        timing=timing,
        search={
            "stopped_because": res.stopped_because,
            "generations": len(res.history) - 1,
            "refine_runs": sum(1 for row in pareto if row.get("phase") == "refine"),
            **({"exchange_swaps": sum(x["swaps"] for x in refine_stats),
                "exchange_from": refine_stats[0]["from"], "exchange_to": refine_stats[0]["to"]} if refine_stats else {}),
            **polish_stats,
            "n_evaluations": n_evaluations[0],
            "n_candidates": int(m),
            "n_valid_candidates": int(valid.sum()),
            "visibility_key": db.key,
            "visibility_from_cache": bool(db.from_cache),
            "poses_kept": kept,
            "search_fitness": search_fitness,
            "exact_fitness": final["score"],
            "exact_violation": final["violation"],
            **bound_facts,
        },
    )


def _bound_facts(options: PlannerOptions, info: np.ndarray, valid: np.ndarray, vis: np.ndarray,
                 genes: np.ndarray, final: dict, required: np.ndarray | None, cols: np.ndarray, report) -> dict:
    """``search`` entries of the lower bound (planning.bound) for this plan; {} if it does not apply."""
    progress = lambda stage, fraction: report("bound", fraction)  # noqa: E731
    if options.mode == "fixed":
        if options.criterion != "worst":
            return {}
        b = worst_sigma_lower_bound(info, len(genes), valid=valid, visible=vis, min_rays=options.min_rays,
                                    progress=progress)
        worst = float(np.max(final["sigma"]))
        return {"lower_bound_sigma_m": b.lower, "lower_bound_relaxed_m": b.relaxed,
                "plan_over_lower_bound": worst / b.lower, "lower_bound_stopped": b.stopped_because,
                "seconds": b.seconds}
    fewer = len(genes) - 1
    if fewer < options.min_rays or required is None:
        return {}
    # one station fewer: can any network reach sigma / required <= 1?  Stop as soon as it is decided.
    b = worst_sigma_lower_bound(info, fewer, valid=valid, visible=vis, min_rays=options.min_rays,
                                scale=required[cols], stop_above=1.0, stop_below=1.0, progress=progress)
    return {"fewer_stations": fewer, "fewer_stations_lower_bound_ratio": b.lower,
            "fewer_stations_cannot_meet": bool(b.lower > 1.0), "seconds": b.seconds}


def cheapest_network(
    part,
    intr: Intrinsics,
    options: PlannerOptions,
    rng: np.random.Generator | None = None,
    reachable: np.ndarray | None = None,
    cache_dir=None,
    progress: Progress | None = None,
    **kwargs,
) -> NetworkPlan:
    """The fewest stations (at most ``options.n_stations``) meeting the required precision."""
    return plan_network(part, intr, replace(options, mode="cheapest"), rng, reachable, cache_dir, progress, **kwargs)
