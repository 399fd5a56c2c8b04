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
from the factors' rows by a step-by-step QR (a square-root information filter, :func:`_qr_logdet`),
not from a Cholesky factorisation of ``H``: the trajectory prior's per-step blocks span 1e15 in
eigenvalue, and squaring that left its log-determinant's derivative in a parameter to noise.

:func:`flexforce.smoother.batch.optimize` estimates ``theta`` by minimising this (type-II maximum
likelihood, with ``theta``'s own prior), the states by MAP given it; the diagnostics score an
effect by the gain in it (:mod:`flexforce.compare.diagnose`).
"""

from __future__ import annotations

import numpy as np

from flexforce.errors import EstimatorError
from flexforce.factors.core import njit
from flexforce.smoother import solvers
from flexforce.smoother.linearize import Linearization, assemble, drop_global_walks, is_global, linearize

MEASUREMENT_FAMILIES = ("imu", "ft")
"""Factor families that are measurements; every other family is part of the trajectory prior."""


def _family(key: str) -> str:
    return key.split("/")[0]


def theta_prior_keys(prob) -> set[str]:
    """Keys of the global effects' own priors (on ``theta``, not on the states)."""
    return {f"effect_prior/{eff.name}" for eff in prob.effects if is_global(eff, prob)}


@njit
def _qr_logdet(Ju, J0, J1, Jf):
    """``ln det (J^T J)`` of the stacked rows of a chain, by a square-root information filter:
    ``Ju`` (N, ru, d) each step's own rows, ``J0``/``J1`` (N-1, rb, d) the rows linking steps
    ``k`` and ``k+1``, ``Jf`` (rf, d) rows on the first step only (its priors).  Step by step,
    the rows on ``x_k`` (carried from the previous step, own, first-step, link) are reduced by QR;
    ``R_kk``'s diagonal gives the determinant.  Unlike a Cholesky
    factorisation of ``J^T J`` this does not square the rows' condition number (the trajectory
    prior's blocks span 1e15 in eigenvalue).  Returns -inf when a pivot vanishes."""
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
        R = np.linalg.qr(M)[1]
        for i in range(d):
            v = abs(R[i, i])
            if v == 0.0:
                return -np.inf
            total += np.log(v)
        if not last:
            carry = np.zeros((d, d))
            m = min(R.shape[0], 2 * d) - d
            if m > 0:
                carry[:m] = R[d:d + m, d:]
    return 2.0 * total


def _stacked(lin: Linearization, keys_u, keys_b, n: int, aidx, s):
    """The rows of the families ``keys_u`` (unary) and ``keys_b`` (binary), on the columns ``aidx``
    scaled by ``s``: ``(Ju, J0, J1, Jf)`` for :func:`_qr_logdet`."""
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


def log_dets(prob, lin: Linearization, cidx: np.ndarray) -> tuple[float, float]:
    """``(ln det H_post, ln det H_model)`` over the per-step states (the columns ``cidx`` held):
    ``H_post``'s by its block Cholesky pivots, ``H_model``'s from the model factors' rows by QR
    (:func:`_qr_logdet`); the columns Jacobi-scaled by ``H_post``'s diagonal (the scale cancels
    in the difference)."""
    lin = drop_global_walks(prob, lin) if cidx.size else lin
    n, D = prob.n, prob.state_dim
    aidx = np.setdiff1d(np.arange(D), cidx)
    Hd, B, _ = assemble(lin, n, D)
    Ha, Ba = Hd[:, aidx][:, :, aidx], B[:, aidx][:, :, aidx]
    s = 1.0 / np.sqrt(np.maximum(np.diagonal(Ha, axis1=1, axis2=2), 1e-300))
    shift = -2.0 * float(np.sum(np.log(s)))
    # the posterior (the measurements make it well conditioned) by the block Cholesky pivots of
    # H; the trajectory prior by QR of its rows
    Hs = np.ascontiguousarray(Ha * s[:, :, None] * s[:, None, :])
    Bs = np.ascontiguousarray(Ba * s[:-1, :, None] * s[1:, None, :])
    try:
        post = float(solvers.block_tridiag_logdet(Hs, Bs))
    except np.linalg.LinAlgError:
        post = -np.inf
    model_u = [k for k in lin.unary if _family(k) not in MEASUREMENT_FAMILIES]
    prior = float(_qr_logdet(*_stacked(lin, model_u, list(lin.binary), n, aidx, s)))
    out = []
    for val, what in ((post, "posterior"), (prior, "trajectory prior")):
        if not np.isfinite(val):
            raise EstimatorError(f"smoother: the {what} information of the states is not positive definite "
                                 "(an unobservable direction: check contacts and stiffness)")
        out.append(val + shift)
    return out[0], out[1]


def occam(prob, lin: Linearization, cidx: np.ndarray) -> float:
    """``1/2 (ln det H_post - ln det H_model)``: what the states' integral adds to ``J``."""
    post, model = log_dets(prob, lin, cidx)
    return 0.5 * (post - model)


def occam_gradient(prob, traj, cidx: np.ndarray, rel_step: float = 1e-3) -> np.ndarray:
    """Gradient of :func:`occam` in the global parameters (central differences, the states held;
    steps of ``rel_step`` of each parameter's prior sigma)."""
    off = prob.state_dim - prob.effect_dim
    sig = global_prior_sigma(prob)
    grad = np.zeros(cidx.size)
    for j, col in enumerate(cidx):
        h = rel_step * sig[j]
        vals = []
        for sgn in (1.0, -1.0):
            e = traj.e.copy()
            e[:, col - off] += sgn * h
            cand = type(traj)(traj.R, traj.q, traj.W, e)
            vals.append(occam(prob, linearize(prob, cand), cidx))
        grad[j] = (vals[0] - vals[1]) / (2.0 * h)
    return grad


def global_prior_sigma(prob) -> np.ndarray:
    """Prior sigma of every global parameter, in the order of the global columns."""
    out: list[float] = []
    for eff in prob.effects:
        if is_global(eff, prob):
            _, s0 = eff.prior(prob)
            out.extend(np.broadcast_to(np.asarray(s0, dtype=float), (int(eff.dim),)))
    return np.asarray(out, dtype=float)


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
