"""The start's drift x_{t+1} = A_t x_t + B_t u_t + c_t as one kernel
(:func:`rvdjax.solver.start.drift` on a GPU)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from rvdjax.solver.lanes.algebra import _mv
from rvdjax.solver.lanes.refs import _load, _store
from rvdjax.solver.rows_kernel.calls import _launch
from rvdjax.solver.rows_kernel.stage import _load_any


def _drift_kernel(dims, N, u_r, x0_r, M_r, c_r, x_out):
    """x_{t+1} = A_t x_t + B_t u_t + c_t from x0, a stage a trip (start.drift)."""
    nx, nu = dims

    def stage(t, x_prev):
        M = _load(M_r, t, nx, nu + nx)
        Ax = _mv([row[nu:] for row in M], x_prev)
        Bu = _mv([row[:nu] for row in M], _load(u_r, t, nu))
        x = [(a + b) + c for a, b, c in zip(Ax, Bu, _load_any(c_r, t, nx), strict=True)]
        _store(x_out, t, x)
        return x

    jax.lax.fori_loop(0, N, stage, _load(x0_r, 0, nx))


@functools.cache
def drift_batched(interpret: bool, block_io: bool = True):
    """The drift x_{t+1} = A_t x_t + B_t u_t + c_t (:func:`rvdjax.solver.start.drift`) of one
    problem, args (A (N, nx, nx), B (N, nx, nu), c (N, nx), u (N, nu), x0 (nx,)), and under
    ``vmap`` of a batch as one kernel (a model and offset the batch shares read once a
    tile)."""

    def run(M, c, u, x0, tables, shared_c):
        """The states (N, nx, b) from u (N, nu, b), x0 (nx, b), [B, A] (N, nx, nu + nx, b)
        or ``tables``, c (N, nx, b) or (N, nx) where ``shared_c``."""
        N, nu, nx = u.shape[0], u.shape[1], x0.shape[0]
        (x,) = _launch(
            functools.partial(_drift_kernel, (nx, nu), N),
            "rvdjax_drift",
            [u, x0[None], M, c],
            [(N, nx)],
            interpret,
            tables,
            shared=(3,) if shared_c else (),
            block_io=block_io,
        )
        return x

    @jax.custom_batching.custom_vmap
    def fn(A, B, c, u, x0):
        M = jnp.concatenate([B, A], axis=2)
        return run(*(a[..., None] for a in (M, c, u, x0)), None, False)[..., 0]

    @fn.def_vmap
    def rule_(axis_size, in_batched, A, B, c, u, x0):
        def last(a, batched):
            return jnp.moveaxis(a if batched else jnp.broadcast_to(a, (axis_size, *a.shape)), 0, -1)

        u, x0 = last(u, in_batched[3]), last(x0, in_batched[4])
        shared_c = not in_batched[2]
        c = c if shared_c else last(c, True)
        if in_batched[0] or in_batched[1]:  # a model each
            M = jnp.concatenate([last(B, in_batched[1]), last(A, in_batched[0])], axis=2)
            tables = None
        else:  # one model: a table of one, read once a tile (its place in the inputs unread)
            M = jnp.concatenate([B, A], axis=2)
            M, tables = u, (jnp.zeros((axis_size,), jnp.int32), {2: M.reshape(1, M.shape[0], -1)})
        return jnp.moveaxis(run(M, c, u, x0, tables, shared_c), -1, 0), True

    return fn
