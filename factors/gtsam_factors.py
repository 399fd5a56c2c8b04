r"""GTSAM factors of the flexible-contact model, one per physical law (DESIGN.md, "The factor graph").

Variables of step ``k`` (keys from :func:`X`, :func:`V`, :func:`A`, :func:`W`):

- ``X(k)``: ``gtsam.Pose3`` flexibility ``(R, t)`` local -> world;
- ``V(k)``: ``Vector6`` ``(w, v)`` world-frame angular (rad/s) and linear (m/s) velocity;
- ``A(k)``: ``Vector6`` ``(dw, a)`` their derivatives (rad/s^2, m/s^2);
- ``W(k, i)``: ``Vector6`` wrench ``(F, T)`` of contact ``i`` (N, N m about the world origin),
  only while the contact is active.

Every factor is a ``gtsam.CustomFactor`` whose arithmetic is a compiled kernel of
:mod:`flexforce.factors.core` (Jacobians with respect to world-frame increments).  GTSAM's
``Pose3`` tangent is ``(d_phi, d_rho)`` in the body frame, rotation first, with
``d_theta = R d_phi`` and ``d_t = R d_rho`` (physics.py's docstring), so the pose block of a
Jacobian is ``[J_theta R, J_t R]``; the vector variables are in world axes already.
"""

from __future__ import annotations

import gtsam
import numpy as np

from flexforce.factors import core

MAX_CONTACTS = 64
"""Contacts per step addressable by :func:`W`."""


def X(k: int) -> int:
    """Key of the flexibility pose at step ``k``."""
    return gtsam.symbol("x", k)


def V(k: int) -> int:
    """Key of the velocity ``(w, v)`` at step ``k``."""
    return gtsam.symbol("v", k)


def A(k: int) -> int:
    """Key of the acceleration ``(dw, a)`` at step ``k``."""
    return gtsam.symbol("a", k)


def W(k: int, i: int) -> int:
    """Key of the wrench of contact ``i`` at step ``k``."""
    return gtsam.symbol("w", k * MAX_CONTACTS + i)


def _state(values, k_x, k_v, k_a):
    pose = values.atPose3(k_x)
    R = pose.rotation().matrix()
    q = np.empty(15)
    q[0:3] = pose.translation()
    q[3:9] = values.atVector(k_v)
    if k_a is not None:
        q[9:15] = values.atVector(k_a)
    else:
        q[9:15] = 0.0
    return R, q


def _pose_block(J, R):
    """Pose3 tangent block ``[J_theta R, J_t R]`` of a world-increment Jacobian ``J`` (m, 18)."""
    out = np.empty((J.shape[0], 6))
    out[:, 0:3] = J[:, 0:3] @ R
    out[:, 3:6] = J[:, 3:6] @ R
    return out


def newton_euler_factor(noise, k: int, contacts: list[int], m: float, c, dc, ddc, I, dI, sig, dsig,
                        g: float) -> gtsam.CustomFactor:
    """Newton-Euler (eq. 16, 23) on ``X, V, A, W_i`` (active contacts): required wrench minus the
    contact wrenches, i.e. the unexplained external wrench (N, N m about the world origin)."""
    keys = [X(k), V(k), A(k)] + [W(k, i) for i in contacts]
    c, dc, ddc, sig, dsig = (np.ascontiguousarray(x, dtype=float) for x in (c, dc, ddc, sig, dsig))
    I, dI = np.ascontiguousarray(I, dtype=float), np.ascontiguousarray(dI, dtype=float)
    r = np.empty(6)
    J = np.empty((6, 18))
    neg = -np.eye(6)

    def error(this, values, H):
        R, q = _state(values, keys[0], keys[1], keys[2])
        Wsum = np.zeros(6)
        for key in keys[3:]:
            Wsum += values.atVector(key)
        core.newton_euler(R, q, Wsum, m, c, dc, ddc, I, dI, sig, dsig, g, r, J)
        if H is not None:
            H[0] = _pose_block(J, R)
            H[1] = J[:, 6:12].copy()
            H[2] = J[:, 12:18].copy()
            for j in range(3, len(keys)):
                H[j] = neg
        return r.copy()

    return gtsam.CustomFactor(noise, gtsam.KeyVector(keys), error)


def contact_factor(noise, k: int, i: int, p_l, R_l, params, p_r=None, R_r=None) -> gtsam.CustomFactor:
    """Contact law (eq. 6-12) on ``X, V, W_i``: spring-damper wrench minus ``W_i`` (N, N m).

    ``p_l, R_l``: the contact's placement in the local frame; ``p_r, R_r``: its rest placement in
    the world (foothold), default ``p_l, R_l``.
    """
    keys = [X(k), V(k), W(k, i)]
    p_l = np.ascontiguousarray(p_l, dtype=float)
    R_l = np.ascontiguousarray(R_l, dtype=float)
    p_r = p_l if p_r is None else np.ascontiguousarray(p_r, dtype=float)
    R_r = R_l if R_r is None else np.ascontiguousarray(R_r, dtype=float)
    no_rest_jac = np.empty((0, 6))
    Ks = [np.ascontiguousarray(K, dtype=float) for K in (params.K_fs, params.K_fd, params.K_ts, params.K_td)]
    bf, bt, iso = float(params.beta_f), float(params.beta_t), bool(params.isotropic)
    r = np.empty(6)
    J = np.empty((6, 18))
    neg = -np.eye(6)

    def error(this, values, H):
        R, q = _state(values, keys[0], keys[1], None)
        core.contact_law(R, q, values.atVector(keys[2]), p_l, R_l, p_r, R_r, Ks[0], Ks[1], Ks[2], Ks[3], bf, bt, iso,
                         r, J, no_rest_jac)
        if H is not None:
            H[0] = _pose_block(J, R)
            H[1] = J[:, 6:12].copy()
            H[2] = neg
        return r.copy()

    return gtsam.CustomFactor(noise, gtsam.KeyVector(keys), error)


def imu_factor(noise, k: int, y, Ra, p, pv, pa, pw, g: float) -> gtsam.CustomFactor:
    """IMU (eq. 26-28) on ``X, V, A``: predicted minus read gyro (rad/s) and accelerometer (m/s^2)."""
    keys = [X(k), V(k), A(k)]
    y, Ra, p, pv, pa, pw = (np.ascontiguousarray(x, dtype=float) for x in (y, Ra, p, pv, pa, pw))
    r = np.empty(6)
    J = np.empty((6, 18))

    def error(this, values, H):
        R, q = _state(values, keys[0], keys[1], keys[2])
        core.imu(R, q, y, Ra, p, pv, pa, pw, g, r, J)
        if H is not None:
            H[0] = _pose_block(J, R)
            H[1] = J[:, 6:12].copy()
            H[2] = J[:, 12:18].copy()
        return r.copy()

    return gtsam.CustomFactor(noise, gtsam.KeyVector(keys), error)


def integration_factor(noise, k: int, dt: float) -> gtsam.CustomFactor:
    """Integration on ``X, V, A`` of steps ``k`` and ``k+1`` (12 rows: rad, m, rad/s, m/s)."""
    keys = [X(k), V(k), A(k), X(k + 1), V(k + 1), A(k + 1)]
    r = np.empty(12)
    J0 = np.empty((12, 18))
    J1 = np.empty((12, 18))

    def error(this, values, H):
        R0, q0 = _state(values, keys[0], keys[1], keys[2])
        R1, q1 = _state(values, keys[3], keys[4], keys[5])
        core.integration(R0, q0, R1, q1, dt, r, J0, J1)
        if H is not None:
            H[0] = _pose_block(J0, R0)
            H[1] = J0[:, 6:12].copy()
            H[2] = J0[:, 12:18].copy()
            H[3] = _pose_block(J1, R1)
            H[4] = J1[:, 6:12].copy()
            H[5] = J1[:, 12:18].copy()
        return r.copy()

    return gtsam.CustomFactor(noise, gtsam.KeyVector(keys), error)


def ft_factor(noise, k: int, i: int, p_l, R_l, y) -> gtsam.CustomFactor:
    """F/T reading of contact ``i`` on ``X, W_i``: predicted minus read wrench in the contact frame
    about its origin (N, N m); NaN components are not measured (zero rows)."""
    keys = [X(k), W(k, i)]
    p_l, R_l, y = (np.ascontiguousarray(x, dtype=float) for x in (p_l, R_l, y))
    r = np.empty(6)
    Js = np.empty((6, 18))
    JW = np.empty((6, 6))
    q = np.zeros(15)

    def error(this, values, H):
        pose = values.atPose3(keys[0])
        R = pose.rotation().matrix()
        q[0:3] = pose.translation()
        core.ft(R, q, values.atVector(keys[1]), p_l, R_l, y, r, Js, JW)
        if H is not None:
            H[0] = _pose_block(Js, R)
            H[1] = JW.copy()
        return r.copy()

    return gtsam.CustomFactor(noise, gtsam.KeyVector(keys), error)


def state_prior_factors(k: int, R, q, sigmas) -> list:
    """Priors on ``X(k)``, ``V(k)``, ``A(k)`` around ``(R, q)`` with sigmas (18,) in world increments.

    The pose sigma is given for ``(theta, t)``; it is isotropic per block in the module's use, so
    the body-frame tangent sees the same sigmas.
    """
    sigmas = np.asarray(sigmas, dtype=float)
    pose = gtsam.Pose3(gtsam.Rot3(R), q[0:3])
    return [
        gtsam.PriorFactorPose3(X(k), pose, gtsam.noiseModel.Diagonal.Sigmas(sigmas[0:6])),
        gtsam.PriorFactorVector(V(k), q[3:9], gtsam.noiseModel.Diagonal.Sigmas(sigmas[6:12])),
        gtsam.PriorFactorVector(A(k), q[9:15], gtsam.noiseModel.Diagonal.Sigmas(sigmas[12:18])),
    ]


def insert_state(values, k: int, R, q, wrenches=None, contacts=()):
    """Insert step ``k``'s variables into ``values`` (``wrenches`` (C, 6) for the listed contacts)."""
    values.insert(X(k), gtsam.Pose3(gtsam.Rot3(R), np.asarray(q[0:3], dtype=float)))
    values.insert(V(k), np.asarray(q[3:9], dtype=float))
    values.insert(A(k), np.asarray(q[9:15], dtype=float))
    for i in contacts:
        values.insert(W(k, i), np.asarray(wrenches[i], dtype=float))
