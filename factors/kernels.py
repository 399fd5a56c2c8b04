r"""Compiled residuals and analytic Jacobians of the factor families, one step or all steps at once.

The arithmetic of :mod:`flexforce.factors.physics` restated for speed (numba): the same equations,
the same world-frame increment convention, checked against physics.py entry by entry in
``tests/test_factors.py``.  The smoothers call nothing else when they linearise, so a Python
``gtsam.CustomFactor`` costs its ~6 us of binding overhead plus a few us of arithmetic instead of
the ~100 us of the readable numpy version (measured: ``benchmarks/smoother_speed.py``).

State of one step (the columns of every ``J`` below, world-frame increments, rotation first)::

    s = (theta, t, w, v, dw, a)        18 components: rad, m, rad/s, m/s, rad/s^2, m/s^2

passed as ``R`` (3x3, local to world) and ``q = (t, w, v, dw, a)`` (15,).  A wrench is
``(F, T)`` (N, N m about the world origin), world axes.

Families (residual = model minus measurement or minus variable):

- :func:`contact_law`: ``r = f(R, t, w, v) - W_i`` (eq. 6-12, corrections 1, 2, 5), 6 rows;
  ``dr/dW_i = -I``.
- :func:`newton_euler`: ``r = required_wrench(R, t, w, v, dw, a) - sum_i W_i`` (eq. 16, 23), 6
  rows; ``dr/dW_i = -I``.
- :func:`imu`: ``r = h(R, w, dw, a) - y`` (eq. 26-28, correction 6), 6 rows.
- :func:`integration`: kinematic consistency of two successive steps with the acceleration linear
  in time over the step (exact for constant jerk), 12 rows ``(theta, t, w, v)``::

      r_theta = log(R1 R0^T) - (T w0 + T^2/6 (2 dw0 + dw1))
      r_t     = t1 - t0 - (T v0 + T^2/6 (2 a0 + a1))
      r_w     = w1 - w0 - T/2 (dw0 + dw1)
      r_v     = v1 - v0 - T/2 (a0 + a1)

  (the rotation line neglects the commutator ``w x dw T^3/12``, below 1e-9 rad here).
- :func:`ft`: F/T reading predicted from the contact wrench: ``r = (R_c^T F, R_c^T (T - p_c x F))
  - y`` with ``R_c = R local_R_c`` and ``p_c = R local_p_c + t`` (the sensor frame moves with the
  flexibility), 6 rows; Jacobians with respect to the state and to ``W_i``.
"""

from __future__ import annotations

import math

import numpy as np

try:  # pragma: no cover - exercised by whichever branch the machine has
    import numba

    def njit(fn):
        return numba.njit(cache=True, nogil=True)(fn)

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    # Same code, interpreted: correct but ~100x slower (the speed targets need numba).
    def njit(fn):
        return fn

    HAVE_NUMBA = False

STATE_DIM = 18
"""Columns of a per-step Jacobian: (theta, t, w, v, dw, a)."""


# ----------------------------------------------------------------------------------------------
# 3-vector and 3x3 helpers (explicit loops: numba's BLAS path costs ~0.3 us per 3x3 product)
# ----------------------------------------------------------------------------------------------


@njit
def _skew(v):
    S = np.zeros((3, 3))
    S[0, 1] = -v[2]
    S[0, 2] = v[1]
    S[1, 0] = v[2]
    S[1, 2] = -v[0]
    S[2, 0] = -v[1]
    S[2, 1] = v[0]
    return S


@njit
def _cross(a, b):
    out = np.empty(3)
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]
    return out


@njit
def _mm(A, B):
    C = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            C[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
    return C


@njit
def _mmt(A, B):
    """A B^T."""
    C = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            C[i, j] = A[i, 0] * B[j, 0] + A[i, 1] * B[j, 1] + A[i, 2] * B[j, 2]
    return C


@njit
def _mtm(A, B):
    """A^T B."""
    C = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            C[i, j] = A[0, i] * B[0, j] + A[1, i] * B[1, j] + A[2, i] * B[2, j]
    return C


@njit
def _mv(A, x):
    out = np.empty(3)
    for i in range(3):
        out[i] = A[i, 0] * x[0] + A[i, 1] * x[1] + A[i, 2] * x[2]
    return out


@njit
def _mtv(A, x):
    out = np.empty(3)
    for i in range(3):
        out[i] = A[0, i] * x[0] + A[1, i] * x[1] + A[2, i] * x[2]
    return out


@njit
def _outer(a, b):
    C = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            C[i, j] = a[i] * b[j]
    return C


@njit
def so3_exp(phi):
    """Rodrigues' formula (as :func:`flexforce.factors.so3.exp`)."""
    th2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    K = _skew(phi)
    KK = _mm(K, K)
    if th2 < 1e-16:
        a, b = 1.0, 0.5
    else:
        th = math.sqrt(th2)
        a = math.sin(th) / th
        b = (1.0 - math.cos(th)) / th2
    R = np.eye(3) + a * K + b * KK
    return R


@njit
def so3_log(R):
    """Rotation vector of ``R`` (as :func:`flexforce.factors.so3.log`, accurate up to pi)."""
    w = np.empty(3)
    w[0] = R[2, 1] - R[1, 2]
    w[1] = R[0, 2] - R[2, 0]
    w[2] = R[1, 0] - R[0, 1]
    cos_t = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    sin_t = 0.5 * math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    theta = math.atan2(sin_t, cos_t)
    if cos_t > -0.9:
        if sin_t < 1e-8:
            return 0.5 * (1.0 + sin_t * sin_t / 6.0) * w
        return (0.5 * theta / sin_t) * w
    S = 0.5 * (R + R.T)
    for i in range(3):
        S[i, i] -= cos_t
    k = 0
    if S[1, 1] > S[k, k]:
        k = 1
    if S[2, 2] > S[k, k]:
        k = 2
    axis = S[:, k].copy()
    if axis[0] * w[0] + axis[1] * w[1] + axis[2] * w[2] < 0.0:
        axis = -axis
    return (theta / math.sqrt(axis[0] ** 2 + axis[1] ** 2 + axis[2] ** 2)) * axis


@njit
def so3_jl_inv(phi):
    """``J_l(phi)^-1`` (as :func:`flexforce.factors.so3.left_jacobian_inverse`)."""
    th2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    K = _skew(phi)
    if th2 < 1e-2:
        c = 1.0 / 12.0 + th2 * (1.0 / 720.0 + th2 * (1.0 / 30240.0 + th2 / 1209600.0))
    else:
        th = math.sqrt(th2)
        c = 1.0 / th2 - 0.5 / (th * math.tan(0.5 * th))
    return np.eye(3) - 0.5 * K + c * _mm(K, K)


# ----------------------------------------------------------------------------------------------
# One step
# ----------------------------------------------------------------------------------------------


@njit
def contact_law(R, q, W, p_l, R_l, Kfs, Kfd, Kts, Ktd, beta_f, beta_t, iso, r, J):
    """Contact-law residual ``f(R, t, w, v) - W`` into ``r`` (6,) and ``dr/ds`` into ``J`` (6, 18).

    ``f`` is :func:`flexforce.factors.physics.contact_wrench` (eq. 6-12); the stiffness and
    damping matrices are in the contact frame (rotated into the world unless ``iso``).
    """
    t = q[0:3]
    w = q[3:6]
    v = q[6:9]
    Rp = _mv(R, p_l)
    s = Rp + t - p_l
    ds = _cross(w, Rp) + v
    Om = so3_log(R)
    if not iso:
        Rc = _mm(R, R_l)
        Kfs = _mmt(_mm(Rc, Kfs), Rc)
        Kfd = _mmt(_mm(Rc, Kfd), Rc)
        Kts = _mmt(_mm(Rc, Kts), Rc)
        Ktd = _mmt(_mm(Rc, Ktd), Rc)
    gf = 1.0 + beta_f * (s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
    gt = 1.0 + beta_t * (Om[0] * Om[0] + Om[1] * Om[1] + Om[2] * Om[2])
    ss = s * gf
    OO = Om * gt
    F = -_mv(Kfs, ss) - _mv(Kfd, ds)
    p_w = Rp + t
    T = -_mv(Kts, OO) - _mv(Ktd, w) + _cross(p_w, F)
    for i in range(3):
        r[i] = F[i] - W[i]
        r[3 + i] = T[i] - W[3 + i]
    I3 = np.eye(3)
    Ds = gf * I3 + 2.0 * beta_f * _outer(s, s)
    DO = gt * I3 + 2.0 * beta_t * _outer(Om, Om)
    S_Rp = _skew(Rp)
    dF_dth = _mm(_mm(Kfs, Ds), S_Rp) + _mm(_mm(Kfd, _skew(w)), S_Rp)
    dT0_dth = -_mm(_mm(Kts, DO), so3_jl_inv(Om))
    if not iso:
        dF_dth += (_skew(_mv(Kfs, ss)) - _mm(Kfs, _skew(ss)) + _skew(_mv(Kfd, ds)) - _mm(Kfd, _skew(ds)))
        dT0_dth += (_skew(_mv(Kts, OO)) - _mm(Kts, _skew(OO)) + _skew(_mv(Ktd, w)) - _mm(Ktd, _skew(w)))
    dF_dt = -_mm(Kfs, Ds)
    dF_dw = _mm(Kfd, S_Rp)
    S_pw = _skew(p_w)
    S_F = _skew(F)
    J[:, :] = 0.0
    J[0:3, 0:3] = dF_dth
    J[0:3, 3:6] = dF_dt
    J[0:3, 6:9] = dF_dw
    J[0:3, 9:12] = -Kfd
    J[3:6, 0:3] = dT0_dth + _mm(S_F, S_Rp) + _mm(S_pw, dF_dth)
    J[3:6, 3:6] = -S_F + _mm(S_pw, dF_dt)
    J[3:6, 6:9] = -Ktd + _mm(S_pw, dF_dw)
    J[3:6, 9:12] = -_mm(S_pw, Kfd)


@njit
def newton_euler(R, q, Wsum, m, c, dc, ddc, I, dI, sig, dsig, g, r, J):
    """Newton-Euler residual ``required_wrench - Wsum`` into ``r`` (6,), ``dr/ds`` into ``J`` (6, 18).

    ``required_wrench`` is :func:`flexforce.factors.physics.required_wrench` (eq. 15-16, 22-23).
    """
    t = q[0:3]
    w = q[3:6]
    dw = q[9:12]
    a = q[12:15]
    Rc = _mv(R, c)
    Rdc = _mv(R, dc)
    Rddc = _mv(R, ddc)
    RIRt = _mmt(_mm(R, I), R)
    RdIRt = _mmt(_mm(R, dI), R)
    Rs = _mv(R, sig)
    Rds = _mv(R, dsig)
    ag = a.copy()
    ag[2] += g
    w_Rc = _cross(w, Rc)
    F = m * (_cross(dw, Rc) + _cross(w, w_Rc) + 2.0 * _cross(w, Rdc) + Rddc + ag)
    Iw = _mv(RIRt, w)
    T = (_cross(w, Iw) + _mv(RdIRt, w) + _mv(RIRt, dw) + _cross(w, Rs) + Rds
         + _cross(t, F) + m * _cross(Rc, ag))
    for i in range(3):
        r[i] = F[i] - Wsum[i]
        r[3 + i] = T[i] - Wsum[3 + i]
    Sw = _skew(w)
    S_Rc = _skew(Rc)
    S_t = _skew(t)
    dF_dth = m * (-_mm(_skew(dw), S_Rc) - _mm(_mm(Sw, Sw), S_Rc) - 2.0 * _mm(Sw, _skew(Rdc)) - _skew(Rddc))
    dF_dw = m * (-_skew(w_Rc) - _mm(Sw, S_Rc) - 2.0 * _skew(Rdc))
    dIw_dth = -_skew(Iw) + _mm(RIRt, Sw)
    dT_dth = (_mm(Sw, dIw_dth) - _skew(_mv(RdIRt, w)) + _mm(RdIRt, Sw)
              - _skew(_mv(RIRt, dw)) + _mm(RIRt, _skew(dw))
              - _mm(Sw, _skew(Rs)) - _skew(Rds)
              + _mm(S_t, dF_dth) + m * _mm(_skew(ag), S_Rc))
    J[:, :] = 0.0
    J[0:3, 0:3] = dF_dth
    J[0:3, 6:9] = dF_dw
    J[0:3, 12:15] = -m * S_Rc
    for i in range(3):
        J[i, 15 + i] = m
    J[3:6, 0:3] = dT_dth
    J[3:6, 3:6] = -_skew(F)
    J[3:6, 6:9] = -_skew(Iw) + _mm(Sw, RIRt) + RdIRt - _skew(Rs) + _mm(S_t, dF_dw)
    J[3:6, 12:15] = RIRt - m * _mm(S_t, S_Rc)
    J[3:6, 15:18] = m * S_t + m * S_Rc


@njit
def imu(R, q, y, Ra, p, pv, pa, pw, g, r, J):
    """IMU residual ``h(s) - y`` (gyro rad/s, accelerometer m/s^2, IMU frame) and ``dr/ds``.

    ``h`` is :func:`flexforce.factors.physics.imu_readings` (eq. 26-28).
    """
    w = q[3:6]
    dw = q[9:12]
    a = q[12:15]
    u = _mtv(R, w)
    ud = _mtv(R, dw)
    ag = a.copy()
    ag[2] += g
    up = _cross(u, p)
    acc_l = _cross(ud, p) + _cross(u, up) + 2.0 * _cross(u, pv) + pa + _mtv(R, ag)
    yg = _mtv(Ra, u + pw)
    ya = _mtv(Ra, acc_l)
    for i in range(3):
        r[i] = yg[i] - y[i]
        r[3 + i] = ya[i] - y[3 + i]
    RaT = Ra.T.copy()
    Rt = R.T.copy()
    du_dth = _mm(Rt, _skew(w))
    dacc_du = -_skew(up) - _mm(_skew(u), _skew(p)) - 2.0 * _skew(pv)
    dacc_dud = -_skew(p)
    J[:, :] = 0.0
    J[0:3, 0:3] = _mm(RaT, du_dth)
    RaTRt = _mm(RaT, Rt)
    J[0:3, 6:9] = RaTRt
    J[3:6, 0:3] = _mm(RaT, _mm(dacc_du, du_dth) + _mm(_mm(dacc_dud, Rt), _skew(dw)) + _mm(Rt, _skew(ag)))
    J[3:6, 6:9] = _mm(_mm(RaT, dacc_du), Rt)
    J[3:6, 12:15] = _mm(_mm(RaT, dacc_dud), Rt)
    J[3:6, 15:18] = RaTRt


@njit
def integration(R0, q0, R1, q1, dt, r, J0, J1):
    """Integration residual (12,) between steps 0 and 1 ``dt`` s apart, and its two (12, 18) Jacobians."""
    h2 = dt * dt / 6.0
    phi = so3_log(_mmt(R1, R0))
    Jinv = so3_jl_inv(phi)
    for i in range(3):
        r[i] = phi[i] - (dt * q0[3 + i] + h2 * (2.0 * q0[9 + i] + q1[9 + i]))
        r[3 + i] = q1[i] - q0[i] - (dt * q0[6 + i] + h2 * (2.0 * q0[12 + i] + q1[12 + i]))
        r[6 + i] = q1[3 + i] - q0[3 + i] - 0.5 * dt * (q0[9 + i] + q1[9 + i])
        r[9 + i] = q1[6 + i] - q0[6 + i] - 0.5 * dt * (q0[12 + i] + q1[12 + i])
    J0[:, :] = 0.0
    J1[:, :] = 0.0
    # log(R1 exp(-d) R0^T...) : d/dtheta0 = -J_l^-1(phi) exp(phi), d/dtheta1 = J_l^-1(phi)
    J0[0:3, 0:3] = -_mm(Jinv, _mmt(R1, R0))
    J1[0:3, 0:3] = Jinv
    for i in range(3):
        J0[i, 6 + i] = -dt
        J0[i, 12 + i] = -2.0 * h2
        J1[i, 12 + i] = -h2
        J0[3 + i, 3 + i] = -1.0
        J1[3 + i, 3 + i] = 1.0
        J0[3 + i, 9 + i] = -dt
        J0[3 + i, 15 + i] = -2.0 * h2
        J1[3 + i, 15 + i] = -h2
        J0[6 + i, 6 + i] = -1.0
        J1[6 + i, 6 + i] = 1.0
        J0[6 + i, 12 + i] = -0.5 * dt
        J1[6 + i, 12 + i] = -0.5 * dt
        J0[9 + i, 9 + i] = -1.0
        J1[9 + i, 9 + i] = 1.0
        J0[9 + i, 15 + i] = -0.5 * dt
        J1[9 + i, 15 + i] = -0.5 * dt


@njit
def ft(R, q, W, p_l, R_l, y, r, Js, JW):
    """F/T residual: predicted minus read wrench in the contact frame about its origin.

    ``Js`` (6, 18) with respect to the state, ``JW`` (6, 6) with respect to ``W = (F, T)``.
    NaN readings give zero rows (the component is not measured).
    """
    t = q[0:3]
    Rc = _mm(R, R_l)
    Rp = _mv(R, p_l)
    p = Rp + t
    F = W[0:3]
    u = W[3:6] - _cross(p, F)
    Fl = _mtv(Rc, F)
    Tl = _mtv(Rc, u)
    RcT = Rc.T.copy()
    S_F = _skew(F)
    Js[:, :] = 0.0
    JW[:, :] = 0.0
    Js[0:3, 0:3] = _mm(RcT, S_F)
    Js[3:6, 0:3] = _mm(RcT, _skew(u) - _mm(S_F, _skew(Rp)))
    Js[3:6, 3:6] = _mm(RcT, S_F)
    JW[0:3, 0:3] = RcT
    JW[3:6, 0:3] = -_mm(RcT, _skew(p))
    JW[3:6, 3:6] = RcT
    for i in range(3):
        r[i] = Fl[i] - y[i]
        r[3 + i] = Tl[i] - y[3 + i]
    for i in range(6):
        if not np.isfinite(y[i]):
            r[i] = 0.0
            Js[i, :] = 0.0
            JW[i, :] = 0.0


# ----------------------------------------------------------------------------------------------
# All steps (batch linearisation)
# ----------------------------------------------------------------------------------------------


@njit
def newton_euler_all(Rs, Q, Wsum, m, c, dc, ddc, I, dI, sig, dsig, g, r, J):
    for k in range(Rs.shape[0]):
        newton_euler(Rs[k], Q[k], Wsum[k], m, c[k], dc[k], ddc[k], I[k], dI[k], sig[k], dsig[k], g, r[k], J[k])


@njit
def contact_all(Rs, Q, W, active, P, PR, Kfs, Kfd, Kts, Ktd, beta, iso, r, J):
    """Per step and contact; an inactive contact gets ``r = -W`` (its wrench held at zero), ``J = 0``."""
    n, nc = active.shape
    for k in range(n):
        for i in range(nc):
            if active[k, i]:
                contact_law(Rs[k], Q[k], W[k, i], P[k, i], PR[k, i], Kfs[i], Kfd[i], Kts[i], Ktd[i],
                            beta[i, 0], beta[i, 1], iso[i], r[k, i], J[k, i])
            else:
                for j in range(6):
                    r[k, i, j] = -W[k, i, j]
                J[k, i, :, :] = 0.0


@njit
def imu_all(Rs, Q, Y, Ra, p, pv, pa, pw, g, r, J):
    for k in range(Rs.shape[0]):
        imu(Rs[k], Q[k], Y[k], Ra[k], p[k], pv[k], pa[k], pw[k], g, r[k], J[k])


@njit
def integration_all(Rs, Q, dt, r, J0, J1):
    for k in range(Rs.shape[0] - 1):
        integration(Rs[k], Q[k], Rs[k + 1], Q[k + 1], dt, r[k], J0[k], J1[k])


@njit
def ft_all(Rs, Q, W, active, P, PR, Y, r, Js, JW):
    n, nc = active.shape
    for k in range(n):
        for i in range(nc):
            if active[k, i]:
                ft(Rs[k], Q[k], W[k, i], P[k, i], PR[k, i], Y[k, i], r[k, i], Js[k, i], JW[k, i])
            else:
                r[k, i, :] = 0.0
                Js[k, i, :, :] = 0.0
                JW[k, i, :, :] = 0.0


@njit
def retract_all(Rs, Q, dS):
    """In place: ``R <- exp(d_theta) R``, ``q <- q + d_q`` for every step (world-frame increments)."""
    for k in range(Rs.shape[0]):
        Rs[k] = _mm(so3_exp(dS[k, 0:3]), Rs[k])
        for j in range(15):
            Q[k, j] += dS[k, 3 + j]


# ----------------------------------------------------------------------------------------------
# Block-tridiagonal solver (the Gauss-Newton system of a chain)
# ----------------------------------------------------------------------------------------------


@njit
def _trsm_lower(L, B):
    """L^-1 B for lower-triangular L (d, d) and B (d, m)."""
    d, m = B.shape
    X = B.copy()
    for j in range(m):
        for i in range(d):
            acc = X[i, j]
            for k in range(i):
                acc -= L[i, k] * X[k, j]
            X[i, j] = acc / L[i, i]
    return X


@njit
def _trsv_lower(L, b):
    d = b.shape[0]
    x = b.copy()
    for i in range(d):
        acc = x[i]
        for k in range(i):
            acc -= L[i, k] * x[k]
        x[i] = acc / L[i, i]
    return x


@njit
def _trsv_upper_t(L, b):
    """L^-T b for lower-triangular L."""
    d = b.shape[0]
    x = b.copy()
    for i in range(d - 1, -1, -1):
        acc = x[i]
        for k in range(i + 1, d):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]
    return x


@njit
def block_tridiag_solve(D, B, g, want_cov):
    """Solve ``H x = g`` for ``H`` symmetric positive definite, block tridiagonal.

    ``D`` (N, d, d) diagonal blocks, ``B`` (N-1, d, d) upper blocks ``H[k, k+1]``.  Block
    Cholesky ``H = L L^T`` (``L`` block lower bidiagonal: ``L_kk``, ``C_k = L_k+1,k``), i.e. a
    square-root information filter, then back substitution (its RTS smoother).  With
    ``want_cov`` also returns the diagonal blocks of ``H^-1`` (N, d, d), the marginal covariances:
    ``P_k = M_k^T (I + C_k^T P_k+1 C_k) M_k`` with ``M_k = L_kk^-1``.
    Raises ``np.linalg.LinAlgError`` when ``H`` is not positive definite.
    """
    n, d = D.shape[0], D.shape[1]
    Ld = np.empty((n, d, d))
    C = np.empty((max(n - 1, 0), d, d))
    y = np.empty((n, d))
    S = D[0].copy()
    for k in range(n):
        if k > 0:
            S = D[k] - C[k - 1] @ C[k - 1].T
        Ld[k] = np.linalg.cholesky(S)
        if k < n - 1:
            C[k] = _trsm_lower(Ld[k], B[k]).T.copy()
        rhs = g[k].copy()
        if k > 0:
            rhs -= C[k - 1] @ y[k - 1]
        y[k] = _trsv_lower(Ld[k], rhs)
    x = np.empty((n, d))
    x[n - 1] = _trsv_upper_t(Ld[n - 1], y[n - 1])
    for k in range(n - 2, -1, -1):
        x[k] = _trsv_upper_t(Ld[k], y[k] - C[k].T @ x[k + 1])
    P = np.empty((n, d, d)) if want_cov else np.empty((0, d, d))
    if want_cov:
        eye = np.eye(d)
        for k in range(n - 1, -1, -1):
            M = _trsm_lower(Ld[k], eye)
            if k == n - 1:
                P[k] = M.T @ M
            else:
                P[k] = M.T @ (eye + C[k].T @ P[k + 1] @ C[k]) @ M
    return x, P


@njit
def block_tridiag_covariances(D, B):
    """Marginal covariances of ``H^-1`` for ``H`` as in :func:`block_tridiag_solve`: the diagonal
    blocks ``P`` (N, d, d) and the lag-one cross blocks ``Pc`` (N-1, d, d), ``Pc[k] = (H^-1)[k, k+1]``.

    With ``H = L L^T`` (block Cholesky, ``M_k = L_kk^-1``, ``C_k = L_k+1,k``), block row ``k`` of
    ``L^T H^-1 = L^-1`` above the diagonal gives ``(H^-1)[k, k+1] = -M_k^T C_k^T P_k+1`` (the
    smoother's lag-one covariance); ``P_k = M_k^T (I + C_k^T P_k+1 C_k) M_k``.
    """
    n, d = D.shape[0], D.shape[1]
    Ld = np.empty((n, d, d))
    C = np.empty((max(n - 1, 0), d, d))
    S = D[0].copy()
    for k in range(n):
        if k > 0:
            S = D[k] - C[k - 1] @ C[k - 1].T
        Ld[k] = np.linalg.cholesky(S)
        if k < n - 1:
            C[k] = _trsm_lower(Ld[k], B[k]).T.copy()
    P = np.empty((n, d, d))
    Pc = np.empty((max(n - 1, 0), d, d))
    eye = np.eye(d)
    for k in range(n - 1, -1, -1):
        M = _trsm_lower(Ld[k], eye)
        if k == n - 1:
            P[k] = M.T @ M
        else:
            CP = C[k].T @ P[k + 1]
            P[k] = M.T @ (eye + CP @ C[k]) @ M
            Pc[k] = -(M.T @ CP)
    return P, Pc


@njit
def _trsm_upper_t(L, B):
    """L^-T B for lower-triangular L (d, d) and B (d, m)."""
    d, m = B.shape
    X = B.copy()
    for j in range(m):
        for i in range(d - 1, -1, -1):
            acc = X[i, j]
            for k in range(i + 1, d):
                acc -= L[k, i] * X[k, j]
            X[i, j] = acc / L[i, i]
    return X


@njit
def block_tridiag_solve_multi(D, B, G, want_cov):
    """:func:`block_tridiag_solve` with ``m`` right-hand sides ``G`` (N, d, m) -> ``X`` (N, d, m).

    One block Cholesky serves every column (the batch smoother's arrow system: the state's
    right-hand side and the border columns of the global effect parameters).  With ``want_cov``
    also returns the marginal covariances ``P`` (N, d, d) and the lag-one cross blocks ``Pc``
    (N-1, d, d) of ``H^-1`` (as :func:`block_tridiag_covariances`).
    """
    n, d, m = G.shape[0], G.shape[1], G.shape[2]
    Ld = np.empty((n, d, d))
    C = np.empty((max(n - 1, 0), d, d))
    Y = np.empty((n, d, m))
    S = D[0].copy()
    for k in range(n):
        if k > 0:
            S = D[k] - C[k - 1] @ C[k - 1].T
        Ld[k] = np.linalg.cholesky(S)
        if k < n - 1:
            C[k] = _trsm_lower(Ld[k], B[k]).T.copy()
        rhs = G[k].copy()
        if k > 0:
            rhs -= C[k - 1] @ Y[k - 1]
        Y[k] = _trsm_lower(Ld[k], rhs)
    X = np.empty((n, d, m))
    X[n - 1] = _trsm_upper_t(Ld[n - 1], Y[n - 1])
    for k in range(n - 2, -1, -1):
        X[k] = _trsm_upper_t(Ld[k], Y[k] - C[k].T @ X[k + 1])
    P = np.empty((n, d, d)) if want_cov else np.empty((0, d, d))
    Pc = np.empty((max(n - 1, 0), d, d)) if want_cov else np.empty((0, d, d))
    if want_cov:
        eye = np.eye(d)
        for k in range(n - 1, -1, -1):
            M = _trsm_lower(Ld[k], eye)
            if k == n - 1:
                P[k] = M.T @ M
            else:
                CP = C[k].T @ P[k + 1]
                P[k] = M.T @ (eye + CP @ C[k]) @ M
                Pc[k] = -(M.T @ CP)
    return X, P, Pc



@njit
def block_tridiag_logdet(D, B):
    """``log det H`` for ``H`` symmetric positive definite, block tridiagonal (as
    :func:`block_tridiag_solve`): twice the sum of the logs of the block Cholesky pivots.
    Raises ``np.linalg.LinAlgError`` when ``H`` is not positive definite."""
    n, d = D.shape[0], D.shape[1]
    out = 0.0
    S = D[0].copy()
    for k in range(n):
        L = np.linalg.cholesky(S)
        for i in range(d):
            out += 2.0 * np.log(L[i, i])
        if k < n - 1:
            C = _trsm_lower(L, B[k])
            S = D[k + 1] - C.T @ C
    return out

# ----------------------------------------------------------------------------------------------
# Fixed-lag window (smoother/fixed_lag.py): incremental block elimination, oldest first
# ----------------------------------------------------------------------------------------------


@njit
def window_eliminate(Sp0, rp0, first_partial, U, gU, Fw, gF, B, Cprev, yprev, has_prev, Ld, C, y, Sp, rp):
    """Forward (oldest-first) block Cholesky of the newest steps of a chain.

    Steps ``0..m-1`` of the arrays are consecutive steps of the window.  ``U[i]``, ``gU[i]``: the
    information of step i's own factors and of the link from step i-1; ``Fw[i]``, ``gF[i]`` that
    of the link to step i+1 on step i; ``B[i]`` the cross block ``H[i, i+1]``.  With
    ``first_partial`` the first step's eliminated-so-far information is ``(Sp0, rp0)`` (a frozen
    step whose predecessors are already eliminated); otherwise it is ``U[0] - Cprev Cprev^T``
    (``has_prev``) or ``U[0]``.  Writes ``Ld[i]`` (Cholesky factor), ``C[i] = (Ld[i]^-1 B[i])^T``,
    ``y[i]`` and the partials ``Sp[i], rp[i]`` (before the forward link).  Raises LinAlgError if
    not positive definite.
    """
    m = U.shape[0]
    for i in range(m):
        if i == 0:
            if first_partial:
                Sp[0] = Sp0
                rp[0] = rp0
            elif has_prev:
                Sp[0] = U[0] - Cprev @ Cprev.T
                rp[0] = gU[0] - Cprev @ yprev
            else:
                Sp[0] = U[0]
                rp[0] = gU[0]
        else:
            Sp[i] = U[i] - C[i - 1] @ C[i - 1].T
            rp[i] = gU[i] - C[i - 1] @ y[i - 1]
        S = Sp[i] + Fw[i]
        Ld[i] = np.linalg.cholesky(S)
        if i < m - 1:
            C[i] = _trsm_lower(Ld[i], B[i]).T.copy()
        y[i] = _trsv_lower(Ld[i], rp[i] + gF[i])


@njit
def window_back_substitute(Ld, C, y, order, x):
    """Back substitution over ring-buffer positions ``order`` (newest first): ``x[p]`` for each
    (``x_k = Ld_k^-T (y_k - C_k^T x_k+1)``), without temporaries."""
    d = y.shape[1]
    b = np.empty(d)
    for kk in range(order.shape[0]):
        p = order[kk]
        for i in range(d):
            b[i] = y[p, i]
        if kk > 0:
            pn = order[kk - 1]
            for j in range(d):
                xj = x[pn, j]
                if xj != 0.0:
                    for i in range(d):
                        b[i] -= C[p, j, i] * xj
        for i in range(d - 1, -1, -1):
            acc = b[i]
            for m in range(i + 1, d):
                acc -= Ld[p, m, i] * x[p, m]
            x[p, i] = acc / Ld[p, i, i]


@njit
def window_marginals(Ld, C, order, P):
    """Marginal covariances ``P[p]`` of the window at ring positions ``order`` (newest first):
    ``P_k = M_k^T (I + C_k^T P_k+1 C_k) M_k``, ``M_k = Ld_k^-1`` (as :func:`block_tridiag_solve`)."""
    d = Ld.shape[1]
    eye = np.eye(d)
    Pn = np.empty((d, d))
    for k in range(order.shape[0]):
        p = order[k]
        M = _trsm_lower(Ld[p], eye)
        if k == 0:
            Pn = M.T @ M
        else:
            Pn = M.T @ (eye + C[p].T @ Pn @ C[p]) @ M
        P[p] = Pn
