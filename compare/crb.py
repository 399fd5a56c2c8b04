"""Efficiency reference: the Cramér–Rao bound of the batch smoothing problem.

The information matrix of the factor graph, evaluated at the ground truth, is the Fisher
information of the whole trajectory under the smoother's probabilistic model (sensor noise plus
the model-error families of :mod:`flexforce.smoother.problem`).  Its inverse bounds the covariance
of any unbiased estimator under that model; its per-step marginal blocks give lower bounds on the
RMSE of each quantity:

- rotation and translation: ``sqrt(mean_k trace P_k)`` of the (theta) and (t) blocks;
- total force and moment: the sum of the contact-wrench blocks (all cross terms included);
- CoP: the total wrench's bound through the CoP Jacobian.

An estimator whose RMSE is close to the bound is efficient; far above it, it leaves information
unused.  The bound is that of the smoother's model: the simulator's world has no process noise,
so an estimator can come under it only through luck or a prior tighter than the model's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flexforce.factors.physics import center_of_pressure


@dataclass
class CramerRao:
    """RMSE lower bounds (same keys as the metrics' ``rmse``) and the per-step marginals."""

    rmse_bound: dict[str, float | None] = field(default_factory=dict)
    rotation_std: np.ndarray | None = None
    """(N,) sqrt of the trace of the rotation block, rad."""
    force_std: np.ndarray | None = None
    """(N,) sqrt of the trace of the total-force block, N."""

    def efficiency(self, rmse: dict) -> dict[str, float | None]:
        """RMSE divided by its bound (1: efficient)."""
        out = {}
        for key, bound in self.rmse_bound.items():
            value = rmse.get(key)
            out[key] = value / bound if value is not None and bound else None
        return out


def cramer_rao(rec, model, skip: float = 0.5) -> CramerRao:
    """The bound for a simulated recording (one that carries ground truth)."""
    from flexforce.smoother.linearize import Trajectory, assemble, linearize, solve
    from flexforce.smoother.problem import Problem

    tr = rec.truth
    if tr is None:
        raise ValueError("the Cramér–Rao bound needs a recording with ground truth")
    prob = Problem.build(rec, model)
    n, nc = rec.n, len(rec.contact_names)
    q = np.concatenate([tr.t, tr.w, tr.v, tr.dw, tr.a], axis=1)
    W = tr.wrench * rec.contact_active[:, :, None]
    traj = Trajectory(tr.R.copy(), q, W.copy(), np.zeros((n, prob.effect_dim)))
    lin = linearize(prob, traj)
    Hd, B, g = assemble(lin, n, prob.state_dim)
    _, P = solve(Hd, B, g, want_cov=True)
    keep = rec.time >= skip
    rot = np.sqrt(np.trace(P[:, 0:3, 0:3], axis1=1, axis2=2))
    trans = np.sqrt(np.trace(P[:, 3:6, 3:6], axis1=1, axis2=2))
    S = 18
    sel = np.zeros((6, prob.state_dim))
    for i in range(nc):
        sel[:, S + 6 * i:S + 6 * i + 6] = np.eye(6)
    Pw = sel @ P @ sel.T  # (N, 6, 6) total contact wrench
    force = np.sqrt(np.trace(Pw[:, :3, :3], axis1=1, axis2=2))
    moment = np.sqrt(np.trace(Pw[:, 3:, 3:], axis1=1, axis2=2))
    cop = np.full(n, np.nan)
    for k in range(n):
        _, Jc = center_of_pressure(tr.total_wrench[k], z0=0.0, jacobian=True)
        if np.all(np.isfinite(Jc)):
            cop[k] = np.sqrt(np.trace(Jc[:2] @ Pw[k] @ Jc[:2].T))

    def rms(x):
        x = x[keep & np.isfinite(x)]
        return float(np.sqrt(np.mean(x * x))) if x.size else None

    bound = {"force_N": rms(force), "moment_Nm": rms(moment), "cop_m": rms(cop), "rotation_rad": rms(rot),
             "translation_m": rms(trans), "hand_m": None}
    return CramerRao(rmse_bound=bound, rotation_std=rot, force_std=force)
