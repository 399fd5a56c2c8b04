"""Fitting a model for the diagnosis: :class:`Fit` (a fitted model and the numbers the criterion
needs), :func:`fit_model`, the refit's watch :class:`LeavingPlausible`, the BIC :func:`score` of a
candidate and the views of a fit's residuals (:func:`snapshot`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import stats

from flexforce.compare.diagnostics.candidates import _constant, _plausibility
from flexforce.compare.diagnostics.config import DEFAULT
from flexforce.compare.diagnostics.residuals import consistency, flag_windows, residual_rms
from flexforce.compare.diagnostics.results import Snapshot
from flexforce.compare.metrics import evaluate

if TYPE_CHECKING:
    from flexforce.datasets.estimate import Estimate


@dataclass
class Fit:
    """One fitted model: its estimate and the numbers the information criterion needs."""

    effects: tuple[str, ...]
    estimate: Estimate
    cost_data: float
    """Half the sum of squared whitened data residuals (negative log-likelihood + const)."""
    n_residuals: int
    effective_dof: dict[str, float]
    """Effect name -> effective degrees of freedom it adds."""
    cost_evidence: float | None = None
    """Negative log marginal likelihood of the data given the constant parameters, the states
    integrated out (Laplace; :mod:`flexforce.smoother.evidence`), up to a constant."""
    global_effects: tuple[str, ...] = ()
    """Effects whose unknowns are constants (one global block): the evidence is conditioned on them."""
    trajectory: object = None
    """The fitted trajectory (:attr:`flexforce.smoother.FitStatistics.trajectory`): where the
    candidates are screened and the residuals' own variances are computed."""
    model: object = None
    """The fitted ModelConfig."""
    stopped: str | None = None
    """Why the fit stopped before the evidence's optimum (:class:`LeavingPlausible`), or None."""


def fit_model(rec, model, progress: Callable[[float], None] | None = None, start: Fit | None = None,
              evidence_tol: float = DEFAULT.evidence_tol, watch: Callable | None = None) -> Fit:
    """Fit ``model`` (with its effects) to ``rec`` with :func:`flexforce.smoother.fit`; ``start``: a
    fit of the same recording with some of these effects, to start from (the smoother's
    ``start``); ``evidence_tol`` and ``watch``: the smoother's (:attr:`DiagnoseConfig.evidence_tol`,
    :class:`LeavingPlausible`)."""
    from flexforce.smoother import fit

    begin = None
    if start is not None and start.trajectory is not None and start.model is not None:
        begin = (tuple(getattr(start.model, "effects", ())), start.trajectory)
    est, stats = fit(rec, model, progress=progress, start=begin, evidence_tol=evidence_tol, watch=watch)
    ev = stats.cost_evidence
    return Fit(tuple(e.name for e in model.effects), est, float(stats.cost_data), int(stats.n_residuals),
               {k: float(v) for k, v in stats.effective_dof.items()},
               None if not math.isfinite(ev) else float(ev), tuple(stats.global_effects),
               getattr(stats, "trajectory", None), model, getattr(stats, "stopped", None))


class LeavingPlausible:
    """A refit's watch (:func:`flexforce.smoother.fit`'s ``watch``): it ends the refit once an
    added constant effect's estimate (``names``) has been implausible (its ``plausible`` verdict)
    after ``patience`` (:attr:`DiagnoseConfig.watch_patience`) consecutive outer steps of the
    marginal likelihood, each farther from its prior mean than the one before, or after one more
    such step in any direction (an implausible optimum the steps circle).

    An implausible estimate is no finding whatever its evidence (:func:`diagnose`), so the rest of
    such a refit decides nothing (docs/diagnostics.md, "Tuning").  The evidence of a
    stopped refit is where it stopped (a lower bound of its score), and its row says so.

    Returns (when called with ``(prob, traj)``): why the refit stops, or None to go on."""

    def __init__(self, names: Iterable[str], patience: int | None = None):
        self.names = set(names)
        self.patience = DEFAULT.watch_patience if patience is None else int(patience)
        self.count = 0  # consecutive implausible steps, each farther from the prior mean
        self.implausible = 0  # consecutive implausible steps
        self.last = -math.inf

    def __call__(self, prob, traj) -> str | None:
        from flexforce.smoother.result import call_report

        t = (prob.rec.t_ns - prob.rec.t_ns[0]) * 1e-9
        reasons: list[str] = []
        dist = 0.0
        off = 0
        for eff in prob.effects:
            dim = int(eff.dim)
            if eff.name in self.names and _constant(eff, prob):
                vals = traj.e[:, off:off + dim]
                try:
                    why = _plausibility(eff, call_report(eff, vals, None, t), prob)
                    mean = np.asarray(eff.prior(prob)[0], dtype=float)
                except Exception:  # a user's effect that cannot say: never stopped for it
                    why, mean = None, vals[-1]
                if why and not why.startswith("its plausibility check raised"):
                    reasons.append(why)
                    dist += float(np.sum((vals[-1] - mean) ** 2))
            off += dim
        if not reasons:
            self.count, self.implausible, self.last = 0, 0, -math.inf
            return None
        self.implausible += 1
        self.count = self.count + 1 if math.sqrt(dist) > self.last else 0
        self.last = math.sqrt(dist)
        if self.count >= self.patience:
            return (f"the refit stopped after {self.count} steps of the marginal likelihood with the estimate "
                    "implausible and moving away from its prior mean: its evidence is where it stopped")
        if self.implausible > self.patience:
            return (f"the refit stopped after {self.implausible} steps of the marginal likelihood with the estimate "
                    "implausible: its evidence is where it stopped")
        return None


def score(base: Fit, fit: Fit, effect: str, alpha: float = DEFAULT.alpha,
          tests: int = 1) -> tuple[float, float, float, float, bool]:
    """``(score, lr, nu, p, significant)`` of ``fit`` (base + ``effect``) against ``base``.

    With the evidence of both fits (:attr:`Fit.cost_evidence`), ``lr`` is twice the gain in log
    marginal likelihood; the BIC penalty ``nu ln n`` applies to the effect's constant unknowns
    (its states, e.g. a random-walk wrench, are integrated out: their Occam factor is already in
    the evidence).  Without it, the data cost's likelihood ratio with every effective dof
    penalised.  ``p``: ``lr`` against chi-square(``nu``), ``nu`` the effective dof.

    Significant: ``score > 0`` and ``p < alpha / tests``.  ``tests``: the candidates tested in the
    same selection round.  Testing the best of ``m`` candidates at ``alpha`` each would select a
    false effect with probability up to ``m alpha``; at ``alpha / m`` in every round (Holm's
    step-down procedure: the ``m`` of a later round is smaller by the effects already selected), a
    recording without a hidden effect selects one with probability at most ``alpha``.
    """
    use_evidence = base.cost_evidence is not None and fit.cost_evidence is not None
    if use_evidence:  # both evidences checked not None just above
        lr = 2.0 * (base.cost_evidence - fit.cost_evidence)  # type: ignore[operator]
    else:
        lr = 2.0 * (base.cost_data - fit.cost_data)
    nu = float(fit.effective_dof.get(effect, 0.0))
    integrated = use_evidence and effect not in fit.global_effects
    penalised = 0.0 if integrated else nu
    n = max(fit.n_residuals, 2)
    bic = lr - penalised * math.log(n)
    if integrated:
        # per-step unknowns integrated out: 2 dE is twice the log Bayes factor, whose expectation
        # under the base model is 1, so P(BF >= 1/p) <= p (Markov): p = 1/BF is a valid p-value
        p = float(math.exp(-0.5 * lr)) if lr > 0 else 1.0
    else:
        p = float(stats.chi2.sf(lr, nu)) if nu > 0 else (0.0 if lr > 0 else 1.0)
    return bic, lr, nu, p, bool(bic > 0 and p < alpha / max(tests, 1))


def calibrated_view(rec, fit: Fit, window: float) -> tuple[dict, dict, dict] | None:
    """``(standardised, variances, correlations)`` of a fit's residuals
    (:mod:`flexforce.smoother.leverage`): each whitened residual divided by the square root of its
    own variance ``1 - h``, and the lag correlations (up to a window) the tests account for;
    None without the fitted trajectory."""
    if fit.trajectory is None or fit.model is None:
        return None
    from flexforce.smoother import NoiseRule, Problem
    from flexforce.smoother.leverage import residual_lag_correlations, residual_variances, standardized_residuals

    prob = Problem.build(rec, fit.model, NoiseRule())
    var = residual_variances(prob, fit.trajectory)  # type: ignore[arg-type]
    lags = max(1, int(round(window / rec.dt)))
    corr = residual_lag_correlations(prob, fit.trajectory, var, lags, fit.estimate.residuals)  # type: ignore[arg-type]
    return standardized_residuals(fit.estimate.residuals, var), var, corr


def snapshot(rec, fit: Fit, window: float, alpha: float, skip: float, calibrated: bool = True) -> Snapshot:
    """``fit`` seen through the diagnostics: its residuals (standardised by their own variance when
    ``calibrated``: :func:`calibrated_view`), the windows of ``window`` s flagged at ``alpha``, the
    consistency tests and the errors (``skip`` s left out at the start)."""
    est = fit.estimate
    view = calibrated_view(rec, fit, window) if calibrated else None
    if view is None:
        return Snapshot(fit.effects, est, evaluate(est, rec, skip=skip), flag_windows(est, window=window, alpha=alpha),
                        consistency(est), residual_rms(est), fit.cost_data, fit.n_residuals)
    z, var, corr = view
    raw = est.residuals
    shown = dataclasses.replace(est, residuals=z, meta={**est.meta, "residuals": "standardised by their own variance"})
    return Snapshot(fit.effects, shown, evaluate(est, rec, skip=skip),
                    flag_windows(shown, window=window, alpha=alpha, raw=raw, corr=corr),
                    consistency(shown, raw=raw, corr=corr), residual_rms(shown), fit.cost_data, fit.n_residuals,
                    residual_rms_smoothed=residual_rms(est), raw_residuals=raw)


def _criterion(f: Fit) -> float | None:
    """The selection's criterion of a fitted model, half its BIC: the negative log evidence plus
    ``ln n / 2`` per effective dof of its constant unknowns (score differences are twice its
    differences); None without the evidence."""
    if f.cost_evidence is None:
        return None
    charge = sum(f.effective_dof.get(e, 0.0) for e in f.global_effects)
    return float(f.cost_evidence) + 0.5 * math.log(max(f.n_residuals, 2)) * charge
