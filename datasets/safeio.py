"""Safe outputs: check a path before the work, lock it, write aside, move into place when complete.

Every file or folder flexforce writes (an estimate ``.npz`` or ``.csv``, a bag, a report folder)
goes through :func:`safe_output`:

- **one writer per target**: ``<target>.lock`` is created exclusively (``O_CREAT | O_EXCL``) and
  holds the writer's PID; a second writer of the same target is refused with an
  :class:`~flexforce.errors.OutputError` naming the PID.  A lock whose PID is no longer running
  (a writer killed with SIGKILL, a power cut) is stale and taken over; whoever takes a lock removes
  the temporaries its dead writers left beside the target (:func:`clean_temporaries`).  The lock is re-entrant
  within one process (the command line holds it for the whole command, the writer inside takes
  it again);
- **all or nothing**: the content is written under a temporary name in the target's own folder
  (same file system) and moved into place with :func:`os.replace` only once complete.  Any
  exception, Ctrl-C included, removes the temporary and leaves the previous output as it was (or
  none).  A folder is built in a temporary sibling and swapped in: the old folder is renamed
  aside, the new one renamed into place, the old one deleted; Ctrl-C is held back during those
  two renames, so the target is always the previous folder or the new one.

:func:`check_output` is the check the command line runs before any work: the folder exists and
is writable, the suffix is one the writer knows, an existing target may be replaced.

Locks are advisory (only flexforce looks at them) and local: two hosts writing into one network
folder are not protected against each other.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import signal
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

from flexforce.errors import OutputError

LOCK_SUFFIX = ".lock"
"""The lock of ``target`` is the file ``target`` + this suffix, beside it."""

STALE_EMPTY_LOCK_S = 10.0
"""A lock file with no readable PID (its writer died between creating and filling it) is stale
after this many seconds."""

REPORT_SUFFIXES = frozenset({".html", ".json", ".png", ".svg", ".pdf", ".csv", ".txt"})
"""Files a report folder may hold: only such a folder is replaced by a new report."""

_held: dict[Path, int] = {}
"""Locks this process holds: target -> depth of nesting."""
_held_guard = threading.Lock()


def _key(target: Path) -> Path:
    return Path(os.path.abspath(target))


def lock_path(target: str | Path) -> Path:
    """``<target>.lock``."""
    target = _key(Path(target))
    return target.with_name(target.name + LOCK_SUFFIX)


def _pid_running(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    return True


def _read_pid(path: Path) -> int | None:
    try:
        return int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def _stale(path: Path) -> bool:
    """The lock at ``path`` belongs to no running writer."""
    pid = _read_pid(path)
    if pid is None:
        try:
            return time.time() - path.stat().st_mtime > STALE_EMPTY_LOCK_S
        except FileNotFoundError:
            return True
    if pid == os.getpid():  # our PID, but not a lock we hold (a previous process with the same PID)
        return True
    return not _pid_running(pid)


def _acquire(target: Path) -> None:
    lock = lock_path(target)
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            if _stale(lock):
                with contextlib.suppress(FileNotFoundError):
                    lock.unlink()
                continue
            pid = _read_pid(lock)
            who = f"process {pid}" if pid is not None else "another process"
            raise OutputError(f"{target} is being written by {who} (lock {lock}); expected one writer at a "
                              "time: wait for it to finish, or delete the lock if that process is gone") from None
        except OSError as err:
            raise OutputError(f"cannot create the lock {lock}: {err.strerror or err}; expected a writable "
                              "folder") from err
        try:
            os.write(fd, f"{os.getpid()}\n".encode())
        finally:
            os.close(fd)
        clean_temporaries(target)
        return
    raise OutputError(f"cannot take the lock {lock}: other writers keep taking it; expected one writer at a time")


@contextlib.contextmanager
def output_lock(target: str | Path) -> Iterator[Path]:
    """Hold ``<target>.lock`` for the block (re-entrant within this process).

    Raises:
        OutputError: another running process holds the lock.
    """
    key = _key(Path(target))
    with _held_guard:
        depth = _held.get(key, 0)
        if depth == 0:
            _acquire(key)
        _held[key] = depth + 1
    try:
        yield key
    finally:
        with _held_guard:
            _held[key] -= 1
            if _held[key] == 0:
                del _held[key]
                lock = lock_path(key)
                if _read_pid(lock) == os.getpid():
                    with contextlib.suppress(FileNotFoundError):
                        lock.unlink()


_TAGS = ("tmp", "old", "probe")
"""The tags of :func:`_temporary_name`: a file or folder being written, an old folder being
swapped out, a write probe."""


def _temporary_name(target: Path, tag: str) -> Path:
    """A hidden sibling of ``target`` keeping its suffix (numpy adds ``.npz`` to names without it):
    ``.<stem>.<tag>-<pid>-<8 hex digits><suffix>``, the PID its writer's."""
    return target.with_name(f".{target.stem}.{tag}-{os.getpid()}-{uuid.uuid4().hex[:8]}{target.suffix}")


def clean_temporaries(target: str | Path) -> list[Path]:
    """Remove the temporaries of ``target`` (:func:`_temporary_name`) left by writers that are no
    longer running (killed with SIGKILL, a power cut): called when the lock is taken, so that no
    writer is using them.  A temporary of a running process (or of this one) is kept.  Returns the
    paths removed."""
    target = _key(Path(target))
    pattern = re.compile(rf"^\.{re.escape(target.stem)}\.(?:{'|'.join(_TAGS)})-(\d+)-[0-9a-f]{{8}}"
                         rf"{re.escape(target.suffix)}(?:\.bag)?$")  # .bag: an MCAP writer's bag folder
    removed: list[Path] = []
    try:
        siblings = list(target.parent.iterdir())
    except OSError:
        return removed
    for path in siblings:
        match = pattern.match(path.name)
        if match is None:
            continue
        pid = int(match.group(1))
        if pid == os.getpid() or _pid_running(pid):
            continue
        _remove(path)
        removed.append(path)
    return removed


@contextlib.contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Hold Ctrl-C back for the block (main thread only; elsewhere a no-op) and deliver it after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[tuple] = []
    previous = signal.signal(signal.SIGINT, lambda *a: caught.append(a))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught and callable(previous):
            previous(*caught[0])


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def is_report_folder(path: Path) -> bool:
    """A folder holding only a flexforce report: index.html, and files of :data:`REPORT_SUFFIXES`
    (or report folders, for several recordings)."""
    if not path.is_dir() or not (path / "index.html").is_file():
        return False
    for entry in path.iterdir():
        if entry.is_dir():
            if not is_report_folder(entry):
                return False
        elif entry.suffix not in REPORT_SUFFIXES:
            return False
    return True


def replaceable_by_report(path: Path) -> bool:
    """An empty folder, or a report folder (:func:`is_report_folder`): a new report may replace it."""
    return path.is_dir() and (not any(path.iterdir()) or is_report_folder(path))


def is_bag_folder(path: Path) -> bool:
    """A ROS 2 bag directory: metadata.yaml and storage files only."""
    if not path.is_dir() or not (path / "metadata.yaml").is_file():
        return False
    return all(e.is_file() and (e.name == "metadata.yaml" or e.suffix in {".mcap", ".db3", ".zstd"})
               for e in path.iterdir())


def check_output(path: str | Path, what: str, *, suffixes: tuple[str, ...] | None = None,
                 file_suffixes: tuple[str, ...] = (), folder: bool = False, overwrite: bool = True,
                 replaceable: Callable[[Path], bool] | None = None, replaceable_what: str = "") -> Path:
    """Check, before any work, that ``path`` can be written; return it as a :class:`Path`.

    Args:
        path: the output (a file, or a folder when ``folder``).
        what: what is written, for the messages (``estimate``, ``report folder``...).
        suffixes: the suffixes the writer knows (``None``: any; ``""`` stands for none).
        file_suffixes: for a folder, suffixes refused because they name a file (``.npz``...).
        folder: the output is a folder (a report, a ROS 2 bag directory).
        overwrite: an existing output may be replaced; otherwise it is refused.
        replaceable: whether an existing output may be replaced (a report folder, a bag: never a
            folder of other files); ``replaceable_what`` says what it must be.  Without it, an
            existing file is replaced by a file and a folder by a folder.

    Raises:
        OutputError: naming the path, what is wrong and what is expected.
    """
    path = Path(path)
    if str(path) in ("", ".", "..") or path.name in ("", ".", ".."):
        raise OutputError(f"output {str(path)!r} for the {what} names no new file or folder; expected a path "
                          "such as out/result")
    if suffixes is not None and path.suffix not in suffixes:
        known = ", ".join(s or "no suffix" for s in suffixes)
        raise OutputError(f"output {path} has suffix {path.suffix or '(none)'!r}; expected {known} for the {what}")
    if folder and path.suffix in file_suffixes:
        raise OutputError(f"output {path} has the suffix of a file ({path.suffix}); expected a folder name for "
                          f"the {what}")
    parent = path.parent
    if not parent.exists():
        raise OutputError(f"folder {parent} of output {path} does not exist; expected an existing folder "
                          "(create it first)")
    if not parent.is_dir():
        raise OutputError(f"{parent} in output {path} is not a folder; expected an existing, writable folder")
    try:  # the real test of writability (os.access says yes to root, no on some network mounts)
        probe = _temporary_name(path, "probe")
        fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
        os.close(fd)
        probe.unlink()
    except OSError as err:
        reason = err.strerror or str(err)
        if err.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            reason = "not writable"
        raise OutputError(f"cannot write into folder {parent} for output {path}: {reason}; expected a writable "
                          "folder") from err
    if path.exists() or path.is_symlink():
        if not overwrite:
            raise OutputError(f"{path} exists already; expected a new path (or --force to replace it)")
        if replaceable is not None:
            if not replaceable(path):
                kind = "folder" if path.is_dir() else "file"
                raise OutputError(f"cannot replace {path}: it is a {kind} that is not {replaceable_what}; expected "
                                  f"a new path (remove the {kind} yourself to reuse its name)")
        elif folder and not path.is_dir():
            raise OutputError(f"{path} is a file; expected a new path or a folder for the {what}")
        elif not folder and path.is_dir():
            raise OutputError(f"{path} is a folder; expected a file path for the {what}")
    lock = lock_path(path)
    if lock.exists() and _key(path) not in _held and not _stale(lock):
        pid = _read_pid(lock)
        who = f"process {pid}" if pid is not None else "another process"
        raise OutputError(f"{path} is being written by {who} (lock {lock}); expected one writer at a time: wait "
                          "for it to finish, or delete the lock if that process is gone")
    return path


class OutputOSError(Exception):
    """An OSError of writing an output, raised inside code that reads an input (an MCAP export copying
    the input bag, a stream copying its messages), whose reader's catch-all would blame the input:
    raise this around it, catch it past the reader and raise :attr:`error` again."""

    def __init__(self, error: OSError):
        super().__init__(str(error))
        self.error = error


_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG, errno.EIO})
"""Errors of writing an output (a full disk, a quota, a read-only or failing file system): raised
inside :func:`safe_output` they name the output, whatever the writer was reading at the time."""


@contextlib.contextmanager
def safe_output(target: str | Path, *, folder: bool = False) -> Iterator[Path]:
    """Lock ``target``, yield a temporary path beside it to write, move it into place on success.

    The caller writes the complete output at the yielded path (a file; with ``folder``, a folder
    it creates there -- a bag writer that insists on creating its directory can).  When the block
    ends normally the output replaces ``target`` (:func:`os.replace` for a file; for a folder the
    swap described in the module docstring).  When it raises (Ctrl-C included) the temporary is
    removed and ``target`` is left as it was.

    Raises:
        OutputError: another process is writing ``target``, or the move fails.
    """
    target = Path(target)
    with output_lock(target):
        if folder:
            staging = _temporary_name(target, "tmp")
            staging.mkdir()
            work = staging / target.name  # inside the staging folder: the writer sees the final name
        else:
            staging = work = _temporary_name(target, "tmp")
        try:
            try:
                yield work
            except OSError as err:
                if err.errno not in _WRITE_ERRNOS:
                    raise
                raise OutputError(f"cannot write {target}: {err.strerror or err}; nothing was changed there "
                                  "(expected room and write access on its file system)") from err
            if not (work.exists() or work.is_symlink()):
                raise OutputError(f"nothing was written for {target}")
            if folder:
                _swap_folder(work, target)
            else:
                try:
                    os.replace(work, target)
                except OSError as err:
                    raise OutputError(f"cannot move the new {target.name} into place at {target}: "
                                      f"{err.strerror or err}") from err
        finally:
            _remove(staging)


def _swap_folder(new: Path, target: Path) -> None:
    """Put folder ``new`` at ``target``, the old ``target`` (if any) deleted after."""
    old = _temporary_name(target, "old")
    with _sigint_deferred():
        try:
            had_old = target.exists() or target.is_symlink()
            if had_old:
                os.replace(target, old) if not target.is_dir() else os.rename(target, old)
            try:
                os.rename(new, target)
            except OSError:
                if had_old:
                    os.rename(old, target)
                raise
        except OSError as err:
            raise OutputError(f"cannot move the new {target.name} into place at {target}: "
                              f"{err.strerror or err}") from err
    _remove(old)
