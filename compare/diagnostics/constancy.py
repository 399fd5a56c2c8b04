"""The constancy check: a constant effect the selection would take, fitted again on each half of
the recording."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from flexforce.compare.diagnostics.config import DEFAULT, DiagnoseConfig
from flexforce.compare.diagnostics.fitting import Fit, fit_model
from flexforce.compare.diagnostics.text import constancy_text


def constancy(rec, model, makers: dict[str, Callable[[], object]], base: tuple[str, ...], name: str,
              jobs: int | str = 1, start: Fit | None = None, config: DiagnoseConfig = DEFAULT) -> dict:
    """Whether the constant effect ``name`` is the same on both halves of ``rec``.

    The model with ``base`` and ``name`` (``makers``' effects) is fitted on each half
    (:meth:`~flexforce.datasets.recording.Recording.window`, in ``jobs`` processes); the halves'
    estimates are compared component by component, the difference standardised by the two halves'
    sigmas and relative to the larger estimate's departure from the effect's ``null``.  A constant
    effect (a bias, a mounting, a stiffness, a delay, a mass) is the same in both halves within
    ``config.constancy_z`` sigma or within ``config.constancy_rel`` of its size; an estimate that
    changes beyond both stands for something else that changes over the recording
    (docs/diagnostics.md, "Tuning", has the measurements behind the thresholds).

    ``start``: a fit of ``rec`` with ``base`` and ``name`` (the round's refit), whose states and
    effects each half starts from, cut to it: the candidate starts at its estimate on the whole
    recording, so that a half whose evidence has more than one optimum in the effect (a delay on a
    walk) looks for its own near it; without it, at the effect's prior mean.

    Returns ``{"made": True, "constant": bool, "halves": [[t0, t1], [t1, t2]], "value": [...],
    "std": [...], "z": [...], "relative": [...], "largest": (component, z), "text": ...}``, or
    ``{"made": False, "text": why}`` when the recording is shorter than two halves of
    ``config.constancy_min_s`` s or a half cannot be fitted.
    """
    duration = float(rec.time[-1]) if rec.n else 0.0
    eff0 = makers[name]()
    if duration < 2.0 * config.constancy_min_s:
        return {"made": False, "text": f"not checked for constancy: the recording ({duration:.1f} s) is shorter than "
                                       f"two halves of {config.constancy_min_s:g} s"}
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
        fitted = fit_model(part, dataclasses.replace(model, effects=effects), start=begin,
                           evidence_tol=config.evidence_tol)
        return fitted.estimate.effects.get(name, {})

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
    apart = (np.abs(z) > config.constancy_z) & (rel > config.constancy_rel)
    # the component that fails both parts, else the one farthest apart in sigmas
    i = int(np.argmax(np.where(apart, np.abs(z), -1.0))) if apart.any() else int(np.argmax(np.abs(z)))
    names = eff0.component_names() if hasattr(eff0, "component_names") else tuple(str(k) for k in range(v.shape[1]))
    units = eff0.units() if hasattr(eff0, "units") else ("",) * v.shape[1]
    comp = names[i] if i < len(names) else str(i)
    unit = units[i] if i < len(units) and units[i] not in ("", "-") else ""
    what = getattr(eff0, "what", name)
    constant = not bool(apart.any())
    text = constancy_text(what, comp, unit, v[:, i], sd[:, i], spans, float(z[i]), float(rel[i]), constant, config)
    return {"made": True, "constant": constant, "halves": [list(sp) for sp in spans], "value": v.tolist(),
            "std": sd.tolist(), "z": z.tolist(), "relative": rel.tolist(), "largest": [comp, float(z[i])],
            "text": text}
