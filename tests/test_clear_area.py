"""planning.clear_area: the clear flat surface around a target, against plates and a skin whose edges are known."""
from __future__ import annotations

import numpy as np
import trimesh

from planning.clear_area import clear_radius, disc_on_surface

RADII = np.array([2.0, 4.0, 6.0, 8.0, 10.0, 12.0])  # mm


def _plate():
    return trimesh.creation.box(extents=(200.0, 100.0, 10.0))  # top face at z = 5, edges at x = +-100, y = +-50


def test_the_clear_radius_is_the_distance_to_the_nearest_edge():
    mesh = _plate()
    up = np.array([0.0, 0.0, 1.0])
    pts = np.array([[0.0, 0.0, 5.0], [95.5, 0.0, 5.0], [0.0, -43.0, 5.0], [-91.0, 41.0, 5.0]])
    r = clear_radius(mesh, pts, np.tile(up, (4, 1)), RADII)
    # 4.5 mm from x = 100; 7 mm from y = -50; 9 mm from both x = -100 and y = 50
    np.testing.assert_array_equal(r, [12.0, 4.0, 6.0, 8.0])


def test_a_step_on_the_face_is_an_edge_too():
    """A plate 10 mm thick up to x = 20, 16 mm beyond (two boxes meeting at the step, no face hidden under another)."""
    low = trimesh.creation.box(extents=(120.0, 100.0, 10.0), transform=trimesh.transformations.translation_matrix((-40.0, 0.0, 5.0)))
    high = trimesh.creation.box(extents=(80.0, 100.0, 16.0), transform=trimesh.transformations.translation_matrix((60.0, 0.0, 8.0)))
    mesh = trimesh.util.concatenate([low, high])
    up = np.array([[0.0, 0.0, 1.0]])
    assert clear_radius(mesh, [[12.0, 0.0, 10.0]], up, RADII)[0] == 8.0  # the step's wall at x = 20
    assert clear_radius(mesh, [[29.0, 0.0, 16.0]], up, RADII)[0] == 8.0  # on the high side: its edge 9 mm away
    assert not disc_on_surface(mesh, [[12.0, 0.0, 10.0]], up, 10.0, 0.5, 0.98)[0]


def test_a_gently_curved_skin_is_clear_and_its_outline_is_not():
    box = trimesh.creation.box(extents=(300.0, 200.0, 8.0))
    v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=6.0)
    v = v.copy()
    v[:, 2] += 40.0 * (2 * v[:, 0] / 300.0) ** 2  # a skin bent about y: radius of curvature ~280 mm
    skin = trimesh.Trimesh(v, f, process=True)

    def on_top(x, y):
        z = 4.0 + 40.0 * (2 * x / 300.0) ** 2
        n = np.array([-40.0 * 8 * x / 300.0**2, 0.0, 1.0])
        return np.array([x, y, z]), n / np.linalg.norm(n)

    p0, n0 = on_top(60.0, 0.0)
    p1, n1 = on_top(60.0, 95.0)  # 5 mm from the long edge
    r = clear_radius(skin, np.array([p0, p1]), np.array([n0, n1]), RADII)
    assert r[0] == 12.0 and r[1] == 4.0, r


def test_planning_warns_when_a_scale_bar_end_has_an_edge_close_by(monkeypatch):
    """planning.scalebar.ends_clear / bar_warnings (metres, as the cell works): a 5 mm dot 4 mm from the plate's
    outline is named with the edge's distance; one in the middle is clear and says nothing."""
    from types import SimpleNamespace

    from planning.scalebar import bar_warnings, ends_clear

    mesh = trimesh.creation.box(extents=(0.2, 0.1, 0.01))
    targets = SimpleNamespace(ids=np.array(["T1", "T2"]), xyz=np.array([[0.0, 0.0, 0.005], [0.096, 0.0, 0.005]]),
                              normals=np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]))
    part = SimpleNamespace(mesh=mesh, targets=targets, target_diameter_m=0.005)
    facts = ends_clear(part, [0, 1])
    assert facts[0]["clear"] and facts[0]["edge_within_m"] is None
    assert not facts[1]["clear"] and facts[1]["edge_within_m"] == 0.005  # 4 mm: inside the 5 mm disc, not the 2.5
    doc = {"ends": ["T1", "T2"], "met": True, "requirement": {"rays_min": 6}, "candidates_seeing_end": [20, 20],
           "ends_clear": facts}
    import planning.scalebar as sb

    monkeypatch.setattr(sb, "bar_line", lambda d: "bar line")  # the bar's own line is tested in test_scalebar.py
    lines = bar_warnings(doc)
    edge = [line for level, line in lines if "edge of the part" in line]
    assert len(edge) == 1 and "5.0 mm of T2" in edge[0] and "T1" not in edge[0].split("within")[1]
