"""The diagnostics on held-out-style recordings: motions, robots' settings, sizes and combinations
that the confusion benchmarks (``diagnose_confusion.py``, ``diagnose_confusion_wide.py``) do not
contain, run as a user would (``diagnose(rec, add=["auto"], jobs=1)``, the default catalogue and
configuration).

Usage::

    python benchmarks/diagnose_heldout.py [--only NAME ...] [--jobs 1] [--out PATH]
    python benchmarks/diagnose_heldout.py --markdown      # the table of the JSON written, as Markdown
    python benchmarks/diagnose_heldout.py --rescore       # its summary recomputed from its recordings

Writes ``benchmarks/results/diagnose_heldout.json`` and prints a short table.

Recordings (simulated, 4 s each, :data:`CASES`): motions written here (:data:`MOTIONS`: a sideways
CoM sway without arms, a sideways CoM step, a weight shift onto one foot with the arms swinging, a
fore-aft sway with the arms swinging, a forward CoM step; none of them a built-in scenario) on
TALOS and Romeo; hidden effects at physically large sizes (a 60 N push on a hand, a yaw gyrometer
bias of 0.02 rad/s, contacts half as stiff, a cubic stiffening beta_t = 1000 /rad^2 seen in roll, a
CoM 2 cm off), two at once (an accelerometer bias of 0.15 m/s^2 with a push; a yaw gyrometer bias
with soft contacts), and two clean recordings (other noise seeds).  The IMU bias random walk is
off, as in the confusion benchmarks, so that a clean recording holds no effect.

Scored per recording: the truth, the ranking's first row, the selection, whether the first
selected is the truth (or a candidate the recording's identifiability table calls inseparable from
it: ``partners`` of ``diagnose_confusion_wide.py``), the rows turned down (by their check against
the truth, ``Candidate.vetoed``, or as implausible, with the reason), the errors against the
simulated truth (force, CoP, tilt) before and after adding the selection and their ratio, the
flagged windows before and after, and the seconds of the diagnosis.  Summary: right first among the
single-effect recordings whose truth the table calls seen and separable; recordings with a wrong
selection (a selected effect neither a truth nor inseparable from one); clean recordings with a
selection; the largest after/before error ratio per quantity (target: at most 1.05), over force, CoP
and tilt and over every error the diagnosis checks against the truth (moment, position and hand too:
``before_all``, ``after_all``, ``ratio_all``); the median seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import traceback
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from diagnose_confusion import KEYS  # type: ignore[import-not-found]  # noqa: E402
from diagnose_confusion_wide import partners, seen  # type: ignore[import-not-found]  # noqa: E402

DURATION = 4.0
"""s, every recording."""
TARGET_RATIO = 1.05
"""Largest after/before error ratio the target allows (``--add auto`` never raises an error by more
than 5 %)."""

ARMS = [{"joint": {"romeo": "LShoulderPitch", "talos": "arm_left_1_joint"}, "kind": "sine", "start": 0.3,
         "duration": 3.5, "amplitude": 0.35, "frequency": 0.8},
        {"joint": {"romeo": "RShoulderPitch", "talos": "arm_right_1_joint"}, "kind": "sine", "start": 0.3,
         "duration": 3.5, "amplitude": 0.35, "frequency": 0.8},
        {"joint": {"romeo": "LElbowRoll", "talos": "arm_left_4_joint"}, "kind": "sine", "start": 0.5,
         "duration": 3.2, "amplitude": -0.3, "frequency": 1.1}]
"""Both arms swinging in phase (shoulder pitch, 0.35 rad, 0.8 Hz) and the left elbow bending."""

MOTIONS: dict[str, dict[str, Any]] = {
    # the CoM sways sideways, 4 cm at 0.5 Hz, the arms still (sway.toml: 3 cm, 0.4 Hz, arms swinging)
    "side-sway": {"base": [{"kind": "sine", "target": "com", "start": 0.3, "duration": 3.5,
                            "amplitude": [0.0, 0.04, 0.0], "frequency": 0.5}]},
    # the CoM steps 1.5 cm sideways and back (com-step.toml: 2 cm forward)
    "side-step": {"base": [{"kind": "step", "target": "com", "start": 0.8, "duration": 0.5,
                            "offset": [0.0, 0.015, 0.0]},
                           {"kind": "step", "target": "com", "start": 2.6, "duration": 0.5,
                            "offset": [0.0, -0.015, 0.0]}]},
    # the CoM over the left foot, the right foot lifts 2 cm and lands back, the CoM back to the
    # middle, the arms swinging throughout
    "shift-arms": {"base": [{"toward": "left_foot", "fraction": 1.0, "start": 0.1, "duration": 1.5},
                            {"toward": "middle", "start": 2.6, "duration": 1.4}],
                   "swing": [{"contact": "right_foot", "lift": 1.8, "land": 2.5,
                              "displacement": [0.0, 0.0, 0.0], "height": 0.02}],
                   "joint": ARMS},
    # the CoM sways fore and aft, 2.5 cm at 0.6 Hz, the arms swinging
    "fore-aft-arms": {"base": [{"kind": "sine", "target": "com", "start": 0.3, "duration": 3.5,
                                "amplitude": [0.025, 0.0, 0.0], "frequency": 0.6}],
                      "joint": ARMS},
    # the CoM steps 3 cm forward and stays
    "forward-step": {"base": [{"kind": "step", "target": "com", "start": 0.6, "duration": 0.6,
                               "offset": [0.03, 0.0, 0.0]}]},
}
"""Motions of 4 s written here (scenario tables, :mod:`flexforce.datasets.sim.scenario`)."""

HAND_PUSH = {"type": "external-wrench", "link": "@link:0", "force": [0.0, -60.0, 0.0], "start": 1.6,
             "duration": 0.3, "profile": "half-sine"}
BASE_PUSH = {"type": "external-wrench", "link": "@base", "force": [-35.0, 25.0, 0.0], "start": 2.2,
             "duration": 0.25, "profile": "half-sine"}
YAW_GYRO = {"type": "gyro-bias", "value": [0.0, 0.0, 0.02]}
SOFT = {"type": "stiffness", "stiffness": 0.5, "damping": 1.0}
CUBIC_ROLL = {"type": "nonlinear-stiffness", "beta_f": 0.0, "beta_t": 1000.0}
ACCEL = {"type": "accel-bias", "value": [0.09, -0.12, 0.0]}  # |b| = 0.15 m/s^2
COM_2CM = {"type": "com-offset", "offset": [0.0, 0.02, 0.0]}

CASES: list[dict[str, Any]] = [
    {"name": "hand-push-60N", "robot": "talos", "motion": "side-sway", "effects": [HAND_PUSH], "seed": 0},
    {"name": "yaw-gyro-bias", "robot": "romeo", "motion": "side-step", "effects": [YAW_GYRO], "seed": 0},
    {"name": "soft-contacts", "robot": "talos", "motion": "shift-arms", "effects": [SOFT], "seed": 0},
    {"name": "cubic-roll-romeo", "robot": "romeo", "motion": "side-sway", "effects": [CUBIC_ROLL], "seed": 0},
    {"name": "cubic-roll-talos", "robot": "talos", "motion": "side-sway", "effects": [CUBIC_ROLL], "seed": 1},
    {"name": "com-offset-2cm", "robot": "romeo", "motion": "shift-arms", "effects": [COM_2CM], "seed": 0},
    {"name": "accel-bias+push", "robot": "talos", "motion": "forward-step", "effects": [ACCEL, BASE_PUSH],
     "seed": 0},
    {"name": "yaw-gyro+soft", "robot": "romeo", "motion": "fore-aft-arms", "effects": [YAW_GYRO, SOFT], "seed": 0},
    {"name": "clean-talos", "robot": "talos", "motion": "side-sway", "effects": [], "seed": 3},
    {"name": "clean-romeo", "robot": "romeo", "motion": "fore-aft-arms", "effects": [], "seed": 4},
]
"""The recordings: a name, the robot, the motion (:data:`MOTIONS`), the hidden effects
(:mod:`flexforce.datasets.sim.effects`) and the noise seed."""


def scenario_dict(case: dict) -> dict:
    """The scenario table of ``case`` (for :meth:`Scenario.from_dict`)."""
    motion = MOTIONS[case["motion"]]
    return {"name": f'heldout-{case["name"]}', "robot": case["robot"], "duration": DURATION,
            "seed": case["seed"], "imu_noise": {"gyro_bias_rw": 0.0, "accel_bias_rw": 0.0},
            "base": [dict(b) for b in motion.get("base", [])], "joint": [dict(j) for j in motion.get("joint", [])],
            "swing": [dict(s) for s in motion.get("swing", [])], "effects": [dict(e) for e in case["effects"]]}


def truth_of(case: dict) -> list[str]:
    """The hidden effects' types, once each."""
    return list(dict.fromkeys(e["type"] for e in case["effects"]))


def one(case: dict) -> dict:
    try:
        return _one(case)
    except Exception as exc:  # one failed recording must not lose the others
        return {**case, "truth": truth_of(case), "selected": [], "first": "error",
                "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc(limit=6)}


def _one(case: dict) -> dict:
    from flexforce.compare.diagnostics.run import diagnose
    from flexforce.datasets.sim.scenario import Scenario
    from flexforce.datasets.sim.simulator import Simulator

    t0 = time.perf_counter()
    rec = Simulator(Scenario.from_dict(scenario_dict(case))).run()
    sim_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    d = diagnose(rec, add=["auto"], jobs=1)
    seconds = time.perf_counter() - t0
    ident = d.identifiability
    truth = truth_of(case)
    rows = [c for row in d.rounds for c in row]
    top = d.ranking[0] if d.ranking else None
    before = {k: d.before.rmse[k] for k in KEYS}
    after = {k: d.after.rmse[k] for k in KEYS} if d.after is not None else None
    return {**case, "truth": truth, "selected": list(d.selected), "added": list(d.added),
            "first": d.selected[0] if d.selected else "none",
            "ranking_first": None if top is None else
            {"effect": top.effect, "round": top.round, "score": top.score, "status": top.status,
             "finding": top.finding or top.summary},
            "inseparable": [[p.a, p.b, float(p.largest)] for p in ident.inseparable()] if ident else None,
            "not_seen": [c.effect for c in ident.not_seen()] if ident else None,
            "status": {t: ident.candidates[t].status for t in truth if t in ident.candidates} if ident else None,
            "identifiability_error": d.identifiability_error,
            "turned_down": [{"effect": c.effect, "round": c.round, "by_check": bool(c.vetoed),
                             "why": c.implausible, "check": c.check_text() if c.check else ""}
                            for c in rows if c.implausible],
            "significant_not_truth": sorted({c.effect for c in rows if c.significant and c.effect not in truth}),
            "fitted": {c.effect: c.finding or c.summary for c in rows if c.effect in d.selected and c.significant},
            "before": before, "after": after,
            "ratio": {k: _ratio(after[k], before[k]) for k in KEYS} if after else None,
            # every error the diagnosis computes against the truth (its check's quantities), not only KEYS
            "before_all": dict(d.before.rmse), "after_all": None if d.after is None else dict(d.after.rmse),
            "ratio_all": None if d.after is None else
            {k: _ratio(d.after.rmse.get(k), b) for k, b in d.before.rmse.items()},
            "flagged_before": len(d.before.flags),
            "flagged_after": None if d.after is None else len(d.after.flags),
            "seconds": seconds, "simulation_s": sim_s}


def _ratio(after: float | None, before: float | None) -> float | None:
    """``after / before``, None when either is missing or ``before`` is 0."""
    return after / before if after is not None and before else None


def score(runs: list[dict]) -> dict:
    """The summary of the recordings (see the module documentation)."""
    ok = [r for r in runs if r["first"] != "error"]
    singles = [r for r in ok if len(r["truth"]) == 1]
    separable = [r for r in singles if r.get("not_seen") is not None and seen(r, r["truth"][0])
                 and not partners(r, r["truth"][0])]

    def right(r) -> bool:
        """The first selected is a truth or inseparable from one."""
        return any(r["first"] == t or r["first"] in partners(r, t) for t in r["truth"])

    wrong = []
    for r in ok:
        allowed = set(r["truth"]).union(*(partners(r, t) for t in r["truth"])) if r["truth"] else set()
        extra = [s for s in r["selected"] if s not in allowed]
        if extra:
            wrong.append([r["name"], extra])
    ratios: dict[str, list[tuple[float, str]]] = {}
    for r in ok:
        for k, v in (r.get("ratio") or {}).items():
            if v is not None:
                ratios.setdefault(k, []).append((v, r["name"]))
    largest: dict[str, tuple[float, str]] = {k: (round(max(v)[0], 4), max(v)[1]) for k, v in ratios.items()}
    every: dict[str, list[tuple[float, str]]] = {}
    for r in ok:
        for k, v in (r.get("ratio_all") or {}).items():
            if v is not None:
                every.setdefault(k, []).append((v, r["name"]))
    largest_all = {k: (round(max(v)[0], 4), max(v)[1]) for k, v in every.items()}
    clean = [r for r in ok if not r["truth"]]
    pairs = [r for r in ok if len(r["truth"]) == 2]
    return {
        "recordings": len(runs), "errors": [[r["name"], r["error"]] for r in runs if r["first"] == "error"],
        "right_first_separable": [sum(r["first"] == r["truth"][0] for r in separable), len(separable)],
        "separable": [r["name"] for r in separable],
        "right_first_or_partner_single": [sum(right(r) for r in singles), len(singles)],
        "two_effects_both_found": [sum(set(r["truth"]) <= set(r["selected"]) for r in pairs), len(pairs)],
        "recordings_with_a_wrong_selection": wrong,
        "clean_with_a_selection": [[r["name"], r["selected"]] for r in clean if r["selected"]],
        "clean": len(clean),
        "turned_down_by_check": sum(t["by_check"] for r in ok for t in r["turned_down"]),
        "turned_down_implausible": sum(not t["by_check"] for r in ok for t in r["turned_down"]),
        # a hidden effect's row turned down (implausible, or by its check) in some round
        "truth_turned_down": [[r["name"], t["effect"], t["round"], t["why"]] for r in ok for t in r["turned_down"]
                              if t["effect"] in r["truth"]],
        "largest_error_ratio_after_before": largest,
        "error_ratio_within_target": all(v[0] <= TARGET_RATIO for v in largest.values()),
        # the same over every error the diagnosis checks against the truth (moment, position, hand too)
        "largest_error_ratio_after_before_all": largest_all,
        "error_ratio_within_target_all": all(v[0] <= TARGET_RATIO for v in largest_all.values()),
        "seconds_median": float(np.median([r["seconds"] for r in ok] or [0.0])),
        "seconds_range": [float(min(r["seconds"] for r in ok)), float(max(r["seconds"] for r in ok))] if ok else None,
    }


def _size(e: dict) -> str:
    """A hidden effect in a few words."""
    kind = e["type"]
    if kind == "external-wrench":
        return f'push {np.linalg.norm(e["force"]):.0f} N on {e["link"]}'
    if kind in ("gyro-bias", "accel-bias"):
        return f'{kind} {np.linalg.norm(e["value"]):.3g}'
    if kind == "stiffness":
        return f'stiffness x{e["stiffness"]:g}'
    if kind == "nonlinear-stiffness":
        return f'beta_t {e["beta_t"]:g}' if e.get("beta_t") else f'beta_f {e["beta_f"]:g}'
    if kind == "com-offset":
        return f'CoM offset {100 * np.linalg.norm(e["offset"]):.0f} cm'
    return kind


def markdown(result: dict) -> str:
    """The recordings' table and the summary's lines, as Markdown (docs/diagnostics.md)."""
    s = result["summary"]
    lines = ["| recording | robot, motion | hidden | ranking's first | selected | right first | turned down "
             "| force / CoP / tilt after ÷ before | flagged windows | s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["details"]:
        hidden = " + ".join(_size(e) for e in r["effects"]) or "none"
        if r["first"] == "error":
            lines.append(f'| {r["name"]} | {r["robot"]}, {r["motion"]} | {hidden} | error: {r["error"][:80]} '
                         "| | | | | | |")
            continue
        top = r.get("ranking_first") or {}
        first = f'{top.get("effect")} ({top.get("status")})' if top else "—"
        if not r["truth"]:
            verdict = "—" if not r["selected"] else "no (clean)"
        else:
            p = set().union(*(partners(r, t) for t in r["truth"]))
            verdict = ("yes" if r["first"] in r["truth"] else "partner" if r["first"] in p
                       else "no" if r["selected"] else "none selected")
            if len(r["truth"]) == 1 and r["name"] not in s["separable"]:
                verdict += " (not separable)"
        down = ", ".join(f'{t["effect"]}{" (check)" if t["by_check"] else ""}' for t in r["turned_down"]) or "—"
        ratio = " / ".join(f"{v:.2f}" if v is not None else "—" for v in r["ratio"].values()) if r["ratio"] else "—"
        flags = f'{r["flagged_before"]} → {r["flagged_after"]}' if r["flagged_after"] is not None \
            else f'{r["flagged_before"]}'
        lines.append(f'| {r["name"]} | {r["robot"]}, {r["motion"]} | {hidden} | {first} | '
                     f'{", ".join(r["selected"]) or "none"} | {verdict} | {down} | {ratio} | {flags} | '
                     f'{r["seconds"]:.0f} |')
    largest = s["largest_error_ratio_after_before"]
    every = s.get("largest_error_ratio_after_before_all", {})
    head = [f'- right effect first, single effect seen and separable: {s["right_first_separable"][0]} of '
            f'{s["right_first_separable"][1]}; the truth or an inseparable partner first, every single effect: '
            f'{s["right_first_or_partner_single"][0]} of {s["right_first_or_partner_single"][1]}',
            f'- two effects, both selected: {s["two_effects_both_found"][0]} of {s["two_effects_both_found"][1]}',
            f'- recordings with a wrong selection: {len(s["recordings_with_a_wrong_selection"])}'
            + ("".join(f'; {n}: {", ".join(e)}' for n, e in s["recordings_with_a_wrong_selection"])),
            f'- clean recordings with a selection: {len(s["clean_with_a_selection"])} of {s["clean"]}',
            f'- a hidden effect turned down: {len(s["truth_turned_down"])}'
            + "".join(f"; {n}: {e} in round {k} ({why})" for n, e, k, why in s["truth_turned_down"]),
            "- largest error ratio after/before: "
            + (", ".join(f"{k} {v[0]:.2f} ({v[1]})" for k, v in largest.items()) or "no addition")
            + f' (target ≤ {TARGET_RATIO:.2f}: {"met" if s["error_ratio_within_target"] else "not met"})',
            "- the same over every error the diagnosis checks against the truth: "
            + (", ".join(f"{k} {v[0]:.2f} ({v[1]})" for k, v in every.items()) or "no addition")
            + (f' (target ≤ {TARGET_RATIO:.2f}: {"met" if s["error_ratio_within_target_all"] else "not met"})'
               if "error_ratio_within_target_all" in s else ""),
            f'- seconds per diagnosis: median {s["seconds_median"]:.0f}'
            + (f' ({s["seconds_range"][0]:.0f}–{s["seconds_range"][1]:.0f})' if s["seconds_range"] else ""),
            f'- errors: {len(s["errors"])}', ""]
    return "\n".join(head + lines) + "\n"


def short_table(runs: list[dict]) -> str:
    """One line per recording, for the terminal."""
    out = [f'{"recording":18} {"truth":36} {"first":22} {"selected":40} {"force/CoP/tilt ratio":22} {"s":>4}']
    for r in runs:
        ratio = " ".join(f"{v:.2f}" if v is not None else "-" for v in r["ratio"].values()) if r.get("ratio") else "-"
        first = r["first"] if r["first"] != "error" else "error: " + r.get("error", "")[:60]
        out.append(f'{r["name"]:18} {"+".join(r["truth"]) or "none":36} {first:22} '
                   f'{",".join(r["selected"]) or "none":40} {ratio:22} {r.get("seconds", 0.0):4.0f}')
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", default=None, help="recording names to run")
    ap.add_argument("--jobs", type=int, default=1, help="recordings diagnosed at once")
    ap.add_argument("--list", action="store_true", help="list the recordings and stop")
    ap.add_argument("--markdown", action="store_true", help="print the Markdown table of --out and stop")
    ap.add_argument("--rescore", action="store_true",
                    help="recompute the summary of --out from its recordings (no diagnosis) and stop")
    ap.add_argument("--out", default=str(Path(__file__).with_name("results") / "diagnose_heldout.json"))
    args = ap.parse_args()
    if args.markdown:
        print(markdown(json.loads(Path(args.out).read_text())), end="")
        return
    if args.rescore:
        result = json.loads(Path(args.out).read_text())
        result["summary"] = score(result["details"])
        Path(args.out).write_text(json.dumps(result, indent=1, default=float))
        print(short_table(result["details"]))
        print(json.dumps(result["summary"], indent=1))
        return
    cases = [c for c in CASES if not args.only or c["name"] in args.only]
    if args.list:
        print("\n".join(f'{c["name"]}: {c["robot"]}, {c["motion"]}, {" + ".join(map(_size, c["effects"])) or "clean"}'
                        for c in cases))
        return
    t0 = time.perf_counter()
    runs = []
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        for r in pool.map(one, cases):
            runs.append(r)
            print(f'{r["name"]}: {r["first"]} {r.get("selected")} {r.get("seconds", 0):.0f} s'
                  + (f' {r["error"]}' if r["first"] == "error" else ""), file=sys.stderr, flush=True)
    summary = score(runs)
    result = {"benchmark": "diagnose_heldout", "duration_s": DURATION, "motions": MOTIONS,
              "call": 'diagnose(rec, add=["auto"], jobs=1)', "summary": summary, "details": runs,
              "wall_s": time.perf_counter() - t0,
              "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                          "loadavg_at_end": list(os.getloadavg())}}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1, default=float))
    print(short_table(runs))
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
