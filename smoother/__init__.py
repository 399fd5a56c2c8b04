"""flexforce.smoother: factor-graph smoothing of the flexible-contact model (batch and fixed-lag).

Public API: :func:`run_batch`, :func:`run_fixed_lag` (both return an Estimate), :func:`fit` (batch
smoothing for the diagnostics: ``(Estimate, FitStatistics)``), the noise rule :class:`NoiseRule` and
:class:`Problem`.  The effect protocol :class:`Effect` and the :class:`ProblemView` it is written
against live in :mod:`flexforce.factors.effects`; they are re-exported here under their old path.
"""

from flexforce.smoother.batch import FitStatistics, fit, run_batch
from flexforce.smoother.problem import FAMILIES, Effect, NoiseRule, Problem, ProblemView, derive_sigmas

__all__ = ["fit", "FitStatistics", "run_batch", "run_fixed_lag", "Effect", "ProblemView", "NoiseRule", "Problem",
           "derive_sigmas", "FAMILIES"]


def run_fixed_lag(rec, model, progress=None, lag: float = 1.0, **options):
    """Fixed-lag smoothing (see :mod:`flexforce.smoother.fixed_lag`)."""
    from flexforce.smoother.fixed_lag import run_fixed_lag as _run

    return _run(rec, model, progress=progress, lag=lag, **options)
