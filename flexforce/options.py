"""Validation of the estimators' frozen config dataclasses and of their keyword options.

Each estimator's options are one frozen dataclass beside it (:class:`flexforce.compare.ekf.filter.EKFConfig`,
:class:`flexforce.smoother.batch.BatchConfig`, :class:`flexforce.smoother.fixed_lag.FixedLagConfig`,
:class:`flexforce.smoother.problem.NoiseRule`); their ``__post_init__`` checks every field with the
helpers below, so that a bad option is a :class:`~flexforce.errors.ConfigError` that names the
option, its value, its unit and what is expected::

    FixedLagConfig.lag = -1.0 s; expected a positive duration

:func:`with_options` builds a config from loose keyword options (the estimators' older calling
convention, and a TOML table mapped one to one onto the fields); :func:`read_toml` reads a
configuration file (a robot's, a scenario's) into its table.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import tomllib
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from flexforce.errors import ConfigError

C = TypeVar("C")


def article(noun: str) -> str:
    """``a`` or ``an`` before ``noun``, as it is read aloud (``an EKFConfig``, ``a FixedLagConfig``)."""
    return "an" if noun[:1] in "AEIOaeio" else "a"


def invalid(owner: str, name: str, value: Any, unit: str, expected: str) -> ConfigError:
    """The error for field ``name`` of ``owner`` holding ``value`` (in ``unit``, '' if none)."""
    shown = f"{value!r} {unit}" if unit else f"{value!r}"
    return ConfigError(f"{owner}.{name} = {shown}; expected {expected}")


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def check_finite(owner: str, name: str, value: Any, unit: str, expected: str) -> None:
    """A finite number."""
    if not _is_real(value):
        raise invalid(owner, name, value, unit, expected)


def check_positive(owner: str, name: str, value: Any, unit: str, expected: str, optional: bool = False) -> None:
    """A finite number > 0 (or None when ``optional``)."""
    if optional and value is None:
        return
    if not (_is_real(value) and value > 0):
        raise invalid(owner, name, value, unit, expected)


def check_fraction(owner: str, name: str, value: Any, expected: str) -> None:
    """A finite number in [0, 1] (dimensionless)."""
    if not (_is_real(value) and 0.0 <= value <= 1.0):
        raise invalid(owner, name, value, "", expected)


def check_int(owner: str, name: str, value: Any, minimum: int, unit: str, expected: str) -> None:
    """An integer (not a bool) >= ``minimum``."""
    if not (isinstance(value, numbers.Integral) and not isinstance(value, bool) and int(value) >= minimum):
        raise invalid(owner, name, value, unit, expected)


def check_bool(owner: str, name: str, value: Any) -> None:
    """True or False (numpy's bool included)."""
    if not isinstance(value, bool | np.bool_):
        raise invalid(owner, name, value, "", "True or False")


def check_choice(owner: str, name: str, value: Any, choices: tuple[str, ...]) -> None:
    """One of ``choices``."""
    if value not in choices:
        raise invalid(owner, name, value, "", " or ".join(repr(c) for c in choices))


def check_type(owner: str, name: str, value: Any, cls: type) -> None:
    """An instance of ``cls`` (a nested config)."""
    if not isinstance(value, cls):
        raise invalid(owner, name, value, "", f"{article(cls.__name__)} {cls.__name__}")


def with_options(config: C, options: dict[str, Any], what: str) -> C:
    """``config`` with the fields in ``options`` replaced (``dataclasses.replace``, which validates).

    ``what`` names the estimator in the error for an unknown option, e.g. ``fixed-lag smoother``.

    Raises:
        ConfigError: an option that is not a field of the config (listing the known ones), or a
            bad value (from the config's ``__post_init__``).
    """
    if not options:
        return config
    known = [f.name for f in dataclasses.fields(config)]  # type: ignore[arg-type]
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise ConfigError(f"unknown {what} option(s) {unknown}; known: {', '.join(known)}")
    return dataclasses.replace(config, **options)  # type: ignore[type-var]


def require_config(config: Any, cls: type, what: str) -> None:
    """``config`` is a ``cls`` (a ConfigError naming the expected type otherwise)."""
    if not isinstance(config, cls):
        got = type(config).__name__
        raise ConfigError(f"{what}: config is {article(got)} {got} ({config!r}); expected {article(cls.__name__)} "
                          f"{cls.__name__}")


def read_toml(path: Path, what: str, missing: str | None = None) -> dict[str, Any]:
    """The table of the configuration file ``path``; a :class:`ConfigError` naming ``what`` (``robot
    configuration``, ``scenario``) when it is not valid TOML, and ``missing`` (default ``what``) when
    the file does not exist."""
    if not path.exists():
        raise ConfigError(f"{missing or what} not found: {path}")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{what} {path} is not valid TOML: {err}") from err
