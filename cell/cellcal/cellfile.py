"""The cell file (CELL.toml): what a cell is, independent of any part.

Sections (lengths in the file's ``units`` unless the key names its unit; unknown keys are an error;
relative paths are relative to the cell file's folder):

* ``[cell]``: as a job file's ``[cell]`` (robot, backend, host, obstacles, limits,
  ``flange_from_cam``) plus ``name``, ``units`` and, written by the hand-eye job,
  ``flange_from_cam_date`` (ISO 8601, UTC), ``flange_from_cam_record`` (its archive record) and
  ``camera_lens``, the lens estimated with it (the cell's own jobs use it in place of ``[camera]``'s data sheet).
  ``base_from_part`` has no meaning for a cell and is not allowed.
* ``[camera]``: as a job file's ``[camera]``.
* ``[hand_eye]``: the calibration artefact (mesh, targets, dot and marker size), its approximate
  ``placement`` in the base frame; what the network planner is asked for (``n_stations``,
  ``min_rays``, ``n_candidates``, tilt and incidence limits, ``seed``) and the conditioning the planned
  network must have (``max_sigma_translation``, ``max_sigma_rotation_deg``, ``min_weakest_rotation_deg``;
  ``max_plans`` networks are tried).
* ``[reverification]``: the scale bar (mesh, targets, ``a``, ``b``, calibrated ``length`` and
  its ``sigma``), the bar ``positions`` in the measuring volume, the maximum permissible length
  measurement error ``E_MPE = max_permissible_error + max_permissible_error_per_length * L``, the planner's
  ``stations_per_position`` (each sees both ends), ``n_candidates``, tilt and incidence limits
  and the reverification ``interval_days``.
* ``[archive]``: ``url`` of the archive database (``sqlite:///PATH`` or ``postgresql://...``; the
  command line's ``--archive-url`` and ``CELL_ARCHIVE_URL`` come first) and ``push``, the shared
  storage (a folder or ``s3://bucket/prefix``) every closed job is copied to.
* ``[sim]``: as a job file's ``[sim]``, but the simulated cell's real hand-eye is stated absolutely
  (``flange_from_cam_true``: calibration rewrites ``flange_from_cam``, the truth stays); ``base_from_part_error``
  is the artefacts' true placement error. A part's unknowns (``deviations``, worn dots: ``damaged_targets``)
  belong in a job file and are refused here.

:func:`write_flange_from_cam` rewrites only the hand-eye lines of ``[cell]`` (comments and every
other line kept byte for byte), validates the result, and replaces the file atomically.
"""
from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, Strict, ValidationError, field_validator, model_validator
from scipy.spatial.transform import Rotation

from calibration.errors import JobSpecError
from cell.record.jobfolder import atomic_write_bytes
from cell.jobspec import (DEFAULT_CAMERA_BOX_MM, DEFAULT_CODED_SIZE_MM, CameraSection, CellSection, Pose, SimSection,
                          _format_validation_error, fill_unit_defaults, pose_matrix)
from planning.part import UNITS_TO_M

__all__ = ["CellFile", "load_cell_file", "write_flange_from_cam", "pose_from_matrix"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, strict=True)  # as a job file's


#: the calibration artefacts' dot diameter, mm, where [hand_eye] or [reverification] leaves it out
ARTEFACT_DOT_DIAMETER_MM = 5.0


class CameraLens(_Strict):
    """The lens the hand-eye was calibrated with (pixels; distortion in normalised coordinates), written with it."""

    fx_px: float = Field(gt=0)
    fy_px: float = Field(gt=0)
    cx_px: float
    cy_px: float
    k1: float = Field(default=0.0, ge=-10, le=10)  # the ranges of a job file's [camera]
    k2: float = Field(default=0.0, ge=-100, le=100)
    k3: float = Field(default=0.0, ge=-1000, le=1000)
    p1: float = Field(default=0.0, ge=-1, le=1)
    p2: float = Field(default=0.0, ge=-1, le=1)
    cov: tuple[Annotated[tuple[float, ...], Strict(False)], ...] | None = Field(
        default=None, strict=False, description="covariance of the nine terms above, in their order (px^2 for fx_px .. cy_px): the "
        "lens's uncertainty from the hand-eye calibration; a job that holds the lens carries it (decision 0056)")

    @field_validator("cov")
    @classmethod
    def _covariance(cls, v):
        if v is None:
            return v
        C = np.asarray(v, dtype=float)
        if C.shape != (9, 9) or not np.isfinite(C).all():
            raise ValueError(f"camera_lens.cov must be 9 x 9 finite numbers (fx_px .. p2), got shape {C.shape}")
        d = np.sqrt(np.clip(np.diag(C), 1e-300, None))
        R = C / np.outer(d, d)  # its correlations: the terms' scales differ by 10 orders
        if (np.diag(C) < 0).any() or not np.allclose(R, R.T, atol=1e-9) or np.linalg.eigvalsh(0.5 * (R + R.T)).min() < -1e-6:
            raise ValueError("camera_lens.cov must be a covariance: symmetric and positive semi-definite")
        return v


LENS_KEYS = ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3", "p1", "p2")
#: a calibrated principal distance over the data sheet's (focal_length_mm / pixel_size_um), and fy over fx: the
#: ranges of a job's [sim] lens (principal_distance_factor, aspect); outside, the lens is another camera's or a typo
FX_OVER_NOMINAL = (0.8, 1.25)
ASPECT_RANGE = (0.9, 1.1)


class CellFileCell(CellSection):
    name: str = Field(min_length=1)
    units: Literal["m", "mm", "cm", "um", "in", "ft"] = "mm"
    base_from_part: None = None  # a cell has no part; jobs state where theirs is
    flange_from_cam: Pose
    flange_from_cam_date: str | None = Field(default=None, description="when flange_from_cam was calibrated")
    flange_from_cam_record: str | None = Field(default=None, description="archive record of that calibration")
    camera_lens: CameraLens | None = Field(
        default=None, description="the lens estimated with flange_from_cam (written by the hand-eye job; the "
        "cell's own jobs use it in place of [camera]'s data sheet, decision 0055)")


class HandEyeSection(_Strict):
    mesh: str
    targets: str
    target_diameter: float = Field(default=ARTEFACT_DOT_DIAMETER_MM, gt=0, description="file units (default 5 mm)")
    coded_size: float = Field(default=DEFAULT_CODED_SIZE_MM, gt=0, description="file units (default 20 mm)")
    placement: Pose = Field(description="approximate base_from_artefact, file units")
    n_stations: int = Field(default=14, ge=4, le=60)
    min_rays: int = Field(default=3, ge=2, description="fewest stations that must measure every dot (planner)")
    n_candidates: int = Field(default=600, ge=20, le=20_000, description="candidate stations of the planner")
    incidence_max_deg: float = Field(default=55.0, gt=0, lt=90)
    max_tilt_deg: float = Field(default=45.0, gt=0, lt=90, description="largest camera tilt from the artefact normal")
    roll_spread_deg: float = Field(default=60.0, ge=0, le=90, description="stations rolled about the optical axis "
                                   "over +- this (the planner plans at zero roll; AX = XB needs such rotations too)")
    max_sigma_translation: float = Field(default=0.05, gt=0, description="required predicted sigma of the "
                                         "hand-eye's translation, file units")
    max_sigma_rotation_deg: float = Field(default=0.005, gt=0, description="required predicted sigma of its rotation")
    min_weakest_rotation_deg: float = Field(default=10.0, ge=0, lt=180, description="required rotation of the "
                                            "stations' motions about their least-excited direction")
    max_plans: int = Field(default=4, ge=1, le=20, description="planned networks (seeds) tried for the conditioning")
    seed: int = Field(default=0, ge=0, lt=2**62, description="random seed (a non-negative integer)")

    @model_validator(mode="after")
    def _rays_fit(self):
        if self.min_rays > self.n_stations:
            raise ValueError(f"hand_eye.min_rays = {self.min_rays} exceeds n_stations = {self.n_stations}")
        return self


class ReverificationSection(_Strict):
    mesh: str
    targets: str
    a: str
    b: str
    length: float = Field(gt=0, description="calibrated distance a-b, file units")
    sigma: float = Field(default=0.0, ge=0)
    target_diameter: float = Field(default=ARTEFACT_DOT_DIAMETER_MM, gt=0, description="file units (default 5 mm)")
    coded_size: float = Field(default=DEFAULT_CODED_SIZE_MM, gt=0, description="file units (default 20 mm)")
    positions: list[Pose] = Field(min_length=1, description="base_from_bar in each position, file units")
    stations_per_position: int = Field(default=5, ge=2, le=30, description="planned stations, each sees a and b")
    n_candidates: int = Field(default=300, ge=20, le=20_000, description="candidate stations of the planner")
    max_tilt_deg: float = Field(default=40.0, gt=0, lt=90)
    incidence_max_deg: float = Field(default=55.0, gt=0, lt=90)
    max_permissible_error: float = Field(gt=0, description="E_MPE constant term, file units")
    max_permissible_error_per_length: float = Field(default=0.0, ge=0, description="E_MPE term per unit length")
    interval_days: float = Field(default=30.0, gt=0)
    seed: int = Field(default=0, ge=0, lt=2**62, description="random seed (a non-negative integer)")


class CellSimSection(SimSection):
    flange_from_cam_true: Pose | None = Field(
        default=None, description="the simulated cell's real hand-eye (absolute: the file's flange_from_cam changes "
                                  "when calibrated, the truth does not); default: the file's")


class ArchiveSection(_Strict):
    """Where the cell's jobs are indexed and copied for the site (``--archive-url`` and
    ``CELL_ARCHIVE_URL`` come first)."""

    url: str | None = Field(default=None, pattern=r"^(sqlite:///|postgres(ql)?(\+psycopg)?://)",
                            description="the archive database: sqlite:///PATH or postgresql://USER@HOST:PORT/DB")
    push: str | None = Field(default=None, min_length=1,
                             description="shared storage every closed job is copied to: a folder or s3://bucket/prefix")


class CellFile(_Strict):
    """A whole cell file, validated. Use :func:`load_cell_file`."""

    cell: CellFileCell
    camera: CameraSection
    hand_eye: HandEyeSection | None = None
    reverification: ReverificationSection | None = None
    sim: CellSimSection = CellSimSection()
    archive: ArchiveSection = ArchiveSection()

    @model_validator(mode="after")
    def _physical_defaults(self):  # the keys left out are physical sizes, in the file's units (as a job's)
        fill_unit_defaults(self.cell, self.cell.units, {"camera_box": DEFAULT_CAMERA_BOX_MM})
        for section in (self.hand_eye, self.reverification):
            if section is not None:
                fill_unit_defaults(section, self.cell.units, {"target_diameter": ARTEFACT_DOT_DIAMETER_MM,
                                                              "coded_size": DEFAULT_CODED_SIZE_MM})
        return self

    @model_validator(mode="after")
    def _lens_of_this_camera(self):
        lens, cam = self.cell.camera_lens, self.camera
        if lens is None:
            return self
        for key, value, size in (("cx_px", lens.cx_px, cam.width), ("cy_px", lens.cy_px, cam.height)):
            if not 0 <= value <= size - 1:
                raise ValueError(f"cell.camera_lens.{key} = {value} lies outside the image (0..{size - 1} px of "
                                 "[camera])")
        nominal = cam.focal_length_mm / cam.pixel_size_um * 1e3
        lo, hi = FX_OVER_NOMINAL
        for key in ("fx_px", "fy_px"):
            value = getattr(lens, key)
            if not lo <= value / nominal <= hi:
                raise ValueError(f"cell.camera_lens.{key} = {value} is {value / nominal:.3g} times the data sheet's "
                                 f"{nominal:.1f} px ([camera] focal_length_mm / pixel_size_um), outside {lo}..{hi}: "
                                 "another camera's lens, or not in pixels")
        if not ASPECT_RANGE[0] <= lens.fy_px / lens.fx_px <= ASPECT_RANGE[1]:
            raise ValueError(f"cell.camera_lens fy_px / fx_px = {lens.fy_px / lens.fx_px:.4g}, outside "
                             f"{ASPECT_RANGE[0]}..{ASPECT_RANGE[1]}: a sensor's pixels are square within a few per cent")
        return self

    @model_validator(mode="after")
    def _sim_has_no_deviations(self):
        if self.sim.deviations is not None:
            raise ValueError("sim.deviations belongs in a job file, not in a cell file")
        if self.sim.damaged_targets:
            raise ValueError("sim.damaged_targets belongs in a job file (worn dots of a part), not in a cell file")
        if self.sim.flange_from_cam_error is not None:
            raise ValueError("a cell file states the simulated hand-eye absolutely: use sim.flange_from_cam_true")
        return self

    @property
    def scale(self) -> float:
        return UNITS_TO_M[self.cell.units]

    def flange_from_cam(self) -> np.ndarray:
        return pose_matrix(self.cell.flange_from_cam, self.scale)

    def mpe_m(self, length_m: float) -> float:
        r = self.reverification
        return r.max_permissible_error * self.scale + r.max_permissible_error_per_length * length_m


def load_cell_file(path: str | Path) -> tuple[CellFile, Path]:
    """Read and validate a cell file; returns ``(cell, folder)``. Raises JobSpecError naming file and key."""
    path = Path(path)
    if not path.is_file():
        raise JobSpecError(f"{path}: cell file not found")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise JobSpecError(f"{path}: not valid TOML ({exc})") from None
    try:
        cf = CellFile.model_validate(data)
    except ValidationError as err:
        raise JobSpecError(_format_validation_error(path, err)) from None
    return cf, path.resolve().parent


def pose_from_matrix(T: np.ndarray, scale: float) -> Pose:
    """The :class:`Pose` (file units, rpy degrees) of a 4x4 transform in metres."""
    T = np.asarray(T, dtype=float)
    rpy = Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)
    return Pose(xyz=tuple(float(v) for v in T[:3, 3] / scale), rpy_deg=tuple(float(v) for v in rpy))


def _fmt_pose(p: Pose) -> str:
    xyz = ", ".join(f"{v:.5f}" for v in p.xyz)
    rpy = ", ".join(f"{v:.7f}" for v in p.rpy_deg)
    return f"{{ xyz = [{xyz}], rpy_deg = [{rpy}] }}"


def _section_span(lines: list[str], name: str) -> tuple[int, int]:
    head = re.compile(r"^\s*\[\s*" + re.escape(name) + r"\s*\]\s*(#.*)?$")
    any_head = re.compile(r"^\s*\[")
    start = next((i for i, ln in enumerate(lines) if head.match(ln)), None)
    if start is None:
        raise JobSpecError(f"cell file has no [{name}] section")
    end = next((i for i in range(start + 1, len(lines)) if any_head.match(lines[i])), len(lines))
    return start, end


def write_flange_from_cam(path: str | Path, flange_from_cam: np.ndarray, date: str, record: str | None = None,
                          lens=None, lens_cov=None) -> CellFile:
    """Write a calibrated hand-eye (4x4, metres) and its date into the cell file's ``[cell]``, with the lens
    (:class:`calibration.camera.Intrinsics`) it was estimated with when given, and that lens's covariance ``lens_cov``
    (9 x 9 over :data:`LENS_KEYS`).

    Only the lines ``flange_from_cam = ...``, ``flange_from_cam_date = ...``,
    ``flange_from_cam_record = ...`` and ``camera_lens = ...`` are replaced (or added after
    ``flange_from_cam``); the new text is validated before it atomically replaces the file, so a
    failure leaves the old file. Returns the new, validated cell file.
    """
    path = Path(path)
    cf, _ = load_cell_file(path)
    text = path.read_text(encoding="utf-8-sig")
    nl = "\r\n" if "\r\n" in text else "\n"
    lines = text.splitlines()
    s, e = _section_span(lines, "cell")
    keys = {"flange_from_cam": _fmt_pose(pose_from_matrix(flange_from_cam, cf.scale)),
            "flange_from_cam_date": f'"{date}"'}
    if record is not None:
        keys["flange_from_cam_record"] = f'"{record}"'
    if lens is not None:
        terms = [f"{k} = {float(getattr(lens, k)):.9g}" for k in LENS_KEYS]
        if lens_cov is not None:  # the lens's uncertainty with it (decision 0056)
            terms.append("cov = [" + ", ".join("[" + ", ".join(f"{float(x):.12g}" for x in row) + "]"
                                               for row in np.asarray(lens_cov, dtype=float)) + "]")
        keys["camera_lens"] = "{ " + ", ".join(terms) + " }"
    found = {}
    for i in range(s + 1, e):
        m = re.match(r"^(\s*)(flange_from_cam(?:_date|_record)?|camera_lens)\s*=(.*)$", lines[i])
        if m and m.group(2) in keys:
            rest = m.group(3)
            table = m.group(2) in ("flange_from_cam", "camera_lens")
            if table and rest.count("{") != rest.count("}"):
                raise JobSpecError(f"{path}:{i + 1}: [cell] {m.group(2)} must be a one-line inline table to be "
                                   "rewritten; put it on one line")
            comment = ""
            c = re.search(r"\}\s*(#.*)$" if table else r"\"\s*(#.*)$", rest)
            if c:
                comment = "  " + c.group(1)
            lines[i] = f"{m.group(1)}{m.group(2)} = {keys[m.group(2)]}{comment}"
            found[m.group(2)] = i
    if "flange_from_cam" not in found:
        raise JobSpecError(f"{path}: [cell] has no flange_from_cam line to update")
    at = found["flange_from_cam"]
    for k in ("flange_from_cam_date", "flange_from_cam_record", "camera_lens"):
        if k in keys and k not in found:
            at += 1
            lines.insert(at, f"{k} = {keys[k]}")
    new = nl.join(lines) + (nl if text.endswith(("\n", "\r\n")) else "")
    try:
        out = CellFile.model_validate(tomllib.loads(new))
    except (tomllib.TOMLDecodeError, ValidationError) as exc:  # pragma: no cover - guarded by the edits above
        raise JobSpecError(f"{path}: rewriting flange_from_cam would break the file ({exc}); left unchanged") from None
    atomic_write_bytes(path, new.encode("utf-8"))
    return out
