"""The baselines without estimation, the per-phase and low-passed errors, the physical violations
and the headline sentences: on hand-built recordings whose answers are known by construction."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from flexforce.compare.baseline import BASELINES, equal_split, leg_odometry, weight_equal
from flexforce.compare.metrics import (
    FRICTION_MU,
    NO_SOLE,
    Metrics,
    lowpass,
    lowpass_key,
    phase_masks,
    phase_metrics,
    violations,
)
from flexforce.compare.reports.comparison import write_report
from flexforce.compare.runner import compare, headline
from flexforce.datasets.estimate import Estimate
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator


@pytest.fixture(scope="module")
def rec():
    sc = Scenario.load("push-pitch")
    sc.duration = 1.0
    return Simulator(sc).run()


def truth_estimate(rec):
    tr = rec.truth
    return Estimate(estimator="truth", t_ns=rec.t_ns.copy(), contact_names=rec.contact_names, R=tr.R.copy(),
                    t=tr.t.copy(), w=tr.w.copy(), v=tr.v.copy(), dw=tr.dw.copy(), a=tr.a.copy(),
                    wrench=tr.wrench.copy(), cop=tr.cop.copy())


def test_equal_split_by_hand():
    feet = np.array([[0.0, 0.1], [0.0, -0.1], [0.3, 0.0]])
    np.testing.assert_allclose(equal_split(np.array([5.0, 5.0]), feet, 300.0), [100.0] * 3)
    np.testing.assert_allclose(equal_split(np.zeros(2), feet[:1], 300.0), [300.0])
    assert equal_split(np.zeros(2), feet[:0], 300.0).shape == (0,)


def test_weight_equal_is_leg_odometry_with_the_equal_split(rec):
    eq, lo = weight_equal(rec), leg_odometry(rec)
    assert eq.meta["kind"] == "baseline" and eq.estimator == "weight-equal"
    np.testing.assert_array_equal(eq.R, lo.R)
    weight = rec.mass * rec.gravity
    np.testing.assert_allclose(eq.total_wrench[:, 2], weight)
    k = rec.contact_active.sum(axis=1)
    np.testing.assert_allclose(eq.wrench[..., 2], rec.contact_active * (weight / np.maximum(k, 1))[:, None])
    assert not eq.wrench[..., :2].any()
    assert list(BASELINES) == ["leg-odometry", "weight-equal"]


def test_phase_masks_by_hand(rec):
    import dataclasses

    n = 40
    act = np.ones((n, 2), dtype=bool)
    act[20:, 1] = False  # right foot lifts at sample 20
    r = dataclasses.replace(rec.slice(0, n), contact_active=act)
    t = r.time
    m = phase_masks(r, skip=0.0, window=0.05)
    near = np.abs(t - t[20]) <= 0.05
    np.testing.assert_array_equal(m["transition"], near)
    np.testing.assert_array_equal(m["single_support"], (np.arange(n) >= 20) & ~near)
    np.testing.assert_array_equal(m["double_support"], (np.arange(n) < 20) & ~near)
    assert m["all"].all()
    assert not phase_masks(r, skip=t[10])["all"][:10].any()


def test_lowpass_keeps_a_slow_sine_and_removes_a_fast_one():
    rate = 100.0
    t = np.arange(1000) / rate
    slow, fast = np.sin(2 * np.pi * 0.5 * t), 0.5 * np.sin(2 * np.pi * 20 * t)
    y = lowpass(slow + fast, 5.0, rate)
    np.testing.assert_allclose(y[50:-50], slow[50:-50], atol=2e-3)
    # a NaN gap: each finite run filtered on its own, the gap stays NaN
    x = (slow + fast)[:, None].repeat(2, axis=1)
    x[400:410, 0] = np.nan
    z = lowpass(x, 5.0, rate)
    assert np.isnan(z[400:410, 0]).all() and np.isfinite(z[:400, 0]).all() and np.isfinite(z[:, 1]).all()
    with pytest.raises(ValueError, match="Nyquist"):
        lowpass(x, 60.0, rate)


def test_phase_metrics_of_a_known_force_offset(rec):
    # the truth itself as the estimate, then 3 N more on every active foot: per-foot 3 N where in
    # contact, total 3 N per contact in force
    perfect = truth_estimate(rec)
    biased = truth_estimate(rec)
    biased.wrench = biased.wrench.copy()
    # +3 N along each contact's normal (world z here: the feet are flat), about the contact point
    for k in range(rec.n):
        for i in np.flatnonzero(rec.contact_active[k]):
            n_w = rec.truth.R[k] @ rec.contact_R[k, i][:, 2]
            p_w = rec.truth.R[k] @ rec.contact_p[k, i] + rec.truth.t[k]
            biased.wrench[k, i, :3] += 3.0 * n_w
            biased.wrench[k, i, 3:] += np.cross(p_w, 3.0 * n_w)
    m0, m1 = Metrics("perfect"), Metrics("biased")
    phase_metrics(m0, perfect, rec)
    phase_metrics(m1, biased, rec)
    for phase, d in m0.per_phase.items():
        if d["samples"]:
            assert d["rmse"]["foot_vertical_force_N"] == pytest.approx(0.0, abs=1e-9), phase
            assert d[lowpass_key()]["total_vertical_force_N"] == pytest.approx(0.0, abs=1e-9), phase
    on = rec.contact_active
    d = m1.per_phase["all"]["rmse"]
    assert d["foot_vertical_force_N"] == pytest.approx(3.0 * np.sqrt(on.sum() / on.size), rel=1e-6)
    assert d["total_vertical_force_N"] == pytest.approx(3.0 * np.sqrt(np.mean(on.sum(axis=1) ** 2)), rel=1e-6)
    assert d["rotation_rad"] is None  # no rotation error series in a bare Metrics
    assert set(m1.per_phase) == {"all", "single_support", "double_support", "transition"}
    assert m1.to_dict()["per_phase"]["all"]["samples"] == rec.n


def test_violations_counted_by_hand(rec):
    est = weight_equal(rec)
    v = violations(est, rec)
    assert v["samples_in_contact"] == int(rec.contact_active.sum())
    assert v["friction_mu"] == FRICTION_MU
    assert v["negative_normal"]["count"] == 0 and v["cop_outside_sole"] == {"skipped": NO_SOLE}
    # pull on the first active (step, contact), push one sideways beyond the cone
    k0, i0 = np.argwhere(rec.contact_active)[0]
    k1, i1 = np.argwhere(rec.contact_active)[-1]
    est.wrench = est.wrench.copy()
    est.wrench[k0, i0, :3] = [0.0, 0.0, -10.0]
    est.wrench[k1, i1, :3] = [est.wrench[k1, i1, 2], 0.0, est.wrench[k1, i1, 2]]  # |F_t| = F_z > 0.7 F_z
    v = violations(est, rec, skip=0.0)
    assert v["negative_normal"]["count"] == 1
    assert v["friction_cone"]["count"] == 2
    assert v["friction_cone"]["fraction"] == pytest.approx(2 / v["samples_in_contact"])
    # the equal split's forces sit at the contact origins: inside a sole around the origin, outside
    # one that starts 1 cm ahead of it
    fresh = weight_equal(rec)
    inside = violations(fresh, rec, skip=0.0, sole=(-0.1, 0.1, -0.05, 0.05))["cop_outside_sole"]
    assert inside == {"count": 0, "fraction": 0.0, "sole_m": [-0.1, 0.1, -0.05, 0.05]}
    outside = violations(fresh, rec, skip=0.0, sole=(0.01, 0.1, -0.05, 0.05))["cop_outside_sole"]
    assert outside["count"] == int(rec.contact_active.sum())


def test_comparison_adds_baselines_phases_and_headline(rec, tmp_path):
    comp = compare(rec, estimators=("ekf",), crb=False)
    s = comp.summary()
    assert set(s["baselines"]) == {"leg_odometry", "weight_equal"}
    assert all(b["kind"] == "baseline" for b in s["baselines"].values())
    for row in (s["estimators"]["ekf"], *s["baselines"].values()):
        assert set(row["per_phase"]) == {"all", "single_support", "double_support", "transition"}
        assert lowpass_key() == "rmse_lowpass_5Hz" and "rmse_lowpass_5Hz" in row["per_phase"]["all"]
        assert row["violations"]["samples_in_contact"] > 0
    assert "5 Hz" in s["definitions"]["rmse_lowpass_5Hz"]
    lines = headline(s)
    assert [x.split(":")[0] for x in lines] == ["Per-foot vertical force", "Total vertical force", "Rotation"]
    ekf = s["estimators"]["ekf"]["per_phase"]["all"]["rmse"]["foot_vertical_force_N"]
    best = min(b["per_phase"]["all"]["rmse"]["foot_vertical_force_N"] for b in s["baselines"].values())
    assert (f"EKF is best ({ekf:.3g} N)" in lines[0]) == (ekf < best)
    out = write_report(comp, rec, tmp_path / "report")
    page = (out / "index.html").read_text()
    assert page.index(lines[0]) < page.index("<h2>Summary</h2>")  # the first thing said
    for text in ("weight_equal <small>(baseline)</small>", "Errors per contact phase", "Forces low-passed at 5 Hz",
                 "Physical violations", "single support", "transition", "not checked"):
        assert text in page, text
    assert json.loads((out / "summary.json").read_text())["baselines"]["weight_equal"]["per_phase"]


def test_headline_from_numbers():
    def row(foot, total, tilt):
        return {"per_phase": {"all": {"rmse": {"foot_vertical_force_N": foot, "total_vertical_force_N": total}}},
                "rmse": {"rotation_rad": tilt}}

    s = {"recording": {"has_truth": False},
         "estimators": {"ekf": row(34.7, 30.7, 0.0184), "batch": row(36.3, 31.1, 0.0137)},
         "baselines": {"leg_odometry": row(28.5, 12.1, 0.0198), "weight_equal": row(30.9, 12.1, 0.0198)}}
    foot, total, tilt = headline(s)
    assert foot == ("Per-foot vertical force: the leg-odometry baseline is best (28.5 N); the best estimator, EKF, "
                    "is 22 % worse (34.7 N).")
    assert total.startswith("Total vertical force: the leg-odometry and weight-equal baselines are best (12.1 N)")
    assert tilt == ("Tilt: batch is best (13.7 mrad), 31 % better than the best baselines, leg-odometry and "
                    "weight-equal (19.8 mrad).")
    assert headline({"estimators": {}, "baselines": {}}) == []


def test_each_contact_is_judged_against_its_own_sole(rec):
    """Per-contact soles (ModelConfig.soles): a contact without one is not judged; the count is of
    the judged samples (in contact, positive normal force)."""
    est = weight_equal(rec)
    nc = len(rec.contact_names)
    on = rec.contact_active & (rec.time >= 0.0)[:, None]
    ahead = (0.01, 0.1, -0.05, 0.05)  # starts 1 cm ahead of the contact point: every CoP outside
    around = (-0.1, 0.1, -0.05, 0.05)
    v = violations(est, rec, soles=(ahead,) + (around,) * (nc - 1))["cop_outside_sole"]
    assert v["count"] == int(on[:, 0].sum()) and v["fraction"] == pytest.approx(on[:, 0].sum() / on.sum())
    assert v["sole_m"][0] == list(ahead)
    v = violations(est, rec, soles=(ahead,) + (None,) * (nc - 1))["cop_outside_sole"]
    assert v["count"] == int(on[:, 0].sum()) and v["fraction"] == 1.0
    assert violations(est, rec, soles=(None,) * nc)["cop_outside_sole"] == {"skipped": NO_SOLE}


def test_robot_config_soles_reach_the_model_and_bad_ones_are_refused(tmp_path):
    from flexforce.datasets.robot import RobotConfig
    from flexforce.errors import ConfigError
    from flexforce.factors.model import _soles

    cfg = RobotConfig.load("icub-identified")
    assert [c.sole for c in cfg.contacts] == [(-0.066, 0.122, -0.042, 0.047), (-0.066, 0.122, -0.047, 0.042)]
    assert _soles(cfg, ("right_foot", "left_foot")) == ((-0.066, 0.122, -0.047, 0.042), (-0.066, 0.122, -0.042, 0.047))
    assert _soles(RobotConfig.load("romeo"), ("left_foot", "right_foot")) == ()
    robots = Path(__file__).parents[1] / "datasets" / "robots"
    src = (robots / "icub.toml").read_text()
    bad = src.replace("sole = [-0.066, 0.122, -0.042, 0.047]", "sole = [0.01, 0.122, -0.042, 0.047]")
    assert bad != src
    p = tmp_path / "bad.toml"
    p.write_text(bad.replace('urdf = "urdf/', f'urdf = "{robots}/urdf/'))
    with pytest.raises(ConfigError, match=r"contacts\[0\]\.sole = \[0\.01.*x_min < 0 < x_max"):
        RobotConfig.load(p)


def test_compare_takes_a_comma_separated_string_of_estimators(rec):
    """``compare(rec, "ekf, batch")`` runs those two, as the command line's ``--estimators`` does
    (not one estimator per character)."""
    comp = compare(rec, estimators="ekf, batch", crb=False, baseline=False, model_band=False)
    assert list(comp.metrics) == ["ekf", "batch"] and not comp.failures
