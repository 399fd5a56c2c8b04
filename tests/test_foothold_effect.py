"""Tests of the foothold candidate (``foothold``): the simulator's hidden foothold error, the
effect made for the recording, and the diagnosis that names a foothold error where it otherwise
blames the IMU.

The recordings: 3 s of the ``sway`` scenario (Romeo; the CoM sways sideways, the load moves from
foot to foot), the simulator's own noise and contact model (not the estimator's), the IMU bias
random walk off.  The hidden error: the ground under the left foot 4 mm higher than the robot
believes (a shim).  Slow: Romeo's short walk, whose touch-downs the simulator lands where the
floor stops the foot (``touchdown = "floor"``) while the recording keeps the kinematics' placement
-- the foothold errors a real walk has, with no hidden effect added.
"""

from __future__ import annotations

import numpy as np
import pytest
from baseline import lower, upper

from flexforce.compare.diagnostics.run import diagnose
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import ConfigError
from flexforce.factors import core
from flexforce.factors.effects import make_effect
from flexforce.factors.footholds import Footholds
from flexforce.factors.model import ModelConfig
from flexforce.smoother import Problem

SHIM = {"type": "foothold", "contact": "left_foot", "position": [0.0, 0.0, 0.004], "rotation": [0.0, 0.0, 0.0]}
CANDIDATES = ["foothold", "accel-bias", "com-offset", "imu-mounting"]
"""The foothold candidate and what a wrong rest placement looks like to the IMU and the dynamics:
a tilt read as a bias or a turned IMU, a load moved between the feet read as a CoM offset."""
_CACHE: dict = {}


def simulate(effects, motion: str = "sway", duration: float = 3.0):
    key = (repr(effects), motion, duration)
    if key not in _CACHE:
        sc = Scenario.load(motion)
        sc.duration = duration
        sc.seed = 0
        sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
        sc.effects = list(effects)
        _CACHE[key] = Simulator(sc).run()
    return _CACHE[key]


def test_the_hidden_foothold_moves_the_true_rest_not_the_recorded_one():
    rec, clean = simulate([SHIM]), simulate([])
    first = {e["contact"]: e for e in rec.meta["contact_episodes"] if e["start"] == 0.0}
    left, right = first["left_foot"], first["right_foot"]
    np.testing.assert_allclose(np.subtract(left["world_p"], left["local_p"]), SHIM["position"], atol=1e-12)
    np.testing.assert_allclose(right["world_p"], right["local_p"], atol=1e-12)
    # the recording's placements are the nominal ones; the robot stands tilted by the shim
    np.testing.assert_allclose(rec.contact_p, clean.contact_p, atol=1e-12)
    assert np.abs(rec.truth.R[0] - clean.truth.R[0]).max() > 1e-3
    for bad, what in (({**SHIM, "contact": "nose"}, "unknown contact 'nose'"),):
        sc = Scenario.load("sway")
        sc.duration = 0.1
        sc.effects = [bad]
        with pytest.raises(ConfigError, match=what):
            Simulator(sc).run()
    # a contact in the air at the first sample has no rest placement to move
    sc = Scenario.load("step")
    sc.duration = 0.1
    sc.swing[0]["lift"] = 0.0
    sc.effects = [{**SHIM, "contact": sc.swing[0]["contact"]}]
    with pytest.raises(ConfigError, match="'right_foot', which is not in contact at the start"):
        Simulator(sc).run()


def test_the_twin_is_the_term_at_the_truth():
    """At the true states and wrenches of a noise-free sway (1.5 s) with the left foot's ground
    4 mm higher and pitched 3 mrad, the contact law on the nominal rest misses the left foot's
    wrench by 112 N (measured); with the foothold term at the true correction it is exact to the
    integrator's tolerance (measured 2e-9 N, the clean recording's own level): bound 1e-9 of the
    nominal miss."""
    shim = {**SHIM, "rotation": [0.0, 0.003, 0.0]}
    sc = Scenario.load("sway")
    sc.duration = 1.5
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    sc.effects = [shim]
    rec = Simulator(sc, noise=False).run()
    eff = Footholds(2)
    prob = Problem.build(rec, ModelConfig.from_recording(rec, effects=(eff,)))
    tr = rec.truth
    c = np.ascontiguousarray
    R, q = c(tr.R), c(np.concatenate([tr.t, tr.w, tr.v, tr.dw, tr.a], axis=1))
    n, nc = rec.n, 2
    r, J = np.empty((n, nc, 6)), np.empty((n, nc, 6, 18))
    core.contact_all(R, q, c(tr.wrench), c(prob.active), c(prob.contact_p), c(prob.contact_R), c(prob.rest_p),
                     c(prob.rest_R), c(prob.K_fs), c(prob.K_fd), c(prob.K_ts), c(prob.K_td), c(prob.beta),
                     c(prob.iso), r, J, np.empty((0, nc, 6, 6)))
    value = np.zeros((n, eff.dim))
    value[:, :3], value[:, 3:6] = shim["position"], shim["rotation"]
    after = r + eff.residual_terms("contact", prob, np.arange(n), R, q, None, value)[0]
    keep = slice(20, n - 20)
    before = np.abs(r[keep]).max()
    assert before > 50.0, before  # N: the error is there
    assert np.abs(after[keep]).max() <= 1e-9 * before, np.abs(after[keep]).max(axis=0)


def test_the_effect_is_made_for_the_recording():
    rec = simulate([])
    model = ModelConfig.from_recording(rec)
    eff = make_effect("foothold")
    assert eff.dim == 12 and len(eff.labels) == eff.dim == len(eff.excites)
    three = Footholds(3)
    prob = Problem.build(rec, ModelConfig.from_recording(rec, effects=(three,)))
    with pytest.raises(ConfigError, match="made for 3 contacts, the recording has 2"):
        three.prior(prob)
    bound = three.bind(rec, model)
    assert bound.nc == 2 and bound.prior_config == model.foothold_prior
    with pytest.raises(ConfigError, match="positive count"):
        Footholds(0)
    # estimated footholds hold each episode's nominal placement from its first step
    prob = Problem.build(rec, ModelConfig.from_recording(rec, effects=(bound,)))
    on = rec.contact_active
    first = np.argmax(on, axis=0)
    for c in range(rec.contact_p.shape[1]):
        held = prob.rest_p[on[:, c], c]
        np.testing.assert_allclose(held, np.broadcast_to(rec.contact_p[first[c], c], held.shape), atol=0.0)


def test_left_out_of_the_default_catalogue_without_a_touch_down():
    from types import SimpleNamespace

    from flexforce.compare.diagnostics.run import left_out_by_default

    rec = simulate([])
    out = left_out_by_default(rec, {"foothold": lambda: make_effect("foothold"),
                                    "gyro-bias": lambda: make_effect("gyro-bias")})
    assert list(out) == ["foothold"] and "no contact touches down" in out["foothold"], out
    active = np.ones((50, 2), dtype=bool)
    active[10:30, 1] = False  # a step: the right foot lifts and lands again
    assert Footholds().by_default(SimpleNamespace(contact_active=active)) is None


def _rotation_ratio(d) -> float:
    return d.after.rmse["rotation_rad"] / d.before.rmse["rotation_rad"]


def test_the_diagnosis_names_a_shim_under_a_foot():
    rec = simulate([SHIM])
    d = diagnose(rec, candidates=CANDIDATES, add=["auto"], ekf=False)
    assert d.selected[:1] == ["foothold"], d.ranking_table()
    first = d.rounds[0]
    assert first[0].effect == "foothold" and not first[0].rivals, d.ranking_table()
    rep = first[0].parameters
    left, right = (next(e for e in rep["episodes"] if e["contact"] == c and e["step"] == 0) for c in (0, 1))
    # the left foot found higher than the right (the ground prior, the floor within 2 mm of the
    # feet's mean plane, takes part of the shim's 4 mm)
    dz = left["dp_m"][2] - right["dp_m"][2]
    assert 0.0 < dz <= SHIM["position"][2], rep["summary"]
    assert dz >= lower("foothold.shim.left_dz", dz, rel=0.2), rep["summary"]
    # tilt and force errors fall once the footholds are estimated
    ratio = _rotation_ratio(d)
    assert ratio <= upper("foothold.shim.tilt_ratio", ratio, rel=0.5, add=0.02), (d.before.rmse, d.after.rmse)
    force = d.after.rmse["force_N"] / d.before.rmse["force_N"]
    assert force <= upper("foothold.shim.force_ratio", force, rel=0.2, add=0.02), (d.before.rmse, d.after.rmse)


def test_a_clean_recording_has_no_foothold_error():
    d = diagnose(simulate([]), candidates=CANDIDATES, add=["auto"], ekf=False)
    assert "foothold" not in d.selected, d.ranking_table()


@pytest.mark.slow
def test_on_a_walk_the_diagnosis_finds_the_footholds_not_an_imu_error():
    """The simulated walk lands its feet where the floor stops them, the recording keeps where the
    kinematics put them: the foothold candidate, not an IMU bias, explains it, and the tilt error
    falls."""
    rec = simulate([], motion="walk-short", duration=9.5)
    d = diagnose(rec, candidates=["foothold", "accel-bias", "gyro-bias", "imu-mounting", "com-offset"],
                 add=["auto"], ekf=False, max_effects=1)
    assert d.selected == ["foothold"], d.ranking_table()
    ratio = _rotation_ratio(d)
    assert ratio <= upper("foothold.walk.tilt_ratio", ratio, rel=0.5, add=0.02), (d.before.rmse, d.after.rmse)


def test_the_default_catalogue_keeps_the_footholds_in_the_table():
    """Left out of the default catalogue's refits on a recording without a touch-down, the footholds
    stay in the identifiability table: standing, a shim under a foot reads like a CoM offset, an
    accelerometer bias or a turned IMU, and the notes say so beside what the ranking chose."""
    rec = simulate([SHIM])
    d = diagnose(rec, ekf=False, screen_level=1e-300)  # the table, no refit
    assert any(line.startswith("foothold: left out by default") for line in d.skipped), d.skipped
    tested = {t.effect for t in d.screening} | {c.effect for c in d.ranking}
    assert "foothold" not in tested and "foothold" in d.identifiability.candidates
    partners = {p.b if p.a == "foothold" else p.a for p in d.identifiability.inseparable() if "foothold" in (p.a, p.b)}
    assert partners & {"com-offset", "accel-bias", "imu-mounting"}, d.identifiability.text()
    notes = [n for n in d.identifiability_notes() if "foothold" in n]
    assert notes and all("foothold in the table only, not tested" in n for n in notes), notes
    assert notes == [n for n in d.to_json()["identifiability"]["notes"] if "foothold" in n]
