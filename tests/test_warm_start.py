"""A fit started from a fit with fewer effects (flexforce.smoother.batch.carried_over): the same
optimum as from the first step's equilibrium, reached in fewer iterations, never above the
smaller model's cost."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import ConfigError
from flexforce.factors.effects import make_effect
from flexforce.factors.model import ModelConfig
from flexforce.smoother import Problem, fit
from flexforce.smoother.batch import carried_over


@pytest.fixture(scope="module")
def fits():
    """A 3 s sway with a hidden gyro bias and a push; the nominal fit, then the accelerometer-bias
    and external-wrench models from the equilibrium and from the smaller fit."""
    sc = Scenario.load("sway")
    sc.duration = 3.0
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    sc.effects = [{"type": "gyro-bias", "value": [0.0, 0.01, 0.0]}]
    rec = Simulator(sc).run()
    model = ModelConfig.from_recording(rec)
    m_gyro = dataclasses.replace(model, effects=(make_effect("gyro-bias"),))
    m_both = dataclasses.replace(model, effects=(make_effect("gyro-bias"), make_effect("external-wrench")))
    out = {"rec": rec, "m_gyro": m_gyro, "m_both": m_both}
    out["nominal"] = fit(rec, model)
    out["gyro_cold"] = fit(rec, m_gyro)
    out["gyro_warm"] = fit(rec, m_gyro, start=((), out["nominal"][1].trajectory))
    out["both_cold"] = fit(rec, m_both)
    out["both_warm"] = fit(rec, m_both, start=(m_gyro.effects, out["gyro_cold"][1].trajectory))
    return out


@pytest.mark.parametrize("which", ["gyro", "both"])
def test_a_warm_start_reaches_the_same_optimum(fits, which):
    (e_cold, s_cold), (e_warm, s_warm) = fits[f"{which}_cold"], fits[f"{which}_warm"]
    # measured: the evidence 1.3e-10 / 1.5e-9 relatively apart, the gyro bias 4e-7 / 2.6e-3 of its
    # std; bounds: the convergence test's resolution (rel_tol 1e-7 of the cost), 0.05 std
    assert s_warm.cost_evidence == pytest.approx(s_cold.cost_evidence, rel=1e-7)
    assert s_warm.cost_data <= fits["nominal"][1].cost_data
    name = "gyro-bias"
    v_cold, v_warm = np.asarray(e_cold.effects[name]["value"]), np.asarray(e_warm.effects[name]["value"])
    std = np.asarray(e_cold.effects[name]["std"])
    assert np.all(np.abs(v_warm - v_cold) <= 0.05 * std), (v_warm, v_cold, std)
    assert e_warm.meta["iterations"] <= e_cold.meta["iterations"]  # measured 3 vs 11, 5 vs 12


def test_the_start_carries_states_and_shared_effects(fits):
    rec, m_gyro, m_both = fits["rec"], fits["m_gyro"], fits["m_both"]
    from flexforce.smoother import NoiseRule

    traj = fits["gyro_cold"][1].trajectory
    prob = Problem.build(rec, m_both, NoiseRule())
    start = carried_over(prob, m_gyro.effects, traj)
    np.testing.assert_array_equal(start.R, traj.R)
    np.testing.assert_array_equal(start.q, traj.q)
    np.testing.assert_array_equal(start.e[:, :3], traj.e[:, :3])  # the gyro bias, matched by name
    np.testing.assert_array_equal(start.e[:, 3:], 0.0)  # the new wrench at its prior mean


def test_a_start_of_another_recording_or_model_is_refused(fits):
    rec, m_gyro, m_both = fits["rec"], fits["m_gyro"], fits["m_both"]
    from flexforce.smoother import NoiseRule

    traj = fits["gyro_cold"][1].trajectory
    prob = Problem.build(rec, m_both, NoiseRule())
    short = type(traj)(traj.R[:-5], traj.q[:-5], traj.W[:-5], traj.e[:-5])
    with pytest.raises(ConfigError, match="same recording"):
        carried_over(prob, m_gyro.effects, short)
    with pytest.raises(ConfigError, match="effects the start was fitted with"):
        carried_over(prob, m_both.effects, traj)
