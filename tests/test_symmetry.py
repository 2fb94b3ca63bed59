"""The symmetries of a target layout (planning/symmetry.py, decision 0058): a disc of plain dots in rings of equal
pitch, placed one pitch turned, has every dot named as its neighbour and no image can tell; the layout says so
before the job (``cell check``, LOAD), and a coded target off the axis takes it back."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from jobutil import REPO, run_cell
from planning.part import load_targets
from planning.symmetry import layout_symmetries, symmetry_note, symmetry_summary

UP = (0.0, 0.0, 1.0)


def disc(r_mm=(110.0, 65.0), phase_deg=(0.0, 15.0), z_mm=20.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The outside tester's disc: two rings of 12 plain dots at 30 deg pitch, the inner one half a pitch on (m)."""
    xyz = [(r * np.cos(a), r * np.sin(a), z_mm) for r, ph in zip(r_mm, phase_deg)
           for a in np.radians(ph + 30.0 * np.arange(12))]
    xyz = np.array(xyz) / 1000
    return xyz, np.tile(UP, (len(xyz), 1)), -np.ones(len(xyz), dtype=int)


def grid(k: int, pitch_m: float = 0.01) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xyz = np.array([(i, j, 0.0) for i in range(k) for j in range(k)]) * pitch_m
    return xyz, np.tile(UP, (len(xyz), 1)), -np.ones(len(xyz), dtype=int)


def _turns(found) -> list[float]:
    return sorted({round(s["angle_deg"], 3) for s in found if s["axis"] is not None and abs(s["axis"][2]) > 0.999})


def test_the_two_ring_disc_maps_onto_itself_under_a_turn_of_one_pitch():
    found = layout_symmetries(*disc())
    first = found[0]
    assert first["angle_deg"] == pytest.approx(30.0, abs=1e-6)
    assert abs(first["axis"][2]) == pytest.approx(1.0)
    assert np.allclose(first["axis_point_m"], [0, 0, 0.020], atol=1e-9)
    assert first["share"] == 1.0 and first["mapped"] == first["moved"] == first["n_targets"] == 24
    assert _turns(found) == [30.0, 60.0, 90.0, 120.0, 150.0, 180.0]  # the whole 12-fold group, both senses
    assert len(found) == 11 and all(s["share"] == 1.0 for s in found)
    note = symmetry_note(first)
    for said in ("30.0 deg", "+z axis", "(24 of 24 targets)", "every dot named as its neighbour", "coded markers",
                 "half a step (15.0 deg"):
        assert said in note, note


def test_one_coded_target_on_the_rim_pins_the_disc():
    xyz, n, labels = disc()
    labels[2] = 17  # a unique code off the axis: no turn carries it onto its code
    assert layout_symmetries(xyz, n, labels) == []


def test_a_coded_target_on_the_axis_leaves_the_turns_that_fix_it():
    xyz, n, labels = disc()
    xyz, n, labels = np.vstack([xyz, [0, 0, 0.020]]), np.vstack([n, UP]), np.append(labels, 5)
    found = layout_symmetries(xyz, n, labels)
    assert _turns(found) == [30.0, 60.0, 90.0, 120.0, 150.0, 180.0]
    assert all(s["mapped"] == 25 and s["moved"] == 24 for s in found)  # the coded one stays where it is


def test_a_random_layout_has_no_symmetry():
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-0.1, 0.1, (400, 3))
    assert layout_symmetries(xyz, rng.normal(size=(400, 3)), -np.ones(400, dtype=int)) == []
    xyz[:, 2] = 0.0  # a flat plate of random dots, every normal up
    assert layout_symmetries(xyz, np.tile(UP, (400, 1)), -np.ones(400, dtype=int)) == []


def test_a_mirror_image_is_not_a_symmetry():
    """A plate mirror-symmetric about its y axis: the half-turn that mirrors it turns its normals over."""
    half = np.array([(0.010, 0.0), (0.030, 0.005), (0.022, 0.041), (0.047, 0.013), (0.015, 0.070)])
    xy = np.vstack([half, half * [-1, 1], [(0.0, 0.023)]])
    xyz = np.c_[xy, np.zeros(len(xy))]
    assert layout_symmetries(xyz, np.tile(UP, (len(xyz), 1)), -np.ones(len(xyz), dtype=int)) == []


def test_a_grid_has_its_quarter_and_half_turns_and_a_one_pitch_shift():
    found = layout_symmetries(*grid(10))
    whole = [s for s in found if s["share"] == 1.0]
    assert _turns(whole) == [90.0, 180.0]  # 90 deg about +z and -z (270), and 180
    assert all(np.allclose(s["axis_point_m"][:2], [0.045, 0.045], atol=1e-9) for s in whole)
    shift = found[0]  # the smallest motion first: one pitch along x or y, 90 of the 100 dots on a neighbour
    assert shift["angle_deg"] == pytest.approx(0.0, abs=1e-6)
    assert shift["slide_m"] == pytest.approx(0.010) and shift["step_m"] == pytest.approx(0.010)
    assert shift["share"] == pytest.approx(0.9) and shift["mapped"] == shift["moved"] == 90
    shifts = {tuple(np.round(np.array(s["translation_m"]) * 1000, 3)) for s in found if s["angle_deg"] < 1e-6}
    assert {(10.0, 0.0, 0.0), (-10.0, 0.0, 0.0), (0.0, 10.0, 0.0), (0.0, -10.0, 0.0)} <= shifts
    assert "shift of 10.0 mm" in symmetry_note(shift) and "(90 of 100 targets)" in symmetry_note(shift)
    assert layout_symmetries(*grid(10), min_share=0.95) == whole  # a stricter share: the whole grid's turns only


def test_the_example_brackets_targets_have_no_symmetry_and_are_judged_in_milliseconds():
    t = load_targets(REPO / "examples" / "bracket" / "targets.csv", "mm")
    t0 = time.perf_counter()
    found = layout_symmetries(t.xyz, t.normals, t.code)
    elapsed = time.perf_counter() - t0
    assert found == []
    assert elapsed < 1.0, elapsed  # 0.01 s on the 2 shared cores
    s = symmetry_summary(t.xyz, t.normals, t.code)
    assert s["warning"] is None and s["symmetries"] == [] and s["tol_m"] > 0


def test_400_targets_in_well_under_a_second_and_20000_without_hanging():
    rng = np.random.default_rng(5)
    xyz = rng.uniform(-0.2, 0.2, (400, 3))
    t0 = time.perf_counter()
    assert layout_symmetries(xyz, rng.normal(size=(400, 3)), -np.ones(400, dtype=int)) == []
    assert time.perf_counter() - t0 < 1.0
    t0 = time.perf_counter()
    found = layout_symmetries(*grid(20))
    assert time.perf_counter() - t0 < 1.0
    assert found[0]["share"] == pytest.approx(0.95)
    big = grid(141)  # 19 881 dots
    t0 = time.perf_counter()
    found = layout_symmetries(*big)
    elapsed = time.perf_counter() - t0
    assert elapsed < 10.0, elapsed  # 0.4 s measured (decision 0058); generous for a shared machine
    assert found[0]["slide_m"] == pytest.approx(0.010) and found[0]["moved"] == 141 * 140
    assert {90.0, 180.0} <= set(_turns(s for s in found if s["share"] == 1.0))


def test_fewer_than_three_targets_or_coincident_ones_give_nothing():
    assert layout_symmetries(np.zeros((2, 3)), np.tile(UP, (2, 1)), [-1, -1]) == []
    assert layout_symmetries(np.zeros((4, 3)), np.tile(UP, (4, 1)), [-1] * 4) == []


# --- the job: cell check and LOAD say it --------------------------------------------------------------------

DISC_JOB = """\
[job]
name = "disc"
number = "BR-1002"
revision = "C"
mesh = "disc.stl"
units = "mm"
targets = "targets.csv"
target_diameter = 5.0
coded_size = 20.0
seed = 7
scale_bar = { a = "T0001", b = "T0007", length = 220.0, sigma = 0.002 }

[camera]
width = 2448
height = 2048
pixel_size_um = 3.45
focal_length_mm = 8.0
sigma_px = 0.05
near = 300.0
far = 700.0

[cell]
robot = "ur10e"
backend = "sim"
base_from_part = { xyz = [700.0, 0.0, 0.0], rpy_deg = [0.0, 0.0, 90.0] }
flange_from_cam = { xyz = [0.0, 40.0, 90.0], rpy_deg = [0.0, 0.0, 0.0] }
table_z = 0.0
obstacles = [
  { name = "fence", size = [40.0, 1600.0, 1200.0], pose = { xyz = [1500.0, 0.0, 600.0] } },
]
max_joint_speed_rad_s = 1.0
max_tcp_speed_m_s = 0.25

[planning]
mode = "fixed"
n_stations = 16
min_rays = 3
incidence_max_deg = 60.0
criterion = "worst"
elevation_min_deg = 20.0
elevation_max_deg = 85.0

[report]
tolerance = 0.25
sigma_factor = 3.0

[sim]
image_sigma_px = 0.0
seed = 11
deviations = "deviations.csv"
motion = "instant"
base_from_part_error = { xyz = [0.0, 0.0, 0.0], rpy_deg = [0.0, 0.0, 30.0] }
"""


def disc_job(folder, coded_rim: bool = False):
    """The outside tester's reproduction (disc 260 mm across, two rings of 12 plain dots, placed one pitch turned)
    as its make.py writes it; ``coded_rim``: T0003 a coded target (code 3) instead."""
    import trimesh

    folder.mkdir(parents=True, exist_ok=True)
    trimesh.creation.cylinder(radius=130.0, height=20.0, sections=96,
                              transform=trimesh.transformations.translation_matrix((0, 0, 10.0))
                              ).export(folder / "disc.stl")
    xyz = disc()[0] * 1000
    rows = ["id,x,y,z,nx,ny,nz,kind,tolerance,code"]
    for k, (x, y, z) in enumerate(xyz, 1):
        kind, code = ("coded", 3) if coded_rim and k == 3 else ("retro", -1)
        rows.append(f"T{k:04d},{x:.4f},{y:.4f},{z:.4f},0,0,1,{kind},0.25,{code}")
    (folder / "targets.csv").write_text("\n".join(rows) + "\n")
    (folder / "deviations.csv").write_text("id,dx,dy,dz\nT0003,0.0,0.0,0.5000\nT0016,0.0,0.0,-0.4000\n")
    (folder / "job.toml").write_text(DISC_JOB)
    return folder / "job.toml"


def test_cell_check_says_the_discs_symmetry_on_stderr_and_in_the_json(tmp_path):
    r = run_cell("check", str(disc_job(tmp_path / "disc")))
    assert r.code == 0, r.stderr
    sym = r.doc["part"]["symmetry"]
    assert sym["symmetries"][0]["angle_deg"] == pytest.approx(30.0, abs=1e-6)
    # a quarter of the median spacing: the inner ring's pitch and the outer dots' distance to the inner ring
    inner, across = 2 * 0.065 * np.sin(np.radians(15)), np.hypot(0.110 - 0.065 * np.cos(np.radians(15)),
                                                                 0.065 * np.sin(np.radians(15)))
    assert sym["symmetries"][0]["moved"] == 24 and sym["tol_m"] == pytest.approx(0.25 * (inner + across) / 2)
    warned = [line for line in r.stderr.splitlines() if line.startswith("targets WARNING")]
    assert len(warned) == 1 and "30.0 deg" in warned[0] and "coded markers" in warned[0], r.stderr
    assert warned[0] == f"targets WARNING {sym['warning']}"


def test_cell_check_of_the_disc_with_a_coded_target_on_its_rim_says_nothing(tmp_path):
    r = run_cell("check", str(disc_job(tmp_path / "disc", coded_rim=True)))
    assert r.code == 0, r.stderr
    sym = r.doc["part"]["symmetry"]
    assert sym["symmetries"] == [] and sym["warning"] is None
    assert "targets WARNING" not in r.stderr


def test_load_writes_the_symmetry_into_part_json_the_journal_and_the_run_log(tmp_path):
    from cell.loadedjob import load
    from cell.record.jobfolder import JobFolder
    from cell.stages import load as load_stage

    class Log:
        def __init__(self):
            self.lines = []

        def log(self, level, message):
            self.lines.append((level, message))

    class Ctx:
        pass

    ctx = Ctx()
    ctx.job = load(disc_job(tmp_path / "disc"))
    (tmp_path / "job").mkdir()
    ctx.folder, ctx.log, said = JobFolder(tmp_path / "job"), Log(), []
    ctx.say = said.append
    load_stage.run(ctx)
    part = ctx.folder.read_json("part.json")["part"]
    assert part["symmetry"]["symmetries"][0]["angle_deg"] == pytest.approx(30.0, abs=1e-6)
    rec = [r for r in ctx.folder.records() if r["event"] == "layout_symmetry"]
    assert len(rec) == 1 and rec[0]["warning"] == part["symmetry"]["warning"]
    assert ctx.log.lines == [("warning", "load: " + part["symmetry"]["warning"])]
    assert said == ["  WARNING " + part["symmetry"]["warning"]]


def test_the_disc_placed_one_step_off_is_reported_with_its_symmetry(tmp_path):
    """The outside tester's case end to end: the dots are named as their neighbours (nothing in the images can tell);
    the report says why its names rest on the placement, in report.json and report.html."""
    job = disc_job(tmp_path / "disc")
    r = run_cell("run", str(job), "--archive", str(tmp_path / "archive"), "--yes", timeout=900)
    assert r.code == 0, r.stderr[-2000:]
    folder = Path(r.doc["folder"])
    rep = json.loads((folder / "report.json").read_text())
    assert "30.0 deg" in rep["layout_symmetry"]["warning"] and "coded markers" in rep["layout_symmetry"]["warning"]
    assert 'id="symmetry-alert"' in (folder / "report.html").read_text()
    assert rep["layout_symmetry"]["warning"] in r.stderr
