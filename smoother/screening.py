r"""Screening candidate effects at a fitted model without refitting: the score (Rao, Lagrange-multiplier) test.

At the fit of a base model (the trajectory ``x*``), a candidate effect's unknowns ``c`` are appended
at their prior mean (zero: "no effect").  One linearisation gives the gradient of the fit's cost in
``c`` and the Gauss-Newton information.  Eliminating the states (and the base model's own constant
parameters) leaves, on ``c``,

.. math::  \bar g = g_c - I_{cx} I_{xx}^{-1} g_x, \qquad S = I_{cc} - I_{cx} I_{xx}^{-1} I_{xc}

(``g`` the gradient of minus the cost, ``S`` the Schur complement: the inverse of the ``c`` block of
the inverse information), and the score statistic is

.. math::  T = \bar g^T S^{-1} \bar g

twice the cost decrease the quadratic model promises when ``c`` is freed: the likelihood ratio
without the refit.  Under the base model it is chi-square with the effect's effective dof
``nu = dim - tr(S^{-1} Lambda_0)`` (``Lambda_0`` the information of the effect's own prior, which
``S`` includes: ``dim`` when the data determine the effect).

For a constant effect the gradient is that of the marginal likelihood the fit maximises
(:mod:`flexforce.smoother.evidence`): the data cost's, minus the gradient of the Occam term (the
log-determinants of the states' information depend on a parameter that enters the dynamics: the
joint cost alone would call the contact damping significant on a clean recording).

A per-step effect (e.g. an external wrench, a random walk) is screened on time windows: its value
is taken constant within each window (``window`` s), with the effect's first-step prior on each
window's value, and each window is tested alone, its level Bonferroni-corrected for the number of
windows; the windows that pass say *when* the effect acts.  Its Occam gradient is left out (an
additive term has none, besides the Huber weights).

Everything is one linearisation and one block-tridiagonal elimination with the candidate's
columns as right-hand sides: seconds, against minutes for a refit.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from flexforce.errors import EstimatorError
from flexforce.factors.effects.base import traits
from flexforce.smoother import evidence, solvers
from flexforce.smoother.linearize import (
    Linearization,
    Trajectory,
    assemble,
    drop_global_walks,
    global_columns,
    is_global,
    linearize,
)
from flexforce.smoother.problem import NoiseRule, Problem

S_CORE = 18

WINDOW = 0.25
"""Default length of the windows on which a per-step effect is screened, s."""


@dataclass
class ScoreWindow:
    """One time window of a per-step effect's screening."""

    start_s: float
    end_s: float
    statistic: float
    dof: float
    p_value: float
    """Uncorrected p-value (compare with ``level / n_windows``)."""

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class ScoreTest:
    """The score test of one candidate effect at a base fit."""

    effect: str
    statistic: float
    """``T = g^T S^-1 g`` (for a windowed effect: the largest window's)."""
    dof: float
    """Effective degrees of freedom of the chi-square reference."""
    p_value: float
    """p-value (for a windowed effect: the smallest window's, Bonferroni-corrected by the window count)."""
    kind: str = "constant"
    """``"constant"`` (one global block) or ``"windowed"`` (a per-step effect, tested per window)."""
    windows: list[ScoreWindow] = field(default_factory=list)
    """Windowed effect: every window, in time order."""
    seconds: float = 0.0

    def passing_windows(self, level: float) -> list[ScoreWindow]:
        """The windows significant at ``level`` after the Bonferroni correction."""
        m = max(len(self.windows), 1)
        return [w for w in self.windows if w.p_value < level / m]

    def to_dict(self, level: float | None = None) -> dict:
        out = {"effect": self.effect, "statistic": _f(self.statistic), "dof": _f(self.dof),
               "p_value": _f(self.p_value), "kind": self.kind, "seconds": _f(self.seconds)}
        if self.kind == "windowed":
            out["window_s"] = (self.windows[0].end_s - self.windows[0].start_s) if self.windows else None
            out["n_windows"] = len(self.windows)
            if level is not None:
                out["passing_windows"] = [w.to_dict() for w in self.passing_windows(level)]
        return out


def _f(x):
    x = float(x)
    return x if np.isfinite(x) else None


def _border_terms(Hd, B, g, aidx, sel, T):
    """The border terms of a block-tridiagonal system whose columns ``sel`` are tied to ``m``
    border unknowns by ``x_k[sel] = T_k c`` (``T`` (N, len(sel), m)): the coupling ``F`` (N,
    len(aidx), m) of the remaining per-step columns ``aidx`` to the border, the border's own
    information ``G`` (m, m) and gradient ``gc`` (m,)."""
    n, m = Hd.shape[0], T.shape[2]
    F = Hd[:, aidx][:, :, sel] @ T
    # sums over the steps as one matrix product each (a three-operand einsum loops naively: 17 s
    # of a 19 s table on 20 s of sway with the footholds' 12 border unknowns)
    r = T.shape[1]
    Tf = T.reshape(n * r, m)
    G = Tf.T @ (Hd[:, sel][:, :, sel] @ T).reshape(n * r, m)
    gc = Tf.T @ g[:, sel].reshape(n * r)
    if n > 1:
        F[:-1] += B[:, aidx][:, :, sel] @ T[1:]
        F[1:] += B[:, sel][:, :, aidx].transpose(0, 2, 1) @ T[:-1]
        X = T[:-1].reshape((n - 1) * r, m).T @ (B[:, sel][:, :, sel] @ T[1:]).reshape((n - 1) * r, m)
        G += X + X.T
    return F, G, gc


def _scaled_states(Hd, B, aidx):
    """The per-step columns' blocks, Jacobi-scaled: ``s``, ``As`` (N, a, a), ``ABs`` (N-1, a, a)."""
    Ad = Hd[:, aidx][:, :, aidx]
    AB = B[:, aidx][:, :, aidx]
    s = 1.0 / np.sqrt(np.maximum(np.diagonal(Ad, axis1=1, axis2=2), 1e-300))
    As = np.ascontiguousarray(Ad * s[:, :, None] * s[:, None, :])
    ABs = np.ascontiguousarray(AB * s[:-1, :, None] * s[1:, None, :])
    return s, As, ABs


def _solve_states(As, ABs, rhs):
    try:
        X, _, _ = solvers.block_tridiag_solve_multi(As, ABs, np.ascontiguousarray(rhs), False)
    except np.linalg.LinAlgError as exc:
        raise EstimatorError("screening: the information of the states is not positive definite") from exc
    return X


def _eliminate_border(Hd, B, g, aidx, sel, T, states=None):
    """Eliminate the per-step columns ``aidx`` of a block-tridiagonal system whose columns ``sel``
    are tied to ``m`` border unknowns by ``x_k[sel] = T_k c`` (``T`` (N, len(sel), m)).

    Returns the reduced gradient ``gbar`` (m,), the Schur complement ``S`` (m, m) and the scaled
    elimination it ran, ``(s, As, ABs, X)`` with ``X`` (N, len(aidx), 1 + m) the scaled states'
    solution for ``[g, F]``.  ``states``: the states' scaled blocks and factor when they are known
    already (:class:`~flexforce.smoother.evidence.SharedStates` of this system, the same ``aidx``)."""
    F, G, gc = _border_terms(Hd, B, g, aidx, sel, T)
    if states is None:
        s, As, ABs = _scaled_states(Hd, B, aidx)
    else:
        s, As, ABs = states.s, states.Hs, states.Bs
    rhs = np.concatenate([(g[:, aidx] * s)[:, :, None], F * s[:, :, None]], axis=2)
    if states is None:
        X = _solve_states(As, ABs, rhs)
    else:
        try:
            X = solvers.block_tridiag_substitute(*states.cholesky(), np.ascontiguousarray(rhs))
        except EstimatorError as exc:
            raise EstimatorError("screening: the information of the states is not positive definite") from exc
    Fs = F * s[:, :, None]
    Sc = G - np.einsum("kai,kaj->ij", Fs, X[:, :, 1:])
    gbar = gc - np.einsum("kai,ka->i", Fs, X[:, :, 0])
    return gbar, 0.5 * (Sc + Sc.T), (s, As, ABs, X)


@dataclass
class _WindowedSchur:
    """States eliminated from a system bordered by constant columns and by columns constant on
    time windows, each window on its own: the constant border's ``gc`` (mc,), ``Scc`` (mc, mc);
    per window ``gw`` (W, dw), ``Sww`` (W, dw, dw) and the cross block ``Scw`` (W, mc, dw)."""

    gc: np.ndarray
    Scc: np.ndarray
    gw: np.ndarray
    Sww: np.ndarray
    Scw: np.ndarray

    def joint(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """``(gbar, S)`` over the constant columns then window ``j``'s columns."""
        S = np.block([[self.Scc, self.Scw[j]], [self.Scw[j].T, self.Sww[j]]])
        return np.concatenate([self.gc, self.gw[j]]), 0.5 * (S + S.T)


def _windowed_schur(Hd, B, g, aidx, ccols, wcols, bounds) -> _WindowedSchur:
    r"""Eliminate the per-step columns ``aidx`` with the columns ``ccols`` tied to one constant
    and the columns ``wcols`` tied to one value per window of ``bounds`` ((k0, k1) pairs), each
    window's border taken alone (the others at zero).

    Linear in the length: one elimination for the constant columns; for a window, ``F_w^T
    A^{-1} F_w`` needs ``A^{-1}`` only on the steps ``a = k0 - 1 .. b = k1`` its columns touch,
    which is the inverse of ``A`` restricted to them with the first diagonal block replaced by the
    forward elimination's pivot at ``a`` (the steps before eliminated) and the last by the
    backward elimination's pivot at ``b``.
    """
    n = Hd.shape[0]
    ccols = np.asarray(ccols, dtype=int)
    wcols = np.asarray(wcols, dtype=int)
    mc, dw = len(ccols), len(wcols)
    Tc = np.ascontiguousarray(np.broadcast_to(np.eye(mc), (n, mc, mc)))
    gc, Scc, (s, As, ABs, X) = _eliminate_border(Hd, B, g, aidx, ccols, Tc)
    # forward and backward pivots of the scaled states' system
    try:
        Lf, _ = solvers._block_cholesky(As, ABs)
        Lb, _ = solvers._block_cholesky(np.ascontiguousarray(As[::-1]),
                                        np.ascontiguousarray(ABs[::-1].transpose(0, 2, 1)))
    except np.linalg.LinAlgError as exc:
        raise EstimatorError("screening: the information of the states is not positive definite") from exc
    Pf = Lf @ Lf.transpose(0, 2, 1)
    Pb = (Lb @ Lb.transpose(0, 2, 1))[::-1]
    # the blocks a window's columns touch
    H_aw, H_ww, H_cw = Hd[:, aidx][:, :, wcols], Hd[:, wcols][:, :, wcols], Hd[:, ccols][:, :, wcols]
    B_aw, B_wa = B[:, aidx][:, :, wcols], B[:, wcols][:, :, aidx]
    B_ww, B_cw, B_wc = B[:, wcols][:, :, wcols], B[:, ccols][:, :, wcols], B[:, wcols][:, :, ccols]
    W = len(bounds)
    gw = np.zeros((W, dw))
    Sww = np.zeros((W, dw, dw))
    Scw = np.zeros((W, mc, dw))
    for j, (k0, k1) in enumerate(bounds):
        a, b = max(k0 - 1, 0), min(k1, n - 1)
        L = b - a + 1
        F = np.zeros((L, len(aidx), dw))
        F[k0 - a:k1 - a] += H_aw[k0:k1]
        if k0 >= 1:  # step k takes B_k T_k+1: steps k0-1 .. k1-2
            F[k0 - 1 - a:k1 - 1 - a] += B_aw[k0 - 1:k1 - 1]
        else:
            F[0:k1 - 1 - a] += B_aw[0:k1 - 1]
        hi = min(k1, n - 1)  # step k takes B_k-1^T T_k-1: steps k0+1 .. k1
        F[k0 + 1 - a:hi + 1 - a] += B_wa[k0:hi].transpose(0, 2, 1)
        G = H_ww[k0:k1].sum(axis=0)
        Gcw = H_cw[k0:k1].sum(axis=0) + B_cw[max(k0 - 1, 0):k1 - 1].sum(axis=0) + \
            B_wc[k0:min(k1, n - 1)].sum(axis=0).T
        if k1 - k0 > 1:
            Xw = B_ww[k0:k1 - 1].sum(axis=0)
            G = G + Xw + Xw.T
        Dl = As[a:b + 1].copy()
        if L == 1:
            Dl[0] = Pf[a] + Pb[a] - As[a]
        else:
            Dl[0] = Pf[a]
            Dl[-1] = Pb[b]
        Fs = F * s[a:b + 1, :, None]
        Y = _solve_states(np.ascontiguousarray(Dl), np.ascontiguousarray(ABs[a:b]), Fs)
        S = G - np.einsum("kai,kaj->ij", Fs, Y)
        Sww[j] = 0.5 * (S + S.T)
        Scw[j] = Gcw - np.einsum("kai,kaj->ij", X[a:b + 1, :, 1:], Fs)
        gw[j] = g[k0:k1][:, wcols].sum(axis=0) - np.einsum("kai,ka->i", Fs, X[a:b + 1, :, 0])
    return _WindowedSchur(gc, Scc, gw, Sww, Scw)


def _quad(g, S, idx):
    """``g[idx]^T S[idx, idx]^-1 g[idx]`` (0 for an empty ``idx``) and the inverse block."""
    if len(idx) == 0:
        return 0.0, np.zeros((0, 0))
    Si = np.linalg.pinv(S[np.ix_(idx, idx)], rcond=1e-12, hermitian=True)
    return float(g[idx] @ Si @ g[idx]), Si


def _with_candidate(prob_base: Problem, traj: Trajectory, effect, rule: NoiseRule):
    model = dataclasses.replace(prob_base.model,  # type: ignore[type-var]
                                effects=tuple(prob_base.effects) + (effect,))
    prob = Problem.build(prob_base.rec, model, rule, prob_base.rest_p, prob_base.rest_R)
    mean, _ = effect.prior(prob)
    e_new = np.broadcast_to(np.asarray(mean, dtype=float), (prob.n, int(effect.dim)))
    tr = Trajectory(traj.R, traj.q, traj.W, np.concatenate([traj.e, e_new], axis=1))
    return prob, tr


def score_test(prob_base: Problem, traj: Trajectory, effect, rule: NoiseRule | None = None,
               window: float = WINDOW, occam: bool = True) -> ScoreTest:
    """The score test of ``effect`` added to the fitted ``prob_base`` at its optimum ``traj``.

    Args:
        prob_base: the base model's Problem (its effects' constant parameters are re-estimated
            jointly with the states in the test: eliminated, not held).
        traj: the base fit's trajectory (:attr:`flexforce.smoother.FitStatistics.trajectory`).
        effect: the candidate (an :class:`~flexforce.factors.effects.Effect`).
        window: window length of a per-step effect's test, s.
        occam: for a constant effect, use the marginal likelihood's gradient (with the Occam term).
    """
    import time

    t0 = time.perf_counter()
    rule = rule or NoiseRule()
    prob, tr = _with_candidate(prob_base, traj, effect, rule)
    n, D = prob.n, prob.state_dim
    dim = int(effect.dim)
    ecols = np.arange(D - dim, D)
    gcols = [int(c) for c in global_columns(prob) if c < D - dim]
    lin = linearize(prob, tr)
    if is_global(effect, prob):
        lin = drop_global_walks(prob, lin)
        Hd, B, g = assemble(lin, n, D)
        cidx = np.asarray(gcols + list(ecols), dtype=int)
        # the states' part, shared by the candidates of this base (evidence.shared_states)
        states = evidence.shared_states(prob, lin, cidx)
        if occam:
            # minus the Occam term's gradient (g is minus the cost's gradient); summed over steps,
            # so put it on the first step
            grad = evidence.occam_gradient(prob, tr, cidx, lin=lin, states=states)
            g = g.copy()
            g[0, cidx] -= grad
        aidx = states.aidx
        T = np.broadcast_to(np.eye(len(cidx)), (n, len(cidx), len(cidx)))
        gbar, Sc, _ = _eliminate_border(Hd, B, g, aidx, cidx, np.ascontiguousarray(T), states=states)
        m0 = len(gcols)
        full, Si = _quad(gbar, Sc, np.arange(len(cidx)))
        held, _ = _quad(gbar, Sc, np.arange(m0))
        stat = max(full - held, 0.0)
        # the candidate's block of the inverse (the base's constants eliminated too)
        Pee = Si[m0:, m0:]
        _, s0 = effect.prior(prob)
        s0 = np.broadcast_to(np.asarray(s0, dtype=float), (dim,))
        dof = float(max(dim - np.sum(np.diagonal(Pee) / s0**2), 1e-6))
        p = float(stats.chi2.sf(stat, dof))
        return ScoreTest(effect.name, stat, dof, p, "constant", [], time.perf_counter() - t0)
    # a per-step effect: piecewise constant on windows, each with the effect's first-step prior
    drop = {f"effect_walk/{effect.name}", f"effect_level/{effect.name}", f"effect_prior/{effect.name}"}
    lin = Linearization(unary={k: v for k, v in lin.unary.items() if k not in drop},
                        binary={k: v for k, v in lin.binary.items() if k not in drop}, cost=lin.cost)
    lin = drop_global_walks(prob, lin)
    Hd, B, g = assemble(lin, n, D)
    _, s0 = effect.prior(prob)
    lam0 = 1.0 / np.broadcast_to(np.asarray(s0, dtype=float), (dim,)) ** 2
    t = (np.asarray(prob.rec.t_ns) - prob.rec.t_ns[0]) * 1e-9
    w = max(1, int(round(window / prob.dt)))
    starts = list(range(0, n, w))
    if len(starts) > 1 and n - starts[-1] < w // 2:  # a short tail joins the last window
        starts.pop()
    bounds = [(s, starts[i + 1] if i + 1 < len(starts) else n) for i, s in enumerate(starts)]
    windows: list[ScoreWindow] = []
    m0 = len(gcols)
    cidx = np.asarray(gcols + list(ecols), dtype=int)
    aidx = np.setdiff1d(np.arange(D), cidx)
    ws = _windowed_schur(Hd, B, g, aidx, gcols, ecols, bounds)
    for j, (k0, k1) in enumerate(bounds):
        gbar, Sw = ws.joint(j)
        held, _ = _quad(gbar, Sw, np.arange(m0))
        Sw[m0:, m0:] += np.diag(lam0)
        Si = np.linalg.pinv(Sw, rcond=1e-12, hermitian=True)
        full = float(gbar @ Si @ gbar)
        stat = max(full - held, 0.0)
        dof = float(max(dim - np.sum(np.diagonal(Si[m0:, m0:]) * lam0), 1e-6))
        windows.append(ScoreWindow(float(t[k0]), float(t[k1 - 1]), stat, dof, float(stats.chi2.sf(stat, dof))))
    best = min(windows, key=lambda x: (x.p_value, -x.statistic))
    p = min(1.0, best.p_value * len(windows))
    return ScoreTest(effect.name, best.statistic, best.dof, p, "windowed", windows, time.perf_counter() - t0)


# ----------------------------------------------------------------------------------------------
# Identifiability: which candidates the nominal fit's information can see and tell apart
# ----------------------------------------------------------------------------------------------

INSEPARABLE = 0.95
"""Largest canonical correlation above which two candidates cannot be told apart: the data see one
direction of each as the same (docs/diagnostics.md, "Identifiability")."""


@dataclass
class CandidateInformation:
    """What the nominal fit's data say about one candidate's unknowns (states eliminated)."""

    effect: str
    dim: int
    labels: tuple[str, ...]
    kind: str
    """``"constant"`` or ``"windowed"`` (a per-step effect, taken constant on windows)."""
    detectability: float
    """Smallest eigenvalue of the data information scaled by the effect's prior sigmas,
    ``eig_min(D S D)``: twice the log-likelihood gain an effect of one prior sigma along the worst
    direction would bring (for a windowed effect, that of one window, the median window)."""
    weakest: str
    """The unknown that dominates the worst direction."""
    weakest_index: int
    threshold: float
    """Detection threshold on :attr:`detectability` (BIC's ``ln n``)."""
    excites: str = ""
    """What motion excites the weakest unknown (the effect's ``excites``)."""
    strongest: float = float("inf")
    """Largest eigenvalue of the same scaled information (the best-seen direction)."""
    detectable: tuple[float, ...] = ()
    """Per unknown (in its own unit, the :attr:`labels`' order), the smallest value this recording
    detects: the size whose gain in ``2 ln L``, the candidate's other unknowns fitted with it,
    pays for the candidate's ``dim`` unknowns, ``dim`` times :attr:`threshold` (the selection's
    score charges ``ln n`` per unknown) -- ``sqrt(dim threshold / s_i)``, ``s_i`` the Schur
    complement of the unknown in the candidate's information (inf: not seen alone).  For a windowed
    candidate (scored by its Bayes factor), an effect lasting one window (the median window) whose
    gain reaches :attr:`threshold`."""

    def detectable_text(self) -> str:
        """``x ≥ 0.012 m/s^2, ...``: the detectable sizes, one per unknown."""
        out = []
        for i, size in enumerate(self.detectable):
            label = self.labels[i] if i < len(self.labels) else f"#{i}"
            name, _, unit = label.partition(" [")
            unit = unit.rstrip("]")
            out.append(f"{name} {'not alone' if not math.isfinite(size) else f'≥ {size:.2g}'}"
                       f"{' ' + unit if unit and unit != '-' and math.isfinite(size) else ''}")
        return ", ".join(out)

    @property
    def seen(self) -> bool:
        """Every direction seen: a prior-sized value along the worst one pays for its dof."""
        return bool(self.detectability >= self.threshold)

    @property
    def status(self) -> str:
        """``"seen"``, ``"partly seen"`` (some direction is not) or ``"not seen"`` (none is)."""
        if self.seen:
            return "seen"
        return "partly seen" if self.strongest >= self.threshold else "not seen"

    def unexcited(self) -> str:
        """``the recording does not excite yaw stiffness: no torque about z``-style reason."""
        what = f": {self.excites}" if self.excites else ""
        return f"the recording does not excite {self.effect} {self.weakest}{what}"

    def text(self) -> str:
        if self.seen:
            return (f"seen (a prior-sized {self.weakest} gains {self.detectability:.3g} in 2 ln L, "
                    f">= {self.threshold:.1f}; detects {self.detectable_text()})")
        return (f"{self.status}: {self.unexcited()} (a prior-sized value gains {self.detectability:.2g} in 2 ln L, "
                f"below {self.threshold:.1f}; detects {self.detectable_text()})")

    def to_dict(self) -> dict:
        return {"effect": self.effect, "dim": self.dim, "kind": self.kind, "detectability": _f(self.detectability),
                "strongest": _f(self.strongest), "threshold": _f(self.threshold), "seen": self.seen,
                "detectable": [_f(x) for x in self.detectable], "detectable_text": self.detectable_text(),
                "status": self.status, "weakest": self.weakest, "excites": self.excites, "summary": self.text()}


def detectable_sizes(S: np.ndarray, sigma: np.ndarray, threshold: float) -> tuple[float, ...]:
    """Per unknown of a candidate whose data information is ``S`` (raw units; ``sigma`` its prior
    sigmas, for the scaling only), the smallest value whose gain in ``2 ln L`` with the other
    unknowns fitted reaches ``threshold``: ``sqrt(threshold / s_i)``, ``s_i = S_ii - S_io S_oo^+
    S_oi`` (inf where ``s_i`` vanishes: that unknown is not seen apart from the others)."""
    sigma = np.asarray(sigma, dtype=float)
    Z = sigma[:, None] * np.asarray(S, dtype=float) * sigma[None, :]  # scaled: conditioned
    Z = 0.5 * (Z + Z.T)
    scale = max(float(np.max(np.abs(np.diag(Z)))) if Z.size else 0.0, 1e-300)
    out = []
    for i in range(Z.shape[0]):
        o = [j for j in range(Z.shape[0]) if j != i]
        s_i = float(Z[i, i])
        if o:
            s_i -= float(Z[i, o] @ np.linalg.pinv(Z[np.ix_(o, o)], rcond=1e-12, hermitian=True) @ Z[o, i])
        out.append(float(sigma[i] * np.sqrt(threshold / s_i)) if s_i > 1e-12 * scale else float("inf"))
    return tuple(out)


@dataclass
class PairCorrelation:
    """The canonical correlations of two candidates' score directions at the nominal fit."""

    a: str
    b: str
    correlations: list[float]
    """Canonical correlations, largest first (``min(dim_a, dim_b)`` of them)."""
    direction_a: str
    """The unknown of ``a`` that dominates the most correlated direction."""
    direction_b: str
    hint: str = ""

    @property
    def largest(self) -> float:
        return self.correlations[0] if self.correlations else 0.0

    @property
    def inseparable(self) -> bool:
        return bool(self.largest > INSEPARABLE)

    def text(self) -> str:
        head = (f"{self.a} ({self.direction_a}) and {self.b} ({self.direction_b}): canonical correlation "
                f"{self.largest:.3f}")
        if not self.inseparable:
            return head
        return (f"{head} > {INSEPARABLE}: cannot be told apart by this recording"
                + (f"; to separate them: {self.hint}" if self.hint else ""))

    def to_dict(self) -> dict:
        return {"a": self.a, "b": self.b, "correlation": _f(self.largest),
                "canonical_correlations": [_f(c) for c in self.correlations], "direction_a": self.direction_a,
                "direction_b": self.direction_b, "inseparable": self.inseparable, "hint": self.hint,
                "summary": self.text()}


@dataclass
class Identifiability:
    """Per candidate its own information, per pair the correlation of their score directions."""

    candidates: dict[str, CandidateInformation]
    pairs: list[PairCorrelation]
    """Every pair, most correlated first."""
    threshold: float = INSEPARABLE
    seconds: float = 0.0
    errors: dict[str, str] = field(default_factory=dict)
    """Candidates left out (their information could not be formed), with the reason."""

    def inseparable(self) -> list[PairCorrelation]:
        return [p for p in self.pairs if p.inseparable]

    def not_seen(self) -> list[CandidateInformation]:
        """Candidates with a direction the recording does not excite (partly or not seen)."""
        return [c for c in self.candidates.values() if not c.seen]

    def pair(self, a: str, b: str) -> PairCorrelation | None:
        return next((p for p in self.pairs if {p.a, p.b} == {a, b}), None)

    def to_dict(self) -> dict:
        return {"threshold": self.threshold, "seconds": _f(self.seconds),
                "candidates": [c.to_dict() for c in self.candidates.values()],
                "pairs": [p.to_dict() for p in self.pairs],
                "inseparable": [[p.a, p.b] for p in self.inseparable()],
                "not_seen": [c.effect for c in self.not_seen()], "errors": dict(self.errors)}

    def table(self) -> str:
        """Plain text: the candidates not seen, then the pairs that cannot be told apart."""
        lines = [f"identifiability at the nominal fit ({len(self.candidates)} candidates):"]
        lines += [f"  {c.effect}: {c.text()}" for c in self.candidates.values() if not c.seen]
        lines += [f"  {p.text()}" for p in self.inseparable()]
        if len(lines) == 1:
            lines.append(f"  every candidate seen, no pair correlated above {self.threshold}")
        lines += [f"  {k}: {v}" for k, v in self.errors.items()]
        return "\n".join(lines)


def _constant_here(eff, prob) -> bool:
    """A per-step effect constant on this recording (its ``constant_on(prob)``: the footholds of a
    recording without a touch-down, one episode per contact), compared as a constant: window by
    window it would be a window's worth of itself."""
    check = traits(eff).constant_on
    return bool(check(prob)) if callable(check) else False


def _pair_hint(ea, eb) -> str:
    parts = [f"{e.name}: {h}" for e in (ea, eb) if (h := str(traits(e).hint or ""))]
    return "; ".join(parts)


def _label(eff, i: int) -> str:
    labels = tuple(getattr(eff, "labels", ()))
    return labels[i] if i < len(labels) else f"{eff.name}[{i}]"


def _excites(eff, i: int) -> str:
    ex = tuple(traits(eff).excites or ())
    return str(ex[i]) if i < len(ex) else ""


def _canonical(P, A, Bb, sa, sb, ea, eb) -> PairCorrelation:
    """The canonical correlations of the blocks ``A`` and ``Bb`` of the information ``P``."""
    Wa, Wb = _inv_sqrt(P[np.ix_(A, A)]), _inv_sqrt(P[np.ix_(Bb, Bb)])
    U, sv, Vt = np.linalg.svd(Wa @ P[np.ix_(A, Bb)] @ Wb)
    # the canonical directions in multiples of each unknown's prior sigma
    ua = (Wa @ U[:, 0]) / sa
    vb = (Wb @ Vt[0]) / sb
    ia_ = int(np.argmax(np.abs(ua))) % int(ea.dim)
    ib_ = int(np.argmax(np.abs(vb))) % int(eb.dim)
    return PairCorrelation(ea.name, eb.name, [float(min(x, 1.0)) for x in sv[:min(len(A), len(Bb), 6)]],
                           _label(ea, ia_).split(" [")[0], _label(eb, ib_).split(" [")[0], _pair_hint(ea, eb))


def _inv_sqrt(A):
    w, V = np.linalg.eigh(0.5 * (A + A.T))
    w = np.maximum(w, 1e-12 * max(float(w.max()), 1e-300))
    return (V / np.sqrt(w)) @ V.T


def _candidate_columns(prob: Problem, effects, first: int, gcols: list[int]):
    """The candidates' columns after the base model's (from ``first`` on): ``(const, windowed,
    ccols, wcols)``.  ``ccols``: the base constants ``gcols``, then the constant candidates';
    ``wcols``: the per-step candidates' (each taken constant on a window, every window on its
    own).  ``const``: per constant candidate ``(effect, its index range in the constant border
    after the base constants, prior sigma)``; ``windowed``: per per-step candidate ``(effect, its
    index range in a window's columns, prior sigma, step sigma or None)``."""
    m0 = len(gcols)
    const: list = []
    windowed: list = []
    ccols: list[int] = list(gcols)
    wcols: list[int] = []
    col = first
    for eff in effects:
        dim = int(eff.dim)
        _, s0 = eff.prior(prob)
        s0 = np.broadcast_to(np.asarray(s0, dtype=float), (dim,))
        if is_global(eff, prob) or _constant_here(eff, prob):
            const.append((eff, np.arange(len(ccols) - m0, len(ccols) - m0 + dim), s0))
            ccols.extend(range(col, col + dim))
        else:
            step = traits(eff).step_prior_sigma
            ss = np.broadcast_to(np.asarray(step(prob), dtype=float), (dim,)) if step is not None else None
            windowed.append((eff, np.arange(len(wcols), len(wcols) + dim), s0, ss))
            wcols.extend(range(col, col + dim))
        col += dim
    return const, windowed, ccols, wcols


def _without_base(S, m0: int):
    """The information on the candidates, the first ``m0`` (the base model's constants) eliminated."""
    if not m0:
        return 0.5 * (S + S.T)
    X = np.linalg.pinv(S[:m0, :m0], rcond=1e-12, hermitian=True) @ S[:m0, m0:]
    J = S[m0:, m0:] - S[m0:, :m0] @ X
    return 0.5 * (J + J.T)


def identifiability(prob_base: Problem, traj: Trajectory, effects, rule: NoiseRule | None = None,
                    window: float = WINDOW, n_residuals: int | None = None) -> Identifiability:
    """Which candidates the base fit's information sees, and which pairs it cannot tell apart.

    Every candidate is appended at its prior mean (as in :func:`score_test`, all at once) and one
    linearisation gives the Gauss-Newton information of the data; eliminating the states and the
    base model's constants leaves the joint information ``J`` of all candidates' unknowns (a
    per-step effect taken constant on ``window`` s windows, each window on its own, as its score
    test takes it: linear in the recording's length).  Per candidate, the smallest
    eigenvalue of its block scaled by its prior sigmas (:attr:`CandidateInformation.detectability`;
    below ``ln n`` a prior-sized effect along that direction would not pay for its own degree of
    freedom: "not seen").  Per pair, the canonical correlations of the two blocks with the priors'
    information added (the correlations of their estimates were both fitted): the largest above
    :data:`INSEPARABLE` means one direction of each explains the data in the same way; a per-step
    candidate is compared with another window by window and the most alike window is kept (a
    push over one window against a constant bias: can that push be told from the bias).
    """
    import time

    t0 = time.perf_counter()
    rule = rule or NoiseRule()
    effects = list(effects)
    errors: dict[str, str] = {}
    model = dataclasses.replace(prob_base.model,  # type: ignore[type-var]
                                effects=tuple(prob_base.effects) + tuple(effects))
    prob = Problem.build(prob_base.rec, model, rule, prob_base.rest_p, prob_base.rest_R)
    n, D = prob.n, prob.state_dim
    means = []
    for eff in effects:
        mean, _ = eff.prior(prob)
        means.append(np.broadcast_to(np.asarray(mean, dtype=float), (n, int(eff.dim))))
    tr = Trajectory(traj.R, traj.q, traj.W, np.concatenate([traj.e, *means], axis=1))
    lin = linearize(prob, tr)
    own = {f"{kind}/{eff.name}" for eff in effects
           for kind in ("effect_walk", "effect_level", "effect_prior")}
    lin = Linearization(unary={k: v for k, v in lin.unary.items() if k not in own},
                        binary={k: v for k, v in lin.binary.items() if k not in own}, cost=lin.cost)
    lin = drop_global_walks(prob, lin)
    Hd, B, g = assemble(lin, n, D)
    d_new = sum(int(e.dim) for e in effects)
    first = D - d_new
    gcols = [int(c) for c in global_columns(prob) if c < first]
    m0 = len(gcols)
    w = max(1, int(round(window / prob.dt)))
    starts = list(range(0, n, w))
    if len(starts) > 1 and n - starts[-1] < w // 2:
        starts.pop()
    bounds = [(s, starts[i + 1] if i + 1 < len(starts) else n) for i, s in enumerate(starts)]
    const, windowed, ccols, wcols = _candidate_columns(prob, effects, first, gcols)
    cidx = np.asarray(ccols + wcols, dtype=int)
    aidx = np.setdiff1d(np.arange(D), cidx)
    ws = _windowed_schur(Hd, B, g, aidx, ccols, wcols, bounds if wcols else [])

    Jc = _without_base(ws.Scc, m0)
    nc_ = Jc.shape[0]
    lam_c = np.concatenate([1.0 / s0**2 for _, _, s0 in const]) if const else np.zeros(0)
    Jw = [_without_base(ws.joint(j)[1], m0) for j in range(len(ws.gw))]
    lam_w = []
    for k0, k1 in (bounds if wcols else []):
        lam_w.append(np.concatenate([(k1 - k0) / ss**2 if ss is not None else 1.0 / s0**2
                                     for _, _, s0, ss in windowed]))
    thr = float(np.log(max(n_residuals or n * 6, 2)))
    cands: dict[str, CandidateInformation] = {}

    def info(eff, kind, Sb, s0):
        wv, V = np.linalg.eigh(s0[:, None] * Sb * s0[None, :])
        i = int(np.argmax(np.abs(V[:, 0])))
        # a constant's size pays for all its unknowns (the selection charges dim ln n); a per-step
        # one's score is its Bayes factor, one window at a time
        charge = thr * (int(eff.dim) if kind == "constant" else 1)
        cands[eff.name] = CandidateInformation(eff.name, int(eff.dim), tuple(getattr(eff, "labels", ())), kind,
                                               float(max(wv[0], 0.0)), _label(eff, i).split(" [")[0], i, thr,
                                               _excites(eff, i), float(max(wv[-1], 0.0)),
                                               detectable_sizes(Sb, s0, charge))

    for eff, blk, s0 in const:
        info(eff, "constant", Jc[np.ix_(blk, blk)], s0)
    for eff, blk, s0, _ in windowed:
        # the median window's information: how well a push lasting one window is seen
        per = [J[np.ix_(nc_ + blk, nc_ + blk)] for J in Jw]
        mins = [float(np.linalg.eigvalsh(s0[:, None] * P * s0[None, :])[0]) for P in per]
        info(eff, "windowed", per[int(np.argsort(mins)[len(mins) // 2])], s0)
    pairs: list[PairCorrelation] = []
    Pc = Jc + np.diag(lam_c)
    for ia in range(len(const)):
        for ib in range(ia + 1, len(const)):
            (ea, A, sa), (eb, Bb, sb) = const[ia], const[ib]
            pairs.append(_canonical(Pc, A, Bb, sa, sb, ea, eb))
    # a per-step candidate against another: window by window, the window where they are most alike
    for iw, (ea, A, sa, _) in enumerate(windowed):
        others = [(eb, Bb, sb) for eb, Bb, sb in const] + \
            [(eb, nc_ + Bb, sb) for eb, Bb, sb, _ in windowed[iw + 1:]]
        for eb, Bb, sb in others:
            best = None
            for J, lw in zip(Jw, lam_w):
                P = J + np.diag(np.concatenate([lam_c, lw]))
                pc = _canonical(P, nc_ + A, Bb, sa, sb, ea, eb)
                if best is None or pc.largest > best.largest:
                    best = pc
            if best is not None:
                pairs.append(best)
    pairs.sort(key=lambda p: -p.largest)
    return Identifiability(cands, pairs, INSEPARABLE, time.perf_counter() - t0, errors)
