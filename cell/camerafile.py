"""CAMERA.toml: a camera for measuring existing photographs (``cell detect``, ``cell measure``,
``cell calibrate camera``).

One ``[camera]`` table, every key optional (unknown keys are an error)::

    [camera]
    polarity = "auto"            # "auto" | "bright" (retro-reflective) | "dark" (printed dots)
    coded_family = "schneider14" # ring-code family of the coded targets (calibration.ringcodes), or "aruco"
    target_diameter_px = 0       # 0: found per image
    fx_px = 3480.2               # a calibrated camera: focal length in pixels (wins over focal_length_mm)
    fy_px = 3480.9
    focal_length_mm = 12.0       # else the photographs' EXIF focal length
    pixel_size_um = 3.45         # else from the EXIF focal-plane resolution (sensor size)
    width = 2448                 # else the first image's size
    height = 2048
    cx_px = 1223.5               # default: the image centre
    cy_px = 1023.5
    k1 = 0.0                     # Brown radial k1, k2, k3 and tangential p1, p2 (OpenCV's model)
    sigma_px = 0.1               # a priori image sigma for the bundle
    self_calibrate = true        # estimate focal length, principal point and distortion in the bundle
    radial = 3                   # radial terms estimated: 2 (k1, k2) or 3 (k1, k2, k3: bundle model OPENCV_K3)

Every problem is an ``InputError`` naming the file and the key.
"""
from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from calibration.errors import InputError

__all__ = ["CameraFile", "load_camera_file", "camera_toml", "CODED_FAMILIES"]

CODED_FAMILIES = ("aruco", "ring12", "ring14", "schneider12", "schneider14", "cct8", "cct12")


#: a focal length in pixels: at most this (a 2000 mm lens on 2 um pixels), and at least the image's width over
#: :data:`MIN_FX_OVER_WIDTH`'s inverse (a field of view beyond 157 deg is no lens the model describes)
MAX_FX_PX = 1e6
MIN_FX_OVER_WIDTH = 0.1
#: fy / fx of a sensor's pixels (as a job's [sim] lens aspect)
ASPECT_RANGE = (0.9, 1.1)


class CameraFile(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, strict=True)  # "1" is no number

    polarity: Literal["auto", "bright", "dark"] = "auto"
    coded_family: Literal["aruco", "ring12", "ring14", "schneider12", "schneider14", "cct8", "cct12"] = "schneider14"
    fx_px: float | None = Field(default=None, gt=0, le=MAX_FX_PX)
    fy_px: float | None = Field(default=None, gt=0, le=MAX_FX_PX)
    focal_length_mm: float | None = Field(default=None, gt=0, le=2000)
    pixel_size_um: float | None = Field(default=None, gt=0, le=100)
    width: int | None = Field(default=None, gt=0, le=100_000)
    height: int | None = Field(default=None, gt=0, le=100_000)
    cx_px: float | None = Field(default=None, ge=0, le=100_000)
    cy_px: float | None = Field(default=None, ge=0, le=100_000)
    k1: float = Field(default=0.0, ge=-10, le=10)  # the ranges of a job file's [camera]
    k2: float = Field(default=0.0, ge=-100, le=100)
    k3: float = Field(default=0.0, ge=-1000, le=1000)
    p1: float = Field(default=0.0, ge=-1, le=1)
    p2: float = Field(default=0.0, ge=-1, le=1)
    sigma_px: float = Field(default=0.1, gt=0, le=10)
    self_calibrate: bool = True
    radial: Literal[2, 3] = 3

    @model_validator(mode="after")
    def _plausible_lens(self):
        for key, value, size in (("cx_px", self.cx_px, self.width), ("cy_px", self.cy_px, self.height)):
            if value is not None and size is not None and not value <= size - 1:
                raise ValueError(f"{key} = {value} lies outside the image (0..{size - 1} px)")
        if self.fx_px is not None and self.width is not None and self.fx_px < MIN_FX_OVER_WIDTH * self.width:
            raise ValueError(f"fx_px = {self.fx_px} is below a tenth of the image's width ({self.width} px): a field of "
                             "view no lens of this model has; is it in mm?")
        if self.fx_px is not None and self.fy_px is not None \
                and not ASPECT_RANGE[0] <= self.fy_px / self.fx_px <= ASPECT_RANGE[1]:
            raise ValueError(f"fy_px / fx_px = {self.fy_px / self.fx_px:.4g}, outside {ASPECT_RANGE[0]}..{ASPECT_RANGE[1]}: "
                             "a sensor's pixels are square to within a few per cent")
        return self


def load_camera_file(path: str | Path | None) -> CameraFile:
    """The ``[camera]`` table of ``path`` (all defaults when ``path`` is None)."""
    if path is None:
        return CameraFile()
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise InputError(f"{path}: camera file not found") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise InputError(f"{path}: not a readable TOML file ({e})") from None
    extra = set(doc) - {"camera"}
    if extra:
        raise InputError(f"{path}: unknown table(s) {sorted(extra)}; a camera file has one [camera] table")
    try:
        return CameraFile(**doc.get("camera", {}))
    except ValidationError as e:
        err = e.errors()[0]
        key = ".".join(str(x) for x in err["loc"])
        msg = err["msg"].removeprefix("Value error, ")
        raise InputError(f"{path}: [camera] {key + ': ' if key else ''}{msg}") from None


def camera_toml(cam: CameraFile, comments: dict[str, str] | None = None) -> str:
    """``cam`` as a CAMERA.toml text (keys that are set), with an optional trailing comment per key."""
    comments = comments or {}
    lines = ["[camera]"]
    for key, value in cam.model_dump().items():
        if value is None:
            continue
        if isinstance(value, str):
            v = f'"{value}"'
        elif isinstance(value, bool):
            v = "true" if value else "false"
        else:
            v = repr(int(value)) if isinstance(value, int) else repr(float(value))
        lines.append(f"{key} = {v}" + (f"  # {comments[key]}" if key in comments else ""))
    return "\n".join(lines) + "\n"
