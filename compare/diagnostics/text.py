"""The diagnosis in words: the sentences of its rows, checks, rounds and table, rendered from the
typed results (:mod:`.results`), which hold only data."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from flexforce.compare.diagnostics.config import CHECK_FLOORS, DEFAULT, DiagnoseConfig
from flexforce.errors import FlexforceError
from flexforce.factors.effects import EFFECTS
from flexforce.factors.effects.base import traits

if TYPE_CHECKING:
    from flexforce.compare.diagnostics.results import Candidate, Diagnosis
    from flexforce.smoother.screening import Identifiability


CHECK_LABELS = {"force_N": ("force", 1.0, " N"), "moment_Nm": ("moment", 1.0, " N m"), "cop_m": ("CoP", 1e3, " mm"),
                "rotation_rad": ("tilt", 1e3, " mrad"), "translation_m": ("position", 1e3, " mm"),
                "hand_m": ("hand", 1e3, " mm"), "vertical_force_N": ("vertical force", 1.0, " N"),
                "contact_force_N": ("contact force", 1.0, " N"), "contact_moment_Nm": ("contact moment", 1.0, " N m"),
                "contact_cop_m": ("sole CoP", 1e3, " mm")}
"""How :meth:`Candidate.check_text` names and scales each error: the diagnosis's units (:data:`UNITS`)."""

DISPLAY_UNITS = {"m": ("mm", 1e3), "rad": ("mrad", 1e3)}
"""SI unit of an effect's value -> the unit the diagnosis's sentences show it in, and the factor:
one system with :data:`CHECK_LABELS` (:data:`UNITS`)."""

UNITS = ("Units: forces N, moments N m, lengths mm (CoP, positions, hands, offsets), rotations and tilt mrad, "
         "time s (those of the comparison's report).")
"""The diagnosis report's units, stated on its page."""

ADVICE = ("resynchronise", "check the", "recalibrate", "re-measure")
"""How the clauses of an effect's implausibility text that advise an action begin: advice for an
effect that was found, dropped when the effect is turned down (:func:`without_advice`)."""


def _scored(c: Candidate) -> str:
    """``name (score S)``, with ``, implausible`` when its estimate is."""
    return f"{c.effect} (score {c.score:.1f}{', implausible' if c.implausible else ''})"


def _check_items(check: dict) -> list[tuple[str, float, float, str]]:
    """``(label, before, after, "tilt 10.6 -> 5.2 mrad")`` of each error a :attr:`Candidate.check`
    holds both numbers of, in its order (:data:`CHECK_LABELS`)."""
    out = []
    for key, b in check["before"].items():
        a = check["after"].get(key)
        if b is None or a is None:
            continue
        label, scale, unit = CHECK_LABELS.get(key, (key, 1.0, ""))
        out.append((label, b, a, f"{label} {b * scale:.3g} -> {a * scale:.3g}{unit}"))
    return out


def _check_keys(check: dict) -> list[str]:
    """The error keys of :func:`_check_items`' items, in the same order."""
    return [key for key, b in check["before"].items() if b is not None and check["after"].get(key) is not None]


def _check_reference(check: dict) -> str:
    """What a check holds the fit against: ``the truth``, ``the F/T and motion capture``, ..."""
    if check["against"] == "truth":
        return "the truth"
    return f"the {' and '.join(check['sensors'])}" if check.get("sensors") else "the reference sensors"


def _check_after(check: dict) -> str:
    """``(tilt 10.6 -> 5.2 mrad, vertical force 36.3 -> 35 N)`` of a :attr:`Candidate.check`."""
    return "(" + ", ".join(text for _, _, _, text in _check_items(check)) + ")"


def _check_preference(chosen: dict, partner: dict,
                      check_worse: float = DEFAULT.check_worse) -> str | None:
    """Which of two checks of one base the errors favour: ``"partner"`` when the partner's are lower
    by more than ``check_worse`` (:attr:`DiagnoseConfig.check_worse`) on some error and higher by
    no more than it on any, ``"chosen"`` the other way round, ``"split"`` when each wins one, None
    when they are alike."""
    lower = higher = False
    for key, a in chosen["after"].items():
        b = partner["after"].get(key)
        if a is None or b is None:
            continue
        if b < (1.0 - check_worse) * a:
            lower = True
        elif b > (1.0 + check_worse) * a:
            higher = True
    if lower and not higher:
        return "partner"
    if higher and not lower:
        return "chosen"
    return "split" if lower else None


def _lean(chosen: dict, partner: dict, check_worse: float = DEFAULT.check_worse) -> str | None:
    """For a split preference (:func:`_check_preference`): ``"partner"`` when every error the choice
    wins, it wins by no more than ``2 check_worse`` while the partner wins one by more (a force
    error ten times lower outweighs a CoP error 6 % higher), ``"chosen"`` the other way round,
    else None (a real split)."""
    mine, theirs = [1.0], [1.0]  # each side's advantages (ratios of the other's error to its own)
    for key, a in chosen["after"].items():
        b = partner["after"].get(key)
        if a is None or b is None or a <= 0 or b <= 0:
            continue
        if b < (1.0 - check_worse) * a:
            theirs.append(a / b)
        elif b > (1.0 + check_worse) * a:
            mine.append(b / a)
    marginal = 1.0 + 2.0 * check_worse
    if max(mine) <= marginal < max(theirs):
        return "partner"
    if max(theirs) <= marginal < max(mine):
        return "chosen"
    return None


def check_changes(chk: dict, worse: float) -> tuple[list[tuple[str, float]], list[tuple[str, float]]]:
    """``(rises, falls)`` of a check (:attr:`Candidate.check`): the errors that rise, and those
    that fall, by more than ``worse`` of their value before and more than their
    :data:`CHECK_FLOORS`, each with ``ln(after / before)``."""
    rises, falls = [], []
    for key, b in chk["before"].items():
        a = chk["after"].get(key)
        if b is None or a is None or not b > 0 or not a > 0:
            continue
        floor = CHECK_FLOORS.get(key, 0.0)
        if a > (1.0 + worse) * b and a - b > floor:
            rises.append((key, math.log(a / b)))
        elif a < (1.0 - worse) * b and b - a > floor:
            falls.append((key, math.log(a / b)))
    return rises, falls


def _floor_text(key: str) -> str:
    """:data:`CHECK_FLOORS`' step of the error ``key`` in its display unit: ``1 mrad``, ``1 mm``, ``0.5 N``."""
    floor = CHECK_FLOORS.get(key, 0.0)
    if key.endswith("_rad"):
        return f"{floor * 1e3:g} mrad"
    if key.endswith("_m"):
        return f"{floor * 1e3:g} mm"
    return f"{floor:g} {'N m' if key.endswith('_Nm') else 'N'}"


def check_text(c: Candidate, check_worse: float = DEFAULT.check_worse) -> str:
    """``against the F/T and motion capture (not fitted): vertical force 36.3 -> 31.9 N, ...``,
    ending with what the check says of the effect ("" without a check); ``check_worse``:
    :attr:`DiagnoseConfig.check_worse`."""
    items = _check_items(c.check) if c.check else []
    if not c.check or not items:
        return ""
    parts = [text for _, _, _, text in items]
    # the veto's own rule (:func:`check_changes`): a rise beyond check_worse and beyond its floor
    rose = {key for key, _ in check_changes(c.check, check_worse)[0]}
    keys = _check_keys(c.check)
    worse = [label for key, (label, _, _, _) in zip(keys, items) if key in rose]
    slight = [(label, key) for key, (label, b, a, _) in zip(keys, items)
              if key not in rose and a > (1.0 + check_worse) * b]
    what = _check_reference(c.check)
    names = ", ".join(worse[:-1]) + " and " + worse[-1] if len(worse) > 1 else "".join(worse)
    if worse:
        verdict = (f"the check disagrees: the {names} error{'s' if len(worse) > 1 else ''} "
                   f"rose by more than {check_worse:.0%}")
    elif slight:
        steps = ", ".join(_floor_text(key) for _, key in slight)
        verdict = (f"the check agrees: the {' and '.join(label for label, _ in slight)} error"
                   f"{'s' if len(slight) > 1 else ''} rose by more than {check_worse:.0%} but by less than the "
                   f"check's smallest step ({steps})")
    else:
        verdict = f"the check agrees (no error rose by more than {check_worse:.0%})"
    return f"against {what} (not fitted): {', '.join(parts)}; {verdict}"


def screen_text(c: Candidate, level: float | None = None) -> str:
    """``score T = 322.5 (nu 3.0), p = 1.3e-69`` (and the passing windows of a windowed test at
    ``level``)."""
    s = c.screen
    if s is None:
        return ""
    out = f"score T = {s.statistic:.1f} (nu {s.dof:.1f}), p = {s.p_value:.2g}"
    if c.base:  # a later round's test: at that round's base
        out += " at + " + " + ".join(c.base)
    if s.kind == "windowed" and level is not None:
        spans = [f"{w.start_s:.2f}-{w.end_s:.2f} s" for w in s.passing_windows(level)]
        shown = ", ".join(spans[:6]) + (" ..." if len(spans) > 6 else "")
        out += f"; windows passing: {shown or 'none'}"
    return out


def identifiability_notes(d: Diagnosis) -> list[str]:
    """One sentence per pair that cannot be told apart, with the choice the ranking made between
    them when it refitted both in one round."""
    if d.identifiability is None:
        return []
    out = []
    tested = {t.effect for t in d.screening} | {c.effect for row in d.rounds for c in row}
    for p in d.identifiability.inseparable():
        text = p.text()
        if d.screening or d.rounds:
            aside = [n for n in (p.a, p.b) if n not in tested]
            if aside:
                text += (f"; {' and '.join(aside)} in the table only, not tested (left out of the default "
                         "catalogue: name it in the candidates to test it)")
        for i, row in enumerate(d.rounds):
            ca = next((c for c in row if c.effect == p.a and c.score is not None), None)
            cb = next((c for c in row if c.effect == p.b and c.score is not None), None)
            if ca is not None and cb is not None:
                hi, lo = (ca, cb) if ca.score >= cb.score else (cb, ca)  # type: ignore[operator]
                taken = d.selected[i] if i < len(d.selected) else None
                if lo.effect == taken:
                    hi, lo = lo, hi
                # "chose" only for the round's choice; otherwise the two scores as they stand
                verb = "chose" if hi.effect == taken else "scored"
                text += f"; round {hi.round} {verb} {_scored(hi)} over {_scored(lo)}"
                break
        out.append(text)
    return out


def ranking_table(d: Diagnosis) -> str:
    """Plain-text ranking (what the CLI prints)."""
    lines = [f"{'#':>2s} {'effect':24s} {'score':>10s} {'LR':>10s} {'dof':>6s} {'p':>9s}  sig  estimate"]
    level = d.criterion.get("screen_level")
    for i, c in enumerate(d.ranking, 1):
        if c.error:
            lines.append(f"{i:2d} {c.effect:24s} {'-':>10s} {'-':>10s} {'-':>6s} {'-':>9s}  no   "
                         f"cannot be fitted: {c.error}")
            continue
        if not c.refitted:
            lines.append(f"{i:2d} {c.effect:24s} {'-':>10s} {'-':>10s} {'-':>6s} {'-':>9s}  no   "
                         f"{not_refitted_text(c, d)}")
            continue
        mark = "yes" if c.significant else ("imp" if c.implausible else "no ")
        lines.append(f"{i:2d} {c.effect:24s} {c.score:10.1f} {c.lr:10.1f} {c.effective_dof:6.1f} "
                     f"{c.p_value:9.2g}  {mark:3s}  {c.finding or c.summary}")
        if c.screen is not None:
            lines.append(f"{'':28s}screened: {screen_text(c, level)}")
        if c.check:
            lines.append(f"{'':28s}checked {check_text(c, d.config.check_worse)}")
        if c.constancy and not c.implausible:
            lines.append(f"{'':28s}constancy: {constancy_line(c, d.config)}")
    lines += [f"   {w}" for w in d.swaps]
    lines += [f"   {w}" for w in ambiguities(d)]
    lines += [f"   {w}" for w in partner_checks(d)]
    lines += [f"   {w}" for w in inconstant(d)]
    lines += [f"   {w}" for w in d.skipped]
    if d.identifiability is not None:
        lines.append(d.identifiability.table())
        # a candidate the table calls not fully seen that the diagnosis found or added all the same
        lines += [f"   {w.split(':', 1)[0]}: {w[w.index('; found all the same') + 2:]}"
                  for w in identifiability_items(d) if "; found all the same" in w]
        # the table just printed each pair's sentence: what the rounds made of it, under the pair's name
        lines += [f"   {w.split(':', 1)[0]}: {w[w.index('; round ') + 2:]}"
                  for w in identifiability_notes(d) if "; round " in w]
    elif d.identifiability_error:
        lines.append(f"identifiability: not computed ({d.identifiability_error})")
    return "\n".join(lines)


def partner_checks(d: Diagnosis) -> list[str]:
    """One sentence per selected effect whose round also refitted a candidate that may stand for
    it (a rival within :attr:`DiagnoseConfig.tie`, or a pair the identifiability table calls inseparable,
    significant and plausible): each one's errors against what the fits did not use (the truth,
    or the reference sensors), and which of them those favour.  The selection stands (the data
    chose); the sentence shows the user what the independent references say of the choice."""
    out = []
    for i, name in enumerate(d.selected):
        if i >= len(d.rounds):
            break
        row = d.rounds[i]
        chosen = next((c for c in row if c.effect == name), None)
        partners = [c for c in row if c.effect != name and c.check and c.partner_of == name]
        if chosen is None or not chosen.check or not partners:
            continue
        parts = [f"{chosen.effect} {_check_after(chosen.check)}"]
        favoured = []
        for c in partners:
            assert c.check is not None
            parts.append(f"{c.effect} {_check_after(c.check)}")
            verdict = _check_preference(chosen.check, c.check, d.config.check_worse)
            if verdict == "split":
                verdict = _lean(chosen.check, c.check, d.config.check_worse) or "split"
            if verdict is not None:
                favoured.append((c.effect, verdict))
        what = _check_reference(chosen.check)
        rivals = [c.effect for c in partners if c.effect in chosen.rivals]
        table = [c.effect for c in partners if c.effect not in chosen.rivals]
        why = ([f"{' and '.join(rivals)} (score{'s' if len(rivals) > 1 else ''} within {d.config.tie:g} of it)"]
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
        elif any(v == "split" for _, v in favoured):
            split = [e for e, v in favoured if v == "split"]
            tail = (f"the errors split between the choice and {' and '.join(split)} (each lower by more than "
                    f"{d.config.check_worse:.0%} on one of them): {what} do{'es' if one else ''} not decide "
                    "between them")
        else:
            tail = f"{what} do{'es' if one else ''} not decide between them"
        out.append(f"round {i + 1} took {name}; beside it, {'; '.join(why)} refitted in that round; against "
                   f"{what} (not fitted), each added to the round's base: {'; '.join(parts)}: {tail}")
    return out


def inconstant(d: Diagnosis) -> list[str]:
    """One sentence per round in which the constancy check (:func:`constancy`) turned down a
    candidate the evidence favoured: what it means for the model."""
    out = []
    for i, row in enumerate(d.rounds):
        bad = [c for c in row if c.inconstant]
        if not bad:
            continue
        took = next((c.effect for c in row if c.effect in d.selected and c.significant), None)
        names = ", ".join(c.effect for c in bad)
        several = len(bad) > 1
        out.append(f"round {i + 1}: {names} {'were' if several else 'was'} significant but not constant over the "
                   f"recording (each fitted on its two halves: estimates apart beyond {d.config.constancy_z:g}σ and "
                   f"{d.config.constancy_rel:.0%} of {'their' if several else 'its'} size); "
                   + (f"the round took {took}" if took else "the round took none")
                   + ": what the model misses here changes over the recording (a drift of the local frame, a "
                     "load or a contact that changes, a model error that depends on the motion), and a "
                     "constant effect only stands in for it")
    return out


def ambiguities(d: Diagnosis) -> list[str]:
    """One sentence per round whose best effect the data cannot tell from another."""
    out = []
    for row in d.rounds:
        best = row[0] if row else None
        if best is None or not best.rivals:
            continue
        rows = [next(c for c in row if c.effect == r) for r in best.rivals]
        close = [c for c in rows if best.score - c.score < d.config.tie]  # type: ignore[operator]
        if close:
            others = ", ".join(f"{c.effect} ({c.score:.1f})" for c in close)
            out.append(f"round {best.round}: {best.effect} ({best.score:.1f}) is not told apart from {others}: "
                       f"the scores differ by less than {d.config.tie:g} (a Bayes factor of 20); "
                       f"more varied motion, or knowledge of the robot, must decide")
        charged = [c for c in rows if c not in close]
        if charged:
            others = ", ".join(f"{c.effect} (2ΔE {c.lr:.1f}, score {c.score:.1f})" for c in charged)
            out.append(f"round {best.round}: {best.effect} (2ΔE {best.lr:.1f}, score {best.score:.1f}) fits the "
                       f"data as well as {others}, which the identifiability table calls inseparable from it: "
                       f"the evidence differs by less than {d.config.tie:g}, and the score prefers {best.effect} "
                       "only for its count of unknowns; knowledge of the robot, or a motion that separates them, must "
                       "decide (the check against what the fit did not use may tell)")
    return out


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
    if traits(effect).constant:
        return "acts throughout (a constant)"
    return "acts throughout"


def finding(c: Candidate, rep: dict, effect) -> str:
    """The row's sentence, consistent with its status: a significant effect's size, evidence and
    when it acts; an implausible one flagged as such; a non-significant one never "found"."""
    summary = c.summary
    if c.implausible and c.vetoed:
        return f"turned down: {c.implausible} (estimate {summary}); not taken, not added by --add auto"
    if c.implausible and c.dominant:
        return (f"implausible: {without_advice(c.implausible)} (estimate {summary}); yet the round's highest score "
                f"by far ({c.score:.1f}): the data point to what this effect does, with values the physics refuses, "
                "and no candidate is taken in its place")
    if c.implausible:
        return (f"implausible: {without_advice(c.implausible)} (estimate {summary}); not a finding: another "
                "effect in disguise")
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
    null = getattr(effect, "null", 0.0)
    sigmas = _largest_z(rep, null)
    if sigmas is not None and sigmas >= 3.0 and c.p_value is not None:
        # the Laplace sigma and the likelihood ratio disagree: say which one the verdict follows
        if c.level is not None and c.p_value >= c.level:
            test = (f"the likelihood-ratio test, which decides, does not confirm it: its p = {c.p_value:.2g} is above "
                    f"its level {c.level:.2g}")
        else:
            test = (f"its BIC score, {c.score:.1f}, is not above 0: the gain in fit does not pay for its unknowns "
                    "(significance needs both the score and the likelihood-ratio test)")
        return (f"not significant: the estimate {summary} is {sigmas:.1f}σ from {_fmt_null(null)} by its local "
                f"(Laplace) sigma, but {test} ({evidence})")
    return f"not significant ({evidence}); estimate {summary}"


def _fmt_null(null) -> str:
    """The effect's null value as the sentence names it (``0``, ``1``; ``its nominal value`` for a vector)."""
    arr = np.atleast_1d(np.asarray(null, dtype=float))
    return f"{arr[0]:g}" if arr.size and np.all(arr == arr[0]) else "its nominal value"


def _largest_z(rep: dict, null=0.0) -> float | None:
    """The largest ``|value - null| / std`` of a constant effect's report (None without both)."""
    if not isinstance(rep, dict) or rep.get("value") is None or rep.get("std") is None or rep.get("windows"):
        return None
    try:
        v = np.atleast_1d(np.asarray(rep["value"], dtype=float)).ravel()
        sd = np.atleast_1d(np.asarray(rep["std"], dtype=float)).ravel()
    except (TypeError, ValueError):
        return None
    if v.size == 0 or v.shape != sd.shape or not np.all(sd > 0):
        return None
    try:
        z = np.abs(v - np.broadcast_to(np.asarray(null, dtype=float), v.shape)) / sd
    except ValueError:
        return None
    return float(np.max(z)) if np.all(np.isfinite(z)) else None


def without_advice(text: str) -> str:
    """An implausibility text without its clauses of advice (:data:`ADVICE`): a turned-down effect
    stands for something else, so what to do about that effect does not apply."""
    parts: list[str] = []
    for part in text.split("; "):
        if part.strip().lower().startswith(ADVICE):
            closing = len(part) - len(part.rstrip(")"))  # the brackets the clause closed stay closed
            if parts and closing:
                parts[-1] += ")" * closing
            continue
        parts.append(part)
    return "; ".join(parts) if parts else text




def constancy_text(what: str, comp: str, unit: str, value, std, spans, z: float, rel: float, constant: bool,
                   config: DiagnoseConfig = DEFAULT) -> str:
    """The constancy check's sentence (:func:`~flexforce.compare.diagnostics.constancy.constancy`):
    the component ``comp`` of the effect ``what`` on the two halves ``spans`` (s), ``value`` ±
    ``std`` (in ``unit``) on each, ``z`` sigmas and ``rel`` of its size apart."""
    from flexforce.factors.effects import _fmt

    halves = ", ".join(f"{_fmt(value[h])} ± {_fmt(std[h])}{(' ' + unit) if unit else ''} in "
                       f"{spans[h][0]:.1f}-{spans[h][1]:.1f} s" for h in (0, 1))
    if constant:
        return (f"its halves agree: {what} {comp} = {halves} ({abs(z):.1f}σ and {rel:.0%} of it apart, the "
                f"largest difference; not both beyond {config.constancy_z:g}σ and {config.constancy_rel:.0%})")
    return (f"not constant over the recording: {what} {comp} = {halves} ({abs(z):.0f}σ and {rel:.0%} of "
            f"it apart, beyond {config.constancy_z:g}σ and {config.constancy_rel:.0%}); a constant effect does not "
            "change within a recording: the estimate stands for something the model misses that changes over it")


# ----------------------------------------------------------------------------------------------
# The verdict: the report's first words
# ----------------------------------------------------------------------------------------------

ACTIONS = {"external-wrench": "look for what touched or pulled the robot then (a push, a cable, a collision)",
           "com-offset": "correct the mass model (the links' inertial parameters)",
           "mass-scale": "correct the robot's mass in the model",
           "accel-bias": "calibrate the accelerometer's bias", "gyro-bias": "calibrate the gyroscope's bias",
           "imu-mounting": "correct the IMU's mounting rotation in the robot configuration",
           "time-offset": "resynchronise the logs (shift the IMU's time stamps by the offset)",
           "stiffness": "re-identify the contacts' stiffness and damping",
           "anisotropic-stiffness": "re-identify the contacts' stiffness axis by axis",
           "nonlinear-stiffness": "model the contacts' stiffening with the load",
           "ft-offset": "re-zero the F/T sensors", "foothold": "check the ground and the feet's placement"}
"""What to do about an effect the diagnosis found (said only of a selected or added effect)."""


def display(value: float, unit: str) -> tuple[float, str]:
    """``value`` in ``unit`` (SI) shown in the report's units (:data:`DISPLAY_UNITS`)."""
    shown, factor = DISPLAY_UNITS.get(unit, (unit, 1.0))
    return value * factor, shown


def _num(x: float, sd: float | None = None) -> str:
    """``21.2 ± 0.4``: the value to the precision of its sigma, given to two digits below 3 in its
    leading digit and one above (3 significant digits without a sigma)."""
    if sd is None or not math.isfinite(sd) or sd <= 0:
        return f"{x:.3g}"
    exponent = int(math.floor(math.log10(sd)))
    leading = sd / 10.0 ** exponent  # two digits of a sigma below 3 (1.7), one above (0.4)
    digits = max(0, min(6, -exponent + (1 if leading < 3.0 else 0)))
    return f"{x:.{digits}f} ± {sd:.{digits}f}"


def effect_values(name: str, rep: dict) -> str:
    """An effect's fitted values in the report's units: ``CoM offset x = 21.2 ± 0.4 mm`` (its
    significant components, else all), or for a per-step wrench its windows (``external force of
    32 ± 2 N along x at 2.51-2.69 s, peak at 2.60 s``); the report's ``summary`` when it has no
    values ("" without a report)."""
    if not isinstance(rep, dict) or not rep:
        return ""
    if rep.get("windows"):
        return "; ".join(_window_text(w) for w in rep["windows"][:4]) + (" ..." if len(rep["windows"]) > 4 else "")
    value, std = rep.get("value"), rep.get("std")
    if value is None:
        return str(rep.get("summary") or "")
    v = np.atleast_1d(np.asarray(value, dtype=float)).ravel()
    sd = np.atleast_1d(np.asarray(std, dtype=float)).ravel() if std is not None else np.full(v.shape, np.nan)
    labels = list(rep.get("labels") or [f"#{i}" for i in range(v.size)])
    names = [str(lab).partition(" [")[0] for lab in labels]
    units = [str(lab).partition(" [")[2].rstrip("]") or str(rep.get("unit") or "") for lab in labels]
    keep = [i for i, n in enumerate(names) if n in (rep.get("significant") or ())]
    if not keep:
        keep = list(range(min(v.size, 6)))
    cls = EFFECTS.get(name)
    what = getattr(cls, "what", "") or name
    parts = []
    for i in keep:
        if i >= v.size:
            continue
        x, unit = display(float(v[i]), units[i] if i < len(units) else "")
        s, _ = display(float(sd[i]), units[i] if i < len(units) else "") if i < sd.size else (float("nan"), "")
        unit = "" if unit in ("", "-") else f" {unit}"
        parts.append(f"{names[i] if i < len(names) else i} = {_num(x, s)}{unit}")
    return f"{what} " + ", ".join(parts) if parts else str(rep.get("summary") or "")


def _window_text(w: dict) -> str:
    """``external force of 32 ± 2 N along x at 2.51-2.69 s (peak at 2.60 s)`` of a wrench window."""
    f = np.asarray(w.get("peak_force") or (w.get("peak_wrench") or [0, 0, 0])[:3], dtype=float)
    sd = np.asarray((w.get("peak_std") or [np.nan] * 3)[:3], dtype=float)
    k = int(np.argmax(np.abs(f)))
    span = f"{w['start_s']:.2f}-{w['end_s']:.2f} s"
    peak = f", peak at {w['peak_s']:.2f} s" if w.get("peak_s") is not None else ""
    return (f"external force of {_num(abs(float(f[k])), float(sd[k]))} N along {'-' if f[k] < 0 else '+'}{'xyz'[k]} "
            f"at {span}{peak}")


def _errors_change(before: dict, after: dict, check_worse: float, limit: int = 3) -> tuple[str, str]:
    """``("the force error from 3.16 to 1.12 N, the tilt error from 8.88 to 0.499 mrad", "")``: the
    errors that fall (the force first, then the largest falls, at most ``limit``), and the ones
    that rise by more than ``check_worse`` (second, "" when none)."""
    rows = []
    for key, b in before.items():
        a = after.get(key)
        if b is None or a is None or b <= 0:
            continue
        label, scale, unit = CHECK_LABELS.get(key, (key, 1.0, ""))
        rows.append((key, a / b, f"the {label} error from {b * scale:.3g} to {a * scale:.3g}{unit}"))
    fall = sorted((r for r in rows if r[1] < 1.0 - check_worse), key=lambda r: (r[0] != "force_N", r[1]))
    rise = [r for r in rows if r[1] > 1.0 + check_worse]
    return ", ".join(r[2] for r in fall[:limit]), ", ".join(r[2] for r in rise)


def _row(d: Diagnosis, name: str) -> Candidate | None:
    """The latest refitted row of ``name`` (its ranking row first)."""
    for c in d.ranking:
        if c.effect == name and c.score is not None:
            return c
    for row in reversed(d.rounds):
        for c in row:
            if c.effect == name and c.score is not None:
                return c
    return None


def _and(names: list[str]) -> str:
    return ", ".join(names[:-1]) + " and " + names[-1] if len(names) > 1 else "".join(names)


def verdict(d: Diagnosis) -> str:
    """The diagnosis in plain words, first on the page and in the terminal: what the model misses
    (the selected effects with their fitted values, units and time spans), what adding them does
    to the errors (the after view against the before view, else the selection's check) and the
    flagged windows, what the check against the truth or the references says; when nothing is
    selected, why (turned down by the check, implausible, not constant, none significant)."""
    worse = d.config.check_worse
    found = [n for n in d.selected]
    added = list(d.added)
    out = []
    after_effects = (d.after.estimate.effects or {}) if d.after is not None else {}
    if found:
        parts = []
        for name in found:
            c = _row(d, name)
            rep = after_effects.get(name) or (c.parameters if c is not None else {})
            values = effect_values(name, rep)
            parts.append(f"{name} ({values})" if values else name)
        out.append(f"The model misses {_and(parts)}.")
    elif d.rounds or d.screening:
        out.append(f"No effect is selected: {_none_reason(d)}.")
    by_hand = [n for n in added if n not in found]
    if by_hand:
        fitted = [effect_values(n, after_effects.get(n, {})) for n in by_hand]
        out.append("Added by hand" + (f" (the selection did not take {'them' if len(by_hand) > 1 else 'it'})"
                                      if d.rounds else "") + ": "
                   + _and([f"{n} ({v})" if v else n for n, v in zip(by_hand, fitted)]) + ".")
    if d.after is not None:
        fall, rise = _errors_change(d.before.rmse, d.after.rmse, worse)
        what = "the errors against the truth" if d.recording.get("has_truth") else "the errors"
        flags = f"the flagged windows from {len(d.before.flags)} to {len(d.after.flags)}"
        sentence = f"Adding {'them' if len(added) > 1 else 'it'} lowers " + (f"{fall} and {flags}" if fall else flags)
        if not fall and len(d.after.flags) >= len(d.before.flags):
            sentence = f"Adding {'them' if len(added) > 1 else 'it'} changes {what} little ({flags})"
        out.append(sentence + (f"; but it raises {rise}" if rise else "") + ".")
    elif found:
        c = _row(d, found[0]) if len(found) == 1 else None
        chk = c.check if c is not None else None
        if chk:
            fall, rise = _errors_change(chk["before"], chk["after"], worse)
            if fall or rise:
                out.append(f"Against {_check_reference(chk)} (not fitted), adding it lowers " + (fall or "no error")
                           + (f"; but it raises {rise}" if rise else "") + ".")
        out.append(f"Rerun with --add {' --add '.join(found)} (or --add auto) to fit "
                   f"{'them' if len(found) > 1 else 'it'} and compare the errors and flagged windows.")
    for c in [c for row in d.rounds for c in row if c.dominant]:
        out.append(f"The data point {'further ' if found else ''}to {c.effect}, fitted to physically implausible "
                   f"values ({without_advice(str(c.implausible))}), with the highest score of its round by far "
                   f"({c.score:.1f}): no candidate describes that misfit, and none is taken in its place.")
    down = [c for row in d.rounds for c in row if c.vetoed and c.effect not in found]
    if found and down:
        out.append("Turned down by their check against what the fits did not use: "
                   + "; ".join(f"{c.effect} ({_veto_short(c, worse)})" for c in down[:3]) + ".")
    for name in found + [n for n in added if n not in found]:
        if name in ACTIONS:
            out.append(f"To act on {name}: {ACTIONS[name]}.")
            break
    return " ".join(out)


def _veto_short(c: Candidate, check_worse: float) -> str:
    """``raises the force error from 3.16 to 10.3 N``: the rise that turned ``c`` down, else its word."""
    if c.check:
        _, rise = _errors_change(c.check["before"], c.check["after"], check_worse)
        if rise:
            return f"raises {rise.split(', the ')[0]}"
    return str(c.implausible)


def _none_reason(d: Diagnosis) -> str:
    """Why nothing was selected, in plain words, from the first round's rows."""
    rows = [c for row in d.rounds for c in row]
    vetoed = [c for c in rows if c.vetoed]
    inconstant_ = [c for c in rows if c.implausible and not c.vetoed and c.inconstant]
    implausible = [c for c in rows if c.implausible and c not in vetoed and c not in inconstant_]
    reasons = []
    if vetoed:
        reasons.append("turned down by their check against what the fits did not use: "
                       + "; ".join(f"{c.effect} (score {c.score:.1f}: {_veto_short(c, d.config.check_worse)})"
                                   for c in vetoed[:3]))
    if inconstant_:
        reasons.append("significant but not constant over the recording: " + _and([c.effect for c in inconstant_]))
    if implausible:
        reasons.append("fitted to physically implausible values: "
                       + "; ".join(f"{c.effect} ({without_advice(str(c.implausible))})" for c in implausible[:3]))
    if reasons:
        return "the candidates the data favoured were " + "; and ".join(reasons)
    if not rows:
        return "no candidate passed the score test at the nominal fit: the model explains the data within their noise"
    best = max((c for c in rows if c.score is not None), key=lambda c: c.score, default=None)  # type: ignore
    if best is None:
        return "no candidate could be fitted"
    return (f"none is significant (the best, {best.effect}, scores {best.score:.1f} with p = {best.p_value:.2g}): "
            "the model explains the data within their noise")


def not_refitted_text(c: Candidate, d: Diagnosis) -> str:
    """Why a row was not refitted in its round, with what an earlier round's refit of it found
    (a candidate refitted, even significant, in round 1 and screened out at a later base)."""
    level = d.criterion.get("screen_level")
    why = without_advice(c.deferred) if c.deferred else ""
    screen = screen_text(c, level)
    if not why and c.screen is not None and level is not None:
        why = f"score test p = {c.screen.p_value:.2g} ≥ {level:g}" + (" at + " + " + ".join(c.base) if c.base else "")
        screen = ""
    earlier = [r for row in d.rounds for r in row if r.effect == c.effect and r.score is not None and r.round < c.round]
    text = f"not refitted in round {c.round}: {why}" if why else f"not refitted in round {c.round}"
    if earlier and not (c.deferred and "its refit in round" in c.deferred):
        e = earlier[-1]
        text += (f"; refitted in round {e.round}: {e.status} (score {e.score:.1f})"
                 + (f", {effect_values(e.effect, e.parameters)}" if e.status == "significant" else ""))
    return text + (f"; {screen}" if screen and not c.deferred else "")


def constancy_line(c: Candidate, config: DiagnoseConfig = DEFAULT) -> str:
    """The constancy check's sentence about the component the fit found (the estimate's significant
    components), with the largest difference when it was on another component."""
    con = c.constancy or {}
    if not con.get("made") or "value" not in con:
        return str(con.get("text", ""))
    rep = c.parameters if isinstance(c.parameters, dict) else {}
    labels = [str(lab) for lab in rep.get("labels") or ()]
    names = [lab.partition(" [")[0] for lab in labels]
    units = [lab.partition(" [")[2].rstrip("]") or str(rep.get("unit") or "") for lab in labels]
    found = [names.index(n) for n in rep.get("significant") or () if n in names]
    largest = con.get("largest", [None])[0]
    v, sd, z, spans = con["value"], con["std"], con["z"], con["halves"]
    verdict_ = "its halves agree" if con.get("constant") else "its halves disagree"

    def comp(i: int) -> str:
        unit = units[i] if i < len(units) else ""
        halves = []
        for h in (0, 1):
            x, u = display(float(v[h][i]), unit)
            s, _ = display(float(sd[h][i]), unit)
            halves.append(f"{_num(x, s)}{'' if u in ('', '-') else ' ' + u} in {spans[h][0]:.1f}-{spans[h][1]:.1f} s")
        return f"{names[i]} = {', '.join(halves)} ({abs(float(z[i])):.1f}σ apart)"

    if not found or len(names) != len(v[0]):
        return str(con.get("text", ""))
    text = f"{verdict_} on {', '.join(comp(i) for i in found)}"
    if largest is not None and largest in names and names.index(largest) not in found:
        text += f"; the largest difference is on {comp(names.index(largest))}"
    return text + (f" (the check calls halves apart beyond {config.constancy_z:g}σ and {config.constancy_rel:.0%} "
                   "of the size on one component inconstant)")


def identifiability_items(d: Diagnosis) -> list[str]:
    """The identifiability table's candidates with a direction the recording does not excite, each
    said as what it is (a prior-sized value along that direction goes unseen at the nominal fit)
    and, for an effect the diagnosis found or added all the same, that it did; then the pairs the
    recording cannot tell apart (:func:`identifiability_notes`)."""
    if d.identifiability is None:
        return []
    found = set(d.selected) | set(d.added)
    out = []
    not_seen = getattr(d.identifiability, "not_seen", None)
    for info in not_seen() if not_seen is not None else []:
        what = f" ({info.excites})" if info.excites else ""
        text = (f"{info.effect}: {info.status}: at the nominal fit, a prior-sized {info.weakest}{what} gains "
                f"{info.detectability:.2g} in 2 ln L, below {info.threshold:.1f}: an effect that small along it "
                f"goes unseen; detects {detectable_text(info)}")
        if info.effect in found:
            text += ("; found all the same (see the verdict): larger than these sizes, or along the directions "
                     "the recording does excite")
        out.append(text)
    return out + identifiability_notes(d)


def detectable_text(info) -> str:
    """``x ≥ 1.9 mrad, ...``: a candidate's detectable sizes (:attr:`CandidateInformation.detectable`)
    in the report's units, one per unknown."""
    out = []
    for i, size in enumerate(info.detectable):
        label = info.labels[i] if i < len(info.labels) else f"#{i}"
        name, _, unit = label.partition(" [")
        unit = unit.rstrip("]")
        if not math.isfinite(size):
            out.append(f"{name} not alone")
            continue
        x, shown = display(size, unit)
        out.append(f"{name} ≥ {x:.2g}{' ' + shown if shown and shown != '-' else ''}")
    return ", ".join(out)
