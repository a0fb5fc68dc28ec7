"""A stage's rows as the row kernels read them (lists of lane vectors, one problem a lane),
the rows' steps, and the terms they add to the Newton system and its right-hand side: the
pieces the kernels of :mod:`rvdjax.solver.rows_kernel` share."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from rvdjax.solver.lanes.algebra import _add, _mtm, _mv
from rvdjax.solver.lanes.refs import _Entries, _Gathered, _load


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
    (:class:`rvdjax.solver.lanes.refs._Gathered`); the table's input rows are those before the
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
        """h = tau_x / sx + tau_s / s - rho (pd_algebra._soft_h)."""
        return [
            tx / x + ts / s - r
            for tx, x, ts, s, r in zip(tau_x, self.sx, tau_s, self.s, self.rho, strict=True)
        ]


def _row_entries(ref, t, i, n):
    """Entries i n ... i n + n - 1 of stage t (row i of n entries, ``i`` traced) of a ref read
    entry by entry (:class:`rvdjax.solver.lanes.refs._Entries`) or of a flattened table read at
    each lane's index (:class:`rvdjax.solver.lanes.refs._Gathered` without blocks)."""
    if isinstance(ref, _Entries):
        return [ref.ref[t, i * n + j] for j in range(n)]
    return [ref.ref[ref.index, t, i * n + j] for j in range(n)]


class Steps:
    """The rows' steps from the row products Fu du, Fx dx and the targets
    (pd_algebra._row_steps)."""

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
    """The corrector's steps: targets kappa - alpha_a dv dy (pd_algebra._targets)."""
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
    where a step is not finite with ``nan_if_not_finite`` (pd_algebra._max_step)."""
    for v, dv, w in pairs:
        shrink = (w > 0) & (dv < 0)
        ratio = jnp.where(shrink, -v / jnp.where(shrink, dv, -1.0), jnp.inf)
        if nan_if_not_finite:
            ratio = ratio + 0.0 * dv
        alpha = jnp.minimum(alpha, ratio)
    return alpha


def _input_terms(rows: StageRows, r: Steps):
    """The input rows' parts of the corrector's right-hand side (pd_algebra._pd_rhs):
    w tau_u / su = kappa u1 + alpha u2, u1 = w / su, u2 = -w P_u / su, P_u = dsu dlam."""
    u1 = [w / v for w, v in zip(rows.wu, rows.su, strict=True)]
    u2 = [-(w * (a * b)) / v for w, a, b, v in zip(rows.wu, r.dsu, r.dlam, rows.su, strict=True)]
    return u1, u2


def _soft_terms(rows: StageRows, r: Steps):
    """The soft rows' parts x0 + kappa x1 + alpha x2 of w (tau_x / sx - q h),
    q = a / (a + c), h = tau_x / sx + tau_s / s - rho (pd_algebra._pd_rhs)."""
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


def _hessian_block(W, F, d):
    """2 W + F^T diag(d) F (pd_algebra._newton_blocks), F's rows summed in order."""
    scaled = [[dk * f for f in row] for dk, row in zip(d, F, strict=True)]
    return _add([[2.0 * w for w in row] for row in W], _mtm(F, scaled))


def _soft_parts(wx, rho, s, g, mu, pi):
    """The soft rows' weights in the predictor's Newton system at (s, g, mu, pi): d of
    Phi_x = 2 Q + Fx^T diag(d) Fx and v of g_x = base_x + Fx^T v (pd_algebra._pd_rhs with
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
    """(j, k) of a symmetric n x n matrix's lower triangle, in :func:`lanes.refs._tri`'s order."""
    return [(j, k) for j in range(n) for k in range(j + 1)]


def _twice_plus(W, sums):
    """The lower triangle of 2 W + S from S's (``sums``, :func:`_pairs`' order): a Newton
    block from its rows' sum F^T diag(d) F."""
    return [2.0 * W[j][k] + p for p, (j, k) in zip(sums, _pairs(len(W)), strict=True)]
