"""The diagnosis's progress: full stage labels, the round out of how many, the time elapsed and
an estimate of what is left; on stderr, and only without --quiet."""

from __future__ import annotations

import re

import pytest

from flexforce.cli import main
from flexforce.compare.diagnostics.progress import DiagnosisProgress


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_rounds_and_time_left_from_the_refits_done():
    """Three candidates, max_effects 2: at most two rounds, three refits in the first and two in
    the second; the time left is the mean time per refit since round 1 began times those left."""
    clock = Clock()
    p = DiagnosisProgress(max_effects=2, clock=clock)
    clock.t += 4.0
    assert p.update("nominal", 1.0, "fitted the nominal model") == "fitted the nominal model -- 4.0 s elapsed"
    # the number of candidates is read from the screening (one call per candidate)
    note = p.update("screening", 1 / 3, "a: T = 3")
    assert p.candidates == 3 and p.rounds == 2 and p.refits_left() == 3 + 2
    assert note == "a: T = 3 -- round 1 of 2, 4.0 s elapsed, time left: known after the first refit"
    p.update("screening", 2 / 3, "b: T = 1")
    p.update("screening", 1.0, "c: T = 9")
    clock.t += 10.0
    p.update("+ a", 0.5)
    assert p.refits == 0
    note = p.update("+ a", 1.0, "fitted + a")
    assert p.refits == 1 and p.refits_left() == 2 + 2
    assert note == "fitted + a -- round 1 of 2, 14.0 s elapsed, at most ~40.0 s left (4 refit(s) at 10.0 s each)"
    p.update("+ a", 1.0, "a: score 3")  # the same refit's second message is not a second refit
    assert p.refits == 1
    clock.t += 10.0
    p.update("+ b", 1.0, "fitted + b")
    p.update("+ c", 1.0, "fitted + c")
    assert p.refits_left() == 2
    clock.t += 6.0
    note = p.update("screening at + c", 0.5, "a: T = 2")
    assert note.endswith("round 2 of 2, 30.0 s elapsed, at most ~17.3 s left (2 refit(s) at 8.7 s each)")
    p.update("+ c + a", 1.0, "fitted + c + a")
    p.update("+ c + b", 1.0, "fitted + c + b")
    assert p.update("+ c + b", 1.0, "b: score 1").endswith("no refit left")
    assert p.update("second look: screening at + a", 1.0, "x").startswith("x -- second look, ")


def test_the_rounds_are_bounded_by_the_candidates_or_max_effects():
    assert DiagnosisProgress(max_effects=3, candidates=2).rounds == 2
    assert DiagnosisProgress(max_effects=1, candidates=5).rounds == 1
    p = DiagnosisProgress(max_effects=3)
    assert p.rounds == 3 and p.update("+ a", 1.0, "fitted + a").startswith("fitted + a -- round 1 of 3, ")
    assert p.update("ekf", 1.0) is None


@pytest.fixture(scope="module")
def two_effects_bag(tmp_path_factory):
    """1.5 s of standing with a hidden gyrometer and accelerometer bias: two rounds."""
    from test_diagnose import ACCEL, GYRO, simulate

    from flexforce.datasets.io.bagio import save_recording

    return save_recording(simulate([GYRO, ACCEL], duration=1.5), tmp_path_factory.mktemp("progress") / "rec")


def test_cli_diagnose_progress(two_effects_bag, tmp_path, capsys):
    args = ["diagnose", str(two_effects_bag), "--candidates", "gyro-bias,accel-bias", "--no-ekf"]
    assert main([*args, "-o", str(tmp_path / "quiet"), "-q"]) == 0
    assert capsys.readouterr().err == ""
    assert main([*args, "-o", str(tmp_path / "rep")]) == 0
    captured = capsys.readouterr()
    err = captured.err
    assert "round" not in captured.out and "elapsed" not in captured.out
    lines = err.splitlines()
    # full labels: a second round's screening and refit, longer than a bar's label column
    assert any(re.search(r"\] screening at \+ (gyro|accel)-bias: ", line) for line in lines), err
    refit = [line for line in lines if re.search(r"\] \+ (accel-bias \+ gyro-bias|gyro-bias \+ accel-bias): fitted",
                                                 line)]
    assert refit and "round 2 of 2" in refit[0] and "elapsed" in refit[0], err
    assert any("round 1 of 2" in line and re.search(r"at most ~[\d.]+ s left \(\d refit\(s\) at [\d.]+ s each\)", line)
               for line in lines), err
    assert sum("elapsed" in line for line in lines) >= 5


def test_a_note_on_a_terminal_is_a_full_line_above_the_bar(capsys):
    from flexforce.cli import Progress

    label = "  screening at + accel-bias + gyro-bias"
    bar = Progress(label, enabled=True)
    bar(0.5)
    bar.note("ftoffset: T = 2 -- round 3 of 3")
    bar(0.5)  # the bar is drawn again below the note
    err = capsys.readouterr().err
    assert "\r\x1b[K[" in err and f"] {label.strip()}: ftoffset: T = 2 -- round 3 of 3\n" in err
    assert err.count(f"\r{label}") == 2
    Progress(label, enabled=False).note("nothing")
    assert capsys.readouterr().err == ""
