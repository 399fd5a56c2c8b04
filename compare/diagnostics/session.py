"""A diagnosis in progress: the recording, the candidates' factories, the configuration, the fits
made so far (by effect set) and the progress callback; created by
:func:`~flexforce.compare.diagnostics.diagnose` for one diagnosis and passed down."""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from typing import Any

from flexforce.compare.diagnostics.checks import reference_check
from flexforce.compare.diagnostics.config import DiagnoseConfig
from flexforce.compare.diagnostics.fitting import Fit, LeavingPlausible, fit_model, snapshot
from flexforce.compare.diagnostics.progress import progress_caller
from flexforce.compare.diagnostics.results import Snapshot


class Session:
    """The state one diagnosis shares between its steps.

    Attributes:
        rec, model: the Recording and the nominal ModelConfig.
        makers: effect name -> factory of every candidate and added effect (bound to ``rec``).
        config: the :class:`DiagnoseConfig`.
        jobs: worker processes (``config.jobs`` until :meth:`resolve_jobs` decides ``"auto"``).
        cache: the fits, by their sorted effect names; ``fit_errors`` the failed ones (raised by
            :meth:`fitted`), ``fit_seconds`` the time of those fitted in workers.
        side: before/after views formed beside refits, by the fit's sorted effect names.
        checked: errors against the truth or the reference sensors, by the fit's sorted effects.
        watching: whether new effects' refits are watched (:class:`LeavingPlausible`): the
            selection's are, the added effects' fit is not.
    """

    def __init__(self, rec, model, makers: dict[str, Callable[[], object]], config: DiagnoseConfig,
                 progress: Callable[..., None] | None = None):
        self.rec, self.model, self.makers, self.config = rec, model, makers, config
        self.call = progress_caller(progress)
        self.t_start = time.perf_counter()
        self.jobs: Any = config.jobs
        self.cache: dict[tuple[str, ...], Fit] = {}
        self.fit_errors: dict[tuple[str, ...], Exception] = {}
        self.fit_seconds: dict[tuple[str, ...], float] = {}
        self.side: dict[tuple[str, ...], Snapshot] = {}
        self.checked: dict = {}
        self.watching = config.rank

    def resolve_jobs(self) -> None:
        """Decide ``"auto"`` (:func:`flexforce.compare.runner.resolve_jobs`), with the nominal fit in
        memory (what a worker starts from)."""
        from flexforce.compare.runner import resolve_jobs

        self.jobs = resolve_jobs(self.jobs)

    # -- progress -------------------------------------------------------------------------------

    def cb(self, label: str):
        """A stage's ``progress(fraction)``, None without a callback."""
        call = self.call
        return (lambda f: call(label, f)) if call else None

    def cb_message(self, label: str):
        """A stage's progress that also takes a message (the screening's, one per candidate)."""
        call = self.call
        return (lambda f, message=None: call(label, f, message)) if call else None

    def say(self, label: str, message: str, t0: float) -> None:
        """The stage's message with its time since ``t0`` and the diagnosis's so far."""
        if self.call is not None:
            self.call(label, 1.0, f"{message} [{time.perf_counter() - t0:.1f} s, "
                                  f"{time.perf_counter() - self.t_start:.0f} s in all]")

    # -- fits -----------------------------------------------------------------------------------

    def fit_with(self, names: tuple[str, ...], progress=None) -> Fit:
        """The model with the candidates ``names`` added, fitted, from the fit of the most of them
        there is (the round's base: the refit only moves what the new effect explains)."""
        cache = self.cache
        effects = tuple(self.model.effects) + tuple(self.makers[n]() for n in names)
        within = [key for key in cache if set(key) < set(names)]
        # the round's base when it is there (a round's refit adds the last name to it), else the most
        start = cache.get(tuple(sorted(names[:-1]))) if names else None
        if start is None and within:
            start = cache[max(within, key=len)]
        # the effects this refit adds are watched: an estimate leaving the plausible range ends it
        new = set(names) - set(start.effects if start is not None else ())
        watch = LeavingPlausible(new, self.config.watch_patience) if new and self.watching else None
        return fit_model(self.rec, dataclasses.replace(self.model, effects=effects), progress=progress, start=start,
                         evidence_tol=self.config.evidence_tol, watch=watch)

    def fitted(self, names: tuple[str, ...]) -> Fit:
        """The fit with ``names`` added, from :attr:`cache` or fitted now.

        Raises:
            Exception: what a worker's fit of it raised (:meth:`fit_all`).
        """
        key = tuple(sorted(names))
        if key in self.fit_errors:
            raise self.fit_errors.pop(key)
        if key not in self.cache:
            label = "nominal" if not names else "+ " + " + ".join(names)
            t0 = time.perf_counter()
            self.cache[key] = self.fit_with(names, progress=self.cb(label))
            self.say(label, f"fitted {label if names else 'the nominal model'}", t0)
        return self.cache[key]

    def snapshot(self, fit: Fit) -> Snapshot:
        """:func:`~flexforce.compare.diagnostics.fitting.snapshot` of ``fit`` with the config's windows."""
        c = self.config
        return snapshot(self.rec, fit, c.window, c.alpha, c.skip, c.calibrated)

    def check(self, base: Fit, fit: Fit) -> dict | None:
        """:func:`~flexforce.compare.diagnostics.checks.reference_check` of ``fit`` against ``base``."""
        return reference_check(self.rec, base, fit, self.config.skip, self.checked)

    def fit_all(self, names_list: list[tuple[str, ...]], views: list[tuple[str, ...]] | None = None) -> None:
        """Fit the models not fitted yet, in :attr:`jobs` worker processes (into :attr:`cache`; a
        failure into :attr:`fit_errors`, raised by :meth:`fitted`).  With ``views`` (fitted effect
        sets), their before/after views and the nominal fit's are formed beside them, as more tasks
        (the last to be taken): the second look's trials, the diagnosis's last fits, then share the
        processes with the views that would follow them.  Not earlier: a view formed beside a
        round's refits lengthens that round when it does not fit in a process they leave idle.  A
        view that fails is left to the end, formed again there, where it raises."""
        from flexforce.compare.runner import fork_map

        todo = [n for n in dict.fromkeys(names_list) if tuple(sorted(n)) not in self.cache]
        wanted = [(), *(tuple(sorted(v)) for v in views)] if views else []
        shown = [k for k in dict.fromkeys(wanted) if k in self.cache and k not in self.side]
        if self.jobs == 1 or not todo or len(todo) + len(shown) < 2:
            return
        tasks: list[Callable[[], Any]] = [functools.partial(self.fit_with, n) for n in todo]
        tasks += [functools.partial(self.snapshot, self.cache[k]) for k in shown]
        for i, ok, value, seconds in fork_map(lambda task: task(), tasks, self.jobs):
            if i >= len(todo):
                if ok:
                    self.side[shown[i - len(todo)]] = value
                continue
            key = tuple(sorted(todo[i]))
            if ok:
                self.cache[key] = value
                label = "+ " + " + ".join(todo[i])
                if self.call is not None:
                    self.call(label, 1.0, f"fitted {label} [{seconds:.1f} s, "
                                          f"{time.perf_counter() - self.t_start:.0f} s in all]")
            else:
                self.fit_errors[key] = value
            self.fit_seconds[key] = seconds
