"""The gtsam graph with effects, and its export (``to_gtsam``) and read-back (``from_gtsam``).

Jacobians of every factor of a step with every catalogue effect enabled (and the footholds) are
checked against central differences through ``Values.retract``; gtsam's Levenberg-Marquardt on the
exported graph is checked against the batch smoother on a recording with a push and the
``external-wrench`` effect; the key table and its errors; the marginals read back.
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from test_factors import check_factor_jacobians  # the numerical Jacobian check (factorTesting)

from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import ConfigError
from flexforce.factors import gtsam_factors as gf
from flexforce.factors.effects import EFFECTS, make_effect
from flexforce.factors.model import ModelConfig
from flexforce.smoother import from_gtsam, run_batch, to_gtsam
from flexforce.smoother.batch import BatchConfig, initial_trajectory
from flexforce.smoother.graph import GraphBuilder, GtsamKeys
from flexforce.smoother.problem import NoiseRule, Problem, with_footholds

# Largest differences gtsam's LM vs the batch smoother, measured (the thresholds are 10x these).
MEASURED_BIAS, MEASURED_T = 4.9e-7, 2.5e-8  # rad/s, m: gyro bias, 0.6 s of push-pitch
MEASURED_FT, MEASURED_FW, MEASURED_FF = 3.1e-6, 5.8e-3, 3.1e-6  # m, N, m: footholds, step scenario


@pytest.fixture(scope="module")
def rec():
    sc = Scenario.load("push-pitch")
    sc.duration = 1.5  # the 30 N push on the pelvis is at 1.0-1.15 s
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    return Simulator(sc).run()


@pytest.fixture(scope="module")
def model(rec):
    return ModelConfig.from_recording(rec)


# ----------------------------------------------------------------------------------------------
# Jacobians through Values.retract
# ----------------------------------------------------------------------------------------------


def _perturbed_values(builder, rng, k0, k1):
    """Values of steps k0..k1-1 off the equilibrium: every variable moved at random, effects too."""
    prob = builder.prob
    traj = initial_trajectory(prob)
    n = prob.n
    dx = np.zeros((n, prob.state_dim))
    dx[:, 0:3] = rng.normal(0, 0.02, (n, 3))
    dx[:, 3:6] = rng.normal(0, 0.005, (n, 3))
    dx[:, 6:18] = rng.normal(0, 0.2, (n, 12))
    dx[:, 18:18 + 6 * prob.nc] = rng.normal(0, 20.0, (n, 6 * prob.nc))
    traj = traj.retract(dx)
    off = 0
    for eff in prob.effects:
        _, sigma = eff.prior(prob)
        traj.e[:, off:off + eff.dim] += rng.normal(0, 0.3, (n, eff.dim)) * np.asarray(sigma)
        off += eff.dim
    return builder.values(traj, k0, k1)


@pytest.mark.parametrize("k", [0, 7])
def test_factor_jacobians_with_every_effect(rec, model, k):
    """Every factor of step k (families with the effects' terms, the effects' priors, walks and
    own factors) against numerical derivatives, at a perturbed state.  The time offset's
    derivative is the rate of the readings' signal, not of their shifted noise: it is checked on
    noise-free readings (below)."""
    short = rec.slice(0, 12)
    effects = tuple(make_effect(name) for name in EFFECTS if name != "time-offset")
    m, rest_p, rest_R = with_footholds(short, dataclasses.replace(model, effects=effects))
    # Gaussian Newton-Euler noise: a Huber weight depends on the state, so the derivative of the
    # reweighted residual is not the reweighted Jacobian (gtsam's robust linearisation)
    builder = GraphBuilder(Problem.build(short, m, NoiseRule(robust_k=None), rest_p, rest_R))
    # every family is touched by some effect, and the footholds bring factors of their own at k = 0
    assert all(builder.touch[f] for f in ("newton_euler", "contact", "imu"))
    values = _perturbed_values(builder, np.random.default_rng(k), max(k - 1, 0), k + 1)
    factors = builder.step_factors(k)
    own = [f for f in factors if isinstance(f, gtsam.CustomFactor)
           and any(gtsam.Symbol(key).chr() == ord("e") for key in f.keys())]
    assert len(own) >= 4  # Newton-Euler, IMU, two contacts (+ footholds' own at k = 0)
    for f in factors:
        check_factor_jacobians(f, values)


@pytest.mark.parametrize("k", [0, 7])
def test_factor_jacobians_with_the_time_offset(k):
    """The IMU factor with the time offset's term (an exact delay of the readings) against
    numerical derivatives, on noise-free readings (where the signal is the readings)."""
    sc = Scenario.load("push-pitch")
    sc.duration = 0.3
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    short = Simulator(sc, noise=False).run().slice(0, 12)
    m = dataclasses.replace(ModelConfig.from_recording(short), effects=(make_effect("time-offset"),))
    builder = GraphBuilder(Problem.build(short, m, NoiseRule(robust_k=None)))
    values = _perturbed_values(builder, np.random.default_rng(k), max(k - 1, 0), k + 1)
    factors = builder.step_factors(k)
    assert any(isinstance(f, gtsam.CustomFactor) and any(gtsam.Symbol(key).chr() == ord("e") for key in f.keys())
               for f in factors)
    for f in factors:
        check_factor_jacobians(f, values)


def test_imu_factor_skips_missing_axes(rec, model):
    """An axis marked missing (zero weight) has a zero row, whatever its placeholder reading."""
    prob = Problem.build(rec.slice(0, 3), model)
    p = prob
    use = np.array([1.0, 0.0, 1.0, 1.0, 1.0, 0.0])
    values = GraphBuilder(prob).values(initial_trajectory(prob))
    f = gf.imu_factor(gtsam.noiseModel.Unit.Create(6), 1, p.y_imu[1] + 100.0, p.imu_R[1], p.imu_p[1], p.imu_v[1],
                      p.imu_a[1], p.imu_w[1], p.g, use=use)
    err = f.unwhitenedError(values)
    assert err[1] == 0.0 and err[5] == 0.0 and abs(err[0]) > 50
    check_factor_jacobians(f, values)


# ----------------------------------------------------------------------------------------------
# gtsam's optimum with an effect = the batch smoother's
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def with_push(rec, model):
    m = dataclasses.replace(model, effects=(make_effect("external-wrench"),))
    est = run_batch(rec, m)
    graph, values, keys = to_gtsam(rec, m)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setMaxIterations(100)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return est, graph, result, keys


def test_gtsam_reaches_the_batch_estimate_with_an_effect(rec, with_push):
    """gtsam's LM on the exported graph (external-wrench effect enabled) lands on the batch
    smoother's estimate.  Measured on this 1.5 s recording: translation 1.8e-8 m, rotation 9e-8,
    contact wrench 5.8e-4 N (of 202 N), external wrench within the report's rounding (1e-3 N);
    thresholds about 10x those (5x for the rounded one)."""
    est, graph, result, keys = with_push
    mine = from_gtsam(result, keys)
    assert mine.estimator == "gtsam" and mine.meta["backend"] == "gtsam"
    assert np.abs(mine.t - est.t).max() < 2e-7
    np.testing.assert_allclose(mine.R, est.R, atol=1e-6)
    assert np.abs(mine.wrench - est.wrench).max() < 6e-3
    ours = np.asarray(est.effects["external-wrench"]["wrench"])[:, :3]
    theirs = np.asarray(mine.effects["external-wrench"]["wrench"])[:, :3]
    assert np.abs(ours - theirs).max() < 5e-3
    # and the push is there: the half-sine of 30 N forward at 1.0-1.15 s peaks at 25.7 N, at 1.075 s
    t = (rec.t_ns - rec.t_ns[0]) * 1e-9
    during = (t > 1.05) & (t < 1.1)
    assert theirs[during, 0].max() > 20.0


def test_marginals_read_back(rec, model):
    """``from_gtsam(values, keys, graph)``: per-step joint marginals in world increments, equal to
    the batch smoother's exact marginals.  Measured on the standard deviations, all 40 steps: 1.4e-3
    relative at most for the state (the two optima differ by the solvers' stopping points), 4.7e-4
    for the total wrench; threshold 3e-3 (about twice)."""
    short = rec.slice(0, 40)
    est = run_batch(short, model)
    graph, values, keys = to_gtsam(short, model)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    mine = from_gtsam(result, keys, graph)
    assert mine.cov is not None and mine.wrench_cov is not None
    std = lambda c: np.sqrt(np.einsum("kii->ki", c))  # noqa: E731
    np.testing.assert_allclose(std(mine.cov), std(est.cov), rtol=3e-3)
    np.testing.assert_allclose(std(mine.wrench_cov), std(est.wrench_cov), rtol=3e-3)
    # the full pose block, cross terms included
    assert np.abs(mine.cov[:, 0:6, 0:6] - est.cov[:, 0:6, 0:6]).max() < 3e-3 * np.abs(est.cov[:, 0:6, 0:6]).max()


# ----------------------------------------------------------------------------------------------
# Keys and errors
# ----------------------------------------------------------------------------------------------


def test_keys_name_every_variable(rec, model):
    short = rec.slice(0, 5)
    m = dataclasses.replace(model, effects=(make_effect("gyro-bias"),))
    graph, values, keys = to_gtsam(short, m)
    assert isinstance(keys, GtsamKeys) and keys.steps == 5 and keys.effect_names == ("gyro-bias",)
    name = keys.contact_names[1]
    expected = {keys.pose(k) for k in range(5)} | {keys.velocity(k) for k in range(5)}
    expected |= {keys.acceleration(k) for k in range(5)} | {keys.effect(k, "gyro-bias") for k in range(5)}
    expected |= {keys.wrench(k, i) for k in range(5) for i in range(2)}
    assert set(values.keys()) == expected
    assert keys.wrench(3, name) == gf.W(3, 1) and keys.effect(2, 0) == gf.E(2, 0)
    assert values.atVector(keys.effect(0, "gyro-bias")).shape == (3,)
    assert set(graph.keys()) == expected
    text = keys.describe()
    assert "gtsam.Pose3" in text and "gyro-bias" in text and name in text
    with pytest.raises(ConfigError, match="unknown contact 'hand'"):
        keys.wrench(0, "hand")
    with pytest.raises(ConfigError, match="step 5 is outside"):
        keys.pose(5)
    with pytest.raises(ConfigError, match="effect index 1 is out of range"):
        keys.effect(0, 1)
    partial = gtsam.Values()
    partial.insert(keys.pose(0), values.atPose3(keys.pose(0)))
    with pytest.raises(ConfigError, match="lack a variable of step 0"):
        from_gtsam(partial, keys)
    with pytest.raises(ConfigError, match="keys must be the GtsamKeys"):
        from_gtsam(values, {})


def test_gtsam_fixed_lag_refuses_effects_clearly(rec, model):
    from flexforce.smoother import run_fixed_lag

    m = dataclasses.replace(model, effects=(make_effect("gyro-bias"),))
    with pytest.raises(ConfigError, match="gtsam fixed-lag backend does not take effects.*gyro-bias"):
        run_fixed_lag(rec.slice(0, 10), m, backend="gtsam")


def test_constant_effect_matches_the_joint_map(rec, model):
    """A constant effect (gyro bias) in the graph is the joint MAP with its stated prior, which is
    ``run_batch(..., global_constants=False)``.  Measured on 0.6 s with a hidden bias: the
    estimated biases agree to 4.9e-7 rad/s, translations to 2.5e-8 m; thresholds 10x."""
    short = rec.slice(0, 121)
    short.gyro = short.gyro + np.array([0.01, -0.02, 0.005])
    m = dataclasses.replace(model, effects=(make_effect("gyro-bias"),))
    est = run_batch(short, m, BatchConfig(global_constants=False))
    graph, values, keys = to_gtsam(short, m)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    mine = from_gtsam(gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize(), keys)
    d_bias = np.abs(np.subtract(mine.effects["gyro-bias"]["value"], est.effects["gyro-bias"]["value"])).max()
    d_t = np.abs(mine.t - est.t).max()
    assert d_bias < 10 * MEASURED_BIAS and d_t < 10 * MEASURED_T


def test_footholds_at_a_touch_down_match_the_batch_smoother():
    """``to_gtsam(..., footholds=True)``: the episodes' footholds as unknowns (the effect's own
    factors: leg kinematics at the touch-down, ground plane) around the right foot's landing of
    the ``step`` scenario (0.3 s either side).  Measured: translation 3.1e-6 m, contact wrench
    5.8e-3 N (of 401 N), foothold corrections 3.1e-6 m (largest 17 mm); thresholds 10x."""
    sc = Scenario.load("step")
    sc.duration = 4.6
    full = Simulator(sc).run()
    change = np.flatnonzero(np.any(np.diff(full.contact_active.astype(int), axis=0) != 0, axis=1))[-1]
    rec = full.slice(change - 60, change + 60)
    assert not rec.contact_active[0].all() and rec.contact_active[-1].all()  # the landing is inside
    model = ModelConfig.from_recording(rec)
    est = run_batch(rec, model, BatchConfig(footholds=True))
    graph, values, keys = to_gtsam(rec, model, footholds=True)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    mine = from_gtsam(gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize(), keys)
    d_t = np.abs(mine.t - est.t).max()
    d_w = np.abs(mine.wrench - est.wrench).max()
    d_f = np.abs(np.subtract(mine.effects["foothold"]["value"], est.effects["foothold"]["value"])).max()
    assert d_t < 10 * MEASURED_FT and d_w < 10 * MEASURED_FW and d_f < 10 * MEASURED_FF
