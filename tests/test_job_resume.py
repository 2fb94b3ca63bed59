"""Reliability: a job killed (SIGKILL) again and again during acquisition and resumed each time
loses no image, duplicates none, keeps a readable run log of every session, and measures the
same part as an uninterrupted run with the same seed, within the stated uncertainty.
"""
from __future__ import annotations

import json
import signal
import subprocess
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2, norm

from cell.record.jobfolder import sha256_file
from cell.record.runlog import read_messages
from jobutil import (cell_command, child_env, example_run, job_variant, mahalanobis, records, run_cell,
                     truth_xyz_m)

N_KILLS = 20
SEED = 20261121


def _sessions(recs: list[dict]) -> list[list[dict]]:
    """The journal split into sessions: each starts with ``created`` (the run) or ``resumed``."""
    out: list[list[dict]] = []
    for r in recs:
        if r["event"] in ("created", "resumed"):
            out.append([])
        if out:
            out[-1].append(r)
    return out


def _job_folder(archive: Path) -> Path | None:
    dirs = [p for p in archive.iterdir() if p.is_dir() and not p.name.startswith(".")] if archive.exists() else []
    assert len(dirs) <= 1, f"more than one job folder in {archive}: {dirs}"
    return dirs[0] if dirs else None


def _wait_for_acquire(proc: subprocess.Popen, archive: Path, n_acquire_before: int, timeout_s: float = 60.0) -> Path:
    """Block until this session has entered ACQUIRE (its state record is in the journal)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        folder = _job_folder(archive)
        if folder is not None:
            n = sum(1 for r in records(folder) if r["event"] == "state" and r["to"] == "ACQUIRE")
            if n > n_acquire_before:
                return folder
        if proc.poll() is not None:
            pytest.fail(f"the cell exited ({proc.returncode}) before reaching ACQUIRE")
        time.sleep(0.02)
    proc.kill()
    proc.wait()
    pytest.fail(f"the session did not reach ACQUIRE within {timeout_s} s")


def _wait_for_records(proc: subprocess.Popen, folder: Path, event: str, n: int, timeout_s: float = 60.0) -> None:
    """Block until the journal holds ``n`` records of ``event``."""
    deadline = time.monotonic() + timeout_s
    while sum(1 for r in records(folder) if r["event"] == event) < n:
        if proc.poll() is not None or time.monotonic() > deadline:
            pytest.fail(f"the session ended or stalled before {event} record {n}")
        time.sleep(0.01)


def _station_cycle_s(folder: Path, default_s: float = 1.0) -> float:
    """Median wall time from a station's start to its image being journalled, so far."""
    start, cycle = {}, []
    for r in records(folder):
        if r["event"] == "station_start":
            start[r["station"]] = datetime.fromisoformat(r["t"])
        elif r["event"] == "station_done" and r["station"] in start:
            cycle.append((datetime.fromisoformat(r["t"]) - start[r["station"]]).total_seconds())
    return float(np.median(cycle)) if cycle else default_s


def _check_session_log(folder: Path, k: int, session: list[dict]) -> bool:
    """Run log of session ``k``, cut off by the kill, still reads and agrees with the journal.

    Returns whether it holds the image of the station in flight (logged, not yet journalled).
    """
    log = folder / ("run.mcap" if k == 0 else f"run.{k}.mcap")
    assert log.exists(), f"session {k}: no run log {log.name}"
    msgs = list(read_messages(log))
    assert msgs, f"session {k}: {log.name} yields no message"
    topics = [t for t, _ in msgs]
    assert any(t == "/state" and m["to"] == "ACQUIRE" for t, m in msgs), f"session {k}: no ACQUIRE state in {log.name}"
    images = [m["frame_id"].removeprefix("camera/") for t, m in msgs if t == "/camera/image"]
    done = [r["station"] for r in session if r["event"] == "station_done"]
    # the image is logged before its journal record: at most the one in flight is extra
    assert images[: len(done)] == done, f"session {k}: images in {log.name} {images} vs journal {done}"
    assert len(images) - len(done) in (0, 1), f"session {k}: {len(images)} images logged, {len(done)} journalled"
    assert topics.count("/robot/joint_states") >= len(done)
    return len(images) > len(done)


def _check_images(folder: Path) -> dict[str, dict]:
    """Every journalled station has exactly one record, and its image file has the journalled sha256."""
    done = [r for r in records(folder) if r["event"] == "station_done"]
    stations = [r["station"] for r in done]
    assert len(stations) == len(set(stations)), f"a station was journalled twice: {sorted(stations)}"
    for r in done:
        assert sha256_file(folder / r["image"]) == r["sha256"], f"{r['image']}: sha256 differs from the journal"
    return {r["station"]: r for r in done}


@pytest.mark.slow
@pytest.mark.timeout(420)
def test_sigkill_during_acquisition_resumes_without_losing_or_duplicating_images(tmp_path, tmp_path_factory):
    ref_job, ref_folder, _ = example_run(tmp_path_factory)
    job = job_variant(tmp_path / "job", {"sim": {"motion": "timed", "time_scale": 8.0}})
    archive = tmp_path / "archive"
    rng = np.random.default_rng(SEED)
    env = child_env()
    n_stations = None
    kills, cycle_s, progress, phases = [], [], [], []
    t_start = time.perf_counter()
    while len(kills) < N_KILLS:
        t0 = time.perf_counter()
        folder = _job_folder(archive)
        n_acq = 0 if folder is None else sum(1 for r in records(folder) if r["event"] == "state" and r["to"] == "ACQUIRE")
        args = ["run", str(job), "--archive", str(archive)] if folder is None else \
            ["resume", folder.name, "--archive", str(archive), "--yes"]
        with open(tmp_path / f"session{len(kills)}.err", "w") as err:
            proc = subprocess.Popen([*cell_command(), *args], stdout=subprocess.DEVNULL, stderr=err, env=env)
        try:
            folder = _wait_for_acquire(proc, archive, n_acq)
            if n_stations is None:
                n_stations = len(json.loads((folder / "plan.json").read_text())["stations"])
            if len(kills) == 1:  # once: a second session of a job that is still running is refused
                n_resumed = sum(r["event"] == "resumed" for r in records(folder))
                twice = run_cell("resume", folder.name, "--archive", str(archive), "--yes", env=env)
                assert twice.code == 2 and "running in another process" in twice.stderr, twice.stderr
                assert sum(r["event"] == "resumed" for r in records(folder)) == n_resumed
                assert proc.poll() is None
            n_done = sum(1 for r in records(folder) if r["event"] == "station_done")
            n_start = sum(1 for r in records(folder) if r["event"] == "station_start")
            remaining = n_stations - n_done
            # a random moment of a station's cycle (move, capture, encode, write, log, journal): once this session
            # has started its first station (a long move: every session starts at home) or its second, within
            # ~0.8 station cycles (as measured so far); sometimes while it opens its devices. Near the end only
            # then, so that acquisition is still going on at every one of the kills. The delay counts from the
            # station's journalled start, not from when this process saw it (under load that can be a station
            # later), and the second station is waited for only while stations are to spare for the kills to
            # come: the kills land mid-station however busy the machine is
            kills_left = N_KILLS - len(kills)
            if remaining > 3 and rng.random() < 0.85:
                m = int(rng.random() < 0.4 and remaining - 4 > kills_left // 2)
                _wait_for_records(proc, folder, "station_start", n_start + 1 + m)
                delay = rng.uniform(0.0, 0.8 * _station_cycle_s(folder))
                started = [r for r in records(folder) if r["event"] == "station_start"][n_start + m]
                time.sleep(max(0.0, datetime.fromisoformat(started["t"]).timestamp() + delay - time.time()))
            else:
                delay = rng.uniform(0.0, 0.3)
                time.sleep(delay)
            assert proc.poll() is None, f"the cell exited ({proc.returncode}) before kill {len(kills) + 1}"
            proc.send_signal(signal.SIGKILL)
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
        recs = records(folder)
        assert not any(r["event"] == "stage_done" and r["stage"] == "ACQUIRE" for r in recs), \
            f"kill {len(kills) + 1} landed after acquisition"
        sessions = _sessions(recs)
        in_flight = _check_session_log(folder, len(sessions) - 1, sessions[-1])
        phases.append(sessions[-1][-1]["event"] + ("+logged" if in_flight else ""))
        done = _check_images(folder)
        kills.append(delay)
        progress.append(len(done))
        cycle_s.append(time.perf_counter() - t0)
    final = run_cell("resume", folder.name, "--archive", str(archive), "--yes", timeout=300)
    assert final.code == 0, final.stderr[-2000:]
    assert final.doc["status"] == "DONE"
    total_s = time.perf_counter() - t_start

    # no image lost or duplicated: every station exactly one journalled image, files as journalled
    done = _check_images(folder)
    plan = json.loads((folder / "plan.json").read_text())
    assert sorted(done) == sorted(s["id"] for s in plan["stations"])
    acq = json.loads((folder / "acquisition.json").read_text())
    assert sorted(im["station"] for im in acq["images"]) == sorted(done)
    pngs = sorted(p.name for p in (folder / "images").iterdir())
    assert pngs == sorted(Path(done[s]["image"]).name for s in done), f"images folder holds {pngs}"
    assert not list(folder.rglob(".*.tmp*")), "a partial file of a killed write is left in the job folder"
    assert progress[-1] >= 3, f"the killed sessions acquired only {progress[-1]} stations: resume was not exercised"
    assert sum(p.startswith("station_") for p in phases) >= N_KILLS // 2, phases
    # one terminal record per session: the killed ones are recorded as such on resume
    recs = records(folder)
    sessions = _sessions(recs)
    assert len(sessions) == N_KILLS + 1
    for s in sessions:
        assert [r["event"] for r in s].count("terminal") == 1
    assert sessions[-1][-1] == next(r for r in reversed(recs) if r["event"] == "terminal")
    assert sessions[-1][-1]["status"] == "DONE"
    assert sum(1 for s in sessions[:-1] if "killed" in s[-1]["reason"]) == N_KILLS
    assert (folder / f"run.{N_KILLS}.mcap").exists() and not (folder / f"run.{N_KILLS + 1}.mcap").exists()
    verify = run_cell("archive", "verify", folder.name, "--archive", str(archive))
    assert verify.code == 0 and verify.doc["intact"], verify.doc

    # the same measurement as an uninterrupted run with the same seeds
    ref_plan = json.loads((ref_folder / "plan.json").read_text())
    np.testing.assert_allclose([s["part_from_cam"] for s in plan["stations"]],
                               [s["part_from_cam"] for s in ref_plan["stations"]], atol=1e-12)
    rep = {t["id"]: t for t in json.loads((folder / "report.json").read_text())["targets"] if None not in t["measured"]}
    ref = {t["id"]: t for t in json.loads((ref_folder / "report.json").read_text())["targets"] if None not in t["measured"]}
    assert set(rep) == set(ref)
    ids = sorted(rep)
    d = np.array([np.subtract(rep[i]["measured"], ref[i]["measured"]) for i in ids])
    cov = np.array([np.add(rep[i]["cov"], ref[i]["cov"]) for i in ids])
    m = mahalanobis(d, cov)
    level = norm.isf(chi2.sf(m**2, 3) / 2)  # equivalent one-dimensional sigma level
    # the re-taken images carry new noise: the two runs differ like two measurements of the same part. One run's
    # errors are dominated by a few weak whole-network modes that move many targets together, so the share beyond
    # 3 sigma in one comparison scatters widely (two uninterrupted runs with other seeds: 0, 0 and 4 of 195);
    # none far beyond
    assert np.mean(level <= 3.0) >= 0.95, f"{np.sum(level > 3)} of {len(ids)} targets differ beyond 3 sigma"
    assert level.max() <= 5.0, f"target {ids[int(np.argmax(level))]} differs by {level.max():.1f} sigma"
    # the same verdicts, but for a target whose deviation is within its uncertainty of the tolerance
    for i in ids:
        if rep[i]["pass"] != ref[i]["pass"]:
            margin = abs(ref[i]["deviation_norm_m"] - ref[i]["tolerance_m"])
            assert margin < 3 * np.hypot(rep[i]["achieved_sigma_m"], ref[i]["achieved_sigma_m"]), i
    t_ids, nominal, truth = truth_xyz_m(job)
    beyond = {i for i, n, t in zip(t_ids, nominal, truth) if np.linalg.norm(t - n) > 0.25e-3}
    assert len(beyond) == 3 and {i for i in ids if not rep[i]["pass"]} >= beyond  # injected beyond tolerance
    print(f"\n{N_KILLS} kills, {len(sessions)} sessions, {total_s:.1f} s in all; kill cycle "
          f"{np.mean(cycle_s):.2f} s mean ({np.min(cycle_s):.2f}..{np.max(cycle_s):.2f}); stations done after each kill "
          f"{progress}; last journal event before each kill {phases}; coordinate difference to the uninterrupted run: max {level.max():.2f} sigma, "
          f"max {np.abs(d).max() * 1e6:.1f} um")
