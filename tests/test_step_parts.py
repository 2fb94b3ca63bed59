"""STEP parts: trimesh's STEP path (cascadio / OpenCASCADE), the file's units, the tessellation
tolerance, and broken files as clear errors."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from calibration.errors import PartError
from planning.cad import step_length_unit
from planning.part import load_mesh
from planning.step_export import step_text, write_step

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "bracket"


def _cylinder_step(r_mm: float, h_mm: float) -> str:
    """A solid cylinder in mm, written by hand: one cylindrical face, two planar caps, a seam edge."""
    body = f"""#1=CARTESIAN_POINT('',(0.,0.,0.));
#2=CARTESIAN_POINT('',(0.,0.,{h_mm:.6f}));
#3=CARTESIAN_POINT('',({r_mm:.6f},0.,0.));
#4=CARTESIAN_POINT('',({r_mm:.6f},0.,{h_mm:.6f}));
#5=DIRECTION('',(0.,0.,1.));
#6=DIRECTION('',(1.,0.,0.));
#7=AXIS2_PLACEMENT_3D('',#1,#5,#6);
#8=AXIS2_PLACEMENT_3D('',#2,#5,#6);
#9=VERTEX_POINT('',#3);
#10=VERTEX_POINT('',#4);
#11=CIRCLE('',#7,{r_mm:.6f});
#12=CIRCLE('',#8,{r_mm:.6f});
#13=EDGE_CURVE('',#9,#9,#11,.T.);
#14=EDGE_CURVE('',#10,#10,#12,.T.);
#15=VECTOR('',#5,{h_mm:.6f});
#16=LINE('',#3,#15);
#17=EDGE_CURVE('',#9,#10,#16,.T.);
#18=ORIENTED_EDGE('',*,*,#13,.T.);
#19=ORIENTED_EDGE('',*,*,#17,.T.);
#20=ORIENTED_EDGE('',*,*,#14,.F.);
#21=ORIENTED_EDGE('',*,*,#17,.F.);
#22=EDGE_LOOP('',(#18,#19,#20,#21));
#23=FACE_OUTER_BOUND('',#22,.T.);
#24=CYLINDRICAL_SURFACE('',#7,{r_mm:.6f});
#25=ADVANCED_FACE('',(#23),#24,.T.);
#26=ORIENTED_EDGE('',*,*,#13,.F.);
#27=EDGE_LOOP('',(#26));
#28=FACE_OUTER_BOUND('',#27,.T.);
#29=PLANE('',#7);
#30=ADVANCED_FACE('',(#28),#29,.F.);
#31=ORIENTED_EDGE('',*,*,#14,.T.);
#32=EDGE_LOOP('',(#31));
#33=FACE_OUTER_BOUND('',#32,.T.);
#34=PLANE('',#8);
#35=ADVANCED_FACE('',(#33),#34,.T.);
#36=CLOSED_SHELL('',(#25,#30,#35));
#37=MANIFOLD_SOLID_BREP('cylinder',#36);
#40=(LENGTH_UNIT()NAMED_UNIT(*)SI_UNIT(.MILLI.,.METRE.));
#41=(NAMED_UNIT(*)PLANE_ANGLE_UNIT()SI_UNIT($,.RADIAN.));
#42=(NAMED_UNIT(*)SI_UNIT($,.STERADIAN.)SOLID_ANGLE_UNIT());
#43=UNCERTAINTY_MEASURE_WITH_UNIT(LENGTH_MEASURE(1.E-07),#40,'distance_accuracy_value','');
#44=(GEOMETRIC_REPRESENTATION_CONTEXT(3)GLOBAL_UNCERTAINTY_ASSIGNED_CONTEXT((#43))GLOBAL_UNIT_ASSIGNED_CONTEXT((#40,#41,#42))REPRESENTATION_CONTEXT('',''));
#45=ADVANCED_BREP_SHAPE_REPRESENTATION('',(#37,#7),#44);
#46=APPLICATION_CONTEXT('automotive design');
#47=APPLICATION_PROTOCOL_DEFINITION('international standard','automotive_design',2000,#46);
#48=PRODUCT_CONTEXT('',#46,'mechanical');
#49=PRODUCT('cylinder','cylinder','',(#48));
#50=PRODUCT_DEFINITION_FORMATION('','',#49);
#51=PRODUCT_DEFINITION_CONTEXT('part definition',#46,'design');
#52=PRODUCT_DEFINITION('design','',#50,#51);
#53=PRODUCT_DEFINITION_SHAPE('','',#52);
#54=SHAPE_DEFINITION_REPRESENTATION(#53,#45);
"""
    return ("ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION(('cylinder'),'2;1');\nFILE_NAME('c.step','',(''),(''),'','','');\n"
            "FILE_SCHEMA(('AUTOMOTIVE_DESIGN { 1 0 10303 214 1 1 1 1 }'));\nENDSEC;\nDATA;\n" + body
            + "ENDSEC;\nEND-ISO-10303-21;\n")


def test_example_bracket_step_is_the_same_solid_as_its_stl():
    step = load_mesh(EXAMPLE / "bracket.step", "mm")
    stl = load_mesh(EXAMPLE / "bracket.stl", "mm")
    assert step.is_watertight
    np.testing.assert_allclose(step.bounds, stl.bounds, atol=1e-7)
    assert step.volume == pytest.approx(stl.volume, rel=1e-6)
    _, dist, _ = trimesh.proximity.closest_point(stl, step.vertices)
    assert dist.max() < 1e-7


def test_the_files_own_units_are_honoured_not_the_jobs(tmp_path):
    box = trimesh.creation.box(extents=(100.0, 50.0, 20.0))
    write_step(box, tmp_path / "mm.step", units="mm")
    write_step(box, tmp_path / "in.stp", units="inch")
    mm = load_mesh(tmp_path / "mm.step", "mm")
    inch = load_mesh(tmp_path / "in.stp", "mm")  # the job is in mm, the file in inches
    np.testing.assert_allclose(mm.extents, [0.1, 0.05, 0.02], rtol=1e-6)
    np.testing.assert_allclose(inch.extents, [2.54, 1.27, 0.508], rtol=1e-6)
    np.testing.assert_allclose(load_mesh(tmp_path / "mm.step", "in").extents, mm.extents)  # job units do not rescale
    assert step_length_unit((tmp_path / "in.stp").read_text()) == ("inch", 0.0254)
    assert step_length_unit((tmp_path / "mm.step").read_text()) == ("millimetre", 1e-3)


@pytest.mark.parametrize("units, tol, max_sagitta_mm", [("mm", 0.1, 0.1), ("mm", 1.0, 1.0), ("in", 0.004, 0.1016)])
def test_tessellation_tolerance_bounds_the_distance_to_the_surface(tmp_path, units, tol, max_sagitta_mm):
    path = tmp_path / "cyl.step"
    path.write_text(_cylinder_step(50.0, 100.0))
    mesh = load_mesh(path, units, tessellation_tolerance=tol)
    assert mesh.is_watertight
    ring = mesh.vertices[np.abs(mesh.vertices[:, 2]) < 1e-9]
    ring = ring[np.hypot(ring[:, 0], ring[:, 1]) > 0.0499]
    ang = np.sort(np.arctan2(ring[:, 1], ring[:, 0]))
    gap = np.diff(np.r_[ang, ang[0] + 2 * np.pi]).max()
    sagitta_mm = 50.0 * (1 - np.cos(gap / 2))  # chord's largest distance from the true circle
    assert sagitta_mm <= max_sagitta_mm
    assert sagitta_mm > max_sagitta_mm / 10  # the tolerance is used, not a much finer default
    assert mesh.volume == pytest.approx(np.pi * 0.05 ** 2 * 0.1, rel=2 * max_sagitta_mm / 50 + 1e-6)


def _good(tmp_path) -> str:
    return step_text(trimesh.creation.box(extents=(100.0, 50.0, 20.0)), "mm")


@pytest.mark.parametrize("mangle, message", [
    (lambda t: "solid bracket\n" + t, "not a STEP file"),
    (lambda t: t[: len(t) // 2], "cut off"),
    (lambda t: t.split("DATA;")[0] + "DATA;\n#1=CARTESIAN_POINT('',(0.,0.,0.));\nENDSEC;\nEND-ISO-10303-21;\n",
     "holds no solid or surface"),
    (lambda t: t.replace("(LENGTH_UNIT()NAMED_UNIT(*)SI_UNIT(.MILLI.,.METRE.))", "(NAMED_UNIT(*)SI_UNIT($,.SECOND.))"),
     "declares no length unit"),
    (lambda t: t.replace("ADVANCED_FACE(", "ADVANCED_FAEC(").replace("MANIFOLD_SOLID_BREP", "MANIFOLD_SOLID_BERP")
     .replace("#", "@", 40) + "", r"holds no solid|cannot read|no surface"),
])
def test_broken_step_files_are_clear_part_errors(tmp_path, mangle, message):
    path = tmp_path / "bad.step"
    path.write_text(mangle(_good(tmp_path)))
    with pytest.raises(PartError, match=message) as info:
        load_mesh(path, "mm")
    assert str(path) in str(info.value)


def test_step_whose_entities_are_garbage_is_refused_not_empty(tmp_path):
    text = _good(tmp_path)
    head, data = text.split("DATA;")
    garbled = "".join(ch if k % 7 else "Z" for k, ch in enumerate(data))  # corrupt every 7th character
    path = tmp_path / "garbled.step"
    path.write_text(head + "DATA;" + garbled.replace("END-ISO-10303-21", "") + "\nEND-ISO-10303-21;\n"
                    "/* ADVANCED_FACE SI_UNIT(.MILLI.,.METRE.) LENGTH_UNIT() */")
    with pytest.raises(PartError, match=r"cut off|cannot read|could not read all of it|no surface|no solid"):
        load_mesh(path, "mm")


def _iges_patch(w: float, h: float, unit_flag: int, unit_name: str) -> str:
    """A flat w x h rectangle as one IGES rational B-spline surface (entity 128, bilinear), written by hand in the
    fixed 80-column layout (start, global, directory, parameter, terminate sections)."""
    def line(data, sec, seq):
        return f"{data:<72}{sec}{seq:7d}"

    start = [line("bilinear patch", "S", 1)]
    g = (f"1H,,1H;,5Hpatch,9Hpatch.igs,4Hcell,3H1.0,32,38,6,308,15,5Hpatch,1.0,{unit_flag},"
         f"{len(unit_name)}H{unit_name},1,1.0,15H20261122.120000,1.0E-6,{max(w, h):.1f},1Ha,1Hb,11,0,"
         "15H20261122.120000;")
    glob = [line(g[i:i + 72], "G", k + 1) for k, i in enumerate(range(0, len(g), 72))]
    pd = (f"128,1,1,1,1,0,0,1,0,0,0.,0.,1.,1.,0.,0.,1.,1.,1.,1.,1.,1.,0.,0.,0.,{w:.1f},0.,0.,0.,{h:.1f},0.,"
          f"{w:.1f},{h:.1f},0.,0.,1.,0.,1.;")
    par = [f"{pd[i:i + 64]:<64}{1:>8}P{k + 1:7d}" for k, i in enumerate(range(0, len(pd), 64))]
    d1 = "".join(f"{v:>8}" for v in (128, 1, 0, 0, 0, 0, 0, 0, "00000000"))
    d2 = "".join(f"{v:>8}" for v in (128, 0, 0, len(par), 0, "", "", "", 0))
    dirs = [line(d1, "D", 1), line(d2, "D", 2)]
    term = [line(f"S{len(start):7d}G{len(glob):7d}D{len(dirs):7d}P{len(par):7d}", "T", 1)]
    return "\n".join(start + glob + dirs + par + term) + "\n"


@pytest.mark.parametrize("unit_flag, unit_name, metres_per_unit", [(2, "MM", 1e-3), (1, "IN", 0.0254)])
def test_iges_surface_loads_in_its_own_units_and_prints_nothing_on_stdout(tmp_path, capfd, unit_flag, unit_name,
                                                                          metres_per_unit):
    path = tmp_path / "patch.igs"
    path.write_text(_iges_patch(100.0, 50.0, unit_flag, unit_name))
    mesh = load_mesh(path, "mm")
    np.testing.assert_allclose(mesh.extents, [100 * metres_per_unit, 50 * metres_per_unit, 0.0], rtol=1e-6, atol=1e-9)
    assert mesh.area == pytest.approx(5000 * metres_per_unit ** 2, rel=1e-6)
    assert capfd.readouterr().out == ""  # OpenCASCADE's chatter goes to stderr: stdout carries the --json document


def test_iges_that_is_not_iges_or_cut_off_is_refused(tmp_path):
    path = tmp_path / "part.igs"
    path.write_text("hello\n")
    with pytest.raises(PartError, match="not an IGES file"):
        load_mesh(path, "mm")
    path.write_text(" " * 72 + "S      1\n" + " " * 72 + "G      1\n")
    with pytest.raises(PartError, match="IGES file is cut off"):
        load_mesh(path, "mm")


def test_job_with_a_step_part_loads(tmp_path):
    from cell.loadedjob import load

    job = load(EXAMPLE / "job_step.toml")
    assert job.part.mesh.is_watertight and len(job.part.targets) == 200
    np.testing.assert_allclose(job.part.mesh.extents, [0.3, 0.2, 0.18], atol=1e-6)
