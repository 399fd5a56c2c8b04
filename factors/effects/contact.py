"""Contact family: scales of the nominal stiffness and damping, per-axis (anisotropic) scales, cubic stiffening.

The contract and the priors' rule: :mod:`flexforce.factors.effects` and :mod:`.base`.
"""

from __future__ import annotations

import numpy as np

from flexforce.factors.effects.base import (
    _AX,
    ProblemView,
    _Constant,
    _fmt,
    _recorded_deflections,
    _static_compression,
    contact_physics,
)

MAX_DAMPING_RATIO = 1.0
"""The largest damping ratio of the flexibility's modes that a contact scale may give
(:func:`~flexforce.factors.effects.base.contact_physics`): a passive contact (a rubber bush, a
sole, foam) is underdamped, its material's loss factor below 1 (a damping ratio below 0.5);
critically damped or beyond, the contact would not ring at all after a touch-down."""

MAX_FALL_GROWTH = 3.0
"""The largest natural log of a tilt's growth (:attr:`ContactPhysics.fall_growth`) that a contact
scale may imply over a stance the recording held: e^3, twenty times.  Springs a little below the
gravity toppling stiffness hold a robot through a short stance (the tilt diverges over a time
``1 / lambda`` that may be longer than a step), and a balance controller may hold it longer; a
twenty-fold growth over a stance it held without falling is not the robot's."""

PHYSICS_EVERY = 5
"""The plausibility checks read every this many samples of the recording (the stances change
slowly against the sampling rate)."""


def _springs_verdict(problem: ProblemView, what: str, fs, fd, ts, td) -> str | None:
    """The springs scaled so (contact-frame axes, :func:`contact_physics`) against the recorded
    stances: None when the robot stands on them (a tilt grows at most :data:`MAX_FALL_GROWTH`
    over a stance) and their damping is underdamped, else the reason."""
    phys = contact_physics(problem, fs=fs, fd=fd, ts=ts, td=td, every=PHYSICS_EVERY)
    out = []
    if phys.fall_growth > MAX_FALL_GROWTH:
        out.append(f"{what} leaves the springs a tilt stiffness of {_fmt(phys.tilt_margin)} times the gravity "
                   f"toppling stiffness m g h about {phys.axis} at t = {phys.t:.2f} s: a tilt would grow "
                   f"{_fmt(float(np.exp(phys.fall_growth)))} times from {phys.fall_start:.2f} to "
                   f"{phys.fall_end:.2f} s, a stance the robot held: it would fall over its springs")
    if phys.damping_ratio > MAX_DAMPING_RATIO:
        out.append(f"{what} gives the flexibility a damping ratio of {_fmt(phys.damping_ratio)}, beyond critical "
                   f"({_fmt(MAX_DAMPING_RATIO)}): a passive contact is underdamped")
    return "; ".join(out) or None

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
    excites = ("load changes on the contacts (sway, shifting weight, pushes): the springs' deflection",
               "fast load changes (quick sway, impacts): the springs' deflection rate")
    hint = "vary the load on the contacts: sway, shift the weight from foot to foot, push"

    def prior_sigma(self, problem: ProblemView):
        return np.array([0.5, 0.5])

    def plausible(self, report: dict, problem: ProblemView | None = None) -> str | None:
        """Physics, at the recording's own stances (:func:`_springs_verdict`): the scaled springs
        must hold the robot up wherever it stood (where they fall short of ``m g h``, a tilt grows
        at most :data:`MAX_FALL_GROWTH` over the stance) and the scaled damping leave the
        flexibility underdamped (:data:`MAX_DAMPING_RATIO`).  No upper bound on
        the stiffness: a stiffer contact is a more rigid robot, which physics allows.  A
        ``plausible_range`` set on the effect (none by default) bounds the scales as well."""
        if problem is None:
            return None
        v = np.atleast_1d(np.asarray(report.get("value", ()), dtype=float))
        if len(v) < 2:
            return None
        s, d = float(v[0]), float(v[1])
        physics = _springs_verdict(problem, f"stiffness scale {_fmt(s)} with damping scale {_fmt(d)}",
                                   (s,) * 3, (d,) * 3, (s,) * 3, (d,) * 3)
        return "; ".join(r for r in (super().plausible(report, problem), physics) if r) or None

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
    excites = ("shear along the contact's x: a fore-aft force", "shear along the contact's y: a sideways force",
               "vertical load changes: no change of the vertical force", "a torque about x (roll)",
               "a torque about y (pitch)", "a torque about z (yaw)")
    hint = ("load each axis on its own: sway fore-aft and sideways, shift the weight, twist about the vertical; "
            "a stiffer pitch spring and a CoM offset tilt a robot at rest alike, a varying moment does not")

    def prior_sigma(self, problem: ProblemView):
        return np.full(6, 0.5)

    def plausible(self, report: dict, problem: ProblemView | None = None) -> str | None:
        """As :meth:`Stiffness.plausible`, per axis: the factors must hold the robot up wherever it
        stood; the damping is the configured one."""
        if problem is None:
            return None
        v = np.atleast_1d(np.asarray(report.get("value", ()), dtype=float))
        if len(v) < 6:
            return None
        label = "stiffness factors " + ", ".join(f"{n} {_fmt(x)}" for n, x in zip(self.component_names(), v))
        physics = _springs_verdict(problem, label, tuple(v[:3]), (1.0,) * 3, tuple(v[3:6]), (1.0,) * 3)
        return "; ".join(r for r in (super().plausible(report, problem), physics) if r) or None

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
        """Physics, at the deflections the recording's loads produce
        (:func:`~flexforce.factors.effects.base._recorded_deflections`): a softening term
        (``beta + d beta < 0``) must leave the spring a positive tangent stiffness
        ``1 + 3 (beta + d beta) s^2`` there, else the contact would give way under loads the robot
        bore (the nominal ``beta`` is left out: zero in the built-in robots).  A hardening term has
        no physical bound (a sole or a bush stiffens without limit as it bottoms out): its evidence
        and its check against the truth or the references judge it, as any other effect's."""
        if problem is None:
            return None
        v = np.atleast_1d(np.asarray(report.get("value", ()), dtype=float))
        ref = _recorded_deflections(problem)
        out = []
        for i, (what, unit) in enumerate((("translational", "m"), ("rotational", "rad"))):
            if i >= len(v) or v[i] >= 0.0:
                continue
            factor = 1.0 + 3.0 * v[i] * ref[i] ** 2  # tangent stiffness of k s (1 + beta s^2)
            if factor <= 0.0:
                out.append(f"{what} cubic softening {_fmt(v[i])} leaves the spring a tangent stiffness of "
                           f"{_fmt(factor)} times the linear one at {_fmt(ref[i])} {unit}, a deflection the "
                           "recording's loads produce: the contact would give way")
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
