"""The identifiability table on the confusion benchmark's recordings (docs/diagnostics.md, "Identifiability").

Usage::

    python benchmarks/diagnose_identifiability.py [TRUTH [LEVEL [SEED]]]   # e.g. accel-bias 0 0; default none

Simulates the recording of ``benchmarks/diagnose_confusion.py`` (3 s ``sway``, Romeo, one hidden
effect of ``CASES`` or none), fits the nominal model and prints every candidate's detectability and
every pair's canonical correlation, most correlated first (JSON with ``--json``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from diagnose_confusion import CASES  # type: ignore[import-not-found]  # noqa: E402

from flexforce.datasets.sim.scenario import Scenario  # noqa: E402
from flexforce.datasets.sim.simulator import Simulator  # noqa: E402
from flexforce.factors.effects import EFFECTS, make_effect  # noqa: E402
from flexforce.factors.model import ModelConfig  # noqa: E402
from flexforce.smoother import NoiseRule, Problem, fit  # noqa: E402
from flexforce.smoother.screening import identifiability  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("truth", nargs="?", default="none")
    ap.add_argument("level", nargs="?", type=int, default=0)
    ap.add_argument("seed", nargs="?", type=int, default=0)
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    sc = Scenario.load("sway")
    sc.duration, sc.seed = args.duration, args.seed
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    sc.effects = [] if args.truth == "none" else [CASES[args.truth][args.level]]
    rec = Simulator(sc).run()
    model = ModelConfig.from_recording(rec)
    t0 = time.perf_counter()
    _, st = fit(rec, model)
    t_fit = time.perf_counter() - t0
    prob = Problem.build(rec, model, NoiseRule())
    ident = identifiability(prob, st.trajectory, [make_effect(n) for n in EFFECTS], n_residuals=st.n_residuals)
    if args.json:
        print(json.dumps({"truth": args.truth, "level": args.level, "seed": args.seed, "fit_s": t_fit,
                          **ident.to_dict()}, indent=1))
        return
    print(f"nominal fit {t_fit:.1f} s, identifiability {ident.seconds:.1f} s")
    for c in ident.candidates.values():
        print(f"{c.effect}: {c.text()}")
    for p in ident.pairs:
        print(f"{p.largest:.4f}  {p.a} ({p.direction_a}) / {p.b} ({p.direction_b})  "
              f"{[round(x, 3) for x in p.correlations]}")


if __name__ == "__main__":
    main()
