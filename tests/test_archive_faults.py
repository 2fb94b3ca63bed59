"""The site archive under faults (decision 0059, an outside tester's findings F1-F13 on PostgreSQL).

An index write the database refuses (a value longer than its column), a job stuck in the outbox, a server
that stops answering or a row lock held elsewhere, another cell's job id, a folder changed after its
manifest: none of them faults a job, stops a sync, or loses a job's data; each is said, with its reason,
and no password is ever shown. Job ids are ASCII; a time without a zone means the same in the CLI and the
console; the console answers 503 while the site database is down.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

from archive_jobs import write_job
from cell.record.archive import Archive, IndexUnavailable
from cell.record.jobfolder import JobFolder
from pgserver import pg, pg_server  # noqa: F401  (fixtures)

PW = "secretpw"
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "bracket"


def _with_pw(url: str, form: str = "userinfo") -> str:
    """The test server's url with a password (the server trusts: the password is carried, never checked)."""
    if form == "userinfo":
        return url.replace("cell@", f"cell:{PW}@", 1)
    if form == "at":
        return url.replace("cell@", "cell:sec@ret@", 1)
    return url + f"?password={PW}"


def _cli(*args, env=None, timeout=120):
    from jobutil import cell_command, child_env

    r = subprocess.run([*cell_command(), *args], capture_output=True, text=True, env=env or child_env(),
                       timeout=timeout)
    return r.returncode, r.stdout, r.stderr


# --- F5/F6: one masking function -------------------------------------------------------------------------
@pytest.mark.parametrize("url, shown", [
    ("postgresql://cell:secretpw@db:5432/archive", "postgresql://cell:***@db:5432/archive"),
    ("postgresql://cell@db:5432/archive?password=secretpw", "postgresql://cell@db:5432/archive?password=***"),
    ("postgresql://cell@db/a?sslmode=require&password=secretpw&application_name=x",
     "postgresql://cell@db/a?sslmode=require&password=***&application_name=x"),
    ("postgresql://cell:sec@ret@db/archive", "postgresql://cell:***@db/archive"),
    ("postgres://cell@db/archive?sslpassword=secretpw", "postgres://cell@db/archive?sslpassword=***"),
    ("sqlite:////srv/archive/index.sqlite", "sqlite:////srv/archive/index.sqlite"),
])
def test_a_password_is_masked_in_every_form(url, shown):
    from cell.record.archive.urls import mask_url, scrub, secrets_of

    assert mask_url(url) == shown
    for s in secrets_of(url):
        assert s not in mask_url(url)
    said = scrub(f"cannot reach {url} (password {secrets_of(url)[0] if secrets_of(url) else ''})", url)
    assert "secretpw" not in said and "sec@ret" not in said and "ret@" not in said


def test_list_of_nothing_and_the_outbox_never_show_the_password(tmp_path, pg):
    """F5: 'no jobs in URL' and --json's archive showed the raw url; F6: ?password= reached the outbox file,
    the job's lines and the errors."""
    from cell.record.archive.urls import mask_url

    root = tmp_path / "arcS"
    root.mkdir()
    for form in ("userinfo", "query", "at"):
        url = _with_pw(pg.url, form)
        for extra in ([], ["--since", "2099-01-01"], ["--part", "no-such"]):
            code, out, err = _cli("archive", "list", "--archive", str(root), "--archive-url", url, *extra)
            assert code == 0, err
            assert "no jobs in" in out + err
            assert PW not in out + err and "sec@ret" not in out + err and "ret@" not in out + err
            code, out, err = _cli("archive", "list", "--archive", str(root), "--archive-url", url, "--json", *extra)
            assert code == 0 and json.loads(out)["archive"] == mask_url(url), err
            assert PW not in out + err and "ret@" not in out + err
    # a job whose write waits in the outbox (the server stopped): the reason and the lines hold no password
    url = _with_pw(pg.url, "query")
    a = Archive(root, url)
    said = []
    pg.stop()
    try:
        write_job(a, "down-1", 1, n_targets=3)
        said += a.messages
    finally:
        pg.start()
    entry = (root / ".outbox" / "index" / "down-1.json").read_text()
    assert "down-1" in a.outbox.pending() and PW not in entry and "password=***" in entry
    a.close()
    # an unknown database with ?password=: one clear line, masked
    code, out, err = _cli("archive", "list", "--archive", str(root), "--archive-url",
                          pg.url.rsplit("/", 1)[0] + f"/nosuchdb?password={PW}")
    assert code != 0 and PW not in out + err and "nosuchdb" in err and "Traceback" not in err


# --- F1/F3: a record the database refuses ------------------------------------------------------------------
def _long_name_record(a: Archive, job_id: str):
    a.record(job_id, name="bracket" + "L" * 230, part="bracket", status="ACQUIRE",
             started="2026-11-23T08:00:00+00:00")


def test_a_record_the_database_refuses_goes_to_the_outbox_and_the_job_goes_on(tmp_path, pg):
    """F1: a name longer than jobs.name (VARCHAR(200)) raised DataError out of record() (the job FAULTED, the SQL
    and its values in the journal); F3: a target id longer than targets.target_id did the same out of job_closed."""
    url = _with_pw(pg.url)
    a = Archive(tmp_path / "cell1", url)
    (a.root / "long-name").mkdir(parents=True)
    _long_name_record(a, "long-name")  # must not raise
    e = a.outbox.entry("long-name")
    assert e["kind"] == "refused" and "value too long" in e["reason"], e
    assert "INSERT" not in e["reason"] and "LLLL" not in e["reason"] and PW not in e["reason"]
    assert any("long-name cannot be indexed" in m for m in a.messages)
    # F3: the job itself closes: report.json with a 125-character target id
    f = write_job(a, "long-target", 3, n_targets=4, between=lambda s: s == "REPORT" and _long_target(a))
    e = a.outbox.entry("long-target")
    assert e.get("kind") == "refused" and "value too long" in e["reason"]
    assert (f.path / "manifest.json").is_file() and f.verify_manifest() == []
    # the others are indexed: an ordinary job after them is written, and verify names the two
    write_job(a, "ordinary", 4, n_targets=4)
    assert a.index.get_job("ordinary")["status"] == "DONE"
    v = a.verify_index()
    text = "\n".join(v["problems"])
    assert "long-target: cannot be indexed" in text and not v["intact"]
    a.close()


def _long_target(a: Archive) -> None:
    p = a.root / "long-target" / "report.json"
    d = json.loads(p.read_text())
    d["targets"][0]["id"] = "T" * 125
    p.write_text(json.dumps(d))


def test_a_job_stuck_in_the_outbox_never_faults_the_next_job(tmp_path, pg):
    """F2: draining re-indexed a refused job first and raised DataError into the next, ordinary job."""
    a = Archive(tmp_path / "cell1", pg.url)
    write_job(a, "poison", 1, n_targets=3, between=lambda s: s == "REPORT" and _long_targets_of(a, "poison"))
    assert a.outbox.pending() == ["poison"]
    a.close()
    a = Archive(tmp_path / "cell1", pg.url)  # the next run of the cell
    write_job(a, "next", 2, n_targets=3)  # must not raise
    row = a.index.get_job("next")
    assert row["status"] == "DONE" and row["targets"] == 3 and row["manifest_sha256"]
    assert a.outbox.pending() == ["poison"] and a.outbox.entry("poison")["kind"] == "refused"
    assert sum("poison cannot be indexed" in m for m in a.messages) <= 1  # said once, not at every state change
    a.close()


def _long_targets_of(a: Archive, job_id: str) -> None:
    p = a.root / job_id / "report.json"
    d = json.loads(p.read_text())
    d["targets"][0]["id"] = "X" * 101
    p.write_text(json.dumps(d))


def test_lengths_the_index_imposes_are_refused_at_load(tmp_path):
    """F1/F3 at the source: `cell check` (LOAD) names the key and the limit."""
    from calibration.errors import InputError
    from cell.loadedjob import load

    job = tmp_path / "bracket"
    shutil.copytree(EXAMPLE, job)
    toml = (job / "job.toml").read_text()
    (job / "job.toml").write_text(toml.replace('name = "bracket"', f'name = "bracket{"L" * 230}"', 1))
    with pytest.raises(InputError) as e:
        load(job / "job.toml")
    assert "job.name" in str(e.value) and "200" in str(e.value) and "\n" not in str(e.value)
    (job / "job.toml").write_text(toml)
    lines = (job / "targets.csv").read_text().splitlines()
    lines[2] = "T" * 125 + lines[2][lines[2].index(","):]
    (job / "targets.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as e:
        load(job / "job.toml")
    assert "targets.csv:3" in str(e.value) and "100" in str(e.value) and "target id" in str(e.value)


def test_the_schema_limits_are_the_loaders(tmp_path):
    from cell.jobspec import NAME_MAX
    from cell.record.archive.tables import jobs, targets
    from planning.part import TARGET_ID_MAX

    assert jobs.c.name.type.length == jobs.c.part.type.length == NAME_MAX
    assert targets.c.target_id.type.length == TARGET_ID_MAX


# --- F4: a server that stops answering ---------------------------------------------------------------------
def test_a_row_lock_held_elsewhere_sends_the_write_to_the_outbox_within_seconds(tmp_path, pg):
    import psycopg

    a = Archive(tmp_path / "cell1", pg.url)
    write_job(a, "held", 1, n_targets=3)
    other = psycopg.connect(pg.url)
    other.execute("SELECT id FROM jobs WHERE id = 'held' FOR UPDATE")  # holds the row, never commits
    release = threading.Timer(30, other.close)  # let go after 30 s whatever happens
    release.start()
    try:
        t0 = time.monotonic()
        a.record("held", status="DONE")
        took = time.monotonic() - t0
    finally:
        release.cancel()
        other.close()
    print(f"\nF4 row lock: the write went to the outbox after {took:.2f} s")
    assert took < 8, took
    assert a.outbox.pending() == ["held"] and "lock" in a.outbox.entry("held")["reason"]
    a.close()


def _server_pids(pg) -> list[int]:
    pm = int((pg.data / "postmaster.pid").read_text().split()[0])
    kids = subprocess.run(["pgrep", "-P", str(pm)], capture_output=True, text=True).stdout.split()
    return [pm, *map(int, kids)]


def test_a_server_that_stops_answering_sends_the_write_to_the_outbox_within_seconds(tmp_path, pg):
    """F4: SIGSTOP to the server (a host that accepts packets, answers nothing): the pooled connection's ping and
    the write waited as long as the server was stopped. Now the watchdog gives up after BOUND_S."""
    from cell.record.archive.postgres import PostgresIndex

    a = Archive(tmp_path / "cell1", pg.url)
    write_job(a, "before", 1, n_targets=3)  # a pooled connection exists
    pids = _server_pids(pg)
    def cont():
        for p in pids:
            os.kill(p, signal.SIGCONT)

    wake = threading.Timer(30, cont)  # the server answers again after 30 s whatever happens
    for p in pids:
        os.kill(p, signal.SIGSTOP)
    wake.start()
    try:
        t0 = time.monotonic()
        a.record("before", status="DONE")
        took = time.monotonic() - t0
    finally:
        wake.cancel()
        cont()
    print(f"\nF4 stopped server: the write went to the outbox after {took:.2f} s")
    assert took < PostgresIndex.BOUND_S + 5, took
    e = a.outbox.entry("before")
    assert "before" in a.outbox.pending() and "no answer within" in e["reason"], e
    a._down_until = 0.0
    write_job(a, "after", 2, n_targets=3)  # the server answers again: the outbox drains
    assert a.outbox.pending() == [] and a.index.get_job("after")["status"] == "DONE"
    a.close()


# --- F7, F9: sync -------------------------------------------------------------------------------------------
def test_sync_goes_past_another_cells_job_and_names_it(tmp_path, pg):
    a1 = Archive(tmp_path / "cellA", pg.url)
    write_job(a1, "2099-01-01T00-00-00-same", 1, n_targets=3)
    a1.close()
    # cell B's folders were written while the index was elsewhere (copied in, another database)
    b_lite = Archive(tmp_path / "cellB", f"sqlite:///{tmp_path / 'bl' / 'index.sqlite'}")
    write_job(b_lite, "2099-01-01T00-00-00-same", 2, n_targets=3)
    write_job(b_lite, "2099-01-01T00-00-01-cellB-bracket", 3, n_targets=3)
    b_lite.close()
    code, out, err = _cli("archive", "sync", "--archive", str(tmp_path / "cellB"), "--archive-url", pg.url, "--json")
    doc = json.loads(out)
    assert code == 1, err
    assert doc["indexed"] == ["2099-01-01T00-00-01-cellB-bracket"]
    assert [s["id"] for s in doc["skipped"]] == ["2099-01-01T00-00-00-same"]
    assert "already in the archive index from" in doc["skipped"][0]["reason"]
    assert "--adopt" not in doc["skipped"][0]["reason"]  # another cell's job (another manifest): never adopted
    code, out, err = _cli("archive", "sync", "--archive", str(tmp_path / "cellB"), "--archive-url", pg.url)
    assert code == 1 and "not indexed: 2099-01-01T00-00-00-same" in out + err
    code, out, err = _cli("archive", "verify", "--archive", str(tmp_path / "cellB"), "--archive-url", pg.url)
    assert code == 1 and "2099-01-01T00-00-00-same: cannot be indexed" in out + err
    assert "run 'cell archive sync'" not in out + err


def test_a_moved_archive_is_named_as_the_same_jobs_and_adopted_only_when_asked(tmp_path, pg):
    """F8: an archive moved to another folder (or a host renamed) holds the same jobs under another origin: sync
    named them another cell's; it now says they are the same jobs (their manifests) and ``--adopt`` re-owns them."""
    a = Archive(tmp_path / "old", pg.url)
    for i in range(2):
        write_job(a, f"2099-01-0{i + 1}T00-00-00-moved", i + 1, n_targets=3)
    a.close()
    shutil.move(tmp_path / "old", tmp_path / "new place")
    code, out, err = _cli("archive", "sync", "--archive", str(tmp_path / "new place"), "--archive-url", pg.url,
                          "--json")
    doc = json.loads(out)
    assert code == 1 and doc["indexed"] == [] and doc["adopted"] == [], err
    assert len(doc["skipped"]) == 2 and all("the same job" in s["reason"] and "sync --adopt" in s["reason"]
                                            for s in doc["skipped"]), doc["skipped"]
    code, out, err = _cli("archive", "sync", "--adopt", "--archive", str(tmp_path / "new place"), "--archive-url",
                          pg.url)
    assert code == 0, out + err
    said = out + err
    assert said.count("adopted 2099-01-0") == 2 and str(tmp_path / "old") in said, said
    b = Archive(tmp_path / "new place", pg.url)
    rows = {r["id"]: r for r in b.index.list_jobs()}
    assert {r["folder"] for r in rows.values()} == {str((tmp_path / "new place" / j).resolve()) for j in rows}
    assert b.outbox.pending() == [] and b.verify_index()["intact"], b.verify_index()
    b.close()


def test_sync_never_indexes_a_report_changed_after_its_manifest(tmp_path, pg):
    """F9: sync re-indexed a report.json changed after the job (FAIL became PASS in the index, silently)."""
    a = Archive(tmp_path / "cell1", pg.url)
    f = write_job(a, "tampered", 1, n_targets=4)
    before = a.index.get_job("tampered")
    rep = json.loads(f.file("report.json").read_text())
    rep["verdict"] = "PASS" if rep["verdict"] == "FAIL" else "FAIL"
    for t in rep["targets"]:
        t["pass"] = not t["pass"]
    f.file("report.json").write_text(json.dumps(rep))
    s = a.sync()
    assert s["indexed"] == [] and [x["id"] for x in s["skipped"]] == ["tampered"]
    assert "does not match its manifest" in s["skipped"][0]["reason"]
    after = a.index.get_job("tampered")
    assert (after["verdict"], after["failed"]) == (before["verdict"], before["failed"])
    v = a.verify_index()
    assert any("tampered: report.json" in p for p in v["problems"]) and not v["intact"]
    a.close()


# --- F10: ASCII job ids ------------------------------------------------------------------------------------
def test_a_job_name_with_accents_gives_an_ascii_job_id_the_archive_takes(tmp_path):
    from cell.record.archive import check_job_id
    from cell.record.jobfolder import new_job_id
    from cell.web.store import _ID

    jid = new_job_id("Bügel'; DROP TABLE jobs;--", now=0)
    assert jid.endswith("-Bugel---DROP-TABLE-jobs---") and jid.isascii()
    assert check_job_id(jid) == jid and _ID.match(jid)
    a = Archive(tmp_path / "arc", f"sqlite:///{tmp_path / 'arc' / 'index.sqlite'}")
    write_job(a, jid, 1, n_targets=3)
    assert [r["id"] for r in a.listing()] == [jid]
    a.close()
    b = Archive(tmp_path / "arc", f"sqlite:///{tmp_path / 'fresh.sqlite'}")  # a fresh index of the same folder
    assert [r["id"] for r in b.listing()] == [jid] and b.verify_index()["intact"]
    b.close()


# --- F11: one rule for a time without a zone ---------------------------------------------------------------
def test_a_time_without_a_zone_means_local_time_in_the_cli_and_the_console(tmp_path):
    from jobutil import child_env

    from cell.web.store import ArchiveView

    root = tmp_path / "arc"
    a = Archive(root)
    for k in range(3):
        write_job(a, f"job-{k}", k, n_targets=3)
        time.sleep(1.1)
    started = [r["started"] for r in a.index.list_jobs(newest_first=False)]
    a.close()
    env = child_env() | {"TZ": "Asia/Kolkata"}  # +05:30: not UTC, not a whole hour
    from datetime import datetime

    # the second job's start, as a local wall-clock time without a zone (as a job id shows it)
    local = datetime.fromisoformat(started[1]).astimezone(__import__("zoneinfo").ZoneInfo("Asia/Kolkata"))
    since = local.replace(tzinfo=None).isoformat(timespec="milliseconds")
    code, out, err = _cli("archive", "list", "--archive", str(root), "--since", since, "--json", env=env)
    assert code == 0, err
    cli_ids = [j["id"] for j in json.loads(out)["jobs"]]
    assert cli_ids == ["job-1", "job-2"], (since, started)
    day = local.date().isoformat()
    code, out, err = _cli("archive", "list", "--archive", str(root), "--until", day, "--json", env=env)
    assert code == 0 and len(json.loads(out)["jobs"]) == 3, err  # --until DATE: the whole day
    # the console, in the same zone
    old = os.environ.get("TZ")
    os.environ["TZ"] = "Asia/Kolkata"
    time.tzset()
    try:
        v = ArchiveView(root)
        assert sorted(r["id"] for r in v.list_jobs(since=since)) == cli_ids
        assert len(v.list_jobs(until=day)) == 3
        v.close()
    finally:
        if old is None:
            os.environ.pop("TZ")
        else:
            os.environ["TZ"] = old
        time.tzset()


# --- F12: the console while the site database is down --------------------------------------------------------
def test_the_console_says_503_while_the_site_database_is_down(tmp_path, pg):
    from fastapi.testclient import TestClient

    from cell.web.app import Config, create_app
    from cell.web.users import UserStore

    root = tmp_path / "arc"
    url = _with_pw(pg.url, "query")
    a = Archive(root, url)
    write_job(a, "job-1", 1, n_targets=3)
    a.close()
    UserStore(root / "console.sqlite").add("eve", "engineer", "engineer-pw-2m")
    (tmp_path / "programs").mkdir()
    with TestClient(create_app(Config(archive=root, programs=tmp_path / "programs", archive_url=url))) as c:
        r = c.post("/login", data={"username": "eve", "password": "engineer-pw-2m"}, follow_redirects=False)
        assert r.status_code == 303
        assert c.get("/api/jobs").status_code == 200
        pg.stop()
        try:
            for path in ("/api/jobs", "/api/parts/bracket/targets"):
                r = c.get(path)
                assert r.status_code == 503, (path, r.status_code, r.text[:200])
                assert r.json()["detail"].startswith("the site archive is not reachable: ")
                assert PW not in r.text
            r = c.get("/archive", headers={"accept": "text/html"})
            assert r.status_code == 503 and "the site archive is not reachable" in r.text and PW not in r.text
        finally:
            pg.start()
        assert c.get("/api/jobs").status_code == 200  # back by itself
