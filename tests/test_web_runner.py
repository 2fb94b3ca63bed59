"""The live view's reading of a job folder (state, progress by station, time left, poses) and the fault
messages an operator gets, from the runner's own fault texts."""
from __future__ import annotations

import json

import pytest

from cell.record.jobfolder import JobFolder
from cell.web.runner import live_state, operator_advice


def _journal(folder, recs):
    folder.mkdir(parents=True)
    (folder / "journal.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))


def test_progress_counts_stages_and_stations_and_estimates_time_left(tmp_path):
    from datetime import datetime, timedelta, timezone

    t0 = datetime.now(timezone.utc) - timedelta(seconds=60)
    ts = lambda s: (t0 + timedelta(seconds=s)).isoformat()  # noqa: E731
    recs = [{"t": ts(0), "event": "created"}]
    for a, b, s in (("CREATED", "LOAD", 1), ("LOAD", "PLAN", 2), ("PLAN", "VALIDATE", 30), ("VALIDATE", "ACQUIRE", 40)):
        recs.append({"t": ts(s), "event": "state", "from": a, "to": b})
        if a != "CREATED":
            recs.append({"t": ts(s), "event": "stage_done", "stage": a, "duration_s": 1.0})
    pose = [[1, 0, 0, 0.5], [0, 1, 0, 0.2], [0, 0, 1, 0.4], [0, 0, 0, 1]]
    recs += [{"t": ts(41 + k), "event": "station_done", "station": f"S{k:03d}", "image": f"images/{k:04d}.png",
              "base_from_flange": pose} for k in range(4)]
    folder = tmp_path / "job"
    _journal(folder, recs)
    (folder / "plan.json").write_text(json.dumps({"stations": [{"id": f"S{k:03d}"} for k in range(16)]}))
    d = live_state(folder)
    assert d["state"] == d["stage"] == "ACQUIRE" and d["stations_done"] == 4 and d["stations"] == 16
    done = 3.0  # LOAD, PLAN, VALIDATE of 7 unit stages + ACQUIRE weighted 4
    from cell.states import STAGES

    total = len(STAGES) - 1 + 4.0
    assert d["progress"] == pytest.approx((done + 4.0 * 4 / 16) / total)
    assert d["time_left_s"] == pytest.approx(60 / d["progress"] * (1 - d["progress"]), rel=0.05)
    assert d["flange_xyz_m"] == [[0.5, 0.2, 0.4]] * 4 and d["latest_image"] == "images/0003.png"
    JobFolder(folder).append("state", **{"from": "ACQUIRE", "to": "FAULTED", "cause": "x"})
    JobFolder(folder).append("terminal", status="FAULTED", reason="ACQUIRE: protective stop (injected) ...")
    d = live_state(folder)
    assert d["state"] == "FAULTED" and d["time_left_s"] is None and "protective stop" in d["reason"]


@pytest.mark.parametrize("reason,words", [
    ("ACQUIRE: protective stop (injected) 0.4 s into a 1.2 s move at 33% of the path", "release the stop on the teach pendant"),
    ("ACQUIRE: emergency stop during move (safety_status_bits=0x2)", "reset the emergency stop"),
    ("ACQUIRE: UR at 10.0.0.2: could not connect (timeout)", "check its power and cable"),
    ("aborted by the operator (AbortRequested)", "Press Resume to continue"),
    ("ACQUIRE: the process ended without a terminal record (killed or crashed)", "controller stopped"),
    ("ADJUST: bundle: no scale bar has both targets observed in two images or more", "Call an engineer"),
])
def test_faults_are_told_in_words_an_operator_can_act_on(reason, words):
    assert words in operator_advice(reason)


def test_live_image_shows_the_dots_found_before_measure_and_the_measured_ones_after(tmp_path):
    import cv2
    import numpy as np

    from cell.web.service import _detections, _preview_detections, latest_image_jpeg

    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:480, 0:640]
    truth = rng.uniform([40, 40], [600, 440], (12, 2))
    img = np.full((480, 640), 20.0) + rng.normal(0, 1.5, (480, 640))
    for u, v in truth:
        img += 200 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 2.5 ** 2))
    folder = tmp_path / "job"
    (folder / "images").mkdir(parents=True)
    cv2.imwrite(str(folder / "images/0001.png"), np.clip(img, 0, 255).astype(np.uint8))
    JobFolder(folder).append("station_done", station="S001", image="images/0001.png", sha256="x")
    assert _detections(folder, "S001") is None  # nothing measured yet
    found = np.array(_preview_detections(str(folder / "images/0001.png"), "x"))
    assert len(found) == len(truth)
    d = np.linalg.norm(found[:, None] - truth[None], axis=2).min(axis=1)
    assert d.max() < 0.1, d  # the detector's centres, to a tenth of a pixel
    jpg = cv2.imdecode(np.frombuffer(latest_image_jpeg(folder), np.uint8), cv2.IMREAD_COLOR)
    green = (jpg[..., 1] > 150) & (jpg[..., 0] < 90) & (jpg[..., 2] < 90)
    assert green.sum() > 12 * 20  # a ring drawn round each dot
    # after MEASURE: the identified observations are drawn instead
    (folder / "observations.json").write_text(json.dumps({"images": [{"station": "S001", "uv": truth[:5].tolist()}]}))
    assert _detections(folder, "S001") == truth[:5].tolist()


@pytest.mark.slow
def test_a_job_started_in_a_terminal_blocks_the_console_and_its_abort_reaches_it(tmp_path):
    import subprocess
    import time

    from fastapi.testclient import TestClient
    from jobutil import cell_command, child_env
    from webutil import tiny_program

    from cell.web.app import create_app
    from cell.web.deps import Config
    from cell.web.users import UserStore

    archive, programs = tmp_path / "archive", tmp_path / "programs"
    job = tiny_program(programs, "bracket", motion="timed", time_scale=2.0)
    UserStore(archive / "console.sqlite").add("olga", "operator", "olga-pw-1234")
    proc = subprocess.Popen([*cell_command(), "run", str(job), "--archive", str(archive), "--serial", "T-1"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=child_env())
    try:
        # until the terminal's job holds its lock (not merely until its .lock file exists)
        held = lambda: any(JobFolder(p.parent).running_pid() == proc.pid  # noqa: E731
                           for p in [*(archive / ".incoming").glob("*/.lock"), *archive.glob("*/.lock")])
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None and not held():
            time.sleep(0.05)
        assert held(), "the terminal's job did not take its lock"
        app = create_app(Config(archive=archive, programs=programs))
        with TestClient(app) as c:
            tok = c.post("/api/token", json={"username": "olga", "password": "olga-pw-1234"}).json()["token"]
            h = {"Authorization": f"Bearer {tok}"}
            r = c.post("/api/jobs", json={"program": "bracket", "serial": "T-2"}, headers=h)
            assert r.status_code == 409, r.text
            job_id = next(p.name for p in [*(archive / ".incoming").glob("*"), *archive.glob("20*")] if p.is_dir())
            assert job_id in r.json()["detail"] and "cell run" in r.json()["detail"]
            assert c.post(f"/api/jobs/{job_id}/abort", headers=h).status_code == 200
            assert proc.wait(timeout=120) == 130  # the terminal's job ended ABORTED, through its own abort path
            assert c.get(f"/api/jobs/{job_id}", headers=h).json()["state"] == "ABORTED"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_damaged_journal_is_reported_not_a_crash_of_the_live_view(tmp_path):
    folder = tmp_path / "job"
    folder.mkdir()
    jf = JobFolder(folder)
    jf.append("created", name="x")
    jf.append("state", **{"from": "CREATED", "to": "LOAD"})
    jf.append("state", **{"from": "LOAD", "to": "PLAN"})
    lines = (folder / "journal.jsonl").read_text().splitlines(keepends=True)
    lines[1] = lines[1].replace("LOAD", "L0AD")  # a flipped byte: its checksum no longer matches
    (folder / "journal.jsonl").write_text("".join(lines))
    d = live_state(folder)
    assert d["state"] == "CREATED" and d["record_damage"] and "journal" in d["record_damage"]


def test_a_job_moving_from_incoming_into_the_archive_is_still_seen_running(tmp_path):
    # ACQUIRE renames the folder out of .incoming and records the job in the index after: in between, the job is
    # in neither list, and the console must still refuse to start a second one
    from cell.record.archive import Archive
    from cell.web.runner import CellRunner

    archive = tmp_path / "archive"
    folder = JobFolder(archive / "20260101T000000-bracket-0001")
    folder.path.mkdir(parents=True)
    Archive(archive).close()
    folder.append("created", name="bracket")
    fd = folder.lock()  # held by this process, as the terminal's job holds it
    try:
        assert CellRunner(archive).external_running() == folder.job_id
    finally:
        import os

        os.close(fd)
    assert CellRunner(archive).external_running() is None
