r"""The model as a gtsam factor graph: the factors of one step or of a whole recording, and the
export of a recording's problem to gtsam (:func:`to_gtsam`) with the way back (:func:`from_gtsam`).

Keys (:mod:`flexforce.factors.gtsam_factors`; :class:`GtsamKeys` names them for a given problem):

=============  ==================  ==========================================================
symbol         type                variable (units)
=============  ==================  ==========================================================
``x``, k       ``gtsam.Pose3``     flexibility ``(R, t)`` of step ``k``, local -> world (rad, m)
``v``, k       Vector6             ``(w, v)`` world-frame angular and linear velocity (rad/s, m/s)
``a``, k       Vector6             ``(dw, a)`` their derivatives (rad/s^2, m/s^2)
``w``, 64k+i   Vector6             wrench ``(F, T)`` of contact ``i`` about the world origin
                                   (N, N m); only while contact ``i`` is active
``e``, 64k+j   Vector (dim)        the ``j``-th enabled effect's unknowns (``ModelConfig.effects``
                                   order; units of its ``labels``)
=============  ==================  ==========================================================

Factors: per step the Newton-Euler, IMU, contact-law (per active contact) and F/T (when fused)
CustomFactors, each with the terms of the effects that act on its family; the integration factor
between successive steps; priors on the first step's state and on each effect's first value; each
effect's random walk (``BetweenFactorVector``), its optional prior at every step and its own
factors.  The noise models are the :class:`Problem`'s; the Newton-Euler factor carries the Huber
loss of the rule (``gtsam.noiseModel.Robust``).  The robust loss of the IMU and F/T sensors
(``NoiseRule.imu_robust``) has no counterpart here: on data without gross sensor faults (the
loss starts at 30 sigma) the two graphs have the same optimum.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from flexforce.errors import ConfigError
from flexforce.factors import gtsam_factors as gf
from flexforce.factors.effects.base import traits
from flexforce.smoother.linearize import Trajectory, walk_sigma
from flexforce.smoother.problem import NoiseRule, Problem, with_footholds

_EFFECT_FAMILIES = ("newton_euler", "contact", "imu")


class GraphBuilder:
    """Builds the gtsam factors of each step of a Problem (noise models made once)."""

    def __init__(self, prob):
        self.prob = prob
        if prob.nc > gf.MAX_CONTACTS or len(prob.effects) > gf.MAX_EFFECTS:
            raise ConfigError(f"the gtsam graph addresses at most {gf.MAX_CONTACTS} contacts and {gf.MAX_EFFECTS} "
                              f"effects per step; the problem has {prob.nc} contacts and {len(prob.effects)} effects")
        s = prob.sigmas
        self.noise_imu = gtsam.noiseModel.Diagonal.Sigmas(s.imu)
        self.noise_ne = gtsam.noiseModel.Gaussian.Covariance(s.newton_euler_cov)
        if s.robust_k is not None:
            self.noise_ne = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(s.robust_k),
                                                           self.noise_ne)
        self.noise_contact = gtsam.noiseModel.Gaussian.Covariance(s.contact_cov)
        self.noise_ft = gtsam.noiseModel.Diagonal.Sigmas(s.ft)
        self.noise_int = gtsam.noiseModel.Gaussian.Covariance(s.integration_cov)
        self._setup_effects()

    def _setup_effects(self) -> None:
        """Which family each effect acts on, its priors and walks, and where its own factors are."""
        p = self.prob
        self.effects = list(enumerate(p.effects))
        self.touch: dict[str, list] = {family: [] for family in _EFFECT_FAMILIES}
        self.effect_prior = []
        self.effect_level = []
        self.effect_walk = []
        self.effect_own: list[dict[str, tuple[int, np.ndarray]]] = []
        if not self.effects:
            return
        R0, q0 = p.prior_mean
        steps0 = np.array([0])
        W0 = np.zeros((1, p.nc, 6))
        for j, eff in self.effects:
            mean, sigma = eff.prior(p)
            mean, sigma = np.asarray(mean, dtype=float), np.asarray(sigma, dtype=float)
            self.effect_prior.append((mean, sigma))
            for family in _EFFECT_FAMILIES:
                if eff.residual_terms(family, p, steps0, R0[None], q0[None], W0, mean[None]) is not None:
                    self.touch[family].append((j, eff))
            if p.use_ft and eff.residual_terms("ft", p, steps0, R0[None], q0[None], W0, mean[None]) is not None:
                raise ConfigError(f"effect {eff.name!r} acts on the F/T readings, which the gtsam graph's F/T factors "
                                  "do not carry; expected the numpy backends (the default batch smoother, "
                                  "diagnose) for it")
            level = traits(eff).step_prior_sigma
            self.effect_level.append(None if level is None else np.asarray(level(p), dtype=float))
            self.effect_walk.append(walk_sigma(eff, p))
            own = traits(eff).factors
            found: dict[str, tuple[int, np.ndarray]] = {}
            if own is not None:
                # Where the own factors exist (weight 1) depends on the step, not on the state:
                # probed once at the prior state.
                n = p.n
                out = own(p, np.arange(n), np.repeat(R0[None], n, axis=0), np.repeat(q0[None], n, axis=0),
                          np.repeat(mean[None], n, axis=0))
                for name, (r, _, _, weight) in out.items():
                    found[name] = (int(np.asarray(r).shape[1]), np.flatnonzero(np.asarray(weight) != 0))
            self.effect_own.append(found)

    def contacts(self, k: int) -> list[int]:
        return [int(i) for i in np.flatnonzero(self.prob.active[k])]

    def _terms(self, family: str, k: int):
        pairs = self.touch[family]
        return gf.EffectTerms(self.prob, k, pairs, self.prob.nc) if pairs else None

    def step_factors(self, k: int, link: bool = True) -> list:
        """Newton-Euler, contact law per active contact, IMU, F/T (if used), integration from k-1
        (``link``), the priors at step 0, and the effects' factors of step ``k``."""
        p = self.prob
        contacts = self.contacts(k)
        out: list[gtsam.NonlinearFactor] = [
            gf.newton_euler_factor(self.noise_ne, k, contacts, float(p.rec.mass), p.com[k], p.com_vel[k],
                                   p.com_acc[k], p.inertia[k], p.inertia_dot[k], p.sigma_l[k], p.sigma_dot[k], p.g,
                                   effects=self._terms("newton_euler", k)),
            gf.imu_factor(self.noise_imu, k, p.y_imu[k], p.imu_R[k], p.imu_p[k], p.imu_v[k], p.imu_a[k],
                          p.imu_w[k], p.g, effects=self._terms("imu", k), use=p.imu_use[k]),
        ]
        for i in contacts:
            out.append(gf.contact_factor(self.noise_contact, k, i, p.contact_p[k, i], p.contact_R[k, i],
                                         p.model.contact_params[i], p.rest_p[k, i], p.rest_R[k, i],
                                         effects=self._terms("contact", k)))
            if p.use_ft:
                out.append(gf.ft_factor(self.noise_ft, k, i, p.contact_p[k, i], p.contact_R[k, i], p.y_ft[k, i]))
        if k > 0 and link:
            out.append(gf.integration_factor(self.noise_int, k - 1, p.dt))
        if k == 0:
            R0, q0 = p.prior_mean
            out.extend(gf.state_prior_factors(0, R0, q0, p.sigmas.prior))
        for j, eff in self.effects:
            mean, sigma = self.effect_prior[j]
            if k == 0:
                out.append(gf.effect_prior_factor(j, mean, sigma))
            if self.effect_level[j] is not None:
                out.append(gf.effect_level_factor(j, k, mean, self.effect_level[j]))
            if k > 0 and link:
                out.append(gf.effect_walk_factor(j, k - 1, self.effect_walk[j][k - 1]))
            for name, (rows, where) in self.effect_own[j].items():
                if np.any(where == k):
                    out.append(gf.effect_own_factor(p, eff, j, k, name, rows))
        return out

    def graph(self, k0: int = 0, k1: int | None = None) -> gtsam.NonlinearFactorGraph:
        """All factors of steps ``k0 .. k1-1`` (the links between steps inside the range only)."""
        k1 = self.prob.n if k1 is None else k1
        graph = gtsam.NonlinearFactorGraph()
        for k in range(k0, k1):
            for f in self.step_factors(k, link=k > k0):
                graph.add(f)
        return graph

    def values(self, traj, k0: int = 0, k1: int | None = None) -> gtsam.Values:
        """gtsam Values of a :class:`Trajectory` for steps ``k0 .. k1-1``."""
        k1 = self.prob.n if k1 is None else k1
        values = gtsam.Values()
        splits = np.cumsum(self.prob.effect_dims)[:-1]
        for k in range(k0, k1):
            effects = np.split(np.asarray(traj.e[k], dtype=float), splits) if self.effects else None
            gf.insert_state(values, k, traj.R[k], traj.q[k], traj.W[k], self.contacts(k), effects)
        return values

    def trajectory(self, values: gtsam.Values) -> Trajectory:
        """The :class:`Trajectory` held by ``values`` (every step; inactive contacts' wrenches zero)."""
        p = self.prob
        n = p.n
        traj = Trajectory(np.empty((n, 3, 3)), np.empty((n, 15)), np.zeros((n, p.nc, 6)),
                          np.zeros((n, p.effect_dim)))
        try:
            for k in range(n):
                pose = values.atPose3(gf.X(k))
                traj.R[k] = pose.rotation().matrix()
                traj.q[k, 0:3] = pose.translation()
                traj.q[k, 3:9] = values.atVector(gf.V(k))
                traj.q[k, 9:15] = values.atVector(gf.A(k))
                for i in self.contacts(k):
                    traj.W[k, i] = values.atVector(gf.W(k, i))
                off = 0
                for j, eff in self.effects:
                    traj.e[k, off:off + eff.dim] = values.atVector(gf.E(k, j))
                    off += eff.dim
        except RuntimeError as err:
            raise ConfigError(f"the gtsam Values lack a variable of step {k} of the {n}-step problem ({err}); "
                              "expected every key of to_gtsam's graph (GtsamKeys.describe() lists them)") from None
        return traj

    def step_keys(self, k: int) -> list[int]:
        """The keys of step ``k`` in the order of the per-step state: X, V, A, active W_i, effects."""
        return ([gf.X(k), gf.V(k), gf.A(k)] + [gf.W(k, i) for i in self.contacts(k)]
                + [gf.E(k, j) for j, _ in self.effects])


# ----------------------------------------------------------------------------------------------
# Export to gtsam and back
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GtsamKeys:
    """What each key of :func:`to_gtsam`'s graph is (module docstring for the symbols and units).

    ``pose(k)``, ``velocity(k)``, ``acceleration(k)``, ``wrench(k, contact)`` (index or name; only
    while the contact is active, :attr:`active`) and ``effect(k, name_or_index)`` give the keys of
    step ``k``; :meth:`describe` prints the table.  :attr:`problem` and :attr:`builder` are what
    :func:`from_gtsam` reads the values back with.
    """

    builder: GraphBuilder

    @property
    def problem(self) -> Problem:
        return self.builder.prob

    @property
    def steps(self) -> int:
        """Number of steps ``N`` (``k = 0 .. N-1``, time ``k dt`` from the first sample)."""
        return int(self.problem.n)

    @property
    def dt(self) -> float:
        return float(self.problem.dt)

    @property
    def contact_names(self) -> tuple[str, ...]:
        return tuple(self.problem.rec.contact_names)

    @property
    def active(self) -> np.ndarray:
        """(N, C) bool: which contacts have a wrench key at each step."""
        return self.problem.active

    @property
    def effect_names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.problem.effects)

    def _step(self, k: int) -> int:
        k = int(k)
        if not 0 <= k < self.steps:
            raise ConfigError(f"step {k} is outside the graph's steps 0 .. {self.steps - 1}")
        return k

    def pose(self, k: int) -> int:
        """``gtsam.Pose3`` flexibility (local -> world) of step ``k``."""
        return gf.X(self._step(k))

    def velocity(self, k: int) -> int:
        """Vector6 ``(w, v)``, world frame (rad/s, m/s)."""
        return gf.V(self._step(k))

    def acceleration(self, k: int) -> int:
        """Vector6 ``(dw, a)``, world frame (rad/s^2, m/s^2)."""
        return gf.A(self._step(k))

    def wrench(self, k: int, contact: int | str) -> int:
        """Vector6 ``(F, T)`` of a contact about the world origin (N, N m), while it is active."""
        k = self._step(k)
        i = self._index(contact, self.contact_names, "contact")
        if not self.active[k, i]:
            raise ConfigError(f"contact {self.contact_names[i]!r} is not active at step {k}: the graph has no "
                              "wrench variable for it there (GtsamKeys.active)")
        return gf.W(k, i)

    def effect(self, k: int, effect: int | str) -> int:
        """Vector of an enabled effect's unknowns at step ``k`` (units of its ``labels``)."""
        return gf.E(self._step(k), self._index(effect, self.effect_names, "effect"))

    @staticmethod
    def _index(which, names, what: str) -> int:
        if isinstance(which, str):
            if which not in names:
                raise ConfigError(f"unknown {what} {which!r}; the graph's {what}s are: {', '.join(names) or 'none'}")
            return names.index(which)
        i = int(which)
        if not 0 <= i < len(names):
            raise ConfigError(f"{what} index {i} is out of range; the graph has {len(names)} {what}s")
        return i

    def describe(self) -> str:
        """A readable table of the keys."""
        lines = [f"{self.steps} steps, dt = {self.dt:g} s (k = 0 .. {self.steps - 1})",
                 "x(k)        gtsam.Pose3  flexibility (R, t), local -> world   [rad, m]",
                 "v(k)        Vector6      (w, v) world frame                   [rad/s, m/s]",
                 "a(k)        Vector6      (dw, a) world frame                  [rad/s^2, m/s^2]"]
        for i, name in enumerate(self.contact_names):
            lines.append(f"w({gf.MAX_CONTACTS}k+{i})   Vector6      wrench of contact {name!r} (F, T about the "
                         f"world origin) [N, N m], while active ({int(self.active[:, i].sum())} steps)")
        for j, eff in enumerate(self.problem.effects):
            lines.append(f"e({gf.MAX_EFFECTS}k+{j})   Vector{eff.dim}      effect {eff.name!r}: "
                         + ", ".join(eff.labels))
        return "\n".join(lines)


def to_gtsam(rec, model, rule: NoiseRule | None = None, rest_p=None, rest_R=None, footholds: bool = False):
    """The smoothing problem of a recording as a gtsam graph: ``(graph, values, keys)``.

    Args:
        rec: the Recording; model: the ModelConfig (contact parameters, sensor noise, ``use_ft``,
            ``effects``).
        rule: the noise rule (default :class:`NoiseRule`).
        rest_p, rest_R: the contacts' rest placements in the world per step (default the local ones).
        footholds: the contact episodes' footholds as unknowns (as ``BatchConfig.footholds``).

    Returns:
        ``graph`` (``gtsam.NonlinearFactorGraph``, module docstring), ``values`` (``gtsam.Values``:
        the batch smoother's initial estimate, every step at the first step's static equilibrium and
        the effects at their prior means) and ``keys`` (:class:`GtsamKeys`).  The graph's optimum is
        :func:`flexforce.smoother.run_batch`'s (with ``global_constants=False`` when a constant
        effect is enabled: the batch default estimates those by the marginal likelihood).

    Raises:
        ConfigError: ``model`` is not a ModelConfig (None included: the graph has no default model).
    """
    from flexforce.factors.model import ModelConfig
    from flexforce.smoother.batch import initial_trajectory

    if not isinstance(model, ModelConfig):
        raise ConfigError(f"to_gtsam needs the recording's model, a ModelConfig (e.g. "
                          f"ModelConfig.from_recording(rec)), got {'None' if model is None else type(model).__name__}")
    if footholds:
        model, rest_p, rest_R = with_footholds(rec, model, rest_p, rest_R)
    prob = Problem.build(rec, model, NoiseRule() if rule is None else rule, rest_p, rest_R)
    builder = GraphBuilder(prob)
    return builder.graph(), builder.values(initial_trajectory(prob)), GtsamKeys(builder)


def from_gtsam(values: gtsam.Values, keys: GtsamKeys, graph: gtsam.NonlinearFactorGraph | None = None,
               name: str = "gtsam", meta: dict | None = None):
    """The :class:`~flexforce.datasets.estimate.Estimate` held by gtsam ``values`` of
    :func:`to_gtsam`'s keys.

    With ``graph``, the covariances are the marginals of ``gtsam.Marginals(graph, values)``, joint
    within each step (pose converted from gtsam's body-frame tangent to world-frame increments);
    without it, the Estimate has none.  Residuals, CoP and the effects' reports are computed as
    for the other estimators.
    """
    from flexforce.smoother.result import make_estimate

    if not isinstance(keys, GtsamKeys):
        raise ConfigError(f"keys must be the GtsamKeys returned by to_gtsam, got {type(keys).__name__}")
    builder = keys.builder
    prob = builder.prob
    traj = builder.trajectory(values)
    P = None if graph is None else _marginals(builder, graph, values, traj)
    return make_estimate(prob, name, traj, P, meta={"backend": "gtsam", **(meta or {})})


def _marginals(builder: GraphBuilder, graph, values, traj) -> np.ndarray:
    """(N, D, D) per-step joint marginal covariances in the smoother's state layout."""
    prob = builder.prob
    S = 18
    D = prob.state_dim
    marginals = gtsam.Marginals(graph, values)
    P = np.zeros((prob.n, D, D))
    e_off = [S + 6 * prob.nc + int(x) for x in np.concatenate([[0], np.cumsum(prob.effect_dims)[:-1]])]
    for k in range(prob.n):
        slots = [(gf.X(k), 0, 6), (gf.V(k), 6, 6), (gf.A(k), 12, 6)]
        slots += [(gf.W(k, i), S + 6 * i, 6) for i in builder.contacts(k)]
        slots += [(gf.E(k, j), e_off[j], eff.dim) for j, eff in builder.effects]
        joint = marginals.jointMarginalCovariance(gtsam.KeyVector([key for key, _, _ in slots]))
        for ka, oa, da in slots:
            for kb, ob, db in slots:
                P[k, oa:oa + da, ob:ob + db] = joint.at(ka, kb)
        Ad = np.kron(np.eye(2), traj.R[k])  # body-frame (d_phi, d_rho) -> world (d_theta, d_t)
        P[k, :, 0:6] = P[k, :, 0:6] @ Ad.T
        P[k, 0:6, :] = Ad @ P[k, 0:6, :]
    return P
