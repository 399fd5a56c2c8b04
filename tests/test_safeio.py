"""Safe outputs: checked before the work, one writer at a time, complete or not at all."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import numpy as np
import pytest

from flexforce.datasets.safeio import (
    check_output,
    is_report_folder,
    lock_path,
    output_lock,
    replaceable_by_report,
    safe_output,
)
from flexforce.errors import OutputError


def _leftovers(folder):
    """Temporary files, folders and locks left in ``folder``."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".") or p.name.endswith(".lock"))


def test_a_file_is_moved_into_place_when_complete(tmp_path):
    target = tmp_path / "est.npz"
    with safe_output(target) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".npz" and tmp != target
        np.savez(tmp, x=np.arange(3))
        assert not target.exists()
        assert lock_path(target).read_text().strip() == str(os.getpid())
    assert np.load(target)["x"].tolist() == [0, 1, 2]
    assert _leftovers(tmp_path) == []


def test_an_interrupted_write_leaves_the_previous_file(tmp_path):
    target = tmp_path / "est.csv"
    target.write_text("previous\n")
    for error in (RuntimeError("disk on fire"), KeyboardInterrupt()):
        with pytest.raises(type(error)):
            with safe_output(target) as tmp, tmp.open("w") as f:
                f.write("half a ")
                raise error
        assert target.read_text() == "previous\n"
        assert _leftovers(tmp_path) == []


def test_an_interrupted_first_write_leaves_nothing(tmp_path):
    target = tmp_path / "report"
    with pytest.raises(KeyboardInterrupt):
        with safe_output(target, folder=True) as tmp:
            tmp.mkdir()
            (tmp / "summary.json").write_text("{}")
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_a_folder_is_swapped_whole(tmp_path):
    target = tmp_path / "report"
    target.mkdir()
    (target / "index.html").write_text("old")
    (target / "old.png").write_text("old figure")
    with pytest.raises(RuntimeError):
        with safe_output(target, folder=True) as tmp:
            tmp.mkdir()
            (tmp / "summary.json").write_text("new")
            raise RuntimeError("interrupted")
    assert sorted(p.name for p in target.iterdir()) == ["index.html", "old.png"]  # the old report, whole
    with safe_output(target, folder=True) as tmp:
        assert tmp.name == "report" and tmp.parent.parent == tmp_path  # the final name, inside a staging folder
        tmp.mkdir()
        (tmp / "index.html").write_text("new")
        (tmp / "summary.json").write_text("new")
    assert sorted(p.name for p in target.iterdir()) == ["index.html", "summary.json"]  # never a mixture
    assert (target / "index.html").read_text() == "new"
    assert _leftovers(tmp_path) == []


def test_a_second_writer_is_refused(tmp_path):
    target = tmp_path / "est.npz"
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock_path(target).write_text(f"{other.pid}\n")
        with pytest.raises(OutputError, match=rf"est.npz is being written by process {other.pid} "
                                              r"\(lock .*est.npz.lock\); expected one writer at a time"):
            with safe_output(target):
                pass
        with pytest.raises(OutputError, match=f"being written by process {other.pid}"):
            check_output(target, "estimate")
        assert lock_path(target).read_text() == f"{other.pid}\n"  # the other writer's lock is left alone
    finally:
        other.kill()
        other.wait()
    with safe_output(target) as tmp:  # its writer is gone: the stale lock is taken over
        tmp.write_bytes(b"x")
    assert target.read_bytes() == b"x" and not lock_path(target).exists()


def test_the_lock_is_reentrant_in_one_process(tmp_path):
    target = tmp_path / "est.csv"
    with output_lock(target):
        check_output(target, "estimate")  # our own lock does not refuse us
        with safe_output(target) as tmp:
            tmp.write_text("a\n")
        assert lock_path(target).exists()  # still held by the outer block
    assert not lock_path(target).exists()
    assert target.read_text() == "a\n"


def test_a_lock_without_a_pid_is_stale_only_when_old(tmp_path):
    target = tmp_path / "est.npz"
    lock_path(target).write_text("")
    with pytest.raises(OutputError, match="being written by another process"):
        with output_lock(target):
            pass
    old = 1_000_000_000
    os.utime(lock_path(target), (old, old))
    with output_lock(target):
        pass


def test_check_output_names_the_problem(tmp_path):
    (tmp_path / "file").write_text("x")
    (tmp_path / "folder").mkdir()
    (tmp_path / "folder" / "notes.txt").write_text("mine")
    cases = [
        (tmp_path / "est.txt", dict(suffixes=(".npz", ".csv")), r"output .*est.txt has suffix '.txt'; expected .npz, "
                                                                 ".csv for the estimate"),
        (tmp_path / "missing" / "est.npz", {}, r"folder .*missing of output .*est.npz does not exist; expected an "
                                               "existing folder"),
        (tmp_path / "file" / "est.npz", {}, r".*file in output .*est.npz is not a folder; expected an existing, "
                                            "writable folder"),
        (tmp_path / "file", dict(overwrite=False), r".*file exists already; expected a new path \(or --force"),
        (tmp_path / "folder", {}, r".*folder is a folder; expected a file path for the estimate"),
        (tmp_path / "folder", dict(folder=True, replaceable=is_report_folder, replaceable_what="a flexforce report"),
         r"cannot replace .*folder: it is a folder that is not a flexforce report; expected a new path"),
        (tmp_path / "rep.json", dict(folder=True, file_suffixes=(".json",)),
         r"output .*rep.json has the suffix of a file \(.json\); expected a folder name"),
        (tmp_path / "sub" / "..", {}, "names no new file or folder"),
    ]
    for path, options, message in cases:
        with pytest.raises(OutputError, match=message):
            check_output(path, "estimate", **options)
    assert check_output(tmp_path / "est.npz", "estimate", suffixes=(".npz",)) == tmp_path / "est.npz"
    assert _leftovers(tmp_path) == []  # the writability probe is removed


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_check_output_refuses_a_read_only_folder(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        with pytest.raises(OutputError, match=r"cannot write into folder .*ro for output .*est.npz: not writable"):
            check_output(folder / "est.npz", "estimate")
    finally:
        folder.chmod(0o755)


def test_is_report_folder(tmp_path):
    rep = tmp_path / "rep"
    rep.mkdir()
    assert not is_report_folder(rep) and replaceable_by_report(rep)  # empty: nothing to lose
    (rep / "index.html").write_text("")
    (rep / "summary.json").write_text("")
    (rep / "seed0").mkdir()
    (rep / "seed0" / "index.html").write_text("")
    assert is_report_folder(rep)
    (rep / "thesis.tex").write_text("")
    assert not is_report_folder(rep) and not replaceable_by_report(rep)


def _dead_pid() -> int:
    """The PID of a process that has ended."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_taking_over_a_dead_writers_lock_removes_its_temporaries(tmp_path):
    """A writer killed mid-write (SIGKILL) leaves its lock and a hidden temporary beside the output:
    the next writer takes the lock over and removes the temporary (file or folder), and only the
    temporaries of that target whose writer is gone."""
    target = tmp_path / "est.npz"
    dead = _dead_pid()
    lock_path(target).write_text(f"{dead}\n")
    leftover = tmp_path / f".est.tmp-{dead}-0123abcd.npz"
    leftover.write_bytes(b"half")
    old_folder = tmp_path / f".est.old-{dead}-89abcdef.npz"
    (old_folder / "inside").mkdir(parents=True)
    other_target = tmp_path / f".other.tmp-{dead}-0123abcd.npz"
    other_target.write_bytes(b"not ours")
    alive = tmp_path / f".est.tmp-{os.getppid()}-0123abcd.npz"  # a running process's: kept
    alive.write_bytes(b"busy")
    with safe_output(target) as tmp:
        tmp.write_bytes(b"x")
    assert target.read_bytes() == b"x"
    assert _leftovers(tmp_path) == sorted([alive.name, other_target.name])


def test_a_dead_mcap_writers_bag_folder_is_removed(tmp_path):
    """An MCAP export writes its bag in a folder named after the temporary plus ``.bag``
    (``export._bag_folder``): a killed writer's folder goes with the lock, like its temporary."""
    target = tmp_path / "est.mcap"
    dead = _dead_pid()
    lock_path(target).write_text(f"{dead}\n")
    folder = tmp_path / f".est.tmp-{dead}-0123abcd.mcap.bag"
    (folder / "est.mcap").parent.mkdir(parents=True)
    (folder / "est.mcap").write_bytes(b"half")
    with safe_output(target) as tmp:
        tmp.write_bytes(b"x")
    assert _leftovers(tmp_path) == []


def test_a_killed_writer_leaves_nothing_after_the_next_run(tmp_path):
    target = tmp_path / "est.csv"
    code = ("import os, signal, sys\n"
            "from flexforce.datasets.safeio import safe_output\n"
            f"with safe_output({str(target)!r}) as tmp:\n"
            "    tmp.write_text('partial')\n"
            "    os.kill(os.getpid(), signal.SIGKILL)\n")
    proc = subprocess.run([sys.executable, "-c", code], check=False)
    assert proc.returncode == -9
    assert len(_leftovers(tmp_path)) == 2  # the lock and the temporary
    with safe_output(target) as tmp:
        tmp.write_text("a\n")
    assert target.read_text() == "a\n" and _leftovers(tmp_path) == []


def test_a_full_disk_names_the_output(tmp_path):
    """A write that fails for want of room (or on a read-only file system) names the output being
    written, not what was being read at the time, and leaves the target as it was."""
    import errno

    target = tmp_path / "est.csv"
    target.write_text("old")
    with pytest.raises(OutputError, match=rf"cannot write {re.escape(str(target))}: No space left on device"):
        with safe_output(target) as tmp:
            tmp.write_text("half")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert target.read_text() == "old" and _leftovers(tmp_path) == []
    with pytest.raises(OSError, match="not a write error"):  # others pass through as they are
        with safe_output(target):
            raise OSError(errno.ENOENT, "not a write error")
