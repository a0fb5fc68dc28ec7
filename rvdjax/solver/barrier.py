"""Cost, log barrier and residuals of the OCP: pure functions of one problem's arrays.

The barrier problem of paper 000 Eq. 17 replaces the inequalities by -kappa sum log(slack).
Soft state rows (exact L1 penalty rho, :mod:`rvdjax.ocp`) are handled without slack variables:
for one row with violation g = F x - f the barrier problem's slack
min_s rho s - kappa log s - kappa log(s - g) has the closed form
s = (rho g + 2 kappa + sqrt(rho^2 g^2 + 4 kappa^2)) / (2 rho), so eliminating it leaves a
smooth convex penalty phi(g) of the state alone (partial minimisation preserves convexity and
leaves the Newton system's structure untouched). phi(g) -> rho max(0, g) as kappa -> 0, and it
is defined for every g: the start never needs to satisfy the state constraints.

Sign convention of the multipliers: the Lagrangian is f(z) + sum_t nu_t^T (x_{t+1} - A_t x_t -
B_t u_t - c_t) (see :mod:`rvdjax.solver.kkt`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from rvdjax.ocp import OCP
from rvdjax.solver import stagewise as sw

__all__ = [
    "Rows",
    "rows_of",
    "rows_in",
    "neutralised",
    "soft_slack",
    "soft_penalty",
    "u_slack",
    "x_violation",
    "objective",
    "max_violation",
    "gradient",
    "hessian",
    "dyn_residual",
    "dual_residual",
    "residual_norms",
    "kkt_residual",
    "m_eff",
    "all_finite",
]


class Rows(NamedTuple):
    """Inequality data with masked rows neutralised (zero row, offset 1, weight 0)."""

    Fu: jnp.ndarray
    fu: jnp.ndarray
    wu: jnp.ndarray
    Fx: jnp.ndarray
    fx: jnp.ndarray
    wx: jnp.ndarray
    rho: jnp.ndarray


def rows_of(ocp: OCP) -> Rows:
    on_u = ocp.u_mask > 0
    on_x = ocp.x_mask > 0
    return Rows(
        Fu=jnp.where(on_u[..., None], ocp.Fu, 0.0),
        fu=jnp.where(on_u, ocp.fu, 1.0),
        wu=ocp.u_mask,
        Fx=jnp.where(on_x[..., None], ocp.Fx, 0.0),
        fx=jnp.where(on_x, ocp.fx, 1.0),
        wx=ocp.x_mask,
        rho=jnp.where(on_x, ocp.rho, 1.0),
    )


def neutralised(ocp: OCP) -> OCP:
    """The OCP with its masked rows neutralised (zero row, offset 1, penalty 1): the same
    problem, whose rows :func:`rows_in` can read without masking again."""
    rows = rows_of(ocp)
    return ocp._replace(Fu=rows.Fu, fu=rows.fu, Fx=rows.Fx, fx=rows.fx, rho=rows.rho)


def rows_in(ocp: OCP) -> Rows:
    """The rows of an OCP returned by :func:`neutralised` (no masking work)."""
    return Rows(ocp.Fu, ocp.fu, ocp.u_mask, ocp.Fx, ocp.fx, ocp.x_mask, ocp.rho)


def m_eff(rows: Rows):
    """Number of barrier terms: one per input row, two (s >= 0, s >= g) per soft row."""
    return jnp.sum(rows.wu) + 2.0 * jnp.sum(rows.wx)


def all_finite(tree):
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in jax.tree.leaves(tree)]))


def _soft_kappas(kappa):
    """(kappa of s - g, kappa of s) of the soft rows: one weight for both, or a pair."""
    if isinstance(kappa, tuple):
        return kappa
    return kappa, kappa


def _soft_slack_parts(g, rho, kappa):
    """(s, s - g) of the optimal slack of one soft row (module docstring) and the two
    weights. With kappa = (k_mu, k_pi) the slack minimises rho s - k_pi log s - k_mu log(s - g)
    (a primal-dual iterate's own products mu (s - g), pi s); one kappa is the barrier problem.

    The stationarity rho = k_pi / s + k_mu / (s - g) is a quadratic in s whose larger root is
    s = (c + root + 2 k_pi) / (2 rho), s - g = (root - c + 2 k_mu) / (2 rho) with c = rho g +
    k_mu - k_pi and root = sqrt(c^2 + 4 k_mu k_pi), written without cancellation.
    """
    k_mu, k_pi = _soft_kappas(kappa)
    c = rho * g + k_mu - k_pi
    four = 4.0 * k_mu * k_pi
    root = jnp.sqrt(c * c + four)
    a = jnp.where(c >= 0, c + root, four / (root - jnp.minimum(c, 0.0)))  # c + root
    b = jnp.where(c <= 0, root - c, four / (root + jnp.maximum(c, 0.0)))  # root - c
    return (a + 2.0 * k_pi) / (2.0 * rho), (b + 2.0 * k_mu) / (2.0 * rho), k_mu, k_pi


def soft_slack(g, rho, kappa):
    """Optimal slack s of a soft row and s - g, both > 0."""
    s, s_minus_g, _, _ = _soft_slack_parts(g, rho, kappa)
    return s, s_minus_g


def soft_penalty(g, rho, kappa):
    """phi(g), phi'(g), phi''(g) of the slack-eliminated soft barrier (module docstring).

    phi' = k_mu / (s - g) (the row's multiplier) and phi'' = 1 / ((s - g)^2 / k_mu + s^2 /
    k_pi), the primal-dual linearisation 1 / ((s - g) / mu + s / pi) of the row.
    """
    s, s_minus_g, k_mu, k_pi = _soft_slack_parts(g, rho, kappa)
    phi = rho * s - k_pi * jnp.log(s) - k_mu * jnp.log(s_minus_g)
    d1 = k_mu / s_minus_g
    d2 = 1.0 / (s_minus_g * s_minus_g / k_mu + s * s / k_pi)
    return phi, d1, d2


def u_slack(rows: Rows, u):
    return rows.fu - sw.mv(rows.Fu, u)


def x_violation(rows: Rows, x):
    return sw.mv(rows.Fx, x) - rows.fx


def objective(ocp: OCP, u, x):
    """QP objective (paper 000 Eq. 1a, plus the exact penalty of the soft state rows)."""
    e = x - ocp.x_ref
    quad = sw.quad(e, ocp.Q) + sw.quad(u, ocp.R)
    lin = jnp.sum(ocp.q * x) + jnp.sum(ocp.r * u)
    rows = rows_of(ocp)
    pen = jnp.sum(rows.wx * rows.rho * jnp.maximum(x_violation(rows, x), 0.0))
    return quad + lin + pen


def max_violation(ocp: OCP, u, x):
    """Largest row-normalised violation of the (soft) state rows and the input rows."""
    rows = rows_of(ocp)
    gx = x_violation(rows, x) / jnp.maximum(jnp.linalg.norm(rows.Fx, axis=-1), 1e-300)
    gu = -u_slack(rows, u) / jnp.maximum(jnp.linalg.norm(rows.Fu, axis=-1), 1e-300)
    vx = jnp.max(jnp.where(rows.wx > 0, gx, -jnp.inf), initial=0.0)
    vu = jnp.max(jnp.where(rows.wu > 0, gu, -jnp.inf), initial=0.0)
    return jnp.maximum(jnp.maximum(vx, vu), 0.0)


def split_kappa(kappa):
    """(kappa of the input rows, kappa of the soft rows): a scalar serves both; a pair gives
    each row its own weight: ((N, mu) array, (N, mx) array or a pair of them for the two
    products of a soft row), the complementarity products of a primal-dual iterate
    (:func:`rvdjax.solver.driver._derivative_kappa`)."""
    if isinstance(kappa, tuple):
        return kappa
    return kappa, kappa


def gradient(ocp: OCP, rows: Rows, u, x, kappa):
    """Gradient blocks of cost + barrier (requires strictly feasible input rows)."""
    k_u, k_x = split_kappa(kappa)
    su = u_slack(rows, u)
    du = rows.wu / su
    _, d1, _ = soft_penalty(x_violation(rows, x), rows.rho, k_x)
    g_u = 2.0 * sw.mv(ocp.R, u) + ocp.r + sw.mtv(rows.Fu, k_u * du)
    g_x = 2.0 * sw.mv(ocp.Q, x - ocp.x_ref) + ocp.q + sw.mtv(rows.Fx, rows.wx * d1)
    return g_u, g_x


def hessian(ocp: OCP, rows: Rows, u, x, kappa):
    """Hessian blocks Phi_u (N, nu, nu), Phi_x (N, nx, nx) (paper 000 Eq. 21: 2H + barrier)."""
    k_u, k_x = split_kappa(kappa)
    su = u_slack(rows, u)
    wu2 = k_u * rows.wu / (su * su)
    _, _, d2 = soft_penalty(x_violation(rows, x), rows.rho, k_x)
    Phi_u = 2.0 * ocp.R + sw.congruence(rows.Fu, wu2)
    Phi_x = 2.0 * ocp.Q + sw.congruence(rows.Fx, rows.wx * d2)
    return Phi_u, Phi_x


def dyn_residual(ocp: OCP, u, x):
    """r_p: x_{t+1} - A_t x_t - B_t u_t - c_t, shape (N, nx)."""
    x_prev = jnp.concatenate([ocp.x0[None], x[:-1]])
    return x - sw.mv(ocp.A, x_prev) - sw.mv(ocp.B, u) - ocp.c


def dual_residual(ocp: OCP, g_u, g_x, nu):
    """r_d = grad f + C^T nu, split into the u and x blocks. Reads only the stage model
    ``ocp.A``, ``ocp.B``, so a :class:`rvdjax.solver.kkt.KKT` serves as well."""
    r_u = g_u - sw.mtv(ocp.B, nu)
    At_nu_next = sw.mtv(ocp.A[1:], nu[1:])
    r_x = g_x + nu - jnp.concatenate([At_nu_next, jnp.zeros_like(nu[:1])])
    return r_u, r_x


def residual_norms(ocp, rows, u, x, nu, kappa):
    """(||r||_2 for the line search, relative inf-norm dual and primal residuals)."""
    g_u, g_x = gradient(ocp, rows, u, x, kappa)
    r_u, r_x = dual_residual(ocp, g_u, g_x, nu)
    r_p = dyn_residual(ocp, u, x)
    norm2 = jnp.sqrt(jnp.sum(r_u**2) + jnp.sum(r_x**2) + jnp.sum(r_p**2))
    d_scale = 1.0 + jnp.maximum(jnp.max(jnp.abs(g_u)), jnp.max(jnp.abs(g_x)))
    p_scale = 1.0 + jnp.maximum(jnp.max(jnp.abs(x)), jnp.max(jnp.abs(ocp.x0)))
    rel_d = jnp.maximum(jnp.max(jnp.abs(r_u)), jnp.max(jnp.abs(r_x))) / d_scale
    rel_p = jnp.max(jnp.abs(r_p)) / p_scale
    return norm2, rel_d, rel_p


def kkt_residual(ocp: OCP, u, x, nu, kappa):
    """Optimality residual of the barrier problem: (r_u, r_x, r_p) (paper 000 Eqs. 19-20).

    One definition serves the stopping test, the tests and the implicit derivative.
    """
    rows = rows_of(ocp)
    g_u, g_x = gradient(ocp, rows, u, x, kappa)
    r_u, r_x = dual_residual(ocp, g_u, g_x, nu)
    return r_u, r_x, dyn_residual(ocp, u, x)
