"""Foxglove and PlotJuggler layouts for the bags that :func:`flexforce.datasets.io.export.export_mcap` writes.

A layout shows the estimate beside the inputs it was computed from, one tab per question:

========  ==================================================================================
tab       panels
========  ==================================================================================
feet      per contact, the estimated normal force F_z beside the F/T reading (when the robot
          has F/T sensors) and the ground truth (simulated bags); the total F_z (with its
          uncertainty band when the bag has one); the contact states (Foxglove only: a State
          Transitions strip per contact, off where its estimated force is exactly zero)
cop       centre of pressure x and y, estimated (with its band) and true
tilt      the flexibility's tilt (rotation vector x, y, rad) and sinking (t_z, m), estimated
          (with their bands) and true (t_z); the estimated angular velocity
imu       the gyrometer and accelerometer readings the estimators were given
mocap     when the bag holds ``/mocap/<link>`` poses: each link's position, and (Foxglove
          only) a 3-D panel of the links' poses beside the estimated flexibility, world frame
========  ==================================================================================

Uncertainty bands are the ``band/<q>/low|high`` topics an export carries with ``bands=True``
(the estimate -+ 2 standard deviations), drawn dashed in the estimate's colour.

The curves depend on the robot (its contact names, its F/T topics) and on the estimator
(``/estimate/<estimator>/...``), so the layouts are made for one robot and estimator
(:func:`render_layout`, :func:`layout_topics`), or for the topics of an exported bag
(:func:`layout_topics_of_bag`); ``flexforce layout`` is the command line face.  Foxglove layouts
are written in the foxglove-sdk's versioned format (``foxglove.layouts.Layout``:
:data:`FOXGLOVE_LAYOUT_VERSION`, a ``content`` tree of tab and split containers and panels);
PlotJuggler's from the template shipped with the package (``datasets/io/layouts/*.j2``).  The
F/T readings are in each sensor's frame, the estimate in the world: for a flat foot both F_z are
the normal force.

Topic names follow :mod:`flexforce.datasets.io.bagio` (``/imu``, ``/ft/<contact>``,
``/truth/...``) for flexforce bags, and the robot configuration's ``[ros]`` table
(``ft_topics``, ``imu_topic``) for raw robot bags.  The robot is never assumed: it is given, or
read from the bag (the export's description, :func:`flexforce.datasets.io.export.export_info`, or
a flexforce recording's ``/flexforce/meta``), else the layout is refused (:func:`bag_robot`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from flexforce.errors import BagError, ConfigError

__all__ = ["BANDS", "FOXGLOVE_LAYOUT_VERSION", "KINDS", "Curve", "LayoutTopics", "Plot", "bag_robot", "layout_topics",
           "layout_topics_of_bag", "panels", "render_layout", "topics_of_layout"]

KINDS = {"foxglove": ".json", "plotjuggler": ".xml"}
"""Layout kind -> suffix of its file."""

_INFO = "flexforce"
"""The key of the export's description (:data:`flexforce.datasets.io.export.INFO_KEY`)."""

COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f")


def _token(name: str) -> str:
    """A name as a topic token (the rule of :mod:`flexforce.datasets.io.export`)."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return token if re.match(r"^[A-Za-z]", token) else f"e_{token}"


@dataclass(frozen=True)
class LayoutTopics:
    """The topics a layout draws from."""

    estimator: str
    """Estimator name as a topic token (``ekf``, ``fixed_lag``, ``batch``)."""
    contacts: tuple[str, ...]
    """Contact names as topic tokens."""
    ft: dict[str, str] = field(default_factory=dict)
    """Contact token -> geometry_msgs/WrenchStamped topic of its F/T sensor."""
    imu: str | None = "/imu"
    """sensor_msgs/Imu topic of the readings, or None."""
    truth: bool = False
    """Whether the bag holds the simulator's ``/truth/...`` topics."""
    robot: str | None = None
    """Name of the robot configuration the topics were chosen for (not drawn)."""
    bands: tuple[str, ...] = ()
    """Quantities whose ``/estimate/<estimator>/band/<q>/low|high`` topics (the estimate -+ 2
    standard deviations, :func:`flexforce.datasets.io.export.export_mcap` with ``bands=True``)
    are drawn: a subset of :data:`BANDS`."""
    mocap: tuple[str, ...] = ()
    """geometry_msgs/PoseStamped topics of motion capture (``/mocap/<link>``, world frame) drawn
    as the reference."""

    @property
    def base(self) -> str:
        return f"/estimate/{self.estimator}"


BANDS = ("tilt", "position", "total_wrench", "cop")
"""The quantities an export can carry uncertainty bands of (``band/<q>/low|high`` topics)."""


@dataclass(frozen=True)
class Curve:
    """One series of a plot."""

    topic: str
    field: tuple[str, ...]
    """Path of a numeric field in the message (``("wrench", "force", "z")``); empty for a
    3-D panel's topic."""
    label: str
    band: bool = False
    """An edge of the uncertainty band of the curve before it: drawn dashed, in its colour."""


@dataclass(frozen=True)
class Plot:
    """One panel: a time plot, a contact-state strip or a 3-D view."""

    title: str
    curves: tuple[Curve, ...]
    kind: str = "plot"
    """``plot`` (values over time), ``states`` (Foxglove State Transitions: a contact is off where
    its estimated normal force is exactly zero, the estimators' contract for an inactive contact)
    or ``3d`` (Foxglove 3D panel of the curves' pose topics in the ``world`` frame).  PlotJuggler
    layouts hold the plots only."""


def layout_topics(robot, estimator: str = "ekf", ft: bool = True, truth: bool = False,
                  raw: bool | None = None, bands: bool = False) -> LayoutTopics:
    """The topics of an exported bag of ``robot`` (name, .toml path or RobotConfig).

    Args:
        robot: the robot configuration; required (None is a ConfigError: no robot is assumed).
        estimator: the estimator of ``flexforce run`` (``ekf``, ``fixed-lag``, ``batch``).
        ft: draw the F/T readings.
        truth: draw the ground truth (bags of ``flexforce simulate``).
        raw: the input was a raw robot bag, whose F/T and IMU topics are the robot configuration's
            ``[ros]`` table; default: when the configuration has one with F/T topics and ``truth``
            is not asked (simulated bags use ``/imu`` and ``/ft/<contact>``).
        bands: draw the uncertainty bands (:data:`BANDS`) of an export written with them.
    """
    from flexforce.datasets.robot import RobotConfig

    if robot is None or robot == "":
        raise ConfigError("a layout made without a bag needs the robot: its contacts and F/T topics; expected "
                          "--robot NAME|CONFIG.toml (e.g. --robot icub), or --bag OUT.mcap of 'flexforce run'")
    config = RobotConfig.load(robot)
    contacts = tuple(_token(c.name) for c in config.contacts)
    ros = config.ros
    if raw is None:
        raw = ros is not None and bool(ros.ft_topics) and not truth
    if raw and ros is None:
        raise ConfigError(f"robot {config.name} has no [ros] table: its raw bags' topics are unknown; expected a "
                          "configuration with [ros] (or the topics of a flexforce bag)")
    imu = ros.imu_topic if raw and ros is not None else "/imu"
    ft_topics: dict[str, str] = {}
    if ft:
        if raw and ros is not None:
            ft_topics = {_token(c): t for c, t in ros.ft_topics.items() if _token(c) in contacts}
        else:
            ft_topics = {c: f"/ft/{c}" for c in contacts}
    return LayoutTopics(estimator=_token(str(estimator).replace("-", "_").lower()), contacts=contacts, ft=ft_topics,
                        imu=imu, truth=truth, robot=config.name, bands=BANDS if bands else ())


def bag_topics(path) -> dict[str, str]:
    """Topic -> message type of a bag (ROS 1 or 2)."""
    from rosbags.highlevel import AnyReader

    path = Path(path)
    if not path.exists():
        raise BagError(f"bag {path} does not exist; expected the output of 'flexforce run ... -o OUT.mcap'")
    try:
        with AnyReader([path]) as reader:
            return {c.topic: c.msgtype for c in reader.connections}
    except Exception as err:  # noqa: BLE001 -- an unreadable bag: one line
        raise BagError(f"cannot read bag {path}: {' '.join(str(err).split()) or type(err).__name__}") from err


def bag_robot(path, topics: dict[str, str] | None = None) -> str | None:
    """The robot configuration (built-in name or ``.toml`` path) a bag says it was recorded or
    exported for: the export's description (:func:`flexforce.datasets.io.export.export_info`),
    else the ``robot`` of a flexforce recording's ``/flexforce/meta``; None when it says neither.

    Args:
        topics: the bag's topic -> message type (:func:`bag_topics`), if already read.

    Raises:
        BagError: a missing or unreadable bag.
    """
    import json

    from flexforce.datasets.io.bagio import META_TOPIC
    from flexforce.datasets.io.export import export_info

    path = Path(path)
    topics = bag_topics(path) if topics is None else topics
    robot = export_info(path).get("robot")
    if robot:
        return str(robot)
    if META_TOPIC not in topics:
        return None
    from rosbags.highlevel import AnyReader

    try:
        with AnyReader([path]) as reader:
            conns = [c for c in reader.connections if c.topic == META_TOPIC]
            for conn, _, raw in reader.messages(connections=conns):
                msg: Any = reader.deserialize(raw, conn.msgtype)  # std_msgs/String
                doc = json.loads(msg.data)
                return str(doc["robot"]) if isinstance(doc, dict) and doc.get("robot") else None
    except Exception as err:  # noqa: BLE001 -- an unreadable description: one line
        raise BagError(f"cannot read {META_TOPIC} of bag {path}: {' '.join(str(err).split()) or type(err).__name__}"
                       ) from err
    return None


def _bag_robot_config(path, topics: dict[str, str], robot=None):
    """The robot configuration of ``robot`` when given, else of the robot the bag names; a
    ConfigError when neither says (no robot is assumed)."""
    from flexforce.datasets.robot import RobotConfig

    if robot is not None and robot != "":
        return RobotConfig.load(robot)
    named = bag_robot(path, topics)
    if named is None:
        raise ConfigError(f"bag {path} does not say which robot it holds (no robot in its '{_INFO}' metadata, "
                          "no /flexforce/meta topic): its F/T and IMU topics are unknown; expected --robot "
                          "NAME|CONFIG.toml (e.g. --robot icub)")
    try:
        return RobotConfig.load(named)
    except ConfigError as err:
        raise ConfigError(f"bag {path} names robot {named!r}, which cannot be loaded here ({err}); expected "
                          "--robot NAME|CONFIG.toml") from err


def layout_topics_of_bag(path, robot=None) -> LayoutTopics:
    """The topics of a bag written by ``flexforce run ... -o OUT.mcap``, read from the bag itself.

    The estimator and the contacts come from its ``/estimate/<estimator>/wrench/<contact>`` topics;
    F/T readings are ``/ft/<contact>`` topics, or those of the robot configuration's
    ``[ros] ft_topics`` (and ``imu_topic``) that the bag holds; uncertainty bands are drawn for the
    ``band/`` topics it holds, motion capture for its ``/mocap/<link>`` poses.  The robot is
    ``robot`` when given, else the one the bag names (:func:`bag_robot`).

    Raises:
        BagError: a missing or unreadable bag, one without ``/estimate/<estimator>/`` topics or
            with several estimators'.
        ConfigError: neither ``robot`` nor the bag names the robot, or its configuration cannot
            be loaded.
    """
    topics = bag_topics(path)
    found = sorted({m[1] for t in topics if (m := re.match(r"^/estimate/([^/]+)/", t))})
    if not found:
        raise BagError(f"bag {path} holds no /estimate/<estimator>/ topics; expected a bag written by "
                       "'flexforce run REC -o OUT.mcap'")
    if len(found) > 1:
        raise BagError(f"bag {path} holds the estimates of {', '.join(found)}; expected one estimator per bag")
    est = found[0]
    contacts = tuple(m[1] for t in sorted(topics) if (m := re.match(rf"^/estimate/{est}/wrench/([^/]+)$", t)))
    wrench = "geometry_msgs/msg/WrenchStamped"
    ft = {c: f"/ft/{c}" for c in contacts if topics.get(f"/ft/{c}") == wrench}
    imu: str | None = "/imu"
    config = _bag_robot_config(path, topics, robot)
    ros = config.ros
    if ros is not None:
        ft.update({_token(c): t for c, t in ros.ft_topics.items() if _token(c) in contacts
                   and topics.get(t) == wrench})
        if ros.imu_topic in topics:
            imu = ros.imu_topic
    if topics.get(imu or "") != "sensor_msgs/msg/Imu":
        imu = None
    truth = "/truth/cop" in topics
    bands = tuple(q for q in BANDS if f"/estimate/{est}/band/{q}/low" in topics
                  and f"/estimate/{est}/band/{q}/high" in topics)
    mocap = tuple(t for t in sorted(topics) if t.startswith("/mocap/")
                  and topics[t] == "geometry_msgs/msg/PoseStamped")
    return LayoutTopics(estimator=est, contacts=contacts, ft=ft, imu=imu, truth=truth, robot=config.name,
                        bands=bands, mocap=mocap)


def panels(topics: LayoutTopics) -> list[tuple[str, list[Plot]]]:
    """The tabs of a layout: (tab name, panels), each panel a list of curves (module docstring)."""
    b = topics.base

    def band(quantity: str, field: tuple[str, ...], label: str) -> list[Curve]:
        if quantity not in topics.bands:
            return []
        return [Curve(f"{b}/band/{quantity}/{side}", field, f"{label} {side} (2 sigma)", band=True)
                for side in ("low", "high")]

    feet = []
    for c in topics.contacts:
        curves = [Curve(f"{b}/wrench/{c}", ("wrench", "force", "z"), f"{c} F_z estimated")]
        if c in topics.ft:
            curves.append(Curve(topics.ft[c], ("wrench", "force", "z"), f"{c} F_z F/T (sensor frame)"))
        if topics.truth:
            curves.append(Curve(f"/truth/wrench/{c}", ("wrench", "force", "z"), f"{c} F_z truth"))
        feet.append(Plot(f"{c}: normal force [N]", tuple(curves)))
    # the simulator writes per-contact truth wrenches only: the total is the estimate's
    total_field = ("wrench", "force", "z")
    feet.append(Plot("total normal force [N]", (Curve(f"{b}/total_wrench", total_field, "total F_z estimated"),
                                                *band("total_wrench", total_field, "total F_z"))))
    feet.append(Plot("contact states (off: estimated normal force exactly zero)",
                     tuple(Curve(f"{b}/wrench/{c}", ("wrench", "force", "z"), c) for c in topics.contacts),
                     kind="states"))
    cop = []
    for ax in "xy":
        curves = [Curve(f"{b}/cop", ("point", ax), f"CoP {ax} estimated"), *band("cop", ("point", ax), f"CoP {ax}")]
        if topics.truth:
            curves.append(Curve("/truth/cop", ("point", ax), f"CoP {ax} truth"))
        cop.append(Plot(f"centre of pressure {ax} [m]", tuple(curves)))
    tilt_curves = []
    for ax, name in (("x", "roll"), ("y", "pitch")):
        tilt_curves += [Curve(f"{b}/tilt", ("vector", ax), f"tilt {ax} ({name}) estimated"),
                        *band("tilt", ("vector", ax), f"tilt {ax}")]
    tilt = [Plot("tilt: rotation vector [rad]", tuple(tilt_curves))]
    sink = [Curve(f"{b}/flexibility", ("pose", "position", "z"), "t_z estimated"),
            *band("position", ("point", "z"), "t_z")]
    if topics.truth:
        sink.append(Curve("/truth/flexibility", ("pose", "position", "z"), "t_z truth"))
    tilt.append(Plot("sinking t_z [m]", tuple(sink)))
    tilt.append(Plot("angular velocity [rad/s]", tuple(Curve(f"{b}/velocity", ("twist", "angular", ax),
                                                             f"w_{ax} estimated") for ax in "xyz")))
    tabs = [("feet", feet), ("cop", cop), ("tilt", tilt)]
    if topics.imu:
        tabs.append(("imu", [
            Plot("gyrometer [rad/s]", tuple(Curve(topics.imu, ("angular_velocity", ax), f"gyro {ax}") for ax in "xyz")),
            Plot("accelerometer [m/s^2]", tuple(Curve(topics.imu, ("linear_acceleration", ax), f"accel {ax}")
                                                for ax in "xyz"))]))
    if topics.mocap:
        mocap = [Plot(f"{t.removeprefix('/mocap/')}: motion-capture position (world) [m]",
                      tuple(Curve(t, ("pose", "position", ax), f"{t.removeprefix('/mocap/')} {ax}") for ax in "xyz"))
                 for t in topics.mocap]
        mocap.append(Plot("3-D: motion-capture poses and the estimated flexibility (world frame)",
                          (*(Curve(t, (), t.removeprefix("/mocap/")) for t in topics.mocap),
                           Curve(f"{b}/flexibility", (), "flexibility estimated")), kind="3d"))
        tabs.append(("mocap", mocap))
    return tabs


def _environment():
    import jinja2

    return jinja2.Environment(loader=jinja2.PackageLoader("flexforce.datasets.io", "layouts"),
                              autoescape=jinja2.select_autoescape(enabled_extensions=("xml",),
                                                                  default_for_string=False),
                              undefined=jinja2.StrictUndefined, keep_trailing_newline=True)


FOXGLOVE_LAYOUT_VERSION = 1
"""``version`` of the Foxglove layouts written: the versioned format of the foxglove-sdk's
``foxglove.layouts.Layout`` (``{"version", "content"}``, containers ``tabs``/``split``, panels
``{"type": "panel", "panelType", "title", "version", "config"}``)."""


def _foxglove_panel(entry: dict) -> dict:
    """One panel of the versioned Foxglove layout."""
    common = {"type": "panel", "title": entry["title"], "version": 1}
    if entry["kind"] == "3d":
        topics = {c["topic"]: {"visible": True, "type": "axis", "axisScale": 0.2} for c in entry["curves"]}
        return {**common, "panelType": "ThreeDee",
                "config": {"followTf": "world", "fixedFrame": "world", "topics": topics,
                           "layers": {"grid": {"layerId": "foxglove.Grid", "visible": True}}}}
    paths = []
    for c in entry["curves"]:
        path = {"value": c["topic"] + "." + ".".join(c["field"]), "label": c["label"], "enabled": True,
                "timestampMethod": "receiveTime"}
        if entry["kind"] == "states":
            path["customStates"] = {"type": "range",
                                    "states": [{"value": 0, "operator": "=", "label": "off", "color": "#7f7f7f"}],
                                    "otherwise": {"label": "in contact", "color": c["color"]}}
        else:
            path["color"] = c["color"]
            if c["band"]:
                path.update(lineStyle="dashed", lineSize=1)
        paths.append(path)
    if entry["kind"] == "states":
        return {**common, "panelType": "StateTransitions", "config": {"paths": paths, "isSynced": True}}
    return {**common, "panelType": "Plot",
            "config": {"paths": paths, "showXAxisLabels": True, "showYAxisLabels": True, "showLegend": True,
                       "legendDisplay": "floating", "showPlotValuesInLegend": False, "isSynced": True,
                       "xAxisVal": "timestamp"}}


def _foxglove(tabs: list[dict]) -> str:
    """The versioned Foxglove layout (:data:`FOXGLOVE_LAYOUT_VERSION`): one tab container, one tab
    per question, its panels stacked in a column."""
    import json

    content = {"type": "tabs", "selectedTabIndex": 0, "tabs": [
        {"title": tab["name"], "content": {"type": "split", "direction": "column", "items": [
            {"proportion": 1, "content": _foxglove_panel(entry)} for entry in tab["plots"]]}}
        for tab in tabs]}
    return json.dumps({"version": FOXGLOVE_LAYOUT_VERSION, "content": content}, indent=2) + "\n"


def render_layout(kind: str, topics: LayoutTopics) -> str:
    """The text of a ``kind`` layout (:data:`KINDS`) for ``topics``: Foxglove's versioned JSON
    (:data:`FOXGLOVE_LAYOUT_VERSION`), or PlotJuggler's XML (its plots only)."""
    if kind not in KINDS:
        raise ConfigError(f"unknown layout kind {kind!r}; expected one of {', '.join(KINDS)}")
    tabs = []
    n = 0
    for name, plots in panels(topics):
        entries = []
        for plot in plots:
            if kind == "plotjuggler" and plot.kind != "plot":
                continue
            n += 1
            curves = []
            color = COLORS[0]
            index = 0
            for c in plot.curves:
                if not c.band:
                    color = COLORS[index % len(COLORS)]
                    index += 1
                curves.append({"topic": c.topic, "field": c.field, "label": c.label, "color": color, "band": c.band})
            entries.append({"id": f"Plot!ff{n}", "title": plot.title, "kind": plot.kind, "curves": curves})
        if entries:
            tabs.append({"name": name, "plots": entries})
    if kind == "foxglove":
        return _foxglove(tabs)
    template = _environment().get_template(f"{kind}{KINDS[kind]}.j2")
    return template.render(tabs=tabs, estimator=topics.estimator)


def _foxglove_series(node) -> list[str]:
    """The message paths of every Plot and State Transitions series under ``node`` (a versioned
    layout's content, or an older layout's ``configById``)."""
    out: list[str] = []
    if isinstance(node, dict):
        if node.get("type") == "panel" and node.get("panelType") in ("Plot", "StateTransitions"):
            return [p["value"] for p in node.get("config", {}).get("paths", [])]
        for value in node.values():
            out += _foxglove_series(value)
    elif isinstance(node, list):
        for value in node:
            out += _foxglove_series(value)
    return out


def topics_of_layout(kind: str, text: str, known: set[str] | dict | None = None) -> set[tuple[str, tuple[str, ...]]]:
    """(topic, field path) of every series (plot curve, contact state) a rendered layout names,
    read back from its text (3-D panels' topics are not series).

    A PlotJuggler curve is one string (``/topic/field/...``): it is split after the longest of the
    ``known`` topics it starts with (the whole string is the topic when none does).
    """
    import json
    import xml.etree.ElementTree as ET

    out = set()
    if kind == "foxglove":
        data = json.loads(text)
        if "configById" in data:  # the unversioned format: panel id -> config
            values = [p["value"] for c in data["configById"].values() for p in c.get("paths", [])]
        else:
            values = _foxglove_series(data.get("content"))
        for value in values:
            topic, *fields = value.split(".")
            out.add((topic, tuple(fields)))
    elif kind == "plotjuggler":
        for curve in ET.fromstring(text).iter("curve"):
            name = curve.attrib["name"]
            topic = max((t for t in (known or ()) if name.startswith(t + "/")), key=len, default=name)
            out.add((topic, tuple(name[len(topic) + 1:].split("/")) if topic != name else ()))
    else:
        raise ConfigError(f"unknown layout kind {kind!r}; expected one of {', '.join(KINDS)}")
    return out

