"""Named closed-loop scenarios: plain records (family, physical values, initial state,
configuration, published figures, assumptions), one module per paper.

A record in the package is for the papers' cases only (and ``examples.py``'s one showcase).
Users fly their own mission from a scenario file: ``rvdjax scenario show thesis-vbar --toml
--out my.toml``, edit it, ``rvdjax run my.toml`` (:mod:`rvdjax.scenarios.files`,
docs/scenario-files.md); every command that takes a scenario name takes a ``.toml`` path
(:func:`get_scenario`). The family (:data:`rvdjax.families.FAMILIES`) turns the physical values
into checked traced parameters (:meth:`Scenario.build`) and supplies the closed loop
(:meth:`Scenario.loop`).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from rvdjax.actuators.thrusters import ThrusterSet
from rvdjax.families import get_family
from rvdjax.loop.family import Family
from rvdjax.loop.kernel import Loop, LoopConfig
from rvdjax.loop.plant import with_plant
from rvdjax.scenarios.flight import Flight, FlightOptions
from rvdjax.solver import SolverParams, SolverSettings

__all__ = [
    "Scenario",
    "SCENARIOS",
    "DEFAULT_SCENARIO",
    "get_scenario",
    "paper_kappa",
    "PAPER_KAPPA",
    "Flight",
    "FlightOptions",
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
        thrusters: the vehicle's :class:`~rvdjax.actuators.ThrusterSet` (flown with
            ``build(thrusters=True)`` and ``loop(thrusters=True)``), or None.
        thruster_metrics: published figure -> the metric that computes it as the paper
            defines it when the thrusters fly (e.g. paper 002's effort, Eq. 11, sums every
            thruster's impulse: ``thruster_impulse_N_s``); figures not listed keep their name.
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
    thrusters: ThrusterSet | None = None
    thruster_metrics: Mapping[str, str] = dataclasses.field(default_factory=dict)

    @property
    def guidance_family(self) -> Family:
        """The :class:`~rvdjax.loop.family.Family` record named by :attr:`family`."""
        return get_family(self.family)

    def build(self, thrusters: bool | ThrusterSet = False, **overrides):
        """(params, x0): the family's checked traced parameters and the initial state.
        ``overrides`` change physical values (and ``x0``) before the checks. ``thrusters``:
        attach the scenario's thruster set (True) or the given one (``params.plant.thrusters``);
        overrides named in :data:`THRUSTER_KEYS` change the set's values and dispersions."""
        physical = {**self.physical, **overrides}
        x0 = np.asarray(physical.pop("x0", self.x0), dtype=float)
        thr_keys = {k: physical.pop(k) for k in list(physical) if k in THRUSTER_KEYS}
        params = self.guidance_family.make_params(**physical, x0=x0)
        tset = self.thruster_set(thrusters)
        if thr_keys and tset is None:
            raise ValueError(
                f"{', '.join(thr_keys)}: only with the thrusters flown (thrusters=True)"
            )
        if tset is not None:
            values = {THRUSTER_KEYS[k]: v for k, v in thr_keys.items()}
            fields = {k: v for k, v in values.items() if k in _SET_FIELDS}
            if fields:
                tset = tset.replace(**fields)
            disp = {k: np.asarray(v, float) for k, v in values.items() if k not in _SET_FIELDS}
            if "misalignment" in disp:
                disp["misalignment"] = disp["misalignment"].reshape(tset.n, 3)
            if "fault" in disp:
                disp["fault"] = disp["fault"].astype(int)
            params = with_plant(params, thrusters=tset.build(**disp))
            if params.plant.Ac is not None:
                from rvdjax.actuators.response import check_series

                check_series(params.plant.Ac, params.ts)
        return params, x0

    def thruster_nominal(self, key: str):
        """The nominal value of a :data:`THRUSTER_KEYS` entry (studies draw around it)."""
        tset = self.thruster_set(True)
        name = THRUSTER_KEYS[key]
        if name in _SET_FIELDS:
            v = getattr(tset, name)
            return (
                tuple(np.broadcast_to(np.asarray(v, float), (tset.n,))) if name == "thrust_N" else v
            )
        shape = (tset.n * 3,) if name == "misalignment" else (tset.n,)
        return tuple(np.zeros(shape))

    def thruster_set(self, thrusters: bool | ThrusterSet = True) -> ThrusterSet | None:
        """The thruster set ``thrusters`` asks for: this scenario's (True), none (False) or
        the one given. ValueError if the scenario has none."""
        if isinstance(thrusters, ThrusterSet):
            return thrusters
        if not thrusters:
            return None
        if self.thrusters is None:
            raise ValueError(f"thrusters: scenario {self.name!r} has no thruster set")
        return self.thrusters

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
        thrusters: bool | ThrusterSet = False,
        faults: bool = False,
        **config,
    ) -> Loop:
        """The static closed loop of this scenario (family config overrides in ``config``;
        in paper mode a family's ``between_samples`` defaults to False;
        ``time_limit_s`` and ``nav_filter``: :class:`~rvdjax.loop.kernel.LoopConfig`;
        ``thrusters``: fly the scenario's thruster set (True) or the one given; ``faults``:
        apply the thrusters' faults, :attr:`~rvdjax.actuators.Actuation.faults`)."""
        fam = self.guidance_family
        tset = self.thruster_set(thrusters)
        config = {**self.config, **config}
        fields = {f.name for f in dataclasses.fields(fam.config_type)}
        if mode == "paper" and "between_samples" in fields and "between_samples" not in config:
            # paper 000's 10 fixed-kappa Newton steps end unconverged in most steps: extra rows
            # between samples then move its plans by rounding (the LP rendezvous from clear of
            # the keep-out sphere to 4 m inside it with XLA's optimisation level 0), so paper
            # mode plans the samples only, as the papers do
            config["between_samples"] = False
        fconfig = fam.config_type(**config)
        return Loop(
            fam,
            LoopConfig(
                family_config=fconfig,
                n_steps=self.n_steps if n_steps is None else n_steps,
                settings=self.settings(mode) if settings is None else settings,
                truth=truth,
                disturbed=disturbed,
                time_limit_s=time_limit_s,
                nav_filter=nav_filter,
                actuation=None if tset is None else tset.actuation(faults=faults),
            ),
        )

    def flight(
        self,
        options: FlightOptions | None = None,
        *,
        settings: SolverSettings | None = None,
        config: Mapping[str, Any] | None = None,
        check: bool = True,
        **physical,
    ) -> Flight:
        """This scenario made runnable: a :class:`~rvdjax.scenarios.flight.Flight` (loop,
        checked params, x0, solver params, key) for ``options``
        (:class:`~rvdjax.scenarios.flight.FlightOptions`, default: ideal forces, accurate
        mode, linear truth).

        ``physical``: physical values (and ``x0``) replacing the scenario's, as in
        :meth:`build`; ``config``: the family's static configuration overrides, as in
        :meth:`loop`; ``settings``: solver settings replacing the mode's. Everything is
        resolved and checked here, once (ValueError naming the parameter), before anything is
        compiled; ``check=False`` skips the family's configuration checks (:meth:`check`)."""
        from rvdjax.scenarios.flight import make_flight

        return make_flight(self, options, settings=settings, config=config, check=check, **physical)

    def check(self, params, x0, loop: Loop) -> None:
        """Configuration-dependent checks of the family (ValueError before anything runs)."""
        if loop.config.truth != "linear" and params.plant.orbit is None:
            raise ValueError(f"truth={loop.config.truth!r} needs the target's orbit")
        if loop.config.disturbed and params.plant.disturbances is None:
            raise ValueError("a disturbed run needs disturbance parameters")
        if self.guidance_family.check is not None:
            self.guidance_family.check(params, x0, loop.config)

    def notes(self, mode: str, thrusters: bool | ThrusterSet = False) -> tuple[str, ...]:
        """The assumptions printed with a run in ``mode`` (and its thruster set's)."""
        out = self.assumptions
        config = self.guidance_family.config_type(**self.config)
        out = (*out, *getattr(config, "notes", tuple)())
        if mode == "paper" and self.paper_kappa != PAPER_KAPPA:
            out = (*out, _KAPPA_NOTE.format(kappa=self.paper_kappa))
        tset = self.thruster_set(thrusters)
        if tset is not None:
            from rvdjax.actuators.fire import FIRE_NOTES

            out = (*out, *tset.assumptions, *FIRE_NOTES)
        return out


#: Physical names of the thruster set (studies' --vary / --grid, Scenario.build overrides):
#: the set's values (a sweep) and its dispersions (per thruster; misalignment: 3 per thruster,
#: a rotation vector [rad]; fault: 0 healthy, 1 stuck off, 2 stuck on).
THRUSTER_KEYS = {
    "thruster_thrust_N": "thrust_N",
    "thruster_valve_s": "valve_s",
    "thruster_min_on_s": "min_on_s",
    "thruster_isp_s": "isp_s",
    "thruster_magnitude_error": "magnitude_error",
    "thruster_misalignment": "misalignment",
    "thruster_fault": "fault",
    "thruster_fault_time_s": "fault_time_s",
}
_SET_FIELDS = ("thrust_N", "valve_s", "min_on_s", "isp_s")


def _registry() -> dict[str, Scenario]:
    from rvdjax.scenarios import examples, paper000, paper001, paper002, paper003

    out: dict[str, Scenario] = {}
    for module in (paper000, paper001, paper002, paper003, examples):
        for sc in module.SCENARIOS:
            if sc.name in out:
                raise ValueError(f"scenario {sc.name!r} is defined twice")
            out[sc.name] = sc
    return out


class _Registry(Mapping):
    """The built-in scenarios by name, collected on first use: the modules that define them
    import this package, so collecting them while it loads would import it half-loaded."""

    def __init__(self):
        self._table: dict[str, Scenario] | None = None

    def _load(self) -> dict[str, Scenario]:
        if self._table is None:
            self._table = _registry()
        return self._table

    def __getitem__(self, name: str) -> Scenario:
        return self._load()[name]

    def __iter__(self):
        return iter(self._load())

    def __len__(self) -> int:
        return len(self._load())

    def __repr__(self) -> str:
        return repr(self._load())


SCENARIOS: Mapping[str, Scenario] = _Registry()
DEFAULT_SCENARIO = "fastmpc-3d"


def get_scenario(name: str) -> Scenario:
    """Look a scenario up by name; ValueError listing the known names otherwise. A name ending
    in ``.toml`` is a scenario file (:func:`rvdjax.scenarios.files.load_scenario_file`, checked
    before anything is compiled); the scenario is then named by its normalised path, so that
    whatever records the name (a study, a tuned-parameters file) resolves it again."""
    if str(name).endswith(".toml"):
        from rvdjax.scenarios.files import load_scenario_file

        path = os.path.normpath(os.fspath(name))
        return dataclasses.replace(load_scenario_file(path), name=path)
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(
            f"unknown scenario {name!r}; known: {', '.join(sorted(SCENARIOS))}"
        ) from None
