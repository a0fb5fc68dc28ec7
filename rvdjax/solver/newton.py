"""Primal infeasible-start Newton iterations: paper mode and the primal barrier continuation.

Paper mode is Algorithm 1 of paper 000: a Newton step of the barrier problem at fixed kappa
(Eqs. 18-23) from the structured KKT solve, a first backtracking loop to strict feasibility of
the input rows and a second on the residual norm with alpha, beta. Barrier mode runs the same
step to convergence with kappa divided by ``kappa_factor`` whenever the Newton decrement shows
the iterate is centred, and Armijo backtracking on the barrier objective.

The line search evaluates ``SolverSettings.line_search_batch`` trial step lengths at once and
takes the first accepted one: the same t as sequential backtracking (the trials are generated
by the same repeated multiplication), but a batch of problems waits for its slowest member in
groups of trials rather than one trial at a time.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from rvdjax.solver import stagewise as sw
from rvdjax.solver.barrier import (
    dual_residual,
    dyn_residual,
    gradient,
    hessian,
    soft_penalty,
    u_slack,
    x_violation,
)
from rvdjax.solver.kkt import kkt_factor_solve
from rvdjax.solver.types import SolverParams, SolverSettings, Status

__all__ = ["NewtonState", "newton_iteration", "backtrack"]


class NewtonState(NamedTuple):
    """Carry of the primal Newton loop (one problem)."""

    u: jnp.ndarray  # (N, nu)
    x: jnp.ndarray  # (N, nx)
    nu: jnp.ndarray  # (N, nx)
    kappa: jnp.ndarray  # ()
    it: jnp.ndarray  # () iterations taken
    done: jnp.ndarray  # () bool: converged or failed
    status: jnp.ndarray  # () int
    rel_res: jnp.ndarray  # () relative residual at (u, x, nu) for kappa


class _Ray(NamedTuple):
    """What the line search needs along z + t dz, precomputed once per iteration so that a
    trial step costs elementwise work and two small row products, not a residual rebuild."""

    su: jnp.ndarray  # (N, mu) input-row slack at t = 0
    dsu: jnp.ndarray  # (N, mu) its rate of change
    g: jnp.ndarray  # (N, mx) soft-row violation at t = 0
    dg: jnp.ndarray  # (N, mx)
    quad: jnp.ndarray  # () quadratic + linear cost at t = 0
    dquad: jnp.ndarray  # () its slope
    ddquad: jnp.ndarray  # () its curvature term (cost(t) = quad + t dquad + t^2 ddquad)
    ru0: jnp.ndarray  # (N, nu) dual residual without barrier terms at t = 0
    ru1: jnp.ndarray  # (N, nu) its rate of change
    rx0: jnp.ndarray  # (N, nx)
    rx1: jnp.ndarray  # (N, nx)
    rp: jnp.ndarray  # (N, nx) dynamics residual at t = 0 (it scales with 1 - t)
    g_scale: jnp.ndarray  # () largest entry of the cost gradient at t = 0


def _ray(ocp, rows, s: NewtonState, du, dx, dnu) -> _Ray:
    e = s.x - ocp.x_ref
    Qe = sw.mv(ocp.Q, e)
    Ru = sw.mv(ocp.R, s.u)
    Qdx = sw.mv(ocp.Q, dx)
    Rdu = sw.mv(ocp.R, du)
    grad_u = 2.0 * Ru + ocp.r
    grad_x = 2.0 * Qe + ocp.q
    ru0, rx0 = dual_residual(ocp, grad_u, grad_x, s.nu)
    ru1, rx1 = dual_residual(ocp, 2.0 * Rdu, 2.0 * Qdx, dnu)
    return _Ray(
        su=u_slack(rows, s.u),
        dsu=-sw.mv(rows.Fu, du),
        g=x_violation(rows, s.x),
        dg=sw.mv(rows.Fx, dx),
        quad=jnp.sum(e * Qe) + jnp.sum(s.u * Ru) + jnp.sum(ocp.q * s.x) + jnp.sum(ocp.r * s.u),
        dquad=jnp.sum(grad_u * du) + jnp.sum(grad_x * dx),
        ddquad=jnp.sum(dx * Qdx) + jnp.sum(du * Rdu),
        ru0=ru0,
        ru1=ru1,
        rx0=rx0,
        rx1=rx1,
        rp=dyn_residual(ocp, s.u, s.x),
        g_scale=jnp.maximum(jnp.max(jnp.abs(grad_u)), jnp.max(jnp.abs(grad_x))),
    )


def _ray_barrier_objective(rows, ray: _Ray, t, kappa):
    """f_kappa(z + t dz) (paper 000 Eq. 17 with the soft rows' phi); +inf outside."""
    su = ray.su + t * ray.dsu
    inside = jnp.all((su > 0) | (rows.wu == 0))
    log_su = jnp.log(jnp.where(su > 0, su, 1.0))
    phi, _, _ = soft_penalty(ray.g + t * ray.dg, rows.rho, kappa)
    f = ray.quad + t * ray.dquad + t * t * ray.ddquad
    f = f - kappa * jnp.sum(rows.wu * log_su) + jnp.sum(rows.wx * phi)
    return jnp.where(inside, f, jnp.inf)


def _ray_residual(rows, ray: _Ray, t, kappa, x_scale):
    """(||r||_2, relative inf-norm residual) at (z, nu) + t (dz, dnu)."""
    su = ray.su + t * ray.dsu
    _, d1, _ = soft_penalty(ray.g + t * ray.dg, rows.rho, kappa)
    gb_u = kappa * sw.mtv(rows.Fu, rows.wu / jnp.where(su > 0, su, 1.0))
    gb_x = sw.mtv(rows.Fx, rows.wx * d1)
    r_u = ray.ru0 + t * ray.ru1 + gb_u
    r_x = ray.rx0 + t * ray.rx1 + gb_x
    r_p = (1.0 - t) * ray.rp
    norm2 = jnp.sqrt(jnp.sum(r_u**2) + jnp.sum(r_x**2) + jnp.sum(r_p**2))
    # Scale of the dual residual: the size of the gradient terms it balances.
    gb_scale = jnp.maximum(jnp.max(jnp.abs(gb_u)), jnp.max(jnp.abs(gb_x)))
    d_scale = 1.0 + jnp.maximum(ray.g_scale, gb_scale)
    rel = jnp.maximum(
        jnp.maximum(jnp.max(jnp.abs(r_u)), jnp.max(jnp.abs(r_x))) / d_scale,
        jnp.max(jnp.abs(r_p)) / x_scale,
    )
    return norm2, rel


def _step_length(rows, ray: _Ray, beta):
    """Algorithm 1, first loop: t = beta^k, the first such step strictly inside the input rows.

    Computed from the ratio test rather than by trial: the same t, without the loop.
    """
    shrinking = (rows.wu > 0) & (ray.dsu < 0)
    t_max = jnp.min(jnp.where(shrinking, ray.su / jnp.where(shrinking, -ray.dsu, 1.0), jnp.inf))
    k = jnp.floor(jnp.log(jnp.minimum(t_max, 1.0)) / jnp.log(beta)) + 1.0
    return jnp.where(t_max > 1.0, 1.0, beta ** jnp.where(jnp.isfinite(k), k, 0.0))


def backtrack(accept, t0, beta, max_steps: int, group: int):
    """The first of t0, beta t0, beta (beta t0), ... (``max_steps`` shrinks at most) for which
    ``accept(t)`` holds, else the last one: sequential backtracking, with ``group`` trials
    evaluated at once per loop iteration."""
    n_trials = max_steps + 1
    group = max(1, min(group, n_trials))

    def trials(t_next):
        ts = []
        t = t_next
        for _ in range(group):
            ts.append(t)
            t = beta * t
        return jnp.stack(ts), t

    def cond(c):
        j0, _, found, _ = c
        return (~found) & (j0 < n_trials)

    def body(c):
        j0, t_next, _, t_best = c
        ts, t_after = trials(t_next)
        js = j0 + jnp.arange(group)
        valid = js < n_trials
        ok = jax.vmap(accept)(ts) & valid
        found = jnp.any(ok)
        # not found: remember the last valid trial (the cap's t when this group reaches it)
        last = jnp.minimum(n_trials - 1 - j0, group - 1)
        t_best = jnp.where(found, ts[jnp.argmax(ok)], ts[last])
        return j0 + group, t_after, found, t_best

    init = (jnp.asarray(0), t0, jnp.asarray(False), t0)
    _, _, _, t = lax.while_loop(cond, body, init)
    return t


def newton_iteration(
    ocp,
    rows,
    m_eff,
    x_scale,
    s: NewtonState,
    settings: SolverSettings,
    params: SolverParams,
    table=None,
) -> NewtonState:
    """One primal Newton iteration (paper or barrier mode) from ``s`` (``table``: the model's
    :class:`~rvdjax.solver.riccati.ModelTable`, for the GPU kernels, or None)."""
    Phi_u, Phi_x = hessian(ocp, rows, s.u, s.x, s.kappa)
    g_u, g_x = gradient(ocp, rows, s.u, s.x, s.kappa)
    r_p = dyn_residual(ocp, s.u, s.x)
    _, step = kkt_factor_solve(
        ocp.A, ocp.B, Phi_u, Phi_x, g_u, g_x, r_p, settings.method, settings.kernel, table
    )
    finite = (
        jnp.all(jnp.isfinite(step.du))
        & jnp.all(jnp.isfinite(step.dx))
        & jnp.all(jnp.isfinite(step.nu))
    )
    du = jnp.where(finite, step.du, 0.0)
    dx = jnp.where(finite, step.dx, 0.0)
    dnu = jnp.where(finite, step.nu, s.nu) - s.nu
    # Newton decrement lambda^2 = dz^T Phi dz (Boyd & Vandenberghe Sec. 10.2): lambda^2 / 2
    # estimates the suboptimality of the pre-step point for the barrier problem.
    dec2 = sw.quad(du, Phi_u) + sw.quad(dx, Phi_x)

    ray = _ray(ocp, rows, s, du, dx, dnu)
    t0 = _step_length(rows, ray, params.beta)
    if settings.mode == "paper":
        # Algorithm 1, second loop: ||r(z + t dz, nu + t dnu)|| <= (1 - alpha t) ||r(z, nu)||.
        r0, _ = _ray_residual(rows, ray, 0.0, s.kappa, x_scale)

        def accept(t):
            return _ray_residual(rows, ray, t, s.kappa, x_scale)[0] <= (1.0 - params.alpha * t) * r0
    else:
        # Armijo on the barrier objective f_kappa (Boyd & Vandenberghe Alg. 9.2 / 10.2): the
        # iterate stays primal feasible, so f_kappa is the natural merit function, and unlike
        # the residual norm it does not mix units of cost gradient and of state.
        f0 = _ray_barrier_objective(rows, ray, 0.0, s.kappa)

        def accept(t):
            return _ray_barrier_objective(rows, ray, t, s.kappa) <= f0 - params.alpha * t * dec2

    t = backtrack(accept, t0, params.beta, settings.max_line_search, settings.line_search_batch)
    u = s.u + t * du
    x = s.x + t * dx

    if settings.mode == "paper":
        nu = s.nu + t * dnu
        _, rel_res = _ray_residual(rows, ray, t, s.kappa, x_scale)
        kappa = s.kappa
        converged = rel_res <= params.tol
    else:
        # The feasible Newton method takes the KKT solve's multiplier estimate.
        nu = s.nu + dnu
        rel_p = jnp.max(jnp.abs((1.0 - t) * ray.rp)) / x_scale
        rel_res = jnp.maximum(0.5 * dec2, m_eff * s.kappa)  # gap bound, refined after the loop
        J = ray.quad + t * ray.dquad + t * t * ray.ddquad
        J = J + jnp.sum(rows.wx * rows.rho * jnp.maximum(ray.g + t * ray.dg, 0.0))
        scale = 1.0 + jnp.abs(J)
        centred = (0.5 * dec2 <= params.centring * m_eff * s.kappa) & (rel_p <= 1e-6)
        converged = (
            (m_eff * s.kappa <= params.tol * scale)
            & (0.5 * dec2 <= params.tol * scale)
            & (rel_p <= params.tol)
        )
        kappa = jnp.where(centred & ~converged, s.kappa / params.kappa_factor, s.kappa)

    status = jnp.where(
        ~finite, Status.NONFINITE, jnp.where(converged, Status.CONVERGED, Status.MAX_ITER)
    )
    # A failed step keeps the last finite iterate.
    keep = lambda new, old: jnp.where(finite, new, old)  # noqa: E731
    return NewtonState(
        u=keep(u, s.u),
        x=keep(x, s.x),
        nu=keep(nu, s.nu),
        kappa=keep(kappa, s.kappa),
        it=s.it + 1,
        done=converged | ~finite,
        status=status,
        rel_res=keep(rel_res, s.rel_res),
    )
