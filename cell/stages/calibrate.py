"""CALIBRATE: Faugeras-Toscani per image (interior and exterior orientation), PnP from the robot pose
where an image gives it no depth; calibration.json."""
from __future__ import annotations

import numpy as np

from calibration.camera import invert
from calibration.errors import CalibrationError
from calibration.faugeras_toscani import faugeras_toscani, orient_without_ft
from cell.record.jobfolder import atomic_write_json


def run(ctx) -> None:
    """Faugeras-Toscani per image: interior and exterior orientation from the nominal targets.

    Faugeras-Toscani refuses what it cannot calibrate from (too few points, nearly coplanar ones, bunched
    image points, an implausible interior orientation: see :mod:`calibration.faugeras_toscani`), and an
    orientation far from the robot's is refused here. Such an image is oriented by PnP with the nominal
    camera instead, started from the robot pose, and says so (calibration.json, journal, console). When
    no image passes, the adjustment starts from the nominal lens (said too); never from a refused estimate.
    An image that cannot be oriented at all (fewer than 4 named dots: glare, a fixture) keeps the robot's pose
    and says so; the adjustment's screening leaves it out when its observations are too few.
    """
    job = ctx.job
    obs = ctx.folder.read_json("observations.json")
    acq = {a["station"]: a for a in ctx.folder.read_json("acquisition.json")["images"]}
    index = job.part.targets.index()
    res = []
    for o in obs["images"]:
        xyz = job.part.targets.xyz[[index[i] for i in o["ids"]]]
        uv = np.asarray(o["uv"], dtype=float).reshape(-1, 2)
        bff = np.asarray(acq[o["station"]]["base_from_flange"], dtype=float)
        robot_pose = invert(invert(job.spec.base_from_part()) @ bff @ job.spec.flange_from_cam())
        rec = {"station": o["station"], "image": o["image"], "n_points": len(uv)}
        try:
            ft = faugeras_toscani(xyz, uv, job.intrinsics.width, job.intrinsics.height, nominal=job.intrinsics)
            centre_gap = float(np.linalg.norm(invert(ft.cam_from_part)[:3, 3] - invert(robot_pose)[:3, 3]))
            if centre_gap > 0.1 * float(np.linalg.norm(robot_pose[:3, 3])):
                raise CalibrationError(f"its camera centre is {centre_gap * 1e3:.0f} mm from the robot's")
            rec |= {"method": "Faugeras-Toscani", "alpha_u": ft.intrinsics.fx_px, "alpha_v": ft.intrinsics.fy_px,
                    "u0": ft.intrinsics.cx_px, "v0": ft.intrinsics.cy_px, "cam_from_part": ft.cam_from_part,
                    "M": ft.M, "rms_px": ft.rms_px}
        except CalibrationError as exc:
            reason = str(exc) if str(exc).startswith("Faugeras-Toscani") else f"Faugeras-Toscani: {exc}"
            try:
                if len(uv) < 4:
                    raise CalibrationError(f"only {len(uv)} targets identified")
                T, rms, method = orient_without_ft(xyz, uv, job.intrinsics, guess=robot_pose)
            except CalibrationError as exc2:
                # a weak image (glare, a fixture) does not fault the job: it keeps the robot's pose, and ADJUST's
                # screening leaves it out unless its observations support it
                T, rms, method = robot_pose, None, "robot pose (not oriented)"
                reason = f"{reason}; and {exc2}: not oriented"
            rec |= {"method": method, "fallback_reason": reason, "cam_from_part": T, "rms_px": rms}
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


def _methods(recs: list[dict]) -> str:
    """How images Faugeras-Toscani refused were oriented, counted: "3 x PnP from the robot pose, 1 x robot pose"."""
    from collections import Counter

    return ", ".join(f"{n} x {m}" for m, n in Counter(r["method"] for r in recs).items())
