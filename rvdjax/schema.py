"""A guidance family's physical inputs, declared once: one :class:`Input` per value that
``make_params`` takes (name, shape, unit, check, default, study alias, one-line description).

The declaration drives

* ``make_params``: :meth:`Schema.bind` fills the defaults and rejects unknown or missing
  names (TypeError, as a keyword-only signature would), :meth:`Schema.check` runs each
  entry's check (ValueError, one line naming the parameter, its unit and the allowed range)
  and :meth:`Schema.signature` is the function's ``inspect`` signature;
* the scenario files' ``[physical]`` table (:mod:`rvdjax.scenarios.files`): the allowed
  keys, the required ones and each value's TOML kind;
* the studies' parameter names, nominal defaults and short names (:mod:`rvdjax.study`);
* the per-family input tables in the docs (:mod:`rvdjax.families.tables`).

Checks that relate several inputs (r3 < r2 < r1, a start outside every keep-out zone) or
need a matrix (positive definite weights) stay in the family's ``make_params`` after
:meth:`Schema.check`. This module imports neither JAX's tracing nor matplotlib.
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Mapping
from types import SimpleNamespace
from typing import Any

from rvdjax import checks

__all__ = [
    "REQUIRED",
    "disturbance_table",
    "Input",
    "Schema",
    "KINDS",
    "CHECKS",
    "value",
    "positive",
    "nonnegative",
    "finite",
    "within",
    "make_params_of",
]


class _Required:
    """The default of an input the caller must give."""

    def __repr__(self) -> str:
        return "REQUIRED"


REQUIRED: Any = _Required()

#: What a value is (the TOML reader converts by it): a number or an array of numbers
#: ("numbers"), an integer, a boolean, a string, a table of numbers (disturbances' keyword
#: values) or the initial state (a top-level key of a scenario file, not a physical one).
KINDS = ("numbers", "int", "bool", "str", "table", "state")

#: What a value must satisfy: every entry finite and > 0, >= 0, finite, inside (lo, hi)
#: (brackets set by lo_open, hi_open), or one of ``choices``.
CHECKS = (None, "positive", "nonnegative", "finite", "range", "choice")


@dataclasses.dataclass(frozen=True)
class Input:
    """One physical input of a family.

    Attributes:
        name: the keyword of ``make_params`` and the key of a scenario file's ``[physical]``.
        description: one line (docs tables, study listings).
        unit: its unit ("" for none; the key's name may say it too: ``altitude_m``).
        shape: "scalar", a shape such as "(3,)" or "(k, 6)", or "per-phase" (one value per
            guidance phase: checked to be ``n_phases`` values).
        kind: one of :data:`KINDS`.
        check: one of :data:`CHECKS` (applied to every entry; None: no entry check).
        lo, hi, lo_open, hi_open: the interval of a "range" check.
        choices: the allowed values of a "choice" check.
        default: the value when the caller gives none (:data:`REQUIRED`: it must be given;
            None: the family derives one, said in ``description``).
        alias: a short study name; for a per-phase input, the prefix of one name per phase
            ("Ts": Ts1 = ts[0], Ts2 = ts[1], ...).
        label: how errors name it when not by ``name`` alone ("gamma (holding-radius shrink
            factor)").
    """

    name: str
    description: str
    unit: str = ""
    shape: str = "scalar"
    kind: str = "numbers"
    check: str | None = None
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = True
    hi_open: bool = True
    choices: tuple = ()
    default: Any = REQUIRED
    alias: str | None = None
    label: str | None = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"Input {self.name}: kind must be one of {KINDS}, got {self.kind!r}")
        if self.check not in CHECKS:
            raise ValueError(
                f"Input {self.name}: check must be one of {CHECKS}, got {self.check!r}"
            )

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    def allowed(self) -> str:
        """The check in words, for the docs ("> 0", "in (0, 90)", "one of -1, 1")."""
        if self.check == "positive":
            return "> 0"
        if self.check == "nonnegative":
            return ">= 0"
        if self.check == "finite":
            return "finite"
        if self.check == "range":
            lb = "-inf" if self.lo is None else f"{self.lo:g}"
            ub = "inf" if self.hi is None else f"{self.hi:g}"
            return f"in {'(' if self.lo_open else '['}{lb}, {ub}{')' if self.hi_open else ']'}"
        if self.check == "choice":
            return "one of " + ", ".join(str(c) for c in self.choices)
        return ""

    def validate(self, value, n_phases: int = 1) -> None:
        """Check one value (ValueError naming the input); None (a derived default) passes."""
        if value is None:
            return
        label = self.label or self.name
        if self.shape == "per-phase":
            import numpy as np

            a = np.asarray(value, dtype=float)
            if a.shape != (n_phases,):
                raise ValueError(
                    f"{self.name} must have one value per phase ({n_phases},), got shape {a.shape}"
                )
        if self.check == "positive":
            checks.positive(label, value, self.unit)
        elif self.check == "nonnegative":
            checks.nonnegative(label, value, self.unit)
        elif self.check == "finite":
            checks.finite(label, value, self.unit)
        elif self.check == "range":
            checks.in_range(
                label, value, self.lo, self.hi, self.lo_open, self.hi_open, unit=self.unit
            )
        elif self.check == "choice":
            checks.choice(label, value, self.choices)


@dataclasses.dataclass(frozen=True)
class Schema:
    """A family's physical inputs, in ``make_params``' order (module docstring).

    Attributes:
        inputs: the :class:`Input` entries.
        n_phases: the length of a per-phase input.
    """

    inputs: tuple[Input, ...]
    n_phases: int = 1

    def __post_init__(self):
        names = [i.name for i in self.inputs]
        if len(set(names)) != len(names):
            raise ValueError(f"a schema names an input twice: {names}")

    def __iter__(self):
        return iter(self.inputs)

    def __len__(self) -> int:
        return len(self.inputs)

    def __getitem__(self, name: str) -> Input:
        for i in self.inputs:
            if i.name == name:
                return i
        raise KeyError(name)

    def __contains__(self, name) -> bool:
        return any(i.name == name for i in self.inputs)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(i.name for i in self.inputs)

    @property
    def required(self) -> tuple[str, ...]:
        return tuple(i.name for i in self.inputs if i.required)

    @property
    def physical(self) -> tuple[Input, ...]:
        """The inputs of a scenario file's ``[physical]`` table (all but the initial state)."""
        return tuple(i for i in self.inputs if i.kind != "state")

    def defaults(self) -> dict:
        """{name: default} of the inputs that have one."""
        return {i.name: i.default for i in self.inputs if not i.required}

    def aliases(self) -> dict[str, str]:
        """Short study names: {alias: name or name[k]} (per-phase: one per phase, from 1)."""
        out = {}
        for i in self.inputs:
            if i.alias is None:
                continue
            if i.shape == "per-phase":
                out.update({f"{i.alias}{k + 1}": f"{i.name}[{k}]" for k in range(self.n_phases)})
            else:
                out[i.alias] = i.name
        return out

    def signature(self, returns: Any = inspect.Signature.empty) -> inspect.Signature:
        """``make_params``' signature: keyword-only, required inputs without a default."""
        return inspect.Signature(
            [
                inspect.Parameter(
                    i.name,
                    inspect.Parameter.KEYWORD_ONLY,
                    default=inspect.Parameter.empty if i.required else i.default,
                )
                for i in self.inputs
            ],
            return_annotation=returns,
        )

    def bind(self, values: Mapping, where: str = "make_params") -> SimpleNamespace:
        """Every input's value (given or default) as attributes; TypeError for an unknown or
        a missing name, worded as Python words a keyword-only call's."""
        for k in values:
            if k not in self:
                raise TypeError(f"{where}() got an unexpected keyword argument {k!r}")
        missing = [n for n in self.required if n not in values]
        if missing:
            names = " and ".join(repr(n) for n in missing)
            s = "s" if len(missing) > 1 else ""
            raise TypeError(
                f"{where}() missing {len(missing)} required keyword-only argument{s}: {names}"
            )
        return SimpleNamespace(**{i.name: values.get(i.name, i.default) for i in self.inputs})

    def check(self, values) -> None:
        """Each input's own check, in order (ValueError naming the first that fails)."""
        get = values.get if isinstance(values, Mapping) else lambda k: getattr(values, k)
        for i in self.inputs:
            i.validate(get(i.name), self.n_phases)

    def markdown(self) -> str:
        """The physical inputs (all but ``x0``) as a Markdown table (the docs' tables)."""
        rows = [
            "| input | shape | unit | allowed | default | description |",
            "|---|---|---|---|---|---|",
        ]
        for i in self.physical:
            default = "required" if i.required else _shown(i.default)
            short = [a for a, full in self.aliases().items() if full.split("[")[0] == i.name]
            name = f"`{i.name}`" + (f" ({', '.join(f'`{a}`' for a in short)})" if short else "")
            shape = {"per-phase": f"per phase ({self.n_phases},)", "scalar": "()"}.get(
                i.shape, i.shape
            )
            shape = "table" if i.kind == "table" else shape
            cells = (name, shape, i.unit or "-", i.allowed() or "-", default, i.description)
            rows.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
        return "\n".join(rows)


def _shown(v) -> str:
    if v is None:
        return "none"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, tuple):
        return "(" + ", ".join(_shown(e) for e in v) + ")"
    return str(v)


def value(name: str, unit: str, description: str, **options) -> Input:
    """An :class:`Input` without an entry check (``options``: the other fields)."""
    return Input(name, description, unit, **options)


def positive(name: str, unit: str, description: str, **options) -> Input:
    """An :class:`Input` whose every entry must be finite and > 0."""
    return Input(name, description, unit, check="positive", **options)


def nonnegative(name: str, unit: str, description: str, **options) -> Input:
    """An :class:`Input` whose every entry must be finite and >= 0."""
    return Input(name, description, unit, check="nonnegative", **options)


def finite(name: str, unit: str, description: str, **options) -> Input:
    """An :class:`Input` whose every entry must be finite."""
    return Input(name, description, unit, check="finite", **options)


def within(name: str, unit: str, lo, hi, description: str, closed: bool = False, **options):
    """An :class:`Input` whose every entry must lie in (lo, hi) ([lo, hi] when ``closed``)."""
    return Input(
        name,
        description,
        unit,
        check="range",
        lo=lo,
        hi=hi,
        lo_open=not closed,
        hi_open=not closed,
        **options,
    )


def disturbance_table(description: str = "disturbance keyword values") -> Input:
    """The ``disturbances`` table every family takes (:func:`rvdjax.disturbances.disturbances`
    keywords over the family's defaults; None: undisturbed)."""
    return value("disturbances", "", description, kind="table", default=None)


def make_params_of(schema: Schema, build, name: str = "make_params", doc: str | None = None):
    """``make_params(**values)`` from ``build(v)``, ``v`` the bound and checked values: its
    signature (for ``inspect`` and help) is the schema's."""

    def make_params(**values):
        v = schema.bind(values, name)
        schema.check(v)
        return build(v)

    make_params.__signature__ = schema.signature(inspect.signature(build).return_annotation)
    make_params.__doc__ = doc if doc is not None else build.__doc__
    make_params.__name__ = make_params.__qualname__ = name
    make_params.__module__ = build.__module__
    make_params.schema = schema
    return make_params
