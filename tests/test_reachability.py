"""Reachability database: truth against a per-branch loop, obstacles, out-of-reach parts, cache."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from calibration.camera import look_at
from planning.kinematics import BoxObstacle, CollisionWorld, load_robot
from planning.reachability import ReachabilityDB, ReachabilityOptions, flange_targets, reachability_mask

FLANGE_FROM_CAM = np.array([[1, 0, 0, 0.0], [0, 1, 0, 0.04], [0, 0, 1, 0.09], [0, 0, 0, 1.0]])


def _cell(x=0.45, y=0.1, obstacles=()):
    part = trimesh.creation.box((0.3, 0.2, 0.15))
    base_from_part = np.eye(4)
    base_from_part[:3, 3] = (x, y, 0.075)
    world = CollisionWorld(part_mesh=part, base_from_part=base_from_part, table_z=0.0, obstacles=obstacles, clearance_m=0.005)
    return base_from_part, world


def _stations(m: int, rng: np.random.Generator) -> np.ndarray:
    """m stations on a hemisphere shell around the part, looking at its centre."""
    u = rng.normal(size=(m, 3))
    u[:, 2] = np.abs(u[:, 2]) + 0.3
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    eyes = u * rng.uniform(0.3, 0.5, m)[:, None]
    return np.stack([look_at(e, np.zeros(3), np.array([0.0, 0.0, 1.0])) for e in eyes])


def test_reachable_joints_put_the_camera_on_the_station():
    robot = load_robot("ur5e")
    bfp, world = _cell()
    pfc = _stations(200, np.random.default_rng(0))
    res = reachability_mask(robot, bfp, FLANGE_FROM_CAM, pfc, world)
    assert 0 < res.reachable.sum() < len(pfc)
    cam = robot.fk_many(res.joints[res.reachable]) @ FLANGE_FROM_CAM
    np.testing.assert_allclose(cam, (bfp @ pfc)[res.reachable], atol=1e-9)
    assert np.all(res.joint_margin_rad[res.reachable] >= 0)
    assert np.all(res.collision_margin_m[res.reachable] >= world.clearance_m)
    assert np.all(res.reason[res.reachable] == "")
    assert np.all(res.reason[~res.reachable] != "")
    assert np.all(np.isnan(res.joints[~res.reachable]))


def test_vectorised_mask_equals_a_per_branch_loop():
    robot = load_robot("ur5e")
    bfp, world = _cell(obstacles=(BoxObstacle("post", (0.1, 0.1, 0.8), np.array([[1, 0, 0, 0.2], [0, 1, 0, 0.35], [0, 0, 1, 0.4], [0, 0, 0, 1.0]])),))
    pfc = _stations(150, np.random.default_rng(1))
    res = reachability_mask(robot, bfp, FLANGE_FROM_CAM, pfc, world)
    targets = flange_targets(bfp, pfc, FLANGE_FROM_CAM)
    truth = np.array([any(bool(robot.check_collision(q, world)) for q in robot.ik(t)) for t in targets])
    np.testing.assert_array_equal(res.reachable, truth)
    assert any("collision" in r for r in res.reason)


def test_station_inside_a_box_obstacle_is_rejected():
    robot = load_robot("ur5e")
    bfp, world = _cell()
    pfc = _stations(60, np.random.default_rng(2))
    free = reachability_mask(robot, bfp, FLANGE_FROM_CAM, pfc, world)
    i = int(np.flatnonzero(free.reachable)[0])
    box_pose = bfp @ pfc[i]  # a 0.1 m cube around the camera's optical centre
    _, boxed_world = _cell(obstacles=(BoxObstacle("fixture", (0.1, 0.1, 0.1), box_pose),))
    res = reachability_mask(robot, bfp, FLANGE_FROM_CAM, pfc, boxed_world)
    assert not res.reachable[i]
    assert res.reason[i].startswith("collision") and "fixture" in res.reason[i]


def test_part_placed_out_of_reach_fails_with_a_clear_message():
    robot = load_robot("ur5e")
    bfp, world = _cell(x=2.0, y=0.0)
    pfc = _stations(40, np.random.default_rng(3))
    res = reachability_mask(robot, bfp, FLANGE_FROM_CAM, pfc, world)
    assert not res.reachable.any()
    assert all(r.startswith("out of reach ") and "> 0.850 m from the shoulder" in r for r in res.reason)
    assert "0/40 stations reachable (40 out of reach)" == res.summary()


def test_required_joint_margin_removes_branches_near_limits():
    robot = load_robot("ur5e")
    bfp, world = _cell()
    pfc = _stations(100, np.random.default_rng(4))
    loose = reachability_mask(robot, bfp, FLANGE_FROM_CAM, pfc, world)
    strict = reachability_mask(robot, bfp, FLANGE_FROM_CAM, pfc, world, ReachabilityOptions(min_joint_margin_rad=2.6))
    assert strict.reachable.sum() < loose.reachable.sum()
    assert np.all(strict.joint_margin_rad[strict.reachable] >= 2.6)
    assert np.all(strict.reachable <= loose.reachable)


def test_database_is_cached_and_keyed_by_its_inputs(tmp_path):
    robot = load_robot("ur5e")
    bfp, world = _cell()
    pfc = _stations(50, np.random.default_rng(5))
    first = ReachabilityDB.load_or_build(robot, bfp, FLANGE_FROM_CAM, pfc, world, cache_dir=tmp_path)
    again = ReachabilityDB.load_or_build(robot, bfp, FLANGE_FROM_CAM, pfc, world, cache_dir=tmp_path)
    assert not first.loaded and again.loaded and again.key == first.key
    for name in ("reachable", "joints", "branch", "reason", "collision_margin_m"):
        np.testing.assert_array_equal(getattr(again.result, name), getattr(first.result, name))
    _, moved = _cell(x=0.5)
    other = ReachabilityDB.load_or_build(robot, bfp, FLANGE_FROM_CAM, pfc, moved, cache_dir=tmp_path)
    assert other.key != first.key and not other.loaded
    ur10 = ReachabilityDB.load_or_build(load_robot("ur10e"), bfp, FLANGE_FROM_CAM, pfc, world, cache_dir=tmp_path)
    assert ur10.key != first.key


def test_bad_station_array_is_an_input_error():
    from calibration.errors import InputError

    with pytest.raises(InputError, match=r"\(m, 4, 4\)"):
        reachability_mask(load_robot("ur5e"), np.eye(4), np.eye(4), np.eye(4), None)
