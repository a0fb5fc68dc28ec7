"""A study's table rows: the runs' inputs and every Metrics column (generated from
:data:`rvdjax.loop.metrics.FIELDS`), the headline effort and why each failed run failed."""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa

from rvdjax.loop import RunStatus
from rvdjax.loop.metrics import metrics_columns
from rvdjax.study.spec import StudySpec


def _strings(n: int, value) -> pa.Array:
    return pa.array(np.full(n, value, dtype=object), pa.string())


def _table(spec, runs, point_values, point_ts, x0, drawn, m, effort) -> pa.Table:
    """One tidy row per run, as columns (no per-run Python object): ``runs`` (n,) run
    indices, ``x0`` (n, nx) and ``drawn`` {name: (n, ...)} their inputs, ``m`` their engine
    metrics; ``point_values`` {name: (points,)} the sweep values, ``point_ts`` (points, P) each
    point's per-phase sample times (None: not per phase)."""
    n = len(runs)
    point, ic, rep = spec.decompose(runs)
    cols: dict[str, Any] = {
        "study": _strings(n, spec.kind),
        "scenario": _strings(n, spec.scenario),
        "point": point.astype(np.int64),
        "run": runs.astype(np.int64),
        "ic": ic.astype(np.int64),
        "replicate": rep.astype(np.int64),
        "seed": np.full(n, spec.seed, np.int64),
    }
    for name, values in point_values.items():
        cols[name] = values[point].astype(np.float64)
    for name, v in drawn.items():
        v = np.asarray(v, np.float64).reshape(n, -1)
        if np.ndim(drawn[name]) == 1:
            cols[name] = v[:, 0]
        else:
            for j in range(v.shape[1]):
                cols[f"{name}[{j}]"] = v[:, j]
    for j in range(x0.shape[1]):
        cols[f"x0_{j}"] = np.asarray(x0[:, j], np.float64)
    status = np.asarray(m.status)
    for group in metrics_columns(m).values():
        cols.update(group)
    cols["status"] = pa.array(cols["status"], pa.string())
    cols["effort"] = cols[effort]
    if point_ts is not None:
        t = np.asarray(m.phase_time_s, np.float64)
        for ph in range(t.shape[1]):
            cols[f"phase{ph}_intervals"] = np.ceil(t[:, ph] / point_ts[point, ph] - 1e-9).astype(
                np.int64
            )
    cols["failure"] = pa.array(_failures(spec, status, cols), pa.string())
    return pa.table(cols)


def _failures(spec: StudySpec, status, cols) -> np.ndarray:
    """Why each run failed ("" for a success)."""
    out = np.full(len(status), "", dtype=object)
    violated = (status == RunStatus.DOCKED) & (cols["max_violation_m"] > 1e-6)
    out[violated] = "docked with a constraint violation"
    out[status == RunStatus.FAILED] = "non-finite truth state"
    timeout = np.flatnonzero(status == RunStatus.TIMEOUT)
    if spec.time_limit_s is not None:
        out[timeout] = f"not docked within {spec.time_limit_s:g} s"
    else:
        out[timeout] = [f"not docked within {k} steps" for k in cols["steps"][timeout]]
    return out
