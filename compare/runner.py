"""Run the EKF and the smoothers on the same recording and compare them like for like."""

from __future__ import annotations

import math
import os
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from flexforce import processes
from flexforce.compare.metrics import (
    FRICTION_MU,
    LOWPASS_HZ,
    LOWPASS_ORDER,
    RMSE_KEYS,
    TRANSITION_S,
    Metrics,
    evaluate,
    force_band,
    lowpass_key,
    phase_metrics,
    reference_checks,
    violations,
)
from flexforce.errors import ConfigError, FlexforceError

if TYPE_CHECKING:
    from flexforce.compare.crb import CramerRao

DEFAULT_ESTIMATORS = ("ekf", "fixed-lag", "batch")


REJECTED_LISTED = 200
"""Sensor samples left out or down-weighted listed per estimator in summary.json (all are counted)."""


def summary_key(name: str) -> str:
    """``fixed-lag`` -> ``fixed_lag`` (the keys of summary.json)."""
    return name.replace("-", "_")


class PeakMemory:
    """Peak growth of the process's resident memory during a block, sampled every ``period`` s.

    Reads /proc/self/statm (Linux); gives None where it is not available.  Sampling misses
    allocations that live shorter than the period, not the sustained peak of an estimator.
    """

    def __init__(self, period: float = 0.005):
        self.period = period
        self.peak_mb: float | None = None
        self._page = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096

    def _rss(self) -> int | None:
        try:
            with open("/proc/self/statm") as f:
                return int(f.read().split()[1]) * self._page
        except OSError:
            return None

    def __enter__(self):
        self._start = self._rss()
        self._peak = self._start
        self._stop = threading.Event()
        if self._start is not None:
            self._thread = threading.Thread(target=self._run, daemon=True)
            self._thread.start()
        return self

    def _run(self):
        while not self._stop.wait(self.period):
            rss = self._rss()
            if rss is not None and rss > self._peak:
                self._peak = rss

    def __exit__(self, *exc):
        self._stop.set()
        if self._start is not None:
            self._thread.join()
            rss = self._rss()
            self._peak = max(self._peak, rss or 0)
            self.peak_mb = (self._peak - self._start) / 2**20
        return False


@dataclass
class Comparison:
    """Estimates and metrics of several estimators on one recording."""

    recording: dict
    """Description of the recording (robot, scenario, duration, hidden effects)."""
    estimates: dict = field(default_factory=dict)
    """summary key -> Estimate."""
    metrics: dict[str, Metrics] = field(default_factory=dict)
    failures: dict[str, str] = field(default_factory=dict)
    """summary key -> error message of an estimator that failed."""
    crb: CramerRao | None = None
    """:class:`flexforce.compare.crb.CramerRao` of the recording (simulated data only)."""
    baselines: dict[str, Metrics] = field(default_factory=dict)
    """summary key -> metrics of a row without estimation (``leg_odometry``, ``weight_equal``), kept
    apart from the estimators: it has no timing, no covariance and no NEES."""
    baseline_estimates: dict = field(default_factory=dict)
    """summary key -> the baseline's Estimate-like object."""
    peers: dict[str, Metrics] = field(default_factory=dict)
    """summary key -> metrics of a peer: another project's estimator of the same inputs
    (:data:`flexforce.compare.peers.PEERS`, GTSAM's legged estimators: tilt and velocities, no forces),
    kept apart from the estimators and the baselines so that their rows and the headline stay
    flexforce's own."""
    peer_estimates: dict = field(default_factory=dict)
    """summary key -> the peer's Estimate."""
    reference: dict | None = None
    """The F/T reference held against the rigid robot's dynamics, from the recording alone
    (:func:`flexforce.compare.metrics.reference_checks`): summary.json's ``reference_checks``; None
    with ground truth or without F/T."""
    warnings: list[dict] = field(default_factory=list)
    """The sensor faults recognised in the recording's data (``Recording.meta['sensor_faults']``,
    :mod:`flexforce.datasets.sensorcheck`): summary.json's ``warnings`` when there are any."""

    def summary(self) -> dict:
        """The numbers of the report's table (summary.json)."""
        out: dict[str, Any] = {"recording": self.recording,
                               "estimators": {k: m.to_dict() for k, m in self.metrics.items()}}
        if self.baselines:
            out["baselines"] = {k: m.to_dict() for k, m in self.baselines.items()}
        if self.peers:
            out["peers"] = {k: m.to_dict() for k, m in self.peers.items()}
        if self.failures:
            out["failures"] = self.failures
        if self.warnings:
            out["warnings"] = self.warnings
        if self.reference:
            out["reference_checks"] = self.reference
        rows = [*self.metrics.values(), *self.baselines.values()]
        if any(m.per_phase or m.violations for m in rows):
            out["definitions"] = DEFINITIONS
        ekf = self.metrics.get("ekf")
        if ekf is not None:
            rel = {}
            for key, m in self.metrics.items():
                if key == "ekf":
                    continue
                rel[key] = {k: (num / den if (num := m.rmse.get(k)) is not None and (den := ekf.rmse.get(k))
                                else None)
                            for k in RMSE_KEYS}
            out["rmse_relative_to_ekf"] = rel
        if self.crb is not None:
            out["cramer_rao"] = {
                "rmse_bound": self.crb.rmse_bound,
                "rmse_relative_to_bound": {k: self.crb.efficiency(m.rmse) for k, m in self.metrics.items()},
            }
        return out


DEFINITIONS = {
    "phases": {
        "all": "every sample after the skipped start",
        "single_support": "one contact in force, not within the transition window of a contact switch",
        "double_support": "two or more contacts in force, not within the transition window of a contact switch",
        "transition": f"within ±{TRANSITION_S * 1000:g} ms of a contact switch (a contact made or released)",
    },
    "foot_vertical_force_N": "each contact's normal force in its own frame (zero when released) against the "
                             "reference, RMSE over every (step, contact)",
    "total_vertical_force_N": "sum over the contacts of the normal force against the reference's sum",
    "rotation_rad": "rotation error (on real logs: tilt of the base against motion capture)",
    lowpass_key(): f"both the estimate and the reference low-passed first: zero-phase Butterworth, order "
                   f"{LOWPASS_ORDER} forward and backward (scipy sosfiltfilt), cut-off {LOWPASS_HZ:g} Hz",
    "violations": f"over the (step, contact) pairs in force after the skipped start, contact frames: normal force "
                  f"below 0 N; outside the friction cone |F_xy| <= mu F_z, mu the robot's friction or {FRICTION_MU:g} "
                  "(a negative normal force included); CoP outside the sole. The estimators report wrenches limited to "
                  "what a contact can carry; contact_law: the same checks on the contact law's wrenches before the "
                  "limit (wrench + wrench_excess)",
}
"""summary.json's ``definitions``: what the per-phase, low-passed and violation numbers mean."""


def _display(key: str) -> str:
    """A row's name in a sentence: ``ekf`` -> ``EKF``, ``leg_odometry`` -> ``leg-odometry``."""
    return "EKF" if key == "ekf" else key.replace("_", "-")


HEADLINE_QUANTITIES = (
    ("Per-foot vertical force", lambda m: ((m.get("per_phase") or {}).get("all") or {}).get("rmse", {})
     .get("foot_vertical_force_N"), 1.0, "N"),
    ("Total vertical force", lambda m: ((m.get("per_phase") or {}).get("all") or {}).get("rmse", {})
     .get("total_vertical_force_N"), 1.0, "N"),
    ("Tilt", lambda m: (m.get("rmse") or {}).get("rotation_rad"), 1e3, "mrad"),
)
"""(quantity, its RMSE in a summary row or None, scale, unit) of the headline's sentences."""


TIE = 1e-3
"""Relative difference of two rows' RMSEs below which :func:`headline` names them together."""


def headline(summary: dict) -> list[str]:
    """One sentence per quantity (:data:`HEADLINE_QUANTITIES`) naming the best estimator and
    whether it beats the best baseline, by how much, from the numbers of ``summary``
    (:meth:`Comparison.summary`); a quantity no row has is left out.  On simulated data the
    rotation is the full rotation error, so ``Tilt`` reads ``Rotation``."""
    estimators = summary.get("estimators") or {}
    baselines = summary.get("baselines") or {}
    out = []
    for name, value, scale, unit in HEADLINE_QUANTITIES:
        if name == "Tilt" and (summary.get("recording") or {}).get("has_truth"):
            name = "Rotation"

        def best(rows: dict, value=value) -> tuple[str, float] | None:
            """(name, RMSE) of the lowest row; rows within :data:`TIE` of it named together."""
            scored = [(k, v) for k, m in rows.items() if (v := value(m)) is not None]
            if not scored:
                return None
            low = min(v for _, v in scored)
            tied = [_display(k) for k, v in scored if v <= low * (1 + TIE)]
            return " and ".join(tied), low

        e, b = best(estimators), best(baselines)
        if e is None and b is None:
            continue

        def num(v: float, scale=scale, unit=unit) -> str:
            return f"{v * scale:.3g} {unit}"

        if b is None:
            assert e is not None
            out.append(f"{name}: {e[0]} {'are the best estimators' if ' and ' in e[0] else 'is the best estimator'} "
                       f"({num(e[1])}); no baseline to compare.")
            continue
        plural = " and " in b[0]
        if e is None:
            out.append(f"{name}: the {b[0]} baseline{'s are' if plural else ' is'} best ({num(b[1])}); "
                       "no estimator to compare.")
        elif e[1] < b[1]:
            pct = 100.0 * (b[1] - e[1]) / b[1]
            out.append(f"{name}: {e[0]} {'are' if ' and ' in e[0] else 'is'} best ({num(e[1])}), {pct:.0f} % "
                       "better than the best "
                       f"baseline{'s' if plural else ''}, {b[0]} ({num(b[1])}).")
        else:
            pct = 100.0 * (e[1] - b[1]) / b[1] if b[1] > 0 else math.inf
            worse = "no better" if pct < 0.5 else f"{pct:.0f} % worse"
            many = " and " in e[0]
            out.append(f"{name}: the {b[0]} baseline{'s are' if plural else ' is'} best ({num(b[1])}); the best "
                       f"estimator{'s' if many else ''}, {e[0]}, {'are' if many else 'is'} {worse} ({num(e[1])}).")
    return out


def describe(rec) -> dict:
    """Short description of a recording for reports."""
    sc = rec.meta.get("scenario", {})
    return {
        "robot": rec.robot,
        "scenario": sc.get("name"),
        "description": sc.get("description"),
        "samples": rec.n,
        "rate_hz": round(1.0 / rec.dt, 6) if rec.dt else None,
        "duration_s": float(rec.time[-1]) if rec.n else 0.0,
        "hidden_effects": rec.meta.get("hidden_effects", []),
        "has_truth": rec.truth is not None,
        "contacts": list(rec.contact_names),
        **({"window": rec.meta["window"]} if rec.meta.get("window") else {}),
        # the faults flexforce.datasets.sensorcheck found in its data (diagnosis.json's, too)
        **({"sensor_faults": list(rec.meta["sensor_faults"])} if rec.meta.get("sensor_faults") else {}),
    }


def compare(rec, estimators=DEFAULT_ESTIMATORS, model=None, skip: float = 0.5,
            progress: Callable[[str, float], None] | None = None, options: dict | None = None,
            crb: bool = True, baseline: bool = True, peers: bool | None = None,
            model_band: bool = True) -> Comparison:
    """Run each estimator on ``rec`` and evaluate it.

    Args:
        estimators: names for :func:`flexforce.compare.estimators.run_estimator` (a list, or one
            comma-separated string as the command line takes them).
        model: the model every estimator assumes; None: the recording's nominal model, its springs
            checked against toppling (:func:`flexforce.compare.estimators.nominal_model`, which
            raises ConfigError or warns).
        skip: seconds at the start left out of the statistics (filter convergence).
        progress: called with (estimator name, fraction done).
        options: estimator name -> keyword options.
        baseline: add the rows without estimation (:data:`flexforce.compare.baseline.BASELINES`:
            leg odometry, the equal split of the weight).
        peers: add GTSAM's legged estimators as peer rows (:mod:`flexforce.compare.peers`, summary.json's
            ``peers``): None, the cheap ones (:data:`~flexforce.compare.peers.CHEAP_PEERS`); True, all of
            :data:`~flexforce.compare.peers.PEERS`; False, none.  Each runs on the same ``model``, timed
            like the estimators, with its per-phase tilt; options under ``options[peer name]``.  A peer
            that fails is a ``failures`` entry.
        model_band: when the model states its parameters' uncertainty (the robot's
            ``[model_uncertainty]``) and the recording has a force reference, each estimator's
            ``force_band["model"]``: the same coverage with the model band
            (:func:`flexforce.compare.band.model_band`; one run of the estimator per parameter).

    Every row also gets its per-phase and low-passed errors
    (:func:`flexforce.compare.metrics.phase_metrics`) and its physical violations
    (:func:`flexforce.compare.metrics.violations`).
    """
    from flexforce.compare.estimators import nominal_model, run_estimator

    if isinstance(estimators, str):  # "ekf,fixed-lag,batch", as the command line takes them
        estimators = [name.strip() for name in estimators.split(",") if name.strip()]
    rec.validate()
    if model is None:
        model = nominal_model(rec)
    result = Comparison(recording=describe(rec), warnings=list(rec.meta.get("sensor_faults") or []),
                        reference=reference_checks(rec, skip))
    for name in estimators:
        key = summary_key(name)
        cb = (lambda f, _n=name: progress(_n, f)) if progress else None
        t0 = time.perf_counter()
        try:
            with PeakMemory() as mem:
                est = run_estimator(name, rec, model, progress=cb, **(options or {}).get(name, {}))
        except FlexforceError as err:
            result.failures[key] = f"{type(err).__name__}: {err}"
            continue
        if not est.total_time:
            est.total_time = time.perf_counter() - t0
        result.estimates[key] = est
        result.metrics[key] = evaluate(est, rec, skip=skip, peak_memory_mb=mem.peak_mb)
        _contact_checks(result.metrics[key], est, rec, skip, model)
        if model_band:
            _model_band(result, key, name, rec, model, est, skip, (options or {}).get(name))
        chosen = (options or {}).get(name)
        if chosen:
            result.metrics[key].extra["options"] = {k: (v if isinstance(v, bool | int | float | str) else repr(v))
                                                    for k, v in chosen.items()}
        if "foothold" in est.effects:
            result.metrics[key].extra["footholds"] = est.effects["foothold"].get("summary")
        rejected = est.meta.get("rejected")
        if rejected is not None:
            from flexforce.datasets.faults import summarize

            result.metrics[key].extra["rejected"] = {
                "count": len(rejected), "summary": summarize(rejected) if rejected else "",
                "samples": rejected[:REJECTED_LISTED], "listed": min(len(rejected), REJECTED_LISTED)}
    if baseline:
        from flexforce.compare.baseline import BASELINES

        for name, make in BASELINES.items():
            key = summary_key(name)
            est = make(rec)
            m = evaluate(est, rec, skip=skip)
            m.kind = "baseline"
            m.time_per_step = {}
            m.total_time = None
            _contact_checks(m, est, rec, skip, model)
            result.baseline_estimates[key] = est
            result.baselines[key] = m
    if peers is None or peers:
        _add_peers(result, rec, model, skip, all_peers=bool(peers), options=options)
    if crb and rec.truth is not None:
        from flexforce.compare.crb import cramer_rao

        try:
            result.crb = cramer_rao(rec, model, skip=skip)
        except FlexforceError as err:
            result.failures["cramer_rao"] = f"{type(err).__name__}: {err}"
    return result


def _model_band(result: Comparison, key: str, name: str, rec, model, est, skip: float, options) -> None:
    """``force_band["model"]`` of row ``key`` (:func:`compare`'s ``model_band``)."""
    from flexforce.compare.band import model_band

    m = result.metrics[key]
    if not m.force_band or getattr(model, "model_uncertainty", None) is None:
        return
    try:
        band = model_band(name, rec, model, est, options)
    except FlexforceError as err:
        result.failures[f"{key}_model_band"] = f"{type(err).__name__}: {err}"
        return
    if band is None:
        return
    entry = force_band(est, rec, skip=skip, sigma=band.sigma)
    entry.pop("per_contact", None)
    entry.update(variance_factor=round(band.variance_factor, 3), components_N=band.components, stds=band.stds)
    m.force_band["model"] = entry


def _add_peers(result: Comparison, rec, model, skip: float, all_peers: bool, options: dict | None) -> None:
    """The peer rows of ``result`` (:func:`compare`'s ``peers``): metrics and per-phase tilt, no
    violation checks (a peer estimates no forces)."""
    from flexforce.compare.peers import CHEAP_PEERS, PEERS, run_peer

    for name in (PEERS if all_peers else CHEAP_PEERS):
        key = summary_key(name)
        try:
            with PeakMemory() as mem:
                est = run_peer(name, rec, model, **(options or {}).get(name, {}))
        except FlexforceError as err:
            result.failures[key] = f"{type(err).__name__}: {err}"
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # the NaN wrenches' empty means, blanked below
            m = evaluate(est, rec, skip=skip, peak_memory_mb=mem.peak_mb)
        m.kind = "peer"
        phase_metrics(m, est, rec, skip=skip)
        _without_forces(m)
        result.peer_estimates[key] = est
        result.peers[key] = m


PEER_KEYS = ("rotation_rad", "translation_m", "angular_velocity_rad_s", "linear_velocity_m_s", "hand_m")
"""The errors a peer row keeps: those of the pose and velocities; its force errors are left out (None)."""


def _without_forces(m: Metrics) -> None:
    """Blank the force errors of a peer's metrics: a peer estimates no wrench (NaN), and the contact
    frames' comparison reads a contact out of force as zero, which would score it as an estimate."""
    for group in (m.rmse, m.max):
        for k in group:
            if k not in PEER_KEYS:
                group[k] = None
    m.errors = {k: e for k, e in m.errors.items() if k in PEER_KEYS}
    m.per_contact, m.contact_errors = {}, {}
    m.references = {k: v for k, v in m.references.items() if k in PEER_KEYS}
    for entry in m.per_phase.values():
        entry["rmse"] = {k: (v if k == "rotation_rad" else None) for k, v in entry["rmse"].items()}
        for k in [k for k in entry if k not in ("samples", "rmse")]:
            del entry[k]


def _contact_checks(m: Metrics, est, rec, skip: float, model=None) -> None:
    """Per-phase and low-passed errors and physical violations of ``est`` into ``m`` (where the
    recording has contacts; the CoP judged against the ``model``'s soles when it gives them)."""
    phase_metrics(m, est, rec, skip=skip)
    if rec.contact_names:
        m.violations = violations(est, rec, skip=skip, mu=getattr(model, "friction", None) or FRICTION_MU,
                                  soles=tuple(getattr(model, "soles", ()) or ()))
        m.force_band = force_band(est, rec, skip=skip)


AUTO_JOBS = "auto"
"""``jobs="auto"`` (``--jobs auto``, the default of ``flexforce diagnose``): as many worker
processes as this process may use cores, fewer when the memory available would not hold them
(:func:`resolve_jobs`)."""

WORKER_MEMORY = 1 << 30
"""Memory, bytes, assumed for each worker process of ``jobs="auto"`` at least (1 GiB: one
diagnosis of the 20 s iCub sway peaks at 0.83 GB per process); a forked worker is assumed to
need as much as this process holds when it forks, if that is more."""


def check_jobs(jobs) -> None:
    """Raise a :class:`ConfigError` unless ``jobs`` is a positive number of worker processes or
    ``"auto"`` (:data:`AUTO_JOBS`)."""
    if jobs == AUTO_JOBS:
        return
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ConfigError(f"jobs = {jobs!r}; expected a positive number of worker processes (1: in this process) "
                          f"or {AUTO_JOBS!r} (one per usable core, as memory allows)")


def cpu_quota(path: str = "/sys/fs/cgroup/cpu.max") -> float | None:
    """The cores' worth of CPU time a cgroup (v2) quota allows this process (``cpu.max``: quota
    and period, e.g. ``200000 100000`` for 2; ``max`` for none), as in a container started with
    ``--cpus``; None without a quota or where it cannot be read."""
    try:
        with open(path) as f:
            quota, period = f.read().split()[:2]
        return None if quota == "max" else max(float(quota) / float(period), 0.0)
    except (OSError, ValueError):
        return None


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity where the platform tells it (else the
    machine's count), no more than a container's CPU quota (:func:`cpu_quota`, rounded up), at
    least 1."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    quota = cpu_quota()
    if quota is not None:
        n = min(n, math.ceil(quota))
    return max(1, n)


def available_memory() -> int | None:
    """Memory available to new processes without swapping, bytes (``MemAvailable`` of
    /proc/meminfo); None where it is not known."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def resident_memory() -> int | None:
    """This process's resident memory, bytes (/proc/self/statm); None where it is not known."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return None


def resolve_jobs(jobs, items: int | None = None, per_worker: int | None = None) -> int:
    """The number of worker processes ``jobs`` stands for: itself when it is a number; for
    ``"auto"`` the usable cores (:func:`usable_cores`), no more than 80 % of the available memory
    holds at ``per_worker`` bytes each (default: :data:`WORKER_MEMORY` or this process's resident
    size, the larger), and no more than ``items``; at least 1.

    Raises:
        ConfigError: ``jobs`` is neither a positive integer nor ``"auto"``.
    """
    check_jobs(jobs)
    if jobs != AUTO_JOBS:
        return int(jobs)
    n = usable_cores()
    avail = available_memory()
    need = per_worker if per_worker is not None else max(WORKER_MEMORY, resident_memory() or 0)
    if avail is not None and need > 0:
        n = min(n, int(0.8 * avail // need))
    if items is not None:
        n = min(n, items)
    return max(1, n)


_libc_prctl = processes.libc_prctl
"""libc's ``prctl`` getter (:func:`flexforce.processes.libc_prctl`; replaced in a test to take the
path of a platform without it)."""


def _exit_with_parent(parent_pid: int, initializer: Callable[..., None] | None = None, initargs: tuple = ()) -> None:
    """A worker process's initializer: the worker ends when its parent ``parent_pid`` dies
    (:func:`flexforce.processes.exit_with_parent`), then ``initializer(*initargs)`` when given."""
    processes.exit_with_parent(parent_pid, _libc_prctl())
    if initializer is not None:
        initializer(*initargs)


def run_jobs(fn: Callable[[Any], Any], items: list, jobs: int | str = 1, initializer: Callable[..., None] | None = None,
             initargs: tuple = ()) -> Iterator[Any]:
    """``fn(item)`` for every item, yielded in the items' order; in ``jobs`` worker processes when
    ``jobs`` > 1 (:class:`concurrent.futures.ProcessPoolExecutor`, fresh interpreters: ``spawn``).

    ``fn`` and the items must pickle (a module-level function, ``functools.partial`` of one).  Each
    result is computed exactly as with ``jobs=1``, only elsewhere; a worker's exception is raised
    here, for the first item that failed, and the items not started yet are cancelled.

    ``jobs="auto"``: :func:`resolve_jobs` (each spawned worker assumed to need
    :data:`WORKER_MEMORY`).  ``initializer(*initargs)``, when given, runs first in each worker.
    The workers end when this process does, even killed (:func:`_exit_with_parent`).

    Raises:
        ConfigError: ``jobs`` is not a positive integer or ``"auto"``.
    """
    jobs = resolve_jobs(jobs, len(items), WORKER_MEMORY)
    if jobs == 1 or len(items) <= 1:
        for item in items:
            yield fn(item)
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=min(jobs, len(items)), mp_context=multiprocessing.get_context("spawn"),
                             initializer=_exit_with_parent, initargs=(os.getpid(), initializer, initargs)) as pool:
        futures = [pool.submit(fn, item) for item in items]
        try:
            for future in futures:
                yield future.result()
        finally:
            for future in futures:
                future.cancel()


_FORK_TASKS: list = []
"""The (function, items) of the running :func:`fork_map` calls, innermost last: what their forked
workers inherit (nothing is pickled on the way there)."""


def _timed_call(fn: Callable[[Any], Any], item) -> tuple[bool, Any, float]:
    """``(ok, fn(item) or its exception, seconds)``."""
    t0 = time.perf_counter()
    try:
        return True, fn(item), time.perf_counter() - t0
    except Exception as err:  # noqa: BLE001 -- returned, as from a worker
        return False, err, time.perf_counter() - t0


def _fork_task() -> tuple[int, bool, Any, float] | None:
    """In a worker: the next item of the innermost :func:`fork_map` no process has claimed yet
    (its shared counter), as (index, ok, the pickled result or the exception, seconds); None once
    every item is claimed.  A result that does not pickle comes back as None (computed again in
    the parent)."""
    import pickle

    fn, items, claim = _FORK_TASKS[-1]
    i = claim()  # from the front
    if i is None:
        return None
    ok, value, seconds = _timed_call(fn, items[i])
    if not ok:
        try:
            pickle.dumps(value)
        except Exception:  # noqa: BLE001 -- an exception that does not pickle: its text
            value = RuntimeError(f"{type(value).__name__}: {value}")
        return i, False, value, seconds
    try:
        data = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception:  # noqa: BLE001 -- e.g. a user's effect holding a lambda
        data = None
    return i, True, data, seconds


def fork_map(fn: Callable[[Any], Any], items: list, jobs: int | str = 1) -> Iterator[tuple[int, bool, Any, float]]:
    """``fn(item)`` for every item, as ``(index, ok, result or exception, seconds)`` in the order
    they finish; in ``jobs`` processes when ``jobs`` > 1 (and the platform forks): this one and
    ``jobs - 1`` forked workers, the workers taking the items from the first, this process from
    the last, each item once.

    Unlike :func:`run_jobs` nothing is sent to the workers: they are forked with ``fn`` and the
    items in memory (a closure over a fitted model is fine), and only the results are pickled
    back -- one recording's candidates on two cores.  This process works through the items too
    rather than wait: it holds what ``fn`` has already formed and touched, where a fresh fork
    first pays a page fault for every page it writes (on the iCub sway a refit took 7.0 s here,
    7.3 s in a fork, with 133 000 more page faults), and one fork fewer is made.  Each result is
    what ``jobs=1`` computes; a result that does not pickle is computed again here.  An exception
    of ``fn`` is returned, not raised (``ok`` False).  ``jobs="auto"``: :func:`resolve_jobs` when
    called (a worker assumed to need what this process then holds, at least :data:`WORKER_MEMORY`).
    The workers end when this process does, even killed (:func:`_exit_with_parent`).

    Raises:
        EstimatorError: a worker process ended abruptly (killed, out of memory).
    """
    import multiprocessing
    import pickle

    jobs = resolve_jobs(jobs, len(items))
    if jobs <= 1 or len(items) <= 1 or "fork" not in multiprocessing.get_all_start_methods():
        for i, item in enumerate(items):
            yield (i, *_timed_call(fn, item))
        return
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    from flexforce.errors import EstimatorError

    ctx = multiprocessing.get_context("fork")
    # the items not taken yet are [front, back): the workers (forked below, sharing this array)
    # take from the front, this process from the back -- the first items, often the longest (a
    # caller puts them first), start at once in a worker, and this process, working through the
    # shorter ones, passes on the workers' results between two of its own
    bounds = ctx.Array("i", [0, len(items)])

    def claim(back: bool = False) -> int | None:
        with bounds.get_lock():
            front, end = bounds[0], bounds[1]
            if front >= end:
                return None
            if back:
                bounds[1] = end - 1
                return end - 1
            bounds[0] = front + 1
            return front

    def received(future) -> tuple[int, bool, Any, float] | None:
        got = future.result()
        if got is None:
            return None
        i, ok, value, seconds = got
        if ok and value is None:
            ok, value, seconds = _timed_call(fn, items[i])
        elif ok:
            value = pickle.loads(value)
        return i, ok, value, seconds

    _FORK_TASKS.append((fn, items, claim))
    try:
        workers = min(jobs, len(items)) - 1
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_exit_with_parent,
                                 initargs=(os.getpid(),)) as pool:
            # one request per item: a worker's request takes the next item left, or none
            futures = [pool.submit(_fork_task) for _ in items]
            pending = list(futures)
            try:
                while (mine := claim(back=True)) is not None:
                    yield (mine, *_timed_call(fn, items[mine]))
                    done = [f for f in pending if f.done()]
                    pending = [f for f in pending if f not in done]
                    for future in done:
                        if (got := received(future)) is not None:
                            yield got
                for future in as_completed(pending):
                    if (got := received(future)) is not None:
                        yield got
            except BrokenProcessPool as err:
                raise EstimatorError(f"a worker process of jobs = {jobs} ended abruptly ({err}: out of memory?); "
                                     "expected it to return its result: run with jobs = 1") from None
            finally:
                with bounds.get_lock():  # stopped early (an error, an interrupt): no more items taken
                    bounds[0] = bounds[1]
                for future in futures:
                    future.cancel()
    finally:
        _FORK_TASKS.pop()


def aggregate(comparisons: list[Comparison]) -> dict:
    """Mean and spread (standard deviation, min, max) of every number over several recordings: the
    same for two runs on the same inputs (no timing or memory:
    :func:`flexforce.compare.reports.comparison.aggregate_timings`)."""
    out: dict[str, Any] = {"recordings": [c.recording for c in comparisons], "estimators": {}}
    groups = [("estimators", lambda c: c.metrics)]
    if any(c.baselines for c in comparisons):
        out["baselines"] = {}
        groups.append(("baselines", lambda c: c.baselines))
    if any(c.peers for c in comparisons):
        out["peers"] = {}
        groups.append(("peers", lambda c: c.peers))
    for group, rows in groups:
        for key in sorted({k for c in comparisons for k in rows(c)}):
            out[group][key] = _aggregate_rows([rows(c)[key] for c in comparisons if key in rows(c)])
    return out


def _aggregate_rows(ms: list[Metrics]) -> dict:
    """Mean and spread of one row's numbers over several recordings."""
    entry: dict[str, Any] = {"count": len(ms), "rmse": {}, "rmse_std": {}, "rmse_min": {}, "rmse_max": {}}
    for k in RMSE_KEYS:
        vals = np.array([m.rmse.get(k) for m in ms if m.rmse.get(k) is not None], dtype=float)
        if vals.size:
            entry["rmse"][k] = float(vals.mean())
            entry["rmse_std"][k] = float(vals.std())
            entry["rmse_min"][k] = float(vals.min())
            entry["rmse_max"][k] = float(vals.max())
        else:
            entry["rmse"][k] = entry["rmse_std"][k] = entry["rmse_min"][k] = entry["rmse_max"][k] = None
    nees = [m.nees for m in ms if m.nees is not None]
    entry["nees"] = float(np.mean(nees)) if nees else None
    entry["nees_std"] = float(np.std(nees)) if nees else None
    return entry
