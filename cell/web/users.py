"""Accounts, sessions, API tokens, login throttling and the audit trail: one SQLite file in the archive.

Passwords are stored only as argon2id hashes (argon2-cffi's defaults, RFC 9106 low-memory profile).
Session ids and API tokens are random 256-bit strings handed to the client once; the store keeps
only their SHA-256, so a copy of the file does not let anyone in.
"""
from __future__ import annotations

import hashlib
import os
import secrets
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError

from calibration.errors import InputError

ROLES = ("operator", "engineer", "admin")
#: what each role may do (a role has the rights of the ones before it)
RANK = {r: k for k, r in enumerate(ROLES)}
SESSION_S = 12 * 3600
TOKEN_S = 30 * 24 * 3600
#: login throttling: after this many failed attempts for one user name within the window, wait
MAX_FAILURES = 5
#: ... or from one client address (more room: operators behind one shared address must not lock each other out)
MAX_CLIENT_FAILURES = 20
WINDOW_S = 300.0
#: a longer password is refused before it is hashed (argon2 hashes whatever it is given)
MAX_PASSWORD_CHARS = 1024

_SCHEMA = """
CREATE TABLE IF NOT EXISTS users (name TEXT PRIMARY KEY, role TEXT NOT NULL, hash TEXT NOT NULL, created REAL NOT NULL,
                                  disabled INTEGER NOT NULL DEFAULT 0);
CREATE TABLE IF NOT EXISTS sessions (digest TEXT PRIMARY KEY, user TEXT NOT NULL, kind TEXT NOT NULL, csrf TEXT,
                                     expires REAL NOT NULL);
CREATE TABLE IF NOT EXISTS failures (key TEXT NOT NULL, t REAL NOT NULL);
CREATE TABLE IF NOT EXISTS audit (t TEXT NOT NULL, user TEXT NOT NULL, action TEXT NOT NULL, job_id TEXT,
                                  detail TEXT);
"""


class Throttled(Exception):
    """Too many failed logins for this name or client: a control-flow signal (HTTP 429), not a fault."""

    def __init__(self, wait_s: float):
        super().__init__(f"too many failed logins: try again in {wait_s:.0f} s")
        self.wait_s = wait_s


@dataclass(frozen=True)
class User:
    name: str
    role: str

    def can(self, role: str) -> bool:
        return RANK[self.role] >= RANK[role]


def _digest(secret: str) -> str:
    return hashlib.sha256(secret.encode()).hexdigest()


def check_name(name: str) -> str:
    n = (name or "").strip()
    if not (1 <= len(n) <= 64) or not all(c.isalnum() or c in "._-@" for c in n):
        raise InputError(f"user name {name!r}: 1 to 64 letters, digits or . _ - @")
    return n


class UserStore:
    """``<archive>/console.sqlite``: users, sessions, tokens, login failures, audit."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._ph = PasswordHasher()  # argon2id
        if not self.path.exists():  # readable by its owner only; SQLite gives its -wal/-shm files the same mode
            os.close(os.open(self.path, os.O_WRONLY | os.O_CREAT, 0o600))
        self.path.chmod(0o600)
        with self._db() as con:
            con.executescript(_SCHEMA)

    def _db(self) -> sqlite3.Connection:
        con = sqlite3.connect(self.path, timeout=10)
        con.execute("PRAGMA journal_mode=WAL")
        return con

    # --- users ------------------------------------------------------------
    def add(self, name: str, role: str, password: str, *, replace: bool = False) -> User:
        name = check_name(name)
        if role not in ROLES:
            raise InputError(f"role {role!r}: one of {', '.join(ROLES)}")
        if not 8 <= len(password) <= MAX_PASSWORD_CHARS:
            raise InputError(f"the password needs 8 to {MAX_PASSWORD_CHARS} characters")
        h = self._ph.hash(password)
        with self._db() as con:
            exists = con.execute("SELECT 1 FROM users WHERE name=?", (name,)).fetchone()
            if exists and not replace:
                raise InputError(f"user {name!r} exists already")
            con.execute("INSERT OR REPLACE INTO users (name, role, hash, created) VALUES (?,?,?,?)",
                        (name, role, h, time.time()))
            if exists:  # a new password or role ends the old sessions
                con.execute("DELETE FROM sessions WHERE user=?", (name,))
        return User(name, role)

    def remove(self, name: str) -> None:
        with self._db() as con:
            if not con.execute("DELETE FROM users WHERE name=?", (name,)).rowcount:
                raise InputError(f"no user {name!r}")
            con.execute("DELETE FROM sessions WHERE user=?", (name,))

    def users(self) -> list[User]:
        with self._db() as con:
            return [User(n, r) for n, r in con.execute("SELECT name, role FROM users ORDER BY name")]

    def get(self, name: str) -> User | None:
        with self._db() as con:
            row = con.execute("SELECT name, role FROM users WHERE name=? AND disabled=0", (name,)).fetchone()
        return User(*row) if row else None

    # --- login --------------------------------------------------------------
    def begin_login(self, name: str, client: str = "") -> tuple[int, ...]:
        """Count one login attempt for ``name`` and ``client`` *before* its password is checked.

        Check and count are one transaction (``BEGIN IMMEDIATE``: concurrent attempts, from this process or
        another, queue for it), so however many arrive at once, at most the limit are ever evaluated. Raises
        :class:`Throttled` when the name has :data:`MAX_FAILURES` or the client :data:`MAX_CLIENT_FAILURES`
        attempts in the last :data:`WINDOW_S`; else returns the attempt's rows for :meth:`end_login`.
        """
        keys = ((f"user:{name}", MAX_FAILURES), (f"client:{client}", MAX_CLIENT_FAILURES))
        now = time.time()
        con = sqlite3.connect(self.path, timeout=30, isolation_level=None)
        try:
            con.execute("BEGIN IMMEDIATE")
            try:
                con.execute("DELETE FROM failures WHERE t < ?", (now - WINDOW_S,))
                wait = None
                for key, limit in keys:
                    ts = [t for (t,) in con.execute("SELECT t FROM failures WHERE key=? ORDER BY t", (key,))]
                    if len(ts) >= limit:
                        wait = max(wait or 0.0, ts[-limit] + WINDOW_S - now, 1.0)
                rows = () if wait is not None else tuple(
                    con.execute("INSERT INTO failures (key, t) VALUES (?, ?)", (key, now)).lastrowid for key, _ in keys)
                con.execute("COMMIT")
            except BaseException:
                if con.in_transaction:
                    con.execute("ROLLBACK")
                raise
        finally:
            con.close()
        if wait is not None:
            raise Throttled(wait)
        return rows

    def end_login(self, attempt: tuple[int, ...], ok: bool) -> None:
        """A right password uncounts its attempt; a wrong one stays counted as a failure."""
        if ok and attempt:
            with self._db() as con:
                con.executemany("DELETE FROM failures WHERE rowid=?", [(r,) for r in attempt])

    def check_password(self, name: str, password: str) -> User | None:
        """The user if the password is right, else None; argon2 (blocking, ~0.15 s and 64 MiB: keep it off an
        event loop). A password longer than :data:`MAX_PASSWORD_CHARS` is wrong without being hashed."""
        if len(password) > MAX_PASSWORD_CHARS:
            return None
        with self._db() as con:
            row = con.execute("SELECT name, role, hash FROM users WHERE name=? AND disabled=0", (name,)).fetchone()
        ok = False
        if row is not None:
            try:
                ok = self._ph.verify(row[2], password)
            except (VerificationError, InvalidHashError):
                ok = False
        else:
            try:  # the same work for an unknown name: timing does not tell which names exist
                self._ph.verify(self._dummy(), password)
            except (VerificationError, InvalidHashError):
                pass
        if not ok:
            return None
        if self._ph.check_needs_rehash(row[2]):
            with self._db() as con:
                con.execute("UPDATE users SET hash=? WHERE name=?", (self._ph.hash(password), name))
        return User(row[0], row[1])

    def authenticate(self, name: str, password: str, client: str = "") -> User | None:
        """The user if the password is right; None otherwise (the attempt counts towards throttling).
        Raises :class:`Throttled` without checking the password when the name or the client is at its limit."""
        attempt = self.begin_login(name, client)
        user = None
        try:
            user = self.check_password(name, password)
        finally:
            self.end_login(attempt, user is not None)
        return user

    _dummy_hash: str | None = None

    def _dummy(self) -> str:
        if UserStore._dummy_hash is None:
            UserStore._dummy_hash = self._ph.hash(secrets.token_urlsafe(16))
        return UserStore._dummy_hash

    # --- sessions and tokens --------------------------------------------------
    def open_session(self, user: User, kind: str = "session") -> tuple[str, str]:
        """A new session (browser) or token (API): ``(secret, csrf)``; the secret is not stored."""
        secret, csrf = secrets.token_urlsafe(32), secrets.token_urlsafe(32)
        ttl = SESSION_S if kind == "session" else TOKEN_S
        with self._db() as con:
            con.execute("DELETE FROM sessions WHERE expires < ?", (time.time(),))
            con.execute("INSERT INTO sessions (digest, user, kind, csrf, expires) VALUES (?,?,?,?,?)",
                        (_digest(secret), user.name, kind, csrf, time.time() + ttl))
        return secret, csrf

    def session(self, secret: str | None, kind: str) -> tuple[User, str] | None:
        """The user and CSRF token of a live session or token, else None."""
        if not secret:
            return None
        with self._db() as con:
            row = con.execute("SELECT s.user, u.role, s.csrf FROM sessions s JOIN users u ON u.name = s.user "
                              "WHERE s.digest=? AND s.kind=? AND s.expires > ? AND u.disabled=0",
                              (_digest(secret), kind, time.time())).fetchone()
        return (User(row[0], row[1]), row[2]) if row else None

    def close_session(self, secret: str) -> None:
        with self._db() as con:
            con.execute("DELETE FROM sessions WHERE digest=?", (_digest(secret),))

    # --- audit ------------------------------------------------------------------
    def audit(self, user: str, action: str, job_id: str | None = None, detail: str = "") -> dict:
        from cell.record.jobfolder import utc_now

        rec = {"t": utc_now(), "user": user, "action": action, "job_id": job_id, "detail": detail}
        with self._db() as con:
            con.execute("INSERT INTO audit (t, user, action, job_id, detail) VALUES (?,?,?,?,?)",
                        (rec["t"], user, action, job_id, detail))
        return rec

    def last_actions(self, action: str) -> dict[str, dict]:
        """Per job, the latest audit record of ``action`` (e.g. who signed each job off, and when)."""
        with self._db() as con:
            rows = con.execute("SELECT job_id, user, t FROM audit WHERE action=? AND job_id IS NOT NULL ORDER BY t",
                               (action,)).fetchall()
        return {j: {"user": u, "t": t} for j, u, t in rows}

    def audit_log(self, job_id: str | None = None, limit: int = 200) -> list[dict]:
        q = "SELECT t, user, action, job_id, detail FROM audit"
        args: tuple = ()
        if job_id is not None:
            q += " WHERE job_id=?"
            args = (job_id,)
        with self._db() as con:
            rows = con.execute(q + " ORDER BY t DESC LIMIT ?", (*args, limit)).fetchall()
        return [dict(zip(("t", "user", "action", "job_id", "detail"), r)) for r in rows]
