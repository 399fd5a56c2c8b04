"""Running a recording end to end: the library functions behind ``flexforce run`` and friends.

A recording is opened (a flexforce bag, a raw robot bag imported with its robot configuration, or
a scenario simulated), cut to a window, and one estimator run on it into a file: the whole
recording at once (:func:`run_offline`), or part by part in bounded memory, the fixed-lag
smoother's estimates written as they leave its window (:func:`stream_recording`).
:func:`run_recording` chooses as ``flexforce run`` does (:func:`streams`).

Progress is reported through a *progress factory*: called with a stage's label (``"import
walk.mcap"``, ``"simulate stand #3"``, ``"fixed-lag"``, ``"fixed-lag (stream)"``) when the stage
starts, it returns the callable given the stage's fraction done (0..1).

This layer sits above the estimators, the I/O and the simulator and may import all of them.
"""

from __future__ import annotations

import itertools
import os
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flexforce.errors import ConfigError

__all__ = ["STREAM_PART_SECONDS", "RunConfig", "RunResult", "demo_listing", "demo_options",
           "demo_while_awaiting", "load_or_simulate", "open_recording",
           "prepare_demo_kernels", "run_offline", "run_recording", "stream_parts", "stream_recording", "streams",
           "warm_up", "window", "window_parts", "write_estimate"]

ProgressFactory = Callable[[str], Callable[[float], None]]
"""A stage's label -> the callable given its fraction done (module docstring)."""

STREAM_PART_SECONDS = 0.5
"""Length, s, of the parts a loaded (flexforce) recording is streamed in."""

_RAW_BAG = ("{path} is a raw robot bag (no /flexforce/meta): give its robot configuration with "
            "--robot NAME|CONFIG.toml (e.g. --robot icub)")


@dataclass(frozen=True)
class RunConfig:
    """How :func:`run_recording` runs one estimator on a recording (the options of ``flexforce run``)."""

    estimator: str = "ekf"
    """``ekf``, ``fixed-lag`` or ``batch`` (:func:`flexforce.compare.estimators.run_estimator`;
    ``fixed_lag`` becomes ``fixed-lag``, an unknown name is a ConfigError)."""
    robot: Any = None
    """Robot configuration: a :class:`flexforce.datasets.robot.RobotConfig`, a built-in name or a
    ``.toml`` path; None: the recording's (required for a raw robot bag)."""
    contacts: str = "ft"
    """Raw bags: contacts from the F/T normal force (``"ft"``, Schmitt trigger) or the
    configuration's fixed set (``"fixed"``)."""
    start: float | None = None
    """Keep the recording from this many s after its first sample (None: its start)."""
    end: float | None = None
    """Keep the recording up to this many s after its first sample (None: its end)."""
    use_ft: bool = False
    """Fuse the recording's F/T readings as measurements."""
    lag: float | None = None
    """Fixed-lag window, s (None: the smoother's default)."""
    block: int | None = None
    """Fixed-lag: samples added per update (None: the smoother's default); other estimators refuse it."""
    footholds: bool = False
    """Smoothers: estimate every contact episode's foothold; the EKF refuses it."""
    offline: bool = False
    """Fixed-lag into a ``.csv``/``.mcap``: load the whole recording first instead of streaming it."""
    covariance: bool = True
    """Streaming fixed-lag: extract the covariances (the ``std_*`` columns)."""
    realtime: bool = False
    """Streaming fixed-lag: pace the input at the recording's clock and count missed deadlines."""
    overwrite: bool = False
    """Replace an existing ``.mcap`` output (an MCAP file only)."""

    def __post_init__(self):
        from flexforce.compare.estimators import estimator_key

        object.__setattr__(self, "estimator", estimator_key(self.estimator))  # raises for an unknown one


@dataclass
class RunResult:
    """What :func:`run_recording` wrote."""

    output: Path
    """The file or bag written."""
    steps: int
    """Steps of the estimate written."""
    streamed: bool
    """Written part by part (:func:`stream_recording`) rather than from one estimate."""
    estimate: Any = None
    """The :class:`flexforce.datasets.estimate.Estimate` (an offline run; None when streamed)."""
    stats: dict = field(default_factory=dict)
    """A streamed run's statistics (:func:`flexforce.smoother.stream.run_stream`: steps, wall time,
    real-time factor, update times, missed deadlines); empty offline."""


def _stage(progress: ProgressFactory | None, label: str) -> Callable[[float], None] | None:
    return progress(label) if progress is not None else None


def open_recording(path, robot: Any = None, contacts: str = "ft", progress: ProgressFactory | None = None):
    """A flexforce bag (simulated or saved), or a raw robot bag imported with a robot configuration.

    Args:
        path: the bag (:func:`flexforce.datasets.io.rosimport.import_bag` lists the formats).
        robot: a raw bag's robot configuration (:attr:`RunConfig.robot`); a flexforce bag names its own.
        contacts: a raw bag's contact detection, ``"ft"`` or ``"fixed"``.
        progress: the progress factory (label ``"import <name>"``).

    Raises:
        BagError: a missing or unreadable bag.
        ConfigError: a raw robot bag without ``robot``.
        DataError: a recording the import or the validation refuses, or an accelerometer in the
            wrong unit.

    The sensor faults the data reveal are checked (:func:`flexforce.datasets.sensorcheck.screen`:
    each a warning naming the fault, its span and its effect, listed in ``meta['sensor_faults']``).
    """
    from flexforce.datasets.io.bagio import load_recording
    from flexforce.datasets.io.rosimport import import_bag, is_flexforce_bag
    from flexforce.datasets.sensorcheck import screen

    path = Path(path)
    if not path.exists() or is_flexforce_bag(path):
        return screen(load_recording(path), where=str(path))
    if not robot:
        raise ConfigError(_RAW_BAG.format(path=path))
    return import_bag(path, robot, contacts=contacts, progress=_stage(progress, f"import {path.name}"))


def load_or_simulate(source, seed: int | None = None, robot: Any = None, contacts: str = "ft",
                     progress: ProgressFactory | None = None):
    """A recording from a bag (:func:`open_recording`), or simulated from a built-in scenario name
    or a scenario ``.toml`` file (``seed``: its noise seed; ``robot``: replacing its robot), its
    sensor faults checked (:func:`flexforce.datasets.sensorcheck.screen`).

    Raises:
        BagError: ``source`` is neither an existing bag nor a scenario (the bag's "does not exist").
    """
    from flexforce.datasets.io.bagio import load_recording
    from flexforce.datasets.sensorcheck import screen
    from flexforce.datasets.sim.scenario import Scenario, builtin_scenarios
    from flexforce.datasets.sim.simulator import Simulator

    path = Path(source)
    if path.exists() and not (path.suffix == ".toml"):
        return open_recording(path, robot, contacts, progress)
    if path.suffix == ".toml" or source in builtin_scenarios():
        scenario = Scenario.load(source)
        if robot:
            scenario.robot = robot
        if seed is not None:
            scenario.seed = seed
        label = f"simulate {scenario.name}" + (f" #{seed}" if seed is not None else "")
        return screen(Simulator(scenario).run(progress=_stage(progress, label)), where=f"scenario {scenario.name}")
    return load_recording(path)  # raises the clear "does not exist" error


def window(rec, start: float | None = None, end: float | None = None):
    """The part of ``rec`` from ``start`` to ``end`` s after its first sample (None: no bound), long
    enough for the estimators.

    Raises:
        DataError: fewer samples than the estimators need
            (:meth:`flexforce.datasets.recording.Recording.require_samples`).
    """
    if start is not None or end is not None:
        rec = rec.window(start, end)
    return rec.require_samples()


def window_parts(parts: Iterable, start: float | None, end: float | None) -> Iterator:
    """The steps of the consecutive Recordings ``parts`` from ``start`` to ``end`` s after the first
    step (None: no bound); stops reading ``parts`` past ``end``."""
    t0 = None
    for part in parts:
        if t0 is None:
            t0 = int(part.t_ns[0])
        t = (part.t_ns - t0) * 1e-9
        keep = np.flatnonzero((t >= (start if start is not None else -np.inf) - 1e-9)
                              & (t <= (end if end is not None else np.inf) + 1e-9))
        if keep.size:
            yield part.slice(int(keep[0]), int(keep[-1]) + 1)
        if end is not None and t[-1] > end:
            return


def streams(config: RunConfig, output) -> bool:
    """:func:`run_recording` streams (reads the input and writes the estimate part by part, in
    bounded memory): the fixed-lag smoother into a ``.csv`` or ``.mcap``, unless ``offline`` or
    ``footholds``.

    Raises:
        ConfigError: ``realtime`` without streaming.
    """
    streamable = config.estimator == "fixed-lag" and Path(output).suffix in (".csv", ".mcap") and not config.footholds
    if config.realtime and not (streamable and not config.offline):
        raise ConfigError("--realtime replays a recording through the streaming fixed-lag smoother: it needs "
                          "--estimator fixed-lag, a .csv or .mcap output, and neither --offline nor --footholds")
    return streamable and not config.offline


def stream_parts(recording, config: RunConfig, on_message: Callable | None = None,
                 progress: ProgressFactory | None = None) -> tuple[Iterable, Any]:
    """``(parts, rec)``: the recording at path ``recording`` as consecutive parts, and ``rec`` the
    whole recording when it is a flexforce bag (loaded, cut to ``config.start``/``end``, parts of
    :data:`STREAM_PART_SECONDS`), None for a raw robot bag (read message by message,
    :func:`flexforce.datasets.io.stream.stream_bag`, not windowed: :func:`window_parts`).

    A raw bag is imported in a child process while the caller smooths (two cores,
    :func:`flexforce.datasets.io.stream.pipelined`) when there are two and no ``on_message`` is
    given (``on_message``: called with every message of a raw bag as it is read).

    Raises:
        ConfigError: a raw robot bag without ``config.robot``.
    """
    from flexforce.datasets.io.rosimport import is_flexforce_bag
    from flexforce.datasets.io.stream import stream_bag

    path = Path(recording)
    if not path.exists() or is_flexforce_bag(path):
        rec = window(open_recording(path, config.robot, config.contacts, progress), config.start, config.end)
        size = max(1, int(round(STREAM_PART_SECONDS / rec.dt)))
        return (rec.slice(a, min(a + size, rec.n)) for a in range(0, rec.n, size)), rec
    if not config.robot:
        raise ConfigError(_RAW_BAG.format(path=path))
    if on_message is None and (os.cpu_count() or 1) > 1:  # import and smoothing on two cores
        from flexforce.datasets.io.stream import pipelined

        return pipelined(stream_bag, path, config.robot, contacts=config.contacts, warm_up=warm_up), None
    return stream_bag(path, config.robot, contacts=config.contacts, on_message=on_message), None


def stream_recording(recording, output, config: RunConfig, progress: ProgressFactory | None = None) -> RunResult:
    """The streaming fixed-lag smoother (:func:`flexforce.smoother.stream.run_stream`) on the bag
    ``recording`` into ``output`` (``.csv``, or ``.mcap`` with every input topic copied beside the
    estimate and its uncertainty bands, the ``band/`` topics, where it has covariances), written
    aside and moved into place when complete (:class:`flexforce.datasets.io.export.EstimateWriter`).

    Raises:
        ConfigError: no step within ``config.start``/``end``, a raw bag without a robot, springs
            that cannot hold the robot upright
            (:func:`flexforce.compare.estimators.nominal_model` on the first part).
        BagError, DataError: the input or the output refused.
    """
    from flexforce.compare.estimators import nominal_model
    from flexforce.datasets.io.export import EstimateWriter
    from flexforce.smoother import FixedLagConfig
    from flexforce.smoother.stream import run_stream

    out = Path(output)
    options: dict[str, Any] = {"lag": config.lag} if config.lag is not None else {}
    if config.block is not None:
        options["block"] = config.block
    smoother = FixedLagConfig(**options)
    with EstimateWriter(out, overwrite=config.overwrite, robot=config.robot, bands=True) as writer:
        parts, rec = stream_parts(recording, config, writer.copy if out.suffix == ".mcap" else None, progress)
        if rec is not None and not config.robot:
            writer.robot = rec.robot
        if rec is not None:  # a flexforce bag: every topic of it (inputs, truth) into the .mcap
            if out.suffix == ".mcap":
                writer.copy_bag(recording)
        elif config.start is not None or config.end is not None:
            parts = window_parts(parts, config.start, config.end)
        parts = iter(parts)
        first = next(parts, None)
        if first is None:
            raise ConfigError("no step of the recording lies within --start/--end")
        model = nominal_model(first, config.robot, use_ft=config.use_ft)
        stats: dict = {}
        bar = _stage(progress, "fixed-lag (stream)")
        span = (rec.n - 1) * rec.dt if rec is not None else None
        for est in run_stream(itertools.chain([first], parts), model, smoother, covariance=config.covariance,
                              realtime=config.realtime, stats=stats):
            writer.write(est)
            if span and bar is not None:
                bar((int(est.t_ns[-1]) - int(first.t_ns[0])) * 1e-9 / span)
    return RunResult(out, stats.get("steps", writer.steps), streamed=True, stats=stats)


def _estimator_options(config: RunConfig) -> dict[str, Any]:
    """The keyword options of :func:`flexforce.compare.estimators.run_estimator` that ``config`` sets.

    Raises:
        ConfigError: ``block`` for another estimator than the fixed-lag smoother, ``footholds`` for the EKF.
    """
    options: dict[str, Any] = {}
    if config.lag is not None:
        options["lag"] = config.lag
    if config.block is not None:
        if config.estimator != "fixed-lag":
            raise ConfigError(f"--block sets the fixed-lag smoother's samples per update; got --estimator "
                              f"{config.estimator}")
        options["block"] = config.block
    if config.footholds:
        if config.estimator == "ekf":
            raise ConfigError("--footholds estimates the footholds in the smoothers (fixed-lag, batch); the EKF "
                              "resets them at each touch-down instead: EKFConfig(touchdown='zero-deflection')")
        options["footholds"] = True
    return options


def write_estimate(est, output, recording=None, overwrite: bool = False, robot: Any = None) -> Path:
    """Write ``est`` to ``output`` by its suffix: ``.csv``
    (:func:`flexforce.datasets.io.export.export_csv`), ``.mcap``: the MCAP file ``output`` with
    the estimate and its uncertainty bands (the ``band/`` topics, for the covariances it has) beside
    the topics of the bag ``recording`` and ``robot`` (name, ``.toml`` path or RobotConfig) in its
    description (:func:`flexforce.datasets.io.export.export_mcap`; ``overwrite`` an existing file),
    else ``.npz`` (:meth:`flexforce.datasets.estimate.Estimate.save`); returns the path written."""
    out = Path(output)
    if out.suffix == ".csv":
        from flexforce.datasets.io.export import export_csv

        return export_csv(est, out)
    if out.suffix == ".mcap":
        from flexforce.datasets.io.export import export_mcap

        return export_mcap(est, recording, out, overwrite=overwrite, robot=robot, bands=True)
    return est.save(out)


def run_offline(recording, output, config: RunConfig, progress: ProgressFactory | None = None) -> RunResult:
    """Estimator ``config.estimator`` on the whole recording at path ``recording`` (opened,
    windowed, its nominal model checked against toppling) into ``output`` (:func:`write_estimate`).

    Raises:
        ConfigError: an option the estimator does not take, a raw bag without a robot, springs
            that cannot hold the robot upright (:func:`flexforce.compare.estimators.nominal_model`).
        BagError, DataError, EstimatorError: the input refused, the estimation failed.
    """
    from flexforce.compare.estimators import nominal_model, run_estimator

    rec = window(open_recording(recording, config.robot, config.contacts, progress), config.start, config.end)
    model = nominal_model(rec, config.robot, use_ft=config.use_ft)
    options = _estimator_options(config)
    est = run_estimator(config.estimator, rec, model, progress=_stage(progress, config.estimator), **options)
    out = write_estimate(est, output, recording, overwrite=config.overwrite, robot=config.robot or rec.robot)
    return RunResult(out, est.n, streamed=False, estimate=est)


def run_recording(recording, output, config: RunConfig, progress: ProgressFactory | None = None) -> RunResult:
    """One estimator on the recording at path ``recording`` into ``output`` (``.npz``, ``.csv`` or
    ``.mcap``): streamed when :func:`streams` says so (:func:`stream_recording`), else at once
    (:func:`run_offline`).

    Raises:
        ConfigError, BagError, DataError, EstimatorError: as :func:`stream_recording` and
            :func:`run_offline`; ``realtime`` without streaming (:func:`streams`).
    """
    if streams(config, output):
        return stream_recording(recording, output, config, progress)
    return run_offline(recording, output, config, progress)


def warm_up() -> None:
    """Load the stream's compiled code (numba's cache: ~1 s) by smoothing a short simulated
    recording, with and without covariances, and the CSV formatting: ``flexforce run`` calls it
    while the import's first part is awaited, so that the stream runs at speed from its first update."""
    from flexforce.datasets.io.csvformat import format_rows
    from flexforce.datasets.sim.scenario import Scenario
    from flexforce.datasets.sim.simulator import Simulator
    from flexforce.factors.model import ModelConfig
    from flexforce.smoother.fixed_lag import FixedLagConfig
    from flexforce.smoother.stream import FixedLagStream

    scenario = Scenario.load("stand")
    scenario.duration = 0.25
    rec = Simulator(scenario, noise=False).run()
    model = ModelConfig.from_recording(rec)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for covariance in (True, False):
            stream = FixedLagStream(model, FixedLagConfig(lag=0.1), covariance=covariance)
            stream.push(rec)
            stream.finish()
    format_rows(np.zeros((1, 2)), np.zeros(1, dtype=np.int64), int_col=1)


def demo_options() -> dict[str, dict[str, object]]:
    """The demo's estimator options: ``{"fixed-lag": {"compiled": False}}`` when the kernel cache
    lacks the fixed-lag smoother's compiled window update
    (:func:`flexforce.smoother.window_kernel.window_update`), else none.

    The general window path gives the same estimates (``tests/test_window_update.py``) and needs
    only the batch smoother's kernels and the window solvers, where the compiled update costs about
    38 s of compilation on a first run; the demo then runs it in about 1.8 s instead of 0.6 s.  Once a
    fixed-lag run has compiled the update (``flexforce run``, ``compare``), the demo uses it.  The
    choice is said on the terminal, in summary.json (the estimator's ``extra.options``) and in the
    report (:func:`flexforce.compare.reports.comparison.option_sentences`)."""
    from flexforce import jit
    from flexforce.smoother import window_kernel

    return {} if jit.cached(window_kernel.window_update) else {"fixed-lag": {"compiled": False}}


def prepare_demo_kernels() -> None:
    """On a first run (the kernel cache without the demo's kernels), share their compilation with
    a helper process (:func:`flexforce.jit.compile_elsewhere`, the listing of
    :mod:`flexforce.demo_kernels` in :func:`demo_listing`'s order): the helper compiles the EKF's
    kernels while the demo simulates its scenario, the demo then compiles the smoothers' until the
    EKF's are cached (:func:`demo_while_awaiting`), and each compiles the rest as it comes, loading
    from the cache what the other has compiled.  Nothing is started when the cache holds them, nor
    on a single core; then the compile notice is written at once and the demo compiles the kernels
    as it needs them.  The fixed-lag smoother's compiled window update is not in the listing: on a
    first run the demo runs its general path (:func:`demo_options`).  Measured on the 2-core
    machine, cold cache: 53-55 s (91-96 s of CPU; the EKF's results at 24 s; the warm demo 28 s);
    57-59 s with the helper compiling the smoothers' kernels first, 73 s (120 s of CPU) compiling
    the window update too, 107-122 s without the helper."""
    from flexforce import jit
    from flexforce.compare.ekf import kernel
    from flexforce.compare.runner import usable_cores
    from flexforce.demo_kernels import DEMO_KERNELS
    from flexforce.smoother import solvers

    if jit.cached(kernel.step, solvers.block_tridiag_factor):
        return
    if usable_cores() < 2:
        jit.announce_compilation()
        return
    jit.compile_elsewhere(demo_listing(DEMO_KERNELS), processes=1)


EKF_STEP = ("flexforce.compare.ekf.kernel", "step")
"""The EKF's kernel in :mod:`flexforce.demo_kernels`' listing: the demo's first estimator."""


def demo_listing(kernels: list[tuple[str, str, str]]) -> list[tuple[str, str, str]]:
    """The demo's kernels in the order :func:`flexforce.jit.compile_elsewhere` shares them: what the
    demo needs for its EKF (the listing up to the EKF's step) last, so that the helper, which
    starts from the end, compiles them while the demo simulates; the smoothers' kernels first,
    which the demo compiles itself once its simulation is done (:func:`demo_while_awaiting`)."""
    ends = [i for i, (module, function, _) in enumerate(kernels) if (module, function) == EKF_STEP]
    if not ends:  # a listing without the EKF: as recorded
        return list(kernels)
    j = ends[-1] + 1
    return list(kernels[j:]) + list(kernels[:j])


def demo_while_awaiting() -> None:
    """After the demo's simulation: while the helper compiles the EKF's kernels, compile the
    smoothers' in this process (:func:`flexforce.jit.compile_while_awaiting`); nothing when no
    helper runs (a warm cache, one core)."""
    from flexforce import jit
    from flexforce.compare.ekf import kernel

    jit.compile_while_awaiting(kernel.step)


