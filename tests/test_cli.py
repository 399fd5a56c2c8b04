"""The command line: thin over the library, one-line errors."""

from __future__ import annotations

import subprocess
import sys

import pytest

from flexforce.cli import main
from flexforce.datasets.bagio import load_recording
from flexforce.datasets.scenario import Scenario, builtin_scenarios


def test_builtin_scenarios_parse():
    names = builtin_scenarios()
    for name in ("stand", "com-step", "push-pitch", "push-roll", "sway", "weight-shift", "step"):
        assert name in names
        sc = Scenario.load(name)
        assert sc.description and sc.duration > 0


def test_simulate_writes_a_bag(tmp_path, capsys):
    out = tmp_path / "rec"
    assert main(["simulate", "push-pitch", "--duration", "0.5", "-o", str(out), "-q"]) == 0
    assert "wrote" in capsys.readouterr().out
    rec = load_recording(out)
    assert rec.n == 101 and rec.truth is not None
    assert rec.meta["scenario"]["name"] == "push-pitch"
    # refuses to overwrite
    assert main(["simulate", "stand", "--duration", "0.1", "-o", str(out), "-q"]) == 1
    assert "exists" in capsys.readouterr().err


def test_unknown_scenario_is_one_line_error(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "flexforce.cli", "simulate", "jump", "-o", str(tmp_path / "x")],
                          capture_output=True, text=True)
    assert proc.returncode == 1
    assert proc.stderr.count("\n") == 1
    assert "unknown scenario 'jump'" in proc.stderr and "push-pitch" in proc.stderr


def test_bad_scenario_file(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('name = "s"\nduration = 1.0\n[[swing]]\ncontact = "left_hand"\nlift = 0.2\nland = 0.5\n')
    with pytest.raises(Exception, match="swing names contact 'left_hand'"):
        from flexforce.datasets.simulator import Simulator

        Simulator(Scenario.load(f))
    f.write_text('name = "s"\nduration = 1.0\nrate = 300.0\n')
    assert main(["simulate", str(f), "-o", str(tmp_path / "o"), "-q"]) == 1


def test_run_exports_npz_csv_and_mcap(tmp_path, capsys):
    rec_path = tmp_path / "rec"
    assert main(["simulate", "stand", "--duration", "0.5", "-o", str(rec_path), "-q"]) == 0
    for suffix in (".npz", ".csv", ".mcap"):
        out = tmp_path / f"est{suffix}"
        assert main(["run", str(rec_path), "--estimator", "ekf", "-o", str(out), "-q"]) == 0, suffix
        assert out.exists() and out.stat().st_size > 1000
    lines = (tmp_path / "est.csv").read_text().splitlines()
    assert len(lines) == 1 + 101  # header and one row per step
    from rosbags.highlevel import AnyReader

    with AnyReader([tmp_path / "est.mcap"]) as reader:
        topics = {c.topic for c in reader.connections}
    assert "/imu" in topics and any(t.startswith("/estimate/ekf/") for t in topics)


def test_raw_robot_bag_needs_a_robot_config(tmp_path, capsys):
    from conftest import ICUB_DIR

    bag = ICUB_DIR / "icub-com-sinusoid-20s.bag"
    if not bag.exists():
        pytest.skip("the iCub recordings are not beside this checkout")
    assert main(["run", str(bag), "-o", str(tmp_path / "e.npz"), "-q"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--robot" in err and "raw robot bag" in err
