"""The predictor's Newton system as one kernel program: the Hessian blocks, the cost's
gradient, the right-hand side and the dynamics' residual
(:func:`rvdjax.solver.rows_kernel.pd_blocks`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rvdjax.solver.lanes.algebra import _mtv, _mv
from rvdjax.solver.lanes.refs import _Entries, _load, _store, _tri
from rvdjax.solver.rows_kernel.stage import (
    StageRows,
    _hessian_block,
    _load_any,
    _pairs,
    _residual,
    _soft_parts,
    _twice_plus,
)


def _blocks_kernel(dims, N, *refs):
    """One program of :func:`~rvdjax.solver.rows_kernel.calls.pd_blocks`: the sweep for a tile of
    problems.

    refs: Fx, Fu, s, g, mu, pi, wx, rho, su, lam, wu, the iterate's u, x, the cost blocks Q,
    R, the model [B, A], the linear costs q, r, the reference x_ref and the dynamics' offset c
    (these four per problem or :class:`~rvdjax.solver.rows_kernel.stage._Shared`), the initial state
    x0 (1, nx); outputs Phi_u (N, tri(nu)), Phi_x (N, tri(nx)) (lower triangles,
    :func:`lanes.tri_pack`'s order), g_x (N, nx), the cost's gradient base_u (N, nu), base_x (N, nx)
    and the dynamics' residual rp (N, nx). The residual at stage t needs the previous stage's state:
    a second sweep forms it, carrying the state (it reads u, x and the model again, 3 KB a
    thesis-vbar problem)."""
    mx, mu, nx, nu = dims
    row_refs = refs[:11]
    u_r, x_r, Q_r, R_r, M_r, q_r, r_r, xref_r, c_r, x0_r = refs[11:21]
    Pu_out, Px_out, gx_out, bu_out, bx_out, rp_out = refs[21:]

    def soft_parts(rows):  # the soft rows' weights: d of Phi_x, v of g_x = base_x + Fx^T v
        return _soft_parts(rows.wx, rows.rho, rows.s, rows.g, rows.mu, rows.pi)

    def cost(t, Q, R):  # the cost's gradient (pd_algebra._cost_gradient)
        x, u = _load(x_r, t, nx), _load(u_r, t, nu)
        e = [a - b for a, b in zip(x, _load_any(xref_r, t, nx), strict=True)]
        base_u = [2.0 * a + b for a, b in zip(_mv(R, u), _load_any(r_r, t, nu), strict=True)]
        base_x = [2.0 * a + b for a, b in zip(_mv(Q, e), _load_any(q_r, t, nx), strict=True)]
        return base_u, base_x

    def stage(t, carry):
        rows = StageRows(dims, row_refs, t)
        Q, R = _load(Q_r, t, nx, nx), _load(R_r, t, nu, nu)
        d, v = soft_parts(rows)
        Phi_u = _hessian_block(R, rows.Fu, rows.Du)
        Phi_x = _hessian_block(Q, rows.Fx, d)
        base_u, base_x = cost(t, Q, R)
        g_x = [b + f for b, f in zip(base_x, _mtv(rows.Fx, v), strict=True)]
        _store(Pu_out, t, list(_tri(Phi_u)))
        _store(Px_out, t, list(_tri(Phi_x)))
        _store(gx_out, t, g_x)
        _store(bu_out, t, base_u)
        _store(bx_out, t, base_x)
        return carry

    def stage_by_row(t, carry):
        """:func:`stage` with the soft rows one at a time in a loop (refs read entry by
        entry), as the step's kernel does (:func:`~rvdjax.solver.rows_kernel.step._step_kernel`):
        F^T diag(d) F (its lower triangle) and F^T v summed row by row in the order of
        :func:`rvdjax.solver.lanes.algebra._mtm`. The input rows stay unrolled: in a loop of their
        own they took the kernel from 168 to 204 registers with 65 536 QPs of a model each (the cost
        block R then lives through the loop; ptxas for sm_90a)."""
        inputs = StageRows(dims, row_refs, t, "inputs")
        Q, R = _load(Q_r, t, nx, nx), _load(R_r, t, nu, nu)
        _store(Pu_out, t, list(_tri(_hessian_block(R, inputs.Fu, inputs.Du))))
        base_u, base_x = cost(t, Q, R)
        _store(bu_out, t, base_u)
        _store(bx_out, t, base_x)

        def soft(i, acc):  # the lower triangle of F^T diag(d) F, row j entry k: F_j (d F_k)
            P, g = acc
            row = StageRows(dims, row_refs, t, i)
            (d,), (v,) = soft_parts(row)
            (F,) = row.Fx
            P = [p + F[j] * (d * F[k]) for p, (j, k) in zip(P, pairs, strict=True)]
            g = [a + f * v for a, f in zip(g, F, strict=True)]
            return P, g

        zero = jnp.zeros_like(Q[0][0])
        pairs = _pairs(nx)
        P, g = jax.lax.fori_loop(0, mx, soft, ([zero] * len(pairs), [zero] * nx))
        # Q read again rather than held through the rows' loop, where its entries took
        # registers (ptxas for sm_90a: 166 registers a thread instead of 184, so three
        # programs a multiprocessor instead of two; docs/benchmark.md)
        Q = _load(Q_r, t, nx, nx)
        _store(Px_out, t, _twice_plus(Q, P))
        _store(gx_out, t, [b + f for b, f in zip(base_x, g, strict=True)])
        return carry

    if isinstance(row_refs[0], _Entries):
        stage = stage_by_row  # noqa: F811

    def residual(t, x_prev):
        # the dynamics' residual x_t - A_t x_{t-1} - B_t u_t - c_t (barrier.dyn_residual) in a
        # sweep of its own, which carries the previous state: in the rows' sweep the model's
        # entries beside the rows' made ptxas give the kernel 32 registers and 12 KB of spill
        # stores (thesis-vbar's engine, sm_90a; sweeps/gpu_registers.py)
        x, u = _load(x_r, t, nx), _load(u_r, t, nu)
        M = _load(M_r, t, nx, nu + nx)
        _store(rp_out, t, _residual(M, nu, x, x_prev, u, _load_any(c_r, t, nx)))
        return x

    jax.lax.fori_loop(0, N, stage, 0)
    jax.lax.fori_loop(0, N, residual, _load(x0_r, 0, nx))
