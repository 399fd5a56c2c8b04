"""docs/results.md from the committed benchmark records, benchmarks/results/*.json.

    python benchmarks/results_md.py            # writes docs/results.md
    python benchmarks/results_md.py --check    # exit status 1 when docs/results.md is not what it writes

Every figure in docs/results.md is read from a JSON record here, never typed in by hand: a section
per record, with the command that writes it, the machine it ran on and its figures as tables.  A
record this script does not know gets the generic table of its scalar fields, so a new benchmark
shows up without a change here.  ``tests/test_results_md.py`` checks that the committed page is
what this script writes from the committed records, so the page cannot go stale.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
OUTPUT = HERE.parent / "docs" / "results.md"

COMMANDS: dict[str, str] = {
    "diagnose_confusion": "python benchmarks/diagnose_confusion.py",
    "diagnose_confusion_quick": "python benchmarks/diagnose_confusion.py --quick "
                                "--out benchmarks/results/diagnose_confusion_quick.json",
    "diagnose_confusion_wide": "python benchmarks/diagnose_confusion_wide.py --jobs 2 --fresh",
    "diagnose_confusion_wide_all": "python benchmarks/diagnose_confusion_wide.py --jobs 2 --fresh --catalogue all "
                                   "--out benchmarks/results/diagnose_confusion_wide_all.json",
    "diagnose_heldout": "python benchmarks/diagnose_heldout.py --jobs 2",
    "diagnose_speed": "python benchmarks/diagnose_speed.py",
    "diagnose_speed_jobs2": "python benchmarks/diagnose_speed.py --durations 20 --jobs 2 "
                            "--out benchmarks/results/diagnose_speed_jobs2.json",
    "diagnose_speed_60s_jobs2": "python benchmarks/diagnose_speed.py --durations 60 --jobs 2 "
                                "--out benchmarks/results/diagnose_speed_60s_jobs2.json",
    "diagnose_speed_icub_jobs1": "python benchmarks/diagnose_speed.py --durations '' --icub "
                                 "--out benchmarks/results/diagnose_speed_icub_jobs1.json",
    "diagnose_speed_icub_jobs2": "python benchmarks/diagnose_speed.py --durations '' --icub --jobs 2 "
                                 "--out benchmarks/results/diagnose_speed_icub_jobs2.json",
    "diagnose_walks": "python benchmarks/diagnose_walks.py",
    "ekf_speed": "python benchmarks/ekf_speed.py",
    "physics_vs_pinocchio": "python benchmarks/physics_vs_pinocchio.py",
    "smoother_speed": "OPENBLAS_NUM_THREADS=1 python benchmarks/smoother_speed.py",
    "stream_memory": "python benchmarks/stream_memory.py --minutes 60 --batch '' --blocks 1,10",
    "time_offset": "python benchmarks/time_offset.py",
    "walk": "python benchmarks/walk.py",
    "walk_deflected": "python benchmarks/walk.py --touchdown deflected --out benchmarks/results/walk_deflected.json",
    "walk_footholds": "python benchmarks/walk.py --estimators fixed-lag batch --footholds "
                      "--out benchmarks/results/walk_footholds.json",
    "walk_short": "python benchmarks/walk.py --scenario walk-short --out benchmarks/results/walk_short.json",
}
"""Record (file stem) -> the command that writes it, from the repository's root: the script with the
options that give the record's settings (its durations, jobs, catalogue, touch-down convention).  A
record that names its own (``command``) is shown with that one; the Holm subset's truths are read
from the record."""

Record = dict[str, Any]


def fmt(value: Any) -> str:
    """A JSON value as table text: floats to four significant digits without trailing zeros
    (scientific below 1e-3 and from 1e6), booleans as yes/no, None as a dash, lists of scalars inline,
    lists of lists or objects by their length."""
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if value == 0.0:
            return "0"
        if not math.isfinite(value):
            return str(value)
        if abs(value) < 1e-3 or abs(value) >= 1e6:
            return f"{value:.3g}"
        digits = max(0, 3 - math.floor(math.log10(abs(value))))
        text = f"{value:.{digits}f}"
        return text.rstrip("0").rstrip(".") if "." in text else text
    if isinstance(value, list):
        if any(isinstance(v, (dict, list)) for v in value):
            return f"{len(value)} entries"
        return ", ".join(fmt(v) for v in value) if value else "none"
    return str(value).replace("|", "\\|").replace("\n", " ")


def table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    """A Markdown table; cells go through :func:`fmt` unless already strings."""
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        out.append("| " + " | ".join(c if isinstance(c, str) else fmt(c) for c in row) + " |")
    return out


def _scalars(node: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """``(dotted key, value)`` of every scalar (or short list of scalars) under ``node``."""
    if isinstance(node, dict):
        out = []
        for key, value in node.items():
            out += _scalars(value, f"{prefix}.{key}" if prefix else str(key))
        return out
    if isinstance(node, list):
        if len(node) <= 4 and all(not isinstance(v, (dict, list)) for v in node):
            return [(prefix, node)]
        return [(prefix, f"({len(node)} entries in the JSON)")]
    return [(prefix, node)]


def scalar_table(node: Any, skip: Iterable[str] = ()) -> list[str]:
    skip = set(skip)
    rows = [(k, v) for k, v in _scalars(node) if k.split(".")[0] not in skip]
    return table(["quantity", "value"], rows) if rows else []


def machine_line(record: Record) -> str:
    """The machine and load the record names, one line."""
    parts = []
    machine = record.get("machine")
    if isinstance(machine, dict):
        parts += [f"{k} {fmt(v)}" for k, v in machine.items()]
    for key in ("load_average", "load_average_at_end"):
        if key in record:
            parts.append(f"{key.replace('_', ' ')} {fmt(record[key])}")
    return "; ".join(parts) if parts else "not recorded"


# The records' own sections --------------------------------------------------------------------

def ekf_speed(r: Record) -> list[str]:
    rows = [(name, r[name]["us_per_step_median"], r[name]["us_per_step_mean"], r[name]["us_per_step_p99"],
             r[name]["total_s"]) for name in ("fast", "fast_no_outputs") if name in r]
    out = [f"{r['scenario']}, {fmt(r['duration_s'])} s at {fmt(r['rate_hz'])} Hz ({r['steps']} steps), "
           f"target {fmt(r['target_us_per_step'])} µs per step (median, outputs on).", ""]
    out += table(["run", "µs/step median", "mean", "p99", "total [s]"], rows)
    out += ["", *table(["compilation", "s"], [(k, r[k]) for k in
                                              ("cold_compile_s", "cold_compile_s_runs", "cached_load_s",
                                               "warmup_compile_s") if k in r])]
    ref = r.get("cited_reference")
    if ref:
        out += ["", f"Cited, not measured here: {ref['what']}: {fmt(ref['us_per_step'])} µs per step "
                    f"({ref['source']})."]
    return out


def _timing(d: Record) -> list[Any]:
    return [d.get("updates"), d.get("median_ms"), d.get("p99_ms"), d.get("max_ms"), d.get("wall_s")]


def smoother_speed(r: Record) -> list[str]:
    rows = []
    pp = r.get("push_pitch", {})
    for key in ("fixed_lag", "fixed_lag_gtsam_backend"):
        if key in pp:
            rows.append([f"push-pitch {fmt(pp['seconds'])} s: {key}", *_timing(pp[key])])
    if "fixed_lag_long" in r:
        rows.append([f"{fmt(r['fixed_lag_long']['seconds'])} s: fixed-lag", *_timing(r["fixed_lag_long"])])
    for key, d in r.get("gtsam_long", {}).items():
        rows.append([f"{fmt(d['seconds'])} s: gtsam {key} (lag {fmt(d['lag_s'])} s)", *_timing(d)])
    flc = r.get("fixed_lag_compare", {})
    for key in ("window", "gtsam_incremental", "gtsam_batch"):
        if key in flc:
            rows.append([f"{fmt(flc['seconds'])} s, lag {fmt(flc['lag_s'])} s: {key}", *_timing(flc[key])])
    out = ["Fixed-lag updates (times per update):", ""]
    out += table(["run", "updates", "median [ms]", "p99 [ms]", "max [ms]", "wall [s]"], rows)
    batch_rows = []
    if "batch_s" in pp:
        batch_rows.append((f"push-pitch {fmt(pp['seconds'])} s", pp["batch_s"], "–"))
    if "batch" in r:
        batch_rows.append((f"{fmt(r['batch']['seconds'])} s ({r['batch']['steps']} steps)", r["batch"]["wall_s"],
                           r["batch"]["iterations"]))
    bvg = r.get("batch_vs_gtsam_lm")
    if bvg:
        for key in ("own_batch", "gtsam_lm"):
            batch_rows.append((f"{bvg.get('recording', '')}: {key}", bvg[key]["wall_s"], bvg[key]["iterations"]))
    out += ["", "Batch smoother:", "", *table(["run", "wall [s]", "iterations"], batch_rows)]
    if bvg:
        out += ["", f"gtsam's Levenberg–Marquardt over the own batch smoother on the same graph: "
                    f"{fmt(bvg['speed_ratio_gtsam_over_own'])}× the time; their estimates agree to:", ""]
        out += table(["quantity", "difference"], list(bvg["agreement"].items()))
    if "targets" in r:
        out += ["", *table(["target", "value"], list(r["targets"].items()))]
    return out


def stream_memory(r: Record) -> list[str]:
    log = r.get("log", {})
    out = [f"Log: {fmt(log.get('minutes'))} min at {fmt(log.get('rate_hz'))} Hz from {log.get('source')} "
           f"({fmt(log.get('bag_mb'))} MB).", ""]
    rows = [(name, d.get("minutes", log.get("minutes")), d["samples_per_update"], d["peak_pss_mb"],
             d["realtime_factor"], d["update_median_ms"], d["update_p99_ms"], d["update_per_sample_ms"])
            for name, d in r.get("stream", {}).items()]
    out += table(["run", "minutes", "samples per update", "peak PSS [MB]", "× real time", "update median [ms]",
                  "p99 [ms]", "per sample [ms]"], rows)
    commands = [(name, f"`{d['command']}`") for name, d in r.get("stream", {}).items() if "command" in d]
    if commands:
        out += ["", *table(["run", "command"], commands)]
    batch = r.get("batch")
    if batch:
        out += ["", "Batch smoother on the log's first seconds:", "", *scalar_table(batch)]
    return out


def physics_vs_pinocchio(r: Record) -> list[str]:
    rows = [(d["robot"], d["scenario"], d["hidden_effects"] or "–", d["newton_euler_force_max_over_mg"],
             d["newton_euler_moment_max_over_mgh"], d["contact_law_max_N"], d["imu_accel_max_m_s2"],
             d["imu_gyro_max_rad_s"]) for d in r["rows"]]
    out = table(["robot", "scenario", "hidden effects", "Newton–Euler force / m g", "moment / m g h",
                 "contact law [N]", "IMU accel [m/s²]", "IMU gyro [rad/s]"], rows)
    for key in ("worst_without_hidden_effects", "worst"):
        if key in r:
            out += ["", f"{key.replace('_', ' ')}:", "", *scalar_table(r[key])]
    return out


def diagnose_speed(r: Record) -> list[str]:
    rows = [(c["case"], c["duration_s"], c["steps"], c["jobs"], c["diagnosis_s"], c["process_s"], c["refitted"],
             c["selected"], c["peak_rss_mb"], c["peak_rss_largest_worker_mb"], c.get("target_s"),
             c.get("within_target")) for c in r["cases"]]
    out = table(["case", "duration [s]", "steps", "jobs", "diagnosis [s]", "process [s]", "refits", "selected",
                 "peak RSS [MB]", "largest worker [MB]", "target [s]", "within"], rows)
    if "targets" in r:
        out += ["", *table(["target", "value"], list(r["targets"].items()))]
    return out


def diagnose_confusion(r: Record) -> list[str]:
    matrix = r["matrix"]
    columns = list(next(iter(matrix.values())).keys())
    rows = [(truth, *(str(counts[c]) if counts[c] else "." for c in columns)) for truth, counts in matrix.items()]
    out = [f"{r['scenario']}, {fmt(r['duration_s'])} s, seeds {fmt(r['seeds'])}: the first effect selected (columns) "
           "for each hidden effect (rows).", ""]
    out += table(["truth \\ first selected", *columns], rows)
    extra = [(k, r[k]) for k in ("correct_first", "runs", "tie", "ambiguous_first", "wall_s") if k in r]
    if extra:
        out += ["", *table(["quantity", "value"], extra)]
    return out


def _count(v: Any) -> Any:
    if isinstance(v, list) and len(v) == 3 and all(isinstance(x, (int, float)) for x in v):
        return f"{v[0]} of {v[1]} ({fmt(v[2])})"
    if isinstance(v, list):
        return f"{len(v)} entries" if v else "none"
    return v


def diagnose_confusion_wide(r: Record) -> list[str]:
    s = r["summary"]
    out = [f"{s['recordings']} recordings, {fmt(r['duration_s'])} s each; robots and motions: "
           f"{', '.join('/'.join(c) for c in r['combos'])}; catalogue: {r.get('catalogue', 'default')}.", ""]
    rows = []
    for key, value in s.items():
        if isinstance(value, dict) and key.startswith("error_ratio"):
            rows += [(f"{key}.{k}", v) for k, v in value.items()]
        elif isinstance(value, dict) and key == "right_first_separable_by_level":
            rows += [(f"{key}.{k}", _count(v)) for k, v in value.items()]
        elif isinstance(value, dict):
            rows.append((key, f"{len(value)} entries"))
        else:
            rows.append((key, _count(value)))
    out += table(["quantity", "value"], rows)
    if "wall_s" in r:
        out += ["", f"Wall time: {fmt(r['wall_s'])} s."]
    return out


def diagnose_walks(r: Record) -> list[str]:
    rows = [(d["robot"], d["truth"], d["selected"], d["found"], d["partner_found"], d["wrong"] or "none",
             d["before"]["force_N"], d["after"]["force_N"], 1e3 * d["before"]["cop_m"], 1e3 * d["after"]["cop_m"],
             1e3 * d["before"]["rotation_rad"], 1e3 * d["after"]["rotation_rad"], d["seconds"]) for d in r["runs"]]
    return table(["robot", "hidden", "selected", "found", "partner found", "wrong", "force before [N]", "after",
                  "CoP before [mm]", "after", "tilt before [mrad]", "after", "s"], rows)


def time_offset(r: Record) -> list[str]:
    rows = [(d["robot"], d["motion"], d["truth_ms"], d["beside"] or "–", d["significant"], d["value_ms"],
             d["std_ms"], d["p"], d["seconds"]) for d in r["runs"]]
    return table(["robot", "motion", "true offset [ms]", "beside", "significant", "estimate [ms]", "σ [ms]", "p",
                  "s"], rows)


def walk(r: Record) -> list[str]:
    rec = r["recording"]
    out = [f"{rec['robot']}, {rec['scenario']}: {fmt(rec['duration_s'])} s, {rec['touch_downs']} touch-downs, "
           f"{fmt(rec['single_support_s'])} s in single support, touch-down convention {rec['touchdown']}; "
           f"windows {fmt(r['windows_s']['first'])} s and {fmt(r['windows_s']['last'])} s.", ""]
    rows = []
    for name, est in r["estimators"].items():
        for window in ("first", "last", "all"):
            m = est[window]
            rows.append((name, window, m["tilt_rmse_deg"], m["force_rmse_N"], m["vertical_force_rmse_N"],
                         m["contact_force_rmse_N"], m["cop_rmse_mm"], m["hand_rmse_mm"]))
    out += table(["estimator", "window", "tilt [deg]", "force [N]", "vertical force [N]", "contact force [N]",
                  "CoP [mm]", "hand [mm]"], rows)
    runs = [(name, est["run_s"], est["flexibility_over_static"], est["nees_mean"]) for name, est in
            r["estimators"].items()]
    out += ["", *table(["estimator", "run [s]", "flexibility / static deflection", "NEES mean"], runs)]
    return out


def icub_identification(r: Record) -> list[str]:
    out = []
    for key in ("identify_on_sway", "identify_on_walk"):
        for variant, d in r.get(key, {}).items():
            out.append((f"{key} ({variant})", d["summary"], d["k_fs_N_per_m"], d["k_ts_Nm_per_rad"], d["k_fd_Ns_per_m"],
                        d["k_td_Nms_per_rad"], d["converged"]))
    lines = table(["fit", "scales", "k_fs [N/m]", "k_ts [N m/rad]", "k_fd [N s/m]", "k_td [N m s/rad]", "converged"],
                  out)
    rows = []
    for key in ("test_on_walk", "test_on_sway"):
        for stiffness, ests in r.get(key, {}).items():
            for name, m in ests.items():
                rows.append((key, stiffness, name, m["vertical_force_rmse_N"], m["vertical_force_rmse_bias_removed_N"],
                             m["tilt_rmse_deg"]))
    lines += ["", "IMU-only estimates against the F/T (vertical force, per foot) and Vicon (tilt):", ""]
    lines += table(["test", "stiffness", "estimator", "vertical force [N]", "bias removed [N]", "tilt [deg]"], rows)
    if "leg_odometry_tilt_rmse_deg" in r:
        lines += ["", *table(["leg odometry tilt [deg]", "value"], list(r["leg_odometry_tilt_rmse_deg"].items()))]
    if "ft_offset" in r:
        sums = [(name, d["weight_N"], d["sum_mean_N"], d["offset_N"], d["offset_percent"]) for name, d in
                r["ft_offset"].items()]
        lines += ["", *table(["F/T sum", "m g [N]", "mean sum [N]", "offset [N]", "offset [%]"], sums)]
    return lines


def demo_first_run(r: Record) -> list[str]:
    rows = [(f"cold {i + 1}", *_demo_row(run)) for i, run in enumerate(r["cold"])]
    if r.get("warm"):
        rows.append(("warm", *_demo_row(r["warm"])))
    t = r["targets"]
    return [f"Runs: `{r['runs']}`; {r['usable_cores']} usable cores.  Targets on a "
            f"first run: the first line within {fmt(t['first_line_s'])} s (met: {r['first_line_met']}), the "
            f"whole demo within {fmt(t['wall_s'])} s (met: {r['wall_met']}).", ""] + table(
        ("run", "wall [s]", "CPU [s]", "first line [s]", "EKF done [s]", "fixed-lag done [s]", "batch done [s]",
         "fixed-lag path"), rows)


def _demo_row(run: Record) -> list[Any]:
    done = run.get("done_at_s", {})
    return [run["wall_s"], run["cpu_s"], run["first_line_s"], done.get("ekf"), done.get("fixed-lag"),
            done.get("batch"), "general" if run.get("fixed_lag_general_path") else "compiled"]


SECTIONS: dict[str, Callable[[Record], list[str]]] = {
    "ekf_speed": ekf_speed, "smoother_speed": smoother_speed, "stream_memory": stream_memory,
    "physics_vs_pinocchio": physics_vs_pinocchio, "diagnose_speed": diagnose_speed,
    "diagnose_confusion": diagnose_confusion, "diagnose_confusion_wide": diagnose_confusion_wide,
    "diagnose_walks": diagnose_walks, "time_offset": time_offset, "walk": walk,
    "icub_identification": icub_identification, "demo_first_run": demo_first_run,
}
"""Benchmark -> its section's figures.  A record names its benchmark (``benchmark``); one that does
not is known by its file name's stem."""


def command(stem: str, record: Record) -> str | None:
    if isinstance(record.get("command"), str):
        return record["command"]
    if stem == "diagnose_confusion_wide_holm_subset":
        # --only keeps a pair when it names one of its effects: the single truths (and none) suffice
        truths = sorted({(d["truth"] or ["none"])[0] for d in record["details"] if len(d["truth"]) <= 1})
        return ("python benchmarks/diagnose_confusion_wide.py --jobs 2 --fresh --only " + " ".join(truths)
                + f" --out benchmarks/results/{stem}.json")
    return COMMANDS.get(stem)


def section(stem: str, record: Record) -> list[str]:
    kind = record.get("benchmark", stem)
    render = SECTIONS.get(kind) or SECTIONS.get(stem)
    cmd = command(stem, record)
    out = [f"## {stem}", "", f"Record: `benchmarks/results/{stem}.json`.  "
                             f"Command: {f'`{cmd}`' if cmd else 'not recorded'}.", "",
           f"Machine: {machine_line(record)}.", ""]
    out += render(record) if render else scalar_table(record, skip=("machine", "benchmark"))
    return out + [""]


def render_all(results: Path = RESULTS) -> str:
    """The whole page from every ``*.json`` of ``results``, in file-name order."""
    paths = sorted(results.glob("*.json"))
    lines = ["# Results", "",
             "<!-- Generated by `python benchmarks/results_md.py` from benchmarks/results/*.json: edit the "
             "benchmarks, not this page. -->", "",
             "Every figure below is read from a benchmark's JSON record in `benchmarks/results/`, written by the "
             "command shown with it on the machine it names (timings depend on that machine and its load). "
             "Rerun the command, then `python benchmarks/results_md.py`, to bring a section up to date.", "",
             "Records:", ""]
    lines += [f"- [{p.stem}](#{p.stem})" for p in paths] + [""]
    for path in paths:
        lines += section(path.stem, json.loads(path.read_text(encoding="utf-8")))
    return "\n".join(lines).rstrip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="only compare with the committed page (exit status 1 "
                                                         "when it differs)")
    ap.add_argument("--output", type=Path, default=OUTPUT)
    args = ap.parse_args(argv)
    text = render_all()
    if args.check:
        current = args.output.read_text(encoding="utf-8") if args.output.exists() else ""
        if current != text:
            print(f"{args.output} is out of date: run python benchmarks/results_md.py", file=sys.stderr)
            return 1
        return 0
    args.output.write_text(text, encoding="utf-8")
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
