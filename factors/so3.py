"""Rotation helpers: skew, exponential and logarithm of SO(3), and the left Jacobians.

Conventions: a rotation vector ``phi`` (rad) maps to ``R = exp([phi]x)``.  A *world-frame* (left)
increment ``dtheta`` of a rotation ``R`` is ``R <- exp([dtheta]x) R``; a *body-frame* (right)
increment ``dphi`` is ``R <- R exp([dphi]x)``, the convention of gtsam's ``Rot3``/``Pose3``
tangent spaces.  The two are related by ``dtheta = R dphi``.

The functions are the compiled core's (:mod:`flexforce.factors.core`, one implementation for
every estimator); ``tests/test_so3.py`` holds them against mpmath.  Series expansions replace the
closed forms where those cancel (below 1e-8 rad for ``exp``, below 0.1 rad for the Jacobians), so
every function is smooth and accurate to a few ulps at zero rotation; ``log`` and ``left_jacobian_inverse``
stay accurate up to an angle of pi.
"""

from __future__ import annotations

import numpy as np

from flexforce.factors import core


def skew(v: np.ndarray) -> np.ndarray:
    """Return the 3x3 skew-symmetric matrix ``[v]x`` with ``[v]x w = v x w`` (seed eq. 5)."""
    x, y, z = np.asarray(v).tolist()  # Python floats: faster than numpy scalars
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def exp(phi: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: the rotation matrix ``exp([phi]x)`` of a rotation vector (rad)."""
    return core.so3_exp(_vec(phi))


def log(R: np.ndarray) -> np.ndarray:
    """The rotation vector ``phi`` (rad, ``|phi| <= pi``) with ``exp([phi]x) = R``.

    ``theta = atan2(sin, cos)`` rather than ``acos``: acos loses half the digits near 0 and pi,
    and near pi ``theta / sin(theta)`` then amplifies the error (~1e-3 rad at pi - 1e-6).  Near pi
    the direction of the antisymmetric part is ill-conditioned: the axis is read off the symmetric
    part ``(1 - cos) a a^T`` and its sign taken from the antisymmetric one.
    """
    return core.so3_log(np.ascontiguousarray(R, dtype=float))


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """Left Jacobian ``J_l(phi)``: ``exp(phi + d) = exp(J_l(phi) d) exp(phi)`` to first order.

    ``I + (1 - cos)/theta^2 [phi]x + (theta - sin)/theta^3 [phi]x^2``, by its series below 0.1 rad
    where the closed form cancels."""
    return core.so3_jl(_vec(phi))


def left_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """``J_l(phi)^-1``: ``log(exp(d) exp(phi)) = phi + J_l^-1(phi) d`` to first order.

    ``I - [phi]x / 2 + (1/theta^2 - cot(theta/2) / (2 theta)) [phi]x^2`` (finite and accurate up
    to pi), by its series below 0.1 rad."""
    return core.so3_jl_inv(_vec(phi))


def _vec(phi) -> np.ndarray:
    return np.ascontiguousarray(phi, dtype=float)


def project(R: np.ndarray) -> np.ndarray:
    """The closest rotation matrix to ``R`` (polar decomposition through the SVD)."""
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.linalg.det(U @ Vt)])
    return U @ D @ Vt
