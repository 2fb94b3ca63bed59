"""The embedded backend: one SQLite file next to the cell's job folders (the default, one cell).

WAL journal (readers never wait for the writer), ``BEGIN IMMEDIATE`` for writes (two writers
queue on the lock instead of deadlocking on a read lock upgrade), a 30 s busy timeout, and an
``flock`` on ``<file>.lock`` around migrations. WAL needs a local disk: a site with several cells
uses the PostgreSQL backend (:mod:`~cell.record.archive.postgres`).
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import sqlite3
import time
from pathlib import Path

import sqlalchemy as sa
from sqlalchemy import event

from cell.record.archive.index import ArchiveIndex


def _set_aside_unversioned(path: Path) -> str | None:
    """An index the migrations cannot take over is set aside (the folders rebuild it); returns its new name.

    Written before the migrations existed (a ``jobs`` table, no ``alembic_version``): renamed
    ``<name>.pre-alembic``; damaged (not a database): ``<name>.damaged-<time>``. None: kept as it is.
    A locked or unreadable file is not damage: that error is raised.
    """
    if not path.exists():
        return None
    con = sqlite3.connect(path, timeout=30)
    try:
        names = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        suffix = ".pre-alembic" if "jobs" in names and "alembic_version" not in names else None
    except sqlite3.OperationalError:
        raise
    except sqlite3.DatabaseError:  # "file is not a database", a malformed image
        suffix = f".damaged-{time.strftime('%Y%m%dT%H%M%S')}"
    finally:
        con.close()
    if suffix is None:
        return None
    aside = path.with_name(path.name + suffix)
    for side in ("-wal", "-shm"):
        p = path.with_name(path.name + side)
        if p.exists():
            if suffix.startswith(".damaged"):
                p.unlink()
            else:
                os.replace(p, aside.with_name(aside.name + side))
    os.replace(path, aside)
    return str(aside)


class SQLiteIndex(ArchiveIndex):
    kind = "sqlite"

    def __init__(self, path: Path):
        self.path = Path(path).resolve()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rebuilt_from = _set_aside_unversioned(self.path)
        engine = sa.create_engine(f"sqlite:///{self.path}", connect_args={"timeout": 30})

        @event.listens_for(engine, "connect")
        def _connect(dbapi_con, _record):
            dbapi_con.isolation_level = None  # SQLAlchemy's events below say when a transaction begins
            cur = dbapi_con.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.close()

        @event.listens_for(engine, "begin")
        def _begin(conn):
            conn.exec_driver_sql("BEGIN IMMEDIATE" if conn.get_execution_options().get("sqlite_write") else "BEGIN")

        self._writer = engine.execution_options(sqlite_write=True)
        super().__init__(engine, f"sqlite:///{self.path}")

    def _begin(self):
        from sqlalchemy import exc as sa_exc

        from cell.record.archive.index import IndexUnavailable, _first_line

        try:
            return self._writer.begin()
        except sa_exc.OperationalError as exc:
            raise IndexUnavailable(f"{self.url}: cannot write the archive index ({_first_line(exc)})") from exc

    def _trend_points(self, stmt) -> list[dict]:
        """As the generic form, but the time comes back as SQLite stores it (``YYYY-MM-DD HH:MM:SS.ffffff``,
        UTC) and is reshaped to ISO 8601 by slicing: parsing 10,000 datetimes and formatting them again
        was a third of the trend's time."""
        sq = stmt.subquery()
        cols = [sa.type_coerce(c, sa.String) if c.name == "finished" else c for c in sq.c]
        rows = self._read(sa.select(*cols).order_by(sq.c.finished.asc(), sq.c.job_id.asc()))
        return [{"job_id": r[0], "serial": r[1],
                 "finished": None if r[2] is None else f"{r[2][:10]}T{r[2][11:23]}+00:00",
                 "deviation": None if r[3] is None else [r[3], r[4], r[5]], "deviation_norm_m": r[6],
                 "tolerance_m": r[7], "uncertainty_U_m": r[8], "decision": r[9], "pass": r[10], "sigma_m": r[11]}
                for r in rows]

    @contextlib.contextmanager
    def _migration_guard(self):
        fd = os.open(f"{self.path}.lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            with self._writer.begin() as conn:
                yield conn
        finally:
            os.close(fd)
