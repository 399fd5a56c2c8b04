"""The identifiability table's smallest detectable sizes (flexforce.smoother.screening.
detectable_sizes): the algebra, and the claim on simulated data -- a hidden effect well below the
size goes unnoticed, one well above it is found."""

from __future__ import annotations

import numpy as np
import pytest

from flexforce.compare.diagnostics.run import diagnose
from flexforce.compare.reports.diagnosis import write_diagnosis
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.smoother.screening import detectable_sizes


def test_the_size_gains_the_threshold_with_the_other_unknowns_fitted():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(5, 3)) * np.array([1e3, 1.0, 1e-2])  # unknowns of very different units
    S = A.T @ A
    sigma = np.array([1e-3, 1.0, 100.0])
    thr = 11.5
    sizes = detectable_sizes(S, sigma, thr)
    for i, d in enumerate(sizes):
        o = [j for j in range(3) if j != i]
        # the gain of theta_i = d with the others at their best: d^2 (S_ii - S_io S_oo^-1 S_oi)
        schur = S[i, i] - S[i, o] @ np.linalg.solve(S[np.ix_(o, o)], S[o, i])
        assert d**2 * schur == pytest.approx(thr, rel=1e-9)


def test_an_unknown_not_seen_apart_from_another_has_no_size():
    S = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 4.0]])  # the first two only as their sum
    sizes = detectable_sizes(S, np.ones(3), 10.0)
    assert np.isinf(sizes[0]) and np.isinf(sizes[1])
    assert sizes[2] == pytest.approx(np.sqrt(10.0 / 4.0))


def _sway(gyro_y: float):
    sc = Scenario.load("sway")
    sc.duration = 3.0
    sc.seed = 4
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    sc.effects = [{"type": "gyro-bias", "value": [0.0, gyro_y, 0.0]}] if gyro_y else []
    return Simulator(sc).run()


def test_a_gyro_bias_is_found_above_its_detectable_size_and_missed_well_below(tmp_path):
    cands = ["gyro-bias", "accel-bias", "com-offset"]
    clean = diagnose(_sway(0.0), candidates=cands, ekf=False, max_effects=1)
    size = clean.identifiability.candidates["gyro-bias"].detectable[1]  # y
    assert np.isfinite(size) and 1e-4 < size < 1e-2, size
    # stated in the JSON and the report
    row = next(c for c in clean.to_json()["identifiability"]["candidates"] if c["effect"] == "gyro-bias")
    assert row["detectable"][1] == pytest.approx(size) and "y ≥ " in row["detectable_text"]
    page = (write_diagnosis(clean, tmp_path / "d") / "index.html").read_text()
    assert f"gyro-bias: {clean.identifiability.candidates['gyro-bias'].detectable_text()}" in page
    above = diagnose(_sway(3.0 * size), candidates=cands, ekf=False, max_effects=1)
    below = diagnose(_sway(0.3 * size), candidates=cands, ekf=False, max_effects=1)
    assert above.selected == ["gyro-bias"], [(c.effect, c.status) for c in above.rounds[0]]
    assert below.selected == []
