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

Each signature's compiled code is a data file named after its index key (not numbered as numba
does), written before its index entry: processes caching kernels at once cannot overwrite each
other's code or be pointed at a missing file (at worst an index entry is lost and compiled again).

How long the first compilation takes
------------------------------------
A kernel called from another kernel is compiled for the *types* of its arguments: numba would
compile it once per literal value of a constant argument (``ld3(x, 0)``, ``ld3(x, 3)``, ... and
every caller again with them).  The demo's kernels take 15 % less to compile so (81 s of CPU
instead of 95 s).  LLVM inlines the callee and folds the constant all the same: the code run is
unchanged.

:func:`compile_elsewhere` shares the compilation of a listing of kernels with a helper process,
whose results this process awaits and loads from the cache instead of compiling them itself
(``flexforce demo`` on a first run: a helper compiles the smoothers' kernels while the demo
simulates and compiles the EKF's; :func:`cached` tells whether there is anything to compile).

The first compilation is announced: when a kernel is about to be compiled because the cache holds
no entry for it (first run, an upgrade, an edited source), or helpers are started, one line goes
to stderr, once per process (:data:`COMPILE_NOTICE`; :func:`set_compile_notice` turns it on, off
or back to "on a terminal only").
"""

from __future__ import annotations

import atexit
import contextlib
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

__all__ = ["COMPILE_NOTICE", "HAVE_NUMBA", "announce_compilation", "cached", "compile_elsewhere",
           "compile_while_awaiting", "kernel_cache_dir", "njit", "recording_compiles", "set_compile_notice"]

COMPILE_NOTICE = ("flexforce: compiling the numerical kernels (first run after an install or upgrade only; "
                  "cached in {cache})...")
"""The line written to stderr before the first kernel of a process is compiled (``{cache}``: the
cache directory, :func:`kernel_cache_dir`)."""

_notice_mode: bool | None = None  # None: announce when stderr is a terminal
_announced = False
_notice_lock = threading.Lock()
_helpers: list[subprocess.Popen] = []  # processes of compile_elsewhere still to be waited for
_work: list[str] = []  # their work folders
_listed: dict[tuple[str, str, str], tuple[str, int]] = {}  # kernel -> (work folder, index) of compile_elsewhere
_mine: set[tuple[str, int]] = set()  # (work folder, index) taken by compile_while_awaiting in this process
HELPER_WAIT = 900.0
"""Seconds a kernel missing from the cache is awaited from the helper processes at most."""


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


def announce_compilation() -> None:
    """Write the compile notice now (once per process, as :func:`set_compile_notice` says): a
    command about to compile kernels it knows the cache lacks says so before its first one."""
    _announce(None)


def _helpers_running() -> bool:
    """Whether a process of :func:`compile_elsewhere` is still compiling (those done are forgotten)."""
    _helpers[:] = [p for p in _helpers if p.poll() is None]
    return bool(_helpers)


def _stop_helpers() -> None:
    """End the helper processes still running (at exit: what they compile is not awaited any more)
    and remove their work folders."""
    for proc in _helpers:
        if proc.poll() is None:
            proc.terminate()
    for proc in _helpers:
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:  # pragma: no cover
            proc.kill()
    _helpers.clear()
    for folder in _work:
        shutil.rmtree(folder, ignore_errors=True)
    _work.clear()
    _listed.clear()
    _mine.clear()


def _take(work: str, index: int) -> bool:
    """Take kernel ``index`` of ``work``'s listing (its file created exclusively): False when
    another process has taken it (or the folder is gone)."""
    try:
        os.close(os.open(os.path.join(work, f"{index}.taken"), os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except OSError:  # FileExistsError: taken; any other: the work folder is gone
        return False
    return True


def _taken_elsewhere(py_func, sig) -> bool:
    """Whether the kernel ``py_func`` for ``sig``, missing from the cache, is being compiled by a
    helper of :func:`compile_elsewhere` (then it is awaited); False when it is not listed, or
    when this process takes it now (then it compiles it)."""
    if not _listed or not _helpers_running():
        return False
    listed = _listed.get((py_func.__module__, py_func.__qualname__, repr(tuple(sig))))
    return listed is not None and listed not in _mine and not _take(*listed)


def compile_elsewhere(kernels: Sequence[tuple[str, str, str]], processes: int = 1) -> None:
    """Share the compilation of ``kernels`` between this process and ``processes`` helper
    processes, through the kernel cache.

    ``kernels``: ``(module, function, signature)`` in the order this process needs them,
    ``signature`` the ``repr`` of the tuple of numba argument types (:func:`recording_compiles`
    lists them).  Each kernel is compiled once, by the first process that takes it (a file created
    exclusively in a shared work folder): this process as it goes, from the front of the listing,
    the helpers from the end, where the kernels needed last are (which share fewer callees with
    the first: two processes compiling kernels with common callees at once compile the callees
    twice; once one has cached a callee, the other loads it).

    When this process needs a listed kernel a helper has taken, it waits for it in the cache (at
    most :data:`HELPER_WAIT` s, or until no helper is left running) rather than compiling it too.
    The compile notice is written now (:func:`set_compile_notice`).  Helpers still running when
    this process exits are ended.  Nothing is started without numba."""
    if not HAVE_NUMBA or _KernelCache is None or not kernels:
        return
    _announce(None)
    work = tempfile.mkdtemp(prefix="flexforce-kernels-")
    if not _helpers and not _work:
        atexit.register(_stop_helpers)
    _work.append(work)
    with open(os.path.join(work, "kernels.json"), "w", encoding="utf-8") as f:
        json.dump([list(k) for k in kernels], f)
    for i, (module, function, signature) in enumerate(kernels):
        _listed[(module, function, signature)] = (work, i)
    code = "import sys; from flexforce.jit import _compile_taken; _compile_taken(sys.argv[1])"
    for _ in range(max(1, processes)):
        _helpers.append(subprocess.Popen([sys.executable, "-c", code, work], stdin=subprocess.DEVNULL,
                                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))


def compile_while_awaiting(*kernels) -> int:
    """While the helpers of :func:`compile_elsewhere` compile ``kernels`` (dispatchers of
    :func:`njit`, needed next), compile in this process the listed kernels nobody has taken, from
    the front of the listing, one at a time: this process's core does the work it would otherwise
    wait through.  Returns when each of ``kernels`` is cached, when no helper is running, or when
    every listed kernel is taken; the number compiled here.  A kernel that fails to compile (a
    stale listing) is skipped: whoever needs it compiles it then."""
    done = 0
    for key, (work, index) in sorted(_listed.items(), key=lambda item: item[1][1]):
        if cached(*kernels) or not _helpers_running():
            break
        if not _take(work, index):
            continue
        _mine.add((work, index))  # compiled here: not awaited from a helper (_taken_elsewhere)
        done += _compile_listed(*key)
    return done


def _compile_listed(module: str, function: str, signature: str) -> bool:
    """Compile one kernel of a listing (:func:`compile_elsewhere`) for its recorded signature;
    False when it cannot be (a stale listing: whoever needs it compiles it then)."""
    import importlib

    try:
        getattr(importlib.import_module(module), function).compile(_signature(signature))
    except Exception:  # noqa: BLE001 -- compiled where it is needed instead
        return False
    return True


def _signature(text: str):
    """The tuple of numba types whose ``repr`` is ``text`` (as :func:`recording_compiles` wrote it)."""
    from numba.core import types

    names = {name: getattr(types, name) for name in dir(types) if not name.startswith("_")}
    names.update(bool=types.boolean, omitted=lambda default: types.Omitted(default))
    sig = eval(text, {"__builtins__": {}}, names)  # noqa: S307 -- our own listing of numba type reprs
    return tuple(sig)


def _compile_taken(work: str) -> None:
    """A helper of :func:`compile_elsewhere`: compile each kernel of ``work``'s listing no other
    process has taken, from the end; a kernel that fails (a stale listing) is left to the caller."""
    with open(os.path.join(work, "kernels.json"), encoding="utf-8") as f:
        kernels = json.load(f)
    for i in reversed(range(len(kernels))):
        if not os.path.isdir(work):  # the caller has finished
            return
        if _take(work, i):
            _compile_listed(*kernels[i])  # one that fails is left to the caller


@contextlib.contextmanager
def recording_compiles() -> Iterator[list[tuple[str, str, str]]]:
    """Within the block, the kernels this process compiles when called from Python (not those
    compiled as callees of others), as ``(module, function, signature)`` for :func:`compile_elsewhere`."""
    from numba.core import event

    compiled: list[tuple[str, str, str]] = []
    depth = [0]

    class Listener(event.Listener):
        def on_start(self, ev):
            if depth[0] == 0:
                fn = ev.data["dispatcher"].py_func
                compiled.append((fn.__module__, fn.__qualname__, repr(tuple(ev.data["args"]))))
            depth[0] += 1

        def on_end(self, ev):
            depth[0] -= 1

    with event.install_listener("numba:compile", Listener()):
        yield compiled


def cached(*kernels) -> bool:
    """Whether the kernel cache holds each of ``kernels`` (dispatchers of :func:`njit`) compiled
    from its current source on this machine, for some argument types.  True without numba, for a
    kernel not cached by :func:`njit`, and when the cache cannot be read (nothing to prepare)."""
    if not HAVE_NUMBA or _KernelCache is None:
        return True
    try:
        for disp in kernels:
            cache = getattr(disp, "_cache", None)
            if not isinstance(cache, _KernelCache):
                continue
            codegen = disp.targetctx.codegen()
            wanted = cache._index_key((), codegen)[1:]  # (machine, source hashes) of any signature
            if not any(key[1:] == wanted for key in cache._cache_file._load_index()):
                return False
    except Exception:  # noqa: BLE001 -- numba internals changed: assume cached, prepare nothing  # pragma: no cover
        return True
    return True


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

    class KeyedIndexDataCacheFile(caching.IndexDataCacheFile):
        """numba's index and data files, a data file named after its index key (not numbered):
        two processes caching two signatures of one kernel at once cannot write the same file and
        leave the index pointing at the other signature's code.  The data is written before the
        index entry, so that a reader never finds the entry without its data."""

        def save(self, key, data):
            digest = hashlib.sha256(repr(key).encode()).hexdigest()[:24]
            name = f"{self._index_name[:-len('.nbi')]}.{digest}.nbc"
            self._save_data(name, data)
            overloads = self._load_index()
            overloads[key] = name
            self._save_index(overloads)

    class KernelCache(caching.FunctionCache):
        """numba's ``FunctionCache`` with the locators and data files above, announcing a
        compilation, awaiting a kernel from the helper processes of :func:`compile_elsewhere`."""

        _impl_class = KernelCacheImpl

        def __init__(self, py_func):
            super().__init__(py_func)
            self._cache_file = KeyedIndexDataCacheFile(self._cache_path, self._impl.filename_base,
                                                       self._impl.locator.get_source_stamp())

        def load_overload(self, sig, target_context):
            cres = super().load_overload(sig, target_context)
            if cres is None:  # not in the cache: the dispatcher compiles next
                _announce(self.cache_path)
                if _taken_elsewhere(self._py_func, sig):
                    deadline = time.monotonic() + HELPER_WAIT
                    while cres is None and _helpers_running() and time.monotonic() < deadline:
                        time.sleep(0.05)
                        cres = super().load_overload(sig, target_context)
            return cres

    return KernelCache


def _kernel_dispatcher_class():
    """numba's CPU dispatcher, compiling a kernel called from another kernel for the types of its
    arguments without their literal values (module docstring), or ``None`` when this numba lacks
    the hook it builds on."""
    try:
        from numba.core import types
        from numba.core.registry import CPUDispatcher
    except ImportError:  # pragma: no cover
        return None
    if not hasattr(CPUDispatcher, "get_call_template"):  # pragma: no cover
        return None

    class KernelDispatcher(CPUDispatcher):
        def get_call_template(self, args, kws):
            args = tuple(types.unliteral(a) for a in args)
            kws = {k: types.unliteral(v) for k, v in kws.items()}
            return super().get_call_template(args, kws)

    return KernelDispatcher


if HAVE_NUMBA:
    _KernelCache = _kernel_cache_class()
    _KernelDispatcher = _kernel_dispatcher_class()

    def njit(fn):
        """``numba.njit(nogil=True)(fn)``, cached on disk where the module docstring says.

        Falls back to ``numba.njit(cache=True, nogil=True)`` if this numba has no locator
        machinery, and to no disk cache if no location is writable."""
        if _KernelCache is None:  # pragma: no cover
            return numba.njit(cache=True, nogil=True)(fn)
        if _KernelDispatcher is not None and not numba.config.DISABLE_JIT:
            disp = _KernelDispatcher(py_func=fn, locals={},
                                     targetoptions={"nopython": True, "nogil": True, "boundscheck": None})
        else:
            disp = numba.njit(nogil=True)(fn)
        if not hasattr(disp, "_cache"):  # NUMBA_DISABLE_JIT: the plain function  # pragma: no cover
            return disp
        try:
            disp._cache = _KernelCache(fn)  # what Dispatcher.enable_caching does, with our locators
        except RuntimeError:  # numba: "cannot cache function ...: no locator available"
            pass
        return disp
else:  # pragma: no cover
    _KernelCache = None

    # Same code, interpreted: correct but ~100x slower (the speed targets need numba).
    def njit(fn):
        """``fn`` itself (numba is not installed)."""
        return fn
