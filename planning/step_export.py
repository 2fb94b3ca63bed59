"""Write a closed triangle mesh as a STEP AP214 B-rep (ISO 10303-21 text): its coplanar triangles merged
into planar faces (holes as inner bounds).

It exists to make STEP parts with a known geometry (the example bracket in STEP, test parts in mm
and in inches) without a CAD kernel in the dependencies: the topology is the mesh's (shared
vertices, one ``EDGE_CURVE`` per boundary edge used by its two faces with opposite orientations,
``ADVANCED_FACE`` on a ``PLANE``, a ``CLOSED_SHELL`` in a ``MANIFOLD_SOLID_BREP``), and the length
unit is declared in the file (``SI_UNIT(.MILLI.,.METRE.)`` or a ``CONVERSION_BASED_UNIT`` for
inches), which is what the reader must honour.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

_UNITS = {"mm": "#{u}=(LENGTH_UNIT()NAMED_UNIT(*)SI_UNIT(.MILLI.,.METRE.));",
          "m": "#{u}=(LENGTH_UNIT()NAMED_UNIT(*)SI_UNIT($,.METRE.));"}


def step_text(mesh: trimesh.Trimesh, units: str = "mm", name: str = "part") -> str:
    """The STEP file of ``mesh`` (coordinates already in ``units``: mm, m or inch)."""
    if units not in ("mm", "m", "inch"):
        raise ValueError(f"units {units!r}: use mm, m or inch")
    if not mesh.is_watertight:
        raise ValueError("the mesh must be closed (watertight) to be written as a solid")
    lines: list[str] = []
    n = [0]

    def add(text: str) -> int:
        n[0] += 1
        lines.append(f"#{n[0]}={text};")
        return n[0]

    def num(x: float) -> str:
        s = f"{float(x):.10G}"
        return s if ("." in s or "E" in s) else s + "."

    def pt(p) -> int:
        return add(f"CARTESIAN_POINT('',({','.join(num(c) for c in p)}))")

    def direction(d) -> int:
        return add(f"DIRECTION('',({','.join(num(c) for c in d)}))")

    V = np.asarray(mesh.vertices, float)
    vp = [add(f"VERTEX_POINT('',#{pt(p)})") for p in V]
    edges: dict[tuple[int, int], int] = {}
    for a, b in mesh.edges_unique:
        d = V[b] - V[a]
        length = float(np.linalg.norm(d))
        line = add(f"LINE('',#{pt(V[a])},#{add(f'VECTOR({chr(39)}{chr(39)},#{direction(d / length)},{num(length)})')})")
        edges[(int(a), int(b))] = add(f"EDGE_CURVE('',#{vp[a]},#{vp[b]},#{line},.T.)")
    faces = []
    for loops, normal in _planar_faces(mesh):
        bounds = []
        for k, loop in enumerate(loops):
            oes = []
            for i in range(len(loop)):
                a, b = int(loop[i]), int(loop[(i + 1) % len(loop)])
                if (a, b) in edges:
                    oes.append(add(f"ORIENTED_EDGE('',*,*,#{edges[(a, b)]},.T.)"))
                else:
                    oes.append(add(f"ORIENTED_EDGE('',*,*,#{edges[(b, a)]},.F.)"))
            el = add(f"EDGE_LOOP('',({','.join(f'#{o}' for o in oes)}))")
            bounds.append(add(f"{'FACE_OUTER_BOUND' if k == 0 else 'FACE_BOUND'}('',#{el},.T.)"))
        ref = V[loops[0][1]] - V[loops[0][0]]
        place = add(f"AXIS2_PLACEMENT_3D('',#{pt(V[loops[0][0]])},#{direction(normal)},"
                    f"#{direction(ref / np.linalg.norm(ref))})")
        plane = add(f"PLANE('',#{place})")
        faces.append(add(f"ADVANCED_FACE('',({','.join(f'#{b}' for b in bounds)}),#{plane},.T.)"))
    shell = add(f"CLOSED_SHELL('',({','.join(f'#{f}' for f in faces)}))")
    solid = add(f"MANIFOLD_SOLID_BREP('{name}',#{shell})")
    # context, units, product structure (AP214 "automotive_design")
    if units == "inch":
        mm = add("(LENGTH_UNIT()NAMED_UNIT(*)SI_UNIT(.MILLI.,.METRE.))")
        lm = add(f"LENGTH_MEASURE_WITH_UNIT(LENGTH_MEASURE(25.4),#{mm})")
        dim = add("DIMENSIONAL_EXPONENTS(1.,0.,0.,0.,0.,0.,0.)")
        length_unit = add(f"(CONVERSION_BASED_UNIT('INCH',#{lm})LENGTH_UNIT()NAMED_UNIT(#{dim}))")
    else:
        n[0] += 1
        length_unit = n[0]
        lines.append(_UNITS[units].format(u=length_unit))
    angle = add("(NAMED_UNIT(*)PLANE_ANGLE_UNIT()SI_UNIT($,.RADIAN.))")
    solid_angle = add("(NAMED_UNIT(*)SI_UNIT($,.STERADIAN.)SOLID_ANGLE_UNIT())")
    unc = add(f"UNCERTAINTY_MEASURE_WITH_UNIT(LENGTH_MEASURE(1.E-07),#{length_unit},'distance_accuracy_value','')")
    ctx = add(f"(GEOMETRIC_REPRESENTATION_CONTEXT(3)GLOBAL_UNCERTAINTY_ASSIGNED_CONTEXT((#{unc}))"
              f"GLOBAL_UNIT_ASSIGNED_CONTEXT((#{length_unit},#{angle},#{solid_angle}))"
              "REPRESENTATION_CONTEXT('',''))")
    origin = add(f"AXIS2_PLACEMENT_3D('',#{pt((0, 0, 0))},#{direction((0, 0, 1))},#{direction((1, 0, 0))})")
    rep = add(f"ADVANCED_BREP_SHAPE_REPRESENTATION('',(#{solid},#{origin}),#{ctx})")
    app = add("APPLICATION_CONTEXT('automotive design')")
    add(f"APPLICATION_PROTOCOL_DEFINITION('international standard','automotive_design',2000,#{app})")
    pctx = add(f"PRODUCT_CONTEXT('',#{app},'mechanical')")
    product = add(f"PRODUCT('{name}','{name}','',(#{pctx}))")
    formation = add(f"PRODUCT_DEFINITION_FORMATION('','',#{product})")
    dctx = add(f"PRODUCT_DEFINITION_CONTEXT('part definition',#{app},'design')")
    pdef = add(f"PRODUCT_DEFINITION('design','',#{formation},#{dctx})")
    shape = add(f"PRODUCT_DEFINITION_SHAPE('','',#{pdef})")
    add(f"SHAPE_DEFINITION_REPRESENTATION(#{shape},#{rep})")
    header = ("ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION(('" + name + "'),'2;1');\n"
              f"FILE_NAME('{name}.step','',(''),(''),'inspection-cell planning.step_export','','');\n"
              "FILE_SCHEMA(('AUTOMOTIVE_DESIGN { 1 0 10303 214 1 1 1 1 }'));\nENDSEC;\nDATA;\n")
    return header + "\n".join(lines) + "\nENDSEC;\nEND-ISO-10303-21;\n"


def _planar_faces(mesh: trimesh.Trimesh) -> list[tuple[list[list[int]], np.ndarray]]:
    """Coplanar triangles merged into planar faces: [(loops of vertex indices, outer first; unit normal)].

    The loops follow the triangles' winding (outer boundary counter-clockwise seen from outside, holes
    clockwise), so each face keeps the solid's orientation.
    """
    in_facet = np.zeros(len(mesh.faces), bool)
    groups = []
    for facet in mesh.facets:
        in_facet[facet] = True
        groups.append(np.asarray(facet))
    groups += [np.array([i]) for i in np.flatnonzero(~in_facet)]
    out = []
    for g in groups:
        tri = mesh.faces[g]
        directed = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
        inner = {tuple(e) for e in directed} & {(b, a) for a, b in directed}
        nxt = {}
        for a, b in directed:
            if (a, b) not in inner:
                nxt.setdefault(int(a), []).append(int(b))
        loops = []
        while nxt:
            start = next(iter(nxt))
            loop, v = [start], start
            while True:
                b = nxt[v].pop()
                if not nxt[v]:
                    del nxt[v]
                if b == start:
                    break
                loop.append(b)
                v = b
            loops.append(loop)
        normal = mesh.face_normals[g[0]]
        # the outer loop encloses the largest area (projected on the face's plane)
        def area(loop):
            p = mesh.vertices[loop]
            return float(np.dot(np.cross(p - p[0], np.roll(p, -1, axis=0) - p[0]).sum(axis=0), normal)) / 2
        loops.sort(key=area, reverse=True)
        out.append((loops, normal))
    return out


def write_step(mesh: trimesh.Trimesh, path: str | Path, units: str = "mm", name: str = "part") -> Path:
    path = Path(path)
    path.write_text(step_text(mesh, units, name))
    return path
