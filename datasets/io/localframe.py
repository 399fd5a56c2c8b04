r"""The local (control) frame of a walking robot: leg kinematics anchored on the stance foot.

The local frame is the robot's own belief (DESIGN.md, "The local (control) frame"): its
kinematics with the contacts at their rest placements.  On a real robot it is leg odometry.
Given the joint trajectory and which contacts are in force, this module places the free-flyer
(root link) in the local frame, step by step:

1. **Anchor.** One active contact is the anchor (stance foot).  At the first sample it is the
   configured one, else the most loaded active contact, else the first.  Its rest placement is
   the identity: the local frame starts *on the anchor sole*, flat, x forward (the sole frame's
   own axes; not the root link's, whose x points backwards on iCub).
2. **Base placement.** ``local_T_base = local_T_anchor_rest * (base_T_anchor)^-1``, where
   ``base_T_anchor`` is forward kinematics of the joints alone.
3. **Rest placements (footholds).** A contact that comes into force at step k gets a rest
   placement for its whole contact episode, fixed while it stays in force: the kinematic
   placement ``local_T_base(k) * base_T_contact(k)`` fused with the ground prior
   (:class:`flexforce.datasets.robot.FootholdConfig`): its tilt off the floor plane and its
   height above it are reduced by the weights of the two priors, its yaw and horizontal position
   kept.  Without the ground prior every leg-kinematics error at a touch-down (encoder offsets,
   the stance foot's own deflection) stays in the local frame as a tilt, and the tilts of
   successive steps add up; with it, the local frame may drift in yaw and position, as leg
   odometry does, but its tilt stays that of the floor.  While a contact is not in force its
   reported placement is its kinematic one (meaningless to the model).
4. **Switch.** When another contact in force carries ``switch_ratio`` times the anchor's load,
   or when the anchor leaves contact, the anchor passes to the most loaded contact in force and its
   *held* rest placement becomes the new anchor placement, so every
   contact's rest placement stays fixed while it is in contact.  If the kinematics disagrees
   slightly with the held placement (the flexibility, encoder errors), the base placement jumps
   by that amount at the switch; ``LocalFrame.drift`` reports the largest disagreement.
   With no contact in force (flight, a sensor gap) the last anchor is kept.
5. **Velocity and acceleration** of the free-flyer follow analytically from the anchor
   constraint (the anchor frame neither moves nor accelerates), so a switch makes no spike:
   with the anchor frame Jacobian ``J = [J_b | J_j]`` (pinocchio LOCAL, body-frame free-flyer
   velocity first)::

       J_b v_b + J_j v_j = 0                      ->  v_b = -J_b^-1 J_j v_j
       J_b a_b + J_j a_j + dJ v = 0               ->  a_b = -J_b^-1 (J_j a_j + dJ v)

   ``J_j a_j + dJ v`` is the anchor frame's spatial acceleration computed with ``a_b = 0``.
   ``J_b`` is the adjoint of ``anchor_T_base``, so ``J_b^-1`` is that of ``base_T_anchor``
   (the forward kinematics of step 2): no matrix is inverted, and both products are taken over
   a whole part at once.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from flexforce.datasets.robot import FootholdConfig
from flexforce.errors import DataError

__all__ = ["LocalFrame", "LocalFrameTracker", "anchored_local_frame", "on_ground"]


@dataclass
class LocalFrame:
    """Free-flyer trajectory in the local frame and the contacts' rest placements."""

    q: np.ndarray
    """(N, nq) pinocchio configurations (x, y, z, qx, qy, qz, qw, joints) in the local frame."""
    v: np.ndarray
    """(N, nv) velocities (body-frame free-flyer, joints)."""
    a: np.ndarray
    """(N, nv) accelerations."""
    anchor: np.ndarray
    """(N,) index of the anchor contact at each step."""
    contact_p: np.ndarray
    """(N, C, 3) rest position of each contact in the local frame (kinematic when inactive), m."""
    contact_R: np.ndarray
    """(N, C, 3, 3) rest orientation (kinematic when inactive)."""
    switches: list = field(default_factory=list)
    """Anchor changes: ``(step, from contact index, to contact index, jump [m])``."""
    drift: float = 0.0
    """Largest distance between an active contact's held rest position and its kinematic
    position, m (zero for a rigid, consistent robot; the flexibility makes it grow)."""
    footholds: list = field(default_factory=list)
    """One row per touch-down: ``(step, contact index, tilt off the floor [rad], height above
    the floor [m])`` of the kinematic placement, before the ground prior."""

    @property
    def base_pose(self) -> np.ndarray:
        """(N, 7) root link pose in the local frame: x, y, z, qx, qy, qz, qw (ROS order)."""
        return self.q[:, :7].copy()


def on_ground(placement: pin.SE3, footholds: FootholdConfig | None) -> tuple[pin.SE3, float, float]:
    """A landing sole's kinematic placement fused with the ground prior (module docstring, 3).

    Returns ``(foothold, tilt, height)``: the fused placement, and the kinematic sole's tilt off
    the floor (rad, angle between its z axis and the floor normal) and height above it (m).
    The sole is rotated about its own origin, so its horizontal position and yaw are kept.
    """
    if footholds is None:
        return placement, 0.0, 0.0
    n = footholds.normal
    z = placement.rotation[:, 2]
    axis = np.cross(z, n)
    s, c = float(np.linalg.norm(axis)), float(np.dot(z, n))
    tilt = float(np.arctan2(s, c))
    height = float(np.dot(n, placement.translation)) - footholds.height
    R = placement.rotation
    if s > 1e-12:
        R = pin.exp3(axis / s * (tilt * footholds.tilt_weight)) @ R
    p = placement.translation - footholds.height_weight * height * n
    return pin.SE3(R, p), tilt, height


def anchored_local_frame(model, q_joints: np.ndarray, v_joints: np.ndarray, a_joints: np.ndarray,
                         active: np.ndarray, load: np.ndarray | None = None, anchor: int | None = None,
                         progress=None, footholds: FootholdConfig | None = None,
                         switch_ratio: float | None = 3.0) -> LocalFrame:
    """Place the free-flyer of ``model`` (a :class:`RobotModel`) by stance-foot leg odometry.

    Args:
        q_joints: (N, nq - 7) joint part of the configurations.
        v_joints, a_joints: (N, nv - 6) joint velocities and accelerations.
        active: (N, C) bool, contacts in force.
        load: (N, C) normal forces, N, used to pick the most loaded contact (NaN = unknown).
        anchor: index of the contact preferred as the first anchor.
        progress: optional callable receiving the fraction done.
        footholds: the ground prior of the touch-downs (None: the kinematic placement, no prior).
        switch_ratio: the anchor passes to another contact in force once that one carries this
            many times the anchor's load (needs ``load``), so that the stance foot is changed
            while both feet are flat rather than when the old one is rolling off its toes; None:
            only when the anchor leaves contact.

    :class:`LocalFrameTracker` does the same part by part (a stream), with identical results.
    """
    tracker = LocalFrameTracker(model, anchor, footholds, switch_ratio)
    return tracker.run(q_joints, v_joints, a_joints, active, load, progress)


class LocalFrameTracker:
    """Stance-foot leg odometry over consecutive parts of a log (:func:`anchored_local_frame`):
    :meth:`run` on each part in turn; the anchor, the held rest placements and the drift carry
    over, and step indices (switches, touch-downs) count from the first part's first step."""

    def __init__(self, model, anchor: int | None = None, footholds: FootholdConfig | None = None,
                 switch_ratio: float | None = 3.0):
        self.model = model
        self.pmodel = model.model
        self.data = self.pmodel.createData()
        self.fids = model.contact_frame_ids
        self.c = len(self.fids)
        self.anchor_pref = anchor
        self.footholds = footholds
        self.switch_ratio = switch_ratio
        self.q = pin.neutral(self.pmodel)
        self.base = pin.SE3.Identity()
        self.current: int | None = None
        self.rest: list[Any] = [None] * self.c  # pin.SE3 or None (pinocchio ships no type information)
        self.was = np.zeros(self.c, dtype=bool)
        self.drift = 0.0
        self.k = 0
        """Steps placed so far (the index of the next part's first step)."""

    def run(self, q_joints: np.ndarray, v_joints: np.ndarray, a_joints: np.ndarray, active: np.ndarray,
            load: np.ndarray | None = None, progress=None) -> LocalFrame:
        """The local frame of the next part (arrays as in :func:`anchored_local_frame`); ``switches``
        and ``footholds`` of the result are this part's, ``drift`` the largest so far.

        Raises:
            DataError: arrays of inconsistent shapes, or of another robot.
        """
        pmodel = self.pmodel
        n, c = active.shape
        if (c != self.c or q_joints.shape != (n, pmodel.nq - 7) or v_joints.shape != (n, pmodel.nv - 6)
                or a_joints.shape != v_joints.shape):
            raise DataError(f"joint arrays have shapes {q_joints.shape}, {v_joints.shape}, {a_joints.shape} and "
                            f"contacts {active.shape}; expected {(n, pmodel.nq - 7)}, {(n, pmodel.nv - 6)} and "
                            f"{(n, self.c)}")
        load = np.zeros((n, c)) if load is None else np.where(np.isfinite(load), load, -np.inf)
        q_out = np.zeros((n, pmodel.nq))
        v_out = np.zeros((n, pmodel.nv))
        a_out = np.zeros((n, pmodel.nv))
        q_out[:, 7:] = q_joints
        v_out[:, 6:] = v_joints
        a_out[:, 6:] = a_joints
        steps = self._place(q_joints, active, load, q_out, progress)
        b_T_a = steps.b_T_c_H[np.arange(n), steps.anchors]  # base_T_anchor of each step
        self._base_motion(b_T_a, steps, q_out, v_out, a_out, v_joints, progress)
        cp, cR = self._contact_placements(b_T_a, steps, active)
        if n:
            self.was = active[n - 1].copy()
        self.k += n
        return LocalFrame(q_out, v_out, a_out, steps.anchors, cp, cR, steps.switches, self.drift, steps.landed)

    def _place(self, q_joints: np.ndarray, active: np.ndarray, load: np.ndarray, q_out: np.ndarray,
               progress) -> _Steps:
        """The step loop of a part (module docstring, 1-4): the anchor, the held rest placements and
        the base placement of each step (into the free-flyer columns of ``q_out``); the anchor, the
        held placements and the base carry over to the next part."""
        pmodel, data, fids = self.pmodel, self.data, self.fids
        n, c = active.shape
        footholds, switch_ratio, rest = self.footholds, self.switch_ratio, self.rest
        k0 = self.k
        on_rows: list[list[bool]] = active.tolist()  # Python rows: the step loop reads them element by element
        load_rows: list[list[float]] = load.tolist()

        def pick(k: int, candidates) -> int:
            candidates = list(candidates)
            return max(candidates, key=lambda i: (load_rows[k][i], -i))

        steps = _Steps(anchors=np.zeros(n, dtype=int), b_T_c_H=np.zeros((n, c, 4, 4)),
                       J_j=np.zeros((n, 6, pmodel.nv - 6)))
        anchors, b_T_c_H, J_j, rest_H = steps.anchors, steps.b_T_c_H, steps.J_j, steps.rest_H
        held: list[int] = [-1] * c  # the rest placement each contact holds (index in rest_H, -1: none)
        for i in range(c):
            if rest[i] is not None:
                held[i] = len(rest_H)
                rest_H.append(rest[i].homogeneous)

        def hold(i: int, placement) -> None:
            rest[i] = placement
            held[i] = len(rest_H)
            rest_H.append(placement.homogeneous)

        def _more_loaded(k: int, i: int) -> bool:
            """Another contact in force carries ``switch_ratio`` times the anchor's load (and held its
            foothold since the last step): the anchor passes to it while both feet are down."""
            assert switch_ratio is not None
            on_k, load_k = on_rows[k], load_rows[k]
            others = [j for j in range(c) if on_k[j] and j != i and was[j] and rest[j] is not None]
            return bool(others) and max(load_k[j] for j in others) > switch_ratio * max(load_k[i], 0.0)

        def touch_down(k: int, i: int, base) -> pin.SE3:
            foothold, tilt, height = on_ground(base * b_T_c[i], footholds)
            steps.landed.append((k0 + k, i, tilt, height))
            return foothold

        q = self.q
        q[:7] = (0, 0, 0, 0, 0, 0, 1)
        base = self.base
        was = self.was.tolist()
        for k in range(n):
            on_k = on_rows[k]
            q[7:] = q_joints[k]
            pin.forwardKinematics(pmodel, data, q)
            b_T_c = [pin.updateFramePlacement(pmodel, data, f) for f in fids]
            for i in range(c):
                b_T_c_H[k, i] = b_T_c[i].homogeneous
                if not on_k[i] and rest[i] is not None:  # released contacts lose their rest placement
                    rest[i] = None
                    held[i] = -1
            if self.current is None:
                on = [i for i in range(c) if on_k[i]]
                anchor = self.anchor_pref
                if anchor is not None and (on_k[anchor] or not on):
                    self.current = anchor
                else:
                    self.current = pick(k, on if on else range(c))
                hold(self.current, pin.SE3.Identity())
            elif (not on_k[self.current] and any(on_k)) or (
                    switch_ratio is not None and on_k[self.current] and _more_loaded(k, self.current)):
                new = pick(k, [i for i in range(c) if on_k[i]])
                if rest[new] is None:  # touched down at this very step
                    hold(new, touch_down(k, new, base))
                jump = float(np.linalg.norm((base * b_T_c[new]).translation - rest[new].translation))
                steps.switches.append((k0 + k, int(self.current), int(new), jump))
                self.current = new
            current = self.current
            if rest[current] is None:  # virtual anchor (no contact in force): hold its last placement
                hold(current, base * b_T_c[current])
            base = rest[current] * b_T_c[current].inverse()
            for i in range(c):
                if on_k[i] and (rest[i] is None or not was[i]) and i != current:
                    hold(i, touch_down(k, i, base))
            steps.held_rows.append(tuple(held))
            anchors[k] = current
            q_out[k, :7] = pin.SE3ToXYZQUAT(base)
            # the anchor's Jacobian in its own frame does not depend on the base placement
            J_j[k] = pin.computeFrameJacobian(pmodel, data, q, fids[current], pin.LOCAL)[:, 6:]
            was = on_k
            if progress is not None and (k % 50 == 0 or k == n - 1):
                progress(0.5 * (k + 1) / n)
        self.base = base
        return steps

    def _base_motion(self, b_T_a: np.ndarray, steps: _Steps, q_out: np.ndarray, v_out: np.ndarray,
                     a_out: np.ndarray, v_joints: np.ndarray, progress) -> None:
        """The free-flyer velocity and acceleration from the anchor constraint (module docstring, 5),
        into the free-flyer columns of ``v_out`` and ``a_out``: ``-J_b^-1 x``, ``J_b^-1`` the
        adjoint of ``b_T_a`` (base_T_anchor, (N, 4, 4))."""
        pmodel, data, fids = self.pmodel, self.data, self.fids
        n = len(steps.anchors)
        R_a, p_a = b_T_a[:, :3, :3], b_T_a[:, :3, 3]

        def minus_adjoint(x: np.ndarray) -> np.ndarray:
            ang = np.einsum("nij,nj->ni", R_a, x[:, 3:])
            return -np.concatenate([np.einsum("nij,nj->ni", R_a, x[:, :3]) + np.cross(p_a, ang), ang], axis=1)

        v_out[:, :6] = minus_adjoint(np.einsum("nij,nj->ni", steps.J_j, v_joints))
        gamma = np.zeros((n, 6))  # the anchor's spatial acceleration with a_b = 0
        for k in range(n):
            pin.forwardKinematics(pmodel, data, q_out[k], v_out[k], a_out[k])
            gamma[k] = pin.getFrameAcceleration(pmodel, data, fids[steps.anchors[k]], pin.LOCAL).vector
            if progress is not None and (k % 50 == 0 or k == n - 1):
                progress(0.5 + 0.5 * (k + 1) / n)
        a_out[:, :6] = minus_adjoint(gamma)

    def _contact_placements(self, b_T_a: np.ndarray, steps: _Steps,
                            active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(contact_p, contact_R)`` of a part: the held rest placement of each contact in force,
        the kinematic one otherwise (every contact in force holds one; so does the anchor); the
        drift updated with the part's largest distance between the two."""
        n, c = active.shape
        R_a, p_a = b_T_a[:, :3, :3], b_T_a[:, :3, 3]
        b_T_c_H = steps.b_T_c_H
        ids = np.array(steps.held_rows, dtype=int).reshape(n, c)
        rests = np.array(steps.rest_H).reshape(-1, 4, 4)
        anchor_rest = rests[ids[np.arange(n), steps.anchors]] if n else np.zeros((0, 4, 4))
        # base = anchor_rest * base_T_anchor^-1 (the placement the step loop formed as an SE3)
        R_base = anchor_rest[:, :3, :3] @ R_a.transpose(0, 2, 1)
        p_base = anchor_rest[:, :3, 3] - np.einsum("nij,nj->ni", R_base, p_a)
        kin_R = R_base[:, None] @ b_T_c_H[:, :, :3, :3]
        kin_p = np.einsum("nij,ncj->nci", R_base, b_T_c_H[:, :, :3, 3]) + p_base[:, None]
        in_force = active[:, :, None]
        placed = rests[np.maximum(ids, 0)] if len(rests) else np.zeros((n, c, 4, 4))
        cp = np.where(in_force, placed[:, :, :3, 3], kin_p)
        cR = np.where(in_force[..., None], placed[:, :, :3, :3], kin_R)
        if active.any():
            gap = np.linalg.norm(cp - kin_p, axis=2)
            self.drift = max(self.drift, float(gap[active].max()))
        return cp, cR


@dataclass
class _Steps:
    """What the step loop of :meth:`LocalFrameTracker.run` forms for a part of N steps."""

    anchors: np.ndarray
    """(N,) index of the anchor contact."""
    b_T_c_H: np.ndarray
    """(N, C, 4, 4) base_T_contact, homogeneous."""
    J_j: np.ndarray
    """(N, 6, nv - 6) the joint columns of the anchor's Jacobian (its own frame)."""
    held_rows: list = field(default_factory=list)
    """(N,) tuples: per step, the index in ``rest_H`` of the rest placement each contact holds (-1: none)."""
    rest_H: list = field(default_factory=list)
    """The rest placements held in the part (homogeneous 4x4), those carried over first."""
    switches: list = field(default_factory=list)
    """Anchor changes, as :attr:`LocalFrame.switches`."""
    landed: list = field(default_factory=list)
    """Touch-downs, as :attr:`LocalFrame.footholds`."""
