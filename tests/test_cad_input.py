"""CAD and targets files as plants export them (decision 0068): a STEP file OpenCASCADE reads only in part, target
normals far from the surface's, a mesh with faces flipped, bodies given twice, and the CSV / file-kind / path /
units slips of an outside tester's ~95 variants of the example, each said in one line naming what and where."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from calibration.errors import PartError
from planning.part import (Targets, check_targets, load_mesh, load_part, load_targets, make_bracket, mesh_health,
                           mesh_warnings, sample_targets)
from planning.step_export import step_text

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "bracket"
HEADER = "id,x,y,z,nx,ny,nz,kind,tolerance,code"


@pytest.fixture(scope="module")
def bracket():
    return make_bracket()


@pytest.fixture(scope="module")
def box_step():
    return step_text(trimesh.creation.box(extents=(100.0, 50.0, 20.0)), "mm")


# --- 1. a STEP file OpenCASCADE reads only in part ------------------------------------------------------------

def test_a_second_body_pointing_at_a_missing_entity_is_refused_not_dropped(tmp_path, box_step, capfd):
    """The tester's S4d: OpenCASCADE said ``Unresolved Reference`` on the C stderr, dropped the body, check OK."""
    text = box_step.replace("#180=MANIFOLD_SOLID_BREP('part',#179);",
                            "#180=MANIFOLD_SOLID_BREP('part',#179);\n#9000=MANIFOLD_SOLID_BREP('second',#999999);")
    text = text.replace("SHAPE_REPRESENTATION('',(#180,#189)", "SHAPE_REPRESENTATION('',(#180,#9000,#189)")
    path = tmp_path / "two.step"
    (tmp_path / "one.step").write_text(box_step)
    assert load_mesh(tmp_path / "one.step", "mm").is_watertight  # the file as written loads, and says nothing
    assert "ERR" not in capfd.readouterr().err
    path.write_text(text)
    with pytest.raises(PartError) as info:
        load_mesh(path, "mm")
    msg = str(info.value)
    assert msg.startswith(f"{path}: OpenCASCADE could not read all of it: ") and "Unresolved Reference" in msg
    assert "#9000 refers to #999999, which the file does not define" in msg and "\n" not in msg
    assert "ERR" not in capfd.readouterr().err  # the raw coloured line no longer leaks


def test_a_face_with_a_syntax_error_is_refused_with_its_line(tmp_path, box_step):
    """The tester's S7c: one ADVANCED_FACE broken, the face dropped, only "the mesh is open" said."""
    line = "#118=ADVANCED_FACE('',(#112),#117,.T.);"
    assert line in box_step
    path = tmp_path / "face.step"
    path.write_text(box_step.replace(line, "#118=ADVANCED_FACE('',((#9999999)),#1,.T.;"))
    lineno = box_step.splitlines().index(line) + 1
    with pytest.raises(PartError, match=rf"could not read all of it \(a STEP syntax error\): .*Incorrect Syntax.*"
                                        rf"line {lineno}: #118's parentheses do not balance"):
        load_mesh(path, "mm")


def test_a_syntax_error_opencascade_cannot_pass_is_said_as_such_not_as_a_missing_glb(tmp_path, box_step):
    """The tester's S4e: ``FileNotFoundError ... converted.glb``."""
    path = tmp_path / "syntax.step"
    text = box_step.replace("SHAPE_REPRESENTATION('',(#180,#189)", "SHAPE_REPRESENTATION('',(#180,#9000,#189)")
    head, tail = text.rsplit("ENDSEC;", 1)
    path.write_text(head + "#9000=MANIFOLD_SOLID_BREP('second',#179;\nENDSEC;" + tail)
    with pytest.raises(PartError, match=r"a STEP syntax error\): .*Line \d+") as info:
        load_mesh(path, "mm")
    assert "converted.glb" not in str(info.value) and "FileNotFoundError" not in str(info.value)


# --- 2. target normals against the surface's -------------------------------------------------------------------

def _rotated(normals: np.ndarray, deg: float) -> np.ndarray:
    """Each normal turned by ``deg`` about an axis across it."""
    a = np.cross(normals, [0.3, 0.5, 0.81])
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    t = np.deg2rad(deg)
    return normals * np.cos(t) + np.cross(a, normals) * np.sin(t)


def _with_normals(t: Targets, normals: np.ndarray) -> Targets:
    u = t.subset(np.arange(len(t)))
    u.normals = normals
    return u


def test_normals_tilted_55_deg_are_said_and_85_deg_or_swapped_columns_refused(bracket):
    t = sample_targets(bracket, 30, np.random.default_rng(4))
    assert check_targets(bracket, t, target_diameter_m=0.005) is None
    note = check_targets(bracket, _with_normals(t, _rotated(t.normals, 55.0)), target_diameter_m=0.005)
    assert note is not None and "up to 55 deg from the surface's (30 beyond 20 deg)" in note and "T0" in note
    with pytest.raises(PartError, match=r"normals of .* are 85 deg from the surface's .*check the nx, ny, nz columns "
                                        r"\(swapped\? another frame\?"):
        check_targets(bracket, _with_normals(t, _rotated(t.normals, 85.0)), target_diameter_m=0.005)
    with pytest.raises(PartError, match=r"are 90 deg from the surface's .*check the nx, ny, nz columns"):
        check_targets(bracket, _with_normals(t, np.abs(t.normals[:, [0, 2, 1]])), target_diameter_m=0.005)


def test_a_target_on_a_sharp_edge_takes_the_face_it_lies_on(tmp_path):
    box = trimesh.creation.box(extents=(0.1, 0.05, 0.02))
    xyz = np.array([[0.05, 0.0, 0.01], [0.05, 0.01, 0.01], [0.0499, -0.01, 0.01], [0.0, 0.0, 0.01],
                    [0.0, 0.025, 0.0], [-0.05, 0.0, 0.0]])
    nrm = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 0, 1.0], [0, 0, 1.0], [0, 1.0, 0], [-1.0, 0, 0]])
    t = Targets(ids=[f"T{i}" for i in range(6)], xyz=xyz, normals=nrm, kind=np.array(["retro"] * 6),
                tolerance_m=np.full(6, np.nan), code=np.full(6, -1))
    assert check_targets(box, t, target_diameter_m=0.002) is None
    t.normals = t.normals.copy()
    t.normals[1] = [np.sqrt(0.5), 0.0, np.sqrt(0.5)]  # on the edge, halfway between its faces: 45 deg from either
    assert check_targets(box, t, target_diameter_m=0.002).startswith("the targets file's normals of T1 are up to 45 deg")


def test_the_examples_targets_pass_without_a_normals_warning():
    part = load_part(EXAMPLE / "bracket.stl", "mm", EXAMPLE / "targets.csv", target_diameter_m=0.005,
                     coded_size_m=0.02)
    assert part.normals_warning is None and part.summary()["normals_warning"] is None
    h = part.summary()["mesh"]
    assert (h["bodies"], h["duplicate_faces"], h["overlapping_bodies"], h["flipped_faces"]) == (1, 0, [], 0)
    assert mesh_warnings(h) == []


# --- 3. a mesh with faces flipped is said before the targets ---------------------------------------------------

def test_faces_flipped_in_the_mesh_are_blamed_on_the_mesh_not_the_targets(bracket):
    t = sample_targets(bracket, 40, np.random.default_rng(5))
    flipped = bracket.copy()
    faces = flipped.faces.copy()
    turn = flipped.face_normals[:, 0] > 0.9  # the +x face(s), as the tester's M4e
    faces[turn] = faces[turn][:, ::-1]
    flipped = trimesh.Trimesh(flipped.vertices, faces, process=False)
    h = mesh_health(flipped)
    assert not h["winding_consistent"] and h["flipped_faces"] == int(turn.sum())
    assert any("not consistently oriented" in w for w in mesh_warnings(h))
    on = t.subset(np.flatnonzero(np.abs(t.xyz[:, 0] - bracket.bounds[1, 0]) > 1e-6))
    extra = Targets(ids=["X1"], xyz=np.array([[bracket.bounds[1, 0], 0.0, 0.015]]), normals=np.array([[1.0, 0, 0]]),
                    kind=np.array(["retro"]), tolerance_m=np.array([np.nan]), code=np.array([-1]))
    both = Targets(ids=on.ids + extra.ids, xyz=np.r_[on.xyz, extra.xyz], normals=np.r_[on.normals, extra.normals],
                   kind=np.r_[on.kind, extra.kind], tolerance_m=np.r_[on.tolerance_m, extra.tolerance_m],
                   code=np.r_[on.code, extra.code])
    with pytest.raises(PartError, match=rf"^targets: the mesh's faces are not consistently oriented "
                                        rf"\({int(turn.sum())} face\(s\) flipped\?\): re-export it with outward normals"):
        check_targets(flipped, both)


def test_an_open_mesh_turned_inside_out_is_not_blamed_on_the_targets_alone(bracket):
    t = sample_targets(bracket, 30, np.random.default_rng(6), min_normal_z=0.5)
    keep = bracket.face_normals[:, 2] > -0.5  # open: the bottom faces gone
    inv = trimesh.Trimesh(bracket.vertices, bracket.faces[keep][:, ::-1], process=True)
    with pytest.raises(PartError, match=r"every target's normal is opposite to the mesh's faces: the mesh is open, "
                                        r"so whether it is inside out cannot be told; re-export it"):
        check_targets(inv, t)


# --- 4. bodies ------------------------------------------------------------------------------------------------

def test_a_body_given_twice_is_said_as_such_not_as_an_open_mesh():
    box = trimesh.creation.box(extents=(0.1, 0.05, 0.02))
    twice = trimesh.Trimesh(np.r_[box.vertices, box.vertices], np.r_[box.faces, box.faces + 8], process=True)
    h = mesh_health(twice)
    assert h["duplicate_faces"] == 12 and h["boundary_edges"] == 0 and h["nonmanifold_edges"] == 18
    w = mesh_warnings(h)
    assert len(w) == 1 and "12 of the mesh's 24 faces are given twice" in w[0] and "open" not in w[0]


@pytest.mark.parametrize("shift, overlap", [(0.00005, [[1, 2]]), (0.0002, [[1, 2]]), (0.2, [])])
def test_a_second_body_near_the_first_is_counted_and_said(shift, overlap):
    box = trimesh.creation.box(extents=(0.1, 0.05, 0.02))
    two = trimesh.Trimesh(np.r_[box.vertices, box.vertices + shift], np.r_[box.faces, box.faces + 8], process=True)
    h = mesh_health(two)
    assert h["bodies"] == 2 and h["overlapping_bodies"] == overlap and h["duplicate_faces"] == 0
    assert any("bodies 1 and 2 of the mesh's 2 overlap" in w for w in mesh_warnings(h)) == bool(overlap)


# --- 5. CSV, file kinds, paths, units -------------------------------------------------------------------------

ROW = "T1,0.0,0.0,30.0,0.0,0.0,1.0,retro,0.25,-1"


@pytest.mark.parametrize("text, match", [
    (HEADER.replace(",", ";") + "\n" + ROW.replace(",", ";") + "\n",
     r":1: targets CSV lacks .*its header is 'id;x;y;.*: the separator must be a comma \(this file uses semicolons"),
    (HEADER.replace(",", "\t") + "\n" + ROW.replace(",", "\t") + "\n", r"the separator must be a comma \(this file uses tabs"),
    (HEADER.upper() + "\n" + ROW + "\n", r"its header is 'ID,X,Y,Z,NX,NY,NZ,KIND,TOLERANCE,CODE': the column names are lower case"),
    ("sep=;\n" + HEADER + "\n" + ROW + "\n", r":1: 'sep=;': the separator must be a comma"),
    (HEADER + "\n" + ROW.replace(",30.0,", ",,") + "\n", r"t\.csv:2: column 'z' is empty$"),
    (HEADER + "\n" + ROW.replace(",30.0,", ",#N/A,") + "\n", r"t\.csv:2: column 'z' holds '#N/A', not a number$"),
    (HEADER + "\n" + ROW.replace(",-1", ",0.5") + "\n", r":2: column 'code': '0.5' is not a whole number"),
])
def test_csv_slips_are_said_with_the_column_and_what_to_do(tmp_path, text, match):
    p = tmp_path / "t.csv"
    p.write_text(text)
    with pytest.raises(PartError, match=match):
        load_targets(p, "mm")


def test_excels_separator_line_empty_rows_and_an_integral_code_are_read(tmp_path):
    p = tmp_path / "t.csv"
    p.write_text("sep=,\n" + HEADER + "\n" + ROW.replace(",retro,0.25,-1", ",coded,,3.0") + "\n"
                 + ROW.replace("T1,", "T2,").replace(",-1", ",-1.0") + "\n,,,,,,,,,\n , ,,,,,,,,\n")
    t = load_targets(p, "mm")
    assert t.ids == ["T1", "T2"] and t.code.tolist() == [3, -1] and t.kind.tolist() == ["coded", "retro"]
    p.write_text(HEADER + "\n" + ROW.replace(",30.0,", ",,") + "\n")  # an empty cell in a row of data is no blank row
    with pytest.raises(PartError, match="column 'z' is empty"):
        load_targets(p, "mm")


def test_a_csv_in_another_encoding_is_told_to_be_saved_as_utf8(tmp_path):
    p = tmp_path / "t.csv"
    p.write_bytes((HEADER + ",note\n" + ROW + ",Prüfteil\n").encode("cp1252"))
    with pytest.raises(PartError, match=r"not UTF-8 text \(byte 0xfc: cp1252 / Latin-1\?\): save it as CSV UTF-8"):
        load_targets(p, "mm")
    p.write_bytes((HEADER + "\n" + ROW + "\n").replace(",", "\t").encode("utf-16"))
    with pytest.raises(PartError, match=r"is UTF-16 text: save it as CSV UTF-8"):
        load_targets(p, "mm")


@pytest.mark.parametrize("content, name, what", [
    (lambda box, step: step, "part.stl", "STEP"),
    (lambda box, step: trimesh.exchange.ply.export_ply(box, encoding="ascii"), "part.stl", "PLY"),
    (lambda box, step: trimesh.exchange.obj.export_obj(box).encode(), "part.stl", "OBJ"),
    (lambda box, step: trimesh.exchange.stl.export_stl_ascii(box).encode(), "part.obj", "ASCII STL"),
    (lambda box, step: trimesh.exchange.stl.export_stl(box), "part.obj", "a binary STL"),
])
def test_a_file_of_another_kind_is_named_for_what_it_holds(tmp_path, box_step, content, name, what):
    box = trimesh.creation.box(extents=(100.0, 50.0, 20.0))
    data = content(box, box_step)
    path = tmp_path / name
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    with pytest.raises(PartError, match=rf"named \.{name[-3:]} but holds {what}"):
        load_mesh(path, "mm")


def test_a_backslash_path_is_told_to_use_slashes(tmp_path):
    with pytest.raises(PartError, match=r'parts\\bracket\.stl: mesh file not found; write paths with "/"'):
        load_mesh(tmp_path / "parts\\bracket.stl", "mm")
    with pytest.raises(PartError, match=r'targets file not found; write paths with "/"'):
        load_targets(tmp_path / "parts\\targets.csv", "mm")


def test_overlapping_targets_on_a_part_implausibly_small_for_its_units_ask_about_the_units(bracket):
    small = bracket.copy()
    small.apply_scale(1 / 25.4)  # the tester's M1b: every length in inches, the job in mm
    t = sample_targets(bracket, 40, np.random.default_rng(7))
    t.xyz = t.xyz / 25.4
    with pytest.raises(PartError, match=r"overlap \(.* mm apart\); the part is 11\.81 mm across in mm: are the units "
                                        r"right \(\[job\] units\)\?$"):
        check_targets(small, t, target_diameter_m=0.005, units="mm")
    with pytest.raises(PartError, match=r"overlap \(.* mm apart\)$"):
        check_targets(small, t, target_diameter_m=0.005)  # without units, no hint
