r"""Import a robot's messages as they come: parts of a :class:`Recording`, in bounded memory.

:class:`StreamImporter` is the online form of :func:`flexforce.datasets.io.rosimport.import_bag`:
it takes the IMU, joint-state and F/T messages in time order (per topic) and hands out
consecutive parts of the recording, each a :class:`Recording` on one uniform grid, as soon as
their inputs are final.  :func:`stream_bag` feeds it from a bag read message by message, so a
log of any length is imported without being loaded.  Same method as the offline import
(docs/real-logs.md), with these rules for the online case:

* **Grid.** From the later first stamp of the IMU and the joints, at ``rate`` (argument, else
  ``ros.rate``, else the median period of the first 50 IMU messages, rounded to whole ns).
* **Resampling.** Linear interpolation between the two messages bracketing each grid time, as
  offline; a step is final for a topic once a message at or after its time has arrived.  An F/T
  topic that has fallen more than ``ros.max_gap`` behind the IMU leaves NaN (a gap), as offline.
* **Derivatives.** The same Savitzky-Golay filter as offline, centred: step ``k``'s joint
  velocity and acceleration need the positions up to step ``k + h`` (``h`` the half window), so
  the inputs lag the messages by ``h`` samples (``ros.savgol_window / 2``: 0.1 s on iCub).  The
  first and last ``h`` steps use the window's polynomial fit, as offline (``mode="interp"``).
  This delay adds to the smoother's lag: the estimate of a step leaves ``lag + savgol_window/2``
  after its time (plus ``report_every`` samples).  With ``ros.imu_filter = "savgol"`` the IMU
  readings go through the same smoother over the same rows, with the same delay (no more).
* **Contacts.** The Schmitt trigger runs step by step with its state carried; it starts at a
  contact's first finite force (offline: the same).
* **Local frame** (:class:`flexforce.datasets.io.localframe.LocalFrameTracker`) and kinematics, step by
  step, as offline.

With the same rate and messages, the parts joined are the offline recording to rounding, except
the contact states before a contact's first finite F/T reading (offline: the state that
reading decides; online: not in contact) -- tested on the iCub walk.  Not streamed: motion
capture (a reference, not an input; compare offline).
"""

from __future__ import annotations

import os
import re
import struct
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import convolve1d
from scipy.signal import savgol_coeffs, savgol_filter

from flexforce.datasets.io.localframe import LocalFrameTracker
from flexforce.datasets.io.rosimport import (
    AIRBORNE_MAX_S,
    T_IMU,
    T_JOINTS,
    T_WRENCH,
    TOPIC_CUT_WARN_S,
    _check_path,
    _reader_error,
    _typestore,
    airborne_error,
    check_carrying_joints,
    check_joint_units,
    check_touch_downs,
    imu_smoothed,
    local_inputs,
    savgol_samples,
    wrench_in_contact_frame,
)
from flexforce.datasets.recording import Recording
from flexforce.datasets.robot import RobotConfig, RobotModel, RosConfig
from flexforce.datasets.safeio import OutputOSError
from flexforce.datasets.sensorcheck import SensorFaultWarning, StreamScreen
from flexforce.errors import BagError, ConfigError, DataError
from flexforce.processes import exit_with_parent, libc_prctl

__all__ = ["StreamImporter", "pipelined", "stream_bag"]

_NS = 1_000_000_000
DERIVATIVE_BATCH = 20
"""Steps differentiated at once (at most a part): the filter runs once per batch, not per message."""
RATE_MESSAGES = 50
"""IMU messages whose median period sets the grid when no rate is given."""


class _Topic:
    """Messages of one topic not yet used: stamps and values, in order."""

    def __init__(self, name: str):
        self.name = name
        self.t: list[int] = []
        self.v: list[np.ndarray] = []
        self.last = -1
        self.count = 0
        self.duplicates = 0

    def add(self, t: int, value: np.ndarray, t0: int | None) -> bool:
        if t < self.last:
            where = f"{(t - t0) * 1e-9:.6f} s" if t0 is not None else f"{t * 1e-9:.6f} s"
            raise DataError(f"time goes backwards on topic {self.name}: message {self.count} is stamped {where}, "
                            f"{(self.last - t) * 1e-6:.3f} ms before message {self.count - 1}; expected "
                            "non-decreasing header stamps")
        self.count += 1
        if t == self.last:
            self.duplicates += 1
            return False
        self.last = t
        self.t.append(t)
        self.v.append(value)
        return True

    def at(self, g: int, max_gap_ns: int, fatal: bool, t0: int) -> np.ndarray | None:
        """Interpolated value at ``g`` (ns); None when no message at or after ``g`` has arrived.
        Drops the messages before the bracket.  NaN before the first message and inside a gap
        longer than ``max_gap_ns`` (a DataError instead when ``fatal``)."""
        t = self.t
        if not t or t[-1] < g:
            return None
        j = 0
        while j + 1 < len(t) and t[j + 1] <= g:
            j += 1
        if j:
            del self.t[:j]
            del self.v[:j]
        if t[0] == g:
            return self.v[0]
        if t[0] > g:
            return np.full_like(self.v[0], np.nan)
        t0_, t1_ = t[0], t[1]
        if t1_ - t0_ > max_gap_ns:
            if fatal:
                raise DataError(f"topic {self.name} has a gap of {(t1_ - t0_) * 1e-9:.3f} s from t = "
                                f"{(t0_ - t0) * 1e-9:.3f} s to {(t1_ - t0) * 1e-9:.3f} s; expected gaps shorter "
                                f"than ros.max_gap = {max_gap_ns * 1e-9} s")
            return np.full_like(self.v[0], np.nan)
        w = (g - t0_) / float(t1_ - t0_)
        return (1.0 - w) * self.v[0] + w * self.v[1]


class StreamImporter:
    """Messages in, parts of a Recording out (module docstring).

    Args:
        robot_config: :class:`RobotConfig`, :class:`RobotModel`, built-in name or TOML path.
        rate: grid rate, Hz (default ``ros.rate``, else the first IMU messages' median rate).
        contacts: ``"ft"`` (Schmitt trigger on the F/T normal forces) or ``"fixed"``.
        part_seconds: length of the parts handed out (s; the last one may be shorter).
        ft_contacts: the contacts whose F/T messages will come (default: every contact with an F/T
            topic in ``ros.ft_topics``); the others' F/T is NaN.

    Feed it with :meth:`add_imu`, :meth:`add_joints` and :meth:`add_ft` in time order per topic
    (topics may interleave freely), collect :meth:`parts` as they come, and :meth:`finish`.
    """

    def __init__(self, robot_config, rate: float | None = None, contacts: str = "ft", part_seconds: float = 0.5,
                 ft_contacts=None):
        model = robot_config if isinstance(robot_config, RobotModel) else RobotModel(robot_config)
        config: RobotConfig = model.config
        ros = config.ros or RosConfig()
        if contacts not in ("ft", "fixed"):
            raise ConfigError(f"contacts = {contacts!r}; expected 'ft' (from F/T normal forces) or 'fixed'")
        if not part_seconds > 0:
            raise ConfigError(f"part_seconds = {part_seconds}; expected a positive duration, s")
        if rate is not None and not rate > 0:
            raise ConfigError(f"rate = {rate} Hz; expected a positive rate")
        names_c = tuple(config.contact_names)
        ft_contacts = tuple(c for c in names_c if c in ros.ft_topics) if ft_contacts is None else tuple(ft_contacts)
        unknown = [c for c in ft_contacts if c not in names_c]
        if unknown:
            raise ConfigError(f"F/T contacts {unknown} are not contacts of robot '{config.name}' ({list(names_c)})")
        if contacts == "ft":
            missing = [c for c in names_c if c not in ft_contacts]
            if missing:
                raise ConfigError(f"contacts='ft' needs the F/T of every contact; none for {missing} "
                                  "(or use contacts='fixed')")
        self.model, self.config, self.ros = model, config, ros
        self.contacts = contacts
        self.names_c = names_c
        self.ft_index = [names_c.index(c) for c in ft_contacts]
        self.part_seconds = float(part_seconds)
        self.rate = rate or ros.rate
        self.period: int | None = int(round(1e9 / self.rate)) if self.rate else None
        self.max_gap_ns = int(round(ros.max_gap * _NS))
        pmodel = model.model
        self.joint_names = tuple(model.joint_names)
        self.index = {name: i for i, name in enumerate(self.joint_names)}
        self.ignore = re.compile(ros.ignore_joints) if ros.ignore_joints else None
        for jname in pmodel.names[2:]:
            if pmodel.joints[pmodel.getJointId(jname)].nq != 1:
                raise ConfigError(f"joint '{jname}' of robot '{config.name}' has "
                                  f"{pmodel.joints[pmodel.getJointId(jname)].nq} position coordinates; only 1-dof "
                                  "joints are supported")
        self.imu = _Topic(ros.imu_topic)
        self.joints = _Topic(ros.joint_states_topic)
        self.ft = {i: _Topic(ros.ft_topics.get(names_c[i], f"F/T of {names_c[i]}")) for i in self.ft_index}
        self.ft_frames: dict[int, str] = {}
        self._frames_known: set[str] = set()
        self._names_checked: tuple | None = None
        self._cols: dict[tuple, tuple] = {}
        self.measured: np.ndarray | None = None
        self.velocity_source: str | None = None
        self._imu_first: list[int] = []
        self.grid0: int | None = None
        self.t_first: int | None = None
        # interpolated rows not yet differentiated (and the h before them, for the filter)
        self._rows: dict[str, list] = {"gyro": [], "accel": [], "q": [], "v": [], "ft": []}
        self._rows_first = 0  # step of self._rows[...][0]
        self._waiting: tuple[np.ndarray | None, np.ndarray | None] = (None, None)  # the next step's IMU, joints
        self._k_interp = 0  # next step to interpolate
        self._k_deriv = 0  # next step to differentiate
        self._ready: list[dict] = []  # steps with every input final, not yet handed out
        self._free_from: int | None = None  # first step of the current span without a contact in force
        self._raw_imu: dict[int, dict[str, np.ndarray]] = {}  # first step of a part -> its readings before the filter
        self._savgol_coeffs: dict[tuple, np.ndarray] = {}  # the derivative filters, by (window, derivative, step)
        self._batch_wait = 0  # steps interpolated past the differentiated ones before a batch can be due
        win = int(round(ros.savgol_window * self.rate)) | 1 if self.rate else None
        self._win = win
        self.tracker = LocalFrameTracker(model, self._anchor(), config.footholds)
        self._state: dict[int, bool | None] = {i: None for i in range(len(names_c))}
        mg = model.mass * config.gravity
        self.on = ros.contact_on if ros.contact_on is not None else ros.contact_on_weight * mg
        self.off = ros.contact_off if ros.contact_off is not None else ros.contact_off_weight * mg
        if contacts == "ft" and not self.off < self.on:
            raise ConfigError(f"contact thresholds: off = {self.off:.1f} N is not below on = {self.on:.1f} N "
                              f"(m g = {mg:.1f} N); set ros.contact_on / ros.contact_off (N) or the "
                              "fractions ros.contact_on_weight / ros.contact_off_weight consistently")
        self._fixed = None
        if contacts == "fixed":
            from flexforce.datasets.contacts import fixed_contacts
            self._fixed = fixed_contacts(1, names_c, ros.fixed_contacts)[0]
        self.steps_out = 0
        self.ever_active = np.zeros(len(names_c), dtype=bool)
        self.finished = False

    def _anchor(self) -> int | None:
        a = self.ros.anchor
        if a is None:
            return None
        if a not in self.names_c:
            raise ConfigError(f"ros.anchor = '{a}' is not a contact of robot '{self.config.name}' "
                              f"({list(self.names_c)})")
        return self.names_c.index(a)

    # ------------------------------------------------------------------ messages
    def _t0(self) -> int | None:
        return self.t_first

    def _seen(self, t: int) -> None:
        if self.t_first is None or t < self.t_first:
            self.t_first = t

    def add_imu(self, t_ns: int, gyro, accel, frame_id: str = "") -> None:
        """One IMU message: stamp (ns), angular velocity (rad/s) and specific force (m/s^2) in the
        IMU frame."""
        if frame_id and frame_id != self.config.imu_frame:
            known = "a frame of the URDF" if self.model.model.existFrame(frame_id) else "unknown to the URDF"
            raise BagError(f"topic {self.imu.name} is in frame '{frame_id}' ({known}); expected the IMU frame "
                           f"'{self.config.imu_frame}' of robot config '{self.config.name}'")
        if type(gyro) is tuple and type(accel) is tuple and len(gyro) == 3 and len(accel) == 3:
            value = np.array(gyro + accel, dtype=float)  # the decoder's floats
        else:
            value = np.concatenate([np.asarray(gyro, float).ravel(), np.asarray(accel, float).ravel()])
        if value.shape != (6,):
            raise DataError(f"topic {self.imu.name} message {self.imu.count} (t = {self._rel(t_ns):.3f} s) has "
                            f"{value.size} angular velocity and linear acceleration components; expected 3 + 3")
        # a NaN or inf component is a missing reading (as offline): the estimators skip it
        if not np.isfinite(value).all():
            value = np.where(np.isfinite(value), value, np.nan)
        self._seen(t_ns)
        if self.imu.add(int(t_ns), value, self._t0()) and self.period is None:
            self._imu_first.append(int(t_ns))
            if len(self._imu_first) >= RATE_MESSAGES:
                self._set_period(int(round(float(np.median(np.diff(self._imu_first))))))

    def _set_period(self, period: int) -> None:
        if period <= 0:
            raise DataError(f"topic {self.imu.name}: its messages' median period is {period} ns; expected a "
                            "positive period (or give the rate)")
        self.period = period
        self.rate = 1e9 / period
        self._win = int(round(self.ros.savgol_window * self.rate)) | 1

    def add_joints(self, t_ns: int, names, position, velocity=None) -> None:
        """One joint-state message: stamp (ns), joint names, positions (rad or m) and, optionally,
        velocities."""
        names = tuple(names)
        k = self.joints.count
        if names not in self._cols:
            src, dst = [], []
            for s, name in enumerate(names):
                if name in self.index:
                    src.append(s)
                    dst.append(self.index[name])
                elif self.ignore is None or not self.ignore.search(name):
                    raise BagError(
                        f"topic {self.joints.name} message {k} names joint '{name}', which robot "
                        f"'{self.config.name}' (URDF {self.config.urdf}) does not have; expected names among "
                        f"{list(self.joint_names)} (or set ros.ignore_joints)")
            self._cols[names] = (np.array(src, dtype=int), np.array(dst, dtype=int))
        src, dst = self._cols[names]
        pos = np.asarray(position, dtype=float)
        if len(pos) != len(names):
            raise BagError(f"topic {self.joints.name} message {k} has {len(pos)} positions for {len(names)} names; "
                           "expected one position per name")
        if not np.all(np.isfinite(pos)):
            s = int(np.flatnonzero(~np.isfinite(pos))[0])
            raise DataError(f"topic {self.joints.name} message {k} (t = {self._rel(t_ns):.3f} s) has NaN or inf "
                            f"position for joint '{names[s]}'; expected finite values")
        if self.measured is not None and names is self._names_checked:
            pass  # the same names as the previous message: checked then
        elif self.measured is None:
            measured = np.zeros(len(self.joint_names), dtype=bool)
            measured[dst] = True
            if not measured.any():
                raise BagError(f"topic {self.joints.name} names none of the joints of robot '{self.config.name}'")
            check_carrying_joints(self.model, measured, self.joints.name)
            self.measured = measured
            vel = None if velocity is None else np.asarray(velocity, dtype=float)
            has_vel = vel is not None and len(vel) == len(names)
            self.velocity_source = "message" if has_vel and self.ros.joint_velocity == "message" else "savgol"
        elif not np.array_equal(self._measured_of(dst), self.measured):
            raise BagError(f"topic {self.joints.name} message {k} names other joints than the first message; "
                           "the streaming import expects every message to name the same joints (import the bag "
                           "offline)")
        q = np.full(len(self.joint_names), np.nan)
        q[dst] = pos[src]
        check_joint_units(self.model, q[None], self.joints.name)
        row = q
        if self.velocity_source == "message":
            vel = np.asarray(velocity if velocity is not None else (), dtype=float)
            if len(vel) != len(names) or not np.all(np.isfinite(vel[src])):
                raise DataError(f"topic {self.joints.name} message {k} (t = {self._rel(t_ns):.3f} s) has no finite "
                                "velocity for every joint; expected the velocities of the first message throughout")
            v = np.full(len(self.joint_names), np.nan)
            v[dst] = vel[src]
            row = np.concatenate([q, v])
        self._names_checked = names
        self._seen(t_ns)
        self.joints.add(int(t_ns), row, self._t0())

    def _measured_of(self, dst) -> np.ndarray:
        measured = np.zeros(len(self.joint_names), dtype=bool)
        measured[dst] = True
        return measured

    def add_ft(self, contact: str, t_ns: int, wrench, frame_id: str = "") -> None:
        """One F/T message of ``contact``: stamp (ns), (force N, torque N m) in ``frame_id`` (the
        contact frame when empty)."""
        if contact not in self.names_c or self.names_c.index(contact) not in self.ft:
            raise ConfigError(f"F/T message for '{contact}'; expected one of the F/T contacts "
                              f"{[self.names_c[i] for i in self.ft]}")
        i = self.names_c.index(contact)
        frame = frame_id or self.config.contacts[i].frame
        prev = self.ft_frames.setdefault(i, frame)
        if prev != frame:
            raise BagError(f"topic {self.ft[i].name} changes frame ({sorted({prev, frame})}); expected one frame")
        if frame not in self._frames_known and not self.model.model.existFrame(frame):
            raise BagError(f"topic {self.ft[i].name} is in frame '{frame}', which is not in the URDF of robot "
                           f"'{self.config.name}'; expected the contact frame '{self.config.contacts[i].frame}'")
        self._frames_known.add(frame)
        self._seen(t_ns)
        self.ft[i].add(int(t_ns), np.asarray(wrench, dtype=float).reshape(6), self._t0())

    def _rel(self, t_ns: int) -> float:
        return (int(t_ns) - (self.t_first if self.t_first is not None else int(t_ns))) * 1e-9

    # ------------------------------------------------------------------ parts
    def parts(self) -> Iterator[Recording]:
        """The parts whose inputs are final (each ``part_seconds`` long), in order."""
        self._advance(final=False)
        yield from self._hand_out(final=False)

    def finish(self) -> Iterator[Recording]:
        """The remaining steps (the last ``h`` with the filter's end fit), as parts.

        Raises:
            DataError: no grid (the IMU and joint topics never overlapped), fewer steps than the
                derivative filter's window, or no contact ever in force.
        """
        if self.finished:
            return
        self.finished = True
        if self.period is None and len(self._imu_first) >= 2:
            self._set_period(int(round(float(np.median(np.diff(self._imu_first))))))
        self._advance(final=True)
        if self._k_interp == 0:
            raise DataError(f"topics {self.imu.name} ({self.imu.count} messages) and {self.joints.name} "
                            f"({self.joints.count} messages) give no common time; expected simultaneous logs")
        yield from self._hand_out(final=True)
        cut = (self.joints.last - self.imu.last) * 1e-9
        if abs(cut) > TOPIC_CUT_WARN_S:
            longer, shorter = (self.joints, self.imu) if cut > 0 else (self.imu, self.joints)
            warnings.warn(f"topic {longer.name} runs {abs(cut):.3f} s after topic {shorter.name} ends: the stream "
                          "covers only the span both are logged, and those samples are left out",
                          SensorFaultWarning, stacklevel=2)
        if not self.ever_active.any():
            raise DataError("no contact ever came into force in the stream; a foot must carry the robot "
                            "(check the F/T topics and thresholds, or use contacts='fixed')")

    def _advance(self, final: bool) -> None:
        if self.period is None:
            return
        if self.grid0 is None:
            if not self.imu.t or not self.joints.t:
                return
            self.grid0 = max(self.imu.t[0], self.joints.t[0])
        self._interpolate(final)
        # the steps to differentiate are taken in batches: nothing to do until one is complete
        if final or self._k_interp - self._k_deriv >= self._batch_wait:
            self._differentiate(final)

    def _interpolate(self, final: bool) -> None:
        assert self.grid0 is not None and self.period is not None
        rows = self._rows
        t0 = self.t_first if self.t_first is not None else self.grid0
        while True:
            g = self.grid0 + self._k_interp * self.period
            # the IMU and joint values of a step kept while it waits for another topic (final once
            # a message at or after the step has arrived)
            imu, joints = self._waiting
            if imu is None:
                imu = self.imu.at(g, self.max_gap_ns, True, t0)
                if imu is None:
                    return
            if joints is None:
                joints = self.joints.at(g, self.max_gap_ns, True, t0)
                if joints is None:
                    self._waiting = (imu, None)
                    return
            self._waiting = (imu, joints)
            wrenches = []
            for i, topic in self.ft.items():
                w = topic.at(g, self.max_gap_ns, False, t0)
                if w is None:
                    # not arrived: wait, unless the topic has fallen behind by more than max_gap (a gap)
                    behind = self.imu.last - max(topic.last, g) > self.max_gap_ns
                    if not (final or behind):
                        return
                    continue
                wrenches.append((i, w))
            self._waiting = (None, None)
            ft = np.full((len(self.names_c), 6), np.nan)
            for i, w in wrenches:
                ft[i] = w
            rows["gyro"].append(imu[:3])
            rows["accel"].append(imu[3:])
            nj = len(self.joint_names)
            rows["q"].append(joints[:nj])
            rows["v"].append(joints[nj:] if len(joints) > nj else None)
            rows["ft"].append(ft)
            self._k_interp += 1

    def _differentiate(self, final: bool) -> None:
        assert self._win is not None and self.rate is not None and self.measured is not None
        ros = self.ros
        win = savgol_samples(ros, 1.0 / self.rate)  # the offline import's window (or its ConfigError)
        h = win // 2
        K = self._k_interp
        stop = K if final else K - h
        # in batches (the filter's edge fits cost as much as its interior), within a part's length
        batch = max(1, min(DERIVATIVE_BATCH, int(round(self.part_seconds * self.rate))))
        if stop <= self._k_deriv or (not final and (K < win or stop - self._k_deriv < batch)):
            self._batch_wait = h + batch  # K - h - k_deriv >= batch, K >= win: not before
            return
        if final and K < win:
            raise DataError(f"stream has {K} samples, fewer than the Savitzky-Golay window of {win} samples "
                            f"(ros.savgol_window = {ros.savgol_window} s); expected a longer log")
        rows = self._rows
        a = self._rows_first
        dt = 1.0 / self.rate
        q = np.array(rows["q"])
        nj = len(self.joint_names)
        q_ref = self.model.q_reference[7:]
        q[:, ~self.measured] = q_ref[~self.measured]
        # filter over the rows held (at least a window, and h before k_deriv unless at the start);
        # keep the outputs k_deriv .. stop: the filter's interior, or its end fits at the ends
        s = a
        seg = q
        lo, hi = self._k_deriv - s, stop - s
        if self.velocity_source == "message":
            v_seg = np.array(rows["v"])
            v_seg[:, ~self.measured] = 0.0
            acc = self._savgol(v_seg, win, 1, dt, lo, hi)
            vel = v_seg
        else:
            vel = self._savgol(seg, win, 1, dt, lo, hi)
            acc = self._savgol(seg, win, 2, dt, lo, hi)
        vel = vel.copy()
        vel[:, ~self.measured] = 0.0
        acc[:, ~self.measured] = 0.0
        # the rows as buffered (a list), or filtered (an array): both indexed by row below
        gyro: Any = rows["gyro"]
        accel: Any = rows["accel"]
        if ros.imu_filter == "savgol":  # the IMU through the same smoother, over the same rows
            noise = self.config.imu_noise
            gyro = imu_smoothed(np.array(gyro), noise.gyro_range, win,
                                lambda x: self._savgol(x, win, 0, dt, lo, hi))
            accel = imu_smoothed(np.array(accel), noise.accel_range, win,
                                 lambda x: self._savgol(x, win, 0, dt, lo, hi))
        for j in range(lo, hi):
            k = s + j
            r = k - a
            self._ready.append({"k": k, "gyro": gyro[r], "accel": accel[r], "q": seg[j],
                                "v": vel[j, :nj], "a": acc[j, :nj], "ft": rows["ft"][r],
                                "gyro_raw": rows["gyro"][r], "accel_raw": rows["accel"][r]})
        self._k_deriv = stop
        # drop the rows the filter no longer needs (it needs h before the next step to differentiate)
        keep_from = max(min(self._k_deriv - h, K - win), 0)
        cut = keep_from - a
        if cut > 0:
            for key in rows:
                del rows[key][:cut]
            self._rows_first = keep_from

    def _savgol(self, x: np.ndarray, win: int, deriv: int, dt: float, lo: int, hi: int) -> np.ndarray:
        """``savgol_filter(x, win, order, deriv, delta=dt, axis=0, mode="interp")`` at rows
        ``lo .. hi-1`` (the other rows undefined).  Rows at least half a window from both ends
        are the filter's interior, the convolution with its coefficients (computed once, the
        same operations as scipy's); the end fits only when the rows reach an end."""
        h = win // 2
        if lo < h or hi > len(x) - h:
            return savgol_filter(x, win, self.ros.savgol_order, deriv=deriv, delta=dt, axis=0, mode="interp")
        key = (win, deriv, dt)
        coeffs = self._savgol_coeffs.get(key)
        if coeffs is None:
            coeffs = self._savgol_coeffs[key] = savgol_coeffs(win, self.ros.savgol_order, deriv=deriv, delta=dt)
        out = np.empty_like(x)
        out[lo - h:hi + h] = convolve1d(x[lo - h:hi + h], coeffs, axis=0, mode="constant")
        return out

    def raw_imu(self, part: Recording) -> dict[str, np.ndarray] | None:
        """The IMU readings of ``part`` (one this importer handed out) as resampled, before
        ``ros.imu_filter`` smoothed them (None without a filter), and forgotten here: what the
        sensor screen judges (a smoother rounds off a clipped flat top)."""
        return self._raw_imu.pop(int(part.meta["stream"]["first_step"]), None)

    def _part_due(self) -> bool:
        """A whole part is ready (:meth:`parts` would hand one out)."""
        return self.rate is not None and len(self._ready) >= max(1, int(round(self.part_seconds * self.rate)))

    def _hand_out(self, final: bool) -> Iterator[Recording]:
        assert self.rate is not None or not self._ready
        size = max(1, int(round(self.part_seconds * (self.rate or 1.0))))
        while len(self._ready) >= size or (final and self._ready):
            steps, self._ready = self._ready[:size], self._ready[size:]
            yield self._part(steps)

    def _contacts(self, ft: np.ndarray) -> np.ndarray:
        n = len(ft)
        active = np.zeros((n, len(self.names_c)), dtype=bool)
        if self._fixed is not None:
            active[:] = self._fixed
            return active
        for i in range(len(self.names_c)):
            state = self._state[i]
            for k in range(n):
                f = ft[k, i, 2]
                if state is None:
                    if np.isfinite(f):
                        state = bool(f >= self.off)
                elif state and f < self.off:
                    state = False
                elif not state and f > self.on:
                    state = True
                active[k, i] = bool(state)
            self._state[i] = state
        return active

    def _check_airborne(self, active: np.ndarray, ks: np.ndarray) -> None:
        """:func:`~flexforce.datasets.io.rosimport.check_airborne` over the stream: the span without a
        contact may start in an earlier part (:attr:`_free_from`, its first step, or None)."""
        assert self.period is not None
        dt = self.period * 1e-9
        free_at: np.ndarray = np.logical_not(active.any(axis=1))
        for k, free in zip(ks, free_at):
            if not free:
                self._free_from = None
                continue
            if self._free_from is None:
                self._free_from = int(k)
            samples = int(k) - self._free_from + 1
            if samples * dt > AIRBORNE_MAX_S:
                raise airborne_error(self.names_c, "in the stream", self._free_from * dt, int(k) * dt, samples)

    def _no_first_contact(self, ft: np.ndarray) -> None:
        """A DataError for a stream whose first sample has no contact in force (the streamed smoother
        starts from one), naming what the F/T topics read."""
        ros = self.ros
        reads = []
        for i, name in enumerate(self.names_c):
            topic = (ros.ft_topics or {}).get(name, "no topic")
            f = ft[:, i, 2]
            seen = f[np.isfinite(f)]
            reads.append(f"{name} ({topic}): " + (f"{seen[0]:.4g} N at first" if seen.size else
                                                   f"no finite normal force in the first {len(f)} samples"))
        raise DataError("no contact is in force at the stream's first sample, where the streamed smoother starts: "
                        + "; ".join(reads) + f"; a contact comes into force above {self.on:.4g} N; expected a foot "
                        "carrying the robot from the start (check the F/T topics, or use contacts='fixed')")

    def _part(self, steps: list[dict]) -> Recording:
        assert self.grid0 is not None and self.period is not None
        n = len(steps)
        ks = np.array([s["k"] for s in steps])
        grid = self.grid0 + self.period * ks.astype(np.int64)
        q = np.array([s["q"] for s in steps])
        v = np.array([s["v"] for s in steps])
        a = np.array([s["a"] for s in steps])
        ft = np.array([s["ft"] for s in steps])
        for i, frame in self.ft_frames.items():
            contact_frame = self.config.contacts[i].frame
            if frame != contact_frame:
                topic = (self.ros.ft_topics or {}).get(self.names_c[i], "")
                ft[:, i] = wrench_in_contact_frame(self.model, q, frame, contact_frame, ft[:, i], topic)
        active = self._contacts(ft)
        if self.steps_out == 0 and self._fixed is None and not active[0].any():
            self._no_first_contact(ft)
        self._check_airborne(active, ks)
        self.ever_active |= active.any(axis=0)
        load = ft[:, :, 2] if self.ft else None
        lf = self.tracker.run(q, v, a, active, load)
        check_touch_downs(lf.footholds, self.config.footholds, self.names_c, lambda k: k * self.period * 1e-9)
        arrays = local_inputs(self.model, lf)
        meta = {"stream": {"first_step": int(ks[0]), "steps": n, "rate_hz": 1e9 / self.period,
                           "period_ns": self.period, "t0_ns": int(self.grid0),
                           "joint_velocity": self.velocity_source,
                           "derivative_filter": {"method": "savgol", "window_s": self.ros.savgol_window,
                                                 "order": self.ros.savgol_order},
                           "imu_filter": self.ros.imu_filter}}
        self.steps_out += n
        if self.ros.imu_filter != "none":  # the readings before the filter, for the sensor screen
            self._raw_imu[int(ks[0])] = {"gyro": np.array([s["gyro_raw"] for s in steps], dtype=float),
                                         "accel": np.array([s["accel_raw"] for s in steps], dtype=float)}
            while len(self._raw_imu) > RAW_IMU_PARTS:  # not taken (no screen reads them): bounded memory
                del self._raw_imu[min(self._raw_imu)]
        return Recording(
            t_ns=grid, robot=self.config.source or self.config.name, contact_names=self.names_c,
            mass=self.model.mass, contact_active=active, contact_p=lf.contact_p, contact_R=lf.contact_R,
            gyro=np.array([s["gyro"] for s in steps]), accel=np.array([s["accel"] for s in steps]),
            joint_names=self.joint_names, joint_q=q, joint_v=v, ft=ft if self.ft else None, mocap={},
            base_pose=lf.base_pose, gravity=self.config.gravity, meta=meta, **arrays)


# ------------------------------------------------------------------------------------------------
_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<iI")
_D3 = struct.Struct("<3d")
_D6 = struct.Struct("<6d")


class _CdrDecoder:
    """The fields the import reads from the little-endian CDR of ROS 2's Imu, JointState and
    WrenchStamped messages, by their fixed layout (offsets computed from the raw bytes): what
    rosbags' deserialisation gives, without building the message objects.  ``decode`` returns
    None for anything else (another type, big-endian, a malformed message): the caller
    deserialises with rosbags then.  Tested equal to rosbags' deserialisation (tests/test_stream.py).

    Returned: ``(stamp_ns, frame_id, (gyro, accel))`` for an Imu, ``(stamp_ns, frame_id, wrench)``
    for a WrenchStamped, ``(stamp_ns, frame_id, (names, position, velocity))`` for a JointState
    (``names`` the same tuple while the names' bytes repeat), ``stamp_ns`` 0 when unset."""

    def __init__(self):
        self._names_raw = b""
        self._names: tuple[str, ...] = ()

    @staticmethod
    def _header(raw) -> tuple[int, str, int]:
        if raw[0] != 0 or raw[1] != 1:  # CDR_LE (0x0001) only
            raise ValueError("not little-endian CDR")
        sec, nsec = _STAMP.unpack_from(raw, 4)
        (n,) = _U32.unpack_from(raw, 12)
        if n < 1 or 16 + n > len(raw) or raw[15 + n] != 0:
            raise ValueError("bad frame_id")
        frame = raw[16:15 + n].decode()
        return sec * _NS + nsec, frame, 16 + n

    @staticmethod
    def _align(pos: int, size: int) -> int:
        return 4 + (-(-(pos - 4) // size)) * size  # alignment counts from after the 4-byte encapsulation

    def _doubles(self, raw, pos: int) -> tuple[np.ndarray, int]:
        pos = self._align(pos, 4)
        (n,) = _U32.unpack_from(raw, pos)
        pos += 4
        if n:
            pos = self._align(pos, 8)
        end = pos + 8 * n
        if end > len(raw):
            raise ValueError("truncated sequence")
        return np.frombuffer(raw, dtype="<f8", count=n, offset=pos).astype(float), end

    def _values(self, raw, pos: int) -> tuple[np.ndarray, np.ndarray]:
        """A JointState's positions and velocities, from the end of its names."""
        position, pos = self._doubles(raw, pos)
        velocity, pos = self._doubles(raw, pos)
        return position, velocity

    def decode(self, msgtype: str, raw):
        if not isinstance(raw, bytes):
            raw = bytes(raw)
        try:
            if msgtype == T_IMU:
                t, frame, pos = self._header(raw)
                o = self._align(pos, 8)
                if o + 296 > len(raw):
                    return None
                return t, frame, (_D3.unpack_from(raw, o + 104), _D3.unpack_from(raw, o + 200))
            if msgtype == T_WRENCH:
                t, frame, pos = self._header(raw)
                o = self._align(pos, 8)
                if o + 48 > len(raw):
                    return None
                return t, frame, _D6.unpack_from(raw, o)
            if msgtype == T_JOINTS:
                t, frame, pos = self._header(raw)
                start = pos = self._align(pos, 4)
                known = len(self._names_raw)
                if known and raw[start:start + known] == self._names_raw:
                    # the previous message's names (the block parses the same from any aligned start)
                    return t, frame, (self._names, *self._values(raw, start + known))
                (count,) = _U32.unpack_from(raw, pos)
                pos += 4
                for _ in range(count):
                    pos = self._align(pos, 4)
                    (n,) = _U32.unpack_from(raw, pos)
                    pos += 4 + n
                if pos > len(raw):
                    return None
                block = bytes(raw[start:pos])
                if block != self._names_raw:
                    names, p = [], start + 4
                    for _ in range(count):
                        p = self._align(p, 4)
                        (n,) = _U32.unpack_from(raw, p)
                        if n < 1 or raw[p + 3 + n] != 0:
                            return None
                        names.append(raw[p + 4:p + 3 + n].decode())
                        p += 4 + n
                    self._names_raw, self._names = block, tuple(names)
                return t, frame, (self._names, *self._values(raw, pos))
        except (ValueError, struct.error, IndexError, UnicodeDecodeError):
            return None
        return None


def _fields(msg: Any, msgtype: str):
    """:meth:`_CdrDecoder.decode`'s fields from a message deserialised by rosbags."""
    stamp = int(msg.header.stamp.sec) * _NS + int(msg.header.stamp.nanosec)
    if msgtype == T_IMU:
        av, la = msg.angular_velocity, msg.linear_acceleration
        return stamp, msg.header.frame_id, ((av.x, av.y, av.z), (la.x, la.y, la.z))
    if msgtype == T_JOINTS:
        return stamp, msg.header.frame_id, (msg.name, msg.position, msg.velocity)
    w = msg.wrench
    return stamp, msg.header.frame_id, (w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z)


def stream_bag(path, robot_config, rate: float | None = None, contacts: str = "ft", part_seconds: float = 0.5,
               on_message: Callable | None = None) -> Iterator[Recording]:
    """Parts of the recording of a raw robot bag, read message by message (bounded memory).

    Args:
        path, robot_config, rate, contacts: as :func:`flexforce.datasets.io.rosimport.import_bag`.
        part_seconds: length of each part, s.
        on_message: called as ``on_message(reader, connection, log_time_ns, raw)`` for every
            message of the bag, in the bag's order (``reader`` the rosbags AnyReader; to copy the
            inputs into an output bag as they are read, :meth:`EstimateWriter.copy`).

    Raises:
        BagError: missing or unreadable bag, missing topic, wrong message type, unknown joint or
            frame (before any part for the topics; as read for the messages).
        DataError: NaN, time going backwards, long gaps, too short, never in contact.
    """
    from rosbags.highlevel import AnyReader

    path = Path(path)
    _check_path(path)
    model = robot_config if isinstance(robot_config, RobotModel) else RobotModel(robot_config)
    ros = model.config.ros or RosConfig()
    try:
        reader_cm = AnyReader([path], default_typestore=_typestore())
        reader = reader_cm.__enter__()
    except Exception as err:  # noqa: BLE001 -- any library failure means an unreadable bag
        raise _reader_error(path, err) from err
    try:
        types = {c.topic: c.msgtype for c in reader.connections}
        counts: dict[str, int] = {}
        for c in reader.connections:
            counts[c.topic] = counts.get(c.topic, 0) + int(getattr(c, "msgcount", 1) or 0)
        wanted = {ros.imu_topic: T_IMU, ros.joint_states_topic: T_JOINTS}
        ft_topics = {topic: name for name, topic in ros.ft_topics.items()}
        wanted.update({topic: T_WRENCH for topic in ft_topics})
        for topic, msgtype in wanted.items():
            if topic in types and types[topic] != msgtype:
                raise BagError(f"topic {topic} of bag {path} has type {types[topic]}; expected {msgtype}")
        required = [ros.imu_topic, ros.joint_states_topic]
        if contacts == "ft":
            required += [ros.ft_topics[c] for c in model.config.contact_names if c in ros.ft_topics]
        name = model.config.name
        for topic in required:
            if topic not in types:
                have = ", ".join(f"{t} ({m})" for t, m in sorted(types.items())) or "none"
                raise BagError(f"bag {path} lacks topic {topic} ({wanted[topic]}) named by robot config '{name}'; "
                               f"the bag has: {have}")
            if counts.get(topic, 1) == 0:
                raise BagError(f"topic {topic} ({types[topic]}) of bag {path} has no messages; expected the "
                               f"messages robot config '{name}' reads from it")
        present = tuple(ft_topics[t] for t in ft_topics if t in types and counts.get(t, 1) > 0)
        imp = StreamImporter(model, rate, contacts, part_seconds, ft_contacts=present)
        check = StreamScreen({"accel": ros.imu_topic, "gyro": ros.imu_topic,
                              **{f"ft/{ft_topics[t]}": t for t in ft_topics if t in types}}, where=str(path),
                             readings=imp.raw_imu)
        read = [c for c in reader.connections if c.topic in wanted] if on_message is None else reader.connections
        skew: dict[str, int] = {}  # topic -> its first header stamp minus its log time, ns
        cdr = _CdrDecoder() if getattr(reader, "is2", False) else None  # ROS 2 bags: CDR messages
        for conn, log_ns, raw in reader.messages(connections=read):
            if on_message is not None:
                try:
                    on_message(reader, conn, log_ns, raw)
                except OSError as err:  # the caller's (writing an output): not the bag's
                    raise OutputOSError(err) from err
            topic = conn.topic
            if topic not in wanted:
                continue
            got = cdr.decode(conn.msgtype, raw) if cdr is not None else None
            if got is None:
                got = _fields(reader.deserialize(raw, conn.msgtype), conn.msgtype)
            stamp, frame, values = got
            t = stamp if stamp != 0 else int(log_ns)
            if stamp != 0 and topic not in skew and topic in (ros.imu_topic, ros.joint_states_topic):
                skew[topic] = int(stamp) - int(log_ns)
                if len(skew) == 2:
                    _check_clocks(skew, ros)
            if topic == ros.imu_topic:
                imp.add_imu(t, values[0], values[1], frame)
            elif topic == ros.joint_states_topic:
                imp.add_joints(t, *values)
            else:
                imp.add_ft(ft_topics[topic], t, values, frame)
            imp._advance(final=False)  # imp.parts(), without a generator per message
            if imp._part_due():
                yield from map(check, imp._hand_out(final=False))
        yield from map(check, imp.finish())
        check.finish()
    except (BagError, DataError, ConfigError):
        raise
    except OutputOSError as err:
        raise err.error from None
    except Exception as err:  # noqa: BLE001 -- a reader failure in the middle: truncated or corrupt
        raise _reader_error(path, err) from err
    finally:
        try:
            reader_cm.__exit__(None, None, None)
        except Exception:  # noqa: BLE001, S110 -- closing a reader that already failed
            pass


RAW_IMU_PARTS = 8
"""Parts whose pre-filter IMU readings an importer keeps until they are taken (:meth:`StreamImporter.raw_imu`)."""
CLOCK_SKEW_MAX = 1.0
"""Largest difference, s, between the IMU's and the joint states' header stamps (each against the
bag's log time at their first message) of a stream: more is two clocks, which would pair
readings taken apart (the offline import refuses the same bag for its topics' short overlap)."""


def _check_clocks(skew: dict[str, int], ros: RosConfig) -> None:
    d = (skew[ros.joint_states_topic] - skew[ros.imu_topic]) * 1e-9
    if abs(d) > CLOCK_SKEW_MAX:
        raise DataError(f"the header stamps of {ros.joint_states_topic} run {d:+.3f} s from those of {ros.imu_topic} "
                        f"(each against the bag's log time at its first message): two clocks; expected stamps from "
                        f"one clock (within {CLOCK_SKEW_MAX:g} s)")


_END = "end"


def _produce(queue, factory, args, kwargs, parent_pid: int) -> None:  # pragma: no cover -- the child process
    exit_with_parent(parent_pid, libc_prctl())  # a killed parent would leave it blocked on the queue
    try:
        for part in factory(*args, **kwargs):
            queue.put(("part", part))
        queue.put((_END, None))
    except KeyboardInterrupt:
        queue.put(("error", KeyboardInterrupt()))
    except BaseException as err:  # noqa: BLE001 -- handed to the parent, which raises it
        queue.put(("error", err))


def pipelined(factory: Callable[..., Iterator[Recording]], *args, depth: int = 64,
              warm_up: Callable[[], None] | None = None, **kwargs) -> Iterator[Recording]:
    """The parts of ``factory(*args, **kwargs)`` (e.g. :func:`stream_bag`), produced in a child
    process while the caller consumes them: the import (message decoding, leg odometry,
    kinematics) and the smoothing run on two cores.  At most ``depth`` parts wait in between
    (bounded memory: ~140 kB a 0.5 s part of the iCub, ~9 MB for 64); deep enough that the
    import runs on while the caller starts (the smoother's first problem, its compiled code
    loaded: ~1.5 s, 30 s of a 200 Hz log at 20x real time).  ``warm_up``: run here once the
    child has started, while its first part is awaited (e.g.
    :func:`flexforce.smoother.stream.warm_up`); its failure is ignored.  An error of the import
    is raised here, as it would be in-process."""
    import gc
    import multiprocessing as mp

    ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else mp.get_context()
    queue = ctx.Queue(maxsize=depth)
    # the objects made so far (the modules above all) leave the collector's generations: its
    # passes in either process would otherwise write to their headers and copy every page
    # shared with the forked child (~20 MB of the two processes' PSS on the iCub)
    gc.freeze()
    proc = ctx.Process(target=_produce, args=(queue, factory, args, kwargs, os.getpid()), daemon=True)
    proc.start()
    if warm_up is not None:
        try:
            warm_up()
        except Exception:  # noqa: BLE001, S110 -- an optimisation only: the stream runs without it
            pass
    try:
        while True:
            try:
                kind, value = queue.get(timeout=1.0)
            except Exception:  # noqa: BLE001 -- queue.Empty: check that the producer is alive
                if not proc.is_alive() and queue.empty():
                    raise DataError(f"the import process ended without a result (exit code {proc.exitcode})") \
                        from None
                continue
            if kind == _END:
                break
            if kind == "error":
                raise value
            yield value
    finally:
        if proc.is_alive():
            proc.terminate()
        proc.join(timeout=5.0)
        gc.unfreeze()  # collectable again (a caller's garbage of before the stream is not kept for good)
