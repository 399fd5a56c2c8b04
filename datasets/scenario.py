"""Scenarios: what the simulated robot does, and which hidden effects the world holds.

A scenario is a TOML file (the built-in ones live in ``flexforce/datasets/scenarios``)::

    name = "com-step"
    description = "..."
    robot = "romeo"          # built-in robot name or .toml path (overridable on the command line)
    duration = 6.0           # s
    rate = 200.0             # Hz, sampling of the recording
    sim_rate = 1000.0        # Hz, integration (a multiple of rate)
    seed = 0                 # noise seed

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

    [[effects]]              # hidden effects, see flexforce.datasets.effects
    type = "external-wrench"; link = "@base"; force = [40.0, 0.0, 0.0]; start = 1.0; duration = 0.2

    [imu_noise]              # overrides of the robot's noise model (same keys as ImuNoise)
    ambient = true           # ambient disturbance at the nominal model's level (see Scenario.ambient)

Step and sine segments have continuous position, velocity and acceleration, so the joints the
robot tracks (stiff position control) are smooth; contacts switch only at swing events.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flexforce.errors import ConfigError

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

    def __call__(self, t: float):
        """Displacement of the contact from its initial placement, with derivatives."""
        T = self.land - self.lift
        tau = (t - self.lift) / T
        s, ds, dds = minjerk(tau)
        h, dh, ddh = bump(tau)
        ez = np.array([0.0, 0.0, 1.0])
        return (self.displacement * s + ez * self.height * h,
                (self.displacement * ds + ez * self.height * dh) / T,
                (self.displacement * dds + ez * self.height * ddh) / T**2)


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
    ambient: bool = True
    """Ambient unmodelled disturbance: a white acceleration of the flexibility at the samples, linear
    in between (continuous), at the level the nominal model assumes
    (:func:`flexforce.factors.model.unmodelled_acceleration`),
    applied as an external wrench on the base; so that the nominal world is the nominal model."""
    source: str = ""

    @classmethod
    def load(cls, name_or_path: str | Path) -> Scenario:
        """A built-in scenario by name, or a scenario TOML file."""
        path = Path(name_or_path)
        if path.suffix != ".toml":
            path = SCENARIOS_DIR / f"{name_or_path}.toml"
            if not path.exists():
                raise ConfigError(f"unknown scenario '{name_or_path}'; built-in scenarios: "
                                  f"{', '.join(builtin_scenarios())}, or give a .toml file")
        if not path.exists():
            raise ConfigError(f"scenario file not found: {path}")
        try:
            raw = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as err:
            raise ConfigError(f"scenario {path} is not valid TOML: {err}") from err
        raw.setdefault("name", path.stem)
        return cls.from_dict(raw, source=str(path))

    @classmethod
    def from_dict(cls, raw: dict, source: str = "") -> Scenario:
        known = set(cls.__dataclass_fields__) - {"source"}
        unknown = set(raw) - known
        if unknown:
            raise ConfigError(f"unknown key(s) {sorted(unknown)} in scenario {source or raw.get('name')}; "
                              f"known keys: {sorted(known)}")
        sc = cls(**raw, source=source)
        if sc.duration <= 0 or sc.rate <= 0 or sc.sim_rate <= 0:
            raise ConfigError("scenario duration, rate and sim_rate must be positive")
        ratio = sc.sim_rate / sc.rate
        if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
            raise ConfigError(f"sim_rate ({sc.sim_rate} Hz) must be a multiple of rate ({sc.rate} Hz)")
        return sc

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
        for item in self.swing:
            item = dict(item)
            try:
                disp = np.asarray(item.pop("displacement", [0.0, 0.0, 0.0]), dtype=float)
                sw = Swing(displacement=disp, **item)
            except TypeError as err:
                raise ConfigError(f"bad swing {item}: {err}") from err
            if sw.land <= sw.lift:
                raise ConfigError(f"swing of {sw.contact}: land ({sw.land} s) must come after lift ({sw.lift} s)")
            out.append(sw)
        return out
