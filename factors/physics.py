r"""The flexible-contact model of Mifsud, Benallegue & Lamiraux (IROS 2015): its readable face.

The laws are computed by the compiled core :mod:`flexforce.factors.core` (one implementation for
the EKF, the smoothers, the GTSAM factors and the Cramér–Rao bound); this module states them with
the seed paper's equation numbers, DESIGN.md's corrections ("correction k") and the conventions,
and calls the core with numpy arrays.

Frames and state
----------------
The flexibility ``(R, t)`` maps a point of the local (control) frame to the world,
``p = R p_l + t`` (eq. 2, 3).  ``w`` is the world-frame angular velocity (``dR/dt = [w]x R``),
``v = dt/dt``; ``dw``, ``a`` are their time derivatives.  Gravity is ``-g e_z`` in the world.

Jacobian convention
-------------------
Every ``*_D_*`` Jacobian is taken with respect to *world-frame increments*:
``R <- exp([d_theta]x) R``, ``t <- t + d_t``, ``w <- w + d_w``, ``v <- v + d_v`` and likewise for
accelerations and wrenches.  Blocks are ordered rotation first (as in gtsam):

- ``x = (theta, t, w, v)`` -- pose and velocity, 12 components;
- ``acc = (dw, a)`` -- acceleration, 6 components;
- a wrench is ``(F, T)``: force (N) then moment (N m) *about the world origin*.

A gtsam ``Pose3`` body-frame tangent ``(d_phi, d_rho)`` relates by ``d_theta = R d_phi`` and
``d_t = R d_rho``.  The paper's EKF state uses the rotation vector ``Omega = log R``; its increment
is ``d_theta = J_l(Omega) d_Omega`` (see :mod:`flexforce.factors.so3`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flexforce.datasets.quantities import GRAVITY, ContactParams, ImuPlacement, Inputs
from flexforce.errors import ModelError
from flexforce.factors import core

E_Z = np.array([0.0, 0.0, 1.0])
_NO_REST_JAC = np.empty((0, 6))


def _f(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=float)


# ----------------------------------------------------------------------------------------------
# Parameters and inputs
# ----------------------------------------------------------------------------------------------


@dataclass
class Jacobians:
    """Jacobians of a model function; ``None`` where the function does not depend on the block."""

    x: np.ndarray | None = None
    """With respect to ``(theta, t, w, v)`` (world-frame increments), rows x 12."""
    acc: np.ndarray | None = None
    """With respect to ``(dw, a)``, rows x 6."""
    wrench: np.ndarray | None = None
    """With respect to the contact wrench ``(F, T)``, rows x 6."""
    extra: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------
# Contact law, eq. (6)-(12)
# ----------------------------------------------------------------------------------------------


def contact_wrench(R, t, w, v, local_p_c, local_R_c, params: ContactParams, jacobian: bool = False,
                   world_p_rest=None, world_R_rest=None, rest_jacobian: bool = False):
    r"""Wrench of one flexible contact, force and moment about the world origin.

    Eq. (6)-(9) and (11) with corrections 1, 2 and 5, generalised to a rest placement
    ``(p_r, R_r)`` in the world (the contact episode's foothold)::

        s     = R p_l + t - p_r                      (7)  displacement of the contact point
        ds    = [w]x R p_l + v                       (9)
        Omega = log(R R_l R_r^T)                          rotation of the contact from its rest
        F     = -K_fs s (1 + beta_f |s|^2) - K_fd ds                                   (6)
        T     = -K_ts Omega (1 + beta_t |Omega|^2) - K_td w + [R p_l + t]x F          (11)

    By default the rest placement is the local placement itself, ``p_r = p_l``, ``R_r = R_l``: at
    zero deformation the local and world frames agree, ``s = R p_l + t - p_l`` and
    ``Omega = log R`` (the paper's law).  ``K`` in the contact frame is rotated into the world with
    the contact's current orientation ``R R_l`` (correction 5).

    Args:
        R, t: flexibility rotation (3x3) and translation (m).
        w, v: flexibility angular (rad/s, world) and linear (m/s) velocity.
        local_p_c, local_R_c: the contact's position (m) and orientation in the local frame.
        params: the contact's stiffness and damping in its own frame.
        jacobian: also return the 6x12 Jacobian with respect to ``(theta, t, w, v)``.
        world_p_rest, world_R_rest: the rest placement in the world (m, rotation matrix).
        rest_jacobian: with ``jacobian``, also return the 6x6 Jacobian with respect to the rest
            placement's increments ``(d_p, d_r)``: ``p_r <- p_r + d_p``, ``R_r <- exp([d_r]x) R_r``.

    Returns:
        ``wrench`` (6,) = (F [N], T [N m]), ``(wrench, J)`` or ``(wrench, J, J_rest)``.
    """
    p_l, R_l = _f(local_p_c), _f(local_R_c)
    p_r = p_l if world_p_rest is None else _f(world_p_rest)
    R_r = R_l if world_R_rest is None else _f(world_R_rest)
    q = np.zeros(15)
    q[0:3], q[3:6], q[6:9] = t, w, v
    r = np.empty(6)
    J = np.empty((6, core.STATE_DIM))
    Jr = np.empty((6, 6)) if rest_jacobian else _NO_REST_JAC
    core.contact_law(_f(R), q, np.zeros(6), p_l, R_l, p_r, R_r, params.K_fs, params.K_fd, params.K_ts,
                     params.K_td, float(params.beta_f), float(params.beta_t), bool(params.isotropic), r, J, Jr)
    if not jacobian:
        return r
    if rest_jacobian:
        return r, J[:, :12].copy(), Jr
    return r, J[:, :12].copy()


def contact_arrays(params) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """The contacts' parameters as the compiled core's batched laws take them
    (:func:`flexforce.factors.core.contact_all`): ``([K_fs, K_fd, K_ts, K_td], beta, iso)``, each
    ``K`` (C, 3, 3), ``beta`` (C, 2) = (beta_f, beta_t), ``iso`` (C,) bool."""
    K = [np.ascontiguousarray(np.array([getattr(p, name) for p in params], dtype=float))
         for name in ("K_fs", "K_fd", "K_ts", "K_td")]
    beta = np.array([[p.beta_f, p.beta_t] for p in params], dtype=float).reshape(-1, 2)
    iso = np.array([p.isotropic for p in params], dtype=bool)
    return K, beta, iso


def total_contact_wrench(R, t, w, v, contacts, jacobian: bool = False):
    """Sum of :func:`contact_wrench` over ``contacts`` (eq. 10, 12).

    Args:
        contacts: iterable of ``(local_p_c, local_R_c, params)`` for the active contacts, or of
            ``(local_p_c, local_R_c, params, world_p_rest, world_R_rest)``.

    Returns:
        ``(wrench, per_contact)`` with ``per_contact`` an (n, 6) array, plus the summed 6x12
        Jacobian when ``jacobian`` is set.
    """
    per = []
    Jsum = np.zeros((6, 12))
    for c in contacts:
        p_l, R_l, params = c[:3]
        rest = c[3:5] if len(c) > 3 else (None, None)
        if jacobian:
            wr, J = contact_wrench(R, t, w, v, p_l, R_l, params, True, *rest)
            Jsum += J
        else:
            wr = contact_wrench(R, t, w, v, p_l, R_l, params, False, *rest)
        per.append(wr)
    per_arr = np.array(per).reshape(-1, 6)
    total = per_arr.sum(axis=0) if per else np.zeros(6)
    if jacobian:
        return total, per_arr, Jsum
    return total, per_arr


# ----------------------------------------------------------------------------------------------
# Newton-Euler, eq. (13)-(25)
# ----------------------------------------------------------------------------------------------


def _state(t, w, v, dw, a) -> np.ndarray:
    q = np.empty(15)
    q[0:3], q[3:6], q[6:9], q[9:12], q[12:15] = t, w, v, dw, a
    return q


def _inputs(inp: Inputs) -> tuple:
    return tuple(_f(x) for x in (inp.c, inp.dc, inp.ddc, inp.I, inp.dI, inp.sigma, inp.dsigma))


def required_wrench(R, t, w, v, dw, a, inp: Inputs, g: float = GRAVITY, jacobian: bool = False):
    r"""The external wrench the motion requires besides gravity (force, moment about the origin).

    Newton (eq. 15, 16) and Euler (eq. 22, 23) solved for the wrench, with corrections 2-3::

        F_req = m ([dw]x R c + [w]x^2 R c + 2 [w]x R dc + R ddc + a + g e_z)
        T_req = [w]x R I R^T w + R dI R^T w + R I R^T dw + [w]x R sigma + R dsigma
                + [t]x F_req + m [R c]x (a + g e_z)

    With ``F_req = F_c`` the first line is eq. (16); substituting ``[t]x F_c`` for ``[t]x F_req``
    the second is eq. (23).  Writing it with ``F_req`` keeps the residual of
    :func:`newton_euler_residual` equal to the unexplained external wrench about the origin.

    Returns:
        ``wrench`` (6,) or ``(wrench, Jacobians)`` with ``x`` (6x12) and ``acc`` (6x6) blocks.
    """
    r = np.empty(6)
    J = np.empty((6, core.STATE_DIM))
    core.newton_euler(_f(R), _state(t, w, v, dw, a), np.zeros(6), float(inp.m), *_inputs(inp), float(g), r, J)
    if not jacobian:
        return r
    return r, Jacobians(x=J[:, :12].copy(), acc=J[:, 12:].copy())


def newton_euler_residual(R, t, w, v, dw, a, wrench_c, inp: Inputs, g: float = GRAVITY,
                          jacobian: bool = False):
    """The wrench the model leaves unexplained: ``required_wrench - wrench_c`` (eq. 16, 23).

    Zero when the contact wrench ``wrench_c`` = (F_c, T_c) (about the world origin) explains the
    motion; otherwise the external wrench (N, N m about the world origin) that is missing, e.g. a
    push on the hand.

    Returns:
        ``r`` (6,) or ``(r, Jacobians)`` with ``x`` (6x12), ``acc`` (6x6) and ``wrench`` (-I).
    """
    if jacobian:
        req, J = required_wrench(R, t, w, v, dw, a, inp, g, jacobian=True)
        J.wrench = -np.eye(6)
        return req - wrench_c, J
    return required_wrench(R, t, w, v, dw, a, inp, g) - wrench_c


def forward_dynamics(R, t, w, v, wrench_c, inp: Inputs, g: float = GRAVITY, jacobian: bool = False):
    r"""The flexibility acceleration ``(dw, a)`` that the contact wrench produces, eq. (24), (25).

    Solves the 6x6 linear system ``required_wrench(dw, a) = wrench_c`` in the accelerations (the
    required wrench is affine in them, with the acceleration block ``A`` of
    :func:`required_wrench`'s Jacobian); by ``A``'s structure this is eq. (24) as corrected
    (correction 4) and eq. (25)::

        dw = R (I + m[c]x^2)^-1 R^T (T_c - [w]x R I R^T w - R dI R^T w - R dsigma - [w]x R sigma
             + m [R c]x (R ddc + 2 [w]x R dc + [w]x^2 R c) - [R c + t]x F_c)
        a  = F_c / m - (R ddc + 2 [w]x R dc + [w]x^2 R c + g e_z) + [R c]x dw

    Args:
        wrench_c: total contact (plus any known external) wrench about the world origin.

    Returns:
        ``acc`` (6,) = (dw [rad/s^2], a [m/s^2]) or ``(acc, Jacobians)`` where ``x`` (6x12) and
        ``wrench`` (6x6) are the derivatives of ``acc`` (implicit function theorem).

    Raises:
        ModelError: when the system is singular (mass or inertia not positive).
    """
    acc = np.empty(6)
    Jx = np.empty((6, 12))
    Jw = np.empty((6, 6))
    ok = core.forward_dynamics(_f(R), _state(t, w, v, np.zeros(3), np.zeros(3)), _f(wrench_c), float(inp.m),
                               *_inputs(inp), float(g), acc, Jx, Jw)
    if not ok:
        raise ModelError(f"Newton-Euler system is singular (mass {inp.m} kg): check the mass and inertia inputs, "
                         "expected a positive mass and a positive definite inertia about the CoM")
    if not jacobian:
        return acc
    return acc, Jacobians(x=Jx, wrench=Jw)


# ----------------------------------------------------------------------------------------------
# IMU, eq. (26)-(28)
# ----------------------------------------------------------------------------------------------


def imu_readings(R, t, w, v, dw, a, imu: ImuPlacement, g: float = GRAVITY, jacobian: bool = False):
    r"""Gyrometer and accelerometer readings in the IMU frame, eq. (26)-(28), correction 6.

    ::

        y_g = R_a^T (R^T w + w_g,l)                                                  (26)
        y_a = R_a^T ([R^T dw]x p + [R^T w]x^2 p + 2 [R^T w]x dp + ddp + R^T (a + g e_z))  (28)

    Returns:
        ``y`` (6,) = (gyro [rad/s], accelerometer [m/s^2]) or ``(y, Jacobians)`` with ``x`` (6x12)
        and ``acc`` (6x6).
    """
    r = np.empty(6)
    J = np.empty((6, core.STATE_DIM))
    core.imu(_f(R), _state(t, w, v, dw, a), np.zeros(6), _f(imu.R), _f(imu.p), _f(imu.v), _f(imu.a), _f(imu.w),
             float(g), r, J)
    if not jacobian:
        return r
    return r, Jacobians(x=J[:, :12].copy(), acc=J[:, 12:].copy())


# ----------------------------------------------------------------------------------------------
# Centre of pressure
# ----------------------------------------------------------------------------------------------


COP_MIN_FORCE = 1e-6
"""Vertical force (N) at or below which the centre of pressure is undefined (NaN)."""


def center_of_pressure(wrench, z0: float = 0.0, jacobian: bool = False, min_force: float = COP_MIN_FORCE):
    r"""Centre of pressure on the horizontal plane ``z = z0`` from the total contact wrench.

    For a wrench (F, T) with T about the world origin, the point p = (px, py, z0) where the
    moment is purely vertical: ``px = (z0 F_x - T_y) / F_z``, ``py = (T_x + z0 F_y) / F_z``.

    Returns:
        ``p`` (3,) in m or ``(p, J)`` with ``J`` the 3x6 Jacobian with respect to (F, T).  When the
        vertical force is below ``min_force`` (N) the CoP is undefined and NaN is returned.
    """
    p = np.empty(3)
    J = np.empty((3, 6))
    core.center_of_pressure(_f(wrench), float(z0), float(min_force), p, J)
    return (p, J) if jacobian else p


def wrench_about(wrench, point):
    """Move a wrench (F, T about the world origin) to be expressed about ``point``: (F, T - p x F)."""
    F = wrench[..., :3]
    T = wrench[..., 3:]
    return np.concatenate([F, T - np.cross(point, F)], axis=-1)


def about_com(c: np.ndarray, r: np.ndarray, J: np.ndarray | None = None):
    """The Newton-Euler residual ``r`` (..., 6), a wrench about the world origin, and its Jacobian
    ``J`` (..., 6, D) taken about the point ``c`` (..., 3): the CoM's coordinates in the local frame
    at that step, a known point within the flexibility's displacement of the CoM.

    Why: the model's unexplained wrench is an unmodelled force on the robot and a moment about its
    CoM.  Taken about the local origin, which the robot walks away from (a metre on the 12 s iCub
    walk), a force error becomes a moment error that grows with the distance, and the residual's
    fixed covariance (computed at the first sample) no longer describes it: the smoothers' forces
    then depended on where the local frame's origin lies (docs/smoother.md, "Noise")."""
    r = wrench_about(np.asarray(r, dtype=float), c)
    if J is None:
        return r
    J = np.array(J, dtype=float, copy=True)
    cc = np.broadcast_to(np.asarray(c, dtype=float)[..., :, None], J[..., :3, :].shape)
    J[..., 3:, :] -= np.cross(cc, J[..., :3, :], axisa=-2, axisb=-2, axisc=-2)
    return r, J
