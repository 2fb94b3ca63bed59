"""Loading CAD meshes and targets: every broken input is one clear PartError, never a silent empty mesh."""
import struct

import numpy as np
import pytest
import trimesh

from calibration.errors import PartError
from planning.part import check_targets, load_mesh, load_part, load_targets, make_bracket, sample_targets


@pytest.fixture(scope="module")
def bracket():
    return make_bracket()


def _stl_bytes(mesh: trimesh.Trimesh) -> bytes:
    return trimesh.exchange.stl.export_stl(mesh)


def test_bracket_is_a_watertight_self_occluding_solid(bracket):
    assert bracket.is_watertight and bracket.is_winding_consistent
    # the pocket makes the volume smaller than the union of base, wall and rib
    assert 0.0028 < bracket.volume < 0.0033
    # self-occlusion: some faces are not on the convex hull
    assert bracket.convex_hull.volume > bracket.volume * 1.5


@pytest.mark.parametrize("suffix,writer", [
    (".stl", lambda m: _stl_bytes(m)),
    (".obj", lambda m: trimesh.exchange.obj.export_obj(m).encode()),
    (".ply", lambda m: trimesh.exchange.ply.export_ply(m)),
    (".glb", lambda m: trimesh.Scene(m).export(file_type="glb")),
])
def test_mesh_formats_load_and_scale_to_metres(tmp_path, bracket, suffix, writer):
    mm = bracket.copy()
    mm.apply_scale(1000.0)
    p = tmp_path / f"part{suffix}"
    p.write_bytes(writer(mm))
    mesh = load_mesh(p, "mm")
    np.testing.assert_allclose(mesh.extents, bracket.extents, rtol=1e-6)


def test_missing_file(tmp_path):
    with pytest.raises(PartError, match="not found"):
        load_mesh(tmp_path / "nope.stl", "mm")


def test_truncated_binary_stl(tmp_path, bracket):
    data = _stl_bytes(bracket)
    p = tmp_path / "cut.stl"
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(PartError, match="truncated"):
        load_mesh(p, "m")


def test_stl_with_face_count_ffffffff(tmp_path, bracket):
    data = bytearray(_stl_bytes(bracket))
    data[80:84] = struct.pack("<I", 0xFFFFFFFF)
    p = tmp_path / "huge.stl"
    p.write_bytes(bytes(data))
    with pytest.raises(PartError, match="4294967295 faces"):
        load_mesh(p, "m")


def test_random_bytes(tmp_path):
    p = tmp_path / "noise.stl"
    p.write_bytes(np.random.default_rng(0).bytes(5000))
    with pytest.raises(PartError, match=r"noise\.stl"):
        load_mesh(p, "m")


def test_nan_vertex_in_binary_stl(tmp_path, bracket):
    data = bytearray(_stl_bytes(bracket))
    data[84 + 12 : 84 + 16] = struct.pack("<f", float("nan"))  # first vertex x of face 0
    p = tmp_path / "nan.stl"
    p.write_bytes(bytes(data))
    with pytest.raises(PartError, match="non-finite"):
        load_mesh(p, "m")


def test_nan_vertex_in_obj(tmp_path):
    p = tmp_path / "nan.obj"
    p.write_text("v 0 0 0\nv 0.1 0 0\nv nan 0.1 0\nf 1 2 3\n")
    with pytest.raises(PartError, match=r"nan\.obj:3: non-finite"):
        load_mesh(p, "m")


def test_obj_face_index_zero(tmp_path):
    p = tmp_path / "zero.obj"
    p.write_text("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 0 1 2\n")
    with pytest.raises(PartError, match=r"zero\.obj:4: face index 0"):
        load_mesh(p, "m")


def test_obj_face_index_out_of_range(tmp_path):
    p = tmp_path / "range.obj"
    p.write_text("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 9\n")
    with pytest.raises(PartError, match="face index 9 out of range"):
        load_mesh(p, "m")


def test_absurd_size_for_the_stated_units(tmp_path, bracket):
    p = tmp_path / "part.stl"
    mm = bracket.copy()
    mm.apply_scale(1000.0)
    p.write_bytes(_stl_bytes(mm))
    with pytest.raises(PartError, match="are the units right"):
        load_mesh(p, "m")  # a 360 m bracket


def test_unknown_units(tmp_path, bracket):
    p = tmp_path / "part.stl"
    p.write_bytes(_stl_bytes(bracket))
    with pytest.raises(PartError, match="unknown units 'furlong'"):
        load_mesh(p, "furlong")


def _write_targets(path, rows, header="id,x,y,z,nx,ny,nz"):
    path.write_text(header + "\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")


def test_targets_csv_missing_column(tmp_path):
    p = tmp_path / "t.csv"
    _write_targets(p, [["T1", 0, 0, 0.03, 0, 0]], header="id,x,y,z,nx,ny")
    with pytest.raises(PartError, match="lacks column.*nz"):
        load_targets(p, "m")


@pytest.mark.parametrize("header, row, match", [
    ("id,x,y,z,nx,ny,nz,tolerence", ["T1", 0, 0, 0.03, 0, 0, 1, 0.001], "unknown column 'tolerence'"),
    ("id,x,y,z,nx,ny,nz,x", ["T1", 0, 0, 0.03, 0, 0, 1, 5], "column 'x' twice"),
    ("id,x,y,z,nx,ny,nz", ["T1", 0, 0, 0.03, 0, 0, 1, 0.001], "8 fields; the header has 7"),
    ("id,x,y,z,nx,ny,nz", ["T\x001", 0, 0, 0.03, 0, 0, 1], "control character"),
])
def test_targets_csv_a_column_misspelt_twice_or_extra_or_a_control_character_is_refused(tmp_path, header, row, match):
    """A misspelt tolerance column read as none would judge every target by the job's default, quietly."""
    p = tmp_path / "t.csv"
    row = [r.encode().decode("unicode_escape") if isinstance(r, str) else r for r in row]
    _write_targets(p, [row], header=header)
    with pytest.raises(PartError, match=match):
        load_targets(p, "m")
    _write_targets(p, [["T1", 0, 0, 0.03, 0, 0, 1, "left flange"]], header="id,x,y,z,nx,ny,nz,note")
    assert load_targets(p, "m").ids == ["T1"]


def test_targets_off_the_surface_duplicates_and_inward_normals(bracket):
    rng = np.random.default_rng(3)
    t = sample_targets(bracket, 20, rng)
    check_targets(bracket, t)  # a good set passes
    off = t.subset(np.arange(20))
    off.xyz = off.xyz.copy()
    off.xyz[4] += off.normals[4] * 0.01
    with pytest.raises(PartError, match="off the part's surface"):
        check_targets(bracket, off)
    dup = t.subset(np.arange(20))
    dup.ids = list(dup.ids)
    dup.ids[3] = dup.ids[2]
    with pytest.raises(PartError, match="duplicate target id"):
        check_targets(bracket, dup)
    inward = t.subset(np.arange(20))
    inward.normals = inward.normals.copy()
    inward.normals[7] *= -1
    with pytest.raises(PartError, match=r"normals of T\d+ are 180 deg from the surface's .* pointing into the part"):
        check_targets(bracket, inward)


def test_sampled_targets_are_reproducible_spread_and_on_the_surface(bracket):
    a = sample_targets(bracket, 150, np.random.default_rng(9), n_coded=6, min_normal_z=-0.5)
    b = sample_targets(bracket, 150, np.random.default_rng(9), n_coded=6, min_normal_z=-0.5)
    np.testing.assert_array_equal(a.xyz, b.xyz)
    assert (a.kind == "coded").sum() == 6 and sorted(a.code[a.code >= 0]) == list(range(6))
    assert (a.normals[:, 2] >= -0.5).all()
    d = np.linalg.norm(a.xyz[:, None] - a.xyz[None], axis=2) + np.eye(150)
    assert d.min() > 0.005
    _, dist, _ = trimesh.proximity.closest_point(bracket, a.xyz)
    assert dist.max() < 1e-9


def test_load_part_from_csv_converts_units(tmp_path, bracket):
    mm = bracket.copy()
    mm.apply_scale(1000.0)
    (tmp_path / "b.stl").write_bytes(_stl_bytes(mm))
    t = sample_targets(bracket, 10, np.random.default_rng(1))
    rows = [[t.ids[i], *(t.xyz[i] * 1000), *t.normals[i]] for i in range(10)]
    _write_targets(tmp_path / "t.csv", rows)
    part = load_part(tmp_path / "b.stl", "mm", targets_csv=tmp_path / "t.csv")
    np.testing.assert_allclose(part.targets.xyz, t.xyz, atol=1e-9)
    assert part.summary()["targets"] == 10


def test_inside_out_mesh_is_named_not_its_targets(tmp_path, bracket):
    """A closed mesh whose faces all point inward: the outside check's message blamed the targets ("200 target
    normal(s) point into the part"); the mesh is named (decision 0057)."""
    m = bracket.copy()
    m.apply_scale(1000.0)
    m.invert()
    m.export(tmp_path / "inverted.stl")
    with pytest.raises(PartError, match="inverted.stl: the mesh is inside out"):
        load_part(tmp_path / "inverted.stl", "mm", n_targets=20, seed=1)
