"""The marginal likelihood (flexforce.smoother.evidence): its block log-determinant against a
dense one, and what it changes on data with no hidden effect (the joint optimum's bias)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import occam_gradient_skips

from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.factors.effects import make_effect
from flexforce.factors.model import ModelConfig
from flexforce.smoother import Problem, fit, solvers
from flexforce.smoother.batch import initial_trajectory
from flexforce.smoother.evidence import log_dets
from flexforce.smoother.linearize import global_columns, linearize


def block_tridiagonal(n, d, seed):
    rng = np.random.default_rng(seed)
    L = np.zeros((n * d, n * d))
    for k in range(n):
        T = np.tril(rng.normal(size=(d, d)))
        T[np.diag_indices(d)] = np.abs(T[np.diag_indices(d)]) + 1.0
        L[k * d:(k + 1) * d, k * d:(k + 1) * d] = T
        if k:
            L[k * d:(k + 1) * d, (k - 1) * d:k * d] = 0.5 * rng.normal(size=(d, d))
    H = L @ L.T
    D = np.array([H[k * d:(k + 1) * d, k * d:(k + 1) * d] for k in range(n)])
    B = np.array([H[k * d:(k + 1) * d, (k + 1) * d:(k + 2) * d] for k in range(n - 1)]).reshape(n - 1, d, d)
    return H, D, B


@pytest.mark.parametrize("n,d", [(1, 3), (12, 4), (30, 6)])
def test_block_logdet_matches_dense(n, d):
    H, D, B = block_tridiagonal(n, d, seed=n)
    sign, ref = np.linalg.slogdet(H)
    assert sign > 0
    assert solvers.block_tridiag_logdet(D, B) == pytest.approx(ref, rel=1e-10, abs=1e-9)


def test_block_logdet_refuses_an_indefinite_matrix():
    _, D, B = block_tridiagonal(5, 3, seed=1)
    D = D.copy()
    D[3] -= 100.0 * np.eye(3)
    with pytest.raises(np.linalg.LinAlgError):
        solvers.block_tridiag_logdet(D, B)


@pytest.fixture(scope="module")
def null_sway():
    sc = Scenario.load("sway")
    sc.duration = 3.0
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    sc.effects = []
    return Simulator(sc).run()


def test_log_dets_posterior_exceeds_prior(null_sway):
    """The IMU adds information: ln det H_post > ln det H_model, on the states of a real problem."""
    rec = null_sway.slice(0, 60)
    model = ModelConfig.from_recording(rec)
    prob = Problem.build(rec, dataclasses.replace(model, effects=(make_effect("stiffness"),)))
    lin = linearize(prob, initial_trajectory(prob))
    post, prior = log_dets(prob, lin, global_columns(prob))
    assert np.isfinite(post) and np.isfinite(prior) and post > prior


def test_marginal_likelihood_removes_the_damping_bias(null_sway):
    """No hidden effect: the joint optimum drove the damping scale to 0.07 (truth 1) with a
    likelihood-ratio gain of 60; the marginal keeps it within its uncertainty of 1."""
    model = ModelConfig.from_recording(null_sway)
    est, stats = fit(null_sway, dataclasses.replace(model, effects=(make_effect("stiffness"),)))
    rep = est.effects["stiffness"]
    v, s = np.array(rep["value"]), np.array(rep["std"])
    assert abs(v[0] - 1.0) < 4 * s[0] and abs(v[1] - 1.0) < 4 * s[1], (v, s)
    _, nominal = fit(null_sway, model)
    gain = 2 * (nominal.cost_evidence - stats.cost_evidence)
    assert gain < 2 * np.log(stats.n_residuals)  # below the BIC penalty of 2 dof


def test_qr_factor_and_its_selected_inverse_match_dense():
    """The SRIF factor R of stacked chain rows gives R^T R = J^T J, and its selected inverse the
    diagonal and lag-one blocks of (J^T J)^-1."""
    from flexforce.smoother.evidence import _factor_selected_inverse, _qr_factor

    rng = np.random.default_rng(4)
    n, d, ru, rb = 7, 4, 3, 5
    Ju, J0, J1, Jf = (rng.normal(size=(n, ru, d)), rng.normal(size=(n - 1, rb, d)), rng.normal(size=(n - 1, rb, d)),
                      rng.normal(size=(2, d)))
    J = np.zeros((n * ru + (n - 1) * rb + 2, n * d))
    row = 0
    for k in range(n):
        J[row:row + ru, k * d:(k + 1) * d] = Ju[k]
        row += ru
    for k in range(n - 1):
        J[row:row + rb, k * d:(k + 1) * d] = J0[k]
        J[row:row + rb, (k + 1) * d:(k + 2) * d] = J1[k]
        row += rb
    J[row:, :d] = Jf
    H = J.T @ J
    Rd, Ru = np.empty((n, d, d)), np.empty((n - 1, d, d))
    ld = _qr_factor(Ju, J0, J1, Jf, Rd, Ru)
    assert ld == pytest.approx(np.linalg.slogdet(H)[1], rel=1e-12)
    Sigma = np.linalg.inv(H)
    P, Pc = _factor_selected_inverse(Rd, Ru)
    for k in range(n):
        np.testing.assert_allclose(P[k], Sigma[k * d:(k + 1) * d, k * d:(k + 1) * d], rtol=1e-9, atol=1e-12)
    for k in range(n - 1):
        np.testing.assert_allclose(Pc[k], Sigma[k * d:(k + 1) * d, (k + 1) * d:(k + 2) * d], rtol=1e-9, atol=1e-12)


def _occam_difference(prob, traj, cidx, j, h):
    """Central difference of :func:`occam` in the global parameter ``j``, with steps of ``h``."""
    from flexforce.smoother.evidence import occam

    off = prob.state_dim - prob.effect_dim
    vals = []
    for sgn in (1.0, -1.0):
        e = traj.e.copy()
        e[:, cidx[j] - off] += sgn * h
        vals.append(occam(prob, linearize(prob, type(traj)(traj.R, traj.q, traj.W, e)), cidx))
    return (vals[0] - vals[1]) / (2 * h)


def test_occam_gradient_is_the_derivative_of_the_occam_term(null_sway):
    """The trace form of the Occam term's gradient (selected inverses contracted with J^T dJ)
    against central differences of the log-determinants themselves, at a trajectory that is not
    an optimum: an additive bias's gradient is exactly 0 (its Jacobian does not move); the
    stiffness scales' and CoM offset's agree with differences of steps of 1e-2 prior sigma
    (measured: within 2.2e-5 relative; asserted 5e-4.  Smaller steps leave the log-determinants'
    difference to rounding at this starting point: 15.137, 15.135, 15.102, 15.074 for one of its
    two parts at 1e-2 .. 1e-5, where the trace form gives 15.136 at every step)."""
    from flexforce.smoother.evidence import global_prior_sigma, occam, occam_gradient

    rec = null_sway.slice(0, 120)
    model = ModelConfig.from_recording(rec)
    effects = (make_effect("gyro-bias"), make_effect("stiffness"), make_effect("com-offset"))
    prob = Problem.build(rec, dataclasses.replace(model, effects=effects))
    traj = initial_trajectory(prob)
    cidx = np.asarray(global_columns(prob), dtype=int)
    grad = occam_gradient(prob, traj, cidx)
    assert np.all(grad[:3] == 0.0)
    sig = global_prior_sigma(prob)
    for j in range(3, cidx.size):
        ref = _occam_difference(prob, traj, cidx, j, 1e-2 * sig[j])
        assert grad[j] == pytest.approx(ref, rel=5e-4), (j, grad[j], ref)
    # with the factors the Occam term formed at the same linearisation (the smoother's outer steps)
    lin = linearize(prob, traj)
    keep: dict = {}
    pen = occam(prob, lin, cidx, keep)
    assert pen == occam(prob, lin, cidx) and keep["lin"] is lin
    np.testing.assert_allclose(occam_gradient(prob, traj, cidx, lin=lin, keep=keep), grad, rtol=1e-12, atol=0.0)
    # a keep formed at another linearisation is not used
    other = linearize(prob, type(traj)(traj.R, traj.q, traj.W, traj.e + 1e-3))
    np.testing.assert_allclose(occam_gradient(prob, traj, cidx, lin=lin, keep={**keep, "lin": other}), grad,
                               rtol=1e-12, atol=0.0)


@pytest.fixture(scope="module")
def pushed_sway():
    """A 3 s sway with a 40 N push the nominal model does not have: its Newton-Euler residuals
    leave the Huber loss's quadratic range during the push."""
    sc = Scenario.load("sway")
    sc.duration = 3.0
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    sc.effects = [{"type": "external-wrench", "link": "@base", "force": [40.0, 0.0, 0.0], "start": 1.5,
                   "duration": 0.4}]
    return Simulator(sc).run()


def _huber_active(prob, traj):
    """A trajectory with the wrenches of 20 steps pushed 300 N off: the Huber weights of their
    Newton-Euler rows fall below 1."""
    W = traj.W.copy()
    W[40:60, :, 0] += 300.0 * prob.active[40:60]
    return type(traj)(traj.R, traj.q, W, traj.e)


def test_trajectory_prior_normaliser_is_that_of_the_plain_rows(null_sway):
    """The trajectory prior's normaliser is the Jacobian determinant of the change of variables
    from the states to the model residuals, whatever their density: with the Huber loss active,
    ``ln det H_model`` is the plain rows' (exactly), ``ln det H_post`` the reweighted ones'
    (lower: a down-weighted row informs less)."""
    rec = null_sway.slice(0, 120)
    model = ModelConfig.from_recording(rec)
    prob = Problem.build(rec, dataclasses.replace(model, effects=(make_effect("stiffness"),)))
    traj = _huber_active(prob, initial_trajectory(prob))
    lin = linearize(prob, traj)
    assert lin.ne_weights is not None and np.sum(lin.ne_weights < 1.0) >= 10
    plain = linearize(prob, traj, robust=False)
    assert plain.ne_weights is None
    cidx = global_columns(prob)
    post, prior = log_dets(prob, lin, cidx)
    post_p, prior_p = log_dets(prob, plain, cidx)
    assert prior == pytest.approx(prior_p, rel=1e-12)
    assert post < post_p - 1.0


def test_occam_gradient_with_the_huber_loss_active(null_sway):
    """The Occam term's gradient where the Huber weights are below 1 (they move with the
    parameter: the posterior's Jacobian with them, the prior's without) against central
    differences of :func:`occam` (relative 5e-4, as without the loss)."""
    from flexforce.smoother.evidence import global_prior_sigma, occam_gradient

    rec = null_sway.slice(0, 120)
    model = ModelConfig.from_recording(rec)
    prob = Problem.build(rec, dataclasses.replace(model, effects=(make_effect("stiffness"), make_effect("com-offset"))))
    traj = _huber_active(prob, initial_trajectory(prob))
    cidx = np.asarray(global_columns(prob), dtype=int)
    grad = occam_gradient(prob, traj, cidx)
    sig = global_prior_sigma(prob)
    for j in range(cidx.size):
        ref = _occam_difference(prob, traj, cidx, j, 1e-2 * sig[j])
        assert grad[j] == pytest.approx(ref, rel=5e-4, abs=1e-6 * max(1.0, abs(ref))), (j, grad[j], ref)


def test_evidence_is_the_objective_without_the_parameters_prior(pushed_sway):
    """The evidence's data term is the objective's robust one: on a push the model does not have
    (Huber active), ``cost_evidence`` is the optimised objective (robust cost + Occam term) less
    ``theta``'s own prior, and its data term lies below the plain residuals' cost."""
    from flexforce.smoother.evidence import occam, theta_prior_cost

    model = ModelConfig.from_recording(pushed_sway)
    model = dataclasses.replace(model, effects=(make_effect("stiffness"),))
    est, stats = fit(pushed_sway, model)
    prob = Problem.build(pushed_sway, model)
    lin = linearize(prob, stats.trajectory)
    assert lin.ne_weights is not None and np.any(lin.ne_weights < 1.0)
    cidx = global_columns(prob)
    objective = lin.cost + occam(prob, lin, cidx)
    assert stats.cost_evidence == pytest.approx(objective - theta_prior_cost(prob, lin), rel=1e-9)
    assert stats.cost_data_robust < stats.cost_data


def test_each_effect_names_the_families_it_enters(null_sway):
    """``acts_on`` of every catalogue effect that declares it is exactly the set of families whose
    ``residual_terms`` it returns (F/T fused, so that ``ft`` is asked too): the Occam gradient
    re-evaluates only those, so a missing one would drop a term of it."""
    from flexforce.factors.effects import EFFECTS

    rec = null_sway.slice(0, 40)
    model = dataclasses.replace(ModelConfig.from_recording(rec), use_ft=True)
    prob = Problem.build(rec, model)
    traj = initial_trajectory(prob)
    steps = np.arange(prob.n)
    declared = 0
    for name in EFFECTS:
        eff = make_effect(name)
        acts = getattr(eff, "acts_on", None)
        if acts is None:
            continue
        declared += 1
        e = np.full((prob.n, int(eff.dim)), 0.01)
        entered = {fam for fam in ("newton_euler", "contact", "imu", "ft")
                   if eff.residual_terms(fam, prob, steps, traj.R, traj.q, traj.W, e) is not None}
        assert set(acts) == entered, (name, acts, entered)
    assert declared >= 10


def test_a_linearisation_of_some_families_is_theirs_in_the_full_one(null_sway):
    """``linearize(families=...)`` evaluates those groups exactly as the full linearisation does
    (the same arrays), leaves the others out and gives no cost; an unknown group is refused."""
    rec = null_sway.slice(0, 60)
    model = ModelConfig.from_recording(rec)
    prob = Problem.build(rec, dataclasses.replace(model, effects=(make_effect("com-offset"),)))
    traj = _huber_active(prob, initial_trajectory(prob))
    full = linearize(prob, traj)
    part = linearize(prob, traj, families=frozenset({"newton_euler", "effects"}))
    assert set(part.unary) == {"newton_euler", "effect_prior/com-offset"}
    assert set(part.binary) == {"effect_walk/com-offset"}
    for key, (r, J) in part.unary.items():
        assert np.array_equal(r, full.unary[key][0]) and np.array_equal(J, full.unary[key][1])
    assert part.ne_weights is not None and np.array_equal(part.ne_weights, full.ne_weights)
    assert np.isnan(part.cost)
    imu = linearize(prob, traj, families=frozenset({"imu"}))
    assert set(imu.unary) == {"imu"} and not imu.binary
    with pytest.raises(ValueError, match="unknown family groups"):
        linearize(prob, traj, families=frozenset({"gps"}))


def test_occam_gradient_evaluates_only_the_families_a_parameter_enters(null_sway, monkeypatch):
    """The gradient formed from the families each effect names (``acts_on``) is the one formed
    from every family (to rounding: the same numbers), for effects on each family: the gyro bias
    and the IMU time offset (IMU), the stiffness (contact laws), the CoM offset (Newton-Euler)."""
    from flexforce.smoother import evidence

    rec = null_sway.slice(0, 120)
    model = ModelConfig.from_recording(rec)
    effects = (make_effect("gyro-bias"), make_effect("time-offset"), make_effect("stiffness"),
               make_effect("com-offset"))
    prob = Problem.build(rec, dataclasses.replace(model, effects=effects))
    traj = _huber_active(prob, initial_trajectory(prob))
    cidx = np.asarray(global_columns(prob), dtype=int)
    groups = evidence._varied_groups(prob)
    assert groups[0] == frozenset({"imu"}) and groups[-1] == frozenset({"newton_euler"})
    grad = evidence.occam_gradient(prob, traj, cidx)
    monkeypatch.setattr(evidence, "_varied_groups", lambda p: [None] * sum(p.effect_dims))
    every = evidence.occam_gradient(prob, traj, cidx)
    np.testing.assert_allclose(grad, every, rtol=1e-12, atol=1e-14)
    assert np.count_nonzero(every) >= 3


def test_occam_gradient_skips_an_additive_bias_only_where_no_weight_can_move(null_sway, monkeypatch):
    """An IMU bias (``additive``) moves no Jacobian while every IMU sample keeps its full robust
    weight short of the threshold: its columns are skipped, and the gradient is the one formed with
    the differences for every column (the same numbers; the biases' are 0, the stiffness's not).
    With accelerometer samples in the log-tail loss's tail their weights move with the bias: no
    column is skipped, and the accelerometer bias's gradient is not 0."""
    rec = null_sway.slice(0, 120)
    model = ModelConfig.from_recording(rec)
    effects = (make_effect("accel-bias"), make_effect("gyro-bias"), make_effect("stiffness"))
    prob = Problem.build(rec, dataclasses.replace(model, effects=effects))
    assert prob.sigmas.imu_robust == "log-tail"
    traj = initial_trajectory(prob)
    held, grad, every = occam_gradient_skips(prob, traj, monkeypatch)
    assert held == [True] * 6 + [False] * 2
    np.testing.assert_array_equal(grad, every)
    assert np.all(every[:6] == 0.0) and np.all(every[6:] != 0.0)

    q = traj.q.copy()
    q[40:45, 12:15] += 50.0  # the accelerations of five steps 50 m/s^2 off: far in the tail
    tail = type(traj)(traj.R, q, traj.W, traj.e)
    assert np.any(linearize(prob, tail).weights["imu"][:, 1] < 1.0)
    held, moved, _ = occam_gradient_skips(prob, tail, monkeypatch)
    assert held == [False] * 8
    assert np.all(moved[:3] != 0.0)


def test_an_effects_level_and_walk_rows_are_formed_once_and_follow_the_window(null_sway):
    """An effect's prior level and random-walk rows have the same Jacobians at every point: the
    second linearisation of a problem shares the first one's arrays (its residuals are its own),
    equal to those of a problem formed afresh; a window of steps further on (the fixed-lag
    smoother's ``k0``) gets rows of its own length with the walk's sigma of its steps."""
    from flexforce.smoother.linearize import Trajectory, walk_sigma

    rec = null_sway.slice(0, 60)
    model = dataclasses.replace(ModelConfig.from_recording(rec),
                                effects=(make_effect("external-wrench"), make_effect("gyro-bias")))
    prob = Problem.build(rec, model)
    traj = initial_trajectory(prob)
    first = linearize(prob, traj)
    moved = Trajectory(traj.R, traj.q, traj.W, traj.e + 0.01)
    second = linearize(prob, moved)
    fresh = linearize(Problem.build(rec, model), moved)
    for key in ("effect_walk/external-wrench", "effect_walk/gyro-bias"):
        assert second.binary[key][1] is first.binary[key][1] and second.binary[key][2] is first.binary[key][2]
        for a, b in zip(second.binary[key], fresh.binary[key]):
            np.testing.assert_array_equal(a, b)
    key = "effect_level/external-wrench"
    assert second.unary[key][1] is first.unary[key][1]
    for a, b in zip(second.unary[key], fresh.unary[key]):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(second.unary[key][0], first.unary[key][0])

    k0, m = 20, 15
    part = Trajectory(traj.R[k0:k0 + m], traj.q[k0:k0 + m], traj.W[k0:k0 + m], traj.e[k0:k0 + m])
    window = linearize(prob, part, k0=k0)
    eff = prob.effects[0]
    r, J0, J1 = window.binary["effect_walk/external-wrench"]
    assert J0.shape[0] == m - 1 and window.unary[key][1].shape[0] == m
    cols = slice(prob.state_dim - prob.effect_dim, prob.state_dim - prob.effect_dim + eff.dim)
    rw = walk_sigma(eff, prob)[k0:k0 + m - 1]
    np.testing.assert_array_equal(J1[:, :, cols], np.eye(eff.dim)[None] / rw[:, :, None])
    assert linearize(prob, traj).binary["effect_walk/external-wrench"][1].shape[0] == prob.n - 1
