"""Visibility of targets from stations, the two ray-casting backends, and the cached database."""
import numpy as np
import pytest
import trimesh

from calibration.camera import Intrinsics, invert, look_at, project
from calibration.errors import PlanningError
from planning.part import Part, Targets, make_bracket, sample_targets
from planning.stations import ViewingSphere
from planning.visibility import (
    Occluder,
    VisibilityDB,
    VisibilityOptions,
    compute_visibility,
)

INTR = Intrinsics(fx_px=2000.0, fy_px=2000.0, cx_px=999.5, cy_px=749.5, width=2000, height=1500)
OPEN = VisibilityOptions(margin_px=0.0, incidence_max_rad=np.pi / 2 - 1e-6, min_target_px=0.0)


def make_targets(xyz, normals) -> Targets:
    xyz = np.atleast_2d(np.asarray(xyz, dtype=float))
    normals = np.atleast_2d(np.asarray(normals, dtype=float))
    n = len(xyz)
    return Targets(ids=[f"T{i}" for i in range(n)], xyz=xyz, normals=normals, kind=np.full(n, "retro"),
                   tolerance_m=np.full(n, np.nan), code=np.full(n, -1))


def floor_and_wall() -> trimesh.Trimesh:
    """A floor slab (top at z=0) and a wall across it at y in [0.05, 0.07], 0.3 m high."""
    floor = trimesh.creation.box(extents=(0.4, 0.4, 0.02))
    floor.apply_translation((0, 0, -0.01))
    wall = trimesh.creation.box(extents=(0.4, 0.02, 0.3))
    wall.apply_translation((0, 0.06, 0.15))
    return trimesh.util.concatenate([floor, wall])


def one_target_part(xyz=(0.0, 0.1, 0.0), normal=(0.0, 0.0, 1.0), diameter=0.006) -> Part:
    return Part("floor-wall", floor_and_wall(), make_targets([xyz], [normal]), target_diameter_m=diameter)


def seen(part, eye, options=OPEN, backend="embree", aim=None) -> bool:
    target = part.targets.xyz[0] if aim is None else np.asarray(aim, float)
    T = look_at(np.asarray(eye, float), target, up=(0, 0, 1))
    return bool(compute_visibility(part, INTR, T[None], options, backend=backend)[0, 0])


@pytest.mark.parametrize("backend", ["embree", "numpy"])
def test_target_behind_wall_is_occluded_and_in_the_open_is_visible(backend):
    part = one_target_part()
    assert seen(part, (0.0, 0.5, 0.6), backend=backend)  # same side as the target
    assert not seen(part, (0.0, -0.3, 0.6), backend=backend)  # the wall is in between
    no_rays = VisibilityOptions(**{**OPEN.__dict__, "check_occlusion": False})
    assert seen(part, (0.0, -0.3, 0.6), options=no_rays, backend=backend)


def test_target_facing_away_is_not_visible():
    part = one_target_part(xyz=(0.0, 0.15, -0.02), normal=(0.0, 0.0, -1.0))  # underside of the floor
    assert not seen(part, (0.0, 0.5, 0.6))
    assert not seen(part, (0.0, 0.5, 0.6), options=VisibilityOptions(**{**OPEN.__dict__, "check_occlusion": False}))


def test_margin_rejects_a_target_imaged_near_the_border():
    part = one_target_part()
    eye = np.array([0.0, 0.4, 0.8])
    aim = part.targets.xyz[0] + np.array([0.35, 0.0, 0.0])
    T = look_at(eye, aim, up=(0, 0, 1))
    u = project(INTR, invert(T), part.targets.xyz)[0]
    to_border = min(u[0] + 0.5, INTR.width - 0.5 - u[0], u[1] + 0.5, INTR.height - 0.5 - u[1])
    assert 5 < to_border < 400
    tight = VisibilityOptions(**{**OPEN.__dict__, "margin_px": to_border + 1.0})
    loose = VisibilityOptions(**{**OPEN.__dict__, "margin_px": to_border - 1.0})
    assert not compute_visibility(part, INTR, T[None], tight)[0, 0]
    assert compute_visibility(part, INTR, T[None], loose)[0, 0]


def test_depth_of_field_bounds_the_target_depth():
    part = one_target_part()
    eye = (0.0, 0.1, 0.7)  # straight above: depth 0.7 m
    assert seen(part, eye, VisibilityOptions(**{**OPEN.__dict__, "near_m": 0.6, "far_m": 0.8}))
    assert not seen(part, eye, VisibilityOptions(**{**OPEN.__dict__, "near_m": 0.75, "far_m": 1.0}))
    assert not seen(part, eye, VisibilityOptions(**{**OPEN.__dict__, "near_m": 0.1, "far_m": 0.65}))


def test_incidence_angle_limit():
    part = one_target_part()
    eye = (0.0, 0.1 + 0.5 * np.sin(np.deg2rad(50)), 0.5 * np.cos(np.deg2rad(50)))  # 50 deg off the normal
    assert seen(part, eye, VisibilityOptions(**{**OPEN.__dict__, "incidence_max_rad": np.deg2rad(55)}))
    assert not seen(part, eye, VisibilityOptions(**{**OPEN.__dict__, "incidence_max_rad": np.deg2rad(45)}))


def test_small_target_image_is_rejected():
    part = one_target_part(diameter=0.004)
    eye = (0.0, 0.1, 1.0)  # 0.004 m * 2000 px / 1.0 m = 8 px
    assert seen(part, eye, VisibilityOptions(**{**OPEN.__dict__, "min_target_px": 7.5}))
    assert not seen(part, eye, VisibilityOptions(**{**OPEN.__dict__, "min_target_px": 8.5}))


@pytest.mark.parametrize("backend", ["embree", "numpy"])
def test_segment_test_ignores_the_mesh_beyond_the_camera(backend):
    occ = Occluder(floor_and_wall(), backend=backend)
    start = np.array([[0.0, -0.2, 0.1]])
    assert not occ.occluded(start, np.array([[0.0, 0.0, 0.1]]))[0]  # stops short of the wall
    assert occ.occluded(start, np.array([[0.0, 0.2, 0.1]]))[0]  # crosses it


def test_embree_and_numpy_backends_agree_on_random_segments():
    mesh = make_bracket()
    rng = np.random.default_rng(3)
    lo, hi = mesh.bounds
    starts = lo + rng.random((4000, 3)) * (hi - lo)
    ends = starts + rng.normal(size=(4000, 3)) * 0.3
    a = Occluder(mesh, "embree").occluded(starts, ends)
    b = Occluder(mesh, "numpy").occluded(starts, ends)
    assert 0.1 < a.mean() < 0.9
    # float32 (embree) vs float64 may differ only for grazing rays
    assert np.count_nonzero(a != b) <= 4


def test_embree_and_numpy_visibility_agree_on_the_bracket():
    mesh = make_bracket()
    part = Part("bracket", mesh, sample_targets(mesh, 150, np.random.default_rng(0)))
    s = ViewingSphere.for_part(part, INTR)
    T = s.poses(s.candidates(40, 2))
    a = compute_visibility(part, INTR, T, backend="embree")
    b = compute_visibility(part, INTR, T, backend="numpy")
    geo = compute_visibility(part, INTR, T, VisibilityOptions(check_occlusion=False))
    assert a.sum() > 500 and (geo & ~a).sum() > 50  # the part does occlude itself here
    assert np.count_nonzero(a != b) <= 2


def small_db_inputs():
    mesh = make_bracket()
    part = Part("bracket", mesh, sample_targets(mesh, 60, np.random.default_rng(1)))
    return part, ViewingSphere.for_part(part, INTR)


def test_database_is_stored_and_reused_for_the_same_inputs(tmp_path):
    part, s = small_db_inputs()
    calls = []
    db = VisibilityDB.load_or_build(part, INTR, s, VisibilityOptions(), 120, cache_dir=tmp_path,
                                    progress=lambda stage, f: calls.append((stage, f)))
    assert not db.from_cache
    assert db.visible.shape == (120, 60) and db.genes.shape == (120, 6) and db.part_from_cam.shape == (120, 4, 4)
    fractions = [f for _, f in calls]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    files = list(tmp_path.iterdir())
    assert [f.name for f in files] == [f"visibility-{db.key}.npz"]
    again = VisibilityDB.load_or_build(part, INTR, s, VisibilityOptions(), 120, cache_dir=tmp_path)
    assert again.from_cache and again.key == db.key
    np.testing.assert_array_equal(again.visible, db.visible)
    np.testing.assert_allclose(again.part_from_cam, db.part_from_cam)
    # the database equals a direct computation
    np.testing.assert_array_equal(db.visible, compute_visibility(part, INTR, db.part_from_cam))


def test_database_key_changes_with_options_camera_and_targets(tmp_path):
    part, s = small_db_inputs()
    base = VisibilityDB.load_or_build(part, INTR, s, VisibilityOptions(), 60, cache_dir=tmp_path).key
    other_opt = VisibilityDB.load_or_build(part, INTR, s, VisibilityOptions(margin_px=30), 60, cache_dir=tmp_path).key
    intr2 = Intrinsics(**{**INTR.to_dict(), "fx_px": 2100.0})
    other_cam = VisibilityDB.load_or_build(part, intr2, s, VisibilityOptions(), 60, cache_dir=tmp_path).key
    moved = Part(part.name, part.mesh, make_targets(part.targets.xyz + 1e-6, part.targets.normals))
    other_tg = VisibilityDB.load_or_build(moved, INTR, s, VisibilityOptions(), 60, cache_dir=tmp_path).key
    assert len({base, other_opt, other_cam, other_tg}) == 4
    assert len(list(tmp_path.glob("visibility-*.npz"))) == 4
    assert not list(tmp_path.glob("*.tmp"))


def test_damaged_cache_file_is_rebuilt(tmp_path):
    part, s = small_db_inputs()
    db = VisibilityDB.load_or_build(part, INTR, s, n_candidates=60, cache_dir=tmp_path)
    path = tmp_path / f"visibility-{db.key}.npz"
    path.write_bytes(path.read_bytes()[:50])
    again = VisibilityDB.load_or_build(part, INTR, s, n_candidates=60, cache_dir=tmp_path)
    assert not again.from_cache
    np.testing.assert_array_equal(again.visible, db.visible)
    assert VisibilityDB.load_or_build(part, INTR, s, n_candidates=60, cache_dir=tmp_path).from_cache


def test_cache_dir_defaults_to_env(tmp_path, monkeypatch):
    monkeypatch.setenv("CELL_CACHE_DIR", str(tmp_path / "cache"))
    part, s = small_db_inputs()
    db = VisibilityDB.load_or_build(part, INTR, s, n_candidates=30)
    assert (tmp_path / "cache" / f"visibility-{db.key}.npz").is_file()


def test_nearest_snaps_a_perturbed_station_to_its_candidate():
    part, s = small_db_inputs()
    db = VisibilityDB.build(part, INTR, s, n_candidates=300)
    rng = np.random.default_rng(5)
    idx = rng.integers(0, len(db.genes), 50)
    g = db.genes[idx].copy()
    g[:, 0] += rng.normal(scale=1e-3, size=50)
    g[:, 1] += rng.normal(scale=1e-3, size=50)
    g[:, 2] += rng.normal(scale=1e-3, size=50)
    g[:, 3:] = rng.normal(scale=0.01, size=(50, 3))  # roll and offset are ignored
    np.testing.assert_array_equal(db.nearest(g), idx)
    assert db.nearest(g.reshape(5, 10, 6)).shape == (5, 10)


def test_bad_inputs_raise_planning_error():
    with pytest.raises(PlanningError, match="backend"):
        Occluder(floor_and_wall(), backend="optix")
    with pytest.raises(PlanningError, match="near_m"):
        VisibilityOptions(near_m=1.0, far_m=0.5)
    with pytest.raises(PlanningError, match="incidence"):
        VisibilityOptions(incidence_max_rad=2.0)
