"""SimCamera renders images whose targets sit where the true geometry puts them."""
import cv2
import numpy as np
import pytest
import trimesh

from calibration.camera import Intrinsics, invert, look_at, project
from calibration.errors import DriverError, InputError, NotConnectedError
from drivers.protocols import Camera
from planning.part import Part, Targets
from sim_backend.sim_camera import (
    Photometry,
    RenderOptions,
    Sensor,
    SimCamera,
    UndistortionLattice,
    _plane_coords,
    aruco_texture,
    disc_coverage,
    marker_coverage,
)
from sim_backend.world import World, marker_axes

# the default camera: 5 MP, 3.45 um pixels, 12 mm lens; a mild lens distortion
INTR = Intrinsics.from_focal_length(0.012, 3.45e-6, 2448, 2048, k1=-0.08, k2=0.05, p1=2e-4, p2=-1e-4)
RADIUS = 0.003
DARK = Photometry(part_level=0.0, ambient_level=0.0)


def _targets(xyz, normals=None, kind=None, code=None):
    n = len(xyz)
    return Targets(
        ids=[f"T{i}" for i in range(n)],
        xyz=np.asarray(xyz, float),
        normals=np.tile([0.0, 0.0, 1.0], (n, 1)) if normals is None else np.asarray(normals, float),
        kind=np.array(["retro"] * n) if kind is None else np.asarray(kind),
        tolerance_m=np.full(n, np.nan),
        code=np.full(n, -1) if code is None else np.asarray(code),
    )


def _plate(targets, extra=()):
    plate = trimesh.creation.box(extents=(0.5, 0.4, 0.02))
    plate.apply_translation((0, 0, -0.01))
    mesh = trimesh.util.concatenate([plate, *extra]) if extra else plate
    return Part("plate", mesh, targets, target_diameter_m=2 * RADIUS, coded_size_m=0.02)


def _tilted_single_target(tilt_rad):
    """One disc at the origin with its normal tilted about y, on a thin plate in its plane."""
    n = np.array([np.sin(tilt_rad), 0.0, np.cos(tilt_rad)])
    mesh = trimesh.creation.box(extents=(0.4, 0.4, 0.01))
    mesh.apply_translation((0, 0, -0.005))
    R = trimesh.geometry.align_vectors([0, 0, 1], n)
    mesh.apply_transform(R)
    return Part("disc", mesh, _targets(np.zeros((1, 3)), n[None]), target_diameter_m=2 * RADIUS)


def _region_centroid(intr, cam_from_part, centre, normal, radius, n=20000):
    """Exact centroid of the image region of a disc: shoelace on 20k projected rim points."""
    e1, e2 = marker_axes(np.asarray(normal)[None])
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rim = centre + radius * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2)
    uv = project(intr, cam_from_part, rim)
    x, y = uv[:, 0], uv[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    c = x * y1 - x1 * y
    return np.array([((x + x1) * c).sum(), ((y + y1) * c).sum()]) / (3 * c.sum())


def _window(img, uv, half):
    """The window about ``uv`` less the median of its border (clipped at 0), and its pixels' (u, v) grids."""
    u0, v0 = int(round(uv[0])) - half, int(round(uv[1])) - half
    win = img[v0 : v0 + 2 * half + 1, u0 : u0 + 2 * half + 1].astype(float)
    border = np.concatenate([win[0], win[-1], win[:, 0], win[:, -1]])
    vv, uu = np.mgrid[v0 : v0 + 2 * half + 1, u0 : u0 + 2 * half + 1]
    return np.clip(win - np.median(border), 0.0, None), uu, vv


def _centroid(img, uv, half):
    """Intensity-weighted centroid in a window, background = median of the window's border."""
    win, uu, vv = _window(img, uv, half)
    return np.array([(win * uu).sum(), (win * vv).sum()]) / win.sum()


def _perspective_bias_px(f_px, radius, dist, tilt):
    """First-order offset of a disc's image centroid from its projected centre, on axis."""
    return f_px * radius**2 * np.sin(tilt) * np.cos(tilt) / dist**2


@pytest.mark.parametrize("tilt_deg", [0, 30, 60])
@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.2, 0.15)])
def test_rendered_disc_centroid_equals_exact_image_region_centroid(tilt_deg, offset):
    """Supersampled coverage, distortion and blur together move the centroid by < 0.005 px."""
    part = _tilted_single_target(np.radians(tilt_deg))
    cam = SimCamera(World(part, np.eye(4), np.eye(4), INTR), sensor=Sensor(noise=False), photometry=DARK)
    part_from_cam = look_at(np.array([0, 0, 0.7]), np.array([-offset[0], -offset[1], 0.0]), up=(0, 1, 0))
    img, truth = cam.render(part_from_cam, quantise=False)
    uv = np.array(truth["uv"][0])
    exact = _region_centroid(INTR, invert(part_from_cam), np.zeros(3), part.targets.normals[0], RADIUS)
    assert np.linalg.norm(_centroid(img, uv, 30) - exact) < 0.005


@pytest.mark.parametrize("tilt_deg", [20, 40, 60])
def test_perspective_bias_of_a_disc_centroid_follows_the_first_order_formula(tilt_deg):
    """The gap between image centroid and projected centre is geometry, not a render error."""
    tilt = np.radians(tilt_deg)
    part = _tilted_single_target(tilt)
    part_from_cam = look_at(np.array([0, 0, 0.7]), np.zeros(3), up=(0, 1, 0))
    exact = _region_centroid(INTR, invert(part_from_cam), np.zeros(3), part.targets.normals[0], RADIUS)
    uv = project(INTR, invert(part_from_cam), np.zeros((1, 3)))[0]
    expected = _perspective_bias_px(INTR.fx_px, RADIUS, 0.7, tilt)
    assert abs(np.linalg.norm(exact - uv) - expected) < 0.1 * expected


@pytest.mark.parametrize("tilt_deg", [0, 10, 15])
def test_noise_free_centroid_lies_within_0p02_px_of_true_projection(tilt_deg):
    tilt = np.radians(tilt_deg)
    # honest: at this geometry the perspective bias alone stays below the tolerance
    assert _perspective_bias_px(INTR.fx_px, RADIUS, 0.7, tilt) < 0.016
    part = _tilted_single_target(tilt)
    cam = SimCamera(World(part, np.eye(4), np.eye(4), INTR), sensor=Sensor(noise=False))
    part_from_cam = look_at(np.array([0, 0, 0.7]), np.array([-0.1, 0.05, 0.0]), up=(0, 1, 0))
    img, truth = cam.render(part_from_cam)  # quantised 8-bit, part background on
    uv = np.array(truth["uv"][0])
    assert np.linalg.norm(_centroid(img, uv, 24) - uv) < 0.02


def _field_part():
    g = np.linspace(-0.15, 0.15, 9)
    gx, gy = np.meshgrid(g, np.linspace(-0.12, 0.12, 7))
    xyz = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    return _plate(_targets(xyz))


FIELD_POSE = look_at(np.array([0.05, -0.03, 0.7]), np.zeros(3), up=(0, 1, 0))


def test_field_of_targets_at_nominal_noise_has_rms_centroid_error_below_0p02_px():
    cam = SimCamera(World(_field_part(), np.eye(4), np.eye(4), INTR, seed=4))
    errs = []
    for _ in range(4):
        img, truth = cam.render(FIELD_POSE)
        assert img.dtype == np.uint8
        errs += [_centroid(img, uv, 20) - uv for uv in np.array(truth["uv"])]
    errs = np.array(errs)
    assert len(errs) == 4 * 63
    assert np.sqrt(np.mean(np.sum(errs**2, axis=1))) <= 0.02


def test_image_sigma_px_displaces_each_target_image_by_the_recorded_jitter():
    cam = SimCamera(World(_field_part(), np.eye(4), np.eye(4), INTR, seed=5), options=RenderOptions(image_sigma_px=0.1))
    img, truth = cam.render(FIELD_POSE)
    uv, shift = np.array(truth["uv"]), np.array(truth["shift_px"])
    c = np.array([_centroid(img, p, 20) for p in uv])
    assert np.sqrt(np.mean((c - uv - shift) ** 2)) < 0.015  # per axis, around the jittered position
    assert 0.07 < np.std(c - uv) < 0.13


def test_occluded_targets_are_not_rendered_and_half_hidden_ones_are_partial():
    wall = trimesh.creation.box(extents=(0.02, 0.4, 0.1))
    wall.apply_translation((0, 0, 0.05))
    # camera at (0.3, 0, 0.5): the wall hides x in (-0.0875, -0.01) on the plate
    xyz = [[0.05, 0, 0], [-0.05, 0, 0], [-0.0875, 0, 0], [-0.13, 0, 0]]
    pose = look_at(np.array([0.3, 0.0, 0.5]), np.array([-0.04, 0.0, 0.0]), up=(0, 1, 0))
    renders = []
    for extra in ([wall], []):
        part = _plate(_targets(xyz), extra=extra)
        cam = SimCamera(World(part, np.eye(4), np.eye(4), INTR), sensor=Sensor(noise=False), photometry=DARK)
        renders.append(cam.render(pose, quantise=False))
    (img, truth), (img_free, truth_free) = renders
    assert truth_free["ids"] == ["T0", "T1", "T2", "T3"] and truth_free["partial_ids"] == []
    assert truth["ids"] == ["T0", "T2", "T3"]
    assert truth["occluded_ids"] == ["T1"] and truth["partial_ids"] == ["T2"]
    uv = project(INTR, invert(pose), np.array(xyz, float))

    def energy(im, p):
        u, v = np.round(p).astype(int)
        return im[v - 25 : v + 26, u - 25 : u + 26].sum()

    ratio = [energy(img, p) / energy(img_free, p) for p in uv]
    assert abs(ratio[0] - 1) < 1e-6 and abs(ratio[3] - 1) < 1e-6
    assert ratio[1] < 1e-6
    assert 0.2 < ratio[2] < 0.8


def test_targets_facing_away_are_not_rendered():
    xyz = [[0.0, 0.0, 0.0], [0.05, 0.0, -0.02]]
    normals = [[0, 0, 1.0], [0, 0, -1.0]]
    cam = SimCamera(World(_plate(_targets(xyz, normals)), np.eye(4), np.eye(4), INTR), sensor=Sensor(noise=False))
    _, truth = cam.render(look_at(np.array([0, 0, 0.7]), np.zeros(3), up=(0, 1, 0)))
    assert truth["ids"] == ["T0"] and truth["occluded_ids"] == []


def _brute_force_plane_coords(intr, u0, v0, h, w, n_sub, centre_c, n_c, e1_c, e2_c):
    """Plane coordinates of n_sub^2 samples per pixel, exact undistortion per sample."""
    sub = (np.arange(n_sub) + 0.5) / n_sub - 0.5
    uu = (u0 + np.arange(w))[None, :, None, None] + sub[None, None, None, :]
    vv = (v0 + np.arange(h))[:, None, None, None] + sub[None, None, :, None]
    uu, vv = np.broadcast_arrays(uu, vv)
    xy = intr.pixel_to_normalised(np.stack([uu.ravel(), vv.ravel()], 1)).reshape(1, h, w, n_sub, n_sub, 2)
    return _plane_coords(xy, centre_c, e1_c, e2_c, n_c)[0]


def _oblique_setup(centre):
    normal = np.array([0.2, -0.3, 1.0]) / np.linalg.norm([0.2, -0.3, 1.0])
    cam_from_part = invert(look_at(np.array([0.25, 0.2, 0.6]), np.zeros(3), up=(0, 1, 0)))
    R, t = cam_from_part[:3, :3], cam_from_part[:3, 3]
    e1, e2 = marker_axes(normal[None])
    uv = project(INTR, cam_from_part, centre[None])[0]
    return (centre @ R.T + t)[None], (normal @ R.T)[None], e1 @ R.T, e2 @ R.T, uv


def test_disc_kernel_matches_brute_force_exact_raster():
    cc, nc, e1c, e2c, uv = _oblique_setup(np.array([0.01, 0.02, 0.0]))
    u0, v0, h, w = int(uv[0]) - 25, int(uv[1]) - 25, 50, 50
    cov = disc_coverage(UndistortionLattice(INTR), np.array([u0]), np.array([v0]), h, w, cc, nc, e1c, e2c,
                        RADIUS, np.zeros((1, 2)))[0]
    st = _brute_force_plane_coords(INTR, u0, v0, h, w, 24, cc, nc, e1c, e2c)
    ref = (np.sum(st**2, axis=-1) <= RADIUS**2).mean(axis=(-1, -2))
    vv, uu = np.mgrid[v0 : v0 + h, u0 : u0 + w]
    c = np.array([(cov * uu).sum(), (cov * vv).sum()]) / cov.sum()
    c_ref = np.array([(ref * uu).sum(), (ref * vv).sum()]) / ref.sum()
    assert np.abs(cov - ref).max() < 0.06  # sub-sample quantisation of boundary pixels only
    assert abs(cov.sum() - ref.sum()) < 0.01 * ref.sum()
    assert np.linalg.norm(c - c_ref) < 0.003


def test_marker_kernel_matches_brute_force_exact_raster():
    cc, nc, e1c, e2c, uv = _oblique_setup(np.array([0.01, 0.02, 0.0]))
    u0, v0, h, w = int(uv[0]) - 62, int(uv[1]) - 62, 124, 124
    tex = aruco_texture(7)[None]
    alpha, white = marker_coverage(UndistortionLattice(INTR), np.array([u0]), np.array([v0]), h, w, cc, nc, e1c,
                                   e2c, 0.02, tex, np.zeros((1, 2)))
    st = _brute_force_plane_coords(INTR, u0, v0, h, w, 12, cc, nc, e1c, e2c)
    cell = 0.02 / 6
    ab = (st + 4 * cell) / cell
    inside = np.all((ab >= 0) & (ab < 8), axis=-1)
    ja, jb = np.clip(np.floor(ab).astype(int), 0, 7).transpose(4, 0, 1, 2, 3)
    ref_white = np.where(inside, tex[0][jb, ja], 0.0).mean(axis=(-1, -2))
    ref_alpha = inside.mean(axis=(-1, -2))
    assert np.abs(alpha[0] - ref_alpha).max() < 0.1  # sub-sample quantisation (1/64 vs 1/144)
    assert np.abs(white[0] - ref_white).max() < 0.1
    black, ref_black = alpha[0] - white[0], ref_alpha - ref_white
    vv, uu = np.mgrid[v0 : v0 + h, u0 : u0 + w]
    d = [(black * g).sum() / black.sum() - (ref_black * g).sum() / ref_black.sum() for g in (uu, vv)]
    assert np.linalg.norm(d) < 0.01


def _coded_plate():
    xyz = [[-0.1, -0.06, 0], [0.1, -0.06, 0], [-0.1, 0.06, 0], [0.1, 0.06, 0], [0.0, 0.0, 0.0]]
    kind = ["coded"] * 4 + ["retro"]
    return _plate(_targets(xyz, kind=kind, code=[3, 17, 42, 249, -1]))


def test_rendered_aruco_markers_are_detected_with_their_ids_and_corners():
    intr = INTR.without_distortion()
    part = _coded_plate()
    cam = SimCamera(World(part, np.eye(4), np.eye(4), intr, seed=2))
    pose = look_at(np.array([0.08, -0.05, 0.65]), np.zeros(3), up=(0, 1, 0))
    img, truth = cam.render(pose)
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_250), cv2.aruco.DetectorParameters())
    params = det.getDetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.relativeCornerRefinmentWinSize = 0.6
    params.cornerRefinementWinSize = 12
    det.setDetectorParameters(params)
    corners, ids, _ = det.detectMarkers(img)
    assert sorted(ids.ravel().tolist()) == [3, 17, 42, 249]
    by_code = {int(c): t for c, t in zip(part.targets.code, part.targets.ids)}
    for c, i in zip(corners, ids.ravel()):
        true_uv = np.array(truth["marker_corners_uv"][by_code[int(i)]])
        # OpenCV's cornerSubPix pulls blurred L-shaped corners inwards by ~0.1-0.15 px here
        assert np.abs(c[0] - true_uv).max() < 0.2


def test_marker_black_area_centroid_matches_the_exact_projected_cells():
    """Geometry check independent of any corner detector: area centroid of the black cells."""
    intr = INTR.without_distortion()
    part = _coded_plate()
    cam = SimCamera(World(part, np.eye(4), np.eye(4), intr), sensor=Sensor(noise=False), photometry=DARK)
    pose = look_at(np.array([0.08, -0.05, 0.65]), np.zeros(3), up=(0, 1, 0))
    img, truth = cam.render(pose, quantise=False)
    cam_from_part = invert(pose)
    tex = aruco_texture(3)
    e1, e2 = marker_axes(part.targets.normals[:1])
    cell, centre = 0.02 / 6, part.targets.xyz[0]
    areas, cents = [], []
    for r, c in zip(*np.nonzero(tex < 0.5)):
        quad = np.array([[c, r], [c + 1, r], [c + 1, r + 1], [c, r + 1]], float) * cell - 4 * cell
        q = project(intr, cam_from_part, centre + quad[:, :1] * e1 + quad[:, 1:] * e2)
        x, y = q[:, 0], q[:, 1]
        x1, y1 = np.roll(x, -1), np.roll(y, -1)
        k = x * y1 - x1 * y
        areas.append(k.sum() / 2)
        cents.append([((x + x1) * k).sum() / (3 * k.sum()), ((y + y1) * k).sum() / (3 * k.sum())])
    exact = np.average(np.array(cents), axis=0, weights=areas)
    # darkness inside the patch shrunk by half a cell (white quiet zone all around, blur negligible)
    half = 3.5 * cell
    ring = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * half
    poly = project(intr, cam_from_part, centre + ring[:, :1] * e1 + ring[:, 1:] * e2)
    mask = np.zeros(img.shape, np.uint8)
    cv2.fillPoly(mask, [np.round(poly * 256).astype(np.int32)], 1, shift=8)
    vv, uu = np.nonzero(mask)
    white_level = img[vv, uu].max()
    darkness = white_level - img[vv, uu].astype(float)
    c = np.array([(darkness * uu).sum(), (darkness * vv).sum()]) / darkness.sum()
    assert np.linalg.norm(c - exact) < 0.02


def test_camera_satisfies_protocol_and_reports_faults():
    cam = SimCamera(World(_field_part(), np.eye(4), np.eye(4), INTR))
    assert isinstance(cam, Camera)
    with pytest.raises(NotConnectedError):
        cam.capture()
    cam.connect()
    cam.world.set_robot(np.zeros(6), FIELD_POSE)
    cam.inject_capture_failure(1)
    with pytest.raises(DriverError, match="timeout"):
        cam.capture()
    frame = cam.capture()
    assert frame.image.shape == (2048, 2448) and frame.meta["frame_id"] == 1
    np.testing.assert_allclose(frame.meta["sim_truth"]["part_from_cam"], FIELD_POSE)
    cam.inject_disconnect()
    with pytest.raises(NotConnectedError):
        cam.capture()


def test_same_seed_gives_the_same_image_and_light_off_hides_the_targets():
    imgs = []
    for _ in range(2):
        cam = SimCamera(World(_field_part(), np.eye(4), np.eye(4), INTR, seed=11))
        imgs.append(cam.render(FIELD_POSE)[0])
    np.testing.assert_array_equal(imgs[0], imgs[1])
    cam.world.light_fraction = 0.0
    dark, truth = cam.render(FIELD_POSE)
    u, v = np.round(truth["uv"][0]).astype(int)
    assert imgs[0][v, u] > 100 and dark[v, u] < 10


def test_sixteen_bit_sensor_gives_uint16_in_range():
    cam = SimCamera(World(_field_part(), np.eye(4), np.eye(4), INTR), sensor=Sensor(bit_depth=12))
    img, truth = cam.render(FIELD_POSE)
    assert img.dtype == np.uint16 and img.max() <= 4095
    u, v = np.round(truth["uv"][0]).astype(int)
    assert img[v, u] > 1500


def test_job_sim_noise_scales_the_sensor_noise(tmp_path):
    """``[sim] noise`` reaches the simulated camera: 0 renders clean images, 2 doubles the noise."""
    from cell.devices import make_job_sim_cell
    from cell.loadedjob import load
    from jobutil import job_variant

    stds = {}
    for noise in (0.0, 1.0, 2.0):
        job = load(job_variant(tmp_path / f"n{noise}", {"sim": {"noise": noise, "image_sigma_px": 0.0}}))
        cam = make_job_sim_cell(job).camera
        T = look_at(np.array([0.25, -0.35, 0.45]), np.zeros(3))
        clean, _ = cam.render(T, noise=False, quantise=False)
        q, _ = cam.render(T)
        if noise == 0:
            np.testing.assert_array_equal(q, cam.render(T, noise=False)[0])
            assert not cam.sensor.noise
            continue
        full = 2**cam.sensor.bit_depth - 1
        diff = q.astype(float) / full - cam.sensor.black_level - clean
        stds[noise] = float(np.std(diff[(clean > 0.2) & (clean < 0.8)]))
    assert stds[2.0] / stds[1.0] == pytest.approx(2.0, rel=0.1), stds


def test_job_exposure_sets_the_simulated_brightness_in_the_cell_and_in_plans_twin(tmp_path):
    """``[camera] exposure_s`` reaches the simulated camera and PLAN's twin (the pre-analysis renders): half the
    reference exposure renders every unclipped pixel at half the irradiance, twice it clips the brightest dots."""
    from cell.devices import make_job_sim_cell
    from cell.loadedjob import load
    from cell.stages.preanalysis import twin_camera
    from jobutil import job_variant

    T = look_at(np.array([0.25, -0.35, 0.45]), np.zeros(3))
    clean, twins = {}, {}
    for exposure in (0.001, 0.002, 0.004):
        job = load(job_variant(tmp_path / f"e{exposure}", {"camera": {"exposure_s": exposure}}))
        cell_cam, twin = make_job_sim_cell(job).camera, twin_camera(job)
        assert cell_cam.exposure_s == twin.exposure_s == exposure
        clean[exposure] = cell_cam.render(T, noise=False, quantise=False)[0]
        twins[exposure] = twin.render(T, noise=False, quantise=False)[0]  # the nominal part: its own image
    for images in (clean, twins):
        lit = images[0.002] < 0.45  # not near the ceiling at twice the exposure
        assert (images[0.002][lit] > 0.3).sum() > 1000  # dots among them
        np.testing.assert_allclose(images[0.001][lit], 0.5 * images[0.002][lit], rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(images[0.004][lit], 2.0 * images[0.002][lit], rtol=1e-4, atol=1e-6)
        assert (images[0.004] >= 0.999).sum() > (images[0.002] >= 0.999).sum()


def test_job_pixel_format_and_gain_set_the_simulated_read_out(tmp_path):
    """``[camera] pixel_format`` sets the simulated images' bit depth (12-bit values in 16-bit words, as the GenICam
    driver delivers them) and ``gain_db`` multiplies the signal before the converter; a format the cell cannot read
    is refused when the job is read."""
    from calibration.errors import JobSpecError
    from cell.devices import make_job_sim_cell
    from cell.loadedjob import load
    from jobutil import job_variant

    T = look_at(np.array([0.25, -0.35, 0.45]), np.zeros(3))
    grey = {}
    for fmt, gain in (("Mono8", None), ("Mono12", None), ("Mono12", 6.0)):
        camera = {"pixel_format": fmt} | ({} if gain is None else {"gain_db": gain})
        cam = make_job_sim_cell(load(job_variant(tmp_path / f"{fmt}{gain}", {"camera": camera}))).camera
        img = cam.render(T, noise=False)[0]
        full = 2**cam.sensor.bit_depth - 1
        assert img.dtype == (np.uint8 if fmt == "Mono8" else np.uint16) and int(img.max()) <= full
        grey[fmt, gain] = img.astype(float) / full - cam.sensor.black_level
    mid = (grey["Mono12", None] > 0.05) & (grey["Mono12", None] < 0.45)
    assert mid.sum() > 1000
    np.testing.assert_allclose(grey["Mono12", 6.0][mid], 10 ** 0.3 * grey["Mono12", None][mid], rtol=0.02, atol=2e-3)
    np.testing.assert_allclose(grey["Mono8", None][mid], grey["Mono12", None][mid], atol=1 / 255)
    with pytest.raises(JobSpecError, match="pixel_format"):
        load(job_variant(tmp_path / "rgb", {"camera": {"pixel_format": "RGB8"}}))


def test_sensor_noise_scale_is_checked():
    with pytest.raises(InputError, match="noise scale"):
        Sensor().with_noise_scale(-1.0)
    assert Sensor().with_noise_scale(1.0) == Sensor()


def test_lattice_on_pixel_grids_equals_the_pointwise_interpolation():
    """Issue 21: the separable (matrix) form of the lattice gives the bilinear values, extrapolation included."""
    lat = UndistortionLattice(INTR, 4.0)
    rng = np.random.default_rng(3)
    u0 = np.array([-40.0, 0.0, 1203.0, 2430.0])  # two windows reach beyond the lattice's margin
    v0 = np.array([-35.0, 2030.0, 977.0, 5.0])
    U = u0[:, None] + np.arange(31) - 0.5 - rng.normal(0, 0.4, (4, 1))
    V = v0[:, None] + np.arange(23) - 0.5 - rng.normal(0, 0.4, (4, 1))
    ref = lat(np.broadcast_to(U[:, None, :], (4, 23, 31)), np.broadcast_to(V[:, :, None], (4, 23, 31)))
    np.testing.assert_allclose(lat.on_grid(U, V), ref, rtol=0, atol=1e-14)
    exact = UndistortionLattice(Intrinsics.from_focal_length(0.012, 3.45e-6, 2448, 2048))
    np.testing.assert_allclose(exact.on_grid(U, V), exact(np.broadcast_to(U[:, None, :], (4, 23, 31)),
                                                          np.broadcast_to(V[:, :, None], (4, 23, 31))))


@pytest.mark.parametrize("sensor", [Sensor(), Sensor(bit_depth=12), Sensor(noise=False)])
def test_sensor_in_row_blocks_is_shot_and_read_noise_of_one_stream(sensor):
    """Issue 21: the block size does not change the image; it is the sensor model on one normal stream."""
    from sim_backend.sim_camera import apply_sensor, standard_normal_image

    rng = np.random.default_rng(4)
    x = (rng.random((37, 53)) * 1.2 - 0.05).astype(np.float32)  # below black and above full scale too
    full = 2.0**sensor.bit_depth - 1
    e = x.astype(np.float64) * sensor.full_well_e
    if sensor.noise:  # photons: none below zero irradiance
        e = np.maximum(e, 0)
        e = e + np.sqrt(e + sensor.read_noise_e**2) * standard_normal_image(np.random.default_rng(9), x.shape)
    ref = np.clip(np.rint(e / sensor.full_well_e * full + sensor.black_level * full), 0, full)
    images = [apply_sensor(x, sensor, np.random.default_rng(9), block_rows=b) for b in (1, 5, 32, 100)]
    for img in images:
        np.testing.assert_array_equal(img, images[0])
    assert images[0].dtype == (np.uint8 if sensor.bit_depth == 8 else np.uint16)
    assert np.abs(images[0].astype(float) - ref).max() <= 1  # float32 arithmetic: a rounding may differ by 1 DN


def test_first_hit_agrees_with_trimesh_ray_casting():
    """Issue 21: Embree without trimesh's wrapper gives the same triangles and float64 distances."""
    mesh = trimesh.creation.box(extents=(0.2, 0.1, 0.05))
    mesh = trimesh.util.concatenate([mesh, trimesh.creation.icosphere(radius=0.03).apply_translation([0.05, 0, 0.05])])
    part = Part("blocks", mesh, _targets(np.zeros((1, 3))), target_diameter_m=0.006)
    w = World(part, np.eye(4), np.eye(4), INTR)
    rng = np.random.default_rng(5)
    origin = np.array([0.02, -0.3, 0.4])
    dirs = -origin + rng.normal(0, 0.08, (2000, 3))
    dist, tri = w.first_hit(origin, dirs)
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    loc, ray, t = w.intersector.intersects_location(np.broadcast_to(origin, d.shape), d, multiple_hits=False)
    ref = np.full(len(d), np.inf)
    ref[ray] = np.einsum("ij,ij->i", loc - origin, d[ray])
    assert 100 < np.isfinite(dist).sum() < len(d)  # some rays miss
    np.testing.assert_array_equal(np.isfinite(dist), np.isfinite(ref))
    np.testing.assert_allclose(dist[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=0, atol=1e-9)
    assert np.mean(tri[ray] == t) > 0.99  # a ray through a shared edge may name either triangle


def _second_moment(img, uv, half):
    """Intensity-weighted variance of a dot's image along u and v (px^2), background = the window border's median."""
    win, uu, vv = _window(img, uv, half)
    c = np.array([(win * uu).sum(), (win * vv).sum()]) / win.sum()
    return np.array([(win * (uu - c[0]) ** 2).sum(), (win * (vv - c[1]) ** 2).sum()]) / win.sum(), c


def test_depth_of_field_defocuses_each_dot_by_its_depth_and_leaves_its_centre():
    """A thin lens focused for 0.5-0.9 m with a 2 px blur circle at the limits: a dot at the focus (0.643 m, the
    harmonic mean) renders as sharp as the lens's own blur; one at the near limit spreads by the blur circle's
    variance, (2 / 4)^2 px^2 along each axis, and its centroid stays within 0.002 px; the job's key sets it."""
    sensor = Sensor(noise=False).with_depth_of_field(0.5, 0.9, 2.0)
    assert sensor.focus_m == pytest.approx(1 / (0.5 * (1 / 0.5 + 1 / 0.9)))
    np.testing.assert_allclose(sensor.defocus_sigma_px(np.array([0.5, sensor.focus_m, 0.9])), [0.5, 0.0, 0.5])
    part = _tilted_single_target(0.0)
    sharp = SimCamera(World(part, np.eye(4), np.eye(4), INTR), sensor=Sensor(noise=False), photometry=DARK)
    lens = SimCamera(World(part, np.eye(4), np.eye(4), INTR), sensor=sensor, photometry=DARK)
    for dist, extra in ((sensor.focus_m, 0.0), (0.5, 0.5)):
        part_from_cam = look_at(np.array([0, 0, dist]), np.array([-0.02, 0.01, 0.0]), up=(0, 1, 0))
        a, truth = sharp.render(part_from_cam, quantise=False)
        b, _ = lens.render(part_from_cam, quantise=False)
        uv = np.array(truth["uv"][0])
        (ma, ca), (mb, cb) = _second_moment(a, uv, 30), _second_moment(b, uv, 30)
        np.testing.assert_allclose(mb - ma, extra**2, atol=0.01)
        assert np.linalg.norm(cb - ca) < 0.002
    # the cell measures the blur from the dot's own image (its moments against its ellipse's; decision 0049): at the
    # far limit the defocused dot shows the blur circle's variance more than the sharp one, within quantisation
    from calibration.targets import DetectionOptions, blur_variances, detect_retro_targets, ellipse_moments

    part_from_cam = look_at(np.array([0, 0, 0.9]), np.array([-0.02, 0.01, 0.0]), up=(0, 1, 0))
    moments = ellipse_moments(INTR, invert(part_from_cam), part.targets.xyz, part.targets.normals, RADIUS)
    b = [blur_variances(detect_retro_targets(c.render(part_from_cam)[0], DetectionOptions()).axes[:1], moments)[0]
         for c in (sharp, lens)]
    assert abs(b[1] - b[0] - 0.25) < 0.06, b
    with pytest.raises(InputError, match="depth of field"):
        Sensor().with_depth_of_field(0.9, 0.5, 2.0)
    assert Sensor().with_depth_of_field(0.5, 0.9, 0.0).defocus_px_m == 0.0


def test_defocus_of_a_window_just_off_the_top_edge_leaves_the_image_alone():
    """A dot's window above the image but for the blur's reach (a generated plate's dot at v0 = -27 px): the write's
    end was negative, counted from the image's other side, and the job faulted in ACQUIRE with a broadcast error."""
    from types import SimpleNamespace

    sensor = Sensor(noise=False).with_depth_of_field(0.5, 0.9, 2.0)
    cam = SimCamera(World(_tilted_single_target(0.0), np.eye(4), np.eye(4), INTR), sensor=sensor, photometry=DARK)
    img = np.random.default_rng(3).uniform(0, 200, (INTR.height, INTR.width)).astype(np.float32)
    vis = SimpleNamespace(depth=np.array([0.5, 0.5]), windows=(np.array([100, INTR.width - 3]), np.array([-28, 40]),
                                                                 np.array([31, 31]), np.array([24, 24])))
    out = cam._defocus(img, vis)  # pad 3: the first window's write ends at -1, its read at 2
    assert out.shape == img.shape and np.array_equal(out[:, :INTR.width - 10], img[:, :INTR.width - 10])
    assert not np.array_equal(out[35:70, INTR.width - 6:], img[35:70, INTR.width - 6:])  # the other one is blurred
