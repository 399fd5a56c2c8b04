"""The one switch for compiled code: :func:`njit` (numba, cached, no GIL) or plain Python without numba.

Every compiled kernel of the package is decorated with :func:`njit` from here, so that how kernels
are compiled and where their cache lives is decided in one place.  It imports nothing of the project
and may be imported from every layer (as :mod:`flexforce.errors` and :mod:`flexforce.options`).

Where the compiled kernels are cached
-------------------------------------
Always in a per-user cache directory, :func:`kernel_cache_dir`: ``$XDG_CACHE_HOME/flexforce/numba``
(``~/.cache/flexforce/numba`` when ``XDG_CACHE_HOME`` is unset or not an absolute path), never
beside the sources by choice.  One rule for every kind of install: a wheel in a read-only or shared
``site-packages``, an editable checkout and a cluster's module tree all work the same way, each
user compiles once, and no compiled files are left in ``site-packages`` that uninstalling the
package would not remove.  Entries are keyed by the source file's path and content (numba's
own stamps), so a second checkout or an edited module never picks up stale code.

The choice is made per kernel, not for the process: the kernels' dispatchers get a numba
``FunctionCache`` whose locator list is, in order, numba's ``NUMBA_CACHE_DIR`` (an explicit
setting wins), the user directory above, the source tree's ``__pycache__`` and numba's own user
cache; the first one writable is used.  Other numba code in the process keeps numba's defaults
(``numba.config.CACHE_DIR`` is not touched), and numba's ``NUMBA_CACHE_LOCATOR_CLASSES``, when
set, still overrides the list.  When no location is writable the kernels are compiled in every
process, uncached.

The first compilation is announced: when a kernel is about to be compiled because the cache holds
no entry for it (first run, an upgrade, an edited source), one line goes to stderr, once per
process (:data:`COMPILE_NOTICE`; :func:`set_compile_notice` turns it on, off or back to "on a
terminal only").
"""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

__all__ = ["COMPILE_NOTICE", "HAVE_NUMBA", "kernel_cache_dir", "njit", "set_compile_notice"]

COMPILE_NOTICE = ("flexforce: compiling the numerical kernels (first run after an install or upgrade only, "
                  "about a minute on 2 cores; cached in {cache})...")
"""The line written to stderr before the first kernel of a process is compiled (``{cache}``: the
cache directory, :func:`kernel_cache_dir`)."""

_notice_mode: bool | None = None  # None: announce when stderr is a terminal
_announced = False
_notice_lock = threading.Lock()


def kernel_cache_dir() -> Path:
    """The per-user directory of the compiled kernels: ``$XDG_CACHE_HOME/flexforce/numba``, or
    ``~/.cache/flexforce/numba`` when ``XDG_CACHE_HOME`` is unset, empty or relative (as the XDG
    base directory specification says).  Read when a kernel is decorated; not created here."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    root = Path(base) if base and os.path.isabs(base) else Path.home() / ".cache"
    return root / "flexforce" / "numba"


def set_compile_notice(enabled: bool | None) -> None:
    """Whether the compile notice (:data:`COMPILE_NOTICE`) is written: ``True`` always, ``False``
    never (a command's ``--quiet``), ``None`` (the default) only when stderr is a terminal."""
    global _notice_mode
    _notice_mode = enabled


def _announce(cache_path: str | None) -> None:
    """Write the compile notice once per process, as :func:`set_compile_notice` says."""
    global _announced
    with _notice_lock:
        if _announced:
            return
        stream = sys.stderr
        mode = _notice_mode
        if mode is None:
            isatty = getattr(stream, "isatty", None)
            mode = bool(isatty and isatty())
        if not mode:
            return
        _announced = True
    where = str(kernel_cache_dir()) if cache_path is None else cache_path
    stream.write(COMPILE_NOTICE.format(cache=where) + "\n")
    stream.flush()


try:  # pragma: no cover - exercised by whichever branch the machine has
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False


def _kernel_cache_class():
    """The numba ``FunctionCache`` subclass of the kernels (module docstring), or ``None`` when this
    numba lacks the locator machinery it builds on (then numba's default cache is used)."""
    try:
        from numba.core import caching
    except ImportError:  # pragma: no cover
        return None
    needed = ("_CacheLocator", "_SourceFileBackedLocatorMixin", "UserProvidedCacheLocator", "InTreeCacheLocator",
              "UserWideCacheLocator", "CompileResultCacheImpl", "FunctionCache")
    if not all(hasattr(caching, name) for name in needed):  # pragma: no cover
        return None

    class UserCacheLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
        """numba locator: the kernels of ``py_file`` under :func:`kernel_cache_dir`, in a
        subfolder named after the source folder and a hash of its path (numba's scheme)."""

        def __init__(self, py_func, py_file):
            self._py_file = py_file
            self._lineno = py_func.__code__.co_firstlineno
            self._cache_path = str(kernel_cache_dir() / self.get_suitable_cache_subpath(py_file))

        def get_cache_path(self):
            return self._cache_path

    class KernelCacheImpl(caching.CompileResultCacheImpl):
        _locator_classes = [caching.UserProvidedCacheLocator, UserCacheLocator, caching.InTreeCacheLocator,
                            caching.UserWideCacheLocator]

    class KernelCache(caching.FunctionCache):
        """numba's ``FunctionCache`` with the locators above, announcing a compilation."""

        _impl_class = KernelCacheImpl

        def load_overload(self, sig, target_context):
            cres = super().load_overload(sig, target_context)
            if cres is None:  # not in the cache: the dispatcher compiles next
                _announce(self.cache_path)
            return cres

    return KernelCache


if HAVE_NUMBA:
    _KernelCache = _kernel_cache_class()

    def njit(fn):
        """``numba.njit(nogil=True)(fn)``, cached on disk where the module docstring says.

        Falls back to ``numba.njit(cache=True, nogil=True)`` if this numba has no locator
        machinery, and to no disk cache if no location is writable."""
        if _KernelCache is None:  # pragma: no cover
            return numba.njit(cache=True, nogil=True)(fn)
        disp = numba.njit(nogil=True)(fn)
        if not hasattr(disp, "_cache"):  # NUMBA_DISABLE_JIT: the plain function  # pragma: no cover
            return disp
        try:
            disp._cache = _KernelCache(fn)  # what Dispatcher.enable_caching does, with our locators
        except RuntimeError:  # numba: "cannot cache function ...: no locator available"
            pass
        return disp
else:  # pragma: no cover
    # Same code, interpreted: correct but ~100x slower (the speed targets need numba).
    def njit(fn):
        """``fn`` itself (numba is not installed)."""
        return fn
