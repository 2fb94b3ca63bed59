"""The console reads the archive through its index: the same jobs and trends from SQLite and from a real
PostgreSQL server, with no report.json read for a trend, and ``cell serve --archive-url`` reaching the
view and the jobs the console starts."""
from __future__ import annotations

from pathlib import Path

import pytest

from webutil import DRIFTING, PART, TARGETS, seed_trend_archive

from cell.web.store import ArchiveView
from pgserver import pg, pg_server  # noqa: F401  (fixtures)

QUERIES = [{}, {"part": PART}, {"part": "trendpart"}, {"part": "no-such-part"}, {"serial": "sn-000"},
           {"serial": "0010"}, {"verdict": "fail"}, {"verdict": "PASS", "part": PART}, {"status": "done", "limit": 3},
           {"since": "2026-11-20T08:04:00+00:00", "until": "2026-11-20T08:07:00+00:00"},
           {"since": "2026-11-20", "until": "2026-11-20"}, {"until": "2026-11-19"}, {"operator": "olga", "limit": 4},
           {"serial": "SN", "limit": 2}]
DROP = ("indexed_at",)  # when the row was written: differs between the two databases


def _rows(rows):
    return [{k: v for k, v in r.items() if k not in DROP} for r in rows]


def test_the_console_reads_the_same_jobs_and_trends_from_sqlite_and_postgresql(tmp_path, pg):
    archive = tmp_path / "archive"
    ids = seed_trend_archive(archive, n_parts=8, drift_from=5, drift_step_m=30e-6)  # the last parts FAIL; indexed in archive/index.sqlite
    lite = ArchiveView(archive)
    assert lite.url == f"sqlite:///{archive.resolve() / 'index.sqlite'}"
    site = ArchiveView(archive, pg.url)
    site.refresh()  # catch-up from the folders into the server
    try:
        for q in QUERIES:
            a, b = lite.list_jobs(**q), site.list_jobs(**q)
            assert _rows(a) == _rows(b), q
        assert [r["id"] for r in lite.list_jobs(part=PART)] == ids[::-1]  # newest first
        assert [r["serial"] for r in lite.list_jobs(serial="sn-000")] == [f"SN-{i:04d}" for i in range(8, 0, -1)]
        assert len(lite.list_jobs(since="2026-11-20T08:04:00+00:00", until="2026-11-20T08:07:00+00:00")) == 4
        assert {r["verdict"] for r in lite.list_jobs(verdict="fail")} == {"FAIL"} and lite.list_jobs(verdict="fail")
        assert lite.list_jobs(until="2026-11-19") == []
        assert lite.job_targets(PART) == site.job_targets(PART) == TARGETS

        trends = {}
        for target in (TARGETS[0], DRIFTING[0], ",".join([TARGETS[0], DRIFTING[0], TARGETS[3]])):
            for axis in ("norm", "z", "x"):
                a = lite.target_trend(PART, target, axis)
                assert a == site.target_trend(PART, target, axis), (target, axis)
                assert [p["serial"] for p in a["points"]] == [f"SN-{i:04d}" for i in range(1, 9)]
                trends[target, axis] = a
        # the values are the reports' own (the simulated truth of the seeded archive)
        import json

        for p in trends[DRIFTING[0], "z"]["points"]:
            rep = json.loads((archive / p["job_id"] / "report.json").read_text())
            t = next(t for t in rep["targets"] if t["id"] == DRIFTING[0])
            assert p["value_m"] == t["deviation"][2] and p["deviation_norm_m"] == t["deviation_norm_m"]
            assert p["finished"] == rep["job"]["finished"] and p["sigma_m"] == t["achieved_sigma_m"]
            assert p["pass"] == t["pass"] and p["target"] == DRIFTING[0]
        group = trends[",".join([TARGETS[0], DRIFTING[0], TARGETS[3]]), "norm"]["points"]
        assert group[-1]["target"] == DRIFTING[0]  # the drifting one is the group's worst at the end

        # a trend is read from the index alone: without the reports it is the same
        for jid in ids:
            (archive / jid / "report.json").rename(archive / jid / "report.json.away")
        assert site.target_trend(PART, DRIFTING[0], "z") == trends[DRIFTING[0], "z"]
    finally:
        lite.close()
        site.close()


def test_serve_archive_url_reaches_the_view_and_the_jobs_the_console_starts(tmp_path, monkeypatch):
    from cell.web.app import create_app
    from cell.web.deps import Config

    url = f"sqlite:///{tmp_path / 'elsewhere' / 'index.sqlite'}"
    (tmp_path / "elsewhere").mkdir()
    app = create_app(Config(archive=tmp_path / "archive", programs=tmp_path / "programs", archive_url=url))
    con = app.state.console
    try:
        assert con.view.url == url and con.runner.archive_url == url
        # the child that runs a job is told the same database (in its environment: a password stays out of ps)
        import sys

        import cell.web.runner as runner_mod

        probe = "import os, sys; print(os.environ.get('CELL_ARCHIVE_URL')); print(' '.join(sys.argv[1:]))"
        monkeypatch.setattr(runner_mod, "_cell_command", lambda: [sys.executable, "-c", probe])
        s = con.runner.start(tmp_path / "p.toml", "SN-1", "olga")
        assert s.proc.wait(timeout=30) == 0
        said = s.out_path.read_text().splitlines()
        assert said[0] == url and said[1].startswith("run ") and "--archive " in said[1]
        con.runner.current = None
        # without --archive-url: CELL_ARCHIVE_URL, as every other cell command
        monkeypatch.setenv("CELL_ARCHIVE_URL", url)
        v = ArchiveView(tmp_path / "archive")
        assert v.url == url
        v.close()
        monkeypatch.delenv("CELL_ARCHIVE_URL")
        v = ArchiveView(tmp_path / "archive")
        assert v.url == f"sqlite:///{(tmp_path / 'archive').resolve() / 'index.sqlite'}"
        v.close()
    finally:
        con.view.close()
    assert not Path(tmp_path / "archive" / "index.sqlite").exists()  # nothing indexed in the default database


def test_serve_banner_masks_a_password_in_any_form_of_the_archive_url(tmp_path, monkeypatch):
    """The start banner names the index without its password: user:pw@ and ?password= alike (an outside check saw
    the query form printed in clear)."""
    import types

    import uvicorn

    from cell.web import serve as serve_mod

    said = []
    monkeypatch.setattr(uvicorn, "run", lambda *a, **k: None)
    monkeypatch.setattr("cell.web.app.create_app", lambda cfg: types.SimpleNamespace(
        state=types.SimpleNamespace(users=types.SimpleNamespace(users=lambda: ["ada"]))))
    out = types.SimpleNamespace(say=said.append)
    for url in ("postgresql://cell:hunter2pw@db.example:5432/archive",
                "postgresql://cell@db.example:5432/archive?password=hunter2pw&sslmode=require"):
        args = types.SimpleNamespace(certfile=None, keyfile=None, host="127.0.0.1", port=8765, archive=str(tmp_path),
                                     programs=str(tmp_path / "programs"), cell_id=None, archive_url=url)
        assert serve_mod.serve(args, out) == 0
    banner = "\n".join(said)
    assert "hunter2pw" not in banner and banner.count("db.example:5432/archive") == 2, banner
