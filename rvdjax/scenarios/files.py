"""Scenario files: a mission as a TOML file instead of a :class:`~rvdjax.scenarios.Scenario`
record in the package (docs/scenario-files.md).

:func:`scenario_to_toml` writes any scenario (``rvdjax scenario show NAME --toml``);
:func:`load_scenario_file` reads one back and checks it before anything is compiled: every
error is a one-line ValueError naming the file, the dotted key (``physical.altitude_m``,
``thrusters.thrust_N[2]``) and what is allowed. The physical values go through the family's own
checks (:meth:`Scenario.build`, host-side arrays, no jit). What comes back holds the types a
record holds (tuples, ints where the family wants ints, floats elsewhere): a written built-in
scenario reads back equal field by field and builds bit-identical arrays.

Commands take a path ending in ``.toml`` wherever they take a scenario name
(:func:`rvdjax.scenarios.get_scenario`).
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import os
import re
import tomllib
from typing import Any

from rvdjax.actuators.thrusters import MODULATORS, ThrusterSet
from rvdjax.families import FAMILIES
from rvdjax.scenarios import PAPER_KAPPA, Scenario
from rvdjax.scenarios.writer import (  # noqa: F401  (re-exported)
    HEADER,
    METRICS,
    REQUIRED,
    TOP_KEYS,
    _key,
    same_scenario,
    scenario_summary,
    scenario_to_toml,
)

__all__ = [
    "scenario_to_toml",
    "scenario_from_toml",
    "load_scenario_file",
    "scenario_summary",
    "same_scenario",
]


# ------------------------------------------------------------------------------- reading


def _kind_of(v) -> str:
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, int):
        return "an integer"
    if isinstance(v, float):
        return "a number"
    if isinstance(v, str):
        return "a string"
    if isinstance(v, list):
        return "an array"
    if isinstance(v, dict):
        return "a table"
    return f"a {type(v).__name__}"


def _shown(v) -> str:
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


class _Reader:
    """Checks and converts the values of one file; every error names the file and the key."""

    def __init__(self, where: str):
        self.where = where

    def error(self, message: str) -> ValueError:
        return ValueError(_one_line(f"{self.where}: {message}"))

    def wrong(self, key: str, expected: str, v) -> ValueError:
        return self.error(f"{key} must be {expected}, got {_kind_of(v)} ({_shown(v)})")

    def keys(self, table: dict, key: str, allowed, what: str) -> None:
        for k in table:
            if k not in allowed:
                name = f"{key}.{k}" if key else k
                raise self.error(
                    f"unknown key {name!r}; allowed {what}: {', '.join(allowed) or '(none)'}"
                )

    def table(self, v, key: str) -> dict:
        if not isinstance(v, dict):
            raise self.wrong(key, "a table", v)
        return v

    def string(self, v, key: str, choices=None) -> str:
        if not isinstance(v, str):
            raise self.wrong(key, "a string", v)
        if choices is not None and v not in choices:
            raise self.error(f"{key} must be one of {', '.join(choices)}, got {v!r}")
        return v

    def strings(self, v, key: str) -> tuple[str, ...]:
        if not isinstance(v, list):
            raise self.wrong(key, "an array of strings", v)
        return tuple(self.string(e, f"{key}[{i}]") for i, e in enumerate(v))

    def boolean(self, v, key: str) -> bool:
        if not isinstance(v, bool):
            raise self.wrong(key, "true or false", v)
        return v

    def integer(self, v, key: str, lo: int | None = None) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.wrong(key, "an integer" + ("" if lo is None else f" >= {lo}"), v)
        if lo is not None and v < lo:
            raise self.error(f"{key} must be an integer >= {lo}, got {v}")
        return v

    def number(self, v, key: str) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.wrong(key, "a number", v)
        return float(v)

    def numbers(self, v, key: str, allow_scalar: bool = True):
        """A number or a rectangular (nested) array of numbers: floats in tuples."""
        if not isinstance(v, list):
            if allow_scalar:
                return self.number(v, key)
            raise self.wrong(key, "an array of numbers", v)
        out = tuple(self.numbers(e, f"{key}[{i}]") for i, e in enumerate(v))
        shapes = {_shape(e) for e in out}
        if len(shapes) > 1:
            raise self.error(
                f"{key} must be a rectangular array (every row of the same length), got rows "
                f"of lengths {', '.join(str(len(e)) if isinstance(e, tuple) else '1' for e in out)}"
            )
        return out

    def integers(self, v, key: str) -> tuple[int, ...]:
        if not isinstance(v, list):
            raise self.wrong(key, "an array of integers", v)
        return tuple(self.integer(e, f"{key}[{i}]") for i, e in enumerate(v))

    def typed(self, v, key: str, kind: str):
        """Convert by a schema kind: number(s), int, ints, bool, str, strs."""
        if kind == "int":
            return self.integer(v, key)
        if kind == "ints":
            return self.integers(v, key)
        if kind == "bool":
            return self.boolean(v, key)
        if kind == "str":
            return self.string(v, key)
        if kind == "strs":
            return self.strings(v, key)
        if kind == "float":
            return self.number(v, key)
        return self.numbers(v, key)

    def rewrap(self, err: Exception, section: str, keys, subsections=None) -> ValueError:
        """A family's (or the solver's, or the thruster set's) ValueError with the file name
        and the dotted key: its message starts with the parameter's name."""
        msg = _one_line(str(err))
        m = re.match(r"[A-Za-z_]\w*", msg)
        token = m.group(0) if m else ""
        if token in ("x0", "thrusters", section):
            return self.error(msg)
        if token in keys:
            return self.error(f"{section}.{msg}")
        for sub, sub_keys in (subsections or {}).items():
            if token in sub_keys:
                return self.error(f"{section}.{sub}.{msg}")
        return self.error(f"{section}: {msg}")


def _shape(v) -> tuple:
    if isinstance(v, tuple):
        return (len(v), *(_shape(v[0]) if v else ()))
    return ()


def _field_kind(annotation, default) -> str:
    """The value kind of a dataclass field (configuration, solver settings, thruster set)
    from its annotation (a string under PEP 563) or its default."""
    a = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", "")
    a = a.replace(" ", "")
    if a in ("bool", "int", "str"):
        return a
    if a.startswith("tuple[int"):
        return "ints"
    if a.startswith("tuple[str"):
        return "strs"
    for kind, t in (("bool", bool), ("int", int), ("str", str)):
        if isinstance(default, t):
            return kind
    return "numbers"


def _physical_schema(family) -> tuple[dict, tuple]:
    """({key: kind}, required keys) of a family's ``[physical]`` table: its schema's inputs
    (:mod:`rvdjax.schema`; x0 is a top-level key)."""
    inputs = family.schema.physical
    kinds = {i.name: i.kind for i in inputs}
    return kinds, tuple(i.name for i in inputs if i.required)


def _disturbance_keys() -> tuple[str, ...]:
    from rvdjax.disturbances import disturbances

    return tuple(inspect.signature(disturbances).parameters)


def _field_schema(cls, exclude=()) -> dict:
    return {
        f.name: _field_kind(f.type, f.default)
        for f in dataclasses.fields(cls)
        if f.name not in exclude
    }


def _read_physical(r: _Reader, raw, family) -> dict:
    table = r.table(raw, "physical")
    kinds, required = _physical_schema(family)
    r.keys(table, "physical", tuple(kinds), f"in [physical] for family {family.name}")
    for k in required:
        if k not in table:
            raise r.error(
                f"missing required key 'physical.{k}' (family {family.name} needs "
                f"{', '.join(required)})"
            )
    out = {}
    for k, v in table.items():
        key = f"physical.{k}"
        if kinds[k] == "table":
            sub = r.table(v, key)
            allowed = _disturbance_keys()
            r.keys(sub, key, allowed, f"in [{key}]")
            out[k] = {kk: r.number(vv, f"{key}.{kk}") for kk, vv in sub.items()}
        else:
            out[k] = r.typed(v, key, kinds[k])
    return out


def _read_config(r: _Reader, raw, family) -> dict:
    table = r.table(raw, "config")
    kinds = _field_schema(family.config_type)
    r.keys(table, "config", tuple(kinds), f"in [config] for family {family.name}")
    out = {k: r.typed(v, f"config.{k}", kinds[k]) for k, v in table.items()}
    try:
        family.config_type(**out)
    except (ValueError, TypeError) as err:
        raise r.rewrap(err, "config", kinds) from None
    return out


def _read_solver(r: _Reader, raw) -> dict:
    from rvdjax.solver import SolverSettings

    table = r.table(raw, "solver")
    kinds = _field_schema(SolverSettings, exclude=("mode",))
    r.keys(table, "solver", tuple(kinds), "in [solver] (SolverSettings; mode is --mode)")
    out = {k: r.typed(v, f"solver.{k}", kinds[k]) for k, v in table.items()}
    try:
        SolverSettings(**out)
        SolverSettings.paper(**{k: v for k, v in out.items() if k != "max_iter"})
    except (ValueError, TypeError) as err:
        raise r.rewrap(err, "solver", kinds) from None
    return out


def _read_thrusters(r: _Reader, raw, family) -> ThrusterSet:
    from rvdjax.actuators.fire import wrench_rows

    table = r.table(raw, "thrusters")
    kinds = _field_schema(ThrusterSet)
    kinds.update(position_m="xyz", direction="xyz", valve_s="float", min_on_s="float")
    kinds.update(isp_s="float", schmitt_levels="numbers")
    r.keys(table, "thrusters", tuple(kinds), "in [thrusters] (ThrusterSet)")
    for k in ("position_m", "direction"):
        if k not in table:
            raise r.error(f"missing required key 'thrusters.{k}' (T rows of 3 numbers)")
    out: dict[str, Any] = {}
    T = None
    for k, v in table.items():
        key = f"thrusters.{k}"
        if kinds[k] == "xyz":
            rows = r.numbers(v, key, allow_scalar=False)
            if not rows or any(not isinstance(e, tuple) or len(e) != 3 for e in rows):
                raise r.error(f"{key} must be one row of 3 numbers per thruster, got {_shown(v)}")
            T = len(rows) if T is None else T
            if len(rows) != T:
                raise r.error(
                    f"{key} must have one row per thruster ({T}, as position_m and direction), "
                    f"got {len(rows)}"
                )
            out[k] = rows
        elif k == "pair_groups":
            if not isinstance(v, list):
                raise r.wrong(key, "an array of arrays of thruster indices", v)
            out[k] = tuple(r.integers(g, f"{key}[{i}]") for i, g in enumerate(v))
        else:
            out[k] = r.typed(v, key, kinds[k])
    for i, d in enumerate(out["direction"]):
        if not any(d):
            raise r.error(f"thrusters.direction[{i}] must be a non-zero vector, got {list(d)}")
    thrust = out.get("thrust_N")
    if isinstance(thrust, tuple):
        if len(thrust) != T or any(isinstance(e, tuple) for e in thrust):
            raise r.error(f"thrusters.thrust_N must be one number or {T} (one per thruster)")
    for i, f in enumerate(thrust if isinstance(thrust, tuple) else (thrust,)):
        if f is not None and not (f > 0 and math.isfinite(f)):
            at = f"[{i}]" if isinstance(thrust, tuple) else ""
            raise r.error(f"thrusters.thrust_N{at} must be finite and > 0 N, got {f}")
    for k, positive in (("valve_s", True), ("min_on_s", False), ("isp_s", True)):
        if k in out and not (math.isfinite(out[k]) and (out[k] > 0 if positive else out[k] >= 0)):
            op = ">" if positive else ">="
            raise r.error(f"thrusters.{k} must be finite and {op} 0 s, got {out[k]}")
    if "modulator" in out:
        r.string(out["modulator"], "thrusters.modulator", MODULATORS)
    if "frame" in out:
        r.string(out["frame"], "thrusters.frame", ("attitude", "fixed"))
        if out["frame"] == "attitude" and not family.layout.att:
            raise r.error(
                f"thrusters.frame 'attitude' needs an attitude state; family {family.name} "
                "has none: use 'fixed'"
            )
    if "ticks" in out:
        r.integer(out["ticks"], "thrusters.ticks", 1)
    rows = out.get("rows", ThrusterSet.__dataclass_fields__["rows"].default)
    for i, row in enumerate(rows):
        if not 0 <= row <= 5:
            raise r.error(f"thrusters.rows[{i}] must be a wrench row in 0..5, got {row}")
    need = sorted({row for _, row in wrench_rows(family.layout)})
    if not set(need) <= set(rows):
        raise r.error(
            f"thrusters.rows must include the rows {need} that family {family.name}'s inputs "
            f"demand (0-2 force x, y, z, 5 torque z), got {list(rows)}"
        )
    for i, group in enumerate(out.get("pair_groups", ())):
        for j, t in enumerate(group):
            if not 0 <= t < T:
                raise r.error(f"thrusters.pair_groups[{i}][{j}] must be in 0..{T - 1}, got {t}")
    if "schmitt_levels" in out:
        lv = out["schmitt_levels"]
        if not isinstance(lv, tuple) or len(lv) != 2 or any(isinstance(e, tuple) for e in lv):
            raise r.error("thrusters.schmitt_levels must be [on, off], 0 < off < on < 1")
    out.setdefault("name", "thrusters")
    try:
        tset = ThrusterSet(**out)
        tset.build()
        tset.actuation()
    except (ValueError, TypeError) as err:
        raise r.rewrap(err, "thrusters", kinds) from None
    return tset


def _read_published(r: _Reader, raw) -> dict:
    table = r.table(raw, "published")
    r.keys(table, "published", METRICS, "metrics in [published]")
    out = {}
    for metric, refs in table.items():
        key = f"published.{metric}"
        refs = r.table(refs, key)
        out[metric] = {}
        for label, v in refs.items():
            value = out[metric][label] = r.number(v, f"{key}.{_key(label)}")
            if value == 0 or not math.isfinite(value):  # results are compared as relative gaps
                raise r.error(f"{key}.{_key(label)} must be finite and non-zero, got {value}")
    return out


def _read_thruster_metrics(r: _Reader, raw) -> dict:
    table = r.table(raw, "thruster_metrics")
    r.keys(table, "thruster_metrics", METRICS, "figures in [thruster_metrics]")
    return {k: r.string(v, f"thruster_metrics.{k}", METRICS) for k, v in table.items()}


def scenario_from_toml(text: str, where: str = "<scenario>", name: str | None = None) -> Scenario:
    """The checked :class:`Scenario` of a scenario file's text. ``where`` names the file in
    errors; ``name``: the scenario's name when the file gives none."""
    r = _Reader(where)
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise r.error(f"not valid TOML: {err}") from None
    r.keys(doc, "", TOP_KEYS, "at the top level")
    for k in REQUIRED:
        if k not in doc:
            extra = f" (one of: {', '.join(FAMILIES)})" if k == "family" else ""
            raise r.error(f"missing required key {k!r}{extra}")
    family_name = r.string(doc["family"], "family")
    if family_name not in FAMILIES:
        raise r.error(f"family must be one of {', '.join(FAMILIES)}, got {family_name!r}")
    family = FAMILIES[family_name]
    nx, names = family.layout.nx, family.layout.names
    x0 = r.numbers(doc["x0"], "x0", allow_scalar=False)
    if len(x0) != nx or any(isinstance(e, tuple) for e in x0):
        raise r.error(
            f"x0 must be {nx} numbers (family {family_name}'s state: {', '.join(names)}), "
            f"got {_shown(doc['x0'])}"
        )
    kappa = r.number(doc.get("paper_kappa", PAPER_KAPPA), "paper_kappa")
    if not (kappa > 0 and math.isfinite(kappa)):
        raise r.error(f"paper_kappa must be finite and > 0, got {kappa}")
    sc = Scenario(
        name=r.string(doc.get("name", name or "scenario-file"), "name"),
        family=family_name,
        source=r.string(doc.get("source", "scenario file"), "source"),
        description=r.string(doc.get("description", ""), "description"),
        physical=_read_physical(r, doc.get("physical", {}), family),
        x0=x0,
        config=_read_config(r, doc.get("config", {}), family),
        n_steps=r.integer(doc["n_steps"], "n_steps", 1),
        published=_read_published(r, doc.get("published", {})),
        assumptions=r.strings(doc.get("assumptions", []), "assumptions"),
        paper_kappa=kappa,
        solver=_read_solver(r, doc.get("solver", {})),
        thrusters=(_read_thrusters(r, doc["thrusters"], family) if "thrusters" in doc else None),
        thruster_metrics=_read_thruster_metrics(r, doc.get("thruster_metrics", {})),
    )
    if not sc.name:
        raise r.error("name must not be empty")
    _check_build(r, sc)
    return sc


def _check_build(r: _Reader, sc: Scenario) -> None:
    from rvdjax.scenarios.flight import FlightOptions

    """The family's own checks (make_params, the configuration-dependent check), host-side:
    arrays are built, nothing is compiled."""
    kinds, _ = _physical_schema(sc.guidance_family)
    subs = {"disturbances": _disturbance_keys()}
    plants = (False, True) if sc.thrusters is not None else (False,)
    for thrusters in plants:
        try:
            sc.flight(FlightOptions(thrusters=thrusters))  # built and checked, not compiled
        except (ValueError, TypeError, IndexError) as err:
            raise r.rewrap(err, "physical", kinds, subs) from None


def load_scenario_file(path) -> Scenario:
    """Read and check a scenario file (ValueError naming the file and the key otherwise). The
    scenario's name is the file's ``name`` key, or the file name without ``.toml``."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            text = f.read().decode("utf-8")
    except FileNotFoundError:
        raise ValueError(f"{path}: no such scenario file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(_one_line(f"{path}: cannot read the scenario file ({err})")) from None
    stem = os.path.splitext(os.path.basename(path))[0]
    return scenario_from_toml(text, where=path, name=stem)
