r"""A user-written effect, written against the Effect protocol alone (docs/diagnostics.md).

A *drifting gyro bias*: an old MEMS gyro warms up after power-on and its bias moves, near enough
linearly over a few seconds:

.. math::  b(t) = b_0 + t\, b_1 \qquad (b_0 \text{ in rad/s},\ b_1 \text{ in rad/s}^2,\ \text{IMU axes})

Six constant unknowns ``e = (b_0, b_1)``.  The IMU residual is ``predicted - measured`` with the
gyro in rows 0-2, so the bias adds to the prediction: ``dr[:3] = b_0 + t_k b_1``.  It does not
depend on the core state (``dr_ds = 0``); ``dr_de = [I, t_k I]``.

Use it with ``flexforce diagnose REC -o DIR --plugin docs/example_effect.py`` (ranked like the
built-in effects, with the same criterion) or ``diagnose(rec, candidates=[GyroDrift, ...])``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the protocol's view of the problem (flexforce.factors.effects); typing only
    from flexforce.factors.effects import ProblemView


class GyroDrift:
    """Gyro bias drifting linearly in time: ``b(t) = b0 + t b1`` (IMU axes)."""

    name = "gyro-drift"
    dim = 6
    labels = ("b0_x [rad/s]", "b0_y [rad/s]", "b0_z [rad/s]",
              "b1_x [rad/s^2]", "b1_y [rad/s^2]", "b1_z [rad/s^2]")

    def prior(self, problem: ProblemView):
        """Zero mean; 0.1 rad/s for the bias, 0.01 rad/s^2 for its drift (loose for a MEMS gyro)."""
        return np.zeros(6), np.array([0.1] * 3 + [0.01] * 3)

    def random_walk_sigma(self, problem: ProblemView):
        """Constants: a numerically tight random walk."""
        return np.full(6, 1e-8)

    def residual_terms(self, family, problem: ProblemView, steps, R, q, W, e):
        if family != "imu":
            return None
        t = (np.asarray(steps, dtype=float) * problem.dt)[:, None]
        n = len(steps)
        dr = np.zeros((n, 6))
        dr[:, :3] = e[:, :3] + t * e[:, 3:]
        dr_de = np.zeros((n, 6, 6))
        dr_de[:, :3, :3] = np.eye(3)
        dr_de[:, :3, 3:] = t[:, :, None] * np.eye(3)
        return dr, np.zeros((n, 6, 18)), dr_de

    def report(self, values, cov):
        value = values[-1]
        std = np.sqrt(np.maximum(np.diagonal(cov[-1]), 0.0)) if cov is not None else np.full(6, np.nan)
        b0 = ", ".join(f"{a} = {v:.4f} ± {s:.4f}" for a, v, s in zip("xyz", value[:3], std[:3]))
        b1 = ", ".join(f"{a} = {v:.4f} ± {s:.4f}" for a, v, s in zip("xyz", value[3:], std[3:]))
        return {"value": value.tolist(), "std": std.tolist(), "unit": ["rad/s"] * 3 + ["rad/s^2"] * 3,
                "summary": f"gyro bias {b0} rad/s, drifting {b1} rad/s^2"}
