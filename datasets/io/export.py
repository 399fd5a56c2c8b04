r"""Export an :class:`Estimate` to CSV, and into a ROS 2 bag (MCAP) beside the input topics.

CSV (:func:`export_csv`): one row per step, a header row of column names with units:

* ``time_s`` (from the first step), ``t_ns`` (absolute stamp, as in the input bag);
* flexibility pose (local frame -> world): ``t_x t_y t_z`` [m], ``q_x q_y q_z q_w`` (ROS order),
  ``theta_x theta_y theta_z`` [rad] (rotation vector of R);
* ``w_*`` [rad/s], ``v_*`` [m/s], ``dw_*`` [rad/s^2], ``a_*`` [m/s^2] (world);
* per contact ``<contact>_F_*`` [N], ``<contact>_T_*`` [N m] (about the world origin), then the
  total ``total_F_*``, ``total_T_*``;
* ``cop_x cop_y cop_z`` [m];
* when the estimate has covariances: ``std_<state label>`` for the 18 state components
  (:data:`flexforce.datasets.layout.STATE_LABELS`), ``std_cop_x std_cop_y``.

Numbers have 15 significant digits (within 1e-14 of the estimate, relatively: the .npz is the
lossless output), ``t_ns`` is exact (:mod:`flexforce.datasets.io.csvformat`).

MCAP (:func:`export_mcap`): a ROS 2 bag (MCAP storage, Humble message definitions embedded) for
PlotJuggler or Foxglove: an output path ending in ``.mcap`` is that one MCAP file, any other a ROS 2
bag directory (``metadata.yaml`` beside the MCAP file).  Under ``/estimate/<estimator>/``:

========================  ========================================  ==========
topic                     message                                   frame_id
========================  ========================================  ==========
``flexibility``           geometry_msgs/PoseStamped (t, R)          ``world``
``flexibility_cov``       geometry_msgs/PoseWithCovarianceStamped   ``world``
                          (only with covariances; ROS order x y z,
                          rot x y z of the world-frame increments)
``velocity``              geometry_msgs/TwistStamped (w, v)         ``world``
``acceleration``          geometry_msgs/AccelStamped (dw, a)        ``world``
``wrench/<contact>``      geometry_msgs/WrenchStamped               ``world``
``total_wrench``          geometry_msgs/WrenchStamped               ``world``
``cop``                   geometry_msgs/PointStamped                ``world``
``tilt``                  geometry_msgs/Vector3Stamped: rotation    ``world``
                          vector of R, rad (x, y: the tilt, z: yaw)
``band/<q>/low``,         with ``bands=True``: the estimate -+      ``world``
``band/<q>/high``         :data:`BAND_SIGMAS` standard deviations,
                          per component, for the covariances the
                          estimate has: ``tilt`` (Vector3Stamped;
                          the rotation increment's, first order),
                          ``position`` (PointStamped, t),
                          ``total_wrench`` (WrenchStamped),
                          ``cop`` (PointStamped, x and y)
========================  ========================================  ==========

Every topic of the input is copied unchanged beside them (ROS 1 messages converted to ROS 2
CDR); given a :class:`Recording` instead of a bag, its ``/imu``, ``/joint_states``,
``/ft/<contact>`` and ``/mocap/<link>`` are written on its grid.  Stamps are the input's
absolute times, so estimates and measurements line up.  :mod:`flexforce.datasets.io.viewers` writes
Foxglove and PlotJuggler layouts for these topics (``flexforce layout``).

What the bag holds is described in the rosbag2 ``custom_data`` under the key :data:`INFO_KEY` (in
``metadata.yaml``, and in the MCAP file's ``rosbag2`` metadata record, which ROS 2 reads as well): a
JSON object ``{"format": "flexforce-estimate", "version": 1, "estimator": <topic token>,
"contact_names": [...], "robot": <robot configuration: built-in name or .toml path, or null>}``;
:func:`export_info` reads it back.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from flexforce.datasets.estimate import Estimate
from flexforce.datasets.io.csvformat import format_rows
from flexforce.datasets.layout import STATE, STATE_LABELS
from flexforce.datasets.recording import Recording
from flexforce.datasets.safeio import OutputOSError, is_bag_folder, safe_output
from flexforce.errors import BagError, DataError

__all__ = ["INFO_KEY", "EstimateWriter", "csv_columns", "export_csv", "export_info", "export_mcap", "mcap_file_output"]

_NS = 1_000_000_000

INFO_KEY = "flexforce"
"""Key of the exported bag's rosbag2 ``custom_data`` describing it (module docstring)."""
INFO_FORMAT = "flexforce-estimate"
"""Value of ``"format"`` in that description."""


def csv_columns(estimate: Estimate) -> list[str]:
    """Column names of :func:`export_csv` for this estimate."""
    cols = ["time_s", "t_ns", "t_x", "t_y", "t_z", "q_x", "q_y", "q_z", "q_w", "theta_x", "theta_y", "theta_z"]
    for prefix in ("w", "v", "dw", "a"):
        cols += [f"{prefix}_{ax}" for ax in "xyz"]
    for name in list(estimate.contact_names) + ["total"]:
        cols += [f"{name}_F_{ax}" for ax in "xyz"] + [f"{name}_T_{ax}" for ax in "xyz"]
    cols += ["cop_x", "cop_y", "cop_z"]
    if estimate.cov is not None:
        cols += [f"std_{label}" for label in STATE_LABELS]
    if estimate.cop_cov is not None:
        cols += ["std_cop_x", "std_cop_y"]
    return cols


def _check(estimate: Estimate) -> None:
    n = estimate.n
    if estimate.R.shape != (n, 3, 3) or estimate.wrench.shape != (n, len(estimate.contact_names), 6):
        raise DataError(f"estimate has R {estimate.R.shape} and wrench {estimate.wrench.shape}; expected "
                        f"{(n, 3, 3)} and {(n, len(estimate.contact_names), 6)}")


def _csv_lines(estimate: Estimate, t0_ns: int | None = None):
    """The CSV rows of ``estimate`` (``time_s`` from ``t0_ns``, default its first step)."""
    rot = Rotation.from_matrix(estimate.R)
    t0 = int(estimate.t_ns[0]) if t0_ns is None else int(t0_ns)
    time_s = (estimate.t_ns - t0).astype(float) * 1e-9
    parts = [time_s[:, None], estimate.t_ns[:, None].astype(float), estimate.t, rot.as_quat(),
             rot.as_rotvec(), estimate.w, estimate.v, estimate.dw, estimate.a,
             estimate.wrench.reshape(estimate.n, -1), estimate.total_wrench, estimate.cop]
    if estimate.cov is not None:
        parts.append(estimate.state_std())
    if estimate.cop_cov is not None:
        parts.append(np.sqrt(np.maximum(np.diagonal(estimate.cop_cov, axis1=1, axis2=2), 0.0)))
    if not estimate.n:
        return
    yield format_rows(np.concatenate(parts, axis=1), estimate.t_ns, int_col=1)  # t_ns exact, not through a float


def export_csv(estimate: Estimate, path) -> Path:
    """Write one row per step (columns in the module docstring); return the path."""
    _check(estimate)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cols = csv_columns(estimate)
    with safe_output(path) as tmp, tmp.open("w") as f:  # complete or not at all, one writer at a time
        f.write(",".join(cols) + "\n")
        f.writelines(_csv_lines(estimate))
    return path


class EstimateWriter:
    """Writes the consecutive estimates of a stream (:class:`flexforce.smoother.stream.FixedLagStream`)
    to a ``.csv`` file or a ``.mcap`` bag as they come, in constant memory.

    The output is written aside and moved into place when the block ends normally (an
    interrupted stream leaves the previous output or none, never a part).  CSV: the columns of
    :func:`export_csv`, fixed by the first estimate, ``time_s`` from the stream's first step.
    MCAP: the topics of :func:`export_mcap`; the inputs are copied with :meth:`copy` (as the
    input bag is read).

    Use::

        with EstimateWriter("out.csv") as w:
            for est in estimates:
                w.write(est)

    Args:
        path: ``.csv`` file, or ``.mcap`` file (one MCAP file, no bag directory).
        overwrite: replace an existing ``.mcap`` file.
        robot: the robot configuration (built-in name, ``.toml`` path or RobotConfig) recorded in
            the MCAP's description (:data:`INFO_KEY`); settable as :attr:`robot` until the block ends.
        bands: MCAP: also write the ``band/`` topics of :func:`export_mcap`.
    """

    def __init__(self, path, *, overwrite: bool = False, robot=None, bands: bool = False):
        self.path = Path(path)
        self.bands = bands
        self.kind = self.path.suffix
        if self.kind not in (".csv", ".mcap"):
            raise DataError(f"streamed estimates are written to .csv or .mcap; got {self.path}")
        if self.kind == ".mcap":
            _check_mcap_target(self.path, overwrite)
        self.robot = robot
        self._info: dict | None = None
        self._bag: Path | None = None
        self.steps = 0
        self.t0_ns: int | None = None
        self._cm: Any = None
        self._file: Any = None
        self._writer: Any = None
        self._ts: Any = None
        self._conns: dict = {}
        self._copied: dict = {}
        self._cols: list[str] | None = None

    def __enter__(self) -> EstimateWriter:
        self._cm = safe_output(self.path)
        tmp = self._cm.__enter__()
        self._tmp = tmp
        try:
            if self.kind == ".csv":
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._file = tmp.open("w")
            else:
                from rosbags.rosbag2 import StoragePlugin, Writer

                self._ts = _typestore()
                self._bag = _bag_folder(tmp, single=True)
                self._writer = Writer(self._bag, version=8, storage_plugin=StoragePlugin.MCAP)
                self._writer.open()
        except BaseException as err:
            self._discard_bag()
            self._cm.__exit__(type(err), err, err.__traceback__)
            raise
        return self

    def __exit__(self, kind, err, tb):
        try:
            if self._file is not None:
                self._file.close()
            if self._writer is not None:
                if self._info is not None:
                    self._info["robot"] = _robot_ref(self.robot)
                    self._writer.set_custom_data(INFO_KEY, json.dumps(self._info))
                self._writer.close()
                if err is None and self.steps and self._bag is not None:
                    _take_mcap(self._bag, self._tmp)
        except Exception as close_err:  # noqa: BLE001 -- reported as the block's failure
            if err is None:
                kind, err, tb = type(close_err), close_err, close_err.__traceback__
        finally:
            self._discard_bag()
        if err is None and self.steps == 0:
            empty = DataError(f"no estimate was written to {self.path}; expected at least one step")
            self._cm.__exit__(DataError, empty, None)
            raise empty
        return self._cm.__exit__(kind, err, tb)

    def _discard_bag(self) -> None:
        if self._bag is not None:
            shutil.rmtree(self._bag, ignore_errors=True)

    def write(self, est: Estimate | None) -> None:
        """Append the steps of ``est`` (after those written before; None: nothing)."""
        if est is None or est.n == 0:
            return
        _check(est)
        if self.t0_ns is None:
            self.t0_ns = int(est.t_ns[0])
        if self.kind == ".csv":
            cols = csv_columns(est)
            if self._cols is None:
                self._cols = cols
                self._file.write(",".join(cols) + "\n")
            elif cols != self._cols:
                raise DataError(f"estimate columns changed within the stream ({len(cols)} against "
                                f"{len(self._cols)}); expected one kind of estimate")
            self._file.writelines(_csv_lines(est, self.t0_ns))
        else:
            if self._info is None:
                self._info = _info(est, None)
            _write_streams(self._writer, self._ts, _estimate_streams(self._ts, est, self.bands), est.t_ns, "world",
                           self._conns)
        self.steps += est.n

    def copy(self, reader, conn, t_ns: int, raw) -> None:
        """Copy one message of the input bag (``reader`` its rosbags AnyReader) into the MCAP."""
        if self._writer is None or conn.topic.startswith("/estimate/"):
            return
        ts = self._ts
        out = self._copied.get(conn.id)
        if out is None:
            if reader.is2:
                store = reader.typestore
            elif conn.msgtype in ts.fielddefs:
                store = ts
            else:
                self._copied[conn.id] = False  # a ROS 1 type without a ROS 2 counterpart
                return
            existing = [c for c in self._writer.connections if c.topic == conn.topic]
            out = existing[0] if existing else self._writer.add_connection(conn.topic, conn.msgtype, typestore=store)
            self._copied[conn.id] = out
        if out is False:
            return
        self._writer.write(out, int(t_ns), raw if reader.is2 else ts.ros1_to_cdr(raw, conn.msgtype))

    def copy_bag(self, path) -> None:
        """Copy every message of the bag at ``path`` into the MCAP (but a previous export's
        ``/estimate/`` topics, and ROS 1 types without a ROS 2 counterpart), as :func:`export_mcap`
        does; nothing into a ``.csv``.

        Raises:
            BagError: a missing or unreadable input bag.
        """
        if self._writer is not None:
            _copy_bag(self._writer, self._ts, Path(path))


# ------------------------------------------------------------------------------------------------
def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _token(name: str) -> str:
    token = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return token if re.match(r"^[A-Za-z]", token) else f"e_{token}"


def export_mcap(estimate: Estimate, source, out_path, *, overwrite: bool = False, robot=None,
                bands: bool = False) -> Path:
    """Write the estimate, beside copies of the inputs, into a ROS 2 bag (MCAP) at ``out_path``.

    Args:
        estimate: the estimate to export.
        source: the input bag (path) whose topics are copied, a :class:`Recording` whose sensor
            topics are written, or ``None`` for the estimate alone.
        out_path: ``X.mcap``: the MCAP file to create; any other name: the ROS 2 bag directory to
            create.  An existing one is refused unless ``overwrite`` (and even then only an MCAP
            file, or a ROS 2 bag directory, is replaced by its own kind).
        robot: the robot configuration (built-in name, ``.toml`` path or RobotConfig) recorded in
            the bag's description (:data:`INFO_KEY`); default: the ``Recording``'s, else none.
        bands: also write the ``band/`` topics (the estimate -+ 2 standard deviations, for the
            viewers' uncertainty bands; module docstring).

    Raises:
        BagError: the output refused, the input unreadable, the writer failed.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    _check(estimate)
    out_path = Path(out_path)
    single = out_path.suffix == ".mcap"
    if single:
        _check_mcap_target(out_path, overwrite)
    elif out_path.exists():
        if not overwrite:
            raise BagError(f"{out_path} exists already; expected a new path (or overwrite=True)")
        if not is_bag_folder(out_path):
            raise BagError(f"cannot overwrite {out_path}: it is not a ROS 2 bag directory; remove it yourself")
    if isinstance(source, (str, Path)) and Path(source).resolve() == out_path.resolve():
        raise BagError(f"output {out_path} is the input bag; expected a new path beside it")
    if robot is None and isinstance(source, Recording):
        robot = source.robot
    ts = _typestore()
    # Written aside and moved into place when complete: an interrupted export leaves the previous bag.
    with safe_output(out_path, folder=not single) as tmp:
        bag = _bag_folder(tmp, single)
        try:
            with Writer(bag, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
                if isinstance(source, Recording):
                    _write_recording(writer, ts, source)
                elif source is not None:
                    _copy_bag(writer, ts, Path(source))
                _write_estimate(writer, ts, estimate, bands)
                writer.set_custom_data(INFO_KEY, json.dumps(_info(estimate, robot)))
            if single:
                _take_mcap(bag, tmp)
        except BagError:
            raise
        except Exception as err:  # noqa: BLE001 -- a writer failure: report one line
            raise BagError(f"cannot write bag {out_path}: {' '.join(str(err).split()) or type(err).__name__}") from err
        finally:
            if single:
                shutil.rmtree(bag, ignore_errors=True)
    return out_path


def _check_mcap_target(path: Path, overwrite: bool) -> None:
    """An MCAP file may be written at ``path``: new, or an existing file with ``overwrite``."""
    if not (path.exists() or path.is_symlink()):
        return
    if not overwrite:
        raise BagError(f"{path} exists already; expected a new path (or overwrite=True)")
    if path.is_dir():
        raise BagError(f"cannot overwrite {path}: it is a folder; expected an MCAP file there (remove the folder "
                       "yourself to reuse its name)")


@contextlib.contextmanager
def mcap_file_output(path, *, overwrite: bool = False) -> Iterator[Path]:
    """Have a ROS 2 bag writer produce the one MCAP file ``path`` (no bag directory).

    Yields the path of a bag directory to create (a hidden sibling of ``path``, not yet existing):
    the caller writes a complete bag there (:func:`flexforce.datasets.io.bagio.save_recording`, a
    rosbags ``Writer``...).  When the block ends normally the bag's single ``.mcap`` file is moved
    to ``path`` and the directory removed; when it raises, ``path`` is left as it was (written aside
    and moved into place: :func:`flexforce.datasets.safeio.safe_output`).  The rosbag2 metadata
    lives on in the MCAP file (its ``rosbag2`` metadata record), so readers take the file alone.

    Raises:
        BagError: ``path`` exists (without ``overwrite``), is a folder, or the bag written holds
            other than exactly one MCAP file.
        OutputError: another process is writing ``path``, or the move fails.
    """
    path = Path(path)
    _check_mcap_target(path, overwrite)
    with safe_output(path) as tmp:
        bag = _bag_folder(tmp, True)
        try:
            try:
                yield bag
            except BagError as err:  # a writer's error names the output, not the hidden bag folder
                if str(bag) not in str(err):
                    raise
                raise BagError(str(err).replace(str(bag), str(path))) from err
            _take_mcap(bag, tmp)
        finally:
            shutil.rmtree(bag, ignore_errors=True)


def _bag_folder(tmp: Path, single: bool) -> Path:
    """The folder the rosbags writer creates: ``tmp`` itself (a bag directory), or for one MCAP
    file a sibling of ``tmp`` whose storage file :func:`_take_mcap` moves to ``tmp``."""
    return tmp.with_name(tmp.name + ".bag") if single else tmp


def _take_mcap(bag: Path, target: Path) -> None:
    """Move the one MCAP file of the bag directory ``bag`` to ``target`` (the folder is left)."""
    files = sorted(bag.glob("*.mcap"))
    if len(files) != 1:
        raise BagError(f"the bag written at {bag} holds {len(files)} MCAP files; expected exactly one")
    os.replace(files[0], target)


def _robot_ref(robot) -> str | None:
    """A robot configuration as :meth:`flexforce.datasets.robot.RobotConfig.load` takes it back:
    a built-in's name, another configuration's ``.toml`` path; None stays None."""
    if robot is None or robot == "":
        return None
    from flexforce.datasets.robot import ROBOTS_DIR, RobotConfig

    if not isinstance(robot, RobotConfig):
        return str(robot)
    if not robot.source or Path(robot.source).parent.resolve() == Path(ROBOTS_DIR).resolve():
        return robot.name
    return robot.source


def _info(est: Estimate, robot) -> dict:
    """The bag's description (:data:`INFO_KEY`) for ``est`` and ``robot``."""
    return {"format": INFO_FORMAT, "version": 1, "estimator": _token(est.estimator),
            "contact_names": [str(c) for c in est.contact_names], "robot": _robot_ref(robot)}


def export_info(path) -> dict:
    """The description (:data:`INFO_KEY`) of a bag written by :func:`export_mcap` or
    :class:`EstimateWriter`: ``{"format", "version", "estimator", "contact_names", "robot"}``;
    ``{}`` for a bag without one (another writer's, or an export older than the description).

    Raises:
        BagError: ``path`` missing, or its metadata unreadable.
    """
    path = Path(path)
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    try:
        if path.is_dir():
            custom = _yaml_custom_data((path / "metadata.yaml").read_text()) if (path / "metadata.yaml").is_file() \
                else {}
        elif path.suffix == ".mcap":
            custom = _mcap_custom_data(path)
        else:
            custom = {}
        doc = json.loads(custom[INFO_KEY]) if INFO_KEY in custom else {}
    except BagError:
        raise
    except Exception as err:  # noqa: BLE001 -- unreadable metadata: one line
        raise BagError(f"cannot read the metadata of bag {path}: {' '.join(str(err).split()) or type(err).__name__}"
                       ) from err
    return doc if isinstance(doc, dict) and doc.get("format") == INFO_FORMAT else {}


def _yaml_custom_data(text: str, top: str | None = "rosbag2_bagfile_information") -> dict:
    from ruamel.yaml import YAML

    doc = YAML(typ="safe").load(text) or {}
    if top is not None:
        doc = doc.get(top) or {}
    return dict(doc.get("custom_data") or {})


def _mcap_custom_data(path: Path) -> dict:
    """The ``custom_data`` of an MCAP file's ``rosbag2`` metadata record, found through its summary
    (MCAP specification: footer, Metadata Index 0x0D, Metadata 0x0C); ``{}`` without one."""
    import struct

    def string(buf: bytes, at: int) -> tuple[str, int]:
        (n,) = struct.unpack_from("<I", buf, at)
        return buf[at + 4:at + 4 + n].decode(), at + 4 + n

    with path.open("rb") as f:
        size = f.seek(0, 2)
        if size < 8 + 37:
            return {}
        f.seek(size - 37)
        footer = f.read(37)
        if footer[0] != 0x02 or footer[-8:] != b"\x89MCAP0\r\n":
            raise BagError(f"{path} does not end with an MCAP footer; expected a complete MCAP file")
        (summary_start,) = struct.unpack_from("<Q", footer, 9)
        if summary_start == 0:
            return {}
        f.seek(summary_start)
        summary = f.read(size - 37 - summary_start)
        at = 0
        while at + 9 <= len(summary):
            op, length = summary[at], struct.unpack_from("<Q", summary, at + 1)[0]
            body = summary[at + 9:at + 9 + length]
            at += 9 + length
            if op != 0x0D:
                continue
            offset, rec_length = struct.unpack_from("<QQ", body, 0)
            name, _ = string(body, 16)
            if name != "rosbag2":
                continue
            f.seek(offset)
            record = f.read(rec_length)
            name, pos = string(record, 9)
            (map_length,) = struct.unpack_from("<I", record, pos)
            pos += 4
            end = pos + map_length
            while pos < end:
                key, pos = string(record, pos)
                value, pos = string(record, pos)
                if key == "serialized_metadata":
                    return _yaml_custom_data(value, top=None)
    return {}


def _copy_bag(writer, ts, path: Path) -> None:
    from rosbags.highlevel import AnyReader

    if not path.exists():
        raise BagError(f"input bag {path} does not exist")
    try:
        with AnyReader([path], default_typestore=ts) as reader:
            conns = {}
            for rconn in reader.connections:
                if rconn.topic.startswith("/estimate/"):
                    continue  # a previous export: the new estimate replaces it
                if reader.is2:
                    store = reader.typestore
                elif rconn.msgtype in ts.fielddefs:
                    store = ts
                else:
                    continue  # a ROS 1 type without a ROS 2 counterpart cannot be converted
                if rconn.topic not in {c.topic for c in writer.connections}:
                    conns[rconn.id] = writer.add_connection(rconn.topic, rconn.msgtype, typestore=store)
                else:
                    conns[rconn.id] = next(c for c in writer.connections if c.topic == rconn.topic)
            if not conns:  # nothing to copy (rosbags reads every connection when given none)
                return
            for rconn, t, raw in reader.messages(connections=[c for c in reader.connections if c.id in conns]):
                data = raw if reader.is2 else ts.ros1_to_cdr(raw, rconn.msgtype)
                try:
                    writer.write(conns[rconn.id], t, data)
                except OSError as err:  # the output's (a full disk), not the input bag's
                    raise OutputOSError(err) from err
    except BagError:
        raise
    except OutputOSError as err:
        raise err.error from None
    except Exception as err:  # noqa: BLE001
        raise BagError(f"cannot read input bag {path}: {' '.join(str(err).split())}") from err


class _Msgs:
    """Small builders over the Humble typestore."""

    def __init__(self, ts):
        self.T = ts.types
        self.ts = ts

    def header(self, t_ns: int, frame: str):
        sec, nanosec = divmod(int(t_ns), _NS)
        return self.T["std_msgs/msg/Header"](stamp=self.T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                             frame_id=frame)

    def vec(self, v):
        return self.T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def point(self, v):
        return self.T["geometry_msgs/msg/Point"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def pose(self, p):
        return self.T["geometry_msgs/msg/Pose"](position=self.point(p[:3]), orientation=self.T[
            "geometry_msgs/msg/Quaternion"](x=float(p[3]), y=float(p[4]), z=float(p[5]), w=float(p[6])))

    def wrench(self, w):
        return self.T["geometry_msgs/msg/Wrench"](force=self.vec(w[:3]), torque=self.vec(w[3:]))


def _estimate_streams(ts, est: Estimate, bands: bool = False) -> list[tuple[str, str, Callable[..., Any]]]:
    M = _Msgs(ts)
    T = M.T
    base = f"/estimate/{_token(est.estimator)}"
    rot = Rotation.from_matrix(est.R)
    quat, rotvec = rot.as_quat(), rot.as_rotvec()
    pose = np.concatenate([est.t, quat], axis=1)
    streams: list[tuple[str, str, Callable[..., Any]]] = [
        (f"{base}/flexibility", "geometry_msgs/msg/PoseStamped",
         lambda k, h: T["geometry_msgs/msg/PoseStamped"](header=h, pose=M.pose(pose[k]))),
        (f"{base}/velocity", "geometry_msgs/msg/TwistStamped",
         lambda k, h: T["geometry_msgs/msg/TwistStamped"](header=h, twist=T["geometry_msgs/msg/Twist"](
             linear=M.vec(est.v[k]), angular=M.vec(est.w[k])))),
        (f"{base}/acceleration", "geometry_msgs/msg/AccelStamped",
         lambda k, h: T["geometry_msgs/msg/AccelStamped"](header=h, accel=T["geometry_msgs/msg/Accel"](
             linear=M.vec(est.a[k]), angular=M.vec(est.dw[k])))),
        (f"{base}/total_wrench", "geometry_msgs/msg/WrenchStamped",
         lambda k, h: T["geometry_msgs/msg/WrenchStamped"](header=h, wrench=M.wrench(est.total_wrench[k]))),
        (f"{base}/cop", "geometry_msgs/msg/PointStamped",
         lambda k, h: T["geometry_msgs/msg/PointStamped"](header=h, point=M.point(est.cop[k]))),
        (f"{base}/tilt", "geometry_msgs/msg/Vector3Stamped",
         lambda k, h: T["geometry_msgs/msg/Vector3Stamped"](header=h, vector=M.vec(rotvec[k]))),
    ]
    for i, name in enumerate(est.contact_names):
        streams.append((f"{base}/wrench/{_token(name)}", "geometry_msgs/msg/WrenchStamped",
                        lambda k, h, i=i: T["geometry_msgs/msg/WrenchStamped"](
                            header=h, wrench=M.wrench(est.wrench[k, i]))))
    if bands:
        streams += _band_streams(M, base, est, rotvec)
    if est.cov is not None:
        # state layout -> ROS pose covariance order (x, y, z, rot x, rot y, rot z)
        idx = np.r_[STATE["t"], STATE["theta"]]
        cov6 = est.cov[:, idx][:, :, idx]
        streams.append((f"{base}/flexibility_cov", "geometry_msgs/msg/PoseWithCovarianceStamped",
                        lambda k, h: T["geometry_msgs/msg/PoseWithCovarianceStamped"](
                            header=h, pose=T["geometry_msgs/msg/PoseWithCovariance"](
                                pose=M.pose(pose[k]), covariance=np.ascontiguousarray(cov6[k].reshape(36))))))
    return streams


BAND_SIGMAS = 2.0
"""Half-width of the ``band/`` topics, in standard deviations (the reports' bands too)."""


def _band_streams(M: _Msgs, base: str, est: Estimate, rotvec: np.ndarray) -> list[tuple[str, str, Callable[..., Any]]]:
    """The ``band/<quantity>/low|high`` topics: the estimate -+ :data:`BAND_SIGMAS` standard
    deviations, for the covariances ``est`` has (none without)."""
    T = M.T
    out: list[tuple[str, str, Callable[..., Any]]] = []
    bands: list[tuple[str, str, np.ndarray, np.ndarray, Callable[..., Any]]] = []
    std = est.state_std()
    if std is not None:
        vec = "geometry_msgs/msg/Vector3Stamped"
        point = "geometry_msgs/msg/PointStamped"
        bands.append(("tilt", vec, rotvec, std[:, STATE["theta"]],
                      lambda h, v: T[vec](header=h, vector=M.vec(v))))
        bands.append(("position", point, est.t, std[:, STATE["t"]],
                      lambda h, v: T[point](header=h, point=M.point(v))))
    if est.wrench_cov is not None:
        wrench = "geometry_msgs/msg/WrenchStamped"
        bands.append(("total_wrench", wrench, est.total_wrench,
                      np.sqrt(np.maximum(np.diagonal(est.wrench_cov, axis1=1, axis2=2), 0.0)),
                      lambda h, v: T[wrench](header=h, wrench=M.wrench(v))))
    if est.cop_cov is not None:
        point = "geometry_msgs/msg/PointStamped"
        cop_std = np.zeros_like(est.cop)
        cop_std[:, :2] = np.sqrt(np.maximum(np.diagonal(est.cop_cov, axis1=1, axis2=2), 0.0))
        bands.append(("cop", point, est.cop, cop_std, lambda h, v: T[point](header=h, point=M.point(v))))
    for name, msgtype, value, sd, make in bands:
        for side, sign in (("low", -1.0), ("high", 1.0)):
            edge = value + sign * BAND_SIGMAS * sd
            out.append((f"{base}/band/{name}/{side}", msgtype, lambda k, h, edge=edge, make=make: make(h, edge[k])))
    return out


def _write_estimate(writer, ts, est: Estimate, bands: bool = False) -> None:
    _write_streams(writer, ts, _estimate_streams(ts, est, bands), est.t_ns, "world")


def _write_streams(writer, ts, streams, t_ns, frame, conns: dict | None = None) -> None:
    """Write ``streams`` at every step; ``conns`` (topic -> connection) keeps the connections of
    earlier calls (a stream written part by part)."""
    conns = {} if conns is None else conns
    for topic, msgtype, _ in streams:
        if topic not in conns:
            conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
    M = _Msgs(ts)
    for k, t in enumerate(t_ns):
        for topic, msgtype, make in streams:
            conn = conns[topic]
            f = frame(conn.topic) if callable(frame) else frame
            writer.write(conn, int(t), ts.serialize_cdr(make(k, M.header(t, f)), msgtype))


def _write_recording(writer, ts, rec: Recording) -> None:
    M = _Msgs(ts)
    T = M.T
    zero9 = np.zeros(9)
    no_orientation = np.zeros(9)
    no_orientation[0] = -1.0
    streams: list[tuple[str, str, Callable[..., Any]]] = [("/imu", "sensor_msgs/msg/Imu", lambda k, h: T[
        "sensor_msgs/msg/Imu"](
        header=h, orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=no_orientation, angular_velocity=M.vec(rec.gyro[k]),
        angular_velocity_covariance=zero9, linear_acceleration=M.vec(rec.accel[k]),
        linear_acceleration_covariance=zero9))]
    frames = {"/imu": "imu"}
    if rec.joint_q is not None:
        names = list(rec.joint_names)
        empty = np.zeros(0)
        streams.append(("/joint_states", "sensor_msgs/msg/JointState", lambda k, h: T["sensor_msgs/msg/JointState"](
            # joint_q checked above; mypy does not carry the check into the lambda
            header=h, name=names, position=np.ascontiguousarray(rec.joint_q[k], dtype=float),  # type: ignore[index]
            velocity=np.ascontiguousarray(rec.joint_v[k], dtype=float) if rec.joint_v is not None else empty,
            effort=empty)))
        frames["/joint_states"] = ""
    if rec.ft is not None:
        for i, name in enumerate(rec.contact_names):
            topic = f"/ft/{_token(name)}"
            streams.append((topic, "geometry_msgs/msg/WrenchStamped", lambda k, h, i=i: T[
                "geometry_msgs/msg/WrenchStamped"](header=h, wrench=M.wrench(rec.ft[k, i]))))  # type: ignore[index]
            frames[topic] = name
    for name, poses in rec.mocap.items():
        topic = f"/mocap/{_token(name)}"
        streams.append((topic, "geometry_msgs/msg/PoseStamped", lambda k, h, p=poses: T[
            "geometry_msgs/msg/PoseStamped"](header=h, pose=M.pose(p[k]))))
        frames[topic] = "world"
    _write_streams(writer, ts, streams, rec.t_ns, lambda topic: frames[topic])
