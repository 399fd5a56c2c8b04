r"""Batch smoothing: Levenberg-Marquardt over the whole recording.

The factor graph (DESIGN.md, "The factor graph") is a chain, so its Gauss-Newton system is block
tridiagonal.  Instead of handing ~5 N Python factors to gtsam (measured, benchmarks/smoother_speed.py:
one gtsam Levenberg-Marquardt iteration on the CustomFactors takes 0.4 / 2.3 / 9.9 s for 200 / 400
/ 801 steps, growing with the square of the graph, 70x the whole own solve of 4 s of data), the
batch smoother linearises all steps at once with the compiled kernels of
:mod:`flexforce.factors.core` and solves the system by block elimination (an information filter
and its RTS back substitution), which also yields the marginal covariances exactly.  The same
factors, as gtsam CustomFactors, make the graph a user can take into gtsam
(:func:`flexforce.smoother.to_gtsam`) and the gtsam fixed-lag backend; ``tests/test_smoother.py``
and ``tests/test_gtsam_graph.py`` check that both agree with gtsam's own Levenberg-Marquardt.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from flexforce.errors import ConfigError, EstimatorError
from flexforce.factors.effects.base import traits
from flexforce.options import check_bool, check_int, check_positive, check_type
from flexforce.smoother import evidence
from flexforce.smoother.linearize import (
    Trajectory,
    _matvec,
    assemble,
    drop_global_walks,
    global_columns,
    is_global,
    linearize,
    solve_arrow,
    solve_arrow_pair,
    walk_sigma,
)
from flexforce.smoother.problem import (
    NoiseRule,
    Problem,
    build_problem,
    configured,
    imu_residual_scale,
    scaled_imu_noise,
)
from flexforce.smoother.result import make_estimate

if TYPE_CHECKING:
    from flexforce.datasets.estimate import Estimate
    from flexforce.datasets.recording import Recording
    from flexforce.factors.model import ModelConfig

S_CORE = 18

GLOBAL_CONSTANTS = True
"""Default of ``global_constants`` (:func:`optimize`, :func:`run_batch`, :func:`fit`): constant effects
as one global block, estimated by the marginal likelihood of the data (:mod:`.evidence`) with the
states re-optimised for each value (variable projection).  False carries them as per-step copies
tied by a tight random walk, as the fixed-lag smoother does (slow to converge in batch)."""


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


def carried_over(prob: Problem, effects, traj: Trajectory) -> Trajectory:
    """A start for ``prob`` from a fit of the same recording with fewer effects: the fitted
    ``traj`` of the model with ``effects`` (its states, wrenches and the values of the effects
    ``prob`` shares with it, matched by name), every other effect at its prior mean.

    A model with an effect added contains the one without it (the effect at zero), so its fit
    starts where the smaller one ended, and ends no higher (and in fewer iterations:
    docs/smoother.md, "Solvers")."""
    out = initial_trajectory(prob)
    if traj.R.shape != out.R.shape or traj.W.shape != out.W.shape:
        raise ConfigError(f"a start of {traj.R.shape[0]} steps and {traj.W.shape[1]} contacts for a problem of "
                          f"{prob.n} steps and {prob.nc} contacts; expected a fit of the same recording")
    out.R[:] = traj.R
    out.q[:] = traj.q
    out.W[:] = traj.W
    have: dict[str, list[tuple[int, int]]] = {}  # name -> its (offset, dim) in the start, in order
    off = 0
    for eff in effects:
        have.setdefault(eff.name, []).append((off, int(eff.dim)))
        off += int(eff.dim)
    if off != traj.e.shape[1]:
        raise ConfigError(f"a start with {traj.e.shape[1]} effect values for effects of {off}; expected the "
                          "effects the start was fitted with")
    off = 0
    for eff in prob.effects:
        src = have.get(eff.name)
        if src:
            at, dim = src.pop(0)
            if dim == int(eff.dim):
                out.e[:, off:off + dim] = traj.e[:, at:at + dim]
        off += int(eff.dim)
    return out


TRIAL_PATIENCE = 10
"""LM iterations after which a trial of the global block (:func:`optimize`) whose states' cost
still exceeds the current cost by over twice the decrease the step promised is given up (the
step is shortened): such trials end above the current cost, rejected anyway, after many
iterations (docs/smoother.md, "Solvers")."""


def _quadratic_decrease(Hd, B, g, dx) -> float:
    """The decrease ``g . dx - dx . H dx / 2`` the Gauss-Newton model promises for the step ``dx``
    (per-step layout; a global block's step repeated in every step sums as the arrow system does)."""
    return float(np.sum(g * dx) - 0.5 * np.sum(dx * _matvec(Hd, B, dx)))


def _levenberg_marquardt(prob, traj, lin, cidx, freeze, max_iterations, rel_tol, lam=1e-6, progress=None,
                         give_up_above: float | None = None):
    """Levenberg-Marquardt on the arrow system (``freeze``: the global block held, the per-step part
    alone).  Returns ``(traj, lin, costs)``, ``costs`` the cost after each accepted step.
    ``give_up_above``: stop after :data:`TRIAL_PATIENCE` iterations if the cost is still above it.

    The damping follows the gain ratio ``rho`` (actual over promised decrease) of each accepted
    step, ``lam *= max(1/10, 1 - (2 rho - 1)^3)`` (a step the model predicts well divides it by
    10, one it predicts half right keeps it), and grows by 2, 4, 8, ... on consecutive rejections
    (Nielsen's rule), which follows a curved valley where a fixed factor of 10 each way
    alternates between accepted and rejected steps (docs/smoother.md, "Solvers").
    Converged when an accepted step gains less than ``rel_tol`` of the cost and either the damping
    is negligible or the undamped Gauss-Newton step promises no more."""
    cost = lin.cost
    log = []
    grow = 2.0
    Hd, B, g = _system(prob, lin, cidx)  # assembled once per linearisation point (a rejection keeps it)
    for it in range(max_iterations):
        if give_up_above is not None and it >= TRIAL_PATIENCE and cost > give_up_above:
            break
        dx, _, _ = solve_arrow(Hd, B, g, cidx, damping=lam, freeze=freeze)
        if not np.all(np.isfinite(dx)):
            raise EstimatorError("batch smoother: the Gauss-Newton step is not finite (singular system)")
        cand = traj.retract(dx)
        lin_c = linearize(prob, cand)
        if lin_c.cost <= cost:
            decrease = cost - lin_c.cost
            promised = _quadratic_decrease(Hd, B, g, dx)
            rho = decrease / promised if promised > 0.0 else 1.0
            traj, lin, cost = cand, lin_c, lin_c.cost
            log.append(cost)
            lam = max(lam * max(0.1, 1.0 - (2.0 * rho - 1.0) ** 3), 1e-12)
            grow = 2.0
            if decrease <= rel_tol * max(cost, 1.0) and lam <= 1e-12:
                break
            Hd, B, g = _system(prob, lin, cidx)
            if decrease <= rel_tol * max(cost, 1.0):
                # damped: converged only if the undamped step has nothing more to give
                dx, _, _ = solve_arrow(Hd, B, g, cidx, damping=0.0, freeze=freeze)
                if not np.all(np.isfinite(dx)) or _quadratic_decrease(Hd, B, g, dx) <= rel_tol * max(cost, 1.0):
                    break
        else:
            lam *= grow
            grow *= 2.0
            if lam > 1e8:
                break
        if progress is not None:
            progress(min(0.9, 0.1 + 0.8 * (it + 1) / max_iterations))
    return traj, lin, log


def _system(prob, lin, cidx):
    """Gauss-Newton blocks; the global effects' random walks left out when they are one block."""
    return assemble(drop_global_walks(prob, lin) if cidx.size else lin, prob.n, prob.state_dim)


def _feasible(prob, traj) -> bool:
    """Every global effect's optional ``feasible(values)`` (e.g. a positive stiffness) holds."""
    off = 0
    for eff in prob.effects:
        check = traits(eff).feasible
        if check is not None and is_global(eff, prob) and not check(traj.e[0, off:off + eff.dim]):
            return False
        off += int(eff.dim)
    return True


OVERSTATED = (1.5, 2)
"""A full secant step that gains more than ``OVERSTATED[0]`` times what it promised was taken with
a curvature over twice the true one along it (for a quadratic the ratio is ``2 - s'Hs / s'(S +
M)s``); after ``OVERSTATED[1]`` such steps in a row the secant is not used again in that fit (the
symmetric rank-one update should have corrected it from the first): an over-stated curvature
otherwise crawls with short steps that each gain more than the tolerance (docs/smoother.md,
"Solvers")."""


def _secant_update(M, s, Ss, g_old, g_new):
    """The symmetric rank-one update of ``M``, the curvature of the constants' objective that the
    Gauss-Newton Schur complement ``S`` misses (the Occam term's, the residuals' own curvature),
    from one accepted step ``s``: the gradient changed by ``y = g_old - g_new`` (``g`` minus the
    gradient), ``S s`` of it predicted, so ``M s`` should be ``y - S s``.  Skipped when the update
    is ill-defined (its denominator small against the vectors' sizes)."""
    y = g_old - g_new
    v = y - Ss - M @ s
    den = float(v @ s)
    nv = float(np.linalg.norm(v))
    if (not np.isfinite(den) or nv <= 1e-12 * max(float(np.linalg.norm(y)), float(np.linalg.norm(Ss)))
            or abs(den) <= 1e-8 * nv * float(np.linalg.norm(s))):
        return M  # nothing to learn along s, or an ill-defined update
    return M + np.outer(v, v) / den


def _global_columns(prob, global_constants):
    on = GLOBAL_CONSTANTS if global_constants is None else bool(global_constants)
    return global_columns(prob) if on else np.zeros(0, dtype=int)


def optimize(prob: Problem, traj: Trajectory | None = None, max_iterations: int = 200, rel_tol: float = 1e-7,
             progress: Callable[[float], None] | None = None, want_cov: bool = True,
             global_constants: bool | None = None, evidence_tol: float = 0.0,
             watch: Callable[[Trajectory], str | None] | None = None, secant: bool = True):
    """Levenberg-Marquardt on the whole trajectory.

    With ``global_constants`` (default :data:`GLOBAL_CONSTANTS`; otherwise constant effects are
    per-step copies tied by their random walk, as in the fixed-lag smoother), constant effects
    (``constant = True``) are one global block (:func:`~flexforce.smoother.linearize.solve_arrow`).
    The joint Gauss-Newton step is then a poor guide for the per-step states (the contact effects
    are bilinear in state and parameter: the linearised response of the trajectory to a change of
    stiffness overshoots by orders of magnitude), so the global block is optimised by variable
    projection: the per-step states are optimised with the global block held (LM), then, per
    outer iteration, the global block moves by its Schur-complement Gauss-Newton step (which
    accounts for the states' linear response) and the states are re-optimised with it held; a
    step that does not lower the cost is shortened (x 1/4).  ``max_iterations`` bounds each LM
    run and the outer iterations.  The Schur complement is the data's curvature, not the Occam
    term's: with ``secant`` (:attr:`BatchConfig.secant`), a symmetric
    rank-one estimate of what it misses, learnt from the gradients of the accepted full steps,
    is added to it (fewer outer steps: docs/smoother.md, "The outer steps"); a shortened step
    resets it, and a step it makes that does not descend, or that promises less than the
    tolerance where the Gauss-Newton one promises more, gives way to the Gauss-Newton one; a
    secant whose full steps gain well over their promise, step after step, is dropped
    (:data:`OVERSTATED`).  The outer iterations end once a full step gains less than ``rel_tol``
    of the cost or ``evidence_tol`` (nats of the marginal likelihood), whichever is larger, or
    when the step promises less (both the secant's and the Gauss-Newton model);
    ``watch(trajectory)``, called after each accepted outer step, ends them too when it returns
    a reason (kept in ``info["stopped"]``).

    Returns ``(trajectory, P, info)`` with ``P`` the (N, D, D) marginal covariances at the optimum
    (None without ``want_cov``) and ``info`` the iteration log (``iterations``: LM steps accepted,
    ``outer``: global steps accepted, ``stopped``: the watch's reason or None, ``final``: the
    linearisation at the returned trajectory and its :func:`~flexforce.smoother.evidence.log_dets`,
    with constants; None without).
    """
    start = traj
    if traj is None:
        traj = initial_trajectory(prob)
    cidx = _global_columns(prob, global_constants)
    lin = linearize(prob, traj)
    log = [lin.cost]
    outer = 0
    fallbacks = 0
    stopped: str | None = None
    held: tuple = (None, None)  # (linearisation, its assembled system) when log_dets formed it
    traj, lin, costs = _levenberg_marquardt(prob, traj, lin, cidx, cidx.size > 0, max_iterations, rel_tol,
                                            lam=1e-6 if start is None else 1e-12,
                                            progress=progress if cidx.size == 0 else None)
    log += costs
    if cidx.size:
        # theta by the marginal likelihood (smoother/evidence.py): J + occam
        keep: dict = {}  # the evidence's factors at the current point, for its gradient there
        dets = evidence.log_dets(prob, lin, cidx, keep)
        pen = 0.5 * (dets[0] - dets[1])
        gpen = evidence.occam_gradient(prob, traj, cidx, lin=lin, keep=keep)
        held = (lin, keep.get("system"))  # the system log_dets assembled at lin, for the step below
        keep.clear()
        curvature = _Secant(np.zeros((cidx.size, cidx.size)), bool(secant))
        for it in range(max_iterations):
            phi = lin.cost + pen
            tol = max(rel_tol * max(lin.cost, 1.0), evidence_tol)
            Hd, B, g = held[1] if held[0] is lin and held[1] is not None else _system(prob, lin, cidx)
            g = g.copy()
            g[0, cidx] -= gpen  # g is minus the gradient; the global block sums its steps
            gsum = g[:, cidx].sum(axis=0)
            curvature.learn(gsum)
            dx, promised_gn = _outer_direction(Hd, B, g, cidx, curvature.M, gsum, tol)
            used = curvature.M.copy()
            if not np.all(np.isfinite(dx)):
                raise EstimatorError("batch smoother: the Gauss-Newton step is not finite (singular system)")
            step = dx[0, cidx]
            full = step.copy()
            response: np.ndarray | None = dx  # the states' linear response to the step
            predicted = 0.5 * float(step @ gsum)
            if predicted <= 0.0 and np.any(gsum):
                # The Schur complement is numerically indefinite (a fit far from the data: the walk
                # with F/T): its step climbs.  Fall back to the Jacobi-scaled gradient, shortened
                # by the line search below, rather than stop at the start as if converged.
                scale = np.einsum("kjj->j", Hd[:, cidx][:, :, cidx])
                step = gsum / np.maximum(scale, 1e-12)
                predicted = 0.5 * float(step @ gsum)
                response = None
                fallbacks += 1
            if predicted <= tol and (promised_gn is None or promised_gn <= tol):
                break  # the Schur step promises nothing more
            accepted, cand, lin_c, costs, pen_c, dets_c, frac = _outer_line_search(
                prob, traj, lin, cidx, step, response, predicted, phi, tol, keep, max_iterations, rel_tol)
            if not accepted:
                break
            curvature.after_step(frac, full, gsum, used, response, predicted, phi - (lin_c.cost + pen_c))
            traj, lin, pen, dets = cand, lin_c, pen_c, dets_c
            log += costs
            outer += 1
            if progress is not None:
                progress(min(0.9, 0.3 + 0.6 * (it + 1) / max_iterations))
            if frac == 1.0 and phi - (lin.cost + pen) <= tol:
                break  # a full step gained less than the tolerance (a shortened one: try another)
            if watch is not None:
                stopped = watch(traj)
                if stopped:
                    break
            gpen = evidence.occam_gradient(prob, traj, cidx, lin=lin, keep=keep)
            held = (lin, keep.get("system"))
            keep.clear()
        if keep.get("lin") is lin and keep.get("system") is not None:  # the loop ended after log_dets at lin
            held = (lin, keep["system"])
    final_system = held[1] if cidx.size and held[0] is lin else None
    P = None
    if want_cov:
        Hd, B, g = final_system if final_system is not None else _system(prob, lin, cidx)
        _, P, _ = solve_arrow(Hd, B, g, cidx, damping=0.0, want_cov=True)
    return traj, P, {"iterations": len(log) - 1, "outer": outer, "gradient_fallbacks": fallbacks, "cost": log,
                     "stopped": stopped, "final": (lin, dets) if cidx.size else None, "final_system": final_system}


class _Secant:
    """The secant estimate ``M`` of the curvature the Schur complement misses, over the outer
    steps of one :func:`optimize` call (:func:`_secant_update`, :data:`OVERSTATED`)."""

    def __init__(self, M: np.ndarray, on: bool):
        self.M = M
        """(G, G) the estimate; zeroed in place where a step gives way to the Gauss-Newton one."""
        self.on = on
        """Learning from the accepted steps: off for the rest of the fit once over-stated."""
        self.last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        """The pair of the last accepted full step (step, S step, gsum), to learn from."""
        self.overstated = 0
        """Full secant steps in a row that gained well over their promise."""

    def learn(self, gsum: np.ndarray) -> None:
        """The update from the last accepted step, with the gradient sum ``gsum`` at its end."""
        if self.on and self.last is not None:
            self.M = _secant_update(self.M, *self.last, gsum)

    def after_step(self, frac, full, gsum, used, response, predicted, gain) -> None:
        """Bookkeeping of an accepted step ``frac * full`` taken with the estimate ``used``."""
        M = self.M
        # the secant pair of this step: the step taken and the change of the gradient the
        # Gauss-Newton Schur complement S predicts, S step = frac (gsum - M full)
        last = (frac * full, frac * (gsum - used @ full), gsum) if response is not None else None
        if frac < 1.0:
            # the model was poor this far from the optimum: learn nothing from it, and forget
            # what was learnt (a secant learnt from a shortened step costs more steps)
            last = None
            M = np.zeros_like(M)
        if frac == 1.0 and response is not None and np.any(used) and predicted > 0.0:
            # a full secant step: its gain against its promise says whether the curvature it
            # used along the step was over-stated (OVERSTATED)
            self.overstated = self.overstated + 1 if gain > OVERSTATED[0] * predicted else 0
            if self.overstated >= OVERSTATED[1]:
                self.on, M, last = False, np.zeros_like(M), None
        self.M, self.last = M, last


def _outer_direction(Hd, B, g, cidx, M, gsum, tol):
    """The outer step of the global block: ``(dx, promised_gn)``, the secant's step (``M`` added
    to the global block) when it is a descent and promises what the Gauss-Newton one does, else
    the Gauss-Newton step (``M`` zeroed in place: learn the curvature again); ``promised_gn`` the
    Gauss-Newton model's promise where the secant's step is taken, else None."""
    dx = None
    dgn = None
    if np.any(M):
        # the secant's step and the Gauss-Newton one, from one elimination of the per-step part
        dx, dgn = solve_arrow_pair(Hd, B, g, cidx, M)
        if dx is None or not np.all(np.isfinite(dx)) or float(dx[0, cidx] @ gsum) <= 0.0:
            M[:] = 0.0  # not a descent model: the Gauss-Newton one alone, and start learning again
            dx = None
    promised_gn = None
    if dx is None:
        dx = dgn if dgn is not None else solve_arrow(Hd, B, g, cidx, damping=0.0)[0]
    else:
        # the Gauss-Newton model's promise too: the secant's estimate alone can call a slope
        # converged that it has learnt wrongly
        assert dgn is not None
        promised_gn = 0.5 * float(dgn[0, cidx] @ gsum) if np.all(np.isfinite(dgn)) else None
        if (promised_gn is not None and promised_gn > tol
                and 0.5 * float(dx[0, cidx] @ gsum) <= tol):
            # the secant's step promises nothing the Gauss-Newton one still does: take that one
            # (the secant's tiny step would end the loop by its gain), and learn the curvature
            # again from it
            dx, M[:], promised_gn = dgn, 0.0, None
    return dx, promised_gn


def _outer_line_search(prob, traj, lin, cidx, step, response, predicted, phi, tol, keep, max_iterations, rel_tol):
    """Try the global block's ``step`` (the states re-optimised with it held, from their linear
    ``response`` when that starts lower), shortened (x 1/4) until the objective with its Occam
    term is at most ``phi``.  Returns ``(accepted, trajectory, linearisation, LM costs, Occam
    term, log_dets, fraction of the step taken)``."""
    n, D = prob.n, prob.state_dim
    frac = 1.0
    cand = lin_c = costs = dets_c = None
    pen_c = np.inf
    for _ in range(8):
        d = np.zeros((n, D))
        d[:, cidx] = step
        cand = traj.retract(d)
        if not _feasible(prob, cand):
            step, frac = 0.25 * step, 0.25 * frac
            continue
        lin_0 = linearize(prob, cand)
        if response is not None:
            # the states moved with the step by their linear response, when that starts lower
            # than the states held (a CoM offset, an IMU rotation: the states follow it nearly
            # linearly; a stiffness: the response overshoots, the held states are kept)
            d = frac * response
            d[:, cidx] = step
            moved = traj.retract(d)
            lin_m = linearize(prob, moved)
            if lin_m.cost < lin_0.cost:
                cand, lin_0 = moved, lin_m
        cand, lin_c, costs = _levenberg_marquardt(prob, cand, lin_0, cidx, True,
                                                  max_iterations, rel_tol, lam=1e-12,
                                                  give_up_above=lin.cost + 2.0 * predicted)
        try:
            dets_c = evidence.log_dets(prob, lin_c, cidx, keep)
            pen_c = 0.5 * (dets_c[0] - dets_c[1])
        except EstimatorError:  # e.g. a stiffness scale driven negative: unstable dynamics
            pen_c = np.inf
            keep.clear()
        if lin_c.cost + pen_c <= phi:
            return True, cand, lin_c, costs, pen_c, dets_c, frac
        step, frac = 0.25 * step, 0.25 * frac
        if frac * predicted <= tol:
            break  # shortened below what the convergence test resolves: converged
    return False, cand, lin_c, costs, pen_c, dets_c, frac


@dataclass(frozen=True)
class BatchConfig:
    """Options of the batch smoother (:func:`run_batch`); every field is checked on construction
    (a :class:`~flexforce.errors.ConfigError` naming the option, its value and what is expected)."""

    max_iterations: int = 200
    """Levenberg-Marquardt iterations at most (count, >= 1; accepted and rejected steps; it stops
    earlier once converged), per LM run and for the outer (global-constant) iterations.  The
    default leaves room for a walk from the first step's equilibrium (docs/smoother.md,
    "Solvers")."""
    rel_tol: float = 1e-7
    """Convergence: a step lowering the cost by less than ``rel_tol * max(cost, 1)`` ends the run
    (dimensionless, relative to the cost, > 0)."""
    covariance: bool = True
    """Compute the marginal covariances at the optimum (cheap: one extra block elimination)."""
    global_constants: bool = GLOBAL_CONSTANTS
    """Constant effects as one global block, estimated by the marginal likelihood (:func:`optimize`);
    False: per-step copies tied by a tight random walk, as in the fixed-lag smoother."""
    footholds: bool = False
    """Estimate every contact episode's rest placement (foothold) with the trajectory, from the leg
    kinematics at its touch-down and the ground plane (:mod:`flexforce.factors.footholds`, priors
    from the model's ``foothold_prior``); False: the rest placements are the given ones."""
    rule: NoiseRule = field(default_factory=NoiseRule)
    """The noise rule of the model-error families (:class:`~flexforce.smoother.problem.NoiseRule`)."""
    secant: bool = True
    """The outer steps of the constants (:func:`optimize`) add to the Gauss-Newton Schur complement
    a symmetric rank-one secant estimate of the curvature it misses (:func:`_secant_update`);
    False: the Gauss-Newton step alone.  Both end at the same optimum (within ``rel_tol``)."""
    noise_calibration: float | None = None
    """Sigmas, or None (off): after the fit, a sensor of the IMU whose whitened residuals have an
    RMS above this (:func:`~flexforce.smoother.problem.imu_residual_scale`) gets its sigma
    multiplied by that RMS (the accelerometer's carrying the model-error sigmas derived from it)
    and the recording is smoothed again with the calibrated noise; ``meta["noise_calibration"]``
    says what was found and used.  For real logs whose IMU sees what the model does not describe
    (a walk's vibration: docs/real-logs.md, "IMU noise"); a value below 3 would recalibrate a
    recording whose noise is right."""

    def __post_init__(self):
        o = "BatchConfig"
        check_int(o, "max_iterations", self.max_iterations, 1, "iterations", "an integer >= 1")
        check_positive(o, "rel_tol", self.rel_tol, "", "a positive relative cost decrease (e.g. 1e-7)")
        check_bool(o, "covariance", self.covariance)
        check_bool(o, "global_constants", self.global_constants)
        check_bool(o, "footholds", self.footholds)
        check_type(o, "rule", self.rule, NoiseRule)
        check_bool(o, "secant", self.secant)
        cal = self.noise_calibration
        if cal is not None and (isinstance(cal, bool) or not isinstance(cal, (int, float)) or not math.isfinite(cal)
                                or not cal > 1.0):
            raise ConfigError(f"BatchConfig.noise_calibration = {cal!r}; expected a number of sigmas above 1 (e.g. "
                              "3.0), or None (the configured noise as given)")


def run_batch(rec: Recording, model: ModelConfig, config: BatchConfig = BatchConfig(), rest_p=None, rest_R=None,
              progress: Callable[[float], None] | None = None, **options) -> Estimate:
    """Batch (whole-recording) smoothing of a Recording; returns an :class:`Estimate`.

    Args:
        rec: the Recording.
        model: the ModelConfig (contact parameters, sensor noise, ``use_ft``, ``effects``).
        config: a :class:`BatchConfig` (iterations, covariance, global constants, noise rule).
        rest_p, rest_R: (N, C, 3), (N, C, 3, 3) the contacts' rest placements in the world per step
            (footholds); default the recording's local placements (:meth:`Problem.build`).
        progress: called with the fraction done.
        options: fields of :class:`BatchConfig` replacing those of ``config`` (the older calling
            convention, ``run_batch(rec, model, max_iterations=50)``; ``rule=None`` is the default rule).

    Raises:
        ConfigError: ``config`` is not a BatchConfig, an unknown option (the known ones listed), or
            a bad value.
    """
    config = configured(config, BatchConfig, options, "batch smoother")
    t0 = time.perf_counter()
    est = _smooth(rec, model, config, rest_p, rest_R, progress, t0)
    if config.noise_calibration is not None and "imu" in est.residuals:
        rms, scale = imu_residual_scale(est.residuals["imu"], rec.time, 0.0, config.noise_calibration)
        calibrated = scaled_imu_noise(model, scale)
        if any(v != 1.0 for v in scale.values()):
            est = _smooth(rec, calibrated, config, rest_p, rest_R, progress, t0)
        est.meta["noise_calibration"] = {"threshold_sigma": config.noise_calibration, "rms_sigma": rms, "scale": scale,
                                         "gyro_sigma": calibrated.gyro_sigma, "accel_sigma": calibrated.accel_sigma}
    est.total_time = time.perf_counter() - t0
    if progress is not None:
        progress(1.0)
    return est


def _smooth(rec, model, config: BatchConfig, rest_p, rest_R, progress, t0: float) -> Estimate:
    """One batch smoothing of ``rec`` with ``model`` (:func:`run_batch`'s work)."""
    prob = build_problem(rec, model, config, rest_p, rest_R)
    if progress is not None:
        progress(0.05)
    traj, P, info = optimize(prob, max_iterations=config.max_iterations, rel_tol=config.rel_tol, progress=progress,
                             want_cov=config.covariance, global_constants=config.global_constants,
                             secant=config.secant)
    elapsed = time.perf_counter() - t0
    return make_estimate(prob, "batch", traj, P, total_time=elapsed,
                         meta={"iterations": info["iterations"], "outer": info["outer"], "final_cost": info["cost"][-1],
                               "use_ft": prob.use_ft})


DATA_FAMILIES = ("imu", "newton_euler", "contact", "integration", "ft")
"""The measurement and model families whose whitened residuals make the data cost of a fit."""


def effective_dof(prob: Problem, P: np.ndarray, Pc: np.ndarray) -> dict[str, float]:
    """Each effect's effective number of parameters: ``tr(I - P_post Lambda_prior)`` over its variables.

    ``Lambda_prior`` is the information of the effect's own factors (first-step prior and random
    walk), ``P_post`` the posterior covariance (``P`` its diagonal blocks, ``Pc`` the lag-one
    cross blocks).  Since ``Lambda_prior = sum_f a_f a_f^T / s_f^2`` over those factors,
    ``tr(P Lambda) = sum_f a_f^T P a_f / s_f^2``: the prior term ``P_00 / s_0^2`` and, per link,
    ``var(e_k+1 - e_k) / s_w^2`` with ``var(e_k+1 - e_k) = P_kk + P_k+1,k+1 - 2 P_k,k+1``, and
    ``P_kk / s_p^2`` per step for an effect with a per-step prior (``step_prior_sigma``).
    For a constant effect (``constant = True``, or a random walk too tight to matter) the steps
    are one parameter: ``dim - tr(P_00 diag(1/s_0^2))``, i.e. its dim when the data determine it,
    less when its prior does.
    """
    out = {}
    off = S_CORE + 6 * prob.nc
    n = prob.n
    for eff in prob.effects:
        d = int(eff.dim)
        sl = slice(off, off + d)
        _, s0 = eff.prior(prob)
        s0 = np.broadcast_to(np.asarray(s0, dtype=float), (d,))
        rw = walk_sigma(eff, prob)
        p00 = np.diagonal(P[0, sl, sl])
        prior_term = float(np.sum(p00 / s0**2))
        constant = traits(eff).constant
        if constant is None:
            constant = bool(np.all(rw * np.sqrt(max(n - 1, 1)) < 1e-3 * s0))
        if constant or n < 2:
            out[eff.name] = float(d - prior_term)
        else:
            var_d = (np.diagonal(P[:-1, sl, sl], axis1=1, axis2=2) + np.diagonal(P[1:, sl, sl], axis1=1, axis2=2)
                     - 2.0 * np.diagonal(Pc[:, sl, sl], axis1=1, axis2=2))
            level = traits(eff).step_prior_sigma
            level_term = 0.0
            if level is not None:
                sl_ = np.broadcast_to(np.asarray(level(prob), dtype=float), (d,))
                level_term = float(np.sum(np.diagonal(P[:, sl, sl], axis1=1, axis2=2) / sl_**2))
            out[eff.name] = float(n * d - prior_term - level_term - np.sum(var_d / rw**2))
        off += d
    return out


@dataclass(frozen=True)
class FitStatistics:
    """What :func:`fit` measures of a fitted model, for the diagnostics' information criterion.

    Costs are dimensionless: halves of sums of squared *whitened* residuals (a negative
    log-likelihood up to a constant), log-determinants natural logarithms of information matrices
    in the state's units (their difference, posterior minus prior, is unit-free).
    """

    cost_data: float
    """``1/2 sum r^2`` over the whitened residuals of the measurement and model families
    (:data:`DATA_FAMILIES`: ``imu``, ``newton_euler`` unweighted, i.e. before the Huber loss,
    ``contact`` of the active contacts, ``integration``, ``ft`` when fused); the effects' own prior
    and random-walk terms and the first-step prior are left out."""
    cost_total: float
    """The optimised objective: robust Newton-Euler, every prior and random walk included."""
    n_residuals: int
    """Number of scalar (finite) residuals in ``cost_data``: the ``n`` of BIC's ``ln n``."""
    effective_dof: dict[str, float]
    """Effect name -> its effective number of parameters (:func:`effective_dof`; ``dim`` for a
    constant the data determine, less when its prior does)."""
    cost_state_prior: float
    """``1/2 sum r^2`` of the state prior: the first-step prior, the per-step effects' priors and
    random walks (:func:`flexforce.smoother.evidence.state_prior_cost`)."""
    log_det_posterior: float
    """``ln det`` of the states' posterior information (Gauss-Newton Hessian at the optimum)."""
    log_det_prior: float
    """``ln det`` of the states' prior information (:func:`flexforce.smoother.evidence.log_dets`)."""
    cost_evidence: float
    """Negative log marginal likelihood of the data given the constant parameters, up to a
    constant (:mod:`.evidence`, Laplace): ``cost_data_robust + cost_state_prior +
    (log_det_posterior - log_det_prior) / 2``: the optimised objective without ``theta``'s prior."""
    cost_data_robust: float = float("nan")
    """The data term of the evidence: as ``cost_data`` with the objective's robust losses (the
    Huber Newton-Euler rows, a robust IMU loss when set) -- the negative log of their densities,
    whose normalisers do not depend on the model."""
    global_effects: tuple[str, ...] = ()
    """Effects whose unknowns were one global block: the constants the evidence is conditioned on
    (empty without ``global_constants``)."""
    trajectory: Trajectory | None = None
    """The fitted trajectory (every variable's value at the optimum): what the score test of a
    candidate effect (:mod:`flexforce.smoother.screening`) and the residuals' own variances
    (:mod:`flexforce.smoother.leverage`) linearise at."""
    stopped: str | None = None
    """Why the fit stopped before the marginal likelihood's optimum (``fit``'s ``watch``), or None:
    the evidence and the estimates are then those of where it stopped."""


def fit(rec: Recording, model: ModelConfig, progress: Callable[[float], None] | None = None,
        rule: NoiseRule | None = None,
        max_iterations: int = 200, global_constants: bool | None = None,
        start: tuple | None = None, evidence_tol: float = 0.0,
        watch: Callable[[Problem, Trajectory], str | None] | None = None,
        secant: bool = True) -> tuple[Estimate, FitStatistics]:
    """Batch smoothing with ``model.effects`` for the diagnostics: ``(estimate, statistics)``.

    The estimate is :func:`run_batch`'s (``Estimate.effects[name]`` is each effect's report: value,
    std, unit, summary, ...); the :class:`FitStatistics` hold the data cost, the evidence, the
    number of residuals and each effect's effective dof.  ``start``: ``(effects, trajectory)`` of a
    fit of the same recording with fewer effects, to start from (:func:`carried_over`); None: the
    first step's equilibrium.  ``evidence_tol``, ``watch(problem, trajectory)`` and ``secant``:
    :func:`optimize`'s (a watch's reason is :attr:`FitStatistics.stopped`).
    """
    t0 = time.perf_counter()
    prob = Problem.build(rec, model, rule or NoiseRule())
    if progress is not None:
        progress(0.05)
    traj0 = carried_over(prob, start[0], start[1]) if start is not None else None
    traj, _, info = optimize(prob, traj0, max_iterations=max_iterations, progress=progress, want_cov=False,
                             global_constants=global_constants, evidence_tol=evidence_tol,
                             watch=None if watch is None else (lambda tr: watch(prob, tr)), secant=secant)
    cidx = _global_columns(prob, global_constants)
    final = info.get("final")
    lin = final[0] if final is not None else linearize(prob, traj)
    system = info.get("final_system") if final is not None else None
    Hd, B, g = system if system is not None else _system(prob, lin, cidx)
    _, P, Pc = solve_arrow(Hd, B, g, cidx, want_cov=True)
    est = make_estimate(prob, "batch", traj, P, total_time=time.perf_counter() - t0,
                        meta={"iterations": info["iterations"], "outer": info["outer"], "final_cost": info["cost"][-1],
                              "use_ft": prob.use_ft})
    cost_data = 0.0
    n_res = 0
    for fam in DATA_FAMILIES:
        r = est.residuals.get(fam)
        if r is None:
            continue
        ok = np.isfinite(r)
        cost_data += 0.5 * float(np.sum(r[ok] ** 2))
        n_res += int(ok.sum())
    # the log-determinants optimize formed at this linearisation (its last Occam term), or anew
    post, prior = final[1] if final is not None else evidence.log_dets(prob, lin, cidx)
    state_prior = evidence.state_prior_cost(prob, lin)
    # the evidence is the objective (robust losses, the Occam term) less theta's own prior
    cost_evidence = float(lin.cost) - evidence.theta_prior_cost(prob, lin) + 0.5 * (post - prior)
    stats = FitStatistics(
        cost_data=cost_data, cost_total=float(lin.cost), n_residuals=n_res,
        effective_dof=effective_dof(prob, P, Pc), cost_state_prior=float(state_prior),
        log_det_posterior=float(post), log_det_prior=float(prior),
        cost_evidence=cost_evidence, cost_data_robust=cost_evidence - state_prior - 0.5 * (post - prior),
        global_effects=tuple(e.name for e in prob.effects if is_global(e, prob)) if cidx.size else (),
        trajectory=traj, stopped=info.get("stopped"))
    est.total_time = time.perf_counter() - t0
    if progress is not None:
        progress(1.0)
    return est, stats
