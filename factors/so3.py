"""Rotation helpers: skew, exponential and logarithm of SO(3), and the left Jacobians.

Conventions: a rotation vector ``phi`` (rad) maps to ``R = exp([phi]x)``.  A *world-frame* (left)
increment ``dtheta`` of a rotation ``R`` is ``R <- exp([dtheta]x) R``; a *body-frame* (right)
increment ``dphi`` is ``R <- R exp([dphi]x)``, the convention of gtsam's ``Rot3``/``Pose3``
tangent spaces.  The two are related by ``dtheta = R dphi``.

Near the identity (angle below 1e-8 rad) the series expansions are used, so every function is
smooth at zero rotation.
"""

from __future__ import annotations

import math

import numpy as np

_SMALL = 1e-8


def skew(v: np.ndarray) -> np.ndarray:
    """Return the 3x3 skew-symmetric matrix ``[v]x`` with ``[v]x w = v x w`` (seed eq. 5)."""
    x, y, z = v
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
    cos_theta = 0.5 * (np.trace(R) - 1.0)
    cos_theta = min(1.0, max(-1.0, cos_theta))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if cos_theta > 1.0 - 1e-12:
        # theta ~ 0: first order in the antisymmetric part, with the cubic correction.
        return 0.5 * w * (1.0 + (1.0 - cos_theta) / 3.0)
    theta = math.acos(cos_theta)
    if theta < math.pi - 1e-6:
        return 0.5 * theta / math.sin(theta) * w
    # theta ~ pi: read the axis off the symmetric part.
    S = 0.5 * (R + R.T) - cos_theta * np.eye(3)
    k = int(np.argmax(np.diag(S)))
    axis = S[:, k] / math.sqrt(max(S[k, k], 1e-300))
    if axis @ w < 0.0:
        axis = -axis
    return theta * axis / np.linalg.norm(axis)


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """Left Jacobian ``J_l(phi)``: ``exp(phi + d) = exp(J_l(phi) d) exp(phi)`` to first order."""
    theta2 = float(phi @ phi)
    K = skew(phi)
    if theta2 < _SMALL * _SMALL:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    theta = math.sqrt(theta2)
    a = (1.0 - math.cos(theta)) / theta2
    b = (theta - math.sin(theta)) / (theta2 * theta)
    return np.eye(3) + a * K + b * K @ K


def left_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """``J_l(phi)^-1``: ``log(exp(d) exp(phi)) = phi + J_l^-1(phi) d`` to first order."""
    theta2 = float(phi @ phi)
    K = skew(phi)
    if theta2 < 1e-10:
        return np.eye(3) - 0.5 * K + K @ K / 12.0
    theta = math.sqrt(theta2)
    c = 1.0 / theta2 - (1.0 + math.cos(theta)) / (2.0 * theta * math.sin(theta))
    return np.eye(3) - 0.5 * K + c * K @ K


def project(R: np.ndarray) -> np.ndarray:
    """The closest rotation matrix to ``R`` (polar decomposition through the SVD)."""
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.linalg.det(U @ Vt)])
    return U @ D @ Vt
