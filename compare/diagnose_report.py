"""Diagnosis reports: a folder with index.html, diagnosis.json and matplotlib figures.

Figures are drawn from a :class:`~flexforce.compare.diagnose.Diagnosis`; plot functions draw on a
given ``Axes`` and never show anything (like :mod:`flexforce.compare.report`).
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

from flexforce.compare.report import LABELS, report_folder  # noqa: E402

BEFORE, AFTER = "tab:red", "tab:green"


# ----------------------------------------------------------------------------------------------
# Plot functions: each draws on the Axes it is given
# ----------------------------------------------------------------------------------------------


def plot_family(ax, est, family: str, flags=(), title: str = ""):
    """Whitened residual of every axis of ``family`` over time; flagged spans shaded."""
    r = est.residuals[family]
    labels = est.residual_labels.get(family, ())
    for j in range(r.shape[1]):
        ax.plot(est.time, r[:, j], lw=0.6, label=labels[j] if j < len(labels) else str(j))
    for f in flags:
        if f.family == family:
            ax.axvspan(f.start_s, f.end_s, color="tab:orange", alpha=0.25, lw=0)
    ax.axhline(3, color="k", lw=0.5, ls="--")
    ax.axhline(-3, color="k", lw=0.5, ls="--")
    ax.set_ylabel(f"{title}{family} [σ]", fontsize=8)
    ax.grid(alpha=0.3)
    if r.shape[1] <= 12:
        ax.legend(loc="upper right", fontsize=6, ncol=6)


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


def _screen_cells(c, level) -> str:
    s = getattr(c, "screen", None)
    if s is None:
        return "<td>–</td><td>–</td><td>–</td>"
    return f"<td>{s.statistic:.1f}</td><td>{s.dof:.1f}</td><td>{s.p_value:.2g}</td>"


def ranking_html(diag) -> str:
    rows = []
    level = diag.criterion.get("screen_level")
    for i, c in enumerate(diag.ranking, 1):
        if c.error:
            rows.append(f"<tr><td>{i}</td><td>{html.escape(c.effect)}</td><td colspan=10>cannot be fitted: "
                        f"{html.escape(c.error)}</td></tr>")
            continue
        windows = ""
        if c.screen is not None and c.screen.kind == "windowed" and level is not None:
            spans = [f"{w.start_s:.2f}–{w.end_s:.2f} s" for w in c.screen.passing_windows(level)]
            windows = f" (score windows passing: {', '.join(spans) or 'none'})"
        if not c.refitted:
            rows.append(f"<tr><td>{i}</td><td style='text-align:left'>{html.escape(c.effect)}</td>"
                        f"{_screen_cells(c, level)}<td>–</td><td colspan=4 style='text-align:left'>not refitted: "
                        f"score p = {c.screen.p_value:.2g} ≥ {level}</td><td>no</td>"
                        f"<td style='text-align:left'>{html.escape(windows)}</td></tr>")
            continue
        rows.append(f"<tr><td>{i}</td><td style='text-align:left'>{html.escape(c.effect)}</td>{_screen_cells(c, level)}"
                    f"<td>{c.round}</td>"
                    f"<td>{c.score:.1f}</td><td>{c.lr:.1f}</td><td>{c.effective_dof:.1f}</td><td>{c.p_value:.2g}</td>"
                    f"<td>{'<b>yes</b>' if c.significant else ('implausible' if c.implausible else 'no')}</td>"
                    f"<td style='text-align:left'>{html.escape((c.finding or c.summary) + windows)}</td></tr>")
    return ("<table><tr><th>#</th><th>effect</th><th>score test T</th><th>ν (T)</th><th>p (T)</th><th>round</th>"
            "<th>score (BIC)</th><th>2ΔC</th><th>ν</th><th>p</th>"
            "<th>significant</th><th>estimate</th></tr>" + "".join(rows) + "</table>")


def identifiability_html(diag) -> str:
    """The candidates the recording does not fully see and the pairs it cannot tell apart."""
    ident = getattr(diag, "identifiability", None)
    if ident is None:
        err = getattr(diag, "identifiability_error", None)
        return f"<p>Not computed{': ' + html.escape(err) if err else ''}.</p>"
    items = [f"<li>{html.escape(c.effect)}: {html.escape(c.text())}</li>" for c in ident.not_seen()]
    items += [f"<li>{html.escape(t)}</li>" for t in diag.identifiability_notes()]
    return "<ul>" + ("".join(items) or "<li>every candidate seen, no pair correlated above "
                     f"{ident.threshold}</li>") + "</ul>"


def flags_html(flags) -> str:
    if not flags:
        return "<p>None: every window is consistent with its noise.</p>"
    rows = "".join(
        f"<tr><td style='text-align:left'>{html.escape(f.estimator)}</td><td style='text-align:left'>"
        f"{html.escape(f.family)}</td><td style='text-align:left'>{html.escape(f.axis)}</td>"
        f"<td>{f.start_s:.2f}–{f.end_s:.2f}</td><td>{_fmt(f.size)} {html.escape(f.unit)}</td>"
        f"<td>{_fmt(f.mean)} {html.escape(f.unit)}</td><td>{f.rms_sigma:.1f}</td>"
        f"<td>{f.chi2:.0f} &gt; {f.bound:.0f}</td></tr>"
        for f in flags)
    return ("<table><tr><th>estimator</th><th>family</th><th>axis</th><th>time [s]</th><th>RMS size</th><th>mean</th>"
            "<th>RMS [σ]</th><th>χ² &gt; bound</th></tr>" + rows + "</table>")


def comparison_html(diag) -> str:
    b, a = diag.before, diag.after
    head = "<tr><th></th><th>before</th>" + ("<th>after</th>" if a else "") + "</tr>"
    rows = []
    for k in b.rmse:
        if b.rmse.get(k) is None and (a is None or a.rmse.get(k) is None):
            continue
        rows.append(f"<tr><th>RMSE {LABELS.get(k, k)}</th><td>{_fmt(b.rmse.get(k))}</td>"
                    + (f"<td>{_fmt(a.rmse.get(k))}</td>" if a else "") + "</tr>")
    rows.append(f"<tr><th>flagged windows</th><td>{len(b.flags)}</td>" + (f"<td>{len(a.flags)}</td>" if a else "")
                + "</tr>")
    rows.append(f"<tr><th>data cost C</th><td>{b.cost_data:.1f}</td>" + (f"<td>{a.cost_data:.1f}</td>" if a else "")
                + "</tr>")
    return "<table>" + head + "".join(rows) + "</table>"


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
            f"p < {level} are refitted (docs/diagnostics.md, \"Screening\").")


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
    info = diag.recording
    hidden = info.get("hidden_effects") or []
    hidden_html = "".join(f"<li>{html.escape(json.dumps(h))}</li>" for h in hidden) or "<li>none known</li>"
    crit = diag.criterion
    ekf_flags = diag.ekf.flags if diag.ekf is not None else []
    nis = ""
    if diag.ekf is not None and diag.ekf.metrics.nis is not None:
        lo, hi = diag.ekf.metrics.nis_bounds
        nis = f"<p>EKF mean NIS {diag.ekf.metrics.nis:.2f} (95% band for a consistent filter {lo:.2f}–{hi:.2f}).</p>"
    page = f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:auto}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:3px 6px;text-align:right}}img{{max-width:100%}}</style></head>
<body><h1>{html.escape(title)}</h1>
<p>Robot <b>{html.escape(str(info.get('robot')))}</b>, {info.get('samples')} samples
({_fmt(info.get('duration_s'))} s). {html.escape(info.get('description') or '')}</p>
<p>Hidden effects in the data (simulated recordings):</p><ul>{hidden_html}</ul>
<h2>What this recording can tell apart</h2>
<p>At the nominal fit, before any refit: the candidates with a direction the recording does not excite, and the
pairs whose score directions correlate above the threshold (docs/diagnostics.md, "Identifiability").</p>
{identifiability_html(diag)}
<h2>Which effect is missing</h2>
<p>{html.escape(_screen_sentence(crit))}</p>
<p>Each candidate that passes is refitted on top of the effects already selected and scored by the gain in log
marginal likelihood (Laplace: the data cost, the priors of the per-step states and their Occam factor),
2ΔE, less ν ln n for each of its constant unknowns (BIC), with n = {crit.get('n_residuals')} scalar residuals
(ln n = {_fmt(crit.get('penalty_per_dof'))}); 2ΔE is in the column 2ΔC and ν is the effective degrees of freedom
the effect adds (docs/diagnostics.md, "The scoring"). Significant: score &gt; 0 and likelihood-ratio p &lt;
{crit.get('alpha')}. Selected (greedy forward selection): <b>{html.escape(', '.join(diag.selected) or 'none')}</b>.</p>
{ranking_html(diag)}
{''.join(f"<p><b>Not told apart:</b> {html.escape(a)}.</p>" for a in diag.ambiguities())}
<h2>Where the nominal model fails</h2>
<p>Windows where a whitened residual exceeds its χ² bound (Bonferroni-corrected over all windows and axes);
sizes are the RMS and mean of the residual in its physical unit.</p>
{flags_html(diag.before.flags + ekf_flags)}
{nis}
<h2>Before and after{(' adding ' + html.escape(', '.join(diag.added))) if diag.added else ''}</h2>
{comparison_html(diag)}
{('<h3>Flagged windows after</h3>' + flags_html(diag.after.flags)) if diag.after is not None else
 '<p>Nothing added: rerun with <code>--add NAME</code> (or <code>--add auto</code>) to compare.</p>'}
{''.join(f'<h2>{html.escape(f[:-4])}</h2><img src="{f}" alt="{f}">' for f in written)}
<p><small>Numbers: <a href="diagnosis.json">diagnosis.json</a>. Fitted with {html.escape(str(crit.get('fit')))}.
</small></p>
</body></html>
"""
    (out / "index.html").write_text(page)
