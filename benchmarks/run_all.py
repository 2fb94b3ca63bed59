"""Run every benchmark of the project and write one table: docs/benchmarks.md (and docs/paper_reproduction.md).

    .venv/bin/python benchmarks/run_all.py [--only bundle render ...] [--skip-examples] [--timeout 900]

Each ``benchmarks/bench_*.py`` is run as its own process from the repository root (with the root and
``benchmarks/`` on the import path, as each script expects), its output is kept verbatim in the
document, and its headline figures are read from it:

* a line ``BENCHMARK {json}`` with keys ``what``, ``figure``, ``baseline``, ``ratio`` is used as it is
  (the machine-readable form every benchmark should print; see ``SUMMARY_PREFIX``);
* otherwise a parser below reads the script's human output (one per script, written against its
  current wording; a row says "not parsed" when the wording changed, and the raw output stays in the
  document).

The paper experiments (``examples/calibration_grid``, ``examples/complex_object``) are run too and add
their timing rows; their results also make docs/paper_reproduction.md. Every figure in both documents
comes from the run that wrote them.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
SUMMARY_PREFIX = "BENCHMARK "
PY = sys.executable


@dataclass
class Row:
    name: str
    what: str
    figure: str
    baseline: str
    ratio: str
    command: str
    seconds: float
    ok: bool


def _num(pattern: str, text: str, group: int = 1) -> float | None:
    m = re.search(pattern, text)
    return float(m.group(group).replace(",", "")) if m else None


def _p_bundle(out: str) -> dict:
    ours = _num(r"bundle_adjust .*?: best ([\d.]+) s", out)
    theirs = _num(r"pycolmap solve alone: best ([\d.]+) s", out)
    net = re.search(r"network: (.*?), (\d+) observations", out)
    return {"what": f"bundle adjustment with covariance ({net.group(1) if net else '?'})",
            "figure": f"{ours:.3f} s" if ours is not None else None,
            "baseline": f"pycolmap's solve alone {theirs:.3f} s" if theirs is not None else None,
            "ratio": f"{ours / theirs:.2f}x (ours / pycolmap solve)" if ours and theirs else None}


def _p_criterion(out: str) -> dict:
    fast = _num(r"vectorised, float32 table, 2 threads: ([\d,]+) evaluations/s", out)
    naive = _num(r"naive per-network loop \(float64\):\s+([\d,]+) evaluations/s", out)
    size = re.search(r"(\d+) candidates x (\d+) measurable targets; population (\d+) networks of (\d+) stations", out)
    what = ("planner criterion: network evaluations/s"
            + (f" ({size.group(4)} stations, {size.group(2)} targets, {size.group(1)} candidates)" if size else ""))
    return {"what": what, "figure": f"{fast:,.0f} evaluations/s" if fast else None,
            "baseline": f"naive per-network loop {naive:,.0f} evaluations/s" if naive else None,
            "ratio": f"{fast / naive:.1f}x faster" if fast and naive else None}


def _p_detection(out: str) -> dict:
    best = _num(r"detection: best ([\d.]+) ms", out)
    base = _num(r"baseline scipy.ndimage \(label \+ center_of_mass\): best ([\d.]+) ms", out)
    std = re.search(r"std \(([\d.]+), ([\d.]+)\) px", out)
    img = re.search(r"image (\S+) \(([\d.]+) MP\), (\d+) targets", out)
    return {"what": "retro-target detection" + (f" ({img.group(2)} MP, {img.group(3)} targets)" if img else ""),
            "figure": (f"{best:.1f} ms; centre std {std.group(1)}/{std.group(2)} px" if best and std else None),
            "baseline": (f"scipy.ndimage label + center_of_mass {base:.1f} ms" if base else "target <= 100 ms"),
            "ratio": (f"{base / best:.2f}x faster; {best / 100:.2f} of the 100 ms budget" if best and base
                      else f"{best / 100:.2f} of the time budget" if best else None)}


def _p_reachability(out: str) -> dict:
    vec = _num(r"vectorised reachability \(with collision margins\): ([\d.]+) s", out)
    base = _num(r"baseline per-station loop:\s+([\d.]+) s", out)
    n = re.search(r"robot (\S+), (\d+) stations", out)
    return {"what": "reachability database" + (f" ({n.group(2)} stations, {n.group(1)})" if n else ""),
            "figure": f"{vec:.3f} s" if vec is not None else None,
            "baseline": f"per-station loop {base:.3f} s" if base is not None else None,
            "ratio": f"{base / vec:.1f}x faster" if vec and base else None}


def _p_render(out: str) -> dict:
    a = _num(r"adaptive \(default\)\s+([\d.]+) ms/image", out)
    b = _num(r"baseline \(all pixels\)\s+([\d.]+) ms/image", out)
    img = re.search(r"image (\d+) x (\d+), (\d+) targets rendered", out)
    return {"what": "SimCamera render" + (f" ({img.group(1)} x {img.group(2)}, {img.group(3)} targets)" if img else ""),
            "figure": f"{a:.1f} ms/image" if a is not None else None,
            "baseline": f"supersampling every pixel {b:.1f} ms/image" if b is not None else None,
            "ratio": f"{b / a:.1f}x faster" if a and b else None}


def _p_visibility(out: str) -> dict:
    rays = re.search(r"embree segment test \(all ([\d,]+) candidate x target rays, 2 threads\): ([\d.]+) s, ([\d.]+) M rays/s", out)
    tri = _num(r"trimesh ray_pyembree intersects_any .*?: ([\d.]+) M rays/s", out)
    build = re.search(r"visibility database build \((\d+) candidates x (\d+) targets.*?\): ([\d.]+) s", out)
    fig = []
    if rays:
        fig.append(f"{rays.group(3)} M rays/s")
    if build:
        fig.append(f"database {build.group(1)} x {build.group(2)} in {build.group(3)} s")
    return {"what": "visibility (segment ray casting, database build)", "figure": "; ".join(fig) or None,
            "baseline": f"trimesh intersects_any {tri} M rays/s" if tri else None,
            "ratio": f"{float(rays.group(3)) / tri:.1f}x faster" if rays and tri else None}


PARSERS: dict[str, Callable[[str], dict]] = {
    "bench_bundle": _p_bundle, "bench_criterion": _p_criterion, "bench_detection": _p_detection,
    "bench_reachability": _p_reachability, "bench_render": _p_render,
    "bench_visibility": _p_visibility,
}
#: arguments that keep a benchmark within a few minutes here (none: its defaults)
ARGS: dict[str, list[str]] = {"bench_planner": ["--quick", "--bound"]}


def run_one(path: Path, timeout: float) -> tuple[Row, str]:
    name = path.stem
    args = ARGS.get(name, [])
    cmd = f".venv/bin/python benchmarks/{path.name}" + (" " + " ".join(args) if args else "")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(BENCH)]), MPLBACKEND="Agg")
    t0 = time.perf_counter()
    try:
        p = subprocess.run([PY, str(path), *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
        out, ok = p.stdout + (("\n[stderr]\n" + p.stderr[-3000:]) if p.returncode else ""), p.returncode == 0
    except subprocess.TimeoutExpired as exc:
        out, ok = (exc.stdout or b"").decode() if isinstance(exc.stdout, bytes) else (exc.stdout or ""), False
        out += f"\n[timed out after {timeout:.0f} s]"
    dt = time.perf_counter() - t0
    fields: dict = {}
    for line in out.splitlines():
        if line.startswith(SUMMARY_PREFIX):
            try:
                fields = json.loads(line[len(SUMMARY_PREFIX):])
            except json.JSONDecodeError:
                pass
    if not fields and name in PARSERS and ok:
        try:
            fields = PARSERS[name](out)
        except (AttributeError, TypeError, ValueError, ZeroDivisionError):
            fields = {}
    na = "not parsed" if ok else "FAILED (see output)"
    row = Row(name, str(fields.get("what") or name), str(fields.get("figure") or na),
              str(fields.get("baseline") or "-"), str(fields.get("ratio") or "-"), cmd, dt, ok)
    return row, out


def run_examples(timeout: float) -> tuple[list[Row], dict, dict[str, str]]:
    rows, results, outputs = [], {}, {}
    for ex in ("calibration_grid", "complex_object"):
        cmd = f".venv/bin/python examples/{ex}/run_experiment.py"
        t0 = time.perf_counter()
        p = subprocess.run([PY, str(ROOT / "examples" / ex / "run_experiment.py")], cwd=ROOT, capture_output=True,
                           text=True, timeout=timeout, env=dict(os.environ, MPLBACKEND="Agg"))
        dt = time.perf_counter() - t0
        outputs[ex] = p.stdout + (("\n[stderr]\n" + p.stderr[-3000:]) if p.returncode else "")
        if p.returncode:
            rows.append(Row(ex, ex, "FAILED (see output)", "-", "-", cmd, dt, False))
            continue
        r = json.loads((ROOT / "examples" / ex / "results.json").read_text())
        results[ex] = r
        if ex == "complex_object":
            pl, b, paper = r["planning"], r["bundle_planned"], r["paper"]
            rows.append(Row("paper_planning", f"paper Fig. 11: planning {pl['images']} images (visibility + UR5e "
                            f"reachability + search, cold cache, {r['object']['features']} features)",
                            f"{pl['time_s']:.1f} s", "paper: under 5 min (Pentium IV 2.4 GHz)",
                            f"<= {pl['time_s'] / paper['planning_s']:.4f} of the paper's", cmd, dt, True))
            rows.append(Row("paper_bundle", f"paper Fig. 11: bundle adjustment of {pl['images']} images with "
                            f"covariance ({b['observations']} observations)", f"{b['time_s']:.2f} s",
                            "paper: about 150 min (Pentium IV 2.4 GHz)",
                            f"{b['time_s'] / paper['bundle_s']:.1e} of the paper's", cmd, dt, True))
        else:
            c = r["cases"]
            rows.append(Row("paper_grid", "paper Figs. 6-7: median error-ellipsoid volume, close pair vs convergent pair",
                            f"{c['close_pair']['all']['volume_um3_median']:.3g} vs "
                            f"{c['convergent_pair']['all']['volume_um3_median']:.3g} um^3",
                            "paper: close pair visibly larger (figure only)",
                            f"{c['close_pair']['all']['volume_um3_median'] / c['convergent_pair']['all']['volume_um3_median']:.0f}x",
                            cmd, dt, True))
    return rows, results, outputs


def _machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cpus, Python {platform.python_version()}"


def write_benchmarks_md(rows: list[Row], outputs: dict[str, str], path: Path) -> None:
    lines = [
        "# Benchmarks",
        "",
        "Generated by `.venv/bin/python benchmarks/run_all.py`; do not edit by hand. Every figure below comes",
        f"from that run ({time.strftime('%Y-%m-%d %H:%M')}, {_machine()}). The full output of each benchmark is",
        "kept below the table.",
        "",
        "| benchmark | what | figure | baseline | ratio | command | run time |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r.name} | {r.what} | {r.figure} | {r.baseline} | {r.ratio} | `{r.command}` | {r.seconds:.0f} s |")
    lines += ["", "## Outputs", ""]
    for name, out in outputs.items():
        lines += [f"### {name}", "", "```", out.strip(), "```", ""]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines))


def write_paper_md(results: dict, path: Path) -> None:
    """docs/paper_reproduction.md from the two examples' results.json."""
    g, c = results.get("calibration_grid"), results.get("complex_object")
    lines = ["# Reproducing the seed paper's experiments", "",
             "Generated by `.venv/bin/python benchmarks/run_all.py` from `examples/*/results.json`; do not edit by",
             "hand. The paper: *Development of a practical photogrammetric network design using evolutionary",
             "computing* (EPOCA). Its real cameras and robot are replaced by the simulated cell: images are rendered",
             "by `SimCamera` and measured by the cell's own detector, so every result can be checked against a known",
             "truth. Details, figures and caveats: `examples/calibration_grid/README.md`,",
             "`examples/complex_object/README.md`.", ""]
    if g:
        cs = g["cases"]
        t = cs["partial_triple"]
        lines += ["## Calibration grid (paper Figs. 5-8)", "",
                  f"{g['grid']['targets']} retro targets on two orthogonal panels, 20 images from a nominal Pulnix "
                  f"TM-6EX + 12.5 mm lens ({g['camera_true']['width']} x {g['camera_true']['height']}, 8.4 x 9.8 um "
                  "pixels). Faugeras-Toscani per image, then bundle adjustment.", "",
                  "| paper | what it shows | here |", "|---|---|---|",
                  f"| Fig. 6 vs Fig. 7 | close pair: larger, elongated ellipsoids; convergent pair: small | median volume "
                  f"{cs['close_pair']['all']['volume_um3_median']:.3g} vs {cs['convergent_pair']['all']['volume_um3_median']:.3g} "
                  f"um^3; elongation {cs['close_pair']['all']['elongation_median']:.1f} vs "
                  f"{cs['convergent_pair']['all']['elongation_median']:.1f} |",
                  f"| Fig. 8 | targets seen by only two images have bigger ellipsoids | median volume "
                  f"{t['seen_by_2']['volume_um3_median']:.3g} um^3 ({t['seen_by_2']['n']} targets seen twice) vs "
                  f"{t['seen_by_3']['volume_um3_median']:.3g} um^3 ({t['seen_by_3']['n']} seen three times) |",
                  f"| calibration | Faugeras-Toscani initialises the bundle adjustment | self-calibrated fx "
                  f"{g['camera_calibrated']['fx_px']:.2f} px (true {g['camera_true']['fx_px']:.2f}), sigma0 "
                  f"{g['full_adjustment']['sigma0_px']:.4f} px |", ""]
    if c:
        n = c["networks"]
        lines += ["## Complex object (paper Figs. 9-11)", "",
                  f"A self-occluding object with {c['object']['features']} features (retro dots standing in for the "
                  "paper's printed corners), a nominal Pulnix TM-9701 + 16 mm lens (768 x 484, 11.6 x 13.6 um pixels), "
                  "and a **UR5e** instead of the paper's Staubli RX60B.", "",
                  "| network | features measured | sigma median (um) | sigma max (um) | homogeneity (cv) | isotropy |",
                  "|---|---|---|---|---|---|"]
        for k, label in (("weak4", "Fig. 9: 4 weakly convergent"), ("convergent4", "Fig. 10: 4 convergent"),
                         ("planned", f"Fig. 11: {c['planning']['images']} planned")):
            m = n[k]["common"]
            lines.append(f"| {label} | {n[k]['measured']}/{c['object']['features']} | {m['sigma_um_median']:.1f} | "
                         f"{m['sigma_um_max']:.1f} | {m['homogeneity_cv']:.2f} | {m['isotropy_median']:.2f} |")
        lines += ["", f"(sigma, homogeneity and isotropy over the {c['common_features']} features all three networks "
                  "measure.)", "", "| time | here | paper (Pentium IV 2.4 GHz) |", "|---|---|---|",
                  f"| planning {c['planning']['images']} images | {c['planning']['time_s']:.1f} s | under 5 min |",
                  f"| bundle adjustment with covariance | {c['bundle_planned']['time_s']:.2f} s | about 150 min |", ""]
    path.write_text("\n".join(lines))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="*", help="benchmark names without 'bench_' (default: all)")
    ap.add_argument("--skip-examples", action="store_true", help="do not run the paper examples")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per benchmark")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks.md")
    a = ap.parse_args()
    scripts = sorted(BENCH.glob("bench_*.py"))
    if a.only:
        scripts = [s for s in scripts if s.stem.removeprefix("bench_") in a.only]
    rows, outputs = [], {}
    for s in scripts:
        print(f"running {s.name} ...", file=sys.stderr, flush=True)
        row, out = run_one(s, a.timeout)
        rows.append(row)
        outputs[s.stem] = out
        print(f"  {row.figure} | {row.baseline} | {row.ratio} ({row.seconds:.0f} s)", file=sys.stderr, flush=True)
    if not a.skip_examples:
        print("running the paper examples ...", file=sys.stderr, flush=True)
        ex_rows, results, ex_out = run_examples(a.timeout)
        rows += ex_rows
        outputs.update({f"examples/{k}": v for k, v in ex_out.items()})
        write_paper_md(results, a.out.parent / "paper_reproduction.md")
    write_benchmarks_md(rows, outputs, a.out)
    print(f"wrote {a.out}", file=sys.stderr)
    return 0 if all(r.ok for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
