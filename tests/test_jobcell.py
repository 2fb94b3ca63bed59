"""What a job takes from the cell file it names, and what it refuses (cell.cellcal.jobcell; decision 0056)."""
from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from calibration.errors import JobSpecError
from calibration.handeye import pose_error
from cell.cellcal.cellfile import load_cell_file, write_flange_from_cam
from cell.jobspec import load_job, pose_matrix
from cell.loadedjob import load
from jobutil import job_variant, run_cell

CELL = Path(__file__).resolve().parents[1] / "examples" / "cell"
EXAMPLE = CELL.parent / "bracket"


def _calibrated_cell(tmp_path: Path) -> Path:
    """The example cell file as a hand-eye calibration leaves it: a hand-eye 1.2 mm / 0.5 deg off the drawing's,
    with the lens it estimated (written by the cell's own writer, as ``cell calibrate hand-eye`` writes it)."""
    from calibration.camera import Intrinsics

    d = tmp_path / "cell"
    d.mkdir()
    for f in CELL.iterdir():
        if f.suffix in (".toml", ".stl", ".csv"):
            shutil.copy(f, d / f.name)
    X = pose_matrix(load_cell_file(d / "cell.toml")[0].sim.flange_from_cam_true, 1e-3)
    X[:3, 3] += [2e-6, -1e-6, 3e-6]
    lens = Intrinsics(fx_px=2336.24, fy_px=2336.2, cx_px=1240.0, cy_px=1012.0, width=2448, height=2048,
                      k1=-0.06, k2=0.09, k3=-0.04, p1=1.5e-4, p2=-2.5e-4)
    write_flange_from_cam(d / "cell.toml", X, "2026-11-20T08:00:00+00:00", record="he-1", lens=lens)
    return d / "cell.toml"


def _fenceless() -> str:
    """The example job's text without its (multi-line) obstacles: a job that leaves the cell's fixtures to the cell."""
    text = re.sub(r"(?ms)^obstacles = \[\n.*?^\]\n", "", (EXAMPLE / "job.toml").read_text())
    assert "fence" not in text
    return text


def test_a_job_that_names_its_cell_file_takes_the_cells_hand_eye_lens_and_simulated_truth(tmp_path):
    cell = _calibrated_cell(tmp_path)
    cf, _ = load_cell_file(cell)
    job = load(job_variant(tmp_path / "job", {"cell": {"cell_file": str(cell), "flange_from_cam": None}}))
    dt, dr = pose_error(job.spec.flange_from_cam(), cf.flange_from_cam())
    assert dt < 1e-9 and dr < 1e-9
    lens = cf.cell.camera_lens
    assert (job.intrinsics.fx_px, job.intrinsics.fy_px, job.intrinsics.cx_px, job.intrinsics.k1) == \
        (lens.fx_px, lens.fy_px, lens.cx_px, lens.k1)
    assert job.cell["hand_eye"] == {"calibrated": True, "date": "2026-11-20T08:00:00+00:00", "record": "he-1"}
    # the simulated camera sits where the cell file's [sim] says, whatever the calibration found
    s = job.spec
    true_x = s.flange_from_cam() @ pose_matrix(s.sim.flange_from_cam_error, s.scale)
    dt, dr = pose_error(true_x, pose_matrix(cf.sim.flange_from_cam_true, cf.scale))
    assert dt < 1e-9 and dr < 1e-9
    # a job that states the cell's hand-eye (as the cell file writes it) is the same job
    text = cell.read_text()
    same = re.search(r"(?m)^flange_from_cam = (.*)$", text).group(1)
    again = load_job(job_variant(tmp_path / "same", {"cell": {"cell_file": str(cell)}},
                                 text=(tmp_path / "job" / "job.toml").read_text().replace(
                                     "[cell]\n", f"[cell]\nflange_from_cam = {same}\n", 1)))[0]
    assert pose_error(again.flange_from_cam(), cf.flange_from_cam())[0] < 1e-9
    # the cell's fence, table and limits where the job leaves them out; in the job's units
    fenceless = _fenceless()
    bare = load_job(job_variant(tmp_path / "bare", {"cell": {"cell_file": str(cell), "flange_from_cam": None,
                                                             "table_z": None, "robot": None}}, text=fenceless))[0]
    assert bare.cell.robot == "ur10e" and [o.name for o in bare.cell.obstacles] == ["fence"]
    # this part's fixture is added to the cell's fence; a job may move slower than the cell allows, not faster
    fixture = load_job(job_variant(tmp_path / "fixture", {"cell": {
        "cell_file": str(cell), "flange_from_cam": None, "max_joint_speed_rad_s": 0.5, "retakes": 4,
        "light_brightness_pct": 150.0,
        "obstacles": [{"name": "clamp", "size": [50.0, 50.0, 80.0], "pose": {"xyz": [600.0, 120.0, 40.0]}},
                      {"name": "fence", "size": [40.0, 1600.0, 1200.0], "pose": {"xyz": [1500.0, 0.0, 600.0]}}]}},
        text=fenceless))[0]
    assert [o.name for o in fixture.cell.obstacles] == ["fence", "clamp"]
    assert fixture.cell.max_joint_speed_rad_s == 0.5 and fixture.cell.retakes == 4
    assert fixture.cell.light_brightness_pct == 150.0
    from cell.cellcal.jobcell import take_cell_file

    raw = job_variant(tmp_path / "metres", {"cell": {"cell_file": str(cell), "flange_from_cam": None}}, text=fenceless)
    from cell.jobspec import read_job

    spec = read_job(raw)
    metres = take_cell_file(spec.model_copy(update={"job": spec.job.model_copy(update={"units": "m"})}), raw)
    fence = metres.cell.obstacles[0]
    assert np.allclose(fence.size, [0.04, 1.6, 1.2]) and np.allclose(fence.pose.xyz, [1.5, 0.0, 0.6])
    assert np.allclose(metres.cell.flange_from_cam.xyz, np.asarray(cf.cell.flange_from_cam.xyz) * 1e-3)
    # a job naming no cell file keeps its own hand-eye and the data sheet's lens
    own = load(job_variant(tmp_path / "own"))
    assert own.cell is None and own.intrinsics.k1 == 0.0 and np.allclose(own.spec.flange_from_cam()[:3, 3], [0, 0.04, 0.09])


@pytest.mark.parametrize("changes, says", [
    ({"cell": {"flange_from_cam": {"xyz": [0.0, 40.0, 90.0], "rpy_deg": [0.0, 0.0, 0.0]}}},
     r"flange_from_cam differs from the cell's hand-eye \(calibrated 2026-11-20T08:00:00\+00:00\) by 2\.08\d+ mm and 0\.53\d+ "
     r"deg; .*delete flange_from_cam from the job"),
    ({"camera": {"k1": -0.05}}, r"\[camera\] states lens terms \(k1\) and the cell file has the lens calibrated"),
    ({"camera": {"width": 2000}}, r"the job's camera is not the cell's: \[camera\] width = 2000 here, 2448 in the cell file"),
    ({"cell": {"robot": "ur5e"}}, r"\[cell\] robot = ur5e here, ur10e in the cell file \(mm\); .*delete robot from the job"),
    ({"cell": {"obstacles": [{"name": "fence", "size": [40.0, 1600.0, 1200.0], "pose": {"xyz": [1400.0, 0.0, 600.0]}}]}},
     r"\[cell\] obstacles: 'fence' = .*1400\.0.* here, .*1500\.0.* in the cell file \(mm\)"),
    ({"cell": {"max_joint_speed_rad_s": 1.5}}, r"\[cell\] max_joint_speed_rad_s = 1.5 here is beyond the cell's 1.0"),
    ({"cell": {"table_z": 5.0}}, r"\[cell\] table_z = 5.0 here, 0.0 in the cell file \(mm\)"),
    ({"sim": {"flange_from_cam_error": {"xyz": [0.0, 0.0, 1.0]}}}, r"the simulated hand-eye is stated twice"),
    ({"cell": {"cell_file": "nowhere.toml"}}, r"\[cell\] cell_file: .*nowhere\.toml: cell file not found"),
])
def test_a_job_that_disagrees_with_its_cell_file_is_refused_with_one_line(tmp_path, changes, says):
    cell = _calibrated_cell(tmp_path)
    base = {"cell": {"cell_file": str(cell), "flange_from_cam": None}}
    for section, kv in changes.items():
        base.setdefault(section, {}).update(kv)
    job = job_variant(tmp_path / "job", base, text=_fenceless())
    with pytest.raises(JobSpecError, match=says) as e:
        load(job)
    assert "\n" not in str(e.value) and str(job) in str(e.value)


def test_a_job_without_a_hand_eye_or_a_cell_file_is_refused(tmp_path):
    job = job_variant(tmp_path / "job", {"cell": {"flange_from_cam": None}})
    with pytest.raises(JobSpecError, match=r"cell\.flange_from_cam: give the hand-eye, or name the cell file"):
        load_job(job)
    run = run_cell("check", str(job))  # the operator's command: one line, exit 2, nothing else
    assert run.code == 2 and "cell.flange_from_cam" in run.stderr and len(run.stderr.strip().splitlines()) == 1


def _reverification_record(archive: Path, cell: Path, passed: bool) -> None:
    """A reverification of ``cell`` in ``archive`` (as cell calibrate reverify writes it), made now with its hand-eye."""
    import json
    from datetime import datetime, timezone

    cf, _ = load_cell_file(cell)
    now = datetime.now(timezone.utc).isoformat(timespec="milliseconds")
    d = archive / "calibration" / f"{now[:19].replace(':', '-')}-{cf.cell.name}-reverification"
    d.mkdir(parents=True)
    (d / "reverification.json").write_text(json.dumps({
        "cell": cf.cell.name, "finished": now, "passed": passed, "interval_days": 30.0, "max_abs_error_m": 2.1e-3,
        "detail": "0 of 7 positions within E_MPE" if not passed else "7 of 7 positions within E_MPE",
        "flange_from_cam": cf.flange_from_cam().tolist()}))


def test_a_cell_whose_reverification_failed_measures_no_part_until_it_is_calibrated_again(tmp_path):
    """docs/bring-up.md: "a failed reverification blocks jobs until the cell is calibrated again". It did not: the job
    ran, and its report carried the status in one table row."""
    from cell.job import check_cell_calibration
    from jobutil import RecordingOutput, archive_entries, incoming_entries

    cell = _calibrated_cell(tmp_path)
    archive = tmp_path / "archive"
    _reverification_record(archive, cell, passed=False)
    job = job_variant(tmp_path / "job", {"cell": {"cell_file": str(cell), "flange_from_cam": None}}, text=_fenceless())
    run = run_cell("run", str(job), "--archive", str(archive))
    assert run.code == 1 and run.doc["status"] == "error", run.stderr[-2000:]
    assert "last reverification" in run.doc["message"] and "failed" in run.doc["message"]
    assert "cell calibrate hand-eye" in run.doc["message"] and "\n" not in run.doc["message"]
    assert archive_entries(archive) <= {"calibration"} and not incoming_entries(archive)  # nothing written
    checked = run_cell("check", str(job), "--archive", str(archive))  # said before the run, as the run says it
    assert checked.code == 1 and "last reverification" in checked.doc["message"]
    # calibrated again: the failed reverification was made with another hand-eye; the job runs, and says so
    X = load_cell_file(cell)[0].flange_from_cam()
    X[2, 3] += 20e-6
    write_flange_from_cam(cell, X, "2026-11-21T08:00:00+00:00", record="he-2")
    out = RecordingOutput()
    st = check_cell_calibration(load(job), archive, out)
    assert st["status"] == "not verified" and "the hand-eye changed" in st["detail"]
    assert any(ln.startswith("WARNING cell example-cell not verified") for ln in out.lines), out.lines
    _reverification_record(archive, cell, passed=True)
    out = RecordingOutput()
    assert check_cell_calibration(load(job), archive, out)["status"] == "verified" and not out.lines


def test_the_cells_lens_covariance_is_read_checked_and_said_when_missing(tmp_path):
    """A held lens without its covariance (a cell file written before decision 0056) is said in the report's lens;
    one with it is carried (ADJUST, tests/test_cellcal.py). A covariance that is not one is refused."""
    from calibration.camera import Intrinsics
    from cell.stages.lens import lens_doc

    cell = _calibrated_cell(tmp_path)
    job = load(job_variant(tmp_path / "job", {"cell": {"cell_file": str(cell), "flange_from_cam": None},
                                              "camera": {"self_calibrate": False}}, text=_fenceless()))
    assert job.cell["lens"]["cov"] is None
    bundle = {"lens": {"model": "held: the cell's, calibrated with its hand-eye"},
              "intrinsics": job.intrinsics.to_dict(), "intrinsics_refined": [], "intrinsics_sigma": []}
    assert "(the cell file states no covariance for it)" in lens_doc(job, bundle)["held_note"]
    bundle["lens"]["held_uncertainty"] = {"carried": True}
    assert lens_doc(job, bundle).get("held_note") is None
    # written with its covariance, read back as written
    A = np.random.default_rng(3).normal(size=(9, 9)) * np.r_[0.01, 0.01, 0.03, 0.03, 1e-4, 1e-3, 4e-3, 4e-6, 4e-6]
    cov = A @ A.T
    X = load_cell_file(cell)[0].flange_from_cam()
    lens = Intrinsics(fx_px=2336.24, fy_px=2336.2, cx_px=1240.0, cy_px=1012.0, width=2448, height=2048, k1=-0.06)
    cf = write_flange_from_cam(cell, X, "2026-11-22T08:00:00+00:00", lens=lens, lens_cov=cov)
    assert np.allclose(np.asarray(cf.cell.camera_lens.cov), cov, rtol=1e-10, atol=0.0)
    assert np.allclose(np.asarray(load(job.path).cell["lens"]["cov"]), cov, rtol=1e-10, atol=0.0)
    bad = cell.read_text().replace("cov = [[", "cov = [[-", 1)
    cell.write_text(bad)
    with pytest.raises(JobSpecError, match="camera_lens.cov must be a covariance"):
        load_cell_file(cell)


def test_the_held_lens_columns_are_the_networks_response_to_a_lens_error():
    """``add_held_lens`` on a synthetic network (calibration.bundle.synthetic): the targets' move when the held lens
    is off by ``e`` is ``sum_k a_k c_k`` of its columns, ``a = V^T e / sqrt(lambda)`` (linear propagation); and the
    added covariance is the columns' sum of outer products (``S C_L S^T``)."""
    from dataclasses import replace

    from calibration.bundle import BundleConfig, BundleOptions, ScaleBar, bundle_adjust
    from calibration.bundle.synthetic import simulate_network
    from calibration.camera import Intrinsics
    from cell.stages.shared_terms import LENS_FIELDS, add_held_lens

    rng = np.random.default_rng(5)
    lens = Intrinsics(fx_px=3000.0, fy_px=3000.0, cx_px=1230.0, cy_px=1015.0, width=2448, height=2048, k1=-0.06,
                      k2=0.09, k3=-0.04, p1=1.5e-4, p2=-2.5e-4)
    net = simulate_network(rng, n_targets=60, n_images=10, intrinsics=lens, sigma_px=0.01)
    far = np.argmax(np.linalg.norm(net.points[:, None] - net.points[None], axis=2))
    a, b = np.unravel_index(far, (60, 60))
    config = BundleConfig(camera_model="OPENCV_K3", scale_bars=(ScaleBar(int(a), int(b),
                          float(np.linalg.norm(net.points[a] - net.points[b])), 1e-6),))
    opts = BundleOptions(sigma_px=0.01, max_rejections=0)
    res = bundle_adjust(net.obs_image, net.obs_target, net.obs_uv, lens, net.cam_from_part, net.points, opts, config)
    A = rng.normal(size=(9, 9)) * np.r_[0.03, 0.03, 0.03, 0.03, 1e-4, 1e-3, 4e-3, 4e-6, 4e-6][:, None] / 3  # as a hand-eye's
    A[1] = A[0]  # fx and fy move together (one principal distance), as the hand-eye estimates them
    cov = A @ A.T
    before = res.cov.copy()
    doc = add_held_lens(res, net.obs_image, net.obs_target, net.obs_uv, config, 0.01, cov)
    assert doc["carried"] and doc["axes"] == 8 and doc["sigma_growth_median"] > 1.0
    cols = res.covariance.U[:, :, -doc["axes"]:]
    assert np.allclose(res.cov - before, np.einsum("nak,nbk->nab", cols, cols), rtol=1e-9, atol=1e-20)
    # each target's share, as REPORT and PLAN take it off for predicted / achieved (decision 0062)
    assert np.allclose(doc["added_variance_m2"], np.trace(res.cov - before, axis1=1, axis2=2), rtol=1e-9, atol=1e-24)
    lam, V = np.linalg.eigh(cov)
    keep = lam > lam.max() * 1e-12
    for _ in range(2):  # a lens error drawn from the covariance: the network's response is the columns' combination
        e = A @ rng.normal(size=9)
        off = replace(lens, **{f: getattr(lens, f) + d for f, d in zip(LENS_FIELDS, e)})
        moved = bundle_adjust(net.obs_image, net.obs_target, net.obs_uv, off, res.cam_from_part, res.points, opts,
                              config).points - res.points
        predicted = cols @ ((V[:, keep].T @ e) / np.sqrt(lam[keep]))
        assert np.linalg.norm(moved - predicted) < 0.03 * np.linalg.norm(moved), (moved, predicted)
    # a re-adjustment that does not converge carries nothing and says why (reached through a monkeypatch: the
    # synthetic network converges from a one-sigma lens move)
    import cell.stages.shared_terms as shared_terms
    from cell.stages.shared_terms import held_lens_line

    def stuck(*a, **k):
        r = bundle_adjust(*a, **k)
        r.converged, r.summary = False, "stopped at its iteration limit"
        return r

    before = res.cov.copy()
    shared_terms.bundle_adjust, real = stuck, shared_terms.bundle_adjust
    try:
        doc = add_held_lens(res, net.obs_image, net.obs_target, net.obs_uv, config, 0.01, cov)
    finally:
        shared_terms.bundle_adjust = real
    assert not doc["carried"] and "did not converge (stopped at its iteration limit)" in doc["why"]
    assert np.array_equal(res.cov, before) and "was not carried" in held_lens_line(doc)
