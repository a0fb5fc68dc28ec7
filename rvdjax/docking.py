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
from rvdjax.ocp import OCP
from rvdjax.solver import Plan, SolverSettings, Status, shift_solution, solve

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
        gap: () holding position distance outside the dynamic circle [m].
        gamma: () shrink factor of r_hold per qualifying step, in (0, 1).
        c_pos: () alpha_1 threshold [m]; c_att: () alpha_2 threshold [rad].
        half_angle: () entry-cone half angle [rad].
        rho: () exact penalty of the soft state rows.
        ts: () sample time [s]; dock_tol: () docked position tolerance [m].
        mass: () chaser mass [kg] (for delta-v).
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
    gap: jnp.ndarray
    gamma: jnp.ndarray
    c_pos: jnp.ndarray
    c_att: jnp.ndarray
    half_angle: jnp.ndarray
    rho: jnp.ndarray
    ts: jnp.ndarray
    dock_tol: jnp.ndarray
    mass: jnp.ndarray


@dataclasses.dataclass(frozen=True)
class DockingConfig:
    N: int = 40
    n_steps: int = 150
    settings: SolverSettings = SolverSettings()


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
    cone_margin: jnp.ndarray  # smallest entry-cone row slack of the truth in phase 1 [m]


class DockingMetrics(NamedTuple):
    """Per-run figures (names shared with :class:`rvdjax.sim.Metrics`)."""

    docked: jnp.ndarray
    time_to_dock_s: jnp.ndarray
    total_impulse_N_s: jnp.ndarray  # sum_k ||(Fx, Fy)||_2 Ts
    effort_l1_N_s: jnp.ndarray  # sum_k (|Fx| + |Fy|) Ts (paper 002 Eq. 11, forces only)
    delta_v_m_s: jnp.ndarray  # total impulse / mass
    torque_l1_N_m_s: jnp.ndarray
    max_violation_m: jnp.ndarray  # fixed keep-out penetration of the truth
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
    if r_hold0 <= r_t:
        raise ValueError(f"r_hold0 ({r_hold0} m) must exceed the keep-out radius r_t ({r_t} m)")
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
    )


def _wrap(a):
    return (a + jnp.pi) % (2.0 * jnp.pi) - jnp.pi


def _geometry(p: DockingParams, t, r_hold, N: int):
    """Predicted port axis angles, docking points, holding states over the horizon."""
    times = t + p.ts * jnp.arange(1, N + 1, dtype=p.A.dtype)
    phi = p.target[2] + p.target_rate * times  # port axis angle
    e = jnp.stack([jnp.cos(phi), jnp.sin(phi)], axis=-1)
    centre = jnp.broadcast_to(p.target[:2], (N, 2))
    dock = centre + p.r_t * e
    hold = centre + (r_hold + p.gap) * e
    # holding point velocity: omega x (hold - centre)
    v_hold = p.target_rate * (r_hold + p.gap) * jnp.stack([-jnp.sin(phi), jnp.cos(phi)], -1)
    return phi, centre, dock, hold, v_hold


def _reference(p, x, phi, hold, v_hold):
    """Holding state per stage: position, attitude facing the port (theta = phi + pi, unwrapped
    near the current attitude), holding-point velocity and the target's rate."""
    theta_ref = x[2] + _wrap(phi + jnp.pi - x[2])
    N = phi.shape[0]
    return jnp.concatenate(
        [hold, theta_ref[:, None], v_hold, jnp.full((N, 1), p.target_rate)], axis=-1
    )


def _build_ocp(p: DockingParams, x, t, r_hold, phase, p_guess, N: int):
    phi, centre, dock, hold, v_hold = _geometry(p, t, r_hold, N)
    x_ref = _reference(p, x, phi, hold, v_hold)
    F1, f1 = holding_radius_rows(p_guess, centre, p.r_t, 6, POS)
    F2, f2 = holding_radius_rows(p_guess, centre, r_hold, 6, POS)
    F3, f3 = entry_cone_rows(dock, phi, p.half_angle, 6, POS)
    Fx = jnp.concatenate([F1, F2, F3], axis=1)
    fx = jnp.concatenate([f1, f2, f3], axis=1)
    cone_on = jnp.where(phase > 0, 1.0, 0.0)
    x_mask = jnp.concatenate([jnp.ones((N, 2)), jnp.broadcast_to(cone_on, (N, 2))], axis=1).astype(
        x.dtype
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


def fly_docking(p: DockingParams, x0, config: DockingConfig = DockingConfig()):
    """Fly one docking maneuver. Pure function of (p, x0): jit / vmap apply.

    Returns:
        (DockingInfo with a leading axis of n_steps, DockingMetrics).
    """
    N = config.N
    dtype = p.A.dtype
    x0 = jnp.asarray(x0, dtype)

    def drift(x, _):
        x = p.A @ x
        return x, x

    _, x_drift = lax.scan(drift, x0, None, length=N)
    init = Plan(jnp.zeros((N, 3), dtype), x_drift, jnp.zeros((N, 6), dtype))
    carry0 = _Carry(x0, jnp.zeros((), dtype), init, p.r_hold0, jnp.asarray(0), jnp.asarray(True))

    def step(c: _Carry, _):
        ocp = _build_ocp(p, c.x, c.t, c.r_hold, c.phase, c.plan.x[:, :2], N)

        def fly(ocp):
            return solve(ocp, config.settings, init=c.plan)

        def idle(ocp):
            shapes = jax.eval_shape(fly, ocp)
            sol = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
            return sol._replace(u=c.plan.u, x=c.plan.x, nu=c.plan.nu)

        sol = lax.cond(c.active, fly, idle, ocp)
        u = jnp.where(c.active, sol.u[0], 0.0)
        x_next = p.A @ c.x + p.B @ u

        # Paper 002 Fig. 4 on the state reached: errors to the current holding state.
        t_next = c.t + p.ts
        phi_now = p.target[2] + p.target_rate * t_next
        e_now = jnp.stack([jnp.cos(phi_now), jnp.sin(phi_now)])
        hold_now = p.target[:2] + (c.r_hold + p.gap) * e_now
        alpha1 = jnp.linalg.norm(x_next[:2] - hold_now)
        alpha2 = jnp.abs(_wrap(phi_now + jnp.pi - x_next[2]))
        close = (alpha1 < p.c_pos) & (alpha2 < p.c_att)
        phase = jnp.where(close, 1, c.phase)
        shrink = close & (c.phase > 0)
        r_hold = jnp.where(shrink, jnp.maximum(p.gamma * c.r_hold, p.r_t), c.r_hold)
        at_port = c.r_hold <= p.r_t + 1e-9
        docked = at_port & (alpha1 < p.dock_tol) & (alpha2 < p.c_att)

        dock_now = p.target[:2] + p.r_t * jnp.stack(
            [jnp.cos(p.target[2] + p.target_rate * c.t), jnp.sin(p.target[2] + p.target_rate * c.t)]
        )
        Fc, fc = entry_cone_rows(
            dock_now[None], (p.target[2] + p.target_rate * c.t)[None], p.half_angle, 6, POS
        )
        cone_slack = jnp.min(fc[0] - Fc[0] @ c.x)
        info = DockingInfo(
            x=c.x,
            u=u,
            r_hold=c.r_hold,
            phase=c.phase,
            status=jnp.where(c.active, sol.status, -1),
            iterations=jnp.where(c.active, sol.iterations, 0),
            active=c.active,
            koz_margin=jnp.linalg.norm(c.x[:2] - p.target[:2]) - p.r_t,
            cone_margin=jnp.where(c.phase > 0, cone_slack, jnp.inf),
        )
        nxt = _Carry(x_next, t_next, shift_solution(sol), r_hold, phase, c.active & ~docked)
        nxt = jax.tree.map(lambda a, b: jnp.where(c.active, a, b), nxt, c)
        return nxt, info

    last, infos = lax.scan(step, carry0, None, length=config.n_steps)
    n_active = jnp.sum(infos.active)
    docked = ~last.active
    counts = jnp.stack(
        [jnp.sum(infos.active & (infos.status == k)) for k in range(len(Status.names))]
    )
    metrics = DockingMetrics(
        docked=docked,
        time_to_dock_s=jnp.where(docked, n_active * p.ts, jnp.inf),
        total_impulse_N_s=jnp.sum(jnp.linalg.norm(infos.u[:, :2], axis=-1)) * p.ts,
        effort_l1_N_s=jnp.sum(jnp.abs(infos.u[:, :2])) * p.ts,
        delta_v_m_s=jnp.sum(jnp.linalg.norm(infos.u[:, :2], axis=-1)) * p.ts / p.mass,
        torque_l1_N_m_s=jnp.sum(jnp.abs(infos.u[:, 2])) * p.ts,
        max_violation_m=jnp.maximum(
            0.0, -jnp.min(jnp.where(infos.active, infos.koz_margin, jnp.inf))
        ),
        status_counts=counts,
        mean_iterations=jnp.sum(infos.iterations) / jnp.maximum(n_active, 1),
    )
    return infos, metrics
