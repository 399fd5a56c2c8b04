"""The Recording: everything an estimator reads, on one uniform time grid.

A Recording is what simulated and real data have in common (DESIGN.md, "Data flow"): per step
the paper's local-frame inputs, the IMU placement and motion in the local frame, the active
contacts with their rest placements, the IMU readings; optionally reference signals (F/T
wrenches, motion capture) and, for simulated data, the ground truth.

Array shapes use ``N`` for the number of steps, ``C`` for the number of contacts (all contacts
the robot has, active or not) and ``J`` for the number of joints.  Time is kept as integer
nanoseconds (``t_ns``); :attr:`Recording.time` gives float seconds from the first sample.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from flexforce.datasets.faults import check_missing
from flexforce.datasets.quantities import GRAVITY, FlexibleMotion, ImuPlacement, Inputs, Stamped
from flexforce.errors import DataError


@dataclass
class Truth(FlexibleMotion):
    """Ground truth of a simulated recording (world frame unless stated): the flexibility's motion
    and contact wrenches (:class:`~flexforce.datasets.quantities.FlexibleMotion`), and what only a
    simulation knows."""

    external_wrench: np.ndarray
    """(N, 6) hidden external wrench of the scenario's effects (F, T about the world origin)."""
    cop: np.ndarray
    """(N, 3) centre of pressure of the total contact wrench on the ground plane, m."""
    links: dict[str, np.ndarray] = field(default_factory=dict)
    """World positions (N, 3) of chosen links (the hands), m."""
    gyro_bias: np.ndarray | None = None
    """(N, 3) gyrometer bias, rad/s (IMU frame)."""
    accel_bias: np.ndarray | None = None
    """(N, 3) accelerometer bias, m/s^2 (IMU frame)."""
    ambient_wrench: np.ndarray | None = None
    """(N, 6) ambient disturbance wrench (F, T about the world origin): the unmodelled wrench the
    nominal model assumes (``Scenario.ambient``), not a hidden effect."""

    @property
    def disturbance_wrench(self) -> np.ndarray:
        """(N, 6) every external wrench besides the contacts: hidden effects plus ambient."""
        if self.ambient_wrench is None:
            return self.external_wrench
        return self.external_wrench + self.ambient_wrench



@dataclass
class Recording(Stamped):
    """Inputs, measurements, references and (optionally) ground truth on a uniform time grid."""

    t_ns: np.ndarray
    """(N,) int64 time stamps, ns."""
    robot: str
    """Name of the robot configuration (a built-in name or a path)."""
    contact_names: tuple[str, ...]
    """Names of the C contacts."""
    mass: float
    """Total mass in the robot's model, kg."""
    com: np.ndarray
    """(N, 3) CoM c_l in the local frame, m."""
    com_vel: np.ndarray
    """(N, 3) dc_l/dt, m/s."""
    com_acc: np.ndarray
    """(N, 3) d2c_l/dt2, m/s^2."""
    inertia: np.ndarray
    """(N, 3, 3) I_l about the local origin, kg m^2."""
    inertia_dot: np.ndarray
    """(N, 3, 3) dI_l/dt, kg m^2/s."""
    sigma: np.ndarray
    """(N, 3) angular momentum sigma_l about the local origin, kg m^2/s."""
    sigma_dot: np.ndarray
    """(N, 3) d sigma_l/dt, N m."""
    imu_R: np.ndarray
    """(N, 3, 3) IMU orientation in the local frame."""
    imu_p: np.ndarray
    """(N, 3) IMU position in the local frame, m."""
    imu_v: np.ndarray
    """(N, 3) IMU velocity in the local frame, m/s."""
    imu_a: np.ndarray
    """(N, 3) IMU acceleration in the local frame, m/s^2."""
    imu_w: np.ndarray
    """(N, 3) IMU angular velocity relative to the local frame, expressed in it, rad/s."""
    contact_active: np.ndarray
    """(N, C) bool, contact in force."""
    contact_p: np.ndarray
    """(N, C, 3) contact rest position in the local frame, m (meaningful while active)."""
    contact_R: np.ndarray
    """(N, C, 3, 3) contact rest orientation in the local frame."""
    gyro: np.ndarray
    """(N, 3) gyrometer readings in the IMU frame, rad/s."""
    accel: np.ndarray
    """(N, 3) accelerometer readings in the IMU frame, m/s^2."""
    joint_names: tuple[str, ...] = ()
    """Names of the J joints of ``joint_q``."""
    joint_q: np.ndarray | None = None
    """(N, J) joint positions, rad or m."""
    joint_v: np.ndarray | None = None
    """(N, J) joint velocities."""
    ft: np.ndarray | None = None
    """(N, C, 6) F/T readings: wrench of the environment on the robot, expressed in the contact
    frame about its origin (F [N], T [N m]); NaN where a component is not measured."""
    mocap: dict[str, np.ndarray] = field(default_factory=dict)
    """Motion capture: link name -> (N, 7) world pose (x, y, z, qx, qy, qz, qw); NaN when lost."""
    base_pose: np.ndarray | None = None
    """(N, 7) pose of the robot's base (free-flyer link) in the local frame (x, y, z, qx, qy, qz, qw):
    with the estimated flexibility it places the base in the world, to compare with motion capture."""
    truth: Truth | None = None
    """Ground truth (simulated recordings only)."""
    gravity: float = GRAVITY
    """Gravity, m/s^2."""
    meta: dict = field(default_factory=dict)
    """Free-form description: scenario, noise model, hidden effects (JSON-serialisable)."""

    # ------------------------------------------------------------------------------------------
    @classmethod
    def from_arrays(
        cls, t_ns: ArrayLike, *, robot: str, contact_names: Sequence[str], mass: float,
        com: ArrayLike, com_vel: ArrayLike, com_acc: ArrayLike, inertia: ArrayLike, inertia_dot: ArrayLike,
        sigma: ArrayLike, sigma_dot: ArrayLike,
        imu_R: ArrayLike, imu_p: ArrayLike, imu_v: ArrayLike, imu_a: ArrayLike, imu_w: ArrayLike,
        contact_active: ArrayLike, contact_p: ArrayLike, contact_R: ArrayLike,
        gyro: ArrayLike, accel: ArrayLike,
        joint_names: Sequence[str] = (), joint_q: ArrayLike | None = None, joint_v: ArrayLike | None = None,
        ft: ArrayLike | None = None, mocap: Mapping[str, ArrayLike] | None = None,
        base_pose: ArrayLike | None = None, truth: Truth | None = None, gravity: float = GRAVITY,
        meta: dict | None = None,
    ) -> Recording:
        """A validated Recording from plain arrays (your own robot's logs, another simulator...).

        The arrays hold one row per step of a uniform time grid; ``N`` steps, ``C`` contacts (every
        contact of the robot, active or not), ``J`` joints.  "Local frame" is the paper's frame
        attached to the contacts' rest placements (the world when the robot does not flex).

        Args:
            t_ns: (N,) time stamps, integer nanoseconds (any epoch), strictly increasing, uniform.
                Float seconds are refused: convert with ``np.round(t_s * 1e9).astype(np.int64)``.
            robot: the robot configuration's built-in name or TOML path (the nominal model's source).
            contact_names: the C contact names, in the order of the contact axes below.
            mass: total mass, kg.
            com, com_vel, com_acc: (N, 3) CoM ``c_l`` in the local frame, m, and its first and second
                time derivatives, m/s and m/s^2.
            inertia, inertia_dot: (N, 3, 3) inertia ``I_l`` about the local origin, kg m^2, and its
                time derivative, kg m^2/s.
            sigma, sigma_dot: (N, 3) angular momentum ``sigma_l`` about the local origin, kg m^2/s,
                and its time derivative, N m.
            imu_R, imu_p: (N, 3, 3) orientation and (N, 3) position of the IMU in the local frame, m.
            imu_v, imu_a: (N, 3) IMU velocity, m/s, and acceleration, m/s^2, in the local frame.
            imu_w: (N, 3) IMU angular velocity relative to the local frame, expressed in it, rad/s.
            contact_active: (N, C) bool, the contact is in force.
            contact_p, contact_R: (N, C, 3) rest position, m, and (N, C, 3, 3) rest orientation of each
                contact in the local frame (read while it is active).
            gyro, accel: (N, 3) gyrometer, rad/s, and accelerometer, m/s^2, readings in the IMU frame;
                NaN marks a missing reading.
            joint_names, joint_q, joint_v: the J joint names and (N, J) positions (rad or m) and
                velocities (optional; the viewers and exports use them).
            ft: (N, C, 6) F/T readings, the wrench of the environment on the robot in the contact
                frame about its origin (F [N], T [N m]); NaN where not measured (optional).
            mocap: link name -> (N, 7) world pose ``(x, y, z, qx, qy, qz, qw)``, NaN when lost.
            base_pose: (N, 7) the base link's pose in the local frame, as ``mocap``.
            truth: ground truth, for simulated data.
            gravity: m/s^2, along -z of the world.
            meta: free-form JSON-serialisable description.

        Floating-point arrays are taken as float64 and ``contact_active`` as bool (no copy when
        they already are).

        Raises:
            DataError: time stamps that are not integers (floats: seconds?), that look like seconds,
                milliseconds or microseconds (a median step under :attr:`MIN_STEP_NS`), that do not
                increase or are not uniform; an array of the wrong shape, a non-finite input, a
                non-positive mass (:meth:`validate`).
        """
        t = cls._checked_time_stamps(t_ns)

        def floats(value: ArrayLike) -> np.ndarray:
            return np.asarray(value, dtype=np.float64)

        def maybe(value: ArrayLike | None) -> np.ndarray | None:
            return None if value is None else floats(value)

        rec = cls(
            t_ns=t.astype(np.int64, copy=False), robot=str(robot), contact_names=tuple(contact_names),
            mass=float(mass), com=floats(com), com_vel=floats(com_vel), com_acc=floats(com_acc),
            inertia=floats(inertia), inertia_dot=floats(inertia_dot), sigma=floats(sigma),
            sigma_dot=floats(sigma_dot), imu_R=floats(imu_R), imu_p=floats(imu_p), imu_v=floats(imu_v),
            imu_a=floats(imu_a), imu_w=floats(imu_w), contact_active=np.asarray(contact_active, dtype=bool),
            contact_p=floats(contact_p), contact_R=floats(contact_R), gyro=floats(gyro), accel=floats(accel),
            joint_names=tuple(joint_names), joint_q=maybe(joint_q), joint_v=maybe(joint_v), ft=maybe(ft),
            mocap={str(k): floats(v) for k, v in (mocap or {}).items()}, base_pose=maybe(base_pose),
            truth=truth, gravity=float(gravity), meta={} if meta is None else meta,
        )
        return rec.validate()

    MIN_STEP_NS = 10_000
    """Shortest median time step :meth:`from_arrays` and :meth:`validate` take, ns (10 us: 100 kHz):
    a shorter one is time counted in seconds, milliseconds or microseconds (steps of 1 to a few
    thousand), not in nanoseconds."""

    @classmethod
    def _checked_time_stamps(cls, t_ns: ArrayLike) -> np.ndarray:
        """``t_ns`` as an (N,) array of integer nanoseconds, or a DataError naming its dtype or step.

        Raises:
            DataError: not one-dimensional; not integers (floats: seconds?); increasing by a median
                step under :attr:`MIN_STEP_NS` (seconds, milliseconds or microseconds).
        """
        t = np.asarray(t_ns)
        if t.ndim != 1:
            raise DataError(f"t_ns has shape {t.shape}; expected (N,) integer nanoseconds")
        if not np.issubdtype(t.dtype, np.integer):
            span = f", values {t.min():g} to {t.max():g}" if t.size and np.issubdtype(t.dtype, np.number) else ""
            raise DataError(f"t_ns has dtype {t.dtype}{span}; expected integer nanoseconds (int64), e.g. "
                            "np.round(t_seconds * 1e9).astype(np.int64)")
        if t.size >= 2:
            steps = np.diff(t.astype(np.int64))
            median = float(np.median(steps))
            if np.all(steps > 0) and median < cls.MIN_STEP_NS:
                raise DataError(f"t_ns steps by {median:g} ns (median), a rate of "
                                f"{1e9 / median:.3g} Hz: these look like seconds, milliseconds or "
                                "microseconds; expected integer nanoseconds, e.g. "
                                "np.round(t_seconds * 1e9).astype(np.int64)")
        return t

    @property
    def dt(self) -> float:
        """Nominal sample period, s (median of the time steps)."""
        if self.n < 2:
            return 0.0
        return float(np.median(np.diff(self.t_ns))) * 1e-9

    def inputs(self, k: int) -> Inputs:
        """The paper's inputs at step ``k``."""
        return Inputs(self.mass, self.com[k], self.com_vel[k], self.com_acc[k], self.inertia[k],
                      self.inertia_dot[k], self.sigma[k], self.sigma_dot[k])

    def imu(self, k: int) -> ImuPlacement:
        """The IMU placement and motion in the local frame at step ``k``."""
        return ImuPlacement(self.imu_R[k], self.imu_p[k], self.imu_v[k], self.imu_a[k], self.imu_w[k])

    def active_contacts(self, k: int) -> list[int]:
        """Indices of the contacts active at step ``k``."""
        return [int(i) for i in np.flatnonzero(self.contact_active[k])]

    def imu_measurement(self, k: int) -> np.ndarray:
        """(6,) gyro then accelerometer readings at step ``k``."""
        return np.concatenate([self.gyro[k], self.accel[k]])

    def slice(self, start: int, stop: int) -> Recording:
        """The steps ``start:stop`` as a new Recording (arrays are copied)."""
        sl = slice(start, stop)

        def cut(value):
            if isinstance(value, np.ndarray) and value.ndim >= 1 and value.shape[0] == self.n:
                return value[sl].copy()
            if isinstance(value, dict):
                return {k: cut(v) for k, v in value.items()}
            return value

        kwargs = {f.name: cut(getattr(self, f.name)) for f in dataclasses.fields(self) if f.name != "truth"}
        truth = None
        if self.truth is not None:
            truth = Truth(**{f.name: cut(getattr(self.truth, f.name)) for f in dataclasses.fields(Truth)})
        return Recording(**kwargs, truth=truth)

    def per_step_fields(self) -> list[str]:
        """Names of the fields that hold one row per step (arrays of first dimension N)."""
        n = self.n
        return [f.name for f in dataclasses.fields(self)
                if isinstance(getattr(self, f.name), np.ndarray) and getattr(self, f.name).ndim >= 1
                and getattr(self, f.name).shape[0] == n]

    MIN_SAMPLES = 10
    """Fewest samples the estimators accept (:meth:`require_samples`; :meth:`window` keeps at least
    as many): below this no estimator has anything to converge on (a 10-sample EKF run has not
    passed its initial transient; the smoothers' integration factors need several steps to
    constrain the velocities)."""
    MIN_WINDOW_SAMPLES = MIN_SAMPLES
    """Fewest samples :meth:`window` accepts (:attr:`MIN_SAMPLES`)."""

    def require_samples(self, minimum: int | None = None) -> Recording:
        """The recording itself, when it holds at least ``minimum`` samples (:attr:`MIN_SAMPLES`).

        Raises:
            DataError: naming the count and the minimum.
        """
        minimum = self.MIN_SAMPLES if minimum is None else minimum
        if self.n < minimum:
            rate = f" at {1.0 / self.dt:.0f} Hz" if self.n >= 2 else ""
            raise DataError(f"recording has {self.n} sample(s){rate}; the estimators need at least {minimum} "
                            "samples")
        return self

    def window(self, start: float | None = None, end: float | None = None) -> Recording:
        """The samples with ``start <= time <= end`` (seconds from the first sample) as a new Recording.

        Every per-step array is cut (inputs, readings, F/T, motion capture, base pose, truth).  The
        new recording's time starts at 0 again; the times kept in ``meta`` (anchor switches, contact
        phases) are shifted to it and those outside the window are dropped, and
        ``meta["window"]`` records the cut in the original recording's seconds.

        Raises:
            DataError: ``start >= end``, a bound outside the recording, or fewer than
                :attr:`MIN_WINDOW_SAMPLES` samples in the window.
        """
        duration = float(self.time[-1]) if self.n else 0.0
        span = f"the recording covers 0 to {duration:.3f} s"
        lo = 0.0 if start is None else float(start)
        hi = duration if end is None else float(end)
        for name, value in (("start", lo), ("end", hi)):
            if not np.isfinite(value):
                raise DataError(f"{name} = {value:g} s is not a finite time; expected seconds from the first sample "
                                f"({span})")
        if start is not None and not (0.0 <= lo < duration):
            raise DataError(f"start = {lo:g} s is outside the recording; {span}")
        if end is not None and not (0.0 < hi <= duration + 0.5 * self.dt):
            raise DataError(f"end = {hi:g} s is outside the recording; {span}")
        if lo >= hi:
            raise DataError(f"start = {lo:g} s is not before end = {hi:g} s; {span}")
        time = self.time
        eps = 1e-9
        idx = np.flatnonzero((time >= lo - eps) & (time <= hi + eps))
        if idx.size < self.MIN_WINDOW_SAMPLES:
            raise DataError(f"window {lo:g} to {hi:g} s holds {idx.size} sample(s) at {1.0 / self.dt:.0f} Hz; "
                            f"at least {self.MIN_WINDOW_SAMPLES} are needed ({span})")
        out = self.slice(int(idx[0]), int(idx[-1]) + 1)
        t0 = float(time[idx[0]])
        t1 = float(time[idx[-1]])
        meta = copy.deepcopy(self.meta)
        previous = meta.get("window")
        offset = t0 + (previous["start_s"] if previous else 0.0)
        meta["window"] = {"start_s": offset, "end_s": offset + (t1 - t0), "samples": int(idx.size),
                          "of_duration_s": previous["of_duration_s"] if previous else duration}
        anchor = meta.get("anchor")
        if isinstance(anchor, dict) and isinstance(anchor.get("switches"), list):
            kept = []
            for sw in anchor["switches"]:
                if t0 <= sw.get("t", -1.0) <= t1:
                    kept.append({**sw, "t": round(sw["t"] - t0, 6)})
            before = [sw for sw in anchor["switches"] if sw.get("t", -1.0) < t0]
            if before:
                anchor["first"] = before[-1].get("to", anchor.get("first"))
            anchor["switches"] = kept
        contacts = meta.get("contacts")
        if isinstance(contacts, dict) and isinstance(contacts.get("phases"), dict):
            phases = {}
            for name, ivs in contacts["phases"].items():
                cut = []
                for a, b in ivs:
                    a, b = max(a, t0), min(b, t1)
                    if a < b:
                        cut.append([round(a - t0, 6), round(b - t0, 6)])
                phases[name] = cut
            contacts["phases"] = phases
        if isinstance(meta.get("sensor_faults"), list):  # flexforce.datasets.sensorcheck's findings
            faults = []
            for f in meta["sensor_faults"]:
                if isinstance(f, dict) and f.get("t1", t1) >= t0 - eps and f.get("t0", t0) <= t1 + eps:
                    faults.append({**f, "t0": round(max(f.get("t0", t0), t0) - t0, 6),
                                   "t1": round(min(f.get("t1", t1), t1) - t0, 6)})
            meta["sensor_faults"] = faults
        if isinstance(meta.get("grid"), dict) and "n" in meta["grid"]:
            meta["grid"]["n"] = int(idx.size)
        out.meta = meta
        return out

    # ------------------------------------------------------------------------------------------
    def validate(self) -> Recording:
        """Check shapes, finiteness and time order; raise :class:`DataError` naming the problem.

        A missing (NaN) gyrometer or accelerometer reading is allowed (the estimators skip it,
        docs/smoother.md "Sensor faults") up to :data:`flexforce.datasets.faults.MAX_MISSING_FRACTION`
        of the samples.

        Returns the recording itself so that calls can be chained.

        Raises:
            DataError: time stamps that are not integer nanoseconds (a float dtype, or steps that
                look like seconds, milliseconds or microseconds), that do not increase or are not
                uniform; fewer than 2 samples; a field of the wrong shape or not finite; too many
                missing IMU readings; a non-positive mass.
        """
        self._checked_time_stamps(self.t_ns)
        n = self.n
        if n < 2:
            raise DataError(f"recording has {n} sample(s); at least 2 are needed")
        c = len(self.contact_names)
        dts = np.diff(self.t_ns)
        if np.any(dts <= 0):
            k = int(np.flatnonzero(dts <= 0)[0])
            raise DataError(
                f"time stamps do not increase at sample {k + 1} (t = {self.t_ns[k + 1] * 1e-9:.6f} s after "
                f"{self.t_ns[k] * 1e-9:.6f} s); expected strictly increasing time")
        med = np.median(dts)
        if np.any(np.abs(dts - med) > 0.01 * med):
            k = int(np.flatnonzero(np.abs(dts - med) > 0.01 * med)[0])
            raise DataError(
                f"time grid is not uniform: step {k} lasts {dts[k] * 1e-6:.3f} ms against a median of "
                f"{med * 1e-6:.3f} ms; resample the data onto a uniform grid first")
        shapes = {
            "com": (n, 3), "com_vel": (n, 3), "com_acc": (n, 3), "inertia": (n, 3, 3),
            "inertia_dot": (n, 3, 3), "sigma": (n, 3), "sigma_dot": (n, 3), "imu_R": (n, 3, 3),
            "imu_p": (n, 3), "imu_v": (n, 3), "imu_a": (n, 3), "imu_w": (n, 3),
            "contact_active": (n, c), "contact_p": (n, c, 3), "contact_R": (n, c, 3, 3),
            "gyro": (n, 3), "accel": (n, 3),
        }
        for name, shape in shapes.items():
            arr = getattr(self, name)
            if not isinstance(arr, np.ndarray) or arr.shape != shape:
                got = getattr(arr, "shape", type(arr).__name__)
                raise DataError(f"field '{name}' has shape {got}; expected {shape}")
            if name in ("gyro", "accel"):
                continue  # a missing IMU reading is skipped by the estimators (checked below)
            if arr.dtype != bool and not np.all(np.isfinite(arr)):
                k = int(np.flatnonzero(~np.isfinite(arr.reshape(n, -1)).all(axis=1))[0])
                raise DataError(f"field '{name}' is not finite (NaN or inf) at sample {k}, "
                                f"t = {(self.t_ns[k] - self.t_ns[0]) * 1e-9:.3f} s")
        check_missing(self.time, self.gyro, self.accel)
        if not (np.isfinite(self.mass) and self.mass > 0):
            raise DataError(f"mass must be a positive number of kg, got {self.mass}")
        if self.ft is not None and self.ft.shape != (n, c, 6):
            raise DataError(f"field 'ft' has shape {self.ft.shape}; expected {(n, c, 6)}")
        if self.base_pose is not None and self.base_pose.shape != (n, 7):
            raise DataError(f"field 'base_pose' has shape {self.base_pose.shape}; expected {(n, 7)}")
        if self.joint_q is not None and self.joint_q.shape != (n, len(self.joint_names)):
            raise DataError(f"field 'joint_q' has shape {self.joint_q.shape}; expected {(n, len(self.joint_names))}")
        return self


def concat_recordings(first: Recording, second: Recording) -> Recording:
    """``second`` appended to ``first`` (one grid: consecutive parts of a stream).  Per-step arrays
    and motion capture are joined; the other fields, ``meta`` included, are ``first``'s; ground
    truth is kept only when both have it."""
    if set(first.per_step_fields()) != set(second.per_step_fields()) or set(first.mocap) != set(second.mocap):
        raise DataError(f"cannot join recordings with different fields ({sorted(first.per_step_fields())} and "
                        f"{sorted(second.per_step_fields())}, motion capture {sorted(first.mocap)} and "
                        f"{sorted(second.mocap)}); expected parts of one stream")
    kwargs = {f.name: getattr(first, f.name) for f in dataclasses.fields(first) if f.name != "truth"}
    for name in first.per_step_fields():
        kwargs[name] = np.concatenate([getattr(first, name), getattr(second, name)], axis=0)
    kwargs["mocap"] = {k: np.concatenate([v, second.mocap[k]], axis=0) for k, v in first.mocap.items()}
    truth = None
    if first.truth is not None and second.truth is not None:
        joined: dict[str, Any] = {}
        for f in dataclasses.fields(Truth):
            a, b = getattr(first.truth, f.name), getattr(second.truth, f.name)
            per_step = isinstance(a, np.ndarray) and a.ndim >= 1 and a.shape[0] == first.n
            joined[f.name] = np.concatenate([a, b]) if per_step else a
        truth = Truth(**joined)
    return Recording(**kwargs, truth=truth)
