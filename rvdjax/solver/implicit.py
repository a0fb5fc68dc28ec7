"""Implicit derivative of a solve (DESIGN §3): one structured KKT solve, no backpropagation
through the Newton iterations.

The returned point satisfies F(z, nu; theta, kappa) = 0 with F = (grad f_kappa + C^T nu,
C z - b) (:func:`rvdjax.solver.barrier.kkt_residual`). With J = dF/d(z, nu) (the symmetric
KKT matrix, factorised by the Riccati method), theta_bar = -(dF/dtheta)^T J^-1 (z_bar, nu_bar).
kappa is held at the returned iterate's value (accurate mode: each row's complementarity
product, :func:`rvdjax.solver.driver._derivative_kappa`); in paper mode that is the traced
``SolverParams.kappa``, which receives its derivative too (the other solver parameters move the
answer only through the iteration count: their derivative is zero).

A back-solve that is not finite (a singular or overflowing factorisation, a non-finite solve)
is replaced by zero so that no NaN leaves a batch, and counted: ``SolverParams.
derivative_probe`` receives 1 per such solve as its cotangent, so the derivative of a loss
with respect to it is the number of zeroed back-solves behind that loss's gradient.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rvdjax.solver.barrier import all_finite, hessian, kkt_residual, rows_of
from rvdjax.solver.kkt import KKT, kkt_factor, kkt_solve
from rvdjax.solver.types import SolverSettings, Status

__all__ = ["kkt_at", "implicit_bwd"]


def kkt_at(ocp, u, x, kappa, settings: SolverSettings) -> KKT:
    """The (factorised) Newton matrix of the barrier problem at a point."""
    Phi_u, Phi_x = hessian(ocp, rows_of(ocp), u, x, kappa)
    return kkt_factor(ocp.A, ocp.B, Phi_u, Phi_x, settings.method, settings.kernel)


def implicit_bwd(settings: SolverSettings, res, sol_bar):
    """Backward rule of the solve: (ocp_bar, params_bar, init_bar) from the cotangent of the
    :class:`~rvdjax.solver.types.Solution`."""
    ocp, params, init, sol, kkt, kappa = res
    # J w = (u_bar, x_bar, nu_bar): the Newton system with g = -z_bar, r_p = -nu_bar.
    w = kkt_solve(kkt, -sol_bar.u, -sol_bar.x, -sol_bar.nu, settings.method, settings.kernel)

    def F(o, kappa):
        return kkt_residual(o, sol.u, sol.x, sol.nu, kappa)

    _, vjp = jax.vjp(F, ocp, kappa)
    ocp_bar, kappa_bar = vjp((-w.du, -w.dx, -w.nu))
    ok = (sol.status != Status.NONFINITE) & all_finite((w.du, w.dx, w.nu))
    # a back-solve that is not finite is zeroed, and counted: the cotangent of
    # params.derivative_probe is 1 for every solve zeroed (in whole or in part)
    finite = ok & all_finite(ocp_bar)
    ocp_bar = jax.tree.map(lambda a: jnp.where(ok & jnp.isfinite(a), a, 0.0), ocp_bar)
    params_bar = jax.tree.map(jnp.zeros_like, params)
    if settings.mode == "paper":  # the returned kappa is params.kappa
        finite = finite & jnp.isfinite(kappa_bar)
        kappa_bar = jnp.where(ok & jnp.isfinite(kappa_bar), kappa_bar, 0.0)
        params_bar = params_bar._replace(kappa=kappa_bar.astype(params_bar.kappa.dtype))
    zeroed = jnp.where(finite, 0.0, 1.0).astype(params_bar.derivative_probe.dtype)
    params_bar = params_bar._replace(derivative_probe=zeroed)
    init_bar = None if init is None else jax.tree.map(jnp.zeros_like, init)
    return ocp_bar, params_bar, init_bar
