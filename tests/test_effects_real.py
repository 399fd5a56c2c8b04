"""The effects real logs show -- ``imu-mounting``, ``time-offset``, ``mass-scale`` -- against their
simulator twins (:mod:`flexforce.datasets.sim.effects`) and against independent paths.

- Each term against the physics computed another way: the mounting rotation is the prediction
  with the IMU frame turned (:func:`flexforce.factors.physics.imu_readings` with a rotated
  placement); the mass scale is the required wrench with scaled inputs
  (:func:`flexforce.factors.physics.required_wrench`).
- Each twin at the truth, noise-free: the simulator really turns its IMU frame, really delays its
  IMU samples (through a cubic spline, the term through a band-limited shift), really scales its
  bodies (pinocchio's multibody model), and the term at the true value leaves of the nominal
  model's residual at the true states what was measured.
- The diagnosis (slow): on a recording with the twin hidden, the right candidate first, the errors
  against the truth falling; on a clean recording, none of the three significant.

(Their Jacobians are checked with the others' in ``tests/test_effects.py``.)
"""

from __future__ import annotations

import numpy as np
import pytest

from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.factors import core, physics, so3
from flexforce.factors.effects import EFFECTS, make_effect
from flexforce.factors.model import ModelConfig
from flexforce.smoother import Problem

NEW = ("imu-mounting", "time-offset", "mass-scale")
TWIN = {
    "imu-mounting": ({"type": "imu-mounting", "rotation": [0.02, -0.01, 0.05]}, [0.02, -0.01, 0.05]),
    "time-offset": ({"type": "time-offset", "delay": 0.02}, [0.02]),
    "mass-scale": ({"type": "mass-scale", "scale": 1.1}, [0.1]),
}
_CACHE: dict = {}


def simulate(effect: dict | None, duration: float, noise: bool = True, scenario: str = "sway", seed: int = 0):
    key = (repr(effect), duration, noise, scenario, seed)
    if key not in _CACHE:
        sc = Scenario.load(scenario)
        sc.duration, sc.seed = duration, seed
        sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
        sc.effects = [effect] if effect else []
        _CACHE[key] = Simulator(sc, noise=noise).run()
    return _CACHE[key]


def truth_state(rec):
    tr = rec.truth
    R = np.ascontiguousarray(tr.R)
    q = np.ascontiguousarray(np.concatenate([tr.t, tr.w, tr.v, tr.dw, tr.a], axis=1))
    return R, q


def imu_prediction(prob, R, q):
    n = len(R)
    y, J = np.empty((n, 6)), np.empty((n, 6, 18))
    core.imu_all(R, q, np.zeros((n, 6)), prob.imu_R, prob.imu_p, prob.imu_v, prob.imu_a, prob.imu_w, prob.g, y, J)
    return y


def test_registered():
    for name in NEW:
        eff = make_effect(name)
        assert name in EFFECTS and eff.name == name and len(eff.labels) == eff.dim
        assert len(eff.excites) == eff.dim and eff.hint


@pytest.fixture(scope="module")
def short():
    rec = simulate(None, 0.3)
    return rec, Problem.build(rec, ModelConfig.from_recording(rec))


def test_imu_mounting_is_the_prediction_in_turned_axes(short):
    """``y + term`` equals eq. 26-28 evaluated with the IMU frame ``imu_R exp(delta)``."""
    rec, prob = short
    rng = np.random.default_rng(1)
    R, q = truth_state(rec)
    steps = np.arange(20, 30)
    q = q[steps] + rng.normal(0.0, 0.1, (len(steps), 15))
    R = R[steps]
    eff = make_effect("imu-mounting")
    for delta in (np.array([0.02, -0.01, 0.05]), np.array([-0.08, 0.03, 0.0])):
        e = np.tile(delta, (len(steps), 1))
        dr = eff.residual_terms("imu", prob, steps, R, q, None, e)[0]
        for j, k in enumerate(steps):
            nominal = physics.ImuPlacement(prob.imu_R[k], prob.imu_p[k], prob.imu_v[k], prob.imu_a[k], prob.imu_w[k])
            turned = physics.ImuPlacement(prob.imu_R[k] @ so3.exp(delta), prob.imu_p[k], prob.imu_v[k],
                                          prob.imu_a[k], prob.imu_w[k])
            args = (R[j], q[j, 0:3], q[j, 3:6], q[j, 6:9], q[j, 9:12], q[j, 12:15])
            want = physics.imu_readings(*args, turned, prob.g) - physics.imu_readings(*args, nominal, prob.g)
            np.testing.assert_allclose(dr[j], want, atol=1e-12)


def test_mass_scale_is_the_wrench_of_scaled_inputs(short):
    """``term`` equals the required wrench with ``m, I, dI, sigma, dsigma`` times ``1 + kappa`` minus the nominal."""
    rec, prob = short
    rng = np.random.default_rng(2)
    R, q = truth_state(rec)
    steps = np.arange(20, 30)
    q = q[steps] + rng.normal(0.0, 0.1, (len(steps), 15))
    R = R[steps]
    kappa = 0.13
    dr = make_effect("mass-scale").residual_terms("newton_euler", prob, steps, R, q, None,
                                                  np.full((len(steps), 1), kappa))[0]
    s = 1.0 + kappa
    for j, k in enumerate(steps):
        inp = physics.Inputs(rec.mass, prob.com[k], prob.com_vel[k], prob.com_acc[k], prob.inertia[k],
                             prob.inertia_dot[k], prob.sigma_l[k], prob.sigma_dot[k])
        big = physics.Inputs(rec.mass * s, prob.com[k], prob.com_vel[k], prob.com_acc[k], prob.inertia[k] * s,
                             prob.inertia_dot[k] * s, prob.sigma_l[k] * s, prob.sigma_dot[k] * s)
        args = (R[j], q[j, 0:3], q[j, 3:6], q[j, 6:9], q[j, 9:12], q[j, 12:15])
        want = physics.required_wrench(*args, big, prob.g) - physics.required_wrench(*args, inp, prob.g)
        np.testing.assert_allclose(dr[j], want, rtol=1e-10, atol=1e-9)


def _residual_at_truth(name, rec):
    """(nominal residual, residual with the term at the true value) of the family ``name`` acts on,
    at the true states, per axis RMS (0.1 s left out at each end)."""
    prob = Problem.build(rec, ModelConfig.from_recording(rec))
    R, q = truth_state(rec)
    n = rec.n
    steps = np.arange(n)
    eff = make_effect(name)
    value = np.tile(np.asarray(TWIN[name][1], dtype=float), (n, 1))
    if name == "mass-scale":
        r, J = np.empty((n, 6)), np.empty((n, 6, 18))
        Wsum = np.ascontiguousarray(rec.truth.wrench.sum(axis=1))
        core.newton_euler_all(R, q, Wsum, float(rec.mass), prob.com, prob.com_vel, prob.com_acc, prob.inertia,
                              prob.inertia_dot, prob.sigma_l, prob.sigma_dot, prob.g, r, J)
        dr = eff.residual_terms("newton_euler", prob, steps, R, q, None, value)[0]
    else:
        r = imu_prediction(prob, R, q) - prob.y_imu
        dr = eff.residual_terms("imu", prob, steps, R, q, None, value)[0]
    keep = slice(20, n - 20)
    rms = lambda x: np.sqrt(np.mean(x[keep] ** 2, axis=0))  # noqa: E731
    return rms(r), rms(r + dr)


@pytest.mark.parametrize("name", ["imu-mounting", "mass-scale"])
def test_twin_is_the_term_at_the_truth(name):
    """The simulator turns its IMU frame (scales its bodies) in pinocchio's model; at the true states
    and wrenches the term at the true value removes the nominal residual entirely (noise-free
    sway, 1.5 s): measured 0 to the last digits; the bound is 1e-9 of the nominal residual, the
    integrator's tolerance far below it."""
    rec = simulate(TWIN[name][0], 1.5, noise=False)
    before, after = _residual_at_truth(name, rec)
    big = np.argmax(before)
    assert before[big] > (0.1 if name == "imu-mounting" else 30.0), before  # m/s^2 or N: the effect is there
    assert np.all(after <= 1e-9 * before.max()), (before, after)


@pytest.mark.parametrize("delay", [0.02, 0.0123])
def test_time_offset_twin_is_an_exact_delay(delay):
    """The simulator's late IMU is the sensor's reading ``tau`` earlier (its samples through a
    cubic spline); at the true states the effect's term at the true offset leaves of the delay's
    residual only what a band-limited shift and the spline disagree on: nothing at whole samples
    (20 ms, four samples), little between them.  Noise-free sway, 2 s; 0.1 s left out at each end
    (the simulator holds the first reading before the start, the term reads the series' return)."""
    rec = simulate({"type": "time-offset", "delay": delay}, 2.0, noise=False)
    prob = Problem.build(rec, ModelConfig.from_recording(rec))
    R, q = truth_state(rec)
    r = imu_prediction(prob, R, q) - prob.y_imu
    eff = make_effect("time-offset")
    dr = eff.residual_terms("imu", prob, np.arange(rec.n), R, q, None, np.full((rec.n, 1), delay))[0]
    keep = slice(20, rec.n - 20)
    rms = lambda x: np.sqrt(np.mean(x[keep] ** 2, axis=0))  # noqa: E731
    before, after = rms(r), rms(r + dr)
    # the delay shows on the gyro x (roll rate) and the accelerometer y (sideways sway)
    assert before[0] > 1e-3 * delay / 0.02 and before[4] > 1e-2 * delay / 0.02, before
    # measured: at most 1.2e-11 of the residual left at 20 ms (rounding), 0.0030 at 12.3 ms (the
    # accelerometer x; the first-order term left 0.04-0.06); margin 2x (at whole samples: 1e-9, rounding)
    assert np.all(after <= (1e-9 if delay == 0.02 else 0.0060) * np.maximum(before, 1e-9)), after / before


# ----------------------------------------------------------------------------------------------
# The diagnosis: the twin hidden, then none
# ----------------------------------------------------------------------------------------------

# Per effect: the candidates it is ranked among (itself and those it resembles), whether the F/T
# sensors are fused, and the RMSE ratios after / before adding the selected effect, as measured
# (3 s sway, seed 0); the margin is 10 % of the ratio (where the fit stops moves it).
DIAGNOSED = {
    "imu-mounting": (["imu-mounting", "accel-bias", "com-offset", "gyro-bias"], False,
                     {"force_N": 0.200, "cop_m": 0.0851, "rotation_rad": 0.0736}),
    "time-offset": (["time-offset", "gyro-bias", "accel-bias", "imu-mounting"], False,
                    {"force_N": 0.801, "cop_m": 0.427, "rotation_rad": 0.449}),
    "mass-scale": (["mass-scale", "stiffness", "com-offset"], True,
                   {"force_N": 0.0670, "cop_m": 0.383}),
}


def _model(rec, ft: bool):
    import dataclasses

    model = ModelConfig.from_recording(rec)
    return dataclasses.replace(model, use_ft=True) if ft else model


@pytest.mark.slow
@pytest.mark.parametrize("name", NEW)
def test_diagnosis_finds_the_hidden_twin(name):
    """The twin hidden in a 3 s sway (the scenarios ``sway-<name>``): the effect ranked first and
    selected, its estimate at the truth within 4 of its sigmas, and the errors against the truth
    falling as measured."""
    from flexforce.compare.diagnostics.run import diagnose

    candidates, ft, ratios = DIAGNOSED[name]
    sc = Scenario.load(f"sway-{name}")  # the built-in scenario of the twin: this test's recording
    assert sc.effects == [TWIN[name][0]] and sc.duration == 3.0 and sc.seed == 0
    assert sc.imu_noise == {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    rec = Simulator(sc).run()
    d = diagnose(rec, _model(rec, ft), candidates=candidates, add=["auto"], ekf=False, identify=False)
    first = d.ranking[0]
    assert first.effect == name and first.significant and d.selected[0] == name, d.ranking_table()
    v = np.asarray(first.parameters["value"], dtype=float)
    s = np.asarray(first.parameters["std"], dtype=float)
    truth = np.asarray(TWIN[name][1], dtype=float) + (1.0 if name == "mass-scale" else 0.0)
    # the time offset: measured 18.6 +- 3.3 ms for the true 20 ms (the first-order term it replaced:
    # 14.0 +- 3.2)
    assert np.all(np.abs(v - truth) < 4 * s), (v, s)
    for key, measured in ratios.items():
        ratio = d.after.rmse[key] / d.before.rmse[key]
        assert ratio < 1.0 and ratio <= measured * 1.1, (key, ratio)


@pytest.mark.slow
@pytest.mark.parametrize("ft", [False, True])
def test_diagnosis_of_a_clean_recording_finds_none_of_them(ft):
    """No hidden effect (3 s sway): none of the three is significant (F/T fused or not)."""
    from flexforce.compare.diagnostics.run import diagnose

    rec = simulate(None, 3.0)
    d = diagnose(rec, _model(rec, ft), candidates=list(NEW), add=(), ekf=False, identify=False)
    # measured: no score test passes (smallest p 0.23 without F/T, mass-scale; 0.52 with); the time
    # offset, refitted whatever its test, gains 2 Delta E = 0.0 without F/T and 0.4 with
    assert not d.selected and not any(c.significant for c in d.ranking), d.ranking_table()


@pytest.mark.parametrize("name, good, bad, words", [
    ("imu-mounting", [0.02, -0.01, 0.05], [0.08, 0.0, 0.08], "beyond 100 mrad"),
    ("time-offset", [-0.03], [0.08], "beyond 0.05 s"),
    ("mass-scale", [1.3], [2.4], "outside the plausible 0.5-2"),
])
def test_each_new_effect_says_when_its_estimate_is_implausible(name, good, bad, words):
    eff = make_effect(name)
    assert eff.plausible({"value": good}) is None
    reason = eff.plausible({"value": bad})
    assert reason is not None and words in reason, reason


def test_imu_mounting_in_the_fixed_lag_smoother():
    """The mounting rotation learnt online (window fixed-lag smoother, 0.5 s lag) on a 2 s sway with
    the twin hidden: the tilt components at the truth within 4 of their sigmas (measured
    x = 0.0205 +- 0.0004, y = -0.0105 +- 0.0004 rad; the rotation about the vertical is not seen in 2 s)."""
    import dataclasses

    from flexforce.smoother import run_fixed_lag

    rec = simulate(TWIN["imu-mounting"][0], 2.0)
    cfg = dataclasses.replace(ModelConfig.from_recording(rec), effects=(make_effect("imu-mounting"),))
    rep = run_fixed_lag(rec, cfg, lag=0.5).effects["imu-mounting"]
    v, s = np.asarray(rep["value"]), np.asarray(rep["std"])
    truth = np.asarray(TWIN["imu-mounting"][1])
    assert np.all(np.abs(v[:2] - truth[:2]) < 4 * s[:2]), (v, s)
