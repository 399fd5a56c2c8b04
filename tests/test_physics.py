"""Tests of flexforce.factors.physics: every analytic Jacobian against central differences, and
the model's equations against independent restatements (seed eq. 6-28, DESIGN.md corrections).

Numerical Jacobians follow the module's convention (world-frame increments), in the spirit of
GTSAM's ``factorTesting.h``: each argument is perturbed through :func:`retract` -- ``exp`` on the
left for a rotation matrix, plain addition otherwise -- and the result differenced centrally.
"""

from __future__ import annotations

import numpy as np
import pytest

from flexforce.errors import ModelError
from flexforce.factors import physics as ph
from flexforce.factors import so3

G = ph.GRAVITY
H = 1e-6  # central-difference step
RTOL = 1e-6  # relative tolerance on every Jacobian entry and on the block norm


# ----------------------------------------------------------------------------------------------
# Numerical differentiation helpers
# ----------------------------------------------------------------------------------------------


def _is_rotation(part) -> bool:
    return np.shape(part) == (3, 3)


def retract(part, d):
    """World-frame increment: ``exp([d]x) R`` for a rotation matrix, ``x + d`` otherwise."""
    if _is_rotation(part):
        return so3.exp(d) @ part
    return np.asarray(part, dtype=float) + d


def numerical_jacobian(f, x0_parts, wrt=None, h: float = H) -> np.ndarray:
    """Central-difference Jacobian of ``f(*parts)`` (a vector) with respect to ``parts[i]``,
    ``i`` in ``wrt`` (default: all), blocks concatenated column-wise in that order.

    A 3x3 part is a rotation with a 3-dimensional tangent (see :func:`retract`), stepped by ``h``
    rad; any other part is a vector of its own size, stepped by ``h max(1, |part|)`` so that large
    arguments (wrenches of kN) are not drowned in round-off.
    """
    parts = [np.array(p, dtype=float) if not np.isscalar(p) else p for p in x0_parts]
    if wrt is None:
        wrt = range(len(parts))
    f0 = np.ravel(f(*parts))
    blocks = []
    for i in wrt:
        if _is_rotation(parts[i]):
            dim, step = 3, h
        else:
            dim, step = np.size(parts[i]), h * max(1.0, float(np.linalg.norm(parts[i])))
        J = np.empty((f0.size, dim))
        for j in range(dim):
            d = np.zeros(dim)
            d[j] = step
            plus = list(parts)
            minus = list(parts)
            plus[i] = retract(parts[i], d)
            minus[i] = retract(parts[i], -d)
            J[:, j] = (np.ravel(f(*plus)) - np.ravel(f(*minus))) / (2.0 * step)
        blocks.append(J)
    return np.hstack(blocks)


def assert_jacobian(J, J_num, rtol: float = RTOL, what: str = ""):
    """Entry-wise ``|J - J_num| <= rtol |J_num| + atol``, ``atol`` scaled to the Jacobian's norm
    per 3-row band (one physical quantity: force, moment, gyro, ...), so that a wrong term in a
    small block of a band is not hidden by a large block of another band."""
    J = np.asarray(J)
    assert J.shape == J_num.shape, (J.shape, J_num.shape)
    for r0 in range(0, J.shape[0], 3):
        band = J_num[r0:r0 + 3]
        atol = rtol * max(float(np.linalg.norm(band)), 1e-9)
        np.testing.assert_allclose(J[r0:r0 + 3], band, rtol=rtol, atol=atol,
                                   err_msg=f"{what} rows {r0}:{r0 + 3}")


# ----------------------------------------------------------------------------------------------
# Sample states, parameters and inputs
# ----------------------------------------------------------------------------------------------


def _rot(rng, angle):
    axis = rng.normal(size=3)
    return so3.exp(angle * axis / np.linalg.norm(axis))


def make_state(kind: str, seed: int = 0):
    """(R, t, w, v, dw, a) of a named kind."""
    rng = np.random.default_rng(seed)
    if kind == "random":
        # Any orientation (away from pi, where log R and its Jacobian are singular).
        R = _rot(rng, rng.uniform(0.5, 2.5))
        t = 0.3 * rng.normal(size=3)
        w, v, dw, a = rng.normal(size=(4, 3)) * [[1.0], [0.5], [5.0], [3.0]]
    elif kind == "near_identity":
        R = _rot(rng, 1e-7)
        t = 1e-4 * rng.normal(size=3)
        w, v, dw, a = 0.1 * rng.normal(size=(4, 3))
    elif kind == "large_deflection":
        R = _rot(rng, 0.3)
        t = np.array([0.02, -0.03, -0.04]) + 0.01 * rng.normal(size=3)
        w, v, dw, a = rng.normal(size=(4, 3))
    elif kind == "zero_velocity":
        R = _rot(rng, 0.05)
        t = np.array([0.0, 0.0, -0.005]) + 1e-3 * rng.normal(size=3)
        w = np.zeros(3)
        v = np.zeros(3)
        dw, a = rng.normal(size=(2, 3))
    else:
        raise ValueError(kind)
    return R, t, w, v, dw, a


STATE_KINDS = ["random", "near_identity", "large_deflection", "zero_velocity"]

ISO = ph.ContactParams.make(5e4, 600.0, 400.0, 12.0)
ANISO = ph.ContactParams.make([1e5, 4e4, 2e5], [800.0, 300.0, 500.0], [300.0, 900.0, 150.0],
                              [10.0, 25.0, 5.0])
ISO_CUBIC = ph.ContactParams.make(5e4, 600.0, 400.0, 12.0, beta_f=2e3, beta_t=30.0)
ANISO_CUBIC = ph.ContactParams.make([1e5, 4e4, 2e5], [800.0, 300.0, 500.0], [300.0, 900.0, 150.0],
                                    [10.0, 25.0, 5.0], beta_f=2e3, beta_t=30.0)
# A full (non-diagonal) symmetric stiffness, given in the contact frame.
_Q = so3.exp(np.array([0.3, -0.5, 0.9]))
FULL = ph.ContactParams.make(_Q @ np.diag([1e5, 4e4, 2e5]) @ _Q.T, 500.0,
                             _Q @ np.diag([300.0, 900.0, 150.0]) @ _Q.T, [10.0, 25.0, 5.0],
                             beta_f=1e3, beta_t=10.0)
PARAMS = {"iso": ISO, "aniso": ANISO, "iso_cubic": ISO_CUBIC, "aniso_cubic": ANISO_CUBIC,
          "full": FULL}


def make_contacts(n: int, seed: int = 0, params=ISO):
    rng = np.random.default_rng(100 + seed)
    out = []
    for i in range(n):
        p = np.array([0.05 * rng.normal(), 0.1 * (1 if i % 2 == 0 else -1), 0.0])
        out.append((p, _rot(rng, rng.uniform(0.2, 1.5)), params))
    return out


def make_inputs(seed: int = 0) -> ph.Inputs:
    rng = np.random.default_rng(200 + seed)
    m = 55.0
    c = np.array([0.02, -0.01, 0.8]) + 0.02 * rng.normal(size=3)
    Q = _rot(rng, 0.4)
    I_G = Q @ np.diag([6.0, 5.0, 1.5]) @ Q.T
    S_c = so3.skew(c)
    I_l = I_G - m * S_c @ S_c  # correction 3: about the local origin
    A = rng.normal(size=(3, 3))
    return ph.Inputs(
        m=m, c=c, dc=0.1 * rng.normal(size=3), ddc=0.5 * rng.normal(size=3), I=I_l,
        dI=0.5 * (A + A.T), sigma=rng.normal(size=3), dsigma=2.0 * rng.normal(size=3),
    )


def make_imu(seed: int = 0, rotated: bool = True) -> ph.ImuPlacement:
    rng = np.random.default_rng(300 + seed)
    return ph.ImuPlacement(
        R=_rot(rng, 1.1) if rotated else np.eye(3),
        p=np.array([0.05, 0.0, 1.0]) + 0.05 * rng.normal(size=3),
        v=0.2 * rng.normal(size=3), a=rng.normal(size=3), w=0.5 * rng.normal(size=3),
    )


# ----------------------------------------------------------------------------------------------
# Contact law, eq. (6)-(12)
# ----------------------------------------------------------------------------------------------


def _reference_contact_wrench(R, t, w, v, p_l, R_cl, params):
    """Eq. (6)-(9), (11) with corrections 1, 2, 5, written out independently."""
    Rc = R @ R_cl
    Kw = [Rc @ K @ Rc.T for K in (params.K_fs, params.K_fd, params.K_ts, params.K_td)]
    s = R @ p_l + t - p_l
    sd = so3.skew(w) @ R @ p_l + v
    Omega = so3.log(R)
    F = -Kw[0] @ s * (1.0 + params.beta_f * s @ s) - Kw[1] @ sd
    T = (-Kw[2] @ Omega * (1.0 + params.beta_t * Omega @ Omega) - Kw[3] @ w
         + so3.skew(R @ p_l + t) @ F)
    return np.concatenate([F, T])


@pytest.mark.parametrize("kind", STATE_KINDS)
@pytest.mark.parametrize("pname", list(PARAMS))
def test_contact_wrench_jacobian(kind, pname):
    params = PARAMS[pname]
    seed = STATE_KINDS.index(kind) + 10 * list(PARAMS).index(pname)
    R, t, w, v, _, _ = make_state(kind, seed=seed)
    (p_l, R_cl, _), = make_contacts(1, seed=3, params=params)
    wrench, J = ph.contact_wrench(R, t, w, v, p_l, R_cl, params, jacobian=True)
    np.testing.assert_allclose(wrench, ph.contact_wrench(R, t, w, v, p_l, R_cl, params))
    ref = _reference_contact_wrench(R, t, w, v, p_l, R_cl, params)
    np.testing.assert_allclose(wrench, ref, rtol=1e-12, atol=1e-9 * np.abs(ref).max())

    def f(R_, t_, w_, v_):
        return ph.contact_wrench(R_, t_, w_, v_, p_l, R_cl, params)

    assert_jacobian(J, numerical_jacobian(f, [R, t, w, v]), what=f"{kind}/{pname}")


def test_contact_wrench_jacobian_larger_deflection_cubic():
    """Large translation and rotation, so that the cubic terms dominate the linear ones."""
    R = so3.exp(np.array([0.1, -0.25, 0.12]))
    t = np.array([0.03, -0.02, -0.05])
    w = np.array([0.4, -0.2, 0.3])
    v = np.array([0.1, 0.05, -0.2])
    for params in (ISO_CUBIC, ANISO_CUBIC, FULL):
        p_l, R_cl = np.array([0.1, -0.08, 0.0]), so3.exp(np.array([0.0, 0.0, 0.7]))
        _, J = ph.contact_wrench(R, t, w, v, p_l, R_cl, params, jacobian=True)
        Jn = numerical_jacobian(lambda *x, p_l=p_l, R_cl=R_cl, params=params: ph.contact_wrench(*x, p_l, R_cl, params),
                                [R, t, w, v])
        assert_jacobian(J, Jn)


def _reference_contact_wrench_rest(R, t, w, v, p_l, R_cl, p_r, R_r, params):
    """The contact law with a world rest placement, written out independently::

        s = R p_l + t - p_r, Omega = log(R R_cl R_r^T), the rest as eq. (6)-(11).
    """
    Rc = R @ R_cl
    Kw = [Rc @ K @ Rc.T for K in (params.K_fs, params.K_fd, params.K_ts, params.K_td)]
    s = R @ p_l + t - p_r
    sd = so3.skew(w) @ R @ p_l + v
    Omega = so3.log(Rc @ R_r.T)
    F = -Kw[0] @ s * (1.0 + params.beta_f * s @ s) - Kw[1] @ sd
    T = (-Kw[2] @ Omega * (1.0 + params.beta_t * Omega @ Omega) - Kw[3] @ w
         + so3.skew(R @ p_l + t) @ F)
    return np.concatenate([F, T])


def _foothold(R, t, p_l, R_cl, deflection: str, rng):
    """A rest placement near the contact's current world placement (deflection 1e-7 m / rad),
    at a moderate one (mm, 0.05 rad) or at a large one (4 cm, 0.4 rad)."""
    size = {"near_identity": 1e-7, "moderate": 1.0, "large": 1.0}[deflection]
    lin, ang = {"near_identity": (1.0, 1.0), "moderate": (3e-3, 0.05), "large": (0.04, 0.4)}[deflection]
    d_p = size * lin * rng.normal(size=3)
    d_r = rng.normal(size=3)
    d_r *= size * ang / np.linalg.norm(d_r)
    return R @ p_l + t + d_p, so3.exp(d_r) @ R @ R_cl


@pytest.mark.parametrize("deflection", ["near_identity", "moderate", "large"])
@pytest.mark.parametrize("pname", list(PARAMS))
def test_contact_wrench_with_foothold_and_its_jacobians(deflection, pname):
    """World rest placement: the wrench against the independent reference, the Jacobian on the
    state and the Jacobian on the foothold (p_r, world increment of R_r) against central
    differences."""
    params = PARAMS[pname]
    rng = np.random.default_rng(7 + list(PARAMS).index(pname))
    R, t, w, v, _, _ = make_state("large_deflection" if deflection == "large" else "random", seed=5)
    (p_l, R_cl, _), = make_contacts(1, seed=3, params=params)
    p_r, R_r = _foothold(R, t, p_l, R_cl, deflection, rng)
    wrench, J, J_rest = ph.contact_wrench(R, t, w, v, p_l, R_cl, params, jacobian=True, world_p_rest=p_r,
                                          world_R_rest=R_r, rest_jacobian=True)
    ref = _reference_contact_wrench_rest(R, t, w, v, p_l, R_cl, p_r, R_r, params)
    np.testing.assert_allclose(wrench, ref, rtol=1e-12, atol=1e-9 * np.abs(ref).max())

    def f(R_, t_, w_, v_):
        return ph.contact_wrench(R_, t_, w_, v_, p_l, R_cl, params, world_p_rest=p_r, world_R_rest=R_r)

    def f_rest(p_, R_):
        return ph.contact_wrench(R, t, w, v, p_l, R_cl, params, world_p_rest=p_, world_R_rest=R_)

    assert_jacobian(J, numerical_jacobian(f, [R, t, w, v]), what=f"state {deflection}/{pname}")
    # The foothold moves by mm at most in the differences: step relative to 1 m, not to |p_r|.
    assert_jacobian(J_rest, numerical_jacobian(f_rest, [p_r, R_r]), what=f"foothold {deflection}/{pname}")
    assert np.all(J_rest[0:3, 3:6] == 0.0)  # the force does not depend on the rest orientation


@pytest.mark.parametrize("kind", STATE_KINDS)
@pytest.mark.parametrize("pname", list(PARAMS))
def test_default_rest_is_the_local_placement(kind, pname):
    """``p_r = p_l``, ``R_r = R_l`` is the paper's law (``s = R p_l + t - p_l``, ``Omega = log R``)."""
    params = PARAMS[pname]
    R, t, w, v, _, _ = make_state(kind, seed=2)
    (p_l, R_cl, _), = make_contacts(1, seed=3, params=params)
    a, Ja = ph.contact_wrench(R, t, w, v, p_l, R_cl, params, jacobian=True)
    b, Jb = ph.contact_wrench(R, t, w, v, p_l, R_cl, params, jacobian=True, world_p_rest=p_l, world_R_rest=R_cl)
    np.testing.assert_allclose(b, a, rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(Jb, Ja, rtol=1e-13, atol=1e-10)
    np.testing.assert_allclose(a, _reference_contact_wrench(R, t, w, v, p_l, R_cl, params), rtol=1e-12,
                               atol=1e-9 * np.abs(a).max())


def test_contact_statics_translation():
    """One isotropic contact at the origin, R = I, t = (0, 0, -d): F = (0, 0, k_fs d), T = 0."""
    k_fs, d = 6e4, 0.004
    params = ph.ContactParams.make(k_fs, 700.0, 500.0, 15.0)
    wrench = ph.contact_wrench(np.eye(3), np.array([0.0, 0.0, -d]), np.zeros(3), np.zeros(3),
                               np.zeros(3), np.eye(3), params)
    np.testing.assert_allclose(wrench, [0.0, 0.0, k_fs * d, 0.0, 0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("th", [1e-7, 0.01, -0.05, 0.3])
def test_contact_statics_rotation(th):
    """Rotation about y by th at the origin: the moment is -k_ts th about y, and no force."""
    k_ts = 450.0
    params = ph.ContactParams.make(6e4, 700.0, k_ts, 15.0)
    R = so3.exp(np.array([0.0, th, 0.0]))
    wrench = ph.contact_wrench(R, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), np.eye(3),
                               params)
    np.testing.assert_allclose(wrench, [0.0, 0.0, 0.0, 0.0, -k_ts * th, 0.0],
                               atol=1e-12 * k_ts)


def test_contact_damping_uses_rotational_damping():
    """Correction 1: the moment's damping is K_td w (the seed prints K_Fd)."""
    params = ph.ContactParams.make(6e4, 700.0, 500.0, 15.0)
    w = np.array([0.0, 0.2, 0.0])
    wrench = ph.contact_wrench(np.eye(3), np.zeros(3), w, np.zeros(3), np.zeros(3), np.eye(3),
                               params)
    np.testing.assert_allclose(wrench, [0, 0, 0, 0, -15.0 * 0.2, 0], atol=1e-12)


@pytest.mark.parametrize("pname", list(PARAMS))
@pytest.mark.parametrize("kind", ["random", "large_deflection"])
def test_contact_moment_is_lever_arm_plus_pure_moment(kind, pname):
    """Correction 2: T = [R p_l + t]x F + the pure spring-damper moment."""
    params = PARAMS[pname]
    R, t, w, v, _, _ = make_state(kind, seed=11)
    (p_l, R_cl, _), = make_contacts(1, seed=4, params=params)
    wrench = ph.contact_wrench(R, t, w, v, p_l, R_cl, params)
    F, T = wrench[:3], wrench[3:]
    p = R @ p_l + t  # displaced contact point, not the rest point p_l
    Rc = R @ R_cl
    Omega = so3.log(R)
    pure = (-(Rc @ params.K_ts @ Rc.T) @ Omega * (1.0 + params.beta_t * Omega @ Omega)
            - (Rc @ params.K_td @ Rc.T) @ w)
    np.testing.assert_allclose(T, np.cross(p, F) + pure, rtol=1e-12, atol=1e-9 * np.abs(T).max())
    # Moved to the contact point, only the pure moment remains.
    np.testing.assert_allclose(ph.wrench_about(wrench, p)[3:], pure, atol=1e-9 * np.abs(T).max())
    assert not np.allclose(T, np.cross(p_l, F) + pure)  # the rest point would be wrong here


def test_isotropic_contact_ignores_orientation():
    R, t, w, v, _, _ = make_state("large_deflection", seed=5)
    p_l = np.array([0.1, 0.05, 0.0])
    a = ph.contact_wrench(R, t, w, v, p_l, np.eye(3), ISO)
    b = ph.contact_wrench(R, t, w, v, p_l, so3.exp(np.array([0.4, 1.0, -2.0])), ISO)
    np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-10)
    assert ISO.isotropic and not ANISO.isotropic


def test_anisotropic_stiffness_is_in_contact_frame():
    """Correction 5: diag(k) in a contact frame R_c equals the full matrix R_c diag(k) R_c^T given
    with the identity as contact frame; and with R = I a displacement along a contact axis meets
    that axis' stiffness."""
    R, t, w, v, _, _ = make_state("random", seed=6)
    p_l = np.array([0.1, 0.05, 0.0])
    R_cl = so3.exp(np.array([0.2, -0.3, 0.8]))
    kf, kd, kt, ktd = [1e5, 4e4, 2e5], [800.0, 300.0, 500.0], [300.0, 900.0, 150.0], [10., 25., 5.]
    diag = ph.ContactParams.make(kf, kd, kt, ktd)
    full = ph.ContactParams.make(*(R_cl @ np.diag(k) @ R_cl.T for k in (kf, kd, kt, ktd)))
    np.testing.assert_allclose(ph.contact_wrench(R, t, w, v, p_l, R_cl, diag),
                               ph.contact_wrench(R, t, w, v, p_l, np.eye(3), full),
                               rtol=1e-12, atol=1e-8)
    # Rest orientation, push 1 mm along the contact's second axis: force -k_y * 1 mm along it.
    e_y = R_cl[:, 1]
    wrench = ph.contact_wrench(np.eye(3), 1e-3 * e_y, np.zeros(3), np.zeros(3), np.zeros(3), R_cl,
                               diag)
    np.testing.assert_allclose(wrench[:3], -kf[1] * 1e-3 * e_y, atol=1e-9)


@pytest.mark.parametrize("n", [0, 1, 2, 3])
@pytest.mark.parametrize("kind", ["random", "near_identity", "zero_velocity"])
def test_total_contact_wrench(n, kind):
    R, t, w, v, _, _ = make_state(kind, seed=7 + n)
    contacts = make_contacts(n, seed=n, params=ISO)
    if n >= 2:
        contacts[1] = (contacts[1][0], contacts[1][1], ANISO_CUBIC)
    total, per, J = ph.total_contact_wrench(R, t, w, v, contacts, jacobian=True)
    total2, per2 = ph.total_contact_wrench(R, t, w, v, contacts)
    assert per.shape == (n, 6)
    np.testing.assert_allclose(total, total2)
    np.testing.assert_allclose(per, per2)
    expected = [ph.contact_wrench(R, t, w, v, p, Rc, prm) for p, Rc, prm in contacts]
    np.testing.assert_allclose(total, np.sum(expected, axis=0) if n else np.zeros(6))
    if n == 0:
        np.testing.assert_array_equal(J, np.zeros((6, 12)))
        return
    Jn = numerical_jacobian(lambda *x: ph.total_contact_wrench(*x, contacts)[0], [R, t, w, v])
    assert_jacobian(J, Jn, what=f"{n} contacts")


# ----------------------------------------------------------------------------------------------
# Newton-Euler, eq. (13)-(25)
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", STATE_KINDS)
def test_required_wrench_jacobians(kind):
    R, t, w, v, dw, a = make_state(kind, seed=21)
    inp = make_inputs(1)
    wrench, J = ph.required_wrench(R, t, w, v, dw, a, inp, jacobian=True)
    np.testing.assert_allclose(wrench, ph.required_wrench(R, t, w, v, dw, a, inp))

    def f(R_, t_, w_, v_, dw_, a_):
        return ph.required_wrench(R_, t_, w_, v_, dw_, a_, inp)

    Jn = numerical_jacobian(f, [R, t, w, v, dw, a])
    assert_jacobian(J.x, Jn[:, :12], what="x")
    assert_jacobian(J.acc, Jn[:, 12:], what="acc")


def _reference_required_wrench(R, t, w, dw, a, inp, g=G):
    """Eq. (16) and (23) (corrections 2, 3) with F_c, T_c the unknowns, written out again."""
    m = inp.m
    Sw = so3.skew(w)
    Rc = R @ inp.c
    F = (m * so3.skew(dw) @ Rc + m * Sw @ Sw @ Rc + 2 * m * Sw @ R @ inp.dc + m * R @ inp.ddc
         + m * a + g * m * np.array([0, 0, 1.0]))
    T = (Sw @ R @ inp.I @ R.T @ w + R @ inp.dI @ R.T @ w + R @ inp.I @ R.T @ dw + Sw @ R @ inp.sigma
         + R @ inp.dsigma + so3.skew(t) @ F + m * so3.skew(Rc) @ a
         + so3.skew(Rc) @ (g * m * np.array([0, 0, 1.0])))
    return np.concatenate([F, T])


def test_required_wrench_matches_equations_16_23():
    R, t, w, v, dw, a = make_state("random", seed=22)
    inp = make_inputs(2)
    ref = _reference_required_wrench(R, t, w, dw, a, inp)
    np.testing.assert_allclose(ph.required_wrench(R, t, w, v, dw, a, inp), ref, rtol=1e-12,
                               atol=1e-10 * np.abs(ref).max())


def test_required_wrench_at_rest_is_weight():
    """Standing still, the contacts carry the weight, m g up, with moment [c]x m g e_z."""
    inp = make_inputs(3)
    inp = ph.Inputs(inp.m, inp.c, np.zeros(3), np.zeros(3), inp.I, np.zeros((3, 3)), np.zeros(3),
                    np.zeros(3))
    z = np.zeros(3)
    wrench = ph.required_wrench(np.eye(3), z, z, z, z, z, inp, g=9.7)
    mg = inp.m * 9.7
    np.testing.assert_allclose(wrench, [0, 0, mg, inp.c[1] * mg, -inp.c[0] * mg, 0], atol=1e-10)


@pytest.mark.parametrize("kind", ["random", "near_identity"])
def test_newton_euler_residual(kind):
    R, t, w, v, dw, a = make_state(kind, seed=23)
    inp = make_inputs(4)
    wrench_c = np.random.default_rng(5).normal(size=6) * 300.0
    r, J = ph.newton_euler_residual(R, t, w, v, dw, a, wrench_c, inp, jacobian=True)
    np.testing.assert_allclose(r, ph.newton_euler_residual(R, t, w, v, dw, a, wrench_c, inp))
    np.testing.assert_allclose(r, ph.required_wrench(R, t, w, v, dw, a, inp) - wrench_c)

    def f(R_, t_, w_, v_, dw_, a_, wr_):
        return ph.newton_euler_residual(R_, t_, w_, v_, dw_, a_, wr_, inp)

    Jn = numerical_jacobian(f, [R, t, w, v, dw, a, wrench_c])
    assert_jacobian(J.x, Jn[:, :12], what="x")
    assert_jacobian(J.acc, Jn[:, 12:18], what="acc")
    assert_jacobian(J.wrench, Jn[:, 18:], what="wrench")


def _closed_form_dynamics(R, t, w, wrench_c, inp, g=G):
    """DESIGN.md correction 4 for dw and seed eq. (25) for a, transcribed independently."""
    m = inp.m
    F_c, T_c = wrench_c[:3], wrench_c[3:]
    Sw = so3.skew(w)
    S_c = so3.skew(inp.c)
    Rc = R @ inp.c
    S_Rc = so3.skew(Rc)
    u_z = np.array([0.0, 0.0, 1.0])
    kin = R @ inp.ddc + 2.0 * Sw @ R @ inp.dc + Sw @ Sw @ Rc  # R c'' + 2[w]x R c' + [w]x^2 R c
    dw = R @ np.linalg.inv(inp.I + m * S_c @ S_c) @ R.T @ (
        T_c - Sw @ R @ inp.I @ R.T @ w - R @ inp.dI @ R.T @ w - R @ inp.dsigma - Sw @ R @ inp.sigma
        + m * S_Rc @ kin - so3.skew(Rc + t) @ F_c)
    a = (F_c - (m * kin + g * m * u_z)) / m + S_Rc @ dw
    return np.concatenate([dw, a])


@pytest.mark.parametrize("kind", STATE_KINDS)
def test_forward_dynamics(kind):
    R, t, w, v, _, _ = make_state(kind, seed=31)
    inp = make_inputs(5)
    contacts = make_contacts(2, seed=6, params=ISO_CUBIC)
    wrench_c, _ = ph.total_contact_wrench(R, t, w, v, contacts)
    acc = ph.forward_dynamics(R, t, w, v, wrench_c, inp)
    # Zero Newton-Euler residual.
    r = ph.newton_euler_residual(R, t, w, v, acc[:3], acc[3:], wrench_c, inp)
    np.testing.assert_allclose(r, 0.0, atol=1e-10 * np.abs(wrench_c).max())
    # Closed form (correction 4, eq. 25).
    np.testing.assert_allclose(acc, _closed_form_dynamics(R, t, w, wrench_c, inp), rtol=1e-9,
                               atol=1e-9 * np.abs(acc).max())
    # Jacobians.
    acc2, J = ph.forward_dynamics(R, t, w, v, wrench_c, inp, jacobian=True)
    np.testing.assert_allclose(acc2, acc)

    def f(R_, t_, w_, v_, wr_):
        return ph.forward_dynamics(R_, t_, w_, v_, wr_, inp)

    Jn = numerical_jacobian(f, [R, t, w, v, wrench_c])
    assert_jacobian(J.x, Jn[:, :12], what="x")
    assert_jacobian(J.wrench, Jn[:, 12:], what="wrench")


def test_forward_dynamics_with_contact_law_chain_rule():
    """The EKF's prediction Jacobian: d acc/dx through the contact wrench, chained."""
    R, t, w, v, _, _ = make_state("large_deflection", seed=32)
    inp = make_inputs(6)
    contacts = make_contacts(2, seed=7, params=ANISO)

    def f(R_, t_, w_, v_):
        wr, _ = ph.total_contact_wrench(R_, t_, w_, v_, contacts)
        return ph.forward_dynamics(R_, t_, w_, v_, wr, inp)

    wr, _, Jc = ph.total_contact_wrench(R, t, w, v, contacts, jacobian=True)
    _, J = ph.forward_dynamics(R, t, w, v, wr, inp, jacobian=True)
    assert_jacobian(J.x + J.wrench @ Jc, numerical_jacobian(f, [R, t, w, v]))


def test_forward_dynamics_at_rest_with_weight_is_still():
    inp = make_inputs(7)
    inp = ph.Inputs(inp.m, inp.c, np.zeros(3), np.zeros(3), inp.I, np.zeros((3, 3)), np.zeros(3),
                    np.zeros(3))
    mg = inp.m * G
    wrench = np.array([0.0, 0.0, mg, inp.c[1] * mg, -inp.c[0] * mg, 0.0])
    z = np.zeros(3)
    np.testing.assert_allclose(ph.forward_dynamics(np.eye(3), z, z, z, wrench, inp), 0.0,
                               atol=1e-12)


def test_forward_dynamics_singular_raises_model_error():
    z = np.zeros(3)
    inp = ph.Inputs(0.0, z, z, z, np.zeros((3, 3)), np.zeros((3, 3)), z, z)
    with pytest.raises(ModelError):
        ph.forward_dynamics(np.eye(3), z, z, z, np.zeros(6), inp)


# ----------------------------------------------------------------------------------------------
# IMU, eq. (26)-(28)
# ----------------------------------------------------------------------------------------------


def test_imu_at_rest_reads_gravity_up():
    z = np.zeros(3)
    imu = ph.ImuPlacement(R=np.eye(3), p=np.array([0.1, -0.2, 0.9]), v=z, a=z, w=z)
    y = ph.imu_readings(np.eye(3), np.array([0.3, 0.1, -0.01]), z, z, z, z, imu)
    np.testing.assert_allclose(y, [0, 0, 0, 0, 0, G], atol=1e-15)
    y = ph.imu_readings(np.eye(3), z, z, z, z, z, imu, g=9.78)
    np.testing.assert_allclose(y, [0, 0, 0, 0, 0, 9.78], atol=1e-15)


@pytest.mark.parametrize("kind", STATE_KINDS)
@pytest.mark.parametrize("rotated", [False, True])
def test_imu_jacobians(kind, rotated):
    R, t, w, v, dw, a = make_state(kind, seed=41)
    imu = make_imu(1, rotated=rotated)
    y, J = ph.imu_readings(R, t, w, v, dw, a, imu, jacobian=True)
    np.testing.assert_allclose(y, ph.imu_readings(R, t, w, v, dw, a, imu))

    def f(R_, t_, w_, v_, dw_, a_):
        return ph.imu_readings(R_, t_, w_, v_, dw_, a_, imu)

    Jn = numerical_jacobian(f, [R, t, w, v, dw, a])
    assert_jacobian(J.x, Jn[:, :12], what="x")
    assert_jacobian(J.acc, Jn[:, 12:], what="acc")


def test_imu_rotated_frame_reads_rotated_values():
    R, t, w, v, dw, a = make_state("random", seed=42)
    imu = make_imu(2, rotated=True)
    local = ph.ImuPlacement(R=np.eye(3), p=imu.p, v=imu.v, a=imu.a, w=imu.w)
    y = ph.imu_readings(R, t, w, v, dw, a, imu)
    y_l = ph.imu_readings(R, t, w, v, dw, a, local)
    np.testing.assert_allclose(y[:3], imu.R.T @ y_l[:3], atol=1e-13)
    np.testing.assert_allclose(y[3:], imu.R.T @ y_l[3:], atol=1e-12)


def test_imu_matches_kinematics_of_a_trajectory():
    """Eq. (26)-(28) against the definition: differentiate a smooth trajectory in time.

    Flexibility R(s), t(s) and IMU placement R_a(s), p_a(s) in the local frame; the IMU's world
    orientation is R R_a and position R p_a + t.  The gyro reads the IMU's angular velocity, the
    accelerometer d2/ds2 (R p_a + t) + g e_z, both in the IMU frame.
    """
    phi0, phi1, phi2 = np.array([[0.1, -0.2, 0.05], [0.7, 0.3, -0.4], [1.0, -2.0, 0.5]])
    psi0, psi1, psi2 = np.array([[0.3, 1.0, -0.6], [-0.5, 0.2, 0.9], [0.4, 0.3, -1.0]])
    t0, t1, t2 = np.array([0.01, -0.02, -0.005]), np.array([0.1, 0.2, -0.1]), np.array([1., -.5, 2])
    p0, p1, p2 = np.array([0.05, 0.0, 1.0]), np.array([0.3, -0.1, 0.2]), np.array([-1., 2, .5])

    def R_of(s):
        return so3.exp(phi0 + s * phi1 + s * s * phi2)

    def Ra_of(s):
        return so3.exp(psi0 + s * psi1 + s * s * psi2)

    def t_of(s):
        return t0 + s * t1 + s * s * t2

    def p_of(s):
        return p0 + s * p1 + s * s * p2

    def vee(S):
        return np.array([S[2, 1], S[0, 2], S[1, 0]])

    def world_rate(Rf, s, h=1e-5):  # world-frame angular velocity of a rotation path
        return vee((Rf(s + h) - Rf(s - h)) / (2 * h) @ Rf(s).T)

    h = 1e-5
    R, Ra = R_of(0.0), Ra_of(0.0)
    w = world_rate(R_of, 0.0)
    dw = (world_rate(R_of, h) - world_rate(R_of, -h)) / (2 * h)
    w_gl = world_rate(Ra_of, 0.0)  # relative angular velocity, expressed in the local frame
    imu = ph.ImuPlacement(R=Ra, p=p0, v=p1, a=2 * p2, w=w_gl)
    y = ph.imu_readings(R, t0, w, t1, dw, 2 * t2, imu)

    def world_pos(s):
        return R_of(s) @ p_of(s) + t_of(s)

    hh = 1e-4
    acc_world = (world_pos(hh) - 2 * world_pos(0.0) + world_pos(-hh)) / hh**2
    gyro_world = world_rate(lambda s: R_of(s) @ Ra_of(s), 0.0)
    R_imu = R @ Ra
    np.testing.assert_allclose(y[:3], R_imu.T @ gyro_world, atol=1e-8)
    np.testing.assert_allclose(y[3:], R_imu.T @ (acc_world + G * np.array([0, 0, 1.0])),
                               atol=1e-5)


# ----------------------------------------------------------------------------------------------
# Centre of pressure
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("z0", [0.0, 0.07])
def test_center_of_pressure_of_a_point_force(z0):
    F = np.array([0.0, 0.0, 420.0])
    for x, y in [(0.0, 0.0), (0.12, -0.05), (-0.3, 0.2)]:
        p = np.array([x, y, z0])
        wrench = np.concatenate([F, np.cross(p, F)])
        np.testing.assert_allclose(ph.center_of_pressure(wrench, z0=z0), p, atol=1e-15)


def test_center_of_pressure_moves_with_pure_moment_and_slanted_force():
    """A force F at (x, y, z0) plus a pure vertical moment: the CoP is still (x, y)."""
    p = np.array([0.08, -0.03, 0.02])
    F = np.array([35.0, -20.0, 500.0])
    wrench = np.concatenate([F, np.cross(p, F) + np.array([0.0, 0.0, 3.0])])
    np.testing.assert_allclose(ph.center_of_pressure(wrench, z0=0.02), p, atol=1e-15)


@pytest.mark.parametrize("z0", [0.0, 0.05])
def test_center_of_pressure_jacobian(z0):
    wrench = np.array([30.0, -15.0, 480.0, 12.0, -25.0, 3.0])
    p, J = ph.center_of_pressure(wrench, z0=z0, jacobian=True)
    np.testing.assert_allclose(p, ph.center_of_pressure(wrench, z0=z0))
    Jn = numerical_jacobian(lambda wr: ph.center_of_pressure(wr, z0=z0), [wrench])
    np.testing.assert_allclose(J, Jn, rtol=RTOL, atol=RTOL * np.linalg.norm(Jn))


@pytest.mark.parametrize("Fz", [0.0, 1e-9, -50.0, np.nan])
def test_center_of_pressure_undefined_without_vertical_force(Fz):
    wrench = np.array([10.0, 0.0, Fz, 1.0, 2.0, 0.0])
    p = ph.center_of_pressure(wrench)
    assert np.isnan(p[0]) and np.isnan(p[1])
    p, J = ph.center_of_pressure(wrench, jacobian=True)
    assert np.isnan(p[:2]).all() and np.isnan(J).all()


# ----------------------------------------------------------------------------------------------
# The test helpers themselves: they must catch a wrong term.
# ----------------------------------------------------------------------------------------------


def test_numerical_jacobian_catches_a_wrong_term():
    R, t, w, v, _, _ = make_state("random", seed=51)
    (p_l, R_cl, _), = make_contacts(1, seed=8, params=ANISO)
    _, J = ph.contact_wrench(R, t, w, v, p_l, R_cl, ANISO, jacobian=True)
    Jn = numerical_jacobian(lambda *x: ph.contact_wrench(*x, p_l, R_cl, ANISO), [R, t, w, v])
    assert_jacobian(J, Jn)
    # Drop the rotation of the anisotropic damping (a 1e-2 relative piece of one block).
    Ktd = (R @ R_cl) @ ANISO.K_td @ (R @ R_cl).T
    wrong = J.copy()
    wrong[3:6, 0:3] -= so3.skew(Ktd @ w) - Ktd @ so3.skew(w)
    with pytest.raises(AssertionError):
        assert_jacobian(wrong, Jn)
    # A body-frame (right) perturbation of R is a different convention and must not pass.
    def f_body(dphi):
        return ph.contact_wrench(R @ so3.exp(dphi), t, w, v, p_l, R_cl, ANISO)
    Jb = numerical_jacobian(f_body, [np.zeros(3)])
    with pytest.raises(AssertionError):
        assert_jacobian(J[:, :3], Jb)
    # ... but it is the world-frame one times R (d_theta = R d_phi).
    assert_jacobian(J[:, :3] @ R, Jb)
