r"""Fused, compiled (numba) step of the EKF of :mod:`flexforce.compare.ekf`.

The same arithmetic as the numpy reference -- :mod:`flexforce.factors.physics` (contact law,
forward dynamics, IMU model, with their analytic Jacobians) and :class:`~flexforce.compare.ekf.EKF`
-- written over plain float arrays so that numba compiles one step into a single function.
Why: the reference costs ~1 ms per step (hundreds of small numpy calls at ~1 us each), the
target is <= 100 us (the authors' C++ runs ~20 us).  ``tests/test_ekf.py`` holds the two against
each other to 1e-10, including anisotropic and cubic-stiffening contacts and contact changes.

Compile time (docs/ekf.md, "Speed"): a cold compilation took a minute; now about 12 s.  Keep it so:
no array expressions, slice assignments or numpy calls other than ``np.zeros`` / ``np.empty`` in
compiled code (use the leaf helpers); leaf helpers get one explicit signature (``_leaf``); thin
layers are inlined into ``step`` (``_inline``), big physics functions stay plain ``@njit``.

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
    from numba import njit, types

    AVAILABLE = True
    A1 = types.float64[::1]
    A2 = types.float64[:, ::1]
    MB = types.Tuple((A2, types.boolean))
    f8 = types.float64
    i8 = types.int64
    void = types.void
except ImportError:  # pragma: no cover - exercised only without numba
    AVAILABLE = False
    A1 = A2 = MB = f8 = i8 = void = None  # type: ignore[assignment]

    def njit(*args, **kwargs):  # type: ignore[no-redef]
        if args and callable(args[0]):
            return args[0]
        return lambda f: f


def _leaf(sig):
    """A small helper: one explicit signature (one specialisation, no literal-argument copies)."""
    if not AVAILABLE:  # pragma: no cover
        return lambda f: f
    if callable(sig):
        return njit(sig(), cache=True, no_cpython_wrapper=True)
    return njit(sig, cache=True, no_cpython_wrapper=True)


def _inline(f):
    """A physics or filter function: inlined into its caller at numba-IR level, so the whole
    step is one LLVM function optimised once (numba re-optimises every linked callee library at
    every level of the call graph otherwise)."""
    return njit(cache=True, inline="always")(f)


_NU0 = 60
_NUC = 13

# ----------------------------------------------------------------------------------------------
# Small linear algebra.  Compile-time rules (docs/ekf.md, "Speed"): no array expressions
# (``a + b`` on arrays), no slice assignments, no numpy calls beyond np.zeros / np.empty -- each
# of those makes numba type and lower a separate broadcasting loop, which is where the first
# version's minute of compilation went.  Every array is float64 and C-contiguous, so each helper
# has exactly one specialisation per rank.
# ----------------------------------------------------------------------------------------------


@_leaf(lambda: A2(A1))
def _skew(v):
    S = np.zeros((3, 3))
    S[0, 1] = -v[2]
    S[0, 2] = v[1]
    S[1, 0] = v[2]
    S[1, 2] = -v[0]
    S[2, 0] = -v[1]
    S[2, 1] = v[0]
    return S


@_leaf(lambda: A1(A1, A1))
def _cross(a, b):
    r = np.empty(3)
    r[0] = a[1] * b[2] - a[2] * b[1]
    r[1] = a[2] * b[0] - a[0] * b[2]
    r[2] = a[0] * b[1] - a[1] * b[0]
    return r


@_leaf(lambda: A2(A2, A2))
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


@_leaf(lambda: A1(A2, A1))
def _mv(A, x):
    n, m = A.shape
    r = np.zeros(n)
    for i in range(n):
        s = 0.0
        for k in range(m):
            s += A[i, k] * x[k]
        r[i] = s
    return r


@_leaf(lambda: A2(A2, A2))
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


@_leaf(lambda: A2(A2))
def _tr(A):
    n, m = A.shape
    C = np.empty((m, n))
    for i in range(n):
        for j in range(m):
            C[j, i] = A[i, j]
    return C


@_leaf(lambda: A2(A2))
def _sym(P):
    n = P.shape[0]
    C = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            C[i, j] = 0.5 * (P[i, j] + P[j, i])
    return C


@_leaf(lambda: A2(i8, f8))
def _eye(n, d):
    """d I_n"""
    C = np.zeros((n, n))
    for i in range(n):
        C[i, i] = d
    return C


@_leaf(lambda: A2(A1, A1))
def _outer(a, b):
    C = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            C[i, j] = a[i] * b[j]
    return C


@_leaf(lambda: A2(f8, A2))
def _scl2(a, A):
    """a A (new array)"""
    n, m = A.shape
    C = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            C[i, j] = a * A[i, j]
    return C


@_leaf(lambda: A2(f8, A2, f8, A2))
def _lin2(a, A, b, B):
    """a A + b B (new array)"""
    n, m = A.shape
    C = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            C[i, j] = a * A[i, j] + b * B[i, j]
    return C


@_leaf(lambda: void(A2, f8, A2))
def _axpy2(Y, a, X):
    """Y += a X, in place."""
    n, m = Y.shape
    for i in range(n):
        for j in range(m):
            Y[i, j] += a * X[i, j]


@_leaf(lambda: A1(f8, A1))
def _scl1(a, x):
    n = x.shape[0]
    r = np.empty(n)
    for i in range(n):
        r[i] = a * x[i]
    return r


@_leaf(lambda: A1(f8, A1, f8, A1))
def _lin1(a, x, b, y):
    """a x + b y (new array)"""
    n = x.shape[0]
    r = np.empty(n)
    for i in range(n):
        r[i] = a * x[i] + b * y[i]
    return r


@_leaf(lambda: void(A1, f8, A1))
def _axpy1(y, a, x):
    """y += a x, in place."""
    for i in range(y.shape[0]):
        y[i] += a * x[i]


@_leaf(lambda: void(A2, i8, i8, A2))
def _put(M, r, c, B):
    """M[r:r+n, c:c+m] = B"""
    n, m = B.shape
    for i in range(n):
        for j in range(m):
            M[r + i, c + j] = B[i, j]


@_leaf(lambda: A2(A2, i8, i8, i8, i8))
def _block(M, r, c, n, m):
    """copy of M[r:r+n, c:c+m]"""
    C = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            C[i, j] = M[r + i, c + j]
    return C


@_leaf(lambda: A1(A1, i8, i8))
def _seg(x, o, n):
    """copy of x[o:o+n]"""
    r = np.empty(n)
    for i in range(n):
        r[i] = x[o + i]
    return r


@_leaf(lambda: void(A1, i8, A1))
def _vput(x, o, v):
    """x[o:o+n] = v"""
    for i in range(v.shape[0]):
        x[o + i] = v[i]


@_leaf(lambda: A2(A1, i8))
def _mat3(x, o):
    """3x3 matrix stored row-major at x[o:o+9]"""
    C = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            C[i, j] = x[o + 3 * i + j]
    return C


@_leaf(lambda: MB(A2))
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


@_leaf(lambda: A1(A2, A1))
def _forward_sub(L, b):
    n = L.shape[0]
    x = np.empty(n)
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    return x


@_leaf(lambda: A1(A2, A1))
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


@_leaf(lambda: MB(A2))
def _inv6(A):
    """Inverse of a 6x6 matrix by Gauss-Jordan with partial pivoting; (Ainv, ok)."""
    n = A.shape[0]
    M = _block(A, 0, 0, n, n)
    Inv = _eye(n, 1.0)
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
                tmp = M[c, j]
                M[c, j] = M[p, j]
                M[p, j] = tmp
                tmp = Inv[c, j]
                Inv[c, j] = Inv[p, j]
                Inv[p, j] = tmp
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


@_leaf(lambda: A2(A1, f8, f8))
def _rodrigues(phi, a, b):
    """I + a [phi]x + b [phi]x^2"""
    K = _skew(phi)
    KK = _mm(K, K)
    R = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            R[i, j] = a * K[i, j] + b * KK[i, j]
        R[i, i] += 1.0
    return R


@_leaf(lambda: A2(A1))
def so3_exp(phi):
    theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    if theta2 < 1e-16:
        return _rodrigues(phi, 1.0, 0.5)
    theta = math.sqrt(theta2)
    return _rodrigues(phi, math.sin(theta) / theta, (1.0 - math.cos(theta)) / theta2)


@_leaf(lambda: A1(A2))
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
            return _scl1(0.5 * (1.0 + sin_theta * sin_theta / 6.0), w)
        return _scl1(0.5 * theta / sin_theta, w)
    S = _sym(R)
    for i in range(3):
        S[i, i] -= cos_theta
    k = 0
    for i in range(1, 3):
        if S[i, i] > S[k, k]:
            k = i
    axis = np.empty(3)
    for i in range(3):
        axis[i] = S[i, k]
    sgn = 1.0
    if axis[0] * w[0] + axis[1] * w[1] + axis[2] * w[2] < 0.0:
        sgn = -1.0
    return _scl1(sgn * theta / math.sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]), axis)


@_leaf(lambda: A2(A1))
def so3_left_jacobian(phi):
    theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    if theta2 < 1e-2:
        a = 0.5 - theta2 * (1.0 / 24.0 - theta2 * (1.0 / 720.0 - theta2 / 40320.0))
        b = 1.0 / 6.0 - theta2 * (1.0 / 120.0 - theta2 * (1.0 / 5040.0 - theta2 / 362880.0))
    else:
        theta = math.sqrt(theta2)
        h = math.sin(0.5 * theta) / theta
        a = 2.0 * h * h
        b = (theta - math.sin(theta)) / (theta2 * theta)
    return _rodrigues(phi, a, b)


@_leaf(lambda: A2(A1))
def so3_left_jacobian_inverse(phi):
    theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    if theta2 < 1e-2:
        c = 1.0 / 12.0 + theta2 * (1.0 / 720.0 + theta2 * (1.0 / 30240.0 + theta2 / 1209600.0))
    else:
        theta = math.sqrt(theta2)
        c = 1.0 / theta2 - 0.5 / (theta * math.tan(0.5 * theta))
    return _rodrigues(phi, -0.5, c)


# ----------------------------------------------------------------------------------------------
# Physics, as flexforce.factors.physics (world-frame increments, (theta, t, w, v) order)
# ----------------------------------------------------------------------------------------------


@njit(cache=True)
def contact_wrench(R, t, w, v, p_l, R_l, cp, want_jac):
    """physics.contact_wrench; ``cp`` a packed parameter row. Returns (wrench (6,), J (6x12))."""
    Kfs = _mat3(cp, 0)
    Kfd = _mat3(cp, 9)
    Kts = _mat3(cp, 18)
    Ktd = _mat3(cp, 27)
    beta_f = cp[36]
    beta_t = cp[37]
    iso = cp[38] != 0.0
    Rp = _mv(R, p_l)
    s = np.empty(3)
    for i in range(3):
        s[i] = Rp[i] + t[i] - p_l[i]
    ds = _cross(w, Rp)
    _axpy1(ds, 1.0, v)
    Omega = so3_log(R)
    if not iso:
        Rc = _mm(R, R_l)
        Kfs = _mmt(_mm(Rc, Kfs), Rc)
        Kfd = _mmt(_mm(Rc, Kfd), Rc)
        Kts = _mmt(_mm(Rc, Kts), Rc)
        Ktd = _mmt(_mm(Rc, Ktd), Rc)
    gf = 1.0 + beta_f * (s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
    gt = 1.0 + beta_t * (Omega[0] * Omega[0] + Omega[1] * Omega[1] + Omega[2] * Omega[2])
    ss = _scl1(gf, s)
    OO = _scl1(gt, Omega)
    F = _lin1(-1.0, _mv(Kfs, ss), -1.0, _mv(Kfd, ds))
    p_w = _lin1(1.0, Rp, 1.0, t)
    Tq = _lin1(-1.0, _mv(Kts, OO), -1.0, _mv(Ktd, w))
    _axpy1(Tq, 1.0, _cross(p_w, F))
    wrench = np.empty(6)
    _vput(wrench, 0, F)
    _vput(wrench, 3, Tq)
    J = np.zeros((6, 12))
    if not want_jac:
        return wrench, J
    S_Rp = _skew(Rp)
    Ds = _eye(3, gf)
    _axpy2(Ds, 2.0 * beta_f, _outer(s, s))
    DO = _eye(3, gt)
    _axpy2(DO, 2.0 * beta_t, _outer(Omega, Omega))
    dF_dth = _mm(_mm(Kfs, Ds), S_Rp)
    _axpy2(dF_dth, 1.0, _mm(_mm(Kfd, _skew(w)), S_Rp))
    dT0_dth = _scl2(-1.0, _mm(_mm(Kts, DO), so3_left_jacobian_inverse(Omega)))
    if not iso:
        _axpy2(dF_dth, 1.0, _skew(_mv(Kfs, ss)))
        _axpy2(dF_dth, -1.0, _mm(Kfs, _skew(ss)))
        _axpy2(dF_dth, 1.0, _skew(_mv(Kfd, ds)))
        _axpy2(dF_dth, -1.0, _mm(Kfd, _skew(ds)))
        _axpy2(dT0_dth, 1.0, _skew(_mv(Kts, OO)))
        _axpy2(dT0_dth, -1.0, _mm(Kts, _skew(OO)))
        _axpy2(dT0_dth, 1.0, _skew(_mv(Ktd, w)))
        _axpy2(dT0_dth, -1.0, _mm(Ktd, _skew(w)))
    dF_dt = _scl2(-1.0, _mm(Kfs, Ds))
    dF_dw = _mm(Kfd, S_Rp)
    S_pw = _skew(p_w)
    S_F = _skew(F)
    _put(J, 0, 0, dF_dth)
    _put(J, 0, 3, dF_dt)
    _put(J, 0, 6, dF_dw)
    _put(J, 0, 9, _scl2(-1.0, Kfd))
    B = _mm(S_pw, dF_dth)
    _axpy2(B, 1.0, dT0_dth)
    _axpy2(B, 1.0, _mm(S_F, S_Rp))
    _put(J, 3, 0, B)
    B = _mm(S_pw, dF_dt)
    _axpy2(B, -1.0, S_F)
    _put(J, 3, 3, B)
    B = _mm(S_pw, dF_dw)
    _axpy2(B, -1.0, Ktd)
    _put(J, 3, 6, B)
    _put(J, 3, 9, _scl2(-1.0, _mm(S_pw, Kfd)))
    return wrench, J


@_inline
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
        wr, J = contact_wrench(R, t, w, v, _seg(u, o + 1, 3), _mat3(u, o + 4), CP[c], want_jac)
        for i in range(6):
            per[c, i] = wr[i]
            total[i] += wr[i]
        if want_jac:
            _axpy2(Jsum, 1.0, J)
    return total, per, Jsum


@njit(cache=True)
def required_wrench_x(R, t, w, dw, a, u, m, g):
    """physics.required_wrench and its 6x12 Jacobian with respect to (theta, t, w, v)."""
    Ic = _mat3(u, 9)
    dIc = _mat3(u, 18)
    Rc = _mv(R, _seg(u, 0, 3))
    Rdc = _mv(R, _seg(u, 3, 3))
    Rddc = _mv(R, _seg(u, 6, 3))
    RIRt = _mmt(_mm(R, Ic), R)
    RdIRt = _mmt(_mm(R, dIc), R)
    Rs = _mv(R, _seg(u, 27, 3))
    Rds = _mv(R, _seg(u, 30, 3))
    ag = _seg(a, 0, 3)
    ag[2] += g
    w_Rc = _cross(w, Rc)
    F = _cross(dw, Rc)
    _axpy1(F, 1.0, _cross(w, w_Rc))
    _axpy1(F, 2.0, _cross(w, Rdc))
    _axpy1(F, 1.0, Rddc)
    _axpy1(F, 1.0, ag)
    F = _scl1(m, F)
    Iw = _mv(RIRt, w)
    Tq = _cross(w, Iw)
    _axpy1(Tq, 1.0, _mv(RdIRt, w))
    _axpy1(Tq, 1.0, _mv(RIRt, dw))
    _axpy1(Tq, 1.0, _cross(w, Rs))
    _axpy1(Tq, 1.0, Rds)
    _axpy1(Tq, 1.0, _cross(t, F))
    _axpy1(Tq, m, _cross(Rc, ag))
    wrench = np.empty(6)
    _vput(wrench, 0, F)
    _vput(wrench, 3, Tq)
    Sw = _skew(w)
    S_Rc = _skew(Rc)
    S_t = _skew(t)
    X = _scl2(-1.0, _mm(_skew(dw), S_Rc))
    _axpy2(X, -1.0, _mm(_mm(Sw, Sw), S_Rc))
    _axpy2(X, -2.0, _mm(Sw, _skew(Rdc)))
    _axpy2(X, -1.0, _skew(Rddc))
    dF_dth = _scl2(m, X)
    X = _scl2(-1.0, _skew(w_Rc))
    _axpy2(X, -1.0, _mm(Sw, S_Rc))
    _axpy2(X, -2.0, _skew(Rdc))
    dF_dw = _scl2(m, X)
    dIw_dth = _mm(RIRt, Sw)
    _axpy2(dIw_dth, -1.0, _skew(Iw))
    dT_dth = _mm(Sw, dIw_dth)
    _axpy2(dT_dth, -1.0, _skew(_mv(RdIRt, w)))
    _axpy2(dT_dth, 1.0, _mm(RdIRt, Sw))
    _axpy2(dT_dth, -1.0, _skew(_mv(RIRt, dw)))
    _axpy2(dT_dth, 1.0, _mm(RIRt, _skew(dw)))
    _axpy2(dT_dth, -1.0, _mm(Sw, _skew(Rs)))
    _axpy2(dT_dth, -1.0, _skew(Rds))
    _axpy2(dT_dth, 1.0, _mm(S_t, dF_dth))
    _axpy2(dT_dth, m, _mm(_skew(ag), S_Rc))
    dT_dw = _mm(Sw, RIRt)
    _axpy2(dT_dw, -1.0, _skew(Iw))
    _axpy2(dT_dw, 1.0, RdIRt)
    _axpy2(dT_dw, -1.0, _skew(Rs))
    _axpy2(dT_dw, 1.0, _mm(S_t, dF_dw))
    Jx = np.zeros((6, 12))
    _put(Jx, 0, 0, dF_dth)
    _put(Jx, 0, 6, dF_dw)
    _put(Jx, 3, 0, dT_dth)
    _put(Jx, 3, 3, _scl2(-1.0, _skew(F)))
    _put(Jx, 3, 6, dT_dw)
    return wrench, Jx, RIRt, S_Rc, S_t


@_inline
def forward_dynamics(R, t, w, wrench_c, u, m, g):
    """physics.forward_dynamics: (acc (dw, a), Jx 6x12, Jwrench 6x6, ok)."""
    zero = np.zeros(3)
    r0, _, RIRt, S_Rc, S_t = required_wrench_x(R, t, w, zero, zero, u, m, g)
    A = np.empty((6, 6))
    _put(A, 0, 0, _scl2(-m, S_Rc))
    _put(A, 0, 3, _eye(3, m))
    _put(A, 3, 0, _lin2(1.0, RIRt, -m, _mm(S_t, S_Rc)))
    _put(A, 3, 3, _scl2(m, _lin2(1.0, S_t, 1.0, S_Rc)))
    Ainv, ok = _inv6(A)
    acc = _mv(Ainv, _lin1(1.0, wrench_c, -1.0, r0))
    _, Jr, _, _, _ = required_wrench_x(R, t, w, _seg(acc, 0, 3), _seg(acc, 3, 3), u, m, g)
    return acc, _scl2(-1.0, _mm(Ainv, Jr)), Ainv, ok


@njit(cache=True)
def imu_readings(R, w, dw, a, u, g):
    """physics.imu_readings: (y (6,), H 6x18 over (theta, t, w, v, dw, a))."""
    Rt = _tr(R)
    uu = _mv(Rt, w)
    ud = _mv(Rt, dw)
    p = _seg(u, 42, 3)
    pv = _seg(u, 45, 3)
    RaT = _tr(_mat3(u, 33))
    ag = _seg(a, 0, 3)
    ag[2] += g
    up = _cross(uu, p)
    acc_l = _cross(ud, p)
    _axpy1(acc_l, 1.0, _cross(uu, up))
    _axpy1(acc_l, 2.0, _cross(uu, pv))
    _axpy1(acc_l, 1.0, _seg(u, 48, 3))
    _axpy1(acc_l, 1.0, _mv(Rt, ag))
    y = np.empty(6)
    _vput(y, 0, _mv(RaT, _lin1(1.0, uu, 1.0, _seg(u, 51, 3))))
    _vput(y, 3, _mv(RaT, acc_l))
    H = np.zeros((6, 18))
    du_dth = _mm(Rt, _skew(w))
    dacc_du = _scl2(-1.0, _skew(up))
    _axpy2(dacc_du, -1.0, _mm(_skew(uu), _skew(p)))
    _axpy2(dacc_du, -2.0, _skew(pv))
    dacc_dud = _scl2(-1.0, _skew(p))
    RaTRt = _mm(RaT, Rt)
    _put(H, 0, 0, _mm(RaT, du_dth))
    _put(H, 0, 6, RaTRt)
    X = _mm(dacc_du, du_dth)
    _axpy2(X, 1.0, _mm(_mm(dacc_dud, Rt), _skew(dw)))
    _axpy2(X, 1.0, _mm(Rt, _skew(ag)))
    _put(H, 3, 0, _mm(RaT, X))
    _put(H, 3, 6, _mm(_mm(RaT, dacc_du), Rt))
    _put(H, 3, 12, _mm(_mm(RaT, dacc_dud), Rt))
    _put(H, 3, 15, RaTRt)
    return y, H


# ----------------------------------------------------------------------------------------------
# The filter's step (state x = (t, Omega, v, w, a, dw), as compare.ekf)
# ----------------------------------------------------------------------------------------------


@_inline
def transition(x, u, CP, dt, m, g):
    """EKF.transition with its Jacobian: (x1, F, ok)."""
    t = _seg(x, 0, 3)
    Om = _seg(x, 3, 3)
    v = _seg(x, 6, 3)
    w = _seg(x, 9, 3)
    a = _seg(x, 12, 3)
    dw = _seg(x, 15, 3)
    h = 0.5 * dt * dt
    phi = _lin1(dt, w, h, dw)
    E = so3_exp(phi)
    R1 = _mm(E, so3_exp(Om))
    t1 = _lin1(1.0, t, dt, v)
    _axpy1(t1, h, a)
    v1 = _lin1(1.0, v, dt, a)
    w1 = _lin1(1.0, w, dt, dw)
    Om1 = so3_log(R1)
    W, _, Jc = total_contact_wrench(R1, t1, w1, v1, u, CP, True)
    acc, Jx, Jw, ok = forward_dynamics(R1, t1, w1, W, u, m, g)
    G = _mm(Jw, Jc)  # Jx + Jw Jc: rows (dw, a), columns (theta, t, w, v)
    _axpy2(G, 1.0, Jx)
    Jphi = so3_left_jacobian(phi)
    D = np.zeros((12, 18))
    _put(D, 0, 3, _mm(E, so3_left_jacobian(Om)))
    _put(D, 0, 9, _scl2(dt, Jphi))
    _put(D, 0, 15, _scl2(h, Jphi))
    for i in range(3):
        D[3 + i, i] = 1.0
        D[3 + i, 6 + i] = dt
        D[3 + i, 12 + i] = h
        D[6 + i, 9 + i] = 1.0
        D[6 + i, 15 + i] = dt
        D[9 + i, 6 + i] = 1.0
        D[9 + i, 12 + i] = dt
    F = np.empty((18, 18))
    _put(F, 0, 0, _block(D, 3, 0, 3, 18))
    _put(F, 3, 0, _mm(so3_left_jacobian_inverse(Om1), _block(D, 0, 0, 3, 18)))
    _put(F, 6, 0, _block(D, 9, 0, 3, 18))
    _put(F, 9, 0, _block(D, 6, 0, 3, 18))
    GD = _mm(G, D)
    _put(F, 12, 0, _block(GD, 3, 0, 3, 18))
    _put(F, 15, 0, _block(GD, 0, 0, 3, 18))
    x1 = np.empty(18)
    _vput(x1, 0, t1)
    _vput(x1, 3, Om1)
    _vput(x1, 6, v1)
    _vput(x1, 9, w1)
    for i in range(3):
        x1[12 + i] = acc[3 + i]
        x1[15 + i] = acc[i]
    return x1, F, ok


@_inline
def _paper_to_world(Om):
    M = np.zeros((18, 18))
    _put(M, 0, 3, so3_left_jacobian(Om))
    for i in range(3):
        M[3 + i, i] = 1.0
        M[6 + i, 9 + i] = 1.0
        M[9 + i, 6 + i] = 1.0
        M[12 + i, 15 + i] = 1.0
        M[15 + i, 12 + i] = 1.0
    return M


@_inline
def predict(x, P, u, CP, Q0, dt, m, g):
    """EKF.predict: (x1, P1, status) with status 0 ok, 1 P not positive definite, 5 singular dynamics."""
    x1, F, ok = transition(x, u, CP, dt, m, g)
    if not ok:
        return x1, P, 5
    B = _eye(18, 1.0)
    _put(B, 3, 3, so3_left_jacobian_inverse(_seg(x1, 3, 3)))
    P1 = _mmt(_mm(F, P), F)
    _axpy2(P1, 1.0, _mmt(_mm(B, Q0), B))
    P1 = _sym(P1)
    _, okp = _cholesky(P1)
    if not okp:
        return x1, P1, 1
    return x1, P1, 0


@_inline
def update(x, P, u, Rn, g):
    """EKF.update: (x1, P1, innovation, S, whitened, nis, status)."""
    Om = _seg(x, 3, 3)
    R = so3_exp(Om)
    hx, Hw = imu_readings(R, _seg(x, 9, 3), _seg(x, 15, 3), _seg(x, 12, 3), u, g)
    H = _mm(Hw, _paper_to_world(Om))
    innov = _lin1(1.0, _seg(u, 54, 6), -1.0, hx)
    PHt = _mmt(P, H)
    S = _mm(H, PHt)
    _axpy2(S, 1.0, Rn)
    S = _sym(S)
    L, ok = _cholesky(S)
    white = np.zeros(6)
    if not ok:
        return x, P, innov, S, white, np.inf, 2
    # K = P H^T S^-1, column by column of K^T: S K^T = H P
    K = np.empty((18, 6))
    for j in range(18):
        col = _back_sub_t(L, _forward_sub(L, PHt[j]))
        for i in range(6):
            K[j, i] = col[i]
    white = _forward_sub(L, innov)
    nis = 0.0
    for i in range(6):
        nis += white[i] * white[i]
    x1 = _lin1(1.0, x, 1.0, _mv(K, innov))
    ph2 = x1[3] * x1[3] + x1[4] * x1[4] + x1[5] * x1[5]
    if ph2 > math.pi * math.pi:
        _vput(x1, 3, so3_log(so3_exp(_seg(x1, 3, 3))))
    IKH = _eye(18, 1.0)
    _axpy2(IKH, -1.0, _mm(K, H))
    P1 = _mmt(_mm(IKH, P), IKH)
    _axpy2(P1, 1.0, _mmt(_mm(K, Rn), K))
    P1 = _sym(P1)
    for i in range(18):
        if not math.isfinite(x1[i]):
            return x1, P1, innov, S, white, nis, 4
    _, okp = _cholesky(P1)
    if not okp:
        return x1, P1, innov, S, white, nis, 3
    return x1, P1, innov, S, white, nis, 0


@_inline
def outputs(x, P, u, CP, z0, min_force):
    """EKF.outputs: (world cov, per-contact wrench, wrench cov, cop, cop cov)."""
    Om = _seg(x, 3, 3)
    R = so3_exp(Om)
    M = _paper_to_world(Om)
    Pw = _sym(_mmt(_mm(M, P), M))
    W, per, Jc = total_contact_wrench(R, _seg(x, 0, 3), _seg(x, 9, 3), _seg(x, 6, 3), u, CP, True)
    Wcov = _sym(_mmt(_mm(Jc, _block(Pw, 0, 0, 12, 12)), Jc))
    cop = np.empty(3)
    cop[2] = z0
    cop_cov = np.empty((2, 2))
    Fz = W[2]
    if not Fz > min_force:
        cop[0] = np.nan
        cop[1] = np.nan
        for i in range(2):
            for j in range(2):
                cop_cov[i, j] = np.nan
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
    return Pw, per, Wcov, cop, _mmt(_mm(Jcop, Wcov), Jcop)


@njit(cache=True)
def step(k, x, P, U, CP, Q0, Rn, prm, X, COV, WR, WCOV, COP, COPCOV, INNOV, S_OUT, WHITE, NIS):
    """Predict (k > 0) and update at step k; x and P are overwritten; outputs written at k.

    ``prm`` = (dt, m, g, z0, min_force).  Returns the status (0 ok, see compare.ekf).
    """
    dt = prm[0]
    m = prm[1]
    g = prm[2]
    u = U[k]
    xk = x
    Pk = P
    if k > 0:
        xk, Pk, st = predict(x, P, u, CP, Q0, dt, m, g)
        if st != 0:
            _vput(x, 0, xk)
            _put(P, 0, 0, Pk)
            return st
    x1, P1, innov, S, white, nis, st = update(xk, Pk, u, Rn, g)
    _vput(x, 0, x1)
    _put(P, 0, 0, P1)
    _vput(INNOV[k], 0, innov)
    _put(S_OUT[k], 0, 0, S)
    _vput(WHITE[k], 0, white)
    NIS[k] = nis
    if st != 0:
        return st
    Pw, per, Wcov, cop, cop_cov = outputs(x1, P1, u, CP, prm[3], prm[4])
    _vput(X[k], 0, x1)
    _put(COV[k], 0, 0, Pw)
    _put(WR[k], 0, 0, per)
    _put(WCOV[k], 0, 0, Wcov)
    _vput(COP[k], 0, cop)
    _put(COPCOV[k], 0, 0, cop_cov)
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
