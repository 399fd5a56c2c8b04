"""The model band of the contact forces: what the model's own uncertain parameters allow.

An estimator's covariance holds the sensors' noise under its model, which it takes as exact: on a
real robot its force bands are a newton wide while the forces are tens of newtons off the F/T
(docs/real-logs.md, "Force bands").  The model band adds what the estimate would be with the
model's parameters moved within what the robot's configuration says of them
(:class:`~flexforce.datasets.robot.ModelUncertainty`, the ``[model_uncertainty]`` table), and
scales the sensor part by how far the fit's residuals lie outside their noise:

    sigma^2 = s0^2 sigma_est^2 + sum_j (F(theta + sigma_j e_j) - F(theta))^2

per contact normal force, with

- ``sigma_est``: the estimator's own standard deviation of the contact-frame normal force;
- ``s0^2``: the a-posteriori variance factor of the fit, the mean square of its whitened
  Newton-Euler and IMU residuals, when above 1 (at 1 the residuals are as the noise model says);
- one term per parameter ``j`` with a standard deviation above zero: the estimator run again on
  the same recording with that parameter moved by one standard deviation (the CoM along the local x
  and y axes, every spring and damper, the normal spring and damper alone), and for the contact
  switches the half-difference of the runs with every switch moved by the timing's standard
  deviation later and earlier.

Parameters are taken as independent; the sensitivities are finite differences of the estimator
itself, so the band holds for any estimator, at the cost of one run per parameter (two for the
timing).
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from flexforce.datasets.recording import Recording

__all__ = ["ModelBand", "model_band", "moved_com", "shifted_switches", "variance_factor"]

VARIANCE_FAMILIES = ("newton_euler", "imu")
"""The factor families whose whitened residuals give the variance factor."""


@dataclass
class ModelBand:
    """The model band of one estimate's contact normal forces."""

    sigma: np.ndarray
    """(N, C) standard deviation of each contact-frame normal force, N."""
    variance_factor: float
    """``s0^2``, the factor applied to the estimator's own variance (>= 1)."""
    components: dict = field(default_factory=dict)
    """Parameter -> RMS of its force change over the (step, contact) pairs in force, N."""
    stds: dict = field(default_factory=dict)
    """Parameter -> the standard deviation it was moved by (m, relative, s)."""


def variance_factor(est) -> float:
    """Mean square of the estimate's whitened Newton-Euler and IMU residuals, at least 1."""
    res = getattr(est, "residuals", None) or {}
    parts = [np.asarray(res[f], dtype=float).ravel() for f in VARIANCE_FAMILIES if f in res]
    if not parts:
        return 1.0
    r = np.concatenate(parts)
    r = r[np.isfinite(r)]
    return max(1.0, float(np.mean(r * r))) if r.size else 1.0


def moved_com(rec: Recording, model, offset_xy) -> Recording:
    """``rec`` with its inputs moved as a CoM offset ``offset_xy`` (m, local x and y) moves them
    (:meth:`flexforce.factors.effects.newton_euler.ComOffset.inputs`: the CoM, the inertia about it
    and the momentum)."""
    from flexforce.factors.effects import make_effect
    from flexforce.smoother.batch import BatchConfig
    from flexforce.smoother.problem import build_problem

    prob = build_problem(rec, model, BatchConfig())
    d = np.tile([float(offset_xy[0]), float(offset_xy[1]), 0.0], (rec.n, 1))
    c, _, _, inertia, inertia_dot, sigma, sigma_dot = make_effect("com-offset").inputs(prob, np.arange(rec.n), d)
    return dataclasses.replace(rec, com=c, inertia=inertia, inertia_dot=inertia_dot, sigma=sigma, sigma_dot=sigma_dot)


def shifted_switches(active: np.ndarray, steps: int) -> np.ndarray:
    """(N, C) contact states with every switch moved ``steps`` samples later (negative: earlier);
    the first and last states stay."""
    out = active.copy()
    n = active.shape[0]
    for i in range(active.shape[1]):
        a = active[:, i]
        for k in np.flatnonzero(a[1:] != a[:-1]) + 1:
            lo, hi = (k, min(k + steps, n)) if steps > 0 else (max(k + steps, 0), k)
            out[lo:hi, i] = a[k - 1] if steps > 0 else a[k]
    return out


def _scaled_springs(model, every: float = 1.0, normal: float = 1.0):
    """``model`` with every contact spring and damper scaled by ``every`` and the normal
    (contact-frame z) stiffness and damping by ``normal`` on top."""
    S = np.diag([1.0, 1.0, normal])
    cps = tuple(dataclasses.replace(cp, K_fs=every * S @ cp.K_fs, K_fd=every * S @ cp.K_fd,
                                    K_ts=every * cp.K_ts, K_td=every * cp.K_td)
                for cp in model.contact_params)
    return dataclasses.replace(model, contact_params=cps)


def normal_force(est, rec) -> np.ndarray:
    """(N, C) contact-frame normal force of an estimate."""
    from flexforce.compare.metrics import contact_frame_wrench

    return contact_frame_wrench(est.R, est.t, est.wrench, rec)[:, :, 2]


def normal_sigma(est, rec) -> np.ndarray:
    """(N, C) the estimator's own standard deviation of each contact-frame normal force (0 without
    a covariance)."""
    cov = getattr(est, "contact_wrench_cov", None)
    if cov is None:
        return np.zeros((rec.n, len(rec.contact_names)))
    normal = np.einsum("nij,ncjk->ncik", est.R, rec.contact_R)[..., :, 2]
    return np.sqrt(np.maximum(np.einsum("nci,ncij,ncj->nc", normal, cov[:, :, :3, :3], normal), 0.0))


def model_band(name: str, rec, model, est, options: dict | None = None) -> ModelBand | None:
    """The model band (module docstring) of ``est``, estimator ``name``'s estimate of ``rec`` under
    ``model``, run again with ``options`` for each parameter of ``model.model_uncertainty``.

    None when the model states no uncertainty or the recording has no contacts.
    """
    from flexforce.compare.estimators import run_estimator

    mu = getattr(model, "model_uncertainty", None)
    if mu is None or not rec.contact_names:
        return None
    opts = dict(options or {})
    base = normal_force(est, rec)
    on = rec.contact_active

    def run(r, m) -> np.ndarray:
        with warnings.catch_warnings():  # the sensor warnings of the estimate itself, again
            warnings.simplefilter("ignore")
            return normal_force(run_estimator(name, r, m, **opts), r)

    diffs: dict[str, np.ndarray] = {}
    stds = mu.perturbations()
    for key, std in stds.items():
        if key == "com_x":
            diffs[key] = run(moved_com(rec, model, (std, 0.0)), model) - base
        elif key == "com_y":
            diffs[key] = run(moved_com(rec, model, (0.0, std)), model) - base
        elif key == "stiffness":
            diffs[key] = run(rec, _scaled_springs(model, every=1.0 + std)) - base
        elif key == "vertical_stiffness":
            diffs[key] = run(rec, _scaled_springs(model, normal=1.0 + std)) - base
        elif key == "contact_timing":
            steps = max(1, int(round(std / rec.dt)))
            later = run(dataclasses.replace(rec, contact_active=shifted_switches(on, steps)), model)
            earlier = run(dataclasses.replace(rec, contact_active=shifted_switches(on, -steps)), model)
            diffs[key] = 0.5 * (later - earlier)
    s0 = variance_factor(est)
    var = s0 * normal_sigma(est, rec) ** 2
    for d in diffs.values():
        var = var + np.nan_to_num(d) ** 2
    comps = {k: round(float(np.sqrt(np.mean(d[on] ** 2))), 3) if on.any() else 0.0 for k, d in diffs.items()}
    return ModelBand(sigma=np.sqrt(var), variance_factor=s0, components=comps, stds=stds)
