"""Robot model: FK against the published DH model, IK round trips, limits, collisions."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from calibration.errors import InputError
from planning.kinematics import BoxObstacle, CollisionWorld, ToolBox, dh_fk, load_robot
from planning.robots import UR_PARAMS, urdf_path, urdf_text


def _wrapdiff(a, b):
    return np.pi - np.mod(np.pi - (a - b), 2 * np.pi)


@pytest.mark.parametrize("name", ["ur5e", "ur10e"])
def test_packaged_urdf_is_the_generators_output(name):
    assert urdf_path(name).read_text() == urdf_text(UR_PARAMS[name])


@pytest.mark.parametrize(
    "name, q, xyz",
    [
        # zero pose: arm stretched along -x, flange pointing along -y, from the DH table by hand
        ("ur5e", [0, 0, 0, 0, 0, 0], [-0.425 - 0.3922, -(0.1333 + 0.0996), 0.1625 - 0.0997]),
        ("ur10e", [0, 0, 0, 0, 0, 0], [-0.6127 - 0.57155, -(0.17415 + 0.11655), 0.1807 - 0.11985]),
        # arm straight up
        ("ur5e", [0, -np.pi / 2, 0, -np.pi / 2, 0, 0], [0.0, -(0.1333 + 0.0996), 0.1625 + 0.425 + 0.3922 + 0.0997]),
        # base turned by 90 degrees
        ("ur5e", [np.pi / 2, 0, 0, 0, 0, 0], [0.1333 + 0.0996, -0.425 - 0.3922, 0.1625 - 0.0997]),
    ],
)
def test_fk_matches_dh_model_at_known_configurations(name, q, xyz):
    robot = load_robot(name)
    q = np.array(q, dtype=float)
    np.testing.assert_allclose(robot.fk(q)[:3, 3], xyz, atol=1e-12)
    np.testing.assert_allclose(robot.fk_many(q[None])[0], robot.fk(q), atol=1e-12)
    np.testing.assert_allclose(dh_fk(robot.params, q), robot.fk(q), atol=1e-12)


@pytest.mark.parametrize("name", ["ur5e", "ur10e"])
def test_pin_urdf_fk_equals_dh_fk_at_random_configurations(name):
    robot = load_robot(name)
    q = np.random.default_rng(1).uniform(-2 * np.pi, 2 * np.pi, (200, 6))
    np.testing.assert_allclose(robot.fk_many(q), dh_fk(robot.params, q), atol=1e-12)
    for qi in q[:10]:
        np.testing.assert_allclose(robot.fk(qi), dh_fk(robot.params, qi), atol=1e-12)


@pytest.mark.parametrize("name, seed", [("ur5e", 2), ("ur10e", 3)])
def test_ik_round_trips_random_reachable_poses(name, seed):
    robot = load_robot(name)
    rng = np.random.default_rng(seed)
    q_true = rng.uniform(robot.lower, robot.upper, (300, 6))
    q_true[:, 2] = rng.uniform(-np.pi, np.pi, 300)
    targets = robot.fk_many(q_true)
    sol = robot.ik_many(targets)
    assert np.all(sol.within_limits.any(axis=1))
    # every returned branch reproduces the pose to 1e-9 m
    T = robot.fk_many(np.where(sol.within_limits[..., None], sol.q, 0.0))
    err = np.linalg.norm(T[..., :3, 3] - targets[:, None, :3, 3], axis=-1)
    assert np.max(err[sol.within_limits]) < 1e-9
    rot_err = np.abs(T[..., :3, :3] - targets[:, None, :3, :3]).max(axis=(-1, -2))
    assert np.max(rot_err[sol.within_limits]) < 1e-9
    # the configuration that made the pose is one of the branches (angles mod 2 pi)
    d = np.abs(_wrapdiff(sol.q, q_true[:, None, :])).max(axis=-1)
    assert np.all(np.nanmin(np.where(sol.within_limits, d, np.inf), axis=1) < 1e-7)


def test_ik_single_pose_returns_all_distinct_branches_in_limits():
    robot = load_robot("ur5e")
    q = np.array([0.3, -1.2, 1.1, -0.7, 1.0, 0.4])
    sols = robot.ik(robot.fk(q))
    assert sols.shape == (8, 6)  # a generic pose has eight branches
    assert np.all(robot.within_limits(sols))
    for s in sols:
        np.testing.assert_allclose(robot.fk(s), robot.fk(q), atol=1e-9)
    assert len({tuple(np.round(s, 6)) for s in sols}) == 8


def test_ik_near_wrist_singularity_is_still_exact():
    robot = load_robot("ur5e")
    q = np.array([0.2, -1.0, 1.2, -0.4, 1e-12, 0.7])
    sols = robot.ik(robot.fk(q), q_ref=q)
    assert len(sols) > 0
    for s in sols:
        np.testing.assert_allclose(robot.fk(s), robot.fk(q), atol=1e-9)


def test_ik_of_unreachable_pose_is_empty_with_a_reason():
    robot = load_robot("ur5e")
    target = np.eye(4)
    target[:3, 3] = (1.5, 0.0, 0.3)
    assert robot.ik(target).shape == (0, 6)
    reason = robot.ik_many(target[None]).failure[0]
    assert reason.startswith("out of reach") and "0.850 m" in reason


def test_elbow_limit_is_configurable_and_respected():
    tight = load_robot("ur5e", elbow_limit_rad=0.5)
    q = np.array([0.3, -1.2, 1.1, -0.7, 1.0, 0.4])  # elbow at 1.1 rad: outside +-0.5
    sols = tight.ik(tight.fk(q))
    assert np.all(np.abs(sols[:, 2]) <= 0.5)
    assert len(sols) < 8
    assert load_robot("ur5e", elbow_limit_rad=None).upper[2] == pytest.approx(2 * np.pi)
    assert load_robot("ur5e").upper[2] == pytest.approx(np.pi)


def test_q_ref_selects_the_nearest_two_pi_equivalent():
    robot = load_robot("ur5e")
    q = np.array([0.3, -1.2, 1.1, -0.7, 1.0, 0.4])
    ref = q + np.array([-2 * np.pi, 0, 0, 2 * np.pi, 0, -2 * np.pi])  # still inside +-2 pi
    sols = robot.ik(robot.fk(q), q_ref=ref)
    best = sols[np.argmin(np.abs(sols - ref).max(axis=1))]
    np.testing.assert_allclose(best, ref, atol=1e-7)


def test_unknown_robot_and_bad_limits_are_input_errors():
    with pytest.raises(InputError, match="unknown robot"):
        load_robot("ur3")
    with pytest.raises(InputError, match="lower < upper"):
        load_robot("ur5e", lower=[0] * 6, upper=[0] * 6)


def _world(**kw) -> CollisionWorld:
    part = trimesh.creation.box((0.3, 0.2, 0.15))
    base_from_part = np.eye(4)
    base_from_part[:3, 3] = (0.5, 0.0, 0.075)
    return CollisionWorld(part_mesh=part, base_from_part=base_from_part, table_z=0.0, **kw)


UP = np.array([0.0, -np.pi / 2, 0.0, -np.pi / 2, 0.0, 0.0])


def test_upright_arm_is_collision_free_with_positive_clearance():
    robot = load_robot("ur5e")
    rep = robot.collision_free(UP, _world())
    assert rep and rep.free
    assert 0.0 < rep.distance_m < 0.2


def test_arm_folded_into_the_table_collides_with_the_table():
    robot = load_robot("ur5e")
    q = np.array([np.pi, -0.3, 2.5, -1.0, -1.57, 0.0])  # wrist driven below z = 0, away from the part
    rep = robot.check_collision(q, _world())
    assert not rep
    assert "table" in rep.pair and rep.distance_m < 0


def test_camera_inside_a_box_obstacle_collides_and_names_the_obstacle():
    robot = load_robot("ur5e")
    flange = robot.fk(UP)
    box_pose = flange.copy()
    box_pose[:3, 3] = flange[:3, :3] @ np.array([0, 0, 0.06]) + flange[:3, 3]  # around the camera body
    world = _world(obstacles=(BoxObstacle("fixture", (0.3, 0.3, 0.3), box_pose),))
    rep = robot.check_collision(UP, world)
    assert not rep and rep.pair == ("camera", "fixture")
    without_tool = load_robot("ur5e", tool=None)
    # without the camera the wrist still sits inside that 0.3 m box
    assert not without_tool.check_collision(UP, world)


def test_arm_touching_the_part_collides():
    robot = load_robot("ur5e")
    # put the part where the upright arm's forearm is
    world = CollisionWorld(
        part_mesh=trimesh.creation.box((0.2, 0.2, 0.2)),
        base_from_part=np.array([[1, 0, 0, 0.0], [0, 1, 0, -0.14], [0, 0, 1, 0.8], [0, 0, 0, 1.0]]),
        table_z=0.0,
    )
    rep = robot.check_collision(UP, world)
    assert not rep and "part" in rep.pair


def test_clearance_turns_near_misses_into_collisions():
    robot = load_robot("ur5e")
    d = robot.check_collision(UP, _world()).distance_m
    assert robot.check_collision(UP, _world(clearance_m=0.5 * d))
    assert not robot.check_collision(UP, _world(clearance_m=2.0 * d))
    assert not robot.collision_free_many(UP[None], _world(clearance_m=2.0 * d))[0]


def test_batched_collision_check_agrees_with_single_checks():
    robot = load_robot("ur5e", tool=ToolBox("camera", (0.1, 0.1, 0.15)))
    world = _world(obstacles=(BoxObstacle("wall", (0.05, 1.0, 1.0), np.array([[1, 0, 0, -0.5], [0, 1, 0, 0], [0, 0, 1, 0.5], [0, 0, 0, 1.0]])),))
    q = np.random.default_rng(4).uniform(-np.pi, np.pi, (150, 6))
    batch = robot.collision_free_many(q, world, n_threads=2)
    single = np.array([bool(robot.collision_free(qi, world)) for qi in q])
    np.testing.assert_array_equal(batch, single)
    assert 0 < batch.sum() < len(q)


def test_a_dense_part_is_measured_through_its_hull_far_away_and_exactly_near(monkeypatch):
    """A part of more than HULL_STAND_IN_FACES faces (a generated skin has 70 000: 39 ms a check, far links costing
    most) is measured through its convex hull where that is more than PART_EXACT_WITHIN_M beyond the clearance: a
    lower bound of the exact distance there, the exact distance nearer, and the same verdict everywhere. A concave
    part (a bowl) puts links inside its hull: those take the exact distance."""
    import planning.kinematics as kin

    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.25)
    lower = ball.triangles_center[:, 2] < 0.0
    bowl = ball.submesh([np.flatnonzero(lower)], append=True)  # the lower half: open, concave from above
    assert len(bowl.faces) > kin.HULL_STAND_IN_FACES
    pose = np.eye(4)
    pose[:3, 3] = (0.45, 0.1, 0.35)
    world = CollisionWorld(part_mesh=bowl, base_from_part=pose, table_z=0.0, clearance_m=0.005)
    q = np.random.default_rng(5).uniform(-np.pi, np.pi, (120, 6))
    hull = load_robot("ur5e")
    got = [hull.check_collision(qi, world) for qi in q]
    monkeypatch.setattr(kin, "HULL_STAND_IN_FACES", 10**9)
    exact = load_robot("ur5e")
    want = [exact.check_collision(qi, world) for qi in q]
    assert [g.free for g in got] == [w.free for w in want]
    assert 0 < sum(g.free for g in got) < len(q)
    near = 0
    for g, w in zip(got, want):
        assert g.distance_m <= w.distance_m + 1e-9
        if w.distance_m < world.clearance_m + kin.PART_EXACT_WITHIN_M or "part" not in w.pair:
            near += "part" in w.pair
            assert g.distance_m == pytest.approx(w.distance_m, abs=1e-6) and g.pair == w.pair  # penetration: 1e-7
    assert near > 0
