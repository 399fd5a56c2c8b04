"""Scenarios: what the simulated robot does, and which hidden effects the world holds.

A scenario is a TOML file (the built-in ones live in ``flexforce/datasets/scenarios``)::

    name = "com-step"
    description = "..."
    robot = "romeo"          # built-in robot name or .toml path (overridable on the command line)
    duration = 6.0           # s
    rate = 200.0             # Hz, sampling of the recording
    sim_rate = 1000.0        # Hz, integration (a multiple of rate)
    seed = 0                 # noise seed
    touchdown = "floor"      # a landing foot's spring starts unloaded where it reaches the floor;
                             # "relaxed" (where it is at the scheduled landing) or "deflected"
                             # (its rest is its placement in the local frame: a preload)

    [[base]]                 # pelvis motion in the local frame, summed over segments (m)
    kind = "step"            # "step" (minimum-jerk transition) or "sine" (smooth envelope)
    start = 1.0
    duration = 0.8
    offset = [0.02, 0.0, 0.0]
    target = "com"           # the offset is the CoM's; the pelvis moves so the CoM does

    [[joint]]                # joint motion added to the reference posture (rad)
    joint = { romeo = "LShoulderPitch", talos = "arm_left_1_joint" }
    kind = "sine"; start = 1.0; duration = 4.0; amplitude = 0.3; frequency = 0.5

    [[swing]]                # a contact lifts at `lift`, moves by `displacement` and lands at `land`
    contact = "right_foot"; lift = 2.0; land = 2.8; displacement = [0.1, 0.0, 0.0]; height = 0.03
    travel = [0.25, 0.75]    # fractions of the swing with horizontal motion (default [0, 1])

    [[effects]]              # hidden effects, see flexforce.datasets.sim.effects
    type = "external-wrench"; link = "@base"; force = [40.0, 0.0, 0.0]; start = 1.0; duration = 0.2

    [imu_noise]              # the simulated IMU (same keys as ImuNoise, default the robot's),
    scale = 2.0              # and a factor on its white-noise densities (mismatched sensor)
    [ft_noise]               # the simulated F/T sensors (same keys as FtNoise, plus ``scale``)

    [ambient]                # ambient disturbance of the world (see Ambient); ``ambient = false`` removes it
    linear = 0.055           # m/s^2, RMS linear acceleration of the flexibility
    corner = 20.0            # Hz, band limit (second-order low-pass)
    scale = 3.0              # factor on the levels (kind = "wrench": force [N], torque [N m])

    [walk]                   # a walk: generates the [[base]] and [[swing]] items (see Walk)
    steps = 20; stride = 0.1; double_support = 1.4; single_support = 0.8

    [posture.icub]           # this robot's reference posture for the scenario (rad)
    l_knee = -0.7

The noise sections describe the simulated sensors only: the estimators take their noise model
from the robot configuration, so a scenario that changes it is a mismatched case.

Step and sine segments have continuous position, velocity and acceleration, so the joints the
robot tracks (stiff position control) are smooth; contacts switch only at swing events.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flexforce.errors import ConfigError
from flexforce.options import read_toml

SCENARIOS_DIR = Path(__file__).resolve().parent / "scenarios"
DEFAULT_SCENARIO = "push-pitch"


def builtin_scenarios() -> list[str]:
    """Names of the scenarios shipped with flexforce."""
    return sorted(p.stem for p in SCENARIOS_DIR.glob("*.toml"))


# ----------------------------------------------------------------------------------------------
# Smooth time profiles with analytic derivatives
# ----------------------------------------------------------------------------------------------


def minjerk(tau: float) -> tuple[float, float, float]:
    """Minimum-jerk 0 -> 1 on tau in [0, 1]: value, d/dtau, d2/dtau2 (zero rates at both ends)."""
    if tau <= 0.0:
        return 0.0, 0.0, 0.0
    if tau >= 1.0:
        return 1.0, 0.0, 0.0
    t2 = tau * tau
    t3 = t2 * tau
    return (10 * t3 - 15 * t3 * tau + 6 * t3 * t2,
            30 * t2 - 60 * t3 + 30 * t3 * tau,
            60 * tau - 180 * t2 + 120 * t3)


def bump(tau: float) -> tuple[float, float, float]:
    """64 tau^3 (1 - tau)^3: 0 at both ends with zero rates, 1 at tau = 0.5."""
    if tau <= 0.0 or tau >= 1.0:
        return 0.0, 0.0, 0.0
    u = 1.0 - tau
    f = 64 * tau**3 * u**3
    df = 64 * (3 * tau**2 * u**3 - 3 * tau**3 * u**2)
    d2f = 64 * (6 * tau * u**3 - 18 * tau**2 * u**2 + 6 * tau**3 * u)
    return f, df, d2f


@dataclass(frozen=True)
class Segment:
    """A smooth motion segment: a minimum-jerk step, or a sine under a smooth envelope."""

    kind: str
    start: float
    duration: float
    value: np.ndarray
    """Offset of a step, amplitude of a sine (m or rad, per axis)."""
    frequency: float = 0.0
    """Hz, for a sine."""
    ramp: float = 0.0
    """s, envelope rise and fall time of a sine (one period by default)."""

    def __call__(self, t: float):
        """Value, first and second time derivatives at time ``t`` (s)."""
        if self.kind == "step":
            s, ds, dds = minjerk((t - self.start) / self.duration)
            return self.value * s, self.value * ds / self.duration, self.value * dds / self.duration**2
        # sine with an envelope e(t) = minjerk(rise) * minjerk(fall)
        zero = np.zeros_like(self.value)
        if t <= self.start or t >= self.start + self.duration:
            return zero, zero.copy(), zero.copy()
        ramp = self.ramp or min(1.0 / self.frequency, 0.5 * self.duration)
        a, da, dda = minjerk((t - self.start) / ramp)
        b, db, ddb = minjerk((self.start + self.duration - t) / ramp)
        da, dda = da / ramp, dda / ramp**2
        db, ddb = -db / ramp, ddb / ramp**2
        e = a * b
        de = da * b + a * db
        dde = dda * b + 2 * da * db + a * ddb
        om = 2 * math.pi * self.frequency
        ph = om * (t - self.start)
        s, ds, dds = math.sin(ph), om * math.cos(ph), -om * om * math.sin(ph)
        f = e * s
        df = de * s + e * ds
        ddf = dde * s + 2 * de * ds + e * dds
        return self.value * f, self.value * df, self.value * ddf


@dataclass(frozen=True)
class Swing:
    """A contact lifting off, moving in the air and landing elsewhere (local frame)."""

    contact: str
    lift: float
    land: float
    displacement: np.ndarray
    height: float = 0.03
    travel: tuple = (0.0, 1.0)
    """Fractions of the swing between which the foot moves horizontally (minimum jerk); before and
    after, it only rises and descends.  A walk travels in the middle half, (0.25, 0.75): a foot that
    touches the floor before its planned landing (the stance leg sinking) or leaves it after its
    planned lift (its spring still pushing) is then not dragged along the floor."""

    def __call__(self, t: float):
        """Displacement of the contact from its initial placement, with derivatives."""
        T = self.land - self.lift
        tau = (t - self.lift) / T
        a, b = self.travel
        s, ds, dds = minjerk((tau - a) / (b - a))
        ds, dds = ds / (b - a), dds / (b - a) ** 2
        h, dh, ddh = bump(tau)
        ez = np.array([0.0, 0.0, 1.0])
        return (self.displacement * s + ez * self.height * h,
                (self.displacement * ds + ez * self.height * dh) / T,
                (self.displacement * dds + ez * self.height * ddh) / T**2)


TOUCHDOWN_MODES = ("floor", "relaxed", "deflected")


def _number(where: str, key: str, value, unit: str, expect: str, ok) -> float:
    """``value`` as a float, or a ConfigError naming the key, the value, its unit and what is expected."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = math.nan
    if isinstance(value, bool) or not math.isfinite(x) or not ok(x):
        raise ConfigError(f"{where}: {key} = {value!r} {unit}: expected {expect}")
    return x


def _timing(where: str, key: str, value) -> None:
    """A ConfigError unless ``value`` suits the scenario's timing field ``key`` (duration, rate,
    sim_rate: positive, finite numbers; seed: a whole number >= 0).  A string is refused, not
    converted: ``duration = "five"`` is a mistake in the file."""
    if key == "seed":
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < 0:
            raise ConfigError(f"{where}: seed = {value!r}: expected a noise seed, a whole number >= 0")
        return
    unit, what = TIMING_FIELDS[key]
    if (isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value)
            or not float(value) > 0):
        raise ConfigError(f"{where}: {key} = {value!r} {unit}: expected {what}, a positive, "
                          "finite number (duration, rate and sim_rate must be positive)")
    bound = TIMING_MAX.get(key)
    if bound is not None and float(value) > bound:
        raise ConfigError(f"{where}: {key} = {value!r} {unit}: expected {what}, at most {bound:g} {unit} (a "
                          "robot's sensors sample at tens of Hz to a few kHz; the integration a few times faster)")


TIMING_FIELDS = {"duration": ("s", "the recording's length in seconds"),
                 "rate": ("Hz", "the recording's sampling rate in Hz"),
                 "sim_rate": ("Hz", "the integration rate in Hz")}
"""The scenario's timing fields checked on every assignment: their units and meaning."""

TIMING_MAX = {"rate": 10_000.0, "sim_rate": 50_000.0}
"""Upper bounds of the rates, Hz: the recording's sampling (as ``[ros] rate`` of a robot
configuration) and the integration (every step integrates the multibody dynamics: at the bound a
second of simulation is 50,000 steps)."""

MAX_SAMPLES = 1_000_000
"""Most recorded samples (``duration * rate``) a scenario may ask for: the simulator keeps the whole
recording, its ground truth and its per-sample kinematics in memory until it writes them."""

BYTES_PER_SAMPLE = 10_000
"""An upper estimate of the simulator's peak memory per recorded sample, bytes (kinematics,
ground truth, sensors, ambient table at ``sim_rate = 5 * rate``); it only sizes the message of
:data:`MAX_SAMPLES`."""


@dataclass(frozen=True)
class Ambient:
    """The world's ambient disturbance: what no model holds (floor vibration, cable pulls, air,
    servo chatter).  ``kind = "acceleration"`` (default): a random acceleration of the flexibility,
    produced by a wrench on the base through the simulated robot's own inertia (pinocchio's CRBA);
    ``kind = "wrench"``: a random force and torque on the base (world axes, torque about the base
    origin), whatever acceleration they cause.  Gaussian, independent per axis.

    It is a property of the simulated world, written in the scenario; the estimators know nothing
    of it beyond their own process-noise assumption.
    """

    enabled: bool = True
    kind: str = "acceleration"
    """``acceleration`` (levels ``linear``, ``angular``) or ``wrench`` (levels ``force``, ``torque``)."""
    linear: float | None = None
    """RMS linear acceleration per axis, m/s^2.  Default: the accelerometer's white noise of the
    robot configuration at the recording rate (``accel_density * sqrt(rate)``): a world shaken at
    the level its IMU just resolves in one sample."""
    angular: float | None = None
    """RMS angular acceleration per axis, rad/s^2.  Default: ``linear / l``, ``l`` the distance
    from the IMU to the contacts' centroid in the reference posture (the rotation that moves the
    IMU by as much)."""
    corner: float | None = None
    """Band limit, Hz.  None: white at the recording's samples and linear in between (a flat
    spectrum up to the recording's Nyquist frequency).  Else white at the integration rate through
    a second-order Butterworth low-pass with this corner, scaled so that the RMS is the level."""
    force: float | None = None
    """RMS force per axis on the base, N (``kind = "wrench"``, required)."""
    torque: float | None = None
    """RMS torque per axis on the base, N m (``kind = "wrench"``, required)."""
    scale: float = 1.0
    """Factor on both levels (3 gives the mismatched case "ambient x3")."""

    @classmethod
    def parse(cls, raw, where: str, sim_rate: float) -> Ambient:
        if isinstance(raw, bool):
            return cls(enabled=raw)
        if not isinstance(raw, dict):
            raise ConfigError(f"{where}: ambient = {raw!r}: expected true, false or a table "
                              "with linear [m/s^2], angular [rad/s^2], corner [Hz], scale")
        known = {"enabled", "kind", "linear", "angular", "force", "torque", "corner", "scale"}
        unknown = set(raw) - known
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)} in [ambient]; known: {sorted(known)}")
        enabled = raw.get("enabled", True)
        if not isinstance(enabled, bool):
            raise ConfigError(f"{where}: ambient.enabled = {enabled!r}: expected true or false")
        kind = raw.get("kind", "acceleration")
        if kind not in ("acceleration", "wrench"):
            raise ConfigError(f"{where}: ambient.kind = {kind!r}: expected 'acceleration' or 'wrench'")
        out = {"enabled": enabled, "kind": kind}
        levels = ((("linear", "m/s^2"), ("angular", "rad/s^2")) if kind == "acceleration"
                  else (("force", "N"), ("torque", "N m")))
        for key in ({"linear", "angular", "force", "torque"} - {k for k, _ in levels}) & set(raw):
            raise ConfigError(f"{where}: ambient.{key} does not apply to kind = {kind!r}; "
                              f"its levels are {', '.join(k for k, _ in levels)}")
        if kind == "wrench":
            for key, unit in levels:
                if raw.get(key) is None:
                    raise ConfigError(f"{where}: ambient.{key} is missing: a wrench disturbance needs an RMS "
                                      f"{key} per axis [{unit}]")
        for key, unit in levels:
            if raw.get(key) is not None:
                out[key] = _number(where, f"ambient.{key}", raw[key], unit, "a non-negative RMS level",
                                   lambda x: x >= 0.0)
        if raw.get("corner") is not None:
            nyquist = 0.5 * sim_rate
            out["corner"] = _number(where, "ambient.corner", raw["corner"], "Hz",
                                    f"a corner frequency above 0 and below half the integration rate ({nyquist:g} Hz)",
                                    lambda x: 0.0 < x < nyquist)
        if "scale" in raw:
            out["scale"] = _number(where, "ambient.scale", raw["scale"], "(factor)", "a non-negative factor",
                                   lambda x: x >= 0.0)
        return cls(**out)


@dataclass(frozen=True)
class Walk:
    """A straight walk forward, generated as ``[[base]]`` and ``[[swing]]`` items.

    Each step is a double-support phase, where the CoM moves (minimum jerk) over the next stance
    foot, then a single-support phase, where the other foot lifts, moves forward and lands flat.
    The first and last swings cover half a stride, so that the feet start and end side by side;
    after the last landing the CoM returns to the middle of the feet.
    """

    start: float = 1.0
    """Start of the first weight shift, s."""
    steps: int = 20
    """Number of swings."""
    stride: float = 0.10
    """Forward displacement of a swinging foot, m (half of it on the first and last swings)."""
    height: float = 0.03
    """Lift of a swinging foot at mid-swing, m."""
    double_support: float = 0.8
    """Duration of each weight shift (both feet in contact), s."""
    single_support: float = 0.7
    """Duration of each swing (one foot in contact), s."""
    shift: float = 1.0
    """Fraction of the horizontal way from the CoM to the stance foot covered by a weight shift."""
    settle: float = 1.5
    """Duration of the final shift of the CoM to the middle of the feet, s."""
    first: str = "right_foot"
    """The first swinging foot."""
    other: str = "left_foot"
    """The other foot."""
    travel: tuple = (0.25, 0.75)
    """Fractions of each swing between which the foot moves forward (see :class:`Swing`)."""

    @classmethod
    def parse(cls, raw, where: str) -> Walk:
        if not isinstance(raw, dict):
            raise ConfigError(f"{where}: walk = {raw!r}: expected a table (see flexforce.datasets.sim.scenario.Walk)")
        known = set(cls.__dataclass_fields__)
        unknown = set(raw) - known
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)} in [walk]; known: {sorted(known)}")
        out = dict(raw)
        steps = raw.get("steps", cls.steps)
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ConfigError(f"{where}: walk.steps = {steps!r}: expected a whole number of swings, at least 1")
        for key, unit, expect, ok in (
                ("start", "s", "a time at or after 0", lambda x: x >= 0.0),
                ("stride", "m", "a forward displacement between -0.5 and 0.5 m", lambda x: abs(x) <= 0.5),
                ("height", "m", "a lift between 0 and 0.2 m", lambda x: 0.0 <= x <= 0.2),
                ("double_support", "s", "a positive duration", lambda x: x > 0.0),
                ("single_support", "s", "a positive duration", lambda x: x > 0.0),
                ("shift", "(fraction)", "a fraction between 0 and 1", lambda x: 0.0 <= x <= 1.0),
                ("settle", "s", "a positive duration", lambda x: x > 0.0)):
            if key in raw:
                out[key] = _number(where, f"walk.{key}", raw[key], unit, expect, ok)
        if "travel" in raw:
            tr = raw["travel"]
            if (not isinstance(tr, (list, tuple)) or len(tr) != 2
                    or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in tr)
                    or not 0.0 <= tr[0] < tr[1] <= 1.0):
                raise ConfigError(f"{where}: walk.travel = {tr!r} (fractions of the swing): "
                                  "expected [start, end] with 0 <= start < end <= 1")
            out["travel"] = (float(tr[0]), float(tr[1]))
        for key in ("first", "other"):
            if key in raw and not isinstance(raw[key], str):
                raise ConfigError(f"{where}: walk.{key} = {raw[key]!r}: expected a contact name")
        walk = cls(**out)
        if walk.first == walk.other:
            raise ConfigError(f"{where}: walk.first and walk.other are both '{walk.first}': "
                              "expected two different feet")
        return walk

    @property
    def end(self) -> float:
        """When the CoM is back in the middle of the feet, s."""
        return self.start + self.steps * (self.double_support + self.single_support) + self.settle

    def items(self) -> tuple[list[dict], list[dict]]:
        """The ``[[base]]`` and ``[[swing]]`` items of the walk."""
        base, swing = [], []
        period = self.double_support + self.single_support
        for i in range(self.steps):
            foot, stance = (self.first, self.other) if i % 2 == 0 else (self.other, self.first)
            t0 = self.start + i * period
            base.append({"toward": stance, "fraction": self.shift, "start": t0, "duration": self.double_support,
                         "horizontal": True})
            length = 0.5 * self.stride if i in (0, self.steps - 1) else self.stride
            swing.append({"contact": foot, "lift": t0 + self.double_support, "land": t0 + period,
                          "displacement": [length, 0.0, 0.0], "height": self.height, "travel": list(self.travel)})
        base.append({"toward": "middle", "start": self.start + self.steps * period, "duration": self.settle,
                     "horizontal": True})
        return base, swing


@dataclass
class Scenario:
    """A parsed scenario file (see the module documentation)."""

    name: str
    robot: str = "romeo"
    description: str = ""
    duration: float = 5.0
    rate: float = 200.0
    sim_rate: float = 1000.0
    seed: int = 0
    base: list[dict] = field(default_factory=list)
    joint: list[dict] = field(default_factory=list)
    swing: list[dict] = field(default_factory=list)
    effects: list[dict] = field(default_factory=list)
    imu_noise: dict = field(default_factory=dict)
    ft_noise: dict = field(default_factory=dict)
    noise: bool = True
    """Add sensor noise and the ambient disturbance; False gives an exact world and readings (tests)."""
    ambient: bool | dict = True
    """The world's ambient disturbance: true (the default levels of :class:`Ambient`), false (none),
    or an ``[ambient]`` table of :class:`Ambient` fields."""
    touchdown: str = "floor"
    """Rest placement (foothold) of a landing contact's spring (see :mod:`flexforce.datasets.sim.simulator`).
    ``"floor"``: where the descending foot reaches the floor, flat on it; contact from that instant,
    lift-off when the spring stops pushing (no force jump at either).  ``"relaxed"``: the foot's
    actual world placement at the scheduled landing (unloaded, but footholds inherit the body's
    tilt).  ``"deflected"``: its placement in the local frame (the spring starts preloaded by the
    flexibility's deflection; a mismatched case)."""
    walk: dict = field(default_factory=dict)
    """A ``[walk]`` table of :class:`Walk` fields; empty for none."""
    posture: dict = field(default_factory=dict)
    """Per robot, joint values (rad) overriding its reference posture for this scenario, e.g.
    ``[posture.icub]`` with bent knees for a robot whose reference has straight legs (singular for
    the legs' inverse kinematics)."""
    source: str = ""

    def __setattr__(self, key: str, value) -> None:
        """Assign a field; ``duration``, ``rate``, ``sim_rate`` and ``seed`` are checked on every
        assignment (the file's values and a command line's overrides alike).

        Raises:
            ConfigError: a timing field that is not a positive, finite number (a seed: a whole
                number >= 0), or a ``duration * rate`` above :data:`MAX_SAMPLES`.
        """
        if key in TIMING_FIELDS or key == "seed":
            _timing(f"scenario {self.__dict__.get('name', '?')}", key, value)
        super().__setattr__(key, value)
        if key in TIMING_FIELDS and "duration" in self.__dict__ and "rate" in self.__dict__:
            self.check_size()

    def check_size(self) -> None:
        """A ConfigError when ``duration * rate`` exceeds :data:`MAX_SAMPLES` recorded samples,
        before any work starts, naming the bound, the memory it would take and how to proceed."""
        samples = self.duration * self.rate
        if samples > MAX_SAMPLES:
            gb = samples * BYTES_PER_SAMPLE / 1e9
            raise ConfigError(
                f"scenario {self.name}: duration = {self.duration:g} s at rate = {self.rate:g} Hz is "
                f"{samples:.3g} samples, above the bound of {MAX_SAMPLES:,} samples (the simulator holds the "
                f"whole recording in memory: about {gb:.3g} GB here, {BYTES_PER_SAMPLE / 1e3:g} kB a sample); "
                f"expected at most {MAX_SAMPLES / self.rate:g} s at this rate: shorten the duration or simulate "
                "several shorter recordings (e.g. other seeds) and compare them together")

    @classmethod
    def load(cls, name_or_path: str | Path) -> Scenario:
        """A built-in scenario by name, or a scenario TOML file."""
        path = Path(name_or_path)
        if path.suffix != ".toml":
            path = SCENARIOS_DIR / f"{name_or_path}.toml"
            if not path.exists():
                raise ConfigError(f"unknown scenario '{name_or_path}'; built-in scenarios: "
                                  f"{', '.join(builtin_scenarios())}, or give a .toml file")
        raw = read_toml(path, "scenario", missing="scenario file")
        raw.setdefault("name", path.stem)
        return cls.from_dict(raw, source=str(path))

    @classmethod
    def from_dict(cls, raw: dict, source: str = "") -> Scenario:
        known = set(cls.__dataclass_fields__) - {"source"}
        unknown = set(raw) - known
        if unknown:
            raise ConfigError(f"unknown key(s) {sorted(unknown)} in scenario {source or raw.get('name')}; "
                              f"known keys: {sorted(known)}")
        sc = cls(**raw, source=source)  # the timing fields are checked on assignment (__setattr__)
        ratio = sc.sim_rate / sc.rate
        if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
            raise ConfigError(f"sim_rate ({sc.sim_rate} Hz) must be a multiple of rate ({sc.rate} Hz)")
        if sc.touchdown not in TOUCHDOWN_MODES:
            raise ConfigError(f"scenario {sc.name}: touchdown = {sc.touchdown!r}: "
                              f"expected one of {list(TOUCHDOWN_MODES)}")
        sc.ambient_spec()
        for robot, joints in sc.posture.items():
            if not isinstance(joints, dict):
                raise ConfigError(f"scenario {sc.name}: posture.{robot} = {joints!r}: "
                                  "expected a table of joint = angle [rad]")
            for joint, value in joints.items():
                _number(f"scenario {sc.name}", f"posture.{robot}.{joint}", value, "rad", "a joint angle",
                        lambda x: abs(x) < 10.0)
        sc.noise_scale("imu_noise")
        sc.noise_scale("ft_noise")
        sc.swings()
        if sc.walk:
            walk = sc.walk_spec()
            assert walk is not None  # sc.walk is set
            if walk.end > sc.duration:
                raise ConfigError(f"scenario {sc.name}: duration = {sc.duration} s: expected at least the walk's "
                                  f"end ({walk.end:g} s: start + steps x (double_support + single_support) + settle)")
        return sc

    # ------------------------------------------------------------------------------------------
    def ambient_spec(self) -> Ambient:
        """The parsed ``ambient`` entry."""
        return Ambient.parse(self.ambient, f"scenario {self.name}", self.sim_rate)

    def walk_spec(self) -> Walk | None:
        """The parsed ``[walk]`` table, or None."""
        return Walk.parse(self.walk, f"scenario {self.name}") if self.walk else None

    def noise_scale(self, section: str) -> float:
        """The ``scale`` factor of a noise section (``imu_noise`` or ``ft_noise``), 1 by default."""
        raw = getattr(self, section).get("scale", 1.0)
        return _number(f"scenario {self.name}", f"{section}.scale", raw, "(factor)",
                       "a non-negative factor on the white-noise levels", lambda x: x >= 0.0)

    def base_items(self) -> list[dict]:
        """The ``[[base]]`` items, with the walk's weight shifts."""
        walk = self.walk_spec()
        return list(self.base) + (walk.items()[0] if walk else [])

    def to_dict(self) -> dict:
        """JSON-serialisable description (stored in the recording's metadata)."""
        out = {k: getattr(self, k) for k in self.__dataclass_fields__}
        return out

    # ------------------------------------------------------------------------------------------
    def segments(self, items: list[dict], robot: str, size: int) -> list[tuple[object, Segment]]:
        """Parse ``[[base]]`` (size 3) or ``[[joint]]`` (size 1) tables into segments."""
        out = []
        for item in items:
            item = dict(item)
            key = item.pop("joint", None)
            if isinstance(key, dict):
                key = key.get(robot)
                if key is None:
                    continue
            target = item.pop("target", None)
            kind = item.pop("kind", "step")
            if kind not in ("step", "sine"):
                raise ConfigError(f"segment kind must be 'step' or 'sine', got '{kind}'")
            value = item.pop("offset", None)
            if value is None:
                value = item.pop("amplitude", None)
            if value is None:
                raise ConfigError(f"segment {item} needs an 'offset' (step) or 'amplitude' (sine)")
            value = np.atleast_1d(np.asarray(value, dtype=float))
            if value.shape != (size,):
                raise ConfigError(f"segment value {value.tolist()} must have {size} component(s)")
            try:
                seg = Segment(kind=kind, value=value, **item)
            except TypeError as err:
                raise ConfigError(f"bad segment {item}: {err}") from err
            if seg.duration <= 0 or (kind == "sine" and seg.frequency <= 0):
                raise ConfigError(f"segment {item} needs a positive duration (and frequency for a sine)")
            out.append((key if size == 1 else target, seg))
        return out

    def swings(self) -> list[Swing]:
        out = []
        walk = self.walk_spec()
        for item in list(self.swing) + (walk.items()[1] if walk else []):
            item = dict(item)
            try:
                disp = np.asarray(item.pop("displacement", [0.0, 0.0, 0.0]), dtype=float)
                travel = tuple(float(x) for x in item.pop("travel", (0.0, 1.0)))
                sw = Swing(displacement=disp, travel=travel, **item)
            except (TypeError, ValueError) as err:
                raise ConfigError(f"bad swing {item}: {err}") from err
            if len(sw.travel) != 2 or not 0.0 <= sw.travel[0] < sw.travel[1] <= 1.0:
                raise ConfigError(f"swing of {sw.contact}: travel = {list(sw.travel)} (fractions of the swing): "
                                  "expected [start, end] with 0 <= start < end <= 1")
            if sw.land <= sw.lift:
                raise ConfigError(f"swing of {sw.contact}: land ({sw.land} s) must come after lift ({sw.lift} s)")
            out.append(sw)
        return out
