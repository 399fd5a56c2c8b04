"""Plausibility from physics: the deflections a recording's own loads produce, a cubic softening
that would make a contact give way, a hardening with no bound; and the selection's rule for a
candidate fitted to implausible values that the data favour by far (DiagnoseConfig.dominance)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flexforce.compare.diagnostics.config import DiagnoseConfig
from flexforce.compare.diagnostics.results import Candidate
from flexforce.compare.diagnostics.selection import _dominated
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import ConfigError
from flexforce.factors.effects import make_effect
from flexforce.factors.effects.base import _recorded_deflections
from flexforce.factors.model import ModelConfig
from flexforce.smoother import Problem


@pytest.fixture(scope="module")
def problem():
    sc = Scenario.load("sway")
    sc.duration = 1.0
    rec = Simulator(sc).run()
    return Problem.build(rec, ModelConfig.from_recording(rec))


def test_recorded_deflections_by_hand(problem):
    s, omega = _recorded_deflections(problem)
    m, g = float(problem.rec.mass), problem.g
    k_f = [float(np.trace(K)) / 3.0 for K in problem.K_fs]
    k_t = [float(np.trace(K)) / 3.0 for K in problem.K_ts]
    act = problem.active
    assert act.all()  # the sway stands on both feet
    load = m * (g + problem.com_acc[:, 2])
    assert s == pytest.approx(float(np.max(load)) / 2.0 / min(k_f))
    centroid = problem.contact_p[:, :, :2].mean(axis=1)
    moment = m * g * np.linalg.norm(problem.com[:, :2] - centroid, axis=1)
    assert omega == pytest.approx(float(np.max(moment)) / 2.0 / min(k_t))
    assert 0 < s < 0.05 and 0 < omega < 0.2


def test_cubic_softening_that_gives_way_is_implausible_hardening_is_not(problem):
    eff = make_effect("nonlinear-stiffness")
    s, omega = _recorded_deflections(problem)
    # hardening of any size: no physical bound (30 times the linear stiffness at the recorded tilt)
    assert eff.plausible({"value": [10.0 / s**2, 10.0 / omega**2]}, problem) is None
    # softening that keeps a positive tangent stiffness where the recording goes: plausible
    assert eff.plausible({"value": [-0.3 / s**2, -0.3 / omega**2]}, problem) is None
    # softening past zero there: the contact would give way under loads the robot bore
    why = eff.plausible({"value": [0.0, -0.34 / omega**2]}, problem)
    assert why is not None and "rotational cubic softening" in why and "give way" in why
    assert "translational" not in why
    why = eff.plausible({"value": [-0.34 / s**2, 0.0]}, problem)
    assert why is not None and why.startswith("translational cubic softening")
    assert eff.plausible({"value": [-1.0, -1.0]}, None) is None


def _row(name: str, score: float | None) -> Candidate:
    return Candidate(name, (), 1, score, score, 2.0, 0.0, True)


def test_dominance_rule():
    cfg = DiagnoseConfig()
    assert cfg.dominance == 2.0
    leader, plausible = _row("nonlinear-stiffness", 900.0), _row("external-wrench", 400.0)
    assert _dominated(cfg, leader, plausible)  # 900 > 2 x 400 and 500 above it
    assert not _dominated(cfg, _row("nonlinear-stiffness", 790.0), plausible)  # not twice
    assert not _dominated(cfg, _row("a", 10.0), _row("b", 4.5))  # twice, but within the tie (6)
    assert _dominated(cfg, _row("a", 12.0), _row("b", -3.0))  # a negative best plausible counts as 0
    assert not _dominated(cfg, None, plausible)
    assert not _dominated(cfg, _row("a", None), plausible)
    assert not _dominated(dataclasses.replace(cfg, dominance=None), leader, plausible)
    for bad in (0.5, True, float("nan"), "2"):
        with pytest.raises(ConfigError, match="dominance"):
            DiagnoseConfig(dominance=bad)


def test_a_dominant_row_says_so():
    from flexforce.compare.diagnostics.text import finding

    c = _row("nonlinear-stiffness", 900.0)
    c.implausible, c.dominant, c.significant, c.summary = "the contact would give way", True, False, "beta = -5"
    text = finding(c, {}, make_effect("nonlinear-stiffness"))
    assert text.startswith("implausible: the contact would give way") and "no candidate is taken in its place" in text
    assert c.to_dict()["dominant"] is True
    c.dominant = False
    assert "dominant" not in c.to_dict() and "another effect in disguise" in finding(c, {}, None)
