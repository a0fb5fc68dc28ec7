"""Driving a solve: start, iterate, finish — and the public :func:`solve` built from them.

A solve is ``start`` (sanitise the data, choose the first iterate and kappa), iterations until
the stopping test or ``max_iter``, and ``finish`` (statuses, multipliers, clean-up). The
three are exposed separately so that a batch engine can run a fixed number of iterations per
call and continue unfinished problems later (:mod:`rvdjax.loop.engine`): an iterate that has
finished is frozen by :func:`iterate`, so any number of extra calls leaves it unchanged and
the answer does not depend on how the iterations were grouped.

:func:`solve` runs the iterations in a ``lax.while_loop`` and differentiates implicitly
(:mod:`rvdjax.solver.implicit`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from rvdjax.batching import varying_like
from rvdjax.ocp import OCP
from rvdjax.solver.barrier import (
    all_finite,
    dyn_residual,
    gradient,
    m_eff,
    max_violation,
    neutralised,
    objective,
    residual_norms,
    rows_in,
    u_slack,
    x_violation,
)
from rvdjax.solver.clarabel import solve_clarabel_backend
from rvdjax.solver.dual import solve_dual
from rvdjax.solver.implicit import implicit_bwd, kkt_at
from rvdjax.solver.kkt import kkt_solve
from rvdjax.solver.newton import NewtonState, newton_iteration
from rvdjax.solver.platform import traces_cuda
from rvdjax.solver.primal_dual import (
    PDState,
    carries_system,
    pd_drift,
    pd_iteration,
    pd_start,
    pd_system,
)
from rvdjax.solver.start import lift_inside, pull_inside, track_plan
from rvdjax.solver.types import Plan, Solution, SolverParams, SolverSettings, Status

__all__ = [
    "SolveState",
    "start",
    "iterate",
    "finished",
    "finish",
    "freeze",
    "solve",
    "solve_batch",
    "solve_if",
    "with_objective",
]


class SolveState(NamedTuple):
    """A solve in progress (one problem).

    Attributes:
        core: the iterate: :class:`~rvdjax.solver.newton.NewtonState` (paper, barrier mode) or
            :class:`~rvdjax.solver.pd_algebra.PDState` (accurate mode).
        x_scale: () 1 + the largest state entry at the start (scale of the primal residual).
        n_barrier: () the number of barrier terms (:func:`~rvdjax.solver.barrier.m_eff`:
            one per input row, two per soft state row), fixed by the rows for the whole solve
            and so counted once, at the start; the iterations read it here.
    """

    core: NewtonState | PDState
    x_scale: jnp.ndarray
    n_barrier: jnp.ndarray


def _prepared(params: SolverParams, dtype) -> SolverParams:
    params = params.astype(dtype)
    # Tolerances below ~1e3 machine epsilon are unreachable (float32: 1.2e-4).
    return params._replace(tol=jnp.maximum(params.tol, 1e3 * jnp.finfo(dtype).eps))


MODEL_FIELDS = ("A", "B", "c", "Q", "R")


def start(
    ocp: OCP,
    settings: SolverSettings,
    params: SolverParams,
    init: Plan | None = None,
    trusted_model: bool = False,
    in_kernels: bool = True,
):
    """Sanitise ``ocp`` and build the first iterate.

    ``trusted_model`` (static): the model fields (A, B, c, Q, R) are known to be finite (checked
    where they were built) and are passed through untouched. A batch engine uses it to keep a
    model shared by every problem of a batch unbatched (one large matrix product for the whole
    batch instead of one small one per problem).

    ``in_kernels`` (static): where the Newton step's form runs the rows in kernels, the start
    runs in them too: the drift of the first inputs as one kernel, and the first Newton
    system where the form carries it (:func:`~rvdjax.solver.pd_kernels.carries_system`).
    Without it the start is XLA's and the state has no system; :func:`with_system` adds it
    later. The batch engine starts so: its slots are stored batch first, and the kernels'
    batch-last arrays cost it transposes (docs/benchmark.md); each tick forms the system
    where its iterations run batch last.

    Returns:
        (the OCP to iterate on — the same problem with its masked rows neutralised, to pass to
        :func:`iterate` and :func:`finish` —, :class:`SolveState`). Non-finite data would
        poison every iterate: the returned OCP is then a neutral copy and the state is finished
        with status NONFINITE.
    """
    if settings.mode == "dual":
        raise ValueError("mode='dual' runs through solve() only (not start / iterate / finish)")
    dtype = ocp.B.dtype
    params = _prepared(params, dtype)
    data = {
        name: getattr(ocp, name)
        for name in OCP._fields
        if not (trusted_model and name in MODEL_FIELDS)
    }
    inputs_ok = all_finite(list(data.values())) & (True if init is None else all_finite(init))
    safe = {name: jnp.where(inputs_ok, a, jnp.zeros_like(a)) for name, a in data.items()}
    if not trusted_model:
        eye = jnp.broadcast_to(jnp.eye(ocp.nu, dtype=dtype), ocp.R.shape)
        safe["R"] = jnp.where(inputs_ok, ocp.R, eye)
    for name in ("fu", "fx", "rho"):  # neutral values that keep the start well defined
        safe[name] = jnp.where(inputs_ok, getattr(ocp, name), 1.0)
    ocp = ocp._replace(**safe)
    ocp = neutralised(ocp)
    rows = rows_in(ocp)
    if init is None:
        u0 = jnp.zeros((ocp.N, ocp.nu), dtype)
        nu0 = jnp.zeros((ocp.N, ocp.nx), dtype)
        x_start = None
    else:
        init = jax.tree.map(lambda a: jnp.where(inputs_ok, a, jnp.zeros_like(a)), init)
        u0, nu0, x_start = init.u, init.nu, init.x
    if x_start is not None and settings.mode == "paper" and settings.paper_start == "track":
        u0 = track_plan(ocp, u0, x_start, settings.method, settings.kernel)
    u0 = pull_inside(rows, u0)
    if settings.mode == "accurate":  # the primal-dual start's multipliers are kappa0 / slack
        u0 = lift_inside(rows, u0)
    # The accurate mode is a feasible-start method; so is paper mode by default (``paper_start
    # = "feasible"``): a run cut at max_iter then still flies a plan that obeys the dynamics.
    # Algorithm 1's literal infeasible start keeps the warm start's states (``"warm"``).
    warm_states = (
        x_start is not None and settings.mode == "paper" and settings.paper_start == "warm"
    )
    drift_form = settings.kernel if in_kernels else "xla"
    x0s = x_start if warm_states else pd_drift(ocp, u0, drift_form)
    start_ok = jnp.all(jnp.where(rows.wu > 0, u_slack(rows, u0) > 0, True))
    start_status = jnp.where(
        ~inputs_ok, Status.NONFINITE, jnp.where(start_ok, Status.MAX_ITER, Status.INFEASIBLE)
    )
    done = ~(start_ok & inputs_ok)
    x_scale = 1.0 + jnp.maximum(jnp.max(jnp.abs(x0s)), jnp.max(jnp.abs(ocp.x0)))
    n_barrier = m_eff(rows)
    if settings.mode == "paper":
        kappa0 = params.kappa
    else:
        J0 = objective(ocp, u0, x0s)
        kappa0 = params.kappa0_rel * (1.0 + jnp.abs(J0)) / jnp.maximum(n_barrier, 1.0)
    if settings.mode == "accurate":
        core = pd_start(rows, u0, x0s, nu0, kappa0, done, start_status)
        if in_kernels and carries_system(settings):  # the first Newton system
            core = core._replace(system=pd_system(ocp, rows, core, settings.kernel))
    else:
        inf = jnp.asarray(jnp.inf, dtype)
        core = NewtonState(u0, x0s, nu0, kappa0, jnp.asarray(0), done, start_status, inf)
    return ocp, SolveState(core, x_scale, n_barrier)


def finished(settings: SolverSettings, state: SolveState):
    """() bool: the solve has met its stopping test, failed, or used its iterations."""
    return state.core.done | (state.core.it >= settings.max_iter)


def freeze(state: SolveState, where=True) -> SolveState:
    """``state`` marked finished where ``where`` (a traced bool; default: always), so that
    :func:`iterate` leaves it unchanged; :func:`finish` still reports its status and
    iterations as they are. A batch engine freezes the solves of its free slots."""
    core = state.core
    return state._replace(core=core._replace(done=core.done | where))


def iterate(
    ocp: OCP, settings: SolverSettings, params: SolverParams, state: SolveState, table=None
):
    """One iteration from ``state`` on the OCP returned by :func:`start`; a finished state is
    returned unchanged. ``table``: a :class:`~rvdjax.solver.riccati.ModelTable` whose entry is
    the OCP's [B, A] (the batch engine's phase models), which the GPU kernels read instead of
    a copy of A and B per problem, or None. Where ``state`` carries the Newton system
    (:func:`with_system`), so does the new state, at its iterate."""
    params = _prepared(params, ocp.B.dtype)
    rows = rows_in(ocp)
    stop = finished(settings, state)
    if settings.mode == "accurate":  # a step of length zero where stopped
        core = pd_iteration(
            ocp, rows, state.n_barrier, state.x_scale, state.core, settings, params, stop, table
        )
        return state._replace(core=core)
    new = newton_iteration(
        ocp, rows, state.n_barrier, state.x_scale, state.core, settings, params, table
    )
    core = jax.tree.map(lambda old, n: jnp.where(stop, old, n), state.core, new)
    return state._replace(core=core)


def with_system(ocp: OCP, settings: SolverSettings, state: SolveState, table=None):
    """``state`` with the Newton system at its iterate, where the Newton step's form carries
    it (:func:`~rvdjax.solver.pd_kernels.carries_system`) and ``state`` has none (a
    :func:`start` without ``in_kernels``); else ``state`` itself. ``table`` as :func:`iterate`.
    The batch engine's ticks start so, and drop the system after their iterations, so that
    the slots hold none between ticks (on a GPU the refresh would form and move it, the
    slots first, for more than the iterations save; docs/benchmark.md)."""
    core = state.core
    if not carries_system(settings) or core.system is not None:
        return state
    system = pd_system(ocp, rows_in(ocp), core, settings.kernel, table)
    return state._replace(core=core._replace(system=system))


def finish(ocp: OCP, settings: SolverSettings, params: SolverParams, state: SolveState):
    """The :class:`Solution` of a finished state (its objective is left at 0: see
    :func:`with_objective`)."""
    params = _prepared(params, ocp.B.dtype)
    rows = rows_in(ocp)
    dtype = ocp.B.dtype
    core = state.core
    u, x, nu, it, status = core.u, core.x, core.nu, core.it, core.status
    if settings.mode == "accurate":
        # kappa of the returned point: its mean complementarity (the barrier weight of the
        # central-path point it approximates; used by the implicit derivative).
        kappa = core.gap / jnp.maximum(state.n_barrier, 1.0)
        residual = core.res  # the primal-dual loop's relative dual residual
    else:
        kappa = core.kappa
        if settings.mode == "barrier":
            # The multipliers of the KKT solve at the returned point (the loop's last
            # estimate belongs to the pre-step point).
            kkt = kkt_at(ocp, u, x, kappa, settings)
            g_u, g_x = gradient(ocp, rows, u, x, kappa)
            step = kkt_solve(
                kkt, g_u, g_x, dyn_residual(ocp, u, x), settings.method, settings.kernel
            )
            nu = jnp.where(jnp.all(jnp.isfinite(step.nu)), step.nu, nu)
        _, rel_d, rel_p = residual_norms(ocp, rows, u, x, nu, kappa)
        residual = jnp.maximum(rel_d, rel_p)

    # Converged, but the soft state rows are violated: the hard problem is infeasible.
    violated = max_violation(ocp, u, x) > params.violation_tol
    status = jnp.where((status == Status.CONVERGED) & violated, Status.INFEASIBLE, status)

    def clean(a):
        return jnp.where(jnp.isfinite(a), a, jnp.zeros_like(a))

    return Solution(
        u=clean(u),
        x=clean(x),
        nu=clean(nu),
        objective=jnp.zeros((), dtype),
        kappa=kappa,
        iterations=it,
        residual=jnp.where(jnp.isfinite(residual), residual, jnp.inf),
        status=status,
    )


def with_objective(ocp: OCP, sol: Solution) -> Solution:
    """Fill in the objective; a failed solve (non-finite data or step) reports +inf."""
    J = objective(ocp, sol.u, sol.x)
    failed = (sol.status == Status.NONFINITE) | ~jnp.isfinite(J)
    return sol._replace(objective=jnp.where(failed, jnp.inf, J))


def _forward_state(ocp, params, init, settings, trusted_model: bool = False):
    """The solve loop: :func:`start` (``trusted_model`` as there), :func:`iterate` until
    finished, :func:`finish`. Returns (solution, the OCP iterated on, the final state)."""
    ocp_safe, state = start(ocp, settings, params, init, trusted_model)
    state = _until_finished(ocp_safe, params, state, settings)
    return finish(ocp_safe, settings, params, state), ocp_safe, state


def _until_finished(ocp_safe, params, state, settings: SolverSettings):
    """:func:`iterate` until :func:`finished` (a ``while`` loop).

    In a process that lowers for a CUDA GPU (:func:`~rvdjax.solver.platform.traces_cuda`), a
    batched (vmapped) solve's loop runs while any problem of the batch is unfinished and takes
    every problem's iteration, finished or not: :func:`iterate` leaves a finished state as it
    is (a step of length zero; its counters kept). vmap's own rule for a loop whose condition
    differs between problems selects between the old and the new state of every problem at
    each iteration, a pass over every array of the state that also keeps the old one alive: on
    a GPU, a copy and a select of each of the iterate's arrays an iteration (counted for
    65 536 fastmpc-3d QPs: 42 of 451 KB a problem and 12 of 20 launches; docs/benchmark.md).
    A CPU-only process keeps vmap's rule, and its programs as they were (not measured there;
    a float32 solve's rounding, for one, depends on the program)."""
    if not traces_cuda():
        return _while(ocp_safe, params, state, settings)
    return _loop(settings)(ocp_safe, params, state)


def _while(ocp_safe, params, state, settings: SolverSettings):
    """:func:`iterate` until :func:`finished`: one problem's ``while`` loop."""

    def body(st):
        return iterate(ocp_safe, settings, params, st)

    state = varying_like(state, ocp_safe.x0)  # vmap: one pass (rvdjax.batching)
    return lax.while_loop(lambda st: ~finished(settings, st), body, state)


@functools.cache
def _loop(settings: SolverSettings):
    """:func:`_until_finished` for ``settings`` (a ``custom_vmap`` function)."""

    def cond(st):
        return ~finished(settings, st)

    @jax.custom_batching.custom_vmap
    def loop(ocp_safe, params, state):
        return _while(ocp_safe, params, state, settings)

    @loop.def_vmap
    def _batched(axis_size, in_batched, ocp_safe, params, state):
        ocp_axes, params_axes = (
            jax.tree.map(lambda b: 0 if b else None, bs) for bs in in_batched[:2]
        )
        state = jax.tree.map(
            lambda a, b: a if b else jnp.broadcast_to(a, (axis_size, *jnp.shape(a))),
            state,
            in_batched[2],
        )
        step = jax.vmap(
            lambda o, p, st: iterate(o, settings, p, st), in_axes=(ocp_axes, params_axes, 0)
        )
        unfinished = jax.vmap(cond)
        out = lax.while_loop(
            lambda st: jnp.any(unfinished(st)), lambda st: step(ocp_safe, params, st), state
        )
        return out, jax.tree.map(lambda _: True, out)

    return loop


def _forward(ocp, params, init, settings):
    return _forward_state(ocp, params, init, settings)[0]


def _derivative_kappa(ocp_safe, state, sol: Solution, settings: SolverSettings):
    """The barrier weight(s) at which the implicit derivative linearises the optimality
    conditions. Paper and barrier modes: the returned kappa (the point is centred for it).
    Accurate mode: each row's own complementarity products (input rows lam s_u; soft rows
    mu (s - g) and pi s), so that the barrier gradient equals the iterate's multipliers and
    the Hessian the primal-dual linearisation (lam / s_u; 1 / ((s - g) / mu + s / pi)). One
    mean complementarity for every row weighted them wrongly (their products spread over
    orders of magnitude): closed-loop derivatives were then off by 1-2 %.
    """
    if settings.mode != "accurate":
        return sol.kappa
    core = state.core
    rows = rows_in(ocp_safe)
    su = u_slack(rows, core.u)
    sx = core.s - x_violation(rows, core.x)
    floor = jnp.finfo(su.dtype).tiny
    k_u = jnp.where(rows.wu > 0, jnp.maximum(core.lam * su, floor), sol.kappa)
    k_mu = jnp.where(rows.wx > 0, jnp.maximum(core.mu * sx, floor), sol.kappa)
    k_pi = jnp.where(rows.wx > 0, jnp.maximum(core.pi * core.s, floor), sol.kappa)
    return (k_u, (k_mu, k_pi))


@functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
def _solve_core(ocp: OCP, params: SolverParams, init: Plan | None, settings: SolverSettings):
    return _forward(ocp, params, init, settings)


def _solve_core_fwd(ocp, params, init, settings):
    # Differentiated, the accurate mode steps 0.99 of the way to the boundary: the adaptive
    # step leaves some rows' complementarity products 1e4x the others' at the end, and the
    # implicit derivative, which holds each product fixed, then gave a closed loop's gradient
    # the wrong sign (poseidyn-lqmpc's sample time: -43.8 against 1.40 by central
    # differences; docs/solver.md).
    settings = dataclasses.replace(settings, step_fraction="fixed")
    sol, ocp_safe, state = _forward_state(ocp, params, init, settings)
    kappa = _derivative_kappa(ocp_safe, state, sol, settings)
    # Factorised once here, only when differentiating; the backward pass reuses it.
    kkt = kkt_at(ocp, sol.u, sol.x, kappa, settings)
    return sol, (ocp, params, init, sol, kkt, kappa)


_solve_core.defvjp(_solve_core_fwd, implicit_bwd)


def _solve(ocp: OCP, settings: SolverSettings, params: SolverParams, init: Plan | None):
    if settings.backend != "rvdjax":
        sol = solve_clarabel_backend(ocp, settings.backend)
    elif settings.mode == "dual":  # paper 001's PQP, a fixed number of iterations
        sol = solve_dual(ocp, settings.max_iter, params.astype(ocp.B.dtype))
    else:
        sol = _solve_core(ocp, params.astype(ocp.B.dtype), init, settings)
    return with_objective(ocp, sol)


_solve_jit = jax.jit(_solve, static_argnums=(1,))


def solve(
    ocp: OCP,
    settings: SolverSettings = SolverSettings(),
    params: SolverParams | None = None,
    init: Plan | None = None,
) -> Solution:
    """Solve one OCP by the barrier / infeasible-start Newton method.

    Args:
        ocp: the problem (one, unbatched; batch with ``jax.vmap``).
        settings: static :class:`SolverSettings` (``SolverSettings.paper()`` for paper 000's
            algorithm, the default for the accurate mode).
        params: traced :class:`SolverParams` (kappa, alpha, beta, tolerances); default: the
            defaults of ``settings.mode``. Changing them does not recompile.
        init: optional warm start (e.g. :func:`shift_solution` of the previous step's
            solution). Its inputs are pulled strictly inside the input rows if needed.

    Returns:
        :class:`Solution` (plan, multipliers, objective, iterations, residual, status). Never
        raises on a numerical failure and never returns NaN: see :class:`Status`. With
        non-finite data the plan is zero, the objective +inf and the status NONFINITE.

    Differentiation: reverse mode (``jax.grad``/``jax.vjp``) w.r.t. every float field of the
    OCP by the implicit function theorem at the returned barrier point (kappa fixed at its
    final value; in paper mode also w.r.t. ``params.kappa``); ``u``, ``x`` and ``nu`` carry
    derivatives, ``objective`` too (computed from them). The custom VJP blocks forward mode
    (``jax.jvp``/``jacfwd``). In paper mode the derivative is that of the barrier solution,
    evaluated at the returned iterate, so it is approximate when the 10 iterations have not
    converged.
    """
    if params is None:
        params = SolverParams.for_settings(settings)
    else:
        params.checked()
    return _solve_jit(ocp, settings, params, init)


def solve_if(active, ocp: OCP, settings: SolverSettings, params=None, init=None):
    """``solve`` when ``active`` (a traced bool), else the warm start returned untouched.

    For closed loops whose finished runs idle under a mask: a single run skips the solve
    (``lax.cond``); under ``vmap`` the predicate is batched and both branches run (the batch
    engine, :mod:`rvdjax.loop.engine`, avoids that). The idle branch returns ``init``'s plan
    (or zeros) with status 0 and zero iterations.
    """
    params = SolverParams.for_settings(settings) if params is None else params

    def fly(ocp):
        return solve(ocp, settings, params=params, init=init)

    def idle(ocp):
        shapes = jax.eval_shape(fly, ocp)
        sol = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
        return sol if init is None else sol._replace(u=init.u, x=init.x, nu=init.nu)

    return lax.cond(active, fly, idle, ocp)


def solve_batch(
    ocps: OCP,
    settings: SolverSettings = SolverSettings(),
    params: SolverParams | None = None,
    init: Plan | None = None,
    chunk=32,
):
    """Solve a batch of OCPs (leading axis on every field) in vmapped chunks of ``chunk``.

    ``jax.lax.map(..., batch_size=chunk)``: one ``vmap`` over thousands of problems streams
    every intermediate through memory, while chunks of ~32 keep a chunk's working set in cache
    (docs/benchmark.md). Results equal ``jax.vmap(solve)``. Jit the caller, e.g.
    ``jax.jit(solve_batch, static_argnames=("settings", "chunk"))``.
    """
    params = SolverParams.for_settings(settings) if params is None else params
    if init is None:
        return lax.map(lambda o: solve(o, settings, params=params), ocps, batch_size=chunk)
    return lax.map(
        lambda a: solve(a[0], settings, params=params, init=a[1]), (ocps, init), batch_size=chunk
    )
