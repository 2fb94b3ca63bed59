"""VALIDATE: branch choice, order, move collision checks, cycle time, plan.json fields."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from calibration.camera import look_at
from calibration.errors import ReachabilityError
from planning.execution import (
    MotionLimits,
    apply_to_plan,
    certify_moves,
    check_move,
    lever_arms,
    move_time,
    validate_plan,
)
from planning.kinematics import BoxObstacle, CollisionWorld, load_robot
from planning.reachability import reachability_mask

FLANGE_FROM_CAM = np.array([[1, 0, 0, 0.0], [0, 1, 0, 0.04], [0, 0, 1, 0.09], [0, 0, 0, 1.0]])
UP = np.array([0.0, -np.pi / 2, 0.0, -np.pi / 2, 0.0, 0.0])


def _cell(obstacles=()):
    base_from_part = np.eye(4)
    base_from_part[:3, 3] = (0.45, 0.1, 0.075)
    world = CollisionWorld(
        part_mesh=trimesh.creation.box((0.3, 0.2, 0.15)), base_from_part=base_from_part, table_z=0.0,
        obstacles=obstacles, clearance_m=0.005,
    )
    return base_from_part, world


def _reachable_stations(k: int, seed: int):
    robot = load_robot("ur5e")
    bfp, world = _cell()
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(8 * k, 3))
    u[:, 2] = np.abs(u[:, 2]) + 0.4
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    eyes = u * rng.uniform(0.3, 0.45, len(u))[:, None]
    pfc = np.stack([look_at(e, np.zeros(3), np.array([0.0, 0.0, 1.0])) for e in eyes])
    res = reachability_mask(robot, bfp, FLANGE_FROM_CAM, pfc, world)
    return robot, bfp, world, pfc[np.flatnonzero(res.reachable)[:k]]


def test_move_time_follows_the_trapezoidal_profile():
    v, a = np.full(6, 1.0), np.full(6, 2.0)
    # 0.2 rad < v^2/a = 0.5: triangle, 2 sqrt(d/a); 2 rad: d/v + v/a; slowest joint wins
    assert move_time(np.array([0.2, 0, 0, 0, 0, 0]), v, a) == pytest.approx(2 * np.sqrt(0.1))
    assert move_time(np.array([0.2, -2.0, 0, 0, 0, 0]), v, a) == pytest.approx(2.5)
    assert move_time(np.zeros(6), v, a) == 0.0


def test_validated_plan_reaches_every_station_collision_free():
    robot, bfp, world, pfc = _reachable_stations(12, seed=0)
    limits = MotionLimits(joint_speed_rad_s=1.0, joint_accel_rad_s2=2.0, settle_s=0.4)
    ep = validate_plan(robot, pfc, bfp, FLANGE_FROM_CAM, world, limits, start_q=UP)
    assert sorted(ep.order.tolist()) == list(range(len(pfc)))
    cam = robot.fk_many(ep.joints) @ FLANGE_FROM_CAM
    np.testing.assert_allclose(cam, bfp @ pfc, atol=1e-9)
    assert np.all(robot.within_limits(ep.joints))
    assert len(ep.moves) == len(pfc) + 1 and all(m.free for m in ep.moves)
    assert ep.moves[0].start == "start" and ep.moves[-1].end == "start"
    path = ep.joint_path
    durations = [float(move_time(path[i + 1] - path[i], np.full(6, 1.0), np.full(6, 2.0))) for i in range(len(path) - 1)]
    assert ep.cycle_time_s == pytest.approx(sum(durations) + 0.4 * len(pfc))
    for m in ep.moves:
        assert m.min_distance_m >= world.clearance_m


def test_order_is_no_longer_than_the_given_order():
    robot, bfp, world, pfc = _reachable_stations(10, seed=1)
    limits = MotionLimits(settle_s=0.0, return_to_start=False)
    ep = validate_plan(robot, pfc, bfp, FLANGE_FROM_CAM, world, limits, start_q=UP)
    speed = np.minimum(np.full(6, limits.joint_speed_rad_s), robot.max_velocity)
    accel = np.full(6, limits.joint_accel_rad_s2)
    # the given order with the same branches (unwrapped along the way) costs at least as much
    given = [UP]
    for i in range(len(pfc)):
        given.append(robot.nearest_equivalent(ep.joints[i], given[-1]))
    given_time = sum(float(move_time(given[i + 1] - given[i], speed, accel)) for i in range(len(given) - 1))
    assert ep.cycle_time_s <= given_time + 1e-9


def test_branch_choice_keeps_the_arm_configuration_for_nearby_stations():
    robot, bfp, world, pfc = _reachable_stations(1, seed=2)
    # small rotations of one station about the part: the same branch all the way
    rot = lambda a: np.array([[np.cos(a), -np.sin(a), 0, 0], [np.sin(a), np.cos(a), 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])  # noqa: E731
    stations = np.stack([rot(a) @ pfc[0] for a in np.linspace(-0.2, 0.2, 6)])
    ep = validate_plan(robot, stations, bfp, FLANGE_FROM_CAM, world, start_q=UP)
    assert len(set(ep.branch.tolist())) == 1
    steps = np.abs(np.diff(ep.joint_path[1:-1], axis=0)).max()
    assert steps < 0.5


def test_out_of_reach_station_raises_naming_the_station():
    robot, bfp, world, pfc = _reachable_stations(3, seed=3)
    far = pfc[0].copy()
    far[:3, 3] += (1.5, 0.0, 0.0)
    with pytest.raises(ReachabilityError, match=r"station S3: no IK solution \(out of reach \d\.\d+ m > 0\.850 m from the shoulder\)"):
        validate_plan(robot, np.concatenate([pfc, far[None]]), bfp, FLANGE_FROM_CAM, world, start_q=UP)


def test_station_inside_an_obstacle_raises_naming_station_and_obstacle():
    robot, bfp, _, pfc = _reachable_stations(3, seed=4)
    _, world = _cell(obstacles=(BoxObstacle("fixture", (0.1, 0.1, 0.1), bfp @ pfc[1]),))
    with pytest.raises(ReachabilityError, match=r"station B: every IK branch collides \(best: camera vs fixture"):
        validate_plan(robot, pfc, bfp, FLANGE_FROM_CAM, world, start_q=UP, ids=["A", "B", "C"])


def test_move_through_an_obstacle_is_caught_between_free_endpoints():
    robot = load_robot("ur5e")
    qa = np.array([-0.8, -1.2, 1.5, -1.9, -1.57, 0.0])
    qb = np.array([0.8, -1.2, 1.5, -1.9, -1.57, 0.0])
    mid = robot.fk(0.5 * (qa + qb))
    box = np.eye(4)
    box[:3, 3] = mid[:3, 3]
    world = CollisionWorld(table_z=0.0, obstacles=(BoxObstacle("post", (0.06, 0.06, 0.06), box),))
    assert robot.check_collision(qa, world) and robot.check_collision(qb, world)
    mc = check_move(robot, world, qa, qb, lever_arms(robot), 0.005, ("a", "b"), 1.0)
    assert not mc.free and "post" in mc.pair and 0.2 < mc.at_fraction < 0.8
    clear = check_move(robot, CollisionWorld(table_z=0.0), qa, qb, lever_arms(robot), 0.005, ("a", "b"), 1.0)
    assert clear.free and clear.n_checks >= 2


def test_start_configuration_in_collision_is_rejected():
    robot, bfp, world, pfc = _reachable_stations(2, seed=5)
    with pytest.raises(ReachabilityError, match="start configuration collides"):
        validate_plan(robot, pfc, bfp, FLANGE_FROM_CAM, world, start_q=np.array([np.pi, -0.3, 2.5, -1.0, -1.57, 0.0]))


def test_plan_json_gets_flange_targets_joints_and_order():
    robot, bfp, world, pfc = _reachable_stations(4, seed=6)
    ids = ["s1", "s2", "s3", "s4"]
    ep = validate_plan(robot, pfc, bfp, FLANGE_FROM_CAM, world, start_q=UP, ids=ids)
    plan = {"seed": 1, "stations": [{"id": i, "part_from_cam": p.tolist()} for i, p in zip(ids, pfc)]}
    out = apply_to_plan(plan, ep)
    assert "joints" not in plan["stations"][0]  # input untouched
    assert sorted(s["order"] for s in out["stations"]) == [0, 1, 2, 3]
    for s in out["stations"]:
        np.testing.assert_allclose(robot.fk(np.array(s["joints"])), np.array(s["base_from_flange"]), atol=1e-9)
    assert out["execution"]["sequence"] == [ids[i] for i in ep.order]
    assert out["execution"]["cycle_time_s"] == pytest.approx(ep.cycle_time_s)


def test_batched_certification_proves_only_moves_that_keep_their_clearance():
    robot = load_robot("ur5e")
    qa = np.array([-0.8, -1.2, 1.5, -1.9, -1.57, 0.0])
    qb = np.array([0.8, -1.2, 1.5, -1.9, -1.57, 0.0])
    box = np.eye(4)
    box[:3, 3] = robot.fk(0.5 * (qa + qb))[:3, 3]
    blocked = CollisionWorld(table_z=0.0, obstacles=(BoxObstacle("post", (0.06, 0.06, 0.06), box),))
    levers = lever_arms(robot)
    path = np.array([qa, qb])
    assert not certify_moves(robot, blocked, path[:-1], path[1:], levers)[0][0]
    for lift in (0.12, 0.16, 0.17, 0.19, 0.25):  # the post above the path: hit, grazing, clear
        near = box.copy()
        near[2, 3] += lift
        world = CollisionWorld(table_z=0.0, obstacles=(BoxObstacle("post", (0.06, 0.06, 0.06), near),))
        proven, guaranteed, _ = certify_moves(robot, world, path[:-1], path[1:], levers)
        d = min(robot.check_collision(qa + s * (qb - qa), world).distance_m for s in np.linspace(0, 1, 200))
        if proven[0]:  # what it proves holds at every configuration checked densely
            assert d >= guaranteed[0] - 1e-9 and guaranteed[0] > world.clearance_m
        else:  # not proven: some sample came within clearance + the finest delta
            assert d < world.clearance_m + 0.005 + 0.002
    assert certify_moves(robot, CollisionWorld(table_z=0.0), path[:-1], path[1:], levers)[0][0]


@pytest.mark.slow
def test_a_move_that_collides_on_every_branch_pair_is_toured_around(tmp_path):
    """Stations planned for a generated skin (tests.partgen seed 103, stored): the direct move between S011 and the
    start collides on every IK branch pair (it failed VALIDATE before); the tour is made again with S011 kept
    away from the start, and every move of the cycle is collision-free."""
    import json
    from pathlib import Path

    from cell.loadedjob import load
    from cell.setup import collision_world, robot_model
    from tests.partgen import make_part_job

    job = load(make_part_job(tmp_path / "job", np.random.default_rng(103)).job)
    doc = json.loads((Path(__file__).parent / "data" / "validate_retour_partgen103.json").read_text())
    T = np.array([s["part_from_cam"] for s in doc["stations"]])
    ids = [s["id"] for s in doc["stations"]]
    ep = validate_plan(robot_model(job), T, job.spec.base_from_part(), job.spec.flange_from_cam(), collision_world(job),
                       ids=ids)
    order = [ep.ids[i] for i in ep.order]
    assert sorted(order) == sorted(ids) and all(m.free for m in ep.moves)
    assert order[0] != "S011" and order[-1] != "S011"  # never next to the start: that move collides
