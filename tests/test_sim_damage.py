"""The simulated cell renders worn retro-reflective targets (``[sim] damaged_targets``): a dot's coating lost
beyond a chord (edge) or under a dark speck (spot) shows the target's black backing there, by exact area
coverage; PLAN's twin does not know the damage."""
import math
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.optimize import brentq

from calibration.camera import Intrinsics, invert, look_at, project
from calibration.errors import InputError, JobSpecError
from planning.part import Part, Targets
from sim_backend.coverage import (DAMAGE_EDGE, DAMAGE_SPOT, UndistortionLattice, damaged_disc_coverage,
                                  disc_coverage, segment_angle)
from sim_backend.sim_camera import Photometry, Sensor, SimCamera
from sim_backend.world import TargetDamage, World, marker_axes

# no lens distortion: a face-on dot's image is its plane scaled by f / Z, so in-plane lengths convert exactly
INTR = Intrinsics.from_focal_length(0.012, 3.45e-6, 2448, 2048)
RADIUS = 0.003
DIST = 0.3
# no part shading, no ambient light, no backing: a pixel's signal is the dot's reflective share of it
BARE = Photometry(part_level=0.0, ambient_level=0.0, marker_black_level=0.0)


def _dot_part(tilt_rad: float = 0.0, n_coded: int = 0) -> Part:
    """One plain dot at the origin (normal tilted about y) on a plate in its plane; ``n_coded`` coded targets
    beside it."""
    normal = np.array([np.sin(tilt_rad), 0.0, np.cos(tilt_rad)])
    mesh = trimesh.creation.box(extents=(0.4, 0.4, 0.01))
    mesh.apply_translation((0, 0, -0.005))
    mesh.apply_transform(trimesh.geometry.align_vectors([0, 0, 1], normal))
    n = 1 + n_coded
    xyz = np.zeros((n, 3))
    xyz[1:, 0] = 0.05 * np.arange(1, n)
    targets = Targets(ids=[f"T{i}" for i in range(n)], xyz=xyz, normals=np.tile(normal, (n, 1)),
                      kind=np.array(["retro"] + ["coded"] * n_coded), tolerance_m=np.full(n, np.nan),
                      code=np.array([-1] + list(range(n_coded))))
    return Part("dot", mesh, targets, target_diameter_m=2 * RADIUS, coded_size_m=0.02)


def _render(part: Part, damage: TargetDamage | None, part_from_cam: np.ndarray, photometry: Photometry = BARE):
    world = World(part, np.eye(4), np.eye(4), INTR, damage=damage)
    cam = SimCamera(world, photometry=photometry, sensor=Sensor(noise=False))
    return cam.render(part_from_cam, quantise=False)


def _face_on(tilt_rad: float = 0.0) -> np.ndarray:
    normal = np.array([np.sin(tilt_rad), 0.0, np.cos(tilt_rad)])
    return look_at(DIST * normal, np.zeros(3), up=(0, 1, 0))


def _window(img: np.ndarray, uv: np.ndarray, half: int):
    u0, v0 = int(round(uv[0])) - half, int(round(uv[1])) - half
    win = img[v0 : v0 + 2 * half + 1, u0 : u0 + 2 * half + 1].astype(float)
    vv, uu = np.mgrid[v0 : v0 + 2 * half + 1, u0 : u0 + 2 * half + 1]
    return win, uu, vv


def _segment_centroid_distance(f: float) -> float:
    """Centroid distance from the disc's centre (in radii) of the circular segment holding the share ``f`` of the
    disc's area: its central angle from (theta - sin theta) / (2 pi) = f, solved independently of the renderer."""
    theta = brentq(lambda x: (x - math.sin(x)) / (2 * math.pi) - f, 1e-9, 2 * math.pi)
    return 4 * math.sin(theta / 2) ** 3 / (3 * (theta - math.sin(theta)))


CASES = {"edge": dict(kind="edge", lost=0.12, direction_rad=np.radians(30.0), offset=0.0),
         "spot": dict(kind="spot", lost=0.08, direction_rad=np.radians(-120.0), offset=0.45)}


def _damage(n: int, case: dict) -> TargetDamage:
    return TargetDamage.of(n, [0], [case["kind"]], [case["lost"]], [case["direction_rad"]], [case["offset"]])


@pytest.mark.parametrize("tilt_deg", [0.0, 45.0])
@pytest.mark.parametrize("name", ["edge", "spot"])
def test_damaged_dot_signal_is_its_reflective_share_of_the_intact_dot(name, tilt_deg):
    """Noise off, no ground and no backing: the dot's summed signal is (1 - lost) of the intact dot's, whatever
    the view; with the backing, the lost part adds the backing's level over it."""
    case, tilt = CASES[name], np.radians(tilt_deg)
    part, T = _dot_part(tilt), look_at(np.array([0.02, -0.03, DIST]), np.zeros(3), up=(0, 1, 0))
    intact, truth = _render(part, None, T)
    worn, truth_worn = _render(part, _damage(1, case), T)
    uv = np.array(truth["uv"][0])
    assert truth_worn["damaged_ids"] == ["T0"] and truth["damaged_ids"] == []
    s_intact, s_worn = (_window(img, uv, 50)[0].sum() for img in (intact, worn))
    assert s_worn / s_intact == pytest.approx(1 - case["lost"], rel=0.01)  # tilted: the image's area, not the plane's
    if tilt_deg == 0.0:
        assert s_worn / s_intact == pytest.approx(1 - case["lost"], rel=1e-3)  # exact coverage: far inside the 1 %
        backed = Photometry(part_level=0.0, ambient_level=0.0)
        to_cam = invert(T)[:3, 3]
        cos_inc = abs(part.targets.normals[0] @ to_cam) / np.linalg.norm(to_cam)
        black_per_level = backed.marker_black_level / (backed.retro_level * cos_inc ** (backed.falloff_exponent - 1))
        b_intact, b_worn = (_window(_render(part, d, T, backed)[0], uv, 50)[0].sum() for d in (None, _damage(1, case)))
        expected = 1 - case["lost"] + case["lost"] * black_per_level
        assert b_worn / b_intact == pytest.approx(expected, rel=2e-3)


@pytest.mark.parametrize("lost", [0.02, 0.1, 0.3])
def test_edge_cut_moves_the_dots_centroid_by_the_analytic_amount_away_from_the_cut(lost):
    """A disc less a segment of area share f has its centroid f / (1 - f) * d_seg from its centre, opposite the
    cut (d_seg = 4 R sin^3(theta/2) / (3 (theta - sin theta)), the segment's centroid): seen face-on, that distance
    times f / Z in pixels, towards -(cos phi e1 + sin phi e2)."""
    phi = np.radians(30.0)
    part, T = _dot_part(), _face_on()
    case = dict(kind="edge", lost=lost, direction_rad=phi, offset=0.0)
    intact, truth = _render(part, None, T)
    worn, _ = _render(part, _damage(1, case), T)
    uv = np.array(truth["uv"][0])

    def centroid(img):
        win, uu, vv = _window(img, uv, 50)
        return np.array([(win * uu).sum(), (win * vv).sum()]) / win.sum()

    moved = centroid(worn) - centroid(intact)
    offset_m = lost / (1 - lost) * _segment_centroid_distance(lost) * RADIUS
    e1, e2 = marker_axes(part.targets.normals[:1])
    expected = project(INTR, invert(T), -offset_m * (np.cos(phi) * e1 + np.sin(phi) * e2))[0] - uv
    assert np.linalg.norm(expected) == pytest.approx(INTR.fx_px * offset_m / DIST, rel=1e-9)  # the pixel scale
    assert np.linalg.norm(moved - expected) < 0.02 * np.linalg.norm(expected), (moved, expected)


def test_spot_moves_the_dots_centroid_away_from_the_speck():
    """A speck of area share f at o R from the centre moves the reflective area's centroid by f o R / (1 - f)."""
    case = CASES["spot"]
    part, T = _dot_part(), _face_on()
    intact, truth = _render(part, None, T)
    worn, _ = _render(part, _damage(1, case), T)
    uv = np.array(truth["uv"][0])
    c = [np.array([(w * uu).sum(), (w * vv).sum()]) / w.sum() for w, uu, vv in
         (_window(img, uv, 50) for img in (intact, worn))]
    offset_m = case["lost"] * case["offset"] * RADIUS / (1 - case["lost"])
    e1, e2 = marker_axes(part.targets.normals[:1])
    d = np.cos(case["direction_rad"]) * e1 + np.sin(case["direction_rad"]) * e2
    expected = project(INTR, invert(T), -offset_m * d)[0] - uv
    assert np.linalg.norm(c[1] - c[0] - expected) < 0.02 * np.linalg.norm(expected)


def test_kernel_keeps_the_whole_disc_as_alpha_and_supersamples_the_chord():
    """The damaged kernel's alpha is the intact disc's coverage; its white is the reflective remainder, exact to
    the supersampling along the chord (no staircase: the area matches for chords at any angle); no damage: white
    is alpha."""
    lattice = UndistortionLattice(INTR)
    cam_centre = np.array([[0.0008, -0.0005, DIST]])
    normal, e1, e2 = np.array([[0.0, 0.0, -1.0]]), np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]])
    uv = project(INTR, np.eye(4), cam_centre)[0]
    u0, v0 = np.floor(uv - 45).astype(int)
    args = (lattice, np.array([u0]), np.array([v0]), 96, 96, cam_centre, normal, e1, e2, RADIUS)
    alpha0 = disc_coverage(*args, np.zeros((1, 2)))
    shares = []
    for deg in np.arange(0.0, 180.0, 7.0):
        alpha, white = damaged_disc_coverage(*args, np.array([DAMAGE_EDGE]), np.array([0.05]),
                                             np.array([np.radians(deg)]), np.zeros(1), np.zeros((1, 2)))
        np.testing.assert_array_equal(alpha, alpha0)
        assert np.all(white <= alpha) and np.all(white >= 0)
        shares.append(1 - white.sum() / alpha.sum())
    assert np.max(np.abs(np.array(shares) - 0.05)) < 2e-4, shares
    alpha, white = damaged_disc_coverage(*args, np.zeros(1, dtype=np.int8), np.zeros(1), np.zeros(1), np.zeros(1),
                                         np.zeros((1, 2)))
    np.testing.assert_array_equal(white, alpha)
    np.testing.assert_array_equal(alpha, alpha0)
    alpha, white = damaged_disc_coverage(*args, np.array([DAMAGE_SPOT]), np.array([0.1]), np.array([1.0]),
                                         np.array([0.5]), np.zeros((1, 2)))
    assert 1 - white.sum() / alpha.sum() == pytest.approx(0.1, abs=2e-4)
    f = np.array([0.01, 0.2, 0.5])
    theta = segment_angle(f)
    np.testing.assert_allclose((theta - np.sin(theta)) / (2 * np.pi), f, atol=1e-12)


def test_world_refuses_damage_it_cannot_render():
    part = _dot_part(n_coded=1)
    with pytest.raises(InputError, match="T0: the spot reaches 1.000 dot radii"):
        World(part, np.eye(4), np.eye(4), INTR, damage=TargetDamage.of(2, [0], ["spot"], [0.25], [0.0], [0.5]))
    with pytest.raises(InputError, match="T1: it is a coded target"):
        World(part, np.eye(4), np.eye(4), INTR, damage=TargetDamage.of(2, [1], ["edge"], [0.1], [0.0], [0.0]))
    with pytest.raises(InputError, match="T0: lost 0.6 is outside"):
        World(part, np.eye(4), np.eye(4), INTR, damage=TargetDamage.of(2, [0], ["edge"], [0.6], [0.0], [0.0]))
    with pytest.raises(InputError, match=r"finite \(2,\) array"):
        World(part, np.eye(4), np.eye(4), INTR, damage=TargetDamage.none(3))
    w = World(part, np.eye(4), np.eye(4), INTR)
    assert w.damage_kind.dtype == np.int8 and not w.damage_kind.any() and w.damage_lost.shape == (2,)


# --- the job: [sim] damaged_targets reaches the simulated cell, not PLAN's twin ------------------------------------

POSE = look_at(np.array([0.25, -0.35, 0.45]), np.zeros(3))


def test_job_damage_reaches_the_simulated_cell_and_not_plans_twin(tmp_path):
    """The simulated cell renders the job's worn dots (only their pixels change); PLAN's twin renders the nominal
    part, the same image as for the job without damage."""
    from cell.devices import make_job_sim_cell
    from cell.loadedjob import load
    from cell.stages.preanalysis import twin_camera
    from jobutil import job_variant

    plain = load(job_variant(tmp_path / "plain"))
    cell_plain = make_job_sim_cell(plain).camera
    before, truth = cell_plain.render(POSE, noise=False, quantise=False)
    ids = [i for i, k in zip(truth["ids"], truth["kind"]) if k == "retro" and i not in truth["partial_ids"]][:2]
    damaged = [{"id": ids[0], "kind": "edge", "lost": 0.2, "direction_deg": 30.0},
               {"id": ids[1], "kind": "spot", "lost": 0.1, "direction_deg": 100.0, "offset": 0.4}]
    job = load(job_variant(tmp_path / "worn", {"sim": {"damaged_targets": damaged}}))
    assert [(job.part.targets.ids[i], d.kind) for i, d in job.damaged_targets] == [(ids[0], "edge"), (ids[1], "spot")]
    cam = make_job_sim_cell(job).camera
    w = cam.world
    hurt = np.flatnonzero(w.damage_kind)
    assert [job.part.targets.ids[i] for i in hurt] == ids and list(w.damage_kind[hurt]) == [DAMAGE_EDGE, DAMAGE_SPOT]
    np.testing.assert_allclose(w.damage_dir_rad[hurt], np.radians([30.0, 100.0]))
    after, truth_after = cam.render(POSE, noise=False, quantise=False)
    assert truth_after["damaged_ids"] == ids
    changed = np.argwhere(after != before)[:, ::-1]  # (u, v)
    uv = np.array([truth["uv"][truth["ids"].index(i)] for i in ids])
    assert len(changed) > 20
    assert np.all(np.min(np.linalg.norm(changed[:, None] - uv[None], axis=2), axis=1) < 25)  # only the worn dots
    assert np.all(after[changed[:, 1], changed[:, 0]] < before[changed[:, 1], changed[:, 0]])  # darker there
    twin_plain, twin_worn = twin_camera(plain), twin_camera(job)
    assert not twin_worn.world.damage_kind.any()
    np.testing.assert_array_equal(twin_worn.render(POSE, noise=False, quantise=False)[0],
                                  twin_plain.render(POSE, noise=False, quantise=False)[0])


@pytest.mark.parametrize("entries,message", [
    ([{"id": "T9999", "kind": "edge", "lost": 0.1}],
     "sim.damaged_targets[0].id = 'T9999' names a target the part does not have"),
    ([{"id": "C0", "kind": "spot", "lost": 0.1}], "sim.damaged_targets[0].id = 'C0' is a coded target"),
    ([{"id": "T0002", "kind": "edge", "lost": 0.1}, {"id": "T0002", "kind": "spot", "lost": 0.05}],
     "sim.damaged_targets[1].id = 'T0002' is damaged already by sim.damaged_targets[0]"),
    ([{"id": "T0002", "kind": "edge", "lost": 0.7}],
     "'sim.damaged_targets[0].lost' = 0.7: the share of the dot's area that lost its coating must be 0 < lost <= 0.5"),
    ([{"id": "T0002", "kind": "spot", "lost": 0.0}], "'sim.damaged_targets[0].lost' = 0.0: the share"),
    ([{"id": "T0002", "kind": "spot", "lost": 0.25, "offset": 0.5}],
     "'sim.damaged_targets[0]': the spot of T0002 (lost = 0.25: radius 0.500 dot radii, offset = 0.5) reaches "
     "1.000 dot radii from the centre: it must lie inside the dot"),
    ([{"id": "T0002", "kind": "edge", "lost": 0.1, "offset": 0.5}], "offset = 0.5 places a spot"),
    ([{"id": "T0002", "kind": "scratch", "lost": 0.1}], "'sim.damaged_targets[0].kind' = 'scratch'"),
])
def test_bad_damaged_targets_are_one_line_naming_the_key_and_value(tmp_path, entries, message):
    from cell.loadedjob import load
    from jobutil import job_variant

    path = job_variant(tmp_path / "job", {"sim": {"damaged_targets": entries}})
    with pytest.raises(JobSpecError) as e:
        load(path)
    assert message in str(e.value) and str(path) in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_spot_reaching_exactly_the_limit_loads(tmp_path):
    from cell.loadedjob import load
    from jobutil import job_variant

    entries = [{"id": "T0002", "kind": "spot", "lost": 0.25, "offset": 0.45, "direction_deg": -90.0}]
    job = load(job_variant(Path(tmp_path) / "job", {"sim": {"damaged_targets": entries}}))
    assert job.summary()["sim_damaged_targets"] == 1


def test_a_cell_file_refuses_damaged_targets(tmp_path):
    """Worn dots belong to a part: the cell file's [sim] (shared by every job of the cell) refuses them."""
    import shutil

    from cell.cellcal.cellfile import load_cell_file

    example = Path(__file__).resolve().parents[1] / "examples" / "cell"
    for f in example.iterdir():
        if f.suffix in (".toml", ".stl", ".csv"):
            shutil.copy(f, tmp_path / f.name)
    cell = tmp_path / "cell.toml"
    text = cell.read_text()
    assert re.findall(r"(?m)^\[(\w+)\]", text)[-1] == "sim"  # the appended line lands in [sim]
    cell.write_text(text + 'damaged_targets = [{ id = "T0001", kind = "edge", lost = 0.1 }]\n')
    with pytest.raises(JobSpecError, match="sim.damaged_targets belongs in a job file"):
        load_cell_file(cell)
