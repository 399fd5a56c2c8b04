"""GTSAM's legged estimators as peers (flexforce.compare.peers): driven from a simulated Recording,
their tilt against the truth, their rows in a comparison, and the errors of bad inputs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flexforce.compare.peers import PEERS, PeerConfig, feet_in_imu, run_gtsam_legged, run_peer
from flexforce.compare.reports.comparison import timings
from flexforce.compare.runner import compare
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.errors import ConfigError, DataError

SKIP_S = 0.5
"""Seconds left out at the start (the filter converging from the identity flexibility)."""
TILT_BOUND = 0.004
"""RMSE of the invariant EKF's tilt against the truth on 1 s of ``push-pitch`` after SKIP_S, rad: measured
2.0e-3 (the true tilt reaches 13.7e-3), doubled."""


@pytest.fixture(scope="module")
def rec():
    sc = Scenario.load("push-pitch")
    sc.duration = 1.0
    return Simulator(sc).run()


def tilt_error(R: np.ndarray, R_true: np.ndarray) -> np.ndarray:
    """(N,) angle between the estimated and the true world vertical seen from the local frame, rad:
    ``arccos(R^T e_z . R_true^T e_z)``, the rows z of the flexibilities."""
    return np.arccos(np.clip(np.sum(R[:, 2, :] * R_true[:, 2, :], axis=1), -1.0, 1.0))


def test_invariant_ekf_tilt_is_bounded(rec):
    est = run_gtsam_legged(rec)
    assert est.estimator == "gtsam_invariant_ekf"
    assert est.R.shape == (rec.n, 3, 3) and np.all(np.isfinite(est.R)) and np.all(np.isfinite(est.t))
    assert np.all(np.isfinite(est.w)) and np.all(np.isfinite(est.v))
    assert np.all(np.isnan(est.wrench)) and np.all(np.isnan(est.a))
    assert est.time_per_step is not None and est.time_per_step.shape == (rec.n,) and est.total_time > 0
    err = tilt_error(est.R, rec.truth.R)[rec.time >= SKIP_S]
    rmse = float(np.sqrt(np.mean(err**2)))
    assert rmse < TILT_BOUND
    # the IMU's world pose the estimate implies is a rotation: R local_R_imu
    world_R_imu = np.einsum("nij,njk->nik", est.R, rec.imu_R)
    np.testing.assert_allclose(np.einsum("nji,njk->nik", world_R_imu, world_R_imu), np.tile(np.eye(3), (rec.n, 1, 1)),
                               atol=1e-9)


def test_feet_in_imu_frame(rec):
    feet = feet_in_imu(rec)
    k, c = rec.n // 2, 0
    np.testing.assert_allclose(rec.imu_R[k] @ feet[k, c] + rec.imu_p[k], rec.contact_p[k, c], atol=1e-12)


def test_compare_adds_peer_rows_only(rec):
    plain = compare(rec, estimators=("ekf",), crb=False, peers=False).summary()
    comp = compare(rec, estimators=("ekf",), crb=False)
    summary = comp.summary()
    assert set(summary) - set(plain) == {"peers"}
    assert list(summary["peers"]) == ["gtsam_invariant_ekf"]
    row = summary["peers"]["gtsam_invariant_ekf"]
    assert row["kind"] == "peer" and row["rmse"]["rotation_rad"] is not None
    assert row["rmse"]["force_N"] is None and row["per_contact"] == {}
    assert row["per_phase"]["all"]["rmse"]["rotation_rad"] is not None
    assert timings(comp)["peers"]["gtsam_invariant_ekf"]["time_per_step_s"]["median"] > 0  # timings.json's
    assert {k: v for k, v in summary.items() if k != "peers"}.keys() == plain.keys()
    assert summary["baselines"] == plain["baselines"]


def test_every_peer_runs(rec):
    short = rec.slice(0, 60)
    for name in PEERS:
        est = run_peer(name, short, lag_s=0.2)
        assert np.all(np.isfinite(est.R))


def test_bad_inputs_raise(rec):
    with pytest.raises(ConfigError, match="kind"):
        run_gtsam_legged(rec, kind="ukf")
    with pytest.raises(ConfigError, match="PeerConfig"):
        run_gtsam_legged(rec, config={"lag_s": 1.0})
    with pytest.raises(ConfigError, match="lag_s"):
        PeerConfig(lag_s=0.0)
    with pytest.raises(ConfigError, match="unknown peer"):
        run_peer("gtsam-ukf", rec)
    with pytest.raises(ConfigError, match="unknown PeerConfig option"):
        run_peer("gtsam-invariant-ekf", rec, lag=1.0)
    contact_p = rec.contact_p.copy()
    k = int(np.flatnonzero(rec.contact_active[:, 0])[5])
    contact_p[k, 0] = np.nan
    with pytest.raises(DataError, match=f"'contact_p' is not finite .* at sample {k}"):
        run_gtsam_legged(dataclasses.replace(rec, contact_p=contact_p))


def test_peer_rows_show_the_aligned_tilt():
    from flexforce.compare.reports.comparison import _peer_rows

    summary = {"peers": {"gtsam_fixed_lag": {"rmse": {"rotation_rad": 0.0143}, "extra": {"tilt_aligned_rad": 0.0135},
                                             "per_phase": {}},
                         "gtsam_invariant_ekf": {"rmse": {"rotation_rad": 0.0143}, "per_phase": {}}}}
    rows = {r["key"]: r for r in _peer_rows(summary)}
    assert rows["gtsam_fixed_lag"]["tilt"] == "14.3" and rows["gtsam_fixed_lag"]["aligned"] == "13.5"
    assert rows["gtsam_invariant_ekf"]["aligned"] == "–"  # no motion capture, no aligned tilt
