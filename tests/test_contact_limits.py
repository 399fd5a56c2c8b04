"""The reported contact wrenches stay inside what a contact can carry: by hand, as a projection that
brings them no further from any feasible wrench, and in every estimator, whose state is unchanged
and whose contact law's wrench is the reported one plus the excess."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flexforce.compare.estimators import nominal_model, run_estimator
from flexforce.compare.metrics import violations
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import ConfigError
from flexforce.factors import contact_limits as cl

SOLE = (-0.08, 0.12, -0.05, 0.04)


def cop(w):
    return np.stack([-w[..., 4] / w[..., 2], w[..., 3] / w[..., 2]], axis=-1)


def test_by_hand():
    w = np.array([[[1.0, 2.0, -5.0, 0.1, 0.2, 0.3],   # pulls: carries nothing
                   [30.0, 40.0, 100.0, 1.0, -2.0, 0.5]]])  # |F_t| 50 > 0.4 x 100; CoP (0.02, 0.01) inside
    active = np.array([[True, True]])
    out, n = cl.limit_contact_wrenches(w, active, (SOLE, SOLE), mu=0.4)
    assert np.all(out[0, 0] == 0.0)
    assert np.linalg.norm(out[0, 1, :2]) == pytest.approx(40.0)
    assert out[0, 1, 0] / out[0, 1, 1] == pytest.approx(0.75)  # direction kept
    assert np.all(out[0, 1, 2:] == w[0, 1, 2:])
    assert (n.negative_normal, n.friction, n.cop, n.in_contact) == (1, 1, 0, 2)
    # a CoP 0.3 m ahead and 0.1 m left of the contact point: onto the sole's front-left corner
    w2 = np.array([[[0.0, 0.0, 200.0, 20.0, -60.0, 0.7]]])
    out2, n2 = cl.limit_contact_wrenches(w2, np.array([[True]]), (SOLE,), mu=None)
    assert cop(out2[0, 0]) == pytest.approx([0.12, 0.04], abs=1e-8)
    assert out2[0, 0, 2] == 200.0 and out2[0, 0, 5] == 0.7
    assert (n2.cop, n2.friction) == (1, 0)
    # inactive contacts and no limits given: untouched
    same, n3 = cl.limit_contact_wrenches(w, np.array([[False, False]]), (), mu=None)
    assert np.array_equal(same, w) and n3.in_contact == 0


def test_projection_brings_no_wrench_further_from_a_feasible_one():
    rng = np.random.default_rng(3)
    n = 4000
    w = np.column_stack([rng.normal(0, 80, (n, 2)), rng.normal(60, 120, n), rng.normal(0, 25, (n, 3))])[:, None, :]
    out, counts = cl.limit_contact_wrenches(w, np.ones((n, 1), bool), (SOLE,), mu=0.6)
    assert counts.negative_normal > 100 and counts.friction > 100 and counts.cop > 100
    fz = out[:, 0, 2]
    on = fz > 0
    assert np.all(fz >= 0.0) and np.all(np.linalg.norm(out[on, 0, :2], axis=1) <= 0.6 * fz[on])
    c = cop(out[on, 0])
    assert np.all((c[:, 0] >= SOLE[0]) & (c[:, 0] <= SOLE[1]) & (c[:, 1] >= SOLE[2]) & (c[:, 1] <= SOLE[3]))
    # any feasible reference: normal force, CoP, and (at the same normal force) tangential force no
    # further than before
    ref_fz = rng.uniform(1.0, 300.0, n)
    ref_ft = rng.normal(0, 1, (n, 2))
    ref_ft *= (0.6 * np.abs(w[:, 0, 2]) * rng.uniform(0, 1, n) / np.linalg.norm(ref_ft, axis=1))[:, None]
    ref_cop = np.column_stack([rng.uniform(SOLE[0], SOLE[1], n), rng.uniform(SOLE[2], SOLE[3], n)])
    assert np.all(np.abs(out[:, 0, 2] - ref_fz) <= np.abs(w[:, 0, 2] - ref_fz) + 1e-9)
    push = w[:, 0, 2] > 0
    assert np.all(np.linalg.norm(out[push, 0, :2] - ref_ft[push], axis=1)
                  <= np.linalg.norm(w[push, 0, :2] - ref_ft[push], axis=1) + 1e-9)
    assert np.all(np.linalg.norm(c - ref_cop[on], axis=1) <= np.linalg.norm(cop(w[on, 0]) - ref_cop[on], axis=1) + 1e-9)


def test_frames_round_trip():
    rng = np.random.default_rng(0)
    n, C = 5, 2
    R = np.array([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(n)])
    R *= np.sign(np.linalg.det(R))[:, None, None]
    t = rng.normal(size=(n, 3))
    p = rng.normal(size=(n, C, 3))
    Rc = np.array([[np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(C)] for _ in range(n)])
    local = rng.normal(size=(n, C, 6))
    world = cl.world_wrench(R, t, local, p, Rc)
    back = cl.contact_frame_wrench(R, t, world, p, Rc, np.ones((n, C), bool))
    assert back == pytest.approx(local, abs=1e-12)


@pytest.fixture(scope="module")
def walk():
    sc = Scenario.load("walk")
    sc.duration = 3.0
    return Simulator(sc).run()


@pytest.mark.parametrize("name", ["ekf", "fixed_lag", "batch"])
def test_estimators_report_limited_wrenches(walk, name):
    """A sole smaller than the simulated robot's and a low friction coefficient make the contact
    law ask for what the contacts cannot carry; the reported wrenches keep inside, the state is the
    unlimited run's, and wrench + wrench_excess is its wrench."""
    base = nominal_model(walk)
    tight = dataclasses.replace(base, soles=((-0.03, 0.05, -0.02, 0.02),) * len(walk.contact_names), friction=0.05)
    free = run_estimator(name, walk, dataclasses.replace(tight, limit_wrenches=False))
    est = run_estimator(name, walk, tight)
    assert est.t == pytest.approx(free.t, abs=1e-12) and est.R == pytest.approx(free.R, abs=1e-12)
    assert est.wrench + est.wrench_excess == pytest.approx(free.wrench, abs=1e-9)
    assert free.wrench_excess is None
    v = violations(est, walk, mu=0.05, soles=tight.soles)
    law = v["contact_law"]
    assert v["negative_normal"]["count"] == v["friction_cone"]["count"] == v["cop_outside_sole"]["count"] == 0
    assert law["friction_cone"]["count"] > 50 and law["cop_outside_sole"]["count"] > 50
    lim = est.meta["contact_limits"]
    assert lim["cop"] == law["cop_outside_sole"]["count"] and lim["negative_normal"] == law["negative_normal"]["count"]
    # the total CoP follows the reported wrenches
    moved = np.any(est.wrench_excess != 0.0, axis=(1, 2)) & (est.total_wrench[:, 2] > 1.0)
    assert moved.any()
    W = est.total_wrench[moved]
    assert est.cop[moved, 0] == pytest.approx(-W[:, 4] / W[:, 2], abs=1e-9)


def test_robot_friction_is_checked():
    import tomllib
    from pathlib import Path

    from flexforce.datasets.robot import RobotConfig

    assert RobotConfig.load("icub").friction == 0.7 and RobotConfig.load("romeo").friction is None
    src = Path(RobotConfig.load("icub").source)
    def raw(friction):
        return {**tomllib.loads(src.read_text()), "friction": friction}

    assert RobotConfig.from_dict(raw(1.1), base=src.parent).friction == 1.1
    for bad in (0, -0.5, "high", float("nan"), float("inf"), 50.0, True):
        with pytest.raises(ConfigError, match="friction = .*expected the Coulomb friction coefficient"):
            RobotConfig.from_dict(raw(bad), base=src.parent)
