"""The Newton (KKT) step of the barrier OCP: the method-independent interface the iterations
call (:class:`KKT`, :func:`kkt_factor`, :func:`kkt_solve`, refinement) and the dense solve.

At each infeasible-start Newton iteration (paper 000 Eqs. 20-23) the step solves::

    [Phi  C^T] [dz  ]     [g ]
    [C    0  ] [nu+ ] = - [rp]

where Phi = blockdiag(Phi_u[0], Phi_x[0], ..., Phi_u[N-1], Phi_x[N-1]) is the Hessian of the
cost plus barrier (one block per input u_t and per state x_{t+1}: the inequality rows are
stage-separable, paper 000 Eq. 2), g its gradient, C the dynamics x_{t+1} - A_t x_t - B_t u_t,
rp the dynamics residual and nu+ = nu + dnu the new multipliers. Solving for nu+ directly
(rather than dnu) is algebraically the same step as paper 000 Eqs. 22-23 with the authors'
correction (Phi dz = -r_d - C^T dnu).

:func:`riccati_solve` (:mod:`rvdjax.solver.riccati`) eliminates the system stage by stage
(equivalent to the block Cholesky factorisation of Y = C Phi^-1 C^T of paper 000 Eqs. 24-26).
:func:`dense_solve` forms and solves the full KKT matrix — the paper's "ISNM" comparison.

Sign convention: the Lagrangian is f(z) + sum_t nu_t^T (x_{t+1} - A_t x_t - B_t u_t - c_t),
so at the optimum grad_u f = B_t^T nu_t and grad_x f(x_{t+1}) = A_{t+1}^T nu_{t+1} - nu_t.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax.numpy as jnp

from rvdjax.solver.platform import AUTO_ON_CUDA, cuda_or_default
from rvdjax.solver.riccati import (  # noqa: F401  (KERNELS and the Riccati names: re-exported)
    KERNELS,
    REFINED_IN_KERNEL,
    ModelTable,
    NewtonStep,
    RiccatiFactor,
    newton_residual,
    riccati_apply,
    riccati_apply_refined,
    riccati_factor,
    riccati_factor_solve,
    riccati_solve,
)
from rvdjax.solver.riccati.recursion import whole

__all__ = [
    "dense_solve",
    "KKT_SOLVERS",
    "KKT",
    "kkt_factor",
    "kkt_factor_solve",
    "kkt_solve",
    "kkt_solve_refined",
]


def dense_solve(A, B, Phi_u, Phi_x, g_u, g_x, rp, kernel: str = "auto") -> NewtonStep:
    """Solve the same KKT system densely (paper 000's ISNM): O((N (2 nx + nu))^3) work.

    Arguments and result as :func:`riccati_solve` (``kernel`` is not used).
    """
    Phi_u, Phi_x = whole(Phi_u), whole(Phi_x)
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


class KKT(NamedTuple):
    """A Newton (KKT) matrix ready for right-hand sides: the stage data and, for the Riccati
    method, its factorisation (computed once, applied to every right-hand side: predictor,
    corrector and the implicit derivative's adjoint solve), and the model's table, if any
    (:class:`~rvdjax.solver.riccati.ModelTable`: the GPU kernels read A and B from it)."""

    A: jnp.ndarray
    B: jnp.ndarray
    Phi_u: jnp.ndarray  # or a SymStored (rvdjax.solver.riccati), as the kernels formed it
    Phi_x: jnp.ndarray
    factor: RiccatiFactor | None
    table: ModelTable | None = None


def kkt_factor(A, B, Phi_u, Phi_x, method: str, kernel: str = "auto", table=None) -> KKT:
    """Factorise (Riccati) or keep (dense) the Newton matrix of the given Hessian blocks."""
    factor = riccati_factor(A, B, Phi_u, Phi_x, kernel, table) if method == "riccati" else None
    return KKT(A, B, Phi_u, Phi_x, factor, table)


def kkt_factor_solve(
    A, B, Phi_u, Phi_x, g_u, g_x, rp, method: str, kernel: str = "auto", table=None
):
    """:func:`kkt_factor` and :func:`kkt_solve` of a first right-hand side: (KKT, step), with
    the Riccati method through :func:`riccati_factor_solve`."""
    if method != "riccati":
        kkt = kkt_factor(A, B, Phi_u, Phi_x, method)
        return kkt, kkt_solve(kkt, g_u, g_x, rp, method)
    factor, step = riccati_factor_solve(A, B, Phi_u, Phi_x, g_u, g_x, rp, kernel, table)
    return KKT(A, B, Phi_u, Phi_x, factor, table), step


def kkt_residual(kkt: KKT, g_u, g_x, rp, step: NewtonStep):
    """K z + (g, rp) for z = (du, dx, nu): the residual of the stage-structured Newton system
    (the rows of :func:`dense_solve`'s matrix, applied stage by stage)."""
    return newton_residual(kkt.A, kkt.B, kkt.Phi_u, kkt.Phi_x, g_u, g_x, rp, step)


def kkt_refine(
    kkt: KKT, g_u, g_x, rp, step: NewtonStep, method: str, kernel: str = "auto"
) -> NewtonStep:
    """One step of iterative refinement: ``step`` plus the solve of its residual with the same
    factorisation (one more :func:`riccati_apply`)."""
    r_u, r_x, r_p = kkt_residual(kkt, g_u, g_x, rp, step)
    d = kkt_solve(kkt, r_u, r_x, r_p, method, kernel)
    return NewtonStep(step.du + d.du, step.dx + d.dx, step.nu + d.nu)


def kkt_solve_refined(kkt: KKT, g_u, g_x, rp, method: str, kernel: str = "auto") -> NewtonStep:
    """:func:`kkt_solve` then :func:`kkt_refine`: with a form of the Newton step in
    :data:`~rvdjax.solver.riccati.REFINED_IN_KERNEL`, one kernel for both
    (:func:`~rvdjax.solver.riccati.riccati_apply_refined`)."""

    def two_solves(kkt, g_u, g_x, rp):
        step = kkt_solve(kkt, g_u, g_x, rp, method, kernel)
        return kkt_refine(kkt, g_u, g_x, rp, step, method, kernel)

    if method == "riccati" and kernel in REFINED_IN_KERNEL:
        return _refined_in_kernel(kernel, kkt, g_u, g_x, rp)
    if method == "riccati" and kernel == "auto" and AUTO_ON_CUDA in REFINED_IN_KERNEL:
        in_kernel = functools.partial(_refined_in_kernel, AUTO_ON_CUDA)
        # the CPU's program is the two solves, as before
        return cuda_or_default(kkt, g_u, g_x, rp, cuda=in_kernel, default=two_solves)
    return two_solves(kkt, g_u, g_x, rp)


def _refined_in_kernel(kernel, kkt: KKT, g_u, g_x, rp) -> NewtonStep:
    return riccati_apply_refined(kkt.factor, kkt.Phi_u, kkt.Phi_x, g_u, g_x, rp, kernel, kkt.table)


def kkt_solve(kkt: KKT, g_u, g_x, rp, method: str, kernel: str = "auto") -> NewtonStep:
    """Solve the Newton system of ``kkt`` for one right-hand side (g_u, g_x, rp)."""
    if method == "riccati":
        return riccati_apply(kkt.factor, g_u, g_x, rp, kernel, kkt.table)
    return KKT_SOLVERS[method](kkt.A, kkt.B, kkt.Phi_u, kkt.Phi_x, g_u, g_x, rp)
