"""Several scale bars (decision 0041): every usable bar enters the adjustment, their certificates are tested against
each other, a bar that fails or whose end cannot be trusted is left out by name, two bars that disagree fault the
job, and report.json's ``scale_bar_gains`` are the aligned deviations' change per metre of each certificate.

Synthetic networks of the example part with a known truth (exact projections of the nominal targets + 0.01 px
noise, ADJUST's own ``run_bundle``; the fixture of tests/test_adjust_trust.py)."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from jobutil import REPO
from test_adjust_trust import _ctx, _with_shape_drops, blunder_across_epipolar, example  # noqa: F401  (the fixture)

from calibration.alignment import PointCovariance
from calibration.bundle import BundleConfig, BundleOptions, ScaleBar, bundle_adjust, simulate_network
from calibration.bundle.bartest import bar_residual_test
from calibration.bundle.coherent import certificate_at_face_value, scale_bar_gains
from calibration.errors import CalibrationError
from cell.stages.adjust import run_bundle

SIGMA = 2e-6  # each certificate's sigma (m)


def _bars(job, obs, n: int) -> tuple:
    """``n`` bars between well-observed targets (7 images or more), long and with distinct ends, certified at the
    truth (the network's nominal targets) with :data:`SIGMA`."""
    t = job.part.targets
    counts = np.bincount(np.concatenate([s for s, _ in obs]), minlength=len(t.ids))
    good = [int(i) for i in np.flatnonzero(counts >= 7)]
    pairs, used = [], set()
    cand = sorted(((float(np.linalg.norm(t.xyz[i] - t.xyz[j])), i, j) for i in good for j in good if i < j),
                  reverse=True)
    for L, i, j in cand:
        if i not in used and j not in used:
            pairs.append((i, j, L, SIGMA))
            used |= {i, j}
        if len(pairs) == n:
            return tuple(pairs)
    raise AssertionError("the synthetic network has too few well-observed targets for the bars")


def _off(bars, j: int, sigmas: float):
    """``bars`` with bar ``j``'s certificate off by ``sigmas`` of its sigma."""
    return tuple((a, b, L + sigmas * s if k == j else L, s) for k, (a, b, L, s) in enumerate(bars))


def test_three_consistent_bars_are_all_used_and_pass_their_test(tmp_path, example):
    job, poses, obs = example
    bars = _bars(job, obs, 3)
    ctx, said = _ctx(tmp_path, replace(job, scale_bars=bars), poses, obs)
    doc = run_bundle(ctx)
    sb = doc["scale_bars"]
    assert doc["datum"] == "scale_bar" and doc["screening"]["scale_established"] is True
    assert [d["used"] for d in sb] == [True] * 3 and [d["gain_column"] for d in sb] == [0, 1, 2]
    assert all(d["test"] == "pass" and abs(d["normalised_residual"]) < d["critical"] for d in sb)
    # the residual's sigma is below the certificate's (the others' scale adds information) and the bars' adjusted
    # lengths are the truth within their stated sigma
    for d, (a, b, L, s) in zip(sb, bars):
        assert 0 < d["residual_sigma_m"] < s and 0 < d["certificate_weight"] < 1
        assert abs(d["adjusted_length_m"] - L) < 5 * s
    assert len(doc["snooping"]["protected"]) >= 3 and all("tested against the other 2 bars" in p
                                                          for p in doc["snooping"]["protected"][:3])
    with np.load(tmp_path / "bundle_covariance.npz") as z:
        assert z["K"].shape == (len(job.part.targets.ids), 3, 3) and z["K_sigma"].shape == (3,)


def test_a_certificate_off_by_ten_sigma_among_three_is_left_out_and_the_result_is_the_adjustment_without_it(
        tmp_path, example):
    job, poses, obs = example
    bars = _bars(job, obs, 3)
    ctx, said = _ctx(tmp_path / "three", replace(job, scale_bars=_off(bars, 1, 10.0)), poses, obs)
    doc = run_bundle(ctx)
    sb = doc["scale_bars"]
    ids = job.part.targets.ids
    name = f"{ids[bars[1][0]]}-{ids[bars[1][1]]}"
    assert [d["used"] for d in sb] == [True, False, True]
    assert sb[1]["left_out"].startswith(f"scale bar {name}: its certificate disagrees with the other bars")
    assert [d["gain_column"] for d in sb] == [0, None, 1]
    assert any(f"scale bar {name}: its certificate disagrees" in str(m) and "adjusting again with the other 2" in str(m)
               for m in said)
    assert doc["screening"]["scale_bars"][1] == {"bar": name, "used": False, "reason": sb[1]["left_out"]}
    # the same as the job with the two good bars only
    ctx2, _ = _ctx(tmp_path / "two", replace(job, scale_bars=(bars[0], bars[2])), poses, obs)
    ref = run_bundle(ctx2)
    got = np.array([t["xyz"] for t in doc["targets"]], dtype=float)
    want = np.array([t["xyz"] for t in ref["targets"]], dtype=float)
    np.testing.assert_allclose(got, want, atol=1e-10, equal_nan=True)
    np.testing.assert_allclose(doc["sigma0_px"], ref["sigma0_px"], rtol=1e-9)
    assert [d["normalised_residual"] for d in (sb[0], sb[2])] == pytest.approx(
        [d["normalised_residual"] for d in (ref["scale_bars"][0], ref["scale_bars"][1])], rel=1e-6)


def test_two_bars_that_disagree_fault_the_job_naming_both(tmp_path, example):
    job, poses, obs = example
    bars = _bars(job, obs, 2)
    ctx, _ = _ctx(tmp_path, replace(job, scale_bars=_off(bars, 0, 10.0)), poses, obs)
    ids = job.part.targets.ids
    with pytest.raises(CalibrationError, match="^scale bars disagree: ") as e:
        run_bundle(ctx)
    msg = str(e.value)
    assert all(f"{ids[a]}-{ids[b]} adjusted minus certificate" in msg for a, b, _, _ in bars) and "\n" not in msg


def test_a_bar_with_an_end_unlike_its_ellipse_is_left_out_and_the_job_measures_with_the_others(tmp_path, example):
    job, poses, obs = example
    bars = _bars(job, obs, 3)
    ids = job.part.targets.ids
    # the third bar's end: a target seen in 5 to 10 of the 14 images (room for more images unlike it than kept it)
    t = job.part.targets
    counts = np.bincount(np.concatenate([s for s, _ in obs]), minlength=len(ids))
    a = next(int(i) for i in np.flatnonzero((counts >= 5) & (counts <= 10) & (t.kind != "coded"))
             if int(i) not in {e for bar in bars for e in bar[:2]})
    b = bars[2][1]
    bars = bars[:2] + ((a, b, float(np.linalg.norm(t.xyz[a] - t.xyz[b])), SIGMA),)
    ctx, said = _ctx(tmp_path, replace(job, scale_bars=bars), poses, obs)
    kept = int(counts[a])
    _with_shape_drops(tmp_path, obs, ids[a], kept + 1)
    doc = run_bundle(ctx)
    sb = doc["scale_bars"]
    assert doc["screening"]["scale_established"] is True and doc["datum"] == "scale_bar"
    assert [d["used"] for d in sb] == [True, True, False]
    assert f"{ids[a]} unlike its ellipse in {kept + 1} of the {2 * kept + 1} images" in sb[2]["left_out"]
    assert all(d["test"] == "pass" for d in sb[:2])
    assert any("bar left out" in m for _, m in said)
    # the scale from the two bars left: the third bar's length comes out right all the same
    xyz = np.array([t["xyz"] for t in doc["targets"]], dtype=float)
    assert abs(np.linalg.norm(xyz[bars[2][0]] - xyz[bars[2][1]]) - bars[2][2]) < 10e-6


def test_one_bar_says_its_certificate_is_not_tested(tmp_path, example):
    job, poses, obs = example
    ctx, _ = _ctx(tmp_path, job, poses, obs)
    doc = run_bundle(ctx)
    (d,) = doc["scale_bars"]
    assert d["used"] and d["test"].startswith("not tested: one bar") and d["normalised_residual"] is None
    ids = job.part.targets.ids
    a, b = job.scale_bars[0][:2]
    assert doc["snooping"]["protected"][0].startswith(f"scale bar {ids[a]}-{ids[b]} length (not tested")
    assert "one bar: its certificate is not tested" in doc["snooping"]["protected"][0]


def test_the_normalised_bar_residuals_have_unit_variance_over_noise_draws():
    """The residual's variance of calibration.bundle.bartest against a Monte Carlo of the adjustment: three bars
    whose certificates err by their sigma, images by their sigma; sqrt(mean w^2) ~ 1 over draws."""
    rng = np.random.default_rng(5)
    net = simulate_network(rng, n_targets=60, n_images=8, sigma_px=0.0)  # exact projections; noise drawn below
    pairs = [(0, 30), (10, 45), (20, 55)]
    L = [float(np.linalg.norm(net.points[a] - net.points[b])) for a, b in pairs]
    s = 3e-6
    w = []
    for _ in range(40):
        uv = net.obs_uv + rng.normal(0, 0.05, net.obs_uv.shape)
        bars = tuple(ScaleBar(a, b, Lk + rng.normal(0, s), s) for (a, b), Lk in zip(pairs, L))
        res = bundle_adjust(net.obs_image, net.obs_target, uv, net.intrinsics, net.cam_from_part, net.points,
                            BundleOptions(sigma_px=0.05, snooping=False), BundleConfig(scale_bars=bars))
        K, Ks = scale_bar_gains(res.covariance, res.points, bars, res.variance_factor)
        _, cov = certificate_at_face_value(res.cov, res.covariance, K, Ks, res.variance_factor)
        w.extend(bar_residual_test(res.points, cov, K, bars).w)
    rms = float(np.sqrt(np.mean(np.square(w))))
    assert 0.8 < rms < 1.2, rms


def test_report_scale_bar_gains_are_the_aligned_deviations_change_per_metre_of_a_certificate(tmp_path, example,
                                                                                            monkeypatch):
    """Finite difference: the job adjusted and aligned (REPORT's own functions) with one certificate 0.2 um longer
    (a tenth of its sigma: the bar test passes). The gains are at fixed weights: the detector model's class factors
    (cell/stages/model_shape.py, estimated from the residuals like the variance factor) are those of the first
    adjustment in both."""
    import cell.stages.adjust as adjust_stage
    from cell.stages.report import align_with_gains

    first: dict = {}

    def fixed_factors(*args, **kwargs):
        out = adjust_stage_shape_check(*args, **kwargs)
        first.setdefault("factors", out["factors"])
        return out | {"factors": first["factors"], "reweight": any(f != 1.0 for f in first["factors"])}

    adjust_stage_shape_check = adjust_stage.shape_check
    monkeypatch.setattr(adjust_stage, "shape_check", fixed_factors)
    job, poses, obs = example
    bars = _bars(job, obs, 3)
    h = 0.2e-6
    out = []
    for k, bb in enumerate((bars, _off(bars, 1, h / SIGMA))):
        ctx, _ = _ctx(tmp_path / str(k), replace(job, scale_bars=bb), poses, obs)
        doc = run_bundle(ctx)
        assert all(d["used"] for d in doc["scale_bars"])
        measured = np.array([t["xyz"] for t in doc["targets"]], dtype=float)
        with np.load(tmp_path / str(k) / "bundle_covariance.npz") as z:
            pc = PointCovariance(z["D"], z["U"], z["C"])
            K = z["K"]
        ok = np.isfinite(measured).all(axis=1)
        outcome, Kd = align_with_gains(job, measured, pc, K, ok, doc["datum"])
        out.append((outcome.alignment.deviation, Kd))
    fd = (out[1][0] - out[0][0]) / h
    Kd = out[0][1]
    assert Kd.shape == (len(job.part.targets.ids), 3, 3)
    ok = np.isfinite(fd).all(axis=1) & np.isfinite(Kd[:, :, 1]).all(axis=1)
    assert ok.sum() > 100
    err = np.abs(fd[ok] - Kd[ok, :, 1])
    # (measured: 1.5e-5 against a largest gain of 0.23)
    assert np.max(err) < 1e-3 * np.max(np.abs(Kd[ok, :, 1])), (np.max(err), np.max(np.abs(Kd[ok, :, 1])))
    assert np.max(np.abs(Kd[ok, :, 1])) > 0.01  # a gain worth the name: the test can fail


# --- the whole job ---------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_the_example_with_three_bars_runs_end_to_end_each_bar_planned_tested_and_reported(tmp_path):
    """``cell run`` of the example with its bar and two more (ends without a simulated deviation, certified at their
    CAD distance = the truth): PLAN secures every bar's ends, ADJUST uses and tests all three, report.json and
    report.html carry each bar and the targets' 3 x 3 ``scale_bar_gains``; the measurement meets the truth."""
    from jobutil import job_variant, run_cell, truth_xyz_m

    from cell.loadedjob import load

    ex = load(REPO / "examples/bracket/job.toml")
    index, xyz = ex.part.targets.index(), ex.part.targets.xyz
    pairs = [("T0094", "T0100"), ("T0075", "T0124"), ("T0022", "T0187")]
    bars = [{"a": a, "b": b, "length": round(float(np.linalg.norm(xyz[index[a]] - xyz[index[b]])) * 1e3, 4),
             "sigma": 0.002} for a, b in pairs]
    job = job_variant(tmp_path / "job", {"job": {"scale_bar": None, "scale_bars": bars}})
    run = run_cell("run", str(job), "--archive", str(tmp_path / "archive"), timeout=600)
    assert run.code == 0, run.stderr[-3000:]
    folder = Path(run.doc["folder"])
    plan = json.loads((folder / "plan.json").read_text())
    assert [d["ends"] for d in plan["scale_bars"]] == [list(p) for p in pairs] and "scale_bar" not in plan
    bundle = json.loads((folder / "bundle.json").read_text())
    sb = bundle["scale_bars"]
    assert [d["bar"] for d in sb] == [list(p) for p in pairs]
    assert all(d["used"] and d["test"] == "pass" for d in sb), sb
    assert bundle["screening"]["scale_established"] is True
    assert sum(p.startswith("scale bar ") for p in bundle["snooping"]["protected"]) == 3
    report = json.loads((folder / "report.json").read_text())
    assert [d["bar"] for d in report["scale_bars"]] == [list(p) for p in pairs]
    g = [t["scale_bar_gains"] for t in report["targets"]]
    assert all(x is None or np.shape(x) == (3, 3) for x in g) and sum(x is not None for x in g) > 150
    html = (folder / "report.html").read_text()
    assert all(f"Scale bar {a}-{b}" in html for a, b in pairs)
    assert "Scale bar T0094-T0100" in run.stderr or "scale bar T0094-T0100" in run.stderr
    # the truth: the measured bars' lengths within their stated sigma, and the scale from three bars
    ids, _, true_xyz = truth_xyz_m(job)
    ti = {t: k for k, t in enumerate(ids)}
    for d in sb:
        a, b = (ti[t] for t in d["bar"])
        assert abs(d["adjusted_length_m"] - np.linalg.norm(true_xyz[a] - true_xyz[b])) < 5 * d["certificate_sigma_m"]


def test_a_bar_whose_end_snooping_takes_below_two_rays_is_left_out_by_name_while_the_others_keep_the_scale(
        tmp_path, example):
    """The example's bar end T0094 is seen in two images; one ray 1.2 px off across the epipolar line (as in
    tests/test_adjust_trust.py). With one bar the scale was lost; with two more bars that bar alone is left out (the
    bundle would skip its length silently), named with the image, and the job adjusted again with the others."""
    job, poses, obs = example
    a, b = job.scale_bars[0][:2]
    others = [bar for bar in _bars(job, obs, 4) if a not in bar[:2] and b not in bar[:2]][:2]
    bars = (job.scale_bars[0], *others)
    obs = blunder_across_epipolar(job, poses, obs, a)
    ctx, said = _ctx(tmp_path, replace(job, scale_bars=bars), poses, obs)
    doc = run_bundle(ctx)
    ids = job.part.targets.ids
    sb = doc["scale_bars"]
    assert doc["screening"]["scale_established"] is True and doc["datum"] == "scale_bar"
    assert [d["used"] for d in sb] == [False, True, True]
    # (with the bar redundant, the adjustment spread T0094's error over the bar: snooping took a ray of T0100 too)
    why = sb[0]["left_out"]
    assert why.startswith(f"scale bar {ids[a]}-{ids[b]}: {ids[a]} usable in 1 image(s)") and "(2 needed) after data " \
        "snooping rejected its observation(s) in images/" in why
    assert any("bar left out, adjusting again" in m for _, m in said)
    assert all(d["test"] == "pass" for d in sb[1:])
    # adjusted again without the bar, T0100 keeps both its rays (its ray was taken only for the bar's sake)
    assert next(t for t in doc["targets"] if t["id"] == ids[b])["n_images"] == 2


def test_a_bar_used_but_not_testable_is_said_on_the_console_and_in_the_journal():
    """say_bars: among several bars, one whose residual has no variance is used but untested: a warning names it
    (bundle.json alone was not enough for an operator)."""
    from types import SimpleNamespace

    from cell.stages.scalebars import say_bars

    said, logged, appended = [], [], []
    ctx = SimpleNamespace(say=said.append, log=SimpleNamespace(log=lambda lv, m: logged.append((lv, m))),
                          folder=SimpleNamespace(append=lambda *a, **k: appended.append(k)))
    doc = [{"bar": ["T1", "T2"], "used": True, "left_out": None, "certificate_m": 0.3, "adjusted_length_m": 0.3000001,
            "residual_m": 1e-7, "residual_sigma_m": 1e-6, "normalised_residual": 0.1, "test": "pass"},
           {"bar": ["T3", "T4"], "used": True, "left_out": None, "normalised_residual": None,
            "test": "not tested: the residual has no variance"}]
    say_bars(ctx, doc)
    assert any("T3-T4" in line and "not tested" in line and "WARNING" in line for line in said), said
    assert ("warning", "scale bar T3-T4: used; not tested: the residual has no variance") in logged
    assert appended and len(appended[0]["bars"]) == 2
