"""The Riccati recursion of the structured Newton step as XLA runs it: the factor and
step types, the factorisation, the solve and one step of iterative refinement, in two
formulations of the stage products (``dot`` and elementwise)."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
from jax import lax

from rvdjax.solver import lanes
from rvdjax.solver import stagewise as sw
from rvdjax.solver.barrier import dual_residual
from rvdjax.solver.stagewise import shift as _shift


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
    return 0.5 * (M + jnp.swapaxes(M, 0, 1))


class RiccatiFactor(NamedTuple):
    """Stage-wise factorisation of the KKT matrix (independent of the right-hand side).

    Attributes:
        M: (N, nx, nu + nx) the stage dynamics [B_t, A_t].
        L: (N, nu, nu) Cholesky factor of the reduced Hessian Phi_u + B^T P_{t+1} B.
        K: (N, nu, nx) feedback gain, du_t = K_t dx_t + k_t. No other product of the
            factorisation (B^T P A) is stored (:func:`_apply`). The GPU kernels store only L
            and P (``Lp``, ``Pp``) and solve without the gain; with their forms K is formed
            from L and P, and is dead code where nothing else reads it.
        P: (N, nx, nx) cost-to-go Hessian P_{t+1} of x_{t+1}.
        Lp: (N, nu (nu + 1) / 2) L's lower triangle and ``Pp`` (N, nx (nx + 1) / 2) P's, as
            the GPU kernels store them (:func:`rvdjax.solver.lanes.pack`), or None (both or
            neither): present with the kernels' forms (and "auto" where a program may run
            on a CUDA GPU), so that a factorisation goes from the factorisation's kernel to
            the solves' in that storage. XLA does not fold the copy of the triangles into
            the matrices and back between two kernels; L and P, for every other use, are
            dead code there.
    """

    M: jnp.ndarray
    L: jnp.ndarray
    K: jnp.ndarray
    P: jnp.ndarray
    Lp: Any = None
    Pp: Any = None


class ModelTable(NamedTuple):
    """K models' stage dynamics (and, optionally, rows) and the one a problem runs:
    ``M[index]`` is the problem's [B_t, A_t]. The batch engine's three-phase family flies one
    model per phase: under ``vmap``, with the tables shared and the index batched, the GPU
    kernels read each problem's stages from the tables instead of from a copy of every
    problem's (the Riccati kernels [B, A], 13 KB a thesis-vbar slot read in every sweep; the
    row kernels of :mod:`rvdjax.solver.rows_kernel` the input rows and the soft rows' mask
    and penalty: docs/benchmark.md). Every other form ignores them: the OCP's arrays are
    passed too, and must equal the tables' entries (the caller's promise, not checked).

    Attributes:
        M: (K, N, nx, nu + nx) the stages' [B_t, A_t] of each model.
        index: () int, the problem's model.
        Fu: (K, N, mu, nu) the input rows before the problem's mask neutralises them (the
            kernels zero the rows whose mask is off, as ``barrier.rows_of`` does), or None.
        x_mask: (K, N, mx) the soft rows' mask, and ``rho`` (K, N, mx) their penalty
            neutralised (1) where the mask is off, or None (both or neither, with ``Fu``).
        Q: (K, N, nx, nx) and ``R`` (K, N, nu, nu) the cost blocks, or None (both or
            neither): with the rows' tables, the kernel that forms the Newton blocks reads
            them too.
    """

    M: Any
    index: Any
    Fu: Any = None
    x_mask: Any = None
    rho: Any = None
    Q: Any = None
    R: Any = None


class SymStored(NamedTuple):
    """A stage-wise symmetric Hessian block and its lower triangle, as the GPU kernels store
    it: the blocks' kernel (:func:`rvdjax.solver.rows_kernel.pd_blocks`) writes Phi_u and
    Phi_x as their lower triangles (:func:`rvdjax.solver.lanes.tri_pack`: 6 and 21 entries a
    stage instead of 9 and 36), which the Riccati kernels read as they are. XLA does not fold
    a copy of the triangles into whole matrices and back between two kernels, so the
    triangles go beside the whole matrices, which every other use reads (the XLA forms, the
    derivatives) and which are dead code where none does. Every function here that takes
    Phi_u or Phi_x takes either an array or this.

    Attributes:
        whole: (N, n, n) the blocks.
        lower: (N, n (n + 1) / 2) their lower triangles, row by row.
    """

    whole: Any
    lower: Any


def whole(a):
    """The matrices of a Hessian block passed as an array or as :class:`SymStored`."""
    return a.whole if isinstance(a, SymStored) else a


def _lower(a, axis: int):
    """The lower triangles of a Hessian block (:class:`SymStored`'s, or formed from the
    matrices at ``axis`` and the next)."""
    return a.lower if isinstance(a, SymStored) else lanes.tri_pack(a, axis)


def _small_chol(H):
    """Cholesky of a small SPD matrix written out element by element
    (:func:`rvdjax.solver.lanes.chol`).

    Under ``vmap`` each entry becomes one vector operation over the batch; XLA's batched
    LAPACK call costs more than the arithmetic at these sizes. NaN if H is not SPD. Indexes
    the two leading axes only, so H may carry trailing batch axes.
    """
    n = H.shape[0]
    L = lanes.chol([[H[i, j] for j in range(n)] for i in range(n)])
    zero = jnp.zeros_like(H[0, 0])
    return jnp.stack([jnp.stack([L[i][j] if j <= i else zero for j in range(n)]) for i in range(n)])


def _chol_solve(L, b):
    """Solve (L L^T) X = b for small lower-triangular L; b of shape (n,) or (n, k) (and the
    same trailing batch axes as L, if any)."""
    n = L.shape[0]
    return jnp.stack(lanes.chol_solve([[L[i, j] for j in range(n)] for i in range(n)], list(b)))


# --------------------------------------------------------------- products, two formulations
#
# The recursion below is written once over four small products. ``_DOT`` uses matrix
# products (``dot_general``: what XLA handles best for batches kept first and large).
# ``_ELEMENTWISE`` writes each product as a broadcast multiply and a sum over the contracted
# axis, indexing leading axes only, so the same code runs on one problem or on arrays with a
# trailing batch axis, where every operation vectorises over the batch. Per problem (N = 30,
# nx = 6, nu = 3, one factorisation and two solves): sweeps/kkt_layouts.py, docs/benchmark.md.


class _Products(NamedTuple):
    mm: Any  # X @ Y
    mtm: Any  # X^T @ Y
    mv: Any  # X @ v
    mtv: Any  # X^T @ v


_DOT = _Products(
    mm=lambda X, Y: X @ Y,
    mtm=lambda X, Y: X.T @ Y,
    mv=lambda X, v: X @ v,
    mtv=lambda X, v: X.T @ v,
)
_ELEMENTWISE = _Products(
    mm=lambda X, Y: jnp.sum(X[:, :, None] * Y[None, :, :], axis=1),
    mtm=lambda X, Y: jnp.sum(X[:, :, None] * Y[:, None, :], axis=0),
    mv=lambda X, v: jnp.sum(X * v[None, :], axis=1),
    mtv=lambda X, v: jnp.sum(X * v[:, None], axis=0),
)


def _factor(A, B, Phi_u, Phi_x, ops: _Products) -> RiccatiFactor:
    Phi_u, Phi_x = whole(Phi_u), whole(Phi_x)
    nu = B.shape[2]
    batch = jnp.broadcast_shapes(A.shape[3:], B.shape[3:])
    A = jnp.broadcast_to(A, A.shape[:3] + batch)
    B = jnp.broadcast_to(B, B.shape[:3] + batch)
    M = jnp.concatenate([B, A], axis=2)

    def backward(P, stage):
        M_t, Phu, Phx = stage
        B_t, A_t = M_t[:, :nu], M_t[:, nu:]
        PM = ops.mm(P, M_t)  # [PB, PA]
        BPM = ops.mtm(B_t, PM)  # [B'PB, B'PA]
        H = Phu + _sym(BPM[:, :nu])
        L = _small_chol(H)
        BPA = BPM[:, nu:]
        K = -_chol_solve(L, BPA)
        # Late in a solve the barrier weights reach 1e9-1e12 and H's condition number
        # follows. The two substitutions then move the last bits of their inputs into K's
        # leading digits, and XLA may evaluate the same substitution with different
        # FMA contractions in different consumers: with its loops compiled whole, K was
        # 1e-9 away (backward error) from the H it came from and the factorisation
        # broke down. One refinement step against H restores K to rounding level.
        K = K - _chol_solve(L, ops.mm(H, K) + BPA)
        # Joseph form (A + BK)' P (A + BK) + K' Phu K: a sum of PSD terms, so P stays PSD
        # whatever K's rounding, and an error in K enters P at second order only (the
        # subtractive form A'PA - A'PB H^-1 B'PA takes it at first order).
        PAcl = PM[:, nu:] + ops.mm(PM[:, :nu], K)
        Acl = A_t + ops.mm(B_t, K)
        P_new = Phx + _sym(ops.mtm(Acl, PAcl)) + _sym(ops.mtm(K, ops.mm(Phu, K)))
        return P_new, (L, K, P)

    _, (L, K, P) = lax.scan(backward, Phi_x[-1], (M, Phi_u, _shift(Phi_x)), reverse=True)
    return RiccatiFactor(M, L, K, P)


def _apply(f: RiccatiFactor, g_u, g_x, rp, ops: _Products) -> NewtonStep:
    nu = f.L.shape[1]

    # p_t = g_x + A^T q + (B^T P A)^T k with k = -H^-1 v, v = g_u + B^T q, q = p - P r; as
    # K = -H^-1 B^T P A, (B^T P A)^T k = K^T v: the gain the forward sweep reads anyway
    # stands for B^T P A, which is then not stored. (The GPU kernels, whose sweeps read the
    # factorisation from device memory, form the same step from L and P alone:
    # rvdjax.solver.lanes.stage._backward_rhs_stored, _forward_solved; docs/solver.md.)
    def backward(p, stage):
        M_t, L, K, P, gu, r, gx = stage
        Mp = ops.mtv(M_t, p - ops.mv(P, r))
        v = gu + Mp[:nu]
        k = -_chol_solve(L, v)
        return gx + Mp[nu:] + ops.mtv(K, v), (k, p)

    stages = (f.M, f.L, f.K, f.P, g_u, rp, _shift(g_x))
    _, (k, p_next) = lax.scan(backward, g_x[-1], stages, reverse=True)

    def forward(dx_t, stage):
        M_t, K_t, k_t, r, P, p = stage
        du = ops.mv(K_t, dx_t) + k_t
        dx_next = ops.mv(M_t, jnp.concatenate([du, dx_t])) - r
        return dx_next, (du, dx_next, -(ops.mv(P, dx_next) + p))

    _, (du, dx, nu_new) = lax.scan(forward, jnp.zeros_like(rp[0]), (f.M, f.K, k, rp, f.P, p_next))
    return NewtonStep(du, dx, nu_new)


class _Model(NamedTuple):
    A: Any
    B: Any


def newton_residual(A, B, Phi_u, Phi_x, g_u, g_x, rp, step: NewtonStep):
    """K z + (g, rp) for z = (du, dx, nu): the residual of the stage-structured Newton system
    (the rows of :func:`rvdjax.solver.kkt.dense_solve`'s matrix, applied stage by stage)."""
    Phi_u, Phi_x = whole(Phi_u), whole(Phi_x)
    r_u, r_x = dual_residual(
        _Model(A, B), sw.mv(Phi_u, step.du) + g_u, sw.mv(Phi_x, step.dx) + g_x, step.nu
    )
    r_p = step.dx - sw.mv(B, step.du) - sw.mv(A, _shift(step.dx)) + rp
    return r_u, r_x, r_p


def _apply_refined(f: RiccatiFactor, Phi_u, Phi_x, g_u, g_x, rp, ops: _Products) -> NewtonStep:
    """:func:`_apply`, then one step of iterative refinement: the XLA form of the kernel
    :func:`rvdjax.solver.lanes.apply_refined`."""
    nu = f.L.shape[1]
    A, B = f.M[:, :, nu:], f.M[:, :, :nu]
    step = _apply(f, g_u, g_x, rp, ops)
    d = _apply(f, *newton_residual(A, B, Phi_u, Phi_x, g_u, g_x, rp, step), ops)
    return NewtonStep(*(a + b for a, b in zip(step, d, strict=True)))
