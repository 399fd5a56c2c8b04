"""Running a recording end to end: the library functions behind ``flexforce run`` and friends.

This layer sits above the estimators, the I/O and the simulator and may import all of them.
"""

from __future__ import annotations

import warnings

import numpy as np

from flexforce.smoother.fixed_lag import FixedLagConfig
from flexforce.smoother.stream import FixedLagStream

__all__ = ["warm_up"]


def warm_up() -> None:
    """Load the stream's compiled code (numba's cache: ~1 s) by smoothing a short simulated
    recording, with and without covariances, and the CSV formatting: ``flexforce run`` calls it
    while the import's first part is awaited, so that the stream runs at speed from its first update."""
    from flexforce.datasets.io.csvformat import format_rows
    from flexforce.datasets.sim.scenario import Scenario
    from flexforce.datasets.sim.simulator import Simulator
    from flexforce.factors.model import ModelConfig

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
