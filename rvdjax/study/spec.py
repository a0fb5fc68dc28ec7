"""What a study flies: the scenario, the sweep points, the runs and their random numbers.

A study is plain data (:class:`StudySpec`, written next to its table as ``config.json``). Its
runs are numbered: run r is (sweep point p, initial condition i, replicate j) with
r = (p * n_initial + i) * replicates + j. A run is reproducible from (seed, r) alone
(:mod:`rvdjax.study.samplers`).

Parameter names (``--grid`` and ``--vary``):

* ``x0`` or ``x0[k]``: the initial state;
* a keyword of the family's ``make_params`` (a *physical* value, SI units unless the name
  says otherwise; ``ts[0]`` indexes a per-phase value): rebuilt and checked on the host;
* a field of the family's static configuration (``N``, ``N[0]``): an array shape, so only in
  ``--grid``, and every distinct value compiles the closed loop once;
* short names of the three-phase family: ``N1``, ``N2``, ``N3`` (horizons) and ``Ts1``,
  ``Ts2``, ``Ts3`` (sample times) for paper 003's sweeps.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import json
import re
from typing import Any

import numpy as np

from rvdjax.study.samplers import INITIAL_SAMPLERS, Dist, parse_dist

__all__ = [
    "StudySpec",
    "Point",
    "ParamRef",
    "resolve",
    "parse_assignment",
    "study_scenario",
    "aliases",
]

#: Short study names of the static configuration, per family (the physical inputs' short
#: names come from their schema: :meth:`rvdjax.schema.Schema.aliases`).
STATIC_ALIASES = {"three-phase": {"N1": "N[0]", "N2": "N[1]", "N3": "N[2]"}}


def aliases(family: str) -> dict[str, str]:
    """A family's short study names: {short name: NAME or NAME[k]}."""
    from rvdjax.families import get_family

    schema = get_family(family).schema
    return {**STATIC_ALIASES.get(family, {}), **(schema.aliases() if schema else {})}


_NAME_RE = re.compile(r"^([A-Za-z_][A-Za-z_0-9]*)(?:\[(\d+)\])?$")


@dataclasses.dataclass(frozen=True)
class ParamRef:
    """A resolved parameter name: ``kind`` "x0", "physical" or "static", ``base`` and an
    optional element ``index``."""

    name: str
    kind: str
    base: str
    index: int | None = None

    def apply(self, nominal, value):
        """``nominal`` with this parameter set to ``value`` (tuples stay tuples)."""
        if self.index is None:
            return value
        seq = (
            list(np.asarray(nominal).tolist()) if not isinstance(nominal, tuple) else list(nominal)
        )
        if self.index >= len(seq):
            raise ValueError(f"{self.name}: index {self.index} out of range (length {len(seq)})")
        seq[self.index] = value
        return tuple(seq)

    def get(self, nominal):
        if self.index is None:
            return nominal
        return np.asarray(nominal).reshape(-1)[self.index]


def resolve(scenario, name: str) -> ParamRef:
    """Resolve ``name`` against ``scenario``'s family (ValueError listing the allowed names)."""
    fam = scenario.guidance_family
    short = aliases(scenario.family)
    alias = short.get(name)
    full = alias or name
    m = _NAME_RE.match(full)
    if not m:
        raise ValueError(f"cannot read parameter name {name!r} (use NAME or NAME[k])")
    base, index = m.group(1), None if m.group(2) is None else int(m.group(2))
    static = {f.name for f in dataclasses.fields(fam.config_type)}
    physical = {i.name for i in fam.schema.physical} - {"disturbances"}
    if getattr(scenario, "thrusters", None) is not None:
        from rvdjax.scenarios import THRUSTER_KEYS

        physical |= set(THRUSTER_KEYS)
    if base == "x0":
        nx = fam.layout.nx
        if index is not None and index >= nx:
            raise ValueError(f"{name}: the state has {nx} components (x0[0] .. x0[{nx - 1}])")
        return ParamRef(name, "x0", base, index)
    if base in static:
        return ParamRef(name, "static", base, index)
    if base in physical:
        return ParamRef(name, "physical", base, index)
    short_names = ", ".join(short)
    raise ValueError(
        f"unknown parameter {name!r} for family {scenario.family!r}; physical: "
        f"{', '.join(sorted(physical))}; static (grid only): {', '.join(sorted(static))}; "
        f"initial state: x0, x0[k]" + (f"; short names: {short_names}" if short_names else "")
    )


def parse_assignment(text: str, flag: str) -> tuple[str, str]:
    """``NAME=VALUE`` -> (NAME, VALUE)."""
    if "=" not in text:
        raise ValueError(f"{flag} expects NAME=VALUE, got {text!r}")
    name, value = text.split("=", 1)
    name, value = name.strip(), value.strip()
    if not name or not value:
        raise ValueError(f"{flag} expects NAME=VALUE, got {text!r}")
    return name, value


@dataclasses.dataclass(frozen=True)
class Point:
    """One sweep point: its number and {parameter name: value}."""

    index: int
    values: dict

    def label(self) -> str:
        return ", ".join(f"{k}={v:g}" for k, v in self.values.items()) or "nominal"


@dataclasses.dataclass(frozen=True)
class StudySpec:
    """A study as plain data.

    Attributes:
        kind: "montecarlo", "sweep" or "robustness" (a label; the numbering is the same).
        scenario: scenario name.
        n_initial: initial conditions per sweep point.
        replicates: runs per initial condition (noise realisations).
        seed: study seed.
        initial: initial-state sampler (:data:`rvdjax.study.samplers.INITIAL_SAMPLERS`).
        vary: ((name, distribution), ...) drawn per run.
        grid: ((name, (v1, v2, ...)), ...): the sweep points are their Cartesian product.
        mode, truth, disturbed, nav_filter: the closed loop.
        thrusters: fly the scenario's thruster set.
        faults: ((thruster index, "stuck-off" or "stuck-on", time [s]), ...) for every run.
        fdir: the allocation knows a fault from its onset (False: it goes unnoticed).
        time_limit_s: a run not docked by then ends (TIMEOUT); None: the scenario's step cap.
        n_steps: MPC steps at most (None: the scenario's).
        slots, chunk, iterations: the batch engine (None: chosen for the device,
            :func:`rvdjax.loop.engine.auto_config`).
        block: runs whose inputs are drawn at once (at least 8 x the slots; bounds the host
            memory of a study).
    """

    kind: str
    scenario: str
    n_initial: int
    replicates: int = 1
    seed: int = 0
    initial: str = "nominal"
    vary: tuple = ()
    grid: tuple = ()
    mode: str = "accurate"
    truth: str = "linear"
    disturbed: bool = False
    nav_filter: bool = False
    thrusters: bool = False
    faults: tuple = ()
    fdir: bool = True
    time_limit_s: float | None = None
    n_steps: int | None = None
    slots: int | None = None
    chunk: int | None = None
    iterations: int | None = None
    block: int = 8192

    def __post_init__(self):
        if self.kind not in ("montecarlo", "sweep", "robustness"):
            raise ValueError(f"kind must be montecarlo, sweep or robustness, got {self.kind!r}")
        for name in ("n_initial", "replicates", "slots", "chunk", "iterations", "block"):
            v = getattr(self, name)
            if v is None and name in ("slots", "chunk", "iterations"):
                continue
            if not (isinstance(v, (int, np.integer)) and v >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        if self.initial not in INITIAL_SAMPLERS:
            raise ValueError(
                f"initial must be one of {', '.join(INITIAL_SAMPLERS)}, got {self.initial!r}"
            )
        if self.mode not in ("accurate", "paper", "barrier"):
            raise ValueError(f"mode must be accurate, paper or barrier, got {self.mode!r}")
        if self.time_limit_s is not None and not self.time_limit_s > 0:
            raise ValueError(f"time_limit_s must be > 0 s, got {self.time_limit_s}")
        if self.n_steps is not None and not self.n_steps >= 1:
            raise ValueError(f"n_steps must be >= 1, got {self.n_steps}")
        if self.nav_filter and not self.disturbed:
            raise ValueError("nav_filter needs disturbed=True (a filter of noisy measurements)")
        object.__setattr__(self, "vary", tuple((str(n), str(d)) for n, d in self.vary))
        object.__setattr__(
            self, "faults", tuple((int(i), str(k), float(t)) for i, k, t in self.faults)
        )
        for i, kind, t in self.faults:
            if kind not in ("stuck-off", "stuck-on"):
                raise ValueError(f"--fault {i}:{kind}: the kind must be stuck-off or stuck-on")
            if not (t >= 0 and np.isfinite(t)):
                raise ValueError(f"--fault {i}:{kind}:{t}: the time must be >= 0 s")
        if self.faults and not self.thrusters:
            raise ValueError("--fault needs --thrusters (a fault is a thruster's)")
        object.__setattr__(
            self, "grid", tuple((str(n), tuple(float(v) for v in vs)) for n, vs in self.grid)
        )
        for name, values in self.grid:
            if not values:
                raise ValueError(f"--grid {name}: no values")

    # ------------------------------------------------------------------ derived

    @functools.cached_property
    def points(self) -> list[Point]:
        names = [n for n, _ in self.grid]
        combos = itertools.product(*(vs for _, vs in self.grid)) if self.grid else [()]
        return [Point(i, dict(zip(names, c, strict=True))) for i, c in enumerate(combos)]

    @property
    def runs_per_point(self) -> int:
        return self.n_initial * self.replicates

    @property
    def n_runs(self) -> int:
        return len(self.points) * self.runs_per_point

    def decompose(self, run):
        """(point, initial condition, replicate) of run indices (NumPy)."""
        run = np.asarray(run)
        point, rest = np.divmod(run, self.runs_per_point)
        ic, rep = np.divmod(rest, self.replicates)
        return point, ic, rep

    @property
    def has_faults(self) -> bool:
        """The runs have a thruster fault (--fault, or a drawn fault time)."""
        return bool(self.faults) or any(
            n.startswith("thruster_fault") for n, _ in (*self.vary, *self.grid)
        )

    def flight_options(self, scenario):
        """The study's :class:`~rvdjax.scenarios.flight.FlightOptions` (the thruster set with
        its FDIR choice; the run keys come from the study's own streams)."""
        from rvdjax.scenarios.flight import FlightOptions

        return FlightOptions.of(
            self,
            thrusters=scenario.thrusters.replace(fdir=self.fdir) if self.thrusters else False,
            faults=self.has_faults,
            seed=0,  # (the study's seed draws its runs' keys)
        )

    def fault_overrides(self, n_thrusters: int) -> dict:
        """Scenario.build overrides of the faults (none: {})."""
        if not self.faults:
            return {}
        fault, when = np.zeros(n_thrusters, int), np.zeros(n_thrusters)
        for i, kind, t in self.faults:
            fault[i] = 1 if kind == "stuck-off" else 2
            when[i] = t
        return {"thruster_fault": tuple(fault), "thruster_fault_time_s": tuple(when)}

    def dists(self) -> list[tuple[str, Dist]]:
        return [(n, parse_dist(d)) for n, d in self.vary]

    def validate(self, scenario) -> None:
        """Every name resolves, every distribution parses, no horizon is drawn at random."""
        if scenario.name != self.scenario:
            raise ValueError("scenario mismatch")
        for name, d in self.dists():
            ref = resolve(scenario, name)
            if ref.kind == "static":
                raise ValueError(
                    f"--vary {name}: a static value (an array shape) cannot be drawn per run; "
                    "use --grid"
                )
            del d
        for name, values in self.grid:
            ref = resolve(scenario, name)
            if ref.kind == "static":
                for v in values:
                    if v != int(v) or v < 1:
                        raise ValueError(f"--grid {name}: horizons must be integers >= 1, got {v}")
            if ref.kind == "x0" and ref.index is None:
                raise ValueError("--grid x0 needs a component: x0[k]")
        if self.thrusters and scenario.thrusters is None:
            raise ValueError(f"thrusters: scenario {scenario.name!r} has no thruster set")
        from rvdjax.scenarios import THRUSTER_KEYS

        for option, name in [("--vary", n) for n, _ in self.vary] + [
            ("--grid", n) for n, _ in self.grid
        ]:
            base = resolve(scenario, name).base
            if base in THRUSTER_KEYS and not self.thrusters:
                raise ValueError(f"{option} {name}: a thruster value, only with --thrusters")
        for i, _, _ in self.faults:
            if self.thrusters and not 0 <= i < scenario.thrusters.n:
                raise ValueError(
                    f"--fault {i}: thruster index must be in [0, {scenario.thrusters.n - 1}]"
                )
        if self.initial == "paper003" and scenario.guidance_family.layout.nx != 6:
            raise ValueError("initial 'paper003' draws 3-D CW states (6 components)")

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StudySpec:
        d = dict(d)
        d["vary"] = tuple(tuple(v) for v in d.get("vary", ()))
        d["grid"] = tuple((n, tuple(vs)) for n, vs in d.get("grid", ()))
        d["faults"] = tuple(tuple(f) for f in d.get("faults", ()))
        return cls(**d)


STUDY_SCENARIO_FILE = "scenario.toml"


def study_scenario(spec: StudySpec, out=None):
    """The scenario of a study. A study of a scenario file records the path of the copy it
    keeps in its directory (``DIR/scenario.toml``); when the directory has moved since, the
    copy in ``out`` is read instead."""
    import os

    from rvdjax.scenarios import get_scenario

    name = spec.scenario
    if out is not None and name.endswith(".toml") and not os.path.exists(name):
        local = os.path.join(str(out), STUDY_SCENARIO_FILE)
        if os.path.exists(local):
            name = local
    return get_scenario(name)


def __getattr__(name: str):
    if name == "ALIASES":  # the short names of every family that has some (read-only)
        from rvdjax.families import FAMILIES

        return {f: a for f in FAMILIES if (a := aliases(f))}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
