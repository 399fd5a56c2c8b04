"""Tests of flexforce.factors.so3: exp/log, left Jacobians, projection."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flexforce.factors import so3

ANGLES = [0.0, 1e-12, 1e-9, 1e-7, 1e-5, 1e-3, 0.05, 0.3, 1.0, 2.0, 2.7, 3.0,
          math.pi - 1e-3, math.pi - 1e-6, math.pi - 1e-7, math.pi - 1e-9]


def _axes(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, 3))
    a = np.vstack([np.eye(3), a])
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def _rodrigues_reference(phi: np.ndarray) -> np.ndarray:
    """Independent reference: scipy's rotation-vector conversion."""
    return Rotation.from_rotvec(phi).as_matrix()


def test_skew_is_cross_product():
    rng = np.random.default_rng(1)
    v, u = rng.normal(size=(2, 3))
    np.testing.assert_allclose(so3.skew(v) @ u, np.cross(v, u), atol=1e-15)
    np.testing.assert_allclose(so3.skew(v), -so3.skew(v).T)


@pytest.mark.parametrize("angle", ANGLES)
def test_exp_matches_reference_and_is_rotation(angle):
    for axis in _axes(8):
        phi = angle * axis
        R = so3.exp(phi)
        np.testing.assert_allclose(R, _rodrigues_reference(phi), atol=2e-15)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=2e-15)
        assert abs(np.linalg.det(R) - 1.0) < 2e-15


@pytest.mark.parametrize("angle", ANGLES)
def test_log_exp_round_trip(angle):
    for axis in _axes(20, seed=2):
        phi = angle * axis
        back = so3.log(so3.exp(phi))
        if angle > math.pi - 1e-5 and back @ phi < 0.0:
            back = -back  # at pi the sign of the axis is a genuine ambiguity (both are logs)
        np.testing.assert_allclose(back, phi, rtol=0.0, atol=2e-15 * max(1.0, angle))
        assert np.linalg.norm(back) <= math.pi + 1e-15


def test_log_at_exactly_pi_and_identity():
    for axis in _axes(10, seed=3):
        R = _rodrigues_reference(math.pi * axis)
        phi = so3.log(R)
        assert abs(np.linalg.norm(phi) - math.pi) < 1e-14
        np.testing.assert_allclose(so3.exp(phi), R, atol=1e-14)
        assert abs(abs(phi @ axis) - math.pi) < 1e-14
    np.testing.assert_array_equal(so3.log(np.eye(3)), np.zeros(3))


def test_exp_log_round_trip_on_random_rotations():
    rng = np.random.default_rng(4)
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = Rotation.from_quat(q).as_matrix()
        np.testing.assert_allclose(so3.exp(so3.log(R)), R, atol=3e-15)


def _numerical_left_jacobian(phi: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Columns of d log(exp(phi + d) exp(phi)^T) / dd at d = 0, by central differences."""
    Rt = so3.exp(phi).T
    J = np.empty((3, 3))
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        J[:, i] = (so3.log(so3.exp(phi + d) @ Rt) - so3.log(so3.exp(phi - d) @ Rt)) / (2.0 * h)
    return J


@pytest.mark.parametrize("angle", [0.0, 1e-7, 1e-4, 0.05, 0.0999, 0.1001, 0.3, 1.0, 2.0, 3.0,
                                   math.pi - 1e-3])
def test_left_jacobian_matches_numerical(angle):
    for axis in _axes(6, seed=5):
        phi = angle * axis
        J = so3.left_jacobian(phi)
        np.testing.assert_allclose(J, _numerical_left_jacobian(phi), rtol=0.0, atol=1e-9)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-7, 1e-5, 1e-3, 0.05, 0.0999, 0.1001, 0.3, 1.0,
                                   2.0, 3.0, math.pi - 1e-6, math.pi])
def test_left_jacobian_inverse_is_inverse(angle):
    for axis in _axes(6, seed=6):
        phi = angle * axis
        J = so3.left_jacobian(phi)
        Jinv = so3.left_jacobian_inverse(phi)
        assert np.all(np.isfinite(Jinv))
        np.testing.assert_allclose(Jinv @ J, np.eye(3), rtol=0.0, atol=2e-14)
        np.testing.assert_allclose(J @ Jinv, np.eye(3), rtol=0.0, atol=2e-14)


@pytest.mark.parametrize("angle", [1e-7, 1e-3, 0.05, 0.0999, 0.1001, 1.0])
def test_left_jacobian_coefficients_are_accurate(angle):
    """Against 50-digit arithmetic: no cancellation at small angles or across the series switch."""
    mpmath = pytest.importorskip("mpmath")
    mpmath.mp.dps = 50
    th = mpmath.mpf(angle)
    a = (1 - mpmath.cos(th)) / th**2
    b = (th - mpmath.sin(th)) / th**3
    c = 1 / th**2 - (1 + mpmath.cos(th)) / (2 * th * mpmath.sin(th))
    phi = angle * np.ones(3) / math.sqrt(3.0)
    K = so3.skew(phi)
    KK = K @ K
    # Entry-wise to a few ulps: the old closed form (1 - cos) / theta^2 was 4e-4 off at 1e-7 rad.
    ref_J = np.eye(3) + float(a) * K + float(b) * KK
    ref_Jinv = np.eye(3) - 0.5 * K + float(c) * KK
    np.testing.assert_allclose(so3.left_jacobian(phi), ref_J, rtol=0.0, atol=4e-16)
    np.testing.assert_allclose(so3.left_jacobian_inverse(phi), ref_Jinv, rtol=0.0, atol=4e-16)


def test_left_jacobian_first_order_property():
    rng = np.random.default_rng(7)
    phi = rng.normal(size=3)
    d = 1e-7 * rng.normal(size=3)
    lhs = so3.exp(phi + d)
    rhs = so3.exp(so3.left_jacobian(phi) @ d) @ so3.exp(phi)
    np.testing.assert_allclose(lhs, rhs, atol=1e-13)


def test_project_gives_nearest_rotation():
    rng = np.random.default_rng(8)
    for _ in range(20):
        R = so3.exp(rng.normal(size=3))
        noisy = R + 1e-3 * rng.normal(size=(3, 3))
        P = so3.project(noisy)
        np.testing.assert_allclose(P @ P.T, np.eye(3), atol=1e-14)
        assert abs(np.linalg.det(P) - 1.0) < 1e-14
        assert np.linalg.norm(P - R) < 1e-2
        # P is a rotation and no rotation nearby is closer in Frobenius norm.
        for _ in range(5):
            Q = so3.exp(1e-4 * rng.normal(size=3)) @ P
            assert np.linalg.norm(noisy - P) <= np.linalg.norm(noisy - Q) + 1e-15
    # A reflection-contaminated matrix still projects onto SO(3), not O(3).
    P = so3.project(np.diag([1.0, 1.0, -1.0]) + 1e-3)
    assert abs(np.linalg.det(P) - 1.0) < 1e-14
    # A rotation projects onto itself.
    R = so3.exp(np.array([0.3, -1.2, 2.0]))
    np.testing.assert_allclose(so3.project(R), R, atol=1e-15)
