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
                                                "application_name": "inspection-cell",
                                                "options": "-c TimeZone=UTC"})
        super().__init__(engine, u.set(drivername="postgresql").render_as_string(hide_password=True))

    def _lock_row(self, conn, job_id: str):
        return conn.execute(sa.select(jobs.c.origin).where(jobs.c.id == job_id).with_for_update()).first()

    def _trend_points(self, stmt) -> list[dict]:
        """The server builds the points as one JSON array of arrays (``json_agg``): 10,000 points cost one
        value to fetch and one ``json.loads``, not 110,000 values through the driver (a third of the
        client's time), and arrays cost the server half what objects do. Floats round-trip exactly
        (PostgreSQL prints the shortest exact form); times are ISO 8601 in UTC (the session's zone)."""
        from sqlalchemy.dialects.postgresql import aggregate_order_by

        sq = stmt.subquery()
        c = sq.c
        arr = sa.func.json_build_array(*sq.c)  # the columns of ArchiveIndex._trend_columns, in order
        rows = self._read(sa.select(sa.func.json_agg(aggregate_order_by(arr, c.finished.asc(), c.job_id.asc()))))
        return [{"job_id": r[0], "serial": r[1], "finished": r[2],
                 "deviation": None if r[3] is None else r[3:6], "deviation_norm_m": r[6],
                 "tolerance_m": r[7], "uncertainty_U_m": r[8], "decision": r[9], "pass": r[10], "sigma_m": r[11]}
                for r in rows[0][0] or []]

    def bulk_load(self, job_rows, target_rows) -> None:
        """Many prepared rows through ``COPY`` (benchmarks, importing an old archive); no checks."""
        from cell.record.archive.tables import targets

        with self._begin() as conn:
            raw = conn.connection.driver_connection
            with raw.cursor() as cur:
                for table, rows in ((jobs, job_rows), (targets, target_rows)):
                    cols = [c.name for c in table.columns]
                    with cur.copy(f"COPY {table.name} ({', '.join(cols)}) FROM STDIN") as cp:
                        for r in rows:
                            cp.write_row([r.get(c) for c in cols])

    @contextlib.contextmanager
    def _migration_guard(self):
        with self.engine.begin() as conn:
            conn.execute(sa.text("SELECT pg_advisory_xact_lock(:k)"), {"k": _MIGRATION_LOCK})
            yield conn
