"""gtsam's BatchFixedLagSmoother behind GtsamFixedLagSmoother(kind="batch") (the benchmark's third
fixed-lag smoother): its options, and its estimate against the window smoother's."""

from __future__ import annotations

import numpy as np
import pytest

from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import ConfigError
from flexforce.factors.model import ModelConfig
from flexforce.smoother import run_fixed_lag
from flexforce.smoother.fixed_lag import GtsamFixedLagSmoother
from flexforce.smoother.problem import Problem


@pytest.fixture(scope="module")
def rec():
    sc = Scenario.load("push-pitch")
    sc.duration = 0.5
    return Simulator(sc).run()


def test_batch_fixed_lag_options(rec):
    prob = Problem.build(rec, ModelConfig.from_recording(rec))
    with pytest.raises(ConfigError, match="no marginal covariances"):
        GtsamFixedLagSmoother(prob, 0.1, kind="batch")
    with pytest.raises(ConfigError, match="kind"):
        GtsamFixedLagSmoother(prob, 0.1, kind="sliding", covariance=False)


def test_batch_fixed_lag_close_to_the_window_smoother(rec):
    """Same lag (0.1 s), same factors.  Measured on 0.5 s of push-pitch: largest differences
    4.0e-5 m and 1.16 N of 200 N (the window smoother relinearises its newest 6 steps once per
    update, gtsam's re-runs LM over the whole window); thresholds 3x."""
    model = ModelConfig.from_recording(rec)
    prob = Problem.build(rec, model)
    fls = GtsamFixedLagSmoother(prob, 0.1, covariance=False, kind="batch")
    for _ in range(prob.n):
        fls.step()
    fls.finish()
    window = run_fixed_lag(rec, model, lag=0.1, covariance=False)
    d_t = np.abs(fls.traj.q[:, 0:3] - window.t).max()
    d_w = np.abs(np.where(prob.active[:, :, None], fls.traj.W, 0.0) - window.wrench).max()
    assert np.all(np.isfinite(fls.update_time)) and fls.update_time.min() > 0
    assert d_t < 3 * 4.0e-5 and d_w < 3 * 1.16
