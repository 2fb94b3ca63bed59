"""The report's interactive 3-D views: plotly figures embedded in report.html, self-contained.

The figures are plain plotly JSON (traces and layout) built here from numpy arrays; plotly.js itself
is embedded once per report, gzip-compressed and base64-encoded (about 2.0 MB instead of 4.8 MB),
and unpacked in the browser with the standard DecompressionStream when the 3-D section scrolls into
view, so the report still opens offline as one file, and at once. A person can turn, zoom and hover (target id, deviation, tolerance).
"""
from __future__ import annotations

import base64
import gzip
import json
from functools import lru_cache
from pathlib import Path

import numpy as np


@lru_cache(maxsize=1)
def _plotly_gz_b64() -> str | None:
    try:
        import plotly
    except ImportError:
        return None
    js = (Path(plotly.__file__).parent / "package_data" / "plotly.min.js").read_bytes()
    return base64.b64encode(gzip.compress(js, compresslevel=9, mtime=0)).decode()


def _mesh_trace(mesh, opacity: float = 0.25) -> dict:
    v = np.asarray(mesh.vertices) * 1000.0
    f = np.asarray(mesh.faces)
    return {"type": "mesh3d", "x": np.round(v[:, 0], 3).tolist(), "y": np.round(v[:, 1], 3).tolist(),
            "z": np.round(v[:, 2], 3).tolist(), "i": f[:, 0].tolist(), "j": f[:, 1].tolist(), "k": f[:, 2].tolist(),
            "color": "#9aa5b1", "opacity": opacity, "hoverinfo": "skip", "name": "part", "flatshading": True}


_SCENE = {"aspectmode": "data", "xaxis": {"title": "x [mm]"}, "yaxis": {"title": "y [mm]"}, "zaxis": {"title": "z [mm]"}}


def network_3d(mesh, stations_part_from_cam: np.ndarray, xyz: np.ndarray, ids: list[str]) -> dict:
    """Part, targets (hover: id) and camera stations (hover: station number), in mm."""
    p = np.asarray(xyz) * 1000
    traces = [_mesh_trace(mesh),
              {"type": "scatter3d", "mode": "markers", "x": p[:, 0].tolist(), "y": p[:, 1].tolist(), "z": p[:, 2].tolist(),
               "text": list(ids), "hovertemplate": "%{text}<extra></extra>", "marker": {"size": 2.5, "color": "#222"},
               "name": "targets"}]
    lx, ly, lz, cx, cy, cz, names = [], [], [], [], [], [], []
    for k, T in enumerate(np.asarray(stations_part_from_cam)):
        c = T[:3, 3] * 1000
        R = T[:3, :3]
        s = 40.0
        corners = [c + s * (R @ np.array([x, y, 1.5])) for x, y in ((-1, -0.8), (1, -0.8), (1, 0.8), (-1, 0.8))]
        for q in corners + [corners[0]]:
            lx += [c[0], q[0], None]
            ly += [c[1], q[1], None]
            lz += [c[2], q[2], None]
        ring = np.array(corners + corners[:1])
        lx += [*ring[:, 0], None]
        ly += [*ring[:, 1], None]
        lz += [*ring[:, 2], None]
        cx.append(c[0])
        cy.append(c[1])
        cz.append(c[2])
        names.append(f"station {k + 1}")
    traces.append({"type": "scatter3d", "mode": "lines", "x": lx, "y": ly, "z": lz, "hoverinfo": "skip",
                   "line": {"color": "#1f77b4", "width": 2}, "name": "cameras"})
    traces.append({"type": "scatter3d", "mode": "markers", "x": cx, "y": cy, "z": cz, "text": names,
                   "hovertemplate": "%{text}<extra></extra>", "marker": {"size": 3, "color": "#1f77b4"},
                   "name": "stations"})
    return {"data": traces, "layout": {"title": {"text": f"Network: {len(names)} stations (drag to turn)"},
                                       "scene": _SCENE, "margin": {"l": 0, "r": 0, "t": 40, "b": 0}, "height": 560}}


def deviations_3d(mesh, nominal: np.ndarray, ids: list[str], dev_norm: np.ndarray, tol: np.ndarray,
                  passed: np.ndarray) -> dict:
    """Targets on the part coloured by |deviation| / tolerance; hover: id, |d|, tolerance, pass/fail."""
    p = np.asarray(nominal) * 1000
    ratio = np.clip(np.nan_to_num(np.asarray(dev_norm) / np.asarray(tol), nan=2.0, posinf=2.0), 0, 2)
    text = [f"{i}: |d| {'not measured' if not np.isfinite(d) else f'{d * 1e6:.1f} um'} / tol {t * 1e6:.1f} um "
            f"{'PASS' if ok else 'FAIL'}" for i, d, t, ok in zip(ids, dev_norm, tol, passed)]
    bad = ~np.asarray(passed, dtype=bool)
    traces = [_mesh_trace(mesh, 0.18),
              {"type": "scatter3d", "mode": "markers", "x": p[:, 0].tolist(), "y": p[:, 1].tolist(),
               "z": p[:, 2].tolist(), "text": text, "hovertemplate": "%{text}<extra></extra>", "name": "targets",
               "marker": {"size": 4, "color": ratio.tolist(), "colorscale": [[0, "#1a7f37"], [0.5, "#f2cc60"], [1, "#cf222e"]],
                          "cmin": 0, "cmax": 2, "colorbar": {"title": {"text": "|d| / tol"}}}}]
    if bad.any():
        traces.append({"type": "scatter3d", "mode": "markers", "x": p[bad, 0].tolist(), "y": p[bad, 1].tolist(),
                       "z": p[bad, 2].tolist(), "text": [t for t, b in zip(text, bad) if b],
                       "hovertemplate": "%{text}<extra></extra>", "name": "out of tolerance",
                       "marker": {"size": 9, "color": "rgba(0,0,0,0)", "line": {"color": "#cf222e", "width": 3}}})
    return {"data": traces, "layout": {"title": {"text": "Deviation from CAD (drag to turn, hover a target)"},
                                       "scene": _SCENE, "showlegend": False, "margin": {"l": 0, "r": 0, "t": 40, "b": 0}, "height": 560}}


def html_block(figures: dict[str, dict]) -> str:
    """The interactive section of report.html: one div per figure and the embedded plotly.js that draws them."""
    payload = _plotly_gz_b64()
    if payload is None or not figures:
        return ""
    divs = "".join(f'<div class="fig3d" id="fig3d-{k}"></div>' for k in figures)
    meshes: list[dict] = []  # the part's mesh once, however many views show it
    keys: dict[str, int] = {}
    figs = {}
    for name, f in figures.items():
        data = []
        for t in f["data"]:
            if t.get("type") == "mesh3d":
                body = {k: v for k, v in t.items() if k != "opacity"}
                key = json.dumps(body, sort_keys=True)
                if key not in keys:
                    keys[key] = len(meshes)
                    meshes.append(body)
                t = {"$mesh": keys[key], "opacity": t.get("opacity", 1.0)}
            data.append(t)
        figs[name] = {"data": data, "layout": f["layout"]}
    specs = json.dumps(figs, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")
    mesh_js = json.dumps(meshes, separators=(",", ":"), allow_nan=False)
    return f"""<h2 class="noprint">3-D views</h2><div class="noprint" id="views3d">{divs}</div>
<script id="plotly-gz" type="application/octet-stream">{payload}</script>
<script>
(function () {{
  const FIGS = {specs};
  const MESHES = {mesh_js};
  for (const f of Object.values(FIGS))
    f.data = f.data.map(t => t.$mesh !== undefined ? Object.assign({{}}, MESHES[t.$mesh], {{opacity: t.opacity}}) : t);
  let started = false;
  async function draw() {{  // unpacked and drawn when the section comes into view: a long report opens at once
    if (started) return; started = true;
    try {{
      const raw = Uint8Array.from(atob(document.getElementById('plotly-gz').textContent), c => c.charCodeAt(0));
      const js = await new Response(new Blob([raw]).stream().pipeThrough(new DecompressionStream('gzip'))).text();
      const s = document.createElement('script'); s.textContent = js; document.head.appendChild(s);
      for (const [k, f] of Object.entries(FIGS)) Plotly.newPlot('fig3d-' + k, f.data, f.layout, {{responsive: true}});
      document.body.dataset.fig3d = 'ready';
    }} catch (e) {{ document.body.dataset.fig3d = 'failed: ' + e; }}
  }}
  const box = document.getElementById('views3d');
  new IntersectionObserver(es => {{ if (es.some(e => e.isIntersecting)) draw(); }}, {{rootMargin: '300px'}}).observe(box);
}})();
</script>"""
