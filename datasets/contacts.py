"""Which contacts are in force: a Schmitt trigger on the F/T normal force, or a fixed set.

A contact is *active* (in force) while its normal force -- the z component of the F/T reading
in the contact frame, the push of the ground on the robot, N -- says so, with hysteresis so
that noise near a single threshold does not make the contact chatter (a Schmitt trigger)::

    inactive --(F_n > on)--> active --(F_n < off)--> inactive,      off < on

The first sample starts active when ``F_n >= off`` (a robot standing at the start of a log is
in contact unless its force is clearly released).  A NaN force (sensor gap) holds the previous
state.  The iCub recordings' authors used on = 150 N, off = 120 N.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flexforce.errors import ConfigError

__all__ = ["ContactPhases", "fixed_contacts", "phases", "schmitt_trigger"]


def schmitt_trigger(force: np.ndarray, on: float, off: float) -> np.ndarray:
    """(N,) bool contact state from an (N,) normal force, N, with hysteresis ``off < on``."""
    if not off < on:
        raise ConfigError(f"Schmitt trigger needs off < on; got off = {off} N, on = {on} N")
    force = np.asarray(force, dtype=float)
    state = np.zeros(force.shape[0], dtype=bool)
    first = np.flatnonzero(np.isfinite(force))
    current = bool(force[first[0]] >= off) if first.size else False
    for k, f in enumerate(force):
        if current and f < off:
            current = False
        elif not current and f > on:
            current = True
        state[k] = current  # NaN compares False both ways: the state is held
    return state


def fixed_contacts(n: int, contact_names, active_names=()) -> np.ndarray:
    """(N, C) bool: the named contacts (all when ``active_names`` is empty) active throughout."""
    contact_names = tuple(contact_names)
    names = tuple(active_names) or contact_names
    unknown = [c for c in names if c not in contact_names]
    if unknown:
        raise ConfigError(f"fixed contact(s) {unknown} are not contacts of the robot; "
                          f"expected some of {list(contact_names)}")
    active = np.zeros((n, len(contact_names)), dtype=bool)
    for name in names:
        active[:, contact_names.index(name)] = True
    return active


@dataclass(frozen=True)
class ContactPhases:
    """Intervals of one contact, in seconds from the first sample: ``[(start, end), ...]``."""

    name: str
    intervals: tuple[tuple[float, float], ...]


def phases(time: np.ndarray, active: np.ndarray, contact_names) -> list[ContactPhases]:
    """The active intervals of each contact (end = time of the last active sample)."""
    out = []
    for i, name in enumerate(contact_names):
        col = np.asarray(active[:, i], dtype=bool)
        edges = np.diff(np.concatenate([[False], col, [False]]).astype(int))
        starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
        out.append(ContactPhases(name, tuple((float(time[a]), float(time[b])) for a, b in zip(starts, stops))))
    return out
