"""Random parts with known truth for whole-job tests: plates with bosses, pockets and flanges, curved skins.

:func:`make_part_job` writes a job folder (mesh STL, targets CSV, deviations CSV, job.toml) for the
simulated cell. The part is built from boxes and cylinders (joined by concatenation: the ray caster and
the renderer only need the outer surfaces) or is a thin box bent into a curved skin; 100-400 dots are
placed on its outer faces where a whole dot fits on one flat patch (checked by projecting its rim onto
the surface), with a random tolerance each. Deviations (the simulated part differs from CAD by them)
are drawn on a share of the targets at 0.5x, 3x or 10x their tolerance or at ``five_sigma_m``, in
random directions. Everything comes from one ``numpy.random.Generator``: a seed is a part.

    python -m tests.partgen OUT_DIR [--seed 3]     writes a job folder and prints its summary
"""
from __future__ import annotations

import argparse
import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from planning.clear_area import disc_on_surface

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "bracket"
KINDS = ("plate", "skin")


@dataclass(frozen=True)
class GeneratedPart:
    folder: Path
    job: Path
    kind: str
    n_targets: int
    deviations: dict  # id -> (3,) mm
    categories: dict  # id -> "0.5x" | "3x" | "10x" | "5sigma"


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))


def _plate(rng) -> tuple[trimesh.Trimesh, list]:
    """A plate (with an optional pocket) plus bosses and a flange; returns the mesh and its solids (for 'inside')."""
    L, W, T = rng.uniform(220, 340), rng.uniform(150, 220), rng.uniform(12, 25)
    solids = []
    if rng.random() < 0.5:  # a pocket: a floor and four walls around it
        px, py = rng.uniform(50, 0.35 * L), rng.uniform(40, 0.3 * W)
        cx, cy = rng.uniform(-0.15 * L, 0.15 * L), rng.uniform(-0.1 * W, 0.1 * W)
        depth = rng.uniform(0.4, 0.7) * T
        solids += [_box((-L / 2, -W / 2, 0), (L / 2, W / 2, T - depth)),
                   _box((-L / 2, -W / 2, T - depth), (cx - px / 2, W / 2, T)),
                   _box((cx + px / 2, -W / 2, T - depth), (L / 2, W / 2, T)),
                   _box((cx - px / 2, -W / 2, T - depth), (cx + px / 2, cy - py / 2, T)),
                   _box((cx - px / 2, cy + py / 2, T - depth), (cx + px / 2, W / 2, T))]
    else:
        solids.append(_box((-L / 2, -W / 2, 0), (L / 2, W / 2, T)))
    for _ in range(rng.integers(1, 4)):  # bosses
        r, h = rng.uniform(12, 30), rng.uniform(15, 50)
        x, y = rng.uniform(-0.35 * L, 0.35 * L), rng.uniform(-0.3 * W, 0.3 * W)
        solids.append(trimesh.creation.cylinder(radius=r, height=h, sections=48,
                                                transform=trimesh.transformations.translation_matrix((x, y, T + h / 2))))
    if rng.random() < 0.7:  # a flange standing on one long edge
        Hf, tf = rng.uniform(50, 110), rng.uniform(8, 15)
        side = rng.choice([-1, 1])
        y0 = side * W / 2
        solids.append(_box((-L / 2, min(y0, y0 - side * tf), T), (L / 2, max(y0, y0 - side * tf), T + Hf)))
    return trimesh.util.concatenate(solids), solids


def _skin(rng) -> tuple[trimesh.Trimesh, list]:
    """A thin panel bent about y (a curved skin), 300-450 mm long."""
    L, W, T = rng.uniform(300, 420), rng.uniform(160, 240), rng.uniform(6, 10)
    m = _box((-L / 2, -W / 2, 0), (L / 2, W / 2, T))
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=4.0)
    sag = rng.uniform(20, 70)  # mm at the ends
    v = v.copy()
    v[:, 2] += sag * (2 * v[:, 0] / L) ** 2
    return trimesh.Trimesh(v, f, process=True), []


def _inside_any(p: np.ndarray, solids: list, skip: int) -> np.ndarray:
    out = np.zeros(len(p), dtype=bool)
    for k, s in enumerate(solids):
        if k == skip:
            continue
        lo, hi = s.bounds
        out |= np.all((p > lo + 1e-3) & (p < hi - 1e-3), axis=1) & s.contains(p)
    return out


def _flat_spots(rng, mesh: trimesh.Trimesh, solids: list, count: int, spacing_mm: float,
                rim_mm: float, gap_mm: float = 0.15, min_cos: float = 0.995) -> tuple[np.ndarray, np.ndarray]:
    """Points on the outer surface where a disc of radius ``rim_mm`` lies on one flat patch, spaced apart (its rim
    within ``gap_mm`` of the surface, the surface's normal there within ``acos(min_cos)`` of the disc's)."""
    pts, fi = trimesh.sample.sample_surface(mesh, count, seed=int(rng.integers(1 << 31)))
    kept: list[int] = []  # greedy thinning to the spacing (a Poisson-disc set)
    from scipy.spatial import cKDTree

    tree = cKDTree(pts)
    taken = np.zeros(len(pts), dtype=bool)
    for k in range(len(pts)):
        if not taken[k]:
            kept.append(k)
            taken[tree.query_ball_point(pts[k], spacing_mm)] = True
    pts, fi = pts[kept], fi[kept]
    nrm = mesh.face_normals[fi]
    keep = nrm[:, 2] > -0.3  # not on the underside (the part stands on it)
    # a whole dot (and a margin) must lie on one flat patch: its rim projected onto the surface stays in plane
    keep &= disc_on_surface(mesh, pts, nrm, rim_mm, gap_mm, min_cos)
    if solids:  # on the outside of the joined solids only (not on a face buried in a neighbour)
        keep &= ~_inside_any(pts + 0.5 * nrm, solids, -1)
    return pts[keep], nrm[keep]


def _scale_bars(mesh: trimesh.Trimesh, xyz: np.ndarray, nrm: np.ndarray, clean: list[int], n_bars: int,
                clear_mm: float = 12.0) -> list[tuple[int, int]]:
    """``n_bars`` scale bars (pairs of dots) as an operator sets them up: each end on the top, on a clear area (no
    edge of the part within ``clear_mm``: a dot next to an edge is centred off by the ground beyond it, outward on
    average, which a bar's length turns into a scale error), the bars as long as the part allows, no dot the end of
    two bars and the ends of different bars apart (their errors independent). The longest bar first."""
    top = [k for k in clean if nrm[k, 2] > 0.7]  # on top: seen by many images
    ok = disc_on_surface(mesh, xyz[top], nrm[top], clear_mm, 0.6, 0.98, rings=3) if top else np.zeros(0, bool)
    cand = [k for k, good in zip(top, ok) if good]
    if len(cand) < 2:  # a part without a clear area: the top dots, else any clean ones
        cand = top if len(top) >= 2 else clean
    P = xyz[cand]
    dist = np.linalg.norm(P[:, None] - P[None], axis=2)
    order = np.dstack(np.unravel_index(np.argsort(-dist, axis=None), dist.shape))[0]
    bars: list[tuple[int, int]] = []
    ends: list[np.ndarray] = []
    for i, j in order:
        if len(bars) == n_bars or dist[i, j] <= 0:
            break
        if i < j and all(min(np.linalg.norm(P[i] - e), np.linalg.norm(P[j] - e)) > 30.0 for e in ends):
            bars.append((cand[i], cand[j]))
            ends += [P[i], P[j]]
    return bars


def _place_targets(rng, mesh: trimesh.Trimesh, solids: list, n: int, dot_mm: float, n_coded: int,
                   coded_mm: float, curved: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``n`` dots and up to ``n_coded`` coded markers (ArUco, for identification and ``cell locate``).

    On a ``curved`` part (a skin) no patch of a marker's size is flat: the markers are rigid plates that touch the
    surface at their centre and stand off it by at most 1 mm at their rim (the simulator renders them as the flat
    squares they are, and ``cell locate`` models them so)."""
    gap, cos = (1.0, 0.98) if curved else (0.15, 0.995)
    cp, cn = _flat_spots(rng, mesh, solids, 4000, 0.5 * coded_mm, 0.8 * coded_mm, gap, cos)
    pick: list[int] = []
    for k in rng.permutation(len(cp)):  # spread the markers: at least three marker sizes apart
        if len(pick) < n_coded and all(np.linalg.norm(cp[k] - cp[j]) > 3 * coded_mm for j in pick):
            pick.append(int(k))
    cp, cn = cp[pick], cn[pick]
    pts, nrm = _flat_spots(rng, mesh, solids, 20000, 2.6 * dot_mm, 0.75 * dot_mm)
    if len(cp):  # no dot under (or touching) a marker
        far = np.min(np.linalg.norm(pts[:, None] - cp[None], axis=2), axis=1) > 1.2 * coded_mm  # marker, quiet zone and a dot
        pts, nrm = pts[far], nrm[far]
    order = rng.permutation(len(pts))[: min(n, len(pts))]
    return pts[order], nrm[order], cp, cn


def toml_inline(d: dict) -> str:
    """A flat dict of numbers and lists of numbers as a TOML inline table."""
    def one(v):
        return "[" + ", ".join(f"{x:.6g}" for x in v) + "]" if isinstance(v, (list, tuple)) else f"{v:.6g}"
    return "{ " + ", ".join(f"{k} = {one(v)}" for k, v in d.items()) + " }"


def draw_lens(rng: np.random.Generator) -> dict:
    """A real lens, as lens calibrations of machine-vision lenses find them
    (decision 0054): the principal distance 1.6 % beyond the focal length (focused at about 500 mm) +- 0.5 %, the
    principal point 15 px off the centre, barrel distortion with k2 and k3 of either sign, decentring of 2e-4."""
    return {"principal_distance_factor": 1.016 + 0.005 * rng.standard_normal(),
            "principal_point_offset_px": [15.0 * rng.standard_normal(), 15.0 * rng.standard_normal()],
            "k1": rng.uniform(-0.12, 0.02), "k2": 0.08 * rng.standard_normal(), "k3": 0.04 * rng.standard_normal(),
            "p1": 2e-4 * rng.standard_normal(), "p2": 2e-4 * rng.standard_normal()}


def make_part_job(out: Path, rng: np.random.Generator, kind: str | None = None, n_targets: int | None = None,
                  deviating_share: float | None = None, five_sigma_m: float = 25e-6,
                  misplacement: tuple[float, float] | None = None, bar_sigma_mm: float = 0.001,
                  n_bars: int = 4, real_lens: bool = True) -> GeneratedPart:
    """Write a random part's job folder into ``out``; returns what was made (with the injected truth).

    ``n_bars``: how many scale bars (:func:`_scale_bars`; one is written as ``[job] scale_bar``, more as
    ``scale_bars``); fewer where the part has no room for more. Four bars certified to 1 um by default: with one bar
    (2 um) the certificate carried 15-50 % of a target's variance, and one draw of it moved a run's truth ratio out
    of 1.00 +- 0.15 on either side however honest the statement (decisions 0041-0043).
    ``bar_sigma_mm``: each bar certificate's stated sigma; a certificate is off its bar's true length by a draw of
    it (the same standard normal draws for a seed whatever the sigma).

    ``real_lens``: the simulated camera's lens is not the nominal one of ``[camera]`` (``[sim] lens``, drawn by
    :func:`draw_lens` from a child stream; decision 0054).

    ``misplacement``: (mm, deg) by which the simulated part lies away from its nominal placement (shifted on
    the table, turned about the vertical; ``[sim] base_from_part_true``), for jobs that locate the part first.
    """
    out.mkdir(parents=True, exist_ok=True)
    kind = kind or str(rng.choice(KINDS))
    mesh, solids = _plate(rng) if kind == "plate" else _skin(rng)
    mesh.apply_translation([0.0, 0.0, -mesh.bounds[0, 2]])
    dot = 5.0
    n = int(n_targets or rng.integers(100, 401))
    coded_mm = 20.0
    xyz, nrm, cxyz, cnrm = _place_targets(rng, mesh, solids, n, dot, 8, coded_mm, curved=kind == "skin")
    n = len(xyz)
    ids = [f"T{k + 1:04d}" for k in range(n)]
    # mm; at 10x the largest moves a dot 2.5 mm, a fifth of the dot spacing: MEASURE names dots by projecting
    # the nominal targets, so a dot moved by half the spacing takes its neighbour's name (a limit of the cell)
    tol = rng.choice([0.05, 0.1, 0.15, 0.2, 0.25], size=n)
    mesh.export(out / "part.stl")
    with (out / "targets.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["id", "x", "y", "z", "nx", "ny", "nz", "kind", "tolerance", "code"])
        for k, (p, q) in enumerate(zip(cxyz, cnrm)):
            w.writerow([f"C{k}", *(f"{v:.4f}" for v in p), *(f"{v:.6f}" for v in q), "coded", "", k])
        for i, p, q, t in zip(ids, xyz, nrm, tol):
            w.writerow([i, *(f"{v:.4f}" for v in p), *(f"{v:.6f}" for v in q), "retro", f"{t:g}", -1])
    share = float(rng.uniform(0.0, 0.5) if deviating_share is None else deviating_share)
    chosen = rng.choice(n, int(round(share * n)), replace=False)
    deviations, categories = {}, {}
    for j in chosen:
        cat = str(rng.choice(["0.5x", "3x", "10x", "5sigma"]))
        size = {"0.5x": 0.5 * tol[j], "3x": 3 * tol[j], "10x": 10 * tol[j], "5sigma": five_sigma_m * 1e3}[cat]
        d = rng.normal(size=3)
        deviations[ids[j]] = d / np.linalg.norm(d) * size
        categories[ids[j]] = cat
    with (out / "deviations.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["id", "dx", "dy", "dz"])
        for i, d in deviations.items():
            w.writerow([i, *(f"{v:.5f}" for v in d)])
    # the scale bars: long ones between targets that carry no deviation, their ends on a clear area
    bars = _scale_bars(mesh, xyz, nrm, [k for k in range(n) if ids[k] not in deviations], n_bars)
    text = (EXAMPLE / "job.toml").read_text()
    text = text.replace('name = "bracket"', f'name = "gen-{kind}"').replace('mesh = "bracket.stl"', 'mesh = "part.stl"')
    # a bar's certificate is a calibration like any other: its length is off the true one by a draw of its stated
    # sigma (1 um), so a run realises the certificates' share of every target's uncertainty as a real cell does; each
    # bar its own draw. Drawn from a child stream: the part, its deviations and its plan are the same as without it.
    bar_sigma = float(bar_sigma_mm)
    draws = rng.spawn(1)[0].standard_normal(len(bars))
    # the targets are adhesive dots 0.05-0.3 mm thick (decision 0049): the camera sees their faces, the job says how
    # thick they are, and a bar's certificate is the length between its ends' faces. A child stream of its own.
    thickness = round(float(rng.spawn(1)[0].uniform(0.05, 0.3)), 2)
    face = xyz + thickness * nrm
    tables = [f'{{ a = "{ids[a]}", b = "{ids[b]}", length = {np.linalg.norm(face[a] - face[b]) + bar_sigma * z:.5f}, '
              f'sigma = {bar_sigma} }}' for (a, b), z in zip(bars, draws)]
    line = f"scale_bar = {tables[0]}" if len(tables) == 1 else f"scale_bars = [{', '.join(tables)}]"
    text = re.sub(r"(?m)^scale_bar = .*$", lambda m: line, text)
    text = re.sub(r"(?m)^seed = 7$", f"seed = {int(rng.integers(1, 1000))}", text)
    text = re.sub(r"(?m)^target_diameter = .*$", f"target_diameter = {dot}\ntarget_thickness = {thickness}", text)
    text = re.sub(r"(?m)^coded_size = .*$", f"coded_size = {coded_mm}", text)
    # a dot the viewing sphere cannot see min_rays times (a low side face, under a flange) is reported not measured:
    # the generator places dots anywhere on the outside, as a designer would
    text = text.replace("[planning]\n", "[planning]\nn_candidates = 800\npopulation = 40\ngenerations = 40\n"
                        'unmeasurable = "report"\n', 1)
    text = re.sub(r"(?m)^seed = 11$", f"seed = {int(rng.integers(1, 1000))}", text)
    if real_lens:  # a real lens is not its data sheet (decision 0054): a child stream of its own
        lens = draw_lens(rng.spawn(1)[0])
        text, found = re.subn(r"(?m)^lens = .*$", lambda m: f"lens = {toml_inline(lens)}", text)
        if found == 0:
            text = text.replace("[sim]\n", f"[sim]\nlens = {toml_inline(lens)}\n", 1)
    else:  # the simulated lens is the nominal one
        text = re.sub(r"(?m)^lens = .*\n", "", text)
    if misplacement is not None:  # the part lies shifted on the table and turned about the vertical
        mm, deg = misplacement
        m = re.search(r"(?m)^base_from_part = \{ xyz = \[([^\]]*)\], rpy_deg = \[([^\]]*)\] \}", text)
        xyz0 = np.array([float(v) for v in m.group(1).split(",")])
        rpy0 = np.array([float(v) for v in m.group(2).split(",")])
        ang = rng.uniform(0, 2 * np.pi)
        xyz1 = xyz0 + mm * np.array([np.cos(ang), np.sin(ang), 0.0])
        rpy1 = rpy0 + np.array([0.0, 0.0, deg * rng.choice([-1, 1])])
        text += (f"base_from_part_true = {{ xyz = [{xyz1[0]:.3f}, {xyz1[1]:.3f}, {xyz1[2]:.3f}], "
                 f"rpy_deg = [{rpy1[0]:.3f}, {rpy1[1]:.3f}, {rpy1[2]:.3f}] }}\n")
    (out / "job.toml").write_text(text)
    return GeneratedPart(out, out / "job.toml", kind, n, deviations, categories)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--kind", choices=KINDS)
    a = ap.parse_args(argv)
    g = make_part_job(a.out, np.random.default_rng(a.seed), a.kind)
    print(f"{g.kind}: {g.n_targets} targets, {len(g.deviations)} deviating -> {g.job}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
