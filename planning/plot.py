"""A picture of a planned network: the part, the stations and the scaled error ellipsoids.

``plot_plan(part, plan, path_png)`` writes one PNG (matplotlib, Agg backend, no display
needed) with four panels: the network around the part (camera centres and viewing
directions), the part with the predicted error ellipsoids magnified and coloured by
sigma, the search history, and the distribution of the target sigmas.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
from matplotlib.figure import Figure  # noqa: E402  (not pyplot: its import is ~0.3-0.5 s of a job)
import numpy as np  # noqa: E402
from matplotlib import cm  # noqa: E402
from matplotlib.colors import Normalize  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection  # noqa: E402

from planning.uncertainty import ellipsoid_axes  # noqa: E402

__all__ = ["plot_plan", "ellipsoid_surfaces", "figure_png"]


def figure_png(fig, *, dpi: float | None = None, tight: bool = False, pad_inches: float = 0.1) -> bytes:
    """PNG bytes of ``fig``, drawn once.

    ``fig.savefig`` draws a figure twice when it has a layout engine (``tight_layout`` leaves one) or when
    ``bbox_inches="tight"``: a dry run to lay it out or measure it, then the picture; 3-D axes make each draw
    costly. Here the figure is drawn once on an Agg canvas and the PNG is written from that buffer with
    savefig's own writer and metadata. ``tight``: the picture is cut to the artists' bounding box plus
    ``pad_inches``, as ``bbox_inches="tight"`` does; when that box reaches outside the figure (a label beyond
    its edge) savefig's tight path, which grows the canvas, is used instead.
    """
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.image import imsave

    if dpi is not None:
        fig.set_dpi(dpi)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    if tight:
        bb = fig.get_tightbbox(canvas.get_renderer())
        w_in, h_in = fig.get_size_inches()
        if bb.x0 < 0 or bb.y0 < 0 or bb.x1 > w_in or bb.y1 > h_in:
            buf = io.BytesIO()
            fig.savefig(buf, format="png", dpi=fig.dpi, bbox_inches="tight", pad_inches=pad_inches)
            return buf.getvalue()
        bb = bb.padded(pad_inches)
        H, W = rgba.shape[:2]
        d = fig.dpi
        c0, c1 = int(np.floor(bb.x0 * d)), int(np.ceil(bb.x1 * d))
        r0, r1 = H - int(np.ceil(bb.y1 * d)), H - int(np.floor(bb.y0 * d))
        # the padding may reach past the canvas: there the picture is the figure's background, as savefig's
        face = np.round(np.asarray(matplotlib.colors.to_rgba(fig.get_facecolor())) * 255).astype(np.uint8)
        out = np.empty((r1 - r0, c1 - c0, 4), dtype=np.uint8)
        out[...] = face
        rs, cs = max(r0, 0), max(c0, 0)
        part = rgba[rs : min(r1, H), cs : min(c1, W)]
        out[rs - r0 : rs - r0 + part.shape[0], cs - c0 : cs - c0 + part.shape[1]] = part
        rgba = out
    buf = io.BytesIO()
    imsave(buf, rgba, format="png", origin="upper", dpi=fig.dpi,
           metadata={"Software": f"Matplotlib version{matplotlib.__version__}, https://matplotlib.org/"})
    return buf.getvalue()


def ellipsoid_surfaces(centres: np.ndarray, axes: np.ndarray, dirs: np.ndarray, scale: float,
                       n_az: int = 10, n_el: int = 6) -> np.ndarray:
    """Quadrilaterals tiling scaled ellipsoids; (e * n_az * n_el, 4, 3).

    Args:
        centres: (e, 3); axes: (e, 3) semi-axes (m); dirs: (e, 3, 3) unit axes as columns.
        scale: magnification of the semi-axes.
    """
    az = np.linspace(0, 2 * np.pi, n_az + 1)
    el = np.linspace(-np.pi / 2, np.pi / 2, n_el + 1)
    A, E = np.meshgrid(az, el, indexing="ij")
    unit = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)  # (n_az+1, n_el+1, 3)
    # points: centre + dirs @ (scale * axes * unit)
    pts = centres[:, None, None, :] + np.einsum("eij,eabj->eabi", dirs, scale * axes[:, None, None, :] * unit[None])
    quads = np.stack([pts[:, :-1, :-1], pts[:, 1:, :-1], pts[:, 1:, 1:], pts[:, :-1, 1:]], axis=3)
    return quads.reshape(-1, 4, 3)


def _set_equal(ax, pts: np.ndarray) -> None:
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    c, r = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo)) or 1.0
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")


def _mesh(ax, mesh) -> None:
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
    ax.add_collection3d(Poly3DCollection(tri, facecolor=(0.75, 0.75, 0.78, 0.35), edgecolor=(0.4, 0.4, 0.45, 0.3),
                                         linewidths=0.3))


def plot_plan(part, plan, path_png, *, max_ellipsoids: int = 400, title: str | None = None, write=None) -> Path:
    """Draw ``plan`` (a :class:`planning.planner.NetworkPlan`) around ``part`` into ``path_png``.

    The ellipsoids (1 sigma, from ``plan.cov``) are magnified so the largest is ~6% of
    the part's size; the factor is printed on the panel. With more than
    ``max_ellipsoids`` targets the worst ones and an even sample of the rest are drawn.
    The file is written atomically (``write(path, data)``: another atomic writer, e.g. a job folder's, which
    journals it). Returns the path.
    """
    path_png = Path(path_png)
    fig = Figure(figsize=(14, 10), dpi=100)
    xyz = np.asarray(plan.xyz, dtype=float)
    T = np.asarray(plan.part_from_cam, dtype=float)
    eyes = T[:, :3, 3]
    size = float(np.ptp(np.asarray(part.mesh.vertices), axis=0).max())
    sigma = np.asarray(plan.sigma, dtype=float)
    finite = np.isfinite(sigma)

    # 1: the network
    ax = fig.add_subplot(2, 2, 1, projection="3d")
    _mesh(ax, part.mesh)
    arrow = 0.25 * float(np.median(np.linalg.norm(eyes - xyz.mean(axis=0), axis=1))) if len(eyes) else size
    ax.add_collection3d(Line3DCollection(np.stack([eyes, eyes + arrow * T[:, :3, 2]], axis=1),
                                         colors="tab:blue", linewidths=1.0))
    ax.scatter(*eyes.T, color="tab:blue", s=18, depthshade=False)
    for sid, e in zip(plan.station_ids, eyes):
        ax.text(*e, sid, fontsize=6, color="tab:blue")
    ax.scatter(*xyz.T, s=2, c=np.where(finite, "k", "r"), depthshade=False)
    _set_equal(ax, np.vstack([eyes, xyz]) if len(eyes) else xyz)
    ax.set_title(f"{len(eyes)} stations ({plan.mode}, criterion {plan.criterion}, min rays {plan.min_rays})")

    # 2: scaled error ellipsoids on the part
    ax = fig.add_subplot(2, 2, 2, projection="3d")
    _mesh(ax, part.mesh)
    if finite.any():
        idx = np.flatnonzero(finite)
        if len(idx) > max_ellipsoids:
            worst = idx[np.argsort(sigma[idx])[::-1][: max_ellipsoids // 4]]
            rest = np.setdiff1d(idx, worst)
            sample = rest[np.linspace(0, len(rest) - 1, max_ellipsoids - len(worst)).astype(int)]
            idx = np.concatenate([worst, sample])
        axes, dirs = ellipsoid_axes(np.asarray(plan.cov)[idx])
        scale = 0.06 * size / float(np.max(axes))
        norm = Normalize(vmin=float(sigma[finite].min()) * 1e6, vmax=float(sigma[finite].max()) * 1e6)
        quads = ellipsoid_surfaces(xyz[idx], axes, dirs, scale)
        colours = cm.viridis(norm(np.repeat(sigma[idx] * 1e6, len(quads) // len(idx))))
        ax.add_collection3d(Poly3DCollection(quads, facecolors=colours, edgecolors="none"))
        fig.colorbar(cm.ScalarMappable(norm=norm, cmap="viridis"), ax=ax, shrink=0.6, label="sigma (um)")
        ax.set_title(f"error ellipsoids (1 sigma) x {scale:,.0f}")
    bad = ~finite
    if bad.any():
        ax.scatter(*xyz[bad].T, s=12, color="r", depthshade=False, label="not measurable")
        ax.legend(loc="upper left", fontsize=7)
    _set_equal(ax, np.asarray(part.mesh.vertices))

    # 3: search history
    ax = fig.add_subplot(2, 2, 3)
    hist = [h for h in plan.history if h.get("best") is not None and np.isfinite(h.get("best") or np.inf)]
    if hist:
        g = [h.get("step", h["generation"]) for h in hist]
        unit = 1e6 if plan.mode == "fixed" else 1.0
        ax.plot(g, [h["best"] * unit for h in hist], label="best")
        mean = [(h.get("step", h["generation"]), h["mean"] * unit) for h in hist if h.get("mean") is not None
                and np.isfinite(h["mean"]) and h.get("phase", "search") == "search"]
        if mean:
            ax.plot(*zip(*mean), label="mean (feasible)", alpha=0.7)
        lb = (plan.search or {}).get("lower_bound_sigma_m")
        if plan.mode == "fixed" and lb:
            ax.axhline(lb * unit, color="k", ls="--", lw=1, label="lower bound, any network (database)")
            ax.axhline(plan.predicted_sigma_max_m * unit, color="tab:red", ls=":", lw=1, label="plan (exact)")
        ax.set_yscale("log")
        ax.legend(fontsize=7)
    ax.set_xlabel("generation" if plan.mode == "fixed" else "generation (front search, then refining searches)")
    ax.set_ylabel("fitness (um)" if plan.mode == "fixed" else "sigma / required")
    ax.set_title("search history")
    ax.grid(True, alpha=0.3)

    # 4: sigma per target
    ax = fig.add_subplot(2, 2, 4)
    if finite.any():
        ax.hist(sigma[finite] * 1e6, bins=40, color="tab:green", histtype="stepfilled")  # one polygon, not 40 bars
    ax.set_xlabel("target sigma = sqrt(trace(cov)) (um)")
    ax.set_ylabel("targets")
    ax.set_title(f"max {plan.predicted_sigma_max_m * 1e6:.2f} um, mean {plan.predicted_sigma_mean_m * 1e6:.2f} um"
                 + (f", {int(bad.sum())} not measurable" if bad.any() else ""))
    fig.suptitle(title or f"network plan: {getattr(part, 'name', '')} (seed {plan.seed})")
    fig.tight_layout()
    png = figure_png(fig)  # one draw (tight_layout leaves a layout engine: savefig would draw twice)
    # atomically and durably (decision 0005): a dot-named temporary file, fsync'ed, renamed, the folder fsync'ed; a
    # kill before the rename leaves a dot-named ``.tmp``, which a resume removes (decision 0060). ``write``: the
    # caller's writer (a job's stage passes the job folder's, which journals the file with its sha256 first)
    from planning.cache import write_bytes_atomic

    (write or write_bytes_atomic)(path_png, png)
    return path_png
