"""The simulated world: truth vs nominal, target geometry conventions, ray casting."""
import numpy as np
import pytest
import trimesh

from calibration.camera import Intrinsics, invert, look_at, make_pose, project
from calibration.errors import InputError
from planning.part import Part, Targets
from sim_backend.world import World, marker_axes, marker_corners

INTR = Intrinsics.from_focal_length(0.012, 3.45e-6, 2448, 2048)


def _plate_part(xyz, normals=None):
    mesh = trimesh.creation.box(extents=(0.4, 0.4, 0.02))
    mesh.apply_translation((0, 0, -0.01))
    n = len(xyz)
    normals = np.tile([0.0, 0.0, 1.0], (n, 1)) if normals is None else np.asarray(normals, float)
    targets = Targets(
        ids=[f"T{i}" for i in range(n)], xyz=np.asarray(xyz, float), normals=normals,
        kind=np.array(["retro"] * n), tolerance_m=np.full(n, np.nan), code=np.full(n, -1),
    )
    return Part("plate", mesh, targets)


def test_true_targets_are_cad_plus_deviations():
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-0.1, 0.1, (5, 3)) * [1, 1, 0]
    dev = rng.normal(0, 1e-4, (5, 3))
    w = World(_plate_part(xyz), np.eye(4), np.eye(4), INTR, dev)
    np.testing.assert_allclose(w.true_xyz, xyz + dev)
    np.testing.assert_allclose(World(_plate_part(xyz), np.eye(4), np.eye(4), INTR).true_xyz, xyz)


def test_deviations_of_wrong_shape_are_rejected_with_the_expected_shape():
    with pytest.raises(InputError, match=r"\(2, 3\)"):
        World(_plate_part(np.zeros((2, 3))), np.eye(4), np.eye(4), INTR, np.zeros((3, 3)))


def test_non_rigid_placement_is_rejected():
    T = np.eye(4)
    T[0, 0] = 2.0
    with pytest.raises(InputError, match="base_from_part"):
        World(_plate_part(np.zeros((1, 3))), T, np.eye(4), INTR)


def test_camera_pose_uses_true_placement_and_hand_eye_not_nominal():
    base_from_part = make_pose(np.eye(3), [0.5, 0.0, 0.0])
    true_bfp = make_pose(np.eye(3), [0.502, -0.001, 0.0005])
    true_fc = make_pose(np.eye(3), [0.0, 0.001, 0.05])
    w = World(_plate_part(np.zeros((1, 3))), base_from_part, np.eye(4), INTR,
              true_base_from_part=true_bfp, true_flange_from_cam=true_fc)
    bff = make_pose(np.eye(3), [0.4, 0.1, 0.6])
    w.set_robot(np.zeros(6), bff)
    np.testing.assert_allclose(w.true_part_from_cam(), invert(true_bfp) @ bff @ true_fc)
    np.testing.assert_allclose(w.base_from_part, base_from_part)  # nominal kept as stated
    assert not np.allclose(w.true_part_from_cam(), invert(base_from_part) @ bff)


def test_marker_axes_are_orthonormal_and_right_handed_with_minus_normal():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[0] = [1.0, 0.0, 0.0]  # the degenerate reference direction
    e1, e2 = marker_axes(n)
    for a, b in ((e1, e2), (e1, n), (e2, n)):
        np.testing.assert_allclose(np.sum(a * b, axis=1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(e1, axis=1), 1.0)
    np.testing.assert_allclose(np.cross(e1, e2), -n, atol=1e-12)


def test_marker_seen_from_the_front_is_not_mirrored():
    """Looking against the normal, corner order TL, TR, BR, BL runs clockwise in the image."""
    normal = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    corners = marker_corners(np.zeros(3), normal[None], 0.02)[0]
    part_from_cam = look_at(0.5 * normal, np.zeros(3), up=(0, 1, 0))
    uv = project(INTR, invert(part_from_cam), corners)
    tl, tr, br, bl = uv
    assert tr[0] > tl[0] and bl[1] > tl[1]  # e1 to the right, e2 down
    np.testing.assert_allclose(np.linalg.norm(corners[1] - corners[0]), 0.02)


def test_first_hit_distance_matches_the_plate_geometry():
    w = World(_plate_part(np.zeros((1, 3))), np.eye(4), np.eye(4), INTR)
    origin = np.array([0.0, 0.0, 0.5])
    dirs = np.array([[0.0, 0.0, -1.0], [0.1, 0.0, -1.0], [0.0, 0.0, 1.0]])
    dist, tri = w.first_hit(origin, dirs)
    np.testing.assert_allclose(dist[:2], [0.5, 0.5 * np.sqrt(1.01)], atol=1e-6)
    assert np.isinf(dist[2]) and tri[2] == -1


def test_random_streams_are_reproducible_from_the_seed():
    part = _plate_part(np.zeros((1, 3)))
    a = World(part, np.eye(4), np.eye(4), INTR, seed=7).spawn_rng().normal(size=4)
    b = World(part, np.eye(4), np.eye(4), INTR, seed=7).spawn_rng().normal(size=4)
    c = World(part, np.eye(4), np.eye(4), INTR, seed=8).spawn_rng().normal(size=4)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
