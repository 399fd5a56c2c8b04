"""Hidden effects: the physics the simulated world has and the nominal model may lack.

Each effect is one ``[[effects]]`` table of a scenario file, with a ``type`` and parameters.  Each
type is a :class:`HiddenEffect` subclass registered under its name in :data:`REGISTRY` (the name of
the estimator-side effect that models it, :mod:`flexforce.factors.effects`), carrying the hooks the
simulator calls; the simulator dispatches through them and never names a type.

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
from typing import Any, ClassVar

import numpy as np
import pinocchio as pin

from flexforce.datasets.sim.scenario import minjerk
from flexforce.errors import ConfigError


@dataclass
class SpringTerms:
    """The matrices and cubic coefficients of one contact's simulated spring while the hidden
    effects adjust them (:meth:`HiddenEffect.adjust_spring`), in the contact frame."""

    K_fs: np.ndarray
    """3x3, N/m."""
    K_fd: np.ndarray
    """3x3, N s/m."""
    K_ts: np.ndarray
    """3x3, N m/rad."""
    K_td: np.ndarray
    """3x3, N m s/rad."""
    beta_f: float
    """1/m^2."""
    beta_t: float
    """1/rad^2."""


@dataclass(frozen=True)
class HiddenEffect:
    """One hidden effect of a scenario (see the module documentation for its parameters).

    The base of the hidden-truth effects: each type is a subclass registered under its name
    (:data:`REGISTRY`, the name of the estimator-side effect that models it) and overrides the
    hooks the simulator calls; every hook of the base does nothing.  Instance hooks are called
    per effect in the scenario's order; group hooks (class methods) once per type with that
    type's effects in the scenario's order, the types in the registry's order.
    """

    type: str
    params: dict = field(default_factory=dict)

    name: ClassVar[str] = ""
    """The effect's type name (the key in :data:`REGISTRY`)."""
    PARAMS: ClassVar[frozenset[str]] = frozenset()
    """The parameters its ``[[effects]]`` table may set."""

    @classmethod
    def parse(cls, raw: dict) -> HiddenEffect:
        """The registered effect of the table's ``type``.

        Raises:
            ConfigError: an unknown type or parameter (the known ones listed).
        """
        raw = dict(raw)
        kind = raw.pop("type", None)
        if kind not in REGISTRY:
            raise ConfigError(f"unknown hidden effect type '{kind}'; known: {', '.join(REGISTRY)}")
        known = REGISTRY[kind].PARAMS
        unknown = set(raw) - known
        if unknown:
            raise ConfigError(f"effect '{kind}' has unknown parameter(s) {sorted(unknown)}; "
                              f"known: {sorted(known)}")
        return REGISTRY[kind](kind, raw)

    def vector(self, key: str, default=(0.0, 0.0, 0.0)) -> np.ndarray:
        """(3,) parameter ``key`` (``default`` when absent); raises ConfigError unless 3 components."""
        value = np.asarray(self.params.get(key, default), dtype=float)
        if value.shape != (3,):
            raise ConfigError(f"effect '{self.type}': '{key}' must have 3 components, got {value.tolist()}")
        return value

    # -- instance hooks -----------------------------------------------------------------------
    def adjust_spring(self, spring: SpringTerms) -> None:
        """Change one contact's simulated spring in place (every contact, before the run)."""

    def add_imu_bias(self, gyro_bias: np.ndarray, accel_bias: np.ndarray) -> None:
        """Add this effect's constant biases to the (N, 3) gyrometer (rad/s) and accelerometer
        (m/s^2) biases, in place."""

    # -- group hooks --------------------------------------------------------------------------
    @classmethod
    def apply_to_model(cls, sim: Any, group: list) -> None:
        """Change the simulated multibody model ``sim.sim_model`` (before its data are made)."""

    @classmethod
    def imu_delay(cls, group: list) -> float:
        """s by which the IMU readings are late (0.0: none)."""
        return 0.0

    @classmethod
    def external_wrenches(cls, sim: Any, group: list) -> list:
        """``(effect, frame id, force N, torque N m)`` of each external wrench the world applies;
        its magnitude at ``t`` is ``effect.profile(t)`` times them."""
        return []

    @classmethod
    def add_ft_offsets(cls, sim: Any, group: list, out: np.ndarray) -> None:
        """Add the (C, 6) constant offsets of the F/T readings (sensor frame) to ``out``, in place."""

    @classmethod
    def add_foothold_offsets(cls, sim: Any, group: list, active, out: dict) -> None:
        """Add to ``out`` (contact index -> (position m, rotation vector rad), world axes) how far
        the true rest placement of a contact standing at the start (``active``) is off its
        nominal one."""


REGISTRY: dict[str, type[HiddenEffect]] = {}
"""Effect type name -> its class; the order is the order of the group hooks."""


def register(cls: type[HiddenEffect]) -> type[HiddenEffect]:
    """Register a hidden-effect class under its :attr:`HiddenEffect.name`."""
    REGISTRY[cls.name] = cls
    return cls


def _contact_index(sim: Any, what: str, contact) -> int:
    names = list(sim.robot.contact_names)
    if contact not in names:
        raise ConfigError(f"{what} on unknown contact {contact!r} of robot '{sim.robot.name}'; "
                          f"known: {', '.join(names)}")
    return names.index(contact)


@register
class ExternalWrench(HiddenEffect):
    """``external-wrench``: a push or a held load on a link."""

    name = "external-wrench"
    PARAMS = frozenset({"link", "force", "torque", "start", "duration", "profile", "ramp"})

    def profile(self, t: float) -> float:
        """Time profile in [0, 1] of the wrench at ``t`` (s)."""
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

    @classmethod
    def external_wrenches(cls, sim: Any, group: list) -> list:
        return [(eff, sim._frame_of(eff.params.get("link", "@base")), eff.vector("force"), eff.vector("torque"))
                for eff in group]


class _ImuBias(HiddenEffect):
    """A constant bias of one IMU sensor (:attr:`sensor`: 0 the gyrometer, 1 the accelerometer)."""

    sensor: ClassVar[int] = 0
    PARAMS = frozenset({"value"})

    def add_imu_bias(self, gyro_bias: np.ndarray, accel_bias: np.ndarray) -> None:
        bias = (gyro_bias, accel_bias)[self.sensor]
        bias += self.vector("value")


@register
class GyroBias(_ImuBias):
    """``gyro-bias``: a constant gyrometer bias (rad/s)."""

    name = "gyro-bias"
    sensor = 0


@register
class AccelBias(_ImuBias):
    """``accel-bias``: a constant accelerometer bias (m/s^2)."""

    name = "accel-bias"
    sensor = 1


@register
class Stiffness(HiddenEffect):
    """``stiffness``: the stiffness and damping of every contact scaled."""

    name = "stiffness"
    PARAMS = frozenset({"stiffness", "damping"})

    def adjust_spring(self, spring: SpringTerms) -> None:
        s = float(self.params.get("stiffness", 1.0))
        d = float(self.params.get("damping", 1.0))
        spring.K_fs, spring.K_ts, spring.K_fd, spring.K_td = (spring.K_fs * s, spring.K_ts * s,
                                                              spring.K_fd * d, spring.K_td * d)


@register
class AnisotropicStiffness(HiddenEffect):
    """``anisotropic-stiffness``: per-axis factors on the stiffness (contact frame)."""

    name = "anisotropic-stiffness"
    PARAMS = frozenset({"k_fs", "k_ts"})

    def adjust_spring(self, spring: SpringTerms) -> None:
        spring.K_fs = np.diag(self.vector("k_fs", (1.0, 1.0, 1.0))) @ spring.K_fs
        spring.K_ts = np.diag(self.vector("k_ts", (1.0, 1.0, 1.0))) @ spring.K_ts


@register
class NonlinearStiffness(HiddenEffect):
    """``nonlinear-stiffness``: cubic stiffening of every contact."""

    name = "nonlinear-stiffness"
    PARAMS = frozenset({"beta_f", "beta_t"})

    def adjust_spring(self, spring: SpringTerms) -> None:
        spring.beta_f += float(self.params.get("beta_f", 0.0))
        spring.beta_t += float(self.params.get("beta_t", 0.0))


@register
class ComOffset(HiddenEffect):
    """``com-offset``: the simulated robot's CoM displaced (the heaviest body's moved)."""

    name = "com-offset"
    PARAMS = frozenset({"offset"})

    @classmethod
    def apply_to_model(cls, sim: Any, group: list) -> None:
        offset = np.sum([e.vector("offset") for e in group], axis=0)
        model = sim.sim_model
        masses = [model.inertias[i].mass for i in range(model.njoints)]
        j = int(np.argmax(masses))
        data = model.createData()
        pin.forwardKinematics(model, data, sim.robot.q_reference)
        R = data.oMi[j].rotation
        Y = model.inertias[j]
        shift = R.T @ offset * (sim.robot.mass / Y.mass)
        # Keep the rotational inertia about the body's own CoM: rebuild with the moved lever.
        model.inertias[j] = pin.Inertia(Y.mass, Y.lever + shift, Y.inertia)


@register
class ImuMounting(HiddenEffect):
    """``imu-mounting``: the simulated IMU frame turned by ``exp(rotation)`` in its own axes (the
    recording's IMU placement is the URDF's)."""

    name = "imu-mounting"
    PARAMS = frozenset({"rotation"})

    @classmethod
    def apply_to_model(cls, sim: Any, group: list) -> None:
        rots = [e.vector("rotation") for e in group]
        fid = sim.robot.imu_frame_id
        frame = sim.sim_model.frames[fid]
        turned = pin.SE3(pin.exp3(np.sum(rots, axis=0)), np.zeros(3))
        frame.placement = frame.placement * turned
        sim.sim_model.frames[fid] = frame


@register
class TimeOffset(HiddenEffect):
    """``time-offset``: the IMU readings late by ``delay``."""

    name = "time-offset"
    PARAMS = frozenset({"delay"})

    @classmethod
    def imu_delay(cls, group: list) -> float:
        return sum(float(e.params.get("delay", 0.0)) for e in group)


@register
class MassScale(HiddenEffect):
    """``mass-scale``: every body's mass and rotational inertia times the factor, its CoM where it
    was (the recording's inputs keep the nominal model).  Registered after ``com-offset``: the
    offset moves the nominal heaviest body's CoM, then the masses scale."""

    name = "mass-scale"
    PARAMS = frozenset({"scale"})

    @classmethod
    def apply_to_model(cls, sim: Any, group: list) -> None:
        s = float(np.prod([float(e.params.get("scale", 1.0)) for e in group]))
        if not s > 0:
            raise ConfigError(f"mass-scale: scale must be positive, got {s}")
        model = sim.sim_model
        for i in range(model.njoints):
            Y = model.inertias[i]
            model.inertias[i] = pin.Inertia(Y.mass * s, Y.lever.copy(), Y.inertia * s)


@register
class FtOffset(HiddenEffect):
    """``ft-offset``: constant offsets of the F/T readings of one contact, or of all."""

    name = "ft-offset"
    PARAMS = frozenset({"contact", "force", "torque"})

    @classmethod
    def add_ft_offsets(cls, sim: Any, group: list, out: np.ndarray) -> None:
        for e in group:
            contact = e.params.get("contact")
            if contact is None:
                rows = list(range(len(sim.robot.contact_names)))
            else:
                names = list(sim.robot.contact_names)
                if contact not in names:
                    raise ConfigError(f"ft-offset on unknown contact '{contact}' of robot '{sim.robot.name}'; "
                                      f"known: {', '.join(names)}")
                rows = [names.index(contact)]
            out[rows] += np.concatenate([e.vector("force"), e.vector("torque")])


@register
class Foothold(HiddenEffect):
    """``foothold``: the ground under a contact standing at the start off its nominal placement."""

    name = "foothold"
    PARAMS = frozenset({"contact", "position", "rotation"})

    @classmethod
    def add_foothold_offsets(cls, sim: Any, group: list, active, out: dict) -> None:
        for e in group:
            contact = e.params.get("contact")
            ci = _contact_index(sim, "foothold", contact)
            if not active[ci]:
                raise ConfigError(f"foothold on '{contact}', which is not in contact at the start; the effect "
                                  "moves the rest placement of a contact standing at the first sample")
            dp, dr = out.get(ci, (np.zeros(3), np.zeros(3)))
            out[ci] = (dp + e.vector("position"), dr + e.vector("rotation"))


EFFECT_TYPES = tuple(REGISTRY)
"""The hidden effect types, the names of the estimator-side effects that model them."""


def parse_effects(items: list[dict]) -> list[HiddenEffect]:
    """Parse the ``[[effects]]`` tables of a scenario."""
    return [HiddenEffect.parse(item) for item in items]


def grouped(effects: list[HiddenEffect]) -> list[tuple[type[HiddenEffect], list[HiddenEffect]]]:
    """``(class, its effects in the scenario's order)`` for every registered type present, in the
    registry's order: what the group hooks are called with."""
    return [(cls, [e for e in effects if type(e) is cls]) for cls in REGISTRY.values()
            if any(type(e) is cls for e in effects)]
