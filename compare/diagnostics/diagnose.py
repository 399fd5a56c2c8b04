r"""Model diagnostics: where the model fails, which effect is missing, and the error once it is added.

Three steps (DESIGN.md, "Diagnostics"; docs/diagnostics.md explains how to read the result):

1. **Where it fails.**  Fit the nominal model; the whitened residual of every factor family and
   axis over time, the windows where it is inconsistent with its noise
   (:func:`flexforce.compare.diagnostics.residuals.flag_windows`: chi-square per window against its
   Bonferroni bound; :func:`~flexforce.compare.diagnostics.residuals.consistency`: whole-run chi-square and
   Ljung-Box whiteness), and the EKF's innovations (NIS, flagged windows) alongside.
2. **Which effect is missing.**  Refit with each candidate effect and score the gain in
   likelihood against the unknowns it adds, with the Bayesian information criterion

   .. math::  \mathrm{score} = 2\,(E_0 - E_1) - \nu_c \ln n

   where ``E`` is the negative log *marginal* likelihood of the data given the effect's constant
   parameters, the states (and any per-step effect values, e.g. a random-walk wrench)
   integrated out by the Laplace approximation (:mod:`flexforce.smoother.evidence`: the data cost
   ``1/2 sum r^2`` plus half the log-determinant ratio of the states' posterior and prior
   information), ``nu_c`` the effective dof of the effect's constant unknowns (``p`` for a
   constant ``p``-vector the data determine, less when its prior does; 0 for per-step unknowns,
   whose Occam factor is already in ``E``) and ``n`` the number of scalar residuals.  An effect is
   *significant* when its score is positive and its p-value is below ``alpha / m`` (``alpha``
   0.01), ``m`` the candidates in the round: for constant unknowns the likelihood-ratio p-value
   of ``2 (E_0 - E_1)`` against chi-square with the effect's effective dof, for per-step ones
   (integrated out: ``2 (E_0 - E_1)`` is twice a log Bayes factor) ``1 / BF``.  Several effects:
   greedy forward selection -- add the best significant one, rescore the rest on top of it, stop
   when none is significant.  Each round
   tests its ``m`` candidates (every one not selected yet) at ``alpha / m``: Holm's step-down
   procedure: a recording without a hidden effect selects one with probability at most ``alpha``
   (at ``alpha`` per candidate, 11 candidates would give up to 10 %).

   Why the marginal and not the joint likelihood: the joint optimum over states and parameters
   is biased for every parameter that enters the dynamics (the trajectory prior's normaliser
   depends on it); measured on a 3 s sway with no hidden effect, the joint optimum drives the
   contact damping scale to 0.07 (truth 1) and the vertical CoM offset to -0.17 m, both
   "significant" (likelihood-ratio gains of 60 and 200); with the marginal, 0.82 +- 0.12 and
   -0.008 +- 0.009 m, neither significant.
3. **Add it.**  Refit with the chosen effects; residuals (and, with ground truth, estimation errors)
   before and after.

Why BIC and not AIC: AIC's penalty (2 per dof) is not consistent -- with the thousands of scalar
residuals of a few seconds of data, the smoothed residuals' small departures from the model
(discretisation, the Huber loss, correlated smoothing errors) make AIC select spurious effects,
and its penalty is negligible against a random-walk effect that can absorb anything.  BIC's
``ln n`` per dof (about 10 for 3 s at 200 Hz) only lets an effect in when the data demand it,
and it is consistent: with more data it picks the true model with probability one.  The
likelihood-ratio p-value is the second guard: it bounds the false-alarm rate of each round at
``alpha`` whatever ``n``.

Fitting goes through :func:`flexforce.smoother.fit`: its :class:`~flexforce.smoother.FitStatistics`
give the data cost, the evidence, the number of residuals and each effect's effective dof (``p``
for a constant, the trace of the effect's share of the hat matrix for a random walk).  The
diagnosis never changes an Estimate it is given: what it adds (the residuals' sigmas) goes into
a copy held by its own :class:`Snapshot`.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import stats

from flexforce.compare.diagnostics.residuals import FlaggedWindow, consistency, flag_windows, residual_rms
from flexforce.compare.metrics import RMSE_KEYS, Metrics, evaluate
from flexforce.errors import ConfigError, FlexforceError

if TYPE_CHECKING:
    from flexforce.datasets.estimate import Estimate
    from flexforce.smoother.screening import Identifiability, ScoreTest

ALPHA = 0.01
"""Family-wise level of each selection round's likelihood-ratio tests (each candidate at ``ALPHA / m``,
``m`` the round's candidates: :func:`score`), and the level of the windowed residual tests."""

SCREEN_LEVEL = 0.01
"""Level of the score test that decides which candidates are refitted (:func:`screen`)."""

SCREEN_WINDOW = 0.25
"""Window of the score test of a per-step effect (the external wrench taken constant within it), s."""

REFIT_BEST = 3
"""Candidates refitted per selection round at most, besides those inseparable from them
(:func:`diagnose`'s ``refit_best``)."""

SWAP_ALTERNATIVES = 2
"""Per-step effects the greedy selection took before its last round are tried again against this
many constant candidates, those whose score tests are strongest without them (:func:`diagnose`)."""

EVIDENCE_TOL = 0.05
"""The diagnosis's fits end their outer steps of the marginal likelihood once a full step gains less
than this, or the step's models promise less, in nats (:func:`flexforce.smoother.batch.optimize`'s
``evidence_tol``); the smoother's own tolerance, ``rel_tol`` of the cost, asks 0.003 nats on the
20 s iCub sway.  The evidence reported is not quite the objective (plain, not robust, Newton-Euler
residuals; no prior on the constants): along a flat direction it stays up to a few tenths of a nat
above its optimum (measured: 0.12 on a 2.5 s stand's contact damping, 0.25 on the iCub sway's CoM
offset y beside the accelerometer bias), under one in a score where a tie is :data:`TIE`."""

WATCH_PATIENCE = 2
"""Outer steps of an implausible estimate moving away that end a refit, one more in any direction
(:class:`LeavingPlausible`)."""

CHECK_WORSE = 0.05
"""An error against the truth or the reference sensors that rises by more than this fraction
when an effect joins the selection makes the check say they disagree with it
(:attr:`Candidate.check`)."""

CHECK_LABELS = {"force_N": ("force", 1.0, " N"), "moment_Nm": ("moment", 1.0, " N m"), "cop_m": ("CoP", 1e3, " mm"),
                "rotation_rad": ("tilt", 180.0 / math.pi, " deg"), "translation_m": ("position", 1e3, " mm"),
                "hand_m": ("hand", 1e3, " mm"), "vertical_force_N": ("vertical force", 1.0, " N"),
                "contact_force_N": ("contact force", 1.0, " N"), "contact_moment_Nm": ("contact moment", 1.0, " N m"),
                "contact_cop_m": ("sole CoP", 1e3, " mm")}
"""How :meth:`Candidate.check_text` names and scales each error."""

AUTO = "auto"
"""``add=["auto"]``: add the effects the greedy selection found significant."""

CONSTANCY_Z = 5.0
"""A constant effect the selection would take is fitted again on each half of the recording (with
the round's base, :func:`constancy`).  It is not constant when, on one of its components, the
halves differ both by more than this many standard deviations (of the difference, from the halves'
Laplace sigmas) and by more than :data:`CONSTANCY_REL` of its size: the estimate then stands for
something the model misses that changes over the recording.  The sigmas alone do not decide: they
are optimistic under a model error, and the more so the longer the recording (a model error
biases each half its own way, and the sigmas shrink with the samples while the biases do not).
Measured on the wide benchmark's recordings (3 s, 1.5 s halves, 49 checks, the simulated world not
the model's): the halves of a hidden constant effect differed by at most 2.9 sigma alone, 5.7 beside
a second hidden effect not yet in the model (Romeo's sway, an IMU mounting beside cubic
stiffening); on the real iCub walk the five constants of round 3 by 13 to 70 sigma."""

CONSTANCY_REL = 0.5
"""The size part of the constancy check (:data:`CONSTANCY_Z`): the halves differ by more than this
fraction of the larger of their two estimates (its departure from the effect's ``null``, 0 or the
nominal 1 of a scale): a constant measured twice is the same within a half of itself.  Measured:
where a hidden effect's halves differed beyond 5 sigma (Romeo's sway above), by 0.18 of it; beyond
3 sigma, by at most 0.43 (TALOS's weight shift, a stiffness scale beside a CoM offset, 3.9 sigma).
On the iCub walk the IMU mounting's halves differ by 1.41 of it (opposite signs), the time
offset's by 0.71 (9.8 and 2.8 ms), the cubic stiffening's by 0.76."""

CONSTANCY_MIN_S = 1.0
"""Each half must be at least this long (s) for the constancy check; a shorter recording is not
checked (the row says so)."""

TIE = 6.0
"""Two significant candidates of one round whose scores differ by less than this (twice the log
of a Bayes factor of 20, "strong evidence" on Kass and Raftery's scale) explain the data about
equally well: the data do not tell them apart, and the diagnosis says so (:attr:`Candidate.rivals`)."""


# ----------------------------------------------------------------------------------------------
# Candidates and fitting
# ----------------------------------------------------------------------------------------------


def registered_effects() -> dict:
    """The built-in effect catalogue (``flexforce.factors.effects.EFFECTS``), empty until it exists."""
    try:
        from flexforce.factors.effects import EFFECTS
    except ImportError:
        return {}
    return dict(EFFECTS)


def _is_effect(obj) -> bool:
    from flexforce.factors.effects import Effect

    return isinstance(obj, Effect)


def effect_factory(spec) -> tuple[str, Callable[[], object]]:
    """``(name, make)`` for a candidate: a registered name, an Effect instance or an Effect class.

    A fresh instance is made for every fit when the candidate is a class or a name; an instance
    is shared (effects are descriptions, their values live in the smoother's state).
    """
    if isinstance(spec, str):
        reg = registered_effects()
        if spec not in reg:
            known = ", ".join(sorted(reg)) or "none registered (flexforce.factors.effects is not available)"
            raise ConfigError(f"unknown effect '{spec}'; known: {known}")
        try:
            from flexforce.factors.effects import make_effect
        except ImportError:  # a registry without the factory
            make_effect = None  # type: ignore[assignment]
        make = (lambda: make_effect(spec)) if make_effect else reg[spec]  # type: ignore[truthy-function]
        eff = make()
        return eff.name, make
    if isinstance(spec, type):
        eff = spec()
        if not _is_effect(eff):
            raise ConfigError(f"{spec.__name__} does not implement the Effect protocol (name, dim, labels, prior, "
                              "random_walk_sigma, residual_terms, report)")
        return eff.name, spec
    if _is_effect(spec):
        return spec.name, lambda: spec
    raise ConfigError(f"candidate {spec!r} is neither an effect name, an Effect class nor an Effect instance")


def bound(make: Callable[[], object], rec, model) -> Callable[[], object]:
    """``make`` whose effects are fitted to ``rec``: an effect with a ``bind(rec, model)`` method
    (one unknown block per contact of the recording, e.g. the footholds) is made through it."""
    def made():
        eff = make()
        bind = getattr(eff, "bind", None)
        return bind(rec, model) if callable(bind) else eff

    return made


def resolve_candidates(candidates: Iterable | None) -> dict[str, Callable[[], object]]:
    """Name -> factory of every candidate (default: every registered effect)."""
    if candidates is None:
        candidates = list(registered_effects())
        if not candidates:
            raise ConfigError("no candidate effects: flexforce.factors.effects is not available; pass candidates")
    out: dict[str, Callable[[], object]] = {}
    for spec in candidates:
        name, make = effect_factory(spec)
        if name in out:
            raise ConfigError(f"two candidate effects are named '{name}'; effect names must be unique")
        out[name] = make
    return out


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
              evidence_tol: float = EVIDENCE_TOL, watch: Callable | None = None) -> Fit:
    """Fit ``model`` (with its effects) to ``rec`` with :func:`flexforce.smoother.fit`; ``start``: a
    fit of the same recording with some of these effects, to start from (the smoother's
    ``start``); ``evidence_tol`` and ``watch``: the smoother's (:data:`EVIDENCE_TOL`,
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


def _scored(c: Candidate) -> str:
    """``name (score S)``, with ``, implausible`` when its estimate is."""
    return f"{c.effect} (score {c.score:.1f}{', implausible' if c.implausible else ''})"


class LeavingPlausible:
    """A refit's watch (:func:`flexforce.smoother.fit`'s ``watch``): it ends the refit once an
    added constant effect's estimate (``names``) has been implausible (its ``plausible`` verdict)
    after :data:`WATCH_PATIENCE` consecutive outer steps of the marginal likelihood, each farther
    from its prior mean than the one before, or after one more such step in any direction (an
    implausible optimum the steps circle: on the iCub sway the contact damping at 7.3 times the
    identified one, implausible from the second step).

    An implausible estimate is no finding whatever its evidence (:func:`diagnose`), so the rest of
    such a refit decides nothing: on the 20 s iCub sway the anisotropic stiffness, added to the
    accelerometer bias, took 18 outer steps (83 s) to reach a vertical-spring factor of 0.05 (the
    bound) that was below the plausible 0.2 from the second step on.  The evidence of a stopped
    refit is where it stopped (a lower bound of its score), and its row says so."""

    def __init__(self, names: Iterable[str], patience: int | None = None):
        self.names = set(names)
        self.patience = WATCH_PATIENCE if patience is None else int(patience)
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


# ----------------------------------------------------------------------------------------------
# Results
# ----------------------------------------------------------------------------------------------


@dataclass
class Candidate:
    """The score of one candidate effect, refitted on top of a base model."""

    effect: str
    base: tuple[str, ...]
    """Effects already in the model it was scored against (greedy selection)."""
    round: int
    """Selection round (1: against the nominal model)."""
    score: float | None
    """BIC gain: ``2 (C_base - C) - nu ln n`` (positive: the data support the effect)."""
    lr: float | None
    """Likelihood-ratio statistic ``2 (C_base - C)``."""
    effective_dof: float | None
    p_value: float | None
    """P-value of ``lr`` against chi-square(``effective_dof``)."""
    significant: bool
    parameters: dict = field(default_factory=dict)
    """The effect's report: estimated values with their uncertainty and a one-line ``summary``."""
    summary: str = ""
    error: str | None = None
    """Why the fit failed, if it did."""
    rivals: tuple[str, ...] = ()
    """For the best of a round: the other significant candidates within :data:`TIE` of its score,
    which the data do not tell apart from it."""
    screen: ScoreTest | None = None
    """Its score test (:mod:`flexforce.smoother.screening`), when screened: at the nominal fit, or, for
    a candidate dropped in a later round, at that round's base (:attr:`base`)."""
    refitted: bool = True
    """False when the score test did not pass: no refit, no evidence (``score`` is None)."""
    implausible: str | None = None
    """Why the estimate is physically implausible (the effect's ``plausible``): then it is not
    ``significant`` whatever its score -- the effect stands in for something else."""
    finding: str = ""
    """The row's one sentence: for a significant effect its size, the evidence and when it acts;
    an implausible one says so; one that cannot be fitted, why in the recording's terms."""
    check: dict | None = None
    """For an effect the selection took, and for the candidates of its round the data do not tell
    from it (:meth:`Diagnosis.partner_checks`): the errors of its base (:attr:`base`) and of the base
    with it against what the fit did not use -- the truth of a simulated recording, or the
    reference sensors of a real one (the F/T readings when not fused, the motion capture):
    ``{"against": "truth" | "sensors", "before": {key: rmse}, "after": {key: rmse}}``
    (:data:`CHECK_WORSE`, :meth:`check_text`)."""

    def check_text(self) -> str:
        """``against the F/T and motion capture (not fitted): vertical force 36.3 -> 31.9 N, ...``,
        ending with what the check says of the effect ("" without a check)."""
        items = _check_items(self.check) if self.check else []
        if not self.check or not items:
            return ""
        parts = [text for _, _, _, text in items]
        worse = [label for label, b, a, _ in items if a > (1.0 + CHECK_WORSE) * b]
        what = _check_reference(self.check)
        names = ", ".join(worse[:-1]) + " and " + worse[-1] if len(worse) > 1 else "".join(worse)
        verdict = (f"the check disagrees: the {names} error{'s' if len(worse) > 1 else ''} "
                   f"rose by more than {CHECK_WORSE:.0%}" if worse else
                   f"the check agrees (no error rose by more than {CHECK_WORSE:.0%})")
        return f"against {what} (not fitted): {', '.join(parts)}; {verdict}"

    @property
    def status(self) -> str:
        """``significant``, ``implausible``, ``not significant``, ``not refitted`` or ``cannot be fitted``."""
        if self.error:
            return "cannot be fitted"
        if not self.refitted:
            return "not refitted"
        if self.implausible:
            return "implausible"
        return "significant" if self.significant else "not significant"

    def screen_text(self, level: float | None = None) -> str:
        """``score T = 322.5 (nu 3.0), p = 1.3e-69`` (and the passing windows of a windowed test)."""
        s = self.screen
        if s is None:
            return ""
        out = f"score T = {s.statistic:.1f} (nu {s.dof:.1f}), p = {s.p_value:.2g}"
        if self.base:  # a later round's test: at that round's base
            out += " at + " + " + ".join(self.base)
        if s.kind == "windowed" and level is not None:
            spans = [f"{w.start_s:.2f}-{w.end_s:.2f} s" for w in s.passing_windows(level)]
            shown = ", ".join(spans[:6]) + (" ..." if len(spans) > 6 else "")
            out += f"; windows passing: {shown or 'none'}"
        return out

    def to_dict(self) -> dict:
        return {"effect": self.effect, "score": _clean(self.score), "significant": bool(self.significant),
                "parameters": _jsonable(self.parameters), "summary": self.summary, "round": self.round,
                "base": list(self.base), "likelihood_ratio": _clean(self.lr),
                "effective_dof": _clean(self.effective_dof), "p_value": _clean(self.p_value),
                "level": _clean(self.level),
                "indistinguishable_from": list(self.rivals), "refitted": bool(self.refitted),
                "status": self.status, "finding": self.finding or self.summary,
                **({"implausible": self.implausible} if self.implausible else {}),
                **({"screen": self.screen.to_dict(self.screen_level)} if self.screen is not None else {}),
                **({"not_refitted": f"not refitted: {self.deferred}" if self.deferred else
                    f"not refitted: score p = {self.screen.p_value:.2g}"}
                   if not self.refitted and self.screen is not None else {}),
                **({"error": self.error} if self.error else {}),
                **({"error_detail": self.error_detail} if self.error_detail else {}),
                **({"check": {**_jsonable(self.check), "text": self.check_text()}} if self.check else {}),
                **({"partner_of": self.partner_of} if self.partner_of else {}),
                **({"constancy": _jsonable(self.constancy)} if self.constancy else {})}

    screen_level: float | None = None
    """Level of the screening (for the passing windows in :meth:`to_dict`)."""
    deferred: str | None = None
    """Why a candidate whose score test passed was not refitted: stronger ones filled the round's
    refits (``diagnose(refit_best=...)``) until the selection stopped."""
    error_detail: str | None = None
    """The solver's own message when the fit failed (``error`` says it in the recording's terms)."""
    partner_of: str | None = None
    """The effect its round selected, for which it may stand (a rival within :data:`TIE`, or a
    pair the identifiability table calls inseparable): its :attr:`check` is then held beside that one's
    (:meth:`Diagnosis.partner_checks`)."""
    level: float | None = None
    """Level its likelihood-ratio p-value was tested at: ``alpha / m``, ``m`` the candidates in its
    round (Holm: :func:`score`); None when not scored (not refitted, or the fit failed)."""
    constancy: dict | None = None
    """For a constant effect the selection would take: its estimate on each half of the recording
    (:func:`constancy`); when the halves disagree the effect is :attr:`implausible`."""


@dataclass
class Snapshot:
    """One fitted model seen through the diagnostics: residuals, flags and, with truth, errors."""

    effects: tuple[str, ...]
    estimate: Estimate
    metrics: Metrics
    flags: list[FlaggedWindow]
    consistency: list
    residual_rms: dict[str, dict[str, float]]
    cost_data: float
    n_residuals: int
    residual_rms_smoothed: dict[str, dict[str, float]] | None = None
    """RMS of the whitened smoothed residuals before standardisation (below 1 under the model:
    the fit absorbs part of the noise); ``residual_rms`` is then that of the standardised ones."""
    raw_residuals: dict[str, np.ndarray] | None = None
    """The whitened smoothed residuals before standardisation (``estimate.residuals`` holds the
    standardised ones: the calibrated view)."""

    @property
    def rmse(self) -> dict[str, float | None]:
        """The comparison's headline errors; on real logs also the errors against the F/T sensors."""
        return headline_errors(self.metrics)

    def to_dict(self) -> dict:
        return {"effects": list(self.effects), "residual_rms": _jsonable(self.residual_rms), "rmse": self.rmse,
                "cost_data": _clean(self.cost_data), "n_residuals": self.n_residuals,
                "flagged_windows": [_jsonable(f.to_dict()) for f in self.flags],
                "inconsistent_axes": [_jsonable(c.to_dict()) for c in self.consistency
                                      if c.chi2_p < ALPHA or c.ljung_box_p < ALPHA],
                "effect_estimates": _jsonable(self.estimate.effects),
                "residuals": ("standardised by their own variance (1 - leverage)" if self.raw_residuals is not None
                              else "whitened"),
                **({"residual_rms_smoothed": _jsonable(self.residual_rms_smoothed)}
                   if self.residual_rms_smoothed is not None else {})}


@dataclass
class Diagnosis:
    """Everything :func:`diagnose` found; :meth:`to_json` is DIR/diagnosis.json."""

    recording: dict
    ranking: list[Candidate]
    """Selected effects in selection order, then the others by their last score."""
    rounds: list[list[Candidate]]
    """Every score of every round of the greedy selection."""
    selected: list[str]
    """Significant effects found by greedy forward selection."""
    added: list[str]
    before: Snapshot
    after: Snapshot | None
    ekf: Snapshot | None = None
    """The EKF on the nominal model: its whitened innovations are its residuals (NIS alongside)."""
    criterion: dict = field(default_factory=dict)
    truth_external_wrench: np.ndarray | None = None
    """(N, 6) the simulated recording's true external wrench (for the figures), None on real logs."""
    screening: list[ScoreTest] = field(default_factory=list)
    """Every candidate's score test at the nominal fit, most significant first (empty unscreened)."""
    identifiability: Identifiability | None = None
    """At the nominal fit, before any refit: which candidates the recording sees and which pairs it
    cannot tell apart (:func:`flexforce.smoother.screening.identifiability`); None when not computed."""
    identifiability_error: str | None = None
    """Why the identifiability table could not be formed."""
    skipped: list[str] = field(default_factory=list)
    """One line per candidate with nothing to act on in the model (:func:`inapplicable`), not tested."""
    swaps: list[str] = field(default_factory=list)
    """One sentence per per-step effect of the greedy selection that a constant candidate replaced
    once the later rounds' effects were in (the selection's second look, :func:`diagnose`)."""

    def identifiability_notes(self) -> list[str]:
        """One sentence per pair that cannot be told apart, with the choice the ranking made between
        them when it refitted both in one round."""
        if self.identifiability is None:
            return []
        out = []
        tested = {t.effect for t in self.screening} | {c.effect for row in self.rounds for c in row}
        for p in self.identifiability.inseparable():
            text = p.text()
            if self.screening or self.rounds:
                aside = [n for n in (p.a, p.b) if n not in tested]
                if aside:
                    text += (f"; {' and '.join(aside)} in the table only, not tested (left out of the default "
                             "catalogue: name it in the candidates to test it)")
            for i, row in enumerate(self.rounds):
                ca = next((c for c in row if c.effect == p.a and c.score is not None), None)
                cb = next((c for c in row if c.effect == p.b and c.score is not None), None)
                if ca is not None and cb is not None:
                    hi, lo = (ca, cb) if ca.score >= cb.score else (cb, ca)  # type: ignore[operator]
                    taken = self.selected[i] if i < len(self.selected) else None
                    if lo.effect == taken:
                        hi, lo = lo, hi
                    # "chose" only for the round's choice; otherwise the two scores as they stand
                    verb = "chose" if hi.effect == taken else "scored"
                    text += f"; round {hi.round} {verb} {_scored(hi)} over {_scored(lo)}"
                    break
            out.append(text)
        return out

    def to_json(self) -> dict:
        out = {"recording": _jsonable(self.recording), "criterion": self.criterion,
               "ranking": [c.to_dict() for c in self.ranking],
               "rounds": [[c.to_dict() for c in r] for r in self.rounds],
               "selected": list(self.selected), "added": list(self.added),
               "ambiguities": self.ambiguities(), "partner_checks": self.partner_checks(),
               "inconstant": self.inconstant(),
               "screening": [s.to_dict(self.criterion.get("screen_level")) for s in self.screening],
               "identifiability": ({**self.identifiability.to_dict(), "notes": self.identifiability_notes()}
                                   if self.identifiability is not None else
                                   ({"error": self.identifiability_error} if self.identifiability_error else None)),
               "before": self.before.to_dict(), "after": self.after.to_dict() if self.after else None,
               "skipped": list(self.skipped), "swaps": list(self.swaps)}
        if self.ekf is not None:
            m = self.ekf.metrics
            out["ekf"] = {"nis": _clean(m.nis), "nis_bounds": list(m.nis_bounds) if m.nis_bounds else None,
                          "flagged_windows": [_jsonable(f.to_dict()) for f in self.ekf.flags],
                          "rmse": self.ekf.rmse}
        return out

    def ranking_table(self) -> str:
        """Plain-text ranking (what the CLI prints)."""
        lines = [f"{'#':>2s} {'effect':24s} {'score':>10s} {'LR':>10s} {'dof':>6s} {'p':>9s}  sig  estimate"]
        level = self.criterion.get("screen_level")
        for i, c in enumerate(self.ranking, 1):
            if c.error:
                lines.append(f"{i:2d} {c.effect:24s} {'-':>10s} {'-':>10s} {'-':>6s} {'-':>9s}  no   "
                             f"cannot be fitted: {c.error}")
                continue
            if not c.refitted:
                why = f"{c.deferred}; " if c.deferred else ""
                lines.append(f"{i:2d} {c.effect:24s} {'-':>10s} {'-':>10s} {'-':>6s} {'-':>9s}  no   "
                             f"not refitted: {why}{c.screen_text(level)}")
                continue
            mark = "yes" if c.significant else ("imp" if c.implausible else "no ")
            lines.append(f"{i:2d} {c.effect:24s} {c.score:10.1f} {c.lr:10.1f} {c.effective_dof:6.1f} "
                         f"{c.p_value:9.2g}  {mark:3s}  {c.finding or c.summary}")
            if c.screen is not None:
                lines.append(f"{'':28s}screened: {c.screen_text(level)}")
            if c.check:
                lines.append(f"{'':28s}checked {c.check_text()}")
            if c.constancy and not c.implausible:
                lines.append(f"{'':28s}constancy: {c.constancy['text']}")
        lines += [f"   {w}" for w in self.swaps]
        lines += [f"   {w}" for w in self.ambiguities()]
        lines += [f"   {w}" for w in self.partner_checks()]
        lines += [f"   {w}" for w in self.inconstant()]
        lines += [f"   {w}" for w in self.skipped]
        if self.identifiability is not None:
            lines.append(self.identifiability.table())
            # the table just printed each pair's sentence: what the rounds made of it, under the pair's name
            lines += [f"   {w.split(':', 1)[0]}: {w[w.index('; round ') + 2:]}"
                      for w in self.identifiability_notes() if "; round " in w]
        elif self.identifiability_error:
            lines.append(f"identifiability: not computed ({self.identifiability_error})")
        return "\n".join(lines)

    def partner_checks(self) -> list[str]:
        """One sentence per selected effect whose round also refitted a candidate that may stand for
        it (a rival within :data:`TIE`, or a pair the identifiability table calls inseparable,
        significant and plausible): each one's errors against what the fits did not use (the truth,
        or the reference sensors), and which of them those favour.  The selection stands (the data
        chose); the sentence shows the user what the independent references say of the choice."""
        out = []
        for i, name in enumerate(self.selected):
            if i >= len(self.rounds):
                break
            row = self.rounds[i]
            chosen = next((c for c in row if c.effect == name), None)
            partners = [c for c in row if c.effect != name and c.check and c.partner_of == name]
            if chosen is None or not chosen.check or not partners:
                continue
            parts = [f"{chosen.effect} {_check_after(chosen.check)}"]
            favoured = []
            for c in partners:
                assert c.check is not None
                parts.append(f"{c.effect} {_check_after(c.check)}")
                verdict = _check_preference(chosen.check, c.check)
                if verdict is not None:
                    favoured.append((c.effect, verdict))
            what = _check_reference(chosen.check)
            rivals = [c.effect for c in partners if c.effect in chosen.rivals]
            table = [c.effect for c in partners if c.effect not in chosen.rivals]
            why = ([f"{' and '.join(rivals)} (score{'s' if len(rivals) > 1 else ''} within {TIE:g} of it)"]
                   if rivals else []) + ([f"{' and '.join(table)} (which the identifiability table cannot tell "
                                          "from it)"] if table else [])
            one = what in ("the truth", "the motion capture")  # "the truth favours", "the F/T ... favour"
            if any(v == "partner" for _, v in favoured):
                better = [e for e, v in favoured if v == "partner"]
                tail = (f"{what} favour{'s' if one else ''} {' and '.join(better)} over the choice (a motion that "
                        "separates them, or knowledge of the robot, settles it)")
            elif any(v == "chosen" for _, v in favoured):
                worse = [e for e, v in favoured if v == "chosen"]
                alike = [c.effect for c in partners if c.effect not in worse]
                tail = (f"{what} agree{'s' if one else ''} with the choice over {' and '.join(worse)}"
                        + (f", not over {' and '.join(alike)}" if alike else ""))
            else:
                tail = f"{what} do{'es' if one else ''} not decide between them"
            out.append(f"round {i + 1} took {name}; beside it, {'; '.join(why)} refitted in that round; against "
                       f"{what} (not fitted), each added to the round's base: {'; '.join(parts)}: {tail}")
        return out

    def inconstant(self) -> list[str]:
        """One sentence per round in which the constancy check (:func:`constancy`) turned down a
        candidate the evidence favoured: what it means for the model."""
        out = []
        for i, row in enumerate(self.rounds):
            bad = [c for c in row if c.constancy and c.constancy.get("made") and not c.constancy["constant"]]
            if not bad:
                continue
            took = next((c.effect for c in row if c.effect in self.selected and c.significant), None)
            names = ", ".join(c.effect for c in bad)
            several = len(bad) > 1
            out.append(f"round {i + 1}: {names} {'were' if several else 'was'} significant but not constant over the "
                       f"recording (each fitted on its two halves: estimates apart beyond {CONSTANCY_Z:g}σ and "
                       f"{CONSTANCY_REL:.0%} of {'their' if several else 'its'} size); "
                       + (f"the round took {took}" if took else "the round took none")
                       + ": what the model misses here changes over the recording (a drift of the local frame, a "
                         "load or a contact that changes, a model error that depends on the motion), and a "
                         "constant effect only stands in for it")
        return out

    def ambiguities(self) -> list[str]:
        """One sentence per round whose best effect the data cannot tell from another."""
        out = []
        for row in self.rounds:
            best = row[0] if row else None
            if best is None or not best.rivals:
                continue
            rows = [next(c for c in row if c.effect == r) for r in best.rivals]
            close = [c for c in rows if best.score - c.score < TIE]  # type: ignore[operator]
            if close:
                others = ", ".join(f"{c.effect} ({c.score:.1f})" for c in close)
                out.append(f"round {best.round}: {best.effect} ({best.score:.1f}) is not told apart from {others}: "
                           f"the scores differ by less than {TIE:g} (a Bayes factor of 20); "
                           f"more varied motion, or knowledge of the robot, must decide")
            charged = [c for c in rows if c not in close]
            if charged:
                others = ", ".join(f"{c.effect} (2ΔE {c.lr:.1f}, score {c.score:.1f})" for c in charged)
                out.append(f"round {best.round}: {best.effect} (2ΔE {best.lr:.1f}, score {best.score:.1f}) fits the "
                           f"data as well as {others}, which the identifiability table calls inseparable from it: "
                           f"the evidence differs by less than {TIE:g}, and the score prefers {best.effect} only for "
                           "its count of unknowns; knowledge of the robot, or a motion that separates them, must "
                           "decide (the check against what the fit did not use may tell)")
        return out


def headline_errors(metrics: Metrics) -> dict[str, float | None]:
    """The comparison's headline errors (``RMSE_KEYS``); on real logs also the errors against the
    F/T sensors (the vertical force's, the force's when the sensors measure more than it, and the
    contacts' moment and sole CoP when they measure moments)."""
    keys: tuple[str, ...] = RMSE_KEYS
    if getattr(metrics, "reference", None) == "sensors":
        keys = keys + ("vertical_force_N", "contact_force_N", "contact_moment_Nm", "contact_cop_m")
    out = {k: _clean(metrics.rmse.get(k)) for k in keys}
    if "contact_force_N" in out and out["contact_force_N"] == out.get("vertical_force_N"):
        # F/T that measure the vertical force alone (the iCub logs): the force error is that one
        del out["contact_force_N"]
    for k in ("contact_moment_Nm", "contact_cop_m"):
        if k in out and out[k] is None:  # F/T without moments: nothing to say
            del out[k]
    return out


def constancy(rec, model, makers: dict[str, Callable[[], object]], base: tuple[str, ...], name: str,
              jobs: int | str = 1, start: Fit | None = None) -> dict:
    """Whether the constant effect ``name`` is the same on both halves of ``rec``.

    The model with ``base`` and ``name`` (``makers``' effects) is fitted on each half
    (:meth:`~flexforce.datasets.recording.Recording.window`); the halves' estimates are compared
    component by component, the difference standardised by the two halves' sigmas and relative to
    the larger estimate.  A constant effect (a bias, a mounting, a stiffness, a delay, a mass) is the
    same in both halves within :data:`CONSTANCY_Z` sigma or within :data:`CONSTANCY_REL` of its size;
    an estimate that changes sign or size between them beyond both stands for
    something else that changes over the recording (on the iCub walk the IMU mounting rotation
    about x: -0.036 +- 0.002 rad in the first 6 s, +0.089 +- 0.0006 in the last 6 s).

    ``start``: a fit of ``rec`` with ``base`` and ``name`` (the round's refit), whose states and
    effects each half starts from, cut to it: the candidate starts at its estimate on the whole
    recording, so that a half whose evidence has more than one optimum in the effect (a delay on a
    walk: from 0, the halves of TALOS's walk with 15 ms stopped at 5.4 and 0.6 ms, from 14.9 ms
    they stay at 14.9) looks for its own near it; without it, at the effect's prior mean.

    Returns ``{"made": True, "constant": bool, "halves": [[t0, t1], [t1, t2]], "value": [...],
    "std": [...], "z": [...], "relative": [...], "largest": (component, z), "text": ...}``, or ``{"made": False,
    "text": why}`` when the recording is too short to halve or a half cannot be fitted.
    """
    duration = float(rec.time[-1]) if rec.n else 0.0
    eff0 = makers[name]()
    if duration < 2.0 * CONSTANCY_MIN_S:
        return {"made": False, "text": f"not checked for constancy: the recording ({duration:.1f} s) is shorter than "
                                       f"two halves of {CONSTANCY_MIN_S:g} s"}
    mid = 0.5 * duration
    spans = [(0.0, mid), (mid, duration)]

    def half(span):
        part = rec.window(*span)
        effects = tuple(model.effects) + tuple(makers[n]() for n in base + (name,))
        begin = None  # the start cut to the half
        if start is not None and start.trajectory is not None and start.model is not None:
            steps = np.flatnonzero((rec.time >= span[0] - 1e-9) & (rec.time <= span[1] + 1e-9))
            tr = start.trajectory
            if steps.size == part.n and tr.R.shape[0] == rec.n:
                from flexforce.smoother.linearize import Trajectory

                begin = dataclasses.replace(start, trajectory=Trajectory(tr.R[steps], tr.q[steps], tr.W[steps],
                                                                         tr.e[steps]))
        return fit_model(part, dataclasses.replace(model, effects=effects), start=begin).estimate.effects.get(name, {})

    from flexforce.compare.runner import fork_map

    reps: list[dict] = [{}, {}]
    for i, ok, value, _ in fork_map(half, spans, jobs):
        if not ok:
            return {"made": False, "text": f"not checked for constancy: a half ({spans[i][0]:.1f}-{spans[i][1]:.1f} s) "
                                           f"cannot be fitted ({type(value).__name__}: {value})"}
        reps[i] = value
    try:
        v = np.array([np.asarray(r["value"], dtype=float).ravel() for r in reps])
        sd = np.array([np.asarray(r["std"], dtype=float).ravel() for r in reps])
    except (KeyError, TypeError, ValueError):
        return {"made": False, "text": "not checked for constancy: the effect's report has no value and std"}
    if v.shape[1] == 0 or v.shape != sd.shape or not np.all(np.isfinite(v)) or not np.all(np.isfinite(sd)):
        return {"made": False, "text": "not checked for constancy: a half's estimate has no finite value or sigma"}
    z = (v[1] - v[0]) / np.sqrt(np.maximum(sd[0] ** 2 + sd[1] ** 2, 1e-300))
    null = np.broadcast_to(np.asarray(getattr(eff0, "null", 0.0), dtype=float), (v.shape[1],))
    size = np.maximum(np.abs(v[0] - null), np.abs(v[1] - null))
    rel = np.abs(v[1] - v[0]) / np.where(size > 0, size, np.inf)
    apart = (np.abs(z) > CONSTANCY_Z) & (rel > CONSTANCY_REL)
    # the component that fails both parts, else the one farthest apart in sigmas
    i = int(np.argmax(np.where(apart, np.abs(z), -1.0))) if apart.any() else int(np.argmax(np.abs(z)))
    names = eff0.component_names() if hasattr(eff0, "component_names") else tuple(str(k) for k in range(v.shape[1]))
    units = eff0.units() if hasattr(eff0, "units") else ("",) * v.shape[1]
    comp = names[i] if i < len(names) else str(i)
    unit = units[i] if i < len(units) and units[i] not in ("", "-") else ""
    what = getattr(eff0, "what", name)
    from flexforce.factors.effects import _fmt

    halves = ", ".join(f"{_fmt(v[h, i])} ± {_fmt(sd[h, i])}{(' ' + unit) if unit else ''} in "
                       f"{spans[h][0]:.1f}-{spans[h][1]:.1f} s" for h in (0, 1))
    constant = not bool(apart.any())
    if constant:
        text = (f"its halves agree: {what} {comp} = {halves} ({abs(z[i]):.1f}σ and {rel[i]:.0%} of it apart, the "
                f"largest difference; not both beyond {CONSTANCY_Z:g}σ and {CONSTANCY_REL:.0%})")
    else:
        text = (f"not constant over the recording: {what} {comp} = {halves} ({abs(z[i]):.0f}σ and {rel[i]:.0%} of "
                f"it apart, beyond {CONSTANCY_Z:g}σ and {CONSTANCY_REL:.0%}); a constant effect does not change "
                "within a recording: the estimate stands for something the model misses that changes over it")
    return {"made": True, "constant": constant, "halves": [list(sp) for sp in spans], "value": v.tolist(),
            "std": sd.tolist(), "z": z.tolist(), "relative": rel.tolist(), "largest": [comp, float(z[i])],
            "text": text}


def _check(rec, base: Fit, fit: Fit, skip: float, known: dict) -> dict | None:
    """:attr:`Candidate.check` of ``fit`` against ``base`` (``known``: errors already computed, by
    the fits' sorted effects); None when the recording has nothing to check against or an
    evaluation fails.  With the F/T fused (``use_ft``) the errors against them are left out: the
    fit used them."""
    errs = []
    for f in (base, fit):
        key = tuple(sorted(f.effects))
        if key not in known:
            try:
                m = evaluate(f.estimate, rec, skip=skip)
            except Exception:  # a check is an aside: the diagnosis goes on without it
                return None
            known[key] = (getattr(m, "reference", None), headline_errors(m), dict(getattr(m, "references", {})))
        errs.append(known[key])
    (ref, before, refs), (_, after, _) = errs
    fused = bool(getattr(fit.model, "use_ft", False))  # --ft: the F/T are data of the fit, no check
    keep = {k: v for k, v in before.items() if v is not None and after.get(k) is not None
            and not (fused and refs.get(k) == "reference: F/T")}
    if not keep:
        return None
    out: dict[str, Any] = {"against": "truth" if ref == "truth" else "sensors", "before": keep,
                           "after": {k: after[k] for k in keep}}
    names = sorted({str(refs[k]).removeprefix("reference: ") for k in keep if k in refs and refs[k] != "truth"})
    if out["against"] == "sensors" and names:
        out["sensors"] = names
    return out


def _check_items(check: dict) -> list[tuple[str, float, float, str]]:
    """``(label, before, after, "tilt 0.61 -> 0.3 deg")`` of each error a :attr:`Candidate.check`
    holds both numbers of, in its order (:data:`CHECK_LABELS`)."""
    out = []
    for key, b in check["before"].items():
        a = check["after"].get(key)
        if b is None or a is None:
            continue
        label, scale, unit = CHECK_LABELS.get(key, (key, 1.0, ""))
        out.append((label, b, a, f"{label} {b * scale:.3g} -> {a * scale:.3g}{unit}"))
    return out


def _check_reference(check: dict) -> str:
    """What a check holds the fit against: ``the truth``, ``the F/T and motion capture``, ..."""
    if check["against"] == "truth":
        return "the truth"
    return f"the {' and '.join(check['sensors'])}" if check.get("sensors") else "the reference sensors"


def _check_after(check: dict) -> str:
    """``(tilt 0.61 -> 0.3 deg, vertical force 36.3 -> 35 N)`` of a :attr:`Candidate.check`."""
    return "(" + ", ".join(text for _, _, _, text in _check_items(check)) + ")"


def _check_preference(chosen: dict, partner: dict) -> str | None:
    """Which of two checks of one base the errors favour: ``"partner"`` when the partner's are lower
    by more than :data:`CHECK_WORSE` on some error and higher by no more than it on any, ``"chosen"``
    the other way round, ``"split"`` when each wins one, None when they are alike."""
    lower = higher = False
    for key, a in chosen["after"].items():
        b = partner["after"].get(key)
        if a is None or b is None:
            continue
        if b < (1.0 - CHECK_WORSE) * a:
            lower = True
        elif b > (1.0 + CHECK_WORSE) * a:
            higher = True
    if lower and not higher:
        return "partner"
    if higher and not lower:
        return "chosen"
    return "split" if lower else None


def _clean(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return _clean(obj)
    return obj if obj is None or isinstance(obj, str) else str(obj)


def summarize_effect(report: dict, effect) -> str:
    """The report's own ``summary``, else ``label = value ± std`` per component."""
    if not isinstance(report, dict):
        return str(report)
    if report.get("summary"):
        return str(report["summary"])
    value = report.get("value")
    if value is None:
        return ""
    value = np.atleast_1d(np.asarray(value, dtype=float))
    std = report.get("std")
    std = np.atleast_1d(np.asarray(std, dtype=float)) if std is not None else None
    labels = tuple(getattr(effect, "labels", ()))
    parts = []
    for j, v in enumerate(value.ravel()[:12]):
        label = labels[j] if j < len(labels) else f"{effect.name}[{j}]"
        unit = ""
        if "[" in label and label.endswith("]"):
            label, unit = label[:label.rindex("[")].strip(), " " + label[label.rindex("[") + 1:-1]
        s = f" ± {std.ravel()[j]:.2g}" if std is not None and j < std.size else ""
        parts.append(f"{label} = {v:.3g}{s}{unit}")
    return ", ".join(parts)


def score(base: Fit, fit: Fit, effect: str, alpha: float = ALPHA,
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


# ----------------------------------------------------------------------------------------------
# The diagnosis
# ----------------------------------------------------------------------------------------------


def mark_rivals(row: list[Candidate], tie: float = TIE, ident=None) -> None:
    """Give the best of a sorted round its rivals: significant candidates within ``tie`` of its
    score, and, with the identifiability table ``ident``, those it calls inseparable from the best
    whose evidence (``lr``, before the unknowns' charge) is within ``tie`` of the best's, both
    charged for constant unknowns: the data fit both equally, and only the count of unknowns
    decides (on a 3 s TALOS sway with an accelerometer bias, the CoM offset scored 6.7 above it
    with 3.3 less evidence: one unknown fewer)."""
    if not row or not row[0].significant or row[0].score is None:
        return
    best = row[0]

    def charged(c: Candidate) -> bool:
        """Whether its score charged constant unknowns (a per-step effect's evidence already
        integrates its own: its score is its 2ΔE, and comparing 2ΔE would leave that out)."""
        return c.lr is not None and c.score is not None and c.lr - c.score > 0.0

    def rival(c: Candidate) -> bool:
        if not c.significant or c.score is None:
            return False
        if best.score - c.score < tie:  # type: ignore[operator]
            return True
        pair = ident.pair(best.effect, c.effect) if ident is not None else None
        return (pair is not None and pair.inseparable and charged(best) and charged(c)
                and abs(best.lr - c.lr) < tie)  # type: ignore[operator]

    best.rivals = tuple(c.effect for c in row[1:] if rival(c))


def with_residual_sigma(est: Estimate) -> Estimate:
    """A copy of a smoother's estimate with the per-axis sigmas of its families (``meta["sigmas"]``)
    where it lacks ``residual_sigma``, so that flagged windows have a size in physical units; the
    estimate itself when it lacks none (the given estimate is never changed).

    Newton-Euler and contact residuals are whitened with a full covariance (force and moment are
    correlated); their standard deviations make the force rows exact and the moment rows an
    approximation (the moment left once the force is explained is smaller).
    """
    sig = est.meta.get("sigmas") or {}
    nc = len(est.contact_names)
    known = {"imu": sig.get("imu"), "newton_euler": sig.get("newton_euler"),
             "integration": sig.get("integration_std"),
             "contact": None if sig.get("contact") is None else list(sig["contact"]) * nc,
             "ft": None if sig.get("ft") is None else list(sig["ft"]) * nc}
    added = {}
    for fam, r in est.residuals.items():
        s = known.get(fam)
        if fam not in est.residual_sigma and s is not None and len(s) == r.shape[1]:
            added[fam] = np.asarray(s, dtype=float)
    if not added:
        return est
    return dataclasses.replace(est, residual_sigma={**est.residual_sigma, **added})


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


def _snapshot(rec, fit: Fit, window: float, alpha: float, skip: float, calibrated: bool = True) -> Snapshot:
    est = with_residual_sigma(fit.estimate)
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


def progress_caller(progress) -> Callable[..., None] | None:
    """``call(label, fraction, message=None)`` for a ``progress`` callback: the message (which
    stage or candidate, what it found, the elapsed time) is passed as a third argument to a callback
    that takes one (a third positional parameter, ``*args`` or a ``message`` keyword), and left out
    for a two-argument ``progress(label, fraction)``."""
    if progress is None:
        return None
    try:
        params = list(inspect.signature(progress).parameters.values())
    except (TypeError, ValueError):  # a builtin without a signature: the two-argument form
        params = []
    positional = [p for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    takes = (len(positional) >= 3 or any(p.kind == p.VAR_POSITIONAL for p in params)
             or any(p.name == "message" for p in params))
    by_keyword = takes and len(positional) < 3 and not any(p.kind == p.VAR_POSITIONAL for p in params)

    def call(label: str, fraction: float, message: str | None = None) -> None:
        if not takes:
            progress(label, fraction)
        elif by_keyword:
            progress(label, fraction, message=message)
        else:
            progress(label, fraction, message)

    return call


def _failure(name: str, err: BaseException, ident: Identifiability | None = None) -> tuple[str, str]:
    """``(reason in the recording's terms, the solver's own message)`` for a candidate that could
    not be screened or fitted."""
    detail = f"{type(err).__name__}: {err}"
    if not isinstance(err, FlexforceError):  # a user's effect raised: say whose code it was
        return f"the effect '{name}' raised {detail}", detail
    info = ident.candidates.get(name) if ident is not None else None
    if info is not None and not info.seen:
        return info.unexcited(), detail
    partner = None
    if ident is not None:
        partner = next((p for p in ident.inseparable() if name in (p.a, p.b)), None)
    if partner is not None:
        other, mine = (partner.b, partner.direction_a) if partner.a == name else (partner.a, partner.direction_b)
        return (f"the recording does not tell its {mine} from {other} (correlation {partner.largest:.3f}): "
                f"{partner.hint or 'more varied motion is needed'}"), detail
    text = str(err).lower()
    if "positive definite" in text or "singular" in text:
        return ("the recording does not determine it: its information at the fit is singular (too short, or "
                "without the motion that excites it)"), detail
    return detail, detail


def _when(rep: dict, effect) -> str:
    """When an estimated effect acts: its significant spans, or throughout for a constant."""
    windows = rep.get("windows") if isinstance(rep, dict) else None
    if windows:
        spans = [f"{w['start_s']:.2f}-{w['end_s']:.2f} s" for w in windows[:6]]
        return "acts " + ", ".join(spans) + (" ..." if len(windows) > 6 else "")
    if isinstance(rep, dict) and "drift" in rep:
        return "acts throughout, drifting"
    if getattr(effect, "constant", False):
        return "acts throughout (a constant)"
    return "acts throughout"


def finding(c: Candidate, rep: dict, effect) -> str:
    """The row's sentence, consistent with its status: a significant effect's size, evidence and
    when it acts; an implausible one flagged as such; a non-significant one never "found"."""
    summary = c.summary
    if c.implausible:
        return f"implausible: {c.implausible} (estimate {summary}); not a finding: another effect in disguise"
    if c.score is None:
        return summary
    level = f", level {c.level:.2g}" if c.level is not None else ""
    evidence = (f"evidence 2ΔE = {c.lr:.1f} for {c.effective_dof:.1f} dof (p = {c.p_value:.2g}{level}), "
                f"BIC score {c.score:.1f}")
    null_text = ("consistent with" in summary) or summary.startswith("no significant")
    if c.significant:
        if null_text:  # the evidence sees it though no single component is beyond 3 sigma
            inner = summary[summary.find("(") + 1:summary.rfind(")")] if "(" in summary else summary
            if int(getattr(effect, "dim", 0)) == 1:  # one unknown: nothing "joint" about it
                summary = f"{inner} (within 3σ of 0, yet the evidence test is significant: a marginal finding)"
            else:
                summary = (f"{inner} (jointly significant; no single component beyond 3σ: the components are "
                           "correlated)")
        return f"{summary}; {evidence}; {_when(rep, effect)}"
    if null_text:
        return f"not significant: {summary}"
    return f"not significant ({evidence}); estimate {summary}"


def screen(rec, fit: Fit, makers: dict[str, Callable[[], object]], window: float = SCREEN_WINDOW,
           progress: Callable[..., None] | None = None, problem=None, jobs: int | str = 1, identify: bool = False,
           table_only: dict[str, Callable[[], object]] | None = None):
    """The score test of every candidate at ``fit`` (name -> :class:`ScoreTest`, or the reason
    when the test failed): one linearisation each, no refit (:mod:`flexforce.smoother.screening`);
    in ``jobs`` forked processes (:func:`flexforce.compare.runner.fork_map`; ``"auto"``:
    :func:`~flexforce.compare.runner.resolve_jobs`), the same results.  ``identify``: also the
    identifiability table of every candidate (:func:`identify_candidates`), as one more task;
    returns ``(tests, (table, reason))``.  ``table_only``: more candidates for the table alone,
    not tested (those left out of the default catalogue).

    ``progress(fraction)`` or ``progress(fraction, message)`` (a callable made by
    :func:`progress_caller` takes the message): one call per candidate, the message naming it
    with its statistic and time."""
    from flexforce.compare.runner import fork_map, resolve_jobs
    from flexforce.smoother import NoiseRule, Problem
    from flexforce.smoother.evidence import forget_states
    from flexforce.smoother.screening import score_test

    if fit.trajectory is None or fit.model is None:
        raise ConfigError("screening needs the fitted trajectory (flexforce.smoother.fit returns it)")
    jobs = resolve_jobs(jobs)
    prob = problem if problem is not None else Problem.build(rec, fit.model, NoiseRule())
    items: list[tuple[str | None, Any]] = ([(None, None)] if identify else []) + list(makers.items())

    def task(item):
        name, make = item
        if name is None:
            return identify_candidates(prob, fit, {**makers, **(table_only or {})}, window)
        return score_test(prob, fit.trajectory, make(), window=window)

    found: dict[str, ScoreTest | str] = {}
    table: tuple = (None, None)
    done = 0
    # With workers, the first constant candidate is tested here, before they fork: the states'
    # factor and inverses its test forms (evidence.shared_states) and the compiled kernels it
    # loads are then the workers' from the start, where each worker formed and loaded them again
    # (on the iCub sway, the two score tests at the final base took 4.8 and 5.2 s in two workers,
    # 1.3 and 0.6 s one after the other in one process).  The same results (jobs = 1 shares them so).
    first: list[tuple[str | None, Any]] = []
    if jobs > 1:
        constant = [it for it in items if it[0] is not None and _constant_effect(it[1], prob)]
        if len(constant) >= 2:
            first = constant[:1]
            items = [it for it in items if it is not constant[0]]

    def results():
        """``(name, ok, result, seconds)``: the candidate tested here first, then the workers'."""
        for i, ok, res, seconds in fork_map(task, first, 1):
            yield first[i][0], ok, res, seconds
        for i, ok, res, seconds in fork_map(task, items, jobs):
            yield items[i][0], ok, res, seconds

    try:
        for name, ok, res, seconds in results():
            if name is None:
                table = res if ok else (None, _failure("identifiability", res)[0])
                continue
            if ok:
                found[name] = res
                msg = f"{name}: T = {res.statistic:.1f} (ν {res.dof:.1f}), p = {res.p_value:.2g}"
            else:  # a user's effect may raise anything: one line, the others go on
                found[name] = _failure(name, res)[0]
                msg = f"{name}: failed ({found[name]})"
            done += 1
            if progress is not None:
                frac = done / max(len(makers), 1)
                if _takes_two(progress):
                    progress(frac, f"{msg} [{seconds:.1f} s]")
                else:
                    progress(frac)
    finally:
        forget_states()  # the candidates' shared inverses (jobs = 1: formed in this process)
    tests = {name: found[name] for name in makers}
    return (tests, table) if identify else tests


def _constant_effect(make: Callable[[], object], prob) -> bool:
    """Whether the effect ``make()`` is one global block (a constant) in ``prob``'s smoother; False
    for a per-step effect or one that cannot be made (its test reports that)."""
    from flexforce.smoother.linearize import is_global

    try:
        return bool(is_global(make(), prob))
    except Exception:  # a user's effect may raise anything: its own test says what
        return False


def _strength(test) -> float:
    """The chi-square tail of a score test, in logs (more negative: stronger)."""
    return float(stats.chi2.logsf(max(test.statistic, 0.0), max(test.dof, 1e-6)))


def _refit_choice(remaining: list[str], tests: dict, ident, best: int | None,
                  understated: Iterable[str] = ()) -> list[str]:
    """The candidates of ``remaining`` a round refits: the ``best`` strongest constant candidates
    by their latest score test, every per-step one (its windowed test, one window at a time at a
    Bonferroni level, is no measure of the whole effect: on the iCub sway the external wrench's
    T = 216 on 5.7 dof was the weakest, its refit the round's best, 5185), every one whose test
    failed (the refit decides), every one of ``understated`` (effects whose ``score_understates``:
    the slope at zero is no measure of a delay; refitted whatever their test), and every one the
    identifiability table cannot tell apart from a chosen one (the refit must choose between them,
    not the screening); all of them when ``best`` is None."""
    understated = set(understated)
    failed = [k for k in remaining if isinstance(tests.get(k), str) or tests.get(k) is None
              or getattr(tests[k], "kind", "constant") == "windowed" or k in understated]
    ranked = sorted((k for k in remaining if k not in failed), key=lambda k: _strength(tests[k]))
    if best is None or len(ranked) <= best:
        return list(remaining)
    chosen = ranked[:best] + failed
    if ident is not None:
        for k in ranked[best:]:
            if any((p := ident.pair(k, c)) is not None and p.inseparable for c in list(chosen)):
                chosen.append(k)
    return [k for k in remaining if k in chosen]


def _score_understates(make: Callable[[], object]) -> bool:
    """Whether the effect ``make`` builds says its score test understates it (``score_understates``)."""
    try:
        return bool(getattr(make(), "score_understates", False))
    except Exception:  # noqa: BLE001 - a plugin that cannot be built fails where it is fitted, with its reason
        return False


def _takes_two(fn) -> bool:
    """Whether ``fn`` accepts two positional arguments."""
    try:
        inspect.signature(fn).bind(0.0, "")
    except TypeError:
        return False
    except ValueError:  # no signature available
        return False
    return True


def diagnose(rec, model=None, candidates: Iterable | None = None, add: Iterable = (), *,
             extra_candidates: Iterable = (), rank: bool = True, max_effects: int = 3, alpha: float = ALPHA,
             window: float = 0.5, skip: float = 0.5,
             ekf: bool = True, progress: Callable[[str, float], None] | None = None,
             screen_level: float | None = SCREEN_LEVEL, screen_window: float = SCREEN_WINDOW,
             calibrated: bool = True, identify: bool = True, refit_best: int | None = REFIT_BEST,
             jobs: int | str = 1, check_constancy: bool = True) -> Diagnosis:
    """Fit the nominal model, rank the candidate effects, and refit with the ``add``-ed ones.

    Args:
        rec: the Recording.
        model: the nominal ModelConfig (the recording's if None); effects it already has stay in.
        candidates: effect names (of ``flexforce.factors.effects.EFFECTS``), Effect classes or
            instances -- a user's effects are treated like the built-in ones.  Default: every
            registered effect, less those whose ``by_default(rec)`` opts out on this recording
            (the footholds without a touch-down: :func:`left_out_by_default`).
        extra_candidates: further candidates ranked beside ``candidates`` (a user's plugins beside
            the default catalogue); named by the user, they never opt out.
        add: effects to add for the before/after comparison (names of candidates, or further
            effect specs); ``"auto"`` stands for the significant effects found by the ranking.
        rank: score the candidates (greedy forward selection); False only refits with ``add``.
        max_effects: at most this many greedy selection rounds add an effect (with screening, the
            candidates left once it is reached are screened at the final base, not refitted).
        alpha: family-wise level of each selection round: its ``m`` candidates (those not selected
            yet, screened out or not) are each tested at ``alpha / m`` (Holm); also the level of the
            windowed residual tests.
        window: length of the residual windows, s.
        skip: seconds left out at the start of the error statistics (filter convergence).
        ekf: also run the EKF on the nominal model (innovations, NIS).
        progress: called with (stage label, fraction done of that stage) -- and, when it takes a
            third argument (or a ``message`` keyword), a message naming the stage or candidate
            with what it found and the elapsed time, once per stage and per candidate
            (:func:`progress_caller`).
        screen_level: level of the score test at the nominal fit (:func:`screen`): only the
            candidates whose score p-value is below it are refitted and scored by the evidence;
            None refits every candidate (no screening).
        screen_window: window of a per-step effect's score test, s.
        calibrated: the smoother's residuals standardised by their own variance, their tests
            accounting for their correlation in time (:func:`calibrated_view`); False: the
            whitened smoothed residuals tested as if they were innovations (conservative).
        identify: before any refit, the identifiability table of the candidates at the nominal
            fit (:attr:`Diagnosis.identifiability`).
        refit_best: per round, refit only this many of the candidates that pass the screening,
            the strongest first (the chi-square tail of their score test), together with every
            candidate the identifiability table cannot tell apart from one of them; the others
            wait for the next round (screened again at its base).  None refits every one that
            passes.  On real logs every candidate passes (the model is never exact).
        jobs: worker processes (forked: :func:`flexforce.compare.runner.fork_map`) for the
            candidates' score tests, a round's refits and the before/after views; the same results
            as ``jobs=1``, each worker taking about the memory of one fit.  ``"auto"``: one per
            usable core, as the memory available holds them, decided once the nominal model is
            fitted (:func:`flexforce.compare.runner.resolve_jobs`; each worker assumed to need what
            this process then holds).
        check_constancy: before a round takes a constant effect, fit it again on each half of the
            recording (:func:`constancy`); halves that disagree beyond :data:`CONSTANCY_Z` sigma make
            it implausible (the round takes the next).  Costs two fits of half the recording per
            round that takes a constant effect.
    """
    from flexforce.compare.runner import check_jobs, describe, fork_map, resolve_jobs
    from flexforce.factors.model import ModelConfig

    rec.validate()
    if model is None:
        model = ModelConfig.from_recording(rec)
    add = list(add or ())
    want_auto = AUTO in add
    add = [a for a in add if a != AUTO]
    cands = resolve_candidates(candidates) if candidates is not None or registered_effects() else {}
    extra = resolve_candidates(list(extra_candidates)) if extra_candidates else {}
    for name in extra:
        if name in cands:
            raise ConfigError(f"two candidate effects are named '{name}'; effect names must be unique "
                              "(an extra candidate beside the catalogue's)")
    cands.update(extra)
    cands = {k: bound(m, rec, model) for k, m in cands.items()}
    if rank and not cands:
        raise ConfigError("no candidate effects to rank: flexforce.factors.effects is not available; pass candidates")
    for name in list(cands):
        if name in {e.name for e in model.effects}:
            del cands[name]  # already in the model
    skipped = inapplicable(rec, model, cands) if rank else {}
    table_only: dict[str, Callable[[], object]] = {}
    if candidates is None and rank:  # the default catalogue: a costly candidate may opt out here
        left_out = left_out_by_default(rec, {k: v for k, v in cands.items() if k not in extra})
        skipped.update(left_out)
        # not refitted, but in the identifiability table: a selection it cannot be told from says so
        table_only = {k: cands[k] for k in left_out}
    for name in skipped:
        del cands[name]  # nothing to act on in this model (an F/T offset without F/T fusion)
    add_makers: dict[str, Callable[[], object]] = {}
    for spec in add:
        if isinstance(spec, str) and spec in cands:
            add_makers[spec] = cands[spec]
        else:
            name, make = effect_factory(spec)
            add_makers[name] = bound(make, rec, model)
    makers = {**cands, **add_makers}

    call = progress_caller(progress)
    t_start = time.perf_counter()

    def cb(label):
        return (lambda f: call(label, f)) if call else None

    def cb_message(label):
        """A stage's progress that also takes a message (the screening's, one per candidate)."""
        return (lambda f, message=None: call(label, f, message)) if call else None

    def say(label: str, message: str, t0: float) -> None:
        if call is not None:
            call(label, 1.0, f"{message} [{time.perf_counter() - t0:.1f} s, {time.perf_counter() - t_start:.0f} s "
                             "in all]")

    cache: dict[tuple[str, ...], Fit] = {}
    watching = rank  # the selection's refits are watched (LeavingPlausible), the added effects' fit is not

    def fit_with(names: tuple[str, ...], progress=None) -> Fit:
        """The model with the candidates ``names`` added, fitted, from the fit of the most of them
        there is (the round's base: the refit only moves what the new effect explains)."""
        effects = tuple(model.effects) + tuple(makers[n]() for n in names)
        within = [key for key in cache if set(key) < set(names)]
        # the round's base when it is there (a round's refit adds the last name to it), else the most
        start = cache.get(tuple(sorted(names[:-1]))) if names else None
        if start is None and within:
            start = cache[max(within, key=len)]
        # the effects this refit adds are watched: an estimate leaving the plausible range ends it
        new = set(names) - set(start.effects if start is not None else ())
        return fit_model(rec, dataclasses.replace(model, effects=effects), progress=progress, start=start,
                         watch=LeavingPlausible(new) if new and watching else None)

    def fitted(names: tuple[str, ...]) -> Fit:
        key = tuple(sorted(names))
        if key in fit_errors:
            raise fit_errors.pop(key)
        if key not in cache:
            label = "nominal" if not names else "+ " + " + ".join(names)
            t0 = time.perf_counter()
            cache[key] = fit_with(names, progress=cb(label))
            say(label, f"fitted {label if names else 'the nominal model'}", t0)
        return cache[key]

    check_jobs(jobs)
    fit_errors: dict[tuple[str, ...], Exception] = {}
    fit_seconds: dict[tuple[str, ...], float] = {}

    side: dict[tuple[str, ...], Snapshot] = {}  # before/after views formed beside refits, by fit

    def after_effects() -> list[str]:
        """The effects of the after fit: the selection (with ``add=["auto"]``), then those added."""
        return list(dict.fromkeys((selected if want_auto else []) + list(add_makers)))

    def fit_all(names_list: list[tuple[str, ...]], views: list[tuple[str, ...]] | None = None) -> None:
        """Fit the models not fitted yet, in ``jobs`` worker processes (into ``cache``; a failure
        into ``fit_errors``, raised by :func:`fitted`).  With ``views`` (fitted effect sets),
        their before/after views and the nominal fit's are formed beside them, as more tasks
        (the last to be taken): the second look's trials, the diagnosis's last fits, often one
        alone, then share the processes with the views that would follow them (on the iCub sway
        a 2.5 s refit, then two views of 2.2 s).  Not earlier: a view formed beside a round's
        refits lengthens that round when it does not fit in a process they leave idle (on a
        60 s recording a view takes 14 s, a refit 14-16 s).  A view that fails is left to the
        end, formed again there, where it raises."""
        todo = [n for n in dict.fromkeys(names_list) if tuple(sorted(n)) not in cache]
        wanted = [(), *(tuple(sorted(v)) for v in views)] if views else []
        shown = [k for k in dict.fromkeys(wanted) if k in cache and k not in side]
        if jobs == 1 or not todo or len(todo) + len(shown) < 2:
            return
        tasks: list[Callable[[], Any]] = [functools.partial(fit_with, n) for n in todo]
        tasks += [functools.partial(_snapshot, rec, cache[k], window, alpha, skip, calibrated) for k in shown]
        for i, ok, value, seconds in fork_map(lambda task: task(), tasks, jobs):
            if i >= len(todo):
                if ok:
                    side[shown[i - len(todo)]] = value
                continue
            key = tuple(sorted(todo[i]))
            if ok:
                cache[key] = value
                label = "+ " + " + ".join(todo[i])
                if call is not None:
                    call(label, 1.0, f"fitted {label} [{seconds:.1f} s, {time.perf_counter() - t_start:.0f} s in all]")
            else:
                fit_errors[key] = value
            fit_seconds[key] = seconds

    if screen_level is not None and not 0.0 < screen_level < 1.0:
        raise ConfigError(f"screen_level = {screen_level!r}; expected a probability in (0, 1) or None (no screening)")
    if refit_best is not None and (isinstance(refit_best, bool) or not isinstance(refit_best, int)
                                   or refit_best < 1):
        raise ConfigError(f"refit_best = {refit_best!r}; expected an integer >= 1 (candidates refitted per round) "
                          "or None (every candidate that passes the screening)")
    nominal = fitted(())
    jobs = resolve_jobs(jobs)  # "auto": decided with the nominal fit in memory (what a worker starts from)
    checked: dict = {}  # errors against the truth or the reference sensors, by the fit's sorted effects
    rounds: list[list[Candidate]] = []
    selected: list[str] = []
    screened: dict[str, ScoreTest | str] = {}
    dropped: list[Candidate] = []
    ident: Identifiability | None = None
    ident_error: str | None = None
    prob = None
    if rank and cands and nominal.trajectory is not None and nominal.model is not None:
        from flexforce.smoother import NoiseRule, Problem

        prob = Problem.build(rec, nominal.model, NoiseRule())
    if rank:
        remaining = list(cands)
        understated = [k for k in cands if _score_understates(cands[k])]
        early: tuple | None = None
        if screen_level is not None and cands:
            t0 = time.perf_counter()
            if jobs > 1 and identify and prob is not None:
                # the table beside the score tests, on every candidate (the longest task first); formed
                # again below only if a test failed (the table leaves out the failed ones)
                screened, early = screen(rec, nominal, cands, screen_window, progress=cb_message("screening"),
                                         problem=prob, jobs=jobs, identify=True, table_only=table_only)
            else:
                screened = screen(rec, nominal, cands, screen_window, progress=cb_message("screening"), problem=prob,
                                  jobs=jobs)
        if identify and cands and prob is not None:
            if early is None or any(isinstance(v, str) for v in screened.values()):
                t0 = time.perf_counter()
                ident, ident_error = identify_candidates(prob, nominal, {**{k: v for k, v in cands.items()
                                                                            if not isinstance(screened.get(k), str)},
                                                                         **table_only}, screen_window)
            else:
                ident, ident_error = early
            if ident is not None:
                msg = (f"identifiability: {len(ident.inseparable())} pairs cannot be told apart, "
                       f"{len(ident.not_seen())} candidates not fully seen")
            else:
                msg = f"identifiability: not computed ({ident_error})"
            say("identifiability", msg, t0)
        if screen_level is not None and screened:
            tests = {k: v for k, v in screened.items() if not isinstance(v, str)}
            for k, v in screened.items():  # a failed test: the reason in the recording's terms
                if isinstance(v, str) and ident is not None and k in ident.candidates \
                        and not ident.candidates[k].seen:
                    screened[k] = ident.candidates[k].unexcited()
            order = sorted(tests, key=lambda k: (tests[k].p_value, -tests[k].statistic))
            # a failed test is refitted (the refit decides); passing ones first, most significant
            # first; an effect whose test understates it (a delay) is refitted whatever its test
            remaining = [k for k in order if tests[k].p_value < screen_level or k in understated] + \
                [k for k, v in screened.items() if isinstance(v, str)]
            for k in order:
                if tests[k].p_value >= screen_level and k not in understated:
                    dropped.append(Candidate(k, (), 1, None, None, None, None, False, screen=tests[k], refitted=False,
                                             screen_level=screen_level))
        latest: dict[str, ScoreTest | str] = dict(screened)
        this_round: list[str] = []
        last_keys: set[tuple[str, ...]] = set()  # the fits of the previous round (kept one round more)

        def waited(k: str, round_: int, why: str) -> None:
            """A candidate that passed the screening but was not refitted: listed with why."""
            t = latest.get(k)
            dropped.append(Candidate(k, tuple(selected), round_, None, None, None, None, False,
                                     screen=None if isinstance(t, str) else t, refitted=False,
                                     screen_level=screen_level, deferred=why))

        while remaining:
            # a candidate whose refit came out implausible in the previous round is neither screened
            # nor refitted again (its estimate stood in for something the effect just selected
            # explains better; on the iCub sway, the anisotropic stiffness beside the accelerometer
            # bias, then beside the wrench too: 17 s): listed with that refit's word
            for c in (rounds[-1] if rounds else []):
                if c.implausible and c.effect in remaining:
                    remaining.remove(c.effect)
                    waited(c.effect, len(rounds) + 1, f"its refit in round {c.round} was implausible ("
                                                      + (f"score {c.score:.1f}: " if c.score is not None else "")
                                                      + f"{c.implausible})")
            if not remaining:
                break
            base = fitted(tuple(selected))
            if selected and screen_level is not None and base.trajectory is not None and base.model is not None:
                # screen the remaining candidates again at the new base: an effect that only stood in
                # for the one just selected stops passing, and is not refitted
                from flexforce.smoother import NoiseRule, Problem

                again = screen(rec, base, {k: makers[k] for k in remaining}, screen_window,
                               progress=cb_message("screening at + " + " + ".join(selected)),
                               problem=Problem.build(rec, base.model, NoiseRule()), jobs=jobs)
                for k, v in again.items():
                    if not isinstance(v, str) and v.p_value >= screen_level and k not in understated:
                        remaining.remove(k)
                        dropped.append(Candidate(k, tuple(selected), len(rounds) + 1, None, None, None, None, False,
                                                 screen=v, refitted=False, screen_level=screen_level))
                if not remaining:
                    break
                latest.update(again)
                if len(selected) >= max_effects:
                    # the selection is full: what is left is reported by its score test at the final
                    # base, not refitted for a round whose choice would not be taken
                    for k in remaining:
                        waited(k, len(rounds) + 1, f"its score test passed at the final base, but {max_effects} "
                                                   "effects (max_effects) are selected")
                    break
            # Holm: the round's tests at alpha / m, m every candidate not selected yet (those the
            # screening dropped were tested too)
            m = len(cands) - len(selected)
            round_base = tuple(selected)
            row = []
            this_round = []
            best = None
            while True:
                # the strongest that wait (refit_best); when every one refitted is turned down
                # (implausible, not constant), the round refits those that waited behind them
                batch = _refit_choice([k for k in remaining if k not in this_round], latest, ident,
                                      refit_best if screen_level is not None else None, understated)
                if not batch:
                    break
                this_round += batch
                fit_all([round_base + (name,) for name in batch])
                for name in batch:
                    t0 = time.perf_counter() - fit_seconds.pop(tuple(sorted(tuple(selected) + (name,))), 0.0)
                    label = "+ " + " + ".join(tuple(selected) + (name,))
                    try:
                        f = fitted(tuple(selected) + (name,))
                    except Exception as err:  # a user's effect may raise anything: one line, the others go on
                        reason, detail = _failure(name, err, ident)
                        row.append(Candidate(name, tuple(selected), len(rounds) + 1, None, None, None, None, False,
                                             error=reason, error_detail=detail, finding=f"cannot be fitted: {reason}"))
                        say(label, f"{name}: cannot be fitted: {reason}", t0)
                        continue
                    s, lr, nu, p, sig = score(base, f, name, alpha, tests=m)
                    rep = f.estimate.effects.get(name, {})
                    test = latest.get(name)  # its score test at this round's base (the nominal fit's in round 1)
                    eff = makers[name]()
                    c = Candidate(name, tuple(selected), len(rounds) + 1, s, lr, nu, p, sig, rep,
                                  summarize_effect(rep, eff), screen=None if isinstance(test, str) else test,
                                  screen_level=screen_level, level=alpha / m)
                    c.implausible = _plausibility(eff, rep, prob) if sig or f.stopped else None
                    if f.stopped:  # the refit ended with the estimate leaving the plausible range
                        c.implausible = f"{c.implausible or 'its estimate left the plausible range'}; {f.stopped}"
                    if c.implausible:
                        c.significant = False
                    c.finding = finding(c, rep, eff)
                    row.append(c)
                    say(label, f"{name}: score {s:.1f}, {c.status}", t0)
                row.sort(key=lambda c: -math.inf if c.score is None else c.score, reverse=True)
                # the best plausible candidate (an implausible one is no finding, whatever its score); a
                # constant one the selection would take must be the same on both halves of the recording
                best = None
                for c in row:
                    if c.implausible:
                        continue
                    if check_constancy and c.significant and len(selected) < max_effects and prob is not None \
                            and c.constancy is None and _constant(makers[c.effect](), prob):
                        t0 = time.perf_counter()
                        row_fit = cache.get(tuple(sorted(tuple(selected) + (c.effect,))), base)
                        c.constancy = constancy(rec, model, makers, tuple(selected), c.effect, jobs, start=row_fit)
                        say(f"constancy of {c.effect}", f"{c.effect}: {c.constancy['text']}", t0)
                        if c.constancy.get("made") and not c.constancy["constant"]:
                            c.implausible = c.constancy["text"]
                            c.significant = False
                            c.finding = finding(c, c.parameters, makers[c.effect]())
                            continue
                    best = c
                    break
                if best is not None or not any(c.implausible for c in row):
                    break
            rounds.append(row)
            # the best's rivals among the plausible ones (those the data do not tell from it)
            mark_rivals([c for c in row if not c.implausible], ident=ident)
            stop = best is None or not best.significant or len(selected) >= max_effects
            if not stop:
                assert best is not None
                selected.append(best.effect)
                remaining.remove(best.effect)
                best.check = _check(rec, base, fitted(tuple(selected)), skip, checked)
                # the candidates that may stand for it (rivals, the table's inseparable ones), refitted
                # in this round: held against the same references (Diagnosis.partner_checks)
                for c in row:
                    if c is best or c.implausible or not c.significant or c.score is None:
                        continue
                    pair = ident.pair(best.effect, c.effect) if ident is not None else None
                    if c.effect in best.rivals or (pair is not None and pair.inseparable):
                        key = tuple(sorted(round_base + (c.effect,)))
                        if key in cache:
                            c.check = _check(rec, base, cache[key], skip, checked)
                            c.partner_of = best.effect
            # the fits of the rounds before the previous one are done with (their rows keep what
            # they found): free their estimates, so that memory does not grow with the number of
            # candidates.  The previous round's are kept: the second look fits the selection without
            # a per-step effect taken before the last round, which is one of them when the last
            # round is this one (on the iCub sway: the accelerometer and gyro biases without the
            # wrench, 5 s)
            this_keys = {tuple(sorted(round_base + (n,))) for n in this_round}
            keep = {(), tuple(sorted(selected))} | this_keys | last_keys
            for key in [k for k in cache if k not in keep]:
                del cache[key]
            last_keys = this_keys
            if stop:
                # those that passed the screening but waited behind stronger ones
                for k in remaining:
                    if k not in this_round:
                        waited(k, len(rounds), f"its score test passed, but the round refitted the {refit_best} "
                                               "strongest (refit_best) and stopped")
                break
    swaps: list[str] = []
    if rank and len(selected) >= 2:
        def strongest(without: tuple[str, ...], names: list[str]) -> list[str] | None:
            """``names`` whose score test passes at the fit of ``without``, strongest first (None
            when the test cannot be formed)."""
            base_fit = fitted(without)
            if screen_level is None or base_fit.trajectory is None or base_fit.model is None or not names:
                return None
            got = screen(rec, base_fit, {k: makers[k] for k in names}, screen_window,
                         progress=cb_message("second look: screening at + " + " + ".join(without)), jobs=jobs)
            ok = {k: v for k, v in got.items() if not isinstance(v, str) and v.p_value < screen_level}
            return sorted(ok, key=lambda k: _strength(ok[k]))

        def fit_trials(trials: list[tuple[str, ...]]) -> None:
            # the view of the selection as it stands is formed beside the trials (used unless one replaces it)
            fit_all(trials, views=[tuple(after_effects())])

        swaps = _second_look(selected, rounds, makers, fitted, fit_trials, prob, say, strongest,
                             check=lambda b, f: _check(rec, b, f, skip, checked))
    ranking: list[Candidate] = []
    for i, name in enumerate(selected):
        ranking.append(next(c for c in rounds[i] if c.effect == name))
    if rounds:
        # a candidate screened out (or left unrefitted) at a later base is listed by that, its latest word
        later = {d.effect for d in dropped if d.round > len(rounds)}
        ranking += [c for c in rounds[-1] if c.effect not in selected and c.effect not in later]
    ranking += dropped
    added = after_effects()
    watching = False
    shown = [()] + ([tuple(added)] if added else [])  # the before and after fits
    fits = [fitted(k) for k in shown]
    views: list[Snapshot | None] = [side.get(tuple(sorted(k))) for k in shown]
    left = [i for i, v in enumerate(views) if v is None]
    for i, ok, value, _ in fork_map(lambda k: _snapshot(rec, fits[k], window, alpha, skip, calibrated), left, jobs):
        if not ok:
            raise value
        views[left[i]] = value
    before, after = views[0], (views[1] if added else None)
    assert before is not None
    ekf_snap = None
    if ekf:
        from flexforce.compare.ekf.filter import run_ekf

        t0 = time.perf_counter()
        try:
            est = run_ekf(rec, model, progress=cb("ekf"))
        except FlexforceError:
            est = None
        say("ekf", "EKF on the nominal model" + (" failed" if est is None else ""), t0)
        if est is not None:
            ekf_snap = Snapshot((), est, evaluate(est, rec, skip=skip), flag_windows(est, window=window, alpha=alpha),
                                consistency(est), residual_rms(est), float("nan"), 0)
    criterion = {"name": "Laplace evidence + BIC for constants",
                 "score": "2 (E_base - E) - nu_constant ln(n), E the negative log marginal likelihood",
                 "alpha": alpha,
                 "significant": ("score > 0 and p < alpha / m (constant unknowns: likelihood-ratio p against "
                                 "chi-square(effective dof); per-step ones: p = 1 / Bayes factor); alpha: "
                                 "family-wise level of each round (Holm: alpha / candidates in the round, m those "
                                 "not selected yet)"),
                 "tie": TIE,
                 "n_residuals": nominal.n_residuals, "penalty_per_dof": math.log(max(nominal.n_residuals, 2)),
                 "fit": "flexforce.smoother.fit",
                 "screen_level": screen_level, "screen_window_s": screen_window if screen_level is not None else None,
                 "refit_best": refit_best if screen_level is not None else None,
                 "constancy": ({"z": CONSTANCY_Z, "relative": CONSTANCY_REL, "min_half_s": CONSTANCY_MIN_S,
                                "rule": "a constant effect a round would take is fitted on each half of the recording; "
                                        "halves apart beyond z sigma and the relative fraction of its size on one "
                                        "component make it implausible"} if check_constancy else None),
                 "screen": ("score (Lagrange-multiplier) test at the nominal fit, and again at each round's base once "
                            "an effect is selected: g^T S^-1 g against chi-square with the effect's effective dof; "
                            "only candidates with p < screen_level are refitted")
                 if screen_level is not None else "none: every candidate refitted"}
    truth = getattr(rec, "truth", None)
    tests_sorted = sorted((v for v in screened.values() if not isinstance(v, str)),
                          key=lambda t: (t.p_value, -t.statistic))
    return Diagnosis(describe(rec), ranking, rounds, selected, added, before, after, ekf_snap, criterion,
                     None if truth is None else np.asarray(truth.external_wrench, dtype=float), tests_sorted,
                     ident, ident_error, list(skipped.values()), swaps)


def _criterion(f: Fit) -> float | None:
    """The selection's criterion of a fitted model, half its BIC: the negative log evidence plus
    ``ln n / 2`` per effective dof of its constant unknowns (score differences are twice its
    differences); None without the evidence."""
    if f.cost_evidence is None:
        return None
    charge = sum(f.effective_dof.get(e, 0.0) for e in f.global_effects)
    return float(f.cost_evidence) + 0.5 * math.log(max(f.n_residuals, 2)) * charge


def _constant(effect, prob) -> bool:
    """Whether the smoothers fit ``effect``'s unknowns as one global block
    (:func:`flexforce.smoother.linearize.is_global`); False when a user's effect cannot say."""
    from flexforce.smoother.linearize import is_global

    try:
        return is_global(effect, prob)
    except Exception:  # a user's effect may raise anything: not taken for a constant
        return False


def _second_look(selected: list[str], rounds: list[list[Candidate]], makers: dict, fitted, fit_all, prob,
                 say, strongest=None, check=None) -> list[str]:
    """Replace, in ``selected`` (in place), a per-step effect the greedy selection took before its
    last round by a constant candidate, when the whole selection with the replacement has the
    better criterion (:func:`_criterion`) and the replacement's estimate is plausible.

    A random-walk wrench can absorb part of every constant effect, so it can win a round against
    each of them alone and still lose, as a model, once the later rounds' effects are in: on the
    wide benchmark's 3 s Romeo weight shift with a CoM offset and softer contacts, the wrench won
    round 1 (2 dE 12 099 against the CoM offset's 8 704) and the stiffness round 2, but the CoM
    offset with the stiffness beats the wrench with it by 2 dE = 116 (constant unknowns charged).
    Tried: for each such effect, the :data:`SWAP_ALTERNATIVES` constant candidates whose score
    tests are strongest at the fit of the rest of the selection (``strongest(without, names)``;
    on TALOS's weight shift the CoM offset was not among round 1's refits), or, without the test,
    the round's strongest significant, plausible refits; one found implausible at its last refit is
    not tried again (on the iCub sway, the anisotropic stiffness: 23 s).  Returns one sentence per
    replacement."""
    out: list[str] = []
    current = fitted(tuple(selected))
    for i, name in enumerate(list(selected[:-1])):
        if name in current.global_effects or i >= len(rounds) or getattr(makers[name](), "per_episode", False):
            # a constant (its rivals are the table's business), or constant per contact episode (the
            # footholds: not a random walk that can follow whatever the model misses): the choice stands
            continue
        constants = [k for k in makers if k not in selected and _constant(makers[k](), prob)]
        # the strongest score tests with the rest of the selection in and this effect out; without
        # them, the round's strongest significant, plausible refits
        alternatives = strongest(tuple(s for s in selected if s != name), constants) if strongest else None
        if alternatives is None:
            alternatives = [c.effect for c in rounds[i] if c.significant and not c.implausible and c.score is not None
                            and c.effect in constants]
        # of those, one whose last refit found it implausible is not tried again (the swap takes a
        # plausible replacement only; a round does not refit one its previous round found implausible)
        gone = {c.effect for row in rounds for c in row if c.implausible}
        alternatives = [a for a in alternatives[:SWAP_ALTERNATIVES] if a not in gone]
        if not alternatives:
            continue
        trials = [tuple(alt if s == name else s for s in selected) for alt in alternatives]
        fit_all(trials)
        best: tuple[float, str, Fit] | None = None
        here = _criterion(current)
        for alt, names in zip(alternatives, trials):
            t0 = time.perf_counter()
            try:
                f = fitted(names)
            except Exception:  # a failed trial changes nothing
                continue
            value = _criterion(f)
            if value is None or here is None or value >= here:
                continue
            if f.stopped or _plausibility(makers[alt](), f.estimate.effects.get(alt, {}), prob):
                continue
            say("second look", f"{alt} in place of {name}: 2ΔE {2.0 * (here - value):.1f}", t0)
            if best is None or value < best[0]:
                best = (value, alt, f)
        if best is not None:
            assert here is not None
            value, alt, f = best
            others = [s for s in selected if s != name]
            # its row: the replacement as fitted with the rest of the selection, scored against it
            # (its round's own row, if it had one, judged it alone)
            rep = f.estimate.effects.get(alt, {})
            eff = makers[alt]()
            rest = fitted(tuple(others))
            sc, lr, nu, p, sig = score(rest, f, alt)
            row = Candidate(alt, tuple(others), i + 1, sc, lr, nu, p, sig, rep, summarize_effect(rep, eff))
            row.finding = finding(row, rep, eff)
            row.check = check(rest, f) if check is not None else None
            rounds[i][:] = [c for c in rounds[i] if c.effect != alt] + [row]
            out.append(f"second look: {alt} in place of {name} beside {', '.join(others)} (2ΔE = "
                       f"{2.0 * (here - value):.1f} in favour, constant unknowns charged): round {i + 1} took "
                       f"{name}, a per-step effect, which stood in for part of what the later rounds' effects "
                       "explain")
            selected[i] = alt
            current = f
    return out


def inapplicable(rec, model, makers: dict[str, Callable[[], object]]) -> dict[str, str]:
    """Name -> ``"<name>: <reason>"`` for the candidates whose optional ``applicable(problem)`` says
    they have nothing to act on in ``model`` (an F/T offset when the F/T readings are not fused):
    skipped with that line, never fitted.  A check that raises leaves its candidate to the tests."""
    checks: dict[str, Any] = {}
    for name, make in makers.items():
        try:
            eff = make()
        except Exception:  # the fit says what is wrong with it
            continue
        if callable(getattr(eff, "applicable", None)):
            checks[name] = eff
    if not checks:
        return {}
    from flexforce.smoother import NoiseRule, Problem

    prob = Problem.build(rec, model, NoiseRule())
    out = {}
    for name, eff in checks.items():
        try:
            why = eff.applicable(prob)
        except Exception:
            continue
        if why:
            out[name] = f"{name}: {why}"
    return out


def left_out_by_default(rec, makers: dict[str, Callable[[], object]]) -> dict[str, str]:
    """Name -> ``"<name>: <reason>"`` for the candidates whose optional ``by_default(rec)`` says
    they are not worth their cost on this recording unless asked for (the footholds without a
    touch-down); they are tested when named in ``candidates``."""
    out = {}
    for name, make in makers.items():
        try:
            check = getattr(make(), "by_default", None)
            why = check(rec) if callable(check) else None
        except Exception:  # the fit says what is wrong with it
            continue
        if why:
            out[name] = f"{name}: {why}"
    return out


def _plausibility(effect, report: dict, problem) -> str | None:
    """The effect's own ``plausible(report, problem)`` verdict (None without the method)."""
    check = getattr(effect, "plausible", None)
    if check is None or not isinstance(report, dict):
        return None
    try:
        return check(report, problem)
    except Exception as err:  # a user's check that fails says so, it does not stop the diagnosis
        return f"its plausibility check raised {type(err).__name__}: {err}"


def identify_candidates(prob, fit: Fit, makers: dict[str, Callable[[], object]], window: float = SCREEN_WINDOW
                        ) -> tuple[Identifiability | None, str | None]:
    """The identifiability table of ``makers`` at ``fit`` (:func:`flexforce.smoother.screening.identifiability`),
    or None and the reason; a candidate that breaks it is left out and named."""
    from flexforce.smoother.screening import identifiability

    effects: dict[str, Any] = {}
    errors: dict[str, str] = {}
    for name, make in makers.items():
        try:
            eff: Any = make()
            eff.prior(prob)
            effects[name] = eff
        except Exception as err:
            errors[name] = _failure(name, err)[0]
    if not effects:
        return None, "no candidate to compare"
    try:
        ident = identifiability(prob, fit.trajectory, list(effects.values()), window=window,  # type: ignore[arg-type]
                                n_residuals=fit.n_residuals)
    except Exception as err:
        return None, _failure("identifiability", err)[0]
    ident.errors.update(errors)
    return ident, None


def identifiability(rec, candidates: Iterable | None = None, model=None, window: float = SCREEN_WINDOW,
                    progress: Callable[[float], None] | None = None) -> Identifiability:
    """Before any refit: fit the nominal model and say which candidates the recording sees and
    which pairs it cannot tell apart (:func:`flexforce.smoother.screening.identifiability`)."""
    from flexforce.factors.model import ModelConfig
    from flexforce.smoother import NoiseRule, Problem

    rec.validate()
    if model is None:
        model = ModelConfig.from_recording(rec)
    cands = {k: bound(m, rec, model) for k, m in resolve_candidates(candidates).items()}
    nominal = fit_model(rec, model, progress=progress)
    if nominal.trajectory is None or nominal.model is None:
        raise ConfigError("the identifiability table needs the fitted trajectory (flexforce.smoother.fit returns it)")
    prob = Problem.build(rec, nominal.model, NoiseRule())
    ident, err = identify_candidates(prob, nominal, cands, window)
    if ident is None:
        raise ConfigError(f"identifiability: {err}")
    return ident


def load_plugin(path) -> list:
    """The user-written effects of a Python file: its ``EFFECTS`` (a dict or list of Effect classes
    or instances) if it defines one, else every class defined in it whose instances (made without
    arguments) implement the Effect protocol."""
    import importlib.util
    from pathlib import Path

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"effect plugin {path} does not exist; expected a Python file defining Effect classes")
    spec = importlib.util.spec_from_file_location(f"flexforce_plugin_{path.stem.replace('-', '_')}", path)
    # spec is None only for a file whose suffix is not a Python one
    module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    try:
        spec.loader.exec_module(module)  # type: ignore[union-attr]
    except Exception as err:  # a user's file: any error is a configuration error
        raise ConfigError(f"cannot load effect plugin {path}: {type(err).__name__}: {err}") from err
    declared = getattr(module, "EFFECTS", None)
    if declared is not None:
        return list(declared.values()) if isinstance(declared, dict) else list(declared)
    found = []
    for obj in vars(module).values():
        if isinstance(obj, type) and obj.__module__ == module.__name__:
            try:
                inst = obj()
            except TypeError:
                continue
            if _is_effect(inst):
                found.append(obj)
    if not found:
        raise ConfigError(f"effect plugin {path} defines no Effect (name, dim, labels, prior, random_walk_sigma, "
                          "residual_terms, report)")
    return found
