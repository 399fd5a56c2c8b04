"""Comparison reports: a folder with index.html, summary.json, timings.json and matplotlib figures.

summary.json holds what the estimates are: two runs on the same input write it byte for byte the
same.  timings.json holds what they cost on this machine (time per step, total time, peak memory),
which varies from run to run; the report's tables show both.

Figures are drawn from result objects (:class:`~flexforce.compare.runner.Comparison`,
:class:`~flexforce.datasets.estimate.Estimate`, the Recording); plot functions draw on a given
``Axes`` and never show anything.
"""

from __future__ import annotations

import functools
import json
import math
import os
import platform
import re
from contextlib import AbstractContextManager
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from flexforce.compare.metrics import (  # noqa: E402
    FRICTION_MU,
    LOWPASS_HZ,
    LOWPASS_ORDER,
    PHASES,
    RMSE_KEYS,
    TRANSITION_S,
    lowpass_key,
)
from flexforce.datasets.safeio import replaceable_by_report, safe_output  # noqa: E402
from flexforce.errors import OutputError  # noqa: E402
from flexforce.factors import so3  # noqa: E402

COLORS = {"ekf": "tab:red", "fixed_lag": "tab:blue", "batch": "tab:green", "leg_odometry": "tab:gray",
          "weight_equal": "tab:brown"}
LABELS = {
    "force_N": "force [N]", "moment_Nm": "moment [N m]", "cop_m": "CoP [m]", "rotation_rad": "rotation [rad]",
    "translation_m": "translation [m]", "hand_m": "hand [m]", "angular_velocity_rad_s": "ang. vel. [rad/s]",
    "linear_velocity_m_s": "lin. vel. [m/s]", "contact_force_N": "contact force [N]",
    "vertical_force_N": "vertical force [N]",
}


LINESTYLES = {"fixed_lag": (0, (5, 2)), "leg_odometry": ":", "weight_equal": "-."}
"""Line style per row: the fixed-lag smoother dashed over the batch one (solid), which it often
follows to within a line width; the baselines dotted and dash-dotted."""
ZORDERS = {"ekf": 2.0, "batch": 2.1, "fixed_lag": 2.2}
"""Drawing order per row: the fixed-lag dashes on top of the batch line."""
UNITS_SENTENCE = ("Units: forces N, moments N m, lengths mm (CoP, translation, hands, sinking), rotations and "
                  "tilt mrad, time s.")
"""Said once in the report: every table and figure uses these units."""


def _color(key: str) -> str:
    return COLORS.get(key, "tab:purple")


def _style(key: str, lw: float = 0.9) -> dict:
    """Matplotlib keyword arguments of a row's line: its colour, style and drawing order."""
    return {"color": _color(key), "ls": LINESTYLES.get(key, "-"), "zorder": ZORDERS.get(key, 1.9), "lw": lw}


def _rows(comp) -> dict:
    """Estimates to draw: the estimators', then the baselines' (leg odometry)."""
    return {**comp.estimates, **getattr(comp, "baseline_estimates", {})}


def _row_label(key: str, comp=None) -> str:
    if comp is not None and key in getattr(comp, "baselines", {}):
        return f"{key} (baseline)"
    return key


def _reference_label(rec) -> str:
    """What the reference curves are: ``truth`` on simulated data, else the sensor's name."""
    return "truth" if rec.truth is not None else "reference: F/T"


ROBUST_PERCENTILES = (0.5, 99.5)
"""Percentiles of the plotted values that set the axis limits: one spike (a sensor glitch, an
estimator's first step) no longer flattens every curve."""
ROBUST_MARGIN = 0.25
"""Margin added on both sides, as a fraction of the percentile range."""
ROBUST_LIMITS_SENTENCE = (f"Axes are cut at robust limits (the {ROBUST_PERCENTILES[0]}–{ROBUST_PERCENTILES[1]} "
                          f"percentiles of the plotted values ± {int(100 * ROBUST_MARGIN)}% of their range); a "
                          "panel with points beyond them says how many in its top left corner.")
"""How the report explains the note :func:`robust_limits` leaves in a panel."""


def robust_limits(ax, values, percentiles=ROBUST_PERCENTILES, margin=ROBUST_MARGIN, log: bool = False) -> int:
    """Set the y limits of ``ax`` from robust percentiles of ``values`` (arrays, NaN ignored).

    Returns the number of points left outside, and says so in the panel's top left corner when there
    are any (the limits themselves: :data:`ROBUST_LIMITS_SENTENCE`, said once in the report).
    """
    v = np.concatenate([np.ravel(np.asarray(x, dtype=float)) for x in values]) if values else np.zeros(0)
    v = v[np.isfinite(v)]
    if log:
        v = np.log10(v[v > 0])
    if v.size == 0:
        return 0
    lo, hi = np.percentile(v, percentiles)
    span = hi - lo
    if span <= 0:
        span = max(abs(hi), 1.0) * 0.1
    lo, hi = lo - margin * span, hi + margin * span
    clipped = int(np.sum((v < lo) | (v > hi)))
    if clipped:
        ax.set_ylim(10**lo, 10**hi) if log else ax.set_ylim(lo, hi)
        ax.text(0.01, 0.97, f"{clipped} point(s) beyond the axis", transform=ax.transAxes, ha="left", va="top",
                fontsize=7, color="0.3", clip_on=True, zorder=5,
                bbox={"facecolor": "white", "alpha": 0.7, "linewidth": 0, "pad": 1})
    return clipped


def intervals(mask: np.ndarray, time: np.ndarray) -> list[tuple[float, float]]:
    """(start, end) seconds of the runs where ``mask`` is true (end: the run's last sample)."""
    m = np.asarray(mask, dtype=bool)
    if m.size == 0:
        return []
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    starts: list[int | np.integer] = [0] if m[0] else []
    ends: list[int | np.integer] = []
    for e in edges:
        if m[e + 1]:
            starts.append(e + 1)
        else:
            ends.append(e)
    if m[-1]:
        ends.append(m.size - 1)
    return [(float(time[a]), float(time[b])) for a, b in zip(starts, ends)]


def _shade_contact(ax, rec, i):
    for a, b in intervals(rec.contact_active[:, i], rec.time):
        ax.axvspan(a, b, color="tab:olive", alpha=0.12, lw=0)


def hidden_spans(rec) -> list[tuple[float, float, str]]:
    """(start, end, label) in the recording's seconds of each time-limited hidden effect of a simulated
    recording (``meta["hidden_effects"]``, the entries with a ``start``, shifted by ``meta["window"]``);
    an effect without a start acts all the time and has no span.  Empty on real logs."""
    effects = (getattr(rec, "meta", None) or {}).get("hidden_effects") or []
    window = rec.meta.get("window") if isinstance(rec.meta.get("window"), dict) else {}
    t0 = float(window.get("start_s", 0.0))
    t_end = float(rec.time[-1]) if rec.n else 0.0
    out = []
    for e in effects:
        if not isinstance(e, dict) or "start" not in e:
            continue
        a = float(e["start"]) - t0
        b = a + float(e.get("duration", math.inf))
        if b < 0.0 or a > t_end:
            continue
        force = e.get("force")
        what = e.get("type", "effect") + (f" {e['link']}" if e.get("link") else "")
        if force is not None:
            what += f" {float(np.linalg.norm(force)):.3g} N"
        out.append((max(a, 0.0), min(b, t_end), what))
    return out


def contact_switches(rec) -> list[float]:
    """Times (s) at which any contact is made or released (``contact_active`` changes)."""
    act = np.asarray(rec.contact_active, dtype=bool)
    if act.shape[0] < 2:
        return []
    changed = np.flatnonzero(np.any(act[1:] != act[:-1], axis=1))
    return [float(rec.time[k + 1]) for k in changed]


def plot_events(ax, rec, legend: bool = False, switches: bool = True) -> None:
    """Mark the events of ``rec`` on a time axis: its hidden effects as shaded spans (orange), its contact
    switches as thin vertical lines (grey; not with ``switches=False``); with ``legend`` the first of
    each kind is labelled."""
    for k, (a, b, _what) in enumerate(hidden_spans(rec)):
        ax.axvspan(a, max(b, a + rec.dt), color="tab:orange", alpha=0.18, lw=0, zorder=0,
                   label="hidden effect" if legend and k == 0 else None)
    for k, t in enumerate(contact_switches(rec) if switches else []):
        ax.axvline(t, color="0.45", lw=0.5, alpha=0.6, zorder=0.5,
                   label="contact switch" if legend and k == 0 else None)


# ----------------------------------------------------------------------------------------------
# Plot functions: each draws on the Axes it is given
# ----------------------------------------------------------------------------------------------


def plot_series(ax, time, estimates: dict, value, std=None, truth=None, label: str = "", scale: float = 1.0,
                truth_label: str = "truth"):
    """One quantity over time on ``ax``: the truth or reference (black) and each estimate (:func:`_style`)
    with a +-2 sigma band; ``value``/``std`` map an estimate to (N,) arrays, multiplied by ``scale``.

    The y limits come from :func:`robust_limits`, so a single spike does not flatten the rest.
    """
    shown = []
    if truth is not None:
        ax.plot(time, truth * scale, color="k", lw=1.2, label=truth_label, zorder=2.5)
        shown.append(truth * scale)
    for key, est in estimates.items():
        y = value(est) * scale
        shown.append(y)
        ax.plot(est.time, y, label=key, **_style(key))
        if std is not None:
            s = std(est)
            if s is not None:
                ax.fill_between(est.time, y - 2 * s * scale, y + 2 * s * scale, color=_color(key), alpha=0.15, lw=0)
    ax.set_ylabel(label)
    ax.grid(alpha=0.3)
    robust_limits(ax, shown)


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


def figure_legend(fig, axes, fontsize: float = 7, ncol: int = 8) -> None:
    """One legend for ``fig`` below its panels, outside every axes: the labelled artists of all
    ``axes`` (a reference drawn on one panel only is listed too), each label once.  ``fig`` needs a
    constrained layout (``layout="constrained"``) to make room for it."""
    handles, labels = [], []
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    if handles:
        fig.legend(handles, labels, loc="outside lower center", fontsize=fontsize, ncol=min(ncol, len(labels)),
                   frameon=False)


def _series_figure(time, estimates: dict, panels: list[tuple], title: str, rec=None):
    """A figure of one :func:`plot_series` panel per row of ``panels``, ``(value, std, truth, label,
    keyword arguments)``, on a shared time axis (s), one legend below the panels
    (:func:`figure_legend`); the events of ``rec`` (:func:`plot_events`) marked on every panel."""
    fig, axes = plt.subplots(len(panels), 1, figsize=(10, 2.4 * len(panels) + 1.0), sharex=True, squeeze=False,
                             layout="constrained")
    axes = axes[:, 0]
    for k, (ax, (value, std, truth, label, options)) in enumerate(zip(axes, panels)):
        if rec is not None:
            plot_events(ax, rec, legend=k == 0)
        plot_series(ax, time, estimates, value, std, truth, label, **options)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(title)
    figure_legend(fig, axes)
    return fig


def figure_forces(comp, rec):
    tr = rec.truth
    ft_sum = None
    if tr is None and rec.ft is not None and np.isfinite(rec.ft[:, :, 2]).any():
        ft_sum = np.nansum(rec.ft[:, :, 2], axis=1)
    panels = [(lambda e: e.total_wrench[:, 2], lambda e: _wrench_std(e, 2),
               tr.total_wrench[:, 2] if tr is not None else ft_sum, "total F_z [N]",
               {"truth_label": "truth" if tr is not None else "reference: F/T (sum)"})]
    panels += [(lambda e, i=i: e.cop[:, i], lambda e, i=i: _cop_std(e, i), None if tr is None else tr.cop[:, i],
                f"CoP {axis} [mm]", {"scale": 1000}) for i, axis in enumerate("xy")]
    return _series_figure(rec.time, _rows(comp), panels, "Contact force and centre of pressure (bands: ±2σ; "
                          "shaded: hidden effects, grey lines: contact switches)", rec)


class _Rigid:
    """An estimate with no flexibility (R = identity): what :func:`base_tilt_error` turns into the
    reference's own tilt of the rigid robot's vertical."""

    def __init__(self, n: int):
        self.R = np.tile(np.eye(3), (n, 1, 1))


def reference_tilt(rec) -> tuple[np.ndarray, str] | None:
    """(N,) tilt (rad) of the flexibility as motion capture sees it, and the system's name; None without.

    The angle between the rigid robot's vertical (leg odometry: ``Recording.base_pose``) and the
    motion-capture one, in the base frame: :func:`flexforce.compare.metrics.base_tilt_error` of an
    identity flexibility, the very quantity the leg-odometry row's tilt error is made of.  An estimate's
    own tilt on the same scale is :func:`flexibility_tilt`.
    """
    from flexforce.compare.metrics import base_tilt_error, mocap_label

    base = rec.meta.get("base_frame")
    if base not in rec.mocap or rec.base_pose is None:
        return None
    tilt = base_tilt_error(_Rigid(rec.n), rec, base)
    return (tilt, mocap_label(rec)) if np.isfinite(tilt).any() else None


def flexibility_tilt(R: np.ndarray) -> np.ndarray:
    """(N,) tilt (rad) of flexibilities ``R`` (N, 3, 3): the angle between ``R^T e_z`` and ``e_z``; the
    angle :func:`reference_tilt` measures, since rotating both verticals by the base pose keeps it."""
    return np.arccos(np.clip(R[:, 2, 2], -1.0, 1.0))


def figure_flexibility(comp, rec):
    tr = rec.truth
    true_rv = None if tr is None else _rotvec(tr.R)
    panels = [(lambda e, i=i: _rotvec(e.R)[:, i], lambda e, i=i: _state_std(e, i),
               None if true_rv is None else true_rv[:, i], f"{name} [mrad]", {"scale": 1000})
              for i, name in enumerate(("roll", "pitch"))]
    ref = reference_tilt(rec)
    if ref is not None:
        panels.append((lambda e: flexibility_tilt(e.R), None, ref[0], "tilt [mrad]",
                       {"scale": 1000, "truth_label": f"reference: {ref[1]}"}))
    panels.append((lambda e: e.t[:, 2], lambda e: _state_std(e, 5), None if tr is None else tr.t[:, 2],
                   "sinking t_z [mm]", {"scale": 1000}))
    title = "Flexibility: rotation vector and vertical translation (bands: ±2σ)"
    if ref is not None:
        title += f"\ntilt: the angle between the rigid robot's vertical and the estimate's, {ref[1]}'s (black)"
    return _series_figure(rec.time, comp.estimates, panels, title, rec)


ERROR_UNITS = {"force_N": ("force [N]", 1.0), "vertical_force_N": ("vertical force [N]", 1.0),
               "cop_m": ("CoP [mm]", 1e3), "rotation_rad": ("rotation [mrad]", 1e3), "hand_m": ("hand [mm]", 1e3)}
"""Label and scale (from SI) of each error series of :func:`figure_errors`, in the report's units."""


def figure_errors(comp, rec):
    rows = {**comp.metrics, **getattr(comp, "baselines", {})}
    keys = [k for k in ("force_N", "vertical_force_N", "cop_m", "rotation_rad", "hand_m")
            if any(np.isfinite(m.errors.get(k, np.array([np.nan]))).any() for m in rows.values())]
    if rec.truth is not None and "force_N" in keys and "vertical_force_N" in keys:
        keys.remove("vertical_force_N")
    if not keys:
        return None
    fig, axes = plt.subplots(len(keys), 1, figsize=(10, 2.2 * len(keys) + 1.2), sharex=True, squeeze=False,
                             layout="constrained")
    for k, (ax, key) in enumerate(zip(axes[:, 0], keys)):
        plot_events(ax, rec, legend=k == 0)
        shown = []
        ref = None
        label, scale = ERROR_UNITS[key]
        for name, m in rows.items():
            e = m.errors.get(key)
            if e is not None:
                ax.semilogy(rec.time, np.maximum(e * scale, 1e-12), label=_row_label(name, comp), **_style(name, 0.8))
                shown.append(e * scale)
                ref = ref or m.references.get(key)
        ax.set_ylabel(label + (f"\n{ref}" if ref and ref != "truth" else ""), fontsize=8)
        ax.grid(alpha=0.3, which="both")
        robust_limits(ax, shown, log=True)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle("Estimation errors against ground truth" if rec.truth is not None else
                 "Estimation errors against reference sensors (references, not ground truth)")
    figure_legend(fig, axes[:, 0])
    return fig


def _reference_contact_wrench(rec):
    """(N, C, 6) reference per-contact wrench in the contact frame: the truth's, else the F/T's."""
    from flexforce.compare.metrics import contact_frame_wrench

    if rec.truth is not None:
        return contact_frame_wrench(rec.truth.R, rec.truth.t, rec.truth.wrench, rec)
    return rec.ft


def plot_contact_force(ax, rec, i: int, axis: int, local: dict, ref=None, comp=None) -> None:
    """Component ``axis`` (0: F_x, 1: F_y, 2: F_z; N, contact frame) of contact ``i`` over time (s) on
    ``ax``: ``ref`` (N, C, 6, the truth's or the F/T's wrenches) in black where finite, each row of
    ``local`` (key -> (N, C, 6) wrenches in the contact frames) in its :func:`_style`; the contact's
    active spans and the hidden effects shaded."""
    _shade_contact(ax, rec, i)
    plot_events(ax, rec, switches=False)
    shown = []
    if ref is not None and np.isfinite(ref[:, i, axis]).any():
        ax.plot(rec.time, ref[:, i, axis], color="k", lw=1.1, label=_reference_label(rec), zorder=2.5)
        shown.append(ref[:, i, axis])
    elif ref is not None or rec.truth is None:
        ax.text(0.01, 0.03, "no reference for this component", transform=ax.transAxes, fontsize=7, color="0.3")
    for key, w in local.items():
        ax.plot(rec.time, w[:, i, axis], label=_row_label(key, comp), **_style(key, 0.8))
        shown.append(w[:, i, axis])
    ax.set_ylabel(f"{rec.contact_names[i]}\nF_{'xyz'[axis]} [N]", fontsize=8)
    ax.grid(alpha=0.3)
    robust_limits(ax, shown)


def figure_foot_forces(comp, rec):
    """One row per contact, its normal (F_z) and horizontal (F_x, F_y) forces in the contact frame,
    each row's against the reference (truth or F/T), contact and hidden effects shaded."""
    from flexforce.compare.metrics import contact_frame_wrench

    ref = _reference_contact_wrench(rec)
    names = rec.contact_names
    if not names:
        return None
    fig, axes = plt.subplots(len(names), 3, figsize=(15, 2.6 * len(names) + 1.2), sharex=True, squeeze=False,
                             layout="constrained")
    rows = _rows(comp)
    local = {key: contact_frame_wrench(e.R, e.t, e.wrench, rec) for key, e in rows.items()}
    for i in range(len(names)):
        for c, axis in enumerate((2, 0, 1)):
            plot_contact_force(axes[i, c], rec, i, axis, local, ref, comp)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle("Per-contact forces in the sole frame: normal F_z, horizontal F_x, F_y "
                 "(green: contact active, orange: hidden effects)")
    figure_legend(fig, axes.ravel())
    return fig


def figure_foot_wrench(comp, rec):
    """Torque and CoP of each contact against a 6-D reference, a 2 x 2 block of panels per contact
    (T_x, T_y above CoP x, CoP y); None when no contact has one."""
    from flexforce.compare.metrics import COP_MIN_LOAD, contact_frame_wrench

    ref = _reference_contact_wrench(rec)
    if ref is None:
        return None
    idx = [i for i in range(len(rec.contact_names)) if np.isfinite(ref[:, i, 3:5]).any()]
    if not idx:
        return None
    rows = _rows(comp)
    local = {key: contact_frame_wrench(e.R, e.t, e.wrench, rec) for key, e in rows.items()}
    min_load = COP_MIN_LOAD * rec.mass * rec.gravity
    fig, axes = plt.subplots(2 * len(idx), 2, figsize=(14, 2.3 * 2 * len(idx) + 1.2), sharex=True, squeeze=False,
                             layout="constrained")

    def cop(w, i):
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.stack([-w[:, i, 4], w[:, i, 3]], axis=1) / w[:, i, 2:3] * 1000
        out[~(w[:, i, 2] > min_load)] = np.nan
        return out

    for r, i in enumerate(idx):
        name = rec.contact_names[i]
        series = [("T_x [N m]", lambda w, i=i: w[:, i, 3]), ("T_y [N m]", lambda w, i=i: w[:, i, 4]),
                  ("CoP x [mm]", lambda w, i=i: cop(w, i)[:, 0]), ("CoP y [mm]", lambda w, i=i: cop(w, i)[:, 1])]
        for c, (label, f) in enumerate(series):
            ax = axes[2 * r + c // 2, c % 2]
            _shade_contact(ax, rec, i)
            plot_events(ax, rec, switches=False)
            y = f(ref)
            ax.plot(rec.time, y, color="k", lw=1.0, label=_reference_label(rec), zorder=2.5)
            shown = [y]
            for key, w in local.items():
                yy = f(w)
                ax.plot(rec.time, yy, label=_row_label(key, comp), **_style(key, 0.7))
                shown.append(yy)
            ax.set_ylabel(f"{name}\n{label}", fontsize=8)
            ax.grid(alpha=0.3)
            robust_limits(ax, shown)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle(f"Sole torque and CoP (sole frame; CoP where the foot carries > {int(COP_MIN_LOAD * 100)}% "
                 f"of the weight)")
    figure_legend(fig, axes.ravel())
    return fig


def figure_contacts(comp, rec):
    """Contact timeline: which contact is active when, and the leg-odometry anchor's switches."""
    names = rec.contact_names
    if not names:
        return None
    anchor = rec.meta.get("anchor") if isinstance(rec.meta.get("anchor"), dict) else {}
    switches = [s for s in anchor.get("switches", []) or [] if isinstance(s, dict) and "t" in s]
    fig, ax = plt.subplots(1, 1, figsize=(10, 0.3 * len(names) + 0.9), layout="constrained")
    for i, _name in enumerate(names):
        spans = [(a, max(b - a, rec.dt)) for a, b in intervals(rec.contact_active[:, i], rec.time)]
        ax.broken_barh(spans, (i - 0.35, 0.7), color="tab:olive", alpha=0.8)
    if anchor.get("first") in names or switches:
        # the anchor (stance foot of the local frame) as a thin dark bar inside its contact's row
        t_end = float(rec.time[-1])
        current = anchor.get("first")
        t_from = 0.0
        for sw in switches + [{"t": t_end, "to": None}]:
            if current in names:
                j = names.index(current)
                ax.broken_barh([(t_from, max(sw["t"] - t_from, rec.dt))], (j - 0.08, 0.16), color="k")
            current, t_from = sw.get("to"), sw["t"]
        for sw in switches:
            ax.axvline(sw["t"], color="tab:red", lw=0.6, alpha=0.6)
    ax.set_yticks(range(len(names)))
    ax.set_yticklabels(names, fontsize=8)
    ax.set_ylim(-0.6, len(names) - 0.4)
    ax.set_xlim(float(rec.time[0]), float(rec.time[-1]))
    ax.set_xlabel("time [s]")
    ax.grid(alpha=0.3, axis="x")
    title = "Contacts in force (bars)"
    if switches or anchor.get("first"):
        title += f"; black: leg-odometry anchor, red lines: its {len(switches)} switch(es)"
    ax.set_title(title, fontsize=9)
    return fig


def plot_family(ax, est, family: str, flags=(), title: str = ""):
    """Whitened residual (σ) of every axis of ``family`` of ``est`` over time (s), the ±3σ lines
    dashed; the spans of ``flags`` (diagnostics' flagged windows) of that family shaded."""
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


def residual_groups(labels, width: int) -> list[tuple[str, list[int]]]:
    """The axes of a factor family grouped by quantity: ``(name, columns)`` in order of first appearance,
    the name the axes' label without its unit (``[...]``) and its ``_x``/``_y``/``_z`` suffix followed by
    the suffixes (``gyro xyz``, ``left_foot F xyz``); an axis without such a label is a group of its own.
    ``width``: the family's number of columns (labels beyond it ignored, missing ones numbered)."""
    groups: dict[str, list[int]] = {}
    suffixes: dict[str, str] = {}
    for j in range(width):
        name = str(labels[j]) if j < len(labels) else str(j)
        name = re.sub(r"\s*\[[^\]]*\]\s*$", "", name)
        m = re.match(r"^(.*)_([xyz])$", name)
        base, axis = (m.group(1), m.group(2)) if m else (name, "")
        groups.setdefault(base, []).append(j)
        suffixes[base] = suffixes.get(base, "") + axis
    return [(f"{base} {suffixes[base]}" if suffixes[base] else base, cols) for base, cols in groups.items()]


RESIDUAL_BINS = 400
"""Points per curve of the residual figure at most: each point the largest |whitened residual| of
its group over a bin of consecutive steps."""


def plot_family_envelope(ax, est, family: str, title: str = "", threshold: float | None = None,
                         bins: int = RESIDUAL_BINS) -> None:
    """The largest |whitened residual| (σ, log axis) of each quantity of ``family`` of ``est``
    (:func:`residual_groups`) over bins of consecutive steps (at most ``bins`` per curve) against
    time (s): a few lines, none hidden, every spike kept; 3σ dashed, ``threshold`` dotted; the legend
    beside the panel, outside it."""
    r = np.abs(np.asarray(est.residuals[family], dtype=float))
    time = np.asarray(est.time, dtype=float)
    step = max(1, -(-r.shape[0] // bins))
    count = -(-r.shape[0] // step)
    for name, cols in residual_groups(est.residual_labels.get(family, ()), r.shape[1]):
        padded = np.full(count * step, np.nan)
        padded[:r.shape[0]] = np.fmax.reduce(r[:, cols], axis=1)  # NaN only where every axis is
        env = np.fmax.reduce(padded.reshape(count, step), axis=1)
        ax.semilogy(time[::step], np.maximum(env, 1e-3), lw=0.8, label=name, drawstyle="steps-post")
    ax.axhline(3, color="k", lw=0.6, ls="--")
    if threshold is not None:
        ax.axhline(threshold, color="k", lw=0.6, ls=":")
    ax.set_ylabel(f"{title}{family}\n|r| [σ]", fontsize=8)
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=6, frameon=False, borderaxespad=0)


def figure_residuals(comp, rec):
    """One panel per (estimator, factor family): :func:`plot_family_envelope`, the events of ``rec``
    marked (:func:`plot_events`)."""
    fams = []
    for key, est in comp.estimates.items():
        for fam in est.residuals:
            if (key, fam) not in fams:
                fams.append((key, fam))
    if not fams:
        return None
    fig, axes = plt.subplots(len(fams), 1, figsize=(11, 1.45 * len(fams) + 1.0), sharex=True, squeeze=False,
                             layout="constrained")
    for k, (ax, (key, fam)) in enumerate(zip(axes[:, 0], fams)):
        plot_events(ax, rec, legend=k == 0)
        plot_family_envelope(ax, comp.estimates[key], fam, title=f"{key}\n", threshold=RESIDUAL_PEAK_SIGMA)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(f"Largest whitened residual per quantity {_bin_seconds(comp)} (log axis; dashed: 3σ, dotted: "
                 f"{RESIDUAL_PEAK_SIGMA:g}σ; orange: hidden effects, grey: contact switches)", fontsize=10)
    return fig


def _bin_seconds(comp, bins: int = RESIDUAL_BINS) -> str:
    """``in bins of 0.025 s`` (the bins of :func:`plot_family_envelope`) or ``per step`` when every
    step is drawn."""
    est = next(iter(comp.estimates.values()))
    n = len(est.time)
    step = max(1, -(-n // bins))
    if step == 1 or n < 2:
        return "per step"
    return f"in bins of {step * float(est.time[1] - est.time[0]):.2g} s"


RESIDUAL_PEAK_SIGMA = 10.0
"""A whitened residual above this (σ) is named in the report beside the residual figure, with the
event it falls in."""


def residual_peaks(comp, rec, threshold: float = RESIDUAL_PEAK_SIGMA) -> list[str]:
    """One sentence per (estimator, factor family) whose largest |whitened residual| exceeds
    ``threshold`` σ: its size, axis, time (s), how many steps exceed ``threshold`` and over which time
    span, and the marked event it falls in or next to (a hidden effect's span, or within two steps of
    a contact switch)."""
    spans = hidden_spans(rec)
    switches = np.asarray(contact_switches(rec))
    out = []
    for key, est in comp.estimates.items():
        for fam, r in est.residuals.items():
            a = np.abs(np.asarray(r, dtype=float))
            if a.size == 0 or not np.isfinite(a).any():
                continue
            k, j = np.unravel_index(int(np.nanargmax(a)), a.shape)
            peak = float(a[k, j])
            if peak <= threshold:
                continue
            t = float(est.time[k])
            labels = est.residual_labels.get(fam, ())
            axis = labels[j] if j < len(labels) else str(j)
            above = np.flatnonzero(np.nanmax(np.where(np.isnan(a), -np.inf, a), axis=1) > threshold)  # NaN: absent
            t_first, t_last = float(est.time[above[0]]), float(est.time[above[-1]])
            count = (f"{above.size} steps above {threshold:g}σ between {t_first:.2f} and {t_last:.2f} s"
                     if above.size > 1 else f"one step above {threshold:g}σ")
            where = [f"inside the hidden effect {what} ({a0:.2f}–{b0:.2f} s): the model lacks it, the data "
                     "carry it" for a0, b0, what in spans if a0 - 2 * rec.dt <= t <= b0 + 2 * rec.dt]
            if not where and switches.size and np.min(np.abs(switches - t)) <= 2 * rec.dt:
                where.append("at a contact switch, where the contact model changes within one step")
            if not where:
                where.append("at none of the marked events")
            out.append(f"{key}: the {fam} residual peaks at {peak:.3g}σ ({axis}) at t = {t:.2f} s, {where[0]}; "
                       f"{count}. This is the {key} {'filter' if key == 'ekf' else 'smoother'}'s misfit to its "
                       f"{fam} factors there (in units of their noise), not a force error: the force errors are in "
                       "the errors figure.")
    return out


def figure_consistency(comp, rec):
    series = [(k, m) for k, m in comp.metrics.items() if m.nees_series is not None or m.nis_series is not None]
    if not series:
        return None
    fig, axes = plt.subplots(2, 1, figsize=(10, 5), sharex=True, layout="constrained")
    for k, ax in enumerate(axes):
        plot_events(ax, rec, legend=k == 0)
    for key, m in series:
        if m.nees_series is not None:
            axes[0].semilogy(rec.time, np.maximum(m.nees_series, 1e-6), label=key, **_style(key, 0.6))
        if m.nis_series is not None:
            axes[1].semilogy(rec.time, np.maximum(m.nis_series, 1e-6), label=key, **_style(key, 0.6))
    axes[0].axhline(18, color="k", ls="--", lw=0.8)
    axes[1].axhline(6, color="k", ls="--", lw=0.8)
    axes[0].set_ylabel("NEES (18-D)")
    axes[1].set_ylabel("NIS (6-D)")
    if not any(m.nees_series is not None for _, m in series):
        axes[0].text(0.5, 0.5, "no ground truth: no NEES", ha="center", va="center", transform=axes[0].transAxes)
    axes[-1].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3, which="both")
    fig.suptitle("Consistency: dashed lines are the expected values")
    figure_legend(fig, axes)
    return fig


FIGURES = {
    "contacts.png": figure_contacts,
    "forces.png": figure_forces,
    "foot_forces.png": figure_foot_forces,
    "foot_wrench.png": figure_foot_wrench,
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


TABLE_COLUMNS = (("force_N", "force RMSE [N]", 1), ("vertical_force_N", "F_z RMSE [N]", 1),
                 ("moment_Nm", "moment RMSE [N m]", 1), ("cop_m", "CoP RMSE [mm]", 1e3),
                 ("rotation_rad", "rotation RMSE [mrad]", 1e3), ("translation_m", "translation RMSE [mm]", 1e3),
                 ("hand_m", "hand RMSE [mm]", 1e3))
PER_CONTACT_COLUMNS = (("vertical_force_N", "F_z RMSE [N]", 1), ("force_N", "3-D force RMSE [N]", 1),
                       ("moment_Nm", "torque RMSE [N m]", 1), ("cop_m", "CoP RMSE [mm]", 1e3))


def _table_rows(summary: dict):
    """(label, row dict, is baseline) for every estimator, then every baseline."""
    for key, m in summary["estimators"].items():
        yield key, m, False
    for key, m in (summary.get("baselines") or {}).items():
        yield key, m, True


def _references(summary: dict) -> dict:
    refs: dict = {}
    for _, m, _ in _table_rows(summary):
        for k, v in (m.get("references") or {}).items():
            refs.setdefault(k, v)
    return refs


@functools.cache
def environment():
    """The jinja2 environment of the report templates (``compare/reports/templates``, shipped with the package).

    Autoescaped HTML; the filter ``fmt`` formats a number like the tables do (:func:`_fmt`).
    """
    import jinja2

    env = jinja2.Environment(loader=jinja2.PackageLoader("flexforce.compare.reports", "templates"), autoescape=True,
                             undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True)
    env.filters["fmt"] = _fmt
    return env


def _summary_columns(summary: dict) -> list:
    return [c for c in TABLE_COLUMNS
            if any(m["rmse"].get(c[0]) is not None for _, m, _ in _table_rows(summary))] or list(TABLE_COLUMNS[:1])


def _contact_groups(summary: dict) -> list:
    """(contact, its columns with a number in some row) for the per-contact table."""
    contacts: list[str] = []
    for _, m, _ in _table_rows(summary):
        for c in (m.get("per_contact") or {}):
            if c not in contacts:
                contacts.append(c)
    groups = []
    for c in contacts:
        keys = [col for col in PER_CONTACT_COLUMNS
                if any((m.get("per_contact") or {}).get(c, {}).get(col[0]) is not None
                       for _, m, _ in _table_rows(summary))]
        if keys:
            groups.append((c, keys))
    return groups


PHASE_LABELS = {"all": "all", "single_support": "single support", "double_support": "double support",
                "transition": "transition"}
PHASE_QUANTITIES = (("foot_vertical_force_N", "per-foot F_z [N]", 1), ("total_vertical_force_N", "total F_z [N]", 1),
                    ("rotation_rad", "rotation [mrad]", 1e3))
"""Columns of each phase in the per-phase table: (key of the phase's ``rmse``, header, scale)."""


def _phases(summary: dict) -> list:
    """(phase, label, samples) of the phases some row has samples in (``all`` first)."""
    out = []
    for ph in ("all", *PHASES):
        n = next(((m.get("per_phase") or {}).get(ph, {}).get("samples") for _, m, _ in _table_rows(summary)
                  if (m.get("per_phase") or {}).get(ph)), None)
        if n:
            out.append((ph, PHASE_LABELS[ph], n))
    return out


def _phase_quantities(summary: dict) -> list:
    """The per-phase columns with a number in some row; the rotation is named tilt on real logs."""
    refs = _references(summary)
    cols = []
    for key, label, scale in PHASE_QUANTITIES:
        if key == "rotation_rad" and refs.get(key, "truth") != "truth":
            label = "tilt [mrad]"
        if any(((m.get("per_phase") or {}).get("all") or {}).get("rmse", {}).get(key) is not None
               for _, m, _ in _table_rows(summary)):
            cols.append((key, label, scale))
    return cols


def _sole_skipped(summary: dict) -> list[str]:
    """The reasons the CoP-in-sole check was skipped (each once)."""
    return list(dict.fromkeys(s for _, m, _ in _table_rows(summary)
                              if (s := ((m.get("violations") or {}).get("cop_outside_sole") or {}).get("skipped"))))


def summary_table_html(summary: dict) -> str:
    """The summary table, from the very numbers of summary.json (estimators, then baselines); its
    timing cells from timings.json when ``summary`` carries them (:func:`with_timings`), else dashes."""
    tables = environment().get_template("_tables.html.j2").module
    return str(tables.summary_table(list(_table_rows(summary)), _summary_columns(summary),
                                    _references(summary)))


def per_contact_table_html(summary: dict) -> str:
    """Per-contact errors (contact frame, like an F/T sensor): one column group per contact."""
    groups = _contact_groups(summary)
    if not groups:
        return ""
    tables = environment().get_template("_tables.html.j2").module
    return str(tables.per_contact_table(list(_table_rows(summary)), groups))


def _peer_rows(summary: dict) -> list[dict]:
    """The peers' rows of the report: tilt RMSE overall, with its constant taken out
    (:func:`flexforce.compare.metrics.aligned_tilt`) and per contact phase (mrad), median step (µs;
    from timings.json: ``summary`` as :func:`with_timings` gives it, else a dash)."""
    def mrad(x):
        return "–" if x is None else f"{1e3 * x:.3g}"

    out = []
    for key, m in (summary.get("peers") or {}).items():
        phases = m.get("per_phase") or {}
        tilt = {ph: (phases.get(ph) or {}).get("rmse", {}).get("rotation_rad") for ph in
                ("single_support", "double_support", "transition")}
        step = (m.get("time_per_step_s") or {}).get("median")
        out.append({"key": key, "tilt": mrad((m.get("rmse") or {}).get("rotation_rad")),
                    "aligned": mrad((m.get("extra") or {}).get("tilt_aligned_rad")),
                    "single": mrad(tilt["single_support"]), "double": mrad(tilt["double_support"]),
                    "transition": mrad(tilt["transition"]), "step": "–" if step is None else f"{1e6 * step:.3g}"})
    return out


OPTION_NOTES: dict[tuple[str, object], str] = {
    ("compiled", False): "its general window path: the same estimates as the compiled update, at a slower step"}
"""What an estimator option given to the comparison means for the row, where it is not obvious."""


def option_sentences(summary: dict) -> list[str]:
    """One sentence per estimator run with options of its own (summary.json ``extra.options``, e.g. the
    demo's fixed-lag smoother on a first run, ``compiled = False``): the row's numbers are those of
    that configuration."""
    out = []
    for key, m in (summary.get("estimators") or {}).items():
        options = (m.get("extra") or {}).get("options") or {}
        if not options:
            continue
        parts = []
        for name, value in options.items():
            note = OPTION_NOTES.get((name, value)) if isinstance(value, bool | int | str) else None
            parts.append(f"{name} = {value}" + (f" ({note})" if note else ""))
        out.append(f"{key} ran with {'; '.join(parts)}.")
    return out


CONSISTENCY_DOF = {"nees": 18, "nis": 6}
"""Dimension of the state error (NEES) and of the EKF's innovation (NIS): a consistent estimator's
run mean equals it."""


def consistency_sentences(summary: dict) -> list[str]:
    """One sentence per statistic (NEES, NIS) and direction whose run mean falls outside its 95% band
    in some estimator's row: what it means, with the factor sqrt(mean / dof) by which the estimator's
    covariance understates (above the band) or overstates (below it) its errors.  Empty when every
    mean is in its band."""
    out = []
    hidden = bool((summary.get("recording") or {}).get("hidden_effects"))
    for stat, dof in CONSISTENCY_DOF.items():
        what = "state error" if stat == "nees" else "innovation"
        for above in (True, False):
            rows = []
            for key, m in (summary.get("estimators") or {}).items():
                value, band = m.get(stat), m.get(f"{stat}_bounds")
                if value is None or not band or not (value > band[1] if above else value < band[0]):
                    continue
                rows.append((key, value, band, math.sqrt(value / dof)))
            if not rows:
                continue
            lo, hi = rows[0][2]
            listed = ", ".join(f"{k} {v:.3g} (×{f:.2g})" for k, v, _, f in rows)
            if above:
                text = (f"{stat.upper()} above its 95% band [{lo:.3g}, {hi:.3g}] for {dof} dimensions: {listed}. "
                        f"The {what} is larger than the covariance says by about √({stat.upper()}/{dof}), the "
                        "factor in brackets: the covariance is too small for the errors (overconfident).")
                if hidden and stat == "nees":
                    text += (" This recording has hidden effects the nominal model lacks (shaded on the figures): "
                             "the errors they cause are outside every estimator's covariance.")
            else:
                text = (f"{stat.upper()} below its 95% band [{lo:.3g}, {hi:.3g}] for {dof} dimensions: {listed}. "
                        f"The {what} is smaller than the covariance says by about √({stat.upper()}/{dof}), the "
                        "factor in brackets: the covariance is too large for the errors (underconfident).")
            out.append(text)
    return out


def _crb_columns(keys) -> list[tuple[str, str, float]]:
    """(key, header in the report's units, scale from SI) of the Cramér–Rao table's columns."""
    heads = {k: (h.replace(" RMSE", ""), sc) for k, h, sc in TABLE_COLUMNS}
    return [(k, *heads.get(k, (k, 1.0))) for k in keys]


FIGURE_HEADINGS = {
    "contacts.png": "Contact timeline",
    "forces.png": "Total vertical force [N] and centre of pressure [mm]",
    "foot_forces.png": "Forces per foot [N], sole frame",
    "foot_wrench.png": "Torque [N m] and centre of pressure [mm] per foot, sole frame",
    "flexibility.png": "Flexibility: roll, pitch, tilt [mrad] and sinking [mm]",
    "errors.png": "Errors over time",
    "residuals.png": "Whitened residuals per factor family [σ]",
    "consistency.png": "Consistency over time: NEES and NIS",
}
"""The report's heading of each figure (:data:`FIGURES`), with its units."""


EFFECT_UNITS = {"force": ("N", 1.0), "torque": ("N m", 1.0), "offset": ("mm", 1e3), "position": ("mm", 1e3),
                "rotation": ("mrad", 1e3), "delay": ("ms", 1e3), "value": ("", 1.0), "scale": ("", 1.0),
                "stiffness": ("", 1.0), "damping": ("", 1.0), "k_fs": ("", 1.0), "k_ts": ("", 1.0),
                "beta_f": ("1/m²", 1.0), "beta_t": ("1/rad²", 1.0), "ramp": ("s", 1.0)}
"""Unit and scale (from the SI of :mod:`flexforce.datasets.sim.effects`) in which a hidden effect's
parameter is listed; ``value`` (a bias) is SI as given."""
BIAS_UNITS = {"gyro-bias": "rad/s", "accel-bias": "m/s²"}
"""Unit of the ``value`` of the bias effects."""
_EFFECT_KEYS = ("type", "link", "contact", "target", "start", "duration", "profile", "kind")


def _effect_value(key: str, value, unit: str, scale: float) -> str:
    """``force 30 N (30, 0, 0)``: a parameter's size (the norm of a vector, with its components)."""
    u = f" {unit}" if unit else ""
    if isinstance(value, (list, tuple)):
        v = np.asarray(value, dtype=float) * scale
        parts = ", ".join(f"{x:.3g}" for x in v)
        return f"{key} {float(np.linalg.norm(v)):.3g}{u} ({parts})"
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return f"{key} {value * scale:.3g}{u}"
    return f"{key} {value}"


def hidden_effect_text(effect: dict, window_start_s: float = 0.0, duration_s: float | None = None) -> str:
    """One hidden effect of a simulated recording (an entry of ``summary["recording"]["hidden_effects"]``)
    in words: its type, where it acts (link, contact), its parameters with units (:data:`EFFECT_UNITS`;
    vectors as norm and components, world or IMU axes as the simulator defines them) and its time span
    in the recording's seconds (``start`` shifted by ``window_start_s``, clipped to ``duration_s``; an
    effect wholly before the start or after the end of the recording says so), or ``throughout``
    without a start."""
    kind = str(effect.get("type", "effect"))
    where = []
    link = effect.get("link")
    if link == "@base":
        where.append("on the base")
    elif isinstance(link, str) and link.startswith("@link:"):
        where.append(f"on tracked link {link[6:]} (a hand)")
    elif link:
        where.append(f"on {link}")
    if effect.get("contact"):
        where.append(f"at {effect['contact']}")
    if effect.get("target"):
        where.append(f"of the {effect['target']}")
    params = []
    for key, value in effect.items():
        if key in _EFFECT_KEYS:
            continue
        unit, scale = EFFECT_UNITS.get(key, ("", 1.0))
        if key == "value":
            unit = BIAS_UNITS.get(kind, "")
        params.append(_effect_value(key, value, unit, scale))
    if "start" in effect:
        a = float(effect["start"]) - window_start_s
        b = a + float(effect.get("duration", math.inf))
        if b <= 0.0:
            span = "before the recording's start (not in the data)"
        elif duration_s is not None and a >= duration_s:
            span = "after the recording's end (not in the data)"
        else:
            a = max(a, 0.0)
            if duration_s is not None:
                b = min(b, duration_s)
            span = f"{a:.2f}–{b:.2f} s" if math.isfinite(b) else f"from {a:.2f} s on"
            if effect.get("profile"):
                span += f", {effect['profile']} profile"
    else:
        span = "throughout"
    text = " ".join([kind.replace("-", " "), *where])
    return text + (": " + ", ".join(params) if params else "") + f"; {span}"


def relative_columns(relative: dict) -> list[tuple[str, str]]:
    """(key, header) of the columns of the "RMSE relative to the EKF" table that have a number in
    some row: the quantity's name of :data:`TABLE_COLUMNS` without its unit (the cells are ratios)."""
    out = []
    for key, head, _scale in TABLE_COLUMNS:
        if any((row or {}).get(key) is not None for row in relative.values()):
            out.append((key, re.sub(r"\s*RMSE\s*\[[^\]]*\]$", "", head)))
    return out


VIOLATION_CHECKS = (("negative_normal", "normal force below 0 N (the ground pulls)"),
                    ("friction_cone", "force outside the friction cone"),
                    ("cop_outside_sole", "centre of pressure outside the sole"))
"""The checks of summary.json's ``violations``, in the words of :func:`violation_sentences`."""


def _checked(check: dict, in_contact) -> int | None:
    """The (step, contact) pairs a violation check judged: ``count / fraction`` (the CoP check judges
    only the pairs with F_z > 0), else the pairs in contact."""
    count, fraction = check.get("count"), check.get("fraction")
    return round(count / fraction) if count and fraction else in_contact


def violation_sentences(summary: dict) -> list[str]:
    """One sentence per physical check (:data:`VIOLATION_CHECKS`) of summary.json's ``violations``:
    the rows that violate it, each with its count, the (step, contact) pairs it judged
    (:func:`_checked`) and the percentage, or that no row does; a check no row made says why.  Empty without
    violations."""
    rows = [(k, m.get("violations"), baseline) for k, m, baseline in _table_rows(summary) if m.get("violations")]
    if not rows:
        return []
    out = []
    for check, words in VIOLATION_CHECKS:
        made = [(k, v[check], _checked(v[check], v.get("samples_in_contact")), b) for k, v, b in rows
                if "count" in (v.get(check) or {})]
        if not made:
            continue
        bad = [f"{k}{' (baseline)' if b else ''} {c['count']} of {n} ({_fmt(c.get('fraction'), 100)} %)"
               for k, c, n, b in made if c["count"]]
        clean = [k for k, c, _, _ in made if not c["count"]]
        if not bad:
            out.append(f"No {words} in any row ({', '.join(clean)}).")
            continue
        text = f"{words[0].upper()}{words[1:]}: {'; '.join(bad)}"
        if clean:
            text += f"; none in {', '.join(clean)}"
        out.append(text + ".")
    law = []
    for k, v, _ in rows:
        asked = [(words.split(" (")[0], (v.get("contact_law") or {}).get(check) or {})
                 for check, words in VIOLATION_CHECKS]
        parts = [f"{c['count']} {w}" for w, c in asked if c.get("count")]
        if parts:
            law.append(f"{k} ({', '.join(parts)})")
    if law:
        out.append("The estimators report each contact's wrench limited to what it can carry; their contact law "
                   f"asked for more in: {'; '.join(law)} (the part removed: Estimate.wrench_excess).")
    return out


def band_sentences(summary: dict) -> list[str]:
    """One sentence on the estimators' normal-force bands (summary.json's ``force_band``,
    :func:`flexforce.compare.metrics.force_band`): which rows cover the reference at about the
    nominal rate, which are overconfident (coverage well below it, with the factor ``z_rms`` by
    which the band understates the errors).  Empty when no row has a band."""
    rows = [(k, m["force_band"]) for k, m in (summary.get("estimators") or {}).items()
            if (m.get("force_band") or {}).get("samples")]
    if not rows:
        return []
    level = rows[0][1]["level"]
    k_sigma = rows[0][1]["k_sigma"]
    ok = [k for k, b in rows if b["coverage"] >= level - BAND_SLACK]
    bad = [f"{k} {100 * b['coverage']:.0f} % (errors ×{b['z_rms']:.2g} the band's σ)" for k, b in rows
           if b["coverage"] < level - BAND_SLACK]
    ref = "truth" if (summary.get("recording") or {}).get("has_truth") else "reference"
    text = (f"The normal-force bands (±{k_sigma:g}σ) should hold the {ref} in {100 * level:.0f} % of the samples "
            "in contact")
    if ok:
        text += f"; they do in {', '.join(ok)}"
    if bad:
        text += f"; they hold it less often in {'; '.join(bad)}: those bands are too narrow for the errors"
    out = [text + "."]
    model = [(k, b["model"]) for k, b in rows if (b.get("model") or {}).get("samples")]
    if model:
        parts = [f"{k} {100 * b['coverage']:.0f} % (median σ {b['median_sigma_N']:.3g} N)" for k, b in model]
        top = max(model[0][1].get("components_N") or {"": 0.0}, key=lambda c: model[0][1]["components_N"][c])
        out.append(f"With the model's own uncertainty (the robot's [model_uncertainty]) the bands hold it in "
                   f"{'; '.join(parts)}" + (f"; the largest part is {top.replace('_', ' ')}" if top else "") + ".")
    return out


def aligned_tilt_sentences(summary: dict) -> list[str]:
    """The tilt against motion capture with each row's constant taken out (summary.json's
    ``extra.tilt_aligned_rad``, :func:`flexforce.compare.metrics.aligned_tilt`): one sentence naming
    every row's figure, lowest first.  Empty when no row has it."""
    rows = []
    for group in ("estimators", "baselines", "peers"):
        for key, m in (summary.get(group) or {}).items():
            extra = m.get("extra") or {}
            if extra.get("tilt_aligned_rad") is not None:
                rows.append((extra["tilt_aligned_rad"], key, extra.get("tilt_offset_rad") or [0.0, 0.0]))
    if not rows:
        return []
    rows.sort()
    parts = [f"{k} {1e3 * a:.1f} mrad (constant {1e3 * o[0]:.1f}, {1e3 * o[1]:.1f})" for a, k, o in rows]
    return ["Each row's tilt error against motion capture holds a constant that is not the estimator's alone "
            "(the markers' frame against the base's, the motion-capture world's vertical against gravity). With "
            "each row's constant taken out (the mean of the estimated minus the motion-capture vertical in the base "
            "frame, x and y, in brackets), the tilt RMSE is: " + "; ".join(parts) + "."]


def reference_sentences(summary: dict) -> list[str]:
    """What the F/T reference's own checks say (summary.json's ``reference_checks``,
    :func:`flexforce.compare.metrics.reference_checks`): the unloaded feet's readings, the F/T sum
    against the weight and the CoM's acceleration.  Empty without them."""
    ref = summary.get("reference_checks") or {}
    out = []
    unloaded = ref.get("unloaded") or {}
    if unloaded:
        parts = [f"{v['mean_N']:.1f} N ({k}, RMS {v['rms_N']:.1f} N)" for k, v in unloaded.items()]
        out.append("Where a foot is not in contact its true contact force is 0; its F/T reads on average "
                   + ", ".join(parts) + ".")
    total = ref.get("total") or {}
    phases = [(p, total[p]) for p in ("double_support", "single_support") if p in total] or \
        [(p, total[p]) for p in ("all",) if p in total]
    if phases:
        parts = [f"{abs(v['mean_N']):.1f} N {'above' if v['mean_N'] >= 0 else 'below'} it in "
                 f"{p.replace('_', ' ')} (RMS {v['rms_N']:.1f} N)" for p, v in phases]
        out.append("The F/T sum against m (g + c̈_z), the weight and the CoM's vertical acceleration from the "
                   "encoders: " + "; ".join(parts) + ".")
    if out:
        out.append("Force errors of these sizes against the F/T are within the reference's own.")
    return out


BAND_SLACK = 0.05
"""How far below the nominal coverage a band may fall and still be called honest (0.05: 90 % for ±2σ)."""


def recording_name(rec, info: dict) -> str:
    """What a report calls a recording: its scenario, else the file or folder it was read from, else
    its robot configuration."""
    source = (getattr(rec, "meta", None) or {}).get("source")
    path = source.get("path") if isinstance(source, dict) else None
    return str(info.get("scenario") or (Path(path).name if path else None) or info.get("robot"))


def write_report(comp, rec, out_dir: str | Path, title: str | None = None) -> Path:
    """Write index.html, summary.json, timings.json (:func:`timings`) and the figures of a
    comparison into ``out_dir``.

    The folder is built aside and swapped in when complete (:func:`report_folder`): an interrupted
    report leaves the previous one whole, never a mixture of old and new files.
    """
    target = Path(out_dir)
    with report_folder(target) as out:
        _write_report(comp, rec, out, title)
    return target


def report_folder(target: Path) -> AbstractContextManager[Path]:
    """Where a report folder is built: a temporary sibling of ``target``, swapped in when complete
    (:func:`flexforce.datasets.safeio.safe_output`); an existing ``target`` is replaced only if it
    holds a flexforce report and nothing else."""
    if target.exists() and not replaceable_by_report(target):
        raise OutputError(f"cannot replace {target}: it is not a flexforce report folder (index.html, .json and "
                          "figures only); expected a new path or an earlier report")
    return safe_output(target, folder=True)


def machine() -> dict:
    """The machine timings are measured on: ``python`` (version), ``processor``, ``cpus`` (the
    machine's, not those free for the run) and ``platform``."""
    return {"python": platform.python_version(), "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(), "platform": platform.platform()}


TIMING_GROUPS = ("estimators", "baselines", "peers")
"""The row groups of summary.json whose rows have their cost in timings.json, under the same keys."""


def timings(comp) -> dict:
    """timings.json of a comparison: ``machine`` (:func:`machine`), and for each row group of its
    summary.json (``estimators``, then ``baselines`` and ``peers`` when it has them) the row key ->
    :meth:`~flexforce.compare.metrics.Metrics.timings_dict` (``time_per_step_s``: ``median``,
    ``p99``, ``amortized``, s; ``total_time_s``, s; ``peak_memory_mb``, MiB; None where not measured)."""
    out: dict = {"machine": machine(), "estimators": {k: m.timings_dict() for k, m in comp.metrics.items()}}
    if comp.baselines:
        out["baselines"] = {k: m.timings_dict() for k, m in comp.baselines.items()}
    if comp.peers:
        out["peers"] = {k: m.timings_dict() for k, m in comp.peers.items()}
    return out


def aggregate_timings(comparisons: list) -> dict:
    """timings.json beside the summary.json of several comparisons
    (:func:`flexforce.compare.runner.aggregate`): ``machine``, and per row group and row key its
    ``time_per_step_s`` over the recordings (s): ``median`` and ``amortized`` the median of the
    recordings', ``p99`` the largest; None where no recording measured it."""
    out: dict = {"machine": machine()}
    for group, rows in (("estimators", lambda c: c.metrics), ("baselines", lambda c: c.baselines),
                        ("peers", lambda c: c.peers)):
        if group != "estimators" and not any(rows(c) for c in comparisons):
            continue
        out[group] = {}
        for key in sorted({k for c in comparisons for k in rows(c)}):
            ms = [rows(c)[key] for c in comparisons if key in rows(c)]
            steps = {}
            for stat, how in (("median", np.median), ("p99", np.max), ("amortized", np.median)):
                times = [t for m in ms if (t := m.time_per_step.get(stat)) is not None]
                steps[stat] = float(how(times)) if times else None
            out[group][key] = {"time_per_step_s": steps}
    return out


def with_timings(summary: dict, times: dict | None) -> dict:
    """A copy of ``summary`` whose rows carry their numbers of ``times`` (:func:`timings`,
    :func:`aggregate_timings`) under the same keys: what the report's tables show.  ``times`` None:
    ``summary`` itself (the timing cells then show a dash)."""
    if not times:
        return summary
    out = dict(summary)
    for group in TIMING_GROUPS:
        if group in summary:
            out[group] = {k: {**m, **((times.get(group) or {}).get(k) or {})} for k, m in summary[group].items()}
    return out


def _write_report(comp, rec, out: Path, title: str | None) -> None:
    out.mkdir(parents=True, exist_ok=True)
    numbers = comp.summary()
    times = timings(comp)
    (out / "summary.json").write_text(json.dumps(numbers, indent=2, allow_nan=False))
    (out / "timings.json").write_text(json.dumps(times, indent=2, allow_nan=False))
    summary = with_timings(numbers, times)  # the tables show both
    figures = []
    for name, make in FIGURES.items():
        fig = make(comp, rec)
        if fig is None:
            continue
        if fig.get_layout_engine() is None:
            fig.tight_layout()
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        figures.append(name)
    info = summary["recording"]
    extra = []
    for _key, m in comp.metrics.items():
        d = m.extra.get("hand_displacement_by_flexibility_max_m")
        if d is not None:
            extra.append(f"Uncompensated, the flexibility moves the hands by up to {d * 1000:.1f} mm.")
            break
    extra += option_sentences(summary)
    win = info.get("window")
    from flexforce.compare.runner import headline

    lp = lowpass_key()
    has_lp = any(lp in ((m.get("per_phase") or {}).get("all") or {}) for _, m, _ in _table_rows(summary))
    page = environment().get_template("comparison.html.j2").render(
        title=title or f"flexforce comparison — {recording_name(rec, info)}",
        info=info,
        window_text=(f", the window {win['start_s']:.3f}–{win['end_s']:.3f} s of a {win['of_duration_s']:.3f} s "
                     "recording" if win else ""),
        effects=[hidden_effect_text(e, float((win or {}).get("start_s", 0.0)), info.get("duration_s"))
                 for e in info.get("hidden_effects") or [] if isinstance(e, dict)],
        rows=list(_table_rows(summary)), columns=_summary_columns(summary), refs=_references(summary),
        references=sorted({v for v in _references(summary).values() if v != "truth"}),
        has_baselines=bool(summary.get("baselines")), extra=extra, peers=_peer_rows(summary),
        contact_groups=_contact_groups(summary), relative=summary.get("rmse_relative_to_ekf") or {},
        relative_columns=relative_columns(summary.get("rmse_relative_to_ekf") or {}),
        crb=summary.get("cramer_rao"), failures=comp.failures, figures=figures,
        headline=headline(summary), phases=_phases(summary), phase_quantities=_phase_quantities(summary),
        lowpass_block=lp if has_lp else None,
        lowpass_quantities=[q for q in _phase_quantities(summary) if q[0] != "rotation_rad"],
        lowpass_hz=LOWPASS_HZ, lowpass_order=LOWPASS_ORDER, transition_ms=TRANSITION_S * 1000,
        has_violations=any(m.get("violations") for _, m, _ in _table_rows(summary)),
        mu=next((v["friction_mu"] for _, m, _ in _table_rows(summary) if (v := m.get("violations"))), FRICTION_MU),
        sole_skipped=_sole_skipped(summary), consistency=consistency_sentences(summary),
        violations=violation_sentences(summary), bands=band_sentences(summary),
        reference_checks=reference_sentences(summary), aligned_tilt=aligned_tilt_sentences(summary),
        has_bands=any((m.get("force_band") or {}).get("samples") for _, m, _ in _table_rows(summary)),
        headings=FIGURE_HEADINGS, robust_limits=ROBUST_LIMITS_SENTENCE,
        units=UNITS_SENTENCE, crb_columns=_crb_columns(RMSE_KEYS), residual_peaks=residual_peaks(comp, rec),
        residual_peak_sigma=RESIDUAL_PEAK_SIGMA)
    (out / "index.html").write_text(page)


INDEX_COLUMNS = (("force_N", "force RMSE [N]", 1), ("vertical_force_N", "F_z RMSE [N]", 1),
                 ("cop_m", "CoP RMSE [mm]", 1e3), ("rotation_rad", "rotation RMSE [mrad]", 1e3))
"""Columns of the recordings table of the index (per estimator)."""


def write_index(out: str | Path, entries: list[tuple[str, dict]], aggregate: dict,
                title: str = "flexforce comparison", times: dict | None = None) -> Path:
    """Write ``out``/index.html for several recordings, each compared in ``out``/<label>/.

    Args:
        entries: (label, summary of its comparison: :meth:`Comparison.summary`) per recording, in order.
        aggregate: :func:`flexforce.compare.runner.aggregate` of the comparisons (the mean and spread
            of every number, written as summary.json beside the index).
        times: :func:`aggregate_timings` of the comparisons (written as timings.json beside the
            index), for the table's time per step; None: the table shows a dash there.
    """
    out = Path(out)
    rows = list(_table_rows(with_timings(aggregate, times)))
    columns = [c for c in TABLE_COLUMNS if any(m["rmse"].get(c[0]) is not None for _, m, _ in rows)]
    keys = [(k, c) for k, _, _ in rows for c in INDEX_COLUMNS
            if any(((s.get("estimators") or {}).get(k) or (s.get("baselines") or {}).get(k) or {})
                   .get("rmse", {}).get(c[0]) is not None for _, s in entries)]
    view = []
    for label, summary in entries:
        both = {**(summary.get("estimators") or {}), **(summary.get("baselines") or {})}
        view.append({"label": label, "link": f"{label}/index.html", "info": summary.get("recording") or {},
                     "failures": summary.get("failures") or {},
                     "cells": [_fmt((both.get(k) or {}).get("rmse", {}).get(c[0]), c[2]) for k, c in keys]})
    page = environment().get_template("index.html.j2").render(
        title=f"{title} — {len(entries)} recordings",
        what="estimators " + ", ".join(k for k, _, baseline in rows if not baseline), entries=view,
        numbers="summary.json", aggregate_rows=rows, columns=columns,
        entry_columns=[f"{k}: {c[1]}" for k, c in keys])
    (out / "index.html").write_text(page)
    return out
