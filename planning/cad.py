"""CAD parts in STEP (and IGES) through trimesh's STEP path: OpenCASCADE, packaged as ``cascadio``,
tessellates the B-rep into a GLB that trimesh reads.

Units: a STEP file declares its length unit (``SI_UNIT(.MILLI.,.METRE.)``, ``CONVERSION_BASED_UNIT
('INCH', ...)``), an IGES file its unit flag (global parameter 14); OpenCASCADE converts from it, so
the part comes out in true size whatever the job's ``units`` (those still apply to the targets file
and every other length of the job). Measured here: a 100 mm box in a STEP file declared in mm, in
inches (as 100 in) and in metres (as 100 m) comes out 0.1 m, 2.54 m and 100 m across (the STEP path
writes metres); a 100 x 50 patch in IGES declared in mm and in inches comes out 100 x 50 and
2540 x 1270 millimetres (the IGES path writes OpenCASCADE's millimetres, scaled here to metres).

Tessellation: cascadio's linear deflection is in millimetres (OpenCASCADE's working unit, whatever
the file's unit); the chord of a 50 mm radius cylinder then deviates from the surface by at most
about half the tolerance (measured: 0.0050 / 0.049 / 0.47 mm for 0.01 / 0.1 / 1 mm). The job gives
``tessellation_tolerance`` in its own units; this module takes metres.

A file that is not STEP, is cut off, holds no geometry, or that OpenCASCADE cannot read is a
``PartError`` naming the file and the problem, never an empty mesh.
"""
from __future__ import annotations

import contextlib
import io
import os
import re
import sys
from pathlib import Path

import numpy as np
import trimesh

from calibration.errors import PartError

STEP_SUFFIXES = (".step", ".stp")
IGES_SUFFIXES = (".iges", ".igs")
#: default linear deflection of the tessellation, metres
DEFAULT_TOLERANCE_M = 1e-5
#: angular deflection, radians (cascadio's default)
ANGULAR_TOLERANCE_RAD = 0.5

_PREFIX = {None: 1.0, "MILLI": 1e-3, "CENTI": 1e-2, "DECI": 1e-1, "MICRO": 1e-6, "KILO": 1e3}


def step_length_unit(text: str) -> tuple[str, float] | None:
    """The length unit a STEP file declares: (name, metres per unit), or None if none is found."""
    m = re.search(r"CONVERSION_BASED_UNIT\s*\(\s*'([^']+)'", text)
    if m and re.search(r"LENGTH_UNIT\s*\(\s*\)", text):
        name = m.group(1).upper()
        per = {"INCH": 0.0254, "FOOT": 0.3048, "MILLIMETRE": 1e-3}.get(name)
        if per is not None:
            return name.lower(), per
    m = re.search(r"LENGTH_UNIT\s*\(\s*\)[^;]*?SI_UNIT\s*\(\s*(?:\.(\w+)\.|\$)\s*,\s*\.METRE\.\s*\)", text)
    if m is None:
        m = re.search(r"SI_UNIT\s*\(\s*(?:\.(\w+)\.|\$)\s*,\s*\.METRE\.\s*\)[^;]*?LENGTH_UNIT", text)
    if m:
        prefix = m.group(1)
        return ((prefix or "").lower() + "metre"), _PREFIX.get(prefix, float("nan"))
    return None


def _check_step_text(path: Path, data: bytes) -> str:
    text = data.decode("latin-1")
    if not text.lstrip().startswith("ISO-10303-21"):
        raise PartError(f"{path}: not a STEP file (it does not begin with ISO-10303-21)")
    if "END-ISO-10303-21" not in text[-200:]:
        raise PartError(f"{path}: STEP file is cut off (no END-ISO-10303-21 at its end)")
    if not re.search(r"\b(MANIFOLD_SOLID_BREP|BREP_WITH_VOIDS|SHELL_BASED_SURFACE_MODEL|FACETED_BREP|"
                     r"ADVANCED_FACE|GEOMETRIC_CURVE_SET|MAPPED_ITEM|NEXT_ASSEMBLY_USAGE_OCCURRENCE)\b", text):
        raise PartError(f"{path}: STEP file holds no solid or surface (no B-rep entities)")
    if step_length_unit(text) is None:
        raise PartError(f"{path}: STEP file declares no length unit; export it again with units")
    return text


def load_brep(path: str | Path, tolerance_m: float | None = None) -> trimesh.Trimesh:
    """Tessellate a STEP or IGES file into one triangle mesh in metres (vertices merged, not yet checked
    for size: :func:`planning.part.load_mesh` does that)."""
    path = Path(path)
    tol_m = DEFAULT_TOLERANCE_M if tolerance_m is None else float(tolerance_m)
    if not np.isfinite(tol_m) or tol_m <= 0:
        raise PartError(f"{path}: tessellation tolerance {tolerance_m} must be a positive length")
    try:
        import cascadio  # noqa: F401  (trimesh's STEP path needs it; say so plainly if it is missing)
    except ImportError:
        raise PartError(f"{path}: reading STEP/IGES needs the cascadio package (pip install cascadio)") from None
    data = path.read_bytes()
    suffix = path.suffix.lower()
    tol_mm = tol_m * 1e3
    try:
        if suffix in STEP_SUFFIXES:
            _check_step_text(path, data)
            with _stdout_to_stderr():
                scene = trimesh.load(str(path), file_type="step", tol_linear=tol_mm,
                                     tol_angular=ANGULAR_TOLERANCE_RAD)
            scale = 1.0
        else:
            lines = [ln for ln in data.decode("latin-1").splitlines() if ln.strip()]
            if not lines or len(lines[0]) < 73 or lines[0][72] != "S":
                raise PartError(f"{path}: not an IGES file (no start section in column 73 of its first line)")
            if len(lines[-1]) < 73 or lines[-1][72] != "T":
                raise PartError(f"{path}: IGES file is cut off (no terminate section at its end)")
            with _stdout_to_stderr():  # OpenCASCADE's IGES reader prints to the C stdout (the --json channel)
                glb = cascadio.load(data, file_type="iges", tol_linear=tol_mm, tol_angular=ANGULAR_TOLERANCE_RAD)
            if not glb:
                raise PartError(f"{path}: OpenCASCADE could not read this IGES file")
            scene = trimesh.load(io.BytesIO(glb), file_type="glb")
            scale = 1e-3  # the IGES path comes out in OpenCASCADE's millimetres (the STEP path in metres)
    except PartError:
        raise
    except Exception as exc:  # OpenCASCADE and the GLB reader raise many types on bad files
        raise PartError(f"{path}: cannot read CAD file ({type(exc).__name__}: {exc})") from None
    mesh = scene.to_mesh() if isinstance(scene, trimesh.Scene) else scene
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise PartError(f"{path}: OpenCASCADE found no surface to tessellate in this file")
    return trimesh.Trimesh(vertices=np.asarray(mesh.vertices, float) * scale, faces=np.asarray(mesh.faces),
                           process=True)


@contextlib.contextmanager
def _stdout_to_stderr():
    """Send what C code writes to file descriptor 1 to 2 for the duration (Python's own stdout is untouched)."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
