"""Measure how much of a dot's background misfit its views share: the detector model's ``rho_background``.

A dot next to an edge of the part or a step of its shading is centred off its true centre; the detector bounds
that error per image (``Detections.background_cov``, ``B``) and the model scales the bound by ``c_background``
(``c``). ADJUST adds to each target's covariance the cross terms between its views of that misfit
(calibration/bundle/coherent.py, decision 0029), modelled as a common displacement seen by each view through its
own bound: ``e_i = sqrt(rho) S_i Jh_i z + independent``, ``S_i = sqrt(c^2 B_i)``, ``Jh_i`` the view's unit-scale
projection, so that for two views ``i != j`` of one target

    E[e_i e_j^T] = rho S_i Jh_i Jh_j^T S_j^T.

Views of the example and of generated plates and skins are rendered as ``benchmarks.detector_precision`` does
(sensor noise, true poses; every uncoded dot's detected centre against the true projection plus the ellipse's
eccentricity), ``--repeats`` times each with fresh noise. For every pair of observations of one target with a
bound in both, ``e_i^T M_ij e_j`` and ``||M_ij||_F^2`` (``M_ij`` the model's matrix) are collected; ``rho`` is
their least-squares ratio over the pairs of distinct views (method of moments), with a bootstrap over targets
for its standard error. Also printed: the same on pairs of repeats of one view (the share of the bound the
view's geometry fixes; the ceiling of what distinct views can share), ``rho`` by the angle between the two
views' lines of sight (a common displacement seen through ``Jh`` gives one ``rho`` at every angle), and per
part. ``--write`` stores ``rho_background`` (clipped to [0, 1]) with its figures and this command in
``calibration/data/detector_precision.json`` (version 4).

    .venv/bin/python -m benchmarks.background_share [--views 40] [--repeats 2] [--plates 3] [--skins 3] [--write]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.detector_precision import collect_each, masked_rows  # noqa: E402
from calibration.bundle.coherent import coherent_background_cov, fit_share, share_pairs, unit_projection  # noqa: E402
from calibration.detector_model import DATA_PATH, load_model, observation_covariances  # noqa: E402

ANGLE_EDGES_DEG = (0, 10, 20, 30, 45, 60, 90, 180)
CHI2_99_3 = 11.344866730144373  # the 99 % quantile of chi^2 with 3 degrees of freedom


def part_pairs(doc: dict, model, whiten: bool = True) -> dict:
    """:func:`share_pairs` of one part's collected rows (``benchmarks.detector_precision.collect``), whitened by
    the covariance the bundle would weight each observation with (``whiten``; the detector model's sigma for the
    dot's incidence and size, its saturation term, ``c^2 B``)."""
    rows = doc["rows"]
    k, t = rows[:, 0].astype(int), rows[:, 1].astype(int)
    T, X = doc["cam_from_part"][k], doc["xyz"][t]
    Jh, _ = unit_projection(T, X)
    centre = -np.einsum("qba,qb->qa", T[:, :3, :3], T[:, :3, 3])
    sight = centre - X
    sight /= np.linalg.norm(sight, axis=1, keepdims=True)
    B = rows[:, [7, 8, 8, 9]].reshape(-1, 2, 2)
    C = None
    if whiten:
        sigma = model.sigma_px(np.radians(rows[:, 2]), rows[:, 3])
        C = observation_covariances(sigma, B, model, clipped_share=rows[:, 10] / np.maximum(rows[:, 11], 1.0),
                                    diameter_px=rows[:, 3])
    return share_pairs(rows[:, 4:6], model.c_background**2 * B, Jh, t, k, sight, C)


def point_check(doc: dict, model, shares) -> dict:
    """What the share does to a target's statement, as the truth figures judge it: each target seen in four views
    or more (first rendering of each view only) is intersected from all its views by weighted least squares with
    the true poses; its error against the truth is compared with the covariance ADJUST states (the independent
    ``N^-1`` plus :func:`coherent_background_cov` with each share). m^2 of the targets with a bound in two views or
    more, ``"edge": (len(shares), k)``; of those with a bound in one view, ``"one"``, and in none, ``"clean"`` (the
    check's control: nothing is shared there)."""
    rows = doc["rows"][doc["rows"][:, 6] == 0]
    k, t = rows[:, 0].astype(int), rows[:, 1].astype(int)
    B = rows[:, [7, 8, 8, 9]].reshape(-1, 2, 2)
    flagged = np.any(B != 0, axis=(1, 2))
    n = len(doc["xyz"])
    n_flagged = np.bincount(t[flagged], minlength=n)
    todo = np.bincount(t, minlength=n) >= 4
    sel = todo[t]
    k, t, B, rows = k[sel], t[sel], B[sel], rows[sel]
    if not len(rows):
        return {"edge": np.zeros((len(shares), 0)), "one": np.zeros(0), "clean": np.zeros(0)}
    sigma = model.sigma_px(np.radians(rows[:, 2]), rows[:, 3])
    C = observation_covariances(sigma, B, model, clipped_share=rows[:, 10] / np.maximum(rows[:, 11], 1.0),
                                    diameter_px=rows[:, 3])
    W = np.linalg.inv(C)
    T, X = doc["cam_from_part"][k], doc["xyz"][t]
    Jh, depth = unit_projection(T, X)
    J = Jh * (np.array([doc["fx_px"], doc["fy_px"]])[None, :, None] / depth[:, None, None])
    N, b = np.zeros((n, 3, 3)), np.zeros((n, 3))
    np.add.at(N, t, np.einsum("qba,qbc,qcd->qad", J, W, J))
    np.add.at(b, t, np.einsum("qba,qbc,qc->qa", J, W, rows[:, 4:6]))
    idx = np.flatnonzero(todo)
    Ni = np.linalg.inv(N[idx])
    delta = np.einsum("kab,kb->ka", Ni, b[idx])
    intr = SimpleNamespace(fx_px=doc["fx_px"], fy_px=doc["fy_px"])
    edge = n_flagged[idx] >= 2
    out = []
    for share in shares:
        E = coherent_background_cov(intr, doc["cam_from_part"], doc["xyz"], k, t, C, B, model.c_background, share)
        out.append(np.einsum("ka,kab,kb->k", delta[edge], np.linalg.inv(Ni[edge] + E[idx][edge]), delta[edge]))
    m2 = np.einsum("ka,kab,kb->k", delta, N[idx], delta)
    return {"edge": np.array(out), "one": m2[n_flagged[idx] == 1], "clean": m2[n_flagged[idx] == 0]}


def cross_moments(doc: dict) -> dict:
    """Mean cross product ``(Jh_i^T e_i) . (Jh_j^T e_j)`` (px^2) over pairs of distinct views of one target (first
    rendering of each view): of targets with a bound in two views or more, between two views with a bound (``FF``:
    what the model shares), one with and one without (``FU``), two without (``UU``); and of targets with no bound
    (``clean``). ``{name: (sum, pairs)}`` to pool over parts."""
    rows = doc["rows"][doc["rows"][:, 6] == 0]
    k, t = rows[:, 0].astype(int), rows[:, 1].astype(int)
    flagged = np.any(rows[:, 7:10] != 0, axis=1)
    Jh, _ = unit_projection(doc["cam_from_part"][k], doc["xyz"][t])
    a = np.einsum("qba,qb->qa", Jh, rows[:, 4:6])
    n_flagged = np.bincount(t[flagged], minlength=len(doc["xyz"]))
    out = {key: [0.0, 0] for key in ("FF", "FU", "UU", "clean")}
    for tt in np.unique(t):
        q = np.flatnonzero(t == tt)
        if len(q) < 2 or n_flagged[tt] == 1:
            continue
        i, j = np.triu_indices(len(q), 1)
        i, j = q[i], q[j]
        prod = np.einsum("pa,pa->p", a[i], a[j])
        groups = (("FF", flagged[i] & flagged[j]), ("FU", flagged[i] ^ flagged[j]), ("UU", ~flagged[i] & ~flagged[j])) \
            if n_flagged[tt] >= 2 else (("clean", np.ones(len(i), dtype=bool)),)
        for key, m in groups:
            out[key][0] += float(prod[m].sum())
            out[key][1] += int(m.sum())
    return out


def _fmt(num, den, tgt, min_targets=20) -> tuple[str, float | None, float | None]:
    try:
        r, s = fit_share(num, den, tgt, min_targets=min_targets)
    except ValueError:
        return "   (too few targets)", None, None
    return f"{r:6.3f} +- {s:5.3f}", r, s


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--seed", type=int, default=100, help="first view seed (the model fit used 0-6)")
    ap.add_argument("--plates", type=int, default=3)
    ap.add_argument("--skins", type=int, default=3)
    ap.add_argument("--write", action="store_true", help=f"store rho_background in {DATA_PATH}")
    ap.add_argument("--rows", help="an .npz to keep the rendered rows in (or to read them from when it exists: "
                                   "the views' arguments are then those of the run that wrote it)")
    ap.add_argument("--background-mask", choices=("none", "cad"), default="none",
                    help="measure the detector with the CAD's surface labels (decision 0035); not with --rows/--write")
    a = ap.parse_args(argv)
    if a.background_mask == "cad" and (a.rows or a.write):
        print("--background-mask cad measures the masked detector for comparison: not with --rows or --write",
              file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    model = load_model()
    c = model.c_background
    if c <= 0:
        print(f"{DATA_PATH}: c_background is {c}: nothing to share", file=sys.stderr)
        return 2
    if a.rows and Path(a.rows).exists():  # the rendered rows of an earlier run (--rows), analysed again
        with np.load(a.rows, allow_pickle=False) as z:
            each = [(str(z[f"name{p}"]), {"rows": z[f"rows{p}"], "cam_from_part": z[f"poses{p}"], "xyz": z[f"xyz{p}"],
                                          "fx_px": float(z[f"f{p}"][0]), "fy_px": float(z[f"f{p}"][1])})
                    for p in range(int(z["n"]))]
            a.views, a.repeats, a.seed, a.plates, a.skins = (int(v) for v in z["args"])
    else:
        each = collect_each(a.views, a.repeats, a.seed, a.plates, a.skins, mask=a.background_mask == "cad")
        if a.background_mask == "cad":
            each = [(name, doc | {"rows": masked_rows(doc["rows"])}) for name, doc in each]
        if a.rows:
            np.savez_compressed(a.rows, n=len(each), args=[a.views, a.repeats, a.seed, a.plates, a.skins],
                                **{f"{k}{p}": v for p, (name, doc) in enumerate(each) for k, v in
                                                        (("name", name), ("rows", doc["rows"]),
                                                         ("f", [doc["fx_px"], doc["fy_px"]]),
                                                         ("poses", doc["cam_from_part"]), ("xyz", doc["xyz"]))})
    parts, plain = [], []
    for p, (name, doc) in enumerate(each):
        for whiten, out in ((True, parts), (False, plain)):
            pr = part_pairs(doc, model, whiten)
            pr["target"] = pr["target"].astype(np.int64) + p * 1_000_000  # a target of one part
            out.append(pr)
    pairs = {key: np.concatenate([pr[key] for pr in parts]) for key in parts[0]}
    unw = {key: np.concatenate([pr[key] for pr in plain]) for key in plain[0]}
    n_rows = sum(len(doc["rows"]) for _, doc in each)
    n_bound = sum(int(np.any(doc["rows"][:, 7:10] != 0, axis=1).sum()) for _, doc in each)
    d = ~pairs["same_view"].astype(bool)
    print(f"{n_rows} dot images from {len(each)} parts x {a.views} views x {a.repeats} "
          f"({time.perf_counter() - t0:.0f} s); {n_bound} with a background bound; c_background {c:.3f}")
    print(f"pairs of distinct views: {d.sum()} over {len(np.unique(pairs['target'][d]))} targets")
    rho, sig = fit_share(pairs["num"][d], pairs["den"][d], pairs["target"][d])
    print(f"rho_background = {rho:.3f} +- {sig:.3f} (moments whitened by the bundle's weights; bootstrap over targets)")
    rho_u, sig_u = fit_share(unw["num"][d], unw["den"][d], unw["target"][d])
    print(f"  unwhitened least squares: {rho_u:.3f} +- {sig_u:.3f} (weighted with the 4th power of the bounds)")
    bmax = np.sqrt(unw["den"] ** 0.5 / 2)  # ~ c sqrt(B / 2) of the pair (px): ||M||_F ~ |S_i| |S_j|
    by_bound = []
    print("  by the pair's bound (sqrt of ||M_ij||_F / 2, px): whitened | unwhitened")
    for lo, hi in ((0, 0.02), (0.02, 0.05), (0.05, 0.1), (0.1, 0.2), (0.2, np.inf)):
        m = d & (bmax >= lo) & (bmax < hi)
        if m.sum() < 10:
            continue
        txt, r, s = _fmt(pairs["num"][m], pairs["den"][m], pairs["target"][m], min_targets=10)
        txt_u, r_u, _ = _fmt(unw["num"][m], unw["den"][m], unw["target"][m], min_targets=10)
        print(f"    {lo:4.2f}-{hi:<4.2f}: {txt} | {txt_u}  ({m.sum()} pairs)")
        by_bound.append({"bound_px": [lo, hi if np.isfinite(hi) else None], "rho": r, "sigma": s, "rho_unwhitened": r_u,
                         "n_pairs": int(m.sum())})
    same = None
    if (~d).any():
        txt, r, s = _fmt(pairs["num"][~d], pairs["den"][~d], pairs["target"][~d])
        same = None if r is None else {"rho": r, "sigma": s, "n_pairs": int((~d).sum())}
        print(f"  repeats of one view (the share the view's geometry fixes): {txt} ({(~d).sum()} pairs)")
    print("  by the angle between the two lines of sight:")
    by_angle = []
    for lo, hi in zip(ANGLE_EDGES_DEG[:-1], ANGLE_EDGES_DEG[1:]):
        m = d & (pairs["angle_deg"] >= lo) & (pairs["angle_deg"] < hi)
        if not m.any():
            continue
        txt, r, s = _fmt(pairs["num"][m], pairs["den"][m], pairs["target"][m], min_targets=10)
        nt = len(np.unique(pairs["target"][m]))
        print(f"    {lo:3d}-{hi:<3d} deg: {txt}  ({m.sum()} pairs, {nt} targets)")
        by_angle.append({"angle_deg": [lo, hi], "rho": r, "sigma": s, "n_pairs": int(m.sum()), "n_targets": nt})
    print("  per part:")
    per_part = []
    for (name, _), pr in zip(each, parts):
        m = ~pr["same_view"].astype(bool)
        txt, r, s = _fmt(pr["num"][m], pr["den"][m], pr["target"][m], min_targets=5)
        print(f"    {name:32s}: {txt}  ({len(np.unique(pr['target'][m]))} targets)")
        per_part.append({"part": name, "rho": r, "sigma": s, "n_targets": int(len(np.unique(pr["target"][m])))})
    # the pairs measure how much of the modelled cross term is there; whether the statement built from it covers
    # the errors is the intersections' question: the share applied is the smallest from the pairs' up to one whose
    # intersections are not optimistic (one where none is: the model then misses shared error elsewhere)
    lo = float(np.clip(rho, 0.0, 1.0))
    shares = np.unique(np.r_[0.0, np.linspace(lo, 1.0, 10)])
    checks = [point_check(doc, model, shares) for _, doc in each]
    m2 = np.concatenate([ck["edge"] for ck in checks], axis=1)
    check = [{"share": float(sh), "ratio": float(np.sqrt(np.mean(m) / 3)), "inside_99": float(np.mean(m <= CHI2_99_3))}
             for sh, m in zip(shares, m2)]
    ok = [ck["share"] for ck in check if ck["share"] >= lo and ck["ratio"] <= 1.0]
    applied = min(ok) if ok else 1.0
    print(f"  targets seen in 4 views or more, intersected with the true poses from all their views (one rendering "
          "of each): sqrt(mean m^2 / 3), share inside the 99 % ellipsoid")
    for name in ("clean", "one"):
        v = np.concatenate([ck[name] for ck in checks])
        print(f"    no bound shared ({'no view' if name == 'clean' else 'one view'} with a bound, {len(v)}): "
              f"{np.sqrt(np.mean(v) / 3):.3f}, {100 * np.mean(v <= CHI2_99_3):.1f} %")
    print(f"    a bound in two views or more ({m2.shape[1]}), by the share ADJUST applies:")
    for ck in check:
        print(f"      share {ck['share']:.2f}: {ck['ratio']:.3f}, {100 * ck['inside_99']:.1f} %")
    cm = [cross_moments(doc) for _, doc in each]
    cross = {key: sum(x[key][0] for x in cm) / max(sum(x[key][1] for x in cm), 1) for key in cm[0]}
    print("  mean cross product of two views' errors as 3-D directions (Jh^T e, px^2): targets with a bound in two "
          f"views or more: both views with a bound {cross['FF']:.2e}, one {cross['FU']:.2e}, none {cross['UU']:.2e}; "
          f"targets without a bound {cross['clean']:.2e}")
    print(f"rho_background applied = {applied:.2f}" + ("" if ok else " (no share up to one makes the intersections "
                                                           "honest: the modelled cross terms miss shared error)"))
    if a.write:
        doc = {k: v for k, v in json.loads(DATA_PATH.read_text()).items() if not k.startswith("rho_background")}
        # rho_background came with version 4: a later model's version is kept (it was written "4" over version 5)
        doc |= {"version": str(max(int(doc.get("version", "1")), 4)), "rho_background": applied, "rho_background_pairs": rho, "rho_background_pairs_sigma": sig,
                "rho_background_measured_by": f"python -m benchmarks.background_share --views {a.views} --repeats "
                                              f"{a.repeats} --seed {a.seed} --plates {a.plates} --skins {a.skins} --write",
                "rho_background_rule": "the pairs' moments measure the share of the modelled cross terms present; the "
                                       "share applied is the smallest from theirs up to one whose intersections (targets "
                                       "with a bound in two views or more, true poses) are not optimistic, one where none "
                                       "is (decision 0032)",
                "rho_background_detail": {"c_background": c, "n_pairs": int(d.sum()),
                                          "unwhitened": {"rho": rho_u, "sigma": sig_u}, "by_bound": by_bound,
                                          "intersection_check": check, "cross_moments_px2": cross,
                                          "n_targets": int(len(np.unique(pairs["target"][d]))),
                                          "repeats_of_one_view": same, "by_angle": by_angle, "per_part": per_part}}
        DATA_PATH.write_text(json.dumps(doc, indent=1) + "\n")
        print(f"written {DATA_PATH}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
