"""The diagnosis in words: the sentences of its rows, checks, rounds and table, rendered from the
typed results (:mod:`.results`), which hold only data."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from flexforce.compare.diagnostics.config import DEFAULT, DiagnoseConfig
from flexforce.errors import FlexforceError
from flexforce.factors.effects.base import traits

if TYPE_CHECKING:
    from flexforce.compare.diagnostics.results import Candidate, Diagnosis
    from flexforce.smoother.screening import Identifiability


CHECK_LABELS = {"force_N": ("force", 1.0, " N"), "moment_Nm": ("moment", 1.0, " N m"), "cop_m": ("CoP", 1e3, " mm"),
                "rotation_rad": ("tilt", 180.0 / math.pi, " deg"), "translation_m": ("position", 1e3, " mm"),
                "hand_m": ("hand", 1e3, " mm"), "vertical_force_N": ("vertical force", 1.0, " N"),
                "contact_force_N": ("contact force", 1.0, " N"), "contact_moment_Nm": ("contact moment", 1.0, " N m"),
                "contact_cop_m": ("sole CoP", 1e3, " mm")}
"""How :meth:`Candidate.check_text` names and scales each error."""


def _scored(c: Candidate) -> str:
    """``name (score S)``, with ``, implausible`` when its estimate is."""
    return f"{c.effect} (score {c.score:.1f}{', implausible' if c.implausible else ''})"


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


def _check_keys(check: dict) -> list[str]:
    """The error keys of :func:`_check_items`' items, in the same order."""
    return [key for key, b in check["before"].items() if b is not None and check["after"].get(key) is not None]


def _check_reference(check: dict) -> str:
    """What a check holds the fit against: ``the truth``, ``the F/T and motion capture``, ..."""
    if check["against"] == "truth":
        return "the truth"
    return f"the {' and '.join(check['sensors'])}" if check.get("sensors") else "the reference sensors"


def _check_after(check: dict) -> str:
    """``(tilt 0.61 -> 0.3 deg, vertical force 36.3 -> 35 N)`` of a :attr:`Candidate.check`."""
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


def check_text(c: Candidate, check_worse: float = DEFAULT.check_worse) -> str:
    """``against the F/T and motion capture (not fitted): vertical force 36.3 -> 31.9 N, ...``,
    ending with what the check says of the effect ("" without a check); ``check_worse``:
    :attr:`DiagnoseConfig.check_worse`."""
    items = _check_items(c.check) if c.check else []
    if not c.check or not items:
        return ""
    parts = [text for _, _, _, text in items]
    worse = [label for label, b, a, _ in items if a > (1.0 + check_worse) * b]
    what = _check_reference(c.check)
    names = ", ".join(worse[:-1]) + " and " + worse[-1] if len(worse) > 1 else "".join(worse)
    verdict = (f"the check disagrees: the {names} error{'s' if len(worse) > 1 else ''} "
               f"rose by more than {check_worse:.0%}" if worse else
               f"the check agrees (no error rose by more than {check_worse:.0%})")
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
            why = f"{c.deferred}; " if c.deferred else ""
            lines.append(f"{i:2d} {c.effect:24s} {'-':>10s} {'-':>10s} {'-':>6s} {'-':>9s}  no   "
                         f"not refitted: {why}{screen_text(c, level)}")
            continue
        mark = "yes" if c.significant else ("imp" if c.implausible else "no ")
        lines.append(f"{i:2d} {c.effect:24s} {c.score:10.1f} {c.lr:10.1f} {c.effective_dof:6.1f} "
                     f"{c.p_value:9.2g}  {mark:3s}  {c.finding or c.summary}")
        if c.screen is not None:
            lines.append(f"{'':28s}screened: {screen_text(c, level)}")
        if c.check:
            lines.append(f"{'':28s}checked {check_text(c, d.config.check_worse)}")
        if c.constancy and not c.implausible:
            lines.append(f"{'':28s}constancy: {c.constancy['text']}")
    lines += [f"   {w}" for w in d.swaps]
    lines += [f"   {w}" for w in ambiguities(d)]
    lines += [f"   {w}" for w in partner_checks(d)]
    lines += [f"   {w}" for w in inconstant(d)]
    lines += [f"   {w}" for w in d.skipped]
    if d.identifiability is not None:
        lines.append(d.identifiability.table())
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
        bad = [c for c in row if c.constancy and c.constancy.get("made") and not c.constancy["constant"]]
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
