r"""The seed paper's Extended Kalman Filter: the baseline every comparison is measured against.

Mifsud, Benallegue & Lamiraux (IROS 2015), sec. III-B, with DESIGN.md's corrections (the
physics is :mod:`flexforce.factors.physics`, shared with the smoothers).  See ``docs/ekf.md`` for
the derivation of Q, R and P0 and the reset policy.

State and model
---------------
The state is the paper's eq. (4), in its order and parametrisation (18 components)::

    x = (t, Omega, v, w, a, dw)      t [m], Omega = log R [rad], v = dt/dt [m/s],
                                     w [rad/s, world], a = d2t/dt2 [m/s^2], dw = dw/dt [rad/s^2]

Prediction from step k to k+1 (``dt`` the sample period)::

    R_{k+1} = exp(dt w_k + dt^2/2 dw_k) R_k,     Omega_{k+1} = log R_{k+1}
    t_{k+1} = t_k + dt v_k + dt^2/2 a_k
    v_{k+1} = v_k + dt a_k,                      w_{k+1} = w_k + dt dw_k
    (dw, a)_{k+1} = forward_dynamics(x_{k+1}, W_c(x_{k+1}; contacts_{k+1}), inputs_{k+1})
                                                                     eq. (24), (25) with (10), (12)

where the contact wrench ``W_c`` sums the spring-dampers of the contacts active at step k+1 --
the set may change from one step to the next.  The correction uses the gyrometer and the
accelerometer readings in the IMU frame, eq. (26)-(28), ``y = h(x_k; imu_k)``.

Jacobians
---------
The physics returns Jacobians with respect to world-frame increments ``(theta, t, w, v, dw, a)``;
with ``d_theta = J_l(Omega) d_Omega`` (:func:`flexforce.factors.so3.left_jacobian`) they become
Jacobians in the state's own parametrisation.  The step -- model, covariance prediction,
correction, outputs -- is compiled once (:mod:`flexforce.compare.ekf.kernel` on the physics core
:mod:`flexforce.factors.core`).  The tests hold it against a reference written with plain Kalman
algebra and numerical Jacobians (the authors' way), kept under ``tests/reference/ekf.py``.

Output
------
:func:`run_ekf` returns the common :class:`~flexforce.datasets.estimate.Estimate`: its ``cov`` is
over world-frame increments in the state layout ``(theta, t, w, v, dw, a)``
(:data:`flexforce.datasets.layout.STATE`), converted from the filter's ``(t, Omega, v, w, a, dw)``
(:data:`PAPER_ORDER`, a permutation of the layout's blocks).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from flexforce.compare.ekf import kernel as K
from flexforce.datasets import faults
from flexforce.datasets.estimate import Estimate
from flexforce.datasets.layout import STATE, STATE_DIM
from flexforce.datasets.recording import Recording
from flexforce.errors import ConfigError, DataError, EstimatorError, ModelError
from flexforce.factors import core, so3
from flexforce.factors.contact_limits import balance_near_switches, limit_world_wrenches, required_force
from flexforce.factors.footholds import rest_placements
from flexforce.factors.model import ModelConfig, check_unmodelled, unmodelled_acceleration
from flexforce.factors.physics import contact_arrays
from flexforce.options import (
    check_bool,
    check_choice,
    check_finite,
    check_fraction,
    check_int,
    check_positive,
    require_config,
    with_options,
)

__all__ = [
    "EKF", "EKFConfig", "run_ekf", "noise_model",
    "STATE_LABELS", "IMU_LABELS", "PAPER_ORDER", "PAPER_INDEX", "paper_to_world", "world_to_paper_cov",
]

PAPER_ORDER = ("t", "theta", "v", "w", "a", "dw")
"""The filter's state, eq. (4), as a permutation of the blocks of the state layout
(:data:`flexforce.datasets.layout.STATE`).  The block ``theta`` stands for the paper's
``Omega = log R``: its increments are the layout's up to ``d_theta = J_l(Omega) d_Omega``
(:func:`paper_to_world`), so that at ``Omega = 0`` the change of order is the permutation alone."""

PAPER_INDEX = STATE.index(PAPER_ORDER)
"""(18,) int: a vector in the state layout rearranged into the filter's order, ``s[PAPER_INDEX]``."""

STATE_LABELS = tuple(STATE.labels[i].replace("theta_", "Omega_") for i in PAPER_INDEX)
"""The filter's state, eq. (4): ``t_x .. dw_z`` in m, rad, m/s, rad/s, m/s^2, rad/s^2."""

IMU_LABELS = ("gyro_x [rad/s]", "gyro_y [rad/s]", "gyro_z [rad/s]",
              "accel_x [m/s^2]", "accel_y [m/s^2]", "accel_z [m/s^2]")
"""Components of the innovation (IMU frame)."""

# Slices of the paper's state x = (t, Omega, v, w, a, dw), in the order of PAPER_ORDER.
T, OM, V, W, A, DW = STATE.slices(PAPER_ORDER)
_I3 = np.eye(3)


# ----------------------------------------------------------------------------------------------
# Configuration
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EKFConfig:
    r"""Options of the EKF.  Noise levels left at ``None`` are derived from the model (docs/ekf.md).

    One rule for every recording: nothing here is tuned per scenario.
    """

    unmodelled_accel: float | None = None
    r"""Standard deviation of the unmodelled linear acceleration per sample, m/s^2 (what the
    contact law and Newton-Euler leave out).  ``None``: the accelerometer's per-sample noise
    ``ModelConfig.accel_sigma`` -- the model is trusted to the resolution of the sensor that
    checks it."""
    unmodelled_ang_accel: float | None = None
    r"""Standard deviation of the unmodelled angular acceleration per sample, rad/s^2.  ``None``:
    ``accel_sigma / l`` with ``l`` the distance (m) from the IMU to the centroid of the contacts at
    the first step: the angular acceleration whose tangential acceleration at the IMU equals the
    accelerometer's noise."""
    p0_scale: float = 1.0
    r"""Multiplies the prior standard deviations derived in :func:`noise_model` (dimensionless)."""
    z0: float = 0.0
    """Height of the ground plane on which the CoP is computed, m (0 for simulated data)."""
    min_force: float = 1e-6
    """Vertical force below which the CoP is undefined (NaN), N."""
    outputs: bool = True
    """Compute every step's world covariance, contact wrenches, their covariance and the CoP.
    ``False``: the state and the innovation only (the other fields of the Estimate are NaN)."""
    on_covariance_failure: str = "raise"
    """``raise`` (EstimatorError) or ``reset`` (P <- P0 with a RuntimeWarning) when the state
    covariance stops being positive definite."""
    nis_limit: float = 1e6
    """Normalised innovation squared (dimensionless, chi^2 with 6 dof, mean 6) above which a step
    counts as diverged."""
    nis_steps: int = 20
    """Consecutive diverged steps after which the filter raises EstimatorError (without the gate,
    ``imu_gate = None``; with it, ``gate_max_time`` applies to each sensor)."""
    touchdown: str = "local"
    """Rest placement of a contact episode that starts during the run (active at step k, not at
    k-1): ``local`` -- the given rest placements (default: the contact's local placement, the
    paper's convention); ``zero-deflection`` -- the contact's world placement at the predicted
    state, ``p_r = R p_l + t``, ``R_r = R R_l``, so that the landing spring starts unloaded where
    the foot touches.  Episodes active at the first step keep the given rest placements."""
    ground_tilt_weight: float = 0.0
    """With ``touchdown='zero-deflection'``: fraction (0 to 1, dimensionless) of the landing sole's
    roll and pitch with respect to gravity removed from its rest orientation (1: the foothold is
    level, the yaw kept; 0: the sole's orientation as it lands)."""
    ground_height_weight: float = 0.0
    """With ``touchdown='zero-deflection'``: fraction (0 to 1) of the landing sole's height above the
    floor (the plane z = 0 of the world, where the first step's contacts rest) removed from its rest
    position (1: the foothold is on the floor; 0: where the foot lands by the estimate)."""
    imu_gate: float | None = 1e6
    """Gross-fault gate on each IMU sensor's innovation (gyrometer and accelerometer apart): the
    normalised innovation squared (dimensionless, against the sensor's block of S) above which the
    sample is left out.  1e6 is a whitened innovation of 1000 sigma: a spike or a stuck sensor, far
    beyond the model errors of a walk (whitened norms up to 96 measured at touch-downs against the
    model's convention, NIS 1e3-1e4 on real walks), which a lower gate would wrongly discard
    (docs/ekf.md, "Robustness").  None: no gate."""
    gate_max_time: float = 1.0
    """With the gate: longest run (s) of one sensor's samples with a NIS above ``nis_limit`` (so far
    beyond the gate that they barely correct the state) before the filter stops with an
    EstimatorError naming the sensor and the time: a stuck sensor the range does not catch, or a
    diverged filter.  Shorter runs are ridden out (a 0.5 s plateau at 16 g leaves the estimate
    unchanged, tests/test_faults.py) and reported in ``meta['rejected']``."""

    def __post_init__(self):
        o = "EKFConfig"
        check_unmodelled(o, self.unmodelled_accel, self.unmodelled_ang_accel,
                         ("the accelerometer's", "accel_sigma / l"))
        check_positive(o, "p0_scale", self.p0_scale, "", "a positive multiplier of the prior standard deviations")
        check_finite(o, "z0", self.z0, "m", "a finite height")
        check_positive(o, "min_force", self.min_force, "N", "a positive force")
        check_bool(o, "outputs", self.outputs)
        check_choice(o, "on_covariance_failure", self.on_covariance_failure, ("raise", "reset"))
        check_positive(o, "gate_max_time", self.gate_max_time, "s", "a positive duration")
        check_positive(o, "nis_limit", self.nis_limit, "", "a positive normalised innovation squared (chi^2, 6 dof)")
        check_int(o, "nis_steps", self.nis_steps, 1, "steps", "an integer >= 1")
        check_choice(o, "touchdown", self.touchdown, ("local", "zero-deflection"))
        check_fraction(o, "ground_tilt_weight", self.ground_tilt_weight,
                       "a number in [0, 1] (the fraction of the sole's tilt removed at a touch-down)")
        check_fraction(o, "ground_height_weight", self.ground_height_weight,
                       "a number in [0, 1] (the fraction of the sole's height above the floor removed at a touch-down)")
        check_positive(o, "imu_gate", self.imu_gate, "",
                       "a positive NIS threshold (1e6: 1000 sigma) or None (no gate)", optional=True)


# ----------------------------------------------------------------------------------------------
# Parametrisation changes
# ----------------------------------------------------------------------------------------------


def paper_to_world(Omega: np.ndarray) -> np.ndarray:
    r"""18x18 ``M`` with ``d_world = M d_x``: world increments ``(theta, t, w, v, dw, a)`` from
    increments of the paper's ``(t, Omega, v, w, a, dw)``; ``d_theta = J_l(Omega) d_Omega``."""
    M = np.zeros((STATE_DIM, STATE_DIM))
    for name, paper in zip(PAPER_ORDER, STATE.slices(PAPER_ORDER)):
        M[STATE[name], paper] = so3.left_jacobian(Omega) if name == "theta" else _I3
    return M


def world_to_paper_cov(Omega: np.ndarray, P_world: np.ndarray) -> np.ndarray:
    """Covariance over world increments ``(theta, t, w, v, dw, a)`` to the filter's parametrisation."""
    Minv = np.linalg.inv(paper_to_world(Omega))
    return Minv @ P_world @ Minv.T


def _split(x):
    return x[T], x[OM], x[V], x[W], x[A], x[DW]


# ----------------------------------------------------------------------------------------------
# Noise model
# ----------------------------------------------------------------------------------------------


class NoiseModel(NamedTuple):
    """Q (per step), R and the prior's standard deviations, see :func:`noise_model`."""

    Q: np.ndarray
    """18x18 process noise in the filter's order, for a small Omega (see EKF.process_noise)."""
    R: np.ndarray
    """6x6 IMU noise."""
    sigma_a: float
    """Unmodelled linear acceleration per sample, m/s^2."""
    sigma_dw: float
    """Unmodelled angular acceleration per sample, rad/s^2."""
    p0_sigma: np.ndarray
    """(12,) prior standard deviations of (t, Omega, v, w): m, rad, m/s, rad/s."""


def _contact_totals(rec: Recording, model: ModelConfig, k: int):
    """Summed stiffness over the contacts active at step k (N/m, N m/rad) and their centroid."""
    act = rec.active_contacts(k)
    if not act:
        raise DataError(f"no contact is active at sample {k}; the EKF needs at least one contact "
                        "to start (the flexibility is not defined in the air)")
    kf = sum(float(np.trace(model.contact_params[i].K_fs)) / 3.0 for i in act)
    kt = sum(float(np.trace(model.contact_params[i].K_ts)) / 3.0 for i in act)
    centroid = np.mean([rec.contact_p[k, i] for i in act], axis=0)
    return kf, kt, centroid


def noise_model(rec: Recording, model: ModelConfig, config: EKFConfig = EKFConfig()) -> NoiseModel:
    r"""Q, R and the prior derived from the sensor noise model and the nominal model (docs/ekf.md).

    * R: ``diag(gyro_sigma^2 I3, accel_sigma^2 I3)`` (ModelConfig, per-sample sigmas).
    * Unmodelled acceleration per sample: ``sigma_a = accel_sigma`` (m/s^2) and
      ``sigma_dw = accel_sigma / l`` with ``l`` the IMU's distance to the contacts' centroid.
    * Q: the unmodelled acceleration is white at the samples and enters the acceleration block
      only (``sigma^2`` per axis); position and velocity receive it at the next step through the
      integration of the acceleration state (docs/ekf.md explains why not the textbook
      discrete white-noise-acceleration Q, which counts it twice here).
    * P0: deflections of the order of the static ones: ``sigma_t = m g / sum k_fs`` (the static
      sinking under the weight), ``sigma_Omega = sigma_t / h`` (the tilt about the contacts that
      moves the CoM, at height h above them, by as much), velocities ``omega_n sigma`` with the
      natural pulsations ``omega_n^2 = sum k_fs / m`` and ``sum k_ts / (m h^2)``; the
      accelerations' prior follows from the dynamics.
    """
    g = model.gravity
    m = rec.mass
    kf, kt, centroid = _contact_totals(rec, model, 0)
    height = float(max(rec.com[0, 2] - centroid[2], 1e-3))
    sa0, sdw0 = unmodelled_acceleration(model.accel_sigma, rec.imu_p[0], centroid)
    sa = config.unmodelled_accel if config.unmodelled_accel is not None else sa0
    sdw = config.unmodelled_ang_accel if config.unmodelled_ang_accel is not None else sdw0
    Rn = np.diag([model.gyro_sigma**2] * 3 + [model.accel_sigma**2] * 3)
    Q = np.zeros((18, 18))
    blk = np.diag([0.0, 0.0, 1.0])  # (position, velocity, acceleration): acceleration only
    for pos, vel, acc, s in ((T, V, A, sa), (OM, W, DW, sdw)):
        idx = [pos, vel, acc]
        for i in range(3):
            for j in range(3):
                Q[idx[i], idx[j]] = s * s * blk[i, j] * _I3
    s_t = m * g / kf
    s_om = s_t / height
    s_v = math.sqrt(kf / m) * s_t
    s_w = math.sqrt(kt / (m * height**2)) * s_om
    p0 = config.p0_scale * np.array([s_t] * 3 + [s_om] * 3 + [s_v] * 3 + [s_w] * 3)
    return NoiseModel(Q, Rn, sa, sdw, p0)


# ----------------------------------------------------------------------------------------------
# The filter
# ----------------------------------------------------------------------------------------------


def _floor_height(rec, rest_p) -> float:
    """Height (m) of the floor in the world: the mean rest height of the contacts in force at the
    first step (0 when none is)."""
    on = rec.contact_active[0]
    return float(np.mean(rest_p[0, on, 2])) if on.any() else 0.0


class EKF:
    r"""The paper's EKF over a recording: its model functions and the compiled step.

    ``transition``, ``measurement``, ``dynamics`` and ``outputs`` are the compiled kernel's
    (:mod:`flexforce.compare.ekf.kernel`, on the physics core) and mutate nothing; :meth:`step` is
    the step :func:`run_ekf` runs.  The tests hold it against a reference written with the plain
    Kalman algebra (``tests/reference/ekf.py``).

    ``rest_p``, ``rest_R``: (N, C, 3), (N, C, 3, 3) the contacts' rest placements in the world
    per step; default the recording's local placements.
    """

    def __init__(self, rec: Recording, model: ModelConfig, config: EKFConfig = EKFConfig(), rest_p=None,
                 rest_R=None):
        if len(model.contact_params) != len(rec.contact_names):
            raise ConfigError(f"the model has {len(model.contact_params)} contact(s), the recording "
                              f"{len(rec.contact_names)} ({', '.join(rec.contact_names)})")
        self.rec = rec
        self.model = model
        self.config = config
        self.dt = rec.dt
        self.g = model.gravity
        self.noise = noise_model(rec, model, config)
        rest_p, rest_R = rest_placements(rec, rest_p, rest_R)
        self.imu_use, self.imu_missing, self.imu_saturated = faults.imu_validity(
            rec.gyro, rec.accel, float(getattr(model, "gyro_range", math.inf)),
            float(getattr(model, "accel_range", math.inf)))
        self.gates = np.zeros(3) if config.imu_gate is None else np.full(3, float(config.imu_gate))
        self.U = K.pack_inputs(rec, rest_p, rest_R, self.imu_use)
        self.CP = K.pack_params(model.contact_params)
        self.C = K.pack_constants(self.noise.Q, self.noise.R, self.dt, rec.mass, self.g, config.z0,
                                  config.min_force, config.touchdown == "zero-deflection", config.ground_tilt_weight,
                                  config.ground_height_weight, _floor_height(rec, rest_p), self.gates)
        self.WS = K.workspace()

    # --- model functions ----------------------------------------------------------------------
    def dynamics(self, R, t, w, v, k: int, jacobian: bool = False):
        """Accelerations ``(a, dw)`` from the contact law and Newton-Euler at step k's inputs.

        With ``jacobian``, also the 6x12 Jacobian of ``(a, dw)`` -- filter order -- with respect
        to world increments ``(theta, t, w, v)``.
        """
        acc = np.empty(6)
        G = np.empty((6, 12))
        f = lambda a: np.ascontiguousarray(a, dtype=float)  # noqa: E731
        if not K.dynamics_into(f(R), f(t), f(w), f(v), self.U[k], self.CP, self.rec.mass, self.g, acc, G):
            raise self._singular(k)
        return (acc, G) if jacobian else acc

    def _singular(self, k: int) -> ModelError:
        return ModelError(f"the Newton-Euler system is singular at sample {k}: check the mass "
                          f"({self.rec.mass} kg, expected > 0) and the inertia inputs")

    def transition(self, x: np.ndarray, k: int, jacobian: bool = False):
        """``f(x_{k-1})``: the predicted state at step k, and its 18x18 Jacobian ``F``."""
        x = np.ascontiguousarray(x, dtype=float)
        x1 = np.empty(18)
        F = np.empty((18, 18))
        if not K.transition(x, self.U[k], self.CP, self.dt, self.rec.mass, self.g, x1, F):
            raise self._singular(k)
        return (x1, F) if jacobian else x1

    def measurement(self, x: np.ndarray, k: int, jacobian: bool = False):
        """``h(x_k)``: gyro and accelerometer readings (IMU frame), eq. (26)-(28), and ``H`` (6x18)."""
        x = np.ascontiguousarray(x, dtype=float)
        hx = np.empty(6)
        H = np.empty((6, 18))
        K.measurement(x, self.U[k], self.g, hx, H)
        return (hx, H) if jacobian else hx

    # --- filter steps --------------------------------------------------------------------------
    def initial_state(self, x0: np.ndarray | None = None, P0: np.ndarray | None = None):
        """The prior at step 0: ``x0`` (default: rest, zero velocity) with accelerations from
        the dynamics, and ``P0`` (default: :func:`noise_model`'s, accelerations' block mapped
        through the dynamics' Jacobian plus the unmodelled acceleration)."""
        if x0 is None:
            x0 = np.zeros(18)
        x0 = np.asarray(x0, dtype=float)
        if x0.shape == (12,):
            x0 = np.concatenate([x0, np.zeros(6)])
        if x0.shape != (18,) or not np.all(np.isfinite(x0)):
            raise ConfigError(f"x0 must be 18 finite numbers (t, Omega, v, w, a, dw), got {x0!r}")
        t, Om, v, w, _, _ = _split(x0)
        R = so3.exp(Om)
        acc, G = self.dynamics(R, t, w, v, 0, jacobian=True)
        x = np.concatenate([x0[:12], acc])
        if P0 is not None:
            P0 = np.asarray(P0, dtype=float)
            if P0.shape != (18, 18) or not np.all(np.isfinite(P0)):
                raise ConfigError(f"P0 must be a finite 18x18 matrix, got shape {P0.shape}")
            try:
                np.linalg.cholesky(P0)
            except np.linalg.LinAlgError as err:
                raise ConfigError("P0 is not positive definite") from err
            return x, 0.5 * (P0 + P0.T)
        P = np.zeros((18, 18))
        P[:12, :12] = np.diag(self.noise.p0_sigma**2)
        # The accelerations are functions of (t, Omega, v, w): same map as in transition().
        D = np.zeros((12, 12))
        D[0:3, OM] = so3.left_jacobian(Om)
        D[3:6, T] = _I3
        D[6:9, W] = _I3
        D[9:12, V] = _I3
        GD = G @ D
        P[12:, :12] = GD @ P[:12, :12]
        P[:12, 12:] = P[12:, :12].T
        P[12:, 12:] = GD @ P[:12, :12] @ GD.T + self.noise.Q[12:, 12:]
        return x, 0.5 * (P + P.T)

    # --- outputs ---------------------------------------------------------------------------
    def outputs(self, x: np.ndarray, P: np.ndarray, k: int) -> dict:
        """World-frame covariance, per-contact wrenches, CoP and their covariances at step k."""
        n_c = len(self.rec.contact_names)
        o = {"cov": np.empty((18, 18)), "wrench": np.empty((n_c, 6)), "wrench_cov": np.empty((6, 6)),
             "cop": np.empty(3), "cop_cov": np.empty((2, 2))}
        K.outputs(np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(P, dtype=float), self.U[k], self.CP,
                  self.config.z0, self.config.min_force, self.WS, o["cov"], o["wrench"], o["wrench_cov"], o["cop"],
                  o["cop_cov"])
        o["R"] = so3.exp(x[OM])
        return o

    def step(self, k: int, x: np.ndarray, P: np.ndarray, out: _Outputs, predict: bool = True) -> int:
        """The compiled step: predict (k > 0) and update in place, outputs into ``out`` at k."""
        return K.step(k, x, P, self.U, self.CP, self.C, self.WS, out.row, predict, out.want)


def _wrap(x: np.ndarray) -> np.ndarray:
    """Keep ``|Omega| <= pi`` (the same rotation) after an additive correction."""
    Om = x[OM]
    if float(Om @ Om) > math.pi**2:
        x = x.copy()
        x[OM] = so3.log(so3.exp(Om))
    return x


# ----------------------------------------------------------------------------------------------
# Input checks
# ----------------------------------------------------------------------------------------------

_FINITE_FIELDS = ("com", "com_vel", "com_acc", "inertia", "inertia_dot", "sigma", "sigma_dot", "imu_R",
                  "imu_p", "imu_v", "imu_a", "imu_w", "contact_p", "contact_R")
"""Fields that must be finite; a missing gyro or accelerometer reading is skipped instead
(:func:`flexforce.datasets.faults.check_missing` bounds how many)."""


def check_recording(rec: Recording, model: ModelConfig) -> None:
    """Raise DataError naming the field, sample and time of the first NaN or inf the EKF would read."""
    time_s = rec.time
    for name in _FINITE_FIELDS:
        arr = np.asarray(getattr(rec, name))
        if name in ("contact_p", "contact_R"):
            # Rest placements matter only while the contact is active.
            flat = arr.reshape(rec.n, arr.shape[1], -1)
            bad = ~np.isfinite(flat).all(axis=2) & rec.contact_active
            bad_k = bad.any(axis=1)
        else:
            bad_k = ~np.isfinite(arr.reshape(rec.n, -1)).all(axis=1)
        if bad_k.any():
            k = int(np.flatnonzero(bad_k)[0])
            raise DataError(f"field '{name}' is not finite (NaN or inf) at sample {k}, "
                            f"t = {time_s[k]:.3f} s; the EKF needs finite inputs and readings")
    faults.check_missing(time_s, rec.gyro, rec.accel)
    if not (math.isfinite(rec.mass) and rec.mass > 0):
        raise DataError(f"mass must be a positive number of kg, got {rec.mass}")
    if rec.n < 2:
        raise DataError(f"recording has {rec.n} sample(s); at least 2 are needed")
    for name in ("gyro_sigma", "accel_sigma"):
        s = getattr(model, name)
        if not (math.isfinite(s) and s > 0):
            raise ConfigError(f"ModelConfig.{name} must be a positive number, got {s}")


# ----------------------------------------------------------------------------------------------
# Running over a recording
# ----------------------------------------------------------------------------------------------


def run_ekf(rec: Recording, model: ModelConfig, config: EKFConfig | None = EKFConfig(), x0: np.ndarray | None = None,
            P0: np.ndarray | None = None, rest_p=None, rest_R=None, progress: Callable[[float], None] | None = None,
            **options) -> Estimate:
    """Run the paper's EKF over a recording and return the common Estimate.

    Args:
        rec: the recording (inputs, active contacts, IMU readings).
        model: the model assumptions (stiffness, sensor noise, gravity).
        config: an :class:`EKFConfig` (None, the former default, is ``EKFConfig()``).
        x0: initial state (t, Omega, v, w[, a, dw]); default: rest.  Accelerations are recomputed
            from the dynamics.
        P0: 18x18 initial covariance in the filter's order; default: derived (docs/ekf.md).
        rest_p, rest_R: (N, C, 3), (N, C, 3, 3) the contacts' rest placements in the world per
            step (footholds); default the recording's local placements ``contact_p``, ``contact_R``.
        progress: called with the fraction done.
        options: fields of :class:`EKFConfig` replacing those of ``config`` (the older calling
            convention, ``run_ekf(rec, model, touchdown="zero-deflection")``).

    Raises:
        ConfigError: ``config`` is not an EKFConfig, an unknown option (the known ones listed), a
            or a bad value.
        DataError: NaN or inf in an input or a reading (naming the field, the sample, the time).
        EstimatorError: covariance no longer positive definite (unless ``on_covariance_failure =
            "reset"``), or divergence (NIS above ``nis_limit`` for ``nis_steps`` steps).
    """
    if config is None:
        config = EKFConfig()
    require_config(config, EKFConfig, "EKF")
    config = with_options(config, options, "EKF")
    check_recording(rec, model)
    if model.use_ft:
        warnings.warn("the seed paper's EKF does not fuse F/T readings; use_ft is ignored", RuntimeWarning,
                      stacklevel=2)
    ekf = EKF(rec, model, config, rest_p, rest_R)
    n, n_c = rec.n, len(rec.contact_names)
    out = _Outputs(n, n_c, config.outputs)
    x, P = ekf.initial_state(x0, P0)
    x = np.ascontiguousarray(x, dtype=float)
    P = np.ascontiguousarray(P, dtype=float)
    P_reset = P.copy()
    start = time.perf_counter()
    diverged = 0
    beyond = np.zeros(2, dtype=int)  # per sensor: consecutive samples with a NIS above nis_limit
    max_run = max(1, int(round(config.gate_max_time / ekf.dt)))
    every = max(1, n // 100)
    step = K.step
    U, CP, C, WS, row, want = ekf.U, ekf.CP, ekf.C, ekf.WS, out.row, out.want
    for k in range(n):
        t0 = time.perf_counter()
        status = step(k, x, P, U, CP, C, WS, row, True, want)  # x and P updated in place
        out.time_per_step[k] = time.perf_counter() - t0
        if status:
            _handle_failure(status, k, ekf, x, P, P_reset, out)
        nis = out.nis[k]
        if config.imu_gate is not None:
            far = out.sensor_nis[k] > config.nis_limit
            beyond = np.where(far, beyond + 1, 0)
            if (beyond >= max_run).any():
                _gate_timeout(ekf, out, k, int(np.argmax(beyond)), int(beyond.max()))
        if config.imu_gate is None and nis > config.nis_limit:
            diverged += 1
            if diverged >= config.nis_steps:
                raise EstimatorError(
                    f"EKF diverged: the normalised innovation squared has exceeded {config.nis_limit:g} "
                    f"(chi^2, 6 dof, mean 6) for {diverged} consecutive steps, up to sample {k} "
                    f"(t = {rec.time[k]:.3f} s, NIS = {nis:.3g}; gyro {out.sensor_nis[k, 0]:.3g}, accel "
                    f"{out.sensor_nis[k, 1]:.3g}); check the model (stiffness, mass, contacts), the IMU "
                    "placement, and that sensor (stuck or saturated: set its range in the robot's [imu_noise])")
        else:
            diverged = 0
        if progress is not None and (k % every == 0 or k == n - 1):
            progress((k + 1) / n)
    total = time.perf_counter() - start
    est = out.estimate(rec, ekf, total)
    est.meta["rejected"] = rejected_samples(ekf, out)
    est.meta["imu_gate"] = None if config.imu_gate is None else {"nis": float(config.imu_gate)}
    faults.warn_summary("EKF", est.meta["rejected"], stacklevel=2)
    return est


def _gate_timeout(ekf: EKF, out: _Outputs, k: int, sensor: int, run: int) -> None:
    rec = ekf.rec
    name = faults.IMU_SENSORS[sensor][0]
    k0 = k - run + 1
    raise EstimatorError(
        f"EKF: the {name} has disagreed with the model beyond the gate (NIS above {ekf.config.nis_limit:g}, "
        f"chi^2 with 3 dof) for {run} consecutive samples, from sample {k0} (t = {rec.time[k0]:.3f} s) to "
        f"{k} (t = {rec.time[k]:.3f} s, NIS = {out.sensor_nis[k, sensor]:.3g}), longer than "
        f"EKFConfig.gate_max_time = {ekf.config.gate_max_time:g} s: a stuck or saturated {name} (set its "
        "range in the robot's [imu_noise]) or a diverged filter; the estimate is not trustworthy past "
        f"t = {rec.time[k0]:.3f} s")


def rejected_samples(ekf: EKF, out: _Outputs) -> list[dict]:
    """The IMU samples the filter gave less weight: missing and saturated axes (left out), and the
    sensors beyond the gate (weight 1 / inflation)."""
    rec = ekf.rec
    time_s = rec.time
    y = np.concatenate([rec.gyro, rec.accel], axis=1)
    entries = faults.masked_entries(time_s, y, ekf.imu_missing, ekf.imu_saturated)
    for sn, (name, _) in enumerate(faults.IMU_SENSORS):
        for k in np.flatnonzero(out.inflation[:, sn] > 1.0):
            entries.append(faults.entry(time_s[k], k, name, "norm", "outlier", math.sqrt(out.sensor_nis[k, sn]),
                                        1.0 / out.inflation[k, sn]))
    entries.sort(key=lambda e: (e["step"], e["sensor"]))
    return entries


_STATUS = {1: "the predicted state covariance", 2: "the innovation covariance", 3: "the corrected state covariance",
           4: "the state"}


def _handle_failure(status: int, k: int, ekf: EKF, x, P, P_reset, out: _Outputs) -> None:
    """Raise, or (``on_covariance_failure='reset'``) restart P from P0 and redo step k's update."""
    rec = ekf.rec
    where = f"at sample {k} (t = {rec.time[k]:.3f} s)"
    if status == 5:
        raise ModelError(f"the Newton-Euler system is singular {where}: check the mass ({rec.mass} kg, expected "
                         "> 0) and the inertia inputs")
    what = _STATUS.get(status, "the filter")
    msg = f"{what} is not positive definite and finite {where}"
    if status == 4 or not np.all(np.isfinite(x)) or ekf.config.on_covariance_failure == "raise":
        raise EstimatorError(msg + "; the filter cannot continue (EKFConfig(on_covariance_failure='reset') "
                                   "restarts the covariance from P0)")
    warnings.warn(msg + "; covariance reset to P0, state kept (EKFConfig.on_covariance_failure='reset')",
                  RuntimeWarning, stacklevel=3)
    P[...] = P_reset
    if ekf.step(k, x, P, out, predict=False):
        raise EstimatorError(msg + "; the reset to P0 did not recover the filter")


def contact_wrench_cov(ekf: EKF, R: np.ndarray, x: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(N, C, 6, 6) covariance of each contact's wrench, ``J_c P J_c^T`` with ``J_c`` the contact
    law's Jacobian at the estimate (world-frame increments of ``(theta, t, w, v)``, the compiled
    :func:`flexforce.factors.core.contact_all`) and the rest placements the filter used
    (:attr:`EKF.U`, the landings' too); zero while inactive.  The law itself is exact in the
    filter: the spread is the state's alone."""
    n, n_c = ekf.rec.n, len(ekf.rec.contact_names)
    u = ekf.U[:, K.NU0:K.NU0 + K.NUC * n_c].reshape(n, n_c, K.NUC)
    q = np.ascontiguousarray(np.concatenate([x[:, T], x[:, W], x[:, V], np.zeros((n, 6))], axis=1))
    (K_fs, K_fd, K_ts, K_td), beta, iso = contact_arrays(ekf.model.contact_params)
    c = np.ascontiguousarray
    J = np.empty((n, n_c, 6, STATE_DIM))
    core.contact_all(c(R, dtype=float), q, np.zeros((n, n_c, 6)), u[:, :, 0] != 0.0, c(u[:, :, 1:4]),
                     c(u[:, :, 4:13]).reshape(n, n_c, 3, 3), c(u[:, :, 13:16]), c(u[:, :, 16:25]).reshape(n, n_c, 3, 3),
                     K_fs, K_fd, K_ts, K_td, beta, iso, np.empty((n, n_c, 6)), J, np.empty((0, 1, 6, 6)))
    Jx = J[..., :12]  # (theta, t, w, v): the law does not depend on the accelerations
    return Jx @ cov[:, None, :12, :12] @ Jx.transpose(0, 1, 3, 2)


class _Outputs:
    """Preallocated per-step outputs: one row per step, filled in place by the compiled step;
    the named fields are views into it."""

    # Views into ``row``, set in __init__ from the kernel's out_layout.
    x: np.ndarray
    cov: np.ndarray
    wrench: np.ndarray
    wrench_cov: np.ndarray
    cop: np.ndarray
    cop_cov: np.ndarray
    innovation: np.ndarray
    S: np.ndarray
    white: np.ndarray
    nis: np.ndarray
    sensor_nis: np.ndarray
    inflation: np.ndarray

    def __init__(self, n: int, n_c: int, want: bool = True):
        layout = K.out_layout(n_c)
        self.want = bool(want)
        self.row = np.zeros((n, layout["_width"][0]))
        if not self.want:
            self.row[:] = np.nan
        for name, (o, shape) in layout.items():
            if name != "_width":
                size = int(np.prod(shape)) if shape else 1
                view = self.row[:, o:o + size]
                setattr(self, name, view.reshape((n,) + shape) if shape else view[:, 0])
        self.time_per_step = np.zeros(n)

    def estimate(self, rec: Recording, ekf: EKF, total: float) -> Estimate:
        x = self.x
        R = np.array([so3.exp(Om) for Om in x[:, OM]])
        nm = ekf.noise
        c = np.array
        wrench, excess, limits = c(self.wrench), None, None
        cop = c(self.cop)
        balanced = None
        if self.want:
            law = wrench
            # a zero-deflection touch-down lands the spring unloaded: the law's forces are kept
            window = float(getattr(ekf.model, "switch_window", 0.0))
            if window > 0 and ekf.config.touchdown != "zero-deflection":
                unexplained = required_force(R, x[:, W], x[:, DW], x[:, A], rec) - wrench[:, :, :3].sum(axis=1)
                wrench, balanced = balance_near_switches(R, x[:, T], wrench, unexplained, rec, window)
            wrench, excess, limits = limit_world_wrenches(R, x[:, T], wrench, rec, ekf.model)
            changed = np.any(wrench != law, axis=(1, 2))
            if changed.any():
                rows = np.flatnonzero(changed)
                summed = np.ascontiguousarray(wrench[rows].sum(axis=1), dtype=float)
                part, part_J = np.empty((len(rows), 3)), np.empty((len(rows), 3, 6))
                core.centers_of_pressure(summed, ekf.config.z0, ekf.config.min_force, part, part_J)
                cop[rows] = part
        meta = {"contact_limits": limits} if limits is not None else {}
        if balanced is not None:
            meta["switch_balance"] = balanced
        return Estimate(
            estimator="ekf", t_ns=rec.t_ns.copy(), contact_names=tuple(rec.contact_names),
            R=R, t=x[:, T].copy(), w=x[:, W].copy(), v=x[:, V].copy(), dw=x[:, DW].copy(), a=x[:, A].copy(),
            wrench=wrench, wrench_excess=excess, cop=cop, cov=c(self.cov), wrench_cov=c(self.wrench_cov),
            contact_wrench_cov=contact_wrench_cov(ekf, R, x, self.cov) if self.want else None,
            cop_cov=c(self.cop_cov), residuals={"imu": c(self.white)}, residual_labels={"imu": IMU_LABELS},
            innovation=c(self.innovation), innovation_cov=c(self.S), time_per_step=self.time_per_step,
            total_time=total,
            meta={"kernel": "numba", "outputs": self.want,
                  "touchdown": ekf.config.touchdown, "ground_tilt_weight": ekf.config.ground_tilt_weight,
                  "sigma_unmodelled_accel": nm.sigma_a, "sigma_unmodelled_ang_accel": nm.sigma_dw,
                  "p0_sigma": nm.p0_sigma.tolist(), "gyro_sigma": ekf.model.gyro_sigma,
                  "accel_sigma": ekf.model.accel_sigma, "mean_nis": float(np.mean(self.nis)), "z0": ekf.config.z0,
                  **meta},
        )
