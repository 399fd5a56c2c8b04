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
   depends on it; docs/diagnostics.md, "Tuning", has the measurement).
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
import math
import time
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING

import numpy as np

from flexforce.compare.diagnostics.candidates import (
    _constant,
    _constant_effect,
    _is_effect,
    _plausibility,
    _score_understates,
    bound,
    effect_factory,
    inapplicable,
    left_out_by_default,
    load_plugin,
    registered_effects,
    resolve_candidates,
)
from flexforce.compare.diagnostics.checks import reference_check
from flexforce.compare.diagnostics.config import AUTO, DEFAULT, DiagnoseConfig
from flexforce.compare.diagnostics.constancy import constancy
from flexforce.compare.diagnostics.fitting import (
    Fit,
    LeavingPlausible,
    _criterion,
    calibrated_view,
    fit_model,
    score,
    snapshot,
)
from flexforce.compare.diagnostics.progress import _takes_two, progress_caller
from flexforce.compare.diagnostics.residuals import consistency, flag_windows, residual_rms
from flexforce.compare.diagnostics.results import Candidate, Diagnosis, Snapshot, _clean, _jsonable, headline_errors
from flexforce.compare.diagnostics.screening import _refit_choice, _strength, identify_candidates, screen
from flexforce.compare.diagnostics.selection import (
    Selection,
    _second_look,
    auto_added,
    mark_rivals,
    run_rounds,
    second_look,
    start_selection,
)
from flexforce.compare.diagnostics.session import Session
from flexforce.compare.diagnostics.text import CHECK_LABELS, _failure, finding, summarize_effect
from flexforce.compare.metrics import evaluate
from flexforce.errors import ConfigError, FlexforceError

if TYPE_CHECKING:
    from flexforce.datasets.recording import Recording
    from flexforce.factors.model import ModelConfig
    from flexforce.smoother.screening import Identifiability

# Names the tests and benchmarks import from here.
_check = reference_check
_snapshot = snapshot

__all__ = [
    "AUTO", "CHECK_LABELS", "Candidate",
    "DiagnoseConfig", "Diagnosis", "Fit", "LeavingPlausible", "Snapshot", "bound", "calibrated_view", "constancy",
    "diagnose", "effect_factory", "finding", "fit_model", "headline_errors", "identifiability", "identify_candidates",
    "inapplicable", "left_out_by_default", "load_plugin", "mark_rivals", "progress_caller", "registered_effects",
    "resolve_candidates", "score", "screen", "summarize_effect",
    "_check", "_clean", "_constant", "_constant_effect", "_criterion", "_failure", "_is_effect", "_jsonable",
    "_plausibility", "_refit_choice", "_score_understates", "_second_look", "_snapshot", "_strength", "_takes_two",
]


def diagnose(rec: Recording, model: ModelConfig | None = None, candidates: Iterable | None = None, add: Iterable = (),
             config: DiagnoseConfig | None = None, *, extra_candidates: Iterable = (),
             progress: Callable[[str, float], None] | None = None, **options) -> Diagnosis:
    """Fit the nominal model, rank the candidate effects, and refit with the ``add``-ed ones.

    Args:
        rec: the Recording.
        config: the :class:`~flexforce.compare.diagnostics.config.DiagnoseConfig` (its defaults if
            None); each of its fields can also be given as a keyword (``**options``), which
            overrides it (``rank``, ``max_effects``, ``alpha``, ``window``, ``skip``, ``ekf``,
            ``screen_level``, ``screen_window``, ``calibrated``, ``identify``, ``refit_best``,
            ``jobs``, ``check_constancy``, ...).
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
            recording (:func:`constancy`); halves that disagree beyond ``constancy_z`` sigma make
            it implausible (the round takes the next).  Costs two fits of half the recording per
            round that takes a constant effect.
        check_veto: before a round takes an effect, hold its fit against the truth or the
            reference sensors; one whose errors rise more than they fall over the round's base or
            the nominal model is turned down (the round takes the next), and ``add=["auto"]``
            adds the selection only as far as no error rises (:attr:`DiagnoseConfig.check_veto`).

    Raises:
        ConfigError: an unknown candidate, two candidates of one name, no candidate to rank, a
            bad ``screen_level``, ``refit_best`` or ``jobs``.
        TypeError: a keyword that is no field of DiagnoseConfig.
    """
    cfg = _config(config, options)
    rec.validate()
    if model is None:
        from flexforce.factors.model import ModelConfig

        model = ModelConfig.from_recording(rec)
    add = list(add or ())
    want_auto = AUTO in add
    add = [a for a in add if a != AUTO]
    cands, skipped, table_only, add_makers = _candidates(rec, model, candidates, extra_candidates, add, cfg.rank)
    s, nominal, noise = _nominal_session(rec, model, {**cands, **add_makers}, cfg, progress)
    if noise is not None:
        model = noise["model"]
        skipped = {**skipped, "noise": noise["text"]}
    s.resolve_jobs()  # "auto": decided with the nominal fit in memory (what a worker starts from)
    sel = start_selection(s, cands, table_only, nominal)

    def after_effects() -> list[str]:
        """The effects of the after fit: the selection (with ``add=["auto"]``), then those added."""
        return list(dict.fromkeys((sel.selected if want_auto else []) + list(add_makers)))

    if cfg.rank:
        run_rounds(s, sel)
    swaps = second_look(s, sel, after_effects)
    ranking = _ranking(sel)
    added = after_effects()
    if want_auto:
        # --add auto adds no selection whose check says it raises an error (selection.auto_added)
        auto, note = auto_added(s, list(sel.selected))
        added = list(dict.fromkeys(auto + list(add_makers)))
        if note:
            skipped = {**skipped, "auto": note}
    s.watching = False
    before, after = _views(s, added)
    ekf_snap = _ekf_snapshot(s) if cfg.ekf else None
    truth = getattr(rec, "truth", None)
    tests_sorted = sorted((v for v in sel.screened.values() if not isinstance(v, str)),
                          key=lambda t: (t.p_value, -t.statistic))
    from flexforce.compare.runner import describe

    return Diagnosis(describe(rec), ranking, sel.rounds, sel.selected, added, before, after, ekf_snap,
                     {**_criterion_record(cfg, nominal),
                      "noise_calibration": (None if noise is None else
                                            {"threshold_sigma": cfg.noise_calibration, "rms_sigma": noise["rms"],
                                             "scale": noise["scale"], "gyro_sigma": model.gyro_sigma,
                                             "accel_sigma": model.accel_sigma})},
                     None if truth is None else np.asarray(truth.external_wrench, dtype=float), tests_sorted,
                     sel.ident, sel.ident_error, list(skipped.values()), swaps, config=cfg)


def _nominal_session(rec: Recording, model: ModelConfig, makers: dict, cfg: DiagnoseConfig,
                     progress: Callable[[str, float], None] | None) -> tuple[Session, Fit, dict | None]:
    """The diagnosis session and its nominal fit, and :func:`calibrate_noise`'s record (None when
    the configured noise holds); with a calibrated noise, a new session on the calibrated model and
    its nominal fit."""
    from flexforce.compare.runner import check_jobs

    s = Session(rec, model, makers, cfg, progress)
    check_jobs(cfg.jobs)
    nominal = s.fitted(())
    noise = calibrate_noise(rec, model, nominal, cfg)
    if noise is not None:
        s.say("noise", noise["text"], s.t_start)
        s = Session(rec, noise["model"], makers, cfg, progress)
        nominal = s.fitted(())
    return s, nominal, noise


def calibrate_noise(rec: Recording, model: ModelConfig, nominal: Fit, cfg: DiagnoseConfig) -> dict | None:
    """The model with its IMU noise calibrated on the nominal fit's residuals
    (:attr:`DiagnoseConfig.noise_calibration`), or None when the configured noise holds.

    Returns ``{"model", "scale": {"gyro", "accel"}, "rms": {...}, "text"}``: a sensor whose
    whitened residuals have an RMS (over its three axes, from ``cfg.skip``) above the threshold
    gets its sigma multiplied by that RMS, the other keeps its own (scale 1)."""
    limit = cfg.noise_calibration
    res = nominal.estimate.residuals.get("imu")
    if limit is None or res is None or res.shape[1] != 6:
        return None
    from flexforce.smoother.problem import imu_residual_scale, scaled_imu_noise

    rms, scale = imu_residual_scale(res, rec.time, cfg.skip, limit)
    if all(v == 1.0 for v in scale.values()):
        return None
    cal = scaled_imu_noise(model, scale)
    parts = [f"{name} {model_sigma:.3g} -> {model_sigma * scale[name]:.3g} {unit} ({rms[name]:.1f}x)"
             for name, model_sigma, unit in (("gyro", model.gyro_sigma, "rad/s"),
                                             ("accel", model.accel_sigma, "m/s^2")) if scale[name] != 1.0]
    text = (f"noise: the nominal fit's IMU residuals are {rms['gyro']:.1f} sigma (gyrometer) and "
            f"{rms['accel']:.1f} sigma (accelerometer) RMS, above {limit:g}: the configured noise is far below "
            f"what the model leaves unexplained, so every candidate would pass; the diagnosis uses the noise the "
            f"residuals show (sigma per sample: {'; '.join(parts)}; noise_calibration=None keeps the configured one)")
    return {"model": cal, "scale": scale, "rms": rms, "text": text}


def _config(config: DiagnoseConfig | None, options: dict) -> DiagnoseConfig:
    """``config`` (the defaults if None) with the keyword ``options`` of :func:`diagnose` in place.

    Raises:
        TypeError: an option that is no field of :class:`DiagnoseConfig`.
    """
    names = {f.name for f in dataclasses.fields(DiagnoseConfig)}
    unknown = sorted(set(options) - names)
    if unknown:
        raise TypeError(f"diagnose() got an unexpected keyword argument '{unknown[0]}'; expected a field of "
                        f"DiagnoseConfig ({', '.join(sorted(names))})")
    base = DEFAULT if config is None else config
    return dataclasses.replace(base, **options) if options else base


def _candidates(rec, model, candidates, extra_candidates, add: list, rank: bool):
    """``(candidates, skipped, table_only, added)``: the candidates ranked and the effects added
    (name -> factory bound to ``rec``), the lines of those skipped (nothing to act on, or left out
    of the default catalogue), and those left out but kept for the identifiability table."""
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
    return cands, skipped, table_only, add_makers


def _ranking(sel: Selection) -> list[Candidate]:
    """Selected effects in selection order, then the last round's others by score, then the rows of
    those not refitted."""
    ranking: list[Candidate] = []
    for i, name in enumerate(sel.selected):
        ranking.append(next(c for c in sel.rounds[i] if c.effect == name))
    if sel.rounds:
        # a candidate screened out (or left unrefitted) at a later base is listed by that, its latest word
        later = {d.effect for d in sel.dropped if d.round > len(sel.rounds)}
        ranking += [c for c in sel.rounds[-1] if c.effect not in sel.selected and c.effect not in later]
    return ranking + sel.dropped


def _views(s: Session, added: list[str]) -> tuple[Snapshot, Snapshot | None]:
    """The before (nominal) and after (``added``) views, those not formed beside the last refits
    formed here in the session's processes."""
    from flexforce.compare.runner import fork_map

    shown = [()] + ([tuple(added)] if added else [])  # the before and after fits
    fits = [s.fitted(k) for k in shown]
    views: list[Snapshot | None] = [s.side.get(tuple(sorted(k))) for k in shown]
    left = [i for i, v in enumerate(views) if v is None]
    for i, ok, value, _ in fork_map(lambda k: s.snapshot(fits[k]), left, s.jobs):
        if not ok:
            raise value
        views[left[i]] = value
    before, after = views[0], (views[1] if added else None)
    assert before is not None
    return before, after


def _ekf_snapshot(s: Session) -> Snapshot | None:
    """The EKF on the nominal model, its innovations as residuals; None when it fails."""
    from flexforce.compare.ekf.filter import run_ekf

    cfg, rec = s.config, s.rec
    t0 = time.perf_counter()
    try:
        est = run_ekf(rec, s.model, progress=s.cb("ekf"))
    except FlexforceError:
        est = None
    s.say("ekf", "EKF on the nominal model" + (" failed" if est is None else ""), t0)
    if est is None:
        return None
    return Snapshot((), est, evaluate(est, rec, skip=cfg.skip), flag_windows(est, window=cfg.window, alpha=cfg.alpha),
                    consistency(est), residual_rms(est), float("nan"), 0)


def _criterion_record(cfg: DiagnoseConfig, nominal: Fit) -> dict:
    """The selection's criterion as diagnosis.json states it."""
    level = cfg.screen_level
    return {"name": "Laplace evidence + BIC for constants",
            "score": "2 (E_base - E) - nu_constant ln(n), E the negative log marginal likelihood",
            "alpha": cfg.alpha,
            "significant": ("score > 0 and p < alpha / m (constant unknowns: likelihood-ratio p against "
                            "chi-square(effective dof); per-step ones: p = 1 / Bayes factor); alpha: "
                            "family-wise level of each round (Holm: alpha / candidates in the round, m those "
                            "not selected yet)"),
            "tie": cfg.tie,
            "n_residuals": nominal.n_residuals, "penalty_per_dof": math.log(max(nominal.n_residuals, 2)),
            "fit": "flexforce.smoother.fit",
            "screen_level": level, "screen_window_s": cfg.screen_window if level is not None else None,
            "refit_best": cfg.refit_best if level is not None else None,
            "constancy": ({"z": cfg.constancy_z, "relative": cfg.constancy_rel, "min_half_s": cfg.constancy_min_s,
                           "rule": "a constant effect a round would take is fitted on each half of the recording; "
                                   "halves apart beyond z sigma and the relative fraction of its size on one "
                                   "component make it implausible"} if cfg.check_constancy else None),
            "screen": ("score (Lagrange-multiplier) test at the nominal fit, and again at each round's base once "
                       "an effect is selected: g^T S^-1 g against chi-square with the effect's effective dof; "
                       "only candidates with p < screen_level are refitted")
            if level is not None else "none: every candidate refitted"}


def identifiability(rec: Recording, candidates: Iterable | None = None, model: ModelConfig | None = None,
                    window: float = DEFAULT.screen_window,
                    progress: Callable[[float], None] | None = None) -> Identifiability:
    """Before any refit: fit the nominal model and say which candidates the recording sees and
    which pairs it cannot tell apart (:func:`flexforce.smoother.screening.identifiability`).

    Raises:
        ConfigError: the table cannot be formed (no trajectory, or no candidate to compare).
    """
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
