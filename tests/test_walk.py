"""The walk scenarios: alternating single and double support, arms swinging, feet landing flat."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from flexforce.datasets.scenario import Scenario
from flexforce.datasets.simulator import Simulator
from flexforce.estimators import run_estimator


@pytest.fixture(scope="module")
def walk_short():
    sim = Simulator(Scenario.load("walk-short"))
    return sim, sim.run()


def test_walk_short_steps_forward(walk_short):
    _, rec = walk_short
    active = rec.contact_active
    lands = [(k, int(np.flatnonzero(active[k] & ~active[k - 1])[0])) for k in range(1, rec.n)
             if np.any(active[k] & ~active[k - 1])]
    assert [rec.contact_names[i] for _, i in lands] == ["right_foot", "left_foot", "right_foot", "left_foot"]
    n_down = active.sum(axis=1)
    assert n_down.min() == 1 and n_down.max() == 2
    # single support, then double support again, four times
    switches = np.flatnonzero(np.diff(n_down) != 0)
    assert len(switches) == 8
    # the feet end side by side, 15 cm ahead (half stride, two strides, half stride)
    np.testing.assert_allclose(rec.contact_p[-1, :, 0], [0.15, 0.15], atol=1e-9)
    # every foothold lies flat on the floor
    for ep in rec.meta["contact_episodes"]:
        assert abs(ep["world_p"][2]) < 1e-12
    # the arms swing: the hands move by centimetres in the local frame
    names = list(rec.truth.links)
    for name in names:
        p = rec.truth.links[name]
        assert np.ptp(p[:, 0] - p[:, 0].mean()) > 0.05


TILT, SINK = 6.76, 18.9  # deg, mm: measured on walk-short, Romeo, seed 0


def test_walk_short_flexibility_is_bounded(walk_short):
    """Open-loop walking on Romeo's flexibility (no stabiliser): the body rolls with each weight
    shift (the springs must tilt it to unload a foot) and the single-support sinking doubles.
    Bounds: the measured peaks (TILT, SINK) with a margin of 1.5x; static sinking 7.1 mm."""
    sim, rec = walk_short
    tr = rec.truth
    tilt = np.degrees([np.linalg.norm(pin.log3(R)[:2]) for R in tr.R])
    mg = rec.mass * rec.gravity
    static = mg / (2 * sim.springs[0].K_fs[0, 0])
    print(f"\npeak tilt {tilt.max():.2f} deg, peak sinking {-1e3 * tr.t[:, 2].min():.1f} mm, "
          f"static {1e3 * static:.1f} mm")
    assert tilt.max() < 1.5 * TILT
    assert -tr.t[:, 2].min() < 1.5 * SINK * 1e-3


def test_estimators_go_through_walk_short(walk_short):
    _, rec = walk_short
    est = run_estimator("ekf", rec)
    assert np.all(np.isfinite(est.t)) and np.all(np.isfinite(est.wrench))
