"""What a contact can carry: a normal force that pushes, a friction cone, a CoP on the sole.

The spring-damper law (eq. 6, 11) is bilateral and unbounded: a sole pressed into the ground by its
deflection pushes, one lifted by it pulls, and a rotational deflection gives a torque whatever the
normal force, so the law's wrench can put the centre of pressure beyond the sole's edge.  A real
foot does neither: it lifts off instead of pulling and rolls on its heel, toe or side instead of
carrying a torque larger than its normal force times the distance to that edge.  The estimators'
state follows the flexibility (the law holds for the deflection); their *reported* contact
wrenches are limited to what the contact can carry (:func:`limit_contact_wrenches`), and the part
removed is reported beside them (:attr:`flexforce.datasets.estimate.Estimate.wrench_excess`): what
the spring law asked for that no foot on the ground can give.

The limit is the projection of each contact's wrench, in its contact frame (z the normal), onto
the set of wrenches the contact can carry, one part after another:

1. a normal force ``F_z <= 0``: the contact carries nothing (the foot lifts);
2. a tangential force beyond ``mu F_z``: scaled onto the cone (when a friction coefficient is
   given), its direction kept;
3. a CoP ``(-T_y / F_z, T_x / F_z)`` outside the sole's rectangle: moved to the nearest point of
   the rectangle (when a sole is given), the normal force and the torque about the normal kept.

The normal force is never raised and the other two steps keep it: each is then the Euclidean
projection onto a convex set (the tangential forces within the cone at that normal force, the
CoPs on the sole), so the limited normal force, and at a given normal force the limited
tangential force and CoP, are never further than the spring law's from a wrench the contact can
carry (an F/T reading, the truth).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flexforce.factors.physics import wrench_about

EDGE = 1e-9
"""How far inside the set a limited wrench is put: relative on the friction cone, m on the sole."""

__all__ = ["ContactLimits", "balance_near_switches", "contact_frame_wrench", "limit_contact_wrenches", "near_switches",
           "required_force", "world_wrench"]


@dataclass(frozen=True)
class ContactLimits:
    """How many (step, contact) pairs in force each limit changed (over all contacts)."""

    in_contact: int
    """(step, contact) pairs with the contact in force."""
    negative_normal: int
    """Normal force below 0: set to carry nothing."""
    friction: int
    """Tangential force beyond ``mu F_z`` (0 without a friction coefficient)."""
    cop: int
    """CoP outside the sole (0 without soles)."""
    friction_mu: float | None
    """The friction coefficient used, or None: no friction limit."""

    def as_dict(self) -> dict:
        return {"in_contact": self.in_contact, "negative_normal": self.negative_normal,
                "friction": self.friction, "cop": self.cop, "friction_mu": self.friction_mu}


def contact_frame_wrench(R: np.ndarray, t: np.ndarray, wrench: np.ndarray, local_p_c: np.ndarray,
                         local_R_c: np.ndarray, active: np.ndarray) -> np.ndarray:
    """(N, C, 6) per-contact wrench in the contact frame about its origin, as an F/T sensor reads it.

    Args:
        R, t: (N, 3, 3), (N, 3) flexibility placing the local frame (and its contacts) in the world.
        wrench: (N, C, 6) world wrench (F, T about the world origin).
        local_p_c, local_R_c: (N, C, 3), (N, C, 3, 3) contact placements in the local frame.
        active: (N, C) contacts in force; inactive ones read zero.
    """
    Rc = np.einsum("nij,ncjk->ncik", R, local_R_c)  # world_R_contact
    p = np.einsum("nij,ncj->nci", R, local_p_c) + t[:, None, :]
    about_p = wrench_about(wrench, p)
    out = np.concatenate([np.einsum("ncji,ncj->nci", Rc, about_p[..., :3]),
                          np.einsum("ncji,ncj->nci", Rc, about_p[..., 3:])], axis=2)
    out[~active] = 0.0
    return out


def world_wrench(R: np.ndarray, t: np.ndarray, local: np.ndarray, local_p_c: np.ndarray,
                 local_R_c: np.ndarray) -> np.ndarray:
    """Inverse of :func:`contact_frame_wrench`: (N, C, 6) contact-frame wrenches to the world (F, T
    about the world origin)."""
    Rc = np.einsum("nij,ncjk->ncik", R, local_R_c)
    p = np.einsum("nij,ncj->nci", R, local_p_c) + t[:, None, :]
    F = np.einsum("ncij,ncj->nci", Rc, local[..., :3])
    T = np.einsum("ncij,ncj->nci", Rc, local[..., 3:]) + np.cross(p, F)
    return np.concatenate([F, T], axis=2)


def limit_contact_wrenches(local: np.ndarray, active: np.ndarray, soles: tuple = (),
                           mu: float | None = None) -> tuple[np.ndarray, ContactLimits]:
    """The wrenches the contacts can carry (module docstring), from contact-frame wrenches.

    Args:
        local: (N, C, 6) wrenches in the contact frames (:func:`contact_frame_wrench`).
        active: (N, C) contacts in force; the others are returned as they are (zero).
        soles: per contact, ``(x_min, x_max, y_min, y_max)`` (m, contact frame) or None; empty:
            no CoP limit.
        mu: friction coefficient (> 0) or None: no friction limit.

    Returns:
        ``(limited, counts)``: (N, C, 6) limited wrenches and :class:`ContactLimits`.
    """
    out = np.array(local, dtype=float, copy=True)
    n_c = out.shape[1]
    on = np.asarray(active, dtype=bool)
    fz = out[..., 2]
    pull = on & ~(fz > 0.0)  # a NaN normal force is left alone below
    pull &= np.isfinite(fz)
    out[pull] = 0.0
    pushing = on & (fz > 0.0)
    n_fric = 0
    if mu is not None:
        ft = np.linalg.norm(out[..., :2], axis=-1)
        over = pushing & (ft > mu * fz)
        # onto the cone's boundary, a relative 1e-9 inside so that rounding in the change of frame
        # does not put it back outside
        scale = np.where(over, mu * (1.0 - EDGE) * fz / np.where(over, ft, 1.0), 1.0)
        out[..., :2] *= scale[..., None]
        n_fric = int(over.sum())
    n_cop = 0
    for i in range(n_c):
        box = soles[i] if i < len(soles) else None
        if box is None:
            continue
        x0, x1, y0, y1 = (float(v) for v in box)
        sel = pushing[:, i]
        if not sel.any():
            continue
        f = fz[sel, i]
        cx = -out[sel, i, 4] / f
        cy = out[sel, i, 3] / f
        moved = (cx < x0) | (cx > x1) | (cy < y0) | (cy > y1)
        # onto the edge, 1e-9 m inside (rounding in the change of frame, as for the cone)
        nx = np.where(moved, np.clip(cx, x0 + EDGE, x1 - EDGE), cx)
        ny = np.where(moved, np.clip(cy, y0 + EDGE, y1 - EDGE), cy)
        n_cop += int(moved.sum())
        out[sel, i, 3] = ny * f
        out[sel, i, 4] = -nx * f
    counts = ContactLimits(in_contact=int(on.sum()), negative_normal=int(pull.sum()), friction=n_fric,
                           cop=n_cop, friction_mu=None if mu is None else float(mu))
    return out, counts


def limit_world_wrenches(R: np.ndarray, t: np.ndarray, wrench: np.ndarray, rec, model
                         ) -> tuple[np.ndarray, np.ndarray | None, dict | None]:
    """An estimator's world wrenches limited to what its contacts can carry (``model.soles``,
    ``model.friction``) when ``model.limit_wrenches`` says so (None: when the model gives soles or
    a friction coefficient).

    Args:
        R, t: (N, 3, 3), (N, 3) the estimated flexibility.
        wrench: (N, C, 6) the contact law's world wrenches (F, T about the world origin).
        rec: the Recording (contact placements and states).
        model: the :class:`~flexforce.factors.model.ModelConfig`.

    Returns:
        ``(limited, excess, counts)``: (N, C, 6) limited world wrenches, ``wrench - limited``
        (exactly zero where nothing was limited) and :meth:`ContactLimits.as_dict`; ``(wrench,
        None, None)`` when limiting is off.
    """
    on = getattr(model, "limit_wrenches", None)
    if on is None:
        on = bool(getattr(model, "soles", ())) or getattr(model, "friction", None) is not None
    if not on:
        return wrench, None, None
    active = np.asarray(rec.contact_active, dtype=bool)
    local = contact_frame_wrench(R, t, wrench, rec.contact_p, rec.contact_R, active)
    lim, counts = limit_contact_wrenches(local, active, tuple(model.soles), model.friction)
    changed = np.any(lim != local, axis=2) & active
    limited = np.array(wrench, dtype=float, copy=True)
    if changed.any():
        back = world_wrench(R, t, lim, rec.contact_p, rec.contact_R)
        limited[changed] = back[changed]
    excess = wrench - limited
    excess[~changed] = 0.0
    return limited, excess, counts.as_dict()


# ---- the force the motion requires, near contact switches ---------------------------------------------


def near_switches(active: np.ndarray, time: np.ndarray, window: float) -> np.ndarray:
    """(N,) bool: within ``window`` s of a change of any contact's state."""
    act = np.asarray(active, dtype=bool)
    near = np.zeros(act.shape[0], dtype=bool)
    if window <= 0 or act.shape[0] < 2:
        return near
    switches = np.flatnonzero(np.any(act[1:] != act[:-1], axis=1)) + 1
    for k in switches:
        near |= np.abs(time - time[k]) <= window
    return near


def required_force(R: np.ndarray, w: np.ndarray, dw: np.ndarray, a: np.ndarray, rec, mass: float | None = None
                   ) -> np.ndarray:
    """(N, 3) world force the contacts must give for the estimated motion: ``m (c'' + g e_z)``, with
    the CoM's world acceleration from the flexibility ``(R, t)``, its world velocities ``(w, v)`` and
    accelerations ``(dw, a)`` and the local-frame CoM ``c_l`` and its derivatives (the recording's):
    ``c'' = R c_l'' + 2 w x R c_l' + dw x R c_l + w x (w x R c_l) + a``."""
    m = float(rec.mass if mass is None else mass)
    c = np.einsum("nij,nj->ni", R, rec.com)
    cv = np.einsum("nij,nj->ni", R, rec.com_vel)
    ca = np.einsum("nij,nj->ni", R, rec.com_acc)
    acc = ca + 2.0 * np.cross(w, cv) + np.cross(dw, c) + np.cross(w, np.cross(w, c)) + a
    acc[:, 2] += float(rec.gravity)
    return m * acc


def balance_near_switches(R: np.ndarray, t: np.ndarray, wrench: np.ndarray, unexplained: np.ndarray, rec,
                          window: float, near: np.ndarray | None = None) -> tuple[np.ndarray, dict | None]:
    """World contact wrenches that carry the ``unexplained`` force (N, 3, world: what the motion
    requires beyond the contact law's wrenches) within ``window`` s of a contact switch.

    At a touch-down the contact law's rest placement is least certain (the landing foot's spring
    starts preloaded by the flexibility's deflection, while a real foot lands unloaded), and the
    law's forces there disagree with the motion (the Newton-Euler residual): the total force is
    then taken from the motion.  The force is shared over the contacts in force in proportion to
    their normal forces (equally when none pushes), each part applied at its contact's CoP so that
    the CoPs stay where the law put them.  Elsewhere the wrenches are returned as they are.

    ``near`` (N,) bool replaces :func:`near_switches` of the recording's own contact states (a
    streamed part, whose switches may lie in the parts before or after it).

    Returns:
        ``(balanced, info)``: (N, C, 6) world wrenches and ``{"window_s", "samples", "rms_N",
        "max_N"}`` (the force moved), or ``(wrench, None)`` when nothing is moved (``window`` 0,
        no switch).
    """
    active = np.asarray(rec.contact_active, dtype=bool)
    if window <= 0:
        return wrench, None
    if near is None:
        near = near_switches(active, rec.time, window)
    near = near & active.any(axis=1) & np.all(np.isfinite(unexplained), axis=1)
    if not near.any():
        return wrench, None
    sel = np.flatnonzero(near)
    Rs, ts, act = R[sel], t[sel], active[sel]
    p_c, R_c = rec.contact_p[sel], rec.contact_R[sel]
    local = contact_frame_wrench(Rs, ts, wrench[sel], p_c, R_c, act)
    fz = np.where(act, np.maximum(local[..., 2], 0.0), 0.0)
    total = fz.sum(axis=1, keepdims=True)
    count = act.sum(axis=1, keepdims=True)
    share = np.where(total > 0, fz / np.where(total > 0, total, 1.0), act / np.maximum(count, 1))
    Rc = np.einsum("nij,ncjk->ncik", Rs, R_c)
    dF = np.einsum("ncji,nj->nci", Rc, unexplained[sel]) * share[..., None]  # contact frames
    cop = np.zeros_like(dF)
    loaded = local[..., 2] > 1e-6
    cop[..., 0] = np.where(loaded, -local[..., 4] / np.where(loaded, local[..., 2], 1.0), 0.0)
    cop[..., 1] = np.where(loaded, local[..., 3] / np.where(loaded, local[..., 2], 1.0), 0.0)
    moved = local.copy()
    moved[..., :3] += dF
    moved[..., 3:] += np.cross(cop, dF)
    moved[~act] = 0.0
    out = np.array(wrench, dtype=float, copy=True)
    out[sel] = np.where(act[..., None], world_wrench(Rs, ts, moved, p_c, R_c), wrench[sel])
    size = np.linalg.norm(unexplained[sel], axis=1)
    return out, {"window_s": float(window), "samples": int(sel.size), "rms_N": float(np.sqrt(np.mean(size ** 2))),
                 "max_N": float(size.max())}
