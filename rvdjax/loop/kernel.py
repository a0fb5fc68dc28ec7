"""The closed-loop kernel shared by every guidance family: ``init``, ``step``, ``fly``.

One ``step`` is one MPC decision (DESIGN §4): the family observes the truth (cone
activation), the guidance sees the measured state (navigation noise; with ``nav_filter``
the estimate of a Kalman filter, :mod:`rvdjax.loop.navigation`), the family builds the OCP,
the solver answers (warm-started from the shifted previous plan, or cold after a phase
change), the command goes through the actuator (minimum impulse bit, thrust-amplitude error)
and the plant, the family updates its guidance state (phase, holding radius, docking) on the
truth, and the step's figures are accumulated. A finished run (docked, out of steps or past
its time limit, or failed) keeps stepping as a no-op, so a batch has one shape. The shape
follows blackjax's kernels: ``init(loop, params, x0, key) -> LoopState`` and ``step(loop,
params, state) -> (state, StepInfo)``, the per-step PRNG key derived from the run's key and
the step index, so a run is reproducible from its key whatever batch it is flown in.

``step`` is :func:`prepare` (observe, measure, build the OCP and the warm start), a solve and
:func:`advance` (command, actuator, plant, guidance update, accumulation); the batch engine
(:mod:`rvdjax.loop.engine`) runs the same two halves with the solver iterations in between
spread over several calls. The actuator path of ``advance`` is :mod:`rvdjax.loop.actuation`;
the figures of merit (``Accumulator``, ``Metrics``, ``metrics``) are
:mod:`rvdjax.loop.metrics`, re-exported here.
"""

from __future__ import annotations

import dataclasses
import numbers
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from rvdjax.actuators.modulation import Pulses
from rvdjax.actuators.thrusters import Actuation
from rvdjax.batching import varying_like
from rvdjax.constraints import hard_mask, margins
from rvdjax.disturbances import gm_init, measure
from rvdjax.loop.actuation import actuate, truth_path
from rvdjax.loop.family import Family
from rvdjax.loop.metrics import (
    HIST_BINS,
    Accumulator,
    Metrics,
    RunStatus,
    accumulate,
    empty_accumulator,
    metrics,
)
from rvdjax.loop.navigation import (
    NavState,
    measurement_covariance,
    nav_init,
    nav_predict,
    nav_update,
    process_noise,
    thrust_error_fraction,
)
from rvdjax.loop.plant import TRUTHS, checked_plant
from rvdjax.ocp import OCP
from rvdjax.solver import (
    Plan,
    Solution,
    SolverParams,
    SolverSettings,
    Status,
    shift_solution,
    solve_if,
    warm_start,
)

__all__ = [
    "LoopConfig",
    "Loop",
    "LoopState",
    "Accumulator",
    "Prepared",
    "StepInfo",
    "Metrics",
    "RunStatus",
    "init",
    "prepare",
    "advance",
    "step",
    "fly",
    "metrics",
    "HIST_BINS",
]


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Static configuration of a closed loop (a change recompiles).

    Attributes:
        family_config: the family's own static configuration (horizon, options); stored in
            provenance records under its former name, ``family``.
        n_steps: MPC steps per run at most; a run not docked by then ends as TIMEOUT.
        settings: solver settings (mode, method, iteration caps).
        truth: "linear" or a nonlinear truth (:data:`rvdjax.loop.plant.TRUTHS`).
        truth_substeps: RK4 steps per sample time for the nonlinear truths.
        disturbed: the guidance sees a noisy state and the thrusters apply (1 + w) u with the
            Gauss-Markov error w, dropping pulses shorter than the minimum impulse bit
            (``params.plant.disturbances``).
        time_limit_s: a run also ends (TIMEOUT unless docked) after the first step whose end
            time reaches this limit [s] (paper 003 Ch. 4: 200 minutes per maneuver); None: no
            limit.
        nav_filter: the guidance sees the estimate of a Kalman filter fed by the noisy
            measurements instead of the measurements (:mod:`rvdjax.loop.navigation`; rvdjax's
            choice, the thesis has no filter). Needs ``disturbed``.
        actuation: fly the vehicle's thrusters (``params.plant.thrusters``): the command is
            allocated, modulated into valve pulses and the truth integrates the pulses
            (:mod:`rvdjax.actuators`); with ``disturbed`` the Gauss-Markov thrust error acts
            per thruster and the thrusters' own minimum on-time replaces the disturbances'
            minimum impulse bit. None: the truth applies the command exactly (ideal forces).
    """

    family_config: Any = dataclasses.field(metadata={"stored_as": "family"})
    n_steps: int = 200
    settings: SolverSettings = SolverSettings()
    truth: str = "linear"
    truth_substeps: int = 3
    disturbed: bool = False
    time_limit_s: float | None = None
    nav_filter: bool = False
    actuation: Actuation | None = None

    def __post_init__(self):
        if self.truth not in TRUTHS:
            raise ValueError(f"truth must be one of {TRUTHS}, got {self.truth!r}")
        for name in ("n_steps", "truth_substeps"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        lim = self.time_limit_s
        if lim is not None and (
            isinstance(lim, bool) or not isinstance(lim, numbers.Real) or not lim > 0
        ):
            raise ValueError(f"time_limit_s must be None or a number > 0 [s], got {lim!r}")
        if self.nav_filter and not self.disturbed:
            raise ValueError(
                "nav_filter=True needs disturbed=True (the filter works on the noisy "
                "measurements of a disturbed run)"
            )
        act = self.actuation
        if act is not None and act.modulator == "delta-sigma" and self.truth != "linear":
            raise ValueError(
                "the delta-sigma modulator needs truth='linear' (the nonlinear truths "
                "integrate pulses that start with the control period: pwm or schmitt)"
            )


@dataclasses.dataclass(frozen=True)
class Loop:
    """A family with its static loop configuration: everything that shapes the program."""

    family: Family
    config: LoopConfig

    def __post_init__(self):
        if self.config.truth not in self.family.truths:
            raise ValueError(
                f"truth={self.config.truth!r} is not available for the {self.family.name} "
                f"family; choose one of {self.family.truths}"
            )

    @property
    def N(self) -> int:
        return self.family.horizon(self.config.family_config)

    def replace(self, **changes) -> Loop:
        """A copy with LoopConfig fields changed (``settings=..., truth=..., n_steps=...``)."""
        return Loop(self.family, dataclasses.replace(self.config, **changes))


class LoopState(NamedTuple):
    """State of one run between MPC steps.

    Attributes:
        x: (nx,) true state.
        t: () time [s].
        k: () MPC steps taken.
        plan: the warm start (the previous plan, shifted) and linearisation guess.
        guidance: the family's guidance state.
        fresh: () the next solve starts cold (start of the run, phase change).
        active: () the run is in progress.
        docked: () the run docked.
        failed: () the truth became non-finite.
        orbit: the target's inertial state (nonlinear truths) or None.
        gm: (nu, 2) Gauss-Markov thrust-error states (zeros when undisturbed).
        key: the run's PRNG key (step keys derive from it and the step index).
        acc: the :class:`Accumulator`.
        nav: with ``nav_filter``, the filter's :class:`NavState` predicted to this step (a
            placeholder before the first measurement, k = 0); None otherwise.
        mod: with thrusters, (T,) the modulator's state (carried on-time, Schmitt state or
            delta-sigma integrator); None otherwise.
    """

    x: jnp.ndarray
    t: jnp.ndarray
    k: jnp.ndarray
    plan: Plan
    guidance: Any
    fresh: jnp.ndarray
    active: jnp.ndarray
    docked: jnp.ndarray
    failed: jnp.ndarray
    orbit: Any
    gm: jnp.ndarray
    key: jnp.ndarray
    acc: Accumulator
    nav: NavState | None = None
    mod: jnp.ndarray | None = None


class Prepared(NamedTuple):
    """A step between its two halves: the observed guidance state, the OCP, the rows that
    stand for hard constraints (for the INFEASIBLE status), the warm start and, with
    ``nav_filter``, the filter's estimate after this step's measurement update."""

    guidance: Any
    ocp: OCP
    hard: jnp.ndarray  # (N, m) 1.0 on hard rows
    warm: Plan
    nav: NavState | None = None


class StepInfo(NamedTuple):
    """Per-step record (leading axis: step when stacked by :func:`fly`)."""

    x: jnp.ndarray  # (nx,) true state at the step start
    u: jnp.ndarray  # (nu,) applied input (zero once finished; disturbed: after the errors)
    u_cmd: jnp.ndarray  # (nu,) commanded input
    t: jnp.ndarray  # () time at the step start [s]
    dt: jnp.ndarray  # () time the input acted [s] (0 once finished)
    phase: jnp.ndarray  # () guidance phase of the step
    status: jnp.ndarray  # solver status; INFEASIBLE only for hard rows (-1 once finished)
    solver_status: jnp.ndarray  # raw solver status (INFEASIBLE also for penalty rows)
    hard_violation: jnp.ndarray  # largest planned violation of the hard rows
    iterations: jnp.ndarray
    objective: jnp.ndarray
    active: jnp.ndarray  # the run was in progress at this step
    margins: dict  # name -> (m,) truth row slacks over the step [m] (+inf: row inactive)
    guidance: Any  # the family's guidance state used by this step
    pulses: Pulses | None = None  # with thrusters: the valve pulses of the step (T, P) [s]


# --------------------------------------------------------------------------------------------


def init(loop: Loop, params, x0, key=None) -> LoopState:
    """The state at the start of a run from ``x0`` (the PRNG ``key`` drives disturbances)."""
    fam, fc = loop.family, loop.config.family_config
    cfg, act = loop.config, loop.config.actuation
    plant = checked_plant(params, fam.name, act, cfg.disturbed, cfg.truth)
    dtype = jnp.result_type(float)
    x0 = jnp.asarray(x0, dtype)
    key = jax.random.key(0) if key is None else key
    g = fam.init(params, fc, x0)
    plan = fam.initial_plan(params, fc, g, x0)
    mod = None if act is None else jnp.zeros(act.n, dtype)
    n_axes = fam.layout.nu if act is None else act.n  # thrust errors per axis / per thruster
    if cfg.disturbed:
        gm = gm_init(jax.random.fold_in(key, 0), plant.disturbances, n_axes)
    else:
        gm = jnp.zeros((n_axes, 2), dtype)
    orbit = plant.orbit if cfg.truth != "linear" else None
    false = jnp.asarray(False)
    nav = None
    if loop.config.nav_filter:  # replaced by the first measurement (prepare, k = 0)
        nx = fam.layout.nx
        nav = NavState(jnp.zeros(nx, dtype), jnp.zeros((nx, nx), dtype))
    return LoopState(
        x=x0,
        t=jnp.zeros((), dtype),
        k=jnp.zeros((), jnp.int32),
        plan=plan,
        guidance=g,
        fresh=jnp.asarray(True),
        active=jnp.asarray(True),
        docked=false,
        failed=false,
        orbit=orbit,
        gm=gm,
        key=key,
        acc=empty_accumulator(loop, params, x0, g, dtype),
        nav=nav,
        mod=mod,
    )


def _keys(state: LoopState):
    """(navigation, actuator) keys of step k: fold_in(fold_in(run key, 1), k) (stream 0 of
    the run key seeds the initial thrust-error state)."""
    steps = jax.random.fold_in(state.key, 1)
    return jax.random.split(jax.random.fold_in(steps, state.k))


def prepare(loop: Loop, params, state: LoopState) -> Prepared:
    """First half of a step: observe, measure (and filter), build the OCP and the warm
    start."""
    fam, fc, lay = loop.family, loop.config.family_config, loop.family.layout
    # observe: the mode decisions the loop takes on the truth (entry-cone activation by the
    # true distance to the port; a no-op for the three-phase family, whose phase switches are
    # in update, also on the truth). Not the measured-state path: it keeps the true state
    # with or without the filter; the guidance's state estimate is x_meas below.
    g = fam.observe(params, fc, state.guidance, state.x, state.t, state.plan)
    x_meas = state.x
    nav = None
    if loop.config.disturbed:
        k_nav, _ = _keys(state)
        d = params.plant.disturbances
        x_meas = measure(k_nav, state.x, d, lay.pos, lay.vel, lay.att, k=state.k)
        if loop.config.nav_filter:
            R = measurement_covariance(lay, d, x_meas.dtype)
            first = state.k == 0
            nav = jax.tree.map(
                lambda a, b: jnp.where(first, a, b),
                nav_init(x_meas, R),
                nav_update(state.nav, x_meas, R),
            )
            x_meas = nav.x_hat
    ocp, blocks = fam.ocp(params, fc, g, x_meas, state.t, state.plan)
    warm = warm_start(ocp, loop.config.settings, state.plan, cold=state.fresh)
    return Prepared(g, ocp, hard_mask(blocks), warm, nav)


def _hard_violation(prep: Prepared, sol: Solution):
    """Largest row-normalised violation of the hard rows by the plan."""
    ocp = prep.ocp
    g = jnp.einsum("tmn,tn->tm", ocp.Fx, sol.x) - ocp.fx
    norm = jnp.maximum(jnp.linalg.norm(ocp.Fx, axis=-1), 1e-300)
    return jnp.max(jnp.maximum(g / norm, 0.0) * ocp.x_mask * prep.hard)


def _truth_margins(loop: Loop, params, g, xs, ts, mask):
    """{name: (m,)} smallest slack over the masked samples of each truth block."""
    fam, fc = loop.family, loop.config.family_config

    def one(x, t):
        return margins(fam.truth_blocks(params, fc, g, x, t), x)

    per_sample = jax.vmap(one)(xs, ts)
    return {n: jnp.min(jnp.where(mask[:, None], m, jnp.inf), axis=0) for n, m in per_sample.items()}


def advance(
    loop: Loop, params, sp: SolverParams, state: LoopState, prep: Prepared, sol: Solution
) -> tuple[LoopState, StepInfo]:
    """Second half of a step: command, actuator, plant, guidance update, accumulation."""
    fam, fc, cfg, lay = loop.family, loop.config.family_config, loop.config, loop.family.layout
    g = prep.guidance
    dtype = state.x.dtype
    active = state.active
    u_cmd = jnp.where(active, fam.control(params, fc, g, sol), 0.0)
    dt = fam.sample_time(params, g)
    k_act = _keys(state)[1] if cfg.disturbed else None
    plant = params.plant
    act = actuate(
        cfg, lay, plant, state.x, state.t, state.k, k_act, state.gm, state.mod, u_cmd, dt, active
    )
    u, fired = act.u, act.fired

    # INFEASIBLE from the solver means "a soft row is violated at the optimum"; penalty rows
    # (external costs of the paper) are not constraints, so only hard rows count.
    hard_violation = _hard_violation(prep, sol)
    status = jnp.where(
        (sol.status == Status.INFEASIBLE) & (hard_violation <= sp.violation_tol),
        Status.CONVERGED,
        sol.status,
    )

    A, B = fam.truth_model(params, g)
    nav_next = state.nav
    if cfg.nav_filter:  # prediction to the next step on the guidance's model of this step
        d = plant.disturbances
        R = measurement_covariance(lay, d, dtype)
        Qp = process_noise(B, act.u_believed, thrust_error_fraction(d, dt), R)
        nav_next = nav_predict(prep.nav, A, B, act.u_believed, Qp)
    x_next, orbit_next, taus, subs = truth_path(
        loop, params, A, B, state.orbit, state.x, act, dt, active
    )
    t_next = state.t + dt
    g_next, docked, dt_flown, sub_mask = fam.update(
        params, fc, g, state.x, u, x_next, state.t, dt, (taus, subs)
    )
    finite = jnp.all(jnp.isfinite(x_next))
    x_next = jnp.where(finite, x_next, state.x)

    # truth margins: the step start, and the sub-samples flown before docking
    xs = jnp.concatenate([state.x[None], subs], axis=0)
    ts_ = jnp.concatenate([state.t[None], state.t + taus])
    mask = jnp.concatenate([jnp.ones(1, bool), sub_mask])
    m = _truth_margins(loop, params, g, xs, ts_, mask)

    dt_flown = jnp.where(active, dt_flown, 0.0)
    info = StepInfo(
        x=state.x,
        u=u,
        u_cmd=u_cmd,
        t=state.t,
        dt=dt_flown,
        phase=jnp.asarray(getattr(g, "phase", 0), jnp.int32),
        status=jnp.where(active, status, -1),
        solver_status=jnp.where(active, sol.status, -1),
        hard_violation=jnp.where(active, hard_violation, 0.0),
        iterations=jnp.where(active, sol.iterations, 0),
        objective=sol.objective,
        active=active,
        margins=m,
        guidance=g,
        pulses=None
        if fired is None
        else jax.tree.map(lambda a: jnp.where(active, a, 0.0), fired.pulses),
    )
    acc = accumulate(loop, params, state.acc, info, fired)
    k_next = state.k + 1
    ended = docked | ~finite | (k_next >= cfg.n_steps)
    if cfg.time_limit_s is not None:
        ended = ended | (t_next >= cfg.time_limit_s)
    nxt = LoopState(
        x=x_next,
        t=t_next,
        k=k_next,
        plan=shift_solution(sol),
        guidance=g_next,
        fresh=getattr(g_next, "phase", 0) != getattr(g, "phase", 0),
        active=active & ~ended,
        docked=state.docked | docked,
        failed=state.failed | ~finite,
        orbit=orbit_next,
        gm=act.gm,
        key=state.key,
        acc=acc,
        nav=nav_next,
        mod=None if fired is None else fired.mod,
    )
    nxt = nxt._replace(fresh=jnp.asarray(nxt.fresh))
    # A finished run idles: its state stops changing.
    nxt = jax.tree.map(lambda a, b: jnp.where(active, a, b), nxt, state)
    return nxt, info


def step(loop: Loop, params, sp: SolverParams, state: LoopState):
    """One MPC decision: :func:`prepare`, a solve (skipped once the run has finished: a
    single run takes the cheap branch of ``lax.cond``), :func:`advance`."""
    prep = prepare(loop, params, state)
    sol = solve_if(state.active, prep.ocp, loop.config.settings, params=sp, init=prep.warm)
    return advance(loop, params, sp, state, prep, sol)


def fly(
    loop: Loop,
    params,
    x0,
    key=None,
    solver_params: SolverParams | None = None,
    remat: bool = False,
):
    """Fly one maneuver: ``n_steps`` MPC steps in one ``lax.scan``. Pure in (params, x0, key,
    solver_params): jit it, vmap it, differentiate it.

    ``remat``: wrap the step in ``jax.checkpoint``. Reverse mode then keeps only the loop
    state of each step and flies the step again (its solve included) in the backward pass,
    instead of keeping every step's solver residuals (the OCP and its factorised KKT
    matrix): memory per step falls from O(N nx^2) to the loop state, for about one more
    forward pass of compute. No effect on the values.

    Returns:
        (StepInfo with a leading step axis, Metrics).
    """
    sp = SolverParams.for_settings(loop.config.settings) if solver_params is None else solver_params
    state = varying_like(init(loop, params, x0, key), x0)  # vmap: one pass (rvdjax.batching)

    def one(s):
        return step(loop, params, sp, s)

    if remat:
        one = jax.checkpoint(one)

    def body(s, _):
        return one(s)

    last, infos = lax.scan(body, state, None, length=loop.config.n_steps)
    return infos, metrics(loop, params, last)
