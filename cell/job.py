"""A job: the state machine that runs the stages, records every transition, and resumes.

The job folder is first built in ``<archive>/.incoming/<id>`` and moved into the
archive when the job reaches ACQUIRE (the first stage that moves hardware): a job
refused for bad input (a wrong file, a part out of reach) leaves nothing in the
archive. From ACQUIRE on, every outcome (done, faulted with its cause, aborted)
is kept, with exactly one terminal record per session in its journal.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from calibration.errors import AbortRequested, CellError, InputError
from cell.loadedjob import LoadedJob, load
from cell.record.archive import Archive
from cell.record.jobfolder import JobFolder, atomic_write_bytes, atomic_write_json, new_job_id, utc_now
from cell.record.runlog import RunLog, next_log_path
from cell.stages import STAGE_FUNCTIONS
from cell.states import STAGES, State, check_transition


@dataclass
class JobResult:
    """How a run ended (bluesky's RunEngineResult): one per session."""

    job_id: str
    status: State
    folder: Path
    reason: str = ""
    interrupted: bool = False
    stage_times_s: dict[str, float] = field(default_factory=dict)

    @property
    def exit_code(self) -> int:
        return {State.DONE: 0, State.ABORTED: 130}.get(self.status, 1)


@dataclass
class Context:
    """What the stages share during one session."""

    job: LoadedJob
    folder: JobFolder
    log: RunLog
    backend: str
    progress: Callable[[str, float], None]
    say: Callable[[str], None]
    devices: object | None = None  # cell.devices.Devices, opened lazily by ACQUIRE
    cache: dict = field(default_factory=dict)


def _copy_inputs(job: LoadedJob, folder: Path) -> dict:
    """Copy the job file and every file it references into the job folder: the job stays reviewable."""
    (folder / "inputs").mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(folder / "job.toml", job.path.read_bytes())
    s = job.spec
    refs = {"job.mesh": s.job.mesh, "job.targets": s.job.targets, "sim.deviations": s.sim.deviations}
    mapping = {}
    for key, rel in refs.items():
        if rel is None:
            continue
        src = Path(rel) if Path(rel).is_absolute() else job.folder / rel
        dst = folder / "inputs" / f"{key.replace('.', '_')}{src.suffix}"
        atomic_write_bytes(dst, src.read_bytes())
        mapping[key] = str(dst.relative_to(folder))
    if s.cell.cell_file is not None:  # the live cell file (its calibration changes): referenced, not copied
        cf = Path(s.cell.cell_file)
        mapping["cell.cell_file"] = str(cf if cf.is_absolute() else (job.folder / cf).resolve())
    atomic_write_json(folder / "inputs.json", mapping)
    return mapping


def load_from_folder(folder: Path) -> LoadedJob:
    """Load a job from its archived copy (job.toml + inputs/)."""
    folder = Path(folder).resolve()
    mapping = json.loads((folder / "inputs.json").read_text())
    return load(folder / "job.toml", overrides={k: str(folder / v) for k, v in mapping.items()})  # abs paths stay


#: the runners of this process, by job id (the web console aborts through :func:`abort_job`)
_ACTIVE: dict[str, "JobRunner"] = {}
_ACTIVE_LOCK = threading.Lock()


def abort_job(job_id: str, reason: str = "console") -> bool:
    """Abort the job ``job_id`` running in this process: the one abort path of SIGTERM, Ctrl-C and the console.

    The robot gets its stop at once (whatever the stage is doing), the job then ends ABORTED with
    the time the arm came to rest in its journal. Safe from any thread. Returns False when no job
    of that id runs in this process.
    """
    with _ACTIVE_LOCK:
        runner = _ACTIVE.get(job_id)
    if runner is None:
        return False
    runner.abort(reason)
    return True


class JobRunner:
    """Runs the stages of one job from a given stage to DONE, FAULTED or ABORTED.

    :meth:`abort` (from a signal handler, another thread, or :func:`abort_job`) stops the robot at
    once and makes the session end ABORTED; the stage in progress is interrupted (by the signal on
    the main thread, otherwise at its next progress report or robot call, which the stop ends).
    """

    def __init__(self, archive: Archive, folder: JobFolder, job: LoadedJob, backend: str, out, *, staged: bool):
        self.archive = archive
        self.folder = folder
        self.job = job
        self.backend = backend
        self.out = out
        self.staged = staged  # still in .incoming
        self.state = State.CREATED
        self.times: dict[str, float] = {}
        self._ctx: Context | None = None
        self._abort: dict | None = None  # {"reason", "t", "monotonic"} once an abort was asked for
        self._interruptible = False  # a signal raises AbortRequested only while the stages run
        self._thread: threading.Thread | None = None

    # --- abort ---------------------------------------------------------------------
    def abort(self, reason: str = "operator") -> None:
        """Ask the session to abort: the robot's stop is sent now; never blocks, never raises."""
        if self._abort is None:
            self._abort = {"reason": reason, "t": utc_now(), "monotonic": time.monotonic()}
        ctx = self._ctx
        robot = getattr(ctx.devices, "robot", None) if ctx is not None else None
        if robot is None:
            return
        try:
            signal_stop = getattr(robot, "signal_stop", None)
            if signal_stop is not None:
                signal_stop()  # a real arm: its client process stops it within a few ms
            elif threading.current_thread() is not threading.main_thread():
                robot.stop()  # the simulated arm stops a timed move through an event
        except Exception:  # an abort must never fail; the runner's own stop follows
            pass

    def _on_signal(self, signum, frame) -> None:
        name = signal.Signals(signum).name
        self.abort(name)
        if self._interruptible:  # else the session is ending already: it records the abort and closes the folder
            raise AbortRequested(name)

    def _progress(self, stage: str, fraction: float) -> None:
        if self._abort is not None and self._interruptible and threading.current_thread() is self._thread:
            raise AbortRequested(self._abort["reason"])
        self.out.progress(stage, fraction)

    # --- transitions --------------------------------------------------------------
    def _go(self, ctx: Context | None, to: State, cause: str = "") -> None:
        check_transition(self.state, to)
        rec = {"from": self.state.value, "to": to.value}
        if cause:
            rec["cause"] = cause
        self.folder.append("state", **rec)
        if ctx is not None:
            ctx.log.state(self.state.value, to.value, cause)
        self.state = to
        if not self.staged:
            self.archive.record(self.folder.job_id, status=to.value)

    def _promote(self) -> None:
        """Move the job folder from .incoming into the archive."""
        if not self.staged:
            return
        dst = self.archive.root / self.folder.job_id
        self.folder.path.rename(dst)
        self.folder = JobFolder(dst)
        self.staged = False
        recs = list(self.folder.records())
        self.archive.record(self.folder.job_id, name=self.job.spec.job.name, part=self.job.part.name,
                            status=self.state.value, started=recs[0]["t"] if recs else None)

    def run(self, start: State, resumed_from: State | None = None) -> JobResult:
        log = RunLog(next_log_path(self.folder.path))
        ctx = Context(job=self.job, folder=self.folder, log=log, backend=self.backend,
                      progress=self._progress, say=self.out.say)
        self._ctx = ctx
        self._thread = threading.current_thread()
        self.state = resumed_from or State.CREATED
        on_main = threading.current_thread() is threading.main_thread()
        old_handlers = {}
        if on_main:  # signals reach only the main thread; a console runs jobs elsewhere and calls abort()
            for sig in (signal.SIGTERM, signal.SIGINT):
                old_handlers[sig] = signal.getsignal(sig)
                signal.signal(sig, self._on_signal)
        with _ACTIVE_LOCK:
            _ACTIVE[self.folder.job_id] = self
        try:
            return self._run(ctx, log, start)
        finally:
            with _ACTIVE_LOCK:
                _ACTIVE.pop(self.folder.job_id, None)
            for sig, handler in old_handlers.items():
                signal.signal(sig, handler)

    def _run(self, ctx: Context, log: RunLog, start: State) -> JobResult:

        status, reason, interrupted = State.DONE, "", False
        self._interruptible = True
        try:
            for stage in STAGES[STAGES.index(start):]:
                if self._abort is not None:
                    raise AbortRequested(self._abort["reason"])
                if stage == State.ACQUIRE:
                    self._promote()
                    ctx.folder = self.folder
                self._go(ctx, stage)
                self.out.say(f"[{stage.value}]")
                t0 = time.perf_counter()
                STAGE_FUNCTIONS[stage](ctx)
                dt = time.perf_counter() - t0
                self.times[stage.value] = dt
                self.folder.append("stage_done", stage=stage.value, duration_s=round(dt, 4))
                log.log("info", f"{stage.value} done in {dt:.2f} s")
            self._interruptible = False
            self._go(ctx, State.DONE)
        except (AbortRequested, KeyboardInterrupt) as exc:
            self._interruptible = False
            self.abort(type(exc).__name__)
            status, reason, interrupted = State.ABORTED, f"aborted by the operator ({self._abort['reason']})", True
            self._stop_robot(ctx)
            self._go(ctx, State.ABORTED, reason)
        except Exception as exc:
            self._interruptible = False
            if self._abort is None:
                status, reason = self._fault(ctx, log, exc)
            else:  # the stop sent by the abort ended a move with an error: the operator's abort, not a fault
                status, reason, interrupted = State.ABORTED, f"aborted by the operator ({self._abort['reason']})", True
                self._stop_robot(ctx)
                self._go(ctx, State.ABORTED, reason)
        finally:
            self._interruptible = False  # from here a signal no longer interrupts: the folder is closed first
            if ctx.devices is not None:
                ctx.devices.close()
            log.close()
        if self.staged:  # faulted before ACQUIRE for a reason that is not bad input: keep it
            self._promote()
        self.folder.append("terminal", status=status.value, reason=reason)
        self.folder.write_manifest()
        self.archive.reindex(only=self.folder.path)
        return JobResult(self.folder.job_id, status, self.folder.path, reason, interrupted, dict(self.times))

    def _fault(self, ctx: Context, log: RunLog, exc: Exception) -> tuple[State, str]:
        """A stage failed: stop the robot, record FAULTED with the cause (bad input before ACQUIRE: re-raise)."""
        if isinstance(exc, CellError):
            status, reason = State.FAULTED, f"{self.state.value}: {exc}"
            self._stop_robot(ctx)
            if (isinstance(exc, InputError) or exc.exit_code == 2) and self.staged:  # bad input (e.g. out of reach)
                log.close()
                shutil.rmtree(self.folder.path, ignore_errors=True)
                raise exc
            self._go(ctx, State.FAULTED, reason)
            return status, reason
        # a bug: still one terminal record with the cause
        status, reason = State.FAULTED, f"{self.state.value}: internal error {type(exc).__name__}: {exc}"
        self.folder.append("traceback", text=traceback.format_exc())
        self._stop_robot(ctx)
        self._go(ctx, State.FAULTED, reason)
        return status, reason

    def _stop_robot(self, ctx: Context) -> None:
        """Stop the robot and journal when it came to rest (and how long after the abort, if one was asked)."""
        if ctx.devices is None:
            return
        robot = ctx.devices.robot
        try:
            at_rest = robot.stop()
            if at_rest is None:
                at_rest = robot.state()
        except Exception as exc:  # the robot may be the thing that failed
            self.folder.append("note", text=f"robot stop after {'abort' if self._abort else 'fault'} failed: {exc}")
            return
        rec = {"at_rest": utc_now(), "joints": at_rest.joints_rad, "robot_timestamp_s": at_rest.timestamp_s}
        rest = getattr(robot, "last_rest", None)
        if rest:  # the driver saw the arm come to rest: controller clock, and seconds after the stop was sent
            rec |= {"rest_controller_timestamp_s": rest.get("controller_timestamp_s"),
                    "rest_after_stop_s": rest.get("after_s")}
        if self._abort is not None:
            rec |= {"abort_requested": self._abort["t"], "abort_reason": self._abort["reason"],
                    "stop_returned_after_abort_s": round(time.monotonic() - self._abort["monotonic"], 4)}
        self.folder.append("robot_stopped", **rec)


def start_job(job_path: Path, archive_root: Path, backend: str | None, out) -> JobResult:
    """``cell run``: LOAD (before anything is written), then the whole job."""
    job = load(job_path)  # bad input fails here, before any folder exists
    archive = Archive(Path(archive_root).resolve())
    job_id = new_job_id(job.spec.job.name)
    incoming = archive.root / ".incoming" / job_id
    k = 1
    while incoming.exists() or (archive.root / job_id).exists():
        k += 1
        job_id = f"{new_job_id(job.spec.job.name)}-{k}"
        incoming = archive.root / ".incoming" / job_id
    incoming.mkdir(parents=True)
    folder = JobFolder(incoming)
    lock = folder.lock()
    try:
        return _start_staged(job_path, job, archive, folder, job_id, backend, out)
    finally:
        os.close(lock)


def _start_staged(job_path: Path, job: LoadedJob, archive: Archive, folder: JobFolder, job_id: str,
                  backend: str | None, out) -> JobResult:
    incoming = folder.path
    folder.append("created", name=job.spec.job.name, job_file=str(job_path), backend=backend or job.spec.cell.backend)
    _copy_inputs(job, incoming)
    # the staged copy is what runs; messages name the operator's job file
    job = dataclasses.replace(load_from_folder(incoming), path=Path(job_path))
    runner = JobRunner(archive, folder, job, backend or job.spec.cell.backend, out, staged=True)
    out.say(f"job {job_id}  ({job.part.name}, {len(job.part.targets)} targets, backend {runner.backend})")
    return runner.run(State.LOAD)


def resume_job(job_id: str, archive_root: Path, out) -> JobResult:
    """``cell resume``: continue from the first stage that did not finish."""
    archive = Archive(Path(archive_root).resolve())
    folder = archive.folder(job_id)
    lock = folder.lock()  # refuses a job still running in another process
    try:
        return _resume_locked(job_id, archive, folder, out)
    finally:
        os.close(lock)


def _resume_locked(job_id: str, archive: Archive, folder: JobFolder, out) -> JobResult:
    recs = list(folder.records())
    done = {r["stage"] for r in recs if r["event"] == "stage_done"}
    last_state = next((State(r["to"]) for r in reversed(recs) if r["event"] == "state"), State.CREATED)
    if last_state == State.DONE:
        raise InputError(f"{job_id}: the job is already DONE; nothing to resume")
    start = next((s for s in STAGES if s.value not in done), None)
    if start is None:
        raise InputError(f"{job_id}: every stage finished; nothing to resume")
    # a session killed without a terminal record: record how it ended before going on
    terminal_seen = bool(recs) and recs[-1]["event"] == "terminal"
    if not terminal_seen:
        # in the order a session that faults writes them: the transition, then its one terminal record
        folder.append("state", **{"from": last_state.value, "to": State.FAULTED.value, "cause": "process ended unexpectedly"})
        folder.append("terminal", status="FAULTED", reason=f"{last_state.value}: the process ended without a terminal record (killed or crashed)")
        last_state = State.FAULTED
    job = load_from_folder(folder.path)
    backend = next((r.get("backend") for r in recs if r["event"] == "created"), job.spec.cell.backend)
    folder.append("resumed", stage=start.value)
    partial = folder.remove_partial_files()
    if partial:
        folder.append("note", text=f"removed {len(partial)} partial file(s) of an interrupted write: {', '.join(partial)}")
    out.say(f"job {job_id}: resuming at {start.value}")
    runner = JobRunner(archive, folder, job, backend, out, staged=False)
    return runner.run(start, resumed_from=last_state)
