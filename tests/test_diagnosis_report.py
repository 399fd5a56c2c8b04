"""The diagnosis report's words: the verdict first, the fitted values after --add, one unit system
(mm, mrad), and sentences that agree with the numbers they quote (compare/diagnostics/text.py,
compare/reports/diagnosis.py, the CLI's printing)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from flexforce.compare.diagnostics import text
from flexforce.compare.diagnostics.config import DiagnoseConfig
from flexforce.compare.diagnostics.results import Candidate, Diagnosis
from flexforce.compare.reports.diagnosis import diagnosis_summary, selected_line

ERRORS = {"force_N": 3.16, "moment_Nm": 8.06, "cop_m": 0.0203, "rotation_rad": 0.00888, "hand_m": 0.00634}


def snap(rmse=None, flags=0, effects=None):
    """A before/after view with only what the words read: errors, flagged windows, estimates."""
    return SimpleNamespace(rmse=dict(rmse or ERRORS), flags=[object()] * flags,
                           estimate=SimpleNamespace(effects=effects or {}))


COM = {"value": [0.0212, 0.0001], "std": [0.0004, 0.0006], "unit": "m", "labels": ["x [m]", "y [m]"],
       "significant": ["x"], "summary": "CoM offset x = 0.0212 ± 0.0004 m"}
PUSH = {"windows": [{"start_s": 2.505, "end_s": 2.69, "peak_s": 2.595, "peak_force": [31.9, -1.6, -1.8],
                     "peak_std": [1.7, 1.7, 2.5]}], "summary": "external force ≈ 32 N along x"}


def row(effect, rnd=1, score=300.0, significant=True, base=(), **kw):
    c = Candidate(effect, tuple(base), rnd, score, None if score is None else score + 20.0,
                  None if score is None else 2.0, None if score is None else 1e-9, significant, **kw)
    return c


def diagnosis(rounds, selected, added=(), before=None, after=None, ranking=None, **kw):
    return Diagnosis({"has_truth": True}, ranking if ranking is not None else [c for r in rounds for c in r],
                     rounds, list(selected), list(added), before or snap(flags=24), after, **kw)


def test_verdict_names_the_effect_its_values_and_what_adding_it_does():
    com = row("com-offset", parameters=COM)
    after = snap({**ERRORS, "force_N": 1.12, "rotation_rad": 0.0005}, flags=3, effects={"com-offset": COM})
    v = diagnosis([[com]], ["com-offset"], ["com-offset"], after=after).verdict()
    assert v.startswith("The model misses com-offset (CoM offset x = 21.2 ± 0.4 mm)"), v
    assert "lowers the force error from 3.16 to 1.12 N" in v and "the tilt error from 8.88 to 0.5 mrad" in v, v
    assert "the flagged windows from 24 to 3" in v, v
    assert "correct the mass model" in v, v  # what to do, said of a found effect


def test_verdict_says_a_rise_of_an_error():
    com = row("com-offset", parameters=COM)
    after = snap({**ERRORS, "force_N": 10.0}, flags=3, effects={"com-offset": COM})
    v = diagnosis([[com]], ["com-offset"], ["com-offset"], after=after).verdict()
    assert "but it raises the force error from 3.16 to 10 N" in v, v


def test_verdict_when_nothing_is_selected_says_why():
    vetoed = row("external-wrench", score=4361.8, significant=False, parameters=PUSH,
                 implausible="its check against the truth disagrees: force 3.16 -> 10.3 N", vetoed=True)
    vetoed.check = {"against": "truth", "before": {"force_N": 3.16}, "after": {"force_N": 10.3}}
    v = diagnosis([[vetoed]], []).verdict()
    assert v.startswith("No effect is selected: the candidates the data favoured were turned down by their "
                        "check"), v
    assert "external-wrench (score 4361.8: raises the force error from 3.16 to 10.3 N)" in v, v
    weak = row("gyro-bias", score=-12.0, significant=False)
    v = diagnosis([[weak]], []).verdict()
    assert "none is significant (the best, gyro-bias, scores -12.0" in v, v


def test_after_add_by_hand_the_fitted_values_with_units_and_never_significant_none():
    after = snap({**ERRORS, "force_N": 2.61}, flags=3, effects={"external-wrench": PUSH, "com-offset": COM})
    d = diagnosis([], [], ["external-wrench", "com-offset"], after=after)
    assert selected_line(d) == "none; added by hand: external-wrench, com-offset"
    values = d.added_values()
    assert values == ["external-wrench: external force of 31.9 ± 1.7 N along +x at 2.50-2.69 s, peak at 2.60 s",
                      "com-offset: CoM offset x = 21.2 ± 0.4 mm"], values
    v = d.verdict()
    assert v.startswith("Added by hand: external-wrench (external force of 31.9 ± 1.7 N"), v
    assert "the flagged windows from 24 to 3" in v, v


def test_cli_prints_the_verdict_first_and_the_added_values(capsys):
    from flexforce.cli import _print_diagnosis

    after = snap(flags=3, effects={"com-offset": COM})
    d = diagnosis([], [], ["com-offset"], after=after)
    d.to_json = lambda: {"verdict": d.verdict(), "added_values": d.added_values(), "recording": {},  # no views
                         "selected": [], "added": ["com-offset"], "before": {"flagged_windows": [0] * 24, "rmse": {}},
                         "after": {"flagged_windows": [0] * 3, "rmse": {}}, "ranking": []}
    _print_diagnosis({"summary": diagnosis_summary(d), "ranking_table": "TABLE", "rmse": []})
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("verdict: Added by hand: com-offset (CoM offset x = 21.2 ± 0.4 mm)"), out
    assert "significant: none; added by hand: com-offset" in out, out
    assert "  added com-offset: CoM offset x = 21.2 ± 0.4 mm" in out, out


def test_a_row_not_refitted_says_what_its_earlier_refit_found():
    early = row("accel-bias", rnd=1, score=3344.0, parameters={"value": [0.08, 0, 0], "std": [0.01, 0.01, 0.01],
                                                                 "labels": ["x [m/s^2]", "y [m/s^2]", "z [m/s^2]"],
                                                                 "significant": ["x"]})
    taken = row("com-offset", rnd=1, score=3353.6, parameters=COM)
    late = row("accel-bias", rnd=2, score=None, significant=False, base=("com-offset",), refitted=False,
               deferred="stronger candidates filled the round's 3 refits")
    d = diagnosis([[taken, early], []], ["com-offset"], ranking=[taken, late])
    line = text.not_refitted_text(late, d)
    assert line.startswith("not refitted in round 2: stronger candidates"), line
    assert "refitted in round 1: significant (score 3344.0), accel bias x = 0.080 ± 0.010 m/s^2" in line, line
    assert "refitted in round 1: significant" in d.ranking_table()


def test_partner_check_with_errors_ten_times_apart_is_not_called_undecided():
    def check(force, cop):
        return {"against": "truth", "before": {"force_N": 150.0, "cop_m": 0.003},
                "after": {"force_N": force, "cop_m": cop}}

    chosen = row("mass-scale", score=310.0, parameters={})
    partner = row("stiffness", score=305.0, parameters={})
    chosen.check, partner.check = check(142.0, 0.0029), check(14.8, 0.00305)  # CoP 5.2 % higher: marginal
    partner.partner_of = "mass-scale"
    chosen.rivals = ("stiffness",)
    out = diagnosis([[chosen, partner]], ["mass-scale"]).partner_checks()
    assert len(out) == 1 and out[0].endswith("the truth favours stiffness over the choice (a motion that separates "
                                             "them, or knowledge of the robot, settles it)"), out
    assert "not decide" not in out[0]
    # a split with both sides clearly ahead on one error stays undecided, and says so
    partner.check = check(14.8, 0.006)
    out = diagnosis([[chosen, partner]], ["mass-scale"]).partner_checks()
    assert out[0].endswith("the errors split between the choice and stiffness (each lower by more than 5% on one "
                           "of them): the truth does not decide between them"), out


def test_constancy_line_quotes_the_component_found():
    bias = row("accel-bias", parameters={"value": [0.001, 0.002, 0.3], "std": [0.01, 0.01, 0.01],
                                          "labels": ["x [m/s^2]", "y [m/s^2]", "z [m/s^2]"], "significant": ["z"]})
    bias.constancy = {"made": True, "constant": True, "halves": [[0.0, 2.0], [2.0, 4.0]],
                      "value": [[0.0, -0.01, 0.30], [0.0, 0.02, 0.31]], "std": [[0.01] * 3, [0.01] * 3],
                      "z": [0.0, 2.1, 0.7], "relative": [0.0, 1.5, 0.03], "largest": ["y", 2.1],
                      "text": "its halves agree: accel bias y = ..."}
    line = text.constancy_line(bias, DiagnoseConfig())
    assert line.startswith("its halves agree on z = 0.300 ± 0.010 m/s^2 in 0.0-2.0 s, 0.310 ± 0.010 m/s^2 in "
                           "2.0-4.0 s (0.7σ apart)"), line
    assert "the largest difference is on y" in line, line


def test_not_significant_beyond_three_sigma_says_what_the_test_says():
    from flexforce.factors.effects import make_effect

    c = row("time-offset", score=-8.0, significant=False)
    c.p_value, c.level, c.lr, c.effective_dof = 0.12, 0.001, 2.4, 1.0
    c.summary = "IMU time offset tau = 0.0190 ± 0.0050 s"
    words = text.finding(c, {"value": [0.019], "std": [0.005]}, make_effect("time-offset"))
    assert words.startswith("not significant: the estimate IMU time offset tau = 0.0190 ± 0.0050 s is 3.8σ from 0"), \
        words
    assert "the likelihood-ratio test, which decides, does not confirm it: its p = 0.12 is above its level" in words
    # a scale is measured from 1, not from 0
    s = row("stiffness", score=-1.0, significant=False)
    s.p_value, s.level, s.summary = 3e-5, 0.001, "contact damping scale = 0.705 ± 0.064"
    words = text.finding(s, {"value": [0.705, 1.0], "std": [0.064, 0.1]}, make_effect("stiffness"))
    assert "4.6σ from 1" in words and "its BIC score, -1.0, is not above 0" in words, words
    assert "does not confirm" not in words, words  # its p is below its level: the score decides


def test_a_rejected_effect_gives_no_advice_a_found_one_does():
    from flexforce.factors.effects import make_effect

    eff = make_effect("time-offset")
    rep = {"value": [0.08], "std": [0.003]}
    c = row("time-offset", score=40.0, significant=False,
            implausible=eff.plausible(rep), summary="IMU time offset tau = 0.080 ± 0.003 s")
    assert "resynchronise" in c.implausible  # the effect's own word ...
    words = text.finding(c, rep, eff)
    assert "resynchronise" not in words and words.startswith("implausible: IMU time offset of 0.08 s"), words
    assert text.without_advice("its refit in round 1 was implausible (offset of 0.08 s is beyond 0.05 s: late; "
                               "resynchronise the logs)") == ("its refit in round 1 was implausible (offset of "
                                                              "0.08 s is beyond 0.05 s: late)")
    found = row("time-offset", parameters={"value": [0.019], "std": [0.003], "labels": ["tau [s]"]})
    v = diagnosis([[found]], ["time-offset"]).verdict()
    assert "To act on time-offset: resynchronise the logs" in v, v  # ... kept for a found one


def test_identifiability_does_not_contradict_a_found_effect():
    from flexforce.smoother.screening import CandidateInformation, Identifiability

    info = CandidateInformation("external-wrench", 6, ("u_Fx", "u_Fy", "u_Fz", "u_Tx", "u_Ty", "u_Tz"), "windowed",
                                2.4, "u_Tx", 3, 10.5, excites="a moment about x", strongest=50.0,
                                detectable=(2.5, 2.7, 1.8, 19.0, 19.0, 14.0))
    ident = Identifiability({"external-wrench": info}, [])
    push = row("external-wrench", parameters=PUSH)
    items = diagnosis([[push]], ["external-wrench"], identifiability=ident).identifiability_items()
    assert len(items) == 1 and "does not excite" not in items[0], items
    assert "a prior-sized u_Tx (a moment about x) gains 2.4 in 2 ln L" in items[0], items
    assert items[0].endswith("found all the same (see the verdict): larger than these sizes, or along the "
                             "directions the recording does excite"), items
    printed = diagnosis([[push]], ["external-wrench"], identifiability=ident).ranking_table()
    assert "   external-wrench: found all the same (see the verdict)" in printed, printed
    items = diagnosis([[]], [], identifiability=ident).identifiability_items()
    assert "found all the same" not in items[0]


def test_one_unit_system_mm_and_mrad():
    c = row("com-offset")
    c.check = {"against": "truth", "before": {"rotation_rad": 0.00888, "cop_m": 0.0203},
               "after": {"rotation_rad": 0.0005, "cop_m": 0.0015}}
    words = c.check_text()
    assert "tilt 8.88 -> 0.5 mrad" in words and "CoP 20.3 -> 1.5 mm" in words and "deg" not in words, words
    assert text.effect_values("imu-mounting", {"value": [0.01], "std": [0.001], "labels": ["x [rad]"]}) \
        == "IMU mounting rotation x = 10.0 ± 1.0 mrad"
    assert text.effect_values("com-offset", COM) == "CoM offset x = 21.2 ± 0.4 mm"


@pytest.mark.parametrize("value,std,expected", [(21.19, 0.37, "21.2 ± 0.4"), (0.0186, 0.0033, "0.019 ± 0.003"),
                                                (31.9, 1.7, "31.9 ± 1.7"), (4361.8, 12.0, "4362 ± 12"),
                                                (0.5, None, "0.5")])
def test_values_are_given_to_the_precision_of_their_sigma(value, std, expected):
    assert text._num(value, std) == expected


def _tutorial_figures():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "docs" / "tutorial_figures.py"
    spec = importlib.util.spec_from_file_location("tutorial_figures", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_tutorial_marks_are_filled_and_checked():
    tf = _tutorial_figures()
    page = "force <!--n:f-->1.0<!--/n--> N\n<!--block:t-->\nold\n<!--/block-->\n"
    values = {"f": "2.5", "block:t": "| a |\n"}
    assert tf.differences(page, values) == ["f: '1.0' != '2.5'", "block t differs"]
    new = tf.render(page, values)
    assert new == "force <!--n:f-->2.5<!--/n--> N\n<!--block:t-->\n| a |\n<!--/block-->\n"
    assert tf.differences(new, values) == []
    with pytest.raises(KeyError, match="g"):
        tf.render("<!--n:g-->1<!--/n-->", values)
    # every mark of the tutorial is one the script makes
    marks = set(tf.NUMBER.findall(tf.TUTORIAL.read_text())) | set(tf.BLOCK.findall(tf.TUTORIAL.read_text()))
    assert marks, "the tutorial has no generated numbers"


@pytest.mark.slow
def test_tutorial_numbers_are_those_of_its_run(tmp_path):
    """docs/tutorial.md's marked numbers equal those of its commands' run (about 80 s)."""
    tf = _tutorial_figures()
    values = tf.numbers(tf.run(tmp_path))
    assert tf.differences(tf.TUTORIAL.read_text(), values) == []


@pytest.fixture(scope="module")
def gyro_sway():
    """1 s of the sideways sway with a 0.02 rad/s gyro bias about y (no bias random walk)."""
    from flexforce.datasets.sim.scenario import Scenario
    from flexforce.datasets.sim.simulator import Simulator

    sc = Scenario.load("sway")
    sc.duration, sc.seed = 1.0, 4
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    sc.effects = [{"type": "gyro-bias", "value": [0.0, 0.02, 0.0]}]
    return Simulator(sc).run()


def test_the_page_opens_with_the_verdict_and_ends_with_the_details(gyro_sway, tmp_path):
    import json

    from flexforce.compare.diagnostics.run import diagnose
    from flexforce.compare.reports.diagnosis import write_diagnosis

    d = diagnose(gyro_sway, candidates=["gyro-bias", "accel-bias"], add=["auto"], ekf=False, max_effects=1)
    assert d.selected == ["gyro-bias"], d.ranking_table()
    page = (write_diagnosis(d, tmp_path / "d") / "index.html").read_text()
    verdict = page.index('<div class="verdict"')
    assert verdict < page.index("Which effect is missing") < page.index('id="details"') < page.index("Glossary")
    assert page[verdict:].split("<p>", 1)[1].startswith("The model misses gyro-bias (gyro bias y = 0.0")
    assert "added gyro-bias: gyro bias y = 0.0" in page and "Selected: <b>gyro-bias</b>" in page
    for term in ("score test (T)", "Holm", "Occam factor", "2 ln L", "BIC score"):
        assert f"<b>{term}" in page, term
    assert "[deg]" not in page and "tilt [mrad]" in page  # one unit system: mm and mrad, as the comparison
    data = json.loads((tmp_path / "d" / "diagnosis.json").read_text())
    assert data["verdict"] == d.verdict() and data["added_values"] == d.added_values()


def test_a_row_turned_down_by_its_check_says_so_in_the_page():
    from flexforce.compare.reports.diagnosis import _ranking_row

    c = row("mass-scale", score=22.4, significant=False, implausible="its check disagrees", vetoed=True)
    d = diagnosis([[c]], [])
    assert _ranking_row(d, c, None)["verdict"] == "turned down by its check" and c.status == "implausible"


def test_after_add_without_ranking_the_page_says_added_by_hand(gyro_sway, tmp_path):
    from flexforce.compare.diagnostics.run import diagnose
    from flexforce.compare.reports.diagnosis import write_diagnosis

    d = diagnose(gyro_sway, add=["gyro-bias"], rank=False, ekf=False)
    page = (write_diagnosis(d, tmp_path / "d") / "index.html").read_text()
    assert "Selected: <b>none; added by hand: gyro-bias</b>" in page and "not ranked" in page
    assert "added gyro-bias: gyro bias y = 0.0" in page
    assert d.verdict().startswith("Added by hand: gyro-bias (gyro bias y = 0.0"), d.verdict()
