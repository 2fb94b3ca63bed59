"""The console in a real browser (Playwright driving Debian's chromium) against ``cell serve`` in a child
process: an operator logs in, starts a simulated job with a serial number and watches it live to DONE,
opens the report, exports PDF and CSV; a quality engineer opens the trend of ten serial parts whose
drifting targets the control chart flags; two browsers cannot start two jobs on one cell, and Abort
stops the running one. The ten trend parts are synthesized finished jobs (tests/webutil.py says how);
the job started from the browser is a real simulated job."""
from __future__ import annotations

import json
import time

import cv2
import numpy as np
import pytest

from webutil import CHROMIUM_ARGS, DRIFTING, PART, Served, add_user, chromium_path, seed_trend_archive, tiny_program

playwright = pytest.importorskip("playwright.sync_api")
CHROMIUM = chromium_path()
pytestmark = [pytest.mark.skipif(CHROMIUM is None, reason="no /usr/bin/chromium (scripts/test.sh installs it)"),
              pytest.mark.slow]
USERS = {"olga": ("operator", "olga-pw-31x9"), "eve": ("engineer", "eve-pw-8k2j"), "ada": ("admin", "ada-pw-0pq7")}
RED, GREEN = (0xCF, 0x22, 0x2E), (0x1A, 0x7F, 0x37)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    base = tmp_path_factory.mktemp("console")
    archive, programs = base / "archive", base / "programs"
    tiny_program(programs, "bracket", motion="timed", time_scale=6.0)
    seed_trend_archive(archive, n_parts=10, drift_from=6)
    for name, (role, pw) in USERS.items():
        add_user(archive, name, role, pw)
    server = Served(archive, programs, base / "serve.log")
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield server, browser, archive, base
        finally:
            browser.close()
            server.stop()
    log = (base / "serve.log").read_text()
    for _, pw in USERS.values():
        assert pw not in log, "a password reached the console's log"


def _login(browser, server, name):
    ctx = browser.new_context(viewport={"width": 1300, "height": 1000})
    page = ctx.new_page()
    page.goto(server.url + "/")  # 401 -> the login page
    page.wait_for_selector("#username")
    page.fill("#username", name)
    page.fill("#password", USERS[name][1])
    page.click("#login button")
    page.wait_for_selector("nav")
    return ctx, page


def _near(img, color, tol=40):
    rgb = img[..., ::-1].astype(int)
    return int((np.abs(rgb - np.array(color)).sum(axis=2) < tol).sum())


def _shot(page, path):
    page.screenshot(path=str(path), full_page=False)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None and (img.min(axis=2) < 230).mean() > 0.01, "the screenshot is (nearly) blank"
    return img


def _wait_state(page, states, timeout_s):
    t_end = time.monotonic() + timeout_s
    seen = []
    while time.monotonic() < t_end:
        st = page.inner_text("#state")
        prog = page.inner_text("#progress")
        src = page.get_attribute("#image", "src")
        loaded = page.evaluate("document.getElementById('image').naturalWidth")
        seen.append((st, prog, src, loaded))
        if st.split(" ")[0] in states and page.get_attribute("#live", "data-state") in states:
            return seen
        time.sleep(0.3)
    raise AssertionError(f"the job did not reach {states} in {timeout_s} s; last {seen[-3:]}")


def test_operator_runs_a_job_with_a_serial_live_to_done_then_report_pdf_csv(site, tmp_path):
    server, browser, archive, _ = site
    ctx, page = _login(browser, server, "olga")
    try:
        page.select_option("#program", "bracket")
        page.fill("#serial", "SN-4711")
        page.check("#placed")
        page.click("#go")
        page.wait_for_url("**/jobs/*")
        job_id = page.url.rsplit("/", 1)[1]
        seen = _wait_state(page, {"DONE"}, 300)
        # the live view moved: several stages and progress figures, and an image from the camera was shown
        assert len({s[0] for s in seen}) >= 3, seen[:: max(1, len(seen) // 10)]
        assert len({s[1] for s in seen}) >= 4
        assert any(src and "/image.jpg" in src and w > 0 for _, _, src, w in seen), "no live image was shown"
        rep = page.request.get(f"{server.url}/api/jobs/{job_id}/report.json").json()
        verdict = page.inner_text("#verdict").strip()
        assert verdict == rep["verdict"] and page.is_visible("#verdict")
        assert rep["part"] == {"number": "BR-1002", "revision": "C", "serial": "SN-4711"}
        assert rep["operator"] == "olga" and rep["cell_id"] == "cell-1"
        img = _shot(page, tmp_path / "job.png")
        # big: the verdict's box is tall (64 px letters) and large, and it is filled with the verdict's colour
        # (measured in its own box: a count over the whole page varied with the text and layout around it)
        box = page.locator("#verdict").bounding_box()
        assert box is not None and box["height"] >= 80 and box["width"] * box["height"] >= 15_000, box
        x0, y0 = int(box["x"]), int(box["y"])
        inside = img[y0:y0 + int(box["height"]), x0:x0 + int(box["width"])]
        colour = {"PASS": GREEN, "FAIL": RED}.get(verdict, (0x9A, 0x67, 0x00))
        assert inside.size and _near(inside, colour) > 0.5 * inside.shape[0] * inside.shape[1], "no big verdict"
        # the serial is in the archive index and the run log too
        rows = page.request.get(f"{server.url}/api/jobs?serial=SN-4711").json()["jobs"]
        assert [r["id"] for r in rows] == [job_id] and rows[0]["part_number"] == "BR-1002"
        from cell.record.runlog import read_messages

        jobs_msgs = [m for t, m in read_messages(archive / job_id / "run.mcap") if t == "/job"]
        assert jobs_msgs and jobs_msgs[0]["part"]["serial"] == "SN-4711" and jobs_msgs[0]["operator"] == "olga"
        # the report, opened from the live view
        page.click("#reportlink")
        page.wait_for_selector("#targets")
        assert page.inner_text("#verdict").startswith(rep["verdict"]) and "SN-4711" in page.inner_text("body")
        # its 3-D views: drawn when scrolled to, turnable (plotly scenes), targets labelled on hover
        page.locator("#views3d").scroll_into_view_if_needed()
        page.wait_for_function("document.body.dataset.fig3d", timeout=90_000)
        assert page.evaluate("document.body.dataset.fig3d") == "ready"
        assert page.locator("#fig3d-deviations .gl-container").count() == 1
        hover = page.evaluate("document.getElementById('fig3d-deviations').data[1].text")
        assert len(hover) == len(rep["targets"]) and all("|d|" in h and "tol" in h for h in hover)
        # exports: PDF from the same HTML, CSV with one row per target
        pdf = page.request.get(f"{server.url}/api/jobs/{job_id}/report.pdf")
        assert pdf.ok and pdf.body()[:5] == b"%PDF-" and len(pdf.body()) > 20_000
        (tmp_path / "report.pdf").write_bytes(pdf.body())
        qif = page.request.get(f"{server.url}/api/jobs/{job_id}/report.qif")
        assert qif.ok and b"<SerialNumber>SN-4711</SerialNumber>" in qif.body() and b"versionQIF=\"3.0.0\"" in qif.body()
        csv = page.request.get(f"{server.url}/api/jobs/{job_id}/report.csv").text().splitlines()
        assert len(csv) == len(rep["targets"]) + 1 and all(",SN-4711," in r for r in csv[1:])
        # the start was audited with who and when, in the journal and the console's audit
        recs = [json.loads(x) for x in (archive / job_id / "journal.jsonl").read_text().splitlines()]
        assert any(r["event"] == "audit" and r["user"] == "olga" and r["action"] == "start" for r in recs)
        assert any(r["event"] == "created" and r.get("operator") == "olga" for r in recs)
    finally:
        ctx.close()


def test_engineer_sees_the_drift_from_part_6_flagged_on_the_trend_and_exports_it(site, tmp_path):
    server, browser, _, _ = site
    ctx, page = _login(browser, server, "eve")
    try:
        page.goto(f"{server.url}/archive?part={PART}")
        assert page.locator("#jobs tr").count() == 11  # header + ten serial parts
        page.goto(f"{server.url}/trend?part={PART}&target={DRIFTING[0]}&axis=z")
        page.wait_for_selector("#ichart .main-svg")
        rows = page.locator("#violations tr").all_inner_texts()[1:]
        parts = sorted({int(r.split("\t")[0]) for r in rows})
        assert parts and max(parts) == 10 and {9, 10} <= set(parts), rows
        assert "Cpk" in page.inner_text("#capability")
        # hover labels carry the serial numbers; the flagged points are drawn red
        labels = page.evaluate("document.getElementById('ichart').data[0].text")
        assert labels[5].startswith("serial SN-0006")
        colors = page.evaluate("document.getElementById('ichart').data[0].marker.color")
        assert colors[9] == "#cf222e" and colors[0] == "#1f77b4"
        img = _shot(page, tmp_path / "trend.png")
        assert _near(img, RED, tol=60) > 200, "the flagged points and control limits are not drawn"
        # an undrifted target: no signal
        page.goto(f"{server.url}/trend?part={PART}&target=T01&axis=z")
        assert page.locator("#violations tr").all_inner_texts()[1:] == ["none"]
        href = page.get_attribute("#trendcsv", "href")
        csv = page.request.get(server.url + href).text().splitlines()
        assert len(csv) == 11 and "SN-0010" in csv[-1]
    finally:
        ctx.close()


def test_two_browsers_cannot_start_two_jobs_abort_stops_the_running_one_and_resume_finishes_it(site):
    server, browser, archive, _ = site
    (ca, a), (cb, b) = _login(browser, server, "olga"), _login(browser, server, "eve")
    try:
        for page, sn in ((a, "SN-A1"), (b, "SN-B2")):
            page.select_option("#program", "bracket")
            page.fill("#serial", sn)
            page.check("#placed")
        # both press Start at once: each page posts its own form (with its session and CSRF token)
        send = ("window._start = fetch('/jobs', {method: 'POST', body: new URLSearchParams(new FormData("
                "document.getElementById('start'))), headers: {'Accept': 'text/html'}})")
        a.evaluate(send)
        b.evaluate(send)
        got = [p.evaluate("window._start.then(r => r.text().then(t => [r.status, r.url, t]))") for p in (a, b)]
        assert sorted(g[0] for g in got) == [200, 409], [g[:2] for g in got]
        k = 0 if got[0][0] == 200 else 1
        winner, loser = (a, b)[k], (a, b)[1 - k]
        job_id = got[k][1].rsplit("/", 1)[1]
        assert "running job" in got[1 - k][2] and job_id in got[1 - k][2], got[1 - k][2][-600:]
        winner.goto(f"{server.url}/jobs/{job_id}")
        # the loser's serial started nothing
        assert not [r for r in json.loads(loser.request.get(f"{server.url}/api/jobs").text())["jobs"]
                    if r.get("serial") in ("SN-A1", "SN-B2") and r["id"] != job_id]
        # Abort, from the winner's live view: the runner stops and records ABORTED; the fault is told in words
        winner.wait_for_selector("#abortform:not([hidden])")
        winner.click("#abort")
        winner.wait_for_url(f"**/jobs/{job_id}")
        _wait_state(winner, {"ABORTED"}, 120)
        winner.wait_for_selector("#resumeform:not([hidden])")  # once the runner's process has ended
        assert "aborted" in winner.inner_text("#fault").lower() and not winner.is_visible("#abort")
        folder = next(p for p in (archive / job_id, archive / ".incoming" / job_id) if p.exists())
        recs = [json.loads(x) for x in (folder / "journal.jsonl").read_text().splitlines()]
        assert any(r["event"] == "audit" and r["action"] == "abort" for r in recs)
        assert recs[-1]["event"] == "terminal" and recs[-1]["status"] == "ABORTED"
        # Resume, from the same view: the job continues from its last finished stage to DONE
        winner.click("#resume")
        winner.wait_for_url(f"**/jobs/{job_id}")
        _wait_state(winner, {"DONE"}, 300)
        recs = [json.loads(x) for x in (archive / job_id / "journal.jsonl").read_text().splitlines()]
        resumed = [r for r in recs if r["event"] == "resumed"]
        assert len(resumed) == 1 and resumed[0]["operator"] in ("olga", "eve")
        assert any(r["event"] == "audit" and r["action"] == "resume" for r in recs)
        assert winner.inner_text("#verdict") in ("PASS", "FAIL", "INCOMPLETE")
    finally:
        ca.close()
        cb.close()
