"""The report as an operator sees it: report.html of the example job opened in a real headless
browser (Debian's chromium), its DOM and a screenshot checked. Skipped when chromium is absent
(scripts/test.sh installs it).
"""
from __future__ import annotations

import base64
import json
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest

from jobutil import example_run

CHROMIUM = next((p for p in (shutil.which("chromium"), shutil.which("chromium-browser"), shutil.which("google-chrome"))
                 if p), None)
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium on PATH (apt-get install chromium; "
                                                         "scripts/test.sh does) to render the report in")


def _chromium(tmp: Path, *args: str, timeout: float = 90.0) -> subprocess.CompletedProcess:
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
           "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-extensions",
           f"--user-data-dir={tmp / 'profile'}", *args]
    return subprocess.run(cmd, capture_output=True, timeout=timeout)


class _Dom(HTMLParser):
    """The parts of the rendered DOM the checks need: elements by id (with their text), rows, images."""

    def __init__(self):
        super().__init__()
        self.by_id: dict[str, dict] = {}
        self.images: list[dict] = []
        self._open: list[tuple[str, str | None]] = []  # (tag, id of the nearest enclosing element with one)
        self.rows: dict[str, int] = {}

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        owner = a.get("id") or (self._open[-1][1] if self._open else None)
        if "id" in a:
            self.by_id[a["id"]] = {"tag": tag, "attrs": a, "text": ""}
        if tag == "img":
            self.images.append(a)
            return  # void element
        if tag == "tr" and owner is not None:
            self.rows[owner] = self.rows.get(owner, 0) + 1
        self._open.append((tag, owner))

    def handle_endtag(self, tag):
        for k in range(len(self._open) - 1, -1, -1):
            if self._open[k][0] == tag:
                del self._open[k:]
                break

    def handle_data(self, data):
        if self._open and self._open[-1][1] in self.by_id:
            self.by_id[self._open[-1][1]]["text"] += data


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    job, folder, run = example_run(tmp_path_factory)
    return folder, json.loads((folder / "report.json").read_text())


def test_report_renders_in_a_headless_browser_with_verdict_targets_and_figures(report, tmp_path):
    folder, doc = report
    url = (folder / "report.html").resolve().as_uri()
    dom_run = _chromium(tmp_path, "--virtual-time-budget=5000", "--dump-dom", url)
    assert dom_run.returncode == 0, dom_run.stderr.decode()[-2000:]
    dom = _Dom()
    dom.feed(dom_run.stdout.decode())
    # the verdict, as report.json has it, with the count of targets within tolerance
    assert "verdict" in dom.by_id, "no #verdict element in the rendered report"
    verdict = dom.by_id["verdict"]["text"].strip()
    from cell.record.decisions import counts, trusted

    n_within = counts(doc["targets"], trusted(doc))["within"]  # within tolerance and decided
    assert verdict.startswith(doc["verdict"]) and f"{n_within} of {len(doc['targets'])}" in verdict, verdict
    # the targets table: a header and one row per judged target
    assert dom.by_id.get("targets", {}).get("tag") == "table", "no #targets table in the rendered report"
    assert dom.rows["targets"] == len(doc["targets"]) + 1
    # every figure is an embedded PNG that decodes to a picture with something drawn on it
    figures = [im for im in dom.images if im.get("src", "").startswith("data:image/png;base64,")]
    assert len(figures) >= 4, f"{len(figures)} embedded figures"
    for im in figures:
        png = base64.b64decode(im["src"].split(",", 1)[1])
        pic = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        assert pic is not None and min(pic.shape[:2]) > 200, f"figure {im.get('alt')} does not decode"
        assert (pic < 200).any(axis=2).mean() > 0.01, f"figure {im.get('alt')} is blank"

    shot = tmp_path / "report.png"
    shot_run = _chromium(tmp_path, "--hide-scrollbars", "--virtual-time-budget=5000", f"--screenshot={shot}",
                         "--window-size=1400,3000", url)
    assert shot_run.returncode == 0 and shot.exists(), shot_run.stderr.decode()[-2000:]
    img = cv2.imread(str(shot), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[:2] == (3000, 1400)
    rgb = img[..., ::-1].astype(int)

    def near(color, tol=40):
        return int((np.abs(rgb - np.array(color)).sum(axis=2) < tol).sum())

    assert (rgb.min(axis=2) < 230).mean() > 0.05, "the screenshot is (nearly) blank"
    # the verdict box in its colour (FAIL red #cf222e, PASS green #1a7f37) ...
    box = {"FAIL": (0xCF, 0x22, 0x2E), "PASS": (0x1A, 0x7F, 0x37), "INCOMPLETE": (0x9A, 0x67, 0x00)}[doc["verdict"]]
    assert near(box) > 5_000, "the verdict box is not drawn"
    # ... and the figures drawn by the browser: matplotlib's blue (stations, ellipsoids, sigma plot) is only in them
    assert near((31, 119, 180), tol=60) > 500, "the figures are not drawn in the screenshot"
