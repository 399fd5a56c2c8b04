r"""The state layout: the order, units and frames of the 18 state components, defined once.

Every estimator's output (:class:`~flexforce.datasets.estimate.Estimate`: its ``cov``, the
``std_*`` columns of an export) and every per-step Jacobian of the physics core
(:mod:`flexforce.factors.core`, its ``STATE_DIM`` columns) use this order::

    s = (theta, t, w, v, dw, a)        18 components: rad, m, rad/s, m/s, rad/s^2, m/s^2

all world-frame increments, rotation first: ``theta`` perturbs the flexibility rotation on the
left, ``R <- exp([theta]x) R`` (``R`` local to world), the other blocks add to their quantity.
An estimator with another internal order (the EKF's eq. (4)) states it as a permutation of these
block names (:meth:`StateLayout.index`) and converts at its output.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from flexforce.errors import ConfigError

__all__ = ["Block", "StateLayout", "STATE", "STATE_DIM", "STATE_LABELS"]


@dataclass(frozen=True)
class Block:
    """One 3-vector block of the state."""

    name: str
    """Short name, the prefix of its labels (``theta``, ``t``, ...)."""
    index: slice
    """Its components in the state vector, ``slice(3 i, 3 i + 3)``."""
    unit: str
    """Unit of each component (``rad``, ``m``, ``rad/s``, ...)."""
    frame: str
    """The axes it is expressed in and what it is."""

    @property
    def labels(self) -> tuple[str, str, str]:
        """``(<name>_x, <name>_y, <name>_z)``."""
        return (f"{self.name}_x", f"{self.name}_y", f"{self.name}_z")


@dataclass(frozen=True)
class StateLayout:
    """An ordered tuple of 3-vector blocks: the columns of a state vector, covariance or Jacobian."""

    blocks: tuple[Block, ...]
    """The blocks in state order; block ``i`` holds components ``3 i .. 3 i + 2``."""

    @property
    def dim(self) -> int:
        """Number of components (18)."""
        return 3 * len(self.blocks)

    @property
    def names(self) -> tuple[str, ...]:
        """Block names in state order."""
        return tuple(b.name for b in self.blocks)

    @property
    def labels(self) -> tuple[str, ...]:
        """Component labels in state order (``theta_x`` ... ``a_z``)."""
        return tuple(label for b in self.blocks for label in b.labels)

    def block(self, name: str) -> Block:
        """The block called ``name``; raises :class:`ConfigError` for an unknown name."""
        for b in self.blocks:
            if b.name == name:
                return b
        raise ConfigError(f"unknown state block {name!r}; expected one of {self.names}")

    def __getitem__(self, name: str) -> slice:
        """``layout["t"]``: the slice of block ``name`` in the state vector."""
        return self.block(name).index

    def _check_order(self, order: Sequence[str]) -> None:
        if sorted(order) != sorted(self.names):
            raise ConfigError(f"state order {tuple(order)} is not a permutation of {self.names}")

    def index(self, order: Sequence[str]) -> np.ndarray:
        """(dim,) int: the components of the state in the block order ``order`` (a permutation of
        :attr:`names`), so that ``s[layout.index(order)]`` is ``s`` rearranged into ``order``
        and ``P[np.ix_(i, i)]`` its covariance.  Raises :class:`ConfigError` if ``order`` is not
        a permutation of the block names."""
        self._check_order(order)
        return np.concatenate([np.arange(self[name].start, self[name].stop) for name in order])

    def slices(self, order: Sequence[str]) -> tuple[slice, ...]:
        """The slices of the blocks, in ``order``, within a vector rearranged into ``order``
        (block ``order[i]`` at ``slice(3 i, 3 i + 3)``).  Raises as :meth:`index`."""
        self._check_order(order)
        return tuple(slice(3 * i, 3 * i + 3) for i in range(len(order)))


def _blocks(*spec: tuple[str, str, str]) -> tuple[Block, ...]:
    return tuple(Block(name, slice(3 * i, 3 * i + 3), unit, frame) for i, (name, unit, frame) in enumerate(spec))


STATE = StateLayout(_blocks(
    ("theta", "rad", "world; rotation increment, R <- exp([theta]x) R, R local to world"),
    ("t", "m", "world; flexibility translation"),
    ("w", "rad/s", "world; angular velocity"),
    ("v", "m/s", "world; linear velocity, dt/dt"),
    ("dw", "rad/s^2", "world; angular acceleration, dw/dt"),
    ("a", "m/s^2", "world; linear acceleration, d2t/dt2"),
))
"""The state layout of every estimate and every per-step Jacobian: ``(theta, t, w, v, dw, a)``."""

STATE_DIM = STATE.dim
"""Number of state components (18)."""

STATE_LABELS = STATE.labels
"""Names of the 18 state components (rad, m, rad/s, m/s, rad/s^2, m/s^2)."""
