"""Where the model fails: windowed chi-square and whiteness tests of whitened residuals.

Every estimator returns the whitened residual of each factor family per step and axis
(:attr:`Estimate.residuals`; for the EKF, its whitened innovation).  Under the model, a whitened
residual is zero-mean unit-variance noise: over a window of ``n`` steps the sum of squares is
chi-square with ``n`` degrees of freedom, and successive values are uncorrelated.  A window whose
sum of squares exceeds the chi-square bound, or an axis whose autocorrelation is significant, is
where the model disagrees with the measurements.

Smoothed residuals have less than unit variance (the estimate absorbs part of the noise) and are
correlated in time.  The calibrated view (:mod:`flexforce.smoother.leverage`) divides each by the
square root of its own variance (``1 - h``, ``h`` its leverage) and gives the correlation of each
row with the next ``L`` ones; the tests then take the correlation into account (Satterthwaite: a
window's sum of squares of correlated unit-variance Gaussians, of mean ``m`` and variance
``2 sum_kl rho_kl^2``, is referred to ``a chi2(nu)`` with the same two moments), and the whiteness
test is made only where the model expects white residuals (expected lag correlations all below
:data:`WHITE_RHO`).  Without that view (an EKF's innovations: white, unit variance) the tests
are the plain ones.

The level of each test is corrected for the number of windows and axes tested (Bonferroni), so
that a run of the right model raises a flag with probability about ``alpha`` in all.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy import stats


@dataclass
class FlaggedWindow:
    """A span of time where one residual axis is inconsistent with its noise."""

    estimator: str
    family: str
    axis: str
    """Axis label with its unit, e.g. ``F_x [N]``."""
    start_s: float
    end_s: float
    chi2: float
    """Sum of squared whitened residuals over the span."""
    dof: int
    bound: float
    """chi-square bound at the corrected level for ``dof`` degrees of freedom."""
    rms_sigma: float
    """RMS of the whitened residual (1 under the model)."""
    size: float | None
    """RMS of the residual in physical units (None without the family's sigma)."""
    unit: str
    mean: float | None
    """Mean of the residual in physical units: its sign tells the direction of what is missing."""

    def describe(self) -> str:
        size = f"{self.size:.3g} {self.unit}" if self.size is not None else f"{self.rms_sigma:.2f} sigma"
        return (f"{self.family} {self.axis}: {self.start_s:.2f}-{self.end_s:.2f} s, RMS {size} "
                f"({self.rms_sigma:.1f} sigma, chi2 {self.chi2:.0f} > {self.bound:.0f})")

    def to_dict(self) -> dict:
        return asdict(self)


def _unit(label: str) -> str:
    if "[" in label and label.endswith("]"):
        return label[label.rindex("[") + 1:-1]
    return ""


def _sigma(est, family: str, n: int, k: int) -> np.ndarray | None:
    s = est.residual_sigma.get(family)
    if s is None:
        return None
    s = np.asarray(s, dtype=float)
    return np.broadcast_to(s, (n, k)) if s.ndim == 1 else s


WHITE_RHO = 0.1
"""The whiteness (Ljung-Box) test of an axis is made only where the model expects its standardised
residual to be white: every expected lag correlation (mean over the run) below this."""


def _satterthwaite(corr, j: int, s0: int, s1: int, ok: np.ndarray) -> float:
    """Scale ``a = var / (2 m)`` of the sum of squares of the standardised rows ``s0..s1-1`` of
    axis ``j`` (correlations ``corr`` (N, k, L+1)); 1 without correlations."""
    if corr is None:
        return 1.0
    m = int(ok.sum())
    if m == 0:
        return 1.0
    L = corr.shape[2] - 1
    tot = float(m)
    mask = ok.astype(float)
    for h in range(1, min(L, s1 - s0 - 1) + 1):
        rho = corr[s0:s1 - h, j, h]
        both = mask[:len(rho)] * mask[h:h + len(rho)]
        tot += 2.0 * float(np.nansum(rho * rho * both))
    return tot / m


def _window_scales(corr, r: np.ndarray, j: int, bounds: list[tuple[int, int]]) -> np.ndarray:
    """:func:`_satterthwaite` of every window ``(s0, s1)`` of axis ``j`` at once (the residuals
    ``r`` (N, k) say which rows are finite): each lag's masked squared correlations summed by a
    running sum, a window's by two of its entries (the same sums, added in another order)."""
    out = np.ones(len(bounds))
    if corr is None or not bounds:
        return out
    n = r.shape[0]
    L = corr.shape[2] - 1
    ok = np.isfinite(r[:, j]).astype(float)
    rho2 = corr[:, j, 1:] ** 2
    rho2 = np.where(np.isfinite(rho2), rho2, 0.0)
    V = np.zeros((n, max(L, 0)))
    for h in range(1, L + 1):
        V[:n - h, h - 1] = rho2[:n - h, h - 1] * ok[:n - h] * ok[h:]
    P = np.zeros((n + 1, max(L, 0)))
    np.cumsum(V, axis=0, out=P[1:])
    okc = np.concatenate([[0.0], np.cumsum(ok)])
    for i, (s0, s1) in enumerate(bounds):
        m = okc[s1] - okc[s0]
        if m <= 0:
            continue
        hmax = min(L, s1 - s0 - 1)
        tot = m
        if hmax > 0:
            lags = np.arange(hmax)
            tot += 2.0 * float(np.sum(P[s1 - 1 - lags, lags] - P[s0, lags]))
        out[i] = tot / m
    return out


def flag_windows(est, window: float = 0.5, alpha: float = 0.01, families: list[str] | None = None,
                 merge: bool = True, raw: dict | None = None, corr: dict | None = None) -> list[FlaggedWindow]:
    """Windows where a whitened residual axis exceeds its chi-square bound.

    Args:
        window: window length, s (non-overlapping windows).
        alpha: overall false-alarm probability for the whole run (Bonferroni-corrected).
        merge: merge adjacent flagged windows of the same axis into one span.
        raw: family -> the whitened residuals before standardisation (the physical sizes are
            computed from them; default ``est.residuals``): ``est.residuals`` are then the
            standardised ones (:mod:`flexforce.smoother.leverage`).
        corr: family -> (N, k, L+1) lag correlations of the standardised residuals: a window's
            bound is then that of ``a chi2(nu)`` (:func:`_satterthwaite`), ``chi2`` and ``bound``
            are in units of the residual's squares and ``dof`` is ``nu`` rounded.
    """
    t = est.time
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    w = max(2, int(round(window / dt)))
    fams = families or list(est.residuals)
    tests = []
    for fam in fams:
        r = est.residuals[fam]
        n, k = r.shape
        for j in range(k):
            for s0 in range(0, n, w):
                seg = r[s0:s0 + w, j]
                ok = np.isfinite(seg)
                if ok.sum() >= 2:
                    tests.append((fam, j, s0, min(s0 + w, n)))
    if not tests:
        return []
    level = alpha / len(tests)
    # each window's Satterthwaite scale (an axis's windows at once), then every bound at once
    scales = np.empty(len(tests))
    by_axis: dict[tuple[str, int], list[int]] = {}
    for i, (fam, j, _, _) in enumerate(tests):
        by_axis.setdefault((fam, j), []).append(i)
    for (fam, j), idx in by_axis.items():
        scales[idx] = _window_scales((corr or {}).get(fam), est.residuals[fam], j,
                                     [(tests[i][2], tests[i][3]) for i in idx])
    counts = np.array([np.isfinite(est.residuals[fam][s0:s1, j]).sum() for fam, j, s0, s1 in tests], dtype=float)
    bounds = scales * stats.chi2.isf(level, counts / scales)
    flagged: list[FlaggedWindow] = []
    for (fam, j, s0, s1), a, bound, count in zip(tests, scales, bounds, counts):
        r = est.residuals[fam]
        seg = r[s0:s1, j]
        ok = np.isfinite(seg)
        m = int(count)
        chi2 = float(np.sum(seg[ok] ** 2))
        nu = m / a
        dof = max(1, int(round(nu)))
        bound = float(bound)
        if chi2 <= bound:
            continue
        labels = est.residual_labels.get(fam, ())
        label = labels[j] if j < len(labels) else f"axis {j}"
        sig = _sigma(est, fam, r.shape[0], r.shape[1])
        size = mean = None
        if sig is not None:
            base = (raw or {}).get(fam, r)[s0:s1, j]
            phys = base[ok] * sig[s0:s1, j][ok]
            size = float(np.sqrt(np.mean(phys**2)))
            mean = float(np.mean(phys))
        flagged.append(FlaggedWindow(est.estimator, fam, label, float(t[s0]), float(t[s1 - 1]), chi2, dof, bound,
                                     math.sqrt(chi2 / m), size, _unit(label), mean))
    if merge:
        flagged = _merge(flagged, est, level, corr is not None)
    return flagged


def _merge(flags: list[FlaggedWindow], est, level: float, correlated: bool = False) -> list[FlaggedWindow]:
    out: list[FlaggedWindow] = []
    dt = float(np.median(np.diff(est.time))) if est.n > 1 else 1.0
    for f in sorted(flags, key=lambda f: (f.family, f.axis, f.start_s)):
        prev = out[-1] if out else None
        if prev and prev.family == f.family and prev.axis == f.axis and f.start_s - prev.end_s <= 1.5 * dt:
            dof = prev.dof + f.dof
            chi2 = prev.chi2 + f.chi2
            size = mean = None
            if prev.size is not None and f.size is not None:
                size = math.sqrt((prev.size**2 * prev.dof + f.size**2 * f.dof) / dof)
                # a window's mean is set whenever its size is
                mean = (prev.mean * prev.dof + f.mean * f.dof) / dof  # type: ignore[operator]
            # correlated residuals: the spans' bounds add (each is a scaled chi-square's quantile)
            bound = prev.bound + f.bound if correlated else float(stats.chi2.isf(level, dof))
            out[-1] = FlaggedWindow(f.estimator, f.family, f.axis, prev.start_s, f.end_s, chi2, dof,
                                    bound, math.sqrt(chi2 / dof), size, f.unit, mean)
        else:
            out.append(f)
    return sorted(out, key=lambda f: (f.start_s, f.family, f.axis))


@dataclass
class AxisConsistency:
    """Whole-run statistics of one residual axis."""

    family: str
    axis: str
    rms_sigma: float
    """RMS of the whitened residual (1 under the model)."""
    rms: float | None
    """RMS in physical units."""
    unit: str
    chi2_p: float
    """p-value of the whole-run chi-square test (small: inconsistent)."""
    ljung_box_p: float
    """p-value of the Ljung-Box whiteness test over ``lags`` lags (small: correlated); NaN where the
    model itself correlates the residual (calibrated view, expected lag correlation above
    :data:`WHITE_RHO`): not tested."""

    def to_dict(self) -> dict:
        return asdict(self)


def consistency(est, lags: int = 10, raw: dict | None = None, corr: dict | None = None) -> list[AxisConsistency]:
    """Chi-square and whiteness (Ljung-Box) of every residual axis over the whole run.

    ``raw``, ``corr``: as :func:`flag_windows` (standardised residuals in ``est.residuals``, their
    raw values for the physical RMS, their lag correlations for the chi-square's two moments and
    to decide where the whiteness test applies)."""
    out = []
    for fam, r in est.residuals.items():
        n, k = r.shape
        sig = _sigma(est, fam, n, k)
        labels = est.residual_labels.get(fam, ())
        for j in range(k):
            x = r[:, j]
            ok = np.isfinite(x)
            if ok.sum() < lags + 2:
                continue
            xs = x[ok]
            dof = xs.size
            chi2 = float(np.sum(xs**2))
            c = (corr or {}).get(fam)
            a = _satterthwaite(c, j, 0, n, ok)
            nu = dof / a
            chi2_p = float(min(stats.chi2.sf(chi2 / a, nu), stats.chi2.cdf(chi2 / a, nu)) * 2)
            xc = xs - xs.mean()
            denom = float(np.sum(xc * xc)) or 1.0
            acf = np.array([np.sum(xc[h:] * xc[:-h]) / denom for h in range(1, lags + 1)])
            q = dof * (dof + 2) * np.sum(acf**2 / (dof - np.arange(1, lags + 1)))
            lb_p = float(stats.chi2.sf(q, lags))
            if c is not None:
                expected = np.nanmean(c[:, j, 1:lags + 1], axis=0) if c.shape[2] > 1 else np.zeros(1)
                if expected.size < lags or not np.all(np.abs(expected) < WHITE_RHO):
                    lb_p = float("nan")
            label = labels[j] if j < len(labels) else f"axis {j}"
            base = (raw or {}).get(fam, r)[:, j][ok]
            rms = float(np.sqrt(np.mean((base * sig[ok, j]) ** 2))) if sig is not None else None
            out.append(AxisConsistency(fam, label, float(np.sqrt(chi2 / dof)), rms, _unit(label), chi2_p, lb_p))
    return out


def residual_rms(est) -> dict[str, dict[str, float]]:
    """RMS of every whitened residual axis: family -> axis label -> value (1 under the model)."""
    out: dict[str, dict[str, float]] = {}
    for fam, r in est.residuals.items():
        labels = est.residual_labels.get(fam, ())
        out[fam] = {}
        for j in range(r.shape[1]):
            x = r[:, j]
            x = x[np.isfinite(x)]
            label = labels[j] if j < len(labels) else f"axis {j}"
            out[fam][label] = float(np.sqrt(np.mean(x * x))) if x.size else float("nan")
    return out
