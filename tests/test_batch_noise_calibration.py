"""The batch smoother's noise calibration (BatchConfig.noise_calibration): IMU residuals far above
the configured noise make it smooth again with that sensor's sigma scaled by their RMS; residuals at
their noise level leave the estimate bit for bit as without it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flexforce.compare.estimators import nominal_model
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import ConfigError
from flexforce.smoother.batch import BatchConfig, run_batch
from flexforce.smoother.problem import imu_residual_scale


@pytest.fixture(scope="module")
def rec():
    sc = Scenario.load("push-pitch")
    sc.duration = 1.5
    return Simulator(sc).run()


def test_noise_at_its_level_changes_nothing(rec):
    model = nominal_model(rec)
    plain = run_batch(rec, model, BatchConfig(covariance=False))
    cal = run_batch(rec, model, BatchConfig(covariance=False, noise_calibration=3.0))
    record = cal.meta["noise_calibration"]
    assert record["scale"] == {"gyro": 1.0, "accel": 1.0} and max(record["rms_sigma"].values()) < 3.0
    np.testing.assert_array_equal(plain.wrench, cal.wrench)
    np.testing.assert_array_equal(plain.R, cal.R)


def test_an_accelerometer_noise_far_too_small_is_found_and_used(rec):
    """The model told the accelerometer is 100 times better than it is: its residuals come out far
    above 3 sigma (113), the sigma is scaled by their RMS, and the vertical forces come closer to
    the true ones than without (0.61 against 0.86 N RMS)."""
    model = nominal_model(rec)
    wrong = dataclasses.replace(model, accel_sigma=model.accel_sigma / 100.0)
    plain = run_batch(rec, wrong, BatchConfig(covariance=False))
    cal = run_batch(rec, wrong, BatchConfig(covariance=False, noise_calibration=3.0))
    record = cal.meta["noise_calibration"]
    assert record["scale"]["gyro"] == 1.0 and record["scale"]["accel"] > 3.0
    assert record["accel_sigma"] == pytest.approx(wrong.accel_sigma * record["scale"]["accel"])
    # the rms the first fit left, recomputed from its own residuals
    rms, _ = imu_residual_scale(plain.residuals["imu"], rec.time, 0.0, 3.0)
    assert record["rms_sigma"]["accel"] == pytest.approx(rms["accel"])
    truth = rec.truth.wrench
    err = [float(np.sqrt(np.mean((e.wrench[..., 2] - truth[..., 2]) ** 2))) for e in (plain, cal)]
    assert err[1] < err[0], err


@pytest.mark.parametrize("bad", [1.0, 0.0, float("inf"), "3", True])
def test_a_bad_threshold_is_refused(bad):
    with pytest.raises(ConfigError, match="noise_calibration"):
        BatchConfig(noise_calibration=bad)
