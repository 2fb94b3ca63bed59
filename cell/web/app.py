"""The console's ASGI application: FastAPI, one router for pages and one for the API."""
from __future__ import annotations

from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.templating import Jinja2Templates
from starlette.exceptions import HTTPException as StarletteHTTPException

from calibration.errors import InputError
from cell.record.archive import IndexRefused, IndexUnavailable, scrub
from cell.web import api, pages
from cell.web.deps import Config
from cell.web.runner import Busy
from cell.web.service import Console
from cell.web.store import NotFound
from cell.web.users import UserStore

TEMPLATES = Path(__file__).parent / "templates"
#: the routes that read a body before anyone is authenticated, and the most they read (bytes): beyond it, 413
LOGIN_ROUTES = ("/login", "/api/token")
LOGIN_BODY_MAX = 64 * 1024
#: what a page may load: only from the console itself (no other site, no framing, forms post only here). Inline
#: scripts stay allowed ('unsafe-inline': the pages and report.html carry theirs), as does eval (plotly's 3-D views
#: compile their WebGL code at run time), so this limits where a page loads from and sends to, not script injection
#: (the templates' escaping does that).
CSP = ("default-src 'self'; script-src 'self' 'unsafe-inline' 'unsafe-eval' blob:; style-src 'self' 'unsafe-inline'; "
       "img-src 'self' data: blob:; font-src 'self' data:; connect-src 'self' data: blob:; worker-src 'self' blob:; "
       "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")


class BodyLimit:
    """ASGI middleware: a request to ``paths`` whose body is over ``limit`` bytes is refused with 413, by its
    Content-Length before a byte is read, else (chunked) as soon as the bytes read pass the limit. Only the
    login routes: every other route reads its body after authenticating the caller."""

    def __init__(self, app, paths: tuple[str, ...], limit: int):
        self.app, self.paths, self.limit = app, paths, limit

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["path"] not in self.paths:
            return await self.app(scope, receive, send)
        too_big = StarletteHTTPException(413, f"request body: more than {self.limit} bytes")
        length = dict(scope["headers"]).get(b"content-length")
        declared = int(length) if length is not None and length.isdigit() else None
        seen = 0

        async def limited():
            nonlocal seen
            if declared is not None and declared > self.limit:
                raise too_big
            msg = await receive()
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > self.limit:
                    raise too_big
            return msg

        await self.app(scope, limited, send)


def _wants_html(request: Request) -> bool:
    return not request.url.path.startswith("/api/") and "text/html" in request.headers.get("accept", "")


def _error(request: Request, status: int, message: str, headers=None):
    if _wants_html(request):
        t = request.app.state.templates
        return t.TemplateResponse(request, "error.html", {"status": status, "message": message, "me": None,
                                                          "csrf": "", "running": None},
                                  status_code=status, headers=headers)
    return JSONResponse({"detail": message}, status_code=status, headers=headers)


def create_app(config: Config) -> FastAPI:
    archive = Path(config.archive).resolve()
    archive.mkdir(parents=True, exist_ok=True)
    users = UserStore(archive / "console.sqlite")
    console = Console(archive, config.programs, users, config.cell_id, config.chromium, config.archive_url)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        app.state.login_limiters = None  # made anew on this event loop at first use (deps.login_limiters)
        console.view.refresh()
        yield
        try:
            console.runner.close()
        finally:
            console.view.close()

    app = FastAPI(title="Inspection cell console", lifespan=lifespan, docs_url=None, redoc_url=None,
                  openapi_url=None)
    app.state.config = config
    app.state.users = users
    app.state.console = console
    app.state.templates = Jinja2Templates(directory=str(TEMPLATES))
    app.include_router(api.router)
    app.include_router(pages.router)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException):
        return _error(request, exc.status_code, str(exc.detail), getattr(exc, "headers", None))

    @app.exception_handler(Busy)
    async def busy(request: Request, exc: Busy):
        return _error(request, 409, str(exc))

    @app.exception_handler(NotFound)
    async def not_found(request: Request, exc: NotFound):
        return _error(request, 404, str(exc))

    @app.exception_handler(IndexUnavailable)
    async def archive_down(request: Request, exc: IndexUnavailable):
        # the site database is away: say so (503, retry later), no traceback in the log, never a password
        return _error(request, 503, f"the site archive is not reachable: {scrub(exc, config.archive_url)}",
                      {"Retry-After": "10"})

    @app.exception_handler(IndexRefused)
    async def archive_refused(request: Request, exc: IndexRefused):
        return _error(request, 503, f"the site archive refused the query: {scrub(exc, config.archive_url)}")

    @app.exception_handler(InputError)
    async def bad_input(request: Request, exc: InputError):
        return _error(request, 400, str(exc))

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, exc: RequestValidationError):
        # never echo the input back (it may hold a password): only where and what
        msg = "; ".join(f"{'.'.join(str(x) for x in e['loc'])}: {e['msg']}" for e in exc.errors())
        return _error(request, 422, msg)

    # inside the headers middleware (added before it): its 413, raised where the route reads the body, is answered
    # by the exception handlers like any other error
    app.add_middleware(BodyLimit, paths=LOGIN_ROUTES, limit=LOGIN_BODY_MAX)

    @app.middleware("http")
    async def headers(request: Request, call_next):
        r = await call_next(request)
        r.headers.setdefault("X-Content-Type-Options", "nosniff")
        r.headers.setdefault("X-Frame-Options", "DENY")
        r.headers.setdefault("Referrer-Policy", "same-origin")
        # pages and JSON hold the archive's data and the session's CSRF token: no copy in any cache (the static
        # assets set their own, private, Cache-Control)
        r.headers.setdefault("Cache-Control", "no-store")
        r.headers.setdefault("Content-Security-Policy", CSP)
        if config.tls:
            r.headers.setdefault("Strict-Transport-Security", "max-age=31536000")
        return r

    return app


__all__ = ["create_app", "Config", "HTMLResponse"]
