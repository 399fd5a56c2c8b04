"""The estimators' frozen config dataclasses: every bad option is a ConfigError
naming the option, its value, its unit and what is expected; unknown keyword options list the
known ones; run_estimator refuses another estimator's config; and the config path and the older
keyword path give the same estimate, bit for bit (the keyword options only build the config).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flexforce.compare.ekf.filter import EKFConfig, run_ekf
from flexforce.compare.estimators import run_estimator
from flexforce.datasets.sim.simulator import simulate
from flexforce.errors import ConfigError
from flexforce.factors.model import ModelConfig
from flexforce.smoother import BatchConfig, FixedLagConfig, NoiseRule, run_batch, run_fixed_lag

# (config class, field, bad value, the message expected, as a regular expression)
BAD = [
    (BatchConfig, "max_iterations", 0, r"BatchConfig.max_iterations = 0 iterations; expected an integer >= 1"),
    (BatchConfig, "max_iterations", 2.5, r"BatchConfig.max_iterations = 2.5 iterations; expected an integer"),
    (BatchConfig, "rel_tol", -1e-7, r"BatchConfig.rel_tol = -1e-07; expected a positive relative cost decrease"),
    (BatchConfig, "covariance", "yes", r"BatchConfig.covariance = 'yes'; expected True or False"),
    (BatchConfig, "global_constants", None, r"BatchConfig.global_constants = None; expected True or False"),
    (BatchConfig, "rule", {"robust_k": 3.0}, r"BatchConfig.rule = \{'robust_k': 3.0\}; expected a NoiseRule"),
    (FixedLagConfig, "lag", -1.0, r"FixedLagConfig.lag = -1.0 s; expected a positive duration"),
    (FixedLagConfig, "lag", float("nan"), r"FixedLagConfig.lag = nan s; expected a positive duration"),
    (FixedLagConfig, "lag", "1s", r"FixedLagConfig.lag = '1s' s; expected a positive duration"),
    (FixedLagConfig, "backend", "isam", r"FixedLagConfig.backend = 'isam'; expected 'window' or 'gtsam'"),
    (FixedLagConfig, "relinearize", 0, r"FixedLagConfig.relinearize = 0 steps; expected an integer >= 1"),
    (FixedLagConfig, "report_every", 0, r"FixedLagConfig.report_every = 0 updates; expected an integer >= 1"),
    (FixedLagConfig, "relinearize_threshold", 0.0,
     r"FixedLagConfig.relinearize_threshold = 0.0; expected a positive number or None"),
    (FixedLagConfig, "relinearize_skip", 0, r"FixedLagConfig.relinearize_skip = 0 updates; expected an integer >= 1"),
    (FixedLagConfig, "covariance", 1, r"FixedLagConfig.covariance = 1; expected True or False"),
    (FixedLagConfig, "rule", None, r"FixedLagConfig.rule = None; expected a NoiseRule"),
    (EKFConfig, "unmodelled_accel", -0.1, r"EKFConfig.unmodelled_accel = -0.1 m/s\^2; expected a positive"),
    (EKFConfig, "unmodelled_ang_accel", 0.0, r"EKFConfig.unmodelled_ang_accel = 0.0 rad/s\^2; expected a positive"),
    (EKFConfig, "p0_scale", 0, r"EKFConfig.p0_scale = 0; expected a positive multiplier"),
    (EKFConfig, "z0", float("inf"), r"EKFConfig.z0 = inf m; expected a finite height"),
    (EKFConfig, "min_force", -1.0, r"EKFConfig.min_force = -1.0 N; expected a positive force"),
    (EKFConfig, "outputs", "no", r"EKFConfig.outputs = 'no'; expected True or False"),
    (EKFConfig, "on_covariance_failure", "ignore",
     r"EKFConfig.on_covariance_failure = 'ignore'; expected 'raise' or 'reset'"),
    (EKFConfig, "nis_limit", -6.0, r"EKFConfig.nis_limit = -6.0; expected a positive normalised innovation"),
    (EKFConfig, "nis_steps", 0, r"EKFConfig.nis_steps = 0 steps; expected an integer >= 1"),
    (EKFConfig, "touchdown", "flat", r"EKFConfig.touchdown = 'flat'; expected 'local' or 'zero-deflection'"),
    (EKFConfig, "ground_tilt_weight", 1.5, r"EKFConfig.ground_tilt_weight = 1.5; expected a number in \[0, 1\]"),
    (EKFConfig, "ground_height_weight", -0.1,
     r"EKFConfig.ground_height_weight = -0.1; expected a number in \[0, 1\]"),
    (NoiseRule, "unmodelled_accel", -1.0, r"NoiseRule.unmodelled_accel = -1.0 m/s\^2; expected a positive"),
    (NoiseRule, "unmodelled_ang_accel", 0.0, r"NoiseRule.unmodelled_ang_accel = 0.0 rad/s\^2; expected a positive"),
    (NoiseRule, "contact_ratio", 0.0, r"NoiseRule.contact_ratio = 0.0; expected a positive ratio"),
    (NoiseRule, "robust_k", -3.5, r"NoiseRule.robust_k = -3.5; expected a positive Huber threshold"),
    (NoiseRule, "jerk_scale", float("nan"), r"NoiseRule.jerk_scale = nan; expected a positive multiplier"),
    (NoiseRule, "inactive_factor", 0, r"NoiseRule.inactive_factor = 0; expected a positive ratio"),
    (NoiseRule, "prior_sigma", (0.1,) * 17, r"NoiseRule.prior_sigma = \(0.1, .*\); expected 18 positive"),
    (NoiseRule, "prior_sigma", (0.0,) * 18, r"NoiseRule.prior_sigma = \(0.0, .*\); expected 18 positive"),
    (NoiseRule, "prior_sigma", "loose", r"NoiseRule.prior_sigma = 'loose'; expected 18 positive"),
]


@pytest.mark.parametrize(("cls", "name", "value", "match"), BAD, ids=[f"{c.__name__}.{n}={v!r}" for c, n, v, _ in BAD])
def test_bad_option_is_a_config_error_naming_it(cls, name, value, match):
    with pytest.raises(ConfigError, match=match):
        cls(**{name: value})
    # the same check when a valid config is modified
    with pytest.raises(ConfigError, match=match):
        dataclasses.replace(cls(), **{name: value})


def test_configs_are_frozen_and_documented():
    import ast
    import inspect

    for cls in (BatchConfig, FixedLagConfig, EKFConfig, NoiseRule):
        with pytest.raises(dataclasses.FrozenInstanceError):
            cls().__setattr__(dataclasses.fields(cls)[0].name, None)
        # every field is followed by its docstring (an expression statement holding a string)
        body = ast.parse(inspect.getsource(cls)).body[0].body
        documented = {stmt.target.id for stmt, nxt in zip(body, body[1:])
                      if isinstance(stmt, ast.AnnAssign) and isinstance(nxt, ast.Expr)
                      and isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str)}
        assert documented == {f.name for f in dataclasses.fields(cls)}, cls.__name__


def test_defaults_are_the_documented_ones():
    assert BatchConfig().max_iterations == 200
    assert FixedLagConfig().lag == 1.0
    assert FixedLagConfig().relinearize == 6
    assert FixedLagConfig().backend == "window"
    # a TOML array (a list) is taken as the tuple it maps onto
    assert NoiseRule(prior_sigma=[0.1] * 18).prior_sigma == (0.1,) * 18


@pytest.fixture(scope="module")
def rec():
    return simulate("stand").slice(0, 200)


@pytest.fixture(scope="module")
def model(rec):
    return ModelConfig.from_recording(rec)


@pytest.mark.parametrize(("run", "what", "known"), [
    (run_batch, "batch smoother", "max_iterations, rel_tol, covariance, global_constants, footholds, rule, secant, "
                                  "noise_calibration"),
    (run_fixed_lag, "fixed-lag smoother", "lag, backend, relinearize, report_every, block, relinearize_threshold, "
                                          "relinearize_skip, covariance, footholds, rule, compiled"),
    (run_ekf, "EKF", "unmodelled_accel, unmodelled_ang_accel, p0_scale, .*, ground_height_weight, imu_gate, "
                     "gate_max_time"),
])
def test_unknown_option_lists_the_known_ones(rec, model, run, what, known):
    with pytest.raises(ConfigError, match=rf"unknown {what} option\(s\) \['lagg'\]; known: {known}$"):
        run(rec, model, lagg=1.0)


def test_unknown_option_through_run_estimator(rec):
    with pytest.raises(ConfigError, match=r"unknown fixed-lag smoother option\(s\) \['max_iterations'\]; known: lag"):
        run_estimator("fixed-lag", rec, max_iterations=3)
    with pytest.raises(ConfigError, match=r"unknown batch smoother option\(s\) \['lag'\]; known: max_iterations"):
        run_estimator("batch", rec, lag=1.0)


def test_bad_keyword_option_is_the_config_error(rec, model):
    with pytest.raises(ConfigError, match=r"FixedLagConfig.lag = -1.0 s; expected a positive duration"):
        run_fixed_lag(rec, model, lag=-1.0)
    with pytest.raises(ConfigError, match=r"FixedLagConfig.report_every = '10' updates; expected an integer >= 1"):
        run_estimator("fixed-lag", rec, model, report_every="10")
    with pytest.raises(ConfigError, match=r"BatchConfig.max_iterations = -5 iterations"):
        run_batch(rec, model, max_iterations=-5)


@pytest.mark.parametrize(("name", "config", "expected"), [
    ("batch", FixedLagConfig(), "BatchConfig"),
    ("fixed-lag", BatchConfig(), "FixedLagConfig"),
    ("ekf", NoiseRule(), "EKFConfig"),
    ("ekf", EKFConfig, "EKFConfig"),
    ("fixed_lag", {"lag": 1.0}, "FixedLagConfig"),
])
def test_wrong_config_type_names_the_expected_one(rec, name, config, expected):
    with pytest.raises(ConfigError, match=rf"takes an? {expected}, got an? {type(config).__name__}"):
        run_estimator(name, rec, config=config)


def test_wrong_config_type_in_the_estimator_itself(rec, model):
    with pytest.raises(ConfigError, match=r"batch smoother: config is a FixedLagConfig .*; expected a BatchConfig"):
        run_batch(rec, model, FixedLagConfig())
    with pytest.raises(ConfigError, match=r"EKF: config is a dict .*; expected an EKFConfig"):
        run_ekf(rec, model, {"outputs": False})


def _same(a, b):
    """Every array of two Estimates equal, bit for bit (timings aside)."""
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name in ("time_per_step", "total_time", "meta"):
            continue
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=f.name)
        elif isinstance(x, dict) and f.name in ("residuals", "residual_sigma"):
            assert x.keys() == y.keys()
            for k in x:
                np.testing.assert_array_equal(x[k], y[k], err_msg=f"{f.name}[{k}]")


RULE = NoiseRule(robust_k=None, contact_ratio=0.2)
CASES = [
    ("batch", BatchConfig(max_iterations=20, covariance=False, rule=RULE),
     {"max_iterations": 20, "covariance": False, "rule": RULE}),
    ("fixed-lag", FixedLagConfig(lag=0.2, relinearize=3, report_every=5, rule=RULE),
     {"lag": 0.2, "relinearize": 3, "report_every": 5, "rule": RULE}),
    ("ekf", EKFConfig(touchdown="zero-deflection", p0_scale=2.0), {"touchdown": "zero-deflection", "p0_scale": 2.0}),
]


@pytest.mark.parametrize(("name", "config", "options"), CASES, ids=[c[0] for c in CASES])
def test_config_and_keyword_paths_give_identical_estimates(rec, model, name, config, options):
    by_config = run_estimator(name, rec, model, config=config)
    by_keywords = run_estimator(name, rec, model, **options)
    _same(by_config, by_keywords)
    # keywords on top of a config replace its fields
    base = dataclasses.replace(config, **{k: getattr(type(config)(), k) for k in options})
    _same(by_config, run_estimator(name, rec, model, config=base, **options))


def test_default_config_is_the_default_behaviour(rec, model):
    _same(run_fixed_lag(rec, model, lag=0.2), run_fixed_lag(rec, model, FixedLagConfig(lag=0.2)))
    _same(run_batch(rec, model, rule=None, max_iterations=20),
          run_batch(rec, model, BatchConfig(max_iterations=20)))
