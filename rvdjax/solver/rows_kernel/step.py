"""The corrector's step taken as one kernel program: its row steps, step length, the new
iterate, the stopping test there and, carried, the next Newton system
(:func:`rvdjax.solver.rows_kernel.pd_step_rows`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rvdjax.solver.lanes.algebra import _dot, _mtv, _mv
from rvdjax.solver.lanes.refs import _Entries, _load, _store, _tri
from rvdjax.solver.rows_kernel.stage import (
    StageRows,
    _affine,
    _corrector,
    _hessian_block,
    _load_any,
    _min_ratio,
    _pairs,
    _residual,
    _row_entries,
    _scalars,
    _soft_parts,
    _sum_products,
    _twice_plus,
)


def _step_kernel(dims, N, system, *refs):
    """One program of :func:`~rvdjax.solver.rows_kernel.calls.pd_step_rows`: two sweeps for a tile
    of problems.

    refs: Fx, Fu, s, g, mu, pi, wx, rho, su, lam, wu, the corrector's step dx, du, nu, the
    predictor's row products Fdx_a, Fdu_a, the iterate's u, x, nu, the cost blocks Q, R, the
    model [B, A], the linear costs q, r, the reference x_ref (these three per problem or
    :class:`~rvdjax.solver.rows_kernel.stage._Shared`), with ``system`` the dynamics' offset c (the
    same) and the initial state x0 (1, nx), the scalars alpha_a, kappa, fraction (1, 1) each;
    outputs U (N, 2, nu), X (N, 2, nx), Fdu, Fdx, the new u, x, nu, s, lam, mu, pi, su, g, with
    ``system`` the next iteration's Newton system at the new point
    (:func:`~rvdjax.solver.rows_kernel.calls.pd_blocks`'s six outputs), and (alpha, gap, relative
    dual residual, objective, finite).

    The first sweep forms the row products and the ratio test; the step length is known only
    after it, so it writes the dual residual's row terms F^T w (y + alpha dy) as two vectors a
    stage (U, X) and sums the complementarity as c0 + alpha c1 + alpha^2 c2. The step length
    is NaN where any entry of the step (du, dx, nu) or of the rows' steps is not finite: the
    one test of the step that the update needs. The second sweep takes the step
    (pd_algebra._updated): from the row products the first one wrote, it forms the rows'
    steps again and writes the new iterate, and forms the stopping test there
    (pd_algebra._stopping_terms): the cost gradient, the dual residual with the row terms
    U0 + alpha U1, X0 + alpha X1, the soft rows' largest |wx (rho - mu - pi)| and the
    objective. The state rows' residual r_x,t = ... - A_{t+1}^T nu_{t+1} needs the next
    stage's multipliers: the sweep carries it one stage and ends it there. On a GPU that
    replaced XLA's passes over the rows, the steps, the iterate and the model after the kernel
    (docs/benchmark.md).

    With ``system`` the second sweep also forms the Newton system of the next iteration at
    the new point, as :func:`~rvdjax.solver.rows_kernel.blocks._blocks_kernel` would from the stored
    iterate (the same arithmetic; the dynamics' residual carries the previous stage's new state):
    the next iteration starts with the factorisation, without the blocks' kernel and its reads of
    the rows and the iterate. That sweep reads every row's constraint matrix anyway, so it also
    forms the corrector's row products Fu du, Fx dx again (the first sweep's operations, the same
    numbers) and the rows' terms of the dual residual at the new point, Fu^T wu lam and Fx^T wx mu
    (as pd_algebra._stopping_terms forms them), instead of the first sweep writing the products and
    the terms' two parts (U, X) for it to read back (docs/benchmark.md); U, X, Fdu and Fdx are then
    (1, 1) placeholders."""
    mx, mu, nx, nu = dims
    row_refs = refs[:11]
    dx_r, du_r, nun_r, Fdxa_r, Fdua_r, u_r, x_r, nu_r = refs[11:19]
    Q_r, R_r, M_r, q_r, r_r, xref_r = refs[19:25]
    n_in = 27 if system else 25
    c_r, x0_r = refs[25:27] if system else (None, None)
    alpha_a, kappa, fraction = _scalars(refs[n_in : n_in + 3])
    U_out, X_out, Fdu_out, Fdx_out, *outs = refs[n_in + 3 :]
    new_out, sys_out, sc_out = outs[:9], outs[9:-1], outs[-1]

    def store_system(t, Phi_u, Phi_x, g_x, base_u, base_x, rp):
        """The next iteration's Newton system at stage t (lower triangles of Phi_u, Phi_x)."""
        for ref, v in zip(sys_out, (Phi_u, Phi_x, g_x, base_u, base_x, rp), strict=True):
            _store(ref, t, v)

    def corrector(rows, t, Fdu, Fdx):
        aff = _affine(dims, rows, _load(Fdua_r, t, mu), _load(Fdxa_r, t, mx))
        return _corrector(dims, rows, aff, Fdu, Fdx, alpha_a, kappa)

    def weighted(w, v):
        return [a * b for a, b in zip(w, v, strict=True)]

    def stage(t, carry):
        alpha, c0, c1, c2 = carry
        rows = StageRows(dims, row_refs, t)
        dx, du = _load(dx_r, t, nx), _load(du_r, t, nu)
        r = corrector(rows, t, _mv(rows.Fu, du), _mv(rows.Fx, dx))
        alpha = _min_ratio(r.pairs(rows), alpha, nan_if_not_finite=True)
        for v in (*dx, *du, *_load(nun_r, t, nx)):  # 0 * v is NaN exactly where v is not finite
            alpha = alpha + 0.0 * v
        c0, c1, c2 = _sum_products(r.products(rows), c0, c1, c2)
        if system:  # the second sweep forms the row products and the row terms again
            return alpha, c0, c1, c2
        U = [_mtv(rows.Fu, weighted(rows.wu, rows.lam)), _mtv(rows.Fu, weighted(rows.wu, r.dlam))]
        X = [_mtv(rows.Fx, weighted(rows.wx, rows.mu)), _mtv(rows.Fx, weighted(rows.wx, r.dmu))]
        _store(Fdu_out, t, r.Fdu)
        _store(Fdx_out, t, r.Fdx)
        _store(U_out, t, U)
        _store(X_out, t, X)
        return alpha, c0, c1, c2

    def stage_by_row(t, carry):
        """:func:`stage` with the input rows, then the soft rows, one at a time in loops (refs read
        entry by entry): a stage's rows, steps and products are never live at once. All of them
        at once, unrolled, leave ptxas at the edge of its register allocation: thesis-vbar's 12
        rows a stage gave 255 registers and 5.6 KB of spill stores, and the same sweep without
        the update's fell to 32 registers and 12.8 KB (sm_90a). The sums over the rows run in the
        same order (X and U as _mtv's), the complementarity's interleaved by row (the ratio
        test's minimum too, which does not depend on the order)."""
        alpha, c0, c1, c2 = carry
        dx, du = _load(dx_r, t, nx), _load(du_r, t, nu)
        for v in (*dx, *du, *_load(nun_r, t, nx)):  # 0 * v is NaN exactly where v is not finite
            alpha = alpha + 0.0 * v
        d_in, d_row = (0, 1, nx, nu), (1, 0, nx, nu)

        def inp(i, acc):  # one input row
            alpha, c0, c1, c2, U0, U1 = acc
            row = StageRows(dims, row_refs, t, ("input", i))
            aff = _affine(d_in, row, _row_entries(Fdua_r, t, i, 1), [])
            r = _corrector(d_in, row, aff, _mv(row.Fu, du), [], alpha_a, kappa)
            alpha = _min_ratio(r.pairs(row), alpha, nan_if_not_finite=True)
            c0, c1, c2 = _sum_products(r.products(row), c0, c1, c2)
            if system:
                return alpha, c0, c1, c2, U0, U1
            U0 = [a + b for a, b in zip(U0, _mtv(row.Fu, weighted(row.wu, row.lam)), strict=True)]
            U1 = [a + b for a, b in zip(U1, _mtv(row.Fu, weighted(row.wu, r.dlam)), strict=True)]
            Fdu_out.ref[t, i] = r.Fdu[0]
            return alpha, c0, c1, c2, U0, U1

        zeros_u = [] if system else [jnp.zeros_like(alpha_a)] * nu
        acc = jax.lax.fori_loop(0, mu, inp, (alpha, c0, c1, c2, zeros_u, zeros_u))
        alpha, c0, c1, c2, U0, U1 = acc
        if not system:
            _store(U_out, t, [U0, U1])

        def soft(i, acc):
            alpha, c0, c1, c2, X0, X1 = acc
            row = StageRows(dims, row_refs, t, i)
            aff = _affine(d_row, row, [], _row_entries(Fdxa_r, t, i, 1))
            r = _corrector(d_row, row, aff, [], _mv(row.Fx, dx), alpha_a, kappa)
            alpha = _min_ratio(r.pairs(row), alpha, nan_if_not_finite=True)
            c0, c1, c2 = _sum_products(r.products(row), c0, c1, c2)
            if system:
                return alpha, c0, c1, c2, X0, X1
            X0 = [a + b for a, b in zip(X0, _mtv(row.Fx, weighted(row.wx, row.mu)), strict=True)]
            X1 = [a + b for a, b in zip(X1, _mtv(row.Fx, weighted(row.wx, r.dmu)), strict=True)]
            Fdx_out.ref[t, i] = r.Fdx[0]
            return alpha, c0, c1, c2, X0, X1

        zeros = [] if system else [jnp.zeros_like(alpha_a)] * nx
        acc = jax.lax.fori_loop(0, mx, soft, (alpha, c0, c1, c2, zeros, zeros))
        alpha, c0, c1, c2, X0, X1 = acc
        if not system:
            _store(X_out, t, [X0, X1])
        return alpha, c0, c1, c2

    if isinstance(row_refs[0], _Entries):
        stage = stage_by_row  # noqa: F811

    zero = 0.0 * kappa
    alpha, c0, c1, c2 = jax.lax.fori_loop(0, N, stage, (zero + jnp.inf, zero, zero, zero))
    # pd_algebra._updated: ``fraction`` of the way to the boundary, at most 1; zero where the
    # step is not finite (alpha NaN) or the solve is stopped (fraction 0)
    finite = ~jnp.isnan(alpha)
    take = finite & (fraction > 0.0)
    alpha = jnp.where(take, jnp.minimum(1.0, fraction * jnp.minimum(1.0, alpha)), 0.0)
    gap = jnp.where(finite, c0 + alpha * (c1 + alpha * c2), c0)

    def upd(v, dv, w=None):
        keep = finite if w is None else finite & (w > 0)  # padding rows stay put
        return v + alpha * jnp.where(keep, dv, 0.0)

    def row_terms(ref, t, n):  # U0 + alpha U1 (the old point's where the step is not finite)
        y, dy = _load(ref, t, 2, n)
        return [jnp.where(finite, a + alpha * b, a) for a, b in zip(y, dy, strict=True)]

    def update(t, carry):
        rs, js, wr, ru, rx, gm, J, p_prev, *x_prev = carry
        rows = StageRows(dims, row_refs, t)
        dx, du = _load(dx_r, t, nx), _load(du_r, t, nu)
        if system:  # the first sweep's products again (the same operations), not stored
            r = corrector(rows, t, _mv(rows.Fu, du), _mv(rows.Fx, dx))
        else:
            r = corrector(rows, t, _load(Fdu_out, t, mu), _load(Fdx_out, t, mx))
        nu_old = _load(nu_r, t, nx)
        dnu = [a - b for a, b in zip(_load(nun_r, t, nx), nu_old, strict=True)]
        new = [
            [upd(v, d) for v, d in zip(_load(u_r, t, nu), du, strict=True)],
            [upd(v, d) for v, d in zip(_load(x_r, t, nx), dx, strict=True)],
            [upd(v, d) for v, d in zip(nu_old, dnu, strict=True)],
            [upd(v, d, w) for v, d, w in zip(rows.s, r.ds, rows.wx, strict=True)],
            [upd(v, d, w) for v, d, w in zip(rows.lam, r.dlam, rows.wu, strict=True)],
            [upd(v, d, w) for v, d, w in zip(rows.mu, r.dmu, rows.wx, strict=True)],
            [upd(v, d, w) for v, d, w in zip(rows.pi, r.dpi, rows.wx, strict=True)],
            [upd(v, d) for v, d in zip(rows.su, r.dsu, strict=True)],
            [upd(v, d) for v, d in zip(rows.g, r.Fdx, strict=True)],
        ]
        for ref, v in zip(new_out, new, strict=True):
            _store(ref, t, v)
        u_n, x_n, nu_n, s_n, lam_n, mu_n, pi_n, su_n, g_n = new
        for w, rho, m, p, g in zip(rows.wx, rows.rho, mu_n, pi_n, g_n, strict=True):
            rs = jnp.maximum(rs, jnp.abs(w * (rho - m - p)))
            js = js + w * rho * jnp.maximum(g, 0.0)
            wr = jnp.maximum(wr, w * rho)
        terms = None
        if system:  # the rows' terms at the new point
            U = _mtv(rows.Fu, weighted(rows.wu, lam_n))
            terms = (U, _mtv(rows.Fx, weighted(rows.wx, mu_n)))
        carry, (base_u, base_x, M) = stopping(t, u_n, x_n, nu_n, (ru, rx, gm, J, p_prev), terms)
        if not system:
            return rs, js, wr, *carry
        Du = [w * lm / v for w, lm, v in zip(rows.wu, lam_n, su_n, strict=True)]
        d, v = _soft_parts(rows.wx, rows.rho, s_n, g_n, mu_n, pi_n)
        store_system(
            t,
            list(_tri(_hessian_block(_load(R_r, t, nu, nu), rows.Fu, Du))),
            list(_tri(_hessian_block(_load(Q_r, t, nx, nx), rows.Fx, d))),
            [b + f for b, f in zip(base_x, _mtv(rows.Fx, v), strict=True)],
            base_u,
            base_x,
            _residual(M, nu, x_n, x_prev[0], u_n, _load_any(c_r, t, nx)),
        )
        return rs, js, wr, *carry, x_n

    def stopping(t, u_n, x_n, nu_n, carry, terms=None):
        """The stopping test (pd_algebra._stopping_terms) at the new point u_n, x_n, nu_n
        of stage t: the dual residual's maxima, the gradient's, the objective and the state
        residual's part carried to the next stage; and the cost's gradient there (the next
        Newton system's base_u, base_x) and the stage's model. ``terms``: the rows' terms
        Fu^T wu lam, Fx^T wx mu at the new point, else U0 + alpha U1, X0 + alpha X1 from the
        first sweep."""
        ru, rx, gm, J, p_prev = carry
        U, X = terms if terms is not None else (row_terms(U_out, t, nu), row_terms(X_out, t, nx))
        e = [a - b for a, b in zip(x_n, _load_any(xref_r, t, nx), strict=True)]
        Ru, Qe = _mv(_load(R_r, t, nu, nu), u_n), _mv(_load(Q_r, t, nx, nx), e)
        q, r_lin = _load_any(q_r, t, nx), _load_any(r_r, t, nu)
        M = _load(M_r, t, nx, nu + nx)
        grad_u = [2.0 * a + b for a, b in zip(Ru, r_lin, strict=True)]
        grad_x = [2.0 * a + b for a, b in zip(Qe, q, strict=True)]
        Bt_nu = _mtv([row[:nu] for row in M], nu_n)
        for g, f, b in zip(grad_u, U, Bt_nu, strict=True):
            ru = jnp.maximum(ru, jnp.abs((g + f) - b))
        # r_x of the previous stage: its part p_{t-1} less A_t^T nu_t (none before stage 0)
        At_nu = _mtv([row[nu:] for row in M], nu_n)
        for p, a in zip(p_prev, At_nu, strict=True):
            rx = jnp.where(t > 0, jnp.maximum(rx, jnp.abs(p - a)), rx)
        p_t = [(g + f) + n for g, f, n in zip(grad_x, X, nu_n, strict=True)]
        for g in (*grad_u, *grad_x):
            gm = jnp.maximum(gm, jnp.abs(g))
        for a, b in ((e, Qe), (u_n, Ru), (q, x_n), (r_lin, u_n)):
            J = J + _dot(a, b)
        return (ru, rx, gm, J, p_t), (grad_u, grad_x, M)

    def update_by_row(t, carry):
        """:func:`update` with the input rows and the soft rows one at a time in loops (as
        :func:`stage_by_row`; the same operations, and the penalty sum in the same order).
        With ``system``, the next Newton system's sums over the rows run in those loops, in
        the order of :func:`~rvdjax.solver.rows_kernel.blocks._blocks_kernel`'s."""
        rs, js, wr, ru, rx, gm, J, p_prev, *x_prev = carry
        dx, du = _load(dx_r, t, nx), _load(du_r, t, nu)
        nu_old = _load(nu_r, t, nx)
        dnu = [a - b for a, b in zip(_load(nun_r, t, nx), nu_old, strict=True)]
        u_n = [upd(v, d) for v, d in zip(_load(u_r, t, nu), du, strict=True)]
        x_n = [upd(v, d) for v, d in zip(_load(x_r, t, nx), dx, strict=True)]
        nu_n = [upd(v, d) for v, d in zip(nu_old, dnu, strict=True)]
        u_o, x_o, nu_o, s_o, lam_o, mu_o, pi_o, su_o, g_o = new_out
        for ref, v in ((u_o, u_n), (x_o, x_n), (nu_o, nu_n)):
            _store(ref, t, v)
        d_in, d_row = (0, 1, nx, nu), (1, 0, nx, nu)

        def inp(i, acc):  # one input row (the next Phi_u's sum over the rows, Fu^T wu lam)
            row = StageRows(dims, row_refs, t, ("input", i))
            aff = _affine(d_in, row, _row_entries(Fdua_r, t, i, 1), [])
            Fdu = _mv(row.Fu, du) if system else _row_entries(Fdu_out, t, i, 1)
            r = _corrector(d_in, row, aff, Fdu, [], alpha_a, kappa)
            lam_n = upd(row.lam[0], r.dlam[0], row.wu[0])
            su_n = upd(row.su[0], r.dsu[0])
            lam_o.ref[t, i] = lam_n
            su_o.ref[t, i] = su_n
            if not system:
                return acc
            (Pu, U), (w,), (F,) = acc, row.wu, row.Fu
            Du = w * lam_n / su_n
            Pu = [p + F[j] * (Du * F[k]) for p, (j, k) in zip(Pu, _pairs(nu), strict=True)]
            return Pu, [a + b for a, b in zip(U, _mtv(row.Fu, [w * lam_n]), strict=True)]

        zero = jnp.zeros_like(x_n[0])
        if system:
            Pu, U = jax.lax.fori_loop(0, mu, inp, ([zero] * len(_pairs(nu)), [zero] * nu))
        else:
            jax.lax.fori_loop(0, mu, inp, 0)

        def soft(i, acc):
            rs, js, wr, *sums = acc
            row = StageRows(dims, row_refs, t, i)
            aff = _affine(d_row, row, [], _row_entries(Fdxa_r, t, i, 1))
            Fdx = _mv(row.Fx, dx) if system else _row_entries(Fdx_out, t, i, 1)
            r = _corrector(d_row, row, aff, [], Fdx, alpha_a, kappa)
            (w,), (rho,) = row.wx, row.rho
            s_n, mu_n, pi_n = (upd(v[0], d[0], w) for v, d in ((row.s, r.ds), (row.mu, r.dmu),
                                                               (row.pi, r.dpi)))  # fmt: skip
            g_n = upd(row.g[0], Fdx[0])
            for ref, v in ((s_o, s_n), (mu_o, mu_n), (pi_o, pi_n), (g_o, g_n)):
                ref.ref[t, i] = v
            rs = jnp.maximum(rs, jnp.abs(w * (rho - mu_n - pi_n)))
            js = js + w * rho * jnp.maximum(g_n, 0.0)
            wr = jnp.maximum(wr, w * rho)
            if not system:
                return rs, js, wr
            # the next Phi_x's and g_x's sums over the rows (_blocks_kernel's stage_by_row), and
            # Fx^T wx mu at the new point
            (d,), (v,) = _soft_parts(row.wx, row.rho, [s_n], [g_n], [mu_n], [pi_n])
            (F,), (P, g, X) = row.Fx, sums
            P = [p + F[j] * (d * F[k]) for p, (j, k) in zip(P, _pairs(nx), strict=True)]
            X = [a + b for a, b in zip(X, _mtv(row.Fx, [w * mu_n]), strict=True)]
            return rs, js, wr, P, [a + f * v for a, f in zip(g, F, strict=True)], X

        sums = ([zero] * len(_pairs(nx)), [zero] * nx, [zero] * nx) if system else ()
        rs, js, wr, *sums = jax.lax.fori_loop(0, mx, soft, (rs, js, wr, *sums))
        terms = (U, sums[2]) if system else None
        carry, (base_u, base_x, M) = stopping(t, u_n, x_n, nu_n, (ru, rx, gm, J, p_prev), terms)
        if not system:
            return rs, js, wr, *carry
        (P, g, _), R, Q = sums, _load(R_r, t, nu, nu), _load(Q_r, t, nx, nx)
        store_system(
            t,
            _twice_plus(R, Pu),
            _twice_plus(Q, P),
            [b + f for b, f in zip(base_x, g, strict=True)],
            base_u,
            base_x,
            _residual(M, nu, x_n, x_prev[0], u_n, _load_any(c_r, t, nx)),
        )
        return rs, js, wr, *carry, x_n

    if isinstance(row_refs[0], _Entries):
        update = update_by_row  # noqa: F811
    carry = (zero,) * 7 + ([zero] * nx,) + ((_load(x0_r, 0, nx),) if system else ())
    rs, js, wr, ru, rx, gm, J, p_last, *_ = jax.lax.fori_loop(0, N, update, carry)
    for p in p_last:  # the last stage's r_x: no next stage
        rx = jnp.maximum(rx, jnp.abs(p))
    rel_d = jnp.maximum(jnp.maximum(ru, rx) / (1.0 + gm), rs / (1.0 + wr))
    _store(sc_out, 0, [alpha, gap, rel_d, J + js, finite.astype(alpha.dtype)])
