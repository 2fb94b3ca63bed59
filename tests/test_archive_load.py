"""Many cells writing into one PostgreSQL archive at once; the server stopped mid-run; a cell killed mid-write.

The cells are processes (``archive_load_worker.py``) that write job folders and index them exactly as
the job runner does (a state record per transition, the job's row and its target values in one
transaction at the end, a push to shared storage checked against the manifest), without running the
photogrammetric pipeline: on 2 cores, 200 real jobs would take an hour. The archive side is the real
one: folders, outbox, PostgreSQL server.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cell.record.archive import Archive, open_index
from cell.record.jobfolder import JobFolder
from jobutil import child_env
from pgserver import pg, pg_server  # noqa: F401  (fixtures)

WORKER = Path(__file__).with_name("archive_load_worker.py")
CELLS, JOBS, TARGETS = 8, 25, 20


def _start(root: Path, url: str, cell: int, n: int, n_targets: int, push: Path | None = None) -> subprocess.Popen:
    args = [sys.executable, str(WORKER), str(root), url, str(cell), str(n), str(n_targets)]
    if push is not None:
        args.append(str(push))
    env = child_env() | {"OMP_NUM_THREADS": "1", "CELL_ARCHIVE_RETRY_S": "0.3", "CELL_LOAD_PACE_S": "0.3"}
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def _count(url: str) -> int:
    ix = open_index(url)
    try:
        return ix.count_jobs()
    except Exception:
        return -1
    finally:
        ix.close()


@pytest.mark.slow
def test_eight_cells_at_once_with_the_database_restarted_lose_nothing(tmp_path, pg):
    shared = tmp_path / "shared"
    procs = [_start(tmp_path / f"cell{c}", pg.url, c, JOBS, TARGETS, shared) for c in range(CELLS)]
    try:
        # stop the server once a quarter of the jobs are in, for long enough that every cell notices
        deadline = time.monotonic() + 300
        while _count(pg.url) < CELLS * JOBS // 4:
            assert time.monotonic() < deadline, "the cells wrote nothing for 5 minutes"
            assert all(p.poll() is None for p in procs), "a cell ended before the outage"
            time.sleep(0.2)
        pg.stop("fast")
        time.sleep(2.0)
        pg.start()
        outs = [p.communicate(timeout=600) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    docs = [json.loads(out.strip().splitlines()[-1]) for out, _ in outs]
    assert sum(d["outboxed"] for d in docs) > 0, "no cell noticed the outage: the test did not test it"
    outboxed, left = sum(d["outboxed"] for d in docs), sum(len(d["pending"]) for d in docs)
    assert left < outboxed, "no cell caught up by itself when the database returned"
    print(f"\nload: {CELLS} cells x {JOBS} jobs x {TARGETS} targets; {sum(d['outboxed'] for d in docs)} job closes "
          f"found the outbox non-empty; {sum(len(d['pending']) for d in docs)} jobs still in an outbox when their "
          "cell stopped (drained by sync)")
    # what a cell's outbox still holds when it stopped is drained by hand ('cell archive sync')
    for c in range(CELLS):
        a = Archive(tmp_path / f"cell{c}", pg.url)
        s = a.sync()
        assert s["pending"] == [] and s["push_pending"] == []
        assert a.outbox.pending() == []
        v = a.verify_index()
        assert v["intact"] and v["checked"] == JOBS, v["problems"]
        a.close()
    ix = open_index(pg.url)
    try:
        expected = {f"c{c}-j{k:03d}" for c in range(CELLS) for k in range(JOBS)}
        rows = ix.list_jobs(limit=None)
        ids = [r["id"] for r in rows]
        assert len(ids) == len(set(ids)) == CELLS * JOBS and set(ids) == expected  # each job exactly once
        assert all(r["status"] == "DONE" and r["targets"] == TARGETS for r in rows)
        for r in rows:  # every target value present, as the folder's report says
            folder = tmp_path / f"cell{r['id'][1]}" / r["id"]
            rep = json.loads((folder / "report.json").read_text())
            got = ix.job_targets(r["id"])
            assert [t["id"] for t in got] == [t["id"] for t in rep["targets"]]
            for g, t in zip(got, rep["targets"]):
                if t["measured"][0] is not None:
                    np.testing.assert_array_equal(g["measured"], t["measured"])
                    np.testing.assert_array_equal(g["cov"], t["cov"])
            assert JobFolder(folder).verify_manifest() == []
            assert JobFolder(shared / r["id"]).verify_manifest() == []  # the site's copy, whole
    finally:
        ix.close()


def _wait_inside_a_job_write(url: str, proc: subprocess.Popen, timeout: float = 120) -> None:
    """Return while a cell's transaction writing a job's target rows is open (seen in pg_stat_activity)."""
    import psycopg

    deadline = time.monotonic() + timeout
    with psycopg.connect(url, autocommit=True) as con:
        while True:
            row = con.execute("SELECT count(*) FROM pg_stat_activity WHERE application_name = 'inspection-cell' "
                              "AND xact_start IS NOT NULL AND state IN ('active', 'idle in transaction') "
                              "AND query ILIKE '%targets%'").fetchone()
            if row[0]:
                return
            assert proc.poll() is None, proc.communicate()[1][-3000:]
            assert time.monotonic() < deadline, "the cell never wrote a job"
            time.sleep(0.002)


def test_a_cell_killed_mid_write_leaves_no_half_job(tmp_path, pg):
    """SIGKILL while a job's rows go in: the server rolls the transaction back; the job is whole or absent."""
    root = tmp_path / "cell0"
    kills_inside = 0
    # a kill lands inside the transaction only when the machine is quick enough between seeing it and killing:
    # on a loaded machine some miss, so up to eight attempts until three have landed (two are needed)
    for attempt in range(8):
        if kills_inside >= 3:
            break
        before = len(pg.log.read_text())
        p = _start(root, pg.url, attempt, 50, 1500)  # big jobs: the index transaction takes ~0.1 s
        try:
            waits = min(attempt, 2) + 1
            for _ in range(waits):  # let the earlier attempts' cells get some jobs in first
                _wait_inside_a_job_write(pg.url, p)
                if _ == waits - 1:
                    break
                time.sleep(0.3)
        finally:
            os.kill(p.pid, signal.SIGKILL)
            p.communicate()
        for _ in range(50):  # the server notices the dead client
            if "unexpected EOF on client connection with an open transaction" in pg.log.read_text()[before:]:
                kills_inside += 1
                break
            time.sleep(0.1)
    assert kills_inside >= 2, f"only {kills_inside} kill(s) landed inside a transaction: the test did not test it"
    a = Archive(root, pg.url)
    state = a.index.index_state()
    assert state and all((s["targets"] or 0) == s["target_rows"] for s in state.values())  # no half job
    assert all(s["target_rows"] in (0, 1500) for s in state.values())
    a.sync()  # the folders of the killed jobs are indexed as far as they got
    v = a.verify_index()
    assert not v["problems"], v["problems"]  # the killed cells' last jobs are listed unclosed, not problems
    a.close()


@pytest.mark.slow
def test_a_real_job_run_with_archive_url_writes_its_record_into_postgresql(tmp_path, pg):
    """``cell run --archive-url postgresql://...``: the runner's own writes (state per transition, the closed
    job with its target values, the push to shared storage) go to the site's database and storage."""
    from jobutil import job_variant, run_cell

    job = job_variant(tmp_path / "job")
    env = child_env() | {"CELL_ID": "cellA", "CELL_ARCHIVE_PUSH": str(tmp_path / "shared"), "OMP_NUM_THREADS": "1"}
    run = run_cell("run", str(job), "--archive", str(tmp_path / "archive"), "--archive-url", pg.url, env=env,
                   timeout=600)
    assert run.code == 0, run.stderr[-3000:]
    job_id = run.doc["job_id"]
    assert "-cellA-" in job_id  # the cell's id is in the job id: the cells of a site never collide
    folder = tmp_path / "archive" / job_id
    rep = json.loads((folder / "report.json").read_text())
    ix = open_index(pg.url)
    try:
        row = ix.get_job(job_id)
        assert (row["status"], row["verdict"], row["cell_id"], row["targets"]) == \
            ("DONE", rep["verdict"], "cellA", len(rep["targets"]))
        got = {t["id"]: t for t in ix.job_targets(job_id)}
        for t in rep["targets"]:
            assert got[t["id"]]["deviation_norm_m"] == t["deviation_norm_m"] and got[t["id"]]["pass"] == t["pass"]
    finally:
        ix.close()
    assert not (tmp_path / "archive" / "index.sqlite").exists()  # nothing went to a local index instead
    assert JobFolder(tmp_path / "shared" / job_id).verify_manifest() == []
    assert "pushed" in run.stderr and "verified" in run.stderr
