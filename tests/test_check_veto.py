"""The check's veto (DiagnoseConfig.check_veto): a round does not take an effect whose fit raises an
error against the truth or the references by more than check_worse, over its base or over the
nominal model; without references nothing is vetoed."""

from __future__ import annotations

from types import SimpleNamespace

from flexforce.compare.diagnostics.config import DiagnoseConfig
from flexforce.compare.diagnostics.results import Candidate
from flexforce.compare.diagnostics.selection import _vetoed, auto_added
from flexforce.compare.diagnostics.text import finding


def _check(before: dict, after: dict) -> dict:
    return {"against": "truth", "before": before, "after": after}


class _Session:
    """What _vetoed reads of a Session: config, cache, check(base, fit), fitted(())."""

    def __init__(self, errors: dict[tuple[str, ...], dict | None]):
        self.config = DiagnoseConfig()
        self.errors = errors  # fitted effects -> their errors (None: nothing to check against)
        self.cache = {tuple(sorted(k)): SimpleNamespace(effects=tuple(sorted(k))) for k in errors}

    def fitted(self, key):
        return self.cache[tuple(sorted(key))]

    def check(self, base, fit):
        b, a = self.errors[base.effects], self.errors[fit.effects]
        return None if b is None or a is None else _check(b, a)


def _cand(name: str, base: tuple[str, ...] = ()) -> Candidate:
    return Candidate(name, base, len(base) + 1, 50.0, 60.0, 3.0, 1e-9, True)


def test_an_effect_that_raises_an_error_beyond_check_worse_is_turned_down_with_the_numbers():
    s = _Session({(): {"vertical_force_N": 28.0, "rotation_rad": 0.010},
                  ("mass-scale",): {"vertical_force_N": 100.0, "rotation_rad": 0.009}})
    c = _cand("mass-scale")
    why = _vetoed(s, c, s.fitted(()))
    assert why is not None and "the truth" in why and "28 -> 100" in why and "5%" in why
    assert c.check is not None and c.check["after"]["vertical_force_N"] == 100.0


def test_within_check_worse_or_lower_errors_pass():
    s = _Session({(): {"vertical_force_N": 28.0, "rotation_rad": 0.010},
                  ("gyro-bias",): {"vertical_force_N": 29.3, "rotation_rad": 0.002}})  # +4.6 %, and lower
    assert _vetoed(s, _cand("gyro-bias"), s.fitted(())) is None


def test_the_nominal_model_bounds_the_drift_of_the_rounds():
    """Each round within 5 % of its base, but the second above the nominal model by more: turned down."""
    s = _Session({(): {"vertical_force_N": 10.0},
                  ("a",): {"vertical_force_N": 10.4},
                  ("a", "b"): {"vertical_force_N": 10.8}})
    why = _vetoed(s, _cand("b", ("a",)), s.fitted(("a",)))
    assert why is not None and "above the nominal model" in why


def test_a_rise_below_its_floor_is_no_reason():
    """+100 % of a tenth of a millimetre of position (the references' noise) vetoes nothing; the
    same relative rise of a force beyond half a newton does."""
    s = _Session({(): {"translation_m": 1.3e-4, "force_N": 15.6},
                  ("nonlinear-stiffness",): {"translation_m": 2.6e-4, "force_N": 1.0},
                  ("mass-scale",): {"translation_m": 1.3e-4, "force_N": 16.4}})
    assert _vetoed(s, _cand("nonlinear-stiffness"), s.fitted(())) is None
    why = _vetoed(s, _cand("mass-scale"), s.fitted(()))
    assert why is not None and "force 15.6 -> 16.4" in why and "position" not in why


def test_nothing_to_check_against_vetoes_nothing():
    s = _Session({(): None, ("gyro-bias",): None})
    assert _vetoed(s, _cand("gyro-bias"), s.fitted(())) is None


def test_a_vetoed_row_says_it_was_turned_down_not_that_it_stands_for_another_effect():
    c = _cand("mass-scale")
    c.implausible, c.vetoed, c.significant = "its check against the truth disagrees: force 28 -> 100 N", True, False
    text = finding(c, {}, None)
    assert text.startswith("turned down:") and "--add auto" in text
    assert c.status == "implausible" and c.to_dict()["turned_down_by_check"] is True


def test_a_rise_outweighed_by_falls_is_taken():
    """A push fitted before the CoM offset it also soaks up: the force error triples, the CoP, tilt
    and hand errors fall tenfold -- taken (the sum of ln(after / before) is below 0)."""
    s = _Session({(): {"force_N": 3.16, "cop_m": 0.0203, "rotation_rad": 0.0089, "hand_m": 0.0063},
                  ("external-wrench",): {"force_N": 10.3, "cop_m": 0.0017, "rotation_rad": 0.0005, "hand_m": 0.0004}})
    c = _cand("external-wrench")
    assert _vetoed(s, c, s.fitted(())) is None and c.check is not None


def test_auto_adds_the_longest_first_part_of_the_selection_that_raises_no_error():
    s = _Session({(): {"force_N": 10.0, "cop_m": 0.010},
                  ("a",): {"force_N": 5.0, "cop_m": 0.005},
                  ("a", "b"): {"force_N": 12.0, "cop_m": 0.002}})
    added, note = auto_added(s, ["a", "b"])
    assert added == ["a"] and note is not None and note.startswith("auto: b not added")
    assert "force 10 -> 12" in note
    s.errors[("a", "b")] = {"force_N": 4.0, "cop_m": 0.002}
    assert auto_added(s, ["a", "b"]) == (["a", "b"], None)
    s.config = DiagnoseConfig(check_veto=False)
    s.errors[("a", "b")] = {"force_N": 40.0, "cop_m": 0.002}
    assert auto_added(s, ["a", "b"]) == (["a", "b"], None)
