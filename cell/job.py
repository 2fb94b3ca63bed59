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
import sqlite3
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from calibration.errors import AbortRequested, CalibrationError, CellError, InputError, RecordError
from cell.jobspec import check_backend
from cell.loadedjob import LoadedJob, load
from cell.record import integrity
from cell.record.archive import Archive, check_archive_root, check_job_id
from cell.record.jobfolder import (JobFolder, JournalDamaged, atomic_write_bytes, atomic_write_json, new_job_id,
                                   utc_now)
from cell.record.runinfo import (RUN_INFO, describe, make_run_info, read_run_info, run_info_from_journal,
                                 run_info_problem, write_run_info)
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
    if s.cell.cell_file is not None:
        # the cell file as the job took it: a calibration run during the job (or before a resume) does not change
        # the hand-eye and lens it measures with; the report's calibration status is judged against it (decision 0056)
        cf = Path(s.cell.cell_file)
        src = cf if cf.is_absolute() else (job.folder / cf).resolve()
        atomic_write_bytes(folder / "inputs" / "cell_file.toml", src.read_bytes())
        mapping["cell.cell_file"] = "inputs/cell_file.toml"
    atomic_write_json(folder / "inputs.json", mapping)
    return mapping


def load_from_folder(folder: Path) -> LoadedJob:
    """Load a job from its archived copy (job.toml + inputs/)."""
    folder = Path(folder).resolve()
    mapping = json.loads((folder / "inputs.json").read_text())
    return load(folder / "job.toml", overrides={k: str(folder / v) for k, v in mapping.items()})  # abs paths stay


def _os_reason(exc: BaseException) -> str:
    """One line for an OS (or SQLite) error: what and where."""
    if isinstance(exc, OSError):
        where = f": {exc.filename}" if exc.filename else ""
        return f"{exc.strerror or type(exc).__name__}{where}"
    return f"{type(exc).__name__}: {exc}"


#: the runners of this process, by job id (the web console aborts through :func:`abort_job`)
_ACTIVE: dict[str, "JobRunner"] = {}
_ACTIVE_LOCK = threading.Lock()


def abort_job(job_id: str, reason: str = "console", archive_root: Path | None = None) -> bool:
    """Abort the job ``job_id``: the one abort path of SIGTERM, Ctrl-C and the console.

    A job running in this process (:class:`JobRunner`) gets :meth:`JobRunner.abort`: the robot's
    stop is sent at once, whatever the stage is doing, and the job ends ABORTED with the time the
    arm came to rest in its journal. Safe from any thread. With ``archive_root``, a job running in
    another process (the pid in its ``.lock``) is sent SIGTERM, which takes the same path there.
    Returns False when no such job is running.
    """
    check_job_id(job_id)
    with _ACTIVE_LOCK:
        runner = _ACTIVE.get(job_id)
    if runner is not None:
        runner.abort(reason)
        return True
    if archive_root is None:
        return False
    pid = Archive(Path(archive_root)).folder(job_id).running_pid()
    if pid is None or pid == os.getpid():
        return False
    try:
        os.kill(pid, signal.SIGTERM)
    except ProcessLookupError:
        return False
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
        info = read_run_info(self.folder.path)
        self.archive.record(self.folder.job_id, name=self.job.spec.job.name, part=self.job.part.name,
                            status=self.state.value, started=recs[0]["t"] if recs else None,
                            part_number=info["part"]["number"], serial=info["part"]["serial"],
                            operator=info["operator"], cell_id=info["cell_id"])

    def run(self, start: State, resumed_from: State | None = None) -> JobResult:
        log = RunLog(next_log_path(self.folder.path))
        ctx = Context(job=self.job, folder=self.folder, log=log, backend=self.backend,
                      progress=self._progress, say=self.out.say)
        self._ctx = ctx
        self._thread = threading.current_thread()
        self.state = resumed_from or State.CREATED
        log.job(self.folder.job_id, read_run_info(self.folder.path))
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
                with self.folder.recording(stage.value):  # every result it writes is journalled with its sha256
                    STAGE_FUNCTIONS[stage](ctx)
                dt = time.perf_counter() - t0
                self.times[stage.value] = dt
                # what the stage wrote, with its sha256: a resume checks the folder against it before it acts
                files = integrity.changed_files(self.folder, list(self.folder.records()))
                self.folder.append("stage_done", stage=stage.value, duration_s=round(dt, 4), files=files)
                log.log("info", f"{stage.value} done in {dt:.2f} s")
            self._interruptible = False
            self._go(ctx, State.DONE)
        except (AbortRequested, KeyboardInterrupt, Exception) as exc:
            self._interruptible = False
            try:
                status, reason, interrupted = self._end_early(ctx, log, exc)
            except (OSError, sqlite3.Error) as exc2:  # the end itself could not be journalled (disk full)
                status, interrupted = (State.ABORTED, True) if self._abort is not None else (State.FAULTED, False)
                reason = (f"{self.state.value}: {exc if str(exc) else type(exc).__name__}; the fault could not be "
                          f"recorded ({_os_reason(exc2)})")
        finally:
            self._interruptible = False  # from here a signal no longer interrupts: the folder is closed first
            if ctx.devices is not None:
                ctx.devices.close()
            try:
                log.close()
            except OSError:
                pass
        unrecorded = self._close(status, reason)
        if unrecorded:
            reason = f"{reason}; {unrecorded}" if reason else unrecorded
            status = State.FAULTED if status == State.DONE else status
        return JobResult(self.folder.job_id, status, self.folder.path, reason, interrupted, dict(self.times))

    def _close(self, status: State, reason: str) -> str:
        """The session's one terminal record, then the manifest (over the files that verify) and the index.

        A disk that is full (or gone) here must not turn the outcome into a traceback: what could not be
        written is returned as a sentence; the next ``cell resume`` sees a session without its
        terminal record and records it as killed.
        """
        try:
            if self.staged:  # faulted before ACQUIRE for a reason that is not bad input: keep it
                self._promote()
            self.folder.append("terminal", status=status.value, reason=reason)
            recs = list(self.folder.records())
            self.folder.write_manifest(expected=integrity.expected_hashes(recs))
        except (OSError, sqlite3.Error, JournalDamaged) as exc:
            return (f"the end of this session could not be recorded ({_os_reason(exc)}); fix that (free space), then "
                    f"'cell resume {self.folder.job_id}' closes the job")
        try:
            for line in self.archive.job_closed(self.folder.path):  # index (or the outbox) and push
                self.out.say(f"archive: {line}")
        except (OSError, sqlite3.Error, CellError) as exc:  # the folder is the record; 'cell archive sync' indexes it
            self.out.say(f"archive: {self.folder.job_id} not indexed ({exc}); 'cell archive sync' indexes it")
        return ""

    def _end_early(self, ctx: Context, log: RunLog, exc: BaseException) -> tuple[State, str, bool]:
        """A stage was interrupted: the operator's abort (also when the stop it sent ended a move with an
        error), or a fault. Stops the robot and records the transition; returns (status, reason, interrupted)."""
        if isinstance(exc, (AbortRequested, KeyboardInterrupt)):
            self.abort(str(exc) or type(exc).__name__)
        if self._abort is not None:
            reason = f"aborted by the operator ({self._abort['reason']})"
            self._stop_robot(ctx)
            self._go(ctx, State.ABORTED, reason)
            return State.ABORTED, reason, True
        status, reason = self._fault(ctx, log, exc)
        return status, reason, False

    def _fault(self, ctx: Context, log: RunLog, exc: Exception) -> tuple[State, str]:
        """A stage failed: stop the robot, record FAULTED with the cause (bad input before ACQUIRE: re-raise)."""
        if isinstance(exc, (OSError, sqlite3.Error)):  # disk full, read-only, I/O error: a clear fault, resumable
            status = State.FAULTED
            reason = (f"{self.state.value}: cannot write the job's record ({_os_reason(exc)}); fix that (free space), "
                      f"then 'cell resume {self.folder.job_id}'")
            self._stop_robot(ctx)
            try:
                self._go(ctx, State.FAULTED, reason)
            except (OSError, sqlite3.Error):
                self.state = State.FAULTED
            return status, reason
        if isinstance(exc, MemoryError):
            exc = CellError(f"out of memory ({exc or 'MemoryError'}): the part or the network is too large for this machine")
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
        self._stop_robot(ctx)  # first: a journal write may fail too (disk full)
        self.folder.append("traceback", text=traceback.format_exc())
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


def open_archive(job: LoadedJob, archive_root: Path, archive_url: str | None = None) -> Archive:
    """The job's archive: folders in ``archive_root``, the index at ``--archive-url``, else
    ``CELL_ARCHIVE_URL``, else the cell file's ``[archive] url``, else SQLite in the folder."""
    from cell.record.archive import resolve_url

    cf_url = cf_push = None
    if job.spec.cell.cell_file is not None:
        from cell.cellcal.cellfile import load_cell_file
        from cell.jobspec import resolve

        cf, _ = load_cell_file(resolve(job.folder, job.spec.cell.cell_file))
        cf_url, cf_push = cf.archive.url, cf.archive.push
    root = Path(archive_root).resolve()
    return Archive(root, resolve_url(archive_url, root, cf_url), push=os.environ.get("CELL_ARCHIVE_PUSH") or cf_push)


def check_cell_calibration(job: LoadedJob, archive_root: Path, out) -> dict | None:
    """The calibration status of the cell a job names (:func:`cell.cellcal.status.calibration_status`, the records in
    ``archive_root``); None when it names none.

    Its last reverification failed: the job is refused (``CalibrationError``, before anything is written): the cell
    measures lengths beyond its maximum permissible error, and every part it measured would carry that. It measures
    again once the hand-eye is calibrated anew (the failed reverification was made with another hand-eye) and
    reverified (docs/bring-up.md). Expired, or never verified with this hand-eye: the job runs, and says so at the
    start and in its report.
    """
    if job.cell is None:
        return None
    from datetime import datetime, timezone

    from cell.cellcal.status import calibration_status

    st = calibration_status(archive_root, job.cell["cell_file"], datetime.now(timezone.utc))
    if st["status"] == "failed":
        raise CalibrationError(f"{job.path}: cell {job.cell['cell']}: {st['detail']}: it measures beyond its maximum "
                               "permissible error; calibrate the hand-eye again (cell calibrate hand-eye CELL.toml) and "
                               "reverify (cell calibrate reverify CELL.toml) before measuring parts")
    if st["status"] != "verified":
        out.say(f"WARNING cell {job.cell['cell']} {st['status']}: {st['detail']}")
    return st


def start_job(job_path: Path, archive_root: Path, backend: str | None, out, *, serial: str | None = None,
              operator: str | None = None, cell_id: str | None = None, archive_url: str | None = None) -> JobResult:
    """``cell run``: LOAD (before anything is written), then the whole job.

    ``serial`` (the part's serial number), ``operator`` and ``cell_id`` (default: ``$CELL_ID``) go
    into the job's run.json, its journal, run log, report and archive row; a cell id also goes into
    the job's id (``<time>-<cell>-<name>``): the cells of a site share one index. ``archive_url``: the
    index (:func:`open_archive`).
    """
    job = load(job_path)  # bad input fails here, before any folder exists
    if backend is not None:  # the command line's robot: what only a simulated one can do is refused for a real one
        check_backend(job.spec, backend, job_path)
    info = make_run_info(job.spec, serial, operator, cell_id)  # a bad serial fails here too
    root = check_archive_root(Path(archive_root), write=True).resolve()
    check_cell_calibration(job, root, out)  # a cell whose reverification failed measures no part
    archive = open_archive(job, root, archive_url)
    stem = f"{info['cell_id']}-{job.spec.job.name}" if info["cell_id"] else job.spec.job.name
    job_id, incoming = _claim_job_folder(archive.root, stem)
    folder = JobFolder(incoming)
    lock = folder.lock()
    try:
        return _start_staged(job_path, job, archive, folder, job_id, backend, out, info)
    finally:
        os.close(lock)
        archive.close()  # the index's connections end with the job (a console runs many in one process)


def _claim_job_folder(root: Path, stem: str) -> tuple[str, Path]:
    """A new job's id and its staging folder, created here. Two ``cell run`` of the same job in the same second
    pick the same id: the folder's creation (``mkdir``, atomic) decides, and the one that loses takes the next
    id (``-2``, ``-3``, ...) instead of failing (decision 0060)."""
    (root / ".incoming").mkdir(parents=True, exist_ok=True)
    job_id = new_job_id(stem)
    k = 1
    while True:
        incoming = root / ".incoming" / job_id
        if not (root / job_id).exists():
            try:
                incoming.mkdir()
            except FileExistsError:  # another process took this id between the check and here
                pass
            else:
                if not (root / job_id).exists():  # (its job cannot have moved into the archive meanwhile)
                    return job_id, incoming
                incoming.rmdir()
        k += 1
        job_id = f"{new_job_id(stem)}-{k}"


def _start_staged(job_path: Path, job: LoadedJob, archive: Archive, folder: JobFolder, job_id: str,
                  backend: str | None, out, info: dict) -> JobResult:
    incoming = folder.path
    write_run_info(incoming, info)
    folder.append("created", name=job.spec.job.name, job_file=str(job_path), backend=backend or job.spec.cell.backend,
                  **info)
    _copy_inputs(job, incoming)
    live_cell_file = job.cell["cell_file"] if job.cell is not None else None
    # the staged copy is what runs; messages name the operator's job file
    job = dataclasses.replace(load_from_folder(incoming), path=Path(job_path))
    runner = JobRunner(archive, folder, job, backend or job.spec.cell.backend, out, staged=True)
    out.say(f"job {job_id}  ({job.part.name}, {len(job.part.targets)} targets, backend {runner.backend})")
    if job.cell is not None:  # which hand-eye and lens it measures with, and from which cell file (decision 0056)
        from cell.cellcal.jobcell import taken_line

        folder.append("cell_file_taken", **(job.cell | {"cell_file": "inputs/cell_file.toml", "source": live_cell_file}))
        out.say("  " + taken_line(job.cell))
    return runner.run(State.LOAD)


def resume_job(job_id: str, archive_root: Path, out, *, operator: str | None = None,
               archive_url: str | None = None) -> JobResult:
    """``cell resume``: verify the job's record, then continue from the first stage that did not finish.

    Before anything moves: the journal must read whole (a damaged line is an error naming it, never a
    rewind); a finished job is never driven again (one that died after DONE is only closed); every
    stored file is checked against the sha256 its journal recorded, and a station whose image fails
    (changed, missing, undecodable) is acquired again, alone; damage that cannot be retaken stops
    the resume with a clear message, having changed nothing. ``operator``: who resumes it (journalled).
    """
    root = check_archive_root(Path(archive_root), write=False)
    archive = Archive(root.resolve())
    folder = archive.folder(job_id)
    try:
        lock = folder.lock()  # refuses a job still running in another process
    except OSError as exc:
        raise InputError(f"{folder.path}: cannot write the job folder ({_os_reason(exc)})") from None
    try:
        archive = _archive_of(folder, archive.root, archive_url)
        return _resume_locked(job_id, archive, folder, out, operator)
    finally:
        os.close(lock)
        archive.close()


def _archive_of(folder: JobFolder, root: Path, archive_url: str | None) -> Archive:
    """The archive a resumed job writes to: as :func:`open_archive` with the job's own copy of its file;
    when that copy does not load (the resume then says why), the index the command line and environment name."""
    from cell.record.archive import resolve_url

    try:
        return open_archive(load_from_folder(folder.path), root, archive_url)
    except Exception:  # noqa: BLE001  (the resume's own checks report a damaged job; this only picks the index)
        return Archive(root, resolve_url(archive_url, root), push=os.environ.get("CELL_ARCHIVE_PUSH"))


#: files a job stores before its robot moves, which its images depend on
_BEFORE_MOTION = frozenset({State.LOAD.value, State.PLAN.value, State.VALIDATE.value})


def _resume_locked(job_id: str, archive: Archive, folder: JobFolder, out, operator: str | None = None) -> JobResult:
    recs, damage = folder.read_journal()
    if damage is not None:
        raise RecordError(f"{damage}; the job is not resumed and nothing was changed: a damaged journal cannot say "
                          f"what the job did (its files: 'cell archive verify {job_id}')")
    if not recs:
        raise RecordError(f"{folder.path / 'journal.jsonl'}: empty; this folder holds no job to resume")
    if (cut := integrity.journal_against_manifest(folder)) is not None:
        raise RecordError(f"{cut}; the job is not resumed and nothing was changed: restore the journal from a copy "
                          f"(its files: 'cell archive verify {job_id}')")
    try:
        states = [State(r["to"]) for r in recs if r["event"] == "state"]
    except (KeyError, ValueError) as exc:
        raise RecordError(f"{folder.path / 'journal.jsonl'}: a state record names no known state ({exc})") from None
    last_state = states[-1] if states else State.CREATED
    terminal_seen = recs[-1]["event"] == "terminal"
    if State.DONE in states:
        return _close_finished(job_id, archive, folder, recs, terminal_seen, out)

    # verify before acting: nothing is written until the record is known to be good enough
    found = integrity.check_stored(folder, recs)
    # run.json (part, serial, operator) is a copy of the journal's created record: the journal restores it
    run_info = run_info_from_journal(recs)
    run_info_why = None if run_info is None else \
        run_info_problem(folder.path, run_info, found.files.get(RUN_INFO, (None,))[0])
    if run_info_why is not None:
        found.files.pop(RUN_INFO, None)
    moved = bool(integrity.acquired(recs)) or any(r["event"] == "station_start" for r in recs)
    for rel, (why, stage) in sorted(found.files.items()):
        if rel in ("job.toml", "inputs.json") or rel.startswith("inputs/") or \
                ((stage in _BEFORE_MOTION or rel == "plan.json") and moved):
            raise RecordError(f"{folder.path / rel}: {why}; it was stored by {stage or 'the job'} before the robot "
                              f"moved and what followed depends on it, so the job is not resumed (nothing was "
                              f"changed); restore it from a copy, or start a new job")

    done = integrity.finished_stages(recs)
    start = next((s for s in STAGES if s.value not in done), None)
    died_after_last_stage = start is None and last_state == State.REPORT and not found
    to_move = bool(found.stations) or (start is not None and STAGES.index(start) <= STAGES.index(State.ACQUIRE))
    cell_lines = _cell_on_resume(folder, recs, archive.root, to_move, job_id)  # refuses before anything is written
    torn = folder.drop_torn_tail()  # a record the killed session was writing: it never counted
    if not terminal_seen and not died_after_last_stage:
        # a session killed without a terminal record: record how it ended before going on, in the order a
        # session that faults writes them: the transition, then its one terminal record
        folder.append("state", **{"from": last_state.value, "to": State.FAULTED.value,
                                  "cause": "process ended unexpectedly"})
        folder.append("terminal", status="FAULTED",
                      reason=f"{last_state.value}: the process ended without a terminal record (killed or crashed)")
        last_state = State.FAULTED
    folder.append("resumed", stage=start.value if start else "DONE", **({"operator": operator} if operator else {}))
    for line in cell_lines:
        folder.append("note", text=line)
        out.say(f"  WARNING {line}")
    partial = folder.remove_partial_files()
    if partial:
        folder.append("note", text=f"removed {len(partial)} partial file(s) of an interrupted write: {', '.join(partial)}")
    if torn:
        folder.append("note", text=f"cut the journal's last line, {torn} bytes of a record the killed session was "
                                   "writing")
    if run_info_why is not None:
        _rebuild_run_info(folder, run_info, run_info_why, out)
    reopen: list[State] = []
    for sid, why in sorted(found.stations.items()):
        image = integrity.acquired(recs)[sid]["image"]
        moved_to = folder.quarantine(image)
        folder.append("station_invalid", station=sid, image=image, why=why, moved_to=moved_to)
        out.say(f"  station {sid}: {why}; it is acquired again")
        reopen.append(State.ACQUIRE)
    for rel, (why, stage) in sorted(found.files.items()):
        moved_to = folder.quarantine(rel)
        folder.append("quarantined", file=rel, why=why, moved_to=moved_to, stage=stage)
        out.say(f"  {rel}: {why}; {stage} makes it again")
        reopen.append(State(stage) if stage in {s.value for s in STAGES} else State.ACQUIRE)
    if reopen:
        first = min(reopen, key=STAGES.index)
        if start is None or STAGES.index(first) < STAGES.index(start):
            folder.append("reopened", stage=first.value, why="stored results failed verification")
            start = first
    if start is None and last_state != State.REPORT:
        folder.append("reopened", stage=State.REPORT.value, why="every stage finished but the job never reached DONE")
        start = State.REPORT
    job = load_from_folder(folder.path)
    backend = next((r.get("backend") for r in recs if r["event"] == "created"), job.spec.cell.backend)
    staged = folder.path.parent.name == ".incoming"
    runner = JobRunner(archive, folder, job, backend, out, staged=staged)
    if start is None:  # the last stage finished and the session died before DONE: only close it
        out.say(f"job {job_id}: every stage finished; closing it")
        runner.state = last_state
        runner._go(None, State.DONE)
        unrecorded = runner._close(State.DONE, "")
        status = State.FAULTED if unrecorded else State.DONE
        return JobResult(job_id, status, runner.folder.path, unrecorded)
    out.say(f"job {job_id}: resuming at {start.value}")
    return runner.run(start, resumed_from=last_state)


def _rebuild_run_info(folder: JobFolder, info: dict, why: str, out) -> None:
    """Write run.json again from the journal's created record (decision 0060); a copy that disagreed is kept in
    ``damaged/``. Journalled (``quarantined``, ``stored``, a note) and said in one line."""
    moved_to = folder.quarantine(RUN_INFO)
    if moved_to is not None:
        folder.append("quarantined", file=RUN_INFO, why=why, moved_to=moved_to, stage=State.LOAD.value)
    with folder.recording(State.LOAD.value):  # journalled with its sha256, as LOAD's files are
        write_run_info(folder.path, info)
    line = (f"run.json: {why}; rebuilt from the journal's created record ({describe(info)})"
            + (f"; the file found is kept as {moved_to}" if moved_to else ""))
    folder.append("note", text=line)
    out.say(f"  {line}")


def _cell_on_resume(folder: JobFolder, recs: list[dict], archive_root: Path, to_move: bool, job_id: str) -> list[str]:
    """The cell's calibration judged again when a job that names its cell file resumes (decision 0057).

    The job keeps the cell file it took (``inputs/cell_file.toml``: its hand-eye and lens), so what counts is that
    calibration's status now: a reverification made with it that failed since the job started refuses a resume
    that would still take images (``CalibrationError``, before anything is written); one that only computes is let
    through with a warning (its report states the status). A live cell file that changed since the job took it is
    said: the job goes on with the calibration it started with. Returns the warnings."""
    taken = next((r for r in recs if r["event"] == "cell_file_taken"), None)
    snapshot = folder.path / "inputs" / "cell_file.toml"
    if taken is None or not snapshot.is_file():
        return []
    import hashlib
    from datetime import datetime, timezone

    from cell.cellcal.status import calibration_status

    lines = []
    st = calibration_status(archive_root, snapshot, datetime.now(timezone.utc))
    if st["status"] == "failed":
        if to_move:
            raise CalibrationError(f"{job_id}: cell {taken.get('cell')}: {st['detail']} (with the hand-eye this job "
                                   "measures with): the job is not resumed and nothing was changed; its images so far "
                                   "are kept. Calibrate the hand-eye again and reverify, then start the part again")
        lines.append(f"cell {taken.get('cell')}: {st['detail']}; the job only computes from images already taken, "
                     "and its report states the status")
    source = Path(str(taken.get("source") or ""))
    if taken.get("source") and source.is_file() and hashlib.sha256(source.read_bytes()).hexdigest() != taken["sha256"]:
        lines.append(f"the cell file {source} changed since this job took it (sha256 {taken['sha256'][:12]}...); "
                     "the job goes on with the hand-eye and lens it started with (inputs/cell_file.toml)")
    return lines


def _close_finished(job_id: str, archive: Archive, folder: JobFolder, recs: list[dict], terminal_seen: bool,
                    out) -> JobResult:
    """A job that reached DONE is never driven again; one that died before closing its folder is closed."""
    from cell.record.jobfolder import MANIFEST

    if terminal_seen and folder.file(MANIFEST).is_file():
        raise InputError(f"{job_id}: the job is already DONE; nothing to resume (check its files with "
                         f"'cell archive verify {job_id}')")
    closed = close_folder(archive, folder, recs, "DONE")
    out.say(f"job {job_id}: DONE already; {closed}")
    return JobResult(job_id, State.DONE, folder.path, closed)


def close_folder(archive: Archive, folder: JobFolder, recs: list[dict], status: str) -> str:
    """Give a job that ended without closing its folder its terminal record (if missing) and a manifest over
    the files that verify against its journal; returns what was done. Never moves anything."""
    did = []
    folder.drop_torn_tail()
    if not recs or recs[-1]["event"] != "terminal":
        folder.append("terminal", status=status, reason="closed afterwards: the session ended before it "
                      "closed the job folder")
        did.append("terminal record written")
    doc = folder.write_manifest(expected=integrity.expected_hashes(list(folder.records())))
    did.append(f"manifest written over {len(doc['files'])} file(s)" +
               (f", {len(doc['unverified'])} not vouched for: {', '.join(sorted(doc['unverified']))}"
                if doc.get("unverified") else ""))
    try:
        archive.reindex(only=folder.path)
    except (OSError, sqlite3.Error):
        pass
    return "; ".join(did)


def repair_job(archive: Archive, job_id: str) -> str:
    """``cell archive verify ID --repair``: close a job that ended without closing its folder.

    Writes what a finished session writes last, never moving anything: a session killed without
    its terminal record gets it (FAULTED, still resumable; a job past DONE gets DONE), a staged job
    (stopped before ACQUIRE) moves into the archive, and a missing or damaged manifest is written over
    the files that verify against the journal. A manifest that is intact but disagrees with the
    files is left alone: repairing never vouches for a changed file. Returns what was done.
    """
    from cell.record.jobfolder import MANIFEST

    folder = archive.folder(job_id)
    lock = folder.lock()
    try:
        recs, damage = folder.read_journal()
        if damage is not None:
            raise RecordError(f"{damage}; nothing was repaired: a damaged journal cannot vouch for any file")
        if not recs:
            raise RecordError(f"{folder.path / 'journal.jsonl'}: empty; this folder holds no job")
        if (cut := integrity.journal_against_manifest(folder)) is not None:
            raise RecordError(f"{cut}; nothing was repaired: restore the journal from a copy")
        manifest_problem = [p for p in folder.verify_manifest() if "no manifest" in p or p.startswith(MANIFEST)]
        ended = recs[-1]["event"] == "terminal"
        if ended and not manifest_problem and folder.path.parent.name != ".incoming":
            return "nothing to repair: the job is closed (its terminal record and manifest are there)"
        did = []
        states = [r.get("to") for r in recs if r["event"] == "state"]
        folder.drop_torn_tail()
        if not ended and State.DONE.value not in states:
            last = states[-1] if states else State.CREATED.value
            folder.append("state", **{"from": last, "to": State.FAULTED.value, "cause": "process ended unexpectedly"})
            folder.append("terminal", status="FAULTED",
                          reason=f"{last}: the process ended without a terminal record (killed or crashed)")
            did.append("the killed session recorded as FAULTED (resumable)")
        if folder.path.parent.name == ".incoming":
            dst = archive.root / folder.job_id
            if dst.exists():
                raise RecordError(f"{dst}: exists; cannot move the staged job {job_id} into the archive")
            folder.path.rename(dst)
            folder = JobFolder(dst)
            did.append("moved from .incoming into the archive")
        did.append(close_folder(archive, folder, list(folder.records()),
                                "DONE" if State.DONE.value in states else "FAULTED"))
        return "; ".join(did)
    finally:
        os.close(lock)
