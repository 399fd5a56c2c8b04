r"""The compiled physics core: every law of the model and its analytic Jacobians, written once.

The EKF, both smoothers, the GTSAM factors and the Cramér–Rao bound call these functions;
:mod:`flexforce.factors.physics` is their readable face, with the seed paper's equation numbers
and DESIGN.md's corrections.  Equations are stated there; this module states how they are
computed.

Representation
--------------
Inside the core a 3-vector is a tuple of three floats and a 3x3 matrix a tuple of its three rows.
numba keeps tuples in registers: the laws allocate nothing on the heap, which is what makes the
EKF step cost about as much as the authors' C++ one (an ``np.empty(3)`` costs ~40 ns in numba, and
one step used to make ~700 of them).  The public functions take and fill numpy arrays.

State of one step (the columns of every Jacobian, world-frame increments, rotation first)::

    s = (theta, t, w, v, dw, a)        18 components: rad, m, rad/s, m/s, rad/s^2, m/s^2

(the state layout :data:`flexforce.datasets.layout.STATE`, whose ``STATE_DIM`` this module
re-exports), passed as ``R`` (3x3, local to world) and ``q = (t, w, v, dw, a)`` (15,).  A wrench is
``(F, T)`` (N, N m about the world origin), world axes.  A contact's rest placement in the world
(its foothold) is ``(p_r, R_r)``; its increments are ``p_r <- p_r + d_p`` and
``R_r <- exp([d_r]x) R_r`` (world frame), columns ``(d_p, d_r)`` of the 6x6 ``Jr``.
"""

from __future__ import annotations

import math

import numpy as np

from flexforce.datasets.layout import STATE_DIM as STATE_DIM  # columns of a per-step Jacobian
from flexforce.jit import HAVE_NUMBA as HAVE_NUMBA  # re-exported: the kernels decorate with core.njit
from flexforce.jit import njit as njit

# ----------------------------------------------------------------------------------------------
# 3-vectors and 3x3 matrices as tuples
# ----------------------------------------------------------------------------------------------


@njit
def ld3(a, o):
    """``a[o:o+3]`` as a 3-tuple."""
    return (a[o], a[o + 1], a[o + 2])


@njit
def ldm(A):
    """A 3x3 array as a tuple of rows."""
    return ((A[0, 0], A[0, 1], A[0, 2]), (A[1, 0], A[1, 1], A[1, 2]), (A[2, 0], A[2, 1], A[2, 2]))


@njit
def ldm9(a, o):
    """The 3x3 matrix stored row-major at ``a[o:o+9]``."""
    return ((a[o], a[o + 1], a[o + 2]), (a[o + 3], a[o + 4], a[o + 5]), (a[o + 6], a[o + 7], a[o + 8]))


@njit
def st3(out, o, x):
    out[o] = x[0]
    out[o + 1] = x[1]
    out[o + 2] = x[2]


@njit
def stm(out, r, c, M):
    """``out[r:r+3, c:c+3] = M``."""
    for i in range(3):
        for j in range(3):
            out[r + i, c + j] = M[i][j]


@njit
def residual6(r, a, b, y):
    """``r = (a, b) - y``: a 6-row residual from two 3-tuples and a measured or variable 6-vector."""
    for i in range(3):
        r[i] = a[i] - y[i]
        r[3 + i] = b[i] - y[3 + i]


@njit
def stm_band(out, r, B0, B1, B2, B3, B4, B5):
    """``out[r:r+3, 0:18] = [B0 .. B5]``: a 3-row band of a per-step Jacobian, one 3x3 block per
    state component (theta, t, w, v, dw, a)."""
    stm(out, r, 0, B0)
    stm(out, r, 3, B1)
    stm(out, r, 6, B2)
    stm(out, r, 9, B3)
    stm(out, r, 12, B4)
    stm(out, r, 15, B5)


@njit
def stm_add(out, r, c, M):
    """``out[r:r+3, c:c+3] += M``."""
    for i in range(3):
        for j in range(3):
            out[r + i, c + j] += M[i][j]


@njit
def vadd(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@njit
def vsub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@njit
def vscl(s, a):
    return (s * a[0], s * a[1], s * a[2])


@njit
def vaxpy(a, s, b):
    """``a + s b``."""
    return (a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2])


@njit
def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit
def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@njit
def skew(v):
    """``[v]x``: ``skew(a) b = a x b``."""
    return ((0.0, -v[2], v[1]), (v[2], 0.0, -v[0]), (-v[1], v[0], 0.0))


@njit
def eye(d):
    """``d I``."""
    return ((d, 0.0, 0.0), (0.0, d, 0.0), (0.0, 0.0, d))


@njit
def outer(a, b):
    return ((a[0] * b[0], a[0] * b[1], a[0] * b[2]),
            (a[1] * b[0], a[1] * b[1], a[1] * b[2]),
            (a[2] * b[0], a[2] * b[1], a[2] * b[2]))


@njit
def mv(A, x):
    return (dot(A[0], x), dot(A[1], x), dot(A[2], x))


@njit
def tr(A):
    return ((A[0][0], A[1][0], A[2][0]), (A[0][1], A[1][1], A[2][1]), (A[0][2], A[1][2], A[2][2]))


@njit
def mtv(A, x):
    """``A^T x``."""
    return (A[0][0] * x[0] + A[1][0] * x[1] + A[2][0] * x[2],
            A[0][1] * x[0] + A[1][1] * x[1] + A[2][1] * x[2],
            A[0][2] * x[0] + A[1][2] * x[1] + A[2][2] * x[2])


@njit
def mmt(A, B):
    """``A B^T``."""
    return ((dot(A[0], B[0]), dot(A[0], B[1]), dot(A[0], B[2])),
            (dot(A[1], B[0]), dot(A[1], B[1]), dot(A[1], B[2])),
            (dot(A[2], B[0]), dot(A[2], B[1]), dot(A[2], B[2])))


@njit
def mm(A, B):
    return mmt(A, tr(B))


@njit
def mtm(A, B):
    """``A^T B``."""
    return mmt(tr(A), tr(B))


@njit
def madd(A, B):
    return (vadd(A[0], B[0]), vadd(A[1], B[1]), vadd(A[2], B[2]))


@njit
def msub(A, B):
    return (vsub(A[0], B[0]), vsub(A[1], B[1]), vsub(A[2], B[2]))


@njit
def mscl(s, A):
    return (vscl(s, A[0]), vscl(s, A[1]), vscl(s, A[2]))


@njit
def maxpy(A, s, B):
    """``A + s B``."""
    return (vaxpy(A[0], s, B[0]), vaxpy(A[1], s, B[1]), vaxpy(A[2], s, B[2]))


@njit
def rotate(Rc, K):
    """``Rc K Rc^T``: a contact-frame matrix in the world (correction 5)."""
    return mmt(mm(Rc, K), Rc)


@njit
def inv3(A):
    """Inverse of a 3x3 matrix by its adjugate; ``(Ainv, det)``, ``det == 0`` when singular."""
    c0 = cross(A[1], A[2])
    c1 = cross(A[2], A[0])
    c2 = cross(A[0], A[1])
    det = dot(A[0], c0)
    if det == 0.0:
        return eye(0.0), 0.0
    return mscl(1.0 / det, tr((c0, c1, c2))), det


# ----------------------------------------------------------------------------------------------
# Small dense linear algebra, in place (the EKF's 6x6 and 18x18 systems, the smoothers' blocks)
# ----------------------------------------------------------------------------------------------


@njit
def cholesky_into(S, L):
    """Lower Cholesky factor of ``S`` (n x n) into ``L`` (lower triangle); False if ``S`` is not
    positive definite."""
    n = S.shape[0]
    for j in range(n):
        d = S[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:
            return False
        L[j, j] = math.sqrt(d)
        for i in range(j + 1, n):
            s = S[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    return True


@njit
def trsv_lower_inplace(L, x):
    """``x <- L^-1 x`` for lower-triangular ``L``."""
    for i in range(x.shape[0]):
        acc = x[i]
        for k in range(i):
            acc -= L[i, k] * x[k]
        x[i] = acc / L[i, i]


@njit
def trsv_upper_t_inplace(L, x):
    """``x <- L^-T x`` for lower-triangular ``L``."""
    for i in range(x.shape[0] - 1, -1, -1):
        acc = x[i]
        for k in range(i + 1, x.shape[0]):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]


@njit
def matmul_into(A, B, out):
    """``out = A B`` (any layouts, no temporaries)."""
    for i in range(A.shape[0]):
        for j in range(B.shape[1]):
            s = 0.0
            for k in range(A.shape[1]):
                s += A[i, k] * B[k, j]
            out[i, j] = s


# ----------------------------------------------------------------------------------------------
# SO(3) (as flexforce.factors.so3, whose closed forms and series are tested against mpmath)
# ----------------------------------------------------------------------------------------------


@njit
def _rodrigues(phi, a, b):
    """``I + a [phi]x + b [phi]x^2``."""
    K = skew(phi)
    return madd(maxpy(eye(1.0), a, K), mscl(b, mm(K, K)))


@njit
def exp_t(phi):
    th2 = dot(phi, phi)
    if th2 < 1e-16:
        return _rodrigues(phi, 1.0, 0.5)
    th = math.sqrt(th2)
    return _rodrigues(phi, math.sin(th) / th, (1.0 - math.cos(th)) / th2)


@njit
def log_t(R):
    """Rotation vector, accurate up to pi (the axis from the symmetric part near pi)."""
    w = (R[2][1] - R[1][2], R[0][2] - R[2][0], R[1][0] - R[0][1])
    cos_t = 0.5 * (R[0][0] + R[1][1] + R[2][2] - 1.0)
    sin_t = 0.5 * math.sqrt(dot(w, w))
    theta = math.atan2(sin_t, cos_t)
    if cos_t > -0.9:
        if sin_t < 1e-8:
            return vscl(0.5 * (1.0 + sin_t * sin_t / 6.0), w)
        return vscl(0.5 * theta / sin_t, w)
    S = madd(R, tr(R))
    d0 = 0.5 * S[0][0] - cos_t
    d1 = 0.5 * S[1][1] - cos_t
    d2 = 0.5 * S[2][2] - cos_t
    if d0 >= d1 and d0 >= d2:
        axis = (d0, 0.5 * S[1][0], 0.5 * S[2][0])
    elif d1 >= d2:
        axis = (0.5 * S[0][1], d1, 0.5 * S[2][1])
    else:
        axis = (0.5 * S[0][2], 0.5 * S[1][2], d2)
    sgn = 1.0 if dot(axis, w) >= 0.0 else -1.0
    return vscl(sgn * theta / math.sqrt(dot(axis, axis)), axis)


@njit
def jl_t(phi):
    """Left Jacobian ``J_l(phi)``."""
    th2 = dot(phi, phi)
    if th2 < 1e-2:
        a = 0.5 - th2 * (1.0 / 24.0 - th2 * (1.0 / 720.0 - th2 / 40320.0))
        b = 1.0 / 6.0 - th2 * (1.0 / 120.0 - th2 * (1.0 / 5040.0 - th2 / 362880.0))
    else:
        th = math.sqrt(th2)
        h = math.sin(0.5 * th) / th
        a = 2.0 * h * h
        b = (th - math.sin(th)) / (th2 * th)
    return _rodrigues(phi, a, b)


@njit
def jl_inv_t(phi):
    """``J_l(phi)^-1``."""
    th2 = dot(phi, phi)
    if th2 < 1e-2:
        c = 1.0 / 12.0 + th2 * (1.0 / 720.0 + th2 * (1.0 / 30240.0 + th2 / 1209600.0))
    else:
        th = math.sqrt(th2)
        c = 1.0 / th2 - 0.5 / (th * math.tan(0.5 * th))
    return _rodrigues(phi, -0.5, c)


@njit
def so3_exp(phi):
    """Rodrigues' formula, array in, 3x3 array out."""
    out = np.empty((3, 3))
    stm(out, 0, 0, exp_t(ld3(phi, 0)))
    return out


@njit
def so3_log(R):
    """Rotation vector of a 3x3 array (accurate up to pi)."""
    out = np.empty(3)
    st3(out, 0, log_t(ldm(R)))
    return out


@njit
def so3_jl(phi, inverse=False):
    """``J_l(phi)`` or (``inverse``) ``J_l(phi)^-1``, 3x3 array."""
    out = np.empty((3, 3))
    p = ld3(phi, 0)
    stm(out, 0, 0, jl_inv_t(p) if inverse else jl_t(p))
    return out


@njit
def so3_exp_jl_all(phi, E, Jl):
    """``E[i] = exp(phi[i])`` and ``Jl[i] = J_l(phi[i])`` for (n, 3) rotation vectors, in one pass
    (per row, :func:`so3_exp` and :func:`so3_jl` called from Python cost 2 us each: 16 ms a
    linearisation of the IMU mounting on 4000 steps)."""
    for i in range(phi.shape[0]):
        p = ld3(phi[i], 0)
        stm(E[i], 0, 0, exp_t(p))
        stm(Jl[i], 0, 0, jl_t(p))


@njit
def so3_jl_inv(phi):
    return so3_jl(phi, True)


# ----------------------------------------------------------------------------------------------
# The laws on tuples
# ----------------------------------------------------------------------------------------------


@njit
def contact_t(R, t, w, v, p_l, R_l, p_r, R_r, Kfs, Kfd, Kts, Ktd, beta_f, beta_t, iso):
    """Contact law (eq. 6-12, corrections 1, 2, 5) with a world rest placement ``(p_r, R_r)``::

        s = R p_l + t - p_r,   ds = [w]x R p_l + v,   Omega = log(R R_l R_r^T)
        F = -K_fs s (1 + beta_f |s|^2) - K_fd ds
        T = -K_ts Omega (1 + beta_t |Omega|^2) - K_td w + [R p_l + t]x F

    Returns ``F, T`` and the blocks of ``d(F, T)/d(theta, t, w, v)`` (``d*_dv``: ``dF_dv = -K_fd``,
    ``dT_dv = [p]x dF_dv``) and of ``d(F, T)/d(p_r, r_r)``.
    """
    Rp = mv(R, p_l)
    p_w = vadd(Rp, t)
    s = vsub(p_w, p_r)
    ds = vadd(cross(w, Rp), v)
    Rc = mm(R, R_l)
    Q = mmt(Rc, R_r)
    Om = log_t(Q)
    if not iso:
        Kfs = rotate(Rc, Kfs)
        Kfd = rotate(Rc, Kfd)
        Kts = rotate(Rc, Kts)
        Ktd = rotate(Rc, Ktd)
    gf = 1.0 + beta_f * dot(s, s)
    gt = 1.0 + beta_t * dot(Om, Om)
    ss = vscl(gf, s)
    OO = vscl(gt, Om)
    F = vsub(vscl(-1.0, mv(Kfs, ss)), mv(Kfd, ds))
    T = vadd(vsub(vscl(-1.0, mv(Kts, OO)), mv(Ktd, w)), cross(p_w, F))
    # d(s (1 + beta |s|^2))/ds
    Ds = maxpy(eye(gf), 2.0 * beta_f, outer(s, s))
    DO = maxpy(eye(gt), 2.0 * beta_t, outer(Om, Om))
    S_Rp = skew(Rp)
    KDs = mm(Kfs, Ds)
    # d log(exp(d) Q)/dd = J_l^-1(Omega); ds/dtheta = -[Rp]x; d ds/dtheta = -[w]x [Rp]x
    KDJ = mm(mm(Kts, DO), jl_inv_t(Om))
    dF_dth = madd(mm(KDs, S_Rp), mm(mm(Kfd, skew(w)), S_Rp))
    dT0_dth = mscl(-1.0, KDJ)
    if not iso:
        # d(K_world y)/dtheta = -[K y]x + K [y]x for y held fixed (correction 5).
        dF_dth = madd(dF_dth, madd(msub(skew(mv(Kfs, ss)), mm(Kfs, skew(ss))),
                                   msub(skew(mv(Kfd, ds)), mm(Kfd, skew(ds)))))
        dT0_dth = madd(dT0_dth, madd(msub(skew(mv(Kts, OO)), mm(Kts, skew(OO))),
                                     msub(skew(mv(Ktd, w)), mm(Ktd, skew(w)))))
    dF_dt = mscl(-1.0, KDs)
    dF_dw = mm(Kfd, S_Rp)
    dF_dv = mscl(-1.0, Kfd)
    S_pw = skew(p_w)
    S_F = skew(F)
    # d([p]x F) = -[F]x dp + [p]x dF,  dp/dtheta = -[Rp]x, dp/dt = I
    dT_dth = madd(madd(dT0_dth, mm(S_F, S_Rp)), mm(S_pw, dF_dth))
    dT_dt = msub(mm(S_pw, dF_dt), S_F)
    dT_dw = msub(mm(S_pw, dF_dw), Ktd)
    dT_dv = mm(S_pw, dF_dv)
    # Foothold: ds/dp_r = -I; log(Q exp(-d_r)) = log(exp(-Q d_r) Q): dOmega/dr_r = -J_l^-1 Q
    dF_dpr = KDs
    dT_dpr = mm(S_pw, KDs)
    dT_drr = mm(KDJ, Q)
    return (F, T, dF_dth, dF_dt, dF_dw, dF_dv, dT_dth, dT_dt, dT_dw, dT_dv, dF_dpr, dT_dpr, dT_drr)


@njit
def required_t(R, t, w, dw, a, m, c, dc, ddc, I, dI, sig, dsig, g):
    """Newton-Euler (eq. 15-16, 22-23, corrections 2-3): the wrench the motion requires.

    Returns ``F, T`` and the blocks of their Jacobian with respect to ``(theta, t, w)`` (none
    on ``v``), plus ``RIRt = R I R^T`` and ``[R c]x`` from which the acceleration block
    ``d(F, T)/d(dw, a)`` is built (:func:`accel_block_t`).
    """
    Rc = mv(R, c)
    Rdc = mv(R, dc)
    Rddc = mv(R, ddc)
    RIRt = rotate(R, I)
    RdIRt = rotate(R, dI)
    Rs = mv(R, sig)
    Rds = mv(R, dsig)
    ag = (a[0], a[1], a[2] + g)
    w_Rc = cross(w, Rc)
    F = vscl(m, vadd(vadd(vadd(cross(dw, Rc), cross(w, w_Rc)), vscl(2.0, cross(w, Rdc))), vadd(Rddc, ag)))
    Iw = mv(RIRt, w)
    T = vadd(vadd(vadd(cross(w, Iw), mv(RdIRt, w)), vadd(mv(RIRt, dw), cross(w, Rs))),
             vadd(vadd(Rds, cross(t, F)), vscl(m, cross(Rc, ag))))
    Sw = skew(w)
    S_Rc = skew(Rc)
    S_t = skew(t)
    # For a world vector u = R u_l: du/dtheta = -[u]x;
    # d(R X R^T y)/dtheta = -[X' y]x + X' [y]x  (X' = R X R^T)
    dF_dth = mscl(m, madd(madd(mm(skew(dw), S_Rc), mm(mm(Sw, Sw), S_Rc)),
                          madd(mscl(2.0, mm(Sw, skew(Rdc))), skew(Rddc))))
    dF_dth = mscl(-1.0, dF_dth)
    dF_dw = mscl(-m, madd(madd(skew(w_Rc), mm(Sw, S_Rc)), mscl(2.0, skew(Rdc))))
    dIw_dth = msub(mm(RIRt, Sw), skew(Iw))
    dT_dth = madd(madd(mm(Sw, dIw_dth), msub(mm(RdIRt, Sw), skew(mv(RdIRt, w)))),
                  madd(msub(mm(RIRt, skew(dw)), skew(mv(RIRt, dw))),
                       mscl(-1.0, madd(mm(Sw, skew(Rs)), skew(Rds)))))
    dT_dth = madd(dT_dth, madd(mm(S_t, dF_dth), mscl(m, mm(skew(ag), S_Rc))))
    dT_dt = mscl(-1.0, skew(F))
    dT_dw = madd(msub(mm(Sw, RIRt), skew(Iw)), madd(msub(RdIRt, skew(Rs)), mm(S_t, dF_dw)))
    return F, T, dF_dth, dF_dw, dT_dth, dT_dt, dT_dw, RIRt, S_Rc, S_t


@njit
def accel_block_t(m, RIRt, S_Rc, S_t):
    """``d(F, T)_required/d(dw, a)``: ``[[-m [Rc]x, m I], [RIRt - m [t]x [Rc]x, m ([t]x + [Rc]x)]]``."""
    return (mscl(-m, S_Rc), eye(m), msub(RIRt, mscl(m, mm(S_t, S_Rc))), mscl(m, madd(S_t, S_Rc)))


@njit
def accel_solve_t(m, RIRt, S_Rc, S_t):
    """Inverse of the acceleration block by its structure (eq. 24, 25): with
    ``I_c = R I R^T + m [Rc]x^2`` (the inertia about the CoM, rotated),
    ``dw = I_c^-1 (T - ([t]x + [Rc]x) F)`` and ``a = F / m + [Rc]x dw``.

    Returns the four 3x3 blocks of ``A^-1`` (rows ``(dw, a)``, columns ``(F, T)``) and ``det I_c``.
    """
    Ic_inv, det = inv3(madd(RIRt, mscl(m, mm(S_Rc, S_Rc))))
    if m == 0.0:
        det = 0.0
        m = 1.0
    L = mm(Ic_inv, madd(S_t, S_Rc))
    dw_F = mscl(-1.0, L)
    dw_T = Ic_inv
    a_F = msub(eye(1.0 / m), mm(S_Rc, L))
    a_T = mm(S_Rc, Ic_inv)
    return dw_F, dw_T, a_F, a_T, det


@njit
def imu_t(R, w, dw, a, Ra, p, pv, pa, pw, g):
    """Gyro and accelerometer readings in the IMU frame (eq. 26-28, correction 6) and the blocks
    of their Jacobian on ``theta, w, dw, a`` (none on ``t``, ``v``)."""
    u = mtv(R, w)
    ud = mtv(R, dw)
    ag = (a[0], a[1], a[2] + g)
    up = cross(u, p)
    acc_l = vadd(vadd(vadd(cross(ud, p), cross(u, up)), vscl(2.0, cross(u, pv))), vadd(pa, mtv(R, ag)))
    yg = mtv(Ra, vadd(u, pw))
    ya = mtv(Ra, acc_l)
    RaT = tr(Ra)
    Rt = tr(R)
    # d(R^T y)/dtheta = R^T [y]x
    du_dth = mm(Rt, skew(w))
    dacc_du = mscl(-1.0, madd(madd(skew(up), mm(skew(u), skew(p))), mscl(2.0, skew(pv))))
    dacc_dud = mscl(-1.0, skew(p))
    RaTRt = mm(RaT, Rt)
    g_th = mm(RaT, du_dth)
    a_th = mm(RaT, madd(madd(mm(dacc_du, du_dth), mm(mm(dacc_dud, Rt), skew(dw))), mm(Rt, skew(ag))))
    a_w = mm(mm(RaT, dacc_du), Rt)
    a_dw = mm(mm(RaT, dacc_dud), Rt)
    return yg, ya, g_th, RaTRt, a_th, a_w, a_dw


# ----------------------------------------------------------------------------------------------
# One step, arrays in and out (residual = model minus measurement or minus variable)
# ----------------------------------------------------------------------------------------------


@njit
def contact_law(R, q, W, p_l, R_l, p_r, R_r, Kfs, Kfd, Kts, Ktd, beta_f, beta_t, iso, r, J, Jr):
    """Contact-law residual ``f(R, t, w, v; p_r, R_r) - W`` into ``r`` (6,), ``dr/ds`` into ``J``
    (6, 18) and ``dr/d(p_r, r_r)`` into ``Jr`` (6, 6) unless ``Jr`` has no rows.

    ``f`` is :func:`contact_t`; the stiffness and damping matrices are in the contact frame
    (rotated into the world unless ``iso``).  ``dr/dW = -I``.
    """
    (F, T, dF_dth, dF_dt, dF_dw, dF_dv, dT_dth, dT_dt, dT_dw, dT_dv, dF_dpr, dT_dpr, dT_drr) = contact_t(
        ldm(R), ld3(q, 0), ld3(q, 3), ld3(q, 6), ld3(p_l, 0), ldm(R_l), ld3(p_r, 0), ldm(R_r),
        ldm(Kfs), ldm(Kfd), ldm(Kts), ldm(Ktd), beta_f, beta_t, iso)
    residual6(r, F, T, W)
    z = eye(0.0)
    stm_band(J, 0, dF_dth, dF_dt, dF_dw, dF_dv, z, z)
    stm_band(J, 3, dT_dth, dT_dt, dT_dw, dT_dv, z, z)
    if Jr.shape[0] > 0:
        stm(Jr, 0, 0, dF_dpr)
        stm(Jr, 0, 3, eye(0.0))
        stm(Jr, 3, 0, dT_dpr)
        stm(Jr, 3, 3, dT_drr)


@njit
def newton_euler(R, q, Wsum, m, c, dc, ddc, I, dI, sig, dsig, g, r, J):
    """Newton-Euler residual ``required_wrench - Wsum`` into ``r`` (6,), ``dr/ds`` into ``J`` (6, 18)."""
    F, T, dF_dth, dF_dw, dT_dth, dT_dt, dT_dw, RIRt, S_Rc, S_t = required_t(
        ldm(R), ld3(q, 0), ld3(q, 3), ld3(q, 9), ld3(q, 12), m, ld3(c, 0), ld3(dc, 0), ld3(ddc, 0),
        ldm(I), ldm(dI), ld3(sig, 0), ld3(dsig, 0), g)
    residual6(r, F, T, Wsum)
    A_Fdw, A_Fa, A_Tdw, A_Ta = accel_block_t(m, RIRt, S_Rc, S_t)
    z = eye(0.0)
    stm_band(J, 0, dF_dth, z, dF_dw, z, A_Fdw, A_Fa)
    stm_band(J, 3, dT_dth, dT_dt, dT_dw, z, A_Tdw, A_Ta)


@njit
def forward_dynamics(R, q, Wc, m, c, dc, ddc, I, dI, sig, dsig, g, acc, Jx, Jw):
    """Accelerations ``(dw, a)`` into ``acc`` (6,) that solve ``required_wrench(dw, a) = Wc``
    (eq. 24, 25, correction 4), ``d acc/d(theta, t, w, v)`` into ``Jx`` (6, 12) and
    ``d acc/d Wc`` into ``Jw`` (6, 6) (implicit function theorem: ``-A^-1 dr/dx``, ``A^-1``).

    The required wrench is affine in the accelerations, ``r0 + A (dw, a)``; ``A`` is solved by its
    structure (:func:`accel_solve_t`).  Returns False when ``A`` is singular.  ``q[9:15]`` is
    not read.
    """
    Rt = ldm(R)
    t = ld3(q, 0)
    w = ld3(q, 3)
    cc, dcc, ddcc, II, dII, ss, dss = (ld3(c, 0), ld3(dc, 0), ld3(ddc, 0), ldm(I), ldm(dI), ld3(sig, 0),
                                       ld3(dsig, 0))
    zero = (0.0, 0.0, 0.0)
    F0, T0, _, _, _, _, _, RIRt, S_Rc, S_t = required_t(Rt, t, w, zero, zero, m, cc, dcc, ddcc, II, dII, ss, dss, g)
    dw_F, dw_T, a_F, a_T, det = accel_solve_t(m, RIRt, S_Rc, S_t)
    if not (det != 0.0 and math.isfinite(det)):
        return False
    bF = vsub(ld3(Wc, 0), F0)
    bT = vsub(ld3(Wc, 3), T0)
    dw = vadd(mv(dw_F, bF), mv(dw_T, bT))
    a = vadd(mv(a_F, bF), mv(a_T, bT))
    st3(acc, 0, dw)
    st3(acc, 3, a)
    _, _, dF_dth, dF_dw, dT_dth, dT_dt, dT_dw, _, _, _ = required_t(Rt, t, w, dw, a, m, cc, dcc, ddcc, II, dII,
                                                                    ss, dss, g)
    stm(Jw, 0, 0, dw_F)
    stm(Jw, 0, 3, dw_T)
    stm(Jw, 3, 0, a_F)
    stm(Jw, 3, 3, a_T)
    # -A^-1 [[dF_dth, 0, dF_dw, 0], [dT_dth, dT_dt, dT_dw, 0]]
    stm(Jx, 0, 0, mscl(-1.0, madd(mm(dw_F, dF_dth), mm(dw_T, dT_dth))))
    stm(Jx, 0, 3, mscl(-1.0, mm(dw_T, dT_dt)))
    stm(Jx, 0, 6, mscl(-1.0, madd(mm(dw_F, dF_dw), mm(dw_T, dT_dw))))
    stm(Jx, 0, 9, eye(0.0))
    stm(Jx, 3, 0, mscl(-1.0, madd(mm(a_F, dF_dth), mm(a_T, dT_dth))))
    stm(Jx, 3, 3, mscl(-1.0, mm(a_T, dT_dt)))
    stm(Jx, 3, 6, mscl(-1.0, madd(mm(a_F, dF_dw), mm(a_T, dT_dw))))
    stm(Jx, 3, 9, eye(0.0))
    return True


@njit
def imu(R, q, y, Ra, p, pv, pa, pw, g, r, J):
    """IMU residual ``h(s) - y`` (gyro rad/s, accelerometer m/s^2, IMU frame) into ``r``, ``dr/ds``
    into ``J`` (6, 18)."""
    yg, ya, g_th, RaTRt, a_th, a_w, a_dw = imu_t(ldm(R), ld3(q, 3), ld3(q, 9), ld3(q, 12), ldm(Ra), ld3(p, 0),
                                                 ld3(pv, 0), ld3(pa, 0), ld3(pw, 0), g)
    residual6(r, yg, ya, y)
    z = eye(0.0)
    stm_band(J, 0, g_th, z, RaTRt, z, z, z)
    stm_band(J, 3, a_th, z, a_w, z, a_dw, RaTRt)


@njit
def integration(R0, q0, R1, q1, dt, r, J0, J1):
    """Integration residual (12,) between steps 0 and 1 ``dt`` s apart (acceleration linear in time
    over the step), and its two (12, 18) Jacobians::

        r_theta = log(R1 R0^T) - (T w0 + T^2/6 (2 dw0 + dw1))
        r_t     = t1 - t0 - (T v0 + T^2/6 (2 a0 + a1))
        r_w     = w1 - w0 - T/2 (dw0 + dw1)
        r_v     = v1 - v0 - T/2 (a0 + a1)

    (the rotation line neglects the commutator ``w x dw T^3/12``, below 1e-9 rad here).
    """
    h2 = dt * dt / 6.0
    Q = mmt(ldm(R1), ldm(R0))
    phi = log_t(Q)
    Jinv = jl_inv_t(phi)
    for i in range(3):
        r[i] = phi[i] - (dt * q0[3 + i] + h2 * (2.0 * q0[9 + i] + q1[9 + i]))
        r[3 + i] = q1[i] - q0[i] - (dt * q0[6 + i] + h2 * (2.0 * q0[12 + i] + q1[12 + i]))
        r[6 + i] = q1[3 + i] - q0[3 + i] - 0.5 * dt * (q0[9 + i] + q1[9 + i])
        r[9 + i] = q1[6 + i] - q0[6 + i] - 0.5 * dt * (q0[12 + i] + q1[12 + i])
    J0[:, :] = 0.0
    J1[:, :] = 0.0
    # log(R1 R0^T exp(-d0)) and log(exp(d1) R1 R0^T): -J_l^-1(phi) exp(phi) and J_l^-1(phi)
    stm(J0, 0, 0, mscl(-1.0, mm(Jinv, Q)))
    stm(J1, 0, 0, Jinv)
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
    """F/T residual: the contact wrench ``W`` seen by a sensor at the contact (moving with the
    flexibility), ``(R_c^T F, R_c^T (T - p_c x F))`` with ``R_c = R R_l``, ``p_c = R p_l + t``,
    minus the reading ``y``.  ``Js`` (6, 18) on the state, ``JW`` (6, 6) on ``W``.  NaN
    readings give zero rows (the component is not measured).
    """
    Rm = ldm(R)
    Rc = mm(Rm, ldm(R_l))
    Rp = mv(Rm, ld3(p_l, 0))
    p = vadd(Rp, ld3(q, 0))
    F = ld3(W, 0)
    u = vsub(ld3(W, 3), cross(p, F))
    Fl = mtv(Rc, F)
    Tl = mtv(Rc, u)
    RcT = tr(Rc)
    S_F = skew(F)
    Js[:, :] = 0.0
    JW[:, :] = 0.0
    stm(Js, 0, 0, mm(RcT, S_F))
    stm(Js, 3, 0, mm(RcT, msub(skew(u), mm(S_F, skew(Rp)))))
    stm(Js, 3, 3, mm(RcT, S_F))
    stm(JW, 0, 0, RcT)
    stm(JW, 3, 0, mscl(-1.0, mm(RcT, skew(p))))
    stm(JW, 3, 3, RcT)
    residual6(r, Fl, Tl, y)
    for i in range(6):
        if not np.isfinite(y[i]):
            r[i] = 0.0
            Js[i, :] = 0.0
            JW[i, :] = 0.0


@njit
def center_of_pressure(W, z0, min_force, p, J):
    """CoP on the plane ``z = z0`` of a wrench ``W`` (about the world origin) into ``p`` (3,) and
    its 3x6 Jacobian into ``J``: ``px = (z0 F_x - T_y) / F_z``, ``py = (T_x + z0 F_y) / F_z``.
    NaN when ``F_z <= min_force`` (N).  Returns whether it is defined."""
    Fz = W[2]
    J[:, :] = 0.0
    p[2] = z0
    if not Fz > min_force:
        p[0] = np.nan
        p[1] = np.nan
        J[:, :] = np.nan
        return False
    px = (z0 * W[0] - W[4]) / Fz
    py = (W[3] + z0 * W[1]) / Fz
    p[0] = px
    p[1] = py
    J[0, 0] = z0 / Fz
    J[0, 2] = -px / Fz
    J[0, 4] = -1.0 / Fz
    J[1, 1] = z0 / Fz
    J[1, 2] = -py / Fz
    J[1, 3] = 1.0 / Fz
    return True


@njit
def centers_of_pressure(W, z0, min_force, p, J):
    """:func:`center_of_pressure` of every wrench ``W`` (N, 6) into ``p`` (N, 3) and ``J`` (N, 3, 6)."""
    for k in range(W.shape[0]):
        center_of_pressure(W[k], z0, min_force, p[k], J[k])


# ----------------------------------------------------------------------------------------------
# All steps (batch linearisation)
# ----------------------------------------------------------------------------------------------


@njit
def newton_euler_all(Rs, Q, Wsum, m, c, dc, ddc, I, dI, sig, dsig, g, r, J):
    for k in range(Rs.shape[0]):
        newton_euler(Rs[k], Q[k], Wsum[k], m, c[k], dc[k], ddc[k], I[k], dI[k], sig[k], dsig[k], g, r[k], J[k])


@njit
def contact_all(Rs, Q, W, active, P, PR, Pr, RR, Kfs, Kfd, Kts, Ktd, beta, iso, r, J, Jr):
    """Per step and contact (rest placements ``Pr``, ``RR`` in the world); an inactive contact gets
    ``r = -W`` (its wrench held at zero), ``J = 0``.  ``Jr`` (N, C, 6, 6), or with no rows to skip."""
    n, nc = active.shape
    want_r = Jr.shape[0] > 0
    none = np.empty((0, 6))
    for k in range(n):
        for i in range(nc):
            if active[k, i]:
                contact_law(Rs[k], Q[k], W[k, i], P[k, i], PR[k, i], Pr[k, i], RR[k, i], Kfs[i], Kfd[i], Kts[i],
                            Ktd[i], beta[i, 0], beta[i, 1], iso[i], r[k, i], J[k, i],
                            Jr[k, i] if want_r else none)
            else:
                for j in range(6):
                    r[k, i, j] = -W[k, i, j]
                J[k, i, :, :] = 0.0
                if want_r:
                    Jr[k, i, :, :] = 0.0


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
        stm(Rs[k], 0, 0, mm(exp_t(ld3(dS[k], 0)), ldm(Rs[k])))
        for j in range(15):
            Q[k, j] += dS[k, 3 + j]
