"""Who is asking: sessions (browser cookie + CSRF) and bearer tokens (API), as FastAPI dependencies."""
from __future__ import annotations

import hmac
from dataclasses import dataclass
from pathlib import Path

import anyio
import anyio.to_thread
from fastapi import Depends, HTTPException, Request

from cell.web.users import MAX_PASSWORD_CHARS, Throttled, User, UserStore

#: password checks (argon2id: ~0.15 s of CPU and 64 MiB each, its four lanes in threads of their own) running at
#: once; the others queue. One: a flood of logins then takes about one core, never the whole computer
HASHERS = 1
#: threads for the logins' SQLite bookkeeping (count, uncount, open the session): their own few, so a flood of logins
#: never takes the thread pool the other routes (an operator's Abort) run in
LOGIN_THREADS = 4

COOKIE = "cell_session"


@dataclass
class Config:
    """What ``cell serve`` was told."""

    archive: Path
    programs: Path
    cell_id: str | None = None
    tls: bool = False
    chromium: str | None = None
    #: the archive's index database (``--archive-url``; None: ``CELL_ARCHIVE_URL``, else SQLite in ``archive``)
    archive_url: str | None = None


@dataclass
class Caller:
    user: User
    csrf: str | None  # the session's CSRF token (None for a bearer token: browsers never send one by themselves)
    via: str  # "session" | "token"


class Unauthorized(HTTPException):
    def __init__(self, detail: str = "log in first"):
        super().__init__(401, detail, headers={"WWW-Authenticate": "Bearer"})


def store(request: Request) -> UserStore:
    return request.app.state.users


def bearer(request: Request) -> str | None:
    """The bearer token the request presents, if any."""
    auth = request.headers.get("authorization", "")
    return auth[7:].strip() if auth.lower().startswith("bearer ") else None


def login_limiters(app) -> tuple[anyio.CapacityLimiter, anyio.CapacityLimiter]:
    """The app's limiters for the logins' bookkeeping and their password checks (made anew at each start: a limiter
    belongs to its event loop)."""
    lims = getattr(app.state, "login_limiters", None)
    if lims is None:
        lims = app.state.login_limiters = (anyio.CapacityLimiter(LOGIN_THREADS), anyio.CapacityLimiter(HASHERS))
    return lims


async def login_work(app, fn, *args):
    """``fn(*args)`` in one of the logins' own threads (SQLite: quick, but it may wait for a lock)."""
    return await anyio.to_thread.run_sync(fn, *args, limiter=login_limiters(app)[0])


async def log_in(request: Request, name: str, password: str) -> User | None:
    """The user if ``password`` is theirs, else None; 413 for an over-long password (not hashed), 429 while the name
    or the client is throttled. The attempt is counted before the password is checked (atomically: see
    ``UserStore.begin_login``); the SQLite and argon2 work runs in threads, never on the event loop."""
    if len(password) > MAX_PASSWORD_CHARS:
        raise HTTPException(413, f"password: longer than {MAX_PASSWORD_CHARS} characters")
    users: UserStore = request.app.state.users
    client = request.client.host if request.client else ""
    try:
        attempt = await login_work(request.app, users.begin_login, name, client)
    except Throttled as e:
        raise HTTPException(429, str(e), headers={"Retry-After": str(int(e.wait_s) + 1)}) from None
    user = None
    try:
        user = await anyio.to_thread.run_sync(users.check_password, name, password,
                                              limiter=login_limiters(request.app)[1])
    finally:
        await login_work(request.app, users.end_login, attempt, user is not None)
    return user


async def caller(request: Request) -> Caller:
    """The authenticated caller, or 401. A state-changing request with the session cookie needs the
    session's CSRF token (form field ``csrf`` for pages, header ``X-CSRF-Token`` for scripts)."""
    users: UserStore = request.app.state.users
    token = bearer(request)
    # the lookup reads SQLite, which may wait for a lock (a login flood writes its attempts): in a thread of the
    # default pool, never on the event loop, and not in the logins' own threads, which a flood may keep busy
    if token is not None:
        found = await anyio.to_thread.run_sync(users.session, token, "api")
        if found is None:
            raise Unauthorized("invalid or expired token")
        return Caller(found[0], None, "token")
    found = await anyio.to_thread.run_sync(users.session, request.cookies.get(COOKIE), "session")
    if found is None:
        raise Unauthorized()
    c = Caller(found[0], found[1], "session")
    if request.method not in ("GET", "HEAD", "OPTIONS"):
        sent = request.headers.get("x-csrf-token")
        ctype = request.headers.get("content-type", "")
        if not sent and ctype.startswith(("application/x-www-form-urlencoded", "multipart/form-data")):
            form = await request.form()  # cached on the request: the route reads the same form
            sent = form.get("csrf")
        if not sent or not hmac.compare_digest(sent, c.csrf or ""):
            raise HTTPException(403, "missing or wrong CSRF token: reload the page and try again")
    return c


def role(name: str):
    """A dependency: the caller, if their role is ``name`` or above; 403 otherwise."""

    def dep(c: Caller = Depends(caller)) -> Caller:
        if not c.user.can(name):
            raise HTTPException(403, f"this needs the {name} role (you are {c.user.role})")
        return c

    return dep
