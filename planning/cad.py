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
``PartError`` naming the file and the problem, never an empty mesh. OpenCASCADE reads what it can of a damaged
file and says the rest only on the C-level output (``*** ERR StepReaderData : Unresolved Reference : Fails Count :
1 ***``), dropping the body or face it could not read: the conversion's file descriptors 1 and 2 go to a temporary
file (:func:`_occ_output`), and any error line there refuses the file with OpenCASCADE's message and, where it gives
no line, the entity the file's own text shows broken (:func:`_step_damage`; decision 0068).

The make-up of a CAD mesh, whatever its format (:func:`mesh_bodies`, :func:`mesh_warnings`): its bodies, faces given
twice, bodies lying on each other, faces flipped against their neighbours (decision 0068).
"""
from __future__ import annotations

import contextlib
import io
import os
import re
import struct
import sys
import tempfile
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
    said: list[str] = []  # what OpenCASCADE wrote on the C-level stdout / stderr during the conversion
    try:
        if suffix in STEP_SUFFIXES:
            text = _check_step_text(path, data)
            try:
                with _occ_output(said):
                    scene = trimesh.load(str(path), file_type="step", tol_linear=tol_mm,
                                         tol_angular=ANGULAR_TOLERANCE_RAD)
            finally:
                _refuse_occ_errors(path, said, text)
            scale = 1.0
        else:
            lines = [ln for ln in data.decode("latin-1").splitlines() if ln.strip()]
            if not lines or len(lines[0]) < 73 or lines[0][72] != "S":
                raise PartError(f"{path}: not an IGES file (no start section in column 73 of its first line)")
            if len(lines[-1]) < 73 or lines[-1][72] != "T":
                raise PartError(f"{path}: IGES file is cut off (no terminate section at its end)")
            try:
                with _occ_output(said):  # OpenCASCADE's IGES reader prints to the C stdout (the --json channel)
                    glb = cascadio.load(data, file_type="iges", tol_linear=tol_mm, tol_angular=ANGULAR_TOLERANCE_RAD)
            finally:
                _refuse_occ_errors(path, said, None)
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


#: an error line of OpenCASCADE's (``*** ERR StepReaderData : ...``, ``**** ERR StepFile : ...``) or cascadio's
_OCC_ERROR = re.compile(r"\bERR\b|\bFail|^Error\b")
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


@contextlib.contextmanager
def _occ_output(said: list[str]):
    """Send what C code writes to file descriptors 1 and 2 to a temporary file for the duration, restored in
    ``finally``; its lines, without their colour codes, are appended to ``said`` (Python's own streams are flushed
    before and after; nothing of OpenCASCADE's reaches the operator's terminal or the --json channel)."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with tempfile.TemporaryFile() as tmp:
        try:
            os.dup2(tmp.fileno(), 1)
            os.dup2(tmp.fileno(), 2)
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
            tmp.seek(0)
            out = _ANSI.sub("", tmp.read().decode("utf-8", "replace"))
            said.extend(ln.strip(" *\t") for ln in out.splitlines() if ln.strip(" *\t"))


def _refuse_occ_errors(path: Path, said: list[str], text: str | None) -> None:
    """A ``PartError`` when OpenCASCADE said it could not read part of the file: its message, and the entity the
    file's text shows broken where the message names no line."""
    errors = [ln for ln in said if _OCC_ERROR.search(ln) and not ln.startswith("Error: Failed to read")]
    if not errors and not any(_OCC_ERROR.search(ln) for ln in said):
        return
    msg = "; ".join(dict.fromkeys(re.sub(r"\s+", " ", e) for e in errors)) or said[-1]
    where = _step_damage(text) if text is not None and not re.search(r"\bLine \d+", msg) else ""
    syntax = " (a STEP syntax error)" if re.search(r"syntax", msg, re.I) else ""
    raise PartError(f"{path}: OpenCASCADE could not read all of it{syntax}: {msg}{'; ' + where if where else ''}; "
                    "a body or face would be missing: export the file again")


def _step_damage(text: str) -> str:
    """The first entity of a STEP file's DATA section whose parentheses do not balance, or that refers to an entity
    the file does not define: ``"line 536: #529 ..."``; empty when none is found."""
    start = text.find("DATA;")
    if start < 0:
        return ""
    body = text[start + 5:]
    line0 = text.count("\n", 0, start + 5) + 1
    defined = set(re.findall(r"(?m)^\s*#(\d+)\s*=", body))
    first_ref = ""
    for m in re.finditer(r"(?:'(?:[^']|'')*'|[^;'])+;", body):
        stmt = m.group(0)
        bare = re.sub(r"'(?:[^']|'')*'", "''", stmt)
        if not bare.strip().startswith("#"):
            continue
        line = line0 + body.count("\n", 0, m.start() + len(stmt) - len(stmt.lstrip()))
        head = bare.strip().split("=")[0].strip()
        depth, low = 0, 0
        for ch in bare:
            depth += (ch == "(") - (ch == ")")
            low = min(low, depth)
        if depth or low < 0:
            return f"line {line}: {head}'s parentheses do not balance ({bare.strip()[:60]})"
        if not first_ref:
            missing = [r for r in re.findall(r"#(\d+)", bare.split("=", 1)[-1]) if r not in defined]
            if missing:
                first_ref = f"line {line}: {head} refers to #{missing[0]}, which the file does not define"
    return first_ref


#: two bodies whose bounding boxes overlap by this share of their union are taken for one part given twice
BODY_OVERLAP_SHARE = 0.9


def mesh_bodies(mesh: trimesh.Trimesh) -> dict:
    """The bodies (connected components of the faces, each face counted once), the faces given twice, the pairs of
    bodies (1-based, largest first) whose bounding boxes nearly coincide (a copy of the part on itself or a fraction
    of a millimetre off: the volume doubled, targets covered by the copy), and the faces flipped against their
    neighbours (the fewer of those :func:`trimesh.repair.fix_winding` turns and those it leaves; decision 0068)."""
    faces = np.asarray(mesh.faces)
    uniq = trimesh.grouping.unique_rows(np.sort(faces, axis=1))[0]
    comps = trimesh.graph.connected_components(trimesh.graph.face_adjacency(faces[uniq]),
                                               nodes=np.arange(len(uniq)), min_len=1)
    comps = sorted((uniq[c] for c in comps), key=len, reverse=True)
    overlap = []
    if 1 < len(comps) <= 200:
        box = np.array([[mesh.vertices[faces[c]].reshape(-1, 3).min(0), mesh.vertices[faces[c]].reshape(-1, 3).max(0)]
                        for c in comps])
        lo, hi = np.maximum(box[:, None, 0], box[None, :, 0]), np.minimum(box[:, None, 1], box[None, :, 1])
        inter = np.prod(np.clip(hi - lo, 0, None), axis=2)
        vol = np.prod(box[:, 1] - box[:, 0], axis=1)
        share = inter / np.maximum(vol[:, None] + vol[None, :] - inter, 1e-30)
        overlap = [[int(a) + 1, int(b) + 1] for a, b in zip(*np.nonzero(np.triu(share > BODY_OVERLAP_SHARE, 1)))][:10]
    flipped = 0
    if not mesh.is_winding_consistent:
        fixed = mesh.copy()
        trimesh.repair.fix_winding(fixed)
        turned = int((np.asarray(fixed.faces) != faces).any(axis=1).sum())
        flipped = min(turned, len(faces) - turned)
    return {"bodies": len(comps), "duplicate_faces": int(len(faces) - len(uniq)), "overlapping_bodies": overlap,
            "flipped_faces": flipped}


def mesh_warnings(h: dict) -> list[str]:
    """What :func:`mesh_health`'s facts mean for the plan, one line each (``cell check`` says them)."""
    out = []
    if h["boundary_edges"]:
        out.append(f"the mesh is open: {h['boundary_edges']} edges with one face, in {h['boundary_loops']} border(s). "
                   "A sheet has its borders; a solid must have none, else rays pass through its openings and the plan "
                   "counts targets as seen through the part: repair the mesh or export it closed")
    if h.get("duplicate_faces"):
        out.append(f"{h['duplicate_faces']} of the mesh's {h['faces']} faces are given twice (identical bodies: the "
                   "part exported twice?): export the part once")
    elif h.get("nonmanifold_edges"):
        out.append(f"the mesh has {h['nonmanifold_edges']} non-manifold edges (shared by more than two faces: bodies "
                   "touching along an edge, or a body given twice): repair the mesh")
    for a, b in h.get("overlapping_bodies") or []:
        out.append(f"bodies {a} and {b} of the mesh's {h['bodies']} overlap (their bounding boxes nearly coincide: "
                   "the part given twice, one copy slightly off?); its volume and the targets' visibility count both: "
                   "export the part once")
    if not h["winding_consistent"]:
        out.append(orientation_line(h["flipped_faces"]))
    return out


def orientation_line(flipped: int) -> str:
    return (f"the mesh's faces are not consistently oriented ({flipped} face(s) flipped?): re-export it with outward "
            "normals (or fix it, e.g. trimesh's fix_normals)")


#: what a mesh file of each name must hold, where :func:`what_file` can tell (a binary STL has no signature)
_SNIFFED = {".stl": "ASCII STL", ".obj": "OBJ", ".ply": "PLY"}


def check_mesh_file(path: Path, data: bytes, suffix: str) -> None:
    """A mesh file's own checks before trimesh reads it (what trimesh would read silently wrong): its content of the
    kind its name says, its declared counts, its face indices, its vertices finite."""
    sniff = what_file(data)
    if sniff is not None and suffix in _SNIFFED and sniff != _SNIFFED[suffix]:
        raise PartError(f"{path}: the file is named {suffix} but holds {sniff} (its first bytes say so): rename it to "
                        f"its kind, or export it as {suffix[1:].upper()}")
    if sniff is None and suffix in (".obj", ".ply", ".off") and len(data) >= 84 and \
            len(data) == 84 + 50 * struct.unpack("<I", data[80:84])[0]:
        raise PartError(f"{path}: the file is named {suffix} but holds a binary STL (its length fits the face count of "
                        f"a binary STL's header): rename it to .stl")
    if suffix == ".stl":
        _check_stl_header(path, data)
    if suffix in (".obj", ".off") or suffix in (".stl", ".ply") and data[:5].lower() in (b"solid", b"ply\nf", b"ply\rf"):
        _check_text(path, data, suffix)
    if suffix == ".obj":
        _check_obj_indices(path, data.decode("latin-1"))
    if suffix in (".ply", ".off"):
        _check_declared_counts(path, data, suffix)
    _check_raw_vertices(path, data, suffix)


def what_file(data: bytes) -> str | None:
    """What a CAD or mesh file's first bytes say it is: ``"STEP"``, ``"PLY"``, ``"ASCII STL"``, ``"OBJ"``,
    ``"GLB"``, ``"IGES"``, or None when they do not tell (a binary STL has no signature)."""
    head = data[:4096].lstrip()
    if head.startswith(b"ISO-10303-21"):
        return "STEP"
    if head.startswith(b"ply"):
        return "PLY"
    if head.startswith(b"glTF"):
        return "GLB"
    if head[:5].lower() == b"solid" and b"facet" in head[:1000]:
        return "ASCII STL"
    if re.match(rb"(?:(?:#[^\n]*|mtllib[^\n]*|o [^\n]*|g [^\n]*)?\s*\n)*\s*v\s+[-+\d.]", head):
        return "OBJ"
    if len(data) >= 80 and data[72:73] == b"S" and re.match(rb"[ -~]{72}S[ \d]{7}\r?\n", data[:82]):
        return "IGES"
    return None


def _check_stl_header(path: Path, data: bytes) -> None:
    """Binary STL: the face count in the header must match the file's length."""
    if data[:5].lower() == b"solid" and b"facet" in data[:1000]:
        return  # ASCII STL
    if len(data) < 84:
        raise PartError(f"{path}: STL file is truncated ({len(data)} bytes, a binary STL needs at least 84)")
    (n,) = struct.unpack("<I", data[80:84])
    expected = 84 + 50 * n
    if n == 0:
        raise PartError(f"{path}: binary STL header says it has 0 faces")
    if len(data) != expected:
        raise PartError(
            f"{path}: binary STL header says {n} faces ({expected} bytes) but the file has {len(data)} bytes: "
            "truncated or corrupt"
        )


def _check_text(path: Path, data: bytes, suffix: str) -> None:
    """A text mesh format must be text: bytes that are not UTF-8 (random data, a binary file renamed) are
    refused here, naming the line, instead of surfacing as a decoder's error from inside trimesh."""
    if suffix == ".ply":
        end = data.find(b"end_header")
        if end < 0:
            raise PartError(f"{path}: PLY file without 'end_header': truncated or not a PLY file")
        if b"format ascii" not in data[:end]:
            return  # binary PLY: only its header is text
        data = data[:end]
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise PartError(f"{path}:{line}: not a text {suffix[1:].upper()} file (binary data at byte {exc.start}); "
                        "is it the right file?") from None
    if b"\0" in data:
        line = data.count(b"\n", 0, data.index(b"\0")) + 1
        raise PartError(f"{path}:{line}: not a text {suffix[1:].upper()} file (a NUL byte); is it the right file?")


def _check_declared_counts(path: Path, data: bytes, suffix: str) -> None:
    """ASCII PLY and OFF: the file must hold as many vertices and faces as its header declares (trimesh reads a
    truncated one as the part's first few faces). Records are counted as written, before any polygon is
    triangulated (a quad is one face here, two triangles in the mesh)."""
    if suffix == ".ply":
        end = data.find(b"end_header")
        if end < 0 or b"format ascii" not in data[:end]:
            return
        elements: list[tuple[str, int, list[bool]]] = []  # name, count, per property: is it a list
        for line in data[:end].decode("utf-8", "replace").splitlines():
            tok = line.split()
            if len(tok) >= 3 and tok[0] == "element":
                try:
                    elements.append((tok[1], int(tok[2]), []))
                except ValueError:
                    raise PartError(f"{path}: PLY header line {line.strip()!r}: the count is not an integer") from None
            elif len(tok) >= 2 and tok[0] == "property" and elements:
                elements[-1][2].append(tok[1] == "list")
        body = data[data.find(b"\n", end) + 1:].split()
        pos = 0
        for name, count, props in elements:
            for i in range(count):
                for is_list in props:
                    if is_list:
                        try:
                            pos += 1 + int(float(body[pos]))
                        except (IndexError, ValueError):
                            pos = len(body) + 1
                    else:
                        pos += 1
                if pos > len(body):
                    _fewer(path, name, count, i)
        return
    lines = [ln.split("#")[0].split() for ln in data.decode("utf-8", "replace").splitlines()]
    lines = [t for t in lines if t]
    if not lines or not lines[0][0].upper().endswith("OFF") or "BINARY" in (t.upper() for t in lines[0]):
        return
    head = lines[0][1:] or (lines[1] if len(lines) > 1 else [])
    rest = lines[1:] if lines[0][1:] else lines[2:]
    try:
        n_v, n_f = int(head[0]), int(head[1])
    except (IndexError, ValueError):
        raise PartError(f"{path}: OFF header without its vertex and face counts") from None
    if len(rest) < n_v:
        _fewer(path, "vertex", n_v, len(rest))
    faces = rest[n_v:n_v + n_f]
    held = len(faces)
    if faces:
        try:
            held -= len(faces[-1]) < 1 + int(faces[-1][0])  # the last line cut short
        except ValueError:
            held -= 1
    if held < n_f:
        _fewer(path, "face", n_f, held)


def _fewer(path: Path, element: str, declared: int, held: int) -> None:
    plural = {"vertex": "vertices", "face": "faces"}.get(element, f"{element} records")
    raise PartError(f"{path}: the file holds fewer {plural} than its header declares ({held} of {declared}): "
                    "truncated or corrupt")


def _check_obj_indices(path: Path, text: str) -> None:
    """OBJ: face indices are 1-based (or negative); 0 or out of range is an error."""
    n_v = 0
    for lineno, line in enumerate(text.splitlines(), 1):
        if line.startswith("v "):
            n_v += 1
        elif line.startswith("f "):
            for tok in line.split()[1:]:
                head = tok.split("/")[0]
                try:
                    idx = int(head)
                except ValueError:
                    raise PartError(f"{path}:{lineno}: face index {head!r} is not an integer") from None
                if idx == 0:
                    raise PartError(f"{path}:{lineno}: face index 0 (OBJ indices start at 1)")
                if idx > n_v or idx < -n_v:
                    raise PartError(f"{path}:{lineno}: face index {idx} out of range (only {n_v} vertices so far)")


def _check_raw_vertices(path: Path, data: bytes, suffix: str) -> None:
    """Find non-finite vertex coordinates that trimesh would drop silently."""
    if suffix == ".stl" and not (data[:5].lower() == b"solid" and b"facet" in data[:1000]):
        n = struct.unpack("<I", data[80:84])[0]
        rec = np.frombuffer(data[84 : 84 + 50 * n], dtype=np.dtype([("n", "<f4", 3), ("v", "<f4", 9), ("a", "<u2")]))
        bad = ~np.isfinite(rec["v"]).all(axis=1)
        if bad.any():
            raise PartError(f"{path}: face {int(np.flatnonzero(bad)[0])} has a non-finite (NaN/inf) vertex coordinate")
    elif suffix in (".obj", ".stl", ".ply"):
        text = data.decode("latin-1")
        for lineno, line in enumerate(text.splitlines(), 1):
            s = line.strip().lower()
            if s.startswith(("v ", "vertex ")) and ("nan" in s or "inf" in s):
                raise PartError(f"{path}:{lineno}: non-finite (NaN/inf) vertex coordinate")
