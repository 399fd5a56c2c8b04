r"""The smoothing problem: per-step data, noise of every factor family, and the enabled effects.

Everything both smoothers (batch and fixed-lag) need from a Recording and a ModelConfig, computed
once: the inputs as contiguous arrays, the contact parameters, the noise sigmas with their
derivation (:class:`NoiseRule`, one rule for every scenario and robot), and the enabled effects.

Noise derivation (docs/smoother.md gives the full argument)
-----------------------------------------------------------
- IMU: the sensor model's per-sample sigmas (``ModelConfig.gyro_sigma``, ``accel_sigma``).
- F/T: the sensor model's per-sample sigmas (``ModelConfig.ft_force_sigma``, ``ft_torque_sigma``).
- Newton-Euler: the wrench the model leaves unexplained (pushes, cables, mass-model error) is
  white with a per-sample sigma of ``unmodelled_fraction`` of the robot's weight for the force,
  times the CoM height for the moment (a horizontal force at the CoM, about the ground origin).
- Contact law: the spring-damper is trusted to ``contact_fraction`` of the weight for the force,
  times the contact lever (the largest horizontal distance of a contact from the local origin,
  at least 5 cm) for the moment.  An inactive contact's wrench is held at zero ``1e3`` times
  tighter.
- Integration: the acceleration is linear in time over a step plus a Brownian bridge (white jerk
  of density ``q``, pinned at both samples).  Over a step ``T`` the bridge leaves in velocity and
  position the errors ``e_v = int B``, ``e_p = int (T - s) B``, with covariance
  ``q^2 [[T^5/45, T^4/24], [T^4/24, T^3/12]]`` per axis (position, velocity).  The jerk density is
  what the unmodelled wrench can do within the bandwidth of the contact springs:
  ``q_lin = (sigma_NE,F / m) sqrt(omega_c)`` and ``q_ang = (sigma_NE,T / lambda_max(I_l))
  sqrt(omega_c)`` with ``omega_c = sqrt(sum k_fs / m)`` the vertical spring mode (rad/s).

Effects
-------
An effect (the :class:`~flexforce.factors.effects.Effect` protocol, written against
:class:`~flexforce.factors.effects.ProblemView`, which :class:`Problem` satisfies) appends ``dim``
unknowns to every step, constrains them with a prior on the first step and a random walk between
steps, and adds a term to the residual of one or more families (e.g. an external wrench subtracts
from the Newton-Euler residual, a gyro bias adds to the gyro residual, a stiffness scale adds to
each active contact's law).  The protocol and the catalogue are :mod:`flexforce.factors.effects`;
``Effect`` is re-exported here (and from :mod:`flexforce.smoother`) under its old import path.
The smoothers handle effects generically: the core never names one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from flexforce.datasets.faults import ROBUST_LOSSES, imu_validity
from flexforce.errors import ConfigError, DataError, ModelError
from flexforce.factors import core
from flexforce.factors.effects import Effect, EffectTraits, ProblemView, traits
from flexforce.factors.footholds import WALK_WITHIN_ANCHORED, Footholds, held_rest, rest_placements
from flexforce.factors.model import check_unmodelled, unmodelled_acceleration
from flexforce.factors.physics import about_com, contact_arrays
from flexforce.options import check_positive, invalid, require_config, with_options

if TYPE_CHECKING:
    from flexforce.datasets.recording import Recording

__all__ = ["FAMILIES", "ConstantRows", "Effect", "NoiseRule", "Problem", "ProblemView", "Sigmas", "derive_sigmas",
           "imu_residual_scale", "scaled_imu_noise", "static_equilibrium", "whitener", "with_footholds"]

FAMILIES = ("integration", "newton_euler", "contact", "imu", "ft")
"""Names of the factor families, the keys of :attr:`Estimate.residuals`."""


# ----------------------------------------------------------------------------------------------
# Noise
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NoiseRule:
    """The one rule that sets the sigmas of the model-error families (no per-scenario tuning).

    The model error is the EKF's (``flexforce.compare.ekf.filter.noise_model``): an unmodelled
    acceleration, white per sample, of ``unmodelled_accel`` (linear, m/s^2) and
    ``unmodelled_ang_accel`` (angular, rad/s^2).  Defaults (``None``) are the EKF's:
    ``accel_sigma`` and ``accel_sigma / l``, ``l`` the IMU's distance to the contacts' centroid at
    the first step.  The smoother turns that acceleration into the wrench it leaves unexplained
    (Newton-Euler), so both estimators assume the same unmodelled-wrench level at the first step;
    the smoother takes that wrench about each step's CoM
    (:func:`flexforce.factors.physics.about_com`), the EKF its acceleration about the local origin.
    """

    unmodelled_accel: float | None = None
    """Per-sample sigma of the unmodelled linear acceleration, m/s^2 (None: the EKF's, accel_sigma)."""
    unmodelled_ang_accel: float | None = None
    """Per-sample sigma of the unmodelled angular acceleration, rad/s^2 (None: the EKF's, accel_sigma / l)."""
    contact_ratio: float = 0.1
    """Contact-law error sigma relative to the unmodelled wrench (the EKF takes the contact law as
    exact; 0.1 is 1 % of the variance: the law all but exact, yet soft enough that W_i stays a
    variable with readable residuals)."""
    robust_k: float | None = 3.548
    """Huber threshold on the norm of the whitened 6-D Newton-Euler residual (None: plain
    Gaussian).  3.548 = sqrt(chi^2_6(0.95)): under the nominal model 95 % of the residual vectors
    keep their full Gaussian weight (Huber's scalar 1.345 would apply to a 1-D residual; the norm
    of a 6-D one exceeds it 9 times out of 10).  A push is an outlier of this family, which the
    Huber loss lets through linearly instead of quadratically, so that it does not drag the state."""
    imu_robust: str | None = "log-tail"
    """Robust loss on the whitened residual of each IMU sensor (the gyrometer's 3-D norm and the
    accelerometer's, separately), and of each F/T sensor's force and torque when fused:
    ``"log-tail"`` (Gaussian up to ``imu_robust_k``, logarithmic beyond: influence at most
    ``imu_robust_k`` and falling to zero for gross outliers), ``"huber"`` (bounded influence,
    convex), ``"cauchy"`` (redescending everywhere) or None (plain Gaussian).  docs/smoother.md,
    "Sensor faults", gives the choice."""
    imu_robust_k: float = 30.0
    """Threshold of the IMU and F/T robust loss (whitened norm of one 3-D sensor).  30: for gross
    faults, above the model errors of a real robot.  On the iCub walk the fixed-lag fit's
    accelerometer residuals reach 30-100 sigma: a threshold at the nominal tail (5.537 =
    sqrt(chi^2_3 upper 1e-6)) down-weighted 1196 samples and raised the tilt error from 0.81 to
    1.10 deg (per-foot F_z 37.0 -> 53.3 N); at 30, 151 samples, 0.83 deg, 34.8 N.  At 100 none is
    touched, but a 16 g plateau without a configured range (whitened ~2700, influence k^2/|r| per
    sample) then drags the fixed-lag smoother (8.5 kN, 1.3 m); at 30 it moves the forces by 0.003 N
    (docs/smoother.md, "Sensor faults")."""
    jerk_scale: float = 1.0
    """Multiplier of the jerk density of the integration noise (1: the derivation below)."""
    inactive_factor: float = 1e-3
    """Sigma of an inactive contact's wrench relative to the active contact-law sigma."""
    prior_sigma: tuple[float, ...] = (0.05, 0.05, 0.05, 0.02, 0.02, 0.02, 0.2, 0.2, 0.2, 0.1, 0.1, 0.1,
                                      2.0, 2.0, 2.0, 1.0, 1.0, 1.0)
    """Sigma of the first-step prior on (theta rad, t m, w rad/s, v m/s, dw rad/s^2, a m/s^2):
    loose, since the model makes the state observable (seed sec. III-A)."""

    def __post_init__(self):
        o = "NoiseRule"
        check_unmodelled(o, self.unmodelled_accel, self.unmodelled_ang_accel,
                         ("the EKF's, accel_sigma", "the EKF's, accel_sigma / l"))
        check_positive(o, "contact_ratio", self.contact_ratio, "", "a positive ratio of standard deviations")
        check_positive(o, "robust_k", self.robust_k, "", "a positive Huber threshold (whitened norm) or None",
                       optional=True)
        if self.imu_robust is not None and self.imu_robust not in ROBUST_LOSSES:
            raise invalid(o, "imu_robust", self.imu_robust, "",
                          " or ".join(repr(c) for c in ROBUST_LOSSES) + " or None (plain Gaussian)")
        check_positive(o, "imu_robust_k", self.imu_robust_k, "",
                       "a positive threshold of the IMU/F-T robust loss (whitened norm of a 3-D sensor)")
        check_positive(o, "jerk_scale", self.jerk_scale, "", "a positive multiplier")
        check_positive(o, "inactive_factor", self.inactive_factor, "", "a positive ratio of standard deviations")
        sigma = self.prior_sigma
        expected = ("18 positive standard deviations (theta rad, t m, w rad/s, v m/s, dw rad/s^2, a m/s^2)")
        try:
            values = tuple(float(v) for v in sigma)  # a TOML array arrives as a list
        except (TypeError, ValueError) as err:
            raise invalid(o, "prior_sigma", sigma, "", expected) from err
        if len(values) != 18 or not all(math.isfinite(v) and v > 0 for v in values):
            raise invalid(o, "prior_sigma", sigma, "", expected)
        object.__setattr__(self, "prior_sigma", values)


@dataclass(frozen=True)
class Sigmas:
    """Sigmas of every family, in the units of its residual."""

    imu: np.ndarray
    """(6,) gyro rad/s, accelerometer m/s^2."""
    newton_euler: np.ndarray
    """(6,) N, N m: standard deviations (square roots of the diagonal of ``newton_euler_cov``)."""
    contact: np.ndarray
    """(6,) N, N m (active contact): standard deviations of ``contact_cov``."""
    integration_cov: np.ndarray
    """(12, 12) covariance of (theta rad, t m, w rad/s, v m/s)."""
    ft: np.ndarray
    """(6,) N, N m."""
    prior: np.ndarray
    """(18,) first-step prior."""
    inactive_factor: float
    newton_euler_cov: np.ndarray | None = None
    """(6, 6) covariance of the unexplained wrench (F, T about the step's CoM point,
    :func:`flexforce.factors.physics.about_com`), the Newton-Euler residual."""
    newton_euler_cov_origin: np.ndarray | None = None
    """(6, 6) the same wrench's covariance about the local origin at the first sample (the scale of
    the ``external-wrench`` effect's unknowns, a wrench about the origin)."""
    contact_cov: np.ndarray | None = None
    """(6, 6) covariance of one active contact's law error."""
    robust_k: float | None = None
    """Huber threshold of the Newton-Euler family (whitened norm), or None."""
    imu_robust: str | None = None
    """Robust loss of each IMU (and F/T) sensor's whitened 3-D residual (``NoiseRule.imu_robust``)."""
    imu_robust_k: float = 30.0
    """Its threshold (whitened norm)."""
    derivation: dict = field(default_factory=dict)
    """The quantities the rule used (JSON-serialisable)."""

    def __post_init__(self):
        if self.newton_euler_cov is None:
            object.__setattr__(self, "newton_euler_cov", np.diag(np.asarray(self.newton_euler, float) ** 2))
        if self.contact_cov is None:
            object.__setattr__(self, "contact_cov", np.diag(np.asarray(self.contact, float) ** 2))


def whitener(cov: np.ndarray) -> np.ndarray:
    """``L^-1`` with ``cov = L L^T`` (lower Cholesky): whitened ``L^-1 r`` has unit covariance.

    For a wrench ordered ``(F, T)`` the first three whitened components are ``F_i / sigma_F`` when
    the force block is diagonal; the last three are the moment left once the force is explained.
    """
    return np.linalg.inv(np.linalg.cholesky(cov))


def derive_sigmas(rec, model, rule: NoiseRule = NoiseRule()) -> Sigmas:
    """Apply :class:`NoiseRule` to a recording's robot (module docstring, docs/smoother.md)."""
    m = float(rec.mass)
    g = float(model.gravity)
    weight = m * g
    active0 = rec.contact_active[0]
    p0 = rec.contact_p[0][active0] if active0.any() else rec.contact_p[0]
    centroid = p0.mean(axis=0)
    lever = float(np.linalg.norm(rec.imu_p[0] - centroid))  # the EKF's l (docs/ekf.md)
    sa0, sdw0 = unmodelled_acceleration(model.accel_sigma, rec.imu_p[0], centroid)
    sa = float(rule.unmodelled_accel) if rule.unmodelled_accel is not None else sa0
    sdw = float(rule.unmodelled_ang_accel) if rule.unmodelled_ang_accel is not None else sdw0
    # Unexplained wrench = d(required wrench)/d(dw, a) times the unmodelled acceleration, at the
    # static equilibrium of the first sample (eq. 16, 23 are affine in (dw, a)).
    R0, q0 = _static_state(rec, model)
    r = np.empty(6)
    J = np.empty((6, core.STATE_DIM))
    core.newton_euler(R0, q0, np.zeros(6), m, np.ascontiguousarray(rec.com[0], float),
                         np.ascontiguousarray(rec.com_vel[0], float), np.ascontiguousarray(rec.com_acc[0], float),
                         np.ascontiguousarray(rec.inertia[0], float), np.ascontiguousarray(rec.inertia_dot[0], float),
                         np.ascontiguousarray(rec.sigma[0], float), np.ascontiguousarray(rec.sigma_dot[0], float),
                         g, r, J)
    JA = J[:, 12:18]
    Qacc = np.diag([sdw**2] * 3 + [sa**2] * 3)
    cov_origin = JA @ Qacc @ JA.T
    cov_origin = 0.5 * (cov_origin + cov_origin.T)
    cov_c = rule.contact_ratio**2 * cov_origin
    # The Newton-Euler residual is the unexplained wrench about the CoM's point of each step
    # (flexforce.factors.physics.about_com), not about the local origin the robot walks away
    # from: its covariance is the same wrench's, moved to the first sample's CoM.
    shift = about_com(np.asarray(rec.com[0], dtype=float), np.zeros(6), np.eye(6))[1]
    cov_ne = shift @ cov_origin @ shift.T
    cov_ne = 0.5 * (cov_ne + cov_ne.T)
    k_total = sum(float(np.trace(p.K_fs)) / 3.0 for p in model.contact_params)
    omega_c = math.sqrt(max(k_total, 1e-9) / m)
    # White jerk within the contact springs' bandwidth, from the same unmodelled acceleration.
    q_lin = rule.jerk_scale * sa * math.sqrt(omega_c)
    q_ang = rule.jerk_scale * sdw * math.sqrt(omega_c)
    T = rec.dt
    bridge = np.array([[T**5 / 45.0, T**4 / 24.0], [T**4 / 24.0, T**3 / 12.0]])
    cov = np.zeros((12, 12))
    for (ip, iv), q in (((0, 6), q_ang), ((3, 9), q_lin)):
        for j in range(3):
            idx = [ip + j, iv + j]
            cov[np.ix_(idx, idx)] = q * q * bridge
    return Sigmas(
        imu=np.array([model.gyro_sigma] * 3 + [model.accel_sigma] * 3),
        newton_euler=np.sqrt(np.diag(cov_ne)),
        contact=np.sqrt(np.diag(cov_c)),
        integration_cov=cov,
        ft=np.array([model.ft_force_sigma] * 3 + [model.ft_torque_sigma] * 3),
        prior=np.asarray(rule.prior_sigma, dtype=float),
        inactive_factor=rule.inactive_factor,
        newton_euler_cov=cov_ne,
        newton_euler_cov_origin=cov_origin,
        contact_cov=cov_c,
        robust_k=rule.robust_k,
        imu_robust=rule.imu_robust,
        imu_robust_k=rule.imu_robust_k,
        derivation={"imu_robust": rule.imu_robust, "imu_robust_k": rule.imu_robust_k,
                    "weight_N": weight, "imu_contact_lever_m": lever,
                    "unmodelled_accel_m_s2": sa, "unmodelled_ang_accel_rad_s2": sdw,
                    "newton_euler_cov": cov_ne.tolist(), "newton_euler_about": "the CoM of each step",
                    "contact_ratio": rule.contact_ratio,
                    "robust_k": rule.robust_k, "omega_c_rad_s": omega_c,
                    "jerk_density_lin": q_lin, "jerk_density_ang": q_ang},
    )


def static_equilibrium(mass: float, g: float, inputs: tuple, active, local_p, local_R, rest_p, rest_R,
                       K: list, beta, iso, iterations: int = 30, where: str = "the first sample"):
    """Static flexibility ``(R, q)`` of one sample: zero velocity and acceleration, the contact
    springs carrying the weight and the inputs' momentum rates (Newton's method on eq. 16, 23 with
    eq. 10, 12).

    Args:
        mass, g: kg, m/s^2.
        inputs: ``(com, com_vel, com_acc, inertia, inertia_dot, sigma, sigma_dot)`` of the sample
            (local frame, see :class:`flexforce.factors.physics.Inputs`).
        active: (C,) bool; local_p, local_R (C, 3), (C, 3, 3) the contacts' placements in the local
            frame; rest_p, rest_R their rest placements in the world.
        K, beta, iso: contact parameters as :func:`~flexforce.factors.physics.contact_arrays` returns them.

    Raises:
        ModelError: when the residual wrench does not fall below 1e-9 (N, N m) within
            ``iterations`` Newton steps (e.g. stiffness too low to carry the robot).
    """
    c = lambda a: np.ascontiguousarray(a, float)  # noqa: E731
    inp = [c(a) for a in inputs]
    R = np.eye(3)
    q = np.zeros(15)
    rne, Jne = np.empty(6), np.empty((6, core.STATE_DIM))
    rc, Jc = np.empty(6), np.empty((6, core.STATE_DIM))
    no_rest_jac = np.empty((0, 6))
    zero = np.zeros(6)
    for _ in range(iterations):
        Wsum = np.zeros(6)
        J = np.zeros((6, 6))
        for i in range(len(active)):
            if active[i]:
                core.contact_law(R, q, zero, c(local_p[i]), c(local_R[i]), c(rest_p[i]), c(rest_R[i]), K[0][i],
                                 K[1][i], K[2][i], K[3][i], beta[i, 0], beta[i, 1], iso[i], rc, Jc, no_rest_jac)
                Wsum += rc
                J -= Jc[:, :6]
        core.newton_euler(R, q, Wsum, float(mass), *inp, float(g), rne, Jne)
        J += Jne[:, :6]
        if np.max(np.abs(rne)) < 1e-9:
            return R, q
        step = np.linalg.solve(J, -rne)
        R = core.so3_exp(step[:3]) @ R
        q[:3] += step[3:]
    raise ModelError(f"no static equilibrium at {where}: after {iterations} Newton steps the contact springs "
                     f"leave {np.max(np.abs(rne)):.3g} N (or N m) of the weight and momentum rates unexplained, "
                     "expected below 1e-9; check the stiffness (can it carry the robot?) and the mass")


def _static_state(rec, model):
    """Static equilibrium of the first sample, before a Problem exists (rest = local placement)."""
    K, beta, iso = contact_arrays(tuple(model.contact_params))
    return static_equilibrium(rec.mass, model.gravity, _inputs(rec, 0), rec.contact_active[0], rec.contact_p[0],
                              rec.contact_R[0], rec.contact_p[0], rec.contact_R[0], K, beta, iso)


def _inputs(rec, k: int) -> tuple:
    return (rec.com[k], rec.com_vel[k], rec.com_acc[k], rec.inertia[k], rec.inertia_dot[k], rec.sigma[k],
            rec.sigma_dot[k])


# ----------------------------------------------------------------------------------------------
# The problem
# ----------------------------------------------------------------------------------------------


def with_footholds(rec, model, rest_p=None, rest_R=None):
    """``(model, rest_p, rest_R)`` with the footholds of the contact episodes as unknowns
    (:class:`~flexforce.factors.footholds.Footholds`, its priors from ``model.foothold_prior``, the
    first stance anchored and the within-episode walk ``WALK_WITHIN_ANCHORED``; the model unchanged
    when they already are); the rest placements as given (None: :meth:`Problem.build` holds the
    nominal ones over each episode, as for any model with footholds).

    The first stance soles define the local frame (flat on the floor at the first sample): anchored
    in all six components, they cannot absorb the model's errors, which on real logs otherwise set
    the standing feet at different heights and move load between them (docs/smoother.md)."""
    if not any(isinstance(e, Footholds) for e in model.effects):
        eff = Footholds(len(rec.contact_names), model.foothold_prior, anchor_first_stance=True,
                        walk_within=WALK_WITHIN_ANCHORED)
        model = replace(model, effects=tuple(model.effects) + (eff,))
    return model, rest_p, rest_R


def imu_residual_scale(residuals, time, skip: float, threshold: float) -> tuple[dict, dict]:
    """How far a fit's whitened IMU residuals are from their noise: ``(rms, scale)``, each
    ``{"gyro": ..., "accel": ...}``.

    ``rms``: the root mean square of the (N, 6) whitened residuals (gyrometer axes, then
    accelerometer axes) about each axis's own mean, over the samples at or after ``skip`` s
    (``time``, (N,) s) that are finite; about 1 when the configured noise describes the data.  The
    mean is taken out so that a constant the model misses (a sensor bias, a mounting), which is an
    effect to find and not noise, does not count.  ``scale``: the sensor's ``rms`` where it
    exceeds ``threshold`` sigmas, else 1 -- what its sigma is multiplied by for the residuals to
    be at their noise level."""
    res = np.asarray(residuals, dtype=float)
    keep = (np.asarray(time, dtype=float) >= skip)[:, None] & np.isfinite(res)
    rms, scale = {}, {}
    for name, cols in (("gyro", slice(0, 3)), ("accel", slice(3, 6))):
        r, k = res[:, cols], keep[:, cols]
        count = k.sum(axis=0)
        if not count.all():
            rms[name], scale[name] = 0.0, 1.0
            continue
        mean = np.where(k, r, 0.0).sum(axis=0) / count
        rms[name] = float(np.sqrt(np.sum(np.where(k, r - mean, 0.0) ** 2) / count.sum()))
        scale[name] = rms[name] if rms[name] > threshold else 1.0
    return rms, scale


def scaled_imu_noise(model, scale: dict):
    """``model`` (a ModelConfig) with its gyrometer and accelerometer sigmas multiplied by
    ``scale["gyro"]`` and ``scale["accel"]`` (:func:`imu_residual_scale`'s)."""
    from dataclasses import replace

    return replace(model, gyro_sigma=model.gyro_sigma * scale["gyro"], accel_sigma=model.accel_sigma * scale["accel"])


def configured(config, config_type: type, options: dict, what: str):
    """``config`` (a ``config_type``) with ``options`` (some of its fields, the older keyword
    calling convention; ``rule=None`` is the default rule) replacing its fields.

    Raises:
        ConfigError: ``config`` is not a ``config_type``, an unknown option (the known ones
            listed), or a bad value; ``what`` names the estimator in the message.
    """
    require_config(config, config_type, what)
    if "rule" in options and options["rule"] is None:  # the older convention: None for the default
        options = {**options, "rule": NoiseRule()}
    return with_options(config, options, what)


def build_problem(rec, model, config, rest_p=None, rest_R=None) -> Problem:
    """:meth:`Problem.build` with a smoother config's ``rule``, and the footholds as unknowns when
    its ``footholds`` is set (:func:`with_footholds`)."""
    if config.footholds:
        model, rest_p, rest_R = with_footholds(rec, model, rest_p, rest_R)
    return Problem.build(rec, model, config.rule, rest_p, rest_R)


class ConstantRows:
    """Cache of the rows of the effects' prior levels and random walks whose Jacobians do not
    depend on the linearisation point (:func:`flexforce.smoother.linearize.linearize`).

    Scope: one :class:`Problem` (its :attr:`Problem.constant_rows`, created with it), so one set
    of effects, noise and column layout.  Key: ``(index of the effect in Problem.effects, kind)``;
    each key holds the rows of the latest ``where`` (first step, steps, columns) only: a
    fixed-lag window moves on.  The cached arrays are shared between linearisations and never
    written.
    """

    def __init__(self) -> None:
        self._rows: dict[tuple, tuple[tuple, tuple]] = {}

    def get(self, key: tuple, where: tuple, make) -> tuple:
        """``make()``'s rows for ``key`` at ``where``: formed on the first call or when ``where``
        changed, else the kept ones."""
        hit = self._rows.get(key)
        if hit is None or hit[0] != where:
            hit = self._rows[key] = (where, make())
        return hit[1]


@dataclass
class Problem:
    """A Recording and a ModelConfig turned into what the factors read (contiguous arrays).

    Satisfies :class:`~flexforce.factors.effects.ProblemView`, the view the effects are written against.
    """

    rec: Recording
    model: object
    sigmas: Sigmas
    effects: tuple
    n: int
    nc: int
    dt: float
    g: float
    use_ft: bool
    offset: int = 0
    """Step index of row 0 in the whole stream (0 for a whole recording; a streaming smoother
    builds problems over consecutive parts of its input, :mod:`flexforce.smoother.stream`)."""
    # Set by :meth:`build` (not constructor arguments; excluded from repr and comparison).
    com: np.ndarray = field(init=False, repr=False, compare=False)
    com_vel: np.ndarray = field(init=False, repr=False, compare=False)
    com_acc: np.ndarray = field(init=False, repr=False, compare=False)
    inertia: np.ndarray = field(init=False, repr=False, compare=False)
    inertia_dot: np.ndarray = field(init=False, repr=False, compare=False)
    sigma_l: np.ndarray = field(init=False, repr=False, compare=False)
    sigma_dot: np.ndarray = field(init=False, repr=False, compare=False)
    imu_R: np.ndarray = field(init=False, repr=False, compare=False)
    imu_p: np.ndarray = field(init=False, repr=False, compare=False)
    imu_v: np.ndarray = field(init=False, repr=False, compare=False)
    imu_a: np.ndarray = field(init=False, repr=False, compare=False)
    imu_w: np.ndarray = field(init=False, repr=False, compare=False)
    y_imu: np.ndarray = field(init=False, repr=False, compare=False)
    active: np.ndarray = field(init=False, repr=False, compare=False)
    contact_p: np.ndarray = field(init=False, repr=False, compare=False)
    contact_R: np.ndarray = field(init=False, repr=False, compare=False)
    rest_p: np.ndarray = field(init=False, repr=False, compare=False)
    rest_R: np.ndarray = field(init=False, repr=False, compare=False)
    y_ft: np.ndarray | None = field(init=False, repr=False, compare=False)
    imu_use: np.ndarray = field(init=False, repr=False, compare=False)
    """(N, 6) 1.0 where the IMU axis carries information, 0.0 where its reading is missing or saturated."""
    imu_missing: np.ndarray = field(init=False, repr=False, compare=False)
    imu_saturated: np.ndarray = field(init=False, repr=False, compare=False)
    ft_use: np.ndarray | None = field(init=False, repr=False, compare=False)
    weight_cap: dict | None = field(default=None, init=False, repr=False, compare=False)
    """family -> (N, sensors) upper bounds of the sensors' robust weights (None: none); the
    fixed-lag smoother lowers them as samples are linearised (a rejected sample stays rejected)."""
    """(N, C, 6) 1.0 where the fused F/T component is finite."""
    K_fs: np.ndarray = field(init=False, repr=False, compare=False)
    K_fd: np.ndarray = field(init=False, repr=False, compare=False)
    K_ts: np.ndarray = field(init=False, repr=False, compare=False)
    K_td: np.ndarray = field(init=False, repr=False, compare=False)
    beta: np.ndarray = field(init=False, repr=False, compare=False)
    iso: np.ndarray = field(init=False, repr=False, compare=False)
    effect_dims: tuple[int, ...] = field(init=False, repr=False, compare=False)
    effect_traits: tuple[EffectTraits, ...] = field(init=False, repr=False, compare=False)
    """The optional parts each effect declares (:func:`~flexforce.factors.effects.traits`), read once."""
    prior_mean: tuple[np.ndarray, np.ndarray] = field(init=False, repr=False, compare=False)
    integration_whitener: np.ndarray = field(init=False, repr=False, compare=False)
    ne_whitener: np.ndarray = field(init=False, repr=False, compare=False)
    contact_whitener: np.ndarray = field(init=False, repr=False, compare=False)
    constant_rows: ConstantRows = field(default_factory=ConstantRows, init=False, repr=False, compare=False)
    """The cache of the effects' constant rows (:class:`ConstantRows`), this problem's own."""

    @classmethod
    def build(cls, rec, model, rule: NoiseRule = NoiseRule(), rest_p=None, rest_R=None, *,
              part_of: Problem | None = None, offset: int = 0) -> Problem:
        """Args:
            rest_p, rest_R: (N, C, 3) and (N, C, 3, 3) the contacts' rest placements in the world
                (footholds) per step; default: the recording's local placements ``contact_p``,
                ``contact_R`` (the spring is at rest where the local frame puts the contact),
                held over each contact episode when the model estimates the footholds.
            part_of, offset: ``rec`` is the part of a stream from step ``offset`` on, and
                ``part_of`` the problem of the stream's first part: its noise (derived from the
                stream's first sample), period and first-step prior are kept, so that every part
                is the same problem.
        """
        rec.validate()
        nc = len(rec.contact_names)
        if len(model.contact_params) != nc:
            raise ConfigError(f"model has {len(model.contact_params)} contact parameter sets; the recording "
                              f"has {nc} contacts ({', '.join(rec.contact_names)})")
        if part_of is None and not rec.contact_active[0].any():
            raise DataError("no contact is active at the first sample; the flexible-contact model needs one")
        use_ft = bool(model.use_ft)
        if use_ft and rec.ft is None:
            raise DataError("use_ft is set but the recording carries no F/T readings (field 'ft')")
        for eff in model.effects:
            if not isinstance(eff, Effect):
                raise ConfigError(f"effect {eff!r} does not implement the smoother's Effect protocol "
                                  "(name, dim, labels, prior, random_walk_sigma, residual_terms, report)")
        sigmas = part_of.sigmas if part_of is not None else derive_sigmas(rec, model, rule)
        dt = part_of.dt if part_of is not None else rec.dt
        prob = cls(rec=rec, model=model, sigmas=sigmas, effects=tuple(model.effects), n=rec.n, nc=nc, dt=dt,
                   g=float(model.gravity), use_ft=use_ft, offset=int(offset))
        c = np.ascontiguousarray
        prob.com, prob.com_vel, prob.com_acc = c(rec.com, float), c(rec.com_vel, float), c(rec.com_acc, float)
        prob.inertia, prob.inertia_dot = c(rec.inertia, float), c(rec.inertia_dot, float)
        prob.sigma_l, prob.sigma_dot = c(rec.sigma, float), c(rec.sigma_dot, float)
        prob.imu_R, prob.imu_p, prob.imu_v = c(rec.imu_R, float), c(rec.imu_p, float), c(rec.imu_v, float)
        prob.imu_a, prob.imu_w = c(rec.imu_a, float), c(rec.imu_w, float)
        use, prob.imu_missing, prob.imu_saturated = imu_validity(
            rec.gyro, rec.accel, float(getattr(model, "gyro_range", math.inf)),
            float(getattr(model, "accel_range", math.inf)))
        prob.imu_use = c(use, float)
        # A missing or saturated axis has zero weight; its reading is replaced by a finite placeholder.
        prob.y_imu = c(np.where(use, np.concatenate([rec.gyro, rec.accel], axis=1), 0.0), float)
        prob.active = c(rec.contact_active, bool)
        prob.contact_p, prob.contact_R = c(rec.contact_p, float), c(rec.contact_R, float)
        if rest_p is None and rest_R is None and any(isinstance(e, Footholds) for e in model.effects):
            # estimated footholds correct each episode's nominal placement, held from its first step
            rest_p, rest_R = held_rest(rec.contact_active, rec.contact_p, rec.contact_R)
        prob.rest_p, prob.rest_R = rest_placements(rec, rest_p, rest_R)
        prob.y_ft = c(rec.ft, float) if use_ft else None  # NaN: not measured (zero rows, factors.core.ft)
        prob.ft_use = c(np.isfinite(rec.ft), float) if use_ft else None
        (prob.K_fs, prob.K_fd, prob.K_ts, prob.K_td), prob.beta, prob.iso = contact_arrays(model.contact_params)
        prob.effect_dims = tuple(int(e.dim) for e in prob.effects)
        prob.effect_traits = tuple(traits(e) for e in prob.effects)
        prob.prior_mean = part_of.prior_mean if part_of is not None else prob.equilibrium(0)
        if part_of is not None:  # the same noise: its whiteners
            prob.integration_whitener = part_of.integration_whitener
            prob.ne_whitener, prob.contact_whitener = part_of.ne_whitener, part_of.contact_whitener
            return prob
        prob.integration_whitener = whitener(prob.sigmas.integration_cov)
        # derive_sigmas sets both covariances.
        assert prob.sigmas.newton_euler_cov is not None and prob.sigmas.contact_cov is not None
        prob.ne_whitener = whitener(prob.sigmas.newton_euler_cov)
        prob.contact_whitener = whitener(prob.sigmas.contact_cov)
        return prob

    # ------------------------------------------------------------------------------------------
    @property
    def effect_dim(self) -> int:
        return int(sum(self.effect_dims))

    @property
    def state_dim(self) -> int:
        """Unknowns per step: 18 + 6 C + effects."""
        return core.STATE_DIM + 6 * self.nc + self.effect_dim

    def contact_wrenches(self, k: int, R, q) -> np.ndarray:
        """(C, 6) contact-law wrenches at step ``k`` (zero for inactive contacts)."""
        out = np.zeros((self.nc, 6))
        r = np.empty(6)
        J = np.empty((6, 18))
        zero = np.zeros(6)
        no_rest_jac = np.empty((0, 6))
        for i in range(self.nc):
            if self.active[k, i]:
                core.contact_law(R, q, zero, self.contact_p[k, i], self.contact_R[k, i], self.rest_p[k, i],
                                 self.rest_R[k, i], self.K_fs[i], self.K_fd[i], self.K_ts[i], self.K_td[i],
                                 self.beta[i, 0], self.beta[i, 1], self.iso[i], r, J, no_rest_jac)
                out[i] = r
        return out

    def contact_law_terms(self, steps: np.ndarray, R: np.ndarray, q: np.ndarray, K_fs, K_fd, K_ts, K_td,
                          beta=None):
        """The contact law of every contact with other parameters, for effects on the contact family.

        Args:
            steps: (n,) step indices; R (n, 3, 3), q (n, 15) the core state at those steps.
            K_fs, K_fd, K_ts, K_td: (C, 3, 3) matrices in the contact frame (rotated into the world
                by the current contact orientation, correction 5), zeros allowed.
            beta: (C, 2) cubic coefficients ``(beta_f, beta_t)`` (default: the model's).

        Returns:
            ``f`` (n, C, 6), the wrench ``(F, T about the world origin)`` of eq. 6-12, and
            ``df/ds`` (n, C, 6, 18); zero for inactive contacts.  ``f`` is linear in the matrices
            jointly (and in ``beta`` for fixed matrices), so an effect that scales a parameter by
            ``(1 + kappa)`` adds ``kappa f`` to the contact residual.
        """
        steps = np.asarray(steps)
        n, nc = len(steps), self.nc
        c = lambda a: np.ascontiguousarray(a, dtype=float)  # noqa: E731
        beta = self.beta if beta is None else beta
        r = np.empty((n, nc, 6))
        J = np.empty((n, nc, 6, core.STATE_DIM))
        core.contact_all(c(R), c(q), np.zeros((n, nc, 6)), np.ascontiguousarray(self.active[steps]),
                         c(self.contact_p[steps]), c(self.contact_R[steps]), c(self.rest_p[steps]),
                         c(self.rest_R[steps]), c(K_fs), c(K_fd), c(K_ts), c(K_td), c(np.reshape(beta, (nc, 2))),
                         np.zeros(nc, dtype=bool), r, J, np.empty((0, nc, 6, 6)))
        return r, J

    def equilibrium(self, k: int = 0, iterations: int = 30):
        """Static flexibility ``(R, q)`` at step ``k`` (:func:`static_equilibrium`)."""
        return static_equilibrium(self.rec.mass, self.g, _inputs(self.rec, k), self.active[k], self.contact_p[k],
                                  self.contact_R[k], self.rest_p[k], self.rest_R[k],
                                  [self.K_fs, self.K_fd, self.K_ts, self.K_td], self.beta, self.iso,
                                  iterations, where=f"step {k}")
