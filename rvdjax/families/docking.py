"""Planar docking to a rotating (and translating) target: paper 002's two-phase switching and
paper 000's holding-radius logic (LQ-MPC versions).

The chaser is a planar 3-DOF air-bearing vehicle (x, y, theta, vx, vy, omega; inputs Fx, Fy,
torque). The target rotates at a constant rate about its centre, which may translate; its
docking port sits on its keep-out circle and points outward along the body axis. At every MPC
step (paper 002 Fig. 4):

1. Free-flying phase: track the holding position (on the dynamic circle r_hold, plus a small
   gap, straight in front of the port), staying outside the fixed keep-out circle r_t and the
   dynamic circle r_hold (both linearised about the previous plan, paper 000 Eqs. 8-9).
2. When the distance error alpha_1 < c_alpha1 and the attitude error alpha_2 < c_alpha2, the
   final docking phase starts: the entry cone (two hyperplanes through the docking point,
   paper 002 Eqs. 5-6) is enforced over the horizon, and each step with both errors below
   their thresholds shrinks r_hold by gamma, down to r_min.
3. Docked when r_hold has reached r_min and the chaser is within ``dock_tol`` of the holding
   position at the port with the attitude error below c_alpha2.

Paper 000's 2-D SPOT cases (``Config(logic="holding-radius")``): two obstacles move on
straight lines (circular keep-out zones), r_hold shrinks whenever the position error < eta
(``c_pos``) and the attitude error < zeta (``c_att``), and the entry cone is active whenever
the chaser is within r_cone of the docking point (paper 000 Sec. IV.B).

The target's attitude and holding position are predicted over the horizon (paper 002: "the
holding position is predictable with the given radius ... and the constant angular velocity").
Paper 002 solves this with NMPC (IPOPT); rvdjax solves the linearised (LQ) problem.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from rvdjax import checks
from rvdjax.constraints import (
    entry_cone,
    holding_radius,
    holding_radius_update,
    sphere_keep_out,
    thrust_box,
)
from rvdjax.disturbances import LAB_DISTURBANCES
from rvdjax.disturbances import disturbances as make_disturbances
from rvdjax.families.common import (
    SHARED_HOOKS,
    derive_terminal,
    field_tunable,
    make_plant,
    model,
    smooth_excess,
    smooth_norm,
    tracking_fixed,
    tracking_ocp,
    weight_tunables,
)
from rvdjax.loop.family import Family, Hooks, Layout, Tuning, lazy
from rvdjax.loop.plant import Plant
from rvdjax.schema import (
    Schema,
    disturbance_table,
    finite,
    make_params_of,
    nonnegative,
    positive,
    value,
    within,
)
from rvdjax.solver import drift_plan

__all__ = ["Params", "Config", "SCHEMA", "make_params", "FAMILY"]

POS = (0, 1)
LAYOUT = Layout(
    nx=6,
    nu=3,
    pos=POS,
    vel=(3, 4),
    att=(2,),
    force=POS,
    input="force",
    names=("x", "y", "theta", "vx", "vy", "omega"),
)


class Params(NamedTuple):
    """Traced parameters (SI units, angles in rad).

    Attributes:
        A, B: (6, 6), (6, 3) discrete planar 3-DOF model (ZOH), also the truth.
        Q, R, Q_f: weights (Q_f: DARE solution).
        u_max: (3,) limits on Fx, Fy [N] and torque [N m].
        target: (3,) target centre x, y [m] and initial attitude [rad] (port direction).
        target_rate: () target angular rate [rad/s].
        target_vel: (2,) target translational velocity [m/s].
        r_t: () fixed keep-out radius about the target centre [m].
        r_hold0: () initial dynamic keep-out radius [m].
        r_min: () smallest holding radius (docked) [m].
        r_port: () distance of the docking point (entry-cone apex) from the target centre [m].
        cone_radius: () "holding-radius" logic: the entry cone is active within this distance
            of the docking point [m].
        obstacles: (k, 4) obstacle x, y, vx, vy at t = 0; obstacle_radii: (k,);
            obstacle_mask: (k,) 1.0 for an obstacle that exists.
        gap: () holding position distance outside the dynamic circle [m].
        gamma: () shrink factor of r_hold per qualifying step, in (0, 1).
        c_pos: () alpha_1 threshold [m]; c_att: () alpha_2 threshold [rad].
        half_angle: () entry-cone half angle [rad].
        rho: () exact penalty of the soft state rows [per metre].
        ts: () sample time [s]; dock_tol: () docked position tolerance [m].
        plant: the vehicle and its surroundings (:class:`~rvdjax.loop.plant.Plant`: mass [kg],
            orbit, drag, disturbances, continuous model, thrusters).
    """

    A: jnp.ndarray
    B: jnp.ndarray
    Q: jnp.ndarray
    R: jnp.ndarray
    Q_f: jnp.ndarray
    u_max: jnp.ndarray
    target: jnp.ndarray
    target_rate: jnp.ndarray
    target_vel: jnp.ndarray
    r_t: jnp.ndarray
    r_hold0: jnp.ndarray
    r_min: jnp.ndarray
    r_port: jnp.ndarray
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
    plant: Plant  # the vehicle and its surroundings (rvdjax.loop.plant)


@dataclasses.dataclass(frozen=True)
class Config:
    """Static configuration.

    Attributes:
        N: horizon.
        logic: "two-phase" (paper 002 Fig. 4) or "holding-radius" (paper 000 Sec. II.C.3).
    """

    N: int = 40
    logic: str = "two-phase"

    def __post_init__(self):
        checks.integer("N", self.N)
        checks.choice("logic", self.logic, ("two-phase", "holding-radius"))


class Guidance(NamedTuple):
    """Guidance state: holding radius, phase (0 free flying, 1 final approach), cone on."""

    r_hold: jnp.ndarray
    phase: jnp.ndarray
    cone_on: jnp.ndarray


SCHEMA = Schema(
    (
        positive("mass", "kg", "chaser mass"),
        positive("inertia", "kg m^2", "chaser moment of inertia about z"),
        positive("ts", "s", "sample time (zero-order hold)"),
        value("Q", "", "state weight: 6 diagonal entries or a (6, 6) PSD matrix", shape="(6, 6)"),
        value("R", "", "input weight: 3 diagonal entries or a (3, 3) PD matrix", shape="(3, 3)"),
        positive("u_max", "N, N, N m", "force and torque bounds", shape="(3,)"),
        value("target", "m, m, rad", "target centre and port direction at t = 0", shape="(3,)"),
        finite("target_rate_deg_s", "deg/s", "target rotation rate"),
        positive("r_t", "m", "target keep-out radius"),
        positive("r_hold0", "m", "initial holding radius (> r_min)"),
        nonnegative("gap", "m", "holding-radius margin over the keep-out radius"),
        within(
            "gamma",
            "",
            0.0,
            1.0,
            "holding-radius shrink factor",
            label="gamma (holding-radius shrink factor)",
        ),
        positive("c_pos", "m", "position tolerance of a holding-radius shrink"),
        positive("c_att_deg", "deg", "attitude tolerance of a holding-radius shrink"),
        within(
            "half_angle_deg",
            "deg",
            0.0,
            90.0,
            "entry-cone half angle",
            label="half_angle_deg (entry cone)",
        ),
        value("r_min", "m", "smallest holding radius, in [r_t, r_hold0) (none: r_t)", default=None),
        value("r_port", "m", "docking-port radius, in (0, r_min] (none: r_t)", default=None),
        value("target_vel", "m/s", "target velocity", shape="(2,)", default=(0.0, 0.0)),
        value("cone_radius", "m", "entry-cone activation radius (> 0)", default=float("inf")),
        finite("obstacles", "m, m/s", "obstacle states at t = 0", shape="(k, 4)", default=None),
        positive("obstacle_radii", "m", "obstacle keep-out radii", shape="(k,)", default=None),
        value("obstacles_on", "", "false switches every obstacle off", kind="bool", default=True),
        positive("rho", "", "exact penalty of the soft constraint rows", default=1e5),
        positive("dock_tol", "m", "docking tolerance", default=0.05),
        value(
            "x0",
            "m, m, rad, m/s, m/s, rad/s",
            "initial state",
            shape="(6,)",
            kind="state",
            default=None,
        ),
        disturbance_table("disturbance keyword values over the lab's"),
    )
)


def _build(v) -> Params:
    """Check physical values and build :class:`Params` (once, before any jit).

    Keywords: :data:`SCHEMA`. Angles in degrees (``target`` = x, y [m] and the port
    direction [rad]); radii must satisfy r_t <= r_min < r_hold0 and 0 < r_port <= r_min;
    ``x0`` (if given) must be finite and outside the target keep-out circle and every obstacle.
    """
    from rvdjax.dynamics import dare, discretize_zoh, planar3dof_continuous

    r_min = v.r_t if v.r_min is None else v.r_min
    r_port = v.r_t if v.r_port is None else v.r_port
    if not v.r_t <= r_min < v.r_hold0:
        raise ValueError(
            f"radii must satisfy r_t <= r_min < r_hold0, got r_t={v.r_t}, r_min={r_min}, "
            f"r_hold0={v.r_hold0} m"
        )
    checks.in_range("r_port", r_port, 0.0, r_min, hi_open=False, unit="m")
    if not v.cone_radius > 0:
        raise ValueError(f"cone_radius must be > 0 m, got {v.cone_radius}")
    obstacles, obstacle_radii, obstacles_on = v.obstacles, v.obstacle_radii, v.obstacles_on
    if obstacles is None or len(obstacles) == 0:  # one inactive placeholder: fixed shapes
        obstacles, obstacle_radii, obstacles_on = np.zeros((1, 4)), np.ones(1), False
    obstacles = np.asarray(obstacles, float).reshape(-1, 4)
    obstacle_radii = np.asarray(obstacle_radii, float).reshape(-1)
    obstacle_mask = np.full(len(obstacle_radii), 1.0 if obstacles_on else 0.0)
    Q = np.diag(np.asarray(v.Q, float)) if np.ndim(v.Q) == 1 else np.asarray(v.Q, float)
    R = np.diag(np.asarray(v.R, float)) if np.ndim(v.R) == 1 else np.asarray(v.R, float)
    checks.shape("Q", Q, (6, 6))
    checks.shape("R", R, (3, 3))
    checks.pos_semidef("Q", Q)
    checks.pos_def("R", R)
    u_max = checks.shape("u_max", v.u_max, (3,))
    target = checks.shape("target", v.target, (3,))
    target_vel = checks.shape("target_vel", v.target_vel, (2,))
    if v.x0 is not None:
        x0 = checks.shape("x0", v.x0, (6,))
        checks.outside("the target keep-out zone", x0[:2], target[:2], v.r_t)
        for j in np.flatnonzero(obstacle_mask):
            checks.outside(
                f"obstacle keep-out zone {j + 1}", x0[:2], obstacles[j, :2], obstacle_radii[j]
            )
    A, B = discretize_zoh(*planar3dof_continuous(v.mass, v.inertia), v.ts)
    P = dare(A, B, jnp.asarray(Q), jnp.asarray(R))
    f = jnp.asarray
    return Params(
        A=A,
        B=B,
        Q=f(Q),
        R=f(R),
        Q_f=P,
        u_max=f(u_max),
        target=f(target),
        target_rate=f(np.deg2rad(v.target_rate_deg_s)),
        target_vel=f(target_vel),
        r_t=f(float(v.r_t)),
        r_hold0=f(float(v.r_hold0)),
        r_min=f(float(r_min)),
        r_port=f(float(r_port)),
        cone_radius=f(float(v.cone_radius)),
        obstacles=f(obstacles),
        obstacle_radii=f(obstacle_radii),
        obstacle_mask=f(obstacle_mask),
        gap=f(float(v.gap)),
        gamma=f(float(v.gamma)),
        c_pos=f(float(v.c_pos)),
        c_att=f(np.deg2rad(v.c_att_deg)),
        half_angle=f(np.deg2rad(v.half_angle_deg)),
        rho=f(float(v.rho)),
        ts=f(float(v.ts)),
        dock_tol=f(float(v.dock_tol)),
        plant=make_plant(
            float(v.mass),
            *planar3dof_continuous(v.mass, v.inertia),
            disturbances=make_disturbances(**{**LAB_DISTURBANCES, **(v.disturbances or {})}),
        ),
    )


make_params = make_params_of(SCHEMA, _build)


def _wrap(a):
    return (a + jnp.pi) % (2.0 * jnp.pi) - jnp.pi


def _unit(phi):
    return jnp.stack([jnp.cos(phi), jnp.sin(phi)], axis=-1)


def target_at(p: Params, times):
    """Target centre (..., 2) and port axis angle (...) at the given times."""
    centre = p.target[:2] + times[..., None] * p.target_vel
    return centre, p.target[2] + p.target_rate * times


def _obstacle_centres(p: Params, times):
    return p.obstacles[..., :2] + times[..., None, None] * p.obstacles[..., 2:]


def init(p: Params, fc: Config, x0):
    return Guidance(r_hold=p.r_hold0, phase=jnp.asarray(0, jnp.int32), cone_on=jnp.asarray(False))


def initial_plan(p: Params, fc: Config, g, x0):
    return drift_plan(p.A, x0, fc.N, LAYOUT.nu)


def observe(p: Params, fc: Config, g: Guidance, x, t, plan):
    """Entry-cone activation at the step start: from the phase switch on (paper 002), or
    within r_cone of the docking point (paper 000)."""
    if fc.logic == "two-phase":
        return g._replace(cone_on=g.phase > 0)
    centre, phi = target_at(p, t)
    dock = centre + p.r_port * _unit(phi)
    return g._replace(cone_on=jnp.linalg.norm(x[:2] - dock) < p.cone_radius)


def ocp(p: Params, fc: Config, g: Guidance, x, t, plan):
    """Blocks: target keep-out r_t, holding circle r_hold (both about the plan), entry cone
    (when on), obstacles."""
    N, nx = fc.N, LAYOUT.nx
    times = t + p.ts * jnp.arange(1, N + 1, dtype=x.dtype)
    centre, phi = target_at(p, times)
    e = _unit(phi)
    dock = centre + p.r_port * e
    hold_r = g.r_hold + p.gap
    hold = centre + hold_r * e
    # holding point velocity: target velocity + omega x (hold - centre)
    v_hold = p.target_vel + p.target_rate * hold_r * jnp.stack([-e[:, 1], e[:, 0]], -1)
    # attitude facing the port (theta = phi + pi, unwrapped near the current attitude)
    theta_ref = x[2] + _wrap(phi + jnp.pi - x[2])
    x_ref = jnp.concatenate(
        [hold, theta_ref[:, None], v_hold, jnp.full((N, 1), p.target_rate)], axis=-1
    )
    # The circles are linearised about the previous plan (paper 000 Eqs. 8-9), except in
    # paper 002's final approach: the chaser, which entered it at the holding point in front
    # of the port, must then stay in the entry cone over the whole horizon, so they are
    # linearised about the port axis (tangent lines across the cone, within 1.7 cm of the
    # circles inside a 20 deg cone at 1.2 m; paper 002's NMPC keeps the circles exact). About
    # a plan that lags a port turning away from the chaser, the tangents cut the cone off:
    # every step infeasible and the truth through the keep-out circle (case C turning
    # clockwise: 27 steps, -8 cm). Paper 000's cone turns on by distance, wherever the
    # chaser is, so its circles stay linearised about the plan.
    axis_lin = g.cone_on if fc.logic == "two-phase" else False
    guess = jnp.where(axis_lin, centre + hold_r * e, plan.x[:, :2])
    blocks = [
        holding_radius(guess, centre, p.r_t, nx, POS, rho=p.rho, name="target_keep_out"),
        holding_radius(guess, centre, g.r_hold, nx, POS, rho=p.rho, name="holding_radius"),
        entry_cone(dock, phi, p.half_angle, nx, POS, rho=p.rho).masked(g.cone_on),
        sphere_keep_out(
            guess,
            _obstacle_centres(p, times),
            p.obstacle_radii,
            nx,
            POS,
            rho=p.rho,
            name="obstacles",
        ).masked(jnp.broadcast_to(p.obstacle_mask, (N, p.obstacle_radii.shape[0]))),
    ]
    problem = tracking_ocp(model(p, fc), x, x_ref, blocks, thrust_box(p.u_max, N))
    return problem, blocks


def update(p: Params, fc: Config, g: Guidance, x, u, x_next, t, ts, samples):
    """Phase switch, shrink rule and docking on the state reached (errors to the current
    holding state)."""
    centre, phi = target_at(p, t + ts)
    hold = centre + (g.r_hold + p.gap) * _unit(phi)
    alpha1 = jnp.linalg.norm(x_next[:2] - hold)
    alpha2 = jnp.abs(_wrap(phi + jnp.pi - x_next[2]))
    # paper 002: shrink only in the final phase; paper 000: whenever both errors are small
    gate = (g.phase > 0) if fc.logic == "two-phase" else True
    r_hold, close = holding_radius_update(
        g.r_hold, alpha1, alpha2, p.gamma, p.c_pos, p.c_att, p.r_min, gate
    )
    at_port = g.r_hold <= p.r_min + 1e-9
    docked = at_port & (alpha1 < p.dock_tol) & (alpha2 < p.c_att)
    phase = jnp.where(close, 1, g.phase).astype(jnp.int32)
    return g._replace(r_hold=r_hold, phase=phase), docked, ts, jnp.zeros(samples[0].shape, bool)


def truth_blocks(p: Params, fc: Config, g: Guidance, x, t):
    """Target keep-out and obstacles (judged), entry cone when on (reported)."""
    t = jnp.asarray(t)
    centre, phi = target_at(p, t[None])
    r = x[None, :2]
    k = p.obstacle_radii.shape[0]
    return [
        sphere_keep_out(r, centre, p.r_t, LAYOUT.nx, POS, name="target_keep_out"),
        sphere_keep_out(
            r, _obstacle_centres(p, t[None]), p.obstacle_radii, LAYOUT.nx, POS, name="obstacles"
        ).masked(p.obstacle_mask.reshape(1, k)),
        entry_cone(
            centre + p.r_port * _unit(phi), phi, p.half_angle, LAYOUT.nx, POS, kind="monitor"
        ).masked(g.cone_on),
    ]


def dock_error(p: Params, fc: Config, g: Guidance, x, t):
    """Distance [m] beyond dock_tol of the docked holding position (the circle shrunk to
    r_min, plus the gap, on the port axis) at time t."""
    centre, phi = target_at(p, jnp.asarray(t))
    return smooth_excess(smooth_norm(x[:2] - (centre + (p.r_min + p.gap) * _unit(phi))), p.dock_tol)


TUNING = Tuning(
    tunables={
        **weight_tunables(),
        "gamma": field_tunable(
            "gamma",
            "holding-radius shrink factor per qualifying step (paper 000 Eq. 18, paper 002)",
            transform="logit",
            bounds=(0.0, 1.0),
        ),
        "gap": field_tunable(
            "gap",
            "keep-out margin: holding position distance outside the dynamic circle [m]",
        ),
    },
    derive=derive_terminal,
)


FAMILY = Family(
    name="planar-docking",
    description="planar 3-DOF docking to a rotating, translating target: holding radius, "
    "entry cone, moving obstacles (papers 000, 002)",
    law=Hooks.of(
        globals(),
        **SHARED_HOOKS,
        model=tracking_fixed,
        layout=LAYOUT,
        n_phases=2,
        config_type=Config,
    ),
    make_params=make_params,
    plot=lazy("rvdjax.families.plots.docking:plot"),
    tuning=TUNING,
)
