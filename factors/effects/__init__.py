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

from flexforce.errors import ConfigError
from flexforce.factors.effects.base import (
    CONSTANT_RW,
    Effect,
    EffectReport,
    EffectTraits,
    ProblemView,
    RecordingView,
    SigmasView,
    traits,
)
from flexforce.factors.effects.base import (
    _fmt as _fmt,  # the diagnosis formats the halves of a constancy check as the reports do
)
from flexforce.factors.effects.contact import AnisotropicStiffness, NonlinearStiffness, Stiffness
from flexforce.factors.effects.ft import FtOffset
from flexforce.factors.effects.imu import AccelBias, GyroBias, ImuMounting, TimeOffset
from flexforce.factors.effects.newton_euler import ComOffset, ExternalWrench, MassScale

__all__ = ["CONSTANT_RW", "EFFECTS", "AccelBias", "AnisotropicStiffness", "ComOffset", "Effect", "EffectReport",
           "EffectTraits", "ExternalWrench", "FtOffset", "GyroBias", "ImuMounting", "MassScale",
           "NonlinearStiffness", "ProblemView", "RecordingView", "SigmasView", "Stiffness", "TimeOffset",
           "make_effect", "traits"]


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
