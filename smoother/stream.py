r"""Fixed-lag smoothing of a stream: parts of a recording in, estimates out as they leave the window.

:class:`FixedLagStream` is the online form of :func:`flexforce.smoother.run_fixed_lag`: the
recording arrives in consecutive parts (:class:`~flexforce.datasets.recording.Recording` objects
on one time grid, any length, e.g. from :class:`flexforce.datasets.io.stream.StreamImporter` as the
messages of a robot come in), and every :meth:`FixedLagStream.push` returns the estimate of the
steps that have left the window since the previous call, an :class:`Estimate` over those steps
only.  Memory is bounded whatever the stream's length: the smoother keeps its window, and the
stream keeps only the steps still needed (the window and the steps not yet reported).

The estimate of a step is the offline fixed-lag smoother's (same window, factors, noise and
update order; the part boundaries change nothing, tested to 1e-9): each step is reported once
``lag`` of later data has been smoothed in (plus up to ``report_every - 1`` samples, and with
``config.block`` > 1 up to ``block - 1`` samples more: the samples wait for their block).  The
noise is derived from the stream's first sample, as offline from the recording's first.

Differences from the offline :class:`Estimate`: each returned estimate holds its own steps only,
so the integration residual of its last step (the factor to the next step, in the next part) is
NaN; its times (``Estimate.time``) start at its own first step (``t_ns`` is absolute); the
sensor samples left out or down-weighted (``meta["rejected"]``, times from the stream's first
step) are announced once, in :meth:`FixedLagStream.finish`'s warning.

Not streamed: estimated footholds (their episodes' nominal placements are held from the
episode's first step, which the offline smoother reads ahead) and the gtsam backend.
"""

from __future__ import annotations

import math
import time
import warnings
from array import array

import numpy as np

from flexforce.datasets import faults
from flexforce.datasets.estimate import Estimate
from flexforce.datasets.recording import Recording, concat_recordings
from flexforce.errors import ConfigError, DataError
from flexforce.options import require_config
from flexforce.smoother.fixed_lag import FixedLagConfig, FixedLagSmoother
from flexforce.smoother.linearize import Trajectory
from flexforce.smoother.problem import Problem
from flexforce.smoother.result import make_estimate

__all__ = ["FixedLagStream", "run_stream"]


class UpdateTimes:
    """A distribution of durations in constant memory: counts in log-spaced bins (ratio 1.002,
    1e-7 to 1e2 s: 83 kB), so that a quantile is within 0.1 % of the sample's (the bin's
    geometric middle), whatever the stream's length; the count, sum and maximum exact."""

    LO, HI, RATIO = 1e-7, 1e2, 1.002

    def __init__(self):
        self._log_ratio = np.log(self.RATIO)
        self.bins = np.zeros(int(np.ceil(np.log(self.HI / self.LO) / self._log_ratio)) + 2, dtype=np.int64)
        self.count = 0
        self.total = 0.0
        self.max = 0.0

    def add(self, seconds: float) -> None:
        seconds = float(seconds)
        x = min(max(seconds, self.LO), self.HI)
        self.bins[int(math.log(x / self.LO) / self._log_ratio)] += 1
        self.count += 1
        self.total += seconds
        self.max = max(self.max, seconds)

    def quantile(self, q: float) -> float:
        """The ``q`` quantile (lower: the smallest value with at least ``q`` of the count at or below it)."""
        if self.count == 0:
            return float("nan")
        i = int(np.searchsorted(np.cumsum(self.bins), max(1, int(np.ceil(q * self.count)))))
        return min(self.LO * self.RATIO ** (i + 0.5), self.max)


class FixedLagStream:
    """Fixed-lag smoother fed part by part (module docstring).

    Args:
        model: the ModelConfig (contact parameters, sensor noise, ``use_ft``, effects).
        config: a :class:`FixedLagConfig` (window backend; ``footholds`` False).
        covariance: per-step marginal covariances in the returned estimates (``config.covariance``
            by default); False saves their extraction and memory.

    Use::

        stream = FixedLagStream(model)
        for part in parts:                 # Recordings, consecutive on one grid
            est = stream.push(part)        # the steps that left the window (None: none yet)
        est = stream.finish()              # the rest, smoothed with what there is
    """

    def __init__(self, model, config: FixedLagConfig | None = None, covariance: bool | None = None):
        config = FixedLagConfig() if config is None else config
        require_config(config, FixedLagConfig, "fixed-lag stream")
        if config.backend != "window":
            raise ConfigError(f"the fixed-lag stream runs the 'window' backend; got backend = {config.backend!r} "
                              "(the gtsam backend is offline only: run_fixed_lag)")
        if config.footholds:
            raise ConfigError("the fixed-lag stream holds the footholds given by the local frame; footholds = True "
                              "(estimated footholds) needs the whole recording: run_fixed_lag")
        self.model = model
        self.config = config
        self.covariance = config.covariance if covariance is None else bool(covariance)
        self.first: Problem | None = None
        self.fls: FixedLagSmoother | None = None
        self.segment: Recording | None = None
        """The steps kept: from :attr:`segment_offset` to the newest pushed."""
        self.segment_offset = 0
        self.n = 0
        """Steps pushed so far."""
        self.t0_ns: int | None = None
        self._switch_ns: set[int] = set()  # contact switches seen (ns), for the rows still to report
        self.update_time = array("d")
        """Wall-clock time of the update of each step not yet reported, s, from step
        :attr:`update_time_offset` on (with ``config.block`` > 1 each update's time shared among
        its samples); the reported steps' times leave with their estimate (``time_per_step``)."""
        self.update_time_offset = 0
        self.update_times = UpdateTimes()
        """The update times' distribution (one per ``config.block`` samples), in constant memory."""
        self.samples_updated = 0
        self.cov_time = 0.0
        self.rejected: list[dict] = []
        self._rows: list[tuple] = []
        self._finished = False

    # ------------------------------------------------------------------------------------------
    @property
    def lag_steps(self) -> int:
        return self.fls.lag_steps if self.fls is not None else 0

    def _sink(self, j, R, q, W, e, P) -> None:
        self._rows.append((j, R, q, W, e, P))

    def push(self, part: Recording) -> Estimate | None:
        """Add the next part of the stream (steps after the previous part's, on its grid) and run
        one update per step; return the estimate of the steps that left the window, or None.

        Raises:
            DataError: the part does not continue the stream (time not after the last step, another
                period, other contacts or robot).
            EstimatorError: the smoother failed (a non-finite estimate, a system not positive
                definite), naming the step.
        """
        if self._finished:
            raise DataError("the fixed-lag stream is finished; expected no part after finish()")
        if not isinstance(part, Recording):
            raise DataError(f"a part of the stream must be a Recording; got {type(part).__name__}")
        if part.n == 0:
            return None
        if self.segment is None:
            segment = part
            self.t0_ns = int(part.t_ns[0])
        else:
            self._check_continues(part)
            segment = concat_recordings(self.segment, part)
        start = self.n
        if self.first is None:
            if segment.n < Recording.MIN_SAMPLES:  # the noise and the first-step prior need a few samples
                self.segment = segment
                self.n += part.n
                return None
            prob = Problem.build(segment, self.model, self.config.rule)
            prob.weight_cap = {}
            self.first = prob
            self.fls = FixedLagSmoother(prob, self.config.lag, relinearize=self.config.relinearize,
                                        covariance=self.covariance, report_every=self.config.report_every,
                                        sink=self._sink, block=self.config.block,
                                        compiled=self.config.compiled)
            start = 0
        else:
            prob = Problem.build(segment, self.model, self.config.rule, part_of=self.first,
                                 offset=self.segment_offset)
            assert self.fls is not None
            self.fls.set_problem(prob)
        self.segment = segment
        self._note_switches(segment)
        self.n = self.segment_offset + segment.n
        self._run(start, self.n)
        est = self._collect()
        self._trim()
        return est

    def finish(self) -> Estimate | None:
        """Smooth the steps still in the window with the data there is, return their estimate and
        announce (one warning) the sensor samples the whole stream left out or down-weighted."""
        if self._finished:
            return None
        self._finished = True
        if self.fls is None:
            if self.segment is None:
                return None
            self.segment.require_samples()  # raises: fewer samples than the estimators need
        assert self.fls is not None
        self.fls.finish()
        self._record()
        est = self._collect()
        faults.warn_summary("fixed_lag", self.rejected, stacklevel=3)
        return est

    # ------------------------------------------------------------------------------------------
    def _check_continues(self, part: Recording) -> None:
        seg = self.segment
        assert seg is not None
        if tuple(part.contact_names) != tuple(seg.contact_names) or part.robot != seg.robot:
            raise DataError(f"part of the stream is of robot {part.robot!r} with contacts {list(part.contact_names)}; "
                            f"expected {seg.robot!r} with {list(seg.contact_names)}")
        last = int(seg.t_ns[-1])
        period = int(round(self.first.dt * 1e9)) if self.first is not None else int(np.median(np.diff(seg.t_ns))) \
            if seg.n > 1 else None
        first = int(part.t_ns[0])
        if first <= last:
            raise DataError(f"part of the stream starts at t_ns = {first}, not after the previous step "
                            f"({last}); expected parts in time order")
        if period is not None and abs((first - last) - period) > 0.01 * period:
            raise DataError(f"part of the stream starts {(first - last) * 1e-9:.6f} s after the previous step; "
                            f"expected one period ({period * 1e-9:.6f} s): parts must be consecutive on one grid")

    def _run(self, k0: int, k1: int) -> None:
        fls = self.fls
        assert fls is not None
        for _ in range(k0, k1):
            fls.step()
            self._record()

    def _record(self) -> None:
        fls = self.fls
        assert fls is not None
        if fls.last_updated:
            self.update_times.add(fls.last_update_time)
            share = fls.last_update_time / fls.last_updated
            self.update_time.extend([share] * fls.last_updated)
            self.samples_updated += fls.last_updated
            fls.last_updated = 0
        self.cov_time += fls.last_cov_time
        fls.last_cov_time = 0.0

    def _note_switches(self, segment: Recording) -> None:
        """Remember the times (ns) of the contact switches in ``segment``: the reported rows near one
        carry the force the motion requires (``ModelConfig.switch_window``), whether the switch lies
        in their part or in one before or after it (within the lag)."""
        act = np.asarray(segment.contact_active, dtype=bool)
        if act.shape[0] > 1:
            ks = np.flatnonzero(np.any(act[1:] != act[:-1], axis=1)) + 1
            self._switch_ns.update(int(x) for x in segment.t_ns[ks])

    def _switch_near(self, part: Recording) -> np.ndarray:
        """(n,) the rows of ``part`` within the model's switch window of a switch seen so far, on the
        stream's time axis (as the whole recording's would be), the switches too old to matter dropped."""
        window = float(getattr(self.model, "switch_window", 0.0))
        t0 = int(self.t0_ns or part.t_ns[0])
        time = (part.t_ns - t0) * 1e-9
        near = np.zeros(part.n, dtype=bool)
        for ns in sorted(self._switch_ns):
            ts = (ns - t0) * 1e-9
            if ts < time[0] - 2.0 * window:
                self._switch_ns.discard(ns)
                continue
            near |= np.abs(time - ts) <= window
        return near

    def _collect(self) -> Estimate | None:
        """The Estimate of the rows reported since the last call (consecutive steps)."""
        rows, self._rows = self._rows, []
        if not rows:
            return None
        assert self.segment is not None and self.first is not None
        j0, j1 = rows[0][0], rows[-1][0] + 1
        a = j0 - self.segment_offset
        part = self.segment.slice(a, a + (j1 - j0))
        prob = Problem.build(part, self.model, self.config.rule, part_of=self.first, offset=j0)
        traj = Trajectory(np.array([r[1] for r in rows]), np.array([r[2] for r in rows]),
                          np.array([r[3] for r in rows]), np.array([r[4] for r in rows]))
        P = np.array([r[5] for r in rows]) if self.covariance else None
        o = self.update_time_offset
        times = (np.frombuffer(self.update_time, dtype=float)[j0 - o:j1 - o].copy()
                 if j0 >= o and len(self.update_time) >= j1 - o else None)
        if j1 > o:  # reported: their times leave with the estimate (memory stays bounded)
            del self.update_time[:min(j1 - o, len(self.update_time))]
            self.update_time_offset = j1
        with warnings.catch_warnings():  # announced once for the whole stream, in finish()
            warnings.simplefilter("ignore", RuntimeWarning)
            # the read-out boundaries within these rows (the last row's factor is with the next part)
            succ = {}
            if self.fls is not None:
                for j in [j for j in self.fls.successors if j < j1]:
                    nxt = self.fls.successors.pop(j)
                    if j0 <= j < j1 - 1:
                        succ[j - j0] = nxt
            est = make_estimate(prob, "fixed_lag", traj, P, time_per_step=times, successors=succ,
                                switch_near=self._switch_near(part),
                                meta={"lag_s": self.lag_steps * self.first.dt, "use_ft": prob.use_ft,
                                      "backend": "window", "stream": {"first_step": j0, "steps": j1 - j0},
                                      "covariance": "per-step marginals of the window (joint within a step)"
                                      if self.covariance else None})
        shift = (int(part.t_ns[0]) - int(self.t0_ns or part.t_ns[0])) * 1e-9
        for entry in est.meta["rejected"]:
            entry["t"] = round(entry["t"] + shift, 6)
            entry["step"] += j0
        self.rejected.extend(est.meta["rejected"])
        return est

    def _trim(self) -> None:
        """Drop the steps neither relinearised again nor still to be reported."""
        fls = self.fls
        assert fls is not None and self.segment is not None
        keep = min(fls.k_done - fls.M - 1, fls.next_report)
        keep = max(keep, self.segment_offset)
        if keep > self.segment_offset:
            self.segment = self.segment.slice(keep - self.segment_offset, self.segment.n)
            self.segment_offset = keep
            # the problem keeps its arrays until the next part; the smoother only reads steps >= keep

    @property
    def update_stats(self) -> dict:
        """Median, p99, max and mean of the update times, ms, the updates counted, and the mean
        time per sample, ms (the same as the mean update time with one update per sample)."""
        u = self.update_times
        if u.count == 0:
            return {"updates": 0}
        return {"updates": u.count, "median_ms": 1e3 * u.quantile(0.5), "p99_ms": 1e3 * u.quantile(0.99),
                "max_ms": 1e3 * u.max, "mean_ms": 1e3 * u.total / u.count,
                "per_sample_ms": 1e3 * u.total / max(self.samples_updated, 1),
                "samples_per_update": self.config.block}


def run_stream(parts, model, config: FixedLagConfig | None = None, *, covariance: bool | None = None,
               realtime: bool = False, clock=time.perf_counter, sleep=time.sleep, stats: dict | None = None):
    """Fixed-lag smoothing of ``parts`` (an iterable of consecutive Recordings); yields the
    estimates as the steps leave the window (:class:`FixedLagStream`), the last from its finish.

    ``realtime``: the parts are paced at the recording's clock (a part is pushed once the wall
    clock since the first part reaches its last step's time), and a part whose updates are not
    done when the next part is due is a missed deadline.  ``stats`` (a dict, filled at the end):
    steps, wall time, real-time factor, update times (:attr:`FixedLagStream.update_stats`), and
    in real time the missed deadlines and the largest lateness behind the recording's clock.
    """
    stream = FixedLagStream(model, config, covariance)
    wall0 = clock()
    t0_ns: int | None = None
    missed, late_max, n_parts = 0, 0.0, 0
    period = 0.0
    for part in parts:
        if part.n == 0:
            continue
        if t0_ns is None:
            t0_ns = int(part.t_ns[0])
        n_parts += 1
        due = (int(part.t_ns[-1]) - t0_ns) * 1e-9
        if realtime:
            wait = due - (clock() - wall0)
            if wait > 0:
                sleep(wait)
            period = part.n * (part.dt or 0.0)
        est = stream.push(part)
        if realtime:
            late = (clock() - wall0) - due
            late_max = max(late_max, late)
            if late > period:  # the next part (as long as this one) was due before this one was done
                missed += 1
        if est is not None:
            yield est
    est = stream.finish()
    wall = clock() - wall0
    if stats is not None:
        span = (stream.n - 1) * stream.first.dt if stream.first is not None and stream.n > 1 else 0.0
        stats.update({"steps": stream.n, "wall_s": wall, "recording_s": span,
                      "realtime_factor": span / wall if wall > 0 else None,
                      "update": stream.update_stats, "parts": n_parts,
                      "lag_s": stream.lag_steps * (stream.first.dt if stream.first is not None else 0.0)})
        if realtime:
            stats.update({"missed_deadlines": missed, "max_late_s": late_max})
    if est is not None:
        yield est
