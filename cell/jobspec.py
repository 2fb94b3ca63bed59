"""The job file: TOML parsed into pydantic models, unknown keys forbidden.

Lengths in ``[job]``, ``[cell]``, ``[report]`` and the ``[sim]`` deviations are in
the job's ``units`` and are converted to metres by :func:`load_job`; keys whose
name carries a unit (``focal_length_mm``, ``pixel_size_um``, ``..._deg``,
``..._px``, ``..._s``) are in that unit. Relative paths are relative to the job
file's folder. Every problem is a ``JobSpecError`` naming the file and the key.

Every number is checked here, at ``cell check``, never after the robot moved: finite
(NaN and infinity are refused everywhere), within a plausible range, and ordered where
two keys bound an interval (near < far, elevation min < max, workspace min < max,
distance min < max). Keys that only a simulated device can honour are checked against the robot the job
will drive (:func:`check_backend`): ``[sim] unreachable_stations`` with a real UR is refused here.

``[sim] damaged_targets`` wears the coating of plain dots in the simulated images (an ``edge`` lost beyond a
chord, a dark ``spot``; :class:`DamagedTarget`): its shares and the spot's place are checked here, one damage per
dot; the ids against the part at LOAD (:func:`damaged_target_rows`, with the job's other target ids).
"""
from __future__ import annotations

import ipaddress
import math
import re
import tomllib
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from scipy.spatial.transform import Rotation

from calibration.camera import Intrinsics, make_pose
from calibration.errors import JobSpecError
from drivers.pixels import BIT_DEPTH
from planning.part import UNITS_TO_M, load_deviations  # noqa: F401 (the [sim] deviations CSV: read there)

__all__ = ["DamagedTarget", "JobSpec", "Pose", "ThermalSection", "check_backend", "damaged_target_rows", "load_job", "read_job", "pose_matrix"]


class _Strict(BaseModel):
    """Strict types: a number written as a string ("16"), a bool as 1 or "yes", an integer count as 16.0 is refused,
    not coerced (an int stands for a float). A TOML array is a tuple's value: those fields say ``strict=False``, their
    items stay strict."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, strict=True)


#: Largest plausible length in a job file, metres (the cell, its obstacles, a part's placement).
MAX_LENGTH_M = 100.0
#: the physical sizes, mm, of the length keys a file may leave out; in the file's own units when it does
DEFAULT_DOT_DIAMETER_MM = 6.0
DEFAULT_CODED_SIZE_MM = 20.0
DEFAULT_CAMERA_BOX_MM = (80.0, 80.0, 120.0)


def fill_unit_defaults(section: BaseModel, units: str, defaults_mm: dict[str, float | tuple[float, ...]]) -> None:
    """Set each key of ``defaults_mm`` that ``section`` was not given to that physical size in ``units`` (a job in
    metres gets a 0.12 m camera box, not a 120 m one). For a model validator of a frozen section: the keys stay out
    of ``model_fields_set`` (the file did not state them). In mm the values are the defaults exactly."""
    k = 1e-3 / UNITS_TO_M[units]
    for key, mm in defaults_mm.items():
        if key not in section.model_fields_set:
            value = tuple(v * k for v in mm) if isinstance(mm, tuple) else mm * k
            object.__setattr__(section, key, value)


class Pose(_Strict):
    """A rigid transform: translation ``xyz`` (job units) and rotation ``rpy_deg``.

    ``rpy_deg`` are roll, pitch, yaw about the fixed x, y, z axes (degrees), i.e.
    ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
    """

    xyz: tuple[float, float, float] = Field(default=(0.0, 0.0, 0.0), strict=False)
    rpy_deg: tuple[float, float, float] = Field(default=(0.0, 0.0, 0.0), strict=False)


class ScaleBar(_Strict):
    a: str
    b: str
    length: float = Field(gt=0, description="calibrated length between a and b, job units")
    sigma: float = Field(default=0.0, ge=0, description="its standard uncertainty, job units")
    cte_ppm_per_K: float | None = Field(
        default=None, ge=-5, le=100, description="the bar's own coefficient of thermal expansion (carbon fibre 0-1, "
                                                 "invar 1.2, steel 11.5): its certificate is at 20 C and [thermal] "
                                                 "bars_C gives its temperature; not given: the ends sit on the part "
                                                 "and expand with it (decision 0053)")
    cte_sigma_ppm_per_K: float | None = Field(
        default=None, ge=0, le=50, description="the standard uncertainty of cte_ppm_per_K (default 10 % of it, at "
                                               "least 0.1)")

    @model_validator(mode="after")
    def _two_targets(self):
        if self.a == self.b:
            raise ValueError(f"a scale bar joins two different targets; a = b = {self.a!r}")
        if self.sigma >= self.length:
            raise ValueError(f"the scale bar's sigma ({self.sigma}) must be below its length ({self.length})")
        return self


#: the longest job name (also the part's name): the archive index's column (``jobs.name``, ``jobs.part``)
NAME_MAX = 200


class JobSection(_Strict):
    name: str = Field(min_length=1, max_length=NAME_MAX, description="also the part's name; at most NAME_MAX "
                      "characters, the archive index's limit")
    mesh: str = Field(description="the part: STEP/IGES (its own units honoured) or a mesh (STL/OBJ/PLY/GLB, in `units`)")
    tessellation_tolerance: float | None = Field(
        default=None, gt=0, description="STEP/IGES: largest distance of the tessellation from the surface, job units "
                                        "(default 0.01 mm)")
    units: Literal["m", "mm", "cm", "um", "in", "ft"]
    targets: str | None = None
    n_targets: int | None = Field(default=None, ge=6, le=100_000,
                                  description="at least 6: an image is oriented from 6 or more targets")
    n_coded: int = Field(default=8, ge=0, le=250)
    target_diameter: float = Field(default=DEFAULT_DOT_DIAMETER_MM, gt=0,
                                   description="retro dot diameter, job units (default 6 mm)")
    target_thickness: float | None = Field(
        default=None, ge=0, description="how far each target's face stands above the CAD surface, job units (adhesive "
                                        "dots 0.1-0.3 mm, magnetic ones 1-2 mm; 0: flush). The cell measures the face's "
                                        "centre and compares it with the CAD point lifted along its normal by this; "
                                        "not given: 0, and said in the report of a real cell (decision 0049)")
    coded_size: float = Field(default=DEFAULT_CODED_SIZE_MM, gt=0, description="ArUco marker side, job units "
                                                                                "(default 20 mm)")
    coded_family: Literal["aruco", "ring12", "ring14", "schneider12", "schneider14", "cct8", "cct12"] = Field(
        default="aruco", description="the coded targets the part carries: ArUco DICT_4X4_250 markers, or ring codes "
                                     "(a centre dot of target_diameter in a coded ring; calibration.ringcodes)")
    seed: int = Field(default=0, ge=0, lt=2**63, description="random seed (a non-negative integer)")
    scale_bar: ScaleBar | None = Field(default=None, description="one scale bar (the same as scale_bars with one)")
    scale_bars: list[ScaleBar] | None = Field(
        default=None, min_length=1, description="several certified scale bars: every usable one enters the adjustment, "
                                                "their certificates are tested against each other (decision 0041)")
    number: str | None = Field(default=None, max_length=80, description="the part number (drawing), e.g. 'BR-1002'")
    revision: str | None = Field(default=None, max_length=40, description="the part's drawing revision")

    @model_validator(mode="after")
    def _physical_defaults(self):  # first: the checks below compare them
        fill_unit_defaults(self, self.units, {"target_diameter": DEFAULT_DOT_DIAMETER_MM,
                                              "coded_size": DEFAULT_CODED_SIZE_MM})
        return self

    @model_validator(mode="after")
    def _thin_targets(self):
        if self.target_thickness is not None and self.target_thickness >= self.target_diameter:
            raise ValueError(f"target_thickness ({self.target_thickness}) must be below target_diameter "
                             f"({self.target_diameter}): a target thicker than wide is a typo (units?)")
        return self

    @model_validator(mode="after")
    def _targets_or_count(self):
        if (self.targets is None) == (self.n_targets is None):
            raise ValueError("give exactly one of 'targets' (a CSV file) or 'n_targets' (a count to sample)")
        return self

    @model_validator(mode="after")
    def _one_bar_key(self):
        if self.scale_bar is not None and self.scale_bars is not None:
            raise ValueError("give either 'scale_bar' (one bar) or 'scale_bars' (a list of bars), not both")
        seen: dict[frozenset, str] = {}
        for key, bar in self.bars():
            pair = frozenset((bar.a, bar.b))
            if pair in seen:
                raise ValueError(f"{key} joins {bar.a} and {bar.b}, as {seen[pair]} does: one certificate per pair "
                                 "of targets")
            seen[pair] = key
        return self

    def bars(self) -> list[tuple[str, ScaleBar]]:
        """Every scale bar with the key that names it in messages (``job.scale_bar`` or ``job.scale_bars[i]``);
        two bars may share an end (their certificates are independent), not both."""
        if self.scale_bar is not None:
            return [("job.scale_bar", self.scale_bar)]
        return [(f"job.scale_bars[{i}]", b) for i, b in enumerate(self.scale_bars or [])]


class CameraSection(_Strict):
    width: int = Field(ge=64, le=100_000, description="pixels; a smaller sensor cannot measure targets")
    height: int = Field(ge=64, le=100_000)
    pixel_size_um: float = Field(gt=0, le=100)
    focal_length_mm: float = Field(gt=0, le=2000)
    cx_px: float | None = None
    cy_px: float | None = None
    k1: float = Field(default=0.0, ge=-10, le=10, description="radial distortion (normalised coordinates)")
    k2: float = Field(default=0.0, ge=-100, le=100)
    k3: float = Field(default=0.0, ge=-1000, le=1000)
    p1: float = Field(default=0.0, ge=-1, le=1, description="decentring distortion")
    p2: float = Field(default=0.0, ge=-1, le=1)
    sigma_px: float = Field(default=0.05, gt=0, le=10, description="image measurement standard deviation")
    near: float = Field(gt=0, description="depth of field, nearest sharp distance, job units")
    far: float = Field(gt=0, description="depth of field, farthest sharp distance, job units")
    device: str | None = Field(default=None, description="real cell: a GenICam camera's serial number / user id "
                               "(driver genicam), or an OpenCV device index or GStreamer pipeline (driver opencv)")
    driver: Literal["genicam", "opencv"] = Field(default="genicam", description="how `device` is opened")
    producer: str | None = Field(default=None, description="GenTL producer .cti (default: GENICAM_GENTL64_PATH)")
    pixel_format: str = Field(default="Mono8", description="GenICam pixel format (Mono8/10/12/16, Mono10p/12p ...)")
    gain_db: float | None = Field(default=None, ge=-40, le=60, description="GenICam Gain (dB); None: leave the camera's "
                                  "(the simulated cell: unit gain)")
    trigger: str = Field(default="software", description="GenICam frame trigger: software, off, or a line (Line1)")
    strobe_line: str | None = Field(default=None, description="GenICam output line that fires the light (Line2)")
    exposure_s: float = Field(default=0.002, gt=0, le=10)
    frame_timeout_s: float = Field(default=2.0, gt=0, le=600, description="longest time from trigger to frame beyond the "
                                   "exposure; a later frame faults the station and it is retaken")
    self_calibrate: bool = Field(default=True, description="refine the lens in the adjustment (lens_model's terms)")
    lens_model: Literal["brown", "radial"] = Field(
        default="brown", description="the terms of the lens the adjustment estimates: brown: fx, fy, cx, cy, radial k1, "
                                     "k2, k3 and decentring p1, p2 (a real lens; decision 0054); radial: one focal "
                                     "length, cx, cy, k1, k2 (a lens known to have no decentring)")
    polarity: Literal["bright", "dark", "auto"] = Field(
        default="bright", description="bright: retro-reflective dots; dark: printed dots on a light ground; auto: per image")
    detection: Literal["cell", "photograph"] = Field(
        default="cell", description="cell: fixed 41 px background kernel (the lit cell's images); photograph: kernel, "
                                    "size limits and local half-maximum threshold found per image (docs/decisions/0015)")
    background_mask: Literal["none", "cad"] = Field(
        default="none", description="cad: each dot's background plane is fitted only to pixels of its own surface, "
                                    "labelled from the CAD at the image's resected pose (a dot near an edge of the "
                                    "part; docs/decisions/0035); none: every pixel of the ring around the dot")
    dot_precision: Literal["model", "stated"] = Field(
        default="model", description="with observation_weights = 'model', where each dot's noise comes from: model: "
                                     "the detector model's sigma for every dot; stated: the detector's covariance of "
                                     "the dot's centre from the image's own measured noise, which follows the light "
                                     "and the sensor (a dot centred by its ellipse keeps the model; "
                                     "docs/decisions/0048)")
    observation_weights: Literal["model", "incidence", "equal"] = Field(
        default="model",
        description="model: each observation's a priori sigma from the detector precision model (incidence, dot "
                    "size in pixels; calibration/data/detector_precision.json), scaled by the adjustment's "
                    "variance factor; incidence: one image sigma per incidence class (< 50, 50-70, >= 70 deg) "
                    "estimated from sigma_px; equal: every observation has sigma_px")

    @model_validator(mode="after")
    def _dof(self):
        if self.far <= self.near:
            raise ValueError("camera.far must be greater than camera.near")
        if self.pixel_format not in BIT_DEPTH:
            raise ValueError(f"camera.pixel_format = {self.pixel_format!r} is not one the cell reads: "
                             f"{', '.join(BIT_DEPTH)}")
        for key, value, size in (("cx_px", self.cx_px, self.width), ("cy_px", self.cy_px, self.height)):
            if value is not None and not 0 <= value <= size - 1:
                raise ValueError(f"camera.{key} = {value} lies outside the image (0..{size - 1} px)")
        held = [k for k in ("k3", "p1", "p2") if getattr(self, k)]
        if self.lens_model == "radial" and self.self_calibrate and held:
            raise ValueError(f"camera.{held[0]} = {getattr(self, held[0])} is a term the radial lens model does not "
                             f"carry (k1, k2 only): the adjustment would drop it; set camera.lens_model = \"brown\"")
        return self


class Obstacle(_Strict):
    name: str
    size: tuple[float, float, float] = Field(strict=False)
    pose: Pose = Pose()

    @field_validator("size")
    @classmethod
    def _positive(cls, v):
        if min(v) <= 0:
            raise ValueError("obstacle size must be positive")
        return v


class CellSection(_Strict):
    robot: Literal["ur5e", "ur10e"] = "ur5e"
    backend: Literal["sim", "ur"] = "sim"
    host: str = "127.0.0.1"
    light_port: str | None = Field(default=None, description="the Gardasoft RT light controller (real cell): a "
                                   "serial port, or tcp://HOST[:PORT]")
    thermometer_port: str | None = Field(default=None, description="the part's thermometer readout (a Fluke/Hart 1521/"
                                         "1522 handheld readout, or a 1504, on RS-232, e.g. /dev/ttyUSB1) that [thermal] "
                                         "part_C = \"probe\" reads (real cell)")
    light_channel: int = Field(default=1, ge=1, le=8, description="the light's output channel on the controller")
    light_input: int | None = Field(default=None, ge=1, le=8, description="controller trigger input wired to the "
                                    "camera's strobe line; None: the light is fired by a software trigger")
    light_brightness_pct: float = Field(default=100.0, gt=0, le=1000, description="pulse brightness, % of rating")
    cell_file: str | None = Field(default=None, description="the cell's CELL.toml: the job measures with its calibrated "
                                  "hand-eye and lens, and its calibration status goes in the report (decision 0056)")
    base_from_part: Pose
    flange_from_cam: Pose | None = Field(default=None, description="the hand-eye; a job that names a cell_file takes "
                                         "the cell's (and may leave this out)")
    table_z: float = 0.0
    obstacles: list[Obstacle] = []
    camera_box: tuple[float, float, float] = Field(default=DEFAULT_CAMERA_BOX_MM, strict=False, description="the camera's "
                                                   "collision box, job units (default 80 x 80 x 120 mm)")
    max_joint_speed_rad_s: float = Field(default=1.0, gt=0, le=3.2)
    max_joint_accel_rad_s2: float = Field(default=1.5, gt=0, le=40)
    max_tcp_speed_m_s: float = Field(default=0.25, gt=0, le=1.0)
    max_tcp_accel_m_s2: float = Field(default=1.0, gt=0, le=10)
    settle_s: float = Field(default=0.2, ge=0, le=60, description="the arm counts as settled when every joint has been "
                            "slower than settle_speed_rad_s for this long (controller clock)")
    settle_speed_rad_s: float = Field(default=0.002, gt=0, le=1)
    settle_timeout_s: float = Field(default=10.0, gt=0, le=600)
    retakes: int = Field(default=2, ge=0, le=10, description="retakes of a station whose frame came late, twice "
                         "or never, before the job faults")
    workspace_min: tuple[float, float, float] | None = Field(default=None, strict=False,
                                                            description="flange box, base frame, job units")
    workspace_max: tuple[float, float, float] | None = Field(default=None, strict=False,
                                                            description="default: the robot's reach")
    elbow_limit_deg: float = Field(default=180.0, gt=0, le=360)

    @field_validator("camera_box")
    @classmethod
    def _box_positive(cls, v):
        if min(v) <= 0:
            raise ValueError("camera_box sides must be positive")
        return v

    @model_validator(mode="after")
    def _workspace(self):
        lo, hi = self.workspace_min, self.workspace_max
        if lo is not None and hi is not None:
            bad = [axis for axis, a, b in zip("xyz", lo, hi) if a >= b]
            if bad:
                raise ValueError(f"cell.workspace_min must be below cell.workspace_max on every axis; "
                                 f"it is not on {', '.join(bad)} ({list(lo)} vs {list(hi)})")
        if lo is not None and hi is None or hi is not None and lo is None:
            raise ValueError("give both cell.workspace_min and cell.workspace_max, or neither")
        return self


class PlanningSection(_Strict):
    mode: Literal["fixed", "cheapest"] = "fixed"
    n_stations: int = Field(default=16, ge=2, le=200)
    max_stations: int = Field(default=40, ge=2, le=200)
    required_sigma: float | None = Field(default=None, gt=0, description="job units; default tolerance/10")
    min_rays: int = Field(default=3, ge=2)
    incidence_max_deg: float = Field(default=60.0, gt=0, lt=90)
    criterion: Literal["worst", "mean", "max_axis", "trace"] = "worst"
    distance_min: float | None = Field(default=None, gt=0, description="job units; default from the camera")
    distance_max: float | None = Field(default=None, gt=0)
    elevation_min_deg: float = Field(default=15.0, ge=-90, le=90)
    elevation_max_deg: float = Field(default=85.0, ge=-90, le=90)
    n_candidates: int = Field(default=2000, ge=50, le=50_000)
    population: int = Field(default=80, ge=4, le=10_000)
    generations: int = Field(default=150, ge=1, le=100_000)
    margin_px: float = Field(default=30.0, ge=0, le=10_000)
    lower_bound: bool = Field(default=False, description="also bound how good any network could be (planning.bound)")
    search_weights: Literal["sigma", "model"] | None = Field(
        default=None, description="how the network search weighs each ray: sigma: [camera] sigma_px for every ray; "
                                  "model: the detector model's sigma of that ray (incidence, dot size; needs "
                                  "[camera] observation_weights = 'model'); default: sigma (docs/decisions/0031 "
                                  "says why)")
    unmeasurable: Literal["fault", "report"] = Field(
        default="fault", description="a target fewer than min_rays reachable stations can see: fault: refuse the job "
                                     "before planning; report: plan for the others, measure it if the images happen "
                                     "to, and report it not measured (verdict INCOMPLETE)")
    closed_loop: bool | None = Field(default=None, description="after ADJUST, add stations for targets that miss their "
                                     "required sigma (default: on when a requirement is set: required_sigma or "
                                     "mode = 'cheapest')")
    closed_loop_rounds: int = Field(default=2, ge=1, le=10, description="closed loop: at most this many rounds")
    closed_loop_max_stations: int = Field(default=8, ge=1, le=100, description="closed loop: extra stations per round")

    def closed_loop_on(self) -> bool:
        """Whether the CLOSE_LOOP stage adds stations (explicit, or on when a requirement is set)."""
        if self.closed_loop is not None:
            return self.closed_loop
        return self.required_sigma is not None or self.mode == "cheapest"

    @model_validator(mode="after")
    def _intervals(self):
        if self.elevation_min_deg >= self.elevation_max_deg:
            raise ValueError(f"planning.elevation_min_deg ({self.elevation_min_deg}) must be below "
                             f"planning.elevation_max_deg ({self.elevation_max_deg})")
        if self.distance_min is not None and self.distance_max is not None and self.distance_min >= self.distance_max:
            raise ValueError(f"planning.distance_min ({self.distance_min}) must be below "
                             f"planning.distance_max ({self.distance_max})")
        if self.min_rays > (self.max_stations if self.mode == "cheapest" else self.n_stations):
            raise ValueError(f"planning.min_rays ({self.min_rays}) exceeds the number of stations")
        return self


class ReportSection(_Strict):
    tolerance: float = Field(gt=0, description="default tolerance on a target's deviation, job units")
    sigma_factor: float = Field(default=3.0, gt=0, le=100, description="deviation significant beyond k sigma")


#: the fewest targets a rigid best fit takes (calibration.robust_alignment): three points not on one line
MIN_FIT_TARGETS = 3


class AlignmentSection(_Strict):
    """How the measured targets are brought into the part frame (the report's deviations are in it)."""

    method: Literal["best_fit", "rps", "bundle_frame"] = Field(
        default="best_fit",
        description="best_fit: rigid fit to CAD over the targets that agree with it (robust); rps: 3-2-1 on the "
                    "datum targets of 'rps'; bundle_frame: the measurement's own frame (a fixtured part whose "
                    "datum is the fixture's control points)")
    targets: list[str] | None = Field(default=None, description="best_fit: only these targets may define the frame")
    rps: dict[str, str] | None = Field(
        default=None, description="rps: datum target id -> the part axes it locks, e.g. "
                                  "{ T0001 = \"z\", T0002 = \"z\", T0003 = \"z\", T0004 = \"x\", T0005 = \"x\", T0006 = \"y\" }")
    on_untrusted: Literal["flag", "fault"] = Field(
        default="flag", description="an alignment that cannot be trusted: flag (report marked 'alignment not "
                                    "trusted' in red, verdict UNTRUSTED) or fault the job")

    @field_validator("targets")
    @classmethod
    def _enough_to_fit(cls, v):
        if v is None:
            return v
        twice = sorted({t for t in v if v.count(t) > 1})
        if twice:
            raise ValueError(f"names {twice[0]!r} twice")
        if len(v) < MIN_FIT_TARGETS:
            raise ValueError(f"names {len(v)} target(s) ({', '.join(v) or 'none'}); a best fit needs at least "
                             f"{MIN_FIT_TARGETS}, not on one line, to fix the part's frame (leave 'targets' out to fit "
                             "over every target)")
        return v

    @model_validator(mode="after")
    def _rps_needs_datum(self):
        if self.method == "rps" and not self.rps:
            raise ValueError("method 'rps' needs 'rps' = { target = \"axes\", ... } (six locked axes for 3-2-1)")
        if self.rps and sum(len(a) for a in self.rps.values()) < 6:
            raise ValueError(f"'rps' locks {sum(len(a) for a in self.rps.values())} axes; a 3-2-1 alignment locks 6 "
                             "(3 targets along the primary axis, 2 along the secondary, 1 along the tertiary)")
        if self.method != "rps" and self.rps:
            raise ValueError(f"'rps' is given but method is {self.method!r}: set method = \"rps\"")
        if self.targets is not None and self.method != "best_fit":
            raise ValueError("'targets' chooses the targets of a best fit: set method = \"best_fit\"")
        return self


class SimLens(_Strict):
    """The simulated camera's true lens where it is not the nominal one of ``[camera]`` (``[sim] lens``): a real lens
    is never its data sheet. Each key given replaces the nominal value for the renderer only; PLAN and the adjustment's
    start know the nominal lens."""

    principal_distance_factor: float = Field(default=1.0, ge=0.8, le=1.25, description="the true principal distance "
                                             "over [camera] focal_length_mm (a lens focused at d: 1 + f / (d - f))")
    principal_point_offset_px: tuple[float, float] = Field(default=(0.0, 0.0), strict=False, description="the true principal "
                                                           "point minus the nominal one (px)")
    aspect: float = Field(default=1.0, ge=0.9, le=1.1, description="fy / fx of the true lens (a sensor's pixel "
                          "aspect, an affinity)")
    k1: float | None = Field(default=None, ge=-10, le=10, description="true radial distortion")
    k2: float | None = Field(default=None, ge=-100, le=100)
    k3: float | None = Field(default=None, ge=-1000, le=1000)
    p1: float | None = Field(default=None, ge=-1, le=1, description="true decentring distortion")
    p2: float | None = Field(default=None, ge=-1, le=1)


class DamagedTarget(_Strict):
    """One plain dot of the simulated part whose retro-reflective coating is damaged (``[sim] damaged_targets``)."""

    id: str = Field(min_length=1, description="the dot's target id: a plain retro-reflective dot of the part (coded "
                    "targets are not damaged)")
    kind: Literal["edge", "spot"] = Field(description="edge: the coating is gone beyond a chord (a chipped rim); "
                                          "spot: a dark round speck (dirt) sits inside the dot")
    lost: float = Field(description="the share of the dot's area that no longer reflects, 0 < lost <= 0.5 (edge: the "
                        "circular segment beyond the chord; spot: the speck, of radius sqrt(lost) dot radii)")
    direction_deg: float = Field(default=0.0, ge=-360, le=360, description="in-plane direction from the dot's centre "
                                 "to the lost side (edge) or to the speck's centre (spot), degrees from the target's "
                                 "first in-plane axis e1 towards e2 (sim_backend.world.marker_axes)")
    offset: float = Field(default=0.0, ge=0, lt=1, description="spot: the speck's centre from the dot's, in dot radii; "
                          "the speck lies inside the dot: offset + sqrt(lost) <= 0.95 (edge: not used)")

    @field_validator("lost")
    @classmethod
    def _share(cls, v):
        if not 0 < v <= 0.5:
            raise ValueError("the share of the dot's area that lost its coating must be 0 < lost <= 0.5")
        return v

    @model_validator(mode="after")
    def _spot_inside(self):
        if self.kind == "edge" and self.offset != 0:
            raise ValueError(f"offset = {self.offset} places a spot; an edge's chord is set by lost and direction_deg "
                             "alone: remove offset")
        reach = self.offset + math.sqrt(self.lost)
        if self.kind == "spot" and reach > 0.95 + 1e-12:
            raise ValueError(f"the spot of {self.id} (lost = {self.lost}: radius {math.sqrt(self.lost):.3f} dot radii, "
                             f"offset = {self.offset}) reaches {reach:.3f} dot radii from the centre: it must lie "
                             "inside the dot (offset + sqrt(lost) <= 0.95)")
        return self


class ThermalSection(_Strict):
    """The temperatures of the measurement (decision 0053): coordinates and deviations are reported at the ISO 1
    reference of 20 C. Without the section they are at whatever temperature the part had, and said."""

    part_C: float | Literal["probe"] = Field(description="the part's temperature during the measurement, deg C (a "
                                             "contact probe on the part, soaked), or \"probe\": read from the "
                                             "thermometer ([cell] thermometer_port; the simulated cell's own) at "
                                             "the start and the end of ACQUIRE")
    part_sigma_K: float = Field(default=0.5, gt=0, le=20, description="its standard uncertainty, K")
    part_cte_ppm_per_K: float = Field(ge=-5, le=100, description="the part's coefficient of thermal expansion, "
                                                                 "ppm/K (aluminium 23.1, steel 11.5, titanium 8.6)")
    part_cte_sigma_ppm_per_K: float | None = Field(default=None, ge=0, le=50, description="its standard uncertainty "
                                                   "(default 10 % of it, at least 0.1)")
    bars_C: float | None = Field(default=None, ge=-30, le=90, description="the temperature of the scale bars that have "
                                 "their own cte_ppm_per_K, deg C (default: part_C)")
    bars_sigma_K: float = Field(default=0.5, gt=0, le=20, description="its standard uncertainty, K")


    @field_validator("part_C")
    @classmethod
    def _plausible_part(cls, v):
        if v != "probe" and not -30 <= v <= 90:
            raise ValueError(f"part_C = {v} deg C is no part in a measuring cell (-30..90); or \"probe\"")
        return v


class SimSection(_Strict):
    image_sigma_px: float = Field(default=0.0, ge=0, le=10, description="an extra random offset per dot (pixels) on top of "
                                  "the rendered photon/read noise, blur and quantisation; 0 = physical")
    seed: int = Field(default=0, ge=0, lt=2**63, description="random seed (a non-negative integer)")
    deviations: str | None = Field(default=None, description="CSV id,dx,dy,dz in job units")
    motion: Literal["instant", "timed"] = "instant"
    time_scale: float = Field(default=1.0, gt=0, le=1000)
    noise: float = Field(default=1.0, ge=0, le=100, description="sensor noise scale (1 = nominal)")
    circle_of_confusion_px: float = Field(default=2.0, ge=0, le=20, description="the simulated lens's blur circle at "
                                          "the job's [camera] near and far (px): a thin lens focused between them "
                                          "defocuses each dot by its depth; 0: every depth as sharp (decision 0049)")
    light: bool = Field(default=False, description="the sim cell's light: the Gardasoft RT driver on its emulator")
    base_from_part_error: Pose | None = Field(default=None, description="true placement minus nominal (tests)")
    flange_from_cam_error: Pose | None = None
    base_from_part_true: Pose | None = Field(default=None, description="absolute true placement (wins over _error); "
                                             "stays put when `cell locate --write` updates [cell] base_from_part")
    dot_max_incidence_deg: float | None = Field(default=None, gt=0, le=90, description="glare: dots seen beyond this "
                                                "incidence are washed out in the simulated images (the plan does not know)")
    target_thickness: float | None = Field(default=None, ge=0, description="the simulated targets' true thickness, job "
                                           "units, where it is not what [job] target_thickness says (a job that "
                                           "mis-states it; default: as the job says)")
    fixture: list[Obstacle] = Field(default=[], description="boxes in the part frame (job units) that hide dots in the "
                                    "simulated images but are not in the part's CAD (the plan does not know them)")
    unreachable_stations: list[str] = Field(default=[], description="planned station ids whose move the simulated "
                                            "controller refuses at run time (the plan does not know): ACQUIRE "
                                            "skips them, the closed loop makes up for them")
    part_C: float | None = Field(default=None, ge=-30, le=90, description="the simulated part's true temperature, "
                                 "deg C: its targets expand about the part origin by part_cte_ppm_per_K from their "
                                 "20 C places (default: [thermal] part_C, else 20: as CAD)")
    part_cte_ppm_per_K: float | None = Field(default=None, ge=-5, le=100, description="the simulated part's true "
                                             "expansion coefficient (default: [thermal] part_cte_ppm_per_K)")
    bars_C: float | None = Field(default=None, ge=-30, le=90, description="the true temperature of the scale bars "
                                 "with their own cte_ppm_per_K: their ends expand about the bar's middle (default: "
                                 "[thermal] bars_C if given, else the simulated part_C)")
    lens: SimLens | None = Field(default=None, description="the simulated camera's true lens where it differs from "
                                 "the nominal [camera] (principal_distance_factor, principal_point_offset_px, aspect, k1, "
                                 "k2, k3, p1, p2): "
                                 "the renderer uses it, the plan and the adjustment's start do not know it")
    damaged_targets: list[DamagedTarget] = Field(
        default=[], description="plain dots whose retro-reflective coating is worn in the simulated images (the plan "
                                "does not know): { id, kind = \"edge\" | \"spot\", lost, direction_deg, offset } each, "
                                "the lost part showing the target's black backing (ids checked against the part at "
                                "LOAD)")

    @model_validator(mode="after")
    def _one_damage_per_dot(self):
        seen: dict[str, int] = {}
        for i, d in enumerate(self.damaged_targets):
            if d.id in seen:
                raise ValueError(f"sim.damaged_targets[{i}].id = {d.id!r} is damaged already by "
                                 f"sim.damaged_targets[{seen[d.id]}]: one damage per dot")
            seen[d.id] = i
        return self


class JobSpec(_Strict):
    """A whole job file, validated. Use :func:`load_job` to read one."""

    job: JobSection
    camera: CameraSection
    cell: CellSection
    planning: PlanningSection = PlanningSection()
    report: ReportSection
    alignment: AlignmentSection = AlignmentSection()
    thermal: ThermalSection | None = None
    sim: SimSection = SimSection()

    @model_validator(mode="after")
    def _physical_defaults(self):  # first: the length checks below see them
        fill_unit_defaults(self.cell, self.job.units, {"camera_box": DEFAULT_CAMERA_BOX_MM})
        return self

    @model_validator(mode="after")
    def _unreachable_stations_planned(self):
        """``[sim] unreachable_stations`` must name stations a plan of this job can have: ``S001``.. (the planner's,
        with those added for the scale bars) and ``L<round>-<k>`` (the closed loop's); another id refuses nothing."""
        ids = self.sim.unreachable_stations
        if not ids:
            return self
        from planning.scalebar import MAX_BAR_STATIONS

        p = self.planning
        n_s = (p.max_stations if p.mode == "cheapest" else p.n_stations) + MAX_BAR_STATIONS * len(self.job.bars())
        rounds, per_round = p.closed_loop_rounds, p.closed_loop_max_stations
        for sid in ids:
            if ids.count(sid) > 1:
                raise ValueError(f"sim.unreachable_stations names {sid!r} twice")
            planned = re.fullmatch(r"S(\d{3,})", sid)
            loop = re.fullmatch(r"L(\d+)-(\d{2,})", sid)
            if not (planned and 1 <= int(planned[1]) <= n_s
                    or loop and 1 <= int(loop[1]) <= rounds and 1 <= int(loop[2]) <= per_round):
                raise ValueError(f"sim.unreachable_stations names {sid!r}, a station no plan of this job has: planned "
                                 f"ones are S001..S{n_s:03d}, the closed loop's L1-01..L{rounds}-{per_round:02d}")
        return self

    @model_validator(mode="after")
    def _thermal_needs(self):
        if self.thermal is not None and not self.job.bars():
            raise ValueError("[thermal] brings the measurement to 20 C through the scale bars' certificates: the job "
                             "has no scale bar ([job] scale_bar or scale_bars)")
        if self.thermal is not None and self.thermal.part_C == "probe" and self.cell.backend == "ur" \
                and not self.cell.thermometer_port:
            raise ValueError("[thermal] part_C = \"probe\" reads the part's thermometer: give [cell] thermometer_port "
                             "(its serial port), or the temperature in deg C")
        s = self.sim
        if s.part_C is not None and s.part_cte_ppm_per_K is None and self.thermal is None:
            raise ValueError("sim.part_C expands the simulated part: give sim.part_cte_ppm_per_K (or [thermal] "
                             "part_cte_ppm_per_K)")
        return self

    @model_validator(mode="after")
    def _hand_eye_stated(self):
        if self.cell.flange_from_cam is None and self.cell.cell_file is None:
            raise ValueError("cell.flange_from_cam: give the hand-eye, or name the cell file whose calibrated hand-eye "
                             "the job measures with (cell.cell_file)")
        return self

    @model_validator(mode="after")
    def _same_weights(self):
        if self.planning.search_weights == "model" and self.camera.observation_weights != "model":
            raise ValueError("planning.search_weights = 'model' needs camera.observation_weights = 'model' (the search "
                             f"must weigh rays as the bundle does; it is {self.camera.observation_weights!r})")
        return self

    @model_validator(mode="after")
    def _plausible_lengths(self):
        """Every length in job units, converted to metres, within MAX_LENGTH_M (1e300 mm is a typo, not a cell)."""
        k = UNITS_TO_M[self.job.units]
        c = self.cell
        lengths = {"job.target_diameter": [self.job.target_diameter], "job.coded_size": [self.job.coded_size],
                   "job.target_thickness": [self.job.target_thickness or 0.0],
                   "sim.target_thickness": [self.sim.target_thickness or 0.0],
                   "camera.near": [self.camera.near], "camera.far": [self.camera.far],
                   "cell.base_from_part.xyz": c.base_from_part.xyz, "cell.flange_from_cam.xyz": c.flange_from_cam.xyz if c.flange_from_cam else (),
                   "cell.table_z": [c.table_z], "cell.camera_box": c.camera_box,
                   "cell.workspace_min": c.workspace_min or (), "cell.workspace_max": c.workspace_max or (),
                   "report.tolerance": [self.report.tolerance],
                   "planning.distance_min": [self.planning.distance_min or 0.0],
                   "planning.distance_max": [self.planning.distance_max or 0.0],
                   "planning.required_sigma": [self.planning.required_sigma or 0.0]}
        for i, ob in enumerate(c.obstacles):
            lengths[f"cell.obstacles[{i}].size"] = ob.size
            lengths[f"cell.obstacles[{i}].pose.xyz"] = ob.pose.xyz
        for key, bar in self.job.bars():
            lengths[f"{key}.length"] = [bar.length]
        for key, values in lengths.items():
            big = [v for v in values if abs(v) * k > MAX_LENGTH_M]
            if big:
                raise ValueError(f"{key} = {big[0]} {self.job.units} is {abs(big[0]) * k:.3g} m: beyond any cell "
                                 f"({MAX_LENGTH_M:g} m); are the units right?")
        return self

    # --- derived values, in SI ---
    @property
    def scale(self) -> float:
        """Job units -> metres."""
        return UNITS_TO_M[self.job.units]

    def intrinsics(self) -> Intrinsics:
        c = self.camera
        return Intrinsics.from_focal_length(
            c.focal_length_mm * 1e-3, c.pixel_size_um * 1e-6, c.width, c.height,
            cx_px=c.cx_px, cy_px=c.cy_px, k1=c.k1, k2=c.k2, k3=c.k3, p1=c.p1, p2=c.p2,
        )

    def true_intrinsics(self) -> Intrinsics:
        """The simulated camera's lens: the nominal one with ``[sim] lens``'s keys in place of its own."""
        c, t = self.camera, self.sim.lens
        if t is None:
            return self.intrinsics()
        nominal = self.intrinsics()
        pick = lambda k: getattr(c, k) if getattr(t, k) is None else getattr(t, k)  # noqa: E731
        return Intrinsics.from_focal_length(
            c.focal_length_mm * t.principal_distance_factor * 1e-3, c.pixel_size_um * 1e-6, c.width, c.height,
            cx_px=nominal.cx_px + t.principal_point_offset_px[0], cy_px=nominal.cy_px + t.principal_point_offset_px[1],
            aspect=t.aspect, k1=pick("k1"), k2=pick("k2"), k3=pick("k3"), p1=pick("p1"), p2=pick("p2"))

    def base_from_part(self) -> np.ndarray:
        return pose_matrix(self.cell.base_from_part, self.scale)

    def flange_from_cam(self) -> np.ndarray:
        return pose_matrix(self.cell.flange_from_cam, self.scale)


def pose_matrix(pose: Pose, scale: float) -> np.ndarray:
    """4x4 transform of a :class:`Pose` with its translation scaled to metres."""
    R = Rotation.from_euler("xyz", pose.rpy_deg, degrees=True).as_matrix()
    return make_pose(R, np.asarray(pose.xyz) * scale)


def _format_validation_error(path: Path, err: ValidationError) -> str:
    e = err.errors()[0]
    loc = "".join(f"[{x}]" if isinstance(x, int) else f".{x}" for x in e["loc"]).lstrip(".")
    kind = e["type"]
    if not loc:  # a check across sections: its message names the keys
        return f"{path}: {e['msg'].removeprefix('Value error, ')}"
    if kind == "extra_forbidden":
        return f"{path}: unknown key '{loc}'"
    if kind == "missing":
        return f"{path}: missing required key '{loc}'"
    if kind == "literal_error":
        return f"{path}: '{loc}' = {e.get('input')!r}: {e['msg']}"
    msg = e["msg"].removeprefix("Value error, ")
    if kind in ("int_type", "float_type", "bool_type") and isinstance(e.get("input"), (str, int, float)):
        msg += {"int_type": " (a whole number, unquoted)", "float_type": " (a number, unquoted)",
                "bool_type": " (true or false, unquoted)"}[kind]
    if "input" in e and not isinstance(e["input"], dict):
        return f"{path}: '{loc}' = {e['input']!r}: {msg}"
    return f"{path}: '{loc}': {msg}"


def load_job(path: str | Path, overrides: dict[str, str] | None = None) -> tuple[JobSpec, Path]:
    """Read and validate a job file. Returns ``(spec, folder)`` where relative paths resolve.

    ``overrides`` maps ``"section.key"`` to a replacement file path (an archived job points its mesh, targets,
    deviations and cell file at its own copies). A job that names a cell file takes the cell's hand-eye
    (:func:`cell.cellcal.jobcell.take_cell_file`).

    Raises:
        JobSpecError: one line naming the file and the problem.
    """
    spec = read_job(path)
    for key, value in (overrides or {}).items():
        section, name = key.split(".")
        sub = getattr(spec, section).model_copy(update={name: value})
        spec = spec.model_copy(update={section: sub})
    if spec.cell.cell_file is not None:  # the cell's calibrated hand-eye, checked against the job's (decision 0056)
        from cell.cellcal.jobcell import take_cell_file

        spec = take_cell_file(spec, Path(path))
    return spec, Path(path).resolve().parent


def read_job(path: str | Path) -> JobSpec:
    """The job file, validated as it is written (:func:`load_job` is what a job runs with)."""
    path = Path(path)
    if not path.is_file():
        raise JobSpecError(f"{path}: job file not found")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8-sig"))  # a BOM (Windows editors) is not TOML: dropped
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise JobSpecError(f"{path}: not valid TOML ({exc})") from None
    try:
        spec = JobSpec.model_validate(data)
    except ValidationError as err:
        raise JobSpecError(_format_validation_error(path, err)) from None
    check_backend(spec, spec.cell.backend, path)
    return spec  # scale-bar ids are checked at LOAD, once the targets are known


def is_loopback_host(host: str) -> bool:
    """``host`` is a loopback IP address (127.x.x.x, ::1): where the loopback UR controller runs
    (``sim_backend.ur_controller`` binds only those), and where no real UR controller, a box of its own, can be."""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_backend(spec: JobSpec, backend: str, path: str | Path) -> None:
    """Refuse what only a simulated device can do when the job drives a real robot; ``backend`` is the one that
    will run (the job file's, or ``cell run --backend``'s). ``JobSpecError``, one line, before anything is written.

    ``[sim] unreachable_stations`` makes the controller refuse stations: the simulated robot does, and so does the
    loopback UR controller (tests drive the real ur-rtde client against it with ``backend = "ur"``), told over an
    emulator-only dashboard command. A real UR cannot be told; before, that surfaced only at ACQUIRE.
    """
    s = spec.sim
    if backend == "ur" and s.unreachable_stations and not is_loopback_host(spec.cell.host):
        raise JobSpecError(
            f"{path}: [sim] unreachable_stations = {list(s.unreachable_stations)} is a simulation device (the "
            f"simulated robot or the loopback UR controller refuses those stations), but the robot is the UR at "
            f"[cell] host = {spec.cell.host!r}, which is not the loopback controller (a 127.x.x.x or ::1 address) and "
            "cannot be told to refuse them: remove [sim] unreachable_stations for a real robot")


def resolve(folder: Path, rel: str) -> Path:
    p = Path(rel)
    return p if p.is_absolute() else folder / p


def damaged_target_rows(spec: JobSpec, ids: list[str], kinds,
                        path: str | Path) -> tuple[tuple[int, DamagedTarget], ...]:
    """``[sim] damaged_targets`` with each dot's index among ``ids`` (the part's targets, of ``kinds``
    ``"retro"``/``"coded"``); ``JobSpecError`` naming the key and the id for an unknown or a coded target."""
    index = {t: i for i, t in enumerate(ids)}
    rows = []
    for i, d in enumerate(spec.sim.damaged_targets):
        key = f"sim.damaged_targets[{i}].id"
        if d.id not in index:
            raise JobSpecError(f"{path}: {key} = {d.id!r} names a target the part does not have")
        if str(kinds[index[d.id]]) == "coded":
            raise JobSpecError(f"{path}: {key} = {d.id!r} is a coded target; only plain retro-reflective dots are "
                               "rendered damaged")
        rows.append((index[d.id], d))
    return tuple(rows)
