r"""The seed paper's EKF step written with textbook Kalman algebra: the reference for the compiled step.

:func:`predict` and :func:`update` run one step of :class:`flexforce.compare.ekf.EKF`'s model (its
``transition`` and ``measurement``, the compiled kernel's model functions) with numpy's dense
algebra; :func:`numeric_jacobian` differentiates them by central differences, as the authors did.
The tests hold :func:`flexforce.compare.ekf.run_ekf`'s compiled step against them.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from flexforce.compare.ekf.filter import OM, _wrap
from flexforce.datasets import faults
from flexforce.factors import so3


def kf_predict(fx: np.ndarray, F: np.ndarray, P: np.ndarray, Q: np.ndarray):
    r"""Covariance prediction ``P' = F P F^T + Q`` around the predicted mean ``fx``; ``P'`` symmetrised."""
    Pp = F @ P @ F.T + Q
    return fx, 0.5 * (Pp + Pp.T)


class Update(NamedTuple):
    """Result of :func:`kf_update`."""

    x: np.ndarray
    P: np.ndarray
    innovation: np.ndarray
    """``y - h(x)``."""
    S: np.ndarray
    """Innovation covariance ``H P H^T + R``."""
    whitened: np.ndarray
    """``L^-1 innovation`` with ``S = L L^T``."""
    nis: float
    """Normalised innovation squared."""


def kf_update(x: np.ndarray, P: np.ndarray, y: np.ndarray, hx: np.ndarray, H: np.ndarray,
              Rn: np.ndarray) -> Update:
    r"""Kalman correction with the Joseph form::

        S = H P H^T + R,  K = P H^T S^-1,  x' = x + K (y - h(x)),
        P' = (I - K H) P (I - K H)^T + K R K^T
    """
    innov = y - hx
    PHt = P @ H.T
    S = H @ PHt + Rn
    S = 0.5 * (S + S.T)
    L = np.linalg.cholesky(S)
    K = np.linalg.solve(S, PHt.T).T
    IKH = np.eye(len(x)) - K @ H
    Pn = IKH @ P @ IKH.T + K @ Rn @ K.T
    white = np.linalg.solve(L, innov)
    return Update(x + K @ innov, 0.5 * (Pn + Pn.T), innov, S, white, float(white @ white))


def numeric_jacobian(f, x: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central differences of ``f`` in the state's own (additive) parametrisation."""
    cols = []
    for i in range(len(x)):
        e = np.zeros(len(x))
        e[i] = h
        cols.append((f(x + e) - f(x - e)) / (2 * h))
    return np.array(cols).T


def transition_numeric(ekf, x: np.ndarray, k: int):
    """``(f(x), F)`` with ``F`` by central differences of the EKF's transition."""
    return ekf.transition(x, k), numeric_jacobian(lambda z: ekf.transition(z, k), x)


def measurement_numeric(ekf, x: np.ndarray, k: int):
    """``(h(x), H)`` with ``H`` by central differences of the EKF's measurement."""
    return ekf.measurement(x, k), numeric_jacobian(lambda z: ekf.measurement(z, k), x)


def process_noise(ekf, x: np.ndarray) -> np.ndarray:
    """Q at the predicted state: the rotation block mapped from world increments to Omega."""
    B = np.eye(18)
    B[OM, OM] = so3.left_jacobian_inverse(x[OM])
    return B @ ekf.noise.Q @ B.T


def predict(ekf, x: np.ndarray, P: np.ndarray, k: int, Q: np.ndarray | None = None):
    """Propagate ``(x, P)`` of step ``k - 1`` to step ``k`` (``Q``: the process noise, default
    :func:`process_noise` at the predicted state)."""
    x1, F = ekf.transition(x, k, jacobian=True)
    return kf_predict(x1, F, P, process_noise(ekf, x1) if Q is None else Q)


def update(ekf, x: np.ndarray, P: np.ndarray, k: int) -> Update:
    """Correct ``(x, P)`` at step ``k`` with its gyrometer and accelerometer readings (missing or
    saturated axes left out; a sensor beyond its gate has its block of S inflated onto the gate)."""
    hx, H = ekf.measurement(x, k, jacobian=True)
    y = ekf.rec.imu_measurement(k)
    use = ekf.imu_use[k]
    innov = np.where(use, y - hx, 0.0)
    H = H * use[:, None]
    HPH = H @ P @ H.T
    S = np.where(np.outer(use, use), HPH + ekf.noise.R, np.diag((~use).astype(float)))
    S = 0.5 * (S + S.T)
    white = np.linalg.solve(np.linalg.cholesky(S), innov)
    S_eff = S.copy()
    for _, sl in faults.IMU_SENSORS:
        idx = np.arange(sl.start, sl.stop)[use[sl]]
        if idx.size and ekf.gates[idx.size - 1] > 0:
            blk = np.ix_(idx, idx)
            v = float(innov[idx] @ np.linalg.solve(S[blk], innov[idx]))
            if v > ekf.gates[idx.size - 1]:
                S_eff[blk] *= v / ekf.gates[idx.size - 1]
    up = kf_update(x, P, hx + innov, hx, H, S_eff - HPH)
    return up._replace(x=_wrap(up.x), S=S, whitened=white, nis=float(white @ white))
