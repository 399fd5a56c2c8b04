"""The diagnosis's progress callbacks: a stage's fraction done and, for a callback that takes it,
a message naming the stage or candidate with what it found."""

from __future__ import annotations

import inspect
from collections.abc import Callable


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
