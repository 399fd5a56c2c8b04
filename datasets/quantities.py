"""The physical quantities the data carry: plain dataclasses and constants, no laws.

The local-frame inputs of the seed paper (:class:`Inputs`), the IMU's placement in the local frame
(:class:`ImuPlacement`), a contact's spring-damper parameters (:class:`ContactParams`), the prior of
a landing sole (:class:`FootholdPrior`), the flexibility's motion and contact wrenches over a run
(:class:`FlexibleMotion`, what an estimate and a simulation's truth share) and gravity.  A
:class:`~flexforce.datasets.recording.Recording` and a robot's configuration hold them; the physics
(:mod:`flexforce.factors.physics`) takes them as arguments and re-exports them under its own name.
Units SI; frames as named on each field.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from flexforce.errors import ModelError
from flexforce.options import check_choice, check_finite, check_positive, invalid

__all__ = ["GRAVITY", "ContactParams", "FlexibleMotion", "FootholdPrior", "ImuPlacement", "Inputs", "Stamped"]

GRAVITY = 9.81
"""Default gravity (m/s^2), along -z of the world (correction 6: a parameter)."""

class Stamped:
    """Per-step series on the time stamps ``t_ns``: the number of steps and the time in seconds (a
    :class:`~flexforce.datasets.recording.Recording` and an :class:`~flexforce.datasets.estimate.Estimate`)."""

    t_ns: np.ndarray
    """(N,) int64 time stamps, ns."""

    @property
    def n(self) -> int:
        """Number of steps."""
        return int(self.t_ns.shape[0])

    @property
    def time(self) -> np.ndarray:
        """(N,) float seconds from the first sample."""
        return (self.t_ns - self.t_ns[0]).astype(float) * 1e-9


@dataclass
class FlexibleMotion:
    """The flexibility's motion and the contact wrenches over ``N`` steps (``C`` contacts): what an
    :class:`~flexforce.datasets.estimate.Estimate` and a simulation's
    :class:`~flexforce.datasets.recording.Truth` both hold, in the same frames and units."""

    R: np.ndarray
    """(N, 3, 3) flexibility rotation, local to world."""
    t: np.ndarray
    """(N, 3) flexibility translation, m."""
    w: np.ndarray
    """(N, 3) flexibility angular velocity (world), rad/s."""
    v: np.ndarray
    """(N, 3) flexibility linear velocity, m/s."""
    dw: np.ndarray
    """(N, 3) angular acceleration, rad/s^2."""
    a: np.ndarray
    """(N, 3) linear acceleration, m/s^2."""
    wrench: np.ndarray
    """(N, C, 6) per-contact wrench (F [N], T [N m] about the world origin); zero when inactive."""

    @property
    def total_wrench(self) -> np.ndarray:
        """(N, 6) sum of the contact wrenches."""
        return self.wrench.sum(axis=1)


def matrix3(value: ArrayLike) -> np.ndarray | None:
    """A 3x3 stiffness from a scalar (isotropic), a 3-vector (diagonal) or a 3x3 matrix (copied);
    None for any other shape (the caller names the value in its error)."""
    a = np.asarray(value, dtype=float)
    if a.ndim == 0:
        return float(a) * np.eye(3)
    if a.shape == (3,):
        return np.diag(a)
    if a.shape == (3, 3):
        return a.copy()
    return None


def _as_matrix(value: ArrayLike, name: str) -> np.ndarray:
    a = matrix3(value)
    if a is None:
        raise ModelError(f"{name} must be a scalar, a 3-vector (diagonal) or a 3x3 matrix, "
                         f"got shape {np.asarray(value, dtype=float).shape}")
    return a


@dataclass(frozen=True)
class ContactParams:
    """Spring-damper of one contact, eq. (6) and (11), expressed in the contact frame.

    The matrices are rotated into the world with the current contact orientation,
    ``K_world = R R_c K R_c^T R^T`` (correction 5); isotropic matrices are unaffected.
    """

    K_fs: np.ndarray
    """Translational stiffness, 3x3, N/m."""
    K_fd: np.ndarray
    """Translational damping, 3x3, N s/m."""
    K_ts: np.ndarray
    """Rotational stiffness, 3x3, N m/rad."""
    K_td: np.ndarray
    """Rotational damping, 3x3, N m s/rad."""
    beta_f: float = 0.0
    """Cubic stiffening of the translational spring, 1/m^2: ``F = -K_fs s (1 + beta_f |s|^2)``."""
    beta_t: float = 0.0
    """Cubic stiffening of the rotational spring, 1/rad^2: ``T = -K_ts Omega (1 + beta_t |Omega|^2)``."""
    _isotropic: bool = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Decided once: np.allclose costs ~0.1 ms, far more than the contact law itself.
        object.__setattr__(self, "_isotropic", all(
            np.allclose(K, K[0, 0] * np.eye(3), rtol=0.0, atol=1e-12 * max(1.0, abs(K[0, 0])))
            for K in (self.K_fs, self.K_fd, self.K_ts, self.K_td)
        ))

    @classmethod
    def make(cls, k_fs: ArrayLike, k_fd: ArrayLike, k_ts: ArrayLike, k_td: ArrayLike, beta_f: float = 0.0,
             beta_t: float = 0.0) -> ContactParams:
        """Build from scalars (isotropic), 3-vectors (diagonal in the contact frame) or 3x3 matrices."""
        return cls(
            _as_matrix(k_fs, "k_fs"),
            _as_matrix(k_fd, "k_fd"),
            _as_matrix(k_ts, "k_ts"),
            _as_matrix(k_td, "k_td"),
            float(beta_f),
            float(beta_t),
        )

    @property
    def isotropic(self) -> bool:
        """True when every matrix is a multiple of the identity (orientation does not matter)."""
        return self._isotropic

    def scaled(self, stiffness: float = 1.0, damping: float = 1.0) -> ContactParams:
        """A copy with stiffnesses multiplied by ``stiffness`` and dampings by ``damping``."""
        return ContactParams(
            self.K_fs * stiffness, self.K_fd * damping, self.K_ts * stiffness, self.K_td * damping,
            self.beta_f, self.beta_t,
        )


@dataclass(frozen=True)
class Inputs:
    """The paper's local-frame inputs at one instant (sec. II-C, III-B); correction 3 applies.

    All vectors and tensors are expressed in the local frame and taken about its origin.
    """

    m: float
    """Total mass, kg."""
    c: np.ndarray
    """CoM position ``c_l``, m."""
    dc: np.ndarray
    """CoM velocity, m/s."""
    ddc: np.ndarray
    """CoM acceleration, m/s^2."""
    I: np.ndarray
    """Rotational inertia about the local origin ``I_l = I_G - m [c_l]x^2``, kg m^2."""
    dI: np.ndarray
    """Its time derivative, kg m^2/s."""
    sigma: np.ndarray
    """Angular momentum about the local origin ``sigma_l = h_G + m c_l x dc_l``, kg m^2/s."""
    dsigma: np.ndarray
    """Its time derivative, N m."""


@dataclass(frozen=True)
class ImuPlacement:
    """The IMU's placement and motion in the local frame (eq. 26-28)."""

    R: np.ndarray
    """Orientation ``R_a,l`` (IMU frame to local frame)."""
    p: np.ndarray
    """Position ``p_a,l``, m."""
    v: np.ndarray
    """Velocity ``dp_a,l/dt`` in the local frame, m/s."""
    a: np.ndarray
    """Acceleration ``d2p_a,l/dt2`` in the local frame, m/s^2."""
    w: np.ndarray
    """Angular velocity ``omega_g,l`` of the IMU relative to the local frame, expressed in it, rad/s."""


@dataclass(frozen=True)
class FootholdPrior:
    """Where a landing sole rests: the leg kinematics' errors and the ground plane.

    Built from the robot configuration's ``[footholds]`` table
    (:class:`flexforce.datasets.robot.FootholdConfig`: terrain, plane, the tilt and height sigmas);
    the horizontal ones are the kinematics' alone.
    """

    terrain: str = "flat"
    """``flat`` (default), ``plane`` (``normal``, ``height``) or ``none`` (no ground factor)."""
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """Floor normal, world (= local frame at the first sample) axes (``terrain = "plane"``)."""
    height: float = 0.0
    """Floor offset along the unit normal, m (``terrain = "plane"``)."""
    ground_sigma_tilt: float = 0.0035
    """Floor flatness: sole tilt about the plane, rad."""
    ground_sigma_height: float = 0.002
    """Floor flatness: sole height about the plane, m."""
    kinematics_sigma_tilt: float = 0.017
    """Leg kinematics (and zero deflection) at a touch-down: sole roll and pitch, rad."""
    kinematics_sigma_height: float = 0.005
    """Leg kinematics at a touch-down: sole height, m."""
    kinematics_sigma_rotation: float = 0.017
    """Leg kinematics at a touch-down: sole yaw, rad."""
    kinematics_sigma_position: float = 0.005
    """Leg kinematics at a touch-down: sole horizontal position, m."""

    def __post_init__(self):
        o = "FootholdPrior"
        check_choice(o, "terrain", self.terrain, ("flat", "plane", "none"))
        for key in ("ground_sigma_tilt", "ground_sigma_height", "kinematics_sigma_tilt", "kinematics_sigma_height",
                    "kinematics_sigma_rotation", "kinematics_sigma_position"):
            unit = "m" if key.endswith(("height", "position")) else "rad"
            check_positive(o, key, getattr(self, key), unit, "a positive standard deviation")
        n = np.asarray(self.normal, dtype=float)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-9:
            raise invalid(o, "normal", self.normal, "", "a non-zero 3-vector")
        check_finite(o, "height", self.height, "m", "a finite number")

    @classmethod
    def from_config(cls, footholds) -> FootholdPrior:
        """From a :class:`~flexforce.datasets.robot.FootholdConfig` (duck-typed: its attributes)."""
        nx, ny, nz = (float(x) for x in footholds.normal)
        return cls(terrain=footholds.terrain, normal=(nx, ny, nz),
                   height=float(footholds.height), ground_sigma_tilt=float(footholds.ground_sigma_tilt),
                   ground_sigma_height=float(footholds.ground_sigma_height),
                   kinematics_sigma_tilt=float(footholds.kinematics_sigma_tilt),
                   kinematics_sigma_height=float(footholds.kinematics_sigma_height))

    def kinematic_sigma(self, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(3, 3) covariances of the position and the rotation from the kinematics, world axes:
        the horizontal and vertical (along ``normal``) sigmas."""
        P = np.outer(normal, normal)
        cov_p = (self.kinematics_sigma_position**2 * (np.eye(3) - P) + self.kinematics_sigma_height**2 * P)
        cov_r = (self.kinematics_sigma_tilt**2 * (np.eye(3) - P) + self.kinematics_sigma_rotation**2 * P)
        return cov_p, cov_r
