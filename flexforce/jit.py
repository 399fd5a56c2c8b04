"""The one switch for compiled code: :func:`njit` (numba, cached, no GIL) or plain Python without numba.

Every compiled kernel of the package is decorated with :func:`njit` from here, so that how kernels
are compiled and where their cache lives is decided in one place.  It imports nothing of the project
and may be imported from every layer (as :mod:`flexforce.errors` and :mod:`flexforce.options`).
"""

from __future__ import annotations

__all__ = ["HAVE_NUMBA", "njit"]

try:  # pragma: no cover - exercised by whichever branch the machine has
    import numba

    def njit(fn):
        """``numba.njit(cache=True, nogil=True)(fn)``."""
        return numba.njit(cache=True, nogil=True)(fn)

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    # Same code, interpreted: correct but ~100x slower (the speed targets need numba).
    def njit(fn):
        """``fn`` itself (numba is not installed)."""
        return fn

    HAVE_NUMBA = False
