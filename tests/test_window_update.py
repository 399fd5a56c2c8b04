"""The fixed-lag window's compiled update against the general path it replaces.

:func:`flexforce.smoother.window_kernel.window_system` must give the blocks of
``assemble_split(linearize(...))`` (the same operations in the same order: measured equal to the
bit), and a whole fixed-lag run with the compiled update and read-out marginals must give the
general path's estimates and covariances (``FixedLagConfig(compiled=False)``).  Checked with and
without F/T fusion, robust sensor loss on and off, a missing and a saturated IMU axis, an
inactive contact in the window, the stream's first compiled window and a part of a stream.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flexforce.datasets.io.export import _csv_lines
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.factors.model import ModelConfig
from flexforce.smoother import FixedLagConfig, run_fixed_lag, window_kernel
from flexforce.smoother.fixed_lag import FixedLagSmoother
from flexforce.smoother.linearize import Trajectory, assemble_split, linearize
from flexforce.smoother.problem import NoiseRule, Problem
from flexforce.smoother.stream import FixedLagStream

TOL = 1e-10
"""Relative to each array's largest entry; the compiled path measures 0.0 (the same operations)."""


@pytest.fixture(scope="module")
def pitch():
    sc = Scenario.load("push-pitch")
    sc.duration = 1.5
    rec = Simulator(sc).run()
    # a missing gyro axis, a saturated accelerometer axis (with accel_range below) and one
    # contact lifted for a while: every branch of the families the window evaluates
    rec.gyro[100, 1] = np.nan
    rec.accel[120, 2] = 90.0
    rec.contact_active[140:160, 1] = False
    return rec


def _model(rec, use_ft):
    return dataclasses.replace(ModelConfig.from_recording(rec), use_ft=use_ft, accel_range=80.0)


def _close(a, b):
    scale = max(float(np.max(np.abs(b))), 1e-300)
    return float(np.max(np.abs(a - b))) / scale


def _compare_window(prob, fls, f, k1):
    """The compiled blocks of the window ``f .. k1-1`` (at the smoother's current ring contents)
    against linearize + assemble_split."""
    pos = np.arange(f, k1) % fls.cap
    lin = linearize(prob, Trajectory(fls.Rb[pos], fls.qb[pos], fls.Wb[pos], fls.eb[pos]), k0=f)
    ref = assemble_split(lin, len(pos), prob.state_dim, skip_first_unary=True)
    m, D, nc = len(pos), prob.state_dim, prob.nc
    U, gU, Fw, gF = np.empty((m, D, D)), np.empty((m, D)), np.empty((m, D, D)), np.empty((m, D))
    B, weights = np.empty((m - 1, D, D)), np.full((m, 1 + nc, 2), np.nan)
    caps = np.full((m, 1 + nc, 2), np.inf)
    fams = ["imu"] + [f"ft/{i}" for i in range(nc)]
    for j, fam in enumerate(fams):
        if prob.weight_cap and fam in prob.weight_cap:
            caps[:, j] = prob.weight_cap[fam][f - prob.offset:k1 - prob.offset]
    cost = window_kernel.window_system(fls.Rb, fls.qb, fls.Wb, pos, f - prob.offset, True,
                                       *window_kernel.WindowProblem(prob).args, caps, U, gU, Fw, gF, B, weights)
    for name, got, want in zip(("U", "gU", "Fw", "gF", "B"), (U, gU, Fw, gF, B), ref):
        assert _close(got, want) <= TOL, name
    assert abs(cost - lin.cost) <= TOL * abs(lin.cost)
    assert set(lin.weights) == {fam for j, fam in enumerate(fams) if prob.sigmas.imu_robust is not None
                                and (j == 0 or prob.use_ft)}
    for j, fam in enumerate(fams):
        if fam in lin.weights:
            assert _close(weights[:, j], lin.weights[fam]) <= TOL, fam


@pytest.mark.parametrize("use_ft", [False, True])
@pytest.mark.parametrize("robust", [None, "log-tail", "huber", "cauchy"])
def test_window_system_equals_linearize_and_assemble(pitch, use_ft, robust):
    prob = Problem.build(pitch, _model(pitch, use_ft), NoiseRule(imu_robust=robust, imu_robust_k=2.0))
    prob.weight_cap = {}
    assert prob.imu_use[100, 1] == 0.0 and prob.imu_use[120, 5] == 0.0
    fls = FixedLagSmoother(prob, 0.1, relinearize=6, compiled=False)
    # windows: the first compiled one (f = 1), a missing and a saturated IMU axis, a lifted contact
    checks = {7: 1, 104: 98, 124: 118, 150: 144}
    for k in range(max(checks) + 1):
        if k in checks:
            f = checks[k]
            for j in range(f + 1, k):  # the update's retraction and prediction, as _update does
                p = j % fls.cap
                fls.Rb[p], fls.qb[p], fls.Wb[p], fls.eb[p] = fls._state(j)
                fls.dx[p] = 0.0
            p = k % fls.cap
            fls.Rb[p], fls.qb[p], fls.Wb[p], fls.eb[p] = fls._predict(k)
            fls.dx[p] = 0.0
            _compare_window(prob, fls, f, k + 1)
        fls.step()
    if robust is not None:
        assert np.min(prob.weight_cap["imu"]) < 1.0  # the caps took part


def test_window_system_on_a_part_of_a_stream(pitch):
    """A problem over a later part of the stream (offset > 0): the rows are the part's."""
    model = _model(pitch, True)
    first = Problem.build(pitch.slice(0, 60), model)
    part = Problem.build(pitch.slice(40, 200), model, part_of=first, offset=40)
    part.weight_cap = {"imu": np.full((part.n, 2), 0.5), **{f"ft/{i}": np.ones((part.n, 2)) for i in range(part.nc)}}
    fls = FixedLagSmoother(first, 0.1, sink=lambda *row: None)
    for _ in range(50):
        fls.step()
    fls.set_problem(part)
    for _ in range(20):
        fls.step()
    _compare_window(part, fls, 63, 70)


def _run_both(run):
    """``run(compiled)`` with the compiled path, then with the general one."""
    return run(True), run(False)


def _assert_same(fast, ref):
    for name in ("R", "t", "w", "v", "dw", "a", "wrench"):
        assert _close(getattr(fast, name), getattr(ref, name)) <= TOL, name
    if ref.cov is not None:
        scale = np.abs(ref.cov).max(axis=(1, 2), keepdims=True)
        assert np.max(np.abs(fast.cov - ref.cov) / scale) <= TOL


@pytest.mark.parametrize("use_ft, robust, block", [(False, "log-tail", 1), (True, "log-tail", 1), (True, None, 1),
                                                   (False, "log-tail", 4)])
def test_fixed_lag_compiled_equals_general(pitch, use_ft, robust, block):
    model = _model(pitch, use_ft)
    config = FixedLagConfig(lag=0.2, block=block, rule=NoiseRule(imu_robust=robust, imu_robust_k=2.0))
    fast, ref = _run_both(lambda compiled: run_fixed_lag(pitch, model, config, compiled=compiled))
    _assert_same(fast, ref)


def test_stream_compiled_equals_general(pitch):
    model = _model(pitch, True)

    def stream(compiled):
        s = FixedLagStream(model, FixedLagConfig(lag=0.2, compiled=compiled))
        ests = [e for e in (s.push(pitch.slice(a, min(a + 37, pitch.n))) for a in range(0, pitch.n, 37))
                if e is not None]
        ests.append(s.finish())
        return ests

    fast, ref = _run_both(stream)
    assert len(fast) == len(ref)
    for a, b in zip(fast, ref):
        _assert_same(a, b)


def test_csv_lines_hold_the_estimate(pitch):
    """The CSV rows formatted at once read back as the estimate's values to 1e-14 (NaN, -0.0,
    infinities kept; the stamps exact)."""
    est = run_fixed_lag(pitch.slice(0, 60), _model(pitch, False), lag=0.1)
    est.wrench[3, 0, 1] = np.nan
    est.wrench[4, 1, 2] = -0.0
    est.t[5, 0] = 1e-300
    est.cov[6, 0, 0] = np.inf
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_matrix(est.R)
    time_s = (est.t_ns - est.t_ns[0]).astype(float) * 1e-9
    parts = [time_s[:, None], est.t_ns[:, None].astype(float), est.t, rot.as_quat(), rot.as_rotvec(), est.w,
             est.v, est.dw, est.a, est.wrench.reshape(est.n, -1), est.total_wrench, est.cop, est.state_std()]
    if est.cop_cov is not None:
        parts.append(np.sqrt(np.maximum(np.diagonal(est.cop_cov, axis1=1, axis2=2), 0.0)))
    with np.errstate(invalid="ignore"):
        expected = np.concatenate(parts, axis=1)
        lines = "".join(_csv_lines(est)).splitlines()
    cells = [line.split(",") for line in lines]
    assert [int(c[1]) for c in cells] == est.t_ns.tolist()
    got = np.array([[float(x) for x in c] for c in cells])
    assert got.shape == expected.shape
    same_kind = (np.isnan(got) == np.isnan(expected)) & (np.isinf(got) == np.isinf(expected))
    assert same_kind.all() and np.signbit(got[4, 32]) and got[4, 32] == 0.0 and got[6, 45] == np.inf
    finite = np.isfinite(expected) & (expected != 0.0)
    finite[:, 1] = False
    assert np.max(np.abs(got[finite] - expected[finite]) / np.abs(expected[finite])) <= 1e-14
