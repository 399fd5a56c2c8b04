"""Recordings from bags and from scenarios: the two entry points :mod:`flexforce` re-exports.

A third way in, from plain arrays, is :meth:`flexforce.datasets.recording.Recording.from_arrays`.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from flexforce.errors import ConfigError

if TYPE_CHECKING:
    from flexforce.datasets.recording import Recording
    from flexforce.datasets.robot import RobotConfig
    from flexforce.datasets.sim.scenario import Scenario

__all__ = ["load_recording", "simulate"]


def load_recording(path: str | os.PathLike[str], robot: str | os.PathLike[str] | RobotConfig | None = None, *,
                   contacts: str = "ft", rate: float | None = None,
                   progress: Callable[[float], None] | None = None) -> Recording:
    """A validated Recording from a bag: flexforce's own, or a robot's raw bag imported.

    A flexforce bag (written by ``flexforce simulate`` or :func:`flexforce.datasets.io.bagio.save_recording`,
    recognised by its ``/flexforce/meta`` topic) is read as it was saved; it names its own robot
    and ``robot``, ``contacts`` and ``rate`` are not used.  Any other bag is imported onto a uniform
    grid through its robot configuration's ``[ros]`` table
    (:func:`flexforce.datasets.io.rosimport.import_bag`), as ``flexforce import`` does.

    Args:
        path: a ROS 2 bag directory, an ``.mcap`` or ``.db3`` file, or a ROS 1 ``.bag`` file.
        robot: a raw bag's robot: a built-in name (``"icub"``), a TOML path or a RobotConfig.
        contacts: a raw bag's contact detection, ``"ft"`` (thresholds on the F/T normal forces) or
            ``"fixed"`` (every contact always in force).
        rate: a raw bag's grid rate, Hz (default the robot's ``ros.rate``, else the IMU's median rate).
        progress: called with the fraction of a raw bag's import done (0..1).

    Raises:
        BagError: a missing or unreadable bag, a missing topic or a wrong message type.
        ConfigError: a raw bag without ``robot``, or a configuration the bag contradicts.
        DataError: data the import or :meth:`~flexforce.datasets.recording.Recording.validate` refuses.
    """
    from flexforce.datasets.io.bagio import load_recording as load_flexforce_bag
    from flexforce.datasets.io.rosimport import import_bag, is_flexforce_bag

    path = Path(path)
    if not path.exists() or is_flexforce_bag(path):
        return load_flexforce_bag(path)  # a missing path: its BagError names it
    if robot is None:
        raise ConfigError(f"{path} is a raw robot bag (no /flexforce/meta): expected its robot configuration, "
                          "robot=NAME, a TOML path or a RobotConfig (e.g. robot='icub')")
    return import_bag(path, robot, rate=rate, contacts=contacts, progress=progress)


def simulate(scenario: str | os.PathLike[str] | Scenario, *, seed: int | None = None, duration: float | None = None,
             robot: str | None = None, noise: bool | None = None,
             progress: Callable[[float], None] | None = None) -> Recording:
    """A simulated Recording, with its ground truth, of a scenario (pinocchio's multibody dynamics).

    Args:
        scenario: a built-in scenario's name (``"stand"``, ``"walk"``...: ``flexforce scenarios``
            lists them), a scenario ``.toml`` file or a :class:`~flexforce.datasets.sim.scenario.Scenario`
            (left unchanged).
        seed: the noise seed, replacing the scenario's (the same seed gives the same recording).
        duration: the length, s, replacing the scenario's.
        robot: the robot, a built-in name or a TOML path, replacing the scenario's.
        noise: False for exact readings and no ambient disturbance; None keeps the scenario's.
        progress: called with the fraction done (0..1).

    Raises:
        ConfigError: an unknown scenario, or a replaced value the scenario refuses (a duration that
            is not positive or ends before its walk).
    """
    from flexforce.datasets.sim.scenario import Scenario
    from flexforce.datasets.sim.simulator import Simulator

    base = scenario if isinstance(scenario, Scenario) else Scenario.load(os.fspath(scenario))
    overrides = {key: value for key, value in (("seed", seed), ("duration", duration), ("robot", robot))
                 if value is not None}
    if overrides:
        raw = copy.deepcopy({k: v for k, v in base.to_dict().items() if k != "source"})
        base = Scenario.from_dict({**raw, **overrides}, source=base.source)
    return Simulator(base, noise=noise).run(progress)
