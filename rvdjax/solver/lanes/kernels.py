"""The Riccati kernels' programs: the factorisation with its first solve, a solve with a
stored factorisation, and a solve with one step of iterative refinement, for one tile of
problems."""

from __future__ import annotations

import functools

import jax.numpy as jnp
from jax import lax

from rvdjax.solver.lanes.algebra import _mtv, _mv
from rvdjax.solver.lanes.packing import (
    tri_size,
)
from rvdjax.solver.lanes.refs import (
    _Block,
    _Entries,
    _load,
    _load_lower,
    _load_sym,
    _lower,
    _model_refs,
    _store,
    _tri,
    _untri,
)
from rvdjax.solver.lanes.stage import (
    _backward_rhs,
    _backward_rhs_of,
    _backward_rhs_stored,
    _factor_stage,
    _forward_solved,
    _offset,
    _split,
)


def _kernel(N, nx, nu, lanes, with_rhs, factorise, block_io, padded, model, model_only, *refs):
    """One program: the sweeps for a tile of ``lanes`` problems (:mod:`rvdjax.solver.lanes`).

    refs: M = [B, A] (N, nx, nu + nx[, lanes]), then (factorise) Phi_u, Phi_x (their lower
    triangles, :func:`~rvdjax.solver.lanes.refs._tri`) or (not factorise) L, P; then (with_rhs) g_u,
    g_x, rp; outputs: (factorise) L, P; (with_rhs) du, dx, nu. The backward sweep keeps p_{t+1} in
    nu's rows until the forward sweep overwrites them. ``model`` as
    :func:`~rvdjax.solver.lanes.refs._model_refs`; ``model_only``: with ``block_io``, the model
    alone in blocks, the rest entry by entry (:attr:`KernelConfig.model_blocks_only`).
    """
    refs = _model_refs(refs, model, block_io, padded)
    if model_only:
        refs = [refs[0], *(_Entries(r.ref) if isinstance(r, _Block) else r for r in refs[1:])]
    M_ref = refs[0]
    pos = 1
    if factorise:
        Phu_ref, Phx_ref = refs[pos : pos + 2]
        pos += 2
    else:
        L_in, P_in = refs[pos : pos + 2]
        pos += 2
    if with_rhs:
        gu_ref, gx_ref, rp_ref = refs[pos : pos + 3]
        pos += 3
    outs = refs[pos:]
    if factorise:
        L_ref, P_ref = outs[:2]
        outs = outs[2:]
    else:
        L_ref, P_ref = L_in, P_in
    if with_rhs:
        du_ref, dx_ref, nu_ref = outs
    dtype = (Phx_ref if factorise else P_ref).dtype
    zero = jnp.zeros((lanes,), dtype)

    def backward(i, carry):
        t = N - 1 - i
        M = _load(M_ref, t, nx, nu + nx)
        # P_{t+1} and p_{t+1} stored and the right-hand side's p - P r formed first, and Phi_x
        # read last (Phx_prev): past its product with [B, A] the factorisation needs nothing
        # else of P, so fewer entries are live at once (ptxas for sm_90a, the factorisation
        # in thesis-vbar's engine: 1.7 / 2.2 KB of spill stores / loads instead of 2.6 / 3.2;
        # docs/benchmark.md)
        if factorise:
            P = _untri(carry[0], nx)
            _store(P_ref, t, list(carry[0]))
        else:
            P = _load_sym(P_ref, t, nx)
        if with_rhs:
            p = list(carry[-1])
            _store(nu_ref, t, p)
            q = _offset(p, P, _load(rp_ref, t, nx))
        if factorise:
            Phu = _load_sym(Phu_ref, t, nu)
            prev = jnp.maximum(t - 1, 0)
            on = t > 0

            def Phx_prev():
                Phx = _load(Phx_ref, prev, tri_size(nx))
                return _untri([jnp.where(on, v, 0.0) for v in Phx], nx)

            P_new, L, K = _factor_stage(P, M, Phu, Phx_prev)
            _store(L_ref, t, list(_lower(L)))
            new = (_tri(P_new),)
        else:
            L = _load_lower(L_ref, t, nu)
            new = ()
        if with_rhs:
            prev = jnp.maximum(t - 1, 0)
            on = t > 0
            gx_prev = [jnp.where(on, v, 0.0) for v in _load(gx_ref, prev, nx)]
            gu = _load(gu_ref, t, nu)
            if factorise:  # the gain is at hand
                p_new, _ = _backward_rhs_of(q, M, L, K, gu, gx_prev)
            else:  # the stored P again (cached): no gain is stored
                P_of = functools.partial(_load_sym, P_ref, t, nx)
                p_new, _ = _backward_rhs_stored(q, M, L, P_of, gu, gx_prev)
            new = new + (tuple(p_new),)
        return new

    carry = ()
    if factorise:
        carry += (tuple(_load(Phx_ref, N - 1, tri_size(nx))),)
    if with_rhs:
        carry += (tuple(_load(gx_ref, N - 1, nx)),)
    lax.fori_loop(0, N, backward, carry)
    if not with_rhs:
        return

    out = (du_ref, dx_ref, nu_ref)
    _forward_sweep((N, nx, nu), zero, M_ref, L_ref, P_ref, gu_ref, rp_ref, nu_ref, out)


def _forward_sweep(dims, zero, M_ref, L_ref, P_ref, g_ref, r_ref, p_ref, out, add=False):
    """The forward sweep of one right-hand side, whose input gradient g_u, affine term p and
    dynamics residual r are stored a stage each (each stage solved again,
    :func:`~rvdjax.solver.lanes.stage._forward_solved`): (du, dx, nu) written to the refs ``out``,
    or (``add``) added to the step they hold (a refinement's correction). ``dims``: (N, nx, nu)."""
    N, nx, nu = dims

    def stage(t, dx):
        dx_next, du, nu_t = _forward_solved(
            list(dx),
            _load(M_ref, t, nx, nu + nx),
            _load_lower(L_ref, t, nu),
            _load(g_ref, t, nu),
            _load(r_ref, t, nx),
            functools.partial(_load_sym, P_ref, t, nx),
            _load(p_ref, t, nx),
        )
        for ref, v in zip(out, (du, dx_next, nu_t), strict=True):
            if add:
                v = [a + b for a, b in zip(_load(ref, t, len(v)), v, strict=True)]
            _store(ref, t, v)
        return tuple(dx_next)

    lax.fori_loop(0, N, stage, tuple(zero for _ in range(nx)))


def _refined_kernel(N, nx, nu, lanes, block_io, padded, model, *refs):
    """One program of :func:`~rvdjax.solver.lanes.calls.apply_refined`: the step of one
    right-hand side, then one step of iterative refinement against the KKT matrix
    (:func:`rvdjax.solver.kkt.kkt_refine`), whose residual is formed stage by stage inside the
    sweeps instead of in a pass of its own.

    refs: M, L, P, Phi_u, Phi_x, g_u, g_x, rp; outputs du, dx, nu (the first step,
    then the refined one), and g2, p2, rp2 (the correction's right-hand side g_u, its affine
    term p and its dynamics residual, kept between its sweeps). ``model`` as
    :func:`~rvdjax.solver.lanes.refs._model_refs`.
    """
    refs = _model_refs(refs, model, block_io, padded)
    M_ref, L_ref, P_ref, Phu_ref, Phx_ref, gu_ref, gx_ref, rp_ref = refs[:8]
    du_ref, dx_ref, nu_ref, g2_ref, p2_ref, rp2_ref = refs[8:]
    zero = jnp.zeros((lanes,), Phx_ref.dtype)

    def backward(g_ref, p_ref, rhs, p0):
        """The backward sweep of rhs(t, M_t) -> (g_u[t], r[t], g_x[t-1]): p_{t+1} stored, and
        g_u[t] where it is formed here (``g_ref`` not None), for the forward sweep."""

        def stage(i, p):
            t = N - 1 - i
            M = _load(M_ref, t, nx, nu + nx)
            gu, r, gx_prev = rhs(t, M)
            P_of = functools.partial(_load_sym, P_ref, t, nx)  # twice: read again, cached
            p_new, _ = _backward_rhs(list(p), M, _load_lower(L_ref, t, nu), P_of, gu, r, gx_prev)
            if g_ref is not None:
                _store(g_ref, t, gu)
            _store(p_ref, t, p)
            return tuple(p_new)

        lax.fori_loop(0, N, stage, tuple(p0))

    def first_rhs(t, M):
        on = t > 0
        gx_prev = _load(gx_ref, jnp.maximum(t - 1, 0), nx)
        return _load(gu_ref, t, nu), _load(rp_ref, t, nx), [jnp.where(on, v, 0.0) for v in gx_prev]

    backward(None, nu_ref, first_rhs, _load(gx_ref, N - 1, nx))

    step = (du_ref, dx_ref, nu_ref)
    _forward_sweep((N, nx, nu), zero, M_ref, L_ref, P_ref, gu_ref, rp_ref, nu_ref, step)

    # The residual K z + (g, rp) of the first step z (kkt.kkt_residual), stage by stage.
    def r_x(t, A_next=None):
        """Phi_x dx_t + g_x + nu_t - A_{t+1}^T nu_{t+1} (``A_next`` = A_{t+1}; none at the last
        stage)."""
        Phx = _load_sym(Phx_ref, t, nx)
        g = [
            a + b for a, b in zip(_mv(Phx, _load(dx_ref, t, nx)), _load(gx_ref, t, nx), strict=True)
        ]
        out = [a + b for a, b in zip(g, _load(nu_ref, t, nx), strict=True)]
        if A_next is None:
            return out
        At_nu = _mtv(A_next, _load(nu_ref, jnp.minimum(t + 1, N - 1), nx))
        return [o - v for o, v in zip(out, At_nu, strict=True)]

    def residual_rhs(t, M):
        A, B = _split(M, nu)
        du, dx, nu_t = _load(du_ref, t, nu), _load(dx_ref, t, nx), _load(nu_ref, t, nx)
        g_u = [
            a + b
            for a, b in zip(_mv(_load_sym(Phu_ref, t, nu), du), _load(gu_ref, t, nu), strict=True)
        ]
        r_u = [a - b for a, b in zip(g_u, _mtv(B, nu_t), strict=True)]
        on = t > 0
        prev = jnp.maximum(t - 1, 0)
        dx_prev = [jnp.where(on, v, 0.0) for v in _load(dx_ref, prev, nx)]
        r_p = [
            a - b - c + d
            for a, b, c, d in zip(
                dx, _mv(B, du), _mv(A, dx_prev), _load(rp_ref, t, nx), strict=True
            )
        ]
        _store(rp2_ref, t, r_p)
        return r_u, r_p, [jnp.where(on, v, 0.0) for v in r_x(prev, A)]  # A = A_{prev + 1}

    backward(g2_ref, p2_ref, residual_rhs, r_x(N - 1))

    _forward_sweep((N, nx, nu), zero, M_ref, L_ref, P_ref, g2_ref, rp2_ref, p2_ref, step, True)
