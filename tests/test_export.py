"""Export of an Estimate to CSV and into a ROS 2 bag (MCAP) beside the input topics."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flexforce.datasets.estimate import STATE_LABELS, Estimate
from flexforce.datasets.io.export import csv_columns, export_csv, export_mcap
from flexforce.errors import BagError

T0 = 1_700_000_000_000_000_000


def make_estimate(t_ns, contacts=("left_foot", "right_foot"), cov=True, seed=0, name="fixed-lag") -> Estimate:
    rng = np.random.default_rng(seed)
    n, c = len(t_ns), len(contacts)
    A = rng.normal(size=(n, 18, 18)) * 1e-2
    return Estimate(
        estimator=name, t_ns=np.asarray(t_ns, dtype=np.int64), contact_names=tuple(contacts),
        R=Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.01).as_matrix(), t=rng.normal(size=(n, 3)) * 1e-3,
        w=rng.normal(size=(n, 3)), v=rng.normal(size=(n, 3)), dw=rng.normal(size=(n, 3)), a=rng.normal(size=(n, 3)),
        wrench=rng.normal(size=(n, c, 6)) * 100, cop=rng.normal(size=(n, 3)),
        cov=A @ A.transpose(0, 2, 1) if cov else None,
        cop_cov=np.tile(np.diag([1e-4, 4e-4]), (n, 1, 1)) if cov else None)


def read_bag(path):
    from rosbags.highlevel import AnyReader

    out = {}
    with AnyReader([path]) as reader:
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t, reader.deserialize(raw, conn.msgtype)))
    return out


def test_csv_one_row_per_step(tmp_path):
    est = make_estimate(T0 + np.arange(20) * 5_000_000)
    path = export_csv(est, tmp_path / "out" / "est.csv")
    header = path.read_text().splitlines()[0].split(",")
    assert header == csv_columns(est)
    assert header[:2] == ["time_s", "t_ns"] and "left_foot_F_z" in header and "std_theta_x" in header
    table = np.loadtxt(path, delimiter=",", skiprows=1)
    col = {name: table[:, i] for i, name in enumerate(header)}
    assert table.shape == (20, len(header))
    np.testing.assert_allclose(col["time_s"], est.time)
    assert [int(x) for x in path.read_text().splitlines()[1:][3].split(",")[1:2]] == [int(est.t_ns[3])]
    np.testing.assert_allclose(col["right_foot_T_y"], est.wrench[:, 1, 4])
    np.testing.assert_allclose(col["total_F_z"], est.wrench[:, :, 2].sum(axis=1))
    R = Rotation.from_quat(np.stack([col[f"q_{a}"] for a in "xyzw"], axis=1)).as_matrix()
    np.testing.assert_allclose(R, est.R, atol=1e-12)
    np.testing.assert_allclose(col["std_a_z"], np.sqrt(est.cov[:, 17, 17]))
    np.testing.assert_allclose(col["std_cop_y"], 0.02)
    assert len(csv_columns(make_estimate([0, 1], cov=False))) == len(header) - len(STATE_LABELS) - 2


@pytest.mark.parametrize("kind", ["mcap", "ros1"])
def test_mcap_beside_the_input_topics(tmp_path, kind):
    """Input topics are copied (ROS 1 converted) and the estimate is on /estimate/<name>/..."""
    from test_rosimport import write_bag

    t = T0 + np.arange(30, dtype=np.int64) * 10_000_000
    topics = {"/imu": ("sensor_msgs/msg/Imu", [(tt, {"gyro": [0.1, 0.2, 0.3], "accel": [0, 0, 9.8], "frame": "imu"})
                                               for tt in t]),
              "/left/wrench": ("geometry_msgs/msg/WrenchStamped", [(tt, {"w": [0, 0, 200.0, np.nan, np.nan, np.nan],
                                                                         "frame": "l_sole"}) for tt in t])}
    src = write_bag(tmp_path / ("in.bag" if kind == "ros1" else "in"), kind, topics)
    est = make_estimate(t)
    out = export_mcap(est, src, tmp_path / "out")
    assert next(out.glob("*.mcap"))
    got = read_bag(out)
    base = "/estimate/fixed_lag"
    assert {"/imu", "/left/wrench", f"{base}/flexibility", f"{base}/flexibility_cov", f"{base}/velocity",
            f"{base}/acceleration", f"{base}/total_wrench", f"{base}/cop", f"{base}/tilt", f"{base}/wrench/left_foot",
            f"{base}/wrench/right_foot"} == set(got)
    assert all(len(v) == 30 for v in got.values())
    imu = got["/imu"][5][1]
    assert imu.header.frame_id == "imu" and imu.angular_velocity.y == 0.2
    assert np.isnan(got["/left/wrench"][0][1].wrench.torque.x)
    flex = [m for _, m in got[f"{base}/flexibility"]]
    quat = np.array([(m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w)
                     for m in flex])
    np.testing.assert_allclose(Rotation.from_quat(quat).as_matrix(), est.R, atol=1e-12)
    tilt = np.array([(m.vector.x, m.vector.y, m.vector.z) for _, m in got[f"{base}/tilt"]])
    np.testing.assert_allclose(tilt, Rotation.from_matrix(est.R).as_rotvec(), atol=1e-12)
    stamps = [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in flex]
    assert stamps == t.tolist() and [tt for tt, _ in got[f"{base}/flexibility"]] == t.tolist()
    wr = np.array([(m.wrench.force.z, m.wrench.torque.x) for _, m in got[f"{base}/wrench/right_foot"]])
    np.testing.assert_allclose(wr, est.wrench[:, 1, [2, 3]])
    cov = got[f"{base}/flexibility_cov"][4][1].pose.covariance.reshape(6, 6)
    np.testing.assert_allclose(cov[:3, :3], est.cov[4, 3:6, 3:6])  # ROS order: position first
    np.testing.assert_allclose(cov[3:, 3:], est.cov[4, 0:3, 0:3])
    tw = got[f"{base}/velocity"][2][1].twist
    assert (tw.angular.x, tw.linear.z) == (est.w[2, 0], est.v[2, 2])

    with pytest.raises(BagError, match="exists already"):
        export_mcap(est, src, out)
    export_mcap(est, src, out, overwrite=True)
    with pytest.raises(BagError, match="is the input bag"):
        export_mcap(est, out, out.resolve(), overwrite=True)


def test_run_output_bag_holds_the_bands(tmp_path):
    """What `flexforce run -o OUT.mcap` writes (:func:`flexforce.pipeline.write_estimate`): the
    topics of :func:`export_mcap` and, as an intended format change, the estimate's uncertainty
    bands (``band/<q>/low``, ``band/<q>/high``), the same messages as with ``bands=True``."""
    import dataclasses

    from flexforce.pipeline import write_estimate

    t = T0 + np.arange(10, dtype=np.int64) * 10_000_000
    est = dataclasses.replace(make_estimate(t), wrench_cov=np.tile(np.eye(6), (10, 1, 1)))
    got = read_bag(write_estimate(est, tmp_path / "out.mcap"))
    plain = set(read_bag(export_mcap(est, None, tmp_path / "plain.mcap")))
    base = "/estimate/fixed_lag/band"
    bands = {f"{base}/{q}/{side}" for q in ("tilt", "position", "total_wrench", "cop") for side in ("low", "high")}
    assert set(got) == plain | bands
    banded = read_bag(export_mcap(est, None, tmp_path / "banded.mcap", bands=True))
    for topic in bands:
        assert [m.header.stamp.nanosec for _, m in got[topic]] == [m.header.stamp.nanosec for _, m in banded[topic]]
    high = f"{base}/total_wrench/high"
    assert [m.wrench.force.z for _, m in got[high]] == [m.wrench.force.z for _, m in banded[high]]


def test_mcap_from_a_recording(tmp_path):
    """Given a Recording, its sensor topics are written on its grid beside the estimate."""
    from test_bagio import make_recording

    rec = make_recording(12)
    est = make_estimate(rec.t_ns, contacts=rec.contact_names, cov=False, name="ekf")
    got = read_bag(export_mcap(est, rec, tmp_path / "out"))
    assert {"/imu", "/joint_states", "/ft/left_foot", "/ft/right_foot", "/mocap/torso",
            "/estimate/ekf/flexibility"} <= set(got)
    assert "/estimate/ekf/flexibility_cov" not in got
    np.testing.assert_allclose([m.linear_acceleration.z for _, m in got["/imu"]], rec.accel[:, 2])
    assert list(got["/joint_states"][0][1].name) == list(rec.joint_names)
    assert got["/ft/left_foot"][0][1].header.frame_id == "left_foot"


def test_an_mcap_path_is_one_mcap_file(tmp_path):
    """``X.mcap`` is the MCAP file itself (no bag folder around it), with the export's description;
    it is replaced only with overwrite, and no temporary is left beside it."""
    from flexforce.datasets.io.export import export_info

    t = T0 + np.arange(15, dtype=np.int64) * 10_000_000
    est = make_estimate(t)
    out = export_mcap(est, None, tmp_path / "walk.mcap", robot="icub")
    assert out == tmp_path / "walk.mcap" and out.is_file()
    assert {p.name for p in tmp_path.iterdir()} == {"walk.mcap"}
    got = read_bag(out)
    assert len(got["/estimate/fixed_lag/flexibility"]) == 15
    assert export_info(out) == {"format": "flexforce-estimate", "version": 1, "estimator": "fixed_lag",
                                "contact_names": ["left_foot", "right_foot"], "robot": "icub"}
    with pytest.raises(BagError, match="exists already"):
        export_mcap(est, None, out)
    export_mcap(make_estimate(t[:5]), None, out, overwrite=True)
    assert len(read_bag(out)["/estimate/fixed_lag/flexibility"]) == 5 and export_info(out)["robot"] is None
    # a bag folder keeps its form; its description is in metadata.yaml
    folder = export_mcap(est, out, tmp_path / "folder", robot="talos")
    assert (folder / "metadata.yaml").is_file() and export_info(folder)["robot"] == "talos"
    assert {p.name for p in tmp_path.iterdir()} == {"walk.mcap", "folder"}
    (tmp_path / "dir.mcap").mkdir()
    with pytest.raises(BagError, match="it is a folder"):
        export_mcap(est, None, tmp_path / "dir.mcap", overwrite=True)


def test_streamed_mcap_is_one_file(tmp_path):
    from flexforce.datasets.io.export import EstimateWriter, export_info
    from flexforce.errors import DataError

    t = T0 + np.arange(12, dtype=np.int64) * 10_000_000
    est = make_estimate(t, name="fixed-lag")
    out = tmp_path / "s.mcap"
    with EstimateWriter(out, robot="romeo") as writer:
        writer.write(est)
    assert out.is_file() and {p.name for p in tmp_path.iterdir()} == {"s.mcap"}
    assert export_info(out)["robot"] == "romeo" and export_info(out)["estimator"] == "fixed_lag"
    with pytest.raises(DataError, match="no estimate was written"), EstimateWriter(tmp_path / "e.mcap"):
        pass
    assert {p.name for p in tmp_path.iterdir()} == {"s.mcap"}


def test_mcap_uncertainty_bands(tmp_path):
    """With bands=True: the estimate -+ 2 sigma per component, for each covariance the estimate has."""
    import dataclasses

    from flexforce.datasets.io.export import BAND_SIGMAS

    t = T0 + np.arange(10, dtype=np.int64) * 10_000_000
    est = dataclasses.replace(make_estimate(t), wrench_cov=np.tile(np.diag([1.0, 4.0, 9.0, 0.1, 0.2, 0.3]), (10, 1, 1)))
    plain = set(read_bag(export_mcap(est, None, tmp_path / "plain.mcap")))
    got = read_bag(export_mcap(est, None, tmp_path / "bands.mcap", bands=True))
    base = "/estimate/fixed_lag/band"
    added = {f"{base}/{q}/{side}" for q in ("tilt", "position", "total_wrench", "cop") for side in ("low", "high")}
    assert set(got) - plain == added and not any("/band/" in topic for topic in plain)
    assert BAND_SIGMAS == 2.0
    std = est.state_std()
    rotvec = Rotation.from_matrix(est.R).as_rotvec()
    for side, sign in (("low", -1), ("high", 1)):
        tilt = np.array([(m.vector.x, m.vector.y, m.vector.z) for _, m in got[f"{base}/tilt/{side}"]])
        np.testing.assert_allclose(tilt, rotvec + sign * 2 * std[:, 0:3], atol=1e-12)
        pos = np.array([(m.point.x, m.point.y, m.point.z) for _, m in got[f"{base}/position/{side}"]])
        np.testing.assert_allclose(pos, est.t + sign * 2 * std[:, 3:6], atol=1e-12)
        fz = np.array([m.wrench.force.z for _, m in got[f"{base}/total_wrench/{side}"]])
        np.testing.assert_allclose(fz, est.total_wrench[:, 2] + sign * 2 * np.sqrt(est.wrench_cov[:, 2, 2]))
        cop = np.array([(m.point.x, m.point.y, m.point.z) for _, m in got[f"{base}/cop/{side}"]])
        np.testing.assert_allclose(cop[:, 1], est.cop[:, 1] + sign * 2 * 0.02)
        np.testing.assert_allclose(cop[:, 2], est.cop[:, 2])
    without = read_bag(export_mcap(make_estimate(t, cov=False), None, tmp_path / "nocov.mcap", bands=True))
    assert not any("/band/" in topic for topic in without)


def test_a_writers_error_names_the_mcap_file_not_its_hidden_folder(tmp_path):
    """``mcap_file_output`` has the writer fill a hidden bag folder: an error naming that folder (a
    full disk under ``simulate -o X.mcap``) names the output instead."""
    from flexforce.datasets.io.export import mcap_file_output

    target = tmp_path / "sim.mcap"
    with pytest.raises(BagError, match=r"^cannot write bag .*sim\.mcap: \[Errno 28\] No space left on device$") as exc:
        with mcap_file_output(target) as bag:
            raise BagError(f"cannot write bag {bag}: [Errno 28] No space left on device")
    assert ".tmp-" not in str(exc.value) and not target.exists()
