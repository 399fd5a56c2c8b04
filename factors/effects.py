r"""Model effects: the :class:`Effect` protocol, the :class:`ProblemView` it is written against, and
the catalogue (the hidden physics of the simulator as estimator-side model extensions).

The protocol lives with the physics, not with an estimator: an effect reads the problem through
:class:`ProblemView` (the per-step inputs, the contact parameters, the noise sigmas and the
contact law with other parameters), which :class:`flexforce.smoother.Problem` satisfies and any
other estimator can provide.  This module imports nothing of the project above ``factors/``.

Each class of the catalogue implements :class:`Effect` (per-step unknowns, a first-step prior, a
random walk between steps, additive terms in family residuals, a readable report) for one of the
simulator's hidden effects (:mod:`flexforce.datasets.sim.effects` defines them; the parameterisation
below is chosen so that the truth maps onto it exactly).

=========================  ====  ==========================  ======================================
name                       dim   unknowns (unit)              family and term
=========================  ====  ==========================  ======================================
``external-wrench``        6     ``(F, T)`` N, N m, world     ``newton_euler``: ``- e`` (a wrench
                                 axes, moment about the       besides the contacts'); random walk
                                 world origin
``gyro-bias``              3     rad/s, IMU frame             ``imu`` gyro rows: ``+ e``
``accel-bias``             3     m/s^2, IMU frame             ``imu`` accelerometer rows: ``+ e``
``stiffness``              2     ``(kappa_s, kappa_d)``: the  ``contact``: ``kappa_s f(K_fs, 0, K_ts,
                                 scales are ``1 + kappa``     0) + kappa_d f(0, K_fd, 0, K_td)``
``anisotropic-stiffness``  6     ``kappa_f``, ``kappa_t``     ``contact``: ``sum_j kappa_fj
                                 per contact-frame axis:      f(E_j K_fs) + kappa_tj f(E_j K_ts)``,
                                 ``K <- diag(1 + kappa) K``   ``E_j = e_j e_j^T``
``nonlinear-stiffness``    2     ``(d beta_f 1/m^2,           ``contact``: the cubic part of eq. 6,
                                 d beta_t 1/rad^2)``          11 times the added coefficient
``com-offset``             2     ``delta`` m, local frame     ``newton_euler``: the required wrench
                                 (x, y; ``axes="xyz"`` for    with ``c_l + delta`` (and ``I_l``,
                                 all three)                   ``sigma_l`` accordingly), minus the
                                                              nominal one
``imu-mounting``           3     ``delta`` rad, rotation      ``imu``: ``(exp(delta)^T - I) y(s)``,
                                 vector, IMU frame            both sensors
``time-offset``            1     ``tau`` s (IMU late)         ``imu``: the readings' signal ``tau``
                                                              later (an exact delay)
``mass-scale``             1     ``kappa``: mass and inertia  ``newton_euler``: ``kappa`` times the
                                 times ``1 + kappa``          required wrench
``ft-offset``              6 n   ``(F, T)`` N, N m, sensor    ``ft`` rows of contact ``i``:
                                 frame, per contact with an   ``+ e_i`` (the reading's offset;
                                 F/T sensor (``n`` of them)   needs ``ModelConfig.use_ft``)
=========================  ====  ==========================  ======================================

``f(K_fs, K_fd, K_ts, K_td)`` is the contact law (eq. 6-12) evaluated with those matrices
(:meth:`ProblemView.contact_law_terms`); it is linear in them, so a parameter that scales a matrix by
``1 + kappa`` adds exactly ``kappa f(K)`` to the contact residual.  The contact effects are
relative changes of the *nominal* law: two of them enabled together add their changes (first
order), they do not compose multiplicatively.

Priors and random walks: one rule, no per-scenario tuning
----------------------------------------------------------
- Constant parameters (biases, stiffness scales, cubic coefficients, CoM offset): a loose prior
  (the data decide) and a random walk of ``1e-6`` of the prior sigma per step (numerically
  constant; the effect declares ``constant = True``).  Prior sigmas:

  * IMU biases: 10 per-sample sensor sigmas (``ModelConfig.gyro_sigma``, ``accel_sigma``):
    a bias the size of one sample's noise is what the data must find; ten times that covers an
    uncalibrated MEMS (0.12 rad/s = 7 deg/s, 0.55 m/s^2 for Romeo's IMU).  A slowly drifting bias
    is available with ``rw_density`` (rad/s/sqrt(s) or m/s^2/sqrt(s), per-step sigma
    ``rw_density sqrt(dt)``); the default is a constant bias.
  * stiffness and damping scales, per-axis stiffness scales: ``kappa`` sigma 0.5 (the nominal
    known to a factor ~1.5, a wrong or worn bush).
  * cubic coefficients: 100 % stiffening at one sigma at the reference deflection:
    ``sigma_beta_f = 1 / s_0^2`` with ``s_0 = m g / sum_i k_fs,i`` the static compression of the
    springs under the robot's weight; ``sigma_beta_t = 1 / Omega_0^2`` with
    ``Omega_0 = s_0 / l``, the rotation that compresses the spring by as much at the contact
    lever ``l`` (the largest horizontal distance of a contact from the local origin, >= 5 cm).
  * CoM offset: 10 % of the CoM's distance from the local origin (first sample) per axis.
  * IMU mounting rotation: 0.05 rad (3 deg) per axis; IMU time offset: 0.02 s (a few samples of
    unsynchronised clocks); mass scale ``kappa``: 0.2 (a model's mass off by a fifth).
  * F/T offsets: 10 per-sample sensor sigmas, as the IMU biases (``ModelConfig.ft_force_sigma``,
    ``ft_torque_sigma``): 20 N and 2 N m per axis with the default 2 N, 0.2 N m.
- ``external-wrench`` (time-varying): prior sigma of the robot's weight (force) and weight
  times the CoM distance from the origin (moment); random walk per step
  ``sigma_NE dt / tau`` with ``sigma_NE`` the Newton-Euler family's per-sample sigma (the
  unmodelled wrench the nominal model already tolerates) and ``tau = 0.02 s``.  A random walk of
  increments ``s_w`` seen through white noise ``s_v`` is smoothed over ``s_v / s_w`` steps, so the
  estimate follows the wrench with a time constant ``tau``: a push rising in 20 ms or more
  (a 0.1 s half-sine) is followed, the sample-to-sample unmodelled wrench is not absorbed,
  and the effective dof stay near ``6 N dt / (2 tau)``, about 5 % of the steps' count per axis.

Reports
-------
``report(values, cov, t)`` returns ``value``, ``std`` (last step; constant effects have one
value), ``unit``, ``labels``, ``summary`` (a readable sentence: ``"gyro bias y = 0.011 ± 0.001
rad/s"``) and, for ``external-wrench``, ``windows``: the spans where the estimated force is
significant (chi-square of the 3-D force against its covariance above the 99.9 % quantile, gaps
under 50 ms merged, spans under 20 ms dropped) with their peak force; and the force series.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from flexforce.errors import ConfigError

# ----------------------------------------------------------------------------------------------
# The protocol
# ----------------------------------------------------------------------------------------------


class RecordingView(Protocol):
    """What an effect reads of the recording itself."""

    @property
    def mass(self) -> float:
        """Total mass of the robot's model, kg."""


class SigmasView(Protocol):
    """What an effect reads of the noise of the factor families (the unwhitened residuals' units)."""

    @property
    def imu(self) -> np.ndarray:
        """(6,) per-sample sigmas of the gyro (rad/s) and accelerometer (m/s^2) residuals."""

    @property
    def ft(self) -> np.ndarray:
        """(6,) per-sample sigmas of the F/T force (N) and torque (N m) residuals (read only by
        effects on the ``ft`` family)."""

    @property
    def newton_euler_cov(self) -> np.ndarray | None:
        """(6, 6) covariance of the wrench the nominal model leaves unexplained (N, N m; F and T
        about the world origin, correlated)."""


@runtime_checkable
class ProblemView(Protocol):
    """The minimal view of an estimation problem that the effects are written against.

    Only what the catalogue and the documented example (docs/example_effect.py) read; read-only.
    Per-step arrays have ``N`` rows (steps) and are indexed by the ``steps`` an effect receives;
    ``C`` is the number of contacts; the inputs are in the local frame (seed sec. II,
    :class:`flexforce.factors.physics.Inputs`).  :class:`flexforce.smoother.Problem` satisfies it.
    """

    @property
    def rec(self) -> RecordingView:
        """The recording (an effect reads its ``mass``, kg)."""

    @property
    def g(self) -> float:
        """Gravity, m/s^2."""

    @property
    def dt(self) -> float:
        """Sampling period, s."""

    @property
    def nc(self) -> int:
        """Number of contacts ``C``."""

    @property
    def sigmas(self) -> SigmasView:
        """Noise of the factor families."""

    @property
    def com(self) -> np.ndarray:
        """(N, 3) CoM in the local frame, m."""

    @property
    def com_vel(self) -> np.ndarray:
        """(N, 3) its velocity, m/s."""

    @property
    def com_acc(self) -> np.ndarray:
        """(N, 3) its acceleration, m/s^2."""

    @property
    def inertia(self) -> np.ndarray:
        """(N, 3, 3) rotational inertia about the local origin, kg m^2."""

    @property
    def inertia_dot(self) -> np.ndarray:
        """(N, 3, 3) its time derivative, kg m^2/s."""

    @property
    def sigma_l(self) -> np.ndarray:
        """(N, 3) angular momentum about the local origin, kg m^2/s."""

    @property
    def sigma_dot(self) -> np.ndarray:
        """(N, 3) its time derivative, N m."""

    @property
    def contact_p(self) -> np.ndarray:
        """(N, C, 3) contact positions in the local frame, m."""

    @property
    def contact_R(self) -> np.ndarray:
        """(N, C, 3, 3) contact orientations in the local frame."""

    @property
    def imu_R(self) -> np.ndarray:
        """(N, 3, 3) IMU orientation in the local frame (the robot's model of it)."""

    @property
    def imu_p(self) -> np.ndarray:
        """(N, 3) IMU position in the local frame, m."""

    @property
    def imu_v(self) -> np.ndarray:
        """(N, 3) its velocity in the local frame, m/s."""

    @property
    def imu_a(self) -> np.ndarray:
        """(N, 3) its acceleration in the local frame, m/s^2."""

    @property
    def imu_w(self) -> np.ndarray:
        """(N, 3) the IMU frame's angular velocity in the local frame, rad/s."""

    @property
    def y_imu(self) -> np.ndarray:
        """(N, 6) the IMU readings: gyro (rad/s) and accelerometer (m/s^2), IMU frame (a placeholder
        where ``imu_use`` is 0)."""

    @property
    def imu_use(self) -> np.ndarray:
        """(N, 6) 1.0 where the IMU reading is used, 0.0 where it is missing or saturated."""

    @property
    def active(self) -> np.ndarray:
        """(N, C) bool: contact in force."""

    @property
    def rest_p(self) -> np.ndarray:
        """(N, C, 3) nominal rest positions in the world (footholds), m."""

    @property
    def rest_R(self) -> np.ndarray:
        """(N, C, 3, 3) nominal rest orientations in the world."""

    @property
    def beta(self) -> np.ndarray:
        """(C, 2) cubic stiffening coefficients ``(beta_f 1/m^2, beta_t 1/rad^2)``."""

    @property
    def iso(self) -> np.ndarray:
        """(C,) bool: isotropic contact (stiffness not rotated with the contact)."""

    @property
    def K_fs(self) -> np.ndarray:
        """(C, 3, 3) translational stiffness in the contact frame, N/m."""

    @property
    def K_fd(self) -> np.ndarray:
        """(C, 3, 3) translational damping, N s/m."""

    @property
    def K_ts(self) -> np.ndarray:
        """(C, 3, 3) rotational stiffness, N m/rad."""

    @property
    def K_td(self) -> np.ndarray:
        """(C, 3, 3) rotational damping, N m s/rad."""

    def contact_law_terms(self, steps: np.ndarray, R: np.ndarray, q: np.ndarray, K_fs: np.ndarray,
                          K_fd: np.ndarray, K_ts: np.ndarray, K_td: np.ndarray,
                          beta: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The contact law (eq. 6-12) of every contact with other parameters: ``f`` (n, C, 6) and
        ``df/ds`` (n, C, 6, 18), zero for inactive contacts (:meth:`flexforce.smoother.Problem.contact_law_terms`)."""


@runtime_checkable
class Effect(Protocol):
    """A named extension of the nominal model: per-step unknowns plus terms in family residuals.

    The state of one step is ``(s, W_1..W_C, e_1..e_E)``: the core 18 components
    ``s = (theta, t, w, v, dw, a)`` (world-frame increments), the contact wrenches, then each
    effect's ``dim`` components in the order of ``ModelConfig.effects``.  All array arguments
    cover ``n`` steps at once (the batch smoother passes the whole recording, the fixed-lag
    smoother one step), so an effect written with numpy broadcasting serves both.
    """

    name: str
    """Short identifier, e.g. ``external-wrench``."""
    dim: int
    """Unknowns per step."""
    labels: tuple[str, ...]
    """One label per unknown, with its unit, e.g. ``("F_x [N]", ...)``."""

    def prior(self, problem: ProblemView) -> tuple[np.ndarray, np.ndarray]:
        """Mean and sigma (both ``(dim,)``) of the effect's value at the first step."""

    def random_walk_sigma(self, problem: ProblemView) -> np.ndarray:
        """Sigma of ``e_k+1 - e_k``: ``(dim,)`` for every step (tiny for a constant parameter), or
        ``(N - 1, dim)`` per transition (row ``k`` between steps ``k`` and ``k + 1``)."""

    def residual_terms(self, family: str, problem: ProblemView, steps: np.ndarray, R: np.ndarray,
                       q: np.ndarray, W: np.ndarray, e: np.ndarray):
        """The effect's additive term in ``family``'s (unwhitened) residual, or None.

        Args:
            family: ``newton_euler`` (6 rows), ``imu`` (6 rows), ``contact`` (6 rows per
                contact: the contact law ``f_i(s) - W_i``; the term is added where contact ``i``
                is active and ignored where it is not; :meth:`ProblemView.contact_law_terms`
                evaluates the law with other stiffness/damping matrices, which is what such terms
                need) or ``ft`` (6 rows per contact, only with ``ModelConfig.use_ft``: the
                contact's wrench in its sensor frame minus the F/T reading; the term is added
                where the contact is active and the reading's component finite).
            steps: (n,) indices of the steps (to read per-step inputs from ``problem``).
            R, q: (n, 3, 3) rotations and (n, 15) ``(t, w, v, dw, a)``.
            W: (n, C, 6) contact wrenches.
            e: (n, dim) the effect's values.

        Returns:
            None when the effect does not touch ``family``, else ``(dr, dr_ds, dr_de)`` with
            shapes (n, 6), (n, 6, 18) and (n, 6, dim) (``contact``: (n, C, 6), (n, C, 6, 18) and
            (n, C, 6, dim)): the term and its Jacobians with respect to the core state
            (world-frame increments) and to ``e``.
        """

    def report(self, values: np.ndarray, cov: np.ndarray | None) -> dict:
        """JSON-serialisable summary of the estimated effect (values (N, dim), cov (N, dim, dim)).

        Optional: when the method takes a ``t`` keyword the smoothers pass the steps' times (N,)
        in seconds from the start (for time-varying effects: *when* the effect acts).  An effect
        may also set ``constant = True`` (its value does not vary: the random walk only ties the
        steps together; without the attribute, a random walk negligible over the recording means
        the same); :func:`flexforce.smoother.fit` then counts its effective dof from its prior
        alone, and the batch smoother makes it one global block estimated by the marginal
        likelihood (docs/smoother.md, :mod:`flexforce.smoother.evidence`), still passing ``e`` of
        shape (n, dim) to ``residual_terms``; its optional ``feasible(values (dim,)) -> bool``
        rejects steps out of the physical range (a negative stiffness).  And an
        effect may define ``step_prior_sigma(problem) -> (dim,)``: a prior at *every* step around
        the prior mean (with the random walk, a mean-reverting process: for transient effects
        whose constant part the data cannot tell from the core state).  Finally an effect may define
        ``factors(problem, steps, R, q, e) -> {name: (r (n, m), dr_ds (n, m, 18), dr_de (n, m, dim),
        weight (n,))}``: factors of its own on single steps, residuals already whitened, ``weight``
        1 where a factor exists and 0 where not (:class:`flexforce.factors.footholds.Footholds`: the
        leg kinematics at a touch-down and the ground plane).  An effect may name the families whose
        ``residual_terms`` it returns in ``acts_on`` (a tuple of ``newton_euler``, ``contact``,
        ``imu``, ``ft``): the Occam term's gradient then re-evaluates only those families and the
        effect's own factors when it varies the effect's values (without it, every family).  An
        effect whose terms are its values on fixed rows (``dr_ds`` zero, ``dr_de`` the same at
        every value) and that has no factors of its own may say so with ``additive = True`` (the
        IMU biases, the F/T offsets): the Occam term's gradient then skips its columns wherever
        no robust weight can move with them.

        For the diagnostics (all optional): ``plausible(report, problem=None) -> str | None``, the
        reason an estimate (this method's dict) is physically implausible (a stiffness a twentieth
        of the configured one, a bias beyond the sensor's specification, a push heavier than the
        robot), None when it is plausible; ``excites`` (one text per unknown: the motion or load
        that makes the data see it, named when a recording does not); ``hint`` (what a recording
        should do to tell the effect from those it resembles); ``applicable(problem) -> str |
        None``, None when the effect has something to act on in ``problem``, else the reason in
        the user's terms (an F/T offset when the F/T readings are not fused): the diagnosis then
        skips the candidate with that one line instead of fitting an unknown nothing constrains;
        ``score_understates = True`` when the score test (the slope at zero) is no measure of the
        effect (a delay is not linear in its value): the diagnosis refits it in every round
        whatever its test.
        """



# ----------------------------------------------------------------------------------------------
# The catalogue
# ----------------------------------------------------------------------------------------------

_AX = ("x", "y", "z")
_CHI2_6_999 = 22.458  # chi^2_6 99.9 % quantile
CONSTANT_RW = 1e-6
"""Random-walk sigma of a constant parameter, relative to its prior sigma."""


def _skew(v):
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape + (3,))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def _fmt(x: float) -> str:
    return f"{x:.3g}" if abs(x) >= 1e-3 or x == 0 else f"{x:.2e}"


def _pm(value: float, std: float, unit: str) -> str:
    """``0.011 ± 0.001 rad/s`` with the value rounded to the std's first significant digit(s)."""
    if std > 0 and np.isfinite(std):
        digits = max(0, 1 - int(np.floor(np.log10(std))))
        if digits <= 8:
            return f"{value:.{digits}f} ± {std:.{digits}f} {unit if unit != '-' else ''}".rstrip()
    return f"{_fmt(value)} ± {_fmt(std)} {unit}".rstrip()


def _static_compression(problem: ProblemView) -> tuple[float, float]:
    """``(s_0, l)``: static spring compression under the weight (m) and the contact lever (m)."""
    m, g = float(problem.rec.mass), problem.g
    k = sum(float(np.trace(K)) / 3.0 for K in problem.K_fs)
    s0 = m * g / max(k, 1e-9)
    p = problem.contact_p[0]
    lever = max(0.05, float(np.max(np.linalg.norm(p[:, :2], axis=1))))
    return s0, lever


class _Constant:
    """Shared parts of a constant-parameter effect: prior sigma, numerically constant walk, report."""

    name = ""
    dim = 0
    labels: tuple[str, ...] = ()
    constant = True
    unit = ""
    what = ""
    offset = 0.0
    """Added to the unknowns in the report (1 for scales ``1 + kappa``)."""
    null = 0.0
    """Report value when the effect is absent."""

    def prior_sigma(self, problem: ProblemView) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    def prior(self, problem: ProblemView):
        return np.zeros(self.dim), np.asarray(self.prior_sigma(problem), dtype=float)

    def random_walk_sigma(self, problem: ProblemView):
        return CONSTANT_RW * np.asarray(self.prior_sigma(problem), dtype=float)

    def residual_terms(self, family, problem: ProblemView, steps, R, q, W, e):  # pragma: no cover - overridden
        return None

    def component_names(self) -> tuple[str, ...]:
        return tuple(lab.split(" [")[0] for lab in self.labels)

    def units(self) -> tuple[str, ...]:
        return tuple(lab.split("[")[1].rstrip("]") if "[" in lab else "" for lab in self.labels)

    plausible_range: tuple[float, float] | None = None
    """Range of a plausible reported value (every component), None: no bound of its own."""
    excites: tuple[str, ...] = ()
    """Per unknown: the motion or load that makes the data see it (what a recording lacks when
    the unknown cannot be fitted)."""
    hint = ""
    """What a recording should do to tell this effect from the others it resembles."""

    def plausible(self, report: dict, problem: ProblemView | None = None) -> str | None:
        """None when the estimate in ``report`` (:meth:`report`'s dict) is physically plausible, else
        the reason in the robot's terms (the value is then no finding: the effect stands in for
        something else)."""
        if self.plausible_range is None:
            return None
        lo, hi = self.plausible_range
        v = np.atleast_1d(np.asarray(report.get("value", ()), dtype=float))
        names, units = self.component_names(), self.units()
        bad = [i for i in range(min(len(v), self.dim)) if not lo <= v[i] <= hi]
        if not bad:
            return None
        return "; ".join(f"{self.what} {names[i]} = {_fmt(v[i])} {units[i] if units[i] != '-' else ''}".rstrip()
                         + f" is outside the plausible {_fmt(lo)}-{_fmt(hi)}" for i in bad)

    def report(self, values, cov, t=None) -> dict:
        v = np.asarray(values, dtype=float)[-1] + self.offset
        std = (np.sqrt(np.maximum(np.diagonal(np.asarray(cov)[-1]), 0.0)) if cov is not None
               else np.full(self.dim, np.nan))
        names, units = self.component_names(), self.units()
        z = np.abs(v - self.null) / np.where(std > 0, std, np.inf)
        sig = [i for i in range(self.dim) if z[i] > 3.0]
        parts = [f"{self.what} {names[i]} = {_pm(v[i], std[i], units[i])}" for i in (sig or range(self.dim))]
        summary = "; ".join(parts)
        if not sig:
            summary = f"{self.what}: consistent with {_fmt(self.null)} ({summary})"
        return {"value": v.tolist(), "std": std.tolist(), "unit": self.unit, "labels": list(self.labels),
                "significant": [names[i] for i in sig], "z": z.tolist(), "summary": summary}


# ----------------------------------------------------------------------------------------------
# IMU family
# ----------------------------------------------------------------------------------------------


class _ImuBias(_Constant):
    acts_on = ("imu",)
    """The residual families its values enter (see :meth:`Effect.report`)."""
    additive = True
    """Its term is its value on fixed rows (see :meth:`Effect.report`)."""
    rows = slice(0, 3)
    sensor = 0

    max_bias = 0.0
    """Largest plausible bias (the sensor's specification), in the effect's unit."""

    def __init__(self, rw_density: float = 0.0, max_bias: float | None = None):
        self.rw_density = float(rw_density)
        if self.rw_density < 0:
            raise ConfigError(f"{self.name}: rw_density must be >= 0, got {rw_density}")
        self.constant = self.rw_density == 0.0
        if max_bias is not None:
            if not max_bias > 0:
                raise ConfigError(f"{self.name}: max_bias must be positive ({self.unit}), got {max_bias}")
            self.max_bias = float(max_bias)

    def plausible(self, report: dict, problem: ProblemView | None = None) -> str | None:
        """A bias beyond the sensor's specification (``max_bias``, per axis) is implausible."""
        v = np.atleast_1d(np.asarray(report.get("value", ()), dtype=float))
        bad = [i for i in range(min(len(v), 3)) if abs(v[i]) > self.max_bias]
        if not bad:
            return None
        return "; ".join(f"{self.what} {_AX[i]} = {_fmt(v[i])} {self.unit} is beyond the sensor's specification "
                         f"(|bias| <= {_fmt(self.max_bias)} {self.unit})" for i in bad)

    def prior_sigma(self, problem: ProblemView):
        return 10.0 * problem.sigmas.imu[self.rows]

    def random_walk_sigma(self, problem: ProblemView):
        if self.rw_density > 0.0:
            return np.full(3, self.rw_density * np.sqrt(problem.dt))
        return super().random_walk_sigma(problem)

    def residual_terms(self, family, problem: ProblemView, steps, R, q, W, e):
        if family != "imu":
            return None
        n = len(steps)
        dr = np.zeros((n, 6))
        dr[:, self.rows] = e
        dr_de = np.zeros((n, 6, 3))
        dr_de[:, self.rows, :] = np.eye(3)
        return dr, np.zeros((n, 6, 18)), dr_de

    def report(self, values, cov, t=None):
        out = super().report(values, cov, t)
        if not self.constant:
            v = np.asarray(values)
            out["mean"] = v.mean(axis=0).tolist()
            out["drift"] = (v[-1] - v[0]).tolist()
        return out


class GyroBias(_ImuBias):
    """Gyrometer bias (IMU frame, rad/s), added to the gyro reading's prediction (the simulator's
    ``gyro = true + bias``).  Constant unless ``rw_density`` (rad/s/sqrt(s)) is given."""

    name = "gyro-bias"
    dim = 3
    labels = tuple(f"{a} [rad/s]" for a in _AX)
    unit = "rad/s"
    what = "gyro bias"
    rows = slice(0, 3)
    max_bias = 0.05
    """0.05 rad/s (3 deg/s): an uncalibrated MEMS gyro's turn-on bias (``max_bias=`` for another part)."""
    excites = ("the gyro's x reading", "the gyro's y reading", "the gyro's z reading")
    hint = ("hold the robot still for a moment (a bias is the rate read at rest) or rotate about each axis: "
            "a true rotation tilts the robot and loads the contacts, a bias does neither")


class AccelBias(_ImuBias):
    """Accelerometer bias (IMU frame, m/s^2), added to the accelerometer's prediction.  Constant
    unless ``rw_density`` (m/s^2/sqrt(s)) is given."""

    name = "accel-bias"
    dim = 3
    labels = tuple(f"{a} [m/s^2]" for a in _AX)
    unit = "m/s^2"
    what = "accel bias"
    rows = slice(3, 6)
    max_bias = 0.3
    """0.3 m/s^2: an uncalibrated MEMS accelerometer's offset (``max_bias=`` for another part)."""
    excites = ("tilting the IMU about y (gravity along x) or accelerating along x",
               "tilting the IMU about x (gravity along y) or accelerating along y",
               "accelerating vertically, or tilting far")
    hint = ("tilt the robot or change its posture: a bias turns with the IMU while gravity does not, and it "
            "does not move the CoP")


def _imu_prediction(problem: ProblemView, steps, R, q) -> tuple[np.ndarray, np.ndarray]:
    """The nominal IMU prediction (eq. 26-28, IMU frame) ``y`` (n, 6) and ``dy/ds`` (n, 6, 18) at the
    given states, with the recording's IMU placement and motion at ``steps``."""
    from flexforce.factors import core

    steps = np.asarray(steps)
    n = len(steps)
    cc = np.ascontiguousarray
    y, J = np.empty((n, 6)), np.empty((n, 6, core.STATE_DIM))
    core.imu_all(cc(R, dtype=float), cc(q, dtype=float), np.zeros((n, 6)), cc(problem.imu_R[steps], dtype=float),
                 cc(problem.imu_p[steps], dtype=float), cc(problem.imu_v[steps], dtype=float),
                 cc(problem.imu_a[steps], dtype=float), cc(problem.imu_w[steps], dtype=float), float(problem.g), y, J)
    return y, J


def _exp_jl(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``exp(phi)`` and the left Jacobian ``J_l(phi)`` for (n, 3) rotation vectors."""
    from flexforce.factors import core

    phi = np.ascontiguousarray(np.reshape(phi, (-1, 3)), dtype=float)
    E, Jl = np.empty((len(phi), 3, 3)), np.empty((len(phi), 3, 3))
    core.so3_exp_jl_all(phi, E, Jl)
    return E, Jl


class ImuMounting(_Constant):
    r"""Small rotation ``delta`` (rad, a rotation vector in the IMU frame) of the IMU frame against
    the robot's model of it: the sensor's true axes are the model's turned by ``exp(delta)``
    (``imu_R_true = imu_R exp(delta)``), the simulator's ``imu-mounting`` (it turns the IMU frame
    of its own copy of the URDF).  Both readings are then the nominal ones seen in the turned axes,
    ``y' = exp(delta)^T y``, so the term on the ``imu`` family (gyro and accelerometer rows alike)
    is::

        dr     = (exp(delta)^T - I) y(s)
        dr/ds  = (exp(delta)^T - I) dy/ds
        dr/dd  = exp(delta)^T [y]x J_l(delta)        (exp(-d - e) = exp(-d) exp(-J_l(d) e) to first order)

    with ``y(s)`` the nominal prediction of eq. 26-28.  Other IMU effects (biases) add to the
    prediction unrotated (first order in the product of the two).  A rotation about a horizontal
    axis turns gravity into the horizontal axes (``g delta`` m/s^2: an accelerometer bias at rest);
    what tells it from a bias is that it turns every other reading too: the gyro's rates, the
    horizontal accelerations of a sway (``delta_z a_y`` on x), the vertical ones.
    """
    acts_on = ("imu",)
    """The residual families its values enter (see :meth:`Effect.report`)."""

    name = "imu-mounting"
    dim = 3
    labels = tuple(f"{a} [rad]" for a in _AX)
    unit = "rad"
    what = "IMU mounting rotation"
    max_angle = 0.1
    """0.1 rad (6 deg): a URDF's IMU frame or a sensor's mounting is not that far off unless it is
    wrong altogether (an axis swapped or flipped: fix the model, do not fit it)."""
    excites = ("rotation rates about y or z, or accelerations along y or z of the IMU (gravity along z "
               "reads as a bias on y)",
               "rotation rates about x or z, or accelerations along x or z of the IMU (gravity along z "
               "reads as a bias on x)",
               "rotation rates about x or y, or horizontal accelerations of the IMU (a sway)")
    hint = ("move the IMU: sway or step briskly (a mounting rotation turns the horizontal accelerations and the "
            "rotation rates, an accelerometer bias and a CoM offset do not); at rest a tilt of the mounting "
            "reads like an accelerometer bias")

    def prior_sigma(self, problem: ProblemView):
        """0.05 rad (3 deg) per axis: a mounting or URDF error of a few degrees."""
        return np.full(3, 0.05)

    def plausible(self, report: dict, problem: ProblemView | None = None) -> str | None:
        """A rotation beyond :attr:`max_angle` is implausible."""
        v = np.atleast_1d(np.asarray(report.get("value", ()), dtype=float))
        angle = float(np.linalg.norm(v))
        if angle <= self.max_angle:
            return None
        return (f"IMU mounting rotation of {_fmt(angle)} rad ({np.degrees(angle):.1f} deg) is beyond "
                f"{_fmt(self.max_angle)} rad: an IMU frame that far off is a wrong model (axes swapped), "
                f"not a mounting error")

    def residual_terms(self, family, problem: ProblemView, steps, R, q, W, e):
        if family != "imu":
            return None
        y, Jy = _imu_prediction(problem, steps, R, q)
        d = np.asarray(e, dtype=float)
        E, Jl = _exp_jl(d)
        Et = E.transpose(0, 2, 1)
        n = len(y)
        M = Et - np.eye(3)
        dr = np.empty((n, 6))
        dr_ds = np.empty((n, 6, 18))
        dr_de = np.empty((n, 6, 3))
        for rows in (slice(0, 3), slice(3, 6)):
            dr[:, rows] = np.einsum("nij,nj->ni", M, y[:, rows])
            dr_ds[:, rows] = M @ Jy[:, rows]
            dr_de[:, rows] = Et @ _skew(y[:, rows]) @ Jl
        return dr, dr_ds, dr_de

    def report(self, values, cov, t=None):
        out = super().report(values, cov, t)
        v = np.asarray(out["value"], dtype=float)
        out["angle_deg"] = float(np.degrees(np.linalg.norm(v)))
        return out


class TimeOffset(_Constant):
    r"""Time offset ``tau`` (s) of the IMU against the joint encoders: the IMU sample stamped ``t``
    was taken at ``t - tau`` (``tau > 0``: the IMU is late), the simulator's ``time-offset``
    (which really delays the IMU: its readings are those of the simulated sensor ``tau`` earlier).

    An exact delay, on the readings' side: the prediction at ``t_k`` (from the encoders' inputs at
    ``t_k``) is held against the readings ``tau`` later, ``y_k(tau)``
    (:class:`flexforce.factors.delay.ShiftedSignal`: band-limited; the bands above the noise
    shifted everywhere, the rest within 60 ms of a transient or of a contact's switch, elsewhere
    left at its sample, so that the noise keeps its variance at every ``tau``).  The term on the
    ``imu`` family is ``y_k - y_k(tau)``; ``dr/ds = 0``; ``dr/dtau`` is minus the rate of the
    readings' signal (each band above the noise weighted by its power above it), the expected
    derivative rather than the noise's.  Exact for any ``tau`` and any motion, a contact's switch
    included (the IMU sees a touch-down ``tau`` late: a first-order term ``-tau dy/dt`` cannot, and
    it needed the rate of the model's prediction, which at uncorrected rest placements was fifteen
    times the readings'), up to the content below the noise away from transients.  The steps'
    states are not involved, so the estimators' structure is unchanged; the term reads the readings
    up to ``tau`` past each step (a fixed-lag smoother's lag must cover it), and past the series'
    ends the readings' smooth return from the last sample to the first (``delay.PAD_S``).
    """
    acts_on = ("imu",)
    """The residual families its values enter (see :meth:`Effect.report`)."""

    name = "time-offset"
    dim = 1
    labels = ("tau [s]",)
    unit = "s"
    what = "IMU time offset"
    max_offset = 0.05
    """0.05 s: no sensor on the robot's own bus is that late; logs that far apart are to be
    resynchronised."""
    excites = ("changing readings: the rate at which the IMU's accelerations and rotation rates change "
               "(brisk motion, impacts)",)
    hint = ("move briskly, with changes of acceleration (quick sways, steps, impacts): a delay shows where the "
            "readings change, a bias or a mounting rotation where they are large")

    def __init__(self):
        self._signal: tuple[np.ndarray, object] | None = None

    def prior_sigma(self, problem: ProblemView):
        """0.02 s: unsynchronised clocks a few samples apart."""
        return np.array([0.02])

    def plausible(self, report: dict, problem: ProblemView | None = None) -> str | None:
        """An offset beyond :attr:`max_offset` is implausible."""
        v = np.atleast_1d(np.asarray(report.get("value", ()), dtype=float))
        if v.size == 0 or abs(float(v[0])) <= self.max_offset:
            return None
        return (f"IMU time offset of {_fmt(float(v[0]))} s is beyond {_fmt(self.max_offset)} s: no sensor on the "
                f"robot's bus is that late; resynchronise the logs")

    def signal(self, problem: ProblemView):
        """The :class:`flexforce.factors.delay.ShiftedSignal` of ``problem``'s IMU readings (kept
        while the problem's readings are the same array)."""
        from flexforce.factors.delay import ShiftedSignal

        y = problem.y_imu
        if self._signal is None or self._signal[0] is not y:
            act = np.asarray(problem.active, dtype=bool)
            switches = 1 + np.nonzero(np.any(act[1:] != act[:-1], axis=1))[0]
            self._signal = (y, ShiftedSignal(y, float(problem.dt), np.asarray(problem.imu_use) > 0, switches))
        return self._signal[1]

    score_understates = True
    """Its score test, the slope at zero, sees of a delay of several samples only what the nearest
    samples show (across an impact, little), and on a slow recording the readings' fast content
    weighs in its information without moving with the delay: a diagnosis refits it in every round
    whatever its test (a 20 ms delay on a 3 s TALOS sway: T = 3.4, its refit 2 Delta E = 26; a
    15 ms delay on a simulated walk: T = 77 beside stiffness tests of 300-450, its refit 4 706)."""

    def residual_terms(self, family, problem: ProblemView, steps, R, q, W, e):
        if family != "imu":
            return None
        steps = np.asarray(steps)
        tau = np.asarray(e, dtype=float)[:, 0]
        # unshifted, the readings are the samples (where one is not used, its row has no weight)
        x1, d1 = self.signal(problem).at(steps, tau)
        return problem.y_imu[steps] - x1, np.zeros((len(steps), 6, 18)), -d1[:, :, None]

    def report(self, values, cov, t=None):
        out = super().report(values, cov, t)
        out["ms"] = 1e3 * float(out["value"][0])
        return out

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_signal"] = None
        return state


# ----------------------------------------------------------------------------------------------
# Contact family
# ----------------------------------------------------------------------------------------------


class _ContactEffect(_Constant):
    """A constant change of the contact law: ``term = sum_j e_j f_j(s)`` (linear in the unknowns)."""
    acts_on = ("contact",)
    """The residual families its values enter (see :meth:`Effect.report`)."""

    def basis(self, problem: ProblemView, steps, R, q):
        """List of ``(f_j (n, C, 6), df_j/ds (n, C, 6, 18))``, one per unknown."""
        raise NotImplementedError  # pragma: no cover

    def residual_terms(self, family, problem: ProblemView, steps, R, q, W, e):
        if family != "contact":
            return None
        fs = self.basis(problem, steps, R, q)
        n, nc = len(steps), problem.nc
        dr = np.zeros((n, nc, 6))
        dr_ds = np.zeros((n, nc, 6, 18))
        dr_de = np.zeros((n, nc, 6, self.dim))
        for j, (f, J) in enumerate(fs):
            ej = e[:, j]
            dr += ej[:, None, None] * f
            dr_ds += ej[:, None, None, None] * J
            dr_de[..., j] = f
        return dr, dr_ds, dr_de


def _zeros_like_K(problem: ProblemView):
    return np.zeros((problem.nc, 3, 3))


class Stiffness(_ContactEffect):
    """Scale of the contacts' stiffness (K_fs and K_ts, by ``1 + kappa_s``) and damping (K_fd and
    K_td, by ``1 + kappa_d``), the same for every contact: the simulator's ``stiffness`` effect
    (``stiffness = 1 + kappa_s``, ``damping = 1 + kappa_d``).  Reported as the scales."""

    name = "stiffness"
    dim = 2
    labels = ("stiffness scale [-]", "damping scale [-]")
    unit = "-"
    what = "contact"
    offset = 1.0
    null = 1.0
    plausible_range = (0.2, 5.0)
    """A stiffness or damping five times off the configured one is a wrong configuration or another
    effect in disguise, not a worn bush."""
    excites = ("load changes on the contacts (sway, shifting weight, pushes): the springs' deflection",
               "fast load changes (quick sway, impacts): the springs' deflection rate")
    hint = "vary the load on the contacts: sway, shift the weight from foot to foot, push"

    def prior_sigma(self, problem: ProblemView):
        return np.array([0.5, 0.5])

    def feasible(self, values) -> bool:
        """A positive stiffness, a damping that does not inject energy."""
        v = np.asarray(values, dtype=float) + self.offset
        return bool(v[0] > 0.05 and v[1] >= 0.0)

    def basis(self, problem: ProblemView, steps, R, q):
        Z = _zeros_like_K(problem)
        spring = problem.contact_law_terms(steps, R, q, problem.K_fs, Z, problem.K_ts, Z)
        damper = problem.contact_law_terms(steps, R, q, Z, problem.K_fd, Z, problem.K_td)
        return [spring, damper]


class AnisotropicStiffness(_ContactEffect):
    """Per-axis scale factors of K_fs and K_ts in the contact frame: ``K <- diag(1 + kappa) K``
    (the simulator's ``anisotropic-stiffness``, ``k_fs = 1 + kappa_f``, ``k_ts = 1 + kappa_t``).
    Reported as the factors."""

    name = "anisotropic-stiffness"
    dim = 6
    labels = tuple(f"k_fs {a} [-]" for a in _AX) + tuple(f"k_ts {a} [-]" for a in _AX)
    unit = "-"
    what = "stiffness factor"
    offset = 1.0
    null = 1.0
    plausible_range = (0.2, 5.0)
    """As :attr:`Stiffness.plausible_range`, per axis."""
    excites = ("shear along the contact's x: a fore-aft force", "shear along the contact's y: a sideways force",
               "vertical load changes: no change of the vertical force", "a torque about x (roll)",
               "a torque about y (pitch)", "a torque about z (yaw)")
    hint = ("load each axis on its own: sway fore-aft and sideways, shift the weight, twist about the vertical; "
            "a stiffer pitch spring and a CoM offset tilt a robot at rest alike, a varying moment does not")

    def prior_sigma(self, problem: ProblemView):
        return np.full(6, 0.5)

    def feasible(self, values) -> bool:
        """Positive stiffness along every axis."""
        return bool(np.all(np.asarray(values, dtype=float) + self.offset > 0.05))

    def basis(self, problem: ProblemView, steps, R, q):
        Z = _zeros_like_K(problem)
        out = []
        for which in ("f", "t"):
            for j in range(3):
                E = np.zeros((3, 3))
                E[j, j] = 1.0
                if which == "f":
                    out.append(problem.contact_law_terms(steps, R, q, E @ problem.K_fs, Z, Z, Z))
                else:
                    out.append(problem.contact_law_terms(steps, R, q, Z, Z, E @ problem.K_ts, Z))
        return out


class NonlinearStiffness(_ContactEffect):
    """Added cubic stiffening ``(d beta_f [1/m^2], d beta_t [1/rad^2])`` of every contact:
    ``F = -K_fs s (1 + (beta_f + d beta_f) |s|^2)``, ``T_0 = -K_ts Omega (1 + (beta_t + d beta_t)
    |Omega|^2)`` (the simulator's ``nonlinear-stiffness`` adds its ``beta_f``, ``beta_t`` so)."""

    name = "nonlinear-stiffness"
    dim = 2
    labels = ("beta_f [1/m^2]", "beta_t [1/rad^2]")
    unit = "1/m^2, 1/rad^2"
    what = "cubic stiffening"
    excites = ("large vertical deflections: large changes of the vertical load",
               "large tilts of the contacts: large moments")
    hint = "vary the load over a wide range (deep sways, stepping): a cubic term grows with the deflection"

    def plausible(self, report: dict, problem: ProblemView | None = None) -> str | None:
        """The tangent stiffness at the reference deflection within ``0.2``-``5`` times the linear
        one, as the stiffness scales: ``1 + 3 (beta + d beta) s_0^2`` (the nominal ``beta`` is left
        out: zero in the built-in robots).  The references: the weight's static compression of
        the translational springs, and the tilt of the rotational springs under the weight's
        largest moment, the CoM over the edge of the contacts (``m g l / K_ts``, the springs'
        own stiffness: on Romeo 0.042 rad, TALOS 0.029; without ``K_ts``, the tilt that
        compresses a contact as much as the weight, ``s_0 / l``)."""
        if problem is None:
            return None
        v = np.atleast_1d(np.asarray(report.get("value", ()), dtype=float))
        s0, lever = _static_compression(problem)
        K_ts = getattr(problem, "K_ts", None)
        k_t = sum(float(np.trace(K)) / 3.0 for K in K_ts) if K_ts is not None else 0.0
        tilt = float(problem.rec.mass) * problem.g * lever / k_t if k_t > 0 else s0 / lever
        ref = (s0, tilt)
        out = []
        for i, (what, unit) in enumerate((("translational", "m"), ("rotational", "rad"))):
            if i >= len(v):
                break
            factor = 1.0 + 3.0 * v[i] * ref[i] ** 2  # tangent stiffness of k s (1 + beta s^2)
            if not 0.2 <= factor <= 5.0:
                out.append(f"{what} cubic stiffening {_fmt(v[i])} makes the tangent stiffness {_fmt(factor)} times "
                           f"the linear one at {_fmt(ref[i])} {unit} (plausible 0.2-5)")
        return "; ".join(out) or None

    def prior_sigma(self, problem: ProblemView):
        s0, lever = _static_compression(problem)
        return np.array([1.0 / s0**2, (lever / s0) ** 2])

    def basis(self, problem: ProblemView, steps, R, q):
        Z = _zeros_like_K(problem)
        nc = problem.nc
        b0 = np.zeros((nc, 2))
        bf = np.zeros((nc, 2))
        bf[:, 0] = 1.0
        bt = np.zeros((nc, 2))
        bt[:, 1] = 1.0
        f1, J1 = problem.contact_law_terms(steps, R, q, problem.K_fs, Z, Z, Z, bf)
        f0, J0 = problem.contact_law_terms(steps, R, q, problem.K_fs, Z, Z, Z, b0)
        t1, Jt1 = problem.contact_law_terms(steps, R, q, Z, Z, problem.K_ts, Z, bt)
        t0, Jt0 = problem.contact_law_terms(steps, R, q, Z, Z, problem.K_ts, Z, b0)
        return [(f1 - f0, J1 - J0), (t1 - t0, Jt1 - Jt0)]


# ----------------------------------------------------------------------------------------------
# Newton-Euler family
# ----------------------------------------------------------------------------------------------


class ExternalWrench:
    """A wrench on the robot besides the contacts' (a push, a cable), world axes, moment about the
    world origin (the simulator's ``Truth.external_wrench``).

    The unknowns are the wrench in the Newton-Euler family's whitened coordinates,
    ``u = L^-1 (F, T)`` with ``L L^T`` the covariance of the unmodelled wrench (a force at the
    CoM has its moment: the two are correlated), so that the random walk and the priors treat a
    push at the CoM as one unit whatever its direction: random walk ``dt / tau`` per step and
    component (time constant ``tau``, module documentation), and a zero-mean prior at every step
    (:meth:`step_prior_sigma`).  The report converts back to ``(F [N], T [N m])``.
    """
    acts_on = ("newton_euler",)
    """The residual families its values enter (see :meth:`Effect.report`)."""

    name = "external-wrench"
    dim = 6
    labels = tuple(f"u_F{a} [-]" for a in _AX) + tuple(f"u_T{a} [-]" for a in _AX)
    unit = "N, N m"
    constant = False
    excites = ("a force along x", "a force along y", "a vertical force (the contacts' total trades against it)",
               "a moment about x", "a moment about y", "a moment about z")
    hint = ("a push is transient: quiet spans before and after it separate it from a constant effect; a steady "
            "wrench is told from a CoM offset only by changing posture")

    def plausible(self, report: dict, problem: ProblemView | None = None) -> str | None:
        """A force larger than the robot's weight (at its peak) is implausible: the contacts could
        not hold the robot against it."""
        weight = self._weight if self._weight else (
            float(problem.rec.mass) * float(problem.g) if problem is not None else None)
        peaks = [float(w.get("peak_norm", 0.0)) for w in report.get("windows") or []]
        if weight is None or not peaks or max(peaks) <= weight:
            return None
        return f"external force of {max(peaks):.0f} N exceeds the robot's weight ({weight:.0f} N)"

    def __init__(self, tau: float = 0.02, prior_weight_fraction: float = 0.08):
        if not tau > 0:
            raise ConfigError(f"external-wrench: tau must be positive (s), got {tau}")
        if not prior_weight_fraction > 0:
            raise ConfigError(f"external-wrench: prior_weight_fraction must be positive, got {prior_weight_fraction}")
        self.tau = float(tau)
        self.prior_weight_fraction = float(prior_weight_fraction)
        # Set from the problem by _setup (the smoother calls prior() before anything else).
        self._L: np.ndarray | None = None
        self._height: float | None = None
        self._weight: float | None = None

    def _setup(self, problem: ProblemView):
        self._L = np.linalg.cholesky(np.asarray(problem.sigmas.newton_euler_cov, dtype=float))
        self._height = max(float(problem.com[0][2]), 0.1)
        self._weight = float(problem.rec.mass) * float(problem.g)
        return self._L

    def prior(self, problem: ProblemView):
        return np.zeros(6), self.step_prior_sigma(problem)

    def step_prior_sigma(self, problem: ProblemView):
        """Zero-mean prior at every step: a force of ``prior_weight_fraction`` (8 %) of the robot's
        weight at the CoM, in whitened units.

        A push is transient; a steady wrench is what a CoM offset (or a lean on the robot) also
        produces, and at rest the two are alike (only the moment tilts the robot).  The prior
        decides who carries the steady part.  With a quarter of the weight a steady wrench cost
        so little that the wrench took a hidden CoM offset too, and pushed the horizontal contact
        forces off by 10 N; at 8 % a steady part costs (0.25/0.08)^2 ~ 10 times more and the
        constant ``com-offset`` takes it (push-com with both effects: force error 3.2 -> 2.8 N
        instead of 3.2 -> 9.7 N), while a real push keeps its size (docs/diagnostics.md)."""
        self._setup(problem)
        weight = float(problem.rec.mass) * float(problem.g)  # what _setup stores in self._weight
        sF = float(np.sqrt(np.mean(np.diag(np.asarray(problem.sigmas.newton_euler_cov, dtype=float))[:3])))
        return np.full(6, self.prior_weight_fraction * weight / sF)

    def random_walk_sigma(self, problem: ProblemView):
        return np.full(6, problem.dt / self.tau)

    def residual_terms(self, family, problem: ProblemView, steps, R, q, W, e):
        if family != "newton_euler":
            return None
        L = self._L if self._L is not None else self._setup(problem)
        n = len(steps)
        return -(np.asarray(e, dtype=float) @ L.T), np.zeros((n, 6, 18)), np.broadcast_to(-L, (n, 6, 6)).copy()

    def wrench(self, values, cov=None):
        """``(F, T)`` (N, 6) and its covariance (N, 6, 6) from the unknowns."""
        L = self._L
        Wv = np.asarray(values, dtype=float) @ L.T
        Wc = None if cov is None else L @ np.asarray(cov) @ L.T
        return Wv, Wc

    def report(self, values, cov, t=None) -> dict:
        v, C = self.wrench(values, cov)
        n = v.shape[0]
        t = np.arange(n, dtype=float) if t is None else np.asarray(t, dtype=float)
        dt = float(t[1] - t[0]) if n > 1 else 1.0
        h = self._height
        F = v[:, :3]
        # the horizontal force at the CoM height with the same moment about the origin
        Feq = np.stack([v[:, 4] / h, -v[:, 3] / h], axis=1)
        u = np.asarray(values, dtype=float)
        if cov is not None:
            Cu = np.asarray(cov)
            z2 = np.einsum("ni,ni->n", u, np.linalg.solve(Cu + 1e-12 * np.eye(6), u[:, :, None])[:, :, 0])
            std = np.sqrt(np.maximum(np.diagonal(C, axis1=1, axis2=2), 0.0))
        else:
            z2 = np.full(n, np.inf)
            std = np.full((n, 6), np.nan)
        on = z2 > _CHI2_6_999
        spans = []
        k = 0
        while k < n:
            if on[k]:
                j = k
                while j + 1 < n and on[j + 1]:
                    j += 1
                spans.append([k, j])
                k = j + 1
            else:
                k += 1
        merged: list[list[int]] = []
        for s_ in spans:
            if merged and (t[s_[0]] - t[merged[-1][1]]) < 0.05:
                merged[-1][1] = s_[1]
            else:
                merged.append(s_)
        windows = []
        for k0, k1 in merged:
            if t[k1] - t[k0] + dt < 0.02:
                continue
            seg = slice(k0, k1 + 1)
            feq = np.linalg.norm(Feq[seg], axis=1)
            kp = k0 + int(np.argmax(feq))
            fx, fy = Feq[kp]
            axis = "x" if abs(fx) >= abs(fy) else "y"
            sign = "-" if (fx if axis == "x" else fy) < 0 else ""
            T = v[kp, 3:]
            fn = np.linalg.norm(F[seg], axis=1)
            kf = k0 + int(np.argmax(fn))
            ax = int(np.argmax(np.abs(F[kf])))
            fsign = "-" if F[kf, ax] < 0 else ""
            windows.append({"start_s": float(t[k0]), "end_s": float(t[k1]), "peak_s": float(t[kf]),
                            "peak_wrench": v[kf].tolist(), "peak_std": std[kf].tolist(),
                            "peak_force": F[kf].tolist(), "peak_norm": float(fn[kf - k0]),
                            "peak_equivalent_force": [float(fx), float(fy)],
                            "impulse": (v[seg].sum(axis=0) * dt).tolist(),
                            "summary": (f"external force ≈ {fn[kf - k0]:.0f} N along {fsign}{_AX[ax]} between "
                                        f"{t[k0]:.2f} s and {t[k1]:.2f} s (peak at {t[kf]:.2f} s: F = "
                                        f"({F[kf, 0]:.0f}, {F[kf, 1]:.0f}, {F[kf, 2]:.0f}) ± ({std[kf, 0]:.0f}, "
                                        f"{std[kf, 1]:.0f}, {std[kf, 2]:.0f}) N, moment about the origin "
                                        f"({T[0]:.1f}, {T[1]:.1f}, {T[2]:.1f}) N m, as a horizontal force at the "
                                        f"CoM height {feq[kp - k0]:.0f} N along {sign}{axis})")})
        steady = None
        if windows and n > 1 and sum(w["end_s"] - w["start_s"] + dt for w in windows) > 0.8 * (t[-1] - t[0] + dt):
            # on for most of the recording: a steady part, which a CoM offset would also explain
            med = np.median(Feq, axis=0)
            a = int(np.argmax(np.abs(med)))
            steady = {"equivalent_force": med.tolist()}
            text = (f"present throughout: a steady part of {abs(med[a]):.1f} N along {'-' if med[a] < 0 else ''}"
                    f"{'xy'[a]} at the CoM height (median)")
            if self._weight:
                delta = np.array([med[0], med[1]]) * h / self._weight
                steady["com_offset_equivalent_m"] = delta.tolist()
                text += (f", which a CoM offset of ({delta[0]:.3f}, {delta[1]:.3f}) m would also explain; "
                         f"try com-offset")
        if windows:
            summary = "; ".join(w["summary"] for w in windows)
            if steady is not None:
                summary += "; " + text
        else:
            summary = (f"no significant external wrench (max equivalent force "
                       f"{float(np.max(np.linalg.norm(Feq, axis=1))):.1f} N)")
        kp = int(np.argmax(z2)) if cov is not None else int(np.argmax(np.linalg.norm(Feq, axis=1)))
        return {"value": v[kp].tolist(), "std": std[kp].tolist(), "unit": self.unit,
                "labels": [f"F_{a} [N]" for a in _AX] + [f"T_{a} [N m]" for a in _AX],
                "peak_s": float(t[kp]), "windows": windows, "summary": summary, "com_height_m": h, "steady": steady,
                "t_s": t.tolist(), "wrench": np.round(v, 3).tolist(), "wrench_std": np.round(std, 3).tolist()}


class ComOffset(_Constant):
    r"""Constant offset ``delta`` (m, local frame) of the CoM ``c_l``.

    The simulator moves the CoM of the heaviest body ``j`` (mass ``m_j = mu M``) by
    ``delta / mu``, keeping its rotational inertia about its own CoM.  Then, with ``c_j`` that
    body's CoM (taken as ``c_l``, and its velocity and acceleration as ``dc_l``, ``ddc_l``: the
    heaviest body carries the CoM's motion), the inputs about the local origin become::

        c_l'     = c_l + delta                              dc_l, ddc_l unchanged
        I_l'     = I_l - M ([c]x [delta]x + [delta]x [c]x) - (M / mu) [delta]x^2   (parallel axis)
        dI_l'    = dI_l - M ([dc]x [delta]x + [delta]x [dc]x)
        sigma_l' = sigma_l + M delta x dc                   (m_j (delta / mu) x dc_j)
        dsigma'  = dsigma_l + M delta x ddc

    and the term is ``required_wrench(inputs') - required_wrench(inputs)`` (eq. 16, 23).  ``mu = 1``
    (default) is a rigid shift of the whole robot; the ``1/mu`` term is second order (``M
    |delta|^2 / mu``, ~0.1 % of ``I_l`` for 3 cm on Romeo).

    ``axes`` (default ``"xy"``): the components estimated, the others held at zero.  The vertical
    offset is left out by default: on a robot standing on flat ground it acts as a change of the
    rotational stiffness (``m g delta_z`` per radian of tilt) and of the rotational inertia, which
    the data barely tell apart from the contact model's own errors -- measured on a 3 s
    ``push-pitch`` with no CoM offset, ``"xyz"`` after the push's external wrench finds
    ``z = -0.115 +- 0.013 m``, "significant" (likelihood-ratio gain 130 for 3 dof), and the force
    error rises from 1.2 to 5.7 N.  Ask for ``axes="xyz"`` where the motion excites it.
    """
    acts_on = ("newton_euler",)
    """The residual families its values enter (see :meth:`Effect.report`)."""

    name = "com-offset"
    unit = "m"
    what = "CoM offset"
    max_fraction = 0.25
    """A CoM more than this fraction of its distance from the local origin off the model's is no
    mass-model error (about 15 cm on Romeo)."""
    hint = ("change posture or load the robot differently (move the arms, lean, step, carry a load): a CoM offset "
            "moves with the body and shifts the CoP, an accelerometer bias does not, and a steady push is not "
            "carried with the posture")

    def plausible(self, report: dict, problem: ProblemView | None = None) -> str | None:
        """An offset beyond :attr:`max_fraction` of the CoM's distance from the local origin."""
        if problem is None:
            return None
        v = np.atleast_1d(np.asarray(report.get("value", ()), dtype=float))
        limit = self.max_fraction * max(float(np.linalg.norm(problem.com[0])), 0.1)
        size = float(np.linalg.norm(v))
        if size <= limit:
            return None
        return (f"CoM offset of {_fmt(size)} m is more than {self.max_fraction:.0%} of the CoM's distance from the "
                f"feet ({_fmt(limit)} m): no mass-model error is that large")

    def __init__(self, mass_fraction: float = 1.0, axes: str = "xy"):
        if not 0 < mass_fraction <= 1:
            raise ConfigError(f"com-offset: mass_fraction must be in (0, 1], got {mass_fraction}")
        axes = str(axes).lower()
        if not axes or any(a not in _AX for a in axes) or len(set(axes)) != len(axes) or list(axes) != sorted(axes):
            raise ConfigError(f"com-offset: axes must be some of 'xyz' in order, e.g. 'xy' or 'xyz'; got {axes!r}")
        self.mu = float(mass_fraction)
        self.axes = axes
        self.dim = len(axes)
        self.labels = tuple(f"{a} [m]" for a in axes)
        self._sel = np.eye(3)[:, [_AX.index(a) for a in axes]]  # (3, dim): delta = sel e
        text = {"x": "gravity's moment about y: a fore-aft tilt or sway",
                "y": "gravity's moment about x: a sideways tilt or sway",
                "z": "tilts large enough for the height to change gravity's moment"}
        self.excites = tuple(text[a] for a in axes)

    def prior_sigma(self, problem: ProblemView):
        return np.full(self.dim, 0.1 * max(float(np.linalg.norm(problem.com[0])), 0.1))

    def inputs(self, problem: ProblemView, steps, d):
        """Modified inputs ``(c, dc, ddc, I, dI, sigma, dsigma)`` for offsets ``d`` (n, 3)."""
        M = float(problem.rec.mass)
        c, dc, ddc = problem.com[steps], problem.com_vel[steps], problem.com_acc[steps]
        Sc, Sdc, Sd = _skew(c), _skew(dc), _skew(d)
        I = problem.inertia[steps] - M * (Sc @ Sd + Sd @ Sc) - (M / self.mu) * (Sd @ Sd)
        dI = problem.inertia_dot[steps] - M * (Sdc @ Sd + Sd @ Sdc)
        sig = problem.sigma_l[steps] + M * np.cross(d, dc)
        dsig = problem.sigma_dot[steps] + M * np.cross(d, ddc)
        return c + d, dc, ddc, I, dI, sig, dsig

    def residual_terms(self, family, problem: ProblemView, steps, R, q, W, e):
        if family != "newton_euler":
            return None
        from flexforce.factors import core

        steps = np.asarray(steps)
        n = len(steps)
        M, g = float(problem.rec.mass), problem.g
        d = np.asarray(e, dtype=float) @ self._sel.T
        cc = np.ascontiguousarray
        R = cc(R, dtype=float)
        q = cc(q, dtype=float)
        zero = np.zeros((n, 6))
        r1, J1 = np.empty((n, 6)), np.empty((n, 6, 18))
        r0, J0 = np.empty((n, 6)), np.empty((n, 6, 18))
        c, dc, ddc, I, dI, sig, dsig = self.inputs(problem, steps, d)
        core.newton_euler_all(R, q, zero, M, cc(c), cc(dc), cc(ddc), cc(I), cc(dI), cc(sig), cc(dsig), g, r1, J1)
        core.newton_euler_all(R, q, zero, M, cc(problem.com[steps]), cc(dc), cc(ddc), cc(problem.inertia[steps]),
                                 cc(problem.inertia_dot[steps]), cc(problem.sigma_l[steps]),
                                 cc(problem.sigma_dot[steps]), g, r0, J0)
        # d/d delta (analytic; module docstring of the class)
        t, w, dw, a = q[:, 0:3], q[:, 3:6], q[:, 9:12], q[:, 12:15]
        ag = a.copy()
        ag[:, 2] += g
        Sw = _skew(w)
        cl = problem.com[steps]

        def G(u, base, quad):
            """d((Delta X) u)/d delta for Delta X = -M([b]x[d]x + [d]x[b]x) - quad [d]x^2, u local."""
            out = M * (_skew(base) @ _skew(u) + _skew(np.cross(base, u)))
            if quad:
                out = out + (M / self.mu) * (_skew(np.cross(d, u)) + _skew(d) @ _skew(u))
            return out

        Rt = R.transpose(0, 2, 1)
        uw = np.einsum("nij,nj->ni", Rt, w)
        udw = np.einsum("nij,nj->ni", Rt, dw)
        dF = M * (_skew(dw) + Sw @ Sw) @ R
        dT = (Sw @ R @ G(uw, cl, True) + R @ G(uw, dc, False) + R @ G(udw, cl, True)
              - M * Sw @ R @ _skew(dc) - M * R @ _skew(ddc) + _skew(t) @ dF - M * _skew(ag) @ R)
        dr_de = np.concatenate([dF, dT], axis=1) @ self._sel
        return r1 - r0, J1 - J0, dr_de


class MassScale(_Constant):
    r"""Scale ``1 + kappa`` of the robot's mass and inertia: every body's mass and rotational inertia
    times ``1 + kappa``, the CoMs where they were (the simulator's ``mass-scale``, which scales the
    bodies of its own copy of the URDF).  The inputs that carry the mass, ``m``, ``I_l``, ``dI_l``,
    ``sigma_l``, ``dsigma_l``, scale with it, ``c_l`` and its derivatives do not, and the required
    wrench (eq. 16, 23) is linear in those five jointly, so the term on the ``newton_euler`` family
    is exactly::

        dr = kappa w_req(s),   dr/ds = kappa dw_req/ds,   dr/dkappa = w_req(s)

    with ``w_req`` the nominal required wrench (:func:`flexforce.factors.physics.required_wrench`).

    Seen through the motion alone it is a stiffness and damping scale by ``1 / (1 + kappa)`` (the
    flexibility moves as ``K / m`` dictates): only a measurement of force tells them apart -- the
    F/T sensors (``model.use_ft``), or an external wrench of known size.  Reported as the scale.
    """
    acts_on = ("newton_euler",)
    """The residual families its values enter (see :meth:`Effect.report`)."""

    name = "mass-scale"
    dim = 1
    labels = ("scale [-]",)
    unit = "-"
    what = "mass"
    offset = 1.0
    null = 1.0
    plausible_range = (0.5, 2.0)
    """A robot half or twice as heavy as its model is a wrong model (a missing battery, the wrong
    URDF), not a mass-model error: weigh it."""
    excites = ("the contact forces measured (F/T sensors); without them it is a stiffness and damping scale",)
    hint = ("fuse the F/T sensors (--ft): the forces scale with the mass and not with the stiffness; from the "
            "motion alone a heavier robot and softer contacts are the same")

    def prior_sigma(self, problem: ProblemView):
        """0.2: a model's mass off by a fifth (cables, batteries, covers left out of the URDF)."""
        return np.array([0.2])

    def feasible(self, values) -> bool:
        """A positive mass."""
        return bool(float(np.asarray(values, dtype=float).ravel()[0]) + self.offset > 0.05)

    def residual_terms(self, family, problem: ProblemView, steps, R, q, W, e):
        if family != "newton_euler":
            return None
        from flexforce.factors import core

        steps = np.asarray(steps)
        n = len(steps)
        cc = np.ascontiguousarray
        r, J = np.empty((n, 6)), np.empty((n, 6, 18))
        core.newton_euler_all(cc(R, dtype=float), cc(q, dtype=float), np.zeros((n, 6)), float(problem.rec.mass),
                              cc(problem.com[steps]), cc(problem.com_vel[steps]), cc(problem.com_acc[steps]),
                              cc(problem.inertia[steps]), cc(problem.inertia_dot[steps]), cc(problem.sigma_l[steps]),
                              cc(problem.sigma_dot[steps]), float(problem.g), r, J)
        kappa = np.asarray(e, dtype=float)[:, 0]
        return kappa[:, None] * r, kappa[:, None, None] * J, r[:, :, None]


# ----------------------------------------------------------------------------------------------
# F/T family
# ----------------------------------------------------------------------------------------------

_WRENCH = tuple(f"F_{a}" for a in _AX) + tuple(f"T_{a}" for a in _AX)


class FtOffset(_Constant):
    r"""Constant offset (bias) of the six-axis force/torque sensors: sensor ``i`` reads its
    contact's true wrench plus a constant ``b_i = (F_off, T_off)`` (N, N m, in the sensor's own
    frame, as the reading is: force and torque about the contact point in the contact frame), the
    simulator's ``ft-offset``.

    The F/T residual (:func:`flexforce.factors.core.ft`) is the contact's wrench seen in the sensor
    frame *minus* the reading, so the offset is part of the predicted reading: the term on contact
    ``i``'s ``ft`` rows is ``+ b_i``, with ``dr/db_i = I`` and ``dr/ds = 0``.  The smoother adds it
    where the reading is fused (the contact active and the component finite); the other rows stay
    zero, like the reading's own.

    ``contacts``: the contacts with an F/T sensor, as a count ``n`` (the recording's first ``n``
    contacts; default 2, a biped's feet) or as indices ``(0, 2, ...)``; 6 unknowns each, in that
    order.  Applicable only where the F/T readings are fused (``ModelConfig.use_ft``):
    :meth:`applicable` says why not (the diagnosis skips the candidate with that line); a fit
    without F/T fusion warns and leaves the offsets at their prior.

    Prior sigma: 10 per-sample sensor sigmas per axis (``ModelConfig.ft_force_sigma``,
    ``ft_torque_sigma``), the IMU biases' rule: 20 N and 2 N m with the default 2 N, 0.2 N m --
    the drift of an uncalibrated foot sensor.  Implausible: a force offset beyond a quarter of
    the robot's weight (about 100 N on Romeo) or a torque offset beyond that force at a 0.1 m
    lever (a foot's half-length): no drift is that large; a sensor frame, a calibration matrix or
    a load the model lacks is wrong.

    When the data see it: a fused reading is the contact's wrench, which the smoother also gets
    from the contact law (the deflection) and from Newton-Euler (the sum over the contacts).  At a
    constant load a constant offset is a constant share of that load moved onto or off the
    sensor's contact, which a stiffness, a rest-placement or a CoM error also produce; a load that
    changes (weight shifts between the feet, sway, steps) separates them: the offset is the part
    of the reading that does not change with the load.
    """
    acts_on = ("ft",)
    """The residual families its values enter (see :meth:`Effect.report`)."""
    additive = True
    """Its term is its value on fixed rows (see :meth:`Effect.report`)."""

    name = "ft-offset"
    unit = "N, N m"
    what = "F/T offset"
    weight_fraction = 0.25
    """A force offset above this fraction of the robot's weight is implausible."""
    lever = 0.1
    """m: the torque bound is the force bound at this lever."""
    hint = ("shift the weight from foot to foot, sway or step: an offset is the part of a reading that does not "
            "change with the load, while a mass error scales every contact's force and a CoM offset moves load "
            "from one contact to another")

    def __init__(self, contacts: int | tuple[int, ...] | list[int] = 2, max_force: float | None = None,
                 max_torque: float | None = None):
        if isinstance(contacts, (int, np.integer)):
            if contacts < 1:
                raise ConfigError(f"ft-offset: contacts must be a positive count or a list of indices, got {contacts}")
            idx = tuple(range(int(contacts)))
        else:
            try:
                idx = tuple(int(i) for i in contacts)
            except (TypeError, ValueError):
                raise ConfigError(f"ft-offset: contacts must be a count or a list of contact indices, "
                                  f"got {contacts!r}") from None
            if not idx or min(idx) < 0 or len(set(idx)) != len(idx):
                raise ConfigError(f"ft-offset: contacts must be distinct non-negative indices, got {list(idx)}")
        for key, val in (("max_force", max_force), ("max_torque", max_torque)):
            if val is not None and not val > 0:
                raise ConfigError(f"ft-offset: {key} must be positive, got {val}")
        self.contacts = idx
        self.max_force = None if max_force is None else float(max_force)
        self.max_torque = None if max_torque is None else float(max_torque)
        self.dim = 6 * len(idx)
        self.labels = tuple(f"c{i} {c} [{'N' if c[0] == 'F' else 'N m'}]" for i in idx for c in _WRENCH)
        per = ("changes of the fore-aft force on that contact (fore-aft sway, pushes)",
               "changes of the sideways force on that contact (sideways sway, pushes)",
               "changes of the vertical load on that contact (weight shifts, steps)",
               "changes of the roll moment on that contact (its CoP moving sideways: weight shifts)",
               "changes of the pitch moment on that contact (its CoP moving fore-aft)",
               "changes of the yaw moment on that contact (twisting)")
        self.excites = per * len(idx)
        self._names: tuple[str, ...] | None = None
        self._warned = False

    # -- applicability -----------------------------------------------------------------------
    def _unfit(self, problem: ProblemView) -> str | None:
        """Why the effect has nothing to act on in ``problem`` (None: it has)."""
        if not getattr(problem, "use_ft", False):
            return "the F/T readings are not fused (use_ft off); nothing to test"
        nc = int(problem.nc)
        if max(self.contacts) >= nc:
            return (f"offsets are set for contacts {list(self.contacts)} but the recording has {nc} "
                    f"contact{'s' if nc != 1 else ''}; give contacts= the indices of those with an F/T sensor")
        return None

    def applicable(self, problem: ProblemView) -> str | None:
        """None when the F/T readings of the offsets' contacts are fused, else the reason."""
        why = self._unfit(problem)
        if why is not None:
            return why
        y = getattr(problem, "y_ft", None)
        if y is not None:
            act = np.asarray(problem.active, dtype=bool)
            read = np.isfinite(np.asarray(y, dtype=float))
            names = self._contact_names(problem)
            dead = [names[j] for j, i in enumerate(self.contacts) if not np.any(act[:, i, None] & read[:, i])]
            if dead:
                return (f"the F/T sensor of {', '.join(dead)} reads nothing while in contact; give contacts= the "
                        f"indices of the contacts whose sensors read")
        return None

    def _contact_names(self, problem: ProblemView | None) -> tuple[str, ...]:
        names = getattr(getattr(problem, "rec", None), "contact_names", None) if problem is not None else None
        if names is not None and len(names) > max(self.contacts):
            self._names = tuple(str(names[i]) for i in self.contacts)
            self.labels = tuple(f"{c} {w} [{'N' if w[0] == 'F' else 'N m'}]" for c in self._names for w in _WRENCH)
        return self._names if self._names is not None else tuple(f"c{i}" for i in self.contacts)

    # -- the model ---------------------------------------------------------------------------
    def prior_sigma(self, problem: ProblemView):
        s = np.asarray(getattr(problem.sigmas, "ft", (2.0, 2.0, 2.0, 0.2, 0.2, 0.2)), dtype=float)
        return np.tile(10.0 * s, len(self.contacts))

    def prior(self, problem: ProblemView):
        """Zero mean, :meth:`prior_sigma`.  Offsets set for contacts the problem lacks are a
        configuration error; without F/T fusion the offsets have nothing to act on and stay at
        their prior (a warning, once: the diagnosis skips such a candidate, and the catalogue's
        generic uses -- screening, identifiability, the factor graph -- see an inert effect)."""
        if not getattr(problem, "use_ft", False):
            if not self._warned:
                import warnings

                self._warned = True
                warnings.warn("ft-offset: the F/T readings are not fused (use_ft off): the offsets have nothing to act "
                              "on and stay at their prior; fuse the F/T readings (use_ft, --ft) to estimate them",
                              RuntimeWarning, stacklevel=2)
        else:
            why = self._unfit(problem)
            if why is not None:
                raise ConfigError(f"ft-offset: {why}")
        self._contact_names(problem)
        return super().prior(problem)

    def residual_terms(self, family, problem: ProblemView, steps, R, q, W, e):
        if family != "ft":
            return None
        n, nc = len(steps), int(problem.nc)
        if max(self.contacts) >= nc:
            raise ConfigError(f"ft-offset: offsets are set for contacts {list(self.contacts)} but the problem has "
                              f"{nc} contacts")
        e = np.asarray(e, dtype=float)
        dr = np.zeros((n, nc, 6))
        dr_de = np.zeros((n, nc, 6, self.dim))
        for j, i in enumerate(self.contacts):
            dr[:, i] = e[:, 6 * j:6 * j + 6]
            dr_de[:, i, :, 6 * j:6 * j + 6] = np.eye(6)
        return dr, np.zeros((n, nc, 6, 18)), dr_de

    # -- the report --------------------------------------------------------------------------
    def component_names(self) -> tuple[str, ...]:
        names = self._names if self._names is not None else tuple(f"c{i}" for i in self.contacts)
        return tuple(f"{c} {w}" for c in names for w in _WRENCH)

    def bounds(self, problem: ProblemView | None) -> tuple[float | None, float | None]:
        """``(force N, torque N m)``: the largest plausible offsets per axis (class documentation)."""
        force = self.max_force
        if force is None and problem is not None:
            force = self.weight_fraction * float(problem.rec.mass) * float(problem.g)
        torque = self.max_torque
        if torque is None and force is not None:
            torque = force * self.lever
        return force, torque

    def plausible(self, report: dict, problem: ProblemView | None = None) -> str | None:
        """An offset beyond :meth:`bounds` on any axis is implausible."""
        if problem is not None:
            self._contact_names(problem)
        force, torque = self.bounds(problem)
        v = np.atleast_1d(np.asarray(report.get("value", ()), dtype=float))
        names = self.component_names()
        out = []
        for k in range(min(len(v), self.dim)):
            limit, unit = (force, "N") if k % 6 < 3 else (torque, "N m")
            if limit is not None and abs(v[k]) > limit:
                out.append(f"{self.what} {names[k]} = {_fmt(v[k])} {unit} is beyond {_fmt(limit)} {unit} (a quarter of "
                           f"the robot's weight{'' if unit == 'N' else f' at {self.lever:g} m'}): no sensor drifts "
                           f"that far; check the sensor's frame and calibration")
        return "; ".join(out) or None

    def report(self, values, cov, t=None):
        out = super().report(values, cov, t)
        v = np.asarray(out["value"], dtype=float).reshape(-1, 6)
        out["contacts"] = list(self._names if self._names is not None else (f"c{i}" for i in self.contacts))
        out["force_N"] = v[:, :3].tolist()
        out["torque_Nm"] = v[:, 3:].tolist()
        return out


# ----------------------------------------------------------------------------------------------
# Registry
# ----------------------------------------------------------------------------------------------

EFFECTS: dict[str, type] = {
    "external-wrench": ExternalWrench,
    "gyro-bias": GyroBias,
    "accel-bias": AccelBias,
    "stiffness": Stiffness,
    "anisotropic-stiffness": AnisotropicStiffness,
    "nonlinear-stiffness": NonlinearStiffness,
    "com-offset": ComOffset,
    "imu-mounting": ImuMounting,
    "time-offset": TimeOffset,
    "mass-scale": MassScale,
    "ft-offset": FtOffset,
}
"""Effect name -> class (the names are the simulator's hidden-effect types); ``foothold``
(:class:`flexforce.factors.footholds.Footholds`) is added below."""


def make_effect(name: str, **params):
    """An effect of the catalogue by name, e.g. ``make_effect("external-wrench", tau=0.05)``.

    Parameters: ``external-wrench``: ``tau`` (s); ``gyro-bias``/``accel-bias``: ``rw_density``;
    ``com-offset``: ``mass_fraction``, ``axes``; ``ft-offset``: ``contacts`` (a count or indices),
    ``max_force``, ``max_torque``; the others take none.
    """
    try:
        cls = EFFECTS[name]
    except KeyError:
        raise ConfigError(f"unknown effect '{name}'; known: {', '.join(EFFECTS)}") from None
    try:
        return cls(**params)
    except TypeError as err:
        raise ConfigError(f"effect '{name}': bad parameters {sorted(params)}: {err}") from None


from flexforce.factors.footholds import Footholds  # noqa: E402  (it reads this module's protocols)

EFFECTS["foothold"] = Footholds
