"""Starting points: warm starts, the input pull-in, the drift of the inputs through the model.

Only the hard input rows need a strictly feasible start (the soft state rows' penalty is
defined everywhere, :mod:`rvdjax.solver.barrier`); u = 0 is one (``validate_ocp`` checks
fu > 0), and a warm start is pulled towards 0 until it is one.
"""

from __future__ import annotations

import operator

import jax
import jax.numpy as jnp
from jax import lax

from rvdjax.ocp import OCP
from rvdjax.solver import stagewise as sw
from rvdjax.solver.barrier import Rows, u_slack
from rvdjax.solver.kkt import KKT_SOLVERS
from rvdjax.solver.platform import cuda_or_default
from rvdjax.solver.types import Plan, Solution, SolverSettings

__all__ = [
    "drift",
    "drift_plan",
    "input_anchor",
    "lift_inside",
    "pull_inside",
    "shift_solution",
    "track_plan",
    "warm_start",
]

# lift_inside: an input row whose start slack is below LIFT_BELOW of its slack at the stage's
# anchor is lifted to LIFT_TO of it. LIFT_BELOW sits under pull_inside's 1 % margin, so that
# starts it leaves are left alone (a warm start at a saturated thruster: lifting those to 0.1
# cost fastmpc-3d 3.75 -> 4.23 iterations a step, thesis-vbar 14.49 -> 16.33); 1e-3 / 1e-2 /
# 0.1 as the lifted slack gave thesis-vbar-lp 22.6 / 19.6 / 17.8 iterations a step
# (docs/benchmark.md, "Against the peers").
LIFT_BELOW = 1e-3
LIFT_TO = 0.1


def _stage_scan(make_step, x0, xs, length=None):
    """The states of ``lax.scan(make_step(mv), x0, xs)`` over a horizon's stages, ``mv(A, x)``
    the product of a stage's matrix and a state: a loop of ``A @ x`` on the CPU; where the
    program runs on a CUDA GPU, the stages unrolled and the products written as multiplies
    and sums (:func:`rvdjax.solver.stagewise.mv`).

    On a CPU, XLA compiles a small loop into one function, and the unrolled form took 1.3-1.8x
    as long to compile a closed loop (thesis-vbar 8.0 s against 5.6, 2026-11-28). On a GPU
    every trip of a loop is several kernel launches: in the batch engine's tick, the two
    drifts of the refresh (the new run's cold plan, the next solve's start) were 270 of
    thesis-vbar's 874 launches (``sweeps/gpu_traffic.py engine``); unrolled, each product of
    a model shared by the slots was still a matrix-multiply launch of its own (30 of a tick's
    555), where the multiplies and sums of the 30 stages fuse into a couple of kernels. (The
    sums run in another order than the GPU's matrix products: the same states to rounding.)
    A process without a GPU backend traces the loop alone
    (:func:`rvdjax.solver.tracing_for_cuda`)."""

    def scan(mv, unroll):
        step = make_step(mv)
        return lambda x0: lax.scan(step, x0, xs, length=length, unroll=unroll)[1]

    return cuda_or_default(x0, cuda=scan(sw.mv, True), default=scan(operator.matmul, 1))


def drift(ocp: OCP, u):
    """States from propagating x0 with inputs u (a primal-feasible x for the start)."""

    def make_step(mv):
        def step(x, stage):
            A_t, B_t, c_t, u_t = stage
            x_next = mv(A_t, x) + mv(B_t, u_t) + c_t
            return x_next, x_next

        return step

    return _stage_scan(make_step, ocp.x0, (ocp.A, ocp.B, ocp.c, u))


def drift_plan(A, x0, N: int, nu: int) -> Plan:
    """Cold-start plan: zero inputs and the unforced drift x_{t+1} = A x_t from x0.

    ``A`` is one (nx, nx) matrix or a stage-wise (N, nx, nx) stack.
    """
    if A.ndim == 2:

        def make_step(mv):
            def step(x, _):
                x = mv(A, x)
                return x, x

            return step

        x = _stage_scan(make_step, x0, None, length=N)
    else:

        def make_step(mv):
            def step(x, A_t):
                x = mv(A_t, x)
                return x, x

            return step

        x = _stage_scan(make_step, x0, A)
    return Plan(jnp.zeros((N, nu), x0.dtype), x, jnp.zeros((N, x0.shape[-1]), x0.dtype))


def shift_solution(sol: Solution | Plan) -> Plan:
    """Shift a plan one stage forward for the next MPC step, repeating the last stage."""

    def shift(a):
        return jnp.concatenate([a[1:], a[-1:]], axis=0)

    return Plan(shift(sol.u), shift(sol.x), shift(sol.nu))


def warm_start(ocp: OCP, settings: SolverSettings, plan: Plan, cold) -> Plan:
    """The ``init`` of a solve of ``ocp``: ``plan`` (the previous plan, shifted), or where
    ``cold`` (a traced bool: the first step, a phase change) a cold start.

    The cold start suits the way ``settings`` starts: paper mode with ``paper_start`` "warm"
    or "track" reads the plan's states, so it gets the unforced drift of ``ocp``; the other
    starts use only the inputs and multipliers (the states are the drift of the inputs), so
    they get zeros and ``plan``'s states, which they ignore.
    """
    if settings.mode == "paper" and settings.paper_start != "feasible":
        cold_plan = drift_plan(ocp.A, ocp.x0, ocp.N, ocp.nu)
    else:
        cold_plan = Plan(jnp.zeros_like(plan.u), plan.x, jnp.zeros_like(plan.nu))
    return jax.tree.map(lambda a, b: jnp.where(cold, a, b), cold_plan, plan)


def pull_inside(rows: Rows, u, margin=0.99):
    """Scale each stage's u towards 0 (strictly feasible) until strictly feasible."""
    Fu_u = sw.mv(rows.Fu, u)
    ratio = jnp.where((rows.wu > 0) & (Fu_u > 0), rows.fu / jnp.where(Fu_u > 0, Fu_u, 1.0), 2.0)
    theta = jnp.minimum(1.0, margin * jnp.min(ratio, axis=-1))
    return u * theta[:, None]


def input_anchor(rows: Rows):
    """A point inside each stage's input rows, away from any row that u = 0 lies close to: one
    step of Newton's method on the rows' log barrier from u = 0, its Hessian taken by its
    diagonal (exact for bounds on single inputs), moved half way to the first row it heads
    for. For rows symmetric about 0 it is 0 itself; for bounds 0 <= u <= u_max (0 a hair
    inside), u_max / 2 where one input is bounded; a direction no row bounds takes the plain
    step. Needs u = 0 strictly inside (``validate_ocp``: fu > 0). Returns the anchor and the
    rows' slacks there."""
    Fu, s, wu = rows.Fu, rows.fu, rows.wu
    s_safe = jnp.where(s > 0, s, 1.0)
    w = wu / s_safe  # the barrier's gradient at 0 is sum_i w_i Fu_i
    g = sw.mtv(Fu, w)
    h = sw.mtv(Fu * Fu, w / s_safe)
    d = jnp.where(h > 0, -g / jnp.where(h > 0, h, 1.0), 0.0)
    Fd = sw.mv(Fu, d)
    shrink = (wu > 0) & (Fd > 0)
    reach = jnp.min(jnp.where(shrink, s / jnp.where(shrink, Fd, 1.0), jnp.inf), axis=-1)
    step = jnp.where(jnp.isfinite(reach), 0.5 * reach, 1.0)[..., None]
    return step * d, s - step * Fd


def lift_inside(rows: Rows, u):
    """``u`` moved towards :func:`input_anchor`, stage by stage, as far as lifts every input row
    whose slack is below LIFT_BELOW of its slack at the anchor to LIFT_TO of it; stages with
    no such row are returned as they are (to the bit).

    A start a hair from a row puts that row's multiplier at kappa0 / slack: the LP cost's
    split inputs (paper 003's fuel-optimal rendezvous) are bounded 1.8e-8 m/s below zero
    (``rvdjax.families.phases_inputs.LP_EPS``), and from u = 0 the multipliers of 1e13 held
    a solve's gap for 250 iterations (docs/benchmark.md). Slacks are affine in the move, so
    every row stays feasible where the anchor is strictly inside them all."""
    anchor, s_a = input_anchor(rows)
    on = rows.wu > 0
    s_u = u_slack(rows, u)
    low = on & (s_u < LIFT_BELOW * s_a)
    gain = jnp.where(low, s_a - s_u, 1.0)
    need = jnp.where(low, (LIFT_TO * s_a - s_u) / gain, 0.0)
    theta = jnp.clip(jnp.max(need, axis=-1), 0.0, 1.0)
    inside = jnp.all(jnp.where(on, s_a > 0, True), axis=-1)
    lift = (theta > 0) & inside
    return jnp.where(lift[..., None], u + theta[..., None] * (anchor - u), u)


def track_plan(ocp: OCP, u_prev, x_prev, method: str, kernel: str = "auto"):
    """Inputs that follow a previous plan from the new x0: the minimiser of
    sum (x - x_prev)' Q (x - x_prev) + (u - u_prev)' R (u - u_prev) subject to the dynamics
    (one Riccati solve: the plan's own weights turn the deviation of x0 into the LQR
    correction). Its states stay near the previous plan, which met the state rows, while
    obeying the dynamics from the measured x0."""
    x_drift = drift(ocp, u_prev)
    Phi_u = 2.0 * ocp.R
    Phi_x = 2.0 * ocp.Q
    g_u = jnp.zeros_like(u_prev)
    g_x = 2.0 * sw.mv(ocp.Q, x_drift - x_prev)
    step = KKT_SOLVERS[method](ocp.A, ocp.B, Phi_u, Phi_x, g_u, g_x, jnp.zeros_like(x_prev), kernel)
    return jnp.where(jnp.all(jnp.isfinite(step.du)), u_prev + step.du, u_prev)
