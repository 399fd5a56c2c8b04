"""F/T family: the offsets of the force/torque sensors.

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
)

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
