"""Foxglove and PlotJuggler layouts name only topics and fields that the exported bag holds."""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET

import pytest

from flexforce.cli import main
from flexforce.compare.estimators import run_estimator
from flexforce.datasets.io.bagio import save_recording
from flexforce.datasets.io.export import export_mcap
from flexforce.datasets.io.viewers import (
    KINDS,
    bag_topics,
    layout_topics,
    layout_topics_of_bag,
    render_layout,
    topics_of_layout,
)
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A 0.4 s simulated recording saved as a bag (with its truth), the EKF run on it and exported."""
    tmp = tmp_path_factory.mktemp("viewers")
    sc = Scenario.load("push-pitch")
    sc.duration = 0.4
    rec = Simulator(sc).run()
    bag = save_recording(rec, tmp / "rec")
    est = run_estimator("ekf", rec)
    return export_mcap(est, bag, tmp / "rec-ekf.mcap")


def first_messages(bag) -> dict:
    """Topic -> its first message, deserialised."""
    from rosbags.highlevel import AnyReader

    out: dict = {}
    with AnyReader([bag]) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic not in out:
                out[conn.topic] = reader.deserialize(raw, conn.msgtype)
    return out


def check_layout(kind, text, bag) -> set[str]:
    """Every curve of the layout is a numeric field of a topic of ``bag``; returns the topics named."""
    topics = bag_topics(bag)
    messages = first_messages(bag)
    curves = topics_of_layout(kind, text, topics)
    assert curves
    for topic, fields in curves:
        assert topic in topics, f"{kind} layout names {topic}, which the export does not write"
        value = messages[topic]
        for name in fields:
            assert hasattr(value, name), f"{topic}: no field {'.'.join(fields)}"
            value = getattr(value, name)
        assert isinstance(value, float) and math.isfinite(value), (topic, fields, value)
    return {t for t, _ in curves}


@pytest.mark.parametrize("kind", list(KINDS))
def test_layouts_name_only_exported_topics(exported, kind):
    from_bag = render_layout(kind, layout_topics_of_bag(exported))
    from_robot = render_layout(kind, layout_topics("romeo", "ekf", truth=True))
    assert from_bag == from_robot
    named = check_layout(kind, from_bag, exported)
    # the estimate beside the inputs: forces per foot with F/T and truth, CoP, tilt, IMU
    for topic in ("/estimate/ekf/wrench/left_foot", "/estimate/ekf/wrench/right_foot", "/ft/left_foot",
                  "/truth/wrench/right_foot", "/estimate/ekf/cop", "/truth/cop", "/estimate/ekf/tilt", "/imu"):
        assert topic in named, topic
    # a layout for another estimator's export names that estimator's topics, which this bag lacks
    topics = bag_topics(exported)
    other = topics_of_layout(kind, render_layout(kind, layout_topics("romeo", "batch")), topics)
    missing = {t for t, _ in other if t not in topics}
    assert missing and all(t.startswith("/estimate/batch/") for t in missing), missing
    with pytest.raises(AssertionError, match="which the export does not write"):
        check_layout(kind, render_layout(kind, layout_topics("romeo", "batch")), exported)


def test_layout_files_parse_and_hold_one_tab_per_question(exported):
    fox = json.loads(render_layout("foxglove", layout_topics_of_bag(exported)))
    assert fox["version"] == 1 and fox["content"]["type"] == "tabs"  # foxglove-sdk's versioned format
    tabs = fox["content"]["tabs"]
    assert [t["title"] for t in tabs] == ["feet", "cop", "tilt", "imu"]
    for tab in tabs:  # each tab: its panels in one column
        assert tab["content"]["type"] == "split" and tab["content"]["direction"] == "column"
        for item in tab["content"]["items"]:
            panel = item["content"]
            assert item["proportion"] > 0 and panel["type"] == "panel" and panel["version"] == 1
            assert panel["panelType"] in ("Plot", "StateTransitions", "ThreeDee") and panel["title"]
    pj = ET.fromstring(render_layout("plotjuggler", layout_topics_of_bag(exported)))
    assert [t.attrib["tab_name"] for t in pj.iter("Tab")] == ["feet", "cop", "tilt", "imu"]
    for splitter in pj.iter("DockSplitter"):
        assert int(splitter.attrib["count"]) == len(splitter.findall("DockArea"))


def test_raw_robot_layout_takes_the_ros_topics():
    topics = layout_topics("icub", "fixed-lag")
    assert topics.estimator == "fixed_lag"
    assert topics.ft == {"left_foot": "/left_foot/wrench", "right_foot": "/right_foot/wrench"}
    text = render_layout("plotjuggler", topics)
    assert 'name="/left_foot/wrench/wrench/force/z"' in text and "/truth/" not in text
    assert "/ft/" not in render_layout("foxglove", layout_topics("icub", truth=True, ft=False))


def test_cli_layout(exported, tmp_path, capsys):
    out = tmp_path / "view.json"
    assert main(["layout", "foxglove", "--bag", str(exported), "-o", str(out)]) == 0
    assert "left_foot, right_foot" in capsys.readouterr().out
    check_layout("foxglove", out.read_text(), exported)
    out = tmp_path / "view.xml"
    assert main(["layout", "plotjuggler", "--robot", "romeo", "--truth", "-o", str(out)]) == 0
    check_layout("plotjuggler", out.read_text(), exported)
    # bad input: one line, status 1
    assert main(["layout", "foxglove", "--bag", str(tmp_path / "none.mcap"), "-o", str(tmp_path / "a.json")]) == 1
    assert "does not exist" in capsys.readouterr().err
    assert main(["layout", "foxglove", "--robot", "romeo", "-o", str(tmp_path / "a.xml")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("flexforce layout: error:") and ".json" in err and err.count("\n") == 1
    assert main(["layout", "plotjuggler", "--bag", str(exported), "--truth", "-o", str(tmp_path / "b.xml")]) == 1
    assert "--bag reads" in capsys.readouterr().err
    assert main(["layout", "plotjuggler", "--robot", "nobody", "-o", str(tmp_path / "b.xml")]) == 1
    assert "unknown robot 'nobody'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        main(["layout", "rviz", "-o", str(tmp_path / "c.json")])
    assert exit_.value.code == 2


def test_a_bag_without_an_estimate_is_refused(exported, tmp_path):
    from flexforce.errors import BagError

    bag = exported.parent / "rec"
    with pytest.raises(BagError, match="no /estimate/<estimator>/ topics"):
        layout_topics_of_bag(bag)


def test_layout_of_a_streamed_fixed_lag_run(exported, tmp_path, capsys):
    """`flexforce run --estimator fixed-lag -o OUT.mcap` streams its estimates into the bag: the
    layout made for the robot and estimator names only topics that bag holds."""
    rec_bag = exported.parent / "rec"
    out = tmp_path / "fl.mcap"
    assert main(["run", str(rec_bag), "--estimator", "fixed-lag", "--lag", "0.2", "-o", str(out), "-q"]) == 0, \
        capsys.readouterr().err
    topics = layout_topics_of_bag(out)
    assert topics.estimator == "fixed_lag" and topics.contacts == ("left_foot", "right_foot")
    for kind in KINDS:
        text = render_layout(kind, topics)
        named = check_layout(kind, text, out)
        assert "/estimate/fixed_lag/tilt" in named
        assert "/estimate/fixed_lag/band/tilt/low" in named  # the streamed estimate's uncertainty bands
        # the streamed run writes the sensor topics of a flexforce bag (no /truth/...)
        if not topics.truth:
            assert text == render_layout(kind, layout_topics("romeo", "fixed-lag"))


def test_run_into_a_bag_writes_the_bands_the_layout_draws(exported, tmp_path, capsys):
    """`flexforce run REC -o OUT.mcap` writes the estimate's uncertainty bands (the ``band/`` topics);
    `flexforce layout foxglove --bag OUT.mcap` draws each of them."""
    from flexforce.datasets.io.viewers import BANDS

    out, layout = tmp_path / "ekf.mcap", tmp_path / "ekf.json"
    assert main(["run", str(exported.parent / "rec"), "--estimator", "ekf", "-o", str(out), "-q"]) == 0, \
        capsys.readouterr().err
    assert {f"/estimate/ekf/band/{q}/{side}" for q in BANDS for side in ("low", "high")} <= set(bag_topics(out))
    assert main(["layout", "foxglove", "--bag", str(out), "-o", str(layout)]) == 0, capsys.readouterr().err
    named = check_layout("foxglove", layout.read_text(), out)
    for q in BANDS:
        assert {f"/estimate/ekf/band/{q}/low", f"/estimate/ekf/band/{q}/high"} <= named, q
    paths = [p["value"] for tab in json.loads(layout.read_text())["content"]["tabs"]
             for item in tab["content"]["items"] for p in item["content"]["config"].get("paths", [])]
    assert "/estimate/ekf/band/total_wrench/high.wrench.force.z" in paths


@pytest.mark.parametrize("robot", ["talos", "icub"])
def test_the_bag_names_its_robot(tmp_path, robot):
    """A bag exported for a simulated recording of ``robot`` gives that robot's layout, no --robot asked."""
    from flexforce.datasets.robot import RobotConfig

    sc = Scenario.load("stand")
    sc.duration = 0.3
    sc.robot = robot
    rec = Simulator(sc).run()
    out = export_mcap(run_estimator("ekf", rec), rec, tmp_path / f"{robot}.mcap")
    topics = layout_topics_of_bag(out)
    config = RobotConfig.load(robot)
    assert topics.robot == robot and topics.contacts == tuple(c.name for c in config.contacts)
    assert topics.ft == {c: f"/ft/{c}" for c in topics.contacts}
    check_layout("foxglove", render_layout("foxglove", topics), out)


def test_a_raw_icub_bag_shows_its_ft_topics(tmp_path, capsys):
    """The issue's case: the export of a raw iCub bag draws the F/T of the configuration's [ros]
    table, the robot read from the export's description."""
    import numpy as np
    from test_export import T0, make_estimate
    from test_rosimport import write_bag

    t = T0 + np.arange(20, dtype=np.int64) * 10_000_000
    raw = {"/imu": ("sensor_msgs/msg/Imu", [(tt, {"gyro": [0, 0, 0], "accel": [0, 0, 9.8], "frame": "imu"})
                                            for tt in t])}
    for side in ("left", "right"):
        raw[f"/{side}_foot/wrench"] = ("geometry_msgs/msg/WrenchStamped",
                                       [(tt, {"w": [0, 0, 150.0, 0, 0, 0], "frame": f"{side[0]}_sole"}) for tt in t])
    src = write_bag(tmp_path / "raw", "mcap", raw)
    out = export_mcap(make_estimate(t, name="ekf"), src, tmp_path / "icub-ekf.mcap", robot="icub")
    topics = layout_topics_of_bag(out)
    assert topics.robot == "icub"
    assert topics.ft == {"left_foot": "/left_foot/wrench", "right_foot": "/right_foot/wrench"}
    assert "/right_foot/wrench" in check_layout("foxglove", render_layout("foxglove", topics), out)
    layout = tmp_path / "icub.json"
    assert main(["layout", "foxglove", "--bag", str(out), "-o", str(layout)]) == 0
    assert "robot icub" in capsys.readouterr().out and "/left_foot/wrench" in layout.read_text()


def test_a_bag_that_names_no_robot_is_refused(tmp_path, capsys):
    """No robot in the bag and none given: a ConfigError saying what is missing and how to give it."""
    import numpy as np
    from test_export import T0, make_estimate

    from flexforce.errors import ConfigError

    out = export_mcap(make_estimate(T0 + np.arange(10) * 10_000_000, name="ekf"), None, tmp_path / "anon.mcap")
    with pytest.raises(ConfigError, match=r"does not say which robot.*expected --robot NAME\|CONFIG.toml"):
        layout_topics_of_bag(out)
    assert main(["layout", "foxglove", "--bag", str(out), "-o", str(tmp_path / "a.json")]) == 1
    err = capsys.readouterr().err
    assert "does not say which robot" in err and "--robot" in err and err.count("\n") == 1
    assert not (tmp_path / "a.json").exists()
    assert layout_topics_of_bag(out, "talos").robot == "talos"
    with pytest.raises(ConfigError, match="needs the robot"):
        layout_topics(None)
    assert main(["layout", "foxglove", "-o", str(tmp_path / "b.json")]) == 1
    assert "expected --robot" in capsys.readouterr().err


@pytest.fixture(scope="module")
def banded(tmp_path_factory):
    """0.3 s of push-pitch with a motion-capture link, the EKF exported with its uncertainty bands."""
    import dataclasses

    import numpy as np

    sc = Scenario.load("push-pitch")
    sc.duration = 0.3
    rec = Simulator(sc).run()
    pose = np.zeros((rec.n, 7))
    pose[:, 2], pose[:, 6] = 0.9, 1.0
    rec = dataclasses.replace(rec, mocap={"root_link": pose})
    est = run_estimator("ekf", rec)
    return est, export_mcap(est, rec, tmp_path_factory.mktemp("banded") / "ekf.mcap", bands=True)


def test_bands_contact_states_and_mocap_of_a_bag(banded):
    from flexforce.datasets.io.viewers import BANDS

    _, bag = banded
    topics = layout_topics_of_bag(bag)
    assert topics.bands == BANDS and topics.mocap == ("/mocap/root_link",)
    for kind in KINDS:
        named = check_layout(kind, render_layout(kind, topics), bag)
        for q in BANDS:
            assert {f"/estimate/ekf/band/{q}/low", f"/estimate/ekf/band/{q}/high"} <= named, (kind, q)
        assert "/mocap/root_link" in named
    fox = json.loads(render_layout("foxglove", topics))
    tabs = {t["title"]: [i["content"] for i in t["content"]["items"]] for t in fox["content"]["tabs"]}
    assert list(tabs) == ["feet", "cop", "tilt", "imu", "mocap"]
    states = [p for p in tabs["feet"] if p["panelType"] == "StateTransitions"]
    assert len(states) == 1
    paths = states[0]["config"]["paths"]
    assert [p["value"] for p in paths] == [f"/estimate/ekf/wrench/{c}.wrench.force.z" for c in topics.contacts]
    assert all(p["customStates"]["states"] == [{"value": 0, "operator": "=", "label": "off", "color": "#7f7f7f"}]
               for p in paths)
    tilt = next(p for p in tabs["tilt"] if p["title"].startswith("tilt"))["config"]["paths"]
    estimate, low, high = tilt[:3]  # tilt x, then its band, drawn dashed in the estimate's colour
    assert estimate["value"] == "/estimate/ekf/tilt.vector.x" and low["value"] == "/estimate/ekf/band/tilt/low.vector.x"
    assert low["color"] == high["color"] == estimate["color"] and low["lineStyle"] == "dashed"
    three = [p for p in tabs["mocap"] if p["panelType"] == "ThreeDee"]
    assert len(three) == 1 and set(three[0]["config"]["topics"]) == {"/mocap/root_link", "/estimate/ekf/flexibility"}
    assert three[0]["config"]["followTf"] == "world"
    # PlotJuggler has no state or 3-D panel: its plots only
    pj = render_layout("plotjuggler", topics)
    assert "contact states" not in pj and "3-D" not in pj and "/estimate/ekf/band/cop/high" in pj


def test_a_layout_from_the_robot_draws_bands_when_asked():
    plain = render_layout("foxglove", layout_topics("romeo", "batch"))
    banded = render_layout("foxglove", layout_topics("romeo", "batch", bands=True))
    assert "/band/" not in plain and "/estimate/batch/band/total_wrench/high.wrench.force.z" in banded


def test_an_unversioned_foxglove_layout_is_still_read():
    text = json.dumps({"configById": {"Plot!a": {"paths": [{"value": "/imu.angular_velocity.x"}]}}, "layout": "Plot!a"})
    assert topics_of_layout("foxglove", text) == {("/imu", ("angular_velocity", "x"))}
