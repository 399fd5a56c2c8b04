"""From a smoothed trajectory to the common :class:`Estimate`: wrenches, CoP, covariances, residuals."""

from __future__ import annotations

import inspect

import numpy as np

from flexforce.datasets import faults
from flexforce.datasets.estimate import Estimate
from flexforce.factors import core
from flexforce.factors.contact_limits import balance_near_switches, limit_world_wrenches
from flexforce.factors.physics import COP_MIN_FORCE
from flexforce.smoother.linearize import Trajectory, linearize

S = core.STATE_DIM
_AX = ("x", "y", "z")
WRENCH_LABELS = tuple(f"F_{a} [N]" for a in _AX) + tuple(f"T_{a} [N m]" for a in _AX)
RESIDUAL_LABELS = {
    "integration": (tuple(f"theta_{a} [rad]" for a in _AX) + tuple(f"t_{a} [m]" for a in _AX)
                    + tuple(f"w_{a} [rad/s]" for a in _AX) + tuple(f"v_{a} [m/s]" for a in _AX)),
    "newton_euler": WRENCH_LABELS,
    "imu": tuple(f"gyro_{a} [rad/s]" for a in _AX) + tuple(f"acc_{a} [m/s^2]" for a in _AX),
}
"""Axis labels (with the unit of the unwhitened residual) of the per-step families; ``contact``
and ``ft`` have ``"<contact> F_x [N]"``-style labels, six per contact."""


def residual_labels(prob) -> dict[str, tuple[str, ...]]:
    labels = dict(RESIDUAL_LABELS)
    per_contact = tuple(f"{name} {lab}" for name in prob.rec.contact_names for lab in WRENCH_LABELS)
    labels["contact"] = per_contact
    if prob.use_ft:
        labels["ft"] = per_contact
    return labels


def family_residuals(prob, traj: Trajectory, successors: dict[int, Trajectory] | None = None) -> dict[str, np.ndarray]:
    """Whitened residual of every family per step and axis, NaN where the family is absent.

    ``integration`` at step k is the factor between k and k+1 (the last step has none); where
    ``successors`` holds step k (a fixed-lag read-out boundary: k and k+1 left the window from
    different solves), the factor is taken with k+1 as the solve that read out k had it
    (:func:`boundary_residuals`).  ``contact`` and ``ft`` are NaN where the contact is inactive.
    """
    k0 = int(getattr(prob, "offset", 0))
    lin = linearize(prob, traj, k0=k0, robust=False)
    n, nc = prob.n, prob.nc
    out = {}
    r_int = np.full((n, 12), np.nan)
    if n > 1:
        r_int[:-1] = lin.binary["integration"][0]
    for k, r in boundary_residuals(prob, traj, successors or {}, k0).items():
        r_int[k] = r
    out["integration"] = r_int
    out["newton_euler"] = lin.unary["newton_euler"][0].copy()
    out["imu"] = np.where(prob.imu_use > 0, lin.unary["imu"][0], np.nan)  # NaN: missing or saturated
    rc = np.full((n, 6 * nc), np.nan)
    for i in range(nc):
        r = lin.unary[f"contact/{i}"][0]
        rc[:, 6 * i:6 * i + 6] = np.where(prob.active[:, i, None], r, np.nan)
    out["contact"] = rc
    if prob.use_ft:
        rf = np.full((n, 6 * nc), np.nan)
        for i in range(nc):
            r = lin.unary[f"ft/{i}"][0]
            measured = prob.active[:, i, None] & np.isfinite(prob.y_ft[:, i])
            rf[:, 6 * i:6 * i + 6] = np.where(measured, r, np.nan)
        out["ft"] = rf
    return out


_INTEGRATION = frozenset({"integration"})


def boundary_residuals(prob, traj: Trajectory, successors: dict[int, Trajectory], k0: int = 0) -> dict[int, np.ndarray]:
    """Step k -> the whitened integration residual (12,) between ``traj``'s step k and
    ``successors[k]``, its successor as one solve had it.

    A fixed-lag smoother reads its window out in blocks: the last step of a block and the first of
    the next come from solves ``report_every`` samples apart, so the factor between them, evaluated
    on the read-out trajectory, compares two estimates rather than the model with the data
    (hundreds of sigmas where the flexibility moves).  Taken within one solve it is the factor the
    smoother fitted."""
    out = {}
    for k, nxt in successors.items():
        if not 0 <= k < prob.n - 1:
            continue
        pair = Trajectory(np.concatenate([traj.R[k:k + 1], nxt.R]), np.concatenate([traj.q[k:k + 1], nxt.q]),
                          np.concatenate([traj.W[k:k + 1], nxt.W]), np.concatenate([traj.e[k:k + 1], nxt.e]))
        out[k] = linearize(prob, pair, k0=k0 + k, robust=False, families=_INTEGRATION).binary["integration"][0][0]
    return out


def residual_sigmas(prob, residuals: dict) -> dict[str, np.ndarray]:
    """The per-axis noise standard deviation behind each family's whitened residual, in the unit of
    its labels (:attr:`Estimate.residual_sigma`).

    Newton-Euler and contact residuals are whitened with a full covariance (force and moment are
    correlated); their standard deviations make the force rows exact and the moment rows an
    approximation (the moment left once the force is explained is smaller).
    """
    sig = prob.sigmas
    per = {"imu": sig.imu, "newton_euler": sig.newton_euler,
           "integration": np.sqrt(np.diag(sig.integration_cov)),
           "contact": np.tile(sig.contact, prob.nc), "ft": np.tile(sig.ft, prob.nc)}
    return {fam: np.asarray(per[fam], dtype=float).copy() for fam, r in residuals.items()
            if fam in per and len(per[fam]) == r.shape[1]}


def rejected_samples(prob, residuals: dict) -> list[dict]:
    """The sensor samples the smoother gave less weight (:mod:`flexforce.datasets.faults`): missing
    and saturated IMU axes (weight 0), and the IMU and F/T sensors whose whitened 3-D residual
    at the estimate lies beyond the robust loss's threshold (with their robust weight)."""
    time_s = prob.rec.time
    y = np.concatenate([prob.rec.gyro, prob.rec.accel], axis=1)
    out = faults.masked_entries(time_s, y, prob.imu_missing, prob.imu_saturated)
    sig = prob.sigmas
    if sig.imu_robust is None:
        return out
    blocks = [(name, residuals["imu"][:, sl]) for name, sl in faults.IMU_SENSORS]
    if prob.use_ft and "ft" in residuals:
        for i, cname in enumerate(prob.rec.contact_names):
            rf = residuals["ft"][:, 6 * i:6 * i + 6]
            blocks += [(f"ft/{cname}/force", rf[:, :3]), (f"ft/{cname}/torque", rf[:, 3:])]
    for name, r in blocks:
        norm = np.sqrt(np.nansum(r * r, axis=1))
        w, _ = faults.robust_weights(norm, sig.imu_robust, sig.imu_robust_k)
        for k in np.flatnonzero(norm > sig.imu_robust_k):
            out.append(faults.entry(time_s[k], k, name, "norm", "outlier", norm[k], w[k]))
    out.sort(key=lambda e: (e["step"], e["sensor"]))
    return out


def call_report(eff, values, cov, t):
    """``eff.report(values, cov)``, with ``t=`` (s) when the effect's report accepts it."""
    try:
        params = inspect.signature(eff.report).parameters
    except (TypeError, ValueError):
        params = {}
    if "t" in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return eff.report(values, cov, t=t)
    return eff.report(values, cov)


def unexplained_force(prob, residuals: dict) -> np.ndarray:
    """(N, 3) world force the Newton-Euler factor leaves unexplained (required by the motion, beyond
    the contact wrenches and the effects): the force rows of its whitened residual, unwhitened."""
    r = residuals["newton_euler"]
    L = np.linalg.inv(prob.ne_whitener)  # the covariance's Cholesky factor
    return r @ L.T[:, :3]


def make_estimate(prob, name: str, traj: Trajectory, P: np.ndarray | None = None,
                  time_per_step: np.ndarray | None = None, total_time: float = 0.0,
                  meta: dict | None = None, successors: dict[int, Trajectory] | None = None,
                  switch_near: np.ndarray | None = None) -> Estimate:
    """Assemble the Estimate of ``traj``; ``P`` (N, D, D) are the per-step marginal covariances;
    ``successors``: a fixed-lag smoother's read-out boundaries (:func:`family_residuals`);
    ``switch_near``: (N,) the steps near a contact switch, when the recording is a part of a longer
    one (:func:`~flexforce.factors.contact_limits.balance_near_switches`)."""
    n, nc = prob.n, prob.nc
    rec = prob.rec
    W = np.where(prob.active[:, :, None], traj.W, 0.0)
    residuals = family_residuals(prob, traj, successors)
    # With the footholds estimated a landing's rest placement is an unknown of its own: the law's
    # forces are then kept at the switches too.
    window = float(getattr(prob.model, "switch_window", 0.0))
    balanced = None
    if window > 0 and not any(e.name == "foothold" for e in prob.effects):
        W, balanced = balance_near_switches(traj.R, traj.q[:, 0:3], W, unexplained_force(prob, residuals), rec,
                                            window, near=switch_near)
    W, excess, limits = limit_world_wrenches(traj.R, traj.q[:, 0:3], W, rec, prob.model)
    total = W.sum(axis=1)
    cop = np.empty((n, 3))
    cop_J = np.empty((n, 3, 6))
    core.centers_of_pressure(np.ascontiguousarray(total, dtype=float), 0.0, COP_MIN_FORCE, cop, cop_J)
    cov = wrench_cov = cop_cov = contact_wrench_cov = None
    if P is not None:
        cov = P[:, :S, :S].copy()
        A = np.zeros((6, prob.state_dim))
        for i in range(nc):
            A[:, S + 6 * i:S + 6 * i + 6] = np.eye(6)
        # Inactive contacts are held at zero: drop them from the sum.
        wrench_cov = np.empty((n, 6, 6))
        for i_mask in np.unique(prob.active, axis=0):
            sel = np.all(prob.active == i_mask, axis=1)
            Ak = A.copy()
            for i in range(nc):
                if not i_mask[i]:
                    Ak[:, S + 6 * i:S + 6 * i + 6] = 0.0
            wrench_cov[sel] = Ak @ P[sel] @ Ak.T
        contact_wrench_cov = np.zeros((n, nc, 6, 6))
        for i in range(nc):
            b = slice(S + 6 * i, S + 6 * i + 6)
            contact_wrench_cov[:, i] = np.where(prob.active[:, i, None, None], P[:, b, b], 0.0)
        Jc = cop_J[:, :2, :]
        cop_cov = Jc @ wrench_cov @ Jc.transpose(0, 2, 1)
    effects = {}
    off = S + 6 * nc
    eoff = 0
    for eff in prob.effects:
        vals = traj.e[:, eoff:eoff + eff.dim]
        ecov = P[:, off:off + eff.dim, off:off + eff.dim] if P is not None else None
        effects[eff.name] = call_report(eff, vals, ecov, (rec.t_ns - rec.t_ns[0]) * 1e-9)
        off += eff.dim
        eoff += eff.dim
    meta = dict(meta or {})
    if balanced is not None:
        meta["switch_balance"] = balanced
    if limits is not None:
        meta["contact_limits"] = limits
    meta["rejected"] = rejected_samples(prob, residuals)
    faults.warn_summary(name, meta["rejected"], stacklevel=4)
    meta.setdefault("noise", {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                              for k, v in prob.sigmas.derivation.items()})
    return Estimate(
        estimator=name, t_ns=rec.t_ns.copy(), contact_names=tuple(rec.contact_names),
        R=traj.R.copy(), t=traj.q[:, 0:3].copy(), w=traj.q[:, 3:6].copy(), v=traj.q[:, 6:9].copy(),
        dw=traj.q[:, 9:12].copy(), a=traj.q[:, 12:15].copy(), wrench=W, wrench_excess=excess, cop=cop,
        cov=cov, wrench_cov=wrench_cov, contact_wrench_cov=contact_wrench_cov, cop_cov=cop_cov,
        residuals=residuals, residual_labels=residual_labels(prob), residual_sigma=residual_sigmas(prob, residuals),
        time_per_step=time_per_step, total_time=float(total_time), effects=effects, meta=meta)
