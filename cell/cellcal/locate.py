"""``cell locate JOB.toml [--write]``: find where the part really sits, from a quick first image set.

The operator places the part roughly where the job's ``[cell] base_from_part`` says; a few
overview images of its coded markers and dots then give the real placement
(:func:`cell.cellcal.placement.estimate_part_placement`, the hand-eye held fixed). With ``write=True``
the job file's ``base_from_part = { ... }`` line is rewritten, so the next ``cell plan`` /
``cell run`` plans stations that follow the part. Only that line changes; the new text is
validated (reloaded, and its pose checked against the estimate) before it atomically replaces
the file, so a failure leaves the old file.
"""
from __future__ import annotations

import re
import tomllib
from pathlib import Path

import numpy as np
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from calibration.errors import JobSpecError
from cell.record.jobfolder import atomic_write_bytes
from cell.jobspec import JobSpec

__all__ = ["locate_part", "write_base_from_part", "format_pose"]

_KEY = re.compile(r"^(?P<indent>[ \t]*)base_from_part[ \t]*=(?P<rest>.*?)(?P<eol>\r?\n)?$", re.DOTALL)
_HEAD = re.compile(r"^[ \t]*\[\s*(?P<name>[A-Za-z0-9_.]+)\s*\][ \t]*(#.*)?$")


def format_pose(base_from_part: np.ndarray, scale: float) -> str:
    """The TOML inline table ``{ xyz = [...], rpy_deg = [...] }`` of a 4x4 transform (metres) in job units.

    ``rpy_deg`` as :class:`cell.jobspec.Pose` reads it (fixed x, y, z axes); translations to 0.1 um
    and angles to 1e-7 degrees, far below what the placement is known to.
    """
    T = np.asarray(base_from_part, dtype=float)
    rpy = Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)
    xyz = ", ".join(f"{v:.4f}" for v in T[:3, 3] / scale)
    return f"{{ xyz = [{xyz}], rpy_deg = [{', '.join(f'{v:.7f}' for v in rpy)}] }}"


def write_base_from_part(job_path: Path, base_from_part: np.ndarray, *, dry_run: bool = False) -> JobSpec:
    """Rewrite the ``[cell] base_from_part = {...}`` line of ``job_path``; every other byte is kept.

    The key must be a one-line inline table (a trailing comment is kept). The new text is parsed and
    validated as a job file and its pose compared with ``base_from_part`` (within 1 um, 1e-6 rad)
    before it atomically replaces the file (``dry_run``: not written; ``cell locate --write`` tries the job's own
    placement so before the robot moves). Returns the new, validated spec.

    Raises:
        JobSpecError: the file has no such line in ``[cell]``, it spans several lines, or the new text
            does not validate (the old file is left as it was).
    """
    job_path = Path(job_path)
    raw = job_path.read_bytes()
    try:
        text = raw.decode("utf-8")
        spec = JobSpec.model_validate(tomllib.loads(text))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError, ValidationError) as exc:
        raise JobSpecError(f"{job_path}: not a valid job file ({str(exc).splitlines()[0]}); fix it before "
                           "writing the placement") from None
    lines = text.splitlines(keepends=True)
    section, hit = None, None
    for i, ln in enumerate(lines):
        h = _HEAD.match(ln.rstrip("\r\n"))
        if h:
            section = h.group("name")
            continue
        if section == "cell" and _KEY.match(ln):
            hit = i
            break
    m = _KEY.match(lines[hit]) if hit is not None else None
    if m is None or "{" not in m.group("rest") or m.group("rest").count("{") != m.group("rest").count("}"):
        where = f"{job_path}:{hit + 1}" if hit is not None else str(job_path)
        raise JobSpecError(f"{where}: [cell] base_from_part must be written on one line as "
                           "base_from_part = { xyz = [...], rpy_deg = [...] } to be rewritten; put it in that form")
    rest = m.group("rest")
    comment = re.search(r"\}[ \t]*(#.*)$", rest)
    new_line = f"{m.group('indent')}base_from_part = {format_pose(base_from_part, spec.scale)}"
    if comment:
        new_line += "  " + comment.group(1)
    lines[hit] = new_line + (m.group("eol") or "")
    new_text = "".join(lines)
    try:
        new_spec = JobSpec.model_validate(tomllib.loads(new_text))
    except (tomllib.TOMLDecodeError, ValidationError) as exc:
        raise JobSpecError(f"{job_path}: the rewritten base_from_part does not validate ({str(exc).splitlines()[0]}); "
                           "the file was left as it was") from None
    got = new_spec.base_from_part()
    want = np.asarray(base_from_part, dtype=float)
    if np.abs(got[:3, 3] - want[:3, 3]).max() > 1e-6 or np.abs(got[:3, :3] - want[:3, :3]).max() > 1e-6:
        raise JobSpecError(f"{job_path}: the rewritten base_from_part does not read back as the estimate; "
                           "the file was left as it was")
    if not dry_run:
        atomic_write_bytes(job_path, new_text.encode("utf-8"))
    return new_spec


def locate_part(job_path: Path, out, *, write: bool, backend: str | None = None, n_images: int = 4) -> dict:
    """Estimate the part's placement on the cell; print it; with ``write`` put it into the job file.

    ``out`` has ``say(str)`` and ``progress(stage, fraction)``. ``backend`` defaults to the job's
    ``[cell] backend``. Returns a JSON-able summary: ``base_from_part`` (4x4, metres), ``pose``
    (job units, as the file states it), ``sigma_translation_m`` (3,) of the part origin,
    ``sigma_rotation_rad`` (3,) about the base axes, ``cov`` (6, 6), the change from the job's
    nominal placement, the adjustment's figures, ``written``; and on the simulated cell ``truth``
    (the estimate's error against the simulated placement).
    """
    from calibration.handeye import pose_error
    from cell.cellcal.placement import estimate_part_placement
    from cell.devices import open_devices
    from cell.loadedjob import load

    job_path = Path(job_path)
    job = load(job_path)
    backend = backend or job.spec.cell.backend
    k = job.spec.scale
    units = job.spec.job.units
    if write:  # a file whose base_from_part cannot be rewritten is said before the robot moves, not after
        write_base_from_part(job_path, job.spec.base_from_part(), dry_run=True)
    out.say(f"locate: {job.spec.job.name}: planning at least {n_images} overview images of the coded markers "
            f"around the nominal placement ({backend})")
    devices = open_devices(job, backend)
    truth = None
    try:
        if devices.world is not None and backend == "sim":
            truth = np.asarray(devices.world.true_base_from_part, dtype=float).copy()
        Y, s = estimate_part_placement(job, devices, out, n_images=n_images)
    finally:
        devices.close()
    pose = format_pose(Y, k)
    sig_t, sig_r = s["sigma_translation_m"], s["sigma_rotation_rad"]
    out.say(f"base_from_part = {pose}")
    out.say(f"  +- xyz [{', '.join(f'{v / k:.4f}' for v in sig_t)}] {units}, rotation about x, y, z "
            f"[{', '.join(f'{np.rad2deg(v):.5f}' for v in sig_r)}] deg (1 sigma, from the images; the hand-eye and "
            "the robot's accuracy come on top)")
    out.say(f"  {s['change_from_nominal_m'] / k:.3f} {units}, {np.rad2deg(s['change_from_nominal_rad']):.3f} deg "
            f"from the job's base_from_part")
    summary = {"job_file": str(job_path), "backend": backend, "base_from_part": Y,
               "pose": {"xyz": [float(v) for v in Y[:3, 3] / k],
                        "rpy_deg": [float(v) for v in Rotation.from_matrix(Y[:3, :3]).as_euler("xyz", degrees=True)],
                        "units": units},
               "sigma_translation_m": sig_t, "sigma_rotation_rad": sig_r, "cov": s["cov"],
               "change_from_nominal_m": s["change_from_nominal_m"],
               "change_from_nominal_rad": s["change_from_nominal_rad"],
               "images": s["images"], "n_observations": s["n_observations"], "n_rejected": s["n_rejected"],
               "sigma0_px": s["sigma0_px"],
               "coded": {key: v for key, v in s["coded"].items() if key != "base_from_part"},
               "markers_not_planned": s["markers_not_planned"], "lens": s["lens"], "warnings": s["warnings"],
               "written": False}
    if truth is not None:
        dt, dr = pose_error(Y, truth)
        summary["truth"] = {"base_from_part": truth, "error_m": dt, "error_rad": dr}
        out.say(f"  simulated cell: the estimate is {dt * 1e6:.1f} um, {np.rad2deg(dr) * 3600:.2f} arcsec "
                "from the truth")
    if write:
        write_base_from_part(job_path, Y)
        summary["written"] = True
        out.say(f"  written to {job_path} ([cell] base_from_part); plan again to follow the part")
    return summary

