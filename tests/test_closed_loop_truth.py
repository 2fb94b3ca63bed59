"""The closed loop under reality (decision 0070): an outside tester's findings, each pinned.

- a target that never met its required sigma makes a PASS at most INCOMPLETE, whether the loop ran or not;
- the extra-station planner keeps partial gains when one round's limit stops it (it used to drop them all and
  the loop ended claiming no station helps);
- a round's records are written so that a kill between them resumes without duplicating its stations, and a
  record that lists a station or an image twice is refused loudly.
"""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from jobutil import job_variant, run_cell

from calibration.errors import RecordError
from cell.record.jobfolder import atomic_write_json
from cell.stages.report import part_verdict
from planning.augment import plan_extra_stations

IDS = [f"T{k:04d}" for k in range(1, 6)]


# --- finding 1: the requirement is part of the judgement -------------------------------------------------
def test_a_target_short_of_its_required_sigma_makes_a_pass_incomplete_with_its_name():
    ok = np.ones(5, bool)
    judged = np.ones(5, bool)
    conforming = ["conforming"] * 5
    required = np.full(5, 0.8e-6)
    achieved = np.array([0.5, 0.7, 1.9, 0.8, 2.4]) * 1e-6
    v, why = part_verdict(True, ok, ok, judged, conforming, np.zeros(5, bool), IDS,
                          requirement=(required, achieved, "[planning] required_sigma"))
    assert v == "INCOMPLETE"
    assert len(why) == 1 and why[0].startswith("2 target(s) measured less precisely than required")
    assert "T0003 1.90 um > 0.80 um" in why[0] and "T0005" in why[0] and "T0004" not in why[0]
    # met everywhere: PASS; a FAIL stays a FAIL (and still says the precision)
    assert part_verdict(True, ok, ok, judged, conforming, np.zeros(5, bool), IDS,
                        requirement=(required, np.full(5, 0.8e-6), "x")) == ("PASS", [])
    passed = ok.copy()
    passed[0] = False
    v, why = part_verdict(True, ok, passed, judged, conforming, np.zeros(5, bool), IDS,
                          requirement=(required, achieved, "x"))
    assert v == "FAIL" and any("less precisely" in w for w in why)
    # a target not judged (a coded marker) is not held to it
    v, _ = part_verdict(True, ok, ok, np.array([1, 1, 0, 1, 0], bool), conforming, np.zeros(5, bool), IDS,
                        requirement=(required, achieved, "x"))
    assert v == "PASS"


# --- finding 2: partial gains are kept -------------------------------------------------------------------
def _one_target_needing_two_stations():
    a = 1e10  # information per station (1/m^2) along each axis
    N_have = np.array([[a, 0, 0, a, 0, a]])
    info = np.array([[[a, 0, 0, a, 0, a]]] * 2, dtype=np.float32)  # two identical candidates
    req = np.array([np.sqrt(3 / (2.5 * a))])  # one station gives sqrt(3/2a) > req, two give sqrt(3/3a) < req
    return N_have, np.array([5]), req, info, np.ones((2, 1), bool), np.ones(2, bool)


def test_a_target_needing_more_stations_than_one_round_allows_keeps_the_partial_gain():
    N_have, rays, req, info, vis, valid = _one_target_needing_two_stations()
    aug = plan_extra_stations(N_have, rays, req, info, vis, valid, min_rays=3, max_new=1)
    assert aug.added.tolist() == [0], "the station that brings it closer was pruned"
    assert not aug.unreachable[0] and not aug.met_after[0]
    assert aug.sigma_after[0] < aug.sigma_before[0]
    assert aug.facts["stopped"] == "max_new" and aug.facts["limited_by_max_new"]
    aug = plan_extra_stations(N_have, rays, req, info, vis, valid, min_rays=3, max_new=2)
    assert aug.added.tolist() == [0, 1] and aug.met_after[0] and aug.facts["stopped"] == "met"
    # the bound proves it: stopped "unreachable", nothing added
    aug = plan_extra_stations(N_have, rays, req / 10, info, vis, valid, min_rays=3, max_new=5)
    assert aug.added.size == 0 and aug.unreachable[0] and aug.facts["stopped"] == "unreachable"
    # pruning still drops a station the others make unnecessary
    a = 1e10
    N_have = np.array([[a, 0, 0, a, 0, a], [a, 0, 0, a, 0, a]])
    req = np.full(2, np.sqrt(3 / (1.9 * a)))
    # candidate 0 helps target 0 a little, 1 helps both a lot, 2 helps target 1 a little
    info = np.zeros((3, 2, 6), dtype=np.float32)
    info[0, 0] = [0.95 * a, 0, 0, 0.95 * a, 0, 0.95 * a]
    info[1] = [a, 0, 0, a, 0, a]
    info[2, 1] = [0.95 * a, 0, 0, 0.95 * a, 0, 0.95 * a]
    vis = info[..., 0] > 0
    aug = plan_extra_stations(N_have, np.array([5, 5]), req, info, vis, np.ones(3, bool), min_rays=3, max_new=3)
    assert aug.added.tolist() == [1] and aug.met_after.all()


# --- finding 4: a round's two writes, a kill between them, duplicates refused ------------------------------
class _Folder:
    def __init__(self, path: Path):
        self.path = path

    def file(self, name: str) -> Path:
        return self.path / name

    def read_json(self, name: str):
        return json.loads((self.path / name).read_text())

    def records(self):
        return iter(())


def _ctx(tmp_path: Path, plan_stations: list[dict]):
    atomic_write_json(tmp_path / "plan.json", {"stations": plan_stations})
    log = SimpleNamespace(log=lambda *a, **k: None)
    return SimpleNamespace(folder=_Folder(tmp_path), log=log)


def _st(sid: str, cand: int | None = None, rnd: int | None = None) -> dict:
    return {"id": sid, "order": 0, "part_from_cam": np.eye(4).tolist()} | (
        {} if cand is None else {"candidate": cand, "round": rnd})


@pytest.mark.parametrize("written", [False, True])
def test_a_round_killed_between_its_two_writes_resumes_without_duplicates(tmp_path, written):
    from cell.stages.close_loop import _commit_round

    new = [_st("L1-01", 7, 1), _st("L1-02", 9, 1)]
    ctx = _ctx(tmp_path, [_st("S001"), _st("S002")] + (new if written else []))
    rec = {"round": 1, "status": "planning", "stations": new, "stations_added": ["L1-01", "L1-02"]}
    doc = {"enabled": True, "rounds": [rec]}
    _commit_round(ctx, doc, tmp_path / "closed_loop.json", rec)
    ids = [s["id"] for s in ctx.folder.read_json("plan.json")["stations"]]
    assert ids == ["S001", "S002", "L1-01", "L1-02"]
    assert ctx.folder.read_json("closed_loop.json")["rounds"][0]["status"] == "planned"


def test_a_round_in_plan_json_but_not_in_closed_loop_json_is_taken_not_planned_again(tmp_path):
    from cell.stages.close_loop import _recovered_round

    ctx = _ctx(tmp_path, [])
    stations = [_st("S001"), _st("L1-01", 7, 1), _st("L1-02", 9, 1)]
    rec = _recovered_round(ctx, 1, stations, ["T0005"])
    assert rec["status"] == "planned" and rec["stations_added"] == ["L1-01", "L1-02"]
    assert _recovered_round(ctx, 2, stations, ["T0005"]) is None


def test_a_record_listing_a_station_or_an_image_twice_is_refused_with_one_line(tmp_path):
    from cell.stages.calibrate import refuse_duplicates
    from cell.stages.close_loop import _plan_stations

    with pytest.raises(RecordError, match=r"acquisition.json lists 1 image\(s\) more than once \(images/0017.png\)"):
        refuse_duplicates("acquisition.json", "image", ["images/0016.png", "images/0017.png", "images/0017.png"])
    refuse_duplicates("acquisition.json", "image", ["images/0016.png", "images/0017.png"])
    ctx = _ctx(tmp_path, [_st("S001"), _st("L1-01", 7, 1), _st("L1-01", 7, 1)])
    with pytest.raises(RecordError, match="plan.json lists 1 station"):
        _plan_stations(ctx)


# --- finding 1 end to end: the loop off does not drop the requirement ---------------------------------------
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_requirement_with_the_closed_loop_off_is_checked_and_said(tmp_path):
    # no deviations: every target within its tolerance, so only the precision can keep the part from a PASS
    job = job_variant(tmp_path / "job", {"planning": {"required_sigma": 0.0008, "closed_loop": False},
                                         "sim": {"deviations": None}})
    res = run_cell("run", str(job), "--archive", str(tmp_path / "archive"), "--yes", timeout=280)
    assert res.doc is not None, res.stderr[-3000:]
    folder = Path(res.doc["folder"])
    report = json.loads((folder / "report.json").read_text())
    assert report["verdict"] == "INCOMPLETE", report["verdict_reasons"]
    pr = report["precision_requirement"]
    assert pr["closed_loop"] is False and pr["required_sigma_m"] == pytest.approx(0.8e-6)
    assert pr["n_met"] < pr["n_judged"] and pr["short"]
    assert any("measured less precisely than required" in r for r in report["verdict_reasons"])
    t = next(t for t in report["targets"] if t["id"] == pr["short"][0])
    assert t["required_met"] is False and t["required_sigma_m"] == pytest.approx(0.8e-6)
    html = (folder / "report.html").read_text()
    assert 'id="precision-requirement"' in html and "closed loop off" in html
