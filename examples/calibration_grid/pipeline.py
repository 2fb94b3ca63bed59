"""The measurement chain shared by the two paper experiments (calibration grid, complex object).

Images are *rendered* by the simulated camera (``sim_backend.sim_camera.SimCamera``) and measured
by the cell's own code, the same steps as the MEASURE, CALIBRATE and ADJUST stages of a job
(``cell/stages.py``), without a job folder:

1. render the image seen from a station (discs with blur, shot and read noise, 8 bits);
2. detect the dots (``detect_retro_targets``), name them by projecting the nominal targets with an
   approximate pose (``identify_targets``: a robot pose / hand-held guess a few mm and a fraction of a
   degree off), drop dots whose rim is partly hidden (``cell.stages.imaging.name_dots``) and remove the
   perspective eccentricity of the ellipse centre (``eccentricity_bias``);
3. Faugeras-Toscani per image (``faugeras_toscani``): interior and exterior orientation;
4. bundle adjustment (``bundle_adjust``) with covariance: error ellipsoids of every target.

Metrics of a set of error ellipsoids (``ellipsoid_metrics``): 1-sigma semi-axes ``a >= b >= c``;
volume ``4/3 pi a b c``; elongation ``a / c``; size ``sigma = sqrt(a^2 + b^2 + c^2)``;
homogeneity = coefficient of variation of ``sigma`` over the targets (0: all the same size);
isotropy = ``c / a`` (1: a sphere).

Run nothing here; see ``run_experiment.py`` in each example folder.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from calibration.bundle import BundleConfig, BundleOptions, BundleResult, bundle_adjust
from calibration.camera import Intrinsics, exp_se3, invert
from calibration.errors import CalibrationError
from calibration.faugeras_toscani import FTResult, combine_intrinsics, faugeras_toscani
from calibration.targets import DetectionOptions, detect_retro_targets

__all__ = [
    "Observations",
    "render_and_measure",
    "calibrate_images",
    "initial_poses",
    "usable_images",
    "adjust_subset",
    "ellipsoid_metrics",
    "truth_consistency",
    "plot_ellipsoids",
    "detector_model_coverage",
    "detector_model_text",
    "honesty_text",
]


@dataclass
class Observations:
    """Measured image coordinates of a set of images.

    Attributes:
        obs_image: (q,) image index; obs_target: (q,) target index; obs_uv: (q, 2) pixels.
        n_images: number of images; per_image: one dict of counts per image.
        render_s, measure_s: total seconds spent rendering and measuring.
    """

    obs_image: np.ndarray
    obs_target: np.ndarray
    obs_uv: np.ndarray
    n_images: int
    per_image: list[dict] = field(default_factory=list)
    render_s: float = 0.0
    measure_s: float = 0.0

    def subset(self, images: list[int] | np.ndarray) -> "Observations":
        """The observations of ``images`` only, re-indexed 0..len(images)-1 in the given order."""
        images = [int(i) for i in images]
        remap = np.full(self.n_images, -1)
        remap[images] = np.arange(len(images))
        keep = remap[self.obs_image] >= 0
        return Observations(remap[self.obs_image[keep]], self.obs_target[keep], self.obs_uv[keep], len(images),
                            [self.per_image[i] for i in images])

    def rays(self, n_targets: int) -> np.ndarray:
        """(n,) number of images measuring each target."""
        return np.bincount(self.obs_target, minlength=n_targets)


def perturb_pose(cam_from_part: np.ndarray, rng: np.random.Generator, rot_rad: float, trans_m: float) -> np.ndarray:
    """A pose off by N(0, rot_rad^2) per rotation axis and N(0, trans_m^2) per translation axis, (4, 4)."""
    xi = np.concatenate([rng.normal(0.0, rot_rad, 3), rng.normal(0.0, trans_m, 3)])
    return exp_se3(xi) @ cam_from_part


def coarse_align(intr: Intrinsics, cam_from_part: np.ndarray, xyz: np.ndarray, det_uv: np.ndarray,
                 iterations: int = 2) -> np.ndarray:
    """Turn an approximate pose so that the projected targets ``xyz: (n, 3)`` overlay the dots ``det_uv: (k, 2)``.

    The median displacement from each dot to its nearest projected target is, for a pose error below
    half the targets' image spacing, the image shift of the whole pattern; a small rotation of the camera
    about its x and y axes removes it (``du = fx * theta_y``, ``dv = -fy * theta_x``). (4, 4).
    """
    from scipy.spatial import cKDTree

    from calibration.camera import project

    T = np.asarray(cam_from_part, dtype=float)
    if len(det_uv) < 3:
        return T
    for _ in range(iterations):
        front = xyz @ T[2, :3] + T[2, 3] > 0
        uv = project(intr, T, xyz[front])
        uv = uv[np.all(np.isfinite(uv), axis=1)]
        if len(uv) < 3:
            return T
        _, j = cKDTree(uv).query(det_uv)
        du, dv = np.median(det_uv - uv[j], axis=0)
        T = exp_se3(np.array([-dv / intr.fy_px, du / intr.fx_px, 0.0, 0.0, 0.0, 0.0])) @ T
    return T


def render_and_measure(
    camera,
    part,
    intr: Intrinsics,
    part_from_cam: np.ndarray,
    rng: np.random.Generator,
    *,
    pose_error: tuple[float, float] = (math.radians(0.15), 0.002),
    max_dist_px: float = 25.0,
    incidence_max_rad: float = math.radians(70.0),
    detection: DetectionOptions | None = None,
    save_images=None,
) -> Observations:
    """Render every station with ``camera`` (a SimCamera of ``part``) and measure the dots.

    Args:
        camera: ``SimCamera`` (its world holds ``part`` and the true intrinsics).
        part: ``planning.part.Part`` (CAD nominal targets; retro dots only).
        intr: the interior orientation used for identification (nominal values).
        part_from_cam: (m, 4, 4) true stations.
        rng: draws the approximate poses used for identification.
        pose_error: (rotation rad, translation m) standard deviation of those approximate poses.
        max_dist_px: identification gate.
        incidence_max_rad: only targets in view from the approximate pose at no more than this incidence (and
            not hidden by the part) are offered to the matcher, as the cell's MEASURE stage does; a dot seen
            at grazing incidence is a thin sliver whose centroid is not worth measuring.
        save_images: a folder to write ``NNNN.png`` into, or None.
    """
    import cv2

    from cell.stages.imaging import name_dots
    from planning.visibility import Occluder

    T = np.asarray(part_from_cam, dtype=float).reshape(-1, 4, 4)
    t = part.targets
    occluder = Occluder(part.mesh)
    opts = detection or DetectionOptions()
    oi, ot, ouv, per = [], [], [], []
    t_render = t_measure = 0.0
    for k, pfc in enumerate(T):
        t0 = time.perf_counter()
        image, truth = camera.render(pfc)
        t1 = time.perf_counter()
        if save_images is not None:
            save_images.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(save_images / f"{k + 1:04d}.png"), image)
        approx = perturb_pose(invert(pfc), rng, *pose_error)
        det = detect_retro_targets(image, opts)
        approx = coarse_align(intr, approx, t.xyz, det.uv)
        # the approximate pose (not the truth) decides what is in view and which rims are clipped
        m = name_dots(det.uv, part, intr, approx, occluder, max_dist_px=max_dist_px,
                      incidence_max_rad=incidence_max_rad)
        oi.append(np.full(len(m.target), k))
        ot.append(m.target)
        ouv.append(m.uv)
        per.append({"image": k + 1, "rendered": len(truth["ids"]), "detected": len(det), "measured": int(len(m.target)),
                    "unidentified": m.n_unidentified, "partly_hidden": m.n_partly_hidden})
        t_render += t1 - t0
        t_measure += time.perf_counter() - t1
    return Observations(np.concatenate(oi).astype(int), np.concatenate(ot).astype(int), np.vstack(ouv), len(T), per,
                        t_render, t_measure)


def calibrate_images(part, obs: Observations, width: int, height: int) -> tuple[list[FTResult], Intrinsics]:
    """Faugeras-Toscani on every image (nominal 3-D targets), and the median interior orientation."""
    res, refused = [], []
    for k in range(obs.n_images):
        sel = obs.obs_image == k
        try:
            res.append(faugeras_toscani(part.targets.xyz[obs.obs_target[sel]], obs.obs_uv[sel], width, height))
        except CalibrationError as exc:  # ill-conditioned or implausible: left out of the median, said
            refused.append(f"image {k + 1}: {exc}")
    if not res:
        raise CalibrationError("Faugeras-Toscani refused every image: " + "; ".join(refused[:3]))
    return res, combine_intrinsics(res)


def initial_poses(part, obs: Observations, intr: Intrinsics, robot_part_from_cam: np.ndarray,
                  min_points: int = 8) -> tuple[np.ndarray, Intrinsics, int]:
    """Starting values for the adjustment: Faugeras-Toscani per image where it can run.

    An image with fewer than ``min_points`` measured targets, or whose targets are coplanar, cannot be
    calibrated linearly; its pose is then solved by ``solvePnP`` from the robot's pose
    ``robot_part_from_cam: (m, 4, 4)`` with the interior orientation ``intr`` (what the cell knows).
    Returns ``cam_from_part (m, 4, 4)``, the median Faugeras-Toscani interior orientation, and how many
    images fell back to PnP.
    """
    from calibration.targets import refine_pose_pnp

    poses, ok = [], []
    for k in range(obs.n_images):
        sel = obs.obs_image == k
        xyz, uv = part.targets.xyz[obs.obs_target[sel]], obs.obs_uv[sel]
        try:
            if len(uv) < min_points:
                raise CalibrationError("too few points")
            r = faugeras_toscani(xyz, uv, intr.width, intr.height)
            poses.append(r.cam_from_part)
            ok.append(r)
        except CalibrationError:
            if len(uv) < 4:  # cannot be oriented: keep the robot's pose; leave the image out (usable_images)
                poses.append(invert(robot_part_from_cam[k]))
                continue
            poses.append(refine_pose_pnp(intr, invert(robot_part_from_cam[k]), xyz, uv))
    if not ok:
        raise CalibrationError("no image could be calibrated by Faugeras-Toscani")
    return np.array(poses), combine_intrinsics(ok), obs.n_images - len(ok)


def usable_images(obs: Observations, min_targets: int = 6) -> list[int]:
    """Indices of the images with at least ``min_targets`` measured targets (the others cannot be oriented)."""
    counts = np.bincount(obs.obs_image, minlength=obs.n_images)
    return [int(k) for k in np.flatnonzero(counts >= min_targets)]


def adjust_subset(
    obs: Observations,
    images: list[int],
    intr: Intrinsics,
    cam_from_part0: np.ndarray,
    points0: np.ndarray,
    *,
    sigma_px: float,
    camera_model: str = "PINHOLE",
    self_calibrate: bool = False,
    a_posteriori: bool = False,
) -> tuple[BundleResult, Observations]:
    """Bundle adjustment of the images ``images`` (indices into ``obs``), free-network datum.

    With ``self_calibrate`` the focal lengths, principal point and distortion of ``camera_model`` are
    refined; otherwise the interior orientation is held at ``intr`` (a calibrated camera, as in the
    seed). ``a_posteriori=False`` scales the covariance by ``sigma_px`` (a priori), so networks are
    compared by their geometry alone.
    """
    sub = obs.subset(images)
    config = BundleConfig(camera_model=camera_model, refine_focal_length=self_calibrate,
                          refine_principal_point=self_calibrate,
                          refine_distortion=self_calibrate and camera_model != "PINHOLE")
    # two images: a 2x2 block of an observation's cofactor matrix is singular (one redundant coordinate per
    # target over four), so no observation can be tested; data snooping is off for pairs
    options = BundleOptions(sigma_px=sigma_px, a_posteriori=a_posteriori, snooping=len(images) > 2,
                            max_rejections=max(20, len(sub.obs_uv) // 50))
    res = bundle_adjust(sub.obs_image, sub.obs_target, sub.obs_uv, intr, np.asarray(cam_from_part0)[images],
                        points0, options, config)
    return res, sub


def detector_model_coverage(res: BundleResult, sub: Observations, intr: Intrinsics, normals: np.ndarray,
                            diameter_m: float) -> dict:
    """Whether the repository's measured detector model (``calibration/detector_model.py``) covers these images.

    For every observation the adjustment kept, the dot's diameter in the image (``fx * D / depth``) and its
    incidence, both from the *adjusted* network (poses ``res.cam_from_part``, points ``res.points``; the CAD
    normals), never from the simulator's truth. Returns the share of observations inside the dot sizes and
    incidences the model was measured over, the ranges seen here, and the model's rms sigma per coordinate
    for them: extrapolated (``sigma_px``) and held inside its measured box (``sigma_px_measured``, what the
    planner uses). Next to the adjustment's ``sigma0_px`` it says whether the model describes these images.
    """
    import json

    from calibration.detector_model import DATA_PATH, load_model

    model = load_model()
    conditions = str(json.loads(DATA_PATH.read_text()).get("conditions", "")).split(";")[0]
    keep = ~np.asarray(res.rejected, dtype=bool)
    img, tgt = sub.obs_image[keep], sub.obs_target[keep]
    pts = res.points[tgt]
    ok = np.all(np.isfinite(pts), axis=1)
    img, tgt, pts = img[ok], tgt[ok], pts[ok]
    cfp = res.cam_from_part[img]
    depth = np.einsum("kj,kj->k", cfp[:, 2, :3], pts) + cfp[:, 2, 3]
    d_px = intr.fx_px * diameter_m / depth
    centre = -np.einsum("kji,kj->ki", cfp[:, :3, :3], cfp[:, :3, 3])  # R^T t, negated: the projection centres
    sight = centre - pts
    sight /= np.linalg.norm(sight, axis=1, keepdims=True)
    theta = np.arccos(np.clip(np.einsum("ka,ka->k", sight, np.asarray(normals, dtype=float)[tgt]), -1.0, 1.0))
    inc_max, d0, d1 = model.measured_box()
    inside = (d_px >= d0) & (d_px <= d1) & (theta <= inc_max)
    return {"model_version": model.version, "model_diameter_range_px": [d0, d1],
            "model_incidence_max_deg": float(np.degrees(inc_max)), "observations": int(len(d_px)),
            "diameter_px": [float(d_px.min()), float(np.median(d_px)), float(d_px.max())],
            "incidence_deg": [float(np.degrees(theta.min())), float(np.degrees(np.median(theta))),
                              float(np.degrees(theta.max()))],
            "share_inside": float(np.mean(inside)),
            "model_rms_px_extrapolated": float(np.sqrt(np.mean(model.sigma_px(theta, d_px) ** 2))),
            "model_rms_px_held": float(np.sqrt(np.mean(model.sigma_px_measured(theta, d_px) ** 2))),
            "model_rms_px_inside": (float(np.sqrt(np.mean(model.sigma_px(theta[inside], d_px[inside]) ** 2)))
                                    if inside.any() else None),
            "model_measured_on": conditions}


def detector_model_text(dm: dict, sigma0_px: float, dots: str) -> str:
    """README sentences: whether the detector model covers these images (``dm``: :func:`detector_model_coverage`),
    next to the images' own ``sigma0_px``; ``dots`` names the dots ("the grid's 6 mm dots")."""
    text = (f"The repository's detector model (`calibration/data/detector_precision.json`, version "
            f"{dm['model_version']}) was measured on the {dm['model_measured_on']}, on dots of "
            f"{dm['model_diameter_range_px'][0]:.1f}-{dm['model_diameter_range_px'][1]:.1f} px. {dots} are "
            f"{dm['diameter_px'][0]:.1f}-{dm['diameter_px'][2]:.1f} px here (median {dm['diameter_px'][1]:.1f} px, at "
            f"{dm['incidence_deg'][0]:.0f}-{dm['incidence_deg'][2]:.0f} deg of incidence; from the adjusted network): "
            f"{dm['share_inside'] * 100:.0f}% of the {dm['observations']} observations lie where the model was measured. ")
    if dm.get("model_rms_px_inside") is not None:
        text += (f"On those it predicts {dm['model_rms_px_inside']:.4f} px rms per coordinate; over all of them "
                 f"{dm['model_rms_px_extrapolated']:.4f} px extrapolated, {dm['model_rms_px_held']:.4f} px held inside "
                 f"its measured range. ")
    else:
        text += (f"Extrapolated it would predict {dm['model_rms_px_extrapolated']:.4f} px rms per coordinate, held at "
                 f"the smallest dot it was measured on {dm['model_rms_px_held']:.4f} px. ")
    why = "another camera" if dm["share_inside"] >= 0.95 else "another camera and larger dots"
    return text + (f"The images' own residuals say {sigma0_px:.4f} px. A model measured on {why} is not these "
                   "images' precision, so it is **not** used.")


def honesty_text(cases: dict[str, dict], image_sigma_px: float, before: dict[str, dict] | None = None) -> str:
    """README sentence on the networks whose covariance is optimistic against the truth (fewer than 85% of the
    targets inside their 95% ellipsoid); ``cases``: label -> {"truth", "sigma0_px"}; ``before``: the same of the
    run compared with. Empty when every network's covariance describes its errors."""
    bad = {k: v for k, v in cases.items() if v["truth"]["inside_95"] < 0.85}
    if not bad:
        return (f"every network's covariance describes its true errors (at least 85% of the targets inside their 95% "
                f"ellipsoid) at the image sigma {image_sigma_px:.4f} px.")
    parts = []
    for k, v in bad.items():
        was = (f"; before {before[k]['truth']['inside_95'] * 100:.0f}%, median d^2 {before[k]['truth']['median_d2']:.1f}"
               if before and k in before else "")
        parts.append(f"{k} ({v['truth']['inside_95'] * 100:.0f}% inside the 95% ellipsoid, median d^2 "
                     f"{v['truth']['median_d2']:.1f} where 2.37 is expected; its own adjustment's sigma0 "
                     f"{v['sigma0_px']:.4f} px{was})")
    return ("the covariance is optimistic for " + "; ".join(parts) + f". Those networks' own residuals agree with the "
            f"images' sigma ({image_sigma_px:.4f} px), so the excess is not random image noise that the residuals "
            "would show: it behaves as an error a target's views share (views nearly alike see a dot nearly alike, "
            "so its centring error repeats and does not average out, and the depth is poorly determined), which the "
            "model of independent image noise used here does not hold. The per-image jitter of the set-up before "
            "was independent between views and larger, and covered it.")


def ellipsoid_metrics(cov: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """Size, shape and spread of the error ellipsoids ``cov: (n, 3, 3)`` (rows with nan skipped).

    Returns medians over the targets (and a few maxima), lengths in micrometres, volumes in um^3.
    """
    cov = np.asarray(cov, dtype=float)
    ok = np.all(np.isfinite(cov), axis=(1, 2))
    if mask is not None:
        ok &= np.asarray(mask, dtype=bool)
    if not ok.any():
        return {"n": 0}
    w = np.clip(np.linalg.eigvalsh(cov[ok]), 0.0, None)  # ascending
    ax = np.sqrt(w) * 1e6
    a, b, c = ax[:, 2], ax[:, 1], ax[:, 0]
    vol = 4.0 / 3.0 * np.pi * a * b * c
    sigma = np.sqrt(a * a + b * b + c * c)
    return {
        "n": int(ok.sum()),
        "volume_um3_median": float(np.median(vol)),
        "volume_um3_max": float(np.max(vol)),
        "elongation_median": float(np.median(a / np.maximum(c, 1e-300))),
        "elongation_max": float(np.max(a / np.maximum(c, 1e-300))),
        "major_axis_um_median": float(np.median(a)),
        "major_axis_um_max": float(np.max(a)),
        "sigma_um_median": float(np.median(sigma)),
        "sigma_um_max": float(np.max(sigma)),
        "homogeneity_cv": float(np.std(sigma) / np.mean(sigma)),
        "isotropy_median": float(np.median(c / a)),
    }


def truth_consistency(res: BundleResult, truth_xyz: np.ndarray) -> dict:
    """How the adjusted targets' true errors compare with their covariance.

    The adjusted points are brought onto the truth by a similarity (the free network's datum is
    arbitrary), then ``d^2 = e^T cov^-1 e`` per target: chi-square with 3 dof if the covariance is right
    (``sigma0`` scaled). Returns the rms true error (um), the median ``d^2`` (2.37 expected) and the
    fraction inside the 95% ellipsoid (0.95 expected).
    """
    from calibration.alignment import similarity_fit
    from scipy.stats import chi2

    ok = np.all(np.isfinite(res.points), axis=1)
    s, R, tt = similarity_fit(res.points[ok], truth_xyz[ok], with_scale=True)
    est = s * res.points[ok] @ R.T + tt
    e = est - truth_xyz[ok]
    cov = res.cov[ok] * s * s
    cov = R @ cov @ R.T
    d2 = np.einsum("ni,ni->n", e, np.linalg.solve(cov, e[..., None])[..., 0])
    return {"rms_error_um": float(np.sqrt(np.mean(np.sum(e * e, axis=1))) * 1e6),
            "median_d2": float(np.median(d2)), "inside_95": float(np.mean(d2 <= chi2.ppf(0.95, 3)))}


def plot_ellipsoids(ax, part, cov: np.ndarray, points: np.ndarray, eyes: np.ndarray | None, scale: float,
                    title: str, colour_max_um: float | None = None) -> None:
    """Draw the part, its targets' error ellipsoids magnified ``scale`` times and the camera centres.

    ``cov: (n, 3, 3)`` (nan rows drawn as red dots), ``points: (n, 3)``, ``eyes: (k, 3)`` or None.
    """
    from matplotlib import cm
    from matplotlib.colors import Normalize
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from planning.plot import ellipsoid_surfaces
    from planning.uncertainty import ellipsoid_axes

    tri = np.asarray(part.mesh.vertices)[np.asarray(part.mesh.faces)]
    ax.add_collection3d(Poly3DCollection(tri, facecolor=(0.8, 0.8, 0.83, 0.25), edgecolor=(0.5, 0.5, 0.55, 0.15),
                                         linewidths=0.2))
    ok = np.all(np.isfinite(cov), axis=(1, 2))
    if ok.any():
        axes, dirs = ellipsoid_axes(cov[ok])
        sig = np.sqrt(np.sum(axes**2, axis=1)) * 1e6
        norm = Normalize(vmin=0.0, vmax=colour_max_um or float(sig.max()))
        quads = ellipsoid_surfaces(points[ok], axes, dirs, scale, n_az=8, n_el=5)
        colours = cm.viridis(norm(np.repeat(sig, len(quads) // len(sig))))
        ax.add_collection3d(Poly3DCollection(quads, facecolors=colours, edgecolors="none"))
    if (~ok).any():
        ax.scatter(*points[~ok].T, s=6, color="r", depthshade=False)
    pts = np.asarray(part.mesh.vertices)
    if eyes is not None and len(eyes):
        ax.scatter(*np.asarray(eyes).T, s=14, color="tab:blue", depthshade=False)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    c, r = 0.5 * (lo + hi), 0.55 * float(np.max(hi - lo))
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.set_title(title, fontsize=9)
    ax.tick_params(labelsize=6)


def before_after(r: dict, before: dict, now: list, then: list, commit: str, commit_json: str, rerun_json: str,
                 scaling: str) -> str:
    """The README's before / after table of a paper example: ``before`` {"commit": results or None, "rerun": results or
    None} (the set-up with 0.05 px of jitter as last committed, and today's code with ``--jitter-px 0.05``), ``now``
    and ``then`` their key figures ([(label, value)], one list per column present), ``scaling`` a paragraph after."""
    heads = {"commit": f"before: commit {commit}, 0.05 px jitter", "rerun": "before: today's code, 0.05 px jitter"}
    cols = [k for k in ("commit", "rerun") if before.get(k) is not None]
    figs = then + [now]
    rows = [f"| {lab} | " + " | ".join(f[i][1] for f in figs) + " |" for i, (lab, _) in enumerate(now)]
    return f"""
Before and after. Before: the set-up with 0.05 px of jitter, twice: as last committed
(`results.json` of commit {commit}, kept verbatim in `{commit_json}`), and this script on today's code
with `--jitter-px 0.05` (`{rerun_json}`: only the jitter differs from this run). The code has changed since
{commit}; the second column separates that from the jitter.

| figure | {' | '.join(heads[k] for k in cols)} | now{' (' + str(r['jitter_px']) + ' px jitter)' if r['jitter_px'] else ', no jitter'} |
|---|{'---|' * len(cols)}---|
{chr(10).join(rows)}

{scaling}
"""


def load_before(here, rerun_json: str, commit_json: str) -> dict | None:
    """The runs of a paper example's set-up before, next to its script in ``here``: ``{"rerun": ..., "commit": ...}``
    (each None when absent), or None when neither is there."""
    import json

    runs = {k: (json.loads((here / f).read_text()) if (here / f).exists() else None)
            for k, f in (("rerun", rerun_json), ("commit", commit_json))}
    return runs if any(runs.values()) else None
