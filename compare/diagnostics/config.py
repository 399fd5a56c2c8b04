"""The diagnosis's tuning: one frozen :class:`DiagnoseConfig` (docs/diagnostics.md gives the
measurements behind the defaults)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from flexforce.errors import ConfigError

AUTO = "auto"
"""``add=["auto"]``: add the effects the greedy selection found significant."""


@dataclass(frozen=True)
class DiagnoseConfig:
    """How :func:`~flexforce.compare.diagnostics.diagnose` screens, refits, selects and checks.

    Raises:
        ConfigError: ``screen_level`` not in (0, 1) nor None; ``refit_best`` not an integer >= 1
            nor None.
    """

    alpha: float = 0.01
    """Family-wise level of each selection round (probability): its ``m`` candidates (those not
    selected yet) are each tested at ``alpha / m`` (Holm); also the level of the windowed residual
    tests and of the inconsistent axes a snapshot lists."""
    screen_level: float | None = 0.01
    """Level (probability) of the score test at the nominal fit and at each round's base: only the
    candidates whose score p-value is below it are refitted; None refits every candidate."""
    screen_window: float = 0.25
    """Window of a per-step effect's score test (the effect taken constant within it), s."""
    refit_best: int | None = 3
    """Per round, refit at most this many of the candidates that pass the screening, the strongest
    first, plus every candidate the identifiability table cannot tell from one of them; the others
    wait for the next round.  None: every one that passes."""
    swap_alternatives: int = 2
    """Constant candidates (the strongest score tests without it) tried in place of a per-step
    effect the greedy selection took before its last round (the second look)."""
    evidence_tol: float = 0.05
    """The fits end their outer steps of the marginal likelihood once a full step gains less than
    this, or the step's models promise less, nats (:func:`flexforce.smoother.batch.optimize`'s
    ``evidence_tol``); well under :attr:`tie`."""
    watch_patience: int = 2
    """Consecutive outer steps of an implausible estimate moving away from its prior mean that end a
    refit (one more such step in any direction ends it too): :class:`LeavingPlausible`."""
    check_worse: float = 0.05
    """Fraction: an error against the truth or the reference sensors that rises by more than this
    when an effect joins the selection makes the check disagree with it (:attr:`Candidate.check`)."""
    constancy_z: float = 5.0
    """Standard deviations (of the difference of the halves' estimates, from their Laplace sigmas):
    a constant effect whose halves differ beyond this and beyond :attr:`constancy_rel` on one
    component is not constant over the recording (:func:`constancy`)."""
    constancy_rel: float = 0.5
    """Fraction of the larger of the halves' estimates (its departure from the effect's ``null``):
    the size part of the constancy check."""
    constancy_min_s: float = 1.0
    """Shortest half of the constancy check, s; a shorter recording is not checked."""
    tie: float = 6.0
    """Score difference (twice the log of a Bayes factor, 6 = a factor of 20, "strong evidence" on
    Kass and Raftery's scale) below which two significant candidates of a round are rivals the data
    do not tell apart (:attr:`Candidate.rivals`)."""

    rank: bool = True
    """Score the candidates (greedy forward selection); False only refits with ``add``."""
    max_effects: int = 3
    """At most this many selection rounds add an effect."""
    window: float = 0.5
    """Length of the residual windows, s."""
    skip: float = 0.5
    """Seconds left out at the start of the error statistics (filter convergence)."""
    ekf: bool = True
    """Also run the EKF on the nominal model (innovations, NIS)."""
    calibrated: bool = True
    """Residuals standardised by their own variance, their tests accounting for their correlation in
    time (:func:`calibrated_view`); False: the whitened smoothed residuals as innovations."""
    identify: bool = True
    """Form the identifiability table of the candidates at the nominal fit, before any refit."""
    jobs: int | str = 1
    """Worker processes (forked) for the score tests, a round's refits and the before/after views;
    the same results as 1.  ``"auto"``: one per usable core the memory holds, decided once the
    nominal model is fitted (:func:`flexforce.compare.runner.resolve_jobs`)."""
    check_constancy: bool = True
    """Before a round takes a constant effect, fit it on each half of the recording
    (:func:`constancy`); halves that disagree make it implausible."""
    noise_calibration: float | None = 3.0
    """Sigmas: when the nominal fit's whitened IMU residuals have an RMS above this (per sensor,
    gyrometer and accelerometer, from :attr:`skip`), the configured noise is far below what the
    model leaves unexplained -- a real walk's vibration and unmodelled compliance, 8-25 sigma on
    the iCub walk, where a correct noise model gives about 1 -- and every candidate would pass at
    p = 0.  That sensor's sigma is then multiplied by its RMS (the accelerometer's carries the
    Newton-Euler, contact and integration sigmas derived from it) and every fit of the diagnosis,
    the nominal one included, uses the calibrated noise; the diagnosis says so
    (:func:`calibrate_noise`).  None: the configured noise as given."""
    dominance: float | None = 2.0
    """A round whose highest score belongs to a candidate fitted to physically implausible values
    (its effect's ``plausible`` check, not its check against the references) takes nothing when
    that score is more than ``dominance`` times the best plausible candidate's (and more than
    :attr:`tie` above it): the data then point to an effect the physics refuses -- a model error
    none of the candidates describes, or a plausibility rule wrong for this robot -- and the next
    plausible one would only stand in for it.  The candidate's row says so
    (:attr:`Candidate.dominant`), and so does the verdict.  None: the best plausible is taken."""
    check_veto: bool = True
    """Before a round takes an effect, hold its fit against what the fits did not use (the truth of
    a simulated recording, the reference sensors of a real one: :attr:`Candidate.check`); an effect
    whose errors rise more than they fall (each change beyond :attr:`check_worse` and its
    :data:`CHECK_FLOORS`, weighed by ``ln(after / before)``: :func:`.selection._vetoed`) over the
    round's base or over the nominal model is turned down, and the round goes on to the next; a
    later round tries it again.  ``add=["auto"]`` adds the selection only as far as no error rises
    over the nominal model (:func:`.selection.auto_added`).  Without references nothing is
    vetoed."""

    def __post_init__(self) -> None:
        level = self.screen_level
        if level is not None and not 0.0 < level < 1.0:
            raise ConfigError(f"screen_level = {level!r}; expected a probability in (0, 1) or None (no screening)")
        cal = self.noise_calibration
        if cal is not None and (isinstance(cal, bool) or not isinstance(cal, (int, float)) or not cal > 1.0
                                or not math.isfinite(cal)):
            raise ConfigError(f"noise_calibration = {cal!r}; expected a number of sigmas above 1, or None (the "
                              "configured noise as given)")
        dom = self.dominance
        if dom is not None and (isinstance(dom, bool) or not isinstance(dom, (int, float)) or not dom >= 1.0
                                or not math.isfinite(dom)):
            raise ConfigError(f"dominance = {dom!r}; expected a ratio of scores of at least 1, or None (the best "
                              "plausible candidate is taken)")
        best = self.refit_best
        if best is not None and (isinstance(best, bool) or not isinstance(best, int) or best < 1):
            raise ConfigError(f"refit_best = {best!r}; expected an integer >= 1 (candidates refitted per round) "
                              "or None (every candidate that passes the screening)")


CHECK_FLOORS = {"force_N": 0.5, "moment_Nm": 0.5, "cop_m": 1e-3, "rotation_rad": 1e-3, "translation_m": 1e-3,
                "hand_m": 1e-3, "vertical_force_N": 0.5, "contact_force_N": 0.5, "contact_moment_Nm": 0.5,
                "contact_cop_m": 1e-3}
"""Smallest rise of each error (SI units: N, N m, m, rad) that lets the check veto an effect
(:attr:`DiagnoseConfig.check_veto`): half a newton or newton-metre, a millimetre, a milliradian --
below what a balance controller or a state estimate acts on.  A rise must exceed both this and
:attr:`DiagnoseConfig.check_worse`."""

DEFAULT = DiagnoseConfig()
"""The defaults (what the module-level names of :mod:`.diagnose` hold)."""
