"""Exceptions: one base class, one subclass per layer.

The command-line interface turns any :class:`FlexforceError` into a single line on stderr and
exit status 1; anything else is a bug and keeps its traceback.
"""


class FlexforceError(Exception):
    """Base class of every error flexforce raises on purpose."""


class ConfigError(FlexforceError):
    """A robot configuration, scenario file or option is invalid."""


class DataError(FlexforceError):
    """Input data is malformed: NaN, wrong shape, time going backwards, missing fields."""


class OutputError(FlexforceError):
    """An output cannot be written: its folder is missing or read-only, its suffix unknown, it
    exists and may not be replaced, or another process is writing it."""


class BagError(DataError):
    """A ROS bag cannot be read or written, or lacks what is expected."""


class ModelError(FlexforceError):
    """The physical model cannot be evaluated (singular inertia, unstable stiffness...)."""


class EstimatorError(FlexforceError):
    """An estimator failed: diverging filter, covariance no longer positive definite..."""


class ConfigWarning(UserWarning):
    """A configuration that works but is probably not what was meant (e.g. a contact spring too soft
    for single support); the command line prints it as one line."""
