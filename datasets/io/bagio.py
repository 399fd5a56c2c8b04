r"""Save and load a ``Recording`` (:mod:`flexforce.datasets.recording`) as a ROS 2 bag (MCAP storage).

Bags are written with :class:`rosbags.rosbag2.Writer` (rosbag2 metadata version 8, MCAP
storage, CDR messages serialised with the ROS 2 Humble typestore; the MCAP file embeds the
message definitions) and read back with :class:`rosbags.highlevel.AnyReader`.

Every message of sample ``k`` carries the sample's time ``t_ns[k]``: as the bag's log time and,
for messages with a header, as ``header.stamp`` (``sec``, ``nanosec``).  Messages without a
header (``std_msgs``) take their time from the log time.  Standard ROS messages are used wherever
one exists, so that the bag can be inspected with the usual ROS tools (rviz, PlotJuggler, Foxglove).

Topics
------

===========================  ====================================  =============================================================  ======================  =============
topic                        message type                          content                                                        units                   frame_id
===========================  ====================================  =============================================================  ======================  =============
``/flexforce/meta``          ``std_msgs/msg/String``               JSON description (below); one message at ``t_ns[0]``           --                      --
``/flexforce/inputs``        ``std_msgs/msg/Float64MultiArray``    local-frame inputs, IMU placement, contacts (layout below)     SI (see Recording)      (no header)
``/imu``                     ``sensor_msgs/msg/Imu``               ``angular_velocity`` = gyro, ``linear_acceleration`` = accel;  rad/s, m/s^2            ``imu``
                                                                   no orientation: ``orientation_covariance[0] = -1``
                                                                   (orientation left at identity); other covariances 0 (unknown)
``/joint_states``            ``sensor_msgs/msg/JointState``        ``name`` = joint_names, ``position`` = joint_q,                rad or m, rad/s or m/s  ``""``
                                                                   ``velocity`` = joint_v (empty when absent), ``effort`` empty
``/ft/<contact>``            ``geometry_msgs/msg/WrenchStamped``   F/T reading: wrench of the environment on the robot about      N, N m                  ``<contact>``
                                                                   the contact origin; NaN where a component is not measured
``/mocap/<link>``            ``geometry_msgs/msg/PoseStamped``     world pose of the link (x, y, z, qx, qy, qz, qw);              m                       ``world``
                                                                   NaN when lost
``/truth/flexibility``       ``geometry_msgs/msg/PoseStamped``     pose of the local frame in the world: position = t,            m                       ``world``
                                                                   orientation = R as a unit quaternion (x, y, z, w)
``/truth/velocity``          ``geometry_msgs/msg/TwistStamped``    angular = w, linear = v                                        rad/s, m/s              ``world``
``/truth/acceleration``      ``geometry_msgs/msg/AccelStamped``    angular = dw, linear = a                                       rad/s^2, m/s^2          ``world``
``/truth/wrench/<contact>``  ``geometry_msgs/msg/WrenchStamped``   contact wrench F, T about the world origin (0 if inactive)     N, N m                  ``world``
``/truth/external_wrench``   ``geometry_msgs/msg/WrenchStamped``   hidden external wrench F, T about the world origin             N, N m                  ``world``
``/truth/ambient_wrench``    ``geometry_msgs/msg/WrenchStamped``   ambient disturbance F, T about the world origin (if any)       N, N m                  ``world``
``/truth/cop``               ``geometry_msgs/msg/PointStamped``    centre of pressure of the total contact wrench                 m                       ``world``
``/truth/link/<name>``       ``geometry_msgs/msg/PointStamped``    world position of a chosen link (the hands)                    m                       ``world``
``/truth/gyro_bias``         ``geometry_msgs/msg/Vector3Stamped``  gyrometer bias                                                 rad/s                   ``imu``
``/truth/accel_bias``        ``geometry_msgs/msg/Vector3Stamped``  accelerometer bias                                             m/s^2                   ``imu``
===========================  ====================================  =============================================================  ======================  =============

``/flexforce/meta``, ``/flexforce/inputs`` and ``/imu`` are always present; ``/joint_states``
when ``joint_q`` or ``joint_v`` is; ``/ft/*`` when ``ft`` is (one topic per contact);
``/mocap/*`` per motion-capture link; ``/flexforce/base_pose`` (PoseStamped, frame ``local``: the
base link's pose in the local frame) when ``base_pose`` is; ``/truth/*`` for simulated recordings (the bias topics
only when the truth has biases).  Contact and link names become topic name tokens, so they
must match ``[A-Za-z][A-Za-z0-9_]*``.

``/flexforce/inputs`` layout
----------------------------
One ``Float64MultiArray`` per sample, ``data_offset = 0``.  The array is a flat record, not a
nested array: each entry of ``layout.dim`` names one consecutive block of ``data``
(``label``, ``size`` = number of values, ``stride`` = ``size``), in this order:

======================  ====  =====================================================  ========
label                   size  content                                                units
======================  ====  =====================================================  ========
``com``                 3     CoM c_l in the local frame                             m
``com_vel``             3     dc_l/dt                                                m/s
``com_acc``             3     d2c_l/dt2                                              m/s^2
``inertia``             9     I_l about the local origin, row-major                  kg m^2
``inertia_dot``         9     dI_l/dt, row-major                                     kg m^2/s
``sigma``               3     angular momentum sigma_l about the local origin        kg m^2/s
``sigma_dot``           3     d sigma_l/dt                                           N m
``imu_R``               9     IMU orientation in the local frame, row-major          --
``imu_p``               3     IMU position in the local frame                        m
``imu_v``               3     IMU velocity in the local frame                        m/s
``imu_a``               3     IMU acceleration in the local frame                    m/s^2
``imu_w``               3     IMU angular velocity w.r.t. the local frame, in it     rad/s
``contact/<c>/active``  1     1.0 while contact <c> is in force, else 0.0            --
``contact/<c>/p``       3     rest position of <c> in the local frame                m
``contact/<c>/R``       9     rest orientation of <c> in the local frame, row-major  --
======================  ====  =====================================================  ========

The three ``contact/<c>/...`` blocks repeat for each contact ``<c>`` in ``contact_names`` order,
so a sample holds 54 + 13 C values.  The reader rebuilds the expected labels from
``/flexforce/meta`` and refuses a bag whose layout differs.

``/flexforce/meta`` JSON
------------------------
``{"format": "flexforce-recording", "version": 1, "robot": str, "contact_names": [...],
"joint_names": [...], "mass": float, "gravity": float, "truth_links": [...],
"mocap_links": [...], "meta": {...}, "present": {"joint_q": bool, "joint_v": bool, "ft": bool, "base_pose": bool,
"truth": bool, "gyro_bias": bool, "accel_bias": bool}}``.
Floats are written with Python's shortest round-trip representation, so they load exactly.

Precision: every float64 is stored as float64 and loads bit for bit, except the truth rotation
R, which goes through a unit quaternion and comes back to about 1e-15.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from flexforce.datasets.recording import Recording, Truth
from flexforce.datasets.safeio import is_bag_folder, safe_output
from flexforce.errors import BagError

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "inputs_layout", "load_recording", "save_recording"]

FORMAT_NAME = "flexforce-recording"
"""Value of ``"format"`` in ``/flexforce/meta``."""
FORMAT_VERSION = 1
"""Value of ``"version"`` in ``/flexforce/meta``; the reader refuses other versions."""

META_TOPIC = "/flexforce/meta"
INPUTS_TOPIC = "/flexforce/inputs"
IMU_TOPIC = "/imu"
JOINTS_TOPIC = "/joint_states"
BASE_TOPIC = "/flexforce/base_pose"

T_IMU = "sensor_msgs/msg/Imu"
T_JOINTS = "sensor_msgs/msg/JointState"
T_WRENCH = "geometry_msgs/msg/WrenchStamped"
T_POSE = "geometry_msgs/msg/PoseStamped"
T_TWIST = "geometry_msgs/msg/TwistStamped"
T_ACCEL = "geometry_msgs/msg/AccelStamped"
T_POINT = "geometry_msgs/msg/PointStamped"
T_VECTOR = "geometry_msgs/msg/Vector3Stamped"
T_ARRAY = "std_msgs/msg/Float64MultiArray"
T_STRING = "std_msgs/msg/String"

_INPUT_BLOCKS = (
    ("com", 3), ("com_vel", 3), ("com_acc", 3), ("inertia", 9), ("inertia_dot", 9),
    ("sigma", 3), ("sigma_dot", 3), ("imu_R", 9), ("imu_p", 3), ("imu_v", 3), ("imu_a", 3),
    ("imu_w", 3),
)
_CONTACT_BLOCKS = (("active", 1), ("p", 3), ("R", 9))
_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_NS = 1_000_000_000


def inputs_layout(contact_names) -> list[tuple[str, int]]:
    """The ``(label, size)`` blocks of ``/flexforce/inputs`` for these contacts, in order."""
    blocks = list(_INPUT_BLOCKS)
    for name in contact_names:
        blocks += [(f"contact/{name}/{part}", size) for part, size in _CONTACT_BLOCKS]
    return blocks


# ------------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------------
def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _check_names(kind: str, names) -> None:
    seen = set()
    for name in names:
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise BagError(f"{kind} name {name!r} cannot be used in a ROS topic name; "
                           "expected letters, digits and '_' starting with a letter")
        if name in seen:
            raise BagError(f"{kind} name {name!r} appears twice; expected unique names")
        seen.add(name)


def check_replaceable_bag(path: Path) -> None:
    """An existing ``path`` may be replaced only if it is a bag (a bag directory or a single bag file)."""
    if path.is_dir():
        if not is_bag_folder(path):
            raise BagError(f"cannot overwrite {path}: it is a directory that is not a ROS 2 bag "
                           "(expected metadata.yaml and .mcap/.db3 files only); remove it yourself")
    elif path.suffix not in {".mcap", ".db3", ".bag"}:
        raise BagError(f"cannot overwrite {path}: it is a file that is not a bag "
                       "(expected a .mcap, .db3 or .bag file); remove it yourself")


def _meta_json(rec: Recording) -> str:
    truth = rec.truth
    doc = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "robot": rec.robot,
        "contact_names": list(rec.contact_names),
        "joint_names": list(rec.joint_names),
        "mass": float(rec.mass),
        "gravity": float(rec.gravity),
        "truth_links": list(truth.links) if truth is not None else [],
        "mocap_links": list(rec.mocap),
        "meta": rec.meta,
        "present": {
            "joint_q": rec.joint_q is not None,
            "joint_v": rec.joint_v is not None,
            "ft": rec.ft is not None,
            "base_pose": rec.base_pose is not None,
            "truth": truth is not None,
            "gyro_bias": truth is not None and truth.gyro_bias is not None,
            "accel_bias": truth is not None and truth.accel_bias is not None,
            "ambient_wrench": truth is not None and truth.ambient_wrench is not None,
        },
    }
    try:
        return json.dumps(doc)
    except (TypeError, ValueError) as err:
        raise BagError(f"recording meta cannot be written to the bag: {err}; expected a "
                       "JSON-serialisable dict (str keys; str, numbers, lists, dicts)") from err


def save_recording(rec: Recording, path, *, overwrite: bool = False) -> Path:
    """Write ``rec`` as a ROS 2 bag directory (MCAP storage) at ``path``; return the path.

    The layout is described in the module docstring.  The recording is validated first
    (:meth:`Recording.validate`).  An existing ``path`` is refused with :class:`BagError`
    unless ``overwrite=True``; even then only an existing bag is replaced.  The bag is written
    aside and moved into place when complete (:func:`flexforce.datasets.safeio.safe_output`).
    """
    from rosbags.rosbag2 import StoragePlugin, Writer, WriterError

    path = Path(path)
    rec.validate()
    n = rec.n
    if rec.t_ns[0] < 0:
        raise BagError(f"first time stamp is {int(rec.t_ns[0])} ns; expected t_ns >= 0 for a bag")
    _check_names("contact", rec.contact_names)
    _check_names("mocap link", rec.mocap)
    for name, pose in rec.mocap.items():
        if np.shape(pose) != (n, 7):
            raise BagError(f"mocap '{name}' has shape {np.shape(pose)}; expected {(n, 7)}")
    if rec.joint_v is not None and rec.joint_v.shape != (n, len(rec.joint_names)):
        raise BagError(f"field 'joint_v' has shape {rec.joint_v.shape}; "
                       f"expected {(n, len(rec.joint_names))}")
    truth = rec.truth
    if truth is not None:
        _check_names("truth link", truth.links)
        _check_truth_shapes(truth, n, len(rec.contact_names))
    meta = _meta_json(rec)

    if path.exists() or path.is_symlink():
        if not overwrite:
            raise BagError(f"{path} exists already; expected a new path (or overwrite=True)")
        check_replaceable_bag(path)

    ts = _typestore()
    # Written aside and swapped in when complete (safeio): an interrupted save leaves the previous
    # bag or none, and a second writer of the same path is refused.
    with safe_output(path, folder=True) as tmp:
        try:
            with Writer(tmp, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
                _write(writer, ts, rec, meta)
        except (WriterError, OSError) as err:
            raise BagError(f"cannot write bag {path}: {err}") from err
    return path


def _check_truth_shapes(truth: Truth, n: int, c: int) -> None:
    shapes = {"R": (n, 3, 3), "t": (n, 3), "w": (n, 3), "v": (n, 3), "dw": (n, 3), "a": (n, 3),
              "wrench": (n, c, 6), "external_wrench": (n, 6), "cop": (n, 3)}
    for name, shape in shapes.items():
        if np.shape(getattr(truth, name)) != shape:
            raise BagError(f"truth field '{name}' has shape {np.shape(getattr(truth, name))}; "
                           f"expected {shape}")
    for name in ("gyro_bias", "accel_bias"):
        value = getattr(truth, name)
        if value is not None and np.shape(value) != (n, 3):
            raise BagError(f"truth field '{name}' has shape {np.shape(value)}; expected {(n, 3)}")
    for name, pos in truth.links.items():
        if np.shape(pos) != (n, 3):
            raise BagError(f"truth link '{name}' has shape {np.shape(pos)}; expected {(n, 3)}")


def _write(writer, ts, rec: Recording, meta: str) -> None:
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Vector3, Point = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Point"]
    Quaternion, Pose = T["geometry_msgs/msg/Quaternion"], T["geometry_msgs/msg/Pose"]
    Wrench, Twist, Accel = (T["geometry_msgs/msg/Wrench"], T["geometry_msgs/msg/Twist"],
                            T["geometry_msgs/msg/Accel"])
    Dim, Layout = T["std_msgs/msg/MultiArrayDimension"], T["std_msgs/msg/MultiArrayLayout"]

    def vec(v):
        return Vector3(x=v[0], y=v[1], z=v[2])

    def pose(p):  # p: (x, y, z, qx, qy, qz, qw)
        return Pose(position=Point(x=p[0], y=p[1], z=p[2]),
                    orientation=Quaternion(x=p[3], y=p[4], z=p[5], w=p[6]))

    def wrench(f):
        return Wrench(force=vec(f[0:3]), torque=vec(f[3:6]))

    channels: list[tuple] = []  # (connection, msgtype, make(k, header) -> msg, frame)

    def add(topic, msgtype, frame, make):
        conn = writer.add_connection(topic, msgtype, typestore=ts)
        channels.append((conn, msgtype, frame, make))

    # ---- per-sample rows as python floats (exact) ----
    n, c = rec.n, len(rec.contact_names)
    parts = [getattr(rec, name).reshape(n, -1) for name, _ in _INPUT_BLOCKS]
    for i in range(c):
        parts += [rec.contact_active[:, i:i + 1].astype(np.float64), rec.contact_p[:, i, :],
                  rec.contact_R[:, i].reshape(n, 9)]
    inputs = np.ascontiguousarray(np.concatenate(parts, axis=1), dtype=np.float64)
    layout = Layout(dim=[Dim(label=label, size=size, stride=size)
                         for label, size in inputs_layout(rec.contact_names)], data_offset=0)

    meta_conn = writer.add_connection(META_TOPIC, T_STRING, typestore=ts)
    add(INPUTS_TOPIC, T_ARRAY, None, lambda k, h: T[T_ARRAY](layout=layout, data=inputs[k]))

    gyro, accel = rec.gyro.tolist(), rec.accel.tolist()
    no_cov = np.zeros(9)
    no_orientation = np.zeros(9)
    no_orientation[0] = -1.0
    identity_q = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    add(IMU_TOPIC, T_IMU, "imu", lambda k, h: T[T_IMU](
        header=h, orientation=identity_q, orientation_covariance=no_orientation,
        angular_velocity=vec(gyro[k]), angular_velocity_covariance=no_cov,
        linear_acceleration=vec(accel[k]), linear_acceleration_covariance=no_cov))

    if rec.joint_q is not None or rec.joint_v is not None:
        names = list(rec.joint_names)
        empty = np.zeros(0)
        q = np.ascontiguousarray(rec.joint_q, dtype=np.float64) if rec.joint_q is not None else None
        qd = np.ascontiguousarray(rec.joint_v, dtype=np.float64) if rec.joint_v is not None else None
        add(JOINTS_TOPIC, T_JOINTS, "", lambda k, h: T[T_JOINTS](
            header=h, name=names, position=q[k] if q is not None else empty,
            velocity=qd[k] if qd is not None else empty, effort=empty))

    if rec.ft is not None:
        for i, name in enumerate(rec.contact_names):
            rows = rec.ft[:, i, :].tolist()
            add(f"/ft/{name}", T_WRENCH, name,
                lambda k, h, rows=rows: T[T_WRENCH](header=h, wrench=wrench(rows[k])))

    if rec.base_pose is not None:
        rows_base = np.asarray(rec.base_pose, dtype=np.float64).tolist()
        add(BASE_TOPIC, T_POSE, "local", lambda k, h: T[T_POSE](header=h, pose=pose(rows_base[k])))

    for name, poses in rec.mocap.items():
        rows = np.asarray(poses, dtype=np.float64).tolist()
        add(f"/mocap/{name}", T_POSE, "world",
            lambda k, h, rows=rows: T[T_POSE](header=h, pose=pose(rows[k])))

    truth = rec.truth
    if truth is not None:
        quat = Rotation.from_matrix(np.asarray(truth.R, dtype=np.float64)).as_quat()  # x, y, z, w
        flex = np.concatenate([truth.t, quat], axis=1).tolist()
        add("/truth/flexibility", T_POSE, "world",
            lambda k, h: T[T_POSE](header=h, pose=pose(flex[k])))
        twist = np.concatenate([truth.w, truth.v], axis=1).tolist()
        add("/truth/velocity", T_TWIST, "world", lambda k, h: T[T_TWIST](
            header=h, twist=Twist(angular=vec(twist[k][0:3]), linear=vec(twist[k][3:6]))))
        acc = np.concatenate([truth.dw, truth.a], axis=1).tolist()
        add("/truth/acceleration", T_ACCEL, "world", lambda k, h: T[T_ACCEL](
            header=h, accel=Accel(angular=vec(acc[k][0:3]), linear=vec(acc[k][3:6]))))
        for i, name in enumerate(rec.contact_names):
            rows = np.asarray(truth.wrench)[:, i, :].tolist()
            add(f"/truth/wrench/{name}", T_WRENCH, "world",
                lambda k, h, rows=rows: T[T_WRENCH](header=h, wrench=wrench(rows[k])))
        ext = np.asarray(truth.external_wrench).tolist()
        add("/truth/external_wrench", T_WRENCH, "world",
            lambda k, h: T[T_WRENCH](header=h, wrench=wrench(ext[k])))
        if truth.ambient_wrench is not None:
            amb = np.asarray(truth.ambient_wrench).tolist()
            add("/truth/ambient_wrench", T_WRENCH, "world",
                lambda k, h: T[T_WRENCH](header=h, wrench=wrench(amb[k])))
        points = [("/truth/cop", truth.cop)] + [(f"/truth/link/{name}", p) for name, p in truth.links.items()]
        for topic, values in points:
            rows = np.asarray(values, dtype=np.float64).tolist()
            add(topic, T_POINT, "world", lambda k, h, rows=rows: T[T_POINT](
                header=h, point=Point(x=rows[k][0], y=rows[k][1], z=rows[k][2])))
        for topic, bias in (("/truth/gyro_bias", truth.gyro_bias), ("/truth/accel_bias", truth.accel_bias)):
            if bias is not None:
                rows = np.asarray(bias, dtype=np.float64).tolist()
                add(topic, T_VECTOR, "imu",
                    lambda k, h, rows=rows: T[T_VECTOR](header=h, vector=vec(rows[k])))

    serialize = ts.serialize_cdr
    t_ns = [int(t) for t in rec.t_ns]
    writer.write(meta_conn, t_ns[0], serialize(T[T_STRING](data=meta), T_STRING))
    for k, t in enumerate(t_ns):
        sec, nanosec = divmod(t, _NS)
        stamp = Time(sec=sec, nanosec=nanosec)
        for conn, msgtype, frame, make in channels:
            header = None if frame is None else Header(stamp=stamp, frame_id=frame)
            writer.write(conn, t, serialize(make(k, header), msgtype))


# ------------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------------
_NOT_FLEXFORCE = ("the bag is not a flexforce recording (expected topics /flexforce/meta and "
                  "/flexforce/inputs as written by save_recording); raw robot logs are imported "
                  "with a robot config: flexforce ... --robot CONFIG)")


def _read_bag(path: Path) -> tuple[dict[str, str], dict[str, list]]:
    """All messages of the bag: (topic -> msgtype, topic -> [(log time ns, message), ...]).

    A topic without messages is left out of the second dict, as if absent.

    Every exception from the library (bad file, truncated storage, bad definitions, bad CDR) is
    turned into a :class:`BagError`.
    """
    from rosbags.highlevel import AnyReader

    types: dict[str, str] = {}
    msgs: dict[str, list] = {}
    try:
        # default_typestore: sqlite3 bags recorded by ROS 2 Humble carry no message definitions
        with AnyReader([path], default_typestore=_typestore()) as reader:
            for conn in reader.connections:
                if types.setdefault(conn.topic, conn.msgtype) != conn.msgtype:
                    raise BagError(f"topic {conn.topic} in bag {path} has two message types "
                                   f"({types[conn.topic]}, {conn.msgtype}); expected one")
            for conn, log_ns, raw in reader.messages():  # topics without messages stay absent
                msgs.setdefault(conn.topic, []).append((log_ns, reader.deserialize(raw, conn.msgtype)))
    except BagError:
        raise
    except Exception as err:  # noqa: BLE001 -- any library failure means an unreadable bag
        detail = " ".join(str(err).split()) or type(err).__name__
        raise BagError(f"cannot read bag {path}: corrupt, truncated or not a bag ({detail}); "
                       "expected a ROS 2 bag directory, .mcap/.db3 file or ROS 1 .bag file") from err
    return types, msgs


class _Topics:
    """Per-sample topic access with the checks shared by every topic."""

    def __init__(self, path: Path, types: dict, msgs: dict, t_ns: np.ndarray):
        self.path, self.types, self.msgs, self.t_ns = path, types, msgs, t_ns

    def get(self, topic: str, msgtype: str, why: str = "") -> list:
        if topic not in self.msgs and topic in self.types:
            raise BagError(f"topic {topic} ({self.types[topic]}) of bag {self.path} has no messages; expected one "
                           f"per sample{why}")
        if topic not in self.msgs:
            raise BagError(f"bag {self.path} lacks topic {topic}; expected it{why}")
        if self.types[topic] != msgtype:
            raise BagError(f"topic {topic} has type {self.types[topic]}; expected {msgtype}")
        items = self.msgs[topic]
        n = len(self.t_ns)
        if len(items) != n:
            raise BagError(f"sample count mismatch: topic {topic} has {len(items)} messages but "
                           f"{INPUTS_TOPIC} has {n}; expected one message per sample on every topic")
        msgs = [m for _, m in items]
        if hasattr(msgs[0], "header"):
            stamps = np.array([m.header.stamp.sec * _NS + m.header.stamp.nanosec for m in msgs],
                              dtype=np.int64)
            bad = np.flatnonzero(stamps != self.t_ns)
            if bad.size:
                k = int(bad[0])
                raise BagError(f"topic {topic}: header stamp of sample {k} is {int(stamps[k])} ns; "
                               f"expected {int(self.t_ns[k])} ns (the time of {INPUTS_TOPIC} sample {k})")
        return msgs


def _xyz(vs) -> np.ndarray:
    return np.array([(v.x, v.y, v.z) for v in vs], dtype=np.float64).reshape(-1, 3)


def _wrenches(ms) -> np.ndarray:
    return np.concatenate([_xyz([m.wrench.force for m in ms]), _xyz([m.wrench.torque for m in ms])], axis=1)


def _poses(ms) -> np.ndarray:
    return np.array([(m.pose.position.x, m.pose.position.y, m.pose.position.z,
                      m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
                      m.pose.orientation.w) for m in ms], dtype=np.float64).reshape(-1, 7)


def _parse_meta(path: Path, items: list) -> dict:
    if len(items) != 1:
        raise BagError(f"topic {META_TOPIC} has {len(items)} messages; expected exactly 1")
    try:
        doc = json.loads(items[0][1].data)
    except (TypeError, ValueError) as err:
        raise BagError(f"topic {META_TOPIC} does not hold valid JSON ({err}); "
                       "expected the JSON written by save_recording") from err
    if not isinstance(doc, dict) or doc.get("format") != FORMAT_NAME:
        raise BagError(f"topic {META_TOPIC} of bag {path} is not a flexforce description; "
                       f"expected a JSON object with \"format\": \"{FORMAT_NAME}\"")
    if doc.get("version") != FORMAT_VERSION:
        raise BagError(f"bag {path} has flexforce format version {doc.get('version')!r}; "
                       f"expected {FORMAT_VERSION}")
    keys = ("robot", "contact_names", "joint_names", "mass", "gravity", "truth_links",
            "mocap_links", "meta", "present")
    if missing := [k for k in keys if k not in doc]:
        raise BagError(f"topic {META_TOPIC} lacks the key(s) {', '.join(missing)}; "
                       f"expected {', '.join(keys)}")
    return doc


def load_recording(path) -> Recording:
    """Read a bag written by :func:`save_recording` back into a validated :class:`Recording`.

    Any problem (missing path, not a bag, corrupt or truncated storage, not a flexforce
    recording, missing topic, wrong layout, sample counts or stamps that disagree) raises
    :class:`BagError` with a one-line message naming it.
    """
    path = Path(path)
    if not path.exists():
        raise BagError(f"bag {path} does not exist; expected a ROS 2 bag directory, "
                       ".mcap/.db3 file or ROS 1 .bag file")
    types, msgs = _read_bag(path)
    _check_recording_topics(path, types, msgs)
    doc = _parse_meta(path, msgs[META_TOPIC])
    contact_names = tuple(doc["contact_names"])
    joint_names = tuple(doc["joint_names"])
    present = doc["present"]
    inputs = _read_inputs(msgs[INPUTS_TOPIC], contact_names)
    t_ns = inputs["t_ns"]
    n = len(t_ns)
    topics = _Topics(path, types, msgs, t_ns)

    imu = topics.get(IMU_TOPIC, T_IMU)
    gyro = _xyz([m.angular_velocity for m in imu])
    accel = _xyz([m.linear_acceleration for m in imu])
    joint_q, joint_v = _read_joints(topics, present, joint_names, n)
    ft = None
    if present["ft"]:
        ft = np.zeros((n, len(contact_names), 6))
        for i, name in enumerate(contact_names):
            ft[:, i] = _wrenches(topics.get(f"/ft/{name}", T_WRENCH, " (the meta says F/T is present)"))
    mocap = {name: _poses(topics.get(f"/mocap/{name}", T_POSE, " (listed in the meta's mocap_links)"))
             for name in doc["mocap_links"]}
    base_pose = (_poses(topics.get(BASE_TOPIC, T_POSE, " (the meta says the base pose is present)"))
                 if present.get("base_pose") else None)
    truth = _read_truth(topics, doc, contact_names, n) if present["truth"] else None
    rec = Recording(
        robot=doc["robot"], contact_names=contact_names, mass=float(doc["mass"]), **inputs,
        gyro=gyro, accel=accel, joint_names=joint_names, joint_q=joint_q, joint_v=joint_v,
        ft=ft, mocap=mocap, base_pose=base_pose, truth=truth, gravity=float(doc["gravity"]), meta=doc["meta"],
    )
    return rec.validate()


def _check_recording_topics(path: Path, types: dict[str, str], msgs: dict[str, list]) -> None:
    """The meta and inputs topics of a flexforce recording are there, with messages, of their types.

    Raises:
        BagError: one is empty or missing (not a flexforce recording), or of another type.
    """
    if empty := [t for t in (META_TOPIC, INPUTS_TOPIC) if t in types and t not in msgs]:
        raise BagError(f"topic {' and '.join(empty)} of bag {path} has no messages; expected a flexforce "
                       "recording written completely")
    if missing := [t for t in (META_TOPIC, INPUTS_TOPIC) if t not in msgs]:
        raise BagError(f"bag {path} lacks {' and '.join(missing)}: {_NOT_FLEXFORCE}")
    for topic, msgtype in ((META_TOPIC, T_STRING), (INPUTS_TOPIC, T_ARRAY)):
        if types[topic] != msgtype:
            raise BagError(f"topic {topic} has type {types[topic]}; expected {msgtype}")


def _read_inputs(items: list, contact_names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The time grid and the local-frame quantities of the inputs topic's ``(t_ns, message)``
    items, as Recording fields (``t_ns``, ``com`` ... ``imu_w``, ``contact_active``, ``contact_p``,
    ``contact_R``).

    Raises:
        BagError: a message whose layout is not :func:`inputs_layout` of ``contact_names``.
    """
    t_ns = np.array([t for t, _ in items], dtype=np.int64)
    n = len(t_ns)
    c = len(contact_names)
    blocks = inputs_layout(contact_names)
    expected = [(label, size, size) for label, size in blocks]
    width = sum(size for _, size in blocks)
    for k, (_, m) in enumerate(items):
        got = [(d.label, int(d.size), int(d.stride)) for d in m.layout.dim]
        if got != expected or m.layout.data_offset != 0 or len(m.data) != width:
            first = next((f"{g[0]}[{g[1]}]" for g, e in zip(got, expected) if g != e), None)
            where = f"block {first}" if first else f"{len(got)} blocks, {len(m.data)} values"
            raise BagError(f"topic {INPUTS_TOPIC} sample {k} has an unexpected layout ({where}); "
                           f"expected {len(expected)} blocks {expected[0][0]}..{expected[-1][0]} "
                           f"holding {width} values for contacts {list(contact_names)}")
    data = np.array([m.data for _, m in items], dtype=np.float64).reshape(n, width)
    fields, col = {}, 0
    for label, size in blocks:
        fields[label] = data[:, col:col + size]
        col += size
    out: dict[str, np.ndarray] = {"t_ns": t_ns}
    out.update({name: fields[name].copy() for name, size in _INPUT_BLOCKS if size == 3})
    out.update({name: fields[name].reshape(n, 3, 3).copy() for name, size in _INPUT_BLOCKS if size == 9})
    contact_active = np.zeros((n, c), dtype=bool)
    contact_p = np.zeros((n, c, 3))
    contact_R = np.zeros((n, c, 3, 3))
    for i, name in enumerate(contact_names):
        contact_active[:, i] = fields[f"contact/{name}/active"][:, 0] != 0.0
        contact_p[:, i] = fields[f"contact/{name}/p"]
        contact_R[:, i] = fields[f"contact/{name}/R"].reshape(n, 3, 3)
    out.update(contact_active=contact_active, contact_p=contact_p, contact_R=contact_R)
    return out


def _read_joints(topics: _Topics, present: dict, joint_names: tuple[str, ...],
                 n: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(joint_q, joint_v)``: the (N, J) joint positions and velocities the meta says are present
    (None: absent).

    Raises:
        BagError: the joint topic missing, naming other joints, or with arrays of the wrong length.
    """
    joint_q = joint_v = None
    if not (present["joint_q"] or present["joint_v"]):
        return joint_q, joint_v
    js = topics.get(JOINTS_TOPIC, T_JOINTS, " (the meta says joint data are present)")
    for k, m in enumerate(js):
        if tuple(m.name) != joint_names:
            raise BagError(f"topic {JOINTS_TOPIC} sample {k} names joints {list(m.name)}; "
                           f"expected {list(joint_names)} as in {META_TOPIC}")
    j = len(joint_names)
    try:
        if present["joint_q"]:
            joint_q = np.array([m.position for m in js], dtype=np.float64).reshape(n, j)
        if present["joint_v"]:
            joint_v = np.array([m.velocity for m in js], dtype=np.float64).reshape(n, j)
    except ValueError as err:
        raise BagError(f"topic {JOINTS_TOPIC} has position/velocity arrays of the wrong length; "
                       f"expected {j} values per sample ({err})") from err
    return joint_q, joint_v


def _read_truth(topics: _Topics, doc: dict, contact_names: tuple[str, ...], n: int) -> Truth:
    """The ground truth of a simulated recording (its ``/truth/...`` topics).

    Raises:
        BagError: a truth topic missing or malformed, a flexibility quaternion not of unit norm.
    """
    present = doc["present"]
    why = " (the meta says ground truth is present)"
    flex = _poses(topics.get("/truth/flexibility", T_POSE, why))
    vel = topics.get("/truth/velocity", T_TWIST, why)
    acc = topics.get("/truth/acceleration", T_ACCEL, why)
    wrench = np.zeros((n, len(contact_names), 6))
    for i, name in enumerate(contact_names):
        wrench[:, i] = _wrenches(topics.get(f"/truth/wrench/{name}", T_WRENCH, why))
    quat = flex[:, 3:7]
    norms = np.linalg.norm(quat, axis=1)
    if not np.all(np.abs(norms - 1.0) < 1e-6):
        k = int(np.flatnonzero(~(np.abs(norms - 1.0) < 1e-6))[0])
        raise BagError(f"topic /truth/flexibility sample {k} has a quaternion of norm {norms[k]:.6g}; "
                       "expected a unit quaternion")
    return Truth(
        R=Rotation.from_quat(quat).as_matrix(),
        t=flex[:, 0:3].copy(),
        w=_xyz([m.twist.angular for m in vel]), v=_xyz([m.twist.linear for m in vel]),
        dw=_xyz([m.accel.angular for m in acc]), a=_xyz([m.accel.linear for m in acc]),
        wrench=wrench,
        external_wrench=_wrenches(topics.get("/truth/external_wrench", T_WRENCH, why)),
        cop=_xyz([m.point for m in topics.get("/truth/cop", T_POINT, why)]),
        links={name: _xyz([m.point for m in topics.get(f"/truth/link/{name}", T_POINT, why)])
               for name in doc["truth_links"]},
        gyro_bias=(_xyz([m.vector for m in topics.get("/truth/gyro_bias", T_VECTOR, why)])
                   if present["gyro_bias"] else None),
        accel_bias=(_xyz([m.vector for m in topics.get("/truth/accel_bias", T_VECTOR, why)])
                    if present["accel_bias"] else None),
        ambient_wrench=(_wrenches(topics.get("/truth/ambient_wrench", T_WRENCH, why))
                        if present.get("ambient_wrench") else None),
    )
