"""Helpers for the web console's tests: a synthesized archive of finished jobs, users, a served console.

The trend tests use *synthesized* finished jobs (report.json, run.json, journal and manifest written
directly, as a DONE job leaves them), so that ten serial parts with a known drift cost milliseconds
instead of ten simulated jobs; the browser test also runs one real simulated job end to end.
"""
from __future__ import annotations

import json
import os
import socket
import subprocess
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from jobutil import cell_command, child_env, job_variant

PART = "TR-500"
TARGETS = [f"T{k:02d}" for k in range(1, 7)]
DRIFTING = ("T02", "T05")
TOL_M = 100e-6


def seed_trend_archive(archive: Path, n_parts: int = 10, drift_from: int = 6, drift_step_m: float = 12e-6,
                       noise_m: float = 2e-6, seed: int = 5) -> list[str]:
    """``n_parts`` DONE jobs of part PART (serials SN-0001...), one a minute; targets DRIFTING move in z by
    ``drift_step_m`` more per part from part ``drift_from`` on (1-based), the others scatter with ``noise_m``.
    Returns the job ids, oldest first."""
    from cell.record.archive import Archive
    from cell.record.jobfolder import JobFolder, atomic_write_json

    rng = np.random.default_rng(seed)
    t0 = datetime(2026, 11, 20, 8, 0, tzinfo=timezone.utc)
    nominal = {t: np.array([0.05 * k, 0.02 * k, 0.01]) for k, t in enumerate(TARGETS)}
    ids = []
    for i in range(1, n_parts + 1):
        jid = f"2026-11-20T08-{i:02d}-00-trendpart"
        folder = Path(archive) / jid
        folder.mkdir(parents=True)
        jf = JobFolder(folder)
        serial = f"SN-{i:04d}"
        info = {"part": {"number": PART, "revision": "B", "serial": serial}, "operator": "olga", "cell_id": "cell-1"}
        atomic_write_json(folder / "run.json", info)
        started = (t0 + timedelta(minutes=i)).isoformat(timespec="milliseconds")
        finished = (t0 + timedelta(minutes=i, seconds=40)).isoformat(timespec="milliseconds")
        targets = []
        for t in TARGETS:
            d = rng.normal(0, noise_m, 3) + np.array([20e-6, -10e-6, 15e-6])
            if t in DRIFTING and i >= drift_from:
                d[2] += drift_step_m * (i - drift_from + 1)
            n = float(np.linalg.norm(d))
            targets.append({"id": t, "kind": "dot", "nominal": nominal[t].tolist(), "measured": (nominal[t] + d).tolist(),
                            "cov": (np.eye(3) * noise_m ** 2).tolist(), "deviation": d.tolist(), "deviation_norm_m": n,
                            "tolerance_m": TOL_M, "pass": n <= TOL_M, "predicted_sigma_m": 2e-6,
                            "achieved_sigma_m": 2.2e-6, "uncertainty_U_m": 4e-6, "decision": "conforming"})
        verdict = "PASS" if all(t["pass"] for t in targets) else "FAIL"
        rep = {"job": {"id": jid, "name": "trendpart", "part": "trendpart", "seed": 0, "status": "DONE",
                       "started": started, "finished": finished, "versions": {}},
               "verdict": verdict, **info, "images": 16, "sigma0_px": 0.05, "targets": targets,
               "alignment": {"method": "rigid", "targets_in_fit": len(targets), "rms_m": 1e-6, "trusted": True}}
        atomic_write_json(folder / "report.json", rep)
        (folder / "journal.jsonl").write_text("".join(json.dumps(r) + "\n" for r in [
            {"t": started, "event": "created", "name": "trendpart", **info},
            *({"t": started, "event": "state", "from": a, "to": b} for a, b in
              zip(["CREATED", "LOAD", "PLAN", "VALIDATE", "ACQUIRE", "MEASURE", "CALIBRATE", "ADJUST", "REPORT"],
                  ["LOAD", "PLAN", "VALIDATE", "ACQUIRE", "MEASURE", "CALIBRATE", "ADJUST", "REPORT", "DONE"])),
            {"t": finished, "event": "terminal", "status": "DONE", "reason": ""}]))
        (folder / "report.html").write_text(f"<html><body><div id=verdict class='verdict {verdict}'>{verdict}</div></body></html>")
        jf.write_manifest()
        ids.append(jid)
    Archive(Path(archive)).reindex()
    return ids


def add_user(archive: Path, name: str, role: str, password: str) -> None:
    """``cell users add NAME --role ROLE`` with the password on stdin, as an administrator does it."""
    p = subprocess.run([*cell_command(), "users", "add", name, "--role", role, "--archive", str(archive)],
                       input=password + "\n", capture_output=True, text=True, env=child_env(), timeout=60)
    assert p.returncode == 0, p.stderr
    assert password not in p.stdout + p.stderr


def tiny_program(programs: Path, name: str = "bracket", **sim) -> Path:
    """A part program: the example bracket made cheap (small camera, short search), with part number."""
    changes = {"job": {"number": "BR-1002", "revision": "C"},
               "planning": {"n_stations": 16, "n_candidates": 400, "population": 24, "generations": 30},
               "camera": {"width": 1224, "height": 1024, "pixel_size_um": 6.9}}
    if sim:
        changes["sim"] = sim
    return job_variant(programs / name, changes)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Served:
    """``cell serve`` in a child process (the console as it runs on a cell), stopped with SIGTERM."""

    def __init__(self, archive: Path, programs: Path, log: Path, extra: list[str] | None = None,
                 scheme: str = "http"):
        self.port = free_port()
        self.url = f"{scheme}://127.0.0.1:{self.port}"
        self.log = log
        self._f = open(log, "wb")
        env = child_env() | {"OMP_NUM_THREADS": "1"}
        self.proc = subprocess.Popen([*cell_command(), "serve", "--port", str(self.port), "--archive", str(archive),
                                      "--programs", str(programs), "--cell-id", "cell-1", *(extra or [])],
                                     stdout=self._f, stderr=subprocess.STDOUT, env=env)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    return
            except OSError:
                if self.proc.poll() is not None:
                    break
                time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"cell serve did not come up:\n{log.read_text()[-2000:]}")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._f.close()


CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]


def chromium_path() -> str | None:
    for p in ("/usr/bin/chromium", "/usr/bin/chromium-browser"):
        if os.path.exists(p):
            return p
    return None


#: the console's accounts in the security tests: one per role
PASSWORDS = {"ada": "admin-pw-9f3k", "eve": "engineer-pw-2m", "olga": "operator-pw-7q"}
ROLES = {"ada": "admin", "eve": "engineer", "olga": "operator"}


def security_site(base: Path) -> tuple[Path, Path, list[str]]:
    """An archive of three synthesized jobs with one account per role, and an empty programs folder, under ``base``:
    ``(archive, programs, job ids)``."""
    from cell.web.users import UserStore

    archive, programs = base / "archive", base / "programs"
    programs.mkdir(parents=True)
    ids = seed_trend_archive(archive, n_parts=3)
    store = UserStore(archive / "console.sqlite")
    for name, pw in PASSWORDS.items():
        store.add(name, ROLES[name], pw)
    return archive, programs, ids

