"""Footholds as unknowns of the smoothers (flexforce.factors.footholds): the factors against numerical
derivatives, the episode structure, the options, and the estimate on a recording whose footholds
are off the local placements.

The recording: the first 3.6 s of the walk (Romeo) in the simulator's ``relaxed`` touch-down mode:
the right foot lands at 2.4 s wherever it is in the world, 25 mm below the floor and tilted by
3 deg with the body, its spring unloaded.  The local frame (the recording's contact placements)
believes it landed on the floor where it planned.  With the rest placements taken from the local
frame the model is wrong by 25 mm of preload after the step; the foothold unknowns must find
where the foot really rests.  The ground plane is turned off (``terrain = "none"``): the floor is
not where the foot rests, so only the leg kinematics at the touch-down (zero deflection, the
relaxed mode's convention) and the dynamics place it.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from baseline import upper

from flexforce.compare.estimators import run_estimator
from flexforce.compare.metrics import evaluate
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import ConfigError
from flexforce.factors import core
from flexforce.factors.footholds import (
    GAUGE,
    WALK_WITHIN,
    WALK_WITHIN_ANCHORED,
    FootholdPrior,
    Footholds,
    episode_starts,
)
from flexforce.factors.model import ModelConfig
from flexforce.smoother import BatchConfig
from flexforce.smoother.linearize import walk_sigma
from flexforce.smoother.problem import Problem, with_footholds

# Accuracy margin: the recording is seeded and the estimators deterministic; 10 % covers summation
# order in other BLAS/numba builds and where the iterations stop.
MARGIN = 0.10


@pytest.fixture(scope="module")
def relaxed_step():
    sc = dataclasses.replace(Scenario.load("walk-short"), touchdown="relaxed", duration=3.6)
    rec = Simulator(sc).run()
    model = ModelConfig.from_recording(rec)
    model = dataclasses.replace(model, foothold_prior=dataclasses.replace(model.foothold_prior, terrain="none"))
    return rec, model


def _landing(rec):
    """(step, contact index, true correction of the rest position (m)) of the touch-down."""
    k, i = np.argwhere(episode_starts(rec.contact_active))[0]
    ep = [e for e in rec.meta["contact_episodes"]
          if e["contact"] == rec.contact_names[i] and abs(e["start"] - (rec.time[k] - rec.time[0])) < 1e-6][0]
    return int(k), int(i), np.asarray(ep["world_p"]) - rec.contact_p[k, i]


def test_factors_match_numerical_derivatives(relaxed_step):
    rec, model = relaxed_step
    model = dataclasses.replace(model, foothold_prior=FootholdPrior())  # ground factors on too
    model, rest_p, rest_R = with_footholds(rec, model)
    prob = Problem.build(rec, model, rest_p=rest_p, rest_R=rest_R)
    eff = prob.effects[-1]
    k, _, _ = _landing(rec)
    steps = np.array([0, k, k + 3])
    rng = np.random.default_rng(1)
    n = len(steps)
    R = np.array([core.so3_exp(rng.normal(0, 0.03, 3)) for _ in steps])
    q = rng.normal(0, 0.01, (n, 15))
    W = rng.normal(0, 10, (n, prob.nc, 6))
    e = rng.normal(0, 0.005, (n, eff.dim))

    def evaluate_all(R, q, e):
        own = {key: v[0] for key, v in eff.factors(prob, steps, R, q, e).items()}
        own["contact"] = eff.residual_terms("contact", prob, steps, R, q, W, e)[0]
        return own

    base_own = eff.factors(prob, steps, R, q, e)
    base_c = eff.residual_terms("contact", prob, steps, R, q, W, e)
    analytic_s = {key: v[1] for key, v in base_own.items()}
    analytic_e = {key: v[2] for key, v in base_own.items()}
    analytic_s["contact"], analytic_e["contact"] = base_c[1], base_c[2]
    # the factors exist where they should: kinematics at the landing only, ground at every start
    assert base_own["kinematics/1"][3].tolist() == [0, 1, 0]
    assert base_own["ground/1"][3].tolist() == [1, 1, 0]
    assert base_own["kinematics/0"][3].tolist() == [0, 0, 0]
    base = evaluate_all(R, q, e)
    h = 1e-6
    for j in range(18):
        dx = np.zeros(18)
        dx[j] = h
        moved = evaluate_all(np.array([core.so3_exp(dx[:3]) @ Ri for Ri in R]), q + dx[3:], e)
        for key in base:
            num = (moved[key] - base[key]) / h
            scale = max(1.0, float(np.abs(analytic_s[key]).max()))
            # central-difference-free check: first-order error ~ h * curvature, relative 1e-4
            np.testing.assert_allclose(num, analytic_s[key][..., j], atol=1e-4 * scale, err_msg=f"{key} d/ds_{j}")
    for j in range(eff.dim):
        e2 = e.copy()
        e2[:, j] += h
        moved = evaluate_all(R, q, e2)
        for key in base:
            num = (moved[key] - base[key]) / h
            scale = max(1.0, float(np.abs(analytic_e[key]).max()))
            np.testing.assert_allclose(num, analytic_e[key][..., j], atol=1e-4 * scale, err_msg=f"{key} d/de_{j}")


def test_each_episode_is_its_own_foothold(relaxed_step):
    """The walk is cut at the touch-down only and tiny elsewhere.  The first stance's prior: on the
    smoothers' path (``with_footholds``: the first stance anchored) ``GAUGE`` times the kinematic
    sigmas in all six components, the first stance soles defining the local frame; on the
    diagnosis' candidate (``bind()``: not anchored) ``GAUGE`` times them in horizontal position
    and yaw only, the full kinematic sigmas in height and tilt (a shim under a standing foot
    must stay findable)."""
    rec, model = relaxed_step
    model, rest_p, rest_R = with_footholds(rec, model)
    prob = Problem.build(rec, model, rest_p=rest_p, rest_R=rest_R)
    eff = prob.effects[-1]
    assert eff.anchor_first_stance and eff.walk_within == WALK_WITHIN_ANCHORED
    rw = walk_sigma(eff, prob)
    s0 = eff.kinematic_sigmas(prob)
    k, i, _ = _landing(rec)
    cut = rw > 10 * s0
    # cut exactly between the step before the touch-down and the touch-down, for that contact's six
    assert np.argwhere(cut).tolist() == [[k - 1, 6 * i + j] for j in range(6)]
    # elsewhere constant: over the whole recording (720 steps) the walk allows 3 % of the sigma
    assert np.all(rw[~cut] * np.sqrt(rec.n) < 0.05 * np.broadcast_to(s0, rw.shape)[~cut])
    first = np.flatnonzero(rec.contact_active[0])
    others = np.setdiff1d(np.arange(len(rec.contact_names)), first)
    gauge = [0, 1, 5]  # horizontal position and yaw
    level = [2, 3, 4]  # height, roll and pitch
    # smoothers: the first stance anchored in all six components, the others at the kinematic sigmas
    prior = eff.prior(prob)[1]
    for j in first:
        np.testing.assert_allclose(prior[6 * j:6 * j + 6], GAUGE * s0[6 * j:6 * j + 6])
    for j in others:
        np.testing.assert_allclose(prior[6 * j:6 * j + 6], s0[6 * j:6 * j + 6])
    # the diagnosis' candidate: the first stance's height and tilt at the full kinematic sigmas
    bound = eff.bind(rec, model)
    assert not bound.anchor_first_stance and bound.walk_within == WALK_WITHIN
    prior = bound.prior(prob)[1]
    for j in first:
        np.testing.assert_allclose(prior[[6 * j + a for a in gauge]], GAUGE * s0[[6 * j + a for a in gauge]])
        np.testing.assert_allclose(prior[[6 * j + a for a in level]], s0[[6 * j + a for a in level]])
    np.testing.assert_allclose(walk_sigma(bound, prob)[~cut], WALK_WITHIN * np.broadcast_to(s0, rw.shape)[~cut])


def test_options_are_checked():
    with pytest.raises(ConfigError, match="BatchConfig.footholds"):
        BatchConfig(footholds="yes")
    with pytest.raises(ConfigError, match="terrain"):
        FootholdPrior(terrain="hill")
    with pytest.raises(ConfigError, match="kinematics_sigma_position"):
        FootholdPrior(kinematics_sigma_position=-1.0)
    with pytest.raises(ConfigError, match="n_contacts"):
        Footholds(0)
    with pytest.raises(ConfigError, match="anchor_first_stance"):
        Footholds(2, anchor_first_stance="yes")
    with pytest.raises(ConfigError, match="walk_within"):
        Footholds(2, walk_within=0.0)


def test_fixed_lag_finds_the_landing_foothold(relaxed_step):
    """Without the unknowns the 25 mm preload of the landing foot wrecks the forces after the step;
    with them the fixed-lag smoother places the foothold and the forces follow the truth."""
    rec, model = relaxed_step
    k, i, truth = _landing(rec)
    plain = evaluate(run_estimator("fixed-lag", rec, model=model), rec, skip=0.5).rmse
    est = run_estimator("fixed-lag", rec, model=model, footholds=True)
    m = evaluate(est, rec, skip=0.5).rmse
    ep = [e for e in est.effects["foothold"]["episodes"] if e["step"] == k and e["contact"] == i][0]
    first = [e for e in est.effects["foothold"]["episodes"] if e["step"] == 0 and e["contact"] == 1 - i][0]
    # the landing foothold relative to the stance foot's (the world's horizontal origin is a gauge)
    rel = np.asarray(ep["dp_m"]) - np.asarray(first["dp_m"])
    print(f"\nforce {plain['force_N']:.2f} -> {m['force_N']:.2f} N, foothold error (mm) "
          f"{np.round(1e3 * (rel - truth), 2)}, truth {np.round(1e3 * truth, 1)}")
    assert m["force_N"] <= upper("footholds.relaxed.fixed_lag.force_N", m["force_N"], rel=MARGIN)
    # without the unknowns: 39.5 N measured; with them at least ten times better
    assert m["force_N"] < 0.1 * plain["force_N"]
    # the landing's sinking found within 2 mm of the 24.9 mm (height is what preloads the spring)
    assert abs(rel[2] - truth[2]) <= upper("footholds.relaxed.fixed_lag.height_error_m", abs(rel[2] - truth[2]),
                                           add=0.5e-3)


@pytest.mark.slow
def test_batch_finds_the_landing_foothold(relaxed_step):
    """The batch smoother sees the whole recording: the landing foothold, relative to the stance
    foot's, to a millimetre in every axis."""
    rec, model = relaxed_step
    k, i, truth = _landing(rec)
    est = run_estimator("batch", rec, model=model, footholds=True)
    m = evaluate(est, rec, skip=0.5).rmse
    eps = est.effects["foothold"]["episodes"]
    ep = [e for e in eps if e["step"] == k and e["contact"] == i][0]
    first = [e for e in eps if e["step"] == 0 and e["contact"] == 1 - i][0]
    err = np.asarray(ep["dp_m"]) - np.asarray(first["dp_m"]) - truth
    print(f"\nbatch force {m['force_N']:.2f} N, tilt {np.degrees(m['rotation_rad']):.3f} deg, "
          f"foothold error (mm) {np.round(1e3 * err, 2)}")
    assert m["force_N"] <= upper("footholds.relaxed.batch.force_N", m["force_N"], rel=MARGIN)
    assert np.max(np.abs(err)) <= upper("footholds.relaxed.batch.foothold_error_m", float(np.max(np.abs(err))),
                                        add=0.5e-3)


@pytest.mark.slow
def test_fixed_lag_footholds_on_the_walk():
    """The walk (Romeo, four steps, the simulator's default ``floor`` touch-down: a foot touching
    early stops, then the leg levels it, so the contacts move in the local frame during their
    episodes and land off their planned placements): with the footholds estimated (flat floor,
    the default terrain) the fixed-lag smoother's force error falls several times."""
    rec = Simulator(Scenario.load("walk-short")).run()
    plain = evaluate(run_estimator("fixed-lag", rec), rec, skip=0.5).rmse
    est = run_estimator("fixed-lag", rec, footholds=True)
    m = evaluate(est, rec, skip=0.5).rmse
    print(f"\nforce {plain['force_N']:.2f} -> {m['force_N']:.2f} N, per contact {plain['contact_force_N']:.2f} -> "
          f"{m['contact_force_N']:.2f} N, tilt {np.degrees(plain['rotation_rad']):.2f} -> "
          f"{np.degrees(m['rotation_rad']):.2f} deg")
    assert m["force_N"] <= upper("footholds.walk_short.fixed_lag.force_N", m["force_N"], rel=MARGIN)
    assert m["contact_force_N"] <= upper("footholds.walk_short.fixed_lag.contact_force_N", m["contact_force_N"],
                                         rel=MARGIN)
    # measured 47.9 -> 5.7 N (total) and 78 -> 16 N (per contact): at least three times better
    assert m["force_N"] < plain["force_N"] / 3 and m["contact_force_N"] < plain["contact_force_N"] / 3
    # the tilt stays that of the floor: no worse than without the unknowns
    assert m["rotation_rad"] <= plain["rotation_rad"] * (1 + MARGIN)
