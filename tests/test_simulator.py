"""The hand-written physics held against the pinocchio simulator (an independent path).

The simulator integrates pinocchio's multibody dynamics (CRBA/RNEA of the free-flyer rows) and
reads the IMU from pinocchio's frame kinematics; none of it calls flexforce.factors.physics.  If
an equation of the seed paper (or one of DESIGN.md's corrections) were wrong, the Newton-Euler
residual evaluated on the ground truth would not vanish.
"""

from __future__ import annotations

import numpy as np
import pytest

from flexforce.datasets.io.bagio import load_recording, save_recording
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
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
        if (ep["contact"] == rec.contact_names[i] and ep["start"] <= t + 1e-9
                and (ep["end"] is None or t < ep["end"] - 1e-9)):
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
    """Eq. (6)-(12) on the ground truth give the wrenches of the simulator's springs, anchored at
    the true footholds, wherever the foot is held still in the local frame at its recorded
    placement: not while a lifting foot unloads, nor while a landing foot that touched the floor
    early brakes and levels (its local placement moves: the law has no local contact velocity)."""
    sim, rec = busy
    tr = rec.truth
    checked = 0
    for k in range(rec.n):
        _, vel, _, planned = sim.motion.contact_targets(rec.time[k])
        for i in range(len(rec.contact_names)):
            if not rec.contact_active[k, i]:
                np.testing.assert_array_equal(tr.wrench[k, i], 0.0)
                continue
            if not planned[i] or np.any(vel[i] != 0.0):
                continue
            checked += 1
            wr = _model_wrench(rec, k, i, _params(sim.springs[i]))
            np.testing.assert_allclose(wr, tr.wrench[k, i], atol=1e-6 * np.abs(tr.wrench[k, i]).max())
    # the 0.42 s of braking and levelling of the right foot, which touches the floor early, are skipped
    assert checked > 0.85 * rec.contact_active.sum()


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
    k = changes[1]
    assert tr.wrench[k - 1, 1, 2] == 0.0  # touch-down: see test_touchdown_*
    # while in the air the contact's placement moves; the landing rest placement is where it landed:
    # the planned 5 cm, short of the travel left when the foot touched the floor early
    ep = rec.meta["contact_episodes"][-1]
    short = np.array(ep.get("local_off_plan", [0.0, 0.0, 0.0]))[:2]
    np.testing.assert_allclose(rec.contact_p[-1, 1][:2] - rec.contact_p[0, 1][:2], [0.05, 0.0] + short, atol=1e-9)


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


# ----------------------------------------------------------------------------------------------
# Touch-down and lift-off
# ----------------------------------------------------------------------------------------------

# Romeo shifts its weight over the left foot, the right foot lifts, moves 5 cm forward and lands.
ONE_STEP = {"name": "one-step", "robot": "romeo", "duration": 2.6,
            "base": [{"toward": "left_foot", "start": 0.05, "duration": 1.2}],
            "swing": [{"contact": "right_foot", "lift": 1.5, "land": 2.1, "displacement": [0.05, 0.0, 0.0],
                       "height": 0.02}]}
LIFT, LAND = 1.5, 2.1


@pytest.fixture(scope="module", params=["floor", "relaxed", "deflected"])
def one_step(request):
    sim = Simulator(Scenario.from_dict({**ONE_STEP, "touchdown": request.param}), noise=False)
    return request.param, sim, sim.run()


def _world_foot(sim, rec, k, i):
    """World position and linear velocity of contact ``i``'s frame at sample ``k``: the truth's
    flexibility applied to the local placement and velocity (pinocchio's frame kinematics)."""
    import pinocchio as pin

    local = sim.motion.sample(rec.time[k])
    model = sim.motion.model
    data = model.createData()
    pin.forwardKinematics(model, data, local.q, local.v)
    fid = sim.robot.contact_frame_ids[i]
    M = pin.updateFramePlacement(model, data, fid)
    v_l = pin.getFrameVelocity(model, data, fid, pin.LOCAL_WORLD_ALIGNED).linear
    tr = rec.truth
    p = tr.R[k] @ M.translation
    return p + tr.t[k], tr.R[k] @ v_l + np.cross(tr.w[k], p) + tr.v[k]


def test_touchdown_without_force_jump(one_step):
    """At the first contact sample the landing spring holds no more than the foot's motion since it
    touched: "floor" and "relaxed" start unloaded; "deflected" starts preloaded by the flexibility's
    deflection, K_fs (world - local placement)."""
    mode, sim, rec = one_step
    tr = rec.truth
    mg = rec.mass * rec.gravity
    ep = [e for e in rec.meta["contact_episodes"] if e["contact"] == "right_foot"][-1]
    off = int(np.flatnonzero(~rec.contact_active[:, 1])[0])
    k = off + int(np.flatnonzero(rec.contact_active[off:, 1])[0])  # first sample of the new episode
    spring = sim.springs[1]
    p_foot, v_foot = _world_foot(sim, rec, k, 1)
    rest_p = np.array(ep["world_p"])
    if mode == "deflected":
        # the whole preload appears at once: K_fs times the offset of the world foot from its belief
        s = p_foot - rec.contact_p[k, 1]
        assert np.linalg.norm(s) > 1e-3
        assert np.linalg.norm(tr.wrench[k, 1, :3] + spring.K_fs @ s) < 0.2 * np.linalg.norm(spring.K_fs @ s)
        assert np.abs(tr.wrench[k, 1, 2]) > 0.02 * mg  # measured 0.09 mg
        return
    if mode == "relaxed":
        # contact at the scheduled landing, where the foot is: the spring force is the damping alone
        assert ep["start"] == pytest.approx(LAND)
        np.testing.assert_allclose(p_foot, rest_p, atol=1e-12)
        np.testing.assert_allclose(tr.wrench[k, 1, :3], -spring.K_fd @ v_foot, atol=1e-9)
        return
    # floor: the foot touched the floor (z = 0) at most one sample before, flat, and has moved
    # since by at most its speed times one sample period
    assert ep["start"] <= rec.time[k] + 1e-12 and ep["start"] > rec.time[k] - rec.dt - 1e-12
    assert abs(rest_p[2]) < 1e-12 and abs(ep["above_floor"]) < 1e-12
    # level as the sole of the reference posture (itself level to 1e-7 rad)
    np.testing.assert_allclose(np.array(ep["world_R"]) @ sim.motion.placements0[1].rotation.T[:, 2],
                               [0.0, 0.0, 1.0], atol=1e-12)
    assert np.linalg.norm(p_foot - rest_p) < 0.5 * rec.dt  # 0.5 m/s: far above the foot's speed
    # The force is the spring's law from zero deflection at the touch: the damping of the foot's
    # landing speed (the foot hits the floor still descending) and the spring of what it moved since.
    spring_part = -spring.K_fs @ (p_foot - rest_p)
    np.testing.assert_allclose(tr.wrench[k, 1, :3], spring_part - spring.K_fd @ v_foot, atol=1e-6)
    assert np.linalg.norm(spring_part) < 0.1 * mg  # measured 0.0x mg: less than one sample's motion


def test_floor_lift_off_unloads_the_foot(one_step):
    """With ``touchdown = "floor"`` a lifting foot stays on the floor while its spring pushes, and
    leaves when it no longer does, or at the latest a quarter into its swing (torn off: the floor
    cannot hold it and a point contact has no friction limit).  Here the body rolls onto the
    lifting foot (statically the CoM over the other foot still leaves it ~0.3 mg through the
    springs): it unloads as it rises, from 165 N at the scheduled lift to 35 N (measured)."""
    mode, sim, rec = one_step
    if mode != "floor":
        pytest.skip("lift-off at the scheduled instant in the other modes")
    tr = rec.truth
    off = int(np.flatnonzero(~rec.contact_active[:, 1])[0])
    assert LIFT <= rec.time[off] <= LIFT + 0.25 * (LAND - LIFT) + rec.dt
    ep = [e for e in rec.meta["contact_episodes"] if e["contact"] == "right_foot"][0]
    at_lift = tr.wrench[int(round(LIFT / rec.dt)), 1, 2]
    assert ep["release_force"][2] < 0.5 * at_lift  # measured 0.21
    # the recording's contact flags are the truth's: the estimators see when the foot is down
    np.testing.assert_array_equal(rec.contact_active[:, 1], np.abs(tr.wrench[:, 1]).max(axis=1) > 0)


def test_simulator_imports_no_estimator_code():
    """The truth shares no code with what it tests: no import of flexforce.factors, smoother or
    compare in the simulator, its scenarios and hidden effects."""
    import ast
    from pathlib import Path

    import flexforce.datasets.sim.simulator as simulator

    folder = Path(simulator.__file__).parent
    for name in ("simulator.py", "scenario.py", "effects.py"):
        tree = ast.parse((folder / name).read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                modules = [node.module or ""]
            elif isinstance(node, ast.Import):
                modules = [a.name for a in node.names]
            else:
                continue
            for m in modules:
                assert not m.startswith(("flexforce.factors", "flexforce.smoother", "flexforce.compare")), (name, m)
