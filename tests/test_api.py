"""The public API: ``import flexforce as ff`` (its names, loaded lazily), the three ways to a
Recording (a scenario, a bag, plain arrays) and the errors a user meets first."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

import flexforce as ff
from flexforce.datasets.io.bagio import save_recording
from flexforce.datasets.recording import Recording
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator

ARRAYS = [f.name for f in dataclasses.fields(Recording)
          if f.name not in ("t_ns", "robot", "contact_names", "mass", "truth", "gravity", "meta")]
"""The from_arrays keywords besides the time stamps and the scalars."""


@pytest.fixture(scope="module")
def rec() -> Recording:
    return ff.simulate("stand", seed=3, duration=0.5)


def _kwargs(rec: Recording) -> dict:
    return {"robot": rec.robot, "contact_names": rec.contact_names, "mass": rec.mass, "gravity": rec.gravity,
            "meta": rec.meta, **{name: getattr(rec, name) for name in ARRAYS}}


def _assert_same(a: Recording, b: Recording) -> None:
    for f in dataclasses.fields(Recording):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), f.name
        elif isinstance(x, dict) and f.name == "mocap":
            assert x.keys() == y.keys() and all(np.array_equal(x[k], y[k], equal_nan=True) for k in x), f.name
        elif f.name != "truth":
            assert x == y, f.name


# ----------------------------------------------------------------------------------------------
# The names
# ----------------------------------------------------------------------------------------------


def test_every_public_name_resolves_and_is_documented():
    assert 15 <= len(ff.__all__) <= 30, ff.__all__
    for name in ff.__all__:
        value = getattr(ff, name)
        assert value is not None, name
        if callable(value):
            assert value.__doc__, f"flexforce.{name} has no docstring"
    assert callable(ff.diagnose) and ff.diagnose.__name__ == "diagnose"
    assert issubclass(ff.BagError, ff.DataError) and issubclass(ff.DataError, ff.FlexforceError)
    assert "stand" not in ff.EFFECTS and "external-wrench" in ff.EFFECTS
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        ff.nope  # noqa: B018


def test_import_flexforce_is_quick_and_loads_no_numerics():
    """The names load on first use: ``import flexforce`` (for its errors, say) loads neither numpy
    nor the compiled libraries."""
    code = ("import sys, flexforce; heavy = {'numpy', 'pinocchio', 'gtsam', 'numba'} & set(sys.modules); "
            "assert not heavy, heavy; flexforce.Recording; assert 'numpy' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


# ----------------------------------------------------------------------------------------------
# From arrays
# ----------------------------------------------------------------------------------------------


def test_a_recording_from_a_simulated_ones_arrays_is_the_same_recording(rec):
    again = Recording.from_arrays(rec.t_ns, **_kwargs(rec))
    _assert_same(rec, again)
    assert again.truth is None
    est_a = ff.run_estimator("ekf", rec)
    est_b = ff.run_estimator("ekf", again)
    assert np.array_equal(est_a.wrench, est_b.wrench) and np.array_equal(est_a.R, est_b.R)


def test_from_arrays_takes_lists_and_other_integer_types(rec):
    kwargs = _kwargs(rec)
    kwargs["com"] = rec.com.tolist()
    kwargs["contact_active"] = rec.contact_active.astype(np.uint8)
    again = Recording.from_arrays(rec.t_ns.astype(np.uint64), **kwargs)
    _assert_same(rec, again)


def test_float_seconds_are_refused_with_the_expected_unit(rec):
    with pytest.raises(ff.DataError, match=r"t_ns has dtype float64, values 0 to 0\.5; expected integer "
                                           r"nanoseconds \(int64\), e\.g\. np\.round\(t_seconds \* 1e9\)"):
        Recording.from_arrays(rec.time, **_kwargs(rec))


@pytest.mark.parametrize("step", [1, 5, 5_000], ids=["s", "ms", "us"])
def test_integer_seconds_milliseconds_or_microseconds_are_refused(rec, step):
    """Whole seconds (steps of 1), 200 Hz in milliseconds (5) or in microseconds (5000)."""
    t = np.arange(rec.n, dtype=np.int64) * step
    with pytest.raises(ff.DataError, match=r"t_ns steps by .* ns \(median\).*look like seconds, milliseconds or "
                                           r"microseconds; expected integer nanoseconds"):
        Recording.from_arrays(t, **_kwargs(rec))


def test_from_arrays_validates_time_order_and_shapes(rec):
    t = rec.t_ns.copy()
    t[10] = t[9]
    with pytest.raises(ff.DataError, match="time stamps do not increase at sample 10"):
        Recording.from_arrays(t, **_kwargs(rec))
    kwargs = _kwargs(rec)
    kwargs["gyro"] = rec.gyro[:, :2]
    with pytest.raises(ff.DataError, match=rf"field 'gyro' has shape \({rec.n}, 2\); expected \({rec.n}, 3\)"):
        Recording.from_arrays(rec.t_ns, **kwargs)
    with pytest.raises(ff.DataError, match=rf"t_ns has shape \({rec.n}, 1\); expected \(N,\) integer nanoseconds"):
        Recording.from_arrays(rec.t_ns[:, None], **_kwargs(rec))


# ----------------------------------------------------------------------------------------------
# From a scenario and from a bag
# ----------------------------------------------------------------------------------------------


def test_simulate_is_the_simulator_with_the_scenarios_values_replaced(rec):
    scenario = Scenario.load("stand")
    scenario.seed, scenario.duration = 3, 0.5
    direct = Simulator(scenario).run()
    _assert_same(rec, direct)
    assert np.array_equal(rec.truth.R, direct.truth.R) and np.array_equal(rec.truth.wrench, direct.truth.wrench)
    assert rec.n == 101 and rec.meta["scenario"]["seed"] == 3


def test_simulate_refuses_what_the_scenario_refuses():
    with pytest.raises(ff.ConfigError, match="unknown scenario 'nope'"):
        ff.simulate("nope")
    with pytest.raises(ff.ConfigError, match="duration, rate and sim_rate must be positive"):
        ff.simulate("stand", duration=-1.0)


def test_load_recording_reads_a_flexforce_bag_back(rec, tmp_path):
    path = save_recording(rec, tmp_path / "stand.mcap")
    again = ff.load_recording(path)
    assert np.array_equal(again.t_ns, rec.t_ns) and np.array_equal(again.gyro, rec.gyro)
    with pytest.raises(ff.BagError, match="does not exist"):
        ff.load_recording(tmp_path / "missing.mcap")


# ----------------------------------------------------------------------------------------------
# Errors a user meets first
# ----------------------------------------------------------------------------------------------


def test_to_gtsam_without_a_model_names_what_it_needs(rec):
    from flexforce.smoother import to_gtsam

    with pytest.raises(ff.ConfigError, match=r"to_gtsam needs the recording's model, a ModelConfig .*got None"):
        to_gtsam(rec, None)
