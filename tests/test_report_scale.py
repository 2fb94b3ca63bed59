"""The HTML report stays readable with thousands of targets: every failing or undecided target listed, the rest capped."""
from __future__ import annotations

import numpy as np

from cell.record import report as R


def _doc(n: int, failing: list[int], inconclusive: list[int]) -> dict:
    rng = np.random.default_rng(0)
    targets = []
    for i in range(n):
        dev = 3e-4 if i in failing else float(rng.uniform(0, 2e-4))
        targets.append({"id": f"T{i:05d}", "measured": [0.0, 0.0, 0.0], "deviation": [0.0, 0.0, dev],
                        "deviation_norm_m": dev, "tolerance_m": 2.5e-4, "pass": i not in failing,
                        "achieved_sigma_m": 1e-5, "predicted_sigma_m": 1e-5, "n_images": 4,
                        "decision": "inconclusive" if i in inconclusive else "conforming"})
    return {"job": {"id": "j", "name": "n", "seed": 0, "started": "", "finished": "", "versions": {}},
            "verdict": "FAIL", "targets": targets, "stage_times_s": {}, "images": 3, "sigma0_px": 0.05}


def test_large_report_lists_every_failing_and_undecided_target_and_says_how_many_are_left_out():
    n = R.TABLE_ROWS + 500
    failing, undecided = [3, 1400], [1450, 1499]
    html = R.render_html(_doc(n, failing, undecided), {})
    body = html.split('<table id="targets">')[1].split("</table>")[0]
    for i in failing + undecided:
        assert f">T{i:05d}<" in body
    n_rows = body.count("<tr") - 1
    assert R.TABLE_ROWS <= n_rows <= R.TABLE_ROWS + len(undecided)
    assert f"{n - n_rows} more targets within tolerance" in html


def test_small_report_lists_every_target():
    html = R.render_html(_doc(50, [7], []), {})
    assert html.split('<table id="targets">')[1].count("<tr") == 51 and "more-targets" not in html
