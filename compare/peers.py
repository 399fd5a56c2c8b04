r"""GTSAM's proprioceptive legged estimators as peers of flexforce's: IMU plus leg kinematics, no model
of the flexibility, run on a :class:`~flexforce.datasets.recording.Recording`.

GTSAM 4.3 ships four estimators of the base state of a legged robot from an IMU and the feet's
positions by forward kinematics (``gtsam/navigation/LeggedEstimator.h``): the contact-aided invariant
EKF of Hartley et al. [1] (``LeggedInvariantEKF``), its variant with the contact update solved as a
small graph (``LeggedInvariantIEKF``), and two fixed-lag smoothers over contact events
(``LeggedFixedLagSmoother``, ``LeggedCombinedFixedLagSmoother``).  The state is the IMU's pose and
velocity in the world, ``NavState(world_R_imu, world_p_imu, world_v_imu)``, plus one world foothold
per foot; a foothold is assumed still while its foot is in contact.

How a Recording drives them (:func:`run_gtsam_legged`):

- IMU: every sample's gyro (rad/s) and accelerometer (m/s^2) readings in the IMU frame, with the
  step to the previous sample as ``dt``; white-noise densities from the model the estimators assume
  (``ModelConfig.gyro_sigma``, ``accel_sigma``, per-sample sigmas: density^2 = sigma^2 dt), gravity
  ``ModelConfig.gravity`` along -z.  A non-finite reading is skipped, its ``dt`` carried to the next.
- Feet: the GTSAM "body" frame is the IMU frame itself (``body_P_imu`` = identity) and each active
  contact is measured at ``imu_p_contact = local_R_imu^T (local_p_contact - local_p_imu)`` from the
  recording's IMU placement in the local frame (``imu_R``, ``imu_p``): the IMU moves in the local frame
  as the robot walks, which one fixed mounting could not describe.
- Contacts: the recording's ``contact_active``; a contact made at a sample is a touchdown.  GTSAM's
  one-time full-contact initialiser needs three feet or more in contact at once and holds the
  estimate still until then (a biped never gets there): it is off, the filter starts from
  :func:`initial_state`.
- Start: the flexibility at the identity (local frame = world at the first sample, as flexforce's
  estimators start), so the IMU starts at its local placement, the feet in contact at their
  kinematic positions.

What the Estimate's fields mean for a peer.  A peer estimates the IMU's world pose, not a
flexibility; the Estimate holds the flexibility that puts the IMU where the peer says, given its
placement in the local frame:

- ``R = world_R_imu local_R_imu^T``, ``t = world_p_imu - R local_p_imu``: then ``R local_R_base``
  is the base orientation the IMU's estimate implies, which is what the tilt against motion capture
  (:func:`flexforce.compare.metrics.base_tilt_error`) compares, and on simulated data ``R`` is compared
  with the true flexibility like flexforce's estimators' (yaw included, unobserved by both);
- ``w = world_R_imu omega_imu - R local_w_imu`` (rad/s, world), ``v = world_v_imu - w x (R local_p_imu)
  - R local_v_imu`` (m/s): the flexibility's velocities by the same composition;
- ``dw``, ``a``, the wrenches and the CoP are NaN: a peer has no dynamics and estimates no forces.

[1] R. Hartley, M. Ghaffari, R. M. Eustice, J. W. Grizzle, "Contact-aided invariant extended Kalman
filtering for robot state estimation", IJRR 39(4), 2020.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from flexforce.datasets.estimate import Estimate
from flexforce.errors import ConfigError, DataError, EstimatorError
from flexforce.options import check_choice, check_positive

if TYPE_CHECKING:
    from flexforce.datasets.recording import Recording
    from flexforce.factors.model import ModelConfig

__all__ = ["CHEAP_PEERS", "KINDS", "PEERS", "PeerConfig", "initial_state", "run_gtsam_legged", "run_peer"]

KINDS = ("invariant-ekf", "invariant-iekf", "fixed-lag", "combined-fixed-lag")
"""The GTSAM estimators :func:`run_gtsam_legged` drives: ``LeggedInvariantEKF``, ``LeggedInvariantIEKF``,
``LeggedFixedLagSmoother``, ``LeggedCombinedFixedLagSmoother``."""

PEERS = {"gtsam-invariant-ekf": "invariant-ekf", "gtsam-fixed-lag": "fixed-lag"}
"""Row name (summary key with ``_``) -> kind, of the peers a comparison can add
(:func:`flexforce.compare.runner.compare`), in the order of their rows."""

CHEAP_PEERS = ("gtsam-invariant-ekf",)
"""The peers a comparison adds by default: those costing a few tens of microseconds per step (the
invariant EKF); the fixed-lag smoother solves a graph at every contact event, milliseconds per step,
and is added on request (``peers=True``, ``flexforce compare --peers``).  Measured figures:
benchmarks/results/real_forces.json."""


@dataclass(frozen=True)
class PeerConfig:
    """Options of a GTSAM legged estimator beyond the recording and the model (SI units)."""

    lag_s: float = 0.5
    """Window of the fixed-lag smoothers, s (kinds ``fixed-lag``, ``combined-fixed-lag``)."""
    rotation_sigma0: float = 0.02
    """Initial standard deviation of the IMU's orientation, rad (each axis)."""
    position_sigma0: float = 0.01
    """Initial standard deviation of the IMU's world position, m."""
    velocity_sigma0: float = 0.01
    """Initial standard deviation of the IMU's world velocity, m/s."""
    integration_sigma: float = 1e-4
    """Position integration noise density, m/s/sqrt(Hz) (GTSAM's ``integrationCovariance`` =
    sigma^2 I)."""
    contact_sigma_xy: float = 0.03
    """Standard deviation of a foot's kinematic position along the IMU frame's x and y, m (GTSAM's
    default ``contactCovariance``)."""
    contact_sigma_z: float = 0.02
    """Standard deviation of a foot's kinematic position along the IMU frame's z, m (GTSAM's default)."""

    def __post_init__(self):
        for key, unit in (("lag_s", "s"), ("rotation_sigma0", "rad"), ("position_sigma0", "m"),
                          ("velocity_sigma0", "m/s"), ("integration_sigma", "m/s/sqrt(Hz)"),
                          ("contact_sigma_xy", "m"), ("contact_sigma_z", "m")):
            check_positive("PeerConfig", key, getattr(self, key), unit, "a positive, finite number")


def _params(rec: Recording, model: ModelConfig, config: PeerConfig):
    """``gtsam.LeggedEstimatorParams``: the model's IMU noise and gravity, the IMU frame as body frame,
    no full-contact initialisation."""
    import gtsam

    dt = rec.dt
    pim = gtsam.PreintegrationParams.MakeSharedU(float(model.gravity))
    pim.setGyroscopeCovariance(np.eye(3) * (model.gyro_sigma**2 * dt))
    pim.setAccelerometerCovariance(np.eye(3) * (model.accel_sigma**2 * dt))
    pim.setIntegrationCovariance(np.eye(3) * config.integration_sigma**2)
    params = gtsam.LeggedEstimatorParams()
    params.preintegrationParams = pim
    params.body_P_imu = gtsam.Pose3()
    params.useFullContactInitialization = False
    params.contactCovariance = np.diag([config.contact_sigma_xy**2, config.contact_sigma_xy**2,
                                        config.contact_sigma_z**2])
    return params


def feet_in_imu(rec: Recording) -> np.ndarray:
    """(N, C, 3) each contact's rest position in the IMU frame, m: ``imu_R^T (contact_p - imu_p)``."""
    return np.einsum("nji,ncj->nci", rec.imu_R, rec.contact_p - rec.imu_p[:, None, :])


def initial_state(rec: Recording, feet: np.ndarray | None = None):
    """``(gtsam.NavState, footholds (3, C))`` at the first sample with the flexibility at the identity:
    the IMU at its local placement and velocity, the feet at their kinematic world positions (zero for
    a contact not in force)."""
    import gtsam

    feet = feet_in_imu(rec) if feet is None else feet
    R0, p0 = rec.imu_R[0], rec.imu_p[0]
    footholds = (R0 @ feet[0].T) + p0[:, None]
    footholds[:, ~rec.contact_active[0]] = 0.0
    return gtsam.NavState(gtsam.Rot3(R0), p0, rec.imu_v[0]), footholds


def _estimator(kind: str, rec: Recording, params, config: PeerConfig, feet: np.ndarray):
    """The GTSAM estimator of ``kind`` at the first sample (:func:`initial_state`)."""
    import gtsam

    nav0, footholds = initial_state(rec, feet)
    names = [str(c) for c in rec.contact_names]
    base = np.diag(np.repeat([config.rotation_sigma0, config.position_sigma0, config.velocity_sigma0], 3) ** 2)
    if kind in ("invariant-ekf", "invariant-iekf"):
        c = len(names)
        P0 = np.zeros((9 + 3 * c, 9 + 3 * c))
        P0[:9, :9] = base
        P0[9:, 9:] = np.eye(3 * c) * params.footholdInitSigma**2
        filt: Any = gtsam.LeggedInvariantEKF if kind == "invariant-ekf" else gtsam.LeggedInvariantIEKF
        return filt(nav0, footholds, P0, params, names)
    smoother: Any = gtsam.LeggedFixedLagSmoother if kind == "fixed-lag" else gtsam.LeggedCombinedFixedLagSmoother
    return smoother(nav0, footholds, base, params, float(config.lag_s), names)


def _check(rec: Recording) -> None:
    """Raise a DataError for a recording a peer cannot run on: invalid (:meth:`Recording.validate`:
    shapes, non-finite placements), too short, or without contacts."""
    rec.validate()
    rec.require_samples()
    if not rec.contact_names:
        raise DataError("recording has no contacts; a GTSAM legged estimator needs at least one foot")


def run_gtsam_legged(rec: Recording, model: ModelConfig | None = None, kind: str = "invariant-ekf",
                     config: PeerConfig | None = None, progress: Callable[[float], None] | None = None) -> Estimate:
    """Run one of GTSAM's legged estimators on ``rec`` (module docstring: inputs, frames, fields).

    Args:
        rec: a :class:`~flexforce.datasets.recording.Recording` with contacts.
        model: the :class:`~flexforce.factors.model.ModelConfig` giving the IMU noise and gravity; None:
            the recording's nominal model (:func:`flexforce.compare.estimators.nominal_model`).
        kind: one of :data:`KINDS`.
        config: :class:`PeerConfig` (None: its defaults).
        progress: called with the fraction done.

    Returns:
        An :class:`Estimate` named ``gtsam_<kind>`` (``-`` as ``_``): ``R``, ``t``, ``w``, ``v`` per
        sample as the module docstring defines them; ``dw``, ``a``, ``wrench``, ``cop`` NaN; the wall
        time of each step (IMU prediction, contact update, reading the estimate) in ``time_per_step``.

    Raises:
        ConfigError: an unknown ``kind``, a ``config`` that is not a PeerConfig.
        DataError: an invalid recording (:meth:`~flexforce.datasets.recording.Recording.validate`), one
            too short or without contacts.
        EstimatorError: GTSAM rejected an input or failed (its message), or the estimate became
            non-finite.
    """
    check_choice("run_gtsam_legged", "kind", kind, KINDS)
    if config is None:
        config = PeerConfig()
    elif not isinstance(config, PeerConfig):
        raise ConfigError(f"config is {type(config).__name__} ({config!r}); expected a PeerConfig")
    _check(rec)
    if model is None:
        from flexforce.compare.estimators import nominal_model

        model = nominal_model(rec)
    import gtsam

    t_start = time.perf_counter()
    n, c = rec.n, len(rec.contact_names)
    feet = feet_in_imu(rec)
    try:
        est = _estimator(kind, rec, _params(rec, model, config), config, feet)
    except (RuntimeError, ValueError, IndexError) as err:
        raise EstimatorError(f"GTSAM {kind} rejected its setup: {err}") from err
    world_R_imu = np.empty((n, 3, 3))
    world_p_imu = np.empty((n, 3))
    world_v_imu = np.empty((n, 3))
    step_time = np.empty(n)
    active = rec.contact_active
    readable = np.all(np.isfinite(rec.gyro), axis=1) & np.all(np.isfinite(rec.accel), axis=1)
    seconds = np.diff(rec.t_ns).astype(float) * 1e-9
    pending = 0.0
    touch = np.empty(c, dtype=bool)
    touch[:] = True
    for k in range(n):
        t0 = time.perf_counter()
        try:
            if k > 0:
                pending += seconds[k - 1]
                if readable[k]:
                    est.predict(rec.gyro[k], rec.accel[k], pending)
                    pending = 0.0
                touch = active[k] & ~active[k - 1]
            contacts = []
            for i in np.flatnonzero(active[k]):
                m = gtsam.ContactMeasurement()
                m.foot, m.bodyPoint, m.touchdown = int(i), feet[k, i], bool(touch[i])
                contacts.append(m)
            est.processContacts(contacts)
            state = est.estimate()
        except (RuntimeError, ValueError, IndexError) as err:
            raise EstimatorError(f"GTSAM {kind} failed at sample {k} (t = {rec.time[k]:.3f} s): {err}") from err
        world_R_imu[k] = state.rotation().matrix()
        world_p_imu[k] = state.x(0)
        world_v_imu[k] = state.x(1)
        step_time[k] = time.perf_counter() - t0
        if progress is not None and (k % 100 == 0 or k == n - 1):
            progress((k + 1) / n)
    if not (np.all(np.isfinite(world_R_imu)) and np.all(np.isfinite(world_p_imu))):
        k = int(np.flatnonzero(~np.all(np.isfinite(world_p_imu), axis=1) | ~np.all(np.isfinite(world_R_imu),
                                                                                 axis=(1, 2)))[0])
        raise EstimatorError(f"GTSAM {kind}'s estimate became non-finite at sample {k} (t = {rec.time[k]:.3f} s); "
                             "expected finite IMU readings and contact positions")
    R = np.einsum("nij,nkj->nik", world_R_imu, rec.imu_R)
    t = world_p_imu - np.einsum("nij,nj->ni", R, rec.imu_p)
    gyro = np.where(readable[:, None], rec.gyro, np.nan)
    w = np.einsum("nij,nj->ni", world_R_imu, gyro) - np.einsum("nij,nj->ni", R, rec.imu_w)
    v = (world_v_imu - np.cross(w, np.einsum("nij,nj->ni", R, rec.imu_p))
         - np.einsum("nij,nj->ni", R, rec.imu_v))
    nan3 = np.full((n, 3), np.nan)
    name = "gtsam_" + kind.replace("-", "_")
    return Estimate(estimator=name, t_ns=rec.t_ns.copy(), contact_names=tuple(rec.contact_names), R=R, t=t, w=w, v=v,
                    dw=nan3, a=nan3.copy(), wrench=np.full((n, c, 6), np.nan), cop=nan3.copy(),
                    time_per_step=step_time, total_time=time.perf_counter() - t_start,
                    meta={"kind": "peer", "gtsam": kind, "frames": "body = IMU frame; R, t: the flexibility "
                          "implied by the IMU's world pose and its local placement",
                          "config": {k: getattr(config, k) for k in config.__dataclass_fields__}})


def run_peer(name: str, rec: Recording, model: ModelConfig | None = None, **options) -> Estimate:
    """The peer of row ``name`` (a key of :data:`PEERS`, ``_`` accepted for ``-``) on ``rec``:
    :func:`run_gtsam_legged` with its kind; ``options``: fields of :class:`PeerConfig`.

    Raises:
        ConfigError: an unknown peer or option; as :func:`run_gtsam_legged` otherwise.
    """
    key = str(name).replace("_", "-")
    if key not in PEERS:
        raise ConfigError(f"unknown peer '{name}'; expected one of {', '.join(PEERS)}")
    try:
        config = PeerConfig(**options)
    except TypeError as err:
        raise ConfigError(f"unknown PeerConfig option(s) in {sorted(options)}; known: "
                          f"{', '.join(PeerConfig.__dataclass_fields__)}") from err
    return run_gtsam_legged(rec, model, kind=PEERS[key], config=config)
