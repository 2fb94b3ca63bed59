"""The site backend: a PostgreSQL server shared by the cells of a plant (psycopg 3).

Writes lock the job's row (``SELECT ... FOR UPDATE``) so that a cell catching up from its outbox
and the same cell's running job cannot interleave; migrations run under a transaction-scoped
advisory lock, so cells starting at once upgrade the schema exactly once. Connections are
checked before use (``pool_pre_ping``): a server that restarted is simply reconnected to.
"""
from __future__ import annotations

import contextlib

import sqlalchemy as sa

from cell.record.archive.index import ArchiveIndex
from cell.record.archive.tables import jobs

#: the advisory lock key of schema migrations ("cellarch" as an int64)
_MIGRATION_LOCK = 0x63656C6C61726368


def engine_url(url: str) -> sa.engine.URL:
    """``postgresql://...`` (or ``postgres://``) as SQLAlchemy's psycopg 3 URL."""
    u = sa.engine.make_url(url.replace("postgres://", "postgresql://", 1) if url.startswith("postgres://") else url)
    return u.set(drivername="postgresql+psycopg")


class PostgresIndex(ArchiveIndex):
    kind = "postgresql"

    def __init__(self, url: str, *, connect_timeout_s: int = 5):
        u = engine_url(url)
        engine = sa.create_engine(u, pool_pre_ping=True, pool_size=2, max_overflow=2,
                                  connect_args={"connect_timeout": connect_timeout_s,
                                                "application_name": "inspection-cell"})
        super().__init__(engine, u.set(drivername="postgresql").render_as_string(hide_password=True))

    def _lock_row(self, conn, job_id: str):
        return conn.execute(sa.select(jobs.c.origin).where(jobs.c.id == job_id).with_for_update()).first()

    @contextlib.contextmanager
    def _migration_guard(self):
        with self.engine.begin() as conn:
            conn.execute(sa.text("SELECT pg_advisory_xact_lock(:k)"), {"k": _MIGRATION_LOCK})
            yield conn
