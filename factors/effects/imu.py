"""IMU family: the gyrometer and accelerometer biases, the IMU's mounting rotation and its time offset.

The contract and the priors' rule: :mod:`flexforce.factors.effects` and :mod:`.base`.
"""

from __future__ import annotations

import numpy as np

from flexforce.errors import ConfigError
from flexforce.factors.effects.base import (
    _AX,
    ProblemView,
    _Constant,
    _fmt,
    _skew,
)

# ----------------------------------------------------------------------------------------------
# IMU family
# ----------------------------------------------------------------------------------------------


class _ImuBias(_Constant):
    acts_on = ("imu",)
    """The residual families its values enter (see :meth:`Effect.report`)."""
    additive = True
    """Its term is its value on fixed rows (see :meth:`Effect.report`)."""
    dim = 3
    sensor = 0
    """The reading it biases: 0 the gyro, 1 the accelerometer (its rows of the IMU residual,
    :attr:`rows`, and its labels, one an axis in :attr:`unit`, follow)."""
    rows = slice(0, 3)

    max_bias = 0.0
    """Largest plausible bias (the sensor's specification), in the effect's unit."""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        cls.rows = slice(3 * cls.sensor, 3 * cls.sensor + 3)
        cls.labels = tuple(f"{a} [{cls.unit}]" for a in _AX)

    def __init__(self, rw_density: float = 0.0, max_bias: float | None = None):
        self.rw_density = float(rw_density)
        if self.rw_density < 0:
            raise ConfigError(f"{self.name}: rw_density must be >= 0, got {rw_density}")
        self.constant = self.rw_density == 0.0
        self.max_bias_given = max_bias is not None
        """Whether ``max_bias`` was given (then :meth:`bind` keeps it)."""
        if max_bias is not None:
            if not max_bias > 0:
                raise ConfigError(f"{self.name}: max_bias must be positive ({self.unit}), got {max_bias}")
            self.max_bias = float(max_bias)

    def bind(self, rec, model):
        """This effect with the robot's data-sheet bound (``model.gyro_bias_max`` or
        ``accel_bias_max``, from the configuration's ``[imu_noise]``) unless ``max_bias`` was given."""
        spec = getattr(model, "accel_bias_max" if self.sensor == 1 else "gyro_bias_max", None)
        if self.max_bias_given or spec is None:
            return self
        return type(self)(rw_density=self.rw_density, max_bias=float(spec))

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
    unit = "rad/s"
    what = "gyro bias"
    max_bias = 0.05
    """0.05 rad/s (3 deg/s): an uncalibrated MEMS gyro's turn-on bias (``max_bias=`` for another part)."""
    excites = ("the gyro's x reading", "the gyro's y reading", "the gyro's z reading")
    hint = ("hold the robot still for a moment (a bias is the rate read at rest) or rotate about each axis: "
            "a true rotation tilts the robot and loads the contacts, a bias does neither")


class AccelBias(_ImuBias):
    """Accelerometer bias (IMU frame, m/s^2), added to the accelerometer's prediction.  Constant
    unless ``rw_density`` (m/s^2/sqrt(s)) is given."""

    name = "accel-bias"
    sensor = 1
    unit = "m/s^2"
    what = "accel bias"
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
        return (f"IMU mounting rotation of {1e3 * angle:.0f} mrad ({np.degrees(angle):.1f} deg) is beyond "
                f"{1e3 * self.max_angle:.0f} mrad: an IMU frame that far off is a wrong model (axes swapped), "
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
