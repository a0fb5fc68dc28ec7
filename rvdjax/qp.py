"""Conversion between the stage-wise :class:`~rvdjax.ocp.OCP` and a sparse QP in standard form.

The standard form used by Clarabel and the peer solvers::

    minimise   1/2 z^T P z + q^T z + const
    subject to A_eq z = b_eq,   G z <= h

with z = (u_0, x_1, u_1, x_2, ..., u_{N-1}, x_N[, s]) — stage-interleaved, so the KKT matrix is
banded — followed, in the soft form, by one slack per active state row (s >= 0,
Fx x - s <= fx, cost rho * s: the exact L1 penalty of :mod:`rvdjax.ocp`). Inactive (masked)
rows are dropped. :func:`condense` eliminates the states of such a QP (the dense form of a
dense active-set solver). This runs in NumPy/SciPy on concrete arrays: it feeds reference
solvers and benchmarks, never a jitted path.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve_triangular

from rvdjax.ocp import OCP

__all__ = ["QP", "CondensedQP", "to_qp", "condense", "split_solution", "qp_objective"]


class QP(NamedTuple):
    """A QP in standard form (SciPy CSC matrices, NumPy vectors)."""

    P: sp.csc_matrix  # (nz, nz) symmetric, full (not triangular)
    q: np.ndarray  # (nz,)
    A_eq: sp.csc_matrix  # (N*nx, nz) dynamics
    b_eq: np.ndarray
    G: sp.csc_matrix  # (n_ineq, nz)
    h: np.ndarray
    const: float  # constant term: sum_t xr_t^T Q_t xr_t
    n_plan: int  # number of plan variables N*(nu+nx); slacks follow
    nu: int = 0  # inputs per stage (0: unknown, e.g. a QP not built by to_qp)
    nx: int = 0  # states per stage


def to_qp(ocp: OCP, soft: bool = True) -> QP:
    """Assemble the sparse QP of one (unbatched, concrete) OCP.

    Args:
        ocp: the problem.
        soft: True for the problem rvdjax solves (state rows with L1-penalised slacks);
            False for the hard-constrained QP of the papers (state rows as plain
            inequalities; may be infeasible).
    """
    o = OCP(*(np.asarray(a, dtype=float) for a in ocp))
    N, nx, nu = o.B.shape
    ns = nu + nx
    n_plan = N * ns
    # column indices of u_t and x_{t+1}, (N, nu) and (N, nx); assembled as COO triplets
    # (vectorised: the reference loops call this once per MPC step)
    iu = np.arange(N)[:, None] * ns + np.arange(nu)
    ix = iu[:, :1] + nu + np.arange(nx)

    def block(rows, cols, values):
        """Triplets of the dense blocks values[t] at rows[t] x cols[t]."""
        r = np.broadcast_to(rows[..., :, None], values.shape)
        c = np.broadcast_to(cols[..., None, :], values.shape)
        return r.ravel(), c.ravel(), values.ravel()

    def row_triplets(rows, cols, values):
        """Triplets of single rows: values[k] at row rows[k], columns cols[k]."""
        return np.broadcast_to(rows[:, None], values.shape).ravel(), cols.ravel(), values.ravel()

    u_act = o.u_mask > 0
    x_act = o.x_mask > 0
    n_slack = int(x_act.sum()) if soft else 0
    nz = n_plan + n_slack

    # Cost (paper convention, no 1/2): (x-xr)^T Q (x-xr) + u^T R u + q^T x + r^T u.
    P = _csc(nz, nz, [block(iu, iu, 2.0 * o.R), block(ix, ix, 2.0 * o.Q)])
    qv = np.zeros(nz)
    qv[iu] = o.r
    qv[ix] = o.q - 2.0 * np.einsum("tij,tj->ti", o.Q, o.x_ref)
    const = float(np.einsum("ti,tij,tj->", o.x_ref, o.Q, o.x_ref))

    # Dynamics: x_{t+1} - A_t x_t - B_t u_t = c_t (+ A_0 x0 at t = 0).
    eq = np.arange(N)[:, None] * nx + np.arange(nx)  # (N, nx) rows of stage t
    eye = np.broadcast_to(np.eye(nx), (N, nx, nx))
    Aeq = _csc(
        N * nx,
        nz,
        [block(eq, ix, eye), block(eq, iu, -o.B), block(eq[1:], ix[:-1], -o.A[1:])],
    )
    beq = o.c.copy()
    beq[0] += o.A[0] @ o.x0
    beq = beq.ravel()

    # Inequalities, stage by stage: active input rows, active state rows (with their slack in
    # the soft form), then the slacks' s >= 0 rows.
    cu = u_act.sum(1)
    cx = x_act.sum(1)
    per_stage = cu + cx * (2 if soft else 1)
    first = np.concatenate([[0], np.cumsum(per_stage)[:-1]])
    tu, ku = np.nonzero(u_act)
    tx, kx = np.nonzero(x_act)
    row_u = first[tu] + (np.cumsum(u_act, 1) - 1)[tu, ku]
    row_x = first[tx] + cu[tx] + (np.cumsum(x_act, 1) - 1)[tx, kx]
    parts = [row_triplets(row_u, iu[tu], o.Fu[tu, ku]), row_triplets(row_x, ix[tx], o.Fx[tx, kx])]
    n_ineq = int(per_stage.sum())
    h = np.zeros(n_ineq)
    h[row_u] = o.fu[tu, ku]
    h[row_x] = o.fx[tx, kx]
    if soft:
        cols = n_plan + np.arange(n_slack)  # the slacks in (stage, row) order
        minus = -np.ones(n_slack)
        parts += [(row_x, cols, minus), (row_x + cx[tx], cols, minus)]  # Fx x - s <= fx; -s <= 0
        qv[cols] = o.rho[tx, kx]
    G = _csc(n_ineq, nz, parts)
    return QP(P, qv, Aeq, beq, G, h, const, n_plan, nu, nx)


def _csc(n_rows: int, n_cols: int, parts) -> sp.csc_matrix:
    """A CSC matrix from (rows, cols, values) triplets, explicit zeros dropped."""
    r, c, v = (np.concatenate(a) for a in zip(*parts, strict=True))
    keep = v != 0.0
    m = sp.coo_matrix((v[keep], (r[keep], c[keep])), shape=(n_rows, n_cols)).tocsc()
    m.sum_duplicates()
    return m


def split_solution(z: np.ndarray, N: int, nx: int, nu: int) -> tuple[np.ndarray, np.ndarray]:
    """Split a standard-form solution vector into the plan: u (N, nu), x (N, nx)."""
    stages = np.asarray(z)[: N * (nu + nx)].reshape(N, nu + nx)
    return stages[:, :nu], stages[:, nu:]


def qp_objective(qp: QP, z: np.ndarray) -> float:
    """Objective of the standard-form QP at z, including the constant term."""
    z = np.asarray(z)
    return float(0.5 * z @ (qp.P @ z) + qp.q @ z + qp.const)


class CondensedQP(NamedTuple):
    """The QP with the states eliminated through the dynamics (dense; w = (u, s))::

        minimise   1/2 w^T H w + f^T w + const   subject to   lb <= w <= ub,   G w <= h

    and z = Z w + z0 maps w back to the standard form's variables. Input and slack rows with a
    single nonzero (thrust boxes, s >= 0) are bounds; the other rows stay general rows."""

    H: np.ndarray  # (nw, nw)
    f: np.ndarray  # (nw,)
    lb: np.ndarray  # (nw,) -inf where none
    ub: np.ndarray  # (nw,) +inf where none
    G: np.ndarray  # (m, nw)
    h: np.ndarray  # (m,)
    const: float
    Z: np.ndarray  # (nz, nw)
    z0: np.ndarray  # (nz,)


def condense(qp: QP) -> CondensedQP:
    """Eliminate the states x = (x_1 .. x_N) of a QP built by :func:`to_qp` through its
    dynamics rows (the "condensed" or "dense" MPC formulation: Borrelli, Bemporad & Morari,
    *Predictive Control*, Sec. 11.3.1): x = X^{-1} (b_eq - W w), where X and W are the dynamics
    rows' state and free (u, s) columns; X is unit lower block bidiagonal, so the solve is a
    forward substitution. Dense in w: N nu inputs plus one slack per active soft row."""
    if qp.nu <= 0 or qp.nx <= 0:
        raise ValueError("qp must come from rvdjax.qp.to_qp (its nu and nx are not set)")
    nz = qp.P.shape[0]
    ns = qp.nu + qp.nx
    N = qp.n_plan // ns
    is_x = np.zeros(nz, bool)
    is_x[(np.arange(N)[:, None] * ns + qp.nu + np.arange(qp.nx)).ravel()] = True
    xc, wc = np.flatnonzero(is_x), np.flatnonzero(~is_x)
    X = qp.A_eq[:, xc].tocsr()
    W = qp.A_eq[:, wc].toarray()
    sol = spsolve_triangular(X, np.column_stack([qp.b_eq, -W]), lower=True)
    Z = np.zeros((nz, wc.size))
    Z[xc] = sol[:, 1:]
    Z[wc, np.arange(wc.size)] = 1.0
    z0 = np.zeros(nz)
    z0[xc] = sol[:, 0]
    PZ = qp.P @ Z
    H = Z.T @ PZ
    H = 0.5 * (H + H.T)
    Pz0 = qp.P @ z0
    f = Z.T @ (Pz0 + qp.q)
    const = float(0.5 * z0 @ Pz0 + qp.q @ z0 + qp.const)
    G = np.asarray(qp.G @ Z)
    h = qp.h - qp.G @ z0
    # rows over a single w: bounds (their coefficient's sign says which)
    nnz = np.count_nonzero(G, axis=1)
    single = nnz == 1
    col = np.argmax(G != 0, axis=1)
    coef = G[np.arange(G.shape[0]), col]
    lb = np.full(wc.size, -np.inf)
    ub = np.full(wc.size, np.inf)
    upper, lower = single & (coef > 0), single & (coef < 0)
    np.minimum.at(ub, col[upper], h[upper] / coef[upper])
    np.maximum.at(lb, col[lower], h[lower] / coef[lower])
    keep = ~single & (nnz > 0)
    return CondensedQP(H, f, lb, ub, G[keep], h[keep], const, Z, z0)
