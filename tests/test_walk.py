"""The walk scenarios: alternating single and double support, arms swinging, feet landing flat."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from flexforce.compare.estimators import run_estimator
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator


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
    # the feet end side by side, 15 cm ahead (half stride, two strides, half stride), short by
    # the travel their last swing had left when it touched the floor early (measured 3.7 and
    # 10.3 mm; earlier shortfalls are made up by the next swing)
    for i, name in enumerate(rec.contact_names):
        last = [ep for ep in rec.meta["contact_episodes"] if ep["contact"] == name][-1]
        short = last.get("local_off_plan", [0.0, 0.0, 0.0])[0]
        assert -0.015 < short <= 0.0
        np.testing.assert_allclose(rec.contact_p[-1, i, 0], 0.15 + short, atol=1e-9)
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


# ----------------------------------------------------------------------------------------------
# Floor touch-down: a foot that touches the floor before its scheduled landing stops there, the
# leg then levels (the skipped descent, over TOUCHDOWN_LEVEL), the recording keeps what the legs do.


def _touch_downs(rec):
    """(episode, sample index at or just after the touch) of every touch-down after the start."""
    out = []
    for ep in rec.meta["contact_episodes"]:
        if ep["start"] > 0.0:
            out.append((ep, int(np.ceil(ep["start"] / rec.dt - 1e-9))))
    return out


@pytest.fixture(scope="module")
def walk_short_talos():
    sim = Simulator(Scenario.load("walk-short"), "talos")
    return sim, sim.run()


def _check_touchdown(sim, rec, first_step: float, first_300ms: float, sinking: float):
    tr = rec.truth
    mg = rec.mass * rec.gravity
    tds = _touch_downs(rec)
    assert len(tds) == 4
    early = [ep for ep, _ in tds if "local_off_plan" in ep]
    assert early, "the stance leg's sinking makes the feet touch before their planned landing"
    for ep, k in tds:
        i = rec.contact_names.index(ep["contact"])
        # (a) no force jump: at the first sample (<= 5 ms after the touch) the spring holds the
        # damping of the landing speed and less than a millimetre of travel; over the next 0.3 s
        # the foot takes its share of the weight without a transient
        assert abs(tr.wrench[k, i, 2]) < first_step * mg
        assert np.abs(tr.wrench[k:k + int(round(0.3 / rec.dt)), i, 2]).max() < first_300ms * mg
        # (c) the foothold is on the floor, flat
        assert abs(ep["world_p"][2]) < 1e-12 and abs(ep["above_floor"]) < 1e-12
    for ep in early:
        # the foot stopped above its planned landing and the leg then levelled: it rests at the
        # planned height, short only of the travel it had left (horizontal)
        assert ep["local_off_plan"][2] > 0.005
        assert abs(ep["levelled_off_plan"][2]) < 1e-9
    # (b) the truth's sinking stays within a multiple of the static deflection (single support
    # alone doubles it)
    static = mg / (2 * sim.springs[0].K_fs[0, 0])
    print(f"\nsinking {-1e3 * tr.t[:, 2].min():.1f} mm = {-tr.t[:, 2].min() / static:.2f} x static")
    assert -tr.t[:, 2].min() < sinking * static


def test_walk_short_floor_touchdown_romeo(walk_short):
    """Romeo, noise-free forces: measured 0.21 mg at the first sample (the damping of a foot still
    descending at ~0.13 m/s, travelling at ~0.2 m/s), 0.43 mg peak over 0.3 s (0.57-0.66 mg when
    the plan drove the foot on ~2 cm into the floor), sinking 3.05 x static (2.69 x before: the
    peak is in single support, before a touch-down).  Margins ~15-20 %."""
    sim, rec = walk_short
    _check_touchdown(sim, rec, first_step=0.25, first_300ms=0.5, sinking=3.5)


@pytest.mark.slow
def test_walk_short_floor_touchdown_talos(walk_short_talos):
    """Talos: measured 0.25 mg at the first sample, 0.67 mg peak over 0.3 s (0.62-0.84 mg when the
    plan drove the foot on into the floor), sinking 2.81 x static (3.46 x before).  Margins ~15-20 %."""
    sim, rec = walk_short_talos
    _check_touchdown(sim, rec, first_step=0.3, first_300ms=0.8, sinking=3.3)


@pytest.mark.parametrize("which", ["romeo", pytest.param("talos", marks=pytest.mark.slow)])
def test_recorded_contacts_are_where_the_legs_put_them(which, request):
    """Self-consistency of the recording: at every sample, the contact placements the recording
    gives (the robot's belief) are the forward kinematics of its own pelvis pose and joint
    encoders, also while a foot that touched early brakes and levels."""
    sim, rec = request.getfixturevalue("walk_short" if which == "romeo" else "walk_short_talos")
    model = sim.robot.model
    data = model.createData()
    worst = 0.0
    for k in range(0, rec.n):
        q = np.concatenate([rec.base_pose[k], rec.joint_q[k]])
        pin.framesForwardKinematics(model, data, q)
        for i, fid in enumerate(sim.robot.contact_frame_ids):
            if rec.contact_active[k, i]:
                worst = max(worst, float(np.abs(data.oMf[fid].translation - rec.contact_p[k, i]).max()))
                worst = max(worst, float(np.abs(data.oMf[fid].rotation - rec.contact_R[k, i]).max()))
    assert worst < 1e-9
