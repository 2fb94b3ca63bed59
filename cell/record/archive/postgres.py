"""The site backend: a PostgreSQL server shared by the cells of a plant (psycopg 3).

Writes lock the job's row (``SELECT ... FOR UPDATE``) so that a cell catching up from its outbox
and the same cell's running job cannot interleave; migrations run under a transaction-scoped
advisory lock, so cells starting at once upgrade the schema exactly once. Connections are
checked before use (a ping at checkout): a server that restarted is simply reconnected to.

**Every operation is bounded** (a server that stops answering must not halt a running job):

* the server gives up a statement after ``statement_timeout`` (5 s) and a lock wait after ``lock_timeout``
  (3 s: another session holding the job's row), sent as the session's ``options``;
* a new connection gives up after ``connect_timeout`` (5 s); TCP keepalives (idle 5 s, every 2 s, 3 probes)
  and ``tcp_user_timeout`` (10 s) drop a connection whose host vanished (a network partition);
* a server that accepts packets but whose process answers nothing (stopped, swapped out, hung) is bounded
  here, on the client: every write and read (and the ping before it) runs under a watchdog that shuts the
  connection's socket after :attr:`PostgresIndex.BOUND_S` (10 s; ``CELL_ARCHIVE_TIMEOUT_S``), so the
  blocked call returns with an error.

Each of these raises :class:`~cell.record.archive.index.IndexUnavailable`: the job's write goes to the
outbox within seconds and the job goes on. Schema migrations get 60 s (lock and statement) and a 90 s watchdog.
"""
from __future__ import annotations

import contextlib
import os
import socket
import threading

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy import exc as sa_exc

from cell.record.archive.index import ArchiveIndex, _first_line
from cell.record.archive.tables import jobs
from cell.record.archive.urls import mask_url

#: the server's own bounds (milliseconds), sent at connect
STATEMENT_TIMEOUT_MS = 5000
LOCK_TIMEOUT_MS = 3000
#: TCP: keepalive probes after 5 s idle, every 2 s, 3 unanswered drop it; unacknowledged data for 10 s drops it
KEEPALIVES = {"keepalives": 1, "keepalives_idle": 5, "keepalives_interval": 2, "keepalives_count": 3,
              "tcp_user_timeout": 10000}


class _Op:
    """One bounded operation: the connections it checked out, and whether its watchdog fired."""

    def __init__(self):
        self.conns: list = []
        self.fired = False
        self.lock = threading.Lock()

    def cut(self) -> None:
        """The watchdog: shut the sockets of this operation's connections (the blocked call then fails)."""
        with self.lock:
            self.fired = True
            conns = list(self.conns)
        for c in conns:
            try:
                fd = (getattr(c, "pgconn", None) or c.driver_connection.pgconn).socket
                s = socket.socket(fileno=os.dup(fd))
                try:
                    s.shutdown(socket.SHUT_RDWR)
                finally:
                    s.close()
            except Exception:  # noqa: BLE001  a connection already closed: nothing to cut
                pass

#: the advisory lock key of schema migrations ("cellarch" as an int64)
_MIGRATION_LOCK = 0x63656C6C61726368


def engine_url(url: str) -> sa.engine.URL:
    """``postgresql://...`` (or ``postgres://``) as SQLAlchemy's psycopg 3 URL.

    The user info ends at the last '@' (as libpq reads it), so a password with an unescaped '@' is the password,
    not the start of a host name that an error would then show."""
    from urllib.parse import quote, unquote

    from cell.record.archive.urls import _SCHEME, _split

    m = _SCHEME.match(url)
    if m:
        info, rest = _split(m.group(2))
        if info is not None:
            user, sep, pw = info.partition(":")
            info = quote(unquote(user), safe="") + (":" + quote(unquote(pw), safe="") if sep else "")
            url = f"{m.group(1)}{info}@{rest}"
    u = sa.engine.make_url(url.replace("postgres://", "postgresql://", 1) if url.startswith("postgres://") else url)
    return u.set(drivername="postgresql+psycopg")


class PostgresIndex(ArchiveIndex):
    kind = "postgresql"
    #: the client's bound of one write or read, ping included (seconds; see the module's docstring)
    BOUND_S = float(os.environ.get("CELL_ARCHIVE_TIMEOUT_S", "10"))
    MIGRATION_BOUND_S = 90.0

    def __init__(self, url: str, *, connect_timeout_s: int = 5):
        u = engine_url(url)
        engine = sa.create_engine(u, pool_size=2, max_overflow=2,
                                  connect_args={"connect_timeout": connect_timeout_s,
                                                "application_name": "inspection-cell",
                                                "options": f"-c TimeZone=UTC -c statement_timeout={STATEMENT_TIMEOUT_MS} "
                                                           f"-c lock_timeout={LOCK_TIMEOUT_MS}",
                                                **KEEPALIVES})
        self._ops = threading.local()

        @event.listens_for(engine, "checkout")
        def _checkout(dbapi_con, _record, _proxy):
            """Register the connection with the running operation's watchdog, then ping it (a server that
            restarted: a fresh connection is made; one that hangs: the watchdog cuts the ping)."""
            op = getattr(self._ops, "op", None)
            if op is not None:
                with op.lock:
                    op.conns.append(dbapi_con)
            try:
                ok = engine.dialect.do_ping(dbapi_con)
            except Exception as exc:  # noqa: BLE001  a dead connection: let the pool make a new one
                if op is not None and op.fired:
                    raise
                raise sa_exc.DisconnectionError(_first_line(exc)) from exc
            if not ok:
                raise sa_exc.DisconnectionError("the ping failed")

        super().__init__(engine, mask_url(url))

    @contextlib.contextmanager
    def _bounded(self, seconds: float | None = None):
        """The operation inside gives up after ``seconds`` (default :attr:`BOUND_S`): its sockets are shut."""
        seconds = self.BOUND_S if seconds is None else seconds
        if getattr(self._ops, "op", None) is not None or not seconds or seconds <= 0:  # nested: the outer bounds it
            yield
            return
        op = _Op()
        self._ops.op = op
        timer = threading.Timer(seconds, op.cut)
        timer.daemon = True
        timer.start()
        try:
            yield
        finally:
            timer.cancel()
            self._ops.op = None
            self._ops.last_fired = op.fired

    def _why(self, exc: BaseException) -> str:
        op = getattr(self._ops, "op", None)
        if (op is not None and op.fired) or getattr(self._ops, "last_fired", False):
            self._ops.last_fired = False
            return f"no answer within {self.BOUND_S:g} s; the connection was dropped"
        return _first_line(exc)

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
            conn.execute(sa.text("SET LOCAL statement_timeout = 0"))  # a bulk load may take minutes
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
            conn.execute(sa.text("SET LOCAL lock_timeout = '60s'"))  # another cell migrating: wait for it
            conn.execute(sa.text("SET LOCAL statement_timeout = '60s'"))
            conn.execute(sa.text("SELECT pg_advisory_xact_lock(:k)"), {"k": _MIGRATION_LOCK})
            yield conn
