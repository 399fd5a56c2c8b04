"""Comparison reports: a folder with index.html, summary.json and matplotlib figures.

Figures are drawn from result objects (:class:`~flexforce.compare.runner.Comparison`,
:class:`~flexforce.datasets.estimate.Estimate`, the Recording); plot functions draw on a given
``Axes`` and never show anything.
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from flexforce.compare.metrics import RMSE_KEYS  # noqa: E402
from flexforce.factors import so3  # noqa: E402

COLORS = {"ekf": "tab:red", "fixed_lag": "tab:blue", "batch": "tab:green"}
LABELS = {
    "force_N": "force [N]", "moment_Nm": "moment [N m]", "cop_m": "CoP [m]", "rotation_rad": "rotation [rad]",
    "translation_m": "translation [m]", "hand_m": "hand [m]", "angular_velocity_rad_s": "ang. vel. [rad/s]",
    "linear_velocity_m_s": "lin. vel. [m/s]", "contact_force_N": "contact force [N]",
    "vertical_force_N": "vertical force [N]",
}


def _color(key: str) -> str:
    return COLORS.get(key, "tab:purple")


# ----------------------------------------------------------------------------------------------
# Plot functions: each draws on the Axes it is given
# ----------------------------------------------------------------------------------------------


def plot_series(ax, time, estimates: dict, value, std=None, truth=None, label: str = "", scale: float = 1.0):
    """One quantity over time: truth (black) and each estimate with a +-2 sigma band."""
    if truth is not None:
        ax.plot(time, truth * scale, color="k", lw=1.2, label="truth")
    for key, est in estimates.items():
        y = value(est) * scale
        ax.plot(est.time, y, color=_color(key), lw=0.9, label=key)
        if std is not None:
            s = std(est)
            if s is not None:
                ax.fill_between(est.time, y - 2 * s * scale, y + 2 * s * scale, color=_color(key), alpha=0.15, lw=0)
    ax.set_ylabel(label)
    ax.grid(alpha=0.3)


def _wrench_std(est, i):
    if est.wrench_cov is None:
        return None
    return np.sqrt(np.maximum(est.wrench_cov[:, i, i], 0.0))


def _cop_std(est, i):
    if est.cop_cov is None:
        return None
    return np.sqrt(np.maximum(est.cop_cov[:, i, i], 0.0))


def _state_std(est, i):
    s = est.state_std()
    return None if s is None else s[:, i]


def _rotvec(R):
    return np.array([so3.log(r) for r in R])


def figure_forces(comp, rec):
    est = comp.estimates
    t = rec.time
    tr = rec.truth
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    plot_series(axes[0], t, est, lambda e: e.total_wrench[:, 2], lambda e: _wrench_std(e, 2),
                None if tr is None else tr.total_wrench[:, 2], "total F_z [N]")
    plot_series(axes[1], t, est, lambda e: e.cop[:, 0], lambda e: _cop_std(e, 0),
                None if tr is None else tr.cop[:, 0], "CoP x [cm]", scale=100)
    plot_series(axes[2], t, est, lambda e: e.cop[:, 1], lambda e: _cop_std(e, 1),
                None if tr is None else tr.cop[:, 1], "CoP y [cm]", scale=100)
    if tr is None and rec.ft is not None:
        fz = np.nansum(rec.ft[:, :, 2], axis=1)
        axes[0].plot(t, fz, color="k", lw=1.0, label="F/T sum")
    axes[0].legend(loc="upper right", fontsize=8, ncol=4)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle("Contact force and centre of pressure (bands: ±2σ)")
    return fig


def figure_flexibility(comp, rec):
    est = comp.estimates
    t = rec.time
    tr = rec.truth
    true_rv = None if tr is None else _rotvec(tr.R)
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for i, name in enumerate(("roll", "pitch")):
        plot_series(axes[i], t, est, lambda e, i=i: _rotvec(e.R)[:, i], lambda e, i=i: _state_std(e, i),
                    None if true_rv is None else true_rv[:, i], f"{name} [mrad]", scale=1000)
    plot_series(axes[2], t, est, lambda e: e.t[:, 2], lambda e: _state_std(e, 5),
                None if tr is None else tr.t[:, 2], "sinking t_z [mm]", scale=1000)
    axes[0].legend(loc="upper right", fontsize=8, ncol=4)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle("Flexibility: rotation vector and vertical translation (bands: ±2σ)")
    return fig


def figure_errors(comp, rec):
    keys = [k for k in ("force_N", "cop_m", "rotation_rad", "hand_m")
            if any(np.isfinite(m.errors.get(k, np.array([np.nan]))).any() for m in comp.metrics.values())]
    if not keys:
        return None
    fig, axes = plt.subplots(len(keys), 1, figsize=(10, 2.2 * len(keys) + 1), sharex=True, squeeze=False)
    for ax, key in zip(axes[:, 0], keys):
        for name, m in comp.metrics.items():
            e = m.errors.get(key)
            if e is not None:
                ax.semilogy(rec.time, np.maximum(e, 1e-12), color=_color(name), lw=0.8, label=name)
        ax.set_ylabel(LABELS[key])
        ax.grid(alpha=0.3, which="both")
    axes[0, 0].legend(loc="upper right", fontsize=8, ncol=3)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle("Estimation errors against ground truth")
    return fig


def figure_residuals(comp, rec):
    fams = []
    for key, est in comp.estimates.items():
        for fam in est.residuals:
            if (key, fam) not in fams:
                fams.append((key, fam))
    if not fams:
        return None
    fig, axes = plt.subplots(len(fams), 1, figsize=(10, 1.8 * len(fams) + 1), sharex=True, squeeze=False)
    for ax, (key, fam) in zip(axes[:, 0], fams):
        est = comp.estimates[key]
        r = est.residuals[fam]
        labels = est.residual_labels.get(fam, ())
        for j in range(r.shape[1]):
            ax.plot(est.time, r[:, j], lw=0.6, label=labels[j] if j < len(labels) else str(j))
        ax.axhline(3, color="k", lw=0.5, ls="--")
        ax.axhline(-3, color="k", lw=0.5, ls="--")
        ax.set_ylabel(f"{key}\n{fam} [σ]", fontsize=8)
        ax.grid(alpha=0.3)
        if r.shape[1] <= 12:
            ax.legend(loc="upper right", fontsize=6, ncol=6)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle("Whitened residuals per factor family (dashed: ±3σ)")
    return fig


def figure_consistency(comp, rec):
    series = [(k, m) for k, m in comp.metrics.items() if m.nees_series is not None or m.nis_series is not None]
    if not series:
        return None
    fig, axes = plt.subplots(2, 1, figsize=(10, 5), sharex=True)
    for key, m in series:
        if m.nees_series is not None:
            axes[0].semilogy(rec.time, np.maximum(m.nees_series, 1e-6), color=_color(key), lw=0.6, label=key)
        if m.nis_series is not None:
            axes[1].semilogy(rec.time, np.maximum(m.nis_series, 1e-6), color=_color(key), lw=0.6, label=key)
    axes[0].axhline(18, color="k", ls="--", lw=0.8)
    axes[1].axhline(6, color="k", ls="--", lw=0.8)
    axes[0].set_ylabel("NEES (18-D)")
    axes[1].set_ylabel("NIS (6-D)")
    for ax in axes:
        if ax.get_legend_handles_labels()[1]:
            ax.legend(fontsize=8)
    if not any(m.nees_series is not None for _, m in series):
        axes[0].text(0.5, 0.5, "no ground truth: no NEES", ha="center", va="center", transform=axes[0].transAxes)
    axes[-1].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3, which="both")
    fig.suptitle("Consistency: dashed lines are the expected values")
    return fig


FIGURES = {
    "forces.png": figure_forces,
    "flexibility.png": figure_flexibility,
    "errors.png": figure_errors,
    "residuals.png": figure_residuals,
    "consistency.png": figure_consistency,
}


# ----------------------------------------------------------------------------------------------
# The report folder
# ----------------------------------------------------------------------------------------------


def _fmt(x, scale=1.0, digits=3):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x * scale:.{digits}g}"


def summary_table_html(summary: dict) -> str:
    """The summary table, from the very numbers of summary.json."""
    est = summary["estimators"]
    cols = [("force_N", "force RMSE [N]", 1), ("moment_Nm", "moment RMSE [N m]", 1), ("cop_m", "CoP RMSE [mm]", 1e3),
            ("rotation_rad", "rotation RMSE [mrad]", 1e3), ("translation_m", "translation RMSE [mm]", 1e3),
            ("hand_m", "hand RMSE [mm]", 1e3)]
    head = "".join(f"<th>{html.escape(c[1])}</th>" for c in cols)
    head += ("<th>NEES (18)</th><th>NIS (6)</th><th>median step [µs]</th><th>p99 step [µs]</th>"
             "<th>amortized step [µs]</th><th>total [s]</th>")
    head += "<th>peak memory [MB]</th>"
    rows = []
    for key, m in est.items():
        cells = "".join(f"<td>{_fmt(m['rmse'].get(c[0]), c[2])}</td>" for c in cols)
        nb = m.get("nees_bounds")
        nees = _fmt(m.get("nees")) + (f" <small>[{nb[0]:.1f}, {nb[1]:.1f}]</small>" if nb else "")
        nib = m.get("nis_bounds")
        nis = _fmt(m.get("nis")) + (f" <small>[{nib[0]:.2f}, {nib[1]:.2f}]</small>" if nib else "")
        tps = m.get("time_per_step_s") or {}
        cells += (f"<td>{nees}</td><td>{nis}</td><td>{_fmt(tps.get('median'), 1e6)}</td><td>{_fmt(tps.get('p99'), 1e6)}"
                  f"</td><td>{_fmt(tps.get('amortized'), 1e6)}</td><td>{_fmt(m.get('total_time_s'))}</td>"
                  f"<td>{_fmt(m.get('peak_memory_mb'))}</td>")
        rows.append(f"<tr><th>{html.escape(key)}</th>{cells}</tr>")
    return f"<table><tr><th>estimator</th>{head}</tr>{''.join(rows)}</table>"


def write_report(comp, rec, out_dir: str | Path, title: str | None = None) -> Path:
    """Write index.html, summary.json and the figures of a comparison into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = comp.summary()
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False))
    figures = []
    for name, make in FIGURES.items():
        fig = make(comp, rec)
        if fig is None:
            continue
        fig.tight_layout()
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        figures.append(name)
    info = summary["recording"]
    title = title or f"flexforce comparison — {info.get('scenario') or info.get('robot')}"
    effects = info.get("hidden_effects") or []
    eff_html = "".join(f"<li><code>{html.escape(json.dumps(e))}</code></li>" for e in effects) or "<li>none</li>"
    fail_html = "".join(f"<li><b>{html.escape(k)}</b>: {html.escape(v)}</li>" for k, v in comp.failures.items())
    rel = summary.get("rmse_relative_to_ekf", {})
    rel_rows = "".join(
        f"<tr><th>{html.escape(k)}</th>" + "".join(f"<td>{_fmt(v.get(c))}</td>" for c in RMSE_KEYS) + "</tr>"
        for k, v in rel.items())
    rel_html = (f"<h2>RMSE relative to the EKF</h2><table><tr><th></th>{''.join(f'<th>{c}</th>' for c in RMSE_KEYS)}"
                f"</tr>{rel_rows}</table>") if rel_rows else ""
    crb_html = ""
    crb = summary.get("cramer_rao")
    if crb:
        bound = crb["rmse_bound"]
        cells = "".join(f"<td>{_fmt(bound.get(c))}</td>" for c in RMSE_KEYS)
        rows = "".join(f"<tr><th>{html.escape(k)} / bound</th>"
                       + "".join(f"<td>{_fmt(v.get(c))}</td>" for c in RMSE_KEYS) + "</tr>"
                       for k, v in crb["rmse_relative_to_bound"].items())
        crb_html = (f"<h2>Cramér–Rao bound</h2><p>RMSE lower bounds of the batch problem's model (its information "
                    f"matrix at the ground truth), SI units, and each estimator's RMSE relative to them.</p>"
                    f"<table><tr><th></th>{''.join(f'<th>{c}</th>' for c in RMSE_KEYS)}</tr>"
                    f"<tr><th>bound</th>{cells}</tr>{rows}</table>")
    extra = []
    for m in comp.metrics.values():
        d = m.extra.get("hand_displacement_by_flexibility_max_m")
        if d is not None:
            extra.append(f"Uncompensated, the flexibility moves the hands by up to {d * 1000:.1f} mm.")
            break
    page = f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:auto}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:3px 6px;text-align:right}}img{{max-width:100%}}</style></head>
<body><h1>{html.escape(title)}</h1>
<p>Robot <b>{html.escape(str(info.get('robot')))}</b>, {info.get('samples')} samples at {_fmt(info.get('rate_hz'))} Hz
({_fmt(info.get('duration_s'))} s). {html.escape(info.get('description') or '')}</p>
<p>Hidden effects in the data (not in the estimators' nominal model):</p><ul>{eff_html}</ul>
<h2>Summary</h2>{summary_table_html(summary)}
<p>Errors against {'ground truth' if info.get('has_truth') else 'reference sensors'}; statistics skip the
first 0.5 s (convergence). NEES and NIS are run means with their 95% band for a consistent estimator.
{' '.join(extra)}</p>
{rel_html}
{crb_html}
{'<h2>Failures</h2><ul>' + fail_html + '</ul>' if fail_html else ''}
{''.join(f'<h2>{html.escape(f[:-4])}</h2><img src="{f}" alt="{f}">' for f in figures)}
<p><small>Numbers: <a href="summary.json">summary.json</a>.</small></p>
</body></html>
"""
    (out / "index.html").write_text(page)
    return out
