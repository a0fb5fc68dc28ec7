"""Primal-dual (Mehrotra predictor-corrector) iterations of the accurate mode.

Barrier continuation with primal-dual Newton steps: kappa = sigma * gap / m with Mehrotra's
sigma = (gap_affine / gap)^3, a predictor and a corrector solve sharing one Riccati
factorisation (Nocedal & Wright Alg. 16.4; Wright 1997, Ch. 10). Primal-dual rather than
primal Newton steps because after each kappa cut the primal barrier Hessian kappa / s^2 is the
curvature of the *old* centre: the step overshoots the active rows and backtracks for several
iterations, whereas the dual estimate lam / s gives the new centre of each row in one step.

Soft state rows carry an explicit slack s >= 0 here (Fx x - s <= fx, cost rho s), with
multipliers mu (of the row) and pi (of s >= 0); mu + pi = rho at the optimum.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax.numpy as jnp

from rvdjax.solver import rows_kernel
from rvdjax.solver import stagewise as sw
from rvdjax.solver.barrier import (
    all_finite,
    dual_residual,
    dyn_residual,
    soft_slack,
    u_slack,
    x_violation,
)
from rvdjax.solver.kkt import kkt_factor_solve, kkt_solve_refined
from rvdjax.solver.lanes import tri_pack, tri_unpack
from rvdjax.solver.platform import AUTO_ON_CUDA, cuda_or_default, traces_cuda
from rvdjax.solver.riccati import ROWS_BLOCK_IO, ROWS_IN_KERNEL, SYSTEM_CARRIED, SymStored
from rvdjax.solver.start import drift
from rvdjax.solver.types import SolverParams, SolverSettings, Status

__all__ = [
    "PDState",
    "pd_start",
    "pd_iteration",
    "carries_system",
    "pd_system",
    "pd_drift",
    "step_fraction",
]

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


def _kernel_model(ocp, table):
    """The model [B, A] of the blocks' and the step's kernels (as the Riccati kernels' rules
    form it; unused, and not formed, where the kernels read the tables) and their tables
    (Fu, wx, rho, Q, R, [B, A], index) where ``table`` has them all, else ()."""
    model = jnp.concatenate([ocp.B, ocp.A], axis=-1)
    if table is None or table.Fu is None or table.Q is None:
        return model, ()
    return model, (table.Fu, table.x_mask, table.rho, table.Q, table.R, table.M, table.index)


def _blocks_in_kernel(ocp, rows, st: PDState, su, sx, interpret, table=None, block_io=True):
    """:func:`_newton_blocks` by :func:`rows_kernel.pd_blocks`, one kernel that reads Fx once
    and forms the cost's gradient too, and the dynamics' residual in a second sweep (the
    input rows' targets are zero: g_u is base_u). ``table``: the model's table, whose input
    rows, soft rows' mask and penalty, cost blocks and model [B, A] the kernel reads where it
    has them all; ``block_io``: as :func:`rvdjax.solver.rows_kernel.batched`."""
    return _system_blocks(_system_in_kernel(ocp, rows, st, su, sx, interpret, table, block_io))


def _system_in_kernel(ocp, rows, st: PDState, su, sx, interpret, table=None, block_io=True):
    """The Newton system as :func:`rows_kernel.pd_blocks` returns it (:attr:`PDState.system`;
    arguments as :func:`_blocks_in_kernel`)."""
    del sx  # the kernel forms s - g itself
    model, tables = _kernel_model(ocp, table)
    fn = rows_kernel.batched("blocks", 0, None, interpret, bool(tables), block_io)
    cost = (ocp.Q, ocp.R, model, ocp.q, ocp.r, ocp.x_ref, ocp.c, ocp.x0[None])
    return tuple(fn(*_kernel_rows(rows, st, su), st.u, st.x, *cost, *tables))


def _system_xla(ocp, rows, st: PDState, su, sx):
    """:func:`_system_in_kernel`'s system by XLA (:func:`_newton_blocks`; g_u is base_u)."""
    Phi_u, Phi_x, _, g_x, base_u, base_x, rp = _newton_blocks(ocp, rows, st, su, sx)
    return tri_pack(Phi_u, 1), tri_pack(Phi_x, 1), g_x, base_u, base_x, rp


def _system_blocks(system):
    """:func:`_newton_blocks`'s (Phi_u, Phi_x, g_u, g_x, base_u, base_x, rp) from a system
    as :attr:`PDState.system` holds it, Phi_u and Phi_x as :class:`SymStored` (the kernels
    read the triangles; the matrices are for XLA's forms)."""
    Phi_u, Phi_x, g_x, base_u, base_x, rp = system
    Phi_u, Phi_x = (SymStored(tri_unpack(a, 1, True), a) for a in (Phi_u, Phi_x))
    return Phi_u, Phi_x, base_u, g_x, base_u, base_x, rp


def carries_system(settings: SolverSettings) -> bool:
    """Whether the solve's state carries the Newton system (:attr:`PDState.system`): the
    accurate mode with a form of :data:`rvdjax.solver.riccati.SYSTEM_CARRIED`, or with
    ``"auto"`` where that is what it runs on a CUDA GPU and the program keeps the CUDA form
    (:func:`rvdjax.solver.platform.traces_cuda`; on a CPU-only process, never)."""
    if settings.mode != "accurate":
        return False
    if settings.kernel == "auto":
        return AUTO_ON_CUDA in SYSTEM_CARRIED and traces_cuda()
    return settings.kernel in SYSTEM_CARRIED


def pd_system(ocp, rows, st: PDState, kernel: str, table=None):
    """The Newton system at ``st`` (:attr:`PDState.system`), by the blocks' kernel where the
    Newton step runs on the GPU kernels, else by XLA (a start's; the iterations form the
    next one in their step's kernel). ``table`` as :func:`_blocks_in_kernel`."""
    args = (ocp, rows, st, st.su, st.s - st.g)
    return _by_kernel(args, kernel, _system_xla, functools.partial(_system_in_kernel, table=table))


def _stored_blocks(ocp, rows, st: PDState, su, sx):
    """:func:`_newton_blocks` with Phi_u and Phi_x as :class:`SymStored`, the structure of
    :func:`_blocks_in_kernel`'s, for the branch of a program that also holds the kernels
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


def _kernel_rows(rows, st: PDState, su):
    """The row arrays the row kernels read (rvdjax.solver.rows_kernel.stage.StageRows)."""
    return (rows.Fx, rows.Fu, st.s, st.g, st.mu, st.pi, rows.wx, rows.rho, su, st.lam, rows.wu)


def _row_tables(table) -> tuple:
    """The row kernels' tables (Fu, wx, rho, index) of a model table that has them, or ()."""
    if table is None or table.Fu is None:
        return ()
    return (table.Fu, table.x_mask, table.rho, table.index)


def _rows_in_kernel(
    rows, st: PDState, base_u, base_x, su, sx, step, h, m_eff, interpret, table=None, block_io=True
):
    """:func:`_corrector_rhs` by :mod:`rvdjax.solver.rows_kernel` (which reads the input rows
    and the soft rows' mask and penalty from ``table``'s, where it has them)."""
    rule = rows_kernel.SigmaRule(SIGMA_FLOOR, SIGMA_FLOOR_RES)
    tables = _row_tables(table)
    fn = rows_kernel.batched("rows", 3, rule, interpret, bool(tables), block_io)
    m_eff = jnp.asarray(m_eff, st.gap.dtype)
    return fn(
        *_kernel_rows(rows, st, su),
        step.dx,
        step.du,
        base_x,
        base_u,
        st.gap,
        st.res,
        m_eff,
        *tables,
    )


def _by_kernel(args, kernel: str, xla, in_kernel):
    """``xla(*args)``, or ``in_kernel(*args, interpret=...)`` where the Newton step runs on
    the GPU kernels of :data:`ROWS_IN_KERNEL` (compiled on a CUDA GPU, interpreted elsewhere,
    as riccati.ops._by_platform chooses; ``kernel="auto"``: compiled on a CUDA GPU, XLA's form
    elsewhere)."""
    on_cuda = AUTO_ON_CUDA if kernel == "auto" else kernel
    # the row kernels' loads and stores: a stage's blocks in the block form's name
    in_kernel = functools.partial(in_kernel, block_io=on_cuda in ROWS_BLOCK_IO)
    compiled = functools.partial(in_kernel, interpret=False)
    if kernel == "auto":
        if AUTO_ON_CUDA not in ROWS_IN_KERNEL:
            return xla(*args)
        return cuda_or_default(*args, cuda=compiled, default=xla)
    if kernel in ROWS_IN_KERNEL:
        interpreted = functools.partial(in_kernel, interpret=True)
        return cuda_or_default(*args, cuda=compiled, default=interpreted)
    return xla(*args)


def pd_drift(ocp, u, kernel: str):
    """The states of the inputs ``u`` from x0 (:func:`rvdjax.solver.start.drift`): one kernel
    where the Newton step's form ``kernel`` runs the rows in kernels (compiled on a CUDA GPU,
    interpreted elsewhere; ``"auto"`` runs XLA's loop on the CPU), else XLA's."""
    return _by_kernel((ocp, u), kernel, drift, _drift_in_kernel)


def _drift_in_kernel(ocp, u, interpret, block_io=True):
    return rows_kernel.drift_batched(interpret, block_io)(ocp.A, ocp.B, ocp.c, u, ocp.x0)


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


def _step_in_kernel(
    ocp,
    rows,
    st: PDState,
    su,
    sx,
    step,
    taus,
    h,
    fraction,
    aff,
    interpret,
    table=None,
    block_io=True,
    system=False,
):
    """:func:`_step_xla` by :func:`rows_kernel.pd_step_rows`, which also takes the step and
    forms the stopping test's terms (``aff``: the predictor's Fdu_a, Fdx_a, alpha_a, kappa,
    from which it forms the targets ``taus`` and ``h`` again; ``table`` as
    :func:`_blocks_in_kernel`, whose model [B, A] it reads too); with ``system``, also the
    Newton system at the new point (:func:`_step_xla_system`)."""
    Fdu_a, Fdx_a, alpha_a, kappa = aff
    model, tables = _kernel_model(ocp, table)
    kind = "step_system" if system else "step"
    fn = rows_kernel.batched(kind, 3, None, interpret, bool(tables), block_io)
    extra = (ocp.c, ocp.x0[None]) if system else ()
    out = fn(
        *_kernel_rows(rows, st, su),
        step.dx,
        step.du,
        step.nu,
        Fdx_a,
        Fdu_a,
        st.u,
        st.x,
        st.nu,
        ocp.Q,
        ocp.R,
        model,
        ocp.q,
        ocp.r,
        ocp.x_ref,
        *extra,
        alpha_a,
        kappa,
        fraction,
        *tables,
    )
    new, sc, finite = out[:3]
    _, gap_n, rel_d, J = sc
    return (new, gap_n, finite, (rel_d, J), *out[3:])


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


def pd_iteration(
    ocp,
    rows,
    m_eff,
    x_scale,
    st: PDState,
    settings: SolverSettings,
    params: SolverParams,
    stop=False,
    table=None,
) -> PDState:
    """One Mehrotra predictor-corrector iteration from ``st``; where ``stop`` (a bool, traced
    or not), ``st`` itself: a step of length zero, so that a finished solve costs no select
    over the state's arrays (docs/benchmark.md, "A stopped solve's step of length zero").
    ``table``: the model's :class:`~rvdjax.solver.riccati.ModelTable`, for the GPU kernels,
    or None. The Newton system is ``st.system`` where it carries one, and then the new state
    carries the system at its iterate, formed by the step's kernel (:attr:`PDState.system`)."""
    stop = jnp.asarray(stop, bool)
    method, kernel = settings.method, settings.kernel
    su = st.su
    sx = st.s - st.g
    # Predictor: the affine-scaling direction (tau = 0), solved with the factorisation.
    zero_u, zero_x = jnp.zeros_like(su), jnp.zeros_like(sx)
    taus = (zero_u, zero_x, zero_x)
    h = _soft_h(rows, st, sx, zero_x, zero_x)
    # base_u, base_x: the cost's gradient, shared by the predictor and the corrector
    carried = st.system is not None
    if carried:  # formed by the start or by the previous iteration's step
        Phi_u, Phi_x, g_u, g_x, base_u, base_x, rp = _system_blocks(st.system)
    else:
        Phi_u, Phi_x, g_u, g_x, base_u, base_x, rp = _by_kernel(
            (ocp, rows, st, su, sx),
            kernel,
            _stored_blocks if kernel == "auto" and traces_cuda() else _newton_blocks,
            functools.partial(_blocks_in_kernel, table=table),
        )
    kkt, step = kkt_factor_solve(ocp.A, ocp.B, Phi_u, Phi_x, g_u, g_x, rp, method, kernel, table)
    args = (rows, st, base_u, base_x, su, sx, step, h, m_eff)
    g_u, g_x, Fdu_a, Fdx_a, alpha_a, kappa = _by_kernel(
        args, kernel, _corrector_rhs, functools.partial(_rows_in_kernel, table=table)
    )
    # the corrector's targets again (as _corrector_rhs formed them) for its row steps
    aff = _row_steps(rows, st, Fdu_a, Fdx_a, su, sx, *taus, h)
    taus = _targets(aff, alpha_a, kappa)
    h = _soft_h(rows, st, sx, taus[1], taus[2])
    # The corrector's step is the one taken, refined once. Near the solution the Newton matrix
    # is as ill-conditioned as the barrier weights (up to 1e12) and the Riccati solve's
    # residual depends on how XLA contracts its products (riccati.py): with loops compiled
    # whole, 4 of 32 random N = 60 problems ended NONFINITE without the refinement step.
    step = kkt_solve_refined(kkt, g_u, g_x, rp, method, kernel)
    eta = STEP_FRACTION_MIN
    if settings.step_fraction == "adaptive":
        eta = step_fraction(kappa, st.gap, m_eff)
    fraction = jnp.where(stop, 0.0, eta)
    args = (ocp, rows, st, su, sx, step, taus, h, fraction)
    in_kernel = functools.partial(
        _step_in_kernel, aff=(Fdu_a, Fdx_a, alpha_a, kappa), table=table, system=carried
    )
    new, gap_n, finite, (rel_d, J), *system = _by_kernel(
        args, kernel, _step_xla_system if carried else _step_xla, in_kernel
    )
    u, x, nu, s_new, lam, mu, pi, su_n, g_n = new

    # Stopping: gap and dual residual relative to the objective / gradient scale.
    scale = 1.0 + jnp.abs(J)
    tol = params.tol
    # The dual residual bounds the objective error through ||r_d|| ||z - z*||: 100x the gap
    # tolerance keeps that error below ~tol relative while staying reachable in float64 on
    # long, ill-conditioned horizons.
    converged = (gap_n <= tol * scale) & (rel_d <= 1e2 * tol)
    # Close to the solution the ratios lam/s overflow first: a failed step from an iterate
    # that already meets 10x the tolerances ends the solve as converged at that iterate.
    nearly = (st.gap <= 10.0 * tol * scale) & (st.res <= 1e3 * tol)
    status = jnp.where(
        ~finite,
        jnp.where(nearly, Status.CONVERGED, Status.NONFINITE),
        jnp.where(converged, Status.CONVERGED, Status.MAX_ITER),
    )
    done = converged | ~finite

    def kept(old, new):
        return jnp.where(stop, old, new)

    return PDState(
        u,
        x,
        nu,
        s_new,
        lam,
        mu,
        pi,
        kept(st.it, st.it + 1),
        kept(st.done, done),
        kept(st.status, status),
        kept(st.gap, gap_n),
        kept(st.res, rel_d),
        su_n,
        g_n,
        system[0] if carried else None,
    )
