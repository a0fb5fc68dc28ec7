"""The accurate mode's row work as three GPU kernels: before, between and after its two
Newton solves.

Before the first solve, the Newton matrix's diagonal blocks Phi_u = 2 R + Fu^T Du Fu,
Phi_x = 2 Q + Fx^T D Fx and the predictor's right-hand side g_x depend on the rows and their
multipliers; XLA formed them in three passes, two of which read Fx. :func:`pd_blocks` forms
them in one sweep, with the cost's gradient 2 R u + r, 2 Q (x - x_ref) + q at the iterate,
which both right-hand sides share.

Between the predictor's solve and the corrector's, a Mehrotra iteration
(:func:`rvdjax.solver.primal_dual.pd_iteration`) works on the constraint rows only: the
predictor's row steps (F du, F dx and the slack and multiplier steps that follow), its step
length (a ratio test over every row), the complementarity after that step, Mehrotra's sigma
and the corrector's targets, and from them the corrector's right-hand side F^T (...). On a GPU
XLA made that about eight passes through device memory, reading the rows, their multipliers
and the constraint matrix Fx again in most of them (thesis-vbar: 12 soft rows a stage, Fx
17 KB a problem; docs/benchmark.md). Here it is one Pallas kernel (Triton on a GPU,
interpreted on the CPU for the tests), one problem per lane as in :mod:`rvdjax.solver.lanes`,
in one sweep over the stages that reads each stage's rows once (:func:`pd_rows`).

After the corrector's solve the same holds for its row steps, its step length (the ratio
test, NaN where a step is not finite), the update of the iterate itself, the complementarity
at the new point and the stopping test there: the cost gradient, the dual residual (with the
rows' terms Fu^T wu lam, Fx^T wx mu and the model's A^T nu, B^T nu) and the objective
(:func:`pd_step_rows`).

A sweep reads its arrays from device memory (a tile's rows are megabytes; they do not stay in
the cache between sweeps while a hundred tiles run at once), so a kernel sweeps as few times
as it can. The step length and the barrier weight are known only at a sweep's end, so the
sweep sums what depends on them as polynomials: the complementarity after the step,
c0 + alpha c1 + alpha^2 c2, and the right-hand side, G0 + kappa G1 + alpha G2 (the targets
kappa - alpha dv dy are affine in both), evaluated once they are known. The update needs the
step length at every row: the corrector's kernel sweeps a second time for it, reading the
rows but not Fx (the row products it wrote in the first sweep), and writes the new iterate
into the old one's buffers. Where the solve carries the Newton system
(``kernel="pallas-carried"``, the default on a CUDA GPU), that second sweep also forms the
next iteration's blocks and right-hand side at the new iterate, reading Fx again, and the next
iteration starts without :func:`pd_blocks` (:attr:`rvdjax.solver.primal_dual.PDState.system`).
Otherwise the kernels compute the expressions of
:mod:`rvdjax.solver.primal_dual`; the results agree with XLA's form to rounding (tests).

Inputs are batch-last and flattened a stage, ``[stage][entry][problem]``; see :func:`pd_rows`.
The kernels read and write them entry by entry, the input rows and then the soft rows one at a
time in loops inside each stage (``kernel="pallas-rows"``, ``"pallas-entries"`` and
``"pallas-carried"``, the default on a CUDA GPU), or a stage's block at a time, every row at once
(``"pallas-block-rows"``): the same arithmetic. A block is split into lane vectors and joined
back through shared memory with a barrier each: assembled by ptxas for an H100, the three
kernels of thesis-vbar's engine held about 1 200 barriers that way, and the step's kernel fell
to 32 registers with 22 KB of spill stores; a stage's 12 rows unrolled entry by entry still
spilled 2-8 KB a kernel. One row at a time, the three hold no barrier and spill nothing
(``sweeps/gpu_registers.py``, docs/benchmark.md). With the input rows one at a time too, the
kernels between and after the solves need 151 and 168 registers instead of 198 and 244 in
thesis-vbar's engine (154 and 168 instead of 218 and 242-254 with 65 536 fastmpc-3d QPs): a
multiprocessor then holds three of their programs instead of two.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from rvdjax.solver import lanes
from rvdjax.solver.lanes import (
    _add,
    _Block,
    _compiler_params,
    _dot,
    _Entries,
    _Gathered,
    _load,
    _mtm,
    _mtv,
    _mv,
    _pad,
    _store,
    _tri,
    tri_size,
)

__all__ = ["SigmaRule", "pd_rows", "pd_step_rows", "pd_blocks", "batched", "drift_batched"]


@dataclasses.dataclass(frozen=True)
class SigmaRule:
    """Mehrotra's centring rule of :func:`rvdjax.solver.primal_dual.pd_iteration` (static):
    sigma = (gap_a / gap)^3, at least ``floor`` while the relative dual residual exceeds
    ``floor_res``."""

    floor: float
    floor_res: float


class _Shared:
    """A kernel input that the batch shares (no problem axis: ``[stage][entry]``, as one
    block): its entries load as scalars, which broadcast over the lanes, instead of from a
    copy for every problem."""

    def __init__(self, ref):
        self.ref = ref


def _scalars(refs):
    """The lane vectors of (1, 1) inputs, one number a problem each."""
    return [_load(r, 0, 1)[0] for r in refs]


def _load_any(ref, t, n):
    """Stage t's n entries of a per-problem ref (lane vectors) or of a :class:`_Shared`
    one (scalars)."""
    if isinstance(ref, _Shared):
        return [ref.ref[t, i] for i in range(n)]
    return _load(ref, t, n)


class StageRows:
    """Stage t's rows of one tile (lists of lane vectors): refs Fx, Fu, s, g, mu, pi, wx, rho,
    su, lam, wu (the first 11 of a kernel's inputs), and sx = s - g, a = mu / sx, c = pi / s,
    Du = wu lam / su. Fu, wx and rho may be read from tables at each lane's index
    (:class:`rvdjax.solver.lanes._Gathered`); the table's input rows are those before the
    problem's mask neutralises them, so the rows whose mask wu is off are zeroed here, as
    ``barrier.rows_of`` zeroes them."""

    def __init__(self, dims, refs, t, part=None):
        """``part``: None (every row), "inputs" (the input rows alone), ("input", i) (input
        row i alone, ``i`` traced) or a soft row's index (traced; that row alone); a row alone
        from refs read entry by entry."""
        mx, mu, nx, nu = dims
        (Fx_r, Fu_r, s_r, g_r, mu_r, pi_r, wx_r, rho_r, su_r, lam_r, wu_r) = refs[:11]
        self.Fx, self.s, self.g, self.mu, self.pi, self.wx, self.rho = ([],) * 7
        self.Fu, self.su, self.lam, self.wu = ([],) * 4
        if isinstance(part, tuple):
            i = part[1]
            self.Fu = [_row_entries(Fu_r, t, i, nu)]
            self.su, self.lam, self.wu = (_row_entries(r, t, i, 1) for r in (su_r, lam_r, wu_r))
        elif part is None:
            self.Fx = _load(Fx_r, t, mx, nx)
            self.s, self.g, self.mu, self.pi = (_load(r, t, mx) for r in (s_r, g_r, mu_r, pi_r))
            self.wx, self.rho = _load(wx_r, t, mx), _load(rho_r, t, mx)
        elif not isinstance(part, str):
            self.Fx = [_row_entries(Fx_r, t, part, nx)]
            self.s, self.g, self.mu, self.pi, self.wx, self.rho = (
                _row_entries(r, t, part, 1) for r in (s_r, g_r, mu_r, pi_r, wx_r, rho_r)
            )
        if part is None or part == "inputs":
            self.Fu = _load(Fu_r, t, mu, nu)
            self.su, self.lam, self.wu = (_load(r, t, mu) for r in (su_r, lam_r, wu_r))
        if isinstance(Fu_r, _Gathered):
            self.Fu = [
                [jnp.where(w > 0, v, 0.0) for v in row]
                for row, w in zip(self.Fu, self.wu, strict=True)
            ]
        self.sx = [si - gi for si, gi in zip(self.s, self.g, strict=True)]
        self.a = [mi / x for mi, x in zip(self.mu, self.sx, strict=True)]
        self.c = [pi / si for pi, si in zip(self.pi, self.s, strict=True)]
        self.Du = [w * lm / v for w, lm, v in zip(self.wu, self.lam, self.su, strict=True)]

    def h(self, tau_x, tau_s):
        """h = tau_x / sx + tau_s / s - rho (primal_dual._soft_h)."""
        return [
            tx / x + ts / s - r
            for tx, x, ts, s, r in zip(tau_x, self.sx, tau_s, self.s, self.rho, strict=True)
        ]


def _row_entries(ref, t, i, n):
    """Entries i n ... i n + n - 1 of stage t (row i of n entries, ``i`` traced) of a ref read
    entry by entry (:class:`rvdjax.solver.lanes._Entries`) or of a flattened table read at
    each lane's index (:class:`rvdjax.solver.lanes._Gathered` without blocks)."""
    if isinstance(ref, _Entries):
        return [ref.ref[t, i * n + j] for j in range(n)]
    return [ref.ref[ref.index, t, i * n + j] for j in range(n)]


class Steps:
    """The rows' steps from the row products Fu du, Fx dx and the targets
    (primal_dual._row_steps)."""

    def __init__(self, r: StageRows, Fdu, Fdx, tau_u, tau_x, tau_s, h):
        self.Fdu, self.Fdx = Fdu, Fdx
        self.ds = [(a * f + hi) / (a + c) for a, f, hi, c in zip(r.a, Fdx, h, r.c, strict=True)]
        self.dlam = [
            tu / v - lm + d * f
            for tu, v, lm, d, f in zip(tau_u, r.su, r.lam, r.Du, Fdu, strict=True)
        ]
        self.dmu = [
            tx / x - mi + a * (f - d)
            for tx, x, mi, a, f, d in zip(tau_x, r.sx, r.mu, r.a, Fdx, self.ds, strict=True)
        ]
        self.dpi = [
            ts / si - pi - c * d
            for ts, si, pi, c, d in zip(tau_s, r.s, r.pi, r.c, self.ds, strict=True)
        ]
        self.dsu = [-f for f in Fdu]
        self.dsx = [-f + d for f, d in zip(Fdx, self.ds, strict=True)]

    def pairs(self, r: StageRows):
        """(value, step, weight) of every row pair the step length keeps >= 0."""
        groups = (
            (r.su, self.dsu, r.wu),
            (r.sx, self.dsx, r.wx),
            (r.s, self.ds, r.wx),
            (r.lam, self.dlam, r.wu),
            (r.mu, self.dmu, r.wx),
            (r.pi, self.dpi, r.wx),
        )
        return [pair for group in groups for pair in zip(*group, strict=True)]

    def products(self, r: StageRows):
        """(weight, value, step, multiplier, its step) of the complementarity products."""
        return (
            (r.wu, r.su, self.dsu, r.lam, self.dlam),
            (r.wx, r.sx, self.dsx, r.mu, self.dmu),
            (r.wx, r.s, self.ds, r.pi, self.dpi),
        )


def _affine(dims, r: StageRows, Fdu, Fdx):
    """The predictor's (affine) steps: zero targets, h = 0 / sx + 0 / s - rho."""
    zu, zx = [0.0] * dims[1], [0.0] * dims[0]
    return Steps(r, Fdu, Fdx, zu, zx, zx, r.h(zx, zx))


def _corrector(dims, r: StageRows, aff: Steps, Fdu, Fdx, alpha_a, kappa):
    """The corrector's steps: targets kappa - alpha_a dv dy (primal_dual._targets)."""
    tau_u = [kappa - alpha_a * a * b for a, b in zip(aff.dsu, aff.dlam, strict=True)]
    tau_x = [kappa - alpha_a * a * b for a, b in zip(aff.dsx, aff.dmu, strict=True)]
    tau_s = [kappa - alpha_a * a * b for a, b in zip(aff.ds, aff.dpi, strict=True)]
    return Steps(r, Fdu, Fdx, tau_u, tau_x, tau_s, r.h(tau_x, tau_s))


def _sum_products(products, c0, c1, c2):
    """c0, c1, c2 of sum w (v + alpha dv)(y + alpha dy) = c0 + alpha c1 + alpha^2 c2."""
    for group in products:
        for w, v, dv, y, dy in zip(*group, strict=True):
            c0 = c0 + w * v * y
            c1 = c1 + w * (v * dy + y * dv)
            c2 = c2 + w * dv * dy
    return c0, c1, c2


def _min_ratio(pairs, alpha, nan_if_not_finite=False):
    """``alpha`` lowered to every ratio -v / dv of an active row whose step shrinks it, NaN
    where a step is not finite with ``nan_if_not_finite`` (primal_dual._max_step)."""
    for v, dv, w in pairs:
        shrink = (w > 0) & (dv < 0)
        ratio = jnp.where(shrink, -v / jnp.where(shrink, dv, -1.0), jnp.inf)
        if nan_if_not_finite:
            ratio = ratio + 0.0 * dv
        alpha = jnp.minimum(alpha, ratio)
    return alpha


def _input_terms(rows: StageRows, r: Steps):
    """The input rows' parts of the corrector's right-hand side (primal_dual._pd_rhs):
    w tau_u / su = kappa u1 + alpha u2, u1 = w / su, u2 = -w P_u / su, P_u = dsu dlam."""
    u1 = [w / v for w, v in zip(rows.wu, rows.su, strict=True)]
    u2 = [-(w * (a * b)) / v for w, a, b, v in zip(rows.wu, r.dsu, r.dlam, rows.su, strict=True)]
    return u1, u2


def _soft_terms(rows: StageRows, r: Steps):
    """The soft rows' parts x0 + kappa x1 + alpha x2 of w (tau_x / sx - q h),
    q = a / (a + c), h = tau_x / sx + tau_s / s - rho (primal_dual._pd_rhs)."""
    x0, x1, x2 = [], [], []
    for w, sx, s, a, c, rho, dsx, dmu, ds, dpi in zip(
        rows.wx,
        rows.sx,
        rows.s,
        rows.a,
        rows.c,
        rows.rho,
        r.dsx,
        r.dmu,
        r.ds,
        r.dpi,
        strict=True,
    ):
        q = a / (a + c)
        px, ps = (dsx * dmu) / sx, (ds * dpi) / s
        x0.append(w * (q * rho))
        x1.append(w * (1.0 / sx - q * (1.0 / sx + 1.0 / s)))
        x2.append(-(w * (px - q * (px + ps))))
    return x0, x1, x2


def _rows_kernel(dims, N, rule: SigmaRule, *refs):
    """One program: the sweeps for a tile of problems (module docstring).

    refs: Fx, Fu, s, g, mu, pi, wx, rho, su, lam, wu, dx, du, base_x, base_u, the scalars
    gap, res, m_eff (1, 1) each; outputs G_u (N, 3, nu), G_x (N, 3, nx), Fdu, Fdx,
    alpha_a (1, 1), kappa (1, 1), g_u (N, nu), g_x (N, nx).

    The step length and the barrier weight are known only after the first sweep, so it forms
    what needs them as polynomials in them: the complementarity after the step,
    c0 + alpha c1 + alpha^2 c2, and the right-hand side, G0 + kappa G1 + alpha G2 (the
    corrector's targets kappa - alpha dv dy are affine in both; primal_dual._pd_rhs). A
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
        read entry by entry), as the step's kernel does (:func:`_step_kernel`)."""
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


def _hessian_block(W, F, d):
    """2 W + F^T diag(d) F (primal_dual._newton_blocks), F's rows summed in order."""
    scaled = [[dk * f for f in row] for dk, row in zip(d, F, strict=True)]
    return _add([[2.0 * w for w in row] for row in W], _mtm(F, scaled))


def _soft_parts(wx, rho, s, g, mu, pi):
    """The soft rows' weights in the predictor's Newton system at (s, g, mu, pi): d of
    Phi_x = 2 Q + Fx^T diag(d) Fx and v of g_x = base_x + Fx^T v (primal_dual._pd_rhs with
    zero targets, h = 0 / sx + 0 / s - rho), formed as :class:`StageRows` forms a, c, h."""
    d, v = [], []
    for w, r, si, gi, m, p in zip(wx, rho, s, g, mu, pi, strict=True):
        sx = si - gi
        a, c = m / sx, p / si
        h = 0.0 / sx + 0.0 / si - r
        d.append(w * a * c / (a + c))
        v.append(w * (0.0 / sx - a * h / (a + c)))
    return d, v


def _residual(M, nu, x, x_prev, u, c):
    """The dynamics' residual x_t - A_t x_{t-1} - B_t u_t - c_t (barrier.dyn_residual) of a
    stage, M = [B_t, A_t]."""
    Ax, Bu = _mv([row[nu:] for row in M], x_prev), _mv([row[:nu] for row in M], u)
    return [((xi - a) - b) - ci for xi, a, b, ci in zip(x, Ax, Bu, c, strict=True)]


def _pairs(n):
    """(j, k) of a symmetric n x n matrix's lower triangle, in :func:`lanes._tri`'s order."""
    return [(j, k) for j in range(n) for k in range(j + 1)]


def _twice_plus(W, sums):
    """The lower triangle of 2 W + S from S's (``sums``, :func:`_pairs`' order): a Newton
    block from its rows' sum F^T diag(d) F."""
    return [2.0 * W[j][k] + p for p, (j, k) in zip(sums, _pairs(len(W)), strict=True)]


def _step_kernel(dims, N, system, *refs):
    """One program of :func:`pd_step_rows`: two sweeps for a tile of problems.

    refs: Fx, Fu, s, g, mu, pi, wx, rho, su, lam, wu, the corrector's step dx, du, nu, the
    predictor's row products Fdx_a, Fdu_a, the iterate's u, x, nu, the cost blocks Q, R, the
    model [B, A], the linear costs q, r, the reference x_ref (these three per problem or
    :class:`_Shared`), with ``system`` the dynamics' offset c (the same) and the initial
    state x0 (1, nx), the scalars alpha_a, kappa, fraction (1, 1) each; outputs U (N, 2, nu),
    X (N, 2, nx), Fdu, Fdx, the new u, x, nu, s, lam, mu, pi, su, g, with ``system`` the
    next iteration's Newton system at the new point (:func:`pd_blocks`'s six outputs), and
    (alpha, gap, relative dual residual, objective, finite).

    The first sweep forms the row products and the ratio test; the step length is known only
    after it, so it writes the dual residual's row terms F^T w (y + alpha dy) as two vectors a
    stage (U, X) and sums the complementarity as c0 + alpha c1 + alpha^2 c2. The step length
    is NaN where any entry of the step (du, dx, nu) or of the rows' steps is not finite: the
    one test of the step that the update needs. The second sweep takes the step
    (primal_dual._updated): from the row products the first one wrote, it forms the rows'
    steps again and writes the new iterate, and forms the stopping test there
    (primal_dual._stopping_terms): the cost gradient, the dual residual with the row terms
    U0 + alpha U1, X0 + alpha X1, the soft rows' largest |wx (rho - mu - pi)| and the
    objective. The state rows' residual r_x,t = ... - A_{t+1}^T nu_{t+1} needs the next
    stage's multipliers: the sweep carries it one stage and ends it there. On a GPU that
    replaced XLA's passes over the rows, the steps, the iterate and the model after the kernel
    (docs/benchmark.md).

    With ``system`` the second sweep also forms the Newton system of the next iteration at
    the new point, as :func:`_blocks_kernel` would from the stored iterate (the same
    arithmetic; the dynamics' residual carries the previous stage's new state): the next
    iteration starts with the factorisation, without the blocks' kernel and its reads of the
    rows and the iterate. That sweep reads every row's constraint matrix anyway, so it also
    forms the corrector's row products Fu du, Fx dx again (the first sweep's operations, the
    same numbers) and the rows' terms of the dual residual at the new point, Fu^T wu lam and
    Fx^T wx mu (as primal_dual._stopping_terms forms them), instead of the first sweep writing
    the products and the terms' two parts (U, X) for it to read back (docs/benchmark.md);
    U, X, Fdu and Fdx are then (1, 1) placeholders."""
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
    # primal_dual._updated: ``fraction`` of the way to the boundary, at most 1; zero where the
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
        """The stopping test (primal_dual._stopping_terms) at the new point u_n, x_n, nu_n
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
        the order of :func:`_blocks_kernel`'s."""
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


def _blocks_kernel(dims, N, *refs):
    """One program of :func:`pd_blocks`: the sweep for a tile of problems.

    refs: Fx, Fu, s, g, mu, pi, wx, rho, su, lam, wu, the iterate's u, x, the cost blocks Q,
    R, the model [B, A], the linear costs q, r, the reference x_ref and the dynamics' offset c
    (these four per problem or :class:`_Shared`), the initial state x0 (1, nx); outputs
    Phi_u (N, tri(nu)), Phi_x (N, tri(nx)) (lower triangles, :func:`lanes.tri_pack`'s order),
    g_x (N, nx), the cost's gradient base_u (N, nu), base_x (N, nx) and the dynamics'
    residual rp (N, nx). The residual at stage t needs the
    previous stage's state: a second sweep forms it, carrying the state (it reads u, x and the
    model again, 3 KB a thesis-vbar problem)."""
    mx, mu, nx, nu = dims
    row_refs = refs[:11]
    u_r, x_r, Q_r, R_r, M_r, q_r, r_r, xref_r, c_r, x0_r = refs[11:21]
    Pu_out, Px_out, gx_out, bu_out, bx_out, rp_out = refs[21:]

    def soft_parts(rows):  # the soft rows' weights: d of Phi_x, v of g_x = base_x + Fx^T v
        return _soft_parts(rows.wx, rows.rho, rows.s, rows.g, rows.mu, rows.pi)

    def cost(t, Q, R):  # the cost's gradient (primal_dual._cost_gradient)
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
        entry), as the step's kernel does (:func:`_step_kernel`): F^T diag(d) F (its lower
        triangle) and F^T v summed row by row in the order of
        :func:`rvdjax.solver.lanes._mtm`. The input rows stay unrolled: in a loop of their own
        they took the kernel from 168 to 204 registers with 65 536 QPs of a model each (the
        cost block R then lives through the loop; ptxas for sm_90a)."""
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


def _launch(body, name, ins, outs, interpret, tables=None, aliases=None, shared=(), block_io=True):
    """A kernel over tiles of problems: ``ins`` batch-last (N, ..., b) arrays, flattened a
    stage; ``outs`` the (N, entries) of each output; returns them (N, entries, b).
    ``tables``: (index (b,), {position: table (K, N, ...)}): the inputs at those positions
    are read from the tables at each problem's index instead (their ``ins`` are not used).
    ``aliases``: {input position: output position} written in the input's buffer (the kernel
    reads each stage of such an input before it writes that stage of the output).
    ``shared``: positions of inputs that may come without the problem axis, shared by the
    batch (:class:`_Shared`): those given with one dimension less than the problem's (N, e).
    ``block_io``: the per-problem arrays and the tables read and written a stage's block at
    a time (:class:`rvdjax.solver.lanes._Block`), else entry by entry
    (:class:`rvdjax.solver.lanes._Entries`)."""
    from jax.experimental import pallas as pl

    b = ins[0].shape[-1]
    shared = {i for i in shared if ins[i].ndim == 2}
    cfg = dataclasses.replace(lanes.default_config(), interpret=interpret)
    L, b_pad = lanes.tile(b, cfg.block)
    index, by_pos = tables if tables is not None else (None, {})
    ins = [
        by_pos[i].reshape(*by_pos[i].shape[:2], -1)
        if i in by_pos
        else a.reshape(a.shape[0], -1)
        if i in shared
        else _pad(a.reshape(a.shape[0], -1, b), b_pad)
        for i, a in enumerate(ins)
    ]
    out_shape = [jax.ShapeDtypeStruct((*o, b_pad), ins[0].dtype) for o in outs]

    def spec(shape, batched=True):
        n = len(shape)
        if not batched:
            return pl.BlockSpec(tuple(shape), lambda i: (0,) * n)
        return pl.BlockSpec((*shape[:-1], L), lambda i: (0,) * (n - 1) + (i,))

    specs = [spec(a.shape, i not in by_pos and i not in shared) for i, a in enumerate(ins)]
    if index is not None:  # the tile's indices, the last input
        ins, specs = [*ins, _pad(index.astype(jnp.int32), b_pad)], [*specs, spec((b_pad,))]

    def kernel(*refs):
        lane_index = None
        if index is not None:  # the last input: the tile's indices
            n = len(ins) - 1
            lane_index, refs = refs[n][...], refs[:n] + refs[n + 1 :]
        refs = [
            _Gathered(r, lane_index, block_io)
            if i in by_pos
            else _Shared(r)
            if i in shared
            else _Block(r)
            if block_io
            else _Entries(r)
            for i, r in enumerate(refs)
        ]
        return body(*refs)

    out = pl.pallas_call(
        kernel,
        out_shape=out_shape,
        grid=(b_pad // L,),
        in_specs=specs,
        out_specs=[spec(o.shape) for o in out_shape],
        interpret=interpret,
        compiler_params=_compiler_params(cfg),
        name=name,
        input_output_aliases=dict(aliases or {}),
    )(*ins)
    return [o[..., :b] for o in out]


def pd_rows(
    rows,
    dx,
    du,
    base_x,
    base_u,
    scalars,
    rule: SigmaRule,
    interpret: bool = False,
    tables=None,
    block_io: bool = True,
):
    """The corrector's right-hand side from the predictor's step, for a batch.

    Args (batch last, b problems): ``rows`` = (Fx (N, mx, nx, b), Fu (N, mu, nu, b), the soft
    rows' slack s, values g = Fx x - fx, multipliers mu, pi, mask wx and penalty rho
    (N, mx, b), the input rows' slack su = fu - Fu u, multiplier lam and mask wu (N, mu, b));
    the predictor's step dx (N, nx, b), du (N, nu, b); the cost gradients base_x (N, nx, b),
    base_u (N, nu, b); scalars: three (b,) arrays, the complementarity gap, the relative
    dual residual and the number of barrier terms; ``rule`` the :class:`SigmaRule`.

    Returns:
        g_u (N, nu, b), g_x (N, nx, b) the corrector's right-hand side, Fdu (N, mu, b) and
        Fdx (N, mx, b) the predictor's row products, alpha_a (b,) its step length and kappa
        (b,) the corrector's barrier weight.

    ``tables``: None, or (index (b,), Fu (K, N, mu, nu), wx (K, N, mx), rho (K, N, mx)):
    the kernel reads Fu (then zeroed where wu is off), wx and rho from the tables at each
    problem's index instead of from ``rows``. ``block_io``: as :func:`_launch`.
    """
    N, mx, nx, b = rows[0].shape
    mu, nu = rows[10].shape[1], du.shape[1]
    dims = (mx, mu, nx, nu)
    # alpha_a and kappa as outputs of their own: the step's kernel reads them as they are
    _, _, Fdu, Fdx, alpha, kappa, g_u, g_x = _launch(
        functools.partial(_rows_kernel, dims, N, rule),
        "rvdjax_pd_rows",
        [*rows, dx, du, base_x, base_u, *(a[None, None] for a in scalars)],
        [(N, 3 * nu), (N, 3 * nx), (N, mu), (N, mx), (1, 1), (1, 1), (N, nu), (N, nx)],
        interpret,
        _tables("rows", tables),
        block_io=block_io,
    )
    return g_u, g_x, Fdu, Fdx, alpha[0, 0], kappa[0, 0]


#: The inputs that tables can stand for, by kernel, in the order :func:`batched` takes the
#: tables: the rows' Fu, wx, rho, and the cost blocks Q, R and the model [B, A] of
#: :func:`pd_blocks` and :func:`pd_step_rows`.
_TABLE_POSITIONS = {
    "rows": (1, 6, 7),
    "blocks": (1, 6, 7, 13, 14, 15),
    "step": (1, 6, 7, 19, 20, 21),
    "step_system": (1, 6, 7, 19, 20, 21),
}

#: The inputs read as a table of one (index 0) when a batch shares them (unbatched under
#: ``vmap``) and no tables are given: not a copy for every problem.
_SHAREABLE = {"rows": (), "blocks": (13, 14, 15), "step": (19, 20, 21)}
_SHAREABLE["step_system"] = _SHAREABLE["step"]

#: The inputs read as :class:`_Shared` when a batch shares them, with tables or without:
#: the linear costs q, r, the reference x_ref and the dynamics' offset c (the batch engine's
#: zero linear costs and offsets).
_SHARED = {"rows": (), "blocks": (16, 17, 18, 19), "step": (22, 23, 24)}
_SHARED["step_system"] = (22, 23, 24, 25)  # and the dynamics' offset c


def _tables(kind, tables):
    """_launch's tables from (index, Fu, wx, rho[, ...]) in :data:`_TABLE_POSITIONS`'s order,
    those given (not None)."""
    if tables is None:
        return None
    index, *ts = tables
    positions = _TABLE_POSITIONS[kind]
    return index, {p: t for p, t in zip(positions, ts, strict=False) if t is not None}


def pd_step_rows(
    rows,
    dx,
    du,
    nu_new,
    Fdx_a,
    Fdu_a,
    u,
    x,
    nu,
    cost,
    scalars,
    interpret: bool = False,
    tables=None,
    block_io: bool = True,
    system=None,
):
    """The corrector's step taken, for a batch: its row products, its step length (zero where
    the step or a row's step is not finite, or the solve is stopped), the new iterate, the
    complementarity there and the stopping test's relative dual residual and objective there.

    Args (batch last, b problems): ``rows`` as :func:`pd_rows`; the corrector's step
    dx (N, nx, b), du (N, nu, b) and new multipliers nu_new (N, nx, b); the predictor's row
    products Fdx_a (N, mx, b), Fdu_a (N, mu, b); the iterate's u (N, nu, b), x (N, nx, b) and
    nu (N, nx, b); ``cost`` = (Q (N, nx, nx, b), R (N, nu, nu, b), the model [B, A]
    (N, nx, nu + nx, b), q (N, nx, b), r (N, nu, b), x_ref (N, nx, b)): the cost and the
    model (:class:`rvdjax.ocp.OCP`'s), q, r and x_ref without the problem axis where the
    batch shares them; scalars: three (b,) arrays, the predictor's step length alpha_a, the
    corrector's barrier weight kappa (its targets are kappa - alpha_a dv dy of the predictor's
    steps) and the fraction of the way to the boundary that the step goes
    (primal_dual.step_fraction; 0 where the solve is stopped).

    Returns:
        new: the new u, x, nu, s, lam, mu, pi, su, g (as the inputs);
        sc (4, b): the step length taken alpha (``fraction`` of the way to the boundary, at most 1;
        NaN in no case: whether the step was finite is ``finite``), the complementarity at the
        new point, the relative dual residual and the objective there
        (primal_dual._stopping_terms);
        finite (b,) bool: whether every entry of the step and of the rows' steps is finite.

    ``tables``: None, or (index (b,), Fu, wx, rho, Q, R, [B, A]), each table (K, N, ...) or
    None: the kernel reads those given from the tables at each problem's index.
    ``block_io``: as :func:`_launch`. ``system``: None, or (c (N, nx, b), x0 (1, nx, b)), the
    dynamics' offset (without the problem axis where the batch shares it) and the initial
    state: the kernel also forms the next iteration's Newton system at the new point, and
    returns it fourth, as :func:`pd_blocks` returns it.
    """
    N, mx, nx, b = rows[0].shape
    mu, n_u = rows[10].shape[1], du.shape[1]
    dims = (mx, mu, nx, n_u)
    extra, sys_shapes = (), []
    if system is not None:
        extra = tuple(system)
        sys_shapes = [(N, tri_size(n_u)), (N, tri_size(nx)), (N, nx), (N, n_u), (N, nx), (N, nx)]
    kind = "step" if system is None else "step_system"
    _, _, _, _, *out, sc = _launch(
        functools.partial(_step_kernel, dims, N, system is not None),
        "rvdjax_pd_step_rows" if system is None else "rvdjax_pd_step_system",
        [*rows, dx, du, nu_new, Fdx_a, Fdu_a, u, x, nu, *cost, *extra]
        + [a[None, None] for a in scalars],
        # the first sweep's row products and row terms, read back by the second; forming the
        # system, the second sweep forms them again from the rows it reads anyway (placeholders)
        ([(N, 2 * n_u), (N, 2 * nx), (N, mu), (N, mx)] if system is None else [(1, 1)] * 4)
        + [(N, n_u), (N, nx), (N, nx), (N, mx), (N, mu), (N, mx), (N, mx), (N, mu), (N, mx)]
        + sys_shapes
        + [(1, 5)],
        interpret,
        _tables(kind, tables),
        # the new iterate in the old one's buffers: otherwise XLA copies each new array into
        # the solver loop's carry (counted for an H100: 8 copies an iteration, 35 KB a
        # thesis-vbar slot read and written)
        {16: 4, 17: 5, 18: 6, 2: 7, 9: 8, 4: 9, 5: 10, 8: 11, 3: 12},
        _SHARED[kind],
        block_io,
    )
    new, next_system, sc = tuple(out[:9]), tuple(out[9:]), sc[0]
    if system is None:
        return new, sc[:4], sc[4] > 0
    return new, sc[:4], sc[4] > 0, next_system


def pd_blocks(rows, u, x, cost, x0, interpret: bool = False, tables=None, block_io: bool = True):
    """The predictor's Newton system, for a batch: the Hessian blocks Phi_u = 2 R + Fu^T Du Fu
    and Phi_x = 2 Q + Fx^T diag(wx a c / (a + c)) Fx, the cost's gradient base_u = 2 R u + r,
    base_x = 2 Q (x - x_ref) + q, the state part of the right-hand side
    g_x = base_x + Fx^T (wx a rho / (a + c)) (the input part is base_u itself: the input rows'
    targets are zero) and the dynamics' residual rp = x_t - A_t x_{t-1} - B_t u_t - c_t, from
    the rows in one sweep that reads Fx once (XLA: in three passes, two of them reading Fx;
    primal_dual.pd_iteration), the residual in a second sweep of the same kernel.

    Args (batch last, b problems): ``rows`` as :func:`pd_rows`; the iterate's u (N, nu, b),
    x (N, nx, b); ``cost`` = (Q (N, nx, nx, b), R (N, nu, nu, b), the model [B, A]
    (N, nx, nu + nx, b), q (N, nx, b), r (N, nu, b), x_ref (N, nx, b), c (N, nx, b)), the
    last four without the problem axis where the batch shares them; x0 (1, nx, b).

    Returns:
        Phi_u (N, tri(nu), b), Phi_x (N, tri(nx), b) as their lower triangles
        (:func:`rvdjax.solver.lanes.tri_pack`; the Riccati kernels read them so),
        g_x (N, nx, b), base_u (N, nu, b), base_x (N, nx, b), rp (N, nx, b).

    ``tables``: None, or (index (b,), Fu, wx, rho, Q, R, [B, A]) with each table (K, N, ...)
    or None: the kernel reads those given from the tables at each problem's index.
    ``block_io``: as :func:`_launch`.
    """
    N, mx, nx, b = rows[0].shape
    mu, nu = rows[10].shape[1], u.shape[1]
    dims = (mx, mu, nx, nu)
    Pu, Px, g_x, base_u, base_x, rp = _launch(
        functools.partial(_blocks_kernel, dims, N),
        "rvdjax_pd_blocks",
        [*rows, u, x, *cost, x0],
        [(N, tri_size(nu)), (N, tri_size(nx)), (N, nx), (N, nu), (N, nx), (N, nx)],
        interpret,
        _tables("blocks", tables),
        shared=_SHARED["blocks"],
        block_io=block_io,
    )
    return Pu, Px, g_x, base_u, base_x, rp


@functools.cache
def batched(
    kind: str,
    n_scalars: int,
    rule: SigmaRule | None,
    interpret: bool,
    tabled: bool = False,
    block_io: bool = True,
):
    """:func:`pd_rows` (``kind`` "rows"), :func:`pd_step_rows` ("step"; "step_system" with
    its ``system``, the dynamics' offset c and the initial state x0 (1, nx) after the cost)
    or :func:`pd_blocks` ("blocks") for one problem (arrays without the batch axis; a batch
    of one), and under ``vmap`` for the batch (``jax.custom_batching.custom_vmap``);
    unbatched inputs are broadcast. The arguments are the 11 row arrays, the kernel's other
    arrays, then
    ``n_scalars`` scalars a problem, then (``tabled``) the tables of
    :data:`_TABLE_POSITIONS` (Fu, wx, rho; and Q, R for "blocks"; Q, R, A, B for "step") and
    the problem's index, which the kernel reads instead of those arrays where the tables are
    shared and the index batched (:class:`rvdjax.solver.riccati.ModelTable`). Without tables,
    the kernels read the cost blocks and the model of :data:`_SHAREABLE` that a batch shares
    as a table of one, not as a copy for every problem. ``block_io``: as :func:`_launch`."""
    n_tables = len(_TABLE_POSITIONS[kind]) + 1 if tabled else 0

    def run(args, tables=None):
        rows, rest = args[:11], args[11 : len(args) - n_scalars]
        scalars = args[len(args) - n_scalars :]
        if kind == "blocks":
            out = pd_blocks(rows, *rest[:2], rest[2:-1], rest[-1], interpret, tables, block_io)
        elif kind == "rows":
            out = pd_rows(rows, *rest, scalars, rule, interpret, tables, block_io)
        elif kind == "step":
            out = pd_step_rows(rows, *rest[:8], rest[8:], scalars, interpret, tables, block_io)
        else:
            cost, system = rest[8:14], rest[14:]
            out = pd_step_rows(rows, *rest[:8], cost, scalars, interpret, tables, block_io, system)
        return jax.tree.map(lambda a: jnp.moveaxis(a, -1, 0), out)

    @jax.custom_batching.custom_vmap
    def fn(*args):
        args = args[: len(args) - n_tables]
        return jax.tree.map(lambda a: a[0], run([a[..., None] for a in args]))

    @fn.def_vmap
    def rule_(axis_size, in_batched, *args):
        n = len(args) - n_tables
        tables = None
        if tabled and not any(in_batched[n:-1]) and in_batched[-1]:
            *ts, index = args[n:]
            tables = (index, *ts)
        elif any(not in_batched[p] for p in _SHAREABLE[kind]):
            one = jnp.zeros((axis_size,), jnp.int32)
            tables = (one,) + tuple(
                None if p not in _SHAREABLE[kind] or in_batched[p] else args[p][None]
                for p in _TABLE_POSITIONS[kind]
            )
        full = [
            a
            if not bt and i in _SHARED[kind]
            else jnp.moveaxis(a if bt else jnp.broadcast_to(a, (axis_size, *a.shape)), 0, -1)
            for i, (a, bt) in enumerate(zip(args[:n], in_batched[:n], strict=True))
        ]
        out = run(full, tables)
        return out, jax.tree.map(lambda _: True, out)

    return fn


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
