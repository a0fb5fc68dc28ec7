"""Structured and dense solves of the Newton (KKT) system of the barrier OCP.

At each infeasible-start Newton iteration (paper 000 Eqs. 20-23) the step solves::

    [Phi  C^T] [dz  ]     [g ]
    [C    0  ] [nu+ ] = - [rp]

where Phi = blockdiag(Phi_u[0], Phi_x[0], ..., Phi_u[N-1], Phi_x[N-1]) is the Hessian of the
cost plus barrier (one block per input u_t and per state x_{t+1}: the inequality rows are
stage-separable, paper 000 Eq. 2), g its gradient, C the dynamics x_{t+1} - A_t x_t - B_t u_t,
rp the dynamics residual and nu+ = nu + dnu the new multipliers. Solving for nu+ directly
(rather than dnu) is algebraically the same step as paper 000 Eqs. 22-23 with the authors'
correction (Phi dz = -r_d - C^T dnu).

:func:`riccati_solve` eliminates the system stage by stage (a discrete Riccati recursion on
the KKT system, equivalent to the block Cholesky factorisation of Y = C Phi^-1 C^T of
paper 000 Eqs. 24-26): O(N (nx + nu)^3) work, `lax.scan` over stages, no dense matrix.
:func:`dense_solve` forms and solves the full KKT matrix — the paper's "ISNM" comparison.

Sign convention: the Lagrangian is f(z) + sum_t nu_t^T (x_{t+1} - A_t x_t - B_t u_t - c_t),
so at the optimum grad_u f = B_t^T nu_t and grad_x f(x_{t+1}) = A_{t+1}^T nu_{t+1} - nu_t.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

__all__ = ["NewtonStep", "riccati_solve", "dense_solve", "KKT_SOLVERS"]


class NewtonStep(NamedTuple):
    """Solution of one KKT system.

    Attributes:
        du: (N, nu) input step.
        dx: (N, nx) state step (dx[t] is the step of x_{t+1}).
        nu: (N, nx) new dynamics multipliers (nu + dnu).
    """

    du: jnp.ndarray
    dx: jnp.ndarray
    nu: jnp.ndarray


def _sym(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def riccati_solve(A, B, Phi_u, Phi_x, g_u, g_x, rp) -> NewtonStep:
    """Solve the stage-structured KKT system by a backward Riccati sweep and a forward pass.

    Args:
        A: (N, nx, nx), B: (N, nx, nu) stage dynamics.
        Phi_u: (N, nu, nu), Phi_x: (N, nx, nx) Hessian blocks (Phi_u positive definite,
            Phi_x positive semidefinite).
        g_u: (N, nu), g_x: (N, nx) gradient blocks.
        rp: (N, nx) dynamics residual x_{t+1} - A_t x_t - B_t u_t - c_t.

    Returns:
        The :class:`NewtonStep`. Non-finite entries signal a failed factorisation.
    """
    # The cost-to-go of x_t is 1/2 dx^T P_t dx + p_t^T dx; P_N = Phi_x[N-1], p_N = g_x[N-1].
    Phi_x_prev = jnp.concatenate([jnp.zeros_like(Phi_x[:1]), Phi_x[:-1]])  # blocks of x_t
    g_x_prev = jnp.concatenate([jnp.zeros_like(g_x[:1]), g_x[:-1]])

    def backward(carry, stage):
        P, p = carry  # cost-to-go of x_{t+1}
        A_t, B_t, Phu, gu, r, Phx, gx = stage
        PB = P @ B_t
        H = _sym(Phu + B_t.T @ PB)  # (nu, nu) reduced Hessian of u_t
        L = jnp.linalg.cholesky(H)
        BPA = PB.T @ A_t
        p_shift = p - P @ r
        rhs = jnp.concatenate([BPA, (gu + B_t.T @ p_shift)[:, None]], axis=1)
        W = jax.scipy.linalg.solve_triangular(L, rhs, lower=True)
        sol = jax.scipy.linalg.solve_triangular(L.T, W, lower=False)
        K, k = -sol[:, :-1], -sol[:, -1]
        Wk = W[:, :-1]
        P_new = _sym(Phx + A_t.T @ P @ A_t - Wk.T @ Wk)
        p_new = gx + A_t.T @ p_shift + BPA.T @ k
        return (P_new, p_new), (K, k, P, p)

    init = (Phi_x[-1], g_x[-1])
    stages = (A, B, Phi_u, g_u, rp, Phi_x_prev, g_x_prev)
    _, (K, k, P_next, p_next) = lax.scan(backward, init, stages, reverse=True)

    def forward(dx_t, stage):
        A_t, B_t, K_t, k_t, r, P, p = stage
        du = K_t @ dx_t + k_t
        dx_next = A_t @ dx_t + B_t @ du - r
        nu_t = -(P @ dx_next + p)
        return dx_next, (du, dx_next, nu_t)

    dx0 = jnp.zeros_like(rp[0])
    _, (du, dx, nu) = lax.scan(forward, dx0, (A, B, K, k, rp, P_next, p_next))
    return NewtonStep(du, dx, nu)


def dense_solve(A, B, Phi_u, Phi_x, g_u, g_x, rp) -> NewtonStep:
    """Solve the same KKT system densely (paper 000's ISNM): O((N (2 nx + nu))^3) work.

    Arguments and result as :func:`riccati_solve`.
    """
    N, nx, nu = B.shape
    ns = nu + nx
    nz = N * ns
    eye_N = jnp.eye(N)
    # Phi = blockdiag over stages of blockdiag(Phi_u[t], Phi_x[t]) in z = (u_0, x_1, u_1, ...).
    stage_blocks = jnp.zeros((N, ns, ns))
    stage_blocks = stage_blocks.at[:, :nu, :nu].set(Phi_u).at[:, nu:, nu:].set(Phi_x)
    Phi = jnp.einsum("st,sij->sitj", eye_N, stage_blocks).reshape(nz, nz)
    # C: row block t is  x_{t+1} - B_t u_t - A_t x_t.
    C_stage = jnp.concatenate([-B, jnp.broadcast_to(jnp.eye(nx), (N, nx, nx))], axis=2)
    C = jnp.einsum("st,sij->sitj", eye_N, C_stage).reshape(N * nx, nz)
    sub = jnp.einsum("st,sij->sitj", jnp.eye(N, k=-1), jnp.pad(-A, ((0, 0), (0, 0), (nu, 0))))
    C = C + sub.reshape(N * nx, nz)
    K = jnp.block([[Phi, C.T], [C, jnp.zeros((N * nx, N * nx))]])
    g = jnp.concatenate([g_u, g_x], axis=1).reshape(nz)
    sol = jnp.linalg.solve(K, -jnp.concatenate([g, rp.reshape(-1)]))
    dz = sol[:nz].reshape(N, ns)
    return NewtonStep(dz[:, :nu], dz[:, nu:], sol[nz:].reshape(N, nx))


KKT_SOLVERS = {"riccati": riccati_solve, "dense": dense_solve}
