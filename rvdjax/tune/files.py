"""The tuned-parameters file: what ``rvdjax tune`` writes and ``rvdjax run --params FILE``
flies (JSON: scenario, solver mode, the tuned names with their natural values, the hand
values they replace, the loss they were tuned for)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from rvdjax.tune.parameters import ParameterSpace

__all__ = ["write_params", "read_params", "apply_params_file"]

FORMAT = "rvdjax-tuned-params/1"


def write_params(path, tuner, values: dict, method: str, spec, provenance=None) -> None:
    """Write the file; ``provenance``: the tuning's record (:mod:`rvdjax.provenance`)."""
    space = tuner.space
    doc = {
        "format": FORMAT,
        "scenario": tuner.scenario.name,
        "family": tuner.scenario.family,
        "mode": spec.mode,
        "method": method,
        "loss": {"effort": spec.loss.effort, "time": spec.loss.time, "margin": spec.loss.margin},
        "parameters": {k: np.asarray(v).tolist() for k, v in values.items()},
        "hand": {k: v.tolist() for k, v in space.hand.items()},
        "description": space.describe(),
    }
    if provenance is not None:
        doc["provenance"] = provenance
    tmp = Path(path).with_suffix(".tmp")
    tmp.write_text(json.dumps(doc, indent=2))
    tmp.replace(path)


def read_params(path) -> dict:
    """The file's JSON document (ValueError on anything that is not a tuned-parameters file)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"--params: no such file {str(path)!r}")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"--params: {path} is not JSON ({e})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ValueError(f"--params: {path} is not an rvdjax tuned-parameters file ({FORMAT})")
    return doc


def apply_params_file(path, scenario, params, sp, mode: str):
    """(params, solver params, doc) with the file's tuned values applied (checked before any
    jit: scenario, mode, names, shapes, ranges)."""
    doc = read_params(path)
    if doc["scenario"] != scenario.name:
        raise ValueError(
            f"--params: {path} was tuned for {doc['scenario']!r}, not {scenario.name!r}"
        )
    values = doc["parameters"]
    if "kappa" in values and mode != doc["mode"]:
        raise ValueError(
            f"--params: {path} tunes paper-mode kappa; fly it with --mode {doc['mode']}"
        )
    space = ParameterSpace.of(scenario, tuple(values), params, sp, doc["mode"])
    checked = space.check_values(values, f"--params {path}")
    p, s = space.apply(params, sp, checked)
    return p, s, doc
