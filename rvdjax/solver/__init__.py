"""Fast MPC: log barrier + infeasible-start Newton method for the linear OCP.

Paper 000 Sec. III (after Wang & Boyd, "Fast model predictive control using online
optimization"): the inequalities are replaced by a log barrier weighted by kappa (Eq. 17) and
the equality-constrained barrier problem is solved by the infeasible-start Newton method
(Eqs. 18-23, Algorithm 1) with a structured step (Eqs. 24-26, :mod:`rvdjax.solver.riccati`).

Three modes (DESIGN §3):

* ``paper``: fixed kappa (0.05), at most 10 Newton iterations, alpha = 0.01, beta = 0.95,
  backtracking on the residual norm — Algorithm 1 as published (:mod:`.newton`). It returns
  the barrier problem's iterate, not the QP optimum; by default it starts from the states the
  warm-start inputs produce (``paper_start``), so the dynamics hold at every iterate.
* ``accurate`` (default): barrier continuation with primal-dual Newton steps and Mehrotra's
  rule for kappa (:mod:`.primal_dual`); stops when the complementarity gap is below ``tol``
  relative to the objective and the dual residual below 100 ``tol`` relative to the gradient.
  Its answer matches Clarabel.
* ``barrier``: the primal barrier continuation of the paper's method run to convergence
  (:mod:`.newton`).

Modules: :mod:`.types` (settings, traced parameters, results), :mod:`.barrier` (cost, barrier
and residuals), :mod:`.kkt` (the Newton step: its interface and the dense solve),
:mod:`.riccati` (the structured Newton step and its batching rules), :mod:`.start` (starting
points and warm starts), :mod:`.newton` and :mod:`.primal_dual` (iterations; the latter's
state and row algebra in :mod:`.pd_algebra`, the same row work on the GPU kernels in
:mod:`.pd_kernels`), :mod:`.driver` (start / iterate / finish and :func:`solve`),
:mod:`.implicit` (the implicit derivative), :mod:`.clarabel` (the Clarabel backend).

One argument order for every public function: the problem, the static settings, the traced
parameters, then the warm start or the solve's state — ``solve(ocp, settings, params, init)``,
``start(ocp, settings, params, init)``, ``iterate(ocp, settings, params, state)``,
``finish(ocp, settings, params, state)``, ``finished(settings, state)``,
``with_system(ocp, settings, state)``, ``warm_start(ocp, settings, plan, cold)``. Keywords are
safest at call sites.

Stopping tests are relative to the problem's scale (the RVD costs are ~1e7 with Riccati
velocity weights ~1e6, so absolute tolerances never trigger). Every loop has a fixed iteration
cap and a per-problem "done" mask, so ``jax.vmap`` of :func:`solve` runs one program for a
whole batch; finished or failed problems are frozen and every branch is NaN-safe.
"""

from rvdjax.solver.barrier import max_violation, objective
from rvdjax.solver.driver import (
    SolveState,
    finish,
    finished,
    freeze,
    iterate,
    solve,
    solve_batch,
    solve_if,
    start,
    with_objective,
    with_system,
)
from rvdjax.solver.pd_kernels import carries_system
from rvdjax.solver.platform import tracing_for_cuda
from rvdjax.solver.start import drift_plan, shift_solution, warm_start
from rvdjax.solver.types import Plan, Solution, SolverParams, SolverSettings, Status

__all__ = [
    "Plan",
    "Solution",
    "SolverParams",
    "SolverSettings",
    "SolveState",
    "Status",
    "carries_system",
    "drift_plan",
    "finish",
    "finished",
    "freeze",
    "iterate",
    "max_violation",
    "objective",
    "shift_solution",
    "solve",
    "solve_batch",
    "solve_if",
    "start",
    "tracing_for_cuda",
    "warm_start",
    "with_objective",
    "with_system",
]
