"""Reduction tests of the smoother's linear algebra against independent dense or textbook code.

- The batch smoother's Gauss-Newton solve (``assemble`` + ``solve``, block-tridiagonal Cholesky
  with Jacobi scaling and one step of refinement) on a linear-Gaussian toy equals a Kalman filter
  followed by a Rauch-Tung-Striebel smoother (written here, textbook form): means, marginal
  covariances and lag-one cross-covariances.
- The block-tridiagonal solver and its covariances equal a dense solve and a dense inverse.
- The arrow (Schur complement) solve, with a global block shared by every step, equals the dense
  solve of the same system written with the global block as one variable.
- The fixed-lag window's incremental elimination (oldest first, with a previously eliminated
  step, or restarted from a frozen step's partial information) and back substitution equal a
  dense solve of the whole chain; its marginals equal the dense inverse's diagonal blocks.

The tolerances are relative to the solution's scale and reflect the conditioning of the random
systems (condition numbers up to ~1e4 here): 1e-9 leaves four digits for it in double precision.
"""

from __future__ import annotations

import numpy as np
import pytest

from flexforce.smoother import solvers
from flexforce.smoother.linearize import Linearization, assemble, covariances, solve, solve_arrow, solve_arrow_pair

RTOL = 1e-9


def _random_chain(rng, n: int, d: int):
    """A random symmetric positive definite block-tridiagonal system ``(Hd, B, g)`` as the sum of
    per-step and between-step least-squares factors (so that it is SPD by construction)."""
    Hd = np.zeros((n, d, d))
    B = np.zeros((n - 1, d, d))
    for k in range(n):
        J = rng.normal(size=(d + 2, d))
        Hd[k] += J.T @ J
    for k in range(n - 1):
        J0, J1 = rng.normal(size=(d, d)), rng.normal(size=(d, d))
        Hd[k] += J0.T @ J0
        Hd[k + 1] += J1.T @ J1
        B[k] = J0.T @ J1
    return Hd, B, rng.normal(size=(n, d))


def _dense(Hd, B):
    n, d = Hd.shape[0], Hd.shape[1]
    H = np.zeros((n * d, n * d))
    for k in range(n):
        H[k * d:(k + 1) * d, k * d:(k + 1) * d] = Hd[k]
    for k in range(n - 1):
        H[k * d:(k + 1) * d, (k + 1) * d:(k + 2) * d] = B[k]
        H[(k + 1) * d:(k + 2) * d, k * d:(k + 1) * d] = B[k].T
    return H


def _blocks(M, n, d):
    """Diagonal blocks (n, d, d) and upper lag-one blocks (n-1, d, d) of a dense (n d, n d) matrix."""
    diag = np.array([M[k * d:(k + 1) * d, k * d:(k + 1) * d] for k in range(n)])
    upper = np.array([M[k * d:(k + 1) * d, (k + 1) * d:(k + 2) * d] for k in range(n - 1)])
    return diag, upper


def _close(a, b, rtol=RTOL):
    np.testing.assert_allclose(a, b, rtol=0, atol=rtol * max(np.abs(b).max(), 1e-300))


# ----------------------------------------------------------------------------------------------
# Batch smoother on a linear toy == Kalman filter + RTS smoother
# ----------------------------------------------------------------------------------------------


def _kalman_rts(m0, P0, A, Q, C, R, ys):
    """Kalman filter (covariance form) then the Rauch-Tung-Striebel backward pass.

    Returns smoothed means (N, d), covariances (N, d, d) and lag-one cross-covariances
    ``cov(x_k, x_k+1)`` (N-1, d, d) = ``G_k P_k+1|N`` with the smoother gain
    ``G_k = P_k|k A^T P_k+1|k^-1``.
    """
    n, d = len(ys), len(m0)
    mf, Pf, mp, Pp = np.zeros((n, d)), np.zeros((n, d, d)), np.zeros((n, d)), np.zeros((n, d, d))
    m, P = m0, P0
    for k, y in enumerate(ys):
        if k > 0:
            m, P = A @ m, A @ P @ A.T + Q
        mp[k], Pp[k] = m, P
        S = C @ P @ C.T + R
        K = P @ C.T @ np.linalg.inv(S)
        m = m + K @ (y - C @ m)
        P = P - K @ S @ K.T
        mf[k], Pf[k] = m, P
    ms, Ps, Pc = mf.copy(), Pf.copy(), np.zeros((n - 1, d, d))
    for k in range(n - 2, -1, -1):
        G = Pf[k] @ A.T @ np.linalg.inv(Pp[k + 1])
        ms[k] = mf[k] + G @ (ms[k + 1] - mp[k + 1])
        Ps[k] = Pf[k] + G @ (Ps[k + 1] - Pp[k + 1]) @ G.T
        Pc[k] = G @ Ps[k + 1]
    return ms, Ps, Pc


def _whitener(cov):
    """``W`` with ``W^T W = cov^-1``."""
    return np.linalg.cholesky(np.linalg.inv(cov)).T


def test_batch_solve_on_a_linear_toy_equals_the_rts_smoother():
    """Linear-Gaussian chain ``x_k+1 = A x_k + w``, ``y_k = C x_k + v``, prior ``x_0 ~ N(m0, P0)``.
    Its negative log-posterior is a sum of whitened least-squares factors (the prior on step 0,
    the dynamics between steps, a measurement per step), linear in x: one Gauss-Newton step from
    x = 0 lands on the MAP, which for a linear-Gaussian model is the RTS smoother's mean, and the
    inverse of the Gauss-Newton matrix is its joint posterior covariance."""
    rng = np.random.default_rng(0)
    n, d, m = 40, 6, 3
    A = np.eye(d) + 0.05 * rng.normal(size=(d, d))
    Lq = 0.1 * rng.normal(size=(d, d))
    Q = Lq @ Lq.T + 1e-2 * np.eye(d)
    C = rng.normal(size=(m, d))
    R = np.diag(rng.uniform(0.05, 0.2, m))
    m0, P0 = rng.normal(size=d), np.diag(rng.uniform(0.5, 2.0, d))
    ys = rng.normal(size=(n, m))

    # Whitened residuals r = W (J x - b) and Jacobians at x = 0, in the smoother's layout.
    Wp, Wq, Wr = _whitener(P0), _whitener(Q), _whitener(R)
    prior = (-(Wp @ m0)[None, :], Wp[None, :, :])
    meas = (-(ys @ Wr.T), np.broadcast_to(Wr @ C, (n, m, d)).copy())
    dyn = (np.zeros((n - 1, d)), np.broadcast_to(-Wq @ A, (n - 1, d, d)).copy(),
           np.broadcast_to(Wq, (n - 1, d, d)).copy())
    lin = Linearization(unary={"prior": prior, "measurement": meas}, binary={"dynamics": dyn})
    Hd, B, g = assemble(lin, n, d)
    x, P = solve(Hd, B, g, want_cov=True)
    P2, Pc = covariances(Hd, B)

    ms, Ps, Pcs = _kalman_rts(m0, P0, A, Q, C, R, ys)
    _close(x, ms)
    _close(P, Ps)
    _close(P2, Ps)
    _close(Pc, Pcs)


# ----------------------------------------------------------------------------------------------
# Block-tridiagonal solver == dense solve
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n,d", [(1, 4), (2, 3), (25, 6)])
def test_block_tridiagonal_solve_equals_dense(n, d):
    rng = np.random.default_rng(n)
    Hd, B, g = _random_chain(rng, n, d)
    H = _dense(Hd, B)
    x, P = solvers.block_tridiag_solve(Hd, B, g, True)
    _close(x.ravel(), np.linalg.solve(H, g.ravel()))
    Hinv = np.linalg.inv(H)
    diag, upper = _blocks(Hinv, n, d)
    _close(P, diag)
    if n > 1:
        P2, Pc = solvers.block_tridiag_covariances(Hd, B)
        _close(P2, diag)
        _close(Pc, upper)


def test_block_tridiagonal_solve_rejects_an_indefinite_system():
    rng = np.random.default_rng(7)
    Hd, B, g = _random_chain(rng, 5, 3)
    Hd[2] -= 1e3 * np.eye(3)
    with pytest.raises(np.linalg.LinAlgError):
        solvers.block_tridiag_solve(Hd, B, g, False)


# ----------------------------------------------------------------------------------------------
# Arrow (Schur complement) solve == dense solve with the global block as one variable
# ----------------------------------------------------------------------------------------------


def _arrow_dense(Hd, B, g, cidx):
    """Dense solve of the per-step system restricted to ``x_k[cidx] = c`` for every k: with the
    map ``x = T z``, ``z = (a_0, ..., a_N-1, c)``, solve ``T^T H T z = T^T g``."""
    n, d = Hd.shape[0], Hd.shape[1]
    aidx = np.setdiff1d(np.arange(d), cidx)
    da, dc = len(aidx), len(cidx)
    T = np.zeros((n * d, n * da + dc))
    for k in range(n):
        for j, col in enumerate(aidx):
            T[k * d + col, k * da + j] = 1.0
        for j, col in enumerate(cidx):
            T[k * d + col, n * da + j] = 1.0
    H = _dense(Hd, B)
    Hz = T.T @ H @ T
    z = np.linalg.solve(Hz, T.T @ g.ravel())
    Pfull = T @ np.linalg.inv(Hz) @ T.T
    return (T @ z).reshape(n, d), Pfull


@pytest.mark.parametrize("n,cidx", [(12, [4, 5]), (8, [0]), (1, [1, 2])])
def test_arrow_solve_equals_dense(n, cidx):
    rng = np.random.default_rng(10 + n)
    d = 6
    Hd, B, g = _random_chain(rng, n, d)
    cidx = np.array(cidx)
    x_ref, P_ref = _arrow_dense(Hd, B, g, cidx)
    dx, P, Pc = solve_arrow(Hd, B, g, cidx, want_cov=True)
    _close(dx, x_ref)
    diag, upper = _blocks(P_ref, n, d)
    _close(P, diag)
    if n > 1:
        _close(Pc, upper)


def test_arrow_solve_without_global_columns_is_the_block_tridiagonal_solve():
    rng = np.random.default_rng(3)
    Hd, B, g = _random_chain(rng, 10, 5)
    dx, _, _ = solve_arrow(Hd, B, g, np.array([], dtype=int))
    _close(dx.ravel(), np.linalg.solve(_dense(Hd, B), g.ravel()))


def test_arrow_pair_gives_both_steps_of_the_dense_solve():
    """The secant's step (a curvature added to the global block) and the Gauss-Newton one from one
    elimination equal two dense solves; an indefinite addition gives None and keeps the other."""
    rng = np.random.default_rng(21)
    n, d = 9, 6
    Hd, B, g = _random_chain(rng, n, d)
    cidx = np.array([2, 5])
    M = rng.normal(size=(2, 2))
    M = M @ M.T
    Hq = Hd.copy()
    Hq[0][np.ix_(cidx, cidx)] += M  # the global block is the sum of the steps' blocks
    with_m, plain = solve_arrow_pair(Hd, B, g, cidx, M)
    _close(with_m, _arrow_dense(Hq, B, g, cidx)[0])
    _close(plain, _arrow_dense(Hd, B, g, cidx)[0])
    worse, plain2 = solve_arrow_pair(Hd, B, g, cidx, -1e6 * np.eye(2))
    assert worse is None
    _close(plain2, plain)


@pytest.mark.parametrize("n,d", [(1, 3), (30, 7)])
def test_single_right_hand_side_substitution_equals_the_matrix_form(n, d):
    rng = np.random.default_rng(30 + n)
    Hd, B, g = _random_chain(rng, n, d)
    Ld, C = solvers.block_tridiag_factor(Hd, B)
    x = solvers.block_tridiag_substitute_vec(Ld, C, g)
    _close(x, solvers.block_tridiag_substitute(Ld, C, g[:, :, None])[:, :, 0])
    _close(x.ravel(), np.linalg.solve(_dense(Hd, B), g.ravel()))


def test_assembly_step_by_step_equals_the_dense_normal_equations():
    """``assemble`` (every family formed step by step) equals ``J^T J`` and ``-J^T r`` of the
    stacked rows written densely: unary families over every step and over the first step only
    (a prior), binary ones over successive steps, with columns they never touch."""
    rng = np.random.default_rng(5)
    n, D = 7, 5
    J_u = rng.normal(size=(n, 3, D))
    J_u[:, :, 4] = 0.0  # a column this family never touches
    J_p = rng.normal(size=(1, 2, D))
    J0, J1 = rng.normal(size=(n - 1, 4, D)), rng.normal(size=(n - 1, 4, D))
    J0[:, :, 0] = 0.0
    r_u, r_p, r_b = rng.normal(size=(n, 3)), rng.normal(size=(1, 2)), rng.normal(size=(n - 1, 4))
    lin = Linearization(unary={"u": (r_u, J_u), "prior": (r_p, J_p)}, binary={"b": (r_b, J0, J1)})
    rows, res = [], []
    for k in range(n):
        row = np.zeros((3, n * D))
        row[:, k * D:(k + 1) * D] = J_u[k]
        rows.append(row)
        res.append(r_u[k])
    row = np.zeros((2, n * D))
    row[:, :D] = J_p[0]
    rows.append(row)
    res.append(r_p[0])
    for k in range(n - 1):
        row = np.zeros((4, n * D))
        row[:, k * D:(k + 1) * D] = J0[k]
        row[:, (k + 1) * D:(k + 2) * D] = J1[k]
        rows.append(row)
        res.append(r_b[k])
    J, r = np.vstack(rows), np.concatenate(res)
    Hd, B, g = assemble(lin, n, D)
    diag, upper = _blocks(J.T @ J, n, D)
    _close(Hd, diag)
    _close(B, upper)
    _close(g.ravel(), -J.T @ r)


def test_r_factor_is_the_triangular_factor_of_a_qr():
    """The R-only QR (LAPACK's geqrf) gives ``R^T R = M^T M`` with ``R`` upper triangular, as
    ``np.linalg.qr``'s up to the signs of its rows; a NaN gives a NaN factor, not an exception."""
    from flexforce.smoother.evidence import _r_factor

    rng = np.random.default_rng(8)
    for shape in ((9, 5), (4, 6)):
        M = rng.normal(size=shape)
        R = _r_factor(M)
        assert R.shape == (min(shape), shape[1])
        assert np.allclose(np.tril(R, -1), 0.0)
        _close(R.T @ R, M.T @ M)
        _close(np.abs(R), np.abs(np.linalg.qr(M)[1]))
    M[1, 2] = np.nan
    assert np.isnan(_r_factor(M)).all()


# ----------------------------------------------------------------------------------------------
# Fixed-lag window elimination == dense solve
# ----------------------------------------------------------------------------------------------


def _split_chain(rng, n, d):
    """The same kind of chain split as the window stores it: ``U`` (own factors and the link from
    the previous step), ``Fw`` (the link to the next step), ``B`` and the right-hand sides."""
    U = np.zeros((n, d, d))
    Fw = np.zeros((n, d, d))
    B = np.zeros((n - 1, d, d))
    gU, gF = rng.normal(size=(n, d)), np.zeros((n, d))
    for k in range(n):
        J = rng.normal(size=(d + 2, d))
        U[k] += J.T @ J
    for k in range(n - 1):
        J0, J1 = rng.normal(size=(d, d)), rng.normal(size=(d, d))
        Fw[k] += J0.T @ J0
        U[k + 1] += J1.T @ J1
        B[k] = J0.T @ J1
        gF[k] = rng.normal(size=d)
    return U, gU, Fw, gF, B


def _eliminate(U, gU, Fw, gF, B, *, first_partial=False, Sp0=None, rp0=None, Cprev=None, yprev=None):
    m, d = U.shape[0], U.shape[1]
    Ld, C, y = np.zeros((m, d, d)), np.zeros((m, d, d)), np.zeros((m, d))
    Sp, rp = np.zeros((m, d, d)), np.zeros((m, d))
    has_prev = Cprev is not None
    solvers.window_eliminate(Sp0 if Sp0 is not None else np.zeros((d, d)), rp0 if rp0 is not None else np.zeros(d),
                             first_partial, U, gU, Fw, gF, np.ascontiguousarray(B),
                             Cprev if has_prev else np.zeros((d, d)), yprev if has_prev else np.zeros(d), has_prev,
                             Ld, C, y, Sp, rp)
    return Ld, C, y, Sp, rp


def _back_substitute(Ld, C, y):
    n, d = y.shape
    x = np.zeros((n, d))
    solvers.window_back_substitute(Ld, C, y, np.arange(n - 1, -1, -1), x)
    return x


def _window_dense(U, gU, Fw, gF, B):
    Hd = U + Fw
    return _dense(Hd, B), (gU + gF).ravel()


def test_window_elimination_equals_dense():
    rng = np.random.default_rng(21)
    n, d = 15, 6
    U, gU, Fw, gF, B = _split_chain(rng, n, d)
    H, g = _window_dense(U, gU, Fw, gF, B)
    Ld, C, y, _, _ = _eliminate(U, gU, Fw, gF, B)
    _close(_back_substitute(Ld, C, y).ravel(), np.linalg.solve(H, g))
    P = np.zeros((n, d, d))
    solvers.window_marginals(Ld, C, np.arange(n - 1, -1, -1), P)
    _close(P, _blocks(np.linalg.inv(H), n, d)[0])


def test_window_elimination_continues_an_eliminated_chain():
    """Eliminate the oldest steps, then the newest ones on top of them (``has_prev``: the last
    eliminated step's ``C`` and ``y``); back substitution over the whole chain equals the dense
    solve -- the window's state after steps were added one update at a time."""
    rng = np.random.default_rng(22)
    n, d, split = 12, 5, 7
    U, gU, Fw, gF, B = _split_chain(rng, n, d)
    H, g = _window_dense(U, gU, Fw, gF, B)
    old = _eliminate(U[:split], gU[:split], Fw[:split], gF[:split], B[:split])
    # the last old step's link to the first new one: C = (Ld^-1 B)^T
    Cl = np.linalg.solve(old[0][-1], B[split - 1]).T
    new = _eliminate(U[split:], gU[split:], Fw[split:], gF[split:], B[split:], Cprev=Cl, yprev=old[2][-1])
    Ld = np.concatenate([old[0], new[0]])
    C = np.concatenate([old[1][:-1], Cl[None], new[1]])
    y = np.concatenate([old[2], new[2]])
    _close(_back_substitute(Ld, C, y).ravel(), np.linalg.solve(H, g))


def test_window_elimination_restarted_from_a_frozen_step():
    """Re-eliminate the newest steps (relinearised) from a frozen step's partial information
    (``first_partial``): the factors of the earlier steps stay as they were eliminated."""
    rng = np.random.default_rng(23)
    n, d, j = 10, 4, 6
    U, gU, Fw, gF, B = _split_chain(rng, n, d)
    H, g = _window_dense(U, gU, Fw, gF, B)
    full = _eliminate(U, gU, Fw, gF, B)
    # the newest steps change (relinearised): their own factors
    U2, gU2, Fw2, gF2, B2 = U.copy(), gU.copy(), Fw, gF, B
    more = _split_chain(rng, n - j, d)
    U2[j + 1:] += more[0][1:]
    gU2[j + 1:] += more[1][1:]
    H2, g2 = _window_dense(U2, gU2, Fw2, gF2, B2)
    again = _eliminate(U2[j:], gU2[j:], Fw2[j:], gF2[j:], B2[j:], first_partial=True, Sp0=full[3][j], rp0=full[4][j])
    Ld = np.concatenate([full[0][:j], again[0]])
    C = np.concatenate([full[1][:j], again[1]])
    y = np.concatenate([full[2][:j], again[2]])
    _close(_back_substitute(Ld, C, y).ravel(), np.linalg.solve(H2, g2))
    assert not np.allclose(np.linalg.solve(H2, g2), np.linalg.solve(H, g))  # the change mattered
