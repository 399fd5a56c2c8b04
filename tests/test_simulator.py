"""The hand-written physics held against the pinocchio simulator (an independent path).

The simulator integrates pinocchio's multibody dynamics (CRBA/RNEA of the free-flyer rows) and
reads the IMU from pinocchio's frame kinematics; none of it calls flexforce.factors.physics.  If
an equation of the seed paper (or one of DESIGN.md's corrections) were wrong, the Newton-Euler
residual evaluated on the ground truth would not vanish.
"""

from __future__ import annotations

import numpy as np
import pytest

from flexforce.datasets.bagio import load_recording, save_recording
from flexforce.datasets.scenario import Scenario
from flexforce.datasets.simulator import Simulator
from flexforce.factors import physics as ph
from flexforce.factors import so3

ARM = {"romeo": "LShoulderPitch", "talos": "arm_left_1_joint"}

# A short scenario exercising every input: pelvis motion (CoM moves, legs follow), an arm swing
# (angular momentum, inertia rate), a push on a hand (external wrench), a foot lifting and
# landing elsewhere (contacts vanish and appear).
BUSY = {
    "name": "busy",
    "duration": 2.6,
    "base": [
        {"toward": "left_foot", "fraction": 1.0, "start": 0.05, "duration": 0.9},
        {"kind": "sine", "start": 0.2, "duration": 2.2, "amplitude": [0.01, 0.0, 0.005], "frequency": 1.5},
    ],
    "joint": [{"joint": ARM, "kind": "sine", "start": 0.1, "duration": 2.4, "amplitude": 0.4, "frequency": 1.0}],
    "swing": [{"contact": "right_foot", "lift": 1.1, "land": 1.6, "displacement": [0.05, 0.0, 0.0],
               "height": 0.02}],
    "effects": [{"type": "external-wrench", "link": "@link:0", "force": [15.0, -10.0, 5.0],
                 "torque": [0.0, 0.0, 2.0], "start": 0.3, "duration": 0.2}],
}


def _params(spring) -> ph.ContactParams:
    """The model's parameters for one of the simulator's springs (same matrices, same stiffening)."""
    return ph.ContactParams(spring.K_fs, spring.K_fd, spring.K_ts, spring.K_td, spring.beta_f, spring.beta_t)


def _foothold(rec, k: int, i: int):
    """World rest placement (p, R) of contact ``i``'s spring at sample ``k``, from the recording's
    contact episodes (the simulator's truth of each touch-down)."""
    t = rec.time[k]
    for ep in rec.meta["contact_episodes"]:
        if ep["contact"] == rec.contact_names[i] and ep["start"] <= t + 1e-9 and (ep["end"] is None or t < ep["end"] - 1e-9):
            return np.array(ep["world_p"]), np.array(ep["world_R"])
    raise AssertionError(f"no episode of {rec.contact_names[i]} at {t} s")


def _model_wrench(rec, k: int, i: int, params) -> np.ndarray:
    """Eq. (6)-(12) at the truth of sample ``k``, for a spring anchored at the true foothold.

    The model anchors a contact at its local placement p_l (rest = p_l in the world).  A foothold
    (p_r, R_r) is the placement of p_l under the flexibility (R_f, t_f) the robot had when it
    landed, so the model's law applies to the flexibility relative to it: R' = R R_f^T and
    t' = t - R' t_f with the contact at p_r, R_r (same displacement, velocity and lever arm).
    """
    tr = rec.truth
    p_r, R_r = _foothold(rec, k, i)
    R_f = R_r @ rec.contact_R[k, i].T
    t_f = p_r - R_f @ rec.contact_p[k, i]
    R1 = tr.R[k] @ R_f.T
    off = R1 @ t_f
    return ph.contact_wrench(R1, tr.t[k] - off, tr.w[k], tr.v[k] - np.cross(tr.w[k], off), p_r, R_r, params)


@pytest.fixture(scope="module", params=["romeo", "talos"])
def busy(request):
    sc = Scenario.from_dict({**BUSY, "robot": request.param})
    sim = Simulator(sc, noise=False)
    return sim, sim.run()


def test_newton_euler_holds_on_ground_truth(busy):
    """Eq. (16), (23) with corrections 2-4 vanish on pinocchio's trajectory (integration-error level)."""
    sim, rec = busy
    tr = rec.truth
    m, g = rec.mass, rec.gravity
    h = rec.com[0, 2]
    res = np.array([ph.newton_euler_residual(tr.R[k], tr.t[k], tr.w[k], tr.v[k], tr.dw[k], tr.a[k],
                                             tr.total_wrench[k] + tr.external_wrench[k], rec.inputs(k), g)
                    for k in range(rec.n)])
    assert np.abs(res[:, :3]).max() < 1e-4 * m * g * 1e-3
    assert np.abs(res[:, 3:]).max() < 1e-4 * m * g * h * 1e-3
    # Without the hidden push the residual is the push: the residual measures what is missing.
    res_nopush = res + tr.external_wrench
    k = int(np.argmax(np.linalg.norm(tr.external_wrench[:, :3], axis=1)))
    np.testing.assert_allclose(res_nopush[k], tr.external_wrench[k], rtol=1e-6, atol=1e-6)


def test_forward_dynamics_reproduces_ground_truth_acceleration(busy):
    """Eq. (24), (25) (correction 4) give pinocchio's flexibility acceleration."""
    sim, rec = busy
    tr = rec.truth
    for k in range(0, rec.n, 7):
        acc = ph.forward_dynamics(tr.R[k], tr.t[k], tr.w[k], tr.v[k], tr.total_wrench[k] + tr.external_wrench[k],
                                  rec.inputs(k), rec.gravity)
        np.testing.assert_allclose(acc[:3], tr.dw[k], atol=1e-9)
        np.testing.assert_allclose(acc[3:], tr.a[k], atol=1e-9)


def test_imu_model_reproduces_noise_free_readings(busy):
    """Eq. (26)-(28) on the ground truth give pinocchio's gyro and accelerometer readings."""
    sim, rec = busy
    tr = rec.truth
    for k in range(rec.n):
        y = ph.imu_readings(tr.R[k], tr.t[k], tr.w[k], tr.v[k], tr.dw[k], tr.a[k], rec.imu(k), rec.gravity)
        np.testing.assert_allclose(y[:3], rec.gyro[k], atol=1e-12)
        np.testing.assert_allclose(y[3:], rec.accel[k], atol=1e-10)


def test_contact_law_reproduces_ground_truth_wrenches(busy):
    """Eq. (6)-(12) on the ground truth give the wrenches of the simulator's springs."""
    sim, rec = busy
    tr = rec.truth
    for k in range(rec.n):
        for i in range(len(rec.contact_names)):
            if not rec.contact_active[k, i]:
                np.testing.assert_array_equal(tr.wrench[k, i], 0.0)
                continue
            wr = _model_wrench(rec, k, i, _params(sim.springs[i]))
            np.testing.assert_allclose(wr, tr.wrench[k, i], atol=1e-6 * np.abs(tr.wrench[k, i]).max())


def test_step_changes_contacts_without_jump_in_flexibility(busy):
    sim, rec = busy
    tr = rec.truth
    active = rec.contact_active
    changes = np.flatnonzero(np.any(active[1:] != active[:-1], axis=1)) + 1
    assert len(changes) == 2  # lift-off and touch-down of the right foot
    assert not active[changes[0], 1] and active[changes[1], 1]
    dt = rec.dt
    # The pose moves by what the velocity integrates to, and the velocity by what the acceleration
    # integrates to, across the switches as elsewhere: no jump.
    for k in range(1, rec.n):
        dv = tr.v[k] - tr.v[k - 1]
        bound = dt * np.maximum(np.abs(tr.a[k]), np.abs(tr.a[k - 1])) * 1.5 + 1e-9
        assert np.all(np.abs(dv) <= bound + 0.5 * dt * dt * 50.0), k
        dtr = tr.t[k] - tr.t[k - 1] - 0.5 * dt * (tr.v[k] + tr.v[k - 1])
        assert np.abs(dtr).max() < dt * dt * np.abs(tr.a[k - 1:k + 1]).max() + 1e-9
    # The landing spring starts unloaded where the foot is (touchdown = "relaxed"): at the first
    # contact sample its force is the damping of the foot's velocity alone (see test_touchdown_*).
    k = changes[1]
    assert tr.wrench[k - 1, 1, 2] == 0.0
    v_foot = np.cross(tr.w[k], tr.R[k] @ rec.contact_p[k, 1]) + tr.v[k]  # the foot lands at rest in the local frame
    np.testing.assert_allclose(tr.wrench[k, 1, :3], -sim.springs[1].K_fd @ v_foot, atol=1e-9)
    # while in the air the contact's placement moves; the landing rest placement is where it landed
    np.testing.assert_allclose(rec.contact_p[-1, 1][:2] - rec.contact_p[0, 1][:2], [0.05, 0.0], atol=1e-9)


def test_statics_standing_still():
    """Total vertical force m g, sinking m g / sum k_fs (both feet, isotropic springs)."""
    sc = Scenario.from_dict({"name": "still", "robot": "romeo", "duration": 0.3})
    sim = Simulator(sc, noise=False)
    rec = sim.run()
    tr = rec.truth
    m, g = rec.mass, rec.gravity
    k_fs = sum(p.K_fs[0, 0] for p in sim.springs)
    np.testing.assert_allclose(tr.total_wrench[:, 2], m * g, rtol=1e-9)
    np.testing.assert_allclose(tr.total_wrench[:, :2], 0.0, atol=1e-9)
    np.testing.assert_allclose(tr.t[:, 2], -m * g / k_fs, rtol=1e-6)
    assert np.abs(tr.v).max() < 1e-9 and np.abs(tr.a).max() < 1e-9
    # The CoP lies under the world CoM (statics), here between the feet.
    com_w = np.einsum("nij,nj->ni", tr.R, rec.com) + tr.t
    np.testing.assert_allclose(tr.cop[:, :2], com_w[:, :2], atol=1e-9)


def test_hidden_effects_reach_the_truth():
    eff = [
        {"type": "gyro-bias", "value": [0.0, 0.01, 0.0]},
        {"type": "accel-bias", "value": [0.05, 0.0, 0.0]},
        {"type": "stiffness", "stiffness": 0.5},
        {"type": "com-offset", "offset": [0.02, 0.0, 0.0]},
    ]
    base = {"name": "still", "robot": "romeo", "duration": 0.2}
    nominal = Simulator(Scenario.from_dict(base), noise=False).run()
    hidden = Simulator(Scenario.from_dict({**base, "effects": eff}), noise=False).run()
    # Inputs come from the nominal mass model: identical.
    np.testing.assert_array_equal(nominal.com, hidden.com)
    # Softer springs: twice the sinking.
    np.testing.assert_allclose(hidden.truth.t[0, 2], 2 * nominal.truth.t[0, 2], rtol=1e-3)
    # The CoM offset moves the CoP forward by about 2 cm (plus the softer tilt).
    assert hidden.truth.cop[0, 0] - nominal.truth.cop[0, 0] > 0.02
    np.testing.assert_allclose(hidden.truth.gyro_bias[0], [0.0, 0.01, 0.0])
    np.testing.assert_allclose(hidden.truth.accel_bias[0], [0.05, 0.0, 0.0])


def test_anisotropic_and_cubic_springs_match_the_contact_law():
    eff = [{"type": "anisotropic-stiffness", "k_fs": [0.5, 2.0, 1.0], "k_ts": [1.5, 0.7, 1.0]},
           {"type": "nonlinear-stiffness", "beta_f": 3000.0, "beta_t": 20.0},
           {"type": "external-wrench", "link": "@base", "force": [30.0, 20.0, 0.0], "start": 0.05, "duration": 0.2}]
    sc = Scenario.from_dict({"name": "aniso", "robot": "romeo", "duration": 0.4, "effects": eff})
    sim = Simulator(sc, noise=False)
    rec = sim.run()
    tr = rec.truth
    for k in range(0, rec.n, 5):
        for i in range(2):
            wr = ph.contact_wrench(tr.R[k], tr.t[k], tr.w[k], tr.v[k], rec.contact_p[k, i], rec.contact_R[k, i],
                                   _params(sim.springs[i]))
            np.testing.assert_allclose(wr, tr.wrench[k, i], atol=1e-6 * np.abs(tr.wrench[k, i]).max())
    nominal = [ph.contact_wrench(tr.R[k], tr.t[k], tr.w[k], tr.v[k], rec.contact_p[k, 0], rec.contact_R[k, 0],
                                 sim.robot.contact_params()[0]) for k in (rec.n - 1,)]
    assert np.abs(nominal[0] - tr.wrench[-1, 0]).max() > 1.0


def test_noise_statistics_and_seed():
    sc = {"name": "still", "robot": "romeo", "duration": 1.0, "ambient": False}
    clean = Simulator(Scenario.from_dict(sc), noise=False).run()
    noisy = Simulator(Scenario.from_dict({**sc, "seed": 3}), noise=True).run()
    again = Simulator(Scenario.from_dict({**sc, "seed": 3}), noise=True).run()
    np.testing.assert_array_equal(noisy.gyro, again.gyro)
    cfg = Simulator(Scenario.from_dict(sc)).imu_noise
    err = noisy.gyro - clean.gyro - noisy.truth.gyro_bias
    assert abs(err.std() / cfg.gyro_sigma(200.0) - 1.0) < 0.1
    err = noisy.accel - clean.accel - noisy.truth.accel_bias
    assert abs(err.std() / cfg.accel_sigma(200.0) - 1.0) < 0.1


def test_simulated_recording_survives_bag_round_trip(tmp_path, busy):
    sim, rec = busy
    path = save_recording(rec, tmp_path / "rec")
    back = load_recording(path)
    np.testing.assert_array_equal(back.t_ns, rec.t_ns)
    for name in ("com", "com_vel", "com_acc", "inertia", "inertia_dot", "sigma", "sigma_dot", "imu_R", "imu_p",
                 "imu_v", "imu_a", "imu_w", "contact_active", "contact_p", "contact_R", "gyro", "accel",
                 "joint_q", "joint_v", "ft"):
        np.testing.assert_array_equal(getattr(back, name), getattr(rec, name), err_msg=name)
    for name in ("t", "w", "v", "dw", "a", "wrench", "external_wrench", "cop"):
        np.testing.assert_array_equal(getattr(back.truth, name), getattr(rec.truth, name), err_msg=name)
    np.testing.assert_allclose(back.truth.R, rec.truth.R, atol=1e-12)
    assert back.contact_names == rec.contact_names and back.mass == rec.mass
    assert back.meta == rec.meta


def test_flexibility_stays_small_and_rotation_valid(busy):
    sim, rec = busy
    tr = rec.truth
    assert np.abs(tr.t).max() < 0.05
    assert max(np.linalg.norm(so3.log(R)) for R in tr.R) < 0.2
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", tr.R, tr.R), np.tile(np.eye(3), (rec.n, 1, 1)), atol=1e-12)
