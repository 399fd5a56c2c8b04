"""Metrics and reports on estimates whose errors are known by construction."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flexforce.compare.metrics import chi2_mean_bounds, evaluate
from flexforce.compare.reports.comparison import write_report
from flexforce.compare.runner import Comparison, aggregate, describe
from flexforce.datasets.estimate import Estimate
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.factors import so3


@pytest.fixture(scope="module")
def rec():
    sc = Scenario.load("push-pitch")
    sc.duration = 1.5
    return Simulator(sc, noise=False).run()


def truth_estimate(rec, name="perfect", cov_scale=1e-6):
    tr = rec.truth
    n = rec.n
    return Estimate(estimator=name, t_ns=rec.t_ns.copy(), contact_names=rec.contact_names, R=tr.R.copy(),
                    t=tr.t.copy(), w=tr.w.copy(), v=tr.v.copy(), dw=tr.dw.copy(), a=tr.a.copy(),
                    wrench=tr.wrench.copy(), cop=tr.cop.copy(), cov=np.tile(np.eye(18) * cov_scale, (n, 1, 1)),
                    time_per_step=np.full(n, 1e-5), total_time=n * 1e-5)


def test_perfect_estimate_has_zero_error(rec):
    m = evaluate(truth_estimate(rec), rec, skip=0.0)
    for key, value in m.rmse.items():
        assert value == pytest.approx(0.0, abs=1e-9), key
    assert m.nees == pytest.approx(0.0, abs=1e-9)
    assert m.time_per_step["median"] == pytest.approx(1e-5)


def test_known_errors_are_measured(rec):
    est = truth_estimate(rec, "biased", cov_scale=1.0)
    delta = np.array([0.0, 0.002, 0.0])
    est.R = np.array([so3.exp(delta) @ R for R in est.R])
    est.t = est.t + np.array([0.0, 0.0, 0.001])
    est.wrench = est.wrench.copy()
    est.wrench[:, 0, 2] += 5.0  # 5 N more on the left foot
    est.cop = est.cop + np.array([0.01, 0.0, 0.0])
    m = evaluate(est, rec, skip=0.0)
    assert m.rmse["rotation_rad"] == pytest.approx(0.002, rel=1e-9)
    assert m.rmse["translation_m"] == pytest.approx(0.001, rel=1e-9)
    assert m.rmse["force_N"] == pytest.approx(5.0, rel=1e-9)
    assert m.rmse["cop_m"] == pytest.approx(0.01, rel=1e-9)
    # hands: rotation about y of 2 mrad at ~0.8 m height plus 1 mm: a few mm
    assert 0.001 < m.rmse["hand_m"] < 0.004
    assert m.extra["hand_displacement_by_flexibility_max_m"] > 0.001
    # NEES with unit covariance: the squared error
    assert m.nees == pytest.approx(0.002**2 + 0.001**2, rel=1e-6)


def test_chi2_bounds_contain_the_dof():
    lo, hi = chi2_mean_bounds(18, 1000)
    assert lo < 18 < hi and hi - lo < 2.0


def test_report_folder_holds_what_the_table_shows(rec, tmp_path):
    comp = Comparison(recording=describe(rec))
    for name, scale in (("ekf", 1.234), ("batch", 0.617)):
        est = truth_estimate(rec, name)
        est.wrench = est.wrench.copy()
        est.wrench[:, :, 2] += scale
        est.wrench_cov = np.tile(np.eye(6), (rec.n, 1, 1))
        est.cop_cov = np.tile(np.eye(2) * 1e-6, (rec.n, 1, 1))
        est.residuals = {"imu": np.random.default_rng(0).standard_normal((rec.n, 6))}
        est.residual_labels = {"imu": tuple(f"axis {i}" for i in range(6))}
        comp.estimates[name] = est
        comp.metrics[name] = evaluate(est, rec)
    out = write_report(comp, rec, tmp_path / "report")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["estimators"]["ekf"]["rmse"]["force_N"] == pytest.approx(2 * 1.234)  # two contacts
    assert summary["rmse_relative_to_ekf"]["batch"]["force_N"] == pytest.approx(0.5)
    for key in ("force_N", "moment_Nm", "cop_m", "rotation_rad", "translation_m", "hand_m"):
        assert key in summary["estimators"]["batch"]["rmse"]
    page = (out / "index.html").read_text()
    assert "<td>2.47</td>" in page  # the table shows the summary's number
    for fig in ("forces.png", "flexibility.png", "errors.png", "residuals.png", "consistency.png"):
        assert (out / fig).stat().st_size > 10_000, fig
        assert fig in page
    agg = aggregate([comp, comp])
    assert agg["estimators"]["ekf"]["rmse"]["force_N"] == pytest.approx(2 * 1.234)
    assert agg["estimators"]["ekf"]["rmse_std"]["force_N"] == pytest.approx(0.0)


def test_estimate_save_load_round_trip(rec, tmp_path):
    est = truth_estimate(rec, "x")
    est.residuals = {"imu": np.ones((rec.n, 6))}
    est.residual_labels = {"imu": ("a",) * 6}
    path = est.save(tmp_path / "est")
    back = Estimate.load(path)
    np.testing.assert_array_equal(back.R, est.R)
    np.testing.assert_array_equal(back.cov, est.cov)
    np.testing.assert_array_equal(back.residuals["imu"], est.residuals["imu"])
    assert back.contact_names == est.contact_names and back.estimator == "x"


def test_six_axis_ft_give_the_contacts_moment_and_sole_cop_errors(rec):
    """Without a truth the errors are against the reference sensors; six-axis F/T measure the
    contacts' moments too, so the contact moment and sole-CoP errors come with the forces'."""
    import dataclasses

    real = dataclasses.replace(rec, truth=None)  # the simulated F/T, noiseless: the true wrenches
    est = truth_estimate(rec)
    m = evaluate(est, real, skip=0.0)
    assert m.reference == "sensors"
    for key in ("vertical_force_N", "contact_force_N", "contact_moment_Nm", "contact_cop_m"):
        assert m.rmse[key] == pytest.approx(0.0, abs=1e-6), key
        assert m.references[key] == "reference: F/T"
    est.wrench = est.wrench.copy()
    est.wrench[:, 0, 3] += 2.0  # 2 N m more about the left sole's x (world and sole axes alike here)
    m = evaluate(est, real, skip=0.0)
    on = rec.contact_active
    # the RMS over every (step, contact) the F/T read: 2 N m on the left foot's, 0 on the right's
    assert m.rmse["contact_moment_Nm"] == pytest.approx(2.0 * np.sqrt(on[:, 0].sum() / on.sum()), rel=0.05)
    assert m.rmse["contact_cop_m"] > 0.0 and m.rmse["vertical_force_N"] == pytest.approx(0.0, abs=1e-6)
    # F/T reading the vertical force alone (the iCub's): no moment, no sole CoP
    only_z = dataclasses.replace(real, ft=np.where(np.arange(6) == 2, rec.ft, np.nan))
    m = evaluate(est, only_z, skip=0.0)
    assert "contact_moment_Nm" not in m.rmse and "contact_cop_m" not in m.rmse


def test_aligned_tilt_takes_out_a_constant_marker_rotation(rec):
    """Motion capture whose markers sit 10 mrad off the base frame: the raw tilt error of a perfect
    estimate is that constant, the aligned one nothing; a 5 mrad sinusoidal pitch error on top is
    what the alignment leaves (its RMS, 5 / sqrt 2 mrad)."""
    import dataclasses

    from scipy.spatial.transform import Rotation

    from flexforce.compare.metrics import aligned_tilt, base_tilt_error

    R_local = Rotation.from_quat(rec.base_pose[:, 3:]).as_matrix()
    R_base = np.einsum("nij,njk->nik", rec.truth.R, R_local)  # the base in the world
    markers = Rotation.from_rotvec([0.01, 0.0, 0.0]).as_matrix()
    pose = np.zeros((rec.n, 7))
    pose[:, 3:] = Rotation.from_matrix(R_base @ markers).as_quat()
    mocap_rec = dataclasses.replace(rec, mocap={"base": pose})
    keep = np.ones(rec.n, dtype=bool)
    est = truth_estimate(rec)
    raw = base_tilt_error(est, mocap_rec, "base")
    assert np.sqrt(np.mean(raw**2)) == pytest.approx(0.01, rel=0.02)
    out = aligned_tilt(est, mocap_rec, "base", keep)
    assert np.hypot(*out["tilt_offset_rad"]) == pytest.approx(0.01, rel=0.02)
    # measured 1.3e-6 rad (second order: the base's own tilt times the markers' 10 mrad); margin x10
    assert out["tilt_aligned_rad"] < 1.5e-5
    # a pitch error varying about zero stays
    wobble = 0.005 * np.sin(2 * np.pi * 2.0 * rec.time)
    est.R = np.einsum("nij,njk->nik", est.R, Rotation.from_rotvec(np.c_[0 * wobble, wobble, 0 * wobble]).as_matrix())
    out = aligned_tilt(est, mocap_rec, "base", keep)
    assert out["tilt_aligned_rad"] == pytest.approx(0.005 / np.sqrt(2), rel=0.05)
    # an estimate with a gap (NaN rows) is judged where it has values; one without any gives nothing
    est.R = est.R.copy()
    est.R[: rec.n // 3] = np.nan
    gap = aligned_tilt(est, mocap_rec, "base", keep)
    assert np.isfinite(gap["tilt_aligned_rad"]) and np.all(np.isfinite(gap["tilt_offset_rad"]))
    est.R[:] = np.nan
    assert aligned_tilt(est, mocap_rec, "base", keep) == {}


def test_aligned_tilt_sentence_lowest_first():
    from flexforce.compare.reports.comparison import aligned_tilt_sentences

    summary = {"estimators": {"batch": {"extra": {"tilt_aligned_rad": 0.011, "tilt_offset_rad": [0.0077, 0.0007]}},
                              "ekf": {"extra": {}}},
               "peers": {"gtsam_fixed_lag": {"extra": {"tilt_aligned_rad": 0.0134,
                                                       "tilt_offset_rad": [-0.003, -0.003]}}}}
    (text,) = aligned_tilt_sentences(summary)
    assert text.index("batch 11.0 mrad (constant 7.7, 0.7)") < text.index("gtsam_fixed_lag 13.4 mrad")
    assert "ekf" not in text
    assert aligned_tilt_sentences({"estimators": {"ekf": {}}}) == []
