"""Screening: the score test of every candidate at a fit (no refit), the identifiability table
of the candidates, and the choice of the candidates a round refits."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from scipy import stats

from flexforce.compare.diagnostics.candidates import _constant_effect
from flexforce.compare.diagnostics.config import DEFAULT
from flexforce.compare.diagnostics.fitting import Fit
from flexforce.compare.diagnostics.progress import _takes_two
from flexforce.compare.diagnostics.text import _failure
from flexforce.errors import ConfigError

if TYPE_CHECKING:
    from flexforce.smoother.screening import Identifiability, ScoreTest


def screen(rec, fit: Fit, makers: dict[str, Callable[[], object]], window: float = DEFAULT.screen_window,
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
    from flexforce.smoother.evidence import states_cache
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
    # factor and inverses its test forms (evidence.states_cache) and the compiled kernels it
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

    # the candidates' shared states (jobs = 1: formed in this process), freed when the screening ends
    with states_cache():
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
    tests = {name: found[name] for name in makers}
    return (tests, table) if identify else tests


def identify_candidates(prob, fit: Fit, makers: dict[str, Callable[[], object]], window: float = DEFAULT.screen_window
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
