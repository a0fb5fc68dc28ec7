"""Planar two-phase docking to a rotating target (paper 002; LQ-MPC version).

The chaser is a planar 3-DOF air-bearing vehicle (x, y, theta, vx, vy, omega; inputs Fx, Fy,
torque). The target rotates at a constant rate about a fixed centre; its docking port sits
on its keep-out circle and points outward along the body axis. Paper 002 Fig. 4, as flown
here at every MPC step:

1. Free-flying phase: track the holding position (on the dynamic circle r_hold, plus a small
   gap, straight in front of the port), staying outside the fixed keep-out circle r_t and the
   dynamic circle r_hold (both linearised about the previous plan, paper 000 Eqs. 8-9).
2. When the distance error alpha_1 < c_alpha1 and the attitude error alpha_2 < c_alpha2, the
   final docking phase starts: the entry cone (two hyperplanes through the docking point,
   paper 002 Eqs. 5-6) is enforced over the horizon, and each step with both errors below
   their thresholds shrinks r_hold by gamma, down to r_t.
3. Docked when r_hold has reached r_t and the chaser is within ``dock_tol`` of the holding
   position at the port with the attitude error below c_alpha2.

The same loop flies paper 000's 2-D SPOT cases (``DockingConfig(logic="holding-radius")``):
the target also translates, two obstacles move on straight lines (circular keep-out zones),
r_hold shrinks by gamma whenever the position error < eta (``c_pos``) and the attitude error
< zeta (``c_att``) down to r_hold,min (paper 000 Sec. II.C.3), and the entry cone is active
whenever the chaser is within r_cone of the docking point (paper 000 Sec. IV.B).

The target's attitude and holding position are predicted over the horizon (paper 002: "the
holding position is predictable with the given radius ... and the constant angular velocity").
Paper 002 solves this with NMPC (IPOPT); rvdjax solves the linearised (LQ) problem with its
QP solver, so its figures differ by construction.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from rvdjax.constraints import entry_cone_rows, holding_radius_rows, thrust_box_rows
from rvdjax.disturbances import (
    LAB_DISTURBANCES,
    Disturbances,
    actuate,
    disturbances,
    sense,
    start,
)
from rvdjax.ocp import OCP
from rvdjax.solver import Plan, SolverSettings, Status, drift_plan, shift_solution, solve_if

__all__ = [
    "DockingParams",
    "DockingConfig",
    "DockingInfo",
    "DockingMetrics",
    "docking_params",
    "fly_docking",
]

POS = (0, 1)


class DockingParams(NamedTuple):
    """Traced parameters (SI units, angles in rad).

    Attributes:
        A, B: (6, 6), (6, 3) discrete planar 3-DOF model (ZOH), also the truth.
        Q, R, Q_f: weights (Q_f: DARE solution).
        u_max: (3,) limits on Fx, Fy [N] and torque [N m].
        target: (3,) target centre x, y [m] and initial attitude [rad] (port direction).
        target_rate: () target angular rate [rad/s].
        r_t: () fixed keep-out radius about the target centre [m].
        r_hold0: () initial dynamic keep-out radius [m].
        r_min: () smallest holding radius (docked) [m].
        r_port: () distance of the docking point (entry-cone apex) from the target centre [m].
        target_vel: (2,) target translational velocity [m/s].
        cone_radius: () "holding-radius" logic: the entry cone is active within this distance
            of the docking point [m].
        obstacles: (n_obs, 4) obstacle x, y, vx, vy at t = 0; obstacle_radii: (n_obs,);
            obstacle_mask: (n_obs,) 1.0 for an obstacle that exists.
        gap: () holding position distance outside the dynamic circle [m].
        gamma: () shrink factor of r_hold per qualifying step, in (0, 1).
        c_pos: () alpha_1 threshold [m]; c_att: () alpha_2 threshold [rad].
        half_angle: () entry-cone half angle [rad].
        rho: () exact penalty of the soft state rows.
        ts: () sample time [s]; dock_tol: () docked position tolerance [m].
        mass: () chaser mass [kg] (for delta-v).
        disturbances: navigation noise and thrust error of a disturbed run
            (:mod:`rvdjax.disturbances`, ``DockingConfig.disturbed``).
    """

    A: jnp.ndarray
    B: jnp.ndarray
    Q: jnp.ndarray
    R: jnp.ndarray
    Q_f: jnp.ndarray
    u_max: jnp.ndarray
    target: jnp.ndarray
    target_rate: jnp.ndarray
    r_t: jnp.ndarray
    r_hold0: jnp.ndarray
    r_min: jnp.ndarray
    r_port: jnp.ndarray
    target_vel: jnp.ndarray
    cone_radius: jnp.ndarray
    obstacles: jnp.ndarray
    obstacle_radii: jnp.ndarray
    obstacle_mask: jnp.ndarray
    gap: jnp.ndarray
    gamma: jnp.ndarray
    c_pos: jnp.ndarray
    c_att: jnp.ndarray
    half_angle: jnp.ndarray
    rho: jnp.ndarray
    ts: jnp.ndarray
    dock_tol: jnp.ndarray
    mass: jnp.ndarray
    disturbances: Disturbances | None = None


@dataclasses.dataclass(frozen=True)
class DockingConfig:
    """Static configuration.

    Attributes:
        N: horizon; n_steps: MPC steps simulated; settings: solver settings.
        logic: "two-phase" (paper 002 Fig. 4) or "holding-radius" (paper 000 Sec. II.C.3).
        disturbed: the guidance sees a noisy state (position, velocity, attitude) and the
            thrusters apply (1 + w) u with the Gauss-Markov error w; force pulses shorter than
            the minimum impulse bit are dropped (``DockingParams.disturbances``; needs a key).
    """

    N: int = 40
    n_steps: int = 150
    settings: SolverSettings = SolverSettings()
    logic: str = "two-phase"
    disturbed: bool = False

    def __post_init__(self):
        if self.logic not in ("two-phase", "holding-radius"):
            raise ValueError(f"logic must be 'two-phase' or 'holding-radius', got {self.logic!r}")


class DockingInfo(NamedTuple):
    """Per-step record (leading axis: step)."""

    x: jnp.ndarray  # (6,) state at the step start
    u: jnp.ndarray  # (3,) applied input
    r_hold: jnp.ndarray  # dynamic radius used at this step
    phase: jnp.ndarray  # 0 free flying, 1 final approach
    status: jnp.ndarray  # solver status (-1 once docked)
    iterations: jnp.ndarray
    active: jnp.ndarray
    koz_margin: jnp.ndarray  # |p - c| - r_t of the truth [m]
    obstacle_margin: jnp.ndarray  # (n_obs,) |p - o_j| - r_j of the truth [m]
    cone_margin: jnp.ndarray  # smallest entry-cone row slack of the truth in phase 1 [m]


class DockingMetrics(NamedTuple):
    """Per-run figures (names shared with :class:`rvdjax.sim.Metrics`)."""

    docked: jnp.ndarray
    time_to_dock_s: jnp.ndarray
    total_impulse_N_s: jnp.ndarray  # sum_k ||(Fx, Fy)||_2 Ts
    effort_l1_N_s: jnp.ndarray  # sum_k (|Fx| + |Fy|) Ts (paper 002 Eq. 11, forces only)
    delta_v_m_s: jnp.ndarray  # total impulse / mass
    torque_l1_N_m_s: jnp.ndarray
    max_violation_m: jnp.ndarray  # keep-out penetration of the truth (target and obstacles)
    status_counts: jnp.ndarray
    mean_iterations: jnp.ndarray


def docking_params(
    *,
    mass: float,
    inertia: float,
    ts: float,
    Q,
    R,
    u_max,
    target,
    target_rate_deg_s: float,
    r_t: float,
    r_hold0: float,
    gap: float,
    gamma: float,
    r_min: float | None = None,
    r_port: float | None = None,
    target_vel=(0.0, 0.0),
    cone_radius: float = float("inf"),
    obstacles=None,
    obstacle_radii=None,
    c_pos: float,
    c_att_deg: float,
    half_angle_deg: float,
    rho: float = 1e5,
    dock_tol: float = 0.05,
    x0=None,
) -> DockingParams:
    """Build and check :class:`DockingParams` from physical values (before any jit).

    Raises ValueError naming the parameter: mass, inertia, ts, radii, tolerances > 0;
    gamma in (0, 1); half angle in (0, 90) deg; r_hold0 > r_t; R positive definite; x0 (if
    given) outside the fixed keep-out circle and finite.
    """
    import numpy as np

    from rvdjax.dynamics import dare, discretize_zoh, planar3dof_continuous

    for name, v in (
        ("mass", mass),
        ("inertia", inertia),
        ("ts", ts),
        ("r_t", r_t),
        ("r_hold0", r_hold0),
        ("c_pos", c_pos),
        ("c_att_deg", c_att_deg),
        ("rho", rho),
        ("dock_tol", dock_tol),
    ):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be finite and > 0, got {v}")
    if not 0.0 < gamma < 1.0:
        raise ValueError(f"gamma (holding-radius shrink factor) must be in (0, 1), got {gamma}")
    if not 0.0 < half_angle_deg < 90.0:
        raise ValueError(
            f"half_angle_deg (entry cone) must be in (0, 90) deg, got {half_angle_deg}"
        )
    r_min = r_t if r_min is None else r_min
    r_port = r_t if r_port is None else r_port
    if not r_t <= r_min < r_hold0:
        raise ValueError(
            f"radii must satisfy r_t <= r_min < r_hold0, got r_t={r_t}, r_min={r_min}, "
            f"r_hold0={r_hold0} m"
        )
    if not 0 < r_port <= r_min:
        raise ValueError(f"r_port must be in (0, r_min], got {r_port} m")
    if obstacles is None:  # one inactive placeholder keeps the shapes fixed
        obstacles, obstacle_radii, obstacle_mask = np.zeros((1, 4)), np.ones(1), np.zeros(1)
    else:
        obstacles = np.asarray(obstacles, dtype=float).reshape(-1, 4)
        obstacle_radii = np.asarray(obstacle_radii, dtype=float).reshape(-1)
        obstacle_mask = np.ones(len(obstacle_radii))
        if np.any(obstacle_radii <= 0):
            raise ValueError(f"obstacle_radii must be > 0 m, got {obstacle_radii}")
    if gap < 0:
        raise ValueError(f"gap must be >= 0 m, got {gap}")
    R = np.asarray(R, dtype=float)
    if np.min(np.linalg.eigvalsh(R)) <= 0:
        raise ValueError("R must be positive definite")
    if np.any(np.asarray(u_max, dtype=float) <= 0):
        raise ValueError(f"u_max must be > 0 on every input, got {u_max}")
    target = np.asarray(target, dtype=float)
    if x0 is not None:
        x0 = np.asarray(x0, dtype=float)
        if not np.all(np.isfinite(x0)):
            raise ValueError("x0 contains NaN or inf")
        dist = float(np.linalg.norm(x0[:2] - target[:2]))
        if dist <= r_t:
            raise ValueError(
                f"x0 starts inside the target keep-out zone ({dist:.3g} m from its centre, "
                f"radius {r_t} m)"
            )
        gaps = np.linalg.norm(x0[:2][None] - obstacles[:, :2], axis=1)
        inside = (gaps <= obstacle_radii) & (obstacle_mask > 0)
        if np.any(inside):
            j = int(np.flatnonzero(inside)[0])
            raise ValueError(
                f"x0 starts inside obstacle keep-out zone {j + 1} ({gaps[j]:.3g} m from its "
                f"centre, radius {obstacle_radii[j]} m)"
            )
    Ac, Bc = planar3dof_continuous(mass, inertia)
    A, B = discretize_zoh(Ac, Bc, ts)
    Q = jnp.asarray(Q, dtype=float)
    P = dare(A, B, Q, jnp.asarray(R))
    f = jnp.asarray
    return DockingParams(
        A=A,
        B=B,
        Q=Q,
        R=f(R),
        Q_f=P,
        u_max=f(u_max, dtype=float),
        target=f(target),
        target_rate=f(np.deg2rad(target_rate_deg_s)),
        r_t=f(r_t),
        r_hold0=f(r_hold0),
        gap=f(gap),
        gamma=f(gamma),
        c_pos=f(c_pos),
        c_att=f(np.deg2rad(c_att_deg)),
        half_angle=f(np.deg2rad(half_angle_deg)),
        rho=f(rho),
        ts=f(ts),
        dock_tol=f(dock_tol),
        mass=f(mass),
        r_min=f(r_min),
        r_port=f(r_port),
        target_vel=f(np.asarray(target_vel, dtype=float)),
        cone_radius=f(cone_radius),
        obstacles=f(obstacles),
        obstacle_radii=f(obstacle_radii),
        obstacle_mask=f(obstacle_mask),
        disturbances=disturbances(**LAB_DISTURBANCES),
    )


def _wrap(a):
    return (a + jnp.pi) % (2.0 * jnp.pi) - jnp.pi


def _target_at(p: DockingParams, times):
    """Target centre (..., 2) and port axis angle (...) at the given times."""
    centre = p.target[:2] + times[..., None] * p.target_vel
    return centre, p.target[2] + p.target_rate * times


def _geometry(p: DockingParams, t, r_hold, N: int):
    """Predicted port axis angles, target centres, docking points, holding points and their
    velocities over the horizon (stage instants t + (j + 1) Ts)."""
    times = t + p.ts * jnp.arange(1, N + 1, dtype=p.A.dtype)
    centre, phi = _target_at(p, times)
    e = jnp.stack([jnp.cos(phi), jnp.sin(phi)], axis=-1)
    dock = centre + p.r_port * e
    hold = centre + (r_hold + p.gap) * e
    # holding point velocity: target velocity + omega x (hold - centre)
    v_hold = p.target_vel + p.target_rate * (r_hold + p.gap) * jnp.stack(
        [-jnp.sin(phi), jnp.cos(phi)], -1
    )
    return phi, centre, dock, hold, v_hold


def _reference(p, x, phi, hold, v_hold):
    """Holding state per stage: position, attitude facing the port (theta = phi + pi, unwrapped
    near the current attitude), holding-point velocity and the target's rate."""
    theta_ref = x[2] + _wrap(phi + jnp.pi - x[2])
    N = phi.shape[0]
    return jnp.concatenate(
        [hold, theta_ref[:, None], v_hold, jnp.full((N, 1), p.target_rate)], axis=-1
    )


def _build_ocp(p: DockingParams, x, t, r_hold, cone_on, p_guess, N: int):
    """Rows: fixed keep-out r_t, dynamic circle r_hold, entry cone (2, masked by ``cone_on``),
    one per obstacle (masked by ``obstacle_mask``)."""
    phi, centre, dock, hold, v_hold = _geometry(p, t, r_hold, N)
    x_ref = _reference(p, x, phi, hold, v_hold)
    F1, f1 = holding_radius_rows(p_guess, centre, p.r_t, 6, POS)
    F2, f2 = holding_radius_rows(p_guess, centre, r_hold, 6, POS)
    F3, f3 = entry_cone_rows(dock, phi, p.half_angle, 6, POS)
    times = t + p.ts * jnp.arange(1, N + 1, dtype=p.A.dtype)
    obs_c = p.obstacles[None, :, :2] + times[:, None, None] * p.obstacles[None, :, 2:]
    Fo, fo = jax.vmap(
        lambda c, r: holding_radius_rows(p_guess, c, r, 6, POS), in_axes=(1, 0), out_axes=1
    )(obs_c, p.obstacle_radii)
    n_obs = p.obstacle_radii.shape[0]
    Fx = jnp.concatenate([F1, F2, F3, Fo.reshape(N, n_obs, 6)], axis=1)
    fx = jnp.concatenate([f1, f2, f3, fo.reshape(N, n_obs)], axis=1)
    x_mask = jnp.concatenate(
        [
            jnp.ones((N, 2), x.dtype),
            jnp.broadcast_to(cone_on.astype(x.dtype), (N, 2)),
            jnp.broadcast_to(p.obstacle_mask, (N, n_obs)),
        ],
        axis=1,
    )
    Fu, fu = thrust_box_rows(p.u_max, N)
    Q = jnp.broadcast_to(p.Q, (N, 6, 6)).at[-1].set(p.Q_f)
    zeros = jnp.zeros((N, 6), x.dtype)
    return OCP(
        A=jnp.broadcast_to(p.A, (N, 6, 6)),
        B=jnp.broadcast_to(p.B, (N, 6, 3)),
        c=zeros,
        x0=x,
        Q=Q,
        R=jnp.broadcast_to(p.R, (N, 3, 3)),
        x_ref=x_ref,
        q=zeros,
        r=jnp.zeros((N, 3), x.dtype),
        Fu=Fu,
        fu=fu,
        u_mask=jnp.ones(fu.shape, x.dtype),
        Fx=Fx,
        fx=fx,
        rho=jnp.full(fx.shape, p.rho, x.dtype),
        x_mask=x_mask,
    )


class _Carry(NamedTuple):
    x: jnp.ndarray
    t: jnp.ndarray
    plan: Plan
    r_hold: jnp.ndarray
    phase: jnp.ndarray
    active: jnp.ndarray
    key: jnp.ndarray | None = None  # PRNG key (disturbed runs)
    gm: jnp.ndarray | None = None  # (3, 2) Gauss-Markov thrust-error states


def fly_docking(p: DockingParams, x0, config: DockingConfig = DockingConfig(), key=None):
    """Fly one docking maneuver. Pure function of (p, x0, key): jit / vmap apply.

    ``key`` drives the navigation noise and thrust error of a disturbed run
    (``config.disturbed``); undisturbed runs ignore it. The shrink rule, docking and the
    margins are judged on the true state.

    Returns:
        (DockingInfo with a leading axis of n_steps, DockingMetrics).
    """
    N = config.N
    dtype = p.A.dtype
    x0 = jnp.asarray(x0, dtype)
    two_phase = config.logic == "two-phase"

    init = drift_plan(p.A, x0, N, 3)
    key, gm0 = start(config.disturbed, p.disturbances, key, 3, "DockingParams")
    carry0 = _Carry(
        x0, jnp.zeros((), dtype), init, p.r_hold0, jnp.asarray(0), jnp.asarray(True), key, gm0
    )

    def cone_active(c: _Carry):
        if two_phase:  # paper 002: from the phase switch on
            return c.phase > 0
        centre, phi = _target_at(p, c.t)  # paper 000: within r_cone of the docking point
        dock = centre + p.r_port * jnp.stack([jnp.cos(phi), jnp.sin(phi)])
        return jnp.linalg.norm(c.x[:2] - dock) < p.cone_radius

    def step(c: _Carry, _):
        cone_on = cone_active(c)
        key, k_act, x_meas = sense(config.disturbed, c.key, c.x, p.disturbances, POS, (3, 4), (2,))
        ocp = _build_ocp(p, x_meas, c.t, c.r_hold, cone_on, c.plan.x[:, :2], N)

        sol = solve_if(c.active, ocp, config.settings, init=c.plan)
        u = jnp.where(c.active, sol.u[0], 0.0)
        # MIB on the force axes (the torque comes from thruster pairs), (1 + w) on every axis
        u, gm_next = actuate(config.disturbed, k_act, c.gm, u, p.disturbances, p.ts, p.ts, POS)
        x_next = p.A @ c.x + p.B @ u

        # Shrink rule on the state reached: errors to the current holding state.
        t_next = c.t + p.ts
        centre_n, phi_n = _target_at(p, t_next)
        hold_now = centre_n + (c.r_hold + p.gap) * jnp.stack([jnp.cos(phi_n), jnp.sin(phi_n)])
        alpha1 = jnp.linalg.norm(x_next[:2] - hold_now)
        alpha2 = jnp.abs(_wrap(phi_n + jnp.pi - x_next[2]))
        close = (alpha1 < p.c_pos) & (alpha2 < p.c_att)
        phase = jnp.where(close, 1, c.phase)
        # paper 002: shrink only in the final phase; paper 000: whenever both errors are small
        shrink = close & (c.phase > 0) if two_phase else close
        r_hold = jnp.where(shrink, jnp.maximum(p.gamma * c.r_hold, p.r_min), c.r_hold)
        at_port = c.r_hold <= p.r_min + 1e-9
        docked = at_port & (alpha1 < p.dock_tol) & (alpha2 < p.c_att)

        centre_c, phi_c = _target_at(p, c.t)
        dock_now = centre_c + p.r_port * jnp.stack([jnp.cos(phi_c), jnp.sin(phi_c)])
        Fc, fc = entry_cone_rows(dock_now[None], phi_c[None], p.half_angle, 6, POS)
        cone_slack = jnp.min(fc[0] - Fc[0] @ c.x)
        obs_now = p.obstacles[:, :2] + c.t * p.obstacles[:, 2:]
        obs_margin = jnp.linalg.norm(c.x[:2][None] - obs_now, axis=-1) - p.obstacle_radii
        info = DockingInfo(
            x=c.x,
            u=u,
            r_hold=c.r_hold,
            phase=jnp.where(two_phase, c.phase, cone_on.astype(c.phase.dtype)),
            status=jnp.where(c.active, sol.status, -1),
            iterations=jnp.where(c.active, sol.iterations, 0),
            active=c.active,
            koz_margin=jnp.linalg.norm(c.x[:2] - centre_c) - p.r_t,
            obstacle_margin=jnp.where(p.obstacle_mask > 0, obs_margin, jnp.inf),
            cone_margin=jnp.where(cone_on, cone_slack, jnp.inf),
        )
        nxt = _Carry(
            x_next, t_next, shift_solution(sol), r_hold, phase, c.active & ~docked, key, gm_next
        )
        nxt = jax.tree.map(lambda a, b: jnp.where(c.active, a, b), nxt, c)
        return nxt, info

    last, infos = lax.scan(step, carry0, None, length=config.n_steps)
    n_active = jnp.sum(infos.active)
    docked = ~last.active
    counts = Status.counts(infos.status, infos.active)
    margin = jnp.minimum(infos.koz_margin, jnp.min(infos.obstacle_margin, axis=-1))
    impulse = jnp.sum(jnp.linalg.norm(infos.u[:, :2], axis=-1)) * p.ts
    metrics = DockingMetrics(
        docked=docked,
        time_to_dock_s=jnp.where(docked, n_active * p.ts, jnp.inf),
        total_impulse_N_s=impulse,
        effort_l1_N_s=jnp.sum(jnp.abs(infos.u[:, :2])) * p.ts,
        delta_v_m_s=impulse / p.mass,
        torque_l1_N_m_s=jnp.sum(jnp.abs(infos.u[:, 2])) * p.ts,
        max_violation_m=jnp.maximum(0.0, -jnp.min(jnp.where(infos.active, margin, jnp.inf))),
        status_counts=counts,
        mean_iterations=jnp.sum(infos.iterations) / jnp.maximum(n_active, 1),
    )
    return infos, metrics
