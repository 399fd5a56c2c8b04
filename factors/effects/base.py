"""The effect contract: the :class:`Effect` protocol, its optional parts with their defaults
(:class:`EffectTraits`, read once by :func:`traits`), the :class:`ProblemView` effects are written
against, and the shared parts of the catalogue's constant effects (:class:`_Constant`).

The protocol lives with the physics, not with an estimator: an effect reads the problem through
:class:`ProblemView`, which :class:`flexforce.smoother.Problem` satisfies and any other estimator
can provide.  This package imports nothing of the project above ``factors/``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any, Protocol, TypedDict, runtime_checkable

import numpy as np

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
        about each step's CoM point, :func:`flexforce.factors.physics.about_com`: the
        Newton-Euler residual's)."""


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

    def report(self, values: np.ndarray, cov: np.ndarray | None) -> EffectReport:
        """JSON-serialisable summary of the estimated effect (values (N, dim), cov (N, dim, dim)).

        Optional: when the method takes a ``t`` keyword the smoothers pass the steps' times (N,)
        in seconds from the start (for time-varying effects: *when* the effect acts).  The other
        optional parts of the contract (``constant``, ``feasible``, ``step_prior_sigma``, ``factors``,
        ``acts_on``, ``additive``, and for the diagnostics ``plausible``, ``excites``, ``hint``,
        ``applicable``, ``by_default``, ``constant_on``, ``bind``, ``score_understates``) are listed with
        their defaults and meaning in :class:`EffectTraits`.
        """


class EffectReport(TypedDict, total=False):
    """What :meth:`Effect.report` returns (JSON-serialisable): the catalogue's constant effects fill
    the first seven keys; a time-varying effect adds its own (``external-wrench``: ``windows``, the
    spans where the force is significant, and the force series)."""

    value: list[float]
    """The estimate (the last step's; a constant effect has one value), in ``unit``."""
    std: list[float]
    """Its standard deviation, same shape and unit (NaN without a covariance)."""
    unit: str
    labels: list[str]
    """One label per unknown, with its unit."""
    significant: list[str]
    """The components beyond 3 sigma from the effect's null."""
    z: list[float]
    """``|value - null| / std`` per component."""
    summary: str
    """One readable sentence (``"gyro bias y = 0.011 ± 0.001 rad/s"``)."""


# ----------------------------------------------------------------------------------------------
# The optional parts of the contract
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EffectTraits:
    """The optional parts of the :class:`Effect` contract with their defaults.

    An effect declares any of these as attributes or methods of the same name (the catalogue's do;
    a plugin may declare none).  The estimators and the diagnosis read them through :func:`traits`
    only, so that what an effect may declare, and what holds when it does not, is written here once.
    """

    constant: bool | None = None
    """True: the value does not vary (the random walk only ties the steps together); the batch
    smoother makes it one global block estimated by the marginal likelihood and the dof count takes
    its prior alone.  None (undeclared): decided from the random walk (negligible over the
    recording: constant)."""
    additive: bool = False
    """True: the terms are the values on fixed rows (``dr_ds`` zero, ``dr_de`` the same at every value)
    and the effect has no factors of its own (the IMU biases, the F/T offsets)."""
    acts_on: tuple[str, ...] | None = None
    """The families whose ``residual_terms`` the effect returns (``newton_euler``, ``contact``, ``imu``,
    ``ft``); None: any of them."""
    score_understates: bool = False
    """True when the score test (the slope at zero) is no measure of the effect (a delay is not
    linear in its value): the diagnosis refits it in every round whatever its test."""
    excites: tuple[str, ...] = ()
    """Per unknown: the motion or load that makes the data see it."""
    hint: str = ""
    """What a recording should do to tell the effect from those it resembles."""
    feasible: Callable[[np.ndarray], bool] | None = None
    """``feasible(values (dim,)) -> bool``: False for a value out of the physical range (a negative
    stiffness); None: every value is feasible."""
    step_prior_sigma: Callable[[Any], np.ndarray] | None = None
    """``step_prior_sigma(problem) -> (dim,)``: a prior at every step around the prior mean (with the
    random walk, a mean-reverting process); None: no such prior."""
    factors: Callable[..., dict] | None = None
    """``factors(problem, steps, R, q, e) -> {name: (r (n, m), dr_ds (n, m, 18), dr_de (n, m, dim),
    weight (n,))}``: whitened factors of the effect's own on single steps; None: none."""
    constant_on: Callable[[Any], bool] | None = None
    """``constant_on(problem) -> bool``: a per-step effect that is constant on this recording (the
    footholds of a recording without a touch-down)."""
    bind: Callable[[Any, Any], Any] | None = None
    """``bind(rec, model) -> effect``: the effect made for one recording and model (the footholds
    take their priors from the model)."""
    by_default: Callable[[Any], str | None] | None = None
    """``by_default(rec) -> str | None``: the reason to leave the effect out of a diagnosis's default
    candidates on this recording, None to keep it."""
    plausible: Callable[..., str | None] | None = None
    """``plausible(report, problem=None) -> str | None``: why an estimate is physically implausible,
    None when it is plausible."""
    applicable: Callable[[Any], str | None] | None = None
    """``applicable(problem) -> str | None``: None when the effect has something to act on, else the
    reason in the user's terms (an F/T offset when the F/T readings are not fused)."""


_TRAIT_NAMES = tuple(f.name for f in fields(EffectTraits))


def traits(effect: object) -> EffectTraits:
    """The optional parts ``effect`` declares, the defaults of :class:`EffectTraits` for the rest."""
    found: dict[str, Any] = {}
    for name in _TRAIT_NAMES:
        value = getattr(effect, name, None)
        if value is not None:
            found[name] = tuple(value) if name in ("acts_on", "excites") else value
    return EffectTraits(**found)


# ----------------------------------------------------------------------------------------------
# A user's effect, its values checked
# ----------------------------------------------------------------------------------------------


class CheckedEffect:
    """A user's effect (a plugin file's) whose values are checked as the estimators read them.

    Everything is the wrapped effect's (its attributes, traits and ``report`` are read through);
    :meth:`prior`, :meth:`random_walk_sigma` and :meth:`residual_terms` return what it returns
    after checking that the arrays are finite and of the contract's shapes, so that an effect
    returning NaN fails with its name and file where it is fitted or screened (the diagnosis lists
    it with that reason) instead of dropping out of a ranking.  ``bind`` wraps the effect it makes.

    Raises (from the checked methods):
        ConfigError: naming the plugin file, the effect, the method and what was expected.
    """

    def __init__(self, effect: object, source: str):
        self.__dict__["_inner"] = effect
        self.__dict__["source"] = str(source)  # the plugin file the effect came from

    def __getattr__(self, name: str) -> Any:
        inner = self.__dict__.get("_inner")
        if inner is None or (name.startswith("__") and name.endswith("__")):
            raise AttributeError(name)
        value = getattr(inner, name)
        if name == "bind" and callable(value):
            source = self.__dict__["source"]
            return lambda *args, **kwargs: CheckedEffect(value(*args, **kwargs), source)
        return value

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self.__dict__["_inner"], name, value)

    def __repr__(self) -> str:
        return f"CheckedEffect({self.__dict__['_inner']!r}, source={self.__dict__['source']!r})"

    @property
    def wrapped(self) -> object:
        """The user's effect itself."""
        return self.__dict__["_inner"]

    def _fail(self, method: str, what: str) -> None:
        from flexforce.errors import ConfigError

        name = getattr(self.__dict__["_inner"], "name", type(self.__dict__["_inner"]).__name__)
        raise ConfigError(f"effect plugin {self.__dict__['source']}: effect '{name}' {method} {what}")

    def _finite(self, method: str, label: str, value: Any, shapes: tuple[tuple[int, ...], ...] = ()) -> np.ndarray:
        try:
            arr = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            self._fail(method, f"returned {label} {value!r}; expected an array of numbers")
        if shapes and arr.shape not in shapes:
            self._fail(method, f"returned {label} of shape {arr.shape}; expected {' or '.join(map(str, shapes))}")
        if not np.all(np.isfinite(arr)):
            bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
            self._fail(method, f"returned {label} with {bad} of {arr.size} value(s) NaN or inf; expected finite "
                               "numbers")
        return arr

    def prior(self, problem: ProblemView) -> tuple[np.ndarray, np.ndarray]:
        """The wrapped effect's prior, checked: finite ``(dim,)`` mean and positive sigma."""
        inner: Any = self.__dict__["_inner"]
        out = inner.prior(problem)
        try:
            mean, sigma = out
        except (TypeError, ValueError):
            self._fail("prior()", f"returned {out!r}; expected (mean, sigma), each of shape ({inner.dim},)")
        dim = (int(inner.dim),)
        self._finite("prior()", "mean", mean, (dim,))
        sig = self._finite("prior()", "sigma", sigma, (dim,))
        if np.any(sig <= 0):
            self._fail("prior()", f"returned sigma {sig.tolist()}; expected positive values")
        return mean, sigma

    def random_walk_sigma(self, problem: ProblemView) -> np.ndarray:
        """The wrapped effect's random-walk sigma, checked: finite, non-negative."""
        inner: Any = self.__dict__["_inner"]
        out = inner.random_walk_sigma(problem)
        sig = self._finite("random_walk_sigma()", "sigma", out)
        if np.any(sig < 0):
            self._fail("random_walk_sigma()", "returned a negative sigma; expected values >= 0")
        return out

    def residual_terms(self, family: str, problem: ProblemView, steps: np.ndarray, R: np.ndarray,
                       q: np.ndarray, W: np.ndarray, e: np.ndarray):
        """The wrapped effect's term in ``family``, checked: None or three finite arrays."""
        inner: Any = self.__dict__["_inner"]
        out = inner.residual_terms(family, problem, steps, R, q, W, e)
        if out is None:
            return None
        if not (isinstance(out, tuple | list) and len(out) == 3):
            self._fail(f"residual_terms('{family}')", f"returned {type(out).__name__}; expected None or "
                                                       "(dr, dr_ds, dr_de)")
        for label, value in zip(("dr", "dr_ds", "dr_de"), out):
            self._finite(f"residual_terms('{family}')", label, value)
        return out


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


def _recorded_deflections(problem: ProblemView) -> tuple[float, float]:
    """``(s, Omega)``: the largest translational (m) and rotational (rad) spring deflections the
    recording's own loads produce at the configured springs, from its inputs alone: at each sample
    the vertical load ``m (g + c''_z)`` and the moment of the weight about the active contacts'
    centroid, ``m g |c_xy - centroid_xy|``, shared equally by the active contacts (each contact's
    ``K_fs`` and ``K_ts`` along their mean diagonal); the largest over the recording.  Static: the
    springs' dynamic overshoot is not in it."""
    m, g = float(problem.rec.mass), problem.g
    active = np.asarray(problem.active, dtype=bool)
    k_f = np.array([float(np.trace(K)) / 3.0 for K in problem.K_fs])
    k_t = np.array([float(np.trace(K)) / 3.0 for K in problem.K_ts])
    n_on = active.sum(axis=1)
    on = n_on > 0
    if not on.any():
        return 0.0, 0.0
    p = np.asarray(problem.contact_p, dtype=float)[:, :, :2]
    centroid = (p * active[..., None]).sum(axis=1) / np.maximum(n_on, 1)[:, None]
    com = np.asarray(problem.com, dtype=float)
    load = m * (g + np.asarray(problem.com_acc, dtype=float)[:, 2])
    moment = m * g * np.linalg.norm(com[:, :2] - centroid, axis=1)
    share = np.where(on, 1.0 / np.maximum(n_on, 1), 0.0)
    # the softest active contact carries its share: the largest deflection
    soft_f = np.where(active, 1.0 / np.maximum(k_f, 1e-9)[None, :], 0.0).max(axis=1)
    soft_t = np.where(active, 1.0 / np.maximum(k_t, 1e-9)[None, :], 0.0).max(axis=1) if (k_t > 0).all() else None
    s = float(np.max(np.abs(load) * share * soft_f))
    omega = float(np.max(moment * share * soft_t)) if soft_t is not None else 0.0
    return s, omega


@dataclass(frozen=True)
class ContactPhysics:
    """What the recorded stances ask of the contact springs (:func:`contact_physics`).

    ``tilt_margin``: the smallest ratio, over the recording's samples with a contact in force and
    the two horizontal axes, of the springs' tilt stiffness (``sum k_ts`` about the axis plus
    ``k_fs d^2`` for each contact at a distance ``d`` from the active contacts' centroid across it)
    to the gravity toppling stiffness ``m g h`` (``h`` the CoM's height above that centroid): at 1
    or below the springs alone do not hold the robot up there.  ``t`` and ``axis`` locate it
    (seconds from the first sample; ``"x (roll)"`` or ``"y (pitch)"``).  ``fall_growth``: where
    the margin is below 1 the tilt diverges at the rate ``lambda = -c / (2 I) + sqrt((c / (2 I))^2
    + (m g h - k_tilt) / I)`` (``c`` the tilt damping, ``I`` the robot's inertia about the axis
    through the centroid); the largest ``sum lambda dt`` over a run of such samples, the natural
    log of how many times a tilt would grow while the robot stood so (0 when the margin stays
    above 1), from ``fall_start`` to ``fall_end`` (s).  ``damping_ratio``: the largest damping
    ratio of the flexibility's vertical mode (``c / (2 sqrt(k m))``, summed over the contacts in
    force) and of its rocking modes (tilt damping over ``2 sqrt((k_tilt - m g h) I)``) where they
    are stable."""

    tilt_margin: float
    t: float
    axis: str
    damping_ratio: float
    fall_growth: float = 0.0
    fall_start: float = 0.0
    fall_end: float = 0.0


def contact_physics(problem: ProblemView, fs=(1.0, 1.0, 1.0), fd=(1.0, 1.0, 1.0), ts=(1.0, 1.0, 1.0),
                    td=(1.0, 1.0, 1.0), every: int = 1) -> ContactPhysics:
    """:class:`ContactPhysics` of the problem's springs with ``K_fs``, ``K_fd``, ``K_ts``,
    ``K_td`` scaled per contact-frame axis by ``fs``, ``fd``, ``ts``, ``td`` (``K <- diag(f) K``,
    as the contact effects scale them), from every ``every``-th sample."""
    m, g = float(problem.rec.mass), problem.g
    active = np.asarray(problem.active, dtype=bool)[::every]
    P = np.asarray(problem.contact_p, dtype=float)[::every]
    Rc = np.asarray(problem.contact_R, dtype=float)[::every]
    com = np.asarray(problem.com, dtype=float)[::every]
    inertia = np.asarray(problem.inertia, dtype=float)[::every]
    scaled = [np.diag(np.asarray(f, dtype=float)) @ np.asarray(K, dtype=float)
              for f, K in ((fs, problem.K_fs), (fd, problem.K_fd), (ts, problem.K_ts), (td, problem.K_td))]
    iso = np.asarray(problem.iso, dtype=bool)
    Rc = np.where(iso[None, :, None, None], np.eye(3), Rc)  # an isotropic contact's springs do not turn
    # world-axis stiffness u^T (R K R^T) u for u = x, y, z: (N, C, 3)
    world = [np.einsum("ncia,cab,ncib->nci", Rc, K, Rc) for K in scaled]
    k_fz, c_fz, k_t, c_t = world[0][..., 2], world[1][..., 2], world[2], world[3]
    on = active.any(axis=1)
    n_on = np.maximum(active.sum(axis=1), 1)
    centroid = (P * active[..., None]).sum(axis=1) / n_on[:, None]
    h = com[:, 2] - centroid[:, 2]
    mgh = m * g * h
    cc = com - centroid
    # inertia about the centroid: I_o - m ([c]^2 terms about the origin) + m (about the centroid)
    def parallel(v):
        return (np.einsum("ni,ni->n", v, v)[:, None, None] * np.eye(3) - np.einsum("ni,nj->nij", v, v))
    I_cent = inertia - m * parallel(com) + m * parallel(cc)
    worst_margin, worst_t, worst_axis = np.inf, 0.0, "x (roll)"
    growth, g_start, g_end = 0.0, 0.0, 0.0
    dt = problem.dt * every
    k_vert = np.maximum((k_fz * active).sum(axis=1), 1e-12)
    zeta_v = np.where(on, (c_fz * active).sum(axis=1) / (2.0 * np.sqrt(k_vert * m)), 0.0)
    zeta = float(np.max(zeta_v)) if on.any() else 0.0
    for axis, name, across in ((0, "x (roll)", 1), (1, "y (pitch)", 0)):
        d2 = (P[..., across] - centroid[:, None, across]) ** 2
        k_tilt = ((k_t[..., axis] + k_fz * d2) * active).sum(axis=1)
        c_tilt = ((c_t[..., axis] + c_fz * d2) * active).sum(axis=1)
        inertia_u = np.maximum(I_cent[:, axis, axis], 1e-12)
        up = on & (mgh > 0)
        if up.any():
            margin = np.where(up, k_tilt / np.where(up, mgh, 1.0), np.inf)
            k = int(np.argmin(margin))
            if margin[k] < worst_margin:
                worst_margin, worst_t, worst_axis = float(margin[k]), k * dt, name
            half = c_tilt / (2.0 * inertia_u)
            rate = np.where(up & (margin < 1.0),
                            -half + np.sqrt(half**2 + np.maximum(mgh - k_tilt, 0.0) / inertia_u), 0.0)
            run, start = 0.0, 0
            for j, r in enumerate(rate):  # the largest growth over a run of unstable samples
                if r <= 0.0:
                    run = 0.0
                    continue
                if run == 0.0:
                    start = j
                run += r * dt
                if run > growth:
                    growth, g_start, g_end = run, start * dt, (j + 1) * dt
        net = k_tilt - np.maximum(mgh, 0.0)
        ok = on & (net > 0)
        if ok.any():
            zr = c_tilt[ok] / (2.0 * np.sqrt(net[ok] * inertia_u[ok]))
            zeta = max(zeta, float(np.max(zr)))
    return ContactPhysics(tilt_margin=worst_margin, t=worst_t, axis=worst_axis, damping_ratio=zeta,
                          fall_growth=float(growth), fall_start=float(g_start), fall_end=float(g_end))


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

    def report(self, values, cov, t=None) -> EffectReport:
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


