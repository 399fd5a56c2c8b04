"""The ``flexforce`` command line: a thin layer over the library.

Every command ends with one line on stderr when it fails, and an exit status (:data:`EXIT_STATUSES`):

- 0: done;
- 1: bad input, configuration or output path, or the estimation failed
  (:class:`flexforce.errors.FlexforceError`, an operating-system error such as a full disk, or an
  unexpected internal error, which says so; ``FLEXFORCE_DEBUG=1`` shows its traceback);
- 2: wrong command-line usage (argparse);
- 130: interrupted (Ctrl-C, wherever it lands: also inside the compiled kernels, where it
  surfaces as a ``SystemError`` whose cause is the ``KeyboardInterrupt``).

Every output path is checked before any work (:func:`flexforce.datasets.safeio.check_output`),
locked for the whole command, written aside and moved into place when complete.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Any

from flexforce.errors import ConfigError, FlexforceError

EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
EXIT_STATUSES = {
    EXIT_OK: "done",
    EXIT_ERROR: "bad input, configuration or output path, or the estimation failed (one line on stderr)",
    EXIT_USAGE: "wrong command-line usage",
    EXIT_INTERRUPTED: "interrupted (Ctrl-C); every output is the previous one or none, never a mixture",
}
"""Exit status -> meaning (README "Command line", ``flexforce --help``)."""

FILE_SUFFIXES = (".npz", ".csv", ".json", ".html", ".toml", ".txt", ".png", ".py", ".db3", ".bag")
"""Suffixes refused for an output folder (a bag directory, a report): they name files."""


PROGRESS_ORIGIN = time.time()
"""Wall-clock start of the command: the elapsed time of the progress lines counts from it (main()
sets it; worker processes of --jobs are given the parent's)."""


PROGRESS_WORKER = False
"""In a worker process of --jobs: progress as lines, whatever stderr is (bars of several processes
would overwrite each other), each prefixed with its recording (:data:`PROGRESS_PREFIX`)."""
PROGRESS_PREFIX = ""


def set_progress_origin(origin: float) -> None:
    """Count the elapsed time of progress lines from ``origin`` (``time.time()`` of the command's start)."""
    global PROGRESS_ORIGIN
    PROGRESS_ORIGIN = origin


def _worker_init(origin: float, command: str = "") -> None:
    """Initialiser of the worker processes of --jobs: the parent's clock, progress as lines, and
    warnings as the parent prints them (``flexforce <command>: warning: ...``, one line)."""
    global PROGRESS_WORKER
    set_progress_origin(origin)
    PROGRESS_WORKER = True
    if command:
        warnings.showwarning = _show_warning(command)


class Progress:
    """Progress of one stage on stderr.

    On a terminal, a one-line bar redrawn in place; off a terminal (a log file, CI, a pipe), one line
    when the stage is done, with the elapsed time of the command (``[  12.3 s] fixed-lag: done
    (4.1 s)``), since a redrawn bar would fill the log with carriage returns.

    Args:
        enabled: ``None`` chooses by stderr (bar on a terminal, lines elsewhere), ``False`` is silent,
            ``True`` forces the bar, ``"lines"`` forces the lines.
    """

    def __init__(self, label: str, enabled: bool | str | None = None, width: int = 30):
        self.label = f"{PROGRESS_PREFIX}{label.strip()}" if PROGRESS_PREFIX else label
        self.width = width
        if PROGRESS_WORKER and enabled is not False:
            self.mode = "lines"
        elif enabled is None:
            self.mode = "bar" if sys.stderr.isatty() else "lines"
        elif enabled == "lines":
            self.mode = "lines"
        else:
            self.mode = "bar" if enabled else "off"
        self.enabled = self.mode != "off"
        self.start = time.perf_counter()
        self._last = -1

    def note(self, message: str) -> None:
        """One line with the stage's news (which candidate, its statistic, the round), in full; on
        a terminal above the bar, which is drawn again after it."""
        if self.mode == "off" or not message:
            return
        since = time.time() - PROGRESS_ORIGIN
        line = f"[{since:7.1f} s] {self.label.strip()}: {message}\n"
        if self.mode == "bar":
            line = "\r\x1b[K" + line  # over the bar's line; the next update draws the bar below
            self._last = -1
        sys.stderr.write(line)
        sys.stderr.flush()

    def __call__(self, fraction: float) -> None:
        if self.mode == "off":
            return
        pct = int(100 * min(max(fraction, 0.0), 1.0))
        if pct == self._last:
            return
        self._last = pct
        elapsed = time.perf_counter() - self.start
        if self.mode == "lines":
            if pct >= 100:
                since = time.time() - PROGRESS_ORIGIN
                sys.stderr.write(f"[{since:7.1f} s] {self.label.strip()}: done ({elapsed:.1f} s)\n")
                sys.stderr.flush()
            return
        filled = int(self.width * pct / 100)
        sys.stderr.write(f"\r{self.label:<24s} [{'#' * filled}{'.' * (self.width - filled)}] {pct:3d}% {elapsed:6.1f}s")
        if pct >= 100:
            sys.stderr.write("\n")
        sys.stderr.flush()


def _is_bag(path: Path) -> bool:
    from flexforce.datasets.safeio import is_bag_folder

    return is_bag_folder(path) if path.is_dir() else path.suffix in {".mcap", ".db3", ".bag"}


def _check_bag_output(path: Path, force: bool, what: str) -> Path:
    from flexforce.datasets.safeio import check_output

    return check_output(path, what, folder=True, file_suffixes=FILE_SUFFIXES, overwrite=force, replaceable=_is_bag,
                        replaceable_what="a ROS 2 bag")


def _check_report_output(path: Path) -> Path:
    from flexforce.datasets.safeio import check_output, replaceable_by_report

    return check_output(path, "report folder", folder=True, file_suffixes=FILE_SUFFIXES,
                        replaceable=replaceable_by_report,
                        replaceable_what="a flexforce report (index.html, .json and figures only)")


def _cmd_simulate(args) -> int:
    """``simulate``: the output checked before any work (``X.mcap``: one MCAP file, replaceable
    by its own kind with --force; any other name: a ROS 2 bag directory), then :func:`_simulate`."""
    from flexforce.datasets.safeio import check_output, output_lock

    out = Path(args.output)
    if out.suffix == ".mcap":
        check_output(out, "recording bag", overwrite=args.force,
                     replaceable=lambda p: p.is_file() and p.suffix == ".mcap", replaceable_what="an MCAP file")
    else:
        out = _check_bag_output(out, args.force, "recording bag")
    with output_lock(out):
        return _simulate(args)


def _simulate(args) -> int:
    from flexforce.datasets.io.bagio import save_recording
    from flexforce.datasets.sim.scenario import Scenario
    from flexforce.datasets.sim.simulator import Simulator

    scenario = Scenario.load(args.scenario)
    if args.robot:
        scenario.robot = args.robot
    if args.duration is not None:  # checked by the scenario: a positive number of seconds, within its bound
        scenario.duration = args.duration
    if args.seed is not None:
        scenario.seed = args.seed
    sim = Simulator(scenario, noise=not args.no_noise)
    rec = sim.run(progress=Progress(f"simulate {scenario.name}", enabled=not args.quiet and None))
    out = Path(args.output)
    if out.suffix == ".mcap":  # the one MCAP file its name says, as `run -o X.mcap` writes
        from flexforce.datasets.io.export import mcap_file_output

        with mcap_file_output(out, overwrite=args.force) as bag:
            save_recording(rec, bag)
    else:
        out = save_recording(rec, out, overwrite=args.force)
    print(f"wrote {out}: {rec.n} samples at {1.0 / rec.dt:.0f} Hz, robot {sim.robot.name}, "
          f"scenario {scenario.name}")
    return 0


def _progress(quiet: bool):
    """The library's progress factory (:mod:`flexforce.pipeline`): a :class:`Progress` per stage,
    silent with --quiet."""
    return lambda label: Progress(label, enabled=not quiet and None)


def _window(rec, args):
    """The part of ``rec`` chosen with --start/--end (the whole recording without them), long
    enough for the estimators (:func:`flexforce.pipeline.window`)."""
    from flexforce.pipeline import window

    return window(rec, getattr(args, "start", None), getattr(args, "end", None))


def _model(rec, args):
    """The nominal model of ``rec`` with the robot configuration of --robot (or the recording's),
    its springs checked against gravity toppling on the recording's first sample
    (:func:`flexforce.compare.estimators.nominal_model`: an error, or a warning printed as one line)."""
    from flexforce.compare.estimators import nominal_model

    return nominal_model(rec, args.robot, use_ft=args.ft)


def _cmd_run(args) -> int:
    from flexforce.compare.estimators import estimator_key
    from flexforce.datasets.safeio import check_output, output_lock
    from flexforce.errors import OutputError

    args.estimator = estimator_key(args.estimator)
    out = Path(args.output)
    if out.suffix == ".mcap":
        check_output(out, "estimate bag", overwrite=args.force,
                     replaceable=lambda p: p.is_file() and p.suffix == ".mcap", replaceable_what="an MCAP file")
    else:
        check_output(out, "estimate", suffixes=(".npz", ".csv", ".mcap"))
    if Path(args.recording).exists() and out.resolve() == Path(args.recording).resolve():
        raise OutputError(f"output {out} is the input recording; expected a new path beside it")
    with output_lock(out):
        return _run(args)


def _run(args) -> int:
    from flexforce.pipeline import RunConfig, run_recording

    config = RunConfig(estimator=args.estimator, robot=args.robot, contacts=args.contacts, start=args.start,
                       end=args.end, use_ft=args.ft, lag=args.lag, block=args.block, footholds=args.footholds,
                       offline=args.offline, covariance=not args.no_cov, realtime=args.realtime,
                       overwrite=args.force)
    print(_run_line(run_recording(args.recording, args.output, config, progress=_progress(args.quiet)),
                    args.realtime))
    return 0


def _run_line(result, realtime: bool) -> str:
    """The line ``run`` prints: what it wrote, and its timing (a stream's update times, and in real
    time its missed deadlines)."""
    if not result.streamed:
        est = result.estimate
        tps = est.time_per_step
        timing = f", {1e6 * float(sorted(tps)[len(tps) // 2]):.0f} us per step (median)" if tps is not None else ""
        return f"wrote {result.output}: {est.n} steps in {est.total_time:.2f} s{timing}"
    stats = result.stats
    up = stats.get("update", {})
    line = (f"wrote {result.output}: {result.steps} steps streamed in {stats.get('wall_s', 0.0):.2f} s "
            f"({stats.get('realtime_factor') or 0.0:.1f}x real time), update {up.get('median_ms', 0.0):.2f} ms "
            f"median, {up.get('p99_ms', 0.0):.2f} ms p99")
    if up.get("samples_per_update", 1) > 1:
        line += (f" ({up['samples_per_update']} samples per update: {up.get('per_sample_ms', 0.0):.3f} ms per "
                 "sample)")
    if realtime:
        line += (f"; real time: {stats['missed_deadlines']} missed deadline(s) of {stats['parts']} parts, "
                 f"at most {1e3 * max(stats['max_late_s'], 0.0):.1f} ms behind the recording's clock")
    return line


def _load_or_simulate(source: str, seed: int | None, quiet: bool, robot: str | None = None, contacts: str = "ft"):
    """A recording from a bag, or simulated from a built-in scenario name or scenario file
    (:func:`flexforce.pipeline.load_or_simulate` with the command's progress bars)."""
    from flexforce.pipeline import load_or_simulate

    return load_or_simulate(source, seed, robot, contacts, progress=_progress(quiet))


def _compare_one(rec, args, out: Path):
    from flexforce.compare.reports.comparison import write_report
    from flexforce.compare.runner import compare

    model = _model(rec, args)
    if getattr(args, "after_load", None):  # the demo's (pipeline.demo_while_awaiting)
        args.after_load()
    bars = {}

    def progress(name, fraction):
        if name not in bars:
            bars[name] = Progress(f"  {name}", enabled=not args.quiet and None)
        bars[name](fraction)

    options: dict[str, dict[str, object]] | None = None
    if getattr(args, "estimator_options", None):  # the demo's (pipeline.demo_options)
        options = {name: dict(value) for name, value in args.estimator_options.items()}
    if getattr(args, "footholds", False):
        options = options or {}
        for name in args.estimators:
            if name != "ekf":
                options[name] = {**options.get(name, {}), "footholds": True}
    if getattr(args, "calibrate_noise", False) and "batch" in args.estimators:
        options = options or {}
        options["batch"] = {**options.get("batch", {}), "noise_calibration": CALIBRATE_NOISE_SIGMA}
    comp = compare(rec, estimators=args.estimators, model=model, progress=progress, options=options,
                   peers=True if getattr(args, "peers", False) else None)
    write_report(comp, rec, out)
    return comp


CALIBRATE_NOISE_SIGMA = 3.0
"""``compare --calibrate-noise``: the batch smoother's ``noise_calibration`` threshold, sigmas."""


def _print_table(comp) -> None:
    from flexforce.compare.metrics import PHASES, lowpass_key
    from flexforce.compare.runner import headline

    def f(x, s=1.0):
        return f"{x * s:.3g}" if x is not None else "-"

    rows: list[tuple[str, Any, bool | str]] = [(k, m, False) for k, m in comp.metrics.items()]
    rows += [(k, m, True) for k, m in comp.baselines.items()]
    rows += [(k, m, "+") for k, m in comp.peers.items()]

    def tag(marker) -> str:
        return " +" if marker == "+" else " *" if marker else ""

    contacts = list(dict.fromkeys(c for _, m, _ in rows for c in m.per_contact))
    short = {c: c.replace("_foot", "").replace("foot_", "")[:6] for c in contacts}
    head = (f"{'estimator':13s} {'force[N]':>9s} {'Fz[N]':>7s} {'CoP[mm]':>8s} {'rot[mrad]':>9s} {'hand[mm]':>8s} "
            f"{'NEES':>7s} {'step[us]':>9s}")
    head += "".join(f" {'Fz ' + short[c] + '[N]':>12s}" for c in contacts)
    print(head)
    for key, m, baseline in rows:
        r = m.rmse
        med = (m.time_per_step.get("median") or m.time_per_step.get("amortized")) if m.time_per_step else None
        line = (f"{key + tag(baseline):13s} {f(r.get('force_N')):>9s} {f(r.get('vertical_force_N')):>7s} "
                f"{f(r.get('cop_m'), 1e3):>8s} {f(r.get('rotation_rad'), 1e3):>9s} "
                f"{f(r.get('hand_m'), 1e3):>8s} {f(m.nees):>7s} {f(med, 1e6):>9s}")
        line += "".join(f" {f(m.per_contact.get(c, {}).get('vertical_force_N')):>12s}" for c in contacts)
        print(line)
    if any(m.per_phase for _, m, _ in rows):
        lp = lowpass_key()
        phases = [p for p in ("all", *PHASES) if any(m.per_phase.get(p, {}).get("samples") for _, m, _ in rows)]
        print(f"{'foot/total Fz[N]':17s}" + "".join(f" {p.replace('_support', ''):>13s}" for p in phases)
              + f" {'all ' + lp.replace('rmse_lowpass_', 'lp '):>13s}")
        for key, m, baseline in rows:
            def pair(block, phase, m=m):
                d = m.per_phase.get(phase, {}).get(block) or {}
                return f"{f(d.get('foot_vertical_force_N'))}/{f(d.get('total_vertical_force_N'))}"

            print(f"{key + tag(baseline):17s}" + "".join(f" {pair('rmse', p):>13s}" for p in phases)
                  + f" {pair(lp, 'all'):>13s}")
    refs = sorted({v for _, m, _ in rows for v in m.references.values()})
    notes = []
    if comp.baselines:
        notes.append("* baseline without estimation (rigid robot; leg_odometry: static CoM split, weight_equal: "
                     "equal split)")
    if comp.peers:
        notes.append("+ peer: GTSAM's legged estimator on the same IMU and contacts (tilt only, no forces)")
    if refs:
        notes.append("errors against " + ", ".join(refs))
    if notes:
        print("; ".join(notes))
    for key, msg in comp.failures.items():
        print(f"{key:13s} failed: {msg}")
    for sentence in headline(comp.summary()):
        print(sentence)


def _cmd_compare(args) -> int:
    from flexforce.compare.estimators import estimator_key
    from flexforce.datasets.safeio import output_lock
    from flexforce.errors import ConfigError

    names = [e.strip() for e in args.estimators.split(",") if e.strip()]
    if not names:
        raise ConfigError(f"--estimators {args.estimators!r} names no estimator; expected a comma-separated list "
                          "such as ekf,fixed-lag,batch")
    args.estimators = [estimator_key(e) for e in names]  # the message of 'run' for an unknown one
    _check_jobs(args)
    out = _check_report_output(args.output)
    with output_lock(out):
        return _compare(args)


def _compare(args) -> int:
    import json

    from flexforce.compare.runner import aggregate
    from flexforce.datasets.safeio import safe_output

    sources: list[tuple[str, str, int | None]] = []
    for src in args.recordings:
        if args.seeds and args.seeds > 1:
            sources += [(f"{Path(src).stem}-seed{s}", src, s) for s in range(args.seeds)]
        else:
            sources.append((Path(src).stem or str(src), src, None))
    out = Path(args.output)
    if len(sources) == 1:
        label, src, seed = sources[0]
        rec = _window(_load_or_simulate(src, seed, args.quiet, args.robot, args.contacts), args)
        _print_table(_compare_one(rec, args, out))  # the report is written aside and swapped in whole
    else:
        # one folder of reports, built aside and swapped in whole: an interrupted comparison leaves
        # the previous folder (or none), never new reports beside an old index
        from flexforce.compare.reports.comparison import aggregate_timings, write_index
        from flexforce.compare.runner import run_jobs

        with safe_output(out, folder=True) as staging:
            staging.mkdir()
            jobs = [(label, src, seed, staging / label) for label, src, seed in _unique_labels(sources)]
            comps = []
            results = run_jobs(functools.partial(_compare_job, args), jobs, args.jobs, _worker_init,
                               (PROGRESS_ORIGIN, args.command))
            for (label, _, _, _), comp in zip(jobs, results):
                comps.append(comp)
                print(f"{label}:")
                _print_table(comp)
            agg, times = aggregate(comps), aggregate_timings(comps)  # the same for two runs; the machine's cost
            (staging / "summary.json").write_text(json.dumps(agg, indent=2, allow_nan=False))
            (staging / "timings.json").write_text(json.dumps(times, indent=2, allow_nan=False))
            write_index(staging, [(label, comp.summary()) for (label, _, _, _), comp in zip(jobs, comps)], agg,
                        times=times)
    print(f"report: {out / 'index.html'}")
    return 0


def _jobs(text: str) -> int | str:
    """The value of --jobs: a number, or 'auto' (one worker per usable core, as memory allows)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}; expected a number of worker processes or 'auto'") from None


def _whole(minimum: int, what: str):
    """An argparse type: a whole number at least ``minimum``; ``what`` names what it counts."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            raise argparse.ArgumentTypeError(f"{text!r}; expected {what}, a whole number >= {minimum}")
        return value
    return parse


def _check_jobs(args) -> None:
    jobs = getattr(args, "jobs", 1)
    if jobs != "auto" and jobs < 1:
        raise ConfigError(f"--jobs {jobs}; expected a positive number of worker processes (1: one at a time, here) "
                          "or auto")


def _unique_labels(sources: list) -> list:
    """The sources with their labels (first item) made unique: recordings of the same name in two
    folders get their own report folders (``walk``, ``walk-2``)."""
    seen: dict[str, int] = {}
    out = []
    for label, *rest in sources:
        seen[label] = seen.get(label, 0) + 1
        out.append((label if seen[label] == 1 else f"{label}-{seen[label]}", *rest))
    return out


def _compare_job(args, job):
    """One recording of a multi-recording comparison (here or in a worker process of --jobs): its
    report in its folder; returns the Comparison without its estimates (they stay in the report)."""
    global PROGRESS_PREFIX
    label, src, seed, out = job
    PROGRESS_PREFIX = f"{label}: "
    try:
        rec = _window(_load_or_simulate(src, seed, args.quiet, args.robot, args.contacts), args)
        comp = _compare_one(rec, args, out)
    finally:
        PROGRESS_PREFIX = ""
    comp.estimates, comp.baseline_estimates = {}, {}
    return comp


def _cmd_demo(args) -> int:
    from flexforce.datasets.sim.scenario import DEFAULT_SCENARIO

    args.recordings = [args.scenario or DEFAULT_SCENARIO]
    args.seeds = None
    args.robot = None
    args.ft = False
    args.contacts = "ft"
    args.start = args.end = None
    args.estimators = "ekf,fixed-lag,batch"
    args.jobs = 1
    from flexforce.jit import set_compile_notice
    from flexforce.pipeline import demo_options, demo_while_awaiting, prepare_demo_kernels

    print(f"flexforce demo: simulate '{args.recordings[0]}' (Romeo, pushed on the torso then the hand), "
          f"run the EKF, the fixed-lag and the batch smoothers, compare them against ground truth", flush=True)
    args.estimator_options = demo_options()
    if args.estimator_options and not args.quiet:
        print("flexforce demo: the fixed-lag smoother's compiled window update is not in the kernel cache yet; "
              "this demo runs its general path (the same estimates, a slower step) rather than wait for it "
              "to compile (the first 'flexforce run' or 'compare' compiles it)", flush=True)

    if not args.quiet:
        set_compile_notice(True)  # the demo is a first run's first command: its wait explained, on a terminal or not
    prepare_demo_kernels()
    args.after_load = demo_while_awaiting
    return _cmd_compare(args)


def _cmd_diagnose(args) -> int:
    from flexforce.datasets.safeio import output_lock

    _check_jobs(args)
    out = _check_report_output(args.output)
    with output_lock(out):
        return _diagnose(args)


def _diagnose(args) -> int:
    level = None if args.no_screen else args.screen_level
    if level is not None and not 0.0 < level < 1.0:
        raise ConfigError(f"--screen-level {level}; expected a probability in (0, 1) (or --no-screen)")
    if args.refit_best < 0:
        raise ConfigError(f"--refit-best {args.refit_best}; expected an integer >= 1 (candidates refitted per round), "
                          "or 0 for every candidate that passes the screening")
    sources = _unique_labels([(Path(src).stem or str(src), src) for src in args.recording])
    out = Path(args.output)
    if len(sources) == 1:
        _print_diagnosis(_diagnose_job(args, (None, sources[0][1], out)))
    else:
        import json

        from flexforce.compare.reports.diagnosis import write_diagnosis_index
        from flexforce.compare.runner import run_jobs
        from flexforce.datasets.safeio import safe_output

        with safe_output(out, folder=True) as staging:  # built aside, swapped in whole
            staging.mkdir()
            jobs = [(label, src, staging / label) for label, src in sources]
            results = []
            for (label, _, _), result in zip(jobs, run_jobs(functools.partial(_diagnose_job, args), jobs,
                                                             args.jobs, _worker_init,
                                                             (PROGRESS_ORIGIN, args.command))):
                print(f"{label}:")
                _print_diagnosis(result)
                results.append((label, result))
            summary = {"recordings": [{"label": label, **result["summary"]} for label, result in results]}
            (staging / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False))
            write_diagnosis_index(staging, [(label, result["summary"]) for label, result in results])
    print(f"report: {out / 'index.html'}")
    return 0


def _diagnose_job(args, job) -> dict:
    """Diagnose one recording (here or in a worker process of --jobs) and write its report; returns
    what the terminal shows and the index lists."""
    global PROGRESS_PREFIX
    from flexforce.compare.diagnostics.config import DiagnoseConfig
    from flexforce.compare.diagnostics.progress import DiagnosisProgress
    from flexforce.compare.diagnostics.run import diagnose, load_plugin
    from flexforce.compare.reports.diagnosis import diagnosis_summary, write_diagnosis

    label, source, out = job
    PROGRESS_PREFIX = f"{label}: " if label else ""
    try:
        rec = _window(_load_or_simulate(str(source), args.seed, args.quiet, args.robot, args.contacts), args)
        model = _model(rec, args)
        plugins = [eff for path in args.plugin for eff in load_plugin(path)]
        # without --candidates the default catalogue, whose costly members may opt out on this
        # recording (the footholds without a touch-down), and the plugins' effects beside it
        candidates = [c.strip() for c in args.candidates.split(",") if c.strip()] if args.candidates else None
        if candidates is not None:  # a plugin's effect named there is ranked as a plugin (always, beside them)
            names = {eff.name for eff in plugins}
            candidates = [c for c in candidates if c not in names]
        bars = {}
        # rounds, time elapsed and left; the default catalogue's size is read from its screening
        notes = DiagnosisProgress(args.max_effects, len(candidates) + len(plugins) if candidates else None)

        def progress(label, fraction, message=None):
            if label not in bars:
                bars[label] = Progress(f"  {label}", enabled=not args.quiet and None)
            note = notes.update(label, fraction, message)
            if note:
                bars[label].note(note)
            bars[label](fraction)

        level = None if args.no_screen else args.screen_level
        config = DiagnoseConfig(rank=not args.no_rank, max_effects=args.max_effects, ekf=not args.no_ekf,
                                screen_level=level, refit_best=args.refit_best or None,
                                jobs=args.jobs if label is None else 1, check_constancy=not args.no_constancy,
                                check_veto=not args.no_check_veto)
        diag = diagnose(rec, model, candidates=candidates, extra_candidates=plugins, add=args.add, config=config,
                        progress=progress)
        write_diagnosis(diag, out)
    finally:
        PROGRESS_PREFIX = ""
    rmse = [(key, b, diag.after.rmse.get(key)) for key, b in diag.before.rmse.items()] if diag.after else []
    return {"ranking_table": diag.ranking_table() if diag.ranking else None, "summary": diagnosis_summary(diag),
            "rmse": rmse}


def _print_diagnosis(result: dict) -> None:
    s = result["summary"]
    print(f"verdict: {s['verdict']}\n")  # the answer first, the ranking behind it
    if result["ranking_table"]:
        print(result["ranking_table"])
    print(f"significant: {s['selected_line']}")
    if s["flags_after"] is not None:
        print(f"added {', '.join(s['added'])}: flagged windows {s['flags_before']} -> {s['flags_after']}")
        for line in s["added_values"]:
            print(f"  added {line}")
        from flexforce.compare.diagnostics.text import CHECK_LABELS

        for key, b, a in result["rmse"]:
            if b is not None and a is not None:  # the report's units (mm, deg)
                label, scale, unit = CHECK_LABELS.get(key, (key, 1.0, ""))
                print(f"  RMSE {label + ' [' + unit.strip() + ']' if unit else label:20s} {b * scale:10.4g} -> "
                      f"{a * scale:10.4g}")


def _cmd_layout(args) -> int:
    from flexforce.datasets.io.viewers import KINDS, layout_topics, layout_topics_of_bag, render_layout
    from flexforce.datasets.safeio import check_output, output_lock, safe_output

    out = check_output(args.output, f"{args.kind} layout", suffixes=(KINDS[args.kind],))
    with output_lock(out):
        if args.bag is not None:
            if args.estimator or args.truth:
                raise ConfigError("--bag reads the estimator and the truth topics from the bag itself; expected "
                                  "--bag alone (or --robot with --estimator/--truth, without --bag)")
            topics = layout_topics_of_bag(args.bag, args.robot)
        else:
            from flexforce.compare.estimators import estimator_key

            topics = layout_topics(args.robot, estimator_key(args.estimator or "ekf"), ft=not args.no_ft,
                                   truth=args.truth)
        text = render_layout(args.kind, topics)
        with safe_output(out) as tmp:
            tmp.write_text(text)
    print(f"wrote {out}: {args.kind} layout for /estimate/{topics.estimator}/ of robot {topics.robot}, contacts "
          f"{', '.join(topics.contacts)}"
          + (f", F/T {', '.join(topics.ft.values())}" if topics.ft else "") + (", truth" if topics.truth else ""))
    return 0


def _apply_urdf(args) -> None:
    """``--urdf``: the robot configuration of ``--robot`` with that URDF (args.robot becomes the
    configuration itself, which every reader of ``--robot`` takes as well as a name)."""
    urdf = getattr(args, "urdf", None)
    if urdf is None:
        return
    import dataclasses

    from flexforce.datasets.robot import RobotConfig

    if not args.robot:
        raise ConfigError("--urdf replaces the URDF of a robot configuration: give that configuration with --robot "
                          "(e.g. --robot icub --urdf path/to/iCubGenova04.urdf)")
    path = Path(urdf).expanduser().resolve()
    if not path.is_file():
        raise ConfigError(f"--urdf {urdf}: no such file; expected the robot's URDF")
    args.robot = dataclasses.replace(RobotConfig.load(args.robot), urdf=str(path))


def _add_input_options(p: argparse.ArgumentParser) -> None:
    """Options of every command that reads a recording (raw robot bags need a robot config)."""
    p.add_argument("--robot", help="robot name or .toml configuration (default: the recording's; required for a "
                                   "raw robot bag)")
    p.add_argument("--urdf", type=Path, metavar="FILE",
                   help="the robot's URDF, replacing the one its configuration names (needs --robot)")
    p.add_argument("--contacts", choices=("ft", "fixed"), default="ft",
                   help="raw bags: contacts from the F/T normal force (Schmitt trigger) or the config's fixed set")
    p.add_argument("--start", type=float, metavar="S",
                   help="keep the recording from S seconds after its first sample (default: its start)")
    p.add_argument("--end", type=float, metavar="S",
                   help="keep the recording up to S seconds after its first sample (default: its end)")


def _epilog() -> str:
    lines = "\n".join(f"  {code:<4d} {meaning}" for code, meaning in EXIT_STATUSES.items())
    return (f"exit status:\n{lines}\n\nOutputs are checked before any work, written aside and moved into place "
            "when complete;\na second writer of the same output is refused (a <output>.lock file holds the "
            "writer's PID).")


def _add_simulate_parser(sub) -> None:
    p = sub.add_parser("simulate", help="simulate a scenario into a ROS 2 bag (MCAP) with ground truth")
    p.add_argument("scenario", help="built-in scenario name (stand, com-step, push-pitch, push-roll, push-com, "
                                    "sway, weight-shift, step, walk, walk-short) or a scenario .toml file")
    p.add_argument("-o", "--output", required=True, type=Path, help="output: a bag directory, or X.mcap for "
                                                                 "one MCAP file")
    p.add_argument("--robot", help="robot name or .toml configuration (overrides the scenario's)")
    p.add_argument("--duration", type=float, help="duration in s (overrides the scenario's)")
    p.add_argument("--seed", type=_whole(0, "a noise seed"), help="noise seed (overrides the scenario's)")
    p.add_argument("--no-noise", action="store_true", help="exact sensor readings")
    p.add_argument("--force", action="store_true", help="overwrite an existing output")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_simulate)


def _add_run_parser(sub) -> None:
    p = sub.add_parser("run", help="run one estimator on a recording and save its estimate (.npz)")
    p.add_argument("recording", type=Path, help="bag written by 'flexforce simulate' (or a flexforce recording)")
    p.add_argument("--estimator", default="ekf", help="ekf (the seed paper's filter), fixed-lag or batch")
    p.add_argument("-o", "--output", required=True, type=Path,
                   help="estimate file: .npz (flexforce), .csv (one row per step) or .mcap (ROS 2 bag with the "
                        "estimate beside the inputs, for PlotJuggler or Foxglove)")
    _add_input_options(p)
    p.add_argument("--force", action="store_true", help="overwrite an existing .mcap output")
    p.add_argument("--ft", action="store_true", help="fuse the recording's F/T readings as measurements")
    p.add_argument("--lag", type=float, help="fixed-lag window, s (default 1)")
    p.add_argument("--block", type=int,
                   help="fixed-lag: samples added per update (default 1; B > 1 pays the update's overhead once "
                        "per B samples, with fewer Gauss-Newton passes per step and up to B-1 samples more latency)")
    p.add_argument("--footholds", action="store_true",
                   help="smoothers: estimate every contact episode's foothold (leg kinematics at the touch-down, "
                        "ground plane of the robot's [footholds] table) instead of holding the given one")
    p.add_argument("--offline", action="store_true",
                   help="fixed-lag into .csv/.mcap: load the whole recording first instead of streaming it")
    p.add_argument("--no-cov", action="store_true",
                   help="streaming fixed-lag: no covariances (saves their extraction; no std_* columns)")
    p.add_argument("--realtime", action="store_true",
                   help="streaming fixed-lag: pace the input at the recording's clock and report missed deadlines")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_run)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="flexforce",
        description="Contact forces and floating-base kinematics of flexible legged robots from an IMU "
                    "and joint encoders.",
        epilog=_epilog(), formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    _add_simulate_parser(sub)
    _add_run_parser(sub)

    p = sub.add_parser("compare", help="EKF vs fixed-lag vs batch on recordings: report folder with summary.json")
    p.add_argument("recordings", nargs="+", help="bags, or built-in scenario names / scenario files to simulate")
    p.add_argument("-o", "--output", required=True, type=Path, help="report folder")
    p.add_argument("--estimators", default="ekf,fixed-lag,batch", help="comma-separated list")
    p.add_argument("--seeds", type=_whole(1, "a number of noise seeds"),
                   help="simulate each scenario with this many noise seeds and aggregate")
    _add_input_options(p)
    p.add_argument("--ft", action="store_true", help="fuse the recording's F/T readings as measurements")
    p.add_argument("--footholds", action="store_true",
                   help="smoothers: estimate every contact episode's foothold (docs/smoother.md)")
    p.add_argument("--peers", action="store_true",
                   help="add every GTSAM legged estimator as a peer row, the fixed-lag smoother too (default: "
                        "the invariant EKF only)")
    p.add_argument("--calibrate-noise", action="store_true",
                   help="batch smoother: when its IMU residuals are above 3 sigma RMS, scale that sensor's noise by "
                        "their RMS and smooth again (BatchConfig.noise_calibration; for real walks)")
    p.add_argument("--jobs", "-j", type=_jobs, default=1, metavar="N",
                   help="compare N recordings at a time, in worker processes (default 1; 'auto': one per usable "
                        "core, as memory allows); the results are the same")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_compare)

    p = sub.add_parser("demo", help="simulate the default scenario, compare the estimators, write a report")
    p.add_argument("-o", "--output", type=Path, default=Path("flexforce-demo"), help="report folder (./flexforce-demo)")
    p.add_argument("--scenario", help="another built-in scenario or file")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("diagnose",
                       help="where the nominal model fails, which effect is missing, before/after adding it")
    p.add_argument("recording", nargs="+", help="bags, or built-in scenario names / scenario files to simulate "
                                                "(several: one report folder each, and an index)")
    p.add_argument("-o", "--output", required=True, type=Path, help="report folder (index.html, diagnosis.json)")
    p.add_argument("--jobs", "-j", type=_jobs, default="auto", metavar="N",
                   help="worker processes (default auto: one per usable core, as memory allows; 1: none; the "
                        "results are the same): several recordings, N at a time; one recording, its candidates' "
                        "tests and refits N at a time")
    p.add_argument("--add", action="append", default=[], metavar="NAME",
                   help="refit with this effect and compare before/after (repeatable; 'auto': the significant ones)")
    p.add_argument("--candidates", help="comma-separated effect names to rank (default: every built-in effect)")
    p.add_argument("--plugin", action="append", default=[], type=Path, metavar="FILE.py",
                   help="Python file with user-written effects, ranked like the built-in ones (repeatable)")
    p.add_argument("--max-effects", type=_whole(0, "a number of effects"), default=3,
                   help="at most this many effects selected (default 3)")
    p.add_argument("--no-rank", action="store_true", help="only refit with --add, no ranking")
    p.add_argument("--screen-level", type=float, default=0.01, metavar="P",
                   help="refit only the candidates whose score test at the nominal fit has p < P (default 0.01)")
    p.add_argument("--no-screen", action="store_true", help="refit every candidate (no score-test screening)")
    p.add_argument("--refit-best", type=int, default=3, metavar="N",
                   help="per selection round, refit the N candidates with the strongest score test (and those the "
                        "identifiability table cannot tell from them); the others wait for the next round "
                        "(default 3; 0: every candidate that passes)")
    p.add_argument("--no-ekf", action="store_true", help="do not run the EKF (innovations, NIS)")
    p.add_argument("--no-constancy", action="store_true",
                   help="take a constant effect without fitting it again on each half of the recording "
                        "(the constancy check: halves that disagree make it implausible)")
    p.add_argument("--no-check-veto", action="store_true",
                   help="take and add an effect even when its check against the truth or the reference sensors says "
                        "its errors rise more than they fall (default: turned down; --add auto adds no rise)")
    p.add_argument("--seed", type=_whole(0, "a noise seed"), help="noise seed when simulating a scenario")
    _add_input_options(p)
    p.add_argument("--ft", action="store_true", help="fuse the recording's F/T readings as measurements")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_diagnose)

    p = sub.add_parser("layout", help="a Foxglove (.json) or PlotJuggler (.xml) layout for the bag of "
                                      "'flexforce run REC -o OUT.mcap'")
    p.add_argument("kind", choices=("foxglove", "plotjuggler"), help="the viewer")
    p.add_argument("-o", "--output", required=True, type=Path, help="layout file: .json (foxglove), .xml (plotjuggler)")
    p.add_argument("--robot", help="robot name or .toml configuration: its contacts, and for raw robot bags its "
                                   "[ros] F/T and IMU topics (required without --bag; with --bag, default: the "
                                   "robot the bag names)")
    p.add_argument("--bag", type=Path, help="the exported bag: take the estimator, contacts, F/T and truth topics "
                                            "from it")
    p.add_argument("--estimator", help="the estimator of 'flexforce run' (default ekf)")
    p.add_argument("--truth", action="store_true", help="draw the ground truth (bags of 'flexforce simulate')")
    p.add_argument("--no-ft", action="store_true", help="do not draw the F/T readings")
    p.set_defaults(func=_cmd_layout)
    return parser


def interrupted(err: BaseException) -> bool:
    """``err`` is, or was caused by, a KeyboardInterrupt (through ``__cause__`` or ``__context__``).

    Ctrl-C landing inside a compiled (numba) kernel surfaces as ``SystemError: ... returned a
    result with an exception set`` whose context is the KeyboardInterrupt; a library that turned
    it into its own error keeps it as the cause.
    """
    seen: set[int] = set()
    stack: list[BaseException | None] = [err]
    while stack:
        e = stack.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, KeyboardInterrupt):
            return True
        stack += [e.__cause__, e.__context__]
    return False


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def exit_status(err: BaseException, command: str) -> int:
    """Print the one line for ``err`` (raised by ``command``) on stderr and return the exit status."""
    if interrupted(err):
        print(f"flexforce {command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    if isinstance(err, FlexforceError):
        message = _one_line(err) or type(err).__name__
    elif isinstance(err, OSError):
        where = f" {err.filename}" if err.filename else ""
        message = f"cannot access{where}: {_one_line(err.strerror or err)}"
    elif isinstance(err, MemoryError):
        message = "out of memory; expected a shorter recording (--start/--end) or a smaller problem"
    else:
        message = (f"internal error {type(err).__name__}: {_one_line(err)} (a bug in flexforce; "
                   "FLEXFORCE_DEBUG=1 shows its traceback)")
    print(f"flexforce {command}: error: {message}", file=sys.stderr)
    return EXIT_ERROR


def _show_warning(command: str):
    def show(message, category, filename, lineno, file=None, line=None):
        print(f"flexforce {command}: warning: {_one_line(message)}", file=sys.stderr)
    return show


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return its exit status (:data:`EXIT_STATUSES`)."""
    set_progress_origin(time.time())
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except KeyboardInterrupt:
        print("flexforce: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    if getattr(args, "quiet", False):
        from flexforce.jit import set_compile_notice

        set_compile_notice(False)
    with warnings.catch_warnings():
        warnings.showwarning = _show_warning(args.command)
        try:
            _apply_urdf(args)
            return args.func(args)
        except (SystemExit, GeneratorExit):
            raise
        except BaseException as err:  # noqa: BLE001 -- every path ends in one line and a documented status
            if os.environ.get("FLEXFORCE_DEBUG") and not interrupted(err):
                raise
            return exit_status(err, args.command)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
