r"""Fixed-lag smoothing for online use, one update per sample, bounded memory.

Two backends share the factors and the noise of :class:`Problem`:

``window`` (default, :class:`FixedLagSmoother`)
    The window's Gauss-Newton system is a block-tridiagonal chain.  It is eliminated oldest first
    (a square-root information filter): when step ``k`` arrives, only the newest ``relinearize``
    steps are relinearised (one Gauss-Newton iteration per update, at the previous update's
    estimate, the new step at its prediction) and re-eliminated, starting from the stored partial
    elimination of the newest frozen step; older steps keep their linearisation point and their
    elimination, and marginalising the oldest step is dropping its conditional.  A back
    substitution over the window gives every step's estimate.  The factors are linearised by the
    compiled kernels (:func:`flexforce.smoother.linearize.linearize`, the batch smoother's), so
    effects (the :class:`~flexforce.factors.effects.Effect` protocol) work as in batch.
    Every update back-substitutes the newest steps only (what the next relinearisation needs);
    every ``report_every`` updates the whole window is back-substituted and the steps that have
    left it since are read out, each smoothed with at least ``lag`` of future data (output
    latency ``lag`` plus up to ``report_every - 1`` samples).  Covariances: the window's
    marginals of the steps read out, at the same moments, by the recursion of
    :func:`flexforce.smoother.solvers.window_marginals` through the steps not yet final and by
    block maps across the final ones (:func:`flexforce.smoother.solvers.window_marginals_blocked`),
    timed apart from the updates.  ``block`` > 1 (:attr:`FixedLagConfig.block`): one update per
    ``block`` samples, adding them together.

``gtsam`` (:class:`GtsamFixedLagSmoother`)
    gtsam's IncrementalFixedLagSmoother (iSAM2) on the CustomFactors of
    :mod:`flexforce.factors.gtsam_factors`: the reference the window backend is tested against;
    slower (it re-eliminates the window at every update) and without effects.

gtsam backend: each sample adds the step's variables (predicted from the previous step by the integration model)
and factors (:class:`flexforce.smoother.graph.GraphBuilder`) and marginalises the steps older than
the lag, so memory is bounded however long the recording.  The estimate reported for step ``j``
is the smoothed one when ``j`` leaves the window (``lag`` seconds of future data); the last
``lag`` seconds are reported from the final window.

Covariances are the marginals of the pose, velocity and acceleration (and wrench) keys, each on
its own: the cross-covariances between keys are not extracted (iSAM2 gives per-key marginals
cheaply, joint ones only through a full ``Marginals``).  Pose covariances are converted from
gtsam's body-frame tangent to world-frame increments (``blkdiag(R, R) Sigma blkdiag(R, R)^T``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from flexforce.errors import ConfigError, EstimatorError
from flexforce.factors import core
from flexforce.options import (
    check_bool,
    check_choice,
    check_int,
    check_positive,
    check_type,
)
from flexforce.smoother import solvers, window_kernel
from flexforce.smoother.linearize import Trajectory, assemble_split, linearize
from flexforce.smoother.problem import NoiseRule, Problem, build_problem, configured
from flexforce.smoother.result import make_estimate

if TYPE_CHECKING:
    import gtsam

    from flexforce.datasets.estimate import Estimate
    from flexforce.datasets.recording import Recording
    from flexforce.factors import gtsam_factors as gf
    from flexforce.factors.model import ModelConfig

S = core.STATE_DIM


def _load_gtsam() -> None:
    """Import gtsam and the CustomFactors for the gtsam backend, on first use: the window
    backend (the stream) runs without them (~65 MB of libraries)."""
    if "gtsam" not in globals():
        import gtsam as gtsam_module

        from flexforce.factors import gtsam_factors
        globals().update(gtsam=gtsam_module, gf=gtsam_factors)


RELINEARIZE_THRESHOLD = {
    "x": (5e-3, 5e-3, 5e-3, 1e-3, 1e-3, 1e-3),  # rad, m: the Jacobians change by ~1e-3 relative
    "v": (0.05,) * 6,  # rad/s, m/s: enter through w x (.) only
    "a": (1.0,) * 6,  # the factors are affine in the acceleration
    "w": (10.0,) * 6,  # N, N m: affine in the wrench (the F/T factor mildly bilinear with X)
}
"""iSAM2 relinearisation thresholds per variable type (delta from the linearisation point).
Measured: one scalar threshold (1e-3) relinearised the wrench keys at every update, and each
relinearisation re-eliminates the chain back to that step (p99 update > 0.5 s)."""


def _isam_params(relinearize_threshold, relinearize_skip: int) -> gtsam.ISAM2Params:
    _load_gtsam()
    params = gtsam.ISAM2Params()
    if relinearize_threshold is None:
        thresholds = gtsam.ISAM2ThresholdMap()
        for key, value in RELINEARIZE_THRESHOLD.items():
            thresholds.insert((key, np.asarray(value, dtype=float)))
        params.setRelinearizeThreshold(thresholds)
    else:
        params.setRelinearizeThreshold(float(relinearize_threshold))
    params.relinearizeSkip = relinearize_skip
    return params



def predict_step(R_prev, q_prev, dt: float):
    """Initial guess of the next step: the previous one moved at constant acceleration over ``dt``.

    ``q = (t, w, v, dw, a)``; the rotation is composed on SO(3) with the world-frame increment.
    """
    w, v, dw, a = q_prev[3:6], q_prev[6:9], q_prev[9:12], q_prev[12:15]
    R = core.so3_exp(w * dt + 0.5 * dw * dt * dt) @ R_prev
    q = q_prev.copy()
    q[0:3] = q_prev[0:3] + v * dt + 0.5 * a * dt * dt
    q[3:6] = w + dw * dt
    q[6:9] = v + a * dt
    return R, q

class GtsamFixedLagSmoother:
    """gtsam's IncrementalFixedLagSmoother on the CustomFactors (reference backend, no effects):
    call :meth:`step` once per sample (in order), then :meth:`finish`.

    ``kind="batch"``: gtsam's BatchFixedLagSmoother instead (Levenberg-Marquardt over the whole
    window at every update, ``lm_params`` default gtsam's; no marginal covariances: ``covariance``
    must be False), for comparison (benchmarks/smoother_speed.py)."""

    def __init__(self, prob: Problem, lag: float = 1.0, relinearize_threshold: float | None = None,
                 relinearize_skip: int = 10, covariance: bool = True, kind: str = "incremental",
                 lm_params: gtsam.LevenbergMarquardtParams | None = None):
        check_choice("GtsamFixedLagSmoother", "kind", kind, ("incremental", "batch"))
        if kind == "batch" and covariance:
            raise ConfigError("GtsamFixedLagSmoother: gtsam's BatchFixedLagSmoother gives no marginal covariances; "
                              "expected covariance=False with kind='batch'")
        check_positive("GtsamFixedLagSmoother", "lag", lag, "s", "a positive duration")
        check_positive("GtsamFixedLagSmoother", "relinearize_threshold", relinearize_threshold, "",
                       "a positive number or None", optional=True)
        check_int("GtsamFixedLagSmoother", "relinearize_skip", relinearize_skip, 1, "updates", "an integer >= 1")
        if prob.effects:
            raise ConfigError("the gtsam fixed-lag backend does not take effects (got "
                              + ", ".join(e.name for e in prob.effects) + "); use backend='window', or the "
                              "batch graph of flexforce.smoother.to_gtsam")
        _load_gtsam()
        from flexforce.smoother.graph import GraphBuilder

        self.prob = prob
        self.builder = GraphBuilder(prob)
        self.lag_steps = max(1, int(round(lag / prob.dt)))
        # Half a step of margin: step j stays while t_j >= t_k - lag, without float ties.
        self.smoother: gtsam.IncrementalFixedLagSmoother | gtsam.BatchFixedLagSmoother
        if kind == "batch":
            self.smoother = gtsam.BatchFixedLagSmoother((self.lag_steps + 0.5) * prob.dt,
                                                        gtsam.LevenbergMarquardtParams() if lm_params is None
                                                        else lm_params)
        else:
            self.smoother = gtsam.IncrementalFixedLagSmoother((self.lag_steps + 0.5) * prob.dt,
                                                              _isam_params(relinearize_threshold, relinearize_skip))
        self.covariance = covariance
        n, nc = prob.n, prob.nc
        self.traj = Trajectory(np.zeros((n, 3, 3)), np.zeros((n, 15)), np.zeros((n, nc, 6)), np.zeros((n, 0)))
        self.P = np.zeros((n, prob.state_dim, prob.state_dim)) if covariance else None
        self.update_time = np.zeros(n)
        self.cov_time = np.zeros(n)
        self.k = 0
        self._last: tuple[np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------------------------------
    def _predict(self, k: int):
        p = self.prob
        if k == 0:
            R, q = p.prior_mean
            R, q = R.copy(), q.copy()
        else:
            assert self._last is not None  # set by the previous step()
            R, q = predict_step(*self._last, p.dt)
        W = p.contact_wrenches(k, R, q)
        return R, q, W

    def _read(self, j: int, full_values=None):
        sm = self.smoother
        if full_values is not None:
            pose = full_values.atPose3(gf.X(j))
            vel = full_values.atVector(gf.V(j))
            acc = full_values.atVector(gf.A(j))
        else:
            pose = sm.calculateEstimatePose3(gf.X(j))
            vel = sm.calculateEstimateVector(gf.V(j))
            acc = sm.calculateEstimateVector(gf.A(j))
        R = pose.rotation().matrix()
        self.traj.R[j] = R
        self.traj.q[j, 0:3] = pose.translation()
        self.traj.q[j, 3:9] = vel
        self.traj.q[j, 9:15] = acc
        for i in self.builder.contacts(j):
            key = gf.W(j, i)
            self.traj.W[j, i] = (full_values.atVector(key) if full_values is not None
                                 else sm.calculateEstimateVector(key))
        if self.covariance:
            t0 = time.perf_counter()
            assert self.P is not None  # allocated when covariance is set
            assert isinstance(sm, gtsam.IncrementalFixedLagSmoother)  # kind="batch" refuses covariances
            P = self.P[j]
            Cx = sm.marginalCovariance(gf.X(j))
            Ad = np.zeros((6, 6))
            Ad[:3, :3] = R
            Ad[3:, 3:] = R
            P[0:6, 0:6] = Ad @ Cx @ Ad.T
            P[6:12, 6:12] = sm.marginalCovariance(gf.V(j))
            P[12:18, 12:18] = sm.marginalCovariance(gf.A(j))
            for i in self.builder.contacts(j):
                P[S + 6 * i:S + 6 * i + 6, S + 6 * i:S + 6 * i + 6] = sm.marginalCovariance(gf.W(j, i))
            self.cov_time[j] = time.perf_counter() - t0

    def step(self) -> None:
        """Add the next sample and update (one iSAM2 update, marginalising what leaves the window)."""
        k = self.k
        p = self.prob
        t0 = time.perf_counter()
        R, q, W = self._predict(k)
        graph = gtsam.NonlinearFactorGraph()
        for f in self.builder.step_factors(k):
            graph.add(f)
        values = gtsam.Values()
        contacts = self.builder.contacts(k)
        gf.insert_state(values, k, R, q, W, contacts)
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        tk = k * p.dt
        for key in [gf.X(k), gf.V(k), gf.A(k)] + [gf.W(k, i) for i in contacts]:
            stamps.insert((key, tk))
        try:
            self.smoother.update(graph, values, stamps)
        except RuntimeError as err:
            raise EstimatorError(f"fixed-lag smoother failed at step {k} (t = {tk:.3f} s): {err}") from err
        pose = self.smoother.calculateEstimatePose3(gf.X(k))
        qn = np.concatenate([pose.translation(), self.smoother.calculateEstimateVector(gf.V(k)),
                             self.smoother.calculateEstimateVector(gf.A(k))])
        self._last = (pose.rotation().matrix(), qn)
        self.update_time[k] = time.perf_counter() - t0
        j = k - self.lag_steps
        if j >= 0:
            self._read(j)
        self.k += 1

    def finish(self) -> None:
        """Read the steps still in the window from the final estimate."""
        values = self.smoother.calculateEstimate()
        for j in range(max(0, self.k - self.lag_steps), self.k):
            self._read(j, values)


class FixedLagSmoother:
    """Own fixed-lag smoother over a window (module docstring): :meth:`step` once per sample, then
    :meth:`finish`.  Memory: ring buffers of ``lag + relinearize + report_every + block + 2`` steps."""

    def __init__(self, prob: Problem, lag: float = 1.0, relinearize: int = 6, covariance: bool = True,
                 report_every: int = 10, sink: Callable[..., None] | None = None, block: int = 1,
                 compiled: bool = True):
        """``sink``: called as ``sink(j, R, q, W, e, P)`` for each step ``j`` as it leaves the
        window (``P`` None without covariances) instead of filling :attr:`traj` and :attr:`P`:
        a stream of unknown length (:mod:`flexforce.smoother.stream`), whose problem is replaced
        part by part (:meth:`set_problem`).

        ``block``: samples per update (:attr:`FixedLagConfig.block`): :meth:`step` queues a sample
        and every ``block``-th runs one update that adds the queued samples together (each
        predicted from the one before), relinearising them with the ``relinearize`` steps
        before them.

        ``compiled``: :attr:`FixedLagConfig.compiled` (the compiled update and read-out where they
        apply; False: the general path they are tested against)."""
        check_positive("FixedLagSmoother", "lag", lag, "s", "a positive duration")
        check_int("FixedLagSmoother", "relinearize", relinearize, 1, "steps", "an integer >= 1")
        check_int("FixedLagSmoother", "report_every", report_every, 1, "updates", "an integer >= 1")
        check_int("FixedLagSmoother", "block", block, 1, "samples", "an integer >= 1")
        check_bool("FixedLagSmoother", "compiled", compiled)
        self.compiled = compiled
        """:attr:`FixedLagConfig.compiled`."""
        self.prob = prob
        self.lag_steps = max(1, int(round(lag / prob.dt)))
        self.M = int(relinearize)
        self.block = int(block)
        self.report_every = max(1, min(int(report_every), self.lag_steps))
        self.covariance = covariance
        n, nc, D, E = prob.n, prob.nc, prob.state_dim, prob.effect_dim
        self.cap = cap = self.lag_steps + self.M + self.report_every + self.block + 2
        # ring buffers (bounded memory): linearisation points, elimination, corrections
        self.Rb = np.zeros((cap, 3, 3))
        self.qb = np.zeros((cap, 15))
        self.Wb = np.zeros((cap, nc, 6))
        self.eb = np.zeros((cap, E))
        self.Ld = np.zeros((cap, D, D))
        self.C = np.zeros((cap, D, D))
        self.y = np.zeros((cap, D))
        self.Sp = np.zeros((cap, D, D))
        self.rp = np.zeros((cap, D))
        self.dx = np.zeros((cap, D))
        self.Pw = np.zeros((cap, D, D))
        # marginals: the final steps' recursion factors and block maps (window_marginals_blocked)
        self.nblk = cap // self.report_every + 2
        shape = (cap, D, D) if covariance else (0, D, D)
        self.Af, self.Gf = np.zeros(shape), np.zeros(shape)
        bshape = (self.nblk, D, D) if covariance else (0, D, D)
        self.Ab, self.Phib = np.zeros(bshape), np.zeros(bshape)
        self._final_next = 0
        self._block_next = 0
        # outputs (the Estimate, not the smoother's memory); a sink takes them instead
        self.sink = sink
        n_out = 0 if sink is not None else n
        self.traj = Trajectory(np.zeros((n_out, 3, 3)), np.zeros((n_out, 15)), np.zeros((n_out, nc, 6)),
                               np.zeros((n_out, E)))
        self.P = np.zeros((n_out, D, D)) if covariance else None
        self.successors: dict[int, Trajectory] = {}
        """Read-out boundaries: step ``j`` -> the one-step :class:`Trajectory` of step ``j + 1`` as the
        window held it when ``j`` was read out (``j + 1`` is read out later, from a later solve).
        The residual of the factor between ``j`` and ``j + 1`` is taken with it
        (:func:`~flexforce.smoother.result.boundary_residuals`).  With a ``sink`` the reader takes
        (and removes) them."""
        self.update_time = np.zeros(n_out)
        self.cov_time = np.zeros(n_out)
        self.last_update_time = 0.0
        """Wall-clock time of the last update, s (0.0 after a :meth:`step` that only queued)."""
        self.last_updated = 0
        """Samples the last :meth:`step` updated with (0: it queued its sample; ``block`` at an update)."""
        self.last_cov_time = 0.0
        self.k = 0
        """Samples taken so far (the next :meth:`step`'s)."""
        self.k_done = 0
        """Samples updated with so far (``k - k_done < block`` queued)."""
        self.next_report = 0
        e0 = np.zeros(E)
        off = 0
        for eff in prob.effects:
            e0[off:off + eff.dim] = eff.prior(prob)[0]
            off += eff.dim
        self._e0 = e0
        self._wp = window_kernel.WindowProblem(prob) if not prob.effects else None
        self._scratch: dict = {}
        self._capbuf: tuple | None = None
        # rows of the elimination's C that can be nonzero: the integration factors (the only
        # ones linking steps) touch the core state only, the effects' random walks their unknowns
        self._nz = S if not prob.effects else D
        self._no_caps = np.ones((1 + nc, 0, 2))

    def _lower_weight_caps(self, f: int, lin, new: int = 1) -> None:
        """Remember the sensors' robust weights of the steps just linearised: a sample's weight
        never rises again (IRLS with one Gauss-Newton step per update would otherwise let an
        outlier back in as the estimate drifts towards it, and freeze that drift)."""
        caps = self.prob.weight_cap
        if caps is None:
            return
        for fam, w in lin.weights.items():
            # not the newest steps (the ``new`` samples of this update): they are linearised at
            # their prediction, which a legitimate jump of the readings (a push) leaves far from
            # them; their weight is remembered once the step has been estimated.
            cap = caps.setdefault(fam, np.ones((self.prob.n, w.shape[1])))
            m = len(w) - new
            a = f - self.prob.offset
            cap[a:a + m] = np.minimum(cap[a:a + m], w[:m])

    def _state(self, k: int):
        """Current estimate of step ``k`` (in the window): linearisation point retracted by dx."""
        p = k % self.cap
        S_, nc = S, self.prob.nc
        d = self.dx[p]
        R = core.so3_exp(d[:3]) @ self.Rb[p]
        q = self.qb[p] + d[3:S_]
        W = self.Wb[p] + d[S_:S_ + 6 * nc].reshape(nc, 6)
        e = self.eb[p] + d[S_ + 6 * nc:]
        return R, q, W, e

    def _predict(self, k: int):
        p = self.prob
        if k == 0:
            R, q = p.prior_mean
            R, q = R.copy(), q.copy()
            e = self._e0.copy()
        else:
            Rp, qp, _, e = self._state(k - 1)
            R, q = predict_step(Rp, qp, p.dt)
        W = p.contact_wrenches(k - p.offset, R, q)
        return R, q, W, e

    def set_problem(self, prob: Problem) -> None:
        """Continue on ``prob``, the next part of the stream (:attr:`Problem.offset` on; it must
        hold every step still relinearised, from ``k - relinearize``, and the steps to come).
        The sensors' robust weight caps of the steps both parts hold are carried over."""
        first = self.k_done - self.M
        if prob.offset > max(first, 0):
            raise EstimatorError(f"fixed-lag smoother: the new part of the stream starts at step {prob.offset}; "
                                 f"expected at most {max(first, 0)} (the oldest step still relinearised)")
        old = self.prob
        if old.weight_cap is not None:
            caps: dict = {}
            for fam, cap in old.weight_cap.items():
                new = np.ones((prob.n, cap.shape[1]))
                a, b = max(prob.offset, old.offset), min(prob.offset + prob.n, old.offset + old.n)
                if b > a:
                    new[a - prob.offset:b - prob.offset] = cap[a - old.offset:b - old.offset]
                caps[fam] = new
            prob.weight_cap = caps
        self.prob = prob
        self._wp = window_kernel.WindowProblem(prob) if not prob.effects else None
        self._capbuf = None

    def step(self) -> None:
        """Add the next sample; at every ``block``-th, update with the queued samples: relinearise
        the newest steps, eliminate, back-substitute, read out the steps that left the window."""
        self.k += 1
        if self.k - self.k_done < self.block:
            self.last_update_time = 0.0
            self.last_updated = 0
            return
        self._update(self.k_done, self.k)

    def _update(self, k0: int, k1: int) -> None:
        """One update adding the samples ``k0 .. k1-1``."""
        prob = self.prob
        cap, M, D, R = self.cap, self.M, prob.state_dim, self.report_every
        t0 = time.perf_counter()
        frozen_first = k0 - M >= 0
        f = max(k0 - M, 0)
        if f > 0 and self._wp is not None and self.compiled:
            self._update_compiled(f, k0, k1, t0)
            return
        # relinearise the unfrozen steps at their current estimate; the new ones at their prediction
        solvers.window_retract(self.Rb, self.qb, self.Wb, self.eb, self.dx,
                               np.arange(f + 1 if frozen_first else f, k0) % cap, S)
        # the block's later samples start where its first is predicted (its state held): a
        # constant-acceleration prediction over several samples runs off (the iCub walk diverged)
        pk0 = k0 % cap
        self.Rb[pk0], self.qb[pk0], self.Wb[pk0], self.eb[pk0] = self._predict(k0)
        self.dx[pk0] = 0.0
        for k in range(k0 + 1, k1):
            pk = k % cap
            self.Rb[pk], self.qb[pk], self.Wb[pk], self.eb[pk] = self.Rb[pk0], self.qb[pk0], self.Wb[pk0], self.eb[pk0]
            self.dx[pk] = 0.0
        k = k1 - 1
        pk = k % cap
        pos = np.arange(f, k1) % cap
        traj = Trajectory(self.Rb[pos], self.qb[pos], self.Wb[pos], self.eb[pos])
        lin = linearize(prob, traj, k0=f)
        self._lower_weight_caps(f, lin, k1 - k0)
        U, gU, Fw, gF, B = assemble_split(lin, len(pos), D, skip_first_unary=frozen_first)
        m = len(pos)
        Ld = np.empty((m, D, D))
        C = np.empty((max(m - 1, 1), D, D))
        y = np.empty((m, D))
        Sp = np.empty((m, D, D))
        rp = np.empty((m, D))
        pf = pos[0]
        has_prev = (not frozen_first) and f > 0
        try:
            solvers.window_eliminate(self.Sp[pf], self.rp[pf], frozen_first, U, gU, Fw, gF,
                                     B if m > 1 else np.zeros((1, D, D)), self.C[(f - 1) % cap],
                                     self.y[(f - 1) % cap], has_prev, Ld, C, y, Sp, rp)
        except np.linalg.LinAlgError as err:
            raise EstimatorError(f"fixed-lag smoother: the window's system is not positive definite at step {k} "
                                 f"(t = {k * prob.dt:.3f} s)") from err
        self.Ld[pos] = Ld
        self.y[pos] = y
        if m > 1:
            self.C[pos[:-1]] = C[:m - 1]
        if frozen_first:
            self.Sp[pos[1:]] = Sp[1:]
            self.rp[pos[1:]] = rp[1:]
        else:
            self.Sp[pos] = Sp
            self.rp[pos] = rp
        # back substitution: the newest steps (the next relinearisation) at every update; down to
        # the oldest step read out when blocks of `report_every` steps have left the window.
        j0 = self.next_report
        j1 = j0 + R * max(0, (k - self.lag_steps - j0 + 1) // R)
        oldest = min(f, j0) if j1 > j0 else f
        order = np.arange(k, oldest - 1, -1) % cap
        solvers.window_back_substitute(self.Ld, self.C, self.y, order, self.dx)
        if not np.all(np.isfinite(self.dx[pk])):
            raise EstimatorError(f"fixed-lag smoother: non-finite estimate at step {k} (t = {k * prob.dt:.3f} s)")
        self._finish_update(k0, k1, k, j0, j1, t0)

    def _finish_update(self, k0: int, k1: int, k: int, j0: int, j1: int, t0: float) -> None:
        """The update's time; the read-outs of the steps that left the window (``j0 .. j1-1``)."""
        R = self.report_every
        self.last_update_time = time.perf_counter() - t0
        self.last_updated = k1 - k0
        self.k_done = k1
        if self.sink is None:
            self.update_time[k0:k1] = self.last_update_time / (k1 - k0)
        cov_time = 0.0
        for a in range(j0, j1, R):
            if self.covariance:
                self._covariances(k, a, a + R)
                cov_time += self.last_cov_time
            self._report(a, a + R)
        self.last_cov_time = cov_time
        self.next_report = j1

    def _update_compiled(self, f: int, k0: int, k1: int, t0: float) -> None:
        """:meth:`_update` in one compiled call (:func:`window_kernel.window_update`): the same
        operations in the same order, without the Python work per family and per step."""
        prob, R = self.prob, self.report_every
        wp = self._wp
        assert wp is not None
        k = k1 - 1
        m = k1 - f
        bufs = self._scratch.get(m)
        if bufs is None:
            nc, D = prob.nc, prob.state_dim
            bufs = (np.empty((m, D, D)), np.empty((m, D)), np.empty((m, D, D)), np.empty((m, D)),
                    np.empty((max(m - 1, 1), D, D)), np.empty((m, 1 + nc, 2)), np.empty((m, 1 + nc, 2)))
            self._scratch[m] = bufs
        capbuf = self._weight_caps()
        j0 = self.next_report
        j1 = j0 + R * max(0, (k - self.lag_steps - j0 + 1) // R)
        oldest = min(f, j0) if j1 > j0 else f
        try:
            ok = window_kernel.window_update(self.Rb, self.qb, self.Wb, self.dx, self.Ld, self.C, self.y, self.Sp,
                                             self.rp, f, k0, k1, oldest, prob.offset, *wp.args,
                                             self._no_caps if capbuf is None else capbuf, capbuf is not None, *bufs)
        except np.linalg.LinAlgError as err:
            raise EstimatorError(f"fixed-lag smoother: the window's system is not positive definite at step {k} "
                                 f"(t = {k * prob.dt:.3f} s)") from err
        if not ok:
            raise EstimatorError(f"fixed-lag smoother: non-finite estimate at step {k} (t = {k * prob.dt:.3f} s)")
        self._finish_update(k0, k1, k, j0, j1, t0)

    def _weight_caps(self):
        """The sensors' weight caps as one array (1 + C, steps, 2) for the compiled update, the
        entries of ``prob.weight_cap`` its views (None: the problem keeps no caps)."""
        prob = self.prob
        stored = prob.weight_cap
        if stored is None or self._wp is None or not self._wp.robust:
            return None
        if self._capbuf is not None and self._capbuf[0] is stored:
            return self._capbuf[1]
        buf = np.ones((1 + prob.nc, prob.n, 2))  # no cap: 1 (a robust weight is at most 1)
        fams = ("imu",) + tuple(f"ft/{i}" for i in range(prob.nc) if prob.use_ft)
        for j, fam in enumerate(fams):
            c = stored.get(fam)
            if c is not None:
                buf[j] = c
            stored[fam] = buf[j]
        self._capbuf = (stored, buf)
        return buf

    def _covariances(self, k: int, j0: int, j1: int) -> None:
        """Window marginals (timed apart); kept for steps ``j0 .. j1-1``.

        At a read-out (the ``report_every`` steps ``j0 .. j1-1`` of one block, all final: their
        elimination no longer changes) the recursion from the newest step crosses the final steps
        by the maps of whole blocks, each composed once (:func:`solvers.window_marginals_blocked`);
        otherwise (the last read-out, a lag shorter than ``relinearize``) step by step."""
        t0 = time.perf_counter()
        R, cap = self.report_every, self.cap
        hi = k - self.M  # the newest step whose elimination is final
        if j1 - j0 == R and j0 % R == 0 and j1 - 1 <= hi and not self.compiled:
            start = max(self._final_next, j0)
            if hi >= start:
                solvers.window_final_factors(self.Ld, self.C, np.arange(start, hi + 1) % cap, self.Af, self.Gf)
            self._final_next = hi + 1
            b = j0 // R
            newest_block = (hi + 1) // R - 1
            for bb in range(max(self._block_next, b + 1), newest_block + 1):
                solvers.window_block_map(self.Af, self.Gf, np.arange(bb * R, bb * R + R) % cap, self.Ab, self.Phib,
                                         bb % self.nblk)
            self._block_next = max(self._block_next, newest_block + 1)
            top = max(newest_block, b)
            solvers.window_marginals_blocked(self.Ld, self.C, np.arange(k, hi, -1) % cap, self.Af, self.Gf,
                                             np.arange(hi, (top + 1) * R - 1, -1) % cap, self.Ab, self.Phib,
                                             np.arange(top, b, -1) % self.nblk, np.arange(j1 - 1, j0 - 1, -1) % cap,
                                             self.Pw)
        elif j1 - j0 == R and j0 % R == 0 and j1 - 1 <= hi:
            start = max(self._final_next, j0)
            self._final_next = hi + 1
            b = j0 // R
            newest_block = (hi + 1) // R - 1
            bb0 = max(self._block_next, b + 1)
            self._block_next = max(self._block_next, newest_block + 1)
            top = max(newest_block, b)
            window_kernel.window_covariances(self.Ld, self.C, self.Af, self.Gf, self.Ab, self.Phib, self.Pw, k, hi,
                                             start, bb0, newest_block + 1, top, b, j0, j1, R, self._nz)
        else:
            order = np.arange(k, j0 - 1, -1) % cap
            solvers.window_marginals(self.Ld, self.C, order, self.Pw)
        self.last_cov_time = time.perf_counter() - t0
        if self.sink is None:
            self.cov_time[k] += self.last_cov_time

    def _report(self, j0: int, j1: int) -> None:
        """Report steps ``j0 .. j1-1`` (to the sink, or into :attr:`traj` and :attr:`P`)."""
        n, nc, E = j1 - j0, self.prob.nc, self.prob.effect_dim
        R, q, W, e = np.empty((n, 3, 3)), np.empty((n, 15)), np.empty((n, nc, 6)), np.empty((n, E))
        window_kernel.window_states(self.Rb, self.qb, self.Wb, self.eb, self.dx, j0, j1, R, q, W, e)
        cap = self.cap
        if j1 < self.k:  # the next step stays in the window: keep it as this solve has it
            nxt = Trajectory(np.empty((1, 3, 3)), np.empty((1, 15)), np.empty((1, nc, 6)), np.empty((1, E)))
            window_kernel.window_states(self.Rb, self.qb, self.Wb, self.eb, self.dx, j1, j1 + 1,
                                        nxt.R, nxt.q, nxt.W, nxt.e)
            self.successors[j1 - 1] = nxt
        if self.sink is not None:
            for j in [j for j in self.successors if j < j0 - self.cap]:  # not taken by the sink's reader
                del self.successors[j]
            for i in range(n):
                j = j0 + i
                self.sink(j, R[i], q[i], W[i], e[i], self.Pw[j % cap].copy() if self.covariance else None)
            return
        self.traj.R[j0:j1], self.traj.q[j0:j1], self.traj.W[j0:j1], self.traj.e[j0:j1] = R, q, W, e
        if self.covariance:
            assert self.P is not None  # allocated when covariance is set
            self.P[j0:j1] = self.Pw[np.arange(j0, j1) % cap]

    def finish(self) -> None:
        """Update with the samples still queued, then report the steps still in the window (and any
        not yet read out) from the final estimate."""
        if self.k == 0:
            return
        if self.k_done < self.k:
            self._update(self.k_done, self.k)
        j0 = self.next_report
        order = np.arange(self.k - 1, j0 - 1, -1) % self.cap
        solvers.window_back_substitute(self.Ld, self.C, self.y, order, self.dx)
        if self.covariance:
            self._covariances(self.k - 1, j0, self.k)
        if self.k > j0:
            self._report(j0, self.k)


@dataclass(frozen=True)
class FixedLagConfig:
    """Options of the fixed-lag smoother (:func:`run_fixed_lag`); every field is checked on
    construction (a :class:`~flexforce.errors.ConfigError` naming the option, its value, its unit and
    what is expected)."""

    lag: float = 1.0
    """Smoothing window, s (> 0): each step is reported smoothed with at least ``lag`` of future
    data; rounded to a whole number of samples, at least one."""
    backend: str = "window"
    """``window`` (own incremental square-root smoother, effects supported) or ``gtsam`` (iSAM2's
    IncrementalFixedLagSmoother, the reference; no effects)."""
    relinearize: int = 6
    """Window backend: steps relinearised per update, the newest included (count, >= 1): each step
    takes part in ``relinearize`` Gauss-Newton passes as it ages, then its linearisation point is
    frozen.  Cost per update O(relinearize D^3), independent of the lag.  Why 6: a touch-down is
    far from its linearisation point (docs/smoother.md, "Fixed-lag")."""
    report_every: int = 10
    """Window backend: updates between read-outs of the window (count, >= 1; capped at the lag in
    samples).  Output latency: ``lag`` plus up to ``report_every - 1`` samples."""
    block: int = 1
    """Window backend: samples added per update (count, >= 1).  1: one update per sample.  B > 1:
    the samples wait until B have come, then one update adds them together (the first predicted
    from the previous estimate, the others starting at that prediction), relinearising them with
    the ``relinearize`` steps before them: the per-update cost is paid once per B samples.  The
    estimate changes: each step takes part in about ``relinearize / B + 1`` Gauss-Newton passes
    instead of ``relinearize`` (less accurate at touch-downs: docs/smoother.md, "Fixed-lag");
    latency grows by up to ``B - 1`` samples.  ``Estimate.time_per_step``: each update's time
    shared among its samples."""
    relinearize_threshold: float | None = None
    """Gtsam backend: iSAM2's relinearisation threshold on every variable's tangent delta (rad, m,
    m/s, N mixed; > 0).  None: the per-type thresholds of :data:`RELINEARIZE_THRESHOLD`."""
    relinearize_skip: int = 10
    """Gtsam backend: iSAM2 checks for relinearisation every ``relinearize_skip`` updates (count, >= 1)."""
    covariance: bool = True
    """Extract the marginal covariances (timed apart from the updates)."""
    footholds: bool = False
    """Estimate every contact episode's rest placement (foothold) with the trajectory, from the leg
    kinematics at its touch-down and the ground plane (:mod:`flexforce.factors.footholds`, priors
    from the model's ``foothold_prior``); False: the rest placements are the given ones."""
    rule: NoiseRule = field(default_factory=NoiseRule)
    """The noise rule of the model-error families (:class:`~flexforce.smoother.problem.NoiseRule`)."""
    compiled: bool = True
    """Window backend: use the compiled update (:func:`flexforce.smoother.window_kernel.window_update`)
    where it applies (no effects, past the stream's first ``relinearize`` steps) and the compiled
    read-out marginals (:func:`~flexforce.smoother.window_kernel.window_covariances`); False: the
    general linearisation and the marginals step by step.  Both give the same estimates and
    covariances (``tests/test_window_update.py``); False is the reference path for tests."""

    def __post_init__(self):
        o = "FixedLagConfig"
        check_positive(o, "lag", self.lag, "s", "a positive duration")
        check_choice(o, "backend", self.backend, ("window", "gtsam"))
        check_int(o, "relinearize", self.relinearize, 1, "steps", "an integer >= 1 (steps relinearised per update)")
        check_int(o, "report_every", self.report_every, 1, "updates", "an integer >= 1")
        check_int(o, "block", self.block, 1, "samples", "an integer >= 1 (samples added per update)")
        check_positive(o, "relinearize_threshold", self.relinearize_threshold, "", "a positive number or None",
                       optional=True)
        check_int(o, "relinearize_skip", self.relinearize_skip, 1, "updates", "an integer >= 1")
        check_bool(o, "covariance", self.covariance)
        check_bool(o, "footholds", self.footholds)
        check_type(o, "rule", self.rule, NoiseRule)
        check_bool(o, "compiled", self.compiled)


def run_fixed_lag(rec: Recording, model: ModelConfig, config: FixedLagConfig = FixedLagConfig(), rest_p=None,
                  rest_R=None, progress: Callable[[float], None] | None = None, **options) -> Estimate:
    """Fixed-lag smoothing of a Recording, one update per sample; returns an :class:`Estimate`.

    Args:
        rec: the Recording.
        model: the ModelConfig (contact parameters, sensor noise, ``use_ft``, ``effects``).
        config: a :class:`FixedLagConfig` (lag, backend and its settings, covariance, noise rule).
        rest_p, rest_R: (N, C, 3), (N, C, 3, 3) the contacts' rest placements in the world per step
            (footholds); default the recording's local placements (:meth:`Problem.build`).
        progress: called with the fraction done.
        options: fields of :class:`FixedLagConfig` replacing those of ``config`` (the older calling
            convention, ``run_fixed_lag(rec, model, lag=0.5)``; ``rule=None`` is the default rule).

    ``Estimate.time_per_step`` holds the wall-clock time of each update (prediction,
    linearisation, elimination, back substitution); the covariance extraction is in
    ``meta["cov_time_median_s"]`` (window backend: the mean per update, amortised).

    Raises:
        ConfigError: ``config`` is not a FixedLagConfig, an unknown option (the known ones listed),
            or a bad value.
    """
    config = configured(config, FixedLagConfig, options, "fixed-lag smoother")
    lag, backend, covariance = config.lag, config.backend, config.covariance
    t0 = time.perf_counter()
    prob = build_problem(rec, model, config, rest_p, rest_R)
    prob.weight_cap = {}  # the sensors' robust weights only fall (FixedLagSmoother._lower_weight_caps)
    fls: FixedLagSmoother | GtsamFixedLagSmoother
    if backend == "window":
        fls = FixedLagSmoother(prob, lag, relinearize=config.relinearize, covariance=covariance,
                               report_every=config.report_every, block=config.block, compiled=config.compiled)
    else:
        fls = GtsamFixedLagSmoother(prob, lag, config.relinearize_threshold, config.relinearize_skip, covariance)
    for k in range(prob.n):
        fls.step()
        if progress is not None and k % 50 == 0:
            progress(0.95 * k / prob.n)
    fls.finish()
    cov_stat = (float(np.median(fls.cov_time)) if backend == "gtsam" else float(np.mean(fls.cov_time)))
    successors = fls.successors if isinstance(fls, FixedLagSmoother) else None
    est = make_estimate(prob, "fixed_lag", fls.traj, fls.P, time_per_step=fls.update_time, successors=successors,
                        meta={"lag_s": fls.lag_steps * prob.dt, "use_ft": prob.use_ft, "backend": backend,
                              "cov_time_median_s": cov_stat if covariance else None,
                              "covariance": ("per-key marginals (no cross-covariance between keys)"
                                             if backend == "gtsam"
                                             else "per-step marginals of the window (joint within a step)")})
    est.total_time = time.perf_counter() - t0
    if progress is not None:
        progress(1.0)
    return est
