"""The report's residual histogram is scaled to the accepted observations (a rejected gross error
does not stretch it), the rejected ones are found and listed apart, and the 3-D views carry a label
per target."""
from __future__ import annotations

import json

import numpy as np
import trimesh

from cell.record import figures3d as F3
from cell.record.report import _rejected_table, accepted_residuals, figure_residuals
from cell.stages.report import rejected_mask


def test_rejected_observations_leave_the_histogram_and_are_listed_apart():
    rng = np.random.default_rng(0)
    res = rng.normal(0, 0.03, (400, 2))
    res[[17, 230]] = [[-15.2, 3.1], [0.9, 8.8]]  # two gross errors the bundle rejected
    bundle = {"residuals_px": json.loads(json.dumps(res.tolist())),
              "rejected": [{"image": "images/0003.png", "target": "T0094", "residual_px": res[17].tolist()},
                           {"image": "images/0009.png", "target": "T0080", "residual_px": res[230].tolist()}]}
    mask = rejected_mask(bundle)
    assert np.flatnonzero(mask).tolist() == [17, 230]
    a, lim = accepted_residuals(np.asarray(bundle["residuals_px"]), mask)
    assert len(a) == 398 and 0.08 < lim < 0.2  # the axis of 0.03 px residuals, not of -15 px
    assert accepted_residuals(res, None)[1] > 15  # what the old histogram did
    png = figure_residuals(res, mask)
    assert len(png) > 1000
    table = _rejected_table({"rejected_observations": bundle["rejected"]})
    assert "T0094" in table and "-15.20" in table and "8.80" in table and table.count("<tr>") == 3


def test_3d_views_label_every_target_and_embed_plotly():
    mesh = trimesh.creation.box((0.2, 0.1, 0.05))
    xyz = np.array([[0.0, 0.0, 0.025], [0.05, 0.02, 0.025], [-0.05, 0.01, 0.025]])
    fig = F3.deviations_3d(mesh, xyz, ["T1", "T2", "T3"], np.array([10e-6, 300e-6, np.nan]),
                           np.full(3, 250e-6), np.array([True, False, False]))
    text = fig["data"][1]["text"]
    assert text[0].startswith("T1: |d| 10.0 um / tol 250.0 um PASS") and "FAIL" in text[1] and "not measured" in text[2]
    assert fig["data"][2]["name"] == "out of tolerance" and len(fig["data"][2]["x"]) == 2
    html = F3.html_block({"deviations": fig})
    assert 'id="fig3d-deviations"' in html and "DecompressionStream" in html and len(html) > 1_000_000
