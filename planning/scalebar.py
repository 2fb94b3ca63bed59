"""The scale bar's ends in the plan: measured as well as the certificate deserves.

A job's scale comes from its scale bars (``job.scale_bars``: each two of the part's targets and a certified length;
the planner secures them one after the other, each counting the stations added for the bars before it, decision
0041; this module handles one bar).
Every target's coordinates follow the scale, so the measurement of the bar's two ends enters every target's
uncertainty (ADJUST: bundle.json, report.json ``uncertainty_budget.scale_sigma_ppm``). The search treats the ends
as two targets among hundreds; this module checks them after the search and, where they fall short, adds stations
from the visibility database's reachable candidates (:func:`planning.augment.plan_extra_stations`, the closed
loop's "fewest extra stations" with the stations already planned held fixed). The search's own stations are
kept as they are.

The requirement (docs/decisions/0033), judged by limiting error propagation of the planned network with the job's
image precision (the information the search uses):

- **length**: the ends' part of the bar's measured length, ``sqrt(u^T (C_a + C_b) u)`` (``u`` the bar's direction,
  ``C`` the ends' predicted covariance), is no larger than :data:`LENGTH_SHARE` times the certificate's sigma: the
  measurement adds no more to the scale than the certificate does;
- **rays**: each end is seen by at least :data:`RAYS_FACTOR` x ``min_rays`` stations, counting only the rays the
  detector is sure to keep: the end's image at least :data:`BAR_MARGIN_FRAC` of the image inside its border and
  its incidence :data:`BAR_INCIDENCE_MARGIN_DEG` below the plan's limit (the length and the spread are judged on
  these rays too: a bar end at the image border is the first dot the detector loses);
- **spread**: the azimuths of each end's lines of sight about its normal leave no gap wider than
  :data:`AZIMUTH_GAP_MAX_DEG` (views from several sides, so a misfit an edge dot shares between views from one
  side does not move the end as a whole along the bar).

The length budget is split between the ends: an end already within half the variance leaves the rest to the
other, otherwise each gets half (a sufficient condition for the sum). When no choice of reachable candidates can
meet the requirement (the closed loop's bound: the planned stations plus every candidate that sees the end), the
plan says so in one line with the best achievable and takes the stations that come nearest; it does not fail.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planning.augment import plan_extra_stations
from planning.uncertainty import covariance_for_network, target_information
from planning.visibility import compute_visibility

__all__ = ["BarCheck", "secure_scale_bar", "finish_doc", "bar_facts", "bar_line", "bar_warnings", "ends_clear", "rendered_rays_note", "covariance_with", "LENGTH_SHARE", "RAYS_FACTOR",
           "AZIMUTH_GAP_MAX_DEG", "MAX_BAR_STATIONS"]

#: the ends' part of the bar length's sigma may be at most this times the certificate's sigma
LENGTH_SHARE = 1.0
#: each end needs this many times ``min_rays`` rays
RAYS_FACTOR = 2
#: the widest gap allowed between the azimuths (about the end's normal) of the stations that see an end
AZIMUTH_GAP_MAX_DEG = 150.0
#: a line of sight within this angle of the normal has no azimuth worth the name (it counts for no side)
AZIMUTH_MIN_TILT_DEG = 5.0
#: a ray of an end counts for the bar only when the end's image lies this share of the image's smaller side inside
#: the border (dots at the border are the first the detector loses: clipped, stretched by the distortion, merged)
BAR_MARGIN_FRAC = 0.05
#: and when its incidence is this much below the plan's limit (the detector's precision falls with incidence)
BAR_INCIDENCE_MARGIN_DEG = 10.0
#: the most stations the bar may add to a plan
MAX_BAR_STATIONS = 8
#: where the requirement cannot be met, the stations aim at this factor over the best achievable (bound)
BOUND_MARGIN = 1.1
#: the reference of the network: this quantile of its targets' predicted sigma along the bar (its best tenth)
REFERENCE_QUANTILE = 0.1
#: a station added for the spread must narrow the widest gap by this much (and the goal is the best achievable
#: gap plus this, where no candidate closes it to AZIMUTH_GAP_MAX_DEG)
GAP_SLACK_DEG = 10.0


@dataclass
class BarCheck:
    """How the bar's ends stand in a network. ``length_sigma_m``: ``sqrt(u^T (C_a + C_b) u)`` (inf where an end is
    not measured); ``rays``, ``gap_deg``: per end; ``met``: all three parts of the requirement."""

    length_sigma_m: float
    along_sigma_m: tuple[float, float]
    rays: tuple[int, int]
    gap_deg: tuple[float, float]
    met: bool

    def to_dict(self) -> dict:
        fin = lambda v: float(v) if np.isfinite(v) else None  # noqa: E731
        return {"length_sigma_m": fin(self.length_sigma_m), "along_sigma_m": [fin(v) for v in self.along_sigma_m],
                "rays": [int(r) for r in self.rays], "azimuth_gap_deg": [float(g) for g in self.gap_deg],
                "met": bool(self.met)}


def trusted_views(intr, T: np.ndarray, xyz: np.ndarray, normals: np.ndarray, visible: np.ndarray,
                  incidence_max_rad: float) -> np.ndarray:
    """``visible: (k, e)`` restricted to the rays of the ends ``xyz, normals: (e, 3)`` the bar counts on: the end's
    image :data:`BAR_MARGIN_FRAC` of the image's smaller side inside the border, its incidence
    :data:`BAR_INCIDENCE_MARGIN_DEG` below ``incidence_max_rad``."""
    from calibration.camera import invert, project

    out = np.asarray(visible, dtype=bool).copy()
    T = np.asarray(T, dtype=float)
    m = BAR_MARGIN_FRAC * min(intr.width, intr.height)
    cos_lim = np.cos(max(incidence_max_rad - np.deg2rad(BAR_INCIDENCE_MARGIN_DEG), 0.0))
    for i in np.flatnonzero(out.any(axis=1)):
        uv = project(intr, invert(T[i]), xyz)
        d = T[i, :3, 3] - xyz
        cos_inc = np.einsum("ea,ea->e", d, normals) / np.linalg.norm(d, axis=1)
        with np.errstate(invalid="ignore"):
            inside = ((uv[:, 0] >= m - 0.5) & (uv[:, 0] <= intr.width - 0.5 - m) & (uv[:, 1] >= m - 0.5)
                      & (uv[:, 1] <= intr.height - 0.5 - m))
        out[i] &= inside & (cos_inc >= cos_lim)
    return out


def _along(N6: np.ndarray, u: np.ndarray) -> float:
    """sqrt(u^T N^-1 u) for one 3x3 information ``N6: (6,)`` (inf when singular)."""
    N = np.array([[N6[0], N6[1], N6[2]], [N6[1], N6[3], N6[4]], [N6[2], N6[4], N6[5]]], dtype=float)
    if not np.all(np.isfinite(N)) or np.linalg.det(N) <= 0 or np.linalg.cond(N) > 1e12:
        return float("inf")
    return float(np.sqrt(max(u @ np.linalg.solve(N, u), 0.0)))


def azimuth_gap_deg(eyes: np.ndarray, xyz: np.ndarray, normal: np.ndarray) -> float:
    """The widest gap (deg) between the azimuths about ``normal`` of the lines of sight from ``eyes: (k, 3)`` to
    ``xyz``; 360 when fewer than two of them are tilted by :data:`AZIMUTH_MIN_TILT_DEG` or more."""
    nrm = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    d = np.asarray(eyes, dtype=float).reshape(-1, 3) - xyz
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = d - np.outer(d @ nrm, nrm)
    tilted = np.linalg.norm(t, axis=1) >= np.sin(np.deg2rad(AZIMUTH_MIN_TILT_DEG))
    if tilted.sum() < 2:
        return 360.0
    e1 = np.cross(nrm, [1.0, 0.0, 0.0] if abs(nrm[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(nrm, e1)
    az = np.sort(np.degrees(np.arctan2(t[tilted] @ e2, t[tilted] @ e1)) % 360.0)
    gaps = np.diff(np.concatenate([az, [az[0] + 360.0]]))
    return float(gaps.max())


def bar_facts(N6: np.ndarray, rays: np.ndarray, eyes: list[np.ndarray], xyz: np.ndarray, normals: np.ndarray,
              u: np.ndarray, length_max: float, min_rays: int, gap_max=(AZIMUTH_GAP_MAX_DEG,) * 2) -> BarCheck:
    """The requirement checked for the two ends: ``N6: (2, 6)`` information, ``rays: (2,)``, ``eyes``: per end the
    stations' positions that see it (part frame), ``xyz, normals: (2, 3)``, ``length_max``: the largest ends' part
    of the length sigma allowed, ``gap_max``: per end the widest azimuth gap allowed."""
    along = tuple(_along(N6[k], u) if rays[k] >= min_rays else float("inf") for k in range(2))
    length = float(np.hypot(*along)) if all(np.isfinite(along)) else float("inf")
    gaps = tuple(azimuth_gap_deg(eyes[k], xyz[k], normals[k]) if len(eyes[k]) else 360.0 for k in range(2))
    met = (length <= length_max and min(rays) >= RAYS_FACTOR * min_rays
           and all(g <= m + 1e-9 for g, m in zip(gaps, gap_max)))
    return BarCheck(length, along, (int(rays[0]), int(rays[1])), gaps, bool(met))


def reference_along(cov: np.ndarray, cols: np.ndarray, ends: np.ndarray, u: np.ndarray) -> float:
    """The :data:`REFERENCE_QUANTILE` of the planned targets' predicted sigma along ``u`` (the ends left out):
    how well the network measures its best targets in the bar's direction (inf when none is measured)."""
    others = np.setdiff1d(np.asarray(cols, dtype=int), ends)
    c = np.asarray(cov, dtype=float)[others]
    var = np.einsum("a,nab,b->n", u, c, u)
    var = var[np.isfinite(var) & (var > 0)]
    return float(np.sqrt(np.quantile(var, REFERENCE_QUANTILE))) if len(var) else float("inf")


def _fewest(N_have, rays_have, req, info, vis, ok, min_rays, along, max_new):
    """:func:`plan_extra_stations` for the two ends; where ``max_new`` stations cannot meet ``req`` (its pruning
    then keeps none), the requirement is relaxed by steps of 15 % until they can: the nearest the cap allows."""
    for _ in range(40):
        aug = plan_extra_stations(N_have, rays_have, req, info, vis, ok, min_rays=min_rays, max_new=max_new,
                                  along=along)
        if np.all(aug.met_after | ~aug.short) or not np.any(ok):
            return aug, req
        req = np.where(aug.met_after | ~aug.short, req, 1.15 * req)
    return aug, req


def secure_scale_bar(part, intr, options, db, valid: np.ndarray, T: np.ndarray, visible: np.ndarray, cov: np.ndarray,
                     cols: np.ndarray, bar: tuple[int, int, float, float]) -> tuple[np.ndarray, dict]:
    """Candidates to add so that the bar's ends meet the requirement (see the module), and the bar's record of plan.json
    ``scale_bars``.

    Args:
        part, intr, options: the plan's part, camera and :class:`planning.planner.PlannerOptions`.
        db: the visibility database searched; ``valid: (m,)`` its candidates that see a target and are reachable.
        T: (k, 4, 4) the planned stations (part_from_cam); ``visible: (k, n)`` what they measure; ``cov: (n, 3, 3)``
            the search's predicted covariance (the network's reference, :func:`reference_along`); ``cols``: the
            targets planned for.
        bar: ``(index_a, index_b, length_m, sigma_m)``.
    Returns:
        ``(added, doc)``: candidate indices of ``db`` to append to the plan (possibly empty) and the record
        (completed by :func:`finish_doc` once the network with them is evaluated).
    """
    a, b, length, sigma_cert = int(bar[0]), int(bar[1]), float(bar[2]), float(bar[3])
    ends = np.array([a, b])
    xyz = np.asarray(part.targets.xyz, dtype=float)[ends]
    normals = np.asarray(part.targets.normals, dtype=float)[ends]
    u = xyz[0] - xyz[1]
    u /= np.linalg.norm(u)
    min_rays = int(options.min_rays)
    need_rays = RAYS_FACTOR * min_rays
    ref = reference_along(cov, cols, ends, u)
    end_req = float(max(LENGTH_SHARE * sigma_cert / np.sqrt(2.0), ref))
    budget = float(np.sqrt(2.0) * end_req)
    sig = options.image_sigma(ends)
    inc_max = float(options.incidence_max_rad)
    vis_plan = trusted_views(intr, T, xyz, normals, np.asarray(visible, dtype=bool)[:, ends], inc_max)
    N_have = (target_information(intr, T, xyz, vis_plan, sig, dtype=np.float64).sum(axis=0) if len(T)
              else np.zeros((2, 6)))
    rays_have = vis_plan.sum(axis=0)
    eyes_plan = [T[vis_plan[:, k], :3, 3] for k in range(2)]
    ids = list(part.targets.ids)
    doc = {"ends": [ids[a], ids[b]], "length_m": length, "certificate_sigma_m": sigma_cert,
           "requirement": {"length_sigma_max_m": budget, "end_along_sigma_max_m": end_req,
                           "network_best_decile_along_m": ref if np.isfinite(ref) else None,
                           "rays_min": need_rays, "azimuth_gap_max_deg": AZIMUTH_GAP_MAX_DEG,
                           "rays_counted": f"views with the end at least {BAR_MARGIN_FRAC:.0%} of the image inside "
                                           f"its border and its incidence {BAR_INCIDENCE_MARGIN_DEG:g} deg below the "
                                           "plan's limit",
                           "rule": f"each end's predicted sigma along the bar (limiting error propagation, the "
                                   f"search's image precision) <= the larger of {LENGTH_SHARE:g} x the certificate's "
                                   f"sigma / sqrt(2) and the best-measured {REFERENCE_QUANTILE:.0%} of the planned "
                                   f"targets along the bar; >= {RAYS_FACTOR} x min_rays rays per end; azimuth gap of "
                                   f"each end's views <= {AZIMUTH_GAP_MAX_DEG:g} deg"},
           "stations_added": [], "added_reasons": []}
    valid = np.asarray(valid, dtype=bool)
    db_vis = np.asarray(db.visible, dtype=bool)[:, ends] & valid[:, None]
    db_vis = trusted_views(intr, db.part_from_cam, xyz, normals, db_vis, inc_max)
    # candidates that see an end, reachable, and not one of the planned stations already
    dup = np.zeros(len(db.part_from_cam), dtype=bool)
    for Tp in T:
        dup |= np.all(np.abs(db.part_from_cam - Tp).reshape(len(dup), -1) < 1e-9, axis=1)
    cand_ok = valid & db_vis.any(axis=1) & ~dup
    doc["candidates_seeing_end"] = [int((valid & db_vis[:, k]).sum()) for k in range(2)]
    vi = np.flatnonzero(cand_ok)
    eyes_db = db.part_from_cam[:, :3, 3]
    # the best any choice can do: every candidate at once (information only grows; planning.augment's bound)
    info = np.zeros((len(cand_ok), 2, 6))
    if vi.size:
        info[vi] = target_information(intr, db.part_from_cam[vi], xyz, db_vis[vi], sig, dtype=np.float64)
    N_all = N_have + info[vi].sum(axis=0)
    rays_all = rays_have + db_vis[vi].sum(axis=0)
    bound = np.array([_along(N_all[k], u) if rays_all[k] >= min_rays else np.inf for k in range(2)])
    gap_all = [azimuth_gap_deg(np.concatenate([eyes_plan[k], eyes_db[vi][db_vis[vi, k]]]), xyz[k], normals[k])
               for k in range(2)]
    doc["best_achievable"] = {"along_sigma_m": [float(v) if np.isfinite(v) else None for v in bound],
                              "length_sigma_m": float(np.hypot(*bound)) if np.all(np.isfinite(bound)) else None,
                              "rays": [int(r) for r in rays_all], "azimuth_gap_deg": [float(g) for g in gap_all],
                              "with": "the planned stations and every reachable candidate that sees an end"}
    # the spread the cell allows: where no reachable candidate closes the gap to AZIMUTH_GAP_MAX_DEG (the robot
    # reaches the end from one side only), the widest gap the candidates allow (+ GAP_SLACK_DEG) is the goal
    gap_goal = tuple(max(AZIMUTH_GAP_MAX_DEG, g + GAP_SLACK_DEG) if g > AZIMUTH_GAP_MAX_DEG else AZIMUTH_GAP_MAX_DEG
                     for g in gap_all)
    doc["requirement"]["azimuth_gap_goal_deg"] = [float(g) for g in gap_goal]
    before = bar_facts(N_have, rays_have, eyes_plan, xyz, normals, u, budget, min_rays, gap_goal)
    doc.update(before=before.to_dict(), after=before.to_dict(), met=before.met)
    if before.met or not vi.size:
        return np.zeros(0, dtype=int), doc

    along = np.stack([u, u])
    rays_goal = np.minimum(need_rays, rays_all)
    req = np.maximum(end_req, np.where(np.isfinite(bound), BOUND_MARGIN * bound, end_req))
    used = lambda: np.isin(np.arange(len(cand_ok)), added)  # noqa: E731
    # first the fewest stations for the length and the rays together (planning.augment); where the cap does not
    # allow both (its pruning then keeps none), the rays first, stations that serve both ends preferred, and then
    # the fewest for the length with what is left, the requirement relaxed as far as the cap needs
    aug = plan_extra_stations(N_have, rays_have, req, info, db_vis, cand_ok, min_rays=int(max(rays_goal.min(), min_rays)),
                              max_new=MAX_BAR_STATIONS, along=along)
    added: list[int] = []
    reasons: dict[int, str] = {}
    N_now, rays_now = N_have.copy(), rays_have.copy()

    def take(c: int, why: str) -> None:
        nonlocal N_now, rays_now
        added.append(int(c))
        reasons[int(c)] = why
        N_now = N_now + info[c]
        rays_now = rays_now + db_vis[c]

    def eyes_of(k: int) -> np.ndarray:
        return np.concatenate([eyes_plan[k], eyes_db[[c for c in added if db_vis[c, k]]].reshape(-1, 3)])

    if aug.added.size and np.all(aug.met_after | ~aug.short):
        for c in aug.added:
            take(c, "sigma along the bar and rays of the ends (fewest stations, planning.augment)")
    while len(added) < MAX_BAR_STATIONS:  # ends short of their ray goal
        short = rays_now < rays_goal
        pool = np.flatnonzero(cand_ok & (db_vis & short[None]).any(axis=1) & ~used())
        if not short.any() or not pool.size:
            break
        serves = (db_vis[pool] & short[None]).sum(axis=1)
        pool = pool[serves == serves.max()]
        # among them the one that widens the ends' views most (the narrowest widest gaps), then the best length
        gap_sum = np.array([sum(azimuth_gap_deg(np.concatenate([eyes_of(k), eyes_db[i][None]]) if db_vis[i, k]
                                                else eyes_of(k), xyz[k], normals[k]) for k in range(2)) for i in pool])
        pool = pool[gap_sum <= gap_sum.min() + 1.0]
        c = int(pool[np.argmin([sum(_along(N_now[k] + info[i, k], u) for k in range(2)) for i in pool])])
        take(c, "rays of " + " and ".join(ids[ends[k]] for k in range(2) if short[k] and db_vis[c, k]))
    along_now = [_along(N_now[k], u) if rays_now[k] >= min_rays else np.inf for k in range(2)]
    if len(added) < MAX_BAR_STATIONS and any(along_now[k] > req[k] for k in range(2)):
        aug, req_used = _fewest(N_now, rays_now, req, info, db_vis, cand_ok & ~used(), min_rays, along,
                                MAX_BAR_STATIONS - len(added))
        for c in aug.added:
            take(c, "sigma along the bar (fewest stations, planning.augment)")
        if np.any(req_used > req):
            doc["relaxed_along_sigma_m"] = [float(v) for v in req_used]
    free = lambda k: np.flatnonzero(cand_ok & db_vis[:, k] & ~used())  # noqa: E731
    for k in range(2):  # spread: fill the widest azimuth gap of an end seen from one side, while it helps
        goal = gap_goal[k]
        while len(added) < MAX_BAR_STATIONS and free(k).size:
            eyes_k = eyes_of(k)
            gap = azimuth_gap_deg(eyes_k, xyz[k], normals[k]) if len(eyes_k) else 360.0
            if gap <= goal:
                break
            pool = free(k)
            gaps = np.array([azimuth_gap_deg(np.concatenate([eyes_k, eyes_db[i][None]]), xyz[k], normals[k])
                             for i in pool])
            if gaps.min() > gap - GAP_SLACK_DEG:
                break
            best = np.flatnonzero(gaps <= gaps.min() + 1e-9)
            c = int(pool[best[np.argmin([_along(N_now[k] + info[i, k], u) for i in pool[best]])]])
            take(c, f"azimuth spread of {ids[ends[k]]} (gap {gap:.0f} -> {gaps.min():.0f} deg)")
    doc["added_reasons"] = [reasons[c] for c in added]
    return np.asarray(added, dtype=int), doc


def finish_doc(doc: dict, part, intr, options, T: np.ndarray, visible: np.ndarray, station_ids: list[str],
               added_ids: list[str]) -> dict:
    """``doc`` with the check of the final network (``T``, ``visible``: every station, the added ones included)
    and, when the requirement is still missed, the one-line ``note`` with the best achievable."""
    a, b = (list(part.targets.ids).index(e) for e in doc["ends"])
    ends = np.array([a, b])
    xyz = np.asarray(part.targets.xyz, dtype=float)[ends]
    normals = np.asarray(part.targets.normals, dtype=float)[ends]
    u = (xyz[0] - xyz[1]) / np.linalg.norm(xyz[0] - xyz[1])
    vis = trusted_views(intr, T, xyz, normals, np.asarray(visible, dtype=bool)[:, ends], float(options.incidence_max_rad))
    N = target_information(intr, T, xyz, vis, options.image_sigma(ends),
                           dtype=np.float64).sum(axis=0)
    after = bar_facts(N, vis.sum(axis=0), [T[vis[:, k], :3, 3] for k in range(2)], xyz, normals, u,
                      doc["requirement"]["length_sigma_max_m"], int(options.min_rays),
                      doc["requirement"].get("azimuth_gap_goal_deg", (AZIMUTH_GAP_MAX_DEG,) * 2))
    doc = dict(doc, after=after.to_dict(), met=after.met,
               stations_added=[{"id": s, "why": w} for s, w in zip(added_ids, doc.pop("added_reasons", []))],
               ends_clear=ends_clear(part, ends))
    if not after.met:
        doc["note"] = bar_line(doc)
    return doc


#: a bar's end wants this many dot diameters of clear surface around it (decision 0042: 5 mm dots within 6 mm of
#: an edge were centred 0.64 um outward on average, those 10 mm or more away without a measurable shift)
CLEAR_DIAMETERS = 2.0


def ends_clear(part, ends) -> list[dict]:
    """Per end of a bar: the clear radius around it (:func:`planning.clear_area.clear_radius`, checked in steps of
    half a dot diameter up to :data:`CLEAR_DIAMETERS` diameters) and whether that is enough."""
    from planning.clear_area import clear_radius

    d = float(part.target_diameter_m)
    radii = 0.5 * d * np.arange(1, int(2 * CLEAR_DIAMETERS) + 1)
    idx = np.asarray(ends, dtype=int)
    r = clear_radius(part.mesh, np.asarray(part.targets.xyz, dtype=float)[idx],
                     np.asarray(part.targets.normals, dtype=float)[idx], radii)
    out = []
    for k, v in zip(idx, r):
        beyond = radii[radii > v + 1e-12]  # the smallest disc that left the surface: an edge lies within it
        out.append({"target": str(part.targets.ids[k]), "clear_radius_m": float(v), "clear": not len(beyond),
                    "edge_within_m": float(beyond[0]) if len(beyond) else None})
    return out


def bar_line(doc: dict) -> str:
    """One line for the console and the journal: what the plan did for the bar, or why it falls short."""
    a, b = doc["ends"]
    req = doc["requirement"]
    bef, aft = doc["before"], doc["after"]
    um = lambda v: "inf" if v is None else f"{v * 1e6:.2f}"  # noqa: E731
    n = len(doc["stations_added"])
    head = (f"scale bar {a}-{b}: ends' part of the length sigma {um(bef['length_sigma_m'])} -> "
            f"{um(aft['length_sigma_m'])} um (required <= {um(req['length_sigma_max_m'])}), rays "
            f"{aft['rays'][0]}/{aft['rays'][1]} (>= {req['rays_min']}), azimuth gap "
            f"{aft['azimuth_gap_deg'][0]:.0f}/{aft['azimuth_gap_deg'][1]:.0f} deg "
            f"(<= {'/'.join(f'{g:.0f}' for g in req.get('azimuth_gap_goal_deg') or [req['azimuth_gap_max_deg']] * 2)}"
            f"{'' if max(req.get('azimuth_gap_goal_deg') or [0]) <= req['azimuth_gap_max_deg'] else ': the reachable stations see an end from one side only'}"
            f"); {n} station(s) added")
    if doc["met"]:
        return head
    best = doc.get("best_achievable") or {}
    seen = doc.get("candidates_seeing_end") or ["?", "?"]
    gaps = best.get("azimuth_gap_deg") or [360.0, 360.0]
    return (f"{head}; requirement NOT met, best achievable with every reachable candidate: length sigma "
            f"{um(best.get('length_sigma_m'))} um, rays {'/'.join(str(r) for r in best.get('rays') or ['?', '?'])}, "
            f"azimuth gap {gaps[0]:.0f}/{gaps[1]:.0f} deg ({seen[0]}/{seen[1]} reachable candidates see the ends"
            f"{'; at most ' + str(MAX_BAR_STATIONS) + ' stations are added for the bar' if n >= MAX_BAR_STATIONS else ''})")


def bar_warnings(doc: dict) -> list[tuple[str, str]]:
    """``(level, line)`` for the console and the journal: the bar's line (a warning when the requirement is not
    met), and a warning naming the bar when an end is seen by fewer than the rays it needs among the reachable
    candidates."""
    out = [("info" if doc["met"] else "warning", bar_line(doc))]
    need = doc["requirement"]["rays_min"]
    seen = doc.get("candidates_seeing_end") or []
    weak = [f"{t} ({n})" for t, n in zip(doc["ends"], seen) if n < need]
    if weak:
        out.append(("warning", f"scale bar {'-'.join(doc['ends'])}: end(s) {', '.join(weak)} seen by fewer than "
                               f"{need} reachable candidate stations: the scale rests on few rays"))
    near = [e for e in doc.get("ends_clear") or [] if not e["clear"]]
    if near:
        out.append(("warning", f"scale bar {'-'.join(doc['ends'])}: an edge of the part within "
                               + ", ".join(f"{e['edge_within_m'] * 1e3:.1f} mm of {e['target']}" for e in near)
                               + ": a dot there is centred off by what lies beyond the edge (outward, on average), "
                               "which the bar turns into a scale error of every target; put the bar's ends on a clear "
                               f"flat area ({CLEAR_DIAMETERS:g} dot diameters around each)"))
    return out


def rendered_rays_note(doc: dict, named: list[int]) -> list[tuple[str, str]]:
    """The pre-analysis's renders (PLAN renders the nominal part from every planned station and names the dots as
    MEASURE does) against the rays the bar counts on: records ``rendered_rays`` in ``doc`` and returns a warning
    naming each end the renders name in fewer than the rays it needs (the detector loses it where the geometry says
    it is seen: an edge, a shading step; its measurement, and the scale, then rest on the few views that keep it)."""
    doc["rendered_rays"] = [int(k) for k in named]
    need = doc["requirement"]["rays_min"]
    planned = (doc.get("after") or {}).get("rays") or [None, None]
    short = [f"{t} in {n} image(s) ({p} sure views planned)" for t, n, p in zip(doc["ends"], named, planned)
             if n < need]
    if not short:
        return []
    return [("warning", f"scale bar {'-'.join(doc['ends'])}: the renders of the plan name {', '.join(short)} "
                        f"(fewer than {need}): the detector loses the end where the geometry sees it, and the scale "
                        "rests on the views that keep it; a bar end with clear surroundings, or [planning] "
                        "closed_loop, measures better")]


def covariance_with(intr, options, part, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fresh ray casting and covariance of a network ``T: (k, 4, 4)``, as the planner's exact check."""
    visible = compute_visibility(part, intr, T, options.visibility_options(), backend=options.backend)
    cov, n_rays = covariance_for_network(intr, T, part.targets.xyz, visible, options.image_sigma(),
                                         min_rays=options.min_rays)
    return visible, cov, n_rays
