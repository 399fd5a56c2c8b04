"""Many recordings: compare and diagnose with --jobs give the results of one process; the index of
several recordings links each report; progress off a terminal is one line per stage."""

from __future__ import annotations

import json
import re
import sys

import pytest

from flexforce.cli import Progress, main
from flexforce.compare.runner import run_jobs
from flexforce.datasets.io.bagio import save_recording
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import ConfigError

TIMING = {"time_per_step_s", "total_time_s", "peak_memory_mb", "seconds"}
"""Numbers that measure the machine, not the estimate: they differ between any two runs."""


def without_timing(value):
    if isinstance(value, dict):
        return {k: without_timing(v) for k, v in value.items() if k not in TIMING}
    if isinstance(value, list):
        return [without_timing(v) for v in value]
    return value


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """Two small simulated recordings (0.6 s of the pushed Romeo, two noise seeds), as bags of one name
    in two folders (their reports must not overwrite each other)."""
    tmp = tmp_path_factory.mktemp("jobs")
    out = []
    for seed in (1, 2):
        sc = Scenario.load("push-pitch")
        sc.duration = 0.6
        sc.seed = seed
        (tmp / f"seed{seed}").mkdir()
        out.append(save_recording(Simulator(sc).run(), tmp / f"seed{seed}" / "push"))
    return out


def test_run_jobs_keeps_the_order_and_raises_the_workers_error():
    assert list(run_jobs(abs, [-3, 2, -1], jobs=2)) == [3, 2, 1]
    assert list(run_jobs(abs, [-3], jobs=4)) == [3]
    with pytest.raises(TypeError):
        list(run_jobs(abs, [-1, "x"], jobs=2))
    with pytest.raises(ConfigError, match="jobs = 0; expected a positive number"):
        list(run_jobs(abs, [1], jobs=0))


@pytest.mark.slow
def test_compare_jobs_gives_the_results_of_one_process(bags, tmp_path, capsys):
    reports = {}
    for jobs in (1, 2):
        out = tmp_path / f"jobs{jobs}"
        assert main(["compare", *map(str, bags), "--estimators", "ekf,fixed-lag", "--jobs", str(jobs), "-o", str(out),
                     "-q"]) == 0, capsys.readouterr().err
        reports[jobs] = out
    printed = capsys.readouterr().out
    assert printed.count("push:") == 2 and printed.count("push-2:") == 2
    for name in ("summary.json", "push/summary.json", "push-2/summary.json"):
        one, two = (json.loads((reports[j] / name).read_text()) for j in (1, 2))
        assert one == two, name  # no timing in it
        # the timings sit apart, in timings.json, for the same rows
        one, two = (json.loads((reports[j] / name.replace("summary", "timings")).read_text()) for j in (1, 2))
        assert {g: set(rows) for g, rows in one.items()} == {g: set(rows) for g, rows in two.items()}, name
    per = [json.loads((reports[2] / f"{label}/summary.json").read_text()) for label in ("push", "push-2")]
    assert per[0]["estimators"]["ekf"]["rmse"]["force_N"] != per[1]["estimators"]["ekf"]["rmse"]["force_N"]
    agg = json.loads((reports[2] / "summary.json").read_text())
    assert agg["estimators"]["fixed_lag"]["count"] == 2
    # the index links each report and shows the aggregate table with the summary's mean
    page = (reports[2] / "index.html").read_text()
    assert 'href="push/index.html"' in page and 'href="push-2/index.html"' in page
    mean = agg["estimators"]["fixed_lag"]["rmse"]["force_N"]
    row = re.search(r'<tr class="estimator"><th>fixed_lag</th><td>2</td><td>(.*?) ± ', page)
    assert row and row.group(1) == f"{mean:.3g}"
    assert f"{per[1]['estimators']['ekf']['rmse']['force_N']:.3g}" in page


@pytest.mark.slow
def test_diagnose_jobs_gives_the_results_of_one_process(bags, tmp_path, capsys):
    reports = {}
    for jobs in (1, 2):
        out = tmp_path / f"jobs{jobs}"
        assert main(["diagnose", *map(str, bags), "--candidates", "gyro-bias", "--no-ekf", "--jobs", str(jobs),
                     "-o", str(out), "-q"]) == 0, capsys.readouterr().err
        reports[jobs] = out
    for name in ("summary.json", "push/diagnosis.json", "push-2/diagnosis.json"):
        one, two = (json.loads((reports[j] / name).read_text()) for j in (1, 2))
        assert without_timing(one) == without_timing(two), name
    summary = json.loads((reports[2] / "summary.json").read_text())
    assert [r["label"] for r in summary["recordings"]] == ["push", "push-2"]
    page = (reports[2] / "index.html").read_text()
    assert 'href="push/index.html"' in page and 'href="push-2/index.html"' in page
    assert (reports[2] / "push-2" / "index.html").is_file()


def test_one_recording_diagnosed_with_jobs_gives_the_results_of_one_process(bags, tmp_path, capsys):
    """--jobs on one recording: its score tests, a round's refits and the before/after views in
    forked workers; the report is that of one process."""
    for flags in (["--no-screen"], []):  # every candidate refitted; screened, with the identifiability table
        reports = {}
        for jobs in (1, 2):
            out = tmp_path / f"one{jobs}{len(flags)}"
            assert main(["diagnose", str(bags[0]), "--candidates", "gyro-bias,external-wrench,com-offset,stiffness",
                         *flags, "--add", "auto", "--no-ekf", "--jobs", str(jobs), "-o", str(out), "-q"]) == 0, \
                capsys.readouterr().err
            reports[jobs] = json.loads((out / "diagnosis.json").read_text())
        assert without_timing(reports[1]) == without_timing(reports[2])
        if flags:
            assert len(reports[2]["rounds"][0]) == 4  # every candidate refitted in the first round
        else:
            assert len(reports[2]["screening"]) == 4 and reports[2]["identifiability"] is not None


def test_fork_map_returns_each_result_or_exception():
    from flexforce.compare.runner import fork_map

    def fn(x):
        if x == 2:
            raise ValueError("two")
        return lambda: x if x == 3 else x * 10  # a lambda does not pickle: computed again here

    for jobs in (1, 2):
        got = {i: (ok, value) for i, ok, value, _ in fork_map(fn, [0, 1, 2, 3], jobs)}
        assert sorted(got) == [0, 1, 2, 3]
        assert [got[i][1]() for i in (0, 1, 3)] == [0, 10, 3]
        assert got[2][0] is False and isinstance(got[2][1], ValueError) and str(got[2][1]) == "two"


def test_fork_map_shares_the_items_between_this_process_and_its_workers():
    """jobs = 2: this process and one forked worker each take the next item left, every item once."""
    import os
    import time

    from flexforce.compare.runner import fork_map
    from flexforce.errors import EstimatorError

    def fn(x):
        time.sleep(0.1)
        return x, os.getpid()

    got = list(fork_map(fn, list(range(12)), 2))
    assert sorted(i for i, *_ in got) == list(range(12))
    assert all(ok and value[0] == i for i, ok, value, _ in got)
    by = {i: value[1] for i, _, value, _ in got}
    # both worked: the worker from the first item (a caller puts the longest first), this process
    # from the last (1.2 s of items for it alone: the worker starts well before)
    assert by[11] == os.getpid() and by[0] != os.getpid() and len(set(by.values())) == 2, by
    # stopped early by the caller: no error, and a later map starts afresh
    it = fork_map(fn, list(range(6)), 2)
    next(it)
    it.close()
    assert sorted(i for i, *_ in fork_map(fn, list(range(3)), 2)) == [0, 1, 2]

    # a worker that dies: one clear error, not a hang
    def die(x):
        if os.getpid() != parent:
            os._exit(3)
        time.sleep(0.2)
        return x

    parent = os.getpid()
    with pytest.raises(EstimatorError, match="a worker process of jobs = 2 ended abruptly"):
        list(fork_map(die, list(range(4)), 2))


def test_bad_jobs_is_one_line(bags, tmp_path, capsys):
    for command in ("compare", "diagnose"):
        assert main([command, str(bags[0]), "--jobs", "0", "-o", str(tmp_path / "r"), "-q"]) == 1
        err = capsys.readouterr().err
        assert err == f"flexforce {command}: error: --jobs 0; expected a positive number of worker processes " \
                      "(1: one at a time, here) or auto\n"
        assert not (tmp_path / "r").exists()
        with pytest.raises(SystemExit) as exc:  # not a number: a usage error (exit 2)
            main([command, str(bags[0]), "--jobs", "many", "-o", str(tmp_path / "r"), "-q"])
        assert exc.value.code == 2
        assert "argument --jobs/-j: 'many'; expected a number of worker processes or 'auto'" in capsys.readouterr().err
        assert not (tmp_path / "r").exists()
    # a worker's error is the command's one line, and no report folder is left
    missing = tmp_path / "missing-bag"
    assert main(["compare", str(bags[0]), str(missing), "--estimators", "ekf", "--jobs", "2", "-o",
                 str(tmp_path / "r"), "-q"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("flexforce compare: error:") and "missing-bag" in err and err.count("\n") == 1, err
    assert not (tmp_path / "r").exists()


def test_progress_off_a_terminal_is_one_line_per_stage(bags, tmp_path, capsys):
    bar = Progress("stage")  # pytest's stderr is not a terminal
    for f in (0.0, 0.3, 0.7, 1.0, 1.0):
        bar(f)
    err = capsys.readouterr().err
    assert re.fullmatch(r"\[ *\d+\.\d s\] stage: done \(\d+\.\d s\)\n", err), err
    Progress("quiet", enabled=False)(1.0)
    forced = Progress("bar", enabled=True)
    forced(0.5)
    forced(1.0)
    err = capsys.readouterr().err
    assert "quiet" not in err and err.startswith("\rbar") and "100%" in err and err.endswith("\n")
    # a whole command: one line per stage, none redrawn
    assert main(["compare", str(bags[0]), "--estimators", "ekf", "-o", str(tmp_path / "r")]) == 0
    lines = capsys.readouterr().err.splitlines()
    assert lines and "\r" not in "".join(lines)
    assert any(re.fullmatch(r"\[ *\d+\.\d s\] ekf: done \(\d+\.\d s\)", line) for line in lines), lines


def test_auto_jobs_is_the_usable_cores_as_memory_allows(monkeypatch):
    from flexforce.compare import runner

    monkeypatch.setattr(runner, "usable_cores", lambda: 8)
    monkeypatch.setattr(runner, "available_memory", lambda: 10 << 30)
    monkeypatch.setattr(runner, "resident_memory", lambda: 3 << 30)
    # 80 % of 10 GiB holds two workers of 3 GiB (this process's size, above WORKER_MEMORY)
    assert runner.resolve_jobs("auto") == 2
    assert runner.resolve_jobs("auto", per_worker=1 << 30) == 8
    assert runner.resolve_jobs("auto", items=3, per_worker=1 << 30) == 3
    monkeypatch.setattr(runner, "resident_memory", lambda: 1 << 20)  # a small process: WORKER_MEMORY each
    assert runner.resolve_jobs("auto") == int(0.8 * (10 << 30) // runner.WORKER_MEMORY)
    monkeypatch.setattr(runner, "available_memory", lambda: 1 << 29)  # too little for one: still one
    assert runner.resolve_jobs("auto") == 1
    monkeypatch.setattr(runner, "available_memory", lambda: None)  # unknown: the cores
    assert runner.resolve_jobs("auto") == 8
    assert runner.resolve_jobs(3) == 3  # a number is taken as given
    for bad in (0, -1, "some", 2.0, True):
        with pytest.raises(ConfigError, match="expected a positive number of worker processes .* or 'auto'"):
            runner.resolve_jobs(bad)
    # the real machine: at least one, no more than its cores
    monkeypatch.undo()
    assert 1 <= runner.resolve_jobs("auto") <= runner.usable_cores()
    assert list(runner.run_jobs(abs, [-3, 2, -1], jobs="auto")) == [3, 2, 1]
    assert sorted(v for _, ok, v, _ in runner.fork_map(abs, [-3, 2, -1], "auto")) == [1, 2, 3]


def test_a_container_cpu_quota_bounds_the_usable_cores(tmp_path, monkeypatch):
    from flexforce.compare import runner

    quota = tmp_path / "cpu.max"
    quota.write_text("150000 100000\n")  # 1.5 cores' worth: two processes may share it
    assert runner.cpu_quota(str(quota)) == 1.5
    quota.write_text("max 100000\n")
    assert runner.cpu_quota(str(quota)) is None
    quota.write_text("garbage")
    assert runner.cpu_quota(str(quota)) is None
    assert runner.cpu_quota(str(tmp_path / "none")) is None
    monkeypatch.setattr(runner, "cpu_quota", lambda: 1.5)
    monkeypatch.setattr(runner.os, "sched_getaffinity", lambda pid: set(range(64)), raising=False)
    assert runner.usable_cores() == 2
    monkeypatch.setattr(runner, "cpu_quota", lambda: 0.2)
    assert runner.usable_cores() == 1
    monkeypatch.setattr(runner, "cpu_quota", lambda: None)
    assert runner.usable_cores() == 64


PARENT_SCRIPT = """
import os, sys, time

from flexforce.compare import runner


def nap(x):
    os.write(1, f"{os.getpid()}\\n".encode())  # one write: the workers' lines do not interleave
    time.sleep(600)


if __name__ == "__main__":
    pool, watch = sys.argv[1:]
    if watch == "poll":  # as where prctl is not available (inherited by the forked workers)
        runner._libc_prctl = lambda: None
    if pool == "run_jobs":  # spawned workers: compare of many recordings
        list(runner.run_jobs(nap, [0, 1], jobs=2))
    else:  # forked workers (two, and this process) as in the diagnosis
        list(runner.fork_map(nap, [0, 1, 2], jobs=3))
"""


def _alive(pid: int) -> bool:
    """The process ``pid`` runs (a zombie, ended but not reaped by its new parent, does not)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except (FileNotFoundError, ProcessLookupError):
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("pool, watch", [("run_jobs", "prctl"), ("fork_map", "prctl"), ("fork_map", "poll")])
def test_workers_end_when_their_parent_is_killed(tmp_path, pool, watch):
    """A parent killed outright (SIGKILL: no clean-up) takes its pool's workers with it: through
    the kernel (prctl PR_SET_PDEATHSIG) or, where that is not available, a thread watching the parent."""
    import os
    import select
    import signal
    import subprocess
    import time

    script = tmp_path / "parent.py"
    script.write_text(PARENT_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script), pool, watch], stdout=subprocess.PIPE)
    workers: set[int] = set()
    try:
        printed = b""
        deadline = time.monotonic() + 60
        while len(workers) < 2 and time.monotonic() < deadline:
            if select.select([proc.stdout], [], [], 1.0)[0]:
                chunk = os.read(proc.stdout.fileno(), 4096)  # unbuffered: select sees all that is left
                assert chunk, f"the parent ended before its workers started (exit {proc.wait()})"
                printed += chunk
                # fork_map's parent works through the items too
                workers = {int(pid) for pid in printed.split(b"\n")[:-1]} - {proc.pid}
        assert len(workers) == 2, printed
        time.sleep(0.2)  # the workers are in their task, past the initializer
        proc.kill()
        proc.wait()
        deadline = time.monotonic() + 5
        while any(map(_alive, workers)) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not [pid for pid in workers if _alive(pid)]
    finally:
        proc.kill()
        for pid in workers:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
        proc.stdout.close()


PIPELINE_SCRIPT = """
import os, sys, time

from flexforce.datasets.io.stream import pipelined


def parts():
    os.write(1, f"{os.getpid()}\\n".encode())
    while True:  # more parts than the queue holds: the producer blocks on it
        yield list(range(1000))


if __name__ == "__main__":
    for _ in pipelined(parts, depth=2):
        time.sleep(600)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_streamed_imports_producer_ends_when_its_parent_is_killed(tmp_path):
    """``pipelined`` imports in a child process that waits for room in its queue: a parent killed
    outright takes it along (it was left sleeping for good, holding its memory)."""
    import os
    import select
    import signal
    import subprocess
    import time

    script = tmp_path / "parent.py"
    script.write_text(PIPELINE_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE)
    child = None
    try:
        deadline = time.monotonic() + 60
        printed = b""
        while child is None and time.monotonic() < deadline:
            if select.select([proc.stdout], [], [], 1.0)[0]:
                chunk = os.read(proc.stdout.fileno(), 4096)
                assert chunk, f"the parent ended before its producer started (exit {proc.wait()})"
                printed += chunk
                if b"\n" in printed:
                    child = int(printed.split(b"\n")[0])
        assert child is not None and child != proc.pid
        time.sleep(0.5)  # the producer fills the queue and blocks
        assert _alive(child)
        proc.kill()
        proc.wait()
        deadline = time.monotonic() + 5
        while _alive(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(child)
    finally:
        proc.kill()
        if child is not None and _alive(child):
            os.kill(child, signal.SIGKILL)
        proc.stdout.close()


def test_a_workers_warnings_read_as_the_parents(capsys, monkeypatch):
    """The --jobs workers print a warning as the command does (``flexforce compare: warning: ...``,
    one line), not as Python's default (file, line, category and a source line)."""
    import warnings

    import flexforce.cli as cli

    monkeypatch.setattr(warnings, "showwarning", warnings.showwarning)  # restored after the test
    monkeypatch.setattr(cli, "PROGRESS_WORKER", False)
    monkeypatch.setattr(cli, "PROGRESS_ORIGIN", cli.PROGRESS_ORIGIN)
    cli._worker_init(0.0, "compare")
    warnings.warn("accel (/imu) clipped\nfrom t = 0 s", UserWarning, stacklevel=1)
    err = capsys.readouterr().err
    assert err == "flexforce compare: warning: accel (/imu) clipped from t = 0 s\n"
