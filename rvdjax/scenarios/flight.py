"""A flight: one scenario made runnable, checked once.

"Fly scenario X with its thrusters, disturbed, in paper mode" is one choice of
:class:`FlightOptions`; :meth:`Scenario.flight <rvdjax.scenarios.Scenario.flight>` resolves it
into a :class:`Flight` (the static loop, the checked traced parameters, the initial state, the
solver's traced parameters and the PRNG key). Every command and study builds its runs through
it, so that a bad choice is refused in the same words wherever it is made, before anything is
compiled.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import TYPE_CHECKING, Any

import numpy as np

from rvdjax.actuators.thrusters import ThrusterSet
from rvdjax.loop.kernel import Loop
from rvdjax.solver import SolverParams

if TYPE_CHECKING:  # the scenario module imports this one
    from rvdjax.scenarios import Scenario

__all__ = ["FlightOptions", "Flight", "MODES", "TRUTHS"]

#: Solver modes: "accurate" (barrier continuation to the tolerance), "paper" (paper 000's fixed
#: kappa and Newton steps), "barrier" (fixed kappa, converged).
MODES = ("accurate", "paper", "barrier")
#: Truth propagations (what a family supports: ``Family.truths``).
TRUTHS = ("linear", "two-body", "two-body-j2", "two-body-j2-drag")


@dataclasses.dataclass(frozen=True)
class FlightOptions:
    """How to fly a scenario (plain data; checked when made).

    Attributes:
        mode: solver mode, one of :data:`MODES`.
        truth: truth propagation, one of :data:`TRUTHS` (the family must support it).
        disturbed: navigation noise, thrust-amplitude error and minimum impulse bit of the
            scenario's disturbance parameters (paper 003 Ch. 5), drawn from ``seed``.
        nav_filter: a Kalman filter on the noisy measurements feeds the guidance (needs
            ``disturbed``).
        thrusters: fly the scenario's thruster set (True), ideal forces (False) or the given
            :class:`~rvdjax.actuators.ThrusterSet`.
        faults: apply the thruster set's faults (needs thrusters).
        n_steps: MPC steps at most (None: the scenario's).
        time_limit_s: a run not docked by then ends as a timeout [s] (None: no limit).
        seed: the PRNG seed of the run's key (noise draws).
    """

    mode: str = "accurate"
    truth: str = "linear"
    disturbed: bool = False
    nav_filter: bool = False
    thrusters: bool | ThrusterSet = False
    faults: bool = False
    n_steps: int | None = None
    time_limit_s: float | None = None
    seed: int = 0

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.truth not in TRUTHS:
            raise ValueError(f"truth must be one of {', '.join(TRUTHS)}, got {self.truth!r}")
        if self.nav_filter and not self.disturbed:
            raise ValueError("nav_filter needs disturbed (it filters the noisy measurements)")
        if self.faults and self.thrusters is False:
            raise ValueError("faults needs thrusters (the faults are the thruster set's)")
        if self.n_steps is not None and int(self.n_steps) < 1:
            raise ValueError(f"n_steps must be >= 1, got {self.n_steps}")
        if self.time_limit_s is not None and not float(self.time_limit_s) > 0:
            raise ValueError(f"time_limit_s must be > 0 [s], got {self.time_limit_s}")

    def replace(self, **changes) -> FlightOptions:
        return dataclasses.replace(self, **changes)

    @classmethod
    def of(cls, source, **changes) -> FlightOptions:
        """The options held by ``source`` (a study's, a verification's or a tuning's spec,
        parsed arguments: any object with some of these fields by name), with ``changes``."""
        names = [f.name for f in dataclasses.fields(cls)]
        values = {n: getattr(source, n) for n in names if hasattr(source, n)}
        return cls(**{**values, **changes})


@dataclasses.dataclass(frozen=True, eq=False)
class Flight:
    """A scenario ready to fly: what :func:`rvdjax.loop.fly` and the batch engine take.

    Attributes:
        scenario: the :class:`~rvdjax.scenarios.Scenario`.
        options: the :class:`FlightOptions` it was made from.
        loop: the static closed loop (:class:`~rvdjax.loop.Loop`).
        params: the family's checked traced parameters (thrusters attached when flown).
        x0: the initial state.
        solver_params: the solver's traced parameters of the mode (paper mode: the scenario's
            kappa).
        key: the PRNG key of ``options.seed``.
        physical: the physical values that replaced the scenario's (``Scenario.flight``'s
            keywords), kept so that :meth:`build` disperses around this flight.
    """

    scenario: Scenario
    options: FlightOptions
    loop: Loop
    params: Any
    x0: np.ndarray
    solver_params: SolverParams
    key: Any
    physical: dict = dataclasses.field(default_factory=dict)

    @property
    def thruster_set(self) -> ThrusterSet | None:
        """The thruster set flown, or None (ideal forces)."""
        return self.scenario.thruster_set(self.options.thrusters)

    def build(self, **physical):
        """(params, x0) with other physical values (and ``x0``) on top of this flight's, the
        same thrusters: a run of a study or a verification that disperses the scenario's
        values. Not checked against the loop again (the nominal flight was)."""
        return self.scenario.build(
            thrusters=self.options.thrusters, **{**self.physical, **physical}
        )

    def replace(self, **changes) -> Flight:
        return dataclasses.replace(self, **changes)

    def fly(self, remat: bool = False):
        """Fly it once, jitted: (StepInfo with a leading step axis, Metrics). Compiled once
        per loop (the static part): flights that share it, and later calls, reuse the
        program."""
        return _fly()(self.loop, self.params, self.x0, self.key, self.solver_params, remat=remat)

    def fly_timed(self):
        """Compile, then fly once: (infos, metrics, wall time per MPC step [ms], the compiled
        flight excluded)."""
        import time

        import jax

        compiled = self.compile()
        t0 = time.perf_counter()
        infos, metrics = jax.block_until_ready(
            compiled(self.params, self.x0, self.key, self.solver_params)
        )
        wall = time.perf_counter() - t0
        return infos, metrics, 1e3 * wall / max(int(metrics.steps), 1)

    def compile(self, remat: bool = False):
        """The compiled flight: a function of (params, x0, key, solver params)."""
        lowered = _fly().lower(
            self.loop, self.params, self.x0, self.key, self.solver_params, remat=remat
        )
        return lowered.compile()

    def notes(self) -> tuple[str, ...]:
        """The assumptions printed with this flight's results."""
        return self.scenario.notes(self.options.mode, thrusters=self.options.thrusters)


def make_flight(
    scenario: Scenario,
    options: FlightOptions | None = None,
    *,
    settings=None,
    config: dict | None = None,
    check: bool = True,
    **physical,
) -> Flight:
    """:meth:`Scenario.flight <rvdjax.scenarios.Scenario.flight>` (its docstring)."""
    import jax

    options = FlightOptions() if options is None else options
    tset = scenario.thruster_set(options.thrusters)  # ValueError when it has none
    loop = scenario.loop(  # first: its checks need no arrays (nothing computed yet)
        options.mode,
        truth=options.truth,
        disturbed=options.disturbed,
        n_steps=options.n_steps,
        settings=settings,
        time_limit_s=options.time_limit_s,
        nav_filter=options.nav_filter,
        thrusters=False if tset is None else tset,
        faults=options.faults,
        **(config or {}),
    )
    params, x0 = scenario.build(thrusters=False if tset is None else tset, **physical)
    if check:
        scenario.check(params, x0, loop)
    return Flight(
        scenario=scenario,
        options=options,
        loop=loop,
        params=params,
        x0=x0,
        solver_params=scenario.solver_params(options.mode),
        key=jax.random.key(int(options.seed)),
        physical=dict(physical),
    )


@functools.cache
def _fly():
    """:func:`rvdjax.loop.fly` jitted with the loop static (one program per loop)."""
    import jax

    from rvdjax.loop import fly

    return jax.jit(fly, static_argnames=("loop", "remat"))
