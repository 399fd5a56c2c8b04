"""The greedy forward selection: the screening at the nominal fit, the rounds (refit the strongest
candidates, take the best plausible, constant one if significant, rescreen the rest at the new
base), the rivals of a round's best, and the second look at the per-step effects taken early."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from flexforce.compare.diagnostics.candidates import _constant, _plausibility, _score_understates
from flexforce.compare.diagnostics.config import DEFAULT
from flexforce.compare.diagnostics.constancy import constancy
from flexforce.compare.diagnostics.fitting import Fit, _criterion, score
from flexforce.compare.diagnostics.results import Candidate
from flexforce.compare.diagnostics.screening import _refit_choice, _strength, identify_candidates, screen
from flexforce.compare.diagnostics.text import _failure, check_changes, finding, summarize_effect

if TYPE_CHECKING:
    from flexforce.compare.diagnostics.session import Session
    from flexforce.smoother.screening import Identifiability, ScoreTest


@dataclass
class Selection:
    """The selection's state, from the screening at the nominal fit to its last round."""

    cands: dict[str, Callable[[], object]]
    """The candidates ranked (name -> factory)."""
    table_only: dict[str, Callable[[], object]] = field(default_factory=dict)
    """Candidates in the identifiability table only (left out of the default catalogue)."""
    prob: object = None
    """The nominal fit's Problem (None without candidates or a trajectory)."""
    understated: list[str] = field(default_factory=list)
    """Candidates whose score test understates them: refitted whatever their test."""
    screened: dict[str, ScoreTest | str] = field(default_factory=dict)
    """Each candidate's score test at the nominal fit, or why it failed."""
    latest: dict[str, ScoreTest | str] = field(default_factory=dict)
    """Each candidate's latest score test (at the latest round's base)."""
    ident: Identifiability | None = None
    ident_error: str | None = None
    remaining: list[str] = field(default_factory=list)
    """Candidates not selected, dropped or set aside yet, in the order they are refitted."""
    rounds: list[list[Candidate]] = field(default_factory=list)
    selected: list[str] = field(default_factory=list)
    dropped: list[Candidate] = field(default_factory=list)
    """Rows of the candidates not refitted (screened out, or waiting), in the order they were."""
    last_keys: set[tuple[str, ...]] = field(default_factory=set)
    """The fits of the previous round (kept one round more, for the second look)."""

    def waited(self, k: str, round_: int, why: str, level: float | None) -> None:
        """A candidate that passed the screening but was not refitted: listed with why."""
        t = self.latest.get(k)
        self.dropped.append(Candidate(k, tuple(self.selected), round_, None, None, None, None, False,
                                      screen=None if isinstance(t, str) else t, refitted=False,
                                      screen_level=level, deferred=why))


def mark_rivals(row: list[Candidate], tie: float = DEFAULT.tie, ident=None) -> None:
    """Give the best of a sorted round its rivals: significant candidates within ``tie`` of its
    score, and, with the identifiability table ``ident``, those it calls inseparable from the best
    whose evidence (``lr``, before the unknowns' charge) is within ``tie`` of the best's, both
    charged for constant unknowns: the data fit both equally, and only the count of unknowns
    decides."""
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


# ----------------------------------------------------------------------------------------------
# The screening at the nominal fit
# ----------------------------------------------------------------------------------------------


def start_selection(s: Session, cands: dict[str, Callable[[], object]], table_only: dict[str, Callable[[], object]],
                    nominal: Fit) -> Selection:
    """The selection before its first round: the score tests at the nominal fit, the
    identifiability table, the candidates to refit and those screened out."""
    cfg = s.config
    sel = Selection(cands, table_only)
    if cfg.rank and cands and nominal.trajectory is not None and nominal.model is not None:
        from flexforce.smoother import NoiseRule, Problem

        sel.prob = Problem.build(s.rec, nominal.model, NoiseRule())
    if not cfg.rank:
        return sel
    sel.remaining = list(cands)
    sel.understated = [k for k in cands if _score_understates(cands[k])]
    early: tuple | None = None
    t0 = time.perf_counter()
    if cfg.screen_level is not None and cands:
        t0 = time.perf_counter()
        if s.jobs > 1 and cfg.identify and sel.prob is not None:
            # the table beside the score tests, on every candidate (the longest task first); formed
            # again below only if a test failed (the table leaves out the failed ones)
            sel.screened, early = screen(s.rec, nominal, cands, cfg.screen_window, progress=s.cb_message("screening"),
                                         problem=sel.prob, jobs=s.jobs, identify=True, table_only=table_only)
        else:
            sel.screened = screen(s.rec, nominal, cands, cfg.screen_window, progress=s.cb_message("screening"),
                                  problem=sel.prob, jobs=s.jobs)
    if cfg.identify and cands and sel.prob is not None:
        _identify(s, sel, nominal, early, t0)
    if cfg.screen_level is not None and sel.screened:
        _screen_out(sel, cfg.screen_level)
    sel.latest = dict(sel.screened)
    return sel


def _identify(s: Session, sel: Selection, nominal: Fit, early: tuple | None, t0: float) -> None:
    """The identifiability table at the nominal fit: the one formed beside the score tests, or
    formed here without the candidates whose test failed."""
    if early is None or any(isinstance(v, str) for v in sel.screened.values()):
        t0 = time.perf_counter()
        ok = {k: v for k, v in sel.cands.items() if not isinstance(sel.screened.get(k), str)}
        sel.ident, sel.ident_error = identify_candidates(sel.prob, nominal, {**ok, **sel.table_only},
                                                         s.config.screen_window)
    else:
        sel.ident, sel.ident_error = early
    if sel.ident is not None:
        msg = (f"identifiability: {len(sel.ident.inseparable())} pairs cannot be told apart, "
               f"{len(sel.ident.not_seen())} candidates not fully seen")
    else:
        msg = f"identifiability: not computed ({sel.ident_error})"
    s.say("identifiability", msg, t0)


def _screen_out(sel: Selection, level: float) -> None:
    """The candidates to refit after the screening at the nominal fit, and the rows of those it drops."""
    tests = {k: v for k, v in sel.screened.items() if not isinstance(v, str)}
    ident = sel.ident
    for k, v in sel.screened.items():  # a failed test: the reason in the recording's terms
        if isinstance(v, str) and ident is not None and k in ident.candidates and not ident.candidates[k].seen:
            sel.screened[k] = ident.candidates[k].unexcited()
    order = sorted(tests, key=lambda k: (tests[k].p_value, -tests[k].statistic))
    # a failed test is refitted (the refit decides); passing ones first, most significant
    # first; an effect whose test understates it (a delay) is refitted whatever its test
    sel.remaining = [k for k in order if tests[k].p_value < level or k in sel.understated] + \
        [k for k, v in sel.screened.items() if isinstance(v, str)]
    for k in order:
        if tests[k].p_value >= level and k not in sel.understated:
            sel.dropped.append(Candidate(k, (), 1, None, None, None, None, False, screen=tests[k], refitted=False,
                                         screen_level=level))


# ----------------------------------------------------------------------------------------------
# The rounds
# ----------------------------------------------------------------------------------------------


def run_rounds(s: Session, sel: Selection) -> None:
    """The greedy selection's rounds, until none is significant, ``max_effects`` are selected or no
    candidate is left (into ``sel``)."""
    cfg = s.config
    while sel.remaining:
        # a candidate whose refit came out implausible in the previous round is neither screened
        # nor refitted again (its estimate stood in for something the effect just selected
        # explains better): listed with that refit's word.  One its check turned down stays: at
        # the new base (the effect it was soaking up now in the model) it may be what is missing
        for c in (sel.rounds[-1] if sel.rounds else []):
            if c.implausible and not c.vetoed and c.effect in sel.remaining:
                sel.remaining.remove(c.effect)
                sel.waited(c.effect, len(sel.rounds) + 1, f"its refit in round {c.round} was "
                           + ("turned down by its check (" if c.vetoed else "implausible (")
                           + (f"score {c.score:.1f}: " if c.score is not None else "")
                           + f"{c.implausible})", cfg.screen_level)
        if not sel.remaining:
            break
        base = s.fitted(tuple(sel.selected))
        if _rescreen(s, sel, base):
            break
        round_base = tuple(sel.selected)
        row, best, this_round = _refit_round(s, sel, base)
        sel.rounds.append(row)
        # the best's rivals among the plausible ones (those the data do not tell from it)
        mark_rivals([c for c in row if not c.implausible], cfg.tie, ident=sel.ident)
        stop = best is None or not best.significant or len(sel.selected) >= cfg.max_effects
        if not stop:
            assert best is not None
            _take(s, sel, row, best, base, round_base)
        # the fits of the rounds before the previous one are done with (their rows keep what
        # they found): free their estimates, so that memory does not grow with the number of
        # candidates.  The previous round's are kept: the second look fits the selection without
        # a per-step effect taken before the last round, which is one of them when the last
        # round is this one
        this_keys = {tuple(sorted(round_base + (n,))) for n in this_round}
        keep = {(), tuple(sorted(sel.selected))} | this_keys | sel.last_keys
        for key in [k for k in s.cache if k not in keep]:
            del s.cache[key]
        sel.last_keys = this_keys
        if stop:
            # those that passed the screening but waited behind stronger ones
            for k in sel.remaining:
                if k not in this_round:
                    sel.waited(k, len(sel.rounds), f"its score test passed, but the round refitted the "
                                                   f"{cfg.refit_best} strongest (refit_best) and stopped",
                               cfg.screen_level)
            break


def _rescreen(s: Session, sel: Selection, base: Fit) -> bool:
    """Screen the remaining candidates again at the new ``base`` (after a selection): an effect
    that only stood in for the one just selected stops passing, and is not refitted.  True when
    the selection ends here (none left, or ``max_effects`` selected)."""
    cfg = s.config
    level = cfg.screen_level
    if not (sel.selected and level is not None and base.trajectory is not None and base.model is not None):
        return False
    from flexforce.smoother import NoiseRule, Problem

    again = screen(s.rec, base, {k: s.makers[k] for k in sel.remaining}, cfg.screen_window,
                   progress=s.cb_message("screening at + " + " + ".join(sel.selected)),
                   problem=Problem.build(s.rec, base.model, NoiseRule()), jobs=s.jobs)
    for k, v in again.items():
        if not isinstance(v, str) and v.p_value >= level and k not in sel.understated:
            sel.remaining.remove(k)
            sel.dropped.append(Candidate(k, tuple(sel.selected), len(sel.rounds) + 1, None, None, None, None, False,
                                         screen=v, refitted=False, screen_level=level))
    if not sel.remaining:
        return True
    sel.latest.update(again)
    if len(sel.selected) >= cfg.max_effects:
        # the selection is full: what is left is reported by its score test at the final
        # base, not refitted for a round whose choice would not be taken
        for k in sel.remaining:
            sel.waited(k, len(sel.rounds) + 1, f"its score test passed at the final base, but {cfg.max_effects} "
                                               "effects (max_effects) are selected", level)
        return True
    return False


def _refit_round(s: Session, sel: Selection, base: Fit) -> tuple[list[Candidate], Candidate | None, list[str]]:
    """One round's refits: ``(row sorted by score, its best plausible candidate or None, the
    candidates refitted)``.  Holm: the round's tests at ``alpha / m``, ``m`` every candidate not
    selected yet (those the screening dropped were tested too)."""
    cfg = s.config
    m = len(sel.cands) - len(sel.selected)
    row: list[Candidate] = []
    this_round: list[str] = []
    best = None
    while True:
        # the strongest that wait (refit_best); when every one refitted is turned down
        # (implausible, not constant), the round refits those that waited behind them
        batch = _refit_choice([k for k in sel.remaining if k not in this_round], sel.latest, sel.ident,
                              cfg.refit_best if cfg.screen_level is not None else None, sel.understated)
        if not batch:
            break
        this_round += batch
        s.fit_all([tuple(sel.selected) + (name,) for name in batch])
        for name in batch:
            row.append(_refit_row(s, sel, base, name, m))
        row.sort(key=lambda c: -math.inf if c.score is None else c.score, reverse=True)
        best = _best_plausible(s, sel, row, base)
        if best is not None or not any(c.implausible for c in row) or any(c.dominant for c in row):
            break
    return row, best, this_round


def _refit_row(s: Session, sel: Selection, base: Fit, name: str, m: int) -> Candidate:
    """The row of candidate ``name`` refitted on the round's ``base`` and scored at ``alpha / m``."""
    cfg = s.config
    selected = sel.selected
    t0 = time.perf_counter() - s.fit_seconds.pop(tuple(sorted(tuple(selected) + (name,))), 0.0)
    label = "+ " + " + ".join(tuple(selected) + (name,))
    try:
        f = s.fitted(tuple(selected) + (name,))
    except Exception as err:  # a user's effect may raise anything: one line, the others go on
        reason, detail = _failure(name, err, sel.ident)
        s.say(label, f"{name}: cannot be fitted: {reason}", t0)
        return Candidate(name, tuple(selected), len(sel.rounds) + 1, None, None, None, None, False,
                         error=reason, error_detail=detail, finding=f"cannot be fitted: {reason}")
    sc, lr, nu, p, sig = score(base, f, name, cfg.alpha, tests=m)
    rep = f.estimate.effects.get(name, {})
    test = sel.latest.get(name)  # its score test at this round's base (the nominal fit's in round 1)
    eff = s.makers[name]()
    c = Candidate(name, tuple(selected), len(sel.rounds) + 1, sc, lr, nu, p, sig, rep,
                  summarize_effect(rep, eff), screen=None if isinstance(test, str) else test,
                  screen_level=cfg.screen_level, level=cfg.alpha / m)
    c.implausible = _plausibility(eff, rep, sel.prob) if sig or f.stopped else None
    if f.stopped:  # the refit ended with the estimate leaving the plausible range
        c.implausible = f"{c.implausible or 'its estimate left the plausible range'}; {f.stopped}"
    if c.implausible:
        c.significant = False
    c.finding = finding(c, rep, eff)
    s.say(label, f"{name}: score {sc:.1f}, {c.status}", t0)
    return c


def _best_plausible(s: Session, sel: Selection, row: list[Candidate], base: Fit) -> Candidate | None:
    """The best plausible candidate of a sorted row (an implausible one is no finding, whatever its
    score); a constant one the selection would take must be the same on both halves of the
    recording (:func:`~flexforce.compare.diagnostics.constancy.constancy`), else it is implausible."""
    cfg = s.config
    selected = sel.selected
    leader = None  # the highest-scoring candidate fitted to implausible values
    for c in row:
        if c.implausible:
            if leader is None and not c.vetoed and not c.inconstant and c.score is not None:
                leader = c
            continue
        if cfg.check_constancy and c.significant and len(selected) < cfg.max_effects and sel.prob is not None \
                and c.constancy is None and _constant(s.makers[c.effect](), sel.prob):
            t0 = time.perf_counter()
            row_fit = s.cache.get(tuple(sorted(tuple(selected) + (c.effect,))), base)
            c.constancy = constancy(s.rec, s.model, s.makers, tuple(selected), c.effect, s.jobs, start=row_fit,
                                    config=cfg)
            s.say(f"constancy of {c.effect}", f"{c.effect}: {c.constancy['text']}", t0)
            if c.constancy.get("made") and not c.constancy["constant"]:
                c.implausible = c.constancy["text"]
                c.significant = False
                c.finding = finding(c, c.parameters, s.makers[c.effect]())
                continue
        if cfg.check_veto and c.significant and len(selected) < cfg.max_effects:
            t0 = time.perf_counter()
            veto = _vetoed(s, c, base)
            if veto:
                c.implausible, c.vetoed = veto, True
                c.significant = False
                c.finding = finding(c, c.parameters, s.makers[c.effect]())
                s.say(f"check of {c.effect}", f"{c.effect}: turned down, {veto}", t0)
                continue
        if _dominated(cfg, leader, c):
            assert leader is not None
            leader.dominant = True
            leader.finding = finding(leader, leader.parameters, s.makers[leader.effect]())
            s.say(f"dominance of {leader.effect}", f"{leader.effect}: implausible, yet scores {leader.score:.1f} "
                  f"against {c.effect}'s {c.score:.1f}: nothing is taken in its place", time.perf_counter())
            return None
        return c
    return None


def _dominated(cfg, leader: Candidate | None, c: Candidate) -> bool:
    """Whether the implausible ``leader`` outscores the plausible ``c`` by the config's
    ``dominance`` ratio and more than its ``tie``."""
    if cfg.dominance is None or leader is None or leader.score is None or c.score is None:
        return False
    return leader.score > cfg.dominance * max(c.score, 0.0) and leader.score - c.score > cfg.tie


def _vetoed(s: Session, c: Candidate, base: Fit) -> str | None:
    """Why the check turns ``c`` down (:attr:`DiagnoseConfig.check_veto`), or None.

    Against the round's base, and the nominal model: the errors against the truth or the
    references that rise (beyond ``check_worse`` and their :data:`CHECK_FLOORS`) outweigh those
    that fall, the sum of ``ln(after / before)`` over both above 0 -- a push fitted before the CoM
    offset it also soaks up raises the force error threefold while it cuts the CoP, tilt and hand
    errors tenfold: taken; an effect that raises the force error and lowers nothing: turned down.
    Sets :attr:`Candidate.check` (against the base)."""
    from flexforce.compare.diagnostics.text import CHECK_LABELS, _check_items, _check_keys, _check_reference

    worse = s.config.check_worse
    fit = s.cache.get(tuple(sorted(tuple(c.base) + (c.effect,))))
    if fit is None:
        return None
    checks = [("its base" if c.base else "the nominal model", s.check(base, fit))]
    if c.base:
        checks.append(("the nominal model", s.check(s.fitted(()), fit)))
    c.check = checks[0][1]
    for against, chk in checks:
        if not chk:
            continue
        rises, falls = check_changes(chk, worse)
        if not rises or sum(v for _, v in rises) + sum(v for _, v in falls) <= 0.0:
            continue
        up = {k for k, _ in rises}
        items = [text for key, (_, _, _, text) in zip(_check_keys(chk), _check_items(chk)) if key in up]
        lower = [CHECK_LABELS.get(k, (k,))[0] for k, _ in falls]
        return (f"its check against {_check_reference(chk)} disagrees: {', '.join(items)} (more than {worse:.0%} "
                f"above {against}" + (f", more than the {', '.join(lower)} error{'s' if len(lower) > 1 else ''} "
                                      "fall" if lower else "") + ")")
    return None


def auto_added(s: Session, selected: list[str]) -> tuple[list[str], str | None]:
    """What ``add=["auto"]`` adds of the ``selected`` effects (in selection order): the longest
    first part of them whose fit raises no error against the truth or the references beyond
    ``check_worse`` and its :data:`CHECK_FLOORS` over the nominal model, with the sentence saying
    what was left out and why (None when all are added, or nothing is checked)."""
    if not (s.config.check_veto and selected):
        return list(selected), None
    nominal = s.fitted(())
    whole = s.check(nominal, s.fitted(tuple(selected)))
    if whole is None or not check_changes(whole, s.config.check_worse)[0]:
        return list(selected), None
    n = len(selected) - 1
    while n > 0:
        chk = s.check(nominal, s.fitted(tuple(selected[:n])))
        if chk is None:  # nothing to check against after all
            return list(selected), None
        if not check_changes(chk, s.config.check_worse)[0]:
            break
        n -= 1
    from flexforce.compare.diagnostics.text import _check_after, _check_reference

    left = selected[n:]
    return list(selected[:n]), (f"auto: {', '.join(left)} not added: with {'them' if len(left) > 1 else 'it'} an "
                                f"error against {_check_reference(whole)} rises by more than "
                                f"{s.config.check_worse:.0%} over the nominal model {_check_after(whole)}")


def _take(s: Session, sel: Selection, row: list[Candidate], best: Candidate, base: Fit,
          round_base: tuple[str, ...]) -> None:
    """Select the round's ``best``; check it, and the candidates that may stand for it (rivals, the
    table's inseparable ones, refitted in this round), against the same references
    (:meth:`Diagnosis.partner_checks`)."""
    sel.selected.append(best.effect)
    sel.remaining.remove(best.effect)
    best.check = s.check(base, s.fitted(tuple(sel.selected)))
    for c in row:
        if c is best or c.implausible or not c.significant or c.score is None:
            continue
        pair = sel.ident.pair(best.effect, c.effect) if sel.ident is not None else None
        if c.effect in best.rivals or (pair is not None and pair.inseparable):
            key = tuple(sorted(round_base + (c.effect,)))
            if key in s.cache:
                c.check = s.check(base, s.cache[key])
                c.partner_of = best.effect


# ----------------------------------------------------------------------------------------------
# The second look
# ----------------------------------------------------------------------------------------------


def second_look(s: Session, sel: Selection, after: Callable[[], list[str]]) -> list[str]:
    """:func:`_second_look` of the selection (two effects or more), with the score tests at the
    selection without the effect replaced, and the after view (``after()``'s effects) formed beside
    the trials.  Returns one sentence per replacement."""
    cfg = s.config
    if not cfg.rank or len(sel.selected) < 2:
        return []

    def strongest(without: tuple[str, ...], names: list[str]) -> list[str] | None:
        """``names`` whose score test passes at the fit of ``without``, strongest first (None
        when the test cannot be formed)."""
        base_fit = s.fitted(without)
        if cfg.screen_level is None or base_fit.trajectory is None or base_fit.model is None or not names:
            return None
        got = screen(s.rec, base_fit, {k: s.makers[k] for k in names}, cfg.screen_window,
                     progress=s.cb_message("second look: screening at + " + " + ".join(without)), jobs=s.jobs)
        ok = {k: v for k, v in got.items() if not isinstance(v, str) and v.p_value < cfg.screen_level}
        return sorted(ok, key=lambda k: _strength(ok[k]))

    def fit_trials(trials: list[tuple[str, ...]]) -> None:
        # the view of the selection as it stands is formed beside the trials (used unless one replaces it)
        s.fit_all(trials, views=[tuple(after())])

    return _second_look(sel.selected, sel.rounds, s.makers, s.fitted, fit_trials, sel.prob, s.say, strongest,
                        check=s.check, n_alternatives=cfg.swap_alternatives)


def _second_look(selected: list[str], rounds: list[list[Candidate]], makers: dict, fitted, fit_all, prob,
                 say, strongest=None, check=None, n_alternatives: int = DEFAULT.swap_alternatives) -> list[str]:
    """Replace, in ``selected`` (in place), a per-step effect the greedy selection took before its
    last round by a constant candidate, when the whole selection with the replacement has the
    better criterion (:func:`~flexforce.compare.diagnostics.fitting._criterion`) and the
    replacement's estimate is plausible.

    A random-walk wrench can absorb part of every constant effect, so it can win a round against
    each of them alone and still lose, as a model, once the later rounds' effects are in
    (docs/diagnostics.md, "Tuning").  Tried: for each such effect, the
    ``n_alternatives`` (:attr:`DiagnoseConfig.swap_alternatives`) constant candidates whose score
    tests are strongest at the fit of the rest of the selection (``strongest(without, names)``),
    or, without the test, the round's strongest significant, plausible refits; one found
    implausible at its last refit is not tried again.  ``fitted(names)``, ``fit_all(trials)``:
    the session's fits; ``check(base, fit)``: the reference check of a replacement's row.
    Returns one sentence per replacement."""
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
        alternatives = [a for a in alternatives[:n_alternatives] if a not in gone]
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
