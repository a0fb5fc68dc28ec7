"""LQ-MPC docking on the POSEIDYN air-bearing table (paper 001, Sec. 3.1, Tables 1-3, 6).

Paper 001 flies a planar double integrator (state x, y, vx, vy; inputs Fx, Fy; Eqs. 1-3) to a
docking point in front of a non-moving target, around a non-moving obstacle, finishing inside
an entry cone. The LQ-MPC of Eq. 5 is, at every step (Ts = 5 s, N = 20):

    min  (x_N - x_t)^T P (x_N - x_t) + sum_i (x_i - x_t)^T Q (x_i - x_t) + u_i^T R u_i
    s.t. x_{i+1} = A_d x_i + B_d u_i,  |Fx|, |Fy| <= F_max               (5b-5d)
         n_obs . r_i >= n_obs . p_obs      rotating hyperplane keep-out   (5e)
         n_c1 . r_i >= n_c1 . p_dock,  n_c2 . r_i <= n_c2 . p_dock   entry cone (5f-5g)

with P = 100 P_bar (initial tuning) or P_bar (re-tuned; F_max halved), P_bar the DARE
solution. The keep-out hyperplane is tangent to the keep-out circle; its normal starts at the
chaser's initial bearing from the obstacle and rotates at a fixed rate (paper 001: "the
hyperplane rotation rate was not adjusted" between the tunings; the rate itself is not
published) until it points at the docking point, and stays there. The normal is predicted over
the horizon. The entry cone rows are switched on for every stage once the chaser comes within
the cone range of the docking point and stay on until docking ("the FSS is forced to stay
within the two hyperplanes until docking is achieved"); before that they are enforced on the
stages whose previous-plan position lies within the range (``Config.predict_cone``).

The truth is the same double integrator (exact ZOH, no thruster modulation). Docking is
detected on the continuous truth inside each ZOH step (``Config.substeps`` samples), so
``time_to_dock_s`` is not quantised to Ts, and effort is integrated up to that instant (paper
001 Eq. 14: u_T = int ||u||_1 dt).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from rvdjax import checks
from rvdjax.constraints import entry_cone, rotating_hyperplane, sphere_keep_out, thrust_box
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
    Input,
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
NX, NU = 4, 2
LAYOUT = Layout(
    nx=NX, nu=NU, pos=POS, vel=(2, 3), force=POS, input="force", names=("x", "y", "vx", "vy")
)


class Params(NamedTuple):
    """Traced parameters (SI units, angles in rad).

    Attributes:
        A, B: (4, 4), (4, 2) ZOH model of the planar double integrator (also the truth).
        Q, R, Q_f: weights; Q_f = terminal_scale * P_bar (P_bar: DARE solution).
        terminal_scale: () the scale of Q_f (paper 001: 100 initial, 1 re-tuned).
        u_max: (2,) force limits on Fx, Fy [N].
        dock: (2,) docking point x_t (cone apex) [m].
        cone_axis: () outward cone axis angle [rad]; half_angle: () [rad];
        cone_range: () distance from the apex within which the cone is enforced [m].
        obstacle: (2,) keep-out centre [m]; r_obs: () keep-out radius [m].
        phi0: () initial hyperplane normal angle (chaser bearing from the obstacle) [rad].
        phi_final: () final normal angle (docking-point bearing from the obstacle) [rad].
        plane_rate: () signed rotation rate of the normal [rad/s] (sign = direction).
        rho: () exact penalty of the soft state rows [per metre].
        ts: () sample time [s].
        dock_tol: () docked when within this distance of the docking point [m] ...
        dock_speed_tol: () ... and slower than this [m/s].
        plant: the vehicle and its surroundings (:class:`~rvdjax.loop.plant.Plant`: mass [kg],
            orbit, drag, disturbances, continuous model, thrusters).
    """

    A: jnp.ndarray
    B: jnp.ndarray
    Q: jnp.ndarray
    R: jnp.ndarray
    Q_f: jnp.ndarray
    terminal_scale: jnp.ndarray
    u_max: jnp.ndarray
    dock: jnp.ndarray
    cone_axis: jnp.ndarray
    half_angle: jnp.ndarray
    cone_range: jnp.ndarray
    obstacle: jnp.ndarray
    r_obs: jnp.ndarray
    phi0: jnp.ndarray
    phi_final: jnp.ndarray
    plane_rate: jnp.ndarray
    rho: jnp.ndarray
    ts: jnp.ndarray
    dock_tol: jnp.ndarray
    dock_speed_tol: jnp.ndarray
    plant: Plant  # the vehicle and its surroundings (rvdjax.loop.plant)


@dataclasses.dataclass(frozen=True)
class Config:
    """Static configuration.

    Attributes:
        N: horizon (paper 001 Tables 2-3: 20).
        substeps: samples of the truth inside a ZOH step for docking detection and margins.
        predict_cone: also enforce the cone on stages predicted (previous plan) to lie within
            the cone range; False: only from the step the chaser is within range.
    """

    N: int = 20
    substeps: int = 50
    predict_cone: bool = True

    def __post_init__(self):
        checks.integer("N", self.N)
        checks.integer("substeps", self.substeps)


class Guidance(NamedTuple):
    """The entry cone has been reached (its rows stay on until docking)."""

    cone_on: jnp.ndarray


SCHEMA = Schema(
    (
        positive("mass", "kg", "chaser mass", default=10.0),
        positive("ts", "s", "sample time (zero-order hold)", default=5.0),
        value(
            "Q",
            "",
            "state weight: 4 diagonal entries or a (4, 4) PSD matrix",
            shape="(4, 4)",
            default=(1e2, 1e2, 1e5, 1e5),
        ),
        value(
            "R",
            "",
            "input weight: 2 diagonal entries or a (2, 2) PD matrix",
            shape="(2, 2)",
            default=(1e3, 1e3),
        ),
        positive(
            "terminal_scale",
            "",
            "P = terminal_scale * P_bar (100 initial, 1 re-tuned)",
            default=100.0,
        ),
        positive("u_max", "N", "F_max on each axis", default=0.15),
        value("target", "m", "target centre", shape="(2,)", default=(0.5, 0.5)),
        nonnegative(
            "dock_offset", "m", "docking point (cone apex) from the target centre", default=0.3
        ),
        finite("cone_angle_deg", "deg", "direction of the cone axis", default=45.0),
        within(
            "half_angle_deg",
            "deg",
            0.0,
            90.0,
            "entry-cone half angle",
            label="half_angle_deg (entry cone)",
            default=10.0,
        ),
        positive(
            "cone_range", "m", "distance to the docking point that activates the cone", default=0.5
        ),
        value("obstacle", "m", "keep-out zone centre", shape="(2,)", default=(2.5, 2.5)),
        positive("r_obs", "m", "keep-out zone radius", default=0.4),
        positive("plane_rate_deg_s", "deg/s", "hyperplane rotation rate", default=1.8),
        Input(
            "plane_direction",
            "+1 anticlockwise, -1 clockwise",
            kind="int",
            check="choice",
            choices=(-1, 1),
            default=1,
        ),
        positive("rho", "", "exact penalty of the soft constraint rows", default=1e8),
        positive("dock_tol", "m", "docking position tolerance", default=0.05),
        positive("dock_speed_tol", "m/s", "docking speed tolerance", default=0.05),
        value(
            "x0",
            "m, m/s",
            "initial state (x, y, vx, vy): outside the keep-out zone",
            shape="(4,)",
            kind="state",
            default=(3.5, 3.5, 0.0, 0.0),
        ),
        disturbance_table("disturbance keyword values over the lab's"),
    )
)


def _build(v) -> Params:
    """Check physical values and build :class:`Params` (once, before any jit). Keywords and
    defaults: :data:`SCHEMA` (paper 001 Tables 1-2, initial tuning, plus the scenario's
    assumptions); the docking point (cone apex) is ``dock_offset`` metres from ``target``
    along the cone axis (``cone_angle_deg``) and must lie outside the keep-out zone.
    """
    Q, R, target, obstacle, x0 = v.Q, v.R, v.target, v.obstacle, v.x0
    Q = np.diag(np.asarray(Q, float)) if np.ndim(Q) == 1 else np.asarray(Q, float)
    R = np.diag(np.asarray(R, float)) if np.ndim(R) == 1 else np.asarray(R, float)
    checks.shape("Q", Q, (NX, NX))
    checks.shape("R", R, (NU, NU))
    checks.pos_semidef("Q", Q)
    checks.pos_def("R", R)
    target = checks.shape("target", target, (2,))
    obstacle = checks.shape("obstacle", obstacle, (2,))
    x0 = checks.shape("x0", x0, (NX,))
    axis = np.deg2rad(v.cone_angle_deg)
    dock = target + v.dock_offset * np.array([np.cos(axis), np.sin(axis)])
    checks.outside("the keep-out zone", x0[:2], obstacle, v.r_obs)
    dd = float(np.linalg.norm(dock - obstacle))
    if dd <= v.r_obs:
        raise ValueError(
            f"the docking point lies inside the keep-out zone ({dd:.3g} m from the obstacle "
            f"centre, radius r_obs = {v.r_obs} m)"
        )

    from rvdjax.dynamics import dare, discretize_zoh, planar2dof_continuous

    A, B = discretize_zoh(*planar2dof_continuous(v.mass), v.ts)
    P_bar = dare(A, B, jnp.asarray(Q), jnp.asarray(R))
    phi0 = np.arctan2(*(x0[:2] - obstacle)[::-1])
    phi_f = np.arctan2(*(dock - obstacle)[::-1])
    # unwrap the final angle in the chosen direction (a full half turn when collinear)
    delta = (
        (phi_f - phi0) % (2 * np.pi) if v.plane_direction > 0 else -((phi0 - phi_f) % (2 * np.pi))
    )
    f = jnp.asarray
    return Params(
        A=A,
        B=B,
        Q=f(Q),
        R=f(R),
        Q_f=v.terminal_scale * P_bar,
        terminal_scale=f(float(v.terminal_scale)),
        u_max=f(np.full(NU, v.u_max, dtype=float)),
        dock=f(dock),
        cone_axis=f(axis),
        half_angle=f(np.deg2rad(v.half_angle_deg)),
        cone_range=f(float(v.cone_range)),
        obstacle=f(obstacle),
        r_obs=f(float(v.r_obs)),
        phi0=f(phi0),
        phi_final=f(phi0 + delta),
        plane_rate=f(v.plane_direction * np.deg2rad(v.plane_rate_deg_s)),
        rho=f(float(v.rho)),
        ts=f(float(v.ts)),
        dock_tol=f(float(v.dock_tol)),
        dock_speed_tol=f(float(v.dock_speed_tol)),
        plant=make_plant(
            float(v.mass),
            *planar2dof_continuous(v.mass),
            disturbances=make_disturbances(**{**LAB_DISTURBANCES, **(v.disturbances or {})}),
        ),
    )


make_params = make_params_of(SCHEMA, _build)


def plane_angle(p: Params, times):
    """Normal angle of the rotating hyperplane at the given times (fixed rate, then held)."""
    delta = p.phi_final - p.phi0
    return p.phi0 + jnp.sign(delta) * jnp.minimum(jnp.abs(delta), jnp.abs(p.plane_rate) * times)


def _near(p: Params, r):
    return jnp.linalg.norm(r - p.dock, axis=-1) <= p.cone_range


def init(p: Params, fc: Config, x0):
    return Guidance(cone_on=_near(p, x0[:2]))


def initial_plan(p: Params, fc: Config, g, x0):
    return drift_plan(p.A, x0, fc.N, NU)


def observe(p: Params, fc: Config, g: Guidance, x, t, plan):
    return Guidance(cone_on=g.cone_on | _near(p, x[:2]))


def ocp(p: Params, fc: Config, g: Guidance, x, t, plan):
    """Rotating-hyperplane keep-out and entry cone (on for the stages in range)."""
    N = fc.N
    times = t + p.ts * jnp.arange(1, N + 1, dtype=x.dtype)
    # predicted activation: stages whose previous-plan position lies in the cone range
    stage_on = g.cone_on | (_near(p, plan.x[:, :2]) & fc.predict_cone)
    blocks = [
        rotating_hyperplane(
            jnp.broadcast_to(p.obstacle, (N, 2)),
            plane_angle(p, times),
            p.r_obs,
            NX,
            POS,
            rho=p.rho,
            name="keep_out_plane",
        ),
        entry_cone(
            jnp.broadcast_to(p.dock, (N, 2)),
            jnp.broadcast_to(p.cone_axis, (N,)),
            p.half_angle,
            NX,
            POS,
            rho=p.rho,
        ).masked(stage_on),
    ]
    x_ref = jnp.broadcast_to(jnp.concatenate([p.dock, jnp.zeros(2, x.dtype)]), (N, NX))
    problem = tracking_ocp(model(p, fc), x, x_ref, blocks, thrust_box(p.u_max, N))
    return problem, blocks


def subsamples(p: Params, fc: Config, x, u, dt=None):
    """The truth at ``fc.substeps`` instants inside the step of ``p.ts`` seconds (double
    integrator, constant force): taus (M,) [s] and states (M, 4). ``dt`` is ``p.ts`` here."""
    M = fc.substeps
    tau = p.ts * jnp.arange(1, M + 1, dtype=x.dtype) / M
    a = u / p.plant.mass
    r = x[None, :2] + tau[:, None] * x[None, 2:] + 0.5 * tau[:, None] ** 2 * a
    v = x[None, 2:] + tau[:, None] * a
    return tau, jnp.concatenate([r, v], axis=-1)


def update(p: Params, fc: Config, g: Guidance, x, u, x_next, t, ts, samples):
    """Docked at the first sub-sample within ``dock_tol`` of the docking point and slower
    than ``dock_speed_tol``; the command acted until then."""
    tau, sub = samples
    ok = (jnp.linalg.norm(sub[:, :2] - p.dock, axis=-1) < p.dock_tol) & (
        jnp.linalg.norm(sub[:, 2:], axis=-1) < p.dock_speed_tol
    )
    docked = jnp.any(ok)
    dt = jnp.where(docked, tau[jnp.argmax(ok)], ts)
    return g, docked, dt, tau <= dt


def truth_blocks(p: Params, fc: Config, g: Guidance, x, t):
    """Keep-out circle and entry cone within range (judged), the rotating plane (reported)."""
    r = x[None, :2]
    phi = plane_angle(p, jnp.asarray(t))[None]
    return [
        sphere_keep_out(r, p.obstacle[None], p.r_obs, NX, POS, name="keep_out"),
        entry_cone(p.dock[None], p.cone_axis[None], p.half_angle, NX, POS).masked(
            g.cone_on & _near(p, x[:2])
        ),
        rotating_hyperplane(p.obstacle[None], phi, p.r_obs, NX, POS, name="keep_out_plane").with_(
            kind="monitor"
        ),
    ]


def dock_error(p: Params, fc: Config, g: Guidance, x, t):
    """Distance beyond dock_tol of the docking point [m]."""
    return smooth_excess(smooth_norm(x[:2] - p.dock), p.dock_tol)


def _derive(p: Params, names) -> Params:
    """The ZOH model from the sample time, then Q_f = terminal_scale * P_bar."""
    from rvdjax.dynamics import discretize_zoh, planar2dof_continuous

    if "ts" in names:
        A, B = discretize_zoh(*planar2dof_continuous(p.plant.mass), p.ts)
        p = p._replace(A=A, B=B)
    return derive_terminal(p, names, p.terminal_scale)


TUNING = Tuning(
    tunables={
        **weight_tunables(),
        "terminal_scale": field_tunable(
            "terminal_scale",
            "terminal weight scale: Q_f = terminal_scale P_bar (paper 001 Tables 2-3)",
            derived=True,
        ),
        "ts": field_tunable(
            "ts",
            "sample time [s] (the discrete model follows; the run's step budget does not)",
            derived=True,
        ),
    },
    derive=_derive,
)


FAMILY = Family(
    name="poseidyn",
    description="planar double-integrator LQ-MPC docking with a rotating-hyperplane keep-out "
    "and entry cone (paper 001)",
    law=Hooks.of(
        globals(),
        **SHARED_HOOKS,
        model=tracking_fixed,
        layout=LAYOUT,
        n_phases=1,
        config_type=Config,
    ),
    make_params=make_params,
    plot=lazy("rvdjax.families.plots.poseidyn:plot"),
    baselines=("idvd",),
    tuning=TUNING,
)
