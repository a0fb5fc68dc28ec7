"""Named closed-loop scenarios: plain records (family, physical values, initial state,
configuration, published figures, assumptions), one module per paper.

Adding a scenario is one :class:`Scenario` record in a module listed in ``_MODULES``; its family
(:data:`rvdjax.families.FAMILIES`) turns the physical values into checked traced parameters
(:meth:`Scenario.build`) and supplies the closed loop (:meth:`Scenario.loop`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from rvdjax.families import get_family
from rvdjax.loop.family import Family
from rvdjax.loop.kernel import Loop, LoopConfig
from rvdjax.solver import SolverParams, SolverSettings

__all__ = [
    "Scenario",
    "SCENARIOS",
    "DEFAULT_SCENARIO",
    "get_scenario",
    "paper_kappa",
    "PAPER_KAPPA",
]

# Paper 000 Sec. IV.A: kappa = 0.05 for its simulations (0.1 on the SPOT test bed, Sec. IV.C).
PAPER_KAPPA = 0.05
_KAPPA_NOTE = (
    "paper mode: kappa = {kappa:.3g} instead of paper 000's 0.05. A fixed-kappa barrier holds "
    "the chaser about sqrt(kappa / q) from a docking point that sits on a constraint boundary "
    "(the entry-cone apex, the holding circle), q = the position weight; kappa = "
    "min(0.05, q (tol / 2)^2) keeps that stand-off below half the docking tolerance tol. With "
    "0.05 the planar chasers hover 0.08-0.13 m off the port and never dock"
)


def paper_kappa(q_position: float, dock_tol_m: float) -> float:
    """Paper-mode kappa for a docking set-up: min(0.05, q (tol / 2)^2).

    Near a docking point on a constraint boundary (cone apex, holding circle) the fixed-kappa
    barrier problem balances the cost gradient ~2 q e with the barrier gradient ~2 kappa / e
    (two cone faces at distance ~e), so the chaser settles e ~ sqrt(kappa / q) off the point;
    this keeps e <= tol / 2. Smaller kappa is not free: with 10 Newton iterations a warm
    start no longer converges (poseidyn-lqmpc fails to dock at kappa = 5e-4).
    """
    return min(PAPER_KAPPA, q_position * (0.5 * dock_tol_m) ** 2)


@dataclasses.dataclass(frozen=True, eq=False)
class Scenario:
    """A named closed-loop case (plain data).

    Attributes:
        name: command-line name.
        family: key of :data:`rvdjax.families.FAMILIES`.
        source: paper and table.
        description: one line.
        physical: keyword values of the family's ``make_params`` (plain numbers, SI units
            unless the key says otherwise).
        x0: initial state.
        config: keyword values of the family's static configuration (horizon, options).
        n_steps: MPC steps at most.
        published: metric name (a field of :class:`rvdjax.loop.Metrics`) -> {label: value}.
        assumptions: what rvdjax chose where the paper is silent (printed with every result).
        paper_kappa: the fixed barrier weight of paper mode for this scenario (:func:`paper_kappa`).
        solver: SolverSettings overrides (e.g. a larger iteration cap).
    """

    name: str
    family: str
    source: str
    description: str
    physical: Mapping[str, Any]
    x0: tuple
    config: Mapping[str, Any]
    n_steps: int
    published: Mapping[str, Mapping[str, float]]
    assumptions: tuple[str, ...]
    paper_kappa: float = PAPER_KAPPA
    solver: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def family_(self) -> Family:
        return get_family(self.family)

    def build(self, **overrides):
        """(params, x0): the family's checked traced parameters and the initial state.
        ``overrides`` change physical values (and ``x0``) before the checks."""
        physical = {**self.physical, **overrides}
        x0 = np.asarray(physical.pop("x0", self.x0), dtype=float)
        params = self.family_.make_params(**physical, x0=x0)
        return params, x0

    def settings(self, mode: str = "accurate", **overrides) -> SolverSettings:
        """Solver settings of a named mode ("paper", "accurate" or "barrier")."""
        base = {**self.solver, **overrides}
        if mode == "paper":
            return SolverSettings.paper(**{k: v for k, v in base.items() if k != "max_iter"})
        return SolverSettings(mode=mode, **base)

    def solver_params(self, mode: str = "accurate", **overrides) -> SolverParams:
        """Traced solver parameters of a mode (paper mode: this scenario's kappa)."""
        if mode == "paper":
            return SolverParams.paper(**{"kappa": self.paper_kappa, **overrides})
        return SolverParams.accurate(**overrides)

    def loop(
        self,
        mode: str = "accurate",
        truth: str = "linear",
        disturbed: bool = False,
        n_steps: int | None = None,
        settings: SolverSettings | None = None,
        time_limit_s: float | None = None,
        nav_filter: bool = False,
        **config,
    ) -> Loop:
        """The static closed loop of this scenario (family config overrides in ``config``;
        ``time_limit_s`` and ``nav_filter``: :class:`~rvdjax.loop.kernel.LoopConfig`)."""
        fam = self.family_
        fconfig = fam.config_type(**{**self.config, **config})
        return Loop(
            fam,
            LoopConfig(
                family=fconfig,
                n_steps=self.n_steps if n_steps is None else n_steps,
                settings=self.settings(mode) if settings is None else settings,
                truth=truth,
                disturbed=disturbed,
                time_limit_s=time_limit_s,
                nav_filter=nav_filter,
            ),
        )

    def check(self, params, x0, loop: Loop) -> None:
        """Configuration-dependent checks of the family (ValueError before anything runs)."""
        if loop.config.truth != "linear" and params.orbit is None:
            raise ValueError(f"truth={loop.config.truth!r} needs the target's orbit")
        if loop.config.disturbed and params.disturbances is None:
            raise ValueError("a disturbed run needs disturbance parameters")
        if self.family_.check is not None:
            self.family_.check(params, x0, loop.config)

    def notes(self, mode: str) -> tuple[str, ...]:
        """The assumptions printed with a run in ``mode``."""
        if mode == "paper" and self.paper_kappa != PAPER_KAPPA:
            return (*self.assumptions, _KAPPA_NOTE.format(kappa=self.paper_kappa))
        return self.assumptions


def _registry() -> dict[str, Scenario]:
    from rvdjax.scenarios import examples, paper000, paper001, paper002, paper003

    out: dict[str, Scenario] = {}
    for module in (paper000, paper001, paper002, paper003, examples):
        for sc in module.SCENARIOS:
            if sc.name in out:
                raise ValueError(f"scenario {sc.name!r} is defined twice")
            out[sc.name] = sc
    return out


SCENARIOS: dict[str, Scenario] = _registry()
DEFAULT_SCENARIO = "fastmpc-3d"


def get_scenario(name: str) -> Scenario:
    """Look a scenario up by name; ValueError listing the known names otherwise."""
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(
            f"unknown scenario {name!r}; known: {', '.join(sorted(SCENARIOS))}"
        ) from None
