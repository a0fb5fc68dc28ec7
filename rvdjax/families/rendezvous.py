"""3-D CW rendezvous to a holding point around moving spherical keep-out zones (paper 000
Sec. IV.A).

Every MPC step solves (paper 000 Eqs. 1-2, 5-8): the CW model at a zero-order hold, quadratic
cost to the holding point with the DARE terminal weight, the thrust box, and one keep-out row
per obstacle and stage, linearised about the previous plan's position at that stage (paper
000: expansion points from "the reference trajectory of the chaser from the previous
iteration"; the first step uses the unforced drift). The obstacles move on straight lines at
constant velocity in the LVLH frame. The run ends when the chaser is within ``stop_radius`` of
the target (paper 000: 2.3 m).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from rvdjax import checks
from rvdjax.constraints import sphere_keep_out, thrust_box
from rvdjax.disturbances import disturbances as make_disturbances
from rvdjax.families.common import (
    SHARED_HOOKS,
    derive_terminal,
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
from rvdjax.propagate import circular_orbit
from rvdjax.schema import Schema, disturbance_table, finite, make_params_of, positive, value, within
from rvdjax.solver import drift_plan

__all__ = ["Params", "Config", "SCHEMA", "make_params", "FAMILY"]

LAYOUT = Layout(
    nx=6,
    nu=3,
    pos=(0, 1, 2),
    vel=(3, 4, 5),
    force=(0, 1, 2),
    input="force",
    names=("x", "y", "z", "vx", "vy", "vz"),
)


class Params(NamedTuple):
    """Traced parameters (SI units).

    Attributes:
        A, B: (6, 6), (6, 3) discrete CW model at the sample time (ZOH; also the linear truth).
        Q, R, Q_f: weights (Q_f: the DARE solution).
        u_max: (3,) thrust box [N].
        x_ref: (6,) holding state (the target sits at the origin).
        obstacles: (k, 6) obstacle states (position, velocity) at t = 0 [m, m/s].
        radii: (k,) spherical keep-out radii [m].
        obstacle_mask: (k,) 1.0 for an obstacle that exists, 0.0 to switch it off.
        rho: (k,) exact penalty of each obstacle's keep-out rows [per metre of penetration].
        ts: () sample time [s].
        stop_radius: () the run ends when |r| <= stop_radius [m].
        plant: the vehicle and its surroundings (:class:`~rvdjax.loop.plant.Plant`: mass [kg],
            orbit, drag, disturbances, continuous model, thrusters).
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
    stop_radius: jnp.ndarray
    plant: Plant  # the vehicle and its surroundings (rvdjax.loop.plant)


@dataclasses.dataclass(frozen=True)
class Config:
    """Static configuration: the horizon."""

    N: int = 30

    def __post_init__(self):
        checks.integer("N", self.N)


class Guidance(NamedTuple):
    """No guidance state: one phase, fixed constraints."""


SCHEMA = Schema(
    (
        positive("altitude_m", "m", "circular target orbit altitude (CW mean motion)"),
        positive("mass", "kg", "chaser mass"),
        positive("ts", "s", "sample time (zero-order hold)"),
        value("Q", "", "state weight: 6 diagonal entries or a (6, 6) PSD matrix", shape="(6, 6)"),
        value("R", "", "input weight: 3 diagonal entries or a (3, 3) PD matrix", shape="(3, 3)"),
        positive("u_max", "N", "per-axis thrust bound (one value or 3)", shape="(3,)"),
        positive("stop_radius", "m", "distance to the target that ends the run"),
        finite("obstacles", "m, m/s", "obstacle states at t = 0", shape="(k, 6)", default=None),
        positive("radii", "m", "keep-out radius of each obstacle", shape="(k,)", default=None),
        value("obstacles_on", "", "false switches every obstacle off", kind="bool", default=True),
        positive("rho", "per metre", "exact penalty of the keep-out rows", default=1e8),
        value("x_ref", "m, m/s", "holding state (none: the origin)", shape="(6,)", default=None),
        value("x0", "m, m/s", "initial state", shape="(6,)", kind="state", default=None),
        within(
            "inclination_deg",
            "deg",
            0.0,
            180.0,
            "target orbit inclination",
            closed=True,
            default=0.0,
        ),
        disturbance_table(),
    )
)


def _build(v) -> Params:
    """Check physical values and build :class:`Params` (once, before any jit).

    Keywords: :data:`SCHEMA` (each value's unit, check and default); ``x0``, when given, is
    checked to be finite and outside every keep-out zone and the stop radius.
    """
    from rvdjax.dynamics import cw_continuous, dare, discretize_zoh, mean_motion

    Q, R, u_max, obstacles, radii, obstacles_on, x_ref, x0 = (
        v.Q,
        v.R,
        v.u_max,
        v.obstacles,
        v.radii,
        v.obstacles_on,
        v.x_ref,
        v.x0,
    )
    Q = np.diag(np.asarray(Q, float)) if np.ndim(Q) == 1 else np.asarray(Q, float)
    R = np.diag(np.asarray(R, float)) if np.ndim(R) == 1 else np.asarray(R, float)
    checks.shape("Q", Q, (6, 6))
    checks.shape("R", R, (3, 3))
    checks.pos_semidef("Q", Q)
    checks.pos_def("R", R)
    u_max = np.broadcast_to(np.asarray(u_max, float), (3,)).copy()
    if obstacles is None or len(obstacles) == 0:  # one inactive placeholder: fixed shapes
        obstacles, radii, obstacles_on = np.zeros((1, 6)), np.ones(1), False
    obstacles = np.asarray(obstacles, float).reshape(-1, 6)
    radii = np.asarray(radii, float).reshape(-1)
    if radii.shape != (len(obstacles),):
        raise ValueError(f"radii must give one radius per obstacle ({len(obstacles)})")
    x_ref = np.zeros(6) if x_ref is None else checks.shape("x_ref", x_ref, (6,))
    if x0 is not None:
        x0 = checks.shape("x0", x0, (6,))
        checks.outside("the stop radius (it has already arrived)", x0[:3], x_ref[:3], v.stop_radius)
        if obstacles_on:
            for j, (o, r) in enumerate(zip(obstacles, radii, strict=True)):
                checks.outside(f"keep-out zone {j + 1}", x0[:3], o[:3], r)
    n = mean_motion(altitude_m=v.altitude_m)
    A, B = discretize_zoh(*cw_continuous(n, v.mass), v.ts)
    P = dare(A, B, jnp.asarray(Q), jnp.asarray(R))
    f = jnp.asarray
    return Params(
        A=A,
        B=B,
        Q=f(Q),
        R=f(R),
        Q_f=P,
        u_max=f(u_max),
        x_ref=f(x_ref),
        obstacles=f(obstacles),
        radii=f(radii),
        obstacle_mask=f(np.full(len(radii), 1.0 if obstacles_on else 0.0)),
        rho=f(np.broadcast_to(np.asarray(v.rho, float), radii.shape).copy()),
        ts=f(float(v.ts)),
        stop_radius=f(float(v.stop_radius)),
        plant=make_plant(
            float(v.mass),
            *cw_continuous(n, v.mass),
            orbit=circular_orbit(v.altitude_m, inclination_rad=np.deg2rad(v.inclination_deg)),
            disturbances=make_disturbances(**(v.disturbances or {})),
        ),
    )


make_params = make_params_of(SCHEMA, _build)


def _centres(p: Params, times):
    """Obstacle centres (..., k, 3) at the given times: straight lines at constant velocity."""
    return p.obstacles[..., :3] + times[..., None, None] * p.obstacles[..., 3:]


def init(p: Params, fc: Config, x0):
    return Guidance()


def initial_plan(p: Params, fc: Config, g, x0):
    # the unforced drift: a straight line to the target can cross an obstacle and leave no
    # feasible plan
    return drift_plan(p.A, x0, fc.N, LAYOUT.nu)


def observe(p, fc, g, x, t, plan):
    return g


def ocp(p: Params, fc: Config, g, x, t, plan):
    """The OCP at the measured state x and time t, keep-out rows about the plan's positions."""
    N, nx = fc.N, LAYOUT.nx
    times = t + p.ts * jnp.arange(1, N + 1, dtype=x.dtype)
    keep_out = sphere_keep_out(
        plan.x[:, :3], _centres(p, times), p.radii, nx, rho=p.rho, name="keep_out"
    ).masked(jnp.broadcast_to(p.obstacle_mask, (N, p.radii.shape[0])))
    x_ref = jnp.broadcast_to(p.x_ref, (N, nx))
    problem = tracking_ocp(model(p, fc), x, x_ref, [keep_out], thrust_box(p.u_max, N))
    return problem, [keep_out]


def update(p: Params, fc, g, x, u, x_next, t, ts, samples):
    docked = jnp.linalg.norm(x_next[:3] - p.x_ref[:3]) <= p.stop_radius
    return g, docked, ts, jnp.zeros(samples[0].shape, bool)


def truth_blocks(p: Params, fc, g, x, t):
    """The keep-out spheres linearised at the truth itself: slack = |r - o| - radius."""
    k = p.radii.shape[0]
    centres = _centres(p, jnp.asarray(t)[None])
    keep_out = sphere_keep_out(x[None, :3], centres, p.radii, LAYOUT.nx, name="keep_out")
    return [keep_out.masked(p.obstacle_mask.reshape(1, k))]


def dock_error(p: Params, fc, g, x, t):
    """Distance beyond ``stop_radius`` of the holding position [m] (where the run ends)."""
    return smooth_excess(smooth_norm(x[:3] - p.x_ref[:3]), p.stop_radius)


TUNING = Tuning(tunables=weight_tunables(), derive=derive_terminal)

FAMILY = Family(
    name="rendezvous",
    description="3-D CW rendezvous to a holding point around moving keep-out spheres (paper 000)",
    law=Hooks.of(
        globals(),
        **SHARED_HOOKS,
        model=tracking_fixed,
        layout=LAYOUT,
        n_phases=1,
        config_type=Config,
    ),
    make_params=make_params,
    truths=("linear", "two-body", "two-body-j2"),
    plot=lazy("rvdjax.families.plots.rendezvous:plot"),
    baselines=("nmpc",),
    tuning=TUNING,
)
