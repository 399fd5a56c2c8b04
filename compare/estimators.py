"""One entry point for every estimator, used by the command line and the comparisons."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from flexforce.errors import ConfigError
from flexforce.options import article

if TYPE_CHECKING:
    from flexforce.datasets.estimate import Estimate
    from flexforce.datasets.recording import Recording
    from flexforce.factors.model import ModelConfig

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


def nominal_model(rec: Recording, robot: Any = None, **overrides) -> ModelConfig:
    """The nominal model of ``rec`` with the robot configuration ``robot``, its springs checked
    against gravity toppling on the recording's first sample.

    An estimator run on springs that cannot hold the robot upright fails slowly and obscurely (its
    covariances blow up), so the check comes first (:func:`flexforce.datasets.robot.check_toppling`,
    DESIGN.md "Stability").

    Args:
        rec: a :class:`flexforce.datasets.recording.Recording`.
        robot: a :class:`flexforce.datasets.robot.RobotConfig` or
            :class:`~flexforce.datasets.robot.RobotModel`, a built-in robot name or a ``.toml`` path
            (None: the recording's robot).
        overrides: fields of the :class:`flexforce.factors.model.ModelConfig` replacing the nominal
            ones (e.g. ``use_ft=True``).

    Returns:
        The :class:`flexforce.factors.model.ModelConfig` of
        :meth:`~flexforce.factors.model.ModelConfig.from_recording`.

    Raises:
        ConfigError: an unknown robot, or springs whose tilt stiffness with the contacts in force at
            the first sample does not exceed the gravity toppling stiffness ``m g h`` (N m/rad).

    Warns:
        ConfigWarning: one contact alone cannot hold the robot upright (``k_ts <= m g h``), so single
            support will not be explained.
    """
    from flexforce.datasets.robot import RobotConfig, RobotModel, check_toppling
    from flexforce.factors.model import ModelConfig

    if isinstance(robot, RobotModel):
        robot = robot.config
    config = RobotConfig.load(robot or rec.robot)
    active = rec.contact_active[0]
    check_toppling(config.stiffness, rec.mass, rec.com[0], rec.contact_p[0][active], rec.contact_R[0][active],
                   rec.gravity, config.name)
    return ModelConfig.from_recording(rec, robot=config, **overrides)


def run_estimator(name: str, rec: Recording, model: ModelConfig | None = None, config: Any = None,
                  progress: Callable[[float], None] | None = None, **options) -> Estimate:
    """Run estimator ``name`` on a Recording and return its Estimate.

    Args:
        name: ``ekf`` (the seed paper's filter), ``fixed-lag`` or ``batch`` (factor-graph smoothers).
        rec: a :class:`flexforce.datasets.recording.Recording`.
        model: a :class:`flexforce.factors.model.ModelConfig`, taken as it is; None: the nominal
            model of the recording's robot, its springs checked against toppling
            (:func:`nominal_model`).
        config: the estimator's options, :class:`flexforce.compare.ekf.filter.EKFConfig`,
            :class:`flexforce.smoother.FixedLagConfig` or :class:`flexforce.smoother.BatchConfig`
            (None: its defaults).
        progress: called with the fraction done.
        options: fields of the estimator's config replacing those of ``config`` (e.g. ``lag`` for
            the fixed-lag smoother), and its other arguments (``rest_p``, ``rest_R``; ``x0``, ``P0``
            for the EKF).

    Raises:
        ConfigError: an unknown estimator, a config of another estimator's type (naming the expected
            one), an unknown option or a bad value; without ``model``, springs that cannot hold the
            robot upright (:func:`nominal_model`).
        DataError: an invalid recording, or one shorter than
            :attr:`~flexforce.datasets.recording.Recording.MIN_SAMPLES` samples.

    Warns:
        ConfigWarning: without ``model``, springs with which one contact alone cannot hold the robot
            upright (:func:`nominal_model`).
    """
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
        model = nominal_model(rec)
    return run(rec, model, config=config, progress=progress, **options)
