"""Tests of the effect catalogue (flexforce.factors.effects) and of the fit API (flexforce.smoother.fit).

For each effect: a 3 s simulated sway whose truth holds it (datasets/sim/effects.py parameters),
fitted with and without the effect; and the same effect fitted on the recording without it.  Plus
finite-difference checks of every effect's residual terms (world-frame increments, the smoothers'
retraction) and the protocol's contact family in the fixed-lag smoother.

The figures each effect reaches on these recordings (estimate ± std, score, errors before and
after) are measured by ``benchmarks/diagnose_confusion.py`` (same sway, every effect at two
magnitudes and two seeds, ranked among all the others): ``benchmarks/results/diagnose_confusion.json``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
from baseline import lower, upper

from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.factors import core, so3
from flexforce.factors.effects import EFFECTS, make_effect
from flexforce.factors.model import ModelConfig
from flexforce.smoother import Effect, Problem, fit, run_fixed_lag

# Margins.  The recordings are seeded, so each number below is deterministic; the fit stops at a
# relative cost decrease of 1e-7 or after its iteration budget, which is what moves them.
# FIT: 10 % on an error ratio or an estimated value's error of a converged fit.
FIT = 0.10

DURATION = 3.0
TRUTH: dict[str, dict[str, Any]] = {
    "external-wrench": {"type": "external-wrench", "link": "@base", "force": [40.0, 0.0, 0.0], "start": 1.5,
                        "duration": 0.4},
    "gyro-bias": {"type": "gyro-bias", "value": [0.0, 0.01, 0.0]},
    "accel-bias": {"type": "accel-bias", "value": [0.08, -0.05, 0.0]},
    "stiffness": {"type": "stiffness", "stiffness": 0.7, "damping": 1.0},
    "anisotropic-stiffness": {"type": "anisotropic-stiffness", "k_fs": [1.0, 1.0, 0.7], "k_ts": [0.7, 1.0, 1.0]},
    "nonlinear-stiffness": {"type": "nonlinear-stiffness", "beta_f": 4000.0, "beta_t": 0.0},
    "com-offset": {"type": "com-offset", "offset": [0.02, 0.0, 0.0]},
}
_CACHE: dict = {}


def simulate(effect: str | None, duration: float = DURATION):
    key = (effect, duration)
    if key not in _CACHE:
        sc = Scenario.load("sway")
        sc.duration = duration
        sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
        sc.effects = [TRUTH[effect]] if effect else []
        _CACHE[key] = Simulator(sc).run()
    return _CACHE[key]


@pytest.fixture(scope="module")
def null():
    rec = simulate(None)
    model = ModelConfig.from_recording(rec)
    est, stats = fit(rec, model)
    return rec, model, est, stats


_FITS: dict = {}


def fits(name, null):
    """(rec, nominal fit, fit with the effect, fit of the effect on the recording without it), each
    fit an ``(Estimate, FitStatistics)`` pair."""
    if name not in _FITS:
        rec0, model, _, _ = null
        rec = simulate(name)
        cfg = dataclasses.replace(model, effects=(make_effect(name),))
        _FITS[name] = (rec, fit(rec, model), fit(rec, cfg), fit(rec0, cfg))
    return _FITS[name]


def errors(est, rec):
    tr = rec.truth
    force = np.sqrt(np.mean(np.sum((est.total_wrench[:, :3] - tr.total_wrench[:, :3]) ** 2, axis=1)))
    cop = np.sqrt(np.mean(np.sum((est.cop[:, :2] - tr.cop[:, :2]) ** 2, axis=1)))
    theta = np.array([so3.log(est.R[k] @ tr.R[k].T) for k in range(rec.n)])
    return force, cop, np.sqrt(np.mean(np.sum(theta**2, axis=1)))


def gain(a, b):
    """Data cost of fit statistics ``a`` minus that of ``b``."""
    return a.cost_data - b.cost_data


# ----------------------------------------------------------------------------------------------
# Registry, protocol, Jacobians
# ----------------------------------------------------------------------------------------------


def test_registry_covers_the_simulator_effects():
    from flexforce.datasets.sim.effects import EFFECT_TYPES

    assert set(EFFECTS) == set(EFFECT_TYPES)
    for name in EFFECTS:
        eff = make_effect(name)
        assert isinstance(eff, Effect) and eff.name == name and len(eff.labels) == eff.dim
    from flexforce.errors import ConfigError

    with pytest.raises(ConfigError):
        make_effect("no-such-effect")
    with pytest.raises(ConfigError):
        make_effect("gyro-bias", bogus=1)


@pytest.fixture(scope="module")
def small_problem():
    rec = simulate(None, 0.2)
    return Problem.build(rec, ModelConfig.from_recording(rec, use_ft=True)), rec  # ft-offset needs F/T fused


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_residual_terms_match_finite_differences(name, small_problem):
    """Jacobians of each effect's terms against central differences through the retraction."""
    prob, rec = small_problem
    rng = np.random.default_rng(3)
    steps = np.arange(10, 14)
    n = len(steps)
    tr = rec.truth
    R = tr.R[steps].copy()
    q = np.concatenate([tr.t, tr.w, tr.v, tr.dw, tr.a], axis=1)[steps].copy()
    q[:, 3:] += rng.normal(0.0, 0.1, (n, 12))
    W = np.zeros((n, prob.nc, 6))
    eff = make_effect(name)
    s0 = eff.prior(prob)[1]
    e = rng.normal(0.0, 0.3, (n, eff.dim)) * s0
    touched = 0
    for fam in ("newton_euler", "imu", "contact", "ft"):
        out = eff.residual_terms(fam, prob, steps, R, q, W, e)
        if out is None:
            continue
        touched += 1
        dr, Js, Je = out
        h = 1e-6
        for j in range(18):
            d = np.zeros((n, 18))
            d[:, j] = h
            Rp, qp, Rm, qm = R.copy(), q.copy(), R.copy(), q.copy()
            core.retract_all(Rp, qp, d)
            core.retract_all(Rm, qm, -d)
            num = (eff.residual_terms(fam, prob, steps, Rp, qp, W, e)[0]
                   - eff.residual_terms(fam, prob, steps, Rm, qm, W, e)[0]) / (2 * h)
            np.testing.assert_allclose(Js[..., j], num, atol=1e-6 * (np.abs(Js).max() + 1.0))
        # the step: a millionth of the unknown's scale (the footholds' gauge priors are a thousandth
        # of their kinematic sigmas: a step that small drowns in rounding)
        scale = eff.kinematic_sigmas(prob) if hasattr(eff, "kinematic_sigmas") else s0
        if name == "time-offset":
            # dr/dtau is the rate of the readings' signal, not of their shifted noise (its expected
            # value: factors/delay.py; checked against the signal's differences in tests/test_delay.py)
            sig = eff.signal(prob)
            np.testing.assert_allclose(Je[..., 0], -sig.at(steps, e[:, 0])[1], rtol=1e-12)
            continue
        for j in range(eff.dim):
            he = 1e-6 * scale[j]
            ep, em = e.copy(), e.copy()
            ep[:, j] += he
            em[:, j] -= he
            num = (eff.residual_terms(fam, prob, steps, R, q, W, ep)[0]
                   - eff.residual_terms(fam, prob, steps, R, q, W, em)[0]) / (2 * he)
            np.testing.assert_allclose(Je[..., j], num, atol=1e-6 * (np.abs(Je[..., j]).max() + 1e-9))
    assert touched >= 1


def test_contact_effect_in_the_window_fixed_lag_smoother():
    """The contact family's effect terms in the (window) fixed-lag smoother: a stiffness scale is
    learnt online, close to the batch fit."""
    rec = simulate("stiffness")
    cfg = dataclasses.replace(ModelConfig.from_recording(rec), effects=(make_effect("stiffness"),))
    est = run_fixed_lag(rec, cfg, lag=0.5)
    rep = est.effects["stiffness"]
    err = abs(rep["value"][0] - 0.7)
    # 0.01 absolute on the scale's error (the scale is learnt online: where the window stops matters)
    assert err <= upper("effects.fixed_lag_stiffness.scale_error", err, add=0.01), rep["summary"]


# ----------------------------------------------------------------------------------------------
# Fit API
# ----------------------------------------------------------------------------------------------


def test_fit_statistics(null):
    rec, model, est, info = null
    assert "fit" not in est.meta  # the statistics are returned, typed, not a side channel
    assert info.effective_dof == {}
    # nominal world = nominal model: the data cost is below half the number of residuals (the
    # fit absorbs part of the noise), at the fraction measured
    frac = info.cost_data / info.n_residuals
    assert frac < 0.5
    key = "effects.null_fit.cost_data_per_residual"
    assert lower(key, frac, rel=FIT) <= frac <= upper(key, frac, rel=FIT), frac
    r = np.concatenate([np.ravel(est.residuals[f]) for f in ("imu", "newton_euler", "contact", "integration")])
    r = r[np.isfinite(r)]
    assert info.n_residuals == r.size
    np.testing.assert_allclose(info.cost_data, 0.5 * np.sum(r**2))


# ----------------------------------------------------------------------------------------------
# Recovery, per effect
# ----------------------------------------------------------------------------------------------


def check_common(name, null):
    """The cost gain of the effect where it is present, per effective degree of freedom, as
    measured (FIT; the gains are tens to thousands of dof, far above a BIC penalty of ~ln N per
    dof); and, where it is absent, a gain within chance: below 10 + 2 dof (chi-square(dof)/2 has
    mean dof/2 and standard deviation sqrt(dof/2))."""
    rec, (base, base_stats), (with_e, with_stats), (null_fit, null_stats) = fits(name, null)
    dof = with_stats.effective_dof[name]
    g = gain(base_stats, with_stats)
    assert g / dof >= lower(f"effects.{name}.gain_per_dof", g / dof, rel=FIT), (g, dof)
    g0 = gain(null[3], null_stats)
    dof0 = null_stats.effective_dof[name]
    assert g0 < 10 + 2 * dof0, (g0, dof0)
    return rec, base, with_e, null_fit, g0, dof0


def check_errors(name, base_errors, effect_errors):
    """Each error (force, CoP, tilt) with the effect, relative to the nominal fit: as measured (FIT)."""
    ratios = {}
    for what, e, b in zip(("force", "cop", "tilt"), effect_errors, base_errors):
        ratios[what] = e / b
        assert e / b <= upper(f"effects.{name}.{what}_over_nominal", e / b, rel=FIT), (what, e, b)
    return ratios


def test_gyro_bias(null):
    rec, base, est, nfit, g0, dof0 = check_common("gyro-bias", null)
    rep = est.effects["gyro-bias"]
    v, s = np.array(rep["value"]), np.array(rep["std"])
    truth = np.array(TRUTH["gyro-bias"]["value"])
    # 4 sigma: the estimate against the truth in its own uncertainty (false alarm 6e-5 per axis)
    assert np.all(np.abs(v - truth) < 4 * s), (v, s)
    err = np.abs(v - truth).max()
    # 1e-4 rad/s absolute: a tenth of the estimate's standard deviation
    assert err <= upper("effects.gyro-bias.value_error_rad_s", err, add=1e-4), (v, s)
    assert "gyro bias y" in rep["summary"] and rep["unit"] == "rad/s"
    ratios = check_errors("gyro-bias", errors(base, rec), errors(est, rec))
    assert ratios["tilt"] < 1 and ratios["cop"] < 1 and ratios["force"] <= 1, ratios
    nv, ns = np.array(nfit.effects["gyro-bias"]["value"]), np.array(nfit.effects["gyro-bias"]["std"])
    assert np.all(np.abs(nv) < 4 * ns)
    # a constant 3-vector with a weak prior: 3 effective dof, to the prior's share (< 1e-2)
    assert abs(dof0 - 3) < 0.01


@pytest.mark.slow
def test_accel_bias(null):
    rec, base, est, nfit, g0, dof0 = check_common("accel-bias", null)
    rep = est.effects["accel-bias"]
    v, s = np.array(rep["value"]), np.array(rep["std"])
    truth = np.array(TRUTH["accel-bias"]["value"])
    assert np.all(np.abs(v - truth) < 4 * s), (v, s)
    err = np.abs(v - truth).max()
    # 1e-3 m/s^2 absolute: about a tenth of the estimate's standard deviation
    assert err <= upper("effects.accel-bias.value_error_m_s2", err, add=1e-3), (v, s)
    ratios = check_errors("accel-bias", errors(base, rec), errors(est, rec))
    assert all(r < 1 for r in ratios.values()), ratios
    nv, ns = np.array(nfit.effects["accel-bias"]["value"]), np.array(nfit.effects["accel-bias"]["std"])
    assert np.all(np.abs(nv) < 4 * ns)


@pytest.mark.slow
def test_external_wrench(null):
    rec, base, est, nfit, g0, dof0 = check_common("external-wrench", null)
    rep = est.effects["external-wrench"]
    assert len(rep["windows"]) == 1, rep["summary"]
    w = rep["windows"][0]
    # the push acts from 1.5 s to 1.9 s; the window's ends as measured, to 20 ms (4 samples)
    for end in ("start_s", "end_s"):
        key = f"effects.external-wrench.window_{end}"
        assert lower(key, w[end], add=0.02) <= w[end] <= upper(key, w[end], add=0.02), w
    assert w["start_s"] < 1.5 + 0.1 and w["end_s"] > 1.9 - 0.1, w
    # truth at the estimated peak (about the world origin)
    k = int(round(w["peak_s"] / rec.dt))
    truth = rec.truth.external_wrench[k]
    est_w, std = np.array(w["peak_wrench"]), np.array(w["peak_std"])
    assert abs(est_w[0] - truth[0]) < max(4 * std[0], 0.15 * abs(truth[0])), (est_w, truth, std)
    assert abs(est_w[4] - truth[4]) < max(4 * std[4], 0.15 * abs(truth[4])), (est_w, truth, std)
    assert "external force" in rep["summary"] and "along x" in rep["summary"]
    # the tilt and CoP errors fall; the horizontal force (only seen through the contacts'
    # dynamics) does not, by as much as measured
    ratios = check_errors("external-wrench", errors(base, rec), errors(est, rec))
    assert ratios["tilt"] < 1 and ratios["cop"] < 1, ratios
    assert nfit.effects["external-wrench"]["windows"] == []
    # a random walk of 6-vectors with a tight prior: its effective dof on the null recording as
    # measured, to 25 % (it counts how much of the noise the walk can absorb: sensitive to the fit)
    key = "effects.external-wrench.null_effective_dof"
    assert lower(key, dof0, rel=0.25) <= dof0 <= upper(key, dof0, rel=0.25), dof0


@pytest.mark.slow
def test_com_offset(null):
    rec, base, est, nfit, g0, dof0 = check_common("com-offset", null)
    rep = est.effects["com-offset"]
    v, s = np.array(rep["value"]), np.array(rep["std"])
    truth = np.array(TRUTH["com-offset"]["offset"])
    # x, y (the z component is confounded with the rotational stiffness: not estimated by default)
    assert v.shape == (2,) and np.all(np.abs(v - truth[:2]) < 4 * s), (v, s)
    ratios = check_errors("com-offset", errors(base, rec), errors(est, rec))
    assert all(r < 1 for r in ratios.values()), ratios
    nv, ns = np.array(nfit.effects["com-offset"]["value"]), np.array(nfit.effects["com-offset"]["std"])
    assert np.all(np.abs(nv[:2]) < 4 * ns[:2])


@pytest.mark.slow
def test_stiffness(null):
    rec, base, est, nfit, g0, dof0 = check_common("stiffness", null)
    rep = est.effects["stiffness"]
    v, s = np.array(rep["value"]), np.array(rep["std"])
    # truth: stiffness scale 0.7, damping scale 1
    assert abs(v[1] - 1.0) < 4 * s[1], (v, s)
    err = abs(v[0] - 0.7)
    # 0.01 absolute on the scale's error (a fit that stops after its iteration budget)
    assert err <= upper("effects.stiffness.scale_error", err, add=0.01), (v, s)
    ratios = check_errors("stiffness", errors(base, rec), errors(est, rec))
    assert all(r < 1 for r in ratios.values()), ratios
    nv, ns = np.array(nfit.effects["stiffness"]["value"]), np.array(nfit.effects["stiffness"]["std"])
    assert abs(nv[0] - 1) < 4 * ns[0] and abs(nv[1] - 1) < 4 * ns[1]


@pytest.mark.slow
def test_stiffness_recovered_within_its_std(null):
    rec, _, (est, _), _ = fits("stiffness", null)
    rep = est.effects["stiffness"]
    assert abs(rep["value"][0] - 0.7) < 4 * rep["std"][0]


@pytest.mark.slow
def test_anisotropic_stiffness(null):
    rec, base, est, nfit, g0, dof0 = check_common("anisotropic-stiffness", null)
    rep = est.effects["anisotropic-stiffness"]
    v, s = np.array(rep["value"]), np.array(rep["std"])
    truth = np.r_[TRUTH["anisotropic-stiffness"]["k_fs"], TRUTH["anisotropic-stiffness"]["k_ts"]]
    assert np.all(np.abs(v - truth) < 4 * s), (v, s)
    ratios = check_errors("anisotropic-stiffness", errors(base, rec), errors(est, rec))
    assert all(r < 1 for r in ratios.values()), ratios
    aniso = nfit.effects["anisotropic-stiffness"]
    nv, ns = np.array(aniso["value"]), np.array(aniso["std"])
    assert np.all(np.abs(nv - 1) < 4 * ns)


@pytest.mark.slow
def test_nonlinear_stiffness(null):
    rec, base, est, nfit, g0, dof0 = check_common("nonlinear-stiffness", null)
    rep = est.effects["nonlinear-stiffness"]
    v, s = np.array(rep["value"]), np.array(rep["std"])
    # stiffening found (beta_t: truth 0), with the relative bias on beta_f (truth 4000) as measured
    # (7 %); test_nonlinear_stiffness_is_recovered holds the estimate to the truth in its own sigma
    assert v[0] > 2 * s[0] and abs(v[1]) < 4 * s[1], (v, s)
    bias = abs(v[0] - 4000.0) / 4000.0
    # 0.05 absolute on the relative bias (a fit that stops after its iteration budget)
    assert bias <= upper("effects.nonlinear-stiffness.beta_f_relative_bias", bias, add=0.05), (v, s)
    ratios = check_errors("nonlinear-stiffness", errors(base, rec), errors(est, rec))
    assert all(r < 1 for r in ratios.values()), ratios
    cubic = nfit.effects["nonlinear-stiffness"]
    nv, ns = np.array(cubic["value"]), np.array(cubic["std"])
    assert np.all(np.abs(nv) < 4 * ns)


@pytest.mark.slow
def test_nonlinear_stiffness_is_recovered(null):
    rec, _, (est, _), _ = fits("nonlinear-stiffness", null)
    rep = est.effects["nonlinear-stiffness"]
    v, s = np.array(rep["value"]), np.array(rep["std"])
    assert abs(v[0] - 4000.0) < 4 * s[0], (v, s)
