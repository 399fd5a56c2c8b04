r"""The marginal likelihood of the data given the constant effect parameters (Laplace).

The smoother's objective is the negative log of the joint density of the measurements ``y``
(IMU, F/T) and the states ``x`` (flexibility, its velocity and acceleration, contact wrenches,
per-step effect values) given the constant parameters ``theta`` of the effects::

    J(x, theta) = 1/2 |r_meas(x, theta)|^2 + 1/2 |r_model(x, theta)|^2

where the *model* factors (Newton-Euler, contact law, integration, first-step prior, the per-step
effects' priors and random walks) are the prior over trajectories.  Minimising ``J`` jointly over
``x`` and ``theta`` (the joint MAP) is biased for every parameter that enters the model factors'
Jacobian -- the damping and stiffness scales, the CoM offset: the trajectory prior's normaliser
``Z(theta) = int exp(-1/2 |r_model|^2) dx`` depends on ``theta`` and the joint MAP ignores it
(measured on a 3 s sway with no hidden effect: the damping scale goes to 0.07 for a truth of 1,
the vertical CoM offset to -0.17 m, and both look significant).

The Laplace approximation of the states' integral gives the marginal likelihood::

    -ln p(y | theta) ~ J(x*, theta) + 1/2 ln det H_post(x*, theta) - 1/2 ln det H_model(x*, theta) + const

with ``x*`` the states' optimum for ``theta``, ``H_post`` the Gauss-Newton Hessian of ``J`` in the
per-step states (the constant parameters held) and ``H_model`` that of the model factors alone
(``ln Z = -1/2 ln det H_model`` + const: the model factors have as many rows as the states have
unknowns, so their minimum is zero).  Both are block tridiagonal; their log-determinants come
from the factors' rows by a step-by-step QR (a square-root information filter, :func:`_qr_factor`),
not from a Cholesky factorisation of ``H``: the trajectory prior's per-step blocks span 1e15 in
eigenvalue, and squaring that left its log-determinant's derivative in a parameter to noise.

With robust losses (the Huber loss of the Newton-Euler rows, a robust IMU loss) ``J`` is the
robust objective and ``H_post`` its Gauss-Newton Hessian with the IRLS weights; ``H_model`` stays
that of the *plain* model rows: the prior over trajectories is the density of the model
residuals carried to the states by a change of variables, whose Jacobian determinant does not
see the residuals' density (:func:`plain_model_rows`).  The losses' normalisers do not depend on
``theta``.

:func:`flexforce.smoother.batch.optimize` estimates ``theta`` by minimising this (type-II maximum
likelihood, with ``theta``'s own prior), the states by MAP given it; the diagnostics score an
effect by the gain in it (:mod:`flexforce.compare.diagnostics.run`).
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from flexforce.errors import EstimatorError
from flexforce.factors.core import njit
from flexforce.factors.effects.base import traits
from flexforce.smoother import solvers
from flexforce.smoother.linearize import (
    Linearization,
    _scaled_blocks,
    assemble,
    drop_global_walks,
    is_global,
    linearize,
)
from flexforce.smoother.solvers import _trsm_lower, _trsm_upper_t

MEASUREMENT_FAMILIES = ("imu", "ft")
"""Factor families that are measurements; every other family is part of the trajectory prior."""


def _family(key: str) -> str:
    return key.split("/")[0]


def theta_prior_keys(prob) -> set[str]:
    """Keys of the global effects' own priors (on ``theta``, not on the states)."""
    return {f"effect_prior/{eff.name}" for eff in prob.effects if is_global(eff, prob)}


def _geqrf_external():
    """numba's own LAPACK ``geqrf`` binding (the one ``np.linalg.qr`` calls), or None if this numba
    does not have it (then :func:`_r_factor` falls back to ``np.linalg.qr``)."""
    try:
        from numba import types
        from numba.np.linalg import _LAPACK

        return _LAPACK().numba_ez_geqrf(types.float64)
    except Exception:  # pragma: no cover - a numba without the binding
        return None


_GEQRF = _geqrf_external()
_HAVE_GEQRF = _GEQRF is not None


@njit
def _r_factor(M):
    """The ``R`` of a QR factorisation of ``M`` (m, n), by LAPACK's ``geqrf`` alone: ``np.linalg.qr``
    also forms ``Q``, which :func:`_qr_factor` does not use, for as much again (measured: 2025
    factorisations of 110 x 72 in 215 ms against 418).  Non-finite entries give a NaN ``R``."""
    m, n = M.shape
    if not _HAVE_GEQRF:
        return np.linalg.qr(M)[1]
    k = min(m, n)
    for i in range(m):
        for j in range(n):
            if not np.isfinite(M[i, j]):
                return np.full((k, n), np.nan)
    A = np.asfortranarray(M)
    tau = np.empty(k)
    if _GEQRF(ord("d"), m, n, A.ctypes, m, tau.ctypes) < 0:
        return np.full((k, n), np.nan)
    R = np.zeros((k, n))
    for i in range(k):
        for j in range(i, n):
            R[i, j] = A[i, j]
    return R


@njit
def _qr_factor(Ju, J0, J1, Jf, Rd, Ru):
    """Square-root information filter of the stacked rows of a chain: ``Ju`` (N, ru, d) each
    step's own rows, ``J0``/``J1`` (N-1, rb, d) the rows linking steps ``k`` and ``k+1``, ``Jf``
    (rf, d) rows on the first step only (its priors).  Step by step, the rows on ``x_k`` (carried
    from the previous step, own, first-step, link) are reduced by QR into ``R_kk`` (written to
    ``Rd`` (N, d, d)) and ``R_k,k+1`` (``Ru`` (N-1, d, d)): ``J^T J = R^T R`` with ``R`` block
    upper bidiagonal.  Returns ``ln det (J^T J)`` (-inf when a pivot vanishes).  Unlike a Cholesky
    factorisation of ``J^T J`` this does not square the rows' condition number (the trajectory
    prior's blocks span 1e15 in eigenvalue)."""
    n, ru, d = Ju.shape
    rb = J0.shape[1]
    carry = np.zeros((d, d))
    total = 0.0
    rf = Jf.shape[0]
    for k in range(n):
        last = k == n - 1
        cols = d if last else 2 * d
        top = d + ru + (rf if k == 0 else 0)
        M = np.zeros((top + (0 if last else rb), cols))
        M[:d, :d] = carry
        M[d:d + ru, :d] = Ju[k]
        if k == 0:
            M[d + ru:top, :d] = Jf
        if not last:
            M[top:, :d] = J0[k]
            M[top:, d:] = J1[k]
        R = _r_factor(M)
        for i in range(d):
            v = abs(R[i, i])
            if v == 0.0 or not np.isfinite(v):
                return -np.inf
            total += np.log(v)
        Rd[k] = R[:d, :d]
        if not last:
            Ru[k] = R[:d, d:]
            carry = np.zeros((d, d))
            m = min(R.shape[0], 2 * d) - d
            if m > 0:
                carry[:m] = R[d:d + m, d:]
    return 2.0 * total


@njit
def _factor_selected_inverse(Rd, Ru):
    """Diagonal blocks ``P`` and upper blocks ``Pc`` (``Pc[k] = Sigma[k, k+1]``) of ``Sigma = (R^T
    R)^-1`` for ``R`` block upper bidiagonal (:func:`_qr_factor`), by the backward recursion of
    ``R Sigma = R^-T``: ``Sigma_k,k+1 = -R_kk^-1 R_k,k+1 Sigma_k+1,k+1`` and ``Sigma_kk =
    R_kk^-1 (R_kk^-T - R_k,k+1 Sigma_k+1,k)`` -- triangular solves with ``R``, whose condition
    number is the square root of ``J^T J``'s."""
    n, d = Rd.shape[0], Rd.shape[1]
    P = np.empty((n, d, d))
    Pc = np.empty((max(n - 1, 0), d, d))
    eye = np.eye(d)
    for k in range(n - 1, -1, -1):
        L = np.ascontiguousarray(Rd[k].T)  # R_kk^-1 B = L^-T B, R_kk^-T = L^-1
        X = _trsm_lower(L, eye)
        if k < n - 1:
            Pc[k] = -_trsm_upper_t(L, Ru[k] @ P[k + 1])
            X = X - Ru[k] @ Pc[k].T
        Pk = _trsm_upper_t(L, X)
        P[k] = 0.5 * (Pk + Pk.T)
    return P, Pc


def _stacked(lin: Linearization, keys_u, keys_b, n: int, aidx, s):
    """The rows of the families ``keys_u`` (unary) and ``keys_b`` (binary), on the columns ``aidx``
    scaled by ``s``: ``(Ju, J0, J1, Jf)`` for :func:`_qr_factor`."""
    d = len(aidx)
    first = [k for k in keys_u if lin.unary[k][1].shape[0] == 1 and n > 1]  # the first step's priors
    keys_u = [k for k in keys_u if k not in first]
    ru = sum(lin.unary[k][1].shape[1] for k in keys_u)
    Ju = np.zeros((n, ru, d))
    row = 0
    for k in keys_u:
        J = lin.unary[k][1]
        Ju[:J.shape[0], row:row + J.shape[1]] = J[:, :, aidx] * s[:J.shape[0], None, :]
        row += J.shape[1]
    Jf = np.concatenate([lin.unary[k][1][0][:, aidx] * s[0] for k in first], axis=0) if first else np.zeros((0, d))
    rb = sum(lin.binary[k][1].shape[1] for k in keys_b)
    J0 = np.zeros((max(n - 1, 0), rb, d))
    J1 = np.zeros((max(n - 1, 0), rb, d))
    row = 0
    for k in keys_b:
        _, A0, A1 = lin.binary[k]
        J0[:, row:row + A0.shape[1]] = A0[:, :, aidx] * s[:-1, None, :]
        J1[:, row:row + A1.shape[1]] = A1[:, :, aidx] * s[1:, None, :]
        row += A0.shape[1]
    return Ju, J0, J1, np.ascontiguousarray(Jf)


def plain_model_rows(lin: Linearization) -> Linearization:
    """``lin`` with the Newton-Euler rows unweighted (their Huber IRLS weights divided out): the
    trajectory prior's normaliser is the Jacobian determinant of the change of variables from the
    states to the model residuals, whatever the residuals' density (Gaussian or Huber), so its
    ``ln det H_model`` is that of the plain rows.  The posterior's ``H_post`` keeps the weights
    (the Gauss-Newton Hessian of the robust objective)."""
    if lin.ne_weights is None or "newton_euler" not in lin.unary:
        return lin
    sw = np.sqrt(lin.ne_weights)
    r, J = lin.unary["newton_euler"]
    unary = dict(lin.unary)
    unary["newton_euler"] = (r / sw[:, None], J / sw[:, None, None])
    return Linearization(unary=unary, binary=lin.binary, cost=lin.cost, weights=lin.weights)


def _scaled_states(prob, lin: Linearization, cidx: np.ndarray):
    """``(aidx, s, Hs, Bs)``: the per-step states' columns (``cidx`` held), their Jacobi scale
    from ``H``'s diagonal, and ``H``'s diagonal and upper blocks on them, scaled."""
    return _scaled_system(prob, lin, cidx)[:4]


def _scaled_system(prob, lin: Linearization, cidx: np.ndarray):
    """:func:`_scaled_states` and the unscaled system ``(Hd, B, g)`` it comes from."""
    n, D = prob.n, prob.state_dim
    aidx = np.setdiff1d(np.arange(D), cidx)
    Hd, B, g = assemble(lin, n, D)
    Hs, Bs, _, s = _scaled_blocks(Hd, B, g, aidx.astype(np.int64), 0.0)
    return aidx, s, Hs, Bs, (Hd, B, g)


def log_dets(prob, lin: Linearization, cidx: np.ndarray, keep: dict | None = None) -> tuple[float, float]:
    """``(ln det H_post, ln det H_model)`` over the per-step states (the columns ``cidx`` held):
    ``H_post``'s by its block Cholesky pivots, ``H_model``'s from the model factors' rows by QR
    (:func:`_qr_factor`); the columns Jacobi-scaled by ``H_post``'s diagonal (the scale cancels
    in the difference).  ``keep``: a dict that receives what :func:`occam_gradient` at the same
    linearisation reuses (the scaled system and the prior's QR factor)."""
    full = lin
    lin = drop_global_walks(prob, lin) if cidx.size else lin
    n = prob.n
    aidx, s, Hs, Bs, system = _scaled_system(prob, lin, cidx)
    shift = -2.0 * float(np.sum(np.log(s)))
    # the posterior (the measurements make it well conditioned) by the block Cholesky pivots of
    # H; the trajectory prior by QR of its rows
    factor = None
    try:
        factor = solvers.block_tridiag_factor(Hs, Bs)
        post = float(solvers.block_factor_logdet(factor[0]))
    except np.linalg.LinAlgError:
        post = -np.inf
    model_u = [k for k in lin.unary if _family(k) not in MEASUREMENT_FAMILIES]
    d = len(aidx)
    Rd, Ru = np.empty((n, d, d)), np.empty((max(n - 1, 0), d, d))
    plain = plain_model_rows(lin)
    prior = float(_qr_factor(*_stacked(plain, model_u, list(plain.binary), n, aidx, s), Rd, Ru))
    if keep is not None:
        keep.clear()
        if np.isfinite(prior) and np.isfinite(post):
            # the system itself too: the next Gauss-Newton step of the constants at this point
            # assembles the same one (flexforce.smoother.batch.optimize)
            keep.update(lin=full, base=lin, aidx=aidx, s=s, Hs=Hs, Bs=Bs, Rd=Rd, Ru=Ru, factor=factor,
                        system=system)
    out = []
    for val, what in ((post, "posterior"), (prior, "trajectory prior")):
        if not np.isfinite(val):
            raise EstimatorError(f"smoother: the {what} information of the states is not positive definite "
                                 "(an unobservable direction: check contacts and stiffness)")
        out.append(val + shift)
    return out[0], out[1]


def occam(prob, lin: Linearization, cidx: np.ndarray, keep: dict | None = None) -> float:
    """``1/2 (ln det H_post - ln det H_model)``: what the states' integral adds to ``J``
    (``keep``: :func:`log_dets`')."""
    post, model = log_dets(prob, lin, cidx, keep)
    return 0.5 * (post - model)


def _changed(lin_a: Linearization, lin_b: Linearization, aidx: np.ndarray) -> list[str]:
    """Keys of the families whose Jacobian on the states' columns ``aidx`` differs between two
    linearisations (the others add the same information to ``H``)."""
    out = []
    for key, (_, J) in lin_a.unary.items():
        J2 = lin_b.unary[key][1]
        if not np.array_equal(J, J2) and not np.array_equal(J[..., aidx], J2[..., aidx]):
            out.append(key)
    for key, (_, J0, J1) in lin_a.binary.items():
        _, K0, K1 = lin_b.binary[key]
        if not (np.array_equal(J0, K0) and np.array_equal(J1, K1)) and not (
                np.array_equal(J0[..., aidx], K0[..., aidx]) and np.array_equal(J1[..., aidx], K1[..., aidx])):
            out.append(key)
    return out


def _contract(P, A, dA) -> float:
    """``sum_k sum_r A[k, r] P[k] dA[k, r]^T``."""
    return float(np.sum(np.matmul(A, P) * dA))


def _trace_term(P, Pc, lin0: Linearization, lin_p: Linearization, lin_m: Linearization, keys, aidx, s,
                h: float) -> float:
    """``tr(Sigma dH)`` for ``H = J^T J`` over the families ``keys`` (the others' Jacobians held),
    ``Sigma``'s diagonal blocks ``P`` and upper blocks ``Pc`` (the Jacobi-scaled system's), and
    ``dH = J^T dJ + dJ^T J`` with ``dJ`` the central difference ``(J(+h) - J(-h)) / 2h``: twice
    ``sum_rows J_row Sigma dJ_row^T`` over the steps each row touches.  Formed from ``J^T dJ``,
    not from the difference of two ``H`` (which the trajectory prior's 1e15 spread would cancel)."""
    out = 0.0
    sc = s[:, None, :]
    for key in keys:
        if key in lin0.unary:
            J = lin0.unary[key][1]
            m = J.shape[0]
            Js = J[..., aidx] * sc[:m]
            dJ = (lin_p.unary[key][1][..., aidx] - lin_m.unary[key][1][..., aidx]) * sc[:m] / (2.0 * h)
            out += _contract(P[:m], Js, dJ)
        else:
            _, J0, J1 = lin0.binary[key]
            _, P0, P1 = lin_p.binary[key]
            _, M0, M1 = lin_m.binary[key]
            A0, A1 = J0[..., aidx] * sc[:-1], J1[..., aidx] * sc[1:]
            d0 = (P0[..., aidx] - M0[..., aidx]) * sc[:-1] / (2.0 * h)
            d1 = (P1[..., aidx] - M1[..., aidx]) * sc[1:] / (2.0 * h)
            out += (_contract(P[:-1], A0, d0) + _contract(P[1:], A1, d1) + _contract(Pc, A0, d1)
                    + _contract(np.swapaxes(Pc, 1, 2), A1, d0))
    return 2.0 * out


def _varied_groups(prob) -> list[frozenset[str] | None]:
    """Per effect column (of ``Trajectory.e``), the family groups of
    :func:`~flexforce.smoother.linearize.linearize` that its values enter: the families the
    effect names in ``acts_on``, and its own factors when it has some (``factors``: its prior and
    random walk are linear in its values, their Jacobians never move; None, every group, for an
    effect that does not name them)."""
    out: list[frozenset[str] | None] = []
    for eff, d in zip(prob.effects, prob.effect_dims):
        declared = traits(eff)
        acts = declared.acts_on
        groups = None
        if acts is not None and set(acts) <= {"newton_euler", "contact", "imu", "ft"}:
            groups = frozenset(acts) | ({"effects"} if declared.factors is not None else frozenset())
        out += [groups] * int(d)
    return out


def _jacobians_held(prob, base: Linearization, traj, eff, col: int, h: float) -> bool:
    """Whether moving column ``col`` (of ``Trajectory.e``) of the effect ``eff`` by ``h`` either way
    leaves every Jacobian of ``base`` as it is, so that its Occam gradient is 0 without the two
    linearisations that would find so.  Only for an ``additive`` effect on the sensor families
    (``acts_on`` within ``imu`` and ``ft``): its terms are its values on fixed rows (Jacobians that
    do not depend on them, no factors of its own), so only a robust loss's weights could move the
    Jacobians, and they do not when the loss is off, or when it is flat below its threshold
    (log-tail, Huber) and every sample of those families keeps weight 1 with a whitened norm
    short of the threshold by more than the step moves it.  An accelerometer or gyro bias on the
    20 s iCub sway: 222 of the diagnosis's 370 columns, 444 linearisations of 740."""
    declared = traits(eff)
    acts = declared.acts_on
    if not declared.additive or acts is None or not set(acts) <= {"imu", "ft"}:
        return False
    sig = prob.sigmas
    kind = sig.imu_robust
    if kind is None:
        return True
    if kind not in ("log-tail", "huber") or getattr(prob, "weight_cap", None) is not None:
        return False
    dims = [int(d) for d in prob.effect_dims]
    first = sum(dims[:list(prob.effects).index(eff)])
    one = np.arange(1)
    e = traj.e[:1, first:first + int(eff.dim)]
    for fam in acts:
        if fam == "ft" and not prob.use_ft:
            continue
        terms = eff.residual_terms(fam, prob, one, traj.R[:1], traj.q[:1], traj.W[:1], e)
        if terms is None:
            continue
        step = np.asarray(terms[2], dtype=float)[0][..., col - first]  # (6,) or (C, 6): its rows' change per unit
        if fam == "imu":
            pairs = [("imu", step / np.asarray(sig.imu, dtype=float))]
        else:
            pairs = [(f"ft/{i}", step[i] / np.asarray(sig.ft, dtype=float)) for i in range(prob.nc)]
        for key, move in pairs:
            w = base.weights.get(key)
            if w is None or key not in base.unary or np.any(np.asarray(w) < 1.0):
                return False
            r = base.unary[key][0]
            for a, b in ((0, 3), (3, 6)):
                reach = abs(h) * float(np.linalg.norm(move[a:b]))
                if r.shape[0] and float(np.sqrt(np.max(np.sum(r[:, a:b] ** 2, axis=1)))) + reach >= sig.imu_robust_k:
                    return False
    return True


def occam_gradient(prob, traj, cidx: np.ndarray, rel_step: float = 1e-3, lin: Linearization | None = None,
                   keep: dict | None = None, states: SharedStates | None = None) -> np.ndarray:
    """Gradient of :func:`occam` in the global parameters, the states held, by
    ``d ln det H = tr(H^-1 dH)`` for both Hessians: ``dH = J^T dJ + dJ^T J`` with ``dJ`` the
    central difference of the Jacobians (steps of ``rel_step`` of each parameter's prior sigma),
    only over the families whose Jacobian moves with the parameter (an additive bias moves none:
    its gradient is 0; only the families the parameter's effect enters, its ``acts_on``, are
    evaluated again), contracted with the block-tridiagonal part of ``H^-1``: the posterior's
    from its block Cholesky factor, the trajectory prior's from its QR factor
    (:func:`_qr_factor`, :func:`_factor_selected_inverse`; a Cholesky factor of the prior would
    square its 1e15 spread).  Each inverse is formed once for every parameter.

    Equal to the central difference of :func:`occam` to the differences' truncation error (tested).
    ``lin`` (the linearisation at ``traj``) with the ``keep`` of :func:`occam` at it: their scaled
    system and QR factor are reused (the same numbers, formed once).  Without ``keep``, the
    states' part comes from ``states`` or :func:`shared_states` (the candidates of one screening
    share it), and the inverses formed here are kept in it."""
    off = prob.state_dim - prob.effect_dim
    sig = global_prior_sigma(prob)
    grad = np.zeros(cidx.size)
    if not cidx.size:
        return grad
    n = prob.n
    reuse = keep is not None and lin is not None and keep.get("lin") is lin
    entry: SharedStates | None = states
    if reuse:
        assert keep is not None
        base, aidx, s, Hs, Bs = keep["base"], keep["aidx"], keep["s"], keep["Hs"], keep["Bs"]
    else:
        base = drop_global_walks(prob, lin if lin is not None else linearize(prob, traj))
        if entry is None:
            entry = shared_states(prob, base, cidx)
        aidx, s, Hs, Bs = entry.aidx, entry.s, entry.Hs, entry.Bs
    post_inv = None if entry is None else entry.post_inv
    model_inv = None if entry is None else entry.model_inv
    mbase = plain_model_rows(base)
    d = len(aidx)
    model_u = [k for k in base.unary if _family(k) not in MEASUREMENT_FAMILIES]
    groups = _varied_groups(prob)
    owners = [eff for eff, dim in zip(prob.effects, prob.effect_dims) for _ in range(int(dim))]
    for j, col in enumerate(cidx):
        h = rel_step * sig[j]
        if _jacobians_held(prob, base, traj, owners[col - off], col - off, h):
            continue  # its gradient is 0 (what the differences below would find, without them)
        lins = []
        for sgn in (1.0, -1.0):
            e = traj.e.copy()
            e[:, col - off] += sgn * h
            lins.append(drop_global_walks(prob, linearize(prob, type(traj)(traj.R, traj.q, traj.W, e),
                                                          families=groups[col - off])))
        keys = _changed(lins[0], lins[1], aidx)
        if not keys:
            continue
        if post_inv is None:
            try:
                post_inv = (solvers.block_tridiag_marginals(*keep["factor"]) if reuse and keep is not None
                            and keep.get("factor") is not None else solvers.block_tridiag_covariances(Hs, Bs))
            except np.linalg.LinAlgError as err:
                raise EstimatorError("smoother: the posterior information of the states is not positive definite "
                                     "(an unobservable direction: check contacts and stiffness)") from err
        post = _trace_term(post_inv[0], post_inv[1], base, lins[0], lins[1], keys, aidx, s, h)
        model = 0.0
        mkeys = [k for k in keys if _family(k) not in MEASUREMENT_FAMILIES]
        if mkeys:
            if model_inv is None and reuse:
                assert keep is not None
                model_inv = _factor_selected_inverse(keep["Rd"], keep["Ru"])
            if model_inv is None:
                Rd, Ru = np.empty((n, d, d)), np.empty((max(n - 1, 0), d, d))
                if not np.isfinite(_qr_factor(*_stacked(mbase, model_u, list(mbase.binary), n, aidx, s), Rd, Ru)):
                    raise EstimatorError("smoother: the trajectory prior information of the states is not positive "
                                         "definite (an unobservable direction: check contacts and stiffness)")
                model_inv = _factor_selected_inverse(Rd, Ru)
            model = _trace_term(model_inv[0], model_inv[1], mbase, plain_model_rows(lins[0]),
                                plain_model_rows(lins[1]), mkeys, aidx, s, h)
        grad[j] = 0.5 * (post - model)
    if entry is not None:
        entry.post_inv, entry.model_inv = post_inv, model_inv
    return grad


@dataclass
class SharedStates:
    """The per-step states' part of a linearisation that the candidates of one base fit share
    (:func:`shared_states`): the states' columns ``aidx``, their Jacobi scale ``s``, the scaled
    diagonal and upper blocks ``Hs``, ``Bs``, and, formed the first time one is needed, their
    block Cholesky factor (the screening's elimination) and the selected inverses of the posterior
    and of the trajectory prior (:func:`occam_gradient`)."""

    aidx: np.ndarray
    s: np.ndarray
    Hs: np.ndarray
    Bs: np.ndarray
    factor: tuple[np.ndarray, np.ndarray] | None = None
    post_inv: tuple[np.ndarray, np.ndarray] | None = None
    model_inv: tuple[np.ndarray, np.ndarray] | None = None

    def cholesky(self) -> tuple[np.ndarray, np.ndarray]:
        """The block Cholesky factor of ``Hs``/``Bs`` (:func:`~flexforce.smoother.solvers.block_tridiag_factor`)."""
        if self.factor is None:
            try:
                self.factor = solvers.block_tridiag_factor(self.Hs, self.Bs)
            except np.linalg.LinAlgError as err:
                raise EstimatorError("smoother: the posterior information of the states is not positive definite "
                                     "(an unobservable direction: check contacts and stiffness)") from err
        return self.factor


class StatesCache:
    """The latest :class:`SharedStates` formed by :func:`shared_states`, by the fingerprint of the
    rows they come from (:func:`_states_fingerprint`): a screening tests every candidate at one base
    fit, and a constant candidate at its null value adds no rows on the states (its prior is on
    ``theta``), so the candidates of one base share them (the rows differ only by the candidates'
    zero rows there).  One entry, the latest; its arrays are the size of a fit's covariances, so a
    cache lives for one screening (:func:`states_cache`) and is cleared at its end."""

    def __init__(self) -> None:
        self._key: bytes | None = None
        self._entry: SharedStates | None = None

    def __len__(self) -> int:
        return 0 if self._entry is None else 1

    @property
    def key(self) -> bytes | None:
        """The fingerprint of the entry held, None when empty."""
        return self._key

    def get(self, prob, base: Linearization, cidx: np.ndarray) -> SharedStates:
        """The states' part of ``base`` (a linearisation without the global walks, ``cidx`` its
        global columns): the entry held when its fingerprint is the same, else formed and held."""
        aidx = np.setdiff1d(np.arange(prob.state_dim), cidx)
        key = _states_fingerprint(prob, base, aidx)
        if self._entry is None or self._key != key:
            aidx, s, Hs, Bs = _scaled_states(prob, base, cidx)
            self._key, self._entry = key, SharedStates(aidx, s, Hs, Bs)
        return self._entry

    def clear(self) -> None:
        """Free the entry."""
        self._key = self._entry = None


_ACTIVE_STATES: contextvars.ContextVar[StatesCache | None] = contextvars.ContextVar("flexforce_states_cache",
                                                                                   default=None)
"""The cache of the innermost :func:`states_cache` scope of this context (inherited by the processes
forked inside it), None outside any."""


@contextlib.contextmanager
def states_cache() -> Iterator[StatesCache]:
    """A scope whose :func:`shared_states` calls share one :class:`StatesCache` (the score tests of
    one screening); the cache is cleared when the scope ends.  Outside any scope every call forms
    the states' part anew."""
    cache = StatesCache()
    token = _ACTIVE_STATES.set(cache)
    try:
        yield cache
    finally:
        _ACTIVE_STATES.reset(token)
        cache.clear()


def shared_states(prob, base: Linearization, cidx: np.ndarray, cache: StatesCache | None = None) -> SharedStates:
    """The states' part of ``base`` (a linearisation without the global walks, ``cidx`` its
    global columns), from ``cache`` or else the active :func:`states_cache` scope's
    (:meth:`StatesCache.get`); formed anew outside any scope."""
    cache = cache if cache is not None else _ACTIVE_STATES.get()
    if cache is None:
        aidx, s, Hs, Bs = _scaled_states(prob, base, cidx)
        return SharedStates(aidx, s, Hs, Bs)
    return cache.get(prob, base, cidx)


def _states_fingerprint(prob, lin: Linearization, aidx: np.ndarray) -> bytes:
    """A digest of everything the states' part of ``lin`` is formed from: each family's name and
    Jacobian on the states' columns ``aidx`` (the families on ``theta`` alone, its priors, left
    out: they are zero there) and the Newton-Euler Huber weights.  Each Jacobian enters by its
    product with two fixed random vectors that vanish off ``aidx`` (the same rows give the same
    bytes; rows that differ give other bytes unless the difference is below the products' rounding),
    which reads each Jacobian once without copying it."""
    import hashlib

    h = hashlib.blake2b(digest_size=20)
    h.update(np.asarray(aidx, dtype=np.int64).tobytes())
    V = np.zeros((prob.state_dim, 2))
    V[aidx] = np.random.default_rng(20151001).standard_normal((len(aidx), 2))
    on_theta = theta_prior_keys(prob)

    def add(J: np.ndarray) -> None:
        h.update(np.asarray(J.shape[:-1], dtype=np.int64).tobytes())  # not the columns: a candidate's add none on aidx
        h.update(np.ascontiguousarray(J @ V).tobytes())

    for key in sorted(lin.unary):
        if key in on_theta:
            continue
        h.update(key.encode())
        add(lin.unary[key][1])
    for key in sorted(lin.binary):
        _, J0, J1 = lin.binary[key]
        h.update(key.encode())
        add(J0)
        add(J1)
    if lin.ne_weights is not None:
        h.update(np.ascontiguousarray(lin.ne_weights).tobytes())
    return h.digest()


def global_prior_sigma(prob) -> np.ndarray:
    """Prior sigma of every global parameter, in the order of the global columns."""
    out: list[float] = []
    for eff in prob.effects:
        if is_global(eff, prob):
            _, s0 = eff.prior(prob)
            out.extend(np.broadcast_to(np.asarray(s0, dtype=float), (int(eff.dim),)))
    return np.asarray(out, dtype=float)


def theta_prior_cost(prob, lin: Linearization) -> float:
    """Half the squared residuals of ``theta``'s own prior (the global effects' priors and random
    walks): what the objective adds to the negative log evidence."""
    keys = theta_prior_keys(prob) | {f"effect_walk/{e.name}" for e in prob.effects if is_global(e, prob)}
    total = 0.0
    for key, (r, *_) in list(lin.unary.items()) + list(lin.binary.items()):
        if key in keys:
            total += 0.5 * float(np.sum(r * r))
    return total


def state_prior_cost(prob, lin: Linearization) -> float:
    """Half the squared residuals of the trajectory prior's own factors that are not data: the
    first-step prior and the per-step effects' priors and random walks (not ``theta``'s prior)."""
    skip = theta_prior_keys(prob)
    total = 0.0
    for key, (r, *_) in list(lin.unary.items()) + list(lin.binary.items()):
        fam = _family(key)
        if key in skip or fam not in ("prior", "effect_prior", "effect_level", "effect_walk"):
            continue
        if fam == "effect_walk" and key.split("/", 1)[1] in {e.name for e in prob.effects if is_global(e, prob)}:
            continue
        total += 0.5 * float(np.sum(r * r))
    return total
