"""Sensor faults recognised from the data of a Recording: clipping, wrong units, stuck and missing sensors.

Faults that the readings themselves reveal, checked before any estimator runs
(:func:`check_recording`, :func:`screen`):

* **clipped** -- a flat top: several consecutive samples of one IMU axis equal (within
  :data:`EQUAL_TOL`) at that axis's largest or smallest value, more of them than in the band just
  below it, while the axis otherwise varies (a sensor saturating at its full scale);
* **units** -- the accelerometer's norm has a median over the recording near 1 (g instead of
  m/s^2) or far above gravity (mg, cm/s^2): refused, no robot on the ground can read that; a
  median off gravity by more than :data:`ACCEL_NORM_TOL` is a warning (scale, clipping, bias); the
  gyrometer reading :data:`DEG_SCALE_MIN` times or more the rotation rate of the joint kinematics
  (``Recording.imu_w``), or a median rate above :data:`GYRO_MEDIAN_MAX` (deg/s instead of rad/s),
  is a warning, and refused when it follows the kinematics at 180/pi times their rate
  (:data:`DEG_REFUSE`);
* **stuck** -- an IMU or F/T channel exactly constant for :data:`STUCK_MIN_S` s or more (a
  frozen driver repeats its last value; real sensors always show noise); an F/T channel that is
  NaN or exactly 0 throughout is not measured (a force-only sensor), not stuck;
* **missing** -- a span without F/T reading (NaN) in a channel measured elsewhere in the
  recording, :data:`MISSING_MIN_S` s or longer.

Times are seconds from the recording's first sample.  This module is plain numpy (the data layer).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from flexforce.errors import DataError

__all__ = ["ACCEL_NORM_TOL", "DEG_SCALE_MIN", "EQUAL_TOL", "GYRO_MEDIAN_MAX", "MISSING_MIN_S", "STUCK_MIN_S",
           "Finding", "SensorFaultWarning", "StreamScreen", "check_recording", "screen"]

EQUAL_TOL = 1e-9
"""Two readings closer than this (in the sensor's unit) are equal: a flat top or a stuck value."""
CLIP_MIN_RUN = 3
"""Fewest consecutive samples at an axis's extreme value that make a flat top."""
CLIP_MIN_LEVELS = 20
"""Fewest distinct values an axis must take to be judged for a flat top (a coarsely quantised
signal repeats its extremes without being clipped)."""
CLIP_MIN_SPREAD = 1e-6
"""Smallest spread of an axis, relative to its largest magnitude (at least 1), for it to be judged
for a flat top: an axis that varies less is constant (a noise-free simulation at rest), not
clipped."""
CLIP_MIN_TOPS = 3
"""Separate flat tops at one extreme value that mark a fine-grained signal as clipped, however
many of its samples lie just inside the top."""
CLIP_FLOOR = {"accel": 1.0, "gyro": 0.05}
"""Smallest magnitude of a flat top that is a clip (m/s^2, rad/s): no sensor's full scale is lower."""
ACCEL_NORM_TOL = 0.1
"""Warn when the accelerometer norm's median differs from gravity by more than this fraction."""
G_UNITS = (0.7, 1.4)
"""An accelerometer norm median in this range of m/s^2 is gravity in g: refused."""
ACCEL_NORM_MAX = 5.0
"""An accelerometer norm median above this many g is a unit of mg or cm/s^2: refused."""
DEG_SCALE_MIN = 10.0
"""Warn when the gyrometer reads this many times the joint kinematics' rotation rate or more
(deg/s give 57.3) with a correlation of at least :data:`KINEMATIC_CORRELATION`."""
KINEMATIC_CORRELATION = 0.5
"""Correlation of gyrometer and kinematic rate above which their ratio is trusted."""
KINEMATIC_MIN_RATE = 0.02
"""Rms rotation rate of the kinematics, rad/s, below which the ratio is not judged."""
AXES_ANGLE_MAX = 30.0
"""Largest angle, deg, between the accelerometer's mean reading and the mean specific force the
joint kinematics predict in the IMU frame (a robot standing on its feet: the IMU's tilt from the
kinematics is a few degrees); more is another frame or swapped axes: refused."""
AXES_CORRELATION = 0.8
"""A gyrometer axis that follows another axis of the kinematic rotation rate this closely (and its
own less than :data:`KINEMATIC_CORRELATION`) reads in another frame: refused."""
DEG_REFUSE = (40.0, 80.0)
"""A gyrometer that follows the joint kinematics (correlation above :data:`KINEMATIC_CORRELATION`)
at this many times their rate reads deg/s (57.3): refused."""
GYRO_MEDIAN_MAX = 3.0
"""A median rotation rate above this, rad/s, is not a standing or walking robot (deg/s?)."""
STUCK_MIN_S = 0.5
"""Shortest span, s, of an exactly constant channel reported as stuck (real logs hold a value over
a network gap for up to a few tenths of a second)."""
STUCK_MIN_SAMPLES = 20
"""Fewest samples of a stuck span, whatever the rate."""
MOCAP_MISSING_MIN_S = 0.1
"""A motion-capture body unseen this long or longer (s) is reported: a reference gap."""
WHOLE_MISSING_FT_EFFECT = (
    "there is no F/T reference for this contact (no force error against it), no F/T measurement for --ft, and "
    "the local frame cannot pass its anchor to the most loaded foot (leg odometry, hence every estimate, differs "
    "from a run with the F/T); contact states cannot come from it (use contacts='fixed', or fix the topic)")
"""The effect of an F/T topic that never reads a number."""
MISSING_MIN_S = 0.05
"""Shortest span, s, without F/T reading reported as missing."""

MISSING_EFFECT = ("contact states detected from the F/T normal force hold their last value, force errors against "
                  "F/T skip the span and --ft fuses nothing there")
"""What a span without F/T reading does to the output (a ``missing`` finding's effect)."""
_AXES = ("x", "y", "z")
_FT = ("F_x", "F_y", "F_z", "T_x", "T_y", "T_z")
_UNIT = {"accel": "m/s^2", "gyro": "rad/s"}
_RANGE_KEY = {"accel": "imu_noise.accel_range", "gyro": "imu_noise.gyro_range"}


class SensorFaultWarning(RuntimeWarning):
    """A sensor fault recognised from the data (:class:`Finding`); the command line prints it as one line."""


@dataclass(frozen=True)
class Finding:
    """One sensor fault recognised from the data."""

    sensor: str
    """``accel``, ``gyro`` or ``ft/<contact>``, with the topic it came from when known
    (``ft/left_foot (/left_foot/wrench)``)."""
    kind: str
    """``clipped``, ``units``, ``stuck`` or ``missing``."""
    t0: float
    """Start of the span, s from the recording's first sample."""
    t1: float
    """End of the span, s from the recording's first sample."""
    detail: str
    """What was seen (channel, value, count)."""
    effect: str
    """What it does to the output."""
    severity: str = "warning"
    """``warning`` (reported) or ``error`` (the recording is refused)."""
    channel: str = ""
    """The channel of a clipped or stuck finding (``axis x``, ``F_z``); empty for a whole sensor."""

    def message(self) -> str:
        """One line: the fault, its span and its effect."""
        return (f"{self.sensor} {self.kind} from t = {self.t0:.3f} s to {self.t1:.3f} s: {self.detail}; "
                f"effect: {self.effect}")

    def to_dict(self) -> dict:
        """JSON-serialisable form (``Recording.meta['sensor_faults']``, summary.json's ``warnings``)."""
        return {**asdict(self), "t0": round(float(self.t0), 6), "t1": round(float(self.t1), 6)}


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[(first, last), ...]`` of the runs of True in the (N,) bool ``mask``."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), (np.flatnonzero(edges == -1) - 1).tolist()))


def _named(sensor: str, topics: Mapping[str, str] | None) -> str:
    topic = (topics or {}).get(sensor)
    return f"{sensor} ({topic})" if topic else sensor


def _clipped(time: np.ndarray, name: str, y: np.ndarray, topics) -> tuple[list[Finding], list[tuple[int, float]]]:
    """Flat tops of the (N, 3) readings ``y`` of sensor ``name``; also ``(axis, value)`` of each."""
    out, tops = [], []
    for a in range(3):
        x = y[:, a]
        finite = np.isfinite(x)
        if finite.sum() < CLIP_MIN_LEVELS or np.unique(x[finite]).size < CLIP_MIN_LEVELS:
            continue
        lo, hi = float(np.min(x[finite])), float(np.max(x[finite]))
        if hi - lo <= CLIP_MIN_SPREAD * max(1.0, abs(hi), abs(lo)):
            continue
        band = 0.05 * (hi - lo)
        # A fine-grained signal (its levels closer than a thousandth of its span) does not dwell on
        # its extreme value in several separate runs unless something cut it there: resampled onto
        # a grid, a cut signal also piles up just inside the top (interpolated between the flat
        # top and its neighbours), which the count against the band would take for a turn.
        levels = np.unique(x[finite])
        fine = float(np.median(np.diff(levels))) <= 1e-3 * (hi - lo)
        for value, side in ((hi, 1.0), (lo, -1.0)):
            if abs(value) < CLIP_FLOOR[name]:
                continue
            with np.errstate(invalid="ignore"):
                at = finite & (np.abs(x - value) <= EQUAL_TOL)
                near = finite & ~at & (side * (value - x) <= band)
            runs = [(i, j) for i, j in _runs(at) if j - i + 1 >= CLIP_MIN_RUN]
            if not runs or (int(at.sum()) <= int(near.sum()) and not (fine and len(runs) >= CLIP_MIN_TOPS)):
                continue
            k = np.flatnonzero(at)
            unit = _UNIT[name]
            out.append(Finding(
                _named(name, topics), "clipped", float(time[k[0]]), float(time[k[-1]]),
                f"axis {_AXES[a]} sits at {value:.6g} {unit} (its {'largest' if side > 0 else 'smallest'} value) "
                f"for {k.size} samples in {len(runs)} flat top(s) of up to "
                f"{max(j - i + 1 for i, j in runs)} samples: the sensor saturates at about {abs(value):.4g} {unit}",
                f"the true {name} reading is beyond the flat top there, so the IMU update pulls the estimated forces "
                f"and tilt off; set {_RANGE_KEY[name]} = {abs(value):.6g} in the robot configuration to leave these "
                "samples out", channel=f"axis {_AXES[a]}"))
            tops.append((a, value))
    return out, tops


def _stuck_channel(time: np.ndarray, dt: float, sensor: str, channel: str, x: np.ndarray, unit: str,
                   effect: str, skip_values: tuple[float, ...] = (), cause: str = "") -> list[Finding]:
    """Spans of at least :data:`STUCK_MIN_S` s where the (N,) channel ``x`` does not change, other
    than at one of ``skip_values`` (the axis's flat tops, reported as clipped)."""
    if x.size < 2:
        return []
    with np.errstate(invalid="ignore"):
        same = np.abs(np.diff(x)) <= EQUAL_TOL * np.maximum(1.0, np.abs(x[1:]))
    need = max(STUCK_MIN_SAMPLES, int(np.ceil(STUCK_MIN_S / dt)) if dt > 0 else STUCK_MIN_SAMPLES)
    out = []
    for i, j in _runs(same):
        first, last = i, j + 1  # samples first..last are equal
        if last - first + 1 < need:
            continue
        value = float(x[first])
        if any(abs(value - v) <= EQUAL_TOL for v in skip_values):
            continue  # a flat top, reported as clipped
        out.append(Finding(sensor, "stuck", float(time[first]), float(time[last]),
                           f"{channel} is constant at {value:.6g} {unit} for {last - first + 1} samples "
                           f"({time[last] - time[first]:.3f} s) while a live sensor shows noise{cause}", effect,
                           channel=channel))
    return out


def _accel_units(time: np.ndarray, accel: np.ndarray, gravity: float, topics) -> list[Finding]:
    ok = np.isfinite(accel).all(axis=1)
    if not ok.any():
        return []
    med = float(np.median(np.linalg.norm(accel[ok], axis=1)))
    t0, t1 = float(time[0]), float(time[-1])
    name = _named("accel", topics)
    if G_UNITS[0] <= med <= G_UNITS[1]:
        return [Finding(name, "units", t0, t1,
                        f"the accelerometer's norm has a median of {med:.4g} over the recording against gravity "
                        f"{gravity:.4g} m/s^2: the readings are in g; expected m/s^2 (multiply them by {gravity:.4g})",
                        "every estimate would be wrong (gravity read 10 times too weak): refused", "error")]
    if med > ACCEL_NORM_MAX * gravity:
        return [Finding(name, "units", t0, t1,
                        f"the accelerometer's norm has a median of {med:.6g} over the recording, "
                        f"{med / gravity:.0f} times gravity {gravity:.4g} m/s^2: the readings are not in m/s^2 "
                        "(mg? cm/s^2?); expected m/s^2",
                        "every estimate would be wrong: refused", "error")]
    if abs(med / gravity - 1.0) > ACCEL_NORM_TOL:
        return [Finding(name, "units", t0, t1,
                        f"the accelerometer's norm has a median of {med:.4g} m/s^2 over the recording against gravity "
                        f"{gravity:.4g} m/s^2 ({100 * (med / gravity - 1):+.0f} %): a wrong scale, a clipped axis or a "
                        "large bias",
                        "the IMU update reads a wrong gravity: estimated forces and tilt are off")]
    return []


def _gyro_units(rec, g: np.ndarray, time: np.ndarray, topics) -> list[Finding]:
    ok = np.isfinite(g).all(axis=1)
    if not ok.any():
        return []
    t0, t1 = float(time[0]), float(time[-1])
    name = _named("gyro", topics)
    effect = ("the gyrometer is read as rad/s: the estimated rotation rates, tilt and forces are off by the same "
              "factor; convert the readings to rad/s")
    kin = np.einsum("nji,nj->ni", rec.imu_R[ok], rec.imu_w[ok])  # kinematic rate in the IMU frame
    gc = g[ok] - g[ok].mean(axis=0)
    kc = kin - kin.mean(axis=0)
    # axis by axis first: one axis in deg/s among two in rad/s
    kka, gka, gga = (kc * kc).sum(axis=0), (gc * kc).sum(axis=0), (gc * gc).sum(axis=0)
    moving = np.sqrt(kka / max(len(kc), 1)) > KINEMATIC_MIN_RATE
    with np.errstate(invalid="ignore", divide="ignore"):
        scale_a = gka / kka
        corr_a = gka / np.sqrt(np.maximum(gga * kka, 1e-300))
    deg = [i for i in range(3) if moving[i] and corr_a[i] > KINEMATIC_CORRELATION
           and DEG_REFUSE[0] <= scale_a[i] <= DEG_REFUSE[1]]
    fine = [i for i in range(3) if moving[i] and corr_a[i] > KINEMATIC_CORRELATION and 0.5 <= scale_a[i] <= 2.0]
    if deg and fine:
        axes = ", ".join(f"{_AXES[i]} ({scale_a[i]:.3g} times, correlation {corr_a[i]:.2f})" for i in deg)
        return [Finding(name, "units", t0, t1,
                        f"the gyrometer's axis {axes} reads the joint kinematics' rotation rate in deg/s (57.3) "
                        f"while axis {', '.join(_AXES[i] for i in fine)} reads it in rad/s; expected rad/s on every "
                        "axis (multiply that axis by pi/180)",
                        "every estimate would be wrong (one rotation rate 57 times too large): refused", "error",
                        channel="axis " + "".join(_AXES[i] for i in deg))]
    kk = float((kc * kc).sum())
    if np.isfinite(kk) and np.sqrt(kk / max(len(kc), 1)) > KINEMATIC_MIN_RATE:
        gk = float((gc * kc).sum())
        corr = gk / np.sqrt(max(float((gc * gc).sum()) * kk, 1e-300))
        scale = gk / kk
        if corr > KINEMATIC_CORRELATION and scale >= DEG_SCALE_MIN:
            sure = DEG_REFUSE[0] <= scale <= DEG_REFUSE[1]  # 180/pi, within the kinematics' agreement
            return [Finding(name, "units", t0, t1,
                            f"the gyrometer reads {scale:.3g} times the rotation rate of the joint kinematics "
                            f"(correlation {corr:.2f}): the readings "
                            + ("are in deg/s (57.3); expected rad/s (multiply them by pi/180)" if sure else
                               "look like deg/s (57.3); expected rad/s"),
                            "every estimate would be wrong (rotation rates 57 times too large): refused" if sure
                            else effect, "error" if sure else "warning")]
    med = float(np.median(np.linalg.norm(g[ok], axis=1)))
    if med > GYRO_MEDIAN_MAX:
        return [Finding(name, "units", t0, t1,
                        f"the gyrometer's rate has a median of {med:.4g} rad/s over the recording, more than "
                        f"{GYRO_MEDIAN_MAX:g} rad/s for a standing or walking robot: deg/s? expected rad/s", effect)]
    return []


def _imu_axes(rec, imu: Mapping[str, np.ndarray], time: np.ndarray, topics) -> list[Finding]:
    """Readings whose axes are not the IMU frame's of the URDF (swapped, or the frame wrong): the
    accelerometer's mean against the kinematics' mean specific force (gravity, mostly), the
    gyrometer's axes against the kinematic rotation rate's, axis by axis.  Not judged where the
    units are already wrong (those findings come first) or the kinematics do not move."""
    out: list[Finding] = []
    t0, t1 = float(time[0]), float(time[-1])
    R = np.asarray(rec.imu_R, dtype=float)
    a = imu["accel"]
    ok = np.isfinite(a).all(axis=1)
    if ok.sum() >= CLIP_MIN_LEVELS:
        up = np.array([0.0, 0.0, rec.gravity])
        pred = np.einsum("nji,nj->ni", R[ok], np.asarray(rec.imu_a, dtype=float)[ok] + up)
        m_read, m_pred = a[ok].mean(axis=0), pred.mean(axis=0)
        nr, npred = float(np.linalg.norm(m_read)), float(np.linalg.norm(m_pred))
        if nr > 0.5 * npred > 0 and 0.5 * nr < npred:  # a norm like gravity's: the units are right
            angle = float(np.degrees(np.arccos(np.clip(m_read @ m_pred / (nr * npred), -1.0, 1.0))))
            if angle > AXES_ANGLE_MAX:
                out.append(Finding(
                    _named("accel", topics), "axes", t0, t1,
                    f"the accelerometer's mean reading ({_vec(m_read)} m/s^2) is {angle:.0f} deg from the specific "
                    f"force the joint kinematics predict in the IMU frame ({_vec(m_pred)} m/s^2): the axes are "
                    "swapped or the IMU frame of the robot configuration is not the sensor's; expected readings in "
                    "that frame", "every estimate would be wrong (gravity read along another axis): refused",
                    "error"))
    g = imu["gyro"]
    ok = np.isfinite(g).all(axis=1)
    if ok.sum() >= CLIP_MIN_LEVELS:
        kin = np.einsum("nji,nj->ni", R[ok], np.asarray(rec.imu_w, dtype=float)[ok])
        gc, kc = g[ok] - g[ok].mean(axis=0), kin - kin.mean(axis=0)
        sg, sk = np.sqrt((gc * gc).mean(axis=0)), np.sqrt((kc * kc).mean(axis=0))
        if np.all(sk > KINEMATIC_MIN_RATE) and np.all(sg > 0):
            C = (gc.T @ kc) / len(gc) / np.outer(sg, sk)  # C[i, j]: gyro axis i against kinematic axis j
            for i in range(3):
                j = int(np.argmax(np.abs(C[i])))
                if j != i and abs(C[i, j]) > AXES_CORRELATION and abs(C[i, i]) < KINEMATIC_CORRELATION:
                    sign = "-" if C[i, j] < 0 else ""
                    out.append(Finding(
                        _named("gyro", topics), "axes", t0, t1,
                        f"the gyrometer's {_AXES[i]} axis follows the joint kinematics' rotation rate about "
                        f"{sign}{_AXES[j]} (correlation {C[i, j]:.2f}), not about {_AXES[i]} ({C[i, i]:.2f}): the "
                        "axes are swapped or the IMU frame of the robot configuration is not the sensor's; "
                        "expected readings in that frame",
                        "every estimate would be wrong (rotation rates about other axes): refused", "error",
                        channel=f"axis {_AXES[i]}"))
                    break
    return out


def _mocap_gaps(rec, time: np.ndarray, dt: float, topics) -> list[Finding]:
    """Spans of :data:`MOCAP_MISSING_MIN_S` s or longer without a motion-capture pose (a body seen
    somewhere in the recording): the references the comparison holds estimates against leave
    them out."""
    out: list[Finding] = []
    need = max(1, int(np.ceil(MOCAP_MISSING_MIN_S / dt))) if dt > 0 else 1
    for body, pose in (getattr(rec, "mocap", None) or {}).items():
        pose = np.asarray(pose, dtype=float)
        if pose.ndim != 2 or len(pose) != len(time):
            continue
        seen = np.isfinite(pose).all(axis=1)
        if not seen.any():
            continue
        for i, j in _runs(~seen):
            if j - i + 1 >= need:
                out.append(Finding(_named(f"mocap/{body}", topics), "missing", float(time[i]), float(time[j]),
                                   f"no pose for {j - i + 1} samples ({time[j] - time[i] + dt:.3f} s)",
                                   "the motion-capture reference is missing there: the errors against it (tilt, "
                                   "position) leave these samples out"))
    return out


def _vec(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.3g}" for x in v) + ")"


def _ft_checks(rec, time: np.ndarray, dt: float, topics, stuck: bool, whole: bool = True) -> list[Finding]:
    out: list[Finding] = []
    if rec.ft is None:
        return out
    need_missing = max(1, int(np.ceil(MISSING_MIN_S / dt))) if dt > 0 else 1
    for c, contact in enumerate(rec.contact_names):
        sensor = _named(f"ft/{contact}", topics)
        effect_stuck = ("the F/T reference is wrong there: force errors against it, contact states detected from "
                        "its normal force and the --ft measurement are off")
        with np.errstate(invalid="ignore"):
            zero = np.nanmax(np.abs(rec.ft[:, c]), axis=0, initial=0.0) == 0.0
        measured = np.isfinite(rec.ft[:, c]).any(axis=0) & ~zero  # (6,) channels read (NaN or 0: not measured)
        if not measured.any():
            if topics and f"ft/{contact}" in topics and whole:  # a topic the bag has, reading nothing
                out.append(Finding(sensor, "missing", float(time[0]), float(time[-1]),
                                   "no finite, nonzero reading in the whole recording, although the bag has the topic",
                                   WHOLE_MISSING_FT_EFFECT))
            continue
        lost = ~np.isfinite(rec.ft[:, c][:, measured]).any(axis=1)
        for i, j in _runs(lost):
            if j - i + 1 < need_missing:
                continue
            out.append(Finding(sensor, "missing", float(time[i]), float(time[j]),
                               f"no F/T reading for {j - i + 1} samples ({time[j] - time[i] + dt:.3f} s)",
                               MISSING_EFFECT))
        if stuck:
            for ch in np.flatnonzero(measured):
                out += _stuck_channel(time, dt, sensor, _FT[ch], rec.ft[:, c, ch], "N" if ch < 3 else "N m",
                                      effect_stuck)
    return out


def check_recording(rec, topics: Mapping[str, str] | None = None,
                    readings: Mapping[str, np.ndarray] | None = None, whole: bool = True) -> list[Finding]:
    """The sensor faults the data of ``rec`` reveal (module docstring), in the order clipped, units,
    stuck, missing.

    Args:
        rec: a :class:`flexforce.datasets.recording.Recording` (gyro and accel (N, 3), F/T (N, C, 6)
            or None; NaN where missing).
        topics: sensor (``"accel"``, ``"gyro"``, ``"ft/<contact>"``) -> the topic it came from,
            named in the findings.
        readings: ``"gyro"``/``"accel"`` -> (N, 3) readings judged instead of the recording's
            (an importer's readings before a smoothing filter, which would round off flat tops).
        whole: ``rec`` is the whole recording: an F/T topic of ``topics`` without a reading in
            it is missing (in a part of a stream it may only not have started).

    Stuck channels are not judged on a noise-free simulation (``meta["noise"]`` False), whose
    readings may be exactly constant.
    """
    time = rec.time
    dt = rec.dt
    stuck = rec.meta.get("noise", True) is not False
    imu = {name: np.asarray((readings or {}).get(name, getattr(rec, name)), dtype=float) for name in ("accel", "gyro")}
    out: list[Finding] = []
    tops: dict[str, list[tuple[int, float]]] = {}
    for name in ("accel", "gyro"):
        found, tops[name] = _clipped(time, name, imu[name], topics)
        out += found
    out += _accel_units(time, imu["accel"], rec.gravity, topics)
    out += _gyro_units(rec, imu["gyro"], time, topics)
    out += _imu_axes(rec, imu, time, topics)
    if stuck:
        for name in ("accel", "gyro"):
            effect = (f"the {name} reading is frozen there: the IMU update pulls the estimated forces and tilt "
                      "towards a stale value")
            for a in range(3):
                out += _stuck_channel(time, dt, _named(name, topics), f"axis {_AXES[a]}", imu[name][:, a],
                                      _UNIT[name], effect, tuple(v for axis, v in tops[name] if axis == a),
                                      " (a frozen driver, or the axis saturated at its full scale throughout)")
    out += _ft_checks(rec, time, dt, topics, stuck, whole)
    out += _mocap_gaps(rec, time, dt, topics)
    return out


def screen(rec, topics: Mapping[str, str] | None = None, where: str = "",
           readings: Mapping[str, np.ndarray] | None = None):
    """Check ``rec`` (:func:`check_recording`), record the findings in ``rec.meta['sensor_faults']``
    (left unset when there are none), warn (:class:`SensorFaultWarning`, one per finding) and
    return ``rec``.

    Args:
        topics, readings: as :func:`check_recording`.
        where: the recording's source, named in the messages (a bag's path).

    Raises:
        DataError: an unambiguous unit mistake (the accelerometer in g, mg or cm/s^2).
    """
    findings = check_recording(rec, topics, readings)
    prefix = f"{where}: " if where else ""
    for f in findings:
        if f.severity == "error":
            raise DataError(prefix + f.message())
    if findings:
        rec.meta["sensor_faults"] = [f.to_dict() for f in findings]
    for f in findings:
        warnings.warn(prefix + f.message(), SensorFaultWarning, stacklevel=2)
    return rec


class StreamScreen:
    """The checks of :func:`screen` on a recording that arrives in consecutive parts (a raw bag
    streamed, :func:`flexforce.datasets.io.stream.stream_bag`), part by part and in constant memory.

    Each part is checked with the last ``carry`` seconds of the parts before it, so that a fault
    spanning a boundary is judged whole (a stuck channel needs :data:`STUCK_MIN_S`); a finding is
    warned about once, when first seen (one that lasts to the end of the data read so far says
    "to at least", and :meth:`finish` gives its whole span at the end of the stream): a later
    part that only continues it (the same sensor, kind and channel, starting within ``carry`` of
    where it was last seen) extends its span in :attr:`findings` silently, and a wrong unit is
    reported once per sensor.  Times are seconds from the stream's
    first sample.  What a part-wise check sees less than a whole-recording one: a clipped axis
    whose flat tops are fewer than the band below them within the checked span, and a unit judged
    on the first parts' medians.

    Raises (on :meth:`__call__`):
        DataError: an unambiguous unit mistake (the accelerometer in g, mg or cm/s^2).
    """

    def __init__(self, topics: Mapping[str, str] | None = None, where: str = "", carry: float = 2 * STUCK_MIN_S,
                 readings: Callable[[Any], Mapping[str, np.ndarray] | None] | None = None):
        """``readings``: called with each part, the part's IMU readings to judge instead of its own
        (``"gyro"``/``"accel"`` -> (n, 3); None: the part's), as :func:`check_recording`'s."""
        self.topics = topics
        self.where = where
        self.carry = float(carry)
        self.readings = readings
        self._tail_raw: dict[str, np.ndarray] | None = None
        self.findings: list[Finding] = []
        """Every fault found so far, spans in seconds from the stream's first sample."""
        self._tail = None
        self._t0_ns: int | None = None
        self._last: dict[tuple[str, str, str], int] = {}  # key -> index in findings
        self._open: set[int] = set()  # findings warned about while they lasted ("to at least")
        self._read_ft: dict[str, np.ndarray] = {}  # contact -> (6,) channels read in an earlier part

    def __call__(self, part):
        """Check ``part`` (a Recording, the next of the stream) and return it unchanged."""
        from flexforce.datasets.recording import concat_recordings

        if self._t0_ns is None:
            self._t0_ns = int(part.t_ns[0])
        buf = part if self._tail is None else concat_recordings(self._tail, part)
        raw = self._readings(part, buf)
        offset = (int(buf.t_ns[0]) - self._t0_ns) * 1e-9
        start = (int(part.t_ns[0]) - self._t0_ns) * 1e-9
        end = (int(buf.t_ns[-1]) - self._t0_ns) * 1e-9
        prefix = f"{self.where}: " if self.where else ""
        for f in check_recording(buf, self.topics, raw, whole=False) + self._silent(buf):
            f = replace(f, t0=f.t0 + offset, t1=f.t1 + offset)
            if f.t1 < start - 1e-12:
                continue  # within the carried tail only: seen with the previous part
            key = (f.sensor, f.kind, f.channel)
            i = self._last.get(key)
            if i is not None and (f.kind == "units" or f.t0 <= self.findings[i].t1 + self.carry):
                old = self.findings[i]
                self.findings[i] = replace(old, t0=min(old.t0, f.t0), t1=max(old.t1, f.t1))
                continue
            if f.severity == "error":
                raise DataError(prefix + f.message())
            self._last[key] = len(self.findings)
            self.findings.append(f)
            text = f.message()
            if f.kind != "units" and f.t1 >= end - 0.5 * buf.dt:  # still so at the end of what was read
                text = text.replace(f" to {f.t1:.3f} s: ", f" to at least {f.t1:.3f} s (the data read so far): ", 1)
                self._open.add(len(self.findings) - 1)
            warnings.warn(prefix + text, SensorFaultWarning, stacklevel=2)
        keep = max(1, int(round(self.carry / buf.dt))) if buf.dt > 0 else buf.n
        self._tail = buf.slice(max(0, buf.n - keep), buf.n)
        if raw is not None:
            self._tail_raw = {k: v[max(0, buf.n - keep):] for k, v in raw.items()}
        return part

    def _readings(self, part, buf) -> dict[str, np.ndarray] | None:
        """The readings to judge over ``buf`` (the carried tail and ``part``), or None."""
        got = self.readings(part) if self.readings is not None else None
        if got is None:
            self._tail_raw = None
            return None
        tail = self._tail_raw
        if tail is None or self._tail is None or buf.n - part.n != len(next(iter(tail.values()))):
            tail = {k: np.asarray(getattr(buf, k)[:buf.n - part.n], dtype=float) for k in got}
        return {k: np.concatenate([tail[k], np.asarray(v, dtype=float)]) for k, v in got.items()}

    def _silent(self, buf) -> list[Finding]:
        """A ``missing`` finding over the whole of ``buf`` for each F/T sensor whose channels read
        earlier in the stream are NaN throughout ``buf``: on its own such a span looks like a
        sensor that is not measured (:func:`check_recording` skips it), in a stream it continues a
        gap."""
        out: list[Finding] = []
        if buf.ft is None:
            return out
        with np.errstate(invalid="ignore"):
            zero = np.nanmax(np.abs(buf.ft), axis=0, initial=0.0) == 0.0  # (C, 6)
        measured = np.isfinite(buf.ft).any(axis=0) & ~zero  # (C, 6) channels with a reading in buf
        t = buf.time
        for c, contact in enumerate(buf.contact_names):
            before = self._read_ft.get(contact)
            if measured[c].any():
                self._read_ft[contact] = measured[c] if before is None else (before | measured[c])
            elif before is not None and not np.isfinite(buf.ft[:, c][:, before]).any():
                out.append(Finding(_named(f"ft/{contact}", self.topics), "missing", float(t[0]), float(t[-1]),
                                   f"no F/T reading for {buf.n} samples ({t[-1] - t[0] + buf.dt:.3f} s)",
                                   MISSING_EFFECT))
        return out

    def finish(self) -> None:
        """At the end of the stream: one more warning for each fault first reported while it
        lasted ("to at least"), with its whole span."""
        prefix = f"{self.where}: " if self.where else ""
        if self._t0_ns is not None and self._tail is not None:  # F/T topics that never read anything
            end = (int(self._tail.t_ns[-1]) - self._t0_ns) * 1e-9
            for sensor in sorted(s for s in (self.topics or {}) if s.startswith("ft/")):
                if sensor[3:] not in self._read_ft and sensor[3:] in self._tail.contact_names:
                    f = Finding(_named(sensor, self.topics), "missing", 0.0, end,
                                "no finite, nonzero reading in the whole stream, although the bag has the topic",
                                WHOLE_MISSING_FT_EFFECT)
                    self.findings.append(f)
                    warnings.warn(prefix + f.message(), SensorFaultWarning, stacklevel=2)
        for i in sorted(self._open):
            f = self.findings[i]
            warnings.warn(f"{prefix}{f.sensor} {f.kind}, whole span from t = {f.t0:.3f} s to {f.t1:.3f} s "
                          f"({f.t1 - f.t0:.3f} s){' on ' + f.channel if f.channel else ''}", SensorFaultWarning,
                          stacklevel=2)
        self._open.clear()
