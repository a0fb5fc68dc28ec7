"""A scenario as a file (``rvdjax scenario show --toml``) and as a summary; the keys and
layout both sides of :mod:`rvdjax.scenarios.files` share."""

from __future__ import annotations

import dataclasses
import json
import math
import re

from rvdjax.actuators.thrusters import ThrusterSet
from rvdjax.families import FAMILIES
from rvdjax.loop.metrics import FIGURES
from rvdjax.scenarios import Scenario

__all__ = [
    "scenario_to_toml",
    "scenario_summary",
    "same_scenario",
    "TOP_KEYS",
    "REQUIRED",
    "METRICS",
]

TOP_KEYS = (
    "name",
    "family",
    "source",
    "description",
    "x0",
    "n_steps",
    "paper_kappa",
    "assumptions",
    "physical",
    "config",
    "solver",
    "thrusters",
    "thruster_metrics",
    "published",
)
REQUIRED = ("family", "x0", "n_steps")

#: Metrics a published figure may name (the per-run figures of :class:`rvdjax.loop.Metrics`).
METRICS = FIGURES

HEADER = """\
# rvdjax scenario file, written by `rvdjax scenario show {name} --toml`.
# Edit it and fly it: `rvdjax run FILE.toml` (also study, tune, compare, bench).
# Units are in the key names: SI (m, s, kg, N, rad) unless the name says otherwise
# (altitude_m, target_rate_deg_s, los_deg, ...). Keys and checks: docs/scenario-files.md.
"""

_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


# ------------------------------------------------------------------------------- writing


def _str(s: str) -> str:
    """A TOML basic string (JSON's escapes are TOML's; DEL must be escaped too)."""
    return json.dumps(s, ensure_ascii=False).replace("\x7f", "\\u007f")


def _key(k: str) -> str:
    return k if _BARE_KEY.match(k) else _str(k)


def _value(v, indent: str = "", flat: bool = False) -> str:
    """A TOML value; arrays of strings and wide matrices one element per line (``flat``: all on
    one line, as inside an inline table)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return repr(float(v))  # shortest round-tripping form; inf/-inf: TOML spells them so
    if isinstance(v, str):
        return _str(v)
    if isinstance(v, (tuple, list)):
        inner = indent + "    "
        inline = "[" + ", ".join(_value(e, inner, flat=True) for e in v) + "]"
        strings = any(isinstance(e, str) for e in v)  # assumptions: one per line
        wide = any(isinstance(e, (tuple, list)) for e in v) and len(inline) > 80  # a matrix
        if flat or not v or not (strings or wide):
            return inline
        return "[\n" + "".join(f"{inner}{_value(e, inner)},\n" for e in v) + indent + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(e, flat=True)}" for k, e in v.items()) + "}"
    if hasattr(v, "tolist"):  # a NumPy scalar or array
        return _value(v.tolist(), indent, flat)
    raise TypeError(f"cannot write {type(v).__name__} {v!r} to TOML")


def _table(
    lines: list, header: str, values: dict, comment: str | None = None, units: dict | None = None
) -> None:
    """``[header]`` with its values in order (a dict value as an inline table); ``units``:
    {key: unit} written as a comment after the value."""
    lines.append("")
    if comment:
        lines.append(f"# {comment}")
    lines.append(f"[{header}]")
    units = units or {}
    for k, v in values.items():
        if v is not None:
            unit = units.get(k)
            lines.append(f"{_key(k)} = {_value(v)}" + (f"  # {unit}" if unit else ""))


def scenario_to_toml(scenario: Scenario) -> str:
    """The scenario as a TOML file's text (:func:`load_scenario_file` reads it back). Values that
    are None are left out (the family's default applies)."""
    sc = scenario
    fam = FAMILIES.get(sc.family)
    lines = [HEADER.format(name=sc.name).rstrip("\n"), ""]
    top = {
        "name": sc.name,
        "family": sc.family,
        "source": sc.source,
        "description": sc.description,
        "x0": tuple(sc.x0),
        "n_steps": sc.n_steps,
        "paper_kappa": sc.paper_kappa,
    }
    for k, v in top.items():
        line = f"{k} = {_value(v)}"
        if k == "x0" and fam is not None and fam.layout.names:
            line += f"  # {', '.join(fam.layout.names)}"
        lines.append(line)
    lines.append(f"assumptions = {_value(tuple(sc.assumptions))}")
    _table(
        lines,
        "physical",
        dict(sc.physical),
        f"the {sc.family} family's physical values (make_params; omitted: its defaults)",
        units=None if fam is None else {i.name: i.unit for i in fam.schema.physical},
    )
    _table(lines, "config", dict(sc.config), "static configuration: horizon, options")
    if sc.solver:
        _table(lines, "solver", dict(sc.solver), "solver settings overrides (SolverSettings)")
    if sc.thrusters is not None:
        tset = {f.name: getattr(sc.thrusters, f.name) for f in dataclasses.fields(ThrusterSet)}
        _table(lines, "thrusters", tset, "the vehicle's thruster set (flown with --thrusters)")
    if sc.thruster_metrics:
        _table(
            lines,
            "thruster_metrics",
            dict(sc.thruster_metrics),
            "published figure -> the metric that computes it when the thrusters fly",
        )
    if sc.published:
        lines.append("")
        lines.append("# published figures: metric -> {label = value}")
        lines.append("[published]")
        for metric, refs in sc.published.items():
            _table(lines, f"published.{_key(metric)}", dict(refs))
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------- summary


def _fmt(v) -> str:
    if isinstance(v, dict):
        return ", ".join(f"{k}={_fmt(e)}" for k, e in v.items())
    if isinstance(v, (tuple, list)):
        return "(" + ", ".join(_fmt(e) for e in v) + ")"
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


def scenario_summary(sc: Scenario) -> str:
    """A readable multi-line description of a scenario (``rvdjax scenario show NAME``)."""
    fam = sc.guidance_family
    names = fam.layout.names or tuple(f"x{i}" for i in range(len(sc.x0)))
    lines = [
        f"{sc.name}: {sc.description}",
        f"  source: {sc.source}",
        f"  family: {sc.family} ({fam.description})",
        "  x0: " + ", ".join(f"{n}={_fmt(v)}" for n, v in zip(names, sc.x0, strict=False)),
        f"  MPC steps at most: {sc.n_steps}; configuration: {_fmt(dict(sc.config))}",
        f"  paper-mode kappa: {sc.paper_kappa:g}"
        + (f"; solver overrides: {_fmt(dict(sc.solver))}" if sc.solver else ""),
        "  physical values (SI unless the key says otherwise):",
    ]
    width = max((len(k) for k in sc.physical), default=0) + 2
    lines.extend(f"    {k:<{width}}{_fmt(v)}" for k, v in sc.physical.items())
    if sc.thrusters is not None:
        lines.append(f"  thrusters: {sc.thrusters.describe()}")
    if sc.published:
        lines.append("  published:")
        for metric, refs in sc.published.items():
            lines.append(f"    {metric}: {_fmt(dict(refs))}")
    if sc.assumptions:
        lines.append("  assumptions:")
        lines.extend(f"    - {a}" for a in sc.assumptions)
    return "\n".join(lines)


def same_scenario(a: str, b: str) -> bool:
    """Two scenario files hold the same scenario (their names and comments aside)."""
    if not (str(a).endswith(".toml") and str(b).endswith(".toml")):
        return False
    from rvdjax.scenarios import get_scenario

    texts = {scenario_to_toml(dataclasses.replace(get_scenario(n), name="")) for n in (a, b)}
    return len(texts) == 1
