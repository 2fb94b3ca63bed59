"""Surface labels from the CAD and the detector's background fitted on a dot's own surface (decision 0035)."""
from __future__ import annotations

import numpy as np
import trimesh

from calibration.camera import Intrinsics, invert, look_at, project
from calibration.dots import DetectionOptions, detect_dots
from cell.stages.surface_labels import NO_USE, UNKNOWN, SurfaceLabeller, surface_patches
from tests.test_dots import _match
from tests.test_targets import render_dots


def test_labels_of_a_box_edge_next_to_a_dot_name_each_face_and_keep_off_the_edge():
    """A 100 x 100 x 20 mm box seen obliquely: a window around a point 3 mm from its top face's edge holds the top
    face, the side face and the scene behind; every labelled pixel's ray hits the face its label names (checked
    against the box's planes), pixels within 2 px of a change of face are NO_USE, outside the window UNKNOWN."""
    box = trimesh.creation.box((0.1, 0.1, 0.02))
    assert len(np.unique(surface_patches(box))) == 6  # coplanar triangles share a patch
    lab = SurfaceLabeller(box)
    intr = Intrinsics(500.0, 500.0, 199.5, 149.5, 400, 300)
    # on the top face 3 mm from its +x edge (the side face below it in view) and from its -x edge (the scene behind)
    dots = np.array([[0.047, 0.0, 0.01], [-0.047, 0.0, 0.01]])
    cam_from_part = invert(look_at(np.array([0.25, 0.02, 0.2]), np.zeros(3)))
    uv = project(intr, cam_from_part, dots)
    L = lab.labels(intr, cam_from_part, uv, 25.0)
    assert L.shape == (300, 400)
    ys, xs = np.nonzero(L != UNKNOWN)
    assert np.all(np.min(np.maximum(np.abs(xs[:, None] - uv[:, 0]), np.abs(ys[:, None] - uv[:, 1])), axis=1) <= 29)
    # the truth: intersect each pixel's ray with the box (slab test), which face it enters by
    xy = intr.pixel_to_normalised(np.stack([xs, ys], 1).astype(float))
    part_from_cam = invert(cam_from_part)
    d = np.c_[xy, np.ones(len(xy))] @ part_from_cam[:3, :3].T
    o = part_from_cam[:3, 3]
    half = np.array([0.05, 0.05, 0.01])
    with np.errstate(divide="ignore"):
        t0, t1 = (-half - o) / d, (half - o) / d
    tn = np.minimum(t0, t1)
    enter, t_in, t_out = tn.argmax(axis=1), tn.max(axis=1), np.maximum(t0, t1).min(axis=1)
    hit = t_in < t_out
    face = np.where(hit, enter, -1)  # 0: an x face, 2: the top (seen from above)
    v = L[ys, xs]
    usable = v != NO_USE
    assert set(face[usable]) == {-1, 0, 2}  # the window does hold all three
    for f in (-1, 0, 2):  # one label per true face, and no label on two faces
        assert len(np.unique(v[usable & (face == f)])) == 1
    assert len(np.unique(v[usable])) == 3
    assert np.unique(v[usable & (face == -1)])[0] == lab.miss
    # NO_USE exactly where another face lies within 2 px (a 5 x 5 neighbourhood), away from the window's edge
    img = np.full((300, 400), -2)
    img[ys, xs] = face
    inner = np.min(np.maximum(np.abs(xs[:, None] - uv[:, 0]), np.abs(ys[:, None] - uv[:, 1])), axis=1) < 25
    near = np.array([np.any((img[y - 2:y + 3, x - 2:x + 3] != img[y, x]) & (img[y - 2:y + 3, x - 2:x + 3] != -2))
                     for y, x in zip(ys[inner], xs[inner])])
    assert np.mean(near == ~usable[inner]) > 0.99  # a pixel whose ray grazes an edge may go either way
    assert 0.05 < (~usable).mean() < 0.5


def _step_scene(seed: int = 2):
    """Dots of radius 5 px 7-12 px from a step of the background (one wider than the top-hat kernel: an edge of the
    part), and the true surface labels of the scene (2 px NO_USE band on the step)."""
    rng = np.random.default_rng(seed)
    dists = np.array([-60, -12, -9, -8, -7.5, -7], float)
    edges = 100 + 120 * np.arange(len(dists))
    h, w = 120, int(edges.max() + 120)
    uv = np.stack([edges + dists + rng.uniform(-0.5, 0.5, len(dists)), 60 + rng.uniform(-0.5, 0.5, len(dists))], 1)
    bg = np.full((h, w), 0.08)
    labels = np.ones((h, w), np.int32)
    for e in edges:
        bg[:, e:e + 60] = 0.16
        labels[:, e:e + 60] = 2
        labels[:, e - 2:e + 2] = NO_USE
    return render_dots(rng, h, w, uv, radius_px=5.0, bg_level=bg), uv, labels, np.abs(dists)


def test_a_dot_next_to_an_edge_is_centred_on_its_own_surface_with_the_labels():
    """Next to the step the plain centroid is off by 10-20x its noise sigma (bounded by background_cov); with the
    labels its ring sees only its own surface and its centroid window stays symmetric: within 3.5 sigma of the
    truth, and the dots far from the step do not move. The default detector without labels centres those dots by
    the ellipse of their contour (decision 0037): within 4 of its own noise sigmas."""
    img, uv, labels, dist = _step_scene()
    near = dist < 10
    errs = []
    centroid = DetectionOptions(centre="centroid")
    for lab in (None, labels):
        det = detect_dots(img, centroid, labels=lab)
        j, _ = _match(uv, det.uv)
        o = np.argsort(j)
        assert len(det) == len(uv)
        noise = np.sqrt(np.linalg.eigvalsh(det.cov[o])[:, 1])
        errs.append(np.linalg.norm(det.uv[o] - uv, axis=1) / noise)
        if lab is None:
            plain = det
    assert np.all(errs[0][near] > 8)
    assert np.all(errs[1][near] < 3.5) and np.all(errs[1][near] < 0.3 * errs[0][near])
    masked = detect_dots(img, centroid, labels=labels)
    auto = detect_dots(img, DetectionOptions())
    ja, _ = _match(uv, auto.uv)
    oa = np.argsort(ja)
    err_auto = np.linalg.norm(auto.uv[oa] - uv, axis=1) / np.sqrt(np.linalg.eigvalsh(auto.cov[oa])[:, 1])
    assert np.all(auto.ellipse[oa][near]) and np.all(err_auto[near] < 4.0)
    for q in np.flatnonzero(dist > 20):  # their rings see one surface: nothing left out, the same numbers
        a = np.argmin(np.linalg.norm(plain.uv - uv[q], axis=1))
        b = np.argmin(np.linalg.norm(masked.uv - uv[q], axis=1))
        assert np.array_equal(plain.uv[a], masked.uv[b]) and plain.ring_px[a] == masked.ring_px[b]


def test_without_labels_or_with_one_surface_everywhere_the_detector_is_unchanged():
    """labels=None is today's detector; labels that name one surface everywhere, or nothing (UNKNOWN), leave out
    no pixel: bit-identical centres, covariances and bounds."""
    img, _, _, _ = _step_scene(5)
    ref = detect_dots(img, DetectionOptions())
    for lab in (np.ones(img.shape, np.int32), np.zeros(img.shape, np.int32)):
        det = detect_dots(img, DetectionOptions(), labels=lab)
        for f in ("uv", "cov", "background_cov", "ring_px", "axes", "peak", "flux", "background"):
            assert np.array_equal(getattr(ref, f), getattr(det, f)), f


def test_measure_image_with_the_cad_mask_centres_an_edge_dot_of_the_example_closer_to_the_truth(tmp_path):
    """A noisy render of the example (the simulated camera): target 88 sits next to an edge of the bracket and its
    plain centre is 0.15 px off the true projection; MEASURE with the CAD's surface labels (``surfaces``; named at a
    pose 4 mm off, labelled at the pose resected on the named dots) names the same dots, brings it within 0.05 px and
    keeps a bound on it, and does not make the image's dots worse as a whole."""
    from pathlib import Path

    from calibration.camera import project
    from cell.devices import make_job_sim_cell
    from cell.loadedjob import load
    from cell.stages.imaging import measure_image
    from planning.visibility import Occluder

    from tests.jobutil import job_variant

    # a lens without depth of field (decision 0049): this view and its thresholds were chosen for it; the defocus at
    # target 88's depth blurs the edge beside it too (the mask still helps there: 0.101 -> 0.062 px at a 2 px circle)
    job = load(job_variant(tmp_path / "job", {"sim": {"circle_of_confusion_px": 0.0}}))
    sim = make_job_sim_cell(job, nominal_lens=True)  # truth: the nominal lens's projection
    part_from_cam = np.array([[0.83912308, 0.05066443, 0.54157693, -0.3504904],
                              [0.51792856, -0.37864008, -0.76706042, 0.55167762],
                              [0.16620006, 0.92415626, -0.34396619, 0.31677018], [0, 0, 0, 1.0]])
    sim.camera.rng = np.random.default_rng(1)
    img, _ = sim.camera.render(part_from_cam, noise=True)
    cam_from_part = invert(part_from_cam)
    approx = cam_from_part.copy()
    approx[:3, 3] += [0.002, -0.001, 0.003]
    occ = Occluder(job.part.mesh)
    out = []
    centroid = DetectionOptions(centre="centroid")  # the mask's subject: the centroid's window and ring
    for surfaces in (None, SurfaceLabeller(job.part.mesh)):
        m, counts = measure_image(img, job.part, job.intrinsics, approx, occ, coded_family=job.spec.job.coded_family,
                                  surfaces=surfaces, detection=centroid)
        assert counts.get("background_mask") == (None if surfaces is None else "cad")
        e = m.uv - project(job.intrinsics, cam_from_part, sim.world.true_xyz[m.target])
        i = list(m.target).index(88)
        out.append((m.target, np.linalg.norm(e[i]), np.sqrt(np.mean(e**2)), np.trace(m.bg_cov[i])))
    (t0, e0, rms0, b0), (t1, e1, rms1, b1) = out
    assert np.array_equal(t0, t1)
    assert e0 > 0.1 and e1 < 0.05
    assert b0 > 0 and b1 > 0  # the whole ring's misfit still bounds the masked dot
    assert rms1 < rms0
    # the default detector, unmasked, centres that dot by the ellipse of its contour (decision 0037): closer than the
    # centroid, with the same bound
    m, _ = measure_image(img, job.part, job.intrinsics, approx, occ, coded_family=job.spec.job.coded_family)
    i = list(m.target).index(88)
    e2 = np.linalg.norm(m.uv[i] - project(job.intrinsics, cam_from_part, sim.world.true_xyz[88:89])[0])
    assert m.ellipse[i] and e2 < e0 and np.trace(m.bg_cov[i]) > 0
