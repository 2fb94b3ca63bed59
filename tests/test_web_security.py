"""The console's security, in-process (FastAPI's TestClient): every route refuses strangers, roles gate
what they should, forms need their CSRF token, logins are throttled, passwords never appear in logs or
stores, and no id from a URL reaches outside the archive. (Two browsers starting two jobs at once:
tests/test_web_browser.py, against the served console.)"""
from __future__ import annotations

import json
import logging
import re
import shutil

import pytest
from fastapi.routing import APIRoute
from fastapi.testclient import TestClient

from webutil import PASSWORDS, seed_trend_archive, security_site

from cell.web.app import create_app
from cell.web.deps import Config
from cell.web.users import UserStore

PUBLIC = {("GET", "/login"), ("POST", "/login"), ("POST", "/api/token")}


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    return security_site(tmp_path_factory.mktemp("web"))


@pytest.fixture
def app(site):
    archive, programs, _ = site
    return create_app(Config(archive=archive, programs=programs))


def _routes(app):
    """(method, path) of every route of the app, through included routers."""
    todo = list(app.routes)
    while todo:
        r = todo.pop(0)
        if isinstance(r, APIRoute):
            for m in r.methods:
                yield m, r.path
        elif hasattr(r, "original_router"):  # FastAPI >= 0.165 wraps an included router
            todo += list(r.original_router.routes)
        elif hasattr(r, "routes"):
            todo += list(r.routes)


def _fill(path: str, job_id: str) -> str:
    return (path.replace("{job_id}", job_id).replace("{part}", "TR-500").replace("{target}", "T01")
            .replace("{name}", "x"))


def _login(client: TestClient, name: str) -> str:
    r = client.post("/login", data={"username": name, "password": PASSWORDS[name]}, follow_redirects=False)
    assert r.status_code == 303, r.text
    page = client.get("/").text
    return re.search(r'name="csrf" value="([^"]+)"', page).group(1)


def test_every_route_but_login_and_token_answers_401_without_session_or_token(app, site):
    _, _, ids = site
    with TestClient(app) as c:
        walked = 0
        for method, path in _routes(app):
            if (method, path) in PUBLIC:
                continue
            url = _fill(path, ids[0])
            for headers in ({}, {"Authorization": "Bearer not-a-token"}, {"Cookie": "cell_session=forged"}):
                r = c.request(method, url, headers=headers, follow_redirects=False)
                assert r.status_code == 401, f"{method} {url} with {headers}: {r.status_code}"
            walked += 1
        assert walked >= 30, walked  # the walk saw the whole app
        # the pages say so in HTML and send the browser to the login page
        r = c.get("/", headers={"Accept": "text/html"})
        assert r.status_code == 401 and 'url=/login' in r.text


def test_operator_cannot_reach_admin_or_engineer_routes(app, site):
    _, _, ids = site
    with TestClient(app) as c:
        csrf = _login(c, "olga")
        hdr = {"X-CSRF-Token": csrf}
        admin = [(m, p) for m, p in _routes(app) if p.startswith(("/admin", "/api/users"))]
        engineer_api = [(m, p) for m, p in _routes(app) if p.startswith("/api/programs/")]
        engineer = [("GET", "/programs"), ("GET", "/programs/{name}"), ("POST", "/programs/{name}"),
                    ("POST", "/jobs/{job_id}/acknowledge"), ("POST", "/jobs/{job_id}/signoff"),
                    ("POST", "/api/jobs/{job_id}/acknowledge"), ("POST", "/api/jobs/{job_id}/signoff"),
                    ("GET", "/api/audit")]
        assert len(admin) >= 5
        assert len(engineer_api) == 2
        for m, p in admin + engineer + engineer_api:
            r = c.request(m, _fill(p, ids[0]), headers=hdr, follow_redirects=False)
            assert r.status_code == 403, f"operator reached {m} {p}: {r.status_code}"
        # the engineer reaches the engineer's routes but not the admin's
        c.cookies.clear()
        csrf = _login(c, "eve")
        assert c.get("/api/audit").status_code == 200
        assert c.get("/admin/users").status_code == 403
        assert c.post(f"/api/jobs/{ids[0]}/signoff", json={"note": "ok"}, headers={"X-CSRF-Token": csrf}).status_code == 200


def test_forms_and_scripts_without_the_csrf_token_are_refused(app, site):
    _, _, ids = site
    with TestClient(app) as c:
        csrf = _login(c, "ada")
        changing = [(m, p) for m, p in _routes(app) if m in ("POST", "PUT", "DELETE") and (m, p) not in PUBLIC]
        assert len(changing) >= 12 and {"PUT", "DELETE"} <= {m for m, _ in changing}
        for m, p in changing:
            url = _fill(p, ids[0])
            for kw in ({"data": {"x": "1"}}, {"data": {"csrf": "wrong"}}, {"json": {}},
                       {"json": {}, "headers": {"X-CSRF-Token": "wrong"}}):
                r = c.request(m, url, follow_redirects=False, **kw)
                assert r.status_code == 403, f"{m} {url} {kw}: {r.status_code}"
        # with the token, a form does its work: the engineer's sign-off lands in the audit and the journal
        r = c.post(f"/jobs/{ids[1]}/signoff", data={"csrf": csrf, "note": "checked"}, follow_redirects=False)
        assert r.status_code == 303
        recs = [json.loads(x) for x in (site[0] / ids[1] / "journal.jsonl").read_text().splitlines()]
        assert recs[-1]["event"] == "audit" and recs[-1]["user"] == "ada" and recs[-1]["action"] == "sign off"
        row = next(r for r in c.get("/archive").text.split("<tr>") if ids[1] in r)
        assert "ada " + recs[-1]["t"][:10] in row  # the archive shows who signed it off
        # ... and, beside the targets beyond tolerance, those not measured (not counted as failed)
        tl = json.loads((site[0] / ids[1] / "report.json").read_text())["targets"]
        nm = sum(t["measured"][0] is None for t in tl)
        failed = sum(t["measured"][0] is not None and not t["pass"] for t in tl)
        assert "<th>failed</th><th>not measured</th>" in c.get("/archive").text
        assert f"<td>{failed}</td><td>{nm}</td>" in row
        from cell.record.archive import Archive

        assert Archive(site[0]).verify(ids[1]) == []  # the folder stays closed (manifest rewritten)


def test_bearer_token_works_without_csrf_and_sessions_do_not_leak_into_it(app, site):
    _, _, ids = site
    with TestClient(app) as c:
        r = c.post("/api/token", json={"username": "eve", "password": PASSWORDS["eve"]})
        assert r.status_code == 200
        tok = r.json()["token"]
        h = {"Authorization": f"Bearer {tok}"}
        assert c.get("/api/jobs", params={"part": "TR-500"}, headers=h).json()["jobs"]
        assert c.post(f"/api/jobs/{ids[2]}/signoff", json={"note": "api"}, headers=h).status_code == 200
        # a bearer token is not a session cookie, and a session id is not a token
        assert c.get("/api/jobs", headers={"Cookie": f"cell_session={tok}"}).status_code == 401
        r = c.post("/api/token", data={"username": "eve", "password": PASSWORDS["eve"]})  # form works too
        assert r.status_code == 200


def test_login_is_throttled_after_repeated_failures(tmp_path):
    archive = tmp_path / "archive"
    UserStore(archive / "console.sqlite").add("ada", "admin", PASSWORDS["ada"])
    app = create_app(Config(archive=archive, programs=tmp_path))
    with TestClient(app) as c:
        for _ in range(5):
            assert c.post("/api/token", json={"username": "ada", "password": "guess"}).status_code == 401
        r = c.post("/api/token", json={"username": "ada", "password": PASSWORDS["ada"]})
        assert r.status_code == 429 and "Retry-After" in r.headers
        r = c.post("/login", data={"username": "ada", "password": PASSWORDS["ada"]})
        assert r.status_code == 429


def test_passwords_never_reach_logs_stores_or_answers(app, site, caplog, capfd):
    archive = site[0]
    caplog.set_level(logging.DEBUG)
    with TestClient(app) as c:
        c.post("/login", data={"username": "olga", "password": "wrong-" + PASSWORDS["olga"]})
        csrf = _login(c, "olga")
        c.cookies.clear()
        _login(c, "ada")
        page = c.get("/admin/users").text
        csrf = re.search(r'name="csrf" value="([^"]+)"', page).group(1)
        newpw = "new-user-pw-55x"
        assert c.post("/admin/users", data={"csrf": csrf, "name": "nina", "role": "operator", "password": newpw},
                      follow_redirects=False).status_code == 303
        short = c.post("/api/users", json={"name": "tim", "role": "operator", "password": "pw-x1"},
                       headers={"X-CSRF-Token": csrf})
        assert short.status_code == 422 and "pw-x1" not in short.text
        bad = c.post("/api/token", json={"username": "nina", "password": newpw + "x"})
        assert newpw not in bad.text
    out, err = capfd.readouterr()
    seen = caplog.text + out + err
    stores = b"".join(p.read_bytes() for p in archive.rglob("*") if p.is_file())
    for pw in [*PASSWORDS.values(), newpw, "pw-x1"]:
        assert pw not in seen, "a password reached the log"
        assert pw.encode() not in stores, "a password is stored in clear in the archive"
    assert b"$argon2id$" in (archive / "console.sqlite").read_bytes() + b"".join(
        p.read_bytes() for p in archive.glob("console.sqlite*"))
    for p in archive.glob("console.sqlite*"):  # the store and its WAL: its owner's only
        assert p.stat().st_mode & 0o077 == 0, (p.name, oct(p.stat().st_mode))


def test_ids_from_the_url_cannot_escape_the_archive(app, site, tmp_path):
    archive, _, ids = site
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "journal.jsonl").write_text('{"t": "2026-01-01T00:00:00+00:00", "event": "created"}\n')
    (outside / "report.json").write_text(json.dumps({"secret": "outside the archive"}))
    (outside / "report.html").write_text("outside the archive")
    (archive / "linked").symlink_to(outside)
    bad = ["..", "...", ".incoming", ".console", "index.sqlite", "console.sqlite", "linked", "%2e%2e",
           "..%2F..%2Fetc%2Fpasswd", "%2E%2E%2Foutside", ids[0] + "%2F..%2F..", "a%00b", "~root", "*"]
    with TestClient(app) as c:
        _login(c, "ada")
        for b in bad:
            for url in (f"/api/jobs/{b}", f"/api/jobs/{b}/report.json", f"/api/jobs/{b}/report.csv",
                        f"/jobs/{b}/report", f"/jobs/{b}/image.jpg", f"/jobs/{b}"):
                r = c.get(url)
                if b.strip(".") == "" and r.url.path != url:  # the client normalised the dots away: not our route
                    continue
                assert r.status_code in (404, 400, 422), f"{url}: {r.status_code}"
                assert "outside the archive" not in r.text and "root:" not in r.text
        # a real id still works
        assert c.get(f"/api/jobs/{ids[0]}/report.json").json()["job"]["id"] == ids[0]


def test_job_filters_and_roles_of_the_api(app, site):
    _, _, ids = site
    with TestClient(app) as c:
        tok = c.post("/api/token", json={"username": "olga", "password": PASSWORDS["olga"]}).json()["token"]
        h = {"Authorization": f"Bearer {tok}"}
        rows = c.get("/api/jobs", params={"serial": "SN-0002"}, headers=h).json()["jobs"]
        assert [r["id"] for r in rows] == [ids[1]]
        assert rows[0]["part_number"] == "TR-500" and rows[0]["operator"] == "olga"
        assert len(c.get("/api/jobs", params={"since": "2026-11-20", "until": "2026-11-20"}, headers=h).json()["jobs"]) == 3
        assert c.get("/api/jobs", params={"since": "2026-11-21"}, headers=h).json()["jobs"] == []
        assert c.get("/api/jobs", params={"since": "yesterday"}, headers=h).status_code == 400
        doc = c.get(f"/api/jobs/{ids[0]}", headers=h).json()
        assert {"id", "state", "stage", "progress", "verdict"} <= set(doc) and doc["state"] == "DONE"
        # no such program: refused with the reason, nothing started
        r = c.post("/api/jobs", json={"program": "../../etc/passwd", "serial": "X"}, headers=h)
        assert r.status_code == 404


def test_engineer_edits_a_part_program_only_when_it_is_a_valid_job_file(site, tmp_path):
    archive, programs, _ = site
    import shutil

    from jobutil import EXAMPLE

    prog = programs / "bracket"
    if not prog.exists():
        shutil.copytree(EXAMPLE, prog)
    app = create_app(Config(archive=archive, programs=programs))
    before = (prog / "job.toml").read_text()
    with TestClient(app) as c:
        csrf = _login(c, "eve")
        r = c.post("/programs/bracket", data={"csrf": csrf, "text": before.replace("[camera]", "[camera]\nzoom = 2")})
        assert r.status_code == 400 and "unknown key 'camera.zoom'" in r.text
        assert (prog / "job.toml").read_text() == before  # nothing written
        new = before.replace("seed = 7", "seed = 8")
        assert new != before
        r = c.post("/programs/bracket", data={"csrf": csrf, "text": new}, follow_redirects=False)
        assert r.status_code == 303 and (prog / "job.toml").read_text() == new
        assert c.get("/api/programs").json()["programs"] == ["bracket"]
        # the same through the API, for line integration
        tok = c.post("/api/token", json={"username": "eve", "password": PASSWORDS["eve"]}).json()["token"]
        h = {"Authorization": f"Bearer {tok}"}
        assert c.get("/api/programs/bracket", headers=h).json()["text"] == new
        assert c.put("/api/programs/bracket", json={"text": new + "\n[camera]\n"}, headers=h).status_code == 400
        assert c.put("/api/programs/bracket", json={"text": before}, headers=h).status_code == 200
        assert (prog / "job.toml").read_text() == before
        assert c.get("/api/audit").json()["audit"][0]["action"] == "edit program"
        assert c.post("/programs/../etc", data={"csrf": csrf, "text": new}).status_code in (404, 405)


def test_compare_and_reverification_history_pages(app, site):
    archive, _, ids = site
    rec = archive / "calibration" / "2026-11-19T07-00-00-reverify"
    rec.mkdir(parents=True)
    (rec / "reverification.json").write_text(json.dumps({
        "cell": "cell-1", "finished": "2026-11-19T07:10:00+00:00", "passed": True, "detail": "3 of 3 within E_MPE",
        "positions": [{"position": k, "error_m": e, "mpe_m": 30e-6} for k, e in enumerate((4e-6, -7e-6, 11e-6))]}))
    with TestClient(app) as c:
        _login(c, "eve")
        page = c.get("/compare", params={"a": ids[0], "b": ids[1]}).text
        assert "SN-0001" in page and "SN-0002" in page and page.count("<tr>") >= 6 + 5
        page = c.get("/reverification").text
        assert "3 of 3 within E_MPE" in page and "revchart" in page and "1.1e-05" in page
        assert c.get("/compare", params={"a": ids[0], "b": "../x"}).status_code == 404
        page = c.get("/trend", params={"part": "TR-500", "group": "T01,T02"})
        assert page.status_code == 200 and "worst: " in page.text and '"group": ["T01", "T02"]' in page.text


@pytest.mark.skipif(shutil.which("openssl") is None, reason="no openssl to make a test certificate")
def test_tls_when_a_certificate_is_configured_and_the_cookie_is_secure(site, tmp_path):
    import ssl
    import subprocess
    import urllib.request

    from webutil import Served

    archive, programs, _ = site
    key, cert = tmp_path / "key.pem", tmp_path / "cert.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key), "-out", str(cert),
                    "-days", "1", "-subj", "/CN=127.0.0.1"], check=True, capture_output=True, timeout=60)
    server = Served(archive, programs, tmp_path / "serve.log", ["--certfile", str(cert), "--keyfile", str(key)],
                    scheme="https")
    try:
        ctx = ssl.create_default_context(cafile=str(cert))
        ctx.check_hostname = False
        with urllib.request.urlopen(server.url + "/login", context=ctx, timeout=30) as r:
            assert r.status == 200 and b'id="login"' in r.read()
        req = urllib.request.Request(server.url + "/login", method="POST",
                                     data=f"username=ada&password={PASSWORDS['ada']}".encode(),
                                     headers={"Content-Type": "application/x-www-form-urlencoded"})

        class NoRedirect(urllib.request.HTTPRedirectHandler):
            def redirect_request(self, *a, **k):
                return None

        opener = urllib.request.build_opener(NoRedirect, urllib.request.HTTPSHandler(context=ctx))
        try:
            opener.open(req, timeout=30)
        except urllib.error.HTTPError as e:  # the 303 after a good login
            assert e.code == 303
            cookie = e.headers["set-cookie"].lower()
            assert "httponly" in cookie and "secure" in cookie and "samesite=strict" in cookie
            assert e.headers["strict-transport-security"]
        else:
            raise AssertionError("no redirect after login")
        with pytest.raises(Exception):  # plain HTTP on the TLS port is not served
            urllib.request.urlopen(server.url.replace("https", "http") + "/login", timeout=10)
    finally:
        server.stop()


def test_logout_ends_the_session_for_good(app):
    with TestClient(app) as c:
        csrf = _login(c, "olga")
        cookie = c.cookies.get("cell_session")
        assert c.get("/api/jobs").status_code == 200
        assert c.post("/logout", data={"csrf": csrf}, follow_redirects=False).status_code == 303
        c.cookies.clear()
        assert c.get("/api/jobs", headers={"Cookie": f"cell_session={cookie}"}).status_code == 401


def test_engineer_acknowledges_a_fault_with_who_and_when_in_the_journal(app, site):
    archive, _, ids = site
    from cell.record.jobfolder import JobFolder

    jid = "2026-11-21T09-00-00-faulted"
    folder = archive / jid
    folder.mkdir()
    f = JobFolder(folder)
    f.append("created", name="trendpart")
    f.append("state", **{"from": "CREATED", "to": "LOAD"})
    f.append("state", **{"from": "LOAD", "to": "FAULTED", "cause": "x"})
    f.append("terminal", status="FAULTED", reason="ACQUIRE: protective stop (injected)")
    f.write_manifest()
    with TestClient(app) as c:
        tok = c.post("/api/token", json={"username": "eve", "password": PASSWORDS["eve"]}).json()["token"]
        h = {"Authorization": f"Bearer {tok}"}
        doc = c.get(f"/api/jobs/{jid}", headers=h).json()
        assert doc["state"] == "FAULTED" and "teach pendant" in doc["advice"]
        assert c.post(f"/api/jobs/{ids[2]}/acknowledge", json={}, headers=h).status_code == 400  # not a fault
        r = c.post(f"/api/jobs/{jid}/acknowledge", json={"note": "guard door sensor checked"}, headers=h)
        assert r.status_code == 200 and r.json()["acknowledged_by"] == "eve"
    rec = list(JobFolder(folder).records())[-1]
    assert rec["event"] == "audit" and rec["user"] == "eve" and rec["action"] == "acknowledge fault" and rec["t"]
    assert rec["detail"] == "guard door sensor checked"


def test_names_from_files_cannot_inject_script_into_pages(tmp_path):
    archive = tmp_path / "archive"
    ids = seed_trend_archive(archive, n_parts=3)
    evil = "</script><script>alert(1)</script>"
    for jid in ids:  # a target id as a hostile targets file could name it
        p = archive / jid / "report.json"
        doc = json.loads(p.read_text())
        doc["targets"][0]["id"] = evil
        p.write_text(json.dumps(doc))
    UserStore(archive / "console.sqlite").add("ada", "admin", PASSWORDS["ada"])
    app = create_app(Config(archive=archive, programs=tmp_path))
    with TestClient(app) as c:
        _login(c, "ada")
        for url in ("/trend", "/compare"):
            params = {"part": "TR-500", "target": evil} if url == "/trend" else {"a": ids[0], "b": ids[1]}
            page = c.get(url, params=params)
            assert page.status_code == 200, page.text[:300]
            assert "<script>alert(1)" not in page.text
