"""Screening the network before (and between) bundle adjustments: what the adjustment cannot use is
dropped with its reason instead of faulting the whole job.

A job whose first network was hampered (a fixture the plan did not know, glare, a station the robot
did not take) brings the adjustment images with few trustworthy dots and targets with one ray or two
nearly parallel ones. Each of those used to fault ADJUST ("a target is behind a camera", "an image has
fewer than 3 observed targets", a covariance blown up by one 1 m-deep target). Here, from the initial
orientation (CALIBRATE: Faugeras-Toscani or PnP per image), re-resected with the common interior orientation
and each resection checked against its start (:func:`resect`: worse or jumped -> the start kept, or the image
left out):

- an observation far from the intersection of its target's other rays is a gross error (a misnamed or
  clipped dot MEASURE did not catch): dropped (:data:`GROSS_PX`; leave-one-out, so a real deviation of
  the part, which moves every ray of its target alike, is not one);
- a target whose rays meet at less than :data:`MIN_INTERSECTION_DEG` is not determined: dropped (it stays
  unmeasured; the closed loop can add stations for it);
- an image left with fewer than :data:`MIN_IMAGE_OBS` usable observations is dropped from the adjustment;
- images not linked to the main block of the network (glare can split it into blocks that share no
  targets: no common datum, a covariance of metres) are dropped; their targets stay unmeasured;
- the scale bar needs both its ends usable; otherwise the scale is not established (said, not guessed).

Everything dropped is listed with its reason (bundle.json ``screening``, the journal, the console).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration.camera import Intrinsics, project

#: an observation this far (px) from the intersection of its target's other rays is a gross error
GROSS_PX = 2.0
#: rays of one target must span at least this angle for the target to be determined
MIN_INTERSECTION_DEG = 2.0
#: two images are linked when they share this many targets (a relative orientation needs five points; with
#: five, glare at 58.5 deg left a block tied by scale-free pairs: a singular covariance, every variance < 0)
LINK_TARGETS = 8
#: an image needs this many usable observations to stay in the adjustment (its pose has 6 parameters)
MIN_IMAGE_OBS = 5
#: a resection whose median residual exceeds its start's by this factor (+ 0.01 px) fits worse: the start is kept
RESECTION_WORSE = 1.05
#: a resection that moves the camera by more than this share of its distance to the targets, or turns it by more
#: than this many degrees, has jumped (a focal length 10 % off the common one moves it ~10 %; a principal point
#: 100 px off turns it ~2.5 deg; the mirror minimum of a flat field turns it by twice its tilt)
RESECTION_JUMP_FRACTION = 0.25
RESECTION_JUMP_DEG = 10.0


@dataclass
class Screening:
    """What the adjustment may use. ``keep_obs: (q,) bool``, ``keep_images: (m,) bool``; the dropped ones
    with their reasons: ``obs`` {observation index: reason}, ``targets`` {target index: reason},
    ``images`` {image index: reason}; ``bars_out`` {scale bar position in ``scale_pairs``: why it cannot be used};
    ``scale_ok`` (a bar is left, or the job has none) and, when not, ``scale_reason`` (every bar and why)."""

    keep_obs: np.ndarray
    keep_images: np.ndarray
    obs: dict = field(default_factory=dict)
    targets: dict = field(default_factory=dict)
    images: dict = field(default_factory=dict)
    scale_ok: bool = True
    scale_reason: str | None = None
    bars_out: dict = field(default_factory=dict)


def _rays(intr: Intrinsics, poses: np.ndarray, obs_image: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (q, 3) and unit ray directions (q, 3) in the part frame of observations ``uv: (q, 2)``."""
    import cv2

    if len(uv) == 0:  # cv2 returns None for no points
        return np.zeros((0, 3)), np.zeros((0, 3))
    norm = cv2.undistortPoints(np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2), intr.K,
                               intr.dist_coeffs).reshape(-1, 2)
    d_cam = np.concatenate([norm, np.ones((len(norm), 1))], axis=1)
    R = poses[obs_image, :3, :3]
    t = poses[obs_image, :3, 3]
    centres = -np.einsum("qji,qj->qi", R, t)
    d = np.einsum("qji,qj->qi", R, d_cam)
    return centres, d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclass
class Resection:
    """The poses the screening and the adjustment start from (:func:`resect`), and what was not resected:
    ``poses: (m, 4, 4)``; ``kept_start`` {image index: reason} (the start pose kept: the resection failed, fits
    worse, or jumped to another minimum while the start explains the dots); ``left_out`` {image index: reason}
    (the resection jumped from a start that does not explain the dots: neither pose, nor the naming, is
    trusted); ``resected``: how many images took their resection."""

    poses: np.ndarray
    kept_start: dict = field(default_factory=dict)
    left_out: dict = field(default_factory=dict)
    resected: int = 0


def _median_residual(intr: Intrinsics, T: np.ndarray, xyz: np.ndarray, uv: np.ndarray) -> float:
    """Median image residual (px) of ``uv: (k, 2)`` against ``xyz: (k, 3)`` seen from ``T``; inf if any is behind."""
    Xc = xyz @ T[:3, :3].T + T[:3, 3]
    if np.any(Xc[:, 2] <= 0):
        return float("inf")
    r = np.linalg.norm(uv - project(intr, T, xyz), axis=1)
    return float(np.median(r)) if np.all(np.isfinite(r)) else float("inf")


def pose_change(T0: np.ndarray, T1: np.ndarray, xyz: np.ndarray) -> tuple[float, float, float]:
    """How far ``T1`` is from ``T0`` (both cam_from_part): the camera centre's move (m), the rotation (deg),
    and the start camera's median depth to ``xyz: (k, 3)`` (m)."""
    c0 = -T0[:3, :3].T @ T0[:3, 3]
    c1 = -T1[:3, :3].T @ T1[:3, 3]
    R = T1[:3, :3] @ T0[:3, :3].T
    turned = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
    depth = float(np.median(xyz @ T0[2, :3] + T0[2, 3]))
    return float(np.linalg.norm(c1 - c0)), turned, depth


def resect(intr: Intrinsics, poses: np.ndarray, obs_image: np.ndarray, xyz: np.ndarray, uv: np.ndarray) -> Resection:
    """Each image's pose with the common interior orientation ``intr``, from its own start ``poses: (m, 4, 4)``.

    Faugeras-Toscani orients each image with its own interior orientation: its pose, paired with the common
    one, is off by pixels. A resection (PnP) on the image's named targets ``xyz: (q, 3)`` at ``uv: (q, 2)``,
    twice, each time without the observations beyond 3 robust sigma (1 px at least) of the pose before it (the
    start's, then the first resection's): a few misnamed dots would pull a least-squares resection away.
    An image with fewer than 4 observations keeps its start (the screening leaves it out: too few to orient).

    Each resection is checked against its start (median residual of all the image's observations, pose change):
    one that fits worse (:data:`RESECTION_WORSE`) keeps the start; one that moves the camera by more than
    :data:`RESECTION_JUMP_FRACTION` of its distance or turns it by more than :data:`RESECTION_JUMP_DEG` keeps the
    start when the start explains the dots (median <= :data:`GROSS_PX`: the resection fell into another minimum,
    e.g. the mirror pose of a flat field), and leaves the image out otherwise (its dots were named from a pose
    near the start; a pose that far from it puts the naming itself in doubt).
    """
    from calibration.targets import refine_pose_pnp
    from calibration.errors import CalibrationError

    out = Resection(np.array(poses, dtype=float, copy=True))
    for i in range(len(poses)):
        q = np.flatnonzero(obs_image == i)
        if len(q) < 4:
            continue
        start = out.poses[i]
        r0 = _median_residual(intr, start, xyz[q], uv[q])
        try:
            # the first pass without the observations its start already puts beyond 3 robust sigma: a few
            # misnamed dots tens of pixels off would pull a least-squares resection off a start that fits
            T, r = start, None
            if np.isfinite(r0):
                r = np.linalg.norm(uv[q] - project(intr, start, xyz[q]), axis=1)
            for _ in range(2):
                good = (np.ones(len(q), bool) if r is None or not np.all(np.isfinite(r))
                        else r <= max(1.0, 3.0 * 1.4826 * np.median(r)))
                if good.sum() < 6:
                    good[:] = True
                T = refine_pose_pnp(intr, T, xyz[q[good]], uv[q[good]])
                r = np.linalg.norm(uv[q] - project(intr, T, xyz[q]), axis=1)
        except CalibrationError as exc:
            out.kept_start[i] = f"resection failed ({exc}); start pose kept (median residual {r0:.2f} px)"
            continue
        r1 = _median_residual(intr, T, xyz[q], uv[q])
        if not r1 <= RESECTION_WORSE * r0 + 0.01:
            out.kept_start[i] = (f"its resection fits worse than its start (median residual {r1:.2f} px against "
                                 f"{r0:.2f} px): start pose kept")
            continue
        moved, turned, depth = pose_change(start, T, xyz[q])
        if depth <= 0 or moved > RESECTION_JUMP_FRACTION * depth or turned > RESECTION_JUMP_DEG:
            share = f"{moved / depth:.0%} of its distance" if depth > 0 else "its start has the targets behind it"
            what = (f"its resection moved the camera {moved * 1e3:.0f} mm ({share}) and turned it {turned:.1f} deg "
                    "from its start")
            if r0 <= GROSS_PX:
                out.kept_start[i] = (f"{what}, while the start explains its dots (median residual {r0:.2f} px): "
                                     "another minimum; start pose kept")
            else:
                out.left_out[i] = (f"{what} (median residual {r0:.2f} -> {r1:.2f} px): neither the start nor the "
                                   "resection, nor the naming done from near the start, can be trusted")
            continue
        out.poses[i] = T
        out.resected += 1
    return out


def _intersect(c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Least-squares intersection of rays ``c + s d`` (k, 3): the point nearest to all of them."""
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    A = P.sum(axis=0)
    b = np.einsum("kij,kj->i", P, c)
    return np.linalg.lstsq(A, b, rcond=None)[0]


def _span_deg(d: np.ndarray) -> float:
    """Largest angle (deg) between any two of the unit rays ``d: (k, 3)``."""
    if len(d) < 2:
        return 0.0
    return float(np.degrees(np.arccos(np.clip(np.min(d @ d.T), -1.0, 1.0))))


def _keep_main_block(s: Screening, obs_image: np.ndarray, obs_target: np.ndarray, m: int, n_targets: int) -> bool:
    """Keep the block of images linked to each other (:data:`LINK_TARGETS` common targets) with the most
    observations; the images of other blocks are dropped (the network's blocks have no common datum: its
    covariance would be metres). Returns whether anything was dropped."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    rays = np.bincount(obs_target[s.keep_obs], minlength=n_targets)
    u = s.keep_obs & (rays[obs_target] >= 2)
    A = csr_matrix((np.ones(int(u.sum())), (obs_image[u], obs_target[u])), shape=(m, n_targets))
    common = (A @ A.T).toarray()
    n_blocks, label = connected_components(csr_matrix(common >= LINK_TARGETS), directed=False)
    alive = np.flatnonzero(s.keep_images)
    if n_blocks <= 1 or len(alive) == 0:
        return False
    size = np.bincount(label[obs_image[u]], minlength=n_blocks)
    main = int(np.argmax(size))
    if len(np.unique(label[alive])) <= 1:
        return False
    for i in alive[label[alive] != main]:
        s.images[int(i)] = (f"not linked to the main network (shares fewer than {LINK_TARGETS} targets with its "
                            f"images; {n_blocks} separate blocks)")
        s.keep_images[i] = False
        s.keep_obs &= obs_image != i
    return True


def screen_network(obs_image: np.ndarray, obs_target: np.ndarray, obs_uv: np.ndarray, intr: Intrinsics,
                   poses: np.ndarray, n_targets: int, *, scale_pairs=(),
                   drop_targets: dict | None = None, drop_images: dict | None = None,
                   ids: list[str] | None = None) -> Screening:
    """Screen the observations ``(obs_image, obs_target, obs_uv)`` of a network oriented by ``poses: (m, 4, 4)``.

    ``drop_targets`` / ``drop_images``: {index: reason} already known to be unusable (e.g. a target that ended
    behind a camera in an adjustment); ``scale_pairs``: each scale bar's two target indices (a bar with an end
    left with fewer than two rays is out: ``bars_out``; the scale is lost only when every bar is).
    """
    obs_image = np.asarray(obs_image, dtype=int)
    obs_target = np.asarray(obs_target, dtype=int)
    uv = np.asarray(obs_uv, dtype=float).reshape(-1, 2)
    m = len(poses)
    name = (lambda t: ids[t]) if ids is not None else str
    s = Screening(np.ones(len(uv), dtype=bool), np.ones(m, dtype=bool), targets=dict(drop_targets or {}),
                  images=dict(drop_images or {}))
    for t in s.targets:
        s.keep_obs &= obs_target != t
    for i in s.images:
        s.keep_images[i] = False
        s.keep_obs &= obs_image != i
    poses = np.asarray(poses, dtype=float)
    centres, dirs = _rays(intr, poses, obs_image, uv)
    order = np.argsort(obs_target, kind="stable")
    bounds = np.searchsorted(obs_target[order], np.arange(n_targets + 1))
    for _ in range(10):  # dropping an image thins its targets, which may then drop more: until nothing changes
        changed = False
        for t in range(n_targets):
            if t in s.targets:
                continue
            idx = order[bounds[t]:bounds[t + 1]]
            idx = idx[s.keep_obs[idx]]
            while len(idx) >= 3:  # leave one out: the ray farthest from the others' intersection
                res = np.full(len(idx), np.nan)  # nan: the other rays do not intersect (one station twice)
                for j in range(len(idx)):
                    rest = np.delete(idx, j)
                    if _span_deg(dirs[rest]) < MIN_INTERSECTION_DEG:
                        continue
                    X = _intersect(centres[rest], dirs[rest])
                    res[j] = np.linalg.norm(uv[idx[j]] - project(intr, poses[obs_image[idx[j]]], X[None])[0])
                if not np.any(res > GROSS_PX):
                    break
                worst = int(np.nanargmax(res))
                s.obs[int(idx[worst])] = (f"{res[worst]:.1f} px from the intersection of its target's other "
                                          f"{len(idx) - 1} rays (> {GROSS_PX} px): misnamed or clipped")
                s.keep_obs[idx[worst]] = False
                idx = np.delete(idx, worst)
                changed = True
            if len(idx) == 2:
                X = _intersect(centres[idx], dirs[idx])
                res = [np.linalg.norm(uv[q] - project(intr, poses[obs_image[q]], X[None])[0]) for q in idx]
                if max(res) > GROSS_PX:
                    s.targets[t] = f"its two rays miss each other by {max(res):.1f} px (> {GROSS_PX} px)"
            if t not in s.targets and len(idx) >= 2 and _span_deg(dirs[idx]) < MIN_INTERSECTION_DEG:
                s.targets[t] = (f"its {len(idx)} rays meet at {_span_deg(dirs[idx]):.1f} deg "
                                f"(< {MIN_INTERSECTION_DEG} deg): not determined")
            if t in s.targets:
                s.keep_obs[idx] = False
                changed = True
        # images: usable observations are those of targets with two rays or more
        rays = np.bincount(obs_target[s.keep_obs], minlength=n_targets)
        usable = s.keep_obs & (rays[obs_target] >= 2)
        per_image = np.bincount(obs_image[usable], minlength=m)
        for i in np.flatnonzero(s.keep_images & (per_image < MIN_IMAGE_OBS)):
            s.images[int(i)] = (f"{per_image[i]} usable observation(s) (< {MIN_IMAGE_OBS}): too few to orient it "
                                "in the adjustment")
            s.keep_images[i] = False
            s.keep_obs &= obs_image != i
            changed = True
        changed |= _keep_main_block(s, obs_image, obs_target, m, n_targets)
        if not changed:
            break
    if len(scale_pairs):
        rays = np.bincount(obs_target[s.keep_obs], minlength=n_targets)
        for j, pair in enumerate(scale_pairs):
            short = [t for t in pair if rays[t] < 2]
            if short:
                s.bars_out[j] = ("scale bar " + "-".join(name(t) for t in pair) + ": " + ", ".join(
                    f"{name(t)} usable in {rays[t]} image(s)" + (f" ({s.targets[t]})" if t in s.targets else "")
                    for t in short) + " (2 needed)")
        if len(s.bars_out) == len(scale_pairs):
            s.scale_ok = False
            s.scale_reason = "; ".join(s.bars_out[j] for j in range(len(scale_pairs)))
    return s


#: a screened observation within this of the adjusted network's projection is put back (data snooping then tests it)
REINSTATE_PX = 0.5


def reinstated(scr: Screening, obs_image, obs_target, obs_uv, new_index, res) -> np.ndarray:
    """``(q,)`` bool: observations the screening dropped on their own (their image and target kept, the target
    determined by the adjustment ``res``) whose residual to the adjusted network is below :data:`REINSTATE_PX`."""
    q = np.array(sorted(scr.obs), dtype=int)
    out = np.zeros(len(obs_image), dtype=bool)
    if not len(q):
        return out
    q = q[scr.keep_images[obs_image[q]] & ~np.isin(obs_target[q], list(scr.targets))]
    q = q[np.isfinite(res.points[obs_target[q]]).all(axis=1)]
    for i in np.unique(new_index[obs_image[q]]):
        k = q[new_index[obs_image[q]] == i]
        r = np.linalg.norm(project(res.intrinsics, res.cam_from_part[i], res.points[obs_target[k]]) - obs_uv[k], axis=1)
        out[k[r < REINSTATE_PX]] = True
    return out
