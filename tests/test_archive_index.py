"""The archive index on both backends: SQLite (embedded) and a real PostgreSQL server.

What goes in comes back: every target value of report.json, the trend of one target over jobs,
the list filters; the schema the migrations build is the tables' declaration; a database that
goes away puts jobs in the outbox and they are indexed once when it returns; verify finds a
half-written job; push copies a job and checks it against its manifest.
"""
from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys

import numpy as np
import pytest

from archive_jobs import PART, truth, write_job
from cell.record.archive import Archive, IndexUnavailable, open_index
from cell.record.archive.push import PushError, push_job
from pgserver import pg, pg_server  # noqa: F401  (fixtures)

BACKENDS = ["sqlite", "postgresql"]


@pytest.fixture(params=BACKENDS)
def url(request, tmp_path):
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'db' / 'index.sqlite'}"
    return request.getfixturevalue("pg").url


def _archive(tmp_path, url, name="cell1") -> Archive:
    return Archive(tmp_path / name, url)


def test_migrations_build_exactly_the_declared_tables(url):
    from alembic.autogenerate import compare_metadata
    from alembic.runtime.migration import MigrationContext

    from cell.record.archive.tables import metadata

    ix = open_index(url)
    with ix.engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), metadata)
    rev = ix.schema_revision()
    ix.close()
    assert diff == []
    assert rev == "0001"


def test_every_target_value_comes_back_and_a_trend_is_one_query(tmp_path, url):
    a = _archive(tmp_path, url)
    n_jobs, n_t = 6, 12
    for k in range(n_jobs):
        write_job(a, f"job-{k:02d}", k, n_targets=n_t, serial=f"SN{k % 3}")
    ix = a.index
    assert ix.count_jobs() == n_jobs
    for k in range(n_jobs):
        row = ix.get_job(f"job-{k:02d}")
        rep = json.loads((a.root / f"job-{k:02d}" / "report.json").read_text())
        assert row["status"] == "DONE" and row["part"] == PART and row["serial"] == f"SN{k % 3}"
        assert (row["part_number"], row["operator"], row["problem"]) == ("B-100", "ann", None)
        assert row["verdict"] == rep["verdict"] and row["targets"] == n_t
        assert row["finished"] is not None and row["started"] <= row["finished"]
        got = ix.job_targets(f"job-{k:02d}")
        assert [t["id"] for t in got] == [t["id"] for t in rep["targets"]]
        for g, r in zip(got, rep["targets"]):
            if r["measured"][0] is None:  # not measured: no values, no decision
                assert g["measured"] is None and g["cov"] is None and g["decision"] is None and g["pass"] is False
                continue
            np.testing.assert_array_equal(g["nominal"], r["nominal"])
            np.testing.assert_array_equal(g["measured"], r["measured"])
            np.testing.assert_array_equal(g["cov"], r["cov"])  # full 3x3 back from the upper triangle
            np.testing.assert_array_equal(g["deviation"], r["deviation"])
            assert (g["deviation_norm_m"], g["tolerance_m"], g["uncertainty_U_m"], g["decision"], g["pass"]) == \
                (r["deviation_norm_m"], r["tolerance_m"], r["uncertainty_U_m"], r["decision"], r["pass"])
    # T000 drifts by 1 um per job (the truth): the trend shows it, oldest first
    trend = ix.target_trend(PART, "T000")
    assert [p["job_id"] for p in trend] == [f"job-{k:02d}" for k in range(n_jobs)]
    np.testing.assert_allclose([p["deviation"][2] for p in trend], [1e-6 * k for k in range(n_jobs)], atol=1e-15)
    assert [p["serial"] for p in trend] == [f"SN{k % 3}" for k in range(n_jobs)]
    achieved = [json.loads((a.root / f"job-{k:02d}" / "report.json").read_text())["targets"][0]["achieved_sigma_m"]
                for k in range(n_jobs)]
    assert [p["sigma_m"] for p in trend] == achieved and all(p["tolerance_m"] == 100e-6 for p in trend)
    assert [p["job_id"] for p in ix.target_trend(PART, "T000", limit=2)] == ["job-04", "job-05"]
    assert ix.part_targets(PART) == [f"T{i:03d}" for i in range(n_t)] and ix.parts() == [PART]
    # the part's SPC table in one query, against numpy over the same reports
    reps = [json.loads((a.root / f"job-{k:02d}" / "report.json").read_text())["targets"] for k in range(n_jobs)]
    summary = {r["id"]: r for r in ix.part_summary(PART)}
    for i in range(n_t):
        ts = [rep[i] for rep in reps if rep[i]["measured"][0] is not None]
        d = np.array([t["deviation"] for t in ts])
        norms = np.array([t["deviation_norm_m"] for t in ts])
        got = summary[f"T{i:03d}"]
        assert got["n"] == len(ts) and got["failed"] == sum(not t["pass"] for t in ts)
        assert got["inconclusive"] == sum(t["decision"] == "inconclusive" for t in ts)
        np.testing.assert_allclose(got["deviation_mean"], d.mean(axis=0), rtol=1e-9, atol=1e-18)
        np.testing.assert_allclose(got["deviation_std"], d.std(axis=0, ddof=1), rtol=1e-6, atol=1e-15)
        np.testing.assert_allclose([got["norm_mean"], got["norm_std"]], [norms.mean(), norms.std(ddof=1)],
                                   rtol=1e-6)
    # list filters and paging
    assert [r["id"] for r in ix.list_jobs(serial="SN1")] == ["job-04", "job-01"]
    assert ix.count_jobs(part_number="B-100", operator="ann") == n_jobs and ix.count_jobs(operator="bob") == 0
    assert [r["id"] for r in ix.list_jobs(limit=2, offset=1)] == ["job-04", "job-03"]
    third = ix.get_job("job-03")["started"]
    assert {r["id"] for r in ix.list_jobs(since=third)} == {"job-03", "job-04", "job-05"}
    assert {r["id"] for r in ix.list_jobs(until=third)} == {"job-00", "job-01", "job-02"}
    fails = {f"job-{k:02d}" for k in range(n_jobs) if ix.get_job(f"job-{k:02d}")["verdict"] == "FAIL"}
    assert {r["id"] for r in ix.list_jobs(verdict="FAIL")} == fails and ix.count_jobs(verdict="FAIL") == len(fails)
    # indexing again changes nothing: one row per job, the same target rows
    assert a.reindex() == n_jobs
    assert ix.count_jobs() == n_jobs and len(ix.job_targets("job-02")) == n_t
    assert a.verify_index()["intact"]
    a.close()


def test_the_parts_statistics_leave_out_untrusted_jobs_and_count_them_apart(tmp_path, url):
    """A job whose alignment to CAD was not trusted deviates in a frame nobody trusts: its targets are counted
    ``undecided`` and left out of the mean and the spread (as the trend's Cp/Cpk leave them out)."""
    a = _archive(tmp_path, url)
    n_t = 8
    for k in range(4):
        write_job(a, f"job-{k:02d}", k, n_targets=n_t, untrusted=(k == 2))
    reps = [json.loads((a.root / f"job-{k:02d}" / "report.json").read_text())["targets"] for k in range(4)]
    assert all(t["decision"] in ("undecided", None) for t in reps[2])
    summary = {r["id"]: r for r in a.index.part_summary(PART)}
    for i in range(n_t):
        kept = [rep[i] for k, rep in enumerate(reps) if k != 2 and rep[i]["measured"][0] is not None]
        got = summary[f"T{i:03d}"]
        assert got["n"] == len(kept)
        assert got["undecided"] == (reps[2][i]["measured"][0] is not None)
        assert got["failed"] == sum(not rep[i]["pass"] for rep in reps if rep[i]["measured"][0] is not None)
        if kept:
            np.testing.assert_allclose(got["deviation_mean"], np.mean([t["deviation"] for t in kept], axis=0),
                                       rtol=1e-9, atol=1e-18)
    a.close()


def test_a_job_id_of_another_cell_is_never_overwritten(tmp_path, url):
    a1, a2 = _archive(tmp_path, url, "cell1"), _archive(tmp_path, url, "cell2")
    write_job(a1, "same-id", 1, n_targets=4)
    write_job(a2, "same-id", 2, n_targets=4)
    assert "already in the archive index from" in a2.outbox.entry("same-id")["reason"]
    assert a2.outbox.pending() == ["same-id"]  # kept, loudly, not lost and not written over cell1's
    np.testing.assert_array_equal(a1.index.job_targets("same-id")[1]["deviation"], truth(1, 4)["deviation"][1])
    a1.close()
    a2.close()


def test_verify_finds_a_half_written_job_and_sync_repairs_it(tmp_path, url):
    a = _archive(tmp_path, url)
    for k in range(3):
        write_job(a, f"job-{k}", k, n_targets=5)
    assert a.verify_index() == {"checked": 3, "indexed": 3, "outbox": [], "problems": [], "damaged": [], "unclosed": [],
                                 "running": [], "intact": True}
    from cell.record.archive.tables import targets

    with a.index.engine.begin() as conn:  # what a write that is not one transaction would leave
        conn.execute(targets.delete().where(targets.c.job_id == "job-1", targets.c.target_id == "T003"))
    (a.root / "job-2" / "manifest.json").write_text((a.root / "job-2" / "manifest.json").read_text() + " ")
    (a.root / "job-3").mkdir()
    (a.root / "job-3" / "journal.jsonl").write_text(json.dumps({"t": "2026-11-22T10:00:00+00:00", "event": "created",
                                                                "name": "x"}) + "\n")
    a.index.delete_job("job-0")
    v = a.verify_index()
    assert not v["intact"]
    text = "\n".join(v["problems"])
    assert "job-1: index row claims 5 targets, holds 4" in text
    assert "job-2: the index holds another manifest" in text
    assert "job-0: folder not in the index" in text and "job-3: folder not in the index" in text
    s = a.sync()
    assert sorted(s["indexed"]) == ["job-0", "job-1", "job-2", "job-3"] and s["pending"] == []
    v = a.verify_index()  # job-3 never closed (a journal with its created record only): said, with what to run
    assert not v["problems"] and [u.split(":")[0] for u in v["unclosed"]] == ["job-3"], v
    a.close()


def test_the_database_going_away_fills_the_outbox_and_its_return_drains_it(tmp_path, pg):
    a = Archive(tmp_path / "cell1", pg.url)
    write_job(a, "before", 0, n_targets=5)
    pg.stop()
    write_job(a, "during-1", 1, n_targets=5)
    write_job(a, "during-2", 2, n_targets=5)
    assert a.outbox.pending() == ["during-1", "during-2"]
    with pytest.raises(IndexUnavailable):
        a.index.list_jobs()
    pg.start()
    write_job(a, "during-3", 3, n_targets=5)  # for RETRY_AFTER_S after a failure writes go straight to the outbox
    assert a.outbox.pending() == ["during-1", "during-2", "during-3"]
    a._down_until = 0.0  # (instead of waiting RETRY_AFTER_S)
    write_job(a, "after", 4, n_targets=5)  # the first write that reaches the database drains the outbox first
    assert a.outbox.pending() == []
    ix = a.index
    assert [r["id"] for r in ix.list_jobs(newest_first=False)] == ["before", "during-1", "during-2", "during-3",
                                                                   "after"]
    v = a.verify_index()
    assert v["intact"], v["problems"]
    a.close()


def test_an_index_older_than_the_migrations_is_set_aside_and_rebuilt(tmp_path):
    a = Archive(tmp_path / "arch")
    write_job(a, "j1", 1, n_targets=3)
    a.close()
    db = tmp_path / "arch" / "index.sqlite"
    for p in tmp_path.glob("arch/index.sqlite*"):
        p.unlink()
    con = sqlite3.connect(db)  # the index of the first versions of the cell
    con.execute("CREATE TABLE jobs (id TEXT PRIMARY KEY, name TEXT NOT NULL, status TEXT NOT NULL, folder TEXT)")
    con.execute("INSERT INTO jobs VALUES ('j1', 'bracket', 'DONE', 'x')")
    con.commit()
    con.close()
    b = Archive(tmp_path / "arch")
    assert [r["id"] for r in b.list()] == ["j1"] and len(b.index.job_targets("j1")) == 3
    assert (tmp_path / "arch" / "index.sqlite.pre-alembic").exists()
    b.close()


def test_push_copies_a_job_and_checks_it_against_the_manifest(tmp_path):
    a = Archive(tmp_path / "cell1", push=str(tmp_path / "shared"))
    f = write_job(a, "job-a", 1, n_targets=4)
    dest = tmp_path / "shared" / "job-a"
    manifest = json.loads((f.path / "manifest.json").read_text())
    assert sorted(str(p.relative_to(dest)) for p in dest.rglob("*") if p.is_file()) == \
        sorted([*manifest["files"], "manifest.json"])
    from cell.record.jobfolder import JobFolder

    assert JobFolder(dest).verify_manifest() == []  # the copy is whole by its own manifest
    (f.path / "report.json").write_text("{}")  # a folder that no longer matches its manifest is refused
    with pytest.raises(Exception, match="does not match its manifest"):
        push_job(f.path, str(tmp_path / "shared2"))
    assert not (tmp_path / "shared2").exists()


def test_push_that_reads_back_wrong_bytes_fails(tmp_path, monkeypatch):
    import fsspec.implementations.local as local

    a = Archive(tmp_path / "cell1")
    f = write_job(a, "job-b", 1, n_targets=3)
    real_put = local.LocalFileSystem.put_file

    def corrupting_put(self, lpath, rpath, **kw):  # storage that loses a byte of one file
        real_put(self, lpath, rpath, **kw)
        if rpath.endswith("report.json"):
            with open(rpath, "r+b") as fh:
                fh.truncate(10)

    monkeypatch.setattr(local.LocalFileSystem, "put_file", corrupting_put)
    with pytest.raises(PushError, match="differs from the manifest: report.json"):
        push_job(f.path, str(tmp_path / "shared"))


def test_cell_archive_commands_read_either_backend(tmp_path, url):
    from jobutil import cell_command, child_env

    a = _archive(tmp_path, url)
    for k in range(3):
        write_job(a, f"job-{k}", k, n_targets=4, serial=f"S{k}")
    a.close()

    def cell(*args):
        r = subprocess.run([*cell_command(), "archive", *args, "--archive", str(a.root), "--archive-url", url, "--json"],
                           capture_output=True, text=True, env=child_env(), timeout=120)
        return r.returncode, (json.loads(r.stdout) if r.stdout.strip() else None), r.stderr

    code, doc, err = cell("list", "--serial", "S1")
    assert code == 0, err
    assert [j["id"] for j in doc["jobs"]] == ["job-1"] and doc["total"] == 1
    code, doc, err = cell("verify")
    assert code == 0 and doc["intact"], err
    code, doc, err = cell("sync")
    assert code == 0 and doc["indexed"] == [] and doc["pending"] == [], err
    code, doc, err = cell("show", "job-2")
    assert code == 0 and doc["targets"] == 4, err
    code, doc, err = cell("list", "--since", "yesterday")
    assert code == 2 and "not an ISO 8601 time" in err


def test_a_real_jobs_report_goes_into_postgresql_value_for_value(tmp_path_factory, pg):
    """The example job (run once per session by the whole-job tests) indexed into the site's database."""
    from jobutil import example_run

    _, folder, _ = example_run(tmp_path_factory)
    a = Archive(folder.parent, pg.url)
    assert a.sync()["indexed"] == [folder.name]
    rep = json.loads((folder / "report.json").read_text())
    got = {t["id"]: t for t in a.index.job_targets(folder.name)}
    assert len(got) == len(rep["targets"]) > 0
    for r in rep["targets"]:
        g = got[r["id"]]
        if r["measured"][0] is None:
            assert g["measured"] is None
            continue
        np.testing.assert_array_equal(g["measured"], r["measured"])
        np.testing.assert_array_equal(g["cov"], r["cov"])
        assert (g["deviation_norm_m"], g["decision"], g["pass"]) == (r["deviation_norm_m"], r["decision"], r["pass"])
    row = a.index.get_job(folder.name)
    assert row["verdict"] == rep["verdict"] and row["status"] == "DONE" and row["targets"] == len(rep["targets"])
    assert a.verify_index()["intact"]
    a.close()


def test_push_to_s3_compatible_storage_checks_the_copy(tmp_path):
    """``cell archive push --to s3://...`` against moto's S3 server (a registry package) on a free port."""
    pytest.importorskip("s3fs", reason="s3fs not installed (pip install -e '.[s3,test]')")
    pytest.importorskip("moto.server", reason="moto[server] not installed (the test extra installs it)")
    import hashlib
    import socket
    import time
    import urllib.request

    from jobutil import cell_command, child_env

    a = Archive(tmp_path / "cell1")
    f = write_job(a, "job-s3", 1, n_targets=4)
    a.close()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    endpoint = f"http://127.0.0.1:{port}"
    try:
        for _ in range(200):
            try:
                urllib.request.urlopen(urllib.request.Request(f"{endpoint}/site-archive", method="PUT"), timeout=2)
                break
            except OSError:
                time.sleep(0.1)
        else:
            pytest.fail("moto's S3 server did not start")
        env = child_env() | {"AWS_ACCESS_KEY_ID": "cell", "AWS_SECRET_ACCESS_KEY": "cell", "AWS_DEFAULT_REGION":
                             "us-east-1", "AWS_ENDPOINT_URL": endpoint}
        r = subprocess.run([*cell_command(), "archive", "push", "job-s3", "--to", "s3://site-archive/cells/c1",
                            "--archive", str(a.root), "--json"], capture_output=True, text=True, env=env, timeout=120)
        assert r.returncode == 0, r.stderr[-3000:]
        doc = json.loads(r.stdout)["pushed"][0]
        assert doc["verified"] and doc["dest"] == "s3://site-archive/cells/c1/job-s3"
        manifest = json.loads((f.path / "manifest.json").read_text())
        import boto3

        s3 = boto3.client("s3", endpoint_url=endpoint, aws_access_key_id="cell", aws_secret_access_key="cell",
                          region_name="us-east-1")
        keys = {o["Key"] for o in s3.list_objects_v2(Bucket="site-archive", Prefix="cells/c1/")["Contents"]}
        assert keys == {f"cells/c1/job-s3/{n}" for n in [*manifest["files"], "manifest.json"]}
        for name, meta in manifest["files"].items():  # read back by another client: the bytes the storage holds
            body = s3.get_object(Bucket="site-archive", Key=f"cells/c1/job-s3/{name}")["Body"].read()
            assert hashlib.sha256(body).hexdigest() == meta["sha256"], name
        s3.close()
    finally:
        server.terminate()
        server.wait(timeout=30)


def test_a_folder_the_index_cannot_read_is_named_and_the_others_go_on(tmp_path):
    a = Archive(tmp_path / "arch")
    for k in range(3):
        write_job(a, f"job-{k}", k, n_targets=3)
    (a.root / "job-1" / "report.json").write_text('{"job": {"finished": "2026-01-01T00:00:00+00:00"}, "targets": [{}]}')
    a.index.delete_job("job-1")
    a.index.delete_job("job-2")
    s = a.sync()
    assert s["indexed"] == ["job-1", "job-2"] and len(s["problems"]) == 1 and "job-1" in s["problems"][0]
    assert "a target without 'id' or 'nominal'" in s["problems"][0]
    row = a.index.get_job("job-1")  # indexed as far as it reads: its state, no report values, the problem
    assert row["status"] == "DONE" and row["verdict"] is None and "report.json damaged" in row["problem"]
    assert a.index.job_targets("job-1") == [] and len(a.index.job_targets("job-2")) == 3
    v = a.verify_index()
    assert [p for p in v["damaged"] if "job-1" in p] and len(v["damaged"]) == 1
    # and its report is not the one its manifest closed the job with: a problem, whatever else reads (decision 0057)
    assert not v["intact"] and all(p.startswith("job-1: ") and "report.json" in p for p in v["problems"]), v
    a.close()


def test_a_kill_between_the_manifest_and_the_index_is_caught_up_by_the_listing(tmp_path):
    """Killed after manifest.json and before the index's last write: the row says DONE without the manifest's hash,
    the verdict or the targets (an outside check: the FAIL was missing from every query until 'cell archive sync').
    The listing's catch-up indexes such a row again, and verify names it with what to run."""
    a = _archive(tmp_path, f"sqlite:///{tmp_path / 'index.sqlite'}")
    write_job(a, "job-00", 0, n_targets=6)
    want = a.index.get_job("job-00")
    with a.index.engine.begin() as con:
        con.exec_driver_sql("UPDATE jobs SET manifest_sha256 = NULL, verdict = NULL, targets = NULL, failed = NULL "
                            "WHERE id = 'job-00'")
        con.exec_driver_sql("DELETE FROM targets WHERE job_id = 'job-00'")
    v = a.verify_index()
    assert any("another manifest" in p and "cell archive sync" in p for p in v["problems"]), v
    assert [r["id"] for r in a.listing(verdict=want["verdict"])] == ["job-00"]  # caught up by the listing itself
    row = a.index.get_job("job-00")
    assert (row["verdict"], row["manifest_sha256"], row["targets"]) == (want["verdict"], want["manifest_sha256"], 6)
    assert a.verify_index()["intact"]
    a.close()


def test_verify_names_a_job_killed_and_never_resumed_and_not_one_still_running(tmp_path):
    """A job without a manifest (killed, never resumed) or still in .incoming is said with the resume to run, and
    verify exits non-zero for it; a job whose process holds its lock is running, not abandoned."""
    from cell.record.archive import INCOMING
    from cell.record.jobfolder import JobFolder

    a = _archive(tmp_path, f"sqlite:///{tmp_path / 'index.sqlite'}")
    write_job(a, "job-00", 0, n_targets=4)
    write_job(a, "job-01", 1, n_targets=4)
    write_job(a, "job-02", 2, n_targets=4)
    assert a.verify_index()["intact"]
    (a.root / "job-01" / "manifest.json").unlink()  # killed before it closed
    staged = JobFolder(a.root / INCOMING / "2026-11-25T09-00-00-bracket")
    staged.path.mkdir(parents=True)
    staged.append("created", name="bracket", job_file="job.toml", backend="sim", serial=None)
    (a.root / "job-02" / "manifest.json").unlink()
    fd = JobFolder(a.root / "job-02").lock()  # job-02 is running: this process holds its lock
    try:
        v = a.verify_index()
    finally:
        os.close(fd)
    assert not v["intact"]
    assert sorted(u.split(":")[0] for u in v["unclosed"]) == ["2026-11-25T09-00-00-bracket", "job-01"]
    assert [r.split(":")[0] for r in v["running"]] == ["job-02"]
    # what to run: a job past DONE is only closed (a resume would refuse it), the others resumed
    assert "'cell archive verify job-01 --repair'" in v["unclosed"][0], v["unclosed"]
    assert "'cell resume 2026-11-25T09-00-00-bracket --yes'" in v["unclosed"][1], v["unclosed"]
    from jobutil import run_cell

    run = run_cell("archive", "verify", "--archive", str(a.root), "--archive-url",
                   f"sqlite:///{tmp_path / 'index.sqlite'}", timeout=120)
    assert run.code == 1 and len(run.doc["unclosed"]) == 3, (run.doc, run.stderr)  # job-02's lock is let go
    assert "never closed" in run.stderr
    a.close()
