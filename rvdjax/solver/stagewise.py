"""Stage-wise products of the barrier OCP's small blocks, written as broadcast multiplies and
sums.

Every stage t of a horizon carries a small matrix (a constraint block F_t of m x n rows, a
weight R_t or Q_t, a model block A_t or B_t) and the solver multiplies it with a stage
vector. Written as ``einsum`` these are batched matrix products with a batch of stages (and,
under ``vmap``, of problems) of 3-12 wide blocks; XLA's CPU backend runs each as its own
product kernel with layout copies around it. As a multiply and a sum over the contracted axis
they are plain loops that XLA fuses with the elementwise work around them (the same reason
as the Riccati recursion's elementwise form in :mod:`rvdjax.solver.riccati`; measured in
docs/benchmark.md). Leading axes are indexed only through negative positions, so a block
shared by every problem of a batch (no batch axis) broadcasts against batched vectors.
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["mv", "mtv", "congruence", "quad", "shift"]


def mv(F, v):
    """(..., m, n), (..., n) -> (..., m): F_t v_t for every stage (einsum "tij,tj->ti")."""
    return jnp.sum(F * v[..., None, :], axis=-1)


def mtv(F, w):
    """(..., m, n), (..., m) -> (..., n): F_t^T w_t for every stage (einsum "tij,ti->tj")."""
    return jnp.sum(F * w[..., :, None], axis=-2)


def congruence(F, d):
    """(..., m, n), (..., m) -> (..., n, n): F_t^T diag(d_t) F_t for every stage (einsum
    "tki,tk,tkj->tij")."""
    return jnp.sum(F[..., :, :, None] * (d[..., :, None, None] * F[..., :, None, :]), axis=-3)


def quad(v, M):
    """(N, n), (N, n, n) -> (): sum over stages of v_t^T M_t v_t (einsum "ti,tij,tj->")."""
    return jnp.sum(v * mv(M, v))


def shift(a):
    """(a_0, ..., a_{N-1}) -> (0, a_0, ..., a_{N-2}) along the stage axis."""
    return jnp.concatenate([jnp.zeros_like(a[:1]), a[:-1]])
