"""The accurate mode's primal-dual iteration in XLA's form: its state, its start on the central
path, and its work on the inequality rows (Mehrotra predictor-corrector; Nocedal & Wright
Alg. 16.4, Wright 1997 Ch. 10).

The Newton system's blocks and right-hand sides from the rows' barrier terms, the predictor's
row steps, the corrector's targets and right-hand side, the step taken a fraction of the way to
the boundary and the stopping test's terms. :mod:`rvdjax.solver.rows_kernel` does the same
work as GPU kernels in fewer passes over the rows (:mod:`rvdjax.solver.pd_kernels` calls
them); :func:`rvdjax.solver.primal_dual.pd_iteration` puts the parts together.

Soft state rows carry an explicit slack s >= 0 (Fx x - s <= fx, cost rho s), with multipliers
mu (of the row) and pi (of s >= 0); mu + pi = rho at the optimum.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from rvdjax.solver import stagewise as sw
from rvdjax.solver.barrier import (
    all_finite,
    dual_residual,
    dyn_residual,
    soft_slack,
    u_slack,
    x_violation,
)
from rvdjax.solver.lanes import tri_pack
from rvdjax.solver.riccati import SymStored

__all__ = ["PDState", "pd_start", "step_fraction"]

# sigma >= SIGMA_FLOOR while the relative dual residual exceeds SIGMA_FLOOR_RES (chosen on the
# closed loops of paper 003: 0.2 / 0.3 / 0.5 gave 29.5 / 24.8 / 22.0 iterations per solve on
# thesis-vbar-lp and 12.3 / 12.6 / 14.4 on thesis-vbar; docs/solver.md).
SIGMA_FLOOR = 0.3
SIGMA_FLOOR_RES = 10.0

# The corrector's step goes a fraction eta of the way to the boundary, eta = 1 - sigma clipped
# to [0.99, 0.9999] (step_fraction): Nocedal & Wright, Numerical Optimization (2006) Sec. 14.2
# and Alg. 16.4, take eta_k in [0.9, 1) and let it tend to 1 as the iterates converge. A fixed
# 0.99 caps the complementarity's fall at 100x an iteration, which set the last iterations of
# every warm-started solve; a fixed 0.9999 jammed fastmpc-3d's solves on the boundary (5 of 141
# steps at the iteration cap) where the corrector was still centring. Iterations per MPC step,
# 0.99 -> 1 - sigma: fastmpc-3d 5.48 -> 3.75, rotating-target-b 5.40 -> 3.48, thesis-vbar
# 15.27 -> 14.49, with the same statuses and answers (docs/solver.md).
STEP_FRACTION_MIN = 0.99
STEP_FRACTION_MAX = 0.9999


class PDState(NamedTuple):
    """Carry of the primal-dual loop (one problem). Row arrays: (N, mu) or (N, mx)."""

    u: jnp.ndarray
    x: jnp.ndarray
    nu: jnp.ndarray
    s: jnp.ndarray  # explicit slack of the soft state rows, s >= 0
    lam: jnp.ndarray  # multiplier of the input rows Fu u <= fu
    mu: jnp.ndarray  # multiplier of the soft rows Fx x - s <= fx
    pi: jnp.ndarray  # multiplier of s >= 0 (mu + pi = rho at the optimum)
    it: jnp.ndarray
    done: jnp.ndarray
    status: jnp.ndarray
    gap: jnp.ndarray  # complementarity sum (the duality gap of a dual-feasible point)
    res: jnp.ndarray  # relative dual residual
    # Row values, updated with the steps as primal variables (not recomputed from u and x:
    # each product reads the row matrices, and the row work is memory bound, docs/benchmark.md)
    su: jnp.ndarray  # fu - Fu u (input-row slacks)
    g: jnp.ndarray  # Fx x - fx (soft-row values)
    # The predictor's Newton system at this iterate (Phi_u's and Phi_x's lower triangles, g_x,
    # base_u, base_x, rp: rows_kernel.pd_blocks's outputs), where the Newton step's form
    # carries it (carries_system): formed by the start, then by each iteration's step kernel
    # at the point it steps to, so that the next iteration does not read the rows and the
    # iterate again to form it. None elsewhere (the iteration forms it itself).
    system: tuple | None = None


def pd_start(rows, u0, x0s, nu0, kappa0, done, status) -> PDState:
    """A start on the central path at kappa0 (the soft rows' slack in closed form)."""
    su = u_slack(rows, u0)
    # s minimises rho s - kappa0 log s - kappa0 log(s - g) (closed form, see soft_slack), so
    # mu s_x = pi s = kappa0 and mu + pi = rho hold from the first iterate, whatever rho.
    g = x_violation(rows, x0s)
    s0, sx = soft_slack(g, rows.rho, kappa0)
    lam = jnp.where(rows.wu > 0, kappa0 / jnp.where(su > 0, su, 1.0), 1.0)
    mu = kappa0 / sx
    pi = kappa0 / s0
    gap = jnp.sum(rows.wu * su * lam) + jnp.sum(rows.wx * (sx * mu + s0 * pi))
    inf = jnp.asarray(jnp.inf, gap.dtype)
    return PDState(u0, x0s, nu0, s0, lam, mu, pi, jnp.asarray(0), done, status, gap, inf, su, g)


def _pd_rhs(rows, st: PDState, base_u, base_x, su, sx, tau_u, tau_x, tau_s):
    """Right-hand side (g_u, g_x) of the primal-dual Newton system for complementarity
    targets tau, and h (the soft rows' slack term).

    Linearising lam su = tau_u, mu sx = tau_x, pi s = tau_s and rho = mu + pi, then eliminating
    the row variables leaves the stage-structured system of :mod:`rvdjax.solver.kkt` with
    input-row weight lam/su and soft-row weight a c / (a + c) (a = mu/sx, c = pi/s). ``base_u``,
    ``base_x`` are the cost gradient (2 R u + r, 2 Q (x - x_ref) + q), shared by the predictor
    and the corrector.
    """
    a = st.mu / sx
    c = st.pi / st.s
    h = _soft_h(rows, st, sx, tau_x, tau_s)
    g_u = base_u + sw.mtv(rows.Fu, rows.wu * tau_u / su)
    g_x = base_x + sw.mtv(rows.Fx, rows.wx * (tau_x / sx - a * h / (a + c)))
    return g_u, g_x, h


def _soft_h(rows, st: PDState, sx, tau_x, tau_s):
    """h of the soft rows' elimination (:func:`_pd_rhs`) for targets tau_x, tau_s."""
    return tau_x / sx + tau_s / st.s - rows.rho


def _cost_gradient(ocp, u, x):
    """The cost's gradient at (u, x): 2 R u + r and 2 Q (x - x_ref) + q."""
    return 2.0 * sw.mv(ocp.R, u) + ocp.r, 2.0 * sw.mv(ocp.Q, x - ocp.x_ref) + ocp.q


def _newton_blocks(ocp, rows, st: PDState, su, sx):
    """The predictor's Newton system from ``st``: the Hessian blocks Phi_u, Phi_x (the cost's
    and the rows' barrier terms, :func:`_pd_rhs`'s elimination) and the right-hand side
    g_u, g_x for zero targets; the cost's gradient base_u, base_x at ``st``, which the
    corrector's right-hand side shares; the dynamics' residual rp at ``st``."""
    base_u, base_x = _cost_gradient(ocp, st.u, st.x)
    rp = dyn_residual(ocp, st.u, st.x)
    Du = rows.wu * st.lam / su
    a = st.mu / sx
    c = st.pi / st.s
    Phi_u = 2.0 * ocp.R + sw.congruence(rows.Fu, Du)
    Phi_x = 2.0 * ocp.Q + sw.congruence(rows.Fx, rows.wx * a * c / (a + c))
    zero_u, zero_x = jnp.zeros_like(su), jnp.zeros_like(sx)
    g_u, g_x, _ = _pd_rhs(rows, st, base_u, base_x, su, sx, zero_u, zero_x, zero_x)
    return Phi_u, Phi_x, g_u, g_x, base_u, base_x, rp


def _system_xla(ocp, rows, st: PDState, su, sx):
    """:func:`pd_kernels._system_in_kernel`'s system by XLA (:func:`_newton_blocks`; g_u is
    base_u)."""
    Phi_u, Phi_x, _, g_x, base_u, base_x, rp = _newton_blocks(ocp, rows, st, su, sx)
    return tri_pack(Phi_u, 1), tri_pack(Phi_x, 1), g_x, base_u, base_x, rp


def _stored_blocks(ocp, rows, st: PDState, su, sx):
    """:func:`_newton_blocks` with Phi_u and Phi_x as :class:`SymStored`, the structure of
    :func:`pd_kernels._blocks_in_kernel`'s, for the branch of a program that also holds the kernels
    (the triangles are dead code where XLA's loops run)."""
    Phi_u, Phi_x, *rest = _newton_blocks(ocp, rows, st, su, sx)
    return (SymStored(Phi_u, tri_pack(Phi_u, 1)), SymStored(Phi_x, tri_pack(Phi_x, 1)), *rest)


def _pd_unpack(rows, st: PDState, step, su, sx, tau_u, tau_x, tau_s, h):
    """The full steps of every variable from the step of the stage system, and Fx dx."""
    Fdu = sw.mv(rows.Fu, step.du)
    Fdx = sw.mv(rows.Fx, step.dx)
    return (step, *_row_steps(rows, st, Fdu, Fdx, su, sx, tau_u, tau_x, tau_s, h))


def _row_steps(rows, st: PDState, Fdu, Fdx, su, sx, tau_u, tau_x, tau_s, h):
    """The rows' steps from the row products Fu du, Fx dx: (ds, dlam, dmu, dpi, dsu, dsx,
    Fdx)."""
    Du = rows.wu * st.lam / su
    a = st.mu / sx
    c = st.pi / st.s
    ds = (a * Fdx + h) / (a + c)
    dlam = tau_u / su - st.lam + Du * Fdu
    dmu = tau_x / sx - st.mu + a * (Fdx - ds)
    dpi = tau_s / st.s - st.pi - c * ds
    dsu = -Fdu
    dsx = -Fdx + ds
    return ds, dlam, dmu, dpi, dsu, dsx, Fdx


def _targets(aff, alpha_a, kappa):
    """The corrector's complementarity targets (tau_u, tau_x, tau_s) from the predictor's row
    steps ``aff`` (:func:`_row_steps`): centring plus Mehrotra's second-order term, damped by
    the affine step length.

    The full term dsu_a dlam_a is the product of the affine steps at alpha = 1; when the
    affine step is cut to alpha_a, the products the corrector should cancel are
    alpha_a^2 dsu_a dlam_a and the full term overshoots: from the warm starts of the
    three-phase family, correctors with the full term were cut to step lengths of 1e-3 for
    dozens of iterations (up to 82 per solve). Damping by alpha_a (one factor, as the
    centring target also moves with the step) halved the iterations per solve there."""
    ds_a, dlam_a, dmu_a, dpi_a, dsu_a, dsx_a, _ = aff
    damp = alpha_a
    return (
        kappa - damp * dsu_a * dlam_a,
        kappa - damp * dsx_a * dmu_a,
        kappa - damp * ds_a * dpi_a,
    )


def _corrector_rhs(rows, st: PDState, base_u, base_x, su, sx, step, h, m_eff):
    """From the predictor's step: the corrector's right-hand side (g_u, g_x), the predictor's
    row products Fu du, Fx dx, its step length alpha_a and the corrector's barrier weight
    kappa (XLA's form; :mod:`rvdjax.solver.rows_kernel` is the same as one GPU kernel)."""
    zero_u, zero_x = jnp.zeros_like(su), jnp.zeros_like(sx)
    aff = _pd_unpack(rows, st, step, su, sx, zero_u, zero_x, zero_x, h)
    _, ds_a, dlam_a, dmu_a, dpi_a, dsu_a, dsx_a, Fdx_a = aff
    wmask = (rows.wu, rows.wx, rows.wx, rows.wu, rows.wx, rows.wx)
    alpha_a = _max_step(
        ((su, sx, st.s, st.lam, st.mu, st.pi), (dsu_a, dsx_a, ds_a, dlam_a, dmu_a, dpi_a)), wmask
    )
    gap = st.gap
    gap_a = jnp.sum(rows.wu * (su + alpha_a * dsu_a) * (st.lam + alpha_a * dlam_a)) + jnp.sum(
        rows.wx
        * (
            (sx + alpha_a * dsx_a) * (st.mu + alpha_a * dmu_a)
            + (st.s + alpha_a * ds_a) * (st.pi + alpha_a * dpi_a)
        )
    )
    sigma = jnp.clip(gap_a / jnp.maximum(gap, 1e-300), 0.0, 1.0) ** 3
    # While the dual residual is large, keep centring: from a warm start whose multipliers are
    # far from dual feasible (the LP cost of thesis-vbar-lp), Mehrotra's sigma drove the gap
    # down 5000x in five iterations while the residual stayed, and the iterate then crept
    # along the boundary for 100-300 iterations.
    res = jnp.where(jnp.isfinite(st.res), st.res, 0.0)
    sigma = jnp.where(res > SIGMA_FLOOR_RES, jnp.maximum(sigma, SIGMA_FLOOR), sigma)
    kappa = sigma * gap / jnp.maximum(m_eff, 1.0)
    taus = _targets(aff[1:], alpha_a, kappa)
    g_u, g_x, _ = _pd_rhs(rows, st, base_u, base_x, su, sx, *taus)
    return g_u, g_x, -dsu_a, Fdx_a, alpha_a, kappa


def step_fraction(kappa, gap, m_eff):
    """The fraction eta of the way to the boundary that the corrector's step goes: 1 - sigma
    (sigma = kappa m / gap, the centring weight of :func:`_corrector_rhs`) clipped to
    [STEP_FRACTION_MIN, STEP_FRACTION_MAX]; NaN where kappa is."""
    sigma = kappa * jnp.maximum(m_eff, 1.0) / jnp.maximum(gap, 1e-300)
    return jnp.clip(1.0 - sigma, STEP_FRACTION_MIN, STEP_FRACTION_MAX)


def _step_xla(ocp, rows, st: PDState, su, sx, step, taus, h, fraction):
    """The corrector's step taken, ``fraction`` (:func:`step_fraction`, 0 where the solve is
    stopped) of the way to the boundary: (the new u, x, nu, s, lam, mu, pi, su, g; the
    complementarity there; whether the step was finite; the stopping test's relative dual
    residual and objective there, :func:`_stopping_terms`)."""
    step, ds, dlam, dmu, dpi, dsu, dsx, Fdx = _pd_unpack(rows, st, step, su, sx, *taus, h)
    wmask = (rows.wu, rows.wx, rows.wx, rows.wu, rows.wx, rows.wx)
    # The rows' steps are finite where this ratio test is not NaN (Fdx is, where ds and dsx
    # are); the Newton step's own blocks are tested apart.
    alpha = _max_step(
        ((su, sx, st.s, st.lam, st.mu, st.pi), (dsu, dsx, ds, dlam, dmu, dpi)), wmask, True
    )
    row_steps = (ds, dlam, dmu, dpi, dsu, Fdx)
    finite, alpha, new = _updated(rows, st, su, step, alpha, fraction, row_steps)
    u, x, nu, s_new, lam, mu, pi, su_n, g_n = new
    sx_n = s_new - g_n
    gap_n = jnp.sum(rows.wu * su_n * lam) + jnp.sum(rows.wx * (sx_n * mu + s_new * pi))
    Fu_lam, Fx_mu = sw.mtv(rows.Fu, rows.wu * lam), sw.mtv(rows.Fx, rows.wx * mu)
    r_s, J_s = _soft_terms(rows, mu, pi, g_n)
    return new, gap_n, finite, _stopping_terms(ocp, rows, u, x, nu, Fu_lam, Fx_mu, r_s, J_s)


def _stopping_terms(ocp, rows, u, x, nu, Fu_lam, Fx_mu, r_s, J_s):
    """The stopping test's (relative dual residual, objective) at (u, x, nu): the dual
    residual (barrier.dual_residual) of the cost gradient plus the rows' terms Fu^T wu lam,
    Fx^T wx mu, relative to the gradient's scale, or the soft rows' largest |wx (rho - mu -
    pi)| = ``r_s`` relative to their largest penalty; the objective (barrier.objective) with
    the soft rows' penalty sum ``J_s``."""
    e = x - ocp.x_ref
    Ru = sw.mv(ocp.R, u)
    Qe = sw.mv(ocp.Q, e)
    grad_u = 2.0 * Ru + ocp.r
    grad_x = 2.0 * Qe + ocp.q
    r_u, r_x = dual_residual(ocp, grad_u + Fu_lam, grad_x + Fx_mu, nu)
    d_scale = 1.0 + jnp.maximum(jnp.max(jnp.abs(grad_u)), jnp.max(jnp.abs(grad_x)))
    rel_d = jnp.maximum(
        jnp.maximum(jnp.max(jnp.abs(r_u)), jnp.max(jnp.abs(r_x))) / d_scale,
        r_s / (1.0 + jnp.max(rows.wx * rows.rho)),
    )
    # the objective (barrier.objective) from the products above
    J = jnp.sum(e * Qe) + jnp.sum(u * Ru) + jnp.sum(ocp.q * x) + jnp.sum(ocp.r * u) + J_s
    return rel_d, J


def _soft_terms(rows, mu, pi, g):
    """The soft rows' terms of the stopping test at (mu, pi, g): the largest dual residual
    |wx (rho - mu - pi)| and the penalty sum wx rho max(g, 0)."""
    r_s = rows.wx * (rows.rho - mu - pi)
    return jnp.max(jnp.abs(r_s)), jnp.sum(rows.wx * rows.rho * jnp.maximum(g, 0.0))


def _updated(rows, st: PDState, su, step, alpha, fraction, row_steps):
    """(finite, the step length taken, the new u, x, nu, s, lam, mu, pi, su, g) from the ratio
    test's ``alpha`` (NaN where a row's step is not finite) and the rows' steps (ds, dlam,
    dmu, dpi, dsu, Fdx): ``fraction`` of the way to the boundary, at most 1; a step of length
    zero where it is not finite or ``fraction`` is not positive (a stopped solve's 0; NaN)."""
    ds, dlam, dmu, dpi, dsu, Fdx = row_steps
    finite = all_finite(step) & ~jnp.isnan(alpha)
    alpha = jnp.where(finite & (fraction > 0.0), jnp.minimum(1.0, fraction * alpha), 0.0)

    def upd(v, dv, w=1.0):
        return v + alpha * jnp.where(finite & (w > 0), dv, 0.0)  # padding rows stay put

    u, x, s_new = upd(st.u, step.du), upd(st.x, step.dx), upd(st.s, ds, rows.wx)
    lam, mu = upd(st.lam, dlam, rows.wu), upd(st.mu, dmu, rows.wx)
    pi = upd(st.pi, dpi, rows.wx)
    nu = upd(st.nu, step.nu - st.nu)
    su_n = upd(su, dsu)
    g_n = upd(st.g, Fdx)  # soft-row values at the new point
    return finite, alpha, (u, x, nu, s_new, lam, mu, pi, su_n, g_n)


def _step_xla_system(ocp, rows, st: PDState, su, sx, step, taus, h, fraction):
    """:func:`_step_xla`'s results and the Newton system at the new point
    (:func:`_system_xla`): XLA's form of the step kernel that carries the system."""
    new, gap_n, finite, terms = _step_xla(ocp, rows, st, su, sx, step, taus, h, fraction)
    u, x, nu, s, lam, mu, pi, su_n, g_n = new
    at = st._replace(u=u, x=x, nu=nu, s=s, lam=lam, mu=mu, pi=pi, su=su_n, g=g_n)
    return new, gap_n, finite, terms, _system_xla(ocp, rows, at, su_n, s - g_n)


def _max_step(pairs, wmask, nan_if_not_finite=False):
    """Largest alpha in (0, 1] keeping every (value + alpha * step) >= 0 on active rows.

    ``nan_if_not_finite``: NaN where a step has a non-finite entry on any row, masked or not
    (0 * dv is NaN exactly there, and the minimum keeps a NaN), so that the same pass over
    the rows is also the step's finiteness test: a separate test read every row array again
    (on a GPU one more pass through device memory, docs/benchmark.md)."""
    by_shape: dict = {}  # the elementwise minimum of the ratios of one shape, reduced once
    for v, dv, w in zip(*pairs, wmask, strict=True):
        shrink = (w > 0) & (dv < 0)
        ratio = jnp.where(shrink, -v / jnp.where(shrink, dv, -1.0), jnp.inf)
        if nan_if_not_finite:
            ratio = ratio + 0.0 * dv
        old = by_shape.get(ratio.shape)
        by_shape[ratio.shape] = ratio if old is None else jnp.minimum(old, ratio)
    alpha = jnp.asarray(1.0)
    for ratio in by_shape.values():
        alpha = jnp.minimum(alpha, jnp.min(ratio))
    return alpha
