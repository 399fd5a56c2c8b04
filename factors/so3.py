"""Rotation helpers: skew, exponential and logarithm of SO(3), and the left Jacobians.

Conventions: a rotation vector ``phi`` (rad) maps to ``R = exp([phi]x)``.  A *world-frame* (left)
increment ``dtheta`` of a rotation ``R`` is ``R <- exp([dtheta]x) R``; a *body-frame* (right)
increment ``dphi`` is ``R <- R exp([dphi]x)``, the convention of gtsam's ``Rot3``/``Pose3``
tangent spaces.  The two are related by ``dtheta = R dphi``.

Series expansions replace the closed forms where those cancel (below 1e-8 rad for ``exp``, below
0.1 rad for the Jacobians), so every function is smooth and accurate to a few ulps at zero
rotation; ``log`` and ``left_jacobian_inverse`` stay accurate up to an angle of pi.
"""

from __future__ import annotations

import math

import numpy as np

_SMALL = 1e-8


def skew(v: np.ndarray) -> np.ndarray:
    """Return the 3x3 skew-symmetric matrix ``[v]x`` with ``[v]x w = v x w`` (seed eq. 5)."""
    x, y, z = np.asarray(v).tolist()  # Python floats: faster than numpy scalars
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def exp(phi: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: the rotation matrix ``exp([phi]x)`` of a rotation vector (rad)."""
    theta2 = float(phi @ phi)
    K = skew(phi)
    if theta2 < _SMALL * _SMALL:
        return np.eye(3) + K + 0.5 * K @ K
    theta = math.sqrt(theta2)
    a = math.sin(theta) / theta
    b = (1.0 - math.cos(theta)) / theta2
    return np.eye(3) + a * K + b * K @ K


def log(R: np.ndarray) -> np.ndarray:
    """The rotation vector ``phi`` (rad, ``|phi| <= pi``) with ``exp([phi]x) = R``."""
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])  # 2 sin(theta) axis
    cos_theta = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    sin_theta = 0.5 * math.sqrt(float(w @ w))
    # atan2 rather than acos: acos(cos_theta) loses half the digits near 0 and pi, and near pi
    # theta / sin(theta) then amplifies the error (|error| ~ 1e-3 rad at pi - 1e-6).
    theta = math.atan2(sin_theta, cos_theta)
    if cos_theta > -0.9:
        if sin_theta < _SMALL:
            return 0.5 * (1.0 + sin_theta * sin_theta / 6.0) * w
        return (0.5 * theta / sin_theta) * w
    # theta near pi: the direction of w is ill-conditioned; read the axis off the symmetric part
    # S = (1 - cos) a a^T and take its sign from w.
    S = 0.5 * (R + R.T)
    S[0, 0] -= cos_theta
    S[1, 1] -= cos_theta
    S[2, 2] -= cos_theta
    k = int(np.argmax(np.diag(S)))
    axis = S[:, k]
    if axis @ w < 0.0:
        axis = -axis
    return (theta / math.sqrt(float(axis @ axis))) * axis


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """Left Jacobian ``J_l(phi)``: ``exp(phi + d) = exp(J_l(phi) d) exp(phi)`` to first order."""
    theta2 = float(phi @ phi)
    K = skew(phi)
    if theta2 < 1e-2:
        # Series: the closed forms below cancel catastrophically at small angles.
        a = 0.5 - theta2 * (1.0 / 24.0 - theta2 * (1.0 / 720.0 - theta2 / 40320.0))
        b = 1.0 / 6.0 - theta2 * (1.0 / 120.0 - theta2 * (1.0 / 5040.0 - theta2 / 362880.0))
    else:
        theta = math.sqrt(theta2)
        h = math.sin(0.5 * theta) / theta
        a = 2.0 * h * h  # (1 - cos) / theta^2
        b = (theta - math.sin(theta)) / (theta2 * theta)
    return np.eye(3) + a * K + b * (K @ K)


def left_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """``J_l(phi)^-1``: ``log(exp(d) exp(phi)) = phi + J_l^-1(phi) d`` to first order."""
    theta2 = float(phi @ phi)
    K = skew(phi)
    if theta2 < 1e-2:
        c = 1.0 / 12.0 + theta2 * (1.0 / 720.0 + theta2 * (1.0 / 30240.0 + theta2 / 1209600.0))
    else:
        theta = math.sqrt(theta2)
        # (1 + cos) / (2 sin) = cot(theta / 2) / 2, which stays finite and accurate at pi.
        c = 1.0 / theta2 - 0.5 / (theta * math.tan(0.5 * theta))
    return np.eye(3) - 0.5 * K + c * (K @ K)


def project(R: np.ndarray) -> np.ndarray:
    """The closest rotation matrix to ``R`` (polar decomposition through the SVD)."""
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.linalg.det(U @ Vt)])
    return U @ D @ Vt
