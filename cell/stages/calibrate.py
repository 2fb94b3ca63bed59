"""CALIBRATE: Faugeras-Toscani per image (interior and exterior orientation), PnP from the robot pose
where an image gives it no depth; calibration.json."""
from __future__ import annotations

import cv2
import numpy as np

from calibration.camera import invert, project
from calibration.errors import CalibrationError
from calibration.faugeras_toscani import faugeras_toscani
from cell.record.jobfolder import atomic_write_json


def _pnp_from_robot(job, xyz: np.ndarray, uv: np.ndarray, base_from_flange: np.ndarray) -> tuple[np.ndarray, float]:
    """Exterior orientation by PnP with the nominal camera, started from the robot's pose and the hand-eye."""
    cam_from_part = invert(invert(job.spec.base_from_part()) @ base_from_flange @ job.spec.flange_from_cam())
    rvec, _ = cv2.Rodrigues(cam_from_part[:3, :3])
    ok, rvec, tvec = cv2.solvePnP(xyz, uv, job.intrinsics.K, job.intrinsics.dist_coeffs, rvec.copy(),
                                  cam_from_part[:3, 3].copy(), useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError("PnP from the robot pose failed")
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    rms = float(np.sqrt(np.mean(np.sum((project(job.intrinsics, T, xyz) - uv) ** 2, axis=1))))
    return T, rms


def run(ctx) -> None:
    """Faugeras-Toscani per image: interior and exterior orientation from the nominal targets.

    An image whose targets are nearly coplanar (one face of the part fills it) gives Faugeras-Toscani
    no depth to work with: it fails, or returns an orientation far from the robot's. Such an image
    is oriented by PnP with the nominal camera instead, started from the robot pose, and says so.
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
            ft = faugeras_toscani(xyz, uv, job.intrinsics.width, job.intrinsics.height)
            centre_gap = float(np.linalg.norm(invert(ft.cam_from_part)[:3, 3] - invert(robot_pose)[:3, 3]))
            if centre_gap > 0.1 * float(np.linalg.norm(robot_pose[:3, 3])):
                raise CalibrationError(f"its camera centre is {centre_gap * 1e3:.0f} mm from the robot's")
            rec |= {"method": "Faugeras-Toscani", "alpha_u": ft.intrinsics.fx_px, "alpha_v": ft.intrinsics.fy_px,
                    "u0": ft.intrinsics.cx_px, "v0": ft.intrinsics.cy_px, "cam_from_part": ft.cam_from_part,
                    "M": ft.M, "rms_px": ft.rms_px}
        except CalibrationError as exc:
            if len(uv) < 4:
                raise CalibrationError(f"image {o['image']} (station {o['station']}): only {len(uv)} targets "
                                       "identified; cannot orient it") from None
            T, rms = _pnp_from_robot(job, xyz, uv, bff)
            rec |= {"method": "PnP from the robot pose", "fallback_reason": f"Faugeras-Toscani: {exc}",
                    "cam_from_part": T, "rms_px": rms}
            ctx.log.log("warning", f"{o['image']}: Faugeras-Toscani unusable ({exc}); oriented by PnP")
        res.append(rec)
    atomic_write_json(ctx.folder.file("calibration.json"), {"method": "Faugeras-Toscani", "images": res})
    ft_ok = [r for r in res if r["method"] == "Faugeras-Toscani"]
    if not ft_ok:
        raise CalibrationError("Faugeras-Toscani failed on every image: check the target identification")
    fx = np.array([r["alpha_u"] for r in ft_ok])
    ctx.say(f"  alpha_u {fx.mean():.1f} +- {fx.std():.1f} px over {len(ft_ok)} images "
            f"(nominal {job.intrinsics.fx_px:.1f}); rms {np.median([r['rms_px'] for r in ft_ok]):.3f} px"
            + (f"; {len(res) - len(ft_ok)} image(s) oriented by PnP" if len(ft_ok) < len(res) else ""))
