"""Accuracy, consistency and cost of an Estimate, against ground truth or reference sensors.

Computing stays apart from reporting: :func:`evaluate` returns a :class:`Metrics` object (plain
numbers and per-step error series); :mod:`flexforce.compare.reports.comparison` draws figures from it.

Errors are taken per step and summarised as RMSE and max:

- ``rotation_rad``: angle of ``R_est R_true^T``;
- ``translation_m``: norm of the translation error;
- ``angular_velocity_rad_s``, ``linear_velocity_m_s``: norms of the velocity errors;
- ``force_N``, ``moment_Nm``: norms of the total contact force and moment errors (moment about
  the world origin, which the simulator puts at the ground between the feet);
- ``contact_force_N``: norm of the per-contact force error, over the steps where it is active;
- ``cop_m``: horizontal distance between estimated and true CoP;
- ``hand_m``: world position error of the tracked links (the hands) when the estimated
  flexibility is used to place them: the paper's hand-compensation experiment.

Where the contacts are what is judged (:func:`phase_metrics`, added by the comparison runner):
the per-foot and total vertical force in the contact frames and the rotation (tilt) error over
each contact phase (:data:`PHASES`), raw and after a zero-phase low-pass of both estimate and
reference (:data:`LOWPASS_HZ`); and the estimate's physical violations (:func:`violations`).

Consistency: NEES of the 18-D state (mean over the run, with its 95% two-sided chi-square band
for the mean of N independent draws) and, for filters, NIS of the 6-D innovation.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from flexforce.factors import contact_limits, so3

RMSE_KEYS = ("force_N", "moment_Nm", "cop_m", "rotation_rad", "translation_m", "hand_m")
"""The headline errors of a comparison (summary.json's ``rmse`` keys)."""

ALL_KEYS = RMSE_KEYS + ("angular_velocity_rad_s", "linear_velocity_m_s", "contact_force_N",
                        "vertical_force_N")


@dataclass
class Metrics:
    """Accuracy, consistency and cost of one estimator on one recording."""

    estimator: str
    rmse: dict[str, float | None] = field(default_factory=dict)
    max: dict[str, float | None] = field(default_factory=dict)
    errors: dict[str, np.ndarray] = field(default_factory=dict)
    """Per-step error series (N,) behind each key (NaN where undefined)."""
    nees: float | None = None
    """Mean NEES of the 18-D state (expected value 18 for a consistent estimator)."""
    nees_bounds: tuple[float, float] | None = None
    """95% band of the mean NEES over the run for a consistent estimator."""
    nees_series: np.ndarray | None = None
    nis: float | None = None
    """Mean NIS of the innovation (expected 6), filters only."""
    nis_bounds: tuple[float, float] | None = None
    nis_series: np.ndarray | None = None
    time_per_step: dict[str, float | None] = field(default_factory=dict)
    """median and p99 of the per-step wall time (s; None for the batch smoother, which has no
    steps), and ``amortized``: total time over the number of steps."""
    total_time: float | None = None
    peak_memory_mb: float | None = None
    reference: str = "truth"
    """``truth`` (simulated) or ``sensors`` (real logs: F/T, motion capture)."""
    references: dict[str, str] = field(default_factory=dict)
    """Error key -> what it is measured against: ``truth``, ``reference: F/T``, ``reference: Vicon``
    (a reference sensor is not ground truth: its own noise and offsets are in the error)."""
    kind: str = "estimator"
    """``estimator``, or ``baseline`` for a row without estimation (leg odometry): no timing, no NEES."""
    per_contact: dict[str, dict[str, float | None]] = field(default_factory=dict)
    """Contact name -> RMSE per key, in the contact frame about its origin (like an F/T sensor):
    ``vertical_force_N`` (|F_z error|), ``force_N`` (3-D force error), ``moment_Nm`` (3-D torque
    error), ``cop_m`` (the foot's own CoP, while the reference and the estimate both carry more
    than :data:`COP_MIN_LOAD` of the weight).  A key is absent when the reference lacks the
    components it needs."""
    contact_errors: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    """Contact name -> key -> (N,) error series behind :attr:`per_contact` (NaN where undefined)."""
    per_phase: dict = field(default_factory=dict)
    """Phase (``all`` and :data:`PHASES`) -> ``samples``, ``rmse`` (``foot_vertical_force_N``,
    ``total_vertical_force_N``, ``rotation_rad``) and :func:`lowpass_key` (the forces after the
    low-pass): :func:`phase_metrics`; empty where it was not computed."""
    violations: dict = field(default_factory=dict)
    """Counts and fractions of physically impossible contact wrenches: :func:`violations`."""
    force_band: dict = field(default_factory=dict)
    """Coverage of the contacts' normal-force bands by the reference: :func:`force_band`."""
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-serialisable summary (no series) of what the estimate is, the same for two runs on the
        same input: no timing or memory, which measure the machine (:meth:`timings_dict`)."""
        return {
            "rmse": {k: _clean(v) for k, v in self.rmse.items()},
            "max": {k: _clean(v) for k, v in self.max.items()},
            "nees": _clean(self.nees),
            "nees_bounds": list(self.nees_bounds) if self.nees_bounds else None,
            "nis": _clean(self.nis),
            "nis_bounds": list(self.nis_bounds) if self.nis_bounds else None,
            "reference": self.reference,
            "references": dict(self.references),
            "kind": self.kind,
            "per_contact": {c: {k: _clean(v) for k, v in d.items()} for c, d in self.per_contact.items()},
            **({"extra": self.extra} if self.extra else {}),
            **({"per_phase": {ph: {k: ({q: _clean(x) for q, x in v.items()} if isinstance(v, dict) else v)
                                   for k, v in d.items()} for ph, d in self.per_phase.items()}}
               if self.per_phase else {}),
            **({"violations": self.violations} if self.violations else {}),
            **({"force_band": self.force_band} if self.force_band else {}),
        }

    def timings_dict(self) -> dict:
        """JSON-serialisable cost of the run, which varies between two runs on the same input:
        ``time_per_step_s`` (``median``, ``p99``, ``amortized``; s), ``total_time_s`` (s) and
        ``peak_memory_mb`` (MiB); None where not measured (a non-finite value too)."""
        return {"time_per_step_s": {k: _clean(v) for k, v in self.time_per_step.items()},
                "total_time_s": _clean(self.total_time), "peak_memory_mb": _clean(self.peak_memory_mb)}


def _clean(x) -> float | None:
    """``x`` as a float, None for None or a non-finite value (JSON has no NaN)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


COP_MIN_LOAD = 0.05
"""Fraction of the weight a foot must carry (estimate and reference) for its CoP to be compared:
below it the CoP, a torque over a small force, is dominated by the sensor's torque noise."""


def contact_frame_wrench(R: np.ndarray, t: np.ndarray, wrench: np.ndarray, rec) -> np.ndarray:
    """(N, C, 6) per-contact wrench in the contact frame about its origin, as an F/T sensor reads it.

    Args:
        R, t: (N, 3, 3), (N, 3) flexibility placing the local frame (and its contacts) in the world.
        wrench: (N, C, 6) world wrench (F, T about the world origin).
    Inactive contacts read zero (:func:`flexforce.factors.contact_limits.contact_frame_wrench`).
    """
    return contact_limits.contact_frame_wrench(R, t, wrench, rec.contact_p, rec.contact_R, rec.contact_active)


def _per_contact(m: Metrics, est_local: np.ndarray, ref: np.ndarray, rec, keep: np.ndarray) -> None:
    """Per-contact errors of ``est_local`` against ``ref`` (both (N, C, 6), contact frame)."""
    weight = rec.mass * rec.gravity
    diff = est_local - ref
    for i, name in enumerate(rec.contact_names):
        series = {}
        fz = np.abs(diff[:, i, 2])
        if np.isfinite(fz[keep]).any():
            series["vertical_force_N"] = fz
        f3 = np.linalg.norm(diff[:, i, :3], axis=1)
        if np.isfinite(f3[keep]).any():
            series["force_N"] = f3
        t3 = np.linalg.norm(diff[:, i, 3:], axis=1)
        if np.isfinite(t3[keep]).any():
            series["moment_Nm"] = t3
        with np.errstate(invalid="ignore", divide="ignore"):
            loaded = (ref[:, i, 2] > COP_MIN_LOAD * weight) & (est_local[:, i, 2] > COP_MIN_LOAD * weight)
            # sole CoP of a wrench about the sole origin: x = -T_y / F_z, y = T_x / F_z
            cop_ref = np.stack([-ref[:, i, 4], ref[:, i, 3]], axis=1) / ref[:, i, 2:3]
            cop_est = np.stack([-est_local[:, i, 4], est_local[:, i, 3]], axis=1) / est_local[:, i, 2:3]
            cop = np.linalg.norm(cop_est - cop_ref, axis=1)
        cop[~loaded] = np.nan
        if np.isfinite(cop[keep]).any():
            series["cop_m"] = cop
        m.contact_errors[name] = series
        m.per_contact[name] = {}
        for key, e in series.items():
            s = e.copy()
            s[~keep] = np.nan
            m.per_contact[name][key] = _summ(s)[0]


def _summ(err: np.ndarray) -> tuple[float | None, float | None]:
    e = err[np.isfinite(err)]
    if e.size == 0:
        return None, None
    return float(np.sqrt(np.mean(e * e))), float(np.max(np.abs(e)))


def chi2_mean_bounds(dof: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Two-sided band of the mean of ``n`` chi-square(dof) draws (the NEES test of Bar-Shalom)."""
    lo = stats.chi2.ppf((1 - level) / 2, dof * n) / n
    hi = stats.chi2.ppf(1 - (1 - level) / 2, dof * n) / n
    return float(lo), float(hi)


def state_error(est, truth) -> np.ndarray:
    """(N, 18) error in world-frame increments (theta, t, w, v, dw, a): estimate minus truth."""
    n = est.n
    e = np.zeros((n, 18))
    for k in range(n):
        e[k, :3] = so3.log(est.R[k] @ truth.R[k].T)
    e[:, 3:6] = est.t - truth.t
    e[:, 6:9] = est.w - truth.w
    e[:, 9:12] = est.v - truth.v
    e[:, 12:15] = est.dw - truth.dw
    e[:, 15:18] = est.a - truth.a
    return e


def nees_series(est, truth) -> np.ndarray | None:
    """(N,) normalised estimation error squared of the 18-D state."""
    if est.cov is None:
        return None
    e = state_error(est, truth)
    out = np.full(est.n, np.nan)
    for k in range(est.n):
        try:
            out[k] = e[k] @ np.linalg.solve(est.cov[k], e[k])
        except np.linalg.LinAlgError:
            pass
    return out


def evaluate(est, rec, skip: float = 0.0, peak_memory_mb: float | None = None) -> Metrics:
    """Metrics of ``est`` on recording ``rec`` (ground truth if any, else reference sensors).

    Args:
        skip: seconds at the start left out of the statistics (filter convergence).
    """
    m = Metrics(est.estimator, peak_memory_mb=peak_memory_mb)
    keep = rec.time >= skip
    m.time_per_step = {"median": None, "p99": None,
                       "amortized": float(est.total_time / est.n) if est.total_time and est.n else None}
    if est.time_per_step is not None and len(est.time_per_step):
        m.time_per_step["median"] = float(np.median(est.time_per_step))
        m.time_per_step["p99"] = float(np.percentile(est.time_per_step, 99))
    m.total_time = est.total_time
    if est.innovation is not None and est.innovation_cov is not None:
        nis = np.full(est.n, np.nan)
        for k in range(est.n):
            if np.all(np.isfinite(est.innovation[k])):
                try:
                    nis[k] = est.innovation[k] @ np.linalg.solve(est.innovation_cov[k], est.innovation[k])
                except np.linalg.LinAlgError:
                    pass
        m.nis_series = nis
        ok = keep & np.isfinite(nis)
        if ok.any():
            m.nis = float(np.mean(nis[ok]))
            m.nis_bounds = chi2_mean_bounds(6, int(ok.sum()))
    if rec.truth is not None:
        _against_truth(m, est, rec, keep)
    else:
        _against_sensors(m, est, rec, keep)
    return m


def _against_truth(m: Metrics, est, rec, keep):
    tr = rec.truth
    e = state_error(est, tr)
    err = {
        "rotation_rad": np.linalg.norm(e[:, 0:3], axis=1),
        "translation_m": np.linalg.norm(e[:, 3:6], axis=1),
        "angular_velocity_rad_s": np.linalg.norm(e[:, 6:9], axis=1),
        "linear_velocity_m_s": np.linalg.norm(e[:, 9:12], axis=1),
    }
    W_est = est.total_wrench
    W_true = tr.total_wrench
    err["force_N"] = np.linalg.norm(W_est[:, :3] - W_true[:, :3], axis=1)
    err["moment_Nm"] = np.linalg.norm(W_est[:, 3:] - W_true[:, 3:], axis=1)
    err["vertical_force_N"] = np.abs(W_est[:, 2] - W_true[:, 2])
    cf = np.linalg.norm(est.wrench[..., :3] - tr.wrench[..., :3], axis=2)
    cf[~rec.contact_active] = np.nan
    with np.errstate(invalid="ignore"):
        err["contact_force_N"] = np.sqrt(np.nanmean(cf * cf, axis=1))
    err["cop_m"] = np.linalg.norm(est.cop[:, :2] - tr.cop[:, :2], axis=1)
    if tr.links:
        hand = []
        moved = []
        for p_w in tr.links.values():
            p_l = np.einsum("nji,nj->ni", tr.R, p_w - tr.t)  # local position: R^T (p - t)
            p_est = np.einsum("nij,nj->ni", est.R, p_l) + est.t
            hand.append(np.linalg.norm(p_est - p_w, axis=1))
            moved.append(np.linalg.norm(p_w - p_l, axis=1))
        err["hand_m"] = np.max(hand, axis=0)
        m.extra["hand_displacement_by_flexibility_max_m"] = float(np.max(moved))
    else:
        err["hand_m"] = np.full(est.n, np.nan)
    for key, series in err.items():
        s = series.copy()
        s[~keep] = np.nan
        m.errors[key] = series
        m.rmse[key], m.max[key] = _summ(s)
    m.references = {k: "truth" for k in err}
    _per_contact(m, contact_frame_wrench(est.R, est.t, est.wrench, rec),
                 contact_frame_wrench(tr.R, tr.t, tr.wrench, rec), rec, keep)
    ns = nees_series(est, tr)
    if ns is not None:
        m.nees_series = ns
        ok = keep & np.isfinite(ns)
        if ok.any():
            m.nees = float(np.mean(ns[ok]))
            m.nees_bounds = chi2_mean_bounds(18, int(ok.sum()))


def base_verticals(est, rec, link: str) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) and (N, 3): the estimated and the motion-capture vertical in the base frame (rows of
    ``R^T e_z``), NaN rows where motion capture (or ``Recording.base_pose``) is missing.

    The estimated base orientation is the flexibility composed with the base's local orientation
    (``Recording.base_pose``); motion capture gives it directly."""
    from scipy.spatial.transform import Rotation

    pose = rec.mocap[link]
    ok = np.all(np.isfinite(pose), axis=1)
    g_est = np.full((rec.n, 3), np.nan)
    g_moc = np.full((rec.n, 3), np.nan)
    if not ok.any() or rec.base_pose is None:
        return g_est, g_moc
    R_local = Rotation.from_quat(rec.base_pose[ok, 3:]).as_matrix()
    g_est[ok] = np.einsum("nij,njk->nik", est.R[ok], R_local)[:, 2, :]
    g_moc[ok] = Rotation.from_quat(pose[ok, 3:]).as_matrix()[:, 2, :]
    return g_est, g_moc


def base_tilt_error(est, rec, link: str, verticals: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(N,) angle (rad) between the estimated and the motion-capture vertical, in the base frame
    (:func:`base_verticals`, or ``verticals`` already computed); NaN without motion capture.

    Comparing the direction of the vertical seen from the base leaves out yaw, which neither leg
    odometry nor the IMU observe against the motion-capture frame.
    """
    g_est, g_moc = base_verticals(est, rec, link) if verticals is None else verticals
    cos = np.clip(np.sum(g_est * g_moc, axis=1), -1.0, 1.0)
    return np.arccos(cos)


def aligned_tilt(est, rec, link: str, keep: np.ndarray,
                 verticals: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """The tilt error against motion capture split into its constant and the rest: what a constant
    rotation between the two verticals (the markers' frame against the base's, the motion-capture
    world's vertical against gravity: neither is the estimator's) leaves.  Over the samples of
    ``keep`` where both verticals are known (:func:`base_verticals`, or ``verticals`` already
    computed), in the base frame:

    - ``tilt_offset_rad``: [x, y], the mean of the estimated minus the motion-capture vertical
      (small angles: the base's roll and pitch offset, as rotations about -y and x);
    - ``tilt_aligned_rad``: the RMS angle between the verticals once that mean is taken out (as
      evo's trajectory alignment does for a whole pose).

    Empty when no sample of ``keep`` has both (no motion capture, an estimate of NaN)."""
    g_est, g_moc = base_verticals(est, rec, link) if verticals is None else verticals
    d = (g_est - g_moc)[keep]
    d = d[np.all(np.isfinite(d), axis=1)]
    if not len(d):
        return {}
    offset = d.mean(axis=0)
    chord = np.linalg.norm(d - offset, axis=1)
    angle = 2.0 * np.arcsin(np.clip(chord / 2.0, 0.0, 1.0))
    return {"tilt_offset_rad": [float(offset[0]), float(offset[1])],
            "tilt_aligned_rad": float(np.sqrt(np.mean(angle * angle)))}


def mocap_label(rec) -> str:
    """The motion-capture system's name: ``meta["mocap_system"]`` when the importer sets it, ``Vicon``
    when a topic name says so, else ``motion capture``."""
    if rec.meta.get("mocap_system"):
        return str(rec.meta["mocap_system"])
    topics = " ".join((rec.meta.get("source") or {}).get("topics", {}) if isinstance(rec.meta.get("source"), dict)
                      else []).lower()
    return "Vicon" if "vicon" in topics else "motion capture"


def _against_sensors(m: Metrics, est, rec, keep):
    """Real logs: F/T wrenches (NaN components skipped), per-contact vertical force, mocap."""
    m.reference = "sensors"
    for key in RMSE_KEYS:
        m.rmse.setdefault(key, None)
        m.max.setdefault(key, None)
    base = rec.meta.get("base_frame")
    if base in rec.mocap and rec.base_pose is not None:
        verticals = base_verticals(est, rec, base)
        tilt = base_tilt_error(est, rec, base, verticals)
        m.errors["rotation_rad"] = tilt
        s = tilt.copy()
        s[~keep] = np.nan
        m.rmse["rotation_rad"], m.max["rotation_rad"] = _summ(s)
        m.extra["rotation_reference"] = f"tilt of {base} against motion capture"
        m.extra.update(aligned_tilt(est, rec, base, keep, verticals))
        m.references["rotation_rad"] = f"reference: {mocap_label(rec)}"
    if rec.ft is not None:
        local = contact_frame_wrench(est.R, est.t, est.wrench, rec)
        diff = local - rec.ft
        fz = np.abs(diff[:, :, 2])
        fz[~keep] = np.nan
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # rows left out (NaN) stay NaN
            m.errors["vertical_force_N"] = np.sqrt(np.nanmean(fz * fz, axis=1))
        m.rmse["vertical_force_N"], m.max["vertical_force_N"] = _summ(fz.ravel())
        ff = diff[:, :, :3]
        if np.isfinite(ff).any():
            norm = np.sqrt(np.nansum(ff * ff, axis=2))
            norm[~np.isfinite(ff).any(axis=2)] = np.nan
            norm[~keep] = np.nan
            m.rmse["contact_force_N"], m.max["contact_force_N"] = _summ(norm.ravel())
            m.references["contact_force_N"] = "reference: F/T"
        m.references["vertical_force_N"] = "reference: F/T"
        _per_contact(m, local, rec.ft, rec, keep)
        # where the F/T measure moments too (six-axis sensors): the contacts' moment and sole-CoP
        # errors -- the quantities the estimator is for -- over the contacts and the steps
        for key, name in (("moment_Nm", "contact_moment_Nm"), ("cop_m", "contact_cop_m")):
            series = [m.contact_errors[c][key] for c in rec.contact_names if key in m.contact_errors.get(c, {})]
            if not series:
                continue
            e = np.stack(series, axis=1)
            e[~keep] = np.nan
            m.rmse[name], m.max[name] = _summ(e.ravel())
            m.references[name] = "reference: F/T"


# ----------------------------------------------------------------------------------------------
# Contact phases, low-passed forces and physical violations (the comparison's plain verdict)
# ----------------------------------------------------------------------------------------------

PHASES = ("single_support", "double_support", "transition")
"""Contact phases of :func:`phase_masks`, besides ``all``."""
TRANSITION_S = 0.05
"""Half-width of a transition, s: the samples within this of a contact switch (a contact made or
released) are the ``transition`` phase and belong to no support phase."""
LOWPASS_HZ = 5.0
"""Cut-off of the low-pass applied to both estimate and reference before the low-passed RMSEs, Hz:
the iCub's F/T forces come through the robot's dynamics filtered, so the raw RMSE also counts
the estimate's content above the reference's band."""
LOWPASS_ORDER = 4
"""Order of the Butterworth low-pass (applied forward and backward: zero phase, twice the order)."""
FRICTION_MU = 0.7
"""Friction coefficient of the friction-cone check when the robot config gives none (its ``friction``)."""
NO_SOLE = ("no sole dimensions: the robot config gives its contacts no sole (a contact's "
           "sole = [x_min, x_max, y_min, y_max] in m, in its frame)")
"""Why the CoP-in-sole check is skipped when no sole is given."""


def lowpass_key(cutoff_hz: float = LOWPASS_HZ) -> str:
    """``rmse_lowpass_5Hz``: the key of the low-passed RMSEs, the cut-off in it."""
    return f"rmse_lowpass_{cutoff_hz:g}Hz"


def lowpass(x: np.ndarray, cutoff_hz: float, rate_hz: float, order: int = LOWPASS_ORDER) -> np.ndarray:
    """Zero-phase Butterworth low-pass of ``x`` (N, ...) along axis 0 (``scipy.signal.sosfiltfilt``).

    Each run of finite samples of each column is filtered on its own; a run too short for the
    filter's padding, and every NaN, comes back NaN.

    Raises:
        ValueError: ``cutoff_hz`` is not below the Nyquist frequency ``rate_hz / 2``.
    """
    from scipy.signal import butter, sosfiltfilt

    if not 0 < cutoff_hz < rate_hz / 2:
        raise ValueError(f"low-pass cut-off {cutoff_hz} Hz; expected between 0 and the Nyquist frequency "
                         f"{rate_hz / 2:g} Hz")
    sos = butter(order, cutoff_hz / (rate_hz / 2), output="sos")
    pad = 3 * (2 * len(sos) + 1)  # sosfiltfilt's default padding
    flat = np.asarray(x, dtype=float).reshape(len(x), -1)
    out = np.full(flat.shape, np.nan)
    for j in range(flat.shape[1]):
        ok = np.isfinite(flat[:, j])
        for a, b in _runs(ok):
            if b - a > pad:
                out[a:b, j] = sosfiltfilt(sos, flat[a:b, j])
    return out.reshape(np.shape(x))


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) index ranges of the runs where ``mask`` is true."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return list(zip(edges[::2], edges[1::2]))


def phase_masks(rec, skip: float = 0.0, window: float = TRANSITION_S) -> dict[str, np.ndarray]:
    """(N,) bool masks of the samples after ``skip`` s: ``all``, ``single_support`` (one contact in
    force), ``double_support`` (two or more), ``transition`` (within ``window`` s of a contact
    switch); the support phases leave the transitions out; samples with no contact are in ``all`` only."""
    from flexforce.factors.contact_limits import near_switches

    t = rec.time
    keep = t >= skip
    act = rec.contact_active
    near = near_switches(act, t, window)
    count = act.sum(axis=1)
    return {"all": keep, "single_support": keep & (count == 1) & ~near,
            "double_support": keep & (count >= 2) & ~near, "transition": keep & near}


def _reference_contact_fz(rec) -> np.ndarray | None:
    """(N, C) reference normal forces in the contact frames: the truth's, else the F/T's; None without."""
    if rec.truth is not None:
        return contact_frame_wrench(rec.truth.R, rec.truth.t, rec.truth.wrench, rec)[:, :, 2]
    if rec.ft is not None and np.isfinite(rec.ft[:, :, 2]).any():
        return rec.ft[:, :, 2]
    return None


def _rms(e: np.ndarray) -> float | None:
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e * e))) if e.size else None


def phase_metrics(m: Metrics, est, rec, skip: float = 0.0, cutoff_hz: float = LOWPASS_HZ) -> None:
    """Fill ``m.per_phase``: per contact phase (:func:`phase_masks`) the RMSE of

    - ``foot_vertical_force_N``: each contact's normal force in its frame (zero when released)
      against the reference, over every (step, contact) -- on real logs the ``vertical_force_N``
      of :attr:`Metrics.rmse`;
    - ``total_vertical_force_N``: the sum of the contacts' normal forces against the reference's sum;
    - ``rotation_rad``: ``m.errors["rotation_rad"]`` (the tilt against motion capture on real logs);

    and the two forces again after :func:`lowpass` at ``cutoff_hz`` of both the estimate and the
    reference (:func:`lowpass_key`; left out when the rate is too low for the cut-off).  Nothing
    is filled without contacts or a force reference.
    """
    ref = _reference_contact_fz(rec)
    if ref is None or not rec.contact_names:
        return
    fz = contact_frame_wrench(est.R, est.t, est.wrench, rec)[:, :, 2]
    filtered = None
    rate = 1.0 / rec.dt if rec.dt > 0 else 0.0
    if 0 < cutoff_hz < rate / 2 and rec.n > 1:
        filtered = (lowpass(fz, cutoff_hz, rate), lowpass(ref, cutoff_hz, rate))
    rot = m.errors.get("rotation_rad")
    for phase, mask in phase_masks(rec, skip).items():
        entry: dict = {"samples": int(mask.sum())}
        entry["rmse"] = {"foot_vertical_force_N": _rms((fz - ref)[mask].ravel()),
                         "total_vertical_force_N": _rms(fz[mask].sum(axis=1) - ref[mask].sum(axis=1)),
                         "rotation_rad": _rms(rot[mask]) if rot is not None else None}
        if filtered is not None:
            a, b = filtered
            entry[lowpass_key(cutoff_hz)] = {"foot_vertical_force_N": _rms((a - b)[mask].ravel()),
                                             "total_vertical_force_N": _rms(a[mask].sum(axis=1) - b[mask].sum(axis=1))}
        m.per_phase[phase] = entry


BAND_SIGMAS = 2.0
"""Half-width of the force band, in standard deviations (nominal coverage of a Gaussian: 95.4 %)."""


def force_band(est, rec, skip: float = 0.0, k: float = BAND_SIGMAS, sigma: np.ndarray | None = None) -> dict:
    """How honest each contact's normal-force band is: over the (step, contact) pairs in force after
    ``skip`` s where the reference (the truth's, else the F/T's normal force) is finite, the
    fraction within ``k`` standard deviations of the estimate (``coverage``; a consistent Gaussian
    band covers :func:`band_level` of them) and the RMS of the normalised error (``z_rms``, 1 when
    consistent), per contact phase (:func:`phase_masks`) and per contact, with the median
    standard deviation (``median_sigma_N``).

    The standard deviation is that of the contact-frame F_z, ``n^T Sigma_F n`` with ``n`` the
    contact's normal and ``Sigma_F`` the force block of :attr:`Estimate.contact_wrench_cov`, or
    ``sigma`` (N, C) when given (the model band, :func:`flexforce.compare.band.model_band`).
    Empty without either, contacts or a force reference.
    """
    from flexforce.compare.band import normal_sigma

    ref = _reference_contact_fz(rec)
    cov = getattr(est, "contact_wrench_cov", None)
    if ref is None or (cov is None and sigma is None) or not rec.contact_names:
        return {}
    fz = contact_frame_wrench(est.R, est.t, est.wrench, rec)[:, :, 2]
    if sigma is None:
        sigma = normal_sigma(est, rec)
    ok = rec.contact_active & np.isfinite(ref) & np.isfinite(fz) & (sigma > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(ok, (fz - ref) / sigma, np.nan)

    def stats(mask: np.ndarray) -> dict:
        zz = z[mask & ok]
        if not zz.size:
            return {"samples": 0}
        return {"samples": int(zz.size), "coverage": float(np.mean(np.abs(zz) <= k)),
                "z_rms": float(np.sqrt(np.mean(zz * zz))), "median_sigma_N": float(np.median(sigma[mask & ok]))}

    masks = phase_masks(rec, skip)
    out: dict = {"k_sigma": k, "level": band_level(k)}
    out["per_phase"] = {ph: stats(np.broadcast_to(mask[:, None], ok.shape)) for ph, mask in masks.items()}
    keep = np.broadcast_to(masks["all"][:, None], ok.shape)
    out["per_contact"] = {name: stats(keep & (np.arange(len(rec.contact_names)) == i)[None, :])
                          for i, name in enumerate(rec.contact_names)}
    out.update(out["per_phase"]["all"])
    return out


def band_level(k: float = BAND_SIGMAS) -> float:
    """Probability that a Gaussian lies within ``k`` standard deviations of its mean."""
    return math.erf(k / math.sqrt(2.0))


def violations(est, rec, skip: float = 0.0, mu: float = FRICTION_MU,
               sole: tuple[float, float, float, float] | None = None, soles: tuple = ()) -> dict:
    """Physically impossible contact wrenches of ``est``, over the (step, contact) pairs in force
    after ``skip`` s, in the contact frames (:func:`contact_frame_wrench`, z the contact normal):

    - ``negative_normal``: normal force F_z below 0 N (the ground pulls);
    - ``friction_cone``: outside the cone |F_xy| <= ``mu`` F_z (a negative normal force included);
    - ``cop_outside_sole``: the contact's CoP (x = -T_y / F_z, y = T_x / F_z, where F_z > 0)
      outside ``sole`` = (x_min, x_max, y_min, y_max), m, in the contact frame, or each contact's
      own of ``soles`` (per contact, a rectangle or None: that contact's samples are not judged,
      :attr:`flexforce.factors.model.ModelConfig.soles`); without a sole ``{"skipped": reason}``.

    Returns:
        ``samples_in_contact``, ``friction_mu`` and per check ``count`` and ``fraction`` (of the
        samples in contact; None when there are none).  When the estimator limited its wrenches
        (:attr:`~flexforce.datasets.estimate.Estimate.wrench_excess`), ``contact_law`` holds the
        same checks on the contact law's wrenches (``wrench + wrench_excess``): how often the
        model asked a contact for what it cannot carry.
    """
    excess = getattr(est, "wrench_excess", None)
    out = _violations(est.R, est.t, est.wrench, rec, skip, mu, sole, soles)
    if excess is not None:
        out["contact_law"] = _violations(est.R, est.t, est.wrench + excess, rec, skip, mu, sole, soles)
    return out


def _violations(R, t, wrench, rec, skip, mu, sole, soles) -> dict:
    keep = rec.time >= skip
    on = rec.contact_active & keep[:, None]
    n = int(on.sum())
    w = contact_frame_wrench(R, t, wrench, rec)[on]  # (n, 6)

    def counted(bad: np.ndarray, total: int = n) -> dict:
        c = int(np.sum(bad))
        return {"count": c, "fraction": c / total if total else None}

    fn = w[:, 2]
    ft = np.linalg.norm(w[:, :2], axis=1)
    out: dict = {"samples_in_contact": n, "friction_mu": mu, "negative_normal": counted(fn < 0),
                 "friction_cone": counted((fn < 0) | (ft > mu * fn))}
    per = [sole] * len(rec.contact_names) if sole is not None else list(soles)
    if not any(r is not None for r in per):
        out["cop_outside_sole"] = {"skipped": NO_SOLE}
        return out
    if len(per) != len(rec.contact_names):
        raise ValueError(f"soles: {len(per)} given for {len(rec.contact_names)} contacts")
    which = np.nonzero(on)[1]  # the contact of each judged (step, contact) pair, in w's order
    box = np.array([r if r is not None else (np.nan,) * 4 for r in per], dtype=float)[which]  # (n, 4)
    judged = (fn > 0) & np.isfinite(box[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        cx = np.where(judged, -w[:, 4] / fn, 0.0)
        cy = np.where(judged, w[:, 3] / fn, 0.0)
    bad = judged & ((cx < box[:, 0]) | (cx > box[:, 1]) | (cy < box[:, 2]) | (cy > box[:, 3]))
    shown = list(sole) if sole is not None else [None if r is None else list(r) for r in per]
    out["cop_outside_sole"] = {**counted(bad, int(judged.sum())), "sole_m": shown}
    return out


# ----------------------------------------------------------------------------------------------
# The F/T reference held against the rigid robot's dynamics (no estimate involved)
# ----------------------------------------------------------------------------------------------

MIN_CHECK_SAMPLES = 10
"""Samples below which a check of :func:`reference_checks` is left out (too few to average)."""


def reference_checks(rec, skip: float = 0.0) -> dict | None:
    """How far the F/T normal forces are from what the robot's rigid dynamics require, from the
    recording alone (no estimate): the reference's own error, which every row's force error
    against the F/T contains.  None without F/T normal forces, or with ground truth (then the
    reference is the truth).

    - ``unloaded``: per contact, the F/T normal force where the contact is not in force (the
      swing foot, whose true contact force is 0): ``samples``, ``mean_N``, ``rms_N``.  A mean away
      from 0 is the sensor's offset (or the unmodelled weight under it).
    - ``total``: per phase (``all``, ``single_support``, ``double_support``; :func:`phase_masks`)
      the F/T sum minus ``m (g + c_z'')`` (the CoM's vertical acceleration from the encoders, the
      flexibility's left out): ``samples``, ``mean_N``, ``rms_N``.  A mean away from 0 in double
      support, where the feet stand still, is an offset of the F/T sum.
    """
    if rec.truth is not None or rec.ft is None:
        return None
    fz = np.asarray(rec.ft[:, :, 2], dtype=float)
    act = np.asarray(rec.contact_active, dtype=bool)
    if not np.isfinite(fz[act]).any():
        return None
    g = float(rec.gravity)
    keep = rec.time >= skip
    out: dict[str, Any] = {"unloaded": {}, "total": {}}
    for i, name in enumerate(rec.contact_names):
        sel = keep & ~act[:, i] & np.isfinite(fz[:, i])
        if sel.sum() >= MIN_CHECK_SAMPLES:
            x = fz[sel, i]
            out["unloaded"][name] = {"samples": int(sel.sum()), "mean_N": float(x.mean()),
                                     "rms_N": float(np.sqrt(np.mean(x * x)))}
    loaded = np.where(act, fz, 0.0)
    resid = loaded.sum(axis=1) - rec.mass * (rec.com_acc[:, 2] + g)
    finite = np.isfinite(loaded).all(axis=1)
    masks = phase_masks(rec, skip)
    for phase in ("all", "single_support", "double_support"):
        sel = masks[phase] & act.any(axis=1) & finite
        if sel.sum() >= MIN_CHECK_SAMPLES:
            x = resid[sel]
            out["total"][phase] = {"samples": int(sel.sum()), "mean_N": float(x.mean()),
                                   "rms_N": float(np.sqrt(np.mean(x * x)))}
    return out
