"""Bad input is found at ``cell check``, never after the robot moved: every number of a job file is
checked (finite, in range, intervals ordered), a job needs targets enough and a scale bar between two
of them, a plan's stations have unique ids and proper rotations, and a mesh that is garbage or too
large for memory is one clear line. Each case exits 2 with one line naming what and where."""
from __future__ import annotations

import json
import resource
import struct
import subprocess

import numpy as np
import pytest

from cell.cli import main as cell_main
from jobutil import EXAMPLE, cell_command, child_env, example_run, job_variant

NAN, INF = float("nan"), float("inf")
PLACE = {"xyz": [700.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 90.0]}

CASES = {
    "placement NaN": ({"cell": {"base_from_part": PLACE | {"xyz": [700.0, NAN, 0.0]}}}, "cell.base_from_part.xyz"),
    "rotation inf": ({"cell": {"flange_from_cam": {"xyz": [0.0, 40.0, 90.0], "rpy_deg": [0.0, INF, 0.0]}}},
                     "cell.flange_from_cam.rpy_deg"),
    "distortion NaN": ({"camera": {"k1": NAN}}, "camera.k1"),
    "principal point NaN": ({"camera": {"cx_px": NAN}}, "camera.cx_px"),
    "principal point off the image": ({"camera": {"cx_px": 5000.0}}, "outside the image"),
    "table_z NaN": ({"cell": {"table_z": NAN}}, "cell.table_z"),
    "elevation min > max": ({"planning": {"elevation_min_deg": 70.0, "elevation_max_deg": 30.0}},
                            "elevation_min_deg"),
    "inverted workspace": ({"cell": {"workspace_min": [1000.0, 1000.0, 1000.0],
                                     "workspace_max": [-1000.0, -1000.0, 0.0]}}, "workspace_min"),
    "1x1 camera": ({"camera": {"width": 1, "height": 1}}, "camera.width"),
    "noise = inf": ({"sim": {"noise": INF}}, "sim.noise"),
    "settle_s = 1e300": ({"cell": {"settle_s": 1e300}}, "cell.settle_s"),
    "placement 1e300 mm": ({"cell": {"base_from_part": PLACE | {"xyz": [1e300, 0.0, 0.0]}}}, "beyond any cell"),
    "scale bar to itself": ({"job": {"scale_bar": {"a": "T0094", "b": "T0094", "length": 1.0}}}, "two different"),
    "negative seed": ({"job": {"seed": -1}}, "job.seed"),
    "one target": ({"job": {"targets": "one.csv", "scale_bar": None}}, "at least 6"),
    "garbage obj": ({"job": {"mesh": "garbage.obj"}}, "not a text OBJ"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_value_exits_2_at_check_with_one_line_naming_it(case, tmp_path, capsys):
    changes, expected = CASES[case]
    job = job_variant(tmp_path / "job", changes)
    lines = (EXAMPLE / "targets.csv").read_text().splitlines()
    (tmp_path / "job" / "one.csv").write_text("\n".join(lines[:2]) + "\n")
    (tmp_path / "job" / "garbage.obj").write_bytes(np.random.default_rng(1).integers(0, 256, 4000, np.uint8).tobytes())
    code = cell_main(["check", str(job), "--json"])
    out, err = capsys.readouterr()
    errors = [ln for ln in err.splitlines() if ln.startswith("cell: error:")]
    assert code == 2 and len(errors) == 1 and "Traceback" not in err, err
    assert expected in errors[0] and str(job.parent) in errors[0], errors[0]
    assert json.loads(out)["exit_code"] == 2


def test_bad_value_leaves_nothing_in_the_archive(tmp_path, capsys):
    job = job_variant(tmp_path / "job", {"cell": {"table_z": NAN}})
    code = cell_main(["run", str(job), "--archive", str(tmp_path / "archive")])
    assert code == 2 and "cell.table_z" in capsys.readouterr().err
    assert not (tmp_path / "archive").exists() or not [p for p in (tmp_path / "archive").rglob("*") if p.is_dir()]


def _rotz(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


@pytest.mark.parametrize("damage", ["duplicate id", "mirrored rotation", "scaled rotation", "non-finite pose",
                                    "another camera", "another part", "other targets"])
def test_hand_edited_plan_is_refused_by_check(damage, tmp_path, tmp_path_factory, capsys):
    _, folder, _ = example_run(tmp_path_factory)
    plan = json.loads((folder / "plan.json").read_text())
    st = plan["stations"]
    if damage == "another camera":  # reachable all the same: check said OK (an outside check; decision 0057)
        plan["camera"]["fx_px"] = 1000.0
        expected = "planned for another camera (fx_px 1000.0 there"
    elif damage == "another part":
        plan["targets"][5]["xyz"][0] += 0.01
        expected = "planned for another part: 1 target(s)"
    elif damage == "other targets":
        plan["targets"] = plan["targets"][:-10]
        expected = "planned for other targets (10 of the job's missing"
    elif damage == "duplicate id":
        st[3]["id"] = st[1]["id"]
        expected = f"station id {st[1]['id']!r} appears twice"
    else:
        T = np.asarray(st[2]["part_from_cam"])
        if damage == "mirrored rotation":
            T[:3, 0] *= -1
            expected = "a mirror"
        elif damage == "scaled rotation":
            T[:3, :3] *= 1.01
            expected = "not orthonormal"
        else:
            T[0, 3] = NAN
            expected = "non-finite"
        st[2]["part_from_cam"] = T.tolist()
    bad = tmp_path / "plan.json"
    bad.write_text(json.dumps(plan))
    job = job_variant(tmp_path / "job")
    code = cell_main(["check", str(job), "--plan", str(bad)])
    err = capsys.readouterr().err
    assert code == 2 and expected in err and "Traceback" not in err, err


def test_mesh_too_large_for_memory_is_one_line(tmp_path):
    """A 5.6 GB binary STL (sparse: it costs no disk) under a 3 GiB address-space limit."""
    job = job_variant(tmp_path / "job", {"job": {"mesh": "huge.stl"}})
    n = 120_000_000
    with open(tmp_path / "job" / "huge.stl", "wb") as f:
        f.write(b"\0" * 80 + struct.pack("<I", n))
        f.truncate(84 + 50 * n)

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))

    p = subprocess.run([*cell_command(), "check", str(job)], capture_output=True, text=True, env=child_env(),
                       preexec_fn=limit, timeout=120)
    assert p.returncode == 2 and "does not fit in this machine's memory" in p.stderr, p.stderr[-2000:]
    assert "Traceback" not in p.stderr
