"""Estimators in a world that is not their model: the mismatched cases of the simulator.

The estimators assume the robot configuration (noise densities, and until footholds are
estimated, a contact's rest at its local placement); the simulated world here departs from it:
- ``noisy``: ambient disturbance 3x its default level and an IMU 2x noisier than the data sheet;
- ``floor``: the default touch-down (the landing foot's spring starts unloaded where it reaches
  the floor), against ``deflected``, the estimators' own convention.

Bounds are the errors measured on these seeds (stated beside each) with a margin of 1.5x for
another platform's arithmetic and library versions; the NEES is reported as it is -- the models
are wrong on purpose, so it is expected above its consistent band, and the test checks that it
says so rather than forcing it into the band.
"""

from __future__ import annotations

import numpy as np
import pytest

from flexforce.compare.estimators import run_estimator
from flexforce.compare.metrics import chi2_mean_bounds, nees_series, state_error
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator

SKIP = 0.5  # s, start-up excluded from the figures
MARGIN = 1.5


def _simulate(name: str, duration: float, **overrides):
    sc = Scenario.load(name)
    sc.duration = duration
    # no slow IMU bias drift: an effect for the diagnostics, not part of these cases
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0, **overrides.pop("imu_noise", {})}
    for key, value in overrides.items():
        setattr(sc, key, value)
    return Simulator(sc).run()


def _figures(rec, est) -> dict:
    keep = rec.time >= SKIP
    e = state_error(est, rec.truth)
    tilt = np.degrees(np.linalg.norm(e[keep, :2], axis=1))
    force = np.linalg.norm(est.total_wrench[keep, :3] - rec.truth.total_wrench[keep, :3], axis=1)
    ns_all = nees_series(est, rec.truth)
    assert ns_all is not None  # the estimators report a covariance
    ns = ns_all[keep]
    return {"tilt_deg": float(np.sqrt(np.mean(tilt**2))), "force_N": float(np.sqrt(np.mean(force**2))),
            "nees": float(np.nanmean(ns)), "nees_band": chi2_mean_bounds(18, int(np.isfinite(ns).sum()))}


@pytest.fixture(scope="module")
def sway():
    out = {}
    for case, over in (("matched", {}), ("noisy", {"ambient": {"scale": 3.0}, "imu_noise": {"scale": 2.0}})):
        rec = _simulate("sway", 4.0, **over)
        out[case] = {name: _figures(rec, run_estimator(name, rec)) for name in ("ekf", "batch")}
    return out


@pytest.fixture(scope="module")
def weight_shift():
    out = {}
    for case in ("deflected", "floor"):
        rec = _simulate("weight-shift", 8.0, touchdown=case)
        out[case] = {name: _figures(rec, run_estimator(name, rec)) for name in ("ekf", "batch")}
    return out


# measured on sway, 4 s, seed 0: (tilt deg, force N)
NOISY_MEASURED = {"ekf": (0.0666, 3.19), "batch": (0.0494, 2.33)}


@pytest.mark.parametrize("name", ["ekf", "batch"])
def test_noisier_world_than_the_model(sway, name):
    noisy, matched = sway["noisy"][name], sway["matched"][name]
    print(f"\n{name}: matched {matched}\n{name}: ambient x3, IMU x2 {noisy}")
    tilt, force = NOISY_MEASURED[name]
    assert noisy["tilt_deg"] < MARGIN * tilt
    assert noisy["force_N"] < MARGIN * force
    # the errors grow with the world's noise (measured 2.8x / 3.0x tilt, 2.9x / 2.7x force)
    assert noisy["tilt_deg"] > 1.5 * matched["tilt_deg"]
    assert noisy["force_N"] > 1.5 * matched["force_N"]
    # and the NEES says the covariance is too small: above its band, several times the matched
    # one (measured 127 / 136 against 16.8 / 20.0, band 17.6-18.4)
    assert noisy["nees"] > noisy["nees_band"][1]
    assert noisy["nees"] > 3.0 * matched["nees"]


# measured on weight-shift, 8 s, seed 0: (tilt deg, force N) with the floor touch-down
FLOOR_MEASURED = {"ekf": (0.643, 14.9), "batch": (0.242, 16.4)}


@pytest.mark.parametrize("name", ["ekf", "batch"])
def test_touchdown_on_the_floor_against_the_models_convention(weight_shift, name):
    """The estimators anchor a landing foot's spring at its local placement (the ``deflected``
    world); on the floor the foot lands unloaded, touches before its planned landing and leaves
    after its planned lift: the estimates are an order of magnitude worse, which is what footholds
    as estimated variables repair (tests/test_foothold_variables.py)."""
    floor, own = weight_shift["floor"][name], weight_shift["deflected"][name]
    print(f"\n{name}: deflected {own}\n{name}: floor {floor}")
    tilt, force = FLOOR_MEASURED[name]
    assert floor["tilt_deg"] < MARGIN * tilt
    assert floor["force_N"] < MARGIN * force
    # measured 18x / 12x tilt, 3.6x / 9.5x force against the model's own convention
    assert floor["tilt_deg"] > 5.0 * own["tilt_deg"]
    assert floor["force_N"] > 2.0 * own["force_N"]
    assert floor["nees"] > 100.0 * floor["nees_band"][1]  # measured 2.3e4 / 1.05e4
