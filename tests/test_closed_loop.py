"""The closed loop on the simulated cell: a job asked for more than its first network gives adds stations
until every target meets its requirement (or says why not), survives a kill inside the loop, and measures
the true part within its stated uncertainty."""
from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from jobutil import (
    cell_command,
    child_env,
    job_variant,
    mahalanobis,
    records,
    rigid_fit,
    run_cell,
    truth_xyz_m,
)
from scipy.stats import chi2

# the example's plan (16 stations of the search and those its scale bar's ends need, planning/scalebar.py) achieves
# about 2.7 um at worst: some targets must fall short
REQUIRED_MM = 0.003


def _folder(archive: Path) -> Path:
    dirs = [p for p in archive.iterdir() if p.is_dir() and not p.name.startswith(".")]
    assert len(dirs) == 1, dirs
    return dirs[0]


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_closed_loop_adds_stations_until_targets_meet_requirement_and_resumes_after_kill(tmp_path):
    job = job_variant(tmp_path / "job", {"planning": {"required_sigma": REQUIRED_MM, "closed_loop_rounds": 3}})
    archive = tmp_path / "archive"
    env = child_env()
    err = open(tmp_path / "run.err", "w")
    proc = subprocess.Popen([*cell_command(), "run", str(job), "--archive", str(archive), "--yes"],
                            stdout=subprocess.DEVNULL, stderr=err, env=env)
    # kill it inside the closed loop, after the first extra station is on disk
    deadline = time.monotonic() + 600
    folder = None
    while time.monotonic() < deadline:
        if archive.exists() and any(p.is_dir() and not p.name.startswith(".") for p in archive.iterdir()):
            folder = _folder(archive)
            if any(r["event"] == "station_done" and str(r["station"]).startswith("L1-") for r in records(folder)):
                break
        if proc.poll() is not None:
            err.close()
            pytest.fail(f"the job ended ({proc.returncode}) before the closed loop took a station: "
                        f"{(tmp_path / 'run.err').read_text()[-2000:]}")
        time.sleep(0.05)
    else:
        proc.kill()
        proc.wait()
        err.close()
        pytest.fail("no closed-loop station within 600 s")
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    err.close()
    loop = json.loads((folder / "closed_loop.json").read_text())
    assert loop["rounds"][-1]["status"] == "planned"
    planned = loop["rounds"][-1]["stations_added"]

    res = run_cell("resume", folder.name, "--archive", str(archive), "--yes", timeout=600, env=env)
    assert res.code in (0, 1) and res.doc is not None, res.stderr[-2000:]
    assert res.doc["status"] == "DONE", res.doc
    recs = records(folder)
    done = [r["station"] for r in recs if r["event"] == "station_done"]
    assert len(done) == len(set(done)), "a station was taken twice"
    assert set(planned) <= set(done), "the resumed round did not take its planned stations"

    report = json.loads((folder / "report.json").read_text())
    cl = report["closed_loop"]
    assert cl["required_sigma_m"] == pytest.approx(REQUIRED_MM * 1e-3)
    rounds = [r for r in cl["rounds"] if r["status"] == "done"]
    assert rounds and rounds[0]["targets_short"], "the first network met a requirement it cannot meet"
    assert sum(len(r["stations_added"]) for r in rounds) >= 1
    assert any(r["targets_fixed"] for r in rounds)
    # every target within its requirement, or named with the reason
    unmet = {u["id"]: u["reason"] for u in cl["unmet"]}
    for t in report["targets"]:
        if t["id"] not in unmet:
            assert t["achieved_sigma_m"] <= REQUIRED_MM * 1e-3 * (1 + 1e-9), t["id"]
        else:
            assert unmet[t["id"]], t["id"]
    assert len(unmet) <= 2, unmet
    # the images of the extra stations are in the adjustment
    bundle = json.loads((folder / "bundle.json").read_text())
    assert {i["station"] for i in bundle["images"]} >= set(planned)
    # the truth: CAD + deviations; a rigid fit to it leaves residuals the stated covariance explains
    ids, _, true_xyz = truth_xyz_m(job)
    where = {tid: k for k, tid in enumerate(ids)}
    T = [t for t in report["targets"] if t["measured"] is not None and np.all(np.isfinite(t["measured"]))]
    meas = np.array([t["measured"] for t in T], dtype=float)
    cov = np.array([t["cov"] for t in T], dtype=float)
    truth = np.array([true_xyz[where[t["id"]]] for t in T])
    fit = rigid_fit(meas, truth)
    r = meas @ fit[:3, :3].T + fit[:3, 3] - truth
    m2 = mahalanobis(r, cov) ** 2
    within = m2 <= chi2.ppf(0.9973, 3)
    assert within.mean() >= 0.95, f"only {within.mean():.1%} of {len(T)} targets within 3 sigma of the truth"
    assert 1.0 <= m2.mean() <= 6.0, f"mean squared normalised error {m2.mean():.2f} (3 expected)"
