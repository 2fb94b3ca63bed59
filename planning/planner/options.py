"""What to plan and how to search: :class:`PlannerOptions`."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from calibration.camera import Intrinsics
from calibration.errors import InputError
from planning.evolution import EvolutionOptions
from planning.stations import ViewingSphere
from planning.uncertainty import CRITERIA, ImagePrecision
from planning.visibility import VisibilityOptions

Progress = Callable[[str, float], None]
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
        image_precision: the image precision per station and target from the detector model
            (:class:`planning.uncertainty.ImagePrecision`); None: ``sigma_px`` for every ray.
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
        ladder_base: "fixed" with the "worst" criterion and more stations than this: the network is grown
            from the plan of ``ladder_base`` stations, doubling (base, 2 base, 4 base, ..., n_stations): each
            size adds stations greedily to the polished plan of the size below and polishes the result
            (planning.planner.ladder), so a plan of more stations is never worse than the plans of the ladder's
            sizes below it; 0: every size searched on its own.
        link_targets: two stations are linked when they see this many common targets; a network whose stations
            fall into blocks not linked to each other is infeasible (one violation per station outside the largest
            block): ADJUST's screening would drop those images (cell/stages/screen.py LINK_TARGETS, the same 8).
            Limiting error propagation holds the orientations fixed and cannot see it (docs/decisions/0031); 0: off
            (the default; a job's search weighted by the detector model sets 8, cell.setup.planner_options).
        scale_bars: ``(index_a, index_b, length_m, sigma_m)`` per scale bar of the job (empty: none): after the
            search the plan adds stations until every bar's ends meet the requirement of :mod:`planning.scalebar`,
            bar after bar, each counting the stations added for the bars before it (the search's own stations kept
            as they are).
        sole_links: with ``link_targets``, a station that alone links a part of the network to the rest (removing it
            splits the network) counts as a violation too (the model-ranked search's failure, decision 0031).
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
    image_precision: ImagePrecision | None = None
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
    ladder_base: int = 32
    lower_bound: bool = False
    link_targets: int = 0
    sole_links: bool = True
    scale_bars: tuple = ()

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

    def image_sigma(self, cols: np.ndarray | None = None):
        """What :func:`planning.uncertainty.target_information` takes for the targets ``cols`` (None: all)."""
        if self.image_precision is None:
            return self.sigma_px
        return self.image_precision if cols is None else self.image_precision.subset(cols)

    def visibility_options(self) -> VisibilityOptions:
        """The measurability limits, with this plan's incidence angle."""
        return replace(self.visibility or VisibilityOptions(), incidence_max_rad=self.incidence_max_rad)

    def search_sphere(self, part, intr: Intrinsics) -> ViewingSphere:
        """The viewing sphere searched: ``sphere`` (or one sized for the part) with roll and
        look-at offset held at zero (see :mod:`planning.planner`)."""
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
