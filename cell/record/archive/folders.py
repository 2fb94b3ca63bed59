"""The archive of one cell: one folder per job, closed by a manifest, listed in an index.

The folders and their manifests are the record; the index (SQLite next to them, or the site's
PostgreSQL) can always be rebuilt from them (:meth:`Archive.reindex`). Every index write goes
through :meth:`Archive._to_index`: when the database is away (or silent: the backend bounds every
call), refuses the record, or holds the id for another cell, the job waits in the outbox
(``.outbox/index/``, with the reason) and is written at the next write that reaches it, or by
:meth:`Archive.sync`. No index error ever reaches the running job: the folder is the record.
"""
from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path

import numpy as np

from sqlalchemy import exc as sa_exc

from calibration.errors import InputError
from cell.record.archive.ids import INCOMING, JOB_ID_PATTERN, resolve_job_id
from cell.record.archive.index import ArchiveIndex, IndexConflict, IndexRefused, IndexUnavailable, _first_line
from cell.record.archive.outbox import Outbox
from cell.record.archive.urls import mask_url, scrub
from cell.record.archive.records import job_record, manifest_sha256
from cell.record.decisions import beyond, measured, trusted, undecided
from cell.record.jobfolder import JOURNAL, JobFolder


def _is_job_folder(d: Path) -> bool:
    """A job's folder in the archive: named like a job id, not a link, with a journal."""
    return (d.is_dir() and not d.is_symlink() and not d.name.startswith(".") and bool(JOB_ID_PATTERN.fullmatch(d.name))
            and (d / JOURNAL).is_file())


class Archive:
    """The archive at ``root`` (default ``./archive``), indexed in the database at ``url``.

    ``url`` None: ``CELL_ARCHIVE_URL``, else ``sqlite:///<root>/index.sqlite``. ``push`` (a path or
    fsspec URL): where closed jobs are copied for the site (:meth:`push`).
    """

    def __init__(self, root: Path, url: str | None = None, *, push: str | None = None):
        from cell.record.archive import resolve_url

        self.root = Path(root)
        self.url = url or resolve_url(None, self.root)  # CELL_ARCHIVE_URL, else SQLite in the folder
        self.push_dest = push
        self.outbox = Outbox(self.root)
        self.push_outbox = Outbox(self.root, "push")
        self._index: ArchiveIndex | None = None
        self._down_until = 0.0
        self.origin = f"{socket.gethostname()}:{self.root.resolve()}"
        self.messages: list[str] = []  # what the archive had to say (outbox, catch-up) for the caller
        self._said: set[str] = set()  # outbox jobs already named as not indexable (said once per Archive)
        #: job id -> what is damaged in its folder, found by the last :meth:`reindex` / :meth:`catch_up`
        self.problems: dict[str, str] = {}

    # --- the index ------------------------------------------------------------------
    @property
    def index(self) -> ArchiveIndex:
        """The open index (raises ``IndexUnavailable`` while the database cannot be reached)."""
        if self._index is None:
            from cell.record.archive import open_index

            self._index = open_index(self.url)
            if getattr(self._index, "rebuilt_from", None):  # an index older than the migrations: rebuilt
                self.messages.append(f"the old index was set aside as {self._index.rebuilt_from}; rebuilt from the folders")
                self.reindex()
        return self._index

    def close(self) -> None:
        if self._index is not None:
            self._index.close()
            self._index = None

    #: after the database could not be reached, writes go straight to the outbox for this long (a host
    #: that drops packets costs a connect timeout per try: not at every state change of a running job);
    #: ``CELL_ARCHIVE_RETRY_S`` sets it
    RETRY_AFTER_S = float(os.environ.get("CELL_ARCHIVE_RETRY_S", "5"))

    def _say(self, text) -> str:
        """``text`` without a password (the url's, or any url's in it)."""
        return scrub(text, self.url)

    @property
    def shown_url(self) -> str:
        """The archive's url as it may be shown (no password)."""
        return mask_url(self.url)

    def _to_index(self, job_id: str, write) -> bool:
        """Run ``write(index)``; True if written. Never raises for the index: when the database is away or silent,
        refuses the record, or holds the id for another cell, ``job_id`` waits in the outbox with the reason, and
        :attr:`messages` says so (the job that called goes on: its folder is the record)."""
        if time.monotonic() < self._down_until:
            self.outbox.add(job_id, "the archive database was unreachable moments ago")
            return False
        try:
            self.drain()
            write(self.index)
            return True
        except IndexUnavailable as exc:
            self._down_until = time.monotonic() + self.RETRY_AFTER_S
            why = self._say(exc)
            self.outbox.add(job_id, why)
            self.messages.append(f"archive index unreachable: {job_id} waits in the outbox ({why})")
        except IndexConflict as exc:  # never overwrite another cell's job: keep it waiting, loudly
            self._keep(job_id, exc, "conflict")
        except (IndexRefused, InputError) as exc:  # a record the database (or the reader) refuses
            self._keep(job_id, exc, "refused")
        except sa_exc.SQLAlchemyError as exc:  # anything else of the database's: never the job's fault
            self._keep(job_id, f"{type(exc).__name__}: {_first_line(exc)}", "refused")
        return False

    def _keep(self, job_id: str, exc, kind: str) -> None:
        """``job_id`` stays in (or goes to) the outbox with a reason a person must act on; said once."""
        why = self._say(exc)
        self.outbox.add(job_id, why, kind)
        if job_id not in self._said:
            self._said.add(job_id)
            self.messages.append(f"{job_id} cannot be indexed, it waits in the outbox: {why}")

    def drain(self) -> list[str]:
        """Index every job waiting in the outbox (oldest first); returns their ids.

        Stops at the first that cannot be written because the database is away (raises
        ``IndexUnavailable``); a job the database refuses (or another cell's id) is skipped and stays, with its
        reason, for ``cell archive verify`` to name: it never stops the others or the write that drains.
        A job whose folder is gone leaves the outbox with a message.
        """
        done = []
        for job_id in self.outbox.pending():
            d = self.root / job_id
            if _is_job_folder(d):
                try:
                    self.index.index_job(job_record(d.resolve(), self.origin))
                except IndexConflict as exc:  # stays in the outbox; verify names it
                    self._keep(job_id, exc, "conflict")
                    continue
                except (IndexRefused, InputError) as exc:
                    self._keep(job_id, exc, "refused")
                    continue
                except IndexUnavailable:
                    raise
                except sa_exc.SQLAlchemyError as exc:
                    self._keep(job_id, f"{type(exc).__name__}: {_first_line(exc)}", "refused")
                    continue
            else:
                self.messages.append(f"outbox: {job_id} has no folder in {self.root}; dropped from the outbox")
            self.outbox.done(job_id)
            done.append(job_id)
        return done

    def folder(self, job_id: str) -> JobFolder:
        """The job's folder (see :func:`~cell.record.archive.ids.resolve_job_id`)."""
        return resolve_job_id(self.root, job_id)

    def staged(self) -> list[JobFolder]:
        """Jobs still in ``.incoming`` (stopped before ACQUIRE): listed, resumable."""
        inc = self.root / INCOMING
        if not inc.is_dir():
            return []
        return [JobFolder(d) for d in sorted(inc.iterdir()) if d.is_dir() and not d.is_symlink()
                and JOB_ID_PATTERN.fullmatch(d.name)]

    def record(self, job_id: str, **fields) -> None:
        """A running job's state (``status``, and ``name``, ``part``, ``started`` when known)."""
        status = fields.pop("status", "CREATED")
        folder = str((self.root / job_id).resolve())
        self._to_index(job_id, lambda ix: ix.set_status(job_id, origin=self.origin, folder=folder, status=status,
                                                        **fields))

    def index_folder(self, path: Path) -> bool:
        """Write one job folder's record (row and target values, one transaction); False: it waits in the outbox."""
        path = Path(path)
        try:
            rec = job_record(path.resolve(), self.origin)
        except InputError as exc:  # a folder the index cannot read: the folder stays the record
            self._keep(path.name, exc, "refused")
            return False
        if rec.problem:
            self.problems[path.name] = rec.problem
        return self._to_index(path.name, lambda ix: ix.index_job(rec))

    def job_closed(self, path: Path) -> list[str]:
        """A job folder was closed (manifest written): index it, push it when a destination is set.

        Returns what the archive has to say (a job waiting in the outbox, a failed push that waits
        for ``cell archive sync``); never raises for an unreachable database or storage.
        """
        from cell.record.archive.push import PushError

        path = Path(path)
        try:
            self.index_folder(path)
        except InputError as exc:  # a folder the index cannot read: the folder stays the record
            self._keep(path.name, exc, "refused")
        if self.push_dest:
            try:
                doc = self.push(path.name)
                self.messages.append(f"pushed {doc['files']} files ({doc['bytes']} bytes) to {doc['dest']}, verified")
            except PushError as exc:
                self.push_outbox.add(path.name, str(exc))
                self.messages.append(f"{exc}; the push waits for 'cell archive sync'")
        said, self.messages = self.messages, []
        return said

    def list(self) -> list[dict]:
        """Every job of the index, oldest first."""
        try:
            self.drain()
        except IndexUnavailable:
            pass
        return self.index.list_jobs(limit=None, newest_first=False)

    def _job_dirs(self) -> list[Path]:
        if not self.root.is_dir():
            return []
        return sorted(d for d in self.root.iterdir() if _is_job_folder(d))

    def reindex(self, only: Path | None = None) -> int:
        """Write the index records of the job folders (their journals and reports); ``only`` one folder.

        A folder that is not a job (no journal) is skipped; a job whose journal or report is damaged
        is indexed from what reads (its problem in :attr:`problems` and in the index), never failing
        the others.
        """
        n = 0
        dirs = [Path(only)] if only is not None else self._job_dirs()
        for d in dirs:
            if not (d / JOURNAL).is_file():
                continue
            self.index_folder(d)
            n += 1
        return n

    def folders_not_in(self, known: set[str]) -> list[JobFolder]:
        """The archive's job folders whose ids are not in ``known`` (a directory listing, no index query)."""
        return [JobFolder(d) for d in self._job_dirs() if d.name not in known]

    def catch_up(self) -> list[str]:
        """Drain the outbox and index the job folders the index does not hold yet (a listing's first step:
        a directory listing and one query, not a read of every folder); returns the ids indexed."""
        try:
            self.drain()
            known = self.index.job_ids(origin=self.origin)
            state = self.index.index_state(origin=self.origin)
        except IndexUnavailable:
            return []
        # and a row the job never finished writing: a kill between the manifest and the index's last write leaves it
        # DONE without its manifest's hash, verdict or targets (an outside check: a FAIL missing from every query)
        new = [d for d in self._job_dirs() if d.name not in known
               or (state.get(d.name, {}).get("manifest_sha256") is None and (d / "manifest.json").is_file())]
        for d in new:
            self.index_folder(d)
        return [d.name for d in new]

    def listing(self, **filters) -> list[dict]:
        """``cell archive list``: the index's jobs (caught up with the folders first), oldest first, and the
        staged ones (in ``.incoming``) after them; a row whose folder could not be read whole has ``problem``."""
        self.catch_up()
        rows = self.index.list_jobs(limit=None, newest_first=False, **filters)
        for r in rows:
            r["staged"] = False
            if r.get("problem") is None:
                r.pop("problem", None)
        if not any(v is not None for v in filters.values()):
            rows += self.staged_rows()
        return rows

    def staged_rows(self) -> list[dict]:
        """Rows of the jobs in ``.incoming`` (not in the index: they may still be refused as bad input)."""
        rows = []
        for f in self.staged():
            rec = job_record(f.path, self.origin)
            row = {"id": f.job_id, "folder": str(f.path), "staged": True, "name": rec.name, "status": rec.status,
                   "started": rec.started, "part": rec.part, "verdict": rec.verdict}
            if rec.problem:
                row["problem"] = rec.problem
            rows.append(row)
        return rows

    def sync(self, adopt: bool = False) -> dict:
        """``cell archive sync``: drain the outbox, then index every folder the index lacks or holds stale.

        Stale: another manifest hash or state than the folder's, or fewer target rows than the row
        claims. A folder that does not match its own manifest (a report changed after the job) is not
        re-indexed: the index keeps what it held, and the folder is named in ``skipped`` (as ``push`` refuses
        it); one the index does not hold at all is indexed as far as it reads with the mismatch in its ``problem``
        (listed, marked, never silently). A job the database refuses or another cell owns goes to the outbox with its reason and is
        named in ``skipped`` too; the folders after it are indexed all the same.

        A job the index holds from another origin with the folder's own manifest hash is the same job at another
        path (the archive moved, the host renamed): named so, and re-owned with ``adopt`` (``sync --adopt``). A job
        id of another origin with another manifest is another cell's job: never adopted.

        Returns {``drained``, ``indexed``, ``pending`` (still in the outbox), ``skipped`` ([{``id``,
        ``reason``}]: not indexed, a person must act), ``adopted`` ([{``id``, ``from``}]), ``pushed``,
        ``push_pending``, ``problems`` (folders indexed only as far as they read, one line each)}.
        """
        drained = self.drain()
        state = self.index.index_state(origin=self.origin)
        indexed, problems, skipped, adopted = [], [], {}, []
        for d in self._job_dirs():
            have = state.get(d.name)
            rec = job_record(d.resolve(), self.origin)
            if (have is None or have["manifest_sha256"] != rec.manifest_sha256 or have["status"] != rec.status
                    or (have["targets"] or 0) != have["target_rows"]
                    or (have["failed"] is not None and rec.failed is not None and have["failed"] != rec.failed)):
                # (a failed count of before not-measured targets were told apart from failed ones is stale too)
                changed = [p for p in JobFolder(d).verify_manifest() if "no manifest" not in p]
                if changed:  # never index values the folder's own manifest does not vouch for, silently
                    what = "does not match its manifest (" + "; ".join(changed[:3]) + (" ..." if len(changed) > 3 else "") + ")"
                    if have is not None:  # the index keeps what it held when the job closed
                        skipped[d.name] = f"{what}: not indexed, the index keeps its earlier row; see " \
                                          f"'cell archive verify {d.name}'"
                        continue
                    # not in the index at all: listed as far as it reads, marked (list and console show the problem)
                    rec.problem = "; ".join(x for x in (rec.problem, what) if x)
                if rec.problem:
                    problems.append(f"{d.name}: {rec.problem}")
                try:
                    self.index.index_job(rec)
                except IndexConflict as exc:
                    moved = self._moved(rec, str(d.resolve()), exc, adopt)
                    if moved is None:
                        continue
                    adopted.append({"id": d.name, "from": moved})
                except IndexRefused as exc:
                    self._keep(d.name, exc, "refused")
                    continue
                indexed.append(d.name)
            elif rec.problem:
                problems.append(f"{d.name}: {rec.problem}")
        pending = self.outbox.pending()
        for job_id in pending:
            e = self.outbox.entry(job_id)
            if e.get("kind") in ("conflict", "refused"):
                skipped.setdefault(job_id, f"waits in the outbox: {self._say(e.get('reason'))}")
        pushed = self.drain_pushes()
        return {"drained": drained, "indexed": indexed, "pending": pending,
                "skipped": [{"id": k, "reason": v} for k, v in skipped.items()], "adopted": adopted, "pushed": pushed,
                "push_pending": self.push_outbox.pending(), "problems": problems}

    def _moved(self, rec, folder: str, exc: IndexConflict, adopt: bool) -> str | None:
        """A conflict on ``rec``'s id: the old origin when it was the same job moved and ``adopt`` re-owned it (then
        indexed); else None, the job kept in the outbox with its reason (which names ``--adopt`` for the same job)."""
        held = self.index.owner(rec.id)
        same = held is not None and rec.manifest_sha256 is not None and held[1] == rec.manifest_sha256
        if same and adopt:
            self.index.adopt(rec.id, old_origin=held[0], origin=self.origin, folder=folder,
                             manifest_sha256=rec.manifest_sha256)
            self.index.index_job(rec)
            self.outbox.done(rec.id)
            return held[0]
        if same:
            exc = IndexConflict(f"{exc.args[0].split(': the cells of one site')[0]}: the same job (manifest "
                                f"{rec.manifest_sha256[:12]} matches) at another path, the archive moved or the host "
                                "was renamed: run 'cell archive sync --adopt' to re-own it here")
        self._keep(rec.id, exc, "conflict")
        return None

    def verify_index(self) -> dict:
        """``cell archive verify`` without a job id: the index against the folders of this cell.

        Problems: a folder the index lacks, a row whose folder is gone, a different manifest hash or
        state, a row whose target rows are not the count it claims (a half-written job), a report
        whose targets are not the rows. Jobs still in the outbox are listed apart (not problems), and
        so are folders that do not read whole (``damaged``: indexed as far as they read).
        """
        state = self.index.index_state(origin=self.origin)
        pending = set(self.outbox.pending())
        problems, damaged, checked = [], [], 0
        folders = {d.name: d for d in self._job_dirs()}
        for job_id, d in folders.items():
            checked += 1
            have = state.get(job_id)
            if job_id in pending:  # waiting for the database is no problem; refused or another cell's id is
                e = self.outbox.entry(job_id)
                if e.get("kind") in ("conflict", "refused"):
                    problems.append(f"{job_id}: cannot be indexed, waits in the outbox: {self._say(e.get('reason'))}")
                continue
            if have is None:
                problems.append(f"{job_id}: folder not in the index (run 'cell archive sync')")
                continue
            if have["manifest_sha256"] != manifest_sha256(d):
                problems.append(f"{job_id}: the index holds another manifest than the folder's (run 'cell archive "
                                "sync')")
            rec = job_record(d.resolve(), self.origin)
            if rec.problem:
                damaged.append(f"{job_id}: {rec.problem}")
            if have["status"] != rec.status:
                problems.append(f"{job_id}: index says {have['status']}, the journal {rec.status}")
            if (have["targets"] or 0) != have["target_rows"]:
                problems.append(f"{job_id}: index row claims {have['targets']} targets, holds {have['target_rows']}")
            elif have["target_rows"] != len(rec.targets):
                problems.append(f"{job_id}: report has {len(rec.targets)} targets, the index {have['target_rows']}")
            elif rec.targets:  # the values, not only the counts (an outside check changed a verdict and a coordinate)
                problems += _values_differ(job_id, have, rec, self.index.job_targets(job_id))
            # the folder against its own manifest: a changed report, image or input is a problem here too
            problems += [f"{job_id}: {p}" for p in JobFolder(d).verify_manifest() if "no manifest" not in p]
        for job_id, have in state.items():
            if job_id not in folders:
                problems.append(f"{job_id}: in the index but no folder in {self.root}")
        # a job killed and never resumed has no manifest (and one stopped before ACQUIRE is still in .incoming): the
        # index may match it, but nobody vouches for it until it is resumed (an outside check: verify said "matches")
        unclosed, running = [], []
        for f in [JobFolder(d) for d in folders.values()] + self.staged():
            if (f.path / "manifest.json").is_file():
                continue
            pid = f.running_pid()
            if pid is not None:
                running.append(f"{f.job_id}: running (pid {pid})")
                continue
            status = job_record(f.path.resolve(), self.origin).status
            act = (f"cell archive verify {f.job_id} --repair" if status == "DONE"  # its work is done: only closed
                   else f"cell resume {f.job_id} --yes")
            unclosed.append(f"{f.job_id}: stopped at {status} and never closed (killed, or the computer went down): "
                            f"run '{act}'")
        return {"checked": checked, "indexed": len(state), "outbox": sorted(pending), "problems": problems,
                "damaged": damaged, "unclosed": unclosed, "running": running,
                "intact": not problems and not unclosed}

    def push(self, job_id: str, dest: str | None = None) -> dict:
        """Copy the closed job folder to shared storage and check the copy against its manifest."""
        from cell.record.archive.push import push_job

        dest = dest or self.push_dest or os.environ.get("CELL_ARCHIVE_PUSH")
        if not dest:
            raise InputError("cell archive push: no destination (give --to, CELL_ARCHIVE_PUSH or the cell file's "
                             "[archive] push)")
        return push_job(self.folder(job_id).path, dest)

    def drain_pushes(self) -> list[str]:
        """Push the jobs whose automatic push failed earlier (storage away); returns the ids pushed."""
        from cell.record.archive.push import PushError

        done = []
        for job_id in self.push_outbox.pending():
            try:
                self.push(job_id)
            except PushError as exc:
                self.messages.append(str(exc))
                break
            self.push_outbox.done(job_id)
            done.append(job_id)
        return done

    def show(self, job_id: str) -> dict:
        folder = self.folder(job_id)
        recs, damage = folder.read_journal()
        doc = {"id": job_id, "folder": str(folder.path), "journal": recs[-5:]}
        if damage is not None:
            doc["problem"] = f"journal damaged: {damage}"
        rep = folder.file("report.json")
        if rep.is_file():
            try:
                r = json.loads(rep.read_text(encoding="utf-8"))
                doc |= {"job": r["job"], "verdict": r.get("verdict"), "sigma0_px": r.get("sigma0_px"),
                        "targets": len(r["targets"]), "failed": [t["id"] for t in r["targets"] if beyond(t)],
                        "not_measured": [t["id"] for t in r["targets"] if not measured(t)],
                        "undecided": [t["id"] for t in r["targets"] if undecided(t, trusted(r))]}
            except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as exc:
                doc["problem"] = f"report.json damaged ({type(exc).__name__}: {exc})"
        return doc

    def compare(self, ids: list[str]) -> dict:
        """Deviation trends of the same part over several jobs: per target, the deviation norm in each job.

        The drift is the first job's measured point to the last's; it is significant beyond 3 sigma of the drift
        along its own direction u, sigma = sqrt(u^T (C_first + C_last) u) from both reports' ``cov`` (each job's
        own uncertainty, not one job's). A target not measured in the first or the last job has no drift
        (``drift_m`` None; listed in ``not_measured`` with the jobs that did not measure it). ``untrusted``: the
        jobs whose alignment to CAD is not trusted or whose verdict is UNTRUSTED (their deviations, and a drift
        from or to them, are in a frame that cannot be relied on; ``note`` says so): a drift from or to such a job
        is given but not judged (``drift_significant`` None, not in ``drifting``).
        """
        if len(ids) < 2:
            raise InputError("cell archive compare needs at least two job ids")
        reports = []
        for j in ids:
            p = self.folder(j).file("report.json")
            if not p.exists():
                raise InputError(f"{j}: has no report (status: not DONE)")
            try:
                doc = json.loads(p.read_text(encoding="utf-8"))
                if not isinstance(doc.get("targets"), list) or not isinstance(doc.get("job"), dict):
                    raise ValueError("no 'targets' list or 'job' table")
            except (OSError, UnicodeDecodeError, ValueError, AttributeError) as exc:
                raise InputError(f"{j}: report.json is damaged ({exc}); see 'cell archive verify {j}'") from None
            reports.append(doc)
        parts = {r["job"].get("part") for r in reports}
        if len(parts) > 1:
            raise InputError(f"cell archive compare: the jobs inspect different parts ({', '.join(map(str, parts))})")
        untrusted = []
        for j, r in zip(ids, reports):
            al = r.get("alignment") or {}
            if not trusted(r):
                untrusted.append({"job_id": j, "verdict": r.get("verdict"), "alignment_trusted": al.get("trusted"),
                                  "reasons": list(al.get("reasons") or r.get("verdict_reasons") or [])})
        untrusted_ids = {u["job_id"] for u in untrusted}
        common = set.intersection(*({t["id"] for t in r["targets"]} for r in reports))
        by_id = [{t["id"]: t for t in r["targets"]} for r in reports]
        rows, not_measured = [], []
        for tid in sorted(common):
            dev = [b[tid] for b in by_id]
            missing = [j for j, d in zip(ids, dev) if not measured(d)]
            if missing:
                not_measured.append({"id": tid, "jobs": missing})
            row = {"id": tid, "deviation_norm_m": [d["deviation_norm_m"] for d in dev],
                   "pass": [d["pass"] if measured(d) else None for d in dev],
                   "decision": [d.get("decision") for d in dev],
                   "tolerance_m": [d.get("tolerance_m") for d in dev],
                   "drift_m": None, "drift_sigma_m": None, "drift_significant": None}
            if measured(dev[0]) and measured(dev[-1]):
                change = np.asarray(dev[-1]["measured"], dtype=float) - np.asarray(dev[0]["measured"], dtype=float)
                drift = float(np.linalg.norm(change))
                sig = _drift_sigma(change, dev[0], dev[-1])
                judged = sig is not None and not (untrusted_ids & {ids[0], ids[-1]})
                row |= {"drift_m": drift, "drift_sigma_m": sig,
                        "drift_significant": bool(drift > 3 * sig) if judged else None}
            rows.append(row)
        note = None
        if untrusted:
            note = (f"alignment to CAD not trusted in {', '.join(u['job_id'] for u in untrusted)}: its deviations "
                    "and a drift from or to it are in a frame that cannot be relied on"
                    + ("; no drift is judged (drift_significant None)" if untrusted_ids & {ids[0], ids[-1]} else ""))
        return {"jobs": ids, "part": parts.pop(), "targets": rows,
                "drifting": [r["id"] for r in rows if r["drift_significant"]],
                "not_measured": not_measured, "untrusted": untrusted, "note": note}

    def verify(self, job_id: str) -> list[str]:
        """Problems of the job's folder against its manifest and its journal (empty: intact)."""
        from cell.record import integrity

        folder = self.folder(job_id)
        problems = folder.verify_manifest()
        recs, damage = folder.read_journal()
        if damage is not None:
            problems.append(f"journal damaged: {damage}")
        found = integrity.check_stored(folder, recs, decode_images=False)
        problems += [f"station {sid}: {why}" for sid, why in found.stations.items()]
        problems += [f"{rel}: {why} (per the journal)" for rel, (why, _) in found.files.items()]
        return list(dict.fromkeys(problems))


def _drift_sigma(change: np.ndarray, a: dict, b: dict) -> float | None:
    """The standard deviation of the drift ``change`` (b's measured point minus a's) along its direction:
    sqrt(u^T (C_a + C_b) u), u = change / |change| (the largest axis of C_a + C_b for no change); a report without
    a finite ``cov`` falls back to its ``achieved_sigma_m`` / sqrt(3) per axis (None when neither is known)."""
    covs = []
    for t in (a, b):
        c = t.get("cov")
        try:
            c = np.asarray(c, dtype=float)
        except (TypeError, ValueError):
            c = None
        if c is None or c.shape != (3, 3) or not np.isfinite(c).all():
            s = t.get("achieved_sigma_m")
            if s is None or not np.isfinite(s):
                return None
            c = np.eye(3) * s ** 2 / 3
        covs.append(c)
    C = covs[0] + covs[1]
    n = float(np.linalg.norm(change))
    if n > 0:
        u = change / n
        return float(np.sqrt(max(u @ C @ u, 0.0)))
    return float(np.sqrt(max(np.linalg.eigvalsh(C)[-1], 0.0)))


def _values_differ(job_id: str, have: dict, rec, rows: list[dict]) -> list[str]:
    """Where the index's row and target rows of ``job_id`` say other than the folder's record ``rec`` (what
    :func:`job_record` reads from report.json): the verdict, the count of failed targets, each target's values."""
    out = []
    if have.get("verdict") != rec.verdict:
        out.append(f"{job_id}: index says verdict {have.get('verdict')}, the report {rec.verdict}")
    if have.get("failed") is not None and rec.failed is not None and have["failed"] != rec.failed:
        out.append(f"{job_id}: index says {have['failed']} failed target(s), the report {rec.failed}")
    mine = {r["target_id"]: r for r in rec.targets}
    bad = []
    for t in rows:
        r = mine.get(t["id"])
        if r is None:
            bad.append(t["id"])
            continue
        pairs = [(t[p], [r[f"{p}_{a}"] for a in "xyz"]) for p in ("nominal", "measured", "deviation")]
        pairs += [(t[k], r[c]) for k, c in (("deviation_norm_m", "deviation_norm_m"), ("tolerance_m", "tolerance_m"),
                                            ("uncertainty_U_m", "uncertainty_u_m"))]
        same = all(_same(a, b) for a, b in pairs) and t["decision"] == r["decision"] and t["pass"] == r["passed"]
        if not same:
            bad.append(t["id"])
    if bad:
        out.append(f"{job_id}: index values differ from the report at {len(bad)} target(s): {', '.join(bad[:6])}"
                   + (" ..." if len(bad) > 6 else ""))
    return out


def _same(a, b) -> bool:
    """Equal as the index stores them (None, or floats within a relative 1e-9)."""
    if isinstance(a, list) or isinstance(b, list):
        a = a if isinstance(a, list) else [None] * 3
        b = b if isinstance(b, list) else [None] * 3
        return all(_same(x, y) for x, y in zip(a, b))
    if a is None or b is None:
        return a is None and b is None
    return abs(float(a) - float(b)) <= 1e-9 * max(abs(float(a)), abs(float(b)), 1e-300)
