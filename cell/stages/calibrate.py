"""CALIBRATE: Faugeras-Toscani per image (interior and exterior orientation), PnP from the robot pose
where an image gives it no depth; calibration.json."""
from __future__ import annotations

import numpy as np

from calibration.camera import invert
from calibration.errors import CalibrationError, RecordError
from calibration.faugeras_toscani import faugeras_toscani, orient_without_ft
from cell.record.jobfolder import atomic_write_json

#: Faugeras-Toscani has five parameters more than a pose with the nominal lens: a right solution fits the image
#: at least about as well. One whose reprojection rms exceeds this factor times the nominal lens's (PnP from the
#: robot pose, same points) plus :data:`FT_RMS_SLACK_PX` was pulled off by points that fit no camera (targets off
#: their nominal position, misnamed dots) and is refused: it would start the adjustment from a wrong lens.
FT_RMS_FACTOR = 1.5
FT_RMS_SLACK_PX = 0.05
#: Faugeras-Toscani calibrates from the points a pose of the nominal lens explains within this (pixels): a target
#: a millimetre off its nominal position (5-15 px at the cell's distances) does not. On the example's images with
#: 40 % of the targets moved by 1 mm (2.5 mm), Faugeras-Toscani on every point returned a focal length more than 3 %
#: off in 6 (43) of 72 images, on these points in 1 (0) of 72 (decision 0044). A lens far from its nominal values
#: loses its outer points here and is calibrated from the rest: the adjustment refines it.
CONSISTENT_PX = 3.0
#: fewer points than this: no consensus sought (Faugeras-Toscani needs at least 6, conditioned)
CONSISTENT_MIN = 12


def refuse_duplicates(file: str, what: str, names) -> None:
    """A record that lists one station or image twice (a round of the closed loop written twice before decision 0070)
    is refused with one line naming the file and the names, never adjusted as if they were two."""
    names = [str(n) for n in names]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise RecordError(f"{file} lists {len(dup)} {what}(s) more than once ({', '.join(dup[:6])}"
                          f"{' ...' if len(dup) > 6 else ''}): the record is damaged; the job cannot go on from it")


def run(ctx) -> None:
    """Faugeras-Toscani per image: interior and exterior orientation from the nominal targets.

    Faugeras-Toscani calibrates from the points one pose of the nominal lens explains (:func:`consistent_points`:
    not from targets off their nominal position). It refuses what it cannot calibrate from (too few points, nearly
    coplanar ones, bunched image points, an implausible interior orientation: see
    :mod:`calibration.faugeras_toscani`), and an orientation far from the robot's, or one that fits worse than the
    nominal lens, is refused here. Such an image is oriented by PnP with the nominal
    camera instead, started from the robot pose, and says so (calibration.json, journal, console). When
    no image passes, the adjustment starts from the nominal lens (said too); never from a refused estimate.
    An image that cannot be oriented at all (fewer than 4 named dots: glare, a fixture) keeps the robot's pose
    and says so; the adjustment's screening leaves it out when its observations are too few.
    """
    job = ctx.job
    obs = ctx.folder.read_json("observations.json")
    acq_images = ctx.folder.read_json("acquisition.json")["images"]
    for file, ims in (("acquisition.json", acq_images), ("observations.json", obs["images"])):
        refuse_duplicates(file, "station", [a["station"] for a in ims])
        refuse_duplicates(file, "image", [a["image"] for a in ims])
    acq = {a["station"]: a for a in acq_images}
    index = job.part.targets.index()
    res = []
    for o in obs["images"]:
        xyz = job.part.targets.xyz[[index[i] for i in o["ids"]]]
        uv = np.asarray(o["uv"], dtype=float).reshape(-1, 2)
        bff = np.asarray(acq[o["station"]]["base_from_flange"], dtype=float)
        robot_pose = invert(invert(job.spec.base_from_part()) @ bff @ job.spec.flange_from_cam())
        rec = {"station": o["station"], "image": o["image"]} | orient_image(job, xyz, uv, robot_pose)
        if "fallback_reason" in rec:
            reason, method = rec["fallback_reason"], rec["method"]
            ctx.log.log("warning", f"{o['image']}: {reason}; oriented by {method}")
            ctx.folder.append("orientation_fallback", image=o["image"], station=o["station"], method=method,
                              reason=reason)
        res.append(rec)
    ft_ok = [r for r in res if r["method"] == "Faugeras-Toscani"]
    start = ("Faugeras-Toscani (median of the accepted images)" if ft_ok else
             "the nominal lens: Faugeras-Toscani refused every image (see fallback_reason per image)")
    atomic_write_json(ctx.folder.file("calibration.json"), {"method": "Faugeras-Toscani", "images": res,
                                                            "interior_start": start,
                                                            "n_fallback": len(res) - len(ft_ok)})
    left = [r for r in res if r["ft_points_left_out"]]
    if left:  # what Faugeras-Toscani did not calibrate from: said, with the images
        msg = (f"Faugeras-Toscani left out {sum(r['ft_points_left_out'] for r in left)} point(s) in {len(left)} "
               f"image(s) that one pose of the nominal lens does not explain within {CONSISTENT_PX:g} px (targets off "
               "their nominal position, misnamed dots): calibration.json ft_points_left_out")
        ctx.log.log("info", msg)
        ctx.say(f"  {msg}")
    if not ft_ok:
        ctx.log.log("warning", "Faugeras-Toscani refused every image; interior orientation starts from the nominal lens")
        ctx.say(f"  WARNING Faugeras-Toscani refused all {len(res)} images (e.g. {res[0]['fallback_reason']}); "
                f"oriented instead by {_methods(res)}; interior orientation from the nominal lens")
        return
    fx = np.array([r["alpha_u"] for r in ft_ok])
    ctx.say(f"  alpha_u {fx.mean():.1f} +- {fx.std():.1f} px over {len(ft_ok)} images "
            f"(nominal {job.intrinsics.fx_px:.1f}); rms {np.median([r['rms_px'] for r in ft_ok]):.3f} px"
            + (f"; WARNING the others oriented instead by {_methods([r for r in res if r not in ft_ok])}"
               if len(ft_ok) < len(res) else ""))


def consistent_points(xyz: np.ndarray, uv: np.ndarray, intr, robot_pose: np.ndarray) -> tuple[np.ndarray, bool]:
    """``(keep (k,) bool, consensus)``: the points one pose of the nominal lens explains within
    :data:`CONSISTENT_PX` (OpenCV's PnP RANSAC, from the robot pose): a target far off its nominal position (a
    deviating part) or a misnamed dot pulls a direct linear calibration off by percent of the focal length while
    staying plausible. With fewer than :data:`CONSISTENT_MIN` points, or when no consensus of that many is found,
    every point and ``consensus`` False (calibration.json says so; Faugeras-Toscani's own checks then judge)."""
    import cv2

    xyz = np.asarray(xyz, dtype=float)
    uv = np.asarray(uv, dtype=float)
    every = np.ones(len(uv), dtype=bool)
    if len(uv) < CONSISTENT_MIN:
        return every, False
    rvec0, _ = cv2.Rodrigues(np.asarray(robot_pose, dtype=float)[:3, :3])
    ok, _, _, idx = cv2.solvePnPRansac(xyz, uv, intr.K, intr.dist_coeffs, rvec0.copy(),
                                       np.asarray(robot_pose, dtype=float)[:3, 3].copy(), useExtrinsicGuess=True,
                                       iterationsCount=200, reprojectionError=CONSISTENT_PX, confidence=0.999,
                                       flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or idx is None or len(idx) < CONSISTENT_MIN:
        return every, False
    keep = np.zeros(len(uv), dtype=bool)
    keep[np.ravel(idx)] = True
    return keep, True


def orient_image(job, xyz: np.ndarray, uv: np.ndarray, robot_pose: np.ndarray) -> dict:
    """One image's orientation from its named dots ``uv: (k, 2)`` and their nominal targets ``xyz: (k, 3)``: by
    Faugeras-Toscani (interior and exterior) on the :func:`consistent_points` when it accepts them and its solution
    fits at least about as well as the nominal lens does there (:data:`FT_RMS_FACTOR`), else by PnP with the nominal
    lens from the robot pose ``robot_pose`` (cam_from_part) on the same points, else the robot pose itself.
    calibration.json's record of the image (without its station and name): ``method``, ``cam_from_part``,
    ``rms_px``, ``nominal_lens_rms_px``, ``ft_points_left_out``, ``consensus``, the interior orientation when
    Faugeras-Toscani's, ``fallback_reason`` when not."""
    inl, consensus = consistent_points(xyz, uv, job.intrinsics, robot_pose)
    rec = {"n_points": len(uv), "ft_points_left_out": int(len(uv) - inl.sum()), "consensus": consensus}
    xyz, uv = np.asarray(xyz, dtype=float)[inl], np.asarray(uv, dtype=float)[inl]
    try:  # the nominal lens on the same points: the reference Faugeras-Toscani must match, and the fallback
        if len(uv) < 4:
            raise CalibrationError(f"only {len(uv)} targets identified")
        nominal = orient_without_ft(xyz, uv, job.intrinsics, guess=robot_pose)
        nominal_error = None
    except CalibrationError as exc:
        nominal, nominal_error = None, exc
    rec["nominal_lens_rms_px"] = None if nominal is None else nominal[1]
    try:
        ft = faugeras_toscani(xyz, uv, job.intrinsics.width, job.intrinsics.height, nominal=job.intrinsics)
        centre_gap = float(np.linalg.norm(invert(ft.cam_from_part)[:3, 3] - invert(robot_pose)[:3, 3]))
        if centre_gap > 0.1 * float(np.linalg.norm(robot_pose[:3, 3])):
            raise CalibrationError(f"its camera centre is {centre_gap * 1e3:.0f} mm from the robot's")
        if nominal is not None and ft.rms_px > FT_RMS_FACTOR * nominal[1] + FT_RMS_SLACK_PX:
            raise CalibrationError(f"its reprojection rms {ft.rms_px:.2f} px is worse than the nominal lens's "
                                   f"{nominal[1]:.2f} px on the same points: points that fit no camera (targets "
                                   "off their nominal position, misnamed dots) pulled it off")
        return rec | {"method": "Faugeras-Toscani", "alpha_u": ft.intrinsics.fx_px, "alpha_v": ft.intrinsics.fy_px,
                      "u0": ft.intrinsics.cx_px, "v0": ft.intrinsics.cy_px, "cam_from_part": ft.cam_from_part,
                      "M": ft.M, "rms_px": ft.rms_px}
    except CalibrationError as exc:
        reason = str(exc) if str(exc).startswith("Faugeras-Toscani") else f"Faugeras-Toscani: {exc}"
    if nominal is not None:
        T, rms, method = nominal
    else:
        # a weak image (glare, a fixture) does not fault the job: it keeps the robot's pose, and ADJUST's
        # screening leaves it out unless its observations support it
        T, rms, method = robot_pose, None, "robot pose (not oriented)"
        reason = f"{reason}; and {nominal_error}: not oriented"
    return rec | {"method": method, "fallback_reason": reason, "cam_from_part": T, "rms_px": rms}


def _methods(recs: list[dict]) -> str:
    """How images Faugeras-Toscani refused were oriented, counted: "3 x PnP from the robot pose, 1 x robot pose"."""
    from collections import Counter

    return ", ".join(f"{n} x {m}" for m, n in Counter(r["method"] for r in recs).items())
