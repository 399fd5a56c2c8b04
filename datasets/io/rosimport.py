r"""Import raw robot bags (ROS 1 ``.bag``, ROS 2 sqlite3 or MCAP) into a :class:`Recording`.

All formats go through rosbags' one reader (:class:`rosbags.highlevel.AnyReader`); the robot
configuration's ``[ros]`` table (:class:`flexforce.datasets.robot.RosConfig`) maps the topics:

====================================  ==========================  ===========================================
message                               topic (config key)          becomes
====================================  ==========================  ===========================================
``sensor_msgs/Imu``                   ``imu_topic``               ``gyro``, ``accel`` (IMU frame)
``sensor_msgs/JointState``            ``joint_states_topic``      ``joint_q``, ``joint_v`` and, through the
                                                                  local frame, every local-frame input
``geometry_msgs/WrenchStamped``       ``ft_topics[contact]``      ``ft[:, contact]`` (contact frame) and the
                                                                  contact states (Schmitt trigger)
``geometry_msgs/PoseStamped``         ``mocap_topics[frame]``     ``mocap[frame]`` (world pose, NaN if lost)
====================================  ==========================  ===========================================

Method (docs/real-logs.md has the long form):

* **Time.** A message's time is its ``header.stamp`` (the robot's clock), or the bag's log time
  when the stamp is zero.  A stamp earlier than its predecessor on the same topic is a
  :class:`DataError`; a repeated stamp keeps the first message.
* **Grid.** Uniform, from the latest first stamp to the earliest last stamp of the IMU and joint
  topics, at ``rate`` (argument, else ``ros.rate``, else the IMU's median message rate; the
  period is rounded to whole ns).
* **Missing IMU readings.** A NaN or inf IMU component is a missing reading: the grid points its
  message brackets are NaN on that axis, which the estimators skip (``meta['imu_missing_messages']``
  counts the messages; a recording missing more than 10 % is refused when validated).
* **Resampling.** Linear interpolation onto the grid of the IMU readings, joint positions (and
  message velocities), F/T components; motion-capture positions linearly and orientations by
  normalised linear interpolation of sign-aligned quaternions (nlerp; at 100 Hz it differs from
  slerp by < 1e-6 rad).  Every source interval longer than ``gap_factor`` grid periods is listed
  in ``meta['gaps']``.  Intervals longer than ``max_gap`` s are a :class:`DataError` on the IMU
  and joint topics (no inputs can be made up there); F/T and mocap samples inside them are NaN.
* **Derivatives.** Joint velocities: the message's (interpolated) when every message has them
  and ``ros.joint_velocity = "message"``, else a Savitzky-Golay first derivative of the
  positions.  Joint accelerations: a Savitzky-Golay first derivative of the velocities taken
  from messages, or the second derivative of the positions (scipy.signal.savgol_filter, window
  ``savgol_window`` s, order ``savgol_order``, ``mode="interp"``).
* **IMU bandwidth.** ``ros.imu_filter = "savgol"``: the IMU readings on the grid through the same
  Savitzky-Golay smoother (zeroth derivative), so that they see the band of their kinematic
  prediction (formed from the smoothed joint derivatives); a missing or clipped reading makes the
  outputs whose window holds it missing (:func:`imu_smoothed`).  ``"none"``: as resampled.
* **Contacts.** ``contacts="ft"``: Schmitt trigger on the F/T normal force (``contact_on`` /
  ``contact_off``; :mod:`flexforce.datasets.contacts`); ``contacts="fixed"``: ``fixed_contacts``
  (all contacts by default) active throughout.
* **Sensor faults.** Clipped, stuck or missing sensors and IMU readings in the wrong unit,
  recognised from the data (:mod:`flexforce.datasets.sensorcheck`; the IMU as resampled, before
  ``imu_filter``): an accelerometer in g, mg or cm/s^2 is a :class:`DataError`, every other
  finding a warning naming the topic, the span and the effect, listed in ``meta['sensor_faults']``.
* **Local frame.** Stance-foot leg odometry (:mod:`flexforce.datasets.io.localframe`), then
  :meth:`RobotModel.kinematics` gives the inputs, the IMU placement and the contacts.

``meta`` holds the source, the grid, the method, the gaps, the contact phases, the anchor
switches.  The root link's pose in the local frame is ``Recording.base_pose`` ((N, 7),
x y z qx qy qz qw) so that motion capture can be compared.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
from scipy.signal import savgol_filter

from flexforce.datasets.contacts import fixed_contacts, phases, schmitt_trigger
from flexforce.datasets.faults import RANGE_TOLERANCE
from flexforce.datasets.io.localframe import anchored_local_frame
from flexforce.datasets.recording import Recording
from flexforce.datasets.robot import RobotConfig, RobotModel, RosConfig
from flexforce.datasets.sensorcheck import SensorFaultWarning, screen
from flexforce.errors import BagError, ConfigError, DataError

__all__ = ["import_bag", "is_flexforce_bag", "read_topics"]

T_IMU = "sensor_msgs/msg/Imu"
T_JOINTS = "sensor_msgs/msg/JointState"
T_WRENCH = "geometry_msgs/msg/WrenchStamped"
T_POSE = "geometry_msgs/msg/PoseStamped"
FOOTHOLD_BOUND = 6.0
"""A landing sole further from the floor plane than this many leg-kinematics sigmas contradicts
the ground prior: an error, not a silent correction."""
META_TOPIC = "/flexforce/meta"
INPUT_BLOCK = 500
"""Steps whose inputs :func:`local_inputs` forms at once between two progress reports."""
_NS = 1_000_000_000
_EXPECTED = "expected a ROS 2 bag directory, .mcap/.db3 file or ROS 1 .bag file"


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _check_path(path: Path) -> None:
    if not path.exists():
        raise BagError(f"bag {path} does not exist; {_EXPECTED}")


def _reader_error(path: Path, err: Exception) -> BagError:
    detail = " ".join(str(err).split()) or type(err).__name__
    return BagError(f"cannot read bag {path}: corrupt, truncated or not a bag ({detail}); {_EXPECTED}")


def is_flexforce_bag(path) -> bool:
    """True when the bag at ``path`` is a flexforce recording (it has ``/flexforce/meta``).

    Raises :class:`BagError` when the path is missing or not a readable bag.
    """
    from rosbags.highlevel import AnyReader

    path = Path(path)
    _check_path(path)
    try:
        with AnyReader([path], default_typestore=_typestore()) as reader:
            return any(c.topic == META_TOPIC for c in reader.connections)
    except Exception as err:  # noqa: BLE001 -- any library failure means an unreadable bag
        raise _reader_error(path, err) from err


@dataclass
class _Topic:
    """Messages of one topic: stamps (ns, strictly increasing) and messages, in that order."""

    name: str
    msgtype: str
    t_ns: np.ndarray
    msgs: list
    duplicates: int = 0


def read_topics(path, wanted: dict[str, str]) -> tuple[dict[str, _Topic], dict[str, str], str]:
    """Read the topics ``wanted`` (topic -> expected msgtype) of a bag.

    Returns ``(topics found, all topics of the bag -> msgtype, storage description)``.  A wanted
    topic that is absent is simply not in the first dict; the caller decides if it is required.
    """
    from rosbags.highlevel import AnyReader

    path = Path(path)
    _check_path(path)
    found: dict[str, list] = {}
    try:
        with AnyReader([path], default_typestore=_typestore()) as reader:
            types = {c.topic: c.msgtype for c in reader.connections}
            storage = "ROS 2" if reader.is2 else "ROS 1"
            for topic, msgtype in wanted.items():
                if topic in types and types[topic] != msgtype:
                    raise BagError(f"topic {topic} of bag {path} has type {types[topic]}; expected {msgtype}")
            conns = [c for c in reader.connections if c.topic in wanted]
            for conn, log_ns, raw in reader.messages(connections=conns):
                found.setdefault(conn.topic, []).append((log_ns, reader.deserialize(raw, conn.msgtype)))
    except BagError:
        raise
    except Exception as err:  # noqa: BLE001
        raise _reader_error(path, err) from err
    topics = {}
    for topic, items in found.items():
        stamps = np.array([_stamp(m, log) for log, m in items], dtype=np.int64)
        back = np.flatnonzero(np.diff(stamps) < 0)
        if back.size:
            k = int(back[0]) + 1
            raise DataError(
                f"time goes backwards on topic {topic}: message {k} is stamped {stamps[k] * 1e-9:.6f} s, "
                f"{(stamps[k - 1] - stamps[k]) * 1e-6:.3f} ms before message {k - 1}; "
                "expected non-decreasing header stamps")
        keep = np.concatenate([[True], np.diff(stamps) > 0])
        topics[topic] = _Topic(topic, types[topic], stamps[keep], [m for (_, m), ok in zip(items, keep) if ok],
                               int((~keep).sum()))
    return topics, types, storage


def _stamp(msg, log_ns: int) -> int:
    header = getattr(msg, "header", None)
    if header is not None:
        t = int(header.stamp.sec) * _NS + int(header.stamp.nanosec)
        if t != 0:
            return t
    return int(log_ns)


# ------------------------------------------------------------------------------------------------
# resampling
# ------------------------------------------------------------------------------------------------
def _interp(t_src: np.ndarray, values: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Linear interpolation of (M, ...) ``values`` at ``grid``; NaN outside the source span."""
    shape = values.shape[1:]
    v = values.reshape(len(t_src), -1)
    j = np.clip(np.searchsorted(t_src, grid, side="right") - 1, 0, len(t_src) - 2)
    t0, t1 = t_src[j], t_src[j + 1]
    w = ((grid - t0) / (t1 - t0).astype(float))[:, None]
    out = (1.0 - w) * v[j] + w * v[j + 1]
    exact = grid == t1  # keep an exact sample exactly (no 0 * NaN from the other end)
    out[exact] = v[j[exact] + 1]
    exact = grid == t0
    out[exact] = v[j[exact]]
    out[(grid < t_src[0]) | (grid > t_src[-1])] = np.nan
    return out.reshape((len(grid),) + shape)


def _gaps(topic: str, t_src: np.ndarray, t0: int, report: float, grid: np.ndarray) -> list[dict]:
    """Source intervals longer than ``report`` s that overlap the grid, as meta entries."""
    d = np.diff(t_src) * 1e-9
    out = []
    for j in np.flatnonzero(d > report):
        if t_src[j + 1] < grid[0] or t_src[j] > grid[-1]:
            continue
        out.append({"topic": topic, "start": round((t_src[j] - t0) * 1e-9, 6),
                    "end": round((t_src[j + 1] - t0) * 1e-9, 6), "duration": round(float(d[j]), 6)})
    return out


def _in_long_gap(t_src: np.ndarray, grid: np.ndarray, max_gap: float) -> np.ndarray:
    """(N,) bool: grid points inside a source interval longer than ``max_gap`` s."""
    j = np.clip(np.searchsorted(t_src, grid, side="right") - 1, 0, len(t_src) - 2)
    inside = (grid > t_src[j]) & (grid < t_src[j + 1])
    return inside & ((t_src[j + 1] - t_src[j]) * 1e-9 > max_gap)


def _require_finite(topic: _Topic, values: np.ndarray, what: str, t0: int, labels=None) -> None:
    bad = ~np.isfinite(values.reshape(len(values), -1))
    if bad.any():
        k, col = (int(x[0]) for x in np.nonzero(bad))
        name = f" ({labels[col]})" if labels is not None else ""
        raise DataError(f"topic {topic.name} message {k} (t = {(topic.t_ns[k] - t0) * 1e-9:.3f} s) has NaN or "
                        f"inf in {what}{name}; expected finite values")


def savgol_samples(ros: RosConfig, dt: float) -> int:
    """The Savitzky-Golay window in grid samples: ``ros.savgol_window`` rounded to an odd number.

    Raises:
        ConfigError: fewer samples than the polynomial needs (``ros.savgol_order + 2``, odd): the
            window the configuration asks for cannot be had on this grid.
    """
    win = int(round(ros.savgol_window / dt)) | 1
    need = ros.savgol_order + 2 + ((ros.savgol_order + 1) % 2)
    if win < need:
        raise ConfigError(f"ros.savgol_window = {ros.savgol_window:g} s is {win} sample(s) on this {1.0 / dt:.4g} Hz "
                          f"grid; expected at least {need} samples ({need * dt:.3g} s) for ros.savgol_order = "
                          f"{ros.savgol_order}")
    return win


def window_holds(bad: np.ndarray, win: int) -> np.ndarray:
    """(N, ...) bool: the rows whose Savitzky-Golay window (``win`` samples, ``mode="interp"``) holds
    a True of ``bad`` (N, ...): the window centred on the row, the first (last) window for the
    ``win // 2`` rows at the start (end), whose outputs are that window's polynomial fit."""
    n, h = len(bad), win // 2
    count = np.concatenate([np.zeros((1,) + bad.shape[1:], dtype=np.int64), np.cumsum(bad, axis=0)])
    start = np.clip(np.arange(n) - h, 0, max(n - win, 0))
    stop = np.minimum(start + win, n)
    return (count[stop] - count[start]) > 0


def imu_smoothed(x: np.ndarray, full_scale: float, win: int, smooth) -> np.ndarray:
    """The (N, 3) IMU readings ``x`` of one sensor through ``smooth`` (the Savitzky-Golay smoother of
    ``win`` samples on a finite (N, 3) array), :attr:`RosConfig.imu_filter` ``"savgol"``.

    A reading the smoother cannot use -- missing (NaN) or at the sensor's ``full_scale`` (within
    :data:`~flexforce.datasets.faults.RANGE_TOLERANCE`: clipped, the smoothed value would hide it) --
    leaves NaN (missing, which the estimators skip) on its axis at every output whose window holds it.
    """
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(x) | (np.abs(x) >= full_scale * (1.0 - RANGE_TOLERANCE))
    out = np.array(smooth(np.where(bad, 0.0, x)), dtype=float)
    out[window_holds(bad, win)] = np.nan
    return out


def _savgol(x: np.ndarray, dt: float, deriv: int, ros: RosConfig) -> np.ndarray:
    win = savgol_samples(ros, dt)
    if win > len(x):
        raise DataError(f"recording has {len(x)} samples, fewer than the Savitzky-Golay window of {win} "
                        f"samples (ros.savgol_window = {ros.savgol_window} s); expected a longer log")
    return savgol_filter(x, win, ros.savgol_order, deriv=deriv, delta=dt, axis=0, mode="interp")


# ------------------------------------------------------------------------------------------------
def import_bag(path, robot_config, rate: float | None = None, contacts: str = "ft",
               progress=None) -> Recording:
    """Read a raw robot bag into a validated :class:`Recording` on a uniform grid.

    Args:
        path: ROS 1 ``.bag`` file, ROS 2 bag directory, or ``.mcap``/``.db3`` file.
        robot_config: :class:`RobotConfig`, :class:`RobotModel`, built-in robot name or TOML path;
            its ``[ros]`` table maps the topics (defaults of :class:`RosConfig` when absent).
        rate: grid rate, Hz (overrides ``ros.rate``; default the IMU's median rate).
        contacts: ``"ft"`` (Schmitt trigger on the F/T normal forces) or ``"fixed"``.
        progress: optional callable receiving the fraction done (0..1).

    Raises:
        BagError: missing/unreadable/truncated bag, missing topic, wrong message type,
            unknown joint or frame.
        DataError: NaN, time going backwards, gaps longer than ``ros.max_gap``; an accelerometer
            in g, mg or cm/s^2 (:func:`flexforce.datasets.sensorcheck.screen`).
        ConfigError: inconsistent configuration.

    The sensor faults the data reveal (clipping, units, stuck or missing sensors) are checked
    last (:func:`flexforce.datasets.sensorcheck.screen`): listed in ``meta['sensor_faults']``, each
    a :class:`~flexforce.datasets.sensorcheck.SensorFaultWarning`.
    """
    path = Path(path)
    model = robot_config if isinstance(robot_config, RobotModel) else RobotModel(robot_config)
    config: RobotConfig = model.config
    ros = config.ros or RosConfig()
    _check_ros_config(model, ros, contacts)
    report = progress or (lambda f: None)

    topics, all_types, storage, wanted = _read_robot_topics(path, config, ros, contacts, report)
    imu, joints = topics[ros.imu_topic], topics[ros.joint_states_topic]
    t_first = int(min(t.t_ns[0] for t in topics.values()))
    grid, period = _grid(imu, joints, rate or ros.rate or 1e9 / float(np.median(np.diff(imu.t_ns))))
    dt = period * 1e-9
    gaps = _GapCheck(grid, ros.gap_factor * dt, ros.max_gap)
    gyro, accel, imu_missing = _imu_on_grid(imu, model, grid, gaps)
    joint = _joints_on_grid(joints, model, ros, grid, dt, t_first, gaps)
    resampled = {"gyro": gyro, "accel": accel}  # before the filter: flat tops and stuck values intact
    if ros.imu_filter == "savgol":
        win, noise = savgol_samples(ros, dt), config.imu_noise
        gyro = imu_smoothed(gyro, noise.gyro_range, win, lambda x: _savgol(x, dt, 0, ros))
        accel = imu_smoothed(accel, noise.accel_range, win, lambda x: _savgol(x, dt, 0, ros))
    report(0.3)
    ft = _ft_on_grid(topics, model, ros, grid, joint.q, gaps)
    active, method = _contact_states(model, ros, contacts, ft, len(grid))
    load = ft[:, :, 2] if ft is not None else None
    anchor = _anchor(ros, config)
    _check_in_force(path, ros, contacts, config.contact_names, active, method, ft, dt)
    footholds = config.footholds  # terrain "none": zero weights, the touch-downs still measured
    lf = anchored_local_frame(model, joint.q, joint.v, joint.a, active, load, anchor,
                              progress=lambda f: report(0.3 + 0.3 * f), footholds=footholds)
    check_touch_downs(lf.footholds, footholds, config.contact_names, lambda k: (grid[k] - grid[0]) * 1e-9)
    arrays = local_inputs(model, lf, progress=lambda f: report(0.6 + 0.35 * f))
    mocap = _mocap_on_grid(topics, ros, grid, gaps)
    source = {"path": str(path), "format": storage, "robot_config": config.source or config.name,
              "topics": {t: tp.msgtype for t, tp in topics.items()},
              "missing_topics": sorted(set(wanted) - set(topics)),
              "t0_ns": int(grid[0]),
              "messages": {t: len(tp.t_ns) for t, tp in topics.items()},
              "duplicate_stamps": {t: tp.duplicates for t, tp in topics.items() if tp.duplicates}}
    meta = _import_meta(source, model, ros, grid, period, imu_missing, joint, gaps.found, active, method, lf, mocap)
    rec = Recording(
        t_ns=grid, robot=config.source or config.name, contact_names=config.contact_names, mass=model.mass,
        contact_active=active, contact_p=lf.contact_p, contact_R=lf.contact_R, gyro=gyro, accel=accel,
        joint_names=tuple(model.joint_names), joint_q=joint.q, joint_v=joint.v, ft=ft, mocap=mocap,
        base_pose=lf.base_pose,
        gravity=config.gravity, meta=meta, **arrays)
    report(1.0)
    sensors = {"accel": ros.imu_topic, "gyro": ros.imu_topic,
               **{f"ft/{c}": t for c, t in (ros.ft_topics or {}).items() if t in topics}}
    # the sensor screen first: a unit mistake (a gyro in deg/s beyond its full scale) also leaves
    # readings missing, and the unit is what to name
    return screen(rec, sensors, where=str(path), readings=resampled).validate()


def _check_ros_config(model: RobotModel, ros: RosConfig, contacts: str) -> None:
    """The ``[ros]`` table against the robot and the contact detection ``contacts``.

    Raises:
        ConfigError: an unknown ``contacts``, an F/T topic of an unknown contact, a contact without
            F/T topic under ``contacts="ft"``, a motion-capture frame not in the URDF.
    """
    config = model.config
    if contacts not in ("ft", "fixed"):
        raise ConfigError(f"contacts = {contacts!r}; expected 'ft' (from F/T normal forces) or 'fixed'")
    for name in ros.ft_topics:
        if name not in config.contact_names:
            raise ConfigError(f"ros.ft_topics names contact '{name}'; robot '{config.name}' has contacts "
                              f"{list(config.contact_names)}")
    if contacts == "ft":
        missing = [c for c in config.contact_names if c not in ros.ft_topics]
        if missing:
            raise ConfigError(f"contacts='ft' needs an F/T topic for every contact; ros.ft_topics lacks "
                              f"{missing} (or use contacts='fixed')")
    for frame in ros.mocap_topics:
        if not model.model.existFrame(frame):
            raise ConfigError(f"ros.mocap_topics names frame '{frame}', which is not in the URDF of robot "
                              f"'{config.name}'")


def _read_robot_topics(path: Path, config: RobotConfig, ros: RosConfig, contacts: str,
                       report) -> tuple[dict[str, _Topic], dict[str, str], str, dict[str, str]]:
    """``(topics, all types, storage, wanted)`` of :func:`read_topics` for the topics the ``[ros]``
    table names (``wanted``: topic -> msgtype), the required ones (IMU, joints, and the F/T under
    ``contacts="ft"``) checked present, the IMU and joints with two messages at least; ``report``
    is given 0.15 once they are read.

    Raises:
        BagError: a required topic absent or empty, an IMU or joint topic of one message.
    """
    wanted = {ros.imu_topic: T_IMU, ros.joint_states_topic: T_JOINTS}
    wanted.update({topic: T_WRENCH for topic in ros.ft_topics.values()})
    wanted.update({topic: T_POSE for topic in ros.mocap_topics.values()})
    topics, all_types, storage = read_topics(path, wanted)
    report(0.15)
    required = [ros.imu_topic, ros.joint_states_topic]
    if contacts == "ft":
        required += [ros.ft_topics[c] for c in config.contact_names]
    for required_topic in required:
        if required_topic not in topics and required_topic in all_types:
            raise BagError(f"topic {required_topic} ({all_types[required_topic]}) of bag {path} has no messages; "
                           f"expected the messages robot config '{config.name}' reads from it")
        if required_topic not in topics:
            have = ", ".join(f"{t} ({m})" for t, m in sorted(all_types.items())) or "none"
            raise BagError(f"bag {path} lacks topic {required_topic} ({wanted[required_topic]}) named by robot config "
                           f"'{config.name}'; the bag has: {have}")
    for tp in (topics[ros.imu_topic], topics[ros.joint_states_topic]):
        if len(tp.t_ns) < 2:
            raise BagError(f"topic {tp.name} has {len(tp.t_ns)} message(s); expected at least 2")
    return topics, all_types, storage, wanted


TOPIC_CUT_WARN_S = 0.5
"""The IMU or joint topic running this much longer (s) than the other at either end is warned about:
the recording is their common span."""
OVERLAP_MIN = 0.5
"""The IMU and joint topics must overlap over at least this fraction of the longer one's span: less
is two clocks apart (a joint-state stamp 10 s ahead of the IMU's), not a log cut short."""


def _grid(imu: _Topic, joints: _Topic, rate: float) -> tuple[np.ndarray, int]:
    """``(grid, period)``: the uniform grid (ns) at ``rate`` Hz over the span of both the IMU and
    the joint topics, and its period rounded to whole ns.

    Raises:
        DataError: the two topics do not overlap in time.
    """
    period = int(round(1e9 / rate))
    start = max(imu.t_ns[0], joints.t_ns[0])
    stop = min(imu.t_ns[-1], joints.t_ns[-1])
    if stop <= start:
        raise DataError(f"topics {imu.name} and {joints.name} do not overlap in time; expected simultaneous logs")
    spans = {tp.name: (int(tp.t_ns[0]), int(tp.t_ns[-1])) for tp in (imu, joints)}
    longest = max(b - a for a, b in spans.values())
    if stop - start < OVERLAP_MIN * longest:
        t0 = min(a for a, _ in spans.values())
        told = ", ".join(f"{name} {(a - t0) * 1e-9:.3f} to {(b - t0) * 1e-9:.3f} s" for name, (a, b) in spans.items())
        offset = (joints.t_ns[0] - imu.t_ns[0]) * 1e-9
        raise DataError(f"topics {imu.name} and {joints.name} overlap {(stop - start) * 1e-9:.3f} s only ({told}): "
                        f"their clocks look {offset:+.3f} s apart; expected simultaneous logs (stamps from one clock)")
    n = int((stop - start) // period) + 1
    t0 = min(int(imu.t_ns[0]), int(joints.t_ns[0]))
    for first, other in ((imu, joints), (joints, imu)):
        for side, cut in (("before", int(start) - int(first.t_ns[0])), ("after", int(first.t_ns[-1]) - int(stop))):
            if cut * 1e-9 > TOPIC_CUT_WARN_S:
                edge = (start if side == "before" else stop) - t0
                warnings.warn(f"topic {first.name} runs {cut * 1e-9:.3f} s {side} topic {other.name} "
                              f"{'starts' if side == 'before' else 'ends'} (at t = {edge * 1e-9:.3f} s): the "
                              "recording covers only the span both are logged, and those samples are left out",
                              SensorFaultWarning, stacklevel=3)
    return start + period * np.arange(n, dtype=np.int64), period


class _GapCheck:
    """The source intervals of each topic against the grid: those longer than ``report`` s are
    collected in :attr:`found` (``meta['gaps']``), those longer than ``max_gap`` s mark the grid
    points inside them."""

    def __init__(self, grid: np.ndarray, report: float, max_gap: float):
        self.grid, self.report, self.max_gap = grid, report, max_gap
        self.found: list[dict] = []

    def __call__(self, topic: _Topic, fatal: bool) -> np.ndarray:
        """(N,) bool: the grid points inside a gap longer than ``max_gap`` s of ``topic``.

        Raises:
            DataError: such a gap when ``fatal`` (inputs cannot be made up there).
        """
        grid = self.grid
        self.found.extend(_gaps(topic.name, topic.t_ns, int(grid[0]), self.report, grid))
        long = _in_long_gap(topic.t_ns, grid, self.max_gap)
        if fatal and long.any():
            k = int(np.flatnonzero(long)[0])
            j = int(np.searchsorted(topic.t_ns, grid[k]) - 1)
            raise DataError(
                f"topic {topic.name} has a gap of {(topic.t_ns[j + 1] - topic.t_ns[j]) * 1e-9:.3f} s from "
                f"t = {(topic.t_ns[j] - grid[0]) * 1e-9:.3f} s to {(topic.t_ns[j + 1] - grid[0]) * 1e-9:.3f} s; "
                f"expected gaps shorter than ros.max_gap = {self.max_gap} s")
        return long


def _imu_on_grid(imu: _Topic, model: RobotModel, grid: np.ndarray,
                 gaps: _GapCheck) -> tuple[np.ndarray, np.ndarray, int]:
    """``(gyro, accel, missing)``: the (N, 3) IMU readings on the grid and the count of messages
    with a NaN or inf component (a missing reading: NaN on that axis at the grid points it brackets).

    Raises:
        BagError: a message in another frame than the robot's IMU frame.
        DataError: a gap longer than ``ros.max_gap``.
    """
    config = model.config
    frames = {m.header.frame_id for m in imu.msgs} - {""}
    for frame in frames:
        if frame != config.imu_frame:
            known = "a frame of the URDF" if model.model.existFrame(frame) else "unknown to the URDF"
            raise BagError(f"topic {imu.name} is in frame '{frame}' ({known}); expected the IMU frame "
                           f"'{config.imu_frame}' of robot config '{config.name}'")
    gyro_src = np.array([(m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z) for m in imu.msgs])
    acc_src = np.array([(m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z)
                        for m in imu.msgs])
    # A NaN or inf reading is a missing one: the grid points it brackets are NaN on that axis, and
    # the estimators skip them (Recording.validate refuses more than 10 % missing).
    imu_missing = int(np.sum((~np.isfinite(np.concatenate([gyro_src, acc_src], axis=1))).any(axis=1)))
    gyro_src = np.where(np.isfinite(gyro_src), gyro_src, np.nan)
    acc_src = np.where(np.isfinite(acc_src), acc_src, np.nan)
    gaps(imu, fatal=True)
    return _interp(imu.t_ns, gyro_src, grid), _interp(imu.t_ns, acc_src, grid), imu_missing


@dataclass
class _Joints:
    """The joints on the grid (the URDF's joint order)."""

    q: np.ndarray
    """(N, J) positions, rad (the reference configuration's for a joint never measured)."""
    v: np.ndarray
    """(N, J) velocities, rad/s (zero for a joint never measured)."""
    a: np.ndarray
    """(N, J) accelerations, rad/s^2 (zero for a joint never measured)."""
    measured: np.ndarray
    """(J,) bool: named by the joint messages."""
    velocity_source: str
    """``"message"`` (the messages' velocities) or ``"savgol"`` (differentiated positions)."""


def _joint_sources(joints: _Topic, model: RobotModel, ros: RosConfig) -> tuple[np.ndarray, np.ndarray, bool]:
    """``(q_src, v_src, has_vel)``: the (M, J) positions and velocities of the M joint messages in
    the URDF's joint order (NaN for a joint a message does not name), and whether every message
    has velocities.

    Raises:
        ConfigError: a joint of the URDF with more than one position coordinate.
        BagError: a joint the robot does not have (unless ``ros.ignore_joints``), as many
            positions as names.
    """
    config, pmodel = model.config, model.model
    ignore = re.compile(ros.ignore_joints) if ros.ignore_joints else None
    model_names = model.joint_names
    index = {name: i for i, name in enumerate(model_names)}
    for jname in pmodel.names[2:]:
        if pmodel.joints[pmodel.getJointId(jname)].nq != 1:
            raise ConfigError(f"joint '{jname}' of robot '{config.name}' has "
                              f"{pmodel.joints[pmodel.getJointId(jname)].nq} "
                              "position coordinates; only 1-dof joints are supported")
    nj = len(model_names)
    q_src = np.full((len(joints.msgs), nj), np.nan)
    v_src = np.full((len(joints.msgs), nj), np.nan)
    has_vel = True
    cols_cache: dict[tuple, tuple] = {}
    for k, m in enumerate(joints.msgs):
        names = tuple(m.name)
        if names not in cols_cache:
            src, dst = [], []
            for s, name in enumerate(names):
                if name in index:
                    src.append(s)
                    dst.append(index[name])
                elif ignore is None or not ignore.search(name):
                    raise BagError(
                        f"topic {joints.name} message {k} names joint '{name}', which robot '{config.name}' "
                        f"(URDF {config.urdf}) does not have; expected names among {list(model_names)} "
                        "(or set ros.ignore_joints)")
            cols_cache[names] = (np.array(src, dtype=int), np.array(dst, dtype=int))
        src, dst = cols_cache[names]
        pos = np.asarray(m.position, dtype=float)
        if len(pos) != len(names):
            raise BagError(f"topic {joints.name} message {k} has {len(pos)} positions for {len(names)} names; "
                           "expected one position per name")
        q_src[k, dst] = pos[src]
        vel = np.asarray(m.velocity, dtype=float)
        if len(vel) == len(names):
            v_src[k, dst] = vel[src]
        else:
            has_vel = False
    return q_src, v_src, has_vel


def check_carrying_joints(model: RobotModel, measured: np.ndarray, topic: str) -> None:
    """A BagError unless every joint between the base and a contact or the IMU is measured:
    ``measured`` (J,) bool, the URDF's joints (:attr:`RobotModel.joint_names` order) the joint
    topic names.  A joint elsewhere (a wrist) may stay at its reference; one that carries a contact
    or the IMU would put a foot or the IMU where it is not."""
    pmodel = model.model
    index = {name: i for i, name in enumerate(model.joint_names)}
    frames = [(f"contact '{c.name}' (frame {c.frame})", c.frame) for c in model.config.contacts]
    frames.append((f"the IMU (frame {model.config.imu_frame})", model.config.imu_frame))
    for what, frame in frames:
        j = pmodel.frames[pmodel.getFrameId(frame)].parentJoint
        chain = []
        while j > 0:
            chain.append(pmodel.names[j])
            j = pmodel.parents[j]
        missing = [name for name in reversed(chain) if name in index and not measured[index[name]]]
        if missing:
            raise BagError(f"topic {topic} never names joint{'s' if len(missing) > 1 else ''} "
                           f"{', '.join(repr(m) for m in missing)}, which move{'' if len(missing) > 1 else 's'} "
                           f"{what} of robot '{model.config.name}'; expected every joint between the base and "
                           "the contacts and the IMU (joints elsewhere, a wrist, may be left out)")


def check_joint_units(model: RobotModel, q: np.ndarray, topic: str) -> None:
    """A DataError when joint positions ``q`` (M, J) (NaN: not named) read more than a turn: a
    humanoid's revolute joints stay within +-pi, so readings beyond 2 pi rad are degrees."""
    with np.errstate(invalid="ignore"):
        big = np.nanmax(np.abs(q), axis=0, initial=0.0)
    j = int(np.argmax(big))
    if big[j] > 2.0 * np.pi:
        pmodel = model.model
        jid = pmodel.getJointId(model.joint_names[j])
        iq = pmodel.idx_qs[jid]
        lo, hi = float(pmodel.lowerPositionLimit[iq]), float(pmodel.upperPositionLimit[iq])
        raise DataError(f"topic {topic}: joint '{model.joint_names[j]}' reads {big[j]:.4g}, more than a turn "
                        f"(2 pi rad); its URDF range is [{lo:.3g}, {hi:.3g}] rad: the positions look like degrees; "
                        "expected radians")


def _joints_on_grid(joints: _Topic, model: RobotModel, ros: RosConfig, grid: np.ndarray, dt: float, t_first: int,
                    gaps: _GapCheck) -> _Joints:
    """The joint messages resampled on the grid and differentiated (module docstring, "Derivatives").

    Raises:
        BagError: as :func:`_joint_sources`; no joint of the robot named.
        DataError: a NaN or inf position (or message velocity), a gap longer than ``ros.max_gap``, a
            joint not measured over the whole grid, a log shorter than the Savitzky-Golay window.
    """
    model_names = model.joint_names
    q_src, v_src, has_vel = _joint_sources(joints, model, ros)
    measured = ~np.all(np.isnan(q_src), axis=0)
    for k, m in enumerate(joints.msgs):
        pos = np.asarray(m.position, dtype=float)
        if not np.all(np.isfinite(pos)):
            s = int(np.flatnonzero(~np.isfinite(pos))[0])
            raise DataError(f"topic {joints.name} message {k} (t = {(joints.t_ns[k] - t_first) * 1e-9:.3f} s) has "
                            f"NaN or inf position for joint '{m.name[s]}'; expected finite values")
    from_messages = has_vel and ros.joint_velocity == "message"
    if from_messages:
        _require_finite(joints, v_src[:, measured], "velocity", t_first,
                        [n for n, ok in zip(model_names, measured) if ok])
    if not measured.any():
        raise BagError(f"topic {joints.name} names none of the joints of robot '{model.config.name}'")
    check_carrying_joints(model, measured, joints.name)
    check_joint_units(model, q_src, joints.name)
    gaps(joints, fatal=True)
    n = len(grid)
    q_grid = np.tile(model.q_reference[7:], (n, 1))
    v_grid = np.zeros((n, len(model_names)))
    for j in np.flatnonzero(measured):  # per joint: messages may name different subsets
        ok = np.isfinite(q_src[:, j])
        q_grid[:, j] = _interp(joints.t_ns[ok], q_src[ok, j], grid)
        if from_messages:
            v_grid[:, j] = _interp(joints.t_ns[ok], v_src[ok, j], grid)
    if np.isnan(q_grid).any():
        bad = int(np.flatnonzero(np.isnan(q_grid).any(axis=0))[0])
        raise DataError(f"joint '{model_names[bad]}' is not measured over the whole grid on topic {joints.name}; "
                        "expected every joint in every message span")
    if from_messages:
        a_grid = _savgol(v_grid, dt, 1, ros)
    else:
        v_grid = _savgol(q_grid, dt, 1, ros)
        a_grid = _savgol(q_grid, dt, 2, ros)
    v_grid[:, ~measured] = 0.0
    a_grid[:, ~measured] = 0.0
    return _Joints(q_grid, v_grid, a_grid, measured, "message" if from_messages else "savgol")


def _ft_on_grid(topics: dict[str, _Topic], model: RobotModel, ros: RosConfig, grid: np.ndarray,
                q_grid: np.ndarray, gaps: _GapCheck) -> np.ndarray | None:
    """(N, C, 6) F/T wrenches on the grid in each contact's frame (NaN without a topic and inside
    long gaps); None when the bag has no F/T topic of the ``[ros]`` table.

    Raises:
        BagError: a wrench in a frame not in the URDF, or changing frame.
    """
    config, pmodel = model.config, model.model
    names_c = config.contact_names
    if not (ros.ft_topics and any(t in topics for t in ros.ft_topics.values())):
        return None
    ft = np.full((len(grid), len(names_c), 6), np.nan)
    for i, cname in enumerate(names_c):
        topic = topics.get(ros.ft_topics.get(cname, ""))
        if topic is None:
            continue
        w = np.array([(m.wrench.force.x, m.wrench.force.y, m.wrench.force.z,
                       m.wrench.torque.x, m.wrench.torque.y, m.wrench.torque.z) for m in topic.msgs])
        long = gaps(topic, fatal=False)
        ft[:, i] = _interp(topic.t_ns, w, grid)
        ft[long, i] = np.nan
        frames = {m.header.frame_id for m in topic.msgs} - {""}
        contact_frame = config.contacts[i].frame
        for frame in frames - {contact_frame}:
            if not pmodel.existFrame(frame):
                raise BagError(f"topic {topic.name} is in frame '{frame}', which is not in the URDF of robot "
                               f"'{config.name}'; expected the contact frame '{contact_frame}'")
        if frames - {contact_frame}:
            if len(frames) > 1:
                raise BagError(f"topic {topic.name} changes frame ({sorted(frames)}); expected one frame")
            ft[:, i] = wrench_in_contact_frame(model, q_grid, frames.pop(), contact_frame, ft[:, i], topic.name)
    return ft


def wrench_in_contact_frame(model, q, frame: str, contact_frame: str, w: np.ndarray, topic: str) -> np.ndarray:
    """(N, 6) F/T wrenches ``w`` of ``topic``, in ``frame``, moved to ``contact_frame`` at the joint
    positions ``q``.

    Raises:
        BagError: a normal force that the move loses (a force-only sensor: the components it needs
            are not measured), naming the frames and what is missing.
    """
    moved = _wrench_to_contact_frame(model, q, frame, contact_frame, w)
    if (np.isfinite(w[:, 2]) & ~np.isfinite(moved[:, 2])).any():
        absent = [lab for lab, ok in zip(("F_x", "F_y", "F_z", "T_x", "T_y", "T_z"), np.isfinite(w).any(axis=0))
                  if not ok]
        raise BagError(f"topic {topic} is in frame '{frame}', not the contact frame '{contact_frame}', and its "
                       f"wrench cannot be moved there: {', '.join(absent)} are not measured (NaN); expected the "
                       f"wrench in '{contact_frame}' or all six components")
    return moved


def _contact_states(model: RobotModel, ros: RosConfig, contacts: str, ft: np.ndarray | None,
                    n: int) -> tuple[np.ndarray, dict]:
    """``(active, method)``: the (N, C) contacts in force (a Schmitt trigger on the F/T normal
    force, or the fixed set) and the method's meta entry.

    Raises:
        ConfigError: an off threshold not below the on threshold.
    """
    config = model.config
    names_c = config.contact_names
    if contacts != "ft":
        active = fixed_contacts(n, names_c, ros.fixed_contacts)
        return active, {"method": "fixed", "contacts": [nm for i, nm in enumerate(names_c) if active[0, i]]}
    mg = model.mass * config.gravity
    on = ros.contact_on if ros.contact_on is not None else ros.contact_on_weight * mg
    off = ros.contact_off if ros.contact_off is not None else ros.contact_off_weight * mg
    assert ft is not None  # the F/T topics are required with contacts='ft'
    if not off < on:
        raise ConfigError(f"contact thresholds: off = {off:.1f} N is not below on = {on:.1f} N "
                          f"(m g = {mg:.1f} N); set ros.contact_on / ros.contact_off (N) or the "
                          "fractions ros.contact_on_weight / ros.contact_off_weight consistently")
    active = np.stack([schmitt_trigger(ft[:, i, 2], on, off) for i in range(len(names_c))], axis=1)
    return active, {"method": "schmitt", "on_N": on, "off_N": off}


def _anchor(ros: RosConfig, config: RobotConfig) -> int | None:
    """The index of the contact ``ros.anchor`` names (None: not named).

    Raises:
        ConfigError: not a contact of the robot.
    """
    if ros.anchor is None:
        return None
    if ros.anchor not in config.contact_names:
        raise ConfigError(f"ros.anchor = '{ros.anchor}' is not a contact of robot '{config.name}' "
                          f"({list(config.contact_names)})")
    return config.contact_names.index(ros.anchor)


AIRBORNE_MAX_S = 0.3
"""Longest span, s, with no configured contact in force that an import accepts: a humanoid walks
from foot to foot (a run's flight phase lasts a tenth of a second); longer, a contact that carries
the robot is missing from the configuration or its F/T threshold is too high."""


def airborne_error(names_c: tuple[str, ...], where: str, t_first: float, t_last: float, samples: int) -> DataError:
    """The error for ``samples`` steps from ``t_first`` to ``t_last`` (s) with no contact in force."""
    return DataError(f"no configured contact ({', '.join(names_c)}) is in force {where} from t = {t_first:.3f} s to "
                     f"{t_last:.3f} s ({samples} samples): the model needs a contact carrying the robot (flights up "
                     f"to {AIRBORNE_MAX_S:g} s); is a contact that carries it missing from the robot configuration, "
                     "or its F/T threshold too high?")


def check_airborne(active: np.ndarray, dt: float, names_c: tuple[str, ...], where: str) -> None:
    """A DataError (:func:`airborne_error`) for the first span of ``active`` (N, C) with no contact
    in force longer than :data:`AIRBORNE_MAX_S` (``dt`` s per step)."""
    free: np.ndarray = np.logical_not(np.asarray(active, dtype=bool).any(axis=1))
    k, n = 0, len(free)
    while k < n:
        if not free[k]:
            k += 1
            continue
        j = k
        while j < n and free[j]:
            j += 1
        if (j - k) * dt > AIRBORNE_MAX_S:
            raise airborne_error(names_c, where, k * dt, (j - 1) * dt, j - k)
        k = j


def _check_in_force(path: Path, ros: RosConfig, contacts: str, names_c: tuple[str, ...], active: np.ndarray,
                    method: dict, ft: np.ndarray | None, dt: float) -> None:
    """Some contact is in force somewhere, under ``contacts="ft"`` every one, and no span without a
    contact longer than :data:`AIRBORNE_MAX_S` (:func:`check_airborne`).

    Raises:
        DataError: no contact ever in force; under ``contacts="ft"`` a contact never in force
            (naming the largest normal force of its F/T topic).
    """
    c = len(names_c)
    never = [names_c[i] for i in range(c) if not active[:, i].any()]
    if len(never) == c:
        seen = ""
        if ft is not None and np.isfinite(ft[:, :, 2]).any():
            lo, hi = float(np.nanmin(ft[:, :, 2])), float(np.nanmax(ft[:, :, 2]))
            weight = method.get("on_N") if isinstance(method, dict) else None
            hint = ("; mostly negative: a flipped sign or frame?" if hi < abs(lo) and lo < 0 else
                    "; far below the weight: another unit (kN)?" if weight and 0 < hi < 0.1 * weight else "")
            seen = f"; the F/T normal forces read {lo:.4g} to {hi:.4g} N{hint}"
        how = (f"F/T Schmitt trigger: in force above {method['on_N']:.4g} N, out below {method['off_N']:.4g} N"
               if isinstance(method, dict) and "on_N" in method and "off_N" in method else str(method))
        raise DataError(f"no contact is ever in force in {path} ({how}){seen}; a foot must carry the robot "
                        "somewhere in the log: check the F/T topics and thresholds, or use contacts='fixed'")
    if contacts == "ft" and never:
        assert ft is not None  # the F/T topics are required with contacts='ft'
        peak = {names_c[i]: float(np.nanmax(ft[:, i, 2])) if np.isfinite(ft[:, i, 2]).any() else float("nan")
                for i in range(c) if names_c[i] in never}
        raise DataError(f"contact(s) {never} never come into force (largest F/T normal force "
                        + ", ".join(f"{k}: {v:.1f} N" for k, v in peak.items())
                        + f", on threshold {method['on_N']:.1f} N): check their F/T topics "
                        f"{[ros.ft_topics[k] for k in never]} and ros.contact_on, or use contacts='fixed' with "
                        "ros.fixed_contacts naming the feet that are down")
    check_airborne(active, dt, names_c, f"in {path}")


def _mocap_on_grid(topics: dict[str, _Topic], ros: RosConfig, grid: np.ndarray, gaps: _GapCheck) -> dict:
    """Frame -> (N, 7) motion-capture poses on the grid (:func:`_resample_poses`), for the topics
    with two messages at least."""
    mocap = {}
    for frame, topic_name in ros.mocap_topics.items():
        topic = topics.get(topic_name)
        if topic is None or len(topic.t_ns) < 2:
            continue
        gaps(topic, fatal=False)
        mocap[frame] = _resample_poses(topic, grid, ros.max_gap)
    return mocap


def _import_meta(source: dict, model: RobotModel, ros: RosConfig, grid: np.ndarray, period: int, imu_missing: int,
                 joint: _Joints, gaps: list[dict], active: np.ndarray, method: dict, lf, mocap: dict) -> dict:
    """``Recording.meta`` of an imported bag (module docstring)."""
    config = model.config
    names_c = config.contact_names
    dt = period * 1e-9
    time = (grid - grid[0]) * 1e-9
    return {
        "source": source,
        "grid": {"rate_hz": 1.0 / dt, "period_ns": period, "n": len(grid),
                 "method": "linear interpolation (IMU, joints, F/T); nlerp (mocap orientation)"},
        "imu_missing_messages": imu_missing,
        "joint_velocity": joint.velocity_source,
        "derivative_filter": {"method": "savgol", "window_s": ros.savgol_window, "order": ros.savgol_order},
        "imu_filter": ros.imu_filter,
        "joints_not_measured": [nm for nm, ok in zip(model.joint_names, joint.measured) if not ok],
        "gaps": _merge_gaps(gaps),
        "contacts": {**method, "phases": {p.name: [list(iv) for iv in p.intervals]
                                          for p in phases(time, active, names_c)}},
        "anchor": {"first": names_c[int(lf.anchor[0])],
                   "switches": [{"t": round(float(time[k]), 6), "from": names_c[a], "to": names_c[b], "jump_m": j}
                                for k, a, b, j in lf.switches],
                   "drift_m": lf.drift},
        "footholds": {"terrain": config.footholds.terrain,
                      "tilt_weight": config.footholds.tilt_weight, "height_weight": config.footholds.height_weight,
                      "touch_downs": [{"t": round(float(time[k]), 6), "contact": names_c[i], "tilt_rad": tilt,
                                       "height_m": height} for k, i, tilt, height in lf.footholds]},
        "base_frame": _root_link(model.model, mocap),
    }


def check_touch_downs(landed, footholds, contact_names, time_of) -> None:
    """Refuse a touch-down the ground prior contradicts: a landing sole further from the floor plane
    than :data:`FOOTHOLD_BOUND` leg-kinematics sigmas (``landed``: the local frame's ``footholds``
    rows; ``time_of(step)``: its time, s)."""
    if footholds.terrain == "none":
        return
    bound_tilt = FOOTHOLD_BOUND * footholds.kinematics_sigma_tilt
    bound_height = FOOTHOLD_BOUND * footholds.kinematics_sigma_height
    for k, i, tilt, height in landed:
        if tilt > bound_tilt or abs(height) > bound_height:
            raise DataError(
                f"at t = {time_of(k):.3f} s contact '{contact_names[i]}' lands "
                f"{np.degrees(tilt):.2f} deg off the floor "
                f"plane and {1000 * height:.1f} mm above it by the leg kinematics; the ground prior "
                f"(footholds.terrain = '{footholds.terrain}') allows {FOOTHOLD_BOUND:g} sigma of the kinematics, "
                f"{np.degrees(bound_tilt):.2f} deg and {1000 * bound_height:.1f} mm: the floor is not that plane "
                "(set footholds.terrain = 'plane' or 'none') or the kinematics is wrong (joint offsets, "
                "footholds.kinematics_sigma_tilt/height)")


def local_inputs(model, lf, progress=None) -> dict[str, Any]:
    """The paper's inputs and the IMU placement per step (the Recording fields ``com`` ... ``imu_w``)
    from the local frame ``lf`` (:meth:`RobotModel.local_kinematics`, by blocks of ``INPUT_BLOCK``
    steps when ``progress`` is given)."""
    n = len(lf.q)
    block = INPUT_BLOCK if progress is not None else max(n, 1)
    parts = []
    for k in range(0, max(n, 1), block):
        parts.append(model.local_kinematics(lf.q[k:k + block], lf.v[k:k + block], lf.a[k:k + block]))
        if progress is not None:
            progress(min(k + block, n) / max(n, 1))
    if len(parts) == 1:
        return parts[0]
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def _merge_gaps(gaps: list[dict]) -> list[dict]:
    """One entry per interval, listing every topic that has it (topics often share stamps)."""
    merged: dict[tuple, dict] = {}
    for g in gaps:
        entry = merged.setdefault((g["start"], g["end"]), {"start": g["start"], "end": g["end"],
                                                           "duration": g["duration"], "topics": []})
        entry["topics"].append(g["topic"])
    return sorted(merged.values(), key=lambda g: g["start"])


def _root_link(pmodel, prefer=()) -> str:
    """Name of the URDF link carried by the free-flyer (the frame of ``Recording.base_pose``).

    Several links can sit exactly at the free-flyer's frame (iCub's ``base_link`` and
    ``root_link``); the one tracked by motion capture (in ``prefer``) is named if there is one.
    """
    names = [f.name for f in pmodel.frames
             if f.parentJoint == 1 and f.type == pin.FrameType.BODY and f.placement.isIdentity()]
    for name in names:
        if name in prefer:
            return name
    return names[0] if names else ""


def _wrench_to_contact_frame(model, q_joints, sensor_frame, contact_frame, wrench):
    """Express (N, 6) wrenches given in ``sensor_frame`` (about its origin) in ``contact_frame``."""
    pmodel, data = model.model, model.model.createData()
    fs, fc = pmodel.getFrameId(sensor_frame), pmodel.getFrameId(contact_frame)
    q = pin.neutral(pmodel)
    out = np.empty_like(wrench)
    for k in range(len(wrench)):
        q[7:] = q_joints[k]
        pin.framesForwardKinematics(pmodel, data, q)
        c_T_s = data.oMf[fc].inverse() * data.oMf[fs]
        out[k] = c_T_s.act(pin.Force(wrench[k, :3], wrench[k, 3:])).vector
    return out


def _resample_poses(topic: _Topic, grid: np.ndarray, max_gap: float) -> np.ndarray:
    """(N, 7) poses: positions linearly, quaternions by sign-aligned nlerp; NaN where lost.

    A grid point is lost when it lies outside the valid messages' span, between two valid
    messages more than ``max_gap`` s apart, or across a message that was NaN (tracking lost).
    """
    src = np.array([(m.pose.position.x, m.pose.position.y, m.pose.position.z, m.pose.orientation.x,
                     m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w) for m in topic.msgs])
    ok = np.all(np.isfinite(src), axis=1) & (np.linalg.norm(src[:, 3:], axis=1) > 0.5)
    out = np.full((len(grid), 7), np.nan)
    if ok.sum() < 2:
        return out
    valid = np.flatnonzero(ok)
    t, s = topic.t_ns[ok], src[ok].copy()
    for k in range(1, len(s)):  # q and -q are the same rotation: keep the sign continuous
        if np.dot(s[k, 3:], s[k - 1, 3:]) < 0:
            s[k, 3:] *= -1.0
    out = _interp(t, s, grid)
    out[:, 3:] /= np.linalg.norm(out[:, 3:], axis=1, keepdims=True)
    j = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, len(t) - 2)
    inside = (grid > t[j]) & (grid < t[j + 1])
    lost = inside & (((t[j + 1] - t[j]) * 1e-9 > max_gap) | (valid[j + 1] - valid[j] > 1))
    out[lost] = np.nan
    return out
