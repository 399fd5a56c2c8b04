r"""The flexible-contact model of Mifsud, Benallegue & Lamiraux (IROS 2015), in plain numpy.

One place for the EKF and the factor-graph smoothers alike.  Equation numbers are the seed
paper's; DESIGN.md's corrections are applied and cited as "correction k".

Frames and state
----------------
The flexibility ``(R, t)`` maps a point of the local (control) frame to the world,
``p = R p_l + t`` (eq. 2, 3).  ``w`` is the world-frame angular velocity (``dR/dt = [w]x R``),
``v = dt/dt``; ``dw``, ``a`` are their time derivatives.  Gravity is ``-g e_z`` in the world.

Jacobian convention
-------------------
Every ``*_D_*`` Jacobian is taken with respect to *world-frame increments*:
``R <- exp([d_theta]x) R``, ``t <- t + d_t``, ``w <- w + d_w``, ``v <- v + d_v`` and likewise for
accelerations and wrenches.  Blocks are ordered rotation first (as in gtsam):

- ``x = (theta, t, w, v)`` -- pose and velocity, 12 components;
- ``acc = (dw, a)`` -- acceleration, 6 components;
- a wrench is ``(F, T)``: force (N) then moment (N m) *about the world origin*.

A gtsam ``Pose3`` body-frame tangent ``(d_phi, d_rho)`` relates by ``d_theta = R d_phi`` and
``d_t = R d_rho``.  The paper's EKF state uses the rotation vector ``Omega = log R``; its increment
is ``d_theta = J_l(Omega) d_Omega`` (see :mod:`flexforce.factors.so3`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flexforce.errors import ModelError
from flexforce.factors import so3

GRAVITY = 9.81
"""Default gravity (m/s^2), along -z of the world (correction 6: a parameter)."""

E_Z = np.array([0.0, 0.0, 1.0])
_I3 = np.eye(3)


def _cross(a, b):
    """``a x b`` of two 3-vectors; np.cross costs ~20 us a call, this ~1 us."""
    a0, a1, a2 = np.asarray(a).tolist()
    b0, b1, b2 = np.asarray(b).tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


# ----------------------------------------------------------------------------------------------
# Parameters and inputs
# ----------------------------------------------------------------------------------------------


def _as_matrix(value, name: str) -> np.ndarray:
    a = np.asarray(value, dtype=float)
    if a.ndim == 0:
        return float(a) * np.eye(3)
    if a.shape == (3,):
        return np.diag(a)
    if a.shape == (3, 3):
        return a.copy()
    raise ModelError(f"{name} must be a scalar, a 3-vector (diagonal) or a 3x3 matrix, got shape {a.shape}")


@dataclass(frozen=True)
class ContactParams:
    """Spring-damper of one contact, eq. (6) and (11), expressed in the contact frame.

    The matrices are rotated into the world with the current contact orientation,
    ``K_world = R R_c K R_c^T R^T`` (correction 5); isotropic matrices are unaffected.
    """

    K_fs: np.ndarray
    """Translational stiffness, 3x3, N/m."""
    K_fd: np.ndarray
    """Translational damping, 3x3, N s/m."""
    K_ts: np.ndarray
    """Rotational stiffness, 3x3, N m/rad."""
    K_td: np.ndarray
    """Rotational damping, 3x3, N m s/rad."""
    beta_f: float = 0.0
    """Cubic stiffening of the translational spring, 1/m^2: ``F = -K_fs s (1 + beta_f |s|^2)``."""
    beta_t: float = 0.0
    """Cubic stiffening of the rotational spring, 1/rad^2: ``T = -K_ts Omega (1 + beta_t |Omega|^2)``."""
    _isotropic: bool = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        # Decided once: np.allclose costs ~0.1 ms, far more than the contact law itself.
        object.__setattr__(self, "_isotropic", all(
            np.allclose(K, K[0, 0] * np.eye(3), rtol=0.0, atol=1e-12 * max(1.0, abs(K[0, 0])))
            for K in (self.K_fs, self.K_fd, self.K_ts, self.K_td)
        ))

    @classmethod
    def make(cls, k_fs, k_fd, k_ts, k_td, beta_f: float = 0.0, beta_t: float = 0.0) -> ContactParams:
        """Build from scalars (isotropic), 3-vectors (diagonal in the contact frame) or 3x3 matrices."""
        return cls(
            _as_matrix(k_fs, "k_fs"),
            _as_matrix(k_fd, "k_fd"),
            _as_matrix(k_ts, "k_ts"),
            _as_matrix(k_td, "k_td"),
            float(beta_f),
            float(beta_t),
        )

    @property
    def isotropic(self) -> bool:
        """True when every matrix is a multiple of the identity (orientation does not matter)."""
        return self._isotropic

    def scaled(self, stiffness: float = 1.0, damping: float = 1.0) -> ContactParams:
        """A copy with stiffnesses multiplied by ``stiffness`` and dampings by ``damping``."""
        return ContactParams(
            self.K_fs * stiffness, self.K_fd * damping, self.K_ts * stiffness, self.K_td * damping,
            self.beta_f, self.beta_t,
        )


@dataclass(frozen=True)
class Inputs:
    """The paper's local-frame inputs at one instant (sec. II-C, III-B); correction 3 applies.

    All vectors and tensors are expressed in the local frame and taken about its origin.
    """

    m: float
    """Total mass, kg."""
    c: np.ndarray
    """CoM position ``c_l``, m."""
    dc: np.ndarray
    """CoM velocity, m/s."""
    ddc: np.ndarray
    """CoM acceleration, m/s^2."""
    I: np.ndarray
    """Rotational inertia about the local origin ``I_l = I_G - m [c_l]x^2``, kg m^2."""
    dI: np.ndarray
    """Its time derivative, kg m^2/s."""
    sigma: np.ndarray
    """Angular momentum about the local origin ``sigma_l = h_G + m c_l x dc_l``, kg m^2/s."""
    dsigma: np.ndarray
    """Its time derivative, N m."""


@dataclass(frozen=True)
class ImuPlacement:
    """The IMU's placement and motion in the local frame (eq. 26-28)."""

    R: np.ndarray
    """Orientation ``R_a,l`` (IMU frame to local frame)."""
    p: np.ndarray
    """Position ``p_a,l``, m."""
    v: np.ndarray
    """Velocity ``dp_a,l/dt`` in the local frame, m/s."""
    a: np.ndarray
    """Acceleration ``d2p_a,l/dt2`` in the local frame, m/s^2."""
    w: np.ndarray
    """Angular velocity ``omega_g,l`` of the IMU relative to the local frame, expressed in it, rad/s."""


@dataclass
class Jacobians:
    """Jacobians of a model function; ``None`` where the function does not depend on the block."""

    x: np.ndarray | None = None
    """With respect to ``(theta, t, w, v)`` (world-frame increments), rows x 12."""
    acc: np.ndarray | None = None
    """With respect to ``(dw, a)``, rows x 6."""
    wrench: np.ndarray | None = None
    """With respect to the contact wrench ``(F, T)``, rows x 6."""
    extra: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------
# Contact law, eq. (6)-(12)
# ----------------------------------------------------------------------------------------------


def contact_wrench(R, t, w, v, local_p_c, local_R_c, params: ContactParams, jacobian: bool = False):
    r"""Wrench of one flexible contact, force and moment about the world origin.

    Eq. (6)-(9) and (11) with corrections 1, 2 and 5::

        s  = R p_l + t - p_l                        (7)  displacement of the contact point
        ds = [w]x R p_l + v                         (9)
        F  = -K_fs s (1 + beta_f |s|^2) - K_fd ds   (6)
        T  = -K_ts Omega (1 + beta_t |Omega|^2) - K_td w + [R p_l + t]x F      (11), Omega = log R

    The rest placement is ``p_l`` itself: at zero deformation the local and world frames agree.

    Args:
        R, t: flexibility rotation (3x3) and translation (m).
        w, v: flexibility angular (rad/s, world) and linear (m/s) velocity.
        local_p_c, local_R_c: the contact's rest position (m) and orientation in the local frame.
        params: the contact's stiffness and damping in its own frame.
        jacobian: also return the 6x12 Jacobian with respect to ``(theta, t, w, v)``.

    Returns:
        ``wrench`` (6,) = (F [N], T [N m]) or ``(wrench, J)``.
    """
    Rp = R @ local_p_c
    s = Rp + t - local_p_c
    ds = _cross(w, Rp) + v
    Omega = so3.log(R)
    if params.isotropic:
        Kfs, Kfd, Kts, Ktd = params.K_fs, params.K_fd, params.K_ts, params.K_td
        aniso = False
    else:
        Rc = R @ local_R_c
        Kfs, Kfd, Kts, Ktd = (Rc @ K @ Rc.T for K in (params.K_fs, params.K_fd, params.K_ts, params.K_td))
        aniso = True
    gf = 1.0 + params.beta_f * (s @ s)
    gt = 1.0 + params.beta_t * (Omega @ Omega)
    ss = s * gf
    OO = Omega * gt
    F = -Kfs @ ss - Kfd @ ds
    p_w = Rp + t
    T = -Kts @ OO - Ktd @ w + _cross(p_w, F)
    wrench = np.concatenate([F, T])
    if not jacobian:
        return wrench
    S_Rp = so3.skew(Rp)
    # d(s (1 + beta |s|^2))/ds
    Ds = gf * _I3 + 2.0 * params.beta_f * np.outer(s, s)
    DO = gt * _I3 + 2.0 * params.beta_t * np.outer(Omega, Omega)
    # ds/dtheta = -[Rp]x ; d ds/dtheta = -[w]x [Rp]x
    dF_dth = Kfs @ Ds @ S_Rp + Kfd @ so3.skew(w) @ S_Rp
    dOmega_dth = so3.left_jacobian_inverse(Omega)
    dT0_dth = -Kts @ DO @ dOmega_dth
    if aniso:
        # d(K_world y)/dtheta = -[K y]x + K [y]x  for y held fixed (correction 5).
        dF_dth += so3.skew(Kfs @ ss) - Kfs @ so3.skew(ss) + so3.skew(Kfd @ ds) - Kfd @ so3.skew(ds)
        dT0_dth += so3.skew(Kts @ OO) - Kts @ so3.skew(OO) + so3.skew(Ktd @ w) - Ktd @ so3.skew(w)
    dF_dt = -Kfs @ Ds
    dF_dw = Kfd @ S_Rp
    dF_dv = -Kfd
    S_pw = so3.skew(p_w)
    S_F = so3.skew(F)
    J = np.zeros((6, 12))
    J[0:3, 0:3] = dF_dth
    J[0:3, 3:6] = dF_dt
    J[0:3, 6:9] = dF_dw
    J[0:3, 9:12] = dF_dv
    # d([p_w]x F) = -[F]x dp_w + [p_w]x dF, dp_w/dtheta = -[Rp]x, dp_w/dt = I
    J[3:6, 0:3] = dT0_dth + S_F @ S_Rp + S_pw @ dF_dth
    J[3:6, 3:6] = -S_F + S_pw @ dF_dt
    J[3:6, 6:9] = -Ktd + S_pw @ dF_dw
    J[3:6, 9:12] = S_pw @ dF_dv
    return wrench, J


def total_contact_wrench(R, t, w, v, contacts, jacobian: bool = False):
    """Sum of :func:`contact_wrench` over ``contacts`` (eq. 10, 12).

    Args:
        contacts: iterable of ``(local_p_c, local_R_c, params)`` for the active contacts.

    Returns:
        ``(wrench, per_contact)`` with ``per_contact`` an (n, 6) array, plus the summed 6x12
        Jacobian when ``jacobian`` is set.
    """
    per = []
    Jsum = np.zeros((6, 12))
    for p_l, R_l, params in contacts:
        if jacobian:
            wr, J = contact_wrench(R, t, w, v, p_l, R_l, params, jacobian=True)
            Jsum += J
        else:
            wr = contact_wrench(R, t, w, v, p_l, R_l, params)
        per.append(wr)
    per_arr = np.array(per).reshape(-1, 6)
    total = per_arr.sum(axis=0) if per else np.zeros(6)
    if jacobian:
        return total, per_arr, Jsum
    return total, per_arr


# ----------------------------------------------------------------------------------------------
# Newton-Euler, eq. (13)-(25)
# ----------------------------------------------------------------------------------------------


def required_wrench(R, t, w, v, dw, a, inp: Inputs, g: float = GRAVITY, jacobian: bool = False):
    r"""The external wrench the motion requires besides gravity (force, moment about the origin).

    Newton (eq. 15, 16) and Euler (eq. 22, 23) solved for the wrench, with corrections 2-3::

        F_req = m ([dw]x R c + [w]x^2 R c + 2 [w]x R dc + R ddc + a + g e_z)
        T_req = [w]x R I R^T w + R dI R^T w + R I R^T dw + [w]x R sigma + R dsigma
                + [t]x F_req + m [R c]x (a + g e_z)

    With ``F_req = F_c`` the first line is eq. (16); substituting ``[t]x F_c`` for ``[t]x F_req``
    the second is eq. (23).  Writing it with ``F_req`` keeps the residual of
    :func:`newton_euler_residual` equal to the unexplained external wrench about the origin.

    Returns:
        ``wrench`` (6,) or ``(wrench, Jacobians)`` with ``x`` (6x12) and ``acc`` (6x6) blocks.
    """
    m = inp.m
    Rc = R @ inp.c
    Rdc = R @ inp.dc
    Rddc = R @ inp.ddc
    RIRt = R @ inp.I @ R.T
    RdIRt = R @ inp.dI @ R.T
    Rs = R @ inp.sigma
    Rds = R @ inp.dsigma
    ag = a + g * E_Z
    w_Rc = _cross(w, Rc)
    F = m * (_cross(dw, Rc) + _cross(w, w_Rc) + 2.0 * _cross(w, Rdc) + Rddc + ag)
    Iw = RIRt @ w
    T = (_cross(w, Iw) + RdIRt @ w + RIRt @ dw + _cross(w, Rs) + Rds
         + _cross(t, F) + m * _cross(Rc, ag))
    wrench = np.concatenate([F, T])
    if not jacobian:
        return wrench
    Sw = so3.skew(w)
    S_Rc = so3.skew(Rc)
    S_t = so3.skew(t)
    # Derivatives of F. For a world vector u = R u_l: du/dtheta = -[u]x.
    dF_dth = m * (-so3.skew(dw) @ S_Rc - Sw @ Sw @ S_Rc - 2.0 * Sw @ so3.skew(Rdc) - so3.skew(Rddc))
    dF_dw = m * (-so3.skew(w_Rc) - Sw @ S_Rc - 2.0 * so3.skew(Rdc))
    dF_ddw = -m * S_Rc
    dF_da = m * _I3
    # d(R X R^T y)/dtheta = [theta]x X' y - X'[theta]x y = -[X' y]x + X'[y]x   (X' = R X R^T)
    dIw_dth = -so3.skew(Iw) + RIRt @ Sw
    dT_dth = (Sw @ dIw_dth - so3.skew(RdIRt @ w) + RdIRt @ Sw
              - so3.skew(RIRt @ dw) + RIRt @ so3.skew(dw)
              - Sw @ so3.skew(Rs) - so3.skew(Rds)
              + S_t @ dF_dth + m * so3.skew(ag) @ S_Rc)
    dT_dt = -so3.skew(F)
    dT_dw = -so3.skew(Iw) + Sw @ RIRt + RdIRt - so3.skew(Rs) + S_t @ dF_dw
    dT_ddw = RIRt + S_t @ dF_ddw
    dT_da = S_t @ dF_da + m * S_Rc
    Jx = np.zeros((6, 12))
    Jx[0:3, 0:3] = dF_dth
    Jx[0:3, 6:9] = dF_dw
    Jx[3:6, 0:3] = dT_dth
    Jx[3:6, 3:6] = dT_dt
    Jx[3:6, 6:9] = dT_dw
    Ja = np.zeros((6, 6))
    Ja[0:3, 0:3] = dF_ddw
    Ja[0:3, 3:6] = dF_da
    Ja[3:6, 0:3] = dT_ddw
    Ja[3:6, 3:6] = dT_da
    return wrench, Jacobians(x=Jx, acc=Ja)


def newton_euler_residual(R, t, w, v, dw, a, wrench_c, inp: Inputs, g: float = GRAVITY,
                          jacobian: bool = False):
    """The wrench the model leaves unexplained: ``required_wrench - wrench_c`` (eq. 16, 23).

    Zero when the contact wrench ``wrench_c`` = (F_c, T_c) (about the world origin) explains the
    motion; otherwise the external wrench (N, N m about the world origin) that is missing, e.g. a
    push on the hand.

    Returns:
        ``r`` (6,) or ``(r, Jacobians)`` with ``x`` (6x12), ``acc`` (6x6) and ``wrench`` (-I).
    """
    if jacobian:
        req, J = required_wrench(R, t, w, v, dw, a, inp, g, jacobian=True)
        J.wrench = -np.eye(6)
        return req - wrench_c, J
    return required_wrench(R, t, w, v, dw, a, inp, g) - wrench_c


def forward_dynamics(R, t, w, v, wrench_c, inp: Inputs, g: float = GRAVITY, jacobian: bool = False):
    r"""The flexibility acceleration ``(dw, a)`` that the contact wrench produces, eq. (24), (25).

    Solves the 6x6 linear system ``required_wrench(dw, a) = wrench_c`` in the accelerations; this
    is eq. (24) as corrected (correction 4) and eq. (25)::

        dw = R (I + m[c]x^2)^-1 R^T (T_c - [w]x R I R^T w - R dI R^T w - R dsigma - [w]x R sigma
             + m [R c]x (R ddc + 2 [w]x R dc + [w]x^2 R c) - [R c + t]x F_c)
        a  = F_c / m - (R ddc + 2 [w]x R dc + [w]x^2 R c + g e_z) + [R c]x dw

    Args:
        wrench_c: total contact (plus any known external) wrench about the world origin.

    Returns:
        ``acc`` (6,) = (dw [rad/s^2], a [m/s^2]) or ``(acc, Jacobians)`` where ``x`` (6x12) and
        ``wrench`` (6x6) are the derivatives of ``acc`` (implicit function theorem).
    """
    zero = np.zeros(3)
    r0 = required_wrench(R, t, w, v, zero, zero, inp, g)
    # required_wrench is affine in the accelerations: required = r0 + A (dw, a), with A its
    # acceleration Jacobian (see there), which depends on (R, t) only.
    m = inp.m
    S_Rc = so3.skew(R @ inp.c)
    S_t = so3.skew(t)
    A = np.empty((6, 6))
    A[0:3, 0:3] = -m * S_Rc
    A[0:3, 3:6] = m * _I3
    A[3:6, 0:3] = R @ inp.I @ R.T - m * (S_t @ S_Rc)
    A[3:6, 3:6] = m * (S_t + S_Rc)
    rhs = np.asarray(wrench_c, dtype=float) - r0
    try:
        if not jacobian:
            return np.linalg.solve(A, rhs)
        Ainv = np.linalg.inv(A)
    except np.linalg.LinAlgError as err:
        raise ModelError("Newton-Euler system is singular: check the mass and inertia inputs") from err
    acc = Ainv @ rhs
    # r(x, acc) = required(x, acc) - wrench = 0  =>  d acc = -A^-1 (dr/dx dx - d wrench)
    _, Jr = required_wrench(R, t, w, v, acc[:3], acc[3:], inp, g, jacobian=True)
    return acc, Jacobians(x=-Ainv @ Jr.x, wrench=Ainv)


# ----------------------------------------------------------------------------------------------
# IMU, eq. (26)-(28)
# ----------------------------------------------------------------------------------------------


def imu_readings(R, t, w, v, dw, a, imu: ImuPlacement, g: float = GRAVITY, jacobian: bool = False):
    r"""Gyrometer and accelerometer readings in the IMU frame, eq. (26)-(28), correction 6.

    ::

        y_g = R_a^T (R^T w + w_g,l)                                                  (26)
        y_a = R_a^T ([R^T dw]x p + [R^T w]x^2 p + 2 [R^T w]x dp + ddp + R^T (a + g e_z))  (28)

    Returns:
        ``y`` (6,) = (gyro [rad/s], accelerometer [m/s^2]) or ``(y, Jacobians)`` with ``x`` (6x12)
        and ``acc`` (6x6).
    """
    Rt = R.T
    u = Rt @ w
    ud = Rt @ dw
    p = imu.p
    ag = a + g * E_Z
    up = _cross(u, p)
    acc_l = _cross(ud, p) + _cross(u, up) + 2.0 * _cross(u, imu.v) + imu.a + Rt @ ag
    RaT = imu.R.T
    y = np.concatenate([RaT @ (u + imu.w), RaT @ acc_l])
    if not jacobian:
        return y
    # d(R^T y)/dtheta = R^T [y]x
    du_dth = Rt @ so3.skew(w)
    dacc_du = -so3.skew(up) - so3.skew(u) @ so3.skew(p) - 2.0 * so3.skew(imu.v)
    dacc_dud = -so3.skew(p)
    Jx = np.zeros((6, 12))
    Ja = np.zeros((6, 6))
    Jx[0:3, 0:3] = RaT @ du_dth
    Jx[0:3, 6:9] = RaT @ Rt
    Jx[3:6, 0:3] = RaT @ (dacc_du @ du_dth + dacc_dud @ Rt @ so3.skew(dw) + Rt @ so3.skew(ag))
    Jx[3:6, 6:9] = RaT @ dacc_du @ Rt
    Ja[3:6, 0:3] = RaT @ dacc_dud @ Rt
    Ja[3:6, 3:6] = RaT @ Rt
    return y, Jacobians(x=Jx, acc=Ja)


# ----------------------------------------------------------------------------------------------
# Centre of pressure
# ----------------------------------------------------------------------------------------------


def center_of_pressure(wrench, z0: float = 0.0, jacobian: bool = False, min_force: float = 1e-6):
    r"""Centre of pressure on the horizontal plane ``z = z0`` from the total contact wrench.

    For a wrench (F, T) with T about the world origin, the point p = (px, py, z0) where the
    moment is purely vertical: ``px = (z0 F_x - T_y) / F_z``, ``py = (T_x + z0 F_y) / F_z``.

    Returns:
        ``p`` (3,) in m or ``(p, J)`` with ``J`` the 3x6 Jacobian with respect to (F, T).  When the
        vertical force is below ``min_force`` (N) the CoP is undefined and NaN is returned.
    """
    F = wrench[:3]
    T = wrench[3:]
    Fz = F[2]
    if not Fz > min_force:
        p = np.array([np.nan, np.nan, z0])
        return (p, np.full((3, 6), np.nan)) if jacobian else p
    px = (z0 * F[0] - T[1]) / Fz
    py = (T[0] + z0 * F[1]) / Fz
    p = np.array([px, py, z0])
    if not jacobian:
        return p
    J = np.zeros((3, 6))
    J[0, 0] = z0 / Fz
    J[0, 2] = -px / Fz
    J[0, 4] = -1.0 / Fz
    J[1, 1] = z0 / Fz
    J[1, 2] = -py / Fz
    J[1, 3] = 1.0 / Fz
    return p, J


def wrench_about(wrench, point):
    """Move a wrench (F, T about the world origin) to be expressed about ``point``: (F, T - p x F)."""
    F = wrench[..., :3]
    T = wrench[..., 3:]
    return np.concatenate([F, T - np.cross(point, F)], axis=-1)
