"""The ``flexforce`` command line: a thin layer over the library.

Known errors (:class:`flexforce.errors.FlexforceError`) become one line on stderr and exit
status 1; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from flexforce.errors import FlexforceError


class Progress:
    """A one-line progress bar on stderr (silent when stderr is not a terminal, unless forced)."""

    def __init__(self, label: str, enabled: bool | None = None, width: int = 30):
        self.label = label
        self.width = width
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self.start = time.perf_counter()
        self._last = -1

    def __call__(self, fraction: float) -> None:
        if not self.enabled:
            return
        pct = int(100 * min(max(fraction, 0.0), 1.0))
        if pct == self._last:
            return
        self._last = pct
        filled = int(self.width * pct / 100)
        elapsed = time.perf_counter() - self.start
        sys.stderr.write(f"\r{self.label:<24s} [{'#' * filled}{'.' * (self.width - filled)}] {pct:3d}% {elapsed:6.1f}s")
        if pct >= 100:
            sys.stderr.write("\n")
        sys.stderr.flush()


def _cmd_simulate(args) -> int:
    from flexforce.datasets.bagio import save_recording
    from flexforce.datasets.scenario import Scenario
    from flexforce.datasets.simulator import Simulator

    scenario = Scenario.load(args.scenario)
    if args.robot:
        scenario.robot = args.robot
    if args.duration:
        scenario.duration = args.duration
    if args.seed is not None:
        scenario.seed = args.seed
    sim = Simulator(scenario, noise=not args.no_noise)
    rec = sim.run(progress=Progress(f"simulate {scenario.name}", enabled=not args.quiet and None))
    out = save_recording(rec, args.output, overwrite=args.force)
    print(f"wrote {out}: {rec.n} samples at {1.0 / rec.dt:.0f} Hz, robot {sim.robot.name}, "
          f"scenario {scenario.name}")
    return 0


def _cmd_run(args) -> int:
    from flexforce.datasets.bagio import load_recording
    from flexforce.estimators import run_estimator
    from flexforce.factors.model import ModelConfig

    rec = load_recording(args.recording)
    model = ModelConfig.from_recording(rec, robot=args.robot, use_ft=args.ft)
    options = {}
    if args.lag is not None:
        options["lag"] = args.lag
    est = run_estimator(args.estimator, rec, model, progress=Progress(f"{args.estimator}", enabled=not args.quiet and None),
                        **options)
    out = est.save(args.output)
    tps = est.time_per_step
    timing = f", {1e6 * float(sorted(tps)[len(tps) // 2]):.0f} us per step (median)" if tps is not None else ""
    print(f"wrote {out}: {est.n} steps in {est.total_time:.2f} s{timing}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="flexforce",
        description="Contact forces and floating-base kinematics of flexible legged robots from an IMU "
                    "and joint encoders.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="simulate a scenario into a ROS 2 bag (MCAP) with ground truth")
    p.add_argument("scenario", help="built-in scenario name (stand, com-step, push-pitch, push-roll, sway, "
                                    "weight-shift, step) or a scenario .toml file")
    p.add_argument("-o", "--output", required=True, type=Path, help="bag directory to write")
    p.add_argument("--robot", help="robot name or .toml configuration (overrides the scenario's)")
    p.add_argument("--duration", type=float, help="duration in s (overrides the scenario's)")
    p.add_argument("--seed", type=int, help="noise seed (overrides the scenario's)")
    p.add_argument("--no-noise", action="store_true", help="exact sensor readings")
    p.add_argument("--force", action="store_true", help="overwrite an existing output")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser("run", help="run one estimator on a recording and save its estimate (.npz)")
    p.add_argument("recording", type=Path, help="bag written by 'flexforce simulate' (or a flexforce recording)")
    p.add_argument("--estimator", default="ekf", help="ekf (the seed paper's filter), fixed-lag or batch")
    p.add_argument("-o", "--output", required=True, type=Path, help="estimate file to write (.npz)")
    p.add_argument("--robot", help="robot name or .toml configuration (default: the recording's)")
    p.add_argument("--ft", action="store_true", help="fuse the recording's F/T readings as measurements")
    p.add_argument("--lag", type=float, help="fixed-lag window, s (default 1)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except FlexforceError as err:
        print(f"flexforce {args.command}: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
