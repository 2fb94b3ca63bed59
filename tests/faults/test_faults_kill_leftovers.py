"""What a kill leaves, and what a resume makes of it (decision 0060).

- run.json (part number, revision, serial, operator) missing, edited or unreadable when a job is resumed: rebuilt
  from the journal's ``created`` record, which holds the same fields; the copy found is kept in ``damaged/``.
- A temporary file a kill left beside ``figures/plan.png`` (any ``*.tmp``) is removed by the resume and never
  vouched for by the manifest; plan.png itself is written with the project's atomic writer.
- Two ``cell run`` choosing the same job id: the one whose ``mkdir`` loses takes the next id.
- The pre-analysis cache carries a digest: a flipped byte is refused, the rays rendered again, the journal says so.

The resumes abort as soon as ACQUIRE reports progress: what is checked is what the resume did before.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cell.cli import main as cell_main
from cell.record.jobfolder import JobFolder, _line_hash, sha256_file
from faultutil import copy_job, kill_during_acquire, staged_copy
from jobutil import RecordingOutput, example_run, records

SERIAL, OPERATOR = "SN-4711", "alice"


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    _, folder, _ = example_run(tmp_path_factory)
    return folder


def _rewrite_journal(folder: Path, edit) -> None:
    """Apply ``edit(record)`` to every record and write the journal again with fresh line checksums."""
    out = []
    for line in (folder / "journal.jsonl").read_text(encoding="utf-8").splitlines():
        rec = json.loads(line)
        rec.pop("h", None)
        edit(rec)
        rec["h"] = _line_hash(json.dumps(rec))
        out.append(json.dumps(rec) + "\n")
    (folder / "journal.jsonl").write_text("".join(out), encoding="utf-8")


def _with_serial(folder: Path) -> dict:
    """Give the copied job a serial number and an operator, as ``cell run --serial --operator`` would have."""
    from cell.record.runinfo import write_run_info

    info = json.loads((folder / "run.json").read_text())
    info["part"]["serial"], info["operator"] = SERIAL, OPERATOR
    write_run_info(folder, info)
    sha = sha256_file(folder / "run.json")

    def edit(rec):
        if rec["event"] == "created":
            rec["part"], rec["operator"] = info["part"], info["operator"]
        elif rec["event"] == "stage_done" and "run.json" in (rec.get("files") or {}):
            rec["files"]["run.json"] = sha

    _rewrite_journal(folder, edit)
    return info


def _resume_until_acquire(job_id: str, archive: Path) -> tuple[RecordingOutput, object]:
    """``cell resume``, aborted as soon as ACQUIRE reports progress."""
    from cell.job import abort_job, resume_job

    class AbortAtFirstProgress(RecordingOutput):
        def progress(self, stage, fraction):
            abort_job(job_id, "test")

    out = AbortAtFirstProgress()
    return out, resume_job(job_id, archive, out)


def _cell(capsys, *args: str) -> tuple[int, dict | None]:
    code = cell_main([*args, "--json"])
    out, _ = capsys.readouterr()
    return code, (json.loads(out) if out.strip() else None)


# --- finding 1: run.json -------------------------------------------------------------------------------


@pytest.mark.parametrize("damage", ["missing", "edited", "unreadable"])
def test_resume_rebuilds_run_json_from_the_created_record(finished, tmp_path, capsys, damage):
    archive = tmp_path / "archive"
    if damage == "unreadable":  # killed during ACQUIRE, after 3 stations: the robot had moved
        folder = copy_job(finished, archive)
        kill_during_acquire(folder, 3)
    else:  # killed before the robot moved (the tester's case), staged in .incoming
        folder = staged_copy(finished, archive)
    info = _with_serial(folder)
    good = (folder / "run.json").read_bytes()
    if damage == "missing":
        (folder / "run.json").unlink()
    elif damage == "edited":
        edited = json.loads(good) | {"operator": "mallory"}
        edited["part"] = edited["part"] | {"serial": "SN-0000"}
        (folder / "run.json").write_text(json.dumps(edited, indent=1) + "\n")
    else:
        (folder / "run.json").write_bytes(good[: len(good) // 2])
    n = len(records(folder))
    out, result = _resume_until_acquire(folder.name, archive)
    final = archive / folder.name
    assert result.status.value == "ABORTED" and result.folder == final, (result, out.lines)
    assert (final / "run.json").read_bytes() == good  # the file the job wrote when it started, byte for byte
    said = [ln for ln in out.lines if "run.json" in ln]
    assert len(said) == 1 and "rebuilt from the journal's created record" in said[0] and SERIAL in said[0], out.lines
    new = records(final)[n:]
    assert not any(r["event"] == "reopened" for r in new), new  # nothing is made again for it
    assert any(r["event"] == "stored" and r["file"] == "run.json" and r["sha256"] == sha256_file(final / "run.json")
               for r in new)
    kept = [r for r in new if r["event"] == "quarantined" and r["file"] == "run.json"]
    if damage == "missing":
        assert not kept
    else:  # the copy found is kept, out of the job's data
        assert len(kept) == 1 and (final / kept[0]["moved_to"]).is_file()
    code, doc = _cell(capsys, "archive", "list", "--serial", SERIAL, "--archive", str(archive))
    assert code == 0 and [r["id"] for r in doc["jobs"]] == [folder.name], doc
    code, doc = _cell(capsys, "archive", "verify", folder.name, "--archive", str(archive))
    assert code == 0 and doc["intact"], doc
    assert json.loads((final / "run.json").read_text()) == info


# --- finding 2: a temporary file beside plan.png ----------------------------------------------------------


def test_a_temporary_file_a_kill_left_beside_plan_png_is_removed_and_never_vouched_for(finished, tmp_path, capsys):
    archive = tmp_path / "archive"
    folder = staged_copy(finished, archive)
    png = (folder / "figures" / "plan.png").read_bytes()
    left = ["figures/plan.png.k3j2_x1.tmp", "figures/.plan.png.tmp4242"]  # mkstemp's name, and the atomic writer's
    for rel in left:
        (folder / rel).write_bytes(png[: len(png) // 3])
    out, result = _resume_until_acquire(folder.name, archive)
    final = archive / folder.name
    assert result.status.value == "ABORTED", out.lines
    assert not any((final / rel).exists() for rel in left)
    notes = [r["text"] for r in records(final) if r["event"] == "note" and "partial file" in r["text"]]
    assert len(notes) == 1 and all(rel in notes[0] for rel in left), notes
    manifest = json.loads((final / "manifest.json").read_text())
    assert not [f for f in manifest["files"] if f.endswith(".tmp")], manifest["files"]
    code, doc = _cell(capsys, "archive", "verify", folder.name, "--archive", str(archive))
    assert code == 0 and doc["intact"], doc


def test_a_tmp_file_in_a_job_folder_is_neither_a_stored_file_nor_vouched_for(tmp_path):
    folder = JobFolder(tmp_path / "job")
    (folder.path / "figures").mkdir(parents=True)
    (folder.path / "figures" / "plan.png").write_bytes(b"png")
    (folder.path / "figures" / "plan.png.abc123.tmp").write_bytes(b"half")
    assert folder.stored_files() == ["figures/plan.png"]
    doc = folder.write_manifest()
    assert list(doc["files"]) == ["figures/plan.png"] and "figures/plan.png.abc123.tmp" in doc["unverified"]


def _fake_plan_and_part():
    import trimesh

    rng = np.random.default_rng(3)
    mesh = trimesh.creation.box((0.3, 0.2, 0.1))
    xyz = rng.uniform(-0.1, 0.1, (12, 3))
    T = np.tile(np.eye(4), (3, 1, 1))
    T[:, :3, 3] = [[0, 0, 0.6], [0.4, 0, 0.5], [-0.4, 0, 0.5]]
    cov = np.tile(np.diag([1e-11, 2e-11, 4e-11]), (12, 1, 1))
    plan = SimpleNamespace(xyz=xyz, part_from_cam=T, sigma=np.sqrt(np.trace(cov, axis1=1, axis2=2)), cov=cov,
                           station_ids=["S000", "S001", "S002"], mode="fixed", criterion="max", min_rays=3,
                           history=[], search={}, predicted_sigma_max_m=8e-6, predicted_sigma_mean_m=8e-6, seed=1)
    return SimpleNamespace(mesh=mesh, name="box"), plan


def test_plan_png_is_written_by_the_atomic_writer_and_journalled(tmp_path, monkeypatch):
    from cell.record.jobfolder import atomic_write_bytes
    from planning.plot import plot_plan

    part, plan = _fake_plan_and_part()
    folder = JobFolder(tmp_path / "job")
    folder.path.mkdir()
    with folder.recording("PLAN"):  # as PLAN writes it: through the job folder's writer (planning imports no cell)
        plot_plan(part, plan, folder.file("figures/plan.png"), write=atomic_write_bytes)
    png = folder.path / "figures" / "plan.png"
    stored = [r for r in records(folder.path) if r["event"] == "stored"]
    assert [(r["file"], r["sha256"], r["stage"]) for r in stored] == [("figures/plan.png", sha256_file(png), "PLAN")]

    # killed between the write of the temporary file and its rename: what is left is a partial file
    def killed(src, dst):
        raise KeyboardInterrupt("killed")

    monkeypatch.setattr(os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        plot_plan(part, plan, png, write=atomic_write_bytes)
    monkeypatch.undo()
    leftover = sorted(p.name for p in png.parent.iterdir() if p.name != "plan.png")
    assert leftover and all(n.startswith(".") for n in leftover), leftover
    assert folder.remove_partial_files() and sorted(p.name for p in png.parent.iterdir()) == ["plan.png"]


# --- finding 3: two `cell run` in the same second -----------------------------------------------------------


def test_the_run_that_loses_the_race_for_a_job_id_takes_the_next(tmp_path_factory, tmp_path, monkeypatch):
    """Another process creates the job's folder between this one's choice of the id and its mkdir."""
    import cell.job as job_mod

    job_toml, _, _ = example_run(tmp_path_factory)
    monkeypatch.setattr(job_mod, "new_job_id", lambda stem, now=None: f"2026-11-25T08-00-00-{stem}")
    monkeypatch.setattr(job_mod, "_start_staged", lambda job_path, job, archive, folder, job_id, *a, **k: folder)
    real_mkdir = os.mkdir
    taken: list[str] = []

    def racing_mkdir(path, mode=0o777, **kw):
        p = Path(path)
        if p.parent.name == ".incoming" and not taken:  # the other `cell run` wins this id
            real_mkdir(path, mode)
            taken.append(p.name)
        return real_mkdir(path, mode, **kw)

    monkeypatch.setattr(os, "mkdir", racing_mkdir)
    archive = tmp_path / "archive"
    folder = job_mod.start_job(job_toml, archive, None, RecordingOutput())
    monkeypatch.undo()
    assert taken and folder.path.name == f"{taken[0]}-2", (taken, folder)
    assert sorted(p.name for p in (archive / ".incoming").iterdir()) == sorted([taken[0], f"{taken[0]}-2"])


# --- finding 4: the pre-analysis cache ------------------------------------------------------------------------


def test_a_flipped_byte_in_the_preanalysis_cache_is_refused_rebuilt_and_journalled(tmp_path, monkeypatch):
    import cell.stages.preanalysis as pre

    rng = np.random.default_rng(11)
    q = 500
    made = []

    def rendered(job, poses, progress=None):
        made.append(1)
        r = pre.PredictedRays(np.arange(q) % 7, np.arange(q) % 50, rng.uniform(0, 1e-3, (q, 2, 2)),
                              np.zeros(q), np.zeros(q, dtype=bool), np.full((q, 2, 2), 0.0123456789),
                              np.ones(q, dtype=bool), np.full(q, np.nan), np.zeros((q, 2)))
        r.facts = {"rays": q}
        return r

    monkeypatch.setattr(pre, "_cache_key", lambda job, poses: "k" * 32)
    monkeypatch.setattr(pre, "rendered_rays", rendered)
    cache = tmp_path / "cache"
    first = pre.cached_rendered_rays(None, np.eye(4)[None], cache)
    again = pre.cached_rendered_rays(None, np.eye(4)[None], cache)
    assert len(made) == 1 and np.array_equal(again.cov, first.cov) and again.facts == {"rays": q}
    path = cache / f"preanalysis-{'k' * 32}.npz"
    data = bytearray(path.read_bytes())
    k = data.index(np.float64(0.0123456789).tobytes())  # inside the stored covariances of the centres
    data[k + 3] ^= 0x04
    path.write_bytes(bytes(data))
    folder = JobFolder(tmp_path / "job")
    folder.path.mkdir()
    with folder.recording("PLAN"):
        rebuilt = pre.cached_rendered_rays(None, np.eye(4)[None], cache)
    assert len(made) == 2, "the damaged cache was used"
    assert np.all(rebuilt.cov == 0.0123456789)
    notes = [r["text"] for r in records(folder.path) if r["event"] == "note"]
    assert len(notes) == 1 and "pre-analysis cache" in notes[0] and "refused" in notes[0], notes
    assert rebuilt.facts["cache_refused"] == notes[0]  # PLAN says it on the console and in the run log from there
    again = pre.cached_rendered_rays(None, np.eye(4)[None], cache)
    assert again is not None and len(made) == 2 and "cache_refused" not in again.facts  # rewritten, said once
    assert sorted(p.name for p in cache.iterdir()) == [path.name]  # no temporary file left
