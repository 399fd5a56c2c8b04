r"""Baselines: what a user has without an estimator, as rows beside the estimators.

Leg odometry (:func:`leg_odometry`, ``leg-odometry``) and the equal split of the weight
(:func:`weight_equal`, ``weight-equal``) are computed from the Recording alone, no estimation.

The rigid robot: the flexibility is the identity (R = I, t = 0), so the base's world orientation
is its orientation in the local (leg-odometry) frame, ``Recording.base_pose``; velocity and
acceleration of the flexibility are zero.  The weight m g is split between the contacts in force
by the static balance of the CoM (the CoM's horizontal position is the force-weighted mean of the
contact points):

- one contact: it carries m g;
- two contacts: the lever rule along the segment between them, the CoM projected onto it and
  clamped to its ends, F_1 = (1 - s) m g, F_2 = s m g;
- more: the minimum-norm forces with sum m g and moment balance about the CoM's vertical,
  negative ones set to zero and the rest rescaled to m g.

Forces are vertical, applied at the contact origins (no sole torque), so the CoP is the
force-weighted mean of the contact points.  The CoM acceleration is left out: this is the static
split a rigid-robot controller uses, not a dynamic estimate.

The equal split is the same rigid robot with the weight split equally over the contacts in
force, m g / k each: the plainest force estimate there is, the yardstick for the static split.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from flexforce.datasets.estimate import Estimate

NAME = "leg-odometry"
"""The leg-odometry baseline's name (summary key ``leg_odometry``)."""
EQUAL_NAME = "weight-equal"
"""The equal-split baseline's name (summary key ``weight_equal``)."""


def static_split(com_xy: np.ndarray, feet_xy: np.ndarray, weight: float) -> np.ndarray:
    """(k,) vertical forces (N) of ``k`` contacts at ``feet_xy`` (k, 2) balancing ``weight`` at ``com_xy``."""
    k = feet_xy.shape[0]
    if k == 0:
        return np.zeros(0)
    if k == 1:
        return np.array([weight])
    if k == 2:
        d = feet_xy[1] - feet_xy[0]
        dd = float(d @ d)
        s = 0.5 if dd < 1e-12 else float(np.clip((com_xy - feet_xy[0]) @ d / dd, 0.0, 1.0))
        return np.array([(1.0 - s) * weight, s * weight])
    A = np.vstack([np.ones(k), feet_xy.T])  # sum F = W, sum F p_xy = W c_xy
    f, *_ = np.linalg.lstsq(A, weight * np.array([1.0, *com_xy]), rcond=None)
    f = np.maximum(f, 0.0)
    return f * (weight / f.sum()) if f.sum() > 0 else np.full(k, weight / k)


def equal_split(com_xy: np.ndarray, feet_xy: np.ndarray, weight: float) -> np.ndarray:
    """(k,) vertical forces (N): ``weight`` split equally over the ``k`` contacts at ``feet_xy`` (k, 2);
    ``com_xy`` is not used (the signature of :func:`static_split`)."""
    k = feet_xy.shape[0]
    return np.full(k, weight / k) if k else np.zeros(0)


def _rigid_estimate(rec, name: str, split: Callable[[np.ndarray, np.ndarray, float], np.ndarray],
                    force_split: str) -> Estimate:
    """The rigid robot of ``rec`` (R = I, t = 0, zero velocities) carrying m g split by ``split``
    (com_xy (2,), feet_xy (k, 2), weight N -> (k,) N) as vertical forces at the contact origins."""
    n, c = rec.n, len(rec.contact_names)
    weight = rec.mass * rec.gravity
    wrench = np.zeros((n, c, 6))
    cop = np.full((n, 3), np.nan)
    for k in range(n):
        idx = np.flatnonzero(rec.contact_active[k])
        if idx.size == 0:
            continue
        p = rec.contact_p[k, idx]
        fz = split(rec.com[k, :2], p[:, :2], weight)
        F = np.zeros((idx.size, 3))
        F[:, 2] = fz
        wrench[k, idx, :3] = F
        wrench[k, idx, 3:] = np.cross(p, F)  # about the world origin (= local origin: t = 0)
        cop[k] = fz @ p / weight
    eye = np.tile(np.eye(3), (n, 1, 1))
    zeros = np.zeros((n, 3))
    return Estimate(estimator=name, t_ns=rec.t_ns.copy(), contact_names=tuple(rec.contact_names), R=eye,
                    t=zeros.copy(), w=zeros.copy(), v=zeros.copy(), dw=zeros.copy(), a=zeros.copy(),
                    wrench=wrench, cop=cop, meta={"kind": "baseline", "force_split": force_split})


def leg_odometry(rec) -> Estimate:
    """The leg-odometry baseline of ``rec`` as an :class:`Estimate` (no covariance, no timing)."""
    return _rigid_estimate(rec, NAME, static_split, "static CoM (lever rule between the feet)")


def weight_equal(rec) -> Estimate:
    """The equal-split baseline of ``rec``: leg odometry's pose, m g / k on each of the k contacts in
    force (vertical, at the contact origins), as an :class:`Estimate` (no covariance, no timing)."""
    return _rigid_estimate(rec, EQUAL_NAME, equal_split, "equal over the contacts in force")


BASELINES: dict[str, Callable[..., Estimate]] = {NAME: leg_odometry, EQUAL_NAME: weight_equal}
"""Name -> function of the Recording giving the baseline's Estimate, in the order the rows appear.
The static split by the CoM is leg odometry's own force part, so it has no row of its own."""
