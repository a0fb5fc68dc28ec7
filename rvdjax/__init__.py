"""rvdjax: model predictive control guidance for spacecraft rendezvous and docking in JAX."""

import jax as _jax

# float64 by default: the RVD problems span ~1e7 in cost and ~1e-3 in docking speed.
_jax.config.update("jax_enable_x64", True)

from rvdjax.ocp import OCP, make_ocp, validate_ocp  # noqa: E402
from rvdjax.scenarios import SCENARIOS, Scenario, get_scenario  # noqa: E402
from rvdjax.sim import LoopConfig, LoopParams, Metrics, StepInfo, run_closed_loop  # noqa: E402
from rvdjax.solver import (  # noqa: E402
    Plan,
    Solution,
    SolverSettings,
    Status,
    shift_solution,
    solve,
    solve_batch,
)

__all__ = [
    "OCP",
    "make_ocp",
    "validate_ocp",
    "Plan",
    "Solution",
    "SolverSettings",
    "Status",
    "solve",
    "solve_batch",
    "shift_solution",
    "LoopConfig",
    "LoopParams",
    "Metrics",
    "StepInfo",
    "run_closed_loop",
    "SCENARIOS",
    "Scenario",
    "get_scenario",
]
