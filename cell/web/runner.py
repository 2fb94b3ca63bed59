"""The cell's one running job, as the console starts, watches and stops it.

A job started from the console is ``cell run PROGRAM --serial SN --operator USER`` (or ``cell resume``)
in a child process: the same runner, state machine, journal and run log as on the command line.
Its stderr goes to a file the console reads for log lines; the live view reads the job folder
(journal, plan, images) and the run log's detections. One job at a time per cell: a second start
is refused naming the running job. Abort is the runner's own abort path: SIGTERM, which the
runner turns into AbortRequested (robot stopped, ABORTED recorded).
"""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from calibration.errors import InputError
from cell.record.jobfolder import JobFolder
from cell.states import STAGES


class Busy(InputError):
    """The cell runs a job already."""


@dataclass
class Session:
    """One child process running (or resuming) a job."""

    proc: subprocess.Popen
    user: str
    kind: str  # "run" | "resume"
    err_path: Path
    out_path: Path
    started: float = field(default_factory=time.time)
    job_id: str | None = None
    program: str = ""
    serial: str | None = None

    def alive(self) -> bool:
        return self.proc.poll() is None


_JOB_LINE = re.compile(r"^job (\S+)  \(|^job (\S+): resuming")


def _cell_command() -> list[str]:
    script = Path(sys.executable).parent / "cell"
    return [str(script)] if script.exists() else [sys.executable, "-m", "cell.cli"]


class CellRunner:
    """Starts, watches and stops the one job of this cell."""

    def __init__(self, archive_root: Path, cell_id: str | None = None, archive_url: str | None = None):
        self.root = Path(archive_root).resolve()
        self.cell_id = cell_id
        #: the index the console reads: the jobs it starts are indexed there too (None: the children's default)
        self.archive_url = archive_url
        self.work = self.root / ".console"
        self.work.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self.current: Session | None = None
        self._n = 0

    # --- starting -----------------------------------------------------------------
    def _refuse_if_busy(self) -> None:
        s = self.current
        if s is not None and s.alive():
            name = self.job_id_of(s, wait_s=15.0) or f"{Path(s.program).stem} (starting)"
            raise Busy(f"the cell is running job {name} (started by {s.user}); wait for it to end or abort it")
        other = self.external_running()
        if other is not None:
            raise Busy(f"the cell is running job {other} (started outside the console, e.g. 'cell run'); "
                       "wait for it to end or abort it")

    def external_running(self) -> str | None:
        """A job of this archive that another process runs now (its ``.lock`` held), e.g. ``cell run``.

        A job leaves ``.incoming`` for the archive (at ACQUIRE) by a rename and records itself in the index
        after it: for that moment it is in neither list. So the index is read first, ``.incoming`` listed
        next and the archive's folders the index does not know yet last, and each candidate's lock is looked
        for in both places: a job promoted between any two of these steps is still found.
        """
        from cell.record.archive import Archive
        from cell.record.archive.ids import INCOMING

        a = Archive(self.root, self.archive_url)
        mine = self.current.job_id if self.current is not None and self.current.alive() else None
        try:
            rows = a.list()
            ids = [r["id"] for r in rows
                   if r.get("status") not in ("DONE", "FAULTED", "ABORTED") and r.get("origin") == a.origin]
            ids += [f.job_id for f in a.staged()]
            ids += [f.job_id for f in a.folders_not_in({r["id"] for r in rows})]
        finally:
            a.close()
        for job_id in dict.fromkeys(ids):
            if job_id == mine:
                continue
            for path in (self.root / INCOMING / job_id, self.root / job_id):
                if path.is_dir() and not path.is_symlink() and JobFolder(path).running_pid() is not None:
                    return job_id
        return None

    def _spawn(self, args: list[str], user: str, kind: str, positional: tuple[str, ...] = ()) -> Session:
        """``cell ARGS --archive ROOT --json -- POSITIONAL`` (ROOT is absolute): every value from a user goes as ``--option=value`` or
        after ``--``, so one that starts with ``-`` (a serial ``-12A``) is a value, never an option."""
        self._n += 1
        stem = f"{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}-{self._n}"
        err, out = self.work / f"{stem}.err", self.work / f"{stem}.json"
        env = dict(os.environ)
        env.pop("CELL_DEBUG", None)
        if self.archive_url:
            # the child's --archive-url, given through its environment: a password in the URL stays out of
            # the process list (CELL_ARCHIVE_URL ranks with --archive-url, above the cell file's url)
            env["CELL_ARCHIVE_URL"] = self.archive_url
        with open(err, "wb") as fe, open(out, "wb") as fo:
            proc = subprocess.Popen([*_cell_command(), *args, "--archive", str(self.root), "--json", "--", *positional],
                                    stdout=fo, stderr=fe, stdin=subprocess.DEVNULL, env=env, start_new_session=True)
        return Session(proc, user, kind, err, out)

    def start(self, program: Path, serial: str | None, user: str) -> Session:
        with self._lock:
            self._refuse_if_busy()
            args = ["run", f"--operator={user}"]
            if serial:
                args += [f"--serial={serial}"]
            if self.cell_id:
                args += [f"--cell-id={self.cell_id}"]
            s = self._spawn(args, user, "run", (str(program),))
            s.program, s.serial = str(program), serial
            self.current = s
        return s

    def resume(self, job_id: str, user: str) -> Session:
        with self._lock:
            self._refuse_if_busy()
            s = self._spawn(["resume", "--yes", f"--operator={user}"], user, "resume", (job_id,))
            s.job_id = job_id
            self.current = s
        return s

    # --- watching -------------------------------------------------------------------
    def log_lines(self, s: Session, n: int = 40) -> list[str]:
        try:
            text = s.err_path.read_text(errors="replace")
        except OSError:
            return []
        return [ln for ln in text.splitlines() if ln.strip()][-n:]

    def job_id_of(self, s: Session, wait_s: float = 0.0) -> str | None:
        """The id of the job a session runs (read from its first line); waits up to ``wait_s``."""
        t_end = time.monotonic() + wait_s
        while s.job_id is None:
            for ln in self.log_lines(s, 1000):
                m = _JOB_LINE.match(ln)
                if m:
                    s.job_id = m.group(1) or m.group(2)
                    break
            if s.job_id is not None or time.monotonic() >= t_end or not s.alive():
                break
            time.sleep(0.05)
        return s.job_id

    def session_of(self, job_id: str) -> Session | None:
        s = self.current
        if s is not None and self.job_id_of(s) == job_id:
            return s
        return None

    def result(self, s: Session) -> dict | None:
        """The finished session's JSON document (None while it runs)."""
        if s.alive():
            return None
        try:
            return json.loads(s.out_path.read_text() or "null")
        except (OSError, ValueError):
            return None

    def folder_of(self, job_id: str) -> Path | None:
        """The folder of a job in the archive or still staged in .incoming (None if neither)."""
        from cell.web.store import NotFound, job_folder

        try:
            return job_folder(self.root, job_id, staged=True)
        except NotFound:
            return None

    # --- stopping -------------------------------------------------------------------
    def abort(self, job_id: str, who: str = "console") -> bool:
        """Stop the running job now, through the runner's one abort path (:func:`cell.job.abort_job`: the
        job's process gets SIGTERM, its runner sends the robot's stop at once and ends ABORTED). False if
        this cell is not running that job."""
        from cell.job import abort_job

        s = self.session_of(job_id)
        if s is None or not s.alive():
            return False
        if not abort_job(job_id, reason=f"console: {who}", archive_root=self.root):
            # the child has not taken its job's lock yet (still loading): the same signal, sent directly
            os.kill(s.proc.pid, signal.SIGTERM)
        return True

    def wait(self, timeout_s: float = 600.0) -> None:
        s = self.current
        if s is not None:
            s.proc.wait(timeout=timeout_s)

    def close(self) -> None:
        """On shutdown: abort a running job (it records ABORTED and stops the robot) and reap it."""
        s = self.current
        if s is not None and s.alive():
            os.kill(s.proc.pid, signal.SIGTERM)
            try:
                s.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                s.proc.kill()
                s.proc.wait()


def live_state(folder: Path) -> dict:
    """What the live view shows of a job folder: state, stage, progress (0..1), time left, stations, poses."""
    jf = JobFolder(folder)
    recs, damage = jf.read_journal()  # a damaged line: what precedes it, and the damage said
    state = next((r["to"] for r in reversed(recs) if r["event"] == "state"), "CREATED")
    done = {r["stage"] for r in recs if r["event"] == "stage_done"}
    stations = [r for r in recs if r["event"] == "station_done"]
    n_st = None
    if (folder / "plan.json").exists():
        try:
            n_st = len(json.loads((folder / "plan.json").read_text())["stations"])
        except (ValueError, KeyError):
            n_st = None
    # progress: finished stages, with ACQUIRE counted by station (it is most of a real job's time)
    weights = {s.value: 1.0 for s in STAGES}
    weights["ACQUIRE"] = 4.0
    total = sum(weights.values())
    frac = sum(weights[s] for s in done if s in weights)
    if state == "ACQUIRE" and n_st:
        frac += weights["ACQUIRE"] * min(1.0, len({r["station"] for r in stations}) / n_st)
    progress = 1.0 if state == "DONE" else frac / total
    terminal = next((r for r in reversed(recs) if r["event"] == "terminal"), None)
    # time of this session (since the last 'created' or 'resumed' record) -> time left
    t0 = next((r["t"] for r in reversed(recs) if r["event"] in ("created", "resumed")), recs[0]["t"] if recs else None)
    time_left = None
    if t0 and 0.05 < progress < 1.0 and state not in ("FAULTED", "ABORTED"):
        from datetime import datetime, timezone

        el = (datetime.now(timezone.utc) - datetime.fromisoformat(t0)).total_seconds()
        time_left = el / progress * (1 - progress)
    poses = [r["base_from_flange"] for r in stations if "base_from_flange" in r]
    part_xyz = None
    if (folder / "job.toml").exists():
        try:
            from cell.jobspec import load_job

            part_xyz = load_job(folder / "job.toml")[0].base_from_part()[:3, 3].tolist()
        except Exception:  # a job file the runner will refuse anyway: no part on the picture
            part_xyz = None
    return {"state": state, "stage": state if state in {s.value for s in STAGES} else None, "progress": progress,
            "time_left_s": time_left, "stations_done": len(stations), "stations": n_st,
            "reason": (terminal or {}).get("reason", "") if state in ("FAULTED", "ABORTED") else "",
            "record_damage": None if damage is None else str(damage),
            "flange_xyz_m": [[p[0][3], p[1][3], p[2][3]] for p in poses], "part_xyz_m": part_xyz,
            "latest_image": stations[-1]["image"] if stations else None}


def operator_advice(reason: str) -> str:
    """A fault in words an operator can act on."""
    r = reason.lower()
    if "protective stop" in r or "protective_stop" in r:
        return ("Protective stop: make sure nobody is in the cell and nothing touches the robot, release the stop "
                "on the teach pendant, then press Resume.")
    if "emergency" in r:
        return "Emergency stop: clear the cell, reset the emergency stop button and the pendant, then press Resume."
    if "not connected" in r or "could not connect" in r or "no answer" in r:
        return ("A device does not answer (robot, camera or light): check its power and cable, then press Resume. "
                f"Details: {reason}")
    if "aborted" in r:
        return "The job was aborted. Press Resume to continue from the last finished stage, or start a new part."
    if "ended without a terminal record" in r or "ended unexpectedly" in r:
        return "The controller stopped during the job (power or crash). Press Resume to continue where it stopped."
    if "reach" in r or "collision" in r:
        return ("The part cannot be inspected from where it sits: check it is placed on its fixture as the part "
                f"program expects, then start again. Details: {reason}")
    return f"The job stopped: {reason}. Call an engineer; Resume continues from the last finished stage."
