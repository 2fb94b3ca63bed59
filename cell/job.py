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
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from calibration.errors import AbortRequested, CellError, InputError
from cell.record.archive import Archive
from cell.record.jobfolder import JobFolder, atomic_write_bytes, atomic_write_json, new_job_id
from cell.stages import STAGE_FUNCTIONS
from cell.loadedjob import LoadedJob, load
from cell.record.runlog import RunLog, next_log_path
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


class JobRunner:
    """Runs the stages of one job from a given stage to DONE, FAULTED or ABORTED."""

    def __init__(self, archive: Archive, folder: JobFolder, job: LoadedJob, backend: str, out, *, staged: bool):
        self.archive = archive
        self.folder = folder
        self.job = job
        self.backend = backend
        self.out = out
        self.staged = staged  # still in .incoming
        self.state = State.CREATED
        self.times: dict[str, float] = {}

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
                      progress=self.out.progress, say=self.out.say)
        self.state = resumed_from or State.CREATED
        old_term = signal.getsignal(signal.SIGTERM)

        def _sigterm(signum, frame):
            raise AbortRequested("SIGTERM")

        signal.signal(signal.SIGTERM, _sigterm)
        status, reason, interrupted = State.DONE, "", False
        try:
            for stage in STAGES[STAGES.index(start):]:
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
            self._go(ctx, State.DONE)
        except (AbortRequested, KeyboardInterrupt) as exc:
            status, reason, interrupted = State.ABORTED, f"aborted by the operator ({type(exc).__name__})", True
            self._stop_robot(ctx)
            self._go(ctx, State.ABORTED, reason)
        except CellError as exc:
            status, reason = State.FAULTED, f"{self.state.value}: {exc}"
            self._stop_robot(ctx)
            if (isinstance(exc, InputError) or exc.exit_code == 2) and self.staged:  # bad input (e.g. out of reach)
                log.close()
                shutil.rmtree(self.folder.path, ignore_errors=True)
                raise
            self._go(ctx, State.FAULTED, reason)
        except Exception as exc:  # a bug: still one terminal record with the cause
            status, reason = State.FAULTED, f"{self.state.value}: internal error {type(exc).__name__}: {exc}"
            self.folder.append("traceback", text=traceback.format_exc())
            self._stop_robot(ctx)
            self._go(ctx, State.FAULTED, reason)
        finally:
            signal.signal(signal.SIGTERM, old_term)
            if ctx.devices is not None:
                ctx.devices.close()
            log.close()
        if self.staged:  # faulted before ACQUIRE for a reason that is not bad input: keep it
            self._promote()
        self.folder.append("terminal", status=status.value, reason=reason)
        self.folder.write_manifest()
        self.archive.reindex(only=self.folder.path)
        return JobResult(self.folder.job_id, status, self.folder.path, reason, interrupted, dict(self.times))

    def _stop_robot(self, ctx: Context) -> None:
        if ctx.devices is not None:
            try:
                ctx.devices.robot.stop()
            except Exception as exc:  # the robot may be the thing that failed
                self.folder.append("note", text=f"robot stop after fault failed: {exc}")


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
