"""The comparison report's content: the leg-odometry row, per-contact errors, references, figures.

Checked on numbers and HTML text, not pixels (STYLE.md, habit 12).
"""

from __future__ import annotations

import json

import matplotlib.pyplot as plt
import numpy as np
import pytest
from conftest import ICUB_DIR

from flexforce.cli import main
from flexforce.compare.baseline import leg_odometry, static_split
from flexforce.compare.metrics import evaluate
from flexforce.compare.reports.comparison import figure_contacts, intervals, robust_limits, write_report
from flexforce.compare.runner import compare
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator

WALK = ICUB_DIR / "icub-walk-12s"


@pytest.fixture(scope="module")
def rec():
    sc = Scenario.load("push-pitch")
    sc.duration = 1.0
    return Simulator(sc).run()


@pytest.fixture(scope="module")
def report(rec, tmp_path_factory):
    comp = compare(rec, estimators=("ekf",), crb=False)
    out = write_report(comp, rec, tmp_path_factory.mktemp("report"))
    return comp, out


def test_static_split_by_hand():
    feet = np.array([[0.0, 0.1], [0.0, -0.1]])
    # CoM a quarter of the way from the left foot: 3/4 of the weight on it
    np.testing.assert_allclose(static_split(np.array([0.0, 0.05]), feet, 400.0), [300.0, 100.0])
    # CoM outside the support: everything on the nearer foot, nothing negative
    np.testing.assert_allclose(static_split(np.array([0.0, 0.3]), feet, 400.0), [400.0, 0.0])
    np.testing.assert_allclose(static_split(np.array([0.2, 0.3]), feet[:1], 400.0), [400.0])
    # four contacts at the corners of a square, CoM in the middle: a quarter each
    sq = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])
    np.testing.assert_allclose(static_split(np.zeros(2), sq, 400.0), [100.0] * 4)


def test_leg_odometry_is_the_rigid_robot(rec):
    est = leg_odometry(rec)
    assert est.n == rec.n
    np.testing.assert_array_equal(est.R, np.tile(np.eye(3), (rec.n, 1, 1)))
    assert not est.t.any() and not est.v.any() and not est.w.any()
    np.testing.assert_allclose(est.total_wrench[:, 2], rec.mass * rec.gravity)
    assert not est.wrench[..., :2].any()
    assert est.cov is None and est.time_per_step is None
    m = evaluate(est, rec)
    # its rotation error is the flexibility itself
    tilt = np.linalg.norm([np.linalg.norm(R - np.eye(3)) for R in rec.truth.R])
    assert tilt > 0 and m.rmse["rotation_rad"] > 0
    assert m.nees is None


def test_summary_json_keys(report):
    comp, out = report
    s = json.loads((out / "summary.json").read_text())
    assert set(s["estimators"]) == {"ekf"}
    base = s["baselines"]["leg_odometry"]
    assert base["kind"] == "baseline" and s["estimators"]["ekf"]["kind"] == "estimator"
    timing = json.loads((out / "timings.json").read_text())["baselines"]["leg_odometry"]
    assert base["nees"] is None and timing["total_time_s"] is None and timing["time_per_step_s"] == {}
    assert base["rmse"]["rotation_rad"] > 0 and base["rmse"]["force_N"] > 0
    for row in (base, s["estimators"]["ekf"]):
        assert row["references"]["rotation_rad"] == "truth"
        for foot in ("left_foot", "right_foot"):
            assert set(row["per_contact"][foot]) == {"vertical_force_N", "force_N", "moment_Nm", "cop_m"}
            assert all(v is not None and v >= 0 for v in row["per_contact"][foot].values())
    # the leg-odometry forces sit at the sole origins: its per-foot CoP error is the true CoP offset
    assert base["per_contact"]["left_foot"]["cop_m"] > s["estimators"]["ekf"]["per_contact"]["left_foot"]["cop_m"]


def test_html_has_the_baseline_row_and_per_contact_columns(report):
    comp, out = report
    page = (out / "index.html").read_text()
    assert "leg_odometry <small>(baseline)</small>" in page
    assert "baseline: no estimation" in page
    assert "<h2>Per-contact errors</h2>" in page
    for text in ("left_foot", "right_foot", "F_z RMSE [N]", "3-D force RMSE [N]", "torque RMSE [N m]",
                 "CoP RMSE [mm]"):
        assert text in page, text
    assert "simulator's ground truth" in page
    for fig in ("contacts.png", "foot_forces.png", "foot_wrench.png"):
        assert (out / fig).exists() and f'src="{fig}"' in page


def test_robust_limits_clip_a_single_spike():
    fig, ax = plt.subplots()
    y = np.sin(np.linspace(0, 10, 1000))
    y[500] = 1e4
    ax.plot(y)
    assert robust_limits(ax, [y]) == 1
    lo, hi = ax.get_ylim()
    assert hi < 2.0 and lo > -2.0
    assert any("beyond the axis" in t.get_text() for t in ax.texts)
    fig2, ax2 = plt.subplots()
    assert robust_limits(ax2, [np.sin(np.linspace(0, 10, 1000))]) == 0
    assert not ax2.texts
    plt.close(fig)
    plt.close(fig2)


def test_intervals():
    t = np.arange(8) * 0.1
    m = np.array([1, 1, 0, 0, 1, 0, 1, 1], dtype=bool)
    assert intervals(m, t) == [(0.0, 0.1), (pytest.approx(0.4), pytest.approx(0.4)),
                               (pytest.approx(0.6), pytest.approx(0.7))]
    assert intervals(np.zeros(3, bool), t[:3]) == []


def test_contact_timeline_shows_anchor_switches(rec, report):
    comp, _ = report
    rec = rec.slice(0, rec.n)
    rec.meta["anchor"] = {"first": "left_foot", "switches": [{"t": 0.4, "from": "left_foot", "to": "right_foot"}]}
    fig = figure_contacts(comp, rec)
    assert "1 switch(es)" in fig.axes[0].get_title()
    assert [t.get_text() for t in fig.axes[0].get_yticklabels()] == list(rec.contact_names)
    plt.close(fig)


@pytest.mark.skipif(not WALK.exists(), reason="the iCub recordings are not beside this checkout")
def test_real_walk_window_references_and_leg_odometry(tmp_path, capsys):
    """A 3 s window of the real walk, EKF only: F/T and Vicon named as references, leg odometry's
    tilt equal to the one computed directly from the base pose and Vicon (an independent path)."""
    from scipy.spatial.transform import Rotation

    from flexforce.datasets.io.rosimport import import_bag

    out = tmp_path / "walk"
    assert main(["compare", str(WALK), "--robot", "icub", "-o", str(out), "-q", "--estimators", "ekf",
                 "--start", "2", "--end", "5"]) == 0
    table = capsys.readouterr().out
    assert "leg_odometry *" in table and "reference: F/T" in table
    s = json.loads((out / "summary.json").read_text())
    assert s["recording"]["window"]["start_s"] == pytest.approx(2.0, abs=0.01)
    base = s["baselines"]["leg_odometry"]
    assert base["references"]["vertical_force_N"] == "reference: F/T"
    assert base["references"]["rotation_rad"] in ("reference: Vicon", "reference: motion capture")
    # the F/T measures F_z only: no 3-D force, torque or CoP per foot, and no crash
    for foot, d in base["per_contact"].items():
        assert set(d) == {"vertical_force_N"}, foot
    page = (out / "index.html").read_text()
    assert "references, not ground truth" in page and "leg_odometry <small>(baseline)</small>" in page
    assert not (out / "foot_wrench.png").exists()

    rec = import_bag(WALK, "icub").window(2, 5)
    keep = rec.time >= 0.5
    moc = rec.mocap[rec.meta["base_frame"]]
    ok = keep & np.all(np.isfinite(moc), axis=1)
    up_odo = Rotation.from_quat(rec.base_pose[ok, 3:]).as_matrix()[:, 2, :]
    up_vicon = Rotation.from_quat(moc[ok, 3:]).as_matrix()[:, 2, :]
    tilt = float(np.sqrt(np.mean(np.arccos(np.clip(np.sum(up_odo * up_vicon, axis=1), -1, 1)) ** 2)))
    assert base["rmse"]["rotation_rad"] == pytest.approx(tilt, rel=1e-9)


def test_plot_functions_draw_on_the_given_axes(rec, report):
    from flexforce.compare.metrics import contact_frame_wrench
    from flexforce.compare.reports.comparison import plot_contact_force, plot_series

    comp, _ = report
    fig, (ax1, ax2) = plt.subplots(2, 1)
    figures = plt.get_fignums()
    plot_series(ax1, rec.time, comp.estimates, lambda e: e.total_wrench[:, 2], truth=rec.truth.total_wrench[:, 2])
    local = {"ekf": contact_frame_wrench(comp.estimates["ekf"].R, comp.estimates["ekf"].t,
                                         comp.estimates["ekf"].wrench, rec)}
    plot_contact_force(ax2, rec, 0, 0, local)
    assert plt.get_fignums() == figures  # no figure of their own
    assert [ln.get_label() for ln in ax1.lines] == ["truth", "ekf"]
    assert "F_x" in ax2.get_ylabel() and [ln.get_label() for ln in ax2.lines] == ["ekf"]
    plt.close(fig)


def test_line_styles_keep_fixed_lag_visible_over_batch():
    from flexforce.compare.reports.comparison import _style

    batch, fixed = _style("batch"), _style("fixed_lag")
    assert batch["ls"] == "-" and fixed["ls"] != "-" and fixed["zorder"] > batch["zorder"]


def _summary(nees, nis=6.0):
    row = {"nees": nees, "nees_bounds": [17.7, 18.3], "nis": nis, "nis_bounds": [5.8, 6.2]}
    return {"recording": {"hidden_effects": []}, "estimators": {"batch": row}}


def test_nees_sentence_only_out_of_band():
    from flexforce.compare.reports.comparison import consistency_sentences

    assert consistency_sentences(_summary(18.0)) == []
    (above,) = consistency_sentences(_summary(722.0))
    assert "NEES above" in above and "batch 722" in above and "×6.3" in above and "too small" in above
    (below,) = consistency_sentences(_summary(4.5))
    assert "NEES below" in below and "×0.5" in below and "too large" in below
    (nis,) = consistency_sentences(_summary(18.0, nis=24.0))
    assert "NIS above" in nis and "×2" in nis


def test_option_sentences_say_which_rows_ran_with_their_own_options():
    from flexforce.compare.reports.comparison import option_sentences

    summary = {"estimators": {"ekf": {"extra": {}}, "fixed_lag": {"extra": {"options": {"compiled": False}}},
                              "batch": {"extra": {"options": {"footholds": True}}}}}
    fixed_lag, batch = option_sentences(summary)
    assert fixed_lag.startswith("fixed_lag ran with compiled = False (its general window path")
    assert batch == "batch ran with footholds = True."
    assert option_sentences({"estimators": {"ekf": {}}}) == []


def test_report_page_says_what_an_out_of_band_nees_means(report):
    comp, out = report
    page = (out / "index.html").read_text()
    s = json.loads((out / "summary.json").read_text())
    row = s["estimators"]["ekf"]
    out_of_band = not (row["nees_bounds"][0] <= row["nees"] <= row["nees_bounds"][1])
    assert ('class="consistency"' in page and "NEES " in page.split('class="consistency"')[1]) == out_of_band
    assert "Units: forces N" in page


def test_foot_forces_overlay_the_ft_reference(rec, report):
    from flexforce.compare.metrics import contact_frame_wrench
    from flexforce.compare.reports.comparison import figure_foot_forces

    comp, _ = report
    real = rec.slice(0, rec.n)
    real.ft = contact_frame_wrench(rec.truth.R, rec.truth.t, rec.truth.wrench, rec)
    real.truth = None
    fig = figure_foot_forces(comp, real)
    labels = [[ln.get_label() for ln in ax.lines] for ax in fig.axes]
    assert len(fig.axes) == 3 * len(rec.contact_names)  # F_z, F_x, F_y per contact
    assert all("reference: F/T" in ls for ls in labels)
    plt.close(fig)
    real.ft = None
    fig = figure_foot_forces(comp, real)
    assert not any("reference: F/T" in ln.get_label() for ax in fig.axes for ln in ax.lines)
    plt.close(fig)


def test_hidden_effects_and_contact_switches_are_marked(rec, report):
    from flexforce.compare.reports.comparison import contact_switches, figure_forces, hidden_spans

    comp, _ = report
    pushed = rec.slice(0, rec.n)
    pushed.meta = {**rec.meta, "hidden_effects": [{"type": "external-wrench", "link": "@base", "force": [30, 0, 0],
                                                   "start": 0.4, "duration": 0.2}, {"type": "constant-bias"}]}
    assert hidden_spans(pushed) == [(0.4, pytest.approx(0.6), "external-wrench @base 30 N")]
    pushed.contact_active = rec.contact_active.copy()
    pushed.contact_active[rec.n // 2:, 0] = False
    assert contact_switches(pushed) == [pytest.approx(rec.time[rec.n // 2])]
    fig = figure_forces(comp, pushed)
    labels = fig.axes[0].get_legend_handles_labels()[1]
    assert "hidden effect" in labels and "contact switch" in labels
    plt.close(fig)
