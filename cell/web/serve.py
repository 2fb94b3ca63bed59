"""``cell serve`` and ``cell users ...``: the console's commands."""
from __future__ import annotations

import getpass
import os
import sys
from pathlib import Path

from calibration.errors import InputError


#: the address(es) of a reverse proxy in front of the console, comma-separated: only then is X-Forwarded-For read
PROXY_ENV = "CELL_TRUSTED_PROXY"


def serve(args, out) -> int:
    """Serve the console. A client's address (the login throttle's per-client key) is the TCP peer's:
    X-Forwarded-For is ignored (uvicorn would trust it from 127.0.0.1, so anything on this computer, or a proxy on it
    that passes the header through, could claim any address), unless ``$CELL_TRUSTED_PROXY`` names the proxy."""
    import uvicorn

    from cell.web.app import create_app
    from cell.web.deps import Config

    if (args.certfile is None) != (args.keyfile is None):
        raise InputError("TLS needs both --certfile and --keyfile")
    for p in (args.certfile, args.keyfile):
        if p is not None and not Path(p).is_file():
            raise InputError(f"{p}: no such file")
    tls = args.certfile is not None
    if args.host not in ("127.0.0.1", "localhost", "::1") and not tls:
        out.say(f"warning: serving on {args.host} without TLS: passwords and sessions cross the network in clear")
    from cell.record.archive import resolve_url
    from cell.record.archive.urls import mask_url

    url = resolve_url(getattr(args, "archive_url", None), Path(args.archive))  # --archive-url, else CELL_ARCHIVE_URL
    cfg = Config(archive=Path(args.archive), programs=Path(args.programs), cell_id=args.cell_id or os.environ.get("CELL_ID"),
                 tls=tls, archive_url=url)
    app = create_app(cfg)
    if not app.state.users.users():
        out.say(f"no users yet: add one with  cell users add NAME --role admin --archive {args.archive}")
    scheme = "https" if tls else "http"
    out.say(f"console on {scheme}://{args.host}:{args.port}/  (archive {cfg.archive}, index "
            f"{mask_url(url)}, programs {cfg.programs})")
    proxy = os.environ.get(PROXY_ENV, "").strip()
    if proxy:
        out.say(f"behind a proxy at {proxy}: its X-Forwarded-For names the client")
    uvicorn.run(app, host=args.host, port=args.port, ssl_certfile=args.certfile, ssl_keyfile=args.keyfile,
                log_level="warning", access_log=False, server_header=False,
                proxy_headers=bool(proxy), forwarded_allow_ips=proxy or None)
    return 0


def _read_password(out) -> str:
    if sys.stdin.isatty():
        a = getpass.getpass("password: ")
        b = getpass.getpass("again: ")
        if a != b:
            raise InputError("the two passwords differ")
        return a
    line = sys.stdin.readline()
    return line.rstrip("\r\n")


def users(args, out) -> int:
    from cell.web.users import UserStore

    store = UserStore(Path(args.archive).resolve() / "console.sqlite")
    if args.action == "list":
        rows = [{"name": u.name, "role": u.role} for u in store.users()]
        out.result({"users": rows}, lambda d: [out.say(f"{r['name']:<24} {r['role']}") for r in d["users"]])
        return 0
    if not args.name:
        raise InputError(f"cell users {args.action} needs a NAME")
    if args.action == "remove":
        store.remove(args.name)
        store.audit(_who(), "remove user", None, args.name)
        out.result({"removed": args.name}, lambda d: out.say(f"removed {args.name}"))
        return 0
    if args.role is None:
        raise InputError("cell users add needs --role operator|engineer|admin")
    u = store.add(args.name, args.role, _read_password(out), replace=args.action == "passwd")
    store.audit(_who(), "add user" if args.action == "add" else "set password", None, f"{u.name} ({u.role})")
    out.result({"name": u.name, "role": u.role}, lambda d: out.say(f"{d['name']}: {d['role']}"))
    return 0


def _who() -> str:
    try:
        return f"cli:{getpass.getuser()}"
    except (KeyError, OSError):
        return "cli"
