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

Modules (docs/decisions/0012-split-bundle-planner.md): ``options`` (:class:`PlannerOptions`), ``result``
(:class:`NetworkPlan`, plan.json), ``setup`` (database, valid candidates, targets, information),
``problem`` (fitness on the database, exact evaluation), ``search`` (evolutionary runs, ring seeds,
exchange descent, the fixed-size search), ``cheapest`` (the Pareto front and its refinement),
``final`` (exact re-check, lower bound), ``plan`` (:func:`plan_network`, :func:`cheapest_network`).
"""
from __future__ import annotations

from planning.planner.options import MODES, PlannerOptions, Progress  # noqa: F401 (MODES, Progress: as before)
from planning.planner.plan import cheapest_network, plan_network
from planning.planner.problem import _Problem  # noqa: F401 (tests use it)
from planning.planner.result import NetworkPlan
from planning.planner.search import _best_rings  # noqa: F401 (tests use it)
from planning.planner.setup import build_database, required_sigma
from planning.seeding import greedy_cover

__all__ = [
    "PlannerOptions",
    "NetworkPlan",
    "build_database",
    "plan_network",
    "cheapest_network",
    "required_sigma",
    "greedy_cover",
]
