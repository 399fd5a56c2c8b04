"""Diagnosis reports: a folder with index.html, diagnosis.json and matplotlib figures.

Figures are drawn from a :class:`~flexforce.compare.diagnostics.results.Diagnosis`; plot functions draw on a
given ``Axes`` and never show anything (like :mod:`flexforce.compare.reports.comparison`).
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

from flexforce.compare.diagnostics import text  # noqa: E402
from flexforce.compare.reports.comparison import (  # noqa: E402
    LABELS,
    environment,
    plot_family,
    report_folder,
)

BEFORE, AFTER = "tab:red", "tab:green"


# ----------------------------------------------------------------------------------------------
# Plot functions: each draws on the Axes it is given
# ----------------------------------------------------------------------------------------------


def plot_nis(ax, ekf, level: float = 0.99):
    """NIS of the EKF's 6-D innovation with its per-step chi-square bound; flagged spans shaded."""
    m = ekf.metrics
    if m.nis_series is None:
        ax.text(0.5, 0.5, "no innovation", transform=ax.transAxes, ha="center")
        return
    ax.semilogy(ekf.estimate.time, np.maximum(m.nis_series, 1e-6), color="tab:purple", lw=0.6, label="EKF NIS")
    ax.axhline(6, color="k", ls="--", lw=0.8, label="expected (6)")
    ax.axhline(stats.chi2.ppf(level, 6), color="k", ls=":", lw=0.8, label=f"{100 * level:.0f}% bound")
    for f in ekf.flags:
        ax.axvspan(f.start_s, f.end_s, color="tab:orange", alpha=0.25, lw=0)
    ax.set_ylabel("EKF NIS (6-D)", fontsize=8)
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="upper right", fontsize=6, ncol=3)


def figure_residuals(snap, ekf=None, title: str = ""):
    fams = list(snap.estimate.residuals)
    rows = len(fams) + (1 if ekf is not None else 0)
    fig, axes = plt.subplots(rows, 1, figsize=(10, 1.9 * rows + 1), sharex=True, squeeze=False)
    for ax, fam in zip(axes[:, 0], fams):
        plot_family(ax, snap.estimate, fam, snap.flags)
    if ekf is not None:
        plot_nis(axes[-1, 0], ekf)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(f"{title}: whitened residuals (dashed ±3σ; shaded: windows inconsistent with the noise)")
    return fig


def plot_bars(ax, labels, before, after, ylabel: str):
    x = np.arange(len(labels))
    wid = 0.4 if after is not None else 0.8
    ax.bar(x - (wid / 2 if after is not None else 0), before, wid, color=BEFORE, label="before")
    if after is not None:
        ax.bar(x + wid / 2, after, wid, color=AFTER, label="after")
    ax.set_xticks(x)
    ax.set_xticklabels(labels, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=8)


def figure_before_after(diag):
    b, a = diag.before, diag.after
    keys = [(fam, ax) for fam, d in b.residual_rms.items() for ax in d]
    has_truth = any(v is not None for v in b.rmse.values())
    rows = 2 if has_truth else 1
    fig, axes = plt.subplots(rows, 1, figsize=(11, 4 * rows + 1), squeeze=False)
    plot_bars(axes[0, 0], [f"{f}: {x}" for f, x in keys], [b.residual_rms[f][x] for f, x in keys],
              None if a is None else [a.residual_rms.get(f, {}).get(x, np.nan) for f, x in keys],
              "residual RMS [σ]")
    axes[0, 0].axhline(1, color="k", ls="--", lw=0.8)
    if has_truth:
        ks = [k for k in b.rmse if b.rmse.get(k) is not None]
        ref = np.array([b.rmse[k] for k in ks])
        plot_bars(axes[1, 0], [LABELS.get(k, k) for k in ks], np.ones(len(ks)),
                  None if a is None else np.array([a.rmse[k] if a.rmse[k] is not None else np.nan for k in ks]) / ref,
                  "RMSE relative to before")
    title = "Before" + (f" and after adding {', '.join(diag.added)}" if a is not None else " (nominal model)")
    fig.suptitle(f"{title}: residual RMS (1 under the model) and estimation errors")
    fig.tight_layout()
    return fig


def figure_scores(diag):
    cands = [c for c in diag.ranking if c.score is not None]
    if not cands:
        return None
    fig, ax = plt.subplots(figsize=(8, 0.45 * len(cands) + 1.5))
    y = np.arange(len(cands))[::-1]
    ax.barh(y, [c.score for c in cands], color=["tab:green" if c.significant else "tab:gray" for c in cands])
    ax.set_yticks(y)
    ax.set_yticklabels([f"{c.effect} (round {c.round})" for c in cands], fontsize=8)
    ax.axvline(0, color="k", lw=0.8)
    ax.set_xscale("symlog", linthresh=10)
    ax.set_xlabel("BIC score: 2 ΔC − ν ln n (green: significant)")
    ax.grid(alpha=0.3, axis="x")
    fig.tight_layout()
    return fig


# ----------------------------------------------------------------------------------------------
# The report folder
# ----------------------------------------------------------------------------------------------


def _fmt(x, digits: int = 3) -> str:
    if x is None:
        return "–"
    return f"{x:.{digits}g}"


def figure_wrench(diag):
    """The external wrench estimated with the added effects, ±2σ, over the true one when known."""
    if diag.after is None:
        return None
    rep = (diag.after.estimate.effects or {}).get("external-wrench")
    if not rep or "wrench" not in rep:
        return None
    t = np.asarray(rep["t_s"])
    W, S = np.asarray(rep["wrench"]), np.asarray(rep["wrench_std"])
    truth = diag.truth_external_wrench
    fig, axes = plt.subplots(2, 1, figsize=(10, 5.5), sharex=True)
    for row, (ax, unit) in enumerate(zip(axes, ("force [N]", "moment about the origin [N m]"))):
        for j, (axis, color) in enumerate(zip("xyz", ("C0", "C1", "C2"))):
            c = 3 * row + j
            ax.plot(t, W[:, c], color=color, lw=1.0, label=f"{axis} estimated")
            ax.fill_between(t, W[:, c] - 2 * S[:, c], W[:, c] + 2 * S[:, c], color=color, alpha=0.15, lw=0)
            if truth is not None and len(truth) == len(t):
                ax.plot(t, truth[:, c], color=color, lw=0.8, ls="--", label=f"{axis} true")
        ax.set_ylabel(unit, fontsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=6, loc="upper left")
    axes[-1].set_xlabel("time [s]")
    fig.suptitle("External wrench with " + ", ".join(diag.added) + " (band: ±2σ; dashed: truth)")
    fig.tight_layout()
    return fig


def _screen_sentence(crit) -> str:
    level = crit.get("screen_level")
    if level is None:
        return "No screening: every candidate was refitted."
    return (f"Screening: at the nominal fit, every candidate's score (Lagrange-multiplier) test T = gᵀ S⁻¹ g "
            f"(g the cost's gradient in the effect's unknowns at zero, S their information with the states "
            f"eliminated) against χ² with the effect's effective dof ν; per-step effects are tested on "
            f"{crit.get('screen_window_s')} s windows (Bonferroni over the windows). Only candidates with "
            f"p < {level} are refitted{_refit_clause(crit)}; once an effect is selected, the remaining candidates "
            f"are screened again with it in the model (docs/diagnostics.md, \"Screening\").")


def _refit_clause(crit) -> str:
    best = crit.get("refit_best")
    if not best:
        return ""
    return (f", at most the {best} with the strongest test per round (with those the identifiability table "
            f"cannot tell from them; the others wait for the next round)")


def write_diagnosis(diag, out: str | Path, title: str = "flexforce diagnosis") -> Path:
    """Write DIR/diagnosis.json, DIR/index.html and the figures; returns the folder."""
    target = Path(out)
    with report_folder(target) as out:
        _write_diagnosis(diag, out, title)
    return target


def _write_diagnosis(diag, out: Path, title: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "diagnosis.json").write_text(json.dumps(diag.to_json(), indent=2, allow_nan=False))
    figures = {"residuals_before.png": lambda: figure_residuals(diag.before, diag.ekf, "Nominal model"),
               "scores.png": lambda: figure_scores(diag),
               "before_after.png": lambda: figure_before_after(diag)}
    if diag.after is not None:
        figures["residuals_after.png"] = lambda: figure_residuals(diag.after, None, "With " + ", ".join(diag.added))
        figures["external_wrench.png"] = lambda: figure_wrench(diag)
    written = []
    for name, make in figures.items():
        fig = make()
        if fig is None:
            continue
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        written.append(name)
    crit = diag.criterion
    level = crit.get("screen_level")
    ranking = [_ranking_row(diag, c, level) for c in diag.ranking]
    b, a = diag.before, diag.after
    comparison = [(f"RMSE {_error_label(k)}", _error(b.rmse.get(k), k), _error(a.rmse.get(k), k) if a else None)
                  for k in b.rmse if b.rmse.get(k) is not None or (a is not None and a.rmse.get(k) is not None)]
    comparison.append(("flagged windows", str(len(b.flags)), str(len(a.flags)) if a else None))
    comparison.append(("data cost C", f"{b.cost_data:.1f}", f"{a.cost_data:.1f}" if a else None))
    nis = None
    if diag.ekf is not None and diag.ekf.metrics.nis is not None:
        nis = (diag.ekf.metrics.nis, *diag.ekf.metrics.nis_bounds)
    ident = getattr(diag, "identifiability", None)
    if ident is None:
        err = getattr(diag, "identifiability_error", None)
        identifiability: dict = {"computed": False, "error": err, "items": []}
    else:
        identifiability = {"computed": True, "threshold": ident.threshold,
                           "items": diag.identifiability_items(),
                           "detectable": [f"{c.effect}: {text.detectable_text(c)}" for c in ident.candidates.values()
                                          if c.detectable]}
    page = environment().get_template("diagnosis.html.j2").render(
        identifiability=identifiability,
        title=title, info=diag.recording, crit=crit, level=level,
        hidden=[json.dumps(h) for h in diag.recording.get("hidden_effects") or []],
        screen_sentence=_screen_sentence(crit), selected=diag.selected, ranking=ranking,
        verdict=diag.verdict(), added_values=diag.added_values(), selected_line=selected_line(diag),
        units=text.UNITS, glossary=GLOSSARY,
        swaps=diag.swaps, ambiguities=diag.ambiguities(), partner_checks=diag.partner_checks(),
        inconstant=diag.inconstant(),
        flags_before=[_flag_row(f) for f in diag.before.flags + (diag.ekf.flags if diag.ekf else [])],
        flags_after=[_flag_row(f) for f in a.flags] if a is not None else [],
        nis=nis, added=diag.added, after=a, comparison=comparison, figures=written)
    (out / "index.html").write_text(page)


GLOSSARY = (
    ("residual", "what a sensor read minus what the fitted model predicts, divided by the sensor's noise (σ): "
                 "about 1 in size when the model is right, far above 1 where it misses something."),
    ("flagged window", "a stretch of the recording (0.5 s) where a residual is too large to be noise."),
    ("score test (T)", "a quick test at the nominal fit, before refitting anything: how much a candidate could "
                       "lower the misfit; only candidates that pass it (small p) are refitted."),
    ("2 ln L, 2ΔE", "twice the gain in log-likelihood (the data's fit, with the priors and the Occam factor) when "
                    "the effect is added; larger is a better fit."),
    ("Occam factor", "the price a model pays for unknowns the data do not pin down: an effect that explains "
                     "little with many unknowns loses evidence."),
    ("BIC score", "2ΔE less ln n per constant unknown (n the residuals): positive means the better fit is worth "
                  "the extra unknowns; the ranking's score."),
    ("p-value", "how likely a gain this large would be from noise alone, were the effect absent."),
    ("Holm", "each round tests its m candidates at α/m, so that the chance of any false finding in the round "
             "stays below α."),
    ("significant", "BIC score above 0 and p below its level: the effect is found."),
    ("check", "the errors of the fit with the effect against what the fit did not use (the truth of a simulated "
              "recording, the F/T and motion capture of a real one); an effect that raises one is turned down."),
    ("identifiability", "whether the recording's motion can see a candidate at all, and which pairs of candidates "
                        "it cannot tell apart (they change the predictions alike)."),
)
"""The Details section's glossary: (term, its meaning in plain words)."""


def _flag_row(f) -> dict:
    """A flagged window as the page shows it: its size and mean in the report's units (mm, mrad)."""
    def shown(x):
        return None if x is None else text.display(float(x), f.unit)[0]

    axis, _, unit = f.axis.partition(" [")
    unit = unit.rstrip("]")
    return {"estimator": f.estimator, "family": f.family,
            "axis": f"{axis} [{text.display(1.0, unit)[1]}]" if unit else f.axis, "start_s": f.start_s,
            "end_s": f.end_s, "size": shown(f.size), "mean": shown(f.mean), "unit": text.display(1.0, f.unit)[1],
            "rms_sigma": f.rms_sigma, "chi2": f.chi2, "bound": f.bound}


def selected_line(diag) -> str:
    """``com-offset`` / ``none`` / ``none; added by hand: external-wrench``: what the selection took,
    and the effects added that it did not."""
    by_hand = [n for n in diag.added if n not in diag.selected]
    line = ", ".join(diag.selected) or "none"
    if by_hand:
        line += f"; added by hand: {', '.join(by_hand)}"
    return line


def _error_label(key: str) -> str:
    """The error's name with the report's unit (:data:`text.CHECK_LABELS`)."""
    label, _, unit = text.CHECK_LABELS.get(key, (LABELS.get(key, key), 1.0, ""))
    return f"{label} [{unit.strip()}]" if unit.strip() else label


def _error(value, key: str) -> str:
    """An error in the report's unit (mm, mrad: :data:`text.CHECK_LABELS`)."""
    if value is None:
        return "–"
    return f"{value * text.CHECK_LABELS.get(key, ('', 1.0, ''))[1]:.3g}"


def _ranking_row(diag, c, level) -> dict:
    """What the page shows of one ranking row: its fitted values in the report's units, its sentence,
    its check, its constancy, and for a row not refitted, why (with what an earlier round found)."""
    windows = ""
    if c.screen is not None and c.screen.kind == "windowed" and level is not None:
        spans = [f"{w.start_s:.2f}–{w.end_s:.2f} s" for w in c.screen.passing_windows(level)]
        windows = f" (score windows passing: {', '.join(spans) or 'none'})"
    not_refitted = text.not_refitted_text(c, diag) if not c.refitted and not c.error else ""
    if c.error:
        say = f"cannot be fitted: {c.error}"
    elif not c.refitted:
        say = not_refitted
    elif c.significant:
        say = f"found (BIC score {c.score:.1f}, p = {c.p_value:.2g})"
    else:
        say = c.finding or c.summary
    values = text.effect_values(c.effect, c.parameters) if c.score is not None and c.parameters else ""
    return {"candidate": c, "screen": c.screen, "windows": windows, "not_refitted": not_refitted, "say": say,
            "verdict": "turned down by its check" if c.vetoed else c.status,
            "values": values, "check": c.check_text(diag.config.check_worse) if c.check else "",
            "constancy": text.constancy_line(c, diag.config) if c.constancy and not c.implausible else ""}


def diagnosis_summary(diag) -> dict:
    """The headline of a diagnosis (JSON): the recording, the effects selected and added, the flagged
    windows before and after, the errors before and after, each candidate's verdict."""
    data = diag.to_json()
    after = data.get("after")
    return {"verdict": data["verdict"], "added_values": data["added_values"], "selected_line": selected_line(diag),
            "recording": data["recording"], "selected": data["selected"], "added": data["added"],
            "flags_before": len(data["before"]["flagged_windows"]),
            "flags_after": len(after["flagged_windows"]) if after else None,
            "rmse_before": data["before"]["rmse"], "rmse_after": after["rmse"] if after else None,
            "ranking": [{"effect": c["effect"], "significant": c["significant"],
                         "summary": c.get("finding") or c["summary"],
                         **({"check": c["check"]["text"]} if c.get("check") else {})} for c in data["ranking"]]}


def write_diagnosis_index(out: str | Path, entries: list[tuple[str, dict]],
                          title: str = "flexforce diagnosis") -> Path:
    """Write ``out``/index.html for several recordings, each diagnosed in ``out``/<label>/.

    Args:
        entries: (label, :func:`diagnosis_summary` of its diagnosis) per recording, in order.
    """
    out = Path(out)
    view = []
    for label, s in entries:
        best = next((c for c in s["ranking"] if c["significant"]), None)
        view.append({"label": label, "link": f"{label}/index.html", "info": s["recording"], "failures": {},
                     "cells": [", ".join(s["selected"]) or "none", best["summary"] if best else "–",
                               ", ".join(s["added"]) or "–",
                               f"{s['flags_before']}" + (f" → {s['flags_after']}" if s["flags_after"] is not None
                                                         else "")]})
    page = environment().get_template("index.html.j2").render(
        title=f"{title} — {len(entries)} recordings", what="which effect the nominal model misses", entries=view,
        numbers="summary.json", aggregate_rows=[], columns=[],
        entry_columns=["significant effects", "first significant: estimate", "added", "flagged windows"])
    (out / "index.html").write_text(page)
    return out
