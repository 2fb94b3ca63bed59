"""A real PostgreSQL server for the archive tests: Debian's ``postgresql`` package, started in a
temporary folder on a free port, stopped (and removed) at teardown.

``scripts/test.sh`` installs the package (as root, ``apt-get install postgresql``). The server runs
as an unprivileged user (PostgreSQL refuses root): the current user, or ``postgres`` through
``runuser`` when the tests run as root. Tests that need it take the ``pg`` fixture (import it from
this module); they are skipped, saying why, only when no server binaries are installed.
"""
from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

import pytest


def _bindir() -> Path | None:
    env = os.environ.get("CELL_PG_BINDIR")
    cands = [env] if env else sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=lambda p: int(p.split("/")[-2]))
    for d in reversed(cands):
        if d and (Path(d) / "pg_ctl").exists() and (Path(d) / "initdb").exists():
            return Path(d)
    return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PgServer:
    """One PostgreSQL cluster: ``url`` of its database ``archive``; ``stop()`` and ``start()`` it at will."""

    def __init__(self, bindir: Path):
        self.bindir = bindir
        self.port = _free_port()
        self.dir = Path(tempfile.mkdtemp(prefix="cell-pg-"))
        self.data = self.dir / "data"
        self.log = self.dir / "server.log"
        self.as_user = None
        if os.geteuid() == 0:  # the server refuses to run as root
            try:
                pwd.getpwnam("postgres")
                self.as_user = "postgres"
            except KeyError:
                raise RuntimeError("running as root and no 'postgres' user to run the server as") from None
            shutil.chown(self.dir, user=self.as_user)
        self._run("initdb", "-D", str(self.data), "-U", "cell", "--auth=trust", "-E", "UTF8", "--no-locale")
        with open(self.data / "postgresql.conf", "a") as f:
            f.write(f"port = {self.port}\nlisten_addresses = '127.0.0.1'\nunix_socket_directories = '{self.dir}'\n"
                    "max_connections = 100\nshared_buffers = 64MB\n"
                    "fsync = off\nfull_page_writes = off\n")  # a test cluster: the OS crashing is not under test
        self.start()
        self.admin_url = f"postgresql://cell@127.0.0.1:{self.port}/postgres"
        import psycopg

        with psycopg.connect(self.admin_url, autocommit=True) as con:
            con.execute("CREATE DATABASE archive")
        self.url = f"postgresql://cell@127.0.0.1:{self.port}/archive"

    def _run(self, tool: str, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        cmd = [str(self.bindir / tool), *args]
        if self.as_user:
            cmd = ["runuser", "-u", self.as_user, "--", *cmd]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=self.dir)
        if check and r.returncode != 0:
            raise RuntimeError(f"{tool} failed ({r.returncode}): {r.stderr.strip() or r.stdout.strip()}"
                               + (f"\n{self.log.read_text()[-2000:]}" if self.log.exists() else ""))
        return r

    def start(self) -> None:
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.log), "-w", "-t", "60", "start")

    def stop(self, mode: str = "fast") -> None:
        self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "-t", "60", "stop")

    def running(self) -> bool:
        return self._run("pg_ctl", "-D", str(self.data), "status", check=False).returncode == 0

    def reset(self) -> None:
        """Empty the archive database (drop and create) between tests."""
        import psycopg

        with psycopg.connect(self.admin_url, autocommit=True) as con:
            con.execute("DROP DATABASE IF EXISTS archive WITH (FORCE)")
            con.execute("CREATE DATABASE archive")

    def close(self) -> None:
        if self.running():
            self.stop("immediate")
        shutil.rmtree(self.dir, ignore_errors=True)


_SERVER: list[PgServer] = []  # one server per test session, whichever modules import the fixture


@pytest.fixture(scope="session")
def pg_server():
    bindir = _bindir()
    if bindir is None:
        pytest.skip("no PostgreSQL server installed (Debian package 'postgresql'; scripts/test.sh installs it as root)")
    if not _SERVER:
        _SERVER.append(PgServer(bindir))
    yield _SERVER[0]
    # every module's copy of this fixture ends with the session: the first to end stops the server
    if _SERVER:
        _SERVER.pop().close()


@pytest.fixture
def pg(pg_server):
    """The session's server with an empty ``archive`` database, running."""
    if not pg_server.running():
        pg_server.start()
    pg_server.reset()
    return pg_server
