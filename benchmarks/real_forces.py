"""Benchmark: the estimators' contact forces and tilt on the real iCub recordings, beside the baselines.

    python benchmarks/real_forces.py [--data ../shared/data/icub] [--output benchmarks/results/real_forces.json]

Runs ``flexforce compare <recording> --robot icub-identified --peers`` (the default estimators, the
baselines without estimation, GTSAM's legged estimators as peers) on the iCub walk
(``icub-walk-12s``, single and double support) and the CoM sway (``icub-com-sinusoid-20s.bag``,
double support throughout), and keeps, per estimator and baseline, against the F/T sensors and
Vicon (references, not ground truth):

- ``foot_vertical_force_N``, ``total_vertical_force_N``: RMSE of each foot's normal force and of
  their sum, raw and low-passed (``lowpass_5Hz``: zero-phase Butterworth of both the estimate and
  the reference, summary.json's ``definitions``);
- ``tilt_mrad``: RMSE of the base tilt against Vicon; ``tilt_aligned_mrad``, the same once the
  row's constant tilt offset (``tilt_offset_mrad``, the mean of the estimated minus the Vicon
  vertical in the base frame: the markers' frame, the Vicon world's vertical) is taken out
  (:func:`flexforce.compare.metrics.aligned_tilt`);
- ``per_phase``: the same per contact phase (single support, double support, transitions within
  ±50 ms of a contact switch; a phase without samples is left out);
- ``violations``: counts and fractions of negative normal forces, of forces outside the friction
  cone and of CoPs outside the sole (the robot config's ``sole`` of each contact), over the samples
  in contact;
- ``force_band``: how often each contact's normal-force band (+-2 sigma, from the estimator's
  covariance) holds the F/T (nominal 95 %), overall and per phase, the RMS of the error over the
  band's sigma and the median sigma (:func:`flexforce.compare.metrics.force_band`); and ``model``:
  the same with the model band (:func:`flexforce.compare.band.model_band`, the robot's
  ``[model_uncertainty]``), with its variance factor and the force change per parameter;

GTSAM's legged estimators (``peers``: IMU and leg kinematics, no forces) keep their tilt, per
phase too, and their time per step; and each recording's ``headline``: the sentences naming the
best estimator per quantity against the best baseline (:func:`flexforce.compare.runner.headline`);
``footholds_estimated``: the smoothers' rows again with ``--footholds``; and ``noise_calibrated``:
the batch smoother's row with ``--calibrate-noise`` (its IMU noise scaled by its own residuals'
RMS where above 3 sigma); ``reference_checks``: the F/T held against the rigid robot's dynamics,
no estimate involved (:func:`flexforce.compare.metrics.reference_checks`: the unloaded feet's
readings, the F/T sum against ``m (g + c_z'')``).
Writes the JSON record to
``benchmarks/results/real_forces.json`` and prints it.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from flexforce.cli import main as cli_main
from flexforce.compare.metrics import lowpass_key
from flexforce.compare.runner import headline

HERE = Path(__file__).resolve().parent
DATA = HERE.parents[1] / "shared" / "data" / "icub"
RECORDINGS = {"walk": "icub-walk-12s", "sway": "icub-com-sinusoid-20s.bag"}
"""Record key -> the recording under ``--data``."""
ROBOT = "icub-identified"


def _aligned(m: dict) -> dict:
    """A row's tilt with its constant taken out (summary.json's ``extra``, mrad)."""
    extra = m.get("extra") or {}
    aligned, offset = extra.get("tilt_aligned_rad"), extra.get("tilt_offset_rad")
    return {"tilt_aligned_mrad": None if aligned is None else aligned * 1e3,
            "tilt_offset_mrad": None if offset is None else [x * 1e3 for x in offset]}


def _row(m: dict) -> dict:
    """The figures of one summary row (summary.json's estimator or baseline entry)."""
    lp = lowpass_key()
    short = lp.replace("rmse_", "")

    def forces(block: dict) -> dict:
        return {"foot_vertical_force_N": block.get("foot_vertical_force_N"),
                "total_vertical_force_N": block.get("total_vertical_force_N")}

    phases = m.get("per_phase") or {}
    whole = phases.get("all") or {}
    tilt = (m.get("rmse") or {}).get("rotation_rad")
    out: dict[str, Any] = {"kind": m.get("kind"), **forces(whole.get("rmse") or {}), short: forces(whole.get(lp) or {}),
           "tilt_mrad": None if tilt is None else tilt * 1e3, **_aligned(m), "per_phase": {}}
    for phase, d in phases.items():
        if phase == "all" or not d.get("samples"):
            continue
        rot = (d.get("rmse") or {}).get("rotation_rad")
        out["per_phase"][phase] = {"samples": d["samples"], **forces(d.get("rmse") or {}),
                                   "tilt_mrad": None if rot is None else rot * 1e3, short: forces(d.get(lp) or {})}
    v = m.get("violations") or {}
    out["violations"] = {"samples_in_contact": v.get("samples_in_contact"), "friction_mu": v.get("friction_mu"),
                         **{check: {"count": (v.get(check) or {}).get("count"),
                                    "fraction": (v.get(check) or {}).get("fraction")}
                            for check in ("negative_normal", "friction_cone", "cop_outside_sole")}}
    skipped = (v.get("cop_outside_sole") or {}).get("skipped")
    if skipped:
        out["violations"]["cop_outside_sole"] = {"skipped": skipped}
    law = v.get("contact_law") or {}
    if law:  # the contact law's wrenches before the estimator limited them
        out["violations"]["contact_law"] = {check: (law.get(check) or {}).get("count")
                                            for check in ("negative_normal", "friction_cone", "cop_outside_sole")}
    band = m.get("force_band") or {}
    if band.get("samples"):
        out["force_band"] = {k: band.get(k) for k in ("samples", "level", "coverage", "z_rms", "median_sigma_N")}
        out["force_band"]["per_phase"] = {ph: {k: d.get(k) for k in ("samples", "coverage", "z_rms")}
                                          for ph, d in (band.get("per_phase") or {}).items()
                                          if ph != "all" and d.get("samples")}
        model = band.get("model") or {}
        if model.get("samples"):
            out["force_band"]["model"] = {
                **{k: model.get(k) for k in ("coverage", "z_rms", "median_sigma_N", "variance_factor", "components_N")},
                "per_phase": {ph: {k: d.get(k) for k in ("samples", "coverage", "z_rms")}
                              for ph, d in (model.get("per_phase") or {}).items() if ph != "all" and d.get("samples")}}
    return out


def _peer_row(m: dict, timing: dict) -> dict:
    """The figures of one peer row (summary.json's ``peers`` entry): tilt, per phase, and time per step
    (``timing``: the row's entry of timings.json)."""
    tilt = (m.get("rmse") or {}).get("rotation_rad")
    steps = timing.get("time_per_step_s") or {}
    out: dict[str, Any] = {"kind": m.get("kind"), "tilt_mrad": None if tilt is None else tilt * 1e3, **_aligned(m),
                           "per_phase": {},
           "time_per_step_us": {k: None if v is None else v * 1e6 for k, v in steps.items()},
           "total_time_s": timing.get("total_time_s")}
    for phase, d in (m.get("per_phase") or {}).items():
        if phase == "all" or not d.get("samples"):
            continue
        rot = (d.get("rmse") or {}).get("rotation_rad")
        out["per_phase"][phase] = {"samples": d["samples"], "tilt_mrad": None if rot is None else rot * 1e3}
    return out


def _compare(path: Path, *options: str) -> tuple[dict, dict, float]:
    """``flexforce compare`` into a temporary folder: its summary.json, its timings.json and the
    seconds it took."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "report"
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):
            status = cli_main(["compare", str(path), "--robot", ROBOT, "-o", str(out), "-q", *options])
        seconds = time.perf_counter() - t0
        if status != 0:
            raise SystemExit(f"flexforce compare {path} {' '.join(options)} exited with status {status}")
        return json.loads((out / "summary.json").read_text()), json.loads((out / "timings.json").read_text()), seconds


def run(path: Path) -> dict:
    """The record of one recording: the comparison with the peers, and the smoothers again with their
    footholds estimated (``--footholds``: per episode, the first stance anchored)."""
    summary, timings, seconds = _compare(path, "--peers")
    footholds, _, _ = _compare(path, "--footholds", "--estimators", "fixed-lag,batch")
    calibrated, _, _ = _compare(path, "--calibrate-noise", "--estimators", "batch")
    rec = summary["recording"]
    return {"recording": path.name, "samples": rec.get("samples"), "duration_s": rec.get("duration_s"),
            "headline": headline(summary), "compare_s": round(seconds, 1),
            "reference_checks": summary.get("reference_checks"),
            "estimators": {k: _row(m) for k, m in summary["estimators"].items()},
            "baselines": {k: _row(m) for k, m in (summary.get("baselines") or {}).items()},
            "peers": {k: _peer_row(m, (timings.get("peers") or {}).get(k) or {})
                      for k, m in (summary.get("peers") or {}).items()},
            "footholds_estimated": {k: _row(m) for k, m in footholds["estimators"].items()},
            "noise_calibrated": {k: _row(m) for k, m in calibrated["estimators"].items()},
            "failures": summary.get("failures") or {}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA, help="folder of the iCub recordings")
    parser.add_argument("--output", type=Path, default=HERE / "results" / "real_forces.json")
    args = parser.parse_args()
    record: dict = {"benchmark": "real_forces", "command": "python benchmarks/real_forces.py", "robot": ROBOT,
                    "reference": "F/T normal forces and Vicon tilt (references, not ground truth)",
                    "skip_s": 0.5, "machine": {"python": platform.python_version(),
                                               "processor": platform.processor() or platform.machine(),
                                               "numpy": np.__version__}}
    for key, name in RECORDINGS.items():
        record[key] = run(args.data / name)
    record["load_average_at_end"] = [round(x, 2) for x in os.getloadavg()]
    text = json.dumps(record, indent=2, allow_nan=False)
    print(text)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text + "\n")


if __name__ == "__main__":
    main()
