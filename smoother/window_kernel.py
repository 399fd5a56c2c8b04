r"""The fixed-lag window's linearisation and assembly in one compiled call.

:func:`window_system` evaluates the factors on the newest steps of the window (the families a
problem without effects uses, past the stream's first step: Newton-Euler, contact law, IMU, F/T,
integration), whitens them, applies the robust losses and accumulates the Gauss-Newton blocks of
:func:`flexforce.smoother.linearize.assemble_split` (``U``, ``gU``, ``Fw``, ``gF``, ``B``) directly:
the same numbers as :func:`~flexforce.smoother.linearize.linearize` followed by ``assemble_split``
(the same kernels per family, the same whitening products, the same order of accumulation), without
the Python work per family and per update.  :class:`WindowProblem` holds the problem's arrays in
the order the kernel takes them, built once per :class:`~flexforce.smoother.problem.Problem`.

:func:`window_update` is a whole update of :class:`flexforce.smoother.fixed_lag.FixedLagSmoother`
on that path: retraction of the relinearised steps, prediction of the new ones, the system above,
the incremental elimination and the back substitution, on the smoother's ring buffers.
"""

from __future__ import annotations

import math

import numpy as np

from flexforce.factors import core
from flexforce.factors.core import njit, so3_exp
from flexforce.smoother.linearize import _add_binary, _add_unary
from flexforce.smoother.solvers import _trsm_lower_rows_t, _trsv_lower, retract_core, window_back_substitute

S = core.STATE_DIM

ROBUST_KINDS = {None: 0, "log-tail": 1, "huber": 2, "cauchy": 3}
"""Codes of the sensors' robust losses (:func:`flexforce.datasets.faults.robust_weights`)."""


class WindowProblem:
    """A :class:`~flexforce.smoother.problem.Problem`'s arrays as :func:`window_system` takes them
    (a problem without effects)."""

    def __init__(self, prob):
        if prob.effects:
            raise ValueError("the compiled window path takes a problem without effects")
        sig = prob.sigmas
        nc = prob.nc
        self.prob = prob
        self.offset = int(prob.offset)
        Li = np.diag(1.0 / (np.sqrt(np.diag(sig.contact_cov)) * sig.inactive_factor))
        self.robust = (sig.imu_robust is not None)
        self.args = (
            float(prob.rec.mass), float(prob.g), float(prob.dt), prob.com, prob.com_vel, prob.com_acc,
            prob.inertia, prob.inertia_dot, prob.sigma_l, prob.sigma_dot,
            prob.active, prob.contact_p, prob.contact_R, prob.rest_p, prob.rest_R,
            prob.K_fs, prob.K_fd, prob.K_ts, prob.K_td, prob.beta, prob.iso,
            prob.y_imu, prob.imu_R, prob.imu_p, prob.imu_v, prob.imu_a, prob.imu_w, prob.imu_use,
            prob.y_ft if prob.use_ft else np.zeros((0, nc, 6)), bool(prob.use_ft),
            np.ascontiguousarray(prob.ne_whitener, dtype=float),
            np.ascontiguousarray(prob.contact_whitener, dtype=float),
            np.ascontiguousarray(Li), 1.0 / np.asarray(sig.imu, dtype=float), 1.0 / np.asarray(sig.ft, dtype=float),
            np.ascontiguousarray(prob.integration_whitener, dtype=float),
            -1.0 if sig.robust_k is None else float(sig.robust_k), ROBUST_KINDS[sig.imu_robust],
            float(sig.imu_robust_k))


@njit
def _about_com(c, r, J):
    """``flexforce.factors.physics.about_com`` of one step in place: the moment rows of the
    Newton-Euler residual ``r`` (6,) and its Jacobian ``J`` (6, D) taken about the point ``c``."""
    cx, cy, cz = c[0], c[1], c[2]
    f0, f1, f2 = r[0], r[1], r[2]
    r[3] -= cy * f2 - cz * f1
    r[4] -= cz * f0 - cx * f2
    r[5] -= cx * f1 - cy * f0
    for col in range(J.shape[1]):
        f0, f1, f2 = J[0, col], J[1, col], J[2, col]
        J[3, col] -= cy * f2 - cz * f1
        J[4, col] -= cz * f0 - cx * f2
        J[5, col] -= cx * f1 - cy * f0


@njit
def _gram_into(H, k, A, Bt, ca, cb, sym):
    """``H[k][ca, cb] += A Bt^T`` (``linearize._gram_into``: each entry summed over the rows in
    order from 0.0, the same floating-point result), four entries at a time (independent sums)."""
    rows = A.shape[1]
    nb = cb.shape[0]
    for ia in range(ca.shape[0]):
        a = ca[ia]
        ib = ia if sym else 0
        while ib + 4 <= nb:
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            s3 = 0.0
            for i in range(rows):
                x = A[ia, i]
                s0 += x * Bt[ib, i]
                s1 += x * Bt[ib + 1, i]
                s2 += x * Bt[ib + 2, i]
                s3 += x * Bt[ib + 3, i]
            H[k, a, cb[ib]] += s0
            H[k, a, cb[ib + 1]] += s1
            H[k, a, cb[ib + 2]] += s2
            H[k, a, cb[ib + 3]] += s3
            if sym:
                if ib != ia:
                    H[k, cb[ib], a] += s0
                H[k, cb[ib + 1], a] += s1
                H[k, cb[ib + 2], a] += s2
                H[k, cb[ib + 3], a] += s3
            ib += 4
        while ib < nb:
            s0 = 0.0
            for i in range(rows):
                s0 += A[ia, i] * Bt[ib, i]
            H[k, a, cb[ib]] += s0
            if sym and ib != ia:
                H[k, cb[ib], a] += s0
            ib += 1


@njit
def _robust(norm, kind, k):
    """Weight and robust cost of one whitened norm (as :func:`flexforce.datasets.faults.robust_weights`)."""
    if kind == 1:  # log-tail
        if norm > k:
            safe = max(norm, k)
            t = k / safe
            return t * t, 0.5 * k * k + k * k * math.log(safe / k)
        return 1.0, 0.5 * norm * norm
    if kind == 2:  # huber
        if norm <= k:
            return 1.0, 0.5 * norm * norm
        return k / max(norm, 1e-300), k * norm - 0.5 * k * k
    u = (norm / k) * (norm / k)  # cauchy
    return 1.0 / (1.0 + u), 0.5 * k * k * math.log1p(u)


@njit
def _sensor_reweight(r, J, cap, kind, k, w_out):
    """IRLS of the gyro (rows 0-2) and accelerometer (3-5) blocks of ``r`` (m, 6), ``J`` (m, 6, D)
    in place (``linearize.sensor_reweight``); ``cap`` (m, 2) upper bounds; weights into ``w_out``
    (m, 2); returns the extra cost."""
    rho_sum = 0.0
    wn_sum = 0.0
    for kk in range(r.shape[0]):
        for j in range(2):
            a = 3 * j
            s = r[kk, a] * r[kk, a]
            s = s + r[kk, a + 1] * r[kk, a + 1]
            s = s + r[kk, a + 2] * r[kk, a + 2]
            norm = math.sqrt(s)
            w, rho = _robust(norm, kind, k)
            c = cap[kk, j]
            if c < w:
                w = c
            w_out[kk, j] = w
            rho_sum += rho
            wn_sum += w * (norm * norm)
            sw = math.sqrt(w)
            for i in range(a, a + 3):
                r[kk, i] *= sw
                for col in range(J.shape[2]):
                    J[kk, i, col] *= sw
    return rho_sum - 0.5 * wn_sum


@njit
def _whiten_steps(L, Jraw, out, sel, nsel):
    """``out[k, :, :n] = L @ Jraw[k]`` for the steps ``k = sel[:nsel]`` (``n`` the columns of
    ``Jraw``), by one product over those steps side by side: each entry the same sum as the
    product step by step."""
    if nsel == 0:
        return
    rows, n = Jraw.shape[1], Jraw.shape[2]
    Jc = np.empty((rows, nsel * n))
    for t in range(nsel):
        k = sel[t]
        for i in range(rows):
            for c in range(n):
                Jc[i, t * n + c] = Jraw[k, i, c]
    Oc = np.dot(L, Jc)
    for t in range(nsel):
        k = sel[t]
        for i in range(rows):
            for c in range(n):
                out[k, i, c] = Oc[i, t * n + c]


@njit
def _sumsq(r):
    out = 0.0
    for kk in range(r.shape[0]):
        for i in range(r.shape[1]):
            out += r[kk, i] * r[kk, i]
    return out


@njit
def window_system(Rb, qb, Wb, pos, s0, skip_first,
                  mass, g, dt, com, com_vel, com_acc, inertia, inertia_dot, sigma_l, sigma_dot,
                  active, contact_p, contact_R, rest_p, rest_R, K_fs, K_fd, K_ts, K_td, beta, iso,
                  y_imu, imu_R, imu_p, imu_v, imu_a, imu_w, imu_use, y_ft, use_ft,
                  L_ne, L_c, L_i, inv_imu, inv_ft, L_int, robust_k, sensor_kind, sensor_k,
                  caps, U, gU, Fw, gF, B, weights):
    """Linearise and assemble the window (module docstring).

    The window's steps are at ring positions ``pos`` of ``Rb``, ``qb``, ``Wb`` and at rows
    ``s0 ..`` of the problem's arrays.  ``caps`` (m, 1 + C, 2): upper bounds of the IMU's and each
    F/T's robust weights (``inf``: none); ``weights`` (m, 1 + C, 2) receives them (with
    ``sensor_kind`` 0 untouched).  ``U``, ``gU``, ``Fw``, ``gF``, ``B`` are zeroed and filled;
    returns the cost (``Linearization.cost``)."""
    m = pos.shape[0]
    nc = active.shape[1]
    D = U.shape[1]
    first = 1 if skip_first else 0
    U[:] = 0.0
    gU[:] = 0.0
    Fw[:] = 0.0
    gF[:] = 0.0
    B[:] = 0.0
    total = 0.0
    extra = 0.0
    rs = np.empty(6)
    Js = np.empty((6, S))
    JW = np.empty((6, 6))
    no_rest = np.empty((0, 6))
    # Newton-Euler: required wrench minus the active contacts' wrenches, whitened by L_ne
    r_raw = np.empty((m, 6))
    J_fam = np.empty((m, 6, D))
    J_raw = np.zeros((m, 6, D))
    every = np.arange(m)
    sel_on = np.empty(m, dtype=np.int64)
    sel_off = np.empty(m, dtype=np.int64)
    Wsum = np.empty(6)
    for kk in range(m):
        p = pos[kk]
        s = s0 + kk
        for j in range(6):
            Wsum[j] = Wb[p, 0, j] * (1.0 if active[s, 0] else 0.0)
        for i in range(1, nc):
            a = 1.0 if active[s, i] else 0.0
            for j in range(6):
                Wsum[j] = Wsum[j] + Wb[p, i, j] * a
        core.newton_euler(Rb[p], qb[p], Wsum, mass, com[s], com_vel[s], com_acc[s], inertia[s], inertia_dot[s],
                          sigma_l[s], sigma_dot[s], g, r_raw[kk], Js)
        J_raw[kk, :, :S] = Js
        for i in range(nc):
            for j in range(6):
                J_raw[kk, j, S + 6 * i + j] = -1.0 if active[s, i] else 0.0
        _about_com(com[s], r_raw[kk], J_raw[kk])
    _whiten_steps(L_ne, J_raw, J_fam, every, m)
    r_fam = np.dot(r_raw, L_ne.T)
    if robust_k > 0.0:
        rho_sum = 0.0
        wn_sum = 0.0
        for kk in range(m):
            s = r_fam[kk, 0] * r_fam[kk, 0]
            for i in range(1, 6):
                s = s + r_fam[kk, i] * r_fam[kk, i]
            norm = math.sqrt(s)
            w, rho = _robust(norm, 2, robust_k)
            rho_sum += rho
            wn_sum += w * s
            sw = math.sqrt(w)
            for i in range(6):
                r_fam[kk, i] = r_fam[kk, i] * sw
                for col in range(D):
                    J_fam[kk, i, col] = J_fam[kk, i, col] * sw
        extra += rho_sum - 0.5 * wn_sum
    total += _sumsq(r_fam)
    _add_unary(U, gU, r_fam, J_fam, first, 0)
    # contact law per contact: L_c (active) or L_i (inactive: the wrench held at zero)
    for i in range(nc):
        n_on = 0
        n_off = 0
        J_raw[:] = 0.0
        for kk in range(m):
            p = pos[kk]
            s = s0 + kk
            if active[s, i]:
                core.contact_law(Rb[p], qb[p], Wb[p, i], contact_p[s, i], contact_R[s, i], rest_p[s, i],
                                 rest_R[s, i], K_fs[i], K_fd[i], K_ts[i], K_td[i], beta[i, 0], beta[i, 1], iso[i],
                                 rs, Js, no_rest)
                J_raw[kk, :, :S] = Js
                r_fam[kk] = np.dot(L_c, rs)
                sel_on[n_on] = kk
                n_on += 1
            else:
                for j in range(6):
                    rs[j] = -Wb[p, i, j]
                r_fam[kk] = np.dot(L_i, rs)
                sel_off[n_off] = kk
                n_off += 1
            for j in range(6):
                J_raw[kk, j, S + 6 * i + j] = -1.0
        _whiten_steps(L_c, J_raw, J_fam, sel_on, n_on)
        _whiten_steps(L_i, J_raw, J_fam, sel_off, n_off)
        total += _sumsq(r_fam)
        _add_unary(U, gU, r_fam, J_fam, first, 0)
    # IMU: rows whitened by sigma, missing or saturated axes zero, robust per sensor
    for kk in range(m):
        p = pos[kk]
        s = s0 + kk
        core.imu(Rb[p], qb[p], y_imu[s], imu_R[s], imu_p[s], imu_v[s], imu_a[s], imu_w[s], g, rs, Js)
        for j in range(6):
            u = imu_use[s, j]
            r_fam[kk, j] = (rs[j] * inv_imu[j]) * u
            for col in range(S):
                J_fam[kk, j, col] = (Js[j, col] * inv_imu[j]) * u
            for col in range(S, D):
                J_fam[kk, j, col] = (0.0 * inv_imu[j]) * u
    if sensor_kind != 0:
        extra += _sensor_reweight(r_fam, J_fam, caps[:, 0], sensor_kind, sensor_k, weights[:, 0])
    total += _sumsq(r_fam)
    _add_unary(U, gU, r_fam, J_fam, first, 0)
    # F/T readings: rows whitened by sigma (NaN readings: zero rows), robust per sensor
    if use_ft:
        for i in range(nc):
            for kk in range(m):
                p = pos[kk]
                s = s0 + kk
                if active[s, i]:
                    core.ft(Rb[p], qb[p], Wb[p, i], contact_p[s, i], contact_R[s, i], y_ft[s, i], rs, Js, JW)
                else:
                    rs[:] = 0.0
                    Js[:] = 0.0
                    JW[:] = 0.0
                for j in range(6):
                    r_fam[kk, j] = rs[j] * inv_ft[j]
                    for col in range(D):
                        J_fam[kk, j, col] = 0.0
                    for col in range(S):
                        J_fam[kk, j, col] = Js[j, col] * inv_ft[j]
                    for col in range(6):
                        J_fam[kk, j, S + 6 * i + col] = JW[j, col] * inv_ft[j]
            if sensor_kind != 0:
                extra += _sensor_reweight(r_fam, J_fam, caps[:, 1 + i], sensor_kind, sensor_k, weights[:, 1 + i])
            total += _sumsq(r_fam)
            _add_unary(U, gU, r_fam, J_fam, first, 0)
    # integration between successive steps, whitened by the Brownian-bridge covariance
    if m > 1:
        r_int = np.empty((m - 1, 12))
        J0 = np.zeros((m - 1, 12, D))
        J1 = np.zeros((m - 1, 12, D))
        J0r = np.empty((m - 1, 12, S))
        J1r = np.empty((m - 1, 12, S))
        for kk in range(m - 1):
            p0 = pos[kk]
            p1 = pos[kk + 1]
            core.integration(Rb[p0], qb[p0], Rb[p1], qb[p1], dt, r_int[kk], J0r[kk], J1r[kk])
        _whiten_steps(L_int, J0r, J0, every, m - 1)
        _whiten_steps(L_int, J1r, J1, every, m - 1)
        r_w = np.dot(r_int, L_int.T)
        total += _sumsq(r_w)
        _add_binary(Fw, U, B, gF, gU, r_w, J0, J1)
    return 0.5 * total + extra


@njit
def _predict_into(Rb, qb, Wb, dx, p_prev, p_new, s, dt, active, contact_p, contact_R, rest_p, rest_R,
                  K_fs, K_fd, K_ts, K_td, beta, iso):
    """The new step at ring position ``p_new`` (problem row ``s``) predicted from the current
    estimate of the previous one (``FixedLagSmoother._predict``: ``predict_step`` and the contact
    law's wrenches at the prediction)."""
    R_prev = so3_exp(dx[p_prev, :3]) @ Rb[p_prev]
    q_prev = qb[p_prev] + dx[p_prev, 3:S]
    w = q_prev[3:6]
    v = q_prev[6:9]
    dw = q_prev[9:12]
    a = q_prev[12:15]
    Rb[p_new] = so3_exp(w * dt + 0.5 * dw * dt * dt) @ R_prev
    q = qb[p_new]
    q[:] = q_prev
    q[0:3] = q_prev[0:3] + v * dt + 0.5 * a * dt * dt
    q[3:6] = w + dw * dt
    q[6:9] = v + a * dt
    nc = Wb.shape[1]
    r = np.empty(6)
    J = np.empty((6, S))
    zero = np.zeros(6)
    no_rest = np.empty((0, 6))
    for i in range(nc):
        if active[s, i]:
            core.contact_law(Rb[p_new], q, zero, contact_p[s, i], contact_R[s, i], rest_p[s, i], rest_R[s, i],
                             K_fs[i], K_fd[i], K_ts[i], K_td[i], beta[i, 0], beta[i, 1], iso[i], r, J, no_rest)
            Wb[p_new, i] = r
        else:
            Wb[p_new, i] = 0.0
    dx[p_new] = 0.0


@njit
def window_update(Rb, qb, Wb, dx, Ld, C, y, Sp, rp, f, k0, k1, oldest, s_base,
                  mass, g, dt, com, com_vel, com_acc, inertia, inertia_dot, sigma_l, sigma_dot,
                  active, contact_p, contact_R, rest_p, rest_R, K_fs, K_fd, K_ts, K_td, beta, iso,
                  y_imu, imu_R, imu_p, imu_v, imu_a, imu_w, imu_use, y_ft, use_ft,
                  L_ne, L_c, L_i, inv_imu, inv_ft, L_int, robust_k, sensor_kind, sensor_k,
                  weight_cap, use_caps, U, gU, Fw, gF, B, caps, weights):
    """One update of the fixed-lag window adding the samples ``k0 .. k1-1`` (``f > 0``: the
    oldest relinearised step ``f`` is frozen, its predecessors eliminated), on the smoother's ring
    buffers (``FixedLagSmoother._update``'s operations, in its order): retract steps ``f+1 ..
    k0-1`` to their estimate, predict the new steps, linearise and assemble
    (:func:`window_system`), lower the sensors' weight caps ``weight_cap`` (1 + C, problem
    steps, 2) of the steps before the new ones (``use_caps``), eliminate oldest first
    (``solvers.window_eliminate``) into ``Ld``, ``C``, ``y``, ``Sp``, ``rp``, back-substitute from
    step ``k1-1`` down to ``oldest``.  ``s_base``: the problem's first step.  ``U`` .. ``weights``:
    scratch of the window's size.  Returns False when the newest step's estimate is not finite;
    raises LinAlgError when the system is not positive definite.

    The integration factors touch the core state only: the cross blocks ``B`` and the rows of
    ``C`` past it are zero, and the products with them are left out (the same results)."""
    cap = Rb.shape[0]
    nc = Wb.shape[1]
    for k in range(f + 1, k0):  # window_retract, without effects
        p = k % cap
        retract_core(Rb, qb, Wb, dx, p, S)
        dx[p, :] = 0.0
    pk0 = k0 % cap
    _predict_into(Rb, qb, Wb, dx, (k0 - 1) % cap, pk0, k0 - s_base, dt, active, contact_p, contact_R, rest_p,
                  rest_R, K_fs, K_fd, K_ts, K_td, beta, iso)
    for k in range(k0 + 1, k1):  # the block's later samples start at its first one's prediction
        p = k % cap
        Rb[p] = Rb[pk0]
        qb[p] = qb[pk0]
        Wb[p] = Wb[pk0]
        dx[p] = 0.0
    m = k1 - f
    s0 = f - s_base
    pos = np.empty(m, dtype=np.int64)
    for i in range(m):
        pos[i] = (f + i) % cap
    nf = 1 + (nc if use_ft else 0)
    caps[:] = np.inf
    if use_caps:
        for kk in range(m):
            for j in range(nf):
                for c in range(2):
                    caps[kk, j, c] = weight_cap[j, s0 + kk, c]
    window_system(Rb, qb, Wb, pos, s0, True, mass, g, dt, com, com_vel, com_acc, inertia,
                         inertia_dot, sigma_l, sigma_dot, active, contact_p, contact_R, rest_p, rest_R, K_fs, K_fd,
                         K_ts, K_td, beta, iso, y_imu, imu_R, imu_p, imu_v, imu_a, imu_w, imu_use, y_ft, use_ft,
                         L_ne, L_c, L_i, inv_imu, inv_ft, L_int, robust_k, sensor_kind, sensor_k, caps,
                         U, gU, Fw, gF, B, weights)
    if use_caps and sensor_kind != 0:  # FixedLagSmoother._lower_weight_caps
        for kk in range(m - (k1 - k0)):
            for j in range(nf):
                for c in range(2):
                    w = weights[kk, j, c]
                    if w < weight_cap[j, s0 + kk, c] or w != w:
                        weight_cap[j, s0 + kk, c] = w
    # elimination (solvers.window_eliminate with a frozen first step), in the ring buffers
    D = U.shape[1]
    X = np.empty((D, D))
    for i in range(m):
        p = pos[i]
        if i > 0:
            q = pos[i - 1]
            Cq = C[q, :S]
            CC = Cq @ Cq.T
            Sp[p] = U[i]
            for a in range(S):
                for b in range(S):
                    Sp[p, a, b] = U[i, a, b] - CC[a, b]
            rp[p] = gU[i] - C[q] @ y[q]
        Ld[p] = np.linalg.cholesky(Sp[p] + Fw[i])
        if i < m - 1:
            _trsm_lower_rows_t(Ld[p], B[i, :, :S], X, C[p, :S])
            C[p, S:] = 0.0
        y[p] = _trsv_lower(Ld[p], rp[p] + gF[i])
    window_back_substitute(Ld, C, y, np.arange(k1 - 1, oldest - 1, -1) % cap, dx)
    pk = (k1 - 1) % cap
    for i in range(D):
        if not np.isfinite(dx[pk, i]):
            return False
    return True


@njit
def window_states(Rb, qb, Wb, eb, dx, j0, j1, R, q, W, e):
    """The current estimates of steps ``j0 .. j1-1`` (``FixedLagSmoother._state``: the
    linearisation point moved by ``dx``) into ``R``, ``q``, ``W``, ``e`` (rows ``0 .. j1-j0-1``)."""
    cap = Rb.shape[0]
    nc = Wb.shape[1]
    for j in range(j0, j1):
        p = j % cap
        i = j - j0
        R[i] = so3_exp(dx[p, :3]) @ Rb[p]
        for c in range(15):
            q[i, c] = qb[p, c] + dx[p, 3 + c]
        for c in range(nc):
            for a in range(6):
                W[i, c, a] = Wb[p, c, a] + dx[p, S + 6 * c + a]
        for c in range(eb.shape[1]):
            e[i, c] = eb[p, c] + dx[p, S + 6 * nc + c]


# ----------------------------------------------------------------------------------------------
# Window marginals at a read-out (FixedLagSmoother._covariances), in one call
# ----------------------------------------------------------------------------------------------


@njit
def _tri_inv(L, M):
    """``M = L^-1`` for lower-triangular ``L``: ``solvers._trsm_lower(L, eye)``'s operations
    without its products with the zeros above the diagonal (the same result)."""
    d = L.shape[0]
    for j in range(d):
        for i in range(j):
            M[i, j] = 0.0
        for i in range(j, d):
            acc = 1.0 if i == j else 0.0
            for k in range(j, i):
                acc -= L[i, k] * M[k, j]
            M[i, j] = acc / L[i, i]


@njit
def _sandwich(A, G, P, nz):
    """``A + G^T P G`` for ``G`` whose rows from ``nz`` on are zero (the products with them left
    out: the same result as the whole product)."""
    if nz == G.shape[0]:
        return A + G.T @ P @ G
    Gs = G[:nz]
    return A + Gs.T @ np.ascontiguousarray(P[:nz, :nz]) @ Gs


@njit
def _marginal_step(Ldp, Cp, Pn, first, eye, M, nz):
    """``solvers._marginal_step`` (``C``'s rows from ``nz`` on zero)."""
    _tri_inv(Ldp, M)
    if first:
        return M.T @ M
    return M.T @ _sandwich(eye, Cp, Pn, nz) @ M


@njit
def window_covariances(Ld, C, A, G, Ab, Phib, P, k, hi, start, bb0, bb1, top, b, j0, j1, R, nz):
    """The read-out's marginals of ``FixedLagSmoother._covariances`` (the blocked branch) in one
    call: the final steps ``start .. hi``'s factors (``solvers.window_final_factors``), the block
    maps of blocks ``bb0 .. bb1-1`` (``solvers.window_block_map``), the marginals of steps ``j0
    .. j1-1`` into ``P`` (``solvers.window_marginals_blocked``: from step ``k`` down through
    ``hi + 1``, the final steps down to ``(top + 1) R``, blocks ``top .. b+1``).  Ring positions
    are taken modulo the ring's size, block slots modulo ``len(Ab)``.  The rows of ``C`` from ``nz``
    on are zero (the integration factors touch the core state only, without effects): the
    products with them are left out, the results the same."""
    cap = Ld.shape[0]
    nblk = Ab.shape[0]
    d = Ld.shape[1]
    eye = np.eye(d)
    M = np.empty((d, d))
    for j in range(start, hi + 1):  # window_final_factors
        p = j % cap
        _tri_inv(Ld[p], M)
        A[p] = M.T @ M
        if nz == d:
            G[p] = C[p] @ M
        else:
            G[p, :nz] = C[p, :nz] @ M
            G[p, nz:] = 0.0
    for bb in range(bb0, bb1):  # window_block_map
        p = (bb * R + R - 1) % cap
        Acc = A[p].copy()
        Phi = G[p].copy()
        for kk in range(R - 2, -1, -1):
            p = (bb * R + kk) % cap
            Acc = _sandwich(A[p], G[p], Acc, nz)
            if nz == d:
                Phi = Phi @ G[p]
            else:
                Phi = np.ascontiguousarray(Phi[:, :nz]) @ G[p, :nz]
        Ab[bb % nblk] = Acc
        Phib[bb % nblk] = Phi
    # window_marginals_blocked
    Pn = np.empty((d, d))
    for kk in range(k - hi):
        p = (k - kk) % cap
        Pn = _marginal_step(Ld[p], C[p], Pn, kk == 0, eye, M, nz)
    for j in range(hi, (top + 1) * R - 1, -1):
        p = j % cap
        Pn = _sandwich(A[p], G[p], Pn, nz)
    for bb in range(top, b, -1):
        slot = bb % nblk
        Pn = _sandwich(Ab[slot], Phib[slot], Pn, nz)
    for j in range(j1 - 1, j0 - 1, -1):
        p = j % cap
        Pn = _sandwich(A[p], G[p], Pn, nz)
        P[p] = Pn
