"""SimRobot: real (timed or instant) motion, limits, faults, and the world it writes."""
import threading
import time

import numpy as np
import pytest
import trimesh

from calibration.camera import Intrinsics, invert, look_at, make_pose
from calibration.errors import LimitError, MotionError, NotConnectedError, ProtectiveStopError
from drivers.protocols import Robot
from planning.kinematics import load_robot
from planning.part import Part, Targets
from sim_backend.factory import make_sim_cell
from sim_backend.sim_robot import HOME_JOINTS, RobotLimits, SimRobot, trapezoid_duration, trapezoid_fraction
from sim_backend.world import World

INTR = Intrinsics.from_focal_length(0.012, 3.45e-6, 2448, 2048)
MODEL = load_robot("ur5e")
STEP = np.array([0.3, 0.2, -0.2, 0.1, 0.1, 0.5])


def _part():
    mesh = trimesh.creation.box(extents=(0.3, 0.2, 0.02))
    mesh.apply_translation((0, 0, -0.01))
    g = np.linspace(-0.1, 0.1, 5)
    gx, gy = np.meshgrid(g, g * 0.6)
    xyz = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    n = len(xyz)
    t = Targets(ids=[f"T{i}" for i in range(n)], xyz=xyz, normals=np.tile([0, 0, 1.0], (n, 1)),
                kind=np.array(["retro"] * n), tolerance_m=np.full(n, np.nan), code=np.full(n, -1))
    return Part("plate", mesh, t)


def _robot(**kw):
    world = World(_part(), make_pose(np.eye(3), [0.45, 0.1, 0.0]), np.eye(4), INTR)
    r = SimRobot(world, MODEL, **kw)
    r.connect()
    return r


def test_trapezoid_profile_respects_speed_and_acceleration():
    d, v, a = 0.8, 1.0, 2.0
    T = float(trapezoid_duration(d, v, a))
    assert T == pytest.approx(d / v + v / a)
    t = np.linspace(0, T, 20001)
    s = trapezoid_fraction(t, d, v, a) * d
    vel = np.gradient(s, t)
    assert s[0] == 0 and s[-1] == pytest.approx(d) and np.all(np.diff(s) >= -1e-15)
    assert vel.max() <= v * (1 + 1e-3) and np.abs(np.gradient(vel, t)).max() <= a * 1.01
    assert float(trapezoid_duration(0.1, v, a)) == pytest.approx(2 * np.sqrt(0.1 / a))  # triangular


def test_sim_robot_satisfies_the_robot_protocol():
    assert isinstance(_robot(), Robot)


def test_move_joints_arrives_writes_the_world_and_advances_the_clock_by_the_motion_time():
    r = _robot()
    t0 = r.state().timestamp_s
    st = r.move_joints(HOME_JOINTS + STEP, 1.0, 2.0)
    np.testing.assert_allclose(st.joints_rad, HOME_JOINTS + STEP)
    np.testing.assert_allclose(r.world.base_from_flange, MODEL.fk(HOME_JOINTS + STEP))
    assert st.safety.normal
    assert r.last_duration_s == pytest.approx(float(trapezoid_duration(0.5, 1.0, 2.0)))
    assert st.timestamp_s - t0 >= r.last_duration_s


def test_timed_motion_passes_through_intermediate_poses_in_scaled_real_time():
    r = _robot(motion="timed", time_scale=10.0)
    seen, done = [], threading.Event()

    def sample():
        while not done.is_set():
            seen.append(r.world.joints_rad[5])
            time.sleep(0.002)

    th = threading.Thread(target=sample)
    th.start()
    t0 = time.monotonic()
    try:
        r.move_joints(HOME_JOINTS + STEP, 1.0, 2.0)  # 1.0 s simulated
    finally:
        done.set()
        th.join()
    wall = time.monotonic() - t0
    assert 0.09 <= wall < 0.6
    inner = [q for q in seen if 1e-6 < q < 0.5 - 1e-6]
    assert len(inner) >= 3 and np.all(np.diff(inner) >= -1e-12)


def test_stop_during_a_timed_move_decelerates_and_raises_before_the_target():
    r = _robot(motion="timed", time_scale=4.0)
    timer = threading.Timer(0.1, r.stop)
    timer.start()
    try:
        with pytest.raises(MotionError, match="stop"):
            r.move_joints(HOME_JOINTS + STEP, 0.5, 1.0)  # 1.5 s simulated
    finally:
        timer.cancel()
    q = r.state().joints_rad
    frac = (q - HOME_JOINTS)[5] / STEP[5]
    assert 0.0 < frac < 0.9


def test_limits_are_checked_before_anything_moves():
    r = _robot()
    q_bad = HOME_JOINTS.copy()
    q_bad[2] = 3.5  # elbow limit is pi
    with pytest.raises(LimitError, match="joint 3"):
        r.move_joints(q_bad, 1.0, 2.0)
    with pytest.raises(LimitError, match="exceeds"):
        r.move_joints(HOME_JOINTS + STEP, 5.0, 2.0)
    with pytest.raises(LimitError, match="positive"):
        r.move_joints(HOME_JOINTS + STEP, 1.0, -1.0)
    far = MODEL.fk(HOME_JOINTS)
    far[:3, 3] = [2.0, 0.0, 0.5]
    with pytest.raises(LimitError, match="unreachable"):
        r.move_pose(far, 0.2, 1.0)
    np.testing.assert_allclose(r.state().joints_rad, HOME_JOINTS)


def test_workspace_box_refuses_a_path_that_leaves_it():
    r = _robot(limits=RobotLimits(workspace_m=[[-1, -1, 0.3], [1, 1, 1]]))
    target = MODEL.fk(HOME_JOINTS)
    target[2, 3] = 0.2
    q = MODEL.ik(target, q_ref=HOME_JOINTS)
    with pytest.raises(LimitError, match="workspace"):
        r.move_joints(q[np.argmin(np.abs(q - HOME_JOINTS).max(axis=1))], 1.0, 2.0)


def test_move_pose_follows_a_straight_line_and_arrives_exactly():
    r = _robot(motion="timed", time_scale=5.0)
    T0 = r.state().base_from_flange
    T1 = T0.copy()
    T1[:3, 3] += [0.08, -0.12, -0.05]
    pts, done = [], threading.Event()

    def sample():
        while not done.is_set():
            with r.world.lock:
                pts.append(r.world.base_from_flange[:3, 3].copy())
            time.sleep(0.002)

    th = threading.Thread(target=sample)
    th.start()
    try:
        st = r.move_pose(T1, 0.25, 1.0)
    finally:
        done.set()
        th.join()
    np.testing.assert_allclose(st.base_from_flange, T1, atol=1e-9)
    d = (T1 - T0)[:3, 3] / np.linalg.norm((T1 - T0)[:3, 3])
    off = [np.linalg.norm((p - T0[:3, 3]) - np.dot(p - T0[:3, 3], d) * d) for p in pts]
    assert len(pts) > 5 and max(off) < 2e-4


def test_protective_stop_at_next_move_keeps_the_robot_stopped_until_reset():
    r = _robot()
    r.inject_protective_stop()
    with pytest.raises(ProtectiveStopError):
        r.move_joints(HOME_JOINTS + STEP, 1.0, 2.0)
    st = r.state()
    assert st.safety.protective_stop and not st.safety.normal
    np.testing.assert_allclose(st.joints_rad, HOME_JOINTS)
    with pytest.raises(ProtectiveStopError, match="operator"):
        r.move_joints(HOME_JOINTS, 1.0, 2.0)
    r.reset_protective_stop()
    r.move_joints(HOME_JOINTS + STEP, 1.0, 2.0)
    assert r.state().safety.normal


def test_protective_stop_after_t_seconds_halts_where_the_profile_was():
    r = _robot()
    r.inject_protective_stop(after_s=0.3)
    with pytest.raises(ProtectiveStopError):
        r.move_joints(HOME_JOINTS + STEP, 1.0, 2.0)  # 1.0 s move
    frac = float(trapezoid_fraction(0.3, 0.5, 1.0, 2.0))
    np.testing.assert_allclose(r.state().joints_rad, HOME_JOINTS + frac * STEP, atol=1e-12)


def test_connection_loss_now_and_mid_move():
    r = _robot()
    r.inject_connection_loss()
    with pytest.raises(NotConnectedError):
        r.state()
    r.connect()
    r.inject_connection_loss(after_s=0.5)
    with pytest.raises(NotConnectedError, match="lost"):
        r.move_joints(HOME_JOINTS + STEP, 1.0, 2.0)
    with pytest.raises(NotConnectedError):
        r.move_joints(HOME_JOINTS, 1.0, 2.0)
    r.fail_next_connects(1)
    with pytest.raises(NotConnectedError):
        r.connect()
    r.connect()
    np.testing.assert_allclose(r.state().joints_rad, HOME_JOINTS + 0.5 * STEP, atol=1e-12)  # halfway at t=T/2


def test_repeatability_noise_has_the_requested_spread():
    r = _robot(repeatability_rad=1e-4, rng=np.random.default_rng(0))
    errs = []
    for k in range(40):
        target = HOME_JOINTS + (STEP if k % 2 else 0.0)
        errs.append(r.move_joints(target, 3.0, 10.0).joints_rad - target)
    assert 0.7e-4 < np.std(errs) < 1.3e-4


def test_camera_renders_from_the_pose_the_robot_wrote():
    """One world: the robot moves, the camera sees the part from there (with true hand-eye)."""
    part = _part()
    base_from_part = make_pose(np.eye(3), [0.45, 0.1, 0.0])
    flange_from_cam = make_pose(np.eye(3), [0.0, 0.0, 0.05])
    true_fc = make_pose(np.eye(3), [0.001, -0.002, 0.051])
    cell = make_sim_cell(part, base_from_part, flange_from_cam, INTR, true_flange_from_cam=true_fc, seed=3)
    cell.connect()
    part_from_cam = look_at(np.array([0.05, -0.05, 0.5]), np.zeros(3), up=(0, 1, 0))
    target = base_from_part @ part_from_cam @ invert(flange_from_cam)
    q = MODEL.ik(target, q_ref=HOME_JOINTS)
    q = q[np.argmin(np.abs(q - HOME_JOINTS).max(axis=1))]
    st = cell.robot.move_joints(q, 1.0, 2.0)
    frame = cell.camera.capture()
    truth = frame.meta["sim_truth"]
    np.testing.assert_allclose(truth["part_from_cam"], invert(base_from_part) @ st.base_from_flange @ true_fc, atol=1e-12)
    assert len(truth["ids"]) == 25
    u, v = np.round(truth["uv"][12]).astype(int)
    assert frame.image[v, u] > 100
    cell.close()
