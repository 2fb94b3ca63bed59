"""What a job takes from the cell file it names (``[cell] cell_file``): the cell's own calibration.

``cell calibrate hand-eye`` rewrites the cell file's ``flange_from_cam`` and writes the lens it estimated
with it (``camera_lens``). A job that names the cell file measures through those, not through what its
own file says (decision 0056): a job file written before the calibration would otherwise plan, name its
dots and place its part (``cell locate``) with the drawing's hand-eye and the data sheet's lens, and
nothing would say so.

* **The hand-eye**: the cell file's ``flange_from_cam``, in the job's units. A job may leave its own out;
  one that states it must state the cell's (within 1 um and 1e-4 deg: the cell file's rounding), else
  the job is refused and the line says by how much they differ.
* **The cell's other keys** (``robot``, ``table_z``, ``obstacles``, ``camera_box``, the workspace and elbow limits,
  the speed limits, ``host``, the light's and the thermometer's ports): the cell file's, in the job's units, where
  the job leaves them out; one the job states must be the cell's, else the job is refused (a fence the cell file has
  and the job does not would be planned through). Three exceptions: the job's ``obstacles`` are added to the cell's
  (a part's fixture; one named as a cell's obstacle must be that obstacle); the speed and acceleration limits and
  ``elbow_limit_deg`` may be stricter than the cell's, not looser; and the settling keys, ``retakes`` and the light's
  ``light_brightness_pct`` (a dark part needs more light) are the job's where it states them. ``backend`` stays the job's (or the command line's): which robot runs, the simulated
  one or the real one.
* **The camera** must be the cell's: ``[camera]`` ``width``, ``height``, ``pixel_size_um`` and ``focal_length_mm``.
* **The lens**: the cell's ``camera_lens`` when the hand-eye wrote one (the adjustment still refines it when
  ``self_calibrate``); a job that states lens terms of its own (``cx_px``, ``cy_px``, ``k1`` .. ``p2``) is
  then refused: two lenses for one camera.
* **The simulated cell**: the cell file's ``[sim] flange_from_cam_true`` is the camera's true mounting
  and its ``[sim] lens`` the camera's true lens. A job that states a simulated hand-eye error or another
  true lens as well is refused.

:func:`take_cell_file` returns the job's spec with these in place (every stage reads them from there);
:func:`cell_taken` says what was taken, for the job's journal, console and report, with the lens.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from calibration.errors import JobSpecError
from calibration.handeye import pose_error
from cell.cellcal.cellfile import CellFile, load_cell_file, pose_from_matrix
from cell.jobspec import JobSpec, pose_matrix, resolve

__all__ = ["take_cell_file", "cell_taken", "HAND_EYE_AGREE_M", "HAND_EYE_AGREE_DEG"]

#: a job's own ``flange_from_cam`` counts as the cell's within these (the cell file writes 5 decimals of mm)
HAND_EYE_AGREE_M = 1e-6
HAND_EYE_AGREE_DEG = 1e-4
_CAMERA_KEYS = ("width", "height", "pixel_size_um", "focal_length_mm")
#: [cell] keys that belong to the job, not the cell (backend: which robot runs it, the simulated or the real one)
_JOB_KEYS = ("base_from_part", "cell_file", "flange_from_cam", "backend")
_LENGTH_KEYS = ("table_z", "camera_box", "workspace_min", "workspace_max", "obstacles")
#: limits a job may tighten below the cell's (slower, less bent), never raise
_STRICTER = ("max_joint_speed_rad_s", "max_joint_accel_rad_s2", "max_tcp_speed_m_s", "max_tcp_accel_m_s2",
             "elbow_limit_deg")
#: how this job waits for the arm, retakes a frame and lights its part: its own where it states them, else the cell's
_JOBS_OWN = ("settle_s", "settle_speed_rad_s", "settle_timeout_s", "retakes", "light_brightness_pct")
_LENS_KEYS = ("cx_px", "cy_px", "k1", "k2", "k3", "p1", "p2")


def _read(spec: JobSpec, job_path: Path) -> tuple[CellFile, Path]:
    path = resolve(Path(job_path).resolve().parent, spec.cell.cell_file)
    try:
        cf, _ = load_cell_file(path)
    except JobSpecError as exc:
        raise JobSpecError(f"{job_path}: [cell] cell_file: {exc}") from None
    return cf, path


def take_cell_file(spec: JobSpec, job_path: Path) -> JobSpec:
    """``spec`` with the cell file's hand-eye (and the simulated cell's truth) in place; refusals as above."""
    if spec.cell.cell_file is None:
        return spec
    cf, path = _read(spec, job_path)
    where = f"{job_path}: [cell] cell_file {path}"
    k = cf.scale / spec.scale  # cell file units -> job units
    taken = {}
    for key in type(spec.cell).model_fields:
        if key in _JOB_KEYS or key not in type(cf.cell).model_fields:
            continue
        cells = _in_units(key, getattr(cf.cell, key), k)
        mine = getattr(spec.cell, key)
        if key not in spec.cell.model_fields_set or key in _JOBS_OWN:
            taken[key] = cells if key not in spec.cell.model_fields_set else mine
        elif key == "obstacles":  # the cell's, and this part's own (its fixture) under names the cell does not use
            taken[key] = cells + _own_obstacles(mine, cells, where, spec.job.units)
        elif key in _STRICTER and mine <= cells:  # a job may move slower and bend less than the cell allows
            taken[key] = mine
        elif key in _STRICTER:
            raise JobSpecError(f"{where}: [cell] {key} = {mine} here is beyond the cell's {cells}: a job may keep "
                               f"below the cell's limits, not above them; lower {key} to at most {cells}")
        elif not _close(mine, cells):
            raise JobSpecError(f"{where}: [cell] {key} = {_show(getattr(spec.cell, key))} here, {_show(cells)} in the "
                               f"cell file ({spec.job.units}); a job that names the cell file works in the cell it "
                               f"describes: delete {key} from the job, or correct the cell file")
    for key in _CAMERA_KEYS:
        mine, cells = getattr(spec.camera, key), getattr(cf.camera, key)
        if not np.isclose(float(mine), float(cells), rtol=1e-9, atol=0.0):
            raise JobSpecError(f"{where}: the job's camera is not the cell's: [camera] {key} = {mine} here, {cells} "
                               "in the cell file")
    X = cf.flange_from_cam()
    when = (f"calibrated {cf.cell.flange_from_cam_date}" if cf.cell.flange_from_cam_date
            else "not calibrated: the cell file's nominal one")
    if spec.cell.flange_from_cam is not None:
        dt, dr = pose_error(pose_matrix(spec.cell.flange_from_cam, spec.scale), X)
        if dt > HAND_EYE_AGREE_M or np.rad2deg(dr) > HAND_EYE_AGREE_DEG:
            raise JobSpecError(f"{where}: [cell] flange_from_cam differs from the cell's hand-eye ({when}) by "
                               f"{dt * 1e3:.4f} mm and {np.rad2deg(dr):.4f} deg; a job that names the cell file "
                               "measures with the cell's: delete flange_from_cam from the job")
    if cf.cell.camera_lens is not None:
        stated = [k for k in _LENS_KEYS if getattr(spec.camera, k) not in (None, 0.0)]
        if stated:
            raise JobSpecError(f"{where}: [camera] states lens terms ({', '.join(stated)}) and the cell file has the "
                               f"lens calibrated with its hand-eye (its camera_lens, {when}); the job measures "
                               "through the cell's: delete them from the job")
    cell = spec.cell.model_copy(update=taken | {"flange_from_cam": pose_from_matrix(X, spec.scale)})
    sim = spec.sim
    if cf.sim.flange_from_cam_true is not None:
        if sim.flange_from_cam_error is not None:
            raise JobSpecError(f"{where}: the simulated hand-eye is stated twice: the job's [sim] flange_from_cam_error "
                               "and the cell file's flange_from_cam_true (its [sim]); delete the job's")
        true_x = pose_matrix(cf.sim.flange_from_cam_true, cf.scale)
        sim = sim.model_copy(update={"flange_from_cam_error": pose_from_matrix(np.linalg.inv(X) @ true_x, spec.scale)})
    if cf.sim.lens is not None:
        if sim.lens is not None and sim.lens != cf.sim.lens:
            raise JobSpecError(f"{where}: the simulated camera's true lens is stated twice, differently: the job's "
                               "[sim] lens and the cell file's; delete the job's")
        sim = sim.model_copy(update={"lens": cf.sim.lens})
    return spec.model_copy(update={"cell": cell, "sim": sim})


def _own_obstacles(mine: list, cells: list, where: str, units: str) -> list:
    """The job's obstacles that the cell does not have (its fixture); one named as the cell's must be the cell's."""
    by_name = {ob.name: ob for ob in cells}
    own = []
    for ob in mine:
        if ob.name not in by_name:
            own.append(ob)
        elif not _close(ob, by_name[ob.name]):
            raise JobSpecError(f"{where}: [cell] obstacles: {ob.name!r} = {_show(ob)} here, {_show(by_name[ob.name])} "
                               f"in the cell file ({units}); delete it from the job (the cell's is used), or name "
                               "this part's own obstacle otherwise")
    return own


def _in_units(key: str, value, k: float):
    """A cell file's ``[cell]`` value in the job's units (``k``: cell units -> job units)."""
    if key not in _LENGTH_KEYS or value is None or k == 1.0:
        return value
    if key == "table_z":
        return value * k
    if key == "obstacles":
        return [ob.model_copy(update={"size": tuple(v * k for v in ob.size),
                                      "pose": ob.pose.model_copy(update={"xyz": tuple(v * k for v in ob.pose.xyz)})})
                for ob in value]
    return tuple(v * k for v in value)


def _plain(v):
    if hasattr(v, "model_dump"):
        return _plain(v.model_dump())
    if isinstance(v, dict):
        return {key: _plain(x) for key, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def _close(a, b) -> bool:
    """Equal, floats to 1e-9 relative (a unit conversion's rounding)."""
    a, b = _plain(a), _plain(b)
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_close(a[key], b[key]) for key in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool) and not isinstance(b, bool):
        return bool(np.isclose(float(a), float(b), rtol=1e-9, atol=1e-12))
    return a == b


def _show(v) -> str:
    text = str(_plain(v))
    return text if len(text) <= 120 else text[:117] + "..."


def cell_taken(spec: JobSpec, job_path: Path) -> dict | None:
    """What the job took from its cell file (None: it names none): for its journal, console and report.

    ``{"cell_file", "sha256", "cell", "hand_eye": {"date", "record", "calibrated"}, "lens": {fx_px ..} | None}``;
    ``lens`` is the cell's ``camera_lens`` (pixels; the job's intrinsics), None when the hand-eye wrote none.
    """
    if spec.cell.cell_file is None:
        return None
    cf, path = _read(spec, job_path)
    lens = cf.cell.camera_lens
    return {"cell_file": str(path), "sha256": hashlib.sha256(path.read_bytes()).hexdigest(), "cell": cf.cell.name,
            "hand_eye": {"calibrated": cf.cell.flange_from_cam_date is not None, "date": cf.cell.flange_from_cam_date,
                         "record": cf.cell.flange_from_cam_record},
            "lens": None if lens is None else lens.model_dump()}


def taken_line(taken: dict) -> str:
    """One line for the console and the run log: which hand-eye and lens the job measures with."""
    he = taken["hand_eye"]
    hand_eye = (f"hand-eye calibrated {he['date']}" + (f" (record {he['record']})" if he["record"] else "")
                if he["calibrated"] else "hand-eye NOT calibrated (the cell file's nominal one)")
    lens = (f"its lens ([cell] camera_lens, fx {taken['lens']['fx_px']:.2f} px)" if taken["lens"] is not None
            else "the [camera] data sheet's lens (the cell file has no camera_lens)")
    return f"cell {taken['cell']}: {hand_eye}; {lens}"
