"""A guidance family in one file: a 1-D double integrator (a cart on a rail) driven to the
origin by MPC with a thrust bound. docs/writing-a-family.md walks through it."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from rvdjax import checks
from rvdjax.constraints import thrust_box, velocity_bound
from rvdjax.disturbances import disturbances as make_disturbances
from rvdjax.families.common import (
    control,
    model,
    sample_time,
    tracking_fixed,
    tracking_ocp,
    truth_model,
)
from rvdjax.loop.family import Family, Hooks, Layout
from rvdjax.loop.plant import Plant
from rvdjax.schema import Schema, make_params_of, positive, value
from rvdjax.solver import drift_plan

# 1. The state and the input: position and velocity, one force.
LAYOUT = Layout(nx=2, nu=1, pos=(0,), vel=(1,), force=(0,), names=("x", "vx"))


# 2. The traced parameters: arrays only, the plant (what the kernel flies) in one field.
class Params(NamedTuple):
    A: jnp.ndarray  # (2, 2) discrete model (zero-order hold)
    B: jnp.ndarray  # (2, 1)
    Q: jnp.ndarray  # (2, 2) state weight
    R: jnp.ndarray  # (1, 1) input weight
    Q_f: jnp.ndarray  # (2, 2) terminal weight
    u_max: jnp.ndarray  # (1,) thrust bound [N]
    v_max: jnp.ndarray  # () speed limit [m/s] (soft)
    ts: jnp.ndarray  # () sample time [s]
    arrive_tol: jnp.ndarray  # () the run ends when |x| <= arrive_tol [m]
    plant: Plant  # mass, disturbances, continuous model; no orbit, drag or thrusters


# 3. The static configuration: what shapes the program (a change recompiles).
@dataclasses.dataclass(frozen=True)
class Config:
    N: int = 10

    def __post_init__(self):
        checks.integer("N", self.N)


class Guidance(NamedTuple):
    """No guidance state: one phase, fixed constraints."""


# 4. The physical inputs, declared once: checks, defaults, units, scenario-file keys.
SCHEMA = Schema(
    (
        positive("mass", "kg", "cart mass", default=1.0),
        positive("ts", "s", "sample time (zero-order hold)", default=0.5),
        positive("u_max", "N", "thrust bound", default=0.5),
        positive("v_max", "m/s", "speed limit (soft state rows)", default=1.0),
        value("q", "", "state weight diagonal (position, velocity)", default=(1.0, 1.0)),
        positive("r", "", "input weight", default=1.0),
        positive("arrive_tol", "m", "distance to the origin that ends the run", default=0.05),
        value("x0", "m, m/s", "initial state", shape="(2,)", kind="state", default=None),
        value("disturbances", "", "disturbance keyword values", kind="table", default=None),
    )
)


def _build(v) -> Params:
    """The checked inputs ``v`` -> :class:`Params` (host-side, once, before any jit)."""
    from rvdjax.dynamics import dare, discretize_zoh

    Ac = np.array([[0.0, 1.0], [0.0, 0.0]])
    Bc = np.array([[0.0], [1.0 / v.mass]])
    A, B = discretize_zoh(Ac, Bc, v.ts)
    Q, R = np.diag(np.asarray(v.q, float)), np.array([[float(v.r)]])
    checks.pos_semidef("q", Q)
    f = jnp.asarray
    return Params(
        A=A,
        B=B,
        Q=f(Q),
        R=f(R),
        Q_f=dare(A, B, f(Q), f(R)),
        u_max=f(np.full(1, float(v.u_max))),
        v_max=f(float(v.v_max)),
        ts=f(float(v.ts)),
        arrive_tol=f(float(v.arrive_tol)),
        plant=Plant(
            mass=f(float(v.mass)),
            disturbances=make_disturbances(**(v.disturbances or {})),
            Ac=f(Ac),
            Bc=f(Bc),
        ),
    )


make_params = make_params_of(SCHEMA, _build)


# 5. The guidance law: pure functions of arrays, traced by the kernel.
def init(p: Params, fc: Config, x0):
    return Guidance()


def initial_plan(p: Params, fc: Config, g, x0):
    return drift_plan(p.A, x0, fc.N, LAYOUT.nu)


def observe(p, fc, g, x, t, plan):
    return g


def ocp(p: Params, fc: Config, g, x, t, plan):
    """Track the origin under the thrust box (hard) and the speed limit (soft rows)."""
    x_ref = jnp.zeros((fc.N, LAYOUT.nx), x.dtype)
    speed = velocity_bound(p.v_max, fc.N, LAYOUT.nx, LAYOUT.vel)
    return tracking_ocp(model(p, fc), x, x_ref, [speed], thrust_box(p.u_max, fc.N)), [speed]


def update(p: Params, fc, g, x, u, x_next, t, ts, samples):
    arrived = jnp.abs(x_next[0]) <= p.arrive_tol
    return g, arrived, ts, jnp.zeros(samples[0].shape, bool)


def truth_blocks(p, fc, g, x, t):
    """The speed limit at the truth itself (one stage): its margin is reported per step."""
    return [velocity_bound(p.v_max, 1, LAYOUT.nx, LAYOUT.vel)]


# 6. The registry entry: the hooks, and apart from them what the host side reads.
FAMILY = Family(
    name="double-integrator",
    description="1-D double integrator to the origin under a thrust bound",
    law=Hooks(
        layout=LAYOUT,
        n_phases=1,
        config_type=Config,
        horizon=lambda fc: fc.N,
        init=init,
        initial_plan=initial_plan,
        observe=observe,
        ocp=ocp,
        control=control,
        sample_time=sample_time,
        truth_model=truth_model,
        update=update,
        truth_blocks=truth_blocks,
        model=tracking_fixed,
    ),
    make_params=make_params,
)
