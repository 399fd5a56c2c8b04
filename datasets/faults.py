"""Sensor faults: missing and saturated IMU readings, robust weights, and how they are reported.

Real IMUs and F/T sensors fail in ways the nominal Gaussian noise model does not describe: a
reading goes missing (NaN: a dropped packet, a driver gap), clips at the sensor's range
(saturation: the true value is beyond it, the reading says nothing but "at least this"), or is
grossly wrong for one or a few samples (a spike, a stuck value).  Every estimator treats them the
same way (docs/smoother.md and docs/ekf.md, "Sensor faults"):

* a missing or saturated axis carries no information: zero weight in the smoothers, the axis left
  out of the EKF's update (:func:`imu_validity`);
* a gross outlier has bounded influence: a robust loss on the whitened residual of each sensor in
  the smoothers (:func:`robust_weights`), a chi-square gate with covariance inflation in the EKF;
* every sample so treated is listed in ``Estimate.meta["rejected"]`` (:func:`entry`) and summed up
  in one ``RuntimeWarning`` (:func:`warn_summary`).

This module is plain numpy, shared by the smoothers and the EKF.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from flexforce.errors import DataError

__all__ = ["IMU_SENSORS", "MAX_MISSING_FRACTION", "RANGE_TOLERANCE", "ROBUST_LOSSES", "check_missing", "entry",
           "gate_threshold", "imu_validity", "robust_weights", "summarize", "warn_summary"]

IMU_SENSORS = (("gyro", slice(0, 3)), ("accel", slice(3, 6)))
"""The IMU's two sensors and their rows in the 6-D reading ``(gyro, accel)``."""
AXES = ("x", "y", "z")

RANGE_TOLERANCE = 1e-3
"""A reading within this fraction of the configured range (``|y| >= range (1 - tol)``) counts as
saturated: a clipped reading sits at the full scale up to a few quantisation steps (a 16-bit
converter at +-16 g has steps of 3e-5 of the range)."""

MAX_MISSING_FRACTION = 0.1
"""Above this fraction of samples with a missing (NaN or inf) gyrometer or accelerometer reading a
recording is refused (DataError): the estimate would rest on the model alone."""

ROBUST_LOSSES = ("log-tail", "huber", "cauchy")


def imu_validity(gyro: np.ndarray, accel: np.ndarray, gyro_range: float = math.inf,
                 accel_range: float = math.inf, tol: float = RANGE_TOLERANCE):
    """Which IMU axes carry information.

    Args:
        gyro, accel: (N, 3) readings, rad/s and m/s^2 (NaN where missing).
        gyro_range, accel_range: the sensors' full scale, rad/s and m/s^2 (inf: not configured).

    Returns:
        ``use`` (N, 6) bool (gyro then accel axes), ``missing`` (N, 6) bool (not finite),
        ``saturated`` (N, 6) bool (finite and at or beyond ``range (1 - tol)``).
    """
    y = np.concatenate([np.asarray(gyro, float), np.asarray(accel, float)], axis=1)
    missing = ~np.isfinite(y)
    lim = np.array([gyro_range] * 3 + [accel_range] * 3, dtype=float) * (1.0 - tol)
    with np.errstate(invalid="ignore"):
        saturated = ~missing & (np.abs(y) >= lim)
    return ~(missing | saturated), missing, saturated


def check_missing(time_s: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
                  limit: float = MAX_MISSING_FRACTION) -> None:
    """Raise DataError when more than ``limit`` of the samples have a missing IMU reading."""
    for name, arr in (("gyro", gyro), ("accel", accel)):
        bad = ~np.isfinite(np.asarray(arr, float)).all(axis=1)
        count = int(bad.sum())
        n = len(bad)
        if n and count > limit * n:
            k = int(np.flatnonzero(bad)[0])
            raise DataError(f"field '{name}' is missing (NaN or inf) at {count} of {n} samples "
                            f"({100.0 * count / n:.1f} %, first at sample {k}, t = {time_s[k]:.3f} s); at most "
                            f"{100.0 * limit:.0f} % of the IMU samples may be missing (each is skipped by the "
                            "estimators)")


def gate_threshold(probability: float, dof: int) -> float:
    """The chi-square gate with ``dof`` degrees of freedom whose upper tail is ``probability``
    (a nominal sample exceeds it with that probability)."""
    from scipy.stats import chi2

    return float(chi2.isf(probability, dof))


def robust_weights(norm: np.ndarray, kind: str | None, k: float):
    """IRLS weights and robust cost of residual vectors of whitened norm ``norm``.

    ``log-tail``: quadratic (Gaussian) up to ``k``, logarithmic beyond, ``k^2/2 + k^2 log(|r|/k)``
    (weight ``(k/|r|)^2``, influence ``k^2/|r|``: continuous, at most ``k``, falling to zero for
    gross outliers; nominal residuals keep their full weight);
    ``huber``: quadratic up to ``k``, linear beyond (weight ``k / |r|``, influence bounded by
    ``k``); ``cauchy``: ``k^2/2 log(1 + (|r|/k)^2)`` (weight ``1 / (1 + (|r|/k)^2)``, influence
    falling to zero for gross outliers); ``None``: Gaussian (weight 1).
    """
    norm = np.asarray(norm, dtype=float)
    if kind is None:
        return np.ones_like(norm), 0.5 * norm**2
    if kind == "log-tail":
        big = norm > k
        safe = np.maximum(norm, k)
        return (np.where(big, (k / safe) ** 2, 1.0),
                np.where(big, 0.5 * k * k + k * k * np.log(safe / k), 0.5 * norm**2))
    if kind == "huber":
        w = np.where(norm <= k, 1.0, k / np.maximum(norm, 1e-300))
        return w, np.where(norm <= k, 0.5 * norm**2, k * norm - 0.5 * k * k)
    if kind == "cauchy":
        u = (norm / k) ** 2
        return 1.0 / (1.0 + u), 0.5 * k * k * np.log1p(u)
    raise ValueError(f"unknown robust loss {kind!r}; expected one of {ROBUST_LOSSES} or None")


def entry(t: float, step: int | np.integer, sensor: str, axis: str, reason: str, size: float, weight: float) -> dict:
    """One reported sample: time (s), step, sensor (``gyro``, ``accel``, ``ft/<contact>/force`` ...),
    axis (``x``/``y``/``z`` or ``norm``), reason (``missing``, ``saturated``, ``outlier``), size
    (the reading for missing/saturated; the whitened norm for an outlier) and the weight it kept
    (0 for no information; the robust weight, or 1/inflation in the EKF)."""
    return {"t": round(float(t), 6), "step": int(step), "sensor": sensor, "axis": axis, "reason": reason,
            "size": float(size) if math.isfinite(size) else None, "weight": float(weight)}


def masked_entries(time_s: np.ndarray, y: np.ndarray, missing: np.ndarray, saturated: np.ndarray,
                   sensors=IMU_SENSORS) -> list[dict]:
    """Entries of the missing and saturated axes (``y`` (N, 6) the readings)."""
    out = []
    for name, sl in sensors:
        for reason, mask in (("missing", missing[:, sl]), ("saturated", saturated[:, sl])):
            for k, a in zip(*np.nonzero(mask)):
                out.append(entry(time_s[k], k, name, AXES[a], reason, y[k, sl.start + a], 0.0))
    return out


def summarize(entries: list[dict]) -> str:
    """``"accel outlier 3 (t 1.000-1.010 s, up to 1.2e+07 whitened); gyro missing 1 (t 0.500 s)"``."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for e in entries:
        groups.setdefault((e["sensor"], e["reason"]), []).append(e)
    parts = []
    for (sensor, reason), es in sorted(groups.items()):
        steps = sorted({e["step"] for e in es})
        t0, t1 = min(e["t"] for e in es), max(e["t"] for e in es)
        span = f"t {t0:.3f} s" if t0 == t1 else f"t {t0:.3f}-{t1:.3f} s"
        what = f"{sensor} {reason}: {len(steps)} sample(s) ({span}"
        sizes = [abs(e["size"]) for e in es if e["size"] is not None]
        if reason == "outlier" and sizes:
            what += f", whitened norm up to {max(sizes):.3g}"
        parts.append(what + ")")
    return "; ".join(parts)


def warn_summary(estimator: str, entries: list[dict], stacklevel: int = 3) -> None:
    """One RuntimeWarning listing, per sensor and reason, the samples given less weight."""
    if entries:
        warnings.warn(f"{estimator}: sensor samples left out or down-weighted -- {summarize(entries)}; "
                      "see Estimate.meta['rejected']", RuntimeWarning, stacklevel=stacklevel)
