"""Recording.window and the --start/--end options: what is cut, what is kept, what is refused."""

from __future__ import annotations

import numpy as np
import pytest

from flexforce.cli import main
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import DataError


@pytest.fixture(scope="module")
def rec():
    sc = Scenario.load("push-pitch")
    sc.duration = 1.0
    r = Simulator(sc, noise=False).run()
    r.meta["anchor"] = {"first": r.contact_names[0],
                        "switches": [{"t": 0.2, "from": r.contact_names[0], "to": r.contact_names[1], "jump_m": 0.0},
                                     {"t": 0.7, "from": r.contact_names[1], "to": r.contact_names[0], "jump_m": 0.0}]}
    return r


def test_window_cuts_every_per_step_array(rec):
    w = rec.window(0.3, 0.6)
    k0 = int(np.argmin(np.abs(rec.time - 0.3)))
    k1 = int(np.argmin(np.abs(rec.time - 0.6)))
    assert w.n == k1 - k0 + 1
    assert w.time[0] == 0.0
    assert w.time[-1] == pytest.approx(0.3, abs=1e-9)
    np.testing.assert_array_equal(w.t_ns, rec.t_ns[k0:k1 + 1])
    np.testing.assert_array_equal(w.accel, rec.accel[k0:k1 + 1])
    np.testing.assert_array_equal(w.contact_active, rec.contact_active[k0:k1 + 1])
    np.testing.assert_array_equal(w.truth.R, rec.truth.R[k0:k1 + 1])
    np.testing.assert_array_equal(w.truth.wrench, rec.truth.wrench[k0:k1 + 1])
    if rec.ft is not None:
        np.testing.assert_array_equal(w.ft, rec.ft[k0:k1 + 1])
    if rec.base_pose is not None:
        np.testing.assert_array_equal(w.base_pose, rec.base_pose[k0:k1 + 1])
    for name, pose in rec.mocap.items():
        np.testing.assert_array_equal(w.mocap[name], pose[k0:k1 + 1])
    for name, p in rec.truth.links.items():
        np.testing.assert_array_equal(w.truth.links[name], p[k0:k1 + 1])
    w.validate()


def test_window_keeps_meta_consistent(rec):
    w = rec.window(0.3, 0.9)
    assert w.meta["window"]["start_s"] == pytest.approx(0.3, abs=1e-9)
    assert w.meta["window"]["end_s"] == pytest.approx(0.9, abs=1e-9)
    # the switch at 0.2 s is before the window: its target is the first anchor; 0.7 s becomes 0.4 s
    assert w.meta["anchor"]["first"] == rec.contact_names[1]
    assert [s["t"] for s in w.meta["anchor"]["switches"]] == [pytest.approx(0.4, abs=1e-6)]
    assert len(rec.meta["anchor"]["switches"]) == 2  # the original is untouched
    # a window of a window is placed in the original's seconds
    ww = w.window(0.1, 0.5)
    assert ww.meta["window"]["start_s"] == pytest.approx(0.4, abs=1e-9)


def test_window_open_ends(rec):
    assert rec.window(end=0.5).time[-1] == pytest.approx(0.5, abs=1e-9)
    assert rec.window(start=0.5).n == int(np.sum(rec.time >= 0.5 - 1e-9))


@pytest.mark.parametrize("start, end, match", [
    (0.6, 0.4, r"start = 0.6 s is not before end = 0.4 s; the recording covers 0 to 1\.0\d* s"),
    (0.5, 0.5, r"start = 0.5 s is not before end = 0.5 s"),
    (-1.0, 0.5, r"start = -1 s is outside the recording; the recording covers 0 to"),
    (0.2, 5.0, r"end = 5 s is outside the recording; the recording covers 0 to"),
    (float("nan"), None, r"start = nan s is not a finite time; expected seconds from the first sample \(the "
                         r"recording covers 0 to"),
    (None, float("inf"), r"end = inf s is not a finite time"),
    (0.5, 0.51, r"window 0.5 to 0.51 s holds \d sample\(s\) at \d+ Hz; at least 10 are needed"),
])
def test_window_refuses_bad_bounds(rec, start, end, match):
    with pytest.raises(DataError, match=match):
        rec.window(start, end)


def test_cli_window_errors_are_one_line(tmp_path, capsys):
    bag = tmp_path / "stand"
    assert main(["simulate", "stand", "--duration", "0.5", "-o", str(bag), "-q", "--no-noise"]) == 0
    capsys.readouterr()
    for cmd in (["run", str(bag), "-o", str(tmp_path / "e.npz")],
                ["compare", str(bag), "-o", str(tmp_path / "rep")],
                ["diagnose", str(bag), "-o", str(tmp_path / "diag")]):
        assert main(cmd + ["--start", "0.4", "--end", "0.2", "-q"]) == 1
        err = capsys.readouterr().err.strip()
        assert "\n" not in err
        assert err.startswith(f"flexforce {cmd[0]}: error: start = 0.4 s is not before end = 0.2 s")


def test_cli_run_on_a_window(tmp_path, capsys):
    bag = tmp_path / "stand"
    assert main(["simulate", "stand", "--duration", "0.5", "-o", str(bag), "-q", "--no-noise"]) == 0
    out = tmp_path / "e.npz"
    assert main(["run", str(bag), "-o", str(out), "--start", "0.1", "--end", "0.3", "-q"]) == 0
    from flexforce.datasets.estimate import Estimate

    est = Estimate.load(out)
    assert est.time[-1] == pytest.approx(0.2, abs=1e-9)
