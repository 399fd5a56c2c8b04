"""Residual tests on synthetic residuals whose statistics are known."""

from __future__ import annotations

import numpy as np
import pytest
from baseline import lower, upper

from flexforce.compare.diagnostics.residuals import consistency, flag_windows, residual_rms
from flexforce.datasets.estimate import Estimate


def make_estimate(residuals: dict, sigma: dict | None = None, rate: float = 200.0) -> Estimate:
    n = next(iter(residuals.values())).shape[0]
    z3 = np.zeros((n, 3))
    return Estimate(estimator="test", t_ns=(np.arange(n) * 1e9 / rate).astype(np.int64), contact_names=("a",),
                    R=np.tile(np.eye(3), (n, 1, 1)), t=z3, w=z3, v=z3, dw=z3, a=z3, wrench=np.zeros((n, 1, 6)),
                    cop=z3, residuals=residuals,
                    residual_labels={k: tuple(f"F_{'xyz'[j % 3]} [N]" for j in range(v.shape[1]))
                                     for k, v in residuals.items()},
                    residual_sigma=sigma or {})


def test_white_noise_raises_no_flag():
    rng = np.random.default_rng(1)
    false_alarms = 0
    for _ in range(20):
        est = make_estimate({"newton_euler": rng.standard_normal((2000, 3))})
        false_alarms += bool(flag_windows(est, alpha=0.01))
    # Binomial(20, alpha = 0.01) windows-tests per run: P(more than 2 of 20 runs flag) = 1e-3
    assert false_alarms <= 2


def test_a_push_is_flagged_where_and_how_big_it_is():
    rng = np.random.default_rng(2)
    r = rng.standard_normal((2000, 3))
    sigma = np.array([4.0, 4.0, 4.0])  # N
    push = np.zeros(2000)
    push[620:680] = 38.0 / 4.0  # 38 N along x between 3.1 and 3.4 s, whitened
    r[:, 0] += push
    est = make_estimate({"newton_euler": r}, {"newton_euler": sigma})
    flags = flag_windows(est, window=0.25, alpha=0.01)
    assert len(flags) == 1
    f = flags[0]
    assert f.family == "newton_euler" and f.axis == "F_x [N]" and f.unit == "N"
    # the push is on from 3.1 s to 3.4 s; the flagged window's ends as measured, to 10 ms (2 samples)
    for end in ("start_s", "end_s"):
        value = getattr(f, end)
        assert lower(f"residuals.push.{end}", value, add=0.01) <= value <= upper(f"residuals.push.{end}", value,
                                                                                 add=0.01), f
    assert f.start_s <= 3.1 + 0.05 and f.end_s >= 3.4 - 0.05, f
    # the window's mean force: 38 N along +x (pushed forward), diluted by the window's quiet part
    # as measured; 2 % for the seeded noise's summation order and nothing else
    assert f.mean > 0
    key = "residuals.push.mean_N"
    assert lower(key, f.mean, rel=0.02) <= f.mean <= upper(key, f.mean, rel=0.02), f.mean
    assert "F_x [N]" in f.describe()


def test_correlated_residual_fails_whiteness():
    rng = np.random.default_rng(3)
    e = rng.standard_normal(3000)
    ar = np.zeros(3000)
    for k in range(1, 3000):
        ar[k] = 0.8 * ar[k - 1] + 0.6 * e[k]  # unit variance, strongly correlated
    est = make_estimate({"imu": np.column_stack([rng.standard_normal(3000), ar])})
    cons = {c.axis: c for c in consistency(est)}
    white, colored = cons["F_x [N]"], cons["F_y [N]"]
    assert white.ljung_box_p > 0.001 and colored.ljung_box_p < 1e-6
    rms = residual_rms(est)["imu"]
    assert rms["F_x [N]"] == pytest.approx(1.0, abs=0.05)


def test_nan_steps_are_skipped():
    rng = np.random.default_rng(4)
    r = rng.standard_normal((1000, 2))
    r[:300] = np.nan  # family absent (e.g. a contact in the air)
    est = make_estimate({"contact": r})
    assert flag_windows(est) == []
    assert all(np.isfinite(c.rms_sigma) for c in consistency(est))
