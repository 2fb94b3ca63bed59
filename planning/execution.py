"""VALIDATE: turn a network of stations into an executable, collision-checked robot plan.

Steps (``validate_plan``):

1. Flange targets ``base_from_flange = base_from_part @ part_from_cam @ inv(flange_from_cam)``
   and every IK branch of each; branches outside the joint limits or in collision are
   dropped. A station with none left is a ReachabilityError naming it and why.
2. Order: the stations are toured in joint space from ``start_q`` (nearest neighbour, then
   2-opt) with the move time of a synchronised trapezoidal joint move as the distance.
3. Branches: for that order, a shortest path over the branches of every station (Viterbi)
   chooses the branch sequence with the least total move time, so the arm keeps its
   configuration unless changing it pays. Order and branches are refined in turn.
4. Every move (linear in joint space, as ``moveJ``) is checked for collisions: first all moves at
   once, sampled and checked with a wider security margin in one parallel call (``certify_moves``),
   then those it cannot prove free by conservative advancement: from each checked configuration the arm may move by the
   measured clearance before it can touch anything, bounded by the joint displacement
   times each joint's lever arm. A colliding move forbids that branch pair and step 3
   is repeated; if no branch pair works, a ReachabilityError names the move.
5. Cycle time: the sum of the move times plus a settle/capture time per station.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from calibration.errors import InputError, ReachabilityError
from planning.kinematics import CollisionWorld, RobotModel
from planning.reachability import branch_scores, flange_targets

__all__ = [
    "MotionLimits", "MoveCheck", "ExecutionPlan", "validate_plan", "move_time", "check_move", "certify_moves", "apply_to_plan",
    "stations_from_plan", "lever_arms",
]


@dataclass(frozen=True)
class MotionLimits:
    """The cell's motion limits for joint moves.

    Attributes:
        joint_speed_rad_s: scalar or (6,) joint speed used for moves (capped by the robot's
            own maxima). UR's moveJ default is 1.05 rad/s.
        joint_accel_rad_s2: scalar or (6,) joint acceleration (UR's moveJ default 1.4 rad/s^2).
        settle_s: time spent at each station (settling, strobe and capture).
        return_to_start: the cycle ends back at start_q.
        min_joint_margin_rad: branches closer than this to a joint limit are not used.
        check_resolution_rad: smallest joint step of the move collision check (where the
            clearance is smaller than the motion bound of this step, the check falls back
            to sampling at this step).
        certify_deltas_m: moves are first checked in batches with the security margin clearance +
            delta, sampled so that the arm moves at most delta / 2 between samples, for each delta in
            turn (:func:`certify_moves`); only moves that fail them all get the conservative-advancement check.
    """

    joint_speed_rad_s: float | Sequence[float] = 1.05
    joint_accel_rad_s2: float | Sequence[float] = 1.4
    settle_s: float = 0.5
    return_to_start: bool = True
    min_joint_margin_rad: float = 0.0
    check_resolution_rad: float = 0.005
    certify_deltas_m: tuple[float, ...] = (0.02, 0.005)


@dataclass(frozen=True)
class MoveCheck:
    """Collision check of one joint move.

    Attributes:
        start, end: labels of the endpoints ("start" or a station id).
        free: no collision along the move.
        min_distance_m: smallest clearance measured along the move (a move proven free by the batched
            check: the clearance it guarantees, clearance + delta / 2).
        pair: the closest (or colliding) pair of bodies.
        at_fraction: where along the move the smallest clearance (or the collision) was.
        n_checks: configurations checked.
        duration_s: move time under the motion limits.
    """

    start: str
    end: str
    free: bool
    min_distance_m: float
    pair: tuple[str, str]
    at_fraction: float
    n_checks: int
    duration_s: float


@dataclass(frozen=True)
class ExecutionPlan:
    """A validated plan.

    Attributes:
        ids: (k,) station ids, input order.
        order: (k,) station indices in visiting sequence.
        joints: (k, 6) joint targets (rad) per station, input order.
        base_from_flange: (k, 4, 4) flange targets per station, input order.
        branch: (k,) IK branch used per station.
        start_q: (6,) joints the cycle starts from.
        moves: MoveCheck per move in visiting sequence (start -> first ... [-> start]).
        cycle_time_s: estimated time of one cycle.
    """

    ids: list[str]
    order: np.ndarray
    joints: np.ndarray
    base_from_flange: np.ndarray
    branch: np.ndarray
    start_q: np.ndarray
    moves: list[MoveCheck] = field(default_factory=list)
    cycle_time_s: float = 0.0

    @property
    def rank(self) -> np.ndarray:
        """(k,) position of each station (input order) in the visiting sequence."""
        r = np.empty(len(self.order), dtype=int)
        r[self.order] = np.arange(len(self.order))
        return r

    @property
    def joint_path(self) -> np.ndarray:
        """(n, 6) the waypoints in visiting sequence, start_q first (and last if returning)."""
        path = [self.start_q] + [self.joints[i] for i in self.order]
        if self.moves and self.moves[-1].end == "start":
            path.append(self.start_q)
        return np.array(path)


# ----------------------------------------------------------------------------------------
# kernels
# ----------------------------------------------------------------------------------------


def move_time(dq: np.ndarray, speed: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """Duration (s) of synchronised trapezoidal joint moves.

    Each joint alone needs ``2 sqrt(d / a)`` (triangular profile, d < v^2 / a) or
    ``d / v + v / a``; a joint move lasts as long as its slowest joint.

    Args:
        dq: (..., 6) joint displacements (rad).
        speed, accel: (6,) limits.
    Returns:
        (...,) seconds.
    """
    d = np.abs(np.asarray(dq, dtype=float))
    tri = d < speed**2 / accel
    t = np.where(tri, 2.0 * np.sqrt(d / accel), d / speed + speed / accel)
    t = np.where(d > 0, t, 0.0)
    return np.max(t, axis=-1)


#: tours tried again, each with one more pair of nodes kept apart, when a move collides on every branch pair
MAX_RETOURS = 3
#: the cost (s) of a move the tour must not make
BANNED_MOVE_S = 1e6


def _two_opt(cost: np.ndarray, tour: list[int], closed: bool) -> list[int]:
    """Improve a tour over nodes 1..n starting at node 0 by 2-opt moves (cost: (n+1, n+1))."""
    path = [0] + tour + ([0] if closed else [])
    improved = True
    while improved:
        improved = False
        n = len(path)
        for i in range(1, n - 1):
            for j in range(i + 1, n if not closed else n - 1):
                a, b = path[i - 1], path[i]
                c = path[j]
                nxt = path[j + 1] if j + 1 < n else None
                before = cost[a, b] + (cost[c, nxt] if nxt is not None else 0.0)
                after = cost[a, c] + (cost[b, nxt] if nxt is not None else 0.0)
                if after < before - 1e-12:
                    path[i:j + 1] = path[i:j + 1][::-1]
                    improved = True
    return path[1:-1] if closed else path[1:]


def _tour(cost: np.ndarray, closed: bool) -> list[int]:
    """Nearest-neighbour tour from node 0 over nodes 1..n, then 2-opt."""
    n = cost.shape[0] - 1
    left = set(range(1, n + 1))
    tour, cur = [], 0
    while left:
        nxt = min(left, key=lambda j: (cost[cur, j], j))
        tour.append(nxt)
        left.remove(nxt)
        cur = nxt
    return _two_opt(cost, tour, closed)


def _viterbi(
    cand: list[np.ndarray], start_q: np.ndarray, closed: bool, speed: np.ndarray, accel: np.ndarray,
    forbidden: set[tuple[int, int, int]], wrap: bool,
) -> tuple[list[int], float]:
    """Cheapest branch per step along a fixed sequence.

    Args:
        cand: per step, (b_t, 6) candidate joints.
        forbidden: (step t, branch at t-1, branch at t) transitions known to collide
            (t = 0 is the move from the start, t = len(cand) the move back).
    Returns:
        chosen candidate index per step, total cost.
    """
    def dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        d = b[None, :, :] - a[:, None, :]
        if wrap:
            d = np.pi - np.mod(np.pi - d, 2 * np.pi)
        return move_time(d, speed, accel)

    prev = start_q[None]
    acc = np.zeros(1)
    back: list[np.ndarray] = []
    for t, c in enumerate(cand):
        step = acc[:, None] + dist(prev, c)
        for (ft, fa, fb) in forbidden:
            if ft == t:
                step[fa if t > 0 else 0, fb] = np.inf
        back.append(np.argmin(step, axis=0))
        acc = np.min(step, axis=0)
        prev = c
    if closed:
        last = dist(prev, start_q[None])[:, 0]
        for (ft, fa, _fb) in forbidden:
            if ft == len(cand):
                last[fa] = np.inf
        acc = acc + last
    j = int(np.argmin(acc))
    total = float(acc[j])
    chosen = [j]
    for t in range(len(cand) - 1, 0, -1):
        j = int(back[t][j])
        chosen.append(j)
    return chosen[::-1], total


def lever_arms(robot: RobotModel) -> np.ndarray:
    """(6,) bound on the distance of any robot or tool point from each joint's axis (m)."""
    p = robot.params
    tool = 0.0
    for t in robot.tools:
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * 0.5 * np.asarray(t.size_m)
        pts = corners @ t.flange_from_box[:3, :3].T + t.flange_from_box[:3, 3]
        tool = max(tool, float(np.max(np.linalg.norm(pts, axis=1))))
    r_max = max(p.radius_m) + p.shoulder_offset_m
    lengths = np.abs(np.asarray(p.a)) + np.abs(np.asarray(p.d))
    return np.array([lengths[i:].sum() for i in range(6)]) + tool + r_max


def check_move(
    robot: RobotModel, world: CollisionWorld, qa: np.ndarray, qb: np.ndarray, levers: np.ndarray,
    resolution_rad: float, labels: tuple[str, str], duration_s: float,
) -> MoveCheck:
    """Conservative-advancement collision check of the joint-linear move qa -> qb."""
    dq = qb - qa
    # any point moves at most sum_i lever_i |dq_i| * ds; two robot bodies may approach at twice that
    speed_bound = 2.0 * float(np.sum(levers * np.abs(dq)))
    max_dq = float(np.max(np.abs(dq)))
    min_ds = 1.0 if max_dq <= resolution_rad else resolution_rad / max_dq
    s, n = 0.0, 0
    best = (np.inf, ("", ""), 0.0)
    while True:
        rep = robot.check_collision(qa + s * dq, world)
        n += 1
        if rep.distance_m < best[0] or not rep.free:
            best = (rep.distance_m, rep.pair, s)
        if not rep.free:
            return MoveCheck(labels[0], labels[1], False, float(rep.distance_m), rep.pair, s, n, duration_s)
        if s >= 1.0:
            break
        room = rep.distance_m - world.clearance_m
        ds = room / speed_bound if speed_bound > 0 else 1.0
        s = min(1.0, s + max(ds, min_ds))
    return MoveCheck(labels[0], labels[1], True, float(best[0]), best[1], float(best[2]), n, duration_s)


def certify_moves(robot: RobotModel, world: CollisionWorld, starts: np.ndarray, ends: np.ndarray, levers: np.ndarray,
                  deltas_m: tuple[float, ...] = (0.02, 0.005), n_threads: int = 2
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Moves ``starts[t] -> ends[t]`` (joint-linear, (t, 6) each) proven free by batched checks.

    For each ``delta`` in turn (on the moves not yet proven), each move is sampled so finely that no
    point of the arm moves (relative to another body) by more than ``delta / 2`` between a
    configuration and its nearest sample (the motion bound of :func:`check_move`), and every sample
    is checked with the security margin ``clearance + delta`` in one parallel call. A move whose
    samples all pass keeps at least ``clearance + delta / 2`` everywhere; the others need
    :func:`check_move`. Returns (t,) proven, (t,) the clearance each guarantees (nan: not proven),
    (t,) samples checked.
    """
    qa = np.asarray(starts, dtype=float).reshape(-1, 6)
    dq = np.asarray(ends, dtype=float).reshape(-1, 6) - qa
    bound = 2.0 * np.abs(dq) @ levers
    proven = np.zeros(len(dq), dtype=bool)
    guaranteed = np.full(len(dq), np.nan)
    samples = np.zeros(len(dq), dtype=int)
    for delta in deltas_m:
        todo = np.flatnonzero(~proven)
        if len(todo) == 0:
            break
        n = np.maximum(2, np.ceil(bound[todo] / delta).astype(int) + 1)
        owner = np.repeat(np.arange(len(todo)), n)
        s = np.concatenate([np.linspace(0.0, 1.0, k) for k in n])
        q = qa[todo][owner] + s[:, None] * dq[todo][owner]
        free = robot.collision_free_many(q, world, n_threads=n_threads, margin_m=world.clearance_m + delta)
        ok = np.bincount(owner, weights=~free, minlength=len(todo)) == 0
        samples[todo] += n
        proven[todo[ok]] = True
        guaranteed[todo[ok]] = world.clearance_m + 0.5 * delta
    return proven, guaranteed, samples


# ----------------------------------------------------------------------------------------
# validate_plan
# ----------------------------------------------------------------------------------------


def validate_plan(
    robot: RobotModel,
    part_from_cam: np.ndarray,
    base_from_part: np.ndarray,
    flange_from_cam: np.ndarray,
    world: CollisionWorld | None,
    limits: MotionLimits | None = None,
    start_q: np.ndarray | None = None,
    ids: Sequence[str] | None = None,
    max_repairs: int = 20,
) -> ExecutionPlan:
    """Choose IK branches and an order for the stations, check the moves, time the cycle.

    Args:
        robot: the arm with its tool boxes.
        part_from_cam: (k, 4, 4) stations.
        base_from_part: (4, 4) part placement.
        flange_from_cam: (4, 4) hand-eye.
        world: the cell (part, table, obstacles); None skips collision checks.
        limits: motion limits (speed, acceleration, settle time).
        start_q: (6,) joints at the start of the cycle (default: arm up, camera down).
        ids: (k,) station labels for messages (default "S0", "S1", ...).
    Returns:
        ExecutionPlan.
    Raises:
        ReachabilityError: a station has no IK branch within the limits and free of
            collision, or a move collides whatever the branches.
        InputError: malformed arguments.
    """
    lim = limits or MotionLimits()
    pfc = np.asarray(part_from_cam, dtype=float)
    if pfc.ndim != 3 or pfc.shape[1:] != (4, 4) or len(pfc) == 0:
        raise InputError(f"validate_plan needs (k, 4, 4) stations, got shape {pfc.shape}")
    k = len(pfc)
    ids = [f"S{i}" for i in range(k)] if ids is None else [str(x) for x in ids]
    if len(ids) != k:
        raise InputError(f"{len(ids)} station ids for {k} stations")
    start = np.array([0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0]) if start_q is None else np.asarray(start_q, dtype=float)
    if not robot.within_limits(start):
        raise InputError(f"start joints {np.round(start, 3).tolist()} are outside the joint limits of the {robot.name}")
    speed = np.minimum(np.broadcast_to(np.asarray(lim.joint_speed_rad_s, dtype=float), (6,)), robot.max_velocity)
    accel = np.broadcast_to(np.asarray(lim.joint_accel_rad_s2, dtype=float), (6,))
    if np.any(speed <= 0) or np.any(accel <= 0):
        raise InputError(f"joint speed and acceleration limits must be positive, got {speed} / {accel}")

    if world is not None:
        rep = robot.check_collision(start, world)
        if not rep:
            raise ReachabilityError(
                f"start configuration collides ({rep.pair[0]} vs {rep.pair[1]}): move the robot or give another start_q"
            )

    # 1. candidate branches per station
    bff = flange_targets(base_from_part, pfc, flange_from_cam)
    sol = robot.ik_many(bff, q_ref=start)
    margin = robot.joint_margin(np.where(sol.exists[..., None], sol.q, 0.0))
    ok = sol.within_limits & (margin >= lim.min_joint_margin_rad)
    free = np.zeros_like(ok)
    if world is not None and ok.any():
        free[ok] = robot.collision_free_many(sol.q[ok], world)
    else:
        free = ok.copy()
    problems = []
    for i in range(k):
        if free[i].any():
            continue
        if not sol.within_limits[i].any():
            why = f"no IK solution ({sol.failure[i]})" if not sol.exists[i].any() else "every IK branch is outside the joint limits"
        elif not ok[i].any():
            why = f"every IK branch is closer than {lim.min_joint_margin_rad:.3f} rad to a joint limit"
        else:
            b = int(np.argmax(np.where(ok[i], branch_scores(robot, sol.q[i]), -np.inf)))
            rep = robot.check_collision(sol.q[i, b], world)
            why = f"every IK branch collides (best: {rep.pair[0]} vs {rep.pair[1]}, {rep.distance_m * 1000:.0f} mm)"
        problems.append(f"station {ids[i]}: {why}")
    if problems:
        raise ReachabilityError(
            "; ".join(problems) + ". Move the part (base_from_part), remove obstacles, or re-plan with reachability."
        )
    branches = [np.flatnonzero(free[i]) for i in range(k)]
    cand = [sol.q[i, branches[i]] for i in range(k)]

    # 2-3. order and branch choice, refined in turn
    nodes_q = [start[None]] + cand
    # every branch of every node against every other at once: cost = the fastest pair of branches
    allq = np.concatenate(nodes_q)
    node = np.repeat(np.arange(k + 1), [len(c) for c in nodes_q])
    d = allq[None, :, :] - allq[:, None, :]
    pair = move_time(np.pi - np.mod(np.pi - d, 2 * np.pi), speed, accel)  # (B, B)
    first = np.searchsorted(node, np.arange(k + 1))  # nodes are contiguous runs of branches
    cost = np.minimum.reduceat(np.minimum.reduceat(pair, first, axis=0), first, axis=1)
    np.fill_diagonal(cost, 0.0)
    seq = [s - 1 for s in _tour(cost, lim.return_to_start)]
    forbidden: set[tuple[int, int, int]] = set()
    choice, _ = _viterbi([cand[s] for s in seq], start, lim.return_to_start, speed, accel, forbidden, wrap=True)
    for _ in range(2):
        chosen_nodes = np.zeros((k + 1, 6))
        chosen_nodes[0] = start
        for s, c in zip(seq, choice):
            chosen_nodes[s + 1] = cand[s][c]
        d = chosen_nodes[None] - chosen_nodes[:, None]
        cost2 = move_time(np.pi - np.mod(np.pi - d, 2 * np.pi), speed, accel)
        new_seq = [s - 1 for s in _two_opt(cost2, [s + 1 for s in seq], lim.return_to_start)]
        if new_seq == seq:
            break
        seq = new_seq
        choice, _ = _viterbi([cand[s] for s in seq], start, lim.return_to_start, speed, accel, forbidden, wrap=True)

    # 4. unwrap along the path and check every move; forbid colliding branch pairs
    levers = lever_arms(robot)
    proofs: dict[bytes, tuple] = {}  # move (joints at both ends) -> batched proof; exact: -> check_move
    exact: dict[bytes, MoveCheck] = {}
    retours = tries = 0  # tours made again; repairs of this tour
    for _attempt in range((MAX_RETOURS + 1) * (max_repairs + 1)):
        path = [start]
        for s, c in zip(seq, choice):
            path.append(robot.nearest_equivalent(cand[s][c], path[-1]))
        labels = ["start"] + [ids[s] for s in seq]
        if lim.return_to_start:
            path.append(start)
            labels.append("start")
        moves: list[MoveCheck] = []
        bad = None
        keys = [np.concatenate([path[t], path[t + 1]]).tobytes() for t in range(len(path) - 1)]
        if world is not None:  # most moves are far from everything: proven free at once, the rest checked closely
            new = [t for t in range(len(keys)) if keys[t] not in proofs]  # a repair changes a few moves only
            if new:
                c, g, n_s = certify_moves(robot, world, np.array([path[t] for t in new]),
                                          np.array([path[t + 1] for t in new]), levers, lim.certify_deltas_m)
                for i, t in enumerate(new):
                    proofs[keys[t]] = (c[i], g[i], n_s[i])
        for t in range(len(path) - 1):
            dur = float(move_time(path[t + 1] - path[t], speed, accel))
            if world is None:
                mc = MoveCheck(labels[t], labels[t + 1], True, float("nan"), ("", ""), 0.0, 0, dur)
            elif proofs[keys[t]][0]:
                mc = MoveCheck(labels[t], labels[t + 1], True, float(proofs[keys[t]][1]), ("", ""), 0.0,
                               int(proofs[keys[t]][2]), dur)
            else:
                if keys[t] not in exact:
                    exact[keys[t]] = check_move(robot, world, path[t], path[t + 1], levers, lim.check_resolution_rad,
                                                (labels[t], labels[t + 1]), dur)
                mc = replace(exact[keys[t]], start=labels[t], end=labels[t + 1], duration_s=dur)
            moves.append(mc)
            if not mc.free:
                bad = t
                break
        if bad is None:
            break
        ca = choice[bad - 1] if bad > 0 else 0
        cb = choice[bad] if bad < len(seq) else 0
        key = (bad, ca, cb)
        n_options = (len(cand[seq[bad - 1]]) if bad > 0 else 1) * (len(cand[seq[bad]]) if bad < len(seq) else 1)
        forbidden.add(key)
        stuck = len([f for f in forbidden if f[0] == bad]) >= n_options or tries == max_repairs
        if stuck and retours < MAX_RETOURS:
            # no branch pair tried moves between these two nodes: tour again with them apart (the joint-linear move
            # is the same both ways, so the other direction cannot make it free)
            a = 0 if bad == 0 else seq[bad - 1] + 1
            b = 0 if bad == len(seq) else seq[bad] + 1
            cost[a, b] = cost[b, a] = BANNED_MOVE_S
            seq = [s_ - 1 for s_ in _tour(cost, lim.return_to_start)]
            forbidden = set()
            retours, tries = retours + 1, 0
            choice, _ = _viterbi([cand[s_] for s_ in seq], start, lim.return_to_start, speed, accel, forbidden,
                                 wrap=True)
            continue
        if stuck:
            mc = moves[-1]
            raise ReachabilityError(
                f"move {mc.start} -> {mc.end} collides ({mc.pair[0]} vs {mc.pair[1]} at {mc.at_fraction:.0%} of the move) "
                f"with every IK branch pair tried: add a via station, move the part, or remove the obstacle"
            )
        tries += 1
        choice, total = _viterbi([cand[s] for s in seq], start, lim.return_to_start, speed, accel, forbidden, wrap=True)
        if not np.isfinite(total):
            mc = moves[-1]
            raise ReachabilityError(
                f"move {mc.start} -> {mc.end} collides ({mc.pair[0]} vs {mc.pair[1]}) and no other branch sequence is free"
            )

    joints = np.zeros((k, 6))
    branch = np.zeros(k, dtype=int)
    for pos, (s, c) in enumerate(zip(seq, choice)):
        joints[s] = path[pos + 1]
        branch[s] = branches[s][c]
    cycle = float(sum(mv.duration_s for mv in moves) + k * lim.settle_s)
    return ExecutionPlan(
        ids=ids, order=np.array(seq, dtype=int), joints=joints, base_from_flange=bff, branch=branch,
        start_q=start, moves=moves, cycle_time_s=cycle,
    )


# ----------------------------------------------------------------------------------------
# plan.json
# ----------------------------------------------------------------------------------------


def stations_from_plan(plan: dict, source: str = "plan.json") -> tuple[list[str], np.ndarray]:
    """Station ids and part_from_cam (k, 4, 4) from a plan.json document, checked.

    Raises ``InputError`` naming the station when: a station lacks ``id`` or a 4x4 ``part_from_cam``,
    two stations share an id, a pose is not finite, its last row is not [0, 0, 0, 1], or its rotation
    is not proper (orthonormal with determinant +1: a hand-edited mirror or a scaled matrix).
    """
    try:
        stations = plan["stations"]
        ids = [str(s["id"]) for s in stations]
        pfc = np.array([s["part_from_cam"] for s in stations], dtype=float).reshape(-1, 4, 4)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{source}: stations need 'id' and a 4x4 'part_from_cam' ({exc})") from exc
    if not ids:
        raise InputError(f"{source}: the plan has no stations")
    if len(pfc) != len(ids):
        raise InputError(f"{source}: every station needs a 4x4 'part_from_cam'")
    seen: set[str] = set()
    for sid in ids:
        if sid in seen:
            raise InputError(f"{source}: station id {sid!r} appears twice; station ids must be unique")
        seen.add(sid)
    for sid, T in zip(ids, pfc):
        if not np.all(np.isfinite(T)):
            raise InputError(f"{source}: station {sid!r}: part_from_cam has a non-finite entry")
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            raise InputError(f"{source}: station {sid!r}: part_from_cam's last row is {T[3].tolist()}, not [0, 0, 0, 1]")
        R = T[:3, :3]
        ortho = float(np.max(np.abs(R.T @ R - np.eye(3))))
        det = float(np.linalg.det(R))
        if ortho > 1e-6 or abs(det - 1.0) > 1e-6:
            what = "a mirror (determinant -1)" if abs(det + 1.0) < 1e-6 and ortho <= 1e-6 else \
                f"not orthonormal (|R^T R - I| = {ortho:.2g}, det {det:.6g})"
            raise InputError(f"{source}: station {sid!r}: part_from_cam's rotation is {what}; a camera pose needs a "
                             "proper rotation")
    return ids, pfc


def apply_to_plan(plan: dict, ep: ExecutionPlan) -> dict:
    """A copy of plan.json with each station's base_from_flange, joints and order (0-based
    position in the cycle) filled in, and an ``execution`` summary (cycle time, moves)."""
    out = dict(plan)
    rank = ep.rank
    by_id = {sid: i for i, sid in enumerate(ep.ids)}
    stations = []
    for st in plan["stations"]:
        i = by_id[str(st["id"])]
        st2 = dict(st)
        st2["base_from_flange"] = ep.base_from_flange[i].tolist()
        st2["joints"] = ep.joints[i].tolist()
        st2["order"] = int(rank[i])
        stations.append(st2)
    out["stations"] = stations
    out["execution"] = {
        "start_q": ep.start_q.tolist(),
        "sequence": [ep.ids[i] for i in ep.order],
        "cycle_time_s": ep.cycle_time_s,
        "moves": [
            {
                "from": mv.start, "to": mv.end, "duration_s": mv.duration_s, "free": mv.free,
                "min_distance_m": mv.min_distance_m if np.isfinite(mv.min_distance_m) else None,
                "closest": list(mv.pair), "n_checks": mv.n_checks,
            }
            for mv in ep.moves
        ],
    }
    return out

