"""The cell's core: the state table, the journal, the crash-proof run log, the archive."""
import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from cell.record.archive import Archive
from cell.record.jobfolder import JobFolder, atomic_write_json, utc_now
from cell.record.runlog import RunLog, read_messages
from cell.states import STAGES, TRANSITIONS, State, TransitionError, check_transition


def test_state_table_runs_the_stages_in_order_and_ends_in_terminal_states():
    path = [State.CREATED, *STAGES, State.DONE]
    for a, b in zip(path, path[1:]):
        check_transition(a, b)
    assert not TRANSITIONS[State.DONE]
    for s in STAGES:
        assert {State.FAULTED, State.ABORTED} <= TRANSITIONS[s]


@pytest.mark.parametrize("a,b", [(State.LOAD, State.ACQUIRE), (State.DONE, State.LOAD), (State.PLAN, State.LOAD)])
def test_state_table_refuses_skips_and_restarts(a, b):
    with pytest.raises(TransitionError, match=f"can't go from {a.value} to {b.value}"):
        check_transition(a, b)


def test_journal_ignores_a_torn_last_line(tmp_path):
    f = JobFolder(tmp_path)
    f.append("state", to="LOAD")
    f.append("station_done", station="S1", joints=np.arange(6.0))
    with open(tmp_path / "journal.jsonl", "a") as fh:
        fh.write('{"event": "station_done", "stat')  # a crash mid-write
    recs = list(f.records())
    assert [r["event"] for r in recs] == ["state", "station_done"]
    assert recs[1]["joints"] == [0, 1, 2, 3, 4, 5]


def test_atomic_write_leaves_no_temporary_files_and_replaces_whole(tmp_path):
    p = tmp_path / "a.json"
    atomic_write_json(p, {"x": np.float64(1.5), "nan": float("nan")})
    atomic_write_json(p, {"x": 2})
    assert json.loads(p.read_text()) == {"x": 2}
    assert sorted(os.listdir(tmp_path)) == ["a.json"]


def test_run_log_cut_by_sigkill_still_yields_every_message(tmp_path):
    """A child process writes 300 messages and is killed with SIGKILL before closing the file."""
    path = tmp_path / "run.mcap"
    code = textwrap.dedent(f"""
        import os, signal, sys
        from cell.record.runlog import RunLog
        log = RunLog({str(path)!r})
        for i in range(300):
            log.log("info", f"message {{i}}")
        print("written", flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       cwd=os.path.dirname(os.path.dirname(__file__)))
    assert r.returncode == -9 and "written" in r.stdout
    msgs = [m for t, m in read_messages(path) if t == "/log"]
    assert [m["message"] for m in msgs] == [f"message {i}" for i in range(300)]


def test_run_log_closed_normally_is_a_valid_mcap_with_schemas(tmp_path):
    from mcap.reader import make_reader

    path = tmp_path / "run.mcap"
    log = RunLog(path)
    log.state("CREATED", "LOAD")
    log.robot(np.zeros(6), np.eye(4), 1.25, "S1")
    log.image(b"\x89PNG fake", "S1")
    log.close()
    with open(path, "rb") as f:
        reader = make_reader(f)
        topics = [(s.name, c.topic) for s, c, _ in reader.iter_messages()]
    assert ("cell.State", "/state") in topics
    assert ("foxglove.PoseInFrame", "/robot/flange_pose") in topics
    assert ("foxglove.CompressedImage", "/camera/image") in topics


def _fake_job(root, job_id, deviations, part="bracket"):
    f = JobFolder(root / job_id)
    f.path.mkdir(parents=True)
    f.append("created", name="bracket")
    f.append("state", **{"from": "REPORT", "to": "DONE"})
    targets = [{"id": f"T{i}", "nominal": [0.0, 0.0, 0.0], "measured": [0.0, 0.0, d], "deviation": [0.0, 0.0, d],
                "deviation_norm_m": abs(d), "achieved_sigma_m": 1e-5,
                "pass": abs(d) < 1e-4} for i, d in enumerate(deviations)]
    atomic_write_json(f.file("report.json"), {"job": {"id": job_id, "part": part, "finished": utc_now()},
                                              "verdict": "PASS", "sigma0_px": 1.0, "targets": targets})
    f.write_manifest()
    return f


def test_archive_lists_compares_and_verifies(tmp_path):
    _fake_job(tmp_path, "j1", [0.0, 1e-5, 2e-5])
    _fake_job(tmp_path, "j2", [0.0, 1e-5, 2e-4])
    a = Archive(tmp_path)
    assert a.reindex() == 2
    assert [r["id"] for r in a.list()] == ["j1", "j2"]
    cmp = a.compare(["j1", "j2"])
    assert cmp["drifting"] == ["T2"]  # moved 180 um with 14 um combined sigma
    assert a.verify("j1") == []
    (tmp_path / "j1" / "report.json").write_text("{}")
    (tmp_path / "j1" / "extra.txt").write_text("x")
    problems = a.verify("j1")
    assert any("report.json: changed" in p for p in problems) and any("extra.txt: not in the manifest" in p for p in problems)


def test_archive_compare_refuses_different_parts(tmp_path):
    from calibration.errors import InputError

    _fake_job(tmp_path, "j1", [0.0], part="bracket")
    _fake_job(tmp_path, "j2", [0.0], part="housing")
    with pytest.raises(InputError, match="different parts"):
        Archive(tmp_path).compare(["j1", "j2"])


def test_conformance_follows_iso_14253_with_the_deviations_uncertainty():
    from cell.stages.report import conformance

    iso = np.diag([10e-6, 10e-6, 10e-6]) ** 2  # 10 um per axis: U = 20 um along any direction
    d = np.array([[100e-6, 0, 0], [0, 240e-6, 0], [0, 0, 300e-6], [260e-6, 0, 0], [0, 0, 0], [1, 1, 1]])
    cov = np.repeat(iso[None], len(d), axis=0)
    cov[4] = np.diag([1e-12, 1e-12, (30e-6) ** 2])  # zero deviation: the largest axis counts
    U, dec = conformance(d, cov, np.full(len(d), 250e-6), np.array([True] * 5 + [False]))
    np.testing.assert_allclose(U[:4], 20e-6)
    assert np.isclose(U[4], 60e-6) and np.isnan(U[5])
    assert dec == ["conforming", "inconclusive", "nonconforming", "inconclusive", "conforming", None]
