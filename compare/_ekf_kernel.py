r"""Fused, compiled (numba) step of the EKF of :mod:`flexforce.compare.ekf`.

The same arithmetic as the numpy reference -- :mod:`flexforce.factors.physics` (contact law,
forward dynamics, IMU model, with their analytic Jacobians) and :class:`~flexforce.compare.ekf.EKF`
-- written over plain float arrays so that numba compiles one step into a single function.
Why: the reference costs ~1 ms per step (hundreds of small numpy calls at ~1 us each), the
target is <= 100 us (the authors' C++ runs ~20 us).  ``tests/test_ekf.py`` holds the two against
each other to 1e-10, including anisotropic and cubic-stiffening contacts and contact changes.

Packed inputs, one row per step (``pack_inputs``)::

    0:3 com | 3:6 com_vel | 6:9 com_acc | 9:18 inertia | 18:27 inertia_dot | 27:30 sigma
    30:33 sigma_dot | 33:42 imu_R | 42:45 imu_p | 45:48 imu_v | 48:51 imu_a | 51:54 imu_w
    54:57 gyro | 57:60 accel | then per contact c, at 60 + 13 c: active, p (3), R (9)

Contact parameters, one row per contact: K_fs, K_fd, K_ts, K_td (9 each, row-major), beta_f,
beta_t, isotropic flag.
"""

from __future__ import annotations

import math

import numpy as np

try:  # numba is optional: without it the EKF runs the numpy reference path.
    from numba import njit

    AVAILABLE = True
except ImportError:  # pragma: no cover - exercised only without numba
    AVAILABLE = False

    def njit(*args, **kwargs):
        if args and callable(args[0]):
            return args[0]
        return lambda f: f

_NU0 = 60
_NUC = 13

# ----------------------------------------------------------------------------------------------
# Small linear algebra
# ----------------------------------------------------------------------------------------------


@njit(cache=True)
def _skew(v):
    S = np.zeros((3, 3))
    S[0, 1] = -v[2]
    S[0, 2] = v[1]
    S[1, 0] = v[2]
    S[1, 2] = -v[0]
    S[2, 0] = -v[1]
    S[2, 1] = v[0]
    return S


@njit(cache=True)
def _cross(a, b):
    r = np.empty(3)
    r[0] = a[1] * b[2] - a[2] * b[1]
    r[1] = a[2] * b[0] - a[0] * b[2]
    r[2] = a[0] * b[1] - a[1] * b[0]
    return r


@njit(cache=True)
def _mm(A, B):
    n, m = A.shape
    p = B.shape[1]
    C = np.zeros((n, p))
    for i in range(n):
        for k in range(m):
            a = A[i, k]
            if a != 0.0:
                for j in range(p):
                    C[i, j] += a * B[k, j]
    return C


@njit(cache=True)
def _mv(A, x):
    n, m = A.shape
    r = np.zeros(n)
    for i in range(n):
        s = 0.0
        for k in range(m):
            s += A[i, k] * x[k]
        r[i] = s
    return r


@njit(cache=True)
def _mmt(A, B):
    """A @ B.T"""
    n, m = A.shape
    p = B.shape[0]
    C = np.empty((n, p))
    for i in range(n):
        for j in range(p):
            s = 0.0
            for k in range(m):
                s += A[i, k] * B[j, k]
            C[i, j] = s
    return C


@njit(cache=True)
def _cholesky(S):
    """Lower Cholesky factor; returns (L, ok)."""
    n = S.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        d = S[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:
            return L, False
        L[j, j] = math.sqrt(d)
        for i in range(j + 1, n):
            s = S[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    return L, True


@njit(cache=True)
def _forward_sub(L, b):
    n = L.shape[0]
    x = np.empty(n)
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    return x


@njit(cache=True)
def _back_sub_t(L, b):
    """Solve L^T x = b."""
    n = L.shape[0]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        s = b[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return x


@njit(cache=True)
def _inv6(A):
    """Inverse of a 6x6 matrix by Gauss-Jordan with partial pivoting; (Ainv, ok)."""
    n = A.shape[0]
    M = A.copy()
    Inv = np.eye(n)
    for c in range(n):
        p = c
        best = abs(M[c, c])
        for r in range(c + 1, n):
            if abs(M[r, c]) > best:
                best = abs(M[r, c])
                p = r
        if best == 0.0:
            return Inv, False
        if p != c:
            for j in range(n):
                M[c, j], M[p, j] = M[p, j], M[c, j]
                Inv[c, j], Inv[p, j] = Inv[p, j], Inv[c, j]
        d = 1.0 / M[c, c]
        for j in range(n):
            M[c, j] *= d
            Inv[c, j] *= d
        for r in range(n):
            if r != c:
                f = M[r, c]
                if f != 0.0:
                    for j in range(n):
                        M[r, j] -= f * M[c, j]
                        Inv[r, j] -= f * Inv[c, j]
    return Inv, True


# ----------------------------------------------------------------------------------------------
# SO(3), as flexforce.factors.so3
# ----------------------------------------------------------------------------------------------


@njit(cache=True)
def so3_exp(phi):
    theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    K = _skew(phi)
    KK = _mm(K, K)
    if theta2 < 1e-16:
        return np.eye(3) + K + 0.5 * KK
    theta = math.sqrt(theta2)
    a = math.sin(theta) / theta
    b = (1.0 - math.cos(theta)) / theta2
    return np.eye(3) + a * K + b * KK


@njit(cache=True)
def so3_log(R):
    w = np.empty(3)
    w[0] = R[2, 1] - R[1, 2]
    w[1] = R[0, 2] - R[2, 0]
    w[2] = R[1, 0] - R[0, 1]
    cos_theta = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    sin_theta = 0.5 * math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    theta = math.atan2(sin_theta, cos_theta)
    if cos_theta > -0.9:
        if sin_theta < 1e-8:
            return 0.5 * (1.0 + sin_theta * sin_theta / 6.0) * w
        return (0.5 * theta / sin_theta) * w
    S = 0.5 * (R + R.T)
    for i in range(3):
        S[i, i] -= cos_theta
    k = 0
    for i in range(1, 3):
        if S[i, i] > S[k, k]:
            k = i
    axis = S[:, k].copy()
    if axis[0] * w[0] + axis[1] * w[1] + axis[2] * w[2] < 0.0:
        axis = -axis
    return (theta / math.sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2])) * axis


@njit(cache=True)
def so3_left_jacobian(phi):
    theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    K = _skew(phi)
    if theta2 < 1e-2:
        a = 0.5 - theta2 * (1.0 / 24.0 - theta2 * (1.0 / 720.0 - theta2 / 40320.0))
        b = 1.0 / 6.0 - theta2 * (1.0 / 120.0 - theta2 * (1.0 / 5040.0 - theta2 / 362880.0))
    else:
        theta = math.sqrt(theta2)
        h = math.sin(0.5 * theta) / theta
        a = 2.0 * h * h
        b = (theta - math.sin(theta)) / (theta2 * theta)
    return np.eye(3) + a * K + b * _mm(K, K)


@njit(cache=True)
def so3_left_jacobian_inverse(phi):
    theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    K = _skew(phi)
    if theta2 < 1e-2:
        c = 1.0 / 12.0 + theta2 * (1.0 / 720.0 + theta2 * (1.0 / 30240.0 + theta2 / 1209600.0))
    else:
        theta = math.sqrt(theta2)
        c = 1.0 / theta2 - 0.5 / (theta * math.tan(0.5 * theta))
    return np.eye(3) - 0.5 * K + c * _mm(K, K)


# ----------------------------------------------------------------------------------------------
# Physics, as flexforce.factors.physics (world-frame increments, (theta, t, w, v) order)
# ----------------------------------------------------------------------------------------------


@njit(cache=True)
def contact_wrench(R, t, w, v, p_l, R_l, cp, want_jac):
    """physics.contact_wrench; ``cp`` a packed parameter row. Returns (wrench (6,), J (6x12))."""
    Kfs = cp[0:9].reshape(3, 3)
    Kfd = cp[9:18].reshape(3, 3)
    Kts = cp[18:27].reshape(3, 3)
    Ktd = cp[27:36].reshape(3, 3)
    beta_f = cp[36]
    beta_t = cp[37]
    iso = cp[38] != 0.0
    Rp = _mv(R, p_l)
    s = Rp + t - p_l
    ds = _cross(w, Rp) + v
    Omega = so3_log(R)
    if not iso:
        Rc = _mm(R, R_l)
        Kfs = _mmt(_mm(Rc, Kfs), Rc)
        Kfd = _mmt(_mm(Rc, Kfd), Rc)
        Kts = _mmt(_mm(Rc, Kts), Rc)
        Ktd = _mmt(_mm(Rc, Ktd), Rc)
    gf = 1.0 + beta_f * (s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
    gt = 1.0 + beta_t * (Omega[0] * Omega[0] + Omega[1] * Omega[1] + Omega[2] * Omega[2])
    ss = s * gf
    OO = Omega * gt
    F = -_mv(Kfs, ss) - _mv(Kfd, ds)
    p_w = Rp + t
    Tq = -_mv(Kts, OO) - _mv(Ktd, w) + _cross(p_w, F)
    wrench = np.empty(6)
    wrench[0:3] = F
    wrench[3:6] = Tq
    J = np.zeros((6, 12))
    if not want_jac:
        return wrench, J
    S_Rp = _skew(Rp)
    Ds = gf * np.eye(3) + 2.0 * beta_f * np.outer(s, s)
    DO = gt * np.eye(3) + 2.0 * beta_t * np.outer(Omega, Omega)
    dF_dth = _mm(_mm(Kfs, Ds), S_Rp) + _mm(_mm(Kfd, _skew(w)), S_Rp)
    dT0_dth = -_mm(_mm(Kts, DO), so3_left_jacobian_inverse(Omega))
    if not iso:
        dF_dth += _skew(_mv(Kfs, ss)) - _mm(Kfs, _skew(ss)) + _skew(_mv(Kfd, ds)) - _mm(Kfd, _skew(ds))
        dT0_dth += _skew(_mv(Kts, OO)) - _mm(Kts, _skew(OO)) + _skew(_mv(Ktd, w)) - _mm(Ktd, _skew(w))
    dF_dt = -_mm(Kfs, Ds)
    dF_dw = _mm(Kfd, S_Rp)
    S_pw = _skew(p_w)
    S_F = _skew(F)
    J[0:3, 0:3] = dF_dth
    J[0:3, 3:6] = dF_dt
    J[0:3, 6:9] = dF_dw
    J[0:3, 9:12] = -Kfd
    J[3:6, 0:3] = dT0_dth + _mm(S_F, S_Rp) + _mm(S_pw, dF_dth)
    J[3:6, 3:6] = -S_F + _mm(S_pw, dF_dt)
    J[3:6, 6:9] = -Ktd + _mm(S_pw, dF_dw)
    J[3:6, 9:12] = -_mm(S_pw, Kfd)
    return wrench, J


@njit(cache=True)
def total_contact_wrench(R, t, w, v, u, CP, want_jac):
    """Sum over the active contacts of row ``u``; also the per-contact wrenches (C, 6)."""
    n_c = CP.shape[0]
    per = np.zeros((n_c, 6))
    total = np.zeros(6)
    Jsum = np.zeros((6, 12))
    for c in range(n_c):
        o = _NU0 + _NUC * c
        if u[o] == 0.0:
            continue
        wr, J = contact_wrench(R, t, w, v, u[o + 1:o + 4], u[o + 4:o + 13].reshape(3, 3), CP[c], want_jac)
        per[c] = wr
        total += wr
        if want_jac:
            Jsum += J
    return total, per, Jsum


@njit(cache=True)
def required_wrench_x(R, t, w, dw, a, u, m, g):
    """physics.required_wrench and its 6x12 Jacobian with respect to (theta, t, w, v)."""
    c = u[0:3]
    Ic = u[9:18].reshape(3, 3)
    dIc = u[18:27].reshape(3, 3)
    Rc = _mv(R, c)
    Rdc = _mv(R, u[3:6])
    Rddc = _mv(R, u[6:9])
    RIRt = _mmt(_mm(R, Ic), R)
    RdIRt = _mmt(_mm(R, dIc), R)
    Rs = _mv(R, u[27:30])
    Rds = _mv(R, u[30:33])
    ag = a.copy()
    ag[2] += g
    w_Rc = _cross(w, Rc)
    F = m * (_cross(dw, Rc) + _cross(w, w_Rc) + 2.0 * _cross(w, Rdc) + Rddc + ag)
    Iw = _mv(RIRt, w)
    Tq = (_cross(w, Iw) + _mv(RdIRt, w) + _mv(RIRt, dw) + _cross(w, Rs) + Rds
          + _cross(t, F) + m * _cross(Rc, ag))
    wrench = np.empty(6)
    wrench[0:3] = F
    wrench[3:6] = Tq
    Sw = _skew(w)
    S_Rc = _skew(Rc)
    S_t = _skew(t)
    SwSw = _mm(Sw, Sw)
    dF_dth = m * (-_mm(_skew(dw), S_Rc) - _mm(SwSw, S_Rc) - 2.0 * _mm(Sw, _skew(Rdc)) - _skew(Rddc))
    dF_dw = m * (-_skew(w_Rc) - _mm(Sw, S_Rc) - 2.0 * _skew(Rdc))
    dIw_dth = -_skew(Iw) + _mm(RIRt, Sw)
    dT_dth = (_mm(Sw, dIw_dth) - _skew(_mv(RdIRt, w)) + _mm(RdIRt, Sw)
              - _skew(_mv(RIRt, dw)) + _mm(RIRt, _skew(dw))
              - _mm(Sw, _skew(Rs)) - _skew(Rds)
              + _mm(S_t, dF_dth) + m * _mm(_skew(ag), S_Rc))
    dT_dt = -_skew(F)
    dT_dw = -_skew(Iw) + _mm(Sw, RIRt) + RdIRt - _skew(Rs) + _mm(S_t, dF_dw)
    Jx = np.zeros((6, 12))
    Jx[0:3, 0:3] = dF_dth
    Jx[0:3, 6:9] = dF_dw
    Jx[3:6, 0:3] = dT_dth
    Jx[3:6, 3:6] = dT_dt
    Jx[3:6, 6:9] = dT_dw
    return wrench, Jx, RIRt, S_Rc, S_t


@njit(cache=True)
def forward_dynamics(R, t, w, wrench_c, u, m, g):
    """physics.forward_dynamics: (acc (dw, a), Jx 6x12, Jwrench 6x6, ok)."""
    zero = np.zeros(3)
    r0, _, RIRt, S_Rc, S_t = required_wrench_x(R, t, w, zero, zero, u, m, g)
    A = np.empty((6, 6))
    A[0:3, 0:3] = -m * S_Rc
    A[0:3, 3:6] = m * np.eye(3)
    A[3:6, 0:3] = RIRt - m * _mm(S_t, S_Rc)
    A[3:6, 3:6] = m * (S_t + S_Rc)
    Ainv, ok = _inv6(A)
    acc = _mv(Ainv, wrench_c - r0)
    _, Jr, _, _, _ = required_wrench_x(R, t, w, acc[0:3], acc[3:6], u, m, g)
    return acc, -_mm(Ainv, Jr), Ainv, ok


@njit(cache=True)
def imu_readings(R, w, dw, a, u, g):
    """physics.imu_readings: (y (6,), H 6x18 over (theta, t, w, v, dw, a))."""
    Rt = R.T.copy()
    uu = _mv(Rt, w)
    ud = _mv(Rt, dw)
    p = u[42:45]
    pv = u[45:48]
    RaT = u[33:42].reshape(3, 3).T.copy()
    ag = a.copy()
    ag[2] += g
    up = _cross(uu, p)
    acc_l = _cross(ud, p) + _cross(uu, up) + 2.0 * _cross(uu, pv) + u[48:51] + _mv(Rt, ag)
    y = np.empty(6)
    y[0:3] = _mv(RaT, uu + u[51:54])
    y[3:6] = _mv(RaT, acc_l)
    H = np.zeros((6, 18))
    du_dth = _mm(Rt, _skew(w))
    dacc_du = -_skew(up) - _mm(_skew(uu), _skew(p)) - 2.0 * _skew(pv)
    dacc_dud = -_skew(p)
    RaTRt = _mm(RaT, Rt)
    H[0:3, 0:3] = _mm(RaT, du_dth)
    H[0:3, 6:9] = RaTRt
    H[3:6, 0:3] = _mm(RaT, _mm(dacc_du, du_dth) + _mm(_mm(dacc_dud, Rt), _skew(dw)) + _mm(Rt, _skew(ag)))
    H[3:6, 6:9] = _mm(_mm(RaT, dacc_du), Rt)
    H[3:6, 12:15] = _mm(_mm(RaT, dacc_dud), Rt)
    H[3:6, 15:18] = RaTRt
    return y, H


# ----------------------------------------------------------------------------------------------
# The filter's step (state x = (t, Omega, v, w, a, dw), as compare.ekf)
# ----------------------------------------------------------------------------------------------


@njit(cache=True)
def transition(x, u, CP, dt, m, g):
    """EKF.transition with its Jacobian: (x1, F, ok)."""
    t = x[0:3]
    Om = x[3:6]
    v = x[6:9]
    w = x[9:12]
    a = x[12:15]
    dw = x[15:18]
    phi = dt * w + 0.5 * dt * dt * dw
    E = so3_exp(phi)
    R1 = _mm(E, so3_exp(Om))
    t1 = t + dt * v + 0.5 * dt * dt * a
    v1 = v + dt * a
    w1 = w + dt * dw
    Om1 = so3_log(R1)
    W, _, Jc = total_contact_wrench(R1, t1, w1, v1, u, CP, True)
    acc, Jx, Jw, ok = forward_dynamics(R1, t1, w1, W, u, m, g)
    G = Jx + _mm(Jw, Jc)  # rows (dw, a), columns (theta, t, w, v)
    Jphi = so3_left_jacobian(phi)
    D = np.zeros((12, 18))
    D[0:3, 3:6] = _mm(E, so3_left_jacobian(Om))
    D[0:3, 9:12] = dt * Jphi
    D[0:3, 15:18] = 0.5 * dt * dt * Jphi
    for i in range(3):
        D[3 + i, i] = 1.0
        D[3 + i, 6 + i] = dt
        D[3 + i, 12 + i] = 0.5 * dt * dt
        D[6 + i, 9 + i] = 1.0
        D[6 + i, 15 + i] = dt
        D[9 + i, 6 + i] = 1.0
        D[9 + i, 12 + i] = dt
    F = np.empty((18, 18))
    F[0:3] = D[3:6]
    F[3:6] = _mm(so3_left_jacobian_inverse(Om1), D[0:3])
    F[6:9] = D[9:12]
    F[9:12] = D[6:9]
    GD = _mm(G, D)
    F[12:15] = GD[3:6]
    F[15:18] = GD[0:3]
    x1 = np.empty(18)
    x1[0:3] = t1
    x1[3:6] = Om1
    x1[6:9] = v1
    x1[9:12] = w1
    x1[12:15] = acc[3:6]
    x1[15:18] = acc[0:3]
    return x1, F, ok


@njit(cache=True)
def _paper_to_world(Om):
    M = np.zeros((18, 18))
    M[0:3, 3:6] = so3_left_jacobian(Om)
    for i in range(3):
        M[3 + i, i] = 1.0
        M[6 + i, 9 + i] = 1.0
        M[9 + i, 6 + i] = 1.0
        M[12 + i, 15 + i] = 1.0
        M[15 + i, 12 + i] = 1.0
    return M


@njit(cache=True)
def _sym(P):
    return 0.5 * (P + P.T)


@njit(cache=True)
def predict(x, P, u, CP, Q0, dt, m, g):
    """EKF.predict: (x1, P1, status) with status 0 ok, 1 P not positive definite, 5 singular dynamics."""
    x1, F, ok = transition(x, u, CP, dt, m, g)
    if not ok:
        return x1, P, 5
    B = np.eye(18)
    B[3:6, 3:6] = so3_left_jacobian_inverse(x1[3:6])
    Q = _mmt(_mm(B, Q0), B)
    P1 = _sym(_mmt(_mm(F, P), F) + Q)
    _, okp = _cholesky(P1)
    if not okp:
        return x1, P1, 1
    return x1, P1, 0


@njit(cache=True)
def update(x, P, u, Rn, g):
    """EKF.update: (x1, P1, innovation, S, whitened, nis, status)."""
    Om = x[3:6]
    R = so3_exp(Om)
    hx, Hw = imu_readings(R, x[9:12], x[15:18], x[12:15], u, g)
    H = _mm(Hw, _paper_to_world(Om))
    innov = u[54:60] - hx
    PHt = _mmt(P, H)
    S = _sym(_mm(H, PHt) + Rn)
    L, ok = _cholesky(S)
    white = np.zeros(6)
    if not ok:
        return x, P, innov, S, white, np.inf, 2
    # K = P H^T S^-1, column by column of K^T: S K^T = H P
    Kt = np.empty((6, 18))
    for j in range(18):
        Kt[:, j] = _back_sub_t(L, _forward_sub(L, PHt[j]))
    K = Kt.T.copy()
    white = _forward_sub(L, innov)
    nis = 0.0
    for i in range(6):
        nis += white[i] * white[i]
    x1 = x + _mv(K, innov)
    ph2 = x1[3] * x1[3] + x1[4] * x1[4] + x1[5] * x1[5]
    if ph2 > math.pi * math.pi:
        x1[3:6] = so3_log(so3_exp(x1[3:6]))
    IKH = np.eye(18) - _mm(K, H)
    P1 = _sym(_mmt(_mm(IKH, P), IKH) + _mmt(_mm(K, Rn), K))
    for i in range(18):
        if not math.isfinite(x1[i]):
            return x1, P1, innov, S, white, nis, 4
    _, okp = _cholesky(P1)
    if not okp:
        return x1, P1, innov, S, white, nis, 3
    return x1, P1, innov, S, white, nis, 0


@njit(cache=True)
def outputs(x, P, u, CP, z0, min_force):
    """EKF.outputs: (world cov, per-contact wrench, wrench cov, cop, cop cov)."""
    Om = x[3:6]
    R = so3_exp(Om)
    M = _paper_to_world(Om)
    Pw = _sym(_mmt(_mm(M, P), M))
    W, per, Jc = total_contact_wrench(R, x[0:3], x[9:12], x[6:9], u, CP, True)
    Wcov = _sym(_mmt(_mm(Jc, Pw[0:12, 0:12]), Jc))
    cop = np.empty(3)
    cop[2] = z0
    cop_cov = np.empty((2, 2))
    Fz = W[2]
    if not Fz > min_force:
        cop[0] = np.nan
        cop[1] = np.nan
        cop_cov[:, :] = np.nan
        return Pw, per, Wcov, cop, cop_cov
    px = (z0 * W[0] - W[4]) / Fz
    py = (W[3] + z0 * W[1]) / Fz
    cop[0] = px
    cop[1] = py
    Jcop = np.zeros((2, 6))
    Jcop[0, 0] = z0 / Fz
    Jcop[0, 2] = -px / Fz
    Jcop[0, 4] = -1.0 / Fz
    Jcop[1, 1] = z0 / Fz
    Jcop[1, 2] = -py / Fz
    Jcop[1, 3] = 1.0 / Fz
    cop_cov[:, :] = _mmt(_mm(Jcop, Wcov), Jcop)
    return Pw, per, Wcov, cop, cop_cov


@njit(cache=True)
def step(k, x, P, U, CP, Q0, Rn, prm, X, COV, WR, WCOV, COP, COPCOV, INNOV, S_OUT, WHITE, NIS):
    """Predict (k > 0) and update at step k; x and P are overwritten; outputs written at k.

    ``prm`` = (dt, m, g, z0, min_force).  Returns the status (0 ok, see compare.ekf).
    """
    dt = prm[0]
    m = prm[1]
    g = prm[2]
    u = U[k]
    xk = x.copy()
    Pk = P.copy()
    if k > 0:
        xk, Pk, st = predict(xk, Pk, u, CP, Q0, dt, m, g)
        if st != 0:
            x[:] = xk
            P[:, :] = Pk
            return st
    x1, P1, innov, S, white, nis, st = update(xk, Pk, u, Rn, g)
    x[:] = x1
    P[:, :] = P1
    INNOV[k] = innov
    S_OUT[k] = S
    WHITE[k] = white
    NIS[k] = nis
    if st != 0:
        return st
    Pw, per, Wcov, cop, cop_cov = outputs(x1, P1, u, CP, prm[3], prm[4])
    X[k] = x1
    COV[k] = Pw
    WR[k] = per
    WCOV[k] = Wcov
    COP[k] = cop
    COPCOV[k] = cop_cov
    return 0


# ----------------------------------------------------------------------------------------------
# Packing and the Python-side driver
# ----------------------------------------------------------------------------------------------


def pack_inputs(rec) -> np.ndarray:
    """(N, 60 + 13 C) packed inputs and readings (see the module docstring)."""
    n, n_c = rec.n, len(rec.contact_names)
    U = np.zeros((n, _NU0 + _NUC * n_c))
    cols = [rec.com, rec.com_vel, rec.com_acc, rec.inertia.reshape(n, 9), rec.inertia_dot.reshape(n, 9),
            rec.sigma, rec.sigma_dot, rec.imu_R.reshape(n, 9), rec.imu_p, rec.imu_v, rec.imu_a, rec.imu_w,
            rec.gyro, rec.accel]
    U[:, :_NU0] = np.hstack(cols)
    for c in range(n_c):
        o = _NU0 + _NUC * c
        active = rec.contact_active[:, c]
        U[:, o] = active
        # Rest placements of inactive contacts are never read; keep them finite.
        U[:, o + 1:o + 4] = np.where(active[:, None], rec.contact_p[:, c], 0.0)
        U[:, o + 4:o + 13] = np.where(active[:, None], rec.contact_R[:, c].reshape(n, 9), np.eye(3).ravel())
    return np.ascontiguousarray(U)


def pack_params(params) -> np.ndarray:
    """(C, 39) packed contact parameters."""
    rows = []
    for p in params:
        rows.append(np.concatenate([p.K_fs.ravel(), p.K_fd.ravel(), p.K_ts.ravel(), p.K_td.ravel(),
                                    [p.beta_f, p.beta_t, 1.0 if p.isotropic else 0.0]]))
    return np.ascontiguousarray(np.array(rows, dtype=float).reshape(len(rows), 39))


class Kernel:
    """Binds a :class:`~flexforce.compare.ekf.EKF` to the compiled step."""

    def __init__(self, ekf):
        rec = ekf.rec
        self.U = pack_inputs(rec)
        self.CP = pack_params(ekf.model.contact_params)
        self.Q0 = np.ascontiguousarray(ekf.noise.Q)
        self.Rn = np.ascontiguousarray(ekf.noise.R)
        self.prm = np.array([ekf.dt, rec.mass, ekf.g, ekf.config.z0, ekf.config.min_force])

    def step(self, k: int, x: np.ndarray, P: np.ndarray, out) -> int:
        return step(k, x, P, self.U, self.CP, self.Q0, self.Rn, self.prm, out.x, out.cov, out.wrench,
                    out.wrench_cov, out.cop, out.cop_cov, out.innovation, out.S, out.white, out.nis)
