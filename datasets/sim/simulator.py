"""Ground-truth simulator, independent of the hand-written equations of :mod:`flexforce.factors.physics`.

The robot is a pinocchio free-flyer multibody.  Its joints follow a prescribed trajectory (stiff
position control: the joint motion is imposed, whatever the torque); the only free motion is the
6-D flexibility.  Each contact in force is held to its rest placement by a 6-D spring-damper
acting on the contact frame's actual placement (forward kinematics), and the free-flyer rows of
the multibody dynamics (pinocchio's CRBA and RNEA)::

    M_bb a_b + (M_bj qdd_j + h_b) = sum_c J_c,b^T f_c + J_e,b^T f_e

give the base acceleration.  The flexibility is the rigid transform from the robot's own belief
(the local frame, where the contacts sit at their rest placements) to the world:
``world_T_base = flex * local_T_base``.  The state (flexibility pose and velocity) is integrated
with the classical 4th-order Runge-Kutta scheme at ``sim_rate`` (1 kHz by default) and sampled at
``rate`` (200 Hz by default).

The local-frame motion is computed exactly (inverse kinematics with analytic velocities and
accelerations) at the sample instants and interpolated between them with quintic Hermite
polynomials, which match position, velocity and acceleration at every sample.

The simulator is the truth the estimators are measured against, so it shares none of their code:
its SO(3) is pinocchio's (``exp3``, ``log3``), its contact springs (:class:`Spring`) and centre of
pressure (:func:`center_of_pressure`) are its own, checked by the tests against pinocchio's
statics; its ambient disturbance, its sensor noise and its touch-down rule are parameters of the
scenario (:class:`flexforce.datasets.sim.scenario.Ambient`, ``[imu_noise]``, ``touchdown``).

Touch-down.  A contact's spring acts between the contact frame's actual world placement and a
rest placement (the foothold) fixed for the contact episode; ``meta["contact_episodes"]`` lists
every episode with its foothold in the world.  Three conventions (``Scenario.touchdown``):

- ``"floor"`` (the default): the floor is the plane of the feet at the start.  A swinging foot
  touches it at the first integration instant of its descent (second half of the swing) at which
  it reaches the floor, or at its scheduled landing at the latest; its foothold is where it
  touches, flat on the floor with the foot's heading.  The spring starts with no deflection but
  the sole's tilt (the body's tilt at that instant, taken by the ankle's rotational spring): no
  force jump beyond the damping of the foot's landing speed.  A foot that touches before its
  scheduled landing (the stance leg sinks and the body tilts in single support: on Romeo's
  ``walk-short`` the feet touch ~0.25 s early, 21-26 mm above their planned landing in the local
  frame) stops there, as a walking controller stops a foot on contact (:class:`Stop`): from the
  touch its local motion brakes to rest in ``TOUCHDOWN_STOP`` (20 ms, about a millimetre further)
  and the rest of its swing is dropped; the leg then extends by the descent it skipped, in
  ``TOUCHDOWN_LEVEL`` (0.4 s, minimum jerk) -- a gradual weight transfer that brings the feet
  level again in the robot's belief, as they are on the floor (without it, each step's offset
  carries into the next: measured on ``walk-short``, footholds up to 30 mm above and 45 mm behind
  their plan, the flexibility sinking 62 mm); the foot's next swing makes up the travel it
  skipped (an early touch-down leaves up to a few centimetres of it; the last step of a walk
  stays short).  Pelvis, CoM, joints and the other contacts follow the plan unchanged.  Before,
  the plan drove the foot on through the rest of its swing: ~2 cm into the spring in ~0.25 s,
  0.57-0.66 mg on the landing foot within 0.3 s (0.35-0.43 mg with the stop and levelling).  A
  lifting foot leaves the floor when its spring no longer pushes (vertical force <= 0), or a
  quarter into its swing at the latest (the episode keeps the force it was torn off with).  The
  recording's contact flags are the truth's, as a perfect contact detector would give them.
- ``"relaxed"``: at the scheduled landing, wherever the foot is in the world, sole tilt included:
  the spring starts fully unloaded.  Each foothold inherits the body's tilt and sinking at its
  touch-down, so an open-loop walk drifts (measured on 4 steps of Romeo with 0.7 s weight
  shifts: footholds 12, -14, 44 and -106 mm off the floor, body tilt up to 63 deg); kept for
  single steps.
- ``"deflected"``: the rest is the contact's placement in the local frame read as a world
  placement: the landing foot is pulled from where it is to where the robot believes it is, a
  force step of ``K_fs (world - local placement)`` -- the convention of a model that freezes
  footholds from its own belief, kept as the mismatched case.

The recording's contact placements are always the local-frame ones, the robot's belief: where its
legs hold each contact in force, the forward kinematics of the recorded pelvis pose and joints --
its planned landing, or while a foot brakes, levels or lifts (``floor``), where the leg puts it.
``meta["contact_episodes"]`` gives, for an early touch-down, how far from its planned landing the
foot came to rest (``local_off_plan``) and where it ends once levelled (``levelled_off_plan``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin
from scipy import signal

from flexforce.datasets.quantities import ContactParams, matrix3
from flexforce.datasets.recording import Recording, Truth
from flexforce.datasets.robot import ROBOTS_DIR, FtNoise, ImuNoise, RobotConfig, RobotModel
from flexforce.datasets.sim.effects import HiddenEffect, SpringTerms, grouped, parse_effects
from flexforce.datasets.sim.scenario import Ambient, Scenario, minjerk
from flexforce.errors import ConfigError, ModelError

E_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Spring(ContactParams):
    """The simulated 6-D spring-damper of one contact: the parameters of a
    :class:`~flexforce.datasets.quantities.ContactParams` (matrices in the contact frame, cubic
    coefficients) with the simulator's own law (:meth:`wrench`).

    Force on the robot ``F = -K_fs s (1 + beta_f |s|^2) - K_fd v``, torque about the contact point
    ``T = -K_ts Omega (1 + beta_t |Omega|^2) - K_td w``, with ``s`` (m) and ``Omega = log3(R_c
    R_rest^T)`` (rad, pinocchio's log) the displacement of the contact frame from its rest
    placement, ``v`` and ``w`` the contact frame's world-aligned linear and angular velocity, and
    every matrix rotated into the world with the contact frame's actual orientation.
    """

    @classmethod
    def from_stiffness(cls, stiffness) -> Spring:
        """From a robot configuration's :class:`~flexforce.datasets.robot.Stiffness` (scalars are
        isotropic, 3-vectors diagonal in the contact frame, 3x3 full)."""
        def mat(x, key):
            a = matrix3(x)
            if a is None:
                raise ConfigError(f"stiffness {key} = {x!r}: expected a scalar, 3 values or a 3x3 matrix")
            return a
        return cls(mat(stiffness.k_fs, "k_fs"), mat(stiffness.k_fd, "k_fd"), mat(stiffness.k_ts, "k_ts"),
                   mat(stiffness.k_td, "k_td"))

    def wrench(self, world_M_contact: pin.SE3, world_M_rest: pin.SE3, velocity: pin.Motion) -> np.ndarray:
        """(6,) force (N) and torque about the contact point (N m), world axes."""
        Rc = world_M_contact.rotation
        s = world_M_contact.translation - world_M_rest.translation
        Omega = pin.log3(Rc @ world_M_rest.rotation.T)
        F = (-(Rc @ (self.K_fs @ (Rc.T @ s))) * (1.0 + self.beta_f * (s @ s))
             - Rc @ (self.K_fd @ (Rc.T @ velocity.linear)))
        T = (-(Rc @ (self.K_ts @ (Rc.T @ Omega))) * (1.0 + self.beta_t * (Omega @ Omega))
             - Rc @ (self.K_td @ (Rc.T @ velocity.angular)))
        return np.concatenate([F, T])


def center_of_pressure(wrench: np.ndarray, z0: float = 0.0) -> np.ndarray:
    """Point of the plane ``z = z0`` where the total contact wrench (F, T about the world origin)
    has no horizontal moment: the CoP, m.  NaN when the vertical force is not positive."""
    F, T = wrench[:3], wrench[3:]
    if not F[2] > 1e-6:
        return np.array([np.nan, np.nan, z0])
    return np.array([(z0 * F[0] - T[1]) / F[2], (T[0] + z0 * F[1]) / F[2], z0])


def _cross(a, b):
    # np.cross costs ~50 us on 3-vectors (axis handling); this costs ~1 us.
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


# ----------------------------------------------------------------------------------------------
# Local-frame motion
# ----------------------------------------------------------------------------------------------


@dataclass
class LocalSample:
    """The robot in its local frame at one instant: pinocchio q, v, a (free-flyer body twist)."""

    q: np.ndarray
    v: np.ndarray
    a: np.ndarray
    active: np.ndarray
    """(C,) bool, contacts in force."""


TOUCHDOWN_STOP = 0.02
"""s: how long a landing foot that touched the floor before its scheduled landing takes to come to
rest in the local frame (``touchdown = "floor"``, see :class:`Stop`)."""
TOUCHDOWN_LEVEL = 0.4
"""s: how long the landed leg then takes to extend by the descent it skipped (:class:`Stop`)."""


@dataclass(frozen=True)
class Stop:
    """A landing foot that touched the floor early coming to rest in the local frame.

    From the touch instant ``t0`` the foot's displacement leaves its swing with the swing's
    velocity ``v0`` and acceleration ``a0`` and brakes to rest in ``duration``: the velocity is
    the cubic Hermite blend from (``v0``, ``a0``) to (0, 0), the displacement its integral (a
    quartic, continuous in position, velocity and acceleration).  The foot ends
    ``duration (v0 / 2 + a0 duration / 12)`` past where it touched (about a millimetre).  The
    rest of the swing is dropped; then the leg extends by ``level`` (the skipped descent,
    vertical) in ``level_duration`` (minimum jerk): in the world a gradual weight transfer that
    brings the feet level again in the robot's belief, as they are on the floor.  The skipped
    horizontal travel is made up by the foot's next swing (:meth:`LocalMotion.stop`).
    """

    t0: float
    duration: float
    d0: np.ndarray
    v0: np.ndarray
    a0: np.ndarray
    level: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    level_duration: float = TOUCHDOWN_LEVEL

    @property
    def end(self) -> float:
        """Instant the foot is at rest (s)."""
        return self.t0 + self.duration

    @property
    def rest(self) -> np.ndarray:
        """Displacement at rest, before the levelling (m)."""
        T = self.duration
        return self.d0 + T * (0.5 * self.v0 + self.a0 * T / 12.0)

    @property
    def levelled(self) -> float:
        """Instant the levelling ends (s)."""
        return self.end + self.level_duration

    def __call__(self, t: float):
        """Displacement of the contact from its initial placement, with derivatives (as a swing)."""
        T = self.duration
        s = min(max((t - self.t0) / T, 0.0), 1.0)
        s2, s3 = s * s, s**3
        d = self.d0 + T * (self.v0 * (0.5 * s2 * s2 - s3 + s)
                           + self.a0 * T * (0.25 * s2 * s2 - 2.0 * s3 / 3.0 + 0.5 * s2))
        v = self.v0 * (2.0 * s3 - 3.0 * s2 + 1.0) + self.a0 * T * (s3 - 2.0 * s2 + s)
        a = (self.v0 * (6.0 * s2 - 6.0 * s) + self.a0 * T * (3.0 * s2 - 4.0 * s + 1.0)) / T
        if t > self.end and self.level_duration > 0.0:
            m, dm, ddm = minjerk((t - self.end) / self.level_duration)
            d = d + self.level * m
            v = v + self.level * dm / self.level_duration
            a = a + self.level * ddm / self.level_duration**2
        return d, v, a


class LocalMotion:
    """The prescribed motion of the robot in its local frame.

    The pelvis follows the scenario's ``[[base]]`` segments (translation only, orientation of the
    reference posture), the upper-body joints its ``[[joint]]`` segments, and the leg joints are
    solved by inverse kinematics so that every contact stays at its placement -- its rest
    placement while in contact, the ``[[swing]]`` trajectory in the air.
    """

    def __init__(self, robot: RobotModel, scenario: Scenario):
        self.robot = robot
        self.model = robot.model
        self.data = self.model.createData()
        model = self.model
        self.q_ref = robot.q_reference.copy()
        pin.framesForwardKinematics(model, self.data, self.q_ref)
        self.fids = robot.contact_frame_ids
        self.placements0 = [self.data.oMf[f].copy() for f in self.fids]
        # Leg chains: the joints supporting each contact frame (free-flyer excluded).
        self.leg_q, self.leg_v = [], []
        for fid in self.fids:
            chain = [j for j in model.supports[model.frames[fid].parentJoint] if j > 1]
            if sum(model.joints[j].nv for j in chain) != 6:
                raise ConfigError(f"contact frame '{model.frames[fid].name}' must be carried by a 6-joint leg "
                                  f"for the simulator's inverse kinematics; its chain has "
                                  f"{sum(model.joints[j].nv for j in chain)} degrees of freedom")
            self.leg_q.append(np.array([model.joints[j].idx_q for j in chain]))
            self.leg_v.append(np.array([model.joints[j].idx_v for j in chain]))
        names = robot.contact_names
        self.swings = scenario.swings()
        for sw in self.swings:
            if sw.contact not in names:
                raise ConfigError(f"swing names contact '{sw.contact}'; robot '{robot.name}' has {list(names)}")
        self.swing_index = [names.index(sw.contact) for sw in self.swings]
        self.stops: dict[int, Stop] = {}
        """Per swing (index in ``swings``) that touched the floor early, its :class:`Stop`."""
        self.joint_segments = []
        for name, seg in scenario.segments(scenario.joint, robot.name, 1):
            if not model.existJointName(name):
                raise ConfigError(f"scenario '{scenario.name}' moves joint '{name}', unknown to robot '{robot.name}'")
            jid = model.getJointId(name)
            iq, iv = model.joints[jid].idx_q, model.joints[jid].idx_v
            if any(iv in lv for lv in self.leg_v):
                raise ConfigError(f"joint '{name}' belongs to a leg; legs follow the contacts, move the base instead")
            self.joint_segments.append((iq, iv, seg))
        self.base_segments = []
        self._q_guess = self.q_ref.copy()
        self._com_maps = None
        for item in self._resolve_toward(scenario.base_items()):
            if item.get("horizontal"):
                item = self._walk_shift(item)
            for target, seg in scenario.segments([item], robot.name, 3):
                if target in ("com", "com-horizontal"):
                    full, horizontal = self._com_map()
                    value = (full if target == "com" else horizontal) @ seg.value
                    seg = type(seg)(seg.kind, seg.start, seg.duration, value, seg.frequency, seg.ramp)
                elif target not in (None, "base"):
                    raise ConfigError(f"base segment target must be 'base' or 'com', got '{target}'")
                self.base_segments.append(seg)
        self._q_guess = self.q_ref.copy()

    def _com_map(self):
        """Pelvis translation per CoM translation with the contacts held: the full 3x3 map, and the
        horizontal one that keeps the pelvis's height."""
        if self._com_maps is None:
            J = self._com_jacobian()
            horizontal = np.zeros((3, 3))
            horizontal[:2, :2] = np.linalg.inv(J[:2, :2])
            self._com_maps = (np.linalg.inv(J), horizontal)
        return self._com_maps

    def _walk_shift(self, item: dict) -> dict:
        """A walk's weight shift: the CoM moves horizontally by ``fraction`` of the way from where
        it actually is at the shift's start (the motion so far, exact) to the stance foot (or the
        middle of the feet); the pelvis keeps its height.

        Walking carries the feet along, so a map linearised with the feet held drifts with the
        distance walked (measured on Romeo with the full map and estimated CoM: the pelvis 15 mm
        higher and 3 cm ahead of the CoM after 0.6 m, the legs out of reach at 0.7 m); starting
        each shift from the actual CoM keeps the error to one shift's linearisation.
        """
        item = dict(item)
        toward = item.pop("toward")
        fraction = float(item.pop("fraction", 1.0))
        item.pop("horizontal")
        start = float(item.get("start", 0.0))
        q = self.sample(start).q
        com = pin.centerOfMass(self.model, self.data, q)
        goal = self._toward_goal(toward, start)
        item.update(offset=[fraction * (goal[0] - com[0]), fraction * (goal[1] - com[1]), 0.0],
                    target="com-horizontal", kind="step")
        return item

    # ------------------------------------------------------------------------------------------
    def _toward_goal(self, toward: str, start: float) -> np.ndarray:
        """Where a CoM segment ``toward = CONTACT|"middle"`` heads: that contact's placement, or
        the middle of all contacts, at the segment's start (local frame, m)."""
        placements = self.contact_targets(start)[0]
        names = self.robot.contact_names
        if toward == "middle":
            return np.mean([M.translation for M in placements], axis=0)
        if toward in names:
            return placements[names.index(toward)].translation
        raise ConfigError(f"base segment toward '{toward}': expected 'middle' or one of {list(names)}")

    def _resolve_toward(self, items: list[dict]) -> list[dict]:
        """Turn ``toward = CONTACT|"middle"`` (with ``fraction``) into a CoM offset.

        The CoM moves by ``fraction`` of the horizontal way from where the previous segments left
        it to the contact's placement (or the middle of all contacts) at the segment's start.
        """
        out = []
        com = pin.centerOfMass(self.model, self.data, self.q_ref).copy()
        for item in sorted(items, key=lambda it: it.get("start", 0.0)):
            item = dict(item)
            if item.get("horizontal"):  # resolved from the actual motion (_walk_shift)
                out.append(item)
                continue
            toward = item.pop("toward", None)
            fraction = float(item.pop("fraction", 1.0))
            if toward is not None:
                goal = self._toward_goal(toward, float(item.get("start", 0.0)))
                item["offset"] = [fraction * (goal[0] - com[0]), fraction * (goal[1] - com[1]), 0.0]
                item["target"] = "com"
                item["kind"] = "step"
            if item.get("kind", "step") == "step" and item.get("target") == "com" and "offset" in item:
                com = com + np.asarray(item["offset"], dtype=float)
            out.append(item)
        return out

    def _com_jacobian(self) -> np.ndarray:
        """d CoM / d pelvis translation with the contacts held (3x3, by central differences)."""
        J = np.zeros((3, 3))
        h = 1e-4
        targets = self.placements0
        for i in range(3):
            cols = []
            for sgn in (1.0, -1.0):
                q = self.q_ref.copy()
                q[i] += sgn * h
                q = self._ik(q, targets)
                cols.append(pin.centerOfMass(self.model, self.data, q))
            J[:, i] = (cols[0] - cols[1]) / (2 * h)
        return J

    def _ik(self, q: np.ndarray, targets) -> np.ndarray:
        model, data = self.model, self.data
        for ci, fid in enumerate(self.fids):
            lq, lv = self.leg_q[ci], self.leg_v[ci]
            for _ in range(50):
                pin.forwardKinematics(model, data, q)
                M = pin.updateFramePlacement(model, data, fid)
                err = pin.log6(M.actInv(targets[ci])).vector
                if np.max(np.abs(err)) < 1e-13:
                    break
                J = pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL)[:, lv]
                q[lq] += np.linalg.solve(J, err)
            else:
                raise ModelError(f"inverse kinematics of contact {ci} did not converge "
                                 f"(residual {np.abs(err).max():.2e}); "
                                 "the scenario asks for an unreachable placement")
        return q

    def swing_at(self, ci: int, t: float):
        """The swing of contact ``ci`` under way at ``t`` (lift <= t < land), or None."""
        for i, sw in zip(self.swing_index, self.swings):
            if i == ci and sw.lift <= t < sw.land:
                return sw
        return None

    def stop(self, ci: int, t0: float, duration: float = TOUCHDOWN_STOP,
             level_duration: float = TOUCHDOWN_LEVEL) -> Stop:
        """Contact ``ci``, swinging at ``t0``, touched the floor: from ``t0`` the rest of its swing
        is replaced by a :class:`Stop` (brake, then extend the leg by the skipped descent), and its
        next swing, if any, also makes up the skipped horizontal travel, so that it lands where
        planned.  The rest of the motion (pelvis, CoM, joints, other contacts) is unchanged."""
        for j, (i, sw) in enumerate(zip(self.swing_index, self.swings)):
            if i == ci and sw.lift <= t0 < sw.land:
                d0, v0, a0 = sw(t0)
                stop = Stop(float(t0), float(duration), d0, v0, a0, np.zeros(3), float(level_duration))
                short = sw(sw.land)[0] - stop(stop.end)[0]
                stop = dataclasses.replace(stop, level=short * E_Z)
                self.stops[j] = stop
                later = [jj for jj, (ii, s2) in enumerate(zip(self.swing_index, self.swings))
                         if ii == ci and s2.lift >= sw.land]
                if later:
                    jn = min(later, key=lambda jj: self.swings[jj].lift)
                    nxt = self.swings[jn]
                    if nxt.lift < stop.levelled:
                        raise ModelError(f"contact {ci} lifts at {nxt.lift} s, before its leg has levelled "
                                         f"after touching the floor at {t0:.3f} s ({stop.levelled:.3f} s)")
                    self.swings[jn] = dataclasses.replace(
                        nxt, displacement=nxt.displacement + np.array([short[0], short[1], 0.0]))
                return stop
        raise ValueError(f"contact {ci} is not swinging at {t0} s")

    def contact_targets(self, t: float):
        """Per contact: placement (SE3), LWA velocity and classical acceleration (6,), active flag
        (False while the foot swings or, after an early touch, comes to rest)."""
        n = len(self.fids)
        disp = [np.zeros(3) for _ in range(n)]
        vel = [np.zeros(3) for _ in range(n)]
        acc = [np.zeros(3) for _ in range(n)]
        active = np.ones(n, dtype=bool)
        for j, (ci, sw) in enumerate(zip(self.swing_index, self.swings)):
            stop = self.stops.get(j)
            if stop is not None and t >= stop.t0:
                d, dv, da = stop(t)
                disp[ci] = disp[ci] + d
                vel[ci] = vel[ci] + dv
                acc[ci] = acc[ci] + da
                if t < stop.end:
                    active[ci] = False
                continue
            d, dv, da = sw(min(max(t, sw.lift), sw.land))
            disp[ci] = disp[ci] + d
            if sw.lift <= t < sw.land:
                active[ci] = False
                vel[ci] = vel[ci] + dv
                acc[ci] = acc[ci] + da
        placements = [pin.SE3(M0.rotation, M0.translation + d) for M0, d in zip(self.placements0, disp)]
        v6 = [np.concatenate([v, np.zeros(3)]) for v in vel]
        a6 = [np.concatenate([a, np.zeros(3)]) for a in acc]
        return placements, v6, a6, active

    def sample(self, t: float) -> LocalSample:
        """The exact local-frame q, v, a at time ``t`` (s)."""
        model, data = self.model, self.data
        q = self._q_guess.copy()
        v = np.zeros(model.nv)
        a = np.zeros(model.nv)
        p, dp, ddp = self.q_ref[:3].copy(), np.zeros(3), np.zeros(3)
        for seg in self.base_segments:
            x, dx, ddx = seg(t)
            p += x
            dp += dx
            ddp += ddx
        q[:3] = p
        q[3:7] = self.q_ref[3:7]
        R_l = pin.Quaternion(self.q_ref[3:7]).matrix()
        v[:3] = R_l.T @ dp  # body twist; the pelvis does not rotate in the local frame
        a[:3] = R_l.T @ ddp
        for iq, iv, seg in self.joint_segments:
            x, dx, ddx = seg(t)
            q[iq] = self.q_ref[iq] + x[0]
            v[iv] = dx[0]
            a[iv] = ddx[0]
        placements, vt, at, active = self.contact_targets(t)
        q = self._ik(q, placements)
        self._q_guess = q.copy()
        pin.forwardKinematics(model, data, q, v)
        Js = []
        for ci, fid in enumerate(self.fids):
            J = pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL_WORLD_ALIGNED)[:, self.leg_v[ci]]
            Js.append(J)
        pin.forwardKinematics(model, data, q, v)
        for ci, fid in enumerate(self.fids):
            part = pin.getFrameVelocity(model, data, fid, pin.LOCAL_WORLD_ALIGNED).vector
            v[self.leg_v[ci]] = np.linalg.solve(Js[ci], vt[ci] - part)
        pin.forwardKinematics(model, data, q, v, a)
        for ci, fid in enumerate(self.fids):
            part = pin.getFrameClassicalAcceleration(model, data, fid, pin.LOCAL_WORLD_ALIGNED).vector
            a[self.leg_v[ci]] = np.linalg.solve(Js[ci], at[ci] - part)
        return LocalSample(q, v, a, active)


def _hermite5(s: float, h: float):
    """Quintic Hermite basis at s in [0, 1] for an interval of length h, with time derivatives.

    Returns three 6-vectors (value, d/dt, d2/dt2) of the weights of (y0, v0, a0, y1, v1, a1).
    """
    s2, s3, s4, s5 = s * s, s**3, s**4, s**5
    H = np.array([1 - 10 * s3 + 15 * s4 - 6 * s5, (s - 6 * s3 + 8 * s4 - 3 * s5) * h,
                  0.5 * (s2 - 3 * s3 + 3 * s4 - s5) * h * h, 10 * s3 - 15 * s4 + 6 * s5,
                  (-4 * s3 + 7 * s4 - 3 * s5) * h, 0.5 * (s3 - 2 * s4 + s5) * h * h])
    dH = np.array([-30 * s2 + 60 * s3 - 30 * s4, (1 - 18 * s2 + 32 * s3 - 15 * s4) * h,
                   0.5 * (2 * s - 9 * s2 + 12 * s3 - 5 * s4) * h * h, 30 * s2 - 60 * s3 + 30 * s4,
                   (-12 * s2 + 28 * s3 - 15 * s4) * h, 0.5 * (3 * s2 - 8 * s3 + 5 * s4) * h * h]) / h
    ddH = np.array([-60 * s + 180 * s2 - 120 * s3, (-36 * s + 96 * s2 - 60 * s3) * h,
                    0.5 * (2 - 18 * s + 36 * s2 - 20 * s3) * h * h, 60 * s - 180 * s2 + 120 * s3,
                    (-24 * s + 84 * s2 - 60 * s3) * h, 0.5 * (6 * s - 24 * s2 + 20 * s3) * h * h]) / (h * h)
    return H, dH, ddH


# ----------------------------------------------------------------------------------------------
# World dynamics
# ----------------------------------------------------------------------------------------------


def _quat_to_R(qw):
    w, x, y, z = qw
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _quat_rate(qw, w):
    """d/dt of a (w, x, y, z) quaternion under world angular velocity w: 0.5 (0, w) * q."""
    a, b, c, d = qw
    x, y, z = w
    return 0.5 * np.array([-x * b - y * c - z * d, x * a + y * d - z * c, -x * d + y * a + z * b,
                           x * c - y * b + z * a])


@dataclass
class WorldEval:
    """Result of one evaluation of the world dynamics."""

    dw: np.ndarray
    a: np.ndarray
    wrenches: np.ndarray
    """(C, 6) contact wrenches (F, T about the world origin)."""
    local_wrenches: np.ndarray
    """(C, 6) contact wrenches in the contact frame about its origin (what an F/T sensor reads)."""
    external: np.ndarray
    """(6,) external wrench of the hidden effects, about the world origin."""
    ambient: np.ndarray
    """(6,) ambient disturbance wrench, about the world origin."""
    q_w: np.ndarray
    v_w: np.ndarray
    a_w: np.ndarray


class Simulator:
    """Simulates a scenario on a robot and returns a :class:`Recording` with ground truth."""

    def __init__(self, scenario: Scenario | str, robot: RobotModel | RobotConfig | str | None = None,
                 noise: bool | None = None):
        if not isinstance(scenario, Scenario):
            scenario = Scenario.load(scenario)
        self.scenario = scenario
        if robot is None:
            robot = scenario.robot
        self.robot = robot if isinstance(robot, RobotModel) else RobotModel(robot)
        posture = scenario.posture.get(self.robot.name)
        if posture:  # the scenario's own reference posture for this robot
            cfg = dataclasses.replace(self.robot.config,
                                      reference_joints={**self.robot.config.reference_joints, **posture})
            self.robot = RobotModel(cfg)
        self.noise = scenario.noise if noise is None else noise
        self.effects: list[HiddenEffect] = parse_effects(scenario.effects)
        self._groups = grouped(self.effects)  # (effect class, its effects): the group hooks' calls
        cfg = self.robot.config
        # The simulated sensors: the robot configuration's noise unless the scenario says otherwise;
        # ``scale`` multiplies the white-noise levels (a sensor noisier than its data sheet).
        try:
            imu = {**cfg.imu_noise.__dict__, **{k: v for k, v in scenario.imu_noise.items() if k != "scale"}}
            ft = {**cfg.ft_noise.__dict__, **{k: v for k, v in scenario.ft_noise.items() if k != "scale"}}
            imu_scale, ft_scale = scenario.noise_scale("imu_noise"), scenario.noise_scale("ft_noise")
            imu["gyro_density"] = float(imu["gyro_density"]) * imu_scale
            imu["accel_density"] = float(imu["accel_density"]) * imu_scale
            ft = {k: float(v) * ft_scale for k, v in ft.items()}
            self.imu_noise = ImuNoise(**imu)
            self.ft_noise = FtNoise(**ft)
        except TypeError as err:
            raise ConfigError(f"scenario '{scenario.name}': bad noise override: {err}; "
                              f"known keys: {sorted(ImuNoise.__dataclass_fields__)} (imu_noise), "
                              f"{sorted(FtNoise.__dataclass_fields__)} (ft_noise), and scale") from err
        self.g = cfg.gravity
        self.motion = LocalMotion(self.robot, scenario)
        # The simulated robot: the nominal model, with the hidden mass-model error if any.
        self.sim_model = pin.Model(self.robot.model)
        self.sim_model.gravity = pin.Motion(np.array([0.0, 0.0, -self.g]), np.zeros(3))
        for cls, group in self._groups:
            cls.apply_to_model(self, group)
        self.sim_data = self.sim_model.createData()
        self.springs = self._true_springs()
        self.touchdown = scenario.touchdown
        # Ambient disturbance: a property of the scenario's world (Ambient), None when absent.
        self.ambient_spec = scenario.ambient_spec()
        self.ambient = None
        if self.noise and self.ambient_spec.enabled:
            self.ambient = self._ambient_levels(self.ambient_spec)
        self.ext_effects = [w for cls, group in self._groups for w in cls.external_wrenches(self, group)]
        self.ft_offset = self._ft_offsets()  # checked here, before a long run
        self.episodes: list[dict] = []
        """The contact episodes of the last :meth:`run` (``meta["contact_episodes"]``)."""

    # ------------------------------------------------------------------------------------------
    def _frame_of(self, link: str) -> int:
        model = self.sim_model
        if link == "@base":
            return model.getFrameId(model.names[1])  # the free-flyer joint's frame
        if link.startswith("@link:"):
            i = int(link.split(":")[1])
            return self.robot.link_frame_ids[i]
        if not model.existFrame(link):
            raise ConfigError(f"external wrench on unknown link '{link}' of robot '{self.robot.name}'")
        return model.getFrameId(link)

    def _delay_imu(self, times: np.ndarray, gyro: np.ndarray, accel: np.ndarray):
        """Hidden ``time-offset``: the readings stamped ``t`` are the simulated sensor's at ``t - delay``.

        The sensor's signal between the samples is its cubic spline through them (the samples are
        those of a smooth simulated motion; the spline's error is ``(omega dt)^4 / 384`` of the
        signal, below 1e-5 at 5 Hz and 200 Hz); before the start the robot is at rest (the first
        reading), after the end the last one is held."""
        delay = 0.0
        for cls, group in self._groups:
            delay += cls.imu_delay(group)
        if delay == 0.0:
            return gyro, accel
        from scipy.interpolate import CubicSpline

        at = np.clip(times - delay, times[0], times[-1])
        return CubicSpline(times, gyro, axis=0)(at), CubicSpline(times, accel, axis=0)(at)

    def _foothold_offsets(self, active) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Contact index -> (position m, rotation vector rad, world axes) by which the true rest
        placement of a contact standing at the start is off its nominal one (``foothold``)."""
        out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for cls, group in self._groups:
            cls.add_foothold_offsets(self, group, active, out)
        return out

    def _ft_offsets(self) -> np.ndarray:
        """(C, 6) the hidden constant offsets of the F/T readings (sensor frame), per contact."""
        out = np.zeros((len(self.robot.contact_names), 6))
        for cls, group in self._groups:
            cls.add_ft_offsets(self, group, out)
        return out

    def _ambient_levels(self, spec: Ambient) -> tuple[float, float]:
        """RMS (linear m/s^2, angular rad/s^2) of the ambient acceleration (defaults: see Ambient),
        or (force N, torque N m) of the ambient wrench."""
        if spec.kind == "wrench":
            assert spec.force is not None and spec.torque is not None  # required with kind = "wrench" (Ambient.parse)
            return spec.scale * spec.force, spec.scale * spec.torque
        model = self.robot.model
        data = model.createData()
        pin.framesForwardKinematics(model, data, self.robot.q_reference)
        p_imu = data.oMf[self.robot.imu_frame_id].translation
        centroid = np.mean([data.oMf[f].translation for f in self.robot.contact_frame_ids], axis=0)
        lever = max(float(np.linalg.norm(p_imu - centroid)), 1e-3)
        linear = spec.linear if spec.linear is not None else self.robot.config.imu_noise.accel_sigma(self.scenario.rate)
        angular = spec.angular if spec.angular is not None else linear / lever
        return spec.scale * linear, spec.scale * angular

    def _ambient_table(self, n: int, sub: int) -> np.ndarray | None:
        """((n - 1) sub + 1, 6) ambient acceleration (dw rad/s^2, a m/s^2), or wrench (torque N m
        about the base origin, force N; world axes), at the integration instants.

        Without a corner: white at the samples, linear in between (a continuous acceleration).
        With one: white at the integration rate through a second-order Butterworth low-pass
        (scipy's ``butter``), normalised by the filter's white-noise gain so that the
        stationary RMS is the level; run from 2 s before the start so it is stationary at t = 0.
        """
        if self.ambient is None:
            return None
        sa, sdw = self.ambient
        sc = self.scenario
        rng = np.random.default_rng((sc.seed, 7))
        scale = np.array([sdw] * 3 + [sa] * 3)
        if self.ambient_spec.corner is None:
            white = np.concatenate([rng.standard_normal((n, 3)), rng.standard_normal((n, 3))], axis=1) * scale
            fine = np.arange((n - 1) * sub + 1) / sub
            k = np.minimum(fine.astype(int), n - 2) if n > 1 else np.zeros(len(fine), dtype=int)
            s = (fine - k)[:, None]
            return white[k] * (1.0 - s) + white[np.minimum(k + 1, n - 1)] * s
        fs = sc.sim_rate
        b, a = signal.butter(2, self.ambient_spec.corner, fs=fs)
        lead = int(round(2.0 * fs))
        y = signal.lfilter(b, a, rng.standard_normal(((n - 1) * sub + 1 + lead, 6)), axis=0)
        impulse = np.zeros(4 * lead)
        impulse[0] = 1.0
        gain = math.sqrt(float(np.sum(signal.lfilter(b, a, impulse) ** 2)))  # white-noise RMS gain
        return y[lead:] / gain * scale

    def _true_springs(self) -> list[Spring]:
        nominal = Spring.from_stiffness(self.robot.config.stiffness)
        out = []
        for p in [nominal] * len(self.robot.contact_names):
            k = SpringTerms(p.K_fs.copy(), p.K_fd.copy(), p.K_ts.copy(), p.K_td.copy(), p.beta_f, p.beta_t)
            for e in self.effects:
                e.adjust_spring(k)
            out.append(Spring(k.K_fs, k.K_fd, k.K_ts, k.K_td, k.beta_f, k.beta_t))
        return out

    # ------------------------------------------------------------------------------------------
    def world_dynamics(self, t: float, R, tr, w, v, local: LocalSample, rest, disturbance=None) -> WorldEval:
        """Flexibility acceleration from pinocchio's multibody dynamics.

        Args:
            R, tr, w, v: flexibility rotation, translation, angular and linear velocity (world).
            local: the robot's local-frame q, v, a at ``t``.
            rest: per contact, its rest placement (SE3) when in contact, else None.
            disturbance: (6,) ambient flexibility acceleration (dw rad/s^2, a m/s^2) to produce with an
                external wrench on the base, or with ``Ambient.kind == "wrench"`` the wrench itself
                (torque N m about the base origin, force N; world axes); None for none.
        """
        model, data = self.sim_model, self.sim_data
        ql, vl, al = local.q, local.v, local.a
        R_l = _quat_to_R(np.array([ql[6], ql[3], ql[4], ql[5]]))
        p_l = ql[:3]
        dp_l = R_l @ vl[:3]
        w_l = R_l @ vl[3:6]
        dw_l = R_l @ al[3:6]
        ddp_l = R_l @ (al[:3] + _cross(vl[3:6], vl[:3]))
        R_b = R @ R_l
        Rp = R @ p_l
        p_b = Rp + tr
        w_b = w + R @ w_l
        dp_b = _cross(w, Rp) + R @ dp_l + v
        q_w = ql.copy()
        q_w[:3] = p_b
        quat = pin.Quaternion(R_b)
        quat.normalize()
        q_w[3:7] = quat.coeffs()
        v_w = vl.copy()
        v_w[:3] = R_b.T @ dp_b
        v_w[3:6] = R_b.T @ w_b
        pin.forwardKinematics(model, data, q_w, v_w)
        nc = len(rest)
        wrenches = np.zeros((nc, 6))
        local_wrenches = np.zeros((nc, 6))
        F_sum = np.zeros(3)
        M_sum = np.zeros(3)  # moment about the base origin
        for ci, (fid, M0, spring) in enumerate(zip(self.robot.contact_frame_ids, rest, self.springs)):
            if M0 is None:
                continue
            M = pin.updateFramePlacement(model, data, fid)
            vel = pin.getFrameVelocity(model, data, fid, pin.LOCAL_WORLD_ALIGNED)
            Rc = M.rotation
            wr = spring.wrench(M, M0, vel)
            F, tau = wr[:3], wr[3:]
            wrenches[ci, :3] = F
            wrenches[ci, 3:] = tau + _cross(M.translation, F)
            local_wrenches[ci, :3] = Rc.T @ F
            local_wrenches[ci, 3:] = Rc.T @ tau
            F_sum += F
            M_sum += tau + _cross(M.translation - p_b, F)
        external = np.zeros(6)
        for eff, fid, force, torque in self.ext_effects:
            k = eff.profile(t)
            if k == 0.0:
                continue
            M = pin.updateFramePlacement(model, data, fid)
            F = k * force
            tau = k * torque
            external[:3] += F
            external[3:] += tau + _cross(M.translation, F)
            F_sum += F
            M_sum += tau + _cross(M.translation - p_b, F)
        a0 = al.copy()
        a0[:6] = 0.0
        b = pin.rnea(model, data, q_w, v_w, a0)[:6]
        Mfull = pin.crba(model, data, q_w)
        Mbb = np.triu(Mfull[:6, :6]) + np.triu(Mfull[:6, :6], 1).T
        f_b = np.concatenate([R_b.T @ F_sum, R_b.T @ M_sum])
        if disturbance is not None and self.ambient_spec.kind == "wrench":
            T_d, F_d = disturbance[:3], disturbance[3:]  # world axes, torque about the base origin
            f_dist = np.concatenate([R_b.T @ F_d, R_b.T @ T_d])
            ambient = np.concatenate([F_d, T_d + _cross(p_b, F_d)])
            f_b = f_b + f_dist
        elif disturbance is not None:
            # The base acceleration that moves the flexibility by the disturbance, and the wrench
            # on the base (pinocchio's inertia) that produces it.
            ddw = disturbance[:3]
            ddp_b_dist = disturbance[3:] + _cross(ddw, Rp)
            f_dist = Mbb @ np.concatenate([R_b.T @ ddp_b_dist, R_b.T @ ddw])
            F_d = R_b @ f_dist[:3]
            ambient = np.concatenate([F_d, R_b @ f_dist[3:] + _cross(p_b, F_d)])
            f_b = f_b + f_dist
        else:
            ambient = np.zeros(6)
        a_b = np.linalg.solve(Mbb, f_b - b)
        dw_b = R_b @ a_b[3:]
        ddp_b = R_b @ (a_b[:3] + _cross(v_w[3:6], v_w[:3]))
        dw = dw_b - _cross(w, R @ w_l) - R @ dw_l
        a = ddp_b - _cross(dw, Rp) - _cross(w, _cross(w, Rp)) - 2.0 * _cross(w, R @ dp_l) - R @ ddp_l
        a_w = al.copy()
        a_w[:6] = a_b
        return WorldEval(dw, a, wrenches, local_wrenches, external, ambient, q_w, v_w, a_w)

    def _equilibrium(self, local: LocalSample, rest) -> tuple[np.ndarray, np.ndarray]:
        """Static flexibility (R, t) at the start: zero velocity and zero acceleration."""
        k_total = sum(float(np.trace(p.K_fs)) / 3.0 for p, M0 in zip(self.springs, rest) if M0 is not None)
        if k_total <= 0:
            raise ConfigError("the scenario must start with at least one contact in force")
        R = np.eye(3)
        tr = np.array([0.0, 0.0, -self.robot.mass * self.g / k_total])
        zero = np.zeros(3)

        def acc(R, tr):
            ev = self.world_dynamics(0.0, R, tr, zero, zero, local, rest)
            return np.concatenate([ev.dw, ev.a])

        for _ in range(30):
            f0 = acc(R, tr)
            if np.max(np.abs(f0)) < 1e-11:
                break
            J = np.zeros((6, 6))
            h = 1e-7
            for i in range(6):
                d = np.zeros(6)
                d[i] = h
                Rp, tp = pin.exp3(d[:3]) @ R, tr + d[3:]
                d[i] = -h
                Rm, tm = pin.exp3(d[:3]) @ R, tr + d[3:]
                J[:, i] = (acc(Rp, tp) - acc(Rm, tm)) / (2 * h)
            step = np.linalg.solve(J, -f0)
            R = pin.exp3(step[:3]) @ R
            tr = tr + step[3:]
        else:
            raise ModelError("no static equilibrium found at the start of the scenario: "
                             "check that the stiffness keeps the robot stable (DESIGN.md, Stability)")
        return R, tr

    # ------------------------------------------------------------------------------------------
    def run(self, progress: Callable[[float], None] | None = None) -> Recording:
        """Simulate the scenario; ``progress`` is called with the fraction done."""
        return _Run(self).run(progress)

    # ------------------------------------------------------------------------------------------
    def _recording(self, times, samples, truth_R, truth, truth_wrench, truth_ext, truth_amb, links, ft_true,
                   gyro_true, accel_true, rest_p, rest_R, active) -> Recording:
        sc = self.scenario
        robot = self.robot
        n = len(times)
        rng = np.random.default_rng(sc.seed)
        kin = [robot.kinematics(s.q, s.v, s.a) for s in samples]
        inp = [k.inputs for k in kin]
        imu = [k.imu for k in kin]
        # IMU: white noise, bias random walk, hidden constant biases.
        gyro_bias = np.zeros((n, 3))
        accel_bias = np.zeros((n, 3))
        for e in self.effects:
            e.add_imu_bias(gyro_bias, accel_bias)
        gyro_true, accel_true = self._delay_imu(np.asarray(times, dtype=float), gyro_true, accel_true)
        gyro = gyro_true + gyro_bias
        accel = accel_true + accel_bias
        ft = ft_true + self.ft_offset  # hidden sensor offsets (sensor frame)
        if self.noise:
            dt = 1.0 / sc.rate
            walk_g = np.cumsum(rng.normal(0.0, self.imu_noise.gyro_bias_rw * math.sqrt(dt), (n, 3)), axis=0)
            walk_a = np.cumsum(rng.normal(0.0, self.imu_noise.accel_bias_rw * math.sqrt(dt), (n, 3)), axis=0)
            gyro_bias = gyro_bias + walk_g - walk_g[0]
            accel_bias = accel_bias + walk_a - walk_a[0]
            gyro = gyro_true + gyro_bias + rng.normal(0.0, self.imu_noise.gyro_sigma(sc.rate), (n, 3))
            accel = accel_true + accel_bias + rng.normal(0.0, self.imu_noise.accel_sigma(sc.rate), (n, 3))
            ft[..., :3] += rng.normal(0.0, self.ft_noise.force, ft[..., :3].shape)
            ft[..., 3:] += rng.normal(0.0, self.ft_noise.torque, ft[..., 3:].shape)
        # The sensors clip at their full scale (``[imu_noise]`` accel_range, gyro_range).
        gyro = np.clip(gyro, -self.imu_noise.gyro_range, self.imu_noise.gyro_range)
        accel = np.clip(accel, -self.imu_noise.accel_range, self.imu_noise.accel_range)
        truth_obj = Truth(
            R=truth_R, t=truth["t"], w=truth["w"], v=truth["v"], dw=truth["dw"], a=truth["a"],
            wrench=truth_wrench, external_wrench=truth_ext, cop=truth["cop"],
            links={name: links[:, i].copy() for i, name in enumerate(robot.link_names)},
            gyro_bias=gyro_bias, accel_bias=accel_bias,
            ambient_wrench=truth_amb if self.ambient is not None else None)
        step_ns = int(round(1e9 / sc.rate))
        meta = {
            "source": "simulation",
            "scenario": sc.to_dict(),
            "noise": self.noise,
            "imu_noise": dict(self.imu_noise.__dict__),
            "ft_noise": dict(self.ft_noise.__dict__),
            "stiffness": {k: (list(v) if isinstance(v, tuple) else v)
                          for k, v in robot.config.stiffness.__dict__.items()},
            "hidden_effects": [{"type": e.type, **e.params} for e in self.effects],
            "ambient": (None if self.ambient is None else
                        {**({"sigma_linear_m_s2": self.ambient[0], "sigma_angular_rad_s2": self.ambient[1]}
                            if self.ambient_spec.kind == "acceleration" else
                            {"sigma_force_N": self.ambient[0], "sigma_torque_Nm": self.ambient[1]}),
                         "kind": self.ambient_spec.kind, "corner_hz": self.ambient_spec.corner,
                         "scale": self.ambient_spec.scale}),
            "touchdown": self.touchdown,
            # Per contact episode: the spring's rest placement in the world (the true foothold)
            # and the local placement the recording gives the estimators.
            "contact_episodes": self.episodes,
        }
        return Recording(
            t_ns=np.arange(n, dtype=np.int64) * step_ns,
            robot=(robot.name if robot.config.source.startswith(str(ROBOTS_DIR))
                   else (robot.config.source or robot.name)),
            contact_names=robot.contact_names,
            mass=robot.mass,
            com=np.array([i.c for i in inp]), com_vel=np.array([i.dc for i in inp]),
            com_acc=np.array([i.ddc for i in inp]), inertia=np.array([i.I for i in inp]),
            inertia_dot=np.array([i.dI for i in inp]), sigma=np.array([i.sigma for i in inp]),
            sigma_dot=np.array([i.dsigma for i in inp]),
            imu_R=np.array([m.R for m in imu]), imu_p=np.array([m.p for m in imu]),
            imu_v=np.array([m.v for m in imu]), imu_a=np.array([m.a for m in imu]),
            imu_w=np.array([m.w for m in imu]),
            contact_active=active, contact_p=rest_p, contact_R=rest_R,
            gyro=gyro, accel=accel,
            joint_names=robot.joint_names,
            joint_q=np.array([s.q[7:] for s in samples]), joint_v=np.array([s.v[6:] for s in samples]),
            ft=ft, base_pose=np.array([s.q[:7] for s in samples]), truth=truth_obj, gravity=self.g, meta=meta,
        ).validate()


class _Run:
    """One simulation of a :class:`Simulator`: the state integrated, the contact episodes and the
    truth recorded at the samples (see the module documentation, Touch-down)."""

    def __init__(self, sim: Simulator):
        self.sim = sim
        sc = sim.scenario
        robot = self.robot = sim.robot
        self.motion = sim.motion
        self.n = n = int(round(sc.duration * sc.rate)) + 1
        self.dt = dt = 1.0 / sc.rate
        self.sub = sub = int(round(sc.sim_rate / sc.rate))
        self.h = dt / sub
        self.nc = nc = len(robot.contact_names)
        self.times = np.arange(n) * dt
        # Local motion at the samples (exact), then quintic Hermite in between; each sample is
        # computed when its interval starts (an early touch-down changes the motion from then on).
        self.samples = samples = [self.motion.sample(0.0)]
        rest: list[Any] = [pin.SE3(M) if act else None for M, act in zip(self.motion.placements0, samples[0].active)]
        nominal_rest = [pin.SE3(M) if M is not None else None for M in rest]
        for ci, (dp, dr) in sim._foothold_offsets(samples[0].active).items():
            # the ground under a standing contact is not where the robot believes (a shim, a tilted tile)
            rest[ci] = pin.SE3(pin.exp3(dr) @ rest[ci].rotation, rest[ci].translation + dp)
        self.rest = rest
        R, tr = sim._equilibrium(samples[0], rest)
        quat = pin.Quaternion(R)
        self.y = np.concatenate([[quat.w, quat.x, quat.y, quat.z], tr, np.zeros(6)])

        self.truth = {k: np.zeros((n, 3)) for k in ("t", "w", "v", "dw", "a", "cop")}
        self.truth_R = np.zeros((n, 3, 3))
        self.truth_wrench = np.zeros((n, nc, 6))
        self.truth_ext = np.zeros((n, 6))
        self.truth_amb = np.zeros((n, 6))
        self.links = np.zeros((n, len(robot.link_frame_ids), 3))
        self.ft_true = np.zeros((n, nc, 6))
        self.gyro_true = np.zeros((n, 3))
        self.accel_true = np.zeros((n, 3))
        self.rec_rest_p = np.zeros((n, nc, 3))
        self.rec_rest_R = np.tile(np.eye(3), (n, nc, 1, 1))
        self.active = np.zeros((n, nc), dtype=bool)

        self.amb = sim._ambient_table(n, sub)
        self.disturbance = None
        # The world's rest placement of each contact in force (the spring's anchor), and the local
        # placement the robot believes in (the recording's contact placement).
        self.local_rest: list[Any] = [pin.SE3(M) if M is not None else None for M in nominal_rest]  # pin.SE3 or None
        local_rest = self.local_rest
        self.episodes = [{"contact": robot.contact_names[ci], "start": 0.0, "end": None,
                          "world_p": rest[ci].translation.tolist(), "world_R": rest[ci].rotation.tolist(),
                          "local_p": local_rest[ci].translation.tolist()} if rest[ci] is not None else None
                         for ci in range(nc)]
        self.closed: list = []
        self.scheduled = [bool(a) for a in samples[0].active]
        self.swinging: list = [None] * nc
        self.releasing = [False] * nc
        self.floor_mode = sim.touchdown == "floor"
        # The floor: the plane of the contacts in force at the start (z = 0 for the built-in robots).
        self.floor_z = float(np.mean([M.translation[2] for M in nominal_rest if M is not None]))
        # Each sole's normal to the floor, in its own frame (from the standing posture).
        self.floor_normal = [M.rotation.T @ E_Z for M in self.motion.placements0]
        self.replanned = False  # an early touch-down changed the local motion in the current interval

    def land(self, ci, t, y, q_local):
        """Start a contact episode at ``t``: the spring's rest placement and the recorded one."""
        rest, local_rest, floor_mode, floor_z = self.rest, self.local_rest, self.floor_mode, self.floor_z
        model, data = self.motion.model, self.motion.data
        fid = self.robot.contact_frame_ids[ci]
        sw = self.swinging[ci]
        planned = self.motion.contact_targets(sw.land)[0][ci] if sw is not None else None
        stop = None
        if floor_mode and sw is not None and t < sw.land:
            # touched before its scheduled landing: the foot stops there (Stop), the plan's
            # remaining descent is dropped
            stop = self.motion.stop(ci, t)
            self.replanned = True
        # What the robot believes: where its foot rests, in the local frame (the placement its
        # kinematics holds from the end of the landing on).
        local_rest[ci] = (self.motion.contact_targets(stop.end)[0][ci] if stop is not None else planned
                          if planned is not None else
                          (pin.framesForwardKinematics(model, data, q_local), data.oMf[fid].copy())[1])
        if self.sim.touchdown == "deflected":  # where the robot believes it is: preloaded by the deflection
            rest[ci] = pin.SE3(local_rest[ci])
        else:  # where the foot is in the world: the spring starts unloaded
            pin.framesForwardKinematics(model, data, q_local)
            world_T_local = pin.SE3(_quat_to_R(y[:4] / np.linalg.norm(y[:4])), y[4:7].copy())
            rest[ci] = world_T_local * data.oMf[fid]
            if floor_mode:  # the sole lies flat on the floor, at its height, with the foot's heading
                n_w = rest[ci].rotation @ self.floor_normal[ci]
                axis = np.cross(n_w, E_Z)
                angle = math.atan2(np.linalg.norm(axis), float(n_w @ E_Z))
                if angle > 0.0:
                    rest[ci].rotation = pin.exp3(axis / np.linalg.norm(axis) * angle) @ rest[ci].rotation
                if rest[ci].translation[2] < floor_z:
                    rest[ci].translation = np.array([*rest[ci].translation[:2], floor_z])
        self.swinging[ci] = None
        episodes = self.episodes
        episodes[ci] = {"contact": self.robot.contact_names[ci], "start": float(t), "end": None,
                        "world_p": rest[ci].translation.tolist(), "world_R": rest[ci].rotation.tolist(),
                        "local_p": local_rest[ci].translation.tolist(),
                        "above_floor": float(rest[ci].translation[2] - floor_z)}
        if stop is not None:  # how far the foot stopped from its planned landing, in the local frame:
            # at rest, then once the leg has levelled
            episodes[ci]["local_off_plan"] = (local_rest[ci].translation - planned.translation).tolist()
            episodes[ci]["levelled_off_plan"] = (self.motion.contact_targets(stop.levelled)[0][ci].translation
                                                 - planned.translation).tolist()

    def release(self, ci, t):
        """End contact ``ci``'s episode at ``t``."""
        if self.episodes[ci] is not None:
            self.episodes[ci]["end"] = float(t)
            self.closed.append(self.episodes[ci])
            self.episodes[ci] = None
        self.rest[ci] = None
        self.local_rest[ci] = None
        self.releasing[ci] = False

    def deriv(self, t, y, local, rest):
        qw = y[:4] / np.linalg.norm(y[:4])
        Rm = _quat_to_R(qw)
        ev = self.sim.world_dynamics(t, Rm, y[4:7], y[7:10], y[10:13], local, rest, self.disturbance)
        return np.concatenate([_quat_rate(qw, y[7:10]), y[10:13], ev.dw, ev.a]), ev

    def deriv_with_events(self, t, y, local):
        """``deriv`` at the start of an integration step, after the floor's contact events: a
        descending foot that reached the floor touches it; a lifting foot whose spring no
        longer pushes (normal force <= 0) leaves it."""
        rest, swinging, releasing = self.rest, self.swinging, self.releasing
        if self.floor_mode:
            R_f = None
            for ci in range(self.nc):
                sw = swinging[ci]
                if rest[ci] is not None or sw is None or t < 0.5 * (sw.lift + sw.land):
                    continue
                if R_f is None:
                    R_f = _quat_to_R(y[:4] / np.linalg.norm(y[:4]))
                    pin.framesForwardKinematics(self.motion.model, self.motion.data, local.q)
                M = self.motion.data.oMf[self.robot.contact_frame_ids[ci]]
                if (R_f @ M.translation + y[4:7])[2] <= self.floor_z:
                    self.land(ci, t, y, local.q)
        out = self.deriv(t, y, local, rest)
        if self.floor_mode:
            # A foot still pushing a quarter into its swing is torn off the floor (a force step,
            # kept in the episode): the floor cannot hold it, nor the robot drag it further.
            gone = [ci for ci in range(self.nc) if releasing[ci] and (
                out[1].wrenches[ci, 2] <= 0.0
                or t >= swinging[ci].lift + 0.25 * (swinging[ci].land - swinging[ci].lift))]
            for ci in gone:
                self.episodes[ci]["release_force"] = [float(x) for x in out[1].wrenches[ci, :3]]
                self.release(ci, t)
            if gone:
                out = self.deriv(t, y, local, rest)
        return out

    def local_at(self, k, s):
        """The local sample at ``(k + s) dt``: quintic Hermite between the samples, the pelvis analytic."""
        samples, dt = self.samples, self.dt
        if s == 0.0:
            return samples[k]
        s0, s1 = samples[k], samples[k + 1]
        H, dH, ddH = _hermite5(s, dt)
        ql = s0.q.copy()
        vl = s0.v.copy()
        al = s0.a.copy()
        J0 = slice(7, None)
        V0 = slice(6, None)
        basis = np.array([s0.q[J0], s0.v[V0], s0.a[V0], s1.q[J0], s1.v[V0], s1.a[V0]])
        ql[J0] = H @ basis
        vl[V0] = dH @ basis
        al[V0] = ddH @ basis
        # pelvis: analytic
        base = self.motion
        p, dp, ddp = base.q_ref[:3].copy(), np.zeros(3), np.zeros(3)
        for seg in base.base_segments:
            x, dx, ddx = seg(k * dt + s * dt)
            p += x
            dp += dx
            ddp += ddx
        R_l = _quat_to_R(np.array([ql[6], ql[3], ql[4], ql[5]]))
        ql[:3] = p
        vl[:3] = R_l.T @ dp
        al[:3] = R_l.T @ ddp
        return LocalSample(ql, vl, al, s0.active)

    def contact_events(self, tk, local):
        """The contact set for the interval starting at ``tk``: scheduled landings not touched
        yet land, feet starting to lift swing (and leave the floor once unloaded)."""
        rest, scheduled = self.rest, self.scheduled
        for ci in range(self.nc):
            if local.active[ci] and rest[ci] is None:  # scheduled landing, not touched yet
                self.land(ci, tk, self.y, local.q)
            elif not local.active[ci] and scheduled[ci]:  # the foot starts to lift
                self.swinging[ci] = self.motion.swing_at(ci, tk)
                if self.floor_mode:  # it leaves the floor when its spring is unloaded
                    self.releasing[ci] = True
                else:
                    self.release(ci, tk)
            scheduled[ci] = bool(local.active[ci])

    def record(self, k, tk, local, ev):
        """The truth and the true sensor signals at sample ``k``."""
        y, truth, robot, nc, rest = self.y, self.truth, self.robot, self.nc, self.rest
        qw = y[:4] / np.linalg.norm(y[:4])
        self.truth_R[k] = _quat_to_R(qw)
        truth["t"][k] = y[4:7]
        truth["w"][k] = y[7:10]
        truth["v"][k] = y[10:13]
        truth["dw"][k] = ev.dw
        truth["a"][k] = ev.a
        self.truth_wrench[k] = ev.wrenches
        self.truth_ext[k] = ev.external
        self.truth_amb[k] = ev.ambient
        self.ft_true[k] = ev.local_wrenches
        self.active[k] = [M is not None for M in rest]
        commanded = self.motion.contact_targets(tk)[0]
        for ci in range(nc):
            if rest[ci] is not None:
                # the placement the robot's kinematics holds the contact at: its landing, or
                # while it brakes, levels or lifts, where the leg puts it
                self.rec_rest_p[k, ci] = commanded[ci].translation
                self.rec_rest_R[k, ci] = commanded[ci].rotation
            else:
                # placement in the air: where the contact frame is in the local frame
                pin.framesForwardKinematics(self.motion.model, self.motion.data, local.q)
                M = self.motion.data.oMf[robot.contact_frame_ids[ci]]
                self.rec_rest_p[k, ci] = M.translation
                self.rec_rest_R[k, ci] = M.rotation
        # sensors from pinocchio's kinematics of the simulated robot in the world
        model, data = self.sim.sim_model, self.sim.sim_data
        pin.forwardKinematics(model, data, ev.q_w, ev.v_w, ev.a_w)
        fid = robot.imu_frame_id
        M = pin.updateFramePlacement(model, data, fid)
        self.gyro_true[k] = pin.getFrameVelocity(model, data, fid, pin.LOCAL).angular
        self.accel_true[k] = (pin.getFrameClassicalAcceleration(model, data, fid, pin.LOCAL).linear
                              + M.rotation.T @ (self.sim.g * E_Z))
        for li, lf in enumerate(robot.link_frame_ids):
            self.links[k, li] = pin.updateFramePlacement(model, data, lf).translation
        truth["cop"][k] = center_of_pressure(ev.wrenches.sum(axis=0), z0=0.0)

    def interval(self, k, tk, local, k1_sample):
        """Integrate from sample ``k`` to ``k + 1`` (classical Runge-Kutta at ``sim_rate``)."""
        samples, amb, sub, h, rest = self.samples, self.amb, self.sub, self.h, self.rest
        y = self.y
        for j in range(sub):
            s0 = j / sub
            t0 = tk + j * h
            if amb is not None:
                self.disturbance = amb[k * sub + j]
            k1 = k1_sample if j == 0 else self.deriv_with_events(t0, y, self.local_at(k, s0))[0]
            if self.replanned:  # an early touch-down at t0 changed the motion: re-solve the next sample
                samples[k + 1] = self.motion.sample(float(self.times[k + 1]))
                self.replanned = False
            lm = self.local_at(k, s0 + 0.5 / sub)
            l1 = self.local_at(k, s0 + 1.0 / sub) if j < sub - 1 else LocalSample(
                samples[k + 1].q, samples[k + 1].v, samples[k + 1].a, local.active)
            if amb is not None:
                self.disturbance = 0.5 * (amb[k * sub + j] + amb[k * sub + j + 1])
            k2, _ = self.deriv(t0 + 0.5 * h, y + 0.5 * h * k1, lm, rest)
            k3, _ = self.deriv(t0 + 0.5 * h, y + 0.5 * h * k2, lm, rest)
            if amb is not None:
                self.disturbance = amb[k * sub + j + 1]
            k4, _ = self.deriv(t0 + h, y + h * k3, l1, rest)
            y = y + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
            y[:4] /= np.linalg.norm(y[:4])
            self.y = y
        if not np.all(np.isfinite(y)) or np.max(np.abs(y[4:7])) > 1.0:
            raise ModelError(f"simulation diverged at t = {tk:.3f} s (flexibility translation "
                             f"{np.abs(y[4:7]).max():.3g} m): the stiffness cannot hold the robot")

    def run(self, progress: Callable[[float], None] | None) -> Recording:
        n = self.n
        for k in range(n):
            tk = float(self.times[k])
            local = self.samples[k]
            if self.amb is not None:
                self.disturbance = self.amb[k * self.sub]
            # contact set for the interval starting at t_k (see the module documentation, Touch-down)
            self.contact_events(tk, local)
            k1_sample, ev = self.deriv_with_events(tk, self.y, local)
            self.record(k, tk, local, ev)
            if k == n - 1:
                break
            self.samples.append(self.motion.sample(float(self.times[k + 1])))
            self.replanned = False
            self.interval(k, tk, local, k1_sample)
            if progress is not None and k % 20 == 0:
                progress(k / (n - 1))
        if progress is not None:
            progress(1.0)
        sim = self.sim
        sim.episodes = self.closed + [e for e in self.episodes if e is not None]
        sim.episodes.sort(key=lambda e: (e["start"], e["contact"]))
        return sim._recording(self.times, self.samples, self.truth_R, self.truth, self.truth_wrench, self.truth_ext,
                              self.truth_amb, self.links, self.ft_true, self.gyro_true, self.accel_true,
                              self.rec_rest_p, self.rec_rest_R, self.active)


def simulate(scenario: Scenario | str, robot: str | RobotModel | None = None, noise: bool | None = None,
             progress: Callable[[float], None] | None = None) -> Recording:
    """Simulate a built-in scenario (by name) or a scenario file; see :class:`Simulator`."""
    return Simulator(scenario, robot, noise).run(progress)
