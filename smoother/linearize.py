r"""Whole-trajectory linearisation of the factor graph, vectorised over the steps.

The graph is a chain: every factor touches one step except the integration factors, which touch
two successive steps.  Ordered by time, the Gauss-Newton matrix is block tridiagonal with blocks
of the per-step state dimension ``D = 18 + 6 C + effects``; :func:`assemble` builds its blocks and
:func:`flexforce.factors.kernels.block_tridiag_solve` solves it in ``O(N D^3)``.

Per-step state (columns of every Jacobian): ``(theta, t, w, v, dw, a)`` (world-frame increments),
then ``W_1 .. W_C`` (F N, T N m about the world origin), then the effects' unknowns.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flexforce.errors import EstimatorError
from flexforce.factors import kernels

S = kernels.STATE_DIM


@dataclass
class Trajectory:
    """Values of every variable: ``R`` (N, 3, 3), ``q`` (N, 15) = (t, w, v, dw, a), ``W`` (N, C, 6),
    ``e`` (N, effect dims)."""

    R: np.ndarray
    q: np.ndarray
    W: np.ndarray
    e: np.ndarray

    def copy(self) -> "Trajectory":
        return Trajectory(self.R.copy(), self.q.copy(), self.W.copy(), self.e.copy())

    def retract(self, dx: np.ndarray) -> "Trajectory":
        """A new trajectory moved by ``dx`` (N, D) in world-frame increments."""
        out = self.copy()
        kernels.retract_all(out.R, out.q, np.ascontiguousarray(dx[:, :S]))
        nc = self.W.shape[1]
        out.W += dx[:, S:S + 6 * nc].reshape(out.W.shape)
        out.e += dx[:, S + 6 * nc:]
        return out


@dataclass
class Linearization:
    """Whitened residuals and Jacobians of every family at one trajectory."""

    unary: dict = field(default_factory=dict)
    """family -> (r (N, m), J (N, m, D)) for factors on one step (the prior only on step 0)."""
    binary: dict = field(default_factory=dict)
    """family -> (r (N-1, m), J0 (N-1, m, D), J1 (N-1, m, D)) for factors between steps k, k+1."""
    cost: float = 0.0
    """Half the sum of squared whitened residuals."""


def _whiten_rows(r, J, sigma):
    """Divide rows by sigma ((m,) or (N, m))."""
    inv = 1.0 / np.asarray(sigma)
    if inv.ndim == 1:
        return r * inv, J * inv[:, None]
    return r * inv, J * inv[:, :, None]


def linearize(prob, traj: Trajectory) -> Linearization:
    """Evaluate every factor of ``prob`` at ``traj`` (residuals whitened, Jacobians in world increments)."""
    n, nc = prob.n, prob.nc
    D = prob.state_dim
    sig = prob.sigmas
    R = np.ascontiguousarray(traj.R)
    q = np.ascontiguousarray(traj.q)
    W = np.ascontiguousarray(traj.W)
    act = prob.active
    lin = Linearization()
    steps = np.arange(n)
    eye6 = np.eye(6)
    w_cols = [slice(S + 6 * i, S + 6 * i + 6) for i in range(nc)]
    e_cols, off = [], S + 6 * nc
    for d in prob.effect_dims:
        e_cols.append(slice(off, off + d))
        off += d
    e_parts = []
    off = 0
    for d in prob.effect_dims:
        e_parts.append(traj.e[:, off:off + d])
        off += d

    def add_effects(family, r, J):
        for eff, cols, ev in zip(prob.effects, e_cols, e_parts):
            terms = eff.residual_terms(family, prob, steps, R, q, W, ev)
            if terms is None:
                continue
            dr, dr_ds, dr_de = terms
            r += dr
            J[:, :, :S] += dr_ds
            J[:, :, cols] += dr_de

    # Newton-Euler (eq. 16, 23): required wrench minus the active contacts' wrenches.
    Wsum = np.ascontiguousarray((W * act[:, :, None]).sum(axis=1))
    r = np.empty((n, 6))
    Js = np.empty((n, 6, S))
    kernels.newton_euler_all(R, q, Wsum, float(prob.rec.mass), prob.com, prob.com_vel, prob.com_acc,
                             prob.inertia, prob.inertia_dot, prob.sigma_l, prob.sigma_dot, prob.g, r, Js)
    J = np.zeros((n, 6, D))
    J[:, :, :S] = Js
    for i in range(nc):
        J[:, :, w_cols[i]] = -eye6 * act[:, i, None, None]
    add_effects("newton_euler", r, J)
    lin.unary["newton_euler"] = _whiten_rows(r, J, sig.newton_euler)

    # Contact law (eq. 6-12), one factor per contact; an inactive contact's wrench is held at zero.
    rc = np.empty((n, nc, 6))
    Jc = np.empty((n, nc, 6, S))
    kernels.contact_all(R, q, W, act, prob.contact_p, prob.contact_R, prob.K_fs, prob.K_fd, prob.K_ts,
                        prob.K_td, prob.beta, prob.iso, rc, Jc)
    for i in range(nc):
        J = np.zeros((n, 6, D))
        J[:, :, :S] = Jc[:, i]
        J[:, :, w_cols[i]] = -eye6
        sigma = np.where(act[:, i, None], sig.contact, sig.contact * sig.inactive_factor)
        lin.unary[f"contact/{i}"] = _whiten_rows(rc[:, i].copy(), J, sigma)

    # IMU (eq. 26-28).
    r = np.empty((n, 6))
    Js = np.empty((n, 6, S))
    kernels.imu_all(R, q, prob.y_imu, prob.imu_R, prob.imu_p, prob.imu_v, prob.imu_a, prob.imu_w, prob.g, r, Js)
    J = np.zeros((n, 6, D))
    J[:, :, :S] = Js
    add_effects("imu", r, J)
    lin.unary["imu"] = _whiten_rows(r, J, sig.imu)

    # F/T readings (optional).
    if prob.use_ft:
        rf = np.empty((n, nc, 6))
        Jf = np.empty((n, nc, 6, S))
        JW = np.empty((n, nc, 6, 6))
        kernels.ft_all(R, q, W, act, prob.contact_p, prob.contact_R, prob.y_ft, rf, Jf, JW)
        for i in range(nc):
            J = np.zeros((n, 6, D))
            J[:, :, :S] = Jf[:, i]
            J[:, :, w_cols[i]] = JW[:, i]
            lin.unary[f"ft/{i}"] = _whiten_rows(rf[:, i].copy(), J, sig.ft)

    # Prior on the first step (core state), around the static equilibrium.
    R0, q0 = prob.prior_mean
    phi = kernels.so3_log(R[0] @ R0.T)
    r = np.concatenate([phi, q[0] - q0])[None, :]
    J = np.zeros((n, S, D))[:1]
    J[0, :3, :3] = kernels.so3_jl_inv(phi)
    J[0, 3:S, 3:S] = np.eye(S - 3)
    lin.unary["prior"] = _whiten_rows(r, J, sig.prior)

    # Effects' own factors: prior on the first step, random walk between steps.
    for eff, cols, ev in zip(prob.effects, e_cols, e_parts):
        mean, sigma = eff.prior(prob)
        J = np.zeros((1, eff.dim, D))
        J[0, :, cols] = np.eye(eff.dim)
        lin.unary[f"effect_prior/{eff.name}"] = _whiten_rows((ev[0] - mean)[None, :], J, np.asarray(sigma))
        if n > 1:
            rw = np.asarray(eff.random_walk_sigma(prob), dtype=float)
            J0 = np.zeros((n - 1, eff.dim, D))
            J1 = np.zeros((n - 1, eff.dim, D))
            J0[:, :, cols] = -np.eye(eff.dim)
            J1[:, :, cols] = np.eye(eff.dim)
            r = (ev[1:] - ev[:-1]) / rw
            lin.binary[f"effect_walk/{eff.name}"] = (r, J0 / rw[:, None], J1 / rw[:, None])

    # Integration between successive steps, whitened by the Brownian-bridge covariance.
    if n > 1:
        r = np.empty((n - 1, 12))
        J0s = np.empty((n - 1, 12, S))
        J1s = np.empty((n - 1, 12, S))
        kernels.integration_all(R, q, prob.dt, r, J0s, J1s)
        Linv = prob.integration_whitener
        J0 = np.zeros((n - 1, 12, D))
        J1 = np.zeros((n - 1, 12, D))
        J0[:, :, :S] = Linv @ J0s
        J1[:, :, :S] = Linv @ J1s
        lin.binary["integration"] = (r @ Linv.T, J0, J1)

    total = 0.0
    for r, _ in lin.unary.values():
        total += float(np.sum(r * r))
    for r, _, _ in lin.binary.values():
        total += float(np.sum(r * r))
    lin.cost = 0.5 * total
    return lin


def assemble(lin: Linearization, n: int, D: int):
    """Gauss-Newton blocks: diagonal ``Hd`` (N, D, D), upper ``B`` (N-1, D, D) and ``g = -J^T r`` (N, D)."""
    Hd = np.zeros((n, D, D))
    B = np.zeros((max(n - 1, 0), D, D))
    g = np.zeros((n, D))
    for r, J in lin.unary.values():
        m = r.shape[0]
        Jt = J.transpose(0, 2, 1)
        Hd[:m] += Jt @ J
        g[:m] -= (Jt @ r[:, :, None])[:, :, 0]
    for r, J0, J1 in lin.binary.values():
        J0t = J0.transpose(0, 2, 1)
        J1t = J1.transpose(0, 2, 1)
        Hd[:-1] += J0t @ J0
        Hd[1:] += J1t @ J1
        B += J0t @ J1
        g[:-1] -= (J0t @ r[:, :, None])[:, :, 0]
        g[1:] -= (J1t @ r[:, :, None])[:, :, 0]
    return Hd, B, g


def _matvec(Hd, B, x):
    y = (Hd @ x[:, :, None])[:, :, 0]
    y[:-1] += (B @ x[1:, :, None])[:, :, 0]
    y[1:] += (B.transpose(0, 2, 1) @ x[:-1, :, None])[:, :, 0]
    return y


def solve(Hd, B, g, damping: float = 0.0, want_cov: bool = False):
    """Solve the (Levenberg-Marquardt damped) block-tridiagonal system with Jacobi scaling.

    Returns ``dx`` (N, D) and, with ``want_cov``, the marginal covariances (N, D, D) of ``H^-1``.
    """
    diag = np.diagonal(Hd, axis1=1, axis2=2)
    scale = 1.0 / np.sqrt(np.maximum(diag, 1e-300))
    Hs = Hd * scale[:, :, None] * scale[:, None, :]
    if damping > 0.0:
        idx = np.arange(Hd.shape[1])
        Hs[:, idx, idx] *= 1.0 + damping
    Bs = B * scale[:-1, :, None] * scale[1:, None, :]
    Hs = np.ascontiguousarray(Hs)
    Bs = np.ascontiguousarray(Bs)
    gs = np.ascontiguousarray(g * scale)
    try:
        x, P = kernels.block_tridiag_solve(Hs, Bs, gs, want_cov)
        # One step of iterative refinement: the tight integration factors leave the scaled
        # system with a condition number near 1e10 (measured), costing ~5 digits.
        x2, _ = kernels.block_tridiag_solve(Hs, Bs, np.ascontiguousarray(gs - _matvec(Hs, Bs, x)), False)
    except np.linalg.LinAlgError as err:
        raise EstimatorError("smoother: the Gauss-Newton system is not positive definite "
                             "(an unobservable direction: check contacts and stiffness)") from err
    dx = (x + x2) * scale
    if want_cov:
        P = P * scale[:, :, None] * scale[:, None, :]
        return dx, P
    return dx, None
