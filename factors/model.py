"""ModelConfig: what an estimator assumes about the robot and its sensors.

Shared by the EKF and the smoothers so that they are compared under the same assumptions: the
nominal contact spring-dampers, the sensor noise, gravity, and the enabled model effects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from flexforce.factors.footholds import FootholdPrior
from flexforce.factors.physics import GRAVITY, ContactParams
from flexforce.options import check_positive


@dataclass(frozen=True)
class ModelConfig:
    """Model assumptions of an estimator."""

    contact_params: tuple[ContactParams, ...]
    """Nominal spring-damper of each contact of the recording (eq. 6, 11)."""
    gyro_sigma: float
    """Per-sample gyrometer noise standard deviation, rad/s."""
    accel_sigma: float
    """Per-sample accelerometer noise standard deviation, m/s^2."""
    gravity: float = GRAVITY
    """m/s^2."""
    ft_force_sigma: float = 2.0
    """Per-sample F/T force noise, N (used only with ``use_ft``)."""
    ft_torque_sigma: float = 0.2
    """Per-sample F/T torque noise, N m (used only with ``use_ft``)."""
    gyro_range: float = math.inf
    """Gyrometer full scale, rad/s: readings at or beyond it are saturated (no information);
    ``inf``: no check.  :meth:`from_recording` takes the robot's ``imu_noise.gyro_range``."""
    accel_range: float = math.inf
    """Accelerometer full scale, m/s^2, as ``gyro_range``."""
    gyro_bias_max: float = 0.05
    """Largest plausible gyrometer bias, rad/s (the robot's ``imu_noise.gyro_bias_max``)."""
    accel_bias_max: float = 0.3
    """Largest plausible accelerometer bias, m/s^2 (the robot's ``imu_noise.accel_bias_max``)."""
    mass_factor: float = 2.0
    """How well the mass is known (the robot's ``mass_factor``): a plausible mass scale lies
    within ``1 / mass_factor`` and ``mass_factor``."""
    model_uncertainty: Any = None
    """The standard deviations of the model's parameters
    (:class:`~flexforce.datasets.robot.ModelUncertainty`, the robot's ``[model_uncertainty]``
    table), or None: the comparison's model band on the contact forces
    (:func:`flexforce.compare.band.model_band`) needs them."""
    use_ft: bool = False
    """Fuse the recording's F/T readings as measurements."""
    effects: tuple = field(default_factory=tuple)
    """Enabled model effects (see the diagnostics); empty for the nominal model."""
    foothold_prior: FootholdPrior = field(default_factory=FootholdPrior)
    """Leg-kinematics and ground priors of the footholds, when the smoothers estimate them
    (``BatchConfig.footholds``, ``FixedLagConfig.footholds``; the robot's ``[footholds]`` table)."""
    soles: tuple = ()
    """Per contact, its sole's rectangle ``(x_min, x_max, y_min, y_max)`` (m, contact frame) or
    None; empty: none given.  Where the CoP of a contact's wrench may lie (the comparison counts
    the samples outside: :func:`flexforce.compare.metrics.violations`) and where the reported
    wrenches keep it (``limit_wrenches``)."""
    friction: float | None = None
    """Coulomb friction coefficient of the contacts with the ground (the robot's ``friction``), or
    None: not given (no friction limit on the reported wrenches)."""
    switch_window: float = 0.1
    """Within this of a contact switch (s), the reported contact wrenches carry the force the
    estimated motion requires (the Newton-Euler residual's force, shared over the contacts in force
    by their normal forces: :func:`flexforce.factors.contact_limits.balance_near_switches`), where
    the contact law's rest placement is least certain (a landing foot).  0: the contact law's
    wrenches throughout, as with the footholds estimated (``footholds=True``) or the EKF's
    ``touchdown="zero-deflection"``, which settle a landing's rest placement themselves.  The
    state and the covariances are not changed."""
    limit_wrenches: bool | None = None
    """Report the contact wrenches limited to what a contact can carry: no pulling normal force, a
    tangential force inside the friction cone, a CoP on the sole
    (:func:`flexforce.factors.contact_limits.limit_contact_wrenches`); the part removed goes to
    :attr:`~flexforce.datasets.estimate.Estimate.wrench_excess`.  The state is not changed.  None
    (default): when the robot describes its contacts with the ground (``soles`` or ``friction``
    given); the simulated robots do not, and their simulated springs pull as readily as they push."""

    def __post_init__(self):
        w = self.switch_window
        if isinstance(w, bool) or not isinstance(w, int | float) or not (math.isfinite(w) and w >= 0):
            from flexforce.errors import ConfigError

            raise ConfigError(f"ModelConfig.switch_window = {w!r} s; expected a finite duration >= 0 (0: off)")

    @classmethod
    def from_recording(cls, rec, robot=None, **overrides) -> ModelConfig:
        """Nominal model for a recording: the robot's configured stiffness and noise model.

        The noise densities come from the robot configuration only, the per-sample sigma being
        ``density * sqrt(rate)``.  A simulated recording's metadata describes the sensors of its
        world (``meta["imu_noise"]``), which may differ from what the robot's data sheet says: an
        estimator never reads it, as it could not on a real robot.
        """
        from flexforce.datasets.robot import RobotConfig, RobotModel

        if robot is None:
            robot = RobotConfig.load(rec.robot)
        elif isinstance(robot, RobotModel):
            robot = robot.config
        elif not isinstance(robot, RobotConfig):
            robot = RobotConfig.load(robot)
        rate = 1.0 / rec.dt
        noise = robot.imu_noise.__dict__
        ft = robot.ft_noise.__dict__
        params = robot.stiffness.params()
        cfg = cls(
            contact_params=tuple(params for _ in rec.contact_names),
            gyro_sigma=float(noise["gyro_density"]) * math.sqrt(rate),
            accel_sigma=float(noise["accel_density"]) * math.sqrt(rate),
            gravity=rec.gravity,
            ft_force_sigma=float(ft["force"]),
            ft_torque_sigma=float(ft["torque"]),
            gyro_range=float(noise["gyro_range"]),
            accel_range=float(noise["accel_range"]),
            gyro_bias_max=float(noise["gyro_bias_max"]),
            accel_bias_max=float(noise["accel_bias_max"]),
            mass_factor=float(robot.mass_factor),
            model_uncertainty=robot.model_uncertainty,
            foothold_prior=FootholdPrior.from_config(robot.footholds),
            soles=_soles(robot, rec.contact_names),
            friction=robot.friction,
        )
        return replace(cfg, **overrides) if overrides else cfg


def _soles(robot, names) -> tuple:
    """The soles of the recording's contacts ``names`` from the robot's contacts (by name), or ()
    when the robot gives none."""
    by_name = {c.name: c.sole for c in robot.contacts}
    soles = tuple(by_name.get(n) for n in names)
    return soles if any(s is not None for s in soles) else ()


def unmodelled_acceleration(accel_sigma: float, imu_p: np.ndarray, contact_centroid: np.ndarray) -> tuple[float, float]:
    """The nominal model's unmodelled acceleration of the flexibility, per sample.

    One assumption shared by the EKF (its process noise) and the smoothers (their Newton-Euler
    noise): what the model leaves out moves the flexibility by a white acceleration, constant over
    a sample, at the level the accelerometer can resolve in one sample.  (The simulated world has
    its own ambient disturbance, a scenario parameter: :class:`flexforce.datasets.sim.scenario.Ambient`.)

    Returns:
        ``(sigma_a, sigma_dw)``: linear acceleration ``accel_sigma`` (m/s^2) and angular
        acceleration ``accel_sigma / l`` (rad/s^2), ``l`` the distance from the IMU to the contacts'
        centroid (at least 1 mm): the rotation that moves the IMU by as much.
    """
    lever = float(np.linalg.norm(np.asarray(imu_p) - np.asarray(contact_centroid)))
    return float(accel_sigma), float(accel_sigma) / max(lever, 1e-3)


def check_unmodelled(owner: str, accel, ang_accel, nominal: tuple[str, str]) -> None:
    """Check an estimator's override of :func:`unmodelled_acceleration` (its config's
    ``unmodelled_accel``, m/s^2, and ``unmodelled_ang_accel``, rad/s^2): each a positive standard
    deviation, or None for the nominal one, which ``nominal`` names in the messages (linear, angular)."""
    check_positive(owner, "unmodelled_accel", accel, "m/s^2",
                   f"a positive standard deviation or None ({nominal[0]})", optional=True)
    check_positive(owner, "unmodelled_ang_accel", ang_accel, "rad/s^2",
                   f"a positive standard deviation or None ({nominal[1]})", optional=True)
