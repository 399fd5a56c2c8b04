"""The diagnosis's noise calibration (DiagnoseConfig.noise_calibration): IMU residuals far outside
the configured noise (a real walk) scale that sensor's sigma by their RMS; residuals at the noise
level leave the model as it is."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from flexforce.compare.diagnostics.config import DiagnoseConfig
from flexforce.compare.diagnostics.run import calibrate_noise
from flexforce.errors import ConfigError


def _inputs(gyro_rms: float, accel_rms: float, n: int = 4000):
    rng = np.random.default_rng(0)
    res = np.concatenate([gyro_rms * rng.standard_normal((n, 3)), accel_rms * rng.standard_normal((n, 3))], axis=1)
    res[:10] = 1e3  # before skip: left out
    res[100, 4] = np.nan  # a missing sample: left out
    rec = SimpleNamespace(time=np.arange(n) * 0.01)
    import dataclasses

    @dataclasses.dataclass(frozen=True)
    class Model:
        gyro_sigma: float = 0.0087
        accel_sigma: float = 0.039

    nominal = SimpleNamespace(estimate=SimpleNamespace(residuals={"imu": res}))
    return rec, Model(), nominal


def test_residuals_far_outside_the_noise_scale_that_sensors_sigma():
    rec, model, nominal = _inputs(1.1, 19.0)
    out = calibrate_noise(rec, model, nominal, DiagnoseConfig(skip=0.5))
    assert out is not None
    assert out["scale"]["gyro"] == 1.0 and out["scale"]["accel"] == pytest.approx(19.0, rel=0.02)
    assert out["model"].gyro_sigma == model.gyro_sigma
    assert out["model"].accel_sigma == pytest.approx(0.039 * 19.0, rel=0.02)
    assert out["text"].startswith("noise: ") and f"{out['rms']['accel']:.1f} sigma (accelerometer)" in out["text"]


def test_residuals_at_the_noise_level_or_calibration_off_change_nothing():
    rec, model, nominal = _inputs(1.2, 2.5)
    assert calibrate_noise(rec, model, nominal, DiagnoseConfig(skip=0.5)) is None
    rec, model, nominal = _inputs(9.0, 19.0)
    assert calibrate_noise(rec, model, nominal, DiagnoseConfig(skip=0.5, noise_calibration=None)) is None


@pytest.mark.parametrize("bad", [0.5, 1.0, float("nan"), "3", True])
def test_a_threshold_that_is_no_number_of_sigmas_above_one_is_refused(bad):
    with pytest.raises(ConfigError, match="noise_calibration"):
        DiagnoseConfig(noise_calibration=bad)


def test_a_constant_offset_is_an_effect_to_find_not_noise():
    """Residuals 10 sigma off on average but 1 sigma about their mean (a gyrometer bias the model
    misses): no calibration -- the bias is for the ranking to find."""
    rec, model, nominal = _inputs(1.0, 1.0)
    nominal.estimate.residuals["imu"][:, :3] += 10.0
    assert calibrate_noise(rec, model, nominal, DiagnoseConfig(skip=0.5)) is None
