"""Disk full: a write that fails with ENOSPC (injected under the job folder, and the disk staying full
for the rest of that session) is a clear one-line fault, never a traceback; after space is freed the
job resumes, and in the end nothing is lost or duplicated: every station has exactly one image,
each as journalled, and the manifest is intact. The failures are chained along one job: during
ACQUIRE, during MEASURE, and while the folder is closed."""
from __future__ import annotations

import errno
import json
import os

import pytest

from cell.cli import main as cell_main
from cell.record.integrity import acquired
from cell.record.jobfolder import JobFolder, sha256_file
from faultutil import copy_job, kill_during_acquire
from jobutil import example_run, records


class DiskFull:
    """Makes the disk under ``root`` 'full' from the first durable write whose path contains ``trigger``."""

    def __init__(self, monkeypatch, root):
        self.root, self.trigger, self.full, self.hits = str(root), None, False, 0
        real_fsync, real_append = os.fsync, JobFolder.append

        def fsync(fd):
            path = os.readlink(f"/proc/self/fd/{fd}")
            if path.startswith(self.root) and (self.full or (self.trigger and self.trigger in path)):
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

    def arm(self, trigger: str | None) -> None:
        self.trigger, self.full, self.hits = trigger, False, 0


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
