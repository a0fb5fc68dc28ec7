"""The row work between the predictor's solve and the corrector's as one kernel program
(:func:`rvdjax.solver.rows_kernel.pd_rows`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rvdjax.solver.lanes.algebra import _mtv, _mv
from rvdjax.solver.lanes.refs import _Entries, _load, _store
from rvdjax.solver.rows_kernel.stage import (
    SigmaRule,
    StageRows,
    _affine,
    _input_terms,
    _min_ratio,
    _scalars,
    _soft_terms,
    _sum_products,
)


def _rows_kernel(dims, N, rule: SigmaRule, *refs):
    """One program: the sweeps for a tile of problems (:mod:`rvdjax.solver.rows_kernel`).

    refs: Fx, Fu, s, g, mu, pi, wx, rho, su, lam, wu, dx, du, base_x, base_u, the scalars
    gap, res, m_eff (1, 1) each; outputs G_u (N, 3, nu), G_x (N, 3, nx), Fdu, Fdx,
    alpha_a (1, 1), kappa (1, 1), g_u (N, nu), g_x (N, nx).

    The step length and the barrier weight are known only after the first sweep, so it forms
    what needs them as polynomials in them: the complementarity after the step,
    c0 + alpha c1 + alpha^2 c2, and the right-hand side, G0 + kappa G1 + alpha G2 (the
    corrector's targets kappa - alpha dv dy are affine in both; pd_algebra._pd_rhs). A
    second sweep evaluates the right-hand side from the parts the first one wrote (on a GPU,
    two launches of XLA's an iteration less)."""
    mx, mu, nx, nu = dims
    row_refs = refs[:13]
    bx_r, bu_r = refs[13:15]
    gap, res, m_eff = _scalars(refs[15:18])
    Gu_out, Gx_out, Fdu_out, Fdx_out, alpha_out, kappa_out, gu_out, gx_out = refs[18:]

    def stage(t, carry):
        alpha, c0, c1, c2 = carry
        rows = StageRows(dims, row_refs, t)
        dx, du = _load(row_refs[11], t, nx), _load(row_refs[12], t, nu)
        r = _affine(dims, rows, _mv(rows.Fu, du), _mv(rows.Fx, dx))
        alpha = _min_ratio(r.pairs(rows), alpha)
        c0, c1, c2 = _sum_products(r.products(rows), c0, c1, c2)
        u1, u2 = _input_terms(rows, r)
        x0, x1, x2 = _soft_terms(rows, r)
        G_u = [_load(bu_r, t, nu), _mtv(rows.Fu, u1), _mtv(rows.Fu, u2)]
        G_x = [[b + v for b, v in zip(_load(bx_r, t, nx), _mtv(rows.Fx, x0), strict=True)]]
        G_x += [_mtv(rows.Fx, x1), _mtv(rows.Fx, x2)]
        _store(Gu_out, t, G_u)
        _store(Gx_out, t, G_x)
        _store(Fdu_out, t, r.Fdu)
        _store(Fdx_out, t, r.Fdx)
        return alpha, c0, c1, c2

    def stage_by_row(t, carry):
        """:func:`stage` with the input rows and the soft rows one at a time in loops (refs
        read entry by entry), as the step's kernel does
        (:func:`~rvdjax.solver.rows_kernel.step._step_kernel`)."""
        alpha, c0, c1, c2 = carry
        dx, du = _load(row_refs[11], t, nx), _load(row_refs[12], t, nu)

        def inp(i, acc):  # one input row
            alpha, c0, c1, c2, U1, U2 = acc
            row = StageRows(dims, row_refs, t, ("input", i))
            r = _affine((0, 1, nx, nu), row, _mv(row.Fu, du), [])
            alpha = _min_ratio(r.pairs(row), alpha)
            c0, c1, c2 = _sum_products(r.products(row), c0, c1, c2)
            u1, u2 = _input_terms(row, r)
            U1 = [a + b for a, b in zip(U1, _mtv(row.Fu, u1), strict=True)]
            U2 = [a + b for a, b in zip(U2, _mtv(row.Fu, u2), strict=True)]
            Fdu_out.ref[t, i] = r.Fdu[0]
            return alpha, c0, c1, c2, U1, U2

        zeros_u = [jnp.zeros_like(gap)] * nu
        alpha, c0, c1, c2, U1, U2 = jax.lax.fori_loop(
            0, mu, inp, (alpha, c0, c1, c2, zeros_u, zeros_u)
        )
        _store(Gu_out, t, [_load(bu_r, t, nu), U1, U2])

        def soft(i, acc):
            alpha, c0, c1, c2, *G = acc
            row = StageRows(dims, row_refs, t, i)
            r = _affine((1, 0, nx, nu), row, [], _mv(row.Fx, dx))
            alpha = _min_ratio(r.pairs(row), alpha)
            c0, c1, c2 = _sum_products(r.products(row), c0, c1, c2)
            G = [
                [a + b for a, b in zip(g, _mtv(row.Fx, x), strict=True)]
                for g, x in zip(G, _soft_terms(row, r), strict=True)
            ]
            Fdx_out.ref[t, i] = r.Fdx[0]
            return alpha, c0, c1, c2, *G

        zeros = [jnp.zeros_like(gap)] * nx
        alpha, c0, c1, c2, *G = jax.lax.fori_loop(
            0, mx, soft, (alpha, c0, c1, c2, zeros, zeros, zeros)
        )
        G[0] = [b + v for b, v in zip(_load(bx_r, t, nx), G[0], strict=True)]
        _store(Gx_out, t, G)
        return alpha, c0, c1, c2

    if isinstance(row_refs[0], _Entries):
        stage = stage_by_row  # noqa: F811

    zero = 0.0 * gap
    alpha, c0, c1, c2 = jax.lax.fori_loop(0, N, stage, (zero + jnp.inf, zero, zero, zero))
    alpha = jnp.minimum(1.0, alpha)
    gap_a = c0 + alpha * (c1 + alpha * c2)
    sigma = jnp.clip(gap_a / jnp.maximum(gap, 1e-300), 0.0, 1.0) ** 3
    res = jnp.where(jnp.isfinite(res), res, 0.0)
    sigma = jnp.where(res > rule.floor_res, jnp.maximum(sigma, rule.floor), sigma)
    kappa = sigma * gap / jnp.maximum(m_eff, 1.0)
    _store(alpha_out, 0, [alpha])
    _store(kappa_out, 0, [kappa])

    def combine(t, carry):  # the right-hand side G0 + kappa G1 + alpha G2
        for ref, out, n in ((Gu_out, gu_out, nu), (Gx_out, gx_out, nx)):
            G0, G1, G2 = _load(ref, t, 3, n)
            _store(out, t, [a + kappa * b + alpha * c for a, b, c in zip(G0, G1, G2, strict=True)])
        return carry

    jax.lax.fori_loop(0, N, combine, 0)
