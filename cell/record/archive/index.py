"""The archive index: one repository interface, one subclass per database (``sqlite``, ``postgres``).

Every write is one transaction: a job's row and all its target rows go in together or not at
all (a process killed mid-write leaves the job as it was before). Reads return plain dicts with
times as ISO 8601 UTC strings, ready for JSON.

When the database cannot be reached (or does not answer within the backend's bound) a write raises
:class:`IndexUnavailable`; when it refuses the write (a value longer than its column, a constraint,
any other database error) :class:`IndexRefused`, whose message is the database's first line, never
the statement or its values. The caller (:class:`~cell.record.archive.folders.Archive`) then puts
the job in its outbox with the reason; the job itself goes on.
"""
from __future__ import annotations

import contextlib
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import sqlalchemy as sa
from sqlalchemy import exc as sa_exc

from calibration.errors import CellError, InputError
from cell.record.archive.records import JobRecord
from cell.record.archive.tables import COV_KEYS, jobs, targets

MIGRATIONS = Path(__file__).with_name("migrations")


class IndexUnavailable(CellError):
    """The archive's database cannot be reached (or is locked) now: the write waits in the outbox."""


class IndexRefused(CellError):
    """The database refused a write or a read (not a connection problem): a value too long for its column,
    a constraint, a permission. The job waits in the outbox with this reason; retrying alone will not help."""


class IndexConflict(CellError):
    """A job id the index already holds for another cell (the job ids of a site must be unique)."""

    exit_code = 2


def _utc(t: Any) -> datetime | None:
    """An ISO 8601 string or datetime of a record (the journal's, the report's) as an aware UTC datetime (naive = UTC).

    Times a user gives (``--since``, ``--until``, the console's dates) go through :func:`user_time` instead."""
    if t is None or t == "":
        return None
    if isinstance(t, str):
        try:
            t = datetime.fromisoformat(t)
        except ValueError:
            raise InputError(f"not an ISO 8601 time: {t!r}") from None
    if t.tzinfo is None:
        return t.replace(tzinfo=timezone.utc)
    return t.astimezone(timezone.utc)


def user_time(t: Any, *, end: bool = False) -> datetime | None:
    """A time a user gives to filter by (``cell archive list --since/--until``, the console's from/to): one rule.

    An ISO 8601 time or date; a time without a zone is the cell's local time (as the time in a job id is);
    a date alone is its first instant (local), and with ``end`` (an ``until``) its whole day: the next day's
    first instant, since ``until`` is exclusive. Returns an aware UTC datetime (None for None or "")."""
    if t is None or t == "":
        return None
    date_only = False
    if isinstance(t, str):
        s = t.strip()
        date_only = len(s) == 10 and s[4:5] == "-" and s[7:8] == "-"
        try:
            t = datetime.fromisoformat(s)
        except ValueError:
            raise InputError(f"not an ISO 8601 time or date (YYYY-MM-DD[THH:MM[:SS]][+HH:MM]): {s[:60]!r}") from None
    if not isinstance(t, datetime):
        raise InputError(f"not an ISO 8601 time or date: {t!r}")
    if t.tzinfo is None:
        t = t.astimezone()  # naive: the cell's local time
    if date_only and end:
        from datetime import timedelta

        t = (t.replace(tzinfo=None) + timedelta(days=1)).astimezone()
    return t.astimezone(timezone.utc)


def _iso(t: datetime | None) -> str | None:
    if t is None:
        return None
    if isinstance(t, str):  # a backend handing back text
        t = datetime.fromisoformat(t)
    if t.tzinfo is None:
        t = t.replace(tzinfo=timezone.utc)
    return t.astimezone(timezone.utc).isoformat(timespec="milliseconds")


def _job_dict(row) -> dict:
    d = dict(row._mapping)
    for k in ("started", "finished", "indexed_at"):
        if k in d:
            d[k] = _iso(d[k])
    return d


def _target_dict(row) -> dict:
    m = row._mapping
    cov = [m[f"cov_{k}"] for k in COV_KEYS]
    full = None
    if all(v is not None for v in cov):
        xx, xy, xz, yy, yz, zz = cov
        full = [[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]
    vec = lambda p: None if m[f"{p}_x"] is None else [m[f"{p}_x"], m[f"{p}_y"], m[f"{p}_z"]]  # noqa: E731
    return {"job_id": m["job_id"], "id": m["target_id"], "kind": m["kind"], "nominal": vec("nominal"),
            "measured": vec("measured"), "cov": full, "deviation": vec("deviation"),
            "deviation_norm_m": m["deviation_norm_m"], "tolerance_m": m["tolerance_m"],
            "uncertainty_U_m": m["uncertainty_u_m"], "achieved_sigma_m": m["achieved_sigma_m"],
            "decision": m["decision"], "pass": m["passed"]}


class ArchiveIndex:
    """The repository interface over one database (see the package docstring for the methods)."""

    #: ``sqlite`` or ``postgresql``
    kind = ""
    _head: str | None = None  # the newest migration (read once per process)

    def __init__(self, engine: sa.engine.Engine, url: str):
        self.engine = engine
        self.url = url  # without a password (for messages)
        self._ensure_schema()

    # --- schema -----------------------------------------------------------------
    @classmethod
    def _config(cls):
        from alembic.config import Config
        from alembic.script import ScriptDirectory

        cfg = Config()
        cfg.set_main_option("script_location", str(MIGRATIONS))
        if ArchiveIndex._head is None:
            ArchiveIndex._head = ScriptDirectory.from_config(cfg).get_current_head()
        return cfg

    def _ensure_schema(self) -> None:
        """Bring the database to the newest migration (alembic) under the backend's migration lock."""
        from alembic import command
        from alembic.runtime.migration import MigrationContext

        cfg = self._config()
        try:
            with self._bounded(self.MIGRATION_BOUND_S), self._migration_guard() as conn:
                if MigrationContext.configure(conn).get_current_revision() != self._head:
                    cfg.attributes["connection"] = conn
                    command.upgrade(cfg, "head")
        except (sa_exc.OperationalError, sa_exc.InterfaceError) as exc:
            raise IndexUnavailable(f"{self.url}: cannot reach the archive database ({self._why(exc)})") from exc
        except sa_exc.SQLAlchemyError as exc:
            raise IndexRefused(f"{self.url}: the archive database refused its schema upgrade ({_first_line(exc)})") from exc

    #: how long one write or read may take before it is given up (``IndexUnavailable``): a backend that can
    #: bound its connections sets it (:class:`~cell.record.archive.postgres.PostgresIndex`); 0: unbounded
    BOUND_S = 0.0
    MIGRATION_BOUND_S = 0.0

    def _bounded(self, seconds: float | None = None):
        """A context that gives up the operation inside it after ``seconds`` (default :attr:`BOUND_S`)."""
        return contextlib.nullcontext()

    def _why(self, exc: BaseException) -> str:
        """An error's first line (the backend may say it was its own bound that gave up)."""
        return _first_line(exc)

    def _migration_guard(self):
        """A connection in a transaction that holds the database's migration lock (per backend)."""
        raise NotImplementedError

    def schema_revision(self) -> str | None:
        from alembic.runtime.migration import MigrationContext

        with self.engine.connect() as conn:
            return MigrationContext.configure(conn).get_current_revision()

    # --- writes -----------------------------------------------------------------
    def _begin(self):
        try:
            return self.engine.begin()
        except (sa_exc.OperationalError, sa_exc.InterfaceError) as exc:
            raise IndexUnavailable(f"{self.url}: cannot reach the archive database ({self._why(exc)})") from exc

    def _lock_row(self, conn, job_id: str):
        """The job's row (locked for this transaction where the database can), or None."""
        return conn.execute(sa.select(jobs.c.origin).where(jobs.c.id == job_id)).first()

    def _write(self, fn) -> None:
        """``fn(conn)`` in one transaction, bounded (:attr:`BOUND_S`). An unreachable or silent database raises
        :class:`IndexUnavailable`; any other database error :class:`IndexRefused` with the database's first line
        (never the statement or its parameters, which hold the job's values)."""
        for attempt in range(3):
            try:
                with self._bounded(), self._begin() as conn:
                    fn(conn)
                return
            except sa_exc.IntegrityError as exc:  # two writers inserted the same new id at once: the row now exists
                if attempt == 2:
                    raise IndexRefused(f"{self.url}: the archive database refused the write ({_first_line(exc)})") \
                        from None
            except (sa_exc.OperationalError, sa_exc.InterfaceError) as exc:
                raise IndexUnavailable(f"{self.url}: cannot write to the archive database ({self._why(exc)})") from exc
            except sa_exc.SQLAlchemyError as exc:  # DataError (a value too long), ProgrammingError, ...
                raise IndexRefused(f"{self.url}: the archive database refused the write ({_first_line(exc)})") from None

    @staticmethod
    def _check_origin(row, job_id: str, origin: str) -> None:
        if row is not None and row.origin != origin:
            raise IndexConflict(f"job {job_id!r} is already in the archive index from {row.origin}, not from {origin}: "
                                "the cells of one site need distinct job ids (set CELL_ID or the cell file's [cell] name)")

    def index_job(self, rec: JobRecord) -> None:
        """Insert or replace a job's row and all its target rows, in one transaction."""
        row = rec.job_row() | {"indexed_at": datetime.now(timezone.utc)}
        for k in ("started", "finished"):
            row[k] = _utc(row[k])
        fin = row["finished"]
        trows = [t | {"job_id": rec.id, "part": rec.part, "finished": fin, "serial": rec.serial} for t in rec.targets]

        def fn(conn):
            existing = self._lock_row(conn, rec.id)
            self._check_origin(existing, rec.id, rec.origin)
            if existing is None:
                conn.execute(jobs.insert().values(**row))
            else:
                conn.execute(jobs.update().where(jobs.c.id == rec.id).values(**row))
            conn.execute(targets.delete().where(targets.c.job_id == rec.id))
            if trows:
                conn.execute(targets.insert(), trows)

        self._write(fn)

    def set_status(self, job_id: str, *, origin: str, folder: str, status: str, **fields) -> None:
        """A running job's state (and name, part, started when known), without touching its targets."""
        vals = {"status": status, **{k: v for k, v in fields.items() if v is not None}}
        for k in ("started", "finished"):
            if k in vals:
                vals[k] = _utc(vals[k])

        def fn(conn):
            existing = self._lock_row(conn, job_id)
            self._check_origin(existing, job_id, origin)
            now = datetime.now(timezone.utc)
            if existing is None:
                conn.execute(jobs.insert().values(id=job_id, name=vals.pop("name", job_id), origin=origin, folder=folder,
                                                  indexed_at=now, **vals))
            else:
                conn.execute(jobs.update().where(jobs.c.id == job_id).values(indexed_at=now, **vals))

        self._write(fn)

    def owner(self, job_id: str) -> tuple[str, str | None] | None:
        """The origin and manifest hash the index holds for ``job_id`` (None: it holds no such job)."""
        rows = self._read(sa.select(jobs.c.origin, jobs.c.manifest_sha256).where(jobs.c.id == job_id))
        return (rows[0].origin, rows[0].manifest_sha256) if rows else None

    def adopt(self, job_id: str, *, old_origin: str, origin: str, folder: str, manifest_sha256: str) -> None:
        """Re-own a job the index holds from ``old_origin`` for ``origin`` (an archive moved, a host renamed): only
        the same job, the row's manifest hash equal to the folder's; ``IndexConflict`` otherwise."""
        def fn(conn):
            n = conn.execute(jobs.update().where(jobs.c.id == job_id, jobs.c.origin == old_origin,
                                                 jobs.c.manifest_sha256 == manifest_sha256)
                             .values(origin=origin, folder=folder, indexed_at=datetime.now(timezone.utc))).rowcount
            if n != 1:
                raise IndexConflict(f"job {job_id!r} is not held from {old_origin} with manifest "
                                    f"{manifest_sha256[:12]}: not adopted")

        self._write(fn)

    def delete_job(self, job_id: str) -> None:
        def fn(conn):
            conn.execute(targets.delete().where(targets.c.job_id == job_id))
            conn.execute(jobs.delete().where(jobs.c.id == job_id))

        self._write(fn)

    # --- reads ------------------------------------------------------------------
    def _read(self, stmt) -> list:
        try:
            with self._bounded(), self.engine.connect() as conn:
                return conn.execute(stmt).all()
        except (sa_exc.OperationalError, sa_exc.InterfaceError) as exc:
            raise IndexUnavailable(f"{self.url}: cannot read the archive database ({self._why(exc)})") from exc
        except sa_exc.SQLAlchemyError as exc:
            raise IndexRefused(f"{self.url}: the archive database refused a query ({_first_line(exc)})") from None

    @staticmethod
    def _filters(part=None, serial=None, verdict=None, status=None, since=None, until=None, cell_id=None,
                 origin=None, part_number=None, operator=None) -> list:
        w = []
        for col, v in ((jobs.c.part, part), (jobs.c.serial, serial), (jobs.c.verdict, verdict),
                       (jobs.c.status, status), (jobs.c.cell_id, cell_id), (jobs.c.origin, origin),
                       (jobs.c.part_number, part_number), (jobs.c.operator, operator)):
            if v is not None:
                w.append(col == v)
        if since is not None:
            w.append(jobs.c.started >= user_time(since))
        if until is not None:
            w.append(jobs.c.started < user_time(until, end=True))
        return w

    def list_jobs(self, *, part: str | None = None, serial: str | None = None, verdict: str | None = None,
                  status: str | None = None, since=None, until=None, cell_id: str | None = None,
                  origin: str | None = None, part_number: str | None = None, operator: str | None = None,
                  limit: int | None = 50, offset: int = 0, newest_first: bool = True) -> list[dict]:
        """One page of jobs matching every filter given (``since`` <= started < ``until``), newest first.

        ``since``/``until``: datetimes or ISO 8601 text as :func:`user_time` reads them (no zone: local time;
        ``until`` a date: that whole day)."""
        order = (jobs.c.started.desc(), jobs.c.id.desc()) if newest_first else (jobs.c.started.asc(), jobs.c.id.asc())
        stmt = sa.select(jobs).where(*self._filters(part, serial, verdict, status, since, until, cell_id, origin,
                                                    part_number, operator))
        stmt = stmt.order_by(*order).offset(int(offset))
        if limit is not None:
            stmt = stmt.limit(int(limit))
        return [_job_dict(r) for r in self._read(stmt)]

    def count_jobs(self, **filters) -> int:
        """How many jobs match (the same filters as :meth:`list_jobs`)."""
        stmt = sa.select(sa.func.count()).select_from(jobs).where(*self._filters(**filters))
        return int(self._read(stmt)[0][0])

    def get_job(self, job_id: str) -> dict | None:
        rows = self._read(sa.select(jobs).where(jobs.c.id == job_id))
        return _job_dict(rows[0]) if rows else None

    def job_targets(self, job_id: str) -> list[dict]:
        """The job's target values (nominal, measured, cov 3x3, deviation, ..., decision), by target id."""
        stmt = sa.select(targets).where(targets.c.job_id == job_id).order_by(targets.c.target_id)
        return [_target_dict(r) for r in self._read(stmt)]

    def not_measured_counts(self, job_ids: list[str]) -> dict[str, int]:
        """Per job id of ``job_ids``: how many of its target rows were not measured (no deviation), in one
        GROUP BY query; a job all of whose targets were measured is absent (0)."""
        if not job_ids:
            return {}
        t = targets.c
        out = {}
        ids = list(dict.fromkeys(job_ids))
        for k in range(0, len(ids), 500):  # bounded IN lists
            stmt = (sa.select(t.job_id, sa.func.count()).where(t.job_id.in_(ids[k:k + 500]),
                                                               t.deviation_norm_m.is_(None)).group_by(t.job_id))
            out |= {r[0]: int(r[1]) for r in self._read(stmt)}
        return out

    def target_trend(self, part: str, target_id: str, *, since=None, until=None, limit: int | None = None) -> list[dict]:
        """One target of a part over every job that measured it, oldest first: a trend is one query.

        Points: ``job_id``, ``serial``, ``finished``, ``deviation`` (3), ``deviation_norm_m``,
        ``tolerance_m``, ``uncertainty_U_m``, ``decision``, ``pass``, ``sigma_m`` (the measured point's
        sqrt(trace(cov)), report.json's achieved_sigma_m): all in the covering index
        ``ix_targets_trend``, so the database reads that index alone (the measured point itself is in
        :meth:`job_targets`).
        """
        t = targets.c
        stmt = sa.select(*self._trend_columns()).where(t.part == part, t.target_id == target_id)
        if since is not None:
            stmt = stmt.where(t.finished >= user_time(since))
        if until is not None:
            stmt = stmt.where(t.finished < user_time(until, end=True))
        if limit is not None:  # the newest ``limit`` points (still returned oldest first)
            stmt = stmt.order_by(t.finished.desc(), t.job_id.desc()).limit(int(limit))
        return self._trend_points(stmt)

    def _trend_columns(self) -> list:
        t = targets.c
        return [t.job_id, t.serial, t.finished, t.deviation_x, t.deviation_y, t.deviation_z, t.deviation_norm_m,
                t.tolerance_m, t.uncertainty_u_m, t.decision, t.passed, t.achieved_sigma_m]

    def _trend_points(self, stmt) -> list[dict]:
        """The points of the trend query ``stmt`` (columns as :meth:`_trend_columns`), oldest first.

        The generic form: fetch all rows, one comprehension. A backend may let the database build them.
        """
        sq = stmt.subquery()
        rows = self._read(sa.select(sq).order_by(sq.c.finished.asc(), sq.c.job_id.asc()))
        iso = self._time_text
        return [{"job_id": r[0], "serial": r[1], "finished": iso(r[2]),
                 "deviation": None if r[3] is None else [r[3], r[4], r[5]], "deviation_norm_m": r[6],
                 "tolerance_m": r[7], "uncertainty_U_m": r[8], "decision": r[9], "pass": r[10], "sigma_m": r[11]}
                for r in rows]

    _time_text = staticmethod(_iso)

    def part_summary(self, part: str, *, since=None, until=None) -> list[dict]:
        """Per target of ``part``, over its jobs (``since <= finished < until``): one GROUP BY query.

        ``id``, ``n`` (jobs that measured it), ``mean`` and ``std`` (sample) of each deviation component
        (``deviation_mean``, ``deviation_std``: 3 each, m) and of the deviation's length
        (``norm_mean``, ``norm_std``), ``failed`` (beyond tolerance), ``nonconforming``, ``inconclusive``,
        ``undecided``. The SPC of a whole part without reading one folder; ``std`` None below two jobs.

        ``n``, the means and the spreads take only decided measurements: a target ``undecided`` (its job's
        alignment to CAD not trusted) or measured in an UNTRUSTED job deviates in a frame nobody trusts, so it is
        counted in ``undecided`` and kept out of the statistics, as the trend's Cp/Cpk keep it out
        (:mod:`cell.record.decisions`). ``failed`` counts every measured target beyond tolerance, as the jobs do.
        """
        t = targets.c
        f = sa.func
        measured = t.deviation_norm_m.is_not(None)
        # decided: measured in a frame the job trusts (an older row of an UNTRUSTED job may carry a decision)
        untrusted = sa.or_(t.decision == "undecided", jobs.c.verdict == "UNTRUSTED")
        decided = sa.and_(measured, sa.not_(sa.func.coalesce(untrusted, False)))
        comps = [sa.case((decided, c), else_=None)
                 for c in (t.deviation_x, t.deviation_y, t.deviation_z, t.deviation_norm_m)]
        stmt = (sa.select(t.target_id, f.count(comps[3]),
                          *[f.sum(c) for c in comps], *[f.sum(c * c) for c in comps],
                          f.sum(sa.case((sa.and_(measured, t.passed.is_(False)), 1), else_=0)),
                          f.sum(sa.case((sa.and_(decided, t.decision == "nonconforming"), 1), else_=0)),
                          f.sum(sa.case((sa.and_(decided, t.decision == "inconclusive"), 1), else_=0)),
                          f.sum(sa.case((sa.and_(measured, sa.not_(decided)), 1), else_=0)))
                .select_from(targets.join(jobs, jobs.c.id == t.job_id))
                .where(t.part == part).group_by(t.target_id).order_by(t.target_id))
        if since is not None:
            stmt = stmt.where(t.finished >= user_time(since))
        if until is not None:
            stmt = stmt.where(t.finished < user_time(until, end=True))
        out = []
        for r in self._read(stmt):
            n = int(r[1])
            sums, sq = [float(v or 0.0) for v in r[2:6]], [float(v or 0.0) for v in r[6:10]]
            mean = [x / n if n else None for x in sums]
            # the cancellation in q - n m^2 costs (mean/std)^2 ulps: negligible unless an offset is ~1e6 spreads
            std = [float(np.sqrt(max(q - n * m * m, 0.0) / (n - 1))) if n > 1 else None for q, m in zip(sq, mean)]
            out.append({"id": r[0], "n": n, "deviation_mean": mean[:3], "deviation_std": std[:3],
                        "norm_mean": mean[3], "norm_std": std[3], "failed": int(r[10] or 0),
                        "nonconforming": int(r[11] or 0), "inconclusive": int(r[12] or 0),
                        "undecided": int(r[13] or 0)})
        return out

    def parts(self) -> list[str]:
        stmt = sa.select(jobs.c.part).where(jobs.c.part.is_not(None)).distinct().order_by(jobs.c.part)
        return [r[0] for r in self._read(stmt)]

    def part_targets(self, part: str) -> list[str]:
        stmt = sa.select(targets.c.target_id).where(targets.c.part == part).distinct().order_by(targets.c.target_id)
        return [r[0] for r in self._read(stmt)]

    def job_ids(self, origin: str | None = None) -> set[str]:
        """The ids the index holds (of one ``origin``: a cell's folder root)."""
        stmt = sa.select(jobs.c.id)
        if origin is not None:
            stmt = stmt.where(jobs.c.origin == origin)
        return {r[0] for r in self._read(stmt)}

    def index_state(self, origin: str | None = None) -> dict[str, dict]:
        """Per job id: ``status``, ``manifest_sha256``, ``targets`` (the count the row claims) and
        ``target_rows`` (the rows present): what ``cell archive verify`` compares with the folders."""
        n = (sa.select(targets.c.job_id, sa.func.count().label("n")).group_by(targets.c.job_id).subquery())
        stmt = (sa.select(jobs.c.id, jobs.c.status, jobs.c.manifest_sha256, jobs.c.targets, jobs.c.folder,
                          jobs.c.origin, jobs.c.verdict, jobs.c.failed, n.c.n)
                .outerjoin(n, n.c.job_id == jobs.c.id))
        if origin is not None:
            stmt = stmt.where(jobs.c.origin == origin)
        return {r.id: {"status": r.status, "manifest_sha256": r.manifest_sha256, "targets": r.targets,
                       "target_rows": int(r.n or 0), "folder": r.folder, "origin": r.origin, "verdict": r.verdict,
                       "failed": r.failed}
                for r in self._read(stmt)}

    def bulk_load(self, job_rows: Iterable[dict], target_rows: Iterable[dict]) -> None:
        """Insert many prepared rows at once (benchmarks, migrations of old archives); no checks."""
        job_rows, target_rows = list(job_rows), list(target_rows)
        with self._begin() as conn:
            if job_rows:
                conn.execute(jobs.insert(), job_rows)
            if target_rows:
                conn.execute(targets.insert(), target_rows)

    def close(self) -> None:
        self.engine.dispose()


def _first_line(exc: BaseException) -> str:
    """The first line of a database error: its message, never the statement or its parameters (SQLAlchemy puts
    those on later lines, the driver's own error has none); at most 300 characters."""
    orig = getattr(exc, "orig", None) or exc
    text = str(orig).strip().splitlines()
    line = text[0] if text else type(orig).__name__
    return line if len(line) <= 300 else line[:300] + "..."
