r"""Fixed-lag smoothing for online use: gtsam's IncrementalFixedLagSmoother, one update per sample.

Each sample adds the step's variables (predicted from the previous step by the integration model)
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
from typing import Callable

import gtsam
import numpy as np

from flexforce.errors import EstimatorError
from flexforce.factors import gtsam_factors as gf
from flexforce.factors import kernels
from flexforce.smoother.graph import GraphBuilder
from flexforce.smoother.linearize import Trajectory
from flexforce.smoother.problem import NoiseRule, Problem
from flexforce.smoother.result import make_estimate

S = kernels.STATE_DIM


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


class FixedLagSmoother:
    """Online smoother: call :meth:`step` once per sample (in order), then :meth:`finish`."""

    def __init__(self, prob: Problem, lag: float = 1.0, relinearize_threshold: float | None = None,
                 relinearize_skip: int = 10, covariance: bool = True):
        if not lag > 0:
            raise EstimatorError(f"fixed-lag smoother: lag must be positive (s), got {lag}")
        self.prob = prob
        self.builder = GraphBuilder(prob)
        self.lag_steps = max(1, int(round(lag / prob.dt)))
        # Half a step of margin: step j stays while t_j >= t_k - lag, without float ties.
        self.smoother = gtsam.IncrementalFixedLagSmoother((self.lag_steps + 0.5) * prob.dt,
                                                          _isam_params(relinearize_threshold, relinearize_skip))
        self.covariance = covariance
        n, nc = prob.n, prob.nc
        self.traj = Trajectory(np.zeros((n, 3, 3)), np.zeros((n, 15)), np.zeros((n, nc, 6)), np.zeros((n, 0)))
        self.P = np.zeros((n, prob.state_dim, prob.state_dim)) if covariance else None
        self.update_time = np.zeros(n)
        self.cov_time = np.zeros(n)
        self.k = 0
        self._last = None

    # ------------------------------------------------------------------------------------------
    def _predict(self, k: int):
        p = self.prob
        if k == 0:
            R, q = p.prior_mean
            R, q = R.copy(), q.copy()
        else:
            Rp, qp = self._last
            dt = p.dt
            w, v, dw, a = qp[3:6], qp[6:9], qp[9:12], qp[12:15]
            R = kernels.so3_exp(w * dt + 0.5 * dw * dt * dt) @ Rp
            q = qp.copy()
            q[0:3] = qp[0:3] + v * dt + 0.5 * a * dt * dt
            q[3:6] = w + dw * dt
            q[6:9] = v + a * dt
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
            self.traj.W[j, i] = full_values.atVector(key) if full_values is not None else sm.calculateEstimateVector(key)
        if self.covariance:
            t0 = time.perf_counter()
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


def run_fixed_lag(rec, model, progress: Callable[[float], None] | None = None, lag: float = 1.0,
                  rule: NoiseRule | None = None, relinearize_threshold: float | None = None,
                  relinearize_skip: int = 10, covariance: bool = True, **options):
    """Fixed-lag smoothing of a Recording, one update per sample; returns an :class:`Estimate`.

    Args:
        lag: smoothing window, s (1 s by default).
        rule: the noise rule of the model-error families (default :class:`NoiseRule`).
        relinearize_threshold, relinearize_skip: iSAM2's relinearisation settings.
        covariance: extract the marginal covariances (timed apart from the updates).

    ``Estimate.time_per_step`` holds the wall-clock time of each update (prediction, factor
    creation and the iSAM2 update); the covariance extraction is in ``meta["cov_time_median_s"]``.
    """
    if options:
        raise EstimatorError(f"fixed-lag smoother: unknown option(s) {sorted(options)}; known: lag, rule, "
                             "relinearize_threshold, relinearize_skip, covariance")
    t0 = time.perf_counter()
    prob = Problem.build(rec, model, rule or NoiseRule())
    fls = FixedLagSmoother(prob, lag, relinearize_threshold, relinearize_skip, covariance)
    for k in range(prob.n):
        fls.step()
        if progress is not None and k % 50 == 0:
            progress(0.95 * k / prob.n)
    fls.finish()
    est = make_estimate(prob, "fixed_lag", fls.traj, fls.P, time_per_step=fls.update_time,
                        meta={"lag_s": fls.lag_steps * prob.dt, "use_ft": prob.use_ft,
                              "cov_time_median_s": float(np.median(fls.cov_time)) if covariance else None,
                              "covariance": "per-key marginals (no cross-covariance between keys)"})
    est.total_time = time.perf_counter() - t0
    if progress is not None:
        progress(1.0)
    return est
