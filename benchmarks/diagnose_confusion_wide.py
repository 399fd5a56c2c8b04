"""The diagnostics across robots, motions, magnitudes and two effects at once, scored against the
identifiability table.

Usage::

    python benchmarks/diagnose_confusion_wide.py [--jobs 2] [--duration 3] [--only NAME ...] [--fresh]
        [--catalogue default|all] [--out PATH]

Prints a summary as JSON and writes ``benchmarks/results/diagnose_confusion_wide.json`` (every
recording) and ``diagnose_confusion_wide.md`` (the tables).

Recordings (simulated, 3 s, the IMU bias random walk off so that "clean" means clean):

* every catalogue effect (:data:`WIDE_CASES`: the eight of ``diagnose_confusion.py`` and the
  real-log ones, IMU mounting rotation, IMU/encoder time offset, mass scale, F/T offset, foothold
  error) at a
  clear and a near-detection-limit magnitude, each on two of the six (robot, motion) pairs --
  Romeo and TALOS, the ``sway``, ``weight-shift`` and ``com-step`` scenarios -- so that every
  effect is seen on both robots;
* two effects at once (:data:`PAIRS`) on both robots;
* clean recordings: every (robot, motion) pair, two noise seeds.

The F/T sensors are fused (``use_ft``) for the mass-scale and F/T-offset recordings (without
them a mass scale is a stiffness scale, and an F/T offset acts on nothing); the others use the
IMU and the encoders only, as the paper.  :func:`flexforce.compare.diagnostics.run.diagnose` ranks every
candidate of its default catalogue (``--catalogue all``: every registered one, the footholds
named; by default they are left out, none of these recordings having a touch-down): screening,
refits, greedy forward selection, ``add=["auto"]``, at most two.

Scored as the targets read:

* right effect first, among the single-effect recordings whose truth the identifiability table
  (computed by the diagnosis at the nominal fit, before any refit) calls seen (at least partly:
  some direction of it pays for its dof) and separable from every other candidate;
* the same among those whose hidden size reaches, along one of its unknowns, the smallest size
  the table says the recording detects (:attr:`~flexforce.smoother.screening.CandidateInformation.
  detectable`; the truths that map one to one to their candidate's unknowns; the others counted);
* no significant effect on the clean recordings;
* no wrong candidate in the final selection: a selected effect that is not a truth and not
  called inseparable from one by the table;
* where round 1 took an inseparable partner of the truth: whether the partners' check (each
  candidate the data do not tell from the choice, held against the truth:
  :meth:`~flexforce.compare.diagnostics.run.Diagnosis.partner_checks`) names the hidden effect as the
  one the truth favours;
* the errors (force, CoP, tilt against the simulated truth) after adding the selected effects,
  as a ratio to before, when a truth was selected.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import re
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from diagnose_confusion import CASES, KEYS  # type: ignore[import-not-found]  # noqa: E402

WIDE_CASES = {
    **CASES,
    "imu-mounting": [{"type": "imu-mounting", "rotation": [0.02, -0.01, 0.05]},
                     {"type": "imu-mounting", "rotation": [0.006, 0.0, 0.0]}],
    "time-offset": [{"type": "time-offset", "delay": 0.02}, {"type": "time-offset", "delay": 0.006}],
    "mass-scale": [{"type": "mass-scale", "scale": 1.1}, {"type": "mass-scale", "scale": 1.03}],
    "ft-offset": [{"type": "ft-offset", "contact": "left_foot", "force": [0.0, 0.0, 15.0], "torque": [2.0, 0.0, 0.0]},
                  {"type": "ft-offset", "contact": "right_foot", "force": [4.0, 0.0, 0.0], "torque": [0.0, 0.0, 0.0]}],
    "foothold": [{"type": "foothold", "contact": "left_foot", "position": [0.0, 0.0, 0.004]},
                 {"type": "foothold", "contact": "right_foot", "position": [0.0, 0.0, 0.0015],
                  "rotation": [0.003, 0.0, 0.0]}],
}
"""Per effect: a clear magnitude (level 0) and one near the detection limit (level 1)."""
FUSE_FT = ("mass-scale", "ft-offset")
COMBOS = [("romeo", "sway"), ("talos", "weight-shift"), ("romeo", "com-step"), ("talos", "sway"),
          ("romeo", "weight-shift"), ("talos", "com-step")]
"""(robot, motion); consecutive pairs alternate the robot."""
PAIRS = [("gyro-bias", "external-wrench"), ("com-offset", "stiffness"), ("accel-bias", "anisotropic-stiffness"),
         ("imu-mounting", "nonlinear-stiffness")]
"""Two hidden effects at once (each at its clear magnitude)."""


def jobs_of(duration: float, only=None) -> list[dict]:
    jobs: list[dict[str, Any]] = []
    for robot, motion in COMBOS:
        for seed in (0, 1):
            jobs.append({"truth": [], "robot": robot, "motion": motion, "level": None, "seed": seed})
    for e, name in enumerate(WIDE_CASES):
        for level in (0, 1):
            for j in (0, 1):
                robot, motion = COMBOS[(2 * (2 * e + level) + j) % len(COMBOS)]
                jobs.append({"truth": [name], "robot": robot, "motion": motion, "level": level, "seed": 0})
    for p, (a, b) in enumerate(PAIRS):
        for robot in ("romeo", "talos"):
            motion = ("sway", "weight-shift", "com-step")[p % 3]
            jobs.append({"truth": [a, b], "robot": robot, "motion": motion, "level": 0, "seed": 0})
    for job in jobs:
        job["duration"] = duration
        job["ft"] = any(t in FUSE_FT for t in job["truth"])
    if only:
        jobs = [j for j in jobs if any(t in only for t in (j["truth"] or ["none"]))]
    return jobs


def key(job) -> str:
    truth = "+".join(job["truth"]) or "none"
    return f'{truth}/{job["level"]}/{job["robot"]}/{job["motion"]}/{job["seed"]}'


def one(job):
    try:
        return _one(job)
    except Exception as exc:  # one failed recording must not lose the others
        return {**job, "key": key(job), "selected": [], "first": "error", "error": f"{type(exc).__name__}: {exc}"}


def _one(job):
    from flexforce.compare.diagnostics.run import diagnose, registered_effects
    from flexforce.datasets.sim.scenario import Scenario
    from flexforce.datasets.sim.simulator import Simulator
    from flexforce.factors.model import ModelConfig

    sc = Scenario.load(job["motion"])
    sc.robot = job["robot"]
    sc.duration = job["duration"]
    sc.seed = job["seed"]
    sc.imu_noise = {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    sc.effects = [WIDE_CASES[t][job["level"]] for t in job["truth"]]
    rec = Simulator(sc).run()
    model = ModelConfig.from_recording(rec, use_ft=job["ft"])
    t0 = time.perf_counter()
    # the default catalogue (the footholds left out: no recording here has a touch-down), or with
    # --catalogue all every registered candidate, the footholds named
    cands = list(registered_effects()) if job.get("catalogue") == "all" else None
    d = diagnose(rec, model, candidates=cands, add=["auto"], ekf=False, max_effects=2)
    ident = d.identifiability
    seconds = time.perf_counter() - t0
    # round 1 took an inseparable partner of the single truth, refitted beside it: the same
    # diagnosis with the truth withheld, its checks against the simulated F/T (not fused) -- what a
    # user with six-axis F/T sees
    ft_checks = None
    if len(job["truth"]) == 1 and d.selected and ident is not None and not job["ft"]:
        t = job["truth"][0]
        pair = ident.pair(t, d.selected[0]) if t in ident.candidates else None
        if d.selected[0] != t and pair is not None and pair.inseparable and \
                any(c.effect == t and c.score is not None for c in d.rounds[0]):
            blind = diagnose(dataclasses.replace(rec, truth=None), model, candidates=cands, add=["auto"], ekf=False,
                             max_effects=2)
            ft_checks = {"selected": list(blind.selected), "partner_checks": blind.partner_checks()}
    return {**job, "key": key(job), "selected": list(d.selected), "first": d.selected[0] if d.selected else "none",
            "inseparable": [[p.a, p.b, float(p.largest)] for p in ident.inseparable()] if ident else None,
            "not_seen": [c.effect for c in ident.not_seen()] if ident else None,
            "status": {t: ident.candidates[t].status for t in job["truth"] if t in ident.candidates} if ident else None,
            "detectable": {t: [float(x) for x in ident.candidates[t].detectable] for t in job["truth"]
                           if t in ident.candidates} if ident else None,
            "ranking": [{"effect": c.effect, "score": c.score, "lr": c.lr, "significant": c.significant,
                         "rivals": list(c.rivals)} for c in d.rounds[0]] if d.rounds else [],
            "checks": {c.effect: c.check_text() for row in d.rounds for c in row if c.check},
            "partner_checks": d.partner_checks(),
            # the constancy check of each constant effect a round would have taken (its halves)
            "constancy": [{"effect": c.effect, "round": c.round, **c.constancy} for row in d.rounds for c in row
                          if c.constancy],
            "partner_checks_ft": ft_checks,
            # every round's refits with their score tests at the round's base (what a refit policy
            # bounded by the test would have decided can be read from them)
            "rounds": [[{"effect": c.effect, "score": c.score, "lr": c.lr, "significant": c.significant,
                         "implausible": bool(c.implausible),
                         "T": None if c.screen is None else float(c.screen.statistic),
                         "nu": None if c.screen is None else float(c.screen.dof),
                         "kind": None if c.screen is None else c.screen.kind} for c in row] for row in d.rounds],
            "before": {k: d.before.rmse[k] for k in KEYS},
            "after": {k: d.after.rmse[k] for k in KEYS} if d.after else None,
            "seconds": seconds}


def partners(r, name) -> set[str]:
    """The candidates the recording's identifiability table cannot tell from ``name``."""
    return {b if a == name else a for a, b, _ in (r.get("inseparable") or []) if name in (a, b)}


def seen(r, name) -> bool:
    """The table sees ``name`` at least partly (a direction of it pays for its dof: the external
    wrench's vertical force never does on these robots, its horizontal push does); a truth that was
    no candidate (the footholds, left out of the default catalogue here) is not in the table."""
    if r.get("status") is not None and r.get("not_seen") is not None and name not in r["status"]:
        return False
    return (r.get("status") or {}).get(name, "seen" if name not in (r.get("not_seen") or []) else "not seen") != \
        "not seen"


def truth_size(name: str, level: int) -> list[float] | None:
    """The hidden effect's size in its candidate's unknowns (the labels' order), where they map
    one to one (None: the wrench, the anisotropic stiffness, the F/T offset, the foothold)."""
    spec = WIDE_CASES[name][level]
    if name in ("gyro-bias", "accel-bias"):
        return [float(x) for x in spec["value"]]
    if name == "imu-mounting":
        return [float(x) for x in spec["rotation"]]
    if name == "com-offset":
        return [float(x) for x in spec["offset"][:2]]
    if name == "time-offset":
        return [float(spec["delay"])]
    if name == "mass-scale":
        return [float(spec["scale"]) - 1.0]
    if name == "stiffness":
        return [float(spec["stiffness"]) - 1.0, float(spec.get("damping", 1.0)) - 1.0]
    if name == "nonlinear-stiffness":
        return [float(spec["beta_f"]), float(spec["beta_t"])]
    return None


def above_size(r) -> bool | None:
    """Whether a single hidden effect is at or above the size the recording's table says it
    detects along some unknown (None: no one-to-one size, or no table)."""
    name = r["truth"][0]
    size = truth_size(name, r["level"])
    d = (r.get("detectable") or {}).get(name)
    if size is None or not d or len(d) != len(size):
        return None
    return any(abs(v) >= x for v, x in zip(size, d))


def score(runs: list[dict]) -> dict:
    singles = [r for r in runs if len(r["truth"]) == 1 and r["first"] != "error"]
    separable = [r for r in singles if r.get("not_seen") is not None and seen(r, r["truth"][0])
                 and not partners(r, r["truth"][0])]
    clean = [r for r in runs if not r["truth"] and r["first"] != "error"]
    pairs = [r for r in runs if len(r["truth"]) == 2 and r["first"] != "error"]

    def found(r, t) -> bool:
        """``t`` or a candidate the recording cannot tell from it was selected."""
        return t in r["selected"] or bool(partners(r, t) & set(r["selected"]))

    wrong = []
    for r in runs:
        if r["first"] == "error":
            continue
        allowed = set(r["truth"]).union(*(partners(r, t) for t in r["truth"])) if r["truth"] else set()
        extra = [s for s in r["selected"] if s not in allowed]
        if extra:
            wrong.append([r["key"], extra])
    # a partner taken for the truth: does the round's partner sentence (the truth as the reference)
    # favour the hidden effect over the choice?
    # (the hidden effect refitted in that round: a truth left out of the catalogue cannot be named)
    taken = [r for r in singles if r["first"] != r["truth"][0] and r["first"] in partners(r, r["truth"][0])
             and any(c["effect"] == r["truth"][0] and c["score"] is not None for c in r.get("ranking") or [])]

    def favours_truth(r, sentences) -> bool:
        t = r["truth"][0]
        for sentence in sentences or []:
            got = re.search(r" favours? (.*?) over the choice", sentence)
            if sentence.startswith(f"round 1 took {r['first']}") and got:
                return t in got.group(1).split(" and ")
        return False

    def verdict_ft(r) -> str:
        """What the F/T's sentence says: the truth favoured, another partner, the choice, neither, or
        no sentence."""
        got = r.get("partner_checks_ft") or {}
        if favours_truth(r, got.get("partner_checks")):
            return "truth"
        text = " ".join(got.get("partner_checks") or [])
        if re.search(r" favours? (.*?) over the choice", text):
            return "another"
        return "choice" if re.search(r"agrees? with the choice", text) else ("neither" if text else "none")

    ratios: dict = {}
    for r in runs:
        if r["truth"] and r.get("after") and set(r["truth"]) & set(r["selected"]):
            for k in KEYS:
                if r["before"][k] > 0:
                    ratios.setdefault(k, []).append(r["after"][k] / r["before"][k])

    def frac(a, b):
        return [a, b, round(a / b, 3) if b else None]

    return {
        "recordings": len(runs), "errors": [r["key"] for r in runs if r["first"] == "error"],
        "right_first_separable": frac(sum(r["first"] == r["truth"][0] for r in separable), len(separable)),
        "right_first_all_single": frac(sum(r["first"] == r["truth"][0] for r in singles), len(singles)),
        # of the separable ones, those whose size the table says it detects (or has no size for)
        "right_first_separable_above_detectable_size": frac(
            sum(r["first"] == r["truth"][0] for r in separable if above_size(r) is not False),
            sum(above_size(r) is not False for r in separable)),
        "separable_below_detectable_size": [[r["key"], truth_size(r["truth"][0], r["level"]),
                                             (r.get("detectable") or {}).get(r["truth"][0]), r["first"]]
                                            for r in separable if above_size(r) is False],
        "right_first_separable_by_level": {
            str(lv): frac(sum(r["first"] == r["truth"][0] for r in separable if r["level"] == lv),
                          sum(r["level"] == lv for r in separable)) for lv in (0, 1)},
        "partner_taken_first_truth_favoured": frac(sum(favours_truth(r, r.get("partner_checks")) for r in taken),
                                                   len(taken)),
        # the same recordings, the truth withheld: the check against the simulated F/T (not fused)
        "partner_taken_first_ft_verdicts": {r["key"]: verdict_ft(r) for r in taken if not r.get("ft")},
        "clean_without_selection": frac(sum(not r["selected"] for r in clean), len(clean)),
        "two_effects_both_found": frac(sum(set(r["truth"]) <= set(r["selected"]) for r in pairs), len(pairs)),
        "two_effects_both_found_or_a_partner": frac(sum(all(found(r, t) for t in r["truth"]) for r in pairs),
                                                    len(pairs)),
        "recordings_with_a_wrong_selection": wrong,
        "not_separable": [[r["key"], sorted(partners(r, r["truth"][0])), not seen(r, r["truth"][0]), r["first"]]
                          for r in singles if r not in separable],
        "error_ratio_after_before_median": {k: float(np.median(v)) for k, v in ratios.items()},
        "error_ratio_after_before_range": {k: [float(np.min(v)), float(np.max(v))] for k, v in ratios.items()},
        "seconds_per_recording_median": float(np.median([r["seconds"] for r in runs if "seconds" in r] or [0.0])),
        # the constancy check (each constant effect a round would take, fitted on the two halves):
        # how often the true effect's halves disagreed, and the largest difference of a truth's halves
        "constancy_checks": sum(len(r.get("constancy") or []) for r in runs),
        "constancy_truth_failed": [[r["key"], c["effect"], round(abs(c["largest"][1]), 1)] for r in runs
                                   for c in r.get("constancy") or [] if c.get("made") and not c["constant"]
                                   and c["effect"] in r["truth"]],
        "constancy_other_failed": [[r["key"], c["effect"], round(abs(c["largest"][1]), 1)] for r in runs
                                   for c in r.get("constancy") or [] if c.get("made") and not c["constant"]
                                   and c["effect"] not in r["truth"]],
        "constancy_truth_largest_z": max([abs(c["largest"][1]) for r in runs for c in r.get("constancy") or []
                                          if c.get("made") and c["effect"] in r["truth"]] or [0.0]),
    }


def markdown(runs: list[dict], summary: dict) -> str:
    lines = ["| recording (truth/level/robot/motion/seed) | ft | seen, separable | first | selected | "
             "force / CoP / tilt after ÷ before |", "|---|---|---|---|---|---|"]
    for r in runs:
        sep = "—"
        if len(r["truth"]) == 1 and r.get("not_seen") is not None:
            t = r["truth"][0]
            p = partners(r, t)
            status = (r.get("status") or {}).get(t, "not seen" if t in r["not_seen"] else "seen")
            if r.get("status") is not None and t not in r["status"]:
                status = "not a candidate"
            sep = status + (f"; inseparable from {', '.join(sorted(p))}" if p else "")
        ratio = "—"
        if r.get("after") and r["truth"]:
            ratio = " / ".join(f'{r["after"][k] / r["before"][k]:.2f}' if r["before"][k] > 0 else "—" for k in KEYS)
        lines.append(f'| {r["key"]} | {"yes" if r.get("ft") else ""} | {sep} | {r["first"]} | '
                     f'{", ".join(r["selected"]) or "none"} | {ratio} |')
    head = [f"- right effect first, seen and separable: {summary['right_first_separable'][0]} of "
            f"{summary['right_first_separable'][1]}",
            f"- of those, at or above the size the table says the recording detects (where the truth maps to the "
            f"candidate's unknowns): {summary['right_first_separable_above_detectable_size'][0]} of "
            f"{summary['right_first_separable_above_detectable_size'][1]}",
            f"- right effect first, every single-effect recording: {summary['right_first_all_single'][0]} of "
            f"{summary['right_first_all_single'][1]}",
            f"- an inseparable partner first (the hidden effect refitted beside it), the partners' check naming the "
            f"hidden effect as the one the truth favours: {summary['partner_taken_first_truth_favoured'][0]} of "
            f"{summary['partner_taken_first_truth_favoured'][1]}",
            "- the same, the truth withheld, against the simulated six-axis F/T (not fused): "
            + (", ".join(f"{v} {sum(x == v for x in summary['partner_taken_first_ft_verdicts'].values())}"
                         for v in ("truth", "another", "choice", "neither", "none"))
               + " (the F/T favour the hidden effect, another partner, agree with the choice, do not decide, "
               "no sentence)"),
            f"- clean recordings without a selection: {summary['clean_without_selection'][0]} of "
            f"{summary['clean_without_selection'][1]}",
            f"- two effects, both selected: {summary['two_effects_both_found'][0]} of "
            f"{summary['two_effects_both_found'][1]} ({summary['two_effects_both_found_or_a_partner'][0]} counting an "
            "inseparable partner as found)",
            f"- recordings with a wrong selection: {len(summary['recordings_with_a_wrong_selection'])}",
            "- median error ratio after/before (truth selected): "
            + ", ".join(f"{k} {v:.2f}" for k, v in summary["error_ratio_after_before_median"].items()),
            f"- constancy checks (a constant effect a round would take, fitted on each half): "
            f"{summary.get('constancy_checks', 0)}; a truth's halves disagreeing: "
            f"{len(summary.get('constancy_truth_failed', []))} (largest difference of a truth's halves "
            f"{summary.get('constancy_truth_largest_z', 0.0):.1f} sigma); another effect's: "
            f"{len(summary.get('constancy_other_failed', []))}", ""]
    return "\n".join(head + lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--only", nargs="*", default=None, help="truths to run (effect names or 'none')")
    ap.add_argument("--fresh", action="store_true", help="ignore the results already in --out")
    ap.add_argument("--list", action="store_true", help="list the recordings and stop")
    ap.add_argument("--catalogue", choices=("default", "all"), default="default",
                    help="the diagnosis's default candidates (default), or every registered one, the footholds "
                         "named (all)")
    ap.add_argument("--out", default=str(Path(__file__).with_name("results") / "diagnose_confusion_wide.json"))
    args = ap.parse_args()
    jobs = jobs_of(args.duration, args.only)
    for job in jobs:
        job["catalogue"] = args.catalogue
    if args.list:
        print("\n".join(key(j) + (" (F/T fused)" if j["ft"] else "") for j in jobs))
        print(f"{len(jobs)} recordings")
        return
    t0 = time.perf_counter()
    partial = Path(args.out).with_suffix(".partial.jsonl")  # an interrupted run resumes
    done = {}
    earlier = 0.0  # the wall time of the runs whose recordings are reused
    if Path(args.out).exists() and not args.fresh:
        previous = json.loads(Path(args.out).read_text())
        earlier = float(previous.get("wall_s", 0.0))
        for r in previous.get("details", []):
            if r.get("first") != "error":
                done[r["key"]] = r
    if partial.exists() and not args.fresh:
        for line in partial.read_text().splitlines():
            r = json.loads(line)
            done[r["key"]] = r
    todo = [j for j in jobs if key(j) not in done]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool, partial.open("w" if args.fresh else "a") as fh:
        for r in pool.map(one, todo):
            done[r["key"]] = r
            fh.write(json.dumps(r) + "\n")
            fh.flush()
            print(f'{r["key"]}: {r["first"]} {r.get("selected")} {r.get("seconds", 0):.0f} s', file=sys.stderr,
                  flush=True)
    runs = [done[key(j)] for j in jobs]
    summary = score(runs)
    result = {"benchmark": "diagnose_confusion_wide", "catalogue": args.catalogue, "duration_s": args.duration,
              "cases": WIDE_CASES,
              "combos": COMBOS, "pairs": PAIRS, "fuse_ft": FUSE_FT, "summary": summary, "details": runs,
              "wall_s": earlier + time.perf_counter() - t0,
              "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                          "loadavg_at_end": list(os.getloadavg())}}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    Path(args.out).with_suffix(".md").write_text(markdown(runs, summary))
    partial.unlink()
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
