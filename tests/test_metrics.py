"""The table of the Metrics fields (rvdjax.loop.metrics.FIELDS) and every place generated
from it: a Metrics field missing from the table, the published figures a scenario file may
name, a run's JSON row or a study's columns fails here."""

import numpy as np

from rvdjax.loop import Metrics
from rvdjax.loop.metrics import (
    CARRIED,
    FIELDS,
    FIGURES,
    HIST_BINS,
    Accumulator,
    metrics_columns,
    metrics_row,
)
from rvdjax.scenarios.files import METRICS

DTYPES = {"status", "bool", "int", "float"} | {
    "float[phase]",
    "float[block]",
    "int[status]",
    "int[bin]",
}


def _metrics(n=None, phases=2):
    """Metrics of made-up values (n runs, or one run when n is None)."""
    lead = () if n is None else (n,)
    shapes = {
        "float[phase]": (phases,),
        "int[status]": (4,),
        "int[bin]": (HIST_BINS,),
    }
    values = {}
    for f in FIELDS:
        if f.dtype == "float[block]":
            values[f.name] = {"keep_out": np.full(lead, 1.5), "cone": np.full(lead, np.inf)}
            continue
        shape = lead + shapes.get(f.dtype, ())
        kind = {"bool": bool, "float": float}.get(f.dtype.split("[")[0], np.int32)
        values[f.name] = np.ones(shape, kind)
    return Metrics(**values)


def test_every_metrics_field_is_in_the_table():
    assert [f.name for f in FIELDS] == list(Metrics._fields)
    assert {f.dtype for f in FIELDS} <= DTYPES
    assert all(f.label for f in FIELDS)


def test_published_figures_are_the_per_run_numbers():
    scalar = {f.name for f in FIELDS if f.dtype in ("int", "float")}
    assert set(FIGURES) == set(METRICS) == scalar
    assert "contact_speed_m_s" in METRICS


def test_json_row_has_every_field():
    row = metrics_row(_metrics())
    assert set(row) == {f.row_key for f in FIELDS}
    assert "solver_status_counts" in row and row["margins_m"]["cone"] is None


def test_study_columns_cover_every_field():
    cols = metrics_columns(_metrics(3))
    assert set(cols) == set(Metrics._fields) - {"iteration_histogram"}
    assert {f.name for f in FIELDS if not f.in_table} == {"iteration_histogram"}
    assert all(cols[name] for name in cols), "a field with no column"
    flat = {c: v for group in cols.values() for c, v in group.items()}
    assert all(len(v) == 3 for v in flat.values())
    assert {"phase1_time_s", "margin_keep_out_m", "solves_converged", "contact_speed_m_s"} <= set(
        flat
    )


def test_accumulator_carries_metrics_under_their_names():
    assert set(CARRIED) <= set(Metrics._fields) & set(Accumulator._fields)
    assert set(Accumulator._fields) - set(CARRIED) == {"time_s", "dv_l2", "iterations"}
