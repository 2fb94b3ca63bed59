"""The archive is the truth: resume verifies before it acts, ids are names, every job can be finished
or closed. Each test damages a copy of one finished job (the example job, run once per session) or
of that job cut back to an earlier moment of its life, and checks what the cell then does.

Quick refusals run the ``cell`` command in this process (``cell.cli.main``); resumes that drive the
(simulated) robot run it as the operator does, in a child process.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from cell.cli import main as cell_main
from faultutil import copy_job, cut_journal, kill_during_acquire, snapshot, staged_copy
from jobutil import example_run, records, run_cell


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """The folder of the finished example job (shared: tests only ever copy it)."""
    _, folder, _ = example_run(tmp_path_factory)
    return folder


def cell(capsys, *args: str) -> tuple[int, dict | None, str]:
    """``cell ARGS --json`` in this process: (exit code, JSON document, stderr)."""
    code = cell_main([*args, "--json"])
    out, err = capsys.readouterr()
    return code, (json.loads(out) if out.strip() else None), err


def one_line(err: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("cell: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# --- journal corruption ------------------------------------------------------------------------------


@pytest.mark.parametrize("moment", ["finished", "killed during ACQUIRE"])
def test_flipped_journal_byte_is_named_and_never_rewinds_or_changes_anything(finished, tmp_path, capsys, moment):
    archive = tmp_path / "archive"
    folder = copy_job(finished, archive)
    if moment != "finished":
        kill_during_acquire(folder, 5)
    good = (folder / "journal.jsonl").read_bytes()
    rng = np.random.default_rng(2026 if moment == "finished" else 2027)
    offsets = sorted({int(k) for k in rng.integers(0, len(good), 14)} | {len(good) - 1})  # and the last line end
    for k in offsets:
        damaged = bytearray(good)
        damaged[k] ^= 1 << int(rng.integers(0, 8))
        (folder / "journal.jsonl").write_bytes(bytes(damaged))
        before = snapshot(folder)
        code, doc, err = cell(capsys, "resume", folder.name, "--archive", str(archive), "--yes")
        line = good[:k].count(b"\n") + 1  # the line that holds the flipped byte (or whose end it is)
        msg = one_line(err)
        assert code == 1 and doc["error"] == "RecordError", (k, err)
        assert f"journal.jsonl:{line}:" in msg, (k, msg)
        assert "not resumed" in msg
        assert snapshot(folder) == before, f"byte {k}: the resume changed the job folder"
        code, doc, _ = cell(capsys, "archive", "verify", folder.name, "--archive", str(archive))
        assert code == 1 and any("journal" in p for p in doc["problems"]), doc
    (folder / "journal.jsonl").write_bytes(good)


# --- stored files against the journal -----------------------------------------------------------------


def _png_with_bad_crc(path: Path) -> None:
    data = bytearray(path.read_bytes())
    k = data.index(b"IDAT") + 40  # inside the first image data chunk
    data[k] ^= 0xFF
    path.write_bytes(bytes(data))


def test_finished_job_with_a_swapped_image_is_never_driven_again_and_verify_names_it(finished, tmp_path, capsys):
    archive = tmp_path / "archive"
    folder = copy_job(finished, archive)
    a, b = sorted((folder / "images").iterdir())[2:4]
    da, db = a.read_bytes(), b.read_bytes()
    a.write_bytes(db)
    b.write_bytes(da)
    before = snapshot(folder)
    code, _, err = cell(capsys, "resume", folder.name, "--archive", str(archive), "--yes")
    assert code == 2 and "already DONE" in one_line(err)
    assert snapshot(folder) == before
    code, doc, _ = cell(capsys, "archive", "verify", folder.name, "--archive", str(archive))
    assert code == 1 and not doc["intact"]
    named = " ".join(doc["problems"])
    assert f"images/{a.name}" in named and f"images/{b.name}" in named


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_swapped_and_damaged_images_of_a_killed_job_send_only_their_stations_back(finished, tmp_path):
    archive = tmp_path / "archive"
    folder = copy_job(finished, archive)
    kept = kill_during_acquire(folder, 8)
    done = {r["station"]: r for r in records(folder) if r["event"] == "station_done"}
    s1, s2, s3 = kept[1], kept[4], kept[6]
    i1, i2 = folder / done[s1]["image"], folder / done[s2]["image"]
    d1, d2 = i1.read_bytes(), i2.read_bytes()
    i1.write_bytes(d2)  # two images swapped
    i2.write_bytes(d1)
    _png_with_bad_crc(folder / done[s3]["image"])  # one with a bad CRC: it does not decode
    untouched = {s: (folder / done[s]["image"]).read_bytes() for s in kept if s not in (s1, s2, s3)}
    plan = json.loads((folder / "plan.json").read_text())
    n_recs = len(records(folder))

    r = run_cell("resume", folder.name, "--archive", str(archive), "--yes", timeout=300)
    assert r.code == 0 and r.doc["status"] == "DONE", r.stderr[-3000:]
    new = records(folder)[n_recs:]
    invalid = {x["station"] for x in new if x["event"] == "station_invalid"}
    assert invalid == {s1, s2, s3}
    retaken = [x["station"] for x in new if x["event"] == "station_start"]
    remaining = {s["id"] for s in plan["stations"]} - set(kept)
    assert sorted(retaken) == sorted(remaining | {s1, s2, s3}), "a station other than the damaged ones was retaken"
    for s, data in untouched.items():  # the good images stay as they were taken
        assert (folder / done[s]["image"]).read_bytes() == data, s
    assert len(list((folder / "damaged").rglob("*.png*"))) == 3  # kept for the record, out of the data
    verify = run_cell("archive", "verify", folder.name, "--archive", str(archive))
    assert verify.code == 0 and verify.doc["intact"], verify.doc
    report = json.loads((folder / "report.json").read_text())
    assert report["verdict"] == "FAIL" and len(report["targets"]) == len(json.loads((finished / "report.json")
                                                                                     .read_text())["targets"])


def test_changed_plan_after_motion_stops_the_resume_with_nothing_changed(finished, tmp_path, capsys):
    archive = tmp_path / "archive"
    folder = copy_job(finished, archive)
    kill_during_acquire(folder, 3)
    plan = json.loads((folder / "plan.json").read_text())
    plan["stations"][0]["joints"][0] += 0.1
    (folder / "plan.json").write_text(json.dumps(plan))
    before = snapshot(folder)
    code, _, err = cell(capsys, "resume", folder.name, "--archive", str(archive), "--yes")
    msg = one_line(err)
    assert code == 1 and "plan.json" in msg and "not resumed" in msg
    assert snapshot(folder) == before


# --- jobs that died at the end ------------------------------------------------------------------------


def test_job_that_died_after_its_last_stage_is_closed_by_resume_without_moving(finished, tmp_path, capsys):
    archive = tmp_path / "archive"
    folder = copy_job(finished, archive)
    cut_journal(folder, lambda r, i: not (r["event"] == "state" and r["to"] == "DONE"))
    (folder / "manifest.json").unlink()
    n = len(records(folder))
    code, doc, err = cell(capsys, "resume", folder.name, "--archive", str(archive), "--yes")
    assert code == 0 and doc["status"] == "DONE", err
    new = records(folder)[n:]
    assert not any(r["event"] in ("station_start", "stage_done") for r in new), new
    assert [r.get("to") for r in new if r["event"] == "state"] == ["DONE"]
    assert new[-1]["event"] == "terminal" and new[-1]["status"] == "DONE"
    code, doc, _ = cell(capsys, "archive", "verify", folder.name, "--archive", str(archive))
    assert code == 0 and doc["intact"], doc


def test_job_killed_after_done_is_closed_by_verify_repair(finished, tmp_path, capsys):
    archive = tmp_path / "archive"
    folder = copy_job(finished, archive)
    cut_journal(folder, lambda r, i: r["event"] != "terminal")
    (folder / "manifest.json").unlink()
    code, doc, _ = cell(capsys, "archive", "verify", folder.name, "--archive", str(archive))
    assert code == 1 and not doc["intact"]
    code, doc, err = cell(capsys, "archive", "verify", folder.name, "--archive", str(archive), "--repair")
    assert code == 0 and doc["intact"] and "manifest written" in doc["repaired"], (doc, err)
    assert records(folder)[-1]["event"] == "terminal" and records(folder)[-1]["status"] == "DONE"
    code, _, err = cell(capsys, "resume", folder.name, "--archive", str(archive), "--yes")
    assert code == 2 and "already DONE" in one_line(err)


def test_staged_job_is_listed_and_resumable(finished, tmp_path, capsys):
    from cell.job import abort_job, resume_job
    from jobutil import RecordingOutput

    archive = tmp_path / "archive"
    staged = staged_copy(finished, archive)
    code, doc, _ = cell(capsys, "archive", "list", "--archive", str(archive))
    row = next(r for r in doc["jobs"] if r["id"] == staged.name)
    assert row["staged"] and row["status"] == "VALIDATE"
    code, doc, _ = cell(capsys, "archive", "show", staged.name, "--archive", str(archive))
    assert code == 0 and doc["folder"] == str(staged)

    class AbortAtFirstProgress(RecordingOutput):  # resume, and abort as soon as ACQUIRE reports progress
        def progress(self, stage, fraction):
            abort_job(staged.name, "test")

    out = AbortAtFirstProgress()
    result = resume_job(staged.name, archive, out)
    assert any("resuming at ACQUIRE" in line for line in out.lines), out.lines
    assert result.status.value == "ABORTED" and result.folder == archive / staged.name
    assert not staged.exists()  # it reached ACQUIRE: it is in the archive now
    code, doc, _ = cell(capsys, "archive", "verify", staged.name, "--archive", str(archive))
    assert code == 0 and doc["intact"], doc


def test_staged_job_is_closed_by_verify_repair(finished, tmp_path, capsys):
    archive = tmp_path / "archive"
    staged = staged_copy(finished, archive)
    code, doc, err = cell(capsys, "archive", "verify", staged.name, "--archive", str(archive), "--repair")
    assert code == 0 and doc["intact"], (doc, err)
    assert "moved from .incoming" in doc["repaired"] and (archive / staged.name / "manifest.json").is_file()
    assert records(archive / staged.name)[-1]["status"] == "FAULTED"  # closed, and still resumable


# --- ids are names ----------------------------------------------------------------------------------


def test_path_like_ids_are_refused_by_every_command_and_nothing_is_written_outside(finished, tmp_path, capsys):
    from cell.job import abort_job
    from calibration.errors import InputError

    archive = tmp_path / "archive"
    folder = copy_job(finished, archive)
    outside = copy_job(finished, tmp_path / "elsewhere")  # a job-like folder outside the archive
    os.symlink(outside, archive / "linked")
    os.symlink("/etc", archive / "etc")
    before = snapshot(tmp_path / "elsewhere")
    bad = ["../elsewhere/" + outside.name, str(outside), f"{folder.name}/..", "..", ".", ".incoming", "a/b",
           "linked", "etc", "x\\y", ""]
    for job_id in bad:
        for args in (["resume", job_id, "--yes"], ["archive", "show", job_id], ["archive", "verify", job_id],
                     ["archive", "verify", job_id, "--repair"], ["archive", "compare", folder.name, job_id]):
            code, _, err = cell(capsys, *args, "--archive", str(archive))
            msg = one_line(err)
            assert code == 2, (job_id, args, err)
            assert "not a job id" in msg or "leads out of the archive" in msg or "no job" in msg, (job_id, msg)
        with pytest.raises(InputError):
            abort_job(job_id, archive_root=archive)
    assert snapshot(tmp_path / "elsewhere") == before
    assert not Path("/etc/.lock").exists() and not Path("/etc/journal.jsonl").exists()


# --- one line, never a traceback ----------------------------------------------------------------------


def test_damaged_archive_contents_are_one_line_each_and_never_break_the_archive(finished, tmp_path, capsys):
    archive = tmp_path / "archive"
    good = copy_job(finished, archive)
    bad_report = archive / "bad-report"
    shutil.copytree(good, bad_report)
    (bad_report / "report.json").write_text('{"targets": [oops')
    bad_manifest = archive / "bad-manifest"
    shutil.copytree(good, bad_manifest)
    (bad_manifest / "manifest.json").write_bytes(b"\x00garbage")
    (archive / "junk").mkdir()  # a folder that is no job
    (archive / "junk" / "notes.txt").write_text("x")
    (archive / "junk2").mkdir()
    (archive / "junk2" / "journal.jsonl").write_bytes(os.urandom(300) + b"\n")
    (archive / "stray.txt").write_text("a file in the archive")

    code, doc, err = cell(capsys, "archive", "list", "--archive", str(archive))
    assert code == 0, err
    rows = {r["id"]: r for r in doc["jobs"]}
    assert rows[good.name]["verdict"] == "FAIL" and "problem" not in rows[good.name]
    assert "report.json damaged" in rows["bad-report"]["problem"] and rows["bad-report"]["status"] == "DONE"
    assert "journal damaged" in rows["junk2"]["problem"] and "junk" not in rows
    code, doc, _ = cell(capsys, "archive", "show", "bad-report", "--archive", str(archive))
    assert code == 0 and "report.json damaged" in doc["problem"]
    code, _, err = cell(capsys, "archive", "compare", good.name, "bad-report", "--archive", str(archive))
    assert code == 2 and "report.json is damaged" in one_line(err)
    code, doc, _ = cell(capsys, "archive", "verify", "bad-manifest", "--archive", str(archive))
    assert code == 1 and any(p.startswith("manifest.json: damaged") for p in doc["problems"])
    code, doc, _ = cell(capsys, "archive", "verify", "bad-manifest", "--archive", str(archive), "--repair")
    assert code == 0 and doc["intact"], doc
    (archive / "index.sqlite").write_bytes(os.urandom(4096))  # a damaged index is rebuilt
    for extra in ("index.sqlite-wal", "index.sqlite-shm"):
        (archive / extra).unlink(missing_ok=True)
    code, doc, err = cell(capsys, "archive", "list", "--archive", str(archive))
    assert code == 0 and good.name in {r["id"] for r in doc["jobs"]}, err


def test_archive_that_is_a_file_or_read_only_is_one_line(tmp_path, capsys):
    from jobutil import job_variant

    job = job_variant(tmp_path / "job")
    a_file = tmp_path / "archive.txt"
    a_file.write_text("not a folder")
    for args in (["run", str(job)], ["resume", "x", "--yes"], ["archive", "list"], ["archive", "show", "x"]):
        code, _, err = cell(capsys, *args, "--archive", str(a_file))
        assert code == 2 and "is a file, not an archive folder" in one_line(err), (args, err)
    code, _, err = cell(capsys, "run", str(job), "--archive", str(a_file / "sub"))
    assert code == 2 and "cannot write there" in one_line(err)
    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() == 0:  # root writes into a read-only folder: a read-only file system instead
        if os.system(f"mount -t tmpfs -o ro,size=64k tmpfs {ro} 2>/dev/null") != 0:
            pytest.skip("cannot make a read-only folder here (root, no mount)")
    else:
        ro.chmod(0o555)
    try:
        code, _, err = cell(capsys, "run", str(job), "--archive", str(ro / "archive"))
        assert code == 2 and "cannot write there" in one_line(err), err
    finally:
        if os.geteuid() == 0:
            os.system(f"umount {ro}")
        else:
            ro.chmod(0o755)


def test_a_closed_job_whose_journal_lost_its_last_records_is_neither_resumed_nor_repaired(finished, tmp_path, capsys):
    """An outside check cut a closed job's journal at a line boundary (it still reads whole): ``cell resume`` took it
    for a job killed during ACQUIRE, drove the robot again, overwrote images 0015-0023 and the results, and rewrote
    the manifest, which then vouched for it; ``--repair`` made it "FAULTED (resumable)". The manifest that closed
    the job holds the journal's length and sha256: a shorter journal is damage, named, and nothing changes."""
    archive = tmp_path / "archive"
    folder = copy_job(finished, archive)
    lines = (folder / "journal.jsonl").read_bytes().splitlines(keepends=True)
    for keep in (42, len(lines) - 1):  # half the journal; only its terminal record
        (folder / "journal.jsonl").write_bytes(b"".join(lines[:keep]))
        before = snapshot(folder)
        code, doc, err = cell(capsys, "resume", folder.name, "--archive", str(archive), "--yes")
        msg = one_line(err)
        assert code == 1 and doc["error"] == "RecordError" and "shorter than" in msg and "not resumed" in msg, msg
        code, doc, err = cell(capsys, "archive", "verify", folder.name, "--archive", str(archive), "--repair")
        assert code == 1 and "nothing was repaired" in one_line(err)
        assert snapshot(folder) == before
    (folder / "journal.jsonl").write_bytes(b"".join(lines))
    code, _, err = cell(capsys, "resume", folder.name, "--archive", str(archive), "--yes")
    assert code == 2 and "already DONE" in one_line(err)


def test_verifying_the_whole_archive_compares_the_index_values_and_each_folder_with_its_manifest(finished, tmp_path,
                                                                                                   capsys):
    """An outside check set a job's verdict in the index to PASS (the folder says FAIL) and moved a target's
    measured x by 1 mm there; ``cell archive verify`` (no id) said "index matches the folders", exit 0, as it did for
    a changed report.json. It compares the values now, and each folder with its manifest; an archive folder that
    does not exist is bad input, not an empty archive created and found intact."""
    import sqlite3

    archive = tmp_path / "archive"
    folder = copy_job(finished, archive)
    code, doc, _ = cell(capsys, "archive", "verify", "--archive", str(archive))
    assert code == 1 and "not in the index" in doc["problems"][0]  # a copied folder: sync first
    assert cell(capsys, "archive", "sync", "--archive", str(archive))[0] == 0
    code, doc, _ = cell(capsys, "archive", "verify", "--archive", str(archive))
    assert code == 0 and doc["intact"], doc
    db = sqlite3.connect(archive / "index.sqlite")
    verdict = db.execute("select verdict from jobs").fetchone()[0]
    db.execute("update jobs set verdict = 'PASS'")
    db.execute("update targets set measured_x = measured_x + 0.001 where target_id = 'T0001'")
    db.commit()
    db.close()
    code, doc, _ = cell(capsys, "archive", "verify", "--archive", str(archive))
    said = " ".join(doc["problems"])
    assert code == 1 and f"index says verdict PASS, the report {verdict}" in said and "T0001" in said, said
    report = folder / "report.json"
    report.write_text(report.read_text().replace(f'"verdict": "{verdict}"', '"verdict": "PASS"'))
    code, doc, _ = cell(capsys, "archive", "verify", "--archive", str(archive))
    assert code == 1 and any("report.json" in p for p in doc["problems"]), doc["problems"]
    code, _, err = cell(capsys, "archive", "verify", "--archive", str(tmp_path / "archvie"))
    assert code == 2 and "no archive folder" in one_line(err) and not (tmp_path / "archvie").exists()
