"""rvdjax: model predictive control guidance for spacecraft rendezvous and docking in JAX."""

import jax as _jax

from rvdjax import xla_options as _xla_options

# XLA CPU options for small batched blocks, before JAX starts its backend (rvdjax.xla_options).
_xla_options.apply()

# float64 by default: the RVD problems span ~1e7 in cost and ~1e-3 in docking speed.
_jax.config.update("jax_enable_x64", True)

from rvdjax.families import FAMILIES, get_family  # noqa: E402
from rvdjax.loop import Loop, LoopConfig, Metrics, RunStatus, StepInfo, fly, init, step  # noqa: E402
from rvdjax.ocp import OCP, make_ocp, validate_ocp  # noqa: E402
from rvdjax.scenarios import SCENARIOS, Scenario, get_scenario  # noqa: E402
from rvdjax.solver import (  # noqa: E402
    Plan,
    Solution,
    SolverParams,
    SolverSettings,
    Status,
    shift_solution,
    solve,
    solve_batch,
)

__all__ = [
    "FAMILIES",
    "get_family",
    "Loop",
    "LoopConfig",
    "Metrics",
    "RunStatus",
    "StepInfo",
    "fly",
    "init",
    "step",
    "OCP",
    "make_ocp",
    "validate_ocp",
    "SCENARIOS",
    "Scenario",
    "get_scenario",
    "Plan",
    "Solution",
    "SolverParams",
    "SolverSettings",
    "Status",
    "shift_solution",
    "solve",
    "solve_batch",
]
