"""What a guidance family supplies to the closed-loop kernel: pure functions and a layout.

A family (one module under :mod:`rvdjax.families`) describes one kind of guidance problem: its
traced parameters (a NamedTuple pytree with at least ``mass``, ``disturbances``, ``orbit`` and
``drag`` fields, the last three possibly None), its static configuration (horizon and
options), and these pure functions of arrays:

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
* optionally ``model(params, fconfig) -> (A, B, c, Q, R)``: the OCP's stage-wise model and
  weights when they depend on the parameters alone (not on the guidance state). The batch
  engine then keeps them out of its slots and, when the runs share their parameters, solves
  every slot's Newton step with one model (larger matrix products, less memory).

The plant (:mod:`rvdjax.loop.plant`) supplies the truth step for the family's :class:`Layout`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from rvdjax.schema import Schema

__all__ = ["Layout", "Family", "Tunable", "Tuning"]


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


@dataclasses.dataclass(frozen=True, eq=False)
class Family:
    """A guidance family: its layout, configuration type and pure functions (module doc).

    Attributes:
        name: the family's table name (``rvdjax.families.FAMILIES``).
        description: one line.
        layout: the state and input :class:`Layout`.
        n_phases: number of guidance phases (1 for single-phase families).
        config_type: the static configuration dataclass (horizon, options).
        make_params: physical values (plain numbers) -> checked traced parameters.
        horizon: fconfig -> N of the OCP (padded to the largest phase horizon).
        truths: the truth propagations the family supports ("linear" first).
        check: (params, x0, loop config) -> None: configuration-dependent checks (ValueError).
        subsamples: optional (params, fconfig, x, u, dt) -> (taus (M,), states (M, nx)): the
            truth inside a step of ``dt`` seconds at M instants, for docking detection and
            margins between samples.
        model: optional (params, fconfig) -> (A, B, c, Q, R) of the OCP (module docstring).
        plot: (path, scenario, params, infos) -> None, the run's figure.
        dock_error: optional (params, fconfig, G, x, t) -> distance to docking [m].
        tuning: optional :class:`Tuning` (the parameters ``rvdjax tune`` may change).
        schema: the physical inputs (:class:`rvdjax.schema.Schema`: names, units, checks,
            defaults, study aliases); by default ``make_params.schema``.
    """

    name: str
    description: str
    layout: Layout
    n_phases: int
    config_type: type
    make_params: Callable
    horizon: Callable
    init: Callable
    initial_plan: Callable
    observe: Callable
    ocp: Callable
    control: Callable
    sample_time: Callable
    truth_model: Callable
    update: Callable
    truth_blocks: Callable
    truths: tuple[str, ...] = ("linear",)
    check: Callable | None = None
    subsamples: Callable | None = None
    model: Callable | None = None
    plot: Callable | None = None
    baselines: tuple[str, ...] = ()
    dock_error: Callable | None = None
    tuning: Tuning | None = None
    schema: Schema | None = None

    def __post_init__(self):
        if self.schema is None:  # make_params built by rvdjax.schema.make_params_of
            object.__setattr__(self, "schema", getattr(self.make_params, "schema", None))

    def __hash__(self):
        return hash(self.name)

    def __eq__(self, other):
        return isinstance(other, Family) and other.name == self.name
