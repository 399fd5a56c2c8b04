"""Hidden effects: the physics the simulated world has and the nominal model may lack.

Each effect is one ``[[effects]]`` table of a scenario file, with a ``type`` and parameters:

=========================  ==================================================================
type                       parameters (SI units)
=========================  ==================================================================
``external-wrench``        ``link`` (URDF frame, or ``@base`` for the free-flyer body,
                           ``@link:0``/``@link:1`` for the robot's tracked links, the hands),
                           ``force`` [N] and ``torque`` [N m] (world axes, applied at the
                           link's origin), ``start`` and ``duration`` [s], ``profile``:
                           ``half-sine`` (default, a push) or ``step`` (minimum-jerk on and
                           off over ``ramp`` s).
``gyro-bias``              ``value`` [rad/s], constant bias added to the gyrometer (IMU frame).
``accel-bias``             ``value`` [m/s^2], constant bias added to the accelerometer.
``stiffness``              ``stiffness`` and ``damping``: factors applied to the nominal
                           K_fs, K_ts and K_fd, K_td of every contact (a worn or wrong bush).
``anisotropic-stiffness``  ``k_fs`` and ``k_ts``: per-axis factors (x, y, z of the contact
                           frame) applied to the nominal stiffness.
``nonlinear-stiffness``    ``beta_f`` [1/m^2] and ``beta_t`` [1/rad^2]: cubic stiffening,
                           ``F = -K_fs s (1 + beta_f |s|^2)`` (rubber stiffens under load).
``com-offset``             ``offset`` [m]: the simulated robot's CoM is displaced by this
                           vector (local-frame axes at the reference posture) by moving the
                           centre of mass of its heaviest body; the recording's inputs are
                           still computed with the nominal mass model.
``imu-mounting``           ``rotation`` [rad]: rotation vector (IMU-frame axes) by which the
                           simulated IMU frame is turned against the URDF's
                           (``imu_R_true = imu_R exp(rotation)``); the recording's IMU
                           placement is still the URDF's.
``time-offset``            ``delay`` [s]: the IMU samples are late by this much: the reading
                           stamped ``t`` is the simulated sensor's at ``t - delay`` (negative:
                           early); the encoders are on time.
``mass-scale``             ``scale`` [-]: every body's mass and rotational inertia (about its
                           own CoM, which stays put) times this factor; the recording's inputs
                           are still computed with the nominal mass model.
``ft-offset``              ``force`` [N] and ``torque`` [N m]: constant offset added to the F/T
                           readings (the sensor's frame: force, and torque about the contact
                           point, in the contact frame) of ``contact`` (a contact name; all
                           contacts when absent); the physics and the other sensors are
                           unchanged.  One table per sensor for different offsets.
``foothold``               ``contact`` (a contact name, in force at the start), ``position``
                           [m] and ``rotation`` [rad] (world axes): the ground under that
                           contact is off the nominal rest placement by this much -- a shim,
                           a tilted tile, a foot that settled elsewhere than the kinematics
                           say.  The spring's true rest is moved; the recording's contact
                           placement is still the nominal one.
=========================  ==================================================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from flexforce.datasets.sim.scenario import minjerk
from flexforce.errors import ConfigError

EFFECT_TYPES = ("external-wrench", "gyro-bias", "accel-bias", "stiffness", "anisotropic-stiffness",
                "nonlinear-stiffness", "com-offset", "imu-mounting", "time-offset", "mass-scale", "ft-offset",
                "foothold")

_PARAMS = {
    "external-wrench": {"link", "force", "torque", "start", "duration", "profile", "ramp"},
    "gyro-bias": {"value"},
    "accel-bias": {"value"},
    "stiffness": {"stiffness", "damping"},
    "anisotropic-stiffness": {"k_fs", "k_ts"},
    "nonlinear-stiffness": {"beta_f", "beta_t"},
    "com-offset": {"offset"},
    "imu-mounting": {"rotation"},
    "time-offset": {"delay"},
    "mass-scale": {"scale"},
    "ft-offset": {"contact", "force", "torque"},
    "foothold": {"contact", "position", "rotation"},
}


@dataclass(frozen=True)
class HiddenEffect:
    """One hidden effect of a scenario (see the module documentation for its parameters)."""

    type: str
    params: dict = field(default_factory=dict)

    @classmethod
    def parse(cls, raw: dict) -> HiddenEffect:
        raw = dict(raw)
        kind = raw.pop("type", None)
        if kind not in EFFECT_TYPES:
            raise ConfigError(f"unknown hidden effect type '{kind}'; known: {', '.join(EFFECT_TYPES)}")
        unknown = set(raw) - _PARAMS[kind]
        if unknown:
            raise ConfigError(f"effect '{kind}' has unknown parameter(s) {sorted(unknown)}; "
                              f"known: {sorted(_PARAMS[kind])}")
        return cls(kind, raw)

    def vector(self, key: str, default=(0.0, 0.0, 0.0)) -> np.ndarray:
        value = np.asarray(self.params.get(key, default), dtype=float)
        if value.shape != (3,):
            raise ConfigError(f"effect '{self.type}': '{key}' must have 3 components, got {value.tolist()}")
        return value

    def profile(self, t: float) -> float:
        """Time profile in [0, 1] of an external wrench."""
        start = float(self.params.get("start", 0.0))
        duration = float(self.params.get("duration", math.inf))
        kind = self.params.get("profile", "half-sine")
        if t < start or t > start + duration:
            return 0.0
        if kind == "half-sine":
            return math.sin(math.pi * (t - start) / duration)
        if kind == "step":
            ramp = float(self.params.get("ramp", 0.05))
            return minjerk((t - start) / ramp)[0] * minjerk((start + duration - t) / ramp)[0]
        raise ConfigError(f"external-wrench profile must be 'half-sine' or 'step', got '{kind}'")


def parse_effects(items: list[dict]) -> list[HiddenEffect]:
    """Parse the ``[[effects]]`` tables of a scenario."""
    return [HiddenEffect.parse(item) for item in items]
