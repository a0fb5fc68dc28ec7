"""The accurate mode's row work between its two Newton solves as one GPU kernel.

Between the predictor's solve and the corrector's, a Mehrotra iteration
(:func:`rvdjax.solver.primal_dual.pd_iteration`) works on the constraint rows only: the
predictor's row steps (F du, F dx and the slack and multiplier steps that follow), its step
length (a ratio test over every row), the complementarity after that step, Mehrotra's sigma
and the corrector's targets, and from them the corrector's right-hand side F^T (...). On a GPU
XLA made that about eight passes through device memory, reading the rows, their multipliers
and the constraint matrix Fx again in most of them (thesis-vbar: 12 soft rows a stage, Fx
17 KB a problem; docs/benchmark.md). Here it is one Pallas kernel (Triton on a GPU,
interpreted on the CPU for the tests), one problem per lane as in :mod:`rvdjax.solver.lanes`,
in one sweep over the stages that reads each stage's rows once.

One sweep, because a kernel that sweeps again reads its arrays again from device memory (a
tile's rows are megabytes; they do not stay in the cache between sweeps while a hundred tiles
run at once). The step length and the barrier weight are known only at the sweep's end, so
the sweep sums what depends on them as polynomials: the complementarity after the step,
c0 + alpha c1 + alpha^2 c2, and the right-hand side, G0 + kappa G1 + alpha G2 (the targets
kappa - alpha dv dy are affine in both), evaluated once they are known. Otherwise it computes
the expressions of :mod:`rvdjax.solver.primal_dual`; the results agree with XLA's form to
rounding (tests).

Inputs are batch-last and flattened a stage, ``[stage][entry][problem]``; see
:func:`pd_rows`.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from rvdjax.solver import lanes
from rvdjax.solver.lanes import _Block, _compiler_params, _load, _mtv, _mv, _pad, _store

__all__ = ["RowSteps", "pd_rows", "SigmaRule"]


@dataclasses.dataclass(frozen=True)
class SigmaRule:
    """Mehrotra's centring rule of :func:`rvdjax.solver.primal_dual.pd_iteration` (static):
    sigma = (gap_a / gap)^3, at least ``floor`` while the relative dual residual exceeds
    ``floor_res``."""

    floor: float
    floor_res: float


class RowSteps:
    """The stage-t predictor row steps of one tile (lists of lane vectors)."""

    def __init__(self, dims, refs, t):
        mx, mu, nx, nu = dims
        (Fx_r, Fu_r, s_r, g_r, mu_r, pi_r, wx_r, rho_r, su_r, lam_r, wu_r, dx_r, du_r) = refs
        Fx, Fu = _load(Fx_r, t, mx, nx), _load(Fu_r, t, mu, nu)
        dx, du = _load(dx_r, t, nx), _load(du_r, t, nu)
        s, g, m, p = (_load(r, t, mx) for r in (s_r, g_r, mu_r, pi_r))
        self.wx, self.rho = _load(wx_r, t, mx), _load(rho_r, t, mx)
        self.su, self.lam, self.wu = (_load(r, t, mu) for r in (su_r, lam_r, wu_r))
        self.Fx, self.Fu, self.s, self.mu, self.pi = Fx, Fu, s, m, p
        self.sx = [si - gi for si, gi in zip(s, g, strict=True)]
        self.a = [mi / x for mi, x in zip(m, self.sx, strict=True)]
        self.c = [pi / si for pi, si in zip(p, s, strict=True)]
        # the predictor's targets are zero: h = 0 / sx + 0 / s - rho (primal_dual._pd_rhs)
        h = [0.0 / x + 0.0 / si - r for x, si, r in zip(self.sx, s, self.rho, strict=True)]
        self.Fdu, self.Fdx = _mv(Fu, du), _mv(Fx, dx)
        Du = [w * lm / v for w, lm, v in zip(self.wu, self.lam, self.su, strict=True)]
        self.ds = [
            (a * f + hi) / (a + c) for a, f, hi, c in zip(self.a, self.Fdx, h, self.c, strict=True)
        ]
        self.dlam = [
            0.0 / v - lm + d * f
            for v, lm, d, f in zip(self.su, self.lam, Du, self.Fdu, strict=True)
        ]
        self.dmu = [
            0.0 / x - mi + a * (f - d)
            for x, mi, a, f, d in zip(self.sx, m, self.a, self.Fdx, self.ds, strict=True)
        ]
        self.dpi = [
            0.0 / si - pi - c * d for si, pi, c, d in zip(s, p, self.c, self.ds, strict=True)
        ]
        self.dsu = [-f for f in self.Fdu]
        self.dsx = [-f + d for f, d in zip(self.Fdx, self.ds, strict=True)]

    def pairs(self):
        """(value, step, weight) of every row pair the step length keeps >= 0."""
        groups = (
            (self.su, self.dsu, self.wu),
            (self.sx, self.dsx, self.wx),
            (self.s, self.ds, self.wx),
            (self.lam, self.dlam, self.wu),
            (self.mu, self.dmu, self.wx),
            (self.pi, self.dpi, self.wx),
        )
        return [pair for group in groups for pair in zip(*group, strict=True)]


def _min_ratio(pairs, alpha):
    """``alpha`` lowered to every ratio -v / dv of an active row whose step shrinks it
    (primal_dual._max_step)."""
    for v, dv, w in pairs:
        shrink = (w > 0) & (dv < 0)
        ratio = jnp.where(shrink, -v / jnp.where(shrink, dv, -1.0), jnp.inf)
        alpha = jnp.minimum(alpha, ratio)
    return alpha


def _rows_kernel(dims, N, rule: SigmaRule, *refs):
    """One program: the sweep for a tile of problems (module docstring).

    refs: Fx, Fu, s, g, mu, pi, wx, rho, su, lam, wu, dx, du, base_x, base_u, scalars (gap,
    res, m_eff); outputs G_u (N, 3, nu), G_x (N, 3, nx), Fdu, Fdx, (alpha_a, kappa).

    The step length and the barrier weight are known only after the sweep, so the sweep forms
    what needs them as polynomials in them: the complementarity after the step,
    c0 + alpha c1 + alpha^2 c2, and the right-hand side, G0 + kappa G1 + alpha G2 (the
    corrector's targets kappa - alpha dv dy are affine in both; primal_dual._pd_rhs)."""
    mx, mu, nx, nu = dims
    row_refs = refs[:13]
    bx_r, bu_r, sc_r = refs[13:16]
    Gu_out, Gx_out, Fdu_out, Fdx_out, sc_out = refs[16:]
    gap, res, m_eff = _load(sc_r, 0, 3)

    def stage(t, carry):
        alpha, c0, c1, c2 = carry
        r = RowSteps(dims, row_refs, t)
        alpha = _min_ratio(r.pairs(), alpha)
        products = (
            (r.wu, r.su, r.dsu, r.lam, r.dlam),
            (r.wx, r.sx, r.dsx, r.mu, r.dmu),
            (r.wx, r.s, r.ds, r.pi, r.dpi),
        )
        for group in products:
            for w, v, dv, y, dy in zip(*group, strict=True):
                c0 = c0 + w * v * y
                c1 = c1 + w * (v * dy + y * dv)
                c2 = c2 + w * dv * dy
        # input rows: w tau_u / su = kappa w / su - alpha w P_u / su, P_u = dsu dlam
        u1 = [w / v for w, v in zip(r.wu, r.su, strict=True)]
        u2 = [-(w * (a * b)) / v for w, a, b, v in zip(r.wu, r.dsu, r.dlam, r.su, strict=True)]
        # soft rows: w (tau_x / sx - q h), q = a / (a + c), h = tau_x / sx + tau_s / s - rho
        x0, x1, x2 = [], [], []
        for w, sx, s, a, c, rho, dsx, dmu, ds, dpi in zip(
            r.wx, r.sx, r.s, r.a, r.c, r.rho, r.dsx, r.dmu, r.ds, r.dpi, strict=True
        ):
            q = a / (a + c)
            px, ps = (dsx * dmu) / sx, (ds * dpi) / s
            x0.append(w * (q * rho))
            x1.append(w * (1.0 / sx - q * (1.0 / sx + 1.0 / s)))
            x2.append(-(w * (px - q * (px + ps))))
        G_u = [_load(bu_r, t, nu), _mtv(r.Fu, u1), _mtv(r.Fu, u2)]
        G_x = [[b + v for b, v in zip(_load(bx_r, t, nx), _mtv(r.Fx, x0), strict=True)]]
        G_x += [_mtv(r.Fx, x1), _mtv(r.Fx, x2)]
        _store(Gu_out, t, G_u)
        _store(Gx_out, t, G_x)
        _store(Fdu_out, t, r.Fdu)
        _store(Fdx_out, t, r.Fdx)
        return alpha, c0, c1, c2

    zero = 0.0 * gap
    alpha, c0, c1, c2 = jax.lax.fori_loop(0, N, stage, (zero + jnp.inf, zero, zero, zero))
    alpha = jnp.minimum(1.0, alpha)
    gap_a = c0 + alpha * (c1 + alpha * c2)
    sigma = jnp.clip(gap_a / jnp.maximum(gap, 1e-300), 0.0, 1.0) ** 3
    res = jnp.where(jnp.isfinite(res), res, 0.0)
    sigma = jnp.where(res > rule.floor_res, jnp.maximum(sigma, rule.floor), sigma)
    kappa = sigma * gap / jnp.maximum(m_eff, 1.0)
    _store(sc_out, 0, [alpha, kappa])


def pd_rows(
    Fx,
    Fu,
    s,
    g,
    mu,
    pi,
    wx,
    rho,
    su,
    lam,
    wu,
    dx,
    du,
    base_x,
    base_u,
    scalars,
    rule,
    interpret: bool = False,
):
    """The corrector's right-hand side from the predictor's step, for a batch.

    Args (batch last, b problems): Fx (N, mx, nx, b), Fu (N, mu, nu, b); the soft rows' slack
    s, values g = Fx x - fx, multipliers mu, pi, mask wx and penalty rho (N, mx, b); the input
    rows' slack su = fu - Fu u, multiplier lam and mask wu (N, mu, b); the predictor's step
    dx (N, nx, b), du (N, nu, b); the cost gradients base_x (N, nx, b), base_u (N, nu, b);
    scalars (3, b): the complementarity gap, the relative dual residual and the number of
    barrier terms; ``rule`` the :class:`SigmaRule`.

    Returns:
        g_u (N, nu, b), g_x (N, nx, b) the corrector's right-hand side, Fdu (N, mu, b) and
        Fdx (N, mx, b) the predictor's row steps, alpha_a (b,) its step length and kappa (b,)
        the corrector's barrier weight.
    """
    from jax.experimental import pallas as pl

    N, mx, nx, b = Fx.shape
    mu_, nu = Fu.shape[1], Fu.shape[2]
    cfg = lanes.default_config()
    L = cfg.block
    b_pad = -(-b // L) * L
    flat = [a.reshape(N, -1, b) for a in (Fx, Fu, s, g, mu, pi, wx, rho, su, lam, wu, dx, du)]
    flat += [base_x, base_u, scalars[None]]
    ins = [_pad(a, b_pad) for a in flat]
    outs = [(N, 3 * nu), (N, 3 * nx), (N, mu_), (N, mx), (1, 2)]
    out_shape = [jax.ShapeDtypeStruct((*o, b_pad), Fx.dtype) for o in outs]

    def spec(shape):
        n = len(shape)
        return pl.BlockSpec((*shape[:-1], L), lambda i: (0,) * (n - 1) + (i,))

    def kernel(*refs):
        _rows_kernel((mx, mu_, nx, nu), N, rule, *(_Block(r) for r in refs))

    cfg = dataclasses.replace(cfg, interpret=interpret)
    G_u, G_x, Fdu, Fdx, sc = pl.pallas_call(
        kernel,
        out_shape=out_shape,
        grid=(b_pad // L,),
        in_specs=[spec(a.shape) for a in ins],
        out_specs=[spec(o.shape) for o in out_shape],
        interpret=interpret,
        compiler_params=_compiler_params(cfg),
        name="rvdjax_pd_rows",
    )(*ins)
    alpha, kappa = sc[0, 0, :b], sc[0, 1, :b]
    G_u, G_x = G_u[..., :b].reshape(N, 3, nu, b), G_x[..., :b].reshape(N, 3, nx, b)
    g_u = G_u[:, 0] + kappa * G_u[:, 1] + alpha * G_u[:, 2]
    g_x = G_x[:, 0] + kappa * G_x[:, 1] + alpha * G_x[:, 2]
    return g_u, g_x, Fdu[..., :b], Fdx[..., :b], alpha, kappa


@functools.cache
def batched(rule: SigmaRule, interpret: bool):
    """:func:`pd_rows` for one problem (arrays without the batch axis; a batch of one), and
    under ``vmap`` for the batch (``jax.custom_batching.custom_vmap``); unbatched inputs are
    broadcast."""

    def per_problem_to_last(axis_size, args, in_batched):
        return [
            jnp.moveaxis(a if bt else jnp.broadcast_to(a, (axis_size, *a.shape)), 0, -1)
            for a, bt in zip(args, in_batched, strict=True)
        ]

    def run(args):
        *rows, gap, res, m_eff = args
        scalars = jnp.stack([gap, res, m_eff])
        out = pd_rows(*rows, scalars, rule, interpret)
        return tuple(jnp.moveaxis(a, -1, 0) for a in out)

    @jax.custom_batching.custom_vmap
    def fn(*args):
        out = run([a[..., None] for a in args])
        return tuple(a[0] for a in out)

    @fn.def_vmap
    def rule_(axis_size, in_batched, *args):
        return run(per_problem_to_last(axis_size, args, in_batched)), (True,) * 6

    return fn
