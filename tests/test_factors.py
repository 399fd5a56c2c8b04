"""Tests of the factor families: closed forms of the compiled kernels, and every gtsam factor's
analytic Jacobians against numerical derivatives taken through ``Values.retract``.

The numerical check is a port of GTSAM's ``factorTesting.h`` (the Python wheel lacks it): for
each key and each tangent direction, retract the values by +-h along it, linearise the factor
there and difference its whitened right-hand side; the result must match the whitened Jacobian
of ``factor.linearize`` at the unperturbed values.  States are sampled on purpose near identity
(1e-7 rad), at large deflections, at zero error, and with a contact just coming into force.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from flexforce.factors import core, so3
from flexforce.factors import gtsam_factors as gf
from flexforce.factors import physics as ph
from flexforce.smoother import solvers

G = ph.GRAVITY


# ----------------------------------------------------------------------------------------------
# factorTesting, ported
# ----------------------------------------------------------------------------------------------


def _dim(values, key):
    try:
        values.atPose3(key)
        return 6
    except RuntimeError:
        return values.atVector(key).shape[0]


def numerical_factor_jacobians(factor, values, h=1e-6):
    """Central differences of the whitened error through ``Values.retract``, per key."""
    keys = list(factor.keys())
    dims = {key: _dim(values, key) for key in keys}

    def whitened(vals):
        A, b = factor.linearize(vals).jacobian()
        return -b

    out = []
    for key in keys:
        J = np.empty((factor.dim(), dims[key]))
        for j in range(dims[key]):
            deltas = []
            for sign in (1.0, -1.0):
                delta = gtsam.VectorValues()
                for other in keys:
                    d = np.zeros(dims[other])
                    if other == key:
                        d[j] = sign * h
                    delta.insert(other, d)
                deltas.append(whitened(values.retract(delta)))
            J[:, j] = (deltas[0] - deltas[1]) / (2 * h)
        out.append(J)
    return out


def check_factor_jacobians(factor, values, h=1e-6, rtol=1e-5, atol=1e-6):
    """Assert the analytic (whitened) Jacobian equals the numerical one, block by block."""
    A, _ = factor.linearize(values).jacobian()
    numeric = numerical_factor_jacobians(factor, values, h)
    col = 0
    for key, Jn in zip(factor.keys(), numeric):
        Ja = A[:, col:col + Jn.shape[1]]
        col += Jn.shape[1]
        scale = max(1.0, float(np.abs(Jn).max()))
        np.testing.assert_allclose(Ja, Jn, rtol=rtol, atol=atol * scale,
                                   err_msg=f"Jacobian block of key {gtsam.DefaultKeyFormatter(key)}")


# ----------------------------------------------------------------------------------------------
# States and inputs
# ----------------------------------------------------------------------------------------------


def random_state(rng, angle=0.05, near_identity=False):
    phi = rng.normal(size=3)
    phi *= (1e-7 if near_identity else angle) / np.linalg.norm(phi)
    R = so3.exp(phi)
    q = np.concatenate([rng.normal(size=3) * (1e-7 if near_identity else 0.01), rng.normal(size=3) * 0.3,
                        rng.normal(size=3) * 0.1, rng.normal(size=3) * 2.0, rng.normal(size=3)])
    return R, q


def inputs(rng):
    I = np.diag([23.0, 23.3, 0.8]) + 0.05 * np.ones((3, 3))
    return ph.Inputs(40.5, np.array([0.02, 0.0, 0.66]) + 0.01 * rng.normal(size=3), 0.05 * rng.normal(size=3),
                     0.5 * rng.normal(size=3), I, 0.1 * rng.normal(size=(3, 3)), 0.3 * rng.normal(size=3),
                     rng.normal(size=3))


def imu_placement(rng):
    return ph.ImuPlacement(so3.exp(np.array([0.1, -0.2, 0.3])), np.array([0.05, 0.01, 0.68]),
                           0.05 * rng.normal(size=3), 0.5 * rng.normal(size=3), 0.1 * rng.normal(size=3))


ISO = ph.ContactParams.make(28000.0, 420.0, 450.0, 8.0)
ANISO = ph.ContactParams.make([2.0e4, 3.0e4, 4.0e4], [300.0, 400.0, 500.0], [400.0, 500.0, 300.0], [6.0, 8.0, 9.0],
                              beta_f=50.0, beta_t=5.0)
CONTACTS = [(np.array([0.0, 0.096, 0.0]), so3.exp(np.array([0.0, 0.0, 0.1]))),
            (np.array([0.0, -0.096, 0.0]), so3.exp(np.array([0.0, 0.0, -0.1])))]


def values_of(k, R, q, W=None, contacts=(), k1=None, R1=None, q1=None):
    values = gtsam.Values()
    gf.insert_state(values, k, R, q, W, contacts)
    if k1 is not None:
        gf.insert_state(values, k1, R1, q1)
    return values


# ----------------------------------------------------------------------------------------------
# Core kernels with closed-form answers (the laws themselves are checked in test_physics.py
# against independent references and numerical derivatives)
# ----------------------------------------------------------------------------------------------


def test_integration_is_exact_for_constant_jerk():
    """Closed form: rotation about a fixed axis with a cubic angle and a cubic translation satisfy
    the integration residual exactly (acceleration linear in time over the step)."""
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    c = np.array([0.01, 0.2, -0.7, 3.0])  # angle(s) = c0 + c1 s + c2 s^2 + c3 s^3
    p = np.array([[0.001, -0.002, 0.003], [0.05, 0.01, -0.02], [0.3, -0.1, 0.2], [-2.0, 1.0, 0.5]])
    R0 = so3.exp(np.array([0.02, 0.01, -0.03]))

    def at(s):
        ang = c[0] + c[1] * s + c[2] * s**2 + c[3] * s**3
        dang = c[1] + 2 * c[2] * s + 3 * c[3] * s**2
        ddang = 2 * c[2] + 6 * c[3] * s
        t = p[0] + p[1] * s + p[2] * s**2 + p[3] * s**3
        v = p[1] + 2 * p[2] * s + 3 * p[3] * s**2
        a = 2 * p[2] + 6 * p[3] * s
        return so3.exp(ang * axis) @ R0, np.concatenate([t, dang * axis, v, ddang * axis, a])

    dt = 0.005
    Ra, qa = at(0.1)
    Rb, qb = at(0.1 + dt)
    r = np.empty(12)
    J0 = np.empty((12, 18))
    J1 = np.empty((12, 18))
    core.integration(Ra, qa, Rb, qb, dt, r, J0, J1)
    np.testing.assert_allclose(r, 0.0, atol=1e-15)


def test_ft_kernel_matches_the_sensor_definition():
    """The F/T reading is the contact wrench moved to the contact point, in the contact frame."""
    rng = np.random.default_rng(4)
    R, q = random_state(rng, angle=0.2)
    p_l, R_l = CONTACTS[1]
    Wv = rng.normal(size=6) * 80
    p = R @ p_l + q[0:3]
    Rc = R @ R_l
    moved = ph.wrench_about(Wv, p)
    expected = np.concatenate([Rc.T @ moved[:3], Rc.T @ moved[3:]])
    r = np.empty(6)
    core.ft(R, q, Wv, p_l, R_l, np.zeros(6), r, np.empty((6, 18)), np.empty((6, 6)))
    np.testing.assert_allclose(r, expected, rtol=1e-12, atol=1e-10)


def test_block_tridiagonal_solver_matches_dense():
    rng = np.random.default_rng(5)
    n, d = 7, 5
    J = rng.normal(size=(3 * n * d, n * d))
    for k in range(n):  # keep only couplings between neighbours
        for j in range(n):
            if abs(k - j) > 1:
                J[:, j * d:(j + 1) * d] *= 0.0
    H = J.T @ J + np.eye(n * d)
    for k in range(n):
        for j in range(n):
            if abs(k - j) > 1:
                H[k * d:(k + 1) * d, j * d:(j + 1) * d] = 0.0
    g = rng.normal(size=n * d)
    Dm = np.array([H[k * d:(k + 1) * d, k * d:(k + 1) * d] for k in range(n)])
    B = np.array([H[k * d:(k + 1) * d, (k + 1) * d:(k + 2) * d] for k in range(n - 1)])
    x, P = solvers.block_tridiag_solve(Dm, B, g.reshape(n, d), True)
    np.testing.assert_allclose(x.ravel(), np.linalg.solve(H, g), rtol=1e-10, atol=1e-12)
    Hinv = np.linalg.inv(H)
    for k in range(n):
        np.testing.assert_allclose(P[k], Hinv[k * d:(k + 1) * d, k * d:(k + 1) * d], rtol=1e-9, atol=1e-12)


# ----------------------------------------------------------------------------------------------
# gtsam factors: Jacobians through Values.retract
# ----------------------------------------------------------------------------------------------

NOISE6 = gtsam.noiseModel.Diagonal.Sigmas(np.array([2.0, 2.0, 2.0, 0.3, 0.3, 0.3]))


def _states(rng):
    """(label, R, q): perturbed, near identity, large deflection."""
    return [("perturbed",) + random_state(rng), ("near-identity",) + random_state(rng, near_identity=True),
            ("large",) + random_state(rng, angle=0.6)]


@pytest.mark.parametrize("params", [ISO, ANISO], ids=["isotropic", "anisotropic-cubic"])
def test_contact_factor_jacobians(params):
    rng = np.random.default_rng(10)
    for label, R, q in _states(rng):
        for i, (p_l, R_l) in enumerate(CONTACTS):
            f = gf.contact_factor(NOISE6, 3, i, p_l, R_l, params)
            # zero error: W equal to the contact law
            W0 = ph.contact_wrench(R, q[0:3], q[3:6], q[6:9], p_l, R_l, params)
            for Wv in (W0, W0 + rng.normal(size=6) * 20):
                wrenches = np.zeros((2, 6))
                wrenches[i] = Wv
                values = values_of(3, R, q, wrenches, [i])
                check_factor_jacobians(f, values)
            assert f.error(values_of(3, R, q, np.array([W0, W0]), [0, 1])) < 1e-12, label


def test_contact_factor_near_contact_change():
    """A contact just coming into force: zero deflection at the contact point, tiny velocity."""
    p_l, R_l = CONTACTS[0]
    R = np.eye(3)
    q = np.zeros(15)
    q[3:6] = 1e-9
    f = gf.contact_factor(NOISE6, 0, 0, p_l, R_l, ISO)
    values = values_of(0, R, q, np.zeros((1, 6)), [0])
    check_factor_jacobians(f, values)
    assert f.error(values) < 1e-12


@pytest.mark.parametrize("params", [ISO, ANISO], ids=["isotropic", "anisotropic-cubic"])
def test_contact_factor_with_foothold_jacobians(params):
    """A world rest placement away from the local one (a foothold found at touch-down)."""
    rng = np.random.default_rng(13)
    for label, R, q in _states(rng):
        for i, (p_l, R_l) in enumerate(CONTACTS):
            p_r = R @ p_l + q[0:3] + 0.004 * rng.normal(size=3)
            R_r = so3.exp(0.05 * rng.normal(size=3)) @ R @ R_l
            f = gf.contact_factor(NOISE6, 3, i, p_l, R_l, params, p_r, R_r)
            W0 = ph.contact_wrench(R, q[0:3], q[3:6], q[6:9], p_l, R_l, params, world_p_rest=p_r, world_R_rest=R_r)
            wrenches = np.zeros((2, 6))
            wrenches[i] = W0
            values = values_of(3, R, q, wrenches, [i])
            check_factor_jacobians(f, values)
            assert f.error(values) < 1e-12, label


@pytest.mark.parametrize("contacts", [[0], [0, 1]], ids=["one-contact", "two-contacts"])
def test_newton_euler_factor_jacobians(contacts):
    rng = np.random.default_rng(11)
    for label, R, q in _states(rng):
        inp = inputs(rng)
        f = gf.newton_euler_factor(NOISE6, 5, contacts, inp.m, inp.c, inp.dc, inp.ddc, inp.I, inp.dI, inp.sigma,
                                   inp.dsigma, G)
        req = ph.required_wrench(R, q[0:3], q[3:6], q[6:9], q[9:12], q[12:15], inp, G)
        wrenches = np.zeros((2, 6))
        wrenches[contacts[0]] = req  # zero error: the first contact carries the whole wrench
        values = values_of(5, R, q, wrenches, contacts)
        assert f.error(values) < 1e-16, label
        check_factor_jacobians(f, values)
        wrenches = rng.normal(size=(2, 6)) * 100
        check_factor_jacobians(f, values_of(5, R, q, wrenches, contacts))


def test_newton_euler_factor_near_contact_change():
    """Second contact appearing with zero wrench: the factor is unchanged by its presence."""
    rng = np.random.default_rng(12)
    R, q = random_state(rng)
    inp = inputs(rng)
    W1 = rng.normal(size=6) * 100
    wrenches = np.array([W1, np.zeros(6)])
    errors = []
    for contacts in ([0], [0, 1]):
        f = gf.newton_euler_factor(NOISE6, 0, contacts, inp.m, inp.c, inp.dc, inp.ddc, inp.I, inp.dI, inp.sigma,
                                   inp.dsigma, G)
        values = values_of(0, R, q, wrenches, contacts)
        check_factor_jacobians(f, values)
        errors.append(f.error(values))
    assert errors[0] == pytest.approx(errors[1], rel=1e-12)


def test_imu_factor_jacobians():
    rng = np.random.default_rng(13)
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.012] * 3 + [0.055] * 3))
    for label, R, q in _states(rng):
        imu = imu_placement(rng)
        y = ph.imu_readings(R, q[0:3], q[3:6], q[6:9], q[9:12], q[12:15], imu, G)
        for reading in (y, y + rng.normal(size=6) * 0.1):
            f = gf.imu_factor(noise, 2, reading, imu.R, imu.p, imu.v, imu.a, imu.w, G)
            values = values_of(2, R, q)
            check_factor_jacobians(f, values)
        assert gf.imu_factor(noise, 2, y, imu.R, imu.p, imu.v, imu.a, imu.w, G).error(values) < 1e-20, label


def test_integration_factor_jacobians():
    rng = np.random.default_rng(14)
    cov = np.diag([1e-8] * 3 + [1e-9] * 3 + [1e-5] * 3 + [1e-6] * 3)
    cov[0, 6] = cov[6, 0] = 0.5e-7 * 0.0
    noise = gtsam.noiseModel.Gaussian.Covariance(cov)
    dt = 0.005
    for label, R0, q0 in _states(rng):
        f = gf.integration_factor(noise, 7, dt)
        # zero error: step 1 predicted exactly by the model
        q1 = q0.copy()
        q1[9:15] = q0[9:15] + rng.normal(size=6)
        h2 = dt * dt / 6.0
        R1 = so3.exp(dt * q0[3:6] + h2 * (2 * q0[9:12] + q1[9:12])) @ R0
        q1[0:3] = q0[0:3] + dt * q0[6:9] + h2 * (2 * q0[12:15] + q1[12:15])
        q1[3:6] = q0[3:6] + 0.5 * dt * (q0[9:12] + q1[9:12])
        q1[6:9] = q0[6:9] + 0.5 * dt * (q0[12:15] + q1[12:15])
        values = values_of(7, R0, q0, k1=8, R1=R1, q1=q1)
        assert f.error(values) < 1e-12, label
        check_factor_jacobians(f, values, h=1e-7)
        R1p = so3.exp(rng.normal(size=3) * 0.01) @ R1
        check_factor_jacobians(f, values_of(7, R0, q0, k1=8, R1=R1p, q1=q1 + rng.normal(size=15) * 0.01), h=1e-7)


def test_ft_factor_jacobians():
    rng = np.random.default_rng(15)
    for _label, R, q in _states(rng):
        for i, (p_l, R_l) in enumerate(CONTACTS):
            Wv = rng.normal(size=6) * 100
            y = rng.normal(size=6) * 10
            y_nan = y.copy()
            y_nan[4] = np.nan
            for reading in (y, y_nan):
                f = gf.ft_factor(NOISE6, 1, i, p_l, R_l, reading)
                wrenches = np.zeros((2, 6))
                wrenches[i] = Wv
                check_factor_jacobians(f, values_of(1, R, q, wrenches, [i]))
