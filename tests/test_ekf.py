"""Tests of the seed paper's EKF (flexforce.compare.ekf.filter) and its compiled kernel.

- Reduction: with linear models the EKF's predict/update are a plain Kalman filter (written here
  independently, textbook form).
- Jacobians: the analytic F and H (physics module + J_l(Omega) change of parametrisation) against
  central differences -- the authors' way -- at a perturbed state, near the identity, with one and
  two contacts and with anisotropic, stiffening contacts.
- The compiled step against the same model with numpy's textbook Kalman algebra (tests/reference/ekf.py)
  to 1e-10.
- Simulated stand / com-step / push-pitch (no IMU bias random walk: the nominal model has no bias,
  see docs/ekf.md): convergence from a wrong initial state, Monte Carlo NEES within its two-sided
  chi^2 band, NIS, m g.
- Bad input and failures: NaN -> DataError, non-PD covariance -> EstimatorError or a reset with a
  warning, divergence -> EstimatorError.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from baseline import lower, upper
from reference import ekf as ekf_ref
from scipy import stats

from flexforce.compare.ekf import filter as E
from flexforce.compare.ekf import kernel as kern
from flexforce.datasets.estimate import Estimate
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import simulate
from flexforce.errors import ConfigError, DataError, EstimatorError
from flexforce.factors import physics as ph
from flexforce.factors import so3
from flexforce.factors.model import ModelConfig
from flexforce.factors.physics import ContactParams

# EKF: margin on an error or a statistic of the filter on a seeded recording.  The filter is a
# fixed sequence of float operations (no iteration count, no stopping rule), so only summation
# order in another BLAS/numba build moves these; 5 % leaves room for that and no more.
EKF = 0.05

CHI2_18_975 = 31.526  # chi^2 quantile, 18 dof, 0.975
CHI2_18_995 = 37.156
CHI2_6_995 = 18.548


def _sim(name: str, duration: float):
    sc = Scenario.load(name)
    sc.duration = duration
    # The nominal model has no IMU bias; the simulator's default slow bias random walk is an
    # effect for the diagnostics to find, not something the baseline's covariance should cover.
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    return simulate(sc)


@pytest.fixture(scope="module")
def recs():
    return {"stand": _sim("stand", 3.0), "com-step": _sim("com-step", 3.0), "push-pitch": _sim("push-pitch", 3.0)}


def _errors(est: Estimate, truth) -> np.ndarray:
    """(N, 18) truth minus estimate in world increments (theta, t, w, v, dw, a)."""
    th = np.array([so3.log(Rt @ Re.T) for Rt, Re in zip(truth.R, est.R)])
    return np.hstack([th, truth.t - est.t, truth.w - est.w, truth.v - est.v, truth.dw - est.dw, truth.a - est.a])


def _nees(est: Estimate, truth) -> np.ndarray:
    assert est.cov is not None
    e = _errors(est, truth)
    return np.einsum("ki,ki->k", e, np.linalg.solve(est.cov, e[..., None])[..., 0])


def _wrong_x0(rec):
    """A wrong initial state: truth plus ~3 sigma of the derived prior on every component."""
    tr = rec.truth
    x_true = np.concatenate([tr.t[0], so3.log(tr.R[0]), tr.v[0], tr.w[0]])
    nm = E.noise_model(rec, ModelConfig.from_recording(rec))
    signs = np.resize([1.0, -1.0, 1.0, 1.0, -1.0, -1.0], 12)
    return x_true + 3.0 * signs * nm.p0_sigma


# ----------------------------------------------------------------------------------------------
# Reduction to a plain Kalman filter
# ----------------------------------------------------------------------------------------------


def _plain_kf(x, P, ys, A, C, Q, R):
    """Textbook Kalman filter, standard covariance update, explicit inverse (independent code)."""
    xs = []
    for k, y in enumerate(ys):
        if k > 0:
            x = A @ x
            P = A @ P @ A.T + Q
        K = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
        x = x + K @ (y - C @ x)
        P = (np.eye(len(x)) - K @ C) @ P
        xs.append((x, P))
    return xs


class _LinearToyEKF(E.EKF):
    """The EKF's machinery with linear transition and measurement (a linearised toy)."""

    def __init__(self, A, C, Q, R, ys):
        self.A, self.C, self.ys = A, C, ys
        self.Qm = Q
        self.noise = E.NoiseModel(Q, R, 0.0, 0.0, np.zeros(12))
        self.config = E.EKFConfig()

    def transition(self, x, k, jacobian=False):
        return (self.A @ x, self.A) if jacobian else self.A @ x

    def measurement(self, x, k, jacobian=False):
        return (self.C @ x, self.C) if jacobian else self.C @ x

    def update(self, x, P, k):
        return ekf_ref.kf_update(x, P, self.ys[k], self.C @ x, self.C, self.noise.R)


def test_linear_toy_equals_plain_kalman_filter():
    rng = np.random.default_rng(0)
    n = 18
    A = np.eye(n) + 0.01 * rng.normal(size=(n, n))
    C = rng.normal(size=(6, n))
    Lq = 0.1 * rng.normal(size=(n, n))
    Q = Lq @ Lq.T + 1e-3 * np.eye(n)
    R = np.diag(rng.uniform(0.01, 0.1, 6))
    ys = rng.normal(size=(40, 6))
    x0, P0 = rng.normal(size=n), np.eye(n)
    toy = _LinearToyEKF(A, C, Q, R, ys)
    x, P = x0, P0
    ref = _plain_kf(x0, P0, ys, A, C, Q, R)
    for k in range(len(ys)):
        if k > 0:
            x, P = ekf_ref.predict(toy, x, P, k, Q=toy.Qm)
        up = toy.update(x, P, k)
        x, P = up.x, up.P
        np.testing.assert_allclose(x, ref[k][0], rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(P, ref[k][1], rtol=1e-9, atol=1e-10)
        # whitened innovation: NIS equals innovation^T S^-1 innovation
        assert up.nis == pytest.approx(up.innovation @ np.linalg.solve(up.S, up.innovation), rel=1e-10)


# ----------------------------------------------------------------------------------------------
# Jacobians: analytic against the authors' finite differences
# ----------------------------------------------------------------------------------------------


def _states(rng):
    """A perturbed state and a near-identity one (rotation 1e-7), (t, Omega, v, w, a, dw)."""
    big = np.concatenate([rng.normal(0, 0.01, 3), rng.normal(0, 0.05, 3), rng.normal(0, 0.05, 3),
                          rng.normal(0, 0.3, 3), rng.normal(0, 0.5, 3), rng.normal(0, 2.0, 3)])
    tiny = big * 1e-6
    tiny[3:6] = [1e-7, -1e-7, 5e-8]
    return [big, tiny]


@pytest.mark.parametrize("aniso", [False, True])
def test_analytic_jacobians_match_finite_differences(recs, aniso):
    rec = recs["com-step"]
    model = ModelConfig.from_recording(rec)
    if aniso:
        p = ContactParams.make([3e4, 2e4, 2.8e4], [400, 300, 420], [450, 300, 500], [8, 6, 9], beta_f=50.0,
                               beta_t=2.0)
        model = dataclasses.replace(model, contact_params=(p, p))
    rec2 = rec.slice(0, 20)
    rec2.contact_active[5, 1] = False  # one contact at step 5, two elsewhere
    rot = so3.exp(np.array([0.1, -0.2, 0.3]))
    rec2.contact_R[:, 0] = rot
    ana = E.EKF(rec2, model, E.EKFConfig())
    for x in _states(np.random.default_rng(1)):
        for k in (4, 5):
            f_a, F_a = ana.transition(x, k, jacobian=True)
            f_n, F_n = ekf_ref.transition_numeric(ana, x, k)
            np.testing.assert_allclose(f_a, f_n, rtol=0, atol=0)
            scale = np.maximum(np.abs(F_n).max(axis=1, keepdims=True), 1.0)
            np.testing.assert_allclose(F_a / scale, F_n / scale, atol=2e-6)
            h_a, H_a = ana.measurement(x, k, jacobian=True)
            _, H_n = ekf_ref.measurement_numeric(ana, x, k)
            np.testing.assert_allclose(H_a, H_n, atol=2e-6)


# ----------------------------------------------------------------------------------------------
# Compiled kernel against the reference
# ----------------------------------------------------------------------------------------------


def test_compiled_step_matches_plain_kalman_algebra(recs):
    """The compiled step (block-sparse F P F^T, expanded Joseph form, permuted world covariance)
    against the reference's predict / update (tests/reference/ekf.py): the same model with numpy's
    dense textbook algebra."""
    rec = recs["com-step"].slice(0, 30)
    rec.contact_active[10:15, 0] = False
    p = ContactParams.make([3e4, 2e4, 2.8e4], [400, 300, 420], [450, 300, 500], [8, 6, 9], beta_f=50.0, beta_t=2.0)
    rec.contact_R[:, 1] = so3.exp(np.array([0.0, 0.1, 0.4]))
    model = dataclasses.replace(ModelConfig.from_recording(rec), contact_params=(p, p))
    ekf = E.EKF(rec, model)
    rng = np.random.default_rng(2)
    for x in _states(rng):
        L = rng.normal(size=(18, 18)) * 1e-2
        P = L @ L.T + 1e-4 * np.eye(18)
        for k in (3, 12):
            x_r, P_r = ekf_ref.predict(ekf, x, P, k)
            x_k, P_k = x.copy(), P.copy()
            assert kern.predict(x_k, P_k, ekf.U[k], ekf.CP, ekf.noise.Q, ekf.dt, rec.mass, ekf.g, ekf.WS) == 0
            np.testing.assert_allclose(x_k, x_r, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(P_k, P_r, rtol=1e-10, atol=1e-12 * np.abs(P_r).max())
            up = ekf_ref.update(ekf, x_r, P_r, k)
            x_u, P_u = x_r.copy(), P_r.copy()
            innov, S, white = np.empty(6), np.empty((6, 6)), np.empty(6)
            st, nis = kern.update(x_u, P_u, ekf.U[k], ekf.noise.R, ekf.g, ekf.WS, innov, S, white, ekf.gates,
                                     np.empty(2), np.empty(2))
            assert st == 0
            np.testing.assert_allclose(x_u, up.x, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(P_u, up.P, rtol=1e-9, atol=1e-12 * np.abs(up.P).max())
            np.testing.assert_allclose(innov, up.innovation, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(white, up.whitened, rtol=1e-10, atol=1e-12)
            assert nis == pytest.approx(up.nis, rel=1e-9)


def _plain_run(rec, model, x0):
    """run_ekf written with the reference predict / update and EKF.outputs (numpy Kalman algebra)."""
    ekf = E.EKF(rec, model)
    x, P = ekf.initial_state(x0)
    rows = []
    for k in range(rec.n):
        if k > 0:
            x, P = ekf_ref.predict(ekf, x, P, k)
        up = ekf_ref.update(ekf, x, P, k)
        x, P = up.x, up.P
        o = ekf.outputs(x, P, k)
        rows.append((x, o, up))
    return rows


def test_run_matches_plain_kalman_algebra(recs):
    rec = recs["push-pitch"].slice(0, 300)
    model = ModelConfig.from_recording(rec)
    x0 = _wrong_x0(rec)
    est = E.run_ekf(rec, model, x0=x0)
    assert est.meta["kernel"] == "numba"
    rows = _plain_run(rec, model, x0)
    ref = {"t": np.array([r[0][0:3] for r in rows]), "R": np.array([r[1]["R"] for r in rows]),
           "w": np.array([r[0][9:12] for r in rows]), "v": np.array([r[0][6:9] for r in rows]),
           "dw": np.array([r[0][15:18] for r in rows]), "a": np.array([r[0][12:15] for r in rows]),
           "innovation": np.array([r[2].innovation for r in rows]), "innovation_cov": np.array([r[2].S for r in rows])}
    for name in ("cov", "wrench", "wrench_cov", "cop", "cop_cov"):
        ref[name] = np.array([r[1][name] for r in rows])
    for name, b in ref.items():
        a = getattr(est, name)
        assert (np.isnan(a) == np.isnan(b)).all(), name  # the CoP is undefined where F_z <= 0
        assert np.nanmax(np.abs(a - b)) <= 1e-10 * max(1.0, np.nanmax(np.abs(b))), name


def test_outputs_switched_off_keep_the_state(recs):
    rec = recs["push-pitch"].slice(0, 100)
    model = ModelConfig.from_recording(rec)
    full = E.run_ekf(rec, model)
    lean = E.run_ekf(rec, model, outputs=False)
    for name in ("t", "R", "w", "v", "dw", "a", "innovation", "innovation_cov"):
        np.testing.assert_array_equal(getattr(lean, name), getattr(full, name), err_msg=name)
    assert np.all(np.isnan(lean.wrench)) and np.all(np.isnan(lean.cov))


# ----------------------------------------------------------------------------------------------
# Simulated scenarios
# ----------------------------------------------------------------------------------------------


def _quiet_steps(rec, settle: float = 1.0):
    """Steps after the first second and away (by ``settle`` s) from hidden external wrenches."""
    n = rec.n
    ext = np.abs(rec.truth.external_wrench).max(axis=1) > 0
    m = int(round(settle / rec.dt))
    near = np.convolve(ext.astype(float), np.ones(m), "full")[:n] > 0
    ok = ~near
    ok[: int(round(1.0 / rec.dt))] = False
    return ok


@pytest.mark.parametrize("name", ["stand", "com-step", "push-pitch"])
def test_converges_from_wrong_state_and_is_consistent(recs, name):
    rec = recs[name]
    model = ModelConfig.from_recording(rec)
    x0 = _wrong_x0(rec)
    assert np.abs(x0[0:3] - rec.truth.t[0]).min() > 0.02  # starts > 2 cm off on every axis
    est = E.run_ekf(rec, model, x0=x0)
    err = _errors(est, rec.truth)
    quiet = _quiet_steps(rec)
    # converged: after 1 s, away from the pushes, the largest error as measured
    rot, trans = np.abs(err[quiet, 0:3]).max(), np.abs(err[quiet, 3:6]).max()
    assert rot <= upper(f"ekf.{name}.converged_rotation_error_max_rad", rot, rel=EKF), rot
    assert trans <= upper(f"ekf.{name}.converged_translation_error_max_m", trans, rel=EKF), trans
    # (the covariance's consistency is test_nees_is_consistent's, with initial errors drawn from P0)
    # the innovations' mean NIS: as measured, and near its dof (6) -- test_mean_nis_is_the_dof
    nis = (est.residuals["imu"][quiet] ** 2).sum(axis=1)
    key = f"ekf.{name}.nis_mean"
    assert lower(key, nis.mean(), rel=EKF) <= nis.mean() <= upper(key, nis.mean(), rel=EKF), nis.mean()


@pytest.mark.parametrize("name", ["stand", "com-step", "push-pitch"])
def test_mean_nis_is_the_dof(recs, name):
    """The innovations of a consistent filter are white with covariance S: the NIS of the quiet
    steps are independent chi-square(6) draws, their mean within the two-sided 99 % band of
    chi-square(6 N) / N."""
    rec = recs[name]
    est = E.run_ekf(rec, ModelConfig.from_recording(rec), x0=_wrong_x0(rec))
    nis = (est.residuals["imu"][_quiet_steps(rec)] ** 2).sum(axis=1)
    lo, hi = stats.chi2.ppf([0.005, 0.995], 6 * nis.size) / nis.size
    assert lo < nis.mean() < hi, (nis.mean(), nis.size, lo, hi)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["stand", "push-pitch"])
def test_nees_is_consistent(name):
    """Monte Carlo NEES (Bar-Shalom): initial error drawn from P0, noise and ambient disturbance
    from the nominal model's own assumptions; each run's time-averaged NEES counts as one chi^2(18)
    draw, so the mean of M runs must lie in the two-sided 95% band of chi^2(18 M) / M."""
    M = 3
    means = []
    for seed in range(M):
        sc = Scenario.load(name)
        sc.duration, sc.seed = 3.0, seed
        sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
        rec = simulate(sc)
        model = ModelConfig.from_recording(rec)
        nm = E.noise_model(rec, model)
        tr = rec.truth
        d = np.random.default_rng(100 + seed).standard_normal(12) * nm.p0_sigma
        x0 = np.concatenate([tr.t[0] + d[0:3], so3.log(so3.exp(d[3:6]) @ tr.R[0]), tr.v[0] + d[6:9],
                             tr.w[0] + d[9:12]])
        est = E.run_ekf(rec, model, x0=x0)
        ext = np.abs(tr.external_wrench).max(axis=1) > 0  # hidden pushes: the model is wrong there
        keep = np.convolve(ext.astype(float), np.ones(int(round(1.0 / rec.dt))), "full")[:rec.n] == 0
        means.append(_nees(est, tr)[keep].mean())
    lo, hi = stats.chi2.ppf([0.025, 0.975], 18 * M) / M
    assert lo < np.mean(means) < hi, (means, lo, hi)


def test_push_is_flagged_by_nees_and_nis(recs):
    """The hidden push is unmodelled: the filter's errors leave their bounds while it acts."""
    rec = recs["push-pitch"]
    est = E.run_ekf(rec, ModelConfig.from_recording(rec))
    push = np.abs(rec.truth.external_wrench).max(axis=1) > 0
    nees = _nees(est, rec.truth)
    assert nees[push].mean() > CHI2_18_995
    assert nees[push].mean() >= lower("ekf.push.nees_mean_during_push", nees[push].mean(), rel=EKF)
    nis = (est.residuals["imu"] ** 2).sum(axis=1)
    ratio = nis[push].mean() / nis[_quiet_steps(rec)].mean()
    assert ratio > 1.0 and ratio >= lower("ekf.push.nis_push_over_quiet", ratio, rel=EKF), ratio


def test_standing_vertical_force_is_mg(recs):
    rec = recs["stand"]
    est = E.run_ekf(rec, ModelConfig.from_recording(rec))
    steps = slice(int(1.0 / rec.dt), None)
    fz = est.total_wrench[steps, 2]
    mg = rec.mass * rec.gravity
    sd = np.sqrt(est.wrench_cov[steps, 2, 2])
    bias = abs(fz.mean() - mg)
    # 0.01 N absolute on a mean over 400 steps of a 400 N force (a relative margin on a number near
    # zero would be meaningless)
    assert bias <= upper("ekf.stand.vertical_force_bias_N", bias, add=0.01), bias
    # every step within 5 sigma of its own covariance (false alarm 6e-7 per step)
    assert np.all(np.abs(fz - mg) < 5 * sd)
    # both feet carry it: each foot's vertical force against the simulator's, as measured
    # (each per-contact wrench being zero when inactive is test_estimate_fields_and_roundtrip's)
    for i in range(2):
        err = np.sqrt(np.mean((est.wrench[steps, i, 2] - rec.truth.wrench[steps, i, 2]) ** 2))
        assert err <= upper(f"ekf.stand.contact_{i}_vertical_force_rmse_N", err, rel=EKF), (i, err)
        assert est.wrench[steps, i, 2].min() > 0


# ----------------------------------------------------------------------------------------------
# Output
# ----------------------------------------------------------------------------------------------


def test_estimate_fields_and_roundtrip(recs, tmp_path):
    rec = recs["stand"].slice(0, 60)
    rec.contact_active[30:, 1] = False  # right foot lifts: its wrench must be zero
    est = E.run_ekf(rec, ModelConfig.from_recording(rec))
    n = rec.n
    assert est.estimator == "ekf" and est.cov.shape == (n, 18, 18) and est.wrench.shape == (n, 2, 6)
    assert np.all(est.wrench[30:, 1] == 0.0) and np.any(est.wrench[:30, 1] != 0.0)
    assert est.innovation.shape == (n, 6) and est.innovation_cov.shape == (n, 6, 6)
    assert est.residuals["imu"].shape == (n, 6) and len(est.residual_labels["imu"]) == 6
    assert est.cop_cov.shape == (n, 2, 2) and est.wrench_cov.shape == (n, 6, 6)
    assert np.all(est.time_per_step > 0) and est.total_time >= est.time_per_step.sum() * 0.5
    for P in est.cov[::10]:
        np.linalg.cholesky(P)
    # cov is over world increments (theta, t, w, v, dw, a): the filter's covariance over its own
    # (t, Omega, v, w, a, dw) mapped by the derivative of the world increments with respect to the
    # filter's, taken here by central differences (theta = log(exp(Omega + d) exp(Omega)^T))
    ekf = E.EKF(rec, ModelConfig.from_recording(rec))
    x = np.concatenate([est.t[-1], so3.log(est.R[-1]), est.v[-1], est.w[-1], est.a[-1], est.dw[-1]])

    def world(xp):
        return np.concatenate([so3.log(so3.exp(xp[3:6]) @ so3.exp(x[3:6]).T), xp[0:3], xp[9:12], xp[6:9],
                               xp[15:18], xp[12:15]])

    h = 1e-6
    M = np.column_stack([(world(x + h * e) - world(x - h * e)) / (2 * h) for e in np.eye(18)])
    L = np.random.default_rng(5).normal(size=(18, 18))
    P_paper = L @ L.T
    # central differences of a smooth map: error ~h^2 plus roundoff ~1e-16 / h = 1e-10 per entry
    np.testing.assert_allclose(ekf.outputs(x, P_paper, n - 1)["cov"], M @ P_paper @ M.T,
                               atol=1e-8 * np.abs(P_paper).max())
    back = Estimate.load(est.save(tmp_path / "ekf.npz"))
    np.testing.assert_array_equal(back.cov, est.cov)
    assert back.residual_labels["imu"] == est.residual_labels["imu"]


def test_cli_run(recs, tmp_path):
    from flexforce.cli import main
    from flexforce.datasets.io.bagio import save_recording

    bag = save_recording(recs["stand"].slice(0, 100), tmp_path / "rec")
    out = tmp_path / "out.npz"
    assert main(["run", str(bag), "--estimator", "ekf", "-o", str(out), "--quiet"]) == 0
    est = Estimate.load(out)
    assert est.estimator == "ekf" and est.n == 100


# ----------------------------------------------------------------------------------------------
# Bad input and failures
# ----------------------------------------------------------------------------------------------


def test_nan_reading_is_a_data_error(recs):
    rec = recs["stand"].slice(0, 50)
    rec.gyro[17:23, 1] = np.nan  # a missing reading is skipped (tests/test_faults.py); too many are refused
    with pytest.raises(DataError, match=r"field 'gyro' is missing .* at 6 of 50 samples \(12\.0 %, first at "
                                        r"sample 17, t = 0\.085 s\)"):
        E.run_ekf(rec, ModelConfig.from_recording(rec))
    rec = recs["stand"].slice(0, 50)
    rec.inertia[3, 0, 0] = np.inf
    with pytest.raises(DataError, match=r"field 'inertia' .* sample 3"):
        E.run_ekf(rec, ModelConfig.from_recording(rec))


def test_bad_options_and_prior(recs):
    rec = recs["stand"].slice(0, 20)
    model = ModelConfig.from_recording(rec)
    with pytest.raises(ConfigError, match=r"unknown EKF option\(s\) \['lag'\]; known: .*touchdown"):
        E.run_ekf(rec, model, lag=1.0)
    with pytest.raises(ConfigError, match="P0 is not positive definite"):
        E.run_ekf(rec, model, P0=-np.eye(18))


def test_non_positive_definite_covariance_raises_or_resets(recs, monkeypatch):
    rec = recs["stand"].slice(0, 40)
    model = ModelConfig.from_recording(rec)
    real = kern.step
    calls = {"n": 0}

    def flaky(k, x, P, *args):
        """The predicted covariance fails its check once, at the 21st step."""
        calls["n"] += 1
        status = real(k, x, P, *args)
        return 1 if calls["n"] == 21 else status

    monkeypatch.setattr(kern, "step", flaky)
    with pytest.raises(EstimatorError, match=r"not positive definite .* sample \d+"):
        E.run_ekf(rec, model)
    calls["n"] = 0
    with pytest.warns(RuntimeWarning, match="covariance reset to P0"):
        est = E.run_ekf(rec, model, on_covariance_failure="reset")
    assert np.all(np.isfinite(est.cov)) and np.all(est.cop[:, :2] != 0.0)


def test_divergence_is_an_estimator_error(recs):
    rec = recs["stand"].slice(0, 80)
    rec.gyro[30:] += 1.0  # a gyro offset of ~80 sigma: no flexibility state explains it
    with pytest.raises(EstimatorError, match=r"diverged: .* exceeded 1000 .* for 10 consecutive steps"):
        E.run_ekf(rec, ModelConfig.from_recording(rec), nis_limit=1e3, nis_steps=10, imu_gate=None)
    # With the IMU gate (default) the samples beyond it are down-weighted; a run longer than
    # gate_max_time of one sensor far beyond it is an error naming that sensor and when it began.
    with pytest.raises(EstimatorError, match=r"the gyro has disagreed .* from sample 30 \(t = 0\.150 s\)"):
        E.run_ekf(rec, ModelConfig.from_recording(rec), nis_limit=1e3, gate_max_time=0.05)


# ----------------------------------------------------------------------------------------------
# Footholds: the touch-down rule
# ----------------------------------------------------------------------------------------------


def _landing(recs):
    """com-step with the right foot lifted over steps 10-19 and landing at step 20, and a tilted,
    moving state just before it."""
    rec = recs["com-step"].slice(0, 40)
    rec.contact_active[10:20, 1] = False
    x = np.concatenate([[0.002, -0.001, -0.004], [0.01, -0.02, 0.005], [0.01, 0.0, -0.02], [0.05, -0.1, 0.02],
                        [0.1, 0.2, -0.3], [0.5, -0.4, 0.2]])
    return rec, x, 20


@pytest.mark.parametrize("tilt_weight, height_weight", [(0.0, 0.0), (0.4, 0.5), (1.0, 1.0)])
def test_touchdown_sets_the_foothold_where_the_foot_lands(recs, tilt_weight, height_weight):
    rec, x, k = _landing(recs)
    model = ModelConfig.from_recording(rec)
    ekf = E.EKF(rec, model, E.EKFConfig(touchdown="zero-deflection", ground_tilt_weight=tilt_weight,
                                        ground_height_weight=height_weight))
    rest_before = ekf.U[:, kern.NU0 + kern.NUC:].copy()
    floor = 0.003  # m: the plane the landing sole's height is pulled to
    kern.touch_down(k, x, ekf.U, ekf.dt, tilt_weight, height_weight, floor)
    o = kern.NU0 + kern.NUC  # contact 1
    p_r, R_r = ekf.U[k, o + 13:o + 16], ekf.U[k, o + 16:o + 25].reshape(3, 3)
    x1 = ekf.transition(x, k)
    R1, t1 = so3.exp(x1[3:6]), x1[0:3]
    landed_p = R1 @ rec.contact_p[k, 1] + t1
    expected = landed_p - np.array([0.0, 0.0, height_weight * (landed_p[2] - floor)])
    np.testing.assert_allclose(p_r, expected, atol=1e-15)
    landed = R1 @ rec.contact_R[k, 1]
    # The sole's tilt against gravity is removed in the given fraction, its yaw kept.
    tilt = lambda Rm: math.acos(np.clip(Rm[2, 2], -1.0, 1.0))  # noqa: E731
    assert tilt(R_r) == pytest.approx((1.0 - tilt_weight) * tilt(landed), abs=1e-12)
    heading = lambda Rm: math.atan2(Rm[1, 0] - Rm[0, 1], Rm[0, 0] + Rm[1, 1])  # noqa: E731
    assert heading(R_r) == pytest.approx(heading(landed), abs=1e-3 * tilt(landed))
    if tilt_weight == 0.0:
        np.testing.assert_allclose(R_r, landed, atol=1e-15)
    # Every step of the episode (20 until the end) holds the foothold; the others are untouched.
    for kk in range(k, rec.n):
        np.testing.assert_array_equal(ekf.U[kk, o + 13:o + 25], ekf.U[k, o + 13:o + 25])
    np.testing.assert_array_equal(ekf.U[:k, o:], rest_before[:k])
    # Zero deflection: at the predicted pose the landing contact's spring carries nothing and
    # its wrench is the damper's alone.
    if tilt_weight == 0.0:
        p = model.contact_params[1]
        damper = ContactParams.make(np.zeros((3, 3)), p.K_fd, np.zeros((3, 3)), p.K_td)
        args = (R1, t1, x1[9:12], x1[6:9], rec.contact_p[k, 1], rec.contact_R[k, 1])
        np.testing.assert_allclose(ph.contact_wrench(*args, p, world_p_rest=p_r, world_R_rest=R_r),
                                   ph.contact_wrench(*args, damper), rtol=1e-9, atol=1e-9)


def test_touchdown_rule_in_a_run(recs):
    """Only episodes that start during the run get a foothold; the default keeps today's law."""
    rec, x, k = _landing(recs)
    # the reported forces near a switch carry the motion's force with the local rule only
    # (ModelConfig.switch_window): off here, so that the filters alone are compared
    model = dataclasses.replace(ModelConfig.from_recording(rec), switch_window=0.0)
    local = E.run_ekf(rec, model)
    same = E.run_ekf(rec, model, touchdown="local", rest_p=rec.contact_p, rest_R=rec.contact_R)
    np.testing.assert_array_equal(same.wrench, local.wrench)
    zero = E.run_ekf(rec, model, touchdown="zero-deflection")
    np.testing.assert_array_equal(zero.wrench[:k], local.wrench[:k])
    assert zero.meta["touchdown"] == "zero-deflection"
    # The landing spring starts near zero: its force at touch-down is far below the local rule's
    # (which loads it with the flexibility's whole deflection at once).  Measured: 17.5 N against
    # 156 N (ratio 0.11; what remains is the damper and the update's correction of the pose);
    # margin x2 on the ratio.
    F_zero = np.linalg.norm(zero.wrench[k, 1, :3])
    F_local = np.linalg.norm(local.wrench[k, 1, :3])
    assert F_zero < 0.22 * F_local


def test_touchdown_options_are_checked():
    with pytest.raises(ConfigError, match="EKFConfig.touchdown = 'flat'; expected 'local' or 'zero-deflection'"):
        E.EKFConfig(touchdown="flat")
    with pytest.raises(ConfigError, match=r"EKFConfig.ground_tilt_weight = 1.5; expected a number in \[0, 1\]"):
        E.EKFConfig(ground_tilt_weight=1.5)
    with pytest.raises(ConfigError, match=r"EKFConfig.ground_height_weight = -0.1; expected a number in \[0, 1\]"):
        E.EKFConfig(ground_height_weight=-0.1)
