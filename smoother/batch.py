r"""Batch smoothing: Levenberg-Marquardt over the whole recording.

The factor graph (DESIGN.md, "The factor graph") is a chain, so its Gauss-Newton system is block
tridiagonal.  Instead of handing ~5 N Python factors to gtsam (6 us of binding per factor and
linearisation, ~1 s per iteration for a minute of data before any arithmetic), the batch smoother
linearises all steps at once with the compiled kernels of :mod:`flexforce.factors.kernels` and
solves the system by block elimination (an information filter and its RTS back substitution),
which also yields the marginal covariances exactly.  The same factors, as gtsam CustomFactors,
drive the fixed-lag smoother; ``tests/test_smoother.py`` checks that both agree with gtsam's own
Levenberg-Marquardt on a short recording.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from flexforce.errors import EstimatorError
from flexforce.smoother.linearize import Trajectory, assemble, linearize, solve
from flexforce.smoother.problem import NoiseRule, Problem
from flexforce.smoother.result import make_estimate


def initial_trajectory(prob: Problem) -> Trajectory:
    """Every step at the first step's static equilibrium, at rest; wrenches from the contact law."""
    R0, q0 = prob.prior_mean
    n = prob.n
    R = np.repeat(R0[None], n, axis=0)
    q = np.repeat(q0[None], n, axis=0)
    W0 = prob.contact_wrenches(0, R0, q0)
    W = np.repeat(W0[None], n, axis=0) * prob.active[:, :, None]
    e = np.zeros((n, prob.effect_dim))
    off = 0
    for eff in prob.effects:
        mean, _ = eff.prior(prob)
        e[:, off:off + eff.dim] = mean
        off += eff.dim
    return Trajectory(R, q, W, e)


def optimize(prob: Problem, traj: Trajectory | None = None, max_iterations: int = 30, rel_tol: float = 1e-7,
             progress: Callable[[float], None] | None = None, want_cov: bool = True):
    """Levenberg-Marquardt on the whole trajectory.

    Returns ``(trajectory, P, info)`` with ``P`` the (N, D, D) marginal covariances at the optimum
    (None without ``want_cov``) and ``info`` the iteration log.
    """
    if traj is None:
        traj = initial_trajectory(prob)
    n, D = prob.n, prob.state_dim
    lin = linearize(prob, traj)
    cost = lin.cost
    lam = 1e-6
    log = [cost]
    for it in range(max_iterations):
        Hd, B, g = assemble(lin, n, D)
        dx, _ = solve(Hd, B, g, damping=lam)
        if not np.all(np.isfinite(dx)):
            raise EstimatorError("batch smoother: the Gauss-Newton step is not finite (singular system)")
        cand = traj.retract(dx)
        lin_c = linearize(prob, cand)
        if lin_c.cost <= cost:
            decrease = cost - lin_c.cost
            traj, lin, cost = cand, lin_c, lin_c.cost
            log.append(cost)
            lam = max(lam / 10.0, 1e-12)
            if decrease <= rel_tol * max(cost, 1.0):
                break
        else:
            lam *= 10.0
            if lam > 1e8:
                break
        if progress is not None:
            progress(min(0.9, 0.1 + 0.8 * (it + 1) / max_iterations))
    P = None
    if want_cov:
        Hd, B, g = assemble(lin, n, D)
        _, P = solve(Hd, B, g, damping=0.0, want_cov=True)
    return traj, P, {"iterations": len(log) - 1, "cost": log}


def run_batch(rec, model, progress: Callable[[float], None] | None = None, rule: NoiseRule | None = None,
              max_iterations: int = 30, covariance: bool = True, **options):
    """Batch (whole-recording) smoothing of a Recording; returns an :class:`Estimate`.

    Args:
        rec: the Recording.
        model: the ModelConfig (contact parameters, sensor noise, ``use_ft``, ``effects``).
        progress: called with the fraction done.
        rule: the noise rule of the model-error families (default :class:`NoiseRule`).
        max_iterations: Levenberg-Marquardt iterations at most.
        covariance: compute the marginal covariances (cheap: one extra block elimination).
    """
    if options:
        raise EstimatorError(f"batch smoother: unknown option(s) {sorted(options)}; known: rule, "
                             "max_iterations, covariance")
    t0 = time.perf_counter()
    prob = Problem.build(rec, model, rule or NoiseRule())
    if progress is not None:
        progress(0.05)
    traj, P, info = optimize(prob, max_iterations=max_iterations, progress=progress, want_cov=covariance)
    elapsed = time.perf_counter() - t0
    est = make_estimate(prob, "batch", traj, P, total_time=elapsed,
                        meta={"iterations": info["iterations"], "final_cost": info["cost"][-1],
                              "use_ft": prob.use_ft})
    est.total_time = time.perf_counter() - t0
    if progress is not None:
        progress(1.0)
    return est
