r"""Linear algebra of the smoothers' Gauss-Newton systems (numba).

The normal equations of a chain of steps are block tridiagonal (each factor touches one step or
two successive ones): their block Cholesky factorisation is a square-root information filter and
its back substitution the RTS smoother.  This module holds that solver, the marginal and lag-one
covariances, the log-determinant (the evidence's) and the fixed-lag window's incremental
elimination.  The physics the systems are built from is :mod:`flexforce.factors.core`.
"""

from __future__ import annotations

import numpy as np

from flexforce.factors.core import njit, so3_exp, trsv_lower_inplace, trsv_upper_t_inplace

# ----------------------------------------------------------------------------------------------
# Block-tridiagonal solver (the Gauss-Newton system of a chain)
# ----------------------------------------------------------------------------------------------


@njit
def _substitute_rows(L, X, m, transposed):
    """``X[:, :m] <- L^-1 X[:, :m]`` (forward substitution, top row first) or, ``transposed``,
    ``L^-T X[:, :m]`` (back substitution, bottom row first) for lower-triangular ``L`` (d, d), by
    rows of ``X`` (memory order: each entry the same operations as a column's substitution,
    ``trsv_lower_inplace`` / ``trsv_upper_t_inplace``)."""
    d = L.shape[0]
    for s in range(d):
        i = d - 1 - s if transposed else s
        for t in range(s):  # the rows already solved, in increasing order
            if transposed:
                k = i + 1 + t
                lik = L[k, i]
            else:
                k = t
                lik = L[i, k]
            for j in range(m):
                X[i, j] -= lik * X[k, j]
        inv = L[i, i]
        for j in range(m):
            X[i, j] = X[i, j] / inv


@njit
def _forward_rows(L, X, m):
    """``X[:, :m] <- L^-1 X[:, :m]`` for lower-triangular ``L`` (d, d), by rows of ``X``
    (:func:`_substitute_rows`)."""
    _substitute_rows(L, X, m, False)


@njit
def _trsm_lower(L, B):
    """L^-1 B for lower-triangular L (d, d) and B (d, m) (:func:`_forward_rows`)."""
    X = B.copy()
    _forward_rows(L, X, X.shape[1])
    return X


@njit
def _trsv_lower(L, b):
    x = b.copy()
    trsv_lower_inplace(L, x)
    return x


@njit
def _trsv_upper_t(L, b):
    """L^-T b for lower-triangular L."""
    x = b.copy()
    trsv_upper_t_inplace(L, x)
    return x


@njit
def _trsm_upper_t(L, B):
    """L^-T B for lower-triangular L (d, d) and B (d, m) (:func:`_substitute_rows`)."""
    X = B.copy()
    _substitute_rows(L, X, X.shape[1], True)
    return X


@njit
def _block_cholesky(D, B):
    """Block Cholesky ``H = L L^T`` of the block-tridiagonal ``H`` (diagonal blocks ``D``, upper
    blocks ``B``): the diagonal factors ``Ld`` (N, d, d) and ``C_k = L_k+1,k`` (N-1, d, d)."""
    n, d = D.shape[0], D.shape[1]
    Ld = np.empty((n, d, d))
    C = np.empty((max(n - 1, 0), d, d))
    S = D[0].copy()
    for k in range(n):
        if k > 0:
            S = D[k] - C[k - 1] @ C[k - 1].T
        Ld[k] = np.linalg.cholesky(S)
        if k < n - 1:
            C[k] = _trsm_lower(Ld[k], B[k]).T.copy()
    return Ld, C


@njit
def _marginals(Ld, C):
    """Diagonal blocks ``P`` and lag-one blocks ``Pc`` of ``H^-1`` from its block Cholesky factor:
    ``P_k = M_k^T (I + C_k^T P_k+1 C_k) M_k``, ``Pc_k = -M_k^T C_k^T P_k+1`` with ``M_k = L_kk^-1``
    (block row ``k`` of ``L^T H^-1 = L^-1``)."""
    n, d = Ld.shape[0], Ld.shape[1]
    P = np.empty((n, d, d))
    Pc = np.empty((max(n - 1, 0), d, d))
    eye = np.eye(d)
    for k in range(n - 1, -1, -1):
        M = _trsm_lower(Ld[k], eye)
        if k == n - 1:
            P[k] = M.T @ M
        else:
            CP = C[k].T @ P[k + 1]
            P[k] = M.T @ (eye + CP @ C[k]) @ M
            Pc[k] = -(M.T @ CP)
    return P, Pc


@njit
def block_tridiag_factor(D, B):
    """The block Cholesky factor ``H = L L^T`` of ``H`` as in :func:`block_tridiag_solve_multi`:
    ``(Ld, C)`` for :func:`block_tridiag_substitute` and :func:`block_tridiag_marginals` (one
    factorisation for several solves: the iterative refinement's, the covariances).  Raises
    ``np.linalg.LinAlgError`` when ``H`` is not positive definite."""
    return _block_cholesky(D, B)


@njit
def block_tridiag_substitute(Ld, C, G):
    """``X = H^-1 G`` (N, d, m) from ``H``'s block Cholesky factor (:func:`block_tridiag_factor`):
    forward then back substitution."""
    n, d, m = G.shape[0], G.shape[1], G.shape[2]
    Y = np.empty((n, d, m))
    for k in range(n):
        rhs = G[k].copy()
        if k > 0:
            rhs -= C[k - 1] @ Y[k - 1]
        Y[k] = _trsm_lower(Ld[k], rhs)
    X = np.empty((n, d, m))
    X[n - 1] = _trsm_upper_t(Ld[n - 1], Y[n - 1])
    for k in range(n - 2, -1, -1):
        X[k] = _trsm_upper_t(Ld[k], Y[k] - C[k].T @ X[k + 1])
    return X


@njit
def block_tridiag_substitute_vec(Ld, C, g):
    """``x = H^-1 g`` for one right-hand side ``g`` (N, d), as :func:`block_tridiag_substitute`:
    the products written as row dot products (forward) and column updates (back) on one array, a
    third of the time of the matrix form, whose per-step products are too small for BLAS to pay
    for its calls and temporaries (measured: 9 against 29 ms at N = 2025, d = 37)."""
    n, d = g.shape[0], g.shape[1]
    x = g.copy()
    for k in range(n):  # forward: y_k = L_kk^-1 (g_k - C_k-1 y_k-1)
        if k > 0:
            for i in range(d):
                acc0 = 0.0
                acc1 = 0.0
                j = 0
                while j + 1 < d:  # two accumulators: the additions' latency, not their count, bounds it
                    acc0 += C[k - 1, i, j] * x[k - 1, j]
                    acc1 += C[k - 1, i, j + 1] * x[k - 1, j + 1]
                    j += 2
                if j < d:
                    acc0 += C[k - 1, i, j] * x[k - 1, j]
                x[k, i] -= acc0 + acc1
        for i in range(d):
            acc = x[k, i]
            for j in range(i):
                acc -= Ld[k, i, j] * x[k, j]
            x[k, i] = acc / Ld[k, i, i]
    for k in range(n - 1, -1, -1):  # back: x_k = L_kk^-T (y_k - C_k^T x_k+1)
        if k < n - 1:
            for j in range(d):
                xj = x[k + 1, j]
                for i in range(d):
                    x[k, i] -= C[k, j, i] * xj
        for i in range(d - 1, -1, -1):
            xi = x[k, i] / Ld[k, i, i]
            x[k, i] = xi
            for j in range(i):
                x[k, j] -= Ld[k, i, j] * xi
    return x


@njit
def block_tridiag_marginals(Ld, C):
    """``(P, Pc)``, the diagonal and lag-one blocks of ``H^-1``, from ``H``'s block Cholesky factor
    (:func:`block_tridiag_factor`, :func:`_marginals`)."""
    return _marginals(Ld, C)


@njit
def block_tridiag_solve_multi(D, B, G, want_cov):
    """Solve ``H X = G`` for ``H`` symmetric positive definite, block tridiagonal, with ``m``
    right-hand sides ``G`` (N, d, m) -> ``X`` (N, d, m).

    ``D`` (N, d, d) diagonal blocks, ``B`` (N-1, d, d) upper blocks ``H[k, k+1]``.  Block
    Cholesky ``H = L L^T`` (``L`` block lower bidiagonal: ``L_kk``, ``C_k = L_k+1,k``), i.e. a
    square-root information filter, then back substitution (its RTS smoother); one factorisation
    serves every column (the batch smoother's arrow system: the state's right-hand side and the
    border columns of the global effect parameters).  With ``want_cov`` also returns the marginal
    covariances ``P`` (N, d, d) and the lag-one cross blocks ``Pc`` (N-1, d, d) of ``H^-1`` (see
    :func:`_marginals`).  Raises ``np.linalg.LinAlgError`` when ``H`` is not positive definite.
    """
    d = G.shape[1]
    Ld, C = _block_cholesky(D, B)
    X = block_tridiag_substitute(Ld, C, G)
    if want_cov:
        P, Pc = _marginals(Ld, C)
        return X, P, Pc
    return X, np.empty((0, d, d)), np.empty((0, d, d))


@njit
def block_tridiag_solve(D, B, g, want_cov):
    """:func:`block_tridiag_solve_multi` with one right-hand side ``g`` (N, d) -> ``(x, P)``."""
    n, d = g.shape[0], g.shape[1]
    X, P, _ = block_tridiag_solve_multi(D, B, g.copy().reshape((n, d, 1)), want_cov)
    return X.reshape((n, d)), P


@njit
def block_tridiag_covariances(D, B):
    """Marginal covariances of ``H^-1`` for ``H`` as in :func:`block_tridiag_solve_multi`: the
    diagonal blocks ``P`` (N, d, d) and the lag-one cross blocks ``Pc`` (N-1, d, d),
    ``Pc[k] = (H^-1)[k, k+1]`` (the smoother's lag-one covariance)."""
    Ld, C = _block_cholesky(D, B)
    return _marginals(Ld, C)


@njit
def block_factor_logdet(Ld):
    """``log det H`` from the diagonal blocks ``Ld`` of ``H``'s block Cholesky factor
    (:func:`block_tridiag_factor`): twice the sum of the logs of their pivots."""
    out = 0.0
    for k in range(Ld.shape[0]):
        for i in range(Ld.shape[1]):
            out += 2.0 * np.log(Ld[k, i, i])
    return out


@njit
def block_tridiag_logdet(D, B):
    """``log det H`` for ``H`` symmetric positive definite, block tridiagonal (as
    :func:`block_tridiag_solve_multi`): twice the sum of the logs of the block Cholesky pivots.
    Raises ``np.linalg.LinAlgError`` when ``H`` is not positive definite."""
    return block_factor_logdet(_block_cholesky(D, B)[0])


# ----------------------------------------------------------------------------------------------
# Fixed-lag window (smoother/fixed_lag.py): incremental block elimination, oldest first
# ----------------------------------------------------------------------------------------------


@njit
def retract_core(Rb, qb, Wb, dx, p, S):
    """Move the core state and the wrenches of the linearisation point at ring position ``p`` by
    its correction ``dx[p]`` (``R <- exp(dx_rot) R``, the rest ``+ dx``; ``S`` the state
    dimension); ``dx`` is left as it is."""
    nc = Wb.shape[1]
    Rb[p] = so3_exp(dx[p, :3]) @ Rb[p]
    for i in range(S - 3):
        qb[p, i] += dx[p, 3 + i]
    for c in range(nc):
        for j in range(6):
            Wb[p, c, j] += dx[p, S + 6 * c + j]


@njit
def window_retract(Rb, qb, Wb, eb, dx, positions, S):
    """Move the linearisation points at ring positions ``positions`` to the current estimate
    (:func:`retract_core`, the effects' unknowns ``+ dx``) and zero ``dx``."""
    nc = Wb.shape[1]
    for kk in range(positions.shape[0]):
        p = positions[kk]
        retract_core(Rb, qb, Wb, dx, p, S)
        for i in range(eb.shape[1]):
            eb[p, i] += dx[p, S + 6 * nc + i]
        dx[p, :] = 0.0


@njit
def _trsm_lower_rows_t(L, B, X, out):
    """``out = (L^-1 B)^T`` for lower-triangular ``L`` (d, d), by rows of ``B`` (memory order;
    each entry the same operations as :func:`_trsm_lower`'s); ``X`` (d, d) scratch."""
    d = L.shape[0]
    ncol = B.shape[1]
    for i in range(d):
        for j in range(ncol):
            X[i, j] = B[i, j]
    _forward_rows(L, X, ncol)
    for i in range(d):
        for j in range(ncol):
            out[j, i] = X[i, j]


@njit
def window_eliminate(Sp0, rp0, first_partial, U, gU, Fw, gF, B, Cprev, yprev, has_prev, Ld, C, y, Sp, rp):
    """Forward (oldest-first) block Cholesky of the newest steps of a chain.

    Steps ``0..m-1`` of the arrays are consecutive steps of the window.  ``U[i]``, ``gU[i]``: the
    information of step i's own factors and of the link from step i-1; ``Fw[i]``, ``gF[i]`` that
    of the link to step i+1 on step i; ``B[i]`` the cross block ``H[i, i+1]``.  With
    ``first_partial`` the first step's eliminated-so-far information is ``(Sp0, rp0)`` (a frozen
    step whose predecessors are already eliminated); otherwise it is ``U[0] - Cprev Cprev^T``
    (``has_prev``) or ``U[0]``.  Writes ``Ld[i]`` (Cholesky factor), ``C[i] = (Ld[i]^-1 B[i])^T``,
    ``y[i]`` and the partials ``Sp[i], rp[i]`` (before the forward link).  Raises LinAlgError if
    not positive definite.
    """
    m = U.shape[0]
    X = np.empty((U.shape[1], U.shape[1]))
    for i in range(m):
        if i == 0:
            if first_partial:
                Sp[0] = Sp0
                rp[0] = rp0
            elif has_prev:
                Sp[0] = U[0] - Cprev @ Cprev.T
                rp[0] = gU[0] - Cprev @ yprev
            else:
                Sp[0] = U[0]
                rp[0] = gU[0]
        else:
            Sp[i] = U[i] - C[i - 1] @ C[i - 1].T
            rp[i] = gU[i] - C[i - 1] @ y[i - 1]
        S = Sp[i] + Fw[i]
        Ld[i] = np.linalg.cholesky(S)
        if i < m - 1:
            _trsm_lower_rows_t(Ld[i], B[i], X, C[i])
        y[i] = _trsv_lower(Ld[i], rp[i] + gF[i])


@njit
def window_back_substitute(Ld, C, y, order, x):
    """Back substitution over ring-buffer positions ``order`` (newest first): ``x[p]`` for each
    (``x_k = Ld_k^-T (y_k - C_k^T x_k+1)``), without temporaries; the rows of ``C_k`` and
    ``Ld_k`` are read in memory order."""
    d = y.shape[1]
    b = np.empty(d)
    for kk in range(order.shape[0]):
        p = order[kk]
        for i in range(d):
            b[i] = y[p, i]
        if kk > 0:
            pn = order[kk - 1]
            for j in range(d):
                xj = x[pn, j]
                if xj != 0.0:
                    for i in range(d):
                        b[i] -= C[p, j, i] * xj
        for i in range(d - 1, -1, -1):
            xi = b[i] / Ld[p, i, i]
            x[p, i] = xi
            if xi != 0.0:
                for m in range(i):
                    b[m] -= Ld[p, i, m] * xi


@njit
def window_marginals(Ld, C, order, P):
    """Marginal covariances ``P[p]`` of the window at ring positions ``order`` (newest first):
    ``P_k = M_k^T (I + C_k^T P_k+1 C_k) M_k``, ``M_k = Ld_k^-1`` (as :func:`block_tridiag_solve`)."""
    d = Ld.shape[1]
    eye = np.eye(d)
    Pn = np.empty((d, d))
    for k in range(order.shape[0]):
        Pn = _marginal_step(Ld[order[k]], C[order[k]], Pn, k == 0, eye)
        P[order[k]] = Pn


@njit
def _marginal_step(Ldp, Cp, Pn, first, eye):
    """One step of the window's marginal recursion, ``P_k`` from ``P_k+1`` (``Pn``; unused for the
    newest step, ``first``): ``M^T M`` or ``M^T (I + C^T P_k+1 C) M``, ``M = Ld^-1``."""
    M = _trsm_lower(Ldp, eye)
    if first:
        return M.T @ M
    return M.T @ (eye + Cp.T @ Pn @ Cp) @ M


@njit
def window_final_factors(Ld, C, positions, A, G):
    """For steps whose elimination is final (ring positions ``positions``): ``A[p] = M^T M`` and
    ``G[p] = C[p] M`` with ``M = Ld[p]^-1``, so that the marginal recursion of
    :func:`window_marginals` reads ``P_k = A_k + G_k^T P_k+1 G_k``."""
    d = Ld.shape[1]
    eye = np.eye(d)
    for kk in range(positions.shape[0]):
        p = positions[kk]
        M = _trsm_lower(Ld[p], eye)
        A[p] = M.T @ M
        G[p] = C[p] @ M


@njit
def window_block_map(A, G, positions, Ab, Phib, slot):
    """The affine map ``P_first = Ab + Phib^T P_next Phib`` across the final steps at ring
    positions ``positions`` (oldest first; ``P_next`` the marginal of the step after the last),
    composed from their ``A``, ``G`` (:func:`window_final_factors`) into ``Ab[slot]``, ``Phib[slot]``."""
    n = positions.shape[0]
    p = positions[n - 1]
    Acc = A[p].copy()
    Phi = G[p].copy()
    for kk in range(n - 2, -1, -1):
        p = positions[kk]
        Acc = A[p] + G[p].T @ Acc @ G[p]
        Phi = Phi @ G[p]
    Ab[slot] = Acc
    Phib[slot] = Phi


@njit
def window_marginals_blocked(Ld, C, newest, A, G, singles, Ab, Phib, blocks, reported, P):
    """:func:`window_marginals` for the ``reported`` steps only (ring positions, newest first),
    written to ``P[p]``: the recursion from the newest step runs through the steps not yet final
    (``newest``, newest first, from ``Ld``, ``C``), the final steps one by one (``singles``, from
    ``A``, ``G``), then whole blocks of final steps at once (``blocks``: slots of ``Ab``, ``Phib``,
    :func:`window_block_map`), then the reported steps one by one (from ``A``, ``G``)."""
    d = Ld.shape[1]
    eye = np.eye(d)
    Pn = np.empty((d, d))
    for k in range(newest.shape[0]):
        Pn = _marginal_step(Ld[newest[k]], C[newest[k]], Pn, k == 0, eye)
    for k in range(singles.shape[0]):
        p = singles[k]
        Pn = A[p] + G[p].T @ Pn @ G[p]
    for k in range(blocks.shape[0]):
        s = blocks[k]
        Pn = Ab[s] + Phib[s].T @ Pn @ Phib[s]
    for k in range(reported.shape[0]):
        p = reported[k]
        Pn = A[p] + G[p].T @ Pn @ G[p]
        P[p] = Pn
