"""Compare the estimators on many recordings over a Dask cluster (docs/many-logs.md).

Each recording is one unit of work: the worker reads the bag, runs the estimators, writes the recording's
report where every worker can reach it (a shared file system) and sends back its Comparison
without the per-step estimates (a few kB); the client aggregates them as ``flexforce compare``
does for several recordings (:func:`flexforce.compare.runner.aggregate`) and writes the index.

    python docs/example_dask.py BAG [BAG ...] -o reports/ [--scheduler tcp://host:8786] [--robot icub]

Without ``--scheduler`` it starts a local cluster (one process per core).  The same functions
run on Ray: ``ray.get([ray.remote(compare_recording).remote(p, report) for p in paths])``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from flexforce.compare.runner import DEFAULT_ESTIMATORS, Comparison, aggregate, compare


def read_recording(path, robot: str | None = None):
    """A flexforce bag, or a raw robot bag imported with its robot configuration."""
    from flexforce.datasets.io.bagio import load_recording
    from flexforce.datasets.io.rosimport import import_bag, is_flexforce_bag

    path = Path(path)
    if is_flexforce_bag(path) or robot is None:
        return load_recording(path)
    return import_bag(path, robot)


def compare_recording(path, report: str | Path | None = None, estimators=DEFAULT_ESTIMATORS,
                      robot: str | None = None) -> Comparison:
    """Compare the estimators on one recording (runs on a worker); its report into ``report``."""
    from flexforce.compare.reports.comparison import write_report
    from flexforce.datasets.robot import RobotConfig
    from flexforce.factors.model import ModelConfig

    rec = read_recording(path, robot)
    model = ModelConfig.from_recording(rec, robot=RobotConfig.load(robot or rec.robot))
    comp = compare(rec, estimators=estimators, model=model)
    if report is not None:
        write_report(comp, rec, report)
    comp.estimates, comp.baseline_estimates = {}, {}  # the per-step arrays stay on the worker
    return comp


def compare_many(client, paths, out: str | Path | None = None, estimators=DEFAULT_ESTIMATORS,
                 robot: str | None = None) -> dict:
    """Compare every recording of ``paths`` on the cluster of ``client``; returns the aggregate
    (summary.json of ``flexforce compare`` over several recordings) and, with ``out``, writes the
    reports, summary.json and the index into that folder."""
    labels = [Path(p).stem for p in paths]
    if len(set(labels)) != len(labels):
        raise ValueError(f"recordings of the same name {labels}; expected one name per recording (its report folder)")
    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
    reports = [None if out is None else str(Path(out) / label) for label in labels]
    futures = client.map(compare_recording, [str(p) for p in paths], reports, estimators=estimators, robot=robot,
                         pure=False)
    comps = client.gather(futures)
    agg = aggregate(comps)
    if out is not None:
        from flexforce.compare.reports.comparison import write_index

        (Path(out) / "summary.json").write_text(json.dumps(agg, indent=2, allow_nan=False))
        write_index(out, [(label, c.summary()) for label, c in zip(labels, comps)], agg)
    return agg


def main(argv=None) -> int:
    from dask.distributed import Client, LocalCluster

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("recordings", nargs="+", type=Path)
    parser.add_argument("-o", "--output", type=Path, required=True, help="report folder")
    parser.add_argument("--scheduler", help="address of a running Dask scheduler (default: a local cluster)")
    parser.add_argument("--robot", help="robot configuration of raw robot bags")
    parser.add_argument("--estimators", default=",".join(DEFAULT_ESTIMATORS))
    args = parser.parse_args(argv)
    estimators = tuple(e.strip() for e in args.estimators.split(",") if e.strip())
    if args.scheduler:
        client = Client(args.scheduler)
    else:
        client = Client(LocalCluster(threads_per_worker=1))
    with client:
        agg = compare_many(client, args.recordings, args.output, estimators, args.robot)
    for key, row in agg["estimators"].items():
        print(f"{key:10s} force RMSE {row['rmse']['force_N']:.3g} N over {row['count']} recordings")
    print(f"report: {args.output / 'index.html'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
