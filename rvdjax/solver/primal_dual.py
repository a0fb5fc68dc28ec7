"""Primal-dual (Mehrotra predictor-corrector) iterations of the accurate mode.

Barrier continuation with primal-dual Newton steps: kappa = sigma * gap / m with Mehrotra's
sigma = (gap_affine / gap)^3, a predictor and a corrector solve sharing one Riccati
factorisation (Nocedal & Wright Alg. 16.4; Wright 1997, Ch. 10). Primal-dual rather than
primal Newton steps because after each kappa cut the primal barrier Hessian kappa / s^2 is the
curvature of the *old* centre: the step overshoots the active rows and backtracks for several
iterations, whereas the dual estimate lam / s gives the new centre of each row in one step.

The state, the start and the row algebra in XLA's form are :mod:`rvdjax.solver.pd_algebra`;
the same work on the GPU kernels is :mod:`rvdjax.solver.pd_kernels`.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp

from rvdjax.solver.kkt import kkt_factor_solve, kkt_solve_refined
from rvdjax.solver.pd_algebra import (
    STEP_FRACTION_MIN,
    PDState,
    _corrector_rhs,
    _newton_blocks,
    _row_steps,
    _soft_h,
    _step_xla,
    _step_xla_system,
    _stored_blocks,
    _targets,
    pd_start,
    step_fraction,
)
from rvdjax.solver.pd_kernels import (
    _blocks_in_kernel,
    _by_kernel,
    _rows_in_kernel,
    _step_in_kernel,
    _system_blocks,
    carries_system,
    pd_drift,
    pd_system,
)
from rvdjax.solver.platform import traces_cuda
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
    """One Mehrotra predictor-corrector iteration from ``st``; where ``stop`` (a bool, traced or
    not), ``st`` itself: a step of length zero, so that a finished solve costs no select over the
    state's arrays (docs/benchmark.md, "A stopped solve's step of length zero"). ``table``: the
    model's :class:`~rvdjax.solver.riccati.ModelTable`, for the GPU kernels, or None. The Newton
    system is ``st.system`` where it carries one, and then the new state carries the system at its
    iterate, formed by the step's kernel (:attr:`pd_algebra.PDState.system`)."""
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
