"""A damaged planning cache (visibility, reachability) is detected, discarded and rebuilt: zero length,
truncated, random bytes, and a flipped byte at random offsets (where the zip format alone may not
notice). The rebuilt database equals a fresh computation, and the next load comes from the
rewritten file. A cache folder that cannot be written costs the cache, not the job."""
from __future__ import annotations

import numpy as np
import trimesh

from calibration.camera import Intrinsics, look_at
from planning.cache import load_arrays, save_arrays
from planning.kinematics import CollisionWorld, load_robot
from planning.part import Part, make_bracket, sample_targets
from planning.reachability import ReachabilityDB
from planning.stations import ViewingSphere
from planning.visibility import VisibilityDB, VisibilityOptions

FLANGE_FROM_CAM = np.array([[1, 0, 0, 0.0], [0, 1, 0, 0.04], [0, 0, 1, 0.09], [0, 0, 0, 1.0]])
INTR = Intrinsics(fx_px=2000.0, fy_px=2000.0, cx_px=999.5, cy_px=749.5, width=2000, height=1500)


def _damage(path, how: str, rng: np.random.Generator) -> str:
    data = bytearray(path.read_bytes())
    if how == "empty":
        data = bytearray()
    elif how == "truncated":
        data = data[: len(data) // 2]
    elif how == "garbage":
        data = bytearray(rng.integers(0, 256, len(data), dtype=np.uint8).tobytes())
    else:  # flip one bit of one byte at a random offset
        k = int(rng.integers(0, len(data)))
        data[k] ^= 1 << int(rng.integers(0, 8))
        how = f"bit flipped at byte {k} of {len(data)}"
    path.write_bytes(bytes(data))
    return how


DAMAGE = ["empty", "truncated", "garbage"] + ["flip"] * 6


def _reach_inputs():
    part = trimesh.creation.box((0.3, 0.2, 0.15))
    bfp = np.eye(4)
    bfp[:3, 3] = (0.45, 0.1, 0.075)
    world = CollisionWorld(part_mesh=part, base_from_part=bfp, table_z=0.0, obstacles=(), clearance_m=0.005)
    rng = np.random.default_rng(5)
    u = rng.normal(size=(30, 3))
    u[:, 2] = np.abs(u[:, 2]) + 0.3
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pfc = np.stack([look_at(e, np.zeros(3), np.array([0.0, 0.0, 1.0])) for e in u * 0.4])
    return load_robot("ur5e"), bfp, world, pfc


def test_damaged_reachability_cache_is_discarded_and_rebuilt(tmp_path):
    robot, bfp, world, pfc = _reach_inputs()
    fresh = ReachabilityDB.load_or_build(robot, bfp, FLANGE_FROM_CAM, pfc, world, cache_dir=tmp_path)
    path = tmp_path / f"reachability-{fresh.key}.npz"
    rng = np.random.default_rng(2026)
    for how in DAMAGE:
        what = _damage(path, how, rng)
        db = ReachabilityDB.load_or_build(robot, bfp, FLANGE_FROM_CAM, pfc, world, cache_dir=tmp_path)
        assert not db.loaded, f"{what}: the damaged cache was used"
        for name in ("reachable", "joints", "branch", "reason"):
            np.testing.assert_array_equal(getattr(db.result, name), getattr(fresh.result, name), err_msg=what)
        # the distance query's last digits vary from run to run
        np.testing.assert_allclose(db.result.collision_margin_m, fresh.result.collision_margin_m, atol=1e-6)
        again = ReachabilityDB.load_or_build(robot, bfp, FLANGE_FROM_CAM, pfc, world, cache_dir=tmp_path)
        assert again.loaded, f"{what}: the rebuilt cache was not written"
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporary file left


def test_damaged_visibility_cache_is_discarded_and_rebuilt(tmp_path):
    mesh = make_bracket()
    part = Part("bracket", mesh, sample_targets(mesh, 40, np.random.default_rng(0)))
    sphere = ViewingSphere.for_part(part, INTR)
    fresh = VisibilityDB.load_or_build(part, INTR, sphere, VisibilityOptions(), 60, cache_dir=tmp_path)
    path = tmp_path / f"visibility-{fresh.key}.npz"
    rng = np.random.default_rng(7)
    for how in DAMAGE:
        what = _damage(path, how, rng)
        db = VisibilityDB.load_or_build(part, INTR, sphere, VisibilityOptions(), 60, cache_dir=tmp_path)
        assert not db.from_cache, f"{what}: the damaged cache was used"
        np.testing.assert_array_equal(db.visible, fresh.visible, err_msg=what)
        assert VisibilityDB.load_or_build(part, INTR, sphere, VisibilityOptions(), 60, cache_dir=tmp_path).from_cache


def test_a_flipped_byte_in_an_uncompressed_array_is_caught_by_the_digest(tmp_path):
    a = np.arange(10_000, dtype=np.float64)
    path = save_arrays(tmp_path / "c.npz", {"a": a})
    data = bytearray(path.read_bytes())
    k = data.index(a[5000].tobytes())  # inside the stored (uncompressed) array
    data[k] ^= 0x10
    path.write_bytes(bytes(data))
    assert load_arrays(path, ("a",)) is None and not path.exists()


def test_unwritable_cache_folder_costs_the_cache_not_the_job(tmp_path):
    robot, bfp, world, pfc = _reach_inputs()
    not_a_folder = tmp_path / "cache"
    not_a_folder.write_text("a file where the cache folder should be")
    db = ReachabilityDB.load_or_build(robot, bfp, FLANGE_FROM_CAM, pfc, world, cache_dir=not_a_folder)
    assert db.reachable.any() and not db.loaded
    assert not_a_folder.read_text() == "a file where the cache folder should be"
