"""Job files: validated, unknown keys forbidden, units converted; the CLI says what and where in one line."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration.errors import JobSpecError
from cell.jobspec import load_job
from cell.loadedjob import load

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "bracket"


@pytest.fixture()
def job_dir(tmp_path):
    for f in EXAMPLE.iterdir():
        if f.is_file():
            shutil.copy(f, tmp_path / f.name)
    return tmp_path


def _edit(job_dir, old, new):
    p = job_dir / "job.toml"
    text = p.read_text()
    assert old in text
    p.write_text(text.replace(old, new, 1))
    return p


def test_example_job_loads_in_si_units():
    job = load(EXAMPLE / "job.toml")
    assert job.spec.scale == 1e-3
    np.testing.assert_allclose(job.spec.base_from_part()[:3, 3], [0.7, 0.0, 0.0])
    assert job.intrinsics.fx_px == pytest.approx(8e-3 / 3.45e-6)
    assert job.part.target_diameter_m == pytest.approx(0.005)
    assert 100 <= len(job.part.targets) <= 300
    assert np.count_nonzero(np.linalg.norm(job.deviations, axis=1)) == 6
    assert job.tolerance_m.min() == pytest.approx(2.5e-4)
    assert len(job.scale_bars) == 1 and job.scale_bars[0][2] == pytest.approx(0.3573936)


@pytest.mark.parametrize("old,new,message", [
    ('seed = 7', 'seed = 7\ncolour = "red"', "unknown key 'job.colour'"),
    ('name = "bracket"\n', '', "missing required key 'job.name'"),
    ('width = 2448', 'width = "wide"', "'camera.width' = 'wide'"),
    ('units = "mm"', 'units = "furlong"', "'job.units' = 'furlong'"),
    ('far = 700.0', 'far = 100.0', "camera.far must be greater"),
    ('targets = "targets.csv"', 'targets = "targets.csv"\nn_targets = 50', "exactly one of 'targets'"),
])
def test_bad_job_file_is_one_line_naming_the_key(job_dir, old, new, message):
    p = _edit(job_dir, old, new)
    with pytest.raises(JobSpecError) as e:
        load_job(p)
    assert message in str(e.value) and str(p) in str(e.value) and "\n" not in str(e.value)


def test_model_search_weights_need_the_bundle_to_weigh_rays_by_the_model_too(job_dir):
    from cell.setup import search_weights

    assert search_weights(load(job_dir / "job.toml")) == "sigma"  # the default (decision 0031)
    _edit(job_dir, "min_rays = 3", 'min_rays = 3\nsearch_weights = "model"')
    assert search_weights(load(job_dir / "job.toml")) == "model"
    p = _edit(job_dir, "sigma_px = 0.05", 'sigma_px = 0.05\nobservation_weights = "equal"')
    with pytest.raises(JobSpecError, match="planning.search_weights = 'model' needs camera.observation_weights"):
        load_job(p)


def test_not_toml(job_dir):
    p = job_dir / "job.toml"
    p.write_text("[job\nname=")
    with pytest.raises(JobSpecError, match="not valid TOML"):
        load_job(p)


def test_scale_bar_naming_an_unknown_target(job_dir):
    p = _edit(job_dir, 'a = "T0094"', 'a = "C99"')
    with pytest.raises(JobSpecError, match="C99"):
        load(p)


BAR = 'scale_bar = { a = "T0094", b = "T0100", length = 357.3936, sigma = 0.002 }'
SECOND = '{ a = "T0012", b = "T0094", length = %s, sigma = 0.002 }'


def _two_bars(job_dir, second: str):
    return _edit(job_dir, BAR, 'scale_bars = [ { a = "T0094", b = "T0100", length = 357.3936, sigma = 0.002 }, '
                               + second + ' ]')


def _cad(job, a: str, b: str) -> float:
    i = job.part.targets.index()
    return float(np.linalg.norm(job.part.targets.xyz[i[a]] - job.part.targets.xyz[i[b]])) * 1e3


def test_several_scale_bars_load_in_order_in_metres_and_may_share_an_end(job_dir):
    L = _cad(load(EXAMPLE / "job.toml"), "T0012", "T0094")
    job = load(_two_bars(job_dir, SECOND % f"{L:.4f}"))  # T0094 ends both bars: independent certificates, allowed
    ids = job.part.targets.ids
    assert [(ids[a], ids[b]) for a, b, _, _ in job.scale_bars] == [("T0094", "T0100"), ("T0012", "T0094")]
    assert job.scale_bars[1][2] == pytest.approx(L * 1e-3) and job.scale_bars[1][3] == pytest.approx(2e-6)
    assert not hasattr(job, "scale_bar")  # no attribute that silently means "the first bar"
    assert [b["a"] for b in job.summary()["scale_bars"]] == ["T0094", "T0012"]


@pytest.mark.parametrize("second,message", [
    (SECOND % "300.0", "job.scale_bars[1] length 300.0 mm differs from the CAD distance"),
    ('{ a = "T0012", b = "X9", length = 300.0 }', "job.scale_bars[1] names target 'X9'"),
    ('{ a = "T0012", b = "T0012", length = 300.0 }', "'job.scale_bars[1]'"),
    ('{ a = "T0100", b = "T0094", length = 357.3936, sigma = 0.001 }', "job.scale_bars[1] joins T0100 and T0094, as "
                                                                        "job.scale_bars[0] does"),
    ('{ a = "T0012", b = "T0094", length = -1.0 }', "'job.scale_bars[1].length' = -1.0"),
])
def test_each_scale_bar_is_checked_with_its_index_in_the_message(job_dir, second, message):
    p = _two_bars(job_dir, second)
    with pytest.raises(JobSpecError) as e:
        load(p)
    assert message in str(e.value) and str(p) in str(e.value) and "\n" not in str(e.value)


def test_scale_bar_and_scale_bars_together_are_refused_in_one_line(job_dir):
    p = _edit(job_dir, BAR, BAR + '\nscale_bars = [ { a = "T0012", b = "T0094", length = 300.0 } ]')
    r = _cli("check", p)
    assert r.returncode == 2 and "either 'scale_bar' (one bar) or 'scale_bars'" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


def _cli(*args, cwd=None):
    env = dict(os.environ, PYTHONPATH=str(EXAMPLE.parents[1]))
    return subprocess.run([sys.executable, "-m", "cell.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=120)


def test_cli_check_prints_summary_and_json():
    r = _cli("check", EXAMPLE / "job.toml", "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["part"]["targets"] == 200 and doc["part"]["mesh"]["watertight"] is True
    assert "check  OK" in r.stderr
    assert doc["measurability"]["unmeasurable"] == [] and doc["measurability"]["min_rays"] == 3


def test_cli_check_names_targets_that_cannot_get_min_rays_stations(job_dir):
    # the walls' dots face sideways: within 10 deg of their normal no station above 20 deg elevation sees them
    _edit(job_dir, "incidence_max_deg = 60.0", "incidence_max_deg = 10.0")
    r = _cli("check", job_dir / "job.toml")
    assert r.returncode == 2, r.stderr
    line = [l for l in r.stderr.splitlines() if l.strip()]
    assert len(line) == 1 and "cannot be seen by [planning] min_rays = 3" in line[0] and "T0" in line[0]
    assert "[planning] incidence_max_deg" in line[0]


@pytest.mark.parametrize("table,message", [
    ('[alignment]\nmethod = "rps"', "needs 'rps'"),
    ('[alignment]\nmethod = "rps"\nrps = { T0001 = "z", T0002 = "z" }', "locks 2 axes"),
    ('[alignment]\nmethod = "rps"\nrps = { T0001 = "z", T0002 = "z", T0003 = "z", T0004 = "x", T0005 = "x", '
     'NOPE = "y" }', "NOPE"),
    ('[alignment]\ntargets = ["T0001", "T9999"]', "T9999"),
])
def test_alignment_section_is_checked_at_load(job_dir, table, message):
    (job_dir / "job.toml").write_text((job_dir / "job.toml").read_text() + "\n" + table + "\n")
    with pytest.raises(JobSpecError, match=message):
        load(job_dir / "job.toml")


@pytest.mark.parametrize("case", ["unknown_key", "missing_mesh", "truncated_stl", "targets_missing_column",
                                  "furlong"])
def test_cli_bad_input_exits_2_with_one_line_and_no_traceback(job_dir, case):
    if case == "unknown_key":
        _edit(job_dir, "[camera]", "[camera]\nzoom = 2")
    elif case == "missing_mesh":
        (job_dir / "bracket.stl").unlink()
    elif case == "truncated_stl":
        data = (job_dir / "bracket.stl").read_bytes()
        (job_dir / "bracket.stl").write_bytes(data[:200])
    elif case == "targets_missing_column":
        lines = (job_dir / "targets.csv").read_text().splitlines()
        (job_dir / "targets.csv").write_text("\n".join(",".join(l.split(",")[:6]) for l in lines) + "\n")
    elif case == "furlong":
        _edit(job_dir, 'units = "mm"', 'units = "furlong"')
    before = {p.name: p.read_bytes() for p in job_dir.iterdir()}
    r = _cli("check", job_dir / "job.toml")
    assert r.returncode == 2
    lines = [l for l in r.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and lines[0].startswith("cell: error: "), r.stderr
    assert "Traceback" not in r.stderr
    # a check writes nothing: the job folder is byte for byte as it was
    assert {p.name: p.read_bytes() for p in job_dir.iterdir()} == before


def test_cli_usage_error_exits_2():
    r = _cli("frobnicate")
    assert r.returncode == 2


def test_cli_plan_with_bound_reports_how_good_any_network_could_be(job_dir, tmp_path):
    out = tmp_path / "plan.json"
    r = _cli("plan", job_dir / "job.toml", "--out", out, "--bound", "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    plan = json.loads(out.read_text())
    assert plan["search"]["lower_bound_sigma_m"] == pytest.approx(doc["lower_bound_sigma_m"])
    assert doc["plan_over_lower_bound"] == pytest.approx(doc["predicted_sigma_max_m"] / doc["lower_bound_sigma_m"])
    # the plan may beat the database's bound only by what the polish gains off the database
    assert 0.8 < doc["plan_over_lower_bound"] < 1.5
    assert "bound  no 16-station network" in r.stderr


def _sim_refusals(job_dir, backend: str, host: str | None):
    _edit(job_dir, 'backend = "sim"', f'backend = "{backend}"' + (f'\nhost = "{host}"' if host else ""))
    return _edit(job_dir, "[sim]", '[sim]\nunreachable_stations = ["S003"]')


@pytest.mark.parametrize("host", ["192.168.10.20", "ur-cell-3.local", "localhost"])
def test_sim_unreachable_stations_with_a_real_ur_is_refused_at_load(job_dir, host):
    # a simulation device: only the simulated robot and the loopback UR controller (127.x.x.x) take it
    p = _sim_refusals(job_dir, "ur", host)
    with pytest.raises(JobSpecError) as e:
        load_job(p)
    msg = str(e.value)
    assert str(p) in msg and "\n" not in msg and "[sim] unreachable_stations" in msg and host in msg
    assert "loopback" in msg


@pytest.mark.parametrize("backend,host", [("ur", "127.0.9.10"), ("ur", None), ("ur", "::1"), ("sim", "10.1.2.3")])
def test_sim_unreachable_stations_loads_with_the_simulated_robot_or_the_loopback_controller(job_dir, backend, host):
    spec, _ = load_job(_sim_refusals(job_dir, backend, host))
    assert spec.sim.unreachable_stations == ["S003"] and spec.cell.backend == backend


def test_cli_check_and_run_refuse_sim_unreachable_stations_for_a_real_ur_before_writing(job_dir, tmp_path):
    p = _sim_refusals(job_dir, "ur", "192.168.10.20")
    before = {q.name: q.read_bytes() for q in job_dir.iterdir()}
    r = _cli("check", p)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "[sim] unreachable_stations" in lines[0], r.stderr
    # the job file says sim, the command line says ur: the robot that will move is what counts
    _edit(job_dir, 'backend = "ur"', 'backend = "sim"')
    archive = tmp_path / "archive"
    r = _cli("run", p, "--backend", "ur", "--yes", "--archive", archive)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "[sim] unreachable_stations" in lines[0], r.stderr
    assert "192.168.10.20" in lines[0] and "Traceback" not in r.stderr
    assert not archive.exists() or not any(archive.rglob("journal.jsonl"))  # no job folder, nothing journalled
    assert {q.name for q in job_dir.iterdir()} == set(before)


def test_cli_check_says_a_solid_with_faces_missing_is_open(job_dir):
    """A solid with faces missing passed check quietly; its openings let the plan's rays through the part."""
    import trimesh

    mesh = trimesh.load(job_dir / "bracket.stl")
    bottom = np.flatnonzero(mesh.face_normals[:, 2] < -0.99)[:2]  # underneath: no target sits there
    trimesh.Trimesh(mesh.vertices, np.delete(mesh.faces, bottom, axis=0)).export(job_dir / "bracket.stl")
    r = _cli("check", job_dir / "job.toml", "--json")
    assert r.returncode == 0, r.stderr
    m = json.loads(r.stdout)["part"]["mesh"]
    assert not m["watertight"] and m["boundary_loops"] >= 1 and m["boundary_edges"] >= 3
    assert "WARNING the mesh is open" in r.stderr and f"{m['boundary_edges']} edges with one face" in r.stderr


def test_cli_check_says_targets_no_station_sees_are_the_parts_not_the_cells(job_dir):
    """Targets sunk 0.5 mm under the surface were met with "move the part": no placement helps them."""
    import csv

    p = job_dir / "targets.csv"
    with p.open(newline="") as f:
        rows = list(csv.reader(f))
    h = rows[0]
    sunk = [r for r in rows[1:] if r[h.index("kind")] == "retro"][:4]
    for r in sunk:
        for a in "xyz":
            r[h.index(a)] = str(float(r[h.index(a)]) - 0.5 * float(r[h.index("n" + a)]))
    with p.open("w", newline="") as f:
        csv.writer(f).writerows(rows)
    r = _cli("check", job_dir / "job.toml")
    line = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(line) == 1, r.stderr
    assert "4 of them" in line[0] and "covered by the part's own surface" in line[0] and sunk[0][0] in line[0]
    assert "correct the targets file or the units" in line[0] and "move the part" not in line[0]
