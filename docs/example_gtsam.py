"""Adding your own factor to flexforce's graph in gtsam: a motion-capture marker.

The flexible-contact problem of a recording is exported as a ``gtsam.NonlinearFactorGraph`` with
its initial ``gtsam.Values`` (``flexforce.smoother.to_gtsam``); the keys are named by the
returned ``GtsamKeys`` (``keys.pose(k)`` is the flexibility ``Pose3`` of step ``k``, local frame
-> world).  Here a motion-capture system sees a marker on the IMU housing during the push of the
``push-pitch`` scenario, 2 mm further forward than the model alone puts it.  A ``CustomFactor``
per seen sample pulls the marker's world position, ``p = R p_l + t`` (``p_l`` the marker in the
local frame), towards the reading; Gauss-Newton (:func:`optimize`, iterated from Python: see
there why) optimises both graphs and ``flexforce.smoother.from_gtsam`` reads the results back as
Estimates.  Both optimisations take about a second on this 1.3 s segment (261 steps).

Expected: the marker moves forward (+x) by a fraction of the 2 mm (the springs, the IMU and the
dynamics hold it back), and far less along y and z.

Run: ``python docs/example_gtsam.py``.
"""

from __future__ import annotations

import gtsam
import numpy as np

from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator
from flexforce.factors.model import ModelConfig
from flexforce.smoother import from_gtsam, to_gtsam


def skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def marker_factor(pose_key: int, local_point, measured, noise) -> gtsam.CustomFactor:
    """Motion capture of a marker at ``local_point`` (local frame): ``R p_l + t - measured`` (m).

    Jacobian with respect to gtsam's Pose3 tangent (body-frame rotation, then translation):
    ``d(R exp(phi) p_l)/d phi = -R [p_l]x``, ``d(t + R rho)/d rho = R``.
    """
    local_point = np.asarray(local_point, dtype=float)
    measured = np.asarray(measured, dtype=float)

    def error_func(this: gtsam.CustomFactor, values: gtsam.Values, jacobians):
        pose = values.atPose3(this.keys()[0])
        R = pose.rotation().matrix()
        error = R @ local_point + pose.translation() - measured
        if jacobians is not None:
            jacobians[0] = np.hstack([-R @ skew(local_point), R])
        return error

    return gtsam.CustomFactor(noise, gtsam.KeyVector([pose_key]), error_func)


def optimize(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, rel_tol: float = 1e-8,
             max_iterations: int = 50) -> gtsam.Values:
    """Gauss-Newton iterated from Python, each step halved until it lowers the error (at most 10
    times); stops when the error changes by less than ``rel_tol`` relatively.

    Why not ``gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()``: a C++
    optimizer evaluates the graph on Values it owns, and every call of a Python ``CustomFactor``
    (flexforce's factors and the marker below) then receives a copy of all those Values, so one
    iteration costs (number of factors) x (number of variables), quadratic in the recording's
    length (on this 1.3 s graph LM's 7 iterations take 3 s; on 8 s, minutes).  Iterated from
    Python, the Values are a Python object passed by reference: an iteration is one
    linearisation and one sparse solve (0.05 s here), linear in the length.
    """
    values, error = initial, graph.error(initial)
    for _ in range(max_iterations):
        delta = graph.linearize(values).optimize()
        for _ in range(10):
            trial = values.retract(delta)
            new_error = graph.error(trial)
            if new_error <= error:
                break
            delta = delta.scale(0.5)
        else:
            return values  # no step lowers the error: at the optimum to numerical precision
        values, done = trial, error - new_error <= rel_tol * error
        error = new_error
        if done:
            break
    return values


def main(duration: float = 1.3, offset=(0.002, 0.0, 0.0), seen=(1.0, 1.2), sigma: float = 5e-4,
         verbose: bool = True) -> dict:
    """Returns the marker's mean shift (m, world axes) over the seen samples and elsewhere."""
    scenario = Scenario.load("push-pitch")
    scenario.duration = duration
    rec = Simulator(scenario).run()
    model = ModelConfig.from_recording(rec)

    graph, initial, keys = to_gtsam(rec, model)
    if verbose:
        print(keys.describe())
    optimum = optimize(graph, initial)
    before = from_gtsam(optimum, keys)

    # The marker: on the IMU housing (the IMU's position in the local frame, per step).
    def marker(est, k):
        return est.R[k] @ rec.imu_p[k] + est.t[k]

    t = rec.time
    steps = np.flatnonzero((t >= seen[0]) & (t <= seen[1]))
    noise = gtsam.noiseModel.Isotropic.Sigma(3, sigma)
    with_mocap = gtsam.NonlinearFactorGraph(graph)
    for k in steps:
        reading = marker(before, k) + np.asarray(offset)  # what the motion capture reports
        with_mocap.add(marker_factor(keys.pose(k), rec.imu_p[k], reading, noise))
    after = from_gtsam(optimize(with_mocap, optimum), keys)  # warm start: the optimum without it

    shift = np.array([marker(after, k) - marker(before, k) for k in range(rec.n)])
    far = np.flatnonzero(np.abs(t - 0.5 * (seen[0] + seen[1])) > 0.5)
    result = {"seen_steps": int(steps.size), "shift_seen_m": shift[steps].mean(axis=0),
              "shift_far_m": np.abs(shift[far]).max(axis=0),
              "force_change_N": float(np.abs(after.total_wrench - before.total_wrench)[steps, :3].max())}
    if verbose:
        print(f"motion capture on {steps.size} samples, {1e3 * np.asarray(offset)} mm from the estimate")
        print("mean marker shift where seen (mm):", np.round(1e3 * result["shift_seen_m"], 3))
        print("largest shift 0.5 s away from it (mm):", np.round(1e3 * result["shift_far_m"], 4))
        print(f"largest change of the total contact force where seen: {result['force_change_N']:.1f} N")
    return result


if __name__ == "__main__":
    main()
