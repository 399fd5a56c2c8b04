"""One entry point for every estimator, used by the command line and the comparisons."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from flexforce.errors import ConfigError
from flexforce.options import article

ESTIMATORS = ("ekf", "fixed-lag", "batch")
"""Names accepted by :func:`run_estimator` (``fixed_lag`` is accepted for ``fixed-lag``)."""


def estimator_key(name: str) -> str:
    """The canonical name of estimator ``name`` (``fixed_lag`` -> ``fixed-lag``).

    Raises:
        ConfigError: an unknown estimator, listing the known ones.
    """
    key = str(name).replace("_", "-").lower()
    if key not in ESTIMATORS:
        raise ConfigError(f"unknown estimator '{name}'; expected one of {', '.join(ESTIMATORS)}")
    return key


def run_estimator(name: str, rec, model=None, config: Any = None, progress: Callable[[float], None] | None = None,
                  **options):
    """Run estimator ``name`` on a Recording and return its Estimate.

    Args:
        name: ``ekf`` (the seed paper's filter), ``fixed-lag`` or ``batch`` (factor-graph smoothers).
        rec: a :class:`flexforce.datasets.recording.Recording`.
        model: a :class:`flexforce.factors.model.ModelConfig`; the recording's nominal model if None.
        config: the estimator's options, :class:`flexforce.compare.ekf.filter.EKFConfig`,
            :class:`flexforce.smoother.FixedLagConfig` or :class:`flexforce.smoother.BatchConfig`
            (None: its defaults).
        progress: called with the fraction done.
        options: fields of the estimator's config replacing those of ``config`` (e.g. ``lag`` for
            the fixed-lag smoother), and its other arguments (``rest_p``, ``rest_R``; ``x0``, ``P0``
            for the EKF).

    Raises:
        ConfigError: an unknown estimator, a config of another estimator's type (naming the expected
            one), an unknown option or a bad value.
        DataError: an invalid recording, or one shorter than
            :attr:`~flexforce.datasets.recording.Recording.MIN_SAMPLES` samples.
    """
    from flexforce.factors.model import ModelConfig

    key = estimator_key(name)
    cls: type
    run: Callable[..., Any]
    if key == "ekf":
        from flexforce.compare.ekf.filter import EKFConfig, run_ekf

        cls, run = EKFConfig, run_ekf
    elif key == "batch":
        from flexforce.smoother.batch import BatchConfig, run_batch

        cls, run = BatchConfig, run_batch
    else:
        from flexforce.smoother.fixed_lag import FixedLagConfig, run_fixed_lag

        cls, run = FixedLagConfig, run_fixed_lag
    if config is None:
        config = cls()
    elif not isinstance(config, cls):
        got = type(config).__name__
        raise ConfigError(f"estimator '{key}' takes {article(cls.__name__)} {cls.__name__}, got {article(got)} {got} "
                          f"({config!r})")
    rec.validate()
    rec.require_samples()
    if model is None:
        model = ModelConfig.from_recording(rec)
    return run(rec, model, config=config, progress=progress, **options)
