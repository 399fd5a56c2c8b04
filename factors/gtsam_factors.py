r"""GTSAM factors of the flexible-contact model, one per physical law (DESIGN.md, "The factor graph").

Variables of step ``k`` (keys from :func:`X`, :func:`V`, :func:`A`, :func:`W`):

- ``X(k)``: ``gtsam.Pose3`` flexibility ``(R, t)`` local -> world;
- ``V(k)``: ``Vector6`` ``(w, v)`` world-frame angular (rad/s) and linear (m/s) velocity;
- ``A(k)``: ``Vector6`` ``(dw, a)`` their derivatives (rad/s^2, m/s^2);
- ``W(k, i)``: ``Vector6`` wrench ``(F, T)`` of contact ``i`` (N, N m about the world origin),
  only while the contact is active;
- ``E(k, j)``: ``Vector`` of ``dim`` values of the ``j``-th enabled effect (the order of
  ``ModelConfig.effects``; units of the effect's ``labels``).

Effects (the :class:`~flexforce.factors.effects.Effect` protocol) enter generically: a family
factor built with ``effects=EffectTerms(...)`` adds each listed effect's ``residual_terms`` to its
unwhitened residual (with the effect's key among the factor's keys), and the effects' own factors
are :func:`effect_prior_factor`, :func:`effect_walk_factor`, :func:`effect_level_factor` and
:func:`effect_own_factor`.  An effect's term may not depend on the contact wrenches (the protocol
gives no Jacobian with respect to them): the contact and IMU factors pass it zero wrenches apart
from the factor's own.

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
from flexforce.factors.physics import about_com

MAX_CONTACTS = 64
"""Contacts per step addressable by :func:`W`."""
MAX_EFFECTS = 64
"""Effects per step addressable by :func:`E`."""


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


def E(k: int, j: int) -> int:
    """Key of the values of the ``j``-th enabled effect at step ``k``."""
    return gtsam.symbol("e", k * MAX_EFFECTS + j)


class EffectTerms:
    """The effects that add a term to one family's residual at one step (inside a factor).

    ``problem`` is the :class:`~flexforce.factors.effects.ProblemView` the effects read, ``k`` the
    step, ``effects`` the ``(j, effect)`` pairs (``j`` its index in ``ModelConfig.effects``, for
    :func:`E`), ``nc`` the number of contacts.
    """

    def __init__(self, problem, k: int, effects, nc: int):
        self.problem = problem
        self.k = int(k)
        self.effects = list(effects)
        self.steps = np.array([self.k])
        self.W = np.zeros((1, int(nc), 6))

    def keys(self) -> list[int]:
        return [E(self.k, j) for j, _ in self.effects]

    def add(self, family: str, values, R, q, r, J, contact: int | None = None) -> list[np.ndarray]:
        """Add the terms to ``r`` (6,) and to ``J`` (6, 18) (world increments); return the
        Jacobians with respect to the effects' keys, in order."""
        out = []
        Rn, qn = R[None], q[None]
        for j, eff in self.effects:
            ev = np.asarray(values.atVector(E(self.k, j)), dtype=float)[None]
            terms = eff.residual_terms(family, self.problem, self.steps, Rn, qn, self.W, ev)
            if terms is None:  # not this family at this step: no term, zero Jacobian
                out.append(np.zeros((6, ev.shape[1])))
                continue
            dr, dr_ds, dr_de = (np.asarray(x, dtype=float) for x in terms)
            if contact is not None:
                dr, dr_ds, dr_de = dr[:, contact], dr_ds[:, contact], dr_de[:, contact]
            r += dr[0]
            J[:, :18] += dr_ds[0]
            out.append(dr_de[0].copy())
        return out


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
                        g: float, effects: EffectTerms | None = None) -> gtsam.CustomFactor:
    """Newton-Euler (eq. 16, 23) on ``X, V, A, W_i`` (active contacts) and the effects' keys:
    required wrench minus the contact wrenches, i.e. the unexplained external wrench (N, N m about
    the step's CoM point, :func:`flexforce.factors.physics.about_com`), plus the effects' terms."""
    nw = len(contacts)
    keys = [X(k), V(k), A(k)] + [W(k, i) for i in contacts] + (effects.keys() if effects else [])
    c, dc, ddc, sig, dsig = (np.ascontiguousarray(x, dtype=float) for x in (c, dc, ddc, sig, dsig))
    I, dI = np.ascontiguousarray(I, dtype=float), np.ascontiguousarray(dI, dtype=float)
    r = np.empty(6)
    J = np.empty((6, 18))
    neg = about_com(c, np.zeros(6), -np.eye(6))[1]  # d r / d W_i, about the CoM point

    def error(this, values, H):
        R, q = _state(values, keys[0], keys[1], keys[2])
        Wsum = np.zeros(6)
        for i, key in zip(contacts, keys[3:3 + nw]):
            w = values.atVector(key)
            Wsum += w
            if effects:
                effects.W[0, i] = w
        core.newton_euler(R, q, Wsum, m, c, dc, ddc, I, dI, sig, dsig, g, r, J)
        He = effects.add("newton_euler", values, R, q, r, J) if effects else []
        # about the step's CoM point, as the smoothers' Newton-Euler factor (physics.about_com)
        rc, Jc = about_com(c, r, J)
        r[:], J[:] = rc, Jc
        He = [about_com(c, np.zeros(6), Hj)[1] for Hj in He]
        if H is not None:
            H[0] = _pose_block(J, R)
            H[1] = J[:, 6:12].copy()
            H[2] = J[:, 12:18].copy()
            for j in range(3, 3 + nw):
                H[j] = neg
            for j, Hj in enumerate(He):
                H[3 + nw + j] = Hj
        return r.copy()

    return gtsam.CustomFactor(noise, gtsam.KeyVector(keys), error)


def contact_factor(noise, k: int, i: int, p_l, R_l, params, p_r=None, R_r=None,
                   effects: EffectTerms | None = None) -> gtsam.CustomFactor:
    """Contact law (eq. 6-12) on ``X, V, W_i`` and the effects' keys: spring-damper wrench minus
    ``W_i`` (N, N m), plus the effects' terms for contact ``i``.

    ``p_l, R_l``: the contact's placement in the local frame; ``p_r, R_r``: its rest placement in
    the world (foothold), default ``p_l, R_l``.
    """
    keys = [X(k), V(k), W(k, i)] + (effects.keys() if effects else [])
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
        w = values.atVector(keys[2])
        core.contact_law(R, q, w, p_l, R_l, p_r, R_r, Ks[0], Ks[1], Ks[2], Ks[3], bf, bt, iso, r, J, no_rest_jac)
        He = []
        if effects:
            effects.W[0, i] = w
            He = effects.add("contact", values, R, q, r, J, contact=i)
        if H is not None:
            H[0] = _pose_block(J, R)
            H[1] = J[:, 6:12].copy()
            H[2] = neg
            for j, Hj in enumerate(He):
                H[3 + j] = Hj
        return r.copy()

    return gtsam.CustomFactor(noise, gtsam.KeyVector(keys), error)


def imu_factor(noise, k: int, y, Ra, p, pv, pa, pw, g: float, effects: EffectTerms | None = None,
               use=None) -> gtsam.CustomFactor:
    """IMU (eq. 26-28) on ``X, V, A`` and the effects' keys: predicted minus read gyro (rad/s) and
    accelerometer (m/s^2), plus the effects' terms.  ``use`` (6,): 0 for an axis whose reading is
    missing or saturated (its row is zero), default all 1."""
    keys = [X(k), V(k), A(k)] + (effects.keys() if effects else [])
    y, Ra, p, pv, pa, pw = (np.ascontiguousarray(x, dtype=float) for x in (y, Ra, p, pv, pa, pw))
    mask = None if use is None or np.all(np.asarray(use) == 1.0) else np.asarray(use, dtype=float)
    r = np.empty(6)
    J = np.empty((6, 18))

    def error(this, values, H):
        R, q = _state(values, keys[0], keys[1], keys[2])
        core.imu(R, q, y, Ra, p, pv, pa, pw, g, r, J)
        He = effects.add("imu", values, R, q, r, J) if effects else []
        if mask is not None:
            r[:] *= mask
            J[:] *= mask[:, None]
            He = [Hj * mask[:, None] for Hj in He]
        if H is not None:
            H[0] = _pose_block(J, R)
            H[1] = J[:, 6:12].copy()
            H[2] = J[:, 12:18].copy()
            for j, Hj in enumerate(He):
                H[3 + j] = Hj
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


def effect_prior_factor(j: int, mean, sigma, k: int = 0) -> gtsam.PriorFactorVector:
    """Prior of the ``j``-th effect at step ``k`` (the first step): ``mean``, ``sigma`` (dim,)."""
    return gtsam.PriorFactorVector(E(k, j), np.asarray(mean, dtype=float),
                                   gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigma, dtype=float)))


def effect_level_factor(j: int, k: int, mean, sigma) -> gtsam.PriorFactorVector:
    """The effect's optional prior at every step (``step_prior_sigma``): same as a prior at ``k``."""
    return effect_prior_factor(j, mean, sigma, k)


def effect_walk_factor(j: int, k: int, sigma) -> gtsam.BetweenFactorVector:
    """Random walk of the ``j``-th effect from step ``k`` to ``k + 1``: ``e_k+1 - e_k`` with
    ``sigma`` (dim,)."""
    sigma = np.asarray(sigma, dtype=float)
    return gtsam.BetweenFactorVector(E(k, j), E(k + 1, j), np.zeros(sigma.shape[0]),
                                     gtsam.noiseModel.Diagonal.Sigmas(sigma))


def effect_own_factor(problem, effect, j: int, k: int, name: str, rows: int) -> gtsam.CustomFactor:
    """One of an effect's own factors (its optional ``factors(problem, steps, R, q, e)``) at step
    ``k`` on ``X, V, A, E(k, j)``: ``name`` is its key in the returned dict, ``rows`` its residual
    size.  The residual is already whitened (unit noise) and multiplied by the factor's 0/1 weight."""
    keys = [X(k), V(k), A(k), E(k, j)]
    steps = np.array([int(k)])
    noise = gtsam.noiseModel.Unit.Create(int(rows))

    def error(this, values, H):
        R, q = _state(values, keys[0], keys[1], keys[2])
        ev = np.asarray(values.atVector(keys[3]), dtype=float)[None]
        r, dr_ds, dr_de, weight = effect.factors(problem, steps, R[None], q[None], ev)[name]
        w = float(np.asarray(weight, dtype=float)[0])
        Js = np.asarray(dr_ds, dtype=float)[0] * w
        if H is not None:
            H[0] = _pose_block(Js, R)
            H[1] = Js[:, 6:12].copy()
            H[2] = Js[:, 12:18].copy()
            H[3] = np.asarray(dr_de, dtype=float)[0] * w
        return np.asarray(r, dtype=float)[0] * w

    return gtsam.CustomFactor(noise, gtsam.KeyVector(keys), error)


def insert_state(values, k: int, R, q, wrenches=None, contacts=(), effects=None):
    """Insert step ``k``'s variables into ``values`` (``wrenches`` (C, 6) for the listed contacts;
    ``effects``: one (dim,) array per enabled effect)."""
    values.insert(X(k), gtsam.Pose3(gtsam.Rot3(R), np.asarray(q[0:3], dtype=float)))
    values.insert(V(k), np.asarray(q[3:9], dtype=float))
    values.insert(A(k), np.asarray(q[9:15], dtype=float))
    for i in contacts:
        values.insert(W(k, i), np.asarray(wrenches[i], dtype=float))
    for j, e in enumerate(effects or ()):
        values.insert(E(k, j), np.asarray(e, dtype=float))
