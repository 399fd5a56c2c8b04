"""Worker processes that end with their parent (the ground layer: standard library only).

A parent killed outright (SIGKILL, out of memory) runs no clean-up: its worker processes (a
comparison's or a diagnosis's pool, a streamed import's producer) would wait for work or for room
in a queue for ever, each holding its memory.  :func:`exit_with_parent`, called first in a
worker, ends it when its parent dies.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Callable

__all__ = ["PR_SET_PDEATHSIG", "exit_with_parent", "libc_prctl", "watch_parent"]

PR_SET_PDEATHSIG = 1
"""prctl(2) option: the signal the kernel sends this process when its parent dies (Linux)."""


def libc_prctl() -> Callable[..., int] | None:
    """libc's ``prctl`` (Linux); None where the platform has none or it cannot be loaded."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


def watch_parent(parent_pid: int, period: float = 1.0) -> None:
    """End this process (``os._exit``) once its parent is no longer ``parent_pid``; checks every
    ``period`` s, forever."""
    while os.getppid() == parent_pid:
        time.sleep(period)
    os._exit(1)


def exit_with_parent(parent_pid: int, prctl: Callable[..., int] | None = None) -> None:
    """Make this (worker) process end when its parent ``parent_pid`` dies.

    On Linux the kernel sends it SIGTERM when the parent dies (``prctl(PR_SET_PDEATHSIG)``, with
    ``prctl`` libc's, :func:`libc_prctl`; strictly, when the parent's thread that started the
    worker ends); where that is not available (``prctl`` None or failing) a daemon thread checks
    the parent every second.  A parent that died before this was set up is seen at once: the
    worker's parent is no longer ``parent_pid``, and it exits.
    """
    if prctl is None or prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) != 0:
        threading.Thread(target=watch_parent, args=(parent_pid,), name="flexforce-watch-parent", daemon=True).start()
    if os.getppid() != parent_pid:
        os._exit(1)
