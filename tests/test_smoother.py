"""Tests of the smoothers: accuracy and consistency against the simulator's ground truth, the batch
solver against gtsam's own Levenberg-Marquardt on the same factors, fixed-lag against batch, F/T
fusion, the effect protocol, and the Estimate they return.

The simulator's slow IMU bias random walk is switched off (``imu_noise`` override): the nominal
model has no bias state, so with it the NEES measures the missing effect rather than the
smoother (the diagnostics' gyro-bias/accel-bias effects are what models it).
"""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from baseline import lower, upper
from scipy.stats import chi2

from flexforce.datasets.estimate import Estimate
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import ConfigError
from flexforce.factors import so3
from flexforce.factors.model import ModelConfig
from flexforce.smoother import Effect, Problem, run_batch, run_fixed_lag
from flexforce.smoother.batch import optimize
from flexforce.smoother.graph import GraphBuilder

# Margins.  The recordings are seeded: each error below is one deterministic number, and a margin
# only absorbs floating-point reordering and where the solver's stopping rule lands; the
# smoothers stop at a relative cost decrease of 1e-7, which moves an RMSE by well under 5 %.
# SOLVER: 10 % on an error of the batch or fixed-lag smoother.
SOLVER = 0.10


@pytest.fixture(scope="module")
def rec():
    sc = Scenario.load("push-pitch")
    sc.duration = 3.0
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    return Simulator(sc).run()


@pytest.fixture(scope="module")
def model(rec):
    return ModelConfig.from_recording(rec)


@pytest.fixture(scope="module")
def batch(rec, model):
    return run_batch(rec, model)


def errors(est, rec, skip: float = 0.0):
    """RMSE of total force (N), CoP (m) and tilt (rad), leaving out the first ``skip`` seconds."""
    tr = rec.truth
    k0 = int(round(skip / rec.dt))
    force = np.sqrt(np.mean(np.sum((est.total_wrench[k0:, :3] - tr.total_wrench[k0:, :3]) ** 2, axis=1)))
    cop = np.sqrt(np.mean(np.sum((est.cop[k0:, :2] - tr.cop[k0:, :2]) ** 2, axis=1)))
    theta = np.array([so3.log(est.R[k] @ tr.R[k].T) for k in range(k0, rec.n)])
    return force, cop, np.sqrt(np.mean(np.sum(theta**2, axis=1)))


def away_from_pushes(rec, margin: float = 1.0):
    """Steps at least ``margin`` s before or after any hidden external wrench (where the model is
    right; a smoother looks ahead, so the margin is on both sides)."""
    ext = np.abs(rec.truth.external_wrench).max(axis=1) > 0
    m = int(round(margin / rec.dt))
    return np.convolve(ext.astype(float), np.ones(2 * m + 1), "same") == 0


def nees(err, cov):
    return np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[:, :, None])[:, :, 0])


def test_batch_accuracy_against_ground_truth(batch, rec):
    force, cop, theta = errors(batch, rec)
    # Truth scale: ~400 N of weight, CoP excursions of ~2 cm, tilt of ~10 mrad.
    assert force <= upper("smoother.batch.force_rmse_N", force, rel=SOLVER), force
    assert cop <= upper("smoother.batch.cop_rmse_m", cop, rel=SOLVER), cop
    assert theta <= upper("smoother.batch.tilt_rmse_rad", theta, rel=SOLVER), theta


def test_batch_nees_within_chi2_bounds(batch, rec):
    """Per-step NEES of the total wrench and of the pose, where the model is right (away from the
    hidden push): the mean NEES as measured, and most steps inside the 99.9 % chi-square bound.
    Errors are correlated over hundreds of steps, so the mean is not a chi-square(6 N) draw; a
    consistent covariance has a mean NEES near the dof (6), which test_batch_nees_mean_is_the_dof
    holds to its sampling spread."""
    tr = rec.truth
    we = batch.total_wrench - tr.total_wrench
    theta = np.array([so3.log(batch.R[k] @ tr.R[k].T) for k in range(rec.n)])
    pe = np.concatenate([theta, batch.t - tr.t], axis=1)
    keep = away_from_pushes(rec)
    assert keep.sum() > 0.2 * rec.n
    for what, e, cov in (("wrench", we, batch.wrench_cov), ("pose", pe, batch.cov[:, :6, :6])):
        value = nees(e, cov)[keep]
        key = f"smoother.batch.nees_mean_{what}"
        # 15 %: the NEES is a ratio of two solver outputs (error and covariance), each within SOLVER.
        assert lower(key, value.mean(), rel=0.15) <= value.mean() <= upper(key, value.mean(), rel=0.15), value.mean()
        inside = np.mean(value < chi2.ppf(0.999, 6))
        # 0.02 absolute: a fraction of ~1000 correlated steps; 2 % is about 20 of them.
        assert inside >= lower(f"smoother.batch.nees_inside_999_{what}", inside, add=0.02), inside


def effective_samples(x: np.ndarray) -> float:
    """``N / tau`` with ``tau = 1 + 2 sum_k rho_k`` the integrated autocorrelation time of ``x``,
    the sum stopped at the first non-positive autocorrelation (Geyer's initial positive sequence,
    simplified): how many independent draws a time average of ``x`` is worth."""
    x = np.asarray(x, dtype=float) - np.mean(x)
    n = x.size
    acf = np.correlate(x, x, "full")[n - 1:] / (np.arange(n, 0, -1) * np.var(x))
    tau = 1.0
    for rho in acf[1:n // 2]:
        if rho <= 0:
            break
        tau += 2.0 * rho
    return n / tau


@pytest.mark.parametrize("what", [
    "wrench",
    pytest.param("pose", marks=pytest.mark.xfail(
        strict=True, reason="the pose covariance is optimistic: mean NEES 10.7 for 6 dof, above the 99 % band "
        "(3.6, 9.2) of its ~10 effective samples")),
])
def test_batch_nees_mean_is_the_dof(batch, rec, what):
    """A consistent covariance makes the NEES a chi-square(6) variable: mean 6.  The steps' NEES are
    correlated, so their mean is worth ``N_eff`` independent draws (integrated autocorrelation
    time); the test is the two-sided 99 % band of chi-square(6 N_eff) / N_eff."""
    tr = rec.truth
    if what == "wrench":
        e, cov = batch.total_wrench - tr.total_wrench, batch.wrench_cov
    else:
        theta = np.array([so3.log(batch.R[k] @ tr.R[k].T) for k in range(rec.n)])
        e, cov = np.concatenate([theta, batch.t - tr.t], axis=1), batch.cov[:, :6, :6]
    value = nees(e, cov)[away_from_pushes(rec)]
    n_eff = effective_samples(value)
    lo, hi = chi2.ppf([0.005, 0.995], 6 * n_eff) / n_eff
    assert lo < value.mean() < hi, (value.mean(), n_eff, lo, hi)


def test_batch_estimate_contents(batch, rec, tmp_path):
    n, nc = rec.n, len(rec.contact_names)
    assert batch.estimator == "batch"
    assert batch.cov.shape == (n, 18, 18) and batch.wrench_cov.shape == (n, 6, 6) and batch.cop_cov.shape == (n, 2, 2)
    assert np.all(np.linalg.eigvalsh(batch.cov) > 0)
    shapes = {"integration": 12, "newton_euler": 6, "imu": 6, "contact": 6 * nc}
    for fam, k in shapes.items():
        assert batch.residuals[fam].shape == (n, k)
        assert len(batch.residual_labels[fam]) == k
    assert np.all(np.isnan(batch.residuals["integration"][-1]))
    assert "F_x [N]" in batch.residual_labels["newton_euler"]
    # Whitened residuals of a consistent fit: the IMU's mean square near one (smoothed residuals
    # are smaller than the noise by the fraction of the data's degrees of freedom the fit absorbs).
    ms = np.nanmean(batch.residuals["imu"] ** 2)
    assert ms < 1.0
    # SOLVER on both sides: a fixed fraction of 6 x 600 squared residuals.
    key = "smoother.batch.imu_residual_mean_square"
    assert lower(key, ms, rel=SOLVER) <= ms <= upper(key, ms, rel=SOLVER), ms
    loaded = Estimate.load(batch.save(tmp_path / "est.npz"))
    np.testing.assert_array_equal(loaded.residuals["contact"], batch.residuals["contact"])


def test_noise_free_standing_is_recovered_exactly():
    sc = Scenario.load("stand")
    sc.duration = 0.5
    rec = Simulator(sc, noise=False).run()
    est = run_batch(rec, ModelConfig.from_recording(rec))
    force, cop, theta = errors(est, rec)
    # Noise-free, standing: the model is exact and the errors are roundoff (measured 5e-11 N,
    # 1e-13 m, 4e-14 rad).  Roundoff moves with the BLAS and the operation order by orders of
    # magnitude, so the margin is absolute: 2.5e-11 of the weight (1e-8 N of 400 N), 1e-11 m, 1e-11 rad.
    assert force <= upper("smoother.noise_free.force_rmse_N", force, add=1e-8), force
    assert cop <= upper("smoother.noise_free.cop_rmse_m", cop, add=1e-11), cop
    assert theta <= upper("smoother.noise_free.tilt_rmse_rad", theta, add=1e-11), theta


def test_world_rest_placements_move_the_equilibrium_with_them():
    """The contact law depends on the rest placements only through ``R p_l + t - p_r`` and
    ``R R_l R_r^T``, and gravity is along z: rest placements translated by ``d`` give the
    equilibrium ``(R0, t0 + d)``; rotated by ``Rz`` about the vertical, ``(Rz R0, Rz t0)``."""
    sc = Scenario.load("stand")
    sc.duration = 0.05
    rec = Simulator(sc, noise=False).run()
    model = ModelConfig.from_recording(rec)
    R0, q0 = Problem.build(rec, model).equilibrium(0)
    d = np.array([0.03, -0.02, 0.004])
    R1, q1 = Problem.build(rec, model, rest_p=rec.contact_p + d).equilibrium(0)
    np.testing.assert_allclose(R1, R0, atol=1e-12)
    np.testing.assert_allclose(q1[:3], q0[:3] + d, atol=1e-12)
    Rz = so3.exp(np.array([0.0, 0.0, 0.3]))
    R2, q2 = Problem.build(rec, model, rest_p=rec.contact_p @ Rz.T, rest_R=Rz @ rec.contact_R).equilibrium(0)
    np.testing.assert_allclose(R2, Rz @ R0, atol=1e-12)
    np.testing.assert_allclose(q2[:3], Rz @ q0[:3], atol=1e-12)
    same = Problem.build(rec, model, rest_p=rec.contact_p, rest_R=rec.contact_R).equilibrium(0)
    np.testing.assert_array_equal(same[0], R0)


def test_smoothers_follow_the_rest_placements():
    """Noise-free standing with every foothold 3 cm away: the whole estimate moves by as much."""
    sc = Scenario.load("stand")
    sc.duration = 0.5
    rec = Simulator(sc, noise=False).run()
    model = ModelConfig.from_recording(rec)
    d = np.array([0.0, 0.03, -0.002])
    base = run_batch(rec, model)
    moved = run_batch(rec, model, rest_p=rec.contact_p + d)
    np.testing.assert_allclose(moved.t, base.t + d, atol=1e-9)
    # the same wrenches, their moments about the world origin shifted by d x F
    shifted = base.wrench.copy()
    shifted[..., 3:] += np.cross(d, base.wrench[..., :3])
    np.testing.assert_allclose(moved.wrench, shifted, atol=1e-6 * np.abs(base.wrench).max())
    lag = run_fixed_lag(rec, model, lag=0.1, rest_p=rec.contact_p + d)
    np.testing.assert_allclose(lag.t, base.t + d, atol=1e-6)
    with pytest.raises(ConfigError, match=r"rest_p must have shape \(101, 2, 3\)"):
        run_batch(rec, model, rest_p=rec.contact_p[:, :1])


def test_batch_solver_equals_gtsam_levenberg_marquardt(rec, model):
    """The block-tridiagonal Levenberg-Marquardt and gtsam's LM on the CustomFactors agree."""
    short = rec.slice(0, 60)
    prob = Problem.build(short, model)
    traj, _, _ = optimize(prob, want_cov=False)
    builder = GraphBuilder(prob)
    from flexforce.smoother.batch import initial_trajectory

    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setMaxIterations(50)
    result = gtsam.LevenbergMarquardtOptimizer(builder.graph(), builder.values(initial_trajectory(prob)),
                                               params).optimize()
    for k in range(0, prob.n, 7):
        pose = result.atPose3(gtsam.symbol("x", k))
        # Both stop at a relative cost decrease of ~1e-7: states agree to ~1e-3 of their excursion.
        np.testing.assert_allclose(pose.rotation().matrix(), traj.R[k], atol=1e-6)
        np.testing.assert_allclose(pose.translation(), traj.q[k, :3], atol=1e-7)
        np.testing.assert_allclose(result.atVector(gtsam.symbol("a", k)), traj.q[k, 9:15], atol=1e-2)
    mine = builder.graph().error(builder.values(traj))
    # The block solver's precision (~1e-5 relative, tight integration factors) stops it ~1e-3
    # above gtsam's optimum in cost: far below one unit of chi-square.
    assert mine <= builder.graph().error(result) * (1 + 2e-3)


@pytest.mark.parametrize("backend", ["window", "gtsam"])
def test_fixed_lag_close_to_batch(rec, model, batch, backend):
    est = run_fixed_lag(rec, model, lag=0.5, backend=backend)
    assert est.estimator == "fixed_lag" and est.time_per_step.shape == (rec.n,)
    assert est.meta["backend"] == backend
    fb, cb, tb = errors(batch, rec)
    ff, cf, tf = errors(est, rec)
    # Ratios to the batch smoother, with SOLVER on each (a ratio of two solver outputs).
    for what, mine, ref in (("force", ff, fb), ("cop", cf, cb), ("tilt", tf, tb)):
        ratio = mine / ref
        assert ratio <= upper(f"smoother.fixed_lag_{backend}.{what}_over_batch", ratio, rel=SOLVER), (what, mine, ref)
    assert np.all(np.isfinite(est.cov)) and np.all(np.diagonal(est.cov, axis1=1, axis2=2) > 0)


def test_fixed_lag_memory_is_bounded(rec, model):
    from flexforce.smoother.fixed_lag import FixedLagSmoother, GtsamFixedLagSmoother

    prob = Problem.build(rec.slice(0, 200), model)
    fls = GtsamFixedLagSmoother(prob, lag=0.1, covariance=False)
    sizes = []
    for _ in range(prob.n):
        fls.step()
        sizes.append(fls.smoother.getFactors().nrFactors())
    assert max(sizes[100:]) <= max(sizes[40:100]) + 2
    # The window backend: ring buffers sized by the lag, whatever the recording's length.
    fls = FixedLagSmoother(prob, lag=0.1, covariance=False)
    before = {name: a.shape for name, a in vars(fls).items() if isinstance(a, np.ndarray) and a.shape[:1] != (prob.n,)}
    for _ in range(prob.n):
        fls.step()
    after = {name: a.shape for name, a in vars(fls).items() if isinstance(a, np.ndarray) and a.shape[:1] != (prob.n,)}
    assert before == after and fls.Ld.shape[0] == fls.cap < 40


def test_fixed_lag_residuals_have_no_read_out_seams(rec, model):
    """The window is read out in blocks of ``report_every`` steps: the integration factor between a
    block's last step and the next is evaluated within one solve (``successors``), so it is no
    larger than the other steps' (on the read-out trajectory it compared two solves 10 samples
    apart).  Measured on this 3 s push: the largest seam residual 5.4 sigma, 8.4 elsewhere; on the
    read-out trajectory the seams read 937 sigma.  The bound is the other steps' largest."""
    est = run_fixed_lag(rec, model)
    r = np.nanmax(np.abs(est.residuals["integration"]), axis=1)
    late = np.arange(rec.n) >= 20
    seam = np.zeros(rec.n, dtype=bool)
    seam[9::10] = True
    assert np.nanmax(r[seam & late]) <= np.nanmax(r[~seam & late])


def test_window_fixed_lag_with_full_relinearisation_matches_batch_on_a_short_window(rec, model):
    """Lag longer than the recording and every step relinearised at each update: the window
    smoother's last update is Gauss-Newton on the whole recording, started from its own estimates;
    it must land on the batch optimum.  Its newest step has had one Gauss-Newton iteration from
    the prediction, so the comparison is made where the prediction is good: without the ambient
    disturbance (an algorithmic equivalence, whatever the world)."""
    sc = Scenario.load("push-pitch")
    sc.duration, sc.ambient = 0.4, False
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    short = Simulator(sc).run().slice(0, 80)
    prob = Problem.build(short, model)
    traj, _, _ = optimize(prob, want_cov=False)
    est = run_fixed_lag(short, model, lag=1.0, relinearize=80, covariance=False)
    np.testing.assert_allclose(est.t, traj.q[:, :3], atol=2e-6)
    np.testing.assert_allclose(est.total_wrench[:, :3], (traj.W * prob.active[:, :, None]).sum(axis=1)[:, :3],
                               atol=0.05)


def test_ft_fusion_improves_the_estimate(rec, model, batch):
    fused = run_batch(rec, dataclasses.replace(model, use_ft=True))
    assert "ft" in fused.residuals and fused.residuals["ft"].shape == (rec.n, 12)
    fb, cb, tb = errors(batch, rec)
    ff, cf, tf = errors(fused, rec)
    # The F/T readings add information on every wrench component: no error may grow, and each
    # ratio stays as measured (SOLVER: ratios of two solver outputs).
    for what, mine, ref in (("force", ff, fb), ("cop", cf, cb), ("tilt", tf, tb)):
        ratio = mine / ref
        assert ratio <= upper(f"smoother.ft_fusion.{what}_over_nominal", ratio, rel=SOLVER), (what, mine, ref)
        assert ratio < 1.0, (what, mine, ref)
    assert np.mean(np.trace(fused.wrench_cov, axis1=1, axis2=2)) < np.mean(np.trace(batch.wrench_cov, axis1=1, axis2=2))


class ConstantGyroBias:
    """A test effect: a constant gyro bias (IMU frame, rad/s), added to the gyro residual."""

    name = "gyro-bias"
    dim = 3
    labels = ("b_x [rad/s]", "b_y [rad/s]", "b_z [rad/s]")

    def prior(self, problem):
        return np.zeros(3), np.full(3, 0.1)

    def random_walk_sigma(self, problem):
        return np.full(3, 1e-7)

    def residual_terms(self, family, problem, steps, R, q, W, e):
        if family != "imu":
            return None
        n = len(steps)
        dr = np.zeros((n, 6))
        dr[:, :3] = e
        dr_de = np.zeros((n, 6, 3))
        dr_de[:, :3, :] = np.eye(3)
        return dr, np.zeros((n, 6, 18)), dr_de

    def report(self, values, cov):
        return {"value": values.mean(axis=0).tolist(), "last": values[-1].tolist(),
                "std": np.sqrt(np.diagonal(cov[-1])).tolist()}


def test_effect_protocol_plugs_in_a_gyro_bias(rec, model):
    bias = np.array([0.01, -0.02, 0.005])
    biased = rec.slice(0, rec.n)
    biased.gyro = biased.gyro + bias
    effect = ConstantGyroBias()
    assert isinstance(effect, Effect)
    est = run_batch(biased, dataclasses.replace(model, effects=(effect,)))
    value = np.array(est.effects["gyro-bias"]["value"])
    np.testing.assert_allclose(value, bias, atol=1e-3)
    nominal = run_batch(biased, model)
    ratio = errors(est, rec)[2] / errors(nominal, rec)[2]
    assert ratio <= upper("smoother.gyro_bias_effect.batch_tilt_over_nominal", ratio, rel=SOLVER)


def test_effect_protocol_in_the_fixed_lag_smoother(rec, model):
    """The same effect object in the (window) fixed-lag smoother: the bias is learnt online and
    carried through marginalisation; the gtsam backend refuses effects."""
    bias = np.array([0.01, -0.02, 0.005])
    biased = rec.slice(0, rec.n)
    biased.gyro = biased.gyro + bias
    cfg = dataclasses.replace(model, effects=(ConstantGyroBias(),))
    est = run_fixed_lag(biased, cfg, lag=0.5)
    assert est.cov.shape == (rec.n, 18, 18)
    report = est.effects["gyro-bias"]
    np.testing.assert_allclose(report["last"], bias, atol=1e-3)  # with all the data seen
    np.testing.assert_allclose(report["value"], bias, atol=2e-3)  # averaged over the run, start included
    assert np.all(np.array(report["std"]) < 1e-3)
    nominal = run_fixed_lag(biased, model, lag=0.5, covariance=False)
    # once the bias is learnt online (the first second), the tilt error falls
    ratio = errors(est, rec, skip=1.0)[2] / errors(nominal, rec, skip=1.0)[2]
    assert ratio <= upper("smoother.gyro_bias_effect.fixed_lag_tilt_over_nominal", ratio, rel=SOLVER)
    from flexforce.errors import ConfigError

    with pytest.raises(ConfigError):
        run_fixed_lag(biased.slice(0, 20), cfg, backend="gtsam")


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["push-pitch", "push-roll", "com-step"])
def test_smoothers_beat_the_ekf(scenario):
    ekf_mod = pytest.importorskip("flexforce.compare.ekf.filter")
    sc = Scenario.load(scenario)
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    rec = Simulator(sc).run()
    model = ModelConfig.from_recording(rec)
    ekf = errors(ekf_mod.run_ekf(rec, model), rec)
    for est in (run_batch(rec, model), run_fixed_lag(rec, model)):
        mine = errors(est, rec)
        # The target on total force, CoP and flexibility orientation: at most 0.7x the EKF, and each
        # ratio as measured (SOLVER: the EKF is deterministic, the smoother within its stopping rule).
        for what, m, e in zip(("force", "cop", "tilt"), mine, ekf):
            key = f"smoother.vs_ekf.{scenario}.{est.estimator}.{what}_over_ekf"
            assert m / e <= min(0.7, upper(key, m / e, rel=SOLVER)), (scenario, est.estimator, what, m, e)
