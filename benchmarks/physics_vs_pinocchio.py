"""Hold the hand-written physics against the pinocchio simulator on every built-in scenario.

For each scenario and robot, simulate without noise and evaluate on the ground truth:
- the Newton-Euler residual (eq. 16, 23, corrections 2-4), relative to m g and m g h_CoM;
- the contact law (eq. 6-12) against the simulator's spring wrenches, N;
- the IMU model (eq. 26-28) against pinocchio's frame kinematics, rad/s and m/s^2.

Usage: python benchmarks/physics_vs_pinocchio.py [--robots romeo talos] [--scenarios ...]
Writes JSON to stdout and to benchmarks/results/physics_vs_pinocchio.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from flexforce.datasets.scenario import Scenario, builtin_scenarios
from flexforce.datasets.simulator import Simulator
from flexforce.factors import physics as ph


def check(robot: str, name: str) -> dict:
    sc = Scenario.load(name)
    sc.robot = robot
    sim = Simulator(sc, noise=False)
    t0 = time.perf_counter()
    rec = sim.run()
    elapsed = time.perf_counter() - t0
    tr = rec.truth
    assert tr is not None  # simulated
    m, g, h = rec.mass, rec.gravity, rec.com[0, 2]
    ne, cw, gy, ac = [], [], [], []
    for k in range(rec.n):
        r = ph.newton_euler_residual(tr.R[k], tr.t[k], tr.w[k], tr.v[k], tr.dw[k], tr.a[k],
                                     tr.total_wrench[k] + tr.disturbance_wrench[k], rec.inputs(k), g)
        ne.append(r)
        for i in rec.active_contacts(k):
            # The simulator's true spring of contact i (Simulator.contact_params became Simulator.springs).
            sp = sim.springs[i]
            wr = ph.contact_wrench(tr.R[k], tr.t[k], tr.w[k], tr.v[k], rec.contact_p[k, i], rec.contact_R[k, i],
                                   ph.ContactParams(sp.K_fs, sp.K_fd, sp.K_ts, sp.K_td, sp.beta_f, sp.beta_t))
            cw.append(np.abs(wr - tr.wrench[k, i]).max())
        y = ph.imu_readings(tr.R[k], tr.t[k], tr.w[k], tr.v[k], tr.dw[k], tr.a[k], rec.imu(k), g)
        gy.append(np.abs(y[:3] - rec.gyro[k]).max())
        ac.append(np.abs(y[3:] - rec.accel[k]).max())
    ne = np.abs(np.array(ne))
    return {
        "robot": robot, "scenario": name, "samples": rec.n, "simulation_s": round(elapsed, 2),
        "newton_euler_force_max_over_mg": float(ne[:, :3].max() / (m * g)),
        "newton_euler_moment_max_over_mgh": float(ne[:, 3:].max() / (m * g * h)),
        "contact_law_max_N": float(max(cw)),
        "imu_gyro_max_rad_s": float(max(gy)),
        "imu_accel_max_m_s2": float(max(ac)),
        "max_vertical_force_N": float(tr.total_wrench[:, 2].max()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", nargs="+", default=["romeo", "talos"])
    parser.add_argument("--scenarios", nargs="+", default=builtin_scenarios())
    args = parser.parse_args()
    rows = [check(robot, name) for robot in args.robots for name in args.scenarios]
    out = {"benchmark": "physics_vs_pinocchio", "rows": rows,
           "worst": {k: max(r[k] for r in rows) for k in rows[0] if k.endswith(("_mg", "_mgh", "_N", "_s2", "_rad_s"))
                     and k != "max_vertical_force_N"}}
    text = json.dumps(out, indent=2)
    print(text)
    path = Path(__file__).resolve().parent / "results" / "physics_vs_pinocchio.json"
    path.parent.mkdir(exist_ok=True)
    path.write_text(text + "\n")


if __name__ == "__main__":
    main()
