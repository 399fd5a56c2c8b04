r"""The step of the EKF of :mod:`flexforce.compare.ekf.filter`, compiled (numba): the only one there is.

The physics is the core's (:mod:`flexforce.factors.core`: contact law, Newton-Euler, forward
dynamics, IMU model, SO(3)); this module adds the filter: the transition and its Jacobian in the
paper's parametrisation, the covariance prediction, the correction and the per-step outputs.

Why it is written this way (measured with ``benchmarks/ekf_speed.py``): the physics runs on tuples
(no heap allocation) and the covariance algebra in preallocated buffers, using the structure of
the matrices -- ``F`` is block sparse (22 of its 36 3x3 blocks are non-zero, the position and
velocity rows are multiples of the identity), ``H`` has no position or velocity columns, the
change of parametrisation ``M`` is a permutation with one 3x3 block, and ``Q`` is zero outside the
acceleration blocks -- so that a step costs about as much as the authors' C++ filter.

The correction uses the Joseph form expanded, ``(I - K H) P (I - K H)^T + K R K^T
= P - K U^T - U K^T + K S K^T`` with ``U = P H^T``: the same matrix for any gain ``K`` (so it keeps
the Joseph form's robustness to an inexact gain), a third of the arithmetic.

Packed inputs, one row per step (:func:`pack_inputs`)::

    0:3 com | 3:6 com_vel | 6:9 com_acc | 9:18 inertia | 18:27 inertia_dot | 27:30 sigma
    30:33 sigma_dot | 33:42 imu_R | 42:45 imu_p | 45:48 imu_v | 48:51 imu_a | 51:54 imu_w
    54:57 gyro | 57:60 accel | 60:66 use (1: the axis is read, 0: missing or saturated)
    then per contact c, at 66 + 25 c: active, p_l (3), R_l (9),
    p_r (3), R_r (9) (placement in the local frame, rest placement in the world)

Contact parameters, one row per contact: K_fs, K_fd, K_ts, K_td (9 each, row-major), beta_f,
beta_t, isotropic flag.  Constants (:func:`pack_constants`): Q (324), R (36), then dt, m, g, z0,
min_force, the touch-down rule (1: zero deflection, :func:`touch_down`), its tilt and height
weights, the floor height, and the IMU gates for 1, 2 and 3 used axes of a sensor (chi-square
values; 0: no gate).

Output row of a step (:data:`OUT_FIELDS`): the state, the world covariance, the per-contact
wrenches, their total's covariance, the CoP and its covariance, the innovation, its covariance,
the whitened innovation and the NIS, then per sensor (gyro, accel) its NIS and the gate's
inflation of its innovation covariance (1: not gated).
"""

from __future__ import annotations

import math

import numpy as np

from flexforce.factors import core
from flexforce.factors.core import (
    accel_solve_t,
    contact_t,
    exp_t,
    eye,
    imu_t,
    jl_inv_t,
    jl_t,
    ld3,
    ldm,
    ldm9,
    log_t,
    madd,
    maxpy,
    mm,
    mscl,
    msub,
    mv,
    njit,
    required_t,
    st3,
    stm,
    vadd,
    vaxpy,
    vscl,
    vsub,
)

AVAILABLE = core.HAVE_NUMBA

NU0 = 66
"""Packed columns before the contacts."""
NUC = 25
"""Packed columns per contact."""
_NQ = 324
_NR = 36

# Non-zero 3x3 blocks of F, filter order (t, Omega, v, w, a, dw).
_F_NZ = np.array([[1, 0, 1, 0, 1, 0],
                  [0, 1, 0, 1, 0, 1],
                  [0, 0, 1, 0, 1, 0],
                  [0, 0, 0, 1, 0, 1],
                  [1, 1, 1, 1, 1, 1],
                  [1, 1, 1, 1, 1, 1]], dtype=np.bool_)
# Filter block of each world block (theta, t, w, v, dw, a).
_PERM = np.array([1, 0, 3, 2, 5, 4])


def out_layout(n_c: int) -> dict:
    """Column ranges of one step's output row: name -> (start, shape)."""
    shapes = [("x", (18,)), ("cov", (18, 18)), ("wrench", (n_c, 6)), ("wrench_cov", (6, 6)), ("cop", (3,)),
              ("cop_cov", (2, 2)), ("innovation", (6,)), ("S", (6, 6)), ("white", (6,)), ("nis", ()),
              ("sensor_nis", (2,)), ("inflation", (2,))]
    out, o = {}, 0
    for name, shape in shapes:
        out[name] = (o, shape)
        o += int(np.prod(shape)) if shape else 1
    out["_width"] = (o, ())
    return out


# Offsets in the output row (the contacts' wrenches have a variable length: after them, offsets
# are computed from n_c inside the kernel).
_O_X, _O_COV, _O_WR = 0, 18, 342


# ----------------------------------------------------------------------------------------------
# The model in the filter's parametrisation
# ----------------------------------------------------------------------------------------------


@njit
def _contact(R, t, w, v, u, o, cp):
    """:func:`~flexforce.factors.core.contact_t` of the contact packed at ``u[o:o+25]`` with the
    parameters ``cp``."""
    return contact_t(R, t, w, v, ld3(u, o + 1), ldm9(u, o + 4), ld3(u, o + 13), ldm9(u, o + 16), ldm9(cp, 0),
                     ldm9(cp, 9), ldm9(cp, 18), ldm9(cp, 27), cp[36], cp[37], cp[38] != 0.0)


@njit
def dynamics(R, t, w, v, u, CP, m, g):
    """Accelerations from the contact law and Newton-Euler (eq. 24, 25 with 10, 12) at the inputs
    ``u`` and their derivatives with respect to world increments ``(theta, t, w, v)``.

    Returns ``ok, dw, a`` and the 3x3 blocks ``G_dw_*``, ``G_a_*`` (``*`` = th, t, w, v) of
    ``d(dw, a)/d(theta, t, w, v) = A^-1 (dW_c/dx - dr/dx)``.
    """
    z = eye(0.0)
    WF = (0.0, 0.0, 0.0)
    WT = (0.0, 0.0, 0.0)
    cF_th, cF_t, cF_w, cF_v, cT_th, cT_t, cT_w, cT_v = z, z, z, z, z, z, z, z
    for c in range(CP.shape[0]):
        o = NU0 + NUC * c
        if u[o] == 0.0:
            continue
        (F, T, dF_dth, dF_dt, dF_dw, dF_dv, dT_dth, dT_dt, dT_dw, dT_dv, _, _, _) = _contact(R, t, w, v, u, o, CP[c])
        WF = vadd(WF, F)
        WT = vadd(WT, T)
        cF_th, cF_t, cF_w, cF_v = madd(cF_th, dF_dth), madd(cF_t, dF_dt), madd(cF_w, dF_dw), madd(cF_v, dF_dv)
        cT_th, cT_t, cT_w, cT_v = madd(cT_th, dT_dth), madd(cT_t, dT_dt), madd(cT_w, dT_dw), madd(cT_v, dT_dv)
    inputs = (ld3(u, 0), ld3(u, 3), ld3(u, 6), ldm9(u, 9), ldm9(u, 18), ld3(u, 27), ld3(u, 30))
    zero = (0.0, 0.0, 0.0)
    F0, T0, _, _, _, _, _, RIRt, S_Rc, S_t = required_t(R, t, w, zero, zero, m, inputs[0], inputs[1], inputs[2],
                                                        inputs[3], inputs[4], inputs[5], inputs[6], g)
    dw_F, dw_T, a_F, a_T, det = accel_solve_t(m, RIRt, S_Rc, S_t)
    ok = det != 0.0 and math.isfinite(det)
    bF = vsub(WF, F0)
    bT = vsub(WT, T0)
    dw = vadd(mv(dw_F, bF), mv(dw_T, bT))
    a = vadd(mv(a_F, bF), mv(a_T, bT))
    _, _, rF_th, rF_w, rT_th, rT_t, rT_w, _, _, _ = required_t(R, t, w, dw, a, m, inputs[0], inputs[1], inputs[2],
                                                               inputs[3], inputs[4], inputs[5], inputs[6], g)
    XF_th, XF_w = msub(cF_th, rF_th), msub(cF_w, rF_w)
    XT_th, XT_t, XT_w = msub(cT_th, rT_th), msub(cT_t, rT_t), msub(cT_w, rT_w)
    G_dw = (madd(mm(dw_F, XF_th), mm(dw_T, XT_th)), madd(mm(dw_F, cF_t), mm(dw_T, XT_t)),
            madd(mm(dw_F, XF_w), mm(dw_T, XT_w)), madd(mm(dw_F, cF_v), mm(dw_T, cT_v)))
    G_a = (madd(mm(a_F, XF_th), mm(a_T, XT_th)), madd(mm(a_F, cF_t), mm(a_T, XT_t)),
           madd(mm(a_F, XF_w), mm(a_T, XT_w)), madd(mm(a_F, cF_v), mm(a_T, cT_v)))
    return ok, dw, a, G_dw, G_a


@njit
def dynamics_into(R, t, w, v, u, CP, m, g, acc, G):
    """:func:`dynamics`, arrays in and out: ``acc`` = (a, dw) and ``G`` (6x12) its Jacobian, rows
    (a, dw), columns world ``(theta, t, w, v)``.  Returns ok."""
    ok, dw, a, G_dw, G_a = dynamics(ldm(R), ld3(t, 0), ld3(w, 0), ld3(v, 0), u, CP, m, g)
    st3(acc, 0, a)
    st3(acc, 3, dw)
    for j in range(4):
        stm(G, 0, 3 * j, G_a[j])
        stm(G, 3, 3 * j, G_dw[j])
    return ok


@njit
def predicted_pose(x, dt):
    """The pose the transition predicts from ``x`` (filter order) over ``dt``:
    ``phi = dt w + dt^2/2 dw``, ``E = exp(phi)``, ``R1 = E exp(Omega)``, ``t1 = t + dt v + dt^2/2 a``."""
    h = 0.5 * dt * dt
    phi = vaxpy(vscl(dt, ld3(x, 9)), h, ld3(x, 15))
    E = exp_t(phi)
    return phi, E, mm(E, exp_t(ld3(x, 3))), vaxpy(vaxpy(ld3(x, 0), dt, ld3(x, 6)), h, ld3(x, 12))


@njit
def touch_down(k, x, U, dt, tilt_weight, height_weight, floor_z):
    """Footholds of the contacts that land at step ``k`` (active at k, not at k-1): the rest
    placement in the world is the contact's placement at the predicted pose, ``p_r = R p_l + t``,
    ``R_r = R R_l`` (the landing spring starts at zero deflection), with the fraction
    ``tilt_weight`` of the tilt of the sole (its z axis against gravity's) removed, yaw kept,
    and the fraction ``height_weight`` of its height above the floor ``z = floor_z`` removed.
    Written into the packed rows of the whole episode (k until the contact lifts)."""
    _, _, R1, t1 = predicted_pose(x, dt)
    for c in range((U.shape[1] - NU0) // NUC):
        o = NU0 + NUC * c
        if U[k, o] == 0.0 or U[k - 1, o] != 0.0:
            continue
        p_r = vadd(mv(R1, ld3(U[k], o + 1)), t1)
        p_r = (p_r[0], p_r[1], p_r[2] - height_weight * (p_r[2] - floor_z))
        R_r = mm(R1, ldm9(U[k], o + 4))
        if tilt_weight > 0.0:
            # n x e_z for the sole normal n = R_r e_z: the rotation that levels the sole.
            axis = (R_r[1][2], -R_r[0][2], 0.0)
            sin_t = math.sqrt(axis[0] * axis[0] + axis[1] * axis[1])
            if sin_t > 1e-12:
                angle = math.atan2(sin_t, R_r[2][2])
                R_r = mm(exp_t(vscl(tilt_weight * angle / sin_t, axis)), R_r)
        for kk in range(k, U.shape[0]):
            if U[kk, o] == 0.0:
                break
            st3(U[kk], o + 13, p_r)
            for i in range(3):
                st3(U[kk], o + 16 + 3 * i, R_r[i])


@njit
def transition(x, u, CP, dt, m, g, x1, F):
    """``x1 = f(x)`` (the state predicted at the step of ``u``) and its Jacobian ``F`` (18x18),
    filter order ``(t, Omega, v, w, a, dw)`` (see :mod:`flexforce.compare.ekf.filter`).  Returns ok."""
    Om, v, w, a, dw = ld3(x, 3), ld3(x, 6), ld3(x, 9), ld3(x, 12), ld3(x, 15)
    h = 0.5 * dt * dt
    phi, E, R1, t1 = predicted_pose(x, dt)
    v1 = vaxpy(v, dt, a)
    w1 = vaxpy(w, dt, dw)
    Om1 = log_t(R1)
    ok, dw1, a1, G_dw, G_a = dynamics(R1, t1, w1, v1, u, CP, m, g)
    st3(x1, 0, t1)
    st3(x1, 3, Om1)
    st3(x1, 6, v1)
    st3(x1, 9, w1)
    st3(x1, 12, a1)
    st3(x1, 15, dw1)
    # World increments (theta, t, w, v) at the new step from the filter's increments:
    # d_theta = E J_l(Om) dOm + J_l(phi) (dt dw + h ddw); F's Omega rows are J_l^-1(Om1) d_theta.
    EJ = mm(E, jl_t(Om))
    Jphi = jl_t(phi)
    Jinv1 = jl_inv_t(Om1)
    for i in range(18):
        for j in range(18):
            F[i, j] = 0.0
    for i in range(3):
        F[i, i] = 1.0
        F[i, 6 + i] = dt
        F[i, 12 + i] = h
        F[6 + i, 6 + i] = 1.0
        F[6 + i, 12 + i] = dt
        F[9 + i, 9 + i] = 1.0
        F[9 + i, 15 + i] = dt
    JiJphi = mm(Jinv1, Jphi)
    stm(F, 3, 3, mm(Jinv1, EJ))
    stm(F, 3, 9, mscl(dt, JiJphi))
    stm(F, 3, 15, mscl(h, JiJphi))
    _acc_rows(F, 12, G_a, EJ, Jphi, dt, h)
    _acc_rows(F, 15, G_dw, EJ, Jphi, dt, h)
    return ok


@njit
def _acc_rows(F, r, G, EJ, Jphi, dt, h):
    """F's acceleration rows: ``G D`` with ``D`` the world increments at the new step from the
    filter's increments (columns t, Omega, v, w, a, dw)."""
    G_th, G_t, G_w, G_v = G
    G_thJ = mm(G_th, Jphi)
    stm(F, r, 0, G_t)
    stm(F, r, 3, mm(G_th, EJ))
    stm(F, r, 6, maxpy(G_v, dt, G_t))
    stm(F, r, 9, maxpy(G_w, dt, G_thJ))
    stm(F, r, 12, madd(mscl(h, G_t), mscl(dt, G_v)))
    stm(F, r, 15, madd(mscl(h, G_thJ), mscl(dt, G_w)))


@njit
def measurement(x, u, g, hx, H):
    """``h(x)``: gyro and accelerometer readings (IMU frame) into ``hx`` and ``H`` (6x18, filter
    order; its position and velocity columns are zero)."""
    Om = ld3(x, 3)
    R = exp_t(Om)
    yg, ya, g_th, RaTRt, a_th, a_w, a_dw = imu_t(R, ld3(x, 9), ld3(x, 15), ld3(x, 12), ldm9(u, 33), ld3(u, 42),
                                                 ld3(u, 45), ld3(u, 48), ld3(u, 51), g)
    st3(hx, 0, yg)
    st3(hx, 3, ya)
    Jl = jl_t(Om)
    for i in range(6):
        for j in range(18):
            H[i, j] = 0.0
    stm(H, 0, 3, mm(g_th, Jl))
    stm(H, 0, 9, RaTRt)
    stm(H, 3, 3, mm(a_th, Jl))
    stm(H, 3, 9, a_w)
    stm(H, 3, 12, RaTRt)
    stm(H, 3, 15, a_dw)


# ----------------------------------------------------------------------------------------------
# Covariance algebra on preallocated buffers
# ----------------------------------------------------------------------------------------------


@njit
def propagate(F, P, Q, Jinv, FP, out):
    """``out = F P F^T + B Q B^T`` (symmetric), ``B`` the identity but for its Omega block
    ``Jinv``; ``F``'s zero blocks (``_F_NZ``) and zero entries are skipped."""
    for i in range(18):
        for j in range(18):
            FP[i, j] = 0.0
    for bi in range(6):
        for bj in range(6):
            if not _F_NZ[bi, bj]:
                continue
            for r in range(3):
                i = 3 * bi + r
                for kk in range(3):
                    f = F[i, 3 * bj + kk]
                    if f != 0.0:
                        pr = 3 * bj + kk
                        for c in range(18):
                            FP[i, c] += f * P[pr, c]
    for i in range(18):
        for bj_row in range(6):
            for r in range(3):
                j = 3 * bj_row + r
                if j < i:
                    continue
                s = 0.0
                for bk in range(6):
                    if _F_NZ[bj_row, bk]:
                        for kk in range(3):
                            f = F[j, 3 * bk + kk]
                            if f != 0.0:
                                s += FP[i, 3 * bk + kk] * f
                out[i, j] = s
    # B Q B^T: Q's rows and columns of Omega are mapped by Jinv.
    for i in range(18):
        for j in range(i, 18):
            q = 0.0
            if 3 <= i < 6 and 3 <= j < 6:
                for a in range(3):
                    for b in range(3):
                        q += Jinv[i - 3][a] * Q[3 + a, 3 + b] * Jinv[j - 3][b]
            elif 3 <= i < 6:
                for a in range(3):
                    q += Jinv[i - 3][a] * Q[3 + a, j]
            elif 3 <= j < 6:
                for b in range(3):
                    q += Q[i, 3 + b] * Jinv[j - 3][b]
            else:
                q = Q[i, j]
            out[i, j] += q
            out[j, i] = out[i, j]


@njit
def predict(x, P, u, CP, Q, dt, m, g, WS):
    """Propagate ``(x, P)`` in place to the step of ``u``.  Status: 0 ok, 1 P not positive
    definite, 5 singular dynamics."""
    x1 = WS[6, 0]
    F = WS[0]
    if not transition(x, u, CP, dt, m, g, x1, F):
        return 5
    propagate(F, P, Q, jl_inv_t(ld3(x1, 3)), WS[1], WS[2])
    for i in range(18):
        x[i] = x1[i]
        for j in range(18):
            P[i, j] = WS[2, i, j]
    if not core.cholesky_into(P, WS[3]):
        return 1
    return 0


GATE_REJECT = 1e12
"""Inflation of a gated sensor's block of the innovation covariance: the sample is left out."""


@njit
def update(x, P, u, Rn, g, WS, innov, S, white, gates, snis, infl):
    """Correct ``(x, P)`` in place with the IMU readings of ``u``; writes the innovation, its
    covariance and the whitened innovation.  Returns ``(status, nis)``: 0 ok, 2 S not positive
    definite (x, P unchanged), 3 P not positive definite, 4 state not finite.

    Axes whose ``use`` flag (``u[60:66]``) is 0 (missing or saturated readings) are left out: zero
    innovation and row of ``H``, unit variance uncorrelated with the others, so that their gain is
    zero.  Per sensor (gyro, accel), the NIS of its used axes is written to ``snis``; above the
    gate ``gates[d - 1]`` (d used axes) its block of ``S`` is scaled by :data:`GATE_REJECT` (the
    sample left out: a gross fault, far beyond any model error), and the factor written to ``infl``.
    The whitened innovation and the NIS are those of the raw ``S``."""
    hx = WS[6, 1, 0:6]
    H = WS[5, 0:6]
    measurement(x, u, g, hx, H)
    for i in range(6):
        if u[60 + i] != 0.0:
            innov[i] = u[54 + i] - hx[i]
        else:
            innov[i] = 0.0
            for j in range(18):
                H[i, j] = 0.0
    U = WS[4, :, 0:6]
    K = WS[4, :, 6:12]
    KS = WS[4, :, 12:18]
    cols = (3, 4, 5, 9, 10, 11, 12, 13, 14, 15, 16, 17)  # H's non-zero columns
    for i in range(18):
        for r in range(6):
            s = 0.0
            for j in cols:
                s += P[i, j] * H[r, j]
            U[i, r] = s
    for r in range(6):
        for c in range(r, 6):
            s = 0.0
            for j in cols:
                s += H[r, j] * U[j, c]
            if u[60 + r] != 0.0 and u[60 + c] != 0.0:
                S[r, c] = s + 0.5 * (Rn[r, c] + Rn[c, r])
            else:
                S[r, c] = 1.0 if r == c else 0.0
            S[c, r] = S[r, c]
    L = WS[5, 6:12, 0:6]
    if not core.cholesky_into(S, L):
        for i in range(6):
            white[i] = 0.0
        return 2, np.inf
    nis = 0.0
    for i in range(6):
        white[i] = innov[i]
    core.trsv_lower_inplace(L, white)
    for i in range(6):
        nis += white[i] * white[i]
    # Per-sensor gate: the NIS of each sensor's used axes against its own block of S; the gain
    # uses Se, S with the gated blocks inflated (S itself, an output, stays the model's).
    Se = WS[5, 12:18, 12:18]
    for r in range(6):
        for c in range(6):
            Se[r, c] = S[r, c]
    gated = False
    Ls = WS[6, 6:9, 0:3]
    ws = WS[6, 9, 0:3]
    for sn in range(2):
        d = 0
        for a in range(3):
            if u[60 + 3 * sn + a] != 0.0:
                d += 1
        snis[sn] = 0.0
        infl[sn] = 1.0
        if d == 0:
            continue
        # The 3x3 block (unused axes have unit variance and zero innovation: they add nothing).
        for a in range(3):
            for b in range(3):
                Ls[a, b] = 0.0
        Ss = WS[6, 10:13, 0:3]
        for a in range(3):
            ws[a] = innov[3 * sn + a]
            for b in range(3):
                Ss[a, b] = S[3 * sn + a, 3 * sn + b]
        if not core.cholesky_into(Ss, Ls):
            return 2, np.inf
        core.trsv_lower_inplace(Ls, ws)
        v = ws[0] * ws[0] + ws[1] * ws[1] + ws[2] * ws[2]
        snis[sn] = v
        gate = gates[d - 1]
        if gate > 0.0 and v > gate:
            lam = GATE_REJECT
            infl[sn] = lam
            gated = True
            for a in range(3):
                for b in range(3):
                    if u[60 + 3 * sn + a] != 0.0 and u[60 + 3 * sn + b] != 0.0:
                        Se[3 * sn + a, 3 * sn + b] *= lam
    if gated and not core.cholesky_into(Se, L):
        return 2, np.inf
    for i in range(18):
        for r in range(6):
            K[i, r] = U[i, r]
        core.trsv_lower_inplace(L, K[i])
        core.trsv_upper_t_inplace(L, K[i])
    for i in range(18):
        s = 0.0
        for r in range(6):
            s += K[i, r] * innov[r]
        x[i] += s
    if x[3] * x[3] + x[4] * x[4] + x[5] * x[5] > math.pi * math.pi:
        st3(x, 3, log_t(exp_t(ld3(x, 3))))
    core.matmul_into(K, Se, KS)
    for i in range(18):
        for j in range(i, 18):
            s = P[i, j]
            for r in range(6):
                s += KS[i, r] * K[j, r] - K[i, r] * U[j, r] - U[i, r] * K[j, r]
            P[i, j] = s
            P[j, i] = s
    for i in range(18):
        if not math.isfinite(x[i]):
            return 4, nis
    if not core.cholesky_into(P, WS[3]):
        return 3, nis
    return 0, nis


@njit
def outputs(x, P, u, CP, z0, min_force, WS, Pw, per, Wcov, cop, cop_cov):
    """World covariance ``Pw`` (order ``(theta, t, w, v, dw, a)``), per-contact wrenches ``per``
    (C, 6), the total wrench's covariance ``Wcov``, the CoP and its covariance at ``(x, P)``."""
    Om = ld3(x, 3)
    R = exp_t(Om)
    Jl = jl_t(Om)
    # Pw = M P M^T, M = permutation with J_l(Omega) on the rotation block.
    for bi in range(6):
        for bj in range(6):
            pi = _PERM[bi]
            pj = _PERM[bj]
            for r in range(3):
                for c in range(3):
                    Pw[3 * bi + r, 3 * bj + c] = P[3 * pi + r, 3 * pj + c]
    T = WS[1, 0]
    for j in range(18):
        for r in range(3):
            T[r] = Jl[r][0] * Pw[0, j] + Jl[r][1] * Pw[1, j] + Jl[r][2] * Pw[2, j]
        for r in range(3):
            Pw[r, j] = T[r]
    for i in range(18):
        for r in range(3):
            T[r] = Pw[i, 0] * Jl[r][0] + Pw[i, 1] * Jl[r][1] + Pw[i, 2] * Jl[r][2]
        for r in range(3):
            Pw[i, r] = T[r]
    for i in range(18):
        for j in range(i + 1, 18):
            s = 0.5 * (Pw[i, j] + Pw[j, i])
            Pw[i, j] = s
            Pw[j, i] = s
    t, w, v = ld3(x, 0), ld3(x, 9), ld3(x, 6)
    Jc = WS[5, 12:18, 0:12]
    for i in range(6):
        for j in range(12):
            Jc[i, j] = 0.0
    W = WS[6, 2, 0:6]
    for i in range(6):
        W[i] = 0.0
    for c in range(CP.shape[0]):
        o = NU0 + NUC * c
        for i in range(6):
            per[c, i] = 0.0
        if u[o] == 0.0:
            continue
        (F, Tq, dF_dth, dF_dt, dF_dw, dF_dv, dT_dth, dT_dt, dT_dw, dT_dv, _, _, _) = _contact(R, t, w, v, u, o,
                                                                                            CP[c])
        for i in range(3):
            per[c, i] = F[i]
            per[c, 3 + i] = Tq[i]
            W[i] += F[i]
            W[3 + i] += Tq[i]
        core.stm_add(Jc, 0, 0, dF_dth)
        core.stm_add(Jc, 0, 3, dF_dt)
        core.stm_add(Jc, 0, 6, dF_dw)
        core.stm_add(Jc, 0, 9, dF_dv)
        core.stm_add(Jc, 3, 0, dT_dth)
        core.stm_add(Jc, 3, 3, dT_dt)
        core.stm_add(Jc, 3, 6, dT_dw)
        core.stm_add(Jc, 3, 9, dT_dv)
    JP = WS[5, 0:6, 0:12]
    core.matmul_into(Jc, Pw[0:12, 0:12], JP)
    for i in range(6):
        for j in range(i, 6):
            s = 0.0
            for k in range(12):
                s += JP[i, k] * Jc[j, k]
            Wcov[i, j] = s
            Wcov[j, i] = s
    Jcop = WS[6, 3:6, 0:6]
    if not core.center_of_pressure(W, z0, min_force, cop, Jcop):
        for i in range(2):
            for j in range(2):
                cop_cov[i, j] = np.nan
        return
    for i in range(2):
        for j in range(2):
            s = 0.0
            for a in range(6):
                if Jcop[i, a] != 0.0:
                    for b in range(6):
                        s += Jcop[i, a] * Wcov[a, b] * Jcop[j, b]
            cop_cov[i, j] = s


# ----------------------------------------------------------------------------------------------
# One step
# ----------------------------------------------------------------------------------------------


@njit
def step(k, x, P, U, CP, C, WS, OUT, do_predict, want_outputs):
    """Predict (``do_predict``, k > 0) and update at step ``k``: ``x`` and ``P`` are overwritten,
    the step's output row ``OUT[k]`` written.  ``C`` the packed constants.  Returns the status
    (0 ok, see :mod:`flexforce.compare.ekf.filter`)."""
    n_c = CP.shape[0]
    Q = C[0:_NQ].reshape((18, 18))
    Rn = C[_NQ:_NQ + _NR].reshape((6, 6))
    o = _NQ + _NR
    dt, m, g, z0, min_force = C[o], C[o + 1], C[o + 2], C[o + 3], C[o + 4]
    touchdown, tilt_weight, height_weight, floor_z = C[o + 5], C[o + 6], C[o + 7], C[o + 8]
    gates = C[o + 9:o + 12]
    u = U[k]
    row = OUT[k]
    o_wc = _O_WR + 6 * n_c
    o_cop = o_wc + 36
    o_copc = o_cop + 3
    o_in = o_copc + 4
    o_S = o_in + 6
    o_wh = o_S + 36
    o_nis = o_wh + 6
    o_sn = o_nis + 1
    if do_predict and k > 0:
        if touchdown != 0.0:
            touch_down(k, x, U, dt, tilt_weight, height_weight, floor_z)
        st = predict(x, P, u, CP, Q, dt, m, g, WS)
        if st != 0:
            return st
    S = row[o_S:o_S + 36].reshape((6, 6))
    st, nis = update(x, P, u, Rn, g, WS, row[o_in:o_in + 6], S, row[o_wh:o_wh + 6], gates, row[o_sn:o_sn + 2],
                     row[o_sn + 2:o_sn + 4])
    row[o_nis] = nis
    if st != 0:
        return st
    for i in range(18):
        row[i] = x[i]
    if want_outputs:
        outputs(x, P, u, CP, z0, min_force, WS, row[_O_COV:_O_COV + 324].reshape((18, 18)),
                row[_O_WR:o_wc].reshape((n_c, 6)), row[o_wc:o_cop].reshape((6, 6)), row[o_cop:o_copc],
                row[o_copc:o_in].reshape((2, 2)))
    return 0


# ----------------------------------------------------------------------------------------------
# Packing
# ----------------------------------------------------------------------------------------------


def pack_inputs(rec, rest_p=None, rest_R=None, imu_use=None) -> np.ndarray:
    """(N, 66 + 25 C) packed inputs and readings (see the module docstring); rest placements
    default to the local ones; ``imu_use`` (N, 6) the axes that carry information (default: the
    finite readings)."""
    n, n_c = rec.n, len(rec.contact_names)
    rest_p = rec.contact_p if rest_p is None else rest_p
    rest_R = rec.contact_R if rest_R is None else rest_R
    U = np.zeros((n, NU0 + NUC * n_c))
    cols = [rec.com, rec.com_vel, rec.com_acc, rec.inertia.reshape(n, 9), rec.inertia_dot.reshape(n, 9),
            rec.sigma, rec.sigma_dot, rec.imu_R.reshape(n, 9), rec.imu_p, rec.imu_v, rec.imu_a, rec.imu_w,
            np.zeros((n, 3)), np.zeros((n, 3)), np.ones((n, 6))]
    U[:, :NU0] = np.hstack(cols)
    # Readings and which axes carry information (missing or saturated: use 0, reading 0).
    use = np.ones((n, 6), dtype=bool) if imu_use is None else np.asarray(imu_use, dtype=bool)
    y = np.concatenate([rec.gyro, rec.accel], axis=1)
    use = use & np.isfinite(y)
    U[:, 54:60] = np.where(use, y, 0.0)
    U[:, 60:66] = use
    eye9 = np.eye(3).ravel()
    for c in range(n_c):
        o = NU0 + NUC * c
        active = rec.contact_active[:, c][:, None]
        U[:, o] = active[:, 0]
        # Placements of inactive contacts are never read; keep them finite.
        U[:, o + 1:o + 4] = np.where(active, rec.contact_p[:, c], 0.0)
        U[:, o + 4:o + 13] = np.where(active, rec.contact_R[:, c].reshape(n, 9), eye9)
        U[:, o + 13:o + 16] = np.where(active, rest_p[:, c], 0.0)
        U[:, o + 16:o + 25] = np.where(active, np.asarray(rest_R)[:, c].reshape(n, 9), eye9)
    return np.ascontiguousarray(U)


def pack_params(params) -> np.ndarray:
    """(C, 39) packed contact parameters."""
    rows = []
    for p in params:
        rows.append(np.concatenate([p.K_fs.ravel(), p.K_fd.ravel(), p.K_ts.ravel(), p.K_td.ravel(),
                                    [p.beta_f, p.beta_t, 1.0 if p.isotropic else 0.0]]))
    return np.ascontiguousarray(np.array(rows, dtype=float).reshape(len(rows), 39))


def pack_constants(Q, Rn, dt, m, g, z0, min_force, touchdown: bool = False, tilt_weight: float = 0.0,
                   height_weight: float = 0.0, floor_z: float = 0.0, gates=(0.0, 0.0, 0.0)) -> np.ndarray:
    return np.concatenate([np.asarray(Q, float).ravel(), np.asarray(Rn, float).ravel(),
                           [dt, m, g, z0, min_force, float(touchdown), tilt_weight, height_weight, floor_z],
                           np.asarray(gates, float)])


def workspace() -> np.ndarray:
    """Scratch buffers of one filter: (7, 18, 18)."""
    return np.zeros((7, 18, 18))
