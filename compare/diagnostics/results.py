"""The diagnosis's typed results: a candidate's row (:class:`Candidate`), a fitted model seen
through the diagnostics (:class:`Snapshot`) and the whole :class:`Diagnosis`; data only, their
sentences rendered by :mod:`.text`, their JSON by ``to_dict``/``to_json``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from flexforce.compare.diagnostics import text
from flexforce.compare.diagnostics.config import DEFAULT, DiagnoseConfig
from flexforce.compare.diagnostics.residuals import FlaggedWindow
from flexforce.compare.metrics import RMSE_KEYS, Metrics

if TYPE_CHECKING:
    from flexforce.datasets.estimate import Estimate
    from flexforce.smoother.screening import Identifiability, ScoreTest


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
    """For the best of a round: the other significant candidates within :attr:`DiagnoseConfig.tie` of its score,
    which the data do not tell apart from it."""
    screen: ScoreTest | None = None
    """Its score test (:mod:`flexforce.smoother.screening`), when screened: at the nominal fit, or, for
    a candidate dropped in a later round, at that round's base (:attr:`base`)."""
    refitted: bool = True
    """False when the score test did not pass: no refit, no evidence (``score`` is None)."""
    implausible: str | None = None
    """Why the estimate is physically implausible (the effect's ``plausible``): then it is not
    ``significant`` whatever its score -- the effect stands in for something else."""
    dominant: bool = False
    """Implausible, yet scored far above every plausible candidate of its round
    (:attr:`~flexforce.compare.diagnostics.config.DiagnoseConfig.dominance`): the round took
    nothing in its place."""
    finding: str = ""
    """The row's one sentence: for a significant effect its size, the evidence and when it acts;
    an implausible one says so; one that cannot be fitted, why in the recording's terms."""
    check: dict | None = None
    """For an effect the selection took, and for the candidates of its round the data do not tell
    from it (:meth:`Diagnosis.partner_checks`): the errors of its base (:attr:`base`) and of the base
    with it against what the fit did not use -- the truth of a simulated recording, or the
    reference sensors of a real one (the F/T readings when not fused, the motion capture):
    ``{"against": "truth" | "sensors", "before": {key: rmse}, "after": {key: rmse}}``
    (:attr:`DiagnoseConfig.check_worse`, :meth:`check_text`)."""

    def check_text(self, check_worse: float = DEFAULT.check_worse) -> str:
        """:func:`.text.check_text`: what the check says of the effect ("" without one)."""
        return text.check_text(self, check_worse)

    @property
    def inconstant(self) -> bool:
        """Its constancy check was made and found its halves apart (:attr:`constancy`)."""
        return bool(self.constancy and self.constancy.get("made") and not self.constancy.get("constant"))

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
        """:func:`.text.screen_text`: ``score T = 322.5 (nu 3.0), p = 1.3e-69``."""
        return text.screen_text(self, level)

    def to_dict(self, check_worse: float = DEFAULT.check_worse) -> dict:
        """The JSON of the row (``diagnosis.json``'s ``ranking`` and ``rounds``)."""
        return {"effect": self.effect, "score": _clean(self.score), "significant": bool(self.significant),
                "parameters": _jsonable(self.parameters), "summary": self.summary, "round": self.round,
                "base": list(self.base), "likelihood_ratio": _clean(self.lr),
                "effective_dof": _clean(self.effective_dof), "p_value": _clean(self.p_value),
                "level": _clean(self.level),
                "indistinguishable_from": list(self.rivals), "refitted": bool(self.refitted),
                "status": self.status, "finding": self.finding or self.summary,
                **({"implausible": self.implausible} if self.implausible else {}),
                **({"dominant": True} if self.dominant else {}),
                **({"turned_down_by_check": True} if self.vetoed else {}),
                **({"screen": self.screen.to_dict(self.screen_level)} if self.screen is not None else {}),
                **({"not_refitted": f"not refitted: {self.deferred}" if self.deferred else
                    f"not refitted: score p = {self.screen.p_value:.2g}"}
                   if not self.refitted and self.screen is not None else {}),
                **({"error": self.error} if self.error else {}),
                **({"error_detail": self.error_detail} if self.error_detail else {}),
                **({"check": {**_jsonable(self.check), "text": self.check_text(check_worse)}} if self.check else {}),
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
    """The effect its round selected, for which it may stand (a rival within :attr:`DiagnoseConfig.tie`, or a
    pair the identifiability table calls inseparable): its :attr:`check` is then held beside that one's
    (:meth:`Diagnosis.partner_checks`)."""
    level: float | None = None
    """Level its likelihood-ratio p-value was tested at: ``alpha / m``, ``m`` the candidates in its
    round (Holm: :func:`score`); None when not scored (not refitted, or the fit failed)."""
    vetoed: bool = False
    """True when :attr:`implausible` is its check's word (:attr:`DiagnoseConfig.check_veto`): the fit
    with it raised an error against the truth or the references."""
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

    def to_dict(self, alpha: float = DEFAULT.alpha) -> dict:
        """The JSON of the view; ``alpha``: the level of the inconsistent axes listed."""
        return {"effects": list(self.effects), "residual_rms": _jsonable(self.residual_rms), "rmse": self.rmse,
                "cost_data": _clean(self.cost_data), "n_residuals": self.n_residuals,
                "flagged_windows": [_jsonable(f.to_dict()) for f in self.flags],
                "inconsistent_axes": [_jsonable(c.to_dict()) for c in self.consistency
                                      if c.chi2_p < alpha or c.ljung_box_p < alpha],
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
    config: DiagnoseConfig = DEFAULT
    """The configuration it was made with (its thresholds appear in the sentences)."""

    def identifiability_notes(self) -> list[str]:
        """:func:`.text.identifiability_notes`: one sentence per pair that cannot be told apart."""
        return text.identifiability_notes(self)

    def to_json(self) -> dict:
        """``diagnosis.json``."""
        worse, alpha = self.config.check_worse, self.config.alpha
        out = {"verdict": self.verdict(), "added_values": self.added_values(),
               "recording": _jsonable(self.recording), "criterion": self.criterion,
               "ranking": [c.to_dict(worse) for c in self.ranking],
               "rounds": [[c.to_dict(worse) for c in r] for r in self.rounds],
               "selected": list(self.selected), "added": list(self.added),
               "ambiguities": self.ambiguities(), "partner_checks": self.partner_checks(),
               "inconstant": self.inconstant(),
               "screening": [s.to_dict(self.criterion.get("screen_level")) for s in self.screening],
               "identifiability": ({**self.identifiability.to_dict(), "notes": self.identifiability_notes()}
                                   if self.identifiability is not None else
                                   ({"error": self.identifiability_error} if self.identifiability_error else None)),
               "before": self.before.to_dict(alpha), "after": self.after.to_dict(alpha) if self.after else None,
               "skipped": list(self.skipped), "swaps": list(self.swaps)}
        if self.ekf is not None:
            m = self.ekf.metrics
            out["ekf"] = {"nis": _clean(m.nis), "nis_bounds": list(m.nis_bounds) if m.nis_bounds else None,
                          "flagged_windows": [_jsonable(f.to_dict()) for f in self.ekf.flags],
                          "rmse": self.ekf.rmse}
        return out

    def verdict(self) -> str:
        """:func:`.text.verdict`: the diagnosis in plain words (the report's and the terminal's first lines)."""
        return text.verdict(self)

    def added_values(self) -> list[str]:
        """One line per added effect: its fitted values in the report's units (``com-offset: CoM
        offset x = 22.0 ± 2.1 mm``); empty without an after view."""
        if self.after is None:
            return []
        reps = self.after.estimate.effects or {}
        return [f"{n}: {text.effect_values(n, reps.get(n, {})) or 'no estimate reported'}" for n in self.added]

    def identifiability_items(self) -> list[str]:
        """:func:`.text.identifiability_items`: the candidates not fully seen, then the pairs not told apart."""
        return text.identifiability_items(self)

    def ranking_table(self) -> str:
        """:func:`.text.ranking_table`: the plain-text ranking (what the CLI prints)."""
        return text.ranking_table(self)

    def partner_checks(self) -> list[str]:
        """:func:`.text.partner_checks`: what the references say of each choice and its partners."""
        return text.partner_checks(self)

    def inconstant(self) -> list[str]:
        """:func:`.text.inconstant`: one sentence per round the constancy check turned one down in."""
        return text.inconstant(self)

    def ambiguities(self) -> list[str]:
        """:func:`.text.ambiguities`: one sentence per round whose best the data cannot tell from another."""
        return text.ambiguities(self)


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
