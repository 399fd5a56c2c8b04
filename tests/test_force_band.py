"""Each contact's wrench covariance and the coverage of the normal-force bands: by hand on a known
estimate, against the total wrench's covariance where one contact carries everything, and on a
simulated sway whose model matches the world's springs (the band holds the truth)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flexforce.compare.estimators import run_estimator
from flexforce.compare.metrics import BAND_SIGMAS, band_level, force_band
from flexforce.compare.reports.comparison import band_sentences
from flexforce.datasets.estimate import Estimate
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator


@pytest.fixture(scope="module")
def sway():
    sc = Scenario.load("sway")
    sc.duration = 4.0
    return Simulator(sc).run()


@pytest.fixture(scope="module")
def step():
    sc = Scenario.load("step")
    return Simulator(sc).run()


def truth_with_band(rec, sigma: float) -> Estimate:
    """The truth as an estimate, each active contact's force given an isotropic ``sigma`` (N)."""
    tr = rec.truth
    cov = np.zeros((rec.n, len(rec.contact_names), 6, 6))
    cov[rec.contact_active] = np.diag([sigma**2] * 3 + [1.0] * 3)
    return Estimate(estimator="truth", t_ns=rec.t_ns.copy(), contact_names=rec.contact_names, R=tr.R.copy(),
                    t=tr.t.copy(), w=tr.w.copy(), v=tr.v.copy(), dw=tr.dw.copy(), a=tr.a.copy(),
                    wrench=tr.wrench.copy(), cop=tr.cop.copy(), contact_wrench_cov=cov)


def test_band_by_hand(sway):
    est = truth_with_band(sway, 2.0)
    b = force_band(est, sway)
    pairs = int(sway.contact_active.sum())
    assert b["samples"] == pairs and b["coverage"] == 1.0 and b["z_rms"] == 0.0
    assert b["median_sigma_N"] == pytest.approx(2.0)
    assert b["level"] == pytest.approx(math.erf(BAND_SIGMAS / math.sqrt(2))) == pytest.approx(0.9545, abs=1e-4)
    # push every normal force 3 N off along the contact normal: outside a 2 x 1 N band, inside 2 x 2 N
    normal = np.einsum("nij,ncjk->ncik", est.R, sway.contact_R)[..., :, 2]
    est.wrench = est.wrench.copy()
    est.wrench[..., :3] += 3.0 * normal * sway.contact_active[..., None]
    assert force_band(est, sway)["coverage"] == 1.0
    assert force_band(est, sway)["z_rms"] == pytest.approx(1.5)
    est.contact_wrench_cov = est.contact_wrench_cov / 4.0
    tight = force_band(est, sway)
    assert tight["coverage"] == 0.0 and tight["z_rms"] == pytest.approx(3.0)
    assert set(tight["per_contact"]) == set(sway.contact_names)
    assert sum(d["samples"] for d in tight["per_contact"].values()) == pairs
    est.contact_wrench_cov = None
    assert force_band(est, sway) == {}


def test_band_sentences():
    def row(c, z):
        return {"force_band": {"samples": 100, "coverage": c, "z_rms": z, "level": band_level(), "k_sigma": 2.0}}

    s = {"recording": {"has_truth": False}, "estimators": {"ekf": row(0.96, 1.0), "batch": row(0.25, 8.0)}}
    (text,) = band_sentences(s)
    assert "should hold the reference in 95 %" in text and "they do in ekf" in text
    assert "batch 25 % (errors ×8 the band's σ)" in text
    assert band_sentences({"estimators": {"ekf": {}}}) == []


@pytest.mark.parametrize("name", ["ekf", "fixed-lag", "batch"])
def test_one_contact_carries_the_total_covariance(step, name):
    """Where one contact is in force, its wrench covariance is the total wrench's."""
    est = run_estimator(name, step)
    assert est.contact_wrench_cov is not None
    assert est.contact_wrench_cov.shape == (step.n, len(step.contact_names), 6, 6)
    assert not est.contact_wrench_cov[~step.contact_active].any()
    single = np.flatnonzero(step.contact_active.sum(axis=1) == 1)
    assert single.size > 20
    i = step.contact_active[single].argmax(axis=1)
    per = est.contact_wrench_cov[single, i]
    np.testing.assert_allclose(per, est.wrench_cov[single], rtol=1e-6, atol=1e-9 * np.abs(est.wrench_cov[single]).max())


def test_band_holds_the_truth_on_a_matched_sway(sway):
    """The sway's springs are the robot configuration's, as the estimators assume: their bands hold
    the truth about as often as they say.  Measured on this 4 s sway: 0.976 (EKF) and 0.987
    (fixed-lag) of the pairs within 2 sigma, normalised RMS 0.888 and 0.889 (on its first 3 s,
    0.872 and 0.896, RMS 1.25 and 1.20).  Asserted: coverage at least 0.93 and the normalised RMS
    within 0.7-1.1 (margins 0.05 and 0.2)."""
    for name in ("ekf", "fixed-lag"):
        b = force_band(run_estimator(name, sway), sway, skip=0.5)
        assert b["coverage"] >= 0.93, (name, b)
        assert 0.7 <= b["z_rms"] <= 1.1, (name, b)


def test_estimate_keeps_the_contact_covariance(sway, tmp_path):
    est = truth_with_band(sway, 1.5)
    back = Estimate.load(est.save(tmp_path / "e.npz"))
    np.testing.assert_array_equal(back.contact_wrench_cov, est.contact_wrench_cov)
