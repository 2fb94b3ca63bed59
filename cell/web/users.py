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
#: login throttling: after this many failures for one name (or one client) within the window, wait
MAX_FAILURES = 5
WINDOW_S = 300.0

_SCHEMA = """
CREATE TABLE IF NOT EXISTS users (name TEXT PRIMARY KEY, role TEXT NOT NULL, hash TEXT NOT NULL, created REAL NOT NULL,
                                  disabled INTEGER NOT NULL DEFAULT 0);
CREATE TABLE IF NOT EXISTS sessions (digest TEXT PRIMARY KEY, user TEXT NOT NULL, kind TEXT NOT NULL, csrf TEXT,
                                     expires REAL NOT NULL);
CREATE TABLE IF NOT EXISTS failures (key TEXT NOT NULL, t REAL NOT NULL);
CREATE TABLE IF NOT EXISTS audit (t TEXT NOT NULL, user TEXT NOT NULL, action TEXT NOT NULL, job_id TEXT,
                                  detail TEXT);
"""


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
        if len(password) < 8:
            raise InputError("the password needs at least 8 characters")
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
    def throttled(self, *keys: str) -> float:
        """Seconds to wait before another login attempt for any of ``keys`` (0 when allowed)."""
        now = time.time()
        with self._db() as con:
            con.execute("DELETE FROM failures WHERE t < ?", (now - WINDOW_S,))
            wait = 0.0
            for k in keys:
                ts = [t for (t,) in con.execute("SELECT t FROM failures WHERE key=? ORDER BY t", (k,))]
                if len(ts) >= MAX_FAILURES:
                    wait = max(wait, ts[-MAX_FAILURES] + WINDOW_S - now)
        return wait

    def authenticate(self, name: str, password: str, client: str = "") -> User | None:
        """The user if the password is right; None otherwise (the failure counts towards throttling)."""
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
            with self._db() as con:
                con.executemany("INSERT INTO failures (key, t) VALUES (?, ?)",
                                [(f"user:{name}", time.time()), (f"client:{client}", time.time())])
            return None
        if self._ph.check_needs_rehash(row[2]):
            with self._db() as con:
                con.execute("UPDATE users SET hash=? WHERE name=?", (self._ph.hash(password), name))
        return User(row[0], row[1])

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
