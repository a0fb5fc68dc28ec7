"""Fast MPC: log barrier + infeasible-start Newton method for the linear OCP.

Paper 000 Sec. III (after Wang & Boyd, "Fast model predictive control using online
optimization"): the inequalities are replaced by a log barrier weighted by kappa (Eq. 17) and
the equality-constrained barrier problem is solved by the infeasible-start Newton method
(Eqs. 18-23, Algorithm 1) with the structured step of :mod:`rvdjax.kkt` (Eqs. 24-26).

Three modes (DESIGN §3):

* ``paper``: fixed kappa (0.05), at most 10 Newton iterations, alpha = 0.01, beta = 0.95,
  backtracking on the residual norm — Algorithm 1 as published. It returns the barrier
  problem's iterate, not the QP optimum (on a cold start its plan costs 15-35 % more). It
  starts by default from the states the warm-start inputs produce (``paper_start``), so the
  dynamics hold at every iterate; kappa is a per-problem tuning value (the scenarios set it).
* ``accurate`` (default): barrier continuation with *primal-dual* Newton steps. The barrier
  weight follows Mehrotra's rule kappa = sigma * gap / m, sigma = (gap_affine / gap)^3, with a
  predictor and a corrector solve sharing one Riccati factorisation; it stops when the
  complementarity gap (the duality-gap bound) is below ``tol`` relative to the objective and
  the dual residual below 100 ``tol`` relative to the gradient. 9-25 iterations; its answer
  matches Clarabel. Primal-dual rather than primal Newton steps because after each kappa cut
  the primal barrier Hessian kappa / s^2 is the curvature of the *old* centre: the step
  overshoots the active rows and backtracks for several iterations, whereas the dual
  estimate lam / s gives the new centre of each row in one step.
* ``barrier``: the primal barrier continuation of the paper's method run to convergence
  (kappa / 10 once the Newton decrement shows the iterate is centred, Armijo on the barrier
  objective); ~35 iterations. Kept for comparison and as the literal method.

Soft state rows (exact L1 penalty rho, see :mod:`rvdjax.ocp`) are handled without slack
variables: for one row with violation g = F x - f, the barrier problem's slack
min_s rho s - kappa log s - kappa log(s - g) has the closed form
s = (rho g + 2 kappa + sqrt(rho^2 g^2 + 4 kappa^2)) / (2 rho), so eliminating it leaves a
smooth convex penalty phi(g) of the state alone (partial minimisation preserves convexity and
leaves the Newton system's structure untouched). phi(g) -> rho max(0, g) as kappa -> 0, and it
is defined for every g: the start never needs to satisfy the state constraints. Only the hard
input rows need a strictly feasible start; u = 0 is one (``validate_ocp`` checks fu > 0),
and a warm start is pulled towards 0 until it is one.

Stopping tests are relative to the problem's scale (the RVD costs are ~1e7 with Riccati
velocity weights ~1e6, so absolute tolerances never trigger): the primal residual relative to
1 + max|x|, the dual residual relative to 1 + max|gradient|.

Every loop has a fixed iteration cap and a per-problem "done" mask, so ``jax.vmap`` of
:func:`solve` runs one program for a whole batch; finished or failed problems are frozen and
every branch is NaN-safe, so one bad problem cannot poison a batch.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from rvdjax.kkt import KKT_SOLVERS, riccati_apply, riccati_factor
from rvdjax.ocp import OCP

__all__ = [
    "SolverSettings",
    "Solution",
    "Status",
    "solve",
    "solve_batch",
    "solve_if",
    "drift_plan",
    "shift_solution",
    "objective",
    "max_violation",
]


class Status:
    """Integer status codes of a solve (``Solution.status``)."""

    CONVERGED = 0  # stopping test met
    MAX_ITER = 1  # iteration cap reached; the last iterate is returned
    INFEASIBLE = 2  # state constraints cannot be met (soft penalty active at the optimum),
    #                 or no strictly feasible input exists
    NONFINITE = 3  # the step became non-finite; the last finite iterate is returned

    names = ("converged", "max_iter", "infeasible", "nonfinite")

    @classmethod
    def name(cls, code: int) -> str:
        return cls.names[int(code)]

    @classmethod
    def counts(cls, status, active):
        """(4,) number of steps with each status among the ``active`` ones (a closed loop's
        per-step statuses; idle steps are not counted)."""
        return jnp.stack([jnp.sum(active & (status == k)) for k in range(len(cls.names))])


@dataclasses.dataclass(frozen=True)
class SolverSettings:
    """Static solver configuration (hashable: a change recompiles).

    Attributes:
        mode: "paper" (fixed kappa, Algorithm 1 of paper 000), "accurate" (primal-dual
            barrier continuation, the default) or "barrier" (primal barrier continuation).
        method: "riccati" (structured step) or "dense" (ISNM, dense KKT solve).
        kappa: barrier weight in paper mode (paper 000 Sec. IV.A: 0.05).
        max_iter: Newton iteration cap.
        alpha, beta: backtracking line-search parameters (paper 000: 0.01, 0.95).
        tol: relative tolerance: residual (paper mode), gap (accurate, barrier modes).
        max_line_search: cap on backtracking steps per iteration (when it is reached the
            last, smallest step is taken).
        kappa0_rel: accurate/barrier modes: first kappa = kappa0_rel * (1 + |J(start)|) / m.
        kappa_factor: barrier mode: kappa is divided by this when the iterate is centred.
        centring: barrier mode: centred when decrement^2 / 2 <= centring * m * kappa.
        backend: "rvdjax" (this solver) or "clarabel": the same OCP solved by Clarabel on the
            host through ``jax.pure_callback`` — the reference "Clarabel in the loop" for any
            jitted closed loop (not differentiable; batches are solved one by one).
        violation_tol: a soft state row counts as violated above this distance (row-normalised
            units of the state, e.g. metres).
        paper_start: paper mode's starting states. "feasible" (default): the states the
            warm-start inputs produce through the dynamics, so the equality residual is zero
            from the first iterate and an iterate cut at ``max_iter`` is a flyable plan.
            "warm": the warm start's own states (Algorithm 1's infeasible start, paper 000
            Sec. III.D: "the solution may not be primal feasible"). Measured: with "warm",
            10 iterations leave the thesis cases' plans dynamically inconsistent and the
            flown u_0 breaches the 100 m keep-out by 46 m (README, paper mode).
            "track": feasible, from inputs that follow the warm start's states from the new
            x0 (the LQR correction with the OCP's own Q, R; one extra Riccati solve), so the
            start stays near a plan that met the state rows. Measured: disturbed POSEIDYN
            runs dock 5/8 and 8/8 instead of 4/8 and 0/8; the thesis cases fly worse.
    """

    mode: str = "accurate"
    method: str = "riccati"
    kappa: float = 0.05
    max_iter: int = 100
    alpha: float = 0.01
    beta: float = 0.5
    tol: float = 1e-9
    max_line_search: int = 40
    kappa0_rel: float = 1.0
    kappa_factor: float = 10.0
    centring: float = 1.0
    violation_tol: float = 1e-6
    backend: str = "rvdjax"
    paper_start: str = "feasible"

    def __post_init__(self):
        if self.mode not in ("paper", "accurate", "barrier"):
            raise ValueError(f"mode must be 'paper', 'accurate' or 'barrier', got {self.mode!r}")
        if self.paper_start not in ("feasible", "warm", "track"):
            raise ValueError(
                f"paper_start must be 'feasible', 'warm' or 'track', got {self.paper_start!r}"
            )
        if self.backend not in ("rvdjax", "clarabel"):
            raise ValueError(f"backend must be 'rvdjax' or 'clarabel', got {self.backend!r}")
        if self.method not in KKT_SOLVERS:
            raise ValueError(f"method must be one of {sorted(KKT_SOLVERS)}, got {self.method!r}")
        if not self.kappa > 0:
            raise ValueError(f"kappa must be > 0, got {self.kappa}")
        if not (isinstance(self.max_iter, int) and self.max_iter >= 1):
            raise ValueError(f"max_iter must be an integer >= 1, got {self.max_iter!r}")
        if not 0 < self.alpha < 0.5:
            raise ValueError(f"alpha must be in (0, 0.5), got {self.alpha}")
        if not 0 < self.beta < 1:
            raise ValueError(f"beta must be in (0, 1), got {self.beta}")
        if not self.tol > 0:
            raise ValueError(f"tol must be > 0, got {self.tol}")
        if not self.kappa_factor > 1:
            raise ValueError(f"kappa_factor must be > 1, got {self.kappa_factor}")

    @classmethod
    def paper(cls, **overrides) -> SolverSettings:
        """Paper 000 Sec. IV.A: kappa = 0.05, <= 10 iterations, alpha = 0.01, beta = 0.95.

        Algorithm 1 backtracks until the residual decreases, without a cap; the fixed-shape
        loop needs one, so it is set where t has shrunk to 0.95^300 ~ 2e-7. (A cap of 40,
        t >= 0.13, made the solver take steps that the line search had rejected: POSEIDYN
        then spent 6.4 N s instead of 2.9, and fastmpc-3d 34.87 kN s instead of 33.59.)"""
        base = dict(
            mode="paper",
            kappa=0.05,
            max_iter=10,
            alpha=0.01,
            beta=0.95,
            tol=1e-9,
            max_line_search=300,
        )
        base.update(overrides)
        return cls(**base)

    @classmethod
    def accurate(cls, **overrides) -> SolverSettings:
        return cls(**overrides)


class Solution(NamedTuple):
    """Result of one solve. Batched solves carry a leading batch axis on every field.

    Attributes:
        u: (N, nu) planned inputs u_k .. u_{k+N-1}.
        x: (N, nx) planned states x_{k+1} .. x_{k+N}.
        nu: (N, nx) multipliers of the dynamics (see :mod:`rvdjax.kkt` for the sign).
        objective: QP objective at (u, x), soft rows as rho * max(0, g) (no barrier term).
        kappa: barrier weight of the returned iterate.
        iterations: Newton iterations taken.
        residual: relative KKT residual of the barrier problem at the returned iterate.
        status: :class:`Status` code.
    """

    u: jnp.ndarray
    x: jnp.ndarray
    nu: jnp.ndarray
    objective: jnp.ndarray
    kappa: jnp.ndarray
    iterations: jnp.ndarray
    residual: jnp.ndarray
    status: jnp.ndarray


# --------------------------------------------------------------------------------------------
# Cost, barrier and residuals (pure functions of one problem's arrays)


class _Rows(NamedTuple):
    """Inequality data with masked rows neutralised (zero row, offset 1, weight 0)."""

    Fu: jnp.ndarray
    fu: jnp.ndarray
    wu: jnp.ndarray
    Fx: jnp.ndarray
    fx: jnp.ndarray
    wx: jnp.ndarray
    rho: jnp.ndarray


def _rows(ocp: OCP) -> _Rows:
    on_u = ocp.u_mask > 0
    on_x = ocp.x_mask > 0
    return _Rows(
        Fu=jnp.where(on_u[..., None], ocp.Fu, 0.0),
        fu=jnp.where(on_u, ocp.fu, 1.0),
        wu=ocp.u_mask,
        Fx=jnp.where(on_x[..., None], ocp.Fx, 0.0),
        fx=jnp.where(on_x, ocp.fx, 1.0),
        wx=ocp.x_mask,
        rho=jnp.where(on_x, ocp.rho, 1.0),
    )


def _soft_slack_parts(g, rho, kappa):
    """(s, s - g, b, root) of the optimal slack of one soft row (module docstring).

    Written with cancellation-free forms of rho g + sqrt(.) and sqrt(.) - rho g.
    """
    rg = rho * g
    root = jnp.sqrt(rg * rg + 4.0 * kappa * kappa)
    four_k2 = 4.0 * kappa * kappa
    a = jnp.where(rg >= 0, rg + root, four_k2 / (root - jnp.minimum(rg, 0.0)))  # rho g + root
    b = jnp.where(rg <= 0, root - rg, four_k2 / (root + jnp.maximum(rg, 0.0)))  # root - rho g
    return (a + 2.0 * kappa) / (2.0 * rho), (b + 2.0 * kappa) / (2.0 * rho), b, root


def _soft_slack(g, rho, kappa):
    """Optimal slack s of a soft row and s - g, both > 0."""
    s, s_minus_g, _, _ = _soft_slack_parts(g, rho, kappa)
    return s, s_minus_g


def _soft_penalty(g, rho, kappa):
    """phi(g), phi'(g), phi''(g) of the slack-eliminated soft barrier (module docstring)."""
    s, s_minus_g, b, root = _soft_slack_parts(g, rho, kappa)
    phi = rho * s - kappa * jnp.log(s) - kappa * jnp.log(s_minus_g)
    d1 = kappa / s_minus_g
    d2 = kappa / (s_minus_g * s_minus_g) * (0.5 * b / root)
    return phi, d1, d2


def _u_slack(rows: _Rows, u):
    return rows.fu - jnp.einsum("tij,tj->ti", rows.Fu, u)


def _x_violation(rows: _Rows, x):
    return jnp.einsum("tij,tj->ti", rows.Fx, x) - rows.fx


def objective(ocp: OCP, u, x):
    """QP objective (paper 000 Eq. 1a, plus the exact penalty of the soft state rows)."""
    e = x - ocp.x_ref
    quad = jnp.einsum("ti,tij,tj->", e, ocp.Q, e) + jnp.einsum("ti,tij,tj->", u, ocp.R, u)
    lin = jnp.sum(ocp.q * x) + jnp.sum(ocp.r * u)
    rows = _rows(ocp)
    pen = jnp.sum(rows.wx * rows.rho * jnp.maximum(_x_violation(rows, x), 0.0))
    return quad + lin + pen


def max_violation(ocp: OCP, u, x):
    """Largest row-normalised violation of the (soft) state rows and the input rows."""
    rows = _rows(ocp)
    gx = _x_violation(rows, x) / jnp.maximum(jnp.linalg.norm(rows.Fx, axis=-1), 1e-300)
    gu = -_u_slack(rows, u) / jnp.maximum(jnp.linalg.norm(rows.Fu, axis=-1), 1e-300)
    vx = jnp.max(jnp.where(rows.wx > 0, gx, -jnp.inf), initial=0.0)
    vu = jnp.max(jnp.where(rows.wu > 0, gu, -jnp.inf), initial=0.0)
    return jnp.maximum(jnp.maximum(vx, vu), 0.0)


def _gradient(ocp: OCP, rows: _Rows, u, x, kappa):
    """Gradient blocks of cost + barrier (requires strictly feasible input rows)."""
    su = _u_slack(rows, u)
    du = rows.wu / su
    _, d1, _ = _soft_penalty(_x_violation(rows, x), rows.rho, kappa)
    g_u = (
        2.0 * jnp.einsum("tij,tj->ti", ocp.R, u)
        + ocp.r
        + kappa * jnp.einsum("tij,ti->tj", rows.Fu, du)
    )
    g_x = (
        2.0 * jnp.einsum("tij,tj->ti", ocp.Q, x - ocp.x_ref)
        + ocp.q
        + jnp.einsum("tij,ti->tj", rows.Fx, rows.wx * d1)
    )
    return g_u, g_x


def _hessian(ocp: OCP, rows: _Rows, u, x, kappa):
    """Hessian blocks Phi_u (N, nu, nu), Phi_x (N, nx, nx) (paper 000 Eq. 21: 2H + barrier)."""
    su = _u_slack(rows, u)
    wu2 = kappa * rows.wu / (su * su)
    _, _, d2 = _soft_penalty(_x_violation(rows, x), rows.rho, kappa)
    Phi_u = 2.0 * ocp.R + jnp.einsum("tki,tk,tkj->tij", rows.Fu, wu2, rows.Fu)
    Phi_x = 2.0 * ocp.Q + jnp.einsum("tki,tk,tkj->tij", rows.Fx, rows.wx * d2, rows.Fx)
    return Phi_u, Phi_x


def _dyn_residual(ocp: OCP, u, x):
    """r_p: x_{t+1} - A_t x_t - B_t u_t - c_t, shape (N, nx)."""
    x_prev = jnp.concatenate([ocp.x0[None], x[:-1]])
    return x - jnp.einsum("tij,tj->ti", ocp.A, x_prev) - jnp.einsum("tij,tj->ti", ocp.B, u) - ocp.c


def _dual_residual(ocp: OCP, g_u, g_x, nu):
    """r_d = grad f + C^T nu, split into the u and x blocks."""
    r_u = g_u - jnp.einsum("tij,ti->tj", ocp.B, nu)
    At_nu_next = jnp.einsum("tij,ti->tj", ocp.A[1:], nu[1:])
    r_x = g_x + nu - jnp.concatenate([At_nu_next, jnp.zeros_like(nu[:1])])
    return r_u, r_x


def _residual_norms(ocp, rows, u, x, nu, kappa):
    """(||r||_2 for the line search, relative inf-norm residual for stopping)."""
    g_u, g_x = _gradient(ocp, rows, u, x, kappa)
    r_u, r_x = _dual_residual(ocp, g_u, g_x, nu)
    r_p = _dyn_residual(ocp, u, x)
    norm2 = jnp.sqrt(jnp.sum(r_u**2) + jnp.sum(r_x**2) + jnp.sum(r_p**2))
    d_scale = 1.0 + jnp.maximum(jnp.max(jnp.abs(g_u)), jnp.max(jnp.abs(g_x)))
    p_scale = 1.0 + jnp.maximum(jnp.max(jnp.abs(x)), jnp.max(jnp.abs(ocp.x0)))
    rel_d = jnp.maximum(jnp.max(jnp.abs(r_u)), jnp.max(jnp.abs(r_x))) / d_scale
    rel_p = jnp.max(jnp.abs(r_p)) / p_scale
    return norm2, rel_d, rel_p


# --------------------------------------------------------------------------------------------
# Starting point


def _track_plan(ocp: OCP, u_prev, x_prev, settings):
    """Inputs that follow a previous plan from the new x0: the minimiser of
    sum (x - x_prev)' Q (x - x_prev) + (u - u_prev)' R (u - u_prev) subject to the dynamics
    (one Riccati solve: the plan's own weights turn the deviation of x0 into the LQR
    correction). Its states stay near the previous plan, which met the state rows, while
    obeying the dynamics from the measured x0."""
    x_drift = _drift(ocp, u_prev)
    Phi_u = 2.0 * ocp.R
    Phi_x = 2.0 * ocp.Q
    g_u = jnp.zeros_like(u_prev)
    g_x = 2.0 * jnp.einsum("tij,tj->ti", ocp.Q, x_drift - x_prev)
    step = KKT_SOLVERS[settings.method](
        ocp.A, ocp.B, Phi_u, Phi_x, g_u, g_x, jnp.zeros_like(x_prev)
    )
    return jnp.where(jnp.all(jnp.isfinite(step.du)), u_prev + step.du, u_prev)


def _pull_inside(rows: _Rows, u, margin=0.99):
    """Scale each stage's u towards 0 (strictly feasible) until strictly feasible."""
    Fu_u = jnp.einsum("tij,tj->ti", rows.Fu, u)
    ratio = jnp.where((rows.wu > 0) & (Fu_u > 0), rows.fu / jnp.where(Fu_u > 0, Fu_u, 1.0), 2.0)
    theta = jnp.minimum(1.0, margin * jnp.min(ratio, axis=-1))
    return u * theta[:, None]


def _drift(ocp: OCP, u):
    """States from propagating x0 with inputs u (a primal-feasible x for the start)."""

    def step(x, stage):
        A_t, B_t, c_t, u_t = stage
        x_next = A_t @ x + B_t @ u_t + c_t
        return x_next, x_next

    _, x = lax.scan(step, ocp.x0, (ocp.A, ocp.B, ocp.c, u))
    return x


class Plan(NamedTuple):
    """A warm start: u (N, nu), x (N, nx), nu (N, nx) — e.g. :func:`shift_solution`."""

    u: jnp.ndarray
    x: jnp.ndarray
    nu: jnp.ndarray


def shift_solution(sol: Solution | Plan) -> Plan:
    """Shift a plan one stage forward for the next MPC step, repeating the last stage."""

    def shift(a):
        return jnp.concatenate([a[1:], a[-1:]], axis=0)

    return Plan(shift(sol.u), shift(sol.x), shift(sol.nu))


# --------------------------------------------------------------------------------------------
# Newton iterations


class _State(NamedTuple):
    """Carry of the Newton loop (one problem)."""

    u: jnp.ndarray  # (N, nu)
    x: jnp.ndarray  # (N, nx)
    nu: jnp.ndarray  # (N, nx)
    kappa: jnp.ndarray  # ()
    it: jnp.ndarray  # () iterations taken
    done: jnp.ndarray  # () bool: converged or failed
    status: jnp.ndarray  # () int
    rel_res: jnp.ndarray  # () relative residual at (u, x, nu) for kappa


def _m_eff(rows: _Rows):
    """Number of barrier terms: one per input row, two (s >= 0, s >= g) per soft row."""
    return jnp.sum(rows.wu) + 2.0 * jnp.sum(rows.wx)


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


def _ray(ocp, rows, s, du, dx, dnu) -> _Ray:
    e = s.x - ocp.x_ref
    Qe = jnp.einsum("tij,tj->ti", ocp.Q, e)
    Ru = jnp.einsum("tij,tj->ti", ocp.R, s.u)
    Qdx = jnp.einsum("tij,tj->ti", ocp.Q, dx)
    Rdu = jnp.einsum("tij,tj->ti", ocp.R, du)
    grad_u = 2.0 * Ru + ocp.r
    grad_x = 2.0 * Qe + ocp.q
    ru0, rx0 = _dual_residual(ocp, grad_u, grad_x, s.nu)
    ru1, rx1 = _dual_residual(ocp, 2.0 * Rdu, 2.0 * Qdx, dnu)
    return _Ray(
        su=_u_slack(rows, s.u),
        dsu=-jnp.einsum("tij,tj->ti", rows.Fu, du),
        g=_x_violation(rows, s.x),
        dg=jnp.einsum("tij,tj->ti", rows.Fx, dx),
        quad=jnp.sum(e * Qe) + jnp.sum(s.u * Ru) + jnp.sum(ocp.q * s.x) + jnp.sum(ocp.r * s.u),
        dquad=jnp.sum(grad_u * du) + jnp.sum(grad_x * dx),
        ddquad=jnp.sum(dx * Qdx) + jnp.sum(du * Rdu),
        ru0=ru0,
        ru1=ru1,
        rx0=rx0,
        rx1=rx1,
        rp=_dyn_residual(ocp, s.u, s.x),
        g_scale=jnp.maximum(jnp.max(jnp.abs(grad_u)), jnp.max(jnp.abs(grad_x))),
    )


def _ray_barrier_objective(rows, ray: _Ray, t, kappa):
    """f_kappa(z + t dz) (paper 000 Eq. 17 with the soft rows' phi); +inf outside."""
    su = ray.su + t * ray.dsu
    inside = jnp.all((su > 0) | (rows.wu == 0))
    log_su = jnp.log(jnp.where(su > 0, su, 1.0))
    phi, _, _ = _soft_penalty(ray.g + t * ray.dg, rows.rho, kappa)
    f = ray.quad + t * ray.dquad + t * t * ray.ddquad
    f = f - kappa * jnp.sum(rows.wu * log_su) + jnp.sum(rows.wx * phi)
    return jnp.where(inside, f, jnp.inf)


def _ray_residual(ocp, rows, ray: _Ray, t, kappa, x_scale):
    """(||r||_2, relative inf-norm residual) at (z, nu) + t (dz, dnu)."""
    su = ray.su + t * ray.dsu
    _, d1, _ = _soft_penalty(ray.g + t * ray.dg, rows.rho, kappa)
    gb_u = kappa * jnp.einsum("tij,ti->tj", rows.Fu, rows.wu / jnp.where(su > 0, su, 1.0))
    gb_x = jnp.einsum("tij,ti->tj", rows.Fx, rows.wx * d1)
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


def _backtrack(accept, t0, beta, max_steps):
    """Shrink t by beta until ``accept(t)`` holds (bounded; returns the last t tried)."""

    def cond(c):
        t, ok, n = c
        return (~ok) & (n < max_steps)

    def body(c):
        t, _, n = c
        t = beta * t
        return t, accept(t), n + 1

    t, _, _ = lax.while_loop(cond, body, (t0, accept(t0), 0))
    return t


def _newton_iteration(ocp, rows, m_eff, x_scale, s: _State, settings: SolverSettings):
    Phi_u, Phi_x = _hessian(ocp, rows, s.u, s.x, s.kappa)
    g_u, g_x = _gradient(ocp, rows, s.u, s.x, s.kappa)
    r_p = _dyn_residual(ocp, s.u, s.x)
    step = KKT_SOLVERS[settings.method](ocp.A, ocp.B, Phi_u, Phi_x, g_u, g_x, r_p)
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
    dec2 = jnp.einsum("ti,tij,tj->", du, Phi_u, du) + jnp.einsum("ti,tij,tj->", dx, Phi_x, dx)

    ray = _ray(ocp, rows, s, du, dx, dnu)
    t0 = _step_length(rows, ray, settings.beta)
    if settings.mode == "paper":
        # Algorithm 1, second loop: ||r(z + t dz, nu + t dnu)|| <= (1 - alpha t) ||r(z, nu)||.
        r0, _ = _ray_residual(ocp, rows, ray, 0.0, s.kappa, x_scale)

        def accept(t):
            return (
                _ray_residual(ocp, rows, ray, t, s.kappa, x_scale)[0]
                <= (1.0 - settings.alpha * t) * r0
            )
    else:
        # Armijo on the barrier objective f_kappa (Boyd & Vandenberghe Alg. 9.2 / 10.2): the
        # iterate stays primal feasible, so f_kappa is the natural merit function, and unlike
        # the residual norm it does not mix units of cost gradient and of state.
        f0 = _ray_barrier_objective(rows, ray, 0.0, s.kappa)

        def accept(t):
            return _ray_barrier_objective(rows, ray, t, s.kappa) <= f0 - settings.alpha * t * dec2

    t = _backtrack(accept, t0, settings.beta, settings.max_line_search)
    u = s.u + t * du
    x = s.x + t * dx

    if settings.mode == "paper":
        nu = s.nu + t * dnu
        _, rel_res = _ray_residual(ocp, rows, ray, t, s.kappa, x_scale)
        kappa = s.kappa
        converged = rel_res <= settings.tol
    else:
        # The feasible Newton method takes the KKT solve's multiplier estimate.
        nu = s.nu + dnu
        rel_p = jnp.max(jnp.abs((1.0 - t) * ray.rp)) / x_scale
        rel_res = jnp.maximum(0.5 * dec2, m_eff * s.kappa)  # gap bound, refined after the loop
        J = ray.quad + t * ray.dquad + t * t * ray.ddquad
        J = J + jnp.sum(rows.wx * rows.rho * jnp.maximum(ray.g + t * ray.dg, 0.0))
        scale = 1.0 + jnp.abs(J)
        centred = (0.5 * dec2 <= settings.centring * m_eff * s.kappa) & (rel_p <= 1e-6)
        converged = (
            (m_eff * s.kappa <= settings.tol * scale)
            & (0.5 * dec2 <= settings.tol * scale)
            & (rel_p <= settings.tol)
        )
        kappa = jnp.where(centred & ~converged, s.kappa / settings.kappa_factor, s.kappa)

    it = s.it + 1
    status = jnp.where(
        ~finite, Status.NONFINITE, jnp.where(converged, Status.CONVERGED, Status.MAX_ITER)
    )
    done = converged | ~finite
    # A failed step keeps the last finite iterate.
    keep = lambda new, old: jnp.where(finite, new, old)  # noqa: E731
    return _State(
        u=keep(u, s.u),
        x=keep(x, s.x),
        nu=keep(nu, s.nu),
        kappa=keep(kappa, s.kappa),
        it=it,
        done=done,
        status=status,
        rel_res=keep(rel_res, s.rel_res),
    )


class _PDState(NamedTuple):
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


def _pd_step(ocp, rows, st: _PDState, kkt, su, sx, tau_u, tau_x, tau_s, settings):
    """One solve of the primal-dual Newton system for complementarity targets tau.

    Linearising lam su = tau_u, mu sx = tau_x, pi s = tau_s and rho = mu + pi, then eliminating
    the row variables leaves the stage-structured system of :mod:`rvdjax.kkt` with input-row
    weight lam/su and soft-row weight a c / (a + c) (a = mu/sx, c = pi/s). Returns the full
    steps of every variable.
    """
    Du = rows.wu * st.lam / su
    a = st.mu / sx
    c = st.pi / st.s
    h = tau_x / sx + tau_s / st.s - rows.rho
    g_u = (
        2.0 * jnp.einsum("tij,tj->ti", ocp.R, st.u)
        + ocp.r
        + jnp.einsum("tij,ti->tj", rows.Fu, rows.wu * tau_u / su)
    )
    g_x = (
        2.0 * jnp.einsum("tij,tj->ti", ocp.Q, st.x - ocp.x_ref)
        + ocp.q
        + jnp.einsum("tij,ti->tj", rows.Fx, rows.wx * (tau_x / sx - a * h / (a + c)))
    )
    step = _kkt_solve(ocp, *kkt, g_u, g_x, _dyn_residual(ocp, st.u, st.x), settings)
    Fdu = jnp.einsum("tij,tj->ti", rows.Fu, step.du)
    Fdx = jnp.einsum("tij,tj->ti", rows.Fx, step.dx)
    ds = (a * Fdx + h) / (a + c)
    dlam = tau_u / su - st.lam + Du * Fdu
    dmu = tau_x / sx - st.mu + a * (Fdx - ds)
    dpi = tau_s / st.s - st.pi - c * ds
    dsu = -Fdu
    dsx = -Fdx + ds
    return step, ds, dlam, dmu, dpi, dsu, dsx


def _max_step(pairs, wmask):
    """Largest alpha in (0, 1] keeping every (value + alpha * step) >= 0 on active rows."""
    alpha = jnp.asarray(1.0)
    for v, dv, w in zip(*pairs, wmask, strict=True):
        shrink = (w > 0) & (dv < 0)
        ratio = jnp.where(shrink, -v / jnp.where(shrink, dv, -1.0), jnp.inf)
        alpha = jnp.minimum(alpha, jnp.min(ratio))
    return alpha


def _pd_iteration(ocp, rows, m_eff, x_scale, st: _PDState, settings: SolverSettings):
    """Mehrotra predictor-corrector step (Nocedal & Wright Alg. 16.4; Wright 1997, Ch. 10).

    The barrier weight follows kappa = sigma * gap / m with sigma = (gap_affine / gap)^3: the
    barrier continuation with the schedule chosen by the iterate. Both solves reuse one
    Riccati factorisation.
    """
    su = _u_slack(rows, st.u)
    sx = rows.fx - jnp.einsum("tij,tj->ti", rows.Fx, st.x) + st.s
    Du = rows.wu * st.lam / su
    a = st.mu / sx
    c = st.pi / st.s
    Phi_u = 2.0 * ocp.R + jnp.einsum("tki,tk,tkj->tij", rows.Fu, Du, rows.Fu)
    Phi_x = 2.0 * ocp.Q + jnp.einsum("tki,tk,tkj->tij", rows.Fx, rows.wx * a * c / (a + c), rows.Fx)
    factor = riccati_factor(ocp.A, ocp.B, Phi_u, Phi_x) if settings.method == "riccati" else None
    kkt = (Phi_u, Phi_x, factor)
    wmask = (rows.wu, rows.wx, rows.wx, rows.wu, rows.wx, rows.wx)

    # Predictor: the affine-scaling direction (tau = 0).
    zero_u, zero_x = jnp.zeros_like(su), jnp.zeros_like(sx)
    aff = _pd_step(ocp, rows, st, kkt, su, sx, zero_u, zero_x, zero_x, settings)
    _, ds_a, dlam_a, dmu_a, dpi_a, dsu_a, dsx_a = aff
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
    kappa = sigma * gap / jnp.maximum(m_eff, 1.0)

    # Corrector: centring plus Mehrotra's second-order term.
    step, ds, dlam, dmu, dpi, dsu, dsx = _pd_step(
        ocp,
        rows,
        st,
        kkt,
        su,
        sx,
        kappa - dsu_a * dlam_a,
        kappa - dsx_a * dmu_a,
        kappa - ds_a * dpi_a,
        settings,
    )
    finite = _all_finite((step, ds, dlam, dmu, dpi))
    alpha = _max_step(((su, sx, st.s, st.lam, st.mu, st.pi), (dsu, dsx, ds, dlam, dmu, dpi)), wmask)
    alpha = jnp.minimum(1.0, 0.99 * alpha)
    alpha = jnp.where(finite, alpha, 0.0)

    def upd(v, dv, w=1.0):
        return v + alpha * jnp.where(finite & (w > 0), dv, 0.0)  # padding rows stay put

    u, x, s_new = upd(st.u, step.du), upd(st.x, step.dx), upd(st.s, ds, rows.wx)
    lam, mu = upd(st.lam, dlam, rows.wu), upd(st.mu, dmu, rows.wx)
    pi = upd(st.pi, dpi, rows.wx)
    nu = upd(st.nu, step.nu - st.nu)
    su_n = _u_slack(rows, u)
    sx_n = rows.fx - jnp.einsum("tij,tj->ti", rows.Fx, x) + s_new
    gap_n = jnp.sum(rows.wu * su_n * lam) + jnp.sum(rows.wx * (sx_n * mu + s_new * pi))

    # Stopping: gap and dual residual relative to the objective / gradient scale.
    e = x - ocp.x_ref
    grad_u = 2.0 * jnp.einsum("tij,tj->ti", ocp.R, u) + ocp.r
    grad_x = 2.0 * jnp.einsum("tij,tj->ti", ocp.Q, e) + ocp.q
    r_u, r_x = _dual_residual(
        ocp,
        grad_u + jnp.einsum("tij,ti->tj", rows.Fu, rows.wu * lam),
        grad_x + jnp.einsum("tij,ti->tj", rows.Fx, rows.wx * mu),
        nu,
    )
    r_s = rows.wx * (rows.rho - mu - pi)
    d_scale = 1.0 + jnp.maximum(jnp.max(jnp.abs(grad_u)), jnp.max(jnp.abs(grad_x)))
    rel_d = jnp.maximum(
        jnp.maximum(jnp.max(jnp.abs(r_u)), jnp.max(jnp.abs(r_x))) / d_scale,
        jnp.max(jnp.abs(r_s)) / (1.0 + jnp.max(rows.wx * rows.rho)),
    )
    J = objective(ocp, u, x)
    scale = 1.0 + jnp.abs(J)
    # The dual residual bounds the objective error through ||r_d|| ||z - z*||: 100x the gap
    # tolerance keeps that error below ~tol relative while staying reachable in float64 on
    # long, ill-conditioned horizons.
    converged = (gap_n <= settings.tol * scale) & (rel_d <= 1e2 * settings.tol)
    # Close to the solution the ratios lam/s overflow first: a failed step from an iterate
    # that already meets 10x the tolerances ends the solve as converged at that iterate.
    nearly = (st.gap <= 10.0 * settings.tol * scale) & (st.res <= 1e3 * settings.tol)
    status = jnp.where(
        ~finite,
        jnp.where(nearly, Status.CONVERGED, Status.NONFINITE),
        jnp.where(converged, Status.CONVERGED, Status.MAX_ITER),
    )
    done = converged | ~finite
    return _PDState(u, x, nu, s_new, lam, mu, pi, st.it + 1, done, status, gap_n, rel_d)


def _pd_loop(ocp, rows, m_eff, x_scale, u0, x0s, nu0, kappa0, start_ok, start_status, settings):
    """Run the primal-dual loop from a centred start at kappa0; returns the final state."""
    su = _u_slack(rows, u0)
    # Start on the central path of the soft rows: s minimises rho s - kappa0 log s -
    # kappa0 log(s - g) (closed form, see _soft_slack), so mu s_x = pi s = kappa0 and
    # mu + pi = rho hold from the first iterate, whatever the scale of rho.
    s0, sx = _soft_slack(_x_violation(rows, x0s), rows.rho, kappa0)
    lam = jnp.where(rows.wu > 0, kappa0 / jnp.where(su > 0, su, 1.0), 1.0)
    mu = kappa0 / sx
    pi = kappa0 / s0
    gap = jnp.sum(rows.wu * su * lam) + jnp.sum(rows.wx * (sx * mu + s0 * pi))
    inf = jnp.asarray(jnp.inf, gap.dtype)
    st = _PDState(u0, x0s, nu0, s0, lam, mu, pi, jnp.asarray(0), ~start_ok, start_status, gap, inf)

    def cond(st):
        return (~st.done) & (st.it < settings.max_iter)

    def body(st):
        return _pd_iteration(ocp, rows, m_eff, x_scale, st, settings)

    return lax.while_loop(cond, body, st)


def _kkt_residual(ocp: OCP, u, x, nu, kappa):
    """Optimality residual of the barrier problem: (r_u, r_x, r_p) (paper 000 Eqs. 19-20).

    One definition serves the stopping test, the tests and the implicit derivative.
    """
    rows = _rows(ocp)
    g_u, g_x = _gradient(ocp, rows, u, x, kappa)
    r_u, r_x = _dual_residual(ocp, g_u, g_x, nu)
    return r_u, r_x, _dyn_residual(ocp, u, x)


def _kkt_at(ocp: OCP, u, x, kappa, settings: SolverSettings):
    """Hessian blocks and the factorisation (Riccati method) at a point."""
    rows = _rows(ocp)
    Phi_u, Phi_x = _hessian(ocp, rows, u, x, kappa)
    factor = riccati_factor(ocp.A, ocp.B, Phi_u, Phi_x) if settings.method == "riccati" else None
    return Phi_u, Phi_x, factor


def _kkt_solve(ocp, Phi_u, Phi_x, factor, g_u, g_x, rp, settings: SolverSettings):
    if factor is not None:
        return riccati_apply(factor, g_u, g_x, rp)
    return KKT_SOLVERS[settings.method](ocp.A, ocp.B, Phi_u, Phi_x, g_u, g_x, rp)


def _all_finite(tree):
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in jax.tree.leaves(tree)]))


def _solve_forward(ocp: OCP, settings: SolverSettings, init: Plan | None):
    """The Newton loop; returns the Solution without its objective."""
    rows = _rows(ocp)
    m_eff = _m_eff(rows)
    dtype = ocp.B.dtype
    # Tolerances below ~1e3 machine epsilon are unreachable (float32: 1.2e-4).
    tol = max(settings.tol, 1e3 * float(jnp.finfo(dtype).eps))
    settings = dataclasses.replace(settings, tol=tol)
    inputs_ok = _all_finite(ocp) & (True if init is None else _all_finite(init))
    # Non-finite data would poison every iterate: solve a neutral copy and report the status.
    ocp_safe = jax.tree.map(lambda a: jnp.where(inputs_ok, a, jnp.zeros_like(a)), ocp)
    ocp_safe = ocp_safe._replace(
        R=jnp.where(inputs_ok, ocp.R, jnp.broadcast_to(jnp.eye(ocp.nu, dtype=dtype), ocp.R.shape)),
        fu=jnp.where(inputs_ok, ocp.fu, 1.0),
        fx=jnp.where(inputs_ok, ocp.fx, 1.0),
        rho=jnp.where(inputs_ok, ocp.rho, 1.0),
    )
    ocp = ocp_safe
    rows = _rows(ocp)
    if init is None:
        u0 = jnp.zeros((ocp.N, ocp.nu), dtype)
        nu0 = jnp.zeros((ocp.N, ocp.nx), dtype)
        x_start = None
    else:
        init = jax.tree.map(lambda a: jnp.where(inputs_ok, a, jnp.zeros_like(a)), init)
        u0, nu0, x_start = init.u, init.nu, init.x
    if x_start is not None and settings.mode == "paper" and settings.paper_start == "track":
        u0 = _track_plan(ocp, u0, x_start, settings)
    u0 = _pull_inside(rows, u0)
    # The accurate mode is a feasible-start method; so is paper mode by default (``paper_start
    # = "feasible"``): a run cut at max_iter then still flies a plan that obeys the dynamics.
    # Algorithm 1's literal infeasible start keeps the warm start's states (``"warm"``).
    warm_states = (
        x_start is not None and settings.mode == "paper" and settings.paper_start == "warm"
    )
    x0s = x_start if warm_states else _drift(ocp, u0)
    start_ok = jnp.all(jnp.where(rows.wu > 0, _u_slack(rows, u0) > 0, True))

    if settings.mode == "paper":
        kappa0 = jnp.asarray(settings.kappa, dtype)
    else:
        J0 = objective(ocp, u0, x0s)
        kappa0 = settings.kappa0_rel * (1.0 + jnp.abs(J0)) / jnp.maximum(m_eff, 1.0)
    start_status = jnp.where(
        ~inputs_ok, Status.NONFINITE, jnp.where(start_ok, Status.MAX_ITER, Status.INFEASIBLE)
    )
    s = _State(
        u=u0,
        x=x0s,
        nu=nu0,
        kappa=kappa0,
        it=jnp.asarray(0),
        done=~(start_ok & inputs_ok),
        status=start_status,
        rel_res=jnp.asarray(jnp.inf, dtype),
    )
    x_scale = 1.0 + jnp.maximum(jnp.max(jnp.abs(x0s)), jnp.max(jnp.abs(ocp.x0)))

    if settings.mode == "accurate":
        st = _pd_loop(
            ocp,
            rows,
            m_eff,
            x_scale,
            u0,
            x0s,
            nu0,
            kappa0,
            start_ok & inputs_ok,
            start_status,
            settings,
        )
        # kappa of the returned point: its mean complementarity (the barrier weight of the
        # central-path point it approximates; used by the implicit derivative).
        s = s._replace(
            u=st.u,
            x=st.x,
            nu=st.nu,
            it=st.it,
            status=st.status,
            kappa=st.gap / jnp.maximum(m_eff, 1.0),
            rel_res=st.res,
        )
    else:

        def cond(s):
            return (~s.done) & (s.it < settings.max_iter)

        def body(s):
            return _newton_iteration(ocp, rows, m_eff, x_scale, s, settings)

        s = lax.while_loop(cond, body, s)

    nu = s.nu
    if settings.mode == "barrier":
        # The multipliers of the KKT solve at the returned point (the loop's last estimate
        # belongs to the pre-step point).
        Phi_u, Phi_x, factor = _kkt_at(ocp, s.u, s.x, s.kappa, settings)
        g_u, g_x = _gradient(ocp, rows, s.u, s.x, s.kappa)
        step = _kkt_solve(
            ocp, Phi_u, Phi_x, factor, g_u, g_x, _dyn_residual(ocp, s.u, s.x), settings
        )
        nu = jnp.where(jnp.all(jnp.isfinite(step.nu)), step.nu, s.nu)
    if settings.mode == "accurate":
        residual = s.rel_res  # the primal-dual loop's relative dual residual
    else:
        _, rel_d, rel_p = _residual_norms(ocp, rows, s.u, s.x, nu, s.kappa)
        residual = jnp.maximum(rel_d, rel_p)

    # Converged, but the soft state rows are violated: the hard problem is infeasible.
    violated = max_violation(ocp, s.u, s.x) > settings.violation_tol
    status = jnp.where((s.status == Status.CONVERGED) & violated, Status.INFEASIBLE, s.status)

    def clean(a):
        return jnp.where(jnp.isfinite(a), a, jnp.zeros_like(a))

    sol = Solution(
        u=clean(s.u),
        x=clean(s.x),
        nu=clean(nu),
        objective=jnp.zeros((), dtype),  # filled in by solve(), outside the custom VJP
        kappa=s.kappa,
        iterations=s.it,
        residual=jnp.where(jnp.isfinite(residual), residual, jnp.inf),
        status=status,
    )
    return sol


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def _solve_core(ocp: OCP, settings: SolverSettings, init: Plan | None) -> Solution:
    return _solve_forward(ocp, settings, init)


def _solve_core_fwd(ocp, settings, init):
    sol = _solve_forward(ocp, settings, init)
    # Factorised once here, only when differentiating; the backward pass reuses it.
    kkt = _kkt_at(ocp, sol.u, sol.x, sol.kappa, settings)
    return sol, (ocp, init, sol, kkt)


def _solve_core_bwd(settings, res, sol_bar):
    """Implicit derivative (DESIGN §3): the solution satisfies F(z, nu; theta) = 0 with
    F = (grad f_kappa + C^T nu, C z - b). With J = dF/d(z, nu) (the symmetric KKT matrix, already
    factorised), theta_bar = -(dF/dtheta)^T J^-1 (z_bar, nu_bar): one structured solve, no
    backpropagation through the Newton iterations. kappa is held at its final value.
    """
    ocp, init, sol, (Phi_u, Phi_x, factor) = res
    # J w = (u_bar, x_bar, nu_bar): the Newton system with g = -z_bar, r_p = -nu_bar.
    w = _kkt_solve(ocp, Phi_u, Phi_x, factor, -sol_bar.u, -sol_bar.x, -sol_bar.nu, settings)
    w_u, w_x, w_nu = w.du, w.dx, w.nu

    def F(o):
        return _kkt_residual(o, sol.u, sol.x, sol.nu, sol.kappa)

    _, vjp = jax.vjp(F, ocp)
    (ocp_bar,) = vjp((-w_u, -w_x, -w_nu))
    ok = (sol.status != Status.NONFINITE) & _all_finite((w_u, w_x, w_nu))
    ocp_bar = jax.tree.map(lambda a: jnp.where(ok & jnp.isfinite(a), a, 0.0), ocp_bar)
    init_bar = None if init is None else jax.tree.map(jnp.zeros_like, init)
    return ocp_bar, init_bar


_solve_core.defvjp(_solve_core_fwd, _solve_core_bwd)


def _clarabel_host(*leaves):
    """Host side of the Clarabel backend: one OCP as NumPy arrays -> solution arrays."""
    import numpy as np

    from rvdjax.peers import solve_clarabel
    from rvdjax.qp import split_solution, to_qp

    ocp = OCP(*(np.asarray(a, dtype=np.float64) for a in leaves))
    N, nx, nu = ocp.B.shape
    dtype = np.asarray(leaves[0]).dtype
    try:
        res = solve_clarabel(to_qp(ocp, soft=True))
        u, x = split_solution(res.z, N, nx, nu)
        ok = np.all(np.isfinite(u)) and np.all(np.isfinite(x))
        status = Status.CONVERGED if res.status == "Solved" else Status.MAX_ITER
        if "Infeasible" in res.status:
            status = Status.INFEASIBLE
        its = res.iterations
    except Exception:  # a failed host solve reports a status, never raises into the loop
        ok, status, its = False, Status.NONFINITE, 0
    if not ok:
        u, x, status = np.zeros((N, nu)), np.zeros((N, nx)), Status.NONFINITE
    return (
        u.astype(dtype),
        x.astype(dtype),
        np.int32(status),
        np.int32(its),
    )


def _solve_clarabel(ocp: OCP) -> Solution:
    dtype = ocp.B.dtype
    shapes = (
        jax.ShapeDtypeStruct((ocp.N, ocp.nu), dtype),
        jax.ShapeDtypeStruct((ocp.N, ocp.nx), dtype),
        jax.ShapeDtypeStruct((), jnp.int32),
        jax.ShapeDtypeStruct((), jnp.int32),
    )
    u, x, status, its = jax.pure_callback(_clarabel_host, shapes, *ocp, vmap_method="sequential")
    zero = jnp.zeros((), dtype)
    return Solution(u, x, jnp.zeros((ocp.N, ocp.nx), dtype), zero, zero, its, zero, status)


def _solve(ocp: OCP, settings: SolverSettings, init: Plan | None) -> Solution:
    if settings.backend == "clarabel":
        sol = _solve_clarabel(ocp)
    else:
        sol = _solve_core(ocp, settings, init)
    J = objective(ocp, sol.u, sol.x)
    # A failed solve (non-finite data or step) reports +inf, never NaN.
    failed = (sol.status == Status.NONFINITE) | ~jnp.isfinite(J)
    return sol._replace(objective=jnp.where(failed, jnp.inf, J))


def solve(ocp: OCP, settings: SolverSettings = SolverSettings(), init: Plan | None = None):
    """Solve one OCP by the barrier / infeasible-start Newton method.

    Args:
        ocp: the problem (one, unbatched; batch with ``jax.vmap``).
        settings: static :class:`SolverSettings` (``SolverSettings.paper()`` for paper 000's
            algorithm, the default for the accurate mode).
        init: optional warm start (e.g. :func:`shift_solution` of the previous step's
            solution). Its inputs are pulled strictly inside the input rows if needed.

    Returns:
        :class:`Solution` (plan, multipliers, objective, iterations, residual, status). Never
        raises on a numerical failure and never returns NaN: see :class:`Status`. With
        non-finite data the plan is zero, the objective +inf and the status NONFINITE.

    Differentiation: reverse mode (``jax.grad``/``jax.vjp``) w.r.t. every float field of the
    OCP by the implicit function theorem at the returned barrier point (kappa fixed at its
    final value); ``u``, ``x`` and ``nu`` carry derivatives, ``objective`` too (computed
    from them). The custom VJP blocks forward mode (``jax.jvp``/``jacfwd``). In paper mode the
    derivative is that of the barrier solution, evaluated at the returned iterate, so it is
    approximate when the 10 iterations have not converged.
    """
    return _solve_jit(ocp, settings, init)


_solve_jit = jax.jit(_solve, static_argnums=(1,))


def solve_if(active, ocp: OCP, settings: SolverSettings = SolverSettings(), init=None):
    """``solve`` when ``active`` (a traced bool), else the warm start returned untouched.

    For closed loops whose finished runs idle under a mask: a single run skips the solve
    (``lax.cond``); a vmapped batch evaluates both branches and selects. The idle branch
    returns ``init``'s plan (or zeros) with status 0 and zero iterations.
    """

    def fly(ocp):
        return solve(ocp, settings, init=init)

    def idle(ocp):
        shapes = jax.eval_shape(fly, ocp)
        sol = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
        return sol if init is None else sol._replace(u=init.u, x=init.x, nu=init.nu)

    return lax.cond(active, fly, idle, ocp)


def drift_plan(A, x0, N: int, nu: int) -> Plan:
    """Cold-start plan: zero inputs and the unforced drift x_{t+1} = A x_t from x0."""

    def step(x, _):
        x = A @ x
        return x, x

    _, x = lax.scan(step, x0, None, length=N)
    return Plan(jnp.zeros((N, nu), x0.dtype), x, jnp.zeros((N, x0.shape[-1]), x0.dtype))


def solve_batch(
    ocps: OCP, settings: SolverSettings = SolverSettings(), init: Plan | None = None, chunk=32
):
    """Solve a batch of OCPs (leading axis on every field) in vmapped chunks of ``chunk``.

    ``jax.lax.map(..., batch_size=chunk)``: one ``vmap`` over thousands of problems streams
    every intermediate through memory, while chunks of ~32 keep a chunk's working set in cache
    (measured on a 2-core AMD EPYC: 1024 fastmpc-3d problems 0.61 ms -> 0.44 ms per problem).
    Results equal ``jax.vmap(solve)``. Jit the caller, e.g.
    ``jax.jit(solve_batch, static_argnames=("settings", "chunk"))``.
    """
    if init is None:
        return lax.map(lambda o: solve(o, settings), ocps, batch_size=chunk)
    return lax.map(lambda a: solve(a[0], settings, a[1]), (ocps, init), batch_size=chunk)
