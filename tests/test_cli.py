"""The command line: thin over the library, one-line errors."""

from __future__ import annotations

import subprocess
import sys

import pytest

from flexforce.cli import main
from flexforce.datasets.io.bagio import load_recording
from flexforce.datasets.sim.scenario import Scenario, builtin_scenarios


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
        from flexforce.datasets.sim.simulator import Simulator

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


# ---- exit statuses, one-line errors, outputs checked before the work --------------------------------
import flexforce.cli as cli  # noqa: E402
import flexforce.pipeline as pipeline  # noqa: E402
from flexforce.datasets.safeio import lock_path  # noqa: E402


@pytest.fixture(scope="module")
def stand_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "stand"
    assert main(["simulate", "stand", "--duration", "0.3", "-o", str(path), "-q"]) == 0
    return path


def _err(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err  # one line, no traceback
    return err


def test_help_documents_the_exit_statuses(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    assert "exit status:" in out
    for code in ("0", "1", "2", "130"):
        assert f"  {code} " in out


def test_compare_refuses_an_unknown_estimator_as_run_does(tmp_path, stand_bag, capsys):
    assert main(["run", str(stand_bag), "--estimator", "foo", "-o", str(tmp_path / "e.npz"), "-q"]) == 1
    run_err = _err(capsys)
    assert main(["compare", str(stand_bag), "--estimators", "ekf,foo", "-o", str(tmp_path / "rep"), "-q"]) == 1
    compare_err = _err(capsys)
    message = "error: unknown estimator 'foo'; expected one of ekf, fixed-lag, batch"
    assert message in run_err and message in compare_err
    assert not (tmp_path / "rep").exists()


@pytest.mark.parametrize("command", ["run", "simulate", "compare", "diagnose"])
def test_output_paths_are_checked_before_any_work(tmp_path, stand_bag, capsys, monkeypatch, command):
    def no_work(*args, **kwargs):
        raise AssertionError("the work started before the output was checked")

    monkeypatch.setattr(pipeline, "open_recording", no_work)
    monkeypatch.setattr(pipeline, "load_or_simulate", no_work)
    monkeypatch.setattr(cli, "_load_or_simulate", no_work)
    monkeypatch.setattr(cli, "_simulate", no_work)
    source = "stand" if command == "simulate" else str(stand_bag)
    out = tmp_path / "no-such-folder" / ("e.npz" if command == "run" else "out")
    assert main([command, source, "-o", str(out), "-q"]) == 1
    err = _err(capsys)
    assert "no-such-folder of output" in err and "does not exist; expected an existing folder" in err
    (tmp_path / "afile").write_text("x")
    bad = {"run": tmp_path / "e.txt", "simulate": tmp_path / "afile" / "rec",
           "compare": tmp_path / "report.json", "diagnose": tmp_path / "afile" / "d"}[command]
    expected = {"run": "has suffix '.txt'; expected .npz, .csv, .mcap", "simulate": "is not a folder",
                "compare": "has the suffix of a file (.json); expected a folder name", "diagnose": "is not a folder"}
    assert main([command, source, "-o", str(bad), "-q"]) == 1
    assert expected[command] in _err(capsys)


def test_a_report_never_replaces_a_folder_of_other_files(tmp_path, stand_bag, capsys):
    mine = tmp_path / "thesis"
    mine.mkdir()
    (mine / "chapter1.tex").write_text("precious")
    assert main(["compare", str(stand_bag), "--estimators", "ekf", "-o", str(mine), "-q"]) == 1
    assert "cannot replace" in _err(capsys) and (mine / "chapter1.tex").read_text() == "precious"


def test_a_second_writer_is_refused(tmp_path, stand_bag, capsys):
    out = tmp_path / "e.npz"
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock_path(out).write_text(f"{other.pid}\n")
        assert main(["run", str(stand_bag), "-o", str(out), "-q"]) == 1
        err = _err(capsys)
        assert f"is being written by process {other.pid}" in err and "expected one writer at a time" in err
        assert main(["simulate", "stand", "-o", str(tmp_path / "e.npz"), "-q"]) == 1  # a .npz is no bag folder
        _err(capsys)
    finally:
        other.kill()
        other.wait()
    assert not out.exists()


def test_run_refuses_a_recording_too_short(tmp_path, capsys):
    rec = tmp_path / "short"
    assert main(["simulate", "stand", "--duration", "0.02", "-o", str(rec), "-q"]) == 0
    capsys.readouterr()
    assert main(["run", str(rec), "-o", str(tmp_path / "e.npz"), "-q"]) == 1
    assert "recording has 5 sample(s) at 200 Hz; the estimators need at least 10 samples" in _err(capsys)


def test_run_with_an_unstable_robot_config(tmp_path, stand_bag, capsys):
    from flexforce.datasets.robot import RobotConfig

    text = open(RobotConfig.load("romeo").source).read()
    robot = tmp_path / "soft.toml"
    robot.write_text(text.replace("k_ts = 450.0", "k_ts = 100.0"))
    assert main(["run", str(stand_bag), "--robot", str(robot), "-o", str(tmp_path / "e.npz"), "-q"]) == 1
    assert "stiffness.k_ts = 100.0 N m/rad of robot 'romeo'" in _err(capsys)
    robot.write_text(text.replace("k_fs = 28000.0", "k_fs = -1.0"))
    assert main(["run", str(stand_bag), "--robot", str(robot), "-o", str(tmp_path / "e.npz"), "-q"]) == 1
    assert "stiffness.k_fs = -1.0 N/m; expected a positive, finite stiffness" in _err(capsys)
    robot.write_text(text.replace("k_ts = 450.0", "k_ts = 200.0"))  # below m g h for one foot: a warning
    assert main(["run", str(stand_bag), "--robot", str(robot), "-o", str(tmp_path / "e.npz"), "-q"]) == 0
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and "flexforce run: warning: stiffness.k_ts = 200" in captured.err


def test_run_estimator_checks_toppling_as_the_cli_does(tmp_path, stand_bag):
    """The library raises and warns as ``flexforce run`` reports: run_estimator without a model
    (its nominal model), and the comparison."""
    import warnings

    from flexforce.compare.estimators import nominal_model, run_estimator
    from flexforce.compare.runner import compare
    from flexforce.datasets.robot import RobotConfig
    from flexforce.errors import ConfigError, ConfigWarning

    text = open(RobotConfig.load("romeo").source).read()
    robot = tmp_path / "soft.toml"
    rec = load_recording(stand_bag)
    rec.robot = str(robot)
    robot.write_text(text.replace("k_ts = 450.0", "k_ts = 100.0"))
    for call in (lambda: run_estimator("ekf", rec), lambda: compare(rec, estimators=["ekf"])):
        with pytest.raises(ConfigError, match=r"stiffness.k_ts = 100.0 N m/rad of robot 'romeo'"):
            call()
    robot.write_text(text.replace("k_ts = 450.0", "k_ts = 200.0"))  # below m g h for one foot: a warning
    with pytest.warns(ConfigWarning, match="stiffness.k_ts = 200"):
        est = run_estimator("ekf", rec)
    assert est.n == rec.n
    model = nominal_model(load_recording(stand_bag))  # romeo's own springs: no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConfigWarning)
        run_estimator("ekf", rec, model)  # a given model is taken as it is


def _numba_interrupt():
    """What a numba kernel raises when Ctrl-C lands inside it."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt:
        raise SystemError("<built-in function kernel> returned a result with an exception set")  # noqa: B904


@pytest.mark.parametrize("raise_", [lambda: (_ for _ in ()).throw(KeyboardInterrupt), _numba_interrupt],
                         ids=["KeyboardInterrupt", "SystemError-from-numba"])
def test_an_interrupt_exits_130(tmp_path, stand_bag, capsys, monkeypatch, raise_):
    def interrupted(*args, **kwargs):
        raise_()

    monkeypatch.setattr(cli, "_run", interrupted)
    assert main(["run", str(stand_bag), "-o", str(tmp_path / "e.npz"), "-q"]) == 130
    assert _err(capsys) == "flexforce run: interrupted\n"
    assert list(tmp_path.iterdir()) == []  # no output, no lock


def test_an_interrupt_wrapped_in_a_flexforce_error_exits_130(capsys, monkeypatch, tmp_path):
    from flexforce.errors import BagError

    def interrupted(*args, **kwargs):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as err:
            raise BagError("cannot read bag x: corrupt") from err

    monkeypatch.setattr(cli, "_simulate", interrupted)
    assert main(["simulate", "stand", "-o", str(tmp_path / "r"), "-q"]) == 130


def test_an_unexpected_error_is_one_line(tmp_path, stand_bag, capsys, monkeypatch):
    def bug(*args, **kwargs):
        raise ValueError("shapes (3,) and (4,)\nnot aligned")

    monkeypatch.setattr(cli, "_run", bug)
    monkeypatch.delenv("FLEXFORCE_DEBUG", raising=False)
    assert main(["run", str(stand_bag), "-o", str(tmp_path / "e.npz"), "-q"]) == 1
    err = _err(capsys)
    assert "internal error ValueError: shapes (3,) and (4,) not aligned" in err and "FLEXFORCE_DEBUG=1" in err


def test_an_interrupted_simulate_leaves_the_previous_bag(tmp_path, capsys, monkeypatch):
    from flexforce.datasets.io import bagio

    out = tmp_path / "rec"
    assert main(["simulate", "stand", "--duration", "0.1", "-o", str(out), "-q"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    real = bagio._write

    def half(writer, ts, rec, meta):
        real(writer, ts, rec, meta)  # every message written, the bag not yet closed
        raise KeyboardInterrupt

    monkeypatch.setattr(bagio, "_write", half)
    assert main(["simulate", "stand", "--duration", "0.2", "-o", str(out), "--force", "-q"]) == 130
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]  # no temporary, no lock
    assert load_recording(out).n == 21


def test_an_interrupted_compare_leaves_the_previous_report(tmp_path, stand_bag, capsys, monkeypatch):
    from flexforce.compare.reports import comparison as report

    out = tmp_path / "rep"
    out.mkdir()
    (out / "index.html").write_text("old report")
    (out / "summary.json").write_text("{}")

    def interrupted(comp, rec, folder, title=None):
        folder.mkdir()
        (folder / "summary.json").write_text('{"new": 1}')
        raise KeyboardInterrupt

    monkeypatch.setattr(report, "_write_report", interrupted)
    assert main(["compare", str(stand_bag), "--estimators", "ekf", "-o", str(out), "-q"]) == 130
    assert (out / "index.html").read_text() == "old report" and (out / "summary.json").read_text() == "{}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rep"]
    monkeypatch.undo()
    assert main(["compare", str(stand_bag), "--estimators", "ekf", "-o", str(out), "-q"]) == 0
    assert (out / "index.html").read_text() != "old report" and '"ekf"' in (out / "summary.json").read_text()


def test_urdf_option_replaces_the_configurations(tmp_path, capsys):
    """``--urdf`` points a robot configuration at another copy of its URDF; without ``--robot`` or
    with a missing file it is one line and exit status 1."""
    import shutil

    from conftest import ICUB_DIR

    from flexforce.datasets.robot import RobotConfig

    bag = ICUB_DIR / "icub-walk-12s"
    if not bag.exists():
        pytest.skip("the iCub recordings are not beside this checkout")
    shipped = RobotConfig.load("icub").urdf
    copy = tmp_path / "elsewhere.urdf"
    shutil.copy(shipped, copy)
    out = tmp_path / "est.npz"
    args = ["run", str(bag), "--robot", "icub", "--urdf", str(copy), "--end", "2", "-o", str(out), "-q"]
    assert main(args) == 0 and out.exists()
    capsys.readouterr()
    assert main(["run", str(bag), "--urdf", str(copy), "-o", str(tmp_path / "b.npz"), "-q"]) == 1
    assert "give that configuration with --robot" in capsys.readouterr().err
    assert main(["run", str(bag), "--robot", "icub", "--urdf", str(tmp_path / "none.urdf"), "-o",
                 str(tmp_path / "c.npz"), "-q"]) == 1
    err = capsys.readouterr().err
    assert "no such file" in err and len(err.strip().splitlines()) == 1


def test_icub_urdf_ships_with_the_package():
    """The iCub configurations find their URDF inside the package, not beside the checkout."""
    from pathlib import Path

    import flexforce.datasets
    from flexforce.datasets.robot import RobotConfig

    package = Path(flexforce.datasets.__file__).resolve().parent
    for name in ("icub", "icub-identified"):
        urdf = Path(RobotConfig.load(name).urdf)
        assert urdf.is_file() and package in urdf.parents


def test_compare_with_footholds(stand_bag, tmp_path):
    """``compare --footholds``: the smoothers estimate the footholds (reported), the EKF runs as it is."""
    import json

    out = tmp_path / "rep"
    assert main(["compare", str(stand_bag), "--estimators", "ekf,fixed-lag", "--footholds", "-o", str(out),
                 "-q"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    rows = summary["estimators"]
    assert rows["fixed_lag"]["extra"]["options"] == {"footholds": True}
    assert "footholds estimated" in rows["fixed_lag"]["extra"]["footholds"]
    assert "options" not in rows["ekf"]["extra"]


def test_run_mcap_output_is_the_named_file(tmp_path, capsys):
    """``run REC -o walk.mcap`` writes the MCAP file walk.mcap (no folder holding walk.mcap.mcap),
    offline and streamed, and names its robot for ``layout --bag``."""
    from flexforce.datasets.io.export import export_info

    rec = tmp_path / "rec"
    assert main(["simulate", "stand", "--duration", "0.3", "--robot", "talos", "-o", str(rec), "-q"]) == 0
    for estimator in ("ekf", "fixed-lag"):
        out = tmp_path / f"walk-{estimator}.mcap"
        assert main(["run", str(rec), "--estimator", estimator, "-o", str(out), "-q"]) == 0, capsys.readouterr().err
        assert out.is_file() and export_info(out)["robot"] == "talos"
        assert main(["run", str(rec), "--estimator", estimator, "-o", str(out), "-q"]) == 1
        assert "exists already" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec", "walk-ekf.mcap", "walk-fixed-lag.mcap"]
