"""Conversion between the stage-wise :class:`~rvdjax.ocp.OCP` and a sparse QP in standard form.

The standard form used by Clarabel and the peer solvers::

    minimise   1/2 z^T P z + q^T z + const
    subject to A_eq z = b_eq,   G z <= h

with z = (u_0, x_1, u_1, x_2, ..., u_{N-1}, x_N[, s]) — stage-interleaved, so the KKT matrix is
banded — followed, in the soft form, by one slack per active state row (s >= 0,
Fx x - s <= fx, cost rho * s: the exact L1 penalty of :mod:`rvdjax.ocp`). Inactive (masked)
rows are dropped. This runs in NumPy/SciPy on concrete arrays: it feeds reference solvers and
benchmarks, never a jitted path.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from rvdjax.ocp import OCP

__all__ = ["QP", "to_qp", "split_solution", "qp_objective"]


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
    iu = [t * ns + np.arange(nu) for t in range(N)]
    ix = [t * ns + nu + np.arange(nx) for t in range(N)]

    x_rows = [np.flatnonzero(o.x_mask[t] > 0) for t in range(N)]
    n_slack = sum(len(r) for r in x_rows) if soft else 0
    nz = n_plan + n_slack

    # Cost (paper convention, no 1/2): (x-xr)^T Q (x-xr) + u^T R u + q^T x + r^T u.
    P = sp.lil_matrix((nz, nz))
    qv = np.zeros(nz)
    const = 0.0
    for t in range(N):
        P[np.ix_(iu[t], iu[t])] = 2.0 * o.R[t]
        P[np.ix_(ix[t], ix[t])] = 2.0 * o.Q[t]
        qv[iu[t]] = o.r[t]
        qv[ix[t]] = o.q[t] - 2.0 * o.Q[t] @ o.x_ref[t]
        const += float(o.x_ref[t] @ o.Q[t] @ o.x_ref[t])

    # Dynamics: x_{t+1} - A_t x_t - B_t u_t = c_t (+ A_0 x0 at t = 0).
    Aeq = sp.lil_matrix((N * nx, nz))
    beq = np.zeros(N * nx)
    for t in range(N):
        rows = t * nx + np.arange(nx)
        Aeq[np.ix_(rows, ix[t])] = np.eye(nx)
        Aeq[np.ix_(rows, iu[t])] = -o.B[t]
        beq[rows] = o.c[t]
        if t == 0:
            beq[rows] += o.A[0] @ o.x0
        else:
            Aeq[np.ix_(rows, ix[t - 1])] = -o.A[t]

    G_blocks, h_parts = [], []
    slack = n_plan
    for t in range(N):
        ru = np.flatnonzero(o.u_mask[t] > 0)
        if len(ru):
            g = sp.lil_matrix((len(ru), nz))
            g[:, iu[t]] = o.Fu[t][ru]
            G_blocks.append(g)
            h_parts.append(o.fu[t][ru])
        rx = x_rows[t]
        if len(rx):
            g = sp.lil_matrix((len(rx), nz))
            g[:, ix[t]] = o.Fx[t][rx]
            if soft:
                cols = slack + np.arange(len(rx))
                g[np.arange(len(rx)), cols] = -1.0
                gs = sp.lil_matrix((len(rx), nz))
                gs[np.arange(len(rx)), cols] = -1.0  # s >= 0
                G_blocks += [g, gs]
                h_parts += [o.fx[t][rx], np.zeros(len(rx))]
                qv[cols] = o.rho[t][rx]
                slack += len(rx)
            else:
                G_blocks.append(g)
                h_parts.append(o.fx[t][rx])
    G = sp.vstack(G_blocks).tocsc() if G_blocks else sp.csc_matrix((0, nz))
    h = np.concatenate(h_parts) if h_parts else np.zeros(0)
    return QP(P.tocsc(), qv, Aeq.tocsc(), beq, G, h, const, n_plan)


def split_solution(z: np.ndarray, N: int, nx: int, nu: int) -> tuple[np.ndarray, np.ndarray]:
    """Split a standard-form solution vector into the plan: u (N, nu), x (N, nx)."""
    stages = np.asarray(z)[: N * (nu + nx)].reshape(N, nu + nx)
    return stages[:, :nu], stages[:, nu:]


def qp_objective(qp: QP, z: np.ndarray) -> float:
    """Objective of the standard-form QP at z, including the constant term."""
    z = np.asarray(z)
    return float(0.5 * z @ (qp.P @ z) + qp.q @ z + qp.const)
