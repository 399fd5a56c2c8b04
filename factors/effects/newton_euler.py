"""Newton-Euler family: an external wrench, a CoM offset, a mass scale.

The contract and the priors' rule: :mod:`flexforce.factors.effects` and :mod:`.base`.
"""

from __future__ import annotations

import numpy as np

from flexforce.errors import ConfigError
from flexforce.factors.effects.base import (
    _AX,
    _CHI2_6_999,
    ProblemView,
    _Constant,
    _fmt,
    _skew,
)

# ----------------------------------------------------------------------------------------------
# Newton-Euler family
# ----------------------------------------------------------------------------------------------


def _origin_cov(problem) -> np.ndarray:
    """The unexplained wrench's covariance about the local origin at the first sample (the
    Newton-Euler residual's own is about each step's CoM)."""
    cov = getattr(problem.sigmas, "newton_euler_cov_origin", None)
    return problem.sigmas.newton_euler_cov if cov is None else cov


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
        self._L = np.linalg.cholesky(np.asarray(_origin_cov(problem), dtype=float))
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
        sF = float(np.sqrt(np.mean(np.diag(np.asarray(_origin_cov(problem), dtype=float))[:3])))
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
    """Within ``1 / mass_factor`` and ``mass_factor`` of the robot's configuration (:meth:`bind`;
    default 2: a robot half or twice as heavy as its model is a wrong model, a missing battery or
    the wrong URDF, not a mass-model error: weigh it)."""
    excites = ("the contact forces measured (F/T sensors); without them it is a stiffness and damping scale",)
    hint = ("fuse the F/T sensors (--ft): the forces scale with the mass and not with the stiffness; from the "
            "motion alone a heavier robot and softer contacts are the same")

    def prior_sigma(self, problem: ProblemView):
        """0.2: a model's mass off by a fifth (cables, batteries, covers left out of the URDF)."""
        return np.array([0.2])

    def bind(self, rec, model):
        """This effect with the plausible range of the robot's ``mass_factor`` (``model.mass_factor``)."""
        factor = getattr(model, "mass_factor", None)
        if factor is None:
            return self
        bound_ = type(self)()
        bound_.plausible_range = (1.0 / float(factor), float(factor))
        return bound_

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
