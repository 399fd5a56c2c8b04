"""One entry point for every estimator, used by the command line and the comparisons."""

from __future__ import annotations

from collections.abc import Callable

from flexforce.errors import ConfigError

ESTIMATORS = ("ekf", "fixed-lag", "batch")
"""Names accepted by :func:`run_estimator` (``fixed_lag`` is accepted for ``fixed-lag``)."""


def run_estimator(name: str, rec, model=None, progress: Callable[[float], None] | None = None, **options):
    """Run estimator ``name`` on a Recording and return its Estimate.

    Args:
        name: ``ekf`` (the seed paper's filter), ``fixed-lag`` or ``batch`` (factor-graph smoothers).
        rec: a :class:`flexforce.datasets.recording.Recording`.
        model: a :class:`flexforce.factors.model.ModelConfig`; the recording's nominal model if None.
        progress: called with the fraction done.
        options: passed to the estimator (e.g. ``lag`` for the fixed-lag smoother).
    """
    from flexforce.factors.model import ModelConfig

    key = name.replace("_", "-").lower()
    if key not in ESTIMATORS:
        raise ConfigError(f"unknown estimator '{name}'; expected one of {', '.join(ESTIMATORS)}")
    rec.validate()
    if model is None:
        model = ModelConfig.from_recording(rec)
    if key == "ekf":
        from flexforce.compare.ekf import run_ekf

        return run_ekf(rec, model, progress=progress, **options)
    if key == "batch":
        from flexforce.smoother import run_batch

        return run_batch(rec, model, progress=progress, **options)
    from flexforce.smoother import run_fixed_lag

    return run_fixed_lag(rec, model, progress=progress, **options)
