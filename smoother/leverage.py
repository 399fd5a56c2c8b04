r"""The residuals' own variances: smoothed residuals standardised by their covariance.

A smoothed residual is smaller than its noise: the fit absorbs part of it.  For the whitened
linear(ised) model ``r = J x - e`` with ``e`` unit white noise and the Gauss-Newton estimate
``x = P J^T e`` (``P = (J^T J)^-1``), the residual is ``r = (I - J P J^T) e``: its covariance is
``I - H`` with the hat matrix ``H = J P J^T``, so row ``i`` has variance ``1 - h_i``,
``h_i = J_i P J_i^T`` (the row's *leverage*).  A family whose noise is large against what the
other factors say (IMU, ``h`` small) keeps most of it; one whose noise is small (the integration
factors, ``h`` near 1) keeps almost none: measured on a clean 2.5 s stand, integration residuals
of 0.002-0.1 sigma, Newton-Euler about 0.07 sigma.  Dividing by ``sqrt(1 - h_i)`` makes every
row unit-variance under the model, whatever its family.

Every factor touches one step (``h_i = J_i P_kk J_i^T``) or two successive ones (integration:
``[J0 J1] [[P_kk, P_k,k+1], [., P_k+1,k+1]] [J0 J1]^T``), so the per-step marginal and lag-one
covariances of the fit (one block-tridiagonal elimination) give every leverage.  The robust
Newton-Euler family enters the hat matrix with its Huber weights (``sqrt(w)`` times its rows, as
the fit); its reported residual is the unweighted one.
"""

from __future__ import annotations

import numpy as np

from flexforce.factors.core import njit
from flexforce.smoother.linearize import Trajectory, assemble, drop_global_walks, global_columns, linearize, solve_arrow

VAR_FLOOR = 1e-12
"""Below this residual variance (in units of the noise's) a row is exactly fitted: not testable (NaN)."""


def residual_variances(prob, traj: Trajectory, P: np.ndarray | None = None,
                       Pc: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """``1 - h`` for every row of every family, in the layout of
    :func:`flexforce.smoother.result.family_residuals` (family -> (N, k), NaN where absent).

    ``P`` (N, D, D), ``Pc`` (N-1, D, D): the fit's marginal and lag-one covariances (computed here
    when not given: one elimination of the Gauss-Newton system at ``traj``, constant effects as one
    global block as in the batch fit).
    """
    n, nc, D = prob.n, prob.nc, prob.state_dim
    lin = linearize(prob, traj)  # robust: the weighted rows the fit used
    cidx = global_columns(prob)
    if P is None or Pc is None:
        Hd, B, g = assemble(drop_global_walks(prob, lin) if cidx.size else lin, n, D)
        _, P, Pc = solve_arrow(Hd, B, g, cidx, want_cov=True)
    assert P is not None and Pc is not None

    def unary(J):
        m = J.shape[0]
        return 1.0 - np.einsum("kid,kde,kie->ki", J, P[:m], J)

    out: dict[str, np.ndarray] = {}
    v_int = np.full((n, 12), np.nan)
    if n > 1:
        _, J0, J1 = lin.binary["integration"]
        h = (np.einsum("kid,kde,kie->ki", J0, P[:-1], J0) + np.einsum("kid,kde,kie->ki", J1, P[1:], J1)
             + 2.0 * np.einsum("kid,kde,kie->ki", J0, Pc, J1))
        v_int[:-1] = 1.0 - h
    out["integration"] = v_int
    out["newton_euler"] = unary(lin.unary["newton_euler"][1])
    out["imu"] = unary(lin.unary["imu"][1])
    vc = np.full((n, 6 * nc), np.nan)
    for i in range(nc):
        v = unary(lin.unary[f"contact/{i}"][1])
        vc[:, 6 * i:6 * i + 6] = np.where(prob.active[:, i, None], v, np.nan)
    out["contact"] = vc
    if prob.use_ft:
        vf = np.full((n, 6 * nc), np.nan)
        for i in range(nc):
            v = unary(lin.unary[f"ft/{i}"][1])
            measured = prob.active[:, i, None] & np.isfinite(prob.y_ft[:, i])
            vf[:, 6 * i:6 * i + 6] = np.where(measured, v, np.nan)
        out["ft"] = vf
    return {k: np.where(v > VAR_FLOOR, v, np.nan) for k, v in out.items()}


def standardized_residuals(residuals: dict[str, np.ndarray], variances: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Whitened residuals divided by the square roots of their own variances (family -> (N, k))."""
    out = {}
    for fam, r in residuals.items():
        v = variances.get(fam)
        out[fam] = r / np.sqrt(v) if v is not None and v.shape == r.shape else r.copy()
    return out


def _chain_gains(Hd, B):
    """Scaled block-tridiagonal ``H``: Jacobi scale ``s`` (N, d), marginals ``P`` of the scaled
    system and the gains ``G_k = -Ld_k^-T C_k^T`` with ``P_k,l = G_k P_k+1,l`` (``l > k``)."""
    from flexforce.smoother import solvers

    s = 1.0 / np.sqrt(np.maximum(np.diagonal(Hd, axis1=1, axis2=2), 1e-300))
    Hs = np.ascontiguousarray(Hd * s[:, :, None] * s[:, None, :])
    Bs = np.ascontiguousarray(B * s[:-1, :, None] * s[1:, None, :])
    Ld, C = solvers._block_cholesky(Hs, Bs)
    P, _ = solvers._marginals(Ld, C)
    eye = np.eye(Hd.shape[1])
    M = np.linalg.solve(Ld, np.broadcast_to(eye, Ld.shape))  # Ld^-1
    G = -(M.transpose(0, 2, 1)[:-1] @ C.transpose(0, 2, 1))
    return s, P, G


@njit
def _lag_covariances(Jall, G, PJ, L, out):
    """``out[k, i, h] = -J_k,i G_k .. G_k+h-1 P_k+h J_k+h,i^T`` for ``h = 1 .. L`` (the rows
    ``Jall`` (N, r, d), the gains ``G`` (N-1, d, d), ``PJ[k] = P_k J_k^T`` (N, d, r))."""
    n, r, d = Jall.shape
    A = np.empty((r, d))
    T = np.empty((r, d))
    for k in range(n - 1):
        for i in range(r):
            for e in range(d):
                A[i, e] = Jall[k, i, e]
        for h in range(1, min(L, n - 1 - k) + 1):
            Gm = G[k + h - 1]
            for i in range(r):
                for e in range(d):
                    T[i, e] = 0.0
                for f in range(d):
                    a = A[i, f]
                    if a != 0.0:
                        for e in range(d):
                            T[i, e] += a * Gm[f, e]
            for i in range(r):
                acc = 0.0
                for e in range(d):
                    A[i, e] = T[i, e]
                    acc += T[i, e] * PJ[k + h, e, i]
                out[k, i, h] = -acc


def residual_lag_correlations(prob, traj: Trajectory, variances: dict[str, np.ndarray], max_lag: int,
                              residuals: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Correlation of each standardised residual row with the same axis ``h`` steps later,
    ``h = 0 .. max_lag``: family -> (N, k, max_lag + 1) (``[..., 0] = 1``, NaN where absent).

    The residuals of a smoother are correlated in time (``cov(r_i, r_j) = -h_ij``, the hat
    matrix's off-diagonal): the cross-covariances ``P_k,k+h`` of the states come from the chain's
    block Cholesky factor (``P_k,l = -Ld_k^-T C_k^T P_k+1,l``).  The constant effects' columns, if
    any, are held (their rank-``dim`` share of the correlation is left out).  The integration
    family's correlations are its standardised ``residuals``' sample autocorrelations
    (:func:`empirical_lag_correlations`; left out without ``residuals``).
    """
    n, nc, D = prob.n, prob.nc, prob.state_dim
    lin = linearize(prob, traj)
    cidx = global_columns(prob)
    Hd, B, _ = assemble(drop_global_walks(prob, lin) if cidx.size else lin, n, D)
    aidx = np.setdiff1d(np.arange(D), cidx)
    Hd, B = Hd[:, aidx][:, :, aidx], B[:, aidx][:, :, aidx]
    s, P, G = _chain_gains(Hd, B)
    L = int(max(0, min(max_lag, n - 1)))

    def rows(J):  # Jacobian rows in the scaled per-step coordinates
        return J[:, :, aidx] * s[:J.shape[0], None, :]

    fams: dict[str, tuple] = {"newton_euler": ("u", [rows(lin.unary["newton_euler"][1])]),
                              "imu": ("u", [rows(lin.unary["imu"][1])]),
                              "contact": ("u", [rows(lin.unary[f"contact/{i}"][1]) for i in range(nc)])}
    if prob.use_ft:
        fams["ft"] = ("u", [rows(lin.unary[f"ft/{i}"][1]) for i in range(nc)])
    out: dict[str, np.ndarray] = {}
    for fam, (_, Js) in fams.items():
        Jall = np.concatenate(Js, axis=1)  # (N, k, d)
        c = np.full((n, Jall.shape[1], L + 1), np.nan)
        c[:, :, 0] = 1.0
        # cov(r_k, r_k+h) = -J_k Q_h[k] P_k+h J_k+h^T (same axis), Q_h[k] = G_k .. G_k+h-1
        if L:
            Jc = np.ascontiguousarray(Jall)
            PJ = np.ascontiguousarray(np.einsum("kde,kie->kdi", P, Jc))
            _lag_covariances(Jc, np.ascontiguousarray(G), PJ, L, c)
        out[fam] = c
    # to correlations of the standardised rows
    for fam, c in out.items():
        v = variances.get(fam)
        if v is None:
            continue
        sd = np.sqrt(v)
        for h in range(1, L + 1):
            den = np.full_like(sd, np.nan)
            den[:n - h] = sd[:n - h] * sd[h:]
            c[:, :, h] = c[:, :, h] / den
        c[~np.isfinite(sd), 0] = np.nan
    if residuals is not None and "integration" in residuals and "integration" in variances:
        out["integration"] = empirical_lag_correlations(residuals["integration"] / np.sqrt(variances["integration"]), L)
    return out


def empirical_lag_correlations(z: np.ndarray, max_lag: int) -> np.ndarray:
    """Sample autocorrelation of each column of ``z`` (N, k) at lags ``0 .. max_lag``, the same for
    every step: (N, k, max_lag + 1) (the integration family's: its leverages are within ``1e-5``
    of one, and the model's cross terms cancel to the digits the solver keeps)."""
    n, k = z.shape
    out = np.full((n, k, max_lag + 1), np.nan)
    for j in range(k):
        x = z[:, j]
        ok = np.isfinite(x)
        if ok.sum() < 3:
            continue
        xc = np.where(ok, x - np.mean(x[ok]), 0.0)
        den = float(np.sum(xc * xc)) or 1.0
        acf = np.array([1.0] + [float(np.sum(xc[h:] * xc[:-h])) / den for h in range(1, max_lag + 1)])
        out[:, j, :] = acf[None, :]
        out[~ok, j, :] = np.nan
    return out
