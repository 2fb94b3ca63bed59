"""The detector model's saturation term: a clipped dot's extra variance by its clipped share and its size
(decision 0037), fitted by maximum likelihood, stored and used by ADJUST and the pre-analysis alike."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from calibration.detector_model import (DetectorModel, fit_saturation, load_model, observation_covariances,
                                        observation_geometry)
from calibration.errors import CalibrationError

BASE = DetectorModel(0.0043, 0.0030, 1.5, 2.4, "5", 0.27, 0.002, 6.0, m_saturation=4.0)


def test_the_saturation_term_grows_with_the_clipped_share_and_the_dots_size():
    rho = np.array([0.0, 0.6, 0.6, 0.8])
    d = np.array([30.0, 20.0, 36.0, 20.0])
    v = BASE.saturation_var(rho, d)
    assert v[0] == 0.0  # an unclipped dot has none
    assert v[1] == pytest.approx(0.002**2 * 0.6**6.0)  # at the reference size the size factor is one
    assert v[2] / v[1] == pytest.approx((36.0 / 20.0) ** 4.0)
    assert v[3] > v[1]
    # a model with a size term cannot be evaluated without the sizes: no silent default
    with pytest.raises(CalibrationError, match="diameter"):
        BASE.saturation_var(rho)
    # a model without one (before version 5) needs none, and gives what it gave
    old = replace(BASE, m_saturation=0.0)
    assert np.array_equal(old.saturation_var(rho), old.saturation_var(rho, d))


def test_observation_covariances_add_the_size_dependent_term():
    sig = np.full(3, 0.005)
    C = observation_covariances(sig, None, BASE, clipped_share=np.array([0.0, 0.7, 0.7]),
                                diameter_px=np.array([20.0, 20.0, 40.0]))
    assert C.shape == (3, 2, 2)
    assert C[0, 0, 0] == pytest.approx(0.005**2)
    extra = C[:, 0, 0] - 0.005**2
    assert extra[2] / extra[1] == pytest.approx(2.0**4.0)
    assert np.allclose(C[:, 0, 1], 0.0)


def test_fit_saturation_recovers_a_size_term_it_was_drawn_with():
    rng = np.random.default_rng(5)
    n = 20000
    truth = replace(BASE, c_saturation=0.0015, k_saturation=5.0, m_saturation=8.0)
    inc = rng.uniform(10, 60, n)
    d = rng.uniform(18, 38, n)
    rho = rng.uniform(0.4, 0.85, n)
    var = truth.sigma_px(np.radians(inc), d) ** 2 + truth.saturation_var(rho, d)
    e = rng.standard_normal((n, 2)) * np.sqrt(var)[:, None]
    c, k, m = fit_saturation(truth, inc, d, e, rho, size=True)
    assert m == pytest.approx(8.0, abs=1.5)
    fitted = replace(truth, c_saturation=c, k_saturation=k, m_saturation=m)
    big = d > 33
    for model, lo, hi in ((fitted, 0.95, 1.05), (replace(fitted, m_saturation=0.0), 1.1, np.inf)):
        z2 = np.sum(e[big] ** 2, axis=1) / (model.sigma_px(np.radians(inc[big]), d[big]) ** 2
                                            + model.saturation_var(rho[big], d[big]))
        assert lo < np.sqrt(np.mean(z2) / 2) < hi  # without the size term the large dots are understated
    # held at zero when asked
    assert fit_saturation(truth, inc, d, e, rho, size=False)[2] == 0.0


def test_the_stored_model_round_trips_its_size_term(tmp_path):
    doc = BASE.to_dict()
    assert doc["m_saturation"] == 4.0
    p = tmp_path / "model.json"
    p.write_text(json.dumps(doc))
    m = load_model(str(p))
    assert m.m_saturation == 4.0 and m.k_saturation == 6.0
    del doc["m_saturation"]  # a model file before version 5
    p2 = tmp_path / "old.json"
    p2.write_text(json.dumps(doc))
    assert load_model(str(p2)).m_saturation == 0.0


def test_observation_geometry_gives_the_dots_size_in_pixels():
    # a camera 0.5 m above a dot facing it: d = f D / depth, incidence 0; moved sideways: oblique
    cam_from_part = np.eye(4)
    cam_from_part[2, 3] = 0.5
    pts = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0]])
    nrm = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    theta, d = observation_geometry(pts, nrm, cam_from_part[None], np.zeros(2, int), np.arange(2), 2000.0, 0.005)
    assert d[0] == pytest.approx(2000.0 * 0.005 / 0.5)
    assert theta[0] == pytest.approx(0.0, abs=1e-12)
    assert theta[1] == pytest.approx(np.arctan2(0.2, 0.5))
    assert load_model().saturation_var(np.array([0.7]), d[:1]).shape == (1,)


def test_the_shipped_model_says_it_is_the_version_with_the_size_term():
    # the size term and the auto centre's c_background came with version 5 (decision 0037); a record that says
    # "version 4" would name the model measured for the centroid
    model = load_model()
    assert model.m_saturation != 0.0
    assert int(model.version) >= 5
    assert "(version 5)" in model.describe()


def test_a_centroid_centred_dot_next_to_an_edge_is_weighed_at_the_centroids_share():
    # the model's c_background (version 5) is the ellipse centre's; the centroid errs by ~4x its share: a dot with a
    # bound centred by its centroid (a photograph's detector, a failed ellipse fit, a job measured before decision
    # 0037: no ellipse_centre) is stated at the centroid's share, not silently at the ellipse's
    from calibration.detector_model import C_BACKGROUND_CENTROID
    from cell.stages.adjust import centroid_bounds_scaled, ellipse_centred

    model = load_model()
    assert model.c_background < 0.5 * C_BACKGROUND_CENTROID
    obs = {"images": [{"ids": ["A", "B", "C"], "ellipse_centre": [True, False, False]}, {"ids": ["A", "D"]}]}
    ell = ellipse_centred(obs)
    assert ell.tolist() == [True, False, False, False, False]
    B = np.zeros((5, 2, 2))
    B[[0, 1, 3]] = np.diag([0.04, 0.01])  # C and D have no bound
    scaled, hit = centroid_bounds_scaled(B, ell, model)
    assert hit.tolist() == [False, True, False, True, False]
    sig = np.full(5, 0.004)
    C = observation_covariances(sig, scaled, model)
    extra = C[:, 0, 0] - sig**2
    assert extra[0] == pytest.approx(model.c_background**2 * 0.04)  # the ellipse centre: the model's share
    assert extra[1] == pytest.approx(C_BACKGROUND_CENTROID**2 * 0.04)  # the centroid: its own
    assert extra[3] == pytest.approx(C_BACKGROUND_CENTROID**2 * 0.04)
    assert extra[2] == extra[4] == pytest.approx(0.0)
    # a model whose c_background is the centroid's (before version 5) is left as it is
    old = replace(model, version="4")
    assert np.array_equal(centroid_bounds_scaled(B, ell, old)[0], B)


def _optimiser_out_of_evaluations(monkeypatch, n: int) -> None:
    """scipy's minimize, stopped after ``n`` evaluations: the fits must refuse where it stopped."""
    import scipy.optimize

    real = scipy.optimize.minimize
    monkeypatch.setattr(scipy.optimize, "minimize", lambda fun, x0, method=None, options=None: real(
        fun, x0, method=method, options={**(options or {}), "maxfev": n, "maxiter": n}))


def test_a_saturation_fit_that_does_not_converge_is_refused(monkeypatch):
    rng = np.random.default_rng(2)
    n = 400
    inc, d, rho = rng.uniform(10, 60, n), rng.uniform(18, 38, n), rng.uniform(0.4, 0.85, n)
    e = rng.standard_normal((n, 2)) * np.sqrt(BASE.sigma_px(np.radians(inc), d) ** 2 + BASE.saturation_var(rho, d))[:, None]
    fit_saturation(BASE, inc, d, e, rho, size=True)  # converges as it is
    _optimiser_out_of_evaluations(monkeypatch, 30)
    with pytest.raises(CalibrationError, match="did not converge"):
        fit_saturation(BASE, inc, d, e, rho, size=True)


def test_a_geometry_fit_that_does_not_converge_is_refused(monkeypatch):
    from calibration.detector_model import fit_model

    rng = np.random.default_rng(3)
    n = 2000
    inc, d = rng.uniform(0, 75, n), rng.uniform(15, 38, n)
    e = rng.standard_normal((n, 2)) * BASE.sigma_px(np.radians(inc), d)[:, None]
    m = fit_model(inc, d, e)  # converges as it is, near the model it was drawn from
    assert m.p == pytest.approx(BASE.p, abs=0.5) and m.q == pytest.approx(BASE.q, abs=0.5)
    _optimiser_out_of_evaluations(monkeypatch, 20)
    with pytest.raises(CalibrationError, match="did not converge"):
        fit_model(inc, d, e)
