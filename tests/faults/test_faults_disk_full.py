"""Disk full: a write that fails with ENOSPC (injected under the job folder, and the disk staying full
for the rest of that session) is a clear one-line fault, never a traceback; after space is freed the
job resumes, and in the end nothing is lost or duplicated: every station has exactly one image,
each as journalled, and the manifest is intact. The failures are chained along one job: during
ACQUIRE, during MEASURE, and while the folder is closed."""
from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import pytest

from cell.cli import main as cell_main
from cell.record.integrity import acquired
from cell.record.jobfolder import JobFolder, sha256_file
from faultutil import copy_job, kill_during_acquire
from jobutil import example_run, records


class DiskFull:
    """Makes the disk under ``root`` 'full' from the first durable write (fsync) whose path contains
    ``trigger``, or from the ``nth`` durable write under ``root``; a full disk takes no journal line either."""

    def __init__(self, monkeypatch, root):
        self.root, self.trigger, self.nth, self.full, self.hits, self.writes = str(root), None, None, False, 0, 0
        real_fsync, real_append = os.fsync, JobFolder.append

        def fsync(fd):
            path = os.readlink(f"/proc/self/fd/{fd}")
            if path.startswith(self.root):
                self.writes += 1
                if self.full or (self.trigger and self.trigger in path) or (self.nth and self.writes >= self.nth):
                    self.full = True
                    self.hits += 1
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), path)
            return real_fsync(fd)

        def append(folder, event, **fields):
            if self.full and str(folder.path).startswith(self.root):  # a full disk takes no journal line either
                self.hits += 1
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(folder.path / "journal.jsonl"))
            return real_append(folder, event, **fields)

        monkeypatch.setattr(os, "fsync", fsync)
        monkeypatch.setattr(JobFolder, "append", append)

    def arm(self, trigger: str | None = None, nth: int | None = None) -> None:
        self.trigger, self.nth, self.full, self.hits, self.writes = trigger, nth, False, 0, 0


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_disk_full_at_each_phase_is_one_line_and_the_job_resumes_with_nothing_lost(tmp_path, tmp_path_factory,
                                                                                  monkeypatch, capsys):
    _, finished, _ = example_run(tmp_path_factory)
    archive = tmp_path / "archive"
    folder = copy_job(finished, archive)
    kill_during_acquire(folder, 4)
    disk = DiskFull(monkeypatch, archive)
    n_stations = len(json.loads((folder / "plan.json").read_text())["stations"])

    for trigger, standing in (("images/", 4), ("observations.json", n_stations), ("manifest.json", n_stations)):
        disk.arm(trigger)
        code = cell_main(["resume", folder.name, "--archive", str(archive), "--yes", "--json"])
        out, err = capsys.readouterr()
        assert disk.hits, f"{trigger}: the disk never filled"
        assert code == 1 and "Traceback" not in err, err[-3000:]
        doc = json.loads(out)
        assert doc["status"] == "FAULTED" and "No space left on device" in doc["reason"], doc
        assert f"cell resume {folder.name}" in doc["reason"]
        assert err.strip().splitlines()[-1].startswith(f"job {folder.name}  FAULTED")
        recs = records(folder)
        assert len(acquired(recs)) == standing, trigger
        stations = [r["station"] for r in recs if r["event"] == "station_done"]
        assert len(stations) - len(set(stations)) == 0 or trigger != "images/"

    disk.arm(None)  # space freed
    code = cell_main(["resume", folder.name, "--archive", str(archive), "--yes", "--json"])
    out, err = capsys.readouterr()
    assert code == 0 and json.loads(out)["status"] == "DONE", err[-3000:]
    recs = records(folder)
    standing = acquired(recs)
    assert len(standing) == n_stations
    for r in standing.values():
        assert sha256_file(folder / r["image"]) == r["sha256"]
    assert sorted(p.name for p in (folder / "images").iterdir()) == sorted(r["image"][7:] for r in standing.values())
    assert not list(folder.rglob(".*.tmp*"))
    assert cell_main(["archive", "verify", folder.name, "--archive", str(archive)]) == 0, capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_small_filesystem_fills_during_acquisition_then_the_job_resumes_once_it_grows(tmp_path):
    """A real full disk: the archive on a 12 MiB tmpfs (made by the test; root only), grown after the fault."""
    from jobutil import job_variant, run_cell

    mnt = tmp_path / "small"
    mnt.mkdir()
    if os.geteuid() != 0 or os.system(f"mount -t tmpfs -o size=12m tmpfs {mnt} 2>/dev/null") != 0:
        pytest.skip("making a small file system needs root and mount")
    try:
        job = job_variant(tmp_path / "job")
        archive = mnt / "archive"
        r = run_cell("run", str(job), "--archive", str(archive), timeout=400)
        assert r.code == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
        assert r.doc["status"] == "FAULTED" and "No space left on device" in r.doc["reason"], r.doc
        folder = Path(r.doc["folder"])
        standing = acquired(records(folder))
        n_stations = len(json.loads((folder / "plan.json").read_text())["stations"])
        assert 0 < len(standing) < n_stations, "the disk did not fill during acquisition"
        for rec in standing.values():
            assert sha256_file(folder / rec["image"]) == rec["sha256"]
        assert os.system(f"mount -o remount,size=300m {mnt}") == 0
        r = run_cell("resume", folder.name, "--archive", str(archive), "--yes", timeout=400)
        assert r.code == 0 and r.doc["status"] == "DONE", r.stderr[-3000:]
        recs = records(folder)
        done = [x["station"] for x in recs if x["event"] == "station_done"]
        assert sorted(acquired(recs)) == sorted(set(done)) and len(acquired(recs)) == n_stations
        assert sorted(done) == sorted(set(done)), "a station stored before the fault was taken again"
        verify = run_cell("archive", "verify", folder.name, "--archive", str(archive))
        assert verify.code == 0 and verify.doc["intact"], verify.doc
    finally:
        os.system(f"umount {mnt}")


def test_disk_full_at_every_write_of_closing_a_job_then_it_closes(tmp_path, tmp_path_factory, monkeypatch, capsys):
    """Closing a job that died after its last stage (state, terminal record, manifest): the disk fills at
    each of its durable writes in turn; each time one line and no traceback, and then it closes intact."""
    from faultutil import cut_journal

    _, finished, _ = example_run(tmp_path_factory)
    disk = DiskFull(monkeypatch, tmp_path)
    k = 0
    while True:
        k += 1
        archive = tmp_path / f"a{k}"
        folder = copy_job(finished, archive)
        cut_journal(folder, lambda r, i: not (r["event"] == "state" and r["to"] == "DONE"))
        (folder / "manifest.json").unlink()
        disk.arm(nth=k)
        code = cell_main(["resume", folder.name, "--archive", str(archive), "--yes", "--json"])
        out, err = capsys.readouterr()
        assert "Traceback" not in err, err[-3000:]
        if not disk.hits:  # past the last write: the session closed the job
            assert code == 0 and json.loads(out)["status"] == "DONE"
            break
        assert code == 1 and "No space left on device" in err.strip().splitlines()[-1], (k, err[-2000:])
        disk.arm()  # space freed
        code = cell_main(["resume", folder.name, "--archive", str(archive), "--yes", "--json"])
        out, err = capsys.readouterr()
        # closed now; or closed already (the failed write was the last one, the folder's fsync after the
        # manifest was in place): then resume says so and changes nothing
        assert (code == 0 and json.loads(out)["status"] == "DONE") or (code == 2 and "already DONE" in err), \
            (k, err[-2000:])
        assert cell_main(["archive", "verify", folder.name, "--archive", str(archive)]) == 0, \
            (k, capsys.readouterr().err)
        shutil.rmtree(archive)
        assert k < 40
    assert k > 3  # the state record, the terminal record and the manifest at least
