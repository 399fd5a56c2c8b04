r"""Footholds as unknowns: every contact episode's rest placement estimated with the trajectory.

A contact's spring is at rest at a placement in the world, ``(p_r, R_r)``, fixed for one contact
episode (touch-down to lift-off): the law is ``s = R p_l + t - p_r``, ``Omega = log(R R_l R_r^T)``
(:mod:`flexforce.factors.core`).  The recording gives a nominal rest placement (the local frame's,
e.g. leg odometry's foothold at the touch-down); :class:`Footholds` adds to it, per contact, a
correction ``e_i = (dp_i, dr_i)`` (world axes, m and rad)::

    p_r' = p_r + dp_i,        R_r' = exp([dr_i]x) R_r

estimated by the smoothers with every other unknown.  Three kinds of factors decide it:

- **Leg kinematics at the touch-down.**  At the first step ``k`` of an episode that starts during
  the recording, the landing sole is where the kinematics put it and its spring starts with no
  deflection: ``(s_k, Omega_k) = 0`` within ``kinematics_sigma_position`` / ``_height`` (m) and
  ``kinematics_sigma_rotation`` / ``_tilt`` (rad), horizontal and vertical separately.  This is
  the touch-down convention of the simulator's ``floor`` mode and of the EKF's
  ``touchdown = "zero-deflection"``: landing creates no force jump.  (The paper's convention,
  ``p_r = p_l``, preloads a foot landing while the flexibility is deflected by that deflection.)
  A contact already in force at the first sample has no such factor (the robot stands on
  deflected springs); its correction has a first-step prior instead: ``GAUGE`` (1e-3) times the
  kinematic sigmas in horizontal position and yaw, which fixes where the world is: the first
  stance soles' placements (a common horizontal shift or yaw of every foothold is seen by no
  sensor).  In height and tilt the prior is ``N(0, kinematics sigmas)``, or, with
  ``anchor_first_stance``, ``GAUGE`` times them too: the local frame at the first sample is
  defined by the first stance soles flat on the floor (:class:`~flexforce.datasets.robot.FootholdConfig`),
  so their placements are the frame's definition, not unknowns.
- **Ground.**  At the first step of every episode the corrected sole lies on the floor plane
  (``n . p_r' = h`` within ``ground_sigma_height``; its z axis along ``n`` within
  ``ground_sigma_tilt``, two rows: the components of ``R_r' e_z`` on the plane's tangent axes).
  ``terrain = "flat"``: the plane ``z = `` the first sample's mean rest height of the contacts in
  force; ``"plane"``: ``normal`` and ``height`` as given (world = local frame at the first sample);
  ``"none"``: no ground factor.
- **Constancy.**  Within an episode (and through the swing that follows it) the correction is a
  random walk of ``walk_within`` (default ``WALK_WITHIN``, 1e-3) of the kinematic sigma per
  step; the walk is cut
  (``1e3`` times the kinematic sigma) where the contact touches down, so each episode is its own
  foothold.  This is a per-episode landmark written as per-step copies tied by equality: the
  graph stays a chain (block tridiagonal, O(N D^3)) instead of gaining long-range edges.

The local frame may then drift in yaw and position, as leg odometry does, but not in tilt: the
ground holds every foothold level, and the flexibility ``(R, t)`` stays the springs' deflection.
The estimate reports each episode's foothold correction (``report``).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from flexforce.datasets.quantities import FootholdPrior
from flexforce.errors import ConfigError, DataError
from flexforce.factors import core
from flexforce.options import check_bool, check_positive

if TYPE_CHECKING:
    from flexforce.factors.effects import ProblemView

__all__ = ["FootholdPrior", "Footholds", "episode_starts", "held_rest", "rest_placements", "touches_down"]

WALK_WITHIN = 1e-3
"""Random-walk sigma of a foothold within an episode, relative to its kinematic sigma (the
default of :class:`Footholds`' ``walk_within``)."""
WALK_WITHIN_ANCHORED = 1e-5
"""``walk_within`` of the smoothers' footholds (``footholds = True``, with ``anchor_first_stance``):
over a recording of ``N`` steps an episode's correction may drift by ``1e-5 sqrt(N)`` of its
kinematic sigma, so it stays one foothold instead of following the model's errors."""
GAUGE = 1e-3
"""Prior sigma of the first stance footholds' horizontal position and yaw, relative to the
kinematic sigmas: the world's horizontal origin and heading are theirs."""
WALK_CUT = 1e3
"""Random-walk sigma where the contact touches down, relative to its kinematic sigma."""


def rest_placements(rec, rest_p=None, rest_R=None):
    """Validated (N, C, 3) and (N, C, 3, 3) world rest placements, default the local placements."""
    n, nc = rec.n, len(rec.contact_names)
    out = []
    for name, value, default, shape in (("rest_p", rest_p, rec.contact_p, (n, nc, 3)),
                                        ("rest_R", rest_R, rec.contact_R, (n, nc, 3, 3))):
        a = np.ascontiguousarray(default if value is None else value, dtype=float)
        if a.shape != shape:
            raise ConfigError(f"{name} must have shape {shape} (steps, contacts, ...), got {a.shape}")
        if not np.isfinite(a[rec.contact_active]).all():
            raise DataError(f"{name} is not finite (NaN or inf) where a contact is active; rest placements "
                            "are in m and rotation matrices")
        out.append(a)
    return out[0], out[1]


def episode_starts(active: np.ndarray) -> np.ndarray:
    """(N, C) bool: contact ``i`` comes into force at step ``k`` (active at k, not at k - 1; step 0
    excluded: an episode in force at the first sample did not start in the recording)."""
    out = np.zeros_like(active, dtype=bool)
    out[1:] = active[1:] & ~active[:-1]
    return out


def touches_down(active: np.ndarray) -> bool:
    """Whether some contact comes into force during the recording (an episode starts after step 0)."""
    return bool(episode_starts(np.asarray(active, dtype=bool)).any())


def held_rest(active: np.ndarray, contact_p: np.ndarray, contact_R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nominal footholds: each contact's placement at the first step of its episode, held while it
    stays in force ((N, C, 3), (N, C, 3, 3); the placements themselves where it is not in force).

    The rest placement of an episode is one placement in the world; a contact that moves in the
    local frame during its episode (a foot levelling after an early touch-down, a sole rolling)
    deflects its spring by that motion instead of dragging its rest placement along."""
    p = np.array(contact_p, dtype=float)
    R = np.array(contact_R, dtype=float)
    for k in range(1, len(p)):
        keep = active[k] & active[k - 1]
        p[k, keep] = p[k - 1, keep]
        R[k, keep] = R[k - 1, keep]
    return p, R


def _skew(v):
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def _exp_all(phi):
    out = [core.so3_exp(np.ascontiguousarray(p)) for p in phi.reshape(-1, 3)]
    return np.array(out).reshape(phi.shape[:-1] + (3, 3))


def _log_all(R):
    return np.array([core.so3_log(np.ascontiguousarray(M)) for M in R.reshape(-1, 3, 3)]).reshape(R.shape[:-2] + (3,))


def _jl_all(phi, inverse=False):
    out = [core.so3_jl(np.ascontiguousarray(p), inverse) for p in phi.reshape(-1, 3)]
    return np.array(out).reshape(phi.shape[:-1] + (3, 3))


class Footholds:
    """Per-contact foothold corrections (module docstring): ``6 C`` unknowns per step, ``(dp_i m,
    dr_i rad)`` world axes, each contact's in turn.

    Also the diagnosis' ``foothold`` candidate (the simulator's hidden ``foothold``): a contact
    resting elsewhere than the recording's local frame says -- a shim or a tilted tile under a
    standing foot, a landing the leg odometry places wrong, the local frame's drift in tilt at
    every touch-down of a real walk.  Without it the smoothers read such an error as a deflection
    of the flexibility, and the forces and the tilt follow it.  The diagnosis makes one per
    recording (:meth:`bind`: one per contact, the robot's ``[footholds]`` priors).

    Args:
        n_contacts: contacts of the recording (one correction of 6 unknowns each).
        prior: the priors (sigmas, terrain); default :class:`FootholdPrior` ``()``.
        anchor_first_stance: give the footholds in force at the first sample the ``GAUGE`` prior
            in all six components (height and tilt too), not only in horizontal position and yaw:
            the first stance soles define the local frame, they are not estimated.  The
            smoothers' ``footholds = True`` sets it (:func:`flexforce.smoother.problem.with_footholds`):
            on real logs whose model errors are many sigmas the first stance footholds otherwise
            absorb them (the standing feet at different heights move load between them).  Off for
            the diagnosis' candidate (:meth:`bind`), which must find a shim under a standing foot.
        walk_within: random-walk sigma of a correction within an episode, relative to its
            kinematic sigma (dimensionless, > 0; default ``WALK_WITHIN``).

    Raises:
        ConfigError: ``n_contacts`` not a positive count, ``anchor_first_stance`` not a bool,
            ``walk_within`` not a finite positive number.
    """

    name = "foothold"
    constant = False
    per_episode = True
    """Per-step unknowns, but constant over each contact episode (the diagnosis's second look
    leaves them be: they cannot follow whatever the model misses, as a random-walk wrench can)."""
    unit = "m, rad"
    what = "foothold error"
    hint = ("shift the weight between the contacts, or step: a foothold error is a deflection that stays with "
            "its contact episode whatever the load, while a bias, a CoM offset or a stiffness error follows "
            "the motion")
    plausible_position = 0.05
    """m: a correction beyond this is no foothold error (the leg kinematics are not 5 cm off)."""
    plausible_rotation = 0.35
    """rad (20 deg): a correction beyond this is no foothold error."""

    def __init__(self, n_contacts: int = 2, prior: FootholdPrior | None = None, *,
                 anchor_first_stance: bool = False, walk_within: float = WALK_WITHIN):
        try:
            nc = int(n_contacts)
        except (TypeError, ValueError):
            nc = 0
        if nc < 1 or isinstance(n_contacts, bool):
            raise ConfigError(f"foothold: n_contacts = {n_contacts!r}; expected a positive count of contacts "
                              "(default 2, a biped's feet)")
        check_bool("foothold", "anchor_first_stance", anchor_first_stance)
        check_positive("foothold", "walk_within", walk_within, "",
                       "a positive random-walk sigma relative to the kinematic sigma (default 1e-3)")
        self.nc = nc
        self.dim = 6 * self.nc
        self.anchor_first_stance = bool(anchor_first_stance)
        self.walk_within = float(walk_within)
        self._prior_given = prior is not None
        self.prior_config = FootholdPrior() if prior is None else prior
        self.labels = tuple(f"c{i} {kind}{a} [{u}]" for i in range(self.nc)
                            for kind, u in (("dp_", "m"), ("dr_", "rad")) for a in "xyz")
        per = ("the contact's fore-aft load moment and the base's pitch at rest on it",
               "the contact's sideways load moment and the base's roll at rest on it",
               "the contact's share of the load (weight shifts, steps)",
               "the base's roll while the contact bears load",
               "the base's pitch while the contact bears load",
               "twisting about the contact")
        self.excites = per * self.nc
        self._cache: tuple | None = None

    def constant_on(self, problem: ProblemView) -> bool:
        """True when no contact touches down in the recording: one episode per contact, the
        corrections constant over it (the identifiability table compares them as constants)."""
        return not touches_down(problem.active)

    def by_default(self, rec) -> str | None:
        """Why the diagnosis leaves this candidate out of its default catalogue on ``rec`` (None:
        it is in): without a touch-down the footholds' refit converges slowly (measured 519 s on a
        60 s standing sway, the nominal fit 16 s), and a standing robot's foothold errors are rare
        beside the walks' (named in ``candidates``, it is tested)."""
        if touches_down(rec.contact_active):
            return None
        return ("left out by default: no contact touches down in this recording (its refit is the costliest); "
                "name it in the candidates (--candidates foothold,...) to test a foothold error")

    def bind(self, rec, model) -> Footholds:
        """This effect for ``rec`` and ``model``: one correction per contact of the recording, the
        priors the effect was given or else the model's (the robot's ``[footholds]`` table); the
        first stance not anchored and the default ``walk_within`` whatever this effect's (the
        diagnosis' candidate must be able to find a shim under a foot standing from the first
        sample)."""
        prior = self.prior_config if self._prior_given else getattr(model, "foothold_prior", None)
        return Footholds(len(rec.contact_names), prior)

    def plausible(self, report: dict, problem: ProblemView) -> str | None:
        """None, or why the estimated corrections are no foothold error."""
        p, r = float(report.get("max_position_m", 0.0)), float(report.get("max_rotation_rad", 0.0))
        if p > self.plausible_position:
            return (f"a foothold {1e3 * p:.0f} mm off the kinematics' (beyond {1e3 * self.plausible_position:.0f} mm: "
                    "the leg kinematics are not that wrong)")
        if r > self.plausible_rotation:
            return (f"a foothold turned {1e3 * r:.0f} mrad from the kinematics' (beyond "
                    f"{1e3 * self.plausible_rotation:.0f} mrad)")
        return None

    # -- set-up ---------------------------------------------------------------------------------
    def _setup(self, problem: ProblemView):
        """Plane, kinematic whiteners and episode starts of ``problem`` (cached per problem)."""
        if self._cache is not None and self._cache[0] is problem:
            return self._cache[1]
        if int(problem.nc) != self.nc:
            raise ConfigError(f"foothold: made for {self.nc} contacts, the recording has {int(problem.nc)}; "
                              "make it with n_contacts = the recording's contacts (or let the diagnosis bind it)")
        cfg = self.prior_config
        active = np.asarray(problem.active, dtype=bool)
        rest_p = np.asarray(problem.rest_p, dtype=float)
        if cfg.terrain == "plane":
            n = np.asarray(cfg.normal, dtype=float)
            h = float(cfg.height) / float(np.linalg.norm(n))
            n = n / np.linalg.norm(n)
        else:
            n = np.array([0.0, 0.0, 1.0])
            on = active[0]
            h = float(np.mean(rest_p[0, on, 2])) if on.any() else 0.0
        # tangent axes of the plane
        a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u1 = np.cross(n, a)
        u1 /= np.linalg.norm(u1)
        u2 = np.cross(n, u1)
        cov_p, cov_r = cfg.kinematic_sigma(n)
        sig0 = np.concatenate([np.sqrt(np.diag(cov_p)), np.sqrt(np.diag(cov_r))])
        info = {"normal": n, "height": h, "tangent": np.stack([u1, u2]),
                "Lp": np.linalg.inv(np.linalg.cholesky(cov_p)), "Lr": np.linalg.inv(np.linalg.cholesky(cov_r)),
                "sigma0": np.tile(sig0, self.nc), "starts": episode_starts(active)}
        self._cache = (problem, info)
        return info

    # -- the Effect protocol --------------------------------------------------------------------
    def prior(self, problem: ProblemView):
        """Zero mean (6 C,) and sigmas (6 C,): the kinematic sigmas (per axis of the world, diagonal
        of the covariances), but ``GAUGE`` times them for the horizontal position and yaw of the
        contacts in force at the first sample: they define where the world is (a common
        horizontal shift or yaw of every foothold and of the flexibility changes no measurement),
        and a gauge held only loosely leaves the batch smoother's Gauss-Newton steps wandering
        along it.  With ``anchor_first_stance`` their height and tilt get ``GAUGE`` times the
        kinematic sigmas too (the first stance soles, flat on the floor, define the local frame)."""
        sigma = self._setup(problem)["sigma0"].copy()
        anchored = [0, 1, 2, 3, 4, 5] if self.anchor_first_stance else [0, 1, 5]
        for i in np.flatnonzero(np.asarray(problem.active, dtype=bool)[0]):
            sigma[[6 * i + j for j in anchored]] *= GAUGE
        return np.zeros(self.dim), sigma

    def kinematic_sigmas(self, problem: ProblemView) -> np.ndarray:
        """(6 C,) the kinematic sigmas per unknown (world axes): the scale of the priors and walks."""
        return self._setup(problem)["sigma0"].copy()

    def random_walk_sigma(self, problem: ProblemView):
        """(N - 1, 6 C): ``walk_within`` times the kinematic sigmas within an episode and through
        the swing, ``WALK_CUT`` times them at a touch-down."""
        info = self._setup(problem)
        s0 = info["sigma0"]
        starts = info["starts"][1:]  # transition k-1 -> k cut where contact i starts at k
        cut = np.repeat(starts, 6, axis=1)
        return np.where(cut, WALK_CUT * s0, self.walk_within * s0)

    def rest(self, problem: ProblemView, steps, e):
        """Corrected rest placements ``p_r'`` (n, C, 3), ``R_r'`` (n, C, 3, 3) and the left
        Jacobians ``J_l(dr)`` (n, C, 3, 3) of the rotation corrections."""
        e = np.asarray(e, dtype=float).reshape(len(steps), self.nc, 6)
        p = np.asarray(problem.rest_p, dtype=float)[steps] + e[:, :, :3]
        dr = e[:, :, 3:]
        R = np.einsum("ncij,ncjk->ncik", _exp_all(dr), np.asarray(problem.rest_R, dtype=float)[steps])
        return p, R, _jl_all(dr)

    def residual_terms(self, family, problem: ProblemView, steps, R, q, W, e):
        if family != "contact":
            return None
        steps = np.asarray(steps)
        n, nc = len(steps), self.nc
        c = np.ascontiguousarray
        p1, R1, Jl = self.rest(problem, steps, e)
        active = c(np.asarray(problem.active)[steps])
        args = (c(R, dtype=float), c(q, dtype=float), np.zeros((n, nc, 6)), active,
                c(np.asarray(problem.contact_p)[steps], dtype=float),
                c(np.asarray(problem.contact_R)[steps], dtype=float))
        K = (c(problem.K_fs), c(problem.K_fd), c(problem.K_ts), c(problem.K_td), c(problem.beta), c(problem.iso))
        r0 = np.empty((n, nc, 6))
        J0 = np.empty((n, nc, 6, core.STATE_DIM))
        core.contact_all(*args, c(np.asarray(problem.rest_p, dtype=float)[steps]),
                         c(np.asarray(problem.rest_R, dtype=float)[steps]), *K, r0, J0, np.empty((0, nc, 6, 6)))
        r1 = np.empty((n, nc, 6))
        J1 = np.empty((n, nc, 6, core.STATE_DIM))
        Jr = np.empty((n, nc, 6, 6))
        core.contact_all(*args, c(p1), c(R1), *K, r1, J1, Jr)
        dr_de = np.zeros((n, nc, 6, self.dim))
        for i in range(nc):
            dr_de[:, i, :, 6 * i:6 * i + 3] = Jr[:, i, :, :3]
            dr_de[:, i, :, 6 * i + 3:6 * i + 6] = Jr[:, i, :, 3:] @ Jl[:, i]
        return r1 - r0, J1 - J0, dr_de

    def factors(self, problem: ProblemView, steps, R, q, e) -> dict:
        """The effect's own factors on ``steps``: ``name -> (r (n, m), dr_ds (n, m, 18),
        dr_de (n, m, dim), weight (n,))``, residuals already whitened, ``weight`` 1 where the factor
        exists and 0 elsewhere (rows to drop).

        ``kinematics/i`` (6 rows): the spring deflection ``(s, Omega)`` of contact ``i`` at its
        touch-down, whitened by the kinematic covariances; ``ground/i`` (3 rows): height and tilt
        of its corrected rest placement against the floor plane, at every episode start (step 0
        included).
        """
        info = self._setup(problem)
        steps = np.asarray(steps)
        n, nc = len(steps), self.nc
        R = np.asarray(R, dtype=float)
        t = np.asarray(q, dtype=float)[:, :3]
        p1, R1, Jl = self.rest(problem, steps, e)
        starts = info["starts"][steps]
        active = np.asarray(problem.active, dtype=bool)[steps]
        first = np.zeros((n, nc), dtype=bool)
        if steps[0] == 0:
            first[0] = active[0]
        out: dict = {}
        Lp, Lr = info["Lp"], info["Lr"]
        cp = np.asarray(problem.contact_p, dtype=float)[steps]
        cR = np.asarray(problem.contact_R, dtype=float)[steps]
        for i in range(nc):
            cols = slice(6 * i, 6 * i + 6)
            # kinematics at the touch-down: zero deflection
            k = np.flatnonzero(starts[:, i])
            r = np.zeros((n, 6))
            Js = np.zeros((n, 6, core.STATE_DIM))
            Je = np.zeros((n, 6, self.dim))
            if k.size:
                Rp = np.einsum("nij,nj->ni", R[k], cp[k, i])
                s = Rp + t[k] - p1[k, i]
                M = R[k] @ cR[k, i] @ np.swapaxes(R1[k, i], 1, 2)
                Om = _log_all(M)
                Jli = _jl_all(Om, inverse=True)
                r[k, :3] = s @ Lp.T
                r[k, 3:] = Om @ Lr.T
                Js[k, :3, 0:3] = Lp @ -_skew(Rp)
                Js[k, :3, 3:6] = Lp
                Js[k, 3:, 0:3] = Lr @ Jli
                Je[k, :3, cols.start:cols.start + 3] = -Lp
                Je[k, 3:, cols.start + 3:cols.stop] = -Lr @ Jli @ M @ Jl[k, i]
            out[f"kinematics/{i}"] = (r, Js, Je, starts[:, i].astype(float))
            if self.prior_config.terrain == "none":
                continue
            # ground at every episode start
            g = starts[:, i] | first[:, i]
            k = np.flatnonzero(g)
            cfg = self.prior_config
            nrm, h, T = info["normal"], info["height"], info["tangent"]
            r = np.zeros((n, 3))
            Js = np.zeros((n, 3, core.STATE_DIM))
            Je = np.zeros((n, 3, self.dim))
            if k.size:
                z = R1[k, i][:, :, 2]
                r[k, 0] = (p1[k, i] @ nrm - h) / cfg.ground_sigma_height
                r[k, 1:] = z @ T.T / cfg.ground_sigma_tilt
                Je[k, 0, cols.start:cols.start + 3] = nrm / cfg.ground_sigma_height
                Je[k, 1:, cols.start + 3:cols.stop] = (T @ -_skew(z)) @ Jl[k, i] / cfg.ground_sigma_tilt
            out[f"ground/{i}"] = (r, Js, Je, g.astype(float))
        return out

    def report(self, values, cov, t=None) -> dict:
        """Per contact: the correction of every episode (at its first step) and the largest."""
        v = np.asarray(values, dtype=float)
        if self._cache is None:
            return {"value": v[-1].tolist(), "unit": self.unit, "labels": list(self.labels), "summary": "footholds"}
        info = self._cache[1]
        starts = info["starts"].copy()
        active = np.asarray(self._cache[0].active, dtype=bool)
        starts[0] = active[0]
        episodes = []
        worst = [0.0, 0.0]
        for k, i in zip(*np.nonzero(starts)):
            e = v[k, 6 * i:6 * i + 6]
            std = (np.sqrt(np.maximum(np.diagonal(np.asarray(cov)[k])[6 * i:6 * i + 6], 0.0)).tolist()
                   if cov is not None else None)
            episodes.append({"step": int(k), "t": float(t[k]) if t is not None else None, "contact": int(i),
                             "dp_m": e[:3].tolist(), "dr_rad": e[3:].tolist(), "std": std})
            worst = [max(worst[0], float(np.linalg.norm(e[:3]))), max(worst[1], float(np.linalg.norm(e[3:])))]
        summary = (f"{len(episodes)} footholds estimated; largest correction {1e3 * worst[0]:.1f} mm, "
                   f"{1e3 * worst[1]:.1f} mrad")
        if episodes:  # the episode moved most, its height and tilt (what the forces and the tilt feel)
            cfg = self.prior_config  # in kinematic sigmas: millimetres and degrees weighed alike
            big = max(episodes, key=lambda ep: float(np.linalg.norm(ep["dp_m"])) / cfg.kinematics_sigma_position
                      + float(np.linalg.norm(ep["dr_rad"])) / cfg.kinematics_sigma_tilt)
            sd = big["std"] or [math.nan] * 6
            when = f" at {big['t']:.2f} s" if big["t"] is not None else ""
            summary += (f" (contact {big['contact']}{when}: height {1e3 * big['dp_m'][2]:+.1f} ± {1e3 * sd[2]:.1f} mm, "
                        f"roll {1e3 * big['dr_rad'][0]:+.1f} ± {1e3 * sd[3]:.1f} mrad, "
                        f"pitch {1e3 * big['dr_rad'][1]:+.1f} ± {1e3 * sd[4]:.1f} mrad)")
        return {"value": v[-1].tolist(), "unit": self.unit, "labels": list(self.labels), "episodes": episodes,
                "max_position_m": worst[0], "max_rotation_rad": worst[1], "summary": summary}
