"""The part to inspect: its CAD mesh and its targets, loaded and checked.

trimesh loads several kinds of broken file silently (a truncated STL or random
bytes as an *empty* mesh, a NaN vertex dropped, an OBJ face index 0 wrapped to
the last vertex); every check here turns such a file into a ``PartError`` that
names the file and the problem. Everything inside is in metres.
"""
from __future__ import annotations

import csv
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from calibration.errors import PartError
from planning.cad import IGES_SUFFIXES, STEP_SUFFIXES, load_brep
from planning.target_sampling import spaced_with_clearance

__all__ = ["UNITS_TO_M", "Targets", "Part", "load_mesh", "load_targets", "sample_targets", "load_part", "make_bracket", "mesh_health"]

UNITS_TO_M = {"m": 1.0, "mm": 1e-3, "cm": 1e-2, "um": 1e-6, "in": 0.0254, "ft": 0.3048}

#: Plausible overall size (bounding-box diagonal) of an inspected part, metres.
SIZE_RANGE_M = (1e-3, 5.0)
#: How far a target may lie from the mesh surface, as a fraction of the part's size.
ON_SURFACE_TOL = 2e-3
#: Fewest targets a job can measure: an image is oriented (Faugeras-Toscani) from 6 or more.
MIN_TARGETS = 6
#: Most targets a job can hold (the job file's n_targets maximum).
MAX_TARGETS = 100_000


@dataclass
class Targets:
    """Targets on the part, in the part frame (metres).

    Attributes:
        ids: (n,) target identifiers.
        xyz: (n, 3) float nominal centres.
        normals: (n, 3) float unit outward normals.
        kind: (n,) str, ``"retro"`` (retro-reflective dot) or ``"coded"`` (ArUco marker).
        tolerance_m: (n,) float, nan where the job's default applies.
        code: (n,) int ArUco id of coded targets, -1 for retro targets.
    """

    ids: list[str]
    xyz: np.ndarray
    normals: np.ndarray
    kind: np.ndarray
    tolerance_m: np.ndarray
    code: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    def index(self) -> dict[str, int]:
        return {t: i for i, t in enumerate(self.ids)}

    def subset(self, mask: np.ndarray) -> "Targets":
        idx = np.flatnonzero(mask) if np.asarray(mask).dtype == bool else np.asarray(mask)
        return Targets(
            ids=[self.ids[i] for i in idx],
            xyz=self.xyz[idx],
            normals=self.normals[idx],
            kind=self.kind[idx],
            tolerance_m=self.tolerance_m[idx],
            code=self.code[idx],
        )


@dataclass
class Part:
    """A part: mesh (metres, part frame) and targets.

    Attributes:
        name: the part's name.
        mesh: the CAD surface.
        targets: the targets to measure.
        target_diameter_m: diameter of a retro-reflective dot.
        coded_size_m: side of a coded (ArUco) marker, quiet zone excluded.
    """

    name: str
    mesh: trimesh.Trimesh
    targets: Targets
    target_diameter_m: float = 0.006
    coded_size_m: float = 0.02
    source: str = ""
    _sphere: tuple | None = field(default=None, repr=False)

    @property
    def centre(self) -> np.ndarray:
        """(3,) centre of the bounding box."""
        return self.mesh.bounds.mean(axis=0)

    @property
    def radius(self) -> float:
        """Radius of the sphere about :attr:`centre` that holds the whole mesh."""
        return float(np.linalg.norm(self.mesh.vertices - self.centre, axis=1).max())

    def summary(self) -> dict:
        lo, hi = self.mesh.bounds
        kinds, counts = np.unique(self.targets.kind, return_counts=True)
        return {
            "name": self.name,
            "source": self.source,
            "targets": len(self.targets),
            "targets_by_kind": {str(k): int(c) for k, c in zip(kinds, counts)},
            "bbox_min_m": lo.tolist(),
            "bbox_max_m": hi.tolist(),
            "size_m": (hi - lo).tolist(),
            "mesh": mesh_health(self.mesh),
            "target_diameter_m": self.target_diameter_m,
            "coded_size_m": self.coded_size_m,
        }


def mesh_health(mesh: trimesh.Trimesh) -> dict:
    """Facts about a mesh that an engineer checks before trusting it."""
    return {
        "vertices": int(len(mesh.vertices)),
        "faces": int(len(mesh.faces)),
        "watertight": bool(mesh.is_watertight),
        "winding_consistent": bool(mesh.is_winding_consistent),
        "area_m2": float(mesh.area),
        "volume_m3": float(mesh.volume) if mesh.is_watertight else None,
        "degenerate_faces": int((mesh.area_faces <= 1e-18).sum()),
    } | _openings(mesh)


def _openings(mesh: trimesh.Trimesh) -> dict:
    """Edges with one face (an open mesh's border) and the loops they make. A sheet has one loop per border;
    a solid with faces missing has openings the ray tracing sees through."""
    if mesh.is_watertight:
        return {"boundary_edges": 0, "boundary_loops": 0}
    edges = mesh.edges_sorted[trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)]
    loops = trimesh.graph.connected_components(edges, min_len=1) if len(edges) else []
    return {"boundary_edges": int(len(edges)), "boundary_loops": int(len(loops))}


# --- mesh -------------------------------------------------------------------


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


def load_mesh(path: str | Path, units: str, tessellation_tolerance: float | None = None) -> trimesh.Trimesh:
    """Load a CAD part (STEP/IGES, tessellated; or a mesh: STL, OBJ, PLY, GLB), check it, scale it to metres.

    A STEP or IGES file carries its own length unit, which is honoured (:mod:`planning.cad`); a mesh
    file has none, so it is scaled by ``units``. ``tessellation_tolerance`` (in ``units``) is the
    largest distance of the tessellation from the B-rep surface (STEP/IGES only; default 0.01 mm).

    Raises:
        PartError: the file is missing, unreadable, empty, has non-finite vertices,
            bad face indices, or a size that is absurd for the stated ``units``.
    """
    path = Path(path)
    if units not in UNITS_TO_M:
        raise PartError(f"{path}: unknown units {units!r} (use one of {', '.join(UNITS_TO_M)})")
    if not path.is_file():
        raise PartError(f"{path}: mesh file not found")
    suffix = path.suffix.lower()
    if suffix not in (".stl", ".obj", ".ply", ".glb", ".gltf", ".off") + STEP_SUFFIXES + IGES_SUFFIXES:
        raise PartError(f"{path}: unsupported CAD format {suffix!r} (use STEP, IGES, STL, OBJ, PLY or GLB)")
    try:
        return _load_mesh(path, units, suffix, tessellation_tolerance)
    except MemoryError:
        size = path.stat().st_size
        raise PartError(f"{path}: the mesh ({size / 2**30:.2f} GiB) does not fit in this machine's memory; "
                        "decimate it (a few million faces suffice for planning)") from None
    except OSError as exc:
        raise PartError(f"{path}: cannot read the mesh file ({exc.strerror or exc})") from None


def _load_mesh(path: Path, units: str, suffix: str, tessellation_tolerance: float | None) -> trimesh.Trimesh:
    data = path.read_bytes()
    if not data:
        raise PartError(f"{path}: file is empty")
    if suffix in STEP_SUFFIXES + IGES_SUFFIXES:
        tol = None if tessellation_tolerance is None else tessellation_tolerance * UNITS_TO_M[units]
        return _checked(path, load_brep(path, tol), 1.0, "the file's own")
    if suffix == ".stl":
        _check_stl_header(path, data)
    if suffix in (".obj", ".off") or suffix in (".stl", ".ply") and data[:5].lower() in (b"solid", b"ply\nf", b"ply\rf"):
        _check_text(path, data, suffix)
    if suffix == ".obj":
        _check_obj_indices(path, data.decode("latin-1"))
    if suffix in (".ply", ".off"):
        _check_declared_counts(path, data, suffix)
    _check_raw_vertices(path, data, suffix)
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except MemoryError:
        raise
    except Exception as exc:  # trimesh raises many types on corrupt files
        raise PartError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise PartError(f"{path}: file holds no triangle mesh")
    mesh = loaded
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise PartError(f"{path}: mesh is empty (no faces): the file is corrupt or not a mesh")
    if not np.isfinite(mesh.vertices).all():
        raise PartError(f"{path}: mesh has non-finite (NaN/inf) vertex coordinates")
    if mesh.faces.max() >= len(mesh.vertices) or mesh.faces.min() < 0:
        raise PartError(f"{path}: face indices out of range")
    return _checked(path, mesh, UNITS_TO_M[units], repr(units))


def _checked(path: Path, mesh: trimesh.Trimesh, scale: float, units: str) -> trimesh.Trimesh:
    """``mesh`` times ``scale`` (to metres), vertices merged, checked for area and a plausible size."""
    if not np.isfinite(mesh.vertices).all():
        raise PartError(f"{path}: mesh has non-finite (NaN/inf) vertex coordinates")
    mesh = trimesh.Trimesh(vertices=mesh.vertices * scale, faces=mesh.faces, process=True)
    if len(mesh.faces) == 0 or mesh.area <= 0:
        raise PartError(f"{path}: mesh has no area (all faces degenerate)")
    diag = float(np.linalg.norm(mesh.extents))
    lo, hi = SIZE_RANGE_M
    if not lo <= diag <= hi:
        raise PartError(
            f"{path}: part is {diag:.4g} m across with {units} units, outside {lo}..{hi} m: are the units right?"
        )
    return mesh


# --- targets ------------------------------------------------------------------

_REQUIRED = ("id", "x", "y", "z", "nx", "ny", "nz")
#: the longest target id: the archive index's column (``targets.target_id``)
TARGET_ID_MAX = 100


_OPTIONAL = ("kind", "tolerance", "code")
_FREE = ("note", "comment", "description")  # columns of the user's own, read by no one


def _columns(path: Path, header: list[str]) -> dict[str, int]:
    """Column name -> index. A name twice, or one the cell does not know, is refused: a misspelt
    ``tolerence`` read as no tolerance at all would judge every target against the job's default."""
    col: dict[str, int] = {}
    for i, c in enumerate(header):
        if not c:
            continue
        if c in col:
            raise PartError(f"{path}:1: column {c!r} twice (columns {col[c] + 1} and {i + 1})")
        if c not in _REQUIRED + _OPTIONAL + _FREE:
            raise PartError(f"{path}:1: unknown column {c!r}; the columns are {','.join(_REQUIRED + _OPTIONAL)} "
                            f"(and {', '.join(_FREE)} for text of your own)")
        col[c] = i
    return col


def load_targets(path: str | Path, units: str, max_targets: int = MAX_TARGETS) -> Targets:
    """Read ``id,x,y,z,nx,ny,nz[,kind][,tolerance][,code]`` (lengths in ``units``).

    Streams the file (bounded memory: it stops at ``max_targets`` + 1 rows, and a line longer
    than the csv module's field limit is an error, not a read of the whole file into memory).
    Every problem is a ``PartError`` naming the file and line.
    """
    path = Path(path)
    if not path.is_file():
        raise PartError(f"{path}: targets file not found")
    scale = UNITS_TO_M[units]
    ids: list[str] = []
    num: list[tuple[float, ...]] = []
    kind: list[str] = []
    code: list[int] = []
    isfinite = math.isfinite
    try:
        with path.open(newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            header = [c.strip() for c in next(reader, [])]
            missing = [c for c in _REQUIRED if c not in header]
            if missing:
                raise PartError(f"{path}: targets CSV lacks column(s) {', '.join(missing)} (needs id,x,y,z,nx,ny,nz)")
            col = _columns(path, header)
            i_id = col["id"]
            i_num = [col[c] for c in ("x", "y", "z", "nx", "ny", "nz")]
            i_kind, i_tol, i_code = col.get("kind"), col.get("tolerance"), col.get("code")
            width = len(header)
            for lineno, row in enumerate(reader, 2):
                if not row or len(row) == 1 and not row[0].strip():
                    continue  # a blank line
                if len(ids) >= max_targets:
                    raise PartError(f"{path}:{lineno}: more than {max_targets} targets (the most a job can hold)")
                if len(row) > width and any(v.strip() for v in row[width:]):
                    raise PartError(f"{path}:{lineno}: {len(row)} fields; the header has {width} "
                                    "(a comma inside a value, or a column without a name?)")
                if len(row) < width:
                    row = row + [""] * (width - len(row))
                try:
                    values = tuple(float(row[i]) for i in i_num)
                    t_raw = row[i_tol].strip() if i_tol is not None else ""
                    t = float(t_raw) * scale if t_raw else math.nan
                    c_raw = row[i_code].strip() if i_code is not None else ""
                    c = int(c_raw) if c_raw else -1
                except ValueError as exc:
                    raise PartError(f"{path}:{lineno}: {exc}") from None
                if not all(isfinite(v) for v in values):
                    raise PartError(f"{path}:{lineno}: non-finite coordinate or normal")
                if t_raw and not (isfinite(t) and t > 0):
                    raise PartError(f"{path}:{lineno}: tolerance {t_raw!r} must be a positive number")
                if c_raw and not -1 <= c < 250:
                    raise PartError(f"{path}:{lineno}: code {c} is not an ArUco id of DICT_4X4_250 (0..249, or -1 for none)")
                k = (row[i_kind].strip() if i_kind is not None else "") or ("coded" if c >= 0 else "retro")
                if k not in ("retro", "coded"):
                    raise PartError(f"{path}:{lineno}: kind {k!r} is neither 'retro' nor 'coded'")
                tid = row[i_id].strip()
                if not tid:
                    raise PartError(f"{path}:{lineno}: empty target id")
                if not tid.isprintable():
                    raise PartError(f"{path}:{lineno}: target id {tid!r} holds a control character")
                if len(tid) > TARGET_ID_MAX:
                    raise PartError(f"{path}:{lineno}: target id {tid[:24]!r}... is {len(tid)} characters long; at most "
                                    f"{TARGET_ID_MAX} (the archive index's limit for a target id)")
                if k == "coded" and c < 0:
                    raise PartError(f"{path}:{lineno}: coded target {tid!r} needs a 'code' (ArUco id)")
                ids.append(tid)
                num.append(values + (t,))
                kind.append(k)
                code.append(c)
    except (csv.Error, UnicodeDecodeError) as exc:
        raise PartError(f"{path}: not a readable targets CSV ({exc})") from None
    if not ids:
        raise PartError(f"{path}: no targets")
    arr = np.array(num, dtype=float).reshape(-1, 7)
    nrm_a = arr[:, 3:6]
    lengths = np.linalg.norm(nrm_a, axis=1)
    if (lengths < 1e-9).any():
        raise PartError(f"{path}: target {ids[int(np.argmin(lengths))]!r} has a zero normal")
    return Targets(
        ids=ids,
        xyz=arr[:, :3] * scale,
        normals=nrm_a / lengths[:, None],
        kind=np.array(kind),
        tolerance_m=arr[:, 6].copy(),
        code=np.array(code, dtype=int),
    )


def load_deviations(path: Path, ids: list[str], scale: float) -> np.ndarray:
    """Read the ``[sim] deviations`` CSV ``id,dx,dy,dz`` (job units) -> (n, 3) metres aligned with ``ids``.
    A row short of a field, an id given twice or a bad number is refused naming ``file:line``."""
    if not path.is_file():
        raise PartError(f"{path}: deviations file not found")
    index = {t: i for i, t in enumerate(ids)}
    out = np.zeros((len(ids), 3))
    seen: dict[str, int] = {}
    need = ("id", "dx", "dy", "dz")
    try:
        with path.open(newline="", encoding="utf-8-sig") as f:  # a BOM (spreadsheets write one) is not a column name
            reader = csv.DictReader(f)
            if not reader.fieldnames or any(c not in reader.fieldnames for c in need):
                raise PartError(f"{path}:1: deviations CSV needs columns id,dx,dy,dz; its header is "
                                   f"{','.join(reader.fieldnames or [])!r}")
            for row in reader:
                lineno = reader.line_num
                if None in row or any(row[c] is None for c in need):
                    got = len([v for k, v in row.items() if k is not None and v is not None]) + len(row.get(None, []))
                    raise PartError(f"{path}:{lineno}: {got} field(s); a row is {len(reader.fieldnames)} "
                                       f"({','.join(reader.fieldnames)})")
                tid = row["id"]
                if tid not in index:
                    raise PartError(f"{path}:{lineno}: unknown target id {tid!r}")
                if tid in seen:
                    raise PartError(f"{path}:{lineno}: target {tid!r} again (first on line {seen[tid]}); one "
                                       "deviation per target")
                seen[tid] = lineno
                try:
                    d = [float(row[c]) for c in ("dx", "dy", "dz")]
                except ValueError as exc:
                    raise PartError(f"{path}:{lineno}: {exc}") from None
                if not all(math.isfinite(v) for v in d):
                    raise PartError(f"{path}:{lineno}: non-finite deviation")
                out[index[tid]] = np.asarray(d) * scale
    except UnicodeDecodeError as exc:
        raise PartError(f"{path}: not a UTF-8 text CSV ({exc.reason} at byte {exc.start})") from None
    return out


def check_targets(mesh: trimesh.Trimesh, targets: Targets, source: str = "targets", *,
                  target_diameter_m: float = 0.0, coded_size_m: float = 0.0) -> None:
    """Duplicate ids, targets off the surface, normals pointing into the part, dots under a coded
    marker or overlapping each other -> ``PartError``."""
    seen: dict[str, int] = {}
    for i, t in enumerate(targets.ids):
        if t in seen:
            raise PartError(f"{source}: duplicate target id {t!r}")
        seen[t] = i
    codes = targets.code[targets.code >= 0]
    if len(np.unique(codes)) != len(codes):
        raise PartError(f"{source}: two coded targets share the same ArUco code")
    closest, dist, tri = trimesh.proximity.closest_point(mesh, targets.xyz)
    tol = ON_SURFACE_TOL * float(np.linalg.norm(mesh.extents))
    off = np.flatnonzero(dist > tol)
    if len(off):
        i = int(off[np.argmax(dist[off])])
        raise PartError(
            f"{source}: {len(off)} target(s) are off the part's surface, e.g. {targets.ids[i]!r} "
            f"{dist[i] * 1e3:.2f} mm away (tolerance {tol * 1e3:.2f} mm): wrong units or wrong file?"
        )
    if target_diameter_m > 0 and len(targets) > 1:
        # each target's nearest neighbour (O(n log n), O(n) memory; all close pairs could be n^2)
        dist_nn, nn = cKDTree(targets.xyz).query(targets.xyz, k=2)
        close = np.flatnonzero(dist_nn[:, 1] < target_diameter_m * 1.5)
        if len(close):
            a, b = int(close[0]), int(nn[close[0], 1])
            raise PartError(f"{source}: targets {targets.ids[a]!r} and {targets.ids[b]!r} overlap "
                            f"({np.linalg.norm(targets.xyz[a] - targets.xyz[b]) * 1e3:.2f} mm apart)")
    coded = np.flatnonzero(targets.kind == "coded")
    if coded_size_m > 0 and len(coded):
        reach = coded_size_m * (0.5 + 1 / 6) * np.sqrt(2) + target_diameter_m / 2  # marker + quiet zone corner
        k = min(2, len(coded))
        d, j_near = cKDTree(targets.xyz[coded]).query(targets.xyz, k=k)
        d, j_near = d.reshape(len(targets), k), j_near.reshape(len(targets), k)
        own = coded[j_near] == np.arange(len(targets))[:, None]  # a coded target is not under itself
        d = np.where(own, np.inf, d)
        bad = np.flatnonzero(d.min(axis=1) < reach)
        if len(bad):
            j = int(bad[0])
            raise PartError(f"{source}: target {targets.ids[j]!r} lies under the coded marker "
                            f"{targets.ids[int(coded[j_near[j, np.argmin(d[j])]])]!r} (closer than {reach * 1e3:.1f} mm)")
    face_n = mesh.face_normals[tri]
    inward = np.flatnonzero(np.einsum("ij,ij->i", face_n, targets.normals) < -0.5)
    if len(inward):
        raise PartError(
            f"{source}: {len(inward)} target normal(s) point into the part, e.g. {targets.ids[int(inward[0])]!r}"
        )


def sample_targets(
    mesh: trimesh.Trimesh,
    n: int,
    rng: np.random.Generator,
    *,
    n_coded: int = 0,
    min_spacing_m: float | None = None,
    edge_clearance_m: float = 0.0,
    min_normal_z: float | None = None,
    coded_clearance_m: float = 0.0,
) -> Targets:
    """Sample ``n`` targets on the surface, well spread (Poisson-disc like).

    Faces are drawn by area; candidates closer than ``min_spacing_m`` to an earlier
    target are rejected. The first ``n_coded`` targets (spread out) are coded, with
    ArUco ids 0..n_coded-1. Faces whose normal's z is below ``min_normal_z`` (e.g.
    the face the part stands on) get no targets. Dots closer than ``coded_clearance_m`` to a coded
    target are dropped (so fewer than ``n`` may be returned). Deterministic for a given ``rng``.
    """
    if n <= 0:
        raise PartError(f"cannot sample {n} targets")
    if min_spacing_m is None:
        min_spacing_m = 0.6 * np.sqrt(mesh.area / n)
    n_cand = max(20 * n, 2000)
    area = mesh.area_faces.copy()
    if min_normal_z is not None:
        area[mesh.face_normals[:, 2] < min_normal_z] = 0.0
    area /= area.sum()
    faces = rng.choice(len(mesh.faces), size=n_cand, p=area)
    r = rng.random((n_cand, 2))
    flip = r.sum(axis=1) > 1
    r[flip] = 1 - r[flip]
    tri = mesh.triangles[faces]
    pts = tri[:, 0] + r[:, :1] * (tri[:, 1] - tri[:, 0]) + r[:, 1:] * (tri[:, 2] - tri[:, 0])
    nrm = mesh.face_normals[faces]
    # keep away from the face's edges so a dot lies flat on one facet; spread by a greedy spacing
    chosen, _ = spaced_with_clearance(mesh, pts, faces, n, (min_spacing_m, 0.7 * min_spacing_m,
                                                          0.5 * min_spacing_m, 0.0), edge_clearance_m)
    if len(chosen) < n:
        raise PartError(f"could not place {n} targets on the surface")
    sel = chosen
    xyz, normals = pts[sel], nrm[sel]
    # coded targets: farthest-point spread among the samples
    coded_idx: list[int] = []
    if n_coded:
        coded_idx = [0]
        d = np.linalg.norm(xyz - xyz[0], axis=1)
        for _ in range(1, n_coded):
            j = int(np.argmax(d))
            coded_idx.append(j)
            d = np.minimum(d, np.linalg.norm(xyz - xyz[j], axis=1))
    kind = np.full(n, "retro", dtype=object)
    code = np.full(n, -1, dtype=int)
    for c, j in enumerate(coded_idx):
        kind[j] = "coded"
        code[j] = c
    if coded_idx and coded_clearance_m > 0:
        # a dot under a coded marker's sticker (with its quiet zone) cannot be seen: drop it
        d, _ = cKDTree(xyz[coded_idx]).query(xyz)
        keep = (kind == "coded") | (d >= coded_clearance_m)
        xyz, normals, kind, code = xyz[keep], normals[keep], kind[keep], code[keep]
        n = int(keep.sum())
    ids = [f"C{code[i]}" if kind[i] == "coded" else f"T{i:04d}" for i in range(n)]
    return Targets(ids=ids, xyz=xyz, normals=normals, kind=kind.astype(str), tolerance_m=np.full(n, np.nan), code=code)


def load_part(
    mesh_path: str | Path,
    units: str,
    targets_csv: str | Path | None = None,
    n_targets: int | None = None,
    seed: int = 0,
    n_coded: int = 0,
    *,
    name: str | None = None,
    target_diameter_m: float = 0.006,
    coded_size_m: float = 0.02,
    tessellation_tolerance: float | None = None,
) -> Part:
    """Load and check a part: mesh plus targets (from a CSV, or ``n_targets`` sampled with ``seed``)."""
    mesh = load_mesh(mesh_path, units, tessellation_tolerance)
    if mesh.is_watertight and mesh.volume < 0:  # every face turned inward (the targets' normals were blamed)
        raise PartError(f"{mesh_path}: the mesh is inside out (a closed surface whose faces point inward: volume "
                        f"{mesh.volume:.3g} m^3); export it with outward normals, or fix it (e.g. trimesh's "
                        "fix_normals)")
    if targets_csv is not None:
        targets = load_targets(targets_csv, units)
        source = str(targets_csv)
    elif n_targets:
        clearance = max(target_diameter_m, coded_size_m * 0.75 if n_coded else 0.0)
        reach = coded_size_m * (0.5 + 1 / 6) * np.sqrt(2) + target_diameter_m / 2
        targets = sample_targets(
            mesh, int(n_targets), np.random.default_rng(seed), n_coded=n_coded, edge_clearance_m=clearance,
            coded_clearance_m=reach * 1.05 if n_coded else 0.0,
        )
        source = f"{n_targets} targets sampled with seed {seed}"
    else:
        raise PartError(f"{mesh_path}: give a targets file or a number of targets to sample")
    if len(targets) < MIN_TARGETS:
        raise PartError(f"{source}: {len(targets)} target(s); a job needs at least {MIN_TARGETS} (an image is "
                        f"oriented from {MIN_TARGETS} or more)")
    check_targets(mesh, targets, source, target_diameter_m=target_diameter_m, coded_size_m=coded_size_m)
    return Part(
        name=name or Path(mesh_path).stem,
        mesh=mesh,
        targets=targets,
        target_diameter_m=target_diameter_m,
        coded_size_m=coded_size_m,
        source=str(mesh_path),
    )


def make_bracket() -> trimesh.Trimesh:
    """The example part, in metres: an L-bracket with a pocket and a rib (self-occluding).

    Base plate 0.30 x 0.20 x 0.03 m with a 0.12 x 0.08 x 0.02 m pocket, an upright
    wall 0.30 x 0.03 x 0.15 m along the back edge, and a triangular rib between them.
    The part frame's origin is at the centre of the base plate's bottom face.
    """
    from trimesh import creation

    base = creation.box(extents=(0.30, 0.20, 0.03))
    base.apply_translation((0, 0, 0.015))
    pocket = creation.box(extents=(0.12, 0.08, 0.021))
    pocket.apply_translation((0.05, -0.02, 0.03 - 0.01 + 0.0005))
    # solids overlap (no coplanar contact faces) so the union leaves no internal faces
    wall = creation.box(extents=(0.30, 0.03, 0.16))
    wall.apply_translation((0, 0.085, 0.02 + 0.08))
    rib = trimesh.convex.convex_hull(np.array(
        [[-0.01, 0.08, 0.02], [-0.01, -0.04, 0.02], [-0.01, 0.08, 0.16],
         [0.01, 0.08, 0.02], [0.01, -0.04, 0.02], [0.01, 0.08, 0.16]]
    ))
    rib.apply_translation((-0.09, 0, 0))
    # manifold3d does the booleans: a watertight solid with no internal faces
    solid = trimesh.boolean.union([base, wall, rib], engine="manifold", check_volume=False)
    solid = trimesh.boolean.difference([solid, pocket], engine="manifold", check_volume=False)
    solid.merge_vertices()
    return solid
