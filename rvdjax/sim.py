"""Closed-loop MPC guidance: one `lax.scan` step per MPC decision (DESIGN §4).

This module flies the linear-model scenarios of paper 000 Sec. IV.A (``fastmpc-3d``): at every
step the OCP is rebuilt at the measured state, the moving keep-out zones are re-linearised
about the previous plan (paper 000 Eqs. 6-8, expansion points from "the reference trajectory
of the chaser from the previous iteration"), the solver is warm-started from the shifted
previous solution, u_0 is applied for Ts through a zero-order hold and the truth state is
propagated exactly (linear CW, matrix exponential) or, with ``LoopConfig.truth``, by the
nonlinear two-body / J2 propagator; ``LoopConfig.disturbed`` adds navigation noise and thrust
errors (:mod:`rvdjax.disturbances`). Runs that have reached the holding distance keep stepping
as no-ops under a mask, so a batch has one shape; the whole loop of one run is one pure
function of (parameters, x0, key), so it can be jitted, vmapped over initial conditions and
keys, and differentiated.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from rvdjax.disturbances import (
    Disturbances,
    actuate,
    sense,
    start,
)
from rvdjax.ocp import OCP
from rvdjax.problems import obstacle_rows
from rvdjax.propagate import Orbit, propagate_step
from rvdjax.solver import Plan, SolverSettings, Status, drift_plan, shift_solution, solve_if

__all__ = [
    "validate_loop",
    "LoopParams",
    "LoopConfig",
    "StepInfo",
    "Metrics",
    "run_closed_loop",
]


class LoopParams(NamedTuple):
    """Traced parameters of a linear closed loop (batchable, differentiable).

    Attributes:
        A: (nx, nx), B: (nx, nu) discrete model (also the truth), sample time ``ts``.
        Q: (nx, nx), R: (nu, nu), Q_f: (nx, nx) weights.
        u_max: (nu,) thrust box [N].
        x_ref: (nx,) holding state (the target sits at the origin).
        obstacles: (n_obs, 2 d) obstacle states (position, velocity) at t = 0 [m, m/s].
        radii: (n_obs,) spherical keep-out radii [m].
        obstacle_mask: (n_obs,) 1.0 for an obstacle that exists, 0.0 to switch it off.
        rho: () exact penalty of the keep-out rows.
        ts: () sample time [s].
        mass: () chaser mass [kg] (for delta-v).
        stop_radius: () the run ends when |r| <= stop_radius [m] (paper 000: 2.3 m).
        orbit: the target's inertial state (:class:`rvdjax.propagate.Orbit`) for a nonlinear
            truth (``LoopConfig.truth``); None for the linear truth.
        disturbances: navigation noise, thrust-amplitude error and minimum impulse bit
            (:mod:`rvdjax.disturbances`) of a disturbed run (``LoopConfig.disturbed``).
    """

    A: jnp.ndarray
    B: jnp.ndarray
    Q: jnp.ndarray
    R: jnp.ndarray
    Q_f: jnp.ndarray
    u_max: jnp.ndarray
    x_ref: jnp.ndarray
    obstacles: jnp.ndarray
    radii: jnp.ndarray
    obstacle_mask: jnp.ndarray
    rho: jnp.ndarray
    ts: jnp.ndarray
    mass: jnp.ndarray
    stop_radius: jnp.ndarray
    orbit: Orbit | None = None
    disturbances: Disturbances | None = None


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Static configuration: shapes and the solver.

    Attributes:
        N: horizon.
        n_steps: MPC steps simulated (the scan length); finished runs idle.
        settings: solver settings (paper or accurate mode).
        truth: "linear" (the model itself, exact), "two-body" or "two-body-j2": the chaser and
            the target integrated in the inertial frame (RK4, ``substeps`` per Ts, thrust held
            constant in the LVLH frame; :mod:`rvdjax.propagate`) — model mismatch.
        substeps: RK4 steps per sample time for the nonlinear truth.
        disturbed: the guidance sees a noisy state and the thrusters apply (1 + w) u with the
            Gauss-Markov error w, dropping pulses shorter than the minimum impulse bit
            (``LoopParams.disturbances``; needs a PRNG key).
    """

    N: int = 30
    n_steps: int = 200
    settings: SolverSettings = SolverSettings()
    truth: str = "linear"
    substeps: int = 3
    disturbed: bool = False

    def __post_init__(self):
        if self.truth not in ("linear", "two-body", "two-body-j2"):
            raise ValueError(
                f"truth must be 'linear', 'two-body' or 'two-body-j2', got {self.truth!r}"
            )
        if self.N < 1 or self.n_steps < 1 or self.substeps < 1:
            raise ValueError("N, n_steps and substeps must be >= 1")


class StepInfo(NamedTuple):
    """Per-step record (leading axis: step)."""

    x: jnp.ndarray  # (nx,) true state at the start of the step
    u: jnp.ndarray  # (nu,) applied input [N] (zero after docking; disturbed: after the errors)
    status: jnp.ndarray  # solver status (-1 after docking: no solve needed)
    iterations: jnp.ndarray
    objective: jnp.ndarray
    active: jnp.ndarray  # the run was still flying at this step
    keepout_margin: jnp.ndarray  # (n_obs,) |r - o_j| - r_j of the truth at the step start [m]


class Metrics(NamedTuple):
    """Per-run figures of merit (DESIGN §4)."""

    docked: jnp.ndarray  # reached |r| <= stop_radius within n_steps
    time_to_dock_s: jnp.ndarray  # first time |r| <= stop_radius [s] (inf if never)
    total_impulse_N_s: jnp.ndarray  # sum_k ||u_k||_2 Ts
    effort_l1_N_s: jnp.ndarray  # sum_k ||u_k||_1 Ts (paper 001 Eq. 14)
    delta_v_m_s: jnp.ndarray  # sum_k ||u_k||_2 Ts / m
    max_violation_m: jnp.ndarray  # largest keep-out penetration of the truth at the samples
    status_counts: jnp.ndarray  # (4,) solver statuses over the active steps
    mean_iterations: jnp.ndarray


def validate_loop(p: LoopParams, x0, config: LoopConfig | None = None) -> None:
    """Check a concrete closed-loop set-up before anything runs; ValueError names the field.

    Checks: every field and x0 finite; mass, ts, stop_radius, rho, radii, u_max > 0; R positive
    definite, Q and Q_f positive semidefinite; x0 outside every active keep-out zone; the
    horizon and step count >= 1.
    """
    import numpy as np

    for name, a in list(zip(LoopParams._fields, p, strict=True)) + [("x0", x0)]:
        if a is None:
            continue
        if not np.all(np.isfinite(np.asarray(a, dtype=float))):
            raise ValueError(f"{name} contains NaN or inf; it must be finite")
    for name in ("mass", "ts", "stop_radius", "rho"):
        value = float(getattr(p, name))
        if value <= 0:
            unit = {"mass": " kg", "ts": " s", "stop_radius": " m"}.get(name, "")
            raise ValueError(f"{name} must be > 0{unit}, got {value}")
    if np.any(np.asarray(p.u_max) <= 0):
        raise ValueError(f"u_max must be > 0 N on every axis, got {np.asarray(p.u_max)}")
    if np.any(np.asarray(p.radii) <= 0):
        raise ValueError(f"radii (keep-out) must be > 0 m, got {np.asarray(p.radii)}")
    if np.min(np.linalg.eigvalsh(np.asarray(p.R))) <= 0:
        raise ValueError("R must be positive definite")
    for name in ("Q", "Q_f"):
        M = np.asarray(getattr(p, name))
        if np.min(np.linalg.eigvalsh(0.5 * (M + M.T))) < -1e-10 * max(1.0, np.abs(M).max()):
            raise ValueError(f"{name} must be positive semidefinite")
    d = np.asarray(p.obstacles).shape[-1] // 2
    x0 = np.asarray(x0, dtype=float)
    gaps = np.linalg.norm(x0[:d][None] - np.asarray(p.obstacles)[:, :d], axis=-1)
    inside = (gaps <= np.asarray(p.radii)) & (np.asarray(p.obstacle_mask) > 0)
    if np.any(inside):
        j = int(np.flatnonzero(inside)[0])
        raise ValueError(
            f"x0 starts inside keep-out zone {j + 1} (distance {gaps[j]:.3g} m to its centre, "
            f"radius {float(np.asarray(p.radii)[j]):.3g} m)"
        )
    if config is not None and config.truth != "linear" and p.orbit is None:
        raise ValueError(f"truth={config.truth!r} needs LoopParams.orbit (the target's orbit)")
    if config is not None and config.disturbed and p.disturbances is None:
        raise ValueError("a disturbed run needs LoopParams.disturbances")


def _box_rows(u_max, N):
    nu = u_max.shape[0]
    eye = jnp.eye(nu, dtype=u_max.dtype)
    Fu = jnp.broadcast_to(jnp.concatenate([eye, -eye]), (N, 2 * nu, nu))
    fu = jnp.broadcast_to(jnp.concatenate([u_max, u_max]), (N, 2 * nu))
    return Fu, fu


def build_ocp(p: LoopParams, x, t, p_guess, N: int) -> OCP:
    """The OCP at state x and time t, keep-out rows linearised about ``p_guess`` (N, d)."""
    nx, nu = p.B.shape
    d = p.obstacles.shape[-1] // 2
    times = t + p.ts * jnp.arange(1, N + 1, dtype=x.dtype)
    centres = p.obstacles[None, :, :d] + times[:, None, None] * p.obstacles[None, :, d:]
    Fx, fx = obstacle_rows(p_guess, centres, p.radii, nx=nx)
    n_obs = p.radii.shape[0]
    Q = jnp.broadcast_to(p.Q, (N, nx, nx)).at[-1].set(p.Q_f)
    Fu, fu = _box_rows(p.u_max, N)
    zeros_x = jnp.zeros((N, nx), x.dtype)
    return OCP(
        A=jnp.broadcast_to(p.A, (N, nx, nx)),
        B=jnp.broadcast_to(p.B, (N, nx, nu)),
        c=zeros_x,
        x0=x,
        Q=Q,
        R=jnp.broadcast_to(p.R, (N, nu, nu)),
        x_ref=jnp.broadcast_to(p.x_ref, (N, nx)),
        q=zeros_x,
        r=jnp.zeros((N, nu), x.dtype),
        Fu=Fu,
        fu=fu,
        u_mask=jnp.ones((N, 2 * nu), x.dtype),
        Fx=Fx,
        fx=fx,
        rho=jnp.broadcast_to(p.rho, (N, n_obs)),
        x_mask=jnp.broadcast_to(p.obstacle_mask, (N, n_obs)),
    )


class _Carry(NamedTuple):
    x: jnp.ndarray
    t: jnp.ndarray
    plan: Plan
    active: jnp.ndarray
    orbit: Orbit | None = None
    key: jnp.ndarray | None = None  # PRNG key (disturbed runs)
    gm: jnp.ndarray | None = None  # (nu, 2) Gauss-Markov thrust-error states


def run_closed_loop(p: LoopParams, x0, config: LoopConfig = LoopConfig(), key=None):
    """Fly one maneuver from x0. Pure: jit, vmap over (p, x0, key) and grad apply.

    ``key`` (a PRNG key) drives the navigation noise and thrust error of a disturbed run
    (``config.disturbed``); undisturbed runs ignore it. Docking and the keep-out margins are
    judged on the true state.

    Returns:
        (StepInfo with a leading axis of n_steps, Metrics).
    """
    N = config.N
    nx, nu = p.B.shape
    d = p.obstacles.shape[-1] // 2
    dtype = p.A.dtype
    x0 = jnp.asarray(x0, dtype)

    # First expansion points: the unforced drift of x0 (a straight line to the target can
    # cross an obstacle and leave no feasible plan).
    init = drift_plan(p.A, x0, N, nu)
    if config.truth != "linear" and p.orbit is None:
        raise ValueError(f"truth={config.truth!r} needs LoopParams.orbit (the target's orbit)")
    orbit0 = p.orbit if config.truth != "linear" else None
    active0 = jnp.linalg.norm(x0[:d]) > p.stop_radius
    key, gm0 = start(config.disturbed, p.disturbances, key, nu, "LoopParams")
    carry0 = _Carry(x0, jnp.zeros((), dtype), init, active0, orbit0, key, gm0)

    def step(c: _Carry, _):
        key, k_act, x_meas = sense(
            config.disturbed, c.key, c.x, p.disturbances, tuple(range(d)), tuple(range(d, 2 * d))
        )
        ocp = build_ocp(p, x_meas, c.t, c.plan.x[:, :d], N)

        sol = solve_if(c.active, ocp, config.settings, init=c.plan)
        u = jnp.where(c.active, sol.u[0], 0.0)
        u, gm_next = actuate(  # force input: impulse F Ts
            config.disturbed, k_act, c.gm, u, p.disturbances, p.ts, p.ts, tuple(range(nu))
        )
        if config.truth == "linear":
            x_next, orbit_next = p.A @ c.x + p.B @ u, None
        else:
            orbit_next, x_next = propagate_step(
                c.orbit, c.x, u, p.mass, p.ts, config.substeps, config.truth == "two-body-j2"
            )
        centres = p.obstacles[:, :d] + c.t * p.obstacles[:, d:]
        margin = jnp.linalg.norm(c.x[:d][None] - centres, axis=-1) - p.radii
        margin = jnp.where(p.obstacle_mask > 0, margin, jnp.inf)
        info = StepInfo(
            x=c.x,
            u=u,
            status=jnp.where(c.active, sol.status, -1),
            iterations=jnp.where(c.active, sol.iterations, 0),
            objective=sol.objective,
            active=c.active,
            keepout_margin=margin,
        )
        active = c.active & (jnp.linalg.norm(x_next[:d]) > p.stop_radius)
        nxt = _Carry(x_next, c.t + p.ts, shift_solution(sol), active, orbit_next, key, gm_next)
        # A finished run idles: its carry stops changing.
        nxt = jax.tree.map(lambda a, b: jnp.where(c.active, a, b), nxt, c)
        return nxt, info

    last, infos = lax.scan(step, carry0, None, length=config.n_steps)
    return infos, _metrics(p, infos, last)


def _metrics(p: LoopParams, infos: StepInfo, last: _Carry) -> Metrics:
    n_active = jnp.sum(infos.active)
    docked = ~last.active
    impulse = jnp.sum(jnp.linalg.norm(infos.u, axis=-1)) * p.ts
    effort_l1 = jnp.sum(jnp.abs(infos.u)) * p.ts
    counts = Status.counts(infos.status, infos.active)
    return Metrics(
        docked=docked,
        time_to_dock_s=jnp.where(docked, n_active * p.ts, jnp.inf),
        total_impulse_N_s=impulse,
        effort_l1_N_s=effort_l1,
        delta_v_m_s=impulse / p.mass,
        max_violation_m=jnp.maximum(
            0.0, -jnp.min(jnp.where(infos.active[:, None], infos.keepout_margin, jnp.inf))
        ),
        status_counts=counts,
        mean_iterations=jnp.sum(infos.iterations) / jnp.maximum(n_active, 1),
    )


def run_reference_loop(p: LoopParams, x0, config: LoopConfig = LoopConfig(), solver=None):
    """The same closed loop driven step by step from Python through a reference QP solver.

    Every step builds the identical OCP (:func:`build_ocp`, keep-out rows about the previous
    plan), converts it with :func:`rvdjax.qp.to_qp` (soft form, so it is exactly the problem
    rvdjax solves) and calls ``solver`` (default Clarabel, reference tolerances). Used to check
    that rvdjax flies the same trajectory, and as the "Clarabel in the loop" baseline.

    Returns:
        (StepInfo as NumPy arrays, Metrics as NumPy values, seconds spent in the solver).
    """
    import numpy as np

    from rvdjax.peers import solve_clarabel
    from rvdjax.qp import split_solution, to_qp

    solver = solver or solve_clarabel
    if config.truth != "linear":
        raise ValueError("run_reference_loop supports the linear truth only")
    N, n_steps = config.N, config.n_steps
    nx, nu = p.B.shape
    d = p.obstacles.shape[-1] // 2
    A, B = np.asarray(p.A), np.asarray(p.B)
    x = np.asarray(x0, dtype=float)
    plan_x = np.zeros((N, nx))
    xd = x.copy()
    for i in range(N):  # unforced drift: the first expansion points
        xd = A @ xd
        plan_x[i] = xd
    t, active, solve_s = 0.0, np.linalg.norm(x[:d]) > float(p.stop_radius), 0.0
    rec = {k: [] for k in StepInfo._fields}
    for _ in range(n_steps):
        centres = np.asarray(p.obstacles)[:, :d] + t * np.asarray(p.obstacles)[:, d:]
        margin = np.linalg.norm(x[:d][None] - centres, axis=-1) - np.asarray(p.radii)
        margin = np.where(np.asarray(p.obstacle_mask) > 0, margin, np.inf)
        if active:
            ocp = build_ocp(p, jnp.asarray(x), jnp.asarray(t), jnp.asarray(plan_x[:, :d]), N)
            res = solver(to_qp(ocp, soft=True))
            solve_s += res.solve_ms / 1e3
            u_plan, x_plan = split_solution(res.z, N, nx, nu)
            u = u_plan[0]
            plan_x = np.concatenate([x_plan[1:], x_plan[-1:]])
            status = 0 if res.status in ("Solved",) else 1
            its, obj = res.iterations, res.objective
        else:
            u, status, its, obj = np.zeros(nu), -1, 0, np.nan
        for k, v in zip(StepInfo._fields, (x, u, status, its, obj, active, margin), strict=True):
            rec[k].append(np.asarray(v))
        if active:
            x = A @ x + B @ u
            t += float(p.ts)
            active = np.linalg.norm(x[:d]) > float(p.stop_radius)
    infos = StepInfo(*(np.stack(rec[k]) for k in StepInfo._fields))
    last = _Carry(jnp.asarray(x), jnp.asarray(t), None, jnp.asarray(active))
    return infos, jax.tree.map(np.asarray, _metrics(p, infos, last)), solve_s
