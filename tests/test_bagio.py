"""Round trips of a Recording through a ROS 2 bag (MCAP) and the errors of bad bags."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flexforce.datasets.io.bagio import inputs_layout, load_recording, save_recording
from flexforce.datasets.recording import Recording, Truth
from flexforce.errors import BagError

CONTACTS = ("left_foot", "right_foot")
JOINTS = ("hip_y", "knee", "ankle_p")


def make_recording(n: int = 40, *, full: bool = True, seed: int = 0) -> Recording:
    """Random numbers with the right shapes; ``full`` adds truth, F/T, joints and mocap."""
    rng = np.random.default_rng(seed)
    c = len(CONTACTS)

    def rot(*shape):
        return Rotation.random(int(np.prod(shape)), random_state=rng).as_matrix().reshape(*shape, 3, 3)

    active = np.ones((n, c), dtype=bool)
    active[: n // 2, 1] = False  # the right foot lifts off for the first half
    kw = dict(
        # a real epoch time, so that header stamps use both sec and nanosec
        t_ns=1_700_000_000_123_456_789 + np.arange(n, dtype=np.int64) * 5_000_000,
        robot="hrp2",
        contact_names=CONTACTS,
        mass=58.123456789,
        com=rng.normal(size=(n, 3)), com_vel=rng.normal(size=(n, 3)), com_acc=rng.normal(size=(n, 3)),
        inertia=rng.normal(size=(n, 3, 3)), inertia_dot=rng.normal(size=(n, 3, 3)),
        sigma=rng.normal(size=(n, 3)), sigma_dot=rng.normal(size=(n, 3)),
        imu_R=rot(n), imu_p=rng.normal(size=(n, 3)), imu_v=rng.normal(size=(n, 3)),
        imu_a=rng.normal(size=(n, 3)), imu_w=rng.normal(size=(n, 3)),
        contact_active=active, contact_p=rng.normal(size=(n, c, 3)), contact_R=rot(n, c),
        gyro=rng.normal(size=(n, 3)), accel=rng.normal(size=(n, 3)),
        gravity=9.80665,
        meta={"scenario": "walk", "noise": {"gyro": 0.01, "accel": [0.1, 0.2]}, "effects": ["gyro-bias"]},
    )
    if full:
        ft = rng.normal(size=(n, c, 6))
        ft[:, 1, 3:] = np.nan  # right sensor measures forces only
        ft[5, 0, 2] = np.nan
        torso = rng.normal(size=(n, 7))
        torso[10:13] = np.nan  # markers lost
        wrench = rng.normal(size=(n, c, 6))
        wrench[~active] = 0.0
        kw.update(
            joint_names=JOINTS, joint_q=rng.normal(size=(n, 3)), joint_v=rng.normal(size=(n, 3)),
            ft=ft, mocap={"torso": torso}, base_pose=rng.normal(size=(n, 7)),
            truth=Truth(
                R=rot(n), t=rng.normal(size=(n, 3)), w=rng.normal(size=(n, 3)), v=rng.normal(size=(n, 3)),
                dw=rng.normal(size=(n, 3)), a=rng.normal(size=(n, 3)), wrench=wrench,
                external_wrench=rng.normal(size=(n, 6)), cop=rng.normal(size=(n, 3)),
                links={"l_hand": rng.normal(size=(n, 3)), "r_hand": rng.normal(size=(n, 3))},
                gyro_bias=rng.normal(size=(n, 3)), accel_bias=rng.normal(size=(n, 3)),
            ),
        )
    return Recording(**kw).validate()


def assert_same(a, b, name="", rot_tol=None):
    """Exact equality (NaN == NaN), dtypes included; ``rot_tol`` for rotations via quaternions."""
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray), name
        assert a.shape == b.shape and a.dtype == b.dtype, (name, a.shape, b.shape, a.dtype, b.dtype)
        if rot_tol is None:
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:
            np.testing.assert_allclose(b, a, rtol=0, atol=rot_tol, err_msg=name)
    elif isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b), name
        for key in a:
            assert_same(a[key], b[key], f"{name}[{key}]")
    elif dataclasses.is_dataclass(a):
        assert type(a) is type(b), name
        for f in dataclasses.fields(a):
            tol = 1e-12 if isinstance(a, Truth) and f.name == "R" else None
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{name}.{f.name}", tol)
    else:
        assert type(a) is type(b) and a == b, (name, a, b)


@pytest.fixture(scope="module")
def full_bag(tmp_path_factory):
    rec = make_recording()
    path = save_recording(rec, tmp_path_factory.mktemp("bags") / "full")
    return rec, path


def rewrite(src, dst, keep=lambda topic, i: True, edit=lambda topic, msg: msg):
    """Copy bag ``src`` to ``dst``, keeping message ``i`` of ``topic`` when ``keep`` says so."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    counts: dict[str, int] = {}
    conns = {}
    with AnyReader([src]) as reader, Writer(dst, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        for conn, t, raw in reader.messages():
            i = counts[conn.topic] = counts.get(conn.topic, -1) + 1
            if not keep(conn.topic, i):
                continue
            if conn.topic not in conns:
                conns[conn.topic] = writer.add_connection(conn.topic, conn.msgtype, typestore=ts)
            msg = edit(conn.topic, ts.deserialize_cdr(raw, conn.msgtype))
            writer.write(conns[conn.topic], t, ts.serialize_cdr(msg, conn.msgtype))
    return dst


# ------------------------------------------------------------------------------------------------
def test_full_round_trip(full_bag):
    rec, path = full_bag
    assert (path / "metadata.yaml").is_file() and (path / "full.mcap").is_file()
    back = load_recording(path)
    assert_same(rec, back, "rec")
    assert back.truth.gyro_bias is not None and np.isnan(back.ft[:, 1, 3:]).all()


def test_single_mcap_file_loads(full_bag):
    rec, path = full_bag
    assert_same(rec, load_recording(path / "full.mcap"), "rec")


def test_minimal_round_trip(tmp_path):
    rec = make_recording(n=12, full=False, seed=3)
    back = load_recording(save_recording(rec, tmp_path / "minimal"))
    assert back.truth is None and back.ft is None and back.joint_q is None and back.mocap == {}
    assert_same(rec, back, "rec")


def test_topics_use_standard_messages(full_bag):
    from rosbags.highlevel import AnyReader

    rec, path = full_bag
    with AnyReader([path]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {
            "/flexforce/meta": "std_msgs/msg/String", "/flexforce/inputs": "std_msgs/msg/Float64MultiArray",
            "/imu": "sensor_msgs/msg/Imu", "/joint_states": "sensor_msgs/msg/JointState",
            "/ft/left_foot": "geometry_msgs/msg/WrenchStamped", "/ft/right_foot": "geometry_msgs/msg/WrenchStamped",
            "/mocap/torso": "geometry_msgs/msg/PoseStamped", "/flexforce/base_pose": "geometry_msgs/msg/PoseStamped",
            "/truth/flexibility": "geometry_msgs/msg/PoseStamped",
            "/truth/velocity": "geometry_msgs/msg/TwistStamped",
            "/truth/acceleration": "geometry_msgs/msg/AccelStamped",
            "/truth/wrench/left_foot": "geometry_msgs/msg/WrenchStamped",
            "/truth/wrench/right_foot": "geometry_msgs/msg/WrenchStamped",
            "/truth/external_wrench": "geometry_msgs/msg/WrenchStamped",
            "/truth/cop": "geometry_msgs/msg/PointStamped",
            "/truth/link/l_hand": "geometry_msgs/msg/PointStamped",
            "/truth/link/r_hand": "geometry_msgs/msg/PointStamped",
            "/truth/gyro_bias": "geometry_msgs/msg/Vector3Stamped",
            "/truth/accel_bias": "geometry_msgs/msg/Vector3Stamped",
        }
        first = {}
        for conn, t, raw in reader.messages():
            if conn.topic not in first:
                first[conn.topic] = (t, reader.deserialize(raw, conn.msgtype))
    t0 = int(rec.t_ns[0])
    assert all(t == t0 for t, _ in first.values())
    imu = first["/imu"][1]
    assert imu.header.frame_id == "imu" and imu.orientation_covariance[0] == -1.0
    assert imu.header.stamp.sec * 10**9 + imu.header.stamp.nanosec == t0
    assert imu.angular_velocity.y == rec.gyro[0, 1] and imu.linear_acceleration.z == rec.accel[0, 2]
    assert first["/ft/right_foot"][1].header.frame_id == "right_foot"
    assert first["/truth/wrench/left_foot"][1].header.frame_id == "world"
    assert first["/mocap/torso"][1].header.frame_id == "world"
    q = first["/truth/flexibility"][1].pose.orientation
    np.testing.assert_allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), rec.truth.R[0],
                               atol=1e-12)
    layout = first["/flexforce/inputs"][1].layout
    assert [(d.label, d.size) for d in layout.dim] == inputs_layout(CONTACTS)
    assert layout.dim[-1].label == "contact/right_foot/R" and sum(d.size for d in layout.dim) == 54 + 13 * 2
    meta = json.loads(first["/flexforce/meta"][1].data)
    assert meta["version"] == 1 and meta["truth_links"] == ["l_hand", "r_hand"]
    assert meta["present"] == {"joint_q": True, "joint_v": True, "ft": True, "truth": True,
                               "gyro_bias": True, "accel_bias": True, "base_pose": True,
                               "ambient_wrench": False}


# ------------------------------------------------------------------------------------------------
def test_refuses_to_overwrite(tmp_path):
    rec = make_recording(n=5, full=False)
    path = save_recording(rec, tmp_path / "bag")
    with pytest.raises(BagError, match="exists already"):
        save_recording(rec, path)
    rec2 = make_recording(n=5, full=False, seed=1)
    assert_same(rec2, load_recording(save_recording(rec2, path, overwrite=True)), "rec")
    (tmp_path / "notabag").mkdir()
    (tmp_path / "notabag" / "precious.txt").write_text("keep me")
    with pytest.raises(BagError, match="not a ROS 2 bag"):
        save_recording(rec, tmp_path / "notabag", overwrite=True)
    assert (tmp_path / "notabag" / "precious.txt").exists()


def test_refuses_bad_names(tmp_path):
    rec = dataclasses.replace(make_recording(n=5, full=False), contact_names=("left foot", "right_foot"))
    with pytest.raises(BagError, match="'left foot' cannot be used in a ROS topic name"):
        save_recording(rec, tmp_path / "bag")
    assert not (tmp_path / "bag").exists()


def test_missing_path(tmp_path):
    with pytest.raises(BagError, match=r"nope does not exist; expected a ROS 2 bag"):
        load_recording(tmp_path / "nope")


@pytest.mark.parametrize("name", ["junk.mcap", "junk.bag", "junk.db3", "junk"])
def test_random_bytes(tmp_path, name):
    (tmp_path / name).write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(BagError, match="cannot read bag .*corrupt, truncated or not a bag") as info:
        load_recording(tmp_path / name)
    assert "\n" not in str(info.value)


def test_junk_directory(tmp_path):
    (tmp_path / "dir").mkdir()
    (tmp_path / "dir" / "metadata.yaml").write_text("{{{ not yaml")
    with pytest.raises(BagError, match="cannot read bag .*corrupt, truncated or not a bag"):
        load_recording(tmp_path / "dir")


def test_truncated_bag(full_bag, tmp_path):
    _, path = full_bag
    cut = tmp_path / "cut"
    shutil.copytree(path, cut)
    mcap = cut / "full.mcap"
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match="cannot read bag .*corrupt, truncated or not a bag"):
        load_recording(cut)
    with pytest.raises(BagError, match="cannot read bag .*corrupt, truncated or not a bag"):
        load_recording(mcap)


@pytest.mark.parametrize("drop", ["/flexforce/meta", "/flexforce/inputs"])
def test_not_a_flexforce_recording(full_bag, tmp_path, drop):
    _, path = full_bag
    raw = rewrite(path, tmp_path / "raw", keep=lambda topic, i: topic != drop)
    with pytest.raises(BagError, match=f"lacks {drop}: the bag is not a flexforce recording.*robot config"):
        load_recording(raw)


def test_sample_count_mismatch(full_bag, tmp_path):
    rec, path = full_bag
    short = rewrite(path, tmp_path / "short", keep=lambda topic, i: not (topic == "/imu" and i == rec.n - 1))
    with pytest.raises(BagError, match=f"sample count mismatch: topic /imu has {rec.n - 1} messages but "
                                       f"/flexforce/inputs has {rec.n}"):
        load_recording(short)


def test_missing_topic_listed_in_meta(full_bag, tmp_path):
    _, path = full_bag
    bag = rewrite(path, tmp_path / "nolink", keep=lambda topic, i: topic != "/truth/link/r_hand")
    with pytest.raises(BagError, match="lacks topic /truth/link/r_hand; expected it"):
        load_recording(bag)


def test_layout_mismatch(full_bag, tmp_path):
    _, path = full_bag

    def swap_contacts(topic, msg):
        if topic == "/flexforce/meta":
            doc = json.loads(msg.data)
            doc["contact_names"] = doc["contact_names"][::-1]
            msg.data = json.dumps(doc)
        return msg

    bag = rewrite(path, tmp_path / "swapped", edit=swap_contacts)
    with pytest.raises(BagError, match=r"/flexforce/inputs sample 0 has an unexpected layout "
                                       r"\(block contact/left_foot/active\[1\]\)"):
        load_recording(bag)


def test_topics_without_messages_are_named_as_such(tmp_path):
    """A bag whose topics are declared but hold no message: the error says so, not that they are missing."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(tmp_path / "empty", version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        writer.add_connection("/flexforce/meta", "std_msgs/msg/String", typestore=ts)
        writer.add_connection("/flexforce/inputs", "std_msgs/msg/Float64MultiArray", typestore=ts)
        writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=ts)
    with pytest.raises(BagError, match="topic /flexforce/meta and /flexforce/inputs of bag .*empty has no messages"):
        load_recording(tmp_path / "empty")
