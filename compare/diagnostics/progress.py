"""The diagnosis's progress callbacks: a stage's fraction done and, for a callback that takes it,
a message naming the stage or candidate with what it found; :class:`DiagnosisProgress` adds to
the message which round of how many it belongs to, the time since the diagnosis began and an
estimate of the time left."""

from __future__ import annotations

import inspect
import time
from collections.abc import Callable

__all__ = ["DiagnosisProgress", "progress_caller"]


def progress_caller(progress) -> Callable[..., None] | None:
    """``call(label, fraction, message=None)`` for a ``progress`` callback: the message (which
    stage or candidate, what it found, the elapsed time) is passed as a third argument to a callback
    that takes one (a third positional parameter, ``*args`` or a ``message`` keyword), and left out
    for a two-argument ``progress(label, fraction)``."""
    if progress is None:
        return None
    try:
        params = list(inspect.signature(progress).parameters.values())
    except (TypeError, ValueError):  # a builtin without a signature: the two-argument form
        params = []
    positional = [p for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    takes = (len(positional) >= 3 or any(p.kind == p.VAR_POSITIONAL for p in params)
             or any(p.name == "message" for p in params))
    by_keyword = takes and len(positional) < 3 and not any(p.kind == p.VAR_POSITIONAL for p in params)

    def call(label: str, fraction: float, message: str | None = None) -> None:
        if not takes:
            progress(label, fraction)
        elif by_keyword:
            progress(label, fraction, message=message)
        else:
            progress(label, fraction, message)

    return call


def _takes_two(fn) -> bool:
    """Whether ``fn`` accepts two positional arguments."""
    try:
        inspect.signature(fn).bind(0.0, "")
    except TypeError:
        return False
    except ValueError:  # no signature available
        return False
    return True


def _duration(seconds: float) -> str:
    """``12.3 s``, ``4.5 min`` or ``1.2 h``."""
    if seconds < 90:
        return f"{seconds:.1f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


class DiagnosisProgress:
    """Notes for the messages of a diagnosis's progress (``progress(label, fraction, message)``):
    the selection round, out of how many at most, the time since the diagnosis began and an
    estimate of what is left.

    Rounds are read from the stage labels the diagnosis reports
    (:mod:`flexforce.compare.diagnostics.session`, :mod:`~flexforce.compare.diagnostics.selection`):
    ``screening`` opens round 1, ``screening at + a + b`` round 3; a refit ``+ a + b`` (the round's
    base and one candidate) belongs to round 2.  The rounds are at most ``m = min(max_effects,
    candidates)`` (each round but the last adds one effect; a round refits each remaining candidate
    at most once).  The time left is an upper estimate: the mean time per refit since round 1
    began (screenings included) times the refits left if no candidate were screened out, that is
    ``candidates - (r - 1)`` in round ``r`` less those done, for every round up to ``m``.

    Args:
        max_effects: :attr:`flexforce.compare.diagnostics.config.DiagnoseConfig.max_effects`.
        candidates: the number of candidates; None: read from the first screening (one call per
            candidate, fraction ``k / candidates``), unknown without one (no time left is given).
        clock: seconds, monotonic (``time.perf_counter``); the diagnosis begins at construction.
    """

    def __init__(self, max_effects: int, candidates: int | None = None,
                 clock: Callable[[], float] = time.perf_counter):
        self.max_effects = int(max_effects)
        self.candidates = candidates
        self.clock = clock
        self.start = clock()
        self.round = 0
        """The current round (0: before the first)."""
        self.refits = 0
        """Refits done in the rounds so far."""
        self.round_refits = 0
        """Refits done in the current round."""
        self.rounds_start: float | None = None
        self._done: set[str] = set()

    @property
    def rounds(self) -> int:
        """The most rounds there can be (``m``)."""
        if self.candidates is None:
            return self.max_effects
        return max(1, min(self.max_effects, self.candidates))

    def _enter(self, r: int) -> None:
        if r > self.round:
            self.round, self.round_refits = r, 0
            if self.rounds_start is None:
                self.rounds_start = self.clock()

    def refits_left(self) -> int | None:
        """At most this many refits are left (None: the number of candidates is unknown)."""
        if self.candidates is None or self.round == 0:
            return None
        n, r = self.candidates, self.round
        left = max(0, n - (r - 1) - self.round_refits)
        return left + sum(max(0, n - (q - 1)) for q in range(r + 1, self.rounds + 1))

    def update(self, label: str, fraction: float, message: str | None = None) -> str | None:
        """Record one progress call; returns ``message`` with the round and the times appended
        (None without a message)."""
        if label == "screening":
            self._enter(1)
            if self.candidates is None and 0.0 < fraction <= 1.0:
                self.candidates = max(1, int(round(1.0 / fraction)))
        elif label.startswith("screening at + "):
            self._enter(len(label[len("screening at + "):].split(" + ")) + 1)
        elif label.startswith("+ "):
            r = len(label[2:].split(" + "))
            self._enter(r)
            if fraction >= 1.0 and label not in self._done:
                self._done.add(label)
                self.refits += 1
                if r == self.round:
                    self.round_refits += 1
        if not message:
            return None
        now = self.clock()
        parts = []
        if label.startswith("second look"):
            parts.append("second look")
        elif self.round:
            parts.append(f"round {self.round} of {self.rounds}")
        parts.append(f"{_duration(now - self.start)} elapsed")
        left = self.refits_left()
        if left is not None and self.refits and self.rounds_start is not None:
            each = (now - self.rounds_start) / self.refits
            parts.append(f"at most ~{_duration(left * each)} left ({left} refit(s) at {_duration(each)} each)"
                         if left else "no refit left")
        elif self.round:
            parts.append("time left: known after the first refit")
        return f"{message} -- {', '.join(parts)}"
