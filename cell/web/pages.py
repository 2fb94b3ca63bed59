"""The pages: login, the operator's screen and live job view, the archive, trends, programs, users."""
from __future__ import annotations

import json
from pathlib import Path

from fastapi import APIRouter, Depends, Form, HTTPException, Request
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse, Response

from cell.web.deps import COOKIE, Caller, bearer, caller, log_in, login_work, role
from cell.web.service import latest_image_jpeg, trend
from cell.web.store import job_folder, reverifications
from cell.web.users import ROLES

router = APIRouter()
STATIC = Path(__file__).parent / "static"


def _render(request: Request, template: str, c: Caller | None, status_code: int = 200, /, **ctx) -> HTMLResponse:
    t = request.app.state.templates
    return t.TemplateResponse(request, template, {"me": c.user if c else None, "csrf": c.csrf if c else "",
                                              "running": request.app.state.console.running() if c else None, **ctx},
                              status_code=status_code)


def _console(request: Request):
    return request.app.state.console


def _script_json(doc) -> str:
    """JSON to put inside a <script> element: no '<', '>' or '&' that could end it (ids come from files)."""
    return (json.dumps(doc, default=float).replace("<", "\\u003c").replace(">", "\\u003e")
            .replace("&", "\\u0026"))


#: the only messages a page shows from its ``?msg=`` (a code the console itself puts in its redirects): any other
#: text in the URL is ignored, so a link cannot make the console say what its sender wants
MESSAGES = {
    "login": {"logged-out": "You are logged out.", "expired": "Your session has ended: log in again."},
    "console": {},
    "program": {"saved": "Saved."},
}


def _message(page: str, code: str) -> str:
    return MESSAGES[page].get(code, "")


# --- login ---------------------------------------------------------------------------------
@router.get("/login", response_class=HTMLResponse)
def login_page(request: Request, msg: str = ""):
    return _render(request, "login.html", None, msg=_message("login", msg))


@router.post("/login")
async def login(request: Request, username: str = Form(""), password: str = Form("")):
    try:
        user = await log_in(request, username, password)
    except HTTPException as e:
        if e.status_code != 429:
            raise
        wait = int(e.headers["Retry-After"])
        return _render(request, "login.html", None, 429, msg=f"Too many failed attempts: wait {wait} s and try again.")
    if user is None:
        return _render(request, "login.html", None, 401, msg="Wrong user name or password.")
    users = request.app.state.users

    def open_session() -> str:
        secret, _ = users.open_session(user, "session")
        users.audit(user.name, "log in")
        return secret

    secret = await login_work(request.app, open_session)
    r = RedirectResponse("/", status_code=303)
    r.set_cookie(COOKIE, secret, httponly=True, samesite="strict", secure=request.app.state.config.tls, path="/")
    return r


@router.post("/logout")
def logout(request: Request, c: Caller = Depends(caller)):
    """Ends the session, or the bearer token the request presents (it would otherwise stay valid for 30 days)."""
    request.app.state.users.close_session(bearer(request) or request.cookies.get(COOKIE, ""))
    request.app.state.users.audit(c.user.name, "token revoked" if c.via == "token" else "log out")
    r = RedirectResponse("/login?msg=logged-out", status_code=303)
    r.delete_cookie(COOKIE, path="/")
    return r


@router.get("/static/{name}")
def static(name: str, c: Caller = Depends(caller)):
    if name == "plotly.min.js":
        import plotly

        return FileResponse(Path(plotly.__file__).parent / "package_data" / "plotly.min.js",
                            media_type="text/javascript", headers={"Cache-Control": "private, max-age=86400"})
    files = {p.name: p for p in STATIC.iterdir()}
    if name not in files:
        raise HTTPException(404, "no such file")
    return FileResponse(files[name], headers={"Cache-Control": "private, max-age=3600"})


# --- operator -------------------------------------------------------------------------------
@router.get("/", response_class=HTMLResponse)
def console_page(request: Request, c: Caller = Depends(caller), msg: str = "", program: str = ""):
    con = _console(request)
    recent = con.view.list_jobs(limit=8)
    return _render(request, "console.html", c, programs=sorted(con.programs()), recent=recent, msg=_message("console", msg),
                   chosen=program, programs_dir=str(con.programs_dir))


@router.post("/jobs")
def start(request: Request, program: str = Form(...), serial: str = Form(""), placed: str = Form(""),
          c: Caller = Depends(role("operator"))):
    job_id = _console(request).start(program, serial, c.user.name, placed=placed == "yes")
    return RedirectResponse(f"/jobs/{job_id}", status_code=303)


@router.get("/jobs/{job_id}", response_class=HTMLResponse)
def job_page(request: Request, job_id: str, c: Caller = Depends(caller)):
    con = _console(request)
    doc = con.status(job_id)
    return _render(request, "job.html", c, job=doc, job_id=job_id,
                   audit=request.app.state.users.audit_log(job_id))


@router.get("/jobs/{job_id}/image.jpg")
def job_image(request: Request, job_id: str, c: Caller = Depends(caller)):
    folder = _console(request).runner.folder_of(job_id)
    if folder is None:
        job_folder(_console(request).root, job_id)
    jpg = latest_image_jpeg(folder) if folder else None
    if jpg is None:
        raise HTTPException(404, "no image yet")
    return Response(jpg, media_type="image/jpeg", headers={"Cache-Control": "no-store"})


def _action(request: Request, job_id: str, what: str, c: Caller, note: str = ""):
    con = _console(request)
    if what == "resume":
        con.resume(job_id, c.user.name)
    elif what == "abort":
        con.abort(job_id, c.user.name)
    elif what == "acknowledge":
        con.acknowledge(job_id, c.user.name, note)
    elif what == "signoff":
        con.sign_off(job_id, c.user.name, note)
    return RedirectResponse(f"/jobs/{job_id}", status_code=303)


@router.post("/jobs/{job_id}/resume")
def resume(request: Request, job_id: str, c: Caller = Depends(role("operator"))):
    return _action(request, job_id, "resume", c)


@router.post("/jobs/{job_id}/abort")
def abort(request: Request, job_id: str, c: Caller = Depends(role("operator"))):
    return _action(request, job_id, "abort", c)


@router.post("/jobs/{job_id}/acknowledge")
def acknowledge(request: Request, job_id: str, note: str = Form(""), c: Caller = Depends(role("engineer"))):
    return _action(request, job_id, "acknowledge", c, note)


@router.post("/jobs/{job_id}/signoff")
def signoff(request: Request, job_id: str, note: str = Form(""), c: Caller = Depends(role("engineer"))):
    return _action(request, job_id, "signoff", c, note)


@router.get("/jobs/{job_id}/report", response_class=HTMLResponse)
def report_page(request: Request, job_id: str, c: Caller = Depends(caller)):
    p = job_folder(_console(request).root, job_id) / "report.html"
    if not p.exists():
        raise HTTPException(404, f"{job_id} has no report (not DONE)")
    return HTMLResponse(p.read_text(encoding="utf-8"))


# --- quality engineer ------------------------------------------------------------------------
@router.get("/archive", response_class=HTMLResponse)
def archive_page(request: Request, part: str = "", serial: str = "", verdict: str = "", operator: str = "",
                 since: str = "", until: str = "", c: Caller = Depends(caller)):
    q = {"part": part, "serial": serial, "verdict": verdict, "operator": operator, "since": since, "until": until}
    jobs = _console(request).view.list_jobs(**{k: v or None for k, v in q.items()})
    return _render(request, "archive.html", c, jobs=jobs, q=q, signed=request.app.state.users.last_actions("sign off"))


@router.get("/trend", response_class=HTMLResponse)
def trend_page(request: Request, part: str, target: str = "", axis: str = "norm", baseline: int | None = None,
               group: str = "", c: Caller = Depends(caller)):
    view = _console(request).view
    targets = view.job_targets(part)
    target = group.strip() or target or targets[0]
    doc = trend(view, part, target, axis, baseline)
    return _render(request, "trend.html", c, part=part, target=target, axis=axis, targets=targets, t=doc,
                   doc_json=_script_json(doc))


@router.get("/compare", response_class=HTMLResponse)
def compare_page(request: Request, a: str, b: str, c: Caller = Depends(caller)):
    view = _console(request).view
    ra, rb = view.report(a), view.report(b)
    if ra is None or rb is None:
        raise HTTPException(404, "both jobs need a report (DONE)")
    tb = {t["id"]: t for t in rb["targets"]}
    rows = [(t, tb.get(t["id"])) for t in ra["targets"]]
    return _render(request, "compare.html", c, a=a, b=b, ja=view.get_job(a), jb=view.get_job(b), ra=ra, rb=rb, rows=rows)


@router.get("/reverification", response_class=HTMLResponse)
def reverification_page(request: Request, c: Caller = Depends(caller)):
    recs = reverifications(_console(request).root)
    return _render(request, "reverification.html", c, recs=recs, recs_json=_script_json(recs))


# --- engineer: part programs ---------------------------------------------------------------------
@router.get("/programs", response_class=HTMLResponse)
def programs_page(request: Request, c: Caller = Depends(role("engineer"))):
    return _render(request, "programs.html", c, programs=sorted(_console(request).programs()))


@router.get("/programs/{name}", response_class=HTMLResponse)
def program_page(request: Request, name: str, c: Caller = Depends(role("engineer")), msg: str = ""):
    text = _console(request).program(name).read_text(encoding="utf-8")
    return _render(request, "program.html", c, name=name, text=text, msg=_message("program", msg))


@router.post("/programs/{name}")
def program_save(request: Request, name: str, text: str = Form(...), c: Caller = Depends(role("engineer"))):
    _console(request).save_program(name, text.replace("\r\n", "\n"), c.user.name)
    return RedirectResponse(f"/programs/{name}?msg=saved", status_code=303)


# --- admin: users ---------------------------------------------------------------------------------
@router.get("/admin/users", response_class=HTMLResponse)
def users_page(request: Request, c: Caller = Depends(role("admin"))):
    return _render(request, "users.html", c, users=request.app.state.users.users(), roles=ROLES)


@router.post("/admin/users")
def users_add(request: Request, name: str = Form(...), role_: str = Form(..., alias="role"),
              password: str = Form(...), c: Caller = Depends(role("admin"))):
    u = request.app.state.users.add(name, role_, password)
    request.app.state.users.audit(c.user.name, "add user", None, f"{u.name} ({u.role})")
    return RedirectResponse("/admin/users", status_code=303)


@router.post("/admin/users/{name}/delete")
def users_delete(request: Request, name: str, c: Caller = Depends(role("admin"))):
    if name == c.user.name:
        raise HTTPException(400, "you cannot remove yourself")
    request.app.state.users.remove(name)
    request.app.state.users.audit(c.user.name, "remove user", None, name)
    return RedirectResponse("/admin/users", status_code=303)
