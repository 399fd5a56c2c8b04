"""docs/example_dask.py on a local Dask cluster gives the numbers of the library run in this process."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from flexforce.compare.runner import compare
from flexforce.datasets.io.bagio import load_recording, save_recording
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator

distributed = pytest.importorskip("dask.distributed")

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "example_dask.py"


def load_example():
    spec = importlib.util.spec_from_file_location("example_dask", EXAMPLE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_example_dask_on_a_local_cluster(tmp_path):
    example = load_example()
    paths = []
    for seed in (1, 2):
        sc = Scenario.load("push-pitch")
        sc.duration = 0.6
        sc.seed = seed
        paths.append(save_recording(Simulator(sc).run(), tmp_path / f"push-{seed}"))
    # one in-process worker thread: the test's own interpreter (processes=False)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        agg = example.compare_many(client, paths, tmp_path / "reports", estimators=("ekf",))
    direct = [compare(load_recording(p), estimators=("ekf",)) for p in paths]
    got = [json.loads((tmp_path / "reports" / f"push-{s}" / "summary.json").read_text()) for s in (1, 2)]
    for g, d in zip(got, direct):
        assert g["estimators"]["ekf"]["rmse"] == pytest.approx(d.summary()["estimators"]["ekf"]["rmse"], rel=1e-12)
    mean = sum(d.metrics["ekf"].rmse["force_N"] for d in direct) / 2
    assert agg["estimators"]["ekf"]["count"] == 2
    assert agg["estimators"]["ekf"]["rmse"]["force_N"] == pytest.approx(mean, rel=1e-12)
    page = (tmp_path / "reports" / "index.html").read_text()
    assert 'href="push-1/index.html"' in page and 'href="push-2/index.html"' in page
    with pytest.raises(ValueError, match="same name"):
        example.compare_many(None, [paths[0], paths[0]])
