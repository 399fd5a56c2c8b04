r"""Whole-trajectory linearisation of the factor graph, vectorised over the steps.

The graph is a chain: every factor touches one step except the integration factors, which touch
two successive steps.  Ordered by time, the Gauss-Newton matrix is block tridiagonal with blocks
of the per-step state dimension ``D = 18 + 6 C + effects``; :func:`assemble` builds its blocks and
:func:`flexforce.factors.solvers.block_tridiag_solve` solves it in ``O(N D^3)``.

Per-step state (columns of every Jacobian): ``(theta, t, w, v, dw, a)`` (world-frame increments),
then ``W_1 .. W_C`` (F N, T N m about the world origin), then the effects' unknowns.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from flexforce.datasets.faults import robust_weights
from flexforce.errors import EstimatorError
from flexforce.factors import core
from flexforce.factors.effects.base import traits
from flexforce.factors.physics import about_com
from flexforce.smoother import solvers

S = core.STATE_DIM
_NO_REST_JAC = np.empty((0, 1, 6, 6))


_NOT_PD = ("smoother: the Gauss-Newton system is not positive definite "
           "(an unobservable direction: check contacts and stiffness)")


@dataclass
class Trajectory:
    """Values of every variable: ``R`` (N, 3, 3), ``q`` (N, 15) = (t, w, v, dw, a), ``W`` (N, C, 6),
    ``e`` (N, effect dims)."""

    R: np.ndarray
    q: np.ndarray
    W: np.ndarray
    e: np.ndarray

    def copy(self) -> Trajectory:
        return Trajectory(self.R.copy(), self.q.copy(), self.W.copy(), self.e.copy())

    def retract(self, dx: np.ndarray) -> Trajectory:
        """A new trajectory moved by ``dx`` (N, D) in world-frame increments."""
        out = self.copy()
        core.retract_all(out.R, out.q, np.ascontiguousarray(dx[:, :S]))
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
    weights: dict = field(default_factory=dict)
    """family -> (n, sensors) robust weights of the sensor families (``imu``, ``ft/<i>``)."""
    ne_weights: np.ndarray | None = None
    """(n,) Huber (IRLS) weights of the Newton-Euler rows, whose residuals and Jacobians in
    ``unary`` are scaled by their square root; None without a robust Newton-Euler loss."""


def _whiten_rows(r, J, sigma):
    """Divide rows by sigma ((m,) or (N, m))."""
    inv = 1.0 / np.asarray(sigma)
    if inv.ndim == 1:
        return r * inv, J * inv[:, None]
    return r * inv, J * inv[:, :, None]


def _whiten_matrix(r, J, Linv):
    """Whiten by a full ``L^-1`` (m, m)."""
    return r @ Linv.T, Linv @ J


def walk_sigma(eff, prob) -> np.ndarray:
    """(N - 1, dim) random-walk sigma of an effect per transition (its ``random_walk_sigma``, given
    per effect or per transition)."""
    rw = np.asarray(eff.random_walk_sigma(prob), dtype=float)
    return np.broadcast_to(rw, (max(prob.n - 1, 0), int(eff.dim)))


def huber_weights(r, k):
    """IRLS weights of a Huber loss on each row's norm (whitened units) and the robust cost per row."""
    norm = np.sqrt(np.sum(r * r, axis=1))
    w = np.where(norm <= k, 1.0, k / np.maximum(norm, 1e-300))
    cost = np.where(norm <= k, 0.5 * norm**2, k * norm - 0.5 * k * k)
    return w, cost


def sensor_weights(r, groups, kind, k):
    """(n, len(groups)) IRLS weights, robust costs and whitened norms of the row groups of ``r``
    (one group per sensor: gyro rows 0-2, accelerometer rows 3-5)."""
    norms = np.stack([np.sqrt(np.sum(r[:, a:b] ** 2, axis=1)) for a, b in groups], axis=1)
    w, rho = robust_weights(norms, kind, k)
    return w, rho, norms


def sensor_reweight(r, J, groups, kind, k, cap=None):
    """IRLS on each sensor's whitened 3-D residual: rows scaled by ``sqrt(w)``; returns ``(r, J,
    extra cost, w)`` with the extra cost making ``0.5 |r_w|^2 + extra`` the robust cost.

    ``cap`` (n, groups): upper bounds of the weights (the fixed-lag smoother's memory of the
    weight each sample had when it was first linearised, so that a rejected sample is not let
    back in as the estimate drifts towards it)."""
    w, rho, norms = sensor_weights(r, groups, kind, k)
    if cap is not None:
        w = np.minimum(w, cap)
    r, J = r.copy(), J.copy()
    for j, (a, b) in enumerate(groups):
        sw = np.sqrt(w[:, j])
        r[:, a:b] *= sw[:, None]
        J[:, a:b] *= sw[:, None, None]
    return r, J, float(np.sum(rho)) - 0.5 * float(np.sum(w * norms**2)), w


FAMILY_GROUPS = ("newton_euler", "contact", "imu", "ft", "prior", "effects", "integration")
"""The groups of factor families :func:`linearize` can evaluate alone (``families=``): the
Newton-Euler rows, the contact laws, the IMU, the F/T readings, the first step's prior, the
effects' own factors (prior, level, random walk, ``factors``) and the integration."""


def _constant_rows(prob, key: tuple, where: tuple, make: Callable[[], tuple]) -> tuple:
    """What ``make()`` forms for the rows ``where`` (first step, steps, columns) of an effect's
    prior level or random walk, whose Jacobians are the same at every linearisation: from the
    problem's cache (:class:`~flexforce.smoother.problem.ConstantRows`, ``key`` = (effect index,
    kind)); a problem without one (another :class:`ProblemView`) forms them each time.  Why: these
    dense (N, dim, D) rows are a large part of a linearisation (docs/smoother.md, "Caches")."""
    cache = getattr(prob, "constant_rows", None)
    if cache is None:
        return make()
    return cache.get(key, where, make)


@dataclass
class _Point:
    """What every family's rows of one :func:`linearize` call read: the steps ``k0 .. k0 + n - 1``
    of ``prob`` (its rows ``sl``), the trajectory's arrays, the column layout, and the
    accumulated robust-loss cost correction (``extra_cost``, added to in the families' order)."""

    prob: Any
    n: int
    D: int
    k0: int
    base: int
    sl: slice
    R: np.ndarray
    q: np.ndarray
    W: np.ndarray
    act: np.ndarray
    steps: np.ndarray
    w_cols: list
    e_cols: list
    e_parts: list
    lin: Linearization
    extra_cost: float = 0.0

    def add_effects(self, family, r, J):
        """Every effect's term of ``family`` added to ``r`` and ``J`` in place."""
        for eff, cols, ev in zip(self.prob.effects, self.e_cols, self.e_parts):
            terms = eff.residual_terms(family, self.prob, self.steps, self.R, self.q, self.W, ev)
            if terms is None:
                continue
            dr, dr_ds, dr_de = terms
            r += dr
            J[:, :, :S] += dr_ds
            J[:, :, cols] += dr_de

    def effect_terms(self, family) -> list:
        """``(columns, (dr, dr_ds, dr_de))`` of every effect with a term in ``family`` (per contact)."""
        out = []
        for eff, cols, ev in zip(self.prob.effects, self.e_cols, self.e_parts):
            terms = eff.residual_terms(family, self.prob, self.steps, self.R, self.q, self.W, ev)
            if terms is not None:
                out.append((cols, terms))
        return out


def _point(prob, traj: Trajectory, k0: int) -> _Point:
    n = traj.R.shape[0]
    # A problem over a part of a stream holds the steps from ``prob.offset`` on (its row 0); the
    # priors of the first step belong to step 0 of the stream only.
    base = int(getattr(prob, "offset", 0))
    sl = slice(k0 - base, k0 - base + n)
    D = prob.state_dim
    R = np.ascontiguousarray(traj.R)
    q = np.ascontiguousarray(traj.q)
    W = np.ascontiguousarray(traj.W)
    act = prob.active[sl]
    lin = Linearization()
    steps = np.arange(k0 - base, k0 - base + n)
    w_cols = [slice(S + 6 * i, S + 6 * i + 6) for i in range(prob.nc)]
    e_cols, off = [], S + 6 * prob.nc
    for d in prob.effect_dims:
        e_cols.append(slice(off, off + d))
        off += d
    e_parts = []
    off = 0
    for d in prob.effect_dims:
        e_parts.append(traj.e[:, off:off + d])
        off += d
    return _Point(prob, n, D, k0, base, sl, R, q, W, act, steps, w_cols, e_cols, e_parts, lin)


def _newton_euler_rows(at: _Point, robust: bool) -> None:
    """Newton-Euler (eq. 16, 23): required wrench minus the active contacts' wrenches."""
    prob, n, sl, act, sig = at.prob, at.n, at.sl, at.act, at.prob.sigmas
    Wsum = np.ascontiguousarray((at.W * act[:, :, None]).sum(axis=1))
    r = np.empty((n, 6))
    Js = np.empty((n, 6, S))
    core.newton_euler_all(at.R, at.q, Wsum, float(prob.rec.mass), prob.com[sl], prob.com_vel[sl], prob.com_acc[sl],
                          prob.inertia[sl], prob.inertia_dot[sl], prob.sigma_l[sl], prob.sigma_dot[sl], prob.g,
                          r, Js)
    J = np.zeros((n, 6, at.D))
    J[:, :, :S] = Js
    eye6 = np.eye(6)
    for i in range(prob.nc):
        J[:, :, at.w_cols[i]] = -eye6 * act[:, i, None, None]
    at.add_effects("newton_euler", r, J)
    r, J = about_com(prob.com[sl], r, J)
    r, J = _whiten_matrix(r, J, prob.ne_whitener)
    if robust and sig.robust_k is not None:
        w, rho = huber_weights(r, sig.robust_k)
        sw = np.sqrt(w)
        at.extra_cost += float(np.sum(rho)) - 0.5 * float(np.sum(w * np.sum(r * r, axis=1)))
        r, J = r * sw[:, None], J * sw[:, None, None]
        at.lin.ne_weights = w
    at.lin.unary["newton_euler"] = (r, J)


def _contact_rows(at: _Point) -> None:
    """Contact law (eq. 6-12), one factor per contact; an inactive contact's wrench is held at zero."""
    prob, n, sl, act, sig, D = at.prob, at.n, at.sl, at.act, at.prob.sigmas, at.D
    nc = prob.nc
    rc = np.empty((n, nc, 6))
    Jc = np.empty((n, nc, 6, S))
    core.contact_all(at.R, at.q, at.W, act, prob.contact_p[sl], prob.contact_R[sl], prob.rest_p[sl], prob.rest_R[sl],
                     prob.K_fs, prob.K_fd, prob.K_ts, prob.K_td, prob.beta, prob.iso, rc, Jc, _NO_REST_JAC)
    # Effects acting on the contact law (stiffness scales, anisotropy, cubic terms): their term,
    # per contact, is added where the contact is active (an inactive one's wrench stays at zero).
    c_terms = at.effect_terms("contact")
    Lc = prob.contact_whitener
    Li = np.diag(1.0 / (np.sqrt(np.diag(sig.contact_cov)) * sig.inactive_factor))
    eye6 = np.eye(6)
    for i in range(nc):
        J = np.zeros((n, 6, D))
        J[:, :, :S] = Jc[:, i]
        J[:, :, at.w_cols[i]] = -eye6
        if c_terms:
            on = act[:, i, None]
            for cols, (dr, dr_ds, dr_de) in c_terms:
                rc[:, i] += np.where(on, dr[:, i], 0.0)
                J[:, :, :S] += np.where(on[:, :, None], dr_ds[:, i], 0.0)
                J[:, :, cols] += np.where(on[:, :, None], dr_de[:, i], 0.0)
        Lk = np.where(act[:, i, None, None], Lc, Li)
        at.lin.unary[f"contact/{i}"] = ((Lk @ rc[:, i, :, None])[:, :, 0], Lk @ J)


def _imu_rows(at: _Point, robust: bool) -> None:
    """IMU (eq. 26-28); missing or saturated axes have zero rows."""
    prob, n, sl, sig = at.prob, at.n, at.sl, at.prob.sigmas
    r = np.empty((n, 6))
    Js = np.empty((n, 6, S))
    core.imu_all(at.R, at.q, prob.y_imu[sl], prob.imu_R[sl], prob.imu_p[sl], prob.imu_v[sl], prob.imu_a[sl],
                 prob.imu_w[sl], prob.g, r, Js)
    J = np.zeros((n, 6, at.D))
    J[:, :, :S] = Js
    at.add_effects("imu", r, J)
    r, J = _whiten_rows(r, J, sig.imu)
    use = prob.imu_use[sl]  # missing or saturated axes: zero weight
    r, J = r * use, J * use[:, :, None]
    if robust and sig.imu_robust is not None:
        cap = prob.weight_cap.get("imu") if prob.weight_cap is not None else None
        r, J, c, w = sensor_reweight(r, J, ((0, 3), (3, 6)), sig.imu_robust, sig.imu_robust_k,
                                     None if cap is None else cap[sl])
        at.extra_cost += c
        at.lin.weights["imu"] = w
    at.lin.unary["imu"] = (r, J)


def _ft_rows(at: _Point, robust: bool) -> None:
    """F/T readings, one factor per contact; NaN readings give zero rows (core.ft)."""
    prob, n, sl, act, sig, D = at.prob, at.n, at.sl, at.act, at.prob.sigmas, at.D
    nc = prob.nc
    rf = np.empty((n, nc, 6))
    Jf = np.empty((n, nc, 6, S))
    JW = np.empty((n, nc, 6, 6))
    core.ft_all(at.R, at.q, at.W, act, prob.contact_p[sl], prob.contact_R[sl], prob.y_ft[sl], rf, Jf, JW)
    # Effects on the readings (sensor offsets): their term, per contact, where the reading is
    # fused (contact active, component finite); elsewhere the rows stay zero like the reading's.
    f_terms = at.effect_terms("ft")
    for i in range(nc):
        J = np.zeros((n, 6, D))
        J[:, :, :S] = Jf[:, i]
        J[:, :, at.w_cols[i]] = JW[:, i]
        r = rf[:, i].copy()
        if f_terms:
            on = act[:, i, None] & np.isfinite(prob.y_ft[sl][:, i])
            for cols, (dr, dr_ds, dr_de) in f_terms:
                r += np.where(on, dr[:, i], 0.0)
                J[:, :, :S] += np.where(on[:, :, None], dr_ds[:, i], 0.0)
                J[:, :, cols] += np.where(on[:, :, None], dr_de[:, i], 0.0)
        r, J = _whiten_rows(r, J, sig.ft)  # NaN readings: zero rows (core.ft)
        if robust and sig.imu_robust is not None:
            cap = prob.weight_cap.get(f"ft/{i}") if prob.weight_cap is not None else None
            r, J, c, w = sensor_reweight(r, J, ((0, 3), (3, 6)), sig.imu_robust, sig.imu_robust_k,
                                         None if cap is None else cap[sl])
            at.extra_cost += c
            at.lin.weights[f"ft/{i}"] = w
        at.lin.unary[f"ft/{i}"] = (r, J)


def _prior_rows(at: _Point) -> None:
    """Prior on the first step (core state), around the static equilibrium."""
    R, q = at.R, at.q
    R0, q0 = at.prob.prior_mean
    phi = core.so3_log(R[0] @ R0.T)
    r = np.concatenate([phi, q[0] - q0])[None, :]
    J = np.zeros((1, S, at.D))
    J[0, :3, :3] = core.so3_jl_inv(phi)
    J[0, 3:S, 3:S] = np.eye(S - 3)
    at.lin.unary["prior"] = _whiten_rows(r, J, at.prob.sigmas.prior)


def _effect_rows(at: _Point) -> None:
    """Effects' own factors: prior on the first step, per-step level, their own factors, random
    walk between steps."""
    prob, n, D, k0, base, lin = at.prob, at.n, at.D, at.k0, at.base, at.lin
    for ie, (eff, cols, ev) in enumerate(zip(prob.effects, at.e_cols, at.e_parts)):
        if k0 == 0:
            mean, sigma = eff.prior(prob)
            J = np.zeros((1, eff.dim, D))
            J[0, :, cols] = np.eye(eff.dim)
            lin.unary[f"effect_prior/{eff.name}"] = _whiten_rows((ev[0] - mean)[None, :], J, np.asarray(sigma))
        declared = prob.effect_traits[ie]
        level = declared.step_prior_sigma
        if level is not None:
            def level_rows(eff=eff, cols=cols, level=level):
                mean, _ = eff.prior(prob)
                sl_ = np.asarray(level(prob), dtype=float)
                J = np.zeros((n, eff.dim, D))
                J[:, :, cols] = np.eye(eff.dim)
                return mean, sl_, _whiten_rows(np.zeros((n, eff.dim)), J, sl_)[1]

            mean, sl_, Jl = _constant_rows(prob, (ie, "level"), (k0 - base, n, D), level_rows)
            lin.unary[f"effect_level/{eff.name}"] = ((ev - mean) * (1.0 / sl_), Jl)
        own = declared.factors
        if own is not None:
            for key, (r, dr_ds, dr_de, weight) in own(prob, at.steps, at.R, at.q, ev).items():
                w = np.asarray(weight, dtype=float)[:, None]
                J = np.zeros((n, r.shape[1], D))
                J[:, :, :S] = dr_ds
                J[:, :, cols] = dr_de
                lin.unary[f"effect_factor/{eff.name}/{key}"] = (r * w, J * w[:, :, None])
        if n > 1:
            def walk_rows(eff=eff, cols=cols):
                rw = walk_sigma(eff, prob)[k0 - base:k0 - base + n - 1]
                J0 = np.zeros((n - 1, eff.dim, D))
                J1 = np.zeros((n - 1, eff.dim, D))
                J0[:, :, cols] = -np.eye(eff.dim)
                J1[:, :, cols] = np.eye(eff.dim)
                return rw, J0 / rw[:, :, None], J1 / rw[:, :, None]

            rw, J0, J1 = _constant_rows(prob, (ie, "walk"), (k0 - base, n, D), walk_rows)
            lin.binary[f"effect_walk/{eff.name}"] = ((ev[1:] - ev[:-1]) / rw, J0, J1)


def _integration_rows(at: _Point) -> None:
    """Integration between successive steps, whitened by the Brownian-bridge covariance."""
    n, D = at.n, at.D
    r = np.empty((n - 1, 12))
    J0s = np.empty((n - 1, 12, S))
    J1s = np.empty((n - 1, 12, S))
    core.integration_all(at.R, at.q, at.prob.dt, r, J0s, J1s)
    Linv = at.prob.integration_whitener
    J0 = np.zeros((n - 1, 12, D))
    J1 = np.zeros((n - 1, 12, D))
    np.matmul(Linv, J0s, out=J0[:, :, :S])  # into the columns, without a temporary
    np.matmul(Linv, J1s, out=J1[:, :, :S])
    at.lin.binary["integration"] = (r @ Linv.T, J0, J1)


def linearize(prob, traj: Trajectory, k0: int = 0, robust: bool = True,
              families: frozenset[str] | None = None) -> Linearization:
    """Evaluate every factor of ``prob`` at ``traj`` (residuals whitened, Jacobians in world increments).

    ``traj`` covers steps ``k0 .. k0 + len(traj) - 1`` of the recording (the whole recording by
    default; the fixed-lag smoother passes its newest steps).  The first-step priors are included
    only when ``k0 == 0``.  With a robust Newton-Euler loss (``Sigmas.robust_k``) its rows are
    reweighted (IRLS: ``sqrt(w)`` times residual and Jacobian) and ``cost`` is the robust cost;
    ``robust=False`` gives the plain whitened residuals (the diagnostics).  The IMU (and fused
    F/T) rows of a missing or saturated axis are zero; with a robust sensor loss
    (``Sigmas.imu_robust``) each sensor's 3-D block is reweighted the same way.  ``families``
    (names of :data:`FAMILY_GROUPS`): evaluate only those groups, each exactly as in the full
    linearisation (``cost`` is then NaN: the cost of a part is no cost of the model).
    """
    if families is not None and not set(families) <= set(FAMILY_GROUPS):
        raise ValueError(f"linearize: unknown family groups {sorted(set(families) - set(FAMILY_GROUPS))}; "
                         f"expected some of {FAMILY_GROUPS}")

    def want(group: str) -> bool:
        return families is None or group in families

    at = _point(prob, traj, k0)
    if want("newton_euler"):
        _newton_euler_rows(at, robust)
    if want("contact"):
        _contact_rows(at)
    if want("imu"):
        _imu_rows(at, robust)
    if prob.use_ft and want("ft"):
        _ft_rows(at, robust)
    if k0 == 0 and want("prior"):
        _prior_rows(at)
    if want("effects"):
        _effect_rows(at)
    if at.n > 1 and want("integration"):
        _integration_rows(at)
    lin = at.lin
    total = 0.0
    for r, _ in lin.unary.values():
        total += float(np.sum(r * r))
    for r, _, _ in lin.binary.values():
        total += float(np.sum(r * r))
    lin.cost = 0.5 * total + at.extra_cost if families is None else math.nan
    return lin


@core.njit
def _support(J):
    """The columns of ``J`` (m, rows, D) that are nonzero at some step (int64 array)."""
    m, rows, D = J.shape
    mark = np.zeros(D, dtype=np.bool_)
    for k in range(m):  # in memory order
        for i in range(rows):
            for c in range(D):
                if J[k, i, c] != 0.0:
                    mark[c] = True
    return np.nonzero(mark)[0]


@core.njit
def _gather(buf, Jk, cols):
    """``buf[:, :rows] = Jk[:, cols]^T`` (columns as contiguous rows)."""
    for ia in range(cols.shape[0]):
        c = cols[ia]
        for i in range(Jk.shape[0]):
            buf[ia, i] = Jk[i, c]


@core.njit
def _gram_into(H, k, A, Bt, ca, cb, sym):
    """``H[k][ca, cb] += A Bt^T`` for the gathered ``A`` (len(ca), rows), ``Bt`` (len(cb), rows)
    (the upper triangle mirrored when ``sym``)."""
    rows = A.shape[1]
    for ia in range(ca.shape[0]):
        a = ca[ia]
        for ib in range(ia if sym else 0, cb.shape[0]):
            b = cb[ib]
            acc = 0.0
            for i in range(rows):
                acc += A[ia, i] * Bt[ib, i]
            H[k, a, b] += acc
            if sym and ib != ia:
                H[k, b, a] += acc


@core.njit
def _grad_into(g, k, A, r, cols):
    """``g[k][cols] -= A r`` for the gathered ``A`` (len(cols), rows)."""
    rows = A.shape[1]
    for ia in range(cols.shape[0]):
        acc = 0.0
        for i in range(rows):
            acc += A[ia, i] * r[i]
        g[k, cols[ia]] -= acc


@core.njit
def _add_unary(Hd, g, r, J, first, shift):
    """Step ``k`` (``first`` <= k < len(r)) of a unary family into ``Hd[k + shift]``, ``g[k + shift]``."""
    if r.shape[0] <= first:
        return
    cols = _support(J[first:])
    A = np.empty((cols.shape[0], J.shape[1]))
    for k in range(first, r.shape[0]):
        _gather(A, J[k], cols)
        _gram_into(Hd, k + shift, A, A, cols, cols, True)
        _grad_into(g, k + shift, A, r[k], cols)


@core.njit
def _add_binary(H0, H1, B, g0, g1, r, J0, J1):
    """A binary family: ``J0^T J0`` into ``H0[k]``, ``J1^T J1`` into ``H1[k + 1]``, ``J0^T J1``
    into ``B[k]``; the gradients into ``g0[k]`` and ``g1[k + 1]``."""
    c0 = _support(J0)
    c1 = _support(J1)
    A0 = np.empty((c0.shape[0], J0.shape[1]))
    A1 = np.empty((c1.shape[0], J1.shape[1]))
    for k in range(r.shape[0]):
        _gather(A0, J0[k], c0)
        _gather(A1, J1[k], c1)
        _gram_into(H0, k, A0, A0, c0, c0, True)
        _gram_into(H1, k + 1, A1, A1, c1, c1, True)
        _gram_into(B, k, A0, A1, c0, c1, False)
        _grad_into(g0, k, A0, r[k], c0)
        _grad_into(g1, k + 1, A1, r[k], c1)


def _f64(a):
    return a if a.dtype == np.float64 else a.astype(np.float64)


@core.njit
def _assemble_steps(Hd, B, g, ur, uJ, uc, br, bJ0, bJ1, bc0, bc1):
    """Every family's products into ``Hd``, ``B``, ``g``, step by step (each step's blocks formed
    while they are in cache; family by family, each family's pass read and wrote all of ``Hd``
    again: 27 MB nine times on the 20 s iCub sway, 90 ms an assembly against 82).  ``ur``,
    ``uJ``, ``uc``: the unary families' residuals, Jacobians and supports (a family of fewer
    steps, a first-step prior, stops there); ``br``, ``bJ0``, ``bJ1``, ``bc0``, ``bc1``: the
    binary families' (step ``k`` and ``k + 1``)."""
    n = Hd.shape[0]
    D = Hd.shape[1]
    A0 = np.empty((D, 64))
    A1 = np.empty((D, 64))
    for k in range(n):
        for f in range(len(uJ)):
            J = uJ[f]
            if k >= J.shape[0]:
                continue
            cols = uc[f]
            if J.shape[1] > A0.shape[1]:
                A0 = np.empty((D, J.shape[1]))
            Ak = A0[:cols.shape[0], :J.shape[1]]
            _gather(Ak, J[k], cols)
            _gram_into(Hd, k, Ak, Ak, cols, cols, True)
            _grad_into(g, k, Ak, ur[f][k], cols)
        for f in range(len(bJ0)):
            J0 = bJ0[f]
            if k >= J0.shape[0]:
                continue
            J1 = bJ1[f]
            c0 = bc0[f]
            c1 = bc1[f]
            rows = J0.shape[1]
            if rows > A0.shape[1]:
                A0 = np.empty((D, rows))
                A1 = np.empty((D, rows))
            P0 = A0[:c0.shape[0], :rows]
            P1 = A1[:c1.shape[0], :rows]
            _gather(P0, J0[k], c0)
            _gather(P1, J1[k], c1)
            _gram_into(Hd, k, P0, P0, c0, c0, True)
            _gram_into(Hd, k + 1, P1, P1, c1, c1, True)
            _gram_into(B, k, P0, P1, c0, c1, False)
            _grad_into(g, k, P0, br[f][k], c0)
            _grad_into(g, k + 1, P1, br[f][k], c1)


def assemble(lin: Linearization, n: int, D: int):
    """Gauss-Newton blocks: diagonal ``Hd`` (N, D, D), upper ``B`` (N-1, D, D) and ``g = -J^T r`` (N, D).

    Compiled: each family's products are formed on the columns its Jacobian touches, step by
    step (:func:`_assemble_steps`)."""
    Hd = np.zeros((n, D, D))
    B = np.zeros((max(n - 1, 0), D, D))
    g = np.zeros((n, D))
    unary = [(np.ascontiguousarray(_f64(r)), np.ascontiguousarray(_f64(J))) for r, J in lin.unary.values()]
    binary = [(np.ascontiguousarray(_f64(r)), np.ascontiguousarray(_f64(J0)), np.ascontiguousarray(_f64(J1)))
              for r, J0, J1 in lin.binary.values()]
    if not unary:
        unary = [(np.zeros((0, 1)), np.zeros((0, 1, D)))]
    if not binary:
        binary = [(np.zeros((0, 1)), np.zeros((0, 1, D)), np.zeros((0, 1, D)))]
    _assemble_steps(Hd, B, g, tuple(r for r, _ in unary), tuple(J for _, J in unary),
                    tuple(_support(J) for _, J in unary), tuple(b[0] for b in binary),
                    tuple(b[1] for b in binary), tuple(b[2] for b in binary),
                    tuple(_support(b[1]) for b in binary), tuple(_support(b[2]) for b in binary))
    return Hd, B, g


def assemble_split(lin: Linearization, n: int, D: int, skip_first_unary: bool = False):
    """Gauss-Newton blocks split for incremental elimination (the fixed-lag window).

    Returns ``U`` (n, D, D) and ``gU`` (n, D): step i's own factors plus the link from step i-1;
    ``Fw``, ``gF``: the link to step i+1 on step i; ``B`` (n-1, D, D) the cross blocks.  With
    ``skip_first_unary`` the first step's own factors are left out (already eliminated).
    """
    U = np.zeros((n, D, D))
    Fw = np.zeros((n, D, D))
    B = np.zeros((max(n - 1, 0), D, D))
    gU = np.zeros((n, D))
    gF = np.zeros((n, D))
    first = 1 if skip_first_unary else 0
    for r, J in lin.unary.values():
        _add_unary(U, gU, _f64(r), _f64(J), first, 0)
    for r, J0, J1 in lin.binary.values():
        _add_binary(Fw, U, B, gF, gU, _f64(r), _f64(J0), _f64(J1))
    return U, gU, Fw, gF, B


def covariances(Hd, B):
    """Marginal covariances ``P`` (N, D, D) and lag-one cross-covariances ``Pc`` (N-1, D, D),
    ``Pc[k] = cov(x_k, x_k+1)``, of the Gauss-Newton system (Jacobi-scaled as :func:`solve`)."""
    diag = np.diagonal(Hd, axis1=1, axis2=2)
    scale = 1.0 / np.sqrt(np.maximum(diag, 1e-300))
    Hs = np.ascontiguousarray(Hd * scale[:, :, None] * scale[:, None, :])
    Bs = np.ascontiguousarray(B * scale[:-1, :, None] * scale[1:, None, :])
    try:
        P, Pc = solvers.block_tridiag_covariances(Hs, Bs)
    except np.linalg.LinAlgError as err:
        raise EstimatorError(_NOT_PD) from err
    P = P * scale[:, :, None] * scale[:, None, :]
    Pc = Pc * scale[:-1, :, None] * scale[1:, None, :]
    return P, Pc


def _matvec(Hd, B, x):
    y = (Hd @ x[:, :, None])[:, :, 0]
    y[:-1] += (B @ x[1:, :, None])[:, :, 0]
    y[1:] += (B.transpose(0, 2, 1) @ x[:-1, :, None])[:, :, 0]
    return y


@core.njit
def _scaled_blocks(Hd, B, g, idx, damping):
    """The columns ``idx`` of the block-tridiagonal system, Jacobi-scaled by its diagonal and
    damped (the diagonal times ``1 + damping``), in one pass with no temporaries: ``(Hs, Bs, gs,
    s)`` with ``Hs[k] = S_k Hd[k][idx, idx] S_k (1 + damping on the diagonal)``, ``Bs[k] = S_k
    B[k][idx, idx] S_k+1``, ``gs = s g[:, idx]`` and ``S_k = diag(s_k)``, ``s = 1 / sqrt(diag)``
    (what :func:`solve` formed with fancy indexing and five array temporaries: 100 of its 170 ms
    on the 20 s iCub sway)."""
    n, d = Hd.shape[0], idx.shape[0]
    s = np.empty((n, d))
    for k in range(n):
        for a in range(d):
            s[k, a] = 1.0 / math.sqrt(max(Hd[k, idx[a], idx[a]], 1e-300))
    Hs = np.empty((n, d, d))
    gs = np.empty((n, d))
    for k in range(n):
        for a in range(d):
            ia = idx[a]
            sa = s[k, a]
            for b in range(d):
                Hs[k, a, b] = Hd[k, ia, idx[b]] * sa * s[k, b]
            Hs[k, a, a] *= 1.0 + damping
            gs[k, a] = g[k, ia] * sa
    Bs = np.empty((B.shape[0], d, d))
    for k in range(B.shape[0]):
        for a in range(d):
            ia = idx[a]
            sa = s[k, a]
            for b in range(d):
                Bs[k, a, b] = B[k, ia, idx[b]] * sa * s[k + 1, b]
    return Hs, Bs, gs, s


@core.njit
def _block_matvec(Hs, Bs, x):
    """``H x`` for the block-tridiagonal ``H`` (diagonal blocks ``Hs``, upper ``Bs``) and ``x`` (N, d)."""
    n, d = x.shape[0], x.shape[1]
    y = np.zeros((n, d))
    for k in range(n):
        for a in range(d):
            acc = 0.0
            for b in range(d):
                acc += Hs[k, a, b] * x[k, b]
            if k < n - 1:
                for b in range(d):
                    acc += Bs[k, a, b] * x[k + 1, b]
            y[k, a] += acc
        if k < n - 1:
            for b in range(d):  # B_k^T x_k into y_k+1, by rows of B_k
                xb = x[k, b]
                for a in range(d):
                    y[k + 1, a] += Bs[k, b, a] * xb
    return y


def solve(Hd, B, g, damping: float = 0.0, want_cov: bool = False):
    """Solve the (Levenberg-Marquardt damped) block-tridiagonal system with Jacobi scaling.

    Returns ``dx`` (N, D) and, with ``want_cov``, the marginal covariances (N, D, D) of ``H^-1``.
    """
    return _solve_columns(Hd, B, g, np.arange(Hd.shape[1]), damping, want_cov)


def _solve_columns(Hd, B, g, idx, damping: float = 0.0, want_cov: bool = False):
    """:func:`solve` on the columns ``idx`` of the system (the others held): ``dx`` (N, len(idx))."""
    Hs, Bs, gs, scale = _scaled_blocks(Hd, B, g, np.asarray(idx, dtype=np.int64), float(max(damping, 0.0)))
    try:
        Ld, C = solvers.block_tridiag_factor(Hs, Bs)
    except np.linalg.LinAlgError as err:
        raise EstimatorError(_NOT_PD) from err
    x = _substitute(Ld, C, gs)
    # One step of iterative refinement (the same factor): the tight integration factors leave the
    # scaled system with a condition number near 1e10 (measured), costing ~5 digits.
    x2 = _substitute(Ld, C, gs - _block_matvec(Hs, Bs, x))
    dx = (x + x2) * scale
    if want_cov:
        P, _ = solvers.block_tridiag_marginals(Ld, C)
        P = P * scale[:, :, None] * scale[:, None, :]
        return dx, P
    return dx, None


def _substitute(Ld, C, g):
    """``H^-1 g`` (N, d) from ``H``'s block Cholesky factor."""
    return solvers.block_tridiag_substitute_vec(Ld, C, np.ascontiguousarray(g))


# ----------------------------------------------------------------------------------------------
# Constant effects as one global block: the arrow system (batch)
# ----------------------------------------------------------------------------------------------


def is_global(eff, prob=None) -> bool:
    """An effect whose unknowns are one global block in batch: no per-step prior, and either
    ``constant = True`` or (no ``constant`` attribute, ``prob`` given) a random walk too tight to
    matter over the recording (``rw sqrt(N - 1) < 1e-3`` of the prior sigma, as
    :func:`flexforce.smoother.batch.effective_dof` decides), so that a user's effect written
    without the attribute is treated like the built-in constants."""
    declared = traits(eff)
    if declared.step_prior_sigma is not None:
        return False
    constant = declared.constant
    if constant is not None:
        return constant is True
    if prob is None:
        return False
    _, s0 = eff.prior(prob)
    d = int(eff.dim)
    s0 = np.broadcast_to(np.asarray(s0, dtype=float), (d,))
    rw = walk_sigma(eff, prob)
    return bool(np.all(rw * np.sqrt(max(prob.n - 1, 1)) < 1e-3 * s0))


def global_columns(prob) -> np.ndarray:
    """Indices, in the per-step state of width ``D``, of the global (constant) effects' unknowns."""
    idx: list[int] = []
    off = S + 6 * prob.nc
    for eff in prob.effects:
        if is_global(eff, prob):
            idx.extend(range(off, off + int(eff.dim)))
        off += int(eff.dim)
    return np.asarray(idx, dtype=int)


def drop_global_walks(prob, lin: Linearization) -> Linearization:
    """``lin`` without the random-walk factors of the global effects (exactly zero residual, and a
    Jacobian that vanishes on the constrained subspace ``e_k = e``; left in, its ``1e12``-scale
    information would cancel in the reduction at the cost of digits)."""
    drop = {f"effect_walk/{eff.name}" for eff in prob.effects if is_global(eff, prob)}
    if not drop:
        return lin
    return Linearization(unary=lin.unary, binary={k: v for k, v in lin.binary.items() if k not in drop},
                         cost=lin.cost, weights=lin.weights, ne_weights=lin.ne_weights)


@core.njit
def _arrow_scaled(Hd, B, g, aidx, cidx, damping):
    """The Gauss-Newton system of the per-step layout restricted to ``x_k = (a_k, c)`` (the columns
    ``cidx`` of every step one global block ``c``), Jacobi-scaled and damped as :func:`solve_arrow`
    needs it, with no temporaries: with ``x_k = T (a_k, c)``, the border ``F_k = H_kk[a, c] +
    H_k,k+1[a, c] + H_k-1,k[c, a]^T``, the global block ``G = sum_k H_kk[c, c] + H_k,k+1[c, c] +
    H_k,k+1[c, c]^T`` and ``gc = sum_k g_k[c]``; the per-step blocks by :func:`_scaled_blocks`.
    Returns ``(As, ABs, R, Gs, gcs, sa, sc)``, the scaled per-step blocks, the
    right-hand sides ``R`` (N, Da, 1 + Dc) of the per-step elimination (the scaled ``ga`` then the
    scaled border ``F``), the scaled global block and its right-hand side, and the two scales."""
    n, da, dc = Hd.shape[0], aidx.shape[0], cidx.shape[0]
    nb = B.shape[0]
    G = np.zeros((dc, dc))
    gc = np.zeros(dc)
    for k in range(n):
        for i in range(dc):
            gc[i] += g[k, cidx[i]]
            for j in range(dc):
                G[i, j] += Hd[k, cidx[i], cidx[j]]
                if k < nb:
                    G[i, j] += B[k, cidx[i], cidx[j]] + B[k, cidx[j], cidx[i]]
    sc = np.empty(dc)
    for i in range(dc):
        sc[i] = 1.0 / math.sqrt(max(G[i, i], 1e-300))
    Gs = np.empty((dc, dc))
    for i in range(dc):
        for j in range(dc):
            Gs[i, j] = G[i, j] * sc[i] * sc[j]
        Gs[i, i] *= 1.0 + damping
    gcs = gc * sc
    As, ABs, gas, sa = _scaled_blocks(Hd, B, g, aidx, damping)
    R = np.empty((n, da, 1 + dc))
    for k in range(n):
        for a in range(da):
            ia = aidx[a]
            R[k, a, 0] = gas[k, a]
            for j in range(dc):
                f = Hd[k, ia, cidx[j]]
                if k < nb:
                    f += B[k, ia, cidx[j]]
                if k > 0:
                    f += B[k - 1, cidx[j], ia]
                R[k, a, 1 + j] = f * sa[k, a] * sc[j]
    return As, ABs, R, Gs, gcs, sa, sc


class _ArrowElimination:
    """The per-step part of the arrow system eliminated (:func:`solve_arrow`): Jacobi-scaled and
    damped blocks, their block Cholesky factor and ``A^-1 [g_a, F]``; :meth:`step` then solves the
    global block's Schur system, for the global block as assembled or with a curvature added to
    it (the secant's, :func:`solve_arrow_pair`: both steps from one elimination)."""

    def __init__(self, Hd, B, g, cidx, damping: float):
        n, D = Hd.shape[0], Hd.shape[1]
        self.n, self.D = n, D
        self.cidx = cidx
        self.aidx = np.setdiff1d(np.arange(D), cidx).astype(np.int64)
        self.As, self.ABs, self.R, self.Gs, self.gcs, self.sa, self.sc = _arrow_scaled(
            Hd, B, g, self.aidx, cidx.astype(np.int64), float(max(damping, 0.0)))
        self.gas, self.Fs = self.R[:, :, 0], self.R[:, :, 1:]
        try:
            self.La, self.Ca = solvers.block_tridiag_factor(self.As, self.ABs)
        except np.linalg.LinAlgError as exc:
            raise EstimatorError(_NOT_PD) from exc
        X = solvers.block_tridiag_substitute(self.La, self.Ca, self.R)
        self.u0, self.V = X[:, :, 0], X[:, :, 1:]
        self.FV = np.einsum("nai,naj->ij", self.Fs, self.V)

    def step(self, extra=None):
        """``(dx, Lsc)``: the step (N, D) with ``extra`` (Dc, Dc, unscaled) added to the global
        block, and the Cholesky factor of the scaled Schur complement.  Raises EstimatorError when
        that is not positive definite."""
        Gs = self.Gs if extra is None else self.Gs + extra * self.sc[:, None] * self.sc[None, :]
        Ssc = Gs - self.FV
        Ssc = 0.5 * (Ssc + Ssc.T)
        try:
            Lsc = np.linalg.cholesky(Ssc)
        except np.linalg.LinAlgError as exc:
            raise EstimatorError(_NOT_PD) from exc
        Fs, V = self.Fs, self.V

        def schur(u, rc):
            """(da, dc) from ``u = A^-1 r_a`` and the global right-hand side ``r_c``."""
            rhs = rc - np.einsum("nai,na->i", Fs, u)
            dc = np.linalg.solve(Lsc.T, np.linalg.solve(Lsc, rhs))
            return u - V @ dc, dc

        xa, xc = schur(self.u0, self.gcs)
        # One step of iterative refinement on the whole arrow system (as :func:`solve`).
        ra = self.gas - _block_matvec(self.As, self.ABs, np.ascontiguousarray(xa)) - Fs @ xc
        rc = self.gcs - np.einsum("nai,na->i", Fs, xa) - Gs @ xc
        xa2, xc2 = schur(_substitute(self.La, self.Ca, ra), rc)
        xa, xc = (xa + xa2) * self.sa, (xc + xc2) * self.sc
        dx = np.empty((self.n, self.D))
        dx[:, self.aidx] = xa
        dx[:, self.cidx] = xc
        return dx, Lsc


def solve_arrow_pair(Hd, B, g, cidx, extra):
    """The undamped steps of :func:`solve_arrow` with and without ``extra`` (Dc, Dc) added to the
    global block, from one elimination of the per-step part (which ``extra`` does not touch):
    ``(dx_extra, dx)``, ``dx_extra`` None when that system is not positive definite."""
    el = _ArrowElimination(Hd, B, g, np.asarray(cidx, dtype=int), 0.0)
    try:
        with np.errstate(all="ignore"):  # an indefinite estimate is caught by the caller
            first = el.step(extra)[0]
    except EstimatorError:
        first = None
    return first, el.step()[0]


def solve_arrow(Hd, B, g, cidx, damping: float = 0.0, want_cov: bool = False, freeze: bool = False):
    """Solve the Gauss-Newton system with the columns ``cidx`` one global block (:func:`_arrow_scaled`).

    Block tridiagonal plus a dense border (an "arrow"): the per-step part is eliminated by the
    block-tridiagonal solver with ``1 + Dc`` right-hand sides (the state's and the border's
    columns), leaving the Schur complement ``S = G - F^T A^-1 F`` on the global block.  Jacobi
    scaling, Levenberg-Marquardt damping of the scaled diagonal and one step of iterative
    refinement as :func:`solve`.

    Returns ``dx`` (N, D) (the global step repeated in every step's ``cidx`` columns) and, with
    ``want_cov``, the marginal covariances ``P`` (N, D, D) and lag-one cross-covariances ``Pc``
    (N-1, D, D) in the per-step layout: ``P_k[a, a] = (A^-1)_kk + V_k S^-1 V_k^T`` (``V = A^-1 F``,
    the border's correction), ``P_k[a, c] = -V_k S^-1``, ``P_k[c, c] = S^-1``.
    """
    cidx = np.asarray(cidx, dtype=int)
    if cidx.size == 0:
        if not want_cov:
            return solve(Hd, B, g, damping)[0], None, None
        dx, _ = solve(Hd, B, g, damping)
        P, Pc = covariances(Hd, B)
        return dx, P, Pc
    n, D = Hd.shape[0], Hd.shape[1]
    if freeze:  # the global block held at its value: the per-step part alone
        aidx = np.setdiff1d(np.arange(D), cidx)
        dx = np.zeros((n, D))
        dx[:, aidx] = _solve_columns(Hd, B, g, aidx, damping)[0]
        return dx, None, None
    el = _ArrowElimination(Hd, B, g, cidx, damping)
    dx, Lsc = el.step()
    V = el.V
    if not want_cov:
        return dx, None, None
    if damping > 0.0:
        raise ValueError("solve_arrow: covariances of a damped system are not defined")
    aidx, La, Ca, sa, sc = el.aidx, el.La, el.Ca, el.sa, el.sc
    Pa, Pca = solvers.block_tridiag_marginals(La, Ca)
    Minv = np.linalg.solve(Lsc, np.eye(len(cidx)))
    Sinv = Minv.T @ Minv
    VS = V @ Sinv
    P = np.empty((n, D, D))
    P[:, aidx[:, None], aidx[None, :]] = Pa + VS @ V.transpose(0, 2, 1)
    P[:, aidx[:, None], cidx[None, :]] = -VS
    P[:, cidx[:, None], aidx[None, :]] = -VS.transpose(0, 2, 1)
    P[:, cidx[:, None], cidx[None, :]] = Sinv
    Pc = np.empty((max(n - 1, 0), D, D))
    if n > 1:
        Pc[:, aidx[:, None], aidx[None, :]] = Pca + VS[:-1] @ V[1:].transpose(0, 2, 1)
        Pc[:, aidx[:, None], cidx[None, :]] = -VS[:-1]
        Pc[:, cidx[:, None], aidx[None, :]] = -VS[1:].transpose(0, 2, 1)
        Pc[:, cidx[:, None], cidx[None, :]] = Sinv
    scale = np.empty((n, D))
    scale[:, aidx] = sa
    scale[:, cidx] = sc
    P = P * scale[:, :, None] * scale[:, None, :]
    Pc = Pc * scale[:-1, :, None] * scale[1:, None, :]
    return dx, P, Pc
