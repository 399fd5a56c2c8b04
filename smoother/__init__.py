"""flexforce.smoother: factor-graph smoothing of the flexible-contact model (batch and fixed-lag).

Public API: :func:`run_batch` and :func:`run_fixed_lag` (both return an Estimate) with their
frozen options :class:`BatchConfig` and :class:`FixedLagConfig`, :func:`fit` (batch smoothing for
the diagnostics: ``(Estimate, FitStatistics)``), the noise rule :class:`NoiseRule` and
:class:`Problem`.  The gtsam export: :func:`to_gtsam` (the problem as a ``gtsam.NonlinearFactorGraph``,
its initial ``gtsam.Values`` and the :class:`GtsamKeys` that name every key) and :func:`from_gtsam`
(gtsam Values back to an Estimate), from :mod:`flexforce.smoother.graph`.  The effect protocol
:class:`Effect` and the :class:`ProblemView` it is written against live in
:mod:`flexforce.factors.effects`; they are re-exported here under their old path.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from flexforce.smoother.batch import BatchConfig, FitStatistics, fit, run_batch
from flexforce.smoother.problem import FAMILIES, Effect, NoiseRule, Problem, ProblemView, derive_sigmas

if TYPE_CHECKING:
    from flexforce.datasets.estimate import Estimate
    from flexforce.datasets.recording import Recording
    from flexforce.factors.model import ModelConfig
    from flexforce.smoother.fixed_lag import FixedLagConfig
    from flexforce.smoother.graph import GtsamKeys, from_gtsam, to_gtsam

__all__ = ["fit", "FitStatistics", "run_batch", "run_fixed_lag", "BatchConfig", "FixedLagConfig", "Effect",
           "ProblemView", "NoiseRule", "Problem",
           "derive_sigmas", "FAMILIES", "to_gtsam", "from_gtsam", "GtsamKeys"]

_GTSAM = ("to_gtsam", "from_gtsam", "GtsamKeys")


def __getattr__(name: str) -> Any:
    # The fixed-lag module imports gtsam (~85 ms): loaded on first use, not with the package (the
    # EKF and the batch smoother do not need it).
    if name == "FixedLagConfig":
        from flexforce.smoother.fixed_lag import FixedLagConfig

        return FixedLagConfig
    if name in _GTSAM:
        from flexforce.smoother import graph

        return getattr(graph, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def run_fixed_lag(rec: Recording, model: ModelConfig, config: FixedLagConfig | None = None, rest_p=None,
                  rest_R=None, progress: Callable[[float], None] | None = None, **options) -> Estimate:
    """Fixed-lag smoothing (:func:`flexforce.smoother.fixed_lag.run_fixed_lag`; ``config`` None: the
    default :class:`FixedLagConfig`)."""
    from flexforce.smoother.fixed_lag import FixedLagConfig
    from flexforce.smoother.fixed_lag import run_fixed_lag as _run

    return _run(rec, model, FixedLagConfig() if config is None else config, rest_p, rest_R, progress=progress,
                **options)
