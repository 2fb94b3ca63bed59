"""A part placed into the table or a fixed obstacle of the cell is refused where the job loads (decision 0061):
``cell check`` and ``cell run`` (LOAD) say in one line how deep it goes and which key places it, exit 2, and
nothing is planned or run. A part resting on the table passes."""
from __future__ import annotations

import pytest

from calibration.errors import JobSpecError
from cell.loadedjob import load
from jobutil import job_variant, run_cell


def _placed(tmp_path, xyz):
    return job_variant(tmp_path / "job", {"cell": {"base_from_part": {"xyz": list(xyz), "rpy_deg": [0.0, 0.0, 90.0]}}})


def test_a_part_sunk_into_the_table_is_refused_by_check_and_run(tmp_path):
    job = _placed(tmp_path, [700.0, 0.0, -120.0])
    r = run_cell("check", str(job), "--archive", str(tmp_path / "archive"))
    assert r.code == 2, r.stderr[-2000:]
    line = r.stderr.strip().splitlines()[-1]
    assert "120 mm into the table" in line and "[cell] base_from_part" in line and "150 of 200 targets" in line, line
    r = run_cell("run", str(job), "--archive", str(tmp_path / "archive"), "--yes")
    assert r.code == 2 and "into the table" in r.stderr.strip().splitlines()[-1], r.stderr[-2000:]
    archive = tmp_path / "archive"
    assert not archive.exists() or not [d for d in archive.iterdir() if not d.name.startswith(".")]


def test_a_part_resting_on_the_table_loads(tmp_path):
    load(_placed(tmp_path / "a", [700.0, 0.0, 0.0]))  # the example: its lowest face at z = 0
    load(_placed(tmp_path / "b", [700.0, 0.0, -0.3]))  # within the placement's tolerance (0.5 mm)
    with pytest.raises(JobSpecError, match=r"1\.5 mm into the table"):
        load(_placed(tmp_path / "c", [700.0, 0.0, -1.5]))


def test_a_part_into_an_obstacle_is_refused_naming_it(tmp_path):
    with pytest.raises(JobSpecError, match=r"obstacle 'fence' \(up to .* mm inside it\).*\[cell\] base_from_part"):
        load(_placed(tmp_path / "a", [1450.0, 0.0, 0.0]))  # the fence stands at x = 1480..1520 mm
    load(_placed(tmp_path / "b", [1380.3, 0.0, 0.0]))  # its face 0.3 mm into the fence's: touching passes
