"""Robot model: a URDF through pinocchio plus a small TOML configuration.

The configuration names the contact frames, the IMU frame, the links whose world position is
tracked (the hands), the contact stiffness and damping, and the sensor noise.  Files for
``romeo`` (the default), ``talos`` and ``icub`` ship in ``flexforce/datasets/robots``.

:meth:`RobotModel.kinematics` turns a configuration of the robot *in the local frame* (its own
belief: free-flyer placement and joints, with their velocities and accelerations) into the
paper's inputs (sec. II-C, correction 3 of DESIGN.md), the IMU placement and motion (eq. 26-28)
and the contact placements.
"""

from __future__ import annotations

import contextlib
import math
import numbers
import os
import re
import site
import sys
import tempfile
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

from flexforce.datasets.quantities import GRAVITY, ContactParams, FootholdPrior, ImuPlacement, Inputs
from flexforce.errors import ConfigError, ConfigWarning
from flexforce.options import read_toml

ROBOTS_DIR = Path(__file__).resolve().parent / "robots"
DEFAULT_ROBOT = "romeo"

SAVGOL_ORDERS = (2, 7)
"""Accepted ``[ros] savgol_order`` (the Savitzky-Golay polynomial's order): from 2 (an
acceleration needs a parabola) to 7."""
IMU_FILTERS = ("none", "savgol")
"""The values of ``[ros] imu_filter`` (:attr:`RosConfig.imu_filter`)."""

ROS_RATE_RANGE = (10.0, 10_000.0)
"""Bounds of ``[ros] rate``, Hz: state estimation of a legged robot runs at its IMU's and
encoders' rates, tens of Hz to a few kHz; below the grid would alias the gait, above it the grid
only interpolates the messages, with a cost in memory and time growing with the rate."""

STIFFNESS_UNITS = {"k_fs": "N/m", "k_fd": "N s/m", "k_ts": "N m/rad", "k_td": "N m s/rad"}
"""The keys of a robot configuration's ``[stiffness]`` section (all four required) and their units."""

STIFFNESS_MAX = {"k_fs": 1e9, "k_fd": 1e7, "k_ts": 1e8, "k_td": 1e6}
"""Upper bounds of the ``[stiffness]`` values (units of :data:`STIFFNESS_UNITS`): legged robots'
soles and bushes lie between 1e3 and 1e7 N/m; beyond the bounds a contact is rigid and the
filter's covariances (spring periods of microseconds against a millisecond step) are no longer
numbers it can hold."""


def _finite_number(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def _positive_number(value) -> bool:
    return (isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
            and float(value) > 0)


def _check_positive(section: str, key: str, value, unit: str, what: str) -> None:
    """``value`` is a positive, finite number; a ConfigError naming ``section.key``, the value and unit otherwise."""
    if not _positive_number(value):
        shown = f"{value!r} {unit}" if unit else repr(value)
        raise ConfigError(f"{section}.{key} = {shown}; expected {what}")


def example_robot_data_dir() -> Path:
    """The ``robots`` folder of example-robot-data (installed by the ``example-robot-data`` wheel)."""
    roots = list(site.getsitepackages()) + [site.getusersitepackages(), sys.prefix]
    for root in roots:
        candidate = Path(root) / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
        if candidate.is_dir():
            return candidate
    raise ConfigError("example-robot-data is not installed: its robots folder "
                      "(cmeel.prefix/share/example-robot-data/robots) was not found; pip install example-robot-data")


@dataclass(frozen=True)
class Stiffness:
    """Contact spring-damper, the same for every contact of the robot (eq. 6, 11).

    Scalars are isotropic; 3-vectors are diagonal in the contact frame.
    """

    k_fs: float | tuple = 40000.0
    """Translational stiffness, N/m."""
    k_fd: float | tuple = 600.0
    """Translational damping, N s/m."""
    k_ts: float | tuple = 400.0
    """Rotational stiffness, N m/rad."""
    k_td: float | tuple = 10.0
    """Rotational damping, N m s/rad."""

    def __post_init__(self):
        for key, unit in STIFFNESS_UNITS.items():
            value = getattr(self, key)
            kind = "damping" if key.endswith("d") else "stiffness"
            if isinstance(value, list | tuple | np.ndarray):
                ok = len(value) == 3 and all(_positive_number(v) for v in value)
            else:
                ok = _positive_number(value)
            shown = list(value) if isinstance(value, tuple | np.ndarray) else value
            if not ok:
                raise ConfigError(f"stiffness.{key} = {shown!r} {unit}; expected a positive, finite {kind} (a number, "
                                  "or 3 numbers: one per axis of the contact frame)")
            if float(np.max(value)) > STIFFNESS_MAX[key]:
                raise ConfigError(f"stiffness.{key} = {shown!r} {unit}; expected a {kind} of at most "
                                  f"{STIFFNESS_MAX[key]:g} {unit} (a contact stiffer than steel on steel is rigid: "
                                  "the estimators' covariances lose their precision long before)")

    def minimum(self, key: str) -> float:
        """The smallest value of ``key`` over the axes (the value itself when isotropic)."""
        value = getattr(self, key)
        return float(np.min(value))

    def params(self) -> ContactParams:
        """The :class:`ContactParams` of one contact."""
        return ContactParams.make(self.k_fs, self.k_fd, self.k_ts, self.k_td)


@dataclass(frozen=True)
class ImuNoise:
    """IMU noise model (continuous-time densities; discrete sigma = density * sqrt(rate)).

    Defaults are representative of an old MEMS IMU such as the ten-year-old units of the seed's
    HRP-2: gyro angle random walk 0.05 deg/s/sqrt(Hz), accelerometer velocity random walk
    400 ug/sqrt(Hz), bias instabilities drifting slowly as random walks.
    """

    gyro_density: float = 8.7e-4
    """Gyro white noise, rad/s/sqrt(Hz)."""
    accel_density: float = 3.9e-3
    """Accelerometer white noise, m/s^2/sqrt(Hz)."""
    gyro_bias_rw: float = 2e-5
    """Gyro bias random walk, rad/s^2/sqrt(Hz)."""
    accel_bias_rw: float = 2e-4
    """Accelerometer bias random walk, m/s^3/sqrt(Hz)."""
    accel_range: float = 16.0 * 9.80665
    """Accelerometer full scale, m/s^2 (per axis): a reading at or beyond it (within 0.1 %) is
    saturated and carries no information.  Default +-16 g, the largest range of common MEMS parts;
    set it from the IMU's data sheet (``inf``: no saturation check)."""
    gyro_range: float = math.radians(2000.0)
    """Gyrometer full scale, rad/s (per axis), as ``accel_range``.  Default +-2000 deg/s (34.9 rad/s)."""
    gyro_bias_max: float = 0.05
    """Largest gyrometer bias the data sheet allows, rad/s (per axis): a diagnosis that fits a
    larger one calls it implausible.  Default 0.05 rad/s (3 deg/s), an uncalibrated MEMS gyro's
    turn-on bias."""
    accel_bias_max: float = 0.3
    """Largest accelerometer bias the data sheet allows, m/s^2 (per axis), as ``gyro_bias_max``.
    Default 0.3 m/s^2, an uncalibrated MEMS accelerometer's offset."""

    def __post_init__(self):
        for key, unit in (("gyro_density", "rad/s/sqrt(Hz)"), ("accel_density", "m/s^2/sqrt(Hz)")):
            _check_positive("imu_noise", key, getattr(self, key), unit, "a positive, finite noise density")
        for key, unit in (("gyro_bias_rw", "rad/s^2/sqrt(Hz)"), ("accel_bias_rw", "m/s^3/sqrt(Hz)")):
            value = getattr(self, key)  # 0: biases that do not drift
            if not (value == 0 or _positive_number(value)) or isinstance(value, bool):
                raise ConfigError(f"imu_noise.{key} = {value!r} {unit}; expected a finite random walk >= 0")
        for key, unit in (("gyro_bias_max", "rad/s"), ("accel_bias_max", "m/s^2")):
            _check_positive("imu_noise", key, getattr(self, key), unit,
                            "the largest bias of the sensor's data sheet, a positive finite number")
        for key, unit in (("accel_range", "m/s^2"), ("gyro_range", "rad/s")):
            value = getattr(self, key)
            if not (isinstance(value, numbers.Real) and not isinstance(value, bool) and value > 0
                    and not math.isnan(value)):
                raise ConfigError(f"imu_noise.{key} = {value!r} {unit}; expected the sensor's positive full scale "
                                  "(a reading at or beyond it is saturated, so a range <= 0 would leave no valid "
                                  "reading; inf: no saturation check)")

    def gyro_sigma(self, rate: float) -> float:
        """Per-sample gyro standard deviation (rad/s) at ``rate`` Hz."""
        return self.gyro_density * math.sqrt(rate)

    def accel_sigma(self, rate: float) -> float:
        """Per-sample accelerometer standard deviation (m/s^2) at ``rate`` Hz."""
        return self.accel_density * math.sqrt(rate)


@dataclass(frozen=True)
class ModelUncertainty:
    """How well the model's own parameters are known (``[model_uncertainty]`` table): one standard
    deviation each.  The comparison turns them into a model band on every contact force
    (:func:`flexforce.compare.band.model_band`): each estimator run again with one parameter moved
    by its standard deviation.  0 leaves a parameter out."""

    com_x: float = 0.02
    """The URDF's centre of mass along the local x axis (forward), m."""
    com_y: float = 0.02
    """The centre of mass along the local y axis (sideways), m."""
    stiffness: float = 0.3
    """Every contact spring and damper, relative (0.3: 30 %)."""
    vertical_stiffness: float = 0.3
    """The contacts' normal stiffness and damping alone, relative."""
    contact_timing: float = 0.02
    """The time of every contact switch (the trigger on the F/T or the gait schedule), s."""

    def __post_init__(self):
        units = {"com_x": "m", "com_y": "m", "stiffness": "", "vertical_stiffness": "", "contact_timing": "s"}
        for key, unit in units.items():
            value = getattr(self, key)
            if isinstance(value, bool) or not (value == 0 or _positive_number(value)):
                raise ConfigError(f"model_uncertainty.{key} = {value!r} {unit}".rstrip()
                                  + "; expected a finite standard deviation >= 0 (0: left out)")

    def perturbations(self) -> dict[str, float]:
        """The parameters with a standard deviation above zero: name -> standard deviation."""
        return {k: float(v) for k, v in self.__dict__.items() if v > 0}


@dataclass(frozen=True)
class FtNoise:
    """Force/torque sensor noise, per-sample standard deviations."""

    force: float = 2.0
    """N."""
    torque: float = 0.2
    """N m."""

    def __post_init__(self):
        _check_positive("ft_noise", "force", self.force, "N", "a positive, finite standard deviation")
        _check_positive("ft_noise", "torque", self.torque, "N m", "a positive, finite standard deviation")


@dataclass(frozen=True)
class ContactConfig:
    """One contact of the robot."""

    name: str
    """Name used in recordings and reports (e.g. ``left_foot``)."""
    frame: str
    """Frame of the URDF at the contact (sole), whose origin is the contact point."""
    sole: tuple[float, float, float, float] | None = None
    """The sole's rectangle ``(x_min, x_max, y_min, y_max)``, m, in the contact frame (``x_min <
    0 < x_max``, ``y_min < 0 < y_max``: the contact point lies on the sole); the CoP of the
    contact's wrench must lie inside it.  None: not given (the CoP-in-sole check is skipped)."""


@dataclass(frozen=True)
class RosConfig:
    """How raw robot bags map onto the robot (the optional ``[ros]`` table of a robot config).

    Read by :func:`flexforce.datasets.io.rosimport.import_bag`; docs/real-logs.md describes the method.
    """

    imu_topic: str = "/imu"
    """sensor_msgs/Imu topic: gyrometer (rad/s) and accelerometer (m/s^2) in ``imu_frame``."""
    joint_states_topic: str = "/joint_states"
    """sensor_msgs/JointState topic: joint positions (rad or m), optionally velocities."""
    ft_topics: dict = field(default_factory=dict)
    """Contact name -> geometry_msgs/WrenchStamped topic (wrench of the environment on the robot)."""
    mocap_topics: dict = field(default_factory=dict)
    """URDF frame name -> geometry_msgs/PoseStamped topic (world pose of that frame)."""
    contact_on: float | None = None
    """Schmitt trigger: a contact becomes active when its normal force rises above this, N;
    default ``contact_on_weight`` m g."""
    contact_off: float | None = None
    """Schmitt trigger: an active contact is released when its normal force falls below this, N;
    default ``contact_off_weight`` m g.  Must be below ``contact_on``."""
    contact_on_weight: float = 0.25
    """Default ``contact_on`` as a fraction of the robot's weight (m g)."""
    contact_off_weight: float = 0.20
    """Default ``contact_off`` as a fraction of the weight.  A foot stays in force while it carries
    a fifth of the weight: measured on the iCub walk, a sole carrying more than that stays where
    it landed (its kinematic placement within 6 mm of its foothold) while below it the foot rolls
    off its toes (10-25 mm median, 45 mm at most), which a flat spring at the sole cannot model.
    The authors' trigger released feet at 120 N (37 % of iCub's weight) that carried up to 147 N."""
    fixed_contacts: tuple = ()
    """Contacts active throughout with ``contacts="fixed"``; empty means all contacts."""
    anchor: str | None = None
    """Contact preferred as the first stance-foot anchor (default: the most loaded active one)."""
    rate: float | None = None
    """Grid rate, Hz; default the IMU's median message rate."""
    gap_factor: float = 2.0
    """Source intervals longer than this many grid periods are reported in ``meta['gaps']``."""
    max_gap: float = 0.25
    """Longest interval, s, bridged by interpolation on the IMU and joint topics (DataError beyond;
    F/T and motion capture become NaN instead)."""
    joint_velocity: str = "message"
    """``message``: use JointState.velocity when every message has it; ``differentiate``: always
    differentiate the positions (Savitzky-Golay)."""
    savgol_window: float = 0.1
    """Savitzky-Golay window, s (rounded to an odd number of grid samples, at least order + 2)."""
    savgol_order: int = 3
    """Savitzky-Golay polynomial order."""
    imu_filter: str = "none"
    """The IMU readings' bandwidth.  ``none``: as the messages give them (resampled on the grid);
    ``savgol``: through the joints' Savitzky-Golay smoother (``savgol_window``, ``savgol_order``,
    zero-phase, ``mode="interp"`` at the ends), so that the accelerometer and gyrometer see the
    same band as their kinematic prediction, which is formed from the smoothed joint derivatives.
    A reading the filter cannot use (missing, or at the sensor's full scale, ``[imu_noise]``) makes
    every output whose window holds it missing on that axis.  docs/real-logs.md, "IMU bandwidth"."""
    ignore_joints: str | None = None
    """Regular expression of JointState names to ignore (joints the URDF does not have)."""

    def __post_init__(self):
        for key, unit, what, optional in (
                ("contact_on", "N", "a normal force", True), ("contact_off", "N", "a normal force", True),
                ("contact_on_weight", "", "a fraction of the weight", False),
                ("contact_off_weight", "", "a fraction of the weight", False),
                ("gap_factor", "", "a number of grid periods", False), ("max_gap", "s", "a duration", False),
                ("savgol_window", "s", "a duration", False)):
            value = getattr(self, key)
            if optional and value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
                shown = f"{value!r} {unit}".rstrip()
                raise ConfigError(f"ros.{key} = {shown}; expected {what}, a finite number")
        if isinstance(self.savgol_order, bool) or not isinstance(self.savgol_order, numbers.Integral):
            raise ConfigError(f"ros.savgol_order = {self.savgol_order!r}; expected a whole number >= 2 (the "
                              "Savitzky-Golay polynomial order)")
        for key in ("imu_topic", "joint_states_topic"):
            if not isinstance(getattr(self, key), str):
                raise ConfigError(f"ros.{key} = {getattr(self, key)!r}; expected a topic name (a string)")
        for key in ("ft_topics", "mocap_topics"):
            table = getattr(self, key)
            if not isinstance(table, dict) or not all(isinstance(v, str) for v in table.values()):
                raise ConfigError(f"ros.{key} = {table!r}; expected a table of name = \"/topic\" entries")
        if self.contact_on is not None and self.contact_off is not None and not self.contact_off < self.contact_on:
            raise ConfigError(f"ros.contact_off = {self.contact_off} N must be below ros.contact_on = "
                              f"{self.contact_on} N (Schmitt trigger hysteresis)")
        if not 0 <= self.contact_off_weight < self.contact_on_weight <= 1:
            raise ConfigError(f"ros.contact_off_weight = {self.contact_off_weight} and ros.contact_on_weight = "
                              f"{self.contact_on_weight} (fractions of the weight); expected "
                              "0 <= contact_off_weight < contact_on_weight <= 1")
        if self.joint_velocity not in ("message", "differentiate"):
            raise ConfigError(f"ros.joint_velocity = {self.joint_velocity!r}; expected 'message' or 'differentiate'")
        if self.rate is not None and (isinstance(self.rate, bool) or not isinstance(self.rate, numbers.Real)
                                      or not ROS_RATE_RANGE[0] <= self.rate <= ROS_RATE_RANGE[1]):
            lo, hi = ROS_RATE_RANGE
            raise ConfigError(f"ros.rate = {self.rate!r} Hz; expected a grid rate between {lo:g} Hz and {hi:g} Hz "
                              "(a robot's state estimation: IMUs and joint encoders sample at tens of Hz to a "
                              "few kHz) or no rate (the IMU's median message rate)")
        if not self.max_gap > 0 or not self.gap_factor > 0:
            raise ConfigError("ros.max_gap (s) and ros.gap_factor must be positive")
        if self.imu_filter not in IMU_FILTERS:
            raise ConfigError(f"ros.imu_filter = {self.imu_filter!r}; expected 'none' (the readings as given) "
                              "or 'savgol' (the joints' Savitzky-Golay smoother)")
        if self.savgol_window <= 0 or not SAVGOL_ORDERS[0] <= self.savgol_order <= SAVGOL_ORDERS[1]:
            raise ConfigError(f"ros.savgol_window = {self.savgol_window} s must be positive and "
                              f"ros.savgol_order = {self.savgol_order} from {SAVGOL_ORDERS[0]} to {SAVGOL_ORDERS[1]} "
                              "(a polynomial of higher order fitted over a window is ill-conditioned and follows "
                              "the noise)")


@dataclass(frozen=True)
class FootholdConfig:
    """Footholds: where each contact episode's sole rests in the world (the ``[footholds]`` table).

    A contact's rest placement is fixed for one contact episode (touch-down to lift-off).  Its
    estimate at touch-down fuses two priors, each Gaussian and independent per component:

    - **leg kinematics**: where the stance-foot odometry puts the sole when it lands, with the
      errors ``kinematics_sigma_tilt`` (rad) and ``kinematics_sigma_height`` (m) -- encoder
      offsets, the stance foot's own deflection, link lengths;
    - **ground**: the sole lies on the floor plane (its normal along the plane's, its origin at the
      plane's height) within ``ground_sigma_tilt`` (rad) and ``ground_sigma_height`` (m) -- the
      floor's flatness.

    The fused estimate moves the kinematic placement toward the plane by the weight
    ``w = s_kin^2 / (s_kin^2 + s_ground^2)`` (tilt and height separately); yaw and the horizontal
    position are the kinematics' alone.  Without the ground prior (``terrain = "none"``) the
    kinematic placement is kept, and every error of the leg kinematics at a touch-down becomes a
    permanent tilt of the local frame (on a 90 s iCub walk, 9 deg of leg-odometry tilt).

    The plane is given in the local frame at the first sample, whose origin and axes are the
    first stance sole's (flat on the floor by assumption): ``terrain = "flat"`` is the plane
    ``z = 0``; ``terrain = "plane"`` takes ``plane_normal`` (any length) and ``plane_height`` (m,
    the plane's height along its unit normal: ``n . p = plane_height``).
    """

    terrain: str = "flat"
    """``flat`` (default), ``plane`` (``plane_normal``, ``plane_height``) or ``none`` (no ground prior)."""
    plane_normal: tuple = (0.0, 0.0, 1.0)
    """Floor normal in the local frame of the first sample (``terrain = "plane"``)."""
    plane_height: float = 0.0
    """Floor offset along the unit normal, m (``terrain = "plane"``)."""
    ground_sigma_tilt: float = FootholdPrior.ground_sigma_tilt
    """Floor flatness: sole tilt about the plane, rad (0.2 deg)."""
    ground_sigma_height: float = FootholdPrior.ground_sigma_height
    """Floor flatness: sole height about the plane, m."""
    kinematics_sigma_tilt: float = FootholdPrior.kinematics_sigma_tilt
    """Leg-kinematics error of a landing sole's tilt, rad (1 deg)."""
    kinematics_sigma_height: float = FootholdPrior.kinematics_sigma_height
    """Leg-kinematics error of a landing sole's height, m."""

    def __post_init__(self):
        if self.terrain not in ("flat", "plane", "none"):
            raise ConfigError(f"footholds.terrain = {self.terrain!r}; expected 'flat', 'plane' or 'none'")
        for key in ("ground_sigma_tilt", "ground_sigma_height", "kinematics_sigma_tilt", "kinematics_sigma_height"):
            value = getattr(self, key)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                unit = "rad" if key.endswith("tilt") else "m"
                raise ConfigError(f"footholds.{key} = {value!r}; expected a positive number of {unit}")
        n = np.asarray(self.plane_normal, dtype=float)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-9:
            raise ConfigError(f"footholds.plane_normal = {self.plane_normal!r}; expected a non-zero 3-vector")
        if not np.isfinite(self.plane_height):
            raise ConfigError(f"footholds.plane_height = {self.plane_height!r} m; expected a finite number")

    @property
    def normal(self) -> np.ndarray:
        """Unit floor normal in the local frame of the first sample."""
        n = np.asarray(self.plane_normal if self.terrain == "plane" else (0.0, 0.0, 1.0), dtype=float)
        return n / np.linalg.norm(n)

    @property
    def height(self) -> float:
        """Floor offset along the unit normal, m."""
        if self.terrain != "plane":
            return 0.0
        return float(self.plane_height) / float(np.linalg.norm(np.asarray(self.plane_normal, dtype=float)))

    def _weight(self, sigma_kinematics: float, sigma_ground: float) -> float:
        """``s_kin^2 / (s_kin^2 + s_ground^2)``, or 0 without a ground prior."""
        if self.terrain == "none":
            return 0.0
        return sigma_kinematics**2 / (sigma_kinematics**2 + sigma_ground**2)

    @property
    def tilt_weight(self) -> float:
        """Fraction of a landing sole's tilt off the plane that the ground prior removes."""
        return self._weight(self.kinematics_sigma_tilt, self.ground_sigma_tilt)

    @property
    def height_weight(self) -> float:
        """Fraction of a landing sole's height off the plane that the ground prior removes."""
        return self._weight(self.kinematics_sigma_height, self.ground_sigma_height)


@dataclass(frozen=True)
class RobotConfig:
    """A robot: URDF, frames, stiffness and sensor noise (one TOML file, see ``robots/*.toml``)."""

    name: str
    urdf: str
    """Path of the URDF; ``erd:`` prefixes a path inside example-robot-data's robots folder;
    a relative path is taken from the configuration file's folder."""
    contacts: tuple[ContactConfig, ...]
    imu_frame: str
    """Frame of the IMU (gyrometer and accelerometer axes)."""
    srdf: str | None = None
    """SRDF holding the reference posture (same path rules as ``urdf``)."""
    reference: str = "half_sitting"
    """Name of the SRDF reference configuration; the neutral configuration when absent."""
    reference_joints: dict = field(default_factory=dict)
    """Joint values (rad) overriding the reference posture."""
    lock_joints: str | None = None
    """Regular expression of joint names locked at the reference posture (fingers...)."""
    links: tuple[str, ...] = ()
    """Frames whose world position is tracked in the ground truth (the hands)."""
    stiffness: Stiffness = Stiffness()
    imu_noise: ImuNoise = ImuNoise()
    ft_noise: FtNoise = FtNoise()
    gravity: float = GRAVITY
    footholds: FootholdConfig = FootholdConfig()
    """Rest placements of the contact episodes on real logs (``[footholds]`` table)."""
    friction: float | None = None
    """Coulomb friction coefficient between the soles and the ground (dimensionless, > 0): the
    reported contact wrenches keep their tangential force within ``friction`` times their normal
    force.  None: not given (no friction limit)."""
    model_uncertainty: ModelUncertainty | None = None
    """The standard deviations of the model's parameters (``[model_uncertainty]`` table), from which
    the comparison draws a model band on each contact force; None (no table): no model band."""
    mass_factor: float = 2.0
    """How well the URDF's mass is known (dimensionless, > 1): the robot weighs between
    ``m / mass_factor`` and ``m * mass_factor``, and a diagnosis that fits a mass scale outside it
    calls it implausible.  Default 2 (a model nobody weighed: batteries, covers or a wrong URDF may
    be missing); about 1.05 for a robot on the scales with its URDF checked."""
    ros: RosConfig | None = None
    """Mapping of raw ROS bags onto the robot (``[ros]`` table), for :mod:`flexforce.datasets.io.rosimport`."""
    source: str = ""
    """Where the configuration was read from."""

    def __post_init__(self):
        accel_range = self.imu_noise.accel_range
        if _positive_number(self.gravity) and not accel_range > self.gravity:
            raise ConfigError(f"imu_noise.accel_range = {accel_range!r} m/s^2; expected a full scale above "
                              f"gravity ({self.gravity:g} m/s^2): an accelerometer at rest reads g, so a smaller "
                              "range would clip every reading (inf: no saturation check)"
                              + (f" in robot configuration {self.source}" if self.source else ""))

    @classmethod
    def load(cls, name_or_path: str | Path | RobotConfig) -> RobotConfig:
        """Read a built-in configuration by name (``romeo``, ``talos``, ``icub``) or a TOML file (a
        RobotConfig is returned as it is)."""
        if isinstance(name_or_path, RobotConfig):
            return name_or_path
        path = Path(name_or_path)
        if not path.suffix:
            path = ROBOTS_DIR / f"{name_or_path}.toml"
            if not path.exists():
                known = ", ".join(sorted(p.stem for p in ROBOTS_DIR.glob("*.toml")))
                raise ConfigError(f"unknown robot '{name_or_path}'; built-in robots: {known}, or give a .toml path")
        raw = read_toml(path, "robot configuration")
        return cls.from_dict(raw, base=path.parent, source=str(path))

    @classmethod
    def from_dict(cls, raw: dict, base: Path | None = None, source: str = "") -> RobotConfig:
        """Build from the dictionary of a TOML file; unknown keys are refused."""
        raw = dict(raw)
        known = {f for f in cls.__dataclass_fields__}
        unknown = set(raw) - known
        if unknown:
            raise ConfigError(f"unknown key(s) {sorted(unknown)} in robot configuration {source}; "
                              f"known keys: {sorted(known - {'source'})}")
        where = f" in robot configuration {source}" if source else " in the robot configuration"
        for key in ("name", "urdf", "contacts", "imu_frame"):
            if key not in raw:
                raise ConfigError(f"robot configuration {source} lacks '{key}'")
        if "stiffness" not in raw:
            # No default: the contact springs are the robot's (the seed's HRP-2 values suit a 58 kg
            # robot and must be scaled to another, DESIGN.md "Stability").
            raise ConfigError(f"the [stiffness] section is missing{where}; expected the contact spring-damper "
                              f"of the robot: {', '.join(f'{k} ({u})' for k, u in STIFFNESS_UNITS.items())}")
        for section, cls_ in (("stiffness", Stiffness), ("imu_noise", ImuNoise), ("ft_noise", FtNoise)):
            table = raw.get(section, {})
            if not isinstance(table, dict):
                raise ConfigError(f"{section} = {table!r}{where}; expected a [{section}] table")
            known_keys = [f for f in cls_.__dataclass_fields__]
            if extra := sorted(set(table) - set(known_keys)):
                raise ConfigError(f"unknown key(s) {extra} in [{section}]{where}; known keys: {known_keys}")
        if missing := [k for k in STIFFNESS_UNITS if k not in raw["stiffness"]]:
            raise ConfigError(f"[stiffness] lacks {', '.join(f'{k} ({STIFFNESS_UNITS[k]})' for k in missing)}{where}; "
                              "expected all of k_fs, k_fd, k_ts and k_td")
        for key in ("name", "urdf", "imu_frame"):
            if not isinstance(raw[key], str) or not raw[key]:
                raise ConfigError(f"{key} = {raw[key]!r}{where}; expected a non-empty string")
        _check_contacts(raw["contacts"], where)
        for key in ("footholds", "ros"):
            if key in raw and not isinstance(raw[key], dict):
                raise ConfigError(f"{key} = {raw[key]!r}{where}; expected a [{key}] table")
        if "friction" in raw and not (_positive_number(raw["friction"]) and raw["friction"] <= 10.0):
            raise ConfigError(f"friction = {raw['friction']!r}{where}; expected the Coulomb friction coefficient of "
                              "the soles on the ground, a number in (0, 10] (about 0.5-1 for rubber on a hard floor)")
        if "mass_factor" in raw and not (_positive_number(raw["mass_factor"]) and raw["mass_factor"] > 1.0):
            raise ConfigError(f"mass_factor = {raw['mass_factor']!r}{where}; expected how well the URDF's mass is "
                              "known, a factor above 1 (e.g. 1.05 for a weighed robot, 2 for an unchecked model)")
        if "gravity" in raw and not _positive_number(raw["gravity"]):
            raise ConfigError(f"gravity = {raw['gravity']!r} m/s^2{where}; expected a positive, finite acceleration")
        try:
            contacts = tuple(ContactConfig(**c) for c in raw.pop("contacts"))
            stiffness = Stiffness(**{k: tuple(v) if isinstance(v, list) else v
                                     for k, v in raw.pop("stiffness").items()})
            imu_noise = ImuNoise(**raw.pop("imu_noise", {}))
            ft_noise = FtNoise(**raw.pop("ft_noise", {}))
            mu = raw.pop("model_uncertainty", None)
            if mu is not None:
                if not isinstance(mu, dict):
                    raise ConfigError(f"model_uncertainty = {mu!r}{where}; expected a [model_uncertainty] table")
                if extra := sorted(set(mu) - set(ModelUncertainty.__dataclass_fields__)):
                    raise ConfigError(f"unknown key(s) {extra} in [model_uncertainty]{where}; known keys: "
                                      f"{sorted(ModelUncertainty.__dataclass_fields__)}")
                mu = ModelUncertainty(**mu)
            fh = dict(raw.pop("footholds", {}))
            if "plane_normal" in fh:
                fh["plane_normal"] = tuple(fh["plane_normal"])
            unknown = set(fh) - set(FootholdConfig.__dataclass_fields__)
            if unknown:
                raise ConfigError(f"unknown key(s) {sorted(unknown)} in [footholds] of robot configuration {source}; "
                                  f"known keys: {sorted(FootholdConfig.__dataclass_fields__)}")
            footholds = FootholdConfig(**fh)
            ros = raw.pop("ros", None)
            if ros is not None:
                ros = dict(ros)
                unknown = set(ros) - set(RosConfig.__dataclass_fields__)
                if unknown:
                    raise ConfigError(f"unknown key(s) {sorted(unknown)} in [ros] of robot configuration {source}; "
                                      f"known keys: {sorted(RosConfig.__dataclass_fields__)}")
                if "fixed_contacts" in ros:
                    ros["fixed_contacts"] = tuple(ros["fixed_contacts"])
                ros = RosConfig(**ros)
        except TypeError as err:
            raise ConfigError(f"robot configuration {source}: {err}") from err
        except ConfigError as err:
            if source and source not in str(err):
                raise ConfigError(f"{err}{where}") from None
            raise
        for key in ("urdf", "srdf"):
            if raw.get(key):
                raw[key] = _resolve(raw[key], base)
        raw["links"] = tuple(raw.get("links", ()))
        raw.pop("source", None)
        return cls(contacts=contacts, stiffness=stiffness, imu_noise=imu_noise, ft_noise=ft_noise,
                   footholds=footholds, ros=ros, model_uncertainty=mu, source=source, **raw)

    @property
    def contact_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.contacts)


def check_toppling(stiffness: Stiffness, mass: float, com, contact_p, contact_R, gravity: float = GRAVITY,
                   robot: str = "") -> None:
    """The contact springs against gravity toppling (DESIGN.md, "Stability").

    Tilting a robot of mass ``m`` whose CoM stands ``h`` above its contacts by a small angle moves
    its weight's line of action by ``h`` per radian: gravity pushes it over with a stiffness of
    ``m g h`` (N m/rad) that the springs must beat.  About each horizontal axis, the contacts in
    force resist with ``sum k_ts`` plus ``k_fs d^2`` for each contact at a distance ``d`` from
    their centroid across that axis.

    - **Error** (:class:`ConfigError`): even with every given contact in force the tilt stiffness
      about an axis is at most ``m g h``: the model has no upright equilibrium, the estimators'
      covariances blow up.
    - **Warning** (:class:`ConfigWarning`): one contact alone has ``k_ts <= m g h`` (on its
      softest axis): standing on one point contact is unstable, so a recording with single
      support (steps, walking) will not be explained; double support is.

    Args:
        stiffness: the robot's springs (the same on every contact).
        mass: total mass, kg.
        com: CoM in the frame of ``contact_p`` (z up, along gravity), m.
        contact_p: (C, 3) positions of the contacts in force, m.
        contact_R: (C, 3, 3) their orientations.
        gravity: m/s^2.
        robot: name for the messages.
    """
    contact_p = np.asarray(contact_p, dtype=float).reshape(-1, 3)
    contact_R = np.asarray(contact_R, dtype=float).reshape(-1, 3, 3)
    if contact_p.shape[0] == 0 or not (np.isfinite(contact_p).all() and np.isfinite(com).all()):
        return
    params = stiffness.params()
    centroid = contact_p.mean(axis=0)
    height = float(np.asarray(com, dtype=float)[2] - centroid[2])
    m_g_h = mass * gravity * height
    if not m_g_h > 0:  # CoM at or below the contacts: gravity does not topple it
        return
    who = f" of robot '{robot}'" if robot else ""
    toppling = (f"the gravity toppling stiffness m g h = {mass:.1f} kg x {gravity:.2f} m/s^2 x {height:.3f} m = "
                f"{m_g_h:.0f} N m/rad (m the mass, h the CoM height above the contacts)")
    for axis, name, across in ((0, "x (roll)", 1), (1, "y (pitch)", 0)):
        u = np.eye(3)[axis]
        k_total = 0.0
        for p, R in zip(contact_p, contact_R):
            k_rot = float(u @ R @ params.K_ts @ R.T @ u)
            k_vert = float(np.eye(3)[2] @ R @ params.K_fs @ R.T @ np.eye(3)[2])
            k_total += k_rot + k_vert * float(p[across] - centroid[across]) ** 2
        if k_total <= m_g_h:
            raise ConfigError(
                f"stiffness.k_ts = {stiffness.k_ts!r} N m/rad{who}: with its {len(contact_p)} contact(s) in force the "
                f"tilt stiffness about {name} is {k_total:.0f} N m/rad, not above {toppling}; expected a stiffer "
                "k_ts (and k_fs), or the robot falls over its springs")
    k_ts = stiffness.minimum("k_ts")
    if k_ts <= m_g_h:
        warnings.warn(f"stiffness.k_ts = {k_ts:g} N m/rad{who} is not above {toppling}: one contact alone cannot "
                      "hold the robot upright, so single support (steps, walking) will not be explained; expected "
                      f"k_ts > {m_g_h:.0f} N m/rad unless the robot always stands on several contacts",
                      ConfigWarning, stacklevel=2)


def _check_contacts(contacts, where: str) -> None:
    """A ConfigError unless ``contacts`` is a list of ``{name, frame}`` tables with distinct names
    (``where`` names the configuration)."""
    example = 'e.g. contacts = [{ name = "left_foot", frame = "l_sole", sole = [-0.1, 0.15, -0.05, 0.05] }, ...]'
    if not isinstance(contacts, list):
        raise ConfigError(f"contacts = {contacts!r}{where}; expected a list of contact tables, {example}")
    seen: set[str] = set()
    for i, c in enumerate(contacts):
        if not isinstance(c, dict) or not {"name", "frame"} <= set(c) <= {"name", "frame", "sole"} or not all(
                isinstance(c[k], str) and c[k] for k in ("name", "frame")):
            raise ConfigError(f"contacts[{i}] = {c!r}{where}; expected a table with a name and a frame "
                              f"(non-empty strings) and optionally a sole, {example}")
        if "sole" in c:
            sole = c["sole"]
            ok = (isinstance(sole, list) and len(sole) == 4 and all(_finite_number(v) for v in sole)
                  and sole[0] < 0.0 < sole[1] and sole[2] < 0.0 < sole[3])
            if not ok:
                raise ConfigError(f"contacts[{i}].sole = {sole!r}{where}; expected [x_min, x_max, y_min, y_max] in m "
                                  "in the contact frame, with x_min < 0 < x_max and y_min < 0 < y_max (the contact "
                                  "point on the sole)")
            c["sole"] = tuple(float(v) for v in sole)
        if c["name"] in seen:
            raise ConfigError(f"contacts[{i}] repeats the contact name '{c['name']}'{where}; expected distinct names")
        seen.add(c["name"])


def _resolve(path: str, base: Path | None) -> str:
    if path.startswith("erd:"):
        return str(example_robot_data_dir() / path[4:])
    p = Path(path)
    if not p.is_absolute() and base is not None:
        p = base / p
    return str(p.resolve())


@dataclass
class LocalKinematics:
    """What the robot's own model says at one instant, in the local frame."""

    inputs: Inputs
    imu: ImuPlacement
    contact_p: np.ndarray
    """(C, 3) contact positions, m."""
    contact_R: np.ndarray
    """(C, 3, 3) contact orientations."""
    links: np.ndarray
    """(L, 3) positions of the tracked links, m."""


@contextlib.contextmanager
def _stderr_captured() -> Iterator[Callable[[], list[str]]]:
    """Hold what the process writes on file descriptor 2 (C libraries' messages) during the block;
    yields a function returning its lines (read after the block).  Python's own ``sys.stderr`` is
    the same descriptor, so a warning raised inside goes there too."""
    lines: list[str] = []
    try:
        saved = os.dup(2)
    except OSError:  # no descriptor 2 (a detached process): nothing to hold
        yield lambda: lines
        return
    with tempfile.TemporaryFile() as held:
        try:
            sys.stderr.flush()
            os.dup2(held.fileno(), 2)
            yield lambda: lines
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            lines.extend(x for x in held.read().decode(errors="replace").splitlines() if x.strip())


class RobotModel:
    """Pinocchio model of a robot with a free-flyer root, built from a :class:`RobotConfig`.

    Configuration vectors are pinocchio's: ``q = (x, y, z, qx, qy, qz, qw, joints...)`` and
    ``v = (body linear velocity, body angular velocity, joint velocities)``.
    """

    def __init__(self, config: RobotConfig | str | Path = DEFAULT_ROBOT):
        if not isinstance(config, RobotConfig):
            config = RobotConfig.load(config)
        self.config = config
        if not Path(config.urdf).exists():
            raise ConfigError(f"URDF of robot '{config.name}' not found: {config.urdf}")
        with _stderr_captured() as said:  # urdfdom prints its parse errors on the C stderr
            try:
                full = pin.buildModelFromUrdf(config.urdf, pin.JointModelFreeFlyer())
            except Exception as err:  # pinocchio raises plain RuntimeError/ValueError
                failed: Exception | None = err
            else:
                failed = None
        if failed is not None:
            detail = " ".join(said()).strip()
            raise ConfigError(f"cannot read URDF {config.urdf}: {failed}" + (f" ({detail})" if detail else "")) \
                from failed
        for i in range(1, full.njoints):
            link_mass = float(full.inertias[i].mass)
            if not (math.isfinite(link_mass) and link_mass >= 0):
                raise ConfigError(f"the mass of the links moved by joint '{full.names[i]}' in the URDF "
                                  f"{config.urdf} is {link_mass!r} kg; expected a non-negative, finite mass")
            inertia = np.asarray(full.inertias[i].inertia, dtype=float)
            moments = np.linalg.eigvalsh(0.5 * (inertia + inertia.T)) if np.isfinite(inertia).all() else None
            if moments is None or moments[0] < -1e-9 * max(1.0, float(np.abs(moments).max())):
                shown = "not finite" if moments is None else f"principal moments {np.round(moments, 6).tolist()} kg m^2"
                raise ConfigError(f"the rotational inertia of the links moved by joint '{full.names[i]}' in the URDF "
                                  f"{config.urdf} is not positive semi-definite ({shown}); expected each link's "
                                  "<inertia> to have non-negative principal moments")
        q_ref = pin.neutral(full)
        if config.srdf:
            try:
                pin.loadReferenceConfigurations(full, config.srdf, False)
            except Exception as err:
                raise ConfigError(f"cannot read SRDF {config.srdf}: {err}") from err
            refs = full.referenceConfigurations
            if config.reference in refs:
                q_ref = np.array(refs[config.reference])
        for jname, value in config.reference_joints.items():
            if not full.existJointName(jname):
                raise ConfigError(f"reference_joints names unknown joint '{jname}' of robot '{config.name}'")
            q_ref[full.joints[full.getJointId(jname)].idx_q] = value
        if config.lock_joints:
            pattern = re.compile(config.lock_joints)
            locked = [full.getJointId(n) for n in full.names[2:] if pattern.search(n)]
            self.model = pin.buildReducedModel(full, locked, q_ref) if locked else full
            keep = [i for i, n in enumerate(full.names) if not (i >= 2 and pattern.search(n))]
            q_ref = np.concatenate([q_ref[:7]] + [
                q_ref[full.joints[i].idx_q:full.joints[i].idx_q + full.joints[i].nq] for i in keep[2:]])
        else:
            self.model = full
        self.data = self.model.createData()
        model = self.model
        for frame in [c.frame for c in config.contacts] + [config.imu_frame] + list(config.links):
            if not model.existFrame(frame):
                raise ConfigError(f"frame '{frame}' of robot configuration '{config.name}' is not in the URDF "
                                  f"{config.urdf}")
        self.contact_frame_ids = [model.getFrameId(c.frame) for c in config.contacts]
        self.imu_frame_id = model.getFrameId(config.imu_frame)
        self.link_frame_ids = [model.getFrameId(f) for f in config.links]
        self.mass = float(sum(model.inertias[i].mass for i in range(1, model.njoints)))
        if not self.mass > 0:
            raise ConfigError(f"the total mass of robot '{config.name}' in the URDF {config.urdf} is {self.mass!r} kg; "
                              "expected a positive mass")
        self.joint_names: tuple[str, ...] = tuple(model.names[2:])
        self.q_reference = self._place_on_ground(q_ref)
        self.check_toppling(self.q_reference)

    def check_toppling(self, q: np.ndarray) -> None:
        """:func:`check_toppling` with every contact in force in the configuration ``q`` (the
        reference posture when the model is built)."""
        pin.framesForwardKinematics(self.model, self.data, q)
        com = pin.centerOfMass(self.model, self.data, q)
        cp = np.array([self.data.oMf[i].translation for i in self.contact_frame_ids])
        cR = np.array([self.data.oMf[i].rotation for i in self.contact_frame_ids])
        check_toppling(self.config.stiffness, self.mass, com, cp, cR, self.config.gravity, self.config.name)

    # ------------------------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.config.name

    @property
    def contact_names(self) -> tuple[str, ...]:
        return self.config.contact_names

    @property
    def link_names(self) -> tuple[str, ...]:
        return tuple(self.config.links)

    def contact_params(self) -> list[ContactParams]:
        """The nominal spring-damper of each contact."""
        p = self.config.stiffness.params()
        return [p for _ in self.config.contacts]

    def _place_on_ground(self, q: np.ndarray) -> np.ndarray:
        """Move the free-flyer so that the contacts' mean lies at the origin, on the plane z = 0."""
        q = q.copy()
        q[:3] = 0.0
        q[3:7] = [0.0, 0.0, 0.0, 1.0]
        pin.framesForwardKinematics(self.model, self.data, q)
        mean = np.mean([self.data.oMf[i].translation for i in self.contact_frame_ids], axis=0)
        q[:3] = -mean
        return q

    def joint_index(self, name: str) -> int:
        """Index of joint ``name`` in the joint part of q (after the 7 free-flyer entries)."""
        if not self.model.existJointName(name):
            raise ConfigError(f"robot '{self.name}' has no joint '{name}'")
        jid = self.model.getJointId(name)
        return self.model.joints[jid].idx_q - 7

    # ------------------------------------------------------------------------------------------
    def kinematics(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> LocalKinematics:
        """The paper's inputs, the IMU placement and motion, and the contacts, in the local frame.

        Args:
            q, v, a: configuration, velocity and acceleration of the robot in the local frame
                (pinocchio conventions, free-flyer velocity in the body frame).
        """
        row = {key: value[0] for key, value in self.local_kinematics(q[None], v[None], a[None]).items()}
        inputs = Inputs(self.mass, row["com"], row["com_vel"], row["com_acc"], row["inertia"], row["inertia_dot"],
                        row["sigma"], row["sigma_dot"])
        imu = ImuPlacement(row["imu_R"], row["imu_p"], row["imu_v"], row["imu_a"], row["imu_w"])
        model, data = self.model, self.data  # after local_kinematics: the joint placements of q
        contacts = [pin.updateFramePlacement(model, data, i) for i in self.contact_frame_ids]
        cp = np.array([M.translation for M in contacts]).reshape(-1, 3)
        cR = np.array([M.rotation for M in contacts]).reshape(-1, 3, 3)
        links = np.array([pin.updateFramePlacement(model, data, i).translation
                          for i in self.link_frame_ids]).reshape(-1, 3)
        return LocalKinematics(inputs, imu, cp, cR, links)

    def local_kinematics(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> dict[str, np.ndarray]:
        """:meth:`kinematics` along a trajectory, without the contacts: the paper's inputs and the IMU
        placement and motion of each row of ``q`` (N, nq), ``v`` and ``a`` (N, nv), as arrays named as
        the Recording fields (``com`` ... ``imu_w``).

        Per row, pinocchio's forward kinematics, centre of mass, centroidal momentum and its time
        variation, and ``dccrba`` (the composite inertia and the rate of the centroidal map); the
        rest is formed over all rows at once.
        """
        model, data = self.model, self.data
        n = len(q)
        m = self.mass
        c, dc, ddc, hg_ang, dhg_ang = (np.zeros((n, 3)) for _ in range(5))
        I_G = np.zeros((n, 3, 3))
        dAg = np.zeros((n, 6, 6))  # the rate of the centroidal map's free-flyer columns
        Ag_lin = np.zeros((n, 3, 6))
        imu_H = np.zeros((n, 4, 4))
        imu_vel = np.zeros((n, 6))
        imu_acc = np.zeros((n, 3))
        com, vcom, acom = data.com, data.vcom, data.acom
        fid = self.imu_frame_id
        for k in range(n):
            qk, vk = q[k], v[k]
            pin.forwardKinematics(model, data, qk, vk, a[k])
            # the centre of mass and the centroidal momentum from the kinematics just computed
            pin.centerOfMass(model, data, pin.KinematicLevel.ACCELERATION, False)
            c[k], dc[k], ddc[k] = com[0], vcom[0], acom[0]
            pin.computeCentroidalMomentumTimeVariation(model, data)
            hg_ang[k], dhg_ang[k] = data.hg.angular, data.dhg.angular
            imu_H[k] = pin.updateFramePlacement(model, data, fid).homogeneous
            imu_vel[k] = pin.getFrameVelocity(model, data, fid, pin.LOCAL_WORLD_ALIGNED).vector
            imu_acc[k] = pin.getFrameClassicalAcceleration(model, data, fid, pin.LOCAL_WORLD_ALIGNED).linear
            pin.dccrba(model, data, qk, vk)
            I_G[k] = data.Ig.inertia
            dAg[k] = data.dAg[:, :6]
            Ag_lin[k] = data.Ag[:3, :6]
        Sc = _skews(c)
        I_l = I_G - m * Sc @ Sc
        sigma = hg_ang + (m * Sc @ dc[..., None])[..., 0]
        dsigma = dhg_ang + (m * Sc @ ddc[..., None])[..., 0]
        dI = _inertia_rate_of(m, c, dc, I_l, dAg, Ag_lin, q, v)
        return {"com": c, "com_vel": dc, "com_acc": ddc, "inertia": I_l, "inertia_dot": dI, "sigma": sigma,
                "sigma_dot": dsigma, "imu_R": imu_H[:, :3, :3].copy(), "imu_p": imu_H[:, :3, 3].copy(),
                "imu_v": imu_vel[:, :3].copy(), "imu_a": imu_acc, "imu_w": imu_vel[:, 3:].copy()}

    def _inertia_rate(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        r"""dI_l/dt, I_l = sum_i (R_i I_i R_i^T - m_i [c_i]x^2) about the origin, moving at ``v``:
        :func:`_inertia_rate_of` after pinocchio's ``dccrba`` (on a Data of its own), as
        :meth:`local_kinematics` forms it.  Equal to the analytic per-body sum
        (:meth:`_inertia_rate_bodies`, tests/test_robot.py) to rounding.
        """
        model = self.model
        data = getattr(self, "_rate_data", None)
        if data is None:
            data = self._rate_data = model.createData()
        pin.dccrba(model, data, q, v)
        c = data.com[0][None]
        I_l = data.oYcrb[0].matrix()[3:, 3:][None]  # the whole robot's rotational inertia about the origin
        return _inertia_rate_of(self.mass, c, data.vcom[0][None], I_l, data.dAg[:, :6][None], data.Ag[:3, :6][None],
                                q[None], v[None])[0]

    def _inertia_rate_bodies(self) -> np.ndarray:
        r"""dI_l/dt summed analytically over the bodies (after ``forwardKinematics(q, v)``): the
        reference of :meth:`_inertia_rate`.

        d(R I R^T)/dt = [w]x R I R^T - R I R^T [w]x and d(-m [c]x^2)/dt = -m ([dc]x [c]x + [c]x [dc]x),
        with ``[a]x [b]x = b a^T - (a . b) 1``; summed over the bodies with mass at once.
        """
        model, data = self.model, self.data
        bodies = getattr(self, "_massive", None)
        if bodies is None:
            idx = [i for i in range(1, model.njoints) if model.inertias[i].mass != 0.0]
            bodies = (idx, np.array([model.inertias[i].mass for i in idx]),
                      np.array([model.inertias[i].lever for i in idx]).reshape(-1, 3),
                      np.array([model.inertias[i].inertia for i in idx]).reshape(-1, 3, 3))
            self._massive = bodies
        idx, m, lever, inertia = bodies
        if not idx:
            return np.zeros((3, 3))
        R = np.array([data.oMi[i].rotation for i in idx])
        t = np.array([data.oMi[i].translation for i in idx])
        ang = np.array([data.v[i].angular for i in idx])
        lin = np.array([data.v[i].linear for i in idx])
        w = np.einsum("nij,nj->ni", R, ang)
        c = t + np.einsum("nij,nj->ni", R, lever)
        dc = np.einsum("nij,nj->ni", R, lin + np.cross(ang, lever))
        IR = R @ inertia @ R.transpose(0, 2, 1)
        Sw = np.zeros((len(idx), 3, 3))
        Sw[:, 0, 1], Sw[:, 0, 2], Sw[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
        Sw[:, 1, 0], Sw[:, 2, 0], Sw[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
        rot = (Sw @ IR - IR @ Sw).sum(axis=0)
        outer = np.einsum("n,ni,nj->ij", m, c, dc)
        dot = float(np.sum(m * np.sum(c * dc, axis=1)))
        return rot - (outer + outer.T - 2.0 * dot * np.eye(3))


def _skews(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices ``[v]x`` of (N, 3) vectors."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def _inertia_rate_of(m: float, c: np.ndarray, dc: np.ndarray, I_l: np.ndarray, dAg: np.ndarray, Ag_lin: np.ndarray,
                     q: np.ndarray, v: np.ndarray) -> np.ndarray:
    r"""dI_l/dt of (N, 3, 3) from what pinocchio's ``dccrba`` leaves at each of N configurations.

    ``dccrba`` sums the rates ``dY_i = v_i x* Y_i - Y_i v_i x`` of the bodies' spatial inertias
    (world frame, about the origin) into ``dY``, whose angular block is dI_l, and forms the
    free-flyer columns of the centroidal map's rate ``dAg = dY A + Y (v_1 x) A`` with ``A`` the
    adjoint of the base placement, ``Y`` the composite inertia and ``v_1`` the base's spatial
    velocity, before moving their angular rows to the CoM (``+ c x dAg_lin + dc x Ag_lin``).
    Undone: ``dY = dAg A^-1 - Y (v_1 x)``, whose angular block is
    ``D_ang R^T - D_lin R^T [p]x - m [c]x [v]x - I_l [w]x`` (``R, p`` the base placement,
    ``w, v`` the angular and linear parts of ``v_1``).

    Args:
        m: total mass, kg; c, dc: (N, 3) CoM and its velocity; I_l: (N, 3, 3) rotational inertia
        about the origin; dAg: (N, 6, 6) free-flyer columns of ``data.dAg``; Ag_lin: (N, 3, 6)
        linear rows of those of ``data.Ag``; q, v: (N, nq), (N, nv) configurations and velocities.
    """
    R = Rotation.from_quat(q[:, 3:7]).as_matrix() if len(q) else np.zeros((0, 3, 3))  # (older scipy: no empty)
    p = q[:, :3]
    w = np.einsum("nij,nj->ni", R, v[:, 3:6])
    lin = np.einsum("nij,nj->ni", R, v[:, :3]) + np.cross(p, w)
    Sc = _skews(c)
    D = dAg[:, 3:] + Sc @ dAg[:, :3] + _skews(dc) @ Ag_lin  # the angular rows, about the origin
    RT = R.transpose(0, 2, 1)
    return (D[:, :, 3:] @ RT - D[:, :, :3] @ RT @ _skews(p) - m * Sc @ _skews(lin)
            - I_l @ _skews(w))
