"""Paper 001's QP solver: the parallel quadratic programming (PQP) dual method of its ref. 38
(Brand, Shilpiekandula, Yao, Bortoff, IFAC 2011), capped at a fixed number of iterations.

Paper 001 "transformed [Eq. 5] into a QP problem [38]" and capped the solver at "n = 100"
iterations (Tables 2-3), a limit "only reached when the FSS finds itself within a region of
local infeasibility". PQP solves the dual of the condensed QP by a multiplicative update:

* condense: the states are eliminated, x_{t+1} = M_t x0 + Gamma_t U + d_t, leaving
  min 1/2 U' P U + f' U  s.t.  G U <= g  (input rows and state rows on the predicted states);
* dual: min 1/2 y' H y + h' y over y >= 0 with H = G P^-1 G', h = g + G P^-1 f, and
  U = -P^-1 (f + G' y);
* update (every row at once, hence "parallel"):
  y_i <- y_i (h_i^- + (H^- y)_i) / (h_i^+ + (H^+ y)_i) with H^+ = max(H, 0) + diag(r),
  H^- = max(-H, 0) + diag(r), h^+ = max(h, 0) + s, h^- = max(-h, 0) + s. At a fixed point
  with y_i > 0, (H y + h)_i = 0: the optimality conditions of the dual. r_i = max(H_ii,
  max_j max(-H_ij, 0)) and s > 0 keep the denominators positive (Brand and Chen's choice).

rvdjax's soft state rows (exact L1 penalty rho) are, in the dual, the bound y_i <= rho_i: the
update is followed by clipping at rho (a projected multiplicative update; paper 001's QP had
hard rows, so a row whose multiplier reaches rho is one the QP cannot meet). The rows are
scaled so that diag(H) = 1 and the iteration starts from y = 1 (it needs y > 0; the previous
plan's inputs cannot seed the dual, so every solve starts cold). The returned plan is the
primal U of the last dual iterate with its states from the dynamics (a flyable plan, exactly
as paper 001's controller applied it after 100 iterations, converged or not).

Statuses: CONVERGED when the projected dual gradient is below ``tol`` relative to the scale of
h; MAX_ITER otherwise (the usual outcome within 100 iterations); INFEASIBLE when converged with
a soft row at its penalty; NONFINITE when the data or the iterate is not finite (zero plan).
There is no implicit derivative: ``jax.grad`` differentiates the fixed iterations.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from rvdjax.ocp import OCP
from rvdjax.solver.types import Solution, SolverParams, Status

__all__ = ["condense", "solve_dual"]

_S = 1e-12  # s of the update, relative to max |h| (keeps the denominators positive)


def condense(ocp: OCP):
    """The OCP as a dense QP in the stacked inputs U = (u_0, .., u_{N-1}) (N nu,).

    Returns:
        (P (n, n), f (n,), G (m, n), g (m,), soft (m,) 1.0 on the soft state rows, rho (m,),
        Gamma (N, nx, n), x_free (N, nx)): cost 1/2 U' P U + f' U (+ const), rows G U <= g
        (masked rows zero with g = 1), x_{t+1} = x_free_t + Gamma_t U.
    """
    N, nx, nu = ocp.N, ocp.nx, ocp.nu
    n = N * nu
    dtype = ocp.B.dtype

    def step(carry, stage):
        x_prev, Gam_prev = carry
        t, A, B, c = stage
        place = jnp.zeros((nu, n), dtype)
        place = lax.dynamic_update_slice(place, jnp.eye(nu, dtype=dtype), (0, t * nu))
        x_t = A @ x_prev + c
        Gam_t = A @ Gam_prev + B @ place
        return (x_t, Gam_t), (x_t, Gam_t)

    _, (x_free, Gam) = lax.scan(
        step, (ocp.x0, jnp.zeros((nx, n), dtype)), (jnp.arange(N), ocp.A, ocp.B, ocp.c)
    )
    R_blk = jax.scipy.linalg.block_diag(*[ocp.R[t] for t in range(N)])
    P = 2.0 * jnp.einsum("tia,tij,tjb->ab", Gam, ocp.Q, Gam) + 2.0 * R_blk
    P = 0.5 * (P + P.T)
    grad_x = 2.0 * jnp.einsum("tij,tj->ti", ocp.Q, x_free - ocp.x_ref) + ocp.q
    f = jnp.einsum("tia,ti->a", Gam, grad_x) + ocp.r.reshape(-1)
    on_u = ocp.u_mask > 0
    on_x = ocp.x_mask > 0
    Gu = jax.scipy.linalg.block_diag(
        *[jnp.where(on_u[t][:, None], ocp.Fu[t], 0.0) for t in range(N)]
    )
    gu = jnp.where(on_u, ocp.fu, 1.0).reshape(-1)
    Gx = jnp.einsum("tmi,tia->tma", jnp.where(on_x[..., None], ocp.Fx, 0.0), Gam).reshape(-1, n)
    gx = jnp.where(on_x, ocp.fx - jnp.einsum("tmi,ti->tm", ocp.Fx, x_free), 1.0).reshape(-1)
    G = jnp.concatenate([Gu, Gx])
    g = jnp.concatenate([gu, gx])
    soft = jnp.concatenate([jnp.zeros(gu.shape, dtype), on_x.reshape(-1).astype(dtype)])
    rho = jnp.concatenate([jnp.full(gu.shape, jnp.inf, dtype), ocp.rho.reshape(-1)])
    return P, f, G, g, soft, rho, Gam, x_free


def solve_dual(ocp: OCP, max_iter: int, params: SolverParams) -> Solution:
    """Solve ``ocp`` by ``max_iter`` PQP iterations on its dual (module docstring).

    Args:
        ocp: one problem (vmap for a batch).
        max_iter: static iteration count (paper 001: 100).
        params: ``tol`` is the relative stopping test of the CONVERGED status.

    Returns:
        :class:`Solution` (``nu`` zero: the dynamics multipliers are not formed; ``kappa``
        zero; ``objective`` filled in by the driver).
    """
    dtype = ocp.B.dtype
    ok_in = jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in jax.tree.leaves(ocp)]))
    ocp = jax.tree.map(lambda a: jnp.where(ok_in, a, jnp.zeros_like(a)), ocp)
    eye_R = jnp.broadcast_to(jnp.eye(ocp.nu, dtype=dtype), ocp.R.shape)
    ocp = ocp._replace(R=jnp.where(ok_in, ocp.R, eye_R))
    P, f, G, g, soft, rho, Gam, x_free = condense(ocp)
    Pc = jax.scipy.linalg.cho_factor(P)
    PiGt = jax.scipy.linalg.cho_solve(Pc, G.T)  # P^-1 G'
    Pif = jax.scipy.linalg.cho_solve(Pc, f)
    H = G @ PiGt
    h = g + G @ Pif
    # row scaling: diag(H) = 1 where a row acts on U (y = D y_hat)
    dH = jnp.diagonal(H)
    D = jnp.where(dH > 0, 1.0 / jnp.sqrt(jnp.where(dH > 0, dH, 1.0)), 1.0)
    Hs = D[:, None] * H * D[None, :]
    hs = D * h
    cap = jnp.where(soft > 0, rho / D, jnp.inf)
    r = jnp.maximum(jnp.diagonal(Hs), jnp.max(jnp.maximum(-Hs, 0.0), axis=1))
    Hp = jnp.maximum(Hs, 0.0) + jnp.diag(r)
    Hm = jnp.maximum(-Hs, 0.0) + jnp.diag(r)
    s = _S * (1.0 + jnp.max(jnp.abs(hs)))
    hp = jnp.maximum(hs, 0.0) + s
    hm = jnp.maximum(-hs, 0.0) + s

    def body(_, y):
        y = y * (hm + Hm @ y) / (hp + Hp @ y)
        return jnp.minimum(y, cap)

    y = lax.fori_loop(0, max_iter, body, jnp.ones_like(hs))
    grad = Hs @ y + hs
    # natural residual of the box-constrained dual (0 <= y <= cap): y - clip(y - grad)
    pg = y - jnp.clip(y - grad, 0.0, cap)
    residual = jnp.max(jnp.abs(pg)) / (1.0 + jnp.max(jnp.abs(hs)))
    U = -(Pif + PiGt @ (D * y))
    u = U.reshape(ocp.N, ocp.nu)
    x = x_free + jnp.einsum("tia,a->ti", Gam, U)
    finite = ok_in & jnp.all(jnp.isfinite(u)) & jnp.all(jnp.isfinite(x))
    converged = residual <= params.tol
    at_penalty = jnp.any((soft > 0) & (y >= cap * (1.0 - 1e-9)))
    status = jnp.where(
        ~finite,
        Status.NONFINITE,
        jnp.where(
            converged, jnp.where(at_penalty, Status.INFEASIBLE, Status.CONVERGED), Status.MAX_ITER
        ),
    )
    zero = jnp.zeros((), dtype)
    return Solution(
        u=jnp.where(finite, u, 0.0),
        x=jnp.where(finite, x, 0.0),
        nu=jnp.zeros_like(x),
        objective=zero,
        kappa=zero,
        iterations=jnp.asarray(max_iter, jnp.int32),
        residual=jnp.where(finite, residual, jnp.inf),
        status=jnp.asarray(status, jnp.int32),
    )
