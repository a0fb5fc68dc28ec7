"""What a guidance family supplies to the closed-loop kernel: pure functions and a layout.

A family (one module under :mod:`rvdjax.families`) describes one kind of guidance problem: its
traced parameters (a NamedTuple pytree with a field ``plant``, the
:class:`~rvdjax.loop.plant.Plant` the kernel flies: mass, orbit, drag, disturbances, continuous
model and thrusters), its static configuration (horizon and options), and these pure functions
of arrays:

* ``init(params, fconfig, x0) -> G``: the guidance state at the start (phase, holding radius,
  cone activation: a NamedTuple of arrays);
* ``initial_plan(params, fconfig, G, x0) -> Plan``: the cold-start plan at the start (the
  first linearisation guess);
* ``observe(params, fconfig, G, x, t, plan) -> G``: guidance decisions taken at the start of a
  step from the truth (cone activation), before the OCP is built;
* ``ocp(params, fconfig, G, x_meas, t, plan) -> (OCP, blocks)``: the OCP of this step from the
  measured state, and its state blocks (:mod:`rvdjax.constraints`) in the OCP's row order;
* ``control(params, fconfig, G, solution) -> u``: the command read from the plan (u_0, or
  the recombined inputs of a split formulation);
* ``sample_time(params, G) -> Ts`` and ``truth_model(params, G) -> (A, B)`` (the discrete model
  of the current phase, the linear truth);
* ``update(params, fconfig, G, x, u, x_next, t, Ts, samples) -> (G', docked, dt_flown,
  sample_mask)``: phase switches, holding-radius shrink, docking — decided on the truth;
  ``dt_flown`` is the time the command acted (Ts, less when docking happens inside the step)
  and ``sample_mask`` the sub-samples flown before docking;
* ``truth_blocks(params, fconfig, G, x, t) -> blocks``: single-stage blocks built at the
  truth's own state and time; their slacks are the truth's constraint margins (kind "hard" is
  judged in ``max_violation_m``, "monitor" is reported);
* optionally ``dock_error(params, fconfig, G, x, t) -> ()``: the distance [m] from the state to
  docking (the smooth quantity the tuning loss integrates, :mod:`rvdjax.tune.loss`), and
  ``tuning``: the family's :class:`Tuning` (what ``rvdjax tune`` may change);
* optionally ``model(params, fconfig, G) -> (A, B, c, Q, R)``, or a dict of those and any of
  q, r, the input rows Fu, fu and the state rows' mask and penalty x_mask, rho: the OCP's
  fields that follow from the parameters and the guidance state (the three-phase family's
  from the phase), and optionally ``table``, a function of no arguments returning the
  :class:`rvdjax.solver.riccati.ModelTable` whose entry these fields are (called only where a
  program has the GPU kernels that read it), or None where the configuration
  has none (decided from static structure). The batch engine then rebuilds them instead of
  storing them in its slots and, where they depend on neither the guidance state nor
  per-run parameters, solves every slot's Newton step with one model (larger matrix
  products, less memory).

The plant (:mod:`rvdjax.loop.plant`) supplies the truth step for the family's :class:`Layout`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

from rvdjax.schema import Schema

__all__ = [
    "Layout",
    "Family",
    "GuidanceLaw",
    "Hooks",
    "HOOKS",
    "Tunable",
    "Tuning",
    "lazy",
]


@dataclasses.dataclass(frozen=True)
class Layout:
    """Static description of a family's state and input.

    Attributes:
        nx: state dimension.
        nu: number of physical inputs (the command applied to the plant).
        pos, vel, att: state indices of positions, velocities and attitude angles (att rates
            count as velocities for the navigation noise).
        force: input indices of the translational force (ZOH) or delta-v (impulsive)
            components; the others are torques.
        input: "force" (zero-order hold, [N]; impulse = F dt) or "delta-v" (impulsive, [m/s];
            impulse = m dv, applied at the start of the step).
        names: short labels of the state components (plots, tables).
    """

    nx: int
    nu: int
    pos: tuple[int, ...]
    vel: tuple[int, ...]
    att: tuple[int, ...] = ()
    force: tuple[int, ...] = ()
    input: str = "force"
    names: tuple[str, ...] = ()

    def __post_init__(self):
        if self.input not in ("force", "delta-v"):
            raise ValueError(f"input must be 'force' or 'delta-v', got {self.input!r}")

    @property
    def torque(self) -> tuple[int, ...]:
        return tuple(i for i in range(self.nu) if i not in self.force)


@dataclasses.dataclass(frozen=True)
class Tunable:
    """A parameter the tuner may change (:mod:`rvdjax.tune`).

    Attributes:
        description: what it is, its units and where the paper sets it.
        get: params -> its value (an array; e.g. the diagonal of Q per phase).
        set: (params, value) -> params with the value replaced (pure, jittable; the fields
            derived from it are recomputed by :attr:`Tuning.derive`).
        transform: "log" (value = exp(theta), for positive values) or "logit" (value = lo +
            (hi - lo) sigmoid(theta), for values inside ``bounds``).
        bounds: the open interval the value must lie in.
        derived: it changes fields that :attr:`Tuning.derive` recomputes (weights -> terminal
            weight, sample time -> discrete model).
    """

    description: str
    get: Callable
    set: Callable
    transform: str = "log"
    bounds: tuple[float, float] = (0.0, float("inf"))
    derived: bool = False


@dataclasses.dataclass(frozen=True)
class Tuning:
    """What a family lets the tuner change: named :class:`Tunable` values and ``derive(params,
    names) -> params``, which recomputes the fields derived from the tuned ``names`` (the DARE
    terminal weight from Q and R, the discrete model from the sample time)."""

    tunables: dict
    derive: Callable


# ------------------------------------------------------------------ the kernel's hooks
# Params: the family's NamedTuple of traced arrays; FConfig: its static configuration;
# Guidance: its guidance state (a NamedTuple of arrays); arrays are JAX arrays.

Array = Any
Params = Any
FConfig = Any
Guidance = Any
Blocks = list  # constraint blocks (rvdjax.constraints.Block), in the OCP's row order

HorizonFn = Callable[[FConfig], int]
InitFn = Callable[[Params, FConfig, Array], Guidance]
InitialPlanFn = Callable[[Params, FConfig, Guidance, Array], Any]  # -> rvdjax.solver.Plan
ObserveFn = Callable[[Params, FConfig, Guidance, Array, Array, Any], Guidance]
OcpFn = Callable[[Params, FConfig, Guidance, Array, Array, Any], tuple[Any, Blocks]]
ControlFn = Callable[[Params, FConfig, Guidance, Any], Array]
SampleTimeFn = Callable[[Params, Guidance], Array]
TruthModelFn = Callable[[Params, Guidance], tuple[Array, Array]]
UpdateFn = Callable[
    [Params, FConfig, Guidance, Array, Array, Array, Array, Array, Any],
    tuple[Guidance, Array, Array, Array],
]
TruthBlocksFn = Callable[[Params, FConfig, Guidance, Array, Array], Blocks]
DockErrorFn = Callable[[Params, FConfig, Guidance, Array, Array], Array]
SubsamplesFn = Callable[[Params, FConfig, Array, Array, Array], tuple[Array, Array]]
ModelFn = Callable[[Params, FConfig, Guidance], tuple | dict[str, Array] | None]


@runtime_checkable
class GuidanceLaw(Protocol):
    """What the jitted kernel calls: a family's layout and pure functions of arrays (module
    docstring). Every hook is traced; none may read host state or import plotting.

    * ``horizon(fconfig) -> N``; ``init(params, fconfig, x0) -> G``;
      ``initial_plan(params, fconfig, G, x0) -> Plan``;
    * ``observe(params, fconfig, G, x, t, plan) -> G``;
      ``ocp(params, fconfig, G, x_meas, t, plan) -> (OCP, blocks)``;
      ``control(params, fconfig, G, solution) -> u``;
    * ``sample_time(params, G) -> Ts``; ``truth_model(params, G) -> (A, B)``;
    * ``update(params, fconfig, G, x, u, x_next, t, Ts, samples) -> (G', docked, dt_flown,
      sample_mask)``; ``truth_blocks(params, fconfig, G, x, t) -> blocks``;
    * optional (None when absent): ``dock_error(params, fconfig, G, x, t) -> distance [m]``,
      ``subsamples(params, fconfig, x, u, dt) -> (taus, states)``,
      ``model(params, fconfig, G) -> (A, B, c, Q, R)`` or a dict of OCP fields (module
      docstring), rebuilt instead of stored by the batch engine, or None.
    """

    layout: Layout
    n_phases: int
    config_type: type
    horizon: HorizonFn
    init: InitFn
    initial_plan: InitialPlanFn
    observe: ObserveFn
    ocp: OcpFn
    control: ControlFn
    sample_time: SampleTimeFn
    truth_model: TruthModelFn
    update: UpdateFn
    truth_blocks: TruthBlocksFn
    dock_error: DockErrorFn | None
    subsamples: SubsamplesFn | None
    model: ModelFn | None


@dataclasses.dataclass(frozen=True, eq=False)
class Hooks:
    """A :class:`GuidanceLaw` as a record: the kernel's side of a family (typed fields, the
    signatures of :class:`GuidanceLaw`)."""

    layout: Layout
    n_phases: int
    config_type: type
    horizon: HorizonFn
    init: InitFn
    initial_plan: InitialPlanFn
    observe: ObserveFn
    ocp: OcpFn
    control: ControlFn
    sample_time: SampleTimeFn
    truth_model: TruthModelFn
    update: UpdateFn
    truth_blocks: TruthBlocksFn
    dock_error: DockErrorFn | None = None
    subsamples: SubsamplesFn | None = None
    model: ModelFn | None = None

    @classmethod
    def of(cls, namespace: dict, **given) -> Hooks:
        """The hooks a family module defines under the hooks' own names (``namespace``: its
        ``globals()``), with ``given`` (the layout, the phases, the configuration type, the
        horizon, or a hook under another name). A name the module does not define is None
        (an optional hook absent) or, for a required one, a TypeError naming it."""
        found = {n: namespace[n] for n in HOOKS if n in namespace and callable(namespace[n])}
        return cls(**{**found, **given})


HOOKS = tuple(f.name for f in dataclasses.fields(Hooks))


@dataclasses.dataclass(frozen=True, eq=False)
class Family:
    """A guidance family's registry entry: its kernel hooks (``law``, a :class:`GuidanceLaw`)
    and, apart from them, what the host side reads: the inputs' schema and checks, the run's
    figure, the tuning, the baselines. Each hook is also an attribute (``family.ocp`` is
    ``family.law.ocp``).

    Attributes:
        name: the family's table name (``rvdjax.families.FAMILIES``).
        description: one line.
        law: the kernel's hooks (:class:`Hooks` or any :class:`GuidanceLaw`).
        make_params: physical values (plain numbers) -> checked traced parameters.
        schema: the physical inputs (:class:`rvdjax.schema.Schema`: names, units, checks,
            defaults, study aliases); by default ``make_params.schema``.
        truths: the truth propagations the family supports ("linear" first).
        check: (params, x0, loop config) -> None: configuration-dependent checks (ValueError).
        plot: (path, scenario, params, infos) -> None, the run's figure (its own module:
            :func:`lazy` imports it when it draws).
        baselines: the peer baselines the family can compare with.
        tuning: optional :class:`Tuning` (the parameters ``rvdjax tune`` may change).
    """

    name: str
    description: str
    law: GuidanceLaw
    make_params: Callable
    schema: Schema | None = None
    truths: tuple[str, ...] = ("linear",)
    check: Callable | None = None
    plot: Callable | None = None
    baselines: tuple[str, ...] = ()
    tuning: Tuning | None = None

    def __post_init__(self):
        if self.schema is None:  # make_params built by rvdjax.schema.make_params_of
            object.__setattr__(self, "schema", getattr(self.make_params, "schema", None))

    def __hash__(self):
        return hash(self.name)

    def __eq__(self, other):
        return isinstance(other, Family) and other.name == self.name


def _hook(name: str) -> property:
    return property(lambda self: getattr(self.law, name), doc=f"``law.{name}``")


for _name in HOOKS:
    setattr(Family, _name, _hook(_name))
del _name


def lazy(target: str) -> Callable:
    """A function that imports ``"module:function"`` when first called (a family's plot: its
    module imports matplotlib when it draws, and the family's module never imports it)."""
    module, _, attr = target.partition(":")

    def call(*args, **kwargs):
        import importlib

        return getattr(importlib.import_module(module), attr)(*args, **kwargs)

    call.__name__ = attr
    call.__qualname__ = target
    return call
