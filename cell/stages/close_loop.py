"""CLOSE_LOOP: the cell checks what it measured against what it was asked for, and fixes it while the
part is still in the cell.

After ADJUST, each target's achieved sigma (sqrt(trace(cov)) of the bundle) is compared with its
requirement (``[planning] required_sigma``, or tolerance / 10 as in cheapest mode). Targets that miss it,
or were not measured, go back to the planner with the stations already taken held fixed at the
information the adjustment achieved (:mod:`planning.augment`): it picks the fewest extra stations among
the candidates the robot reaches without collision (the same visibility and reachability databases as
PLAN), with the measured interior orientation and image precision, or proves that no reachable station
can bring a target within its requirement. The new stations are validated (IK, collisions, order),
acquired, measured and oriented like the others, and the whole network is adjusted again. Up to
``[planning] closed_loop_rounds`` rounds.

Resumable like every stage: a round's stations are written into plan.json and its record into
closed_loop.json (status "planned") before the robot moves; a resumed job goes on with the stations of
that round that were not yet taken. closed_loop.json holds every round (targets short, stations added,
targets fixed, time) and every target that still misses, with the reason.
"""
from __future__ import annotations

import time

import numpy as np

from calibration.camera import Intrinsics
from calibration.errors import ReachabilityError
from cell.record.jobfolder import atomic_write_json
from cell.stages.acquire import run as acquire_run
from cell.stages.adjust import run as adjust_run
from cell.stages.calibrate import run as calibrate_run
from cell.stages.measure import run as measure_run
from cell.stages.screen import LINK_TARGETS

NAME = "closed_loop.json"


def _requirement(job) -> np.ndarray:
    from cell.setup import planner_options
    from planning.planner import required_sigma

    return required_sigma(job.part, planner_options(job))


def stated_requirement(job) -> tuple[np.ndarray | None, str]:
    """Each target's required sigma (m) when the job states a requirement, and where it comes from; ``(None, "")``
    when it states none. Stated: ``[planning] required_sigma``, ``mode = "cheapest"`` (tolerance / 10), or the closed
    loop asked for. The closed loop being off does not drop it: REPORT checks it all the same (decision 0070)."""
    p = job.spec.planning
    if p.required_sigma is None and p.mode != "cheapest" and not p.closed_loop_on():
        return None, ""
    source = ("[planning] required_sigma" if p.required_sigma is not None
              else "tolerance / 10 (the targets file or [report] tolerance)")
    return _requirement(job), source


def requirement_doc(job, required, source: str, achieved: np.ndarray, ok: np.ndarray, judged: np.ndarray,
                    targets: list[dict]) -> dict | None:
    """report.json ``precision_requirement`` (None when the job states none), and each judged target's
    ``required_sigma_m`` and ``required_met`` (set on ``targets``, report.json's target dicts). Judged on the
    report's ``achieved_sigma_m`` (the sigma every record shows); a target not measured is not met."""
    if required is None:
        return None
    ids = list(job.part.targets.ids)
    where = {tid: k for k, tid in enumerate(ids)}
    with np.errstate(invalid="ignore"):
        met = ok & (achieved <= required * (1 + 1e-9))
    for t in targets:
        j = where[t["id"]]
        t["required_sigma_m"], t["required_met"] = float(required[j]), bool(met[j])
    short = [ids[j] for j in np.flatnonzero(judged & ok & ~met)]
    uniform = bool(np.allclose(required, required[0]))
    return {"required_sigma_m": float(required[0]) if uniform else None, "source": source,
            "closed_loop": bool(job.spec.planning.closed_loop_on()), "judged_on": "achieved_sigma_m",
            "n_judged": int(judged.sum()), "n_met": int((judged & met).sum()), "short": short,
            "not_measured": [ids[j] for j in np.flatnonzero(judged & ~ok)]}


def _achieved(bundle: dict, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per target: covariance (n, 3, 3) (nan where not measured), sigma (inf where not measured), rays."""
    cov = np.full((n, 3, 3), np.nan)
    rays = np.zeros(n, dtype=int)
    for t, rec in enumerate(bundle["targets"][:n]):
        c = np.asarray(rec.get("cov") if rec.get("cov") is not None else np.full((3, 3), np.nan), dtype=float)
        if c.shape == (3, 3):
            cov[t] = c
        rays[t] = int(rec.get("n_images", 0))
    tr = np.trace(cov, axis1=1, axis2=2)
    sigma = np.where(np.isfinite(tr) & (tr > 0), np.sqrt(np.where(tr > 0, tr, 0.0)), np.inf)
    return cov, sigma, rays


def _short(sigma: np.ndarray, rays: np.ndarray, required: np.ndarray, min_rays: int, judged: np.ndarray) -> np.ndarray:
    """Targets judged (not coded identification aids) whose sigma or rays miss the requirement."""
    return judged & ~((sigma <= required) & (rays >= min_rays))


def _scale_ends(job, bundle: dict) -> np.ndarray:
    """(n,) bool: the scale bars' ends while the last adjustment could not establish the scale (bundle.json
    ``screening.scale_established`` false: no bar left, each with an end without two usable rays, or data snooping
    took them below two, or unlike its ellipse). They are short whatever their sigma: the round plans fresh rays for
    them (decision 0030); every bar's, as any one bar that comes back establishes the scale. A bar left out while
    another kept the scale is not chased (its reason is in bundle.json ``scale_bars``)."""
    out = np.zeros(len(job.part.targets.ids), dtype=bool)
    if job.scale_bars and (bundle.get("screening") or {}).get("scale_established") is False:
        for bar in job.scale_bars:
            out[list(bar[:2])] = True
    return out


def _judged(job) -> np.ndarray:
    return np.asarray(job.part.targets.kind) != "coded"


#: a candidate looks at a target within this angle of a direction from which the target was expected but
#: not seen: it is taken as blocked too (something the CAD does not have: a fixture, a clamp, glare)
BLOCKED_CONE_DEG = 15.0


def _blocked(ctx, db, opts, cols: np.ndarray) -> np.ndarray:
    """(m, len(cols)) candidates whose view of a target is presumed blocked by what the taken images showed.

    For every image taken, the targets the CAD says it measures (ray casting, the plan's limits) but that
    were not identified in it were hidden by something the plan does not know. A candidate whose
    direction to such a target lies within :data:`BLOCKED_CONE_DEG` of a direction it was missed from is
    not counted on for that target.
    """
    from planning.visibility import compute_visibility

    job = ctx.job
    obs = ctx.folder.read_json("observations.json")["images"]
    plan_doc = ctx.folder.read_json("plan.json")
    pfc = {s["id"]: np.asarray(s["part_from_cam"], dtype=float) for s in plan_doc["stations"]}
    stations = [o["station"] for o in obs if o["station"] in pfc]
    out = np.zeros((len(db.part_from_cam), len(cols)), dtype=bool)
    if not stations or cols.size == 0:
        return out
    T = np.array([pfc[s] for s in stations])
    expected = compute_visibility(job.part, job.intrinsics, T, opts.visibility_options(), backend=opts.backend)[:, cols]
    where = {tid: k for k, tid in enumerate(job.part.targets.ids)}
    col_of = {int(t): j for j, t in enumerate(cols)}
    xyz = job.part.targets.xyz[cols]
    eyes = db.part_from_cam[:, :3, 3]
    cos_cone = np.cos(np.deg2rad(BLOCKED_CONE_DEG))
    for k, o in enumerate(obs):
        if o["station"] not in pfc:
            continue
        seen = np.zeros(len(cols), dtype=bool)
        for tid in o["ids"]:
            j = col_of.get(where.get(tid, -1))
            if j is not None:
                seen[j] = True
        for j in np.flatnonzero(expected[k] & ~seen):
            d_miss = T[k][:3, 3] - xyz[j]
            d_miss /= np.linalg.norm(d_miss)
            d_c = eyes - xyz[j]
            d_c /= np.linalg.norm(d_c, axis=1, keepdims=True)
            out[:, j] |= d_c @ d_miss >= cos_cone
    return out


#: a closed-loop station must see this many targets the adjustment measured (the screening's link)
LINK_STATION = LINK_TARGETS
#: a learned incidence limit needs this share of the dots expected beyond it to have been lost
LOST_SHARE = 0.8


def learned_incidence_limit(ctx, opts) -> tuple[float | None, dict]:
    """The incidence (rad) beyond which the taken images lost their dots (glare, a dot type the detector loses
    when tilted), or None when they did not: the planner's limit stands.

    For every image taken, the targets the CAD says it sees within the plan's limits and whether they were
    named. ``a`` is the 98th percentile of the incidences of the named ones; when at least
    :data:`LOST_SHARE` of the expected dots beyond ``a`` (and 20 or more of them) were lost, ``a`` is the limit.
    Returns ``(limit or None, facts)``.
    """
    from planning.visibility import compute_visibility

    job = ctx.job
    obs = ctx.folder.read_json("observations.json")["images"]
    pfc = {s["id"]: np.asarray(s["part_from_cam"], dtype=float) for s in ctx.folder.read_json("plan.json")["stations"]}
    obs = [o for o in obs if o["station"] in pfc]
    if not obs:
        return None, {}
    T = np.array([pfc[o["station"]] for o in obs])
    t = job.part.targets
    expected = compute_visibility(job.part, job.intrinsics, T, opts.visibility_options(), backend=opts.backend)
    where = {tid: k for k, tid in enumerate(t.ids)}
    seen = np.zeros_like(expected)
    for k, o in enumerate(obs):
        seen[k, [where[i] for i in o["ids"] if i in where]] = True
    to_cam = T[:, None, :3, 3] - t.xyz[None]
    inc = np.arccos(np.clip(np.einsum("mnk,nk->mn", to_cam, t.normals) / np.linalg.norm(to_cam, axis=2), -1, 1))
    judged = (t.code < 0)[None]
    named = inc[expected & seen & judged]
    if len(named) < 20:
        return None, {}
    a = float(np.quantile(named, 0.98))
    beyond = expected & judged & (inc > a)
    lost = float(np.mean(~seen[beyond])) if beyond.any() else 0.0
    facts = {"incidence_named_p98_deg": float(np.degrees(a)), "expected_beyond": int(beyond.sum()),
             "lost_share_beyond": lost}
    if beyond.sum() >= 20 and lost >= LOST_SHARE:
        return a, facts
    return None, facts


def _incidence(db, xyz: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(m, k) incidence (rad) of targets ``xyz: (k, 3)`` from the candidates of ``db``."""
    d = db.part_from_cam[:, None, :3, 3] - xyz[None]
    return np.arccos(np.clip(np.einsum("mkc,kc->mk", d, normals) / np.linalg.norm(d, axis=2), -1, 1))


def _plan_round(ctx, rnd: int, bundle: dict, required: np.ndarray, exclude: set[int]) -> tuple[list[dict], dict]:
    """Choose and validate this round's extra stations; returns their plan.json entries and the round's facts."""
    from cell.setup import collision_world, planner_options
    from cell.stages.plan import load_databases
    from planning.augment import information_from_covariance, plan_extra_stations
    from planning.execution import MotionLimits, apply_to_plan, validate_plan
    from planning.uncertainty import target_information
    from planning.visibility import default_cache_dir

    job = ctx.job
    p = job.spec.planning
    opts = planner_options(job)
    n = len(job.part.targets.ids)
    cov, sigma, rays = _achieved(bundle, n)
    ends = _scale_ends(job, bundle)
    short = _short(sigma, rays, required, p.min_rays, _judged(job)) | ends
    rays = np.where(ends, 0, rays)  # the scale bar's ends get min_rays fresh rays, as if unmeasured
    db, reach, robot = load_databases(job, opts, default_cache_dir(), lambda s, f: None)
    intr = Intrinsics.from_dict(bundle["intrinsics"]) if bundle.get("intrinsics") else job.intrinsics
    sigma_px = float(bundle.get("sigma0_px") or job.spec.camera.sigma_px)
    sigma_px = max(sigma_px, 1e-3)
    cols = np.flatnonzero(short)
    visible = db.visible[:, cols] & ~_blocked(ctx, db, opts, cols)
    limit, inc_facts = learned_incidence_limit(ctx, opts)
    if limit is not None:  # the images lost their dots beyond it: candidates must see the targets within it
        visible &= _incidence(db, job.part.targets.xyz[cols], job.part.targets.normals[cols]) <= limit
    valid = reach.reachable & visible.any(axis=1)
    # a new image must tie into the measured network (the adjustment leaves out images not linked to its main
    # block): candidates that see fewer than LINK_STATION measured targets within the limits are no use
    measured_all = np.isfinite(sigma) & (rays >= 2)
    if measured_all.any():
        seen_all = db.visible[:, measured_all]
        if limit is not None:
            t = job.part.targets
            seen_all &= _incidence(db, t.xyz[measured_all], t.normals[measured_all]) <= limit
        valid &= seen_all.sum(axis=1) >= LINK_STATION
    refused = _refused_candidates(ctx, db)
    for i in exclude | refused:
        valid[i] = False
    N6, measured = information_from_covariance(cov[cols])
    measured &= ~ends[cols]
    info = np.zeros((len(valid), len(cols), 6), dtype=np.float32)
    vi = np.flatnonzero(valid)
    if vi.size:
        info[vi] = target_information(intr, db.part_from_cam[vi], job.part.targets.xyz[cols], visible[vi], sigma_px)
    aug = plan_extra_stations(np.where(measured[:, None], N6, 0.0), np.where(measured, rays[cols], 0),
                              required[cols], info, visible, valid, min_rays=p.min_rays,
                              max_new=p.closed_loop_max_stations)
    ids = list(job.part.targets.ids)
    facts = {"round": rnd, "targets_short": [ids[int(t)] for t in cols],
             "sigma_short_m": [float(s) if np.isfinite(s) else None for s in sigma[cols]],
             "required_short_m": [float(r) for r in required[cols]],
             "targets_no_station_can_fix": [ids[int(cols[j])] for j in np.flatnonzero(aug.unreachable)],
             "bound_sigma_m": {ids[int(cols[j])]: (float(aug.bound_sigma[j]) if np.isfinite(aug.bound_sigma[j])
                                                  else None) for j in np.flatnonzero(aug.unreachable)},
             "predicted_fixed": [ids[int(cols[j])] for j in np.flatnonzero(aug.met_after & aug.short)],
             # what the round's stations are predicted to give the targets they can help (decision 0070: compared
             # with what the round achieved)
             "predicted_sigma_m": {ids[int(cols[j])]: float(aug.sigma_after[j])
                                   for j in np.flatnonzero(aug.short & ~aug.unreachable)
                                   if np.isfinite(aug.sigma_after[j])},
             "stopped": aug.facts.get("stopped"), "max_stations": int(p.closed_loop_max_stations),
             "candidates_refused_excluded": sorted(int(i) for i in refused),
             "image_sigma_px": sigma_px, "candidates_valid": int(valid.sum()),
             "candidate_rule": (f"reachable without collision, seeing it within the plan's limits"
                                + ("" if limit is None else f" and within the {np.degrees(limit):.1f} deg incidence "
                                   "beyond which the images lost their dots")
                                + f", and seeing {LINK_STATION} measured targets to tie into the network"),
             "incidence_limit_learned_deg": None if limit is None else float(np.degrees(limit)),
             "incidence_evidence": inc_facts}
    if aug.added.size == 0:
        return [], facts
    # validate the new stations for the robot: IK branch, collision-free moves, order, from where the arm is now
    # (not the last planned station: it may have been skipped, or a resumed session may have stopped elsewhere)
    if ctx.devices is None:
        from cell.devices import open_devices

        ctx.devices = open_devices(ctx.job, ctx.backend)
    here_q = np.asarray(ctx.devices.robot.state().joints_rad, dtype=float)
    new_ids = [f"L{rnd}-{k + 1:02d}" for k in range(len(aug.added))]
    c = job.spec.cell
    limits = MotionLimits(joint_speed_rad_s=c.max_joint_speed_rad_s, joint_accel_rad_s2=c.max_joint_accel_rad_s2,
                          settle_s=c.settle_s)
    pfc = db.part_from_cam[aug.added]
    try:
        ep = validate_plan(robot, pfc, job.spec.base_from_part(), job.spec.flange_from_cam(), collision_world(job),
                           limits, start_q=here_q, ids=new_ids)
    except ReachabilityError as exc:
        facts["validation_failed"] = str(exc)
        facts["excluded"] = [int(i) for i in aug.added]
        return [], facts
    sub = apply_to_plan({"stations": [{"id": sid, "part_from_cam": T.tolist()} for sid, T in zip(new_ids, pfc)]}, ep)
    base = max(int(s["order"]) for s in ctx.folder.read_json("plan.json")["stations"]) + 1
    stations = [dict(s, order=base + int(s["order"]), round=rnd, candidate=int(i), validated_from_q=here_q.tolist())
                for s, i in zip(sub["stations"], aug.added)]
    facts["stations_added"] = new_ids
    facts["stations_planned"] = new_ids
    facts["validated_from_q"] = here_q.tolist()  # the round's first move was checked from here (decision 0070)
    facts["cycle_time_s"] = float(ep.cycle_time_s)
    return stations, facts


def _refused_candidates(ctx, db) -> set[int]:
    """Candidates of the stations the robot refused in this job (journal ``station_skipped``): a loop station by its
    ``candidate``, a planned one by its pose. They are not chosen again (decision 0070: they were, every round)."""
    skipped = {r["station"] for r in ctx.folder.records() if r["event"] == "station_skipped"}
    out: set[int] = set()
    for st in ctx.folder.read_json("plan.json")["stations"]:
        if st["id"] not in skipped:
            continue
        if st.get("candidate") is not None:
            out.add(int(st["candidate"]))
        else:
            T = np.asarray(st["part_from_cam"], dtype=float)
            out |= set(int(i) for i in np.flatnonzero(np.all(np.abs(db.part_from_cam - T) < 1e-6, axis=(1, 2))))
    return out


def _plan_stations(ctx) -> list[dict]:
    """plan.json's stations, refused loudly when one id is there twice (decision 0070)."""
    from cell.stages.calibrate import refuse_duplicates

    stations = ctx.folder.read_json("plan.json")["stations"]
    refuse_duplicates("plan.json", "station", [s["id"] for s in stations])
    return stations


def _commit_round(ctx, doc: dict, path, rec: dict) -> None:
    """Put a round's stations into plan.json: only those not there yet (a kill between the two writes leaves them
    there, or not), then mark the round planned. closed_loop.json holds the round's intent (status "planning" and
    its stations) before plan.json is written, so a kill at any point resumes without re-planning it under the same
    ids (decision 0070)."""
    plan_doc = ctx.folder.read_json("plan.json")
    have = {s["id"]: s for s in plan_doc["stations"]}
    for st in rec.get("stations", []):
        old = have.get(st["id"])
        if old is not None and old.get("candidate") != st.get("candidate"):
            from calibration.errors import RecordError

            raise RecordError(f"plan.json station {st['id']} is candidate {old.get('candidate')}, closed_loop.json's "
                              f"round {rec['round']} says {st.get('candidate')}: the record is damaged")
    new = [st for st in rec.get("stations", []) if st["id"] not in have]
    if new:
        plan_doc["stations"] = plan_doc["stations"] + new
        atomic_write_json(ctx.folder.file("plan.json"), plan_doc)
    rec["status"] = "planned"
    atomic_write_json(path, doc)


def _recovered_round(ctx, rnd: int, stations: list[dict], short_ids: list[str]) -> dict | None:
    """A round whose stations are in plan.json but not in closed_loop.json (a kill between the two writes of a job
    recorded before decision 0070): taken as planned, not planned again under the same ids."""
    mine = [s for s in stations if s.get("round") == rnd]
    if not mine:
        return None
    sids = [s["id"] for s in mine]
    ctx.log.log("warning", f"closed loop round {rnd}: its stations {', '.join(sids)} are in plan.json but the round "
                           "was not recorded (a kill between the two writes); going on with them")
    return {"round": rnd, "status": "planned", "targets_short": short_ids, "stations_added": sids,
            "stations_planned": sids, "recovered_from_plan": True, "predicted_fixed": [], "predicted_sigma_m": {}}


def run(ctx) -> None:
    """CLOSE_LOOP: rounds of extra stations until every target meets its requirement (see the module)."""
    job = ctx.job
    p = job.spec.planning
    if not p.closed_loop_on():
        atomic_write_json(ctx.folder.file(NAME), {"enabled": False})
        return
    required = _requirement(job)
    n = len(job.part.targets.ids)
    ids = list(job.part.targets.ids)
    where = {tid: k for k, tid in enumerate(ids)}
    path = ctx.folder.file(NAME)
    doc = ctx.folder.read_json(NAME) if path.exists() else {"enabled": True, "rounds": []}
    if not doc.get("enabled"):
        doc = {"enabled": True, "rounds": []}
    uniform = bool(np.allclose(required, required[0]))
    doc["required_sigma_m"] = float(required[0]) if uniform else None
    exclude: set[int] = set()
    for rec in doc["rounds"]:
        exclude |= set(rec.get("excluded", []))
    while True:
        last = doc["rounds"][-1] if doc["rounds"] else None
        if last is not None and last.get("status") == "planning":  # killed between its two writes: finish them
            _commit_round(ctx, doc, path, last)
        pending = last if last is not None and last.get("status") == "planned" else None
        if pending is None:
            done_rounds = sum(1 for r in doc["rounds"] if r.get("status") == "done")
            bundle = ctx.folder.read_json("bundle.json")
            _, sigma, rays = _achieved(bundle, n)
            short = _short(sigma, rays, required, p.min_rays, _judged(job)) | _scale_ends(job, bundle)
            if not short.any() or done_rounds >= p.closed_loop_rounds:
                break
            t0 = time.perf_counter()
            ctx.progress("close_loop", 0.0)
            rnd = done_rounds + 1
            pending = _recovered_round(ctx, rnd, _plan_stations(ctx), [ids[int(t)] for t in np.flatnonzero(short)])
            if pending is not None:
                doc["rounds"].append(pending)
                atomic_write_json(path, doc)
        if pending is None:
            stations, facts = _plan_round(ctx, rnd, bundle, required, exclude)
            if "excluded" in facts:  # the robot could not take them after all: plan again without them
                exclude |= set(facts["excluded"])
                msg = (f"closed loop round {rnd}: the robot cannot take the chosen stations "
                       f"({facts['validation_failed']}); planning again without them")
                ctx.log.log("warning", msg)
                ctx.say(f"  WARNING {msg}")
                doc["rounds"].append(facts | {"status": "failed validation", "time_s": time.perf_counter() - t0})
                atomic_write_json(path, doc)
                if len([r for r in doc["rounds"] if r.get("status") == "failed validation"]) > 3:
                    break
                continue
            if not stations:
                k = len(facts["targets_short"])
                msg = (f"round {rnd}: no reachable station can bring the {k} target(s) short within their requirement "
                       "(the bound: every reachable candidate added)" if facts.get("stopped") == "unreachable" else
                       f"round {rnd}: no single reachable station improves the {k} target(s) short")
                ctx.log.log("warning", f"closed loop {msg}")
                ctx.say(f"  {msg}")
                doc["rounds"].append(facts | {"status": "nothing to add", "stations_added": [], "targets_fixed": [],
                                              "time_s": time.perf_counter() - t0})
                atomic_write_json(path, doc)
                break
            # the round's intent first (closed_loop.json, with its stations), then plan.json: a kill between the writes
            # resumes with the round, never plans it again under the same ids (decision 0070)
            pending = facts | {"status": "planning", "stations": stations,
                               "planning_time_s": time.perf_counter() - t0}
            doc["rounds"].append(pending)
            atomic_write_json(path, doc)
            _commit_round(ctx, doc, path, pending)
            ctx.log.log("info", f"closed loop round {rnd}: {len(stations)} station(s) for "
                                f"{len(facts['targets_short'])} target(s) short")
            ctx.say(f"  round {rnd}: {len(facts['targets_short'])} target(s) short of the requirement; "
                    f"{len(stations)} extra station(s) {', '.join(facts['stations_added'])}"
                    + (f" (more would help: at most [planning] closed_loop_max_stations = {p.closed_loop_max_stations} "
                       "per round)" if facts.get("stopped") == "max_new" else ""))
        _plan_stations(ctx)  # refuses a plan.json that lists a station twice
        # take, measure, orient the round's stations, then adjust the whole network again
        t1 = time.perf_counter()
        acquire_run(ctx)
        measure_run(ctx, keep=True)
        calibrate_run(ctx)
        adjust_run(ctx)
        bundle = ctx.folder.read_json("bundle.json")
        _, sigma, rays = _achieved(bundle, n)
        now_short = _short(sigma, rays, required, p.min_rays, _judged(job)) | _scale_ends(job, bundle)
        fixed = [t for t in pending["targets_short"] if not now_short[where[t]]]
        _settle_round(ctx, pending, sigma, now_short, where)
        pending.update(status="done", targets_fixed=fixed,
                       time_s=pending.get("planning_time_s", 0.0) + time.perf_counter() - t1)
        atomic_write_json(path, doc)
        ctx.say(f"  round {pending['round']}: {len(fixed)} of {len(pending['targets_short'])} target(s) now within "
                "the requirement")
    _unmet(ctx, doc, path, required, n)


def _settle_round(ctx, pending: dict, sigma: np.ndarray, now_short: np.ndarray, where: dict) -> None:
    """After a round's acquisition: only the stations whose image was taken count as added; those the robot refused
    are listed apart with the reason; the round's prediction against what it achieved (decision 0070)."""
    taken = {a["station"] for a in ctx.folder.read_json("acquisition.json")["images"]}
    skipped = {r["station"]: r["reason"] for r in ctx.folder.records() if r["event"] == "station_skipped"}
    planned = pending.get("stations_planned", pending.get("stations_added", []))
    cand = {s["id"]: s.get("candidate") for s in pending.get("stations", [])}
    pending["stations_added"] = [s for s in planned if s in taken]
    pending["stations_refused"] = [{"id": s, "candidate": cand.get(s), "reason": skipped.get(s, "not taken")}
                                   for s in planned if s not in taken]
    if pending["stations_refused"]:
        msg = (f"closed loop round {pending['round']}: {len(pending['stations_refused'])} of {len(planned)} station(s) "
               f"not taken: " + "; ".join(f"{r['id']} ({r['reason']})" for r in pending["stations_refused"][:4])
               + "; their candidates are not chosen again")
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")
    pred = pending.get("predicted_sigma_m") or {}
    pending["achieved_sigma_m"] = {t: (float(sigma[where[t]]) if np.isfinite(sigma[where[t]]) else None) for t in pred}
    missed = [t for t in pending.get("predicted_fixed", []) if now_short[where[t]]]
    pending["prediction_missed"] = missed
    if missed:
        def um(v):
            return "not measured" if v is None or not np.isfinite(v) else f"{v * 1e6:.2f} um"
        msg = (f"closed loop round {pending['round']}: the prediction did not hold for {len(missed)} of the "
               f"{len(pending.get('predicted_fixed', []))} target(s) it meant to bring within the requirement"
               + (" (stations refused)" if pending["stations_refused"] else "") + ": "
               + ", ".join(f"{t} predicted {um(pred.get(t))}, achieved {um(pending['achieved_sigma_m'].get(t))}"
                           for t in missed[:6]) + (" ..." if len(missed) > 6 else ""))
        ctx.log.log("warning", msg)
        ctx.say(f"  WARNING {msg}")


def _unmet(ctx, doc: dict, path, required: np.ndarray, n: int) -> None:
    """What still misses after the loop, and why (the bound, too few rays, refused stations, the per-round limit,
    a prediction that failed, or the round limit); closed_loop.json ``unmet``, the console and the run log."""
    job = ctx.job
    p = job.spec.planning
    ids = list(job.part.targets.ids)
    bundle = ctx.folder.read_json("bundle.json")
    _, sigma, rays = _achieved(bundle, n)
    ends = _scale_ends(job, bundle)
    short = _short(sigma, rays, required, p.min_rays, _judged(job)) | ends
    proofs: dict[str, float | None] = {}
    rule: dict[str, str] = {}
    refused_for: dict[str, list[str]] = {}
    for r in doc["rounds"]:
        proofs.update(r.get("bound_sigma_m", {}))
        rule.update({tid: r.get("candidate_rule", "reachable") for tid in r.get("bound_sigma_m", {})})
        if r.get("stations_refused"):
            for tid in r.get("predicted_fixed", []) or r.get("targets_short", []):
                refused_for.setdefault(tid, []).extend(f"{x['id']}: {x['reason']}" for x in r["stations_refused"])
    planned = [r for r in doc["rounds"] if r.get("status") in ("done", "nothing to add")]
    last = planned[-1] if planned else {}
    n_rounds = sum(1 for r in doc["rounds"] if r.get("status") == "done")
    limit = f"after {n_rounds} round(s) (limit [planning] closed_loop_rounds = {p.closed_loop_rounds})"
    unmet = []
    for t in np.flatnonzero(short):
        tid = ids[int(t)]
        s_um = "not measured" if not np.isfinite(sigma[t]) else f"sigma {sigma[t] * 1e6:.1f} um"
        if ends[t] and not _short(sigma[t:t + 1], rays[t:t + 1], required[t:t + 1], p.min_rays, np.ones(1, bool))[0]:
            reason = f"scale not established: {bundle['screening'].get('scale')}"
        elif tid in proofs:
            b = proofs[tid]
            reason = ((f"no candidate station can measure it ({s_um}; candidates: {rule[tid]})") if b is None else
                      f"no reachable station can: with every reachable candidate added the best possible sigma is "
                      f"{b * 1e6:.1f} um > required {required[t] * 1e6:.1f} um ("
                      + (s_um if not np.isfinite(sigma[t]) else f"{s_um} achieved") + f"; candidates: {rule[tid]})")
        elif tid in refused_for:
            reason = (f"{s_um} > required {required[t] * 1e6:.1f} um: the robot refused the station(s) planned for it "
                      f"({'; '.join(refused_for[tid][:3])}); {limit}")
        elif rays[t] < p.min_rays:
            reason = f"{rays[t]} ray(s) of the {p.min_rays} required {limit}"
        elif last.get("stopped") == "max_new" and tid in last.get("targets_short", []) \
                and tid not in last.get("predicted_fixed", []):
            reason = (f"{s_um} > required {required[t] * 1e6:.1f} um: it needs more stations than [planning] "
                      f"closed_loop_max_stations = {p.closed_loop_max_stations} allow per round, {limit}")
        elif tid in last.get("prediction_missed", []):
            pv = (last.get("predicted_sigma_m") or {}).get(tid)
            reason = (f"{s_um} > required {required[t] * 1e6:.1f} um: the round's stations were predicted to give "
                      f"{'?' if pv is None else f'{pv * 1e6:.1f}'} um (the prediction did not hold), {limit}")
        else:
            reason = f"{s_um} > required {required[t] * 1e6:.1f} um {limit}"
        unmet.append({"id": tid, "reason": reason, "sigma_m": float(sigma[t]) if np.isfinite(sigma[t]) else None,
                      "required_m": float(required[t])})
    doc["unmet"] = unmet
    atomic_write_json(path, doc)
    ctx.progress("close_loop", 1.0)
    added = sum(len(r.get("stations_added", [])) for r in doc["rounds"] if r.get("status") == "done")
    refused = sum(len(r.get("stations_refused", [])) for r in doc["rounds"])
    msg = (f"closed loop: {len(doc['rounds'])} round(s), {added} extra station(s) taken"
           + (f" ({refused} refused by the robot)" if refused else "") + "; "
           + (f"{len(unmet)} target(s) still short: " + ", ".join(u["id"] for u in unmet[:8])
              + (" ..." if len(unmet) > 8 else "") if unmet else "every target within its requirement"))
    ctx.log.log("warning" if unmet else "info", msg)
    ctx.say(f"  {msg}")
