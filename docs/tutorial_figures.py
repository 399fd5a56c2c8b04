"""Regenerate the numbers of docs/tutorial.md from the run of its commands.

    python docs/tutorial_figures.py            # run the tutorial's commands, rewrite docs/tutorial.md
    python docs/tutorial_figures.py --check    # run them, exit 1 if a number of the tutorial differs
    python docs/tutorial_figures.py --images   # also copy the reports' figures to docs/figures/tutorial_*.png

The tutorial marks each generated number ``<!--n:KEY-->value<!--/n-->`` and each generated block
``<!--block:KEY-->`` ... ``<!--/block-->`` (HTML comments: invisible once rendered); this script
runs :data:`COMMANDS` through the command line (``flexforce.cli.main``, the reports written to a
temporary folder or ``--out``), reads their diagnosis.json and fills the marks in (:func:`numbers`).
A mark the run has no number for raises ``KeyError`` naming it.  About 80 s on two cores.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
import tempfile
from pathlib import Path

TUTORIAL = Path(__file__).with_name("tutorial.md")
COMMANDS = {"diag": ["diagnose", "push-com", "-o", "{out}/diag", "--add", "auto", "-q"],
            "added": ["diagnose", "push-com", "-o", "{out}/added", "--add", "external-wrench", "--add", "com-offset",
                      "--no-rank", "-q"]}
"""The tutorial's commands (its code blocks show them without ``-o``'s folder prefix and ``-q``)."""
IMAGES = {"diag/residuals_before.png": "tutorial_residuals_before.png", "diag/scores.png": "tutorial_scores.png",
          "added/before_after.png": "tutorial_before_after.png",
          "added/residuals_after.png": "tutorial_residuals_after.png",
          "added/external_wrench.png": "tutorial_external_wrench.png"}
"""Report figure -> docs/figures/ name (``--images``)."""

NUMBER = re.compile(r"<!--n:([\w.]+)-->(.*?)<!--/n-->")
BLOCK = re.compile(r"<!--block:([\w.]+)-->\n(.*?)<!--/block-->", re.S)


def run(out: Path) -> dict[str, dict]:
    """Run :data:`COMMANDS` into ``out``; their diagnosis.json by name (raises RuntimeError on a
    command that fails)."""
    from flexforce.cli import main

    out.mkdir(parents=True, exist_ok=True)
    data = {}
    for name, template in COMMANDS.items():
        argv = [a.format(out=out) for a in template]
        rc = main(argv)
        if rc != 0:
            raise RuntimeError(f"flexforce {' '.join(argv)} exited with {rc}")
        data[name] = json.loads((out / name / "diagnosis.json").read_text())
    return data


def _g(x: float, digits: int = 3) -> str:
    return f"{x:.{digits}g}"


def _row(data: dict, effect: str, round_: int | None = None) -> dict:
    """The first refitted row of ``effect`` (of round ``round_`` when given)."""
    for r in data["rounds"]:
        for c in r:
            if c["effect"] == effect and c["score"] is not None and (round_ is None or c["round"] == round_):
                return c
    raise KeyError(f"{effect}: no refitted row in the run")


def _flags_block(data: dict, families: tuple[str, ...] = ("newton_euler", "imu"), limit: int = 6) -> str:
    """The nominal fit's flagged windows of ``families`` (the batch smoother's), largest first."""
    names = {"newton_euler": "Newton–Euler", "imu": "IMU", "contact": "contact"}
    rows = [f for f in data["before"]["flagged_windows"] if f["estimator"] == "batch" and f["family"] in families]
    rows.sort(key=lambda f: -f["rms_sigma"])
    lines = ["| family | axis | time | RMS size | mean | RMS [σ] |", "|---|---|---|---|---|---|"]
    for f in rows[:limit]:
        lines.append(f"| {names.get(f['family'], f['family'])} | {f['axis'].split(' [')[0]} | "
                     f"{f['start_s']:.1f}–{f['end_s']:.1f} s | {_g(f['size'])} {f['unit']} | "
                     f"{f['mean']:+.3g} {f['unit']} | {f['rms_sigma']:.1f} |")
    return "\n".join(lines) + "\n"


def _ranking_block(data: dict) -> str:
    """The ranking, one line per candidate: its score, status and what the row says."""
    lines = ["```", f"{'#':>2s} {'effect':22s} {'round':>5s} {'score':>8s}  status"]
    for i, c in enumerate(data["ranking"], 1):
        score = "-" if c["score"] is None else f"{c['score']:.1f}"
        lines.append(f"{i:2d} {c['effect']:22s} {c['round']:5d} {score:>8s}  {c['status']}")
    return "\n".join(lines + ["```"]) + "\n"


def _errors_block(data: dict) -> str:
    """The errors against the truth before and after (mm, mrad: the report's units)."""
    cols = [("force_N", "force [N]", 1.0), ("moment_Nm", "moment [N m]", 1.0), ("cop_m", "CoP [mm]", 1e3),
            ("rotation_rad", "tilt [mrad]", 1e3), ("hand_m", "hands [mm]", 1e3)]
    lines = ["| | " + " | ".join(c[1] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for label, view in (("nominal model", data["before"]), (" + ".join(["", *data["added"]]).strip(), data["after"])):
        lines.append(f"| {label} | " + " | ".join(_g(view["rmse"][k] * s) for k, _, s in cols) + " |")
    return "\n".join(lines) + "\n"


def numbers(data: dict[str, dict]) -> dict[str, str]:
    """Every mark of the tutorial, from the run's diagnosis.json (``diag``: ranked, ``--add auto``;
    ``added``: the push and the CoM offset added by hand)."""
    diag, added = data["diag"], data["added"]
    mrad = 1e3
    com = _row(diag, "com-offset", 2)  # the round that took it, on top of the push
    push = _row(diag, "external-wrench", 1)
    chk = push["check"]
    push_after = added["after"]["effect_estimates"]["external-wrench"]["windows"][0]
    com_after = added["after"]["effect_estimates"]["com-offset"]
    auto = diag["after"]
    out = {
        "flags_before": str(len(diag["before"]["flagged_windows"])),
        "nis": f"{diag['ekf']['nis']:.1f}",
        "com_x_mm": f"{com['parameters']['value'][0] * 1e3:.1f} ± {com['parameters']['std'][0] * 1e3:.1f}",
        "com_score": f"{com['score']:.1f}",
        "push_score": f"{push['score']:.1f}",
        "push_force_before": _g(chk["before"]["force_N"]), "push_force_after": _g(chk["after"]["force_N"]),
        "push_steady_N": f"{push['parameters']['steady']['equivalent_force'][0]:.1f}",
        "push_steady_mm": f"{push['parameters']['steady']['com_offset_equivalent_m'][0] * 1e3:.1f}",
        "auto_flags": str(len(auto["flagged_windows"])),
        "auto_force": _g(auto["rmse"]["force_N"]), "auto_cop_mm": _g(auto["rmse"]["cop_m"] * 1e3),
        "auto_tilt_mrad": _g(auto["rmse"]["rotation_rad"] * mrad),
        "added_flags": str(len(added["after"]["flagged_windows"])),
        "added_force": _g(added["after"]["rmse"]["force_N"]),
        "added_tilt_mrad": _g(added["after"]["rmse"]["rotation_rad"] * mrad),
        "push_start": f"{push_after['start_s']:.2f}", "push_end": f"{push_after['end_s']:.2f}",
        "push_peak_N": f"{push_after['peak_force'][0]:.0f}", "push_peak_s": f"{push_after['peak_s']:.2f}",
        "com_after_mm": f"{com_after['value'][0] * 1e3:.1f} ± {com_after['std'][0] * 1e3:.1f}",
        "ne_fx_before": f"{added['before']['residual_rms']['newton_euler']['F_x [N]']:.2f}",
        "ne_fx_after": f"{added['after']['residual_rms']['newton_euler']['F_x [N]']:.2f}",
        "acc_x_before": f"{added['before']['residual_rms']['imu']['acc_x [m/s^2]']:.2f}",
        "acc_x_after": f"{added['after']['residual_rms']['imu']['acc_x [m/s^2]']:.2f}",
    }
    for key in ("cop_m", "rotation_rad", "hand_m", "force_N"):
        b, a = added["before"]["rmse"][key], added["after"]["rmse"][key]
        out[f"fall_{key}"] = f"{b / a:.2g}"
    out.update({"block:flags": _flags_block(diag), "block:ranking": _ranking_block(diag),
                "block:verdict": f"> {diag['verdict']}\n", "block:verdict_added": f"> {added['verdict']}\n",
                "block:errors": _errors_block(added)})
    return out


def render(text: str, values: dict[str, str]) -> str:
    """``text`` with every mark filled from ``values`` (raises KeyError naming a mark without one)."""
    def number(m):
        return f"<!--n:{m.group(1)}-->{values[m.group(1)]}<!--/n-->"

    def block(m):
        return f"<!--block:{m.group(1)}-->\n{values['block:' + m.group(1)]}<!--/block-->"

    return BLOCK.sub(block, NUMBER.sub(number, text))


def differences(text: str, values: dict[str, str]) -> list[str]:
    """The marks of ``text`` whose value is not the run's: ``key: 'in the text' != 'from the run'``."""
    out = [f"{m.group(1)}: {m.group(2)!r} != {values[m.group(1)]!r}" for m in NUMBER.finditer(text)
           if m.group(2) != values[m.group(1)]]
    out += [f"block {m.group(1)} differs" for m in BLOCK.finditer(text) if m.group(2) != values["block:" + m.group(1)]]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if a number of the tutorial differs")
    parser.add_argument("--images", action="store_true", help="copy the figures to docs/figures/")
    parser.add_argument("--out", type=Path, help="keep the reports in this folder (default: a temporary one)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        values = numbers(run(out))
        text = TUTORIAL.read_text()
        if args.check:
            diff = differences(text, values)
            print("\n".join(diff) or "the tutorial's numbers are the run's")
            return 1 if diff else 0
        TUTORIAL.write_text(render(text, values))
        if args.images:
            for src, dst in IMAGES.items():
                if (out / src).exists():
                    shutil.copyfile(out / src, TUTORIAL.parent / "figures" / dst)
    print(f"rewrote {TUTORIAL}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
