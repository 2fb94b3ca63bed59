"""Viewing-sphere parameterisation of stations and candidate generation."""
import numpy as np
import pytest

from calibration.camera import Intrinsics, look_at, project, invert
from calibration.errors import PlanningError
from planning.part import Part, make_bracket, sample_targets
from planning.stations import N_GENES, ViewingSphere, fibonacci_band

CENTRE = (0.01, -0.02, 0.09)


def sphere(**kw) -> ViewingSphere:
    args = dict(centre=CENTRE, distance_min_m=0.5, distance_max_m=1.0,
                elevation_min_rad=np.deg2rad(-30), elevation_max_rad=np.pi / 2, max_offset_m=0.05)
    args.update(kw)
    return ViewingSphere(**args)


def random_genes(s: ViewingSphere, rng: np.random.Generator, n: int) -> np.ndarray:
    return s.lower + rng.random((n, N_GENES)) * (s.upper - s.lower)


def test_pose_puts_camera_at_distance_with_a_right_handed_rotation():
    s = sphere()
    g = random_genes(s, np.random.default_rng(0), 200)
    T = s.poses(g)
    assert T.shape == (200, 4, 4)
    R = T[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(T[:, :3, 3] - CENTRE, axis=1), g[:, 2], rtol=1e-12)
    az, el = g[:, 0], g[:, 1]
    direction = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    np.testing.assert_allclose((T[:, :3, 3] - CENTRE) / g[:, 2:3], direction, atol=1e-12)


def test_zero_offset_pose_equals_look_at_with_z_up_and_roll():
    s = sphere()
    rng = np.random.default_rng(1)
    for _ in range(20):
        g = random_genes(s, rng, 1)[0]
        g[1] = rng.uniform(-1.2, 1.2)  # away from the pole where look_at switches its up vector
        g[4:] = 0.0
        T = s.poses(g)
        ref = look_at(T[:3, 3], np.array(CENTRE), up=(0.0, 0.0, 1.0), roll_rad=g[3])
        np.testing.assert_allclose(T, ref, atol=1e-12)


def test_offset_genes_move_the_aim_point_onto_the_optical_axis():
    s = sphere()
    g = np.array([0.3, 0.4, 0.8, 0.0, 0.0, 0.0])
    base = s.poses(g)
    x0, y0 = base[:3, 0], base[:3, 1]
    g_off = g.copy()
    g_off[4:] = (0.03, -0.02)
    g_off[3] = 0.7  # roll must not move the optical axis
    T = s.poses(g_off)
    aim = np.array(CENTRE) + 0.03 * x0 - 0.02 * y0
    intr = Intrinsics(fx_px=1000, fy_px=1000, cx_px=320, cy_px=240, width=640, height=480)
    uv = project(intr, invert(T), aim[None])[0]
    np.testing.assert_allclose(uv, (320, 240), atol=1e-9)
    # the un-offset centre now images off the principal point, by about offset * f / distance
    uv_c = project(intr, invert(T), np.array([CENTRE]))[0]
    assert np.hypot(*(uv_c - (320, 240))) == pytest.approx(np.hypot(0.03, 0.02) * 1000 / 0.8, rel=0.05)


def test_pose_is_continuous_through_the_pole():
    s = sphere()
    g = np.array([[0.7, np.pi / 2, 0.8, 0.1, 0.01, 0.0], [0.7, np.pi / 2 - 1e-7, 0.8, 0.1, 0.01, 0.0]])
    T = s.poses(g)
    assert np.all(np.isfinite(T))
    np.testing.assert_allclose(T[0], T[1], atol=1e-6)


def test_candidates_are_inside_bounds_and_cover_the_band_evenly():
    s = sphere(elevation_min_rad=np.deg2rad(10), elevation_max_rad=np.deg2rad(80))
    n, shells = 800, 3
    g = s.candidates(n, shells)
    assert g.shape == (n * shells, N_GENES)
    assert np.all(g >= s.lower - 1e-12) and np.all(g <= s.upper + 1e-12)
    np.testing.assert_array_equal(np.unique(g[:, 2]), np.linspace(0.5, 1.0, shells))
    assert np.all(g[:, 3:] == 0)
    # equal area: the share of directions above an elevation matches the share of band area
    el = g[:n, 1]
    mid = np.deg2rad(45)
    share = np.sin([np.deg2rad(10), mid, np.deg2rad(80)])
    assert np.mean(el > mid) == pytest.approx((share[2] - share[1]) / (share[2] - share[0]), abs=0.01)
    # covering: every direction in the band is within ~1.5 mean spacings of a candidate
    dirs = s.eyes(g[:n]) - CENTRE
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    probe = fibonacci_band(5000, np.deg2rad(10), np.deg2rad(80))
    pd = np.stack([np.cos(probe[:, 1]) * np.cos(probe[:, 0]), np.cos(probe[:, 1]) * np.sin(probe[:, 0]), np.sin(probe[:, 1])], 1)
    worst = np.arccos(np.clip((pd @ dirs.T).max(axis=1), -1, 1)).max()
    band_area = 2 * np.pi * (share[2] - share[0])
    assert worst < 1.5 * np.sqrt(band_area / n)


def test_for_part_sizes_the_sphere_so_the_part_fits_in_the_image():
    mesh = make_bracket()
    part = Part("bracket", mesh, sample_targets(mesh, 50, np.random.default_rng(0)))
    intr = Intrinsics.from_focal_length(0.012, 3.45e-6, 2448, 2048)
    s = ViewingSphere.for_part(part, intr, fill=0.7)
    assert s.distance_min_m > part.radius
    # at the nominal distance the bounding sphere spans 'fill' of the short image side
    nominal = s.distance_min_m / 0.75
    assert part.radius * intr.fy_px / nominal == pytest.approx(0.7 * 1024, rel=1e-9)
    # from every candidate at the far shell, the whole part images inside the frame
    far = s.candidates(60, 1)
    far[:, 2] = s.distance_max_m
    for T in s.poses(far):
        uv = project(intr, invert(T), mesh.vertices)
        assert np.all(intr.in_image(uv))


def test_bad_sphere_or_genes_raise_planning_error():
    with pytest.raises(PlanningError, match="distance"):
        sphere(distance_min_m=1.0, distance_max_m=0.5)
    with pytest.raises(PlanningError, match="elevation"):
        sphere(elevation_max_rad=2.0)
    with pytest.raises(PlanningError, match="genes"):
        sphere().poses(np.zeros((3, 4)))
    s = sphere()
    assert s.lower.shape == s.upper.shape == (N_GENES,)
    assert np.all(s.lower <= s.upper)
