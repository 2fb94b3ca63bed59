"""Truth: the example job, run whole on the simulated cell with six injected deviations, finds
them, states its uncertainty honestly against the known truth, and writes report.json as the
contract in ARCHITECTURE.md says.

The job runs once per test session (``cell run`` in a child process, ~30 s) and every test
here reads its job folder.
"""
from __future__ import annotations

import json
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from pydantic import BaseModel, ConfigDict, Field
from scipy.stats import chi2

from cell.record.runlog import read_messages
from jobutil import (archive_entries, example_run, incoming_entries, job_variant, mahalanobis, records, rigid_fit,
                     run_cell, truth_xyz_m)

STAGES = ["LOAD", "PLAN", "VALIDATE", "ACQUIRE", "MEASURE", "CALIBRATE", "ADJUST", "CLOSE_LOOP", "REPORT"]
Vec3 = tuple[float, float, float]
MaybeVec3 = tuple[float, float, float] | tuple[None, None, None]  # a target no image measured
Mat3 = tuple[Vec3, Vec3, Vec3]
MaybeMat3 = Mat3 | tuple[tuple[None, None, None], tuple[None, None, None], tuple[None, None, None]]


# --- the report.json contract (ARCHITECTURE.md); more fields are allowed around it ----------------


class _Contract(BaseModel):
    model_config = ConfigDict(extra="allow", strict=True)


class JobContract(_Contract):
    id: str = Field(min_length=1)
    name: str = Field(min_length=1)
    seed: int
    status: str
    started: str
    finished: str
    versions: dict[str, str]


class TargetContract(_Contract):
    id: str
    nominal: Vec3
    measured: MaybeVec3
    cov: MaybeMat3
    deviation: MaybeVec3
    deviation_norm_m: float | None
    tolerance_m: float = Field(gt=0)
    pass_: bool = Field(alias="pass")
    predicted_sigma_m: float | None
    achieved_sigma_m: float | None


class AlignmentContract(_Contract):
    method: str
    targets_in_fit: list[str]
    rms_m: float = Field(ge=0)
    trusted: bool


class ReportContract(_Contract):
    job: JobContract
    images: int = Field(gt=0)
    sigma0_px: float = Field(gt=0)
    targets: list[TargetContract]
    alignment: AlignmentContract


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    job, folder, run = example_run(tmp_path_factory)
    return job, folder, run, json.loads((folder / "report.json").read_text())


def _measured(report: dict) -> list[dict]:
    return [t for t in report["targets"] if None not in t["measured"]]


def _deviations(job: Path) -> dict[str, np.ndarray]:
    ids, nominal, truth = truth_xyz_m(job)
    return {i: truth[k] - nominal[k] for k, i in enumerate(ids) if np.any(truth[k] != nominal[k])}


def test_example_job_runs_every_stage_once_and_ends_done(example):
    job, folder, run, report = example
    assert run.code == 0 and run.doc["status"] == "DONE" and run.doc["verdict"] == "FAIL"
    recs = records(folder)
    assert [r["stage"] for r in recs if r["event"] == "stage_done"] == STAGES
    states = [r["to"] for r in recs if r["event"] == "state"]
    assert states == STAGES + ["DONE"]
    assert [r["event"] for r in recs].count("terminal") == 1 and recs[-1]["event"] == "terminal"
    assert recs[-1]["status"] == "DONE"
    verify = run_cell("archive", "verify", folder.name, "--archive", str(folder.parent))
    assert verify.code == 0 and verify.doc["intact"], verify.doc
    assert not any((folder.parent / ".incoming").iterdir())


def test_report_json_follows_the_contract(example):
    job, folder, run, report = example
    doc = ReportContract.model_validate_json((folder / "report.json").read_text())
    plan = json.loads((folder / "plan.json").read_text())
    assert doc.job.id == folder.name and doc.job.name == "bracket" and doc.job.seed == 7 and doc.job.status == "DONE"
    assert datetime.fromisoformat(doc.job.started) < datetime.fromisoformat(doc.job.finished)
    assert {"python", "numpy", "inspection-cell"} <= set(doc.job.versions)
    assert doc.images == len(plan["stations"]) == len(list((folder / "images").glob("*.png")))
    # every retro target is judged once; the coded ones are identification aids
    ids, nominal, _ = truth_xyz_m(job)
    coded = set(report["coded_targets"])
    assert sorted(t.id for t in doc.targets) == sorted(set(ids) - coded)
    index = {t: k for k, t in enumerate(ids)}
    for t in doc.targets:
        np.testing.assert_allclose(t.nominal, nominal[index[t.id]], atol=1e-12)
        assert t.tolerance_m == pytest.approx(0.25e-3)
        if t.measured[0] is None:
            assert t.id in report["not_measured"] and not t.pass_
            continue
        m, d, c = np.array(t.measured), np.array(t.deviation), np.array(t.cov)
        np.testing.assert_allclose(d, m - np.array(t.nominal), atol=1e-12)
        assert t.deviation_norm_m == pytest.approx(np.linalg.norm(d), rel=1e-9)
        assert t.pass_ == (t.deviation_norm_m <= t.tolerance_m)
        np.testing.assert_allclose(c, c.T, atol=1e-20)
        assert np.linalg.eigvalsh(c).min() > 0, f"{t.id}: covariance not positive definite"
        # the achieved sigma is sqrt(trace(cov)) of the point (before the CAD fit, which changes it little)
        assert t.achieved_sigma_m == pytest.approx(np.sqrt(np.trace(c)), rel=0.1)
    assert len(report["not_measured"]) <= 0.05 * len(doc.targets)
    # the frame: a trusted robust best fit over the targets that agree with CAD (not the deviating ones)
    al = doc.alignment
    assert al.method == "best_fit" and al.trusted and report["alignment"]["stable"]
    assert set(_deviations(job)).isdisjoint(al.targets_in_fit)
    assert len(al.targets_in_fit) >= 0.9 * len(doc.targets) and al.rms_m < 10e-6
    # predicted (pre-analysis with the detector model) = achieved, and the report shows the ratio
    assert 0.75 <= report["predicted_over_achieved"]["median"] <= 1.25
    assert report["snooping"]["complete"]


def test_injected_deviations_beyond_tolerance_fail_and_those_within_are_significant(example):
    job, folder, run, report = example
    injected = _deviations(job)
    assert len(injected) == 6
    beyond = {i for i, d in injected.items() if np.linalg.norm(d) > 0.25e-3}
    within = set(injected) - beyond
    assert len(beyond) == 3 and len(within) == 3
    decisions = {t["id"]: t["decision"] for t in report["targets"]}
    assert all(decisions[i] == "nonconforming" for i in beyond) and all(decisions[i] == "conforming" for i in within)
    assert set(report["inconclusive"]) == {i for i, d in decisions.items() if d == "inconclusive"}
    measured = {t["id"]: t for t in _measured(report)}
    assert set(injected) <= set(measured), "a target with an injected deviation was not measured"
    failed = {i for i, t in measured.items() if not t["pass"]}
    assert failed == beyond
    assert all(measured[i]["significant"] for i in injected)
    assert all(measured[i]["pass"] for i in within)
    # the reported deviation is the injected one, to within a few sigma of the target
    for i, d in injected.items():
        t = measured[i]
        m = mahalanobis((np.array(t["deviation"]) - d)[None], np.array(t["cov"])[None])[0]
        assert m < 5.0, f"{i}: reported deviation {np.round(np.array(t['deviation']) * 1e6, 1)} um, injected " \
                        f"{np.round(d * 1e6, 1)} um ({m:.1f} sigma apart)"
    # false alarms: targets without a deviation flagged significant at 3 sigma (about 0.5 expected of ~190)
    false = [i for i, t in measured.items() if t["significant"] and i not in injected]
    assert len(false) <= 3, f"significant without a deviation: {false}"
    assert report["verdict"] == "FAIL"


def test_measured_coordinates_agree_with_truth_within_stated_covariance(example):
    """CAD + deviations is the truth; a rigid fit to it leaves residuals the covariance explains."""
    job, folder, run, report = example
    ids, _, truth = truth_xyz_m(job)
    index = {t: k for k, t in enumerate(ids)}
    T = _measured(report)
    measured = np.array([t["measured"] for t in T])
    cov = np.array([t["cov"] for t in T])
    true = truth[[index[t["id"]] for t in T]]
    fit = rigid_fit(measured, true)
    r = measured @ fit[:3, :3].T + fit[:3, 3] - true
    m2 = mahalanobis(r, cov) ** 2
    within = m2 <= chi2.ppf(0.9973, 3)  # the 3-sigma region of a 3-D normal
    assert within.mean() >= 0.95, f"only {within.mean():.1%} of {len(T)} targets within 3 sigma of the truth"
    # and the covariance is not inflated to pass: the mean squared normalised error of a 3-D normal is 3
    assert 1.5 <= m2.mean() <= 6.0, f"mean squared normalised error {m2.mean():.2f} (3 expected)"
    rms = np.sqrt((r**2).sum(axis=1).mean())
    assert rms < 50e-6, f"rms error to the truth {rms * 1e6:.1f} um"
    # the planner's predicted precision matches the achieved one on the whole
    ratio = np.array([t["achieved_sigma_m"] / t["predicted_sigma_m"] for t in T if t["predicted_sigma_m"]])
    assert 0.5 <= np.median(ratio) <= 2.0, f"achieved / predicted sigma: median {np.median(ratio):.2f}"
    print(f"\n{len(T)} targets: {within.mean():.1%} within 3 sigma of the truth, mean m^2 {m2.mean():.2f}, "
          f"rms {rms * 1e6:.1f} um; achieved/predicted sigma median {np.median(ratio):.2f}")


def test_each_images_pixel_noise_line_and_each_dots_blur_are_measured_and_recorded(example):
    """observations.json records, per image, the pixel noise's line its centres' covariances propagated (decision
    0047): on the simulated sensor (10 000 e- full well, 8 bits) the variance grows by 255 / 10 000 grey levels^2 per
    grey level; the example's images each carry enough dots to measure it."""
    job, folder, run, report = example
    obs = json.loads((folder / "observations.json").read_text())["images"]
    slopes = np.array([im["noise_levels"][1] for im in obs])
    assert np.all(slopes > 0), slopes
    assert abs(np.median(slopes) / (255 / 10_000) - 1.0) < 0.2, np.median(slopes)
    # and each dot's blur (decision 0049): the lens's 0.7 px (0.49 px^2) and the defocus within the job's depth of
    # field (a 2 px blur circle at near / far adds up to 0.25 px^2); a clipped dot's is not measured (null). MEASURE
    # records its moments; ADJUST measures the blur against the lens it found (decision 0054: against the nominal lens
    # the example's real one read 0.84 px^2 in the middle of the image and -0.11 at its corners)
    blur = np.array([np.nan if v is None else v for im in obs for v in im["blur_px2"]], dtype=float)
    moments = np.array([np.nan if v is None else v for im in obs for v in im["moments_px2"]], dtype=float)
    assert len(blur) == len(moments) == sum(len(im["ids"]) for im in obs)
    assert np.array_equal(np.isnan(blur), np.isnan(moments))
    adjusted = json.loads((folder / "bundle.json").read_text())["observation_weights"]["model_range"]["blur"]
    assert adjusted["against"] == "the adjusted lens" and adjusted["measured"] >= 0.8 * np.isfinite(blur).sum()
    assert 0.45 <= adjusted["median_blur_px2"] <= 0.65 and adjusted["p5_p95_blur_px2"][1] < 0.85, adjusted
    # and each clipped dot's bound for its unknown level (decision 0050): a clipped dot centred by its ellipse has
    # one, every other dot none; ADJUST carries them, shared by a target's views
    bound = np.array([b for im in obs for b in im["clip_bound_px"]], dtype=float).reshape(-1, 2)
    clipped = np.array([c > 0 for im in obs for c in im["clipped_share"]])
    ellipse = np.array([e for im in obs for e in im["ellipse_centre"]], dtype=bool)
    has = np.linalg.norm(bound, axis=1) > 0
    assert np.all(has <= (clipped & ellipse)) and has.sum() >= 0.9 * (clipped & ellipse).sum() > 0
    level = json.loads((folder / "bundle.json").read_text())["coherent_background"]["clip_level"]
    assert level["n_observations"] > 0 and 1.0 <= level["sigma_growth_median"] <= level["sigma_growth_max"] < 1.5, level
    assert report["uncertainty_budget"]["clip_level"] == level
    assert json.loads((folder / "bundle.json").read_text())["observation_weights"]["clipped_without_bound"] == 0


def test_run_log_holds_every_transition_image_and_detection(example):
    job, folder, run, report = example
    msgs = list(read_messages(folder / "run.mcap"))
    states = [m["to"] for t, m in msgs if t == "/state"]
    assert states == STAGES + ["DONE"]
    acq = json.loads((folder / "acquisition.json").read_text())["images"]
    images = [m["frame_id"].removeprefix("camera/") for t, m in msgs if t == "/camera/image"]
    assert images == [im["station"] for im in acq]
    assert len([1 for t, _ in msgs if t == "/detections"]) == len(acq)
    assert len([1 for t, _ in msgs if t == "/robot/joint_states"]) == len(acq)


# --- bad input: exit 2, one clear line, nothing half-written in the archive --------------------------


def _truncate(path: Path) -> None:
    b = path.read_bytes()
    path.write_bytes(b[: len(b) // 2])


def _replace(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))


def _lift_first_retro_target(path: Path, by: float) -> None:
    """Move the first retro target ``by`` job units along its normal: off the part's surface."""
    lines = path.read_text().splitlines()
    for k, line in enumerate(lines[1:], start=1):
        row = line.split(",")
        if row[7] == "retro":
            xyz = np.array(row[1:4], dtype=float) + by * np.array(row[4:7], dtype=float)
            row[1:4] = [f"{v:.4f}" for v in xyz]
            lines[k] = ",".join(row)
            break
    path.write_text("\n".join(lines) + "\n")


BAD_JOBS = {
    # name: (job-file changes, edit of the copied files, text the error line must name)
    "unknown_key": ({"job": {"colour": "red"}}, None, ("job.toml", "colour")),
    "wrong_type": ({"planning": {"n_stations": "many"}}, None, ("job.toml", "planning.n_stations")),
    "unknown_units": ({"job": {"units": "furlong"}}, None, ("job.toml", "job.units")),
    "toml_syntax": (None, lambda d: _replace(d / "job.toml", "seed = 7", "seed = = 7"), ("job.toml", "TOML")),
    "missing_mesh": ({"job": {"mesh": "nothere.stl"}}, None, ("nothere.stl", "not found")),
    "truncated_mesh": (None, lambda d: _truncate(d / "bracket.stl"), ("bracket.stl", "truncated")),
    "target_off_surface": (None, lambda d: _lift_first_retro_target(d / "targets.csv", 50.0), ("targets.csv", "off")),
    "unknown_deviation_target": (None, lambda d: (d / "deviations.csv").write_text("id,dx,dy,dz\nT9999,0,0,0.1\n"),
                                 ("deviations.csv", "T9999")),
    "part_out_of_reach": ({"cell": {"base_from_part": {"xyz": [3000.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 90.0]}}},
                          None, ("job.toml", "reach")),
}


@pytest.mark.parametrize("case", sorted(BAD_JOBS))
def test_bad_job_exits_2_with_one_line_and_leaves_nothing_in_the_archive(case, tmp_path):
    changes, edit, names = BAD_JOBS[case]
    job = job_variant(tmp_path / "job", changes)
    if edit is not None:
        edit(tmp_path / "job")
    archive = tmp_path / "archive"
    run = run_cell("run", str(job), "--archive", str(archive), timeout=120)
    assert run.code == 2, f"exit {run.code}:\n{run.stderr[-2000:]}"
    assert "Traceback" not in run.stderr
    errors = [ln for ln in run.stderr.splitlines() if ln.startswith("cell: error: ")]
    assert len(errors) == 1 and run.stderr.rstrip().splitlines()[-1] == errors[0], run.stderr
    line = errors[0]
    for word in names:
        assert word in line, f"the error line does not name {word!r}: {line}"
    assert ".incoming" not in line, f"the error names the staging copy, not the operator's file: {line}"
    assert run.doc["status"] == "error" and run.doc["exit_code"] == 2 and run.doc["message"] in line
    # nothing half-written: no job folder, an empty staging area, the operator's files untouched
    assert archive_entries(archive) == set(), f"left in the archive: {archive_entries(archive)}"
    assert incoming_entries(archive) == [], f"left in .incoming: {incoming_entries(archive)}"


def test_resuming_a_finished_job_is_refused_and_changes_nothing(example):
    job, folder, run, report = example
    before = (folder / "journal.jsonl").read_bytes()
    res = run_cell("resume", folder.name, "--archive", str(folder.parent), "--yes")
    assert res.code == 2 and "already DONE" in res.stderr.strip().splitlines()[-1]
    assert (folder / "journal.jsonl").read_bytes() == before
    res = run_cell("resume", "no-such-job", "--archive", str(folder.parent), "--yes")
    assert res.code == 2 and "no job 'no-such-job'" in res.stderr


def test_the_lens_is_estimated_as_the_simulated_lens_is(example):
    """The example's simulated lens is a real one (decision 0054: [sim] lens); the default brown model estimates each
    of its terms within a few of their own sigmas, and report.json says the lens."""
    job, folder, run, report = example
    from cell.jobspec import load_job

    true = load_job(job)[0].true_intrinsics()
    lens = report["lens"]
    assert lens["model"] == "brown" and lens["camera_model"] == "OPENCV_K3" and lens["note"] is None
    bundle = json.loads((folder / "bundle.json").read_text())
    est = dict(bundle["intrinsics"])
    for name, sigma in zip(bundle["intrinsics_refined"], bundle["intrinsics_sigma"]):
        key = {"fx": "fx_px", "fy": "fy_px", "cx": "cx_px", "cy": "cy_px"}.get(name, name)
        z = (est[key] - getattr(true, key)) / sigma
        assert abs(z) < 5, f"{name}: {est[key]:.6g} against the simulated {getattr(true, key):.6g} ({z:+.1f} sigma)"
    assert lens["distortion_at_corner_px"] > 10
