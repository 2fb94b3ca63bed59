"""Calibrating the simulated cell: hand-eye, reverification, calibration status, the cell file."""
from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from calibration.errors import JobSpecError
from calibration.errors import AbortRequested, InputError, PlanningError
from cell.cellcal.common import artefact_job, ask_operator
from cell.cellcal.handeye import plan_hand_eye_stations, run_hand_eye
from cell.cellcal.reverify import run_reverification
from cell.cellcal.status import calibration_status
from cell.cellcal.cellfile import load_cell_file, write_flange_from_cam
from cell.jobspec import pose_matrix

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "cell"
TRUE_FFC = "{ xyz = [1.2, 39.2, 91.5], rpy_deg = [0.3, -0.2, 0.4] }"


from jobutil import RecordingOutput as _Out  # noqa: E402


REAL_LENS = ("{ principal_distance_factor = 1.0075, principal_point_offset_px = [16.5, -11.5], k1 = -0.06, k2 = 0.09, "
             "k3 = -0.04, p1 = 0.00015, p2 = -0.00025 }")  # the bracket example's camera (decision 0054)


def _cell(tmp_path: Path, flange_from_cam: str | None = None, positions: int | None = None,
          lens: str | None = None) -> Path:
    for f in EXAMPLE.iterdir():
        if f.suffix in (".toml", ".stl", ".csv"):
            shutil.copy(f, tmp_path / f.name)
    p = tmp_path / "cell.toml"
    text = p.read_text()
    if flange_from_cam is not None:
        text = re.sub(r"(?m)^flange_from_cam = .*$", f"flange_from_cam = {flange_from_cam}", text)
    if positions is not None:
        head, rest = text.split("positions = [\n", 1)
        body, tail = rest.split("]\nstations_per_position", 1)
        keep = body.splitlines()[:positions]
        text = head + "positions = [\n" + "\n".join(keep) + "\n]\nstations_per_position" + tail
    if lens is not None:  # the simulated camera's real lens, which the cell file does not state
        assert "\n[sim]\n" in text
        text = text.replace("\n[sim]\n", f"\n[sim]\nlens = {lens}\n")
    p.write_text(text)
    return p


def test_hand_eye_job_recovers_the_true_hand_eye_and_writes_it_into_the_cell_file(tmp_path):
    cell = _cell(tmp_path)
    before = cell.read_text()
    s = run_hand_eye(cell, tmp_path / "archive", _Out())
    cf, _ = load_cell_file(cell)
    truth = pose_matrix(cf.sim.flange_from_cam_true, cf.scale)
    from calibration.handeye import pose_error

    dt, dr = pose_error(cf.flange_from_cam(), truth)
    assert dt < 0.5e-3 and np.rad2deg(dr) < 0.05  # the figures
    assert dt < 0.05e-3  # and in fact ten times better on the sim
    assert cf.cell.flange_from_cam_date == s["date"]
    # every closed-form method of OpenCV was compared, and each is already close
    assert {m["method"] for m in s["methods"]} == {"tsai", "park", "horaud", "andreff", "daniilidis"}
    assert s["methods_failed"] == {}
    assert all(m["error_translation_m"] < 0.5e-3 for m in s["methods"])
    # the planner's stations were checked for the hand-eye's conditioning before any image
    c = s["planned_conditioning"]
    assert np.linalg.norm(c["sigma_translation_m"]) < 0.05e-3 and np.rad2deg(c["weakest_rotation_rad"]) >= 10.0
    assert c["pivot_rms_m"] > 1e-3  # two distance bands: the motions do not all turn about one point
    # uncertainty is stated and honest (error within 5 sigma)
    sig = np.linalg.norm(s["sigma_translation_m"])
    assert 0 < sig < 0.1e-3 and dt < 5 * sig + 2e-6
    # only the hand-eye lines changed
    kept = [ln for ln in before.splitlines() if not ln.startswith("flange_from_cam")]
    assert all(ln in cell.read_text().splitlines() for ln in kept)
    rec = tmp_path / "archive" / "calibration" / s["record"]
    assert (rec / "hand_eye.json").exists() and (rec / "manifest.json").exists()
    # docs/bring-up.md: "check that a second run agrees within them". The second run plans from the hand-eye
    # the first wrote; its stations' rolls (chosen after the planning) had taken one out of the arm's reach
    # ("no IK solution" at VALIDATE). A roll the robot does not reach is now reduced.
    again = run_hand_eye(cell, tmp_path / "archive", _Out())
    assert again["status"] == "ok" and again["record"] != s["record"]
    cf2, _ = load_cell_file(cell)
    d = cf2.flange_from_cam()[:3, 3] - cf.flange_from_cam()[:3, 3]
    both = np.hypot(np.asarray(s["sigma_translation_m"], float), np.asarray(again["sigma_translation_m"], float))
    assert np.all(np.abs(d) < 4 * both + 1e-7), (d, both)
    assert pose_error(cf2.flange_from_cam(), truth)[0] < 0.05e-3


def test_the_hand_eye_through_a_lens_the_cell_file_does_not_state_estimates_the_lens_with_it(tmp_path, monkeypatch):
    """Held at the data sheet's, a lens 0.75 % longer with distortion put the hand-eye 1.87 mm and 0.49 deg off at
    a stated 0.05 mm (sigma0 0.92 px; decision 0055). The lens is estimated with X and Y; a fit the model does not
    explain is not written."""
    from calibration.errors import CalibrationError
    from calibration.handeye import pose_error
    import cell.cellcal.handeye as he

    cell = _cell(tmp_path, lens=REAL_LENS)
    s = run_hand_eye(cell, tmp_path / "archive", _Out())
    cf, _ = load_cell_file(cell)
    dt, dr = pose_error(cf.flange_from_cam(), pose_matrix(cf.sim.flange_from_cam_true, cf.scale))
    sig = np.linalg.norm(s["sigma_translation_m"])
    assert dt < 10e-6 and np.rad2deg(dr) < 0.005 and dt < 5 * sig + 2e-6, (dt, sig)
    # the dots' centres through the lens found (decision 0057): without, the translation along the optical axis came
    # out 1.1-3.5 sigma short on every one of five seeds; with, the translation's error is within its statement
    import json

    doc = json.loads((tmp_path / "archive" / "calibration" / s["record"] / "hand_eye.json").read_text())
    assert 1e-3 < doc["centres_through_lens_rms_px"] < 0.02, doc["centres_through_lens_rms_px"]
    X, R = cf.flange_from_cam(), cf.flange_from_cam()[:3, :3]
    e = X[:3, 3] - pose_matrix(cf.sim.flange_from_cam_true, cf.scale)[:3, 3]
    m2 = e @ np.linalg.solve(R @ np.asarray(doc["covariance"])[3:6, 3:6] @ R.T, e)
    assert m2 < 11.34, (m2, e)  # chi-square(3) at 99 %
    lens = s["lens"]
    assert abs(lens["principal_distance_mm"] - 8.06) < 0.002 and s["sigma0_px"] < 0.03, lens
    assert np.allclose(lens["principal_point_offset_px"], [16.5, -11.5], atol=0.5)
    assert abs(lens["k1"] + 0.06) < 0.005 and abs(lens["p2"] + 2.5e-4) < 5e-5, lens
    # the lens is written with the hand-eye, and the reverification measures through it: with the data sheet's
    # lens the bar came out 4.1-5.0 mm short and the cell was failed with "recalibrate the hand-eye"
    assert cf.cell.camera_lens is not None and abs(cf.cell.camera_lens.k1 + 0.06) < 0.005
    rv = run_reverification(cell, tmp_path / "archive", _Out())
    assert rv["passed"], rv["detail"]
    _a_job_of_the_cell_measures_through_its_calibration(tmp_path, cell, cf)
    # a hand-eye whose images the model does not explain is refused, and the cell file keeps what it had
    (tmp_path / "b").mkdir()
    cell = _cell(tmp_path / "b", lens=REAL_LENS)
    before = cell.read_text()
    monkeypatch.setattr(he, "HAND_EYE_MAX_VARIANCE_RATIO", 0.01)
    with pytest.raises(CalibrationError, match="not written"):
        run_hand_eye(cell, tmp_path / "archive2", _Out())
    assert cell.read_text() == before


def _a_job_of_the_cell_measures_through_its_calibration(tmp_path: Path, cell: Path, cf) -> None:
    """The example part, its job naming the calibrated cell file (decision 0056), holding the lens
    (``self_calibrate = false``): with its own data sheet's lens this job fits at > 0.1 px and its report is
    UNTRUSTED (tests/test_lens.py); through the cell's lens it measures, and says what it measured with."""
    import json

    from jobutil import job_variant, mahalanobis, records, run_cell, truth_xyz_m

    job = job_variant(tmp_path / "job", {"cell": {"cell_file": str(cell), "flange_from_cam": None},
                                         "camera": {"self_calibrate": False}})
    run = run_cell("run", str(job), "--archive", str(tmp_path / "archive"), timeout=600)
    assert run.code == 0, run.stderr[-3000:]
    assert "hand-eye calibrated" in run.stderr and "its lens ([cell] camera_lens" in run.stderr
    folder = Path(run.doc["folder"])
    assert (folder / "inputs" / "cell_file.toml").read_bytes() == cell.read_bytes()  # the cell file as taken
    taken = next(r for r in records(folder) if r["event"] == "cell_file_taken")
    assert taken["source"] == str(cell) and taken["hand_eye"]["date"] == cf.cell.flange_from_cam_date
    bundle = json.loads((folder / "bundle.json").read_text())
    assert bundle["sigma0_px"] < 0.05 and bundle["lens"]["model"] == "held: the cell's, calibrated with its hand-eye"
    # the lens's covariance from the hand-eye, written with it, is carried into every target (decision 0056)
    assert np.asarray(cf.cell.camera_lens.cov).shape == (9, 9)
    held = bundle["lens"]["held_uncertainty"]
    assert held["carried"] and held["axes"] >= 6 and 1.05 < held["sigma_growth_median"] < 3.0, held
    assert len(held["added_variance_m2"]) == len(bundle["targets"])
    assert "held lens's uncertainty" in run.stderr
    assert bundle["intrinsics"]["fx_px"] == cf.cell.camera_lens.fx_px and bundle["intrinsics"]["k1"] == cf.cell.camera_lens.k1
    rep = json.loads((folder / "report.json").read_text())
    cal = rep["cell_calibration"]
    assert cal["status"] == "verified", cal  # the reverification above was made with this hand-eye
    assert cal["lens"]["k1"] == cf.cell.camera_lens.k1 and "hand-eye calibrated" in cal["measured_with"]
    assert rep["alignment"]["trusted"] and rep["verdict"] == "FAIL"  # the example's three real deviations
    # predicted / achieved compares the images' precision, the held lens's share taken off both sides; the lens's
    # share as planned and as carried is said beside it (decision 0062)
    poa = rep["predicted_over_achieved"]
    assert poa["held_lens"]["planned_growth_median"] > 1.0 and poa["held_lens"]["achieved_growth_median"] > 1.0
    judged = [t for t in rep["targets"] if t["deviation"][0] is not None]
    assert all(t["predicted_sigma_images_m"] < t["predicted_sigma_m"] for t in judged)
    assert all(t["achieved_sigma_images_m"] < t["achieved_sigma_m"] for t in judged)
    assert "the images&#x27; precision, without the held lens" in (folder / "report.html").read_text()
    html = (folder / "report.html").read_text()
    assert "Measured with" in html and 'id="lens-held"' not in html and not rep["lens"].get("held_note")
    ids, nominal, truth = truth_xyz_m(job)
    dev = {i: truth[k] - nominal[k] for k, i in enumerate(ids)}
    m = [float(mahalanobis((np.asarray(t["deviation"]) - dev[t["id"]])[None], np.asarray(t["cov"])[None])[0])
         for t in rep["targets"] if t["deviation"][0] is not None and not t["suspect"]]
    # without the lens's covariance 1.19 (optimistic); with it 0.83 on this calibration's one lens (decision 0056)
    assert len(m) > 150 and 0.7 < np.sqrt(np.mean(np.square(m)) / 3) < 1.4
    _a_resume_judges_the_cells_calibration_again(tmp_path, folder, cell)


def _a_resume_judges_the_cells_calibration_again(tmp_path: Path, finished: Path, cell: Path) -> None:
    """A resumed job keeps the cell file it took; a reverification of that calibration that failed since the job
    started refuses a resume that would take images, and a live cell file changed since is said (decision 0057)."""
    import importlib.util
    import json

    from jobutil import records, run_cell

    spec = importlib.util.spec_from_file_location("faultutil", Path(__file__).parent / "faults" / "faultutil.py")
    fu = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fu)
    archive = tmp_path / "archive-resume"
    folder = fu.copy_job(finished, archive)
    fu.kill_during_acquire(folder, 5)
    cf, _ = load_cell_file(folder / "inputs" / "cell_file.toml")
    _fake_record(archive, cf.cell.name, False, "2099-01-01T00:00:00+00:00", cf.flange_from_cam())
    before = fu.snapshot(folder)
    run = run_cell("resume", folder.name, "--archive", str(archive), "--yes")
    assert run.code == 1 and "failed" in run.doc["message"] and "not resumed" in run.doc["message"], run.stderr
    assert "\n" not in run.doc["message"] and fu.snapshot(folder) == before  # nothing written
    # a job that has its images computes on, saying so; and a cell file recalibrated since is said
    folder = fu.copy_job(finished, tmp_path / "archive-resume2")
    fu.cut_journal(folder, lambda r, i: not (r["event"] == "state" and r["to"] == "REPORT"))
    (folder / "manifest.json").unlink()  # killed before REPORT: it never closed (a manifest would refuse the cut)
    _fake_record(folder.parent, cf.cell.name, False, "2099-01-01T00:00:00+00:00", cf.flange_from_cam())
    X = cf.flange_from_cam()
    X[2, 3] += 30e-6
    write_flange_from_cam(cell, X, "2026-11-25T08:00:00+00:00", record="he-later")
    run = run_cell("resume", folder.name, "--archive", str(folder.parent), "--yes")
    assert run.code == 0 and run.doc["status"] == "DONE", run.stderr[-2000:]
    assert "WARNING cell" in run.stderr and "changed since this job took it" in run.stderr, run.stderr
    notes = [r["text"] for r in records(folder) if r["event"] == "note"]
    assert any("changed since this job took it" in t for t in notes), notes
    assert json.loads((folder / "report.json").read_text())["cell_calibration"]["status"] == "failed"


@pytest.mark.slow
def test_reverification_passes_a_calibrated_cell_and_fails_one_off_by_2_mm(tmp_path):
    good = tmp_path / "good"
    bad = tmp_path / "bad"
    good.mkdir()
    bad.mkdir()
    archive = tmp_path / "archive"
    asked = []
    rg = run_reverification(_cell(good, TRUE_FFC, positions=3), archive, _Out(), operator=asked.append)
    assert rg["passed"]
    assert len(asked) == 3 and all("put the scale bar" in m for m in asked)
    # each length error is explained by its stated uncertainty (and far inside the 120 um MPE)
    for r in rg["positions"]:
        assert abs(r["error_m"]) <= 3.5 * r["sigma_m"] + 2e-6, (r["error_m"], r["sigma_m"])
    assert rg["max_abs_error_m"] < 0.5 * rg["positions"][0]["mpe_m"]
    assert len({round(r["error_m"], 9) for r in rg["positions"]}) == len(rg["positions"]), "positions share noise"
    out = _Out()
    off = "{ xyz = [3.2, 39.2, 91.5], rpy_deg = [0.3, -0.2, 0.4] }"  # 2 mm off along the flange x axis
    cell_bad = _cell(bad, off, positions=3)
    rb = run_reverification(cell_bad, archive, out)
    assert not rb["passed"]
    assert "recalibrate the hand-eye" in rb["detail"]
    # every position fails: by its length error or, where that stays inside the MPE by chance, by rays
    # that no longer meet (a calibrated cell's miss by hundredths of a pixel)
    assert not any(r["pass"] for r in rb["positions"])
    assert all(r["rays_consistent"] for r in rg["positions"]) and not any(r["rays_consistent"] for r in rb["positions"])
    assert any("FAIL" in ln for ln in out.lines)
    st = calibration_status(archive, cell_bad, "2030-01-01T00:00:00+00:00")
    assert st["status"] == "failed"


def _fake_record(archive: Path, name: str, passed: bool, finished: str, ffc) -> None:
    import json

    d = archive / "calibration" / f"{finished[:19].replace(':', '-')}-{name}-reverification"
    d.mkdir(parents=True)
    (d / "reverification.json").write_text(json.dumps({
        "cell": name, "finished": finished, "passed": passed, "detail": "7 of 7", "interval_days": 30.0,
        "flange_from_cam": np.asarray(ffc).tolist(), "max_abs_error_m": 1e-6}))


def test_calibration_status_reports_verified_expired_failed_and_not_verified(tmp_path):
    cell = _cell(tmp_path)
    cf, _ = load_cell_file(cell)
    archive = tmp_path / "archive"
    assert calibration_status(archive, cell, "2026-01-01T00:00:00+00:00")["status"] == "not verified"
    _fake_record(archive, cf.cell.name, True, "2026-01-01T00:00:00+00:00", cf.flange_from_cam())
    assert calibration_status(archive, cell, "2026-01-20T00:00:00+00:00")["status"] == "verified"
    assert calibration_status(archive, cf.cell.name, "2026-03-01T00:00:00+00:00")["status"] == "expired"
    _fake_record(archive, cf.cell.name, False, "2026-01-25T00:00:00+00:00", cf.flange_from_cam())
    assert calibration_status(archive, cell, "2026-01-26T00:00:00+00:00")["status"] == "failed"
    # a new hand-eye invalidates the last reverification
    X = cf.flange_from_cam().copy()
    X[0, 3] += 1e-3
    write_flange_from_cam(cell, X, "2026-01-27T00:00:00+00:00")
    st = calibration_status(archive, cell, "2026-01-28T00:00:00+00:00")
    assert st["status"] == "not verified" and "changed" in st["detail"]


def test_cell_file_rejects_unknown_keys_and_a_relative_sim_hand_eye(tmp_path):
    cell = _cell(tmp_path)
    cell.write_text(cell.read_text().replace("[hand_eye]", "[hand_eye]\nbogus = 1"))
    with pytest.raises(JobSpecError, match="unknown key 'hand_eye.bogus'"):
        load_cell_file(cell)
    cell = _cell(tmp_path)
    cell.write_text(cell.read_text() + "flange_from_cam_error = { xyz = [1.0, 0.0, 0.0] }\n")
    with pytest.raises(JobSpecError, match="flange_from_cam_true"):
        load_cell_file(cell)


def test_writing_the_hand_eye_keeps_comments_and_round_trips(tmp_path):
    cell = _cell(tmp_path)
    cf, _ = load_cell_file(cell)
    X = cf.flange_from_cam() @ pose_matrix(cf.sim.flange_from_cam_true, 1e-3) @ np.linalg.inv(cf.flange_from_cam())
    write_flange_from_cam(cell, X, "2026-02-02T00:00:00+00:00", record="r1")
    text = cell.read_text()
    assert "# the calibration artefact: a stepped target field" in text
    cf2, _ = load_cell_file(cell)
    assert np.allclose(cf2.flange_from_cam(), X, atol=1e-8)
    assert cf2.cell.flange_from_cam_record == "r1"
    write_flange_from_cam(cell, X, "2026-02-03T00:00:00+00:00")
    assert sum(ln.startswith("flange_from_cam_date") for ln in cell.read_text().splitlines()) == 1


def test_hand_eye_stations_come_from_the_planner_and_a_requirement_they_miss_stops_the_job(tmp_path):
    cell = _cell(tmp_path)
    cf, folder = load_cell_file(cell)
    he = cf.hand_eye
    job = artefact_job(cf, folder, cell, name="field", mesh=he.mesh, targets=he.targets,
                       target_diameter=he.target_diameter, coded_size=he.coded_size, placement=he.placement, seed=he.seed)
    sp, cond, tried = plan_hand_eye_stations(job, he, cf.camera.sigma_px, _Out())
    assert sp.part_from_cam.shape == (he.n_stations, 4, 4) and sp.joints.shape == (he.n_stations, 6)
    assert len(sp.plans) == 2 and all(p.mode == "fixed" for p in sp.plans)
    # every dot is measured by min_rays stations (the planner's constraint), the tilt limit holds
    assert sp.visible.sum(axis=0).min() >= he.min_rays
    tilt = np.rad2deg(np.arccos(np.clip(-sp.part_from_cam[:, 2, 2], -1, 1)))
    assert tilt.max() <= he.max_tilt_deg + 0.5
    assert tried[-1]["missed"] == [] and cond.weakest_rotation_rad > 0
    # an unattainable requirement: every network tried misses it, and the job says what to change
    strict = he.model_copy(update={"max_sigma_translation": 1e-6, "max_plans": 2})
    with pytest.raises(PlanningError, match="none of 2 planned networks.*translation"):
        plan_hand_eye_stations(job, strict, cf.camera.sigma_px, _Out())


class _Operator(_Out):
    def __init__(self, answers):
        super().__init__()
        self.answers, self.asked = list(answers), []

    def ask(self, message):
        self.asked.append(message)
        return self.answers.pop(0)


def test_a_real_cell_asks_the_operator_to_move_the_bar_and_an_abort_stops_before_moving(tmp_path):
    cell = _cell(tmp_path, positions=2)
    out = _Operator(["abort"])
    with pytest.raises(AbortRequested, match="position 1 of 2"):
        run_reverification(cell, tmp_path / "archive", out, backend="ur")
    assert "xyz = [700, 0, 0] mm" in out.asked[0]
    # no terminal and no way to ask: the job refuses instead of measuring a bar nobody moved
    with pytest.raises(InputError, match="operator at a terminal"):
        ask_operator(_Out(), "Put the scale bar at position 1.")
    ask_operator(_Operator([""]), "Put the scale bar at position 1.")  # Enter: done
