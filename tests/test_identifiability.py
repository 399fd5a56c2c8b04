"""The diagnosis's own consistency: plausibility of estimates, identifiability before any refit,
failures said in the recording's terms, and progress messages.

Fast tests work on hand-made reports and stubs; two run a diagnosis on the 2.5 s gyro-bias stand
(nominal fit about 1 s, each refit a few seconds); the identifiability of the confusion benchmark's
sway (3 s, Romeo) is measured in the slow test (docs/diagnostics.md, "Identifiability").
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from flexforce.compare.diagnostics.run import Candidate, _failure, diagnose, finding, progress_caller
from flexforce.errors import EstimatorError
from flexforce.factors.effects import EFFECTS, make_effect
from flexforce.smoother.screening import CandidateInformation, Identifiability, PairCorrelation


def _problem(mass=40.0, com=(0.02, 0.0, 0.6), n=300):
    """What the plausibility checks read of a problem: mass, gravity, CoM, inertia, springs,
    contacts (``n`` samples of 10 ms, both feet in force, 0.2 m apart across x)."""
    return SimpleNamespace(rec=SimpleNamespace(mass=mass), g=9.81, dt=0.01, com=np.tile(com, (n, 1)),
                           com_acc=np.zeros((n, 3)), inertia=np.tile(np.eye(3) * 20.0, (n, 1, 1)),
                           K_fs=np.array([np.eye(3) * 1e5, np.eye(3) * 1e5]),
                           K_fd=np.array([np.eye(3) * 283.0, np.eye(3) * 283.0]),
                           K_ts=np.array([np.eye(3) * 450.0, np.eye(3) * 450.0]),
                           K_td=np.array([np.eye(3) * 5.0, np.eye(3) * 5.0]),
                           iso=np.array([False, False]),
                           contact_p=np.tile([[0.0, 0.1, 0.0], [0.0, -0.1, 0.0]], (n, 1, 1)),
                           contact_R=np.tile(np.eye(3), (n, 2, 1, 1)),
                           active=np.ones((n, 2), dtype=bool))


# The springs of _problem against gravity: m g h = 40 * 9.81 * 0.6 = 235 N m/rad; about x (roll)
# 2 * 450 + 2 * 1e5 * 0.1^2 = 2900 N m/rad, about y (pitch) 900 N m/rad: a scale s below 0.26
# leaves the pitch below m g h, and a tilt then grows at lambda = -0.25 + sqrt(0.0625 + (235 -
# 900 s) / 20) per second (I = 20 kg m^2, tilt damping 10 N m s/rad) over the 3 s: s = 0.2 grows it
# e^4.2 times (beyond e^3), s = 0.25 e^1.4 times.  Vertical damping ratio 2 * 283 / (2 sqrt(2e5 *
# 40)) = 0.100 (a damping scale above 10 is beyond critical).
@pytest.mark.parametrize("name,value,bad", [
    ("stiffness", [0.05, 1.0], True), ("stiffness", [0.7, 1.3], False), ("stiffness", [1.0, 6.0], False),
    ("stiffness", [1.0, 12.0], True), ("stiffness", [0.25, 1.0], False), ("stiffness", [0.2, 1.0], True),
    ("stiffness", [20.0, 1.0], False),
    ("anisotropic-stiffness", [1.0, 1.0, 0.7, 0.7, 1.3, 1.0], False),
    ("anisotropic-stiffness", [1.0, 1.0, 0.1, 1.0, 1.0, 1.0], False),
    ("anisotropic-stiffness", [1.0, 1.0, 0.05, 0.05, 1.0, 1.0], True),
    ("anisotropic-stiffness", [1.0, 1.0, 1.0, 1.0, 0.2, 1.0], True),
    ("anisotropic-stiffness", [1.0, 1.0, 1.0, 1.0, 1.0, 0.01], False),
    ("accel-bias", [0.08, -0.05, 0.0], False), ("accel-bias", [0.0, 0.45, 0.0], True),
    ("gyro-bias", [0.0, 0.011, 0.0], False), ("gyro-bias", [0.2, 0.0, 0.0], True),
    ("com-offset", [0.02, 0.0], False), ("com-offset", [0.3, 0.0], True),
    # translational: the recorded compression 40 * 9.81 / 2 / 1e5 = 1.96 mm; a softening of -1e7
    # leaves 1 - 3e7 * 1.96e-3^2 = -114 times the linear stiffness there; hardening: no bound
    ("nonlinear-stiffness", [4000.0, 0.0], False), ("nonlinear-stiffness", [-1e7, 0.0], True),
    ("nonlinear-stiffness", [-5e4, 0.0], False), ("nonlinear-stiffness", [1e9, 0.0], False),
    # rotational: the weight's moment about the feet 40 * 9.81 * 0.02 / 2 / 450 = 8.7 mrad per foot
    ("nonlinear-stiffness", [0.0, 400.0], False), ("nonlinear-stiffness", [0.0, 1000.0], False),
    ("nonlinear-stiffness", [0.0, -1000.0], False), ("nonlinear-stiffness", [0.0, -1e4], True),
])
def test_each_effect_says_when_its_estimate_is_implausible(name, value, bad):
    eff = make_effect(name)
    reason = eff.plausible({"value": value}, _problem())
    assert (reason is not None) == bad, reason
    if bad:
        assert name.split("-")[0] in reason or eff.what in reason or "stiff" in reason, reason


@pytest.mark.filterwarnings("ignore:stiffness.k_ts = .* is not above the gravity toppling stiffness")
def test_contact_scales_are_judged_by_toppling_and_damping_not_by_a_multiplier():
    from flexforce.datasets.robot import Stiffness as RobotStiffness
    from flexforce.datasets.robot import check_toppling
    from flexforce.errors import ConfigError
    from flexforce.factors.effects.base import contact_physics

    prob = _problem()
    phys = contact_physics(prob)
    assert phys.tilt_margin == pytest.approx(900.0 / (40 * 9.81 * 0.6)) and phys.axis == "y (pitch)"
    assert phys.damping_ratio == pytest.approx(2 * 283.0 / (2 * np.sqrt(2e5 * 40.0)), rel=1e-9)
    # the independent path: the configuration's toppling check on the same stance, springs scaled
    # just above and just below the margin's reciprocal
    for factor, topples in ((1.02, False), (0.98, True)):
        scale = factor / phys.tilt_margin
        springs = RobotStiffness(k_fs=1e5 * scale, k_fd=283.0, k_ts=450.0 * scale, k_td=5.0)
        if topples:
            with pytest.raises(ConfigError, match="falls over its springs"):
                check_toppling(springs, 40.0, np.array([0.02, 0.0, 0.6]), prob.contact_p[0], prob.contact_R[0])
        else:
            check_toppling(springs, 40.0, np.array([0.02, 0.0, 0.6]), prob.contact_p[0], prob.contact_R[0])
        below = contact_physics(prob, fs=(scale,) * 3, ts=(scale,) * 3)
        assert (below.tilt_margin < 1.0) == topples
        # just below: a tilt grows e^0.4 times over the 3 s (rate 0.13 /s), which a stance survives
        assert (below.fall_growth > 0.0) == topples and below.fall_growth < 1.0
        assert make_effect("stiffness").plausible({"value": [scale, 1.0]}, prob) is None
    # the growth against its closed form: s = 0.2, lambda = -0.25 + sqrt(0.0625 + (235.4 - 180) / 20)
    rate = -0.25 + np.sqrt(0.0625 + (40 * 9.81 * 0.6 - 900.0 * 0.2) / 20.0)
    assert contact_physics(prob, fs=(0.2,) * 3, ts=(0.2,) * 3).fall_growth == pytest.approx(rate * 3.0, rel=1e-6)
    assert "fall over its springs" in make_effect("stiffness").plausible({"value": [0.2, 1.0]}, prob)
    verdict = make_effect("stiffness").plausible({"value": [1.0, 12.0]}, prob)
    assert "damping ratio" in verdict and "beyond critical" in verdict


def test_sensor_specification_and_weight_bounds():
    # the specification is the effect's own parameter (a robot's IMU data sheet)
    assert make_effect("accel-bias").plausible({"value": [0.4, 0, 0]}) is not None
    assert make_effect("accel-bias", max_bias=0.5).plausible({"value": [0.4, 0, 0]}) is None
    w = make_effect("external-wrench")
    heavy = {"windows": [{"peak_norm": 500.0}]}  # 40 kg: weight 392 N
    assert "exceeds the robot's weight" in w.plausible(heavy, _problem())
    assert w.plausible({"windows": [{"peak_norm": 40.0}]}, _problem()) is None


def test_every_built_in_effect_names_what_excites_it():
    for name in EFFECTS:
        eff = make_effect(name)
        assert len(eff.excites) == eff.dim and all(eff.excites), name
        assert eff.hint, name


def _cand(**kw):
    base = dict(effect="gyro-bias", base=(), round=1, score=20.0, lr=45.0, effective_dof=3.0, p_value=1e-9,
                significant=True)
    base.update(kw)
    return Candidate(**base)


def test_no_row_is_both_significant_and_consistent_with_zero():
    eff = make_effect("gyro-bias")
    rep = {"summary": "gyro bias: consistent with 0 (gyro bias x = 0.002 ± 0.001 rad/s; gyro bias y = 0.002 ± 0.001 "
                      "rad/s)"}
    c = _cand(summary=rep["summary"])
    text = finding(c, rep, eff)
    assert "consistent with" not in text and "jointly significant" in text
    assert "evidence 2ΔE = 45.0" in text and "acts throughout (a constant)" in text
    # one unknown: no "joint" wording (a time offset at 2.97 sigma, its evidence test significant)
    rep = {"summary": "IMU time offset: consistent with 0 (IMU time offset tau = -0.0101 ± 0.0034 s)"}
    c = _cand(effect="time-offset", summary=rep["summary"], effective_dof=1.0)
    text = finding(c, rep, make_effect("time-offset"))
    assert "consistent with" not in text and "jointly" not in text and "within 3σ of 0" in text
    # not significant: never presented as found
    c = _cand(significant=False, score=-5.0, summary="gyro bias y = 0.004 ± 0.001 rad/s")
    assert finding(c, {}, eff).startswith("not significant")
    c = _cand(significant=False, implausible="gyro bias x = 0.2 rad/s is beyond the sensor's specification",
              summary="gyro bias x = 0.2 ± 0.001 rad/s")
    assert c.status == "implausible" and finding(c, {}, eff).startswith("implausible: gyro bias x = 0.2")
    # a wrench: when it acts
    w = make_effect("external-wrench")
    rep = {"summary": "external force ≈ 40 N along x", "windows": [{"start_s": 1.5, "end_s": 1.9}]}
    assert "acts 1.50-1.90 s" in finding(_cand(effect="external-wrench", summary=rep["summary"]), rep, w)


def test_a_failed_fit_is_said_in_the_recordings_terms():
    info = CandidateInformation("anisotropic-stiffness", 6, (), "constant", 0.02, "k_ts z", 5, 9.8,
                                "a torque about z (yaw)", 700.0)
    ident = Identifiability({"anisotropic-stiffness": info}, [])
    reason, detail = _failure("anisotropic-stiffness", EstimatorError("information not positive definite"), ident)
    assert reason == "the recording does not excite anisotropic-stiffness k_ts z: a torque about z (yaw)"
    assert "not positive definite" in detail
    pair = PairCorrelation("accel-bias", "com-offset", [0.999], "x", "x", "tilt the robot")
    ident = Identifiability({}, [pair])
    reason, _ = _failure("com-offset", EstimatorError("not positive definite"), ident)
    assert "does not tell its x from accel-bias" in reason and "tilt the robot" in reason
    reason, _ = _failure("com-offset", EstimatorError("the information is not positive definite"), None)
    assert "does not determine it" in reason and "positive definite" not in reason
    reason, _ = _failure("mine", ValueError("boom"))
    assert reason == "the effect 'mine' raised ValueError: boom"


def test_progress_keeps_the_two_argument_form():
    seen = []
    progress_caller(lambda label, f: seen.append((label, f)))("nominal", 0.5, "fitting")
    progress_caller(lambda label, f, message=None: seen.append((label, f, message)))("nominal", 1.0, "done")
    progress_caller(lambda *a: seen.append(a))("screening", 1.0, "gyro-bias")

    def kw(label, fraction, *, message=None):
        seen.append((label, fraction, message))

    progress_caller(kw)("ekf", 1.0, "EKF")
    assert seen == [("nominal", 0.5), ("nominal", 1.0, "done"), ("screening", 1.0, "gyro-bias"),
                    ("ekf", 1.0, "EKF")]
    assert progress_caller(None) is None


class Raising:
    """A user's effect whose residual raises (a bug in a plugin)."""

    name = "raising"
    dim = 1
    labels = ("r [-]",)
    constant = True

    def prior(self, problem):
        return np.zeros(1), np.ones(1)

    def random_walk_sigma(self, problem):
        return np.full(1, 1e-8)

    def residual_terms(self, family, problem, steps, R, q, W, e):
        raise ValueError("a bug in the plugin")

    def report(self, values, cov):
        return {}


def test_diagnose_names_candidates_per_stage_and_survives_a_raising_plugin():
    from test_diagnose import GYRO, simulate

    rec = simulate([GYRO])
    messages = []
    d = diagnose(rec, candidates=["gyro-bias", "accel-bias", Raising], ekf=False, calibrated=False,
                 progress=lambda label, f, message=None: message and messages.append((label, message)))
    labels = [m[0] for m in messages]
    # one line per stage and per candidate, naming it, with the elapsed time
    assert labels[0] == "nominal" and "identifiability" in labels and "ekf" not in labels
    screening = [m for lab, m in messages if lab == "screening"]
    assert [m.split(":")[0] for m in screening] == ["gyro-bias", "accel-bias", "raising"]
    assert all(m.endswith(" s]") for m in screening)
    assert any(lab == "+ gyro-bias" and "score" in m for lab, m in messages)
    # the raising plugin: one line, the others ranked
    bad = next(c for c in d.ranking if c.effect == "raising")
    assert bad.status == "cannot be fitted"
    assert bad.error == "the effect 'raising' raised ValueError: a bug in the plugin"
    assert d.selected == ["gyro-bias"]
    first = d.ranking[0]
    assert first.status == "significant" and "acts throughout" in first.finding and "evidence" in first.finding
    for c in d.ranking:  # no row both significant and "consistent with" its null
        assert not (c.significant and "consistent with" in c.finding), c.finding
    ident = d.identifiability
    assert ident is not None and set(ident.candidates) == {"gyro-bias", "accel-bias"}
    assert "raising" in d.ranking_table() and "identifiability at the nominal fit" in d.ranking_table()
    js = d.to_json()
    assert js["identifiability"]["pairs"][0]["a"] in {"gyro-bias", "accel-bias"}
    # gyro and accelerometer biases are separate sensors: uncorrelated (measured 0.005 on the sway)
    assert js["identifiability"]["pairs"][0]["correlation"] < 0.1


@pytest.mark.slow
def test_identifiability_on_the_benchmark_sway_matches_the_rankings_confusions():
    """The pairs the confusion benchmark's ranking confuses are those the table calls inseparable."""
    from flexforce.datasets.sim.scenario import Scenario
    from flexforce.datasets.sim.simulator import Simulator
    from flexforce.factors.model import ModelConfig
    from flexforce.smoother import NoiseRule, Problem, fit
    from flexforce.smoother.screening import INSEPARABLE, identifiability

    sc = Scenario.load("sway")
    sc.duration, sc.seed = 3.0, 0
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    sc.effects = []
    rec = Simulator(sc).run()
    model = ModelConfig.from_recording(rec)
    _, st = fit(rec, model)
    prob = Problem.build(rec, model, NoiseRule())
    ident = identifiability(prob, st.trajectory, [make_effect(n) for n in EFFECTS], n_residuals=st.n_residuals)
    # measured 0.9987 (accel-bias x / com-offset x) and 0.990 (k_ts y / com-offset x): the
    # benchmark's two confusions; the label's threshold is the margin
    for a, b in (("accel-bias", "com-offset"), ("anisotropic-stiffness", "com-offset")):
        p = ident.pair(a, b)
        assert p is not None and p.inseparable and p.largest > INSEPARABLE, (a, b, p)
    assert ident.pair("anisotropic-stiffness", "com-offset").direction_a == "k_ts y"
    # the gyro bias is told from every constant effect: measured at most 0.12 (damping scale); margin 0.1
    # (the footholds of a recording without a touch-down are constants here)
    windowed = {k for k, c in ident.candidates.items() if c.kind == "windowed"}
    assert windowed == {"external-wrench"}, windowed
    for p in ident.pairs:
        if "gyro-bias" in (p.a, p.b) and not windowed & {p.a, p.b}:
            assert p.largest < 0.12 + 0.1, p.text()
    # standing, a height and tilt per foot is what a bias, a turned IMU or a CoM offset does: the
    # footholds cannot be told from them (measured 0.999, 0.998, 0.996 on a CoM step)
    for other in ("accel-bias", "com-offset", "imu-mounting"):
        p = ident.pair("foothold", other)
        assert p is not None and p.inseparable, (other, p)
    # measured: a prior-sized anisotropy along the contacts' fore-aft shear gains 0.055 in 2 ln L
    # (a sideways sway barely shears them fore-aft): partly seen; the biases are seen (> 1e4)
    assert ident.candidates["anisotropic-stiffness"].status == "partly seen"
    assert ident.candidates["gyro-bias"].seen and ident.candidates["accel-bias"].seen


def test_the_robot_configuration_bounds_the_imu_biases_and_the_mass():
    import dataclasses

    from flexforce.compare.diagnostics.candidates import bound
    from flexforce.datasets.robot import RobotConfig
    from flexforce.errors import ConfigError
    from flexforce.factors.model import ModelConfig

    robot = RobotConfig.load("romeo")
    assert (robot.imu_noise.gyro_bias_max, robot.imu_noise.accel_bias_max, robot.mass_factor) == (0.05, 0.3, 2.0)
    weighed = dataclasses.replace(robot, mass_factor=1.1,
                                  imu_noise=dataclasses.replace(robot.imu_noise, accel_bias_max=0.5))
    rec = SimpleNamespace(dt=0.005, gravity=9.81, contact_names=("left_foot", "right_foot"), robot="romeo")
    model = ModelConfig.from_recording(rec, robot=weighed)
    assert (model.accel_bias_max, model.gyro_bias_max, model.mass_factor) == (0.5, 0.05, 1.1)
    accel = bound(lambda: make_effect("accel-bias"), rec, model)()
    assert accel.plausible({"value": [0.4, 0.0, 0.0]}) is None  # within the data sheet's 0.5
    assert "0.5" in accel.plausible({"value": [0.6, 0.0, 0.0]})
    # a bound given to the effect itself wins over the configuration's
    assert bound(lambda: make_effect("accel-bias", max_bias=0.2), rec, model)().plausible(
        {"value": [0.3, 0.0, 0.0]}) is not None
    mass = bound(lambda: make_effect("mass-scale"), rec, model)()
    assert mass.plausible({"value": [1.08]}) is None and "outside the plausible" in mass.plausible({"value": [1.15]})
    assert make_effect("mass-scale").plausible({"value": [1.15]}) is None  # unbound: the default factor 2
    for bad in ({"mass_factor": 0.9}, {"mass_factor": "2"}):
        raw = {"name": "x", "urdf": "u.urdf", "imu_frame": "imu", "contacts": [{"name": "a", "frame": "f"}],
               "stiffness": {"k_fs": 1.0, "k_fd": 1.0, "k_ts": 1.0, "k_td": 1.0}, **bad}
        with pytest.raises(ConfigError, match="mass_factor"):
            RobotConfig.from_dict(raw)
    with pytest.raises(ConfigError, match="accel_bias_max"):
        dataclasses.replace(robot.imu_noise, accel_bias_max=-1.0)
