"""flexforce.smoother: factor-graph smoothing of the flexible-contact model (batch and fixed-lag).

Public API: :func:`run_batch`, :func:`run_fixed_lag` (both return an Estimate), :func:`fit` (batch
smoothing with the fit statistics the diagnostics read, ``Estimate.meta["fit"]``), the effect
protocol :class:`Effect`, the noise rule :class:`NoiseRule` and :class:`Problem`.
"""

from flexforce.smoother.batch import fit, run_batch
from flexforce.smoother.problem import FAMILIES, Effect, NoiseRule, Problem, derive_sigmas

__all__ = ["fit", "run_batch", "run_fixed_lag", "Effect", "NoiseRule", "Problem", "derive_sigmas", "FAMILIES"]


def run_fixed_lag(rec, model, progress=None, lag: float = 1.0, **options):
    """Fixed-lag smoothing (see :mod:`flexforce.smoother.fixed_lag`)."""
    from flexforce.smoother.fixed_lag import run_fixed_lag as _run

    return _run(rec, model, progress=progress, lag=lag, **options)
