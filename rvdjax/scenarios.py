"""Named closed-loop scenarios from the papers, with their published figures and assumptions.

Each scenario gives the traced :class:`~rvdjax.sim.LoopParams`, the static
:class:`~rvdjax.sim.LoopConfig`, the initial state, the values the paper published, and the
assumptions made where the paper is silent (printed with every result).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np

from rvdjax.problems import DEFAULT_RHO, FASTMPC3D, fastmpc3d_model
from rvdjax.propagate import circular_orbit
from rvdjax.sim import LoopConfig, LoopParams
from rvdjax.solver import SolverSettings

__all__ = ["Scenario", "SCENARIOS", "get_scenario", "DEFAULT_SCENARIO"]


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A named closed-loop case.

    Attributes:
        name: command-line name.
        source: paper and table.
        description: one line.
        build: () -> (LoopParams, x0) — concrete arrays, validated.
        config: static loop configuration (horizon, steps, solver).
        published: figure of merit -> (value, unit, what it is) from the paper.
        assumptions: what rvdjax chose where the paper is silent.
    """

    name: str
    source: str
    description: str
    build: Callable[[], tuple[LoopParams, np.ndarray]]
    config: LoopConfig
    published: dict
    assumptions: tuple[str, ...]


def _fastmpc3d(obstacles: bool):
    def build():
        p = FASTMPC3D
        Ad, Bd, P = fastmpc3d_model()
        n_obs = len(p["radii"])
        params = LoopParams(
            A=Ad,
            B=Bd,
            Q=jnp.diag(jnp.asarray(p["Q"])),
            R=jnp.diag(jnp.asarray(p["R"])),
            Q_f=P,
            u_max=jnp.full(3, p["u_max"]),
            x_ref=jnp.zeros(6),
            obstacles=jnp.asarray(p["obstacles"]),
            radii=jnp.asarray(p["radii"]),
            obstacle_mask=jnp.full(n_obs, 1.0 if obstacles else 0.0),
            rho=jnp.asarray(DEFAULT_RHO),
            ts=jnp.asarray(p["ts"]),
            mass=jnp.asarray(p["mass"]),
            stop_radius=jnp.asarray(p["hold_radius"]),
            orbit=circular_orbit(p["altitude_m"]),  # used by the nonlinear truth options
        )
        return params, np.asarray(p["x0"], dtype=float)

    return build


_FASTMPC_ASSUMPTIONS = (
    "obstacles move on straight lines at their Table 1 velocities (paper: 'constant "
    "translational velocity')",
    "keep-out rows re-linearised each step about the previous plan (first step: unforced drift)",
    "keep-out rows are soft with exact L1 penalty rho = 1e8 (~100x the largest multiplier)",
    "'total impulse' compared as sum_k ||u_k||_1 Ts (per-axis thrusters); the L2 sum is also "
    "reported",
    "Earth mu = 3.986004418e14 m^3/s^2, radius 6378.137 km; the truth is the CW model itself "
    "unless --truth two-body / two-body-j2 (equatorial circular target orbit at 705 km)",
)

SCENARIOS: dict[str, Scenario] = {
    "fastmpc-3d": Scenario(
        name="fastmpc-3d",
        source="paper 000 Sec. IV.A, Table 1",
        description="3-D CW rendezvous at 705 km to 2.3 m, two moving spherical keep-out zones",
        build=_fastmpc3d(obstacles=True),
        config=LoopConfig(N=30, n_steps=240, settings=SolverSettings()),
        published={
            "total_impulse_kN_s": {
                "Fast MPC": 33.98,
                "ISNM": 33.80,
                "IPOPT NMPC": 32.93,
                "fmincon": 34.33,
            },
        },
        assumptions=_FASTMPC_ASSUMPTIONS,
    ),
    "fastmpc-3d-free": Scenario(
        name="fastmpc-3d-free",
        source="paper 000 Sec. IV.A, Table 1 (obstacles absent)",
        description="3-D CW rendezvous at 705 km to 2.3 m, no obstacles",
        build=_fastmpc3d(obstacles=False),
        config=LoopConfig(N=30, n_steps=240, settings=SolverSettings()),
        published={},  # paper 000 plots this case (Fig. 3, left) but gives no impulse
        assumptions=_FASTMPC_ASSUMPTIONS[3:],
    ),
}

DEFAULT_SCENARIO = "fastmpc-3d"


def get_scenario(name: str) -> Scenario:
    """Look a scenario up by name; ValueError listing the known names otherwise."""
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(
            f"unknown scenario {name!r}; known: {', '.join(sorted(SCENARIOS))}"
        ) from None
