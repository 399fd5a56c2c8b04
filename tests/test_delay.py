"""The readings at shifted times (:mod:`flexforce.factors.delay`), the time offset's exact delay:
a band-limited series shifted exactly, white noise kept white at every shift, the rate that of the
signal and not of the noise, both evaluation paths the same, and bad input refused."""

from __future__ import annotations

import numpy as np
import pytest

from flexforce.errors import DataError
from flexforce.factors.delay import DIRECT_MAX, ShiftedSignal, noise_sigma

DT = 0.005
T = np.arange(800) * DT  # 4 s at 200 Hz
INNER = slice(60, len(T) - 60)  # 0.3 s from each end: the series' return from its end to its start


def signal(t):
    """A motion's readings: two slow components and a faster one (all below 20 Hz)."""
    return np.stack([np.sin(2 * np.pi * 0.7 * t) + 0.3 * np.cos(2 * np.pi * 3.1 * t),
                     0.2 * np.sin(2 * np.pi * 11.3 * t + 0.4)], axis=1)


def rate(t):
    w1, w2, w3 = 2 * np.pi * 0.7, 2 * np.pi * 3.1, 2 * np.pi * 11.3
    return np.stack([w1 * np.cos(w1 * t) - 0.3 * w2 * np.sin(w2 * t), 0.2 * w3 * np.cos(w3 * t + 0.4)], axis=1)


def test_a_band_limited_series_is_shifted_exactly():
    """Its bands above the noise (here, the noise the third differences of an 11 Hz sine suggest)
    are shifted exactly; what stands below them (the sines' leakage, not periodic over 4 s) stays
    at its sample."""
    sig = ShiftedSignal(signal(T), DT)
    k = np.arange(len(T))
    x, _ = sig.at(k, 0.0)
    np.testing.assert_allclose(x, signal(T), atol=1e-12)  # no shift: the samples
    for tau in (0.005, -0.0123, 0.031):
        x, xd = sig.at(k, tau)
        # measured 8e-4 to 2.5e-3 of the unit amplitude away from the ends (the 11 Hz sine's
        # leakage below the estimated noise, left in place); margin 2x
        assert np.max(np.abs(x[INNER] - signal(T + tau)[INNER])) < 5e-3
        # the rate is the signal's estimate: measured 1.75 % of the largest rate (the leakage's
        # weakest frequencies are below the gain's threshold); margin 2x
        assert np.max(np.abs(xd[INNER] - rate(T + tau)[INNER])) < 0.035 * np.max(np.abs(rate(T)))


@pytest.mark.parametrize("frac", [0.25, 0.5])
def test_white_noise_stays_white_at_a_fractional_shift(frac):
    """Readings ``x(t) + n``: the shifted readings minus the shifted signal keep the noise's variance
    (an average of neighbouring samples, as a linear interpolation, would leave 0.625 of it at half
    a sample, and a fit would prefer such shifts) and stay uncorrelated from sample to sample."""
    rng = np.random.default_rng(4)
    sigma = 0.05
    y = signal(T) + rng.normal(0.0, sigma, (len(T), 2))
    sig = ShiftedSignal(y, DT)
    tau = (7 + frac) * DT
    x, _ = sig.at(np.arange(len(T)), tau)
    noise = (x - signal(T + tau))[INNER]
    var = noise.var(axis=0) / sigma**2
    # 680 samples: the variance's sampling sigma is 5.4 %; measured 1.02-1.09; margin 3 sigma
    assert np.all(np.abs(var - 1.0) < 0.16), var
    lag1 = np.array([np.corrcoef(noise[1:, j], noise[:-1, j])[0, 1] for j in range(2)])
    # measured 0.013 and 0.053; the bound is 3 sampling sigmas of an uncorrelated series
    assert np.all(np.abs(lag1) < 0.12), lag1


def test_the_rate_is_the_signals_not_the_noises():
    """The noise's own derivative has a standard deviation of ``1.8 sigma / dt`` (18 here), more
    than the motion's rate; the returned rate is the signal's: within 0.15 of its own RMS."""
    rng = np.random.default_rng(5)
    sigma = 0.05
    y = signal(T) + rng.normal(0.0, sigma, (len(T), 2))
    sig = ShiftedSignal(y, DT)
    # the noise measured on the readings: 0.0527, 0.0523; margin 2x the deviation
    np.testing.assert_allclose(sig.sigma, sigma, rtol=0.1)
    _, xd = sig.at(np.arange(len(T)), 0.002)
    err = np.sqrt(np.mean((xd - rate(T + 0.002))[INNER] ** 2, axis=0))
    scale = np.sqrt(np.mean(rate(T)[INNER] ** 2, axis=0))
    # measured 0.035 and 0.069 of the rate's RMS (the 11 Hz component is the weaker); margin 2x
    assert np.all(err / scale < 0.15), err / scale
    # and it is the derivative of the signal's estimate (the gained coefficients) in tau
    h = 1e-6
    w = np.full(len(sig.omega), 2.0 / sig.M)
    w[[0, -1]] = 1.0 / sig.M

    def estimate(tt):
        return (np.exp(1j * np.outer(tt, sig.omega)) * w) @ sig.coef_signal

    tt = T[100:110] + 0.002
    num = ((estimate(tt + h) - estimate(tt - h)) / (2 * h)).real
    np.testing.assert_allclose(xd[100:110], num, rtol=1e-6, atol=1e-6 * np.abs(num).max())


def test_white_noise_sigma_is_measured_beside_a_motion_and_impacts():
    rng = np.random.default_rng(6)
    y = signal(T) + rng.normal(0.0, 0.02, (len(T), 2))
    y[::80] += 3.0  # ten impacts
    # measured 0.0218 on both (the impacts touch 40 of the 797 third differences, which moves their
    # median); margin 2x the deviation
    np.testing.assert_allclose(noise_sigma(y), 0.02, rtol=0.2)


def test_the_two_evaluation_paths_agree():
    """Few times are summed directly, many through inverse FFTs (a Taylor step for shifts close to
    their median): the same values."""
    rng = np.random.default_rng(7)
    sig = ShiftedSignal(signal(T) + rng.normal(0.0, 0.05, (len(T), 2)), DT)
    k = np.arange(100, 100 + 3 * DIRECT_MAX)
    tau = 0.0137 + rng.normal(0.0, 2e-6, len(k))
    tau[::7] = -0.004  # a second group, by its own inverse FFT
    x, xd = sig.at(k, tau)
    for part in np.array_split(np.arange(len(k)), 4):
        xs, xds = sig.at(k[part], tau[part])
        np.testing.assert_allclose(x[part], xs, atol=1e-9)
        np.testing.assert_allclose(xd[part], xds, atol=1e-7 * np.abs(xd).max())


def test_missing_readings_are_bridged():
    y = signal(T)
    use = np.ones_like(y, dtype=bool)
    use[300:305, 0] = False
    bad = y.copy()
    bad[300:305, 0] = 0.0  # a placeholder, as the problem's
    x, _ = ShiftedSignal(bad, DT, use).at(np.arange(len(T)), 0.0)
    # at no shift the readings are the samples, the gap a straight line between its neighbours
    bridge = np.interp(np.arange(300, 305), [299, 305], y[[299, 305], 0])
    np.testing.assert_allclose(x[300:305, 0], bridge, atol=1e-9)
    np.testing.assert_allclose(np.delete(x, np.s_[300:305], axis=0), np.delete(y, np.s_[300:305], axis=0),
                               atol=1e-9)


@pytest.mark.parametrize("y, dt, words", [
    (np.zeros((1, 2)), DT, "at least 2 samples"),
    (np.zeros((10, 2)), 0.0, "positive sampling period"),
    (np.full((10, 2), np.nan), DT, "NaN or inf"),
])
def test_bad_input_is_one_clear_error(y, dt, words):
    with pytest.raises(DataError, match=words):
        ShiftedSignal(y, dt)


def test_transients_and_events_are_shifted_whole():
    """A step in the readings (an impact's broadband content, weak in every band) is found as a
    transient and the readings within reach of it are shifted whole; a switch given as an event
    is marked though the readings show nothing; quiet noise is not marked."""
    rng = np.random.default_rng(8)
    sigma = 0.05
    y = signal(T) + rng.normal(0.0, sigma, (len(T), 2))
    y[400:, 1] += 1.0  # a step at 2 s on the second axis
    sig = ShiftedSignal(y, DT, events=[200])
    reach = int(np.ceil(0.06 / DT))
    assert np.all(sig.transient[400 - reach:400 + reach, 1] == 1.0)
    assert np.all(sig.transient[200 - reach:200 + reach] == 1.0)  # the event, on every axis
    quiet = np.r_[300:340, 500:700]
    assert not sig.transient[quiet, 0].any() and not sig.transient[quiet, 1].any()
    # near the step the readings are shifted whole: at a shift of two samples the step has moved
    x, _ = sig.at(np.arange(len(T)), 2 * DT)
    assert abs(x[397, 1] - y[399, 1]) < 1e-9 and abs(x[398, 1] - y[400, 1]) < 1e-9
