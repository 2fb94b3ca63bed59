"""The part to inspect: its CAD mesh and its targets, loaded and checked.

trimesh loads several kinds of broken file silently (a truncated STL or random
bytes as an *empty* mesh, a NaN vertex dropped, an OBJ face index 0 wrapped to
the last vertex); every check here turns such a file into a ``PartError`` that
names the file and the problem. Everything inside is in metres.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from calibration.errors import PartError
from planning.cad import (IGES_SUFFIXES, STEP_SUFFIXES, check_mesh_file, load_brep, mesh_bodies, mesh_warnings,
                          orientation_line)
from planning.target_sampling import spaced_with_clearance

__all__ = ["UNITS_TO_M", "Targets", "Part", "load_mesh", "load_targets", "sample_targets", "load_part", "make_bracket", "mesh_health",
           "mesh_warnings"]

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
    normals_warning: str | None = None  # the targets' normals somewhat off the surface's (decision 0068)

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
            "normals_warning": self.normals_warning,
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
    } | _openings(mesh) | mesh_bodies(mesh)


def _openings(mesh: trimesh.Trimesh) -> dict:
    """Edges with one face (an open mesh's border) and the loops they make, and edges of more than two faces
    (non-manifold: a body given twice, or touching another along an edge). A sheet has one loop per border; a solid
    with faces missing has openings the ray tracing sees through."""
    if mesh.is_watertight:
        return {"boundary_edges": 0, "boundary_loops": 0, "nonmanifold_edges": 0}
    edges = mesh.edges_sorted[trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)]
    loops = trimesh.graph.connected_components(edges, min_len=1) if len(edges) else []
    shared = np.bincount(trimesh.grouping.unique_rows(mesh.edges_sorted)[1])
    return {"boundary_edges": int(len(edges)), "boundary_loops": int(len(loops)),
            "nonmanifold_edges": int((shared > 2).sum())}


#: a part smaller or larger than these (metres) makes a refusal ask whether the job's units are right
PLAUSIBLE_SIZE_M = (0.02, 2.0)


def units_hint(size_m: float, units: str | None) -> str:
    """``"; the part is 11.8 mm across in mm: are the units right ([job] units)?"`` when ``size_m`` (the part's
    largest extent) is implausible for a part in the cell, else empty (decision 0068)."""
    if units not in UNITS_TO_M or PLAUSIBLE_SIZE_M[0] <= size_m <= PLAUSIBLE_SIZE_M[1]:
        return ""
    return f"; the part is {size_m / UNITS_TO_M[units]:.4g} {units} across in {units}: are the units right ([job] units)?"


# --- mesh -------------------------------------------------------------------


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
        raise PartError(f"{path}: mesh file not found" + _backslash(path))
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
    check_mesh_file(path, data, suffix)
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


def _backslash(path: Path) -> str:
    """A Windows path (``parts\\bracket.stl``, ``C:\\...``) in a job file: say to write it with "/"."""
    return ("; write paths with \"/\" (a backslash is no separator here), relative to the job file" if "\\" in str(path)
            else "")


def _header_advice(header: list[str]) -> str:
    """Why a targets file's header lacks the columns: another separator, or names not in lower case."""
    for sep, name in ((";", "semicolons"), ("\t", "tabs")):
        if len(header) == 1 and sep in header[0]:
            return f": the separator must be a comma (this file uses {name}; save it as CSV, comma-separated)"
    if all(c in [h.lower() for h in header] for c in _REQUIRED):
        return ": the column names are lower case (id,x,y,z,nx,ny,nz,kind,tolerance,code)"
    return ""


def _number(path: Path, lineno: int, column: str, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        what = "is empty" if not text.strip() else f"holds {text.strip()!r}, not a number"
        raise PartError(f"{path}:{lineno}: column {column!r} {what}") from None


def load_targets(path: str | Path, units: str, max_targets: int = MAX_TARGETS) -> Targets:
    """Read ``id,x,y,z,nx,ny,nz[,kind][,tolerance][,code]`` (lengths in ``units``).

    Streams the file (bounded memory: it stops at ``max_targets`` + 1 rows, and a line longer
    than the csv module's field limit is an error, not a read of the whole file into memory).
    Every problem is a ``PartError`` naming the file and line.
    """
    path = Path(path)
    if not path.is_file():
        raise PartError(f"{path}: targets file not found" + _backslash(path))
    scale = UNITS_TO_M[units]
    ids: list[str] = []
    num: list[tuple[float, ...]] = []
    kind: list[str] = []
    code: list[int] = []
    isfinite = math.isfinite
    with path.open("rb") as f:
        if f.read(2) in (b"\xff\xfe", b"\xfe\xff"):
            raise PartError(f"{path}: the targets file is UTF-16 text: save it as CSV UTF-8 (comma-separated)")
    try:
        with path.open(newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            header = [c.strip() for c in next(reader, [])]
            first = 2
            if ",".join(header).lower().startswith("sep="):  # Excel's separator line
                if ",".join(header).lower() != "sep=,":
                    raise PartError(f"{path}:1: {','.join(header)!r}: the separator must be a comma")
                header, first = [c.strip() for c in next(reader, [])], 3
            missing = [c for c in _REQUIRED if c not in header]
            if missing:
                raise PartError(f"{path}:{first - 1}: targets CSV lacks column(s) {', '.join(missing)} (needs "
                                f"id,x,y,z,nx,ny,nz); its header is {','.join(header)!r}" + _header_advice(header))
            col = _columns(path, header)
            i_id = col["id"]
            i_num = [col[c] for c in ("x", "y", "z", "nx", "ny", "nz")]
            i_kind, i_tol, i_code = col.get("kind"), col.get("tolerance"), col.get("code")
            width = len(header)
            for lineno, row in enumerate(reader, first):
                if not any(v.strip() for v in row):
                    continue  # a blank line, or one of empty cells only (a spreadsheet's ",,,,")
                if len(ids) >= max_targets:
                    raise PartError(f"{path}:{lineno}: more than {max_targets} targets (the most a job can hold)")
                if len(row) > width and any(v.strip() for v in row[width:]):
                    raise PartError(f"{path}:{lineno}: {len(row)} fields; the header has {width} "
                                    "(a comma inside a value, or a column without a name?)")
                if len(row) < width:
                    row = row + [""] * (width - len(row))
                values = tuple(_number(path, lineno, header[i], row[i]) for i in i_num)
                t_raw = row[i_tol].strip() if i_tol is not None else ""
                t = _number(path, lineno, "tolerance", t_raw) * scale if t_raw else math.nan
                c_raw = row[i_code].strip() if i_code is not None else ""
                c = _number(path, lineno, "code", c_raw) if c_raw else -1
                if c != int(c):
                    raise PartError(f"{path}:{lineno}: column 'code': {c_raw!r} is not a whole number (an ArUco id)")
                c = int(c)
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
    except UnicodeDecodeError as exc:
        raise PartError(f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x}: cp1252 / Latin-1?): save it as "
                        "CSV UTF-8") from None
    except csv.Error as exc:
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
                  target_diameter_m: float = 0.0, coded_size_m: float = 0.0, units: str | None = None) -> str | None:
    """Duplicate ids, targets off the surface, normals far from the surface's (:func:`_check_normals`), dots under
    a coded marker or overlapping each other -> ``PartError``; returns a warning for normals somewhat off, or None."""
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
                            f"({np.linalg.norm(targets.xyz[a] - targets.xyz[b]) * 1e3:.2f} mm apart)"
                            + units_hint(float(np.max(mesh.extents)), units))
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
    return _check_normals(mesh, targets, source, tri, dist, target_diameter_m)


#: a targets file's normal this far from the surface's (degrees) is said, and beyond the second refused (decision 0068)
NORMAL_WARN_DEG, NORMAL_REFUSE_DEG = 20.0, 60.0


def _normal_angles(mesh: trimesh.Trimesh, targets: Targets, tri: np.ndarray, dist: np.ndarray,
                   near_m: float) -> np.ndarray:
    """(n,) degrees between each target's normal and the surface's: the face under it, or, beyond
    :data:`NORMAL_WARN_DEG`, the closest of the faces around that face's corners within ``near_m`` of the target's
    nearest (a target at a sharp edge lies on either face)."""
    ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", mesh.face_normals[tri], targets.normals), -1, 1)))
    for chunk in np.array_split(np.flatnonzero(ang > NORMAL_WARN_DEG), max(1, int(np.sum(ang > NORMAL_WARN_DEG)) // 2000)):
        if not len(chunk):
            continue
        cand = mesh.vertex_faces[mesh.faces[tri[chunk]]].reshape(len(chunk), -1)  # -1 pads
        ok = cand >= 0
        rows = np.repeat(np.arange(len(chunk)), ok.sum(axis=1))
        pts = trimesh.triangles.closest_point(mesh.triangles[cand[ok]], targets.xyz[chunk][rows])
        d = np.linalg.norm(pts - targets.xyz[chunk][rows], axis=1)
        a = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", mesh.face_normals[cand[ok]], targets.normals[chunk][rows]),
                                         -1, 1)))
        a[d > dist[chunk][rows] + near_m] = np.inf
        best = np.full(len(chunk), np.inf)
        np.minimum.at(best, rows, a)
        ang[chunk] = np.minimum(ang[chunk], best)
    return ang


def _check_normals(mesh: trimesh.Trimesh, targets: Targets, source: str, tri: np.ndarray, dist: np.ndarray,
                   target_diameter_m: float) -> str | None:
    """Each target's normal against the surface's (:func:`_normal_angles`): beyond :data:`NORMAL_REFUSE_DEG` a
    ``PartError`` (the mesh's orientation first when its faces are not consistently oriented, or when every target
    faces against an open mesh that cannot tell its inside), beyond :data:`NORMAL_WARN_DEG` the warning returned.
    The thickness correction moves each target along its normal and the planner's incidences use it."""
    ang = _normal_angles(mesh, targets, tri, dist, max(1e-5, 0.25 * target_diameter_m))
    far = np.flatnonzero(ang > NORMAL_REFUSE_DEG)
    order = np.argsort(-ang, kind="stable")

    def named(idx):
        idx = [i for i in order if i in set(idx)]
        return ", ".join(targets.ids[i] for i in idx[:5]) + (f" and {len(idx) - 5} more" if len(idx) > 5 else "")

    if len(far):
        against = f"{len(far)} target normal(s) face away from the surface ({named(far)}: up to {ang.max():.0f} deg)"
        if not mesh.is_winding_consistent:
            raise PartError(f"{source}: {orientation_line(mesh_bodies(mesh)['flipped_faces'])}; {against} because "
                            "of it")
        if (ang > 150).all() and not mesh.is_watertight:
            raise PartError(f"{source}: every target's normal is opposite to the mesh's faces: the mesh is open, so "
                            "whether it is inside out cannot be told; re-export it with outward normals, or, if it is "
                            "right, check the targets file's nx, ny, nz columns (pointing into the part?)")
        raise PartError(f"{source}: the targets file's normals of {named(far)} are {ang.max():.0f} deg from the "
                        f"surface's ({len(far)} beyond {NORMAL_REFUSE_DEG:.0f} deg): check the nx, ny, nz columns "
                        "(swapped? another frame? pointing into the part?)")
    warn = np.flatnonzero(ang > NORMAL_WARN_DEG)
    if len(warn):
        return (f"the targets file's normals of {named(warn)} are up to {ang.max():.0f} deg from the surface's "
                f"({len(warn)} beyond {NORMAL_WARN_DEG:.0f} deg): the targets' thickness and the plan's incidence "
                "angles follow them; check the nx, ny, nz columns")
    return None


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
    if mesh.is_watertight and mesh.is_winding_consistent and mesh.volume < 0:  # every face turned inward (the targets' normals were blamed)
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
    normals_note = check_targets(mesh, targets, source, target_diameter_m=target_diameter_m, coded_size_m=coded_size_m,
                                 units=units)
    return Part(
        name=name or Path(mesh_path).stem,
        mesh=mesh,
        targets=targets,
        target_diameter_m=target_diameter_m,
        coded_size_m=coded_size_m,
        source=str(mesh_path),
        normals_warning=normals_note,
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
