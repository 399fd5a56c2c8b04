"""The comparison report's words and layout: headings with units, hidden effects in words, labelled
tables, the residual and violation sentences, legends and notes that stay out of the data.

Checked on the HTML text and on matplotlib's artists, not on pixels.
"""

from __future__ import annotations

import copy
import dataclasses

import matplotlib.pyplot as plt
import numpy as np
import pytest
from markupsafe import escape

from flexforce.compare.reports.comparison import (
    FIGURE_HEADINGS,
    environment,
    figure_contacts,
    figure_foot_wrench,
    figure_residuals,
    hidden_effect_text,
    relative_columns,
    residual_groups,
    residual_peaks,
    violation_sentences,
    write_report,
)
from flexforce.compare.runner import compare
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator


@pytest.fixture(scope="module")
def rec():
    sc = Scenario.load("push-pitch")
    sc.duration = 1.3
    return Simulator(sc).run()


@pytest.fixture(scope="module")
def comp(rec):
    return compare(rec, estimators=("ekf",), crb=False)


def _spiked(comp, size=25.0, at=50):
    """A copy of ``comp`` whose EKF gyro_y residual is ``size`` σ at step ``at``."""
    est = comp.estimates["ekf"]
    r = np.array(est.residuals["imu"], dtype=float)
    r[at, 1] = size
    out = copy.copy(comp)
    out.estimates = {**comp.estimates, "ekf": dataclasses.replace(est, residuals={**est.residuals, "imu": r})}
    return out


@pytest.fixture(scope="module")
def page(rec, comp, tmp_path_factory):
    out = write_report(_spiked(comp), rec, tmp_path_factory.mktemp("layout"))
    return out, (out / "index.html").read_text()


def test_headings_are_words_with_units(page):
    out, html = page
    assert "<h2>forces</h2>" not in html and "<h2>foot_forces</h2>" not in html and "<h2>residuals</h2>" not in html
    for name in ("forces.png", "foot_forces.png", "residuals.png", "contacts.png"):
        assert (out / name).exists()
        assert f'<h2 id="{name[:-4]}">{FIGURE_HEADINGS[name]}</h2>' in html, name
    assert "Total vertical force [N] and centre of pressure [mm]" in html
    assert "Whitened residuals per factor family [σ]" in html


def test_hidden_effects_are_listed_in_words(page):
    _, html = page
    assert '"type":' not in html and "{&#34;" not in html
    assert "<li>external wrench on the base: force 30 N (30, 0, 0); 1.00–1.15 s, half-sine profile</li>" in html


def test_hidden_effect_text_units_and_spans():
    push = {"type": "external-wrench", "link": "@link:0", "force": [0.0, -20.0, 0.0], "start": 4.5,
            "duration": 0.3, "profile": "half-sine"}
    assert hidden_effect_text(push) == ("external wrench on tracked link 0 (a hand): force 20 N (0, -20, 0); "
                                        "4.50–4.80 s, half-sine profile")
    # shifted by the window's start and clipped to the recording
    assert "0.50–0.70 s" in hidden_effect_text(push, window_start_s=4.0, duration_s=0.7)
    assert hidden_effect_text(push, duration_s=3.0).endswith("; after the recording's end (not in the data)")
    assert hidden_effect_text(push, window_start_s=6.0).endswith("; before the recording's start (not in the data)")
    assert hidden_effect_text({"type": "time-offset", "delay": 0.02}) == "time offset: delay 20 ms; throughout"
    assert hidden_effect_text({"type": "gyro-bias", "value": [0.01, 0, 0]}).startswith(
        "gyro bias: value 0.01 rad/s (0.01, 0, 0)")
    assert "offset 20 mm" in hidden_effect_text({"type": "com-offset", "target": "com", "offset": [0.02, 0, 0]})


def test_relative_table_has_labels_not_raw_keys():
    rel = {"batch": {"force_N": 0.5, "rotation_rad": 0.4, "hand_m": None},
           "fixed_lag": {"force_N": 0.6, "rotation_rad": 0.45, "hand_m": None}}
    cols = relative_columns(rel)
    assert cols == [("force_N", "force"), ("rotation_rad", "rotation")]  # the empty hand column dropped
    html = str(environment().get_template("_tables.html.j2").module.relative_table(rel, cols))
    assert "force_N" not in html and "rotation_rad" not in html and "hand" not in html
    assert "<th>rotation<br><small>RMSE / EKF's</small></th>" in html and "<td>0.45</td>" in html


def test_residual_sentence_names_family_axis_time_and_size(rec, comp, page):
    spiked = _spiked(comp)
    (sentence,) = residual_peaks(spiked, rec)
    t = float(rec.time[50])
    assert sentence.startswith("ekf: the imu residual peaks at 25σ (gyro_y")
    assert f"at t = {t:.2f} s" in sentence and "one step above 10σ" in sentence
    assert "misfit" in sentence and "not a force error" in sentence
    assert residual_peaks(comp, rec) == [s for s in residual_peaks(comp, rec) if "misfit" in s]
    _, html = page
    assert 'class="residual-peaks"' in html and str(escape(sentence)) in html


def test_no_residual_sentence_below_the_threshold(rec, comp):
    quiet = _spiked(comp, size=0.0)
    quiet.estimates["ekf"].residuals["imu"][:] = 0.0
    assert residual_peaks(quiet, rec) == []


def test_residual_figure_has_few_lines_and_legends_outside(rec, comp):
    fig = figure_residuals(_spiked(comp), rec)
    fig.canvas.draw()
    ax = fig.axes[0]
    est = comp.estimates["ekf"]
    groups = residual_groups(est.residual_labels["imu"], est.residuals["imu"].shape[1])
    assert [g for g, _ in groups] == ["gyro xyz", "accel xyz"]
    curves = [ln for ln in ax.lines if not ln.get_label().startswith("_")]
    assert len(curves) == 2 and ax.get_yscale() == "log"
    # the spike is kept (no robust cut on a log axis)
    assert max(np.max(ln.get_ydata()) for ln in curves) == pytest.approx(25.0)
    legend = ax.get_legend().get_window_extent()
    assert legend.x0 >= ax.get_window_extent().x1  # beside the panel, not over the data
    plt.close(fig)


def test_foot_wrench_notes_stay_inside_their_panels(rec, comp):
    fig = figure_foot_wrench(comp, rec)
    fig.canvas.draw()
    assert fig.axes[0].get_subplotspec().get_gridspec().get_geometry() == (2 * len(rec.contact_names), 2)
    assert fig.legends and all(ax.get_legend() is None for ax in fig.axes)
    renderer = fig.canvas.get_renderer()
    notes = 0
    for ax in fig.axes:
        box = ax.get_window_extent()
        for text in ax.texts:
            ext = text.get_window_extent(renderer)
            assert box.x0 - 1 <= ext.x0 and ext.x1 <= box.x1 + 1, text.get_text()
            notes += "beyond the axis" in text.get_text()
    plt.close(fig)


def test_contacts_figure_is_compact(rec, comp):
    fig = figure_contacts(comp, rec)
    assert fig.get_size_inches()[1] < 2.0
    plt.close(fig)


def test_violation_sentences():
    def row(neg, cone, sole):
        return {"violations": {"samples_in_contact": 1808, "friction_mu": 0.7,
                               "negative_normal": {"count": neg, "fraction": neg / 1808},
                               "friction_cone": {"count": cone, "fraction": cone / 1808},
                               "cop_outside_sole": {"count": sole, "fraction": sole / 1808}}}

    summary = {"estimators": {"ekf": row(17, 36, 113), "batch": row(0, 38, 237)},
               "baselines": {"leg_odometry": row(0, 0, 0)}}
    neg, cone, sole = violation_sentences(summary)
    assert neg == ("Normal force below 0 N (the ground pulls): ekf 17 of 1808 (0.94 %); none in batch, "
                   "leg_odometry.")
    assert "ekf 36 of 1808" in cone and "batch 38 of 1808 (2.1 %)" in cone
    assert sole.startswith("Centre of pressure outside the sole: ekf 113 of 1808 (6.25 %); batch 237")
    # the CoP check judges only the pairs with F_z > 0: its fraction says how many
    summary["estimators"]["ekf"]["violations"]["cop_outside_sole"]["fraction"] = 113 / 1791
    assert "ekf 113 of 1791 (6.31 %)" in violation_sentences(summary)[2]
    clean = {"estimators": {"ekf": row(0, 0, 0)}}
    assert violation_sentences(clean)[0] == "No normal force below 0 N (the ground pulls) in any row (ekf)."
    assert violation_sentences({"estimators": {"ekf": {}}}) == []


def test_violations_in_words_on_the_page(page):
    _, html = page
    assert '<p class="violation">No normal force below 0 N (the ground pulls) in any row' in html
