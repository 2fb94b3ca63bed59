"""Who is asking: sessions (browser cookie + CSRF) and bearer tokens (API), as FastAPI dependencies."""
from __future__ import annotations

import hmac
from dataclasses import dataclass
from pathlib import Path

from fastapi import Depends, HTTPException, Request

from cell.web.users import User, UserStore

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


async def caller(request: Request) -> Caller:
    """The authenticated caller, or 401. A state-changing request with the session cookie needs the
    session's CSRF token (form field ``csrf`` for pages, header ``X-CSRF-Token`` for scripts)."""
    users: UserStore = request.app.state.users
    auth = request.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        found = users.session(auth[7:].strip(), "api")
        if found is None:
            raise Unauthorized("invalid or expired token")
        return Caller(found[0], None, "token")
    found = users.session(request.cookies.get(COOKIE), "session")
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
