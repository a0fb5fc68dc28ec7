"""The Riccati sweeps of the Newton step with the batch as the minor axis and the small-matrix
algebra written out entry by entry, as XLA loops over the stages.

This is the GPU kernels' arithmetic (:mod:`rvdjax.solver.lanes`) without Pallas: the same
stage functions run on lane vectors, here jnp arrays of shape ``(b,)`` (one entry of a
matrix across the batch), inside ``lax.scan`` over the horizon. Every operation of a stage is
elementwise over the batch, with no ``dot_general``, reduction or ``linalg`` call, so XLA can
fuse a stage into a few loop kernels whose loads are coalesced across the batch, instead of
the several small batched products per stage of the batch-first form (DESIGN §8a).

Measured on one H200 (2026-11-26): XLA still splits a stage into 4-11 kernels (the
Cholesky's square roots and divisions end fusions), so an accurate-mode iteration is 1 024
launches instead of 1 826, 13 % faster than XLA's loops at 65 536 QPs and slower at 16 384 or
alone; on the CPU 2-4x slower. Opt-in: ``SolverSettings(kernel="unrolled")``
(docs/solver.md).

The backward sweep of the factorisation and that of the first right-hand side share one loop
(:func:`factor_solve`), as in the Pallas kernel. Inputs and outputs as :mod:`rvdjax.solver.lanes`
(batch last; ``M`` without a batch axis when the model is shared); ``unroll`` stages per
loop trip (static), which trades loop overhead against program size.
"""

from __future__ import annotations

import contextlib
import math

import jax
import jax.numpy as jnp
from jax import lax

from rvdjax.solver.lanes.stage import (
    _backward_rhs,
    _backward_rhs_of,
    _factor_stage,
    _forward,
    _offset,
)
from rvdjax.solver.stagewise import shift as _shift

__all__ = ["factor", "factor_solve", "apply", "configured", "default_unroll"]

_UNROLL = [1]


def default_unroll() -> int:
    """Stages per loop trip the solver's sweeps are traced with (1)."""
    return _UNROLL[0]


@contextlib.contextmanager
def configured(unroll: int):
    """Trace the solver's sweeps with ``unroll`` stages per loop trip inside the block (a
    benchmark's variant). JAX's caches are cleared on entry and exit when it changes, as in
    :func:`rvdjax.solver.lanes.configured`."""
    old, _UNROLL[0] = _UNROLL[0], unroll
    if unroll != old:
        jax.clear_caches()
    try:
        yield unroll
    finally:
        _UNROLL[0] = old
        if unroll != old:
            jax.clear_caches()


def _vec(X):
    return [X[i] for i in range(X.shape[0])]


def _mat(X):
    return [[X[i, j] for j in range(X.shape[1])] for i in range(X.shape[0])]


def _stack(X, like):
    """Nested lists back to an array (None, the factor's upper triangle, as zeros)."""
    if not isinstance(X[0], list):
        return jnp.stack([jnp.broadcast_to(v, like.shape) for v in X])
    zero = jnp.zeros_like(like)
    return jnp.stack(
        [jnp.stack([zero if v is None else jnp.broadcast_to(v, like.shape) for v in r]) for r in X]
    )


def _scan(body, carry, xs, reverse, unroll):
    """``lax.scan`` whose per-stage outputs are packed into one (N, rows, b) array: one
    in-place update per stage on a GPU instead of one per output."""
    shapes = []

    def packed(c, x):
        c, ys = body(c, x)
        shapes[:] = [y.shape[:-1] for y in ys]
        b = ys[0].shape[-1]
        return c, jnp.concatenate([y.reshape(-1, b) for y in ys])

    _, Y = lax.scan(packed, carry, xs, reverse=reverse, unroll=unroll)
    out, row = [], 0
    for shape in shapes:
        n = math.prod(shape)
        out.append(Y[:, row : row + n].reshape(Y.shape[0], *shape, Y.shape[-1]))
        row += n
    return out


def _sweeps(M, Phi_u, Phi_x, rhs, unroll):
    """The backward sweep (factorisation, and the affine terms of ``rhs`` = (g_u, g_x, rp)
    if given), then the forward sweep of the step."""
    nx = Phi_x.shape[1]
    like = Phi_x[0, 0, 0]
    with_rhs = rhs is not None

    def backward(carry, stage):
        P_arr, p_arr = carry
        M_t, Phu, Phx_prev = stage[:3]
        P = _mat(P_arr)
        P_new, L, K = _factor_stage(P, _mat(M_t), _mat(Phu), lambda: _mat(Phx_prev))
        out = (_stack(L, like), _stack(K, like), P_arr)
        new_P = _stack(P_new, like)
        if not with_rhs:
            return (new_P, p_arr), out
        gu, r, gx_prev = stage[3:]
        q = _offset(_vec(p_arr), P, _vec(r))
        p_new, k = _backward_rhs_of(q, _mat(M_t), L, K, _vec(gu), _vec(gx_prev))
        return (new_P, _stack(p_new, like)), (*out, _stack(k, like), p_arr)

    xs = (M, Phi_u, _shift(Phi_x))
    p0 = jnp.zeros((nx, *like.shape), like.dtype)
    if with_rhs:
        g_u, g_x, rp = rhs
        xs += (g_u, rp, _shift(g_x))
        p0 = g_x[-1]
    ys = _scan(backward, (Phi_x[-1], p0), xs, True, unroll)
    factor = tuple(ys[:3])
    if not with_rhs:
        return factor, None
    k, p_next = ys[3:]
    return factor, _forward_sweep(M, factor[1], factor[2], k, p_next, rhs[2], unroll)


def _forward_sweep(M, K, P, k, p_next, rp, unroll):
    like = rp[0, 0]

    def forward(dx, stage):
        M_t, K_t, k_t, r, P_t, p = stage
        dx_next, du, nu_t = _forward(
            _vec(dx), _mat(M_t), _mat(K_t), _vec(k_t), _vec(r), _mat(P_t), _vec(p)
        )
        dx_next = _stack(dx_next, like)
        return dx_next, (_stack(du, like), dx_next, _stack(nu_t, like))

    return tuple(_scan(forward, jnp.zeros_like(rp[0]), (M, K, k, rp, P, p_next), False, unroll))


def _backward_apply(M, L, P, g_u, g_x, rp, unroll):
    like = rp[0, 0]

    def backward(p_arr, stage):
        M_t, L_t, P_t, gu, r, gx_prev = stage
        L_list = [
            [L_t[i, j] if j <= i else None for j in range(L_t.shape[1])]
            for i in range(L_t.shape[0])
        ]
        p_new, k = _backward_rhs(
            _vec(p_arr),
            _mat(M_t),
            L_list,
            lambda: _mat(P_t),
            _vec(gu),
            _vec(r),
            _vec(gx_prev),
        )
        return _stack(p_new, like), (_stack(k, like), p_arr)

    xs = (M, L, P, g_u, rp, _shift(g_x))
    k, p_next = _scan(backward, g_x[-1], xs, True, unroll)
    return k, p_next


def factor(M, Phi_u, Phi_x, unroll: int | None = None):
    """Backward Riccati factorisation: (L, K, P), each (N, entries..., b).

    Args:
        M: (N, nx, nu + nx[, b]) the stages' [B_t, A_t] (no batch axis: shared).
        Phi_u: (N, nu, nu, b), Phi_x: (N, nx, nx, b) Hessian blocks.
    """
    return _sweeps(M, Phi_u, Phi_x, None, unroll or default_unroll())[0]


def factor_solve(M, Phi_u, Phi_x, g_u, g_x, rp, unroll: int | None = None):
    """Factorisation and the step of one right-hand side: ((L, K, P), (du, dx, nu));
    g_u (N, nu, b), g_x and rp (N, nx, b)."""
    return _sweeps(M, Phi_u, Phi_x, (g_u, g_x, rp), unroll or default_unroll())


def apply(M, L, K, P, g_u, g_x, rp, unroll: int | None = None):
    """The step (du, dx, nu) of one right-hand side with a stored factorisation."""
    unroll = unroll or default_unroll()
    k, p_next = _backward_apply(M, L, P, g_u, g_x, rp, unroll)
    return _forward_sweep(M, K, P, k, p_next, rp, unroll)
