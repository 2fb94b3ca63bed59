"""The JSON API under /api/ (contract in ARCHITECTURE.md): everything the pages do, for line integration."""
from __future__ import annotations

import json

from fastapi import APIRouter, Depends, HTTPException, Request
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field

from cell.web.deps import COOKIE, Caller, bearer, caller, log_in, login_work, role
from cell.web.service import trend, trend_csv
from cell.web.users import ROLES

router = APIRouter(prefix="/api")


def _console(request: Request):
    return request.app.state.console


class Token(BaseModel):
    token: str
    user: str
    role: str


@router.post("/token", response_model=Token)
async def token(request: Request):
    """Form or JSON {username, password} -> {token} for ``Authorization: Bearer``.

    The body is at most ``app.LOGIN_BODY_MAX`` bytes (413 beyond); the password check runs off the event loop."""
    if request.headers.get("content-type", "").startswith("application/json"):
        try:
            body = await request.json()
        except ValueError:
            raise HTTPException(400, "body: not JSON") from None
        if not isinstance(body, dict):
            raise HTTPException(400, "body: a JSON object {username, password}")
    else:
        body = dict(await request.form())
    name, password = str(body.get("username", "")), str(body.get("password", ""))
    user = await log_in(request, name, password)
    if user is None:
        raise HTTPException(401, "wrong user name or password")
    users = request.app.state.users

    def issue() -> str:
        secret, _ = users.open_session(user, "api")
        users.audit(user.name, "token issued")
        return secret

    return Token(token=await login_work(request.app, issue), user=user.name, role=user.role)


@router.post("/logout")
def logout(request: Request, c: Caller = Depends(caller)):
    """End the presented bearer token (or the browser session) now, not when it expires."""
    users = request.app.state.users
    users.close_session(bearer(request) or request.cookies.get(COOKIE, ""))
    users.audit(c.user.name, "token revoked" if c.via == "token" else "log out")
    return {"revoked": c.via}


class StartJob(BaseModel):
    program: str = Field(min_length=1, max_length=200)
    serial: str | None = Field(default=None, max_length=80)
    placed: bool = True


class JobRef(BaseModel):
    id: str


class Note(BaseModel):
    note: str = Field(default="", max_length=500)


@router.get("/jobs")
def list_jobs(request: Request, part: str | None = None, serial: str | None = None, verdict: str | None = None,
              since: str | None = None, until: str | None = None, operator: str | None = None, status: str | None = None,
              c: Caller = Depends(caller)):
    return {"jobs": _console(request).view.list_jobs(part=part, serial=serial, verdict=verdict, operator=operator,
                                                     since=since, until=until, status=status)}


@router.post("/jobs", response_model=JobRef)
def start_job(request: Request, body: StartJob, c: Caller = Depends(role("operator"))):
    return JobRef(id=_console(request).start(body.program, body.serial, c.user.name, body.placed))


@router.get("/jobs/{job_id}")
def get_job(request: Request, job_id: str, c: Caller = Depends(caller)):
    con = _console(request)
    doc = con.status(job_id)
    try:
        doc |= {k: v for k, v in con.view.get_job(job_id).items() if k not in doc}
    except Exception:  # still in .incoming (before ACQUIRE): the live state is all there is
        pass
    return doc


@router.post("/jobs/{job_id}/resume", response_model=JobRef)
def resume_job(request: Request, job_id: str, c: Caller = Depends(role("operator"))):
    return JobRef(id=_console(request).resume(job_id, c.user.name))


@router.post("/jobs/{job_id}/abort")
def abort_job(request: Request, job_id: str, c: Caller = Depends(role("operator"))):
    _console(request).abort(job_id, c.user.name)
    return {"id": job_id, "abort": "requested"}


@router.post("/jobs/{job_id}/acknowledge")
def acknowledge(request: Request, job_id: str, body: Note | None = None, c: Caller = Depends(role("engineer"))):
    _console(request).acknowledge(job_id, c.user.name, body.note if body else "")
    return {"id": job_id, "acknowledged_by": c.user.name}


@router.post("/jobs/{job_id}/signoff")
def sign_off(request: Request, job_id: str, body: Note | None = None, c: Caller = Depends(role("engineer"))):
    _console(request).sign_off(job_id, c.user.name, body.note if body else "")
    return {"id": job_id, "signed_off_by": c.user.name}


@router.get("/jobs/{job_id}/report.json")
def report_json(request: Request, job_id: str, c: Caller = Depends(caller)):
    rep = _console(request).view.report(job_id)
    if rep is None:
        raise HTTPException(404, f"{job_id} has no report (not DONE)")
    return JSONResponse(rep)


@router.get("/jobs/{job_id}/report.csv")
def report_csv(request: Request, job_id: str, c: Caller = Depends(caller)):
    return Response(_console(request).report_csv(job_id), media_type="text/csv",
                    headers={"Content-Disposition": f'attachment; filename="{job_id}.csv"'})


@router.get("/jobs/{job_id}/report.pdf")
def report_pdf(request: Request, job_id: str, c: Caller = Depends(caller)):
    return Response(_console(request).report_pdf(job_id), media_type="application/pdf",
                    headers={"Content-Disposition": f'attachment; filename="{job_id}.pdf"'})


@router.get("/jobs/{job_id}/report.qif")
def report_qif(request: Request, job_id: str, c: Caller = Depends(caller)):
    from cell.record.qif import qif_results

    rep = _console(request).view.report(job_id)
    if rep is None:
        raise HTTPException(404, f"{job_id} has no report (not DONE)")
    return Response(qif_results(rep, job_id), media_type="application/xml",
                    headers={"Content-Disposition": f'attachment; filename="{job_id}.qif"'})


@router.get("/parts/{part}/targets")
def part_targets(request: Request, part: str, c: Caller = Depends(caller)):
    return {"part": part, "targets": _console(request).view.job_targets(part)}


@router.get("/parts/{part}/targets/{target}/trend")
def target_trend(request: Request, part: str, target: str, axis: str = "norm", baseline: int | None = None,
                 c: Caller = Depends(caller)):
    return json.loads(json.dumps(trend(_console(request).view, part, target, axis, baseline), default=float))


@router.get("/parts/{part}/targets/{target}/trend.csv")
def target_trend_csv(request: Request, part: str, target: str, axis: str = "norm", baseline: int | None = None,
                     c: Caller = Depends(caller)):
    doc = trend(_console(request).view, part, target, axis, baseline)
    return Response(trend_csv(doc), media_type="text/csv",
                    headers={"Content-Disposition": f'attachment; filename="trend-{part}-{target}.csv"'})


@router.get("/programs")
def programs(request: Request, c: Caller = Depends(caller)):
    return {"programs": sorted(_console(request).programs())}


class ProgramText(BaseModel):
    text: str = Field(max_length=1_000_000)


@router.get("/programs/{name}")
def program_text(request: Request, name: str, c: Caller = Depends(role("engineer"))):
    return {"name": name, "text": _console(request).program(name).read_text(encoding="utf-8")}


@router.put("/programs/{name}")
def program_save(request: Request, name: str, body: ProgramText, c: Caller = Depends(role("engineer"))):
    _console(request).save_program(name, body.text, c.user.name)
    return {"name": name, "saved_by": c.user.name}


@router.get("/audit")
def audit(request: Request, job_id: str | None = None, c: Caller = Depends(role("engineer"))):
    return {"audit": request.app.state.users.audit_log(job_id)}


class NewUser(BaseModel):
    name: str
    role: str
    password: str = Field(min_length=8, max_length=200)


@router.get("/users")
def users(request: Request, c: Caller = Depends(role("admin"))):
    return {"users": [{"name": u.name, "role": u.role} for u in request.app.state.users.users()], "roles": ROLES}


@router.post("/users")
def add_user(request: Request, body: NewUser, c: Caller = Depends(role("admin"))):
    u = request.app.state.users.add(body.name, body.role, body.password)
    request.app.state.users.audit(c.user.name, "add user", None, f"{u.name} ({u.role})")
    return {"name": u.name, "role": u.role}


@router.delete("/users/{name}")
def remove_user(request: Request, name: str, c: Caller = Depends(role("admin"))):
    if name == c.user.name:
        raise HTTPException(400, "you cannot remove yourself")
    request.app.state.users.remove(name)
    request.app.state.users.audit(c.user.name, "remove user", None, name)
    return {"removed": name}
