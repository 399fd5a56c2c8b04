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
unknowns, so their minimum is zero).  Both are block tridiagonal: their log-determinants are the
block Cholesky pivots' (:func:`flexforce.factors.solvers.block_tridiag_logdet`).

:func:`flexforce.smoother.batch.optimize` estimates ``theta`` by minimising this (type-II maximum
likelihood, with ``theta``'s own prior), the states by MAP given it; the diagnostics score an
effect by the gain in it (:mod:`flexforce.compare.diagnose`).
"""

from __future__ import annotations

import numpy as np

from flexforce.errors import EstimatorError
from flexforce.smoother import solvers
from flexforce.smoother.linearize import Linearization, assemble, drop_global_walks, is_global, linearize

MEASUREMENT_FAMILIES = ("imu", "ft")
"""Factor families that are measurements; every other family is part of the trajectory prior."""


def _family(key: str) -> str:
    return key.split("/")[0]


def theta_prior_keys(prob) -> set[str]:
    """Keys of the global effects' own priors (on ``theta``, not on the states)."""
    return {f"effect_prior/{eff.name}" for eff in prob.effects if is_global(eff, prob)}


def log_dets(prob, lin: Linearization, cidx: np.ndarray) -> tuple[float, float]:
    """``(ln det H_post, ln det H_model)`` over the per-step states (the columns ``cidx`` held)."""
    lin = drop_global_walks(prob, lin) if cidx.size else lin
    n, D = prob.n, prob.state_dim
    aidx = np.setdiff1d(np.arange(D), cidx)
    Hd, B, _ = assemble(lin, n, D)
    model = Linearization(unary={k: v for k, v in lin.unary.items() if _family(k) not in MEASUREMENT_FAMILIES},
                          binary=lin.binary)
    Hm, Bm, _ = assemble(model, n, D)
    Hd, B = Hd[:, aidx][:, :, aidx], B[:, aidx][:, :, aidx]
    Hm, Bm = Hm[:, aidx][:, :, aidx], Bm[:, aidx][:, :, aidx]
    # one Jacobi scaling for both (it cancels in the difference, and conditions the pivots)
    s = 1.0 / np.sqrt(np.maximum(np.diagonal(Hd, axis1=1, axis2=2), 1e-300))
    shift = -2.0 * float(np.sum(np.log(s)))
    out = []
    for H, Bk, what in ((Hd, B, "posterior"), (Hm, Bm, "trajectory prior")):
        Hs = np.ascontiguousarray(H * s[:, :, None] * s[:, None, :])
        Bs = np.ascontiguousarray(Bk * s[:-1, :, None] * s[1:, None, :])
        try:
            out.append(float(solvers.block_tridiag_logdet(Hs, Bs)) + shift)
        except np.linalg.LinAlgError as exc:
            raise EstimatorError(f"smoother: the {what} information of the states is not positive definite "
                                 "(an unobservable direction: check contacts and stiffness)") from exc
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
